"""Body quantities of a rigid body.

Frames: ``R`` maps body coordinates to space.  ``omega`` is the body angular
velocity (rad/s), ``m = I omega`` the body angular momentum and ``L = R m``
the spatial angular momentum (kg m^2/s).  All functions broadcast over
leading axes.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import so3

__all__ = ["angular_momentum", "kinetic_energy", "body_angular_velocity"]


def angular_momentum(inertia: ArrayLike, omega: ArrayLike, R: ArrayLike | None = None) -> Array:
    """Body momentum ``I omega``, or the spatial ``R I omega`` when ``R`` is given.
    ``(..., 3, 3), (..., 3)[, (..., 3, 3)] -> (..., 3)``."""
    m = so3.matvec(jnp.asarray(inertia), jnp.asarray(omega))
    return m if R is None else so3.matvec(jnp.asarray(R), m)


def kinetic_energy(inertia: ArrayLike, omega: ArrayLike) -> Array:
    """Rotational kinetic energy ``omega . I omega / 2`` (J): ``-> (...)``."""
    omega = jnp.asarray(omega)
    return 0.5 * jnp.sum(omega * so3.matvec(jnp.asarray(inertia), omega), axis=-1)


def body_angular_velocity(inertia: ArrayLike, R: ArrayLike, L: ArrayLike) -> Array:
    """``omega = I^{-1} R^T L`` (the report's formula) for spatial momentum ``L``."""
    m = jnp.einsum("...ji,...j->...i", jnp.asarray(R), jnp.asarray(L))
    return jnp.linalg.solve(jnp.asarray(inertia), m[..., None])[..., 0]
