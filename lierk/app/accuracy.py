"""Work against precision for a scene: which solver and setting reach an error, and at what cost.

`work_precision` runs the scene's problem with each solver over a range of
settings: steps ``dt`` for the fixed-step methods, tolerances
``rtol = atol`` for the adaptive ones.  By default it runs every method that
applies (`default_solvers`): the fixed-step Lie methods `RKMK4`, `CF4`,
``RKMK(DOPRI54)`` and ``RKMK(DOP853)`` (the embedded pairs' tableaux at
fixed steps), the adaptive pairs `DP54`, `DOP853` and `RKF45`, and, for a
body under torques, the splittings `Strang`, `BlanesMoan4` and
`BlanesMoan6`, with the Runge-Kutta-Nystrom `BlanesMoanRKN4` and
`BlanesMoanRKN6` when no torque reads the momentum.  For each run it
records

- the wall time of one call of the compiled solve (a warm-up call first,
  then the minimum of a few repeats, each ended by `jax.block_until_ready`);
- the true error ``max_t ||R(t) - R_ref(t)||_F`` over the saved times;
- the method's own estimate of it (Richardson's, as ``estimate_error=True``
  computes it: the finer solve of `lierk.finer_options`, at ``2 dt/3`` or
  ``rtol/10``, and `lierk.richardson`, the same maximum);
- the number of steps.

Each method compiles once: ``dt`` and the controller are traced values of
one program, `lierk.solve` with ``SaveAt(ts=...)``, whose fixed steps end on
every saved time and are counted at run time.  The report says how much of
the wall time went to compiling.

The saved times are ``n_times`` equally spaced times from 0 to ``t1``, the
same for every run: fixed steps are chosen so that a whole number of them
fits between two saved times, and every solve ends steps on them.

The reference ``R_ref``:

- a torque-free body (``problem.torque_free``): the closed form
  `lierk.exact.free_rigid_body` (a splitting of such a body is that closed
  form too, so none is run);
- otherwise a `DOP853` solve two orders of magnitude tighter than the
  tightest tolerance (and than 1e-12, the smallest decade), but not below
  1e-13 in float64, cross-checked by a second method, `DP54` at the same
  tolerance.  Their disagreement, and the reference's own error estimate,
  set `AccuracyReport.floor`: errors below it cannot be told apart from the
  reference's, so no decade below it is claimed.

`AccuracyReport.best_per_decade` gives, per decade 1e-2 ... 1e-12, the
cheapest run whose true error is at most that decade (`AccuracyReport.table`
as text, `AccuracyReport.summary` with the reference: what ``lierk accuracy``
prints); `figure` draws the work-precision diagram and `to_json` serialises
the report.

Example:
    >>> scene = lierk.app.scene.load("examples/heavy_top.toml")
    >>> report = lierk.app.accuracy.work_precision(scene, max_settings=4)
    >>> row = report.cheapest(1e-6)   # e.g. BlanesMoanRKN4 at dt = 0.0039 s
    >>> print(report.summary())       # the cheapest run per decade
    >>> lierk.app.accuracy.figure(report).savefig("work_precision.png")
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lierk import Progress

from ._device import to_device

__all__ = [
    "Row",
    "AccuracyReport",
    "work_precision",
    "figure",
    "to_json",
    "DECADES",
    "METHODS",
    "default_solvers",
    "method",
]

DECADES: tuple[float, ...] = tuple(10.0**-k for k in range(2, 13))
"""The error levels of `AccuracyReport.best_per_decade`: 1e-2 ... 1e-12."""

METHODS: tuple[str, ...] = (
    "RKMK4",
    "CF4",
    "RKMK(DOPRI54)",
    "RKMK(DOP853)",
    "DP54",
    "DOP853",
    "RKF45",
    "Strang",
    "BlanesMoan4",
    "BlanesMoan6",
    "BlanesMoanRKN4",
    "BlanesMoanRKN6",
)
"""Every method `default_solvers` may pick, in the order they run: the
order-4 Lie methods and the two embedded pairs' tableaux at fixed steps, the
adaptive pairs, the splittings.  The first-order methods, the report's
order-2 RK4 and the Yoshida compositions (never cheaper than Blanes and
Moan's in `benchmarks/torqued.py`) run only when named."""

# Fixed steps start at about this many radians per step (|omega0| dt) and
# halve from there.  A splitting advances the torque-free motion exactly, so
# its step is bounded by the torques, not by the spin: it starts 64x coarser
# (its coarsest steps were the cheapest on the tops of benchmarks/torqued.py).
_FIRST_ANGLE = 0.5
_FIRST_ANGLE_SPLITTING = 32.0
_DEFAULT_MAX_STEPS = 2**17
_DEFAULT_MAX_SETTINGS = 10
# Timed calls of a run stop once at least two have taken this long (s) in all.
_TIMING_BUDGET = 0.2
_REFERENCE_RTOL_CAP = 1e-13  # float64; float32 uses 100 eps
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "*")


@dataclasses.dataclass(frozen=True)
class Row:
    """One run of `work_precision`.

    Attributes:
        solver: the method's name (`method`).
        setting: ``"dt"`` (fixed step, s) or ``"rtol"`` (adaptive, ``atol = rtol``).
        value: the step (s) or the tolerance.
        time: wall time of one call of the compiled solve (s), the minimum
            over repeats; it includes the call's own dispatch (tens of
            microseconds), not the error estimate.
        error: ``max_t ||R(t) - R_ref(t)||_F`` over the saved times; NaN if
            the solve failed.
        error_estimate: Richardson's estimate of the same quantity from a
            finer run (``2 dt/3``, or ``rtol/10``), what
            `Solution.error_estimate` gives.
        num_steps: steps attempted (accepted and rejected).
        num_fevals: field evaluations as `lierk.Solution.stats` counts them
            (drifts for a splitting).
        result: the `lierk.RESULTS` code; 0 is success.
    """

    solver: str
    setting: str
    value: float
    time: float
    error: float
    error_estimate: float
    num_steps: int
    num_fevals: int
    result: int

    @property
    def ok(self) -> bool:
        """The solve succeeded and its error is finite."""
        from lierk import RESULTS

        return self.result == RESULTS.successful and math.isfinite(self.error)

    @property
    def label(self) -> str:
        """``"dt = 0.00125 s"`` or ``"rtol = 1e-08"``."""
        return f"dt = {self.value:.3g} s" if self.setting == "dt" else f"rtol = {self.value:.0e}"


@dataclasses.dataclass(frozen=True)
class AccuracyReport:
    """What `work_precision` measured.

    Attributes:
        scene: the scene's name.
        t1: end time (s).
        ts: ``(n_times,)`` the saved times (s) at which errors are measured.
        rows: every run, in the order they ran (per solver, coarse to fine).
        reference: how ``R_ref`` was computed.
        reference_error: estimate of the reference's own error (max over
            ``ts``): its Richardson estimate for a numerical reference; for
            `lierk.exact`, rounding of ``10 eps`` per radian turned,
            ``10 eps max(1, |omega0| t1)`` (about 1e-12 after 100 periods in
            float64, as its tests measure).
        check: the second method that cross-checks a numerical reference,
            or None for `lierk.exact`.
        check_disagreement: ``max_t ||R_check - R_ref||_F``, or None.
        dtype: ``"float64"`` or ``"float32"``.
        compilations: the programs compiled (or loaded from the persistent
            cache) while it ran (`lierk.app.compilations`), or None if not counted.
        compile_time: wall time (s) spent tracing, lowering and compiling
            them, or None.
    """

    scene: str
    t1: float
    ts: np.ndarray
    rows: tuple[Row, ...]
    reference: str
    reference_error: float
    check: str | None
    check_disagreement: float | None
    dtype: str
    compilations: int | None = None
    compile_time: float | None = None

    @property
    def floor(self) -> float:
        """The error below which runs cannot be told apart from the reference:
        the larger of `reference_error` and `check_disagreement`."""
        d = self.check_disagreement
        if self.check is not None and (d is None or not math.isfinite(d)):
            return math.inf  # the check failed: nothing vouches for the reference
        return max(self.reference_error, d or 0.0)

    @property
    def solvers(self) -> list[str]:
        """Solver names, in the order they ran."""
        return list(dict.fromkeys(r.solver for r in self.rows))

    def cheapest(self, error: float) -> Row | None:
        """The fastest successful run whose true error is at most ``error``;
        None if no run reaches it, or if ``error`` is below `floor` (then the
        reference cannot confirm it)."""
        if error < self.floor:
            return None
        hits = [r for r in self.rows if r.ok and r.error <= error]
        return min(hits, key=lambda r: r.time) if hits else None

    def best_per_decade(self, decades: Sequence[float] = DECADES) -> dict[float, Row | None]:
        """``{decade: cheapest(decade)}`` for each decade (default 1e-2 ... 1e-12)."""
        return {d: self.cheapest(d) for d in decades}

    def table(self, decades: Sequence[float] = DECADES) -> str:
        """`best_per_decade` as a text table, a header and one line per
        decade: the cheapest solver, its setting, time, true error and
        estimate, or why no run is named (below `floor`, or none reached it)."""
        width = max([8, *(len(name) for name in self.solvers)])
        lines = [
            f"{'error <=':>9}  {'cheapest':<{width}}  {'setting':<18}  {'time (s)':>9}  {'error':>8}  {'estimate':>8}"
        ]
        for decade, row in self.best_per_decade(decades).items():
            if row is not None:
                lines.append(
                    f"{decade:>9.0e}  {row.solver:<{width}}  {row.label:<18}  {row.time:>9.3g}  {row.error:>8.1e}  "
                    f"{row.error_estimate:>8.1e}"
                )
            elif decade < self.floor:
                lines.append(f"{decade:>9.0e}  (below the reference's accuracy, {self.floor:.1e})")
            else:
                lines.append(f"{decade:>9.0e}  (no run reached it)")
        return "\n".join(lines)

    def summary(self, wall: float | None = None) -> str:
        """The report ``lierk accuracy`` prints: what ran (with ``wall``, the
        whole run's wall time in s, and how much of it went to compiling),
        the reference and its cross-check, then `table`."""
        head = (
            f"scene {self.scene}: {len(self.rows)} runs of {', '.join(self.solvers)}, T = {self.t1:g} s, "
            f"errors max_t ||R - R_ref||_F at {len(self.ts)} equally spaced times"
        )
        if wall is not None and self.compile_time is not None:
            head += f", {wall:.1f} s wall ({self.compile_time:.1f} s of it compiling {self.compilations} programs)"
        elif wall is not None:
            head += f", {wall:.1f} s wall (incl. compilation)"
        lines = [head, f"  reference: {self.reference}, error about {self.reference_error:.1e}"]
        if self.check is not None:
            d = self.check_disagreement
            lines.append(f"  cross-check: {self.check}" + (f", disagrees by {d:.1e}" if d is not None else ""))
        return "\n".join([*lines, self.table()])


# --------------------------------------------------------------------------


def work_precision(
    scene,
    solvers: Sequence[Any] | None = None,
    settings: Mapping[str, Sequence[float]] | None = None,
    progress: bool = False,
    *,
    max_settings: int | None = None,
    max_steps: int = _DEFAULT_MAX_STEPS,
    n_times: int = 11,
    repeats: int = 5,
) -> AccuracyReport:
    """Error against wall time for each solver and setting on ``scene``'s problem.

    Runs in the precision of the scene's problem (enable float64 first for
    the small decades).  See the module docstring for what is measured.

    Args:
        scene: a `lierk.app.scene.Scene`; its problem and ``t1`` are used, its
            own solver and run settings are not.
        solvers: method names (`method`: those of `lierk.SOLVERS`,
            plus ``"RKMK(DOPRI54)"`` and ``"RKMK(DOP853)"``, the tableaux at
            fixed steps) or solver instances; default `default_solvers`.
        settings: per method name, the values to run: steps ``dt`` (s) for
            fixed-step methods, each rounded so a whole number of steps fits
            between saved times, or tolerances ``rtol`` for adaptive ones.
            Default: ``dt`` from about 0.5 rad per step (``|omega0| dt``; 32
            rad for the splittings), halved each time; ``rtol`` 1e-3, 1e-4,
            ..., 1e-12.  Defaults stop early once a run's error is below the
            smallest decade (or a tenth of the reference's floor), when an
            adaptive run exceeds ``max_steps``, or when the error stops
            falling (rounding).
        progress: draw a progress bar on stderr, one tick per run.
        max_settings: at most this many settings per method (default 10);
            default tolerances are then spread over 1e-3 ... 1e-12.
        max_steps: bound on the steps of one solve: default fixed steps stay
            within it, and it is the adaptive solves' ``max_steps``.
        n_times: number of saved times, ``>= 2``, including 0 and ``t1``.
        repeats: timed calls per run (fewer once two of them take over
            `_TIMING_BUDGET`, 0.2 s, in all).

    Returns:
        An `AccuracyReport`, with the number of programs compiled and the
        time that took.

    Raises:
        ValueError: unknown method names, a method that cannot run this
            problem, settings for methods not run, or settings that are not
            finite numbers > 0.
        RuntimeError: the reference solve failed.
    """
    from .compilations import counting

    problem, t1 = scene.problem, float(scene.t1)
    dtype = problem.R0.dtype
    eps = float(np.finfo(dtype).eps)
    if not (isinstance(n_times, int) and n_times >= 2):
        raise ValueError(f"n_times must be an int >= 2, got {n_times!r}")
    if not (isinstance(max_steps, int) and max_steps >= 1):
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    if max_settings is not None and not (isinstance(max_settings, int) and max_settings >= 1):
        raise ValueError(f"max_settings must be a positive int or None, got {max_settings!r}")
    n_max = _DEFAULT_MAX_SETTINGS if max_settings is None else max_settings
    chosen = _methods_to_run(default_solvers(problem) if solvers is None else solvers, problem)
    settings = _checked_settings(settings, chosen)

    ts_np = np.linspace(0.0, t1, n_times)
    plan = _plan(chosen, settings, problem, t1, n_times, n_max, max_steps, eps)
    numerical = not problem.torque_free
    bar = Progress("accuracy", sum(len(v) for _, v, _ in plan) + (2 if numerical else 1), " runs", quiet=not progress)
    done = [0]

    def tick(n=1):
        done[0] += n
        bar.update(done[0])

    with counting() as compiled:
        bar.update(0)
        programs = _Programs(problem, t1, ts_np, max_steps)
        reference = [method("DOP853"), method("DP54")] if numerical else []
        programs.compile(programs.key(m) for m in [*reference, *(m for m, _, _ in plan)])
        rtols = [v for m, values, _ in plan if m.adaptive for v in values]
        ref = _reference(programs, rtols, numerical, tick)
        # Defaults stop once a run is below what the decades (or the reference) can resolve.
        stop_level = max(min(DECADES) / 10, max(ref.error, ref.disagreement or 0.0) / 10)

        rows: list[Row] = []
        for m, values, is_default in plan:
            previous = None
            for i, v in enumerate(values):
                row = _run(programs, m, v, repeats, ref.R)
                rows.append(row)
                tick()
                if is_default and _stop(row, previous, stop_level):
                    tick(len(values) - i - 1)
                    break
                previous = row if row.ok else previous

    return AccuracyReport(
        scene=scene.name,
        t1=t1,
        ts=ts_np,
        rows=tuple(rows),
        reference=ref.reference,
        reference_error=ref.error,
        check=ref.check,
        check_disagreement=ref.disagreement,
        dtype=str(np.dtype(dtype)),
        compilations=compiled.count,
        compile_time=compiled.seconds,
    )


@dataclasses.dataclass(frozen=True)
class _Method:
    """A solver as `work_precision` runs it: by ``name``, with tolerances
    (``adaptive``) or at fixed steps."""

    name: str
    solver: Any
    adaptive: bool


def method(name: str) -> _Method:
    """The method called ``name`` (any letter case): a solver of
    `lierk.SOLVERS`, adaptive if it has an error estimate, or
    ``"RKMK(DOPRI54)"``/``"RKMK(DOP853)"``, `lierk.RKMK` with the embedded
    pairs' tableaux at fixed steps.  RKMK solvers come with their stages
    unrolled (``compact=False``): the form a batch runs and the fastest for
    one body, so the report times each solver at its fastest (one body's
    solve otherwise loops over the stages of the longer tableaux, which
    compiles sooner and runs slower; `lierk.AbstractRKMK`).

    Raises:
        ValueError: an unknown name; the message lists the known ones.
    """
    from lierk import RKMK, SOLVERS, AbstractRKMK, solver_class, tableaux

    fixed_pairs = {"RKMK(DOPRI54)": tableaux.DOPRI54, "RKMK(DOP853)": tableaux.DOP853}
    for label, tableau in fixed_pairs.items():
        if isinstance(name, str) and name.replace(" ", "").lower() == label.lower():
            return _Method(label, RKMK(tableau, compact=False), adaptive=False)
    try:
        cls = solver_class(name)
    except ValueError:
        raise ValueError(f"unknown solver {name!r}; choose from: {', '.join([*SOLVERS, *fixed_pairs])}") from None
    solver = cls(compact=False) if issubclass(cls, AbstractRKMK) else cls()
    return _Method(solver.name, solver, solver.adaptive)


def default_solvers(problem) -> tuple[str, ...]:
    """The methods `work_precision` runs on ``problem`` by default (names of
    `METHODS`): the Lie Runge-Kutta methods at fixed steps and the adaptive
    pairs always; for a rigid body under torques also the splittings, with
    the Runge-Kutta-Nystrom ones only when no torque reads the momentum
    (``problem.kick_reads_momentum``).  A torque-free body has none: its
    splitting is the closed form, the reference itself."""
    from lierk import AbstractRigidBody

    names = list(METHODS[:7])
    if (
        isinstance(problem, AbstractRigidBody)
        and not problem.torque_free
        and getattr(problem, "splitting_refusal", None) is None
    ):
        names += ["Strang", "BlanesMoan4", "BlanesMoan6"]
        if not problem.kick_reads_momentum:
            names += ["BlanesMoanRKN4", "BlanesMoanRKN6"]
    return tuple(names)


def _methods_to_run(solvers, problem) -> list[_Method]:
    """`_Method`s from names (`method`) or solver instances, each checked to
    apply to ``problem``."""
    from lierk import AbstractRigidBody, AbstractSolver, AbstractSplitting

    chosen = []
    for s in solvers:
        if isinstance(s, str):
            m = method(s)
        elif isinstance(s, AbstractSolver):
            m = _Method(s.name, s, s.adaptive)
        else:
            raise ValueError(f"solvers must be names or lierk solvers, got {s!r}")
        if isinstance(m.solver, AbstractSplitting):
            if not isinstance(problem, AbstractRigidBody):
                raise ValueError(f"{m.name} needs a rigid body with drift and kick, not a {type(problem).__name__}")
            if m.solver.scheme.nystrom and problem.kick_reads_momentum:
                raise ValueError(
                    f"{m.name} is a Runge-Kutta-Nystrom splitting, and this scene's "
                    f"{', '.join(problem.kick_reads_momentum)} reads the momentum; use BlanesMoan4 or BlanesMoan6"
                )
        chosen.append(m)
    if not chosen:
        raise ValueError("no solvers to run")
    return chosen


def _checked_settings(settings, chosen) -> dict:
    settings = dict(settings or {})
    unknown = set(settings) - {m.name for m in chosen}
    if unknown:
        raise ValueError(f"settings given for solvers that are not run: {', '.join(sorted(unknown))}")
    for name, values in settings.items():
        if not values or not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"settings[{name!r}] must be a non-empty list of finite numbers > 0, got {values!r}")
    return settings


def _plan(chosen, settings, problem, t1, n_times, n_max, max_steps, eps) -> list[tuple[_Method, list[float], bool]]:
    """``(method, values, defaults?)`` per method; default ranges stop early."""
    from lierk import AbstractSplitting

    interval = t1 / (n_times - 1)
    rtol_floor = max(1e-12, 100 * eps)
    default_rtols = [10.0**-k for k in range(3, 13) if 10.0**-k >= rtol_floor * (1 - 1e-9)]
    if len(default_rtols) > n_max:
        keep = np.unique(np.round(np.linspace(0, len(default_rtols) - 1, n_max)).astype(int))
        default_rtols = [default_rtols[i] for i in keep]
    omega = float(np.linalg.norm(np.asarray(problem.omega0)))
    plan = []
    for m in chosen:
        if m.name in settings:
            values = [float(v) for v in settings[m.name]]
            if not m.adaptive:
                # Whole steps between saved times, so every run saves the same times.
                values = [interval / max(1, round(interval / v)) for v in values]
            plan.append((m, values, False))
        elif m.adaptive:
            plan.append((m, default_rtols, True))
        else:
            angle = _FIRST_ANGLE_SPLITTING if isinstance(m.solver, AbstractSplitting) else _FIRST_ANGLE
            m0 = 2 ** max(0, math.ceil(math.log2(max(1.0, interval * omega / angle))))
            ms = [m0 * 2**k for k in range(n_max) if (n_times - 1) * m0 * 2**k <= max_steps]
            plan.append((m, [interval / k for k in ms] or [interval / m0], True))
    return plan


class _Programs:
    """The compiled solves of one `work_precision` call: one program per
    method (and per ``max_steps``), whose times, step or controller are
    traced arguments, so every setting, its finer twin (the error estimate)
    and the reference reuse it.  `compile` builds them all first, several at
    once (XLA compiles outside Python's lock), before anything is timed."""

    def __init__(self, problem, t1: float, ts: np.ndarray, max_steps: int):
        dtype = problem.R0.dtype
        self.problem, self.max_steps = problem, max_steps
        self.ts_np = ts
        self.t0, self.t1, self.ts = (to_device(v, dtype) for v in (0.0, t1, ts))
        self.dtype = dtype
        self._programs: dict = {}  # key -> the jitted function, or once compiled its executable
        self._compiled: set = set()

    def compile(self, keys) -> None:
        """Compile the programs of ``keys`` (`_key`) that are not built yet:
        each traced and lowered in turn, then compiled by up to as many
        threads as there are cores."""
        import concurrent.futures

        todo = {
            k: self._jitted(k).lower(*self._arguments(k, {"dt": 1.0} if k[1] == "fixed" else {"rtol": 1.0}))
            for k in dict.fromkeys(keys)
            if k not in self._compiled
        }
        if not todo:
            return
        with concurrent.futures.ThreadPoolExecutor(max(1, min(len(todo), os.cpu_count() or 1))) as pool:
            compiled = dict(zip(todo, pool.map(lambda lowered: lowered.compile(), todo.values())))
        self._programs.update(compiled)
        self._compiled.update(compiled)

    def key(self, m: _Method, max_steps: int | None = None) -> tuple:
        """The program ``m`` runs in (adaptive: with ``max_steps``, default the rows')."""
        if m.adaptive:
            return (m, "adaptive", self.max_steps if max_steps is None else max_steps)
        return (m, "fixed", None)

    def run(self, m: _Method, options: dict, max_steps: int | None = None):
        """A call of ``m``'s program with ``options``: ``{"dt": dt}`` (fixed
        steps ending on the saved times), or ``{"rtol": tol}`` (``atol`` the
        same) or ``{"controller": c}`` (adaptive), as `lierk.solve` takes
        them (`lierk.finer_options` gives the finer ones)."""
        import jax

        key = self.key(m, max_steps)
        if key not in self._programs:
            self._programs[key] = self._jitted(key)
        program, args = self._programs[key], self._arguments(key, options)
        return lambda: jax.block_until_ready(program(*args))

    def _arguments(self, key, options: dict) -> tuple:
        from lierk import Controller

        if key[1] == "fixed":
            return (self.problem, self.t0, self.t1, self.ts, to_device(options["dt"], self.dtype))
        import equinox as eqx
        import jax

        c = options.get("controller")
        if c is None:
            c = Controller.from_tolerances(options["rtol"], options.get("atol", options["rtol"]))
        # Every leaf in the problem's dtype, so that a finer controller runs the same program.
        c = jax.tree_util.tree_map(lambda x: to_device(x, self.dtype) if eqx.is_array(x) else x, c)
        return (self.problem, self.t0, self.t1, self.ts, c)

    def _jitted(self, key):
        import equinox as eqx

        from lierk import SaveAt, one_body_compiler_options, solve

        m, kind, steps = key
        if kind == "fixed":

            def run(problem, t0, t1, ts, dt):
                return solve(problem, m.solver, t1, t0=t0, dt=dt, saveat=SaveAt(ts=ts), throw=False)
        else:

            def run(problem, t0, t1, ts, controller):
                return solve(
                    problem,
                    m.solver,
                    t1,
                    t0=t0,
                    controller=controller,
                    saveat=SaveAt(ts=ts),
                    max_steps=steps,
                    throw=False,
                )

        # One body per program: XLA's one-body settings compile it sooner.
        return eqx.filter_jit(run, compiler_options=one_body_compiler_options())


@dataclasses.dataclass(frozen=True)
class _Reference:
    R: np.ndarray  # (n_times, 3, 3)
    reference: str
    error: float
    check: str | None
    disagreement: float | None


def _gaps(R, R_ref) -> np.ndarray:
    """``||R - R_ref||_F`` at each saved time."""
    return np.linalg.norm(np.asarray(R, dtype=float) - np.asarray(R_ref, dtype=float), axis=(-2, -1))


def _max_gap(R, R_ref) -> float:
    return float(np.max(_gaps(R, R_ref)))


def _richardson(sol, fine, ratio: float) -> float:
    """Richardson's estimate of ``max_t ||R(t) - R_exact(t)||_F`` for ``sol``
    from ``fine``, a solve ``ratio`` times more accurate (``inf`` if it
    failed), as `lierk.solve`'s ``estimate_error=True`` computes it
    (`lierk.richardson`)."""
    from lierk import RESULTS, richardson

    if int(fine.result) != RESULTS.successful:
        return math.inf
    return float(np.max(richardson(_gaps(sol.R, fine.R), ratio)))


def _reference(programs: _Programs, rtols, numerical, tick) -> _Reference:
    """The closed form for a torque-free body, else DOP853 cross-checked by DP54."""
    from lierk import RESULTS, exact

    problem, t1, max_steps = programs.problem, float(programs.t1), programs.max_steps
    eps = float(np.finfo(problem.R0.dtype).eps)
    if not numerical:
        R_ref = np.asarray(
            exact.free_rigid_body(problem.inertia, problem.omega0, programs.ts, problem.R0)[0], dtype=float
        )
        omega = float(np.linalg.norm(np.asarray(problem.omega0)))
        tick()
        # Its rounding grows with the angle turned: ~1e-12 after 100 periods in float64.
        return _Reference(
            R_ref, "lierk.exact.free_rigid_body (closed form)", 10 * eps * max(1.0, omega * t1), None, None
        )

    rtol_ref = max(min(rtols + [1e-12]) / 100, _REFERENCE_RTOL_CAP if eps < 1e-10 else 100 * eps)
    # The rows' programs, with their max_steps first, then with more room.
    for steps in (max_steps, 16 * max_steps):
        ref = programs.run(method("DOP853"), {"rtol": rtol_ref}, max_steps=steps)()
        if int(ref.result) == RESULTS.successful:
            break
    if int(ref.result) != RESULTS.successful:
        raise RuntimeError(
            f"the reference solve (DOP853, rtol = {rtol_ref:.0e}) failed: {RESULTS.message(int(ref.result))}"
        )
    R_ref = np.asarray(ref.R, dtype=float)
    reference = f"DOP853, rtol = atol = {rtol_ref:.0e}, {int(ref.stats['num_steps'])} steps"
    # Its own error: Richardson's estimate from a solve at rtol / 10, as for the rows.
    from lierk import finer_options

    fine_options, ratio = finer_options(method("DOP853").solver, rtol=rtol_ref)
    fine = programs.run(method("DOP853"), fine_options, max_steps=steps)()
    error = _richardson(ref, fine, ratio)
    tick()
    for steps in (max_steps, 16 * max_steps):
        chk = programs.run(method("DP54"), {"rtol": rtol_ref}, max_steps=steps)()
        if int(chk.result) == RESULTS.successful:
            break
    check = f"DP54, rtol = atol = {rtol_ref:.0e}"
    if int(chk.result) == RESULTS.successful:
        check += f", {int(chk.stats['num_steps'])} steps"
        disagreement = _max_gap(chk.R, R_ref)
    else:
        check += f": failed ({RESULTS.message(int(chk.result))})"
        disagreement = None
    tick()
    return _Reference(R_ref, reference, error, check, disagreement)


def _run(programs: _Programs, m: _Method, v: float, repeats: int, R_ref) -> Row:
    """One setting ``v`` of method ``m``: timed, measured against ``R_ref``,
    and with Richardson's estimate of its error from a finer run of the same
    program (as ``lierk.solve(..., estimate_error=True)`` makes it)."""
    from lierk import RESULTS, finer_options

    ts_np = programs.ts_np
    eps = float(np.finfo(programs.dtype).eps)
    t1 = float(programs.t1)
    options = {"rtol": v} if m.adaptive else {"dt": v}
    run = programs.run(m, options)
    # The finer solve of `lierk.solve`'s estimate_error=True, in the same program.
    fine_options, ratio = finer_options(m.solver, **options)
    fine = programs.run(m, {k: fine_options[k] for k in ("dt", "controller") if k in fine_options})
    sol = run()  # compiles; the timed calls follow
    if not np.allclose(np.asarray(sol.ts, dtype=float), ts_np, rtol=0, atol=64 * eps * max(1.0, t1)):
        raise AssertionError(f"{m.name} saved at {np.asarray(sol.ts)}, not at the common times {ts_np}")
    result = int(sol.result)
    ok = result == RESULTS.successful
    estimate = _richardson(sol, fine(), ratio) if ok else math.nan
    best, spent = math.inf, 0.0
    for k in range(max(1, repeats)):
        start = time.perf_counter()
        run()
        took = time.perf_counter() - start
        best, spent = min(best, took), spent + took
        if k >= 1 and spent > _TIMING_BUDGET:
            break
    return Row(
        solver=m.name,
        setting="rtol" if m.adaptive else "dt",
        value=float(v),
        time=best,
        error=_max_gap(sol.R, R_ref) if ok else math.nan,
        error_estimate=estimate,
        num_steps=int(sol.stats["num_steps"]),
        num_fevals=int(sol.stats["num_fevals"]),
        result=result,
    )


def _stop(row: Row, previous: Row | None, stop_level: float) -> bool:
    """Whether a default range of settings can end after ``row``."""
    from lierk import RESULTS

    if row.setting == "rtol" and row.result == RESULTS.max_steps_reached:
        return True  # max_steps reached: tighter tolerances need still more steps
    if not row.ok:
        return False  # e.g. a fixed step too coarse to stay finite: finer ones may work
    if row.error <= stop_level:
        return True
    # Rounding: once small, an error that no longer falls will not fall further.
    return previous is not None and previous.error < 1e-6 and row.error > 0.5 * previous.error


# --------------------------------------------------------------------------


def figure(report: AccuracyReport, title: str | None = None):
    """The work-precision diagram: error against wall time, log-log.

    Top: one colour and marker per solver; solid lines with filled markers
    are the true error, dashed lines with open markers the solver's estimate
    at the same runs.  The grey band is below `AccuracyReport.floor`, where
    the reference cannot confirm an error.  Bottom: the estimate divided by
    the true error for each run above the floor (1 is a perfect estimate).

    Returns:
        A `matplotlib.figure.Figure`.
    """
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    fig = Figure(figsize=(8.0, 7.0), layout="constrained")
    ax, ax_ratio = fig.subplots(2, 1, sharex=True, height_ratios=[3, 1])
    handles = []
    tiny = 1e-16
    floor = report.floor
    for i, name in enumerate(report.solvers):
        rows = [r for r in report.rows if r.solver == name and r.ok]
        if not rows:
            continue
        colour, marker = f"C{i % 10}", _MARKERS[i % len(_MARKERS)]
        t = np.array([r.time for r in rows])
        e = np.maximum([r.error for r in rows], tiny)
        est = np.array([r.error_estimate for r in rows], dtype=float)
        est = np.where(np.isfinite(est), np.maximum(est, tiny), np.nan)
        (h,) = ax.plot(t, e, color=colour, marker=marker, ls="-", lw=1.4, ms=6, label=f"{name} ({rows[0].setting})")
        ax.plot(t, est, color=colour, marker=marker, ls="--", lw=1.0, ms=6, mfc="none", alpha=0.8)
        handles.append(h)
        above = e > floor
        ax_ratio.plot(t[above], est[above] / e[above], color=colour, marker=marker, ls="--", lw=1.0, ms=5, mfc="none")
    for a in (ax, ax_ratio):
        a.set_xscale("log")
        a.set_yscale("log")
        a.grid(True, which="major", alpha=0.3)
    ok = [r.error for r in report.rows if r.ok and r.error > 0]
    if math.isfinite(floor) and floor > 0:
        ax.axhspan(min(ok + [floor]) / 3, floor, color="0.88", zorder=0)
        handles.append(Line2D([], [], color="0.88", lw=8, label=f"below the reference's accuracy ({floor:.1e})"))
    handles += [
        Line2D([], [], color="k", ls="-", marker="o", label="true error"),
        Line2D([], [], color="k", ls="--", marker="o", mfc="none", label="error estimate"),
    ]
    ax.legend(handles=handles, fontsize=8, loc="best")
    ax.set_ylabel(r"$\max_t \|R(t) - R_{ref}(t)\|_F$")
    ax_ratio.axhline(1.0, color="k", lw=0.8)
    ax_ratio.set_ylabel("estimate / error")
    ax_ratio.set_xlabel("wall time per solve [s] (after compilation)")
    ax.set_title(
        title
        or f"{report.scene}: work against precision, T = {report.t1:g} s, errors at {len(report.ts)} times\n"
        f"reference: {report.reference}",
        fontsize=10,
    )
    return fig


def _num(x):
    return None if x is None or (isinstance(x, float) and not math.isfinite(x)) else x


def to_json(report: AccuracyReport) -> str:
    """The report as JSON text: the scene, the saved times, the reference and
    its check, every row and the cheapest row per decade (``null`` where no
    row reaches it or it is below the floor).  Non-finite numbers are ``null``."""
    rows = [{k: _num(v) for k, v in dataclasses.asdict(r).items()} for r in report.rows]
    decades = []
    for d, r in report.best_per_decade().items():
        decades.append(
            {
                "error_at_most": d,
                "below_floor": d < report.floor,
                "cheapest": None if r is None else {"row": report.rows.index(r), **rows[report.rows.index(r)]},
            }
        )
    doc = {
        "scene": report.scene,
        "t1": report.t1,
        "ts": [float(t) for t in report.ts],
        "dtype": report.dtype,
        "error": "max over ts of ||R(t) - R_ref(t)||_F",
        "time": "s, one lierk.solve call after compilation, min over repeats",
        "reference": report.reference,
        "reference_error": _num(report.reference_error),
        "check": report.check,
        "check_disagreement": _num(report.check_disagreement),
        "floor": _num(report.floor),
        "rows": rows,
        "decades": decades,
    }
    return json.dumps(doc, indent=2)
