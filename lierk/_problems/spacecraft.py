"""Spacecraft effects: gravity-gradient torque, magnetic torque (a magnetorquer
or a B-dot controller in a dipole field), reaction wheels driven by motor
torques (`ReactionWheels`, whose speeds are integrated) and rotors whose
momentum relative to the body is prescribed (`Rotor`: a gyrostat).  Each is
an opt-in `AbstractEffect` of `lierk.RigidBodyWithEffects`, compiled only
where a problem holds it.

Frames and orbit.  ``R`` maps body to space as everywhere in lierk; "space"
is an inertial frame centred on the planet.  A circular orbit of radius ``a``
(m) and mean motion ``n = sqrt(mu/a^3)`` (rad/s) lies in the space ``x-y``
plane, with the spacecraft at

    r(t) = a (cos(n t + phase), sin(n t + phase), 0),

so the orbit normal is space ``z``.  Units are SI: torques N m, magnetic
fields T, dipole moments A m^2, wheel momenta kg m^2/s.

The equations are those of Basilisk's ``GravityGradientEffector``,
``MtbEffector`` and ``reactionWheelStateEffector`` (balanced wheels:
`ReactionWheels`), and of Hughes, *Spacecraft Attitude Dynamics* (gyrostats:
`Rotor`; gravity gradient) and Markley and Crassidis, *Fundamentals of
Spacecraft Attitude Determination and Control* (B-dot).

Wheels: `ReactionWheels` or `Rotor`.  A motor torque ``u`` on a wheel changes
the wheel's *absolute* spin momentum, ``Js (Omega' + g . omega') = u``, so the
body's reaction depends on how the body itself turns; `ReactionWheels`
integrates the wheel speeds with the body, as flight software and Basilisk
model driven wheels (and a wheel left alone keeps its absolute momentum).
`Rotor` instead prescribes each wheel's momentum *relative to the body* as a
function of time, whatever the body does: an ideal speed-controlled wheel
(its ``torque=`` is the derivative of that prescribed momentum, not a motor
torque).
"""

from __future__ import annotations

import math
from typing import Callable, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import _validation as validation
from .. import so3
from .effects import AbstractEffect, affine_flow

__all__ = [
    "MU_EARTH",
    "R_EARTH",
    "B0_EARTH",
    "circular_orbit",
    "GravityGradient",
    "dipole_field",
    "MagneticTorque",
    "Rotor",
    "ReactionWheels",
]

MU_EARTH = 3.986004418e14  # m^3/s^2
R_EARTH = 6.371e6  # m, mean radius
B0_EARTH = 3.12e-5  # T, the dipole's field at the equator on the surface


def _positive(x, name: str):
    if x is None:
        return None
    return validation.check_scalar(x, name, bound="positive")


def _mean_motion(radius, mean_motion, mu) -> Array:
    """``n`` (rad/s) from exactly one of the orbit ``radius`` (m, with ``mu``,
    m^3/s^2) or the ``mean_motion`` itself."""
    if (radius is None) == (mean_motion is None):
        raise ValueError("give the orbit as exactly one of radius= (m) or mean_motion= (rad/s)")
    if mean_motion is not None:
        return _positive(mean_motion, "mean_motion")
    radius, mu = _positive(radius, "radius"), _positive(mu, "mu")
    return jnp.sqrt(mu / radius**3)


def circular_orbit(t: Array, mean_motion: Array, phase: Array = 0.0) -> Array:
    """The unit position ``r(t)/|r|`` ``(3,)`` on a circular orbit in the space
    ``x-y`` plane: ``(cos(n t + phase), sin(n t + phase), 0)``."""
    a = mean_motion * t + phase
    return jnp.stack([jnp.cos(a), jnp.sin(a), jnp.zeros_like(a)])


class GravityGradient(AbstractEffect):
    """Gravity-gradient torque of a point-mass planet,

        tau = 3 mu / |r|^5 (r_b x I r_b),    r_b = R^T r  (body frame),

    with ``I`` the inertia about the centre of mass.  On a circular orbit
    this is ``3 n^2 (u_b x I u_b)`` with ``u`` the unit position; a
    spacecraft in it librates in pitch (about the orbit normal) with
    period ``2 pi / (n sqrt(3 (I_x - I_z)/I_y))`` for small amplitudes when
    its ``x`` axis points along the velocity and ``z`` to the planet.

    Give the orbit as ``radius`` (m, with ``mu``) or ``mean_motion`` (rad/s):
    circular, in the space ``x-y`` plane (`circular_orbit`); or as a function
    ``position(t) -> (3,)`` (m, space frame) that JAX can trace, e.g. an
    elliptic orbit.  The torque does not read the momentum, so every solver
    takes it, the splittings with an exact kick.  Conserves nothing in
    inertial space (its potential turns with the orbit).

    Args:
        inertia: ``(3, 3)`` or ``(3,)`` (kg m^2) about the centre of mass,
            body frame (for a body turning about a pivot, not the pivot's).
        radius: circular orbit radius (m), ``> 0``.
        mean_motion: circular orbit rate (rad/s), ``> 0``, instead of ``radius``.
        mu: the planet's gravitational parameter (m^3/s^2), Earth's by default.
        phase: the orbit angle at ``t = 0`` (rad).
        position: ``t -> r(t)`` (m, space frame), instead of a circular orbit.
    """

    inertia: Array
    mean_motion: Array | None
    mu: Array
    phase: Array
    position: Callable | None = eqx.field(static=True)
    # Whether the inertia was given as a concrete diagonal matrix: its
    # moments' spread (`energy_scale`, a tolerance's scale) is then the
    # diagonal's, not the characteristic cubic's (25 operations to trace,
    # twice a solve).  Like a body's own flag it describes the inertia the
    # constructor saw: build a new effect for another inertia rather than
    # swap the array in (`eqx.tree_at`).
    diagonal: bool = eqx.field(static=True)
    reads_momentum: ClassVar[bool] = False

    def __init__(self, inertia: ArrayLike, radius=None, mean_motion=None, mu=MU_EARTH, phase=0.0, position=None):
        self.inertia = validation.check_inertia(inertia)
        self.diagonal = validation.concrete_diagonal(inertia) is not None
        self.mu = _positive(mu, "mu")
        self.phase = validation.check_scalar(phase, "phase")
        if position is not None:
            if radius is not None or mean_motion is not None:
                raise ValueError(
                    "give the orbit as position= or as a circular orbit (radius= or mean_motion=), not both"
                )
            out = jax.eval_shape(position, jax.ShapeDtypeStruct((), jnp.result_type(float)))
            if getattr(out, "shape", None) != (3,):
                raise ValueError(f"position must return shape (3,) for a scalar time, got {getattr(out, 'shape', out)}")
            self.position, self.mean_motion = position, None
        else:
            self.position, self.mean_motion = None, _mean_motion(radius, mean_motion, mu)

    def space_vectors(self):
        eye = np.eye(3, dtype=self.inertia.dtype)
        # A circular orbit needs only the images of space x and y.
        return eye if self.position is not None else eye[:2]

    def torque_from(self, t, v, m, omega):
        I = self.inertia.astype(m.dtype)
        if self.position is None:
            c = circular_orbit(t, self.mean_motion, self.phase).astype(m.dtype)
            u = c[0] * v[0] + c[1] * v[1]  # R^T u
            return (3.0 * self.mean_motion**2) * so3.cross(u, so3.matvec(I, u))
        r = so3.matvec(v.T, jnp.asarray(self.position(t), m.dtype))  # R^T r
        d2 = so3._sq(r)
        return (3.0 * self.mu / (d2 * d2 * jnp.sqrt(d2))) * so3.cross(r, so3.matvec(I, r))

    def energy_scale(self):
        n2 = self.mean_motion**2 if self.position is None else jnp.zeros(())
        if self.diagonal:
            moments = jax.lax.stop_gradient(so3._diagonal(self.inertia))
            return 1.5 * n2 * (jnp.max(moments) - jnp.min(moments))
        return 1.5 * n2 * _moment_spread(self.inertia)


def _moment_spread(inertia: Array) -> Array:
    """``I_max - I_min`` (kg m^2) of a symmetric ``(3, 3)`` inertia, from the
    trigonometric solution of its characteristic cubic, not differentiated
    (a tolerance's scale).  ``jnp.linalg.eigvalsh`` is a LAPACK call whose
    lowering is a noticeable part of every program with gravity gradient.  Within
    1e-8 of the largest moment of eigvalsh's spread (2000 rotated inertias,
    double, triple and 1e12-apart moments included; about sqrt(eps) near a
    double moment): ample for a scale."""
    I = jax.lax.stop_gradient(0.5 * (inertia + inertia.T))
    diagonal = so3._diagonal(I)
    q = jnp.mean(diagonal)
    d = diagonal - q
    p = jnp.sqrt((jnp.sum(d * d) + 2.0 * (I[0, 1] ** 2 + I[0, 2] ** 2 + I[1, 2] ** 2)) / 6.0)
    B = (I - q * jnp.eye(3, dtype=I.dtype)) / jnp.where(p > 0, p, 1.0)
    det = jnp.dot(B[0], so3.cross(B[1], B[2]))
    phi = jnp.arccos(jnp.clip(0.5 * det, -1.0, 1.0)) / 3.0
    # lambda_max - lambda_min = 2 p (cos(phi) - cos(phi + 2 pi/3)).
    return jnp.where(p > 0, 2.0 * math.sqrt(3.0) * p * jnp.sin(phi + math.pi / 3.0), 0.0)


def dipole_field(
    mean_motion=None, radius=None, tilt=0.0, B0=B0_EARTH, planet_radius=R_EARTH, phase=0.0, mu=MU_EARTH
) -> Callable:
    """The field ``B(t)`` (T, space frame) of a centred magnetic dipole along
    the circular orbit of `circular_orbit` (radius ``a``):

        B = B0 (R_p/a)^3 (3 (d . u) u - d),    d = -(sin(tilt), 0, cos(tilt)),

    ``d`` the dipole's direction, ``tilt`` (rad) its angle to the orbit
    normal (space ``z``): 0 is an equatorial orbit (a constant field along
    ``+z``), pi/2 a polar one (the field turns twice per orbit).  Earth's
    dipole, 3.12e-5 T at the equator, by default.  The orbit is given as
    `GravityGradient` takes it: its ``mean_motion`` or its ``radius`` (the
    other follows from ``mu``), or both.

    Args:
        mean_motion: orbit rate (rad/s); default ``sqrt(mu / radius^3)``.
        radius: orbit radius (m); default ``(mu / n^2)^(1/3)``.
        tilt: the dipole's angle to the orbit normal (rad).
        B0: the field at the planet's equator on its surface (T).
        planet_radius: m.
        phase: the orbit angle at ``t = 0`` (rad).
        mu: the planet's gravitational parameter (m^3/s^2), Earth's by default.

    Returns:
        A function ``t -> (3,)`` that JAX traces.  It is a module whose
        numbers (orbit rate, phase, strength, the dipole's direction) are
        array fields, traced by a solve: a `MagneticTorque` with another
        field from `dipole_field` reuses the compiled solve, and a
        sensitivity can select them (``wrt=lambda p: p.effects[0].field``).
        The arguments themselves must be concrete numbers (checked here).
    """
    if mean_motion is None and radius is None:
        raise ValueError("give the orbit as mean_motion= (rad/s), radius= (m), or both")
    for name, value in (
        ("mean_motion", mean_motion),
        ("radius", radius),
        ("mu", mu),
        ("B0", B0),
        ("planet_radius", planet_radius),
    ):
        _positive(value, name)
    if not np.isfinite(tilt):
        raise ValueError(f"tilt must be finite (rad), got {tilt!r}")
    n = math.sqrt(float(mu) / float(radius) ** 3) if mean_motion is None else float(mean_motion)
    a = (float(mu) / n**2) ** (1.0 / 3.0) if radius is None else float(radius)
    strength = float(B0) * (float(planet_radius) / a) ** 3
    d = -np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    return _DipoleField(
        *(
            validation.asarray(x, name=name)
            for x, name in ((n, "mean_motion"), (phase, "phase"), (strength, "B0"), (d, "tilt"))
        )
    )


class _DipoleField(eqx.Module):
    """`dipole_field`'s ``B(t)``: its numbers are arrays, so a field with
    other numbers (another orbit, tilt or strength) runs the program that
    solves with this one (a function of one's own is part of the program:
    a new one compiles again)."""

    mean_motion: Array  # rad/s
    phase: Array  # rad
    strength: Array  # T, B0 (R_p/a)^3
    direction: Array  # (3,) the dipole's, space frame

    def __call__(self, t):
        t = jnp.asarray(t)
        dtype = t.dtype if jnp.issubdtype(t.dtype, jnp.floating) else jnp.result_type(float)
        n, phase, strength, dd = (
            jnp.asarray(x, dtype) for x in (self.mean_motion, self.phase, self.strength, self.direction)
        )
        u = circular_orbit(t.astype(dtype), n, phase)
        # d . u by components: jnp.dot is a reduction, a kernel of its own at
        # every stage, where the products fuse with what reads the field.
        return strength * (3.0 * (dd[0] * u[0] + dd[1] * u[1] + dd[2] * u[2]) * u - dd)


class MagneticTorque(AbstractEffect):
    """Torque of a magnetic dipole on the body in a magnetic field,

        tau = mu_b x B_b,    B_b = R^T B(t)  (body frame),

    with the body's dipole ``mu_b`` (A m^2) given in one of three ways:

    - ``dipole``: ``(3,)`` constant in the body frame (a residual dipole or a
      torque rod held on);
    - ``dipole``: a function ``(t, B_b, omega) -> (3,)`` (a control law);
    - ``bdot_gain=k``: the B-dot detumbling law ``mu_b = -k dB_b/dt``, with
      the field's own change neglected, ``dB_b/dt ~ -omega x B_b``, so
      ``mu_b = k omega x B_b`` and ``tau = k hat(B_b)^2 omega``: it takes
      energy out at ``k |omega x B_b|^2`` and never puts any in.  Its kick
      is exact (a matrix exponential), so the splittings take it.

    A constant dipole does not read the momentum; a control law does, and
    the splittings refuse it (no exact kick).

    Args:
        field: ``t -> B(t)`` (T, space frame), e.g. `dipole_field`.
        dipole: the body's dipole (A m^2), constant or a function, or None.
        bdot_gain: ``k >= 0`` (A m^2 s/T), instead of ``dipole``.
    """

    # dipole_field's field (a Module of arrays) is traced; a function of
    # one's own is part of the program.
    _field_numbers: eqx.Module | None
    _field_function: Callable | None = eqx.field(static=True)
    dipole: Array | None
    law: Callable | None = eqx.field(static=True)
    bdot_gain: Array | None

    def __init__(self, field: Callable, dipole=None, bdot_gain=None):
        if not callable(field):
            raise ValueError(
                f"field must be a function t -> B(t) (T, space frame), e.g. lierk.dipole_field(...), got {field!r}"
            )
        out = jax.eval_shape(field, jax.ShapeDtypeStruct((), jnp.result_type(float)))
        if getattr(out, "shape", None) != (3,):
            raise ValueError(f"field must return shape (3,) for a scalar time, got {getattr(out, 'shape', out)}")
        module = isinstance(field, eqx.Module)
        self._field_numbers, self._field_function = (field, None) if module else (None, field)
        if (dipole is None) == (bdot_gain is None):
            raise ValueError("give exactly one of dipole= (A m^2, constant or a function) and bdot_gain= (B-dot law)")
        self.dipole, self.law, self.bdot_gain = None, None, None
        if bdot_gain is not None:
            self.bdot_gain = validation.check_scalar(bdot_gain, "bdot_gain", bound="non-negative")
        elif callable(dipole):
            self.law = dipole
        else:
            self.dipole = validation.check_vector(dipole, "dipole", jnp.result_type(float))

    @property
    def field(self) -> Callable:
        """``t -> B(t)`` (T, space frame), as given."""
        return self._field_function if self._field_numbers is None else self._field_numbers

    @property
    def reads_momentum(self) -> bool:  # type: ignore[override]
        return self.dipole is None

    def space_vectors(self):
        dtype = next((x.dtype for x in (self.dipole, self.bdot_gain) if x is not None), jnp.result_type(float))
        return np.eye(3, dtype=dtype)

    def _field_body(self, t, v, dtype):
        return so3.matvec(v.T, jnp.asarray(self.field(t), dtype))  # R^T B

    def torque_from(self, t, v, m, omega):
        B = self._field_body(t, v, m.dtype)
        if self.bdot_gain is not None:
            return self.bdot_gain * so3.cross(so3.cross(omega, B), B)
        mu = self.dipole.astype(m.dtype) if self.dipole is not None else jnp.asarray(self.law(t, B, omega), m.dtype)
        return so3.cross(mu, B)

    def affine_torque(self, t, R, inertia_inv):
        if self.bdot_gain is None:
            return super().affine_torque(t, R, inertia_inv)
        # tau = k hat(B)^2 omega = k hat(B)^2 I^{-1} m with B fixed (t and R are).
        K = so3.hat(jnp.asarray(self.field(t), R.dtype) @ R)
        return self.bdot_gain * (K @ K) @ inertia_inv, jnp.zeros(3, R.dtype)

    def kick(self, t, R, m, h, inertia_inv):
        form = self.affine_torque(t, R, inertia_inv)
        if form is None:
            raise ValueError(
                "MagneticTorque with a dipole law reads the momentum and has no exact kick, so a splitting "
                "solver cannot use it; use bdot_gain= for B-dot, or an RKMK solver"
            )
        return affine_flow(*form, m, h)


def _torque_integral(ts: Array, us: Array, t) -> Array:
    """``int_{ts[0]}^t u`` ``(k,)`` of samples ``us`` ``(n, k)`` at ``ts``
    ``(n,)``, linear in between and held at the end values outside (negative
    before ``ts[0]``): exact, a quadratic on each interval."""
    t = jnp.asarray(t, ts.dtype)
    tc = jnp.clip(t, ts[0], ts[-1])
    seg = 0.5 * (us[1:] + us[:-1]) * (ts[1:] - ts[:-1])[:, None]
    cum = jnp.concatenate([jnp.zeros_like(us[:1]), jnp.cumsum(seg, axis=0)])
    i = jnp.clip(jnp.searchsorted(ts, tc, side="right") - 1, 0, ts.shape[0] - 2)
    s = tc - ts[i]
    slope = (us[i + 1] - us[i]) / (ts[i + 1] - ts[i])
    inside = cum[i] + us[i] * s + 0.5 * slope * s * s
    return inside + us[0] * (jnp.minimum(t, ts[0]) - ts[0]) + us[-1] * (jnp.maximum(t, ts[-1]) - ts[-1])


def _wheel_axes(axes) -> Array:
    a = validation.asarray(axes, name="axes")
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
        raise ValueError(f"wheel axes must have shape (k, 3), one unit vector per wheel (body frame), got {a.shape}")
    if not validation.is_traced(a):
        norms = np.linalg.norm(np.asarray(a, float), axis=1)
        bad = np.flatnonzero(~(norms > 1e-12) | ~np.isfinite(norms))
        if bad.size:
            raise ValueError(
                f"wheel axis {int(bad[0])} must be a nonzero finite vector, got {np.asarray(a)[bad[0]].tolist()}"
            )
    return a / jnp.linalg.norm(a, axis=1, keepdims=True)


class Rotor(AbstractEffect):
    """Internal rotors whose momentum relative to the body is prescribed in
    time: a gyrostat, or ideal speed-controlled wheels.

    The rotors' momentum ``h`` (kg m^2/s, body frame: each wheel's spin
    momentum relative to the body along its axis) adds to the body's, and
    whatever torque keeps it on its prescribed course reacts on the body.
    With the problem's momentum ``m = I omega`` (``I`` the whole body's
    inertia, wheels included, as for a balanced wheel in Basilisk),

        dm/dt = m x omega + h x omega - dh/dt.

    The spatial momentum ``R (m + h)`` is conserved without external torques;
    with constant ``h`` so is the kinetic energy ``omega . I omega / 2``.

    Three ways to give ``h(t)``:

    - ``momentum`` ``(3,)`` (body frame) with no ``axes``: a constant rotor
      (a momentum wheel held at constant speed);
    - ``axes`` ``(k, 3)`` and ``momentum`` ``(k,)`` or a function
      ``t -> (k,)`` (each wheel's relative momentum, by autodiff
      differentiated for ``dh/dt``);
    - ``axes``, ``momentum`` ``(k,)`` at ``t = 0`` and ``torque`` ``(n, k)``
      samples (N m) at ``times`` ``(n,)`` (s), linear in between and held
      outside: the rate ``dh/dt`` of the relative momentum, integrated
      exactly to give ``h``.

    ``torque=`` is *not* a motor torque on a free wheel.  It fixes how the
    wheel's speed relative to the body changes, whatever the body does: a
    speed-controlled wheel that follows a commanded profile.  A real motor
    torque ``u`` changes the wheel's absolute momentum, ``Js (Omega' + g .
    omega') = u``, and the relative speed then depends on the body's own
    acceleration: for a spinning body despun by a wheel along its spin axis,
    ``torque=`` makes the body slow down at ``u / I3`` instead of ``u / (I3 -
    Js)``.  For motor torques, and for wheels left to spin freely (which keep
    their absolute momentum, not their relative one), use `ReactionWheels`.

    The state stays the body momentum: the wheels' momenta are known in time,
    so none is integrated.  The term ``h x omega`` reads the momentum; it is
    linear in it, so the splittings' kick is exact
    (`lierk._problems.effects.affine_flow` of ``hat(h) I^{-1}``, with ``dh/dt``
    as a constant forcing over the kick).

    Args:
        momentum: see above (kg m^2/s).
        axes: ``(k, 3)`` wheel spin axes (body frame, normalised here).
        torque: ``(n, k)`` samples of ``dh/dt`` (N m), with ``times``.
        times: ``(n,)`` strictly increasing sample times (s).
    """

    axes: Array | None
    h0: Array
    times: Array | None
    torques: Array | None
    profile: Callable | None = eqx.field(static=True)

    def __init__(self, momentum, axes=None, torque=None, times=None):
        self.axes = None if axes is None else _wheel_axes(axes)
        self.profile, self.times, self.torques = None, None, None
        if callable(momentum):
            if self.axes is None:
                raise ValueError("a wheel momentum function needs the wheels' axes=")
            out = jax.eval_shape(momentum, jax.ShapeDtypeStruct((), jnp.result_type(float)))
            if getattr(out, "shape", None) != (self.axes.shape[0],):
                raise ValueError(
                    f"momentum must return shape ({self.axes.shape[0]},), one per wheel, "
                    f"got {getattr(out, 'shape', out)}"
                )
            self.profile, self.h0 = momentum, jnp.zeros((self.axes.shape[0],), self.axes.dtype)
            return
        k = 3 if self.axes is None else self.axes.shape[0]
        h0 = validation.asarray(momentum, name="momentum")
        if h0.shape != (k,):
            raise ValueError(
                f"momentum must have shape ({k},) ({'body frame' if self.axes is None else 'one per wheel'}), "
                f"got {h0.shape}"
            )
        self.h0 = validation.check(h0, lambda x: (abs(x) < float("inf")).all(), "momentum must be finite, got {value}")
        if torque is None:
            if times is not None:
                raise ValueError("times= go with torque= samples")
            return
        if self.axes is None:
            raise ValueError("motor torques act along wheel axes: give axes= with torque=")
        times = validation.asarray(times, name="times")
        torque = validation.asarray(torque, name="torque")
        if times.ndim != 1 or times.shape[0] < 2 or torque.shape != (times.shape[0], k):
            raise ValueError(
                f"torque must have shape (n, {k}) at times (n,), n >= 2, got {torque.shape} and {times.shape}"
            )
        self.times = validation.check(
            times, lambda v: (v[1:] > v[:-1]).all(), "times must be strictly increasing, got {value}"
        )
        self.torques = validation.check(
            torque, lambda x: (abs(x) < float("inf")).all(), "torque must be finite, got {value}"
        )

    @property
    def driven(self) -> bool:
        """Whether the wheels' prescribed momenta change in time."""
        return self.profile is not None or self.torques is not None

    @property
    def conservative(self) -> bool:  # type: ignore[override]
        return not self.driven

    @property
    def depends_on_time(self) -> bool:  # type: ignore[override]
        return self.driven

    def wheel_momenta(self, t: Array) -> tuple[Array, Array]:
        """``(h, dh/dt)`` at time ``t`` (s), both ``(3,)`` in the body frame."""
        if self.axes is None:
            return self.h0, jnp.zeros_like(self.h0)
        if self.profile is not None:
            hw, uw = jax.jvp(self.profile, (t,), (jnp.ones_like(t),))
        elif self.torques is not None:
            hw, uw = self._integrated(t)
        else:
            hw, uw = self.h0, jnp.zeros_like(self.h0)
        return jnp.asarray(hw) @ self.axes, jnp.asarray(uw) @ self.axes

    def _integrated(self, t):
        """Wheel momenta ``h0 + int_0^t u`` and torques ``u(t)`` ``(k,)`` of the
        piecewise-linear samples held outside their times: exact."""
        u = jax.vmap(lambda col: jnp.interp(t, self.times, col), in_axes=1)(self.torques)
        return self.h0 + _torque_integral(self.times, self.torques, t) - _torque_integral(
            self.times, self.torques, 0.0
        ), u

    def space_vectors(self):
        return np.zeros((0, 3), self.h0.dtype)

    def torque_from(self, t, v, m, omega):
        h, dh = self.wheel_momenta(t)
        return so3.cross(h.astype(m.dtype), omega) - dh.astype(m.dtype)

    def affine_torque(self, t, R, inertia_inv):
        # h_w x omega - dh_w/dt = hat(h_w) I^{-1} m - dh_w/dt, t fixed.
        hw, dh = self.wheel_momenta(t)
        return so3.hat(hw.astype(R.dtype)) @ inertia_inv, -dh.astype(R.dtype)

    def kick(self, t, R, m, h, inertia_inv):
        return affine_flow(*self.affine_torque(t, R, inertia_inv), m, h)

    def invariants(self, R, m):
        """``"|m + h|"`` for constant rotors: the whole body's momentum with
        the rotors', conserved (its spatial direction too) without external
        torques.  None for driven wheels (their momenta depend on time)."""
        if self.driven:
            return {}
        h = self.h0 if self.axes is None else self.h0 @ self.axes
        return {"|m + h|": jnp.linalg.norm(m + h, axis=-1)}

    def conserved(self, inertia):
        return () if self.driven else ("|m + h|",)


class ReactionWheels(AbstractEffect):
    """Reaction wheels driven by motor torques, their speeds integrated with
    the body: Basilisk's balanced wheels (``reactionWheelStateEffector``).

    Wheel ``i`` spins about the body-fixed unit axis ``g_i`` with spin
    inertia ``Js_i`` (kg m^2, about that axis) at ``Omega_i`` (rad/s)
    relative to the body, driven by the motor torque ``u_i(t)`` (N m, on the
    wheel; the body feels ``-u_i g_i``).  ``I`` is the problem's inertia:
    the whole spacecraft's, wheels included (each wheel's inertia about the
    body's centre of mass, its spin inertia about its axis too), as in
    Basilisk.  With ``G = sum Js_i g_i g_i^T``, external torques ``tau`` (the
    problem's other effects) and everything in the body frame,

        (I - G) omega' = -omega x (I omega + sum Js_i Omega_i g_i) - sum u_i g_i + tau,
        Js_i (Omega_i' + g_i . omega') = u_i.

    A motor torque changes a wheel's absolute spin momentum
    ``Js_i (Omega_i + g_i . omega)``; with ``u = 0`` a wheel keeps it (a free
    wheel), not its speed relative to the body.  Spinning a body with
    ``I = diag(I1, I1, I3)`` about a wheel's axis ``z`` and driving the wheel
    with ``u``, the body's rate falls at ``u / (I3 - Js)`` while the wheel
    speeds up at ``u / Js + u / (I3 - Js)``.

    With this effect the problem's state ``y`` is ``(m, Omega)``: the body
    momentum ``m = I omega`` ``(3,)`` (kg m^2/s; ``omega = I^-1 m`` as for
    every body) and the wheels' speeds relative to the body ``Omega``
    ``(k,)`` (rad/s), so a solution's ``y[1]`` are the wheel speeds and
    ``problem.restart(R, y)`` carries them on.  The speeds given here are the
    initial ones, read when the problem is built (so a sensitivity with
    respect to them selects the state's, ``wrt=lambda p: p.y0[1]``);
    `~lierk.RigidBodyWithEffects.with_omega0` keeps the relative speeds of
    the state it starts from.  The spin inertias, axes and torques are read
    at every stage, so a sweep or a sensitivity over them is exact.

    The problem's invariants include the wheels: the total momentum
    ``"|L|"``, ``|m + sum Js_i Omega_i g_i|``, is conserved whenever no
    other effect acts, driven or not; the energy,

        omega . I omega / 2 + sum Js_i Omega_i (g_i . omega) + sum Js_i Omega_i^2 / 2,

    changes at ``sum u_i Omega_i`` (the motors' power) plus the external
    torques' ``tau . omega``, so it is conserved when ``torque`` is None.

    Every RKMK, Crouch-Grossman and adaptive solver takes it, with events,
    dense output and sensitivities (the variational method too).  The
    splittings refuse it: their drift is the exact torque-free flow of a
    rigid body, which a body with wheels does not follow.  A body holds at
    most one `ReactionWheels` (put every wheel in it).

    Args:
        axes: ``(k, 3)`` spin axes (body frame), normalised here.
        spin_inertia: ``(k,)`` each wheel's spin inertia ``Js`` about its
            axis (kg m^2), ``> 0``; ``I - G`` must stay positive definite.
        speeds: ``(k,)`` speeds relative to the body at the start (rad/s).
        torque: the motor torques (N m, on the wheels): None (free wheels),
            a constant ``(k,)``, samples ``(n, k)`` at ``times`` (linear in
            between and held at the end values outside), or a function
            ``t -> (k,)`` of time (s) that JAX can trace.
        times: ``(n,)`` strictly increasing sample times (s), only with
            sampled torques.

    Example:
        >>> wheels = ReactionWheels([[0, 0, 1.0]], [0.159], [100 * 2 * np.pi / 60], torque=[0.2])
        >>> body = lierk.RigidBodyWithEffects([2.0, 2.0, 2.159], [0, 0, 0.35], effects=(wheels,))
        >>> sol = lierk.solve(body, lierk.RKMK4(), 5.0, dt=0.01)
        >>> m, wheel_speeds = sol.y
        >>> wheel_speeds[-1]    # relative to the body at 5 s (rad/s)
    """

    axes: Array
    spin_inertia: Array
    speeds: Array
    times: Array | None
    torques: Array | None
    fn: Callable | None = eqx.field(static=True)
    # Not a torque that the splittings could kick: they refuse the wheels
    # outright (`RigidBodyWithEffects.kick`), and a Runge-Kutta-Nystrom
    # splitting must not first send the user to another splitting.
    reads_momentum: ClassVar[bool] = False

    def __init__(self, axes, spin_inertia, speeds, torque=None, times=None):
        self.axes = _wheel_axes(axes)
        k = self.axes.shape[0]
        self.spin_inertia = _per_wheel(spin_inertia, "spin_inertia", k, "kg m^2")
        self.spin_inertia = validation.check(
            self.spin_inertia, lambda x: (x > 0).all(), "spin_inertia must be > 0 for every wheel (kg m^2), got {value}"
        )
        self.speeds = _per_wheel(speeds, "speeds", k, "rad/s")
        self.fn, self.times, self.torques = None, None, None
        if torque is None:
            if times is not None:
                raise ValueError("times= go with sampled motor torques (torque= of shape (n, k))")
            return
        if callable(torque):
            if times is not None:
                raise ValueError("times apply to sampled torques; a torque function takes the time itself")
            out = jax.eval_shape(torque, jax.ShapeDtypeStruct((), jnp.result_type(float)))
            if getattr(out, "shape", None) != (k,):
                raise ValueError(
                    f"a motor torque function must return shape ({k},), one per wheel, for a scalar time, "
                    f"got {getattr(out, 'shape', out)}"
                )
            self.fn = torque
            return
        u = validation.asarray(torque, name="torque")
        if times is None:
            if u.shape != (k,):
                raise ValueError(
                    f"a constant motor torque must have shape ({k},), one per wheel (N m); samples "
                    f"(n, {k}) need times=; got shape {u.shape}"
                )
        else:
            times = validation.asarray(times, name="times")
            if times.ndim != 1 or times.shape[0] < 1 or u.shape != (times.shape[0], k):
                raise ValueError(
                    f"sampled motor torques must have shape (n, {k}), one row per time, at times (n,); "
                    f"got {u.shape} and {times.shape}"
                )
            times = validation.check(
                times, lambda v: (abs(v) < float("inf")).all(), "times must be finite, got {value}"
            )
            self.times = validation.check(
                times, lambda v: (v[1:] > v[:-1]).all(), "times must be strictly increasing, got {value}"
            )
        self.torques = validation.check(
            u, lambda x: (abs(x) < float("inf")).all(), "torque must be finite, got {value}"
        )

    @property
    def driven(self) -> bool:
        """Whether a motor torque is given (None: free wheels)."""
        return self.fn is not None or self.torques is not None

    @property
    def conservative(self) -> bool:  # type: ignore[override]
        return not self.driven

    @property
    def depends_on_time(self) -> bool:  # type: ignore[override]
        return self.fn is not None or self.times is not None

    def motor_torque(self, t: Array) -> Array | None:
        """The motor torques ``(k,)`` (N m) at time ``t`` (s), or None for
        free wheels (then the problem adds no operation for them)."""
        if self.fn is not None:
            return jnp.asarray(self.fn(t))
        if self.torques is None:
            return None
        if self.times is None:
            return self.torques
        return jax.vmap(lambda col: jnp.interp(t, self.times, col), in_axes=1)(self.torques)

    def relative_momentum(self, speeds: Array) -> Array:
        """``sum Js_i Omega_i g_i`` ``(..., 3)`` (kg m^2/s, body frame): the
        wheels' momentum relative to the body at speeds ``Omega`` ``(..., k)``
        (rad/s), e.g. a solution's ``y[1]``."""
        return _wheel_sum(self.spin_inertia * speeds, self.axes)

    def space_vectors(self):
        return np.zeros((0, 3), self.axes.dtype)

    def torque_from(self, t, v, m, omega):
        raise ValueError(
            "ReactionWheels add no torque of their own: a RigidBodyWithEffects integrates their speeds with the "
            "body (the wheels change how every torque turns it); give the effect to RigidBodyWithEffects"
        )

    def affine_torque(self, t, R, inertia_inv):
        return None


def _wheel_sum(c: Array, axes: Array) -> Array:
    """``sum_i c_i g_i`` ``(..., 3)`` of per-wheel amounts ``c`` ``(..., k)``
    along the axes ``g_i`` (rows of ``axes`` ``(k, 3)``): unrolled products,
    which fuse with a stage's arithmetic where a ``(k,) @ (k, 3)`` product is
    a kernel of its own under vmap."""
    out = c[..., 0, None] * axes[0]
    for i in range(1, axes.shape[0]):
        out = out + c[..., i, None] * axes[i]
    return out


def _along(axes: Array, v: Array) -> Array:
    """``g_i . v`` ``(..., k)`` for each wheel axis (rows of ``axes``
    ``(k, 3)``) and vectors ``v`` ``(..., 3)``."""
    return v[..., 0, None] * axes[:, 0] + v[..., 1, None] * axes[:, 1] + v[..., 2, None] * axes[:, 2]


def _spin_matrix(spin_inertia: Array, axes: Array) -> Array:
    """``G = sum Js_i g_i g_i^T`` ``(3, 3)`` (kg m^2)."""
    G = spin_inertia[0] * (axes[0][:, None] * axes[0][None, :])
    for i in range(1, axes.shape[0]):
        G = G + spin_inertia[i] * (axes[i][:, None] * axes[i][None, :])
    return G


def _per_wheel(x, name: str, k: int, unit: str):
    """``(k,)`` finite numbers, one per wheel."""
    a = validation.asarray(x, name=name)
    if a.shape != (k,):
        raise ValueError(f"{name} must have shape ({k},), one per wheel ({unit}), got shape {a.shape}")
    return validation.check(
        a, lambda v: (abs(v) < float("inf")).all(), f"{name} must be finite ({unit}), got {{value}}"
    )
