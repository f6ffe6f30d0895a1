"""The native anchor for throughput: lierk's RKMK4 on the momentum-state free
body, written out in numba, one thread per core.

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

import numpy as np

try:
    import numba
except ImportError:  # the bench extra installs it
    numba = None


def _make_kernel(F):
    """The kernel for the float type ``F`` (np.float32 or np.float64): every
    constant is an ``F`` so that float32 stays float32."""
    half, sixth, twelfth, one, two, onehalf = F(0.5), F(1 / 6), F(1 / 12), F(1.0), F(2.0), F(1.5)
    # lierk.so3's thresholds on theta^2 for the series
    small = F(1e-1) if F is np.float32 else F(1e-2)
    newton_schulz = F is np.float32

    @numba.njit(inline="always")
    def cross(a0, a1, a2, b0, b1, b2):
        return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0

    @numba.njit(inline="always")
    def stage(Iinv, y0, y1, y2, u0, u1, u2):
        """``(k, m')`` of one stage at momentum ``y`` and algebra point ``u``:
        ``k = dexpinv(-u, omega)`` to ad^2, ``m' = y x omega``."""
        w0 = Iinv[0, 0] * y0 + Iinv[0, 1] * y1 + Iinv[0, 2] * y2
        w1 = Iinv[1, 0] * y0 + Iinv[1, 1] * y1 + Iinv[1, 2] * y2
        w2 = Iinv[2, 0] * y0 + Iinv[2, 1] * y1 + Iinv[2, 2] * y2
        d0, d1, d2 = cross(y0, y1, y2, w0, w1, w2)
        a0, a1, a2 = cross(u0, u1, u2, w0, w1, w2)
        b0, b1, b2 = cross(u0, u1, u2, a0, a1, a2)
        return w0 + half * a0 + twelfth * b0, w1 + half * a1 + twelfth * b1, w2 + half * a2 + twelfth * b2, d0, d1, d2

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
                # exp(hat(u)) = (1 - B theta^2) I + A hat(u) + B u u^T
                c = one - B * x
                e00, e11, e22 = c + B * u0 * u0, c + B * u1 * u1, c + B * u2 * u2
                b01, b02, b12 = B * u0 * u1, B * u0 * u2, B * u1 * u2
                e01, e10 = b01 - A * u2, b01 + A * u2
                e02, e20 = b02 + A * u1, b02 - A * u1
                e12, e21 = b12 - A * u0, b12 + A * u0
                r00, r01, r02 = (r00 * e00 + r01 * e10 + r02 * e20, r00 * e01 + r01 * e11 + r02 * e21,
                                 r00 * e02 + r01 * e12 + r02 * e22)
                r10, r11, r12 = (r10 * e00 + r11 * e10 + r12 * e20, r10 * e01 + r11 * e11 + r12 * e21,
                                 r10 * e02 + r11 * e12 + r12 * e22)
                r20, r21, r22 = (r20 * e00 + r21 * e10 + r22 * e20, r20 * e01 + r21 * e11 + r22 * e21,
                                 r20 * e02 + r21 * e12 + r22 * e22)
                if newton_schulz:
                    # R (3 I - R^T R) / 2, as lierk.so3.right_exp does in float32
                    s00 = r00 * r00 + r10 * r10 + r20 * r20
                    s11 = r01 * r01 + r11 * r11 + r21 * r21
                    s22 = r02 * r02 + r12 * r12 + r22 * r22
                    s01 = r00 * r01 + r10 * r11 + r20 * r21
                    s02 = r00 * r02 + r10 * r12 + r20 * r22
                    s12 = r01 * r02 + r11 * r12 + r21 * r22
                    r00, r01, r02 = (onehalf * r00 - half * (r00 * s00 + r01 * s01 + r02 * s02),
                                     onehalf * r01 - half * (r00 * s01 + r01 * s11 + r02 * s12),
                                     onehalf * r02 - half * (r00 * s02 + r01 * s12 + r02 * s22))
                    r10, r11, r12 = (onehalf * r10 - half * (r10 * s00 + r11 * s01 + r12 * s02),
                                     onehalf * r11 - half * (r10 * s01 + r11 * s11 + r12 * s12),
                                     onehalf * r12 - half * (r10 * s02 + r11 * s12 + r12 * s22))
                    r20, r21, r22 = (onehalf * r20 - half * (r20 * s00 + r21 * s01 + r22 * s02),
                                     onehalf * r21 - half * (r20 * s01 + r21 * s11 + r22 * s12),
                                     onehalf * r22 - half * (r20 * s02 + r21 * s12 + r22 * s22))
            R_out[b, 0, 0], R_out[b, 0, 1], R_out[b, 0, 2] = r00, r01, r02
            R_out[b, 1, 0], R_out[b, 1, 1], R_out[b, 1, 2] = r10, r11, r12
            R_out[b, 2, 0], R_out[b, 2, 1], R_out[b, 2, 2] = r20, r21, r22

    return kernel


_KERNELS: dict = {}


def rkmk4_final_R(inertia, omegas, h: float, n_steps: int, threads: int) -> np.ndarray:
    """``R(n_steps h)`` ``(B, 3, 3)`` of RKMK4 from ``R0 = I`` for each body
    angular velocity in ``omegas`` ``(B, 3)`` (rad/s), inertia ``(3, 3)``
    (kg m^2), step ``h`` (s), on ``threads`` threads; in the dtype of
    ``omegas``.  The first call for a dtype compiles."""
    if numba is None:
        raise ImportError("the native anchor needs numba: pip install 'lierk[bench]'")
    F = np.dtype(omegas.dtype).type
    if F not in _KERNELS:
        _KERNELS[F] = _make_kernel(F)
    numba.set_num_threads(threads)
    inertia = np.asarray(inertia, np.float64)
    Iinv = np.linalg.inv(inertia).astype(F)
    out = np.empty((omegas.shape[0], 3, 3), F)
    _KERNELS[F](inertia.astype(F), Iinv, np.ascontiguousarray(omegas), F(h), int(n_steps), out)
    return out
