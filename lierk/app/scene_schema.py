"""The scene file's schema, declared once as msgspec Structs.

`SceneFile` is a whole file: a `body` (one of the ``*Body`` tables, chosen by
its ``kind``), its `Initial` state, zero or more ``[[effects]]`` and
``[[events]]`` (``*Effect`` and ``*Event`` tables, by their ``kind`` too) and
a `Run`.  Every table refuses keys it does not know.  Each key's type,
constraint and default is its annotation; its meaning and unit are in its
table's ``Attributes``.  `parse` checks a parsed TOML document against the
Structs, and `json_schema`, which ``lierk schema`` prints, gives all of it to
an editor to complete and check scene files (Taplo / Even Better TOML:
``lierk schema > scene.schema.json``, then ``#:schema scene.schema.json`` as
a scene file's first line).

What a schema cannot say is checked by `lierk.app.scene` on the parsed
Structs: rules across keys (exactly one of ``dt``, ``rtol`` or
``target_error``; gravity's ``pivot`` or ``pivot_to_com``; one row per time;
one entry per wheel), non-zero axes, rotations, and bodies whose state
overflows.  Numbers must be finite (TOML allows ``inf`` and ``nan``);
integers are taken where numbers are, booleans and strings are not.

Units are SI; a vector is ``[x, y, z]``, a matrix a list of rows.  The body
frame is the frame the body's dimensions are given in.  In a parsed
`SceneFile`, a key the file leaves out that has no default is ``msgspec.UNSET``.
"""

from __future__ import annotations

import difflib
import functools
import inspect as _inspect
import math
import re
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
from msgspec import UNSET, Meta, Struct, UnsetType

from lierk import SOLVERS, GravityGradient, dipole_field
from lierk import inertia as _inertia

__all__ = [
    "SceneFile",
    "Initial",
    "Run",
    "TeeHandleBody",
    "BoxBody",
    "CylinderBody",
    "SphereBody",
    "CompositeBody",
    "TensorBody",
    "MeshBody",
    "BoxPart",
    "CylinderPart",
    "SpherePart",
    "GravityEffect",
    "BodyTorqueEffect",
    "SpaceTorqueEffect",
    "TimedTorqueEffect",
    "DampingEffect",
    "GravityGradientEffect",
    "MagneticEffect",
    "RotorEffect",
    "ReactionWheelsEffect",
    "EventKeys",
    "FlipEvent",
    "TiltEvent",
    "TiltExtremumEvent",
    "PointingEvent",
    "EnergyEvent",
    "MomentumEvent",
    "Body",
    "Part",
    "Effect",
    "Event",
    "parse",
    "json_schema",
    "MAX_STEPS",
    "MAX_SAVED",
    "MAX_NAME_BYTES",
    # The types of values.
    "Positive",
    "NonNegative",
    "Count",
    "SaveCount",
    "Angle",
    "Vec3",
    "Vec4",
    "Matrix3",
    "Vectors",
    "Axes",
    "Numbers",
    "PositiveNumbers",
    "Rows",
    "NumbersOrRows",
    "Times",
    "Inertia",
    "Terminate",
    "Crossing",
    "SolverName",
]

MAX_STEPS = 2**31 - 1
"""The most steps a scene may ask for: fixed steps ``t1/dt``, and
``run.max_steps``.  Solvers count steps in 32-bit integers."""

MAX_SAVED = 10**7
"""The most states a scene may save (``run.n_save``, or ``t1/dt`` over
``run.save_every``): 10^7 states are about 1 GB in memory and on disk."""

MAX_NAME_BYTES = 240
"""The longest file stem a scene's ``name`` may give
(`lierk.app.scene.identifier` of it, in UTF-8 bytes): the command line names
its outputs after it (``<stem>_components.png``, 15 bytes more), and file
systems take names of up to 255 bytes."""


def _default(function, name: str):
    return _inspect.signature(function).parameters[name].default


# --- the types of values -----------------------------------------------------------
# ``extra`` words a message where the type alone says too little: "expects",
# what the value must be; "choices", the names allowed.  Missing keys with no
# default are ``UNSET`` (``msgspec.UNSET``).

Positive = Annotated[float, Meta(gt=0)]
"""A number > 0."""
NonNegative = Annotated[float, Meta(ge=0)]
"""A number >= 0."""
Count = Annotated[int, Meta(ge=1, le=MAX_STEPS)]
"""An integer from 1 to `MAX_STEPS`."""
SaveCount = Annotated[int, Meta(ge=2, le=MAX_SAVED)]
"""An integer from 2 to `MAX_SAVED`."""
Angle = Annotated[float, Meta(ge=0, le=math.pi, extra={"expects": "in [0, pi] rad"})]
"""A number from 0 to pi."""
Vec3 = Annotated[list[float], Meta(min_length=3, max_length=3)]
"""A list of 3 numbers."""
Vec4 = Annotated[list[float], Meta(min_length=4, max_length=4)]
"""A list of 4 numbers."""
Matrix3 = Annotated[list[Vec3], Meta(min_length=3, max_length=3)]
"""A 3x3 matrix: a list of 3 rows of 3 numbers."""
Vectors = Annotated[list[Vec3], Meta(min_length=1)]
"""A list of one or more `Vec3`."""
Axes = Annotated[Vectors, Meta(extra={"expects": "a non-empty list of [x, y, z] wheel axes (body frame)"})]
"""One or more wheel axes, `Vec3` each."""
Numbers = Annotated[list[float], Meta(min_length=1)]
"""A list of one or more numbers."""
PositiveNumbers = Annotated[list[Positive], Meta(min_length=1)]
"""A list of one or more numbers > 0."""
Rows = Annotated[list[Numbers], Meta(min_length=1)]
"""A list of one or more rows of numbers (one row per time)."""
NumbersOrRows = Annotated[list[float | Numbers], Meta(min_length=1)]
"""`Numbers`, or `Rows` (one row per time)."""
Times = Annotated[list[float], Meta(min_length=1, extra={"expects": "a non-empty list of times (s)"})]
"""A list of one or more times."""
Inertia = Annotated[
    list[float | Vec3],
    Meta(min_length=3, max_length=3, extra={"expects": "a list of 3 numbers (the principal moments) or a 3x3 matrix"}),
]
"""A list of 3 numbers, or a `Matrix3`."""
Terminate = Annotated[
    bool | Annotated[int, Meta(ge=1)], Meta(extra={"expects": "true, false or a positive integer (end at the n-th)"})
]
"""true, false, or an integer >= 1."""
Crossing = Literal["both", "up", "down"]
"""Which way an angle passes its value."""


def _any_case(name: str) -> str:
    return "".join(f"[{c.upper()}{c.lower()}]" if c.isalpha() else re.escape(c) for c in name)


SolverName = Annotated[
    str,
    Meta(
        pattern=f"^(?:{'|'.join(map(_any_case, SOLVERS))})$",
        examples=list(SOLVERS),
        extra={"choices": ", ".join(SOLVERS)},
    ),
]
"""A name in `lierk.SOLVERS`, in any letter case."""


class _Table(Struct, forbid_unknown_fields=True, kw_only=True, omit_defaults=True):
    pass


# --- body ------------------------------------------------------------------------


class _Body(_Table, tag_field="kind"):
    pass


class TeeHandleBody(_Body, tag="tee_handle"):
    """``kind = "tee_handle"``: the report's T-handle, two solid cylinders
    (`lierk.inertia.tee_handle_parts`): the handle along body y through the
    origin, the shaft along x from the handle's surface.

    Attributes:
        handle_length: m; default 0.08.
        handle_radius: m; default 0.01.
        shaft_length: m; default 0.04.
        shaft_radius: m; default 0.01.
        density: kg/m^3; default 6700.
    """

    handle_length: Positive = _default(_inertia.tee_handle_parts, "handle_length")
    handle_radius: Positive = _default(_inertia.tee_handle_parts, "handle_radius")
    shaft_length: Positive = _default(_inertia.tee_handle_parts, "shaft_length")
    shaft_radius: Positive = _default(_inertia.tee_handle_parts, "shaft_radius")
    density: Positive = _default(_inertia.tee_handle_parts, "density")


class BoxBody(_Body, tag="box"):
    """``kind = "box"``: a solid box centred on the origin.

    Attributes:
        mass: kg.
        lx: its edge along body x (m).
        ly: its edge along body y (m).
        lz: its edge along body z (m).
    """

    mass: Positive
    lx: Positive
    ly: Positive
    lz: Positive


class CylinderBody(_Body, tag="cylinder"):
    """``kind = "cylinder"``: a solid cylinder centred on the origin.

    Attributes:
        mass: kg.
        radius: m.
        length: m.
        axis: the body axis it lies along; default "z".
    """

    mass: Positive
    radius: Positive
    length: Positive
    axis: Literal["x", "y", "z"] = "z"


class SphereBody(_Body, tag="sphere"):
    """``kind = "sphere"``: a solid sphere centred on the origin.

    Attributes:
        mass: kg.
        radius: m.
    """

    mass: Positive
    radius: Positive


class BoxPart(BoxBody, tag="box"):
    """A box among a `CompositeBody`'s parts: `BoxBody`'s keys, and where
    the part sits in the body frame, turned by at most one of ``matrix``,
    ``quaternion`` or ``euler`` (part -> body frame).

    Attributes:
        offset: the part's centre in the body frame (m); default [0, 0, 0].
        matrix: a 3x3 rotation (rows).
        quaternion: [w, x, y, z], normalised.
        euler: [phi, theta, psi] (rad), R = Rz(phi) Ry(theta) Rx(psi).
    """

    offset: Vec3 = (0.0, 0.0, 0.0)
    matrix: Matrix3 | UnsetType = UNSET
    quaternion: Vec4 | UnsetType = UNSET
    euler: Vec3 | UnsetType = UNSET


class CylinderPart(CylinderBody, tag="cylinder"):
    """A cylinder among a `CompositeBody`'s parts: `CylinderBody`'s keys,
    placed as a `BoxPart` is.

    Attributes:
        offset: the part's centre in the body frame (m); default [0, 0, 0].
        matrix: a 3x3 rotation (rows).
        quaternion: [w, x, y, z], normalised.
        euler: [phi, theta, psi] (rad), R = Rz(phi) Ry(theta) Rx(psi).
    """

    offset: Vec3 = (0.0, 0.0, 0.0)
    matrix: Matrix3 | UnsetType = UNSET
    quaternion: Vec4 | UnsetType = UNSET
    euler: Vec3 | UnsetType = UNSET


class SpherePart(SphereBody, tag="sphere"):
    """A sphere among a `CompositeBody`'s parts: `SphereBody`'s keys, placed
    as a `BoxPart` is.

    Attributes:
        offset: the part's centre in the body frame (m); default [0, 0, 0].
        matrix: a 3x3 rotation (rows).
        quaternion: [w, x, y, z], normalised.
        euler: [phi, theta, psi] (rad), R = Rz(phi) Ry(theta) Rx(psi).
    """

    offset: Vec3 = (0.0, 0.0, 0.0)
    matrix: Matrix3 | UnsetType = UNSET
    quaternion: Vec4 | UnsetType = UNSET
    euler: Vec3 | UnsetType = UNSET


Part = BoxPart | CylinderPart | SpherePart
"""A `CompositeBody`'s part, by its ``kind``."""


class CompositeBody(_Body, tag="composite"):
    """``kind = "composite"``: solids joined rigidly (`lierk.inertia.composite`).

    Attributes:
        parts: one ``[[body.parts]]`` table per solid, at least one.
    """

    parts: Annotated[list[Part], Meta(min_length=1)]


class TensorBody(_Body, tag="tensor"):
    """``kind = "tensor"``: an inertia given as numbers.

    Attributes:
        inertia: [Ixx, Iyy, Izz] (principal moments) or a symmetric 3x3
            matrix, about the centre of mass at the body origin (kg m^2).
        mass: kg; needed by gravity unless given there.
    """

    inertia: Inertia
    mass: Positive | UnsetType = UNSET


class MeshBody(_Body, tag="mesh"):
    """``kind = "mesh"``: a uniform solid bounded by a closed triangle mesh
    (`lierk.inertia.from_mesh`); the body frame is the file's coordinates.

    Attributes:
        file: STL or OBJ (any format trimesh reads, if it is installed),
            relative to the scene file.
        density: kg/m^3.
        scale: file units -> m (1e-3 for mm); default 1.
    """

    file: str
    density: Positive
    scale: Positive = 1.0


Body = TeeHandleBody | BoxBody | CylinderBody | SphereBody | CompositeBody | TensorBody | MeshBody
"""The ``[body]`` table, by its ``kind``."""

# --- initial state -----------------------------------------------------------------


class Initial(_Table):
    """``[initial]``: the body angular velocity and at most one of the
    attitude's forms (body -> space; default the identity).

    Attributes:
        omega: body angular velocity (rad/s).
        attitude: "identity", the default.
        matrix: a 3x3 rotation (rows).
        quaternion: [w, x, y, z], normalised.
        mrp: modified Rodrigues parameters [s1, s2, s3] (Basilisk's sigma_BN).
        euler: [phi, theta, psi] (rad), R = Rz(phi) Ry(theta) Rx(psi).
    """

    omega: Vec3
    attitude: Literal["identity"] | UnsetType = UNSET
    matrix: Matrix3 | UnsetType = UNSET
    quaternion: Vec4 | UnsetType = UNSET
    mrp: Vec3 | UnsetType = UNSET
    euler: Vec3 | UnsetType = UNSET


# --- effects ---------------------------------------------------------------------


class _Effect(_Table, tag_field="kind"):
    pass


class GravityEffect(_Effect, tag="gravity"):
    """``kind = "gravity"``: uniform gravity along space -z, the body
    turning about a fixed pivot (its inertia moved there); exactly one of
    ``pivot_to_com`` or ``pivot``.

    Attributes:
        pivot_to_com: the vector pivot -> centre of mass, body frame (m).
        pivot: the pivot's position in the body frame (m).
        mass: kg; default the body's, which it must equal.
        g: m/s^2; default 9.81.
    """

    pivot_to_com: Vec3 | UnsetType = UNSET
    pivot: Vec3 | UnsetType = UNSET
    mass: Positive | UnsetType = UNSET
    g: NonNegative = 9.81


class BodyTorqueEffect(_Effect, tag="body_torque"):
    """``kind = "body_torque"``: a constant torque fixed in the body.

    Attributes:
        torque: N m, body frame.
    """

    torque: Vec3


class SpaceTorqueEffect(_Effect, tag="space_torque"):
    """``kind = "space_torque"``: a constant torque fixed in space.

    Attributes:
        torque: N m, space frame.
    """

    torque: Vec3


class TimedTorqueEffect(_Effect, tag="timed_torque"):
    """``kind = "timed_torque"``: a torque given at times, linear in between
    and held outside.

    Attributes:
        times: the times (s).
        torque: one [x, y, z] per time (N m).
        frame: "body" or "space", the frame it is fixed in; default "body".
    """

    times: Times
    torque: Vectors
    frame: Literal["body", "space"] = "body"


class DampingEffect(_Effect, tag="damping"):
    """``kind = "damping"``: linear viscous damping, the torque ``-c omega``.

    Attributes:
        c: N m s.
    """

    c: NonNegative


class GravityGradientEffect(_Effect, tag="gravity_gradient"):
    """``kind = "gravity_gradient"``: the gravity-gradient torque along a
    circular orbit in the space x-y plane (`lierk.GravityGradient`); exactly
    one of ``radius`` or ``mean_motion``.

    Attributes:
        radius: the orbit's radius (m).
        mean_motion: the orbit's mean motion (rad/s).
        mu: gravitational parameter (m^3/s^2); default 3.986004418e14, the Earth's.
        phase: the orbit's phase at t = 0 (rad); default 0.
    """

    radius: Positive | UnsetType = UNSET
    mean_motion: Positive | UnsetType = UNSET
    mu: Positive = _default(GravityGradient.__init__, "mu")
    phase: float = 0.0


class MagneticEffect(_Effect, tag="magnetic"):
    """``kind = "magnetic"``: a magnetorquer in the Earth's dipole field
    along a circular orbit (`lierk.MagneticTorque`, `lierk.dipole_field`):
    exactly one of ``radius`` or ``mean_motion``, and exactly one of
    ``dipole`` or ``bdot_gain``.

    Attributes:
        radius: the orbit's radius (m).
        mean_motion: the orbit's mean motion (rad/s).
        tilt: the dipole's axis to the orbit normal (rad); default 0.
        B0: the dipole's field at the equator on the surface (T); default 3.12e-05.
        phase: the orbit's phase at t = 0 (rad); default 0.
        dipole: a constant dipole moment, body frame (A m^2).
        bdot_gain: a B-dot controller's gain (A m^2 s/T).
    """

    radius: Positive | UnsetType = UNSET
    mean_motion: Positive | UnsetType = UNSET
    tilt: float = 0.0
    B0: Positive = _default(dipole_field, "B0")
    phase: float = 0.0
    dipole: Vec3 | UnsetType = UNSET
    bdot_gain: NonNegative | UnsetType = UNSET


class RotorEffect(_Effect, tag="rotor"):
    """``kind = "rotor"``: rotors whose momentum relative to the body is
    prescribed (`lierk.Rotor`: speed-controlled wheels): ``momentum`` alone,
    or with ``axes``, and then optionally ``torque`` at ``times``.

    Attributes:
        momentum: [x, y, z], body frame, or with axes one per wheel (kg m^2/s).
        axes: one [x, y, z] per wheel, body frame.
        torque: one row per time, one entry per wheel (N m): the rate of the
            relative momentum, not a motor torque.
        times: the times (s).
    """

    momentum: Numbers
    axes: Axes | UnsetType = UNSET
    torque: Rows | UnsetType = UNSET
    times: Times | UnsetType = UNSET


class ReactionWheelsEffect(_Effect, tag="reaction_wheels"):
    """``kind = "reaction_wheels"``: wheels driven by motor torques, their
    speeds integrated with the body (`lierk.ReactionWheels`); the body's
    inertia includes the wheels.

    Attributes:
        axes: one [x, y, z] per wheel, body frame.
        spin_inertia: one per wheel (kg m^2).
        speeds: one per wheel, relative to the body (rad/s); default 0.
        torque: motor torques (N m): one per wheel, constant, or with times
            one row per time.
        times: the times (s).
    """

    axes: Axes
    spin_inertia: PositiveNumbers
    speeds: Numbers | UnsetType = UNSET
    torque: NumbersOrRows | UnsetType = UNSET
    times: Times | UnsetType = UNSET


Effect = (
    GravityEffect
    | BodyTorqueEffect
    | SpaceTorqueEffect
    | TimedTorqueEffect
    | DampingEffect
    | GravityGradientEffect
    | MagneticEffect
    | RotorEffect
    | ReactionWheelsEffect
)
"""An ``[[effects]]`` table, by its ``kind``."""

# --- events ----------------------------------------------------------------------


class EventKeys(_Table, tag_field="kind", kw_only=True):
    """The keys every ``[[events]]`` table takes besides its kind's.

    Attributes:
        terminate: true: end the run at the first event; n: at the n-th; default false.
        name: its label in reports and figures; default the kind.
    """

    terminate: Terminate = False
    name: str | UnsetType = UNSET


class FlipEvent(EventKeys, tag="flip"):
    """``kind = "flip"``: the intermediate-axis flip (`lierk.conditions.flip`)."""


class TiltEvent(EventKeys, tag="tilt"):
    """``kind = "tilt"``: a body axis leaning ``angle`` from space z (`lierk.conditions.tilt`).

    Attributes:
        angle: rad, in [0, pi].
        axis: body frame; default gravity's pivot -> centre of mass, else z.
        crossing: "up" (the tilt grows through angle), "down" or "both"; default "both".
    """

    angle: Angle
    axis: Vec3 | UnsetType = UNSET
    crossing: Crossing = "both"


class TiltExtremumEvent(EventKeys, tag="tilt_extremum"):
    """``kind = "tilt_extremum"``: the turning points of an axis's tilt, its
    nutation (`lierk.conditions.tilt_extremum`).

    Attributes:
        axis: body frame; default gravity's pivot -> centre of mass, else z.
        extremum: "max", "min" or "both"; default "both".
    """

    axis: Vec3 | UnsetType = UNSET
    extremum: Literal["both", "max", "min"] = "both"


class PointingEvent(EventKeys, tag="pointing"):
    """``kind = "pointing"``: a body axis at ``angle`` from a direction in
    space (`lierk.conditions.pointing`).

    Attributes:
        axis: body frame.
        target: space frame.
        angle: rad, in [0, pi].
        crossing: "up" (the angle grows through it), "down" or "both"; default "both".
    """

    axis: Vec3
    target: Vec3
    angle: Angle
    crossing: Crossing = "both"


class EnergyEvent(EventKeys, tag="energy"):
    """``kind = "energy"``: the energy (kinetic plus the effects'
    potentials) changes by more than ``threshold`` relative to its initial
    value (`lierk.conditions.energy_drift`).

    Attributes:
        threshold: the relative change.
    """

    threshold: Positive


class MomentumEvent(EventKeys, tag="momentum"):
    """``kind = "momentum"``: ``|L|`` changes by more than ``threshold``
    relative to its initial value (`lierk.conditions.momentum_drift`).

    Attributes:
        threshold: the relative change.
    """

    threshold: Positive


Event = FlipEvent | TiltEvent | TiltExtremumEvent | PointingEvent | EnergyEvent | MomentumEvent
"""An ``[[events]]`` table, by its ``kind``."""

# --- run -------------------------------------------------------------------------


class Run(_Table):
    """``[run]``: the solver, the end time and exactly one of ``dt``,
    ``rtol`` or ``target_error``.  Runs start at t = 0.

    Attributes:
        solver: a lierk solver's name, in any letter case: fixed step
            (ExplicitEuler, LieEuler, NaiveLieRK4, RKMK4, CF4, the
            splittings) or adaptive (RKF45, DP54, DOP853).
        t1: end time (s).
        dt: the fixed step (s).
        rtol: the relative tolerance of an adaptive solver.
        atol: with rtol, the absolute tolerance; default rtol.
        target_error: the attitude error ||R - R_exact||_F wanted at every
            saved time; any solver, which chooses its own step or
            tolerances (lierk.solve(target_error=)).
        save_every: with dt, keep every k-th step; default 1.
        n_save: with rtol or target_error, the equally spaced output times,
            t = 0 and t1 included; default 1001.
        max_steps: with rtol, a bound on the steps (accepted and rejected);
            with target_error, on each solve's.
    """

    solver: SolverName
    t1: Positive
    dt: Positive | UnsetType = UNSET
    rtol: Positive | UnsetType = UNSET
    atol: Positive | UnsetType = UNSET
    target_error: Positive | UnsetType = UNSET
    save_every: Count | UnsetType = UNSET
    n_save: SaveCount | UnsetType = UNSET
    max_steps: Count | UnsetType = UNSET


# --- the file ----------------------------------------------------------------------


class SceneFile(_Table, kw_only=True):
    """A scene file: a rigid body, its initial state, opt-in effects and
    events, and a run.

    Attributes:
        name: default the file's name without .toml; the command line's
            outputs are named after it, so it may take at most 240 bytes of
            UTF-8 once each run of characters other than letters, digits
            and _ is one _.
        description: free text.
        body: the rigid body, one of the kinds.
        initial: the initial state.
        effects: zero or more ``[[effects]]``, each kind at most once.
        events: zero or more ``[[events]]``: when they happen is reported
            (lierk.Event).
        run: the solver and the run's settings.
    """

    name: str | UnsetType = UNSET
    description: str = ""
    body: Body
    initial: Initial
    effects: list[Effect] = []
    events: list[Event] = []
    run: Run


_TABLES = {
    cls.__name__: cls
    for cls in (SceneFile, Initial, Run, *Body.__args__, *Part.__args__, *Effect.__args__, *Event.__args__)
}


def _keys(cls) -> dict[str, str]:
    """The ``Attributes`` of ``cls``'s docstring and its bases': key -> text on one line."""
    keys = {}
    for c in reversed(cls.__mro__):
        if issubclass(c, _Table):
            section = _inspect.cleandoc(c.__dict__.get("__doc__") or "").partition("\nAttributes:\n")[2]
            keys.update(
                (m[1], " ".join(m[2].split())) for m in re.finditer(r"^    (\w+): (.*(?:\n {8}.*)*)", section, re.M)
            )
    return keys


def json_schema() -> dict:
    """The JSON Schema (2020-12) of scene files, as ``lierk schema`` prints
    it: each table's and key's description from its docstring."""
    schema = msgspec.json.decode(msgspec.json.encode(msgspec.json.schema(SceneFile)))  # lists, not tuples
    for name, table in schema["$defs"].items():
        table["description"] = " ".join(table["description"].partition("Attributes:")[0].split())
        keys = _keys(_TABLES[name])
        for key, p in table["properties"].items():
            if key in keys:
                p["description"] = keys[key]
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}


# --- parsing, and messages naming the key -------------------------------------------


def parse(d: dict) -> SceneFile:
    """A parsed TOML document (a dict) as a `SceneFile`.

    Raises:
        ValueError: one line naming the key's path (``effects[1].pivot_to_com[2]``),
            the value and what is allowed.
    """
    d = _plain(d)
    try:
        scene = msgspec.convert(d, SceneFile)
    except msgspec.ValidationError as e:
        raise ValueError(_message(str(e), d)) from None
    _check_finite(d, "")
    return scene


def _plain(x):
    """``x`` with NumPy scalars and arrays, and tuples, as Python numbers and
    lists: a scene built in Python (`lierk.app.scene.from_dict`) may hold
    them, and msgspec takes only the built-in types."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.ndarray, np.generic)):
        return _plain(x.tolist())
    return x


def _check_finite(x, path: str) -> None:
    if isinstance(x, float) and not math.isfinite(x):
        raise ValueError(f"{path} must be a finite number, got {x!r}")
    items = x.items() if isinstance(x, dict) else enumerate(x) if isinstance(x, list) else ()
    for k, v in items:
        _check_finite(v, f"{path}[{k}]" if isinstance(k, int) else f"{path}.{k}" if path else k)


_MISSING = object()
_inspect_types = functools.cache(lambda: msgspec.inspect.type_info(SceneFile))


def _members(t) -> tuple[list, dict]:
    """The types a value of ``t`` may take (its union's members, ``UNSET``
    left out) and their metadata's ``extra``, the outermost first."""
    extra = {}
    while isinstance(t, msgspec.inspect.Metadata):
        extra = {**(t.extra or {}), **extra}
        t = t.type
    if not isinstance(t, msgspec.inspect.UnionType):
        return [t], extra
    types = []
    for u in t.types:
        sub, more = _members(u)
        types, extra = types + sub, {**more, **extra}
    return types, extra


def _pick(types: list, value):
    """The one of ``types`` that ``value`` is meant for: a tagged Struct by its
    tag, a list or a number by the value; None if that cannot be told."""
    if all(isinstance(t, msgspec.inspect.StructType) for t in types) and len(types) > 1:
        tag = value.get(types[0].tag_field, _MISSING) if isinstance(value, dict) else _MISSING
        return next((t for t in types if t.tag == tag), None)
    if len(types) > 1:
        return next((t for t in types if isinstance(t, msgspec.inspect.ListType) == isinstance(value, list)), None)
    return types[0]


def _lookup(x, tokens):
    for tok in tokens:
        try:
            x = x[tok]
        except (KeyError, IndexError, TypeError):
            return _MISSING
    return x


def _resolve(tokens, d) -> tuple[list, dict]:
    """`_members` of the type at ``tokens``, following the tags in ``d``."""
    types, extra = [_inspect_types()], {}
    for i, tok in enumerate(tokens):
        t = _pick(types, _lookup(d, tokens[:i]))
        if isinstance(t, msgspec.inspect.ListType):
            t = t.item_type
        elif isinstance(t, msgspec.inspect.StructType):
            t = next((f.type for f in t.fields if f.encode_name == tok), None)
        else:
            return [], {}
        types, extra = _members(t) if t is not None else ([], {})
    return types, extra


def _message(text: str, d: dict) -> str:
    """msgspec's ``"Expected `float` > 0.0 - at `$.run.dt`"`` as ``"run.dt must be > 0, got -1.0"``."""
    what, _, where = text.partition(" - at `$")
    tokens = [int(i) if i else k for k, i in re.findall(r"\.(\w+)|\[(\d+)\]", where)]
    path = "".join(f"[{t}]" if isinstance(t, int) else f".{t}" for t in tokens).lstrip(".") or "scene"
    value = _lookup(d, tokens)
    types, extra = _resolve(tokens, d)
    key = re.fullmatch(r"Object (contains unknown|missing required) field `(.*)`", what)
    if key:
        table = _pick(types, value)
        if key[1] == "contains unknown":
            allowed = sorted({f.encode_name for f in table.fields} | {table.tag_field} - {None})
            return (
                f"{path}: unknown key {key[2]!r} (= {value[key[2]]!r}){_did_you_mean(key[2], allowed)}; "
                f"allowed keys: {', '.join(allowed)}"
            )
        if table is None:
            return f"{path}.{key[2]} is missing; choose one of: {', '.join(repr(t.tag) for t in types)}"
        return f"{path}: missing required key {key[2]!r}"
    tables, _ = _resolve(tokens[:-1], d)
    if len(tables) > 1 and all(isinstance(t, msgspec.inspect.StructType) for t in tables) and tokens[-1] == "kind":
        kinds = [t.tag for t in tables]
        return (
            f"{path} = {value!r} is not allowed{_did_you_mean(value, kinds)}; "
            f"choose one of: {', '.join(map(repr, kinds))}"
        )
    return path + _must(types, extra, value, what, path)


def _did_you_mean(given, names: list) -> str:
    """``"; did you mean 'omega'?"`` for the name closest to a misspelt
    ``given`` (`difflib`), or nothing when none is close."""
    if not isinstance(given, str):
        return ""
    close = difflib.get_close_matches(given, [str(n) for n in names], n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def _must(types: list, extra: dict, value: Any, what: str, path: str) -> str:
    """What ``value``, of one of ``types``, must be: the message after its key."""
    got = f", got {value!r}"
    if isinstance(value, float) and not math.isfinite(value):
        return f" must be a finite number{got}"
    if "choices" in extra:
        return f" = {value!r} is not allowed; choose one of: {extra['choices']}"
    if "expects" in extra:
        return f" must be {extra['expects']}{got}"
    t = _pick(types, value)
    integer = isinstance(value, int) and not isinstance(value, bool)
    if isinstance(t, msgspec.inspect.LiteralType):
        return (
            f" = {value!r} is not allowed{_did_you_mean(value, list(t.values))}; "
            f"choose one of: {', '.join(map(repr, t.values))}"
        )
    if isinstance(t, msgspec.inspect.StrType):
        return f" must be a string{got}"
    if isinstance(t, msgspec.inspect.FloatType) and (integer or isinstance(value, float)):
        for bound, op, ok in (("gt", ">", lambda b: value > b), ("ge", ">=", lambda b: value >= b)):
            if getattr(t, bound) is not None and not ok(getattr(t, bound)):
                return f" must be {op} {getattr(t, bound):g}{got}"
    if isinstance(t, msgspec.inspect.FloatType):
        return f" must be a finite number{got}"
    if isinstance(t, msgspec.inspect.IntType):
        if integer and t.le is not None and value > t.le:
            return f" must be at most {t.le}{got}"
        return f" must be >= {t.ge}{got}" if integer and value >= 1 else f" must be a positive integer{got}"
    if isinstance(t, msgspec.inspect.ListType):
        items, n = _members(t.item_type)[0], t.min_length
        if all(isinstance(u, msgspec.inspect.StructType) for u in items):
            return f" must be {'a non-empty' if n else 'an'} array of tables ([[{path}]]){got}"
        row = items[0]
        if isinstance(row, msgspec.inspect.ListType) and n == t.max_length == row.min_length == row.max_length:
            return f" must be a {n}x{n} matrix (a list of {n} rows of {n} numbers){got}"
        if isinstance(row, msgspec.inspect.ListType):
            rows = "[x, y, z] vectors" if row.min_length == row.max_length == 3 else "rows of numbers"
            return f" must be a non-empty list of {rows}{got}"
        return (
            f" must be a list of {n} numbers{got}"
            if n == t.max_length
            else f" must be a non-empty list of numbers{got}"
        )
    if types and all(isinstance(u, msgspec.inspect.StructType) for u in types):
        return f" must be a table{got}"
    return f": {what}"
