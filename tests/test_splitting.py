"""Splitting solvers (kick, exact drift, kick) and time-dependent torques.

Claims: each splitting has its order on heavy tops (fitted slope within 0.15);
the symmetric-top drift equals the general elliptic one; kicks are exact
flows; a conservative top's energy error stays bounded over long runs;
splittings vmap, differentiate and give `target_error`; `TimedTorque` (samples
or a function, body or space frame) integrates exactly where the answer is
known, sweeps without recompiling, and is refused when malformed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    SPLITTING_SOLVERS,
    TORQUE_IMPULSE,
    TORQUE_SAMPLES,
    TORQUE_TIMES,
    derivatives_and_differences,
    final_attitudes,
    order_fit,
    write,
)

import lierk
from lierk import exact, so3

T = 2.0
TILT = so3.exp(jnp.array([-np.pi / 16, 0.0, 0.0]))
# DiffMan's heavy top (symmetric: the drift is two rotations) and an
# asymmetric one (the drift is the elliptic-function flow).
TOPS = {
    "diffman": dict(inertia=[7 / 8, 7 / 8, 2 / 8], chi=[0.0, 0.0, np.sqrt(3) / 2], omega0=[0.0, 0.0, 1.0]),
    "asymmetric": dict(inertia=[0.9, 0.7, 0.3], chi=[0.05, 0.02, 0.8], omega0=[0.3, 0.1, 3.0]),
}


def top(name, **kw):
    t = TOPS[name]
    return lierk.RigidBodyWithEffects(
        t["inertia"], t["omega0"], TILT, effects=(lierk.Gravity(t["chi"], 1.0, 9.81),), **kw
    )


_REFS = {}


def reference(name):
    if name not in _REFS:
        sol = lierk.solve(top(name), lierk.DOP853(), T, rtol=1e-14, atol=1e-14, max_steps=100_000)
        _REFS[name] = np.asarray(sol.R[-1])
    return _REFS[name]


# Steps where each method's error lies between ~1e-4 and ~1e-12 on both tops
# (measured), so the fit sees truncation error, not the reference's 1e-13.
# BlanesMoanRKN4 is pre-asymptotic at 0.1 on DiffMan's top (slope 3.83 from
# 0.1 to 0.025): one halving finer.
# BlanesMoanRKN6 is near the reference's error at 0.025 there (2.8e-13), and
# pre-asymptotic at 0.2 (slope 6.5): 20, 25 and 40 steps.
STEPS: dict = {
    "BlanesMoanRKN4": [0.05, 0.025, 0.0125],
    "BlanesMoanRKN6": [0.1, 0.08, 0.05],
}  # the others: 0.1, 0.05, 0.025


@pytest.mark.parametrize("name", TOPS)
@pytest.mark.parametrize("solver", SPLITTING_SOLVERS, ids=lambda s: s.name)
def test_order_on_heavy_tops(solver, name):
    problem = top(name)
    assert (problem.symmetry_axis == 2) == (name == "diffman")
    hs = STEPS.get(solver.name, [0.1, 0.05, 0.025])
    errs = np.linalg.norm(final_attitudes(problem, solver, T, hs) - reference(name), axis=(-2, -1))
    slope = order_fit(hs, errs)
    print(f"{solver.name} {name}: errors {errs}, slope {slope:.2f}")
    assert min(errs) > 3e-13  # above the reference's own error (~1e-13)
    assert abs(slope - solver.order) <= 0.15, (slope, errs)


def test_symmetric_drift_is_the_elliptic_flow():
    rng = np.random.default_rng(1)
    for k in range(3):
        inertia = jnp.diag(jnp.array([5.0, 5.0, 5.0]).at[k].set(1.0))
        m = jnp.asarray(rng.normal(size=3) * np.where(np.arange(3) == k, 20.0, 1.0))
        h = float(rng.uniform(0.01, 2.0))
        Q1, m1 = exact.free_flow(inertia, m, h)
        Q2, m2 = exact.symmetric_flow(5.0, 1.0, k, m, h)
        assert np.abs(np.asarray(Q1 - Q2)).max() < 1e-12
        assert np.abs(np.asarray(m1 - m2)).max() < 1e-12 * float(jnp.linalg.norm(m))


def test_drift_momentum_takes_every_derivative_of_the_closed_form():
    """The drift moves m by its addition-theorem change (for the energy's
    sake) but differentiates as the closed form's ``inertia omega(h)``: its
    gradient and the gradient of a JVP's primal (reverse over forward, which
    a rule attaching only the tangent left at zero) agree with the closed
    form's, in the momentum and in h.  (A Hessian, forward over reverse,
    reads the tangents only; it doubled this program's compile time.)"""
    inertia = jnp.diag(jnp.array([1.0, 2.0, 3.0]))
    w, v = jnp.array([0.3, -1.0, 0.6]), jnp.array([1.0, -0.5, 0.2, 0.7])

    def drift(x):
        return exact.free_flow(inertia, x[:3], x[3])[1] @ w

    def closed(x):
        omega0 = jnp.linalg.solve(inertia, x[:3])
        return (inertia @ exact._free_motion(inertia, omega0, x[3], jnp.eye(3, dtype=x.dtype))[1]) @ w

    @jax.jit
    def derivatives(x):
        return [(f(x), jax.grad(f)(x), jax.grad(lambda x: jax.jvp(f, (x,), (v,))[0])(x)) for f in (drift, closed)]

    (a, b) = derivatives(jnp.array([0.4, -1.0, 2.0, 0.7]))
    for p, q in zip(a, b):
        np.testing.assert_allclose(p, q, rtol=0, atol=1e-12 * float(np.abs(q).max()))
    assert float(np.abs(a[2]).max()) > 0.1  # (the primal's derivative is the gradient, not zero)


def test_symmetry_axis_is_found_only_for_exactly_symmetric_constant_inertia():
    assert lierk.FreeRigidBody([2.0, 1.0, 2.0], [1.0, 0, 0]).symmetry_axis == 1
    assert lierk.FreeRigidBody([2.0, 1.0, 2.0 + 1e-9], [1.0, 0, 0]).symmetry_axis is None
    assert lierk.FreeRigidBody(np.diag([3.0, 3.0, 3.0]), [1.0, 0, 0]).symmetry_axis is not None
    rot = np.asarray(so3.exp(jnp.array([0.3, 0.2, 0.1])))
    assert lierk.FreeRigidBody(rot @ np.diag([1.0, 1.0, 2.0]) @ rot.T, [1.0, 0, 0]).symmetry_axis is None
    axes = jax.vmap(lambda i: lierk.FreeRigidBody(i, jnp.ones(3)).y0)(jnp.ones((2, 3)))  # traced: general path
    assert axes.shape == (2, 3)


def test_damping_kick_is_the_exponential():
    inertia = np.array([[2.0, 0.3, 0.1], [0.3, 1.5, -0.2], [0.1, -0.2, 1.0]])
    inv = np.linalg.inv(inertia)
    m = jnp.array([0.4, -1.0, 2.0])
    got = lierk.Damping(0.7).kick(0.0, jnp.eye(3), m, 0.3, jnp.asarray(inv))
    want = jax.scipy.linalg.expm(jnp.asarray(-0.7 * 0.3 * inv)) @ m
    assert np.abs(np.asarray(got - want)).max() < 1e-14


@pytest.mark.parametrize("solver", [s for s in SPLITTING_SOLVERS if not s.scheme.nystrom], ids=lambda s: s.name)
def test_damped_sphere_is_exact(solver):
    """On a sphere the drift (a rotation about m) and the damping kick commute,
    so any splitting is exact: omega(t) = omega0 exp(-c t / I)."""
    I, c, w0 = 2.0, 0.5, jnp.array([0.3, -1.0, 2.0])
    body = lierk.RigidBodyWithEffects([I, I, I], w0, effects=lierk.Damping(c))
    sol = lierk.solve(body, solver, 3.0, dt=0.5)
    assert np.abs(np.asarray(sol.omega(body)[-1] - w0 * np.exp(-c * 3.0 / I))).max() < 1e-14


@pytest.mark.parametrize("solver", [lierk.BlanesMoanRKN4(), lierk.BlanesMoanRKN6()], ids=lambda s: s.name)
def test_nystrom_splittings_refuse_torques_that_read_the_momentum(solver):
    # Their order rests on kicks that do not read m ([K, [K, [K, D]]] = 0);
    # with damping they would silently lose it.
    body = lierk.RigidBodyWithEffects(
        [2.0, 2.0, 1.0], [0.3, -1.0, 2.0], effects=(lierk.Gravity([0, 0, 1.0], 1.0), lierk.Damping(0.5))
    )
    with pytest.raises(ValueError, match="Runge-Kutta-Nystrom.*Damping"):
        lierk.solve(body, solver, 1.0, dt=0.1)


@pytest.mark.parametrize("solver", [lierk.BlanesMoanRKN4(), lierk.BlanesMoanRKN6()], ids=lambda s: s.name)
def test_nystrom_order_holds_for_every_torque_of_time_and_attitude(solver):
    """Gravity, a space torque, and body and space torques that vary in time:
    none reads the momentum, so [K, [K, [K, D]]] = 0 still holds and the
    Runge-Kutta-Nystrom order is kept (on the asymmetric top's elliptic drift)."""
    t = TOPS["asymmetric"]
    effects = (
        lierk.Gravity(t["chi"], 1.0, 9.81),
        lierk.SpaceTorque([0.2, -0.1, 0.3]),
        lierk.TimedTorque(lambda s: jnp.stack([0.3 * jnp.sin(2.0 * s), 0.1 * s, 0.2]), frame="body"),
        lierk.TimedTorque(lambda s: jnp.stack([0.1, 0.2 * jnp.cos(s), -0.1 * s]), frame="space"),
    )
    body = lierk.RigidBodyWithEffects(t["inertia"], t["omega0"], TILT, effects=effects)
    ref = np.asarray(lierk.solve(body, lierk.DOP853(), T, rtol=1e-14, atol=1e-14, max_steps=100_000).R[-1])
    hs = STEPS[solver.name]
    errs = np.linalg.norm(final_attitudes(body, solver, T, hs) - ref, axis=(-2, -1))
    slope = order_fit(hs, errs)
    assert min(errs) > 3e-13, errs
    assert abs(slope - solver.order) <= 0.15, (slope, errs)


def symmetric_top_with_timed_torque(dtype):
    t = TOPS["diffman"]
    effects = (
        lierk.Gravity(np.asarray(t["chi"], dtype), dtype(1.0), dtype(9.81)),
        lierk.TimedTorque(lambda s: jnp.stack([0.1 * jnp.sin(s), 0.05, -0.1 * s]).astype(dtype), frame="space"),
    )
    return lierk.RigidBodyWithEffects(
        np.asarray(t["inertia"], dtype), np.asarray(t["omega0"], dtype), np.asarray(TILT, dtype), effects=effects
    )


@pytest.mark.parametrize("solver", [lierk.Strang(), lierk.BlanesMoan6(), lierk.BlanesMoanRKN6()], ids=lambda s: s.name)
def test_float32_on_a_symmetric_top_with_a_timed_space_torque(solver):
    """The unrolled closed-form drift and the kicks stay in float32 (a function
    torque's space vectors once lifted the kick to float64 and broke the
    loop), and land within float32 rounding of the float64 run: 40 steps,
    measured 1.5e-6 to 5.4e-6 over all seven splittings (three run here: the
    kick is the same code for all)."""
    R64 = np.asarray(lierk.solve(symmetric_top_with_timed_torque(np.float64), solver, T, dt=0.05).R[-1])
    R32 = lierk.solve(symmetric_top_with_timed_torque(np.float32), solver, T, dt=0.05).R[-1]
    assert R32.dtype == jnp.float32
    assert np.linalg.norm(np.asarray(R32, np.float64) - R64) < 2e-5


@pytest.mark.parametrize("solver", [lierk.Strang(), lierk.BlanesMoanRKN6()], ids=lambda s: s.name)
def test_unrolled_closed_form_drift_equals_the_looped_elliptic_one(solver):
    """A concrete symmetric inertia takes the two-rotation drift with unrolled
    stages; the same inertia traced takes the elliptic flow in a lax.scan.
    Same motion (measured 1.6e-14 and 1.2e-13)."""
    t = TOPS["diffman"]

    def final(inertia):
        body = lierk.RigidBodyWithEffects(inertia, t["omega0"], TILT, effects=(lierk.Gravity(t["chi"], 1.0, 9.81),))
        return lierk.solve(body, solver, T, dt=0.1).R[-1]

    concrete = final(np.asarray(t["inertia"]))
    traced = jax.jit(final)(jnp.asarray(t["inertia"]))
    assert np.abs(np.asarray(concrete - traced)).max() < 1e-12


def energy_error(problem, sol):
    E = np.asarray(problem.invariants(sol.R, sol.y)["energy"])
    return np.abs(E / E[0] - 1.0)


@pytest.mark.parametrize(
    "name,solver,dt,bound",
    [
        ("diffman", lierk.Strang(), 0.02, 2e-3),
        ("asymmetric", lierk.BlanesMoan4(), 0.05, 1e-6),
    ],
)
def test_energy_error_stays_bounded(name, solver, dt, bound):
    """2e4 and 4e3 steps over 400 s and 200 s: no secular growth (the last
    tenth's largest error at most 2x the first tenth's), below ``bound``.
    (The benchmark runs 10^6 steps; RKMK4 at the same setting drifts.)"""
    problem = top(name)
    t1 = 400.0 if name == "diffman" else 200.0
    n = round(t1 / dt)
    sol = lierk.solve(problem, solver, t1, dt=dt, saveat=lierk.SaveAt(steps=10))
    err = energy_error(problem, sol)
    k = len(err) // 10
    first, last = err[1 : k + 1].max(), err[-k:].max()
    print(f"{solver.name} {name}: {n} steps, first tenth {first:.2e}, last tenth {last:.2e}")
    assert last <= 2 * first
    assert err.max() < bound


def test_rkmk4_energy_drifts_where_splitting_does_not():
    """The control: the same measure does detect RKMK4's linear drift."""
    problem = top("asymmetric")
    sol = lierk.solve(problem, lierk.RKMK4(), 200.0, dt=0.05, saveat=lierk.SaveAt(steps=10))
    err = energy_error(problem, sol)
    k = len(err) // 10
    assert err[-k:].max() > 2 * err[1 : k + 1].max()


@pytest.mark.parametrize(
    "inertia,omega0",
    [
        ([1.0, 2.0, 3.0], [0.3, 1.0, 0.2]),  # tumbling near the separatrix: the elliptic-function drift
        ([1.0, 2.0, 2.9], [1.0, -0.4, 2.0]),  # the elliptic drift, about the largest axis
        ([1.0, 1.0, 1.8], [1.0, 0.3, 0.1]),  # symmetric: the drift is two rotations
    ],
)
def test_energy_rounding_is_a_random_walk_not_a_drift(inertia, omega0):
    """Brouwer's law for a free body: each Strang step is the exact flow, so
    the energy error is rounding alone, and it must not have a sign.  Over
    2e4 steps from 8 nearby omega0 the mean error at the end is within 4
    standard errors of 0 and every error below 1e-13 (measured: at most
    5e-14).  The drift once rebuilt m from the closed form, whose amplitudes,
    functions of the invariants, were rounded alike in every drift of a run,
    so each run drifted with a sign of its own (largest errors 1.3e-12,
    2e-12 here); then it moved m by the difference of two closed-form
    values, which left a bias of about 0.01 ulp a drift (diag(1, 2, 2.9):
    mean 35 standard errors from 0, largest error 2.9e-13).  Now the change of
    m comes from the addition theorems, rounded relative to the change
    (`lierk.exact._momentum_change`)."""
    problem = lierk.FreeRigidBody(inertia, omega0)
    omega0 = np.asarray(omega0) * (1.0 + 1e-3 * np.random.default_rng(0).standard_normal((8, 3)))

    @jax.jit
    @jax.vmap
    def energy_error(w):
        q = problem.with_omega0(w)
        sol = lierk.solve(q, lierk.Strang(), 20.0, dt=1e-3, saveat=lierk.SaveAt(t0=True, steps=200))
        E = sol.invariants(q)["energy"]
        return E / E[0] - 1.0

    dE = np.asarray(energy_error(jnp.asarray(omega0)))
    end = dE[:, -1]
    standard_error = end.std(ddof=1) / np.sqrt(len(end))
    print(f"end: mean {end.mean():.2e}, standard error {standard_error:.2e}; max {np.abs(dE).max():.2e}")
    assert abs(end.mean()) < 4 * standard_error
    assert np.abs(dE).max() < 1e-13


def test_vmap_matches_a_loop():
    solver = lierk.BlanesMoan4()
    omegas = np.array([[0.3, 0.1, 3.0], [0.0, 0.5, 2.0], [1.0, -0.2, 4.0]])
    one = lambda w: lierk.solve(top("asymmetric").with_omega0(w), solver, 1.0, dt=0.05).R[-1]  # noqa: E731
    batch = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(omegas)))
    for i, w in enumerate(omegas):
        assert np.abs(batch[i] - np.asarray(one(jnp.asarray(w)))).max() < 1e-13


def test_gradient_matches_finite_differences():
    solver = lierk.Strang()

    def f(w):
        return lierk.solve(top("asymmetric").with_omega0(w), solver, 1.0, dt=0.05).R[-1][0, 2]

    w = jnp.array([0.3, 0.1, 3.0])
    g = np.asarray(jax.grad(f)(w))
    eps = 1e-6
    fd = np.array([(f(w + eps * e) - f(w - eps * e)) / (2 * eps) for e in np.eye(3)])
    assert np.all(np.isfinite(g))
    assert np.abs(g - fd).max() < 1e-7 * max(1.0, np.abs(fd).max())


def test_target_error_with_a_splitting():
    sol = lierk.solve(top("asymmetric"), lierk.BlanesMoan4(), T, target_error=1e-8)
    assert int(sol.result) == lierk.RESULTS.successful
    err = np.linalg.norm(np.asarray(sol.R[-1]) - reference("asymmetric"))
    print(f"error {err:.2e}, estimate {float(sol.error_estimate[-1]):.2e}")
    assert err < 1e-8


def test_problems_without_a_drift_are_refused():
    class Custom(lierk.AbstractProblem):
        R0: jax.Array
        y0: None = None

        def field(self, t, R, y):
            return jnp.ones(3), None

    with pytest.raises(ValueError, match="drift"):
        lierk.solve(Custom(jnp.eye(3)), lierk.Strang(), 1.0, dt=0.1)


def test_effect_reading_momentum_without_a_kick_is_refused():
    class Drag(lierk.AbstractEffect):
        def torque(self, t, R, m, omega):
            return -0.1 * omega * jnp.linalg.norm(omega)

    body = lierk.RigidBodyWithEffects([1.0, 2.0, 3.0], [1.0, 0, 0], effects=Drag())
    with pytest.raises(ValueError, match="exact kick"):
        lierk.solve(body, lierk.Strang(), 1.0, dt=0.1)
    # RKMK solvers take it.
    assert int(lierk.solve(body, lierk.RKMK4(), 1.0, dt=0.1).result) == lierk.RESULTS.successful


# --- TimedTorque -------------------------------------------------------------

TIMES, SAMPLES, IMPULSE = TORQUE_TIMES, TORQUE_SAMPLES, TORQUE_IMPULSE


@pytest.mark.parametrize(
    "solver,kw,tol",
    [
        (lierk.RKMK4(), dict(dt=0.05), 1e-12),
        (lierk.Strang(), dict(dt=0.05), 1e-12),
        (lierk.BlanesMoan4(), dict(dt=0.05), 1e-12),
    ],
)
def test_sampled_body_torque_about_a_principal_axis(solver, kw, tol):
    """Spin about body z with a torque along body z: m3 grows by the impulse
    (the other components stay 0).  Fixed steps with the sample times on their
    grid integrate the piecewise-linear profile exactly (the adaptive solver,
    which steps across the kinks: tests/test_last_bits.py)."""
    body = lierk.RigidBodyWithEffects([1.0, 2.0, 3.0], [0.0, 0.0, 0.7], effects=lierk.TimedTorque(SAMPLES, times=TIMES))
    sol = lierk.solve(body, solver, 2.5, **kw)
    m = np.asarray(sol.y[-1])
    assert abs(m[2] - (3.0 * 0.7 + IMPULSE)) < tol
    assert np.abs(m[:2]).max() < 1e-14


@pytest.mark.parametrize(
    "solver,kw,tol",
    [
        (lierk.DOP853(), dict(rtol=1e-12, atol=1e-12), 1e-10),
        (lierk.Yoshida6(), dict(dt=0.02), 1e-10),
    ],
)
def test_space_torque_function_changes_L_by_its_integral(solver, kw, tol):
    """Any body: dL/dt = tau_space(t), so L(T) = L0 + int_0^T tau."""
    tau = lambda t: jnp.stack([0.2 * jnp.sin(3.0 * t), 0.1 * t, jnp.cos(t)])  # noqa: E731
    t1 = 2.0
    integral = np.array([0.2 * (1 - np.cos(3.0 * t1)) / 3.0, 0.05 * t1**2, np.sin(t1)])
    body = lierk.RigidBodyWithEffects(
        [1.0, 2.0, 2.5], [0.4, 2.0, -0.3], TILT, effects=lierk.TimedTorque(tau, frame="space")
    )
    sol = lierk.solve(body, solver, t1, **kw)
    L = np.asarray(sol.R[-1] @ sol.y[-1])
    assert np.abs(L - (np.asarray(body.L) + integral)).max() < tol


def test_space_and_body_frames_differ_by_the_attitude():
    """A space-frame torque equals the body-frame torque R^T tau at the same point."""
    R = so3.exp(jnp.array([0.3, -0.5, 1.1]))
    eff_s = lierk.TimedTorque(SAMPLES, times=TIMES, frame="space")
    eff_b = lierk.TimedTorque(SAMPLES, times=TIMES)
    m, w = jnp.ones(3), jnp.ones(3)
    got = eff_s.torque(jnp.asarray(1.0), R, m, w)
    assert np.abs(np.asarray(got - R.T @ eff_b.torque(jnp.asarray(1.0), R, m, w))).max() < 1e-15


def test_sweeping_samples_does_not_recompile_and_differentiates():
    traces = []

    @jax.jit
    def final_m3(values):
        traces.append(1)
        body = lierk.RigidBodyWithEffects(
            [1.0, 2.0, 3.0], [0.0, 0.0, 0.7], effects=lierk.TimedTorque(values, times=TIMES)
        )
        return lierk.solve(body, lierk.RKMK4(), 2.5, dt=0.05).y[-1, 2]

    v = jnp.asarray(SAMPLES)
    a, b = final_m3(v), final_m3(2 * v)
    assert len(traces) == 1
    assert abs(float(b - a) - IMPULSE) < 1e-12
    g = np.asarray(jax.grad(final_m3)(v))
    # d m3 / d sample_k (z) is the area of its hat function over [0, 2.5]: the
    # last sample is also held over [2, 2.5].
    assert np.abs(g[:, 2] - [0.25, 0.75, 0.75, 0.75]).max() < 1e-12
    assert np.abs(g[:, :2]).max() < 1e-12


@pytest.mark.parametrize(
    "args,kw,match",
    [
        (([[0, 0, 1.0]],), {}, "need their times"),
        (([[0, 0, 1.0], [0, 0, 2.0]],), dict(times=[1.0, 1.0]), "strictly increasing"),
        (([[0, 0, 1.0], [0, 0, 2.0]],), dict(times=[0.0, 1.0, 2.0]), r"shape \(3, 3\)"),
        (([[0, 0, float("nan")]],), dict(times=[0.0]), "finite"),
        ((lambda t: jnp.ones(2),), {}, r"shape \(3,\)"),
        ((lambda t: jnp.ones(3),), dict(times=[0.0]), "times apply"),
        (([[0, 0, 1.0]],), dict(times=[0.0], frame="world"), "frame"),
    ],
)
def test_bad_timed_torques_raise(args, kw, match):
    with pytest.raises(ValueError, match=match):
        lierk.TimedTorque(*args, **kw)


SCENE = """
name = "burn"
[body]
kind = "box"
mass = 2.0
lx = 0.3
ly = 0.2
lz = 0.1
[initial]
omega = [0.0, 0.0, 0.7]
[[effects]]
kind = "timed_torque"
frame = "body"
times = [0.0, 0.5, 1.5, 2.0]
torque = [[0, 0, 0], [0, 0, 0.4], [0, 0, 0.4], [0, 0, 0]]
[run]
solver = "BlanesMoan4"
t1 = 2.5
dt = 0.05
"""


def test_scene_timed_torque(tmp_path):
    scene = lierk.app.scene.load(write(tmp_path, SCENE))
    (effect,) = scene.problem.effects
    assert isinstance(effect, lierk.TimedTorque) and effect.frame == "body"
    assert isinstance(scene.solver, lierk.BlanesMoan4)
    sol = scene.solve()
    I3 = float(scene.problem.inertia[2, 2])
    assert abs(float(sol.y[-1, 2]) - (I3 * 0.7 + IMPULSE)) < 1e-12
    bad = SCENE.replace("[0, 0, 0]]", "]").replace(
        "torque = [[0, 0, 0], [0, 0, 0.4], [0, 0, 0.4], ]", "torque = [[0, 0, 0]]"
    )
    with pytest.raises(ValueError, match="one \\[x, y, z\\] per time"):
        lierk.app.scene.load(write(tmp_path, bad, "bad.toml"))


def test_scene_gravity_mass_must_match_the_body(tmp_path):
    text = (
        SCENE.split("[[effects]]")[0] + '[[effects]]\nkind = "gravity"\npivot = [0, 0, -0.05]\nmass = 3.0\n'
        '[run]\nsolver = "RKMK4"\nt1 = 1.0\ndt = 0.01\n'
    )
    with pytest.raises(ValueError, match=r"effects\[0\].mass = 3 kg differs from the body's mass 2 kg"):
        lierk.app.scene.load(write(tmp_path, text))
    same = text.replace("mass = 3.0\n[run]", "mass = 2.0\n[run]")
    assert lierk.app.scene.load(write(tmp_path, same, "same.toml")).problem.effects[0].mass == 2.0


# ------------------------------------------- derivatives at rest and in steady spin


def _final_state(solver, inertia, w):
    sol = lierk.solve(lierk.FreeRigidBody(inertia, w), solver, 2.0, dt=0.05)
    return jnp.concatenate([sol.R[-1].ravel(), sol.y[-1]])


# The inertia is an argument of the program, so it is traced: every body,
# symmetric ones too, drifts with the elliptic-function flow.  One program
# for every case, both modes and the finite differences.
_ELLIPTIC = derivatives_and_differences(lambda w, inertia: _final_state(lierk.Strang(), inertia, w))
STEADY = [
    ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]),
    ([1.0, 2.0, 3.0], [1e-3, 0.0, 0.0]),
    ([1.0, 2.0, 3.0], [1.0, 0.0, 0.0]),
    ([1.0, 2.0, 3.0], [0.0, 1.0, 0.0]),
    ([1.0, 2.0, 3.0], [0.0, 0.0, 1.0]),
    ([1.0, 1.0, 2.0], [0.0, 0.0, 1.0]),
    ([1.0, 1.0, 2.0], [1.0, 0.0, 0.0]),
    ([2.0, 2.0, 2.0], [1.0, 0.0, 0.0]),
    ([2.0, 2.0, 2.0], [0.0, 0.0, 0.0]),
]


def test_jacobian_at_rest_and_steady_spin_with_the_elliptic_drift():
    """d(R(T), m(T))/d omega0 through the exact drift, by jacfwd and jacrev,
    against finite differences, at rest, slow and steady spin about each
    principal axis, a symmetric body and a sphere.  Before the fix (Strang):
    rest J = 0 against 3, |J| = 3000 at (1e-3, 0, 0), axis 0 off by 3.2.
    (Strang only: every splitting drifts with the same `exact.free_flow`.)"""
    for inertia, w in STEADY:
        jacobians, ref = _ELLIPTIC(w, inertia)
        for kind, J in zip(("jacfwd", "jacrev"), jacobians):
            assert np.isfinite(J).all()
            err = np.abs(J - ref).max()
            assert err < 1e-6 * np.abs(ref).max(), (inertia, w, kind, err)


@pytest.mark.parametrize("inertia", [[1.0, 1.0, 2.0], [2.0, 2.0, 2.0]])
def test_jacobian_at_rest_and_steady_spin_with_the_symmetric_drift(inertia):
    """The same with a concrete symmetric inertia (the closed-form drift,
    `exact.symmetric_flow`), about the symmetric axis and a transverse one."""
    assert lierk.FreeRigidBody(inertia, [0.0, 0.0, 1.0]).symmetry_axis is not None

    def value(w):
        return _final_state(lierk.BlanesMoan4(), inertia, w)

    checks = derivatives_and_differences(value)
    for w in ([0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]):
        jacobians, ref = checks(w)
        for kind, J in zip(("jacfwd", "jacrev"), jacobians):
            assert np.abs(J - ref).max() < 1e-6 * np.abs(ref).max(), (w, kind)


def test_heavy_top_released_at_rest_gradient():
    """An asymmetric heavy top tilted about its body x axis and let go: the
    torque, and so m, stays along e1 (a principal axis) in every drift.  Its
    gradient with Strang was wrong by the whole gradient."""
    R0 = so3.exp(jnp.array([0.3, 0.0, 0.0]))
    effects = (lierk.Gravity([0.0, 0.0, 0.5], 1.0, 9.81),)

    def final(w):
        sol = lierk.solve(
            lierk.RigidBodyWithEffects([1.0, 2.0, 3.0], w, R0, effects=effects), lierk.Strang(), 1.0, dt=0.05
        )
        return jnp.concatenate([sol.R[-1].ravel(), sol.y[-1]])

    weights = np.linspace(-1.0, 1.0, 12)

    # (The gradient as jacrev of the weighted sum: one program with jacfwd
    # and the finite differences.)
    def with_loss(w):
        y = final(w)
        return jnp.append(y, y @ weights)

    (J, g), ref = derivatives_and_differences(with_loss)(np.zeros(3))
    J, g, ref = J[:12], g[12], ref[:12]
    assert np.abs(J - ref).max() < 1e-6 * np.abs(ref).max()
    np.testing.assert_allclose(g, weights @ ref, rtol=0, atol=1e-6 * np.abs(weights @ ref).max())
