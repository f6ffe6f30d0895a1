"""The variational equations of a rigid body, integrated with the body.

`Variational` wraps a `RigidBodyWithEffects` and adds to its state the
derivative of the state along ``P`` input directions.  A direction's
perturbation of the attitude is the body-frame turn ``xi`` (rad per unit of
the input: ``R -> R exp(hat(eps xi))``), of the momentum ``dm``; they obey

    xi' = xi x omega + d omega,
    dm' = d(dm/dt),

where ``d omega`` and ``d(dm/dt)`` are the field's derivative along
``(xi, dm)`` (a `jax.jvp` of the body's field at the stage point, so every
effect is covered; a body with `lierk.ReactionWheels` has the state ``(m,
Omega)``, and ``dm`` is then the pair ``(dm, dOmega)``).  Any solver that
advances extra state with its tableau (RKMK, CF4, Euler) then gives the
Jacobian of the exact flow to its own order: this is the "differentiate,
then discretise" sensitivity.  It is not the derivative of the discrete
solve (`jax.jacfwd` through `lierk.solve` gives that), and a step of it costs
about half as much: `lierk.sensitivity` with ``method="variational"`` uses
it.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import Array

from .. import so3
from .base import AbstractProblem
from .rigid_body import RigidBodyWithEffects

__all__ = ["Variational"]


class Variational(AbstractProblem):
    """A `RigidBodyWithEffects` with its variational equations: state
    ``y = (m, xi, dm)``, ``m`` ``(3,)`` the body momentum (kg m^2/s), ``xi``
    ``(P, 3)`` the attitude's body-frame derivative along each of ``P`` input
    directions (rad per unit of the input) and ``dm`` ``(P, 3)`` the
    momentum's (kg m^2/s per unit).  With `lierk.ReactionWheels` the body's
    state is ``(m, Omega)`` and so is its derivative: ``dm`` is ``(dm (P,
    3), dOmega (P, k))``, the wheel speeds' in rad/s per unit.

    Adaptive solves hold the derivatives to the same tolerances as the state
    (each direction's ``xi`` and ``dm`` as vectors, relative to their size;
    `error_tolerance`), so the step control sees their own oscillations,
    which about a steady spin the state does not show.

    Args:
        problem: the body.
        xi0: ``(P, 3)`` initial attitude derivatives.
        dm0: ``(P, 3)`` initial momentum derivatives; with reaction wheels
            either that (the wheel speeds' derivatives start at 0: the
            directions turn the body, not the wheels relative to it) or the
            pair ``(dm0 (P, 3), dOmega0 (P, k))``.
    """

    problem: RigidBodyWithEffects
    R0: Array
    y0: tuple
    # Each direction's reference sizes for absolute tolerances, ``(P, 1)``:
    # xi's (rad per unit) and dm's (kg m^2/s per unit); with reaction wheels
    # dm's is a pair, the wheel speeds' in rad/s per unit.
    xi_scale: Array
    dm_scale: Any

    def __init__(self, problem: RigidBodyWithEffects, xi0: Array, dm0: Any):
        if not isinstance(problem, RigidBodyWithEffects):
            raise ValueError(
                f"Variational needs a RigidBodyWithEffects (or FreeRigidBody), got {type(problem).__name__}"
            )
        dtype = problem.R0.dtype
        wheels = problem.wheels
        dspeeds0 = None
        if wheels is not None and isinstance(dm0, (tuple, list)):
            if len(dm0) != 2:
                raise ValueError(
                    f"dm0 for a body with reaction wheels must be (dm0 (P, 3), dOmega0 (P, k)), got {len(dm0)} parts"
                )
            dm0, dspeeds0 = dm0
        xi0, dm0 = jnp.asarray(xi0, dtype), jnp.asarray(dm0, dtype)
        if xi0.ndim != 2 or xi0.shape[1:] != (3,) or dm0.shape != xi0.shape:
            raise ValueError(f"xi0 and dm0 must both have shape (P, 3), got {xi0.shape} and {dm0.shape}")
        self.problem = problem
        self.R0 = problem.R0
        # A turn of 1 rad per unit, or the turn 1 s of the direction's
        # angular velocity makes; the momentum the body has, turned, or the
        # direction's own.
        xi_scale = _row_norms(xi0) + _row_norms(so3.matvec(problem.inertia_inv, dm0))
        dm_scale = _row_norms(dm0) + problem.momentum_scale * _row_norms(xi0)
        self.xi_scale = jnp.where(xi_scale > 0, xi_scale, 1.0)
        self.dm_scale = jnp.where(dm_scale > 0, dm_scale, problem.momentum_scale)
        if wheels is None:
            self.y0 = (problem.y0, xi0, dm0)
            return
        k = wheels.axes.shape[0]
        dspeeds0 = jnp.zeros((xi0.shape[0], k), dtype) if dspeeds0 is None else jnp.asarray(dspeeds0, dtype)
        if dspeeds0.shape != (xi0.shape[0], k):
            raise ValueError(
                f"dOmega0 must have shape ({xi0.shape[0]}, {k}), one row per direction, got {dspeeds0.shape}"
            )
        self.y0 = (problem.y0, xi0, (dm0, dspeeds0))
        # The wheel speeds move with the body's rate (a free wheel keeps its
        # absolute spin), so the direction's angular velocity sizes their
        # derivatives too, or the wheels' own speeds for a pure turn.
        domega = _row_norms(so3.matvec(problem.inertia_inv, dm0))
        speed_scale = _row_norms(dspeeds0) + domega + problem.wheel_speed_scale * _row_norms(xi0)
        self.dm_scale = (self.dm_scale, jnp.where(speed_scale > 0, speed_scale, problem.wheel_speed_scale))

    def base(self, t, R, y):
        return self.problem.base(t, R, y[0])

    def advance(self, base, u, coefficients=None):
        return self.problem.advance(base, u, coefficients)

    def at(self, base, t, y):
        m, xi, dm = y

        def field(point, m):
            return self.problem.at(point, t, m)

        # One linearisation at the point serves every direction.
        (omega, mdot), linear = jax.linearize(field, base, m)

        def tangent(xi, dm):
            domega, dmdot = linear(self.problem.turn_tangent(base, xi), dm)
            return so3.cross(xi, omega) + domega, dmdot

        xidot, dmdot = jax.vmap(tangent)(xi, dm)
        return omega, (mdot, xidot, dmdot)

    def field(self, t, R, y):
        return self.at(self.base(t, R, y), t, y)

    def error_tolerance(self, y0, y1, rtol, atol):
        """The body's own for ``m``; each direction's ``xi`` and ``dm`` (and
        reaction wheels' ``dOmega``) against ``atol * scale + rtol *
        max(|v_n|, |v_n+1|)`` (vector norms)."""

        def tol(a, b, scale):
            return jnp.broadcast_to(atol * scale + rtol * jnp.maximum(_row_norms(a), _row_norms(b)), a.shape)

        return (
            self.problem.error_tolerance(y0[0], y1[0], rtol, atol),
            tol(y0[1], y1[1], self.xi_scale),
            jax.tree_util.tree_map(tol, y0[2], y1[2], self.dm_scale),
        )

    def modes(self, t, R, y):
        return self.problem.modes(t, R, y[0])

    def invariants(self, R, y) -> dict[str, Array]:
        return self.problem.invariants(R, y[0])

    def conserved(self) -> tuple[str, ...]:
        return self.problem.conserved()

    def invariant_scales(self) -> dict[str, Any]:
        return self.problem.invariant_scales()


def _row_norms(v: Array) -> Array:
    """Each direction's vector norm: ``(P, 3) -> (P, 1)``."""
    return jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))
