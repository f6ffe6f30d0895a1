"""Claims of lierk.solve: what it saves, where it ends, jit/vmap, derivatives,
no recompilation, and input validation."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import OMEGA_GENERIC, TEE, reference_R
from scipy.spatial.transform import Rotation

import lierk
from lierk import so3
from lierk._solvers.base import Step

R0_GENERIC = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()


def _tee(omega0=OMEGA_GENERIC, R0=None, inertia=TEE):
    return lierk.FreeRigidBody(inertia, omega0, R0=R0)


# --- SaveAt -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def all_steps():
    """RKMK4 on the T-handle, 12 steps of 0.1 s, every state saved (t0 included)."""
    return lierk.solve(_tee(), lierk.RKMK4(), 1.2, dt=0.1, saveat=lierk.SaveAt(t0=True, steps=True))


def test_saveat_final_only(all_steps):
    sol = lierk.solve(_tee(), lierk.RKMK4(), 1.2, dt=0.1)
    assert sol.ts.shape == (1,) and sol.R.shape == (1, 3, 3) and int(sol.n_saved) == 1
    assert float(sol.ts[0]) == 1.2
    np.testing.assert_allclose(sol.R[0], all_steps.R[-1], rtol=0, atol=1e-15)
    assert int(sol.stats["num_steps"]) == 12 and int(sol.result) == lierk.RESULTS.successful


def test_saveat_all_steps(all_steps):
    assert all_steps.ts.shape == (13,) and all_steps.R.shape == (13, 3, 3) and int(all_steps.n_saved) == 13
    np.testing.assert_allclose(all_steps.ts, 0.1 * np.arange(13), rtol=1e-15, atol=0)
    assert float(all_steps.ts[-1]) == 1.2
    np.testing.assert_array_equal(all_steps.R[0], np.eye(3))
    # Each saved state is the one the steps reach: compare a few with the reference.
    for k in (3, 12):
        np.testing.assert_allclose(all_steps.R[k], reference_R(TEE, OMEGA_GENERIC, 0.1 * k), atol=1e-6)


@pytest.mark.parametrize(
    "k, t1_flag, expected_steps", [(3, False, [3, 6, 9, 12]), (5, False, [5, 10]), (5, True, [5, 10, 12])]
)
def test_saveat_every_kth_step_matches_all_steps(all_steps, k, t1_flag, expected_steps):
    sol = lierk.solve(_tee(), lierk.RKMK4(), 1.2, dt=0.1, saveat=lierk.SaveAt(steps=k, t1=t1_flag))
    n = len(expected_steps)
    assert sol.ts.shape == (n,) and sol.R.shape == (n, 3, 3) and int(sol.n_saved) == n
    np.testing.assert_allclose(sol.ts, all_steps.ts[np.array(expected_steps)], rtol=0, atol=0)
    np.testing.assert_allclose(sol.R, all_steps.R[np.array(expected_steps)], rtol=0, atol=1e-15)


def test_t1_not_a_multiple_of_dt_ends_exactly_at_t1():
    """The last step is shortened: 1.0 = 3 x 0.3 + 0.1.  On a sphere the Lie solvers are
    exact, so any error would be a wrong end time."""
    omega0 = np.array([0.7, -1.3, 2.1])
    sol = lierk.solve(
        lierk.FreeRigidBody(np.eye(3), omega0), lierk.RKMK4(), 1.0, dt=0.3, saveat=lierk.SaveAt(steps=True)
    )
    np.testing.assert_allclose(sol.ts, [0.3, 0.6, 0.9, 1.0], rtol=1e-15)
    assert float(sol.ts[-1]) == 1.0
    assert int(sol.stats["num_steps"]) == 4
    np.testing.assert_allclose(sol.R[-1], so3.exp(1.0 * omega0), atol=1e-14)
    np.testing.assert_allclose(sol.R[2], so3.exp(0.9 * omega0), atol=1e-14)
    # 0.9 / 0.3 is 3.0000000000000004 in floating point: three steps, not a fourth of 1e-16 s.
    sol = lierk.solve(lierk.FreeRigidBody(np.eye(3), omega0), lierk.RKMK4(), 0.9, dt=0.3)
    assert int(sol.stats["num_steps"]) == 3
    np.testing.assert_allclose(sol.R[-1], so3.exp(0.9 * omega0), atol=1e-14)


def test_t0_nonzero_and_t1_equal_t0():
    sol = lierk.solve(_tee(), lierk.RKMK4(), 2.2, t0=1.0, dt=0.1)
    np.testing.assert_allclose(sol.R[-1], lierk.solve(_tee(), lierk.RKMK4(), 1.2, dt=0.1).R[-1], atol=1e-14)
    sol = lierk.solve(_tee(R0=R0_GENERIC), lierk.RKMK4(), 1.0, t0=1.0, dt=0.1)
    np.testing.assert_allclose(sol.R[-1], R0_GENERIC, atol=1e-15)


# --- jit and vmap -----------------------------------------------------------------------


def _final(omega0, R0, dt, max_steps=None, t1=1.2):
    return lierk.solve(lierk.FreeRigidBody(TEE, omega0, R0=R0), lierk.RKMK4(), t1, dt=dt, max_steps=max_steps).R[-1]


def test_jit_matches_eager():
    eager = _final(OMEGA_GENERIC, R0_GENERIC, 0.1)
    jitted = jax.jit(_final, static_argnames="max_steps")(OMEGA_GENERIC, R0_GENERIC, 0.1, max_steps=12)
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=1e-15)


def test_jit_with_constant_dt_needs_no_max_steps():
    """t1 and dt written as Python numbers inside a jitted function are known while
    tracing, so the step count can be read from them (only traced ones need max_steps)."""
    jitted = jax.jit(lambda w: _final(w, None, 0.1))(OMEGA_GENERIC)
    np.testing.assert_allclose(jitted, _final(OMEGA_GENERIC, None, 0.1), rtol=0, atol=1e-15)


def test_vmap_over_omega0_equals_loop():
    omegas = OMEGA_GENERIC + 0.3 * np.random.default_rng(7).standard_normal((4, 3))
    batched = jax.vmap(lambda w: _final(w, None, 0.1))(omegas)
    loop = np.stack([_final(w, None, 0.1) for w in omegas])
    np.testing.assert_allclose(batched, loop, rtol=0, atol=1e-14)
    assert np.abs(loop[0] - loop[1]).max() > 1e-3  # the sweep really varies


def test_vmap_over_R0_equals_loop():
    R0s = Rotation.random(3, random_state=8).as_matrix()
    batched = jax.jit(jax.vmap(lambda R0: _final(OMEGA_GENERIC, R0, 0.1, max_steps=12)))(R0s)
    loop = np.stack([_final(OMEGA_GENERIC, R0, 0.1) for R0 in R0s])
    np.testing.assert_allclose(batched, loop, rtol=0, atol=1e-14)


def test_vmap_over_dt_with_max_steps_equals_loop():
    """A traced dt needs a static step count; steps past t1 are exact no-ops, and the
    last step of each member is shortened to end at t1 (1.2/0.125 = 9.6)."""
    dts = np.array([0.1, 0.125, 0.2, 0.3])
    batched = jax.jit(jax.vmap(lambda dt: _final(OMEGA_GENERIC, None, dt, max_steps=12)))(dts)
    loop = np.stack([_final(OMEGA_GENERIC, None, dt) for dt in dts])
    np.testing.assert_allclose(batched, loop, rtol=0, atol=1e-14)
    assert np.abs(loop[0] - loop[-1]).max() > 1e-8


def test_vmap_over_the_times_and_atol_with_concrete_save_times_and_rtol():
    """The checks that read a traced neighbour (save times within [t0, t1],
    t1 >= t0, rtol + atol > 0) run in the program: they raised
    TracerBoolConversionError on the host before."""
    body = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    ts = np.array([0.5, 1.0])

    def saved(t0=0.0, t1=2.0, rtol=1e-9, atol=1e-9):
        return lierk.solve(body, lierk.DP54(), t1, t0=t0, rtol=rtol, atol=atol, saveat=lierk.SaveAt(ts=ts)).R

    for name, values, kw in (("t1", [1.5, 2.0], {}), ("t0", [0.0, 0.25], {}), ("atol", [1e-9, 1e-7], dict(rtol=0.0))):
        batched = jax.vmap(lambda v: saved(**{name: v}, **kw))(np.asarray(values))
        loop = np.stack([saved(**{name: v}, **kw) for v in values])
        np.testing.assert_allclose(batched, loop, rtol=0, atol=1e-13, err_msg=name)
    with pytest.raises(Exception, match=r"SaveAt\(ts=...\) must be non-decreasing and lie in \[t0, t1\]"):
        jax.vmap(lambda t1: saved(t1=t1))(np.array([1.5, 0.7]))


class _OwnLieEuler(lierk.AbstractSolver):
    """A solver of one's own that evaluates its first stage itself, given
    ``fsal`` or not (`AbstractSolver.dense_serves_first_stage` False)."""

    order = 1

    def step(self, problem, t, h, R, y, fsal=None):
        omega, ydot = problem.at(problem.base(t, R, y), t, y)
        return Step(lierk.so3.right_exp(R, h * omega), y + h * ydot, None, None)


def _counted_body():
    """A 1:2:3 body whose (zero) torque counts its evaluations at run time,
    a host callback: ``(problem, calls)``, ``calls[0]`` the count."""
    calls = [0]

    def bump():
        calls[0] += 1

    def torque(t):
        jax.debug.callback(bump)
        return jnp.zeros(3) * t

    return lierk.RigidBodyWithEffects(
        np.diag([1.0, 2.0, 3.0]), [0.1, 1.0, 0.05], effects=(lierk.TimedTorque(torque),)
    ), calls


def test_stats_count_every_field_evaluation():
    """``num_fevals`` against a count of the field's evaluations at run time
    (a host callback in the torque): stages, the first-step estimate, and
    the interpolants that events and dense output build (the Hermite node's
    field and rate at each step's end, DOP853's three extra stages).  Dense
    output builds one in every step, and the node's field then serves the
    next step's first stage, with fixed steps or an adaptive loop whose
    controller keeps no field (`ConstantStep`).  An event on a Hermite
    solver builds one only in the step where its condition changed sign,
    from the step's ends: both nodes, 4 evaluations for RKMK4 and CF4.  A
    splitting counts its drifts, and runs one kick more a step."""
    problem, calls = _counted_body()
    event = lierk.Event(lambda t, R, y: t - 0.55)
    dense = lierk.SaveAt(t1=True, dense=True)
    cases = [
        (lierk.RKMK4(), dict(dt=0.1), 80),
        (lierk.RKMK4(), dict(dt=0.1, event=event), 84),
        (lierk.RKMK4(), dict(dt0=0.1, controller=lierk.ConstantStep(), event=event), None),
        (lierk.CF4(), dict(dt=0.1, event=event), 84),
        (lierk.LieEuler(), dict(dt=0.1, saveat=dense), 42),
        (_OwnLieEuler(), dict(dt=0.1, saveat=dense), 62),  # its first stage its own: no saving, and none counted
        (lierk.DOP853(), dict(rtol=1e-8, atol=1e-8, saveat=dense), None),
        (lierk.DP54(), dict(rtol=1e-8, atol=1e-8, event=event), None),
    ]
    for solver, kw, expected in cases:
        calls[0] = 0
        stats = jax.device_get(lierk.solve(problem, solver, 2.0, **kw).stats)
        jax.effects_barrier()
        assert int(stats["num_fevals"]) == calls[0], (solver.name, kw, stats, calls[0])
        assert expected is None or calls[0] == expected
    calls[0] = 0
    stats = jax.device_get(lierk.solve(problem, lierk.BlanesMoan4(), 2.0, dt=0.1).stats)
    jax.effects_barrier()
    assert int(stats["num_fevals"]) == 20 * lierk.BlanesMoan4().stages and calls[0] == int(stats["num_fevals"]) + 20


def test_steps_past_t1_are_skipped_not_run():
    """A static step count far past the run's (a generous max_steps, or a
    scene's last piece padded to the others' length) ran every padding step
    as a no-op: ``lierk simulate`` with ``save_every = 10^9`` spun for ever.
    Chunks and checkpoint blocks that start past the end are skipped now;
    counted by a host callback in the torque, with and without events (the
    two fixed-step loops), saving chunks or not.  The same numbers."""
    problem, calls = _counted_body()
    event = lierk.Event(lambda t, R, y: t - 0.55)
    for kw in (dict(saveat=lierk.SaveAt(t0=True, steps=25, t1=True)), dict(saveat=lierk.SaveAt(t1=True), event=event)):
        counts, sols = [], []
        for max_steps in (None, 10**5):
            calls[0] = 0
            sols.append(jax.device_get(lierk.solve(problem, lierk.RKMK4(), 1.0, dt=0.01, max_steps=max_steps, **kw)))
            jax.effects_barrier()
            counts.append(calls[0])
        exact, padded = sols
        # The run's 100 steps, and at most the rest of the block of ~316 it ends in.
        assert int(exact.stats["num_steps"]) == int(padded.stats["num_steps"]) == 100
        assert counts[0] <= counts[1] <= counts[0] + 5 * 320, (kw, counts)
        n = int(exact.n_saved)
        np.testing.assert_array_equal(padded.R[: n - 1], exact.R[: n - 1])
        # The event's state is located in a conditional that each program
        # compiles on its own: equal to rounding.
        np.testing.assert_allclose(padded.R[-1], exact.R[-1], rtol=0, atol=4 * np.finfo(float).eps)
        np.testing.assert_allclose(padded.ts[-1], exact.ts[-1], rtol=4 * np.finfo(float).eps)


def test_max_steps_too_small_is_reported():
    sol = lierk.solve(_tee(), lierk.RKMK4(), 1.2, dt=0.1, max_steps=5, throw=False)
    assert int(sol.result) == lierk.RESULTS.max_steps_reached
    with pytest.raises(Exception, match="max_steps"):
        lierk.solve(_tee(), lierk.RKMK4(), 1.2, dt=0.1, max_steps=5)


@pytest.mark.parametrize("n", [257, 997, 1000])
def test_long_fixed_runs_take_exactly_their_steps_and_compile_the_step_once(n):
    """Runs of 256+ steps are scanned in checkpointed blocks; a step count
    with no divisor near its root runs a few no-op steps past the end
    instead of a second scan.  The state after n steps equals n steps taken
    one by one, the count of steps taken is n, and the compiled program has
    as many loops as for 32 x 32 steps, i.e. one copy of
    the step.  Cut short by max_steps, the state is that of max_steps steps."""
    dt = 2e-3
    body = _tee()
    solver = lierk.RKMK4()
    sol = lierk.solve(body, solver, n * dt, dt=dt)
    step = jax.jit(lambda R, y, t: solver.step(body, t, dt, R, y))
    R, y = body.R0, body.y0
    for k in range(n):
        st = step(R, y, k * dt)
        R, y = st.R, st.y
    assert int(sol.stats["num_steps"]) == n
    assert np.max(np.abs(np.asarray(sol.R[-1]) - np.asarray(R))) < 1e-13

    def loops(steps):
        text = jax.jit(lambda w: lierk.solve(_tee(w), solver, steps * dt, dt=dt).R[-1]).lower(OMEGA_GENERIC).as_text()
        return text.count("stablehlo.while")

    assert loops(n) == loops(1024)
    short = lierk.solve(body, solver, (n + 5) * dt, dt=dt, max_steps=n, throw=False)
    assert int(short.result) == lierk.RESULTS.max_steps_reached
    assert int(short.stats["num_steps"]) == n
    assert np.max(np.abs(np.asarray(short.R[-1]) - np.asarray(R))) < 1e-13


# --- derivatives ------------------------------------------------------------------------


def _fd_jacobian(f, x, eps):
    """Central differences with per-component steps eps (array like x)."""
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx.flat[i] = eps.flat[i]
        cols.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps.flat[i]))
    return np.stack(cols, axis=-1)


def _assert_rel(J, ref, rtol):
    rel = np.linalg.norm(np.asarray(J) - ref) / np.linalg.norm(ref)
    assert rel < rtol, rel


def _final_R(inertia, omega0, t1, dt):
    """Final R of RKMK4; t1 and dt are arguments (so one compilation serves the
    T-handle and the sphere cases), hence the static max_steps."""
    return lierk.solve(lierk.FreeRigidBody(inertia, omega0), lierk.RKMK4(), t1, dt=dt, max_steps=30).R[-1]


_final_R_jit = jax.jit(_final_R)
_jacfwd = jax.jit(jax.jacfwd(_final_R, argnums=(0, 1)))
_jacrev = jax.jit(jax.jacrev(_final_R, argnums=(0, 1)))


def test_jacobians_wrt_omega0_and_inertia_match_finite_differences():
    """jacfwd and jacrev with respect to omega0 (rad/s) and the (3, 3) inertia tensor,
    against central differences: along each omega0 component, each principal moment,
    and one symmetric off-diagonal perturbation of the tensor."""
    t1, dt = 1.5, 0.05
    eps_w, eps_I = 1e-6, 1e-5 * np.diag(TEE)
    fd_w = _fd_jacobian(lambda w: _final_R_jit(TEE, w, t1, dt), OMEGA_GENERIC, np.full(3, eps_w))
    fd_d = _fd_jacobian(lambda d: _final_R_jit(np.diag(d), OMEGA_GENERIC, t1, dt), np.diag(TEE).copy(), eps_I)
    S = np.array([[0.0, 1.0, 0.3], [1.0, 0.0, -0.5], [0.3, -0.5, 0.2]]) * 1e-5  # 10% of TEE
    eps_S = 1e-3
    fd_S = (
        np.asarray(_final_R_jit(TEE + eps_S * S, OMEGA_GENERIC, t1, dt))
        - np.asarray(_final_R_jit(TEE - eps_S * S, OMEGA_GENERIC, t1, dt))
    ) / (2 * eps_S)
    for fd in (fd_w, fd_d, fd_S):
        assert np.linalg.norm(fd) > 1e-2  # R really depends on each of them here
    for jac in (_jacfwd, _jacrev):
        J_I, J_w = (np.asarray(J) for J in jac(TEE, OMEGA_GENERIC, t1, dt))  # (3, 3, 3, 3), (3, 3, 3)
        _assert_rel(J_w, fd_w, 1e-7)
        _assert_rel(np.stack([J_I[..., k, k] for k in range(3)], axis=-1), fd_d, 1e-7)
        _assert_rel(np.einsum("abij,ij->ab", J_I, S), fd_S, 1e-7)


def test_sphere_jacobian_is_derivative_of_exp():
    """For I = c E the numerical solution is exp(t1 hat(omega0)) for every omega0, so
    its Jacobian is that of the exponential (here with a shortened last step)."""
    t1, dt = 1.3, 0.2
    w = np.array([0.7, -1.3, 2.1])
    exact = np.asarray(jax.jacfwd(lambda w: so3.exp(t1 * w))(w))
    for jac in (_jacfwd, _jacrev):
        np.testing.assert_allclose(jac(0.4 * np.eye(3), w, t1, dt)[1], exact, atol=1e-13)


# --- one compilation for every value ----------------------------------------------------


def test_fixed_step_solve_never_recompiles():
    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def final(inertia, omega0, dt):
        return lierk.solve(lierk.FreeRigidBody(inertia, omega0), lierk.RKMK4(), 1.0, dt=dt, max_steps=20).R[-1]

    cases = [
        (TEE, OMEGA_GENERIC, 0.1),
        (np.diag([1.0, 2.0, 3.0]), np.array([0.0, 1.0, 0.1]), 0.05),
        (TEE * 1e3, np.array([2.0, -0.1, 0.4]), 0.07),
    ]
    for inertia, omega0, dt in cases:
        out = final(np.asarray(inertia, float), omega0, np.float64(dt))
        np.testing.assert_allclose(out, _final_any(inertia, omega0, dt), rtol=0, atol=1e-14)


def _final_any(inertia, omega0, dt):
    return lierk.solve(lierk.FreeRigidBody(inertia, omega0), lierk.RKMK4(), 1.0, dt=dt).R[-1]


def test_adaptive_solve_never_recompiles():
    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def final(inertia, omega0, rtol):
        return lierk.solve(lierk.FreeRigidBody(inertia, omega0), lierk.DP54(), 1.0, rtol=rtol).R[-1]

    errs = []
    for rtol in [1e-4, 1e-6, 1e-8]:
        for inertia, omega0 in [(TEE, OMEGA_GENERIC), (np.diag([1.0, 2.0, 3.0]), np.array([0.0, 1.0, 0.1]))]:
            out = final(np.asarray(inertia, float), omega0, np.float64(rtol))
            errs.append(np.abs(np.asarray(out) - reference_R(inertia, omega0, 1.0)).max())
    # The tolerance is really used, not frozen at its first value.
    assert errs[0] > 10 * errs[-2] and errs[1] > 10 * errs[-1], errs


# --- fixed steps that end on given times ----------------------------------------------


def test_fixed_steps_end_on_the_save_times_with_one_program_for_every_step():
    """``dt=`` with ``SaveAt(ts=...)``: each gap between save times takes
    ceil(gap/dt) steps of dt, the last shortened to end on the time.  The
    counts are traced, so every dt and every ts of a length run one program;
    on a grid the save times share with ``SaveAt(steps=k)`` the states are
    those of the scan, and off it the error is still fourth order against
    the closed form."""
    body = lierk.FreeRigidBody(np.diag([1.0, 2.0, 3.0]), np.array([0.3, 1.0, 0.2]))

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(dt, ts):
        sol = lierk.solve(body, lierk.RKMK4(), 2.0, dt=dt, saveat=lierk.SaveAt(ts=ts))
        return sol.R, sol.stats["num_steps"]

    on_grid = np.linspace(0.0, 2.0, 5)
    for dt, every in ((0.1, 5), (0.05, 10)):
        R, steps = run(np.float64(dt), on_grid)
        scan = lierk.solve(body, lierk.RKMK4(), 2.0, dt=dt, saveat=lierk.SaveAt(t0=True, steps=every))
        np.testing.assert_allclose(R, scan.R, rtol=0, atol=1e-14)
        assert int(steps) == 20 * round(0.1 / dt)
    off_grid = np.array([0.0, 0.33, 0.9, 1.45, 2.0])
    exact = np.asarray(lierk.exact.free_rigid_body(np.diag([1.0, 2.0, 3.0]), body.omega0, off_grid)[0])
    errors = []
    for dt in (0.04, 0.02):
        R, steps = run(np.float64(dt), off_grid)
        gaps = np.diff(off_grid)
        assert int(steps) == int(np.sum(np.ceil(gaps / dt - 1e-9)))
        errors.append(np.abs(np.asarray(R) - exact).max())
    assert 3.8 < np.log2(errors[0] / errors[1]) < 4.2, errors


def test_fixed_steps_at_save_times_differentiate_and_estimate_their_error():
    """Forward and reverse mode (through `ForwardSensitivity`) agree with
    finite differences, and ``estimate_error=True`` (Richardson's, from a
    solve at 2/3 of the step) is the true error to within 10%."""
    ts = np.linspace(0.0, 1.5, 4)

    def final(w):
        return lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.RKMK4(), 1.5, dt=0.05, saveat=lierk.SaveAt(ts=ts)).R[-1]

    w = np.asarray(OMEGA_GENERIC, float)
    fwd, rev = jax.jit(jax.jacfwd(final))(w), jax.jit(jax.jacrev(final))(w)
    fd = np.stack([(final(w + 1e-6 * e) - final(w - 1e-6 * e)) / 2e-6 for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(fwd, fd, atol=1e-7)
    np.testing.assert_allclose(rev, fwd, atol=1e-12)
    sol = lierk.solve(
        lierk.FreeRigidBody(TEE, w), lierk.RKMK4(), 1.5, dt=0.05, saveat=lierk.SaveAt(ts=ts), estimate_error=True
    )
    err = np.linalg.norm(np.asarray(sol.R) - np.asarray(lierk.exact.free_rigid_body(TEE, w, ts)[0]), axis=(-2, -1))
    est = np.asarray(sol.error_estimate)
    np.testing.assert_allclose(est[1:], err[1:], rtol=0.1)


def test_fixed_steps_at_save_times_are_bounded_by_max_steps_and_a_bad_step_is_not_success():
    """``max_steps`` bounds the whole run: cut short, the rows not reached are
    NaN and uncounted, and the result says so; a step that is not a positive
    finite number gives NaN states and its code, not R0 with success."""
    body, ts = _tee(), np.linspace(0.0, 1.0, 5)
    full = lierk.solve(body, lierk.RKMK4(), 1.0, dt=0.05, saveat=lierk.SaveAt(ts=ts, t1=True))
    cut = lierk.solve(body, lierk.RKMK4(), 1.0, dt=0.05, saveat=lierk.SaveAt(ts=ts, t1=True), max_steps=12, throw=False)
    assert int(full.stats["num_steps"]) == 20 and int(full.n_saved) == 6
    assert int(cut.result) == lierk.RESULTS.max_steps_reached and int(cut.stats["num_steps"]) == 12
    assert int(cut.n_saved) == 3  # t = 0, 0.25, 0.5 reached
    np.testing.assert_array_equal(np.asarray(cut.R[:3]), np.asarray(full.R[:3]))
    assert np.isnan(np.asarray(cut.R[3:])).all()

    @jax.jit
    def run(dt):
        sol = lierk.solve(body, lierk.RKMK4(), 1.0, dt=dt, saveat=lierk.SaveAt(ts=ts), throw=False)
        return sol.result, sol.R

    for bad in (np.nan, -0.1, 0.0):
        code, R = run(np.float64(bad))
        assert int(code) == lierk.RESULTS.invalid_step and np.isnan(np.asarray(R)).all(), bad


def test_finer_options_reproduce_estimate_error():
    """`lierk.finer_options` and `lierk.richardson` compute by hand the very
    estimate of ``estimate_error=True``: fixed steps saving every even and
    odd k-th step, at save times, and adaptive steps by tolerance."""
    body = lierk.FreeRigidBody(np.diag([1.0, 2.0, 3.0]), np.array([0.3, 1.0, 0.2]))
    ts = np.array([0.0, 0.33, 0.8, 1.5])
    cases = [
        (lierk.RKMK4(), dict(dt=0.05, saveat=lierk.SaveAt(steps=4))),
        (lierk.RKMK4(), dict(dt=0.05, saveat=lierk.SaveAt(steps=3, t1=True))),
        (lierk.RKMK4(), dict(dt=0.05, saveat=lierk.SaveAt(ts=ts))),
        (lierk.DOP853(), dict(rtol=1e-7, dt0=0.3, saveat=lierk.SaveAt(ts=ts))),
    ]
    for solver, options in cases:
        sol = lierk.solve(body, solver, 1.5, estimate_error=True, **options)
        fine_options, ratio = lierk.finer_options(solver, **options)
        coarse = lierk.solve(body, solver, 1.5, **options)
        fine = lierk.solve(body, solver, 1.5, **fine_options)
        gap = np.linalg.norm(np.asarray(coarse.R) - np.asarray(fine.R), axis=(-2, -1))
        np.testing.assert_allclose(lierk.richardson(gap, ratio), sol.error_estimate, rtol=1e-6, atol=1e-15)


def test_fixed_steps_at_save_times_refuse_what_they_cannot_honour():
    body, ts = _tee(), np.linspace(0.0, 1.0, 3)
    for kw, match in (
        (dict(saveat=lierk.SaveAt(ts=ts, steps=2)), r"SaveAt\(ts=...\) and SaveAt\(steps=2\) cannot be combined"),
        (dict(saveat=lierk.SaveAt(ts=ts, dense=True)), "cannot keep dense output"),
        (dict(event=lierk.Event(lambda t, R, y: R[2, 2])), "event= with fixed steps"),
    ):
        kw = {"saveat": lierk.SaveAt(ts=ts), **kw}
        with pytest.raises(ValueError, match=match):
            lierk.solve(body, lierk.RKMK4(), 1.0, dt=0.1, **kw)


class _GrowingStep(lierk.AbstractStepController):
    """Each step 1.25 times the last, every one taken: a controller of a
    user's own, with no error estimate."""

    decides = False

    def init(self, problem, solver, t0, t1, dt0, floor_eps):
        return None, dt0, None

    def adapt(self, state, problem, solver, st, *, t, t_new, h, h_proposed, clipped, t1, R, y, f, rejected_last):
        return lierk.Decision(jnp.asarray(True), 1.25 * h_proposed, h <= 0, jnp.asarray(False), None)


def test_solve_takes_any_step_controller_and_constant_steps_end_on_save_times():
    """``controller=`` takes any `AbstractStepController`: `ConstantStep`
    (with dt0) takes the steps of ``dt=`` with ``SaveAt(ts=...)``, however
    its steps add up at the save times (without snapping the last step to
    the time, a step of a few ulps was left, and the solve failed), and a
    controller of one's own takes the steps it decides, with a
    non-adaptive solver when it needs no error estimate."""
    body = lierk.FreeRigidBody(np.diag([1.0, 2.0, 3.0]), np.array([0.3, 1.0, 0.2]))
    for t1, n, k in ((1.2, 4, 4), (1.0, 7, 3), (1.0, 7, 7), (0.7, 10, 7)):
        ts = np.linspace(0.0, t1, n)
        dt = t1 / (n - 1) / k
        a = lierk.solve(body, lierk.RKMK4(), t1, controller=lierk.ConstantStep(), dt0=dt, saveat=lierk.SaveAt(ts=ts))
        b = lierk.solve(body, lierk.RKMK4(), t1, dt=dt, saveat=lierk.SaveAt(ts=ts))
        assert int(a.stats["num_steps"]) == int(b.stats["num_steps"]) == (n - 1) * k
        np.testing.assert_allclose(a.R, b.R, rtol=0, atol=1e-15)
    sol = lierk.solve(body, lierk.RKMK4(), 1.0, controller=_GrowingStep(), dt0=0.01)
    steps = np.cumsum(0.01 * 1.25 ** np.arange(40))
    assert int(sol.stats["num_steps"]) == int(np.searchsorted(steps, 1.0 - 1e-12)) + 1
    exact = np.asarray(lierk.exact.free_rigid_body(np.diag([1.0, 2.0, 3.0]), body.omega0, 1.0)[0])
    assert np.abs(np.asarray(sol.R[-1]) - exact).max() < 1e-4
    for kw, match in (
        (dict(controller="pi"), "controller must be a lierk.AbstractStepController"),
        (dict(controller=lierk.ConstantStep()), "ConstantStep\\(\\) takes steps of dt0"),
        (dict(controller=lierk.ConstantStep(), dt0=0.1, estimate_error=True), "estimate_error=True compares"),
    ):
        with pytest.raises(ValueError, match=match):
            lierk.solve(body, lierk.RKMK4(), 1.0, **kw)
    with pytest.raises(ValueError, match="RKMK4 has no error estimate.*Controller decides on error estimates"):
        lierk.solve(body, lierk.RKMK4(), 1.0, controller=lierk.Controller(1e-6, 1e-6))


# --- bad input --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: _tee(omega0=[np.nan, 0.0, 1.0]), "omega0 has NaN or inf"),
        (lambda: _tee(omega0=[np.inf, 0.0, 1.0]), "omega0 has NaN or inf"),
        (lambda: _tee(omega0=np.ones(4)), r"omega0 must have shape \(3,\)"),
        (lambda: _tee(omega0=np.ones((3, 1))), r"omega0 must have shape \(3,\)"),
        (lambda: _tee(R0=1.00001 * np.eye(3)), "R0 must be a rotation"),
        (lambda: _tee(R0=np.diag([1.0, 1.0, -1.0])), "R0 must be a rotation"),
        (lambda: _tee(R0=np.full((3, 3), np.nan)), "R0"),
        (lambda: _tee(R0=np.eye(4)), r"R0 must have shape \(3, 3\)"),
        (lambda: _tee(inertia=np.array([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]])), "symmetric"),
        (lambda: _tee(inertia=np.diag([1.0, -1.0, 1.0])), "positive definite"),
        (lambda: _tee(inertia=np.diag([1.0, np.nan, 1.0])), "NaN"),
        (lambda: _tee(inertia=np.eye(2)), "shape"),
    ],
)
def test_bad_problem_raises(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_R0_within_tolerance_accepted():
    R0 = R0_GENERIC + 1e-8 * np.random.default_rng(9).standard_normal((3, 3))
    np.testing.assert_allclose(_tee(R0=R0).R0, R0, rtol=0, atol=0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(t1=1.0, dt=0.0), "dt must be > 0"),
        (dict(t1=1.0, dt=-0.1), "dt must be > 0"),
        (dict(t1=1.0, dt=np.nan), "dt must be finite"),
        (dict(t1=1.0, dt=np.array([0.1, 0.2])), "dt must be a scalar"),
        (dict(t1=-1.0, dt=0.1), "t1 must be >= t0"),
        (dict(t1=1.0, t0=2.0, dt=0.1), "t1 must be >= t0"),
        (dict(t1=np.inf, dt=0.1), "t1 must be finite"),
        (dict(t1=np.array([1.0, 2.0]), dt=0.1), "t1 must be a scalar"),
        (dict(t1=1.0), "needs a fixed step: pass dt="),
        (dict(t1=1.0, dt=0.1, rtol=1e-6), "rtol"),
        (dict(t1=1.0, dt=0.1, max_steps=0), "max_steps"),
        (dict(t1=1.0, dt=0.1, max_steps=2.5), "max_steps"),
        (dict(t1=1.0, dt=0.1, max_steps=True), "max_steps must be a positive Python int, got True"),
    ],
)
def test_bad_solve_arguments_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        lierk.solve(_tee(), lierk.RKMK4(), **kwargs)


def test_bad_adaptive_and_structural_arguments_raise():
    with pytest.raises(ValueError, match="rtol"):
        lierk.solve(_tee(), lierk.DP54(), 1.0)
    with pytest.raises(ValueError, match="dt0 must be > 0"):
        lierk.solve(_tee(), lierk.DP54(), 1.0, rtol=1e-6, dt0=-1.0)
    with pytest.raises(ValueError, match="problem"):
        lierk.solve(np.eye(3), lierk.RKMK4(), 1.0, dt=0.1)
    with pytest.raises(ValueError, match="solver"):
        lierk.solve(_tee(), "RKMK4", 1.0, dt=0.1)
    with pytest.raises(ValueError, match="SaveAt"):
        lierk.SaveAt()
    with pytest.raises(ValueError, match="max_steps"):
        jax.jit(lambda dt: lierk.solve(_tee(), lierk.RKMK4(), 1.0, dt=dt).R)(0.1)


def test_bad_traced_values_raise_at_run_time():
    run = jax.jit(lambda dt, w: lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.RKMK4(), 1.0, dt=dt, max_steps=10).R[-1])
    np.testing.assert_allclose(run(0.1, OMEGA_GENERIC), _final_any(TEE, OMEGA_GENERIC, 0.1), atol=1e-15)
    with pytest.raises(Exception, match="dt must be > 0"):
        run(-0.1, OMEGA_GENERIC)
    with pytest.raises(Exception, match="dt must be > 0"):
        run(0.0, OMEGA_GENERIC)
    with pytest.raises(Exception, match="dt"):
        run(np.nan, OMEGA_GENERIC)
    with pytest.raises(Exception, match="omega0"):
        run(0.1, np.array([np.nan, 0.0, 1.0]))


def test_chosen_setting_names_the_setting_target_error_chose():
    body = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    fixed = lierk.solve(body, lierk.RKMK4(), 1.0, target_error=1e-6)
    assert fixed.chosen_setting() == f"dt = {float(fixed.stats['dt']):.4g} s"
    # The chosen step is the one the returned (finer) solution took.
    assert int(fixed.stats["num_steps"]) == int(np.ceil(1.0 / float(fixed.stats["dt"]) - 1e-9))
    adaptive = lierk.solve(body, lierk.DP54(), 1.0, target_error=1e-6)
    assert adaptive.chosen_setting() == f"rtol = atol = {float(adaptive.stats['rtol']):.3g}"
    assert lierk.solve(body, lierk.RKMK4(), 1.0, dt=0.1).chosen_setting() is None


def test_solver_registry_names_every_solver_and_refuses_unknown_names():
    for name, cls in lierk.SOLVERS.items():
        assert lierk.solver_class(name.lower()) is cls and cls().name == name
    with pytest.raises(ValueError, match=r"unknown solver 'RK5'; choose from: ExplicitEuler, .*DOP853"):
        lierk.solver_class("RK5")
