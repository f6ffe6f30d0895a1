"""Jacobi elliptic functions and elliptic integrals in pure JAX.

JAX ships none of these, and the exact free-rigid-body solution
(:mod:`lierk.exact`) needs ``sn, cn, dn``, ``K`` and the incomplete integrals of
the first and third kinds.  Everything here:

- takes the parameter ``m = k^2`` and, optionally, its complement ``m1 = 1 - m``
  computed by the caller without cancellation (near the separatrix of the rigid
  body ``m1`` is a small physical quantity; forming ``1 - m`` would throw away
  its leading digits);
- runs a *fixed* number of iterations (static, so it jits, vmaps and
  differentiates), chosen so float64 is converged to rounding for every
  ``m1 >= 1e-300``;
- broadcasts over arguments and works in float32 and float64;
- is one compiled program per call (`jax.jit`), so that a call outside
  ``jit`` does not compile each of its operations on its own.

Algorithms:

- ``K(m) = pi / (2 AGM(1, sqrt(m1)))`` (arithmetic-geometric mean).
- ``sn, cn, dn`` for ``m <= 0.9``: descending Landen / AGM recursion of
  Abramowitz & Stegun 16.4 on the argument reduced to ``[-K, K]``.
- ``sn, cn, dn`` for ``m > 0.9``: the rapidly convergent "sech series" of the
  complementary nome (Jacobi's imaginary transformation applied to the Fourier
  series),
  ``dn(u) = pi/(2K') sum_n sech(pi (u - 2nK) / (2K'))``,
  ``cn(u) = pi/(2kK') sum_n (-1)^n sech(pi (u - 2nK) / (2K'))``,
  and ``sn(u) = pi/(2kK') [tanh(pi u/(2K')) + 4 sum_{n>=1} (-1)^n q'^(2n)
  sinh(n pi u/K') / (1 + q'^(2n))]``, ``q' = exp(-pi K/K')``, whose derivative
  in ``m`` stays accurate as ``m -> 1``.  Near ``m = 1`` the A&S recursion
  loses digits (its first step evaluates ``asin`` next to 1); the series does not,
  and at ``m1 = 0`` it reduces to ``sech``/``tanh``.  ``m1 == 0`` exactly is
  returned in closed form.
- ``R_F``, ``R_J``, ``R_C``: Carlson's duplication algorithm.

References:
    Abramowitz & Stegun, "Handbook of Mathematical Functions", 16.4, 16.9, 17.6.
    NIST DLMF, chapters 19 (sections 19.25, 19.36) and 22 (22.6, 22.11, 22.12).
    B. C. Carlson, "Numerical computation of real or complex elliptic
    integrals", Numer. Algorithms 10 (1995) 13-26.
    Press et al., "Numerical Recipes", 3rd ed., section 6.12.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import Array, lax
from jax.typing import ArrayLike

__all__ = ["ellipk", "ellipj", "ellipf", "ellippi", "elliprf", "elliprj", "elliprc"]

# Static iteration counts.  AGM(1, b) needs ~log2(ln(1/b)) "slow" steps before
# quadratic convergence sets in: 20 covers b = sqrt(m1) down to 1e-150.
_AGM_STEPS = 20
# Landen recursion for m <= 0.9: c_n/a_n goes 0.52 -> 0.07 -> 1e-3 -> 4e-7 ->
# 4e-14 -> 4e-28, so 7 steps are exact in float64.
_LANDEN_STEPS = 7
_M_SWITCH = 0.9
# Series terms for m > 0.9: terms decay like exp(-pi K/K' (2|n| - 1)/2) and
# K/K' >= 1.6 there, so |n| <= 9 reaches 1e-19.
_SERIES_TERMS = 9
# Carlson duplication: each step shrinks the spread of the arguments by 4 once
# they are comparable, after ~log2(ln(max/min)) steps to get them comparable;
# the 5th/7th-order remainder series then needs spread < 1e-3.
_CARLSON_STEPS = 24


def _float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _params(m: ArrayLike, m1: ArrayLike | None) -> tuple[Array, Array]:
    m = _float(m)
    m1 = 1.0 - m if m1 is None else jnp.asarray(m1, dtype=m.dtype)
    return m, m1


def _safe_sqrt(x: Array) -> Array:
    # sqrt with a finite (zero) derivative at 0, so that a branch evaluated at a
    # dummy-free degenerate point does not poison gradients with inf * 0.
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _sech(x: Array) -> Array:
    # 1/cosh(x) overflows (and its derivative is inf/inf) for |x| > 710.
    e = jnp.exp(-jnp.abs(x))
    return 2.0 * e / (1.0 + e * e)


def _agm(a: Array, b: Array, steps: int = _AGM_STEPS) -> Array:
    # lax.fori_loop with static bounds (a scan): keeps the traced graph small
    # while staying reverse-differentiable.
    def body(_, ab):
        a, b = ab
        return 0.5 * (a + b), jnp.sqrt(a * b)

    a, b = lax.fori_loop(0, steps, body, (a, b))
    return 0.5 * (a + b)


@jax.jit
def ellipk(m: ArrayLike, m1: ArrayLike | None = None) -> Array:
    """Complete elliptic integral of the first kind ``K(m)``.

    Args:
        m: parameter ``m = k^2`` in ``[0, 1)``, any shape.
        m1: optional complementary parameter ``1 - m``, passed separately when
            the caller knows it more accurately than ``1 - m``.

    Returns:
        ``K(m) = int_0^{pi/2} dtheta / sqrt(1 - m sin^2 theta)``, same shape.
        ``+inf`` at ``m1 = 0``.

    References:
        A&S 17.6; DLMF 19.8.5.
    """
    m, m1 = _params(m, m1)
    pos = m1 > 0
    agm = _agm(jnp.ones_like(m1), jnp.sqrt(jnp.where(pos, m1, 1.0)))
    return jnp.where(pos, (0.5 * math.pi) / agm, jnp.inf)


def _reduce(u: Array, K: Array) -> tuple[Array, Array]:
    # u = u_r + 2 j K with u_r in [-K, K]; there sn has the sign of u_r, cn >= 0
    # and am(u) = am(u_r) + j pi.
    j = jnp.round(u / (2.0 * K))
    return u - 2.0 * j * K, j


def _landen(u: Array, m: Array, m1: Array) -> tuple[Array, Array, Array]:
    """A&S 16.4 for moderate m: ``(sn, cn, dn)``; accurate for ``m <= 0.9``."""

    # Two scans, not Python loops: each step's arithmetic is compiled once
    # rather than seven times (the drift of every splitting holds it, and
    # its derivative programs were the largest the suite compiles).
    def descend(carry, _):
        a, b, c2 = carry
        a_new = 0.5 * (a + b)
        # c_{n+1} = (a_n - b_n)/2 = c_n^2 / (4 a_{n+1}) without the cancellation.
        c = c2 / (4.0 * a_new)
        return (a_new, jnp.sqrt(a * b), c * c), c / a_new

    # c_0^2 = m itself, not sqrt(m)^2, so the derivative in m is right at m = 0.
    (a, _, _), ratios = lax.scan(descend, (jnp.ones_like(m), jnp.sqrt(m1), m), None, length=_LANDEN_STEPS)

    def ascend(phi, r):
        return 0.5 * (phi + jnp.arcsin(r * jnp.sin(phi))), None

    phi0, _ = lax.scan(ascend, (2.0**_LANDEN_STEPS) * a * u, ratios, reverse=True)
    sn, cn = jnp.sin(phi0), jnp.cos(phi0)
    # dn^2 = m1 + m cn^2 has no cancellation (both terms >= 0).
    dn = jnp.sqrt(m1 + m * cn * cn)
    return sn, cn, dn


def _series(u: Array, m: Array, m1: Array, K: Array) -> tuple[Array, Array, Array]:
    """Sech series of the complementary nome: ``(sn, cn, dn)`` for ``m > 0.9``
    and ``u`` in ``[-K, K]``."""
    Kp = (0.5 * math.pi) / _agm(jnp.ones_like(m), jnp.sqrt(m))
    k = jnp.sqrt(m)  # m > 0.9 here
    scale = (0.5 * math.pi) / Kp

    n = jnp.arange(-_SERIES_TERMS, _SERIES_TERMS + 1, dtype=u.dtype)
    alt = 1.0 - 2.0 * jnp.mod(n, 2.0)

    def cn_dn(v):
        s = _sech(scale[..., None] * (v[..., None] - 2.0 * n * K[..., None]))
        return scale * jnp.sum(alt * s, -1) / k, scale * jnp.sum(s, -1)

    cn, dn = cn_dn(u)
    # dn > 0 everywhere, cn >= 0 on [-K, K]: rounding only in the last ulp.
    cn = jnp.maximum(cn, 0.0)
    # sn from its own series (the Fourier series of sc, DLMF 22.11, under
    # Jacobi's imaginary transformation, DLMF table 22.6.1):
    #   sn = scale/k [tanh(scale u) + 4 sum_{n>=1} (-1)^n q'^2n sinh(2 n scale u) / (1 + q'^2n)],
    # q' = exp(-2 scale K), each product formed from exponents <= 0.  Not
    # cn(K - u)/dn(K - u): equal in value, but there the derivative in m
    # goes through dK/dm ~ 1/(2 m1) twice and cancels, leaving rounding/m1
    # (0.1 at m1 = 1e-16, next to the rigid body's separatrix).
    p = n[_SERIES_TERMS + 1 :]
    alt_p = alt[_SERIES_TERMS + 1 :]
    two = 2.0 * scale[..., None]
    Kx, ux = K[..., None], u[..., None]
    terms = 0.5 * (jnp.exp(two * p * (ux - 2.0 * Kx)) - jnp.exp(-two * p * (ux + 2.0 * Kx)))
    terms = terms / (1.0 + jnp.exp(-2.0 * two * p * Kx))
    sn = scale / k * (jnp.tanh(scale * u) + 4.0 * jnp.sum(alt_p * terms, -1))
    return sn, cn, dn


def _separatrix(u: Array, m1: Array) -> tuple[Array, Array, Array]:
    """``sn, cn, dn`` at ``m = 1`` (``tanh, sech, sech``), with the derivative
    in ``m1 = 1 - m`` of the functions themselves.

    The values are exactly ``tanh u``, ``sech u``, ``sech u``; the first-order
    terms of A&S 16.15.1-3,

        sn = tanh u + m1/4 (tanh u - u sech^2 u),
        cn = sech u - m1/4 tanh u (sinh u - u sech u),
        dn = sech u + m1/4 tanh u (sinh u + u sech u),

    are added multiplied by ``m1 - stop_gradient(m1)``, which is zero but has
    the derivative of ``m1``: so jvp and vjp see ``d/dm1`` (without it the
    separatrix of the rigid body got no derivative with respect to the
    energy).  ``sinh`` is capped below overflow (the derivative there is
    ~1e300 anyway), so the zero term never turns into ``0 * inf``.
    """
    eps = m1 - lax.stop_gradient(m1)
    sech = _sech(u)
    tanh = jnp.tanh(u)
    cap = math.log(jnp.finfo(u.dtype).max) - 1.0
    sinh = jnp.sinh(jnp.clip(u, -cap, cap))
    usech = u * sech
    sn = tanh + (0.25 * eps) * (tanh - usech * sech)
    cn = sech - (0.25 * eps) * tanh * (sinh - usech)
    dn = sech + (0.25 * eps) * tanh * (sinh + usech)
    return sn, cn, dn


def _ellipj_reduced(u: ArrayLike, m: ArrayLike, m1: ArrayLike | None = None):
    """``sn, cn, dn`` at the reduced argument plus the reduction index.

    Returns ``(sn_r, cn_r, dn_r, j, K)`` with ``u = u_r + 2 j K``,
    ``u_r in [-K, K]``, so that ``sn(u) = (-1)^j sn_r``, ``cn(u) = (-1)^j cn_r``,
    ``dn(u) = dn_r`` and ``am(u) = atan2(sn_r, cn_r) + j pi``.  At ``m1 = 0``:
    ``tanh, sech, sech``, ``j = 0`` and ``K = inf``.
    """
    m, m1 = _params(m, m1)
    u = jnp.asarray(u, dtype=m.dtype)
    u, m, m1 = jnp.broadcast_arrays(u, m, m1)
    sep = m1 <= 0
    series = (m > _M_SWITCH) & ~sep
    # Double where: each branch only ever sees parameters it is valid for.
    m1_s = jnp.where(sep, 0.5, m1)
    m_s = jnp.where(sep, 0.5, m)
    K = (0.5 * math.pi) / _agm(jnp.ones_like(m1_s), jnp.sqrt(m1_s))
    ur, j = _reduce(u, K)

    mL = jnp.where(series, 0.5, m_s)
    sn_l, cn_l, dn_l = _landen(ur, mL, jnp.where(series, 0.5, m1_s))
    # m = 0: Landen's recursion is the identity; its derivative in m is finite.
    mS = jnp.where(series, m_s, 0.95)
    m1S = jnp.where(series, m1_s, 0.05)
    # K is only used where `series` holds; elsewhere ur stays in [-K, K] anyway.
    sn_s, cn_s, dn_s = _series(ur, mS, m1S, K)

    us = jnp.where(sep, u, 0.0)
    sn_1, cn_1, dn_1 = _separatrix(us, jnp.where(sep, m1, 0.0))
    sn = jnp.where(sep, sn_1, jnp.where(series, sn_s, sn_l))
    cn = jnp.where(sep, cn_1, jnp.where(series, cn_s, cn_l))
    dn = jnp.where(sep, dn_1, jnp.where(series, dn_s, dn_l))
    j = jnp.where(sep, 0.0, j)
    K = jnp.where(sep, jnp.inf, K)
    return sn, cn, dn, j, K


@jax.jit
def ellipj(u: ArrayLike, m: ArrayLike, m1: ArrayLike | None = None):
    """Jacobi elliptic functions ``sn, cn, dn`` and the amplitude ``am``.

    Args:
        u: argument (real), any shape broadcastable with ``m``.
        m: parameter ``m = k^2`` in ``[0, 1]``.
        m1: optional ``1 - m`` computed without cancellation by the caller.

    Returns:
        ``(sn, cn, dn, ph)`` like ``scipy.special.ellipj``; ``ph = am(u)`` is
        continuous (not wrapped to ``(-pi, pi]``).

    References:
        A&S 16.4; DLMF 22.2, 22.12 (sech series), 22.16.1 (amplitude).
    """
    sn, cn, dn, j, _ = _ellipj_reduced(u, m, m1)
    ph = jnp.arctan2(sn, cn) + math.pi * j
    sign = 1.0 - 2.0 * jnp.mod(j, 2.0)
    return sign * sn, sign * cn, dn, ph


# ---------------------------------------------------------------- Carlson forms


@jax.jit
def elliprc(x: ArrayLike, y: ArrayLike) -> Array:
    """Carlson's degenerate integral ``R_C(x, y) = R_F(x, y, y)`` for
    ``x >= 0, y > 0``.

    References:
        Carlson (1995); Numerical Recipes 3rd ed. ``rc``.
    """
    x = _float(x)
    y = jnp.asarray(y, dtype=x.dtype)
    x, y = jnp.broadcast_arrays(x, y)

    def body(_, xy):
        x, y = xy
        lam = 2.0 * _safe_sqrt(x) * jnp.sqrt(y) + y
        return 0.25 * (x + lam), 0.25 * (y + lam)

    x, y = lax.fori_loop(0, _CARLSON_STEPS, body, (x, y))
    ave = (x + y + y) / 3.0
    s = (y - ave) / ave
    return (1.0 + s * s * (0.3 + s * (1.0 / 7.0 + s * (0.375 + s * 9.0 / 22.0)))) / jnp.sqrt(ave)


@jax.jit
def elliprf(x: ArrayLike, y: ArrayLike, z: ArrayLike) -> Array:
    """Carlson's symmetric integral of the first kind
    ``R_F(x, y, z) = 1/2 int_0^inf dt / sqrt((t+x)(t+y)(t+z))``, ``x, y, z >= 0``
    with at most one zero.

    References:
        Carlson (1995); DLMF 19.16.1, 19.36.1.
    """
    x = _float(x)
    y = jnp.asarray(y, dtype=x.dtype)
    z = jnp.asarray(z, dtype=x.dtype)
    x, y, z = jnp.broadcast_arrays(x, y, z)

    def body(_, xyz):
        x, y, z = xyz
        sx, sy, sz = _safe_sqrt(x), _safe_sqrt(y), _safe_sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        return 0.25 * (x + lam), 0.25 * (y + lam), 0.25 * (z + lam)

    x, y, z = lax.fori_loop(0, _CARLSON_STEPS, body, (x, y, z))
    ave = (x + y + z) / 3.0
    dx, dy = (ave - x) / ave, (ave - y) / ave
    dz = -(dx + dy)
    e2 = dx * dy - dz * dz
    e3 = dx * dy * dz
    return (1.0 + (e2 / 24.0 - 0.1 - 3.0 / 44.0 * e3) * e2 + e3 / 14.0) / jnp.sqrt(ave)


@jax.jit
def elliprj(x: ArrayLike, y: ArrayLike, z: ArrayLike, p: ArrayLike) -> Array:
    """Carlson's symmetric integral of the third kind
    ``R_J(x, y, z, p) = 3/2 int_0^inf dt / ((t+p) sqrt((t+x)(t+y)(t+z)))`` for
    ``x, y, z >= 0`` (at most one zero) and ``p > 0``.

    References:
        Carlson (1995); DLMF 19.16.2, 19.36.1; Numerical Recipes 3rd ed. ``rj``.
    """
    x = _float(x)
    y, z, p = (jnp.asarray(v, dtype=x.dtype) for v in (y, z, p))
    x, y, z, p = jnp.broadcast_arrays(x, y, z, p)

    def body(_, state):
        x, y, z, p, acc, fac = state
        sx, sy, sz = _safe_sqrt(x), _safe_sqrt(y), _safe_sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        alpha = (p * (sx + sy + sz) + sx * sy * sz) ** 2
        beta = p * (p + lam) ** 2
        acc = acc + fac * elliprc(alpha, beta)
        return (0.25 * (x + lam), 0.25 * (y + lam), 0.25 * (z + lam), 0.25 * (p + lam), acc, 0.25 * fac)

    init = (x, y, z, p, jnp.zeros_like(x), jnp.ones_like(x))
    x, y, z, p, acc, fac = lax.fori_loop(0, _CARLSON_STEPS, body, init)
    ave = 0.2 * (x + y + z + p + p)
    dx, dy, dz, dp = (ave - x) / ave, (ave - y) / ave, (ave - z) / ave, (ave - p) / ave
    ea = dx * (dy + dz) + dy * dz
    eb = dx * dy * dz
    ec = dp * dp
    ed = ea - 3.0 * ec
    ee = eb + 2.0 * dp * (ea - ec)
    c1, c2, c3, c4 = 3.0 / 14.0, 1.0 / 3.0, 3.0 / 22.0, 3.0 / 26.0
    c5, c6, c7, c8 = 0.75 * c3, 1.5 * c4, 0.5 * c2, 2.0 * c3
    series = (
        1.0
        + ed * (-c1 + c5 * ed - c6 * ee)
        + eb * (c7 + dp * (-c8 + dp * c4))
        + dp * ea * (c2 - dp * c3)
        - c2 * dp * ec
    )
    return 3.0 * acc + fac * series / (ave * jnp.sqrt(ave))


def _f_reduced(s: Array, c: Array, delta2: Array) -> Array:
    # F for an amplitude in [-pi/2, pi/2] given sin, cos and 1 - m sin^2.
    return s * elliprf(c * c, delta2, jnp.ones_like(s))


def _pi_reduced(s: Array, c: Array, delta2: Array, n: Array) -> Array:
    s2 = s * s
    one = jnp.ones_like(s)
    return s * elliprf(c * c, delta2, one) + (n / 3.0) * s * s2 * elliprj(c * c, delta2, one, 1.0 - n * s2)


@jax.jit
def ellipf(phi: ArrayLike, m: ArrayLike, m1: ArrayLike | None = None) -> Array:
    """Incomplete elliptic integral of the first kind
    ``F(phi | m) = int_0^phi dtheta / sqrt(1 - m sin^2 theta)`` for any real
    ``phi`` (rad) and ``0 <= m < 1`` (or ``m = 1`` with ``|phi| < pi/2``).

    References:
        DLMF 19.25.5 with the quasi-periodicity 19.2.10.
    """
    m, m1 = _params(m, m1)
    phi = jnp.asarray(phi, dtype=m.dtype)
    j = jnp.round(phi / math.pi)
    pr = phi - math.pi * j
    s, c = jnp.sin(pr), jnp.cos(pr)
    F = _f_reduced(s, c, m1 + m * c * c)
    return F + 2.0 * j * jnp.where(j != 0, ellipk(m, jnp.where(j != 0, m1, 0.5)), 0.0)


@jax.jit
def ellippi(n: ArrayLike, phi: ArrayLike, m: ArrayLike, m1: ArrayLike | None = None) -> Array:
    """Incomplete elliptic integral of the third kind
    ``Pi(n; phi | m) = int_0^phi dtheta / ((1 - n sin^2 theta)
    sqrt(1 - m sin^2 theta))`` for ``n < 1``, any real ``phi`` (rad), ``0 <= m < 1``.

    References:
        DLMF 19.25.14 (Carlson form), 19.2.10.
    """
    m, m1 = _params(m, m1)
    phi = jnp.asarray(phi, dtype=m.dtype)
    n = jnp.asarray(n, dtype=m.dtype)
    j = jnp.round(phi / math.pi)
    pr = phi - math.pi * j
    s, c = jnp.sin(pr), jnp.cos(pr)
    P = _pi_reduced(s, c, m1 + m * c * c, n)
    m1c = jnp.where(j != 0, m1, 0.5)
    Pc = _pi_reduced(jnp.ones_like(P), jnp.zeros_like(P), m1c, n)
    return P + 2.0 * j * jnp.where(j != 0, Pc, 0.0)
