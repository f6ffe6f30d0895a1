"""Problems: vector fields on SO(3) x R^n.

A problem describes

    dR/dt = R hat(omega(t, R, y))        (body frame: omega is body angular velocity)
    dy/dt = g(t, R, y)                   (y: a pytree of extra state, or None)

Solvers do not call ``omega(t, R, y)`` at a matrix ``R`` directly.  They write
stage points in local coordinates about the step's base point,
``R = R_n exp(hat(u))``, and ask the problem for the field there with
``problem.local(base, t, u, y)``, where ``base = problem.base(t, R_n, y_n)``
describes the base point, ``problem.advance(base, u)`` describes
``R_n exp(hat(u))`` and ``problem.at(base, t, y)`` evaluates the field there.
The default base is the matrix ``R`` itself; a problem can do better.  The
report's torque-free body (`SpatialFreeRigidBody`) needs only its body
momentum, ``m = exp(-u) m_n``, which is a Rodrigues rotation of one 3-vector,
so its stages need no 3x3 products.  The rigid body with momentum as state
(`lierk.rigid_body`) needs no stage point at all when it has no torques.
"""

from __future__ import annotations

import warnings
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import _checks, so3
from . import inertia as _inertia
from .body import kinetic_energy

__all__ = ["AbstractProblem", "SpatialFreeRigidBody", "check_attitude", "check_vector", "rigid_body_state"]


def check_attitude(R0: ArrayLike | None, dtype) -> Array:
    """Validate an initial attitude: ``(3, 3)``, finite, in SO(3) to 1e-6."""
    if R0 is None:
        return jnp.eye(3, dtype=dtype)
    R0 = _checks.asarray(R0, dtype, "R0")
    _checks.check_shape(R0, (3, 3), "R0")
    tol = 1e-6
    xp = np if isinstance(R0, np.ndarray) else jnp
    R0 = _checks.check(R0, lambda R: (R == R).all() & (abs(R) < float("inf")).all(), "R0 has NaN or inf entries: {value}")
    R0 = _checks.check(
        R0,
        lambda R: (xp.linalg.norm(R.T @ R - xp.eye(3)) < tol) & (xp.linalg.det(R) > 0),
        f"R0 must be a rotation matrix (||R^T R - I|| < {tol:g} and det R = +1), got {{value}}",
    )
    return jnp.asarray(R0)


def check_vector(x: ArrayLike, name: str, dtype) -> Array:
    x = _checks.asarray(x, dtype, name)
    _checks.check_shape(x, (3,), name)
    x = _checks.check(x, lambda v: (v == v).all() & (abs(v) < float("inf")).all(), f"{name} has NaN or inf entries: {{value}}")
    return jnp.asarray(x)


def rigid_body_state(inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None):
    """Validate a rigid body's inertia and initial state, in one common float dtype.

    Returns ``(inertia (3, 3), inertia_inv (3, 3), omega0 (3,), R0 (3, 3))``.
    """
    inertia = _inertia.tensor(inertia)
    dtype = jnp.result_type(inertia.dtype, _checks.asarray(omega0, name="omega0").dtype, float)
    inertia = inertia.astype(dtype)
    if not _checks.is_traced(inertia):
        moments = np.linalg.eigvalsh(np.asarray(inertia, np.float64))
        limit = 1e-10 if dtype == jnp.float64 else 1e-5
        if moments.min() < limit * moments.max():
            warnings.warn(
                f"inertia is nearly singular (I_min/I_max = {moments.min() / moments.max():.1e}): omega = I^-1 m "
                "turns tiny momentum errors into huge spins, so expect a stiff, inaccurate run; "
                "check the units, or drop the rotation about that axis",
                stacklevel=3,
            )
    omega0 = check_vector(omega0, "omega0", dtype)
    return inertia, jnp.linalg.inv(inertia), omega0, check_attitude(R0, dtype)


class AbstractProblem(eqx.Module):
    """A vector field on SO(3) x R^n with its initial state.

    Subclasses provide ``R0`` (``(3, 3)``), ``y0`` (pytree or None) and
    `field`; they may override `base`/`local` for cheaper stages and
    `invariants` for diagnostics.
    """

    R0: eqx.AbstractVar[Array]
    y0: eqx.AbstractVar[Any]

    def field(self, t: Array, R: Array, y: Any) -> tuple[Array, Any]:
        """``(omega, dy/dt)`` at time ``t`` (s), attitude ``R`` ``(3, 3)``, state ``y``.
        ``omega`` is the body angular velocity ``(3,)`` (rad/s)."""
        raise NotImplementedError

    def base(self, t: Array, R: Array, y: Any) -> Any:
        """What `local` needs to know about a step's base point ``R_n``."""
        return R

    def advance(self, base: Any, u: Array, coefficients: tuple | None = None) -> Any:
        """The base of ``R_n exp(hat(u))`` from the base of ``R_n``; ``u`` is ``(3,)``.
        ``coefficients``: ``so3.exp_coefficients`` of ``|u|^2``, if the solver has them."""
        return base @ so3.exp(u, coefficients)

    def at(self, base: Any, t: Array, y: Any) -> tuple[Array, Any]:
        """`field` at the point that ``base`` describes."""
        return self.field(t, base, y)

    def local(self, base: Any, t: Array, u: Array, y: Any, coefficients: tuple | None = None) -> tuple[Array, Any]:
        """`field` at ``R = R_n exp(hat(u))``, given ``base = self.base(t_n, R_n, y_n)``
        (and optionally ``so3.exp_coefficients`` of ``|u|^2``)."""
        return self.at(self.advance(base, u, coefficients), t, y)

    def invariants(self, R: Array, y: Any) -> dict[str, Array]:
        """Quantities the exact flow conserves, for diagnostics.  ``R`` may carry
        leading axes ``(..., 3, 3)``."""
        return {}

    def conserved(self) -> tuple[str, ...]:
        """Keys of `invariants` that the exact flow conserves; `solve` reports
        `RESULTS.invariant_drift` when one of them drifts too far."""
        return ()

    def invariant_scales(self) -> dict[str, Array]:
        """A positive size for each of `conserved`, against which a drift is
        measured (an energy that starts near 0 still has a scale)."""
        q = self.invariants(self.R0, self.y0)
        return {k: jnp.abs(q[k]) for k in self.conserved()}

    def angular_velocity(self, R: Array, y: Any) -> Array:
        """Body angular velocity ``omega`` (rad/s) at attitudes ``R``
        ``(..., 3, 3)`` and states ``y`` (leading axes alike): ``(..., 3)``."""
        return jax.vmap(lambda R, y: self.field(jnp.zeros((), R.dtype), R, y)[0])(
            R.reshape(-1, 3, 3), jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[R.ndim - 2 :]), y)
        ).reshape(R.shape[:-1])

    def error_tolerance(self, y0: Any, y1: Any, rtol: Array, atol: Array) -> Any:
        """What an adaptive step's error in ``y`` is measured against: a pytree
        like ``y`` of positive scales, for a step from ``y0`` to ``y1``.  The
        default is per component, ``atol + rtol * max(|y0|, |y1|)``."""
        return jax.tree_util.tree_map(lambda a, b: atol + rtol * jnp.maximum(jnp.abs(a), jnp.abs(b)), y0, y1)

    def restart(self, R0: ArrayLike, y0: Any) -> "AbstractProblem":
        """The same problem started from attitude ``R0`` ``(3, 3)`` and state ``y0``
        (for solving in pieces)."""
        problem = eqx.tree_at(lambda p: p.R0, self, jnp.asarray(R0, self.R0.dtype))
        if self.y0 is not None:
            problem = eqx.tree_at(lambda p: p.y0, problem, y0)
        return problem


class SpatialFreeRigidBody(AbstractProblem):
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

    def __init__(self, inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None = None):
        self.inertia, self.inertia_inv, omega0, self.R0 = rigid_body_state(inertia, omega0, R0)
        self.L = self.R0 @ (self.inertia @ omega0)

    @property
    def omega0(self) -> Array:
        return self.inertia_inv @ (self.R0.T @ self.L)

    def with_omega0(self, omega0: ArrayLike) -> "SpatialFreeRigidBody":
        """The same body started with body angular velocity ``omega0`` (rad/s)."""
        omega0 = check_vector(omega0, "omega0", self.L.dtype)
        return eqx.tree_at(lambda p: p.L, self, self.R0 @ (self.inertia @ omega0))

    def field(self, t, R, y):
        return self.inertia_inv @ (R.T @ self.L), None

    def base(self, t, R, y):
        return R.T @ self.L  # body momentum m_n

    def advance(self, base, u, coefficients=None):
        # R^T L at R_n exp(u) is exp(-u) m_n: a vector rotation, no matrix product.
        return so3.rotate(-u, base, coefficients)

    def at(self, base, t, y):
        return self.inertia_inv @ base, None

    def drift(self, R, y, h):
        """The exact flow over ``h`` (s) for the splitting solvers: ``(R Q, None)``."""
        from .exact import free_flow  # exact imports this module

        Q, _ = free_flow(self.inertia, R.T @ self.L, h)
        return so3.compose(R, Q), None

    def kick(self, t, R, y, h):
        """No torques: the splitting solvers' kick does nothing."""
        return y

    # No torque reads the momentum (there are none): every splitting applies.
    kick_reads_momentum: ClassVar[tuple] = ()

    def invariants(self, R, y):
        m = jnp.einsum("...ji,j->...i", R, self.L)
        omega = jnp.einsum("ij,...j->...i", self.inertia_inv, m)
        return {"energy": kinetic_energy(self.inertia, omega), "|L|": jnp.linalg.norm(m, axis=-1)}

    def conserved(self):
        return ("energy", "|L|")
