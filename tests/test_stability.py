"""Long runs, invariants and hard cases: staying on SO(3), conserved quantities,
zero and tiny rates, huge steps, scaled and extreme inertia, symmetric bodies, float32."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import ADAPTIVE_SOLVERS, FIXED_SOLVERS, LIE_SOLVERS, OMEGA_GENERIC, TEE, reference_R, scipy_reference_R
from scipy.spatial.transform import Rotation

import lierk
from lierk import so3

R0_GENERIC = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()


@pytest.mark.parametrize("solver", [lierk.RKMK4(), lierk.LieEuler()], ids=lambda s: s.name)
def test_lie_solvers_stay_on_so3_for_1e5_steps(solver):
    """10^5 steps of 0.01 s on the T-handle; the attitude is checked every 10^4 steps."""
    sol = lierk.solve(
        lierk.FreeRigidBody(TEE, OMEGA_GENERIC), solver, 1000.0, dt=0.01, saveat=lierk.SaveAt(steps=10_000), throw=False
    )
    assert sol.R.shape == (10, 3, 3) and int(sol.stats["num_steps"]) == 100_000
    # First-order LieEuler lets |m| grow (explicit Euler on Euler's equations):
    # over 1000 s that is reported; the attitude must stay a rotation regardless.
    expected = lierk.RESULTS.invariant_drift if solver.order == 1 else lierk.RESULTS.successful
    assert int(sol.result) == expected
    err = np.asarray(sol.orthogonality_error)
    print(f"{solver.name}: max ||R^T R - I|| over 1e5 steps = {err.max():.2e}")
    assert err.max() < 1e-12, err
    assert np.all(np.linalg.det(np.asarray(sol.R)) > 0)


def test_explicit_euler_leaves_so3():
    """The baseline drifts off the group: 10^4 steps of 0.01 s (measured: 0.46 after
    2500 steps, 3.1 after 10^4)."""
    sol = lierk.solve(
        lierk.FreeRigidBody(TEE, OMEGA_GENERIC),
        lierk.ExplicitEuler(),
        100.0,
        dt=0.01,
        saveat=lierk.SaveAt(steps=2_500),
        throw=False,
    )
    err = np.asarray(sol.orthogonality_error)
    print(f"ExplicitEuler: ||R^T R - I|| every 2500 steps = {err}")
    assert err[-1] > 1e-3, err
    assert np.all(np.diff(err) > 0), err  # and it keeps growing


@pytest.mark.parametrize(
    "cls, bound_L",
    # |m| drift measured 8.6e-15 (spatial form: to rounding) and 4.6e-13
    # (momentum state: to the method's accuracy); bounds are ~10x.
    [(lierk.SpatialFreeRigidBody, 1e-13), (lierk.FreeRigidBody, 5e-12)],
    ids=["spatial", "momentum"],
)
def test_rkmk4_energy_and_momentum_drift_bounded(cls, bound_L):
    """RKMK4, h = 0.01, 10^4 steps on the T-handle.  The energy error is the
    method's O(h^4) error, which does not grow secularly over this run.
    Measured: relative energy drift 1.3e-11; the bound is ~10x."""
    p = cls(TEE, OMEGA_GENERIC)
    sol = lierk.solve(p, lierk.RKMK4(), 100.0, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=100))
    inv = sol.invariants(p)
    dE = np.abs(np.asarray(inv["energy"]) / float(inv["energy"][0]) - 1).max()
    dL = np.abs(np.asarray(inv["|L|"]) / float(inv["|L|"][0]) - 1).max()
    print(f"RKMK4 h=0.01, 1e4 steps: max relative energy drift {dE:.2e}, |L| drift {dL:.2e}")
    assert dE < 1.5e-10
    assert dL < bound_L


def test_zero_rate_stays_exactly_at_R0():
    p = lierk.FreeRigidBody(TEE, np.zeros(3), R0=R0_GENERIC)
    for solver in FIXED_SOLVERS:
        sol = lierk.solve(p, solver, 1.0, dt=0.25)
        np.testing.assert_array_equal(sol.R[-1], R0_GENERIC, err_msg=solver.name)
    p = lierk.FreeRigidBody(TEE, np.zeros(3))
    for solver in ADAPTIVE_SOLVERS:
        sol = lierk.solve(p, solver, 1.0, rtol=1e-8)
        np.testing.assert_array_equal(sol.R[-1], np.eye(3), err_msg=solver.name)


def test_tiny_rate():
    """|omega0| = 1e-12 rad/s: over 3 s the motion is the uniform rotation to O(|omega|^2 t^2);
    R - I (the off-diagonal entries, free of cancellation) must be right to many digits."""
    w = 1e-12 * OMEGA_GENERIC / np.linalg.norm(OMEGA_GENERIC)
    t1 = 3.0
    expected = t1 * np.asarray(so3.hat(w))
    off = ~np.eye(3, dtype=bool)
    for solver, kw in [
        (lierk.RKMK4(), dict(dt=0.5)),
        (lierk.CF4(), dict(dt=0.5)),
        (lierk.LieEuler(), dict(dt=0.5)),
        (lierk.DP54(), dict(rtol=1e-8)),
    ]:
        R = np.asarray(lierk.solve(lierk.FreeRigidBody(TEE, w), solver, t1, **kw).R[-1])
        np.testing.assert_allclose(R[off], expected[off], rtol=1e-9, err_msg=solver.name)
        assert so3.orthogonality_error(R) < 1e-15


@pytest.mark.parametrize("solver", LIE_SOLVERS, ids=lambda s: s.name)
def test_rotation_over_2pi_in_one_step(solver):
    """|omega| h = 8 rad (more than a turn) in one step: finite, on SO(3), and on a
    sphere still exact."""
    w = 8.0 * np.array([0.36, 0.48, 0.8])
    sol = lierk.solve(lierk.FreeRigidBody(TEE, w), solver, 1.0, dt=1.0, throw=False)
    R = np.asarray(sol.R[-1])
    assert np.all(np.isfinite(R)) and so3.orthogonality_error(R) < 1e-14 and np.linalg.det(R) > 0
    # No accuracy at 8 rad per step on an asymmetric body, and the solve says so
    # (its energy drifts); a splitting composes exact free flows and is right.
    splitting = isinstance(solver, lierk.AbstractSplitting)
    assert int(sol.result) == (lierk.RESULTS.successful if splitting else lierk.RESULTS.invariant_drift)
    sol = lierk.solve(lierk.FreeRigidBody(np.eye(3), 2.5 * w), solver, 1.0, dt=1.0)  # 20 rad
    np.testing.assert_allclose(sol.R[-1], Rotation.from_rotvec(2.5 * w).as_matrix(), atol=1e-13)


def test_inertia_scale_does_not_change_R():
    """R(t) depends only on omega0 and the inertia ratios: I, 1e-8 I and 1e8 I give the
    same attitude, for fixed steps and for adaptive steps (whose control is in the algebra)."""
    for solver, kw in [(lierk.RKMK4(), dict(dt=0.05, max_steps=60)), (lierk.DP54(), dict(rtol=1e-8))]:
        run = jax.jit(lambda inertia: lierk.solve(lierk.FreeRigidBody(inertia, OMEGA_GENERIC), solver, 3.0, **kw).R[-1])
        Rs = [np.asarray(run(s * TEE)) for s in (1.0, 1e-8, 1e8)]
        np.testing.assert_allclose(Rs[1], Rs[0], atol=1e-13, err_msg=solver.name)
        np.testing.assert_allclose(Rs[2], Rs[0], atol=1e-13, err_msg=solver.name)
        np.testing.assert_allclose(Rs[0], reference_R(TEE, OMEGA_GENERIC, 3.0), atol=1e-5)


def test_inertia_ratio_1e6():
    """Moments 1e-3, 1 and 1e3 (ratio 1e6).  The wobble about the major axis is
    ~sqrt(I3^2 / (I1 I2)) omega3 ~ 300 rad/s, so the problem is stiff for its size:
    0.5 s needs ~1000 steps.  Measured errors: DP54 2.4e-8, RKMK4 4.3e-6."""
    I = np.diag([1e-3, 1.0, 1e3])
    w = np.array([1.0, 0.1, 0.01])
    t1 = 0.5
    ref = reference_R(I, w, t1)
    sol = lierk.solve(lierk.FreeRigidBody(I, w), lierk.DP54(), t1, rtol=1e-10, atol=1e-10)
    R = np.asarray(sol.R[-1])
    assert so3.orthogonality_error(R) < 1e-13
    np.testing.assert_allclose(R, ref, atol=1e-6)
    R = np.asarray(lierk.solve(lierk.FreeRigidBody(I, w), lierk.RKMK4(), t1, dt=5e-4).R[-1])
    assert so3.orthogonality_error(R) < 1e-13
    np.testing.assert_allclose(R, ref, atol=5e-5)


def test_symmetric_top_closed_form():
    """For I = diag(a, a, c), m3 = c omega3 is constant and dR/dt = hat(L)/a R + R (1/c - 1/a) m3 hat(e3),
    so R(t) = exp(t L / a) R0 exp(t (1/c - 1/a) m3 e3) with L = R0 I omega0."""
    a, c = 2.0, 3.5
    I = np.diag([a, a, c])
    w = np.array([0.8, -0.3, 1.1])
    L = R0_GENERIC @ I @ w
    e3 = np.array([0.0, 0.0, 1.0])
    for t1 in (4.0,):
        exact = np.asarray(so3.exp(t1 * L / a)) @ R0_GENERIC @ np.asarray(so3.exp(t1 * (1 / c - 1 / a) * c * w[2] * e3))
        np.testing.assert_allclose(scipy_reference_R(I, w, t1, R0=R0_GENERIC), exact, atol=1e-11)  # the formula itself
        sol = lierk.solve(lierk.FreeRigidBody(I, w, R0=R0_GENERIC), lierk.RKMK4(), t1, dt=0.01)
        np.testing.assert_allclose(sol.R[-1], exact, atol=1e-10)
        sol = lierk.solve(lierk.FreeRigidBody(I, w, R0=R0_GENERIC), lierk.DOP853(), t1, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sol.R[-1], exact, atol=1e-11)


@pytest.mark.parametrize("solver", [lierk.RKMK4(), lierk.CF4(), lierk.LieEuler()], ids=lambda s: s.name)
def test_float32_stays_on_so3_for_1e4_steps(solver):
    """A float32 problem (float32 inertia and omega0) integrates in float32 and stays
    on SO(3) to 1e-5 over 10^4 steps; RKMK4 also stays close to the float64 answer."""
    p = lierk.FreeRigidBody(TEE.astype(np.float32), OMEGA_GENERIC.astype(np.float32))
    assert p.R0.dtype == np.float32 and p.L.dtype == np.float32
    sol = lierk.solve(p, solver, 100.0, dt=0.01, saveat=lierk.SaveAt(steps=1000), throw=False)
    assert sol.R.dtype == np.float32 and sol.ts.dtype == np.float32
    # LieEuler's |m| grows by ~65% here (explicit Euler on Euler's equations): reported.
    assert int(sol.result) == (lierk.RESULTS.invariant_drift if solver.order == 1 else lierk.RESULTS.successful)
    err = np.asarray(sol.orthogonality_error)
    print(f"{solver.name} float32: max ||R^T R - I|| = {err.max():.2e}")
    assert np.all(np.isfinite(err)) and err.max() < 1e-5, err
    if isinstance(solver, lierk.RKMK4):
        R64 = lierk.solve(lierk.FreeRigidBody(TEE, OMEGA_GENERIC), solver, 10.0, dt=0.01).R[-1]
        R32 = lierk.solve(p, solver, 10.0, dt=0.01).R[-1]
        assert R32.dtype == np.float32
        np.testing.assert_allclose(R32, R64, atol=1e-5)  # measured 1.2e-6 at t = 10 s


def test_float32_adaptive():
    p = lierk.FreeRigidBody(TEE.astype(np.float32), OMEGA_GENERIC.astype(np.float32))
    sol = lierk.solve(p, lierk.DP54(), 10.0, rtol=1e-5)
    assert sol.R.dtype == np.float32
    np.testing.assert_allclose(sol.R[-1], reference_R(TEE, OMEGA_GENERIC, 10.0), atol=1e-3)
    assert so3.orthogonality_error(sol.R[-1]) < 1e-5


def test_vmapped_long_run_stays_on_so3():
    """A batch of omega0 under jit(vmap), 10^4 steps each: every member stays on SO(3)."""
    omegas = OMEGA_GENERIC + np.random.default_rng(10).standard_normal((3, 3))
    run = jax.jit(
        jax.vmap(
            lambda w: lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.RKMK4(), 100.0, dt=0.01, max_steps=10_000).R[-1]
        )
    )
    assert np.asarray(so3.orthogonality_error(run(omegas))).max() < 1e-13
