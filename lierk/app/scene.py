"""Scenes: a rigid body, its initial state, opt-in effects and a run, from TOML.

A scene simulates only the effects it lists.  With no ``[[effects]]`` its
problem is a plain `lierk.FreeRigidBody`; otherwise it is a
`lierk.RigidBodyWithEffects` holding just those effects.

Schema (every table rejects keys it does not know)::

    name = "heavy top"          # optional; default: the file name without .toml
    description = "..."         # optional, free text

    [body]                      # the body frame is the frame the dimensions are given in
    kind = "tee_handle"         # the report's T-handle; optional overrides (m, kg/m^3):
                                #   handle_length, handle_radius, shaft_length,
                                #   shaft_radius, density
    # kind = "box"        mass, lx, ly, lz               (edges along body x, y, z)
    # kind = "cylinder"   mass, radius, length, axis = "z" ("x" | "y" | "z")
    # kind = "sphere"     mass, radius
    # kind = "mesh"       file = "part.stl" (STL or OBJ, relative to the scene file),
    #                     density (kg/m^3), scale = 1.0 (file units -> m; 1e-3 for mm):
    #                     a closed triangle mesh, the body frame its coordinates
    # kind = "tensor"     inertia = [Ixx, Iyy, Izz] or 3x3, about the centre of mass
    #                     (kg m^2); mass optional (needed by gravity unless given there)
    # kind = "composite"  one [[body.parts]] table per solid:
    #   [[body.parts]]
    #   kind = "cylinder"           # "cylinder" | "box" | "sphere", with their dimensions
    #   mass = 0.5
    #   radius = 0.04
    #   length = 0.01
    #   offset = [0, 0, 0.06]       # the part's centre, in the body frame (m); default 0
    #   euler = [0, 0, 0]           # optional orientation, part -> body frame: at most
    #                               # one of matrix = [[...]], quaternion = [w, x, y, z],
    #                               # euler = [phi, theta, psi] (rad)

    [initial]
    omega = [1.0, 0.05, 0.0]    # body angular velocity (rad/s)
    attitude = "identity"       # or one of: matrix = [[...], [...], [...]] (body -> space),
                                # quaternion = [w, x, y, z], mrp = [s1, s2, s3] (modified
                                # Rodrigues parameters, Basilisk's sigma_BN), euler = [phi,
                                # theta, psi] (rad, R = Rz(phi) Ry(theta) Rx(psi)); default identity

    [[effects]]                 # zero or more; each kind at most once
    kind = "gravity"            # space z is up; give exactly one of
    pivot_to_com = [0, 0, 0.06] #   the vector pivot -> centre of mass (body frame, m)
    # pivot = [0, 0, 0]         #   or the pivot's position in the body frame (m)
    # mass = 0.52               # default: the body's mass (kg)
    # g = 9.81                  # m/s^2
    # kind = "body_torque"   torque = [x, y, z]   (N m, fixed in the body)
    # kind = "space_torque"  torque = [x, y, z]   (N m, fixed in space)
    # kind = "damping"       c = 0.1              (N m s; torque -c omega)
    # kind = "timed_torque"  times = [0, 1, 2]  torque = [[0, 0, 0], [0, 0, 0.1], [0, 0, 0]]
    #                        frame = "body"       (N m at each time (s), linear in between,
    #                                              held outside; "body" or "space")
    # Spacecraft (lierk._problems.spacecraft; circular orbit in the space x-y plane):
    # kind = "gravity_gradient"  radius = 7e6 (m) or mean_motion = 0.0011 (rad/s);
    #                            mu = 3.986e14, phase = 0 (rad)
    # kind = "magnetic"      radius or mean_motion, tilt = 0 (dipole to orbit normal, rad),
    #                        B0 = 3.12e-5 (T); dipole = [x, y, z] (A m^2) or bdot_gain = k
    # kind = "rotor"         momentum = [x, y, z] (kg m^2/s, constant, body frame); or
    #                        axes = [[1, 0, 0], ...], momentum = [h1, ...] (per wheel),
    #                        optional torque = [[u1, ...], ...] at times = [...] (N m, s):
    #                        the rate of the momentum relative to the body (a
    #                        speed-controlled wheel), not a motor torque
    # kind = "reaction_wheels"  axes = [[1, 0, 0], ...] (body frame), spin_inertia = [Js1, ...]
    #                        (kg m^2), speeds = [Omega1, ...] (rad/s relative to the body,
    #                        default 0); motor torques: torque = [u1, ...] (N m, constant)
    #                        or torque = [[u1, ...], ...] at times = [...] (s); the body's
    #                        inertia includes the wheels (lierk.ReactionWheels)

    [[events]]                  # zero or more: when they happen is reported (lierk.Event)
    kind = "flip"               # the intermediate-axis flip (lierk.conditions.flip)
    # kind = "tilt"           angle = 0.5 (rad): a body axis leaning that far from space z
    #                         axis = [0, 0, 1] (body; default gravity's pivot -> centre
    #                         of mass, else body z)
    # kind = "tilt_extremum"  axis = ... (as tilt): the turning points of its tilt (nutation);
    #                         extremum = "both" | "max" | "min"
    # kind = "pointing"       axis = [1, 0, 0] (body), target = [0, 0, 1] (space),
    #                         angle = 0.2 (rad): the axis at that angle from the target
    # kind = "energy"         threshold = 0.01: the energy's relative change passes it
    # kind = "momentum"       threshold = 0.01: the same for |L|
    # crossing = "both"       # tilt, pointing: "up" (the angle grows through it), "down", "both"
    # terminate = false       # true: end the run at the first event; n: at the n-th
    # name = "..."            # its label in reports and figures (default: the kind)

    [run]
    solver = "RKMK4"            # any lierk solver: ExplicitEuler, LieEuler, NaiveLieRK4,
                                # RKMK4, CF4, Strang, Yoshida4, BlanesMoan4, Yoshida6,
                                # BlanesMoan6, BlanesMoanRKN4, BlanesMoanRKN6 (fixed
                                # step), RKF45, DP54, DOP853 (adaptive)
    t1 = 100.0                  # end time (s); runs start at t = 0
    dt = 0.01                   # exactly one of: dt, the fixed step (s);
    # rtol = 1e-8               #   rtol (and optional atol), adaptive solvers only;
    # target_error = 1e-8       #   target_error, the attitude error ||R - R_exact||_F
                                #   wanted at every saved time: any solver, which then
                                #   chooses its own dt or rtol (lierk.solve(target_error=))
    save_every = 10             # dt: keep every k-th step (default 1)
    # n_save = 1001             # rtol, target_error: equally spaced output times
                                # (default 1001)
    # max_steps = 100000        # rtol: bound on steps (accepted + rejected);
                                # target_error: bound on the steps of each solve

With gravity the body turns about the pivot, so the problem's inertia is the
centre-of-mass inertia moved there (`lierk.inertia.parallel_axis`) and its
state is the momentum about the pivot; otherwise the body turns about its
centre of mass.  `Scene.fixed_point` is that point in the body frame, which is
where a drawing of `Scene.body_parts` is pinned.

Every mistake raises `ValueError` before anything runs, naming the key (as a
path such as ``effects[1].kind``), the value and what is allowed.  That
includes runs too large to attempt (more than `MAX_STEPS` fixed steps, more
than `MAX_SAVED` saved states) and a body whose initial momentum, energy or
inverse inertia overflows, or whose state does not fit the working precision
(`lierk._validation.state_range_error`: ``|L|^2``, ``2T``, ``2T I_k``, the
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

import jax.numpy as jnp
import numpy as np

from lierk import (
    SOLVERS,
    AbstractEffect,
    AbstractProblem,
    BodyTorque,
    Damping,
    FreeRigidBody,
    Gravity,
    RigidBodyWithEffects,
    SaveAt,
    Solution,
    SpaceTorque,
    TimedTorque,
    solver_class,
)
from lierk import inertia as _inertia
from lierk import num_steps as _num_steps
from lierk import solve as _solve

# Not yet public: the input checks shared with the library, and the Earth's
# constants of the spacecraft effects.
from .. import _validation as validation
from .._problems import spacecraft
from .._validation import check_attitude

__all__ = ["Scene", "load", "from_dict", "identifier"]

_DEFAULT_N_SAVE = 1001

MAX_STEPS = 2**31 - 1
"""The most steps a scene may ask for: fixed steps ``t1/dt``, and
``run.max_steps``.  Solvers count steps in 32-bit integers."""

MAX_SAVED = 10**7
"""The most states a scene may save (``run.n_save``, or ``t1/dt`` over
``run.save_every``): 10^7 states are about 1 GB in memory and on disk."""


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A loaded scene; see the module docstring for the file format.

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
        values = {"t1": self.t1, **{k: v for k, v in self.solve_kwargs.items() if k in ("dt", "rtol", "atol", "target_error")}}
        for k, v in values.items():
            if not tiny <= v <= big:
                raise ValueError(
                    f"{'t1' if k == 't1' else 'run.' + k} = {v:g} is outside single precision's range ({tiny:.2g} to {big:.2g})"
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
        eps = _number(target_error, "target_error", positive=True)
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
        t1 = _number(t1, "t1", positive=True)
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
        if n_pieces is None and not progress:
            kwargs = {"saveat": self.saveat(), **self.solve_kwargs, **self._event_kwargs(), **overrides}
            return _solve(self.problem, self.solver, self.t1, **kwargs)
        if n_pieces is not None and not (isinstance(n_pieces, (int, np.integer)) and not isinstance(n_pieces, bool) and n_pieces >= 1):
            raise ValueError(f"n_pieces must be a positive int, got {n_pieces!r}")
        unknown = set(overrides) - {"throw"}
        if unknown:
            raise ValueError(f"a scene solved in pieces takes only throw= as an override, got {', '.join(sorted(unknown))}")
        from .segments import N_PIECES, solve_in_pieces

        return solve_in_pieces(self, N_PIECES if n_pieces is None else int(n_pieces), progress,
                               overrides.get("throw", True))

    def _event_kwargs(self) -> dict:
        return {"event": tuple(e for _, e in self.events)} if self.events else {}

    def with_flip_event(self) -> "Scene":
        """This scene with the intermediate-axis flip among its events
        (`lierk.conditions.flip`, named ``"flip"``), when its body has three
        distinct principal moments and the scene has no flip event yet; the
        scene itself otherwise, and for a ``target_error`` run (which takes
        no events).  ``lierk simulate`` reports and marks flips this way
        (`lierk.app.simulation.simulate`); a solver that cannot locate events
        (ExplicitEuler) refuses the event when the scene is solved, and
        ``simulate`` then solves without it and says so."""
        if self.target_error is not None or any(name == "flip" for name, _ in self.events):
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
                f"{path}: not valid TOML: not UTF-8 text (byte {e.object[e.start:e.start + 1].hex()} at offset {e.start})"
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
    _table(d, "scene", {"name", "description", "body", "initial", "effects", "events", "run"}, required={"body", "initial", "run"})
    name = _string(d.get("name", name), "name")
    description = _string(d.get("description", ""), "description")
    body = _body(d["body"], directory)
    # The body as given, before gravity moves its inertia to the pivot (which
    # can hide an impossible one); solids always keep the triangle inequality.
    impossible = validation.impossible_inertia(body.inertia, "body.inertia") if body.parts is None else None
    omega0, R0 = _initial(d["initial"])
    effects_list = d.get("effects", [])
    if not isinstance(effects_list, list):
        raise ValueError(f"effects must be an array of tables ([[effects]]), got {effects_list!r}")
    effects, pivot_to_com = _effects(effects_list, body)
    solver, t1, solve_kwargs, every, n_save = _run(d["run"])

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
    _check_state(inertia, omega0, dtype, "body" if pivot_to_com is None else "body about the gravity pivot",
                 "body.inertia" if body.parts is None and pivot_to_com is None else "inertia")
    singular = validation.nearly_singular_inertia(inertia, dtype, "the body's inertia")
    inertia, omega0, R0 = (np.asarray(a, dtype=dtype) for a in (inertia, omega0, R0))
    if not effects:
        problem = FreeRigidBody(inertia, omega0, R0)
    else:
        problem = RigidBodyWithEffects(inertia, omega0, R0, effects)
    events_list = d.get("events", [])
    if not isinstance(events_list, list):
        raise ValueError(f"events must be an array of tables ([[events]]), got {events_list!r}")
    if events_list and "target_error" in solve_kwargs:
        raise ValueError("events: a run with target_error takes no events (its solves stop at different times); give dt or rtol")
    scene = Scene(
        events=_events(events_list, problem, pivot_to_com),
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
        description=description,
    )
    return scene, [text for text in (impossible, singular) if text is not None]


# --- validation helpers ------------------------------------------------------


def _table(d, path: str, allowed: set, required: set = frozenset()) -> dict:
    if not isinstance(d, dict):
        raise ValueError(f"{path} must be a table, got {d!r}")
    for k in d:
        if k not in allowed:
            raise ValueError(f"{path}: unknown key {k!r} (= {d[k]!r}); allowed keys: {', '.join(sorted(allowed))}")
    for k in sorted(required):
        if k not in d:
            raise ValueError(f"{path}: missing required key {k!r}")
    return d


def _key(path: str, k: str) -> str:
    return k if path == "scene" else f"{path}.{k}"


def _string(x, path: str) -> str:
    if not isinstance(x, str):
        raise ValueError(f"{path} must be a string, got {x!r}")
    return x


def _number(x, path: str, *, positive: bool = False, nonnegative: bool = False) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise ValueError(f"{path} must be a finite number, got {x!r}")
    if positive and not x > 0:
        raise ValueError(f"{path} must be > 0, got {x!r}")
    if nonnegative and not x >= 0:
        raise ValueError(f"{path} must be >= 0, got {x!r}")
    return float(x)


def _int(x, path: str, *, most: int = MAX_STEPS) -> int:
    if isinstance(x, bool) or not isinstance(x, int) or x < 1:
        raise ValueError(f"{path} must be a positive integer, got {x!r}")
    if x > most:
        raise ValueError(f"{path} must be at most {most}, got {x!r}")
    return x


def _check_state(inertia: np.ndarray, omega0: np.ndarray, dtype, what: str, key: str) -> None:
    """The body's inverse inertia, initial momentum and energy must be finite
    (a body of 1e-320 kg m^2, or 1e200 kg m^2 spinning at 1e200 rad/s, is
    not), and its state must fit ``dtype`` (`lierk._validation.state_range_error`:
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
        raise ValueError(f"{what}: the inertia is not finite (too large, or a mass or size too small): {_show(inertia)}")
    if not np.isfinite(inv).all():
        raise ValueError(f"{what}: the inertia {_show(inertia)} kg m^2 is singular or too small to invert")
    if not np.isfinite(m).all():
        raise ValueError(
            f"{what}: the initial momentum I omega overflows (inertia {_show(inertia)} kg m^2, "
            f"omega {_show(omega0)} rad/s)"
        )
    if not math.isfinite(energy):
        raise ValueError(
            f"{what}: the initial kinetic energy omega . I omega / 2 overflows (inertia {_show(inertia)} kg m^2, "
            f"omega {_show(omega0)} rad/s)"
        )
    reason = validation.state_range_error(inertia, omega0, dtype)
    if reason is not None:
        shown = np.diagonal(inertia) if not np.any(inertia - np.diag(np.diagonal(inertia))) else inertia
        raise ValueError(f"{what}: {key} = {_show(shown)} kg m^2 with initial.omega = {_show(omega0)} rad/s: {reason}")


def _show(x) -> str:
    """An array on one line."""
    return " ".join(np.array2string(np.asarray(x), precision=4, separator=", ").split())


def _vec(x, path: str, n: int = 3) -> np.ndarray:
    if not isinstance(x, list) or len(x) != n:
        raise ValueError(f"{path} must be a list of {n} numbers, got {x!r}")
    return np.array([_number(v, f"{path}[{i}]") for i, v in enumerate(x)])


def _mat3(x, path: str) -> np.ndarray:
    if not isinstance(x, list) or len(x) != 3:
        raise ValueError(f"{path} must be a 3x3 matrix (a list of 3 rows of 3 numbers), got {x!r}")
    return np.stack([_vec(row, f"{path}[{i}]") for i, row in enumerate(x)])


def _choice(x, path: str, choices) -> str:
    if x is None:
        raise ValueError(f"{path} is missing; choose one of: {', '.join(map(repr, choices))}")
    if x not in choices:
        raise ValueError(f"{path} = {x!r} is not allowed; choose one of: {', '.join(map(repr, choices))}")
    return x


def _orientation(t: dict, path: str, allow_identity: bool) -> np.ndarray | None:
    """One of ``attitude = "identity"``, ``matrix``, ``quaternion``, ``euler``, or
    None if none is given.  Returns a rotation matrix checked to be in SO(3)."""
    keys = [k for k in ("attitude", "matrix", "quaternion", "mrp", "euler") if k in t]
    if len(keys) > 1:
        raise ValueError(f"{path}: give at most one of {', '.join(keys)}")
    if not keys:
        return None
    (k,) = keys
    p = _key(path, k)
    if k == "attitude":
        _choice(t[k], p, ("identity",) if allow_identity else ())
        return np.eye(3)
    if k == "matrix":
        R = _mat3(t[k], p)
    elif k == "quaternion":
        q = _vec(t[k], p, 4)
        if not np.linalg.norm(q) > 1e-12:
            raise ValueError(f"{p} must be a nonzero quaternion [w, x, y, z], got {t[k]!r}")
        R = _quaternion_matrix(q / np.linalg.norm(q))
    elif k == "mrp":
        R = _mrp_matrix(_vec(t[k], p))
    else:
        R = _euler_matrix(*_vec(t[k], p))
    try:
        return np.asarray(check_attitude(R, jnp.result_type(float)), dtype=float)
    except ValueError as e:
        raise ValueError(f"{p}: {e}") from None


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


# --- body ----------------------------------------------------------------------


@dataclasses.dataclass
class _Body:
    mass: float | None
    com: np.ndarray
    inertia: np.ndarray  # about the centre of mass, body frame
    parts: list | None


_SHAPE_KEYS = {
    "box": ("mass", "lx", "ly", "lz"),
    "cylinder": ("mass", "radius", "length"),
    "sphere": ("mass", "radius"),
}
_TEE_KEYS = ("handle_length", "handle_radius", "shaft_length", "shaft_radius", "density")
_BODY_KINDS = ("tee_handle", "box", "cylinder", "sphere", "composite", "tensor", "mesh")


def _solid(t: dict, path: str, extra: set) -> tuple[float, np.ndarray, tuple]:
    """``(mass, inertia about its centre in its own frame, shape)`` of one solid."""
    kind = _choice(t.get("kind"), _key(path, "kind"), tuple(_SHAPE_KEYS))
    optional = {"axis"} if kind == "cylinder" else set()
    _table(t, path, {"kind", *_SHAPE_KEYS[kind], *optional, *extra}, required=set(_SHAPE_KEYS[kind]))
    v = {k: _number(t[k], _key(path, k), positive=True) for k in _SHAPE_KEYS[kind]}
    if kind == "box":
        return v["mass"], np.asarray(_inertia.box(**v)), ("box", v["lx"], v["ly"], v["lz"])
    if kind == "sphere":
        return v["mass"], np.asarray(_inertia.sphere(**v)), ("sphere", v["radius"])
    axis = _choice(t.get("axis", "z"), _key(path, "axis"), ("x", "y", "z"))
    return (
        v["mass"],
        np.asarray(_inertia.solid_cylinder(v["mass"], v["radius"], v["length"], axis)),
        ("cylinder", v["radius"], v["length"], axis),
    )


def _mesh_body(t: dict, directory) -> _Body:
    _table(t, "body", {"kind", "file", "density", "scale"}, required={"file", "density"})
    file = _string(t["file"], "body.file")
    path = file if os.path.isabs(file) else os.path.join(os.fspath(directory), file)
    try:
        props = _inertia.from_mesh(path, _number(t["density"], "body.density", positive=True),
                                   _number(t.get("scale", 1.0), "body.scale", positive=True))
    except ValueError as e:
        raise ValueError(f"body.file {file!r}: {e}") from None
    part = _inertia.Part(props.mass, props.inertia, props.center_of_mass, None,
                         ("mesh", props.mesh.triangles - props.center_of_mass))
    return _Body(props.mass, props.center_of_mass, props.inertia, [part])


def _body(t, directory=".") -> _Body:
    path = "body"
    if not isinstance(t, dict):
        raise ValueError(f"body must be a table, got {t!r}")
    kind = _choice(t.get("kind"), "body.kind", _BODY_KINDS)
    if kind == "mesh":
        return _mesh_body(t, directory)
    if kind == "tee_handle":
        _table(t, path, {"kind", *_TEE_KEYS})
        dims = {k: _number(t[k], f"body.{k}", positive=True) for k in _TEE_KEYS if k in t}
        parts = _inertia.tee_handle_parts(**dims)
    elif kind == "tensor":
        _table(t, path, {"kind", "inertia", "mass"}, required={"inertia"})
        x = t["inertia"]
        I = _mat3(x, "body.inertia") if isinstance(x, list) and x and isinstance(x[0], list) else np.diag(_vec(x, "body.inertia"))
        try:
            I = np.asarray(_inertia.tensor(I), dtype=float)
        except ValueError as e:
            raise ValueError(f"body.inertia: {e}") from None
        mass = _number(t["mass"], "body.mass", positive=True) if "mass" in t else None
        return _Body(mass, np.zeros(3), I, None)
    elif kind == "composite":
        _table(t, path, {"kind", "parts"}, required={"parts"})
        if not isinstance(t["parts"], list) or not t["parts"]:
            raise ValueError(f"body.parts must be a non-empty array of tables ([[body.parts]]), got {t['parts']!r}")
        parts = []
        for i, pt in enumerate(t["parts"]):
            p = f"body.parts[{i}]"
            if not isinstance(pt, dict):
                raise ValueError(f"{p} must be a table, got {pt!r}")
            mass, I, shape = _solid(pt, p, {"offset", "matrix", "quaternion", "euler"})
            offset = _vec(pt["offset"], f"{p}.offset") if "offset" in pt else np.zeros(3)
            Q = _orientation(pt, p, allow_identity=False)
            parts.append(_inertia.Part(mass, I, offset, Q, shape))
    else:
        mass, I, shape = _solid(t, path, set())
        parts = [_inertia.Part(mass, I, np.zeros(3), None, shape)]
    c = _inertia.composite(parts)
    return _Body(float(c.mass), np.asarray(c.center_of_mass, dtype=float), np.asarray(c.inertia, dtype=float), parts)


# --- initial state -------------------------------------------------------------


def _initial(t) -> tuple[np.ndarray, np.ndarray]:
    _table(t, "initial", {"omega", "attitude", "matrix", "quaternion", "mrp", "euler"}, required={"omega"})
    omega = _vec(t["omega"], "initial.omega")
    R0 = _orientation(t, "initial", allow_identity=True)
    return omega, np.eye(3) if R0 is None else R0


# --- effects -------------------------------------------------------------------

_EFFECT_KEYS = {
    "gravity": ({"pivot_to_com", "pivot", "mass", "g"}, set()),
    "body_torque": ({"torque"}, {"torque"}),
    "space_torque": ({"torque"}, {"torque"}),
    "timed_torque": ({"times", "torque", "frame"}, {"times", "torque"}),
    "damping": ({"c"}, {"c"}),
    "gravity_gradient": ({"radius", "mean_motion", "mu", "phase"}, set()),
    "magnetic": ({"radius", "mean_motion", "tilt", "B0", "phase", "dipole", "bdot_gain"}, set()),
    "rotor": ({"momentum", "axes", "torque", "times"}, {"momentum"}),
    "reaction_wheels": ({"axes", "spin_inertia", "speeds", "torque", "times"}, {"axes", "spin_inertia"}),
}


def _effects(items: list, body: _Body) -> tuple[tuple[AbstractEffect, ...], np.ndarray | None]:
    effects, seen, pivot_to_com = [], set(), None
    for i, t in enumerate(items):
        p = f"effects[{i}]"
        if not isinstance(t, dict):
            raise ValueError(f"{p} must be a table, got {t!r}")
        kind = _choice(t.get("kind"), f"{p}.kind", tuple(_EFFECT_KEYS))
        if kind in seen:
            raise ValueError(f"{p}.kind = {kind!r} appears twice; each effect kind may be given once")
        seen.add(kind)
        allowed, required = _EFFECT_KEYS[kind]
        _table(t, p, {"kind", *allowed}, required=required)
        if kind == "gravity":
            given = [k for k in ("pivot_to_com", "pivot") if k in t]
            if len(given) != 1:
                raise ValueError(f"{p}: gravity needs exactly one of 'pivot_to_com' or 'pivot', got {given or 'neither'}")
            if "pivot" in t:
                pivot_to_com = body.com - _vec(t["pivot"], f"{p}.pivot")
            else:
                pivot_to_com = _vec(t["pivot_to_com"], f"{p}.pivot_to_com")
            if "mass" in t:
                mass = _number(t["mass"], f"{p}.mass", positive=True)
                # One mass for both the torque and the parallel-axis shift of
                # the inertia to the pivot, or the top is not a rigid body.
                if body.mass is not None and abs(mass - body.mass) > 1e-9 * body.mass:
                    raise ValueError(
                        f"{p}.mass = {mass:g} kg differs from the body's mass {body.mass:g} kg; gravity acts on "
                        "the body's own mass (leave 'mass' out), or give the body that mass"
                    )
            elif body.mass is not None:
                mass = body.mass
            else:
                raise ValueError(f"{p}.mass is required: body kind 'tensor' was given without a mass")
            g = _number(t.get("g", 9.81), f"{p}.g", nonnegative=True)
            effects.append(Gravity(pivot_to_com, mass, g))
        elif kind == "body_torque":
            effects.append(BodyTorque(_vec(t["torque"], f"{p}.torque")))
        elif kind == "space_torque":
            effects.append(SpaceTorque(_vec(t["torque"], f"{p}.torque")))
        elif kind == "timed_torque":
            times = np.asarray(t["times"], dtype=object)
            if times.ndim != 1 or len(times) == 0:
                raise ValueError(f"{p}.times must be a non-empty list of times (s), got {_show(t['times'])}")
            times = np.array([_number(x, f"{p}.times[{j}]") for j, x in enumerate(t["times"])])
            torque = t["torque"]
            if not isinstance(torque, list) or len(torque) != len(times):
                raise ValueError(
                    f"{p}.torque must list one [x, y, z] per time ({len(times)}), got {_show(torque)}"
                )
            values = np.stack([_vec(v, f"{p}.torque[{j}]") for j, v in enumerate(torque)])
            frame = _choice(t.get("frame", "body"), f"{p}.frame", ("body", "space"))
            effects.append(TimedTorque(values, times=times, frame=frame))
        elif kind == "damping":
            effects.append(Damping(_number(t["c"], f"{p}.c", nonnegative=True)))
        else:
            effects.append(_SPACECRAFT[kind](t, p, body))
    return tuple(effects), pivot_to_com


def _orbit(t: dict, p: str) -> dict:
    """The circular orbit of a spacecraft effect: exactly one of ``radius``
    (m) or ``mean_motion`` (rad/s)."""
    given = [k for k in ("radius", "mean_motion") if k in t]
    if len(given) != 1:
        raise ValueError(f"{p}: give the orbit as exactly one of 'radius' (m) or 'mean_motion' (rad/s), got {given or 'neither'}")
    (k,) = given
    return {k: _number(t[k], f"{p}.{k}", positive=True)}


def _gravity_gradient(t: dict, p: str, body: _Body):
    orbit = _orbit(t, p)
    mu = _number(t.get("mu", spacecraft.MU_EARTH), f"{p}.mu", positive=True)
    return spacecraft.GravityGradient(body.inertia, mu=mu, phase=_number(t.get("phase", 0.0), f"{p}.phase"), **orbit)


def _magnetic(t: dict, p: str, body: _Body):
    orbit = _orbit(t, p)
    n = orbit.get("mean_motion") or math.sqrt(spacecraft.MU_EARTH / orbit["radius"] ** 3)
    field = spacecraft.dipole_field(
        n, radius=orbit.get("radius"), tilt=_number(t.get("tilt", 0.0), f"{p}.tilt"),
        B0=_number(t.get("B0", spacecraft.B0_EARTH), f"{p}.B0", positive=True), phase=_number(t.get("phase", 0.0), f"{p}.phase"),
    )
    given = [k for k in ("dipole", "bdot_gain") if k in t]
    if len(given) != 1:
        raise ValueError(f"{p}: magnetic needs exactly one of 'dipole' (A m^2, body frame) or 'bdot_gain', got {given or 'neither'}")
    if "dipole" in t:
        return spacecraft.MagneticTorque(field, dipole=_vec(t["dipole"], f"{p}.dipole"))
    return spacecraft.MagneticTorque(field, bdot_gain=_number(t["bdot_gain"], f"{p}.bdot_gain", nonnegative=True))


def _rotor(t: dict, p: str, body: _Body):
    if "axes" not in t:
        for k in ("torque", "times"):
            if k in t:
                raise ValueError(f"{p}.{k}: motor torques act along wheel axes; give 'axes' too")
        return spacecraft.Rotor(_vec(t["momentum"], f"{p}.momentum"))
    if not isinstance(t["axes"], list) or not t["axes"]:
        raise ValueError(f"{p}.axes must be a non-empty list of [x, y, z] wheel axes (body frame), got {_show(t['axes'])}")
    axes = np.stack([_vec(a, f"{p}.axes[{j}]") for j, a in enumerate(t["axes"])])
    k = len(axes)
    momentum = _vec(t["momentum"], f"{p}.momentum", k)
    if ("torque" in t) != ("times" in t):
        raise ValueError(f"{p}: motor torques need both 'torque' (one row of {k} per time, N m) and 'times' (s)")
    if "torque" not in t:
        return spacecraft.Rotor(momentum, axes=axes)
    times = np.array([_number(x, f"{p}.times[{j}]") for j, x in enumerate(t["times"])]) if isinstance(t["times"], list) else None
    if times is None or not isinstance(t["torque"], list) or len(t["torque"]) != len(times):
        raise ValueError(f"{p}.torque must list one row of {k} wheel torques per time, got {_show(t['torque'])}")
    torque = np.stack([_vec(v, f"{p}.torque[{j}]", k) for j, v in enumerate(t["torque"])])
    return spacecraft.Rotor(momentum, axes=axes, torque=torque, times=times)


def _reaction_wheels(t: dict, p: str, body: _Body):
    if not isinstance(t["axes"], list) or not t["axes"]:
        raise ValueError(f"{p}.axes must be a non-empty list of [x, y, z] wheel axes (body frame), got {_show(t['axes'])}")
    axes = np.stack([_vec(a, f"{p}.axes[{j}]") for j, a in enumerate(t["axes"])])
    for j, a in enumerate(axes):
        if not np.any(a):
            raise ValueError(f"{p}.axes[{j}] must be a non-zero vector, got {t['axes'][j]!r}")
    k = len(axes)
    spin = _vec(t["spin_inertia"], f"{p}.spin_inertia", k)
    for j, js in enumerate(spin):
        if not js > 0:
            raise ValueError(f"{p}.spin_inertia[{j}] must be > 0 (kg m^2), got {t['spin_inertia'][j]!r}")
    speeds = _vec(t["speeds"], f"{p}.speeds", k) if "speeds" in t else np.zeros(k)
    if "times" in t:
        times = t["times"]
        if not isinstance(times, list) or not times:
            raise ValueError(f"{p}.times must be a non-empty list of times (s), got {_show(times)}")
        times = np.array([_number(x, f"{p}.times[{j}]") for j, x in enumerate(times)])
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"{p}.times must be strictly increasing, got {_show(times)}")
        if "torque" not in t:
            raise ValueError(f"{p}: times need torque = [[u1, ...], ...], one row of {k} motor torques (N m) per time")
        torque = t["torque"]
        if not isinstance(torque, list) or len(torque) != len(times):
            raise ValueError(f"{p}.torque must list one row of {k} motor torques (N m) per time ({len(times)}), got {_show(torque)}")
        torque = np.stack([_vec(v, f"{p}.torque[{j}]", k) for j, v in enumerate(torque)])
    elif "torque" in t:
        if isinstance(t["torque"], list) and t["torque"] and isinstance(t["torque"][0], list):
            raise ValueError(f"{p}.torque: rows of motor torques need times = [...] (s), one per row")
        torque = _vec(t["torque"], f"{p}.torque", k)
    else:
        torque = None
    return spacecraft.ReactionWheels(axes, spin, speeds, torque=torque, times=times if "times" in t else None)


_SPACECRAFT = {
    "gravity_gradient": _gravity_gradient,
    "magnetic": _magnetic,
    "rotor": _rotor,
    "reaction_wheels": _reaction_wheels,
}

# --- events --------------------------------------------------------------------

_EVENT_KEYS = {
    "flip": (set(), set()),
    "tilt": ({"angle", "axis", "crossing"}, {"angle"}),
    "tilt_extremum": ({"axis", "extremum"}, set()),
    "pointing": ({"axis", "target", "angle", "crossing"}, {"axis", "target", "angle"}),
    "energy": ({"threshold"}, {"threshold"}),
    "momentum": ({"threshold"}, {"threshold"}),
}
_CROSSING = {"both": 0, "up": 1, "down": -1}
_EXTREMUM = {"both": 0, "max": 1, "min": -1}


def _events(items: list, problem, pivot_to_com: np.ndarray | None) -> tuple:
    from lierk import conditions

    events, names = [], set()
    for i, t in enumerate(items):
        p = f"events[{i}]"
        if not isinstance(t, dict):
            raise ValueError(f"{p} must be a table, got {t!r}")
        kind = _choice(t.get("kind"), f"{p}.kind", tuple(_EVENT_KEYS))
        allowed, required = _EVENT_KEYS[kind]
        _table(t, p, {"kind", "terminate", "name", *allowed}, required=required)
        terminate = t.get("terminate", False)
        if not (isinstance(terminate, bool) or (isinstance(terminate, int) and terminate >= 1)):
            raise ValueError(f"{p}.terminate must be true, false or a positive integer (end at the n-th), got {terminate!r}")
        name = _string(t.get("name", kind), f"{p}.name")
        if name in names:
            raise ValueError(f"{p}.name = {name!r} is taken by an earlier event; give each a name of its own")
        names.add(name)
        default_axis = pivot_to_com if pivot_to_com is not None else np.array([0.0, 0.0, 1.0])
        axis = _vec(t["axis"], f"{p}.axis") if "axis" in t else default_axis
        for key in ("axis", "target"):
            if key in t and not np.any(_vec(t[key], f"{p}.{key}")):
                raise ValueError(f"{p}.{key} must be a non-zero vector, got {t[key]!r}")
        if "angle" in t:
            angle = _number(t["angle"], f"{p}.angle", nonnegative=True)
            if angle > math.pi:
                raise ValueError(f"{p}.angle must be in [0, pi] rad, got {angle:g}")
        crossing = _CROSSING[_choice(t.get("crossing", "both"), f"{p}.crossing", tuple(_CROSSING))]
        if kind == "flip":
            event = conditions.flip(problem, terminate=terminate)
        elif kind == "tilt":
            event = conditions.tilt(angle, axis, terminate=terminate, direction=crossing)
        elif kind == "tilt_extremum":
            extremum = _EXTREMUM[_choice(t.get("extremum", "both"), f"{p}.extremum", tuple(_EXTREMUM))]
            event = conditions.tilt_extremum(problem, axis, terminate=terminate, direction=extremum)
        elif kind == "pointing":
            event = conditions.pointing(axis, _vec(t["target"], f"{p}.target"), angle, terminate=terminate,
                                        direction=crossing)
        else:
            threshold = _number(t["threshold"], f"{p}.threshold", positive=True)
            drift = conditions.energy_drift if kind == "energy" else conditions.momentum_drift
            event = drift(problem, threshold, terminate=terminate)
        events.append((name, event))
    return tuple(events)


# --- run -----------------------------------------------------------------------


_RUN_MODES = (
    "run: give exactly one of 'dt' (fixed step), 'rtol' (adaptive, with optional 'atol') "
    "or 'target_error' (the solver chooses its step or tolerances)"
)


def _run(t):
    _table(
        t,
        "run",
        {"solver", "t1", "dt", "rtol", "atol", "target_error", "save_every", "n_save", "max_steps"},
        required={"solver", "t1"},
    )
    s = t["solver"]
    try:
        solver = solver_class(s)()
    except ValueError:
        raise ValueError(f"run.solver = {s!r} is not allowed; choose one of: {', '.join(SOLVERS)}") from None
    t1 = _number(t["t1"], "run.t1", positive=True)
    modes = [k for k in ("dt", "rtol", "target_error") if k in t]
    if len(modes) != 1:
        given = f"; got {', '.join(modes)}" if modes else ""
        raise ValueError(_RUN_MODES + given)
    if "dt" in t:
        for k in ("atol", "n_save", "max_steps"):
            if k in t:
                raise ValueError(f"run.{k} applies to adaptive runs (rtol=), not to a fixed step dt = {t['dt']!r}")
        dt = _number(t["dt"], "run.dt", positive=True)
        every = _int(t.get("save_every", 1), "run.save_every")
        _check_run_size(t1, {"dt": dt}, every, "run.t1")
        return solver, t1, {"dt": dt}, every, None
    if "target_error" in t:
        if "atol" in t:
            raise ValueError("run.atol applies to rtol runs; with run.target_error the solver chooses its tolerances itself")
        if "save_every" in t:
            raise ValueError(
                "run.save_every applies to fixed-step runs (dt=); runs with run.target_error save at run.n_save times"
            )
        kw = {"target_error": _number(t["target_error"], "run.target_error", positive=True)}
    else:
        if not solver.adaptive:
            # `adaptive` is a property on RKMK-family classes: ask instances.
            adaptive = [n for n, c in SOLVERS.items() if c().adaptive]
            raise ValueError(
                f"run.solver = {s!r} has no error estimate, so it needs run.dt (or run.target_error); "
                f"adaptive solvers (for rtol): {', '.join(adaptive)}"
            )
        if "save_every" in t:
            raise ValueError("run.save_every applies to fixed-step runs (dt=); adaptive runs use run.n_save")
        rtol = _number(t["rtol"], "run.rtol", positive=True)
        kw = {"rtol": rtol, "atol": _number(t.get("atol", rtol), "run.atol", positive=True)}
    if "max_steps" in t:
        kw["max_steps"] = _int(t["max_steps"], "run.max_steps")
    n_save = _int(t.get("n_save", _DEFAULT_N_SAVE), "run.n_save", most=MAX_SAVED)
    if n_save < 2:
        raise ValueError(f"run.n_save must be >= 2 (it includes t = 0 and t1), got {n_save}")
    return solver, t1, kw, None, n_save


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
