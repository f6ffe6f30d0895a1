"""Exact solution of the torque-free rigid body (Euler-Poinsot motion).

Conventions (those of :mod:`lierk.so3`): ``R`` maps body to space coordinates,
``dR/dt = R hat(omega)`` with ``omega`` the body angular velocity (rad/s), the
spatial angular momentum ``L = R I omega`` is constant, the body momentum
``m = R^T L`` obeys Euler's equations ``dm/dt = m x omega``, ``omega = I^{-1} m``.
Units are whatever the caller uses consistently (SI: kg m^2, rad/s, s).

Method.  The inertia is diagonalised (``jnp.linalg.eigh``) into a proper
principal frame with ``I1 <= I2 <= I3``.  Let ``2T = m . omega``, ``G = |m|``.
If ``G^2 > 2 T I2`` the momentum circulates around the 3-axis, if
``G^2 < 2 T I2`` around the 1-axis; in the second case the axes are relabelled
by the proper rotation ``(x, y, z) -> (z, y, -x)``, so that in a "working frame"
(inertias ``J1, J2, J3``) the momentum always circulates around ``+e3``
(further half-turn symmetries of Euler's equations make ``m1(0) >= 0`` and
``m3(0) >= 0``).  There

    m(t) = (A1 cn(u), A2 sn(u), A3 dn(u)),   u = lambda t + u0,

with parameter ``k^2``; ``lambda < 0`` in the relabelled case.  On the
separatrix (``k = 1``) ``cn = dn = sech``, ``sn = tanh``; permanent rotations
and symmetric bodies are the cases ``lambda = 0`` or ``k = 0``.

The attitude follows from ``R(t) = S0 Rz(psi(t)) P(m(t))`` where ``P(m)`` is
the minimal rotation taking ``m`` onto ``|m| e3`` (well defined because
``m3 >= 0`` in the working frame) and ``S0 = R(0) P(m(0))^T``: both ``R P^T``
and ``S0`` map ``e3`` onto ``L/|L|``, so they differ by a rotation about
``e3``.  Differentiating gives

    psi' = (2T + G m3/J3) / (G + m3) = G/J3 + (2T - G^2/J3) / (G + m3),

which integrates in closed form (``dn du = d am(u)``):

    psi(t) = G t/J3 + c [G (Pi(n; am u | k^2) - Pi(n; am u0 | k^2))
                         - (A1 A3 / b) (Theta(u) - Theta(u0))],

    n = -J3 (J2 - J1) / (J1 (J3 - J2)),  b = sqrt(A1^2 + A3^2 k^2) = A1 sqrt(1 - n),
    Theta(u) = atan2(sqrt(1 - n) sn u, cn u) (continued), c = sqrt(J2/(J1 J3 r Q)),

in the notation of :func:`_working_constants`.  ``n <= 0``, so the third-kind
integral has no pole.  All elliptic functions and integrals are evaluated by
:mod:`lierk._elliptic` with ``1 - k^2`` computed directly from the momentum
(no cancellation near the separatrix).  Next to the intermediate axis the
small components of ``m`` grow like ``exp(|lambda| t)`` and so would any
loss of their relative precision; so nothing small is formed by subtracting
numbers of size one: the initial ``sn u0 = y/A2`` and ``cn u0 = x/A1`` come
from the momentum (not from the angle ``atan2``, whose rounding would leave
``cn u0 ~ 1e-9`` with 1e-7 relative error), ``r`` and ``1 - r`` from their
own differences of moments, and `free_flow`'s addition theorems from sums of
terms of one sign.

Inputs are validated as `lierk.FreeRigidBody` validates them
(`lierk._validation.rigid_body_inputs`): the inertia is ``(3, 3)`` symmetric
positive definite or ``(3,)`` principal moments, ``omega0`` is a finite
``(3,)`` vector and ``R0`` a rotation matrix.  Concrete values raise
`ValueError` naming the value; traced values (under ``jit``/``vmap``/``grad``)
are checked when the program runs (one `eqx.error_if`).

Branches use ``jnp.where`` with sanitised inputs on both sides ("double
where"), so everything jits, vmaps and differentiates with respect to
``omega0``, ``t`` and ``R0``.  Known limitations of the derivatives: at exact
permanent rotations (``m`` along a principal axis) and exactly on the
separatrix the map is not differentiable in ``omega0`` in the classical sense;
there the derivative is finite but not meaningful.

References:
    E. Celledoni, F. Fasso, N. Safstrom, A. Zanna, "The exact computation of
    the free rigid body motion and its use in splitting methods", SIAM J. Sci.
    Comput. 30 (2008) 2084-2112.
    L. D. Landau, E. M. Lifshitz, "Mechanics", 3rd ed., section 37.
    Principia (mockingbirdnest/Principia), documentation/Celledoni.tex.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.custom_derivatives import SymbolicZero
from jax.typing import ArrayLike

from lierk import so3
from lierk._elliptic import _ellipj_reduced, _pi_reduced, _safe_sqrt, ellipk, elliprf
from lierk._programs import Program
from lierk._validation import first_invalid, is_traced, rigid_body_inputs

__all__ = ["free_rigid_body", "free_flow", "symmetric_flow", "flip_interval", "sphere", "principal_frame"]


def _dtype(*xs) -> jnp.dtype:
    return jnp.result_type(*(jnp.asarray(x) for x in xs), float)


def principal_frame(inertia: ArrayLike) -> tuple[Array, Array]:
    """Principal moments and a proper principal frame.

    Args:
        inertia: symmetric positive-definite inertia tensor, ``(3, 3)``, in body
            coordinates (kg m^2).

    Returns:
        ``(I, V)``: moments ``I = (I1, I2, I3)`` ascending, shape ``(3,)``, and a
        rotation ``V`` (``det V = +1``), ``(3, 3)``, whose columns are the
        corresponding principal axes, so ``inertia = V diag(I) V^T``.

    References:
        Landau & Lifshitz, "Mechanics", section 32.
    """
    inertia = jnp.asarray(inertia, dtype=_dtype(inertia))
    inertia = 0.5 * (inertia + jnp.swapaxes(inertia, -1, -2))
    evals, V = jnp.linalg.eigh(inertia)
    # eigh may return a reflection; flipping the last axis keeps it an
    # eigenbasis and makes it a rotation.
    sign = jnp.sign(jnp.linalg.det(V))
    V = V.at[..., :, 2].multiply(sign[..., None])
    return evals, V


def _validated(inertia: ArrayLike, omega0: ArrayLike, R0: ArrayLike | None = None):
    """``(inertia (3, 3), omega0 (3,), R0 (3, 3))`` checked and in one float
    dtype, as `lierk.FreeRigidBody` checks them.  Traced values that fail
    their checks come back NaN (`lierk._validation.check`); having no result
    code, the closed forms raise for them at run time (one `eqx.error_if`),
    so callers must compute with the returned arrays."""
    inputs = rigid_body_inputs(inertia, omega0, R0)
    if not is_traced(inputs):
        return inputs
    return eqx.error_if(inputs, first_invalid(inputs), _INVALID)


_INVALID = (
    "lierk.exact: an input is NaN, or a traced value failed the check that a known value fails at once, "
    "with its name: inertia must be positive definite (symmetric, finite); omega0 has NaN or inf entries, "
    "or a traced inertia and omega0 give a body state outside the dtype's range; R0 must be a rotation "
    "matrix. Call with the concrete values to see which"
)


def _working_constants(inertia: Array, omega0: Array):
    """Everything about the motion that does not depend on time, from an
    inertia ``(3, 3)`` and ``omega0`` that `_validated` has checked.

    Returns a dict with the working-frame rotation ``W`` (body = W working),
    inertias ``J``, initial momentum ``x, y, z`` (working frame), amplitudes
    ``A1, A2, A3``, ``lam``, ``k2 = k^2``, ``k2c = 1 - k^2``, the ratio
    ``r = (J3 - J2)/(J3 - J1)`` in ``[0, 1]`` and ``rc = 1 - r`` (computed
    as ``(J2 - J1)/(J3 - J1)``), ``P = (2T J3 - G^2)/(J3 - J1)``,
    ``Qv = (G^2 - 2T J1)/(J3 - J1)``, ``d = (G^2 - 2T J2)/(J3 - J1)``,
    ``G``, ``2T`` and the masks ``sep`` (separatrix) and ``stat`` (permanent
    rotation, ``m`` constant).
    """
    dtype = inertia.dtype
    Ip, V = principal_frame(inertia)
    mp = V.T @ (inertia @ omega0)

    I1, I2, I3 = Ip[0], Ip[1], Ip[2]
    spread = I3 - I1
    round_ = spread > 0
    spread_s = jnp.where(round_, spread, 1.0)
    # r = (I3 - I2)/(I3 - I1) and its complement 1 - r = (I2 - I1)/(I3 - I1),
    # each from its own difference of moments: 1 - r by subtraction would
    # keep only the digits of r's rounding when I1 and I2 are close.
    r_orig = jnp.where(round_, (I3 - I2) / spread_s, 0.5)
    rc_orig = jnp.where(round_, (I2 - I1) / spread_s, 0.5)
    # d = (G^2 - 2 T I2)/(I3 - I1), formed from the two terms of opposite sign
    # only: its sign decides about which axis m circulates.
    d_orig = mp[2] ** 2 * r_orig / I3 - mp[0] ** 2 * rc_orig / I1
    case_b = d_orig < 0

    eye = jnp.eye(3, dtype=dtype)
    # (x, y, z) -> (z, y, -x): a proper relabelling putting the smallest axis last.
    Qb = jnp.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=dtype)
    Q = jnp.where(case_b, Qb, eye)
    J = jnp.where(case_b, Ip[::-1], Ip)
    mq = Q @ mp
    # Half-turns about e1 and e3 are symmetries of Euler's equations with a
    # diagonal inertia; they make z >= 0 (so G + m3 never vanishes) and x >= 0
    # (so the initial amplitude lies in [-pi/2, pi/2] even on the separatrix).
    s3 = jnp.where(mq[2] < 0, -1.0, 1.0).astype(dtype)
    s1 = jnp.where(mq[0] < 0, -1.0, 1.0).astype(dtype)
    F = jnp.diag(jnp.stack([s1, s1 * s3, s3]))
    Wt = F @ Q @ V.T  # working = Wt body
    m = F @ mq
    x, y, z = m[0], m[1], m[2]
    J1, J2, J3 = J[0], J[1], J[2]

    r = jnp.where(case_b, rc_orig, r_orig)
    rc = jnp.where(case_b, r_orig, rc_orig)
    G2 = x * x + y * y + z * z
    twoT = x * x / J1 + y * y / J2 + z * z / J3
    # P = (2T J3 - G^2)/(J3 - J1), Qv = (G^2 - 2T J1)/(J3 - J1),
    # d = (G^2 - 2T J2)/(J3 - J1); each a sum of non-negative terms (d by the
    # choice of frame), so none loses digits to cancellation.
    P = x * x / J1 + y * y * r / J2
    Qv = y * y * rc / J2 + z * z / J3
    # (A where, not jnp.maximum: on the separatrix, d = 0, the derivative must
    # be that of the expression, not maximum's half of it.)
    d = z * z * r / J3 - x * x * rc / J1
    d = jnp.where(d >= 0, d, 0.0)
    rQ = r * Qv

    stat = (rQ <= 0) | ((x == 0) & (z == 0))
    rQs = jnp.where(stat, 1.0, rQ)
    k2c = jnp.where(stat, 0.5, d / rQs)
    k2 = jnp.where(stat, 0.5, rc * P / rQs)
    sep = (k2c <= 0) & ~stat
    rs = jnp.where(r > 0, r, 1.0)

    A1 = _safe_sqrt(J1 * P)
    A2 = _safe_sqrt(J2 * P / rs)
    A3 = _safe_sqrt(J3 * Qv)
    sgn = jnp.where(case_b, -1.0, 1.0).astype(dtype)
    lam = sgn * spread * _safe_sqrt(rQ / (J1 * J2 * J3))
    return dict(
        W=Wt.T,
        J=J,
        x=x,
        y=y,
        z=z,
        A1=A1,
        A2=A2,
        A3=A3,
        lam=lam,
        k2=k2,
        k2c=k2c,
        r=r,
        rc=rc,
        P=P,
        Qv=Qv,
        d=d,
        G=_safe_sqrt(G2),
        twoT=twoT,
        sep=sep,
        stat=stat,
        dtype=dtype,
    )


def _minimal_rotation(m: Array, G: Array) -> Array:
    """Rotation ``P`` with ``P m = G e3`` about the axis ``m x e3``;
    ``(..., 3) -> (..., 3, 3)``.  Requires ``m3 > -G`` (here ``m3 >= 0``)."""
    n = m / G[..., None]
    v = jnp.stack([n[..., 1], -n[..., 0], jnp.zeros_like(n[..., 0])], axis=-1)
    H = so3.hat(v)
    eye = jnp.eye(3, dtype=m.dtype)
    return eye + H + (H @ H) / (1.0 + n[..., 2])[..., None, None]


def _rz(psi: Array) -> Array:
    c, s = jnp.cos(psi), jnp.sin(psi)
    z, o = jnp.zeros_like(psi), jnp.ones_like(psi)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2)


def free_rigid_body(
    inertia: ArrayLike, omega0: ArrayLike, t: ArrayLike, R0: ArrayLike | None = None
) -> tuple[Array, Array]:
    """Exact attitude and body angular velocity of a torque-free rigid body.

    Args:
        inertia: symmetric positive-definite inertia tensor in body coordinates,
            ``(3, 3)`` (kg m^2), need not be diagonal; or ``(3,)`` principal
            moments.  Symmetric bodies and the sphere are allowed.
        omega0: initial body angular velocity, ``(3,)`` (rad/s), finite.
        t: time(s) (s), scalar or any shape ``S``.
        R0: initial attitude, ``(3, 3)`` rotation (body -> space); identity if
            ``None``.

    Returns:
        ``(R, omega)`` with ``R`` of shape ``S + (3, 3)`` (body -> space) and the
        body angular velocity ``omega`` of shape ``S + (3,)`` (rad/s), so that
        ``dR/dt = R hat(omega)`` and ``R inertia omega = R0 inertia omega0``.

    Notes:
        Every regime is covered: circulation about the largest or smallest
        axis (elliptic functions), the separatrix ``|m|^2 = 2 T I2`` exactly
        (``sech``/``tanh``), permanent rotations, symmetric bodies
        (``I1 = I2`` or ``I2 = I3``) and the sphere.  Jit-able, vmappable and
        differentiable in ``omega0``, ``t``, ``R0`` (see the module docstring
        for the non-smooth exceptional sets).  float64 accuracy is ~1e-12 over
        100 periods of ``m`` (limited by the rounding of the phase ``lambda t``),
        except on needle-like bodies without two equal moments: the
        precession angle is the difference of two terms of size ``|L| t /
        I1`` (``I1`` the smallest moment), so ``R`` errs by about ``1e-16 |L|
        t / I1`` and up to 30 times that (3.4e-8 at ``I = (1e-6, 1, 1 +
        1e-6)``, ``|L| = 1.1``, ``t = 5``; 5.5e-12 at ``I1 = 1e-3``).  With
        two principal moments exactly equal (a thin rod ``(1e-6, 1, 1)``
        too) the precession rate is constant and taken directly: exact to
        rounding.  A full ``(3, 3)`` inertia whose equal eigenvalues come out
        unequal by rounding takes the general formula (the rod, rotated:
        3.1e-9).  Next to the intermediate axis, where the flow is well
        conditioned in the relative size of each component (``omega0 =
        (2^-30, 1, 2^-30)`` on ``diag(1, 2, 3)``, the T-handle spun about
        its x axis, either side of the separatrix, through the flip): ``m``
        within 1.4e-14 of ``|m|`` (at most 1.75 eps times the flow's
        condition number) and ``R`` within 6.1e-14, against a 34-digit
        Taylor-series integration (``tests/test_exact.py``), where SciPy's
        DOP853 at rtol 1e-13 errs by up to 1.5e-14 and 6.4e-13.

    Raises:
        ValueError: a wrong shape, NaN/inf, a non-symmetric or indefinite
            inertia, or an ``R0`` off SO(3) (checked at run time with
            `eqx.error_if` when traced).

    References:
        Celledoni, Fasso, Safstrom, Zanna, SIAM J. Sci. Comput. 30 (2008);
        Landau & Lifshitz, "Mechanics", section 37.
    """
    inertia, omega0, R0 = _validated(inertia, omega0, R0)
    # One compiled program, also under a transform applied outside `jit`
    # (`jax.jacfwd(free_rigid_body)`, `jax.vmap`): without it every
    # operation of the closed form and its derivative rule ran, and was
    # compiled, on its own (about 200 programs for a batched Jacobian).
    # Inside an outer `jit` the program is inlined.
    return _free_motion_program(inertia, omega0, t if is_traced(t) else np.asarray(t, dtype=inertia.dtype), R0)


def free_flow(inertia: Array, m: Array, h: Array) -> tuple[Array, Array]:
    """The exact torque-free flow over a time ``h`` (s), in the body frame:
    ``(Q, m_h)`` such that a body at ``(R, m)`` is at ``(R Q, m_h)`` after ``h``.

    ``inertia`` ``(3, 3)`` (kg m^2) and the body momentum ``m`` ``(3,)``
    (kg m^2/s) are taken as valid (no checks: this is a solver's inner step;
    `free_rigid_body` is the checked entry point).  ``Q`` is ``(3, 3)``.
    ``m_h`` is ``m`` plus its change over ``h`` from Jacobi's addition
    theorems (`_momentum_change`), so that rounding does not add up to a
    drift of the energy over many drifts; its derivative is that of the
    closed form's ``inertia omega(h)``.  From next to the intermediate axis
    ``m_h`` stays within 6.3e-15 ``|m|`` of a 34-digit integration for any
    ``h`` up to and through the flip (as `free_rigid_body`'s notes).
    """
    # One jitted function, like `free_rigid_body`'s: called on concrete values,
    # one compiled program rather than one per operation; traced (a solver's
    # step), traced once per shape and inlined by XLA.
    return _free_flow_program(inertia, m, h)


def _free_flow(inertia: Array, m: Array, h: Array) -> tuple[Array, Array]:
    omega0 = jnp.linalg.solve(inertia, m)
    Q, omega_h = _free_motion(inertia, omega0, h, jnp.eye(3, dtype=m.dtype))
    # The value is m + change; the derivative is that of the closed form's
    # own m(h) = inertia omega(h), whose tangent the JVP of Q computes anyway.
    # Differentiating the change itself took a second JVP of the closed
    # form, at 0 and h: the largest part of every differentiated splitting's
    # program.
    sg = jax.lax.stop_gradient
    return Q, _value_with_tangent_of(sg(m) + _momentum_change(sg(inertia), sg(m), sg(h)), inertia @ omega_h)


_free_flow_program = Program(_free_flow, jit=jax.jit)


@jax.custom_jvp
def _value_with_tangent_of(value: Array, x: Array) -> Array:
    """``value``, with the derivatives of ``x`` (same shape) under
    differentiation; undifferentiated, ``x`` is not computed at all."""
    return value


@_value_with_tangent_of.defjvp
def _value_with_tangent_of_jvp(primals, tangents):
    value, x = primals
    # The value itself carries x's derivative too (an exact zero that has
    # it), for a derivative taken of the primal of this JVP: without it the
    # primal of a jvp would have none (jax.grad of jax.jvp(f)[0]).
    zero = x - jax.lax.stop_gradient(x)
    return value + jnp.where(jnp.isfinite(zero), zero, 0.0), tangents[1]


def _momentum_change(inertia: Array, m: Array, h: Array) -> Array:
    """The change ``m(h) - m(0)`` ``(3,)`` (kg m^2/s, body frame) of a free
    body's momentum over ``h`` (s), with an error of order eps times the
    change, not eps times ``m``.

    Why: a drift that rebuilds ``m(h)`` from the closed form rounds the
    closed form's constants (amplitudes, modulus: functions of the
    invariants, which hardly change from one drift to the next) the same way
    in every drift, and the energy drifts linearly with the number of drifts
    (0.4 to 0.7 ulp a step with BlanesMoan4, one sign per run).  The
    difference of the closed form at 0 and h cancels that common part but
    keeps the rounding of two evaluations (a bias of 0.01 to 0.04 ulp a
    drift, still a drift over 10^6 steps).  Here the state enters directly:
    with ``(x, y, z) = (A1 cn a, A2 sn a, A3 dn a)`` in the working frame and
    ``b = lam h``, the addition theorems (DLMF 22.8.1-3) give each component's
    change as products of ``x, y, z`` with functions of ``b`` that are
    ``O(b)``, so every rounding is relative to the change.  Not
    differentiated: `free_flow` gives ``m_h`` the derivative of the closed
    form's ``inertia omega(h)`` (with its treatment of permanent rotations)."""
    c = _working_constants(inertia, jnp.linalg.solve(inertia, m))
    J1, J2, J3 = c["J"][0], c["J"][1], c["J"][2]
    x, y, z = c["x"], c["y"], c["z"]
    k2, r, rc, stat = c["k2"], c["r"], c["rc"], c["stat"]
    k2c = c["k2c"]
    sn_b, cn_b, dn_b, j, _ = _ellipj_reduced(c["lam"] * h, k2, k2c)
    sign = 1.0 - 2.0 * jnp.mod(j, 2.0)
    sb, cb, db = sign * sn_b, sign * cn_b, dn_b
    sb2 = sb * sb
    # cn a = x/A1; A1 = 0 only where m is along e3 (k = 0, no change).
    A1 = c["A1"]
    ca = jnp.where(A1 > 0, x / jnp.where(A1 > 0, A1, 1.0), 1.0)
    # The addition theorems' denominator 1 - k^2 sn^2 a sn^2 b is
    # D = dn^2 b + k^2 cn^2 a sn^2 b, and the factors of x, y and z below are
    # cn b - D, cn b dn b - D and dn b - D.  Each is written with cn^2 a, never
    # sn^2 a = 1 - cn^2 a, and with the small differences of b's functions in
    # closed form: cn b - dn^2 b = sn^2 b (k^2 cn b - k'^2)/(1 + cn b) and
    # dn b - cn b = k'^2 sn^2 b/(cn b + dn b) >= 0 where cn b > 0 (where
    # cn b <= 0 the plain differences have terms of one sign), and 1 - dn b =
    # k^2 sn^2 b/(1 + dn b).  All are O(b^2) for small b.  From a state next
    # to the intermediate axis (sn a = +-1 to rounding) D is about dn^2 b,
    # which falls like exp(-2 |lam h|): formed from sn a, or from terms of
    # size one, these factors erred by eps/D relative to |m| (1.7e-3 at
    # lam h = 17 on diag(1, 2, 3)).
    near = cb > 0
    cb_n = jnp.where(near, cb, 0.0)
    cb_less_db2 = jnp.where(near, sb2 * (k2 * cb - k2c) / (1.0 + cb_n), cb - db * db)
    db_less_cb = jnp.where(near, k2c * sb2 / jnp.where(near, cb_n + db, 1.0), db - cb)
    kcs = k2 * (ca * sb) ** 2
    D = db * db + kcs
    # A1/(A2 A3), A2/(A1 A3) and k^2 A3/(A1 A2), from the invariants: s is
    # 1/sqrt(J1 J2 J3 r Qv), so that lam = +-(J3 - J1) r Qv s.
    s = jax.lax.rsqrt(J1 * J2 * J3 * jnp.where(stat, 1.0, r * c["Qv"]))
    dw = jnp.stack(
        [
            x * (cb_less_db2 - kcs) - (r * J1 * s) * y * z * sb * db,
            -y * (db * db_less_cb + kcs) + (J2 * s) * x * z * sb,
            z * (k2 * sb2 * (db / (1.0 + db) - ca * ca)) - (rc * J3 * s) * x * y * sb * cb,
        ]
    ) / jnp.where(D > 0, D, 1.0)
    dw = jnp.where(stat | (D <= 0), 0.0, dw)
    return c["W"] @ dw


def symmetric_flow(I_a: Array, I_3: Array, k: int, m: Array, h: Array) -> tuple[Array, Array]:
    """`free_flow` for a symmetric body in closed form: two rotations.

    The body has moment ``I_3`` about the principal axis ``e_k`` (``k`` = 0,
    1 or 2, static) and ``I_a`` about every axis orthogonal to it.  Its kinetic
    energy ``|m|^2/(2 I_a) + m_k^2 (1/I_3 - 1/I_a)/2`` is a sum of two
    commuting parts: the first turns the body about ``m`` at ``|m|/I_a`` and
    leaves ``m`` fixed, the second turns it about ``e_k`` at
    ``Omega = m_k (1/I_3 - 1/I_a)`` and turns ``m`` back by the same angle.  So
    ``Q = exp(h m / I_a) exp(h Omega e_k)`` ``(3, 3)`` and
    ``m_h = exp(-h Omega e_k) m`` ``(3,)``; the turn about ``e_k`` mixes two
    columns (`so3.axis_turn`), which is cheaper than a second `so3.exp` and a
    3x3 product (a Blanes-Moan step on a heavy top has ten such drifts).
    """
    return _symmetric_flow_program(I_a, I_3, so3._axis_index(k, "symmetric_flow"), m, h)  # as in `free_flow`


def _symmetric_flow(I_a, I_3, k: int, m, h):
    phi = h * m[..., k] * (1.0 / I_3 - 1.0 / I_a)
    Q = so3.axis_turn(so3.exp((h / I_a) * m), k, phi)
    return so3.reorthonormalize(Q), so3.axis_turn(m, k, phi)


_symmetric_flow_program = Program(_symmetric_flow, jit=jax.jit, static_argnums=2)


def _free_motion(inertia: Array, omega0: Array, t, R0: Array) -> tuple[Array, Array]:
    """`free_rigid_body` on inputs that are already checked."""
    return _free_motion_ad(inertia, omega0, jnp.asarray(t, dtype=inertia.dtype), R0)


_free_motion_program = Program(_free_motion, jit=jax.jit)


@jax.custom_jvp
def _free_motion_ad(inertia: Array, omega0: Array, t: Array, R0: Array) -> tuple[Array, Array]:
    """`_closed_form` with the derivative of the flow at permanent rotations
    (`_permanent_rotation_jvp`)."""
    out, _ = _closed_form(inertia, omega0, t, R0)
    return out


def _jvp_of_live(f, primals, tangents, has_aux: bool = False):
    """`jax.jvp` of ``f`` in the inputs that have a tangent, the others held
    constant: an instantiated zero tangent would send the inertia's zero
    through eigh's derivative, which is NaN for equal moments (symmetric
    bodies and the sphere).  ``tangents`` may hold `SymbolicZero`s."""
    live = [not isinstance(d, SymbolicZero) for d in tangents]

    def of_live(*args):
        it = iter(args)
        return f(*[next(it) if lv else p for p, lv in zip(primals, live)])

    return jax.jvp(
        of_live,
        tuple(p for p, lv in zip(primals, live) if lv),
        tuple(d for d, lv in zip(tangents, live) if lv),
        has_aux=has_aux,
    )


def _free_motion_jvp(primals, tangents):
    # Off the permanent rotations: differentiate the closed form.
    live = [not isinstance(d, SymbolicZero) for d in tangents]
    (R, omega), (dR, domega), permanent = _jvp_of_live(_closed_form, primals, tangents, has_aux=True)
    # Within sqrt(eps) of a permanent rotation (m0 and omega0 at an angle
    # below it: rounding in a rotated inertia, say) the closed form's
    # derivative has lost about eps/angle to cancellation, and the
    # linearisation is off by about the angle: it is taken from there on.
    inertia, omega0 = primals[0], primals[1]
    m0 = inertia @ omega0
    tol = _near_permanent_tolerance(R.dtype)
    # (Norms, not squares: squared products of small momenta underflow in float32.)
    size = lambda v: jnp.sqrt(so3._sq(v))  # noqa: E731
    near = size(so3.cross(m0, omega0)) <= tol * size(m0) * size(omega0)
    permanent = permanent | near
    dense = [jnp.zeros_like(p) if not lv else d for p, d, lv in zip(primals, tangents, live)]
    sR, somega = _permanent_rotation_jvp(*primals, R, *dense, permanent)
    dR = jnp.where(permanent, sR, dR)
    domega = jnp.where(permanent, somega, domega)
    return (R, omega), (dR, domega)


_free_motion_ad.defjvp(_free_motion_jvp, symbolic_zeros=True)


def _near_permanent_tolerance(dtype) -> float:
    """The sine of the angle between m0 and omega0 below which a state counts
    as a permanent rotation (see `_free_motion_jvp`): sqrt(eps)."""
    return math.sqrt(float(jnp.finfo(dtype).eps))


def _sinc_family(z: Array) -> tuple[Array, Array, Array]:
    """``(sigma, rho, phi)`` of ``z = s t^2`` (any sign): the entire functions
    ``sigma = sum (-z)^k/(2k+1)!``, ``rho = sum (-z)^k/(2k+2)!``,
    ``phi = sum (-z)^k/(2k+3)!``, i.e. ``sin(r)/r``, ``(1 - cos r)/r^2`` and
    ``(r - sin r)/r^3`` with ``r = sqrt(z)`` (``sinh`` and ``cosh`` for
    ``z < 0``), by their series for ``|z| < 1``."""
    small = jnp.abs(z) < 1.0
    zs = jnp.where(small, z, 0.0)
    sigma = rho = phi = jnp.zeros_like(z)
    term = jnp.ones_like(z)
    # 12 terms: the first omitted one of phi is 1/27! < 1e-28.
    for k in range(12):
        sigma = sigma + term * (1.0 / math.factorial(2 * k + 1))
        rho = rho + term * (1.0 / math.factorial(2 * k + 2))
        phi = phi + term * (1.0 / math.factorial(2 * k + 3))
        term = term * (-zs)
    pos = z > 0
    zl = jnp.where(small, 1.0, jnp.abs(z))
    r = jnp.sqrt(zl)
    sin, half = jnp.where(pos, jnp.sin(r), jnp.sinh(r)), jnp.where(pos, jnp.sin(0.5 * r), jnp.sinh(0.5 * r))
    sign = jnp.where(pos, 1.0, -1.0)
    sigma_l = sin / r
    rho_l = 2.0 * half * half / zl
    phi_l = sign * (r - sin) / (zl * r)
    return (jnp.where(small, sigma, sigma_l), jnp.where(small, rho, rho_l), jnp.where(small, phi, phi_l))


def _permanent_rotation_jvp(inertia, omega0, t, R0, R, d_inertia, d_omega0, dt, dR0, permanent):
    """Tangent of ``(R(t), omega(t))`` at a permanent rotation: ``m0`` an
    eigenvector of the inertia (any ``m0`` of a sphere, ``m0 = 0`` too).

    There the closed form is not differentiable in its own variables (the
    phase of ``m`` about the axis, the amplitude ``|m_perp|``), although the
    flow is smooth.  The tangent comes from the variational equation instead,
    which has constant coefficients there (``omega = omega0`` and ``m = m0``
    are constant).  With ``R -> R (1 + hat(xi))``, ``m -> m + dm`` and
    ``f = d(I^-1) m0`` (the inertia's own tangent):

        dm' = A dm + m0 x f,   A = hat(m0) I^-1 - hat(omega0),
        xi' = -omega0 x xi + I^-1 dm + f.

    ``A = |m0| N`` with ``N = hat(e) (I^-1 - 1/mu)``, ``e = m0/|m0|``,
    ``I e = mu e``, and ``N^2 = -delta (1 - e e^T)`` (``N`` turns the plane
    normal to ``e`` and kills ``e``), so ``exp(t A) = 1 + t sigma A + t^2 rho
    A^2`` with the functions of ``z = |m0|^2 delta t^2`` of `_sinc_family`.
    ``xi``'s component along ``e`` grows linearly; the rest follows from the
    conservation of the spatial momentum, ``xi x m0 + dm(t) = exp(-t
    hat(omega0)) dm(0)``, written so that nothing is divided by ``|m0|``: at
    rest ``xi = t (I^-1 dm(0) + f)`` and ``dm(t) = dm(0)``.  Shapes as
    `_closed_form`'s; the values at other states are finite and unused.
    """
    dtype = R.dtype
    I = 0.5 * (inertia + inertia.T)
    Iinv = jnp.linalg.inv(I)
    m = inertia @ omega0
    dm0 = d_inertia @ omega0 + inertia @ d_omega0
    f = -Iinv @ (0.5 * (d_inertia + d_inertia.T)) @ omega0
    G2 = jnp.sum(m * m)
    pos = permanent & (G2 > 0)
    G = jnp.where(pos, jnp.sqrt(jnp.where(pos, G2, 1.0)), 0.0)
    e = jnp.where(pos, m / jnp.where(pos, G, 1.0), jnp.array([1.0, 0.0, 0.0], dtype))
    E = so3.hat(e)
    mu = e @ I @ e
    N = E @ (Iinv - jnp.eye(3, dtype=dtype) / mu)
    N2 = N @ N
    delta = -0.5 * jnp.trace(N2)
    w = G / mu

    tt = t[..., None]
    sig, rho, phi = _sinc_family(G2 * jnp.where(permanent, delta, 0.0) * t * t)
    sig_w, rho_w, _ = _sinc_family((w * t) ** 2)
    sig, rho, phi, sig_w, rho_w = (a[..., None] for a in (sig, rho, phi, sig_w, rho_w))
    Ndm, N2dm = N @ dm0, N2 @ dm0
    ef = jnp.cross(e, f)
    Nef, N2ef = N @ ef, N2 @ ef
    # exp(t A) dm0 - dm0 and int_0^t exp(s A) ds (m0 x f), both over |m0|.
    growth = tt * sig * Ndm + tt**2 * rho * G * N2dm
    forced = tt * ef + tt**2 * rho * G * Nef + tt**3 * phi * G2 * N2ef
    dm_t = dm0 + G * (growth + forced)
    # (exp(-t hat(omega0)) - 1) dm0 / |m0|.
    Edm = E @ dm0
    turn = -(tt * sig_w / mu) * Edm + (tt**2 * rho_w * w / mu) * (E @ Edm)
    v = turn - growth - forced  # (xi x m0)/|m0|
    xi = jnp.cross(e, v) + (tt * (e @ (Iinv @ dm0) + e @ f)) * e + dt[..., None] * omega0
    # Q = R0^T R = exp(t hat(omega0)).
    Ew = tt * sig_w * w
    Q = jnp.eye(3, dtype=dtype) + Ew[..., None] * E + (tt**2 * rho_w * w * w)[..., None] * (E @ E)
    dR = dR0 @ Q + R @ so3.hat(xi)
    domega = dm_t @ Iinv.T + f
    return dR, domega


def _closed_form(inertia: Array, omega0: Array, t: Array, R0: Array):
    """The closed form: ``((R, omega), permanent)``, ``permanent`` flagging
    a permanent rotation (`_permanent_rotation_jvp`)."""
    c = _working_constants(inertia, omega0)
    dtype = c["dtype"]
    J, W = c["J"], c["W"]
    J1, J2, J3 = J[0], J[1], J[2]
    x, y, z = c["x"], c["y"], c["z"]
    A1, A2, A3, lam = c["A1"], c["A2"], c["A3"], c["lam"]
    k2, k2c, r, Qv = c["k2"], c["k2c"], c["r"], c["Qv"]
    G, twoT, sep, stat = c["G"], c["twoT"], c["sep"], c["stat"]
    Gs = jnp.where(G > 0, G, 1.0)
    m0 = jnp.stack([x, y, z])

    # Sine and cosine of the initial amplitude phi0 in [-pi/2, pi/2] (x >= 0):
    # sn u0 = y/A2 and cn u0 = x/A1, normalised against rounding.  Not through
    # phi0 = atan2(...) and its cos: next to the intermediate axis cn u0 ~ 1e-9
    # would keep only the absolute precision of phi0 (1e-7 relative), and u0
    # = F(phi0) with it; the flow amplifies that like exp(|lambda| t).  A1 = 0
    # means m = G e3 (k = 0): any phase will do.
    has_a = (A1 > 0) & (A2 > 0)
    sa = jnp.where(has_a, y / jnp.where(has_a, A2, 1.0), 0.0)
    ca = jnp.where(has_a, x / jnp.where(has_a, A1, 1.0), 1.0)
    nrm = jnp.sqrt(sa * sa + ca * ca)
    s0, c0 = sa / nrm, ca / nrm
    # Exactly at the intermediate-axis equilibrium (c0 = 0 on the separatrix)
    # u0 would be infinite; that point is flagged `stat` and replaced below.
    regular = ~stat
    c0s = jnp.where(regular, c0, 1.0)
    s0s = jnp.where(regular, s0, 0.0)
    # u0 = F(phi0 | k^2) and Pi(n; phi0 | k^2) below take phi0 through sn and
    # cn, and Carlson's forms give their derivative in phi0 (1/dn0, over 1 -
    # n sn0^2 for Pi) as 0 * inf where cn u0 = 0 exactly (m0 with no
    # component along the working e1, as omega0 = (1, 0.05, 0) on the
    # T-handle).  So sn and cn enter them without derivative, and phi0's own
    # derivative (that of atan2, exact: phi0's value is not used) is added
    # times those integrands.
    sg = jax.lax.stop_gradient
    s0f, c0f = sg(s0s), sg(c0s)
    phi0 = jnp.arctan2(sa, ca)
    dphi0 = jnp.where(regular, phi0 - sg(phi0), 0.0)
    # 1 - k^2 sin^2 = k'^2 + k^2 cos^2: no cancellation near the separatrix.
    delta0s = jnp.where(regular, k2c + k2 * c0f * c0f, 1.0)
    dn0 = jnp.sqrt(delta0s)
    u0 = s0f * elliprf(c0f * c0f, delta0s, jnp.ones_like(c0s)) + dphi0 / dn0

    u = lam * t + u0
    sn_r, cn_r, dn_r, j, K = _ellipj_reduced(u, k2, k2c)
    sign = 1.0 - 2.0 * jnp.mod(j, 2.0)
    m_t = jnp.stack([A1 * sign * cn_r, A2 * sign * sn_r, A3 * jnp.broadcast_to(dn_r, sign.shape)], axis=-1)
    m_t = jnp.where(stat, jnp.broadcast_to(m0, m_t.shape), m_t)

    # Precession angle (module docstring).
    rs = jnp.where(r > 0, r, 1.0)
    n = -(J3 / J1) * c["rc"] / rs
    coef = jnp.sqrt(J2 / (J1 * J3 * jnp.where(stat, 1.0, r * Qv)))
    # b/A1 = sqrt(A1^2 + A3^2 k^2)/A1 = sqrt(1 - n) exactly, so Theta does not
    # degenerate when A1 -> 0 (m along e3).
    q = jnp.sqrt(1.0 - n)
    theta0 = jnp.arctan2(q * s0s, c0s)
    # One call for Pi at u(t), at u0 and the complete Pi (phi = pi/2): a single
    # traced Carlson evaluation keeps compile times down.
    one = jnp.ones((1,), dtype)
    zero = jnp.zeros((1,), dtype)
    flat = lambda a: jnp.ravel(jnp.broadcast_to(a, t.shape))  # noqa: E731
    pis = _pi_reduced(
        jnp.concatenate([flat(sn_r), s0f * one, one]),
        jnp.concatenate([flat(cn_r), c0f * one, zero]),
        jnp.concatenate([flat(dn_r * dn_r), delta0s * one, jnp.where(sep, 1.0, k2c) * one]),
        n,
    )
    pi0 = pis[-2] + dphi0 / ((1.0 - n * s0f * s0f) * dn0)
    pi_c = pis[-1]
    # On the separatrix j == 0 always; avoid inf * 0.
    pi_wind = jnp.where(sep, 0.0, 2.0 * j * pi_c)
    pi_t = pis[:-2].reshape(t.shape) + pi_wind
    theta_t = jnp.arctan2(q * sn_r, cn_r) + math.pi * j
    psi_ell = G * t / J3 + coef * (G * (pi_t - pi0) - (A3 / q) * (theta_t - theta0))
    # With J1 = J2 (r = 1, k = 0 whatever omega0) m3 = z is constant and psi'
    # is too.  Taken from psi_ell instead, it is the difference of two terms
    # of size G t / J3, which a thin rod (J3 = I1 small) would lose to
    # rounding: 2.2e-9 in R at I = (1e-6, 1, 1), t = 5 s.
    psi_sym = (twoT + Gs * (z / J3)) / (Gs + z) * t
    psi = jnp.where(stat, twoT / Gs * t, jnp.where(r == 1.0, psi_sym, psi_ell))

    P0 = _minimal_rotation(m0, Gs)
    Pt = _minimal_rotation(m_t, jnp.broadcast_to(Gs, t.shape))
    S0 = R0 @ W @ P0.T
    R = S0 @ _rz(psi) @ Pt @ W.T
    omega = (m_t / J) @ W.T
    # m0 an eigenvector of the inertia: on the intermediate axis or in the
    # plane of two equal moments (stat), along the working e3 (P = 0; this
    # includes rest), or any m0 of a sphere (lam = 0).
    permanent = stat | (c["P"] <= 0) | (lam == 0)
    return (R, omega), permanent


def flip_interval(inertia: ArrayLike, omega0: ArrayLike) -> Array:
    """Time between successive Dzhanibekov flips (s), or ``inf`` if the body
    never flips.

    What a flip is.  Let ``I1 < I2 < I3`` be the principal moments and ``m``
    the body angular momentum; the body axis closest to the fixed spatial
    momentum ``L`` is the signed principal axis ``+-e_i`` with the largest
    ``|m_i|``.  A flip is a reversal of the intermediate axis ``e2`` with
    respect to ``L``: ``e2`` is the axis closest to ``L`` (``|m2| > |m1|``
    and ``|m2| > |m3|``), and later ``-e2`` is.  Between the two, ``m2``
    changes sign once.

    Whether a body flips is a property of its orbit on the momentum sphere.
    Every orbit circulates around the smallest or the largest axis, and on
    every one ``m2`` oscillates; the orbit flips if and only if at the peak of
    that oscillation, where ``|m2|`` is largest and the other oscillating
    component is zero, ``|m2|`` exceeds the circulation axis's component:
    ``max_t m2^2 > |m|^2/2``, the orbit comes within 45 degrees of the
    intermediate axis.  Then flips recur every half period of ``m(t)``,
    ``2 K(k)/|lambda|``, which is also the time between successive sign
    changes of ``m2``.  Orbits near the smallest or the largest axis, on
    which ``e2`` never gets closest to ``L``, do not flip (``inf``), although
    ``m2`` still oscillates about zero.  Also ``inf``: a steady rotation
    about any principal axis, the separatrix (its one reversal takes
    infinitely long), a body with two equal moments (no distinct
    intermediate axis; the sphere too) and ``omega0 = 0``.

    Args:
        inertia: ``(3, 3)`` symmetric positive definite, or ``(3,)`` principal
            moments (kg m^2).
        omega0: initial body angular velocity ``(3,)`` (rad/s), finite.

    Returns:
        Scalar: the flip interval (s), or ``inf``.

    Raises:
        ValueError: invalid inertia or ``omega0``, as for `free_rigid_body`.

    Example:
        >>> flip_interval(lierk.inertia.tee_handle(), [1.0, 0.05, 0.0])  # about 23.63 s
        >>> flip_interval(lierk.inertia.tee_handle(), [0.05, 0.0, 1.0])  # inf: near the largest axis

    References:
        Landau & Lifshitz, "Mechanics", section 37 (period ``4K/lambda``).
    """
    inertia, omega0, _ = _validated(inertia, omega0)
    # One compiled program, traced or not (see `free_rigid_body`).
    return _flip_interval_program(inertia, omega0)


def _flip_interval(inertia: Array, omega0: Array) -> Array:
    """`flip_interval` of a checked ``inertia`` ``(3, 3)`` and ``omega0`` ``(3,)``."""
    c = _working_constants(inertia, omega0)
    J = c["J"]
    regular = ~(c["stat"] | c["sep"])
    # In the working frame (circulation about e3, J2 the intermediate moment)
    # m2^2 peaks at A2^2 = J2 P/r, where m1 = 0 and m3^2 = A3^2 k'^2 = J3 d/r:
    # e2 is ever closest to L iff J2 P > J3 d.
    flips = regular & (J[0] != J[1]) & (J[1] != J[2]) & (J[1] * c["P"] > J[2] * c["d"])
    K = ellipk(jnp.where(flips, c["k2"], 0.5), jnp.where(flips, c["k2c"], 0.5))
    lam = jnp.where(flips, jnp.abs(c["lam"]), 1.0)
    return jnp.where(flips, 2.0 * K / lam, jnp.inf)


_flip_interval_program = Program(_flip_interval, jit=jax.jit)


def sphere(omega0: ArrayLike, t: ArrayLike, R0: ArrayLike | None = None) -> tuple[Array, Array]:
    """Spherical body (or any permanent rotation): ``R(t) = R0 exp(t hat(omega0))``.

    Args:
        omega0: body angular velocity ``(3,)`` (rad/s), constant.
        t: time(s) (s), scalar or shape ``S``.
        R0: initial attitude ``(3, 3)``; identity if ``None``.

    Returns:
        ``(R, omega)``: shapes ``S + (3, 3)`` and ``S + (3,)``.

    References:
        Landau & Lifshitz, "Mechanics", section 37.
    """
    omega0 = jnp.asarray(omega0, dtype=_dtype(omega0))
    t = jnp.asarray(t, dtype=omega0.dtype)
    R0 = jnp.eye(3, dtype=omega0.dtype) if R0 is None else jnp.asarray(R0, dtype=omega0.dtype)
    R = R0 @ so3.exp(t[..., None] * omega0)
    return R, jnp.broadcast_to(omega0, t.shape + (3,))
