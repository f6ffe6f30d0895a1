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
(`RigidBodyWithEffects`) needs no stage point at all when it has no torques.

`AbstractRigidBody` declares what solvers and tools rely on beyond the field:
the initial angular velocity, whether the body is torque-free (then
`lierk.exact` applies), and the splitting interface (`drift`, `kick`).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import _validation as validation
from .. import exact, so3
from .effects import affine_flow
from .kinematics import kinetic_energy

__all__ = ["AbstractProblem", "AbstractRigidBody"]


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

    def turn_tangent(self, point: Any, xi: Array) -> Any:
        """The tangent of a point that `advance` returns (what `at` reads)
        when the attitude it describes turns to ``R exp(hat(eps xi))``,
        ``xi`` ``(3,)`` (rad, body frame): for the default point, the matrix
        ``R``, ``R hat(xi)``.  The variational equations
        (`lierk._problems.variational.Variational`) read it."""
        return so3.compose(point, so3.hat(xi))

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

    def mode_frequency(self, t: Array, R: Array, y: Any) -> Array:
        """A bound (rad/s) on the fastest oscillation or growth of small
        perturbations about the state ``(R, y)`` at time ``t`` (s) that the
        step control's error estimate cannot see where the solution itself
        does not move (a steady spin, a body at rest under a torque): a
        controller with ``resolve_modes=True`` resolves it.  0 here."""
        return jnp.zeros((), R.dtype)

    def decay_rate(self, t: Array, R: Array, y: Any) -> Array:
        """The fastest decay (1/s) of small perturbations about ``(R, y)`` at
        time ``t`` (s), unseen where the solution does not move (a damped body
        at rest): a controller with ``resolve_modes=True`` keeps its steps
        within an explicit method's stability (``h`` times it at most 2).  A
        decaying perturbation needs no phase resolved: it is gone.  0 here."""
        return jnp.zeros((), R.dtype)

    def modes(self, t: Array, R: Array, y: Any) -> tuple[Array, Array]:
        """``(mode_frequency, decay_rate)`` at once (a problem that derives
        both from one linearisation computes it once)."""
        return self.mode_frequency(t, R, y), self.decay_rate(t, R, y)

    @property
    def torque_free(self) -> bool:
        """Whether this is a torque-free rigid body, whose exact solution is
        `lierk.exact.free_rigid_body`.  False unless a rigid body says so."""
        return False

    def restart(self, R0: ArrayLike, y0: Any) -> "AbstractProblem":
        """The same problem started from attitude ``R0`` ``(3, 3)`` and state ``y0``
        (for solving in pieces: ``problem.restart(sol.R[-1], jax.tree_util.tree_map(lambda x: x[-1], sol.y))``).

        ``R0`` is checked as the constructors check it
        (`lierk.checks.check_attitude`: finite, a rotation to 1e-6; a traced
        one inside the program, where a bad one makes a solve end with
        `lierk.RESULTS.invalid_problem`).  ``y0`` must have the structure, shapes and dtypes
        of this problem's ``y0``: a body's momentum ``(3,)``, with reaction
        wheels the tuple ``(m (3,), speeds (k,))``, None where the problem has
        no state besides ``R`` (Python numbers are converted to the
        problem's dtype; an array of another float dtype is refused).

        Raises:
            ValueError: ``R0`` is not a rotation ``(3, 3)``, or ``y0`` differs
                from the problem's state; the message names the part.
        """
        R0 = validation.check_attitude(R0, self.R0.dtype)
        return self._restarted(R0, validation.check_like(y0, self.y0, "y0"))

    def _restarted(self, R0: Array, y0: Any) -> "AbstractProblem":
        """`restart` from values known to be valid, unchecked: a rotation
        this library formed, or a solve's own end state (ExplicitEuler's
        leaves SO(3), and a scene solved in pieces carries it on as one
        solve does)."""
        problem = eqx.tree_at(lambda p: p.R0, self, R0)
        if self.y0 is not None:
            problem = eqx.tree_at(lambda p: p.y0, problem, y0)
        return problem


class AbstractRigidBody(AbstractProblem):
    """A rigid body: inertia ``I`` (kg m^2, body frame), initial attitude
    ``R0`` and angular velocity, and a tuple of effects (`lierk.AbstractEffect` and its subclasses).

    Subclasses say where the body momentum ``m`` (kg m^2/s, body frame) lives:
    `_body_momenta` reads it from ``(R, y)`` and `_with_initial_momentum`
    restarts from another ``m0``; `_momentum_state` is the ``y`` that goes with
    a new momentum.  Everything else is written once, here:

    - `body_momentum`, `omega0`, `with_omega0` and `torque_free`;
    - the splitting interface: `drift` (the exact torque-free flow), `kick`
      (the torques' flow), `kick_reads_momentum` and `closed_form_drift`;
    - `invariants` and `conserved`.
    """

    inertia: eqx.AbstractVar[Array]
    inertia_inv: eqx.AbstractVar[Array]
    effects: eqx.AbstractVar[tuple]

    def _body_momenta(self, R: Array, y: Any) -> Array:
        """The body momentum ``(..., 3)`` at attitudes ``R`` ``(..., 3, 3)`` and states ``y``."""
        raise NotImplementedError

    def _momentum_state(self, m: Array) -> Any:
        """The state ``y`` that carries body momentum ``m``."""
        raise NotImplementedError

    def _with_initial_momentum(self, m0: Array) -> "AbstractRigidBody":
        raise NotImplementedError

    def body_momentum(self, R: Array, y: Any) -> Array:
        """The body angular momentum ``m`` (kg m^2/s, body frame) ``(..., 3)``
        at attitudes ``R`` ``(..., 3, 3)`` and states ``y``, wherever this
        body keeps it (``y`` itself, or ``R^T L``)."""
        return self._body_momenta(R, y)

    def total_momentum(self, R: Array, y: Any) -> Array:
        """The whole body's angular momentum in the body frame ``(..., 3)``
        (kg m^2/s): `body_momentum`, plus what internal rotors carry
        (`lierk.ReactionWheels`).  ``R @ total_momentum`` is the spatial
        momentum that no internal torque changes."""
        return self._body_momenta(R, y)

    def mode_frequency(self, t: Array, R: Array, y: Any) -> Array:
        """The torque-free part (rad/s), from Euler's equations linearised
        at the momentum ``m`` of ``(R, y)``, ``J = hat(m) I^-1 - hat(omega)``:
        ``sqrt(|c2|)``, ``c2`` the sum of its principal 2x2 minors.  At a
        steady spin about a principal axis ``J`` has the eigenvalues ``0,
        +-sqrt(-c2)`` (``tr J = 0`` and ``det J = 0`` there), so this is its
        spectral radius: the nutation frequency ``omega_k sqrt((I_k -
        I_i)(I_k - I_j)/(I_i I_j))``, the growth rate about the intermediate
        axis.  Away from a steady spin ``det J`` is not 0 and this is an
        estimate of the fastest mode, not a bound (it can be below the
        spectral radius); but there the state moves, and the step control's
        error estimate sees its motion.  `RigidBodyWithEffects` adds its
        effects' modes."""
        m = self._body_momenta(R, y)
        A = self.inertia_inv
        w = so3.matvec(A, m)
        # J's entries written out, (hat(m) A)_ij = (m x A[:, j])_i, so that
        # no matrix is formed: in a differentiated adaptive solve, which
        # bounds its steps by this at every step, the two skew matrices and
        # their product were kernels of their own (a sphere's J is still 0
        # exactly: w = a m entry by entry).
        m0, m1, m2 = m[..., 0], m[..., 1], m[..., 2]
        w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
        X = [
            [m1 * A[..., 2, j] - m2 * A[..., 1, j] for j in range(3)],
            [m2 * A[..., 0, j] - m0 * A[..., 2, j] for j in range(3)],
            [m0 * A[..., 1, j] - m1 * A[..., 0, j] for j in range(3)],
        ]
        W = [[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]]
        J = [[X[i][j] - W[i][j] for j in range(3)] for i in range(3)]
        c2 = validation._principal_minors(J)
        return jnp.sqrt(jnp.abs(c2))

    @property
    def omega0(self) -> Array:
        """Initial body angular velocity ``(3,)`` (rad/s)."""
        m0 = self._body_momenta(self.R0, self.y0)
        # Concrete values: one compiled program (the same product), not eager ops.
        return (jnp.matmul if validation.is_traced(self.inertia_inv, m0) else _matmul_program)(self.inertia_inv, m0)

    def with_omega0(self, omega0: ArrayLike) -> "AbstractRigidBody":
        """The same body and effects started with body angular velocity
        ``omega0`` ``(3,)`` (rad/s) instead; works on traced values (sweeps)."""
        omega0 = validation.check_vector(omega0, "omega0", self.R0.dtype)
        return self._with_initial_momentum(self.inertia @ omega0)

    @property
    def torque_free(self) -> bool:
        """No effects: `lierk.exact.free_rigid_body` is the exact solution."""
        return not self.effects

    def free_flow(self, m: Array, h: Array) -> tuple[Array, Array]:
        """The exact torque-free flow over ``h`` (s) from body momentum ``m``
        ``(3,)``: ``(Q, m_h)``, the body turning by ``Q`` ``(3, 3)`` (``R -> R Q``);
        `lierk.exact.free_flow`."""
        return exact.free_flow(self.inertia, m, h)

    @property
    def closed_form_drift(self) -> bool:
        """Whether `drift` is a closed form small to compile (a symmetric
        body's two rotations) rather than the elliptic-function flow: the
        splitting solvers then unroll their stages."""
        return False

    def drift(self, R: Array, y: Any, h: Array) -> tuple[Array, Any]:
        """The exact torque-free flow over ``h`` (s) from ``(R, y)``: the
        splitting solvers' drift (`free_flow`)."""
        Q, m = self.free_flow(self._body_momenta(R, y), h)
        return so3.compose(R, Q), self._momentum_state(m)

    @property
    def kick_reads_momentum(self) -> tuple[str, ...]:
        """The names of the effects whose torque reads the momentum (damping):
        the Runge-Kutta-Nystrom splittings refuse them."""
        return tuple(type(e).__name__ for e in self.effects if e.reads_momentum)

    def kick(self, t: Array, R: Array, y: Any, h: Array) -> Any:
        """The torques' flow over ``h`` (s) with ``t`` and ``R`` held fixed: the
        kick of a splitting method.  Each effect's own flow is exact
        (`AbstractEffect.kick`); several are composed symmetrically
        (``K_1(h/2) ... K_n(h) ... K_1(h/2)``), which keeps the splitting
        symmetric, and is exact when no torque reads the momentum (they
        commute); when every torque is affine in the momentum
        (`AbstractEffect.affine_torque`) the sum's flow is taken, exactly."""
        effects = self.effects
        if not effects:
            return y
        m = y
        if all(not e.reads_momentum for e in effects):
            omega = self.inertia_inv @ m
            return m + h * sum(e.torque(t, R, m, omega) for e in effects)
        if len(effects) > 1:
            # Torques all affine in m (damping, rotors, B-dot, and those that
            # do not read m): their sum's flow is exact, where composing the
            # separate flows would be second order only and would cap a
            # fourth-order splitting at 2.
            forms = [e.affine_torque(t, R, self.inertia_inv) for e in effects]
            if all(f is not None for f in forms):
                return affine_flow(sum(f[0] for f in forms), sum(f[1] for f in forms), m, h)
        for e in effects[:-1]:
            m = e.kick(t, R, m, 0.5 * h, self.inertia_inv)
        m = effects[-1].kick(t, R, m, h, self.inertia_inv)
        for e in effects[-2::-1]:
            m = e.kick(t, R, m, 0.5 * h, self.inertia_inv)
        return m

    def invariants(self, R: Array, y: Any) -> dict[str, Array]:
        """``"energy"`` (kinetic plus every effect's potential, J), ``"|L|"``
        (kg m^2/s) and each effect's own `AbstractEffect.invariants`.  Which of
        them the exact flow conserves is `conserved`."""
        m = self._body_momenta(R, y)
        omega = so3.matvec(self.inertia_inv, m)
        energy = kinetic_energy(self.inertia, omega)
        out = {}
        for e in self.effects:
            energy = energy + e.potential(R)
            out.update(e.invariants(R, y))
        return {"energy": energy, "|L|": jnp.linalg.norm(m, axis=-1), **out}

    def conserved(self) -> tuple[str, ...]:
        """Keys of `invariants` that the exact flow conserves for this set of effects.

        ``"energy"`` when every effect is conservative; ``"|L|"`` with no effects;
        an effect's own conserved invariants (`AbstractEffect.conserved`) when it
        is the only effect.
        """
        keys = []
        if all(e.conservative for e in self.effects):
            keys.append("energy")
        if not self.effects:
            keys.append("|L|")
        if len(self.effects) == 1:
            keys.extend(self.effects[0].conserved(self.inertia))
        return tuple(keys)


_matmul_program = jax.jit(jnp.matmul)
