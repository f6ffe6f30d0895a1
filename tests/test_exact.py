"""Tests of the exact free-rigid-body solution and of the elliptic functions.

References are independent: scipy.special (elliptic functions and Carlson
integrals), scipy.integrate.solve_ivp(DOP853) on the 9-dimensional attitude
equation ``dR/dt = R hat(I^{-1} R^T L)``, a Taylor-series integration in
34-digit decimal arithmetic (`taylor_reference`), and closed forms for
symmetric bodies.
"""

import functools
from decimal import Decimal, localcontext
from operator import mul

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import scipy.special as sp  # noqa: E402
from helpers import fd_jacobian  # noqa: E402
from scipy.integrate import quad, solve_ivp  # noqa: E402
from scipy.optimize import brentq  # noqa: E402

from lierk import _elliptic as E  # noqa: E402
from lierk import exact, so3  # noqa: E402

# Jitted once at module level: each compiles once per shape/dtype and is then
# reused by every test (the unjitted graph takes seconds per eager call).
frb = jax.jit(exact.free_rigid_body)
flip = jax.jit(exact.flip_interval)


def _flat(inertia, w, t):
    R, om = exact.free_rigid_body(inertia, w, t)
    return jnp.concatenate([R.ravel(), om])


jac_fwd = jax.jit(jax.jacfwd(_flat, argnums=1))
dR_dt = jax.jit(jax.jacfwd(lambda inertia, w, t: exact.free_rigid_body(inertia, w, t)[0], argnums=2))

T_HANDLE = np.diag([9.82271303e-05, 7.22671030e-05, 1.57865031e-04])  # kg m^2


def _rot(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _hat(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def reference(inertia, omega0, ts, R0=np.eye(3)):
    """DOP853 at scipy's tightest usable tolerance (rtol is clamped to 2.2e-14)."""
    inertia = np.asarray(inertia, float)
    Iinv = np.linalg.inv(inertia)
    L = R0 @ inertia @ omega0

    def f(t, y):
        R = y.reshape(3, 3)
        return (R @ _hat(Iinv @ (R.T @ L))).ravel()

    sol = solve_ivp(f, (0, ts[-1]), R0.ravel(), method="DOP853", rtol=2.3e-14, atol=1e-14, t_eval=ts)
    assert sol.success
    return sol.y.T.reshape(-1, 3, 3)


def period(inertia, omega0):
    """Period of the body momentum m(t), 4K(k)/|lambda| (s), from the exact
    solution's constants (flip_interval is half of it only on flipping orbits)."""
    c = exact._working_constants(*exact._validated(inertia, omega0)[:2])
    return 4.0 * sp.ellipkm1(float(c["k2c"])) / abs(float(c["lam"]))


# ------------------------------------------------------------------ elliptic


@pytest.mark.parametrize("m", [0.0, 1e-8, 0.3, 0.5, 0.9, 0.91, 0.99, 0.999999, 1 - 1e-9])
def test_ellipj_vs_scipy(m):
    u = np.concatenate([np.random.default_rng(0).uniform(-30, 30, 300), np.linspace(-5, 5, 101)])
    ref = sp.ellipj(u, m)
    got = [np.asarray(a) for a in E.ellipj(u, m)]
    for g, r in zip(got[:3], ref[:3]):
        assert np.abs(g - r).max() < 1e-13
    assert np.max(np.abs(got[3] - ref[3]) / (1 + np.abs(ref[3]))) < 1e-14


@pytest.mark.parametrize("m1", [1e-10, 1e-12, 3e-13, 1e-15])
def test_ellipj_near_one(m1):
    m = 1.0 - m1
    m1 = 1.0 - m  # exact: the complement scipy effectively sees
    K = sp.ellipk(m)
    # scipy's m > 1 - 1e-9 branch (A&S 16.15) is accurate only for |u| << K:
    # compare there directly, and on [K/2, K] through sn(u) = cd(K - u) etc.
    u = np.linspace(-K / 2, K / 2, 401)
    s, c, d, ph = sp.ellipj(u, m)
    S, C, D, PH = (np.asarray(a) for a in E.ellipj(u, m, m1))
    for g, r in ((S, s), (C, c), (D, d), (PH, ph)):
        assert np.abs(g - r).max() < 1e-13
    u = np.linspace(K / 2, K, 201)
    kp = np.sqrt(m1)
    s, c, d, _ = sp.ellipj(K - u, m)
    S, C, D, _ = (np.asarray(a) for a in E.ellipj(u, m, m1))
    assert np.abs(S - c / d).max() < 1e-13
    assert np.abs(C - kp * s / d).max() < 1e-13
    assert np.abs(D - kp / d).max() < 1e-13
    # Periodicity far out: sn(u + 4K) = sn(u), dn(u + 2K) = dn(u).
    u = np.linspace(-3, 3, 11)
    a = np.asarray(E.ellipj(u, m, m1)[0])
    b = np.asarray(E.ellipj(u + 4 * K, m, m1)[0])
    assert np.abs(a - b).max() < 1e-12


def test_ellipk_and_carlson():
    m = np.array([0.0, 1e-6, 0.2, 0.5, 0.8, 0.99, 1 - 1e-9, 1 - 1e-12, 1 - 1e-15])
    assert np.max(np.abs(np.asarray(E.ellipk(m)) / sp.ellipk(m) - 1)) < 1e-14
    rng = np.random.default_rng(1)
    x, y, z, p = rng.uniform(0, 3, (4, 200))
    x[:20] = 0.0
    y[20:40] = 1e-20
    p = p + 0.05
    for got, ref in (
        (E.elliprf(x, y, z), sp.elliprf(x, y, z)),
        (E.elliprj(x, y, z, p), sp.elliprj(x, y, z, p)),
        (E.elliprc(x, p), sp.elliprc(x, p)),
    ):
        assert np.max(np.abs(np.asarray(got) / ref - 1)) < 1e-13
    phi = rng.uniform(-10, 10, 100)
    for mm in (0.3, 0.95, 1 - 1e-12):
        assert np.abs(np.asarray(E.ellipf(phi, mm)) - sp.ellipkinc(phi, mm)).max() < 1e-13
    # Pi against adaptive quadrature of its integrand.
    phi = np.linspace(-4, 4, 9)
    for n, mm in ((-2.5, 0.7), (-0.3, 0.999), (0.4, 0.2)):

        def integrand(th):
            return 1 / ((1 - n * np.sin(th) ** 2) * np.sqrt(1 - mm * np.sin(th) ** 2))

        ref = [
            quad(
                integrand,
                0,
                p,
                points=[np.sign(p) * np.pi / 2] if abs(p) > 2 else None,
                epsabs=1e-15,
                epsrel=1e-15,
                limit=200,
            )[0]
            for p in phi
        ]
        assert np.abs(np.asarray(E.ellippi(n, phi, mm)) - ref).max() < 1e-13


# ------------------------------------------------------------------ regimes

CASES = {
    # name: (inertia, omega0, horizon in periods of m)
    "largest_axis": (np.diag([1.0, 2.0, 3.0]), np.array([0.3, 0.2, 1.0]), 100),
    "smallest_axis": (np.diag([1.0, 2.0, 3.0]), np.array([1.0, 0.2, 0.3]), 100),
    "largest_axis_negative": (np.diag([1.0, 2.0, 3.0]), np.array([-0.3, 0.5, -1.0]), 20),
    "smallest_axis_negative": (np.diag([1.0, 2.0, 3.0]), np.array([-1.0, -0.4, 0.3]), 20),
    # Separatrix of diag(1, 2, 3) at omega3 = omega1/sqrt(3): here k'^2 ~ 1e-7.
    "near_separatrix": (np.diag([1.0, 2.0, 3.0]), np.array([1.0, 0.1, (1 + 1e-7) / np.sqrt(3.0)]), 30),
    "non_diagonal": (_rot(3) @ np.diag([0.7, 1.9, 2.3]) @ _rot(3).T, np.array([0.3, -0.7, 0.5]), 100),
    "t_handle_a": (T_HANDLE, np.array([1.0, 0.05, 0.0]), 20),
}


@pytest.mark.parametrize("name", list(CASES))
def test_regimes_vs_dop853(name):
    inertia, omega0, n_periods = CASES[name]
    R0 = np.asarray(so3.exp(jnp.array([0.3, -1.1, 0.4])))
    ts = np.linspace(0.0, n_periods * period(inertia, omega0), 101)
    R, omega = frb(inertia, omega0, ts, R0)
    Rref = reference(inertia, omega0, ts, R0)
    err = np.abs(np.asarray(R) - Rref).max()
    # Measured (float64) at the horizon: 3e-12 .. 3.6e-11.  This is the
    # reference's error: DOP853 on the attitude equation and on Euler's
    # equations alone disagree with each other by up to 3e-11 at 100 periods,
    # while the exact solution is self-consistent to ~1e-13
    # (test_restart_consistency).  It moves with R0's last bits: R0 one ulp
    # apart (so3.exp as one program, or op by op) moved the reference by
    # 3.7e-11 on t_handle_a and the exact solution by 2e-16.
    # Near the separatrix the problem itself is ill-conditioned: the period
    # depends on 1/k'^2, and one ulp of omega0 moves R(t) by 1.1e-7 at this
    # horizon (|dR/domega0| |omega0| eps, from jacfwd).  The reference starts
    # from m0 = R0^T R0 I omega0, so R0's own last bits count as much: R0 from
    # so3.exp, from SciPy, or either made orthonormal by an SVD, gave 4e-7 to
    # 2.7e-6 here.  Allow ~40 ulps.
    assert err < (5e-6 if name == "near_separatrix" else 6e-11), err
    # omega(t) consistent with the attitude: m = R^T L.
    L = R0 @ inertia @ omega0
    m = np.einsum("tji,j->ti", np.asarray(R), L)
    assert np.abs(m - np.asarray(omega) @ inertia.T).max() < 1e-11 * np.linalg.norm(L)


def test_restart_consistency():
    # Flow property R(t1 + t2; R0, w0) = R(t2; R(t1), w(t1)): reference-free
    # check of the phase and precession angle over 100 periods.
    for name in ("largest_axis", "smallest_axis", "non_diagonal"):
        inertia, omega0, _ = CASES[name]
        ts = np.linspace(0.0, 100 * period(inertia, omega0), 101)
        R, om = (np.asarray(a) for a in frb(inertia, omega0, ts))
        R2, om2 = (np.asarray(a) for a in frb(inertia, om[50], ts - ts[50], R[50]))
        assert np.abs(R2[50:] - R[50:]).max() < 2e-12
        assert np.abs(om2[50:] - om[50:]).max() < 2e-12


def test_separatrix():
    # G^2 = 2 T I2 exactly in floating point: m = (6, 0.3, 6), I = (2, 3, 6).
    inertia, omega0 = np.diag([2.0, 3.0, 6.0]), np.array([3.0, 0.1, 1.0])
    assert not np.isfinite(float(flip(inertia, omega0)))
    # The reference departs from the (unstable) separatrix like eps e^{lambda t},
    # lambda = 1.4: keep lambda t <= 8.
    ts = np.linspace(0.0, 6.0, 101)
    R, omega = frb(inertia, omega0, ts)
    assert np.abs(np.asarray(R) - reference(inertia, omega0, ts)).max() < 1e-11
    # The body momentum tends to the intermediate axis.
    _, om = frb(inertia, omega0, jnp.array([0.0, 40.0]))
    m_end = np.asarray(om)[-1] * np.diag(inertia)
    assert abs(abs(m_end[1]) - np.linalg.norm(m_end)) < 1e-12 * np.linalg.norm(m_end)


# ------------------------------------------------------------ next to the saddle


def taylor_reference(moments, m0, ts, h, attitude=True, order=30, digits=34):
    """Body momentum ``m(t)`` ``(n, 3)`` and attitude ``R(t)`` ``(n, 3, 3)``
    (``R(0) = 1``; ``None`` unless ``attitude``) of a free body with
    principal moments ``moments``, at the increasing times ``ts``: Taylor
    series of ``order`` terms, steps of ``h``, in ``digits``-digit decimal
    arithmetic.

    ``m`` and the body-frame images ``R^T e_1``, ``R^T e_2`` of two space axes
    all obey ``v' = v x w``, ``w = m / moments``, whose Taylor coefficients
    follow from Cauchy products; ``R^T e_3`` is their cross product.  The
    series' radius is ``K'/|lambda| >= pi/(2 |lambda|)`` (the poles of the
    Jacobi functions); ``h`` a fifth of it leaves a truncation of ``5^-30 =
    1e-21`` per step.  Measured: a second integration (mpmath, 50 digits, 40
    terms, steps 3.3x shorter) agrees to the last bit of float64 on every
    case below."""
    with localcontext() as ctx:
        ctx.prec = digits
        inv = [1 / Decimal(float(i)) for i in moments]
        one, zero = Decimal(1), Decimal(0)
        state = [[Decimal(float(v)) for v in m0]] + ([[one, zero, zero], [zero, one, zero]] if attitude else [])
        step, t, todo, out = Decimal(float(h)), Decimal(0), [Decimal(float(s)) for s in ts], []
        while todo:
            series = [[[c] for c in v] for v in state]  # [vector][component][power]
            w = [[state[0][i] * inv[i]] for i in range(3)]
            for k in range(order):
                wr = [wi[::-1] for wi in w]
                for v in series:
                    c = [
                        sum(map(mul, v[(i + 1) % 3], wr[(i + 2) % 3])) - sum(map(mul, v[(i + 2) % 3], wr[(i + 1) % 3]))
                        for i in range(3)
                    ]
                    for i in range(3):
                        v[i].append(c[i] / (k + 1))
                for i in range(3):
                    w[i].append(series[0][i][-1] * inv[i])

            def at(dt):
                def horner(coeffs):
                    acc = zero
                    for c in reversed(coeffs):
                        acc = acc * dt + c
                    return acc

                return [[horner(cs) for cs in v] for v in series]

            def rows(vals):
                if not attitude:
                    return vals
                (a1, a2, a3), (b1, b2, b3) = vals[1], vals[2]
                return [vals[0], vals[1], vals[2], [a2 * b3 - a3 * b2, a3 * b1 - a1 * b3, a1 * b2 - a2 * b1]]

            while todo and todo[0] <= t + step:
                out.append(rows(at(todo.pop(0) - t)))
            state = at(step)
            t += step
    m = np.array([[float(c) for c in o[0]] for o in out])
    R = np.array([[[float(c) for c in o[i]] for i in (1, 2, 3)] for o in out]) if attitude else None
    return m, R  # (R's row i is R^T e_i)


# name: (principal moments, omega0 (rad/s), horizon (s), Taylor step (s)).
# The momentum starts 1e-9 off the intermediate axis, on either side of the
# separatrix, and the horizon takes it through the flip; 2^-30 is exact in
# float32 too.
NEAR_SADDLE = {
    "diag123_about_largest": ((1.0, 2.0, 3.0), (2.0**-30, 1.0, 2.0**-30), 40.0, 0.5),
    "diag123_about_smallest": ((1.0, 2.0, 3.0), (3 * 2.0**-30, 1.0, 2.0**-30), 40.0, 0.5),
    "t_handle_about_largest": (tuple(np.diag(T_HANDLE)), (1.0, 1e-9, 1e-9), 60.0, 0.8),
    "t_handle_about_smallest": (tuple(np.diag(T_HANDLE)), (1.0, 1e-8, 1e-9), 60.0, 0.8),
}


@functools.cache
def near_saddle_reference(name):
    moments, omega0, horizon, h = NEAR_SADDLE[name]
    ts = np.linspace(0.0, horizon, 101)
    return (ts, *taylor_reference(moments, np.multiply(moments, omega0), ts, h))


@pytest.mark.parametrize("name", list(NEAR_SADDLE))
def test_near_the_intermediate_axis_vs_taylor_reference(name):
    """Next to the intermediate axis the small momentum components grow like
    exp(|lambda| t) until the flip, and so does any error in their relative
    precision.  The initial phase, an elliptic integral of the amplitude
    whose cosine is x/A1 ~ 1e-9, used to go through the angle (atan2, then
    cos): 1e-7 relative error in that cosine, and m/|m| and R erred by 8e-9
    to 4e-8 at the flip.

    The flow is well conditioned here: relative changes eps of m0's entries
    and of the moments move m(t)/|m| by at most 95 eps and R(t) by 163 eps
    (kappa, from the variational equation).  Measured: m/|m| within 1.4e-14
    (at most 1.75 eps (1 + kappa(t)) at every time), R within 6.1e-14 (the
    phase u0 ~ K ~ 21 carries eps K into the precession angle).  SciPy's
    DOP853 at rtol 1e-13 errs by 5.6e-15 to 1.5e-14 in m/|m| and 5.4e-13 to
    6.4e-13 in R."""
    moments, omega0, horizon, _ = NEAR_SADDLE[name]
    ts, m_ref, R_ref = near_saddle_reference(name)
    inertia = np.diag(moments)
    G = np.linalg.norm(m_ref[0])
    lam = float(exact._working_constants(*exact._validated(moments, omega0)[:2])["lam"])
    assert ("smallest" in name) == (lam < 0)  # the relabelled regime, about the smallest axis
    # (R0 given and 101 times: the program of test_regimes_vs_dop853.)
    R, om = (np.asarray(a) for a in frb(inertia, np.asarray(omega0), ts, np.eye(3)))
    m_err = np.abs(om * moments - m_ref).max() / G
    R_err = np.abs(R - R_ref).max()
    assert m_err < 3e-14 and R_err < 1.5e-13, (m_err, R_err)


@pytest.mark.parametrize("name", list(NEAR_SADDLE))
def test_free_flow_from_next_to_the_intermediate_axis_vs_taylor_reference(name):
    """`free_flow` builds the momentum change from Jacobi's addition
    theorems, whose denominator D = 1 - k^2 sn^2 a sn^2 b is about
    dn^2(lambda h) next to the intermediate axis and falls like exp(-2
    |lambda| h).  Its factors cn b dn b - D etc. were formed from terms of
    size one (and from sn^2 a, which is 1 to rounding there), so the change
    erred by eps/D: up to 43 |m| over the times below.  Measured now:
    m(h) within 6.3e-15 |m|, Q within 6e-14 (the closed form's)."""
    moments = NEAR_SADDLE[name][0]
    ts, m_ref, R_ref = near_saddle_reference(name)
    G = np.linalg.norm(m_ref[0])
    for i in (25, 50, 75, 100):
        Q, m_h = (np.asarray(a) for a in exact.free_flow(np.diag(moments), m_ref[0], ts[i]))
        assert np.abs(m_h - m_ref[i]).max() < 2e-14 * G, (i, m_h - m_ref[i])
        assert np.abs(Q - R_ref[i]).max() < 1.5e-13


def test_nearly_symmetric_body_about_its_smallest_axis_vs_taylor_reference():
    """I = (1, 1 + 1e-9, 2.7) circulating about the smallest axis: the
    working frame's r = (I2 - I1)/(I3 - I1) = 5.9e-10 was 1 - (I3 - I2)/(I3
    - I1), which keeps only the rounding of the quotient (2e-7 relative),
    and m erred by 1e-8 |m| after 5 periods of 2.4e5 s.  Measured now: 2e-16.
    (The data are exact as floats; relative changes of I2 of eps would move
    m by 1e-8 too, but that is the data's precision, not the method's.)"""
    moments, omega0 = (1.0, 1.0 + 1e-9, 2.7), np.array([1.0, 0.5, 1e-6])
    assert float(exact._working_constants(*exact._validated(moments, omega0)[:2])["lam"]) < 0
    ts = np.linspace(0.0, 5 * period(np.diag(moments), omega0), 101)
    # Steps of a fifth of the series' radius pi/(2 |lambda|), lambda = -2.8e-5.
    m_ref, _ = taylor_reference(moments, np.multiply(moments, omega0), ts, 1.1e4, attitude=False)
    _, om = frb(np.diag(moments), omega0, ts, np.eye(3))
    G = np.linalg.norm(m_ref[0])
    assert np.abs(np.asarray(om) * moments - m_ref).max() < 4e-15 * G


def test_near_the_intermediate_axis_in_float32():
    """The same starts in float32 (data exact in float32), where the angle's
    rounding used to leave errors of 1.5 to 1.9 |m| at the flip, and
    `free_flow`'s 1.7 |m|.  Measured: m/|m| within 2.5e-6 and R within
    1.5e-5, eps_32 times the conditioning above; free_flow within 1.9e-6."""
    for name in ("diag123_about_largest", "diag123_about_smallest"):
        moments, omega0, _, _ = NEAR_SADDLE[name]
        ts, m_ref, R_ref = near_saddle_reference(name)
        f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
        # (Every other time, 51 of them: the program of test_float32.)
        R, om = frb(f32(np.diag(moments)), f32(omega0), f32(ts[::2]))
        assert R.dtype == jnp.float32
        G = np.linalg.norm(m_ref[0])
        assert np.abs(np.asarray(om, float) * moments - m_ref[::2]).max() < 1e-5 * G
        assert np.abs(np.asarray(R, float) - R_ref[::2]).max() < 5e-5
        _, m_h = exact.free_flow(f32(np.diag(moments)), f32(m_ref[0]), f32(ts[-1]))
        assert np.abs(np.asarray(m_h, float) - m_ref[-1]).max() < 1e-5 * G


# ------------------------------------------------------------------ closed forms


@pytest.mark.parametrize("axis, a, c", [(2, 1.0, 3.0), (0, 3.0, 1.0), (0, 1.0, 1e-6)])
def test_symmetric_bodies(axis, a, c):
    # Axisymmetric about e_axis with I_axis = c, others a (oblate: I1 = I2 < I3;
    # prolate: I1 < I2 = I3; a thin rod, c = 1e-6).  R(t) = exp(t hat(L)/a) R0
    # exp(t beta hat(e)), beta = (1/c - 1/a) m_axis.  The rod's precession angle,
    # taken from the general formula, was a difference of two terms of size
    # |L| t / c and erred by 1e-7 at t = 200 s.
    diag = np.full(3, a)
    diag[axis] = c
    inertia = np.diag(diag)
    omega0 = np.array([0.3, 0.2, 1.0])
    R0 = np.asarray(so3.exp(jnp.array([0.2, 0.5, -0.3])))
    e = np.eye(3)[axis]
    m = inertia @ omega0
    beta = (1 / c - 1 / a) * m[axis]
    ts = np.linspace(0.0, 200.0, 101)
    L = R0 @ m
    ref = np.asarray(so3.exp(ts[:, None] * L / a)) @ R0 @ np.asarray(so3.exp(ts[:, None] * beta * e))
    R, _ = frb(inertia, omega0, ts, R0)
    assert np.abs(np.asarray(R) - ref).max() < 1e-12


def test_sphere_and_permanent_rotations():
    ts = np.linspace(0.0, 100.0, 101)
    R0 = np.asarray(so3.exp(jnp.array([0.2, 0.5, -0.3])))
    w = np.array([0.3, -0.2, 1.0])
    Rs, ws = exact.sphere(w, ts, R0)
    ref = R0 @ np.asarray(so3.exp(ts[:, None] * w))
    assert np.abs(np.asarray(Rs) - ref).max() < 1e-13
    R, om = frb(2.5 * np.eye(3), w, ts, R0)
    assert np.abs(np.asarray(R) - ref).max() < 1e-12
    assert np.abs(np.asarray(om) - w).max() < 1e-14
    inertia = np.diag([1.0, 2.0, 3.0])
    for w in (np.array([0.0, 0.0, -1.3]), np.array([0.7, 0.0, 0.0]), np.array([0.0, 1.1, 0.0]), np.zeros(3)):
        R, om = frb(inertia, w, ts, R0)
        assert np.abs(np.asarray(R) - R0 @ np.asarray(so3.exp(ts[:, None] * w))).max() < 1e-12
        assert np.abs(np.asarray(om) - w).max() < 1e-14


def test_non_diagonal_equals_rotated_diagonal():
    # Body frame b' = Q b: inertia' = Q D Q^T, omega' = Q omega, R' = R Q^T.
    # Includes an eigh basis that comes out as a reflection.
    D = np.diag([1.3, 0.4, 2.2])
    R0 = np.asarray(so3.exp(jnp.array([0.1, 0.2, 0.3])))
    ts = np.linspace(0.0, 50.0, 101)
    w = np.array([0.4, 1.0, -0.3])
    R, om = frb(D, w, ts, R0)
    for seed in range(3):
        Q = _rot(seed)
        Rq, omq = frb(Q @ D @ Q.T, Q @ w, ts, R0 @ Q.T)
        assert np.abs(np.asarray(Rq) - np.asarray(R) @ Q.T).max() < 1e-11
        assert np.abs(np.asarray(omq) - np.asarray(om) @ Q.T).max() < 1e-11


# ------------------------------------------------------------------ transformations


def test_jit_vmap_equals_loop():
    inertia = np.diag([1.0, 2.0, 3.0])
    omegas = np.array([[0.3, 0.2, 1.0], [1.0, 0.2, 0.3], [-0.2, 1.0, 0.4], [0.0, 0.0, 1.0], [1.0, 0.1, np.sqrt(0.5)]])
    ts = np.linspace(0.0, 30.0, 7)
    Rb, wb = jax.jit(jax.vmap(exact.free_rigid_body, in_axes=(None, 0, None)))(inertia, omegas, ts)
    assert Rb.shape == (5, 7, 3, 3) and wb.shape == (5, 7, 3)
    for i, w in enumerate(omegas):
        R, om = frb(inertia, w, ts)
        assert np.abs(np.asarray(Rb[i]) - np.asarray(R)).max() < 1e-13
        assert np.abs(np.asarray(wb[i]) - np.asarray(om)).max() < 1e-13
    # vmap over times equals the array-t call.
    Rt, _ = jax.jit(jax.vmap(frb, in_axes=(None, None, 0)))(inertia, omegas[0], ts)
    assert np.abs(np.asarray(Rt) - np.asarray(frb(inertia, omegas[0], ts)[0])).max() < 1e-13
    # Scalar t gives unbatched shapes.
    R, om = frb(inertia, omegas[0], 1.0)
    assert R.shape == (3, 3) and om.shape == (3,)


# t_handle_a: m0 has no component along the working e1 (cn u0 = 0 exactly),
# where Carlson's forms give the phase's derivative in the amplitude as 0 * inf.
@pytest.mark.parametrize("name", ["largest_axis", "smallest_axis", "non_diagonal", "oblate", "t_handle_a"])
def test_derivatives(name):
    if name == "oblate":
        inertia, omega0 = np.diag([1.0, 1.0, 3.0]), np.array([0.3, 0.2, 1.0])
    else:
        inertia, omega0, _ = CASES[name]
    t = 7.3
    f = lambda w: np.asarray(_flat(inertia, w, t))  # noqa: E731
    J = np.asarray(jac_fwd(inertia, jnp.asarray(omega0), t))
    h = 1e-5
    Jfd = np.stack([(f(omega0 + h * e) - f(omega0 - h * e)) / (2 * h) for e in np.eye(3)], -1)
    assert np.isfinite(J).all()
    assert np.abs(J - Jfd).max() < 1e-7 * (1 + np.abs(J).max())

    # d/dt R = R hat(omega), also by central differences.
    dR = np.asarray(dR_dt(inertia, omega0, t))
    R, om = frb(inertia, omega0, t)
    assert np.abs(dR - np.asarray(R @ so3.hat(om))).max() < 1e-13
    fd = (np.asarray(frb(inertia, omega0, t + 1e-5)[0]) - np.asarray(frb(inertia, omega0, t - 1e-5)[0])) / 2e-5
    assert np.abs(fd - dR).max() < 1e-8


jac_rev = jax.jit(jax.jacrev(_flat, argnums=1))


flat = jax.jit(_flat)
DIAG123 = np.diag([1.0, 2.0, 3.0])
_Q_ROT = _rot(5)
# Steady states, where the closed form's own variables (phase of m about the
# axis, its amplitude, the modulus k) are singular although the flow is smooth.
STEADY = {
    "rest": (DIAG123, [0.0, 0.0, 0.0]),
    "slow_spin_axis0": (DIAG123, [1e-3, 0.0, 0.0]),
    "axis0": (DIAG123, [1.0, 0.0, 0.0]),
    "axis1_intermediate": (DIAG123, [0.0, 1.0, 0.0]),
    "axis2": (DIAG123, [0.0, 0.0, 1.0]),
    "symmetric_about_its_axis": (np.diag([1.0, 1.0, 2.0]), [0.0, 0.0, 1.0]),
    "symmetric_transverse": (np.diag([1.0, 1.0, 2.0]), [1.0, 0.0, 0.0]),
    "symmetric_transverse_oblique": (np.diag([1.0, 1.0, 2.0]), [0.6, 0.8, 0.0]),
    "sphere": (np.diag([2.0, 2.0, 2.0]), [0.3, -1.0, 2.0]),
    "sphere_at_rest": (np.diag([2.0, 2.0, 2.0]), [0.0, 0.0, 0.0]),
    # A rotated inertia: rounding puts omega0 = Q e_i ~1e-16 off the axis.
    "rotated_axis0": (_Q_ROT @ DIAG123 @ _Q_ROT.T, _Q_ROT[:, 0]),
    "rotated_axis1": (_Q_ROT @ DIAG123 @ _Q_ROT.T, _Q_ROT[:, 1]),
    "rotated_at_rest": (_Q_ROT @ DIAG123 @ _Q_ROT.T, [0.0, 0.0, 0.0]),
    # Exactly on the separatrix (d = 0 in floating point): diag(4, 6.5, 9)
    # has r = 1/2 and m = (12, ., 18) gives m3^2 r/I3 = m1^2 (1 - r)/I1 = 18.
    "separatrix": (np.diag([4.0, 6.5, 9.0]), [3.0, 0.5, 2.0]),
    "separatrix_through_axis1": (np.diag([4.0, 6.5, 9.0]), [3.0, 0.0, 2.0]),
}


@pytest.mark.parametrize("name", list(STEADY))
def test_jacobian_at_rest_steady_spin_and_separatrix(name):
    """d(R(t), omega(t))/d omega0 by jacfwd and jacrev against finite
    differences.  Before the fix: rest J = 0 (should be ~t), axis0 off by
    3.2, slow spin |J| = 3000, the separatrix off by 1."""
    inertia, w = STEADY[name]
    w = np.asarray(w, float)
    t = 2.0
    ref = fd_jacobian(lambda v: flat(inertia, v, t), w)
    scale = np.abs(ref).max()
    for jac in (jac_fwd, jac_rev):
        J = np.asarray(jac(inertia, jnp.asarray(w), t))
        assert np.isfinite(J).all()
        assert np.abs(J - ref).max() < 1e-7 * scale, (jac, np.abs(J - ref).max(), scale)
    if name in ("rest", "sphere_at_rest", "rotated_at_rest"):
        # At rest R(t) = exp(t hat(omega0)) to first order: dR/d omega0_k = t hat(e_k).
        J = np.asarray(jac_fwd(inertia, jnp.asarray(w), t))[:9].reshape(3, 3, 3)
        for k in range(3):
            np.testing.assert_allclose(J[..., k], t * _hat(np.eye(3)[k]), atol=1e-13)


def _flat_at_times(w, ts, R0):
    R, om = exact.free_rigid_body(DIAG123, w, ts, R0)
    return jnp.concatenate([R.reshape(-1), om.reshape(-1)])


_flat_at_times_jit = jax.jit(_flat_at_times)
# One program for the three derivatives (each Jacobian of the closed form
# takes ~10 s to compile); jacrev is tested on the same states above.
_at_times_jac = jax.jit(jax.jacfwd(_flat_at_times, argnums=(0, 1, 2)))


def test_jacobian_at_steady_spin_with_times_and_attitude():
    """Several times at once, a general R0, and the derivatives in t and R0
    at a steady spin about the intermediate axis and at rest."""
    R0 = np.asarray(so3.exp(jnp.array([0.3, -0.5, 0.2])))
    ts = np.array([0.0, 0.7, 2.0])
    for w in ([0.0, 1.0, 0.0], [0.0, 0.0, 0.0]):
        w = np.asarray(w, float)
        ref = fd_jacobian(lambda v: _flat_at_times_jit(v, ts, R0), w)
        J, dt, dR0 = (np.asarray(a) for a in _at_times_jac(w, ts, R0))
        assert np.abs(J - ref).max() < 1e-7 * np.abs(ref).max()
        # d/dt: R hat(omega), and omega constant.
        R, om = (np.asarray(a) for a in exact.free_rigid_body(DIAG123, w, ts, R0))
        for i in range(len(ts)):
            np.testing.assert_allclose(dt[:27].reshape(3, 3, 3, 3)[i, :, :, i], R[i] @ _hat(om[i]), atol=1e-13)
        # d/dR0 is R0 -> R0 exp(t hat(omega0)), linear: at t = 2 (the last time).
        g = dR0[:27].reshape(3, 3, 3, 3, 3)[2]
        E = np.asarray(so3.exp(2.0 * jnp.asarray(w)))
        np.testing.assert_allclose(g, np.einsum("ac,db->abcd", np.eye(3), E), atol=1e-12)


def test_jacobian_in_float32_at_rest_steady_spin_and_separatrix():
    """float32: finite, and right to float32's accuracy (measured worst 5e-7
    of the Jacobian's size, on the separatrix)."""
    for name in ("rest", "slow_spin_axis0", "axis1_intermediate", "symmetric_about_its_axis", "sphere", "separatrix"):
        inertia, w = STEADY[name]
        w = np.asarray(w, float)
        ref = fd_jacobian(lambda v: flat(inertia, v, 2.0), w)
        for jac in (jac_fwd, jac_rev):
            J = jac(jnp.asarray(inertia, jnp.float32), jnp.asarray(w, jnp.float32), jnp.float32(2.0))
            assert J.dtype == jnp.float32
            J = np.asarray(J)
            assert np.isfinite(J).all()
            assert np.abs(J - ref).max() < 1e-5 * np.abs(ref).max(), (name, np.abs(J - ref).max())


_U = np.array([0.0, 0.3, 1.15, 3.0, -2.0])


def _sncndn_of_m1(m1):
    return jnp.stack(E.ellipj(_U, 1.0 - m1, m1)[:3])


_sncndn_jacfwd = jax.jit(jax.jacfwd(_sncndn_of_m1))
_sncndn_jacrev = jax.jit(jax.jacrev(_sncndn_of_m1))


@pytest.mark.parametrize("m1", [0.0, 1e-300, 4e-16, 1e-12, 1e-6, 1e-2])
def test_ellipj_derivative_in_m_near_one(m1):
    """d(sn, cn, dn)/dm at fixed u next to m = 1: smooth (A&S 16.15 gives the
    limit), not the rounding/m1 of a derivative through K(m) ~ log(1/m1)."""
    u = _U
    d = np.asarray(_sncndn_jacfwd(m1))
    dr = np.asarray(_sncndn_jacrev(m1))
    if m1 < 1e-10:
        th, sh = np.tanh(u), 1.0 / np.cosh(u)
        ref = 0.25 * np.stack([th - u * sh * sh, -th * (np.sinh(u) - u * sh), th * (np.sinh(u) + u * sh)])
        tol = 1e-12 + 10 * m1 * np.exp(2 * np.abs(u)).max()
    else:
        # Fourth-order differences with h = m1/100: truncation ~(h/m1)^4
        # (the functions vary on the scale m1), rounding ~1e-16/h.
        h = 1e-2 * m1
        v = [np.stack(sp.ellipj(u, 1 - (m1 + k * h))[:3]) for k in (2, 1, -1, -2)]
        ref = (-v[0] + 8 * v[1] - 8 * v[2] + v[3]) / (12 * h)
        tol = 1e-7
    assert np.abs(d - ref).max() < tol
    assert np.abs(dr - d).max() < 1e-13


def test_ellipj_derivative_in_m_at_zero():
    """At m = 0 (a symmetric body's k) the Landen recursion's derivative in m
    was zero: sqrt(m)^2 went through a sqrt with a zero derivative at 0.
    A&S 16.13.1: sn = sin u - m/4 (u - sin u cos u) cos u + O(m^2)."""
    u = np.linspace(-3.0, 3.0, 13)
    d = np.asarray(jax.jit(jax.jacfwd(lambda m: E.ellipj(u, m)[0]))(0.0))
    np.testing.assert_allclose(d, -0.25 * (u - np.sin(u) * np.cos(u)) * np.cos(u), atol=1e-14)


def test_invariants():
    inertia, omega0, _ = CASES["non_diagonal"]
    ts = np.linspace(0.0, 100 * period(inertia, omega0), 101)
    R0 = np.asarray(so3.exp(jnp.array([0.3, -1.1, 0.4])))
    R, om = frb(inertia, omega0, ts, R0)
    R, om = np.asarray(R), np.asarray(om)
    m = om @ inertia
    E0, G0 = omega0 @ inertia @ omega0, np.linalg.norm(inertia @ omega0)
    assert np.abs(np.einsum("ti,ti->t", m, om) / E0 - 1).max() < 1e-13
    assert np.abs(np.linalg.norm(m, axis=-1) / G0 - 1).max() < 1e-13
    L = np.einsum("tij,tj->ti", R, m)
    assert np.abs(L - R0 @ inertia @ omega0).max() < 1e-13 * G0
    assert np.asarray(so3.orthogonality_error(R)).max() < 1e-14


def test_flip_interval_t_handle():
    w0 = np.array([1.0, 0.05, 0.0])
    tau = float(flip(T_HANDLE, w0))
    Idiag = np.diag(T_HANDLE)

    def euler(t, w):
        m = Idiag * w
        return np.cross(m, w) / Idiag

    sol = solve_ivp(euler, (0, 130.0), w0, method="DOP853", rtol=1e-13, atol=1e-15, dense_output=True)
    grid = np.linspace(0, 130.0, 20001)
    wx = sol.sol(grid)[0]
    idx = np.nonzero(np.sign(wx[:-1]) != np.sign(wx[1:]))[0]
    zeros = np.array([brentq(lambda s: sol.sol(s)[0], grid[i], grid[i + 1], xtol=1e-14) for i in idx])
    assert len(zeros) >= 4
    gaps = np.diff(zeros)
    assert np.abs(gaps / tau - 1).max() < 1e-9, (tau, gaps)
    assert abs(tau - 23.6307252) < 1e-6


def test_float32():
    # float32 inputs give float32 outputs; measured error vs float64 about
    # 2e-6 after one period and 1e-4 after 10 (phase error eps_32 * lambda t).
    x64 = jnp.array(1.0).dtype == jnp.float64
    assert x64
    for name in ("largest_axis", "smallest_axis", "t_handle_a"):
        inertia, omega0, _ = CASES[name]
        ts = np.linspace(0.0, 10 * period(inertia, omega0), 51)
        R32, w32 = frb(
            jnp.asarray(inertia, jnp.float32), jnp.asarray(omega0, jnp.float32), jnp.asarray(ts, jnp.float32)
        )
        assert R32.dtype == jnp.float32 and w32.dtype == jnp.float32
        assert np.isfinite(np.asarray(R32)).all() and np.isfinite(np.asarray(w32)).all()
        R64, w64 = frb(inertia, omega0, ts)
        assert np.abs(np.asarray(R32) - np.asarray(R64)).max() < 2e-4
        assert np.abs(np.asarray(w32) - np.asarray(w64)).max() < 2e-4 * np.abs(omega0).max()


# ------------------------------------------------------------------ validation


DIAG = np.diag([1.0, 2.0, 3.0])
BAD_INPUTS = [
    # (inertia, omega0, R0, message)
    (DIAG, [np.nan, 0.2, 1.0], None, "omega0 has NaN or inf entries"),
    (DIAG, [np.inf, 0.2, 1.0], None, "omega0 has NaN or inf entries"),
    (DIAG, [0.3, 1.0], None, r"omega0 must have shape \(3,\)"),
    (np.diag([1.0, -2.0, 3.0]), [0.3, 0.2, 1.0], None, "inertia must be positive definite"),
    (np.diag([1.0, 0.0, 3.0]), [0.3, 0.2, 1.0], None, "inertia must be positive definite"),
    ([1.0, np.nan, 3.0], [0.3, 0.2, 1.0], None, "inertia has NaN or inf entries"),
    (np.array([[1.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]]), [0.3, 0.2, 1.0], None, "inertia must be symmetric"),
    (np.ones((2, 2)), [0.3, 0.2, 1.0], None, r"inertia must have shape \(3, 3\) or \(3,\)"),
    (DIAG, [0.3, 0.2, 1.0], np.diag([1.0, 1.0, -1.0]), "R0 must be a rotation matrix"),
    (DIAG, [0.3, 0.2, 1.0], 2.0 * np.eye(3), "R0 must be a rotation matrix"),
    (DIAG, [0.3, 0.2, 1.0], np.full((3, 3), np.nan), "R0 has NaN or inf entries"),
    (DIAG, [0.3, 0.2, 1.0], np.eye(2), r"R0 must have shape \(3, 3\)"),
]


@pytest.mark.parametrize("inertia, omega0, R0, match", BAD_INPUTS)
def test_bad_inputs_raise_naming_the_value(inertia, omega0, R0, match):
    # These used to return NaN attitudes, accept R0 off SO(3), or raise IndexError.
    with pytest.raises(ValueError, match=match):
        exact.free_rigid_body(inertia, omega0, 1.0, R0)
    if R0 is None:
        with pytest.raises(ValueError, match=match):
            exact.flip_interval(inertia, omega0)


def test_traced_bad_inputs_raise_at_run_time():
    # Under jit the checks must survive: their results feed the computation.
    with pytest.raises(Exception, match="omega0 has NaN or inf entries"):
        jax.block_until_ready(frb(DIAG, jnp.array([jnp.nan, 0.2, 1.0]), 1.0))
    with pytest.raises(Exception, match="inertia must be positive definite"):
        jax.block_until_ready(frb(np.diag([1.0, -2.0, 3.0]), jnp.array([0.3, 0.2, 1.0]), 1.0))
    with pytest.raises(Exception, match="R0 must be a rotation matrix"):
        jax.block_until_ready(frb(DIAG, jnp.array([0.3, 0.2, 1.0]), 1.0, np.diag([1.0, 1.0, -1.0])))
    with pytest.raises(Exception, match="omega0 has NaN or inf entries"):
        jax.block_until_ready(flip(DIAG, jnp.array([0.3, jnp.nan, 1.0])))
    # One bad member of a vmapped batch is caught too.
    batch = jnp.array([[0.3, 0.2, 1.0], [jnp.nan, 0.0, 0.0]])
    with pytest.raises(Exception, match="omega0 has NaN or inf entries"):
        jax.block_until_ready(jax.jit(jax.vmap(exact.flip_interval, in_axes=(None, 0)))(DIAG, batch))
    # Good inputs through the same compiled functions are unaffected.
    assert np.isfinite(np.asarray(frb(DIAG, jnp.array([0.3, 0.2, 1.0]), 1.0)[0])).all()


def test_principal_moments_are_accepted():
    # A (3,) inertia, as lierk.FreeRigidBody accepts, used to raise IndexError.
    w = np.array([0.4, 1.0, -0.3])
    R, om = exact.free_rigid_body(np.array([1.3, 0.9, 2.0]), w, 2.0)
    Rd, omd = frb(np.diag([1.3, 0.9, 2.0]), w, 2.0)
    np.testing.assert_allclose(R, Rd, rtol=0, atol=1e-13)
    np.testing.assert_allclose(om, omd, rtol=0, atol=1e-13)
    assert float(exact.flip_interval([1.3, 0.9, 2.0], w)) == float(flip(np.diag([1.3, 0.9, 2.0]), w))


# ------------------------------------------------------------------ what a flip is


def _box():
    return np.asarray(__import__("lierk").inertia.box(1.0, 1.0, 2.0, 3.0))


FLIP_CASES = {
    # name: (inertia, omega0, flips?)
    "tee_a_intermediate": (T_HANDLE, [1.0, 0.05, 0.0], True),
    "tee_b_smallest": (T_HANDLE, [0.0, 1.0, 0.05], False),
    "tee_c_largest": (T_HANDLE, [0.05, 0.0, 1.0], False),
    # diag(1, 2, 3): m = (0, a, b) circulates about e3 and starts at the peak
    # of |m2|, so it flips iff |m2| > |m3| there; likewise about e1.
    "about_e3_just_flips": (DIAG, [0.0, 1.02 / 2, 1.0 / 3], True),
    "about_e3_just_does_not": (DIAG, [0.0, 1.0 / 2, 1.02 / 3], False),
    "about_e1_just_flips": (DIAG, [1.0, 1.02 / 2, 0.0], True),
    "about_e1_just_does_not": (DIAG, [1.02, 1.0 / 2, 0.0], False),
    "non_diagonal": (_rot(3) @ np.diag([0.7, 1.9, 2.3]) @ _rot(3).T, [0.3, -0.7, 0.5], None),
    "box_steady_largest": (_box(), [1.0, 0.0, 0.0], False),
    "box_steady_intermediate": (_box(), [0.0, 1.0, 0.0], False),
    "box_steady_smallest": (_box(), [0.0, 0.0, 1.0], False),
}


def _closest_axis_reversals(inertia, omega0, horizon):
    """Integrate Euler's equations (SciPy) in the principal frame; return the
    times of the sign changes of m2 and the number of reversals of the
    intermediate axis as the signed principal axis closest to L."""
    I, V = np.linalg.eigh(inertia)
    m0 = V.T @ inertia @ np.asarray(omega0, float)

    def euler(t, m):
        return np.cross(m, m / I)

    sol = solve_ivp(
        euler, (0, horizon), m0, method="DOP853", rtol=1e-12, atol=1e-14 * np.linalg.norm(m0), dense_output=True
    )
    grid = np.linspace(0, horizon, 40001)
    m = sol.sol(grid)
    closest = np.argmax(np.abs(m), axis=0)
    s2 = np.sign(m[1][closest == 1])
    reversals = int(np.count_nonzero(s2[1:] != s2[:-1]))
    idx = np.nonzero(np.sign(m[1][:-1]) * np.sign(m[1][1:]) < 0)[0]
    zeros = np.array([brentq(lambda s: sol.sol(s)[1], grid[i], grid[i + 1], xtol=1e-13) for i in idx])
    return zeros, reversals


@pytest.mark.parametrize("name", list(FLIP_CASES))
def test_flip_interval_matches_the_closest_axis_of_a_numerical_solution(name):
    inertia, omega0, expected = FLIP_CASES[name]
    tau = float(flip(inertia, np.asarray(omega0)))
    if expected is not None:
        assert np.isfinite(tau) == expected, tau
    # Three periods of m(t) (10 s for permanent rotations).
    T = period(inertia, omega0)
    horizon = 3 * T if np.isfinite(T) and T > 0 else 10.0
    zeros, reversals = _closest_axis_reversals(inertia, omega0, horizon)
    if np.isfinite(tau):
        # Six half-periods: a reversal in each (the first may fall before t = 0).
        assert reversals in (5, 6), reversals
        # ... and m2 changes sign once per flip interval.
        assert len(zeros) >= 5
        assert np.abs(np.diff(zeros) / tau - 1).max() < 1e-8
    else:
        assert reversals == 0


def test_no_flip_for_symmetric_bodies_spheres_and_rest():
    for inertia, omega0 in [
        (np.diag([1.0, 1.0, 3.0]), [0.3, 0.2, 1.0]),  # oblate: m1, m2 rotate, no distinct e2
        (np.diag([1.0, 3.0, 3.0]), [1.0, 0.9, 0.3]),  # prolate
        (2.5 * np.eye(3), [0.3, -0.2, 1.0]),  # sphere
        (DIAG, [0.0, 0.0, 0.0]),  # at rest
    ]:
        assert float(flip(inertia, np.asarray(omega0))) == np.inf, (inertia, omega0)


def test_flip_interval_vmaps_and_differentiates():
    omegas = jnp.array([FLIP_CASES[n][1] for n in ("about_e3_just_flips", "about_e3_just_does_not")])
    taus = jax.jit(jax.vmap(exact.flip_interval, in_axes=(None, 0)))(DIAG, omegas)
    assert np.isfinite(taus[0]) and taus[0] == float(flip(DIAG, omegas[0])) and taus[1] == np.inf
    # d tau / d omega0 by central differences.
    w = np.array([1.0, 0.05, 0.0])
    g = np.asarray(jax.jit(jax.grad(exact.flip_interval, argnums=1))(T_HANDLE, w))
    h = 1e-6
    fd = [(float(flip(T_HANDLE, w + h * e)) - float(flip(T_HANDLE, w - h * e))) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())
