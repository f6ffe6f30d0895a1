"""`lierk.app.simulation`: what ``lierk simulate`` saves and prints, from Python."""

from __future__ import annotations

import dataclasses
import re
import warnings

import jax
import numpy as np
import pytest

import lierk
from lierk.app import scene as S
from lierk.app.diagnostics import diagnostics
from lierk.app.simulation import Simulation, simulate

RUN = {"solver": "RKMK4", "t1": 0.5, "dt": 0.01, "save_every": 5}


def _scene(effects=(), omega=(1.0, 0.05, 0.3), **run):
    return S.from_dict(
        {
            "name": "tee |L| test",
            "description": "a T-handle",
            "body": {"kind": "tee_handle"},
            "initial": {"omega": list(omega)},
            "effects": list(effects),
            "run": {**RUN, **run},
        }
    )


def test_record_holds_the_solve_and_its_diagnostics():
    scene = _scene()
    sim = simulate(scene)
    sol, problem = sim.solution, scene.problem
    assert sim.wall > 0 and isinstance(sim, Simulation)
    # One plain solve gives the same numbers.
    plain = scene.solve()
    np.testing.assert_array_equal(np.asarray(sol.R), np.asarray(plain.R))
    record = sim.record()
    assert set(record) == {
        "ts",
        "R",
        "quaternion",
        "omega",
        "L",
        "inertia",
        "omega0",
        "R0",
        "t1",
        "solver",
        "scene",
        "y",
        "invariant_energy",
        "invariant_abs_L",
        "event_flip",
    }
    # The flip event of an asymmetric body (none in 0.5 s).
    assert [name for name, _ in sim.scene.events] == ["flip"] and record["event_flip"].shape == (0,)
    # The quaternions are those of R (against SciPy, w >= 0).
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(
        record["quaternion"], Rotation.from_matrix(record["R"]).as_quat(canonical=True, scalar_first=True), atol=1e-14
    )
    np.testing.assert_array_equal(record["ts"], np.asarray(sol.ts))
    np.testing.assert_array_equal(record["R"], np.asarray(sol.R))
    np.testing.assert_array_equal(record["y"], np.asarray(sol.y))
    d = diagnostics(problem, sol)
    np.testing.assert_array_equal(record["omega"], d.omega)
    np.testing.assert_array_equal(record["L"], d.L)
    np.testing.assert_array_equal(record["invariant_abs_L"], d.invariants["|L|"])
    np.testing.assert_array_equal(record["inertia"], np.asarray(problem.inertia))
    np.testing.assert_array_equal(record["omega0"], [1.0, 0.05, 0.3])
    assert record["R"].shape == (11, 3, 3) and float(record["t1"]) == 0.5
    assert str(record["solver"]) == "RKMK4" and str(record["scene"]) == "tee |L| test"
    np.testing.assert_array_equal(record["R0"], np.eye(3))


def test_summary_reports_steps_drifts_and_the_flip_interval():
    sim = simulate(_scene())
    lines = sim.summary().splitlines()
    assert lines[0] == "scene tee |L| test: a T-handle"
    # 4 stages a step; the flip event reads its condition at each step's end
    # and, never crossing in 0.5 s, builds no interpolant: 50 x 4.
    assert re.fullmatch(
        r"RKMK4, dt = 0\.01 s, t1 = 0\.5 s: 50 steps, 200 field evaluations, [\d.]+ s wall "
        r"\(incl\. compilation\)",
        lines[1],
    ), lines[1]
    d = sim.diagnostics
    assert lines[2:4] == [
        f"  max relative change of energy: {d.drift['energy']:.2e}",
        f"  max relative change of |L|: {d.drift['|L|']:.2e}",
    ]
    assert lines[4] == f"  max ||R^T R - I||: {d.orthogonality:.2e}"
    tau = float(lierk.exact.flip_interval(sim.scene.problem.inertia, [1.0, 0.05, 0.3]))
    assert sim.flip_interval == tau and lines[5] == f"  intermediate-axis flip interval (exact): {tau:.3f} s"
    assert lines[6] == "  event flip: none" and len(lines) == 7
    # Spin about the largest axis: it never flips.
    stable = simulate(_scene(omega=(0.05, 0.0, 1.0)))
    assert stable.flip_interval == np.inf
    assert stable.summary().splitlines()[-2] == (
        "  no flip of the intermediate axis (exact solution: lierk.exact.flip_interval is inf)"
    )
    # Long enough to flip (the report's case a): the flip event's times.
    flips = simulate(_scene(omega=(1.0, 0.05, 0.0), t1=40.0, save_every=100))
    times = flips.event_times["flip"]
    assert flips.summary().splitlines()[-1] == f"  event flip: 2 at t = {times[0]:.6g}, {times[1]:.6g} s"
    assert abs(times[1] - times[0] - 23.6307) < 1e-3


def test_summary_with_effects_and_with_a_target_error():
    damped = simulate(_scene(effects=[{"kind": "damping", "c": 1e-5}]))
    assert damped.flip_interval is None
    lines = damped.summary().splitlines()
    assert lines[2].startswith("  max relative change of energy: ") and lines[2].endswith(
        "  (not conserved by this scene)"
    )
    # No exact flip interval for a body with effects; the flip event's line.
    assert lines[-2].startswith("  max ||R^T R - I||: ") and lines[-1] == "  event flip: none"
    scene = _scene().with_target_error(1e-6)
    sim = simulate(scene)
    record = sim.record()
    est = np.asarray(sim.solution.error_estimate)
    np.testing.assert_array_equal(record["error_estimate"], est[: len(record["ts"])])
    lines = sim.summary().splitlines()
    assert lines[1].startswith(f"RKMK4, target_error = 1e-06 (chose {sim.solution.chosen_setting()}), t1 = 0.5 s: ")
    # The flip is among its events: found by one more solve at the chosen setting.
    assert lines[2] == (
        f"  target_error 1e-06: chose {sim.solution.chosen_setting()} after "
        f"{sim.solution.stats['num_solves']} solves (steps above: the last, finest solve, "
        "events found by one more solve at that setting); "
        f"estimated error at t1 {est[-1]:.2e}, max over saved times {est.max():.2e}"
    )
    assert est.max() <= 1e-6 and lines[-1] == "  event flip: none"


def test_simulate_in_pieces_saves_what_one_solve_saves():
    scene = _scene()
    whole, pieces = simulate(scene), simulate(scene, n_pieces=3)
    a, b = whole.record(), pieces.record()
    assert a.keys() == b.keys() and str(b["scene"]) == str(a["scene"])
    for k, v in a.items():
        if v.dtype.kind == "f":
            np.testing.assert_allclose(b[k], v, rtol=1e-13, atol=1e-15, err_msg=k)
    with pytest.raises(ValueError, match="n_pieces must be a positive int"):
        simulate(scene, n_pieces=0)


def test_a_save_interval_longer_than_the_run_saves_its_ends_in_pieces():
    """dt = 0.01, t1 = 1 and save_every = 10^9: each piece took max_steps =
    save_every, and ran its padding: ``lierk simulate`` and
    ``Scene.solve(n_pieces=...)`` spun at full CPU after compiling.  The
    start and the end, as one solve saves them."""
    scene = _scene(t1=1.0, save_every=10**9)
    whole, pieces = simulate(scene), simulate(scene, n_pieces=4)
    a, b = whole.record(), pieces.record()
    np.testing.assert_array_equal(b["ts"], [0.0, 1.0])
    np.testing.assert_array_equal(b["ts"], a["ts"])
    np.testing.assert_allclose(b["R"], a["R"], rtol=0, atol=1e-13)
    assert pieces.solution.stats["num_steps"] == int(whole.solution.stats["num_steps"]) == 100
    plain = scene.solve(n_pieces=3)
    np.testing.assert_allclose(np.asarray(plain.R), a["R"], rtol=0, atol=1e-13)


@pytest.mark.parametrize("solver, tracked", [("ExplicitEuler", False), ("LieEuler", True), ("NaiveLieRK4", True)])
def test_flips_are_tracked_where_the_solver_can_locate_events(solver, tracked):
    """The T-handle is asymmetric, so the flip event is added; ExplicitEuler
    cannot locate events (it leaves SO(3)) and used to end the run with
    "dense output and events need a Lie-group solver"."""
    sim = simulate(_scene(solver=solver, t1=0.1, save_every=1))
    assert int(sim.solution.result) == 0
    assert ([name for name, _ in sim.scene.events] == ["flip"]) == tracked
    assert ("event_flip" in sim.record()) == tracked
    lines = sim.summary().splitlines()
    if tracked:
        assert sim.flips_untracked is None and lines[-1] == "  event flip: none"
        assert not any("not tracked" in line for line in lines)
    else:
        assert sim.flips_untracked.startswith("ExplicitEuler leaves SO(3), so its steps have no interpolant")
        assert lines[-1] == f"  flips not tracked with ExplicitEuler: {sim.flips_untracked}"
        # The same steps as the scene solved as it is.
        plain = _scene(solver=solver, t1=0.1, save_every=1).solve()
        np.testing.assert_array_equal(np.asarray(sim.solution.R), np.asarray(plain.R))


def test_events_the_scene_asks_for_still_need_a_solver_that_locates_them():
    scene = S.from_dict(
        {
            "body": {"kind": "tee_handle"},
            "initial": {"omega": [1.0, 0.05, 0.3]},
            "events": [{"kind": "tilt", "angle": 0.5}],
            "run": {**RUN, "solver": "ExplicitEuler"},
        }
    )
    with pytest.raises(ValueError, match="dense output and events need a Lie-group solver"):
        simulate(scene)


def test_an_impossible_body_warns_once_from_loading_to_the_report():
    """lierk simulate printed the triangle-inequality warning three times:
    the tensor check, the problem and the report's exact flip interval."""
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        scene = S.from_dict(
            {"body": {"kind": "tensor", "inertia": [0.5, 0.6, 1.5]}, "initial": {"omega": [1.0, 0.05, 0.3]}, "run": RUN}
        )
        sim = simulate(scene)
        sim.summary()
    assert [str(w.message).split(" breaks")[0] for w in shown] == ["body.inertia [0.5, 0.6, 1.5]"]


def test_an_invariant_that_is_not_finite_is_said_so():
    """A state that overflowed at a saved point (a |L| of inf) gave six NumPy
    warnings and "|L|: nan"; now the drift is nan, said so in the report."""
    import equinox as eqx

    sim = simulate(_scene(t1=0.05))
    y = np.array(sim.solution.y)
    y[-1] = [np.inf, 0.0, 0.0]
    sol = eqx.tree_at(lambda s: s.y, sim.solution, jax.numpy.asarray(y))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = diagnostics(sim.scene.problem, sol)
    assert np.isnan(d.drift["|L|"]) and np.isnan(d.drift["energy"])
    lines = dataclasses.replace(sim, diagnostics=d).summary().splitlines()
    assert "  max relative change of |L|: not finite (|L| is inf or nan at a saved time)" in lines
