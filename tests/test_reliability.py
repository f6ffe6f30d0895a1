"""Regression tests from the adversarial pass (the reliability issue): each
input here once gave a wrong answer reported as success, or a raw traceback."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import OMEGA_GENERIC, TEE, reference_R

import lierk

BODY = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)


def test_traced_save_times_are_checked_under_jit():
    # The check's result used to be dropped, so XLA deleted it: NaN rows, result 0.
    run = jax.jit(lambda ts: lierk.solve(BODY, lierk.DP54(), 1.0, rtol=1e-8, saveat=lierk.SaveAt(ts=ts)).R)
    with pytest.raises(Exception, match="SaveAt\\(ts=...\\) must be non-decreasing and lie in"):
        jax.block_until_ready(run(jnp.array([0.5, 2.0])))
    ok = run(jnp.array([0.5, 1.0]))
    np.testing.assert_allclose(ok[-1], reference_R(TEE, OMEGA_GENERIC, 1.0), atol=1e-6)


def test_traced_tolerances_are_checked_under_jit():
    run = jax.jit(lambda r, a: lierk.solve(BODY, lierk.DP54(), 1.0, controller=lierk.Controller(r, a)).R)
    with pytest.raises(Exception, match="rtol \\+ atol must be > 0"):
        jax.block_until_ready(run(0.0, 0.0))


@pytest.mark.parametrize(
    "rtol, atol, message",
    [
        (-1.0, 1e-8, "rtol must be >= 0 and finite"),
        (float("nan"), 1e-8, "rtol must be >= 0 and finite"),
        (1e-8, float("inf"), "atol must be >= 0 and finite"),
        (-1.0, -1.0, "rtol must be >= 0 and finite"),
        (0.0, 0.0, "rtol \\+ atol must be > 0"),
    ],
)
def test_traced_tolerances_are_checked_together_and_the_first_failure_is_named(rtol, atol, message):
    # The three tolerance checks are one run-time check (one branched error):
    # each value that fails must still be named, the first in order.
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(_FINAL(rtol, atol))
    np.testing.assert_allclose(_FINAL(1e-9, 1e-9), reference_R(TEE, OMEGA_GENERIC, 1.0), atol=1e-7)
    # One bad member of a batch is caught, by its name.
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(_FINALS(jnp.array([1e-8, rtol]), jnp.array([1e-8, atol])))


def _final(r, a):
    return lierk.solve(BODY, lierk.DP54(), 1.0, rtol=r, atol=a).R[-1]


# One program each for all the cases.
_FINAL, _FINALS = jax.jit(_final), jax.jit(jax.vmap(_final))


def test_a_step_longer_than_the_interval_is_one_shortened_step():
    # dt = 1e10 used to take zero steps and return R0 with success.
    sol = lierk.solve(lierk.FreeRigidBody(TEE, [0.0, 0.0, 0.1]), lierk.RKMK4(), 1.0, dt=1e10)
    assert int(sol.stats["num_steps"]) == 1 and float(sol.ts[-1]) == 1.0
    # A rotation about a principal axis: RKMK4 is exact for it.
    np.testing.assert_allclose(sol.R[-1], reference_R(TEE, [0.0, 0.0, 0.1], 1.0), atol=1e-14)


def test_t1_a_hair_past_a_multiple_of_dt_ends_at_t1():
    # Used to fail with "max_steps was reached" though no max_steps was given.
    t1 = 1.0000000001
    sol = lierk.solve(BODY, lierk.RKMK4(), t1, dt=0.01)
    assert int(sol.result) == 0 and float(sol.ts[-1]) == t1
    np.testing.assert_allclose(sol.R[-1], reference_R(TEE, OMEGA_GENERIC, t1), atol=1e-9)


@pytest.mark.parametrize("t1, steps", [(0.03, 5), (0.0, True)])
def test_saveat_steps_that_save_nothing_is_a_clear_error(t1, steps):
    with pytest.raises(ValueError, match="saves nothing"):
        lierk.solve(BODY, lierk.RKMK4(), t1, dt=0.01, saveat=lierk.SaveAt(steps=steps))
    # With t1 saved too it is fine.
    sol = lierk.solve(BODY, lierk.RKMK4(), t1, dt=0.01, saveat=lierk.SaveAt(steps=steps, t1=True))
    assert float(sol.ts[-1]) == t1


def test_empty_save_times_are_a_clear_error():
    with pytest.raises(ValueError, match="SaveAt\\(ts=...\\) is empty"):
        lierk.solve(BODY, lierk.DP54(), 1.0, rtol=1e-8, saveat=lierk.SaveAt(ts=np.zeros(0)))


def test_adaptive_time_stays_exact_far_from_zero():
    # The state used to advance by h while the clock advanced by fl(t + h) - t:
    # from t0 = 1e13 the error over 10 s was 15x that from t0 = 0.
    def final(t0):
        return lierk.solve(BODY, lierk.DP54(), t0 + 10.0, t0=t0, rtol=1e-6).R[-1]

    ref = reference_R(TEE, OMEGA_GENERIC, 10.0)
    e0 = float(jnp.linalg.norm(final(0.0) - ref))
    e13 = float(jnp.linalg.norm(final(1e13) - ref))
    assert e13 < 3 * e0, (e13, e0)


def test_float32_interval_below_time_resolution_is_refused():
    b32 = lierk.FreeRigidBody(TEE.astype(np.float32), OMEGA_GENERIC.astype(np.float32))
    with pytest.raises(ValueError, match="rounds to t0"):
        lierk.solve(b32, lierk.RKMK4(), 1e8 + 1, t0=1e8, dt=0.01)


def test_jacfwd_through_a_reverse_only_adjoint_says_what_to_pass():
    def final(w):
        adjoint = lierk.RecursiveCheckpointAdjoint()
        return lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.DP54(), 1.0, rtol=1e-8, adjoint=adjoint).R[-1]

    with pytest.raises(ValueError, match="leave adjoint= out"):
        jax.jacfwd(final)(jnp.asarray(OMEGA_GENERIC))


def test_traced_bad_rtol_is_named_as_rtol_and_readable_under_filter_jit():
    import equinox as eqx

    run = eqx.filter_jit(lambda r: lierk.solve(BODY, lierk.DP54(), 1.0, rtol=r, atol=1e-8).R)
    with pytest.raises(eqx.EquinoxRuntimeError, match="rtol must be >= 0 and finite"):
        jax.block_until_ready(run(jnp.asarray(-1.0)))


@pytest.mark.parametrize(
    "kw, key",
    [
        (dict(rtol=float("inf")), "rtol"),
        (dict(safety=10.0), "safety"),
        (dict(facmin=2.0), "facmin"),
        (dict(facmax=0.5), "facmax"),
        (dict(dtmin=1.0, dtmax=0.1), "dtmax"),
    ],
)
def test_controller_settings_that_cannot_converge_are_refused(kw, key):
    with pytest.raises(ValueError, match=key):
        lierk.Controller(**{"rtol": 1e-6, "atol": 1e-9, **kw})


def test_tolerance_below_rounding_is_refused():
    with pytest.raises(ValueError, match="below the rounding of float64"):
        lierk.solve(BODY, lierk.DP54(), 1.0, rtol=1e-17, atol=1e-17)
    # Given as numbers inside jit too (as a scene's pieces solve): the
    # controller's arrays are traced there, and the check was skipped.
    with pytest.raises(ValueError, match=r"rtol \+ atol = 2e-20 is below the rounding of float64"):
        jax.jit(lambda t1: lierk.solve(BODY, lierk.DP54(), t1, rtol=1e-20).R)(1.0)


@pytest.mark.parametrize("bad", [[1.0 + 1e-3j, 0.0, 0.0], [True, False, True], "abc", ["1", "2", "3"]])
def test_non_real_omega0_names_omega0(bad):
    with pytest.raises(ValueError, match="omega0 must be real numbers"):
        lierk.FreeRigidBody(TEE, bad)


def test_half_precision_inertia_is_computed_in_float32():
    p = lierk.FreeRigidBody(np.array([1.0, 2.0, 2.5], np.float16), np.array([1.0, 0.1, 0.0], np.float32))
    assert p.inertia.dtype == np.float32


def test_physically_impossible_inertia_warns():
    with pytest.warns(UserWarning, match="triangle inequality"):
        lierk.FreeRigidBody([0.5, 0.6, 1.5], [1.0, 0.0, 0.0])


def test_a_single_effect_need_not_be_a_tuple():
    a = lierk.RigidBodyWithEffects(TEE, OMEGA_GENERIC, effects=lierk.Damping(1e-6))
    b = lierk.RigidBodyWithEffects(TEE, OMEGA_GENERIC, effects=(lierk.Damping(1e-6),))
    assert len(a.effects) == 1
    np.testing.assert_array_equal(
        lierk.solve(a, lierk.RKMK4(), 1.0, dt=0.1).R, lierk.solve(b, lierk.RKMK4(), 1.0, dt=0.1).R
    )


def test_reverse_mode_gradient_does_not_depend_on_max_steps():
    # Near rounding, accept/reject decisions used to differ between the forward
    # pass and the checkpointed replay: jacrev was off by 1.4e-7 with
    # max_steps = 20000 and right with 30000.
    def final(w, **kw):
        return lierk.solve(lierk.FreeRigidBody(TEE, w), lierk.DP54(), 2.0, rtol=1e-15, **kw).R[-1]

    w = jnp.array([1.0, 0.05, 0.3])
    J_fwd = jax.jacfwd(lambda w: final(w, max_steps=20000, adjoint=lierk.ForwardMode()))(w)
    J_rev = jax.jacrev(lambda w: final(w, max_steps=20000, adjoint=lierk.RecursiveCheckpointAdjoint()))(w)
    np.testing.assert_allclose(J_rev, J_fwd, rtol=0, atol=1e-12)


@pytest.mark.parametrize("cls", [lierk.FreeRigidBody, lierk.SpatialFreeRigidBody])
def test_solution_gives_omega_and_euler_angles(cls):
    p = cls(TEE, OMEGA_GENERIC)
    sol = lierk.solve(p, lierk.RKMK4(), 1.0, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=25))
    w = np.asarray(sol.omega(p))
    assert w.shape == (5, 3)
    np.testing.assert_allclose(w[0], OMEGA_GENERIC, rtol=1e-14)
    # |L| = |I omega| is conserved.
    np.testing.assert_allclose(np.linalg.norm(w @ TEE, axis=1), np.linalg.norm(TEE @ OMEGA_GENERIC), rtol=1e-9)
    angles = sol.euler_angles("zxz")
    np.testing.assert_allclose(lierk.so3.from_euler(*np.moveaxis(np.asarray(angles), -1, 0), "zxz"), sol.R, atol=1e-12)


def test_under_resolved_run_is_reported_by_its_invariants():
    # RKMK4 at 2 rad per step: energy -57% over 1000 steps, once reported as success.
    w = OMEGA_GENERIC / np.linalg.norm(OMEGA_GENERIC)
    p = lierk.FreeRigidBody(TEE, w)
    sol = lierk.solve(p, lierk.RKMK4(), 2000.0, dt=2.0, throw=False)
    assert int(sol.result) == lierk.RESULTS.invariant_drift
    with pytest.raises(Exception, match="drifted by more than 10%"):
        jax.block_until_ready(lierk.solve(p, lierk.RKMK4(), 2000.0, dt=2.0).R)
    # Resolved, the same run is a success.
    assert int(lierk.solve(p, lierk.RKMK4(), 200.0, dt=0.1, throw=False).result) == 0
    # Under vmap each member gets its own code.
    codes = jax.vmap(
        lambda s: lierk.solve(lierk.FreeRigidBody(TEE, s * w), lierk.RKMK4(), 2000.0, dt=2.0, throw=False).result
    )(jnp.array([0.01, 1.0]))
    assert list(np.asarray(codes)) == [0, lierk.RESULTS.invariant_drift]


def test_stiff_needle_is_solved_to_its_tolerance():
    # RKF45 on I = (1e-6, 1, 1) at rtol 1e-6 once reached an error of 2.8 with success.
    I = np.array([1e-6, 1.0, 1.0])
    sol = lierk.solve(
        lierk.FreeRigidBody(I, OMEGA_GENERIC), lierk.RKF45(), 10.0, rtol=1e-6, max_steps=100000, throw=False
    )
    assert int(sol.result) == 0
    assert float(jnp.linalg.norm(sol.R[-1] - reference_R(np.diag(I), OMEGA_GENERIC, 10.0))) < 30 * 1e-6


def test_nearly_singular_inertia_warns():
    with pytest.warns(UserWarning, match="nearly singular"):
        lierk.FreeRigidBody([1e-18, 1e-3, 1e-3], [0.3, 1.0, 0.5])
    # Inside jit too, where the checked copy of a constant is staged: the
    # warning reads the argument as given.
    with pytest.warns(UserWarning, match="nearly singular"):
        jax.jit(lambda w: lierk.FreeRigidBody([1e-18, 1e-3, 1e-3], w).y0).trace(jnp.asarray([0.3, 1.0, 0.5]))


# --- Traced inputs are checked inside the program -------------------------
# Each case once came back with result 0 inside `lierk.checked_on_host`.
# Now every program checks its traced inputs itself, with no host callback
# (JAX's persistent cache keeps it) and nothing a caller can turn off.

_TOP_I = np.array([2.0, 3.0, 4.0])
_W = np.array([0.3, 1.0, 0.2])


def _fixed(dt=0.05, t1=1.0, R0=None, I=_TOP_I, effects=()):
    body = lierk.RigidBodyWithEffects(I, _W, R0=R0, effects=effects)
    return lierk.solve(body, lierk.RKMK4(), t1, dt=dt, max_steps=40, throw=False)


def _adaptive(ts):
    return lierk.solve(
        lierk.FreeRigidBody(_TOP_I, _W), lierk.DOP853(), 1.0, rtol=1e-8, saveat=lierk.SaveAt(ts=ts), throw=False
    )


_BAD_CASES = {
    "negative dt": (lambda x: _fixed(dt=x), 0.05, -0.05, lierk.RESULTS.invalid_step),
    "t1 < t0": (lambda x: _fixed(t1=x), 1.0, -1.0, lierk.RESULTS.invalid_times),
    "t1 = nan": (lambda x: _fixed(t1=x), 1.0, np.nan, lierk.RESULTS.invalid_times),
    "unsorted save times": (_adaptive, np.array([0.2, 0.5]), np.array([0.5, 0.2]), lierk.RESULTS.invalid_save_times),
    "save times past t1": (_adaptive, np.array([0.2, 0.5]), np.array([0.5, 2.0]), lierk.RESULTS.invalid_save_times),
    "R0 = 2 I": (lambda x: _fixed(R0=x), np.eye(3), 2 * np.eye(3), lierk.RESULTS.invalid_problem),
    "indefinite inertia": (lambda x: _fixed(I=x), _TOP_I, np.array([2.0, -3.0, 4.0]), lierk.RESULTS.invalid_problem),
    "negative mass": (
        lambda x: _fixed(effects=lierk.Gravity([0.0, 0.0, 0.1], x)),
        1.0,
        -1.0,
        lierk.RESULTS.invalid_problem,
    ),
    "negative damping": (lambda x: _fixed(effects=lierk.Damping(x)), 0.1, -0.1, lierk.RESULTS.invalid_problem),
    "negative spin inertia": (
        lambda x: _fixed(effects=lierk.ReactionWheels(np.eye(3), x * jnp.ones(3), np.zeros(3))),
        0.01,
        -0.01,
        lierk.RESULTS.invalid_problem,
    ),
    "unsorted torque times": (
        lambda x: _fixed(effects=lierk.TimedTorque(np.zeros((3, 3)), x)),
        np.array([0.0, 0.5, 1.0]),
        np.array([0.0, 1.0, 0.5]),
        lierk.RESULTS.invalid_problem,
    ),
}


@pytest.mark.parametrize("case", list(_BAD_CASES))
def test_a_bad_traced_input_never_comes_back_as_success(case):
    """Under jit a bad input gives its own result code and NaN states, and
    a batch with one bad member solves the others exactly as alone."""
    fn, good, bad, code = _BAD_CASES[case]
    run = jax.jit(lambda x: (lambda s: (s.result, s.R))(fn(x)))
    ok_code, ok_R = run(good)
    assert int(ok_code) == 0 and np.isfinite(np.asarray(ok_R)).all()
    bad_code, bad_R = run(bad)
    assert int(bad_code) == code and np.isnan(np.asarray(bad_R)).all(), (case, int(bad_code))
    codes, Rs = jax.jit(jax.vmap(lambda x: (lambda s: (s.result, s.R))(fn(x))))(
        jnp.stack([jnp.asarray(good), jnp.asarray(bad)])
    )
    np.testing.assert_array_equal(np.asarray(codes), [0, code])
    np.testing.assert_allclose(np.asarray(Rs[0]), np.asarray(ok_R), rtol=0, atol=1e-14)


def test_checked_on_host_is_a_deprecated_no_op_and_nothing_leaks_out_of_it():
    """A program traced inside the old block is the program traced outside:
    JAX keeps traces by function, so a block that dropped checks let an
    unchecked program run later outside it."""
    f = jax.jit(lambda dt: _fixed(dt=dt).result)
    with pytest.warns(DeprecationWarning, match="does nothing"):
        with lierk.checked_on_host():
            assert int(f(0.05)) == 0
    assert int(f(-0.05)) == lierk.RESULTS.invalid_step
    assert lierk.checks.checking_on_host() is False


def test_throw_raises_a_bad_traced_input_by_its_name():
    run = jax.jit(lambda dt: lierk.solve(BODY, lierk.RKMK4(), 1.0, dt=dt, max_steps=40).R)
    with pytest.raises(Exception, match="dt must be > 0"):
        jax.block_until_ready(run(-0.05))
    with pytest.raises(Exception, match="R0 must be a rotation matrix"):
        jax.block_until_ready(
            jax.jit(
                lambda R0: lierk.solve(lierk.FreeRigidBody(TEE, OMEGA_GENERIC, R0=R0), lierk.RKMK4(), 1.0, dt=0.05).R
            )(2 * jnp.eye(3))
        )


def test_a_float32_refusal_says_how_to_get_float64():
    b32 = lierk.FreeRigidBody(TEE.astype(np.float32), OMEGA_GENERIC.astype(np.float32))
    with pytest.raises(ValueError, match='below the rounding of float32.*jax_enable_x64", True'):
        lierk.solve(b32, lierk.DOP853(), 1.0, rtol=1e-9, atol=1e-9)
    # Not for float64, whose refusal has no other type to point to.
    with pytest.raises(ValueError) as e:
        lierk.solve(BODY, lierk.DOP853(), 1.0, rtol=1e-17, atol=1e-17)
    assert "jax_enable_x64" not in str(e.value)
