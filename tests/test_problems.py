"""The problem layer: one rigid-body interface (`lierk.AbstractRigidBody`)
that every rigid body implements once, and the tools that read it."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import OMEGA_GENERIC, TEE

import lierk
import lierk.app.accuracy
import lierk.app.scene

W = np.array([0.3, 1.0, 0.2])


class _Field(lierk.AbstractProblem):
    """A field that is not a rigid body: a constant spin."""

    R0: jax.Array
    y0: None = None

    def field(self, t, R, y):
        return jnp.array([0.0, 0.0, 1.0], R.dtype), None


def _bodies():
    gravity = lierk.Gravity([0.0, 0.1, 0.3], 1.0)
    return {
        "free": (lierk.FreeRigidBody(TEE, W), True),
        "spatial": (lierk.SpatialFreeRigidBody(TEE, W), True),
        "no effects": (lierk.RigidBodyWithEffects(TEE, W, effects=()), True),
        "gravity": (lierk.RigidBodyWithEffects(TEE, W, effects=(gravity,)), False),
        "damping": (lierk.RigidBodyWithEffects(TEE, W, effects=(lierk.Damping(1e-6),)), False),
        "not a rigid body": (_Field(jnp.eye(3)), False),
    }


@pytest.mark.parametrize("name", list(_bodies()))
def test_torque_free_says_whether_the_closed_form_applies(name):
    problem, expected = _bodies()[name]
    assert problem.torque_free is expected
    if expected:
        # Then lierk.exact is the solution: a solve agrees with it.
        sol = lierk.solve(problem, lierk.DOP853(), 1.0, rtol=1e-12)
        R_exact = lierk.exact.free_rigid_body(problem.inertia, problem.omega0, 1.0, problem.R0)[0]
        assert np.linalg.norm(np.asarray(sol.R[-1]) - np.asarray(R_exact)) < 1e-10


def test_both_free_bodies_share_one_rigid_body_interface():
    """The momentum state and the report's spatial form differ only in where
    the momentum lives: omega0, with_omega0, drift and the invariants agree."""
    free, spatial = lierk.FreeRigidBody(TEE, W), lierk.SpatialFreeRigidBody(TEE, W)
    for p in (free, spatial):
        assert isinstance(p, lierk.AbstractRigidBody)
        np.testing.assert_allclose(p.omega0, W, rtol=1e-14)
        np.testing.assert_allclose(p.with_omega0(OMEGA_GENERIC).omega0, OMEGA_GENERIC, rtol=1e-14)
        assert p.kick_reads_momentum == () and not p.closed_form_drift
    R = lierk.so3.exp(jnp.array([0.2, -0.4, 0.7]))
    m = R.T @ spatial.L
    (Rf, mf), (Rs, ys) = free.drift(R, m, 0.3), spatial.drift(R, None, 0.3)
    np.testing.assert_allclose(Rf, Rs, atol=1e-15)
    assert ys is None and spatial.kick(0.0, R, None, 0.3) is None
    np.testing.assert_allclose(mf, Rf.T @ spatial.L, rtol=1e-13)
    qf, qs = free.invariants(R, m), spatial.invariants(R, None)
    assert set(qf) == set(qs) == {"energy", "|L|"}
    for k in qf:
        np.testing.assert_allclose(qf[k], qs[k], rtol=1e-15)


def test_splittings_refuse_a_problem_that_is_not_a_rigid_body():
    with pytest.raises(ValueError, match="needs a rigid body with `drift`"):
        lierk.solve(_Field(jnp.eye(3)), lierk.Strang(), 1.0, dt=0.1)


def test_accuracy_uses_the_closed_form_for_the_reports_spatial_body():
    """It asked for `effects == ()`, which the spatial body did not have, and
    paid for a numerical reference (DOP853 checked by DP54)."""
    scene = lierk.app.scene.from_dict(
        {
            "body": {"kind": "tensor", "inertia": TEE.diagonal().tolist()},
            "initial": {"omega": W.tolist()},
            "run": {"solver": "RKMK4", "t1": 1.0, "dt": 0.1},
        }
    )
    spatial = dataclasses.replace(scene, problem=lierk.SpatialFreeRigidBody(TEE, W))
    report = lierk.app.accuracy.work_precision(spatial, ["RKMK4"], {"RKMK4": [0.05]}, n_times=3, repeats=1)
    assert report.reference.startswith("lierk.exact") and report.check is None
    assert report.rows[0].ok and report.rows[0].error < 1e-3


def test_restart_checks_the_attitude_as_the_constructor_does():
    """`restart` took any array as the attitude: ``2 R`` solved with result 0
    to ``||R^T R - I|| = 5.2``, and a trajectory of attitudes gave ``R`` of
    shape ``(1, 5, 3, 3)``."""
    body = lierk.FreeRigidBody(TEE, W)
    R = np.asarray(lierk.so3.exp(jnp.array([0.2, -0.4, 0.7])))
    m = np.asarray(body.y0)
    bad = {
        "twice": (2 * R, "rotation matrix"),
        "reflected": (-R, "rotation matrix"),
        "trajectory": (np.stack([R] * 5), r"shape \(3, 3\), got shape \(5, 3, 3\)"),
        "NaN": (np.where(np.eye(3) > 0, np.nan, R), "NaN"),
    }
    for name, (R_bad, match) in bad.items():
        with pytest.raises(ValueError, match=match):
            lierk.FreeRigidBody(TEE, W, R0=R_bad)
        with pytest.raises(ValueError, match=match):
            body.restart(R_bad, m)
    restarted = body.restart(R, m)
    np.testing.assert_array_equal(np.asarray(restarted.R0), R)
    np.testing.assert_array_equal(np.asarray(restarted.y0), m)
    # Traced, it is checked inside the program, as a traced R0 is: a solve
    # from it ends with invalid_problem and NaN states.
    run = jax.jit(
        lambda R: (lambda s: (s.result, s.R))(lierk.solve(body.restart(R, m), lierk.RKMK4(), 0.1, dt=0.05, throw=False))
    )
    code, R1 = run(R)
    assert int(code) == 0 and np.isfinite(np.asarray(R1)).all()
    code, R1 = run(2 * R)
    assert int(code) == lierk.RESULTS.invalid_problem and np.isnan(np.asarray(R1)).all()


def test_restart_refuses_a_state_of_another_structure_by_name():
    """A state unlike the problem's failed inside the solve with JAX's errors
    ("add got incompatible shapes", "scan body function carry input and
    carry output must have equal types")."""
    body = lierk.FreeRigidBody(TEE, W)
    R, m = np.eye(3), np.asarray(body.y0)
    cases = {
        "a trajectory": (np.stack([m] * 5), r"y0 has shape \(5, 3\).*a saved trajectory"),
        "float32": (m.astype(np.float32), "y0 is float32.*float64"),
        "a pair": ((m, m), r"y0 must have the structure of the problem's state, float64\[3\]"),
        "two numbers": ([1.0, 2.0], r"y0 has shape \(2,\)"),
    }
    for name, (y, match) in cases.items():
        with pytest.raises(ValueError, match=match):
            body.restart(R, y)
    # Numbers in a list are converted; the spatial body has no state besides R.
    np.testing.assert_array_equal(np.asarray(body.restart(R, m.tolist()).y0), m)
    spatial = lierk.SpatialFreeRigidBody(TEE, W)
    assert spatial.restart(R, None).y0 is None
    with pytest.raises(ValueError, match="no state besides R"):
        spatial.restart(R, m)
