"""The two loops behind `lierk.solve`, and the saving they share.

- `solve_fixed`: a static number of fixed steps through `lax.scan`
  (checkpointed in blocks for reverse mode).  It saves by structure: an outer
  scan over chunks of ``SaveAt(steps=k)`` steps stacks the chunk ends.
  `solve_fixed_at` takes fixed steps that end on given save times
  (``SaveAt(ts=...)``), their counts traced: one compilation for every step
  size.
- `solve_adaptive`: a while loop driven by a step-size controller
  (`lierk._controller`: `Controller` for embedded pairs, `ConstantStep` for a
  fixed step whose count is not static), differentiated as its adjoint says
  (`lierk._adjoint`).  It saves into buffers (`_save_init`, `_save_update`).

Both end with `_assemble`: the saved times and states, from ``t0`` to the end,
and the `Solution`.  Values (t0, t1, dt, tolerances, inertia, omega0) are
traced, so eager calls with new values reuse the compilation, like diffrax's
diffeqsolve.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import _event as event_lib
from . import _validation as validation
from ._adjoint import ForwardMode
from ._controller import AbstractStepController, frozen
from ._interpolation import DenseInterpolation
from ._solution import RESULTS, SaveAt, Solution

__all__ = ["solve_fixed", "solve_fixed_at", "solve_adaptive", "num_steps", "step_count", "frozen"]

# Fixed-step runs of at least this many steps squared (256) are checkpointed in
# blocks for reverse mode (`solve_fixed`).
_CHECKPOINT_BLOCK_MIN = 16
# Runs of at least this many steps skip their checkpoint blocks past the
# run's end one by one (`_chunked`).
_IDLE_BLOCKS_FROM = 4096


def num_steps(t0, t1, dt, max_steps=None) -> int:
    """Number of fixed steps `solve` takes from ``t0`` to ``t1`` with step ``dt``:
    ``max_steps`` if given, else ``ceil((t1 - t0)/dt)`` (a multiple of ``dt`` up
    to rounding counts exactly).  Needs concrete values."""
    if max_steps is not None:
        return int(max_steps)
    if validation.is_traced(t0, t1, dt):
        raise ValueError(
            "t0, t1 or dt is traced (under jit/vmap), so the number of steps cannot be read from them: "
            "pass max_steps=N, a Python int with N * dt >= t1 - t0"
        )
    dtype = np.result_type(np.asarray(t0), np.asarray(t1), np.asarray(dt), np.float32)
    return int(step_count(*(np.asarray(v, dtype) for v in (t0, t1, dt)), np))


def step_count(t0, t1, dt, xp):
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
    tol = xp.minimum(
        xp.maximum(1e-9 * xp.minimum(1.0, x), 16 * eps * (x + xp.maximum(xp.abs(t0), xp.abs(t1)) / dt)), 0.5
    )
    r = xp.round(x)
    n = xp.where(xp.abs(x - r) <= tol, r, xp.ceil(x))
    # A step longer than the interval is one step, shortened to end at t1.
    return xp.where(t1 > t0, xp.maximum(n, 1.0), 0.0)


def _one(x):
    """A leading axis of length one on every leaf."""
    return jax.tree_util.tree_map(lambda v: v[None], x)


def _assemble(saveat: SaveAt, t0, state0, middle, end) -> tuple[Array, Any, Any, int]:
    """The saved ``(ts, R, y, count)``, in time order: ``t0`` (if saved), then
    ``middle`` (stacked ``(ts, (R, y))`` or None), then ``end`` (``(t, (R, y))``
    of the last state, or None).  ``count`` is the number of rows."""
    ts, states = [], []
    if saveat.t0:
        ts.append(t0[None])
        states.append(_one(state0))
    if middle is not None:
        ts.append(middle[0])
        states.append(middle[1])
    if end is not None:
        ts.append(end[0][None])
        states.append(_one(end[1]))
    R, y = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *states)
    return jnp.concatenate(ts), R, y, sum(len(t) for t in ts)


class _Schedule(NamedTuple):
    """The steps of a fixed-step solve: ``n`` (static) steps of ``dt`` from
    ``t0``, of which ``count`` reach ``t1`` (``needed`` would)."""

    needed: Array
    count: Array
    time: Any  # k -> the time of step k's start (t1 from step `count` on)
    size: Any  # k -> the size of step k (0 from step `count` on)


def _schedule(t0, t1, dt, n: int) -> _Schedule:
    # `count` steps reach t1 (the host's `num_steps` when it chose n; fewer
    # when max_steps set n).  Every step but the last is exactly dt, and the
    # last is what remains of t1 - t0: step sizes are not differences of the
    # times t0 + k dt, which far from t = 0 are rounded to the ulp of t (in
    # float32 at t = 1e5, 0.008 s).  The times themselves only tell
    # time-dependent effects where they are.
    needed = step_count(t0, t1, dt, jnp)
    count = jnp.minimum(needed, n).astype(jnp.asarray(0).dtype)
    # (A run cut short by max_steps ends with a step of dt like the others.)
    last = jnp.where(needed <= n, (t1 - t0) - (count - 1).astype(dt.dtype) * dt, dt)

    def time(k):
        # (`needed`, not `count`: a run cut short by max_steps ends at t0 + n dt.)
        return jnp.where(k.astype(dt.dtype) >= needed, t1, t0 + k.astype(dt.dtype) * dt)

    def size(k):
        return jnp.where(k + 1 < count, dt, jnp.where(k + 1 == count, last, jnp.zeros_like(dt)))

    return _Schedule(needed, count, time, size)


def _blocks(length: int, pad: bool) -> tuple[int, int, int]:
    """``(block, blocks, rem)``: ``length`` steps as ``blocks`` checkpointed
    blocks of ``block`` steps, about ``sqrt(length)``, then ``rem`` more.

    A remainder is a second scan, and each scan length compiles the whole step
    once more (about twice the compile time).  So ``block``
    divides ``length`` when a divisor lies within a factor 2 of the root.
    Otherwise, with ``pad`` (the run's last steps, after which steps are
    exact no-ops), the last block runs past ``length`` by the fewest steps
    (under ``sqrt(length)``, i.e. at most a few percent more work); without
    it the remainder is scanned on its own.
    """
    root = math.isqrt(length)
    near = sorted(range(max(1, root // 2), 2 * root + 1), key=lambda d: abs(d - root))
    exact = next((d for d in near if length % d == 0), None)
    if exact is not None:
        return exact, length // exact, 0
    if pad:
        block = min(near, key=lambda d: -length % d)
        return block, -(-length // block), 0
    return root, length // root, length % root


class _Idle(NamedTuple):
    """The steps of a fixed-step loop after its run has ended (past ``t1``,
    or stopped by an event), which are exact no-ops: ``done(carry)`` says
    that every step from ``carry`` on is one, ``past(carry, length)`` is the
    carry after ``length`` of them (the step index moved on)."""

    done: Any
    past: Any


def _chunked(one, carry, n: int, every: int, time, idle: _Idle | None = None):
    """``n`` steps of the scan body ``one`` from ``carry``, in chunks of
    ``every`` steps: ``(carry, middle)``, ``middle`` the chunk ends' times
    (``time`` of their step index) and stacked ``carry[0]``, or None when
    ``every`` is 0 or exceeds ``n``.

    ``idle``: the no-op steps after the run's end (`_Idle`).  A chunk or a
    remainder of at least `_CHECKPOINT_BLOCK_MIN` steps, and in runs of
    `_IDLE_BLOCKS_FROM` steps or more a checkpoint block, that starts after
    it is skipped (one ``lax.cond`` each), so that a static step count far
    beyond the run's, a generous ``max_steps`` or a scene's last piece
    padded to the others' length, costs few steps.  Where the run ends
    inside such a block, its steps are taken: at most about ``sqrt(n)``.
    (Under ``vmap`` with a batched end the ``cond`` is a select, and every
    step runs, as without it.)"""
    # In reverse mode each step keeps only its starting state and is
    # recomputed in the backward pass: saved as they fall out of the step's
    # fused arithmetic, its residuals were about a hundred small arrays, each
    # written by a kernel of its own (the gradient cost 60 forward steps per
    # step).  Outside reverse mode the checkpoint does nothing.
    step = jax.checkpoint(one, prevent_cse=False)

    def unless_idle(run, carry, length):
        # `run(carry)`, or the carry moved past `length` no-op steps.
        if idle is None or length < _CHECKPOINT_BLOCK_MIN:
            return run(carry)
        return jax.lax.cond(idle.done(carry), lambda c: idle.past(c, length), run, carry)

    def scan(carry, length):
        return jax.lax.scan(step, carry, None, length=length)[0]

    def steps(carry, length, last):
        # Reverse mode through a plain scan keeps every step's residuals:
        # 10^6 steps would hold gigabytes.  Blocks of about sqrt(length)
        # steps, each recomputed from its start in the backward pass, hold
        # O(sqrt(length)) instead, for one more forward pass.  Without reverse
        # mode the checkpoint does nothing.
        if math.isqrt(length) < _CHECKPOINT_BLOCK_MIN:
            return scan(carry, length)
        block, blocks, rem = _blocks(length, pad=last)

        # Each block's skip is a conditional around its scan, which costs
        # a batch of short runs far more than its share of steps
        # (`benchmarks/headline.py`'s top_rkmk_dop853, 400 steps in blocks
        # of 20: 1.4x to 1.7x the run): blocks are skipped in runs of
        # `_IDLE_BLOCKS_FROM` steps and more, where they are 64 steps or
        # longer.  Shorter runs skip whole chunks and the remainder only.
        def run(c):
            if length < _IDLE_BLOCKS_FROM:
                return scan(c, block)
            return unless_idle(lambda c: scan(c, block), c, block)

        body = jax.checkpoint(lambda c, _: (run(c), None), prevent_cse=False)
        carry = jax.lax.scan(body, carry, None, length=blocks)[0]
        return scan(carry, rem) if rem else carry

    n_chunks, rem = divmod(n, every) if every else (0, n)

    def chunk(carry, _):
        carry = unless_idle(lambda c: steps(c, every, last=False), carry, every)
        return carry, carry[0]

    middle = None
    if n_chunks:
        carry, saved = jax.lax.scan(chunk, carry, None, length=n_chunks)
        middle = (time((jnp.arange(n_chunks) + 1) * every), saved)
    if rem:
        # The run's last steps: steps past n are exact no-ops (h = 0).
        carry = unless_idle(lambda c: steps(c, rem, last=True), carry, rem)
    return carry, middle


@eqx.filter_jit
def solve_fixed(problem, solver, t0, t1, dt, saveat: SaveAt, n: int, events: tuple = ()) -> Solution:
    """``n`` (static) fixed steps of ``dt`` from ``t0``, the last shortened to
    end exactly at ``t1``; steps past ``t1`` are exact no-ops.  With
    ``SaveAt(dense=True)`` or ``events`` (a tuple of `lierk.Event`), see
    `_solve_fixed_tracked`."""
    if saveat.dense or events:
        return _solve_fixed_tracked(problem, solver, t0, t1, dt, saveat, n, events)
    needed, count, time, size = schedule = _schedule(t0, t1, dt, n)
    one = _fixed_step(problem, solver, schedule)
    state0 = _moved_together((problem.R0, problem.y0))
    every = saveat.every
    n_chunks, rem = divmod(n, every) if every else (0, n)
    # Past t1 (step `count` on) every step is the identity.
    idle = _Idle(lambda c: c[1] >= count, lambda c, length: (c[0], c[1] + length, c[2]))
    carry, middle = _chunked(one, (state0, jnp.asarray(0), jnp.asarray(0)), n, every, time, idle)
    state, _, taken = carry
    # (The last chunk's end is t1 already when the chunks fill the run.)
    end = (time(jnp.asarray(n)), state) if saveat.t1 and (rem or not n_chunks) else None
    ts, R, y, n_saved = _assemble(saveat, t0, state0, middle, end)
    result = jnp.where(needed <= n, RESULTS.successful, RESULTS.max_steps_reached)
    result = jnp.where(validation.all_finite(state), result, RESULTS.nonfinite)
    return Solution(ts, R, y, jnp.asarray(n_saved), _fixed_stats(taken, solver), result)


def _fixed_step(problem, solver, schedule: _Schedule):
    """The scan body of a fixed-step loop, ``((R, y), k, taken) -> (next, None)``."""
    _, count, time, size = schedule

    # The step index and the count of steps taken ride in the loop's carry:
    # scanning over an array of indices (or of step times) would allocate a
    # buffer of the step count, 8 bytes a step, whatever is saved.
    def one(carry, _):
        (R, y), k, taken = carry
        # Past t1, h = 0 and every solver's step is exactly the identity.
        st = solver.step(problem, time(k), size(k), R, y)
        return ((st.R, st.y), k + 1, taken + (k < count).astype(taken.dtype)), None

    return one


@eqx.filter_jit
def solve_fixed_at(problem, solver, t0, t1, dt, saveat: SaveAt, max_steps: int | None = None) -> Solution:
    """Fixed steps of ``dt`` that end on every save time (``SaveAt(ts=...)``):
    each gap between consecutive times of ``t0, ts..., t1`` is taken in
    `step_count` steps of ``dt``, the last shortened to end on the gap's end
    (a gap within rounding of a whole number of steps takes that number).

    The counts are traced: one compilation serves every ``dt`` and every
    ``ts`` of a length, and a run costs its own steps (no padding).
    ``max_steps`` (static, or None for no bound) bounds the steps of the
    whole run: one that needs more stops there, its later rows unreached
    (NaN, not counted in ``n_saved``), with `RESULTS.max_steps_reached`.  A
    ``dt`` that is not a positive finite number gives a non-finite state
    (`RESULTS.nonfinite`).  Each gap is a loop of traced length, which
    forward mode differentiates and reverse mode cannot enter
    (`ForwardSensitivity` reads reverse mode from the forward
    sensitivities).  The steps are `solve_fixed`'s wherever the save times
    fall on its grid, to rounding."""
    ts = jnp.asarray(saveat.ts, dt.dtype)
    starts = jnp.concatenate([t0[None], ts])
    ends = jnp.concatenate([ts, t1[None]])
    # A bad step (NaN after its check in the program) makes one step of NaN.
    valid = jnp.isfinite(dt) & (dt > 0)
    bound = jnp.iinfo(jnp.int32).max if max_steps is None else max_steps

    def gap(carry, ab):
        state, taken, short = carry
        a, b = ab
        needed = jnp.where(valid, step_count(a, b, dt, jnp), 1.0)
        count = jnp.minimum(needed, bound).astype(jnp.int32)
        allowed = jnp.clip(bound - taken, 0, count)
        last = jnp.where(valid, (b - a) - (count - 1).astype(dt.dtype) * dt, jnp.nan)

        def one(k, c):
            (R, y), n = c
            h = jnp.where(k + 1 < count, dt, last)
            st = solver.step(problem, a + k.astype(dt.dtype) * dt, h, R, y)
            return (st.R, st.y), n + 1

        state, taken = jax.lax.fori_loop(0, allowed, one, (state, taken))
        short = short | (allowed.astype(needed.dtype) < needed)
        row = jax.tree_util.tree_map(lambda x: jnp.where(short, jnp.full_like(x, jnp.nan), x), state)
        return (state, taken, short), (row, ~short)

    state0 = _moved_together((problem.R0, problem.y0))
    init = (state0, jnp.asarray(0, jnp.int32), jnp.asarray(False))
    (state, taken, short), (saved, reached) = jax.lax.scan(gap, init, (starts, ends))
    n = ts.shape[0]
    middle = (ts, jax.tree_util.tree_map(lambda x: x[:n], saved))
    end = (t1, jax.tree_util.tree_map(lambda x: x[n], saved)) if saveat.t1 else None
    ts_out, R, y, _ = _assemble(saveat, t0, state0, middle, end)
    reached = reached.astype(jnp.int32)
    n_saved = int(saveat.t0) + jnp.sum(reached[:n], dtype=jnp.int32) + (reached[n] if saveat.t1 else 0)
    result = jnp.where(short, RESULTS.max_steps_reached, RESULTS.successful)
    result = jnp.where(validation.all_finite(state), result, RESULTS.nonfinite)
    return Solution(ts_out, R, y, n_saved.astype(jnp.int32), _fixed_stats(taken, solver), result)


def _tracked(saveat: SaveAt, solver, events: tuple) -> bool:
    """Whether every step builds its interpolant: for dense output, for
    events that sample inside the steps, and for events on a solver whose
    interpolant comes from the step's own stages (`dense_in_step`).  Other
    events build it only in a step where a condition changed sign."""
    return bool(saveat.dense or events and (event_lib.samples_inside(events) or solver.dense_in_step))


def _rebuild_fevals(solver, ev, like: Array) -> Array | int:
    """Field evaluations of the interpolants events built apart (`_tracked`),
    in ``like``'s dtype."""
    return 0 if ev is None else (ev.rebuilt * solver.dense_rebuild_fevals).astype(like.dtype)


def _fixed_stats(taken, solver, tracked: bool = False, rebuilt: Array | int = 0) -> dict:
    """Step and field-evaluation counts of ``taken`` fixed steps; ``tracked``:
    each step built its interpolant (`AbstractSolver.dense_fevals`);
    ``rebuilt``: the evaluations of those events built apart (`_rebuild_fevals`)."""
    per_step, initial = solver.dense_fevals if tracked else (0, 0)
    served = 1 if tracked and solver.dense_serves_first_stage else 0
    return {
        "num_steps": taken,
        "num_accepted_steps": taken,
        "num_rejected_steps": jnp.zeros_like(taken),
        "num_fevals": initial + taken * (solver.stages + per_step - served) + rebuilt,
    }


def _solve_fixed_tracked(problem, solver, t0, t1, dt, saveat: SaveAt, n: int, events: tuple) -> Solution:
    """`solve_fixed` that also builds each step's interpolant
    (`AbstractSolver.dense_step`), for events (`lierk._event`) and, with
    ``SaveAt(dense=True)``, keeps them (`DenseInterpolation`).  A terminating
    event makes the remaining steps no-ops (``h = 0``) from the state at the
    event."""
    needed, count, time, size = _schedule(t0, t1, dt, n)
    R0, y0 = problem.R0, problem.y0
    ev0 = event_lib.init(events, t0, R0, y0) if events else None
    stopped0 = ev0.nan if events else jnp.asarray(False)
    every = saveat.every
    partial = solver.dense_partial(problem)
    tracked = _tracked(saveat, solver, events)

    def one(carry, _):
        (R, y), node, k, taken, ev, stopped, t_end = carry
        t = time(k)
        h = jnp.where(stopped, jnp.zeros_like(dt), size(k))
        if tracked:
            st, (Fu, Fy), node1 = solver.dense_step(problem, t, h, R, y, None, node)
        else:
            st, Fu, Fy, node1 = solver.step(problem, t, h, R, y), None, None, None
        live = (k < count) & ~stopped
        state = (st.R, st.y)
        t_end = jnp.where(live, time(k + 1), t_end)
        if events:
            interpolant = event_lib.Interpolant((Fu, Fy) if tracked else None, problem, solver, partial, (st.R, st.y))
            ev, stop = event_lib.process(events, ev, (t, h, R, y), live, interpolant)
            state = jax.tree_util.tree_map(lambda a, b: jnp.where(stop.stop, a, b), (stop.R, stop.y), state)
            t_end = jnp.where(stop.stop, stop.t, t_end)
            stopped = stopped | stop.stop | ev.nan
        carry = (state, node1, k + 1, taken + live.astype(taken.dtype), ev, stopped, t_end)
        if not saveat.dense:
            return carry, None
        record = (jnp.where(live, t, jnp.inf), jnp.where(live, h, jnp.zeros_like(h)), R, y, Fu, Fy)
        return carry, (record, state if every else None)

    izero = jnp.asarray(0)
    node0 = solver.dense_node(problem, t0, R0, y0) if tracked else None
    carry = (_moved_together((R0, y0)), node0, izero, izero, ev0, stopped0, t0)
    n_chunks, rem = divmod(n, every) if every else (0, n)
    interpolation = None
    if saveat.dense:
        # Every step's interpolant is kept: memory O(n) is what was asked for.
        # (At least one step, of size 0 when t1 = t0, so that t0 has an interpolant.)
        carry, (records, states) = jax.lax.scan(jax.checkpoint(one, prevent_cse=False), carry, None, length=max(n, 1))
        middle = None
        if n_chunks:
            saved = jax.tree_util.tree_map(lambda x: x[every - 1 :: every][:n_chunks], states)
            middle = (time((jnp.arange(n_chunks) + 1) * every), saved)
    else:
        # Past t1 or a terminating event every step is the identity on what
        # is read at the end (the dense node is not).
        def past(c, length):
            return (c[0], c[1], c[2] + length, *c[3:])

        carry, middle = _chunked(one, carry, n, every, time, _Idle(lambda c: (c[2] >= count) | c[5], past))
    state, _, _, taken, ev, stopped, t_end = carry
    if saveat.dense:
        interpolation = DenseInterpolation(*records, t0=t0, t1=t_end, n=taken, partial=partial)
    unreached = 0
    fills = n_chunks and not rem  # the last chunk's end is the t1 row
    if middle is not None:
        times, saved = middle
        # Rows past a terminating event were never reached.
        reached = times <= t_end
        if saveat.t1 and fills:
            # The t1 row holds the state where the solve ended.
            reached = reached.at[-1].set(True)
            times = times.at[-1].set(t_end)
            saved = jax.tree_util.tree_map(lambda x, v: x.at[-1].set(v), saved, state)
        saved = jax.tree_util.tree_map(
            lambda x: jnp.where(reached.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.nan), saved
        )
        middle, unreached = (times, saved), jnp.sum(~reached)
    end = (t_end, state) if saveat.t1 and not fills else None
    ts, R, y, n_saved = _assemble(saveat, t0, (R0, y0), middle, end)
    n_saved = jnp.asarray(n_saved) - unreached
    result = jnp.where(needed <= n, RESULTS.successful, RESULTS.max_steps_reached)
    result = jnp.where(validation.all_finite(state), result, RESULTS.nonfinite)
    records_out = None
    if events:
        result = jnp.where(jnp.any(ev.stopped), RESULTS.event_occurred, result)
        result = jnp.where(ev.nan, RESULTS.event_condition_nan, result)
        records_out = event_lib.records(events, ev)
    return Solution(
        ts,
        R,
        y,
        n_saved,
        _fixed_stats(taken, solver, tracked=tracked, rebuilt=_rebuild_fevals(solver, ev, taken)),
        result,
        interpolation=interpolation,
        events=records_out,
    )


def _save_init(saveat: SaveAt, t0, R0, y0, max_steps: int):
    """The adaptive loop's save buffers ``(ts, R, y)``: one row per possible
    step for ``SaveAt(steps=True)`` (``inf``/NaN until written), the requested
    times for ``SaveAt(ts=...)`` (those at ``t0`` filled already), or None."""
    dtype = R0.dtype
    if saveat.steps:
        return (
            jnp.full((max_steps,), jnp.inf, dtype),
            jnp.full((max_steps, 3, 3), jnp.nan, dtype),
            jax.tree_util.tree_map(lambda x: jnp.full((max_steps,) + x.shape, jnp.nan, x.dtype), y0),
        )
    if saveat.ts is not None:
        ts_req = jnp.asarray(saveat.ts, dtype=dtype)
        at_start = ts_req <= t0
        return (
            ts_req,
            jnp.where(at_start[:, None, None], R0, jnp.nan),
            jax.tree_util.tree_map(lambda x: jnp.where(at_start.reshape((-1,) + (1,) * x.ndim), x, jnp.nan), y0),
        )
    return None


def _save_update(saveat: SaveAt, saved, save_index, accept, t_new, R, y, max_steps: int):
    """The buffers after an attempt that ended at ``t_new`` with ``(R, y)``:
    an accepted step is written to the next row (``steps=True``) or to the
    requested time it hit (``ts=``).  Returns ``(saved, save_index)``."""
    if saveat.steps:
        ts_b, R_b, y_b = saved
        i = jnp.minimum(save_index, max_steps - 1)
        saved = (
            ts_b.at[i].set(jnp.where(accept, t_new, ts_b[i])),
            R_b.at[i].set(jnp.where(accept, R, R_b[i])),
            jax.tree_util.tree_map(lambda b, v: b.at[i].set(jnp.where(accept, v, b[i])), y_b, y),
        )
        return saved, save_index + accept.astype(jnp.int32)
    if saveat.ts is not None:
        ts_b, R_b, y_b = saved
        write = accept & (jnp.asarray(saveat.ts, ts_b.dtype) == t_new)
        saved = (
            ts_b,
            jnp.where(write[:, None, None], R, R_b),
            jax.tree_util.tree_map(lambda b, v: jnp.where(write.reshape((-1,) + (1,) * v.ndim), v, b), y_b, y),
        )
    return saved, save_index


class _Carry(NamedTuple):
    t: Array
    h: Array
    R: Array
    y: Any
    f: Any  # (omega, dy/dt) at (t, R, y): the next step's first stage, or None
    num_steps: Array
    num_accepted: Array
    num_rejected: Array
    rejected_last: Array
    done: Array
    result: Array
    save_index: Array
    saved: Any  # (ts, R, y) buffers, or None
    decisions: Any  # per-attempt record for reverse-mode replay (see _adaptive_loop), or None
    # Only with dense output or events (None otherwise, which leaves the
    # program of other solves as it was):
    node: Any = None  # `AbstractSolver.dense_node` at (t, R, y)
    ev: Any = None  # `lierk._event.State`
    dense: Any = None  # the `DenseInterpolation` buffers (ts, hs, R, y, Fu, Fy), max_steps rows


@eqx.filter_jit
def solve_adaptive(
    problem,
    solver,
    t0,
    t1,
    dt0,
    saveat: SaveAt,
    max_steps: int,
    controller: AbstractStepController,
    adjoint,
    floor_eps: float = 50.0,
    events: tuple = (),
) -> Solution:
    """Steps chosen by ``controller`` from ``t0`` to ``t1``, at most
    ``max_steps`` attempts (accepted plus rejected); ``dt0`` is the first step
    (None: the controller's choice).  ``floor_eps``: the local error test is
    never tighter than this many eps (see `Controller`)."""
    replay = None
    if controller.decides and adjoint.kind == "bounded":
        # DirectAdjoint's scans rematerialise steps from carries, and a step
        # recomputed in a differently compiled body can decide differently
        # (see `_adaptive_loop`): its jacrev was 4e-9 off at rtol 1e-11 and
        # changed with max_steps.  So an undifferentiated solve takes the
        # decisions first (one more forward solve), and the differentiated
        # loop only replays them: every pass of it takes the same steps.
        _, replay = _adaptive_loop(
            frozen(problem),
            solver,
            frozen(t0),
            frozen(t1),
            frozen(dt0),
            saveat,
            max_steps,
            frozen(controller),
            ForwardMode(),
            floor_eps,
            record=True,
            events=events,
        )
    return _adaptive_loop(
        problem, solver, t0, t1, dt0, saveat, max_steps, controller, adjoint, floor_eps, replay=replay, events=events
    )[0]


def _adaptive_loop(
    problem,
    solver,
    t0,
    t1,
    dt0,
    saveat: SaveAt,
    max_steps: int,
    controller: AbstractStepController,
    adjoint,
    floor_eps: float,
    record: bool = False,
    replay: Array | None = None,
    events: tuple = (),
) -> tuple[Solution, Array | None]:
    """The while loop: ``(Solution, decisions)``.  ``decisions``
    ``(max_steps,)`` holds each attempt's next step, negative if the attempt
    was rejected (NaN after the last attempt), when they are recorded: for a
    controller that decides, always with the checkpointed adjoint, and when
    ``record``.  ``replay`` (decisions recorded by an earlier solve of the same
    problem) makes the loop take those decisions instead of its own."""
    R0, y0 = problem.R0, problem.y0
    ctrl_state, h0, f0 = controller.init(problem, solver, t0, t1, dt0, floor_eps)
    ts_req = None if saveat.ts is None else jnp.asarray(saveat.ts, dtype=R0.dtype)

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
    # yet, so `solve_adaptive` records their decisions in a solve of its own
    # and hands them over as ``replay``.
    record = controller.decides and replay is None and (record or adjoint.kind == "checkpointed")
    decisions = jnp.full((max_steps,), jnp.nan, R0.dtype) if record else None

    tracked = _tracked(saveat, solver, events)
    init = _adaptive_init(problem, solver, t0, t1, dt0, h0, f0, saveat, max_steps, decisions, events, tracked)
    init = _batched_together(init, (problem, t0, t1, h0, f0, controller))

    def cond(c: _Carry):
        return ~c.done

    def body(c: _Carry) -> _Carry:
        # Steps end exactly on each requested save time, so saved states carry
        # the solver's own accuracy (no interpolation error), then on t1.
        stop = t1 if ts_req is None else jnp.min(jnp.where(ts_req > c.t, ts_req, t1))
        remaining = stop - c.t
        h_proposed = controller.bound(ctrl_state, problem, solver, c.t, c.R, c.y, c.f, c.h)
        # A step within rounding of the remaining time ends on the stop (as
        # `step_count` snaps fixed steps): steps of a constant dt that add up
        # to a save time, up to the rounding of the times, would otherwise
        # leave a step of a few ulps.
        eps = jnp.finfo(remaining.dtype).eps
        snap = jnp.minimum(
            jnp.maximum(1e-9 * h_proposed, 16 * eps * jnp.maximum(jnp.abs(c.t), jnp.abs(stop))), 0.5 * h_proposed
        )
        clipped = h_proposed + snap >= remaining
        last = clipped & (stop >= t1)
        t_new = jnp.where(clipped, stop, c.t + jax.lax.stop_gradient(h_proposed))
        # Step by exactly the time the clock advances: far from t = 0, c.t + h
        # rounds, and a state advanced by h would drift from its time stamp.
        # (The proposal is a decision, out of the gradient; a step clipped to t1 or a
        # save time moves with it, so derivatives in t0, t1 and the save
        # times are those of the solve.)
        h = t_new - c.t
        if tracked:
            st, (Fu, Fy), node1 = solver.dense_step(problem, c.t, h, c.R, c.y, c.f, c.node)
        else:
            st = solver.step(problem, c.t, h, c.R, c.y, c.f)
        d = controller.adapt(
            ctrl_state,
            problem,
            solver,
            st,
            t=c.t,
            t_new=t_new,
            h=h,
            h_proposed=h_proposed,
            clipped=clipped,
            t1=t1,
            R=c.R,
            y=c.y,
            f=c.f,
            rejected_last=c.rejected_last,
        )
        accept, h_out, decisions = _decide(c, d, h, record, replay)

        def pick(a, b):
            return jax.tree_util.tree_map(lambda x, z: jnp.where(accept, x, z), a, b)

        # Where the step ends: its end, or where a terminating event stopped it.
        t_end, R_end, y_end = t_new, st.R, st.y
        ev, stopped, nan = c.ev, jnp.asarray(False), jnp.asarray(False)
        if events:
            interpolant = event_lib.Interpolant((Fu, Fy) if tracked else None, problem, solver, None, (st.R, st.y))
            ev, stopped, nan, (t_end, R_end, y_end) = _events_in_step(events, c, h, interpolant, st, t_new, accept)
        dense = c.dense
        if saveat.dense:
            dense = _dense_update(c.dense, c.num_accepted, accept, (c.t, h, c.R, c.y, Fu, Fy))
        saved, save_index = _save_update(saveat, c.saved, c.save_index, accept, t_end, R_end, y_end, max_steps)

        # A terminating event or a NaN condition ends the solve too.  (Applied
        # in place in the carry below, so that a solve without events
        # compiles to the program it always did.)
        def finished(done):
            return done | stopped | nan if events else done

        def coded(result):
            if not events:
                return result
            return jnp.where(stopped, RESULTS.event_occurred, jnp.where(nan, RESULTS.event_condition_nan, result))

        return _Carry(
            t=jnp.where(accept, t_end, c.t),
            h=h_out,
            R=jnp.where(accept, R_end, c.R),
            y=pick(y_end, c.y),
            f=pick(d.fsal, c.f),
            num_steps=c.num_steps + 1,
            num_accepted=c.num_accepted + accept.astype(jnp.int32),
            num_rejected=c.num_rejected + (~accept).astype(jnp.int32),
            rejected_last=~accept,
            done=finished((accept & last) | d.stuck | d.end),
            result=coded(jnp.where(d.stuck, RESULTS.dt_min_reached, c.result)).astype(jnp.int32),
            save_index=save_index,
            saved=saved,
            decisions=decisions,
            node=pick(node1, c.node) if tracked else None,
            ev=ev,
            dense=dense,
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
    return _adaptive_solution(
        final, solver, saveat, t0, (R0, y0), ts_req, max_steps, events, f0, dt0, tracked
    ), final.decisions


def _adaptive_init(
    problem, solver, t0, t1, dt0, h0, f0, saveat: SaveAt, max_steps: int, decisions, events, tracked
) -> _Carry:
    """The adaptive loop's first carry: at ``t0``, the first step ``h0`` and
    field ``f0`` (the controller's), empty buffers."""
    R0, y0 = problem.R0, problem.y0
    izero = jnp.asarray(0, dtype=jnp.int32)
    ev0 = event_lib.init(events, t0, R0, y0) if events else None
    node0 = solver.dense_node(problem, t0, R0, y0) if tracked else None
    dense0 = (
        _dense_init(problem, solver, t0, dt0 if dt0 is not None else h0, node0, max_steps) if saveat.dense else None
    )
    R, y = _moved_together((R0, y0))
    return _Carry(
        t=t0,
        h=h0,
        R=R,
        y=y,
        f=f0,
        num_steps=izero,
        num_accepted=izero,
        num_rejected=izero,
        rejected_last=jnp.asarray(False),
        done=(t1 <= t0) if ev0 is None else (t1 <= t0) | ev0.nan,
        result=jnp.asarray(RESULTS.successful, jnp.int32)
        if ev0 is None
        else jnp.where(ev0.nan, RESULTS.event_condition_nan, RESULTS.successful).astype(jnp.int32),
        save_index=izero,
        saved=_save_init(saveat, t0, R0, y0, max_steps),
        decisions=decisions,
        node=node0,
        ev=ev0,
        dense=dense0,
    )


def _batched_together(carry, inputs):
    """``carry``, each array leaf tied to the floating arrays of ``inputs`` by
    an identity that XLA removes (``select(p, x, x)``).  Under ``vmap`` the
    while loop's batching rule traces the body once more for every round in
    which a carry entry turns batched (the step count after the state, the
    result code after the step count); a carry batched from the start saves
    those rounds of tracing."""
    probes = [
        jnp.isnan(jnp.ravel(x)[0])
        for x in jax.tree_util.tree_leaves(inputs)
        if eqx.is_array(x) and x.size and jnp.issubdtype(x.dtype, jnp.inexact)
    ]
    if not probes:
        return carry
    p = functools.reduce(jnp.logical_or, probes)
    return jax.tree_util.tree_map(
        lambda x: jax.lax.select(jnp.broadcast_to(p, x.shape), x, x) if eqx.is_array(x) else x, carry
    )


@jax.custom_jvp
def _moved_together(state):
    """``state`` (a loop's initial ``(R, y)``) as it is.  Differentiated,
    each floating leaf's tangent is tied to all of theirs by an exact zero
    (the sum of an empty slice of each: no NaN or inf in one tangent can
    reach another, in either mode), so the attitude has one from the start
    whenever ``y`` has (omega0 perturbed, R0 not).  JAX's rules for
    differentiating and batching a loop find the carries that get tangents
    by tracing the body again until nothing changes; the attitude, which got
    one only after a step, cost a second pass of each rule over the whole
    body.  The compiled loop is the same."""
    return state


def _floating(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


@_moved_together.defjvp
def _moved_together_jvp(primals, tangents):
    (state,), (dstate,) = primals, tangents
    leaves = jax.tree_util.tree_leaves(state)
    pairs = zip(leaves, jax.tree_util.tree_leaves(dstate))
    zero = sum(jnp.sum(jnp.ravel(t)[:0], dtype=leaves[0].dtype) for x, t in pairs if _floating(x))
    return state, jax.tree_util.tree_map(lambda x, t: t + zero.astype(x.dtype) if _floating(x) else t, state, dstate)


def _decide(c: _Carry, d, h, record: bool, replay):
    """An attempt's ``(accept, next step, decisions)``: the controller's, or
    the recorded ones when the loop replays (see `_adaptive_loop`)."""
    accept = d.accept
    h_out = jax.lax.stop_gradient(jnp.where(d.stuck, h, d.h_next))
    decisions = c.decisions
    if record or replay is not None:
        # c.num_steps < max_steps inside the loop: one slot per attempt.
        recorded = (decisions if replay is None else replay)[c.num_steps]
        known = ~jnp.isnan(recorded)
        accept = jnp.where(known, ~jnp.signbit(recorded), accept)
        h_out = jnp.where(known, jnp.abs(recorded), h_out)
    if record:
        decisions = decisions.at[c.num_steps].set(jnp.where(accept, h_out, -h_out))
    return accept, h_out, decisions


def _events_in_step(events, c: _Carry, h, interpolant, st, t_new, accept):
    """The events of one attempt of size ``h`` with its
    `lierk._event.Interpolant`: ``(event state, stopped, NaN condition,
    (t, R, y) where the step ends)``, the stop of a terminating event or the
    step's end."""
    ev, stop = event_lib.process(events, c.ev, (c.t, h, c.R, c.y), accept, interpolant)
    stopped = stop.stop
    end = (
        jnp.where(stopped, stop.t, t_new),
        jnp.where(stopped, stop.R, st.R),
        jax.tree_util.tree_map(lambda a, b: jnp.where(stopped, a, b), stop.y, st.y),
    )
    return ev, stopped, ev.nan, end


def _adaptive_solution(
    final: _Carry, solver, saveat: SaveAt, t0, state0, ts_req, max_steps: int, events, f0, dt0, tracked: bool
) -> Solution:
    """The `Solution` from the adaptive loop's final carry; ``tracked``: its
    steps built their interpolants (dense output, events)."""
    finite = validation.all_finite((final.R, final.y))
    result = jnp.where(
        final.done & finite, final.result, jnp.where(finite, RESULTS.max_steps_reached, RESULTS.nonfinite)
    ).astype(jnp.int32)
    middle = None if final.saved is None else (final.saved[0], (final.saved[1], final.saved[2]))
    end = (final.t, (final.R, final.y)) if saveat.t1 and not saveat.steps else None
    ts, R, y, n_saved = _assemble(saveat, t0, state0, middle, end)
    # Rows of the buffers that were never written.
    if saveat.steps:
        n_saved = n_saved - (max_steps - final.save_index)
    if ts_req is not None:
        n_saved = n_saved - jnp.sum(ts_req > final.t)
    interpolation = None
    if saveat.dense:
        interpolation = DenseInterpolation(*final.dense, t0=t0, t1=final.t, n=final.num_accepted)
    records = event_lib.records(events, final.ev) if events else None
    stats = _adaptive_stats(solver, final, f0, dt0, tracked)
    return Solution(ts, R, y, jnp.asarray(n_saved), stats, result, interpolation=interpolation, events=records)


def _adaptive_stats(solver, final: _Carry, f0, dt0, tracked: bool) -> dict[str, Array]:
    """The adaptive loop's step and field-evaluation counts, from its final
    carry; ``tracked``: every attempt built its interpolant (dense output,
    events: `AbstractSolver.dense_fevals`)."""
    # The first stage is reused from the previous step when the controller
    # keeps the field at the new point (the FSAL stage or one extra
    # evaluation); one evaluation at t0, plus one inside the automatic
    # first-step estimate.
    # (With no field kept, an interpolant's node may serve it.)
    reuses_first_stage = solver.tableau.fsal if f0 is not None else tracked and solver.dense_serves_first_stage
    per_step, initial = solver.dense_fevals if tracked else (0, 0)
    fevals_per_attempt = solver.stages - (1 if reuses_first_stage else 0) + per_step
    fevals_setup = (0 if f0 is None else 1 if dt0 is not None else 2) + initial
    return {
        "num_steps": final.num_steps,
        "num_accepted_steps": final.num_accepted,
        "num_rejected_steps": final.num_rejected,
        "num_fevals": fevals_setup
        + final.num_steps * fevals_per_attempt
        + _rebuild_fevals(solver, final.ev, final.num_steps),
    }


def _dense_init(problem, solver, t0, h, node0, max_steps: int):
    """Empty `DenseInterpolation` buffers of ``max_steps`` rows: no step
    (``ts = inf``, ``hs = 0``), each at the initial state, so that ``t0`` is
    covered before any step is taken."""
    R0, y0 = problem.R0, problem.y0
    _, (Fu, Fy), _ = jax.eval_shape(lambda: solver.dense_step(problem, t0, h, R0, y0, None, node0))
    rows = lambda x: jnp.broadcast_to(x, (max_steps,) + jnp.shape(x))  # noqa: E731
    zeros = lambda s: jnp.zeros((max_steps,) + s.shape, s.dtype)  # noqa: E731
    return (
        jnp.full((max_steps,), jnp.inf, R0.dtype),
        jnp.zeros((max_steps,), R0.dtype),
        rows(R0),
        jax.tree_util.tree_map(rows, y0),
        zeros(Fu),
        jax.tree_util.tree_map(zeros, Fy),
    )


def _dense_update(buffers, i, accept, row):
    """The buffers with row ``i`` set to an accepted step's ``(t, h, R, y, Fu, Fy)``."""
    return jax.tree_util.tree_map(lambda b, v: b.at[i].set(jnp.where(accept, v, b[i])), buffers, row)
