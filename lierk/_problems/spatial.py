"""The torque-free rigid body as the report writes it (spatial momentum fixed)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import _validation as validation
from .. import so3
from .base import AbstractRigidBody

__all__ = ["SpatialFreeRigidBody"]


class SpatialFreeRigidBody(AbstractRigidBody):
    """The torque-free rigid body as the report writes it: spatial angular
    momentum ``L = R0 I omega0`` is fixed, there is no extra state
    (``y0 = None``) and ``omega = I^{-1} R^T L`` (the report's
    ``omega_i = I^{-1} W_i^T L``).

    It conserves ``L``, and so ``|m|``, to rounding, which `FreeRigidBody`
    does only to the solver's accuracy.  It is not the default because the
    body momentum ``R^T L`` inherits every attitude error: near the
    intermediate axis that shifts the flip, and its error at the same setting
    was 28 to 5000 times larger than `FreeRigidBody`'s in every case measured
    (``benchmarks/results/formulation.md``).  Pick it when exact conservation
    of ``L`` matters more than the attitude, or to reproduce the report.

    Args:
        inertia: ``(3, 3)`` symmetric positive-definite, or ``(3,)`` principal
            moments (kg m^2), in the body frame.
        omega0: ``(3,)`` initial body angular velocity (rad/s).
        R0: ``(3, 3)`` initial attitude, body -> space (identity if None).
    """

    inertia: Array
    inertia_inv: Array
    R0: Array
    L: Array
    y0: None = None
    effects: tuple = ()

    def __init__(self, inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None = None):
        self.inertia, self.inertia_inv, omega0, self.R0 = validation.rigid_body_state(inertia, omega0, R0)
        self.L = self.R0 @ (self.inertia @ omega0)

    def _body_momenta(self, R, y):
        return jnp.einsum("...ji,j->...i", R, self.L)

    def _momentum_state(self, m):
        return None  # the momentum is read off the attitude

    def _with_initial_momentum(self, m0):
        return eqx.tree_at(lambda p: p.L, self, self.R0 @ m0)

    def field(self, t, R, y):
        return self.inertia_inv @ (R.T @ self.L), None

    def base(self, t, R, y):
        return R.T @ self.L  # body momentum m_n

    def advance(self, base, u, coefficients=None):
        # R^T L at R_n exp(u) is exp(-u) m_n: a vector rotation, no matrix product.
        return so3.rotate(-u, base, coefficients)

    def at(self, base, t, y):
        return self.inertia_inv @ base, None

    def turn_tangent(self, point, xi):
        # The point is m = R^T L, which the turn R exp(hat(eps xi)) moves by m x xi.
        return so3.cross(point, xi)
