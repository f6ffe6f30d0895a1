"""Ready-made events (`lierk.Event`) for what rigid-body users ask for: the
intermediate-axis flip, the tilt of a top, the angle between a body axis and
a space direction (pointing), and a conserved quantity drifting past a
threshold.

Each function returns an `Event` whose condition is an `equinox.Module`:
its numbers (an angle, an axis, a threshold, the body's inertia) are array
fields, so changing them does not recompile and the event time is
differentiable with respect to them.  Angles are in radians, axes are
``(3,)`` vectors (normalised here), body axes in the body frame and
directions in space (z up).

Example:
    >>> top = lierk.app.scene.load("examples/heavy_top.toml").problem
    >>> sol = lierk.solve(top, lierk.DOP853(), 5.0, rtol=1e-10,
    ...                   event=lierk.conditions.tilt(0.5, axis=[0, 0, 1], terminate=True))
    >>> sol.ts[-1]          # when the top's axis first leans 0.5 rad from the vertical
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import _validation as validation
from ._event import Event
from ._problems import AbstractRigidBody
from ._solvers.base import field_at

__all__ = ["flip", "tilt", "pointing", "tilt_extremum", "energy_drift", "momentum_drift"]


def _unit(v: ArrayLike, name: str, dtype) -> Array:
    v = validation.asarray(v, dtype, name)
    validation.check_shape(v, (3,), name)
    v = validation.check(
        v,
        lambda x: ((x * x).sum() > 0) & (abs(x) < float("inf")).all(),
        f"{name} must be a finite non-zero vector, got {{value}}",
    )
    xp = np if isinstance(v, np.ndarray) else jnp
    return jnp.asarray(v / xp.sqrt((v * v).sum()))


def _rigid_body(problem, what: str) -> AbstractRigidBody:
    if not isinstance(problem, AbstractRigidBody):
        raise ValueError(
            f"{what} needs a rigid body (lierk.FreeRigidBody, RigidBodyWithEffects, ...), got {type(problem).__name__}"
        )
    return problem


def _principal(inertia: Array) -> tuple[Array, Array]:
    """Principal moments in ascending order ``(3,)`` and axes (columns) ``(3, 3)``."""
    if validation.is_traced(inertia):
        moments, axes = jnp.linalg.eigh(inertia)
        return moments, axes
    # Concrete: NumPy, so that building an event compiles nothing.
    moments, axes = np.linalg.eigh(np.asarray(inertia))
    return moments.astype(inertia.dtype), axes.astype(inertia.dtype)


class IntermediateMomentum(eqx.Module):
    """``m . e2`` (kg m^2/s): the body momentum along the intermediate
    principal axis ``e2``.  It changes sign in the middle of each flip."""

    problem: AbstractRigidBody
    axis: Array  # (3,) e2, body frame

    def __call__(self, t, R, y):
        return self.axis @ self.problem.body_momentum(R, y)


class OrbitFlips(eqx.Module):
    """Whether the torque-free orbit through the current momentum flips: the
    definition of `lierk.exact.flip_interval` (its ``|m2|`` peaks above
    ``|m|/sqrt(2)``, so ``e2`` is at times the body axis closest to ``L``),
    applied to the orbit the body would follow if its torques stopped now.
    False for a body with two equal moments."""

    problem: AbstractRigidBody
    moments: Array  # (3,) ascending
    axes: Array  # (3, 3) principal axes as columns

    def __call__(self, t, R, y):
        m = self.axes.T @ self.problem.body_momentum(R, y)
        I1, I2, I3 = self.moments[0], self.moments[1], self.moments[2]
        distinct = (I1 < I2) & (I2 < I3)
        M2 = m @ m
        E2 = jnp.sum(m * m / self.moments)  # twice the kinetic energy
        # m2^2 where m2 peaks on the orbit: at m1 = 0 for an orbit about the
        # largest axis, at m3 = 0 about the smallest; the other formula then
        # exceeds |m|^2, so the smaller of the two is the peak.
        safe = lambda x: jnp.where(distinct, x, 1.0)  # noqa: E731
        about_largest = (E2 - M2 / I3) / safe(1 / I2 - 1 / I3)
        about_smallest = (M2 / I1 - E2) / safe(1 / I1 - 1 / I2)
        return distinct & (jnp.minimum(about_largest, about_smallest) > 0.5 * M2)


def flip(problem, *, terminate: bool | int = False, max_count: int | None = None) -> Event:
    """The Dzhanibekov flip of ``problem``'s intermediate axis, under any effects.

    The event is the middle of each flip: the body momentum crosses the plane
    normal to the intermediate principal axis (``m . e2 = 0``), on an orbit
    that flips (`OrbitFlips`).  For a torque-free body these are exactly the
    flips of `lierk.exact.flip_interval`'s definition, one every flip
    interval; a body near its smallest or largest axis, whose ``m2`` also
    changes sign, gives none.  With torques, the orbit is the torque-free
    one through the state at the crossing.

    Args:
        problem: a rigid body (its inertia and where it keeps ``m``).
        terminate: as for `Event`.
        max_count: as for `Event`.
    """
    problem = _rigid_body(problem, "flip")
    moments, axes = _principal(problem.inertia)
    return Event(
        IntermediateMomentum(problem, validation.as_jax(axes[:, 1])),
        where=OrbitFlips(problem, validation.as_jax(moments), validation.as_jax(axes)),
        terminate=terminate,
        max_count=max_count,
    )


class AxisAngle(eqx.Module):
    """``cos(angle) - (R axis) . direction``: zero where the body ``axis`` is
    at ``angle`` from the space ``direction``, rising as it leans further."""

    axis: Array  # (3,) unit, body frame
    direction: Array  # (3,) unit, space frame
    cos_angle: Array

    def __call__(self, t, R, y):
        return self.cos_angle.astype(R.dtype) - (R @ self.axis.astype(R.dtype)) @ self.direction.astype(R.dtype)


def pointing(
    body_axis: ArrayLike,
    space_direction: ArrayLike,
    angle: ArrayLike,
    *,
    terminate: bool | int = False,
    direction: int = 0,
    max_count: int | None = None,
) -> Event:
    """The angle between a body axis and a space direction crossing ``angle``
    (pointing a satellite: the event where an instrument's boresight comes
    within ``angle`` of a target).

    Args:
        body_axis: ``(3,)`` body-frame axis.
        space_direction: ``(3,)`` space-frame direction.
        angle: the angle (rad), in ``[0, pi]``.
        terminate: as for `Event`.
        max_count: as for `Event`.
        direction: ``1`` when the angle grows through ``angle``, ``-1`` when
            it shrinks through it (the axis comes within ``angle``), 0 both.
    """
    dtype = jnp.result_type(float)
    angle = validation.check_scalar(angle, "angle", dtype)
    angle = validation.check(angle, lambda a: (a >= 0) & (a <= math.pi), "angle must be in [0, pi] rad, got {value}")
    xp = np if isinstance(angle, np.ndarray) else jnp
    cond = AxisAngle(
        _unit(body_axis, "body_axis", dtype),
        _unit(space_direction, "space_direction", dtype),
        jnp.asarray(xp.cos(angle)),
    )
    return Event(cond, terminate=terminate, direction=direction, max_count=max_count)


def tilt(
    angle: ArrayLike,
    axis: ArrayLike = (0.0, 0.0, 1.0),
    *,
    terminate: bool | int = False,
    direction: int = 0,
    max_count: int | None = None,
) -> Event:
    """The tilt of a body axis from the vertical (space z) crossing ``angle``
    (rad): a top's symmetry axis (``axis``, body frame; default body z)
    leaning through ``angle``.  ``direction=1``: leaning further;
    ``-1``: rising back.  `pointing` with space direction z."""
    return pointing(axis, (0.0, 0.0, 1.0), angle, terminate=terminate, direction=direction, max_count=max_count)


class TiltRate(eqx.Module):
    """``d/dt cos(tilt)`` of a body axis (1/s): ``(R (omega x axis)) . e_z``."""

    problem: Any
    axis: Array  # (3,) unit, body frame

    def __call__(self, t, R, y):
        omega = field_at(self.problem, t, R, y)[0]
        return (R @ jnp.cross(omega, self.axis.astype(R.dtype)))[2]


_EXTREMA = {"both": 0, "max": 1, "min": -1}


def tilt_extremum(
    problem,
    axis: ArrayLike = (0.0, 0.0, 1.0),
    *,
    extremum: str = "both",
    terminate: bool | int = False,
    max_count: int | None = None,
    direction: int | None = None,
) -> Event:
    """The turning points of a body axis's tilt from the vertical (a top's
    nutation): where ``d tilt/dt = 0``.  A top released at rest in its
    nutation starts at a turning point, which does not count (`lierk._event`).

    Args:
        problem: the rigid body (its angular velocity is read at each state).
        axis: ``(3,)`` body-frame axis (default body z).
        extremum: ``"max"`` keeps the largest tilts (the axis lowest),
            ``"min"`` the smallest, ``"both"`` (default) both; a scene's
            ``extremum`` key.
        terminate: as for `Event`.
        max_count: as for `Event`.
        direction: deprecated: ``1`` for ``extremum="max"``, ``-1`` for
            ``"min"``, ``0`` for ``"both"``.

    Raises:
        ValueError: an unknown ``extremum``, or both ``extremum`` and
            ``direction`` given.
    """
    if direction is not None:
        if extremum != "both":
            raise ValueError("tilt_extremum takes extremum= ('max', 'min' or 'both'), not both it and direction=")
        names = {v: k for k, v in _EXTREMA.items()}
        if direction not in names:
            raise ValueError(
                f"tilt_extremum(direction=...) must be 1, -1 or 0, got {direction!r}; use extremum='max' or 'min'"
            )
        warnings.warn(
            f"tilt_extremum(direction={direction}) is deprecated: use extremum={names[direction]!r}",
            DeprecationWarning,
            stacklevel=2,
        )
        extremum = names[direction]
    if extremum not in _EXTREMA:
        raise ValueError(f"extremum must be 'max', 'min' or 'both', got {extremum!r}")
    dtype = problem.R0.dtype
    # At a largest tilt cos(tilt) stops falling: its rate rises through zero.
    return Event(
        TiltRate(problem, _unit(axis, "axis", dtype)),
        terminate=terminate,
        direction=_EXTREMA[extremum],
        max_count=max_count,
    )


class InvariantDrift(eqx.Module):
    """``|q(R, y) - q0| - threshold |q0|`` for one of the problem's
    `invariants` ``q``, ``q0`` its value at the problem's initial state:
    rising through zero when its relative change passes ``threshold``."""

    problem: Any
    key: str = eqx.field(static=True)
    threshold: Array

    def __call__(self, t, R, y):
        q0 = self.problem.invariants(self.problem.R0, self.problem.y0)[self.key]
        scale = jnp.where(q0 != 0, jnp.abs(q0), 1.0)
        return jnp.abs(self.problem.invariants(R, y)[self.key] - q0) - self.threshold.astype(R.dtype) * scale


def _drift(problem, key: str, threshold, terminate, max_count) -> Event:
    dtype = problem.R0.dtype
    threshold = validation.check_scalar(threshold, "threshold", dtype, bound="positive")
    keys = jax.eval_shape(problem.invariants, problem.R0, problem.y0)
    if key not in keys:
        raise ValueError(f"{type(problem).__name__} has no invariant {key!r}; it has {', '.join(keys)}")
    cond = InvariantDrift(problem, key, jnp.asarray(threshold))
    return Event(cond, terminate=terminate, direction=1, max_count=max_count)


def energy_drift(
    problem, threshold: ArrayLike, *, terminate: bool | int = False, max_count: int | None = None
) -> Event:
    """The energy (kinetic plus the effects' potentials) changing by more
    than ``threshold`` relative to its initial value (|E0|; 1 J if it is 0):
    a check on a solve's accuracy, or the time a damped body has lost that
    fraction of its energy."""
    return _drift(problem, "energy", threshold, terminate, max_count)


def momentum_drift(
    problem, threshold: ArrayLike, *, terminate: bool | int = False, max_count: int | None = None
) -> Event:
    """``|L|`` changing by more than ``threshold`` relative to its initial value."""
    return _drift(problem, "|L|", threshold, terminate, max_count)
