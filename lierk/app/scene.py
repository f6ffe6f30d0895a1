"""Scenes: a rigid body, its initial state, opt-in effects and a run, from TOML.

A scene simulates only the effects it lists.  With no ``[[effects]]`` its
problem is a plain `lierk.FreeRigidBody`; otherwise it is a
`lierk.RigidBodyWithEffects` holding just those effects.

The file's format is declared once, in `lierk.app.scene_schema`: `SceneFile`
and the tables it holds, each key with its type, unit, default and
constraint (a ``*Body`` by ``body.kind``, ``*Effect`` and ``*Event`` tables
by their ``kind``).  ``lierk schema`` prints it as JSON Schema, for an editor
to complete and check scene files; ``examples/`` holds complete scenes.  A
short one:

    name = "heavy top"          # optional; default: the file name without .toml
    [body]
    kind = "sphere"             # tee_handle, box, cylinder, sphere, composite, tensor, mesh
    mass = 1.0                  # kg
    radius = 0.1                # m
    [initial]
    omega = [1.0, 2.0, 3.0]     # body angular velocity (rad/s); attitude: identity
    [[effects]]                 # zero or more; each kind at most once
    kind = "gravity"
    pivot_to_com = [0, 0, 0.1]  # body frame (m)
    [[events]]                  # zero or more: when they happen is reported
    kind = "tilt"
    angle = 0.5                 # rad
    [run]
    solver = "RKMK4"
    t1 = 10.0                   # s
    dt = 0.01                   # or rtol, or target_error

With gravity the body turns about the pivot, so the problem's inertia is the
centre-of-mass inertia moved there (`lierk.inertia.parallel_axis`) and its
state is the momentum about the pivot; otherwise the body turns about its
centre of mass.  `Scene.fixed_point` is that point in the body frame, which is
where a drawing of `Scene.body_parts` is pinned.

Every mistake raises `ValueError` before anything runs, on one line naming
the key (as a path such as ``effects[1].pivot_to_com[2]``), the value and
what is allowed.  The schema checks each key; this module checks what it
cannot say: rules across keys, rotations and non-zero axes, runs too large
to attempt (more than `MAX_STEPS` fixed steps, more than `MAX_SAVED` saved
states) and a body whose initial momentum, energy or inverse inertia
overflows, or whose state does not fit the working precision
(`lierk.checks.state_range_error`: ``|L|^2``, ``2T``, ``2T I_k``, the
moments and their product must be normal numbers; 1e300 kg m^2 spinning at 1
rad/s is refused).  An inertia no rigid body has (the triangle inequality)
is warned about once, as ``body.inertia``.

Example:
    >>> scene = lierk.app.scene.load("examples/heavy_top.toml")
    >>> sol = scene.solve()
    >>> scene.problem.invariants(sol.R, sol.y)["energy"]
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from msgspec import UNSET

from lierk import (
    RESULTS,
    SOLVERS,
    AbstractEffect,
    AbstractProblem,
    BodyTorque,
    Damping,
    FreeRigidBody,
    Gravity,
    GravityGradient,
    MagneticTorque,
    ReactionWheels,
    RigidBodyWithEffects,
    Rotor,
    SaveAt,
    Solution,
    SpaceTorque,
    TimedTorque,
    dipole_field,
    solver_class,
)

# The library's checks of a body, worded here with the scene's key paths.
from lierk import checks as validation
from lierk import inertia as _inertia
from lierk import num_steps as _num_steps
from lierk import solve as _solve
from lierk.checks import check_attitude

from . import scene_schema as schema
from .scene_schema import MAX_NAME_BYTES, MAX_SAVED, MAX_STEPS

__all__ = ["Scene", "load", "from_dict", "identifier"]

_DEFAULT_N_SAVE = 1001


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A loaded scene; `lierk.app.scene_schema` declares the file format.

    Attributes:
        name: the scene's name.
        problem: `lierk.FreeRigidBody` without effects, else
            `lierk.RigidBodyWithEffects`.
        solver: a lierk solver instance.
        t1: end time (s); runs start at 0.
        solve_kwargs: keyword arguments for `lierk.solve` besides ``saveat``:
            ``{"dt": ...}``, ``{"rtol": ..., "atol": ...[, "max_steps": ...]}``
            or ``{"target_error": ...[, "max_steps": ...]}``.
        saveat_every: fixed step: save every k-th step (None otherwise).
        n_save: rtol or target_error: number of equally spaced output times
            in ``[0, t1]`` (None with a fixed step).
        body_parts: the solids for drawing (`lierk.inertia.Part`, offsets in the
            body frame, ``shape`` one of ``("cylinder", radius, length, axis)``,
            ``("box", lx, ly, lz)``, ``("sphere", radius)``), or None for ``kind = "tensor"``.
        effects: the effects, in file order (empty without effects).
        mass: total mass (kg), or None if unknown (``kind = "tensor"`` without mass).
        center_of_mass: ``(3,)`` centre of mass in the body frame (m).
        fixed_point: ``(3,)`` the point of the body frame that stays put in
            space: the pivot with gravity, else the centre of mass (m).
            A body point ``x`` is drawn at ``R (x - fixed_point)``.
        description: free text from the file.
        events: ``(name, lierk.Event)`` pairs from ``[[events]]``, in file
            order; `solve` passes the events to `lierk.solve`.
    """

    name: str
    problem: AbstractProblem
    solver: Any
    t1: float
    solve_kwargs: dict
    saveat_every: int | None
    n_save: int | None
    body_parts: list | None
    effects: tuple
    mass: float | None
    center_of_mass: np.ndarray
    fixed_point: np.ndarray
    description: str = ""
    events: tuple = ()

    @property
    def adaptive(self) -> bool:
        """True unless the scene gives a fixed step ``dt``: with ``rtol`` or
        ``target_error`` the steps are chosen by the solve, and the scene
        saves at ``n_save`` equally spaced times."""
        return "dt" not in self.solve_kwargs

    @property
    def target_error(self) -> float | None:
        """``run.target_error``, or None when the scene gives ``dt`` or ``rtol``."""
        return self.solve_kwargs.get("target_error")

    @property
    def file_stem(self) -> str:
        """The scene's name as the start of file names (`identifier`; ``"scene"``
        if nothing is left of it)."""
        return identifier(self.name) or "scene"

    def describe_run(self, solution: Solution | None = None) -> str:
        """The solver and its run settings as text: ``"RKMK4, dt = 0.01 s"``,
        ``"DP54, rtol = 1e-08, atol = 1e-10"`` or ``"RKMK4, target_error = 1e-06"``;
        with the `Solution` of a ``target_error`` run, the setting it chose too
        (``"... (chose dt = 0.005 s)"``, `Solution.chosen_setting`)."""
        kw = self.solve_kwargs
        if "dt" in kw:
            settings = f"dt = {kw['dt']:g} s"
        elif "target_error" in kw:
            settings = f"target_error = {kw['target_error']:g}"
            if solution is not None:
                settings = f"{settings} (chose {solution.chosen_setting()})"
        else:
            settings = f"rtol = {kw['rtol']:g}, atol = {kw['atol']:g}"
        return f"{self.solver.name}, {settings}"

    @property
    def euler_convention(self) -> str:
        """The Euler angles that read best for this scene (`lierk.so3.to_euler`):
        ``"zxz"`` (precession, nutation, spin) for a top under `Gravity`,
        whose Z-Y-X angles would ramp with the spin; ``"zyx"`` otherwise."""
        return "zxz" if any(isinstance(e, Gravity) for e in self.problem.effects) else "zyx"

    def check_single_precision(self) -> None:
        """Raise `ValueError` naming the first setting (``t1``, ``run.dt``,
        ``run.rtol``, ``run.atol``, ``run.target_error``) that float32 cannot
        hold: outside its range (1e300 would become inf, 1e-50 zero)."""
        info = np.finfo(np.float32)
        tiny, big = float(info.tiny), float(info.max)
        values = {
            "t1": self.t1,
            **{k: v for k, v in self.solve_kwargs.items() if k in ("dt", "rtol", "atol", "target_error")},
        }
        for k, v in values.items():
            if not tiny <= v <= big:
                raise ValueError(
                    f"{'t1' if k == 't1' else 'run.' + k} = {v:g} is outside single precision's range "
                    f"({tiny:.2g} to {big:.2g})"
                )

    def saveat(self) -> SaveAt:
        """Fixed step: the initial state and every ``saveat_every``-th step (the
        last state too when the step count is not a multiple).  ``rtol`` or
        ``target_error``: ``n_save`` equally spaced times from 0 to ``t1``
        (``target_error`` cannot save steps: they differ per setting tried)."""
        if self.adaptive:
            return SaveAt(ts=jnp.linspace(0.0, self.t1, self.n_save, dtype=self.problem.R0.dtype))
        return SaveAt(t0=True, steps=self.saveat_every, t1=True)

    def with_target_error(self, target_error: float) -> "Scene":
        """This scene run with ``target_error`` instead of its ``dt``/``rtol``.

        The solver is kept and chooses its own step or tolerances.  The scene
        then saves at ``n_save`` equally spaced times: its own ``n_save`` if
        it has one, else as many points as its fixed-step run saves, so the
        output keeps the resolution the scene asked for.  A ``max_steps``
        given for ``rtol`` is dropped (it bounded steps at that tolerance).

        Raises:
            ValueError: ``target_error`` is not a finite number > 0.
        """
        eps = _positive(target_error, "target_error")
        kw = {"target_error": eps}
        if self.target_error is not None and "max_steps" in self.solve_kwargs:
            kw["max_steps"] = self.solve_kwargs["max_steps"]
        n_save = self.n_save if self.n_save is not None else max(2, self.saved_count())
        return dataclasses.replace(self, solve_kwargs=kw, saveat_every=None, n_save=n_save)

    def with_t1(self, t1: float) -> "Scene":
        """This scene run to end time ``t1`` (s) instead, checked as ``run.t1`` is.

        Raises:
            ValueError: ``t1`` is not a finite number > 0, or the run would
                take more than `MAX_STEPS` fixed steps or save more than
                `MAX_SAVED` states.
        """
        t1 = _positive(t1, "t1")
        _check_run_size(t1, self.solve_kwargs, self.saveat_every, "t1")
        return dataclasses.replace(self, t1=t1)

    def solve(self, *, n_pieces: int | None = None, progress: bool = False, **overrides) -> Solution:
        """``lierk.solve(problem, solver, t1, saveat=self.saveat(), **solve_kwargs)``;
        keyword ``overrides`` replace entries (e.g. ``throw=False``).

        With ``n_pieces`` or ``progress``, the run is solved in pieces (20 by
        default), each a `lierk.solve` from the end state of the one before,
        compiled once before the first runs.  ``progress=True`` shows the
        compilation and then the simulated time on stderr (elapsed, rate,
        time left).  The pieces save exactly the times one solve saves; the
        states agree with one solve to rounding with a fixed step, and to the
        tolerance with ``rtol`` (each piece picks its first step anew).  A ``target_error`` run
        is solved in one piece: its bound holds over the whole run, and a
        setting chosen on a first piece would not bound the rest.

        Args:
            n_pieces: the number of pieces (a positive int), or None.
            progress: report progress on stderr.
            **overrides: replace `lierk.solve` arguments; in pieces only
                ``throw`` may be given.

        Returns:
            A `Solution`: ``ts`` ``(n_saved,)`` in s, ``R`` ``(n_saved, 3, 3)``,
            ``y`` the state besides ``R`` at those times; in pieces ``stats``
            holds Python ints (summed over pieces) and, with
            ``target_error``, the setting chosen.

        Raises:
            ValueError: ``n_pieces`` is not a positive int, or overrides other
                than ``throw`` are given with pieces.
            RuntimeError: with ``throw=True`` (default), a piece failed; the
                message names the interval and the `lierk.RESULTS` code's
                meaning.  With ``throw=False`` the solution up to and
                including the failed piece comes back with its result code.
        """
        if self.target_error is not None and self.events:
            return self._target_error_then_events(n_pieces, progress, overrides)
        if n_pieces is None and not progress:
            kwargs = {"saveat": self.saveat(), **self.solve_kwargs, **self._event_kwargs(), **overrides}
            return _solve(self.problem, self.solver, self.t1, **kwargs)
        if n_pieces is not None and not (
            isinstance(n_pieces, (int, np.integer)) and not isinstance(n_pieces, bool) and n_pieces >= 1
        ):
            raise ValueError(f"n_pieces must be a positive int, got {n_pieces!r}")
        unknown = set(overrides) - {"throw"}
        if unknown:
            raise ValueError(
                f"a scene solved in pieces takes only throw= as an override, got {', '.join(sorted(unknown))}"
            )
        from .segments import N_PIECES, solve_in_pieces

        return solve_in_pieces(
            self, N_PIECES if n_pieces is None else int(n_pieces), progress, overrides.get("throw", True)
        )

    def _target_error_then_events(self, n_pieces, progress, overrides) -> Solution:
        """A ``target_error`` run with events.  `lierk.solve` takes no events
        with ``target_error`` (its solves would stop at different times), so
        the setting is chosen first, by the run without the events, and the
        events are found by a second solve at the setting it chose.  The
        solution is the first run's (its saved states and error estimate),
        with the second's event records, its result and, where a
        terminating event ended the run, only the saved times up to there
        (the rest padding, as a solve stopped by an event leaves it);
        ``stats`` are the first run's, with ``num_solves`` counting the
        second solve too."""
        chosen = dataclasses.replace(self, events=()).solve(n_pieces=n_pieces, progress=progress, **overrides)
        if int(chosen.result) != 0:
            return chosen  # with throw=False: the failed run, without events, as it came back
        if "dt" in chosen.stats:
            setting = {"dt": float(chosen.stats["dt"])}
        else:
            rtol = float(chosen.stats["rtol"])
            setting = {"rtol": rtol, "atol": rtol, "max_steps": self.solve_kwargs.get("max_steps")}
        found = _solve(
            self.problem,
            self.solver,
            self.t1,
            saveat=SaveAt(t1=True),
            throw=overrides.get("throw", True),
            **setting,
            **self._event_kwargs(),
        )
        ts = np.asarray(chosen.ts)
        keep = np.ones(ts.shape, bool)
        if int(found.result) == RESULTS.event_occurred:
            keep = ts <= float(found.trajectory()[0][-1])

        def cut(x):
            # NumPy, then one transfer: eager jax.numpy compiles a program per call.
            x = np.asarray(x)
            return jax.device_put(np.where(keep.reshape(keep.shape + (1,) * (x.ndim - 1)), x, np.nan))

        stats = {**chosen.stats, "num_solves": int(chosen.stats["num_solves"]) + 1}
        return dataclasses.replace(
            chosen,
            R=cut(chosen.R),
            y=jax.tree_util.tree_map(cut, chosen.y),
            error_estimate=cut(chosen.error_estimate),
            n_saved=jax.device_put(np.asarray(keep.sum(), np.asarray(chosen.n_saved).dtype)),
            result=found.result,
            events=found.events,
            stats=stats,
        )

    def _event_kwargs(self) -> dict:
        return {"event": tuple(e for _, e in self.events)} if self.events else {}

    def with_flip_event(self) -> "Scene":
        """This scene with the intermediate-axis flip among its events
        (`lierk.conditions.flip`, named ``"flip"``), when its body has three
        distinct principal moments and the scene has no flip event yet; the
        scene itself otherwise.  ``lierk simulate`` reports and marks flips this way
        (`lierk.app.simulation.simulate`); a solver that cannot locate events
        (ExplicitEuler) refuses the event when the scene is solved, and
        ``simulate`` then solves without it and says so."""
        if any(name == "flip" for name, _ in self.events):
            return self
        moments = np.linalg.eigvalsh(np.asarray(self.problem.inertia, dtype=float))
        if not (moments[0] < moments[1] < moments[2]):
            return self
        from ..conditions import flip

        return dataclasses.replace(self, events=self.events + (("flip", flip(self.problem)),))

    def event_times(self, solution: Solution) -> dict[str, np.ndarray]:
        """The times (s) each of the scene's events happened in ``solution``
        (a solve of this scene), by name, in order (host NumPy arrays)."""
        records = solution.events if solution.events is not None else ()
        out = {}
        for (name, _), r in zip(self.events, records):
            ts = np.asarray(r.ts)
            out[name] = ts[np.isfinite(ts)]
        return out

    def saved_count(self) -> int:
        """How many states a run of this scene saves (times included)."""
        if self.adaptive:
            return self.n_save
        n = _num_steps(0.0, self.t1, self.solve_kwargs["dt"])
        return 1 + n // self.saveat_every + (1 if n % self.saveat_every else 0)

    def bytes_per_saved(self) -> int:
        """Bytes of one saved point: its time, ``R`` (9 numbers) and the state
        besides ``R``, in the problem's dtype."""
        from jax.tree_util import tree_leaves

        y = sum(int(np.size(x)) for x in tree_leaves(self.problem.y0))
        return (1 + 9 + y) * np.dtype(self.problem.R0.dtype).itemsize


def identifier(name: str) -> str:
    """``name`` as a key for file names and `numpy.savez`: ``|x|`` becomes
    ``abs_x`` and each run of characters other than letters, digits and
    ``_`` one ``_``, none at the ends (``"|L|"`` -> ``"abs_L"``,
    ``"heavy top"`` -> ``"heavy_top"``; may be empty)."""
    name = re.sub(r"\|(\w+)\|", r"abs_\1", name)
    return re.sub(r"\W+", "_", name).strip("_")


def load(path: str | os.PathLike) -> Scene:
    """Read a scene from a TOML file.  Raises `ValueError` if it is not valid
    TOML (or not UTF-8) or not a valid scene (the message names the file),
    and `OSError` if it cannot be read."""
    path = os.fspath(path)
    with open(path, "rb") as f:
        try:
            d = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise ValueError(f"{path}: not valid TOML: {e}") from None
        except UnicodeDecodeError as e:
            raise ValueError(
                f"{path}: not valid TOML: not UTF-8 text "
                f"(byte {e.object[e.start : e.start + 1].hex()} at offset {e.start})"
            ) from None
    stem = os.path.splitext(os.path.basename(path))[0]
    try:
        return from_dict(d, name=stem, directory=os.path.dirname(path))
    except ValueError as e:
        # One line: arrays in messages (np.array2string) span several.
        raise ValueError(f"{path}: {' '.join(str(e).split())}") from None


def from_dict(d: dict, name: str = "scene", directory: str | os.PathLike = ".") -> Scene:
    """Build a scene from a parsed TOML document (a dict); ``d["name"]``, if
    present, overrides ``name``.  Relative file names in it (a mesh) are
    read from ``directory`` (`load`: the scene file's).

    Warns once (`UserWarning`) about a ``body.inertia`` no rigid body has
    (the triangle inequality) and about an inertia nearly singular for the
    working precision; the problem, its effects and events, built from the
    same inertia, do not warn again."""
    # Overflows are reported as errors below, not as NumPy warnings.  The
    # inertia is warned about here, by its key, not again by each object
    # built from it (lierk.inertia.tensor, the problem, a gravity gradient).
    with np.errstate(all="ignore"), validation.inertia_warned():
        scene, warnings_ = _from_dict(d, name, directory)
    for text in warnings_:
        warnings.warn(text, stacklevel=3)
    return scene


def _from_dict(d: dict, name: str, directory: str | os.PathLike = ".") -> tuple[Scene, list[str]]:
    """The scene, and the warnings it deserves (given by `from_dict`)."""
    f = schema.parse(d)
    body = _body(f.body, directory)
    # The body as given, before gravity moves its inertia to the pivot (which
    # can hide an impossible one); solids always keep the triangle inequality.
    impossible = validation.impossible_inertia(body.inertia, "body.inertia") if body.parts is None else None
    omega0 = np.array(f.initial.omega)
    R0 = _orientation(f.initial, "initial", ("attitude", "matrix", "quaternion", "mrp", "euler"))
    R0 = np.eye(3) if R0 is None else R0
    effects, pivot_to_com = _effects(f.effects, body)
    solver, t1, solve_kwargs, every, n_save = _run(f.run)

    if not effects:
        inertia = body.inertia
        fixed_point = body.com
    elif pivot_to_com is not None:
        mass = body.mass if body.mass is not None else float(next(e for e in effects if isinstance(e, Gravity)).mass)
        inertia = np.asarray(_inertia.parallel_axis(body.inertia, mass, pivot_to_com), dtype=float)
        fixed_point = body.com - pivot_to_com
    else:
        inertia = body.inertia
        fixed_point = body.com
    # In JAX's default float type (float32 unless x64 is on), so that building
    # the problem does not ask JAX for float64 it would truncate, with a warning.
    dtype = jnp.result_type(float)
    _check_state(
        inertia,
        omega0,
        dtype,
        "body" if pivot_to_com is None else "body about the gravity pivot",
        "body.inertia" if body.parts is None and pivot_to_com is None else "inertia",
    )
    if "rtol" in solve_kwargs:
        # The rule lierk.solve applies, checked before anything runs.
        reason = validation.tolerances_below_rounding(solve_kwargs["rtol"], solve_kwargs["atol"], dtype)
        if reason is not None:
            raise ValueError(f"run.rtol = {solve_kwargs['rtol']:g}, run.atol = {solve_kwargs['atol']:g}: {reason}")
    singular = validation.nearly_singular_inertia(inertia, dtype, "the body's inertia")
    inertia, omega0, R0 = (np.asarray(a, dtype=dtype) for a in (inertia, omega0, R0))
    if not effects:
        problem = FreeRigidBody(inertia, omega0, R0)
    else:
        problem = RigidBodyWithEffects(inertia, omega0, R0, effects)
    name = _given(f, "name", name)
    stem = identifier(name)
    if len(stem.encode()) > MAX_NAME_BYTES:
        # Found before the run, not when its outputs are written.
        raise ValueError(
            f"name: the outputs are named after it ({stem[:20]}..._components.png), and {len(stem.encode())} bytes "
            f"is more than a file name may take ({MAX_NAME_BYTES} bytes and the suffix); shorten it"
        )
    scene = Scene(
        events=_events(f.events, problem, pivot_to_com),
        name=name,
        problem=problem,
        solver=solver,
        t1=t1,
        solve_kwargs=solve_kwargs,
        saveat_every=every,
        n_save=n_save,
        body_parts=body.parts,
        effects=effects,
        mass=body.mass,
        center_of_mass=body.com,
        fixed_point=np.asarray(fixed_point, dtype=float),
        description=f.description,
    )
    return scene, [text for text in (impossible, singular) if text is not None]


# --- what the schema cannot say ----------------------------------------------------
# `schema.parse` has checked every key's type and range, and that numbers are
# finite; the rules across keys are checked here, on its Structs.


def _given(table, key: str, default=None):
    """``table.key``, or ``default`` where the file leaves it out."""
    value = getattr(table, key, UNSET)
    return default if value is UNSET else value


def _exactly_one(table, keys: tuple, path: str, what: str) -> str:
    """The one of ``keys`` that ``table`` gives; ``what`` says which when not one is given."""
    given = [k for k in keys if _given(table, k) is not None]
    if len(given) != 1:
        raise ValueError(f"{path}: {what}, got {given or 'neither'}")
    return given[0]


def _kind(table) -> str:
    return type(table).__struct_config__.tag


def _positive(x, path: str) -> float:
    """A finite number > 0 given to a `Scene` method (files are checked by the schema)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise ValueError(f"{path} must be a finite number, got {x!r}")
    if not x > 0:
        raise ValueError(f"{path} must be > 0, got {x!r}")
    return float(x)


def _sized(values: list, n: int, path: str) -> np.ndarray:
    """``values`` (numbers) as an array of ``n`` (one per wheel)."""
    if len(values) != n:
        raise ValueError(f"{path} must be a list of {n} numbers, got {values!r}")
    return np.array(values, dtype=float)


def _orientation(table, path: str, keys: tuple) -> np.ndarray | None:
    """The rotation one of ``keys`` gives (``attitude``, ``matrix``,
    ``quaternion``, ``mrp``, ``euler``), checked to be in SO(3); None if
    none is given."""
    given = [k for k in keys if _given(table, k) is not None]
    if len(given) > 1:
        raise ValueError(f"{path}: give at most one of {', '.join(given)}")
    if not given:
        return None
    if given == ["attitude"]:  # the schema allows only "identity"
        return np.eye(3)
    k = given[0]
    x, p = np.array(getattr(table, k), dtype=float), f"{path}.{k}"
    if k == "quaternion":
        if not np.linalg.norm(x) > 1e-12:
            raise ValueError(f"{p} must be a nonzero quaternion [w, x, y, z], got {getattr(table, k)!r}")
        R = _quaternion_matrix(x / np.linalg.norm(x))
    elif k == "mrp":
        R = _mrp_matrix(x)
    elif k == "euler":
        R = _euler_matrix(*x)
    else:
        R = x
    try:
        return np.asarray(check_attitude(R, jnp.result_type(float)), dtype=float)
    except ValueError as e:
        raise ValueError(f"{p}: {e}") from None


# --- body ----------------------------------------------------------------------


@dataclasses.dataclass
class _Body:
    mass: float | None
    com: np.ndarray
    inertia: np.ndarray  # about the centre of mass, body frame
    parts: list | None


def _solid(s) -> tuple[np.ndarray, tuple]:
    """``(inertia about its centre in its own frame, shape)`` of a box, cylinder or sphere."""
    if isinstance(s, schema.BoxBody):
        return np.asarray(_inertia.box(s.mass, s.lx, s.ly, s.lz)), ("box", s.lx, s.ly, s.lz)
    if isinstance(s, schema.SphereBody):
        return np.asarray(_inertia.sphere(s.mass, s.radius)), ("sphere", s.radius)
    I = _inertia.solid_cylinder(s.mass, s.radius, s.length, s.axis)
    return np.asarray(I), ("cylinder", s.radius, s.length, s.axis)


def _body(b, directory=".") -> _Body:
    if isinstance(b, schema.MeshBody):
        path = b.file if os.path.isabs(b.file) else os.path.join(os.fspath(directory), b.file)
        try:
            props = _inertia.from_mesh(path, b.density, b.scale)
        except ValueError as e:
            raise ValueError(f"body.file {b.file!r}: {e}") from None
        part = _inertia.Part(
            props.mass, props.inertia, props.center_of_mass, None, ("mesh", props.mesh.triangles - props.center_of_mass)
        )
        return _Body(props.mass, props.center_of_mass, props.inertia, [part])
    if isinstance(b, schema.TensorBody):
        rows = [isinstance(x, list) for x in b.inertia]
        if any(rows) and not all(rows):
            raise ValueError(f"body.inertia must be a list of 3 numbers or a 3x3 matrix, got {b.inertia!r}")
        I = np.array(b.inertia, dtype=float) if all(rows) else np.diag(b.inertia)
        try:
            I = np.asarray(_inertia.tensor(I), dtype=float)
        except ValueError as e:
            raise ValueError(f"body.inertia: {e}") from None
        return _Body(_given(b, "mass"), np.zeros(3), I, None)
    if isinstance(b, schema.TeeHandleBody):
        parts = _inertia.tee_handle_parts(b.handle_length, b.handle_radius, b.shaft_length, b.shaft_radius, b.density)
    elif isinstance(b, schema.CompositeBody):
        parts = []
        for i, part in enumerate(b.parts):
            Q = _orientation(part, f"body.parts[{i}]", ("matrix", "quaternion", "euler"))
            I, shape = _solid(part)
            parts.append(_inertia.Part(part.mass, I, np.array(part.offset, dtype=float), Q, shape))
    else:
        I, shape = _solid(b)
        parts = [_inertia.Part(b.mass, I, np.zeros(3), None, shape)]
    c = _inertia.composite(parts)
    return _Body(float(c.mass), np.asarray(c.center_of_mass, dtype=float), np.asarray(c.inertia, dtype=float), parts)


# --- effects -------------------------------------------------------------------


def _effects(items: list, body: _Body) -> tuple[tuple[AbstractEffect, ...], np.ndarray | None]:
    effects, seen, pivot_to_com = [], set(), None
    for i, e in enumerate(items):
        p, kind = f"effects[{i}]", _kind(e)
        if kind in seen:
            raise ValueError(f"{p}.kind = {kind!r} appears twice; each effect kind may be given once")
        seen.add(kind)
        if isinstance(e, schema.GravityEffect):
            pivot_to_com = _gravity(e, p, body)
            effects.append(Gravity(pivot_to_com, body.mass if _given(e, "mass") is None else e.mass, e.g))
        elif isinstance(e, schema.BodyTorqueEffect):
            effects.append(BodyTorque(np.array(e.torque)))
        elif isinstance(e, schema.SpaceTorqueEffect):
            effects.append(SpaceTorque(np.array(e.torque)))
        elif isinstance(e, schema.TimedTorqueEffect):
            if len(e.torque) != len(e.times):
                raise ValueError(f"{p}.torque must list one [x, y, z] per time ({len(e.times)}), got {e.torque!r}")
            effects.append(TimedTorque(np.array(e.torque), times=np.array(e.times), frame=e.frame))
        elif isinstance(e, schema.DampingEffect):
            effects.append(Damping(e.c))
        else:
            effects.append(_SPACECRAFT[kind](e, p, body))
    return tuple(effects), pivot_to_com


def _gravity(e, p: str, body: _Body) -> np.ndarray:
    """Gravity's vector pivot -> centre of mass; its mass must be the body's."""
    which = _exactly_one(e, ("pivot_to_com", "pivot"), p, "gravity needs exactly one of 'pivot_to_com' or 'pivot'")
    if _given(e, "mass") is not None:
        # One mass for both the torque and the parallel-axis shift of the
        # inertia to the pivot, or the top is not a rigid body.
        if body.mass is not None and abs(e.mass - body.mass) > 1e-9 * body.mass:
            raise ValueError(
                f"{p}.mass = {e.mass:g} kg differs from the body's mass {body.mass:g} kg; gravity acts on "
                "the body's own mass (leave 'mass' out), or give the body that mass"
            )
    elif body.mass is None:
        raise ValueError(f"{p}.mass is required: body kind 'tensor' was given without a mass")
    return body.com - np.array(e.pivot) if which == "pivot" else np.array(e.pivot_to_com)


def _orbit(e, p: str) -> dict:
    """The circular orbit of a spacecraft effect: ``radius`` (m) or ``mean_motion`` (rad/s)."""
    k = _exactly_one(
        e, ("radius", "mean_motion"), p, "give the orbit as exactly one of 'radius' (m) or 'mean_motion' (rad/s)"
    )
    return {k: getattr(e, k)}


def _gravity_gradient(e, p: str, body: _Body):
    return GravityGradient(body.inertia, mu=e.mu, phase=e.phase, **_orbit(e, p))


def _magnetic(e, p: str, body: _Body):
    field = dipole_field(**_orbit(e, p), tilt=e.tilt, B0=e.B0, phase=e.phase)
    if (
        _exactly_one(
            e, ("dipole", "bdot_gain"), p, "magnetic needs exactly one of 'dipole' (A m^2, body frame) or 'bdot_gain'"
        )
        == "dipole"
    ):
        return MagneticTorque(field, dipole=np.array(e.dipole))
    return MagneticTorque(field, bdot_gain=e.bdot_gain)


def _rotor(e, p: str, body: _Body):
    if _given(e, "axes") is None:
        for k in ("torque", "times"):
            if _given(e, k) is not None:
                raise ValueError(f"{p}.{k}: motor torques act along wheel axes; give 'axes' too")
        return Rotor(_sized(e.momentum, 3, f"{p}.momentum"))
    axes = np.array(e.axes)
    k = len(axes)
    momentum = _sized(e.momentum, k, f"{p}.momentum")
    if (_given(e, "torque") is None) != (_given(e, "times") is None):
        raise ValueError(f"{p}: motor torques need both 'torque' (one row of {k} per time, N m) and 'times' (s)")
    if _given(e, "torque") is None:
        return Rotor(momentum, axes=axes)
    if len(e.torque) != len(e.times):
        raise ValueError(f"{p}.torque must list one row of {k} wheel torques per time, got {e.torque!r}")
    torque = np.stack([_sized(row, k, f"{p}.torque[{j}]") for j, row in enumerate(e.torque)])
    return Rotor(momentum, axes=axes, torque=torque, times=np.array(e.times))


def _reaction_wheels(e, p: str, body: _Body):
    axes = np.array(e.axes)
    for j, a in enumerate(axes):
        if not np.any(a):
            raise ValueError(f"{p}.axes[{j}] must be a non-zero vector, got {e.axes[j]!r}")
    k = len(axes)
    spin = _sized(e.spin_inertia, k, f"{p}.spin_inertia")
    speeds = _sized(e.speeds, k, f"{p}.speeds") if _given(e, "speeds") is not None else np.zeros(k)
    torque, times = _given(e, "torque"), _given(e, "times")
    rows = [isinstance(u, list) for u in torque] if torque is not None else []
    if times is not None:
        times = np.array(times)
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"{p}.times must be strictly increasing, got {validation.show(times)}")
        if torque is None:
            raise ValueError(f"{p}: times need torque = [[u1, ...], ...], one row of {k} motor torques (N m) per time")
        if len(torque) != len(times) or not all(rows):
            raise ValueError(
                f"{p}.torque must list one row of {k} motor torques (N m) per time ({len(times)}), got {torque!r}"
            )
        torque = np.stack([_sized(u, k, f"{p}.torque[{j}]") for j, u in enumerate(torque)])
    elif any(rows):
        raise ValueError(f"{p}.torque: rows of motor torques need times = [...] (s), one per row")
    elif torque is not None:
        torque = _sized(torque, k, f"{p}.torque")
    return ReactionWheels(axes, spin, speeds, torque=torque, times=times)


_SPACECRAFT = {
    "gravity_gradient": _gravity_gradient,
    "magnetic": _magnetic,
    "rotor": _rotor,
    "reaction_wheels": _reaction_wheels,
}

# --- events --------------------------------------------------------------------

_CROSSING = {"both": 0, "up": 1, "down": -1}


def _events(items: list, problem, pivot_to_com: np.ndarray | None) -> tuple:
    from lierk import conditions

    events, names = [], set()
    for i, ev in enumerate(items):
        p, kind = f"events[{i}]", _kind(ev)
        name = _given(ev, "name", kind)
        if name in names:
            raise ValueError(f"{p}.name = {name!r} is taken by an earlier event; give each a name of its own")
        names.add(name)
        for key in ("axis", "target"):
            if _given(ev, key) is not None and not np.any(getattr(ev, key)):
                raise ValueError(f"{p}.{key} must be a non-zero vector, got {getattr(ev, key)!r}")
        default_axis = pivot_to_com if pivot_to_com is not None else np.array([0.0, 0.0, 1.0])
        axis = np.array(_given(ev, "axis", default_axis), dtype=float)
        crossing, terminate = _CROSSING[_given(ev, "crossing", "both")], ev.terminate
        if kind == "flip":
            event = conditions.flip(problem, terminate=terminate)
        elif kind == "tilt":
            event = conditions.tilt(ev.angle, axis, terminate=terminate, direction=crossing)
        elif kind == "tilt_extremum":
            event = conditions.tilt_extremum(problem, axis, terminate=terminate, extremum=ev.extremum)
        elif kind == "pointing":
            event = conditions.pointing(axis, np.array(ev.target), ev.angle, terminate=terminate, direction=crossing)
        else:
            drift = conditions.energy_drift if kind == "energy" else conditions.momentum_drift
            event = drift(problem, ev.threshold, terminate=terminate)
        events.append((name, event))
    return tuple(events)


# --- run -----------------------------------------------------------------------


_RUN_MODES = (
    "run: give exactly one of 'dt' (fixed step), 'rtol' (adaptive, with optional 'atol') "
    "or 'target_error' (the solver chooses its step or tolerances)"
)


def _run(r):
    solver = solver_class(r.solver)()  # the schema allows only solvers' names
    modes = [k for k in ("dt", "rtol", "target_error") if _given(r, k) is not None]
    if len(modes) != 1:
        raise ValueError(_RUN_MODES + (f"; got {', '.join(modes)}" if modes else ""))
    if modes == ["dt"]:
        for k in ("atol", "n_save", "max_steps"):
            if _given(r, k) is not None:
                raise ValueError(f"run.{k} applies to adaptive runs (rtol=), not to a fixed step dt = {r.dt!r}")
        every = _given(r, "save_every", 1)
        _check_run_size(r.t1, {"dt": r.dt}, every, "run.t1")
        return solver, r.t1, {"dt": r.dt}, every, None
    if modes == ["target_error"]:
        if _given(r, "atol") is not None:
            raise ValueError(
                "run.atol applies to rtol runs; with run.target_error the solver chooses its tolerances itself"
            )
        if _given(r, "save_every") is not None:
            raise ValueError(
                "run.save_every applies to fixed-step runs (dt=); runs with run.target_error save at run.n_save times"
            )
        kw = {"target_error": r.target_error}
    else:
        if not solver.adaptive:
            # `adaptive` is a property on RKMK-family classes: ask instances.
            adaptive = [n for n, c in SOLVERS.items() if c().adaptive]
            raise ValueError(
                f"run.solver = {r.solver!r} has no error estimate, so it needs run.dt (or run.target_error); "
                f"adaptive solvers (for rtol): {', '.join(adaptive)}"
            )
        if _given(r, "save_every") is not None:
            raise ValueError("run.save_every applies to fixed-step runs (dt=); adaptive runs use run.n_save")
        kw = {"rtol": r.rtol, "atol": _given(r, "atol", r.rtol)}
    if _given(r, "max_steps") is not None:
        kw["max_steps"] = r.max_steps
    return solver, r.t1, kw, None, _given(r, "n_save", _DEFAULT_N_SAVE)


def _check_state(inertia: np.ndarray, omega0: np.ndarray, dtype, what: str, key: str) -> None:
    """The body's inverse inertia, initial momentum and energy must be finite
    (a body of 1e-320 kg m^2, or 1e200 kg m^2 spinning at 1e200 rad/s, is
    not), and its state must fit ``dtype`` (`lierk.checks.state_range_error`:
    |L|^2 of 1e300 kg m^2 at 1 rad/s overflows, although |L| does not).
    ``key`` names the inertia in messages."""
    inertia = np.asarray(inertia, dtype=float)
    with np.errstate(all="ignore"):
        finite = np.isfinite(inertia).all()
        try:
            inv = np.linalg.inv(inertia)
        except np.linalg.LinAlgError:
            inv = np.full((3, 3), np.inf)
        m = inertia @ omega0
        energy = 0.5 * float(omega0 @ m)
    if not finite:
        raise ValueError(
            f"{what}: the inertia is not finite (too large, or a mass or size too small): {validation.show(inertia)}"
        )
    if not np.isfinite(inv).all():
        raise ValueError(f"{what}: the inertia {validation.show(inertia)} kg m^2 is singular or too small to invert")
    if not np.isfinite(m).all():
        raise ValueError(
            f"{what}: the initial momentum I omega overflows (inertia {validation.show(inertia)} kg m^2, "
            f"omega {validation.show(omega0)} rad/s)"
        )
    if not math.isfinite(energy):
        raise ValueError(
            f"{what}: the initial kinetic energy omega . I omega / 2 overflows "
            f"(inertia {validation.show(inertia)} kg m^2, "
            f"omega {validation.show(omega0)} rad/s)"
        )
    reason = validation.state_range_error(inertia, omega0, dtype)
    if reason is not None:
        shown = np.diagonal(inertia) if not np.any(inertia - np.diag(np.diagonal(inertia))) else inertia
        raise ValueError(
            f"{what}: {key} = {validation.show(shown)} kg m^2 "
            f"with initial.omega = {validation.show(omega0)} rad/s: {reason}"
        )


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """`lierk.so3.from_quaternion` of a unit ``q = (w, x, y, z)``, in NumPy."""
    w, x, y, z = q
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + 2.0 * w * K + 2.0 * (K @ K)


def _mrp_matrix(sigma: np.ndarray) -> np.ndarray:
    """`lierk.so3.from_mrp` of modified Rodrigues parameters, in NumPy."""
    x, y, z = sigma
    S = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s2 = float(sigma @ sigma)
    return np.eye(3) + (8.0 * S @ S + 4.0 * (1.0 - s2) * S) / (1.0 + s2) ** 2


def _euler_matrix(phi: float, theta: float, psi: float) -> np.ndarray:
    """`lierk.so3.from_euler` (``R = Rz(phi) Ry(theta) Rx(psi)``), in NumPy."""
    c, s = np.cos([phi, theta, psi]), np.sin([phi, theta, psi])
    Rz = np.array([[c[0], -s[0], 0.0], [s[0], c[0], 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[c[1], 0.0, s[1]], [0.0, 1.0, 0.0], [-s[1], 0.0, c[1]]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, c[2], -s[2]], [0.0, s[2], c[2]]])
    return Rz @ Ry @ Rx


def _check_run_size(t1: float, kw: dict, every: int | None, t1_name: str) -> None:
    """A fixed-step run may take at most `MAX_STEPS` steps and save at most
    `MAX_SAVED` states (adaptive runs: ``n_save`` is bounded where it is read)."""
    if "dt" not in kw:
        return
    dt = kw["dt"]
    steps = t1 / dt  # inf when it overflows (dt = 1e-320)
    if not steps <= MAX_STEPS:
        raise ValueError(
            f"{t1_name} / run.dt = {t1!r} s / {dt!r} s is {steps:.3g} steps, more than a run may take "
            f"({MAX_STEPS}): raise run.dt or lower {t1_name}"
        )
    if steps / every > MAX_SAVED:
        raise ValueError(
            f"saving every {every} of {steps:.3g} steps keeps {steps / every:.3g} states, more than a run may save "
            f"({MAX_SAVED:g}): raise run.save_every"
        )
