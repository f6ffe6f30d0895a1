"""Design by gradient: `lierk.solve_sampled` (a control law sampled at a fixed
rate and held), and optimisation through it.

It is the loop of solves it replaces (to rounding); its gradient with respect
to held commands, and through `lierk.ReactionWheels`' interpolated samples in
one solve, agrees with central differences; the minimum-effort rest-to-rest
slew of a sphere, found by an augmented Lagrangian around optimistix's BFGS,
is the closed form's held optimum (the closed form at each period's middle
over ``1 - 1/N^2``, the effort ``12 J^2 theta^2/T^3 / (1 - 1/N^2)``) for a
body-fixed torque (``J``) and for three wheels (``J - Js``); reverse mode's
memory does not grow with the steps inside a period; bad input is refused by
name."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import derivatives_and_differences

import lierk

so3 = lierk.so3
WHEELS = jnp.eye(3)
JS = 0.1  # kg m^2, each wheel
I_ASYM = np.array([[4.0, 0.3, -0.2], [0.3, 6.0, 0.4], [-0.2, 0.4, 5.0]])  # kg m^2


def with_wheels(inertia, omega0=np.zeros(3), R0=None, speeds=np.zeros(3)):
    wheels = lierk.ReactionWheels(WHEELS, jnp.full(3, JS), speeds, torque=jnp.zeros(3))
    return lierk.RigidBodyWithEffects(inertia, omega0, R0=R0, effects=(wheels,))


def motor_torques(p):
    return p.effects[0].torques


def test_it_is_the_loop_of_solves_it_replaces():
    # A feedback law on a body with products of inertia, wheels spinning: the
    # Python loop of solves the detumble example wrote by hand, to rounding.
    R0 = so3.exp(jnp.array([0.3, -0.2, 0.5]))
    body = with_wheels(I_ASYM, np.array([0.02, -0.03, 0.01]), R0, speeds=np.array([5.0, -3.0, 1.0]))
    inertia_inv = np.linalg.inv(I_ASYM)

    def law(k, t, R, y):
        return 0.4 * so3.to_mrp(R) + 2.0 * (inertia_inv @ y[0]) + 1e-3 * jnp.sin(t)

    sol, u = lierk.solve_sampled(body, lierk.RKMK4(), law, motor_torques, 1.5, 6, t0=2.0, dt=0.5)
    R, y = body.R0, body.y0
    for k in range(6):
        t = 2.0 + 1.5 * k
        command = law(k, t, R, y)
        np.testing.assert_allclose(u[k], command, rtol=0, atol=1e-15)
        wheels = lierk.ReactionWheels(WHEELS, jnp.full(3, JS), y[1], torque=command)
        step = lierk.solve(
            lierk.RigidBodyWithEffects(I_ASYM, inertia_inv @ y[0], R0=R, effects=(wheels,)),
            lierk.RKMK4(),
            t + 1.5,
            t0=t,
            dt=0.5,
        )
        R, y = step.R[-1], (step.y[0][-1], step.y[1][-1])
        np.testing.assert_allclose(sol.R[k + 1], R, rtol=0, atol=1e-14)
        np.testing.assert_allclose(sol.y[0][k + 1], y[0], rtol=0, atol=1e-15)
        np.testing.assert_allclose(sol.y[1][k + 1], y[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.ts, 2.0 + 1.5 * np.arange(7), rtol=0, atol=1e-14)
    assert sol.R.shape == (7, 3, 3) and u.shape == (6, 3) and int(sol.n_saved) == 7
    assert int(sol.stats["num_steps"]) == 6 * 3 and int(sol.result) == 0


def test_float32_problems_stay_in_float32():
    def run(dtype):
        body = lierk.RigidBodyWithEffects(
            np.diag([3.0, 4.0, 5.0]).astype(dtype),
            np.array([0.1, -0.2, 0.3], dtype),
            effects=(lierk.BodyTorque(np.zeros(3, dtype)),),
        )
        law = lambda k, t, R, y: -0.5 * y + 0.01 * so3.to_mrp(R)  # noqa: E731
        return lierk.solve_sampled(body, lierk.RKMK4(), law, lambda p: p.effects[0].tau, 0.5, 8, dt=0.25)

    (sol32, u32), (sol64, u64) = run(np.float32), run(np.float64)
    assert sol32.R.dtype == sol32.y.dtype == sol32.ts.dtype == u32.dtype == jnp.float32
    np.testing.assert_allclose(sol32.R, sol64.R, rtol=0, atol=1e-6)
    np.testing.assert_allclose(u32, u64, rtol=0, atol=1e-6)


def test_a_failed_period_is_reported():
    body = with_wheels(I_ASYM)
    blow_up = lambda k, t, R, y: jnp.where(k == 3, jnp.inf, 0.01) * jnp.ones(3)  # noqa: E731
    sol, _ = lierk.solve_sampled(body, lierk.RKMK4(), blow_up, motor_torques, 1.0, 5, dt=0.5, throw=False)
    assert int(sol.result) == int(lierk.RESULTS.nonfinite)
    with pytest.raises(RuntimeError, match="non-finite"):
        lierk.solve_sampled(body, lierk.RKMK4(), blow_up, motor_torques, 1.0, 5, dt=0.5)


def test_bad_input_is_refused_by_name():
    body = with_wheels(I_ASYM)
    law = lambda k, t, R, y: jnp.zeros(3)  # noqa: E731
    free = lierk.RigidBodyWithEffects(
        I_ASYM, np.zeros(3), effects=(lierk.ReactionWheels(WHEELS, jnp.full(3, JS), np.zeros(3)),)
    )
    with pytest.raises(ValueError, match="control selects None"):
        lierk.solve_sampled(free, lierk.RKMK4(), law, motor_torques, 1.0, 2, dt=0.5)
    with pytest.raises(ValueError, match=r"law returns \(2,\), but control selects \(3,\)"):
        lierk.solve_sampled(body, lierk.RKMK4(), lambda k, t, R, y: jnp.zeros(2), motor_torques, 1.0, 2, dt=0.5)
    with pytest.raises(ValueError, match="n, the number of periods"):
        lierk.solve_sampled(body, lierk.RKMK4(), law, motor_torques, 1.0, 0, dt=0.5)
    with pytest.raises(ValueError, match="period must be positive"):
        lierk.solve_sampled(body, lierk.RKMK4(), law, motor_torques, -1.0, 2, dt=0.5)
    with pytest.raises(ValueError, match="dt must be positive"):
        lierk.solve_sampled(body, lierk.RKMK4(), law, motor_torques, 1.0, 2, dt=np.float64(-0.5))
    with pytest.raises(ValueError, match="sets saveat"):
        lierk.solve_sampled(body, lierk.RKMK4(), law, motor_torques, 1.0, 2, dt=0.5, saveat=lierk.SaveAt(t1=True))
    with pytest.raises(ValueError, match="pass max_steps="):
        jax.jit(lambda p: lierk.solve_sampled(body, lierk.RKMK4(), law, motor_torques, p, 2, dt=0.5)[0].R)(1.0)


# --- gradients against central differences -------------------------------------

N_FD, T_FD = 8, 16.0
TARGET = so3.exp(jnp.array([0.4, -0.3, 0.6]))


def slew_loss(U):
    """A scalar of a held-command manoeuvre of the asymmetric body with wheels:
    its miss of the target, its final rate and wheel speeds, and its effort."""
    sol, _ = lierk.solve_sampled(
        with_wheels(I_ASYM), lierk.RKMK4(), lambda k, t, R, y: U[k], motor_torques, T_FD / N_FD, N_FD, dt=0.5
    )
    miss = so3.log(TARGET.T @ sol.R[-1])
    return (
        jnp.sum(miss * jnp.array([1.0, -2.0, 0.5]))
        + 10.0 * jnp.sum(sol.y[0][-1] ** 2)
        + 0.1 * jnp.sum(sol.y[1][-1])
        + 2.0 * jnp.sum(U**2)
    )


def smooth_loss(samples):
    """The same through piecewise-linear motor torques in one solve: the
    samples are `ReactionWheels`' array leaves."""
    wheels = lierk.ReactionWheels(
        WHEELS, jnp.full(3, JS), np.zeros(3), torque=samples, times=jnp.linspace(0.0, T_FD, samples.shape[0])
    )
    sol = lierk.solve(lierk.RigidBodyWithEffects(I_ASYM, np.zeros(3), effects=(wheels,)), lierk.RKMK4(), T_FD, dt=0.5)
    miss = so3.log(TARGET.T @ sol.R[-1])
    return jnp.sum(miss * jnp.array([1.0, -2.0, 0.5])) + 10.0 * jnp.sum(sol.y[0][-1] ** 2) + 0.1 * jnp.sum(sol.y[1][-1])


@pytest.mark.parametrize(
    "loss, shape", [(slew_loss, (N_FD, 3)), (smooth_loss, (N_FD + 1, 3))], ids=["held commands", "interpolated samples"]
)
def test_gradient_with_respect_to_the_torques_matches_central_differences(loss, shape):
    # 24 or 27 inputs: past ForwardSensitivity's 6, so reverse mode goes
    # through the fixed-step scans.  Compared along three random directions
    # (reverse mode of the loss along them is the gradient contracted with them).
    rng = np.random.default_rng(3)
    U = 0.02 * rng.standard_normal(shape)
    directions = rng.standard_normal((3, *shape))

    def along(s, U, directions):
        return loss(U + jnp.tensordot(s, directions, axes=1))

    (grad,), fd = derivatives_and_differences(along, modes=("jacrev",), h=1e-3)(np.zeros(3), U, directions)
    np.testing.assert_allclose(grad, fd, rtol=1e-8, atol=1e-10)
    assert np.abs(grad).min() > 1e-3  # the directions move the loss


# --- the closed form -----------------------------------------------------------

N, T, THETA, J = 12, 30.0, np.pi / 2, 4.0
AXIS = np.array([1.0, 2.0, 2.0]) / 3.0


def augmented_lagrangian(miss, effort, shape, scale):
    """Minimise ``effort(U)`` subject to ``miss(U) = 0``: BFGS on the
    augmented Lagrangian, the multipliers updated until the miss is 1e-8."""
    bfgs = optx.BFGS(rtol=1e-10, atol=1e-10)

    def lagrangian(V, args):
        lam, mu = args
        c = miss(scale * V)
        return effort(scale * V) / (T * scale**2) + lam @ c + 0.5 * mu * (c @ c)

    @jax.jit
    def inner(V, lam, mu):
        V = optx.minimise(lagrangian, bfgs, V, args=(lam, mu), max_steps=1000, throw=False).value
        return V, miss(scale * V)

    V, lam = jnp.zeros(shape), jnp.zeros(6)
    for _ in range(10):
        V, c = inner(V, lam, 100.0)
        lam = lam + 100.0 * c
        if jnp.abs(c).max() < 1e-8:
            break
    assert jnp.abs(c).max() < 1e-8
    return scale * V


@pytest.mark.parametrize("drive", ["body torque", "wheels"])
def test_the_minimum_effort_slew_of_a_sphere_is_the_closed_form(drive):
    # A body-fixed torque turns I = J 1 as J theta'' = tau; three wheels turn
    # it as (J - Js) theta'' = -u.  Held commands: the closed form at each
    # period's middle over 1 - 1/N^2, the effort over 1 - 1/N^2.
    period = T / N
    target = so3.exp(THETA * jnp.asarray(AXIS))
    if drive == "body torque":
        body = lierk.RigidBodyWithEffects(J * np.eye(3), np.zeros(3), effects=(lierk.BodyTorque(jnp.zeros(3)),))
        control, J_eff, sign = (lambda p: p.effects[0].tau), J, 1.0
    else:
        body, control, J_eff, sign = with_wheels(J * np.eye(3)), motor_torques, J - JS, -1.0

    def miss(U):
        sol, _ = lierk.solve_sampled(
            body, lierk.RKMK4(), lambda k, t, R, y: U[k], control, period, N, dt=period / 4, throw=False
        )
        m = sol.y[0][-1] if drive == "wheels" else sol.y[-1]
        return jnp.concatenate([so3.log(target.T @ sol.R[-1]), T * m / J])

    U = augmented_lagrangian(miss, lambda U: period * jnp.sum(U**2), (N, 3), 6 * J * THETA / T**2)
    shrink = 1 - 1 / N**2
    closed_effort = 12 * J_eff**2 * THETA**2 / T**3
    middles = (np.arange(N) + 0.5) * period
    closed = sign * (6 * J_eff * THETA / T**2) * (1 - 2 * middles / T)[:, None] * AXIS
    effort = float(period * jnp.sum(U**2))
    np.testing.assert_allclose(effort, closed_effort / shrink, rtol=1e-7)
    np.testing.assert_allclose(U, closed / shrink, rtol=0, atol=1e-7 * np.abs(closed).max())
    # Within 1% of the closed form (at 12 held commands: 0.7%).
    assert effort / closed_effort - 1 < 0.01
    assert np.abs(U - closed).max() < 0.01 * np.abs(closed).max()


# --- memory --------------------------------------------------------------------


def _gradient_temporaries(periods, steps_per_period):
    body = lierk.RigidBodyWithEffects(I_ASYM, np.zeros(3), effects=(lierk.BodyTorque(jnp.zeros(3)),))

    def loss(U):
        sol, _ = lierk.solve_sampled(
            body,
            lierk.RKMK4(),
            lambda k, t, R, y: U[k],
            lambda p: p.effects[0].tau,
            1.0,
            periods,
            dt=1.0 / steps_per_period,
        )
        return sol.R[-1, 0, 1] + jnp.sum(sol.y[-1])

    compiled = jax.jit(jax.grad(loss)).lower(jnp.zeros((periods, 3))).compile()
    return compiled.memory_analysis().temp_size_in_bytes


def test_reverse_mode_memory_does_not_grow_with_the_steps():
    # One state per period and one period's steps at a time: 4 or 1024 steps
    # a period (blocks of 32 from 256 steps on) differ by a few kilobytes;
    # ten times the periods add about a state (12 numbers) and a command per
    # period, a few copies each.
    few = _gradient_temporaries(10, 4)
    many_steps = _gradient_temporaries(10, 1024)
    many_periods = _gradient_temporaries(100, 4)
    assert many_steps - few < 16 * 1024, (few, many_steps)
    assert 0 < many_periods - few < 90 * 15 * 8 * 4, (few, many_periods)
