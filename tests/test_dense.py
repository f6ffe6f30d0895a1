"""Dense output on SO(3) (`SaveAt(dense=True)`, `Solution.evaluate`):
interpolation order by fitted slopes against `lierk.exact`, the error between
steps against the error at the steps, and evaluate under jit, vmap and
autodiff."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lierk
import lierk.exact
from helpers import TEE, fd_jacobian, order_fit

OMEGA = np.array([1.0, 0.05, 0.3])
BODY = lierk.FreeRigidBody(TEE, OMEGA)
exact_R = jax.jit(jax.vmap(lambda t: lierk.exact.free_rigid_body(TEE, OMEGA, t)[0]))


@eqx.filter_jit
def _one_step_midpoints(problem, solver, hs):
    """``R(h/2)`` of one dense step of each size in ``hs`` from ``t = 0``."""

    def one(h):
        sol = lierk.solve(problem, solver, h, dt=h, max_steps=1, saveat=lierk.SaveAt(dense=True))
        return sol.evaluate(0.5 * h)[0]

    return jax.vmap(one)(hs)


# The order q of the interpolant: one step from the exact state, its error at
# theta = 1/2 is O(h^(q+1)).  Quintic Hermite (interpolation error O(h^6))
# carries the solver's local error: order 4 for RKMK4 and CF4, 5 for RKF45;
# DOP853's continuous extension is order 7.  Measured slopes: 5.00, 5.00,
# 5.99, 8.07.
@pytest.mark.parametrize(
    "solver, order, hs",
    [
        (lierk.RKMK4(), 4, np.geomspace(0.05, 0.4, 4)),
        (lierk.CF4(), 4, np.geomspace(0.05, 0.4, 4)),
        (lierk.RKF45(), 5, np.geomspace(0.05, 0.4, 4)),
        (lierk.DOP853(), 7, np.geomspace(0.3, 0.8, 4)),
    ],
    ids=lambda x: getattr(x, "name", None),
)
def test_interpolant_order_at_midpoints(solver, order, hs):
    err = np.linalg.norm(np.asarray(_one_step_midpoints(BODY, solver, hs)) - np.asarray(exact_R(hs / 2)), axis=(1, 2))
    assert order_fit(hs, err) == pytest.approx(order + 1, abs=0.15)


def test_dp54_interpolant_is_at_least_order_5():
    # DP54's step is order 5 and the Hermite interpolant's own error O(h^6):
    # the slope tends to 6 from above (6.27 to 6.45 on these steps; 6.8 at
    # h = 0.8), so only the bound is claimed.
    hs = np.geomspace(0.05, 0.2, 4)
    err = np.linalg.norm(np.asarray(_one_step_midpoints(BODY, lierk.DP54(), hs)) - np.asarray(exact_R(hs / 2)), axis=(1, 2))
    assert order_fit(hs, err) >= 6 - 0.15


def test_splitting_interpolant_orders_on_a_heavy_top():
    # A symmetric heavy top (Simo and Wong's, spin 50 rad/s), where the
    # splittings' steps are not exact; reference: DOP853 at rtol 1e-13 (its
    # own dense output).  Strang's step error (order 2) dominates its
    # interpolant; BlanesMoanRKN4's steps are so accurate (1e-12 at
    # h = 0.01) that the Hermite interpolant's own O(h^6) error, set by the
    # spin per step, is what remains: slope 6.0 to 6.3, and at these steps up
    # to 1000 times the error at the steps (README: dense output, limits).
    top = lierk.RigidBodyWithEffects(
        [5.0, 5.0, 1.0], [0.3, 0.0, 50.0], R0=lierk.so3.exp(np.array([0.0, 0.3, 0.0])),
        effects=(lierk.Gravity([0.0, 0.0, 1.0], 20.0 / 9.81, 9.81),),
    )
    hs = np.geomspace(0.005, 0.02, 4)
    ref = lierk.solve(top, lierk.DOP853(), 0.02, rtol=1e-13, saveat=lierk.SaveAt(dense=True)).evaluate(hs / 2)[0]
    slopes = []
    for solver in (lierk.Strang(), lierk.BlanesMoanRKN4()):
        err = np.linalg.norm(np.asarray(_one_step_midpoints(top, solver, hs)) - np.asarray(ref), axis=(1, 2))
        slopes.append(order_fit(hs, err))
    assert slopes[0] == pytest.approx(3, abs=0.15)
    assert slopes[1] >= 6 - 0.15


@pytest.mark.parametrize(
    "solver, kwargs",
    [(lierk.RKMK4(), dict(dt=0.05)), (lierk.DP54(), dict(rtol=1e-8)), (lierk.DOP853(), dict(rtol=1e-9))],
    ids=["RKMK4", "DP54", "DOP853"],
)
def test_error_between_steps_is_within_10x_of_the_error_at_steps(solver, kwargs):
    # Measured (largest between steps / largest at steps): 1.00, 1.00, 2.6.
    T = 10.0
    steps = lierk.SaveAt(steps=True, dense=True) if "rtol" in kwargs else lierk.SaveAt(steps=1, dense=True)
    sol = lierk.solve(BODY, solver, T, saveat=steps, max_steps=2000 if "rtol" in kwargs else None, **kwargs)
    n = int(sol.interpolation.n)
    t_nodes = np.asarray(sol.ts)[: int(sol.n_saved)]
    node_err = np.linalg.norm(np.asarray(sol.R)[: int(sol.n_saved)] - np.asarray(exact_R(t_nodes)), axis=(1, 2)).max()
    # Four points inside every step.
    starts, hs = np.asarray(sol.interpolation.ts)[:n], np.asarray(sol.interpolation.hs)[:n]
    t_mid = (starts[:, None] + np.array([0.2, 0.4, 0.6, 0.8]) * hs[:, None]).ravel()
    mid_err = np.linalg.norm(np.asarray(sol.evaluate(t_mid)[0]) - np.asarray(exact_R(t_mid)), axis=(1, 2)).max()
    assert 0 < mid_err <= 10 * node_err, (mid_err, node_err)


def test_evaluate_reproduces_the_steps_and_stays_on_so3():
    sol = lierk.solve(BODY, lierk.DOP853(), 5.0, rtol=1e-8, saveat=lierk.SaveAt(steps=True, dense=True), max_steps=500)
    k = int(sol.n_saved)
    R, m = sol.evaluate(sol.ts[:k])
    np.testing.assert_allclose(R, sol.R[:k], atol=2e-15)
    np.testing.assert_allclose(m, sol.y[:k], rtol=1e-13, atol=1e-20)
    Rm = sol.evaluate(jnp.linspace(0.0, 5.0, 333))[0]
    assert float(jnp.max(lierk.so3.orthogonality_error(Rm))) < 1e-14


def test_more_than_half_a_turn_per_step():
    # A sphere turns steadily: every Lie solver is exact, and so must the
    # interpolant be, though log(R_n^T R_n+1) only knows the turn modulo 2 pi.
    sphere = lierk.FreeRigidBody(np.eye(3), [0.0, 0.0, 4.0])
    sol = lierk.solve(sphere, lierk.CF4(), 2.0, dt=1.0, saveat=lierk.SaveAt(dense=True))
    R = sol.evaluate(jnp.array([0.25, 0.5, 1.5]))[0]
    np.testing.assert_allclose(R, lierk.so3.exp(jnp.array([0.25, 0.5, 1.5])[:, None] * jnp.array([0.0, 0.0, 4.0])), atol=1e-13)


def test_evaluate_under_vmap_matches_a_loop():
    sol = lierk.solve(BODY, lierk.RKMK4(), 2.0, dt=0.1, saveat=lierk.SaveAt(dense=True))
    ts = jnp.array([0.0, 0.03, 0.5, 1.37, 2.0])
    R, m = sol.evaluate(ts)
    for i, t in enumerate(ts):
        Ri, mi = sol.evaluate(float(t))
        np.testing.assert_allclose(R[i], Ri, rtol=0, atol=1e-15)
        np.testing.assert_allclose(m[i], mi, rtol=1e-15)
    # A batch of solutions, vmapped over the solution and the time.
    omegas = jnp.array([OMEGA, [0.2, 1.0, 0.1]])

    def solve(w):
        return lierk.solve(BODY.with_omega0(w), lierk.RKMK4(), 2.0, dt=0.1, saveat=lierk.SaveAt(dense=True))

    batch = jax.vmap(solve)(omegas)
    Rb = jax.vmap(lambda s, t: s.evaluate(t)[0])(batch, jnp.array([0.7, 1.9]))
    for i, (w, t) in enumerate(zip(omegas, [0.7, 1.9])):
        np.testing.assert_allclose(Rb[i], solve(w).evaluate(t)[0], atol=1e-15)


def test_evaluate_is_differentiable_in_t_and_in_the_inputs():
    def R_at(w, t):
        sol = lierk.solve(BODY.with_omega0(w), lierk.RKMK4(), 2.0, dt=0.05, saveat=lierk.SaveAt(dense=True))
        return sol.evaluate(t)

    t = 1.2345  # inside a step
    w = jnp.asarray(OMEGA)
    f = eqx.filter_jit(lambda w: R_at(w, t)[0].ravel())
    J = eqx.filter_jit(jax.jacfwd(lambda w: R_at(w, t)[0].ravel()))(w)
    np.testing.assert_allclose(J, fd_jacobian(f, OMEGA, 1e-3), rtol=1e-6, atol=1e-8)
    g = eqx.filter_jit(jax.grad(lambda w: R_at(w, t)[0][0, 2]))(w)
    np.testing.assert_allclose(g, J[2], rtol=1e-10, atol=1e-13)
    # d/dt of the interpolant is the motion's dR/dt = R hat(omega), to the
    # interpolant's accuracy.
    dR = eqx.filter_jit(jax.jacfwd(lambda t: R_at(w, t)[0]))(jnp.asarray(t))
    R, m = R_at(w, t)
    np.testing.assert_allclose(dR, R @ lierk.so3.hat(jnp.linalg.solve(TEE, m)), atol=1e-6)


def test_evaluate_outside_the_interval_raises():
    sol = lierk.solve(BODY, lierk.RKMK4(), 1.0, dt=0.1, saveat=lierk.SaveAt(dense=True))
    for bad in (1.0 + 1e-9, -0.1, float("nan"), [0.5, 2.0]):
        with pytest.raises(ValueError, match="outside the solved interval"):
            sol.evaluate(bad)
    with pytest.raises(Exception, match="outside the solved interval"):
        jax.block_until_ready(jax.jit(lambda s, t: s.evaluate(t))(sol, 1.5))
    plain = lierk.solve(BODY, lierk.RKMK4(), 1.0, dt=0.1)
    assert plain.interpolation is None
    with pytest.raises(ValueError, match="SaveAt\\(dense=True"):
        plain.evaluate(0.5)


def test_dense_alone_saves_the_end_and_covers_t0():
    sol = lierk.solve(BODY, lierk.RKMK4(), 0.5, dt=0.1, saveat=lierk.SaveAt(dense=True))
    assert sol.ts.shape == (1,) and float(sol.ts[0]) == 0.5
    np.testing.assert_array_equal(sol.evaluate(0.0)[0], BODY.R0)
    empty = lierk.solve(BODY, lierk.DOP853(), 0.0, rtol=1e-8, saveat=lierk.SaveAt(dense=True))
    np.testing.assert_array_equal(empty.evaluate(0.0)[0], BODY.R0)


def test_explicit_euler_has_no_dense_output():
    with pytest.raises(ValueError, match="leaves SO\\(3\\)"):
        lierk.solve(BODY, lierk.ExplicitEuler(), 1.0, dt=0.1, saveat=lierk.SaveAt(dense=True))


def test_dense_output_in_float32():
    body = lierk.FreeRigidBody(jnp.asarray(TEE, jnp.float32), jnp.asarray(OMEGA, jnp.float32))
    sol = lierk.solve(body, lierk.RKMK4(), 2.0, dt=0.05, saveat=lierk.SaveAt(dense=True))
    ts = np.linspace(0.0, 2.0, 37)
    R = sol.evaluate(ts.astype(np.float32))[0]
    assert R.dtype == jnp.float32
    assert np.abs(np.asarray(R, float) - np.asarray(exact_R(ts))).max() < 2e-6


def test_solves_without_dense_output_or_events_never_reach_their_code(monkeypatch):
    # The dense output's and the events' code is reached only by solves that
    # ask for them: a plain solve traces with all of it broken (its compiled
    # program was compared before and after: the same equations).
    def broken(*args, **kwargs):
        raise AssertionError("reached")

    import lierk.event
    import lierk.solvers.base
    import lierk.solvers.rkmk

    for cls in (lierk.solvers.base.AbstractSolver, lierk.solvers.rkmk.AbstractRKMK):
        monkeypatch.setattr(cls, "dense_step", broken)
        monkeypatch.setattr(cls, "dense_node", broken)
    for name in ("init", "process", "records"):
        monkeypatch.setattr(lierk.event, name, broken)
    jax.clear_caches()  # trace anew, not from a solve an earlier test compiled
    w = jnp.asarray(OMEGA)
    jax.make_jaxpr(lambda w: lierk.solve(BODY.with_omega0(w), lierk.RKMK4(), 1.0, dt=0.1).R)(w)
    jax.make_jaxpr(lambda w: lierk.solve(BODY.with_omega0(w), lierk.DOP853(), 1.0, rtol=1e-8,
                                         saveat=lierk.SaveAt(steps=True), max_steps=16).R)(w)
    with pytest.raises(AssertionError, match="reached"):
        jax.make_jaxpr(lambda w: lierk.solve(BODY.with_omega0(w), lierk.RKMK4(), 1.0, dt=0.1,
                                             saveat=lierk.SaveAt(dense=True)).R)(w)


def test_dop853_continuous_extension_is_scipys():
    # The tableau's extension, applied to one step of a scalar ODE in NumPy,
    # against SciPy's DOP853 dense output of the same step (an independent
    # copy of Hairer's coefficients).
    from scipy.integrate import solve_ivp

    T = lierk.tableaux.DOP853
    f = lambda t, y: np.array([np.cos(t) * y[0] + t])  # noqa: E731
    h, y0 = 0.5, np.array([1.0])
    ref = solve_ivp(f, (0.0, h), y0, method="DOP853", dense_output=True, first_step=h, max_step=h, rtol=1.0, atol=1.0)
    assert len(ref.t) == 2  # one step
    A, C = list(T.a) + list(T.dense_a), list(T.c) + list(T.dense_c)
    K = []
    for i in range(len(C)):
        K.append(f(C[i] * h, y0 + h * sum(A[i][j] * K[j] for j in range(i))))
    F = h * np.asarray(T.dense_b) @ np.asarray(K)
    for theta in (0.1, 0.37, 0.5, 0.9, 1.0):
        ours = y0 + lierk.interpolation.nested(F, theta)
        np.testing.assert_allclose(ours, ref.sol(theta * h), rtol=0, atol=2e-15)


def test_continuous_extensions_are_checked_when_defined():
    import dataclasses

    T = lierk.tableaux.DOP853
    assert T.dense and T.dense_order == 7 and not lierk.tableaux.DOPRI54.dense
    with pytest.raises(ValueError, match="continuous weights"):
        dataclasses.replace(T, dense_b=(T.dense_b[1],) + T.dense_b[1:])
    with pytest.raises(ValueError, match="one row of dense_a per dense_c"):
        dataclasses.replace(T, dense_a=T.dense_a[:2])
    with pytest.raises(ValueError, match="dense row 1 must have 14 entries summing"):
        dataclasses.replace(T, dense_a=(T.dense_a[0], T.dense_a[1][:-1] + (0.5,), T.dense_a[2]))
