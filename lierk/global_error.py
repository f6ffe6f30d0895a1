"""Global error: Richardson's estimate (``solve(..., estimate_error=True)``)
and accuracy on request (``solve(..., target_error=eps)``).

Both compare a solve with a finer one: a step ``dt_fine < dt`` (fixed steps)
or tolerances divided by `TOLERANCE_RATIO` (adaptive).  With ``K`` the
expected accuracy ratio of the two, ``||R - R_fine|| K/(K - 1)`` estimates the
error of the solution returned by ``estimate_error=True`` and ``gap/(K - 1)``
that of the finer solution ``target_error`` returns; `lierk.solve` says what
each promises.  Neither is differentiated: the finer solves are diagnostics.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from . import validation
from .adjoint import ForwardMode
from .controller import ConstantStep, Controller
from .loops import frozen, solve_adaptive, solve_fixed
from .solution import RESULTS, SaveAt, Solution
from .solvers.base import field_at

__all__ = ["TOLERANCE_RATIO", "DEFAULT_TARGET_MAX_STEPS", "finer", "estimate_fixed", "estimate_adaptive", "solve_to_target"]

# The finer solve of an adaptive error estimate divides both tolerances by
# this; the calibrated pairs' global error is proportional to the tolerance
# (tests/test_accuracy.py), so the finer solution is about this much better.
TOLERANCE_RATIO = 10.0
DEFAULT_TARGET_MAX_STEPS = 100_000
_TARGET_ROUNDS = 6
# `target_error` checks an estimate below this many eps against rounding.
_ROUNDING_CHECK = 1e4
# The local-error floor (in eps) of the solves behind error estimates.
DIAGNOSTIC_FLOOR_EPS = 5.0


def finer(controller: Controller, order: int) -> Controller:
    """``controller`` with both tolerances divided by `TOLERANCE_RATIO`, and
    its turn bound ``max_angle`` by ``TOLERANCE_RATIO^(1/order)`` (``order``:
    the solver's).  Where the turn bound, not the error test, sets the steps
    (a fast spin, nearly symmetric: the error estimate is small at every
    step), both solves took the same steps and their gap was 0: DOP853 at
    ``target_error=1e-5`` claimed success with an estimate of 1.5e-15 and an
    error of 3.1e-4.  So the finer solve is finer under either bound."""
    scale = TOLERANCE_RATIO ** (-1.0 / order)
    return eqx.tree_at(
        lambda c: (c.rtol, c.atol, c.max_angle),
        controller,
        (controller.rtol / TOLERANCE_RATIO, controller.atol / TOLERANCE_RATIO, controller.max_angle * scale),
    )


def _own_controller(tol: Array) -> Controller:
    """A `Controller` with ``rtol = atol = tol``, a tolerance this module
    computed itself (positive and finite): it is not checked again at run
    time, so the program has no host callback and JAX's persistent cache can
    keep it."""
    with validation.checked_on_host():
        return Controller(tol, tol)


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


def estimate_fixed(sol: Solution, problem, solver, t0, t1, dt, saveat: SaveAt, n: int) -> Solution:
    """``sol`` (``n`` fixed steps of ``dt``) with its estimate from a finer solve."""
    # The finer solve takes 3 steps for every 2 (cost 1.5x), or 2 for 1 when
    # an odd save interval leaves no other common grid.
    num, den = (2, 1) if saveat.steps and saveat.every % 2 else (3, 2)
    fine_saveat = SaveAt(t0=saveat.t0, t1=saveat.t1, steps=saveat.every * num // den if saveat.steps else False)
    fine_dt = jax.lax.stop_gradient(dt) * den / num
    fine = solve_fixed(frozen(problem), solver, t0, t1, fine_dt, fine_saveat, -(-n * num // den))
    return _with_estimate(sol, fine, (num / den) ** solver.order)


def estimate_adaptive(sol: Solution, problem, solver, t0, t1, saveat: SaveAt, max_steps: int, controller, adjoint) -> Solution:
    """``sol`` (an adaptive solve) with its estimate from a solve at tolerances
    divided by `TOLERANCE_RATIO`."""
    fine = solve_adaptive(
        frozen(problem), solver, t0, t1, None, saveat, 2 * max_steps, finer(controller, solver.order), adjoint, DIAGNOSTIC_FLOOR_EPS
    )
    return _with_estimate(sol, fine, TOLERANCE_RATIO)


@eqx.filter_jit
def solve_to_target(problem, solver, t0, t1, saveat, eps, max_steps: int, adjoint) -> Solution:
    """Rounds of (setting, finer setting) pairs until the finer solution's
    estimated error is at most ``eps``; see `solve`."""
    problem = frozen(problem)
    dtype = problem.R0.dtype
    adaptive = solver.adaptive
    # The rounds run in a lax.while_loop, which reverse mode cannot enter anyway.
    adjoint = ForwardMode() if adjoint is None else adjoint
    if adaptive:
        ratio, power = TOLERANCE_RATIO, 1.0
        # The calibrated tolerances give errors of 1 to 10 tol, and the finer
        # solve of the pair is 10x better: eps/2 is enough for nearly every
        # member.  Under vmap one member that needs a second round makes the
        # whole batch pay for it, so the first try leans to the safe side.
        s0 = eps / 2
    else:
        ratio, power = 2.0**solver.order, float(solver.order)
        # A coarse first try, cheap next to the rounds that follow: at most
        # a radian per step and an eighth of the interval.
        omega = jnp.linalg.norm(field_at(problem, t0, problem.R0, problem.y0)[0])
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
        # (first step, controller) of the setting and of its finer twin.
        if adaptive:
            c = _own_controller(s)
            twins = ((None, c), (None, finer(c, solver.order)))
        else:
            twins = ((s, ConstantStep()), (s / 2, ConstantStep()))
        coarse, fine = (
            solve_adaptive(problem, solver, t0, t1, h, saveat, max_steps, c, adjoint, DIAGNOSTIC_FLOOR_EPS) for h, c in twins
        )
        gap = _attitude_gap(coarse, fine)
        ok = (coarse.result == RESULTS.successful) & (fine.result == RESULTS.successful)
        # The finer solution's estimate: the gap is (ratio - 1) of its error.
        est = gap / (ratio - 1.0)
        return fine, jnp.where(ok, jnp.max(est), jnp.inf), est

    sol0, worst0, est0 = pair(s0)

    def out_of_steps(sol):
        # Tighter settings take more steps: a pair that ran out of max_steps
        # cannot be mended by another round.
        return sol.result == RESULTS.max_steps_reached

    def cond(c):
        k, s, sol, worst, est = c
        return (worst > eps) & (k < _TARGET_ROUNDS) & (s > 0) & ~out_of_steps(sol)

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
        new = pair(s_new)
        # Out of steps, the last finished round is the answer (its estimate
        # above eps says it is not reached), not the unfinished solve.
        keep = out_of_steps(new[0]) & jnp.isfinite(worst)
        sol, worst, est = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), (sol, worst, est), new)
        # No finer setting left (max_steps or rounding): stop, flagged by s = -s.
        s_next = jnp.where(keep, -s, jnp.where(s_new < s, s_new, -s_new))
        return k + 1, s_next, sol, worst, est

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
    # rounding: an estimate below 1e4 eps (always in float32 at useful
    # targets, in float64 below ~2e-12; for fixed steps, times the square
    # root of a hundredth of the step count), or, for an adaptive pair, a
    # finer tolerance below 1e4 eps.  The flow amplifies rounding and truncation
    # alike (by |dR(T)/dy0|, 1e3 to 1e4 near the intermediate axis over long
    # horizons), so it is the local accuracy asked of each step that meets
    # rounding, whatever the size of the global error: a T-handle near the
    # axis at T = 200 s claimed 1.8e-11 at a tolerance of 4e-13 and was
    # 1.2e-10 off.  Under vmap a member that needs the twin makes the batch
    # pay for it.
    def rounding_checked(est):
        s_fine = jnp.abs(s) / (ratio if adaptive else 2.0)
        if adaptive:
            h, c = None, _own_controller(2 * s_fine)
        else:
            h, c = s_fine * 2.0 ** (1.0 / power), ConstantStep()
        twin = solve_adaptive(problem, solver, t0, t1, h, saveat, max_steps, c, adjoint, DIAGNOSTIC_FLOOR_EPS)
        return jnp.maximum(est, 2.0 * _attitude_gap(sol, twin))

    near_eps = _ROUNDING_CHECK * jnp.finfo(dtype).eps
    if adaptive:
        near_rounding = (worst < near_eps) | (jnp.abs(s) / ratio < near_eps)
    else:
        # Rounding grows like the square root of the step count (a random
        # walk): RKMK4 on that T-handle, 1.1e5 steps of 1.8 ms, claimed 1e-11
        # at target 1e-10 and was 2.7e-10 off.
        steps = (t1 - t0) / (jnp.abs(s) / 2.0)
        near_rounding = worst < near_eps * jnp.sqrt(jnp.maximum(steps / 100.0, 1.0))
    near_rounding = jnp.isfinite(worst) & near_rounding
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
