"""The Lagrange top by quadrature: tilt extrema, nutation period and mean
precession rate from the conserved quantities (pure NumPy/SciPy, float64).

A Lagrange top is a heavy top whose inertia about the pivot is symmetric about
the axis through the pivot and the centre of mass: with ``a`` the unit body
vector along ``chi`` (pivot -> centre of mass, ``|chi| = l``), ``I a = I3 a``
and ``I = I1`` on the plane orthogonal to ``a``.  The axis need not be body z
(the Bruls-Cardona-Arnold top is symmetric about body y).

Derivation, in lierk's conventions (``R`` body -> space, ``dR/dt = R hat(omega)``,
body momentum ``m = I omega`` about the pivot, space z up, torque
``M g (Gamma x chi)`` with ``Gamma = R^T e3``); Goldstein, Classical
Mechanics, 3rd ed., section 5.7, and Landau and Lifshitz, Mechanics, section 35,
do the same in Euler angles.  Let

    u = cos(theta) = e3 . (R a) = Gamma . a          (theta: tilt of the axis from vertical)
    m = m3 a + m_perp,   m3 = m . a,                   m_perp . a = 0.

Three quantities are conserved:

    m3  = m . a                                   (dm/dt . a = (m x omega + tau) . a = 0 for this I, chi)
    L_z = e3 . (R m) = Gamma . m = m3 u + m_perp . Gamma_perp
    E   = m3^2/(2 I3) + |m_perp|^2/(2 I1) + M g l u

and ``E' = E - m3^2/(2 I3) = |m_perp|^2/(2 I1) + M g l u`` (computed that
way, without the cancellation a fast spin would cause).  Since
``dGamma/dt = Gamma x omega``, ``du/dt = a . (Gamma x omega) = (m_perp/I1) . (a x Gamma_perp)``.
Write ``m_perp = p e_g + q e_h`` in the orthonormal basis ``e_g = Gamma_perp/|Gamma_perp|``,
``e_h = a x e_g`` of the plane orthogonal to ``a``, with ``|Gamma_perp| = sqrt(1 - u^2)``:

    p = (L_z - m3 u)/sqrt(1 - u^2),      q = I1 u'/sqrt(1 - u^2),

and the energy ``p^2 + q^2 = 2 I1 (E' - M g l u)`` gives the one-dimensional motion

    I1^2 u'^2 = f(u) = 2 I1 (E' - M g l u)(1 - u^2) - (L_z - m3 u)^2.

``f`` is a cubic with leading coefficient ``2 I1 M g l > 0``, ``f(+-1) = -(L_z -+ m3)^2 <= 0``
and ``f(u0) = I1^2 u0'^2 >= 0``, so it has roots ``-1 <= u1 <= u0 <= u2 <= 1 < u3``
and ``u`` oscillates between ``u1`` and ``u2``: the tilt between
``theta_min = arccos(u2)`` and ``theta_max = arccos(u1)``.  The nutation period is

    T = 2 I1 int_{u1}^{u2} du / sqrt(f(u)),

and with ``u = u1 + (u2 - u1) sin^2(s)``, ``f = c3 (u - u1)(u2 - u)(u3 - u)`` and
``(u - u1)(u2 - u) = (u2 - u1)^2 sin^2(s) cos^2(s)`` the endpoint singularities cancel:

    T = 4 I1 int_0^{pi/2} ds / sqrt(c3 (u3 - u(s))),    c3 = 2 I1 M g l,

a smooth integrand (it is ``4 I1 K(k)/sqrt(c3 (u3 - u1))`` with
``k^2 = (u2 - u1)/(u3 - u1)``, which `nutation_period_elliptic` uses as a check).
The azimuth ``phi`` of the axis ``n = R a`` about space z (counter-clockwise
seen from above) turns at

    phi' = p/(I1 sqrt(1 - u^2)) = (L_z - m3 u)/(I1 (1 - u^2))

(the horizontal angular momentum ``p e_g`` about the axis), which depends on
``u`` alone, so over any interval of length ``T`` it advances by the same

    Delta phi = 2 int_{u1}^{u2} (L_z - m3 u)/(1 - u^2) du/sqrt(f)
              = 4 int_0^{pi/2} (L_z - m3 u)/((1 - u)(1 + u)) ds/sqrt(c3 (u3 - u(s))),

and the mean precession rate is ``Delta phi / T``.  Both integrals are
computed with `scipy.integrate.quad` at ``epsrel = 5e-14`` (its floor is 50 eps;
on these smooth integrands Gauss-Kronrod reaches rounding).

The roots come from `numpy.roots` and are polished by Newton's method on
``f`` evaluated in ``numpy.longdouble`` (80-bit on x86), so they carry the
accuracy of the float64 conserved quantities (a few ulp for well separated
roots).  The formulas need ``M g l > 0`` and an axis that does not pass
through the vertical (``L_z != +-m3``), which all the tops here satisfy.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
from scipy import integrate, special

__all__ = [
    "LagrangeTop",
    "lagrange_top",
    "symmetry_axis",
    "tilt_jets",
    "hermite_extrema",
    "axis_azimuth",
    "ode_reference",
]


@dataclasses.dataclass(frozen=True)
class LagrangeTop:
    """The reduced motion of one Lagrange top (SI units).

    Attributes:
        I1, I3: transverse and axial moments about the pivot (kg m^2).
        mgl: ``M g l`` (N m), ``l = |chi|``.
        axis: ``(3,)`` unit body vector from the pivot to the centre of mass.
        m3: body momentum along the axis (kg m^2/s).
        Lz: vertical component of the spatial momentum (kg m^2/s).
        E_prime: energy less the axial spin's ``m3^2/(2 I3)`` (J).
        u0: initial ``cos(theta)``.
        u1, u2, u3: roots of ``f``; ``u`` oscillates in ``[u1, u2]``, ``u3 > 1``.
        gap_lo, gap_hi: ``1 + u1`` and ``1 - u2`` to full relative precision.
        theta_min, theta_max: extreme tilts of the axis from the vertical (rad).
        period: nutation period ``T`` (s).
        precession_per_period: azimuth advanced by the axis per period (rad).
    """

    I1: float
    I3: float
    mgl: float
    axis: np.ndarray
    m3: float
    Lz: float
    E_prime: float
    u0: float
    u1: float
    u2: float
    u3: float
    gap_lo: float
    gap_hi: float
    period: float
    precession_per_period: float

    @property
    def theta_min(self) -> float:
        """``arccos(u2)`` (rad), from the gap: ``1 - cos(theta) = 2 sin^2(theta/2)``."""
        return 2 * math.asin(math.sqrt(self.gap_hi / 2))

    @property
    def theta_max(self) -> float:
        """``arccos(u1)`` (rad), from the gap ``1 + u1``."""
        return math.pi - 2 * math.asin(math.sqrt(self.gap_lo / 2))

    @property
    def mean_precession_rate(self) -> float:
        """``Delta phi / T`` (rad/s)."""
        return self.precession_per_period / self.period

    @property
    def nutation_frequency(self) -> float:
        """``2 pi / T`` (rad/s)."""
        return 2 * math.pi / self.period

    def f(self, u):
        """``f(u) = I1^2 u'^2`` ((kg m^2)^2/s^2) at ``u`` (any shape)."""
        u = np.asarray(u)
        return 2 * self.I1 * (self.E_prime - self.mgl * u) * (1 - u * u) - (self.Lz - self.m3 * u) ** 2

    def precession_rate(self, u):
        """Instantaneous ``phi'`` (rad/s) at ``u`` (any shape)."""
        u = np.asarray(u)
        return (self.Lz - self.m3 * u) / (self.I1 * (1 - u) * (1 + u))

    def nutation_period_elliptic(self) -> float:
        """``T = 4 I1 K(k)/sqrt(c3 (u3 - u1))``, ``k^2 = (u2 - u1)/(u3 - u1)``: the
        closed form of `period`, an independent check of the quadrature."""
        c3 = 2 * self.I1 * self.mgl
        return (
            4
            * self.I1
            * special.ellipk((self.u2 - self.u1) / (self.u3 - self.u1))
            / math.sqrt(c3 * (self.u3 - self.u1))
        )


def symmetry_axis(inertia, pivot_to_com, rtol: float = 1e-12):
    """``(a, I1, I3)``: the unit axis along ``pivot_to_com`` ``(3,)`` and the
    transverse and axial moments of ``inertia`` ``(3, 3)`` (kg m^2, about the
    pivot).  Raises ValueError unless the inertia is symmetric about that axis
    (relative tolerance ``rtol``): only then is the top a Lagrange top."""
    I = np.asarray(inertia, dtype=float)
    I = np.diag(I) if I.ndim == 1 else I
    chi = np.asarray(pivot_to_com, dtype=float)
    a = chi / np.linalg.norm(chi)
    I3 = float(a @ I @ a)
    P = np.eye(3) - np.outer(a, a)
    I1 = 0.5 * float(np.trace(P @ I @ P))
    scale = np.abs(I).max()
    if np.abs(I @ a - I3 * a).max() > rtol * scale or np.abs(P @ I @ P - I1 * P).max() > rtol * scale:
        raise ValueError(f"inertia {I.tolist()} is not symmetric about pivot_to_com {chi.tolist()}")
    return a, I1, I3


def _polish(f, df, u, iterations: int = 8) -> float:
    """Newton on ``f`` (evaluated in extended precision by the caller) from ``u``."""
    x = np.longdouble(u)
    for _ in range(iterations):
        d = df(x)
        if d == 0:
            break
        step = f(x) / d
        x = x - step
        if abs(step) <= 1e-19 * max(1.0, abs(x)):
            break
    return float(x)


def lagrange_top(inertia, pivot_to_com, mg, R0, omega0) -> LagrangeTop:
    """The Lagrange top with ``inertia`` ``(3, 3)`` or ``(3,)`` about the pivot
    (kg m^2), centre of mass at ``pivot_to_com`` ``(3,)`` (body frame, m),
    weight ``mg = M g`` (N), initial attitude ``R0`` ``(3, 3)`` (body -> space)
    and body angular velocity ``omega0`` ``(3,)`` (rad/s)."""
    I = np.asarray(inertia, dtype=float)
    I = np.diag(I) if I.ndim == 1 else I
    a, I1, I3 = symmetry_axis(I, pivot_to_com)
    mgl = float(mg) * float(np.linalg.norm(pivot_to_com))
    if not mgl > 0:
        raise ValueError("the quadrature needs M g l > 0")
    R0 = np.asarray(R0, dtype=float)
    m0 = I @ np.asarray(omega0, dtype=float)
    gamma = R0[2, :]
    u0 = float(gamma @ a)
    m3 = float(m0 @ a)
    Lz = float(gamma @ m0)
    m_perp = m0 - m3 * a
    E_prime = float(m_perp @ m_perp) / (2 * I1) + mgl * u0

    # f(u) = c3 u^3 + c2 u^2 + c1 u + c0 (expand the definition in the docstring).
    coeffs = [
        2 * I1 * mgl,
        -(2 * I1 * E_prime + m3 * m3),
        -2 * I1 * mgl + 2 * Lz * m3,
        2 * I1 * E_prime - Lz * Lz,
    ]
    roots = np.sort(np.real(np.roots(coeffs)))
    # Polish on f's defining form, in extended precision: the expanded
    # coefficients are rounded at the scale of their largest term (m3^2 for a
    # fast top), which moves the roots by ~1e-13; the conserved quantities
    # themselves are exact to an ulp.
    ld = np.longdouble
    I1_, mgl_, E_, Lz_, m3_ = ld(I1), ld(mgl), ld(E_prime), ld(Lz), ld(m3)

    def f(u):
        return 2 * I1_ * (E_ - mgl_ * u) * (1 - u * u) - (Lz_ - m3_ * u) ** 2

    def df(u):
        return -2 * I1_ * mgl_ * (1 - u * u) - 4 * I1_ * (E_ - mgl_ * u) * u + 2 * m3_ * (Lz_ - m3_ * u)

    u1, u2, u3 = (_polish(f, df, r) for r in roots)
    # The gaps 1 + u1 and 1 - u2 to full relative precision, by Newton in the
    # shifted variable (float64 u1 = -1 + 2.6e-13 would know 1 + u1 only to
    # 4e-4; the azimuth's spike near the vertical and theta near 0 or pi need it).
    d_lo, d_hi = ld(Lz) + ld(m3), ld(Lz) - ld(m3)  # L_z -+ m3, exact for float64 inputs

    def f_lo(v):  # f(-1 + v)
        return 2 * I1_ * (E_ + mgl_ - mgl_ * v) * v * (2 - v) - (d_lo - m3_ * v) ** 2

    def df_lo(v):
        return (
            -2 * I1_ * mgl_ * v * (2 - v) + 2 * I1_ * (E_ + mgl_ - mgl_ * v) * (2 - 2 * v) + 2 * m3_ * (d_lo - m3_ * v)
        )

    def f_hi(w):  # f(1 - w)
        return 2 * I1_ * (E_ - mgl_ + mgl_ * w) * w * (2 - w) - (d_hi + m3_ * w) ** 2

    def df_hi(w):
        return (
            2 * I1_ * mgl_ * w * (2 - w) + 2 * I1_ * (E_ - mgl_ + mgl_ * w) * (2 - 2 * w) - 2 * m3_ * (d_hi + m3_ * w)
        )

    gap_lo = _polish(f_lo, df_lo, 1 + u1)
    gap_hi = _polish(f_hi, df_hi, 1 - u2)
    # A top released at an extremum has u0 as a root: rounding may leave it a hair outside.
    slack = 1e-12
    if not (-1 - slack <= u1 <= u0 + slack and u0 - slack <= u2 <= 1 + slack and u3 > 1):
        raise ValueError(f"roots {u1, u2, u3} do not bracket u0 = {u0}: not a physical top?")
    c3 = coeffs[0]
    d = u2 - u1

    def dt_ds(s):  # T = 4 I1 int ds/sqrt(c3 (u3 - u))
        return 1.0 / math.sqrt(c3 * (u3 - u1 - d * math.sin(s) ** 2))

    def dphi_ds(s):
        sin2, cos2 = math.sin(s) ** 2, math.cos(s) ** 2
        u = u1 + d * sin2
        # 1 + u = gap_lo + d sin^2 s and 1 - u = gap_hi + d cos^2 s, free of cancellation.
        return (Lz - m3 * u) / ((gap_hi + d * cos2) * (gap_lo + d * sin2)) / math.sqrt(c3 * (u3 - u))

    quad = dict(epsabs=0.0, epsrel=5e-14, limit=500)  # quad refuses epsrel < 50 eps
    period = 4 * I1 * integrate.quad(dt_ds, 0.0, math.pi / 2, **quad)[0]
    # An axis that passes close to the vertical (|L_z| ~ |m3|) swings its
    # azimuth by ~pi within a sliver of s of width sqrt((1 -+ u)/(u2 - u1))
    # (s -> 0 near u1 = -1, s -> pi/2 near u2 = 1): breakpoints on a geometric
    # ladder from that width let quad see the spike.
    points = []
    for gap, at_end in ((gap_lo, False), (gap_hi, True)):
        w = math.sqrt(max(gap, 0.0) / (u2 - u1))
        while 0 < w < 0.1:
            points.append(math.pi / 2 - w if at_end else w)
            w *= 10
    with warnings.catch_warnings():
        # With a spike (the Bruls-Cardona-Arnold top passes 7e-7 rad from the
        # nadir) quad reports roundoff short of 5e-14; the result still matches
        # SciPy's DOP853 trajectories to 1.2e-10 (tests/test_tops.py).
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        precession = 4 * integrate.quad(dphi_ds, 0.0, math.pi / 2, points=sorted(points) or None, **quad)[0]
    return LagrangeTop(I1, I3, mgl, a, m3, Lz, E_prime, u0, u1, u2, u3, gap_lo, gap_hi, period, precession)


def tilt_jets(inertia, pivot_to_com, mg, R, m):
    """``(u, u', u'')`` of ``u = e3 . (R a)`` along a trajectory, from the state alone.

    ``R`` ``(n, 3, 3)`` and ``m`` ``(n, 3)`` at ``n`` times; with
    ``Gamma = R^T e3``, ``omega = I^{-1} m``, ``dGamma/dt = Gamma x omega`` and
    ``I omega' = m x omega + mg (Gamma x chi)``:
    ``u' = a . (Gamma x omega)``, ``u'' = a . ((Gamma x omega) x omega + Gamma x omega')``.
    Returns three ``(n,)`` arrays (1, 1/s, 1/s^2)."""
    I = np.asarray(inertia, dtype=float)
    I = np.diag(I) if I.ndim == 1 else I
    chi = np.asarray(pivot_to_com, dtype=float)
    a = chi / np.linalg.norm(chi)
    R, m = np.asarray(R, dtype=float), np.asarray(m, dtype=float)
    gamma = R[:, 2, :]
    w = np.linalg.solve(I, m.T).T
    dgamma = np.cross(gamma, w)
    dw = np.linalg.solve(I, (np.cross(m, w) + mg * np.cross(gamma, chi)).T).T
    return gamma @ a, dgamma @ a, (np.cross(dgamma, w) + np.cross(gamma, dw)) @ a


def hermite_extrema(ts, u, du, d2u):
    """Local extrema of ``u(t)`` strictly inside ``ts``, from samples of ``u``,
    ``u'`` and ``u''`` (each ``(n,)``): on every interval where ``u'`` changes sign,
    the quintic Hermite interpolant's extremum.

    Its interpolation error is at most ``max|u^(6)| h^6/(6! 4^3)`` on an
    interval of length ``h`` (nodes of multiplicity three at both ends), and
    the interpolant's extreme value is within that of the true one.

    Returns ``(t_star, u_star)``, two arrays in time order."""
    ts, u, du, d2u = (np.asarray(x, dtype=float) for x in (ts, u, du, d2u))
    t_out, u_out = [], []
    for k in np.nonzero(du[:-1] * du[1:] < 0)[0]:
        h = ts[k + 1] - ts[k]
        # p(x) = u_k + sum_{j>=1} c_j x^j on x in [0, 1]; match value, slope and
        # curvature at both ends (slopes scaled by h, curvatures by h^2).
        A = np.array(
            [
                [1, 0, 0, 0, 0],
                [0, 2, 0, 0, 0],
                [1, 1, 1, 1, 1],
                [1, 2, 3, 4, 5],
                [0, 2, 6, 12, 20],
            ],
            dtype=float,
        )
        b = np.array([h * du[k], h * h * d2u[k], u[k + 1] - u[k], h * du[k + 1], h * h * d2u[k + 1]])
        c = np.linalg.solve(A, b)  # c_1 .. c_5
        dp = np.array([5 * c[4], 4 * c[3], 3 * c[2], 2 * c[1], c[0]])
        cand = [r.real for r in np.roots(dp) if abs(r.imag) < 1e-9 and -1e-9 <= r.real <= 1 + 1e-9]
        if not cand:
            continue
        # The root nearest the linear estimate of u' = 0 is the bracketed one.
        x_lin = du[k] / (du[k] - du[k + 1])
        x = min(cand, key=lambda r: abs(r - x_lin))
        for _ in range(3):  # Newton on p' polishes np.roots' answer
            x = x - np.polyval(dp, x) / np.polyval(np.polyder(dp), x)
        t_out.append(ts[k] + h * x)
        u_out.append(u[k] + np.polyval(np.concatenate([c[::-1], [0.0]]), x))
    return np.array(t_out), np.array(u_out)


def axis_azimuth(R, pivot_to_com):
    """Unwrapped azimuth (rad) about space z of the axis ``R a`` at each of the
    ``n`` attitudes ``R`` ``(n, 3, 3)``; consecutive samples must differ by less
    than pi."""
    chi = np.asarray(pivot_to_com, dtype=float)
    n = np.asarray(R, dtype=float) @ (chi / np.linalg.norm(chi))
    return np.unwrap(np.arctan2(n[:, 1], n[:, 0]))


def ode_reference(inertia, pivot_to_com, mg, R0, omega0, t_eval, rtol: float = 1e-13):
    """``(R, m)`` of the heavy top at ``t_eval`` ``(n,)`` (s) from SciPy's DOP853
    on the 12-component system ``dR/dt = R hat(omega)``,
    ``dm/dt = m x omega + mg (Gamma x chi)``, ``Gamma = R^T e3``; an
    integrator independent of lierk.  ``R`` ``(n, 3, 3)``, ``m`` ``(n, 3)``;
    ``atol = rtol`` on both (``R``'s entries are O(1), pick units so ``m`` is too)."""
    I = np.asarray(inertia, dtype=float)
    I = np.diag(I) if I.ndim == 1 else I
    Iinv = np.linalg.inv(I)
    chi = np.asarray(pivot_to_com, dtype=float)

    def f(t, x):
        R, m = x[:9].reshape(3, 3), x[9:]
        w = Iinv @ m
        W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return np.concatenate([(R @ W).ravel(), np.cross(m, w) + mg * np.cross(R[2, :], chi)])

    t_eval = np.asarray(t_eval, dtype=float)
    x0 = np.concatenate([np.asarray(R0, dtype=float).ravel(), I @ np.asarray(omega0, dtype=float)])
    sol = integrate.solve_ivp(f, (0.0, t_eval[-1]), x0, method="DOP853", rtol=rtol, atol=rtol, t_eval=t_eval)
    if not sol.success:
        raise RuntimeError(sol.message)
    return sol.y[:9].T.reshape(-1, 3, 3), sol.y[9:].T
