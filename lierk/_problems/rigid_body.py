"""The rigid-body problem: attitude and body momentum, with opt-in effects.

One problem covers every rigid body in lierk.  Its state is the attitude ``R``
(body -> space) and the body angular momentum ``m`` (kg m^2/s, body frame),

    dR/dt = R hat(omega),    omega = I^{-1} m,
    dm/dt = m x omega + sum_k tau_k(t, R, m, omega),

where each ``tau_k`` is the body-frame torque of one effect (`lierk.AbstractEffect` and its subclasses).
A torque-free body, `FreeRigidBody`, is this problem with no effects.

Why the momentum is state even without torque: the report instead keeps the
spatial momentum ``L`` fixed and reads ``m = R^T L`` off the attitude
(`lierk.SpatialFreeRigidBody`).  Then every attitude error, which the fast
spin dominates, becomes a momentum error, and near the intermediate axis the
momentum decides when the body flips, so a small phase error turns into a
large error in the flip time.  Integrating Euler's equations for ``m`` keeps
the spin's phase error out of the momentum.  On near-intermediate-axis
batches of four bodies this made RKMK4 30 to 300 times and DOP853 170 to 5000
times more accurate, and RKMK4 faster, since a torque-free stage needs no
rotation at all (``benchmarks/results/formulation.md``).  The price is that ``|m|`` and ``L``
are conserved only to the solver's accuracy, not to rounding.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import _validation as validation
from .. import exact, so3
from ..inertia import parallel_axis
from .base import AbstractRigidBody
from .effects import AbstractEffect, Gravity
from .kinematics import kinetic_energy
from .spacecraft import ReactionWheels, _along, _spin_matrix, _wheel_sum

__all__ = ["RigidBodyWithEffects", "FreeRigidBody", "heavy_top"]


class RigidBodyWithEffects(AbstractRigidBody):
    """A rigid body under a tuple of effects; state ``y`` is the body momentum ``m``.

    ``dm/dt = m x omega + sum(effect.torque(t, R, m, omega))`` with
    ``omega = I^{-1} m``.  The sum is unrolled in Python over ``effects``, so
    only the effects present are traced: with ``effects=()`` the stages never
    form a rotation matrix at all.

    With `lierk.ReactionWheels` among the effects the state is ``y = (m,
    Omega)``, the body momentum and the wheels' speeds relative to the body
    ``(k,)`` (rad/s), and the field is Basilisk's balanced wheels (see
    `lierk.ReactionWheels`): the other effects' torques still add up, and the
    sum turns the body through ``(I - G)^-1``.  `body_momentum` is still
    ``m = I omega``; the invariants include the wheels.

    Adaptive solves measure the momentum's error relative to its size
    (`error_tolerance`), so ``rtol`` means the same for a 1e-4 kg m^2 handle
    and a 500 kg satellite.

    Args:
        inertia: ``(3, 3)`` or ``(3,)`` principal moments (kg m^2), body frame,
            about the point the body turns about (the pivot for `Gravity`,
            otherwise the centre of mass).
        omega0: ``(3,)`` initial body angular velocity (rad/s).
        R0: ``(3, 3)`` initial attitude, body -> space (identity if None).
        effects: tuple of `lierk.AbstractEffect`; at most one
            `lierk.ReactionWheels`.

    Example:
        >>> top = RigidBodyWithEffects([5.0, 5.0, 1.0], [0.0, 0.3, 50.0],
        ...                            effects=(Gravity([0, 0, 1.0], 1.0, 20.0),))
        >>> sol = lierk.solve(top, lierk.RKMK4(), 1.0, dt=1e-3)
    """

    inertia: Array
    inertia_inv: Array
    R0: Array
    y0: Array
    effects: tuple
    # The principal axis (0, 1, 2) of a diagonal inertia whose other two
    # moments are equal, found when the inertia is concrete; None otherwise.
    # Only the splitting solvers' drift reads it (a closed form instead of the
    # elliptic one), so a traced inertia merely takes the general path.  Note
    # that inside jit even jnp.asarray(constant) is traced: pass NumPy arrays
    # or lists to get the closed form there.
    symmetry_axis: int | None = eqx.field(static=True)
    # The position of the `ReactionWheels` effect in ``effects``, or None.
    # Static: with wheels the state is a pair and the field another program;
    # without, nothing of them is traced.
    wheel_index: int | None = eqx.field(static=True)
    # Whether the inertia is a concrete diagonal matrix: then omega = I^-1 m is
    # an elementwise product, which XLA fuses with the rest of a stage, where
    # the 3x3 product is a kernel of its own.  Found like `symmetry_axis`; a
    # traced inertia is general.
    diagonal: bool = eqx.field(static=True)

    def __init__(
        self,
        inertia: ArrayLike,
        omega0: ArrayLike,
        R0: ArrayLike | None = None,
        effects: tuple | list = (),
    ):
        if isinstance(effects, AbstractEffect):
            effects = (effects,)
        effects = tuple(effects)
        for i, e in enumerate(effects):
            if not isinstance(e, AbstractEffect):
                raise ValueError(
                    f"effects[{i}] must be a lierk effect (Gravity, BodyTorque, SpaceTorque, TimedTorque, Damping, "
                    f"GravityGradient, MagneticTorque, Rotor, ReactionWheels), got {e!r}"
                )
        wheels = [i for i, e in enumerate(effects) if isinstance(e, ReactionWheels)]
        if len(wheels) > 1:
            raise ValueError(
                f"effects[{wheels[1]}]: a body takes one ReactionWheels effect, and effects[{wheels[0]}] is one "
                "already; give all the wheels to one (axes (k, 3))"
            )
        self.wheel_index = wheels[0] if wheels else None
        self.inertia, omega0, self.R0 = validation.rigid_body_inputs(inertia, omega0, R0)
        self.inertia_inv, m0 = validation.inverse_inertia(self.inertia, inertia), _momentum(self.inertia, omega0)
        self.effects = tuple(e._cast(self.inertia.dtype) for e in effects)
        if self.wheel_index is None:
            self.y0 = m0
        else:
            w = self.wheels
            checked = _check_wheels(self.inertia, w.axes, w.spin_inertia, f"effects[{self.wheel_index}]")
            # Traced, the check rides on the values it guards (a discarded
            # check would be dropped from the program).
            self.inertia, axes, spin_inertia = checked
            self.effects = eqx.tree_at(
                lambda es: (es[self.wheel_index].axes, es[self.wheel_index].spin_inertia),
                self.effects,
                (axes, spin_inertia),
            )
            self.y0 = (m0, w.speeds)
        # From the argument as given: the checked copy may be traced (its checks
        # join the traced R0's) even when the inertia itself is a constant.
        diagonal = validation.concrete_diagonal(inertia)
        self.diagonal = diagonal is not None
        self.symmetry_axis = None if diagonal is None else _symmetry_axis(diagonal)

    @property
    def wheels(self) -> ReactionWheels | None:
        """The `lierk.ReactionWheels` effect, or None."""
        return None if self.wheel_index is None else self.effects[self.wheel_index]

    @property
    def L(self) -> Array:
        """Initial spatial angular momentum ``R0 m0`` ``(3,)`` (kg m^2/s);
        constant in time for a torque-free body.  With reaction wheels, the
        whole spacecraft's, ``R0 (m0 + sum Js Omega0 g)``, constant in time
        without other effects."""
        return self.R0 @ self.total_momentum(self.R0, self.y0)

    def total_momentum(self, R, y):
        """`body_momentum`, and with reaction wheels their momentum relative
        to the body, ``m + sum Js Omega g`` ``(..., 3)`` (kg m^2/s)."""
        if self.wheel_index is None:
            return y
        m, speeds = y
        return m + _wheel_sum(self.wheels.spin_inertia * speeds, self.wheels.axes)

    def _body_momenta(self, R, y):
        return y if self.wheel_index is None else y[0]

    def _momentum_state(self, m):
        if self.wheel_index is not None:
            self._refuse_splitting()
        return m

    def _with_initial_momentum(self, m0):
        # With wheels the speeds relative to the body stay as they are (a
        # sweep of omega0 turns the body, not the wheels' motors).
        if self.wheel_index is not None:
            return eqx.tree_at(lambda p: p.y0[0], self, m0)
        return eqx.tree_at(lambda p: p.y0, self, m0)

    def with_omega0(self, omega0: ArrayLike) -> "RigidBodyWithEffects":
        """The same body and effects started with body angular velocity
        ``omega0`` ``(3,)`` (rad/s) instead; works on traced values (sweeps).
        Reaction wheels keep the speeds relative to the body that the state
        holds (so `lierk.sensitivity` with respect to ``omega0`` holds them
        fixed)."""
        return super().with_omega0(omega0)

    @property
    def splitting_refusal(self) -> str | None:
        """Why the splitting solvers cannot take this body, or None: their
        drift is the exact torque-free flow of a rigid body, which a body with
        reaction wheels does not follow."""
        if self.wheel_index is None:
            return None
        return (
            "the splitting solvers (Strang, Yoshida4, BlanesMoan4, ...) drift with the exact torque-free flow of a "
            f"rigid body, which a body with ReactionWheels (effects[{self.wheel_index}]) does not follow; use an RKMK, "
            "CF4 or adaptive solver (RKMK4, CF4, DP54, DOP853, ...)"
        )

    def _refuse_splitting(self):
        raise ValueError(self.splitting_refusal)

    def drift(self, R, y, h):
        if self.wheel_index is not None:
            self._refuse_splitting()
        return super().drift(R, y, h)

    def kick(self, t, R, y, h):
        if self.wheel_index is not None:
            self._refuse_splitting()
        return super().kick(t, R, y, h)

    def _space_vectors(self) -> Array | None:
        """The effects' `AbstractEffect.space_vectors` stacked, ``(K, 3)``, or
        None when some effect reads the attitude another way."""
        vs = [e.space_vectors() for e in self.effects]
        if any(v is None for v in vs):
            return None
        # Constants stay NumPy: every stage asks for them, and jax.numpy would
        # trace the same constant operations again each time.
        xp = np if all(isinstance(v, np.ndarray) for v in vs) else jnp
        return xp.concatenate(
            [xp.asarray(v, self.R0.dtype).reshape(-1, 3) for v in vs] + [xp.zeros((0, 3), self.R0.dtype)]
        )

    # Stages never need the whole attitude when every effect reads it only
    # through the body images R^T s of a few space-fixed vectors s (gravity's
    # vertical, a space-fixed torque): the base of a step is those images, and
    # at a stage point R_n exp(u) they are exp(-u) R_n^T s, a Rodrigues rotation
    # of each vector, with no 3x3 product.  Without such vectors (no effects,
    # body torques, damping) the stage point is not formed at all.
    def base(self, t, R, y):
        S = self._space_vectors()
        return R if S is None else so3.compose(S, R)  # rows: (R^T s_j)^T

    def advance(self, base, u, coefficients=None):
        if self._space_vectors() is None:
            return super().advance(base, u, coefficients)
        return so3.rotate(-u, base, coefficients)

    def turn_tangent(self, point, xi):
        """With space vectors the point is their body images ``v_j = R^T s_j``
        (rows), which a body-frame turn ``exp(hat(eps xi))`` moves by
        ``v_j x xi``; otherwise the attitude's ``R hat(xi)``."""
        if self._space_vectors() is None:
            return super().turn_tangent(point, xi)
        return so3.cross(point, xi)

    def at(self, base, t, y):
        if self.wheel_index is not None:
            return self._at_with_wheels(base, t, y)
        omega = so3._diagonal(self.inertia_inv) * y if self.diagonal else self.inertia_inv @ y
        return omega, self._add_torques(so3.cross(y, omega), base, t, y, omega)

    def _add_torques(self, dm, base, t, m, omega):
        """``dm`` plus every effect's torque at the point ``base``, time ``t``,
        momentum ``m`` and angular velocity ``omega`` (reaction wheels, which
        are no torque, aside)."""
        vectors = self._space_vectors() is not None
        start = 0
        for i, e in enumerate(self.effects):
            if i == self.wheel_index:
                continue
            # The scope names the effect's equations (including the sum, so a
            # constant torque shows up too) in jaxprs and profiles.
            with jax.named_scope(f"lierk_effect_{type(e).__name__}"):
                if vectors:
                    k = np.shape(e.space_vectors())[0]
                    dm = dm + e.torque_from(t, base[start : start + k], m, omega)
                    start += k
                else:
                    dm = dm + e.torque(t, base, m, omega)
        return dm

    def _at_with_wheels(self, base, t, y):
        """Basilisk's balanced wheels (`lierk.ReactionWheels`): ``(I - G)
        omega' = (m + h_w) x omega - sum u g + tau`` with ``h_w = sum Js Omega
        g``, then ``m' = I omega'`` and ``Omega' = u / Js - g . omega'``."""
        m, speeds = y
        w = self.wheels
        omega = so3._diagonal(self.inertia_inv) * m if self.diagonal else self.inertia_inv @ m
        with jax.named_scope("lierk_effect_ReactionWheels"):
            u = w.motor_torque(t)
            u = None if u is None else u.astype(m.dtype)
            rhs = so3.cross(m + _wheel_sum(w.spin_inertia * speeds, w.axes), omega)
            if u is not None:
                rhs = rhs - _wheel_sum(u, w.axes)
        rhs = self._add_torques(rhs, base, t, m, omega)
        with jax.named_scope("lierk_effect_ReactionWheels"):
            # I - G is formed and solved here, not kept from the constructor:
            # a perturbed spin inertia or axis (a sensitivity with respect to
            # it) then turns the body as it should.  A 3x3 solve by cofactors
            # is a few dozen products that fuse with the rest of the stage.
            domega = _solve3(self.inertia - _spin_matrix(w.spin_inertia, w.axes), rhs)
            dm = so3._diagonal(self.inertia) * domega if self.diagonal else self.inertia @ domega
            dspeeds = -_along(w.axes, domega)
            if u is not None:
                dspeeds = dspeeds + u / w.spin_inertia
        return omega, (dm, dspeeds)

    def field(self, t, R, y):
        return self.at(self.base(t, R, y), t, y)

    def local(self, base, t, u, y, coefficients=None):
        S = self._space_vectors()
        if S is not None and S.shape[0] == 0:
            # The torques do not depend on the attitude: skip the stage point.
            return self.at(base, t, y)
        return super().local(base, t, u, y, coefficients)

    def _effects_linearisation(self, t, R, y):
        """The effects' torque at ``(R, y)``, time ``t``, linearised in the
        attitude and returned as ``I^-1 K_u`` (1/s^2; ``K_u`` in N m/rad for a
        body-frame rotation ``R exp(hat(u))``), and in the momentum, ``K_m``
        (1/s), both ``(3, 3)``, and the rate
        (rad/s) at which time turns them, ``max(||dK/dt|| / ||K||)`` (an
        orbit's or a rotating field's; 0 for effects that do not depend on
        time).  Not differentiated.

        With reaction wheels ``K_m`` is taken with the wheels' absolute
        momenta ``Js (Omega + g . omega)`` held, which their motor torques
        alone change: perturbations of them do not grow or turn, so the
        modes are those of ``m`` with them fixed (the gyrostat's nutation
        through ``I - G``)."""
        m0 = self._body_momenta(R, y)
        t = jnp.asarray(t, m0.dtype)

        def linearised(t):
            base = self.base(t, R, y)

            def torque(u, m):
                # The point turned to first order in u (`turn_tangent`): its
                # value and derivative at u = 0, all that is asked of it, are
                # those of the exact turn (`local`), without the derivative of
                # the exponential's series (a third of a differentiated
                # adaptive step's trace, which the loop's transformations
                # process again and again).
                point = base + self.turn_tangent(base, u)
                omega, dm = self.at(point, t, self._state_with_momentum(y, m))
                return self._body_momenta(R, dm) - so3.cross(m, omega)

            K_u, K_m = jax.jacfwd(torque, argnums=(0, 1))(jnp.zeros(3, m0.dtype), m0)
            # A diagonal inertia's product is a scaling of rows, which fuses
            # with the norms `modes` takes (a dot is a kernel of its own).
            if self.diagonal:
                return so3._diagonal(self.inertia_inv)[:, None] * K_u, K_m
            return self.inertia_inv @ K_u, K_m

        if not any(e.depends_on_time for e in self.effects):
            K_u, K_m = linearised(t)
            return jax.lax.stop_gradient((K_u, K_m, jnp.zeros((), m0.dtype)))
        (K_u, K_m), (dK_u, dK_m) = jax.jvp(linearised, (t,), (jnp.ones_like(t),))

        def rate(K, dK):
            size = _frobenius(K)
            return jnp.where(size > 0, _frobenius(dK) / jnp.where(size > 0, size, 1.0), 0.0)

        return jax.lax.stop_gradient((K_u, K_m, jnp.maximum(rate(K_u, dK_u), rate(K_m, dK_m))))

    def _state_with_momentum(self, y, m):
        """The state ``y`` with its body momentum replaced by ``m``; reaction
        wheels keep their absolute momenta (their relative speeds take up
        the change of ``g . omega``)."""
        if self.wheel_index is None:
            return m
        m0, speeds = y
        return m, speeds - _along(self.wheels.axes, so3.matvec(self.inertia_inv, m - m0))

    def modes(self, t, R, y):
        """``(frequency, decay)``: bounds on the oscillation or growth (rad/s)
        and on the decay (1/s, ``||sym(K_m)||_F``) of small perturbations
        about ``(R, y)`` at time ``t`` (s).  The frequency: the torque-free nutation
        (`AbstractRigidBody`) and the effects' own, from their torque
        linearised (``K_u``, ``K_m``).  An attitude stiffness turns a
        perturbation at ``sqrt(||I^-1 K_u||)`` (a pendulum's frequency
        ``sqrt(M g l / I)``, a gravity-gradient libration's, the same growth
        rate upright); with the gyroscopic frequency ``rho`` and the stiffness
        ``s = ||I^-1 K_u||`` the fastest mode is ``(rho + sqrt(rho^2 + 4 s))
        / 2``, the fast nutation of a spinning top under gravity.  The
        momentum coupling's antisymmetric part turns it too (a wheel's
        nutation ``|h| / I``), and its symmetric part may make it grow; its
        decay (a damper's, a B-dot law's) is `decay_rate`'s.  Where time
        turns the linearisation (an orbit, a rotating field: a body at rest
        does not move, its perturbations do), that rate adds.  Frobenius norms
        and Gershgorin's bound, so each is bounded from above.  Works for any
        effect, a user's too: the torque is differentiated, not looked up."""
        rho = AbstractRigidBody.mode_frequency(self, t, R, y)
        if not self.effects:
            return rho, jnp.zeros((), rho.dtype)
        IK_u, K_m, turned = self._effects_linearisation(t, R, y)
        stiffness = _frobenius(IK_u)
        turning = _frobenius(0.5 * (K_m - K_m.T))
        sym = 0.5 * (K_m + K_m.T)
        d = so3._diagonal(sym)
        growth = jnp.maximum(0.0, jnp.max(d + jnp.sum(jnp.abs(sym), axis=1) - jnp.abs(d)))
        frequency = 0.5 * (rho + jnp.sqrt(rho**2 + 4.0 * stiffness)) + turning + growth + turned
        return frequency, _frobenius(sym)

    def mode_frequency(self, t, R, y):
        """`modes`' frequency (rad/s)."""
        return self.modes(t, R, y)[0]

    def decay_rate(self, t, R, y):
        """The fastest decay (1/s) of small perturbations of the momentum under
        the effects (``||sym(K_m)||_F``: a damper's ``c / I``, a B-dot law's
        ``k |B|^2 / I``), 0 without effects; see `modes`."""
        return self.modes(t, R, y)[1]

    def free_flow(self, m: Array, h: Array) -> tuple[Array, Array]:
        """The exact torque-free flow over ``h`` (s) from body momentum ``m``
        ``(3,)``: ``(Q, m_h)``, the body turning by ``Q`` ``(3, 3)`` (``R -> R Q``).
        A symmetric body (`symmetry_axis`) uses two rotations
        (`lierk.exact.symmetric_flow`), any other the elliptic-function
        solution (`lierk.exact.free_flow`)."""
        k = self.symmetry_axis
        if k is None:
            return exact.free_flow(self.inertia, m, h)
        moments = so3._diagonal(self.inertia)
        return exact.symmetric_flow(moments[(k + 1) % 3], moments[k], k, m, h)

    @property
    def closed_form_drift(self) -> bool:
        """Whether `drift` is the symmetric body's closed form (two rotations,
        small to compile), rather than the elliptic-function flow: the
        splitting solvers then unroll their stages."""
        return self.symmetry_axis is not None

    def error_tolerance(self, y0, y1, rtol, atol):
        """The momentum's error is measured as a vector against
        ``atol * m_ref + rtol * max(|m_n|, |m_n+1|)``: relative to its size, so
        units and body size drop out, and near a principal axis the small
        components are not held to a relative accuracy they cannot matter for.
        ``m_ref`` (`momentum_scale`) keeps a body at rest well defined.
        Reaction wheels' speeds likewise, as one vector against ``atol *
        Omega_ref + rtol * max(|Omega_n|, |Omega_n+1|)`` (`wheel_speed_scale`):
        ``rtol`` is relative for them too."""
        if self.wheel_index is not None:
            (m0, s0), (m1, s1) = y0, y1
            size = jnp.maximum(jnp.linalg.norm(s0), jnp.linalg.norm(s1))
            speeds = jnp.broadcast_to(atol * self.wheel_speed_scale + rtol * size, s0.shape)
            return self.error_tolerance_momentum(m0, m1, rtol, atol), speeds
        return self.error_tolerance_momentum(y0, y1, rtol, atol)

    def error_tolerance_momentum(self, m0, m1, rtol, atol):
        """`error_tolerance`'s for the body momentum ``(3,)`` alone."""
        size = jnp.maximum(jnp.linalg.norm(m0), jnp.linalg.norm(m1))
        return jnp.broadcast_to(atol * self.momentum_scale + rtol * size, m0.shape)

    @property
    def momentum_scale(self) -> Array:
        """A reference momentum (kg m^2/s) for absolute tolerances: ``|m0|``, plus
        the momentum that the effects' potential energy can give the body,
        ``sqrt(I_max * sum(effect.energy_scale()))``, plus the reaction wheels'
        relative momentum ``|sum Js Omega0 g|`` (which they can hand to the
        body); for a body at rest without potential, ``I_max * 1 rad/s``."""
        i_max = jnp.max(jnp.abs(self.inertia))
        scale = jnp.linalg.norm(self._body_momenta(self.R0, self.y0)) + jnp.sqrt(i_max * self._effects_energy())
        if self.wheel_index is not None:
            w = self.wheels
            scale = scale + jnp.linalg.norm(_wheel_sum(w.spin_inertia * self.y0[1], w.axes))
        # A body at rest without potential: I_max times 1 rad/s.
        return jnp.where(scale > 0, scale, i_max)

    @property
    def wheel_speed_scale(self) -> Array:
        """A reference speed (rad/s) for the reaction wheels' absolute
        tolerances: ``|Omega0|`` plus the body's rate scale ``momentum_scale /
        I_max`` (1 rad/s for a body and wheels at rest)."""
        if self.wheel_index is None:
            raise ValueError("wheel_speed_scale: this body has no ReactionWheels")
        return jnp.linalg.norm(self.y0[1]) + self.momentum_scale / jnp.max(jnp.abs(self.inertia))

    def invariant_scales(self):
        """Energies against the kinetic energy plus what the effects' potentials
        can give; momenta against `momentum_scale`."""
        if self.wheel_index is not None:
            kinetic = self._wheels_kinetic_energy(*self.y0)
        else:
            kinetic = kinetic_energy(self.inertia, self.omega0)
        energy = kinetic + self._effects_energy()
        return {k: (energy if k == "energy" else self.momentum_scale) for k in self.conserved()}

    def _wheels_kinetic_energy(self, m, speeds):
        """The kinetic energy (J) of the body with its reaction wheels,
        ``omega . I omega / 2 + sum Js Omega (g . omega) + sum Js Omega^2 / 2``
        (``I`` the whole spacecraft's inertia), at momenta ``m`` ``(..., 3)``
        and speeds ``(..., k)``."""
        w = self.wheels
        omega = so3.matvec(self.inertia_inv, m)
        spin = w.spin_inertia * speeds
        return (
            kinetic_energy(self.inertia, omega)
            + jnp.sum(spin * _along(w.axes, omega), axis=-1)
            + 0.5 * jnp.sum(spin * speeds, axis=-1)
        )

    def invariants(self, R, y):
        """``"energy"`` (kinetic plus every effect's potential, J), ``"|L|"``
        (kg m^2/s) and each effect's own `AbstractEffect.invariants`.  With
        reaction wheels the kinetic energy and the momentum are the whole
        spacecraft's (`lierk.ReactionWheels`), and the other effects'
        invariants read its whole momentum ``m + sum Js Omega g``."""
        if self.wheel_index is None:
            return super().invariants(R, y)
        m, speeds = y
        w = self.wheels
        H = m + _wheel_sum(w.spin_inertia * speeds, w.axes)
        energy = self._wheels_kinetic_energy(m, speeds)
        out = {}
        for i, e in enumerate(self.effects):
            if i != self.wheel_index:
                energy = energy + e.potential(R)
                out.update(e.invariants(R, H))
        return {"energy": energy, "|L|": jnp.linalg.norm(H, axis=-1), **out}

    def conserved(self):
        """As `AbstractRigidBody.conserved`; with reaction wheels and no other
        effect also ``"|L|"``, the whole spacecraft's momentum, driven or not
        (the motors' torques are internal)."""
        keys = super().conserved()
        if self.wheel_index is not None and len(self.effects) == 1:
            keys = keys + ("|L|",)
        return keys

    def _effects_energy(self) -> Array:
        """The energy (J) the effects can give the body: sum of `energy_scale`."""
        # In the body's dtype: an effect's own 0 is the default float (float64
        # under x64), which made a float32 body's loop carry change dtype.
        dtype = self.R0.dtype
        return sum((jnp.asarray(e.energy_scale(), dtype) for e in self.effects), jnp.zeros((), dtype))


class FreeRigidBody(RigidBodyWithEffects):
    """The torque-free rigid body: `RigidBodyWithEffects` with no effects.

    The state is the attitude and the body momentum ``m`` (``y``), advanced by
    Euler's equations ``m' = m x I^{-1} m`` with the solver's tableau.  This is
    the most accurate formulation near the intermediate axis (see the module
    docstring); the report's own formulation, with spatial ``L`` fixed and
    ``|m|`` and ``L`` conserved to rounding, is `lierk.SpatialFreeRigidBody`.

    Args:
        inertia: ``(3, 3)`` symmetric positive-definite, or ``(3,)`` principal
            moments (kg m^2), in the body frame.
        omega0: ``(3,)`` initial body angular velocity (rad/s).
        R0: ``(3, 3)`` initial attitude, body -> space (identity if None).

    Example:
        >>> body = FreeRigidBody(lierk.inertia.tee_handle(), [1.0, 0.05, 0.0])
        >>> sol = lierk.solve(body, lierk.RKMK4(), 10.0, dt=0.01)
    """

    def __init__(self, inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None = None):
        super().__init__(inertia, omega0, R0, effects=())


def _solve3(M: Array, r: Array) -> Array:
    """``M^-1 r`` for a symmetric ``(3, 3)`` ``M`` by cofactors: the rows of
    ``M^-1`` are ``(c1 x c2, c2 x c0, c0 x c1) / det M`` for its columns
    ``c_j`` (its rows, being symmetric)."""
    c0, c1, c2 = M[0], M[1], M[2]
    a, b, c = so3.cross(c1, c2), so3.cross(c2, c0), so3.cross(c0, c1)
    det = c0[0] * a[0] + c0[1] * a[1] + c0[2] * a[2]
    x = jnp.stack(
        [
            a[0] * r[0] + a[1] * r[1] + a[2] * r[2],
            b[0] * r[0] + b[1] * r[1] + b[2] * r[2],
            c[0] * r[0] + c[1] * r[1] + c[2] * r[2],
        ]
    )
    return x / det


def _check_wheels(inertia: Array, axes: Array, spin_inertia: Array, path: str) -> tuple[Array, Array, Array]:
    """``(inertia, axes, spin_inertia)``, checked: ``I - G`` must be positive
    definite, ``I`` being the whole spacecraft's inertia and the wheels' spin
    inertia ``G = sum Js g g^T`` part of it.  Concrete values raise now;
    traced ones at run time (`lierk._validation.check`)."""
    message = (
        f"{path}.spin_inertia: the wheels' spin inertia G = sum Js g g^T must leave I - G positive definite, since "
        "the body's inertia I is the whole spacecraft's, wheels included (I - G turns the body under a motor "
        "torque)"
    )
    if validation.is_traced(inertia, axes, spin_inertia):

        def positive_definite(x):
            # Sylvester's leading minors, as `validation.check_inertia`.
            A = x[0] - _spin_matrix(x[2], x[1])
            minor2 = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
            det = (
                A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
                - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
                + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0])
            )
            return (A[0, 0] > 0) & (minor2 > 0) & (det > 0)

        return validation.check((inertia, axes, spin_inertia), positive_definite, message + "; got {value}")
    g, js, I = (np.asarray(x, float) for x in (axes, spin_inertia, inertia))
    moments = np.linalg.eigvalsh(I - (g.T * js) @ g)
    if not moments.min() > 1e-12 * np.abs(I).max():
        raise ValueError(
            f"{message}; with I = {np.array2string(I, precision=6, separator=', ')} and Js = "
            f"{np.array2string(js, precision=6, separator=', ')}, I - G has eigenvalues "
            f"{np.array2string(moments, precision=6, separator=', ')}"
        )
    return inertia, axes, spin_inertia


def _frobenius(A: Array) -> Array:
    """The Frobenius norm of a matrix ``(3, 3)``: the bound `modes` takes of
    each part of the effects' linearisation."""
    return jnp.sqrt(jnp.sum(A * A))


@jax.jit
def _momentum(inertia: Array, omega0: Array) -> Array:
    """``I omega0`` ``(3,)`` as one compiled program: eager ``jax.numpy``
    compiles one per operation, for concrete values and for the values an
    eager `jax.jacfwd` or `jax.grad` traces; inside `jax.jit` it is
    inlined, entry by entry (`so3.matvec`): a matrix product is an XLA
    kernel of its own."""
    return so3.matvec(inertia, omega0)


def _symmetry_axis(d: np.ndarray) -> int | None:
    """See `RigidBodyWithEffects.symmetry_axis`: the axis whose two companions
    in the diagonal ``d`` ``(3,)`` are equal to a few ulps."""
    close = lambda a, b: abs(a - b) <= 4 * np.finfo(float).eps * max(abs(a), abs(b))  # noqa: E731
    for k in range(3):
        i, j = (k + 1) % 3, (k + 2) % 3
        if close(d[i], d[j]):
            return k
    return None


def heavy_top(
    inertia_cm: ArrayLike,
    mass: ArrayLike,
    pivot_to_com: ArrayLike,
    omega0: ArrayLike,
    R0: ArrayLike | None = None,
    *,
    g: ArrayLike = 9.81,
    effects: tuple | list = (),
) -> RigidBodyWithEffects:
    """A heavy top: a body turning about a fixed pivot under uniform gravity,
    built as a scene's ``pivot`` builds it.

    `Gravity` needs the problem's inertia about the pivot; this moves the
    inertia about the centre of mass there (`lierk.inertia.parallel_axis`)
    and adds the `Gravity` effect:
    ``RigidBodyWithEffects(parallel_axis(inertia_cm, mass, pivot_to_com),
    omega0, R0, (Gravity(pivot_to_com, mass, g), *effects))``.

    Args:
        inertia_cm: ``(3, 3)`` or ``(3,)`` principal moments (kg m^2), body
            frame, about the centre of mass.
        mass: the body's mass (kg), ``> 0``.
        pivot_to_com: ``(3,)`` body-frame vector from the pivot to the centre
            of mass (m): for a pivot at body point ``p``, ``com - p``.
        omega0: ``(3,)`` initial body angular velocity (rad/s).
        R0: ``(3, 3)`` initial attitude, body -> space (identity if None).
        g: gravitational acceleration (m/s^2), pulling along space ``-z``.
        effects: further effects (damping, torques), after the gravity.

    Returns:
        A `RigidBodyWithEffects` whose momentum is taken about the pivot.

    Example:
        >>> top = lierk.heavy_top(lierk.inertia.solid_cylinder(0.5, 0.04, 0.01), 0.5, [0.0, 0.0, 0.06],
        ...                       [0.0, 0.0, 150.0], lierk.so3.from_euler(0.0, 0.3, 0.0))
    """
    if isinstance(effects, AbstractEffect):
        effects = (effects,)
    gravity = Gravity(pivot_to_com, mass, g)
    inertia = validation.check_inertia(inertia_cm)
    return RigidBodyWithEffects(
        parallel_axis(inertia, gravity.mass, gravity.pivot_to_com), omega0, R0, (gravity, *tuple(effects))
    )
