"""Dense output on SO(3) (`SaveAt(dense=True)`, `Solution.evaluate`):
interpolation order by fitted slopes against `lierk.exact`, the error between
steps against the error at the steps (for the splittings, whose interpolant
is a shortened step, on a free body against `lierk.exact` and on a heavy top
against a fine DOP853 solve), events found on a splitting's interpolant, and
evaluate under jit, vmap and autodiff."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TEE, fd_from_values, fd_points, order_fit

import lierk
import lierk.exact

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
    err = np.linalg.norm(
        np.asarray(_one_step_midpoints(BODY, lierk.DP54(), hs)) - np.asarray(exact_R(hs / 2)), axis=(1, 2)
    )
    assert order_fit(hs, err) >= 6 - 0.15


# A symmetric heavy top (Simo and Wong's, spin 50 rad/s), where the
# splittings' steps are not exact; its drift is two rotations, cheap to
# compile.  Reference: DOP853 at rtol 1e-13 with steps ending on every
# time asked for (no interpolation), within 1.6e-12 of a BlanesMoanRKN6
# solve at dt = 0.0025 s (itself within 1.1e-14 of dt = 0.005 s).
TOP = lierk.RigidBodyWithEffects(
    [5.0, 5.0, 1.0],
    [0.3, 0.0, 50.0],
    R0=lierk.so3.exp(np.array([0.0, 0.3, 0.0])),
    effects=(lierk.Gravity([0.0, 0.0, 1.0], 20.0 / 9.81, 9.81),),
)
MIDPOINT_HS = np.geomspace(0.03, 0.1, 4)
# Every multiple of 4 ms (the steps of 0.04 s and 0.08 s, and tenths of
# them), every 5 ms (0.1 s and tenths) and the midpoints of MIDPOINT_HS.
_TOP_TIMES = np.unique(np.round(np.concatenate([np.arange(251) * 0.004, np.arange(201) * 0.005, MIDPOINT_HS / 2]), 12))
_TOP_REFERENCE = []


def top_reference(t):
    """The reference attitudes ``(n, 3, 3)`` at times ``t`` ``(n,)`` of `_TOP_TIMES`."""
    if not _TOP_REFERENCE:
        saveat = lierk.SaveAt(ts=_TOP_TIMES)
        sol = lierk.solve(TOP, lierk.DOP853(), 1.0, rtol=1e-13, atol=1e-13, max_steps=1000, saveat=saveat)
        _TOP_REFERENCE.append(np.asarray(sol.R)[: int(sol.n_saved)])
    i = np.abs(_TOP_TIMES[None, :] - np.asarray(t, np.float64)[:, None]).argmin(axis=1)
    assert np.abs(_TOP_TIMES[i] - t).max() < 1e-12
    return _TOP_REFERENCE[0][i]


def test_splitting_interpolant_orders_on_a_heavy_top():
    # A splitting's interpolant is a step of the method of size theta h, so
    # at mid-step its error from the exact start is the local error of a
    # step of h/2: slope p + 1 (measured 3.00 and 5.00; errors 5.6e-6 to
    # 2.1e-4 and 4.0e-11 to 1.7e-8).  The quintic Hermite interpolant it
    # replaces had slopes 5.7 and 9.2 at these steps (1.5 to 5 rad per
    # step): its own error, 2e-5 to 3e-2 and 4e-7 to 3e-2, swamped both
    # methods' errors.
    hs = MIDPOINT_HS
    ref = top_reference(hs / 2)
    for solver, order in ((lierk.Strang(), 2), (lierk.BlanesMoan4(), 4)):
        err = np.linalg.norm(np.asarray(_one_step_midpoints(TOP, solver, hs)) - ref, axis=(1, 2))
        assert err.min() > 2e-11  # above the reference's error (1.6e-12)
        assert order_fit(hs, err) == pytest.approx(order + 1, abs=0.15), (solver.name, err)


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


def _errors_at_and_between_steps(sol, exact):
    """The largest attitude error at the saved steps and at five points
    inside every step, against ``exact(t) -> R``."""
    k = int(sol.n_saved)
    node = np.linalg.norm(np.asarray(sol.R)[:k] - exact(np.asarray(sol.ts)[:k]), axis=(1, 2)).max()
    n = int(sol.interpolation.n)
    starts, hs = np.asarray(sol.interpolation.ts)[:n], np.asarray(sol.interpolation.hs)[:n]
    t_mid = (starts[:, None] + np.array([0.1, 0.3, 0.5, 0.7, 0.9]) * hs[:, None]).ravel()
    mid = np.linalg.norm(np.asarray(sol.evaluate(t_mid)[0], np.float64) - exact(t_mid), axis=(1, 2)).max()
    return node, mid


# The slow free body of issue 38 (|omega| = 2.1 rad/s), asymmetric (the
# splittings' drift is the elliptic-function flow) or symmetric (two
# rotations): either way the splittings' steps are exact to rounding.
SLOW_I, SLOW_OMEGA = np.array([1.0, 2.0, 3.0]), np.array([1.2, 1.0, 1.4])
SYMMETRIC_I = np.array([1.0, 1.0, 2.0])
_exact_R_at = jax.jit(
    jax.vmap(lambda inertia, w, t: lierk.exact.free_rigid_body(inertia, w, t)[0], in_axes=(None, None, 0))
)


def exact_R_of(inertia, omega0, t, piece=512):
    """`lierk.exact`'s attitudes ``(n, 3, 3)`` at times ``t`` ``(n,)`` (s)
    from the identity: one compiled program for every body, in pieces."""
    t = np.asarray(t, np.float64).ravel()
    padded = np.concatenate([t, np.zeros(-t.size % piece)])
    inertia, omega0 = np.asarray(inertia, np.float64), np.asarray(omega0, np.float64)
    out = [np.asarray(_exact_R_at(inertia, omega0, padded[i : i + piece])) for i in range(0, padded.size, piece)]
    return np.concatenate(out)[: t.size]


@pytest.mark.parametrize(
    "solver, dt, inertia",
    # BlanesMoan6 on the asymmetric body (the elliptic drift, in a loop over
    # the stages), the others on a symmetric one (the two-rotation drift,
    # unrolled: seconds less to compile, and the same failure before).
    [
        (lierk.BlanesMoan6(), 0.2, SLOW_I),
        (lierk.Strang(), 0.05, SYMMETRIC_I),
        (lierk.Yoshida4(), 0.1, SYMMETRIC_I),
        (lierk.BlanesMoan4(), 0.1, SYMMETRIC_I),
    ],
    ids=["BlanesMoan6", "Strang-symmetric", "Yoshida4-symmetric", "BlanesMoan4-symmetric"],
)
def test_splitting_dense_output_on_a_free_body_is_exact_to_rounding(solver, dt, inertia):
    # Measured at the steps and between them: 1.1e-14 and 1.6e-14
    # (BlanesMoan6), 4.9e-15 and 4.8e-15 (Strang), 6.7e-15 and 7.0e-15
    # (Yoshida4), 6.9e-15 and 6.9e-15 (BlanesMoan4).  The quintic Hermite
    # interpolant gave 1.6e-7, 2.1e-12, 1.5e-10 and 1.5e-10 between the
    # steps: 440 to 1.4e7 times the steps' error (and Strang on the
    # asymmetric body 3.7e-11, 5.6e3 times).
    body = lierk.FreeRigidBody(inertia, SLOW_OMEGA)
    sol = lierk.solve(body, solver, 4.0, dt=dt, saveat=lierk.SaveAt(steps=1, dense=True))
    node, mid = _errors_at_and_between_steps(sol, lambda t: exact_R_of(inertia, SLOW_OMEGA, t))
    assert node < 1e-13
    assert mid <= max(3 * node, 1e-13), (mid, node)


@pytest.mark.parametrize(
    "solver, dt",
    [(lierk.BlanesMoan4(), 0.04), (lierk.BlanesMoanRKN4(), 0.04), (lierk.BlanesMoan6(), 0.08)],
    ids=lambda x: getattr(x, "name", None),
)
def test_splitting_dense_output_on_a_heavy_top_is_as_accurate_as_its_steps(solver, dt):
    # Measured at the steps and between them: 3.2e-8 and 3.3e-8
    # (BlanesMoan4), 1.5e-9 and 1.5e-9 (BlanesMoanRKN4), 1.75e-9 and
    # 1.76e-9 (BlanesMoan6).  The quintic Hermite interpolant's own error
    # at 2 to 4 rad per step, 5.5e-6 to 2.6e-3 between the steps, was 170 to
    # 1.5e6 times the steps' there.  (Checked by hand, not kept for its
    # compile time: BlanesMoanRKN6 at dt = 0.1, 9.0e-10 and 8.9e-10, where
    # Hermite gave 5.8e-2.  Strang's and Yoshida4's steps are coarse enough
    # that on this top the Hermite interpolant kept within 1.01 of them at
    # the steps they need; the free body above covers them.)
    sol = lierk.solve(TOP, solver, 1.0, dt=dt, saveat=lierk.SaveAt(steps=1, dense=True))
    node, mid = _errors_at_and_between_steps(sol, top_reference)
    assert node > 1e-10  # far above the reference's error
    assert mid <= 3 * node, (mid, node)


def test_splitting_dense_output_in_float32():
    # A sanity check (the Hermite interpolant passed it too): the
    # interpolation keeps the problem in its own dtype, float32 in, float32
    # out, within float32 rounding of the float64 solve at and between the
    # steps (measured 5.1e-6 and 4.3e-6; the time's own rounding, 6e-8 s at
    # t = 1 s, is 3e-6 at 50 rad/s).
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    top32 = lierk.RigidBodyWithEffects(
        f32([5.0, 5.0, 1.0]),
        f32([0.3, 0.0, 50.0]),
        R0=f32(TOP.R0),
        effects=(lierk.Gravity(f32([0.0, 0.0, 1.0]), f32(20.0 / 9.81), f32(9.81)),),
    )
    saveat = lierk.SaveAt(steps=1, dense=True)
    sol32 = lierk.solve(top32, lierk.BlanesMoan4(), 1.0, dt=0.04, saveat=saveat)
    sol64 = lierk.solve(TOP, lierk.BlanesMoan4(), 1.0, dt=0.04, saveat=saveat)
    t = np.concatenate([np.asarray(sol32.ts), np.float32(0.04) * (np.arange(25, dtype=np.float32) + np.float32(0.5))])
    R32 = sol32.evaluate(t)[0]
    assert R32.dtype == jnp.float32 and sol32.evaluate(np.float32(0.5))[0].dtype == jnp.float32
    err = np.linalg.norm(np.asarray(R32, np.float64) - np.asarray(sol64.evaluate(t.astype(np.float64))[0]), axis=(1, 2))
    at_steps, between = err[: len(sol32.ts)].max(), err[len(sol32.ts) :].max()
    assert at_steps < 2e-5 and between < 2e-5, (at_steps, between)


def test_splitting_events_on_a_free_body_match_the_exact_times():
    # Events are found on the same interpolant.  On a symmetric free body
    # the body momentum's (m1, m2) turns at Omega = m3 (1/I1 - 1/I3), so m1
    # is zero at (pi/2 + k pi - phi0) / Omega.  Strang at dt = 0.5 s (0.7
    # rad a step): measured 1.8e-15 s; on the quintic Hermite interpolant
    # 1.3e-7 s.  (The T-handle's flip, on the elliptic drift, was checked
    # alike: 5.5e-13 s against 1.0e-8 s; not kept, for its compile time.)
    body = lierk.FreeRigidBody(SYMMETRIC_I, SLOW_OMEGA)
    m = SYMMETRIC_I * SLOW_OMEGA
    omega = m[2] * (1 / SYMMETRIC_I[0] - 1 / SYMMETRIC_I[2])
    ref = (np.pi / 2 + np.arange(5) * np.pi - np.arctan2(m[1], m[0])) / omega
    assert 9.5 < ref[-1] < 10.0
    sol = lierk.solve(body, lierk.Strang(), 10.0, dt=0.5, event=lierk.Event(lambda t, R, m: m[0]))
    assert int(sol.events.count) == 5
    np.testing.assert_allclose(np.asarray(sol.events.ts)[:5], ref, rtol=0, atol=1e-12)
    # The states recorded there are the exact ones.
    assert np.abs(np.asarray(sol.events.R)[:5] - exact_R_of(SYMMETRIC_I, SLOW_OMEGA, ref)).max() < 1e-13
    assert np.abs(np.asarray(sol.events.y)[:5, 0]).max() < 1e-14


def test_splitting_evaluate_under_jit_vmap_and_autodiff():
    # A symmetric free body (the two-rotation drift: cheap to compile),
    # where the interpolant is exact.  Concrete times are evaluated in
    # chunks of one compiled step, traced ones in the caller's program (here
    # also vmapped over a batch of solutions and differentiated in time):
    # the same numbers, and the time derivative is the motion's R hat(omega).
    # (The derivative in a solve's input, through the kicks the interpolant
    # takes, was checked by hand: d R(t)/dg of a heavy top within 3e-12 of
    # central differences; a forward-mode solve costs 16 s of CPU to compile.)
    body = lierk.FreeRigidBody(SYMMETRIC_I, SLOW_OMEGA)

    def solve(w):
        saveat = lierk.SaveAt(steps=1, dense=True)
        return lierk.solve(body.with_omega0(w), lierk.BlanesMoan4(), 2.0, dt=0.1, saveat=saveat)

    sol = solve(SLOW_OMEGA)
    ts = np.concatenate([[0.0, 0.03, 0.5, 1.37, 1.999], np.asarray(sol.ts)])
    R, m = sol.evaluate(ts)
    np.testing.assert_allclose(sol.evaluate(1.37)[0], R[3], rtol=0, atol=1e-15)
    assert sol.evaluate(np.zeros((2, 0)))[0].shape == (2, 0, 3, 3)
    # At the steps (theta = 0, and theta = 1 at t1): the start and the saved states.
    np.testing.assert_array_equal(R[0], body.R0)
    np.testing.assert_allclose(R[5:], sol.R, rtol=0, atol=1e-15)
    assert np.abs(np.asarray(R) - exact_R_of(SYMMETRIC_I, SLOW_OMEGA, ts)).max() < 1e-13

    omegas = np.array([SLOW_OMEGA, [0.2, 1.0, -0.1]])
    times = np.array([1.37, 0.73])
    batch = jax.vmap(solve)(jnp.asarray(omegas))
    at = jax.jit(jax.vmap(lambda s, t: jax.jvp(s.evaluate, (t,), (jnp.ones_like(t),))))
    (Rb, mb), (dRb, _) = at(batch, jnp.asarray(times))
    np.testing.assert_allclose(Rb[0], R[3], rtol=0, atol=1e-15)  # traced and concrete
    for i in range(2):
        np.testing.assert_allclose(Rb[i], exact_R_of(SYMMETRIC_I, omegas[i], times[i : i + 1])[0], rtol=0, atol=1e-13)
        np.testing.assert_allclose(dRb[i], Rb[i] @ lierk.so3.hat(mb[i] / SYMMETRIC_I), rtol=0, atol=1e-13)


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
    np.testing.assert_allclose(
        R, lierk.so3.exp(jnp.array([0.25, 0.5, 1.5])[:, None] * jnp.array([0.0, 0.0, 4.0])), atol=1e-13
    )


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


def test_jit_of_the_bound_evaluate_gives_the_eager_values():
    """``jax.jit(sol.evaluate)`` raised ``TypeError: unhashable type``
    (equinox's bound methods hash the solution's arrays); a lambda around it
    worked.  The bound method is still a pytree: it can be passed into jit."""
    sol = lierk.solve(BODY, lierk.RKMK4(), 2.0, dt=0.1, saveat=lierk.SaveAt(dense=True))
    ts = jnp.array([0.0, 0.03, 0.5, 1.37, 2.0])
    R, m = sol.evaluate(ts)
    Rj, mj = jax.jit(sol.evaluate)(ts)
    np.testing.assert_allclose(Rj, R, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mj, m, rtol=1e-15)
    Rp, _ = jax.jit(lambda evaluate, t: evaluate(t))(sol.evaluate, ts)
    np.testing.assert_allclose(Rp, R, rtol=0, atol=1e-15)
    assert sol.evaluate == sol.evaluate and hash(sol.evaluate) == hash(sol.evaluate)
    assert sol.evaluate.__doc__ == lierk.Solution.evaluate.__doc__


def test_evaluate_is_differentiable_in_t_and_in_the_inputs():
    def R_at(w, t):
        sol = lierk.solve(BODY.with_omega0(w), lierk.RKMK4(), 2.0, dt=0.05, saveat=lierk.SaveAt(dense=True))
        return sol.evaluate(t)

    t = 1.2345  # inside a step
    w = jnp.asarray(OMEGA)
    # Every derivative and the differences' values from one program.
    J, g, dR, (R, m), values = eqx.filter_jit(
        lambda w, t: (
            jax.jacfwd(lambda w: R_at(w, t)[0].ravel())(w),
            jax.grad(lambda w: R_at(w, t)[0][0, 2])(w),
            jax.jacfwd(lambda t: R_at(w, t)[0])(t),
            R_at(w, t),
            jax.vmap(lambda p: R_at(p, t)[0].ravel())(jnp.asarray(fd_points(OMEGA, 1e-3))),
        )
    )(w, jnp.asarray(t))
    np.testing.assert_allclose(J, fd_from_values(values, 1e-3), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(g, J[2], rtol=1e-10, atol=1e-13)
    # d/dt of the interpolant is the motion's dR/dt = R hat(omega), to the
    # interpolant's accuracy.
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
    # Nor an interpolant built apart for an event's crossing step.
    with pytest.raises(ValueError, match="leaves SO\\(3\\)"):
        lierk.solve(BODY, lierk.ExplicitEuler(), 1.0, dt=0.1, event=lierk.Event(lambda t, R, y: t - 0.55))


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

    import lierk._event
    import lierk._solvers.base
    import lierk._solvers.rkmk

    for cls in (lierk.AbstractSolver, lierk.AbstractRKMK):
        monkeypatch.setattr(cls, "dense_step", broken)
        monkeypatch.setattr(cls, "dense_node", broken)
    for name in ("init", "process", "records"):
        monkeypatch.setattr(lierk._event, name, broken)
    jax.clear_caches()  # trace anew, not from a solve an earlier test compiled
    w = jnp.asarray(OMEGA)
    jax.make_jaxpr(lambda w: lierk.solve(BODY.with_omega0(w), lierk.RKMK4(), 1.0, dt=0.1).R)(w)
    jax.make_jaxpr(
        lambda w: (
            lierk.solve(
                BODY.with_omega0(w), lierk.DOP853(), 1.0, rtol=1e-8, saveat=lierk.SaveAt(steps=True), max_steps=16
            ).R
        )
    )(w)
    with pytest.raises(AssertionError, match="reached"):
        jax.make_jaxpr(
            lambda w: lierk.solve(BODY.with_omega0(w), lierk.RKMK4(), 1.0, dt=0.1, saveat=lierk.SaveAt(dense=True)).R
        )(w)


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
        ours = y0 + lierk._interpolation.nested(F, theta)
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
