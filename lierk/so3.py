"""The rotation group SO(3) and its Lie algebra so(3) ~ R^3.

Conventions (those of the seed report):

- ``hat(a) @ b == cross(a, b)``; ``vee`` is its inverse.
- ``exp(w)`` is the rotation by the angle ``|w|`` (rad) about ``w/|w|``.
- A rotation matrix ``R`` maps body coordinates to space coordinates.

Every function broadcasts over leading batch axes: vectors are ``(..., 3)`` and
matrices ``(..., 3, 3)``.  Each works in float32 and float64 and is safe for
autodiff everywhere it is smooth, including ``w = 0`` ("double where": the
unselected branch never sees a division by zero, so its cotangent is finite).
The conversions refuse a wrong shape, and a known (not traced) finite input that
is no rotation: a matrix off SO(3) by more than rounding, a zero quaternion.

References:
    Munthe-Kaas, "High order Runge-Kutta methods on manifolds", Appl. Numer.
    Math. 29 (1999).  Iserles, Munthe-Kaas, Norsett, Zanna, "Lie-group methods",
    Acta Numerica (2000).
"""

from __future__ import annotations

import functools
import math
import operator

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import _validation as validation

__all__ = [
    "hat",
    "vee",
    "exp",
    "log",
    "dexp",
    "dexpinv",
    "rotate",
    "right_exp",
    "axis_turn",
    "compose",
    "reorthonormalize",
    "exp_coefficients",
    "cross",
    "orthogonality_error",
    "from_quaternion",
    "to_quaternion",
    "from_mrp",
    "to_mrp",
    "from_euler",
    "to_euler",
]


def _float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _one_program(f=None, *, static: tuple[str, ...] = ()):
    """``f`` as one jitted function, called eagerly or traced.

    Called eagerly, each `jax.numpy` operation of ``f`` would be a small
    program of its own, compiled on first use: ``log`` of a concrete rotation
    compiled about 40 of them, where one program of the whole function compiles once per shape and
    dtype.  Traced (inside a caller's `jax.jit`, `jax.vmap` or autodiff), JAX
    traces ``f`` once per shape and dtype and reuses that for every later call
    in the caller's trace, and XLA inlines it: a solver calls these in every
    stage, so this shortens a first solve's trace, to the same optimized
    program.  ``static``: the
    arguments that select the program (checked by ``f``'s caller first)."""
    if f is None:
        return functools.partial(_one_program, static=static)
    return jax.jit(f, static_argnames=static)


@_one_program
def cross(a: Array, b: Array) -> Array:
    """``a x b`` for ``(..., 3)`` arrays, written out by component (cheaper than
    ``jnp.cross``'s transposes inside tight stage loops)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def matvec(M: Array, v: Array) -> Array:
    """``M @ v`` for ``(..., 3, 3)`` and ``(..., 3)`` stacks (either may be a
    single matrix or vector), written as three elementwise products: under
    ``vmap`` XLA on CPU runs a batched 3x3 product as a dot kernel of its own
    that no stage arithmetic fuses into, and a torque evaluated at every stage
    paid one such kernel per product."""
    return M[..., :, 0] * v[..., None, 0] + M[..., :, 1] * v[..., None, 1] + M[..., :, 2] * v[..., None, 2]


def _cross_cross(u: Array, v: Array) -> Array:
    """``u x (u x v) = u (u.v) - |u|^2 v``, ``(..., 3)``: written without the
    inner cross product, whose stacked result XLA would store for its two
    uses (a kernel of its own in every RKMK stage)."""
    uv = u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]
    return u * uv[..., None] - _sq(u)[..., None] * v


@_one_program
def hat(w: ArrayLike) -> Array:
    """Skew matrix of ``w``: ``(..., 3) -> (..., 3, 3)`` with ``hat(w) @ b = w x b``."""
    w = _float(w)
    if w.shape[-1:] != (3,):
        raise ValueError(f"hat expects shape (..., 3), got {w.shape}")
    z = jnp.zeros_like(w[..., 0])
    w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
    return jnp.stack(
        [
            jnp.stack([z, -w2, w1], axis=-1),
            jnp.stack([w2, z, -w0], axis=-1),
            jnp.stack([-w1, w0, z], axis=-1),
        ],
        axis=-2,
    )


@_one_program
def vee(W: ArrayLike) -> Array:
    """Inverse of :func:`hat`: ``(..., 3, 3) -> (..., 3)``.  Uses the
    antisymmetric part, so a slightly non-skew input is projected."""
    W = _float(W)
    if W.shape[-2:] != (3, 3):
        raise ValueError(f"vee expects shape (..., 3, 3), got {W.shape}")
    return 0.5 * jnp.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def _small(dtype) -> float:
    # Threshold on theta^2 below which the Taylor series are used.  The series
    # below are truncated after the theta^8 term, so their relative error is
    # about (theta^2)^5 / 10!; these thresholds keep it below eps.  Above them the
    # closed forms have no cancellation worse than eps/theta^2 on terms that are
    # themselves O(theta^2), i.e. an absolute error of O(eps).
    return 1e-2 if jnp.finfo(dtype).bits >= 64 else 1e-1


# pi/2 in three parts (Cephes' split of pi/4, doubled): the first two have 23
# and 21 significant bits (float32: 8 and 11), so ``n * part`` is exact for
# quadrant counts n < 2^30 (float32: 2^13), i.e. theta up to 3e9 rad (float32:
# 2.6e4).  Beyond that the reduction error grows like ulp(theta), which is the
# angle's own uncertainty there.
_PI_2_PARTS = {
    64: (2 * 7.85398125648498535156e-1, 2 * 3.77489470793079817668e-8, 2 * 2.69515142907905952645e-15),
    32: (2 * 0.78515625, 2 * 2.4187564849853515625e-4, 2 * 3.77489497744594108e-8),
}
# Taylor coefficients (in x^2) of sin(x)/x, cos(x) and (sin(x)/x - cos(x))/x^2;
# 10 terms: on |x| <= pi/4 the first dropped term of each is < 1e-20 relative.
_SIN_X = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(10))
_COS = tuple((-1) ** k / math.factorial(2 * k) for k in range(10))
_E = tuple((-1) ** k * (2 * k + 2) / math.factorial(2 * k + 3) for k in range(10))


def _horner(coef, x2):
    acc = jnp.full_like(x2, coef[-1])
    for c in coef[-2::-1]:
        acc = acc * x2 + c
    return acc


@_one_program
def exp_coefficients(theta2: Array) -> tuple[Array, Array, Array]:
    """Coefficients ``(A, B, D)`` of the closed forms on so(3), from ``theta^2``:
    ``(...) -> 3 x (...)``.

    - ``A = sin(theta)/theta``
    - ``B = (1 - cos(theta))/theta^2``
    - ``D = (1 - (theta/2) cot(theta/2))/theta^2``

    so that ``exp(hat(u)) = I + A hat(u) + B hat(u)^2`` and
    ``dexpinv_u(v) = v - u x v / 2 + D u x (u x v)``.  Exact to rounding at
    every angle (several turns included) and smooth at 0, in value and
    derivatives; ``D`` is singular where ``theta = 2 pi k``, k >= 1, as dexpinv
    is.

    One ``sin``/``cos`` pair of ``x = theta/2`` serves all three, evaluated from
    polynomials only: XLA on CPU runs ``jnp.sin``/``jnp.cos`` in float64 at
    many times the cost of a multiply-add, which made them most of an RKMK
    stage's arithmetic.  For ``x > pi/4``, ``x`` is reduced to
    ``r = x - n pi/2``, ``|r| <= pi/4`` (three-part Cody-Waite), where the
    power series of ``sin r / r`` and ``cos r`` converge to rounding in 10
    terms.  For ``x <= pi/4`` the series of ``sin x / x``, ``cos x`` and
    ``(sin x / x - cos x)/x^2`` are taken in ``x^2`` itself: no square root,
    and no cancellation at small angles.

    """
    return _exp_coefficients(theta2, False)


def _coefficients(theta2: Array, compact: bool) -> tuple[Array, Array, Array]:
    """`exp_coefficients` in a solver's form (`lierk._programs`): with
    ``compact``, the three end in one division of stacked values, which XLA
    compiles as one kernel instead of three, for one body; a batch runs
    slower that way.  The same numbers to rounding (XLA may contract a
    multiply-add differently: an ulp)."""
    return _exp_coefficients(theta2, compact)


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _exp_coefficients(theta2: Array, compact: bool = False) -> tuple[Array, Array, Array]:
    numerators, denominators = _exp_fractions(theta2)
    if not compact:
        return tuple(n / d for n, d in zip(numerators, denominators))
    ABD = jnp.stack(numerators, axis=-1) / jnp.stack(denominators, axis=-1)
    return ABD[..., 0], ABD[..., 1], ABD[..., 2]


def _exp_fractions(theta2: Array) -> tuple[tuple, tuple]:
    """`exp_coefficients`' ``(A, B, D)`` as three numerators and three
    denominators, before the divisions."""
    x2 = 0.25 * theta2
    near = x2 <= (0.25 * math.pi) ** 2
    # Each branch sees only its own inputs, so neither divides by zero and
    # both have finite cotangents.  Far: x = n pi/2 + r.
    xf2 = jnp.where(near, jnp.ones_like(x2), x2)
    x = jnp.sqrt(xf2)
    p1, p2, p3 = _PI_2_PARTS[64 if jnp.finfo(x.dtype).bits >= 64 else 32]
    n = jnp.round(x * (2.0 / math.pi))
    # The clip only matters where x is so large that ulp(x) > pi (no angle left).
    r = jnp.clip(((x - n * p1) - n * p2) - n * p3, -0.786, 0.786)
    # One pair of series serves both branches: near, r is x itself (n = 0),
    # and r^2 is taken as x^2 (no square root, exact derivatives at 0).
    r2 = jnp.where(near, x2, r * r)
    S, C = _horner(_SIN_X, r2), _horner(_COS, r2)  # sin r / r, cos r
    E_near = _horner(_E, jnp.where(near, x2, jnp.zeros_like(x2)))
    sin_r = r * S
    q = n - 4.0 * jnp.floor(0.25 * n)  # quadrant, 0..3
    odd = (q == 1.0) | (q == 3.0)
    sin_x = jnp.where(odd, C, sin_r)
    cos_x = jnp.where(odd, sin_r, C)
    sin_x = jnp.where(q >= 2.0, -sin_x, sin_x)
    cos_x = jnp.where((q == 1.0) | (q == 2.0), -cos_x, cos_x)
    # Each coefficient ends in one division (an expensive op for XLA), so it is
    # computed once per angle and stored, instead of being re-derived inside
    # every consumer's fused loop (once per vector component).
    one = jnp.ones_like(x2)
    numerators = (
        jnp.where(near, S * C, sin_x * cos_x),
        jnp.where(near, 0.5 * S * S, 0.5 * sin_x * sin_x),
        jnp.where(near, E_near, sin_x - x * cos_x),
    )
    denominators = (jnp.where(near, one, x), jnp.where(near, one, xf2), jnp.where(near, 4.0 * S, 4.0 * xf2 * sin_x))
    return numerators, denominators


@_exp_coefficients.defjvp
def _exp_coefficients_jvp(compact, primals, tangents):
    # The derivatives with respect to theta^2 are computed once per angle, as
    # primal values; each tangent direction then costs one product per
    # coefficient.  Left to JAX, forward mode carried every direction through
    # the polynomial chains, and XLA re-derived them inside each consumer.
    (theta2,), (dtheta2,) = primals, tangents
    (N, D), (dN, dD) = jax.jvp(_exp_fractions, (theta2,), (jnp.ones_like(theta2),))
    if not compact:
        values = tuple(n / d for n, d in zip(N, D))
        slopes = tuple((dn - v * dd) / d for v, dn, d, dd in zip(values, dN, D, dD))
        return values, tuple(s * dtheta2 for s in slopes)
    # Values and slopes (n/d)' = (n' d - n d') / d^2 in one division of
    # stacked values: one kernel, where the quotient rule's divisions were
    # several in every differentiated stage.
    num = jnp.stack([*N, *(dn * d - n * dd for n, d, dn, dd in zip(N, D, dN, dD))], axis=-1)
    den = jnp.stack([*D, *(d * d for d in D)], axis=-1)
    q = num / den
    return tuple(q[..., i] for i in range(3)), tuple(q[..., 3 + i] * dtheta2 for i in range(3))


def _sq(u: Array) -> Array:
    return u[..., 0] ** 2 + u[..., 1] ** 2 + u[..., 2] ** 2


def _diagonal(A: Array) -> Array:
    """The diagonal ``(3,)`` of a ``(3, 3)`` matrix, as three entries:
    ``jnp.diagonal`` traces a gather behind a per-platform ``cond``, about
    20 equations a call, and every stage calls it."""
    return jnp.stack([A[0, 0], A[1, 1], A[2, 2]])


@_one_program
def exp(w: ArrayLike, coefficients: tuple | None = None) -> Array:
    """Exponential map ``so(3) -> SO(3)`` (Rodrigues): ``(..., 3) -> (..., 3, 3)``.

    Exact to rounding for any angle, including several full turns in one
    call, and at ``w = 0`` in value and in both forward- and reverse-mode
    derivatives (the Jacobian there is the three generators ``hat(e_i)``).
    The angle ``|w|`` is reduced modulo 2 pi; once its own rounding, ``|w|
    eps``, reaches a turn (``|w|`` above about 3e16 rad in float64, 5e7 in
    float32), every angle is within the rounding of ``w``, and the result
    is a rotation about ``w/|w|`` by an angle within it (within ``|w| eps /
    2`` of the exact one everywhere, ``tests/test_so3.py``).  Finite for
    every finite ``w``: one so large that ``|w|^2`` would overflow (above
    3e153 in float64, 4e18 in float32) is first shortened along its axis to
    that size, which changes its angle only within its rounding.
    ``coefficients``: ``(A, B, D)`` of
    ``w`` from `exp_coefficients`, if the caller has them.
    """
    w = _float(w)
    if w.shape[-1:] != (3,):
        raise ValueError(f"exp expects shape (..., 3), got {w.shape}")
    if coefficients is None:
        w = _squarable(w)
    return _exp(w, coefficients)


def _squarable(v: Array) -> Array:
    """``v`` ``(..., 3)``, shortened along itself where ``|v|^2`` would
    overflow, to a length whose square does not (about ``sqrt(max)/4``).
    Elsewhere ``v`` itself, with derivative 1 (at 0 too: the scale's other
    branch never sees a 0)."""
    limit = math.sqrt(float(jnp.finfo(v.dtype).max)) / 4
    m = jnp.maximum(jnp.maximum(jnp.abs(v[..., 0]), jnp.abs(v[..., 1])), jnp.abs(v[..., 2]))
    huge = m > limit
    scale = jnp.where(huge, limit / jnp.where(huge, m, 1.0), 1.0)
    return v * scale[..., None]


def _exp(w: Array, coefficients: tuple | None = None) -> Array:
    """`exp` of a ``w`` whose ``|w|^2`` is finite (a solver's stage)."""
    theta2 = _sq(w)
    A, B, _ = exp_coefficients(theta2) if coefficients is None else coefficients
    # hat(w)^2 = w w^T - theta^2 I, so exp = (1 - B theta^2) I + A hat(w) + B w w^T,
    # written entry by entry: XLA on CPU runs a batched 3x3 matmul as a separate
    # dot kernel that no elementwise work fuses into.
    w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
    c = 1.0 - B * theta2
    Aw0, Aw1, Aw2 = A * w0, A * w1, A * w2
    Bw0, Bw1 = B * w0, B * w1
    b01, b02, b12 = Bw0 * w1, Bw0 * w2, Bw1 * w2
    return jnp.stack(
        [
            jnp.stack([c + Bw0 * w0, b01 - Aw2, b02 + Aw1], axis=-1),
            jnp.stack([b01 + Aw2, c + Bw1 * w1, b12 - Aw0], axis=-1),
            jnp.stack([b02 - Aw1, b12 + Aw0, c + B * w2 * w2], axis=-1),
        ],
        axis=-2,
    )


@_one_program
def compose(X: ArrayLike, Y: ArrayLike) -> Array:
    """``X @ Y`` for ``(..., k, 3) @ (..., 3, 3)`` stacks, written as elementwise
    products that fuse with their neighbours: under ``vmap`` XLA on CPU runs a
    batched 3x3 matmul as a separate dot kernel (see `exp`), which inside a
    solver step costs more than the arithmetic."""
    X, Y = _float(X), _float(Y)
    return X[..., :, 0:1] * Y[..., 0:1, :] + X[..., :, 1:2] * Y[..., 1:2, :] + X[..., :, 2:3] * Y[..., 2:3, :]


@_one_program
def right_exp(R: ArrayLike, u: ArrayLike, *more: ArrayLike) -> Array:
    """The group update of a body-frame step, ``R exp(hat(u)) exp(hat(more[0])) ...``:
    ``(..., 3, 3), (..., 3)... -> (..., 3, 3)``.

    Every Lie-group solver advances its attitude through this function.  In
    float32 (and narrower) the result gets one Newton-Schulz step
    ``R <- R (3I - R^T R)/2``, which squares the distance to SO(3): the rounding
    of each product leaves ``||R^T R - I||`` of order eps ~ 1e-7 per step, and
    without the correction that random walk reaches ~2e-5 after 10^4 steps.  The
    correction moves ``R`` only by that rounding-level amount, so it changes
    nothing about the method's accuracy.  In float64 the same drift is ~1e-14
    after 10^5 steps, so nothing is done (the check is on the static dtype).
    """
    return _right_exp(R, u, False, *more)


def _right_exp(R: ArrayLike, u: ArrayLike, compact: bool, *more: ArrayLike) -> Array:
    """`right_exp` in a solver's form (`lierk._programs`): with ``compact``,
    each row ``r`` of ``R`` is turned by ``exp(-hat(u))``, ``r + A r x u +
    B u x (u x r)``, without forming the exponential, whose rows XLA stored
    for the product, a kernel each: fewer kernels for one body, slower for a
    batch.  The same numbers to rounding."""
    R = _float(R)
    for v in (u,) + more:
        R = _compose_exp(R, _float(v), compact)
    return reorthonormalize(R)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _compose_exp(R: Array, u: Array, compact: bool = False) -> Array:
    """``R exp(hat(u))``, ``(..., 3, 3), (..., 3) -> (..., 3, 3)``."""
    if not compact:
        return compose(R, _exp(u))
    A, B, _ = _coefficients(_sq(u), True)
    return _turn_rows(R, u, A, B)


def _turn_rows(X: Array, u: Array, A: Array, B: Array) -> Array:
    """``X exp(hat(u))`` for ``(..., k, 3)`` rows ``X`` and ``(A, B)`` of ``u``,
    row by row: each row ``r`` becomes ``r + A (r x u) + B u x (u x r)``."""
    w = u[..., None, :]
    return X + A[..., None, None] * cross(X, w) + B[..., None, None] * _cross_cross(w, X)


@_compose_exp.defjvp
def _compose_exp_jvp(compact, primals, tangents):
    # d(R exp(u)) = dR exp(u) + R exp(u) hat(dexp_{-u}(du)): each direction
    # costs two 3x3 products.  Differentiated entry by entry instead, XLA
    # rebuilt the exponential's tangent inside every entry of dR (about 190
    # operations each) under jax.jacfwd.
    (R, u), (dR, du) = primals, tangents
    coefficients = _coefficients(_sq(u), compact)
    w = dexp(-u, du, coefficients)
    if compact:
        # Row by row, as the primal: r hat(w) = r x w.
        A, B, _ = coefficients
        R1 = _turn_rows(R, u, A, B)
        return R1, _turn_rows(dR, u, A, B) + cross(R1, w[..., None, :])
    E = exp(u, coefficients)
    R1 = compose(R, E)
    return R1, compose(dR, E) + compose(R1, hat(w))


def _axis_index(k, where: str) -> int:
    """``k`` as a coordinate axis 0, 1 or 2 (a static int), or a ValueError
    that names ``where`` and the bad value."""
    try:
        index = None if isinstance(k, bool) else operator.index(k)
    except TypeError:
        index = None
    if index not in (0, 1, 2):
        raise ValueError(f"{where}: k is the coordinate axis, 0, 1 or 2 (a static int), got {k!r}")
    return index


def axis_turn(X: ArrayLike, k: int, phi: ArrayLike) -> Array:
    """``X @ exp(phi hat(e_k))`` along the last axis: ``(..., 3)`` or
    ``(..., n, 3)``, with ``phi`` ``(...)`` -> the shape of ``X``.

    The rotation by ``phi`` (rad) about the coordinate axis ``k`` (0, 1, 2,
    static), applied from the right: to each row of a matrix, or to a vector
    ``x`` as a row, which gives ``exp(-phi hat(e_k)) x``.  It mixes two
    components with ``cos phi`` and ``sin phi`` (`exp_coefficients`, exact at
    every angle), so it is cheaper than a general `exp` and a 3x3 product.
    """
    return _axis_turn(X, _axis_index(k, "axis_turn"), phi)


@_one_program(static=("k",))
def _axis_turn(X: ArrayLike, k: int, phi: ArrayLike) -> Array:
    X, phi = _float(X), _float(phi)
    A, B, _ = exp_coefficients(phi * phi)
    # The trailing axes are added after the coefficients, so that a matrix and
    # a vector turned by the same phi share one evaluation (XLA merges equal
    # expressions; on (..., 1) arrays it made a heavy-top step several times
    # slower).
    extra = (1,) * (X.ndim - 1 - phi.ndim)
    s, c1 = (A * phi).reshape(phi.shape + extra), (-B * phi * phi).reshape(phi.shape + extra)
    i, j = (k + 1) % 3, (k + 2) % 3
    xi, xj = X[..., i], X[..., j]
    out = [X[..., k]] * 3
    # x + (turned x - x), with cos phi - 1 formed directly: a turn by the same
    # phi over and over (a symmetric body's drift, whose phi is set by
    # conserved quantities) would otherwise scale x by the same rounded
    # cos^2 + sin^2 every time, a drift of |x| linear in the number of turns.
    out[i], out[j] = xi + (c1 * xi + s * xj), xj + (c1 * xj - s * xi)
    return jnp.stack(out, axis=-1)


@_one_program
def reorthonormalize(R: ArrayLike) -> Array:
    """The rounding correction every solver step ends with (`right_exp`): in
    float32 and narrower one Newton-Schulz step ``R (3I - R^T R)/2``; in
    float64 ``R`` unchanged (the check is on the static dtype).  ``(..., 3, 3)``."""
    R = _float(R)
    if jnp.finfo(R.dtype).bits < 64:
        S = compose(jnp.swapaxes(R, -1, -2), R)
        R = 1.5 * R - 0.5 * compose(R, S)
    return R


@_one_program
def rotate(u: ArrayLike, x: ArrayLike, coefficients: tuple | None = None) -> Array:
    """``exp(hat(u)) @ x`` without forming the matrix: ``(..., 3), (..., 3) -> (..., 3)``.

    ``coefficients``: ``(A, B, D)`` of ``u`` from `exp_coefficients`, when the
    caller has them already (a solver stage shares them with `dexpinv`).
    """
    u, x = _float(u), _float(x)
    A, B, _ = exp_coefficients(_sq(u)) if coefficients is None else coefficients
    return _rotate(u, x, A, B)


@jax.custom_jvp
def _rotate(u: Array, x: Array, A: Array, B: Array) -> Array:
    """`rotate` with ``(A, B)`` the `exp_coefficients` of ``u``."""
    return x + A[..., None] * cross(u, x) + B[..., None] * _cross_cross(u, x)


@_rotate.defjvp
def _rotate_jvp(primals, tangents):
    # d(exp(u) x) = exp(u) (dx + dexp_{-u}(du) x x): the change moved back to
    # the start, turned, and rotated with the same coefficients.  (A and B are
    # u's own, so their tangents follow from du.)  Differentiated term by term
    # instead, forward mode through a heavy top's stages (each turns the
    # vertical to the stage point) cost more than twice what this rule does.
    (u, x, A, B), (du, dx, _, _) = primals, tangents
    w = dexp(-u, du, (A, B, None))
    return _rotate(u, x, A, B), _rotate(u, dx + cross(w, x), A, B)


@_one_program
def dexp(u: ArrayLike, v: ArrayLike, coefficients: tuple | None = None) -> Array:
    """Left-trivialised derivative of exp, ``dexp_u(v) = sum_k ad_u^k v/(k+1)!``.

    ``d/dt exp(u(t)) = hat(dexp_u(u')) exp(u)``; in body form
    ``d/dt exp(u(t)) = exp(u) hat(dexp_{-u}(u'))``.  ``(..., 3), (..., 3) ->
    (..., 3)``; ``coefficients``: ``(A, B, D)`` of ``u`` from
    `exp_coefficients`, if the caller has them (those of ``-u`` are the same).
    """
    u, v = _float(u), _float(v)
    theta2 = _sq(u)
    A, B, _ = exp_coefficients(theta2) if coefficients is None else coefficients
    # C = (1 - A)/theta^2 has the same cancellation as D; use its series near 0.
    small = theta2 < _small(theta2.dtype)
    t2 = jnp.where(small, jnp.ones_like(theta2), theta2)
    C = jnp.where(
        small,
        1.0 / 6.0 - theta2 / 120.0 * (1.0 - theta2 / 42.0 * (1.0 - theta2 / 72.0)),
        (1.0 - A) / t2,
    )
    uv = cross(u, v)
    return v + B[..., None] * uv + C[..., None] * _cross_cross(u, v)


def dexpinv(u: ArrayLike, v: ArrayLike, terms: int | None = None, coefficients: tuple | None = None) -> Array:
    """Inverse of :func:`dexp`: exact closed form, or its truncated series.

    ``dexpinv_u(v) = v - 1/2 u x v + D(theta) u x (u x v)`` with ``theta = |u|``
    and ``D = (1 - (theta/2) cot(theta/2))/theta^2 = 1/12 + theta^2/720 + ...``.

    Args:
        u: ``(..., 3)``, the point in the algebra.
        v: ``(..., 3)``, the vector dexpinv is applied to.
        terms: None for the exact closed form (singular at ``|u| = 2 pi k``,
            k >= 1, as dexpinv is).  An int keeps the series up to
            ``ad_u^terms``: 0 gives ``v``, 1 adds ``-u x v/2``, 2 adds
            ``u x (u x v)/12`` (no trigonometry, no singularity).  An RKMK
            method of order p needs ``terms >= p - 2`` (Munthe-Kaas 1999).
        coefficients: ``(A, B, D)`` of ``u`` from `exp_coefficients`, when
            the caller has them (used only with ``terms=None``).

    Sign convention: this is the left (space-frame) form.  For the body-frame
    equation ``dR/dt = R hat(omega)`` with ``R = R_n exp(hat(u))`` one has
    ``u' = dexpinv(-u, omega) = omega + 1/2 u x omega + D u x (u x omega)``.
    """
    if terms is not None and not (isinstance(terms, int) and 0 <= terms <= 2):
        raise ValueError(f"terms must be None (exact) or 0, 1 or 2, got {terms!r}")
    return _dexpinv(u, v, terms, coefficients)


@_one_program(static=("terms",))
def _dexpinv(u: ArrayLike, v: ArrayLike, terms: int | None, coefficients: tuple | None) -> Array:
    u, v = _float(u), _float(v)
    if terms == 0:
        return v
    uv = cross(u, v)
    if terms == 1:
        return v - 0.5 * uv
    if terms == 2:
        return v - 0.5 * uv + _cross_cross(u, v) / 12.0
    _, _, D = exp_coefficients(_sq(u)) if coefficients is None else coefficients
    return v - 0.5 * uv + D[..., None] * _cross_cross(u, v)


def _rotation_tolerance(dtype) -> float:
    # ||R^T R - I|| allowed of an input rotation: check_attitude's 1e-6 in
    # float64, and about a thousand roundings in narrower types (float32:
    # 1.2e-4; a float32 solve keeps R within ~1e-6, and a float32 product of
    # a few thousand rotations within ~1e-5).
    return max(1e-6, 1000 * float(jnp.finfo(dtype).eps))


def _rotation_input(R: ArrayLike, where: str) -> Array:
    """``R`` as a float array of rotation matrices, or a ValueError naming
    ``where`` and the shape; when ``R`` is known now (not traced), also the
    first matrix, by index, that is not a rotation (``||R^T R - I||`` over
    `_rotation_tolerance`, or ``det R < 0``).  The value is checked in NumPy:
    no program is compiled for it.  Matrices with NaN or inf entries pass (a
    diverged solve's states convert to NaN, as every map here does), and a
    traced ``R`` is not checked at all: a run-time check would be a host
    callback in every compiled caller."""
    x = R
    R = _float(R)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"{where} expects rotation matrices of shape (..., 3, 3), got shape {R.shape}")
    if not validation.is_traced(x):
        M = np.asarray(x, np.float64).reshape(R.shape)
        with np.errstate(all="ignore"):  # NaN and inf entries pass, below
            E = np.swapaxes(M, -1, -2) @ M - np.eye(3)
            err = np.sqrt(np.sum(E * E, axis=(-2, -1)))
            det = np.linalg.det(M)
        tol = _rotation_tolerance(R.dtype)
        bad = np.isfinite(M).all(axis=(-2, -1)) & ((err > tol) | (det < 0))
        if bad.any():
            i = tuple(int(k) for k in np.argwhere(bad)[0])
            name = f"R[{', '.join(map(str, i))}]" if i else "R"
            raise ValueError(
                f"{where} expects rotation matrices (||R^T R - I|| <= {tol:.2g} in {R.dtype.name}, det R = +1); "
                f"{name} has ||R^T R - I|| = {err[i]:.3g} and det R = {det[i]:.6g}: {validation.show(M[i])}"
            )
    return R


@_one_program
def _quaternion(R: Array) -> Array:
    """`to_quaternion` without its input checks (for the conversions built on it)."""
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    d21 = R[..., 2, 1] - R[..., 1, 2]
    d02 = R[..., 0, 2] - R[..., 2, 0]
    d10 = R[..., 1, 0] - R[..., 0, 1]
    s21 = R[..., 2, 1] + R[..., 1, 2]
    s02 = R[..., 0, 2] + R[..., 2, 0]
    s10 = R[..., 1, 0] + R[..., 0, 1]

    def safe_sqrt(x):
        # Branches that are not selected may see a negative argument; keep their
        # values and cotangents finite.  (The selected one has x >= 1, so no
        # branch divides by less than 2 t = 1 below.)  NaN is kept: a NaN
        # matrix gives a NaN quaternion, not (0.5, NaN, NaN, NaN).
        return jnp.sqrt(jnp.where(x <= 0.25, jnp.ones_like(x), x))

    # Each candidate is 4 q_k^2 for its largest component k, times the others.
    t0 = safe_sqrt(1.0 + tr)
    q0 = jnp.stack([t0 * t0, d21, d02, d10], axis=-1) / (2.0 * t0[..., None])
    t1 = safe_sqrt(1.0 + r00 - r11 - r22)
    q1 = jnp.stack([d21, t1 * t1, s10, s02], axis=-1) / (2.0 * t1[..., None])
    t2 = safe_sqrt(1.0 - r00 + r11 - r22)
    q2 = jnp.stack([d02, s10, t2 * t2, s21], axis=-1) / (2.0 * t2[..., None])
    t3 = safe_sqrt(1.0 - r00 - r11 + r22)
    q3 = jnp.stack([d10, s02, s21, t3 * t3], axis=-1) / (2.0 * t3[..., None])
    k = jnp.argmax(jnp.stack([tr, r00, r11, r22], axis=-1), axis=-1)[..., None]
    q = jnp.where(k == 0, q0, jnp.where(k == 1, q1, jnp.where(k == 2, q2, q3)))
    return jnp.where(q[..., :1] < 0, -q, q)


def to_quaternion(R: ArrayLike) -> Array:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix.

    Shepperd's method: the branch on the largest of ``(tr R, R_00, R_11, R_22)``
    keeps the square root well away from zero, so it is accurate at every angle
    including pi, and its derivatives are finite there (at ``w = 0`` exactly,
    those of the branch whose sign was kept).  ``(..., 3, 3) -> (..., 4)``.

    Raises ValueError on another shape, and on a known (not traced) ``R``
    that is not a rotation, by more than rounding (see `_rotation_input`).
    """
    return _quaternion(_rotation_input(R, "to_quaternion"))


def from_quaternion(q: ArrayLike) -> Array:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first):
    ``(..., 4) -> (..., 3, 3)``.

    Raises ValueError on another shape, and on a known (not traced) zero
    quaternion, or one whose squared norm underflows in its dtype (it has no
    direction to normalise: the result would be NaN)."""
    x = q
    q = _float(q)
    if q.shape[-1:] != (4,):
        raise ValueError(f"from_quaternion expects shape (..., 4), got shape {q.shape}")
    if not validation.is_traced(x):
        qn = np.asarray(x).astype(np.dtype(q.dtype)).reshape(q.shape)
        bad = np.sum(qn * qn, axis=-1) == 0
        if bad.any():
            i = tuple(int(k) for k in np.argwhere(bad)[0])
            name = f"q[{', '.join(map(str, i))}]" if i else "q"
            raise ValueError(f"from_quaternion needs a non-zero quaternion, got {name} = {validation.show(qn[i])}")
    return _from_quaternion(q)


@_one_program
def _from_quaternion(q: Array) -> Array:
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, v = q[..., 0], q[..., 1:]
    K = hat(v)
    eye = jnp.eye(3, dtype=q.dtype)
    return eye + 2.0 * w[..., None, None] * K + 2.0 * (K @ K)


def to_mrp(R: ArrayLike) -> Array:
    """Modified Rodrigues parameters ``sigma = n tan(phi/4)`` of a rotation by
    ``phi`` about the unit axis ``n``: ``(..., 3, 3) -> (..., 3)``.

    ``R`` maps body to space, so this is Basilisk's ``sigma_BN`` (the MRP of
    the body frame B relative to the space frame N) and SciPy's
    ``Rotation.from_matrix(R).as_mrp()``.  The set is the one with
    ``|sigma| <= 1`` (``phi <= pi``): its shadow ``-sigma/|sigma|^2`` is taken
    where ``|sigma|`` would pass 1, as Basilisk's MRP switching does, so a
    saved history jumps from ``sigma`` to its shadow where the angle passes
    pi.  From the quaternion with ``w >= 0`` (`to_quaternion`):
    ``sigma = v/(1 + w)``, with ``1 + w >= 1``, so it is finite and
    differentiable at 0 and at pi.  Raises ValueError as `to_quaternion` does.
    """
    return _mrp(_rotation_input(R, "to_mrp"))


@_one_program
def _mrp(R: Array) -> Array:
    q = _quaternion(R)
    return q[..., 1:] / (1.0 + q[..., :1])


@_one_program
def from_mrp(sigma: ArrayLike) -> Array:
    """Rotation matrix (body -> space) of modified Rodrigues parameters,
    either set: ``(..., 3) -> (..., 3, 3)``,
    ``R = I + (8 S^2 + 4 (1 - |sigma|^2) S)/(1 + |sigma|^2)^2`` with
    ``S = hat(sigma)`` (the transpose of Schaub and Junkins' ``[BN]``).  A
    rational function: smooth everywhere, ``sigma = 0`` and ``|sigma| = 1``
    (a half turn) included.  Where ``|sigma| > 1`` it is formed from the
    shadow set ``-sigma/|sigma|^2`` (the same rotation), computed without
    forming ``|sigma|^2``: a large ``sigma`` is a rotation near the identity
    (``[1e160, 0, 0]`` is a turn of 4e-160 rad), which the formula above
    would give as ``inf/inf``."""
    sigma = _float(sigma)
    if sigma.shape[-1:] != (3,):
        raise ValueError(f"from_mrp expects shape (..., 3), got {sigma.shape}")
    # With m the largest |component|: |sigma| = m |sigma/m| and the shadow
    # -(sigma/m)/(m |sigma/m|^2), neither of which overflows.  At sigma = 0
    # the shadow's branch sees a constant (finite derivatives there).
    m = jnp.maximum(jnp.maximum(jnp.abs(sigma[..., 0]), jnp.abs(sigma[..., 1])), jnp.abs(sigma[..., 2]))[..., None]
    moved = m > 0
    safe_m = jnp.where(moved, m, 1.0)
    unit = jnp.where(moved, sigma, 1.0) / safe_m
    unit2 = _sq(unit)[..., None]
    sigma = jnp.where(m * jnp.sqrt(unit2) > 1.0, -unit / (safe_m * unit2), sigma)
    s2 = _sq(sigma)[..., None, None]
    S = hat(sigma)
    eye = jnp.eye(3, dtype=sigma.dtype)
    return eye + (8.0 * compose(S, S) + 4.0 * (1.0 - s2) * S) / (1.0 + s2) ** 2


def log(R: ArrayLike) -> Array:
    """Logarithm ``SO(3) -> so(3)``, the rotation vector with ``|w| <= pi``.

    Goes through the quaternion (never ``arccos`` of the trace), so it is stable
    near 0 and near pi, and ``log(exp(w)) == w`` for ``|w| < pi``.
    ``(..., 3, 3) -> (..., 3)``.  Its derivatives are finite everywhere in both
    modes; at a half turn, where log jumps between ``+pi n`` and ``-pi n``,
    they are those of the side whose value it returns.  Raises ValueError as
    `to_quaternion` does.
    """
    return _log(_rotation_input(R, "log"))


@_one_program
def _log(R: Array) -> Array:
    q = _quaternion(R)
    w, v = q[..., 0], q[..., 1:]
    n2 = _sq(v)
    small = n2 < _small(n2.dtype) * 1e-2
    n = jnp.sqrt(jnp.where(small, jnp.ones_like(n2), n2))
    closed = 2.0 * jnp.arctan2(n, w) / n
    # 2 atan(n/w)/n = (2/w)(1 - x/3 + x^2/5 - x^3/7 + ...), x = (n/w)^2, w ~ 1.
    # The series sees w = 1 where it is not taken: at a half turn w -> 0, and
    # its 1/w (or, in float32 within 1e-6 of pi, its overflowing x^3) turned
    # the zero cotangent of the unused branch into NaN.
    ws = jnp.where(small, w, jnp.ones_like(w))
    x = n2 / (ws * ws)
    series = 2.0 / ws * (1.0 - x / 3.0 + x * x / 5.0 - x * x * x / 7.0)
    return jnp.where(small, series, closed)[..., None] * v


@_one_program
def orthogonality_error(R: ArrayLike) -> Array:
    """Frobenius norm ``||R^T R - I||``: ``(..., 3, 3) -> (...)``."""
    R = _float(R)
    E = jnp.swapaxes(R, -1, -2) @ R - jnp.eye(3, dtype=R.dtype)
    return jnp.sqrt(jnp.sum(E * E, axis=(-2, -1)))


def _axis_rotation(angle: Array, axis: int) -> Array:
    e = jnp.zeros(angle.shape + (3,), angle.dtype).at[..., axis].set(1.0)
    return exp(angle[..., None] * e)


def from_euler(phi: ArrayLike, theta: ArrayLike, psi: ArrayLike, convention: str = "zyx") -> Array:
    """Rotation from Euler angles (rad); scalars or broadcastable arrays
    ``(...) -> (..., 3, 3)``.

    - ``"zyx"`` (default, the report's): ``R = Rz(phi) Ry(theta) Rx(psi)``.
    - ``"zxz"`` (the classical angles of a top): ``R = Rz(phi) Rx(theta) Rz(psi)``,
      with ``phi`` the precession, ``theta`` the nutation (tilt of the body z
      axis from space z) and ``psi`` the spin.
    """
    return _from_euler(phi, theta, psi, _convention(convention))


@_one_program(static=("convention",))
def _from_euler(phi: ArrayLike, theta: ArrayLike, psi: ArrayLike, convention: str) -> Array:
    phi, theta, psi = jnp.broadcast_arrays(_float(phi), _float(theta), _float(psi))
    middle = {"zyx": (1, 0), "zxz": (0, 2)}[convention]
    return _axis_rotation(phi, 2) @ _axis_rotation(theta, middle[0]) @ _axis_rotation(psi, middle[1])


def _convention(convention: str) -> str:
    if convention not in ("zyx", "zxz"):
        raise ValueError(f"convention must be 'zyx' or 'zxz', got {convention!r}")
    return convention


def _wrap(a: Array) -> Array:
    # Into (-pi, pi] by one turn at most (the sums of two half angles below
    # lie in (-2 pi, 2 pi]), added only where needed: a small angle keeps its
    # relative accuracy, which a remainder modulo 2 pi would round away.
    return jnp.where(a > math.pi, a - 2 * math.pi, jnp.where(a <= -math.pi, a + 2 * math.pi, a))


def _safe_norm(s2: Array) -> Array:
    # sqrt(s2) of a sum of squares, with a finite derivative (0) at s2 = 0
    # (and NaN kept NaN).
    pos = s2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s2, jnp.ones_like(s2))), s2)


def to_euler(R: ArrayLike, convention: str = "zyx") -> Array:
    """Euler angles ``(phi, theta, psi)`` (rad) of ``R`` (see `from_euler`):
    ``(..., 3, 3) -> (..., 3)``, ``phi`` and ``psi`` in ``(-pi, pi]``.

    - ``"zyx"``: ``theta`` lies in ``[-pi/2, pi/2]``; at the gimbal lock
      ``|theta| = pi/2`` only ``phi - psi`` (or ``phi + psi``) is determined,
      and ``psi`` is set to 0.
    - ``"zxz"``: ``theta`` lies in ``[0, pi]``; at ``theta = 0`` or ``pi`` only
      ``phi + psi`` (or ``phi - psi``) is determined, and ``psi`` is set to 0.

    From the quaternion (`to_quaternion`), after Bernardes and Viollet,
    "Quaternion to Euler angles conversion: a direct, general and
    computationally efficient method", PLoS ONE 17 (2022), as SciPy's
    ``as_euler``: the quaternion falls into two pairs ``(a, b)`` and
    ``(c, d)`` whose lengths are the cosine and sine of the middle angle's
    half (of ``theta + pi/2`` for ``"zyx"``) and whose directions are the half
    sum and half difference of the outer angles.  The middle angle is an
    ``atan2`` of those lengths, accurate to rounding in absolute terms at and
    near the lock (``arcsin``/``arccos`` of one entry lose half the digits
    there) and relatively near ``theta = 0``.  Near the lock the outer angles
    are each as ill-determined as the lock is close (``eps/|cos theta|``),
    but their errors cancel in the rotation: ``from_euler`` of the result is
    ``R`` to rounding at every distance from the lock.  Only where a pair's
    length is within a few roundings of 0 (the lock itself) is ``psi`` set to
    0.  Derivatives are finite everywhere (at the lock, those with ``psi``
    held at 0).  Raises ValueError as `to_quaternion` does.
    """
    return _euler(_rotation_input(R, "to_euler"), _convention(convention))


@_one_program(static=("convention",))
def _euler(R: Array, convention: str) -> Array:
    q = _quaternion(R)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    if convention == "zxz":
        # Rz(phi) Rx(theta) Rz(psi): (w, z) = cos(theta/2) (cos, sin)((phi + psi)/2),
        # (x, y) = sin(theta/2) (cos, sin)((phi - psi)/2).
        a, b, c, d = w, z, x, y
    else:
        # Rz(phi) Ry(theta) Rx(psi), whose pairs are those of a symmetric
        # sequence turned by pi/2 about y: the middle angle is theta + pi/2.
        a, b, c, d = w - y, x + z, w + y, z - x
    h_ab, h_cd = _safe_norm(a * a + b * b), _safe_norm(c * c + d * d)
    if convention == "zxz":
        theta = 2.0 * jnp.arctan2(h_cd, h_ab)
    else:
        # sin theta = -R_20 = 2 (w y - x z) = (h_cd^2 - h_ab^2)/2 and
        # cos theta = h_ab h_cd: formed so, theta keeps its relative accuracy
        # near 0, which 2 atan2(h_cd, h_ab) - pi/2 would round to ulp(pi/2).
        theta = jnp.arctan2(2.0 * (w * y - x * z), h_ab * h_cd)
    # At a lock one pair vanishes and its direction is rounding noise; its
    # half angle is then taken equal to the other's, which sets psi to 0.
    # (Each atan2 sees (0, 1) where it is not used: finite cotangents.)
    tiny = 4 * jnp.finfo(q.dtype).eps
    no_cd, no_ab = h_cd <= tiny * h_ab, h_ab <= tiny * h_cd
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    half_sum = jnp.arctan2(jnp.where(no_ab, zero, b), jnp.where(no_ab, one, a))
    half_diff = jnp.arctan2(jnp.where(no_cd, zero, d), jnp.where(no_cd, one, c))
    half_sum, half_diff = jnp.where(no_ab, half_diff, half_sum), jnp.where(no_cd, half_sum, half_diff)
    phi, psi = _wrap(half_sum + half_diff), _wrap(half_sum - half_diff)
    return jnp.stack([phi, theta, psi], axis=-1)
