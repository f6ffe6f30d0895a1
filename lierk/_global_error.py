"""Global error: Richardson's estimate (``solve(..., estimate_error=True)``)
and accuracy on request (``solve(..., target_error=eps)``).

Both compare a solve with a finer one: a step ``dt_fine < dt`` (fixed steps)
or tighter tolerances (adaptive).  With ``K`` the expected accuracy ratio of
the two, ``||R - R_fine|| K/(K - 1)`` estimates the error of the coarser
solution (``estimate_error=True``); ``target_error`` returns the coarser
solution of its confirming pair with twice their gap, an upper bound whenever
the finer solve is at least twice as accurate (when it gives up, the finer
solution of its best pair, with the same bound).  `lierk.solve` says what
each promises.  Neither is differentiated: the finer solves are diagnostics.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import _validation as validation
from ._adjoint import ForwardMode
from ._controller import ConstantStep, Controller
from ._loops import _batched_together, frozen, solve_adaptive, solve_fixed, solve_fixed_at
from ._solution import RESULTS, SaveAt, Solution
from ._solvers.base import field_at

__all__ = [
    "TOLERANCE_RATIO",
    "DEFAULT_ADAPTIVE_MAX_STEPS",
    "DEFAULT_TARGET_MAX_STEPS",
    "finer",
    "finer_options",
    "fixed_refinement",
    "richardson",
    "estimate_fixed",
    "estimate_adaptive",
    "solve_to_target",
]

# The finer solve of an adaptive error estimate divides both tolerances by
# this; the calibrated pairs' global error is proportional to the tolerance
# (tests/test_accuracy.py), so the finer solution is about this much better.
TOLERANCE_RATIO = 10.0
DEFAULT_TARGET_MAX_STEPS = 100_000
# `lierk.solve`'s bound on an adaptive solve's attempts.
DEFAULT_ADAPTIVE_MAX_STEPS = 4096
# At most this many solves per `target_error` call.
_TARGET_SOLVES = 8
# A `target_error` confirming solve takes about this many times the steps of
# the solve it confirms: its tolerance is 100x tighter for DOP853, 18x for
# DP54 and RKF45 (see `solve_to_target`).
_CONFIRM_STEPS = 100**0.125
# The first adaptive tolerance is the target over this (see `solve_to_target`).
_FIRST_TOLERANCE = 20.0
# Rounding that every solve of a problem shares, in eps per radian turned
# (see `solve_to_target`).
_SHARED_ROUNDING = 30.0
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
        (
            _scaled(controller.rtol, 1 / TOLERANCE_RATIO),
            _scaled(controller.atol, 1 / TOLERANCE_RATIO),
            _scaled(controller.max_angle, scale),
        ),
    )


def _scaled(x, factor: float):
    """``x factor``; a concrete ``x`` in NumPy, so that a host path (a
    report's settings) compiles nothing for it."""
    if validation.is_traced(x):
        return x * factor
    return validation.as_jax(np.asarray(x) * np.asarray(factor, np.asarray(x).dtype))


def _diagnostic(x):
    """``x`` out of the gradient (the finer solve is a diagnostic); a
    concrete value has no gradient, and is left as it is."""
    return frozen(x) if validation.is_traced(x) else x


def fixed_refinement(every: int | None = None) -> tuple[int, int]:
    """``(num, den)``: the finer solve of a fixed-step error estimate takes
    ``num`` steps for every ``den`` (its step is ``dt den / num``), so it is
    ``(num / den)^order`` times more accurate: 3 for 2 (1.5x the cost), or 2
    for 1 when an odd save interval ``every`` leaves no other common grid."""
    return (2, 1) if every is not None and every % 2 else (3, 2)


def richardson(gap, ratio):
    """Richardson's estimate of a solve's global error from ``gap``, its
    distance to a solve ``ratio`` times more accurate (`finer_options`):
    ``gap ratio / (ratio - 1)``.  Arrays or floats, in the units of ``gap``
    (for the attitude, the Frobenius norm ``||R - R_fine||_F``); this is how
    ``lierk.solve(..., estimate_error=True)`` fills `Solution.error_estimate`."""
    return gap * (ratio / (ratio - 1.0))


def finer_options(solver, **options) -> tuple[dict, float]:
    """The finer solve behind ``estimate_error=True``: its `lierk.solve`
    options, and how many times more accurate than the given ones it is
    expected to be.

    Example:
        >>> fine, K = lierk.finer_options(solver, dt=0.01)   # dt = 0.00667, K = 1.5^order
        >>> gap = ||solve(..., dt=0.01).R - solve(..., **fine).R||
        >>> error = lierk.richardson(gap, K)

    Args:
        solver: the solve's solver (its ``order`` sets ``K`` for fixed steps).
        **options: the coarser solve's keyword arguments: ``dt=`` (with
            ``saveat=``, ``max_steps=``) for fixed steps; ``rtol=``/``atol=``
            or ``controller=`` (with ``max_steps=``) for adaptive ones.  The
            others are passed through.

    Returns:
        ``(fine, K)``.  Fixed steps: ``dt`` times 2/3, ``K = 1.5^order``
        (times 1/2 and ``K = 2^order`` when ``SaveAt(steps=k)`` saves every
        odd k-th step, so that both solves save at the same times), with
        ``max_steps`` and ``k`` scaled to match.  Adaptive: both tolerances
        divided by 10 and the controller's turn bound ``max_angle`` by
        ``10^(1/order)`` (`finer`), ``K = 10``, ``max_steps`` doubled
        (default 4096), ``dt0`` left to the solve.  Values may be traced;
        ``dt`` and the tolerances of the finer solve are out of the gradient
        (a diagnostic).  One difference remains: ``estimate_error``'s finer
        solve floors its local error test at 5 eps, a solve you run at 50
        eps, so within a few hundred eps of rounding (rtol below about
        1e-13 in float64) the two estimates differ.
    """
    fine = dict(options)
    if options.get("dt") is not None:
        saveat = options.get("saveat")
        every = saveat.every if saveat is not None and saveat.steps else None
        num, den = fixed_refinement(every)
        dt = options["dt"]
        fine["dt"] = _scaled(_diagnostic(dt), den / num) if eqx.is_array(dt) else float(dt) * den / num
        if options.get("max_steps") is not None:
            fine["max_steps"] = -(-num * int(options["max_steps"]) // den)
        if every is not None:
            fine["saveat"] = SaveAt(
                t0=saveat.t0, t1=saveat.t1, steps=every * num // den, ts=saveat.ts, dense=saveat.dense
            )
        return fine, (num / den) ** solver.order
    controller = options.get("controller")
    if controller is None:
        if options.get("rtol") is None:
            raise ValueError(
                f"{solver.name}: pass dt= for fixed steps, or rtol=/atol= or controller= for adaptive ones"
            )
        controller = Controller.from_tolerances(options["rtol"], options.get("atol"))
        del fine["rtol"]
        fine.pop("atol", None)
    if not isinstance(controller, Controller):
        raise ValueError(
            f"finer_options tightens a lierk.Controller's tolerances; {type(controller).__name__} has none"
        )
    fine["controller"] = finer(_diagnostic(controller), solver.order)
    fine["max_steps"] = 2 * (options.get("max_steps") or DEFAULT_ADAPTIVE_MAX_STEPS)
    # The finer solve chooses its own first step, as estimate_error's does.
    fine.pop("dt0", None)
    return fine, TOLERANCE_RATIO


def _own_controller(tol: Array) -> Controller:
    """A `Controller` with ``rtol = atol = tol``, a tolerance this module
    computed itself."""
    return Controller(tol, tol)


def _attitude_gap(sol: Solution, fine: Solution) -> Array:
    """``||R - R_fine||_F`` at each saved time, ``inf`` where the finer solve failed."""
    gap = jnp.linalg.norm(jax.lax.stop_gradient(sol.R) - fine.R, axis=(-2, -1))
    # Padding entries (save times past a failed solve's end) are NaN in both.
    gap = jnp.where(jnp.isnan(gap) & jnp.isnan(sol.R[..., 0, 0]), 0.0, gap)
    return jnp.where(fine.result == RESULTS.successful, gap, jnp.inf)


def _with_estimate(sol: Solution, fine: Solution, ratio) -> Solution:
    """``sol`` with Richardson's estimate from a solve ``ratio`` times more accurate."""
    est = richardson(_attitude_gap(sol, fine), ratio)
    # A solve that blew up has no error bound, whatever its finer twin did.
    est = jnp.where(sol.result == RESULTS.nonfinite, jnp.inf, est)
    return eqx.tree_at(lambda s: s.error_estimate, sol, est, is_leaf=lambda x: x is None)


def estimate_fixed(sol: Solution, problem, solver, t0, t1, dt, saveat: SaveAt, n: int | None) -> Solution:
    """``sol`` (``n`` fixed steps of ``dt``, or with ``SaveAt(ts=...)`` steps
    ending on the save times, at most ``n`` (None: no bound)) with its
    estimate from a finer solve."""
    options, ratio = finer_options(solver, dt=dt, saveat=saveat, max_steps=n)
    if saveat.ts is not None:
        fine = solve_fixed_at(frozen(problem), solver, t0, t1, options["dt"], saveat, options["max_steps"])
    else:
        # The estimate reads the saved states only: no dense output.
        steps = options["saveat"].steps
        fine = solve_fixed(
            frozen(problem),
            solver,
            t0,
            t1,
            options["dt"],
            SaveAt(t0=saveat.t0, t1=saveat.t1, steps=steps),
            options["max_steps"],
        )
    return _with_estimate(sol, fine, ratio)


def estimate_adaptive(
    sol: Solution, problem, solver, t0, t1, saveat: SaveAt, max_steps: int, controller, adjoint
) -> Solution:
    """``sol`` (an adaptive solve) with its estimate from a solve at tolerances
    divided by `TOLERANCE_RATIO`."""
    fine = solve_adaptive(
        frozen(problem),
        solver,
        t0,
        t1,
        None,
        saveat,
        2 * max_steps,
        finer(controller, solver.order),
        adjoint,
        DIAGNOSTIC_FLOOR_EPS,
    )
    return _with_estimate(sol, fine, TOLERANCE_RATIO)


@eqx.filter_jit
def solve_to_target(problem, solver, t0, t1, saveat, eps, max_steps: int, adjoint) -> Solution:
    """Solves at ever finer settings, one at a time, until a solution is
    confirmed within ``eps`` by a finer one; see `solve`.

    Each solve is compared with the last one that finished.  On success
    what comes back is the coarser solution of that pair, with twice their
    gap as its estimate: ``err <= gap + err_fine``, so that bounds its error
    whenever the finer solve is at least twice as accurate.  Success needs
    the finer solve of the pair to be a confirming one: tolerances 100x
    tighter for DOP853 and 18x for DP54 and RKF45 (about 1.8x the steps), or
    2/3 of the step (5x more accurate for RKMK4; for orders 1 and 2, whose
    2/3 is less than 3x, ``3^(-1/order)`` of it).  When it gives up, the
    finer solution of the pair with the smallest estimate comes back, with
    that estimate: the same bound holds for it whenever it is the more
    accurate of the two.

    Returning the finer solution with ``gap/(K - 1)`` instead (K the
    expected accuracy ratio) needs it to be K times more accurate, which at
    loose tolerances it is not: DOP853 on a 1:10:100 body errs 7.0e-4,
    8.2e-4 and 2.8e-5 at rtol 5e-5, 5e-6 and 5e-7, and success was claimed
    8.2x over the target (37x on a random body; 3% of random bodies missed).
    The coarser solution with ``gap K/(K - 1)`` and K = 10 still missed 2.4x
    with DOP853, whose error can stall over a decade of tolerance (3.8e-3 at
    rtol 5e-5, 3.4e-3 at 5e-6, the two errors nearly parallel): hence the
    wider ratio, and twice the gap (with 100x and ``gap (K + 1)/(K - 1)``,
    estimates were still down to 0.7x the error on random bodies).  Twice
    the gap also covers rounding that differs between the two solves
    (independent errors of about the same size: float32, or float64 near the
    intermediate axis over long horizons) unless they nearly cancel;
    rounding they share is bounded apart (`_SHARED_ROUNDING`).

    One `solve_adaptive` call in the loop body, its setting traced, serves
    every solve (fixed steps through `ConstantStep`): one copy of the solver
    loop for XLA to compile, where the rounds of pairs and the rounding
    check had five.
    """
    problem = frozen(problem)
    dtype = problem.R0.dtype
    adaptive = solver.adaptive
    # The solves run in a lax.while_loop, which reverse mode cannot enter anyway.
    adjoint = ForwardMode() if adjoint is None else adjoint
    omega = jnp.linalg.norm(field_at(problem, t0, problem.R0, problem.y0)[0])
    if adaptive:
        # Error ~ tolerance; steps ~ tolerance^(-1/(q + 1)) for an error
        # estimate of order q.
        power = 1.0
        confirm = _CONFIRM_STEPS ** -(solver.error_order + 1)
        # Below this the local error test is floored (DIAGNOSTIC_FLOOR_EPS
        # eps), and a finer tolerance takes the same steps: float32 pairs
        # there (rtol 4.8e-8, which a direct solve refuses) agreed exactly
        # and claimed success with an estimate of 0 at 20 to 425x the target.
        floor = DIAGNOSTIC_FLOOR_EPS * jnp.finfo(dtype).eps / (2.0 * solver.tableau.tolerance_calibration)
        # A solution that comes back is one a direct solve at its tolerance
        # would compute (above the 50-eps floor of `Controller`), and its
        # confirming solve is still 10x finer.
        lowest = 10.0 * floor
        # The calibrated global error is 1 to 10 tol, and success needs
        # twice the gap, about twice the error, within eps: then most
        # members succeed with the first pair (under vmap one member that
        # needs a third solve makes the whole batch pay for it).
        s0 = jnp.maximum(eps / _FIRST_TOLERANCE, lowest)
    else:
        # Error ~ dt^order: 2/3 of the step, 5x more accurate for RKMK4, as
        # for estimate_error=True (finer below order 3: see min_ratio).
        power, confirm = float(solver.order), 2.0 / 3.0
        # A coarse first try, cheap next to the solves that follow: at most
        # a radian per step and an eighth of the interval.
        s0 = jnp.minimum((t1 - t0) / 8, 1.0 / jnp.maximum(omega, 1e-30))
        s0 = jnp.where(s0 > 0, s0, 1.0)
        n_ts = 0
        if saveat.ts is not None:
            # Steps end on every save time: a step longer than their spacing
            # would be cut to the same grid in both solves of a pair, whose
            # gap would then say nothing about the error.
            grid = jnp.concatenate([t0[None], jnp.asarray(saveat.ts, dtype), t1[None]])
            gaps = jnp.diff(grid)
            s0 = jnp.minimum(s0, jnp.min(jnp.where(gaps > 0, gaps, jnp.inf)))
            n_ts = saveat.ts.shape[0]
        # The smallest step within max_steps (each save time cuts one step),
        # and the smallest one that a finer step can confirm.
        floor = (t1 - t0) / max(max_steps - n_ts - 1, 1) * (1.0 + 1e-6)
        lowest = floor / confirm
    # Every solve is at least 3x more accurate, by the error model, than the
    # last one that finished; a confirming one too.  For fixed steps of
    # order 1 and 2, 2/3 of the step is only 1.5x and 2.25x: the search
    # stopped after one solve (its next setting was not 3x finer), and twice
    # the gap would not bound an order-1 error (the premise is a confirming
    # solve at least twice as accurate).  So the confirming step is
    # 3^(-1/order) of the step there: 1/3 for order 1, 0.577 for order 2.
    min_ratio = 3.0 ** (-1.0 / power)
    confirm = min(confirm, min_ratio)

    def solve(s, go):
        if adaptive:
            h, c = None, _own_controller(s)
            # The turn bound tightens with the tolerance, as in `finer`: where
            # it sets the steps (a fast spin of a nearly symmetric body), a
            # finer setting must still take finer steps.
            c = eqx.tree_at(lambda c: c.max_angle, c, c.max_angle.astype(dtype) * (s / s0) ** (1.0 / solver.order))
        else:
            h, c = s, ConstantStep()
        # Under vmap, a member that is done ends at once (its result is dropped).
        end = jnp.where(go, t1, t0)
        return solve_adaptive(problem, solver, t0, end, h, saveat, max_steps, c, adjoint, DIAGNOSTIC_FLOOR_EPS)

    def cond(c):
        return c["go"] & (c["k"] < _TARGET_SOLVES)

    def body(c):
        s, prev, s_prev, has_prev = c["s"], c["prev"], c["s_prev"], c["has_prev"]
        sol = solve(s, c["go"])
        finished = sol.result == RESULTS.successful
        gap = _attitude_gap(prev, sol)
        K = (s_prev / s) ** power
        # Rounding that every solve shares, which no comparison of two sees:
        # float32 fast spins were up to 25 eps per radian turned off at every
        # setting (DOP853 at 570 rad/s for 0.2 s: 3.4e-4, 2.9e-4 and 3.3e-4
        # at rtol 1.5e-5, 3e-6 and 9e-7, where float64 errs 1.3e-4, 1.7e-5
        # and 4e-6), and success was claimed at 3e-4 with 3.7e-4.
        turned = jnp.where(jnp.isfinite(prev.ts), omega * jnp.abs(prev.ts - t0), 0.0)
        est = jnp.maximum(2.0 * gap, _SHARED_ROUNDING * jnp.finfo(dtype).eps * (1.0 + turned))
        # A confirming tolerance held at the local-error floor is not
        # `confirm` finer: both solves of the pair are then rounding noise of
        # about one size, amplified by the flow (near the intermediate axis
        # over long horizons), and two such draws can nearly agree while
        # each errs far more (DOP853, a T-handle 0.007 rad/s off the axis
        # for 200 s at rtol 5e-14: twice the gap 1.4e-11, the error
        # 7.4e-11).  The pair before, one more draw and a coarser one,
        # bounds the noise too.
        floored = s_prev * confirm < floor * (1 - 1e-6)
        est = jnp.where(floored & c["has_gap"], jnp.maximum(est, c["gap_prev"]), est)
        confirmed = has_prev & finished
        confirming = s <= jnp.maximum(s_prev * confirm, floor) * (1 + 1e-6)
        success = confirmed & confirming & (s_prev >= lowest) & (jnp.max(est) <= eps)

        # The next setting.  This solution's error, by Richardson (the
        # premise that fails above; it only steers): confirm it when twice
        # that is well within eps, else aim at a tenth of eps.  After a
        # failed solve, 100x more accurate.
        predicted = jnp.max(gap) / (K - 1.0)
        wanted = finished & (s >= lowest) & (~has_prev | (predicted <= eps / 4))
        aim = jnp.where(predicted > 0, (eps / 10 / predicted) ** (1.0 / power), 1.0)
        s_next = jnp.where(
            wanted,
            jnp.maximum(s * confirm, floor),
            jnp.maximum(s * jnp.where(finished, jnp.clip(aim, 1e-3, min_ratio), 0.01 ** (1.0 / power)), lowest),
        )
        last = jnp.where(finished, s, jnp.where(has_prev, s_prev, jnp.inf))
        steps = jnp.where(finished, sol.stats["num_steps"], c["steps"])
        if adaptive:
            # A solve that would run out of max_steps (steps ~ tol^(-1/(q+1)))
            # is replaced by the finest one that fits with a margin: still an
            # estimate of the last solution's error, though not a confirming
            # one.  Running out costs max_steps steps, for the whole batch
            # under vmap.
            fits = last * (0.8 * max_steps / jnp.maximum(steps, 1).astype(dtype)) ** -(solver.error_order + 1.0)
            s_next = jnp.where(steps > 0, jnp.maximum(s_next, fits), s_next)
        # Out of max_steps, a finer setting would take more steps still.
        go = ~success & (sol.result != RESULTS.max_steps_reached) & (s_next <= last * min_ratio * (1 + 1e-6))

        # What comes back: on success the coarser solution of the confirming
        # pair with its estimate.  Otherwise the most accurate solution with
        # an estimate: the finer of the pair whose estimate is the smallest
        # (twice their gap bounds the finer one's error too whenever it is
        # the more accurate of the two).  The coarser of the last pair was
        # returned before: RKMK4 at 1000 rad/s gave up with an error of 2.0
        # where its finer solve had reached 1e-9.  Before any pair, the first
        # solve (not reached, or its failure), with an estimate of inf.
        first = ~has_prev
        finer = ~success & confirmed & (jnp.max(est) <= jnp.max(c["out_est"]))
        out = jax.tree_util.tree_map(
            lambda a, b, o: jnp.where(success, a, jnp.where(finer | first, b, o)), prev, sol, c["out"]
        )
        out_est = jnp.where(success | finer, est, jnp.where(first, jnp.inf, c["out_est"]))
        out_s = jnp.where(success, s_prev, jnp.where(finer | first, s, c["out_s"]))
        not_reached = confirmed | (first & finished)
        code = jnp.where(
            success,
            RESULTS.successful,
            jnp.where(not_reached, RESULTS.target_error_not_reached, jnp.where(first, sol.result, c["code"])),
        ).astype(jnp.int32)
        return dict(
            k=c["k"] + 1,
            gap_prev=jnp.where(confirmed, gap, c["gap_prev"]),
            has_gap=c["has_gap"] | confirmed,
            s=s_next,
            go=go,
            prev=jax.tree_util.tree_map(lambda a, b: jnp.where(finished, a, b), sol, prev),
            s_prev=jnp.where(finished, s, s_prev),
            has_prev=has_prev | finished,
            steps=steps,
            out=out,
            out_est=out_est,
            out_s=out_s,
            code=code,
        )

    # The carry's solutions start as zeros of the solution's shape, tied to
    # the inputs so that under vmap they are batched from the start (the
    # while loop's batching rule would trace the body again otherwise).
    blank = jax.tree_util.tree_map(
        lambda x: jnp.zeros(x.shape, x.dtype), eqx.filter_eval_shape(solve, s0, jnp.asarray(True))
    )
    init = dict(
        k=jnp.asarray(0),
        gap_prev=jnp.zeros(blank.ts.shape, dtype),
        has_gap=jnp.asarray(False),
        s=s0,
        go=jnp.asarray(True),
        prev=blank,
        s_prev=s0,
        has_prev=jnp.asarray(False),
        steps=blank.stats["num_steps"],
        out=blank,
        out_est=jnp.full(blank.ts.shape, jnp.inf, dtype),
        out_s=s0,
        code=jnp.asarray(RESULTS.target_error_not_reached, jnp.int32),
    )
    c = jax.lax.while_loop(cond, body, _batched_together(init, (problem, t0, t1, eps)))
    sol = c["out"]
    stats = dict(sol.stats)
    stats["num_solves"] = c["k"]
    stats["rtol" if adaptive else "dt"] = c["out_s"]
    return eqx.tree_at(
        lambda x: (x.result, x.stats, x.error_estimate),
        sol,
        (c["code"], stats, c["out_est"]),
        is_leaf=lambda x: x is None,
    )
