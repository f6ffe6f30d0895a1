"""A scene solved in segments ("pieces"), with progress between them:
`lierk.app.scene.Scene.solve`'s ``n_pieces``."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import numpy as np

from lierk import RESULTS, EventRecord, Progress, SaveAt, Solution, num_steps, one_body_compiler_options, solve

from ._device import to_device

__all__ = ["N_PIECES", "solve_in_pieces"]

N_PIECES = 20
"""Pieces of a `Scene.solve(progress=True)` when ``n_pieces`` is not given."""


def solve_in_pieces(scene, n_pieces: int, progress: bool, throw: bool) -> Solution:
    """``scene.solve()`` in ``n_pieces`` pieces; see `Scene.solve`."""
    # One body: `solve`, traced in each program here, takes the solver's
    # one-body form itself (`lierk._programs`).
    problem, solver, t1 = scene.problem, scene.solver, float(scene.t1)
    dtype = problem.R0.dtype
    kw = {k: v for k, v in scene.solve_kwargs.items() if k != "max_steps"}
    bar = Progress(f"{scene.name}: t", t1, "s", quiet=not progress)
    events = tuple(e for _, e in scene.events)
    if any(e.stop_at > 1 for e in events):
        # Each piece counts crossings from zero: an event that ends the run at
        # its n-th crossing needs one piece.
        n_pieces = 1
    kw.update({"event": events} if events else {})

    if scene.target_error is not None:
        # The save times are made here, concrete, so they are checked now
        # rather than by a run-time check in the program.
        saveat = scene.saveat()
        with bar.compiling():
            run = _compiled(
                lambda problem: solve(problem, solver, t1, saveat=saveat, throw=False, **scene.solve_kwargs), problem
            )
        sol = jax.block_until_ready(run(problem))
        code = int(sol.result)
        if throw and code == RESULTS.target_error_not_reached:
            worst = float(np.max(np.asarray(sol.error_estimate)))
            raise RuntimeError(
                f"target_error = {scene.target_error:g} was not reached: the best estimate was {worst:.2g} "
                f"(last tried {sol.chosen_setting()}); loosen it or use another solver"
            )
        _check(code, 0.0, t1, throw)
        bar.update(t1)
        stats = {k: (float(v) if k in ("dt", "rtol") else int(v)) for k, v in sol.stats.items()}
        return eqx.tree_at(lambda s: s.stats, sol, stats)

    if not scene.adaptive:
        dt = float(kw["dt"])
        n_total = num_steps(0.0, t1, dt, None)
        # Saving every n_total-th step or less often saves the same grid (the
        # start and t1): pieces of save_every = 10^9 steps each ran the
        # padding of their static length.
        every = min(scene.saveat_every, n_total)
        # Pieces hold a whole number of save intervals, so the saved grid is
        # the one a single solve saves.
        per = every * max(1, math.ceil(n_total / (n_pieces * every)))
        bounds = [min(k * per, n_total) for k in range(math.ceil(n_total / per) + 1)]
        times = [min(b * dt, t1) for b in bounds]
        times[-1] = t1

        def piece(problem, ta, tb):
            # Padding steps past tb are exact no-ops (the loop skips them in
            # blocks), so every piece has the same static length and
            # compiles once.
            return solve(problem, solver, tb, t0=ta, max_steps=per, saveat=SaveAt(steps=every), throw=False, **kw)

        pieces = [(times[k], times[k + 1], None) for k in range(len(times) - 1)]
    else:
        # The very times one solve is asked for, so the grids agree bit for bit.
        rest = np.asarray(scene.saveat().ts)[1:]
        size = math.ceil(len(rest) / n_pieces)
        max_steps = scene.solve_kwargs.get("max_steps")

        def piece(problem, ta, tb, ts):
            return solve(problem, solver, tb, t0=ta, saveat=SaveAt(ts=ts), max_steps=max_steps, throw=False, **kw)

        pieces, ta = [], 0.0
        for k in range(0, len(rest), size):
            group = rest[k : k + size]
            # Every piece saves `size` times (the last repeats its end), so all share one compilation.
            group = np.concatenate([group, np.full(size - len(group), group[-1])])
            pieces.append((ta, float(group[-1]), group))
            ta = float(group[-1])

    def arguments(problem, ta, tb, group):
        args = (problem, to_device(ta, dtype), to_device(tb, dtype))
        return args if group is None else args + (to_device(group, dtype),)

    with bar.compiling():
        piece = _compiled(piece, *arguments(problem, *pieces[0]))

    # Host-side bookkeeping is NumPy: an eager jax.numpy operation would
    # compile a program of its own.
    ts_out, R_out = [np.zeros(1)], [np.asarray(problem.R0)[None]]
    y_out = [jax.tree_util.tree_map(lambda x: np.asarray(x)[None], problem.y0)]
    stats, code = {}, RESULTS.successful
    found = [[] for _ in events]  # per event: each piece's record
    for ta, tb, group in pieces:
        sol = jax.device_get(piece(*arguments(problem, ta, tb, group)))
        code = int(sol.result)
        ts = np.asarray(sol.ts)
        # Padding repeats the end state; keep each time once.  Rows past a
        # terminating event were not reached (NaN).
        keep = np.concatenate([[True], ts[1:] > ts[:-1]]) & (ts > ts_out[-1][-1])
        keep &= np.isfinite(np.asarray(sol.R)).all(axis=(1, 2)) | (code != RESULTS.event_occurred)
        for i, r in enumerate(sol.events or ()):
            found[i].append(jax.tree_util.tree_map(np.asarray, r))
        ts_out.append(ts[keep])
        R_out.append(np.asarray(sol.R)[keep])
        y_out.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[keep], sol.y))
        if code == RESULTS.event_occurred:
            # The run ends with the state at the event, as one solve's t1 row does.
            r = next(f[-1] for f in found if bool(f[-1].stopped))
            j = min(int(r.count), len(r.ts)) - 1
            ts_out.append(r.ts[j : j + 1])
            R_out.append(r.R[j : j + 1])
            y_out.append(jax.tree_util.tree_map(lambda x: x[j : j + 1], r.y))
        stats = {k: stats.get(k, 0) + int(v) for k, v in sol.stats.items()}
        if _check(code, ta, tb, throw):
            break
        # The solve's own end state, unchecked: ExplicitEuler's attitude
        # leaves SO(3) (||R^T R - I|| grows by about (dt |omega|)^2 a step),
        # and one solve carries it on as it is.
        problem = problem._restarted(to_device(sol.R[-1]), jax.tree_util.tree_map(lambda x: to_device(x[-1]), sol.y))
        bar.update(tb)

    ts = np.concatenate(ts_out)
    if not scene.adaptive and code == RESULTS.successful:
        # A piece counts its time from its own start (ta + j dt), one solve
        # from 0 (k dt): the same times up to rounding.  Saved times are
        # reported as one solve reports them, k dt and then t1.
        ts = np.append(np.arange(0, n_total, every).astype(dtype) * np.asarray(dt, dtype), np.asarray(t1, dtype))[
            : len(ts)
        ]
    y = None if scene.problem.y0 is None else jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *y_out)
    return Solution(
        ts=to_device(ts, dtype),
        R=to_device(np.concatenate(R_out), dtype),
        y=jax.tree_util.tree_map(lambda x: to_device(x, dtype), y),
        n_saved=to_device(len(ts)),
        stats=stats,
        result=to_device(code),
        events=tuple(_joined(e, records) for e, records in zip(events, found)) if events else None,
    )


def _compiled(fun, *args):
    """``fun`` compiled for arguments like ``args`` (the same structure and
    non-array values; arrays of the same shapes and dtypes), one body's
    solve: compiled here, so that a progress bar reports the compilation
    apart from the run, and found in JAX's persistent cache where it is on."""
    return eqx.filter_jit(fun).lower(*args).compile(one_body_compiler_options())


def _joined(event, records) -> EventRecord:
    """One `EventRecord` from the pieces' records of ``event``, in time
    order: the first ``max_count`` crossings, the count of all."""
    kept = [(r.ts[: min(int(r.count), len(r.ts))], r) for r in records]
    n = event.max_count
    ts = np.concatenate([k for k, _ in kept])[:n]
    R = np.concatenate([r.R[: len(k)] for k, r in kept])[:n]
    y = jax.tree_util.tree_map(
        lambda *xs: np.concatenate(xs)[:n], *[jax.tree_util.tree_map(lambda a: a[: len(k)], r.y) for k, r in kept]
    )
    pad = n - len(ts)
    return EventRecord(
        ts=to_device(np.concatenate([ts, np.full(pad, np.inf, ts.dtype)])),
        R=to_device(np.concatenate([R, np.full((pad, 3, 3), np.nan, R.dtype)])),
        y=jax.tree_util.tree_map(
            lambda a: to_device(np.concatenate([a, np.full((pad,) + a.shape[1:], np.nan, a.dtype)])), y
        ),
        count=to_device(np.int32(sum(int(r.count) for r in records))),
        stopped=to_device(np.bool_(any(bool(r.stopped) for r in records))),
    )


def _check(code: int, ta: float, tb: float, throw: bool) -> bool:
    """True if the solve ends after the piece from ``ta`` to ``tb``: it
    failed (raised with ``throw``) or a terminating event stopped it."""
    if code == RESULTS.successful:
        return False
    if code == RESULTS.event_occurred:
        return True
    if throw:
        raise RuntimeError(f"integration failed between t = {ta:g} s and {tb:g} s: {RESULTS.message(code)}")
    return True
