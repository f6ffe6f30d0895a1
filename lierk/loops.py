"""The two loops behind `lierk.solve`, and the saving they share.

- `solve_fixed`: a static number of fixed steps through `lax.scan`
  (checkpointed in blocks for reverse mode).  It saves by structure: an outer
  scan over chunks of ``SaveAt(steps=k)`` steps stacks the chunk ends.
  `solve_fixed_counted` takes the same steps with a traced ``k`` (one
  compilation for every step size, as `lierk.accuracy` needs).
- `solve_adaptive`: a while loop driven by a step-size controller
  (`lierk.controller`: `Controller` for embedded pairs, `ConstantStep` for a
  fixed step whose count is not static), differentiated as its adjoint says
  (`lierk.adjoint`).  It saves into buffers (`_save_init`, `_save_update`).

Both end with `_assemble`: the saved times and states, from ``t0`` to the end,
and the `Solution`.  Values (t0, t1, dt, tolerances, inertia, omega0) are
traced, so eager calls with new values reuse the compilation, like diffrax's
diffeqsolve.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import validation
from .adjoint import ForwardMode
from .controller import AbstractStepController
from .solution import RESULTS, SaveAt, Solution

__all__ = ["solve_fixed", "solve_fixed_counted", "solve_adaptive", "num_steps", "step_count", "frozen"]

# Fixed-step runs of at least this many steps squared (256) are checkpointed in
# blocks for reverse mode (`solve_fixed`).
_CHECKPOINT_BLOCK_MIN = 16


def frozen(tree):
    """A pytree (a problem, a controller, times) with its array leaves out of
    the gradient: an error estimate's finer solve is a diagnostic and would
    double the cost of a backward pass, and DirectAdjoint's deciding solve is
    not differentiated at all."""
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree)


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
    tol = xp.minimum(xp.maximum(1e-9 * xp.minimum(1.0, x), 16 * eps * (x + xp.maximum(xp.abs(t0), xp.abs(t1)) / dt)), 0.5)
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


class _FixedSteps(NamedTuple):
    """The steps of a fixed-step run (`_fixed_steps`)."""

    one: Any  # the scan body: ((R, y), k, taken) -> (next carry, None)
    time: Any  # k -> the time (s) at which step k starts (t1 past the end)
    needed: Array  # steps that reach t1
    count: Array  # steps taken: needed, at most n


def _fixed_steps(problem, solver, t0, t1, dt, n) -> _FixedSteps:
    """Steps of ``dt`` from ``t0``, at most ``n`` (a Python int, or traced),
    the last shortened to end exactly at ``t1``; steps past ``t1`` are exact
    no-ops."""
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

    return _FixedSteps(one, time, needed, count)


def _fixed_solution(solver, saveat: SaveAt, t0, state0, middle, end, state, taken, needed, n) -> Solution:
    """The `Solution` of a fixed-step run of at most ``n`` steps that needed
    ``needed``: what it saved (`_assemble`), its counts, and its result."""
    ts, R, y, n_saved = _assemble(saveat, t0, state0, middle, end)
    result = jnp.where(needed <= n, RESULTS.successful, RESULTS.max_steps_reached)
    result = jnp.where(validation.all_finite(state), result, RESULTS.nonfinite)
    stats = {
        "num_steps": taken,
        "num_accepted_steps": taken,
        "num_rejected_steps": jnp.zeros_like(taken),
        "num_fevals": taken * solver.stages,
    }
    return Solution(ts, R, y, jnp.asarray(n_saved), stats, result)


@eqx.filter_jit
def solve_fixed(problem, solver, t0, t1, dt, saveat: SaveAt, n: int) -> Solution:
    """``n`` (static) fixed steps of ``dt`` from ``t0``, the last shortened to
    end exactly at ``t1``; steps past ``t1`` are exact no-ops."""
    one, time, needed, _ = _fixed_steps(problem, solver, t0, t1, dt, n)

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

    state0 = (problem.R0, problem.y0)
    every = saveat.every
    n_chunks, rem = divmod(n, every) if every else (0, n)

    def chunk(carry, _):
        carry = steps(carry, every)
        return carry, carry[0]

    carry = (state0, jnp.asarray(0), jnp.asarray(0))
    middle = None
    if n_chunks:
        carry, saved = jax.lax.scan(chunk, carry, None, length=n_chunks)
        middle = (time((jnp.arange(n_chunks) + 1) * every), saved)
    if rem:
        carry = steps(carry, rem)
    state, _, taken = carry
    # (The last chunk's end is t1 already when the chunks fill the run.)
    end = (time(jnp.asarray(n)), state) if saveat.t1 and (rem or not n_chunks) else None
    return _fixed_solution(solver, saveat, t0, state0, middle, end, state, taken, needed, n)


@eqx.filter_jit
def solve_fixed_counted(problem, solver, t0, t1, dt, every, n_saves: int) -> Solution:
    """`solve_fixed` saving ``t0`` and every ``every``-th step
    (``SaveAt(t0=True, steps=every)``) with ``every`` traced: ``n_saves``
    (static) states after ``t0``, at most ``n_saves * every`` steps.

    One compilation serves every step count, and a run costs its own steps
    (no padding): each save interval is a loop whose trip count is
    ``every``.  The steps, and so the numbers, are `solve_fixed`'s, and a
    run takes the same time to within a few percent.  Forward mode only
    (a loop of traced length cannot be reverse-differentiated).
    """
    n = (n_saves * every).astype(dt.dtype)  # (compared with step counts, which are floats)
    one, time, needed, _ = _fixed_steps(problem, solver, t0, t1, dt, n)

    def chunk(carry, _):
        carry = jax.lax.fori_loop(0, every, lambda _, c: one(c, None)[0], carry)
        return carry, carry[0]

    state0 = (problem.R0, problem.y0)
    carry, saved = jax.lax.scan(chunk, (state0, jnp.asarray(0), jnp.asarray(0)), None, length=n_saves)
    middle = (time((jnp.arange(n_saves) + 1) * every), saved)
    state, _, taken = carry
    return _fixed_solution(solver, SaveAt(t0=True, steps=1), t0, state0, middle, None, state, taken, needed, n)


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


@eqx.filter_jit
def solve_adaptive(
    problem, solver, t0, t1, dt0, saveat: SaveAt, max_steps: int, controller: AbstractStepController, adjoint,
    floor_eps: float = 50.0,
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
            frozen(problem), solver, frozen(t0), frozen(t1), frozen(dt0), saveat, max_steps, frozen(controller),
            ForwardMode(), floor_eps, record=True,
        )
    return _adaptive_loop(problem, solver, t0, t1, dt0, saveat, max_steps, controller, adjoint, floor_eps, replay=replay)[0]


def _adaptive_loop(
    problem, solver, t0, t1, dt0, saveat: SaveAt, max_steps: int, controller: AbstractStepController, adjoint,
    floor_eps: float, record: bool = False, replay: Array | None = None,
) -> tuple[Solution, Array | None]:
    """The while loop: ``(Solution, decisions)``.  ``decisions``
    ``(max_steps,)`` holds each attempt's next step, negative if the attempt
    was rejected (NaN after the last attempt), when they are recorded: for a
    controller that decides, always with the checkpointed adjoint, and when
    ``record``.  ``replay`` (decisions recorded by an earlier solve of the same
    problem) makes the loop take those decisions instead of its own."""
    R0, y0 = problem.R0, problem.y0
    ctrl_state, h0, f0 = controller.init(problem, solver, t0, t1, dt0, floor_eps)
    izero = jnp.asarray(0, dtype=jnp.int32)
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
        saved=_save_init(saveat, t0, R0, y0, max_steps),
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
        d = controller.adapt(
            ctrl_state, problem, solver, st, t=c.t, t_new=t_new, h=h, h_proposed=c.h, clipped=clipped, t1=t1, y=c.y,
            f=c.f, rejected_last=c.rejected_last,
        )
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

        def pick(a, b):
            return jax.tree_util.tree_map(lambda x, z: jnp.where(accept, x, z), a, b)

        saved, save_index = _save_update(saveat, c.saved, c.save_index, accept, t_new, st.R, st.y, max_steps)
        return _Carry(
            t=jnp.where(accept, t_new, c.t),
            h=h_out,
            R=jnp.where(accept, st.R, c.R),
            y=pick(st.y, c.y),
            f=pick(d.fsal, c.f),
            num_steps=c.num_steps + 1,
            num_accepted=c.num_accepted + accept.astype(jnp.int32),
            num_rejected=c.num_rejected + (~accept).astype(jnp.int32),
            rejected_last=~accept,
            done=(accept & last) | d.stuck | d.end,
            result=jnp.where(d.stuck, RESULTS.dt_min_reached, c.result).astype(jnp.int32),
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
    finite = validation.all_finite((final.R, final.y))
    result = jnp.where(
        final.done & finite, final.result, jnp.where(finite, RESULTS.max_steps_reached, RESULTS.nonfinite)
    ).astype(jnp.int32)
    middle = None if final.saved is None else (final.saved[0], (final.saved[1], final.saved[2]))
    end = (final.t, (final.R, final.y)) if saveat.t1 and not saveat.steps else None
    ts, R, y, n_saved = _assemble(saveat, t0, (R0, y0), middle, end)
    # Rows of the buffers that were never written.
    if saveat.steps:
        n_saved = n_saved - (max_steps - final.save_index)
    if ts_req is not None:
        n_saved = n_saved - jnp.sum(ts_req > final.t)
    return Solution(ts, R, y, jnp.asarray(n_saved), _adaptive_stats(solver, final, f0, dt0), result), final.decisions


def _adaptive_stats(solver, final: _Carry, f0, dt0) -> dict[str, Array]:
    """The adaptive loop's step and field-evaluation counts, from its final carry."""
    # The first stage is reused from the previous step when the controller
    # keeps the field at the new point (the FSAL stage or one extra
    # evaluation); one evaluation at t0, plus one inside the automatic
    # first-step estimate.
    reuses_first_stage = f0 is not None and solver.tableau.fsal
    fevals_per_attempt = solver.stages - (1 if reuses_first_stage else 0)
    fevals_setup = 0 if f0 is None else 1 if dt0 is not None else 2
    return {
        "num_steps": final.num_steps,
        "num_accepted_steps": final.num_accepted,
        "num_rejected_steps": final.num_rejected,
        "num_fevals": fevals_setup + final.num_steps * fevals_per_attempt,
    }
