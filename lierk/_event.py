"""Events: the times at which a condition of the motion crosses zero, found
on the dense output of each step, and optionally the end of the solve there.

An `Event` holds a scalar condition ``cond(t, R, y)``.  After every accepted
step `lierk.solve` reads the condition at the step's end (and, with
``samples > 1``, at ``samples - 1`` equally spaced points inside the step,
on its interpolant), and brackets each sign change between neighbouring
points.  Only in a step where some condition changed sign is the crossing
located: on the step's interpolant (`lierk._interpolation`: ``R(t_n +
theta h) = R_n exp(hat(u(theta)))``, or for the splittings a shortened step
of the method), by the Illinois method (regula falsi that halves a stale
end's value, and steps at least half its tolerance inside the bracket, as
Brent's method does) on ``theta``, to a few rounding errors of the step.
The time is then as accurate as the interpolant: the solver's own accuracy
(``tests/test_events.py``).

What that costs.  A Hermite interpolant (RKMK4, CF4, ...) is built from the
step's two ends (the field and its rate at each), only in a step where a
condition changed sign; a continuous extension (DOP853's) continues the
step's own stages and is built in every step, as is any interpolant when
an event samples inside the steps.  Under `jax.vmap` the members whose
condition changed sign are gathered and located as a small batch of their
own (`_crossings`), so a step where one member of many crossed costs about
one member's location.  Measured in ``benchmarks/results/event_cost.md``.

A crossing is a move from a strictly negative value to zero or above
(rising) or from a strictly positive value to zero or below (falling).  So a
condition that starts at zero (at ``t0``, or after an event stopped a solve
that is restarted from there) does not fire by leaving zero, only by
reaching it again; a condition that touches zero from above counts once, as
falling.  Crossings closer together than ``1/samples`` of a step (one step
by default) can be missed in pairs: the points read show no sign change.
Raise ``samples`` or bound the step (`lierk.Controller` ``dtmax``) for such
conditions.

The event time is differentiable with respect to everything the condition
and the motion depend on (initial state, inertia, the condition's own
parameters): by the implicit function theorem,
``d theta*/dp = -(dg/dp) / (dg/dtheta)`` at the root, where ``g(theta) =
cond(t_n + theta h, R(theta), y(theta))``.  The derivative is that of the
interpolant's crossing, so it carries the interpolant's accuracy; it is
infinite where the condition only touches zero.
"""

from __future__ import annotations

import functools
import types
from typing import Any, Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ._interpolation import interpolate

__all__ = ["Event", "EventRecord"]

# Illinois iterations at most; it converges superlinearly, and ~10 are usual.
_MAX_ITERATIONS = 100
# The fewest members of a batch whose crossings are located together.
_CROSSED_AT_ONCE = 8


class Event(eqx.Module):
    """A condition of the motion whose zero crossings `lierk.solve` finds
    (``solve(..., event=Event(...))``, one event or a sequence of them).

    Args:
        cond: ``cond(t, R, y) -> scalar``: a real function of the time (s),
            the attitude ``R`` ``(3, 3)`` (body -> space) and the extra state
            ``y`` (a rigid body's body momentum ``m`` (kg m^2/s), ``(3,)``).
            Its zero crossings are the events.  A function, or an
            `equinox.Module` whose array fields (a threshold, an axis) stay
            traced: changing them does not recompile, and the event time is
            differentiable with respect to them.  Ready-made conditions are in
            `lierk.conditions`.
        terminate: ``False`` (default, as SciPy): record every crossing and
            go on.  ``True``: end the solve at the first crossing.  An int
            ``n``: end it at the ``n``-th.  The solve then ends at the event
            time: the final saved state (``SaveAt(t1=True)``) is the state
            there, ``Solution.ts[-1]`` is that time and `Solution.result` is
            `RESULTS.event_occurred`.  Under `jax.vmap` each member stops at
            its own event.
        direction: ``0`` (default): both ways; ``1``: only rising crossings
            (from negative to positive); ``-1``: only falling ones.
        where: optional ``where(t, R, y) -> bool``, read at each crossing: a
            crossing counts only where it is true (the intermediate-axis
            flip of `lierk.conditions.flip` uses it to keep only crossings on
            an orbit that flips).
        max_count: how many crossing times (and states) to keep, per batch
            member: by default ``n`` for ``terminate=n``, 1 for ``True`` and
            64 otherwise.  `EventRecord.count` keeps counting past it.
        samples: sign checks per step (default 1: at the step's end, as
            SciPy and diffrax check): crossings closer than ``h/samples``
            apart can be missed in pairs.  Above 1, the condition is also
            read inside each step, on its interpolant, which every step then
            builds: in a fixed-step solve that costs about a step more per
            step (``benchmarks/results/event_cost.md``).

    Raises:
        ValueError: bad arguments here; in `lierk.solve`, a ``cond`` that
            does not return a real scalar (while tracing).  A ``cond`` that
            returns NaN ends the solve with `RESULTS.event_condition_nan`
            (an error with ``throw=True``).

    Example:
        >>> # stop when the body's x axis first points 30 degrees from space z
        >>> ev = lierk.Event(lambda t, R, y: R[2, 0] - jnp.cos(jnp.pi / 6), terminate=True)
        >>> sol = lierk.solve(body, lierk.DOP853(), 100.0, rtol=1e-10, event=ev)
        >>> sol.events.ts[0], sol.ts[-1]          # the same time
    """

    cond: Callable
    where: Callable | None
    terminate: bool | int = eqx.field(static=True)
    direction: int = eqx.field(static=True)
    max_count: int = eqx.field(static=True)
    samples: int = eqx.field(static=True)

    def __init__(
        self,
        cond: Callable,
        *,
        terminate: bool | int = False,
        direction: int = 0,
        where: Callable | None = None,
        max_count: int | None = None,
        samples: int = 1,
    ):
        if not callable(cond):
            raise ValueError(f"Event(cond): cond must be a function cond(t, R, y) -> scalar, got {cond!r}")
        if where is not None and not callable(where):
            raise ValueError(f"Event(where=...) must be a function where(t, R, y) -> bool or None, got {where!r}")
        if not (isinstance(terminate, bool) or (_is_int(terminate) and terminate >= 1)):
            raise ValueError(
                "Event(terminate=...) must be True, False or a positive int (stop at the n-th crossing), "
                f"got {terminate!r}"
            )
        if direction not in (-1, 0, 1) or isinstance(direction, bool):
            raise ValueError(f"Event(direction=...) must be 0 (both), 1 (rising) or -1 (falling), got {direction!r}")
        if max_count is None:
            max_count = int(terminate) if terminate else 64
        if not (_is_int(max_count) and max_count >= 1):
            raise ValueError(f"Event(max_count=...) must be a positive int, got {max_count!r}")
        if _is_int(terminate) and not isinstance(terminate, bool) and max_count < terminate:
            raise ValueError(
                f"Event(max_count={max_count}) must be at least terminate={terminate}, "
                "to hold the crossing that ends the solve"
            )
        if not (_is_int(samples) and samples >= 1):
            raise ValueError(f"Event(samples=...) must be a positive int, got {samples!r}")
        self.cond = cond
        self.where = where
        self.terminate = terminate if isinstance(terminate, bool) else int(terminate)
        self.direction = int(direction)
        self.max_count = int(max_count)
        self.samples = int(samples)

    @property
    def stop_at(self) -> int:
        """The crossing that ends the solve: 0 (none), 1, 2, ..."""
        return int(self.terminate)


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


class EventRecord(eqx.Module):
    """What a solve found for one `Event` (in `Solution.events`).  Leading
    batch axes appear in front under `jax.vmap`.

    Attributes:
        ts: ``(..., max_count)`` crossing times (s) in order, ``inf`` after
            the last.
        R: ``(..., max_count, 3, 3)`` attitudes there (NaN after the last).
        y: extra state there (leaves ``(..., max_count, ...)``), or None.
        count: ``(...)`` number of crossings (it may exceed ``max_count``;
            only the first ``max_count`` are kept).
        stopped: ``(...)`` whether this event ended the solve.
    """

    ts: Array
    R: Array
    y: Any
    count: Array
    stopped: Array


def with_closures_converted(events: tuple[Event, ...], t0, R0, y0) -> tuple[Event, ...]:
    """``events`` with each condition (and ``where``) written as a plain
    function closure-converted (`equinox.filter_closure_convert`) at the
    solve's argument types: values it closes over (a threshold being
    differentiated, say) become array leaves of the event, so the event
    time's derivative and `lierk.ForwardSensitivity` see them."""

    def convert(f):
        if isinstance(f, (types.FunctionType, functools.partial)):
            return eqx.filter_closure_convert(f, t0, R0, y0)
        return f

    return tuple(
        eqx.tree_at(lambda e: (e.cond, e.where), e, (convert(e.cond), convert(e.where)), is_leaf=lambda x: x is None)
        for e in events
    )


def events_tuple(event) -> tuple[Event, ...]:
    """``solve``'s ``event=`` argument as a tuple of `Event` (ValueError otherwise)."""
    events = (event,) if isinstance(event, Event) else event
    if not isinstance(events, (tuple, list)) or not events:
        raise ValueError(f"event= must be a lierk.Event or a non-empty sequence of them, got {event!r}")
    for i, e in enumerate(events):
        if not isinstance(e, Event):
            raise ValueError(f"event[{i}] must be a lierk.Event (wrap the condition: lierk.Event(cond)), got {e!r}")
    return tuple(events)


def records(event, state: "State") -> Any:
    """The `EventRecord` of each event from the final `State`, shaped like
    ``solve``'s ``event=`` argument."""
    out = tuple(
        EventRecord(state.ts[i], state.R[i], state.y[i], state.counts[i], state.stopped[i])
        for i in range(len(state.ts))
    )
    return out[0] if isinstance(event, Event) else out


class State(NamedTuple):
    """The events' part of a solve's loop carry."""

    g: tuple  # per event: cond at the current point (scalar)
    counts: Array  # (n_events,) crossings found so far
    ts: tuple  # per event: (max_count,) times, inf padded
    R: tuple  # per event: (max_count, 3, 3)
    y: tuple  # per event: pytree of (max_count, ...)
    stopped: Array  # (n_events,) which event ended the solve
    nan: Array  # a condition was NaN
    rebuilt: Array  # steps whose interpolant was built again to locate a crossing


def _check_output(out, what: str, i: int, floating: bool) -> None:
    shape, dtype = jnp.shape(out), jnp.result_type(out)
    if shape != ():
        raise ValueError(f"event[{i}]: {what}(t, R, y) must return a scalar, got shape {shape}")
    if floating and not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(
            f"event[{i}]: cond(t, R, y) must return a real (floating-point) scalar whose sign change marks the "
            f"event, got dtype {dtype}"
        )


def init(events: tuple[Event, ...], t0: Array, R0: Array, y0: Any) -> State:
    """The events' state at the start: each condition at ``t0`` and empty
    records.  Checks the conditions' output while tracing."""
    dtype = R0.dtype
    gs = []
    for i, ev in enumerate(events):
        _check_output(jax.eval_shape(ev.cond, t0, R0, y0), "cond", i, floating=True)
        if ev.where is not None:
            _check_output(jax.eval_shape(ev.where, t0, R0, y0), "where", i, floating=False)
        gs.append(jnp.asarray(ev.cond(t0, R0, y0), dtype))
    n = len(events)
    return State(
        g=tuple(gs),
        counts=jnp.zeros((n,), jnp.int32),
        ts=tuple(jnp.full((ev.max_count,), jnp.inf, dtype) for ev in events),
        R=tuple(jnp.full((ev.max_count, 3, 3), jnp.nan, dtype) for ev in events),
        y=tuple(
            jax.tree_util.tree_map(lambda x: jnp.full((ev.max_count,) + x.shape, jnp.nan, x.dtype), y0) for ev in events
        ),
        stopped=jnp.zeros((n,), bool),
        nan=jnp.any(jnp.isnan(jnp.stack(gs))),
        rebuilt=jnp.zeros((), jnp.int32),
    )


class Stop(NamedTuple):
    """Where a terminating event ended a step (valid where ``stop``)."""

    stop: Array
    t: Array
    R: Array
    y: Any


class Interpolant(eqx.Module):
    """One step's interpolant (`lierk._interpolation`), as the events need
    it: the coefficients ``(Fu, Fy)`` where the loop built them (dense
    output, or an event that samples inside its steps), else the solver and
    problem to build them apart (`AbstractSolver.dense_between`), which a
    solve does only in the steps where a condition changed sign.  ``partial``: the splittings'
    `lierk._interpolation.PartialStep`, or None.  ``end``: the state at the
    step's end ``(R1, y1)``."""

    coefficients: Any
    problem: Any
    solver: Any
    partial: Any
    end: Any

    @property
    def rebuilds(self) -> bool:
        """Whether calling it builds the coefficients apart (none given, and
        not a shortened step)."""
        return self.coefficients is None and self.partial is None

    def __call__(self, t, h, R, y) -> tuple:
        if self.coefficients is not None:
            return self.coefficients
        if self.partial is not None:
            return None, None  # a shortened step needs none
        return self.solver.dense_between(self.problem, t, h, R, y, *self.end)

    def full(self, step: tuple) -> tuple:
        """The step ``(t, h, R, y)`` with its interpolant, ``(t, h, R, y, Fu,
        Fy, partial)``, as `lierk._interpolation.interpolate` takes it."""
        return (*step, *self(*step), self.partial)


def _any_crossed(brackets) -> Array:
    """Whether some bracket of some event holds a crossing."""
    return jnp.any(jnp.stack([jnp.any(b[4]) for b in brackets]))


def samples_inside(events: tuple[Event, ...]) -> bool:
    """Whether some event samples its condition inside the steps
    (``samples > 1``): the loop then builds every step's interpolant."""
    return any(ev.samples > 1 for ev in events)


def process(
    events: tuple[Event, ...], state: State, step: tuple, active: Array, interpolant: Interpolant
) -> tuple[State, Stop]:
    """The events of one step.

    Args:
        events: the events.
        state: their state at the step's start.
        step: ``(t, h, R, y)``: the step's start (s), size (s) and start state.
        active: whether the step counts (accepted, and not past the end).
        interpolant: the step's `Interpolant`, which holds the state at the
            step's end (``end``).

    Returns:
        The state after the step (unchanged where not ``active``) and the
        `Stop` of a terminating event in it.

    The conditions are read at the step's end (and, for ``samples > 1``,
    inside it); the crossings are located, and ``where`` read at them, only
    in a step where some condition changed sign (`_crossings`).
    """
    t, h, R, y = step
    R1, y1 = interpolant.end
    dtype = R.dtype
    if samples_inside(events):
        interpolant = eqx.tree_at(
            lambda s: s.coefficients, interpolant, interpolant(*step), is_leaf=lambda x: x is None
        )
    interior = {}
    brackets, g_ends = [], []
    nan = state.nan
    for i, ev in enumerate(events):
        K = ev.samples
        if K not in interior:
            thetas = jnp.arange(1, K, dtype=dtype) / K
            full = interpolant.full(step) if K > 1 else None
            interior[K] = (thetas, jax.vmap(lambda th: _state(full, th))(thetas) if K > 1 else (None, None))
        thetas, (Rs, ys) = interior[K]
        g_end = jnp.asarray(ev.cond(t + h, R1, y1), dtype)
        if K > 1:
            gi = jax.vmap(lambda th, Ri, yi: jnp.asarray(ev.cond(t + th * h, Ri, yi), dtype))(thetas, Rs, ys)
            g = jnp.concatenate([state.g[i][None], gi, g_end[None]])
            # The states at each bracket's far end; the root finder carries
            # them along, so the interpolant is not evaluated again at the
            # roots (a splitting's is a step of the method: a large program,
            # and a step's cost per bracket).
            ends = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), (Rs, ys), (R1, y1))
        else:
            g = jnp.stack([state.g[i], g_end])
            ends = jax.tree_util.tree_map(lambda b: b[None], (R1, y1))
        grid = jnp.concatenate([jnp.zeros((1,), dtype), thetas, jnp.ones((1,), dtype)])
        glo, ghi = g[:-1], g[1:]
        up, down = (glo < 0) & (ghi >= 0), (glo > 0) & (ghi <= 0)
        cross = up | down if ev.direction == 0 else up if ev.direction == 1 else down
        nan = nan | (active & jnp.any(jnp.isnan(g)))
        brackets.append((grid[:-1], grid[1:], glo, ghi, active & cross, ends))
        g_ends.append(g_end)

    brackets = tuple(brackets)
    found, stopped = _crossings(events, state.counts, step, interpolant, brackets)

    # Where the solve ended: at the crossing of the event that ended it.
    terminates = any(ev.stop_at for ev in events)
    t_stop, stop_R, stop_y = t + h, R1, y1
    for i, (ev, (keep, tr, Rr, yr)) in enumerate(zip(events, found)):
        if ev.stop_at:
            j = jnp.argmax(keep & (state.counts[i] + jnp.cumsum(keep, dtype=jnp.int32) == ev.stop_at))
            t_stop = jnp.where(stopped[i], tr[j], t_stop)
            stop_R = jnp.where(stopped[i], Rr[j], stop_R)
            stop_y = jax.tree_util.tree_map(lambda a, b: jnp.where(stopped[i], a[j], b), yr, stop_y)
    # (Without a terminating event nothing stops: a constant, so that the
    # loop's choices between the step's end and the event's fold away.)
    stop = Stop(jnp.any(stopped) if terminates else jnp.asarray(False), t_stop, stop_R, stop_y)

    # The records are written here, in place: carried through a loop around
    # the location, they were copied whole in every step (64 rows: 5x the
    # step's time).
    counts, ts_b, R_b, y_b = [], [], [], []
    for i, (ev, (keep, tr, Rr, yr)) in enumerate(zip(events, found)):
        if keep.shape[0] == 1:
            # One bracket, one row at most: read and write it in place.
            n = state.counts[i]
            pos, write = jnp.minimum(n, ev.max_count - 1), keep[0] & (n < ev.max_count)

            def put(buf, v):
                return buf.at[pos].set(jnp.where(write, v[0], buf[pos]))
        else:
            pos = state.counts[i] + jnp.cumsum(keep, dtype=jnp.int32) - 1
            pos = jnp.where(keep, pos, ev.max_count)  # out of range: dropped

            def put(buf, v):
                return buf.at[pos].set(v, mode="drop")

        ts_b.append(put(state.ts[i], tr))
        R_b.append(put(state.R[i], Rr))
        y_b.append(jax.tree_util.tree_map(put, state.y[i], yr))
        counts.append(state.counts[i] + jnp.sum(keep, dtype=jnp.int32))
    new = State(
        g=tuple(jnp.where(active, g_end, g0) for g_end, g0 in zip(g_ends, state.g)),
        counts=jnp.stack(counts),
        ts=tuple(ts_b),
        R=tuple(R_b),
        y=tuple(y_b),
        stopped=state.stopped | stopped if terminates else state.stopped,
        nan=nan,
        rebuilt=state.rebuilt + _any_crossed(brackets).astype(jnp.int32) if interpolant.rebuilds else state.rebuilt,
    )
    return new, stop


@eqx.filter_custom_jvp
def _crossings(events, counts, step, interpolant, brackets):
    """`process` past the sign checks: `_found`, computed only where some
    bracket is valid; elsewhere no crossing (zeros, and ``keep`` false).
    One body computes it in a conditional, in a step where it crossed; a
    batch under `jax.vmap` computes it for the members that crossed only, a
    few at a time (`_crossed_members`).  Its derivative is `_found`'s,
    computed in every step."""
    args = (events, counts, step, interpolant, brackets)
    dynamic, static = eqx.partition(args, eqx.is_array)
    # "No crossing": zeros, and ``keep`` false.
    none = lambda lead=(): jax.tree_util.tree_map(lambda s: jnp.zeros(lead + s.shape, s.dtype), shapes)  # noqa: E731

    def crossed(d):
        return _any_crossed(eqx.combine(d, static)[-1])

    # `custom_vmap` refuses a function whose constants an enclosing
    # transformation batched: its constants (a tableau, a condition's
    # arrays) become explicit arguments of a traced jaxpr.
    closed, shapes = jax.make_jaxpr(lambda d: _found(*eqx.combine(d, static)), return_shape=True)(dynamic)
    _, out_tree = jax.tree_util.tree_flatten(shapes)

    def found(consts, d):
        return jax.tree_util.tree_unflatten(
            out_tree, jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree_util.tree_leaves(d))
        )

    @jax.custom_batching.custom_vmap
    def one(consts, d):
        return jax.lax.cond(crossed(d), found, lambda *_: none(), consts, d)

    @one.def_vmap
    def batch(axis_size, in_batched, consts, d):
        out = _crossed_members(crossed, found, (consts, d), tuple(in_batched), axis_size, none((axis_size,)))
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return one(tuple(closed.consts), dynamic)


def _crossed_members(crossed, found, args, batched, size: int, out):
    """``found(*args)`` for the members of a batch of ``size`` (``args``
    batched where ``batched``) where ``crossed(args[-1])``, written into
    ``out`` (the batch's "no crossing"): the members that crossed are
    gathered, `_CROSSED_AT_ONCE` or ``size / 64`` at a time, and computed as
    a small batch, so that a step where one member of thousands crossed
    costs about one member's location, not the batch's."""
    axes = jax.tree_util.tree_map(lambda b: 0 if b else None, batched)
    if any(jax.tree_util.tree_leaves(batched[-1])):
        need = jax.vmap(crossed, in_axes=(axes[-1],))(args[-1])
    else:
        need = jnp.broadcast_to(crossed(args[-1]), (size,))
    chunk = min(size, max(_CROSSED_AT_ONCE, size // 64))

    def body(carry):
        need, out = carry
        (idx,) = jnp.nonzero(need, size=chunk, fill_value=0)
        real = need[idx] & (jnp.arange(chunk) < jnp.sum(need))
        rows = jnp.where(real, idx, size)  # out of range: dropped
        picked = jax.tree_util.tree_map(lambda x, b: x[idx] if b else x, args, batched)
        res = jax.vmap(found, in_axes=axes)(*picked)
        out = jax.tree_util.tree_map(lambda o, r: o.at[rows].set(r, mode="drop"), out, res)
        return need.at[rows].set(False, mode="drop"), out

    def chunks(need, out):
        return jax.lax.while_loop(lambda c: jnp.any(c[0]), body, (need, out))[1]

    # A conditional on the whole batch: in the steps where no member crossed
    # (most of them) the loop is not entered, and its operands not copied.
    return jax.lax.cond(jnp.any(need), chunks, lambda need, out: out, need, out)


@_crossings.def_jvp
def _crossings_jvp(primals, tangents):
    return eqx.filter_jvp(_found, primals, tangents)


def _found(events, counts, step, interpolant, brackets):
    """The crossings in one step's ``brackets`` (per event ``(lo, hi, g(lo),
    g(hi), valid, ends)``), located and filtered by ``where``, given each
    event's ``counts`` so far: per event ``(keep, t*, R*, y*)`` (``keep``:
    the crossings to record), and which event ended the solve
    ``(n_events,)``."""
    t, h = step[:2]
    dtype = step[2].dtype
    conds = tuple(ev.cond for ev in events)
    located = _located(conds, step, interpolant, brackets)
    found = []  # per event: (valid, t*, R*, y*)
    for ev, (theta, Rr, yr), bracket in zip(events, located, brackets):
        valid = bracket[4]
        tr = t + theta * h
        if ev.where is not None:
            valid = valid & jax.vmap(ev.where)(tr, Rr, yr)
        found.append((valid, tr, Rr, yr))
    # The first crossing that ends the solve, over every event.
    inf = jnp.asarray(jnp.inf, dtype)
    firsts = []
    for i, (ev, (valid, tr, Rr, yr)) in enumerate(zip(events, found)):
        if ev.stop_at:
            ends = valid & (counts[i] + jnp.cumsum(valid, dtype=jnp.int32) == ev.stop_at)
            firsts.append(jnp.where(jnp.any(ends), tr[jnp.argmax(ends)], inf))
        else:
            firsts.append(inf)
    t_stop = inf
    stopped = []
    for tf in firsts:
        stopped.append(tf < t_stop)
        t_stop = jnp.minimum(t_stop, tf)
    # Only the first event to reach t_stop ended the solve.
    stopped = jnp.stack(stopped)
    stopped = stopped & (jnp.cumsum(stopped) == jnp.sum(stopped))  # the last "earlier" is the earliest
    kept = tuple((valid & (tr <= t_stop), tr, Rr, yr) for valid, tr, Rr, yr in found)
    return kept, stopped


def _state(step, theta):
    """``(R, y)`` on the step's interpolant at ``theta`` (a scalar), ``step``
    being ``(t, h, R, y, Fu, Fy, partial)``."""
    return interpolate(step[:6], theta, step[6])


def _g(cond, step, theta):
    """The condition along the step's interpolant at ``theta`` (a scalar)."""
    t, h, R = step[:3]
    Rt, yt = _state(step, theta)
    return jnp.asarray(cond(t + theta * h, Rt, yt), R.dtype)


def _illinois(cond, step, bracket):
    """Each bracketed crossing's ``(theta, R, y)``: ``theta`` the end of the
    final bracket on the far side of the crossing (where the condition has
    changed sign), or ``lo`` where not ``valid``; ``(R, y)`` the interpolant's
    state at that far end (at the initial ``hi`` where not ``valid``)."""
    lo, hi, glo, ghi, valid, ends = bracket
    tol = 4 * jnp.finfo(lo.dtype).eps
    t, h = step[:2]

    def g(theta):
        Rt, yt = jax.vmap(lambda th: _state(step, th))(theta)
        return jax.vmap(lambda th, Ri, yi: jnp.asarray(cond(t + th * h, Ri, yi), lo.dtype))(theta, Rt, yt), (Rt, yt)

    def running(c):
        a, b, ga, gb, _, it, _ = c
        return valid & (gb != 0) & (b - a > tol) & ~jnp.isnan(gb) & (it < _MAX_ITERATIONS)

    def body(c):
        a, b, ga, gb, side, it, at_b = c
        run = running(c)
        c_ = a - ga * (b - a) / jnp.where(gb != ga, gb - ga, 1.0)
        # At least half the tolerance inside the bracket, as Brent's method
        # steps.  Once one end is the root to rounding, the estimate rounds
        # to that end; a step of half the tolerance then closes the bracket,
        # where halving it from the far end took 30 and more passes.
        c_ = jnp.clip(jnp.where(jnp.isfinite(c_), c_, 0.5 * (a + b)), a + 0.5 * tol, b - 0.5 * tol)
        gc, at_c = g(c_)
        move_a = gc * ga > 0  # same sign as the near end: the root is in (c, b]
        a2, ga2 = jnp.where(move_a, c_, a), jnp.where(move_a, gc, ga)
        b2, gb2 = jnp.where(move_a, b, c_), jnp.where(move_a, gb, gc)
        # Illinois: an end kept twice in a row has its value halved.
        gb2 = jnp.where(move_a & (side < 0), 0.5 * gb2, gb2)
        ga2 = jnp.where(~move_a & (side > 0), 0.5 * ga2, ga2)
        side2 = jnp.where(move_a, -1, 1)
        pick = lambda new, old: jnp.where(run, new, old)  # noqa: E731
        moved_b = run & ~move_a
        at_b2 = jax.tree_util.tree_map(
            lambda new, old: jnp.where(moved_b.reshape((-1,) + (1,) * (new.ndim - 1)), new, old), at_c, at_b
        )
        return (
            pick(a2, a),
            pick(b2, b),
            pick(ga2, ga),
            pick(gb2, gb),
            pick(side2, side),
            it + run.astype(it.dtype),
            at_b2,
        )

    init = (lo, hi, glo, ghi, jnp.zeros(lo.shape, jnp.int32), jnp.zeros(lo.shape, jnp.int32), ends)
    _, b, _, _, _, _, (Rb, yb) = jax.lax.while_loop(lambda c: jnp.any(running(c)), body, init)
    return jnp.where(valid, b, lo), Rb, yb


@eqx.filter_custom_jvp
def _located(conds, step, interpolant, brackets):
    """Per event, `_illinois`'s ``(theta, R, y)`` for its ``brackets``, with
    the step ``(t, h, R, y)`` and its `Interpolant`."""
    full = interpolant.full(step)
    return tuple(_illinois(c, full, b) for c, b in zip(conds, brackets))


@_located.def_jvp
def _located_jvp(primals, tangents):
    # The implicit function theorem at each root: d theta = -(dg/dp . dp) / (dg/dtheta);
    # the states there move with the root and with the interpolant.
    conds, step, interpolant, brackets = primals
    t_conds, t_step, t_interpolant, _ = tangents
    dyn, static = eqx.partition((conds, step, interpolant), eqx.is_inexact_array)
    t_dyn = _materialised(dyn, (t_conds, t_step, t_interpolant))

    def full(d):
        # The conditions and the step with its interpolant's coefficients,
        # built once here (with their tangents) for every root.
        cs, st, interp = eqx.combine(d, static)
        return cs, interp.full(st)

    (cs, st), (t_cs, t_st) = eqx.filter_jvp(full, (dyn,), (t_dyn,))
    located = tuple(_illinois(c, st, b) for c, b in zip(cs, brackets))
    out_tangents = []
    for i, ((theta, Rr, yr), bracket) in enumerate(zip(located, brackets)):
        cdyn, cstatic = eqx.partition((cs[i], st), eqx.is_inexact_array)
        out_tangents.append(_root_tangents(cdyn, cstatic, _materialised(cdyn, (t_cs[i], t_st)), theta, bracket[4]))
    return located, tuple(out_tangents)


def _materialised(dyn, tangents):
    """``tangents`` for the arrays ``dyn`` (None elsewhere), with symbolic
    zeros (None) made zero arrays."""
    return jax.tree_util.tree_map(
        lambda p, t: p if p is None else jnp.zeros_like(p) if t is None else t,
        dyn,
        tangents,
        is_leaf=lambda x: x is None,
    )


def _root_tangents(dyn, static, t_dyn, theta, valid):
    """``(d theta, dR, dy)`` at the roots ``theta`` of one condition, for
    ``dyn`` (the condition and step's arrays) moving along ``t_dyn``."""

    def g(th, d):
        c, s = eqx.combine(d, static)
        return _g(c, s, th)

    def rates(th):
        slope = jax.jvp(lambda x: g(x, dyn), (th,), (jnp.ones_like(th),))[1]
        change = jax.jvp(lambda d: g(th, d), (dyn,), (t_dyn,))[1]
        return slope, change

    slope, change = jax.vmap(rates)(theta)
    ok = valid & (slope != 0)
    d_theta = jnp.where(ok, -change / jnp.where(ok, slope, 1.0), 0.0)

    def state(th, d):
        return _state(eqx.combine(d, static)[1], th)

    d_state = jax.vmap(lambda th, dth: jax.jvp(state, (th, dyn), (dth, t_dyn))[1])(theta, d_theta)
    return (d_theta, *d_state)
