"""Scenes from TOML: the example files load and give physically sensible runs,
a scene without effects is exactly the free rigid body, and bad files fail
with messages that name the key."""

from __future__ import annotations

import copy
import dataclasses
import pathlib
import warnings

import jax
import numpy as np
import pytest
from helpers import reference_R

import lierk
from lierk import Damping, Gravity, RigidBodyWithEffects
from lierk.app import scene as S

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"
TEE = np.diag([9.82271303e-05, 7.22671030e-05, 1.57865031e-04])


def short(scene, t1):
    return dataclasses.replace(scene, t1=t1)


@pytest.mark.parametrize("letter, omega0", [("a", [1.0, 0.05, 0.0]), ("b", [0.0, 1.0, 0.05]), ("c", [0.05, 0.0, 1.0])])
def test_tee_handle_examples(letter, omega0):
    scene = S.load(EXAMPLES / f"tee_handle_{letter}.toml")
    assert scene.name == f"tee_handle_{letter}"
    assert type(scene.problem) is lierk.FreeRigidBody and scene.effects == ()
    assert isinstance(scene.solver, lierk.RKMK4) and scene.solve_kwargs == {"dt": 0.01} and scene.t1 == 100.0
    # The report's inertia, built from the file's geometry and density.
    np.testing.assert_allclose(scene.problem.inertia, TEE, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(scene.problem.omega0, omega0, rtol=1e-12)
    np.testing.assert_allclose(scene.fixed_point, [0.01, 0.0, 0.0], atol=1e-15)
    sol = short(scene, 2.0).solve()
    assert sol.R.shape == (21, 3, 3)  # t = 0 and every 10th of 200 steps
    np.testing.assert_allclose(np.asarray(sol.ts)[[0, -1]], [0.0, 2.0])
    assert (
        np.abs(np.asarray(sol.R[-1]) - reference_R(TEE, omega0, 2.0)).max() < 1.5e-9
    )  # RKMK4 h=0.01: measured 1.7e-11 (a) to 1.5e-10 (c)


def test_sphere_example_turns_uniformly():
    scene = S.load(EXAMPLES / "sphere.toml")
    assert type(scene.problem) is lierk.FreeRigidBody
    np.testing.assert_allclose(scene.problem.inertia, 0.4 * 1.0 * 0.1**2 * np.eye(3), rtol=1e-14)
    sol = short(scene, 1.0).solve()
    omega0 = np.array([1.0, 2.0, 3.0])
    exact = np.asarray(lierk.so3.exp(np.asarray(sol.ts)[:, None] * omega0))
    assert np.abs(np.asarray(sol.R) - exact).max() < 1e-12


def test_heavy_top_example_precesses_and_nutates():
    scene = S.load(EXAMPLES / "heavy_top.toml")
    p = scene.problem
    assert isinstance(p, RigidBodyWithEffects) and [type(e) for e in scene.effects] == [Gravity]
    # The pivot is the tip (body origin); the inertia is moved there.
    M, com = scene.mass, scene.center_of_mass
    np.testing.assert_allclose(scene.fixed_point, 0.0, atol=1e-15)
    np.testing.assert_allclose(scene.effects[0].pivot_to_com, com)
    I_cm = lierk.inertia.composite(scene.body_parts).inertia
    np.testing.assert_allclose(p.inertia, np.asarray(I_cm) + M * com[2] ** 2 * np.diag([1.0, 1.0, 0.0]), rtol=1e-12)
    assert set(p.conserved()) == {"energy", "L_vertical", "m_chi"}
    sol = short(scene, 0.5).solve()
    R, m = np.asarray(sol.R), np.asarray(sol.y)
    inv = p.invariants(R, m)
    E = np.asarray(inv["energy"])
    # RKMK4 at omega3 h = 0.15 (measured over 0.5 s: energy 9.3e-8, L_vertical 1.5e-6).
    assert np.ptp(E) / E[0] < 5e-7
    assert np.ptp(np.asarray(inv["L_vertical"])) / abs(float(inv["L_vertical"][0])) < 1e-5
    assert np.ptp(np.asarray(inv["m_chi"])) < 1e-12
    axis = R[:, :, 2]  # the symmetry axis in space
    tilt = np.arccos(axis[:, 2])
    assert tilt[0] == pytest.approx(0.3) and 0.1 < np.ptp(tilt) < 0.4  # nutation, about 0.2 rad
    azimuth = np.unwrap(np.arctan2(axis[:, 1], axis[:, 0]))
    # Precession at roughly M g l / (I3 omega3).
    rate = (azimuth[-1] - azimuth[0]) / 0.5
    slow = M * 9.81 * com[2] / (p.inertia[2, 2] * 150.0)
    assert 0.5 * slow < rate < 2.0 * slow


def test_damped_satellite_example_loses_energy_as_predicted():
    scene = S.load(EXAMPLES / "damped_satellite.toml")
    p = scene.problem
    assert [type(e) for e in scene.effects] == [Damping] and "energy" not in p.conserved()
    sol = dataclasses.replace(short(scene, 10.0), saveat_every=1).solve()
    ts, R, m = np.asarray(sol.ts), np.asarray(sol.R), np.asarray(sol.y)
    E = np.asarray(p.invariants(R, m)["energy"])
    assert np.all(np.diff(E) < 0)
    w2 = np.sum(np.einsum("ij,nj->ni", np.asarray(p.inertia_inv), m) ** 2, axis=1)
    dissipated = 5.0 * np.concatenate([[0.0], np.cumsum(0.5 * (w2[1:] + w2[:-1]) * np.diff(ts))])
    assert np.abs(E - E[0] + dissipated).max() / (E[0] - E[-1]) < 2e-5  # trapezoid at h = 0.05: measured 2.2e-6


def test_no_effect_scene_is_the_free_body_with_the_same_jaxpr():
    scene = S.load(EXAMPLES / "tee_handle_a.toml")
    assert type(scene.problem) is lierk.FreeRigidBody and scene.problem.effects == ()
    direct = lierk.FreeRigidBody(lierk.inertia.tee_handle(), [1.0, 0.05, 0.0])

    def program(problem):
        def run(p):
            return lierk.solve(p, scene.solver, 1.0, dt=0.01, max_steps=100, saveat=scene.saveat()).R

        return str(jax.make_jaxpr(run)(problem))

    assert program(scene.problem) == program(direct)
    # A scene with an effect is a different program (the comparison can fail).
    damped = S.from_dict(_tee(effects=[{"kind": "damping", "c": 0.1}]))
    assert program(damped.problem) != program(direct)


def _tee(**changes):
    d = {
        "body": {"kind": "tee_handle"},
        "initial": {"omega": [1.0, 0.05, 0.0]},
        "run": {"solver": "RKMK4", "dt": 0.01, "t1": 1.0},
    }
    for k, v in changes.items():
        if isinstance(v, dict) and k in d:
            d[k] = {**d[k], **v}
        else:
            d[k] = v
    return d


def test_attitude_forms_agree():
    phi, theta, psi = 0.3, -0.5, 1.2
    R = np.asarray(lierk.so3.from_euler(phi, theta, psi))
    q = np.asarray(lierk.so3.to_quaternion(R))
    forms = [{"euler": [phi, theta, psi]}, {"matrix": R.tolist()}, {"quaternion": q.tolist()}]
    for f in forms:
        R0 = S.from_dict(_tee(initial={"omega": [1.0, 0.0, 0.0], **f})).problem.R0
        np.testing.assert_allclose(R0, R, atol=1e-14)
    np.testing.assert_array_equal(
        S.from_dict(_tee(initial={"omega": [1.0, 0, 0], "attitude": "identity"})).problem.R0, np.eye(3)
    )


def test_composite_rotated_part_and_tensor_gravity():
    # A box rotated by 90 degrees about z has its x and y edges swapped.
    part = {
        "kind": "box",
        "mass": 2.0,
        "lx": 1.0,
        "ly": 2.0,
        "lz": 3.0,
        "euler": [np.pi / 2, 0.0, 0.0],
        "offset": [0.1, 0, 0],
    }
    sc = S.from_dict(_tee(body={"kind": "composite", "parts": [part]}))
    np.testing.assert_allclose(sc.problem.inertia, lierk.inertia.box(2.0, 2.0, 1.0, 3.0), atol=1e-14)
    np.testing.assert_allclose(sc.center_of_mass, [0.1, 0, 0])
    # Simo-Wong's top from a tensor about the centre: diag(4, 4, 1) + M l^2 = diag(5, 5, 1).
    top = S.from_dict(
        {
            "body": {"kind": "tensor", "inertia": [4.0, 4.0, 1.0], "mass": 1.0},
            "initial": {"omega": [0.0, 0.0, 50.0], "euler": [0.0, 0.3, 0.0]},
            "effects": [{"kind": "gravity", "pivot_to_com": [0.0, 0.0, 1.0], "g": 20.0}],
            "run": {"solver": "DP54", "rtol": 1e-10, "t1": 1.0, "n_save": 11},
        }
    )
    np.testing.assert_allclose(top.problem.inertia, np.diag([5.0, 5.0, 1.0]))
    assert top.body_parts is None and top.solve_kwargs == {"rtol": 1e-10, "atol": 1e-10}
    sol = top.solve()
    np.testing.assert_allclose(sol.ts, np.linspace(0.0, 1.0, 11))
    E = np.asarray(top.problem.invariants(sol.R, sol.y)["energy"])
    assert np.ptp(E) / E[0] < 5e-11  # interpolated outputs: measured 4.8e-12


def _mutate(path, value):
    """``_tee()`` with the entry at ``path`` (keys and indices) set to ``value``,
    or removed when ``value`` is ``DELETE``."""
    d = _tee(effects=[{"kind": "damping", "c": 0.1}])
    d["body"] = {"kind": "composite", "parts": [{"kind": "sphere", "mass": 1.0, "radius": 0.1}]}
    d = copy.deepcopy(d)
    node = d
    for k in path[:-1]:
        node = node[k]
    if value is DELETE:
        del node[path[-1]]
    elif isinstance(node, list) and path[-1] == len(node):
        node.append(value)
    else:
        node[path[-1]] = value
    return d


DELETE = object()
BAD = [
    (("colour",), "red", "unknown key 'colour'"),
    (("body", "kind"), "cube", "body.kind = 'cube' is not allowed; choose one of: 'tee_handle', 'box'"),
    (("body", "parts", 0, "colour"), "red", r"body.parts\[0\]: unknown key 'colour'"),
    (("body", "parts", 0, "mass"), -1.0, r"body.parts\[0\].mass must be > 0, got -1.0"),
    (("body", "parts", 0, "radius"), 0.0, r"body.parts\[0\].radius must be > 0"),
    (("body", "parts", 0, "radius"), DELETE, r"body.parts\[0\]: missing required key 'radius'"),
    (
        ("body", "parts", 0, "matrix"),
        [[1, 0, 0], [0, 1, 0], [0, 0, -1]],
        r"body.parts\[0\].matrix: R0 must be a rotation",
    ),
    (("initial", "omega"), DELETE, "initial: missing required key 'omega'"),
    (("initial", "omega"), [1.0, 2.0], r"initial.omega must be a list of 3 numbers"),
    (("initial", "spin"), 1.0, "initial: unknown key 'spin'"),
    (("initial", "attitude"), "upright", "initial.attitude = 'upright' is not allowed; choose one of: 'identity'"),
    (("initial", "matrix"), [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "initial.matrix: R0 must be a rotation matrix"),
    (("initial", "quaternion"), [0, 0, 0, 0], "initial.quaternion must be a nonzero quaternion"),
    (
        ("effects", 0, "kind"),
        "magnetism",
        r"effects\[0\].kind = 'magnetism' is not allowed; did you mean 'magnetic'\?; choose one of: 'gravity'",
    ),
    (("effects", 0, "k"), 1.0, r"effects\[0\]: unknown key 'k'"),
    (("effects", 0, "c"), DELETE, r"effects\[0\]: missing required key 'c'"),
    (("effects", 0, "c"), -0.1, r"effects\[0\].c must be >= 0"),
    (("effects", 1), {"kind": "damping", "c": 1.0}, r"effects\[1\].kind = 'damping' appears twice"),
    (("effects", 0), {"kind": "gravity", "mass": 1.0}, "exactly one of 'pivot_to_com' or 'pivot'"),
    (("effects", 0), {"kind": "gravity", "pivot": [0, 0, 0], "mass": -2.0}, r"effects\[0\].mass must be > 0"),
    (("run", "solver"), "RK45", "run.solver = 'RK45' is not allowed; choose one of: ExplicitEuler"),
    (("run", "t1"), DELETE, "run: missing required key 't1'"),
    (("run", "t1"), "ten", "run.t1 must be a finite number, got 'ten'"),
    (("run", "dt"), -0.01, "run.dt must be > 0"),
    (("run", "rtol"), 1e-6, "exactly one of 'dt'"),
    (("run", "steps"), 10, "run: unknown key 'steps'"),
    (("run", "save_every"), 0, "run.save_every must be a positive integer, got 0"),
]


@pytest.mark.parametrize("path, value, match", BAD, ids=[".".join(map(str, p)) + "=" + repr(v)[:12] for p, v, _ in BAD])
def test_bad_scenes_raise_naming_the_key(path, value, match):
    with pytest.raises(ValueError, match=match):
        S.from_dict(_mutate(path, value))


def test_bad_run_combinations():
    def with_run(run):
        d = _tee()
        d["run"] = run
        return d

    # The list of adaptive solvers used to include NaiveLieRK4 and RKMK4.
    with pytest.raises(ValueError, match="run.solver = 'RKMK4' has no error estimate.*: RKF45, DP54, DOP853$"):
        S.from_dict(with_run({"solver": "RKMK4", "rtol": 1e-6, "t1": 1.0}))
    with pytest.raises(ValueError, match="run.save_every applies to fixed-step runs"):
        S.from_dict(with_run({"solver": "DP54", "rtol": 1e-6, "t1": 1.0, "save_every": 2}))
    with pytest.raises(ValueError, match="run.atol applies to adaptive runs"):
        S.from_dict(with_run({"solver": "DP54", "dt": 0.1, "t1": 1.0, "atol": 1e-6}))
    with pytest.raises(ValueError, match=r"effects\[0\].mass is required"):
        S.from_dict(
            _tee(
                body={"kind": "tensor", "inertia": [1.0, 1.0, 1.0]},
                effects=[{"kind": "gravity", "pivot": [0, 0, -1.0]}],
            )
        )
    with pytest.raises(ValueError, match="body.inertia: inertia must be positive definite"):
        S.from_dict(_tee(body={"kind": "tensor", "inertia": [1.0, -1.0, 1.0]}))


def test_a_name_too_long_for_the_outputs_files_is_refused_on_loading():
    """A 400-character name ran, and failed when its outputs were written
    (``OSError: File name too long``)."""
    with pytest.raises(
        ValueError,
        match=r"name: the outputs are named after it \(x{20}\.\.\._components.png\), and 400 "
        r"bytes is more than a file name may take \(240 bytes",
    ):
        S.from_dict(_tee(name="x" * 400))
    # Counted in bytes, as file systems count them (2 a letter here), after
    # the characters a file name leaves out.
    with pytest.raises(ValueError, match="and 242 bytes"):
        S.from_dict(_tee(name="é" * 121))
    longest = S.from_dict(_tee(name="x" * 240 + " ?!"))
    assert longest.file_stem == "x" * 240 and len(f"{longest.file_stem}_components.png") == 255


def test_load_reports_the_file(tmp_path):
    bad = tmp_path / "broken.toml"
    bad.write_text("[body\nkind = 'sphere'\n")
    with pytest.raises(ValueError, match="broken.toml: not valid TOML"):
        S.load(bad)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text((EXAMPLES / "sphere.toml").read_text().replace("radius = 0.1", "radius = -0.1"))
    with pytest.raises(ValueError, match=r"wrong.toml: body.radius must be > 0, got -0.1"):
        S.load(wrong)


# --- run.target_error ----------------------------------------------------------


def _target_run(**run):
    d = _tee()
    d["run"] = {"solver": "RKMK4", "t1": 1.0, **run}
    return d


def test_target_error_scene_solves_to_the_target():
    scene = S.from_dict(_target_run(target_error=1e-9, n_save=5, t1=2.0))
    assert scene.target_error == 1e-9 and scene.solve_kwargs == {"target_error": 1e-9}
    assert scene.adaptive and scene.saveat_every is None and scene.n_save == 5
    sol = scene.solve()
    np.testing.assert_allclose(sol.ts, np.linspace(0.0, 2.0, 5))
    assert int(sol.stats["num_solves"]) >= 2 and float(sol.stats["dt"]) > 0
    exact = np.stack([reference_R(TEE, [1.0, 0.05, 0.0], t) for t in np.asarray(sol.ts)])
    err = np.linalg.norm(np.asarray(sol.R) - exact, axis=(-2, -1))
    assert err.max() <= 1e-9
    assert np.asarray(sol.error_estimate).max() <= 1e-9
    # Adaptive solvers choose a tolerance instead, and max_steps bounds each solve.
    adaptive = S.from_dict(_target_run(solver="DOP853", target_error=1e-7, max_steps=500))
    assert adaptive.solve_kwargs == {"target_error": 1e-7, "max_steps": 500} and adaptive.n_save == 1001


@pytest.mark.parametrize(
    "run, match",
    [
        ({"target_error": 0.0}, "run.target_error must be > 0, got 0.0"),
        ({"target_error": -1e-8}, "run.target_error must be > 0"),
        ({"target_error": float("inf")}, "run.target_error must be a finite number, got inf"),
        ({"target_error": float("nan")}, "run.target_error must be a finite number, got nan"),
        ({"target_error": "1e-8"}, "run.target_error must be a finite number, got '1e-8'"),
        ({"target_error": 1e-8, "dt": 0.01}, "exactly one of 'dt'.*'target_error'.*got dt, target_error"),
        ({"target_error": 1e-8, "rtol": 1e-8, "solver": "DP54"}, "exactly one of.*got rtol, target_error"),
        ({}, "exactly one of 'dt'"),
        ({"target_error": 1e-8, "atol": 1e-8}, "run.atol applies to rtol runs"),
        ({"target_error": 1e-8, "save_every": 2}, "run.save_every applies to fixed-step runs"),
        ({"target_error": 1e-8, "n_save": 1}, "run.n_save must be >= 2"),
    ],
)
def test_bad_target_error_runs_name_the_key(run, match):
    with pytest.raises(ValueError, match=match):
        S.from_dict(_target_run(**run))


def test_with_target_error_keeps_the_saved_resolution():
    scene = S.from_dict(_tee(run={"t1": 1.0, "dt": 0.01, "save_every": 3}))
    n = int(scene.solve().n_saved)  # t = 0, every 3rd of 100 steps, and t1
    assert n == 35
    target = scene.with_target_error(1e-8)
    assert target.solve_kwargs == {"target_error": 1e-8} and target.n_save == n and target.saveat_every is None
    assert target.solver is scene.solver and target.problem is scene.problem
    adaptive = S.from_dict(_target_run(solver="DP54", rtol=1e-6, n_save=7, max_steps=10))
    # rtol's max_steps bounded steps at that tolerance; it is not carried over.
    assert adaptive.with_target_error(1e-8).solve_kwargs == {"target_error": 1e-8}
    assert adaptive.with_target_error(1e-8).n_save == 7
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="target_error must be"):
            scene.with_target_error(bad)


# --- runs too large to attempt, and bodies that overflow --------------------------


@pytest.mark.parametrize(
    "run, match",
    [
        # t1/dt used to overflow inside the solve (OverflowError traceback).
        ({"dt": 1e-320}, r"run.t1 / run.dt = 1.0 s / 1e-320 s is inf steps, more than a run may take \(2147483647\)"),
        ({"t1": 1e300}, r"is 1e\+302 steps, more than a run may take"),
        ({"t1": 1e9, "dt": 0.1}, r"is 1e\+10 steps"),
        ({"t1": 1e6, "dt": 0.01}, r"keeps 1e\+08 states, more than a run may save \(1e\+07\): raise run.save_every"),
        ({"save_every": 2**40}, r"run.save_every must be at most 2147483647"),
        ({"dt": None, "solver": "DP54", "rtol": 1e-8, "n_save": 10**12}, r"run.n_save must be at most 10000000"),
        ({"dt": None, "solver": "DP54", "rtol": 1e-8, "max_steps": 2**63}, r"run.max_steps must be at most 2147483647"),
    ],
)
def test_runs_too_large_to_attempt_are_rejected_on_loading(run, match):
    d = _tee(run=run)
    d["run"] = {k: v for k, v in d["run"].items() if v is not None}
    with pytest.raises(ValueError, match=match):
        S.from_dict(d)


def test_the_largest_runs_allowed_load():
    S.from_dict(_tee(run={"t1": 2147483647.0, "dt": 1.0, "save_every": 1000}))
    S.from_dict(_tee(run={"t1": 1e5, "dt": 0.01}))  # 10^7 saved states
    # A step longer than the run: one shortened step.
    scene = S.from_dict(_tee(run={"t1": 0.5, "dt": 1e12}))
    sol = scene.solve()
    np.testing.assert_array_equal(sol.ts, [0.0, 0.5])
    np.testing.assert_allclose(sol.R[-1], reference_R(TEE, [1.0, 0.05, 0.0], 0.5), atol=1e-2)


def test_with_t1_is_checked_like_run_t1():
    scene = S.from_dict(_tee())
    assert scene.with_t1(2.5).t1 == 2.5 and scene.t1 == 1.0
    with pytest.raises(ValueError, match=r"t1 / run.dt = 1e\+300 s / 0.01 s is 1e\+302 steps"):
        scene.with_t1(1e300)
    for bad in (0.0, -1.0, float("nan"), float("inf"), "2"):
        with pytest.raises(ValueError, match="t1 must be"):
            scene.with_t1(bad)
    # target_error and rtol runs have no step count to bound.
    assert scene.with_target_error(1e-6).with_t1(1e300).t1 == 1e300


@pytest.mark.parametrize(
    "changes, match",
    [
        (
            {"body": {"kind": "box", "mass": 1e-300, "lx": 1e-5, "ly": 1e-5, "lz": 1e-5}},
            "body: the inertia .* is singular or too small to invert",
        ),
        # (A subnormal inertia: NumPy keeps it, where XLA flushed it to zero and reported a NaN.)
        (
            {"body": {"kind": "box", "mass": 1e-310, "lx": 1.0, "ly": 1.0, "lz": 1.0}},
            "body: the inertia .* is singular or too small to invert",
        ),
        (
            {"body": {"kind": "tensor", "inertia": [1e300, 1e300, 1e300]}, "initial": {"omega": [1e300, 0.0, 0.0]}},
            "body: the initial momentum I omega overflows",
        ),
        (
            {"body": {"kind": "box", "mass": 1e300, "lx": 1e200, "ly": 1.0, "lz": 1.0}},
            "the inertia is not finite|NaN or inf",
        ),
        (
            {
                "body": {"kind": "sphere", "mass": 1.0, "radius": 0.1},
                "effects": [{"kind": "gravity", "pivot_to_com": [0, 0, 1e300]}],
            },
            "body about the gravity pivot: the inertia is not finite",
        ),
        # |L| = 1e155 is finite, its square is not.  (1e300 kg m^2 loaded and
        # printed "|L|: nan"; its moments are refused now, below.)
        (
            {"body": {"kind": "tensor", "inertia": [1e100, 1e100, 1e100]}, "initial": {"omega": [1e55, 0.0, 0.0]}},
            r"^body: body.inertia = \[1.e\+100, 1.e\+100, 1.e\+100\] kg m\^2 with initial.omega = \[1.e\+55, 0.e\+00, "
            r"0.e\+00\] rad/s: \|L\|\^2 = \|I omega\|\^2 = 1e\+310 overflows float64, whose normal numbers lie between "
            r"2.2e-308 and 1.8e\+308",
        ),
        (
            {"body": {"kind": "tensor", "inertia": [1e300, 1e300, 1e300]}},
            r"^body: body.inertia = \[1.e\+300, 1.e\+300, 1.e\+300\] kg m\^2 with initial.omega = \[1. , 0.05, 0. \] "
            r"rad/s: det\(I\), the product of the principal moments, = 1e\+900 overflows float64",
        ),
        # Was refused as "not positive definite" (the check's determinant underflowed).
        (
            {"body": {"kind": "tensor", "inertia": [1e-300, 2e-300, 3e-300]}},
            r"body.inertia = \[1.e-300, 2.e-300, 3.e-300\] .*: det\(I\), the product of the principal moments, "
            r"= 6e-900 underflows float64",
        ),
        ({"initial": {"omega": [1e155, 0.0, 0.0]}}, r"\|omega\|\^2 = 1e\+310 overflows float64"),
        # Was "the initial momentum I omega overflows", which it does not (1e196).
        ({"initial": {"omega": [1e200, 0.0, 0.0]}}, "the initial kinetic energy omega . I omega / 2 overflows"),
        (
            {
                "body": {"kind": "sphere", "mass": 1.0, "radius": 0.1},
                "effects": [{"kind": "gravity", "pivot_to_com": [0, 0, 1e150]}],
            },
            r"^body about the gravity pivot: inertia = .* det\(I\), "
            r"the product of the principal moments, = .* overflows",
        ),
    ],
)
def test_bodies_whose_state_overflows_are_rejected(changes, match):
    with pytest.raises(ValueError, match=match):
        S.from_dict(_tee(**changes))


def test_state_range_holds_for_extreme_bodies_that_fit_and_follows_the_precision():
    for moments in ([1e100, 2e100, 3e100], [1e-100, 2e-100, 3e-100]):
        scene = S.from_dict(_tee(body={"kind": "tensor", "inertia": moments}))
        np.testing.assert_array_equal(np.diagonal(np.asarray(scene.problem.inertia)), moments)
    # Moments of 1e150 were refused as "not positive definite" (the check's
    # determinant overflowed); they are too large, and now the message says why.
    with pytest.raises(
        ValueError, match=r"det\(I\), the product of the principal moments, = 6e\+450 overflows float64"
    ):
        S.from_dict(_tee(body={"kind": "tensor", "inertia": [1e150, 2e150, 3e150]}))
    # At rest nothing is squared, but the moments must fit.
    S.from_dict(_tee(body={"kind": "tensor", "inertia": [1e100, 1e100, 1e100]}, initial={"omega": [0.0, 0.0, 0.0]}))
    with pytest.raises(ValueError, match=r"det\(I\), the product of the principal moments, = 1e\+900 overflows"):
        S.from_dict(_tee(body={"kind": "tensor", "inertia": [1e300, 1e300, 1e300]}, initial={"omega": [0.0, 0.0, 0.0]}))
    # Single precision (lierk --float32): the bound is float32's.
    big = _tee(body={"kind": "tensor", "inertia": [1e10, 2e10, 2.5e10]}, initial={"omega": [1e10, 0.0, 0.0]})
    S.from_dict(big)
    with jax.enable_x64(False):
        with pytest.raises(
            ValueError,
            match=r"\|L\|\^2 = \|I omega\|\^2 = 1e\+40 overflows float32, whose normal "
            r"numbers lie between 1.2e-38 and 3.4e\+38",
        ):
            S.from_dict(big)


@pytest.mark.parametrize("effects", [[], [{"kind": "gravity_gradient", "radius": 7e6}]])
def test_an_impossible_inertia_is_warned_about_once_by_its_key(effects):
    """The tensor check, the problem and a gravity gradient each validate the
    inertia; one warning names it (it was printed three times)."""
    d = _tee(body={"kind": "tensor", "inertia": [0.5, 0.6, 1.5]}, effects=effects)
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        scene = S.from_dict(d)
    assert [str(w.message) for w in shown] == [
        "body.inertia [0.5, 0.6, 1.5] breaks the triangle inequality I_max <= I_a + I_b: no rigid body has these "
        "principal moments; the equations are solved as given"
    ]
    # Re-validating the body's own inertia (lierk.exact, as the report does) is silent too.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lierk.exact.flip_interval(scene.problem.inertia, scene.problem.omega0)
    # A physical body, and a solid (never impossible), warn about nothing.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        S.from_dict(_tee(body={"kind": "tensor", "inertia": [1.0, 2.0, 3.0]}, effects=effects))
        S.from_dict(_tee(effects=effects))


def test_load_reports_bytes_that_are_not_utf8(tmp_path):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes("name = 'caf\u00e9'\n".encode("latin-1"))
    # This used to be a bare UnicodeDecodeError, without the file's name.
    with pytest.raises(ValueError, match=r"latin1.toml: not valid TOML: not UTF-8 text \(byte e9 at offset 11\)"):
        S.load(bad)


# --- solved in pieces ----------------------------------------------------------

PIECE_SCENES = {
    # 1037 steps: the last save interval (every 10) and the last step are short.
    "fixed": {
        "body": {"kind": "tee_handle"},
        "initial": {"omega": [1.0, 0.05, 0.3]},
        "run": {"solver": "RKMK4", "dt": 0.01, "t1": 10.37, "save_every": 10},
    },
    "adaptive, effects": {
        "body": {"kind": "tensor", "inertia": [1.0, 2.0, 3.0], "mass": 1.0},
        "initial": {"omega": [0.3, 1.0, 0.2]},
        "effects": [{"kind": "damping", "c": 0.01}],
        "run": {"solver": "DP54", "rtol": 1e-10, "t1": 3.0, "n_save": 23},
    },
}


@pytest.mark.parametrize("name", PIECE_SCENES)
def test_pieces_equal_one_solve(name, capsys):
    """The same saved times, bit for bit; the same states to rounding with
    fixed steps, and to the tolerance (1e-10) adaptively, where each piece
    picks its first step anew."""
    scene = S.from_dict(copy.deepcopy(PIECE_SCENES[name]))
    one = scene.solve()
    pieces = scene.solve(n_pieces=7, progress=True)
    np.testing.assert_array_equal(np.asarray(pieces.ts), np.asarray(one.ts))
    tol = 1e-9 if scene.adaptive else 1e-12
    np.testing.assert_allclose(np.asarray(pieces.R), np.asarray(one.R), rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(pieces.y), np.asarray(one.y), rtol=tol, atol=1e-15)
    assert int(pieces.result) == 0 and int(pieces.n_saved) == len(one.ts)
    if not scene.adaptive:
        assert pieces.stats["num_steps"] == int(one.stats["num_steps"]) == 1037
    err = capsys.readouterr().err
    assert "compiling" in err and "100%" in err


def test_pieces_carry_on_an_attitude_off_so3_as_one_solve_does():
    """ExplicitEuler leaves SO(3); a piece starts where the last ended, as
    one solve's next step does (`restart` would refuse it as an input)."""
    scene = S.from_dict(_tee(run={"solver": "ExplicitEuler", "t1": 0.5, "save_every": 5}))
    one, pieces = scene.solve(), scene.solve(n_pieces=5)
    assert float(lierk.so3.orthogonality_error(one.R[-1])) > 1e-6
    np.testing.assert_array_equal(np.asarray(pieces.ts), np.asarray(one.ts))
    np.testing.assert_allclose(np.asarray(pieces.R), np.asarray(one.R), rtol=0, atol=1e-14)


def test_pieces_report_a_failed_piece_by_its_interval():
    d = copy.deepcopy(PIECE_SCENES["adaptive, effects"])
    d["run"]["max_steps"] = 5
    scene = S.from_dict(d)
    with pytest.raises(RuntimeError, match=r"integration failed between t = 0 s and .* max_steps"):
        scene.solve(n_pieces=3)
    sol = scene.solve(n_pieces=3, throw=False)
    assert int(sol.result) == lierk.RESULTS.max_steps_reached


@pytest.mark.parametrize(
    "kwargs, match", [({"n_pieces": 0}, "n_pieces must be a positive int"), ({"n_pieces": 2, "dt": 0.1}, "only throw=")]
)
def test_bad_pieces_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        S.from_dict(copy.deepcopy(PIECE_SCENES["fixed"])).solve(**kwargs)


def test_saved_count_and_bytes_match_a_solve():
    scene = S.from_dict(copy.deepcopy(PIECE_SCENES["fixed"]))
    sol = scene.solve()
    assert scene.saved_count() == len(sol.ts)
    assert scene.bytes_per_saved() == (sol.ts.nbytes + sol.R.nbytes + sol.y.nbytes) // len(sol.ts)


def test_euler_convention_and_the_single_precision_check():
    free = S.from_dict(
        {
            "body": {"kind": "tensor", "inertia": [1.0, 2.0, 3.0]},
            "initial": {"omega": [0.3, 1.0, 0.2]},
            "run": {"solver": "RKMK4", "t1": 1.0, "dt": 0.1},
        }
    )
    assert free.euler_convention == "zyx"
    with pytest.raises(ValueError, match=r"run.dt = 1e-40 is outside single precision's range"):
        dataclasses.replace(free, solve_kwargs={"dt": 1e-40}).check_single_precision()
    with pytest.raises(ValueError, match=r"^t1 = 1e\+39 is outside"):
        dataclasses.replace(free, t1=1e39, solve_kwargs={"dt": 1.0}).check_single_precision()
    dataclasses.replace(free, solve_kwargs={"dt": 1e-3}).check_single_precision()  # in range: no error
    top = dataclasses.replace(
        free, problem=RigidBodyWithEffects([1.0, 2.0, 3.0], [0.3, 1.0, 0.2], effects=(lierk.Gravity([0, 0, 0.1], 1.0),))
    )
    assert top.euler_convention == "zxz"


def test_describe_run_and_file_stem():
    d = {
        "name": "heavy top!",
        "body": {"kind": "tensor", "inertia": [1.0, 2.0, 3.0]},
        "initial": {"omega": [0.3, 1.0, 0.2]},
        "run": {"solver": "RKMK4", "t1": 1.0, "dt": 0.01},
    }
    fixed = S.from_dict(d)
    assert fixed.describe_run() == "RKMK4, dt = 0.01 s" and fixed.file_stem == "heavy_top"
    adaptive = S.from_dict({**d, "name": "--", "run": {"solver": "dp54", "t1": 1.0, "rtol": 1e-8, "atol": 1e-10}})
    assert adaptive.describe_run() == "DP54, rtol = 1e-08, atol = 1e-10" and adaptive.file_stem == "scene"
    target = fixed.with_target_error(1e-6)
    assert target.describe_run() == "RKMK4, target_error = 1e-06"
    sol = target.solve()
    assert target.describe_run(sol) == f"RKMK4, target_error = 1e-06 (chose {sol.chosen_setting()})"
    assert sol.chosen_setting().startswith("dt = ")
    assert [S.identifier(k) for k in ("|L|", "energy", "L.z (space)", "é")] == ["abs_L", "energy", "L_z_space", "é"]
