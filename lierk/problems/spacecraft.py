"""Spacecraft effects: gravity-gradient torque, magnetic torque (a magnetorquer
or a B-dot controller in a dipole field) and internal rotors (reaction or
momentum wheels: a gyrostat).  Each is an opt-in `AbstractEffect` of
`lierk.RigidBodyWithEffects`, compiled only where a problem holds it.

Frames and orbit.  ``R`` maps body to space as everywhere in lierk; "space"
is an inertial frame centred on the planet.  A circular orbit of radius ``a``
(m) and mean motion ``n = sqrt(mu/a^3)`` (rad/s) lies in the space ``x-y``
plane, with the spacecraft at

    r(t) = a (cos(n t + phase), sin(n t + phase), 0),

so the orbit normal is space ``z``.  Units are SI: torques N m, magnetic
fields T, dipole moments A m^2, wheel momenta kg m^2/s.

The equations are those of Basilisk's ``GravityGradientEffector``,
``MtbEffector`` and ``reactionWheelStateEffector`` (balanced wheels), and of
Hughes, *Spacecraft Attitude Dynamics* (gyrostats, gravity gradient) and
Markley and Crassidis, *Fundamentals of Spacecraft Attitude Determination and
Control* (B-dot).
"""

from __future__ import annotations

from typing import Callable, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import so3, validation
from .effects import AbstractEffect, affine_flow

__all__ = ["MU_EARTH", "R_EARTH", "B0_EARTH", "circular_orbit", "GravityGradient", "dipole_field", "MagneticTorque", "Rotor"]

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
    reads_momentum: ClassVar[bool] = False

    def __init__(self, inertia: ArrayLike, radius=None, mean_motion=None, mu=MU_EARTH, phase=0.0, position=None):
        self.inertia = validation.check_inertia(inertia)
        self.mu = _positive(mu, "mu")
        self.phase = validation.check_scalar(phase, "phase")
        if position is not None:
            if radius is not None or mean_motion is not None:
                raise ValueError("give the orbit as position= or as a circular orbit (radius= or mean_motion=), not both")
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
        eig = jnp.linalg.eigvalsh(self.inertia)
        return 1.5 * n2 * (eig[-1] - eig[0])


def dipole_field(mean_motion, radius=None, tilt=0.0, B0=B0_EARTH, planet_radius=R_EARTH, phase=0.0) -> Callable:
    """The field ``B(t)`` (T, space frame) of a centred magnetic dipole along
    the circular orbit of `circular_orbit` (radius ``a``):

        B = B0 (R_p/a)^3 (3 (d . u) u - d),    d = -(sin(tilt), 0, cos(tilt)),

    ``d`` the dipole's direction, ``tilt`` (rad) its angle to the orbit
    normal (space ``z``): 0 is an equatorial orbit (a constant field along
    ``+z``), pi/2 a polar one (the field turns twice per orbit).  Earth's
    dipole, 3.12e-5 T at the equator, by default.

    Args:
        mean_motion: orbit rate (rad/s).
        radius: orbit radius (m); default ``(MU_EARTH / n^2)^(1/3)``.
        tilt: the dipole's angle to the orbit normal (rad).
        B0: the field at the planet's equator on its surface (T).
        planet_radius: m.
        phase: the orbit angle at ``t = 0`` (rad).

    Returns:
        A function ``t -> (3,)`` that JAX traces.
    """
    n = float(mean_motion)
    a = (MU_EARTH / n**2) ** (1.0 / 3.0) if radius is None else float(radius)
    for name, value in (("mean_motion", n), ("radius", a), ("B0", B0), ("planet_radius", planet_radius)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    if not np.isfinite(tilt):
        raise ValueError(f"tilt must be finite (rad), got {tilt!r}")
    strength = float(B0) * (float(planet_radius) / a) ** 3
    d = -np.array([np.sin(tilt), 0.0, np.cos(tilt)])

    def field(t):
        u = circular_orbit(t, n, phase)
        dd = jnp.asarray(d, u.dtype)
        # d . u by components: jnp.dot is a reduction, a kernel of its own at
        # every stage, where the products fuse with what reads the field.
        return strength * (3.0 * (dd[0] * u[0] + dd[1] * u[1] + dd[2] * u[2]) * u - dd)

    return field


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

    field: Callable = eqx.field(static=True)
    dipole: Array | None
    law: Callable | None = eqx.field(static=True)
    bdot_gain: Array | None

    def __init__(self, field: Callable, dipole=None, bdot_gain=None):
        if not callable(field):
            raise ValueError(f"field must be a function t -> B(t) (T, space frame), e.g. lierk.dipole_field(...), got {field!r}")
        out = jax.eval_shape(field, jax.ShapeDtypeStruct((), jnp.result_type(float)))
        if getattr(out, "shape", None) != (3,):
            raise ValueError(f"field must return shape (3,) for a scalar time, got {getattr(out, 'shape', out)}")
        self.field = field
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
            raise ValueError(f"wheel axis {int(bad[0])} must be a nonzero finite vector, got {np.asarray(a)[bad[0]].tolist()}")
    return a / jnp.linalg.norm(a, axis=1, keepdims=True)


class Rotor(AbstractEffect):
    """Internal rotors (reaction or momentum wheels) that make the body a
    gyrostat.

    The rotors' momentum ``h`` (kg m^2/s, body frame: each wheel's spin
    momentum relative to the body along its axis) adds to the body's, and a
    motor torque ``u`` on a wheel reacts on the body.  With the problem's
    momentum ``m = I omega`` (``I`` the whole body's inertia, wheels
    included, as for a balanced wheel in Basilisk),

        dm/dt = m x omega + h x omega - dh/dt.

    The spatial momentum ``R (m + h)`` is conserved without external torques;
    with constant ``h`` so is the kinetic energy ``omega . I omega / 2``.

    Three ways to give ``h(t)``:

    - ``momentum`` ``(3,)`` (body frame) with no ``axes``: a constant rotor
      (a momentum wheel at constant speed);
    - ``axes`` ``(k, 3)`` and ``momentum`` ``(k,)`` or a function
      ``t -> (k,)`` (each wheel's momentum; its derivative is the motor
      torque, by autodiff);
    - ``axes``, ``momentum`` ``(k,)`` at ``t = 0`` and ``torque`` ``(n, k)``
      samples (N m) at ``times`` ``(n,)`` (s): motor torques linear in
      between and held outside, whose integral gives ``h`` exactly.

    The state stays the body momentum: the wheels' momenta are known in time
    (a driven wheel's commanded profile), so none is integrated.  The term
    ``h x omega`` reads the momentum; it is linear in it, so the splittings'
    kick is exact (`lierk.problems.effects.affine_flow` of ``hat(h) I^{-1}``,
    with the motor torque as a constant forcing over the kick).

    Args:
        momentum: see above (kg m^2/s).
        axes: ``(k, 3)`` wheel spin axes (body frame, normalised here).
        torque: ``(n, k)`` motor torque samples (N m), with ``times``.
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
                raise ValueError(f"momentum must return shape ({self.axes.shape[0]},), one per wheel, got {getattr(out, 'shape', out)}")
            self.profile, self.h0 = momentum, jnp.zeros((self.axes.shape[0],), self.axes.dtype)
            return
        k = 3 if self.axes is None else self.axes.shape[0]
        h0 = validation.asarray(momentum, name="momentum")
        if h0.shape != (k,):
            raise ValueError(f"momentum must have shape ({k},) ({'body frame' if self.axes is None else 'one per wheel'}), got {h0.shape}")
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
            raise ValueError(f"torque must have shape (n, {k}) at times (n,), n >= 2, got {torque.shape} and {times.shape}")
        self.times = validation.check(times, lambda v: (v[1:] > v[:-1]).all(), "times must be strictly increasing, got {value}")
        self.torques = validation.check(torque, lambda x: (abs(x) < float("inf")).all(), "torque must be finite, got {value}")

    @property
    def driven(self) -> bool:
        """Whether the wheels' momenta change in time (a motor torque acts)."""
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
        return self.h0 + _torque_integral(self.times, self.torques, t) - _torque_integral(self.times, self.torques, 0.0), u

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
