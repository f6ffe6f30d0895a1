"""The native anchors for throughput: lierk's RKMK4 on the momentum-state free
body, written out natively, one thread per core.

- `rkmk4_final_R`: numba, one body at a time (the whole state of a body in
  registers, no SIMD across bodies).
- `rkmk4_soa_final_R`: numba, structure of arrays: blocks of 64 bodies whose
  state stays in L1 for all steps, the loop over the bodies of a block
  innermost so that LLVM vectorises it, threads across blocks; diagonal
  inertia and Taylor polynomials for the sin/cos of the half-angle (exact to
  rounding below 1 rad per step), as the C anchor has them.
- `c_soa_final_R`: the C anchor of issue 24 (``anchors/rkmk4_soa.c``: the
  same structure of arrays with OpenMP), built by `build_c_soa` with its own
  build line when a C compiler with OpenMP is present.

The same method, step for step, as ``lierk.solve(lierk.FreeRigidBody(I,
omega0), lierk.RKMK4(), ...)``: body form, the classical RK4 tableau applied
to ``u' = omega + 1/2 u x omega + 1/12 u x (u x omega)`` (dexpinv truncated at
``ad_u^2``), Euler's equations ``m' = m x I^{-1} m`` for the body momentum
through the same tableau, ``R_{n+1} = R_n exp(hat(u_1))`` by Rodrigues with
one sin/cos pair of ``theta/2``, and in float32 the one Newton-Schulz step of
`lierk.so3.right_exp`.  What it leaves out is what lierk adds around the
steps: result codes, the invariant-drift check and saving.

Scripts import it as ``native`` (they run as ``python benchmarks/NAME.py``).
"""

from __future__ import annotations

import ctypes
import functools
import os
import pathlib
import shutil
import subprocess
import tempfile

import numpy as np

try:
    import numba
except ImportError:  # the bench extra installs it
    numba = None


def _helpers(F):
    """What both kernels share, for the float type ``F``: ``cross``, ``slopes``,
    ``times_exp`` (``R exp(hat(u))`` from ``x = |u|^2`` and the coefficients
    ``A``, ``B`` of ``u``) and ``newton_schulz`` (lierk's float32 step ``R (3 I - R^T R) / 2``),
    on scalars (9 for a matrix, row by row), inlined so that LLVM keeps them
    in registers."""
    half, twelfth, one, onehalf = F(0.5), F(1 / 12), F(1.0), F(1.5)

    @numba.njit(inline="always")
    def cross(a0, a1, a2, b0, b1, b2):
        return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0

    @numba.njit(inline="always")
    def slopes(y0, y1, y2, u0, u1, u2, w0, w1, w2):
        """``(k, m')`` of one stage at momentum ``y``, algebra point ``u`` and
        ``omega = w``: ``k = dexpinv(-u, omega)`` to ad^2, ``m' = y x omega``."""
        d0, d1, d2 = cross(y0, y1, y2, w0, w1, w2)
        a0, a1, a2 = cross(u0, u1, u2, w0, w1, w2)
        b0, b1, b2 = cross(u0, u1, u2, a0, a1, a2)
        return w0 + half * a0 + twelfth * b0, w1 + half * a1 + twelfth * b1, w2 + half * a2 + twelfth * b2, d0, d1, d2

    @numba.njit(inline="always")
    def times_exp(r00, r01, r02, r10, r11, r12, r20, r21, r22, u0, u1, u2, x, A, B):
        # exp(hat(u)) = (1 - B theta^2) I + A hat(u) + B u u^T, x = theta^2
        c = one - B * x
        e00, e11, e22 = c + B * u0 * u0, c + B * u1 * u1, c + B * u2 * u2
        b01, b02, b12 = B * u0 * u1, B * u0 * u2, B * u1 * u2
        e01, e10 = b01 - A * u2, b01 + A * u2
        e02, e20 = b02 + A * u1, b02 - A * u1
        e12, e21 = b12 - A * u0, b12 + A * u0
        return (
            r00 * e00 + r01 * e10 + r02 * e20,
            r00 * e01 + r01 * e11 + r02 * e21,
            r00 * e02 + r01 * e12 + r02 * e22,
            r10 * e00 + r11 * e10 + r12 * e20,
            r10 * e01 + r11 * e11 + r12 * e21,
            r10 * e02 + r11 * e12 + r12 * e22,
            r20 * e00 + r21 * e10 + r22 * e20,
            r20 * e01 + r21 * e11 + r22 * e21,
            r20 * e02 + r21 * e12 + r22 * e22,
        )

    @numba.njit(inline="always")
    def newton_schulz(r00, r01, r02, r10, r11, r12, r20, r21, r22):
        s00 = r00 * r00 + r10 * r10 + r20 * r20
        s11 = r01 * r01 + r11 * r11 + r21 * r21
        s22 = r02 * r02 + r12 * r12 + r22 * r22
        s01 = r00 * r01 + r10 * r11 + r20 * r21
        s02 = r00 * r02 + r10 * r12 + r20 * r22
        s12 = r01 * r02 + r11 * r12 + r21 * r22
        return (
            onehalf * r00 - half * (r00 * s00 + r01 * s01 + r02 * s02),
            onehalf * r01 - half * (r00 * s01 + r01 * s11 + r02 * s12),
            onehalf * r02 - half * (r00 * s02 + r01 * s12 + r02 * s22),
            onehalf * r10 - half * (r10 * s00 + r11 * s01 + r12 * s02),
            onehalf * r11 - half * (r10 * s01 + r11 * s11 + r12 * s12),
            onehalf * r12 - half * (r10 * s02 + r11 * s12 + r12 * s22),
            onehalf * r20 - half * (r20 * s00 + r21 * s01 + r22 * s02),
            onehalf * r21 - half * (r20 * s01 + r21 * s11 + r22 * s12),
            onehalf * r22 - half * (r20 * s02 + r21 * s12 + r22 * s22),
        )

    return cross, slopes, times_exp, newton_schulz


def _make_kernel(F):
    """The kernel for the float type ``F`` (np.float32 or np.float64): every
    constant is an ``F`` so that float32 stays float32."""
    half, sixth, one, two = F(0.5), F(1 / 6), F(1.0), F(2.0)
    # lierk.so3's thresholds on theta^2 for the series
    small = F(1e-1) if F is np.float32 else F(1e-2)
    newton_schulz = F is np.float32
    _, slopes, times_exp, ns_step = _helpers(F)

    @numba.njit(inline="always")
    def stage(Iinv, y0, y1, y2, u0, u1, u2):
        """``(k, m')`` of one stage at momentum ``y`` and algebra point ``u``."""
        w0 = Iinv[0, 0] * y0 + Iinv[0, 1] * y1 + Iinv[0, 2] * y2
        w1 = Iinv[1, 0] * y0 + Iinv[1, 1] * y1 + Iinv[1, 2] * y2
        w2 = Iinv[2, 0] * y0 + Iinv[2, 1] * y1 + Iinv[2, 2] * y2
        return slopes(y0, y1, y2, u0, u1, u2, w0, w1, w2)

    # Scalars only, so that LLVM keeps the whole state in registers.
    @numba.njit(parallel=True, fastmath=False)
    def kernel(inertia, Iinv, omega0, h, n_steps, R_out):  # (3, 3), (3, 3), (B, 3), F, int, (B, 3, 3)
        hh, h6 = half * h, sixth * h
        for b in numba.prange(omega0.shape[0]):
            o0, o1, o2 = omega0[b, 0], omega0[b, 1], omega0[b, 2]
            m0 = inertia[0, 0] * o0 + inertia[0, 1] * o1 + inertia[0, 2] * o2
            m1 = inertia[1, 0] * o0 + inertia[1, 1] * o1 + inertia[1, 2] * o2
            m2 = inertia[2, 0] * o0 + inertia[2, 1] * o1 + inertia[2, 2] * o2
            r00, r01, r02 = one, F(0.0), F(0.0)
            r10, r11, r12 = F(0.0), one, F(0.0)
            r20, r21, r22 = F(0.0), F(0.0), one
            z = F(0.0)
            for _ in range(n_steps):
                k10, k11, k12, d10, d11, d12 = stage(Iinv, m0, m1, m2, z, z, z)
                k20, k21, k22, d20, d21, d22 = stage(
                    Iinv, m0 + hh * d10, m1 + hh * d11, m2 + hh * d12, hh * k10, hh * k11, hh * k12
                )
                k30, k31, k32, d30, d31, d32 = stage(
                    Iinv, m0 + hh * d20, m1 + hh * d21, m2 + hh * d22, hh * k20, hh * k21, hh * k22
                )
                k40, k41, k42, d40, d41, d42 = stage(
                    Iinv, m0 + h * d30, m1 + h * d31, m2 + h * d32, h * k30, h * k31, h * k32
                )
                u0 = h6 * (k10 + two * k20 + two * k30 + k40)
                u1 = h6 * (k11 + two * k21 + two * k31 + k41)
                u2 = h6 * (k12 + two * k22 + two * k32 + k42)
                m0 = m0 + h6 * (d10 + two * d20 + two * d30 + d40)
                m1 = m1 + h6 * (d11 + two * d21 + two * d31 + d41)
                m2 = m2 + h6 * (d12 + two * d22 + two * d32 + d42)
                x = u0 * u0 + u1 * u1 + u2 * u2
                if x < small:  # the series of lierk.so3.exp_coefficients
                    A = one - x / F(6.0) * (one - x / F(20.0) * (one - x / F(42.0) * (one - x / F(72.0))))
                    B = half - x / F(24.0) * (one - x / F(30.0) * (one - x / F(56.0) * (one - x / F(90.0))))
                else:
                    theta = np.sqrt(x)
                    sn, cs = np.sin(half * theta), np.cos(half * theta)
                    A = two * sn * cs / theta
                    B = two * sn * sn / x
                r00, r01, r02, r10, r11, r12, r20, r21, r22 = times_exp(
                    r00, r01, r02, r10, r11, r12, r20, r21, r22, u0, u1, u2, x, A, B
                )
                if newton_schulz:  # as lierk.so3.right_exp does in float32
                    r00, r01, r02, r10, r11, r12, r20, r21, r22 = ns_step(r00, r01, r02, r10, r11, r12, r20, r21, r22)
            R_out[b, 0, 0], R_out[b, 0, 1], R_out[b, 0, 2] = r00, r01, r02
            R_out[b, 1, 0], R_out[b, 1, 1], R_out[b, 1, 2] = r10, r11, r12
            R_out[b, 2, 0], R_out[b, 2, 1], R_out[b, 2, 2] = r20, r21, r22

    return kernel


_KERNELS: dict = {}


def _numba_call(cache: dict, make, omegas, threads: int):
    """``(kernel, F, out)`` for a numba kernel call on ``omegas`` ``(B, 3)``:
    the kernel for their dtype ``F`` (``make(F)`` compiles it on first use,
    kept in ``cache``), ``threads`` threads set, and the ``(B, 3, 3)`` output."""
    if numba is None:
        raise ImportError("the native anchor needs numba: pip install 'lierk[bench]'")
    F = np.dtype(omegas.dtype).type
    if F not in cache:
        cache[F] = make(F)
    numba.set_num_threads(threads)
    return cache[F], F, np.empty((omegas.shape[0], 3, 3), F)


def rkmk4_final_R(inertia, omegas, h: float, n_steps: int, threads: int) -> np.ndarray:
    """``R(n_steps h)`` ``(B, 3, 3)`` of RKMK4 from ``R0 = I`` for each body
    angular velocity in ``omegas`` ``(B, 3)`` (rad/s), inertia ``(3, 3)``
    (kg m^2), step ``h`` (s), on ``threads`` threads; in the dtype of
    ``omegas``.  The first call for a dtype compiles."""
    kernel, F, out = _numba_call(_KERNELS, _make_kernel, omegas, threads)
    inertia = np.asarray(inertia, np.float64)
    Iinv = np.linalg.inv(inertia).astype(F)
    kernel(inertia.astype(F), Iinv, np.ascontiguousarray(omegas), F(h), int(n_steps), out)
    return out


# Bodies per block in the structure-of-arrays kernels: 64 bodies' state (12
# numbers each) is 6 kB in float64, well inside L1.
BLK = 64


def _make_soa_kernel(F):
    """The structure-of-arrays kernel for ``F``: the C anchor's method and
    layout, with lierk's float32 Newton-Schulz step when ``F`` is float32."""
    half, sixth, one, two = F(0.5), F(1 / 6), F(1.0), F(2.0)
    # Taylor coefficients of sin(z)/z and cos(z) as the C anchor nests them
    s6, s20, s42, s72, s110, s156 = F(6.0), F(20.0), F(42.0), F(72.0), F(110.0), F(156.0)
    c2, c12, c30, c56, c90, c132 = F(2.0), F(12.0), F(30.0), F(56.0), F(90.0), F(132.0)
    tiny = F(1e-300) if F is np.float64 else F(1e-30)
    newton_schulz = F is np.float32
    cross, slopes, times_exp, ns_step = _helpers(F)

    @numba.njit(inline="always")
    def stage(I0, I1, I2, y0, y1, y2, u0, u1, u2):
        """`_make_kernel`'s stage with the inverse inertia diagonal."""
        return slopes(y0, y1, y2, u0, u1, u2, I0 * y0, I1 * y1, I2 * y2)

    @numba.njit(parallel=True, fastmath=False)
    def kernel(inv_diag, omega0, h, n_steps, R_out):  # (3,), (B, 3), F, int, (B, 3, 3)
        n_bodies = omega0.shape[0]
        I0, I1, I2 = inv_diag[0], inv_diag[1], inv_diag[2]
        hh, h6 = half * h, sixth * h
        for blk in numba.prange((n_bodies + BLK - 1) // BLK):
            b0 = blk * BLK
            n = min(BLK, n_bodies - b0)
            m = np.empty((3, BLK), F)
            r = np.zeros((9, BLK), F)
            for b in range(n):
                m[0, b] = omega0[b0 + b, 0] / I0
                m[1, b] = omega0[b0 + b, 1] / I1
                m[2, b] = omega0[b0 + b, 2] / I2
                r[0, b] = one
                r[4, b] = one
                r[8, b] = one
            for _ in range(n_steps):
                for b in range(n):  # the vectorised loop: bodies side by side
                    y0, y1, y2 = m[0, b], m[1, b], m[2, b]
                    # stage 1 (u = 0: k = omega)
                    w0, w1, w2 = I0 * y0, I1 * y1, I2 * y2
                    d10, d11, d12 = cross(y0, y1, y2, w0, w1, w2)
                    k10, k11, k12 = w0, w1, w2
                    k20, k21, k22, d20, d21, d22 = stage(
                        I0, I1, I2, y0 + hh * d10, y1 + hh * d11, y2 + hh * d12, hh * k10, hh * k11, hh * k12
                    )
                    k30, k31, k32, d30, d31, d32 = stage(
                        I0, I1, I2, y0 + hh * d20, y1 + hh * d21, y2 + hh * d22, hh * k20, hh * k21, hh * k22
                    )
                    k40, k41, k42, d40, d41, d42 = stage(
                        I0, I1, I2, y0 + h * d30, y1 + h * d31, y2 + h * d32, h * k30, h * k31, h * k32
                    )
                    U0 = h6 * (k10 + two * k20 + two * k30 + k40)
                    U1 = h6 * (k11 + two * k21 + two * k31 + k41)
                    U2 = h6 * (k12 + two * k22 + two * k32 + k42)
                    m[0, b] = y0 + h6 * (d10 + two * d20 + two * d30 + d40)
                    m[1, b] = y1 + h6 * (d11 + two * d21 + two * d31 + d41)
                    m[2, b] = y2 + h6 * (d12 + two * d22 + two * d32 + d42)
                    x = U0 * U0 + U1 * U1 + U2 * U2
                    th = np.sqrt(x) + tiny
                    zz = half * th
                    z2 = zz * zz
                    sn = zz * (
                        one
                        - z2
                        / s6
                        * (one - z2 / s20 * (one - z2 / s42 * (one - z2 / s72 * (one - z2 / s110 * (one - z2 / s156)))))
                    )
                    cs = one - z2 / c2 * (
                        one - z2 / c12 * (one - z2 / c30 * (one - z2 / c56 * (one - z2 / c90 * (one - z2 / c132))))
                    )
                    A = two * sn * cs / th
                    Bc = two * sn * sn / (th * th)
                    r00, r01, r02, r10, r11, r12, r20, r21, r22 = times_exp(
                        r[0, b],
                        r[1, b],
                        r[2, b],
                        r[3, b],
                        r[4, b],
                        r[5, b],
                        r[6, b],
                        r[7, b],
                        r[8, b],
                        U0,
                        U1,
                        U2,
                        x,
                        A,
                        Bc,
                    )
                    if newton_schulz:  # as lierk.so3.right_exp does in float32
                        r00, r01, r02, r10, r11, r12, r20, r21, r22 = ns_step(
                            r00, r01, r02, r10, r11, r12, r20, r21, r22
                        )
                    r[0, b], r[1, b], r[2, b] = r00, r01, r02
                    r[3, b], r[4, b], r[5, b] = r10, r11, r12
                    r[6, b], r[7, b], r[8, b] = r20, r21, r22
            for b in range(n):
                for k in range(9):
                    R_out[b0 + b, k // 3, k % 3] = r[k, b]

    return kernel


_SOA_KERNELS: dict = {}


def _inverse_diagonal(inertia) -> np.ndarray:
    inertia = np.asarray(inertia, np.float64)
    if np.any(inertia != np.diag(np.diag(inertia))):
        raise ValueError(
            f"the structure-of-arrays anchors take a diagonal inertia (principal axes), got {inertia.tolist()}"
        )
    return 1.0 / np.diag(inertia)


def rkmk4_soa_final_R(inertia, omegas, h: float, n_steps: int, threads: int) -> np.ndarray:
    """As `rkmk4_final_R`, by the structure-of-arrays numba kernel; ``inertia``
    must be diagonal.  The first call for a dtype compiles."""
    kernel, F, out = _numba_call(_SOA_KERNELS, _make_soa_kernel, omegas, threads)
    kernel(_inverse_diagonal(inertia).astype(F), np.ascontiguousarray(omegas), F(h), int(n_steps), out)
    return out


# The C anchor's build line (its header) plus what a shared library needs.
C_FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fopenmp", "-shared", "-fPIC")
_C_SOURCE = pathlib.Path(__file__).parent / "anchors" / "rkmk4_soa.c"


@functools.lru_cache(maxsize=1)
def _c_soa() -> tuple:
    """``(function, build line, None)`` once built, or ``(None, None, why
    not)``; the build (or its failure) happens once per process."""
    cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        return None, None, "no C compiler (gcc or cc) on PATH"
    lib = pathlib.Path(tempfile.mkdtemp(prefix="lierk-anchor-")) / "librkmk4_soa.so"
    run = subprocess.run([cc, *C_FLAGS, str(_C_SOURCE), "-lm", "-o", str(lib)], capture_output=True, text=True)
    if run.returncode != 0:
        return None, None, f"{cc} failed: {run.stderr.strip()[:300]}"
    f = ctypes.CDLL(str(lib)).rkmk4_soa_run
    f.restype = None
    f.argtypes = [
        ctypes.c_int,
        ctypes.c_void_p,
        ctypes.c_void_p,
        ctypes.c_double,
        ctypes.c_int,
        ctypes.c_int,
        ctypes.c_void_p,
    ]
    return f, f"{os.path.basename(cc)} {' '.join(C_FLAGS)}", None


def build_c_soa() -> str | None:
    """Build the C anchor; None when built, or why it could not be (no
    compiler, no OpenMP, a failed build)."""
    return _c_soa()[2]


def c_soa_build_line() -> str | None:
    """The command line the C anchor was built with (None if not built)."""
    return _c_soa()[1]


def c_soa_final_R(inertia, omegas, h: float, n_steps: int, threads: int) -> np.ndarray:
    """As `rkmk4_final_R`, by the C anchor (float64 only; ``inertia``
    diagonal); `build_c_soa` must have succeeded."""
    f, _, why = _c_soa()
    if f is None:
        raise RuntimeError(f"the C anchor is not built: {why}")
    Ii = np.diag(_inverse_diagonal(inertia)).astype(np.float64)
    w = np.ascontiguousarray(omegas, np.float64)
    out = np.empty((w.shape[0], 3, 3), np.float64)
    f(w.shape[0], Ii.ctypes.data, w.ctypes.data, float(h), int(n_steps), int(threads), out.ctypes.data)
    return out
