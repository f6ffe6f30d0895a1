"""Adaptive RKMK solves (RKF45, DP54, DOP853): tolerance proportionality, edge
cases, failure codes, vmap, saving, autodiff and float32.

Reference: the closed-form solution `lierk.exact.free_rigid_body` (agrees with
SciPy's DOP853 at rtol 1e-13 to ~1e-13 on these problems)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ADAPTIVE_SOLVERS, OMEGA_GENERIC, TEE, fd_jacobian, scipy_reference_R

import lierk
import lierk.exact

T = 10.0
BODY = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
R_EXACT = np.asarray(lierk.exact.free_rigid_body(TEE, OMEGA_GENERIC, T)[0])
RTOLS = [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
ids = [s.name for s in ADAPTIVE_SOLVERS]


def frob(a, b):
    return float(jnp.linalg.norm(jnp.asarray(a) - jnp.asarray(b)))


def test_exact_reference_agrees_with_scipy():
    assert frob(R_EXACT, scipy_reference_R(TEE, OMEGA_GENERIC, T)) < 1e-11


_RUNNERS = {}


def run_steps(solver, rtol):
    """SaveAt(steps=True) solve of BODY, jitted once per solver (rtol is traced)."""
    if solver.name not in _RUNNERS:
        _RUNNERS[solver.name] = jax.jit(
            lambda r: lierk.solve(BODY, solver, T, rtol=r, throw=False, max_steps=2000, saveat=lierk.SaveAt(steps=True))
        )
    sol = _RUNNERS[solver.name](rtol)
    n = int(sol.n_saved)
    return sol, n


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
def test_error_proportional_to_rtol(solver):
    errs, orths = [], []
    for rtol in RTOLS:
        sol, n = run_steps(solver, rtol)
        assert int(sol.result) == lierk.RESULTS.successful
        assert float(sol.ts[n - 1]) == T
        errs.append(frob(sol.R[n - 1], R_EXACT))
        orths.append(float(jnp.max(lierk.so3.orthogonality_error(sol.R[:n]))))
    slope = np.polyfit(np.log(RTOLS), np.log(errs), 1)[0]
    assert 0.85 < slope < 1.15, (slope, errs)
    assert all(e <= 100 * r for e, r in zip(errs, RTOLS)), errs
    assert max(orths) <= 1e-13, orths


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
def test_extreme_tolerance_terminates(solver):
    for rtol in (1e-13, 1e-14):
        sol, n = run_steps(solver, rtol)
        assert bool(jnp.all(jnp.isfinite(sol.R[:n])))
        code = int(sol.result)
        assert code in (lierk.RESULTS.successful, lierk.RESULTS.max_steps_reached, lierk.RESULTS.dt_min_reached)
        if code == lierk.RESULTS.successful:
            assert float(sol.ts[n - 1]) == T
            # The reference itself is good to ~1e-13.
            assert frob(sol.R[n - 1], R_EXACT) <= max(100 * rtol, 5e-13)
        else:
            assert int(sol.stats["num_steps"]) <= 2000


def test_unreachable_tolerance_reports_dt_min():
    # A floor on the step far above what rtol 1e-14 needs: the solve must stop, not loop.
    ctrl = lierk.Controller(1e-14, 1e-14, dtmin=0.05)
    sol = lierk.solve(BODY, lierk.DP54(), T, controller=ctrl, dt0=1.0, throw=False)
    assert int(sol.result) == lierk.RESULTS.dt_min_reached
    assert float(sol.ts[-1]) < T
    assert bool(jnp.all(jnp.isfinite(sol.R)))
    with pytest.raises(Exception, match="step size fell below dtmin"):
        jax.block_until_ready(lierk.solve(BODY, lierk.DP54(), T, controller=ctrl, dt0=1.0).R)


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
def test_huge_first_step_is_rejected_and_recovered(solver):
    sol = lierk.solve(BODY, solver, T, rtol=1e-8, dt0=100.0)
    assert int(sol.stats["num_rejected_steps"]) >= 1
    assert frob(sol.R[-1], R_EXACT) < 1e-6


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
def test_rejected_steps_restart_from_the_step_start(solver):
    # The report's RKF45 retried a rejected step from the rejected end point.
    # Replay every accepted step from the previous accepted state: each must be
    # reproduced exactly, so nothing of a rejected attempt leaks into the state.
    sol = lierk.solve(BODY, solver, T, rtol=1e-8, dt0=5.0, saveat=lierk.SaveAt(t0=True, steps=True))
    n = int(sol.n_saved)
    assert int(sol.stats["num_rejected_steps"]) >= 1
    ts, Rs, ms = sol.ts[:n], sol.R[:n], sol.y[:n]
    assert bool(jnp.all(jnp.diff(ts) > 0))
    for k in range(n - 1):
        st = solver.step(BODY, ts[k], ts[k + 1] - ts[k], Rs[k], ms[k])
        assert frob(st.R, Rs[k + 1]) < 1e-14, k
        assert float(jnp.max(jnp.abs(st.y - ms[k + 1]))) < 1e-14 * float(jnp.linalg.norm(ms[k])), k
    assert frob(Rs[-1], R_EXACT) < 1e-5


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
def test_zero_angular_velocity_takes_one_step(solver):
    body = lierk.FreeRigidBody(TEE, jnp.zeros(3))
    sol = lierk.solve(body, solver, T, rtol=1e-8)
    assert int(sol.stats["num_steps"]) == 1
    assert int(sol.stats["num_accepted_steps"]) == 1
    assert float(sol.ts[-1]) == T
    np.testing.assert_array_equal(np.asarray(sol.R[-1]), np.eye(3))


def test_max_steps_reached_codes_and_errors():
    sol = lierk.solve(BODY, lierk.DP54(), T, rtol=1e-10, max_steps=5, throw=False)
    assert int(sol.result) == lierk.RESULTS.max_steps_reached
    assert int(sol.stats["num_steps"]) == 5
    # The partial solution is the state after the accepted steps.
    t_end = float(sol.ts[-1])
    assert 0 < t_end < T
    R_at = np.asarray(lierk.exact.free_rigid_body(TEE, OMEGA_GENERIC, t_end)[0])
    assert frob(sol.R[-1], R_at) < 1e-8
    with pytest.raises(Exception, match="max_steps was reached"):
        jax.block_until_ready(lierk.solve(BODY, lierk.DP54(), T, rtol=1e-10, max_steps=5).R)


def test_max_steps_per_batch_member_under_vmap():
    omegas = jnp.asarray([[0.0, 0.0, 0.0], OMEGA_GENERIC, [0.01, 0.0, 0.0]])

    def one(w):
        return lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.DP54(), T, rtol=1e-10, max_steps=8, throw=False)

    sol = jax.jit(jax.vmap(one))(omegas)
    codes = np.asarray(sol.result)
    assert codes[0] == lierk.RESULTS.successful
    assert codes[1] == lierk.RESULTS.max_steps_reached
    assert codes[2] == lierk.RESULTS.successful
    assert float(sol.ts[1, -1]) < T and float(sol.ts[0, -1]) == T


def test_vmap_mixed_batch_matches_solo_runs():
    omegas = np.array([[0.0, 0.0, 0.0], OMEGA_GENERIC, [3.0, 0.4, -0.2], [0.1, 0.01, 0.0], [-2.0, 1.0, 2.0]])

    def one(w):
        return lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.DOP853(), T, rtol=1e-10)

    batch = jax.jit(jax.vmap(one))(jnp.asarray(omegas))
    solo = jax.jit(one)
    steps = set()
    for i, w in enumerate(omegas):
        alone = solo(jnp.asarray(w))
        # Same steps (stats below), so only rounding differs: batched and single
        # stage sums may be reduced in a different order (measured 1.0e-13).
        assert frob(batch.R[i], alone.R) < 1e-12
        for k, v in alone.stats.items():
            assert int(batch.stats[k][i]) == int(v), (i, k)
        steps.add(int(alone.stats["num_steps"]))
    assert len(steps) >= 3  # the members really differ in work


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
@pytest.mark.parametrize("dt0", [None, 3.0])
def test_stats_are_consistent(solver, dt0):
    counter = []

    class Counted(lierk.FreeRigidBody):
        # `at` is where the rigid body evaluates its equations (`field` and
        # the stages both go through it).
        def at(self, base, t, y):
            jax.debug.callback(lambda: counter.append(1))
            return super().at(base, t, y)

    body = Counted(TEE, OMEGA_GENERIC)
    sol = lierk.solve(body, solver, T, rtol=1e-7, dt0=dt0, saveat=lierk.SaveAt(steps=True))
    jax.effects_barrier()
    s = {k: int(v) for k, v in sol.stats.items()}
    assert s["num_rejected_steps"] >= (1 if dt0 else 0)
    assert s["num_steps"] == s["num_accepted_steps"] + s["num_rejected_steps"]
    assert int(sol.n_saved) == s["num_accepted_steps"]
    assert s["num_fevals"] == len(counter)


def test_saveat_t1_and_steps():
    sol = lierk.solve(BODY, lierk.DP54(), T, rtol=1e-9)
    assert sol.ts.shape == (1,) and float(sol.ts[0]) == T
    steps = lierk.solve(BODY, lierk.DP54(), T, rtol=1e-9, max_steps=500, saveat=lierk.SaveAt(steps=True))
    n = int(steps.n_saved)
    assert steps.ts.shape == (500,) and steps.R.shape == (500, 3, 3)
    assert n == int(steps.stats["num_accepted_steps"])
    assert bool(jnp.all(jnp.isinf(steps.ts[n:]))) and bool(jnp.all(jnp.isnan(steps.R[n:])))
    assert float(steps.ts[n - 1]) == T
    assert frob(steps.R[n - 1], sol.R[0]) < 1e-14  # to the bit: tests/test_last_bits.py
    R_nodes = lierk.exact.free_rigid_body(TEE, OMEGA_GENERIC, steps.ts[:n])[0]
    assert float(jnp.max(jnp.linalg.norm(steps.R[:n] - R_nodes, axis=(1, 2)))) < 100 * 1e-9


@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
def test_saveat_ts_sphere_is_exact(solver):
    # Steps end exactly on every requested time, so a uniform rotation (the
    # sphere) is reproduced to rounding at each of them, also when single
    # steps turn the body by more than 2 pi.
    omega = jnp.asarray([0.3, -1.2, 0.7])
    T_s = 10.0
    ts = jnp.linspace(0.0, T_s, 57)
    sol = lierk.solve(lierk.FreeRigidBody(2.0 * jnp.eye(3), omega), solver, T_s, rtol=1e-6, saveat=lierk.SaveAt(ts=ts))
    assert int(sol.n_saved) == 57
    np.testing.assert_array_equal(np.asarray(sol.ts), np.asarray(ts))
    R_ex = lierk.exact.sphere(omega, ts)[0]
    assert float(jnp.max(jnp.linalg.norm(sol.R - R_ex, axis=(1, 2)))) < 1e-13


# Saved states are step end points, so their error is the solver's own: the
# same bound as the tolerance test, for every pair including DOP853.
@pytest.mark.parametrize("solver", ADAPTIVE_SOLVERS, ids=ids)
@pytest.mark.parametrize("rtol", [1e-6, 1e-9])
def test_saveat_ts_dense_on_t_handle(solver, rtol):
    ts = jnp.linspace(0.0, T, 301)
    sol = lierk.solve(BODY, solver, T, rtol=rtol, saveat=lierk.SaveAt(ts=ts))
    assert int(sol.n_saved) == 301
    R_ex = lierk.exact.free_rigid_body(TEE, OMEGA_GENERIC, ts)[0]
    err = float(jnp.max(jnp.linalg.norm(sol.R - R_ex, axis=(1, 2))))
    assert err < 100 * rtol
    assert float(jnp.max(lierk.so3.orthogonality_error(sol.R))) < 1e-13


OMEGA_GRAD = jnp.asarray([1.0, 0.05, 0.3])
T_GRAD = 5.0


def final_R(omega, adjoint=None):
    body = lierk.FreeRigidBody(TEE, omega)
    # A small max_steps keeps the checkpointed reverse pass cheap (~20 steps needed).
    return lierk.solve(body, lierk.DOP853(), T_GRAD, rtol=1e-12, max_steps=200, adjoint=adjoint).R[-1]


@pytest.fixture(scope="module")
def fd_jac():
    return fd_jacobian(jax.jit(final_R), OMEGA_GRAD)


def test_jacfwd_through_adaptive_solve(fd_jac):
    J = jax.jit(jax.jacfwd(lambda w: final_R(w, lierk.ForwardMode())))(OMEGA_GRAD)
    assert frob(J, fd_jac) <= 1e-6 * float(jnp.linalg.norm(fd_jac))
    # and both agree with the closed form's derivative
    J_ex = jax.jacfwd(lambda w: lierk.exact.free_rigid_body(TEE, w, T_GRAD)[0])(OMEGA_GRAD)
    assert frob(J, J_ex) <= 1e-6 * float(jnp.linalg.norm(J_ex))


def test_grad_through_adaptive_solve(fd_jac):
    target = jnp.asarray(lierk.so3.exp(jnp.asarray([0.2, -0.1, 0.4])))

    def loss(w):
        return jnp.sum((final_R(w) - target) ** 2)

    g = jax.jit(jax.grad(loss))(OMEGA_GRAD)
    R = final_R(OMEGA_GRAD)
    g_fd = jnp.einsum("ij,ijk->k", 2 * (R - target), fd_jac)
    assert float(jnp.linalg.norm(g - g_fd)) <= 1e-6 * float(jnp.linalg.norm(g_fd))


REPLAY_OMEGA0 = jnp.asarray([0.9, 0.07, 0.2])


def replay_R(omega0, max_steps, adjoint):
    body = lierk.FreeRigidBody(lierk.inertia.tee_handle(), omega0)
    return lierk.solve(body, lierk.DP54(), 2.5, rtol=1e-11, atol=1e-11, max_steps=max_steps, adjoint=adjoint).R[-1]


@pytest.fixture(scope="module")
def replay_jac():
    return jax.jacfwd(lambda w: replay_R(w, 300, lierk.ForwardMode()))(REPLAY_OMEGA0)


@pytest.mark.parametrize(
    "max_steps,adjoint",
    [
        (300, lierk.RecursiveCheckpointAdjoint()),
        (5000, lierk.RecursiveCheckpointAdjoint()),
        (300, lierk.DirectAdjoint()),
        (300, None),
    ],
    ids=["checkpointed-300", "checkpointed-5000", "direct-300", "default-300"],
)
def test_reverse_mode_is_the_derivative_of_the_solve_taken_for_any_max_steps(replay_jac, max_steps, adjoint):
    """The checkpointed reverse pass recomputes the steps between checkpoints
    in a differently compiled body, where the error estimate (a nearly
    cancelling sum) comes out ~1e-7 different and the step sizes after it
    drift: jacrev was 2e-9 off (4e-9 at 1000) whenever
    the 60 steps outnumbered the checkpoints (sqrt(2 max_steps)), and right
    at 5000.  The loop now records each attempt's decisions and the
    recomputation replays them.  DirectAdjoint's rematerialised scans had the
    same fault (4e-9 off at 300); its decisions now come from a solve of
    their own, which its loop replays.  The default, `ForwardSensitivity`,
    replays nothing: its reverse mode reads forward tangents."""
    J = jax.jacrev(lambda w: replay_R(w, max_steps, adjoint))(REPLAY_OMEGA0)
    assert frob(J, replay_jac) <= 1e-12 * float(jnp.linalg.norm(replay_jac))


def test_float32():
    body = lierk.FreeRigidBody(jnp.asarray(TEE, jnp.float32), jnp.asarray(OMEGA_GENERIC, jnp.float32))
    sol = lierk.solve(body, lierk.DP54(), T, rtol=1e-5)
    assert sol.R.dtype == jnp.float32
    assert int(sol.result) == lierk.RESULTS.successful
    assert frob(np.asarray(sol.R[-1], np.float64), R_EXACT) < 1e-3
    assert float(lierk.so3.orthogonality_error(sol.R[-1])) < 5e-6


def test_dop853_needs_far_fewer_steps_at_tight_tolerance():
    dp = lierk.solve(BODY, lierk.DP54(), T, rtol=1e-12)
    d8 = lierk.solve(BODY, lierk.DOP853(), T, rtol=1e-12)
    # Calibrated tolerances: both reach about the error asked for (see
    # test_accuracy.py), DOP853 with far less work.
    assert frob(d8.R[-1], R_EXACT) <= 30 * 1e-12 and frob(dp.R[-1], R_EXACT) <= 30 * 1e-12
    assert int(d8.stats["num_steps"]) * 4 < int(dp.stats["num_steps"])
    assert int(d8.stats["num_fevals"]) * 3 < int(dp.stats["num_fevals"])


def test_steps_turn_the_body_by_at_most_max_angle():
    """dexpinv, applied at every RKMK stage, has its pole at 2 pi.  At a loose
    tolerance on a fast top the error control alone proposed steps turning the
    body by more than that and rejected them (measured on 256 tops spun at 30
    to 120 rad/s, rtol 1e-4: 28% of attempts).  Every step now starts with
    |omega| h <= max_angle (pi); without the bound this top takes steps of up
    to 4.1 rad and rejects 36 attempts, with it none, at the same accuracy
    (2.7e-4 with the bound, 3.6e-4 without; the batch's worst case improved
    3x).  A given dt0 is bounded too."""
    top = lierk.RigidBodyWithEffects(
        [0.6, 0.8, 0.3],
        [1.0, -1.5, 110.0],
        lierk.so3.exp(jnp.array([0.3, 0.0, 0.0])),
        effects=lierk.Gravity([0.02, 0.01, 0.5], 1.0, 9.81),
    )
    ref = lierk.solve(top, lierk.DOP853(), 2.0, rtol=1e-13, atol=1e-13, max_steps=100_000).R[-1]

    def run(max_angle):
        c = lierk.Controller(1e-4, 1e-4, max_angle=max_angle)
        sol = lierk.solve(
            top, lierk.DOP853(), 2.0, controller=c, saveat=lierk.SaveAt(t0=True, steps=True), max_steps=1000
        )
        n = int(sol.stats["num_accepted_steps"])
        turn = np.diff(np.asarray(sol.ts[: n + 1])) * np.linalg.norm(np.asarray(sol.omega(top)[:n]), axis=-1)
        return turn, int(sol.stats["num_rejected_steps"]), frob(sol.R[n], ref)

    turn, rejected, err = run(np.pi)
    turn_free, rejected_free, err_free = run(np.inf)
    assert turn.max() <= np.pi * (1 + 1e-9)
    assert turn_free.max() > np.pi
    assert rejected < rejected_free
    assert err < 1.2 * err_free
    sol = lierk.solve(
        top,
        lierk.DOP853(),
        2.0,
        controller=lierk.Controller(1e-4, 1e-4),
        dt0=0.05,
        saveat=lierk.SaveAt(t0=True, steps=True),
        max_steps=1000,
    )
    first = float(sol.ts[1]) * float(np.linalg.norm(np.asarray(sol.omega(top)[0])))
    assert first <= np.pi * (1 + 1e-9) and int(sol.stats["num_rejected_steps"]) == 0
    with pytest.raises(ValueError, match="max_angle"):
        lierk.Controller(1e-6, max_angle=0.0)


def test_a_controller_built_outside_jit_is_used_inside_it():
    """Its concrete tolerances were added with jax.numpy inside the trace
    (a tracer) and read with float(): ConcretizationTypeError."""
    controller = lierk.Controller(1e-9, 1e-9)
    body = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    inside = jax.jit(lambda w: lierk.solve(body.with_omega0(w), lierk.DP54(), 1.0, controller=controller).R[-1])
    outside = lierk.solve(body, lierk.DP54(), 1.0, controller=controller).R[-1]
    np.testing.assert_allclose(inside(jnp.asarray(OMEGA_GENERIC)), outside, rtol=0, atol=1e-14)
