"""Reaction wheels driven by motor torques (`lierk.ReactionWheels`): Basilisk's
balanced wheels, whose speeds are integrated with the body.

Against Basilisk's closed-form despin, an independent SciPy integration of
the same equations (written out here in NumPy, with the angular velocity as
state), the conservation of the total momentum and the motors' work on the
energy; every RKMK, Crouch-Grossman and adaptive solver; events, dense
output, restarts, sensitivities (both methods), vmap, float32, scenes; the
splittings refused; bad input refused by name.  `Rotor`, a speed-controlled
wheel, gives a different (documented) answer for the same motor torque."""

import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import lierk

# Basilisk's despin: a body of I = diag(2, 2, 2 + Js) spinning about z, one
# wheel along z at 100 RPM driven with u.  The body's rate falls at u / I1
# (I1 = I3 - Js = 2), the wheel speeds up at u / Js + u / I1.
JS, W0, U, I1, SPIN = 0.159, 100 * 2 * np.pi / 60, 0.2, 2.0, 0.35


def despin(torque=U, dtype=np.float64, **wheel):
    wheels = lierk.ReactionWheels(
        np.array([[0.0, 0.0, 1.0]], dtype),
        np.array([JS], dtype),
        np.array([W0], dtype),
        torque=np.array([torque], dtype),
        **wheel,
    )
    return lierk.RigidBodyWithEffects(
        np.array([I1, I1, I1 + JS], dtype), np.array([0.0, 0.0, SPIN], dtype), effects=(wheels,)
    )


def despin_exact(t):
    """``(omega_z, Omega)`` of the despin (Basilisk's closed form)."""
    return SPIN - U * t / I1, W0 + U * t * (1 / JS + 1 / I1)


# A 1:2:3-ish body with products of inertia and four skewed wheels (a pyramid).
I_BODY = np.array([[3.0, 0.1, -0.05], [0.1, 5.0, 0.2], [-0.05, 0.2, 7.0]])
AXES = np.array([[1.0, 0.0, 0.4], [0.0, 1.0, 0.4], [-1.0, 0.0, 0.4], [0.1, -1.0, 0.4]])
AXES_UNIT = AXES / np.linalg.norm(AXES, axis=1, keepdims=True)
JS4 = np.array([0.05, 0.06, 0.07, 0.04])
SPEEDS4 = np.array([20.0, -10.0, 5.0, 30.0])
OMEGA0 = np.array([0.1, -0.2, 0.3])
R0 = np.asarray(lierk.so3.exp(jnp.asarray([0.2, 0.1, -0.3])))


def u_smooth(t, xp=jnp):
    return 0.01 * xp.stack([xp.sin(t), xp.cos(0.5 * t), -1.0 + 0.0 * t, 0.3 * xp.sin(2.0 * t)])


T_SAMPLES = np.array([0.0, 5.0, 10.0, 20.0])
U_SAMPLES = np.array(
    [[0.0, 0.0, 0.0, 0.0], [0.02, -0.01, 0.005, 0.0], [0.0, 0.01, -0.02, 0.01], [0.0, 0.0, 0.0, -0.01]]
)


def u_sampled(t):
    return np.array([np.interp(t, T_SAMPLES, U_SAMPLES[:, i]) for i in range(4)])


def hat(a):
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def basilisk_rhs(I, axes, Js, u, tau):
    """Basilisk's balanced wheels with the angular velocity as state:
    ``x = (R (9), omega (3), Omega (k))``; ``u(t)`` the motor torques,
    ``tau(t, R, omega)`` the external torque (body frame)."""
    G = (axes.T * Js) @ axes

    def f(t, x):
        R, w, Om = x[:9].reshape(3, 3), x[9:12], x[12:]
        ut = u(t)
        H = I @ w + axes.T @ (Js * Om)
        dw = np.linalg.solve(I - G, -np.cross(w, H) - axes.T @ ut + tau(t, R, w))
        return np.concatenate([(R @ hat(w)).ravel(), dw, ut / Js - axes @ dw])

    return f


def scipy_final(f, omega0, speeds, t1, breaks=()):
    """SciPy's DOP853 at rtol 1e-12, restarted at the torque samples' kinks."""
    x = np.concatenate([R0.ravel(), omega0, speeds])
    ts = [0.0, *[b for b in breaks if 0 < b < t1], t1]
    for a, b in zip(ts[:-1], ts[1:]):
        x = solve_ivp(f, (a, b), x, method="DOP853", rtol=1e-12, atol=1e-14).y[:, -1]
    return x[:9].reshape(3, 3), x[9:12], x[12:]


def pyramid(torque=None, times=None, effects=()):
    wheels = lierk.ReactionWheels(AXES, JS4, SPEEDS4, torque=torque, times=times)
    return lierk.RigidBodyWithEffects(I_BODY, OMEGA0, R0, effects=(wheels, *effects))


def omega_and_speeds(body, sol):
    return np.asarray(body.angular_velocity(sol.R, sol.y)), np.asarray(sol.y[1])


# --- the despin: Basilisk's closed form --------------------------------------------


@pytest.mark.parametrize(
    "solver, kw",
    [
        (lierk.RKMK4(), dict(dt=0.05)),
        (lierk.CF4(), dict(dt=0.05)),
        (lierk.LieEuler(), dict(dt=0.05)),
        (lierk.RKF45(), dict(rtol=1e-8)),
        (lierk.DP54(), dict(rtol=1e-8)),
        (lierk.DOP853(), dict(rtol=1e-8)),
    ],
    ids=lambda x: getattr(x, "name", ""),
)
def test_despin_follows_basilisks_closed_form(solver, kw):
    """Rates linear in time: every consistent method is exact to rounding."""
    body = despin()
    saveat = lierk.SaveAt(t0=True, steps=20) if "dt" in kw else lierk.SaveAt(ts=jnp.linspace(0.0, 5.0, 6))
    sol = lierk.solve(body, solver, 5.0, saveat=saveat, **kw)
    w, speeds = omega_and_speeds(body, sol)
    wz, Om = despin_exact(np.asarray(sol.ts))
    assert np.asarray(sol.ts).tolist() == pytest.approx([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_allclose(w[:, 2], wz, rtol=0, atol=1e-12)  # -0.15 rad/s at 5 s
    np.testing.assert_allclose(speeds[:, 0], Om, rtol=1e-13)
    np.testing.assert_allclose(w[:, :2], 0.0, atol=1e-15)


def test_the_speed_controlled_rotor_is_another_model():
    """`Rotor` with ``torque=`` prescribes the wheel's speed relative to the
    body: the same 0.2 N m slows the body at u / I3, not u / (I3 - Js)
    (-0.113 rad/s at 5 s where the driven wheel gives -0.15)."""
    rotor = lierk.Rotor([JS * W0], axes=[[0.0, 0.0, 1.0]], torque=[[U], [U]], times=[0.0, 10.0])
    body = lierk.RigidBodyWithEffects([I1, I1, I1 + JS], [0.0, 0.0, SPIN], effects=(rotor,))
    sol = lierk.solve(body, lierk.RKMK4(), 5.0, dt=0.05)
    wz = float(body.angular_velocity(sol.R[-1], sol.y[-1])[2])
    np.testing.assert_allclose(wz, SPIN - 5.0 * U / (I1 + JS), rtol=1e-12)
    assert abs(wz - despin_exact(5.0)[0]) > 0.03


# --- conservation and the motors' work ----------------------------------------------


def kinetic_energy_np(w, Om):
    """The platform (every mass, the wheels' spin about their axes aside)
    turning at omega with inertia I - G, plus each wheel's spin at its
    absolute rate Omega + g . omega: the kinetic energy from first principles."""
    G = (AXES_UNIT.T * JS4) @ AXES_UNIT
    return 0.5 * np.einsum("ti,ij,tj->t", w, I_BODY - G, w) + 0.5 * np.sum(JS4 * (Om + w @ AXES_UNIT.T) ** 2, axis=1)


@pytest.mark.parametrize("driven", [False, True], ids=["free", "driven"])
def test_total_momentum_conserved_and_energy_changes_by_the_motors_work(driven):
    body = pyramid(torque=(lambda t: u_smooth(t)) if driven else None)
    assert set(body.conserved()) == ({"|L|"} if driven else {"|L|", "energy"})
    ts = np.linspace(0.0, 20.0, 2001)
    sol = lierk.solve(body, lierk.DOP853(), 20.0, rtol=1e-12, atol=1e-12, saveat=lierk.SaveAt(ts=jnp.asarray(ts)))
    assert int(sol.result) == 0
    w, Om = omega_and_speeds(body, sol)
    R, m = np.asarray(sol.R), np.asarray(sol.y[0])
    # The whole spacecraft's momentum, in space.
    L = np.einsum("tij,tj->ti", R, m + (JS4 * Om) @ AXES_UNIT)
    assert np.max(np.linalg.norm(L - L[0], axis=1)) < 1e-11 * np.linalg.norm(L[0])
    q = sol.invariants(body)
    np.testing.assert_allclose(np.asarray(q["|L|"]), np.linalg.norm(L, axis=1), rtol=1e-13)
    # The energy invariant is the kinetic energy of the body and its wheels ...
    E = np.asarray(q["energy"])
    np.testing.assert_allclose(E, kinetic_energy_np(w, Om), rtol=1e-13)
    if not driven:
        assert np.max(np.abs(E - E[0])) < 1e-11 * E[0]
        # A free wheel keeps its absolute spin momentum, not its relative speed.
        h = JS4 * (Om + w @ AXES_UNIT.T)
        assert np.max(np.abs(h - h[0])) < 1e-11 * np.max(np.abs(h[0]))
        assert np.max(np.abs(Om - Om[0])) > 0.01
        return
    # ... and it changes by the motors' work, int sum u Omega dt (Simpson).
    power = np.sum(np.asarray(u_smooth(ts, np)).T * Om, axis=1)
    work = np.concatenate([[0.0], np.cumsum((power[:-2:2] + 4 * power[1:-1:2] + power[2::2]) * (ts[1] - ts[0]) / 3)])
    np.testing.assert_allclose(E[::2] - E[0], work, rtol=0, atol=1e-10 * E[0])
    assert np.max(np.abs(work)) > 0.01 * E[0]  # 2% of the energy: 1e8 times the bound above


# --- against SciPy, with external torques -------------------------------------------------

N_GG = 0.05  # rad/s: a fast "orbit", so that the gravity gradient matters over 30 s


def gg_torque(t, R, w):
    ub = R.T @ np.array([np.cos(N_GG * t), np.sin(N_GG * t), 0.0])
    return 3 * N_GG**2 * np.cross(ub, I_BODY @ ub)


def test_against_scipy_sampled_torques_and_gravity_gradient():
    body = pyramid(U_SAMPLES, T_SAMPLES, effects=(lierk.GravityGradient(I_BODY, mean_motion=N_GG),))
    # Restarted at the samples' kinks, as the reference is: an adaptive step
    # straddling a kink is accepted or rejected by its error estimate's luck
    # (3e-11 to 4e-9 off over the 30 s, with rounding-level changes to the
    # program), which is not what this test is about.
    part = body
    for t0, t1 in zip([0.0, 5.0, 10.0, 20.0], [5.0, 10.0, 20.0, 30.0]):
        sol = lierk.solve(
            part, lierk.DOP853(), jnp.asarray(t1), t0=jnp.asarray(t0), rtol=1e-12, atol=1e-12, max_steps=20000
        )
        part = body.restart(sol.R[-1], jax.tree_util.tree_map(lambda x: x[-1], sol.y))
    R_ref, w_ref, Om_ref = scipy_final(
        basilisk_rhs(I_BODY, AXES_UNIT, JS4, u_sampled, gg_torque), OMEGA0, SPEEDS4, 30.0, T_SAMPLES
    )
    w, Om = omega_and_speeds(body, sol)
    assert np.linalg.norm(np.asarray(sol.R[-1]) - R_ref) < 1e-9
    assert np.linalg.norm(w[-1] - w_ref) < 1e-9 * np.linalg.norm(w_ref)
    assert np.linalg.norm(Om[-1] - Om_ref) < 1e-9 * np.linalg.norm(Om_ref)


def test_against_scipy_a_torque_function_and_damping_with_every_kind_of_solver():
    """Damping reads omega, so the wheels change how it acts too.  The fixed
    step methods keep their orders; the adaptive ones their tolerances."""
    c = 0.3
    body = pyramid(lambda t: u_smooth(t), effects=(lierk.Damping(c),))
    t1 = 10.0
    R_ref, w_ref, Om_ref = scipy_final(
        basilisk_rhs(I_BODY, AXES_UNIT, JS4, lambda t: u_smooth(t, np), lambda t, R, w: -c * w), OMEGA0, SPEEDS4, t1
    )
    sol = lierk.solve(body, lierk.DOP853(), t1, rtol=1e-12, atol=1e-12)
    w, Om = omega_and_speeds(body, sol)
    assert np.linalg.norm(np.asarray(sol.R[-1]) - R_ref) < 1e-10
    assert np.linalg.norm(w[-1] - w_ref) < 1e-10 * np.linalg.norm(w_ref)
    assert np.linalg.norm(Om[-1] - Om_ref) < 1e-10 * np.linalg.norm(Om_ref)
    for solver, order in ((lierk.RKMK4(), 4), (lierk.CF4(), 4), (lierk.LieEuler(), 1)):
        dts = (0.1, 0.05) if order > 1 else (0.01, 0.005)
        errs = [np.linalg.norm(np.asarray(lierk.solve(body, solver, t1, dt=dt).R[-1]) - R_ref) for dt in dts]
        assert abs(np.log2(errs[0] / errs[1]) - order) < 0.2, (solver.name, errs)
    for solver in (lierk.RKF45(), lierk.DP54()):
        err = np.linalg.norm(np.asarray(lierk.solve(body, solver, t1, rtol=1e-8).R[-1]) - R_ref)
        assert 1e-11 < err < 1e-7, (solver.name, err)


# --- the solve's other features ---------------------------------------------------------


def test_events_dense_output_and_restarts():
    body = despin()
    # The body's spin stops at t = SPIN I1 / U = 3.5 s; the wheel reaches 15 rad/s at 3.3 s.
    t_stop = SPIN * I1 / U
    t_wheel = (15.0 - W0) / (U * (1 / JS + 1 / I1))
    events = (lierk.Event(lambda t, R, y: y[0][2]), lierk.Event(lambda t, R, y: y[1][0] - 15.0))
    sol = lierk.solve(body, lierk.DP54(), 5.0, rtol=1e-8, event=events, saveat=lierk.SaveAt(t1=True, dense=True))
    np.testing.assert_allclose(float(sol.events[0].ts[0]), t_stop, rtol=1e-10)
    np.testing.assert_allclose(float(sol.events[1].ts[0]), t_wheel, rtol=1e-10)
    R, y = sol.evaluate(2.345)
    np.testing.assert_allclose(float(y[1][0]), despin_exact(2.345)[1], rtol=1e-12)
    np.testing.assert_allclose(float(body.angular_velocity(R, y)[2]), despin_exact(2.345)[0], rtol=1e-12)
    # In two pieces: the wheels' state carries over (the same steps, so the same numbers).
    whole = lierk.solve(body, lierk.RKMK4(), 4.0, dt=0.05)
    half = lierk.solve(body, lierk.RKMK4(), 2.0, dt=0.05)
    rest = lierk.solve(body.restart(half.R[-1], (half.y[0][-1], half.y[1][-1])), lierk.RKMK4(), 4.0, t0=2.0, dt=0.05)
    np.testing.assert_allclose(np.asarray(rest.y[1][-1]), np.asarray(whole.y[1][-1]), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(rest.y[0][-1]), np.asarray(whole.y[0][-1]), atol=1e-14)


def test_with_omega0_keeps_the_wheel_speeds_and_L_includes_the_wheels():
    body = pyramid()
    other = body.with_omega0([0.0, 0.0, 1.0])
    np.testing.assert_allclose(np.asarray(other.omega0), [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_array_equal(np.asarray(other.y0[1]), SPEEDS4)
    np.testing.assert_allclose(np.asarray(body.L), R0 @ (I_BODY @ OMEGA0 + AXES_UNIT.T @ (JS4 * SPEEDS4)), rtol=1e-14)


def test_a_batch_under_vmap_matches_a_loop():
    """Spin inertias, speeds, motor torques and omega0 are array leaves: one
    program for the whole sweep."""
    Js = np.array([[0.05, 0.06, 0.07, 0.04], [0.1, 0.02, 0.03, 0.05], [0.01, 0.01, 0.2, 0.1]])
    speeds = np.array([SPEEDS4, -SPEEDS4, 0.5 * SPEEDS4])
    u = np.array([[0.01, 0.0, -0.02, 0.0], [0.0, 0.03, 0.0, 0.01], [0.0, 0.0, 0.0, 0.0]])
    w0 = np.array([OMEGA0, 2 * OMEGA0, [0.0, 0.0, 0.5]])

    def final(Js, speeds, u, w0):
        body = lierk.RigidBodyWithEffects(I_BODY, w0, R0, effects=(lierk.ReactionWheels(AXES, Js, speeds, torque=u),))
        sol = lierk.solve(body, lierk.DP54(), 10.0, rtol=1e-9, saveat=lierk.SaveAt(t1=True))
        return sol.R[-1], sol.y[1][-1]

    R, Om = jax.vmap(final)(Js, speeds, u, w0)
    for i in range(3):
        Ri, Omi = final(Js[i], speeds[i], u[i], w0[i])
        np.testing.assert_allclose(np.asarray(R[i]), np.asarray(Ri), atol=1e-12)
        np.testing.assert_allclose(np.asarray(Om[i]), np.asarray(Omi), rtol=1e-12)


def test_float32_runs_in_float32():
    body = despin(dtype=np.float32)
    assert body.y0[0].dtype == jnp.float32 and body.y0[1].dtype == jnp.float32
    for solver, kw in ((lierk.RKMK4(), dict(dt=0.01)), (lierk.DP54(), dict(rtol=1e-5))):
        sol = lierk.solve(body, solver, 5.0, **kw)
        assert sol.R.dtype == sol.y[0].dtype == sol.y[1].dtype == jnp.float32
        w, Om = omega_and_speeds(body, sol)
        wz, Om_exact = despin_exact(5.0)
        # 500 float32 steps: 6e-6 of rounding in the speed (the wrong model is 10% off).
        assert abs(w[-1, 2] - wz) < 1e-5 and abs(Om[-1, 0] - Om_exact) < 3e-5 * Om_exact, (solver.name, w[-1], Om[-1])


def test_sensitivity_both_methods_against_finite_differences():
    """With respect to omega0 (the wheels' relative speeds held): the
    attitude's Jacobian and the wheel speeds', by the variational equations
    (adaptive: their tolerances cover the wheels' derivatives) and by the
    derivative of a fixed-step solve."""
    body = pyramid(lambda t: u_smooth(t), effects=(lierk.GravityGradient(I_BODY, mean_motion=N_GG),))
    t1, eps = 3.0, 1e-6
    # Central differences of the fixed-step solve whose derivative is taken
    # below (its error against the exact flow, ~1e-10 here, is below the
    # bound; a tight DOP853 solve took three times as long to compile).
    solve = jax.jit(
        lambda w: (lambda s: (s.R[-1], s.y[1][-1]))(lierk.solve(body.with_omega0(w), lierk.RKMK4(), t1, dt=0.01))
    )
    R = np.asarray(solve(OMEGA0)[0])
    J, J_speeds = np.zeros((3, 3)), np.zeros((4, 3))
    for j in range(3):
        e = np.eye(3)[j] * eps
        (Rp, Op), (Rm, Om) = solve(OMEGA0 + e), solve(OMEGA0 - e)
        J[:, j] = np.asarray(lierk.so3.vee(jnp.asarray(R.T @ (np.asarray(Rp) - np.asarray(Rm)) / (2 * eps))))
        J_speeds[:, j] = (np.asarray(Op) - np.asarray(Om)) / (2 * eps)
    for solver, method, kw in (
        (lierk.DP54(), "variational", dict(rtol=1e-10)),
        (lierk.RKMK4(), "derivative", dict(dt=0.01)),
    ):
        s = lierk.sensitivity(body, solver, t1, method=method, estimate_error=False, **kw)
        np.testing.assert_allclose(np.asarray(s.jacobian), J, atol=1e-6 * np.abs(J).max(), err_msg=method)
        np.testing.assert_allclose(
            np.asarray(s.jacobian_y[1]), J_speeds, atol=1e-6 * np.abs(J_speeds).max(), err_msg=method
        )


def test_modes_bound_the_gyrostat_nutation():
    """The step control's mode bound (`resolve_modes=True`, the derivative
    sensitivity's adaptive solves) covers the nutation that the wheels'
    momentum gives the body: the eigenvalues of the field's Jacobian."""
    from jax.flatten_util import ravel_pytree

    @jax.jit
    def jacobian_and_modes(body):
        flat, unravel = ravel_pytree(body.y0)
        J = jax.jacfwd(lambda x: ravel_pytree(body.field(0.0, jnp.eye(3), unravel(x))[1])[0])(flat)
        return J, body.modes(0.0, jnp.eye(3), body.y0)[0]

    for w0, speeds in (([0.0, 0.0, 0.0], 10 * SPEEDS4), (OMEGA0, SPEEDS4)):
        wheels = lierk.ReactionWheels(AXES, JS4, speeds, torque=[0.01, 0.0, 0.0, 0.0])
        body = lierk.RigidBodyWithEffects(I_BODY, w0, effects=(wheels,))
        J, frequency = jacobian_and_modes(body)
        nutation = np.max(np.abs(np.linalg.eigvals(np.asarray(J))))
        assert nutation < float(frequency) < 3 * nutation, (nutation, frequency)


def test_splittings_refuse_the_wheels_when_traced():
    body = despin()
    for solver in (lierk.Strang(), lierk.Yoshida4(), lierk.BlanesMoan4(), lierk.BlanesMoanRKN4()):
        with pytest.raises(ValueError, match="ReactionWheels .effects.0.. does not follow"):
            lierk.solve(body, solver, 1.0, dt=0.1)
    with pytest.raises(ValueError, match="splitting"):
        lierk.sensitivity(body, lierk.Strang(), 1.0, dt=0.1, method="derivative")
    assert (
        body.splitting_refusal is not None
        and lierk.FreeRigidBody([1.0, 2.0, 3.0], [1.0, 0.0, 0.0]).splitting_refusal is None
    )


def test_the_wheels_are_traced_only_where_a_body_has_them():
    def scopes(p):
        text = jax.make_jaxpr(lambda p, R, y: lierk.RKMK4().step(p, 0.0, 0.01, R, y))(p, p.R0, p.y0).pretty_print(
            name_stack=True
        )
        return "lierk_effect_ReactionWheels" in text

    top = lierk.RigidBodyWithEffects(
        [5.0, 5.0, 1.0], [0.0, 0.3, 50.0], effects=(lierk.Gravity([0.0, 0.0, 1.0], 1.0, 20.0),)
    )
    assert not scopes(lierk.FreeRigidBody(I_BODY, OMEGA0)) and not scopes(top)
    assert scopes(pyramid())
    # Free wheels add no motor torque: fewer operations than driven ones.
    free = jax.make_jaxpr(pyramid().field)(0.0, jnp.eye(3), pyramid().y0)
    driven = jax.make_jaxpr(pyramid(np.zeros(4)).field)(0.0, jnp.eye(3), pyramid().y0)
    assert len(free.eqns) < len(driven.eqns)


# --- bad input ------------------------------------------------------------------------


def one_wheel(**kw):
    return lierk.ReactionWheels([[1.0, 0.0, 0.0]], [0.1], [0.0], **kw)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: lierk.ReactionWheels([1.0, 0.0, 0.0], [0.1], [0.0]), r"axes must have shape \(k, 3\)"),
        (lambda: lierk.ReactionWheels([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [0.1, 0.1], [0.0, 0.0]), "wheel axis 1"),
        (lambda: lierk.ReactionWheels([[1.0, 0.0, 0.0]], [0.1, 0.2], [0.0]), r"spin_inertia must have shape \(1,\)"),
        (lambda: lierk.ReactionWheels([[1.0, 0.0, 0.0]], [-0.1], [0.0]), "spin_inertia must be > 0"),
        (lambda: lierk.ReactionWheels([[1.0, 0.0, 0.0]], [0.0], [0.0]), "spin_inertia must be > 0"),
        (lambda: lierk.ReactionWheels([[1.0, 0.0, 0.0]], [0.1], [np.nan]), "speeds must be finite"),
        (lambda: lierk.ReactionWheels([[1.0, 0.0, 0.0]], [0.1], [0.0, 1.0]), r"speeds must have shape \(1,\)"),
        (lambda: one_wheel(torque=[0.1, 0.2]), r"constant motor torque must have shape \(1,\)"),
        (lambda: one_wheel(torque=[[0.1], [0.2]], times=[1.0, 0.5]), "strictly increasing"),
        (lambda: one_wheel(torque=[[0.1], [0.2]], times=[0.0]), r"shape \(n, 1\)"),
        (lambda: one_wheel(times=[0.0]), "times= go with sampled"),
        (lambda: one_wheel(torque=lambda t: jnp.zeros(2)), r"return shape \(1,\)"),
        (lambda: one_wheel(torque=[np.inf]), "torque must be finite"),
        # Js = 1.5 about x leaves I - G with -0.5 there: I is the whole spacecraft's.
        (
            lambda: lierk.RigidBodyWithEffects(
                [1.0, 2.0, 3.0],
                [0.0, 0.0, 0.0],
                effects=(lierk.Damping(0.1), lierk.ReactionWheels([[1.0, 0.0, 0.0]], [1.5], [0.0])),
            ),
            r"effects\[1\].spin_inertia: .* I - G positive definite",
        ),
        (
            lambda: lierk.RigidBodyWithEffects([1.0, 2.0, 3.0], [0.0, 0.0, 0.0], effects=(one_wheel(), one_wheel())),
            r"effects\[1\]: a body takes one ReactionWheels",
        ),
        (
            lambda: lierk._problems.Variational(pyramid(), np.zeros((3, 3)), (np.zeros((3, 3)), np.zeros((3, 2)))),
            r"dOmega0 must have shape \(3, 4\)",
        ),
    ],
)
def test_bad_input_is_refused_by_name(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_a_traced_spin_inertia_is_checked_when_the_program_runs():
    """Traced, the check is made in the program: the body's values come back
    NaN, and a solve of it ends with `RESULTS.invalid_problem` (or raises,
    naming the spin inertias, with ``throw=True``)."""
    import equinox as eqx

    def body(js):
        return lierk.RigidBodyWithEffects(
            [1.0, 2.0, 3.0], [0.1, 0.0, 0.0], effects=(lierk.ReactionWheels([[1.0, 0.0, 0.0]], js, [0.0]),)
        )

    inertia = eqx.filter_jit(lambda js: body(js).inertia)
    assert float(inertia(jnp.array([0.5]))[0, 0]) == 1.0
    assert np.isnan(np.asarray(inertia(jnp.array([1.5])))).all()
    result = eqx.filter_jit(lambda js: lierk.solve(body(js), lierk.RKMK4(), 0.1, dt=0.05, throw=False).result)
    assert int(result(jnp.array([0.5]))) == 0
    assert int(result(jnp.array([1.5]))) == lierk.RESULTS.invalid_problem
    with pytest.raises(Exception, match="positive-definite spin inertias"):
        jax.block_until_ready(
            eqx.filter_jit(lambda js: lierk.solve(body(js), lierk.RKMK4(), 0.1, dt=0.05).R)(jnp.array([1.5]))
        )


def test_the_wheels_add_no_torque_of_their_own():
    wheels = lierk.ReactionWheels([[1.0, 0.0, 0.0]], [0.1], [0.0])
    with pytest.raises(ValueError, match="add no torque of their own"):
        wheels.torque(0.0, jnp.eye(3), jnp.zeros(3), jnp.zeros(3))


# --- scenes ----------------------------------------------------------------------------

SCENE = """
[body]
kind = "tensor"
inertia = [[3.0, 0.1, -0.05], [0.1, 5.0, 0.2], [-0.05, 0.2, 7.0]]
[initial]
omega = [0.1, -0.2, 0.3]
[[effects]]
kind = "damping"
c = 0.3
[[effects]]
kind = "reaction_wheels"
{wheels}
[run]
solver = "DP54"
t1 = 5.0
rtol = 1e-9
"""
WHEELS = """axes = [[1.0, 0.0, 0.4], [0.0, 1.0, 0.4], [-1.0, 0.0, 0.4], [0.1, -1.0, 0.4]]
spin_inertia = [0.05, 0.06, 0.07, 0.04]
speeds = [20.0, -10.0, 5.0, 30.0]
times = [0.0, 5.0, 10.0, 20.0]
torque = [[0.0, 0.0, 0.0, 0.0], [0.02, -0.01, 0.005, 0.0], [0.0, 0.01, -0.02, 0.01], [0.0, 0.0, 0.0, -0.01]]"""


def test_scene_reaction_wheels_are_the_library_effect():
    scene = lierk.app.scene.from_dict(tomllib.loads(SCENE.format(wheels=WHEELS)), "sat")
    direct = lierk.RigidBodyWithEffects(
        I_BODY,
        OMEGA0,
        effects=(lierk.Damping(0.3), lierk.ReactionWheels(AXES, JS4, SPEEDS4, torque=U_SAMPLES, times=T_SAMPLES)),
    )
    a, b = scene.solve(), lierk.solve(direct, lierk.DP54(), 5.0, rtol=1e-9, saveat=scene.saveat())
    np.testing.assert_allclose(np.asarray(a.y[1]), np.asarray(b.y[1]), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(a.R), np.asarray(b.R), atol=1e-14)
    # A constant motor torque, and wheels at rest by default.
    constant = "axes = [[0.0, 0.0, 1.0]]\nspin_inertia = [0.1]\ntorque = [0.01]"
    wheels = lierk.app.scene.from_dict(tomllib.loads(SCENE.format(wheels=constant)), "sat").problem.wheels
    assert np.asarray(wheels.torques).tolist() == [0.01] and np.asarray(wheels.speeds).tolist() == [0.0]


def test_simulate_saves_the_wheel_speeds_and_the_whole_spacecrafts_momentum():
    # `lierk simulate` of a wheel scene: the record used to hand the pair
    # state to numpy.savez (uneven shapes), and L left the wheels out.
    from lierk.app.simulation import simulate

    sim = simulate(lierk.app.scene.from_dict(tomllib.loads(SCENE.format(wheels=WHEELS)), "sat"))
    rec = sim.record()
    m, speeds = (np.asarray(x) for x in sim.solution.y)
    np.testing.assert_array_equal(rec["wheel_speeds"], speeds[: len(rec["ts"])])
    np.testing.assert_array_equal(rec["y"], m[: len(rec["ts"])])
    H = m + (JS4 * speeds) @ AXES_UNIT
    np.testing.assert_allclose(
        rec["L"], np.einsum("nij,nj->ni", np.asarray(sim.solution.R), H)[: len(rec["ts"])], rtol=1e-12, atol=1e-12
    )


Z = "axes = [[0.0, 0.0, 1.0]]\nspin_inertia = [0.1]\n"  # one wheel about body z


@pytest.mark.parametrize(
    "wheels, match",
    [
        ("axes = [[0.0, 0.0, 1.0]]", r"effects\[1\]: missing required key 'spin_inertia'"),
        ("axes = [[0.0, 0.0, 0.0]]\nspin_inertia = [0.1]", r"effects\[1\].axes\[0\] must be a non-zero vector"),
        ("axes = [[0.0, 0.0, 1.0]]\nspin_inertia = [-0.1]", r"effects\[1\].spin_inertia\[0\] must be > 0"),
        (Z + "speeds = [1.0, 2.0]", r"effects\[1\].speeds must be a list of 1 numbers"),
        (Z + "torque = [[0.1], [0.2]]", r"effects\[1\].torque: rows of motor torques need times"),
        (Z + "times = [0.0, 1.0]\ntorque = [[0.1]]", r"effects\[1\].torque must list one row"),
        (Z + "times = [1.0, 0.0]\ntorque = [[0.1], [0.2]]", r"effects\[1\].times must be strictly increasing"),
        ("axes = [[0.0, 0.0, 1.0]]\nspin_inertia = [8.0]", r"effects\[1\].spin_inertia: .* I - G positive definite"),
        (Z + "momentum = [1.0]", r"effects\[1\]: unknown key 'momentum'"),
    ],
)
def test_bad_scene_wheels_are_refused_by_key_path(wheels, match):
    with pytest.raises(ValueError, match=match):
        lierk.app.scene.from_dict(tomllib.loads(SCENE.format(wheels=wheels)), "sat")


def test_restart_refuses_a_state_unlike_the_wheels_by_name():
    """A restart whose state is not ``(m (3,), speeds (k,))`` failed inside the
    solve with JAX's errors ("too many values to unpack", "scan body function
    carry input and carry output must have equal types")."""
    body = pyramid()
    m, speeds = (np.asarray(x) for x in body.y0)
    pair = r"\(float64\[3\], float64\[4\]\)"
    cases = {
        "the speeds' trajectory": ((m, np.stack([speeds] * 5)), r"y0\[1\] has shape \(5, 4\).*a saved trajectory"),
        "one array": (np.concatenate([m, speeds]), "y0 must have the structure of the problem's state, " + pair),
        "a list": ([m, speeds], "y0 must have the structure .*, got \\[float64\\[3\\], float64\\[4\\]\\]"),
        "three speeds for four wheels": (
            (m, speeds[:3]),
            r"y0\[1\] has shape \(3,\), where the problem's state " + pair,
        ),
        "float32": ((m, speeds.astype(np.float32)), r"y0\[1\] is float32"),
    }
    for name, (y, match) in cases.items():
        with pytest.raises(ValueError, match=match):
            body.restart(R0, y)
    restarted = body.restart(R0, (m, speeds))
    for a, b in zip(restarted.y0, (m, speeds)):
        np.testing.assert_array_equal(np.asarray(a), b)
