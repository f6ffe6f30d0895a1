"""`lierk.app.omega_sweep`: the sweep behind ``lierk sweep``, called from Python."""

from __future__ import annotations

import numpy as np
import pytest

import lierk
from lierk import so3
from lierk.app import scene as S
from lierk.app.omega_sweep import omega_grid, open_sweep_store, sweep_method, sweep_omega0

TEE = [9.82271303e-05, 7.22671030e-05, 1.57865031e-04]


def _scene(**run):
    return S.from_dict(
        {
            "body": {"kind": "tensor", "inertia": TEE},
            "initial": {"omega": [1.0, 0.05, 0.3]},
            "run": {"solver": "RKMK4", "t1": 0.5, "dt": 0.05, **run},
        }
    )


def test_sweep_matches_a_python_loop_of_sensitivities():
    scene = _scene()
    # An RKMK solver on a rigid body: the variational equations.
    assert sweep_method(scene) == "variational"
    axes = omega_grid(np.asarray(scene.problem.omega0), [None, (0.0, 0.1, 2), (0.2, 0.4, 3)])
    res = sweep_omega0(scene, axes, chunk_size=4)
    assert res.varied == [1, 2] and res.shape == (2, 3) and not res.failed.any()
    for i in range(2):
        for j in range(3):
            w = res.grid[i, j]
            np.testing.assert_allclose(w, [1.0, axes[1][i], axes[2][j]])
            s = lierk.sensitivity(scene.problem.with_omega0(w), scene.solver, 0.5, dt=0.05, method="variational")
            np.testing.assert_allclose(
                res.values["sensitivity"][i, j], np.sqrt(np.sum(np.asarray(s.jacobian_R) ** 2)), rtol=1e-10
            )
            np.testing.assert_allclose(res.values["angle"][i, j], np.linalg.norm(np.asarray(so3.log(s.R))), rtol=1e-10)
            tau = float(lierk.exact.flip_interval(scene.problem.inertia, w))
            assert res.values["flip_interval"][i, j] == pytest.approx(tau, rel=1e-12) or not np.isfinite(tau)


def test_a_splitting_sweep_takes_the_derivative():
    # The splittings step through drift and kick, not a tableau that could
    # carry the variational equations: the sweep differentiates the solve.
    scene = _scene(solver="Strang")
    assert sweep_method(scene) == "derivative"
    axes = omega_grid(np.asarray(scene.problem.omega0), [None, (0.0, 0.1, 2), None])
    res = sweep_omega0(scene, axes, chunk_size=2)
    for i in range(2):
        # (Without the estimate's finer solve: the Jacobian is the same, and
        # the reference compiles in half the time.)
        s = lierk.sensitivity(scene.problem.with_omega0(res.grid[i]), scene.solver, 0.5, dt=0.05, estimate_error=False)
        np.testing.assert_allclose(
            res.values["sensitivity"][i], np.sqrt(np.sum(np.asarray(s.jacobian_R) ** 2)), rtol=1e-10
        )


def test_a_stored_sweep_resumes_to_the_same_numbers(tmp_path):
    scene = _scene()
    axes = omega_grid(np.asarray(scene.problem.omega0), span=0.1, n=3)
    assert [len(a) for a in axes] == [1, 3, 3]  # the two smallest components vary
    whole = sweep_omega0(scene, axes, chunk_size=4)
    store = open_sweep_store(scene, axes, tmp_path / "chunks", chunk_size=4, key={"run": "a"})
    assert store.resumed == 0
    stored = sweep_omega0(scene, axes, chunk_size=4, store=store)
    for k in whole.values:
        np.testing.assert_array_equal(stored.values[k], whole.values[k])
    reopened = open_sweep_store(scene, axes, tmp_path / "chunks", chunk_size=4, key={"run": "a"})
    assert reopened.complete and reopened.resumed == 3
    with pytest.raises(ValueError, match="another run"):
        open_sweep_store(scene, axes, tmp_path / "chunks", chunk_size=4, key={"run": "b"})


def test_bad_sweeps_are_refused():
    scene = _scene()
    with pytest.raises(ValueError, match="nothing to sweep"):
        sweep_omega0(scene, [[1.0], [0.05], [0.3]])
    with pytest.raises(ValueError, match="at most two components"):
        sweep_omega0(scene, [[1.0, 1.1], [0.0, 0.1], [0.2, 0.3]])
    with pytest.raises(ValueError, match="omega0 is zero"):
        omega_grid(np.zeros(3))
    target = S.from_dict(
        {
            "body": {"kind": "tensor", "inertia": TEE},
            "initial": {"omega": [1.0, 0.05, 0.3]},
            "run": {"solver": "RKMK4", "t1": 0.5, "target_error": 1e-6},
        }
    )
    with pytest.raises(ValueError, match="target_error chooses a setting"):
        sweep_omega0(target, omega_grid([1.0, 0.05, 0.3], span=0.1, n=2))


def test_summary_gives_the_ranges_lierk_sweep_prints():
    from lierk.app.omega_sweep import OmegaSweep

    axes = (np.array([1.0]), np.array([0.0, 0.1]), np.array([0.2, 0.3]))
    failed = np.array([[False, False], [True, False]])
    values = {
        "angle": np.array([[0.1, 0.2], [np.nan, 0.4]]),
        "sensitivity": np.array([[2.0, 3.0], [np.nan, 40.0]]),
        "sensitivity_error": np.array([[2e-7, 3e-9], [np.nan, 4e-8]]),
        "lyapunov": np.array([[0.5, 1.5], [np.nan, 2.25]]),
        "flip_interval": np.array([[7.5, np.inf], [12.0, np.inf]]),
    }
    res = OmegaSweep(axes, values, failed, 0.5)
    assert res.summary().splitlines() == [
        "  1 points failed to integrate (NaN in the outputs)",
        "  ||dR(T)/d omega0|| (derivative of the solve): 2 .. 40 s (estimated error of it: up to 1e-07 relative)",
        "  finite-time Lyapunov exponent: 0.5 .. 2.25 1/s",
        "  flip interval: 7.5 .. 12 s",
    ]
    # No failures and no flip anywhere (or a body with effects): those lines go.
    calm = OmegaSweep(
        axes, {**values, "flip_interval": np.full((2, 2), np.inf)}, np.zeros((2, 2), bool), 0.5, "variational"
    )
    assert [line.split(":")[0] for line in calm.summary().splitlines()] == [
        "  ||dR(T)/d omega0|| (variational equations)",
        "  finite-time Lyapunov exponent",
    ]
    no_flip = {k: v for k, v in values.items() if k != "flip_interval"}
    assert len(OmegaSweep(axes, no_flip, failed, 0.5).summary().splitlines()) == 3
