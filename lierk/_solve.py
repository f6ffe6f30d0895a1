"""`solve`: validate the call, then dispatch to a loop (`lierk._loops`) and,
when asked, to a global-error estimate (`lierk._global_error`)."""

from __future__ import annotations

import functools
from typing import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import _global_error as global_error
from . import _validation as validation
from ._adjoint import AbstractAdjoint, ForwardSensitivity, _may_capture_tracer
from ._controller import AbstractStepController, ConstantStep, Controller, frozen
from ._event import Event, events_tuple, with_closures_converted
from ._loops import _batched_together, num_steps, solve_adaptive, solve_fixed, solve_fixed_at
from ._problems import AbstractProblem
from ._programs import Program, in_form
from ._solution import RESULTS, SaveAt, Solution, raise_if_failed
from ._solvers.base import AbstractSolver

__all__ = ["solve", "num_steps"]


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
    controller: AbstractStepController | None = None,
    throw: bool = True,
    adjoint: AbstractAdjoint | None = None,
    estimate_error: bool = False,
    target_error: ArrayLike | None = None,
    event: Event | Sequence[Event] | None = None,
) -> Solution:
    """Integrate ``problem`` from ``t0`` to ``t1`` (s) with ``solver``.

    Fixed steps (``dt=``): ``ceil((t1 - t0)/dt)`` steps through `lax.scan`, the
    last one shortened to end exactly at ``t1``.  When ``t0``, ``t1`` or ``dt``
    is traced (for example a swept ``dt`` under `vmap`), the step count
    cannot be read and ``max_steps`` (a Python int) must give it; steps past
    ``t1`` are exact no-ops, skipped in blocks of 16 and more (a generous
    bound costs next to nothing, but under vmap with a batched end every
    step runs), and falling short of ``t1`` is reported as
    `RESULTS.max_steps_reached`.  With ``saveat=SaveAt(ts=...)`` the steps
    end on every save time instead (``ceil(gap/dt)`` steps per gap, the last
    shortened), counted at run time: one compilation for every ``dt`` and
    ``ts``, and a run costs its own steps; ``max_steps`` is then optional, a
    bound on the whole run's steps.  Its loops have traced lengths, which
    forward mode goes through; reverse mode (`jax.grad`) goes through
    `ForwardSensitivity`, the default adjoint, for up to its ``max_inputs``
    (6) perturbed input scalars, and otherwise fails: for reverse mode with
    respect to more inputs (an inertia, an attitude) or with another adjoint,
    save with ``SaveAt(steps=k)``.

    Adaptive steps (``rtol=``/``atol=`` or ``controller=``, with an embedded
    pair such as `RKF45`, `DP54` or `DOP853`): a while loop with the error
    measured in the Lie algebra (see `lierk._controller`).  ``max_steps``
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
    batch member, with traced settings so nothing recompiles.  It solves at
    ever finer settings, one at a time, and returns a solution with twice
    its distance to a finer, confirming solve as `Solution.error_estimate`
    (tolerances 100x tighter for DOP853, 18x for DP54 and RKF45; 2/3 of the
    step for fixed steps of order 3 and up, 0.58 of it for order 2 and 1/3
    for order 1, at least 3x more accurate): an upper bound on the error
    whenever the confirming solve is at least twice as accurate, and never
    below 30 eps per radian the body has turned (rounding that every solve
    shares).
    Success (result 0) means that estimate is at most ``eps`` at every saved
    time; no success above ``eps`` was found on random bodies with inertia
    ratios up to 1:100 and spins up to 1000 rad/s, heavy tops,
    ``SaveAt(ts=...)`` and float32 (``tests/test_accuracy.py``), and the
    error is then typically eps/30 to eps/2.  It takes 2 solves for most
    members, 3 or 4 for some (at most 8); under vmap the batch runs as many
    as its hardest member.  ``stats["num_solves"]`` counts every solve,
    ``stats["dt"]``/``stats["rtol"]`` give the setting of the solution
    returned, and the other stats are that solve's.  Adaptive tolerances
    stay where the local error test is not floored (in float32, rtol at
    least 9e-6 for DOP853, 4.5e-5 for DP54, 9e-5 for RKF45).  A target that
    cannot be met (below rounding, or needing more than ``max_steps``,
    default 100000 per solve) ends with `RESULTS.target_error_not_reached`
    and the most accurate solution that has an estimate: the finer solve
    of the pair with the smallest estimate, with that estimate (twice their
    gap also bounds the finer one's error, whenever it is the more accurate
    of the two; inf if no pair finished; if the first solve runs out of
    ``max_steps``, `RESULTS.max_steps_reached`).  Not differentiable: to
    differentiate, solve again at the chosen setting.

    Dense output (``saveat=SaveAt(dense=True)``): every step's interpolant
    on SO(3) is kept, and `Solution.evaluate` gives the state at any time
    (`lierk._interpolation`; memory O(steps)).

    Events (``event=lierk.Event(cond, ...)``, or a sequence): the zero
    crossings of ``cond(t, R, y)`` are found on each step's interpolant, to
    the solver's accuracy, and come back in `Solution.events`; a terminating
    event ends the solve at its time (`lierk._event`).

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
        controller: full control of step-size selection: a `Controller`,
            `ConstantStep()` (steps of ``dt0``, any solver), or a
            `AbstractStepController` of your own.
        throw: raise on failure (default).  With ``throw=False`` the partial
            `Solution` comes back with its `Solution.result` code, per batch
            member under `vmap`.
        adjoint: how the solve is differentiated (`lierk._adjoint`); default
            `ForwardSensitivity()`: forward and reverse mode at the cost of
            the Jacobian in the differentiated inputs.
        estimate_error: fill `Solution.error_estimate`.
        target_error: the attitude error wanted at every saved time
            (Frobenius norm, dimensionless), ``> 0``.
        event: a `lierk.Event` or a sequence of them.  `Solution.events` is
            then an `EventRecord` (a tuple of them for a sequence).

    Returns:
        A `Solution`.

    Raises:
        ValueError: bad structure or values known while tracing.  Traced
            values that are bad raise at run time (`eqx.error_if`).
    """
    saveat = _check_call(problem, solver, saveat, max_steps, estimate_error)
    events = _check_events(event, saveat, estimate_error, target_error)
    dtype = problem.R0.dtype
    # The arguments are checked here, on the host where their values are
    # known (NumPy: nothing is compiled for it), and the solve itself, with
    # everything it computes from them, is one compiled program (`_program`):
    # a first call compiles that program and nothing else, where each array
    # operation around the loop used to be a small compilation of its own
    # (61 for a heavy top), and a new value of any number reruns it.
    t0, t1 = _check_times(t0, t1, dtype)
    if events:
        events = with_closures_converted(events, t0, problem.R0, problem.y0)
    saveat = _check_save_times(saveat, t0, t1, dtype)
    eps = n = None
    if target_error is not None:
        given = [
            n for n, v in (("dt", dt), ("rtol", rtol), ("atol", atol), ("controller", controller)) if v is not None
        ]
        if given:
            raise ValueError(
                f"target_error= chooses the step or the tolerances itself, so {', '.join(given)} cannot be given too"
            )
        if saveat.steps is not False:
            raise ValueError(
                "target_error= saves at SaveAt(t0/t1/ts=...): the steps differ per setting, "
                "so SaveAt(steps=...) cannot be used"
            )
        eps = validation.check(
            validation.check_scalar(target_error, "target_error", dtype),
            lambda x: x > 0,
            "target_error must be > 0, got {value}",
        )
        n = max_steps or global_error.DEFAULT_TARGET_MAX_STEPS
    elif dt is not None:
        given = [
            n for n, v in (("rtol", rtol), ("atol", atol), ("dt0", dt0), ("controller", controller)) if v is not None
        ]
        if given:
            raise ValueError(f"dt= asks for fixed steps, so {', '.join(given)} would be ignored; pass one or the other")
        dt, n = _check_fixed(dt, t0, t1, saveat, max_steps, dtype)
        if events and saveat.ts is not None:
            raise ValueError("event= with fixed steps saves by SaveAt(steps=...) or t0/t1, not SaveAt(ts=...) (yet)")
        adjoint = _check_adjoint(adjoint)
    else:
        controller, adjoint, dt0 = _check_adaptive(
            solver, saveat, rtol, atol, dt0, controller, adjoint, estimate_error, dtype
        )
        n = max_steps or global_error.DEFAULT_ADAPTIVE_MAX_STEPS
    args = (problem, solver, t0, t1, dt, dt0, saveat, n, controller, adjoint, estimate_error, eps, events)
    try:
        # A function in the problem that closes over a value being
        # differentiated is seen only by the adjoints' own rules, which
        # closure-convert it (`lierk._adjoint`): those calls take `_program`.
        # Which program runs is `lierk._programs`' rule.
        if _may_capture_tracer(args):
            sol = _program.default(*args)
        elif validation.is_traced(args):
            sol = _differentiable_program(args)
        else:
            # Concrete values: nothing to differentiate, and the custom
            # derivative's wrapping is work on the host for every call.
            sol = _program(*args)
    except TypeError as e:
        if dt is not None or eps is not None or "custom_vjp" not in str(e):
            raise
        raise ValueError(
            f"forward-mode autodiff (jax.jvp, jax.jacfwd) cannot go through an adaptive solve with "
            f"{type(adjoint).__name__}, which supports reverse mode only: leave adjoint= out "
            "(lierk.ForwardSensitivity(), both modes), or pass adjoint=lierk.ForwardMode() (forward only)"
        ) from None
    if isinstance(event, Event):
        sol = eqx.tree_at(lambda s: s.events, sol, sol.events[0])
    return raise_if_failed(sol, throw)


def _forms(form, problem, solver, t0, t1, dt, dt0, saveat, n, *rest):
    """`_program`'s arguments with the solver in ``form`` for at most ``n``
    steps (`lierk._programs.in_form`)."""
    return (problem, in_form(solver, form, n), t0, t1, dt, dt0, saveat, n, *rest)


@functools.partial(Program, forms=_forms)
def _program(problem, solver, t0, t1, dt, dt0, saveat, n, controller, adjoint, estimate_error, eps, events):
    """The solve `solve` has checked: ``eps`` (``target_error``), ``dt``
    (fixed steps, ``n`` of them) or ``controller`` (adaptive, at most ``n``
    attempts) says which.  An input that is NaN, as a traced value that
    failed its check is (`lierk._validation.check`), ends the solve with
    its code in `RESULTS.invalid` and NaN states (`_invalid_code`)."""
    invalid = _invalid_code(problem, t0, t1, dt, dt0, saveat, controller, eps)
    if eps is not None:
        sol = global_error.solve_to_target(problem, solver, t0, t1, saveat, eps, n, adjoint)
    elif dt is not None and saveat.ts is not None:
        sol = adjoint.run_steps(_fixed_at_loop, True, problem, solver, t0, t1, dt, saveat, n, steps=n)
        if estimate_error:
            sol = global_error.estimate_fixed(sol, problem, solver, t0, t1, dt, saveat, n)
    elif dt is not None:
        sol = adjoint.run_steps(_fixed_loop, True, problem, solver, t0, t1, dt, saveat, n, events, steps=n)
        if estimate_error:
            sol = global_error.estimate_fixed(sol, problem, solver, t0, t1, dt, saveat, n)
    else:
        sol = adjoint.run_steps(
            _adaptive_loop, False, problem, solver, t0, t1, dt0, saveat, n, controller, events, steps=n
        )
        if estimate_error:
            sol = global_error.estimate_adaptive(sol, problem, solver, t0, t1, saveat, n, controller, adjoint)
    # Every output batched whenever an input is: a `jax.vmap` that meets
    # the solve inside a caller's `jit` solves the batch by a batching
    # rule that reports every output batched (`lierk._programs.by_batch`), and JAX
    # needs the custom derivative's rule to batch its outputs alike (a
    # `grad` of a `vmap(jit)` failed to lower: the count of saved states
    # batched in one and not the other).  XLA removes the ties.
    sol = _marked_invalid(_flag_drift(problem, sol), invalid)
    return _batched_together(sol, (problem, t0, t1, dt, dt0, saveat, controller, eps, events))


# Why a derivative of `solve` is not the derivative of `_program`'s jitted
# call: JAX takes the JVP of a jitted function from its traced program, so
# the solve was traced twice, once undifferentiated into that program (whose
# loops' own derivative rules then discard it) and once more by those rules.
# Traced by its rule straight from the Python, the derivative's program is
# the same and the undifferentiated trace is skipped, which shortens a first
# Jacobian's trace (benchmarks/results/first_result-solve-jacfwd.md).
@eqx.filter_custom_jvp
def _differentiable_program(args):
    """``_program(*args)``, with the derivative `_program_jvp`."""
    return _program(*args)


@_differentiable_program.def_jvp
def _differentiable_program_jvp(primals, tangents):
    return _program_jvp(primals[0], tangents[0])


@Program
def _program_jvp(args, t_args):
    """``(solution, tangent)`` of `_program` at ``args`` in the direction
    ``t_args`` (None: not perturbed), as one program.  The solver keeps the
    form it was given: `lierk.ForwardSensitivity` computes its Jacobian in
    a program of its own, by `lierk._programs`' rule."""
    return eqx.filter_jvp(lambda a: _program.__wrapped__(*a), (args,), (t_args,))


def _X64_HINT(dtype) -> str:
    """The way to float64, for a float32 refusal: float32 is JAX's default."""
    if np.dtype(dtype) != np.float32:
        return ""
    return (
        ' (float32 is JAX\'s default: jax.config.update("jax_enable_x64", True) before making any array gives float64)'
    )


def _check_events(event, saveat: SaveAt, estimate_error: bool, target_error) -> tuple[Event, ...]:
    """``event=`` as a tuple of `Event` (empty for None), refused where it
    cannot be honoured."""
    if saveat.dense and (estimate_error or target_error is not None):
        raise ValueError(
            "SaveAt(dense=True) cannot be combined with estimate_error=True or target_error= (yet): the error "
            "estimate covers the saved times only; solve with dense output at the chosen setting instead"
        )
    if event is None:
        return ()
    events = events_tuple(event)
    if estimate_error or target_error is not None:
        raise ValueError(
            "event= cannot be combined with estimate_error=True or target_error= (yet): a finer solve would stop "
            "at another time; solve with the event at the chosen setting instead"
        )
    return events


def _check_call(problem, solver, saveat, max_steps, estimate_error) -> SaveAt:
    """The structural arguments; returns the `SaveAt` (default: t1)."""
    if not isinstance(problem, AbstractProblem):
        raise ValueError(f"problem must be a lierk problem such as FreeRigidBody, got {type(problem).__name__}")
    if not isinstance(solver, AbstractSolver):
        raise ValueError(f"solver must be a lierk solver such as RKMK4(), got {solver!r}")
    saveat = SaveAt(t1=True) if saveat is None else saveat
    if not isinstance(saveat, SaveAt):
        raise ValueError(f"saveat must be a lierk.SaveAt, got {saveat!r}")
    if saveat.dense and not (saveat.t0 or saveat.t1 or saveat.steps or saveat.ts is not None):
        # Dense output alone saves the final state too.
        saveat = SaveAt(t1=True, dense=True)
    # (A bool is an int to Python: max_steps=True would run one step.)
    if max_steps is not None and not (
        isinstance(max_steps, (int, np.integer)) and not isinstance(max_steps, bool) and max_steps >= 1
    ):
        raise ValueError(f"max_steps must be a positive Python int, got {max_steps!r}")
    if not isinstance(estimate_error, bool):
        raise ValueError(f"estimate_error must be True or False, got {estimate_error!r}")
    return saveat


def _check_times(t0, t1, dtype) -> tuple[Array, Array]:
    """``t0`` and ``t1`` (s) as scalars of the problem's dtype, ``t1 >= t0``."""
    t0_given, t1_given = t0, t1
    t0 = validation.check_scalar(t0, "t0", dtype)
    t1 = validation.check_scalar(t1, "t1", dtype)
    if not validation.is_traced(t0_given, t1_given) and float(t1_given) > float(t0_given) and float(t1) <= float(t0):
        raise ValueError(
            f"t1 = {float(t1_given)!r} rounds to t0 = {float(t0)!r} in {np.dtype(dtype).name}: the interval is below "
            "the resolution of the time axis; shift t0 towards 0 or use float64" + _X64_HINT(dtype)
        )
    t1 = validation.check(
        t1,
        lambda x: x >= t0,
        f"t1 must be >= t0 = {t0 if not validation.is_traced(t0) else 't0'}, got t1 = {{value}}",
        reads=t0,
    )
    return t0, t1


def _check_save_times(saveat: SaveAt, t0, t1, dtype) -> SaveAt:
    if saveat.ts is None:
        return saveat
    ts = validation.asarray(saveat.ts, dtype, "SaveAt(ts=...)")
    if np.shape(ts)[0] == 0:
        raise ValueError("SaveAt(ts=...) is empty: give at least one time, or save t0/t1 instead")
    ts = validation.check(
        ts,
        lambda x: (x >= t0).all() & (x <= t1).all() & (x[1:] >= x[:-1]).all(),
        "SaveAt(ts=...) must be non-decreasing and lie in [t0, t1], got {value}",
        reads=(t0, t1),
    )
    # The solve must use the checked array, or a traced check is dead code.
    return eqx.tree_at(lambda s: s.ts, saveat, jnp.asarray(ts))


def _check_fixed(dt, t0, t1, saveat: SaveAt, max_steps, dtype) -> tuple[Array, int | None]:
    """The step ``dt`` (s) and the static step count of a fixed-step solve
    (None with ``SaveAt(ts=...)``, whose counts are traced)."""
    if saveat.ts is not None:
        if saveat.steps:
            raise ValueError(
                f"SaveAt(ts=...) and SaveAt(steps={saveat.steps}) cannot be combined: pass one or the other"
            )
        if saveat.dense:
            raise ValueError(
                "SaveAt(ts=...) with fixed steps cannot keep dense output (yet): use SaveAt(dense=True) alone"
            )
    dt = validation.check_scalar(dt, "dt", dtype)
    dt = validation.check(dt, lambda x: x > 0, "dt must be > 0, got {value}")
    if not validation.is_traced(t0, t1, dt) and dt <= np.finfo(dt.dtype).eps * max(abs(t0), abs(t1)):
        # The step itself would still be integrated exactly dt long, but
        # the times t0 + k dt, which time-dependent effects read and the
        # solution reports, could not move forward.
        raise ValueError(
            f"dt = {float(dt)!r} is below the resolution of {np.dtype(dt.dtype).name} times near "
            f"t = {float(max(abs(t0), abs(t1)))!r} (one ulp is about {float(np.spacing(max(abs(t0), abs(t1))))!r}): "
            "measure time from a closer origin (t0 = 0) or use float64" + _X64_HINT(dt.dtype)
        )
    if saveat.ts is not None:
        return dt, max_steps
    n = num_steps(t0, t1, dt, max_steps)
    if saveat.steps and not (saveat.t0 or saveat.t1) and n // saveat.every == 0:
        raise ValueError(
            f"SaveAt(steps={saveat.steps}) saves nothing: this run takes {n} steps; "
            "save t1 too (SaveAt(steps=..., t1=True)) or save more often"
        )
    return dt, n


def _check_adaptive(solver, saveat: SaveAt, rtol, atol, dt0, controller, adjoint, estimate_error, dtype):
    """``(controller, adjoint, dt0)`` of a solve whose steps a controller
    chooses (any `AbstractStepController`; `Controller` from ``rtol``)."""
    if controller is not None and not isinstance(controller, AbstractStepController):
        raise ValueError(
            f"controller must be a lierk.AbstractStepController such as lierk.Controller(...), got {controller!r}"
        )
    if not solver.adaptive and (controller is None or controller.decides):
        raise ValueError(
            f"{solver.name} has no error estimate, so it needs a fixed step: pass dt=, or target_error="
            + (f"; {type(controller).__name__} decides on error estimates. " if controller is not None else ". ")
            + "Adaptive solvers: RKF45(), DP54(), DOP853()."
        )
    if controller is None:
        if rtol is None:
            raise ValueError(
                f"adaptive {solver.name} needs rtol= (and atol=), or controller=, or target_error=; "
                "or pass dt= for fixed steps"
            )
        controller = Controller.from_tolerances(rtol, atol)
    elif rtol is not None or atol is not None:
        raise ValueError("pass tolerances either as rtol=/atol= or inside controller=, not both")
    if not isinstance(controller, Controller):
        if estimate_error:
            raise ValueError(
                f"estimate_error=True compares with a solve at a lierk.Controller's tolerances divided by 10; "
                f"{type(controller).__name__} has none: estimate by hand (lierk.finer_options, lierk.richardson)"
            )
        if isinstance(controller, ConstantStep) and dt0 is None:
            raise ValueError("ConstantStep() takes steps of dt0: pass dt0= (or dt= for fixed steps)")
    if saveat.steps is not False and saveat.steps is not True:
        raise ValueError(f"adaptive solves save every accepted step (SaveAt(steps=True)), not every {saveat.steps}-th")
    if saveat.steps and saveat.ts is not None:
        raise ValueError("SaveAt(steps=True) and SaveAt(ts=...) cannot be combined in one adaptive solve")
    if saveat.steps and estimate_error:
        raise ValueError(
            "estimate_error=True compares with a finer solve at the same saved times, and adaptive "
            "SaveAt(steps=True) saves different times in each: use SaveAt(ts=...)"
        )
    # The tolerances as given when they are known: inside a trace the
    # controller's own arrays are tracers even for constants (a Controller
    # built outside `jit` and closed over inside it, or built here from
    # rtol= under jit, as a scene's pieces are).
    tolerances = (rtol, rtol if atol is None else atol) if rtol is not None else None
    if isinstance(controller, Controller) and (tolerances is None or validation.is_traced(tolerances)):
        tolerances = (controller.rtol, controller.atol)
    reason = (
        None
        if tolerances is None or validation.is_traced(tolerances)
        else (validation.tolerances_below_rounding(*tolerances, dtype))
    )
    if reason is not None:
        raise ValueError(reason + _X64_HINT(dtype))
    adjoint = _check_adjoint(adjoint)
    if dt0 is not None:
        dt0 = validation.check(
            validation.check_scalar(dt0, "dt0", dtype), lambda x: x > 0, "dt0 must be > 0, got {value}"
        )
    return controller, adjoint, dt0


def _check_adjoint(adjoint) -> AbstractAdjoint:
    adjoint = ForwardSensitivity() if adjoint is None else adjoint
    if not isinstance(adjoint, AbstractAdjoint):
        raise ValueError(f"adjoint must be a lierk._adjoint object such as lierk.ForwardSensitivity(), got {adjoint!r}")
    return adjoint


# The loops as `AbstractAdjoint.run` calls them: the adjoint first (the
# fixed-step scan has no use for it).
def _fixed_loop(adjoint, problem, solver, t0, t1, dt, saveat, n, events):
    return solve_fixed(problem, solver, t0, t1, dt, saveat, n, events)


def _fixed_at_loop(adjoint, problem, solver, t0, t1, dt, saveat, max_steps):
    return solve_fixed_at(problem, solver, t0, t1, dt, saveat, max_steps)


def _adaptive_loop(adjoint, problem, solver, t0, t1, dt0, saveat, max_steps, controller, events):
    return solve_adaptive(problem, solver, t0, t1, dt0, saveat, max_steps, controller, adjoint, events=events)


def _invalid_code(problem, t0, t1, dt, dt0, saveat: SaveAt, controller, eps) -> Array:
    """The `RESULTS.invalid` code of the first input group holding a NaN (a
    NaN given, or a traced value that failed its check in the program), 0
    if none: a traced bool per group and one select each."""
    groups = [(t0, t1), (dt, dt0), saveat.ts, controller, eps, problem]
    code = jnp.zeros((), jnp.int32)
    for value, c in reversed(list(zip(groups, RESULTS.invalid))):
        code = jnp.where(validation.first_invalid(value), c, code)
    return code


def _marked_invalid(sol: Solution, code) -> Solution:
    """``sol`` with the result ``code`` and NaN states where it is not 0."""
    bad = code != 0
    result = jnp.where(bad, code.astype(sol.result.dtype), sol.result)
    return eqx.tree_at(
        lambda s: (s.R, s.y, s.result),
        sol,
        (validation.poisoned(sol.R, ~bad), validation.poisoned(sol.y, ~bad), result),
        is_leaf=lambda x: x is None,
    )


# A conserved quantity that moves by more than this (relative to its scale)
# marks a run as under-resolved or unstable: RESULTS.invariant_drift.
_DRIFT_LIMIT = 0.1


def _flag_drift(problem, sol: Solution) -> Solution:
    keys = problem.conserved()
    if not keys:
        return sol
    # A result code, never differentiated: a differentiated solve traced the
    # invariants' derivative at every saved point only to drop it.
    problem, R, y = frozen((problem, sol.R, sol.y))
    q0 = problem.invariants(problem.R0, problem.y0)
    q = problem.invariants(R, y)
    scales = problem.invariant_scales()
    worst = jnp.zeros((), sol.R.dtype)
    for k in keys:
        d = jnp.abs(q[k] - q0[k]) / jnp.where(scales[k] > 0, scales[k], 1.0)
        # Padding rows are NaN; a non-finite run has its own code.
        worst = jnp.maximum(worst, jnp.max(jnp.where(jnp.isfinite(d), d, 0.0)))
    finished = sol.result == RESULTS.successful if sol.events is None else sol.ok
    drifted = finished & (worst > _DRIFT_LIMIT)
    result = jnp.where(drifted, RESULTS.invariant_drift, sol.result).astype(sol.result.dtype)
    return eqx.tree_at(lambda s: s.result, sol, result)
