"""Effects: torques against exact solutions and a high-accuracy reference,
conservation laws each effect documents, and that absent effects are never traced."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import reference_R
from scipy.integrate import solve_ivp

import lierk
from lierk import BodyTorque, Damping, Gravity, RigidBodyWithEffects, SpaceTorque

# Simo & Wong's heavy symmetric top: J = diag(5, 5, 1) about the pivot,
# M g l = 20, fast spin about the symmetry axis, slightly tilted.
J_TOP = np.array([5.0, 5.0, 1.0])
TILT = 0.3
OMEGA_TOP = np.array([0.0, 0.0, 50.0])


def heavy_top(**kw):
    return RigidBodyWithEffects(
        J_TOP, OMEGA_TOP, R0=lierk.so3.from_euler(0.0, TILT, 0.0), effects=(Gravity([0.0, 0.0, 1.0], 1.0, 20.0),), **kw
    )


def reference(inertia, omega0, R0, torque, t_eval, rtol=1e-12):
    """``(R, m)`` at ``t_eval`` from SciPy's DOP853 on the 12-component ODE
    ``dR/dt = R hat(omega)``, ``dm/dt = m x omega + torque(t, R, m, omega)``."""
    I = np.diag(inertia) if np.ndim(inertia) == 1 else np.asarray(inertia)
    Iinv = np.linalg.inv(I)

    def f(t, x):
        R, m = x[:9].reshape(3, 3), x[9:]
        w = Iinv @ m
        W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return np.concatenate([(R @ W).ravel(), np.cross(m, w) + torque(t, R, m, w)])

    x0 = np.concatenate([np.asarray(R0).ravel(), I @ omega0])
    sol = solve_ivp(f, (0.0, t_eval[-1]), x0, method="DOP853", rtol=rtol, atol=rtol, t_eval=t_eval)
    return sol.y[:9].T.reshape(-1, 3, 3), sol.y[9:].T


def saved(sol):
    n = int(sol.n_saved)
    return np.asarray(sol.ts[:n]), np.asarray(sol.R[:n]), np.asarray(sol.y[:n])


def drift(x):
    x = np.asarray(x)
    return float(np.max(np.abs(x - x[0])))


@pytest.mark.parametrize(
    "solver, kwargs, bounds",
    [
        # Measured over t1 = 2 (relative drifts; errors vs SciPy at t1):
        #   DP54 rtol 1e-10: energy 1.1e-12, L_vertical 5.4e-11, R 2.1e-10, m 2.5e-9
        #   RKMK4 h = 1e-3:  energy 1.5e-11, L_vertical 1.2e-9,  R 7.6e-8,  m 1.1e-6
        # Bounds are ~10x.
        (
            lierk.DP54(),
            dict(rtol=1e-10, atol=1e-10, max_steps=20000),
            dict(energy=1e-11, L_vertical=5e-10, R=2e-9, m=2.5e-8),
        ),
        (lierk.RKMK4(), dict(dt=1e-3), dict(energy=1.5e-10, L_vertical=1.2e-8, R=8e-7, m=1.1e-5)),
    ],
    ids=["DP54", "RKMK4"],
)
def test_heavy_symmetric_top_conserves_its_invariants(solver, kwargs, bounds):
    top = heavy_top()
    t1 = 2.0
    sol = lierk.solve(top, solver, t1, saveat=lierk.SaveAt(t0=True, steps=True), **kwargs)
    ts, R, m = saved(sol)
    inv = top.invariants(R, m)
    assert set(top.conserved()) == {"energy", "L_vertical", "m_chi"}
    E0 = float(inv["energy"][0])
    assert drift(inv["energy"]) / abs(E0) < bounds["energy"]
    assert drift(inv["L_vertical"]) / abs(float(inv["L_vertical"][0])) < bounds["L_vertical"]
    # dm3/dt is exactly zero in the field (symmetric body, chi on its axis): any
    # Runge-Kutta combination of stages keeps m3 to rounding.
    assert drift(inv["m_chi"]) < 1e-12 * 50.0
    # The top genuinely moves: it nutates (the tilt changes) and precesses, so
    # the conservation above is not trivial.
    tilt = np.arccos(R[:, 2, 2])
    assert np.ptp(tilt) > 0.01
    assert np.ptp(np.asarray(inv["|L|"])) > 1e-3

    # And it moves the right way: the torque's sign and size against SciPy.
    def g(t, R_, m_, w):
        return 20.0 * np.cross(R_[2, :], [0.0, 0.0, 1.0])

    R_ref, m_ref = reference(J_TOP, OMEGA_TOP, np.asarray(top.R0), g, np.array([0.0, t1]))
    assert np.abs(R[-1] - R_ref[-1]).max() < bounds["R"]
    assert np.abs(m[-1] - m_ref[-1]).max() < bounds["m"]


def test_space_torque_changes_L_linearly():
    """``dL/dt = tau`` exactly, so ``L(t) = L0 + tau t``; body torques in
    general also run against the reference."""
    inertia = np.array([1.0, 2.0, 3.0])
    omega0 = np.array([0.4, -1.0, 0.7])
    tau = np.array([0.3, -0.2, 0.5])
    R0 = lierk.so3.from_euler(0.3, -0.2, 1.1)
    p = RigidBodyWithEffects(inertia, omega0, R0=R0, effects=(SpaceTorque(tau),))
    sol = lierk.solve(p, lierk.RKMK4(), 2.0, dt=2e-3, saveat=lierk.SaveAt(t0=True, steps=10))
    ts, R, m = saved(sol)
    L = np.einsum("nij,nj->ni", R, m)
    L0 = np.asarray(R0) @ (inertia * omega0)
    err = np.abs(L - (L0 + ts[:, None] * tau)).max()
    assert err < 2.5e-11  # measured 2.5e-12
    # The components of L orthogonal to tau do not change.
    assert drift(p.invariants(R, m)["L_perp"]) < 1e-11  # measured 6.3e-13
    assert p.conserved() == ("L_perp",)


def test_body_torque_matches_reference():
    inertia = np.array([1.0, 2.0, 3.0])
    omega0 = np.array([0.4, -1.0, 0.7])
    tau = np.array([0.3, -0.2, 0.5])
    p = RigidBodyWithEffects(inertia, omega0, effects=(BodyTorque(tau),))
    sol = lierk.solve(p, lierk.DP54(), 2.0, rtol=1e-11, atol=1e-11)
    R_ref, m_ref = reference(inertia, omega0, np.eye(3), lambda t, R, m, w: tau, np.array([0.0, 2.0]))
    assert np.abs(np.asarray(sol.R[-1]) - R_ref[-1]).max() < 1e-10  # measured 9.7e-12
    assert np.abs(np.asarray(sol.y[-1]) - m_ref[-1]).max() < 1e-10  # measured 1.1e-11
    assert p.conserved() == ()


def test_damping_on_a_sphere_is_exact_exponential_decay():
    """For a sphere ``omega(t) = omega0 exp(-c t / I)`` and the body turns about
    the fixed axis ``omega0/|omega0|`` by ``|omega0| I/c (1 - exp(-c t/I))``."""
    I, c = 2.0, 0.5
    omega0 = np.array([0.4, -1.0, 0.7])
    p = RigidBodyWithEffects(np.full(3, I), omega0, effects=(Damping(c),))
    sol = lierk.solve(p, lierk.RKMK4(), 4.0, dt=1e-2, saveat=lierk.SaveAt(t0=True, steps=20))
    ts, R, m = saved(sol)
    decay = np.exp(-c * ts / I)
    omega = m / I
    assert np.abs(omega - omega0 * decay[:, None]).max() < 2e-12  # measured 1.2e-13 (RK4 error ~ h^4)
    angle = (I / c) * (1.0 - decay)
    R_exact = np.asarray(lierk.so3.exp(angle[:, None] * omega0))
    assert np.abs(R - R_exact).max() < 5e-12  # measured 4.9e-13


def test_damping_dissipates_energy_at_the_predicted_rate():
    inertia = np.array([1.0, 2.0, 3.0])
    c = 0.2
    p = RigidBodyWithEffects(inertia, [0.3, 1.0, 0.2], effects=(Damping(c),))
    sol = lierk.solve(p, lierk.RKMK4(), 5.0, dt=1e-3, saveat=lierk.SaveAt(t0=True, steps=True))
    ts, R, m = saved(sol)
    E = np.asarray(p.invariants(R, m)["energy"])
    assert np.all(np.diff(E) < 0)
    # E(t) - E(0) = -c int_0^t |omega|^2 (trapezoid on the fine step grid).
    w2 = np.sum((m / inertia) ** 2, axis=1)
    dissipated = np.concatenate([[0.0], np.cumsum(0.5 * (w2[1:] + w2[:-1]) * np.diff(ts))]) * c
    rel = np.abs(E - E[0] + dissipated).max() / (E[0] - E[-1])
    assert E[0] - E[-1] > 0.3 * E[0]  # a real decay, not rounding
    assert rel < 5e-8  # measured 4.9e-9 (trapezoid error ~ h^2)
    assert "energy" not in p.conserved()


def test_no_effects_is_the_free_rigid_body():
    inertia = np.array([9.82271303e-05, 7.22671030e-05, 1.57865031e-04])
    omega0 = np.array([1.0, 0.05, 0.3])
    R0 = lierk.so3.from_euler(0.2, 0.4, -0.3)
    free = lierk.FreeRigidBody(inertia, omega0, R0)
    withe = RigidBodyWithEffects(inertia, omega0, R0, effects=())
    assert withe.conserved() == ("energy", "|L|")
    kw = dict(rtol=1e-11, atol=1e-11, saveat=lierk.SaveAt(ts=jnp.linspace(0.0, 5.0, 6)))
    a = lierk.solve(free, lierk.DP54(), 5.0, **kw)
    b = lierk.solve(withe, lierk.DP54(), 5.0, **kw)
    ref = reference_R(np.diag(inertia), omega0, 5.0, np.asarray(R0))
    assert np.abs(np.asarray(b.R[-1]) - ref).max() < 1e-10  # measured 7e-12
    assert np.abs(np.asarray(a.R) - np.asarray(b.R)).max() < 1e-8  # measured 1.3e-9 (FreeRigidBody's own error)
    ia, ib = free.invariants(a.R, a.y), withe.invariants(b.R, b.y)
    np.testing.assert_allclose(ib["energy"], ia["energy"], rtol=1e-8)
    np.testing.assert_allclose(ib["|L|"], ia["|L|"], rtol=1e-8)


def _traced_effects(problem) -> set[str]:
    solver = lierk.RKMK4()
    jaxpr = jax.make_jaxpr(lambda p, R, y: solver.step(p, 0.0, 0.01, R, y))(problem, problem.R0, problem.y0)
    text = jaxpr.pretty_print(name_stack=True)
    return {
        n for n in ("Gravity", "BodyTorque", "SpaceTorque", "TimedTorque", "Damping") if f"lierk_effect_{n}" in text
    }


def test_absent_effects_are_never_traced():
    inertia, omega0 = np.array([1.0, 2.0, 3.0]), np.array([0.3, 1.0, 0.2])
    only_damping = RigidBodyWithEffects(inertia, omega0, effects=(Damping(0.1),))
    assert _traced_effects(only_damping) == {"Damping"}
    # The probe sees every effect that is present.
    timed = lierk.TimedTorque([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], times=[0.0, 1.0], frame="space")
    every = (
        Gravity([0.0, 0.0, 0.1], 1.0),
        BodyTorque([1.0, 0.0, 0.0]),
        SpaceTorque([0.0, 0.0, 1.0]),
        timed,
        Damping(0.1),
    )
    assert _traced_effects(RigidBodyWithEffects(inertia, omega0, effects=every)) == {
        "Gravity",
        "BodyTorque",
        "SpaceTorque",
        "TimedTorque",
        "Damping",
    }
    # A time-dependent torque is compiled only where a scene has one.
    assert _traced_effects(RigidBodyWithEffects(inertia, omega0, effects=every[:3])) == {
        "Gravity",
        "BodyTorque",
        "SpaceTorque",
    }
    # Without effects the field is the bare Euler equation: its jaxpr has one
    # multiply-add fewer per stage than with damping.
    bare = jax.make_jaxpr(RigidBodyWithEffects(inertia, omega0).field)(0.0, jnp.eye(3), jnp.ones(3))
    damped = jax.make_jaxpr(only_damping.field)(0.0, jnp.eye(3), jnp.ones(3))
    assert len(damped.eqns) > len(bare.eqns)


def test_float32_runs_in_float32():
    f32 = np.float32
    p = RigidBodyWithEffects(
        np.array([1.0, 2.0, 3.0], f32),
        np.array([0.3, 1.0, 0.2], f32),
        effects=(Gravity(np.array([0.0, 0.0, 0.1], f32), f32(1.0)), Damping(f32(0.0))),
    )
    assert all(x.dtype == jnp.float32 for x in jax.tree_util.tree_leaves(p) if eqx.is_array(x))
    sol = lierk.solve(p, lierk.RKMK4(), 1.0, dt=0.01, saveat=lierk.SaveAt(t0=True, t1=True))
    assert sol.R.dtype == jnp.float32 and sol.y.dtype == jnp.float32
    E = np.asarray(p.invariants(sol.R, sol.y)["energy"], dtype=float)
    assert abs(E[1] - E[0]) / abs(E[0]) < 1e-5
    # Adaptive steps too (their tolerances read the effects' energy scale,
    # whose 0 for Damping was float64 under x64: the loop's carry changed
    # dtype and the solve failed to trace; found by an adversarial pass).
    damped = RigidBodyWithEffects(
        np.array([2.0, 3.0, 1.5], f32), np.array([0.1, 1.0, 0.2], f32), effects=(Damping(f32(0.4)),)
    )
    sol = lierk.solve(damped, lierk.DOP853(), 5.0, rtol=1e-5)
    ref = lierk.solve(
        RigidBodyWithEffects([2.0, 3.0, 1.5], [0.1, 1.0, 0.2], effects=(Damping(0.4),)), lierk.DOP853(), 5.0, rtol=1e-10
    )
    assert sol.R.dtype == jnp.float32
    assert np.linalg.norm(np.asarray(sol.R[-1], float) - np.asarray(ref.R[-1])) < 1e-4


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Gravity([0.0, 0.0, 1.0], -1.0), "mass must be positive"),
        (lambda: Gravity([0.0, 1.0], 1.0), r"pivot_to_com must have shape \(3,\)"),
        (lambda: Damping(-0.1), "c must be non-negative"),
        (lambda: SpaceTorque([0.0, np.nan, 0.0]), "tau has NaN"),
        (lambda: RigidBodyWithEffects([1.0, 2.0, 3.0], [0.0, 0.0, 1.0], effects=("gravity",)), "effects\\[0\\]"),
    ],
)
def test_bad_effects_raise(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_diagonal_inertia_takes_the_elementwise_path_with_the_same_result():
    """A concrete diagonal inertia computes omega = I^-1 m elementwise; a rotated
    or traced inertia takes the 3x3 product.  Both give the same motion: the
    heavy top solved with its inertia concrete, and traced through jit (the
    general path), agree to rounding."""
    assert heavy_top().diagonal
    rot = np.asarray(lierk.so3.exp(jnp.array([0.2, -0.4, 0.1])))
    assert not RigidBodyWithEffects(rot @ np.diag(J_TOP) @ rot.T, OMEGA_TOP).diagonal
    seen = []

    def final(inertia):
        p = RigidBodyWithEffects(
            inertia, OMEGA_TOP, R0=lierk.so3.from_euler(0.0, TILT, 0.0), effects=(Gravity([0.0, 0.0, 1.0], 1.0, 20.0),)
        )
        seen.append(p.diagonal)
        sol = lierk.solve(p, lierk.DOP853(), 0.5, rtol=1e-10, atol=1e-10)
        return sol.R[-1], sol.y[-1]

    R_elementwise, m_elementwise = final(J_TOP)
    R_general, m_general = jax.jit(final)(jnp.asarray(J_TOP))
    assert seen == [True, False]
    np.testing.assert_allclose(R_elementwise, R_general, rtol=0, atol=1e-13)
    np.testing.assert_allclose(m_elementwise, m_general, rtol=1e-13, atol=0)
