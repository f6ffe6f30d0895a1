"""Step-size control for embedded pairs (Hairer, Norsett, Wanner I, II.4).

The error is measured in the Lie algebra: a step's estimate ``e_u`` is the
difference of the two solutions' increments ``u_high - u_low`` from the same
base point.  It is an angle (rad) and the attitude is O(1), so ``e_u`` is
scaled by ``atol + rtol``.  Extra state ``y`` is scaled by what the problem
says (`lierk.AbstractProblem.error_tolerance`): the rigid body measures its
momentum relative to ``|m|``, so tolerances are dimensionless and mean the
same for any body size.

Tolerances are local, calibrated to mean global error on one family only.
Error-per-step control bounds
each step's local error, and near the intermediate axis those errors are
amplified on the way to the end of the run, so how far the global error lands
from ``tol`` depends on the pair.  Each tableau therefore carries a measured
``tolerance_calibration`` (`lierk.tableaux.ButcherTableau`): the step's error
estimate is held to ``tol * tolerance_calibration``.  With it the largest
attitude error on near-axis batches of four very different bodies stays
between 1x and 10x of ``tol`` for ``tol`` from 1e-6 to 1e-12, for RKF45, DP54
and DOP853 (``tests/test_accuracy.py``).  Off that family (fast bodies,
long horizons, torqued bodies) the global error is up to ~1e4 ``tol``
(``benchmarks/results/tolerance_scope.md``): ``solve(..., target_error=)``
asks for a global accuracy, and the global error estimate
(``solve(..., estimate_error=True)``) reports what was actually reached.  All controller arithmetic runs under
`jax.lax.stop_gradient`: step sizes are not differentiated (otherwise
``0 * inf`` turns into NaN on the backward pass).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from . import _validation as validation
from . import so3, tableaux
from ._solvers.base import field_at

__all__ = ["AbstractStepController", "Controller", "ConstantStep", "Decision"]


def frozen(tree):
    """A pytree (a problem, a controller, times) with its array leaves out of
    the gradient: an error estimate's finer solve is a diagnostic and would
    double the cost of a backward pass, and DirectAdjoint's deciding solve is
    not differentiated at all."""
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree)


def _leaves(tree) -> list[Array]:
    return [jnp.ravel(x) for x in jax.tree_util.tree_leaves(tree)]


class Decision(NamedTuple):
    """A controller's verdict on one attempted step (`AbstractStepController.adapt`).

    Attributes:
        accept: whether the step is taken.
        h_next: the next attempt's step (s), before the loop clips it to a
            save time or ``t1``.
        stuck: the solve cannot go on (`RESULTS.dt_min_reached`).
        end: the solve ends here without being stuck (a non-finite fixed step,
            reported as `RESULTS.nonfinite`).
        fsal: the field at the new point, or None when the controller does not
            need it.
    """

    accept: Array
    h_next: Array
    stuck: Array
    end: Array
    fsal: Any


class AbstractStepController(eqx.Module):
    """How the while loop of an adaptive solve (`lierk.solve`) chooses its
    steps, in diffrax's shape: `init` once, `adapt` after every attempt.

    Class attributes:
        decides: the steps depend on error tests, so reverse mode must replay
            the recorded decisions (see `lierk._loops`).
    """

    decides: ClassVar[bool]

    def init(self, problem, solver, t0, t1, dt0, floor_eps: float) -> tuple[Any, Array, Any]:
        """``(state, first step (s), field at t0 or None)``; ``state`` is what
        `adapt` needs besides ``self``."""
        raise NotImplementedError

    def adapt(
        self, state, problem, solver, st, *, t, t_new, h, h_proposed, clipped, t1, R, y, f, rejected_last
    ) -> Decision:
        """Judge step ``st`` from ``(t, R, y)`` to ``t_new = t + h`` (``f`` the
        field at ``t``); ``h_proposed`` was the attempt's step before it was
        clipped to a save time or t1 (``clipped``)."""
        raise NotImplementedError

    def bound(self, state, problem, solver, t, R, y, f, h) -> Array:
        """The step (s) an attempt from ``(t, R, y)`` (``f`` the field there)
        takes, given the proposal ``h`` (`init`'s, or `adapt`'s): ``h`` unless
        the state bounds it (`Controller`'s ``resolve_modes``)."""
        return h


class ConstantStep(AbstractStepController):
    """Steps of the given ``dt0``, every one taken; for a fixed-step solve
    whose step count is not static (a traced step size under `vmap`).  A
    non-finite step ends the solve."""

    decides: ClassVar[bool] = False

    def init(self, problem, solver, t0, t1, dt0, floor_eps):
        return None, dt0, None

    def adapt(self, state, problem, solver, st, *, t, t_new, h, h_proposed, clipped, t1, R, y, f, rejected_last):
        finite = validation.all_finite((st.R, st.y))
        return Decision(jnp.asarray(True), h_proposed, h <= 0, ~finite, None)


def _modes_step(modes) -> Array:
    """The largest step (s) that ``modes`` ``(rho, angle, decay)`` allow (a
    mode frequency, rad/s; the largest phase, rad, it may turn per step; a
    decay rate, 1/s): the phase ``rho h`` at most ``angle``, and ``h decay``
    at most 2, within stability."""
    rho, angle, decay = modes
    turn = jnp.where(rho > 0, angle / jnp.where(rho > 0, rho, 1.0), jnp.inf)
    return jnp.minimum(turn, jnp.where(decay > 0, 2.0 / jnp.where(decay > 0, decay, 1.0), jnp.inf))


def _compact(solver) -> bool:
    """Whether ``solver`` loops over its stages (`lierk.AbstractRKMK.compact`
    True: one body's solve, a differentiated one): the controller's helpers
    then take their compact forms, fewer XLA kernels to compile, where a
    batch's forms run faster."""
    return getattr(solver, "compact", None) is True


class Controller(AbstractStepController):
    """Error-per-step controller ``h_new = h min(facmax, max(facmin, safety err^(-1/(q+1))))``.

    Every field is an array leaf, so sweeping tolerances never recompiles.

    Attributes:
        rtol, atol: relative and absolute tolerances (dimensionless; the
            attitude is O(1)).
        safety: 0.9 by default.
        facmin, facmax: bounds on the step-size ratio; ``facmax`` is 1 right
            after a rejection.
        dtmin: smallest allowed step (s); below it the solve stops with
            `RESULTS.dt_min_reached`.  Machine precision relative to ``t`` is
            always a floor.
        dtmax: largest allowed step (s).
        max_angle: largest body rotation ``|omega| h`` (rad) the controller
            proposes for a step, with ``omega`` the body angular velocity
            where the step starts (the rotation itself differs when omega
            changes within the step); pi by default, ``inf`` for no bound.
            Every RKMK stage applies dexpinv, whose pole is at 2 pi: steps
            that turn the body by more than a half-turn often fail their
            error test, and at loose
            tolerances the controller kept proposing them (on heavy tops
            spun at 30 to 120 rad/s, DOP853 at rtol 1e-4 rejected 28% of its
            attempts and took more steps than at 1e-5; with the bound it
            rejects none, takes 38% fewer, and is 3x more accurate).
        resolve_modes: also keep the phase ``rho h`` of the body's fastest
            small perturbation (`lierk.AbstractProblem.mode_frequency`, the
            torque-free nutation of a rigid body and its effects' modes)
            within what the error test
            would accept for a unit oscillation at this tolerance,
            ``(tol / c)^(1/(q+1))`` with ``c`` from
            `lierk.tableaux.oscillation_error_constant`.  The error estimate
            measures the state, and about a steady spin the state does not
            move: steps grow to the turn bound, where perturbations, and so
            derivatives, are not resolved (an adaptive DP54 Jacobian of a
            symmetric body spinning about its axis was 1e10 off, reported
            successful).  Off (False) for plain solves, which it can only
            slow; a differentiated solve turns it on (the default adjoint,
            `lierk.ForwardSensitivity`, and `lierk.sensitivity`); with
            another adjoint, set it where the body may spin steadily.
            Static.
    """

    decides: ClassVar[bool] = True

    rtol: Array
    atol: Array
    safety: Array
    facmin: Array
    facmax: Array
    dtmin: Array
    dtmax: Array
    max_angle: Array
    resolve_modes: bool = eqx.field(static=True)

    def __init__(
        self,
        rtol: ArrayLike = 1e-6,
        atol: ArrayLike = 1e-9,
        *,
        safety: ArrayLike = 0.9,
        facmin: ArrayLike = 0.2,
        facmax: ArrayLike = 10.0,
        dtmin: ArrayLike = 0.0,
        dtmax: ArrayLike = float("inf"),
        max_angle: ArrayLike = math.pi,
        resolve_modes: bool = False,
    ):
        # Checks run on NumPy values while they are known (see `lierk._validation`);
        # everything becomes a JAX array only at the end.
        def scalar(name, x):
            x = validation.asarray(x, name=name)
            if x.ndim != 0:
                raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(x)}")
            return x

        def bounded(name, x, ok, what):
            return validation.check(scalar(name, x), ok, f"{name} must be {what}, got {{value}}")

        inf = float("inf")
        rtol, atol = scalar("rtol", rtol), scalar("atol", atol)
        # Traced, both are checked in one program (a sweep over tolerances);
        # keep every checked value: a traced check whose result is dropped
        # is dead code to XLA.
        rtol, atol = validation.check_together(
            [
                (rtol, lambda v: (v >= 0) & (v < inf), "rtol must be >= 0 and finite, got {value}"),
                (atol, lambda v: (v >= 0) & (v < inf), "atol must be >= 0 and finite, got {value}"),
            ]
        )
        rtol, atol = validation.check(
            (rtol, atol), lambda ra: ra[0] + ra[1] > 0, "rtol + atol must be > 0, got rtol = 0 and atol = 0"
        )
        # Outside these bounds the step-size update cannot converge: a solve
        # would spin until max_steps.
        safety = bounded("safety", safety, lambda v: (v > 0) & (v <= 1), "in (0, 1]")
        facmin = bounded("facmin", facmin, lambda v: (v > 0) & (v < 1), "in (0, 1)")
        facmax = bounded("facmax", facmax, lambda v: (v > 1) & (v < inf), "> 1 and finite")
        dtmin = bounded("dtmin", dtmin, lambda v: (v >= 0) & (v < inf), ">= 0 and finite")
        dtmax = bounded("dtmax", dtmax, lambda v: (v > 0) & (v >= dtmin), "> 0 and >= dtmin")
        max_angle = bounded("max_angle", max_angle, lambda v: v > 0, "> 0 (rad; inf for no bound)")
        self.rtol, self.atol, self.safety, self.facmin, self.facmax, self.dtmin, self.dtmax, self.max_angle = (
            validation.as_jax_each(rtol, atol, safety, facmin, facmax, dtmin, dtmax, max_angle)
        )
        if not isinstance(resolve_modes, bool):
            raise ValueError(f"resolve_modes must be True or False, got {resolve_modes!r}")
        self.resolve_modes = resolve_modes

    @classmethod
    def from_tolerances(cls, rtol: ArrayLike, atol: ArrayLike | None = None) -> "Controller":
        """The controller that ``solve(..., rtol=, atol=)`` builds: ``atol``
        defaults to ``rtol``."""
        return cls(rtol, rtol if atol is None else atol)

    def resolving_modes(self) -> "Controller":
        """This controller with ``resolve_modes=True``, its (possibly traced)
        values unchanged and not validated again."""
        if self.resolve_modes:
            return self
        structure = jax.tree_util.tree_structure(Controller(resolve_modes=True))
        return jax.tree_util.tree_unflatten(structure, jax.tree_util.tree_leaves(self))

    def largest_step(self, omega: Array, *, compact: bool = False) -> Array:
        """The largest step (s) the controller proposes when a step starts at
        body angular velocity ``omega`` ``(..., 3)`` (rad/s): ``dtmax``, and
        at most ``max_angle / |omega|``, but never below ``dtmin`` (a bound the
        user set explicitly wins).  The mode bounds (``resolve_modes``) apply
        where each step starts (`bound`).  ``compact`` (one body's form,
        `lierk._programs`): ``|omega|`` entry by entry, which XLA fuses with
        its neighbours, where a reduction is a kernel of its own; a batch runs
        slower that way.  The same numbers either way."""
        speed2 = so3._sq(omega) if compact else jnp.sum(omega * omega, axis=-1)
        turn = jnp.where(speed2 > 0, self.max_angle / jnp.sqrt(jnp.where(speed2 > 0, speed2, 1.0)), jnp.inf)
        return self._within_limits(turn)

    def _within_limits(self, h: Array) -> Array:
        """``h`` within ``[dtmin, dtmax]``, a decision (no derivative)."""
        return jax.lax.stop_gradient(jnp.maximum(self.dtmin, jnp.minimum(self.dtmax, h)))

    def norm(self, e_u: Array, e_y, tol_y) -> Array:
        """RMS of the scaled error over the algebra's 3 components and y's:
        ``e_u / (atol + rtol)`` and ``e_y / tol_y``, with ``tol_y`` from
        `lierk.AbstractProblem.error_tolerance`."""
        terms = [e_u / (self.atol + self.rtol)]
        for e, s in zip(_leaves(e_y), _leaves(tol_y)):
            terms.append(e / s)
        x = jnp.concatenate(terms)
        return jnp.sqrt(jnp.mean(x * x))

    def factor(self, err: Array, error_order: int, after_reject: Array) -> Array:
        """Step-size ratio for the next attempt from a step's error norm."""
        err = jax.lax.stop_gradient(err)
        safe = jnp.where(err > 0, err, 1.0)
        fac = jnp.where(err > 0, self.safety * safe ** (-1.0 / (error_order + 1)), self.facmax)
        facmax = jnp.where(after_reject, 1.0, self.facmax)
        return jnp.clip(jnp.where(jnp.isfinite(fac), fac, self.facmin), self.facmin, facmax)

    def init(self, problem, solver, t0, t1, dt0, floor_eps):
        # Tolerances given as Python floats become float64 under x64: every
        # controller (given, or built by a target_error round) computes in the
        # problem's dtype.
        ctrl = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype=problem.R0.dtype), self)
        # The estimate is held to tol * tolerance_calibration, but never below
        # 50 eps: under that, rounding noise decides acceptance.  Such steps
        # only add rounding error, and a reverse-mode pass that recomputes them
        # from checkpoints could decide differently from the forward pass, so
        # the gradient would depend on max_steps.
        # (The finer solves behind error estimates, which are not
        # differentiated, use a smaller floor: at 50 eps both solves of a pair
        # were the same solve in float32 below rtol ~1e-5, and their gap said
        # nothing.)
        floor = floor_eps * jnp.finfo(problem.R0.dtype).eps / (ctrl.rtol + ctrl.atol)
        calibration = jax.lax.stop_gradient(jnp.maximum(solver.tableau.tolerance_calibration, floor))
        mode_angle = None
        if self.resolve_modes:
            c = tableaux.oscillation_error_constant(solver.tableau)
            allowed = (ctrl.rtol + ctrl.atol) * calibration / c
            mode_angle = jax.lax.stop_gradient(jnp.minimum(ctrl.max_angle, allowed ** (1.0 / (solver.error_order + 1))))
        f0 = field_at(problem, t0, problem.R0, problem.y0)
        compact = _compact(solver)
        # The mode bounds (``resolve_modes``) apply where each step starts,
        # the first included (`bound`).
        if dt0 is None:
            h0 = ctrl._initial_step(problem, solver.error_order, t0, t1, f0, compact=compact)
        else:
            # A given first step obeys the controller's bounds like every other.
            h0 = jnp.minimum(dt0, ctrl.largest_step(f0[0], compact=compact))
        return (ctrl, calibration, mode_angle), h0, f0

    def bound(self, state, problem, solver, t, R, y, f, h):
        """``h`` within the mode bounds at ``(t, R, y)`` (``resolve_modes``;
        `largest_step`).  Applied where each step starts rather than where
        the last one ended: one linearisation in the program, not a second
        for the first step, so fewer kernels to compile.  The steps are the same: min and
        max are exact, and the bound is the one `adapt`'s proposal met
        before (a rejected attempt whose proposal only the bound takes below
        the smallest step now tries once more before it ends as stuck).
        Recorded decisions (reverse mode's replay) hold the proposal; a
        replay bounds it again from the same state."""
        ctrl, _, mode_angle = state
        if mode_angle is None:
            return h
        # The turn bound of omega is `adapt`'s, already in ``h``:
        # min(within(a), within(b)) = within(min(a, b)).
        return jnp.minimum(h, ctrl._within_limits(_modes_step(self._modes(problem, t, R, y, mode_angle))))

    def adapt(self, state, problem, solver, st, *, t, t_new, h, h_proposed, clipped, t1, R, y, f, rejected_last):
        ctrl, calibration, mode_angle = state
        tol_y = problem.error_tolerance(y, st.y, ctrl.rtol, ctrl.atol)
        err = solver.error_norm(st.error, lambda e_u, e_y: ctrl.norm(e_u, e_y, tol_y))
        err = jax.lax.stop_gradient(err / calibration)
        f_new = st.fsal if st.fsal is not None else field_at(problem, t_new, st.R, st.y)
        compact = _compact(solver)
        finite = validation.all_finite((st.R, st.y, f_new, err), compact=compact)
        accept = finite & (err <= 1.0)
        # The turn bound reads omega where the next step starts (the mode
        # bounds too, there: `bound`).
        largest = ctrl.largest_step(jnp.where(accept, f_new[0], f[0]), compact=compact)
        h_next = jnp.minimum(h * ctrl.factor(err, solver.error_order, rejected_last), largest)
        # Keep the proposed step when only a save time or t1 shortened it.
        h_next = jnp.where(accept & clipped, jnp.maximum(h_next, jnp.minimum(h_proposed, largest)), h_next)
        eps = jnp.finfo(h.dtype).eps
        h_floor = jnp.maximum(ctrl.dtmin, 16 * eps * jnp.maximum(jnp.abs(t), jnp.abs(t1)))
        # A step that does not move the clock (below its resolution) is stuck too.
        stuck = (~accept & (h_next < h_floor)) | (h <= 0)
        return Decision(accept, h_next, stuck, jnp.asarray(False), f_new)

    @staticmethod
    def _modes(problem, t, R, y, angle):
        """`largest_step`'s ``modes`` at the state ``(R, y)``, time ``t``."""
        # A bound on the step is a decision, never differentiated: cut the
        # state's tangents before the linearisation, not after, so that a
        # differentiated solve does not trace (and compile) the derivative of
        # the body's linearisation in every direction, only to drop it.
        frequency, decay = problem.modes(*jax.lax.stop_gradient((t, R, y)))
        return frequency, angle, decay

    def _initial_step(self, problem, q: int, t0, t1, f0, *, compact: bool = False):
        """Hairer-Norsett-Wanner's starting step (II.4), in the algebra about ``R0``."""
        sg = jax.lax.stop_gradient
        # The step is a decision, never differentiated: cut the tangents at
        # the inputs, so that a differentiated solve does not trace the trial
        # point's derivative only to drop it.
        problem, (omega0, ydot0), t0, t1 = frozen((problem, f0, t0, t1))
        R0, y0 = problem.R0, problem.y0
        tol = problem.error_tolerance(y0, y0, self.rtol, self.atol)
        # The attitude's size is 1 (entries of R are O(1)); y's is its own.
        sizes, slopes = (jnp.ones_like(omega0), y0), (omega0, ydot0)
        if jax.tree_util.tree_structure(sizes) == jax.tree_util.tree_structure(slopes):
            # Both norms as one batched reduction: one XLA kernel, not two.
            pairs = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), sizes, slopes)
            d0, d1 = sg(jax.vmap(lambda e_u, e_y: self.norm(e_u, e_y, tol))(*pairs))
        else:  # y has no rate (y' is None)
            d0, d1 = sg(self.norm(*sizes, tol)), sg(self.norm(*slopes, tol))
        big = (d0 > 1e-5) & (d1 > 1e-5)
        h0 = jnp.where(big, 0.01 * d0 / jnp.where(big, d1, 1.0), 1e-6)
        y1 = jax.tree_util.tree_map(lambda a, b: a + h0 * b, y0, ydot0)
        # The trial point turns by h0 |omega0|: with h0 = 0.01 d0/d1, a few
        # hundredths of a radian at most (else h0 = 1e-6 s).  The
        # exponential's coefficients to second order in the angle serve the
        # estimate, and keep a copy of `so3.exp_coefficients`' series (about
        # 200 instructions) out of every adaptive program.  (The angle is
        # clipped: finite and bounded coefficients whatever it is.)
        u = h0 * omega0
        theta2 = jnp.minimum(so3._sq(u), 1.0)
        coefficients = (1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0, 1.0 / 12.0 + theta2 / 720.0)
        omega1, ydot1 = problem.local(problem.base(t0, R0, y0), t0 + h0, u, y1, coefficients)
        d2 = sg(self.norm(omega1 - omega0, jax.tree_util.tree_map(lambda a, b: a - b, ydot1, ydot0), tol) / h0)
        dmax = jnp.maximum(d1, d2)
        safe = jnp.where(dmax > 0, dmax, 1.0)
        h1 = jnp.where(dmax > 1e-15, (0.01 / safe) ** (1.0 / (q + 1)), jnp.maximum(1e-6, h0 * 1e-3))
        # A field that is exactly zero (omega0 = 0 and no forcing) is solved by any
        # step: take the whole interval.
        span = t1 - t0
        h = jnp.where(dmax == 0, span, jnp.minimum(100 * h0, h1))
        return sg(jnp.clip(h, 0, self.largest_step(omega0, compact=compact)))
