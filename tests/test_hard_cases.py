"""Hard cases with measured bounds: separatrix starts, extreme and nearly
symmetric inertia, per-step angles beyond 2 pi, 10^6 steps, tolerances at
machine precision, float32, and gradients across a flip.

Each bound is a few times the value measured when the test was written (the
measured value is in the comment next to it).  Every solve is jitted with the
varying values traced, so each solver compiles once per test.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ADAPTIVE_SOLVERS, FIXED_SOLVERS, LIE_SOLVERS, OMEGA_GENERIC

import lierk
from lierk import so3

TEE = np.asarray(lierk.inertia.tee_handle())
IX, IY, IZ = np.diag(TEE)  # x is the intermediate axis: IY < IX < IZ


def separatrix_omega(a=1.0, c=0.3):
    """omega0 = (a, b, c) with |m|^2 = 2 E I_x exactly (m = I omega): the
    separatrix condition I_y (I_x - I_y) b^2 = I_z (I_z - I_x) c^2."""
    b = np.sqrt(IZ * (IZ - IX) * c**2 / (IY * (IX - IY)))
    return np.array([a, b, c])


def rel_drift(values):
    values = np.asarray(values)
    return np.abs(values / values[0] - 1)


def exact_R(inertia, omega0, t):
    return np.asarray(lierk.exact.free_rigid_body(inertia, omega0, t)[0])


SEP_TIME = 4.0
SEPARATRIX_RUNS = [
    # (solver, solve kwargs, bound on ||R - R_exact|| at SEP_TIME)
    # Measured (all three starts alike) with the report's spatial form: RKMK4
    # 1.3e-10, CF4 3.0e-10, DP54 2.9e-10, DOP853 3.3e-10; orthogonality <= 8.4e-15.
    (lierk.RKMK4(), dict(dt=1e-2), 5e-10),
    (lierk.CF4(), dict(dt=1e-2), 1e-9),
    (lierk.DP54(), dict(rtol=1e-10), 1e-9),
    (lierk.DOP853(), dict(rtol=1e-10), 1e-9),
]


@pytest.mark.parametrize("solver,kw,bound", SEPARATRIX_RUNS, ids=lambda x: getattr(x, "name", ""))
def test_separatrix_starts(solver, kw, bound):
    w_sep = separatrix_omega()
    m = TEE @ w_sep
    assert abs(m @ m / (2 * 0.5 * w_sep @ TEE @ w_sep * IX) - 1) < 1e-12
    starts = [w_sep, w_sep * np.array([1, 1 + 1e-6, 1]), w_sep * np.array([1, 1 - 1e-6, 1])]
    ts = np.linspace(0.0, SEP_TIME, 9)[1:]
    saveat = lierk.SaveAt(steps=50) if "dt" in kw else lierk.SaveAt(ts=ts)

    @jax.jit
    def run(w):
        return lierk.solve(lierk.FreeRigidBody(TEE, w), solver, SEP_TIME, saveat=saveat, **kw)

    for w in starts:
        p = lierk.FreeRigidBody(TEE, w)
        sol = run(jnp.asarray(w))
        t = np.asarray(sol.ts)
        err = np.linalg.norm(np.asarray(sol.R) - exact_R(TEE, w, t), axis=(-2, -1)).max()
        dL = rel_drift(
            np.concatenate([[float(p.invariants(p.R0, p.y0)["|L|"])], np.asarray(sol.invariants(p)["|L|"])])
        ).max()
        orth = float(np.asarray(sol.orthogonality_error).max())
        print(f"{solver.name} {w}: err {err:.2e}, |m| drift {dL:.2e}, orth {orth:.2e}")
        assert err < bound
        # The momentum-state body keeps |m| to the solver's accuracy (RKMK4
        # measured 8.9e-13 here); the report's spatial form keeps it to
        # rounding (test_accuracy.py).
        assert dL < 1e-11
        assert orth < 1e-12


def symmetric_top_R(inertia, omega0, t):
    """Closed form for a diagonal inertia with two equal moments I_p and the
    symmetry axis e_s, R0 = I: the body precesses about L at |L|/I_p while it
    spins about e_s at (1/I_s - 1/I_p) m_s:
    R(t) = exp(t hat(L)/I_p) exp(t (1/I_s - 1/I_p) m_s hat(e_s))."""
    moments = np.diag(inertia)
    s = 0 if moments[1] == moments[2] else 2
    I_p = moments[(s + 1) % 3]
    L = moments * omega0
    spin = (1 / moments[s] - 1 / I_p) * L[s]
    return np.asarray(so3.exp(jnp.asarray(t * L / I_p))) @ np.asarray(so3.exp(jnp.asarray(t * spin * np.eye(3)[s])))


def test_needle_inertia_ratio_1e6():
    """diag(1e-6, 1, 1): omega = I^{-1} R^T L amplifies an attitude error by
    ~|L|/I1 = 3e5 /s in omega_1, so the field is stiff in R (not in the exact
    motion, a 1 rad/s spin plus 0.3 rad/s precession): fixed steps need
    h |L|/I1 < 1, and the adaptive solver finds that by itself.
    Measured at T = 1 s: RKMK4 (h = 1e-4) 1.3e-8, CF4 (h = 1e-4) 1.0e-8,
    DOP853 (rtol 1e-10) 8.8e-10 in 482 steps (h ~ 2e-3: its embedded
    estimate sees the stiffness); exact vs the symmetric-top closed form 5e-16
    (4.5e-11 before its precession rate was taken directly for two equal moments)."""
    inertia = np.diag([1e-6, 1.0, 1.0])
    T = 1.0
    p = lierk.FreeRigidBody(inertia, OMEGA_GENERIC)
    R_ex = exact_R(inertia, OMEGA_GENERIC, T)
    gap = np.linalg.norm(R_ex - symmetric_top_R(inertia, OMEGA_GENERIC, T))
    print(f"exact vs symmetric-top closed form: {gap:.2e}")
    assert gap < 1e-13
    for solver, kw, bound in [
        (lierk.RKMK4(), dict(dt=1e-4), 5e-8),
        (lierk.CF4(), dict(dt=1e-4), 5e-8),
        (lierk.DOP853(), dict(rtol=1e-10, max_steps=200_000), 5e-9),
    ]:
        sol = lierk.solve(p, solver, T, **kw)
        err = np.linalg.norm(np.asarray(sol.R[-1]) - R_ex)
        orth = float(sol.orthogonality_error[-1])
        print(f"{solver.name}: err {err:.2e}, orth {orth:.2e}, steps {int(sol.stats['num_steps'])}")
        assert err < bound
        # Measured 8.1e-13 (RKMK4), 2.9e-12 (CF4) after 1e4 steps: with omega
        # nearly constant the rounding of each exp repeats and adds up ~ n eps.
        assert orth < 1e-11


def test_nearly_symmetric_inertia():
    """diag(1, 1 + 1e-9, 2): the exact solution must sit within O(1e-9) of the
    symmetric top's closed form, and the solvers on the exact solution.
    Measured at T = 5 s: exact vs closed form 5.3e-9; RKMK4 (h = 1e-3) 6.7e-14,
    CF4 (h = 1e-3) 7.5e-13, DOP853 (rtol 1e-10, 8 steps) 3.7e-9; energy drift
    <= 5.5e-10; orthogonality <= 6.4e-13."""
    inertia = np.diag([1.0, 1.0 + 1e-9, 2.0])
    T = 5.0
    p = lierk.FreeRigidBody(inertia, OMEGA_GENERIC)
    E0 = float(p.invariants(p.R0, p.y0)["energy"])
    R_ex = exact_R(inertia, OMEGA_GENERIC, T)
    gap = np.linalg.norm(R_ex - symmetric_top_R(np.diag([1.0, 1.0, 2.0]), OMEGA_GENERIC, T))
    print(f"exact vs symmetric-top closed form: {gap:.2e}")
    assert 1e-10 < gap < 2e-8  # the 1e-9 asymmetry must show, at its own size
    for solver, kw, bound in [
        (lierk.RKMK4(), dict(dt=1e-3), 3e-13),
        (lierk.CF4(), dict(dt=1e-3), 3e-12),
        (lierk.DOP853(), dict(rtol=1e-10), 2e-8),
    ]:
        sol = lierk.solve(p, solver, T, **kw)
        err = np.linalg.norm(np.asarray(sol.R[-1]) - R_ex)
        dE = abs(float(sol.invariants(p)["energy"][-1]) / E0 - 1)
        orth = float(sol.orthogonality_error[-1])
        print(
            f"{solver.name}: err {err:.2e}, energy drift {dE:.2e}, orth {orth:.2e}, steps {int(sol.stats['num_steps'])}"
        )
        assert err < bound
        assert dE < 3e-9
        assert orth < 1e-12


FAST = 1e4 * OMEGA_GENERIC / np.linalg.norm(OMEGA_GENERIC)  # |omega| = 1e4 rad/s


@pytest.mark.parametrize("solver", LIE_SOLVERS, ids=lambda s: s.name)
def test_fast_spin_fixed_steps_stay_on_so3(solver):
    """dt = 1e-3 s turns the body by 10 rad per step: no accuracy is claimed.
    The report's spatial form keeps |m| by construction, so its attitude stays
    a finite rotation.  The momentum-state default integrates Euler's
    equations far outside any explicit method's stability region, and must
    say so rather than return a number."""
    sol = lierk.solve(
        lierk.SpatialFreeRigidBody(TEE, FAST), solver, 0.2, dt=1e-3, saveat=lierk.SaveAt(steps=20), throw=False
    )
    # A splitting composes exact flows (any step is right); the Lie-group
    # Runge-Kutta methods lose the energy at 10 rad per step and must say so.
    splitting = isinstance(solver, lierk.AbstractSplitting)
    assert int(sol.result) == (lierk.RESULTS.successful if splitting else lierk.RESULTS.invariant_drift)
    R = np.asarray(sol.R)
    orth = float(np.asarray(sol.orthogonality_error).max())
    print(f"{solver.name}: max orth {orth:.2e}")
    assert np.all(np.isfinite(R))
    assert orth < 1e-12
    assert np.all(np.linalg.det(R) > 0)
    sol = lierk.solve(lierk.FreeRigidBody(TEE, FAST), solver, 0.2, dt=1e-3, throw=False)
    if isinstance(solver, lierk.AbstractSplitting):
        # Without torques a splitting is the exact flow, composed: any step works.
        assert int(sol.result) == lierk.RESULTS.successful
        err = np.linalg.norm(np.asarray(sol.R[-1]) - exact_R(TEE, FAST, 0.2))
        print(f"{solver.name}: error {err:.2e}")
        assert err < 1e-9
    else:
        assert int(sol.result) == lierk.RESULTS.nonfinite


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=lambda s: s.name)
def test_fast_spin_adaptive_chooses_small_steps(solver):
    T = 0.01
    sol = lierk.solve(lierk.FreeRigidBody(TEE, FAST), solver, T, rtol=1e-8, max_steps=20_000)
    err = np.linalg.norm(np.asarray(sol.R[-1]) - exact_R(TEE, FAST, T))
    n_acc = int(sol.stats["num_accepted_steps"])
    mean_angle = 1e4 * T / n_acc
    print(
        f"{solver.name}: err {err:.2e}, accepted {n_acc}, rejected {int(sol.stats['num_rejected_steps'])}, "
        f"mean |omega| h {mean_angle:.3f} rad"
    )
    # Measured: RKF45 8.2e-5 (561 steps, mean |omega| h 0.18 rad), DP54 2.8e-5
    # (507, 0.20 rad), DOP853 5.6e-6 (102, 0.98 rad).  The error is that of a
    # 100 rad rotation at rtol 1e-8 (time-rescaling: the same as 100 s at 1 rad/s).
    assert err < 3e-4
    # The controller's steps follow the rotation: within 2x of the measured range.
    assert 0.09 < mean_angle < 2.0


def test_rkmk4_million_steps():
    """10^6 steps of 0.01 s (T = 10^4 s) on the T-handle.  Growth rates are the
    slopes of log(quantity) vs log(t) between 10^4 and 10^6 steps, fitted to
    the running maximum (the raw drift oscillates with the motion)."""
    p = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    sol = lierk.solve(p, lierk.RKMK4(), 1e4, dt=0.01, saveat=lierk.SaveAt(steps=10_000))
    assert int(sol.stats["num_steps"]) == 1_000_000
    t = np.asarray(sol.ts)
    E0 = float(p.invariants(p.R0, p.y0)["energy"])
    dE = np.maximum.accumulate(np.abs(np.asarray(sol.invariants(p)["energy"]) / E0 - 1))
    orth = np.maximum.accumulate(np.asarray(sol.orthogonality_error))
    rate_E = np.polyfit(np.log(t), np.log(dE), 1)[0]
    rate_o = np.polyfit(np.log(t), np.log(orth), 1)[0]
    for k in (0, 9, 99):
        print(f"{(k + 1) * 10_000:>8} steps: energy drift {dE[k]:.2e}, orthogonality {orth[k]:.2e}")
    print(f"growth rates (log-log slope): energy {rate_E:.2f}, orthogonality {rate_o:.2f}")
    # Measured: energy drift 5.4e-12 / 4.1e-11 / 5.3e-10 at 1e4 / 1e5 / 1e6
    # steps (slope 1.04: linear, RKMK4 is not symplectic); orthogonality
    # 1.9e-14 / 7.5e-14 / 3.0e-13 (slope 0.65: rounding, between random walk and linear).
    assert orth[-1] < 1e-12
    assert dE[-1] < 3e-9
    assert rate_E < 1.5
    assert rate_o < 1.2


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=lambda s: s.name)
def test_rtol_at_machine_precision_gives_explicit_outcome(solver):
    """rtol = atol = 1e-14 asks for less than the rounding of a step can give:
    the solve must end with a code (success, dt_min_reached or
    max_steps_reached), finite, on SO(3), never hang."""
    T = 1.0
    sol = lierk.solve(lierk.FreeRigidBody(TEE, OMEGA_GENERIC), solver, T, rtol=1e-14, max_steps=3000, throw=False)
    code = int(sol.result)
    R = np.asarray(sol.R[-1])
    t_end = float(sol.ts[-1])
    print(f"{solver.name}: result {lierk.RESULTS.message(code)!r}, t_end {t_end}, steps {int(sol.stats['num_steps'])}")
    assert code in (lierk.RESULTS.successful, lierk.RESULTS.dt_min_reached, lierk.RESULTS.max_steps_reached)
    assert np.all(np.isfinite(R))
    assert so3.orthogonality_error(R) < 1e-13
    err = np.linalg.norm(R - exact_R(TEE, OMEGA_GENERIC, t_end))
    print(f"  error vs exact at t_end: {err:.2e}")
    # Measured: all three reach t1 ('successful'; RKF45 78 steps, DP54 70,
    # DOP853 7) with errors 4.6e-14, 1.4e-14, 6.8e-15.
    assert err < 3e-13


FLOAT32_RUNS = [(s, dict(dt=0.01)) for s in FIXED_SOLVERS] + [(s, dict(rtol=1e-5)) for s in ADAPTIVE_SOLVERS]


@pytest.mark.parametrize("solver,kw", FLOAT32_RUNS, ids=lambda x: getattr(x, "name", ""))
def test_float32_floors(solver, kw):
    """float32 over 10 s on the T-handle.  The float32 floor is the gap to the
    same solve in float64 (the rounding alone); the error vs the exact motion
    also contains the method's truncation error at this step/tolerance."""
    T = 10.0
    w32 = jnp.asarray(OMEGA_GENERIC, jnp.float32)
    sol32 = lierk.solve(lierk.FreeRigidBody(jnp.asarray(TEE, jnp.float32), w32), solver, T, throw=False, **kw)
    sol64 = lierk.solve(lierk.FreeRigidBody(TEE, OMEGA_GENERIC), solver, T, throw=False, **kw)
    assert sol32.R.dtype == jnp.float32
    R32 = np.asarray(sol32.R[-1], dtype=np.float64)
    gap = np.linalg.norm(R32 - np.asarray(sol64.R[-1]))
    err = np.linalg.norm(R32 - exact_R(TEE, OMEGA_GENERIC, T))
    orth = float(so3.orthogonality_error(R32))
    print(
        f"{solver.name} float32: gap to float64 {gap:.2e}, error vs exact {err:.2e}, orth {orth:.2e}, "
        f"result {int(sol32.result)}"
    )
    # Measured gaps: ExplicitEuler 6.1e-6, LieEuler 1.1e-6, NaiveLieRK4 5.4e-7,
    # RKMK4 7.3e-7, CF4 2.6e-6, RKMK(RK4) 9.2e-7, RKF45 1.0e-6, DP54 7.8e-6,
    # DOP853 1.7e-5; orthogonality <= 1.1e-7 (ExplicitEuler: 0.17).  Error vs
    # exact: RKMK4/CF4/RKMK(RK4) equal to the gap (<= 2.6e-6); NaiveLieRK4 3.0e-5;
    # adaptive at rtol 1e-5: 6.4e-4, 4.0e-4, 3.8e-5; Euler methods 8.5e-2.
    # Splittings evaluate the elliptic-function flow afresh in every drift, and
    # each float32 call adds its rounding: measured gaps 1.2e-4 (Strang, 1000
    # drifts), 3.4e-4 (Yoshida4), 7.1e-4 (BlanesMoan4), 8.1e-4 (Yoshida6),
    # 1.2e-3 (BlanesMoan6, 10^4 drifts): about 1.2e-7 per drift.
    drifts = solver.stages * round(T / kw["dt"]) if isinstance(solver, lierk.AbstractSplitting) else 0
    assert int(sol32.result) == lierk.RESULTS.successful
    assert gap < max(1e-4, 2.5e-7 * drifts)
    if not isinstance(solver, lierk.ExplicitEuler):
        assert orth < 1e-6


def test_gradient_across_flip():
    """d R(T) / d omega0 across a flip of the T-handle (omega0 = (1, 0.05, 0),
    T = 1.05 x flip interval = 24.8 s): forward mode through RKMK4 (h = 2e-3)
    against central differences of the same solve and against jacfwd of
    lierk.exact.  (DOP853 with ForwardMode at rtol 1e-12 passes the same
    bounds but takes ~25 s to compile here.)"""
    w0 = jnp.array([1.0, 0.05, 0.0])
    T = 1.05 * float(lierk.exact.flip_interval(TEE, w0))
    J_exact = np.asarray(jax.jacfwd(lambda w: lierk.exact.free_rigid_body(TEE, w, T)[0])(w0))
    scale = np.abs(J_exact).max()
    # Measured (relative to max |J| = 23.5): vs central differences 2.8e-9,
    # vs exact 3.6e-13; the bound is the 1e-6 the claim is about.
    runs = [
        (lambda w: lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.RKMK4(), T, dt=2e-3).R[-1], 1e-6),
    ]
    for f, bound in runs:
        f = jax.jit(f)
        J = np.asarray(jax.jit(jax.jacfwd(f))(w0))
        eps = 1e-6
        J_fd = np.stack(
            [(np.asarray(f(w0 + eps * e)) - np.asarray(f(w0 - eps * e))) / (2 * eps) for e in jnp.eye(3)], -1
        )
        fd_gap = np.abs(J - J_fd).max() / scale
        ex_gap = np.abs(J - J_exact).max() / scale
        print(f"T = {T:.3f} s, |J| = {scale:.2e}: vs central differences {fd_gap:.2e}, vs exact {ex_gap:.2e}")
        assert np.all(np.isfinite(J))
        assert fd_gap < bound
        assert ex_gap < bound
