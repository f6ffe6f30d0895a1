"""Property-based checks (hypothesis): generated bodies, states, tolerances and
scenes, valid and invalid.

- Valid input gives a finite result with success, or an explicit result code.
- Never NaN together with success.
- Invalid input raises a `ValueError` that names the offending key.

Solves are jitted once per solver with every value traced, so the examples
cost a run each, not a compilation.
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lierk
import lierk.app.scene

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
T = 2.0

moments = st.tuples(*[st.floats(-3.0, 3.0)] * 3).map(lambda e: 10.0 ** np.array(e))
vectors = st.tuples(*[st.floats(-5.0, 5.0)] * 3).map(np.array)
rotvecs = st.tuples(*[st.floats(-3.0, 3.0)] * 3).map(np.array)


def _physical(I):
    # Keep to moments a rigid body can have (the triangle inequality) so the
    # examples do not trip the warning for impossible bodies.
    return I.max() <= I.sum() - I.max()


@jax.jit
def _adaptive(I, w, rv, rtol):
    R0 = lierk.so3.exp(rv)
    sol = lierk.solve(lierk.FreeRigidBody(I, w, R0), lierk.DP54(), T, rtol=rtol, max_steps=20000, throw=False)
    return sol.R[-1], sol.result


@jax.jit
def _fixed(I, w, rv, dt):
    R0 = lierk.so3.exp(rv)
    sol = lierk.solve(lierk.FreeRigidBody(I, w, R0), lierk.RKMK4(), T, dt=dt, max_steps=400, throw=False)
    return sol.R[-1], sol.result


def _never_nan_with_success(R, code):
    R, code = np.asarray(R), int(code)
    assert code in lierk.RESULTS.messages
    if code == lierk.RESULTS.successful:
        assert np.all(np.isfinite(R))
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-9
    return code


@SETTINGS
@given(moments.filter(_physical), vectors, rotvecs, st.floats(-10.0, -4.0))
def test_valid_adaptive_solves_succeed_or_say_why(I, w, rv, log_rtol):
    R, code = _adaptive(I, w, rv, 10.0**log_rtol)
    _never_nan_with_success(R, code)


@SETTINGS
@given(moments.filter(_physical), vectors, rotvecs, st.floats(0.005, 0.05))
def test_valid_fixed_solves_succeed_or_say_why(I, w, rv, dt):
    R, code = _fixed(I, w, rv, dt)
    code = _never_nan_with_success(R, code)
    # At |omega| dt <= 0.25 rad the run is resolved: no drift code.
    if np.linalg.norm(w) * dt <= 0.25:
        assert code == lierk.RESULTS.successful


bad_numbers = st.sampled_from([float("nan"), float("inf"), -float("inf")])


@SETTINGS
@given(st.integers(0, 2), bad_numbers)
def test_non_finite_omega0_names_omega0(i, bad):
    w = np.array([1.0, 0.1, 0.2])
    w[i] = bad
    with pytest.raises(ValueError, match="omega0"):
        lierk.FreeRigidBody([1.0, 2.0, 2.5], w)


@SETTINGS
@given(st.integers(0, 2), st.one_of(bad_numbers, st.floats(-10.0, 0.0)))
def test_bad_inertia_names_inertia(i, bad):
    I = np.array([1.0, 2.0, 2.5])
    I[i] = bad
    with pytest.raises(ValueError, match="inertia"):
        lierk.FreeRigidBody(I, [1.0, 0.0, 0.0])


@SETTINGS
@given(
    st.sampled_from(["dt", "rtol", "atol", "t1", "t0", "target_error", "dt0"]),
    st.one_of(bad_numbers, st.floats(-1e3, -1e-12)),
)
def test_bad_solve_values_name_their_key(key, bad):
    body = lierk.FreeRigidBody([1.0, 2.0, 2.5], [1.0, 0.1, 0.0])
    kw = {
        "dt": dict(dt=bad),
        "rtol": dict(rtol=bad),
        "atol": dict(rtol=1e-6, atol=bad),
        "t1": dict(dt=0.1),
        "t0": dict(dt=0.1, t0=bad),
        "target_error": dict(target_error=bad),
        "dt0": dict(rtol=1e-6, dt0=bad),
    }[key]
    solver = lierk.RKMK4() if "dt" in kw or "target_error" in kw else lierk.DP54()
    t1 = bad if key == "t1" else 1.0
    if key == "t0" and bad < 0 and math.isfinite(bad):
        return  # a negative t0 is fine
    with pytest.raises(ValueError, match=key):
        lierk.solve(body, solver, t1, **kw)


scene_values = st.fixed_dictionaries(
    {
        "mass": st.floats(0.1, 10.0),
        "lx": st.floats(0.01, 1.0),
        "ly": st.floats(0.01, 1.0),
        "lz": st.floats(0.01, 1.0),
        "omega": vectors.map(list),
        "dt": st.floats(1e-3, 1e-2),
    }
)


def _scene(v):
    return {
        "body": {"kind": "box", "mass": v["mass"], "lx": v["lx"], "ly": v["ly"], "lz": v["lz"]},
        "initial": {"omega": v["omega"]},
        "run": {"solver": "RKMK4", "t1": 0.05, "dt": v["dt"]},
    }


@SETTINGS
@given(scene_values)
def test_valid_scenes_solve(v):
    sol = lierk.app.scene.from_dict(_scene(v)).solve(throw=False)
    _never_nan_with_success(sol.R[-1], sol.result)


@SETTINGS
@given(
    scene_values,
    st.sampled_from([("body", "mass"), ("body", "lx"), ("run", "dt"), ("run", "t1"), ("initial", "omega")]),
    st.one_of(bad_numbers, st.just(-1.0), st.just("a string"), st.just([1.0, 2.0])),
)
def test_invalid_scenes_name_the_key(v, where, bad):
    d = _scene(v)
    table, key = where
    if key == "omega" and isinstance(bad, list):
        bad = [1.0, 2.0]  # wrong length
    d[table][key] = bad
    with pytest.raises(ValueError, match=f"{table}.{key}|{key}"):
        lierk.app.scene.from_dict(d)
