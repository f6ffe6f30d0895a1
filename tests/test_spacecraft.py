"""Spacecraft effects: gravity gradient, magnetic torque (constant dipole and
B-dot), rotors (constant and driven wheels).

Each against an independent solution of the same equations (SciPy's DOP853,
written out here from the physics, not from lierk's code), one physics check
each (the gravity-gradient pitch libration period, a rotor that stops the
intermediate-axis flip, B-dot detumbling), the solvers' orders with the
effects on, the splittings' exact kicks, global error estimates, and bad
input refused by name."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import final_attitudes, order_fit
from scipy.integrate import solve_ivp

import lierk

N_ORBIT = 0.0011  # rad/s, a low Earth orbit
I_SAT = np.diag([10.0, 14.0, 6.0])  # kg m^2, I_y > I_x > I_z: gravity-gradient stable
FIELD = lierk.dipole_field(N_ORBIT, tilt=1.2)  # an inclined orbit: the field turns


def hat(a):
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def scipy_solve(inertia, omega0, R0, torque, t1, ts=None):
    """``dR/dt = R hat(omega)``, ``dm/dt = m x omega + torque(t, R, m, omega)``
    with ``omega = I^{-1} m``, by SciPy's DOP853 at rtol 1e-13."""
    Iinv = np.linalg.inv(inertia)

    def f(t, x):
        R, m = x[:9].reshape(3, 3), x[9:]
        w = Iinv @ m
        return np.concatenate([(R @ hat(w)).ravel(), np.cross(m, w) + torque(t, R, m, w)])

    x0 = np.concatenate([np.asarray(R0).ravel(), inertia @ np.asarray(omega0)])
    sol = solve_ivp(f, (0.0, t1), x0, method="DOP853", rtol=1e-13, atol=1e-15, t_eval=ts)
    return sol.y[:9, -1].reshape(3, 3), sol.y[9:, -1]


def gg_torque(t, R, m, w):
    u = np.array([np.cos(N_ORBIT * t), np.sin(N_ORBIT * t), 0.0])
    ub = R.T @ u
    return 3 * N_ORBIT**2 * np.cross(ub, I_SAT @ ub)


def field_np(t, tilt=1.2):
    u = np.array([np.cos(N_ORBIT * t), np.sin(N_ORBIT * t), 0.0])
    a = (lierk._problems.spacecraft.MU_EARTH / N_ORBIT**2) ** (1 / 3)
    d = -np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    return lierk._problems.spacecraft.B0_EARTH * (lierk._problems.spacecraft.R_EARTH / a) ** 3 * (3 * (d @ u) * u - d)


DIPOLE = np.array([0.5, -1.0, 2.0])  # A m^2
BDOT = 1e7  # A m^2 s / T: about 10 A m^2 at 0.05 rad/s, a magnetorquer's range
WHEELS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
W_TIMES, W_TORQUES = np.array([0.0, 20.0, 40.0, 60.0]), np.array([[0.0, 0.0], [0.02, -0.01], [0.0, 0.01], [0.0, 0.0]])


def wheel_np(t):
    """Wheel momenta and motor torques of the sampled profile, integrated here
    on its own for the reference (trapezoids over a grid that holds every
    sample time: exact for a piecewise-linear torque)."""
    grid = np.union1d([0.0, t], W_TIMES[W_TIMES < t])
    u = np.stack([np.interp(grid, W_TIMES, W_TORQUES[:, k]) for k in range(2)], 1)
    h = np.array([0.3, -0.2]) + np.trapezoid(u, grid, axis=0)
    return h @ WHEELS, np.array([np.interp(t, W_TIMES, W_TORQUES[:, k]) for k in range(2)]) @ WHEELS


CASES = {
    # name: (effect, numpy torque(t, R, m, omega), omega0, t1)
    "gravity_gradient": (
        lambda: lierk.GravityGradient(I_SAT, mean_motion=N_ORBIT),
        gg_torque,
        [0.001, -0.002, 0.003],
        3000.0,
    ),
    "magnetic_dipole": (
        lambda: lierk.MagneticTorque(FIELD, dipole=DIPOLE),
        lambda t, R, m, w: np.cross(DIPOLE, R.T @ field_np(t)),
        [0.01, 0.02, -0.015],
        600.0,
    ),
    "bdot": (
        lambda: lierk.MagneticTorque(FIELD, bdot_gain=BDOT),
        lambda t, R, m, w: BDOT * np.cross(np.cross(w, R.T @ field_np(t)), R.T @ field_np(t)),
        [0.05, 0.02, -0.03],
        600.0,
    ),
    "rotor": (
        lambda: lierk.Rotor([0.0, 0.5, 0.1]),
        lambda t, R, m, w: np.cross([0.0, 0.5, 0.1], w),
        [0.02, 0.05, -0.01],
        300.0,
    ),
    "driven_wheels": (
        lambda: lierk.Rotor([0.3, -0.2], axes=WHEELS, torque=W_TORQUES, times=W_TIMES),
        lambda t, R, m, w: np.cross(wheel_np(t)[0], w) - wheel_np(t)[1],
        [0.02, 0.05, -0.01],
        80.0,
    ),
}
R0 = np.asarray(lierk.so3.exp(jnp.asarray([0.3, -0.2, 0.5])))


@pytest.mark.parametrize("name", list(CASES))
def test_against_an_independent_solution(name):
    make, torque, omega0, t1 = CASES[name]
    body = lierk.RigidBodyWithEffects(I_SAT, omega0, R0, effects=(make(),))
    sol = lierk.solve(body, lierk.DOP853(), t1, rtol=1e-13, atol=1e-13, max_steps=20000)
    R_ref, m_ref = scipy_solve(I_SAT, omega0, R0, torque, t1)
    assert float(jnp.linalg.norm(sol.R[-1] - R_ref)) < 1e-10
    assert float(jnp.linalg.norm(sol.y[-1] - m_ref)) < 1e-10 * max(1.0, float(np.linalg.norm(m_ref)))


def pitch_period(inertia, n, amplitude=0.01):
    """Pitch libration of a satellite in the local-vertical frame (x along
    the velocity, z to the planet): the time between upward zero crossings
    of its pitch angle, over about three periods."""
    # At t = 0 the spacecraft is at space x: velocity along y, nadir along -x.
    R_lvlh = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R0 = R_lvlh @ np.asarray(lierk.so3.exp(jnp.asarray([0.0, amplitude, 0.0])))
    # The frame turns with the orbit: -n about body y.
    body = lierk.RigidBodyWithEffects(
        inertia, [0.0, -n, 0.0], R0, effects=(lierk.GravityGradient(inertia, mean_motion=n),)
    )
    T = 3.5 * 2 * np.pi / n
    sol = lierk.solve(body, lierk.RKMK4(), T, dt=T / 7000, saveat=lierk.SaveAt(t0=True, steps=1))
    ts, R = np.asarray(sol.ts), np.asarray(sol.R)
    Rz = np.asarray(jax.vmap(lambda a: lierk.so3.exp(jnp.array([0.0, 0.0, a])))(jnp.asarray(n * ts)))
    rel = np.einsum("ji,tkj->tik", R_lvlh, Rz)  # (Rz R_lvlh)^T
    pitch = np.asarray(lierk.so3.log(jnp.asarray(np.einsum("tij,tjk->tik", rel, R))))[:, 1]
    up = np.flatnonzero((pitch[:-1] < 0) & (pitch[1:] >= 0))
    # Linear interpolation of each crossing.
    tc = ts[up] - pitch[up] * (ts[up + 1] - ts[up]) / (pitch[up + 1] - pitch[up])
    return np.mean(np.diff(tc)), np.max(np.abs(pitch))


def test_gravity_gradient_pitch_libration_period():
    period, amp = pitch_period(I_SAT, N_ORBIT)
    Ix, Iy, Iz = np.diag(I_SAT)
    expected = 2 * np.pi / (N_ORBIT * np.sqrt(3 * (Ix - Iz) / Iy))
    assert amp < 0.011  # it librates: it stays near the local vertical
    np.testing.assert_allclose(period, expected, rtol=1e-3)


def flips(body, t1):
    """Whether the body's intermediate (x) axis turns over: the sign of m_x."""
    sol = lierk.solve(body, lierk.RKMK4(), t1, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=10))
    mx = np.asarray(sol.y)[:, 0] / np.linalg.norm(np.asarray(sol.y), axis=1)
    return float(np.min(mx))


def test_a_rotor_along_the_intermediate_axis_stops_the_flip():
    tee = np.asarray(lierk.inertia.tee_handle())
    w0 = np.array([1.0, 0.05, 0.3])
    t1 = 5 * float(lierk.exact.flip_interval(tee, w0))
    assert flips(lierk.FreeRigidBody(tee, w0), t1) < -0.9
    h = 3.0 * tee[0, 0] * 1.0  # three times the body's own spin momentum
    gyrostat = lierk.RigidBodyWithEffects(tee, w0, effects=(lierk.Rotor([h, 0.0, 0.0]),))
    assert flips(gyrostat, t1) > 0.8  # (0.90 at the start)


def test_bdot_detumbles():
    body = lierk.RigidBodyWithEffects(
        I_SAT, [0.05, -0.04, 0.06], effects=(lierk.MagneticTorque(FIELD, bdot_gain=BDOT),)
    )
    t1 = 2 * np.pi / N_ORBIT
    sol = lierk.solve(body, lierk.RKMK4(), t1, dt=1.0, saveat=lierk.SaveAt(t0=True, steps=100))
    E = np.asarray(sol.invariants(body)["energy"])
    assert E[-1] < 1e-2 * E[0]
    assert np.all(np.diff(E) <= 1e-12 * E[0])  # it only ever takes energy out


def mixed_body():
    effects = (
        lierk.GravityGradient(I_SAT, mean_motion=N_ORBIT),
        lierk.MagneticTorque(FIELD, dipole=DIPOLE),
        lierk.Rotor([0.0, 0.5, 0.1]),
    )
    return lierk.RigidBodyWithEffects(I_SAT, [0.01, 0.05, -0.02], R0, effects=effects)


@pytest.mark.parametrize(
    "solver, dts",
    [
        (lierk.RKMK4(), [1.0, 0.5, 0.25]),
        (lierk.Strang(), [4.0, 2.0, 1.0]),
        (lierk.BlanesMoan4(), [4.0, 2.0, 1.0]),
        (lierk.RKMK(lierk.tableaux.DOP853), [8.0, 4.0, 2.0]),
    ],
    ids=["RKMK4", "Strang", "BlanesMoan4", "RKMK(DOP853)"],
)
def test_orders_hold_with_the_effects(solver, dts):
    """Gravity gradient, a constant dipole and a rotor together.  The
    splittings keep order 4 because the kick of torques affine in the
    momentum is exact (composed one by one, BlanesMoan4 fell to order 2)."""
    body, t1 = mixed_body(), 200.0
    ref = np.asarray(lierk.solve(body, lierk.RKMK(lierk.tableaux.DOP853), t1, dt=0.1).R[-1])
    R = final_attitudes(body, solver, t1, dts)
    errs = np.linalg.norm(R - ref, axis=(1, 2))
    p = order_fit(dts, errs)
    if solver.order == 8:
        # DOP853's eighth-order error constant is small enough that the next
        # term still shows at steps whose error is above rounding (fitted
        # 8.3 to 8.7 from dt = 12 to 1.5): at least order 8.
        assert 7.85 <= p <= 8.8, errs
    else:
        assert abs(p - solver.order) <= 0.15, errs


def test_error_estimates_and_target_error_with_the_effects():
    body, t1 = mixed_body(), 200.0
    ts = jnp.linspace(0.0, t1, 5)
    ref = np.asarray(lierk.solve(body, lierk.DOP853(), t1, rtol=1e-14, atol=1e-14, saveat=lierk.SaveAt(ts=ts)).R)
    sol = lierk.solve(body, lierk.DP54(), t1, rtol=1e-7, saveat=lierk.SaveAt(ts=ts), estimate_error=True)
    err = np.linalg.norm(np.asarray(sol.R) - ref, axis=(1, 2))[-1]
    assert 0.2 < float(sol.error_estimate[-1]) / err < 5
    sol = lierk.solve(body, lierk.RKMK4(), t1, target_error=1e-9, saveat=lierk.SaveAt(ts=ts))
    assert int(sol.result) == 0
    assert np.max(np.linalg.norm(np.asarray(sol.R) - ref, axis=(1, 2))) <= 1e-9


def test_rotor_and_bdot_kicks_are_exact_flows():
    """The splittings' kick for a torque that reads the momentum is its exact
    flow with t and R fixed: against the matrix ODE solved by SciPy."""
    R = np.asarray(R0)
    m = np.array([0.3, -0.1, 0.2])
    Iinv = np.linalg.inv(I_SAT)
    for e in (
        lierk.MagneticTorque(FIELD, bdot_gain=BDOT),
        lierk.Rotor([0.3, -0.2], axes=WHEELS, torque=W_TORQUES, times=W_TIMES),
    ):
        t, h = 30.0, 7.0

        def rhs(s, x, e=e):
            return np.asarray(e.torque(jnp.asarray(t), jnp.asarray(R), jnp.asarray(x), jnp.asarray(Iinv @ x)))

        ref = solve_ivp(rhs, (0, h), m, method="DOP853", rtol=1e-13, atol=1e-16).y[:, -1]
        got = np.asarray(e.kick(jnp.asarray(t), jnp.asarray(R), jnp.asarray(m), jnp.asarray(h), jnp.asarray(Iinv)))
        np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-15)


def test_constant_rotor_conserves_energy_and_total_momentum():
    """The splitting's drift and kick each conserve the kinetic energy, so
    Strang does to rounding; the whole body's momentum |m + h| neither
    substep conserves, so it stays within O(h^2) (and within the solver's
    accuracy for an RKMK solve)."""
    body = lierk.RigidBodyWithEffects(I_SAT, [0.02, 0.05, -0.01], effects=(lierk.Rotor([0.0, 0.5, 0.1]),))
    assert set(body.conserved()) == {"energy", "|m + h|"}
    for solver, kw, tol in (
        (lierk.Strang(), dict(dt=0.5), (1e-12, 1e-5)),
        (lierk.DOP853(), dict(rtol=1e-12), (1e-11, 1e-11)),
    ):
        sol = lierk.solve(
            body,
            solver,
            500.0,
            saveat=lierk.SaveAt(ts=jnp.linspace(0.0, 500.0, 51)) if "rtol" in kw else lierk.SaveAt(t0=True, steps=10),
            **kw,
        )
        q = sol.invariants(body)
        for k, bound in zip(("energy", "|m + h|"), tol):
            v = np.asarray(q[k])
            assert np.max(np.abs(v - v[0])) < bound * abs(v[0]), (solver.name, k)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: lierk.GravityGradient(I_SAT, radius=-7e6), "radius"),
        (lambda: lierk.GravityGradient(I_SAT, radius=0.0), "radius"),
        (lambda: lierk.GravityGradient(I_SAT), "exactly one of radius"),
        (lambda: lierk.Rotor([0.1, 0.2], axes=[[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), "wheel axis 1"),
        (lambda: lierk.MagneticTorque(FIELD, dipole=[np.nan, 0.0, 1.0]), "dipole"),
        (lambda: lierk.MagneticTorque(FIELD), "exactly one of dipole"),
        (lambda: lierk.dipole_field(-1.0), "mean_motion"),
        (lambda: lierk.dipole_field(radius=-7e6), "radius"),
        (lambda: lierk.dipole_field(tilt=1.0), "mean_motion= .rad/s., radius= .m., or both"),
        (
            lambda: lierk.Rotor([0.1], axes=[[1.0, 0, 0]], torque=[[0.0], [1.0]], times=[1.0, 0.5]),
            "strictly increasing",
        ),
    ],
)
def test_bad_input_is_refused_by_name(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_the_dipole_field_takes_the_orbit_as_the_gravity_gradient_does():
    """Its radius or its mean motion, the other from mu (Kepler's third law)."""
    radius, mu, ts = 7.0e6, 3.986004418e14, np.linspace(0.0, 6000.0, 7)
    n = np.sqrt(mu / radius**3)
    expected = np.stack([np.asarray(lierk.dipole_field(n, radius=radius, tilt=1.2)(t)) for t in ts])
    for field in (lierk.dipole_field(radius=radius, tilt=1.2), lierk.dipole_field(n, tilt=1.2)):
        np.testing.assert_allclose(np.stack([np.asarray(field(t)) for t in ts]), expected, rtol=1e-13, atol=0)


def test_a_field_with_other_numbers_runs_the_compiled_solve():
    """`dipole_field`'s numbers are traced: a satellite in another orbit
    (tilt, mean motion) reuses the program, and the field it solves with is
    the new one (SciPy's solution with it)."""
    from lierk.app.compilations import counting

    omega0 = [0.05, 0.02, -0.03]

    def final(n, tilt):
        field = lierk.dipole_field(n, tilt=tilt)
        body = lierk.RigidBodyWithEffects(I_SAT, omega0, R0, effects=(lierk.MagneticTorque(field, bdot_gain=BDOT),))
        return np.asarray(lierk.solve(body, lierk.RKMK4(), 100.0, dt=0.5).R[-1])

    final(N_ORBIT, 1.2)
    with counting() as seen:
        R = final(N_ORBIT, 0.4)
    assert seen.count == 0, seen.names

    def bdot(tilt):
        def torque(t, R, m, w):
            B = R.T @ field_np(t, tilt=tilt)
            return BDOT * np.cross(np.cross(w, B), B)

        return torque

    # RKMK4's error at this step is about 3e-9; the first field's solution is 1e-4 away.
    assert np.abs(R - scipy_solve(I_SAT, omega0, R0, bdot(0.4), 100.0)[0]).max() < 1e-8
    assert np.abs(R - scipy_solve(I_SAT, omega0, R0, bdot(1.2), 100.0)[0]).max() > 1e-4


def test_splittings_refuse_a_dipole_law_without_an_exact_kick():
    law = lambda t, B, w: 1e3 * jnp.cross(w, B)  # noqa: E731
    body = lierk.RigidBodyWithEffects(I_SAT, [0.01, 0.0, 0.0], effects=(lierk.MagneticTorque(FIELD, dipole=law),))
    with pytest.raises(ValueError, match="no exact kick"):
        lierk.solve(body, lierk.Strang(), 10.0, dt=1.0)


# --- scenes ------------------------------------------------------------------------

SCENE = """
name = "sat"
[body]
kind = "box"
mass = 50.0
lx = 0.6
ly = 0.5
lz = 0.8
[initial]
omega = [0.05, -0.03, 0.04]
mrp = [0.1, -0.2, 0.05]
{effects}
[run]
solver = "RKMK4"
dt = 1.0
t1 = 20.0
"""


def test_scene_effects_are_the_library_effects():
    effects = """
[[effects]]
kind = "gravity_gradient"
mean_motion = 0.0011
[[effects]]
kind = "rotor"
axes = [[0.0, 1.0, 0.0], [0.0, 0.0, 2.0]]
momentum = [0.2, 0.0]
torque = [[0.0, 0.0], [0.0, 0.01]]
times = [0.0, 10.0]
[[effects]]
kind = "magnetic"
mean_motion = 0.0011
tilt = 1.2
bdot_gain = 1e7
"""
    scene = lierk.app.scene.from_dict(__import__("tomllib").loads(SCENE.format(effects=effects)), "sat")
    I = np.asarray(lierk.inertia.box(50.0, 0.6, 0.5, 0.8))
    R0 = np.asarray(lierk.so3.from_mrp(jnp.asarray([0.1, -0.2, 0.05])))
    np.testing.assert_allclose(scene.problem.R0, R0, atol=1e-15)
    direct = lierk.RigidBodyWithEffects(
        I,
        [0.05, -0.03, 0.04],
        R0,
        effects=(
            lierk.GravityGradient(I, mean_motion=0.0011),
            lierk.Rotor(
                [0.2, 0.0], axes=[[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], torque=[[0.0, 0.0], [0.0, 0.01]], times=[0.0, 10.0]
            ),
            lierk.MagneticTorque(FIELD, bdot_gain=1e7),
        ),
    )
    a = lierk.solve(scene.problem, lierk.RKMK4(), 20.0, dt=1.0).R[-1]
    b = lierk.solve(direct, lierk.RKMK4(), 20.0, dt=1.0).R[-1]
    np.testing.assert_allclose(a, b, atol=1e-14)


@pytest.mark.parametrize(
    "effects, match",
    [
        ('[[effects]]\nkind = "gravity_gradient"\nradius = -7e6', "radius"),
        ('[[effects]]\nkind = "gravity_gradient"', "exactly one of 'radius'"),
        ('[[effects]]\nkind = "rotor"\naxes = [[0.0, 0.0, 0.0]]\nmomentum = [0.1]', "wheel axis 0"),
        ('[[effects]]\nkind = "magnetic"\nradius = 7e6\ndipole = [nan, 0.0, 1.0]', "dipole"),
        ('[[effects]]\nkind = "magnetic"\nradius = 7e6', "exactly one of 'dipole'"),
        ('[[effects]]\nkind = "rotor"\nmomentum = [0.1, 0.0, 0.0]\ntorque = [[0.1]]', "give 'axes' too"),
    ],
)
def test_bad_scene_effects_are_refused_by_name(effects, match):
    with pytest.raises(ValueError, match=match):
        lierk.app.scene.from_dict(__import__("tomllib").loads(SCENE.format(effects=effects)), "sat")


def test_the_example_satellite_detumbles():
    scene = lierk.app.scene.load(Path(__file__).resolve().parent.parent / "examples" / "satellite.toml")
    sol = lierk.solve(
        scene.problem, lierk.DOP853(), scene.t1, rtol=1e-6, saveat=lierk.SaveAt(ts=jnp.linspace(0.0, scene.t1, 7))
    )
    E = np.asarray(sol.invariants(scene.problem)["energy"])
    assert E[-1] < 1e-2 * E[0]


def test_moment_spread_is_the_eigenvalues_spread():
    # Gravity gradient's energy scale takes I_max - I_min in closed form
    # (no LAPACK call in the program): against eigvalsh on rotated inertias,
    # distinct, double, triple and 1e12 apart.
    from lierk._problems.spacecraft import _moment_spread

    rng = np.random.default_rng(3)
    cases = []
    for lam in ([1.0, 2.0, 3.5], [2.0, 2.0, 5.0], [4.0, 1.0, 1.0], [3.0, 3.0, 3.0], [1e-6, 1.0, 1e6]):
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        cases.append(Q @ np.diag(lam) @ Q.T)
    got = np.asarray(jax.jit(jax.vmap(_moment_spread))(np.stack(cases)))
    for I, g in zip(cases, got):
        e = np.linalg.eigvalsh(I)
        assert abs(g - (e[-1] - e[0])) <= 1e-7 * e[-1], (g, e)
    assert got[3] <= 1e-7 * 3.0


def test_a_diagonal_inertia_gives_gravity_gradient_its_spread_from_the_diagonal():
    # A concrete diagonal inertia takes max - min of its moments (no cubic to
    # trace); a rotated or traced one the closed form.  Both the same scale.
    n = 1.1e-3
    moments = np.array([10.0, 14.0, 6.0])
    Q, _ = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))
    diagonal = lierk.GravityGradient(moments, mean_motion=n)
    rotated = lierk.GravityGradient(Q @ np.diag(moments) @ Q.T, mean_motion=n)
    assert diagonal.diagonal and not rotated.diagonal
    assert float(diagonal.energy_scale()) == 1.5 * n**2 * 8.0
    np.testing.assert_allclose(float(rotated.energy_scale()), 1.5 * n**2 * 8.0, rtol=1e-9)

    def traced(I):
        effect = lierk.GravityGradient(I, mean_motion=n)
        return effect.energy_scale(), effect.diagonal

    scale, flag = jax.jit(traced)(jnp.asarray(np.diag(moments)))
    assert not flag
    np.testing.assert_allclose(float(scale), 1.5 * n**2 * 8.0, rtol=1e-9)
