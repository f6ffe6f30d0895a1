"""`solve`: fixed steps through `lax.scan`, adaptive steps through a while loop."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import _checks, so3
from .adjoint import AbstractAdjoint, RecursiveCheckpointAdjoint
from .adjoint import ForwardMode as ForwardModeAdjoint
from .controller import Controller
from .fields import AbstractProblem
from .solution import RESULTS, SaveAt, Solution, raise_if_failed
from .solvers.base import AbstractSolver

__all__ = ["solve"]

_DEFAULT_ADAPTIVE_MAX_STEPS = 4096
# Fixed-step runs of at least this many steps squared (256) are checkpointed in
# blocks for reverse mode (`_solve_fixed`).
_CHECKPOINT_BLOCK_MIN = 16


def solve(
    problem: AbstractProblem,
    solver: AbstractSolver,
    t1: ArrayLike,
    *,
    t0: ArrayLike = 0.0,
    dt: ArrayLike | None = None,
    saveat: SaveAt | None = None,
    max_steps: int | None = None,
    rtol: ArrayLike | None = None,
    atol: ArrayLike | None = None,
    dt0: ArrayLike | None = None,
    controller: Controller | None = None,
    throw: bool = True,
    adjoint: AbstractAdjoint | None = None,
    estimate_error: bool = False,
    target_error: ArrayLike | None = None,
) -> Solution:
    """Integrate ``problem`` from ``t0`` to ``t1`` (s) with ``solver``.

    Fixed steps (``dt=``): ``ceil((t1 - t0)/dt)`` steps through `lax.scan`, the
    last one shortened to end exactly at ``t1``.  When ``t0``, ``t1`` or ``dt``
    is traced (for example a swept ``dt`` under `vmap`), the step count
    cannot be read and ``max_steps`` (a Python int) must give it; steps past
    ``t1`` are exact no-ops, and falling short of ``t1`` is reported as
    `RESULTS.max_steps_reached`.

    Adaptive steps (``rtol=``/``atol=`` or ``controller=``, with an embedded
    pair such as `RKF45`, `DP54` or `DOP853`): a while loop with the error
    measured in the Lie algebra (see `lierk.controller`).  ``max_steps``
    (default 4096) bounds accepted plus rejected steps.  ``dt0`` is the first
    step; by default it is chosen automatically (Hairer-Norsett-Wanner).
    ``rtol``/``atol`` are local tolerances: the global error is within 1 to
    10x of them on near-axis bodies over 10 s (the calibration), but up to
    ~1e4x on fast bodies or long horizons
    (``benchmarks/results/tolerance_scope.md``); ``target_error`` asks for a
    global error.  Below 50 eps the local error test is floored.

    Global error (``estimate_error=True``): a second solve at a finer setting
    (``2 dt/3``, or ``dt/2`` when saving every odd k-th step; tolerances
    divided by 10) fills `Solution.error_estimate` with
    ``||R - R_fine|| K/(K-1)`` at each saved time, where ``K`` is the expected
    accuracy ratio (``(dt/dt_fine)^order``, or 10).  This is Richardson's
    estimate: it needs only that the finer solve is the more accurate one, so
    it holds near the intermediate axis, with effects, and in float32.  It
    costs about 2.5x a fixed-step solve (3x with an odd save interval) and
    2.2 to 2.6x an adaptive one (``benchmarks/results/error_estimate.md``).
    It is not differentiated.

    Accuracy on request (``target_error=eps``, instead of ``dt``/``rtol``):
    chooses the step (fixed-step solvers) or the tolerances (adaptive) per
    batch member, with traced settings so nothing recompiles, until the
    estimated attitude error is at most ``eps`` at every saved time.  Each
    round solves a pair (a setting and its finer twin) and returns the finer
    solution; an estimate within 1e4 eps of rounding is checked by one more
    solve (a 2x looser twin: where rounding dominates, their gap is about
    the error), so in float32 success means the error is within 2x of
    ``eps``.  ``stats["num_solves"]`` counts the pair solves and
    ``stats["dt"]``/``stats["rtol"]`` give the setting chosen.  A target that
    cannot be met within the rounds (below rounding, or needing more than
    ``max_steps``, default 100000 per solve) ends with
    `RESULTS.target_error_not_reached`.  Not differentiable: to
    differentiate, solve again at the chosen setting.

    Args:
        problem: e.g. `FreeRigidBody`.
        solver: e.g. `RKMK4()` or `DP54()`.
        t1: final time (s), ``>= t0``.
        t0: initial time (s).
        dt: fixed step size (s), ``> 0``.
        saveat: what to return; default `SaveAt(t1=True)`.
        max_steps: static bound on the number of steps.
        rtol: relative tolerance of the default `Controller`.  Dimensionless:
            the attitude in radians, the momentum relative to its size.
        atol: absolute tolerance (defaults to ``rtol``); the momentum's is
            scaled by the problem's reference momentum.
        dt0: initial step of an adaptive solve (s).
        controller: full control of step-size selection.
        throw: raise on failure (default).  With ``throw=False`` the partial
            `Solution` comes back with its `Solution.result` code, per batch
            member under `vmap`.
        adjoint: how an adaptive solve is differentiated (`lierk.adjoint`).
        estimate_error: fill `Solution.error_estimate`.
        target_error: the attitude error wanted at every saved time
            (Frobenius norm, dimensionless), ``> 0``.

    Returns:
        A `Solution`.

    Raises:
        ValueError: bad structure or values known while tracing.  Traced
            values that are bad raise at run time (`eqx.error_if`).
    """
    if not isinstance(problem, AbstractProblem):
        raise ValueError(f"problem must be a lierk problem such as FreeRigidBody, got {type(problem).__name__}")
    if not isinstance(solver, AbstractSolver):
        raise ValueError(f"solver must be a lierk solver such as RKMK4(), got {solver!r}")
    saveat = SaveAt(t1=True) if saveat is None else saveat
    if not isinstance(saveat, SaveAt):
        raise ValueError(f"saveat must be a lierk.SaveAt, got {saveat!r}")
    # (A bool is an int to Python: max_steps=True would run one step.)
    if max_steps is not None and not (
        isinstance(max_steps, (int, np.integer)) and not isinstance(max_steps, bool) and max_steps >= 1
    ):
        raise ValueError(f"max_steps must be a positive Python int, got {max_steps!r}")
    if not isinstance(estimate_error, bool):
        raise ValueError(f"estimate_error must be True or False, got {estimate_error!r}")
    dtype = problem.R0.dtype
    t0_given, t1_given = t0, t1
    t0 = _scalar(t0, "t0", dtype)
    t1 = _scalar(t1, "t1", dtype)
    if not _checks.is_traced(t0_given, t1_given) and float(t1_given) > float(t0_given) and float(t1) <= float(t0):
        raise ValueError(
            f"t1 = {float(t1_given)!r} rounds to t0 = {float(t0)!r} in {np.dtype(dtype).name}: the interval is below "
            "the resolution of the time axis; shift t0 towards 0 or use float64"
        )
    t1 = _checks.check(t1, lambda x: x >= t0, f"t1 must be >= t0 = {t0 if not _checks.is_traced(t0) else 't0'}, got t1 = {{value}}")
    if saveat.ts is not None:
        ts = _checks.asarray(saveat.ts, dtype, "SaveAt(ts=...)")
        if np.shape(ts)[0] == 0:
            raise ValueError("SaveAt(ts=...) is empty: give at least one time, or save t0/t1 instead")
        ts = _checks.check(
            ts,
            lambda x: (x >= t0).all() & (x <= t1).all() & (x[1:] >= x[:-1]).all(),
            "SaveAt(ts=...) must be non-decreasing and lie in [t0, t1], got {value}",
        )
        # The solve must use the checked array, or a traced check is dead code.
        saveat = eqx.tree_at(lambda s: s.ts, saveat, jnp.asarray(ts))

    if target_error is not None:
        given = [n for n, v in (("dt", dt), ("rtol", rtol), ("atol", atol), ("controller", controller)) if v is not None]
        if given:
            raise ValueError(f"target_error= chooses the step or the tolerances itself, so {', '.join(given)} cannot be given too")
        if saveat.steps is not False:
            raise ValueError("target_error= saves at SaveAt(t0/t1/ts=...): the steps differ per setting, so SaveAt(steps=...) cannot be used")
        eps = _checks.check(
            _scalar(target_error, "target_error", dtype), lambda x: x > 0, "target_error must be > 0, got {value}"
        )
        sol = _solve_to_target(problem, solver, t0, t1, saveat, eps, max_steps or _DEFAULT_TARGET_MAX_STEPS, adjoint)
        return _finish(problem, sol, throw)

    if dt is not None:
        given = [n for n, v in (("rtol", rtol), ("atol", atol), ("dt0", dt0), ("controller", controller)) if v is not None]
        if given:
            raise ValueError(f"dt= asks for fixed steps, so {', '.join(given)} would be ignored; pass one or the other")
        if saveat.ts is not None:
            raise ValueError("SaveAt(ts=...) needs an adaptive solve; with fixed steps use SaveAt(steps=k)")
        dt = _scalar(dt, "dt", dtype)
        dt = _checks.check(dt, lambda x: x > 0, "dt must be > 0, got {value}")
        if not _checks.is_traced(t0, t1, dt) and dt <= np.finfo(dt.dtype).eps * max(abs(t0), abs(t1)):
            # The step itself would still be integrated exactly dt long, but
            # the times t0 + k dt, which time-dependent effects read and the
            # solution reports, could not move forward.
            raise ValueError(
                f"dt = {float(dt)!r} is below the resolution of {np.dtype(dt.dtype).name} times near "
                f"t = {float(max(abs(t0), abs(t1)))!r} (one ulp is about {float(np.spacing(max(abs(t0), abs(t1))))!r}): "
                "measure time from a closer origin (t0 = 0) or use float64"
            )
        n = num_steps(t0, t1, dt, max_steps)
        if saveat.steps and not (saveat.t0 or saveat.t1) and n // saveat.every == 0:
            raise ValueError(
                f"SaveAt(steps={saveat.steps}) saves nothing: this run takes {n} steps; "
                "save t1 too (SaveAt(steps=..., t1=True)) or save more often"
            )
        sol = _solve_fixed(problem, solver, t0, t1, dt, saveat, n)
        if estimate_error:
            # The finer solve takes 3 steps for every 2 (cost 1.5x), or 2 for
            # 1 when an odd save interval leaves no other common grid.
            num, den = (2, 1) if saveat.steps and saveat.every % 2 else (3, 2)
            fine_saveat = SaveAt(t0=saveat.t0, t1=saveat.t1, steps=saveat.every * num // den if saveat.steps else False)
            fine_dt = jax.lax.stop_gradient(dt) * den / num
            fine = _solve_fixed(_frozen(problem), solver, t0, t1, fine_dt, fine_saveat, -(-n * num // den))
            sol = _with_estimate(sol, fine, (num / den) ** solver.order)
        return _finish(problem, sol, throw)

    if not solver.adaptive:
        raise ValueError(
            f"{solver.name} has no error estimate, so it needs a fixed step: pass dt=, or target_error=. "
            "Adaptive solvers: RKF45(), DP54(), DOP853()."
        )
    if controller is None:
        if rtol is None:
            raise ValueError(
                f"adaptive {solver.name} needs rtol= (and atol=), or controller=, or target_error=; or pass dt= for fixed steps"
            )
        controller = Controller(rtol, rtol if atol is None else atol)
    elif rtol is not None or atol is not None:
        raise ValueError("pass tolerances either as rtol=/atol= or inside controller=, not both")
    if saveat.steps is not False and saveat.steps is not True:
        raise ValueError(f"adaptive solves save every accepted step (SaveAt(steps=True)), not every {saveat.steps}-th")
    if saveat.steps and saveat.ts is not None:
        raise ValueError("SaveAt(steps=True) and SaveAt(ts=...) cannot be combined in one adaptive solve")
    if saveat.steps and estimate_error:
        raise ValueError(
            "estimate_error=True compares with a finer solve at the same saved times, and adaptive "
            "SaveAt(steps=True) saves different times in each: use SaveAt(ts=...)"
        )
    eps = float(jnp.finfo(dtype).eps)
    if not _checks.is_traced(controller.rtol, controller.atol) and float(controller.rtol + controller.atol) < eps:
        raise ValueError(
            f"rtol + atol = {float(controller.rtol + controller.atol):g} is below the rounding of "
            f"{np.dtype(dtype).name} (eps = {eps:.2g}): no solve can meet it; ask for at least {eps:.2g}"
        )
    adjoint = RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    if not isinstance(adjoint, AbstractAdjoint):
        raise ValueError(f"adjoint must be a lierk.adjoint object, got {adjoint!r}")
    if dt0 is not None:
        dt0 = _checks.check(_scalar(dt0, "dt0", dtype), lambda x: x > 0, "dt0 must be > 0, got {value}")
    max_steps = max_steps or _DEFAULT_ADAPTIVE_MAX_STEPS
    try:
        sol = _solve_adaptive(problem, solver, t0, t1, dt0, saveat, max_steps, controller, adjoint)
    except TypeError as e:
        if "custom_vjp" not in str(e):
            raise
        raise ValueError(
            f"forward-mode autodiff (jax.jvp, jax.jacfwd) cannot go through an adaptive solve with "
            f"{type(adjoint).__name__}, which supports reverse mode only: pass adjoint=lierk.ForwardMode() "
            "(forward only) or adjoint=lierk.DirectAdjoint() (both)"
        ) from None
    if estimate_error:
        fine = _solve_adaptive(
            _frozen(problem), solver, t0, t1, None, saveat, 2 * max_steps, _finer(controller), adjoint, _DIAGNOSTIC_FLOOR_EPS
        )
        sol = _with_estimate(sol, fine, _TOLERANCE_RATIO)
    return _finish(problem, sol, throw)


# The finer solve of an adaptive error estimate divides both tolerances by
# this; the calibrated pairs' global error is proportional to the tolerance
# (tests/test_accuracy.py), so the finer solution is about this much better.
_TOLERANCE_RATIO = 10.0
_DEFAULT_TARGET_MAX_STEPS = 100_000
_TARGET_ROUNDS = 6
# `target_error` checks an estimate below this many eps against rounding.
_ROUNDING_CHECK = 1e4
# The local-error floor (in eps) of the solves behind error estimates.
_DIAGNOSTIC_FLOOR_EPS = 5.0


def _frozen(tree):
    """A pytree (a problem, a controller, times) with its array leaves out of
    the gradient: the estimate's finer solve is a diagnostic and would double
    the cost of a backward pass, and DirectAdjoint's deciding solve is not
    differentiated at all."""
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree)


def _finer(controller: Controller) -> Controller:
    return eqx.tree_at(
        lambda c: (c.rtol, c.atol), controller, (controller.rtol / _TOLERANCE_RATIO, controller.atol / _TOLERANCE_RATIO)
    )


def _attitude_gap(sol: Solution, fine: Solution) -> Array:
    """``||R - R_fine||_F`` at each saved time, ``inf`` where the finer solve failed."""
    gap = jnp.linalg.norm(jax.lax.stop_gradient(sol.R) - fine.R, axis=(-2, -1))
    # Padding entries (save times past a failed solve's end) are NaN in both.
    gap = jnp.where(jnp.isnan(gap) & jnp.isnan(sol.R[..., 0, 0]), 0.0, gap)
    return jnp.where(fine.result == RESULTS.successful, gap, jnp.inf)


def _with_estimate(sol: Solution, fine: Solution, ratio) -> Solution:
    """``sol`` with Richardson's estimate from a solve ``ratio`` times more accurate."""
    est = _attitude_gap(sol, fine) * (ratio / (ratio - 1.0))
    return eqx.tree_at(lambda s: s.error_estimate, sol, est, is_leaf=lambda x: x is None)


@eqx.filter_jit
def _solve_to_target(problem, solver, t0, t1, saveat, eps, max_steps: int, adjoint) -> Solution:
    """Rounds of (setting, finer setting) pairs until the finer solution's
    estimated error is at most ``eps``; see `solve`."""
    problem = _frozen(problem)
    dtype = problem.R0.dtype
    adaptive = solver.adaptive
    # The rounds run in a lax.while_loop, which reverse mode cannot enter anyway.
    adjoint = ForwardModeAdjoint() if adjoint is None else adjoint
    if adaptive:
        ratio, power = _TOLERANCE_RATIO, 1.0
        # The calibrated tolerances give errors of 1 to 10 tol, and the finer
        # solve of the pair is 10x better: eps/2 is enough for nearly every
        # member.  Under vmap one member that needs a second round makes the
        # whole batch pay for it, so the first try leans to the safe side.
        s0 = eps / 2
    else:
        ratio, power = 2.0**solver.order, float(solver.order)
        # A coarse first try, cheap next to the rounds that follow: at most
        # a radian per step and an eighth of the interval.
        omega = jnp.linalg.norm(_field_at(problem, t0, problem.R0, problem.y0)[0])
        s0 = jnp.minimum((t1 - t0) / 8, 1.0 / jnp.maximum(omega, 1e-30))
        s0 = jnp.where(s0 > 0, s0, 1.0)
        if saveat.ts is not None:
            # Steps end on every save time: a step longer than their spacing
            # would be cut to the same grid in both solves of a pair, whose
            # gap would then say nothing about the error.
            grid = jnp.concatenate([t0[None], jnp.asarray(saveat.ts, dtype), t1[None]])
            gaps = jnp.diff(grid)
            s0 = jnp.minimum(s0, jnp.min(jnp.where(gaps > 0, gaps, jnp.inf)))

    def pair(s):
        # (first step, controller) of the setting and of its finer twin; a
        # fixed step is dt0 with no controller.
        if adaptive:
            c = Controller(s, s)
            twins = ((None, c), (None, _finer(c)))
        else:
            twins = ((s, None), (s / 2, None))
        coarse, fine = (
            _solve_adaptive(problem, solver, t0, t1, h, saveat, max_steps, c, adjoint, _DIAGNOSTIC_FLOOR_EPS) for h, c in twins
        )
        gap = _attitude_gap(coarse, fine)
        ok = (coarse.result == RESULTS.successful) & (fine.result == RESULTS.successful)
        # The finer solution's estimate: the gap is (ratio - 1) of its error.
        est = gap / (ratio - 1.0)
        return fine, jnp.where(ok, jnp.max(est), jnp.inf), est

    sol0, worst0, est0 = pair(s0)

    def cond(c):
        k, s, sol, worst, est = c
        return (worst > eps) & (k < _TARGET_ROUNDS) & (s > 0)

    def body(c):
        k, s, sol, worst, est = c
        # Aim at a fifth of eps (a round missed by one member costs the whole
        # batch under vmap); from a failed or saturated solve, tighten 100x.
        ratio_s = jnp.where(jnp.isfinite(worst) & (worst > 0), (eps / 5 / worst) ** (1.0 / power), 0.01)
        s_new = s * jnp.clip(ratio_s, 1e-3, 1.0)
        if not adaptive:
            # Stay within max_steps: the finer solve takes twice the steps.
            s_new = jnp.maximum(s_new, 2.5 * (t1 - t0) / max_steps)
        else:
            s_new = jnp.maximum(s_new, 4 * jnp.finfo(dtype).eps)
        sol, worst, est = pair(s_new)
        # No finer setting left (max_steps or rounding): stop, flagged by s = -s.
        return k + 1, jnp.where(s_new < s, s_new, -s_new), sol, worst, est

    k, s, sol, worst, est = jax.lax.while_loop(cond, body, (jnp.asarray(1), s0, sol0, worst0, est0))

    # Near rounding, Richardson's premise (the finer solve is `ratio` times
    # better) fails: both solutions carry rounding errors of about the same
    # size, amplified by the flow (float32 free bodies: 10 to 100 eps after a
    # dozen steps), and gap/(ratio - 1) understated them 10 to 40x.  A twin of
    # the finer setting, 2x less accurate by the error model, tells: where
    # truncation dominates their gap is about the finer solution's error,
    # and where rounding does, too (their rounding errors are independent).
    # So the larger of twice the gap (two random errors can nearly cancel:
    # the gap alone was 4x low in one of 48 float32 cases) and Richardson's
    # estimate holds in both regimes.  The twin runs only within reach of
    # rounding (an estimate below 1e4 eps: always in float32 at useful
    # targets, in float64 below ~2e-12); under vmap a member that needs it
    # makes the batch pay for it.
    def rounding_checked(est):
        s_fine = jnp.abs(s) / (ratio if adaptive else 2.0)
        if adaptive:
            h, c = None, Controller(2 * s_fine, 2 * s_fine)
        else:
            h, c = s_fine * 2.0 ** (1.0 / power), None
        twin = _solve_adaptive(problem, solver, t0, t1, h, saveat, max_steps, c, adjoint, _DIAGNOSTIC_FLOOR_EPS)
        return jnp.maximum(est, 2.0 * _attitude_gap(sol, twin))

    near_rounding = jnp.isfinite(worst) & (worst < _ROUNDING_CHECK * jnp.finfo(dtype).eps)
    est = jax.lax.cond(near_rounding, rounding_checked, lambda e: e, est)
    worst = jnp.where(near_rounding, jnp.max(est), worst)
    result = jnp.where(
        sol.result != RESULTS.successful,
        sol.result,
        jnp.where(worst <= eps, RESULTS.successful, RESULTS.target_error_not_reached),
    ).astype(jnp.int32)
    stats = dict(sol.stats)
    stats["num_solves"] = 2 * k
    s = jnp.abs(s)
    stats["rtol" if adaptive else "dt"] = s / ratio if adaptive else s / 2
    return eqx.tree_at(
        lambda x: (x.result, x.stats, x.error_estimate), sol, (result, stats, est), is_leaf=lambda x: x is None
    )


# A conserved quantity that moves by more than this (relative to its scale)
# marks a run as under-resolved or unstable: RESULTS.invariant_drift.
_DRIFT_LIMIT = 0.1


def _finish(problem, sol: Solution, throw: bool) -> Solution:
    """What every solve ends with: the drift check, then `throw`."""
    return raise_if_failed(_flag_drift(problem, sol), throw)


def _flag_drift(problem, sol: Solution) -> Solution:
    keys = problem.conserved()
    if not keys:
        return sol
    q0 = problem.invariants(problem.R0, problem.y0)
    q = problem.invariants(sol.R, sol.y)
    scales = problem.invariant_scales()
    worst = jnp.zeros((), sol.R.dtype)
    for k in keys:
        d = jnp.abs(q[k] - q0[k]) / jnp.where(scales[k] > 0, scales[k], 1.0)
        # Padding rows are NaN; a non-finite run has its own code.
        worst = jnp.maximum(worst, jnp.max(jnp.where(jnp.isfinite(d), d, 0.0)))
    drifted = (sol.result == RESULTS.successful) & (worst > _DRIFT_LIMIT)
    result = jnp.where(drifted, RESULTS.invariant_drift, sol.result).astype(sol.result.dtype)
    return eqx.tree_at(lambda s: s.result, sol, result)


def _scalar(x, name, dtype) -> Array:
    if np.ndim(x) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {np.shape(x)}")
    x = _checks.asarray(x, dtype, name)
    return _checks.check(x, lambda v: (v == v) & (abs(v) < float("inf")), f"{name} must be finite, got {{value}}")


def num_steps(t0, t1, dt, max_steps=None) -> int:
    """Number of fixed steps `solve` takes from ``t0`` to ``t1`` with step ``dt``:
    ``max_steps`` if given, else ``ceil((t1 - t0)/dt)`` (a multiple of ``dt`` up
    to rounding counts exactly).  Needs concrete values."""
    if max_steps is not None:
        return int(max_steps)
    if _checks.is_traced(t0, t1, dt):
        raise ValueError(
            "t0, t1 or dt is traced (under jit/vmap), so the number of steps cannot be read from them: "
            "pass max_steps=N, a Python int with N * dt >= t1 - t0"
        )
    dtype = np.result_type(np.asarray(t0), np.asarray(t1), np.asarray(dt), np.float32)
    return int(_step_count(*(np.asarray(v, dtype) for v in (t0, t1, dt)), np))


def _step_count(t0, t1, dt, xp):
    """``ceil((t1 - t0)/dt)`` in the inputs' dtype, with NumPy or jax.numpy
    (``xp``), so that the host's count and the compiled loop's agree.

    A quotient within rounding of a whole number counts as that number: a t1
    that is a multiple of dt up to rounding gets exactly that many steps, not
    one more of length ~1e-16.  "Rounding" is that of the quotient and of the
    times themselves (``eps |t| / dt`` steps), but never more than half a
    step: far from t = 0 in float32 the times resolve only a few ulps per
    step, and a looser snap would merge many steps into the last one.  The
    fixed-step loop ends the run with a step of the remaining length (between
    0.5 and 1.5 dt when snapped), so the steps always add up to t1 - t0.
    """
    x = (t1 - t0) / dt
    eps = float(np.finfo(dt.dtype).eps)
    tol = xp.minimum(xp.maximum(1e-9 * xp.minimum(1.0, x), 16 * eps * (x + xp.maximum(xp.abs(t0), xp.abs(t1)) / dt)), 0.5)
    r = xp.round(x)
    n = xp.where(xp.abs(x - r) <= tol, r, xp.ceil(x))
    # A step longer than the interval is one step, shortened to end at t1.
    return xp.where(t1 > t0, xp.maximum(n, 1.0), 0.0)


def _stack(parts: list) -> Any:
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *parts)


def _finite(tree) -> Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]))


# Both loops are compiled once per problem/solver/SaveAt structure and step
# count, like diffrax's diffeqsolve: values (t0, t1, dt, tolerances, inertia,
# omega0) are traced, so eager calls with new values reuse the compilation.
@eqx.filter_jit
def _solve_fixed(problem, solver, t0, t1, dt, saveat: SaveAt, n: int) -> Solution:
    # `count` steps reach t1 (the host's `num_steps` when it chose n; fewer
    # when max_steps set n).  Every step but the last is exactly dt, and the
    # last is what remains of t1 - t0: step sizes are not differences of the
    # times t0 + k dt, which far from t = 0 are rounded to the ulp of t (in
    # float32 at t = 1e5, 0.008 s).  The times themselves only tell
    # time-dependent effects where they are.
    needed = _step_count(t0, t1, dt, jnp)
    count = jnp.minimum(needed, n).astype(jnp.asarray(0).dtype)
    # (A run cut short by max_steps ends with a step of dt like the others.)
    last = jnp.where(needed <= n, (t1 - t0) - (count - 1).astype(dt.dtype) * dt, dt)

    def time(k):
        return jnp.where(k >= count, t1, t0 + k.astype(dt.dtype) * dt)

    def size(k):
        return jnp.where(k + 1 < count, dt, jnp.where(k + 1 == count, last, jnp.zeros_like(dt)))

    # The step index and the count of steps taken ride in the loop's carry:
    # scanning over an array of indices (or of step times) would allocate a
    # buffer of the step count, 8 bytes a step, whatever is saved.
    def one(carry, _):
        (R, y), k, taken = carry
        # Past t1, h = 0 and every solver's step is exactly the identity.
        st = solver.step(problem, time(k), size(k), R, y)
        return ((st.R, st.y), k + 1, taken + (k < count).astype(taken.dtype)), None

    # In reverse mode each step keeps only its starting state and is
    # recomputed in the backward pass: saved as they fall out of the step's
    # fused arithmetic, its residuals were about a hundred small arrays, each
    # written by a kernel of its own (the gradient cost 60 forward steps per
    # step).  Outside reverse mode the checkpoint does nothing.
    step = jax.checkpoint(one, prevent_cse=False)

    def scan(carry, length):
        return jax.lax.scan(step, carry, None, length=length)[0]

    def steps(carry, length):
        # Reverse mode through a plain scan keeps every step's residuals:
        # 10^6 steps would hold gigabytes.  Blocks of about sqrt(length)
        # steps, each recomputed from its start in the backward pass, hold
        # O(sqrt(length)) instead, for one more forward pass.  Without reverse
        # mode the checkpoint does nothing.
        block = math.isqrt(length)
        if block < _CHECKPOINT_BLOCK_MIN:
            return scan(carry, length)
        blocks, rem = divmod(length, block)
        body = jax.checkpoint(lambda c, _: (scan(c, block), None), prevent_cse=False)
        carry = jax.lax.scan(body, carry, None, length=blocks)[0]
        return scan(carry, rem) if rem else carry

    state = (problem.R0, problem.y0)
    ts, states = [], []
    if saveat.t0:
        ts.append(t0[None])
        states.append(jax.tree_util.tree_map(lambda x: x[None], state))
    every = saveat.every
    n_chunks, rem = divmod(n, every) if every else (0, n)

    def chunk(carry, _):
        carry = steps(carry, every)
        return carry, carry[0]

    carry = (state, jnp.asarray(0), jnp.asarray(0))
    if n_chunks:
        carry, saved = jax.lax.scan(chunk, carry, None, length=n_chunks)
        ts.append(time((jnp.arange(n_chunks) + 1) * every))
        states.append(saved)
    if rem:
        carry = steps(carry, rem)
    state, _, taken = carry
    if saveat.t1 and (rem or not n_chunks):
        ts.append(time(jnp.asarray(n))[None])
        states.append(jax.tree_util.tree_map(lambda x: x[None], state))
    R, y = _stack(states)
    result = jnp.where(needed <= n, RESULTS.successful, RESULTS.max_steps_reached)
    result = jnp.where(_finite(state), result, RESULTS.nonfinite)
    stats = {
        "num_steps": taken,
        "num_accepted_steps": taken,
        "num_rejected_steps": jnp.zeros_like(taken),
        "num_fevals": taken * solver.stages,
    }
    return Solution(jnp.concatenate(ts), R, y, jnp.asarray(sum(len(t) for t in ts)), stats, result)


class _Carry(NamedTuple):
    t: Array
    h: Array
    R: Array
    y: Any
    f: Any  # (omega, dy/dt) at (t, R, y): the next step's first stage
    num_steps: Array
    num_accepted: Array
    num_rejected: Array
    rejected_last: Array
    done: Array
    result: Array
    save_index: Array
    saved: Any  # (ts, R, y) buffers, or None
    decisions: Any  # per-attempt record for reverse-mode replay (see _solve_adaptive), or None


def _field_at(problem, t, R, y):
    return problem.at(problem.base(t, R, y), t, y)


def _initial_step(problem, controller: Controller, q: int, t0, t1, R0, y0, f0):
    """Hairer-Norsett-Wanner's starting step (II.4), in the algebra about ``R0``."""
    omega0, ydot0 = f0
    sg = jax.lax.stop_gradient
    tol = problem.error_tolerance(y0, y0, controller.rtol, controller.atol)
    # The attitude's size is 1 (entries of R are O(1)); y's is its own.
    d0 = sg(controller.norm(jnp.ones_like(omega0), y0, tol))
    d1 = sg(controller.norm(omega0, ydot0, tol))
    big = (d0 > 1e-5) & (d1 > 1e-5)
    h0 = jnp.where(big, 0.01 * d0 / jnp.where(big, d1, 1.0), 1e-6)
    y1 = jax.tree_util.tree_map(lambda a, b: a + h0 * b, y0, ydot0)
    omega1, ydot1 = problem.local(problem.base(t0, R0, y0), t0 + h0, h0 * omega0, y1)
    d2 = sg(
        controller.norm(omega1 - omega0, jax.tree_util.tree_map(lambda a, b: a - b, ydot1, ydot0), tol) / h0
    )
    dmax = jnp.maximum(d1, d2)
    safe = jnp.where(dmax > 0, dmax, 1.0)
    h1 = jnp.where(dmax > 1e-15, (0.01 / safe) ** (1.0 / (q + 1)), jnp.maximum(1e-6, h0 * 1e-3))
    # A field that is exactly zero (omega0 = 0 and no forcing) is solved by any
    # step: take the whole interval.
    span = t1 - t0
    h = jnp.where(dmax == 0, span, jnp.minimum(100 * h0, h1))
    return sg(jnp.clip(h, 0, controller.largest_step(omega0)))


@eqx.filter_jit
def _solve_adaptive(
    problem, solver, t0, t1, dt0, saveat: SaveAt, max_steps: int, controller: Controller | None, adjoint, floor_eps: float = 50.0
):
    replay = None
    if controller is not None and adjoint.kind == "bounded":
        # DirectAdjoint's scans rematerialise steps from carries, and a step
        # recomputed in a differently compiled body can decide differently
        # (see `_adaptive_loop`): its jacrev was 4e-9 off at rtol 1e-11 and
        # changed with max_steps.  So an undifferentiated solve takes the
        # decisions first (one more forward solve), and the differentiated
        # loop only replays them: every pass of it takes the same steps.
        _, replay = _adaptive_loop(
            _frozen(problem), solver, _frozen(t0), _frozen(t1), _frozen(dt0), saveat, max_steps, _frozen(controller),
            ForwardModeAdjoint(), floor_eps, record=True,
        )
    return _adaptive_loop(problem, solver, t0, t1, dt0, saveat, max_steps, controller, adjoint, floor_eps, replay=replay)[0]


def _adaptive_loop(
    problem, solver, t0, t1, dt0, saveat: SaveAt, max_steps: int, controller: Controller | None, adjoint,
    floor_eps: float, record: bool = False, replay: Array | None = None,
) -> tuple[Solution, Array | None]:
    """The adaptive (or, ``controller=None``, variable-count fixed-step) loop:
    ``(Solution, decisions)``.  ``decisions`` ``(max_steps,)`` holds each
    attempt's next step, negative if the attempt was rejected (NaN after the
    last attempt), when they are recorded: always with the checkpointed
    adjoint, and when ``record``.  ``replay`` (decisions recorded by an
    earlier solve of the same problem) makes the loop take those decisions
    instead of its own."""
    # controller=None: fixed steps of dt0 in this loop, whose trip count may
    # differ per batch member (a traced step size needs no static step count).
    fixed = controller is None
    tab_q = None if fixed else solver.error_order
    if not fixed:
        # Tolerances given as Python floats become float64 under x64: every
        # controller (given, or built by a target_error round) computes in the
        # problem's dtype.
        controller = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype=problem.R0.dtype), controller)
        # The estimate is held to tol * tolerance_calibration, but never below
        # 50 eps: under that, rounding noise decides acceptance.  Such steps
        # only add rounding error, and a reverse-mode pass that recomputes them
        # from checkpoints could decide differently from the forward pass, so
        # the gradient would depend on max_steps.
        # (The finer solves behind error estimates, which are not
        # differentiated, use a floor of `_DIAGNOSTIC_FLOOR_EPS` instead: at
        # 50 eps both solves of a pair were the same solve in float32 below
        # rtol ~1e-5, and their gap said nothing.)
        floor = floor_eps * jnp.finfo(problem.R0.dtype).eps / (controller.rtol + controller.atol)
        calibration = jax.lax.stop_gradient(jnp.maximum(solver.tableau.tolerance_calibration, floor))
    R0, y0 = problem.R0, problem.y0
    f0 = None if fixed else _field_at(problem, t0, R0, y0)
    if dt0 is None:
        h0 = _initial_step(problem, controller, tab_q, t0, t1, R0, y0, f0)
    elif fixed:
        h0 = dt0
    else:
        # A given first step obeys the controller's bounds like every other.
        h0 = jnp.minimum(dt0, controller.largest_step(f0[0]))
    dtype = R0.dtype
    eps = jnp.finfo(dtype).eps
    izero = jnp.asarray(0, dtype=jnp.int32)

    ts_req = None if saveat.ts is None else jnp.asarray(saveat.ts, dtype=dtype)
    if saveat.steps:
        saved = (
            jnp.full((max_steps,), jnp.inf, dtype),
            jnp.full((max_steps, 3, 3), jnp.nan, dtype),
            jax.tree_util.tree_map(lambda x: jnp.full((max_steps,) + x.shape, jnp.nan, x.dtype), y0),
        )
    elif ts_req is not None:
        at_start = (ts_req <= t0)
        saved = (
            ts_req,
            jnp.where(at_start[:, None, None], R0, jnp.nan),
            jax.tree_util.tree_map(lambda x: jnp.where(at_start.reshape((-1,) + (1,) * x.ndim), x, jnp.nan), y0),
        )
    else:
        saved = None

    # Reverse mode through the checkpointed loop recomputes the steps between
    # checkpoints inside `jax.vjp`, a differently compiled body.  The error
    # estimate, a sum of stage slopes that nearly cancels, then comes out
    # different from bit-identical inputs (by up to 1.3e-7 relative at rtol
    # 1e-11), and so does every step size after it: the recomputed steps
    # drifted by up to 6e-9 s (rtol 1e-11) and 2e-7 s (1e-13) from the ones
    # taken, and the backward pass chained the Jacobians of steps that were
    # never taken, 2e-9 (1e-7) off the solve's derivative whenever the steps
    # outnumbered the checkpoints (about sqrt(2 max_steps)).  So each
    # attempt's decisions, the next step and (as its sign) whether it was
    # accepted, go into a write-once equinox buffer (NaN: not decided yet),
    # one slot per attempt.  The forward pass reads NaN and decides; the
    # recomputation is handed the filled buffer (`checkpointed_while_loop`
    # gives every replayed body the final buffers) and takes the recorded
    # decisions, so it replays the steps taken.  This reads a slot before the
    # forward pass writes it, outside equinox's documented buffer contract;
    # tests/test_adaptive.py checks the replay.  8 bytes per max_steps, only
    # for this adjoint: ForwardMode recomputes nothing, and DirectAdjoint's
    # rematerialised scans recompute from carries whose buffer is not filled
    # yet, so `_solve_adaptive` records their decisions in a solve of its own
    # and hands them over as ``replay``.
    record = not fixed and replay is None and (record or adjoint.kind == "checkpointed")
    decisions = jnp.full((max_steps,), jnp.nan, dtype) if record else None

    init = _Carry(
        t=t0,
        h=h0,
        R=R0,
        y=y0,
        f=f0,
        num_steps=izero,
        num_accepted=izero,
        num_rejected=izero,
        rejected_last=jnp.asarray(False),
        done=t1 <= t0,
        result=jnp.asarray(RESULTS.successful, jnp.int32),
        save_index=izero,
        saved=saved,
        decisions=decisions,
    )

    def cond(c: _Carry):
        return ~c.done

    def body(c: _Carry) -> _Carry:
        # Steps end exactly on each requested save time, so saved states carry
        # the solver's own accuracy (no interpolation error), then on t1.
        stop = t1 if ts_req is None else jnp.min(jnp.where(ts_req > c.t, ts_req, t1))
        remaining = stop - c.t
        clipped = c.h >= remaining
        last = clipped & (stop >= t1)
        t_new = jnp.where(clipped, stop, c.t + c.h)
        # Step by exactly the time the clock advances: far from t = 0, c.t + h
        # rounds, and a state advanced by h would drift from its time stamp.
        h = jax.lax.stop_gradient(t_new - c.t)
        st = solver.step(problem, c.t, h, c.R, c.y, c.f)
        if fixed:
            f_new = None
            finite = _finite((st.R, st.y))
            # Every fixed step is taken; a non-finite one ends the loop and is reported.
            accept = jnp.asarray(True)
            h_next = c.h
            stuck = h <= 0
        else:
            tol_y = problem.error_tolerance(c.y, st.y, controller.rtol, controller.atol)
            err = controller.norm(st.error[0], st.error[1], tol_y)
            if len(st.error) == 3:
                # DOP853 (Hairer, Norsett, Wanner I, II.10): blend the 5th- and
                # 3rd-order estimates so the norm behaves like O(h^8).
                e3 = controller.norm(st.error[2][0], st.error[2][1], tol_y)
                denom = jnp.sqrt(err * err + 0.01 * e3 * e3)
                blend = jnp.where(denom > 0, err * err / jnp.where(denom > 0, denom, 1.0), 0.0)
                # A rejected stage (inf) must stay inf: inf/inf would be NaN.
                err = jnp.where(jnp.isfinite(err) & jnp.isfinite(e3), blend, jnp.inf)
            err = jax.lax.stop_gradient(err / calibration)
            f_new = st.fsal if st.fsal is not None else _field_at(problem, t_new, st.R, st.y)
            finite = _finite((st.R, st.y, f_new)) & jnp.isfinite(err)
            accept = finite & (err <= 1.0)
            # The turn bound reads omega where the next step starts.
            largest = controller.largest_step(jnp.where(accept, f_new[0], c.f[0]))
            h_next = jnp.minimum(h * controller.factor(err, tab_q, c.rejected_last), largest)
            # Keep the proposed step when only a save time or t1 shortened it.
            h_next = jnp.where(accept & clipped, jnp.maximum(h_next, jnp.minimum(c.h, largest)), h_next)
            h_floor = jnp.maximum(controller.dtmin, 16 * eps * jnp.maximum(jnp.abs(c.t), jnp.abs(t1)))
            # A step that does not move the clock (below its resolution) is stuck too.
            stuck = (~accept & (h_next < h_floor)) | (h <= 0)
        h_out = jax.lax.stop_gradient(jnp.where(stuck, h, h_next))
        decisions = c.decisions
        if record or replay is not None:
            # c.num_steps < max_steps inside the loop: one slot per attempt.
            recorded = (decisions if replay is None else replay)[c.num_steps]
            known = ~jnp.isnan(recorded)
            accept = jnp.where(known, ~jnp.signbit(recorded), accept)
            h_out = jnp.where(known, jnp.abs(recorded), h_out)
        if record:
            decisions = decisions.at[c.num_steps].set(jnp.where(accept, h_out, -h_out))

        def pick(a, b):
            return jax.tree_util.tree_map(lambda x, z: jnp.where(accept, x, z), a, b)

        saved = c.saved
        save_index = c.save_index
        if saveat.steps:
            ts_b, R_b, y_b = saved
            i = jnp.minimum(save_index, max_steps - 1)
            saved = (
                ts_b.at[i].set(jnp.where(accept, t_new, ts_b[i])),
                R_b.at[i].set(jnp.where(accept, st.R, R_b[i])),
                jax.tree_util.tree_map(lambda b, v: b.at[i].set(jnp.where(accept, v, b[i])), y_b, st.y),
            )
            save_index = save_index + accept.astype(jnp.int32)
        elif ts_req is not None:
            ts_b, R_b, y_b = saved
            write = accept & (ts_req == t_new)
            saved = (
                ts_b,
                jnp.where(write[:, None, None], st.R, R_b),
                jax.tree_util.tree_map(lambda b, v: jnp.where(write.reshape((-1,) + (1,) * v.ndim), v, b), y_b, st.y),
            )

        return _Carry(
            t=jnp.where(accept, t_new, c.t),
            h=h_out,
            R=jnp.where(accept, st.R, c.R),
            y=pick(st.y, c.y),
            f=pick(f_new, c.f),
            num_steps=c.num_steps + 1,
            num_accepted=c.num_accepted + accept.astype(jnp.int32),
            num_rejected=c.num_rejected + (~accept).astype(jnp.int32),
            rejected_last=~accept,
            done=(accept & last) | stuck | (fixed & ~finite),
            result=jnp.where(stuck, RESULTS.dt_min_reached, c.result).astype(jnp.int32),
            save_index=save_index,
            saved=saved,
            decisions=decisions,
        )

    final = eqxi.while_loop(
        cond,
        body,
        init,
        max_steps=max_steps,
        kind=adjoint.kind,
        checkpoints=adjoint.checkpoints,
        buffers=(lambda c: c.decisions) if record and adjoint.kind == "checkpointed" else None,
    )
    result = jnp.where(
        final.done & _finite((final.R, final.y)),
        final.result,
        jnp.where(_finite((final.R, final.y)), RESULTS.max_steps_reached, RESULTS.nonfinite),
    ).astype(jnp.int32)
    ts, states = [], []
    if saveat.t0:
        ts.append(t0[None])
        states.append((R0[None], jax.tree_util.tree_map(lambda x: x[None], y0)))
    if saved is not None:
        ts.append(final.saved[0])
        states.append((final.saved[1], final.saved[2]))
    if saveat.t1 and not saveat.steps:
        ts.append(final.t[None])
        states.append((final.R[None], jax.tree_util.tree_map(lambda x: x[None], final.y)))
    R, y = _stack(states)
    n_saved = sum(len(t) for t in ts) - (max_steps - final.save_index if saveat.steps else 0)
    if ts_req is not None:
        n_saved = n_saved - jnp.sum(ts_req > final.t)
    # The first stage is reused from the previous step; the field at the new
    # point is either the FSAL stage or one extra evaluation.
    fevals_per_attempt = solver.stages - (0 if fixed or not solver.tableau.fsal else 1)
    # One evaluation at t0, plus one inside the automatic first-step estimate.
    fevals_setup = 0 if fixed else 1 if dt0 is not None else 2
    stats = {
        "num_steps": final.num_steps,
        "num_accepted_steps": final.num_accepted,
        "num_rejected_steps": final.num_rejected,
        "num_fevals": fevals_setup + final.num_steps * fevals_per_attempt,
    }
    return Solution(jnp.concatenate(ts), R, y, jnp.asarray(n_saved), stats, result), final.decisions
