"""Events (`lierk.Event`, `lierk.conditions`): crossing times against
independent references (the flip against `lierk.exact`, a Lagrange top's
tilt extrema against its quadrature), their gradients against finite
differences, termination (one member of a batch at a time), several events
and several crossings in one step, and bad conditions."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TEE, fd_jacobian
from scipy.integrate import quad
from scipy.optimize import brentq
from test_tops import TOPS, _problem, quadrature

import lierk
import lierk.exact

CASE_A = np.array([1.0, 0.05, 0.0])  # the report's case a: flips every 23.63 s
BODY = lierk.FreeRigidBody(TEE, CASE_A)
# TEE's intermediate principal axis is body x (I = 9.8e-5 between 7.2e-5 and 1.6e-4).
_exact_m = jax.jit(lambda w, t: TEE @ lierk.exact.free_rigid_body(TEE, w, t)[1])


def exact_flip_times(omega0, t1, n_grid=4001):
    """Where the exact body momentum's intermediate component changes sign
    in ``[0, t1]``: a grid, then Brent's method on `lierk.exact` to 1e-14 s."""
    ts = np.linspace(0.0, t1, n_grid)
    m1 = np.asarray(jax.vmap(lambda t: _exact_m(omega0, t))(ts))[:, 0]
    k = np.nonzero(np.signbit(m1[1:]) != np.signbit(m1[:-1]))[0]
    return np.array(
        [brentq(lambda t: float(_exact_m(omega0, t)[0]), ts[i], ts[i + 1], xtol=1e-14, rtol=1e-15) for i in k]
    )


@eqx.filter_jit
def _solve(problem, solver, t1, event, saveat=None, **kwargs):
    return lierk.solve(problem, solver, t1, event=event, saveat=saveat, throw=False, **kwargs)


def _times(record):
    return np.asarray(record.ts)[: min(int(record.count), record.ts.shape[-1])]


# --- against independent references ----------------------------------------------


@pytest.mark.parametrize(
    "solver, kwargs, tol",
    # Measured: 9.1e-11 s, 9.6e-11 s, 2.6e-9 s.
    [
        (lierk.DOP853(), dict(rtol=1e-10, max_steps=4000), 1e-9),
        (lierk.RKMK4(), dict(dt=0.01), 1e-9),
        (lierk.DP54(), dict(rtol=1e-10, max_steps=4000), 1e-8),
    ],
    ids=["DOP853", "RKMK4", "DP54"],
)
def test_flip_times_match_the_exact_solution(solver, kwargs, tol):
    ref = exact_flip_times(CASE_A, 80.0)
    assert len(ref) == 3
    sol = _solve(BODY, solver, 80.0, lierk.conditions.flip(BODY), **kwargs)
    assert int(sol.result) == lierk.RESULTS.successful
    assert int(sol.events.count) == 3 and not bool(sol.events.stopped)
    np.testing.assert_allclose(_times(sol.events), ref, rtol=0, atol=tol)
    np.testing.assert_allclose(np.diff(_times(sol.events)), float(lierk.exact.flip_interval(TEE, CASE_A)), atol=2 * tol)
    # The states recorded there are on the plane m . e2 = 0 (measured 6e-22, |m| = 1e-4).
    assert np.abs(np.asarray(sol.events.y)[:3, 0]).max() < 1e-12 * np.linalg.norm(TEE @ CASE_A)


def test_a_body_near_its_largest_axis_does_not_flip():
    # m2 changes sign on this orbit too, but e2 is never the axis closest to L.
    calm = lierk.FreeRigidBody(TEE, [0.05, 0.1, 1.0])
    assert math.isinf(float(lierk.exact.flip_interval(TEE, [0.05, 0.1, 1.0])))
    plane = lierk.Event(lambda t, R, m: m[0])
    sol = _solve(calm, lierk.DOP853(), 30.0, (lierk.conditions.flip(calm), plane), rtol=1e-8)
    assert int(sol.events[0].count) == 0 and np.isinf(np.asarray(sol.events[0].ts)).all()
    assert int(sol.events[1].count) >= 4


def test_flip_of_the_reports_form_and_under_damping():
    # SpatialFreeRigidBody keeps m = R^T L: the same flips.
    spatial = lierk.SpatialFreeRigidBody(TEE, CASE_A)
    sol = _solve(spatial, lierk.DOP853(), 40.0, lierk.conditions.flip(spatial), rtol=1e-11, max_steps=4000)
    np.testing.assert_allclose(_times(sol.events), exact_flip_times(CASE_A, 40.0), atol=1e-8)
    # Damping slows the body (the first flip comes 0.15 s late) and moves its
    # orbit (the next ones come 3.5 and 8.8 s early); two solvers agree on
    # when (measured 5e-12 s).
    damped = lierk.RigidBodyWithEffects(TEE, CASE_A, effects=(lierk.Damping(2e-7),))
    a = _solve(damped, lierk.DOP853(), 60.0, lierk.conditions.flip(damped), rtol=1e-11, max_steps=4000)
    b = _solve(damped, lierk.RKMK4(), 60.0, lierk.conditions.flip(damped), dt=0.005)
    assert int(a.events.count) == 3
    np.testing.assert_allclose(_times(a.events), _times(b.events), atol=1e-9)
    free = exact_flip_times(CASE_A, 60.0)
    assert _times(a.events)[0] > free[0] + 0.1 and (_times(a.events)[1:] < free[1:] - 1.0).all()


@pytest.mark.parametrize("name", ["simo_wong", "diffman"])
def test_lagrange_top_tilt_extrema_match_the_quadrature(name):
    # Both tops start at rest in their nutation, at the smallest tilt (a
    # turning point at t0, which does not count): the largest tilts come at
    # T/2, 3T/2, ... and the smallest at T, 2T, ... of the quadrature's period.
    top, q = TOPS[name], quadrature(name)
    problem = _problem(top)
    axis = top["chi"] / np.linalg.norm(top["chi"])
    events = (
        lierk.conditions.tilt_extremum(problem, axis, extremum="max"),
        lierk.conditions.tilt_extremum(problem, axis, extremum="min"),
    )
    sol = _solve(problem, lierk.DOP853(), top["t1"], events, rtol=1e-12, max_steps=8000)
    lows, highs = _times(sol.events[0]), _times(sol.events[1])
    k = np.arange(1, len(lows) + 1)
    assert len(lows) >= 2 and len(highs) >= 1
    # Measured: 1.8e-11 s (Simo-Wong, whose nutation is 0.027 rad: u'' is
    # small at the turning points), 1.7e-11 s (DiffMan).
    np.testing.assert_allclose(lows, (k - 0.5) * q.period, rtol=0, atol=1e-10)
    np.testing.assert_allclose(highs, np.arange(1, len(highs) + 1) * q.period, rtol=0, atol=1e-10)
    # The tilt there is the quadrature's extreme tilt.
    u = np.asarray(sol.events[0].R)[: len(lows)] @ axis
    np.testing.assert_allclose(u[:, 2], q.u1, atol=1e-10)
    # The tilt crossing the middle of its range, first on the way down at
    # t_c = I1 int_{u_c}^{u2} du/sqrt(f(u)), f = c3 (u - u1)(u2 - u)(u3 - u):
    # with u = u2 - w^2 the integrand is smooth.
    theta_c = 0.5 * (q.theta_min + q.theta_max)
    c3 = 2 * q.I1 * q.mgl
    t_c = (
        q.I1
        * quad(
            lambda w: 2 / math.sqrt(c3 * (q.u2 - q.u1 - w * w) * (q.u3 - q.u2 + w * w)),
            0.0,
            math.sqrt(q.u2 - math.cos(theta_c)),
            epsabs=0.0,
            epsrel=1e-13,
        )[0]
    )
    sol = _solve(
        problem,
        lierk.DOP853(),
        top["t1"],
        lierk.conditions.tilt(theta_c, axis, terminate=True),
        rtol=1e-12,
        max_steps=8000,
    )
    # Measured: 6.5e-12 s (Simo-Wong), 2e-13 s (DiffMan).
    assert float(sol.ts[-1]) == pytest.approx(t_c, abs=5e-11)


def test_energy_and_momentum_drift_on_a_damped_sphere():
    # omega' = -(c/I) omega: E = E0 exp(-2 c t/I) and |L| = |L0| exp(-c t/I),
    # so a relative change q passes at t = -(I/c) ln(1 - q) (|L|), half that (E).
    # Measured: 1e-15 and 4e-14 s.
    c, q = 0.1, 0.1
    sphere = lierk.RigidBodyWithEffects(np.eye(3), [1.0, 2.0, 3.0], effects=(lierk.Damping(c),))
    events = (lierk.conditions.energy_drift(sphere, q), lierk.conditions.momentum_drift(sphere, q, terminate=True))
    sol = _solve(sphere, lierk.DOP853(), 5.0, events, rtol=1e-10)
    t_L = -math.log(1 - q) / c
    assert float(sol.events[0].ts[0]) == pytest.approx(t_L / 2, abs=1e-9)
    assert float(sol.ts[-1]) == pytest.approx(t_L, abs=1e-9) and bool(sol.events[1].stopped)


# --- gradients of event times ----------------------------------------------------


def _first_flip(w, solver=lierk.RKMK4(), **kwargs):
    body = lierk.FreeRigidBody(TEE, w)
    return lierk.solve(body, solver, 20.0, event=lierk.conditions.flip(body, terminate=True), **kwargs).events.ts[0]


def test_event_time_gradient_matches_finite_differences_of_the_exact_flip():
    w = jnp.asarray(CASE_A)
    # Central differences of the exact first flip (4th order, h = 1e-4).
    fd = fd_jacobian(lambda w: exact_flip_times(w, 14.0)[0], CASE_A, h=1e-4)
    # (One program: compiled apart the three cost a third more.)
    fwd, rev, ada = eqx.filter_jit(
        lambda w: (
            jax.jacfwd(lambda w: _first_flip(w, dt=0.01))(w),
            jax.grad(lambda w: _first_flip(w, dt=0.01))(w),
            jax.jacfwd(lambda w: _first_flip(w, lierk.DOP853(), rtol=1e-10, adjoint=lierk.ForwardMode()))(w),
        )
    )(w)
    # Measured: -9.09, -54.5, -121.6 s per rad/s, all three within 7e-10
    # (relative) of the differences.
    for g in (fwd, rev, ada):
        np.testing.assert_allclose(g, fd, rtol=1e-8)


def test_event_time_gradient_in_a_condition_parameter():
    # The time at which the body's z axis first leans `angle` from space z,
    # differentiated in `angle` (a traced field of the condition).
    body = lierk.FreeRigidBody(TEE, [0.2, 1.0, 0.3])

    def t_star(angle):
        ev = lierk.conditions.pointing([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], angle, terminate=True)
        return lierk.solve(body, lierk.RKMK4(), 5.0, dt=0.01, event=ev).ts[-1]

    # The derivative and the differences' values from one program.
    g, values = eqx.filter_jit(
        lambda a: (jax.jacfwd(t_star)(a), jax.vmap(t_star)(a + jnp.asarray([0.0, 1e-5, -1e-5])))
    )(jnp.asarray(0.3))
    fd = (values[1] - values[2]) / 2e-5
    assert 0.1 < float(values[0]) < 5.0
    np.testing.assert_allclose(g, fd, rtol=1e-8)  # measured 8e-12


# --- termination, batches, saving ------------------------------------------------


def test_a_terminating_event_ends_the_solve_there():
    ev = lierk.conditions.flip(BODY, terminate=2)
    for solver, kwargs in ((lierk.DOP853(), dict(rtol=1e-10, max_steps=4000)), (lierk.RKMK4(), dict(dt=0.01))):
        sol = _solve(BODY, solver, 80.0, ev, saveat=lierk.SaveAt(t1=True, dense=True), **kwargs)
        assert int(sol.result) == lierk.RESULTS.event_occurred and bool(sol.ok) and bool(sol.events.stopped)
        t2 = float(sol.events.ts[1])
        assert float(sol.ts[-1]) == t2 and abs(t2 - exact_flip_times(CASE_A, 40.0)[1]) < 1e-9
        np.testing.assert_array_equal(sol.y[-1], sol.events.y[1])
        assert float(sol.interpolation.t1) == t2
        with pytest.raises(ValueError, match="outside the solved interval"):
            sol.evaluate(t2 + 0.1)
    # throw=True does not treat the event as a failure.
    assert lierk.solve(BODY, lierk.RKMK4(), 80.0, dt=0.01, event=ev).events.count == 2


def test_saved_rows_after_a_terminating_event_are_not_reached():
    ev = lierk.Event(lambda t, R, m: t - 0.33, terminate=True)
    fixed = _solve(BODY, lierk.RKMK4(), 1.0, ev, saveat=lierk.SaveAt(t0=True, steps=2, t1=True), dt=0.1)
    np.testing.assert_allclose(fixed.ts[:-1], [0.0, 0.2, 0.4, 0.6, 0.8, 1.0][:5])
    assert float(fixed.ts[-1]) == pytest.approx(0.33, abs=1e-15)
    assert np.isfinite(np.asarray(fixed.R[:2])).all() and np.isnan(np.asarray(fixed.R[2:5])).all()
    assert int(fixed.n_saved) == 3
    # Chunks that fill the run: the last chunk's row is the t1 row.
    full = _solve(BODY, lierk.RKMK4(), 1.0, ev, saveat=lierk.SaveAt(steps=5, t1=True), dt=0.1)
    assert np.isnan(np.asarray(full.R[0])).all() and float(full.ts[-1]) == pytest.approx(0.33, abs=1e-15)
    adaptive = _solve(
        BODY, lierk.DOP853(), 1.0, ev, saveat=lierk.SaveAt(ts=jnp.linspace(0.0, 1.0, 5), t1=True), rtol=1e-9
    )
    assert np.isnan(np.asarray(adaptive.R[2:5])).all() and int(adaptive.n_saved) == 3
    steps = _solve(BODY, lierk.DOP853(), 1.0, ev, saveat=lierk.SaveAt(steps=True), rtol=1e-9, max_steps=64)
    assert float(steps.ts[int(steps.n_saved) - 1]) == pytest.approx(0.33, abs=1e-15)


def test_batch_members_stop_at_their_own_events():
    # Three bodies: two flip at different times, one never does.
    omegas = np.array([[1.0, 0.05, 0.0], [1.0, 0.2, 0.0], [0.05, 0.1, 1.0]])

    def run(w):
        body = BODY.with_omega0(w)
        return lierk.solve(
            body, lierk.DOP853(), 20.0, rtol=1e-10, event=lierk.conditions.flip(body, terminate=True), throw=False
        )

    batch = eqx.filter_jit(jax.vmap(run))(jnp.asarray(omegas))
    np.testing.assert_array_equal(batch.result, [lierk.RESULTS.event_occurred] * 2 + [lierk.RESULTS.successful])
    assert float(batch.ts[2, -1]) == 20.0 and int(batch.events.count[2]) == 0
    assert float(batch.ts[0, -1]) != float(batch.ts[1, -1])
    for i, w in enumerate(omegas):
        one = eqx.filter_jit(run)(jnp.asarray(w))
        np.testing.assert_allclose(batch.ts[i, -1], one.ts[-1], rtol=1e-12)
        np.testing.assert_allclose(batch.R[i, -1], one.R[-1], atol=1e-12)


# --- several events, several crossings, edge cases -------------------------------


def test_two_crossings_in_one_step_and_several_events():
    # One step of 1 s: the parabola crosses at 0.3 and 0.7 (exactly: it reads t only).
    # Checked at the step's ends only (the default), the pair is not seen;
    # sampled inside the step, both are found.
    quick = lierk.Event(lambda t, R, m: (t - 0.3) * (t - 0.7))
    assert int(_solve(BODY, lierk.RKMK4(), 1.0, quick, dt=1.0).events.count) == 0
    parabola = lierk.Event(lambda t, R, m: (t - 0.3) * (t - 0.7), samples=4)
    sol = _solve(BODY, lierk.RKMK4(), 1.0, parabola, dt=1.0)
    np.testing.assert_allclose(_times(sol.events), [0.3, 0.7], atol=1e-15)
    # A terminating event between them drops the crossing after it.
    half = lierk.Event(lambda t, R, m: t - 0.5, terminate=True)
    rising = lierk.Event(lambda t, R, m: (t - 0.3) * (t - 0.7), direction=1, samples=4)
    sol = _solve(BODY, lierk.RKMK4(), 1.0, [parabola, half, rising], dt=1.0)
    assert [int(r.count) for r in sol.events] == [1, 1, 0]
    assert [bool(r.stopped) for r in sol.events] == [False, True, False]
    assert float(sol.ts[-1]) == pytest.approx(0.5, abs=1e-15)
    # Direction: only the rising crossing at 0.7.
    sol = _solve(BODY, lierk.RKMK4(), 1.0, rising, dt=0.1)
    np.testing.assert_allclose(_times(sol.events), [0.7], atol=1e-14)


def test_a_condition_zero_at_t0_fires_only_when_it_reaches_zero_again():
    # Zero at 0 (leaving it is no event), negative until 1, positive until 2.
    cubic = lierk.Event(lambda t, R, m: t * (t - 1.0) * (t - 2.0))
    sol = _solve(BODY, lierk.RKMK4(), 2.5, cubic, dt=0.1)
    np.testing.assert_allclose(_times(sol.events), [1.0, 2.0], atol=1e-14)


def test_a_condition_that_never_crosses():
    sol = _solve(BODY, lierk.DOP853(), 5.0, lierk.Event(lambda t, R, m: 1.0 + m @ m), rtol=1e-8)
    assert int(sol.result) == lierk.RESULTS.successful and int(sol.events.count) == 0
    assert np.isinf(np.asarray(sol.events.ts)).all() and not bool(sol.events.stopped) and float(sol.ts[-1]) == 5.0


def test_bad_conditions_are_refused():
    with pytest.raises(ValueError, match="must return a scalar, got shape \\(3,\\)"):
        lierk.solve(BODY, lierk.RKMK4(), 1.0, dt=0.1, event=lierk.Event(lambda t, R, m: m))
    with pytest.raises(ValueError, match="real \\(floating-point\\) scalar"):
        lierk.solve(BODY, lierk.RKMK4(), 1.0, dt=0.1, event=lierk.Event(lambda t, R, m: t > 0.5))
    nan_later = lierk.Event(lambda t, R, m: jnp.where(t > 0.45, jnp.nan, 1.0))
    for solver, kwargs in ((lierk.RKMK4(), dict(dt=0.1)), (lierk.DOP853(), dict(rtol=1e-8))):
        sol = _solve(BODY, solver, 1.0, nan_later, **kwargs)
        assert int(sol.result) == lierk.RESULTS.event_condition_nan
        with pytest.raises(Exception, match="event condition returned NaN"):
            jax.block_until_ready(lierk.solve(BODY, solver, 1.0, event=nan_later, **kwargs))
    at_t0 = _solve(BODY, lierk.RKMK4(), 1.0, lierk.Event(lambda t, R, m: jnp.nan * t), dt=0.1)
    assert int(at_t0.result) == lierk.RESULTS.event_condition_nan and int(at_t0.stats["num_steps"]) == 0
    for bad, match in [
        (dict(cond=3.0), "cond must be a function"),
        (dict(cond=abs, terminate=0), "terminate"),
        (dict(cond=abs, direction=2), "direction"),
        (dict(cond=abs, terminate=3, max_count=2), "max_count"),
    ]:
        with pytest.raises(ValueError, match=match):
            lierk.Event(**bad)
    with pytest.raises(ValueError, match="non-empty sequence"):
        lierk.solve(BODY, lierk.RKMK4(), 1.0, dt=0.1, event=[])
    with pytest.raises(ValueError, match="target_error"):
        lierk.solve(BODY, lierk.RKMK4(), 1.0, target_error=1e-6, event=lierk.Event(abs))


def test_tilt_extremum_names_its_extremum_as_a_scene_does():
    """``extremum="max" | "min" | "both"``, the scene's key, is the event's
    direction 1, -1, 0; the old ``direction=`` still gives the same event,
    with a deprecation warning."""
    for extremum, direction in (("max", 1), ("min", -1), ("both", 0)):
        event = lierk.conditions.tilt_extremum(BODY, extremum=extremum)
        assert event.direction == direction
        with pytest.warns(DeprecationWarning, match=f"use extremum='{extremum}'"):
            assert lierk.conditions.tilt_extremum(BODY, direction=direction).direction == direction
    with pytest.raises(ValueError, match="extremum must be 'max', 'min' or 'both', got 'lowest'"):
        lierk.conditions.tilt_extremum(BODY, extremum="lowest")
    with pytest.raises(ValueError, match="not both"):
        lierk.conditions.tilt_extremum(BODY, extremum="max", direction=1)


def test_flip_event_in_float32():
    body = lierk.FreeRigidBody(jnp.asarray(TEE, jnp.float32), jnp.asarray(CASE_A, jnp.float32))
    sol = lierk.solve(body, lierk.RKMK4(), 40.0, dt=0.01, event=lierk.conditions.flip(body))
    assert sol.events.ts.dtype == jnp.float32
    # Measured: 2e-6 s for the first flip; 1.5e-3 s for the second, after
    # 3500 float32 steps near the separatrix, where the solve's own rounding
    # moves the orbit (RKMK4's truncation error alone: 1e-10 s, in float64).
    ref = exact_flip_times(CASE_A, 40.0)
    times = _times(sol.events)
    assert len(times) == 2 and abs(times[0] - ref[0]) < 2e-5 and abs(times[1] - ref[1]) < 5e-3


def test_the_valid_rows_of_a_solve_cut_short_end_with_its_final_state():
    """With SaveAt(t1=True) the final state is the last row (``sol.R[-1]``)
    and the rows never reached come before it: `Solution.trajectory` reads
    the reached rows and then the final one, all finite, times increasing."""
    ev = lierk.conditions.flip(BODY, terminate=True)
    t_flip = exact_flip_times(CASE_A, 20.0)[0]
    cases = [
        (lierk.RKMK4(), dict(dt=0.01), lierk.SaveAt(t0=True, steps=10, t1=True), 1 + int(t_flip / 0.1) + 1),
        (lierk.RKMK4(), dict(dt=0.01), lierk.SaveAt(t0=True, steps=7, t1=True), 1 + int(t_flip / 0.07) + 1),
        (lierk.DOP853(), dict(rtol=1e-10), lierk.SaveAt(ts=jnp.linspace(0.0, 60.0, 61), t1=True), int(t_flip) + 2),
    ]
    for solver, kwargs, saveat, rows in cases:
        sol = _solve(BODY, solver, 60.0, ev, saveat=saveat, **kwargs)
        ts, R, y = sol.trajectory()
        assert len(ts) == rows == int(sol.n_saved)
        assert np.isfinite(R).all() and np.isfinite(y).all() and np.all(np.diff(ts) > 0)
        assert abs(ts[-1] - t_flip) < 1e-8 and float(sol.ts[-1]) == ts[-1]
        np.testing.assert_array_equal(R[-1], np.asarray(sol.R[-1]))
    # Cut short by max_steps (no event): the same layout.
    sol = lierk.solve(
        BODY,
        lierk.DOP853(),
        60.0,
        rtol=1e-10,
        saveat=lierk.SaveAt(ts=jnp.linspace(0.0, 60.0, 61), t1=True),
        max_steps=40,
        throw=False,
    )
    ts, R, _ = sol.trajectory()
    assert int(sol.result) == lierk.RESULTS.max_steps_reached and np.isfinite(R).all() and np.all(np.diff(ts) >= 0)
    assert ts[-1] == float(sol.ts[-1]) < 60.0
