"""``lierk accuracy`` and `lierk.app.accuracy`: the errors it reports are the
errors against the exact solution, its per-decade table picks runs that
really reach each decade, and mistakes end in one line."""

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import run_inprocess, write
from PIL import Image

import lierk
import lierk.app.accuracy as A
import lierk.app.scene
import lierk.exact
from lierk.app import cli

TINY_SCENE = """
name = "tiny"
[body]
kind = "tee_handle"
[initial]
omega = [1.0, 0.05, 0.3]
[run]
solver = "RKMK4"
dt = 0.01
t1 = 0.5
"""

DAMPED_SCENE = """
name = "damped"
[body]
kind = "tensor"
inertia = [1.0, 2.0, 3.0]
[initial]
omega = [0.3, 1.0, 0.2]
[[effects]]
kind = "damping"
c = 0.2
[run]
solver = "RKMK4"
dt = 0.01
t1 = 0.3
"""

LIERK = str(Path(sys.executable).parent / "lierk")
TABLE_LINE = re.compile(r"^\s*(1e-\d\d)\s+(\S+)\s+(dt = \S+ s|rtol = \S+)\s+(\S+)\s+(\S+)\s+(\S+)\s*$")


def _exact_error(scene, row, ts):
    """The row's run repeated with lierk.solve, against lierk.exact at ``ts``."""
    p = scene.problem
    if row["setting"] == "dt":
        m = round((ts[1] - ts[0]) / row["value"])
        sol = lierk.solve(
            p, lierk.SOLVERS[row["solver"]](), scene.t1, dt=row["value"], saveat=lierk.SaveAt(t0=True, steps=m)
        )
    else:
        sol = lierk.solve(
            p,
            lierk.SOLVERS[row["solver"]](),
            scene.t1,
            rtol=row["value"],
            saveat=lierk.SaveAt(ts=np.asarray(ts)),
            max_steps=2**17,
        )
    np.testing.assert_allclose(sol.ts, ts, rtol=0, atol=1e-12)
    R_exact = np.asarray(lierk.exact.free_rigid_body(p.inertia, p.omega0, np.asarray(ts), p.R0)[0])
    return float(np.max(np.linalg.norm(np.asarray(sol.R) - R_exact, axis=(-2, -1))))


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """``lierk accuracy`` on a 0.5 s torque-free scene with two solvers and
    three settings each, run once for the tests below."""
    tmp = tmp_path_factory.mktemp("accuracy")
    scene_path = write(tmp, TINY_SCENE)
    out = tmp / "out"
    import io
    from contextlib import redirect_stderr, redirect_stdout

    so, se = io.StringIO(), io.StringIO()
    with redirect_stdout(so), redirect_stderr(se):
        code = cli.main(
            ["accuracy", str(scene_path), "--out", str(out), "--solvers", "RKMK4,DOP853", "--max-settings", "3"]
        )
    return code, so.getvalue(), se.getvalue(), out, lierk.app.scene.load(scene_path)


def test_accuracy_writes_png_and_json(tiny_run):
    code, stdout, stderr, out, scene = tiny_run
    assert code == 0, stderr
    assert "100%" in stderr and "Traceback" not in stderr  # the progress bar
    with Image.open(out / "work_precision.png") as im:
        assert im.format == "PNG" and im.size == (800, 700)
    doc = json.loads((out / "work_precision.json").read_text(), parse_constant=lambda c: pytest.fail(f"JSON has {c}"))
    assert doc["scene"] == "tiny" and doc["t1"] == 0.5 and doc["dtype"] == "float64"
    np.testing.assert_allclose(doc["ts"], np.linspace(0.0, 0.5, 11))
    assert doc["reference"].startswith("lierk.exact") and doc["check"] is None
    assert {r["solver"] for r in doc["rows"]} == {"RKMK4", "DOP853"}
    assert all(1 <= sum(r["solver"] == s for r in doc["rows"]) <= 3 for s in ("RKMK4", "DOP853"))
    assert str(out / "work_precision.png") in stdout and str(out / "work_precision.json") in stdout


def test_reported_errors_are_the_errors_against_the_exact_solution(tiny_run):
    code, stdout, stderr, out, scene = tiny_run
    doc = json.loads((out / "work_precision.json").read_text())
    for row in doc["rows"]:
        assert row["result"] == 0 and row["time"] > 0 and row["num_steps"] > 0
        err = _exact_error(scene, row, doc["ts"])
        assert row["error"] == pytest.approx(err, rel=1e-6, abs=1e-15), row
        # The solver's own estimate is of the same quantity (measured within 10% here).
        if err > 1e-12:
            assert 0.5 < row["error_estimate"] / err < 2.0, row


def test_table_picks_the_cheapest_run_really_below_each_decade(tiny_run):
    code, stdout, stderr, out, scene = tiny_run
    doc = json.loads((out / "work_precision.json").read_text())
    rows = doc["rows"]
    label = {(r["solver"], A.Row(**r).label): r for r in rows}
    picked = {}
    for line in stdout.splitlines():
        m = TABLE_LINE.match(line)
        if m:
            decade, solver, setting = float(m[1]), m[2], m[3]
            row = label[(solver, setting)]
            assert float(m[4]) == pytest.approx(row["time"], rel=0.01)
            assert float(m[5]) == pytest.approx(row["error"], rel=0.06)
            assert float(m[6]) == pytest.approx(row["error_estimate"], rel=0.06)
            picked[decade] = row
    assert len(picked) >= 4, stdout
    for decade in A.DECADES:
        reaching = [r for r in rows if r["error"] is not None and r["error"] <= decade]
        if decade in picked:
            row = picked[decade]
            assert _exact_error(scene, row, doc["ts"]) <= decade
            assert row["time"] == min(r["time"] for r in reaching)
        else:
            assert not reaching
            assert re.search(rf"^\s*{decade:.0e}\s+\(no run reached it\)", stdout, re.M), stdout
    # The JSON names the same rows.
    for entry in doc["decades"]:
        row = picked.get(entry["error_at_most"])
        assert (entry["cheapest"] is None) == (row is None)
        if row is not None:
            assert rows[entry["cheapest"]["row"]] == row


@pytest.mark.parametrize(
    "argv, message",
    [
        (["accuracy", "{bad}", "--out", "{out}"], "initial.omega must be a list of 3 numbers"),
        (["accuracy", "{missing}", "--out", "{out}"], "scene file not found"),
        (["accuracy", "{scene}", "--out", "{out}", "--solvers", "RKMK4,RK45"], "unknown solver 'RK45'"),
        (["accuracy", "{scene}", "--out", "{out}", "--max-settings", "0"], "--max-settings must be a positive integer"),
    ],
)
def test_mistakes_end_in_one_line(tmp_path, capsys, argv, message):
    files = {
        "bad": write(tmp_path, TINY_SCENE.replace("[1.0, 0.05, 0.3]", "[1.0, 0.05]"), "bad.toml"),
        "missing": tmp_path / "missing.toml",
        "scene": write(tmp_path, TINY_SCENE),
        "out": tmp_path / "out",
    }
    code, out, err = run_inprocess([a.format(**files) for a in argv], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_console_script_bad_scene_without_traceback(tmp_path):
    bad = write(tmp_path, TINY_SCENE.replace('kind = "tee_handle"', 'kind = "cube"'))
    p = subprocess.run([LIERK, "accuracy", bad, "--out", tmp_path / "out"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2
    assert p.stderr.count("\n") == 1 and "body.kind = 'cube' is not allowed" in p.stderr, p.stderr
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------
# The library


def _row(solver, value, time, error, result=0):
    return A.Row(solver, "rtol", value, time, error, error, 10, 100, result)


def _report(rows, floor_parts=(1e-13, None), check=None):
    return A.AccuracyReport(
        "hand", 1.0, np.linspace(0, 1, 3), tuple(rows), "made up", floor_parts[0], check, floor_parts[1], "float64"
    )


def test_cheapest_per_decade_and_the_floor():
    rows = [
        _row("A", 1e-4, 0.01, 3e-3),
        _row("A", 1e-8, 0.05, 2e-7),
        _row("B", 1e-6, 0.02, 5e-4),
        _row("B", 1e-9, 0.03, 4e-8),
        _row("B", 1e-12, 0.01, math.nan, result=1),  # failed: never picked
    ]
    rep = _report(rows)
    best = rep.best_per_decade()
    assert best[1e-2] is rows[0]  # A is cheapest at 1e-2
    assert best[1e-3] is rows[2]  # only B's 5e-4 and the slower ones reach 1e-3
    assert best[1e-7] is rows[3]  # B (0.03 s) beats A (0.05 s)
    assert best[1e-8] is None
    assert rep.floor == 1e-13
    # A numerical reference whose check disagrees by 1e-7: nothing below it is claimed.
    checked = _report(rows, (1e-9, 1e-7), check="DP54")
    assert checked.floor == 1e-7 and checked.cheapest(1e-7) is rows[3] and checked.cheapest(1e-8) is None
    # A check that failed vouches for nothing.
    assert _report(rows, (1e-9, None), check="DP54: failed").cheapest(1e-2) is None


def test_summary_and_table_are_what_lierk_accuracy_prints():
    rows = [_row("A", 1e-4, 0.01, 3e-3), _row("B", 1e-9, 0.03, 4e-8)]
    rep = _report(rows, (1e-9, 2e-9), check="DP54, rtol = atol = 1e-11")
    table = rep.table(decades=(1e-2, 1e-8, 1e-10))
    assert table.splitlines() == [
        " error <=  cheapest  setting              time (s)     error  estimate",
        "    1e-02  A         rtol = 1e-04             0.01   3.0e-03   3.0e-03",
        "    1e-08  (no run reached it)",
        "    1e-10  (below the reference's accuracy, 2.0e-09)",
    ]
    lines = rep.summary(wall=1.25).splitlines()
    assert lines[:3] == [
        "scene hand: 2 runs of A, B, T = 1 s, errors max_t ||R - R_ref||_F at 3 equally spaced times, "
        "1.2 s wall (incl. compilation)",
        "  reference: made up, error about 1.0e-09",
        "  cross-check: DP54, rtol = atol = 1e-11, disagrees by 2.0e-09",
    ]
    assert lines[3:] == rep.table().splitlines() and len(lines) == 3 + 1 + len(A.DECADES)
    # Without the wall time and with the closed form (no cross-check).
    assert _report(rows).summary().splitlines()[:2] == [
        "scene hand: 2 runs of A, B, T = 1 s, errors max_t ||R - R_ref||_F at 3 equally spaced times",
        "  reference: made up, error about 1.0e-13",
    ]


def test_to_json_is_strict_json():
    rows = [_row("A", 1e-4, 0.01, 3e-3), _row("A", 1e-12, 0.01, math.nan, result=1)]
    doc = json.loads(A.to_json(_report(rows)), parse_constant=lambda c: pytest.fail(f"JSON has {c}"))
    assert doc["rows"][1]["error"] is None and doc["rows"][1]["result"] == 1
    assert [d["cheapest"] is not None for d in doc["decades"]][:2] == [True, False]


def test_numerical_reference_is_cross_checked_with_effects():
    import jax

    with jax.enable_x64(True):
        scene = lierk.app.scene.from_dict(__import__("tomllib").loads(DAMPED_SCENE))
        assert scene.problem.effects != ()
        rep = A.work_precision(scene, solvers=["RKMK4"], settings={"RKMK4": [0.03, 0.015]})
        assert rep.reference.startswith("DOP853, rtol = atol = 1e-13") and rep.check.startswith("DP54")
        # Two tight solves of different orders agree to about their tolerance.
        assert 0 < rep.check_disagreement < 1e-10
        assert rep.floor == max(rep.reference_error, rep.check_disagreement)
        assert [r.value for r in rep.rows] == pytest.approx([0.03, 0.015])
        # The rows' errors against an independent reference: CF4 at a 100x finer step.
        fine = lierk.solve(scene.problem, lierk.CF4(), 0.3, dt=0.0003, saveat=lierk.SaveAt(t0=True, steps=100))
        np.testing.assert_allclose(fine.ts, rep.ts, atol=1e-14)
        for row in rep.rows:
            sol = lierk.solve(
                scene.problem,
                lierk.RKMK4(),
                0.3,
                dt=row.value,
                saveat=lierk.SaveAt(t0=True, steps=round(0.03 / row.value)),
            )
            err = float(np.max(np.linalg.norm(np.asarray(sol.R) - np.asarray(fine.R), axis=(-2, -1))))
            assert row.error == pytest.approx(err, rel=1e-3)


GRAVITY_SCENE = """
name = "top"
[body]
kind = "tensor"
inertia = [5.0, 5.0, 1.0]
mass = 1.0
[initial]
omega = [0.3, 0.0, 20.0]
[[effects]]
kind = "gravity"
pivot_to_com = [0.0, 0.0, 2.0]
g = 10.0
[run]
solver = "RKMK4"
dt = 0.01
t1 = 0.2
"""


def _scene(text):
    return lierk.app.scene.from_dict(__import__("tomllib").loads(text))


def test_every_applicable_solver_runs_by_default():
    free = A.default_solvers(_scene(TINY_SCENE).problem)
    assert free == ("RKMK4", "CF4", "RKMK(DOPRI54)", "RKMK(DOP853)", "DP54", "DOP853", "RKF45")
    # Under torques the splittings too; the Runge-Kutta-Nystrom ones only
    # where no torque reads the momentum.
    assert A.default_solvers(_scene(GRAVITY_SCENE).problem) == free + (
        "Strang",
        "BlanesMoan4",
        "BlanesMoan6",
        "BlanesMoanRKN4",
        "BlanesMoanRKN6",
    )
    assert A.default_solvers(_scene(DAMPED_SCENE).problem) == free + ("Strang", "BlanesMoan4", "BlanesMoan6")
    assert A.default_solvers(_scene(GRAVITY_SCENE).problem) == A.METHODS
    # The embedded pairs' tableaux at fixed steps, by name in any case.
    m = A.method("rkmk(dop853)")
    assert (m.name, m.adaptive, m.solver.tableau) == ("RKMK(DOP853)", False, lierk.tableaux.DOP853)
    assert A.method("DOP853").adaptive and not A.method("BlanesMoanRKN4").adaptive
    # Timed at their fastest: the stages unrolled, as a batch runs them.
    assert m.solver.compact is False and A.method("dp54").solver.compact is False
    with pytest.raises(ValueError, match=r"unknown solver 'RKMK\(RK45\)'.*RKMK\(DOP853\)"):
        A.method("RKMK(RK45)")
    with pytest.raises(ValueError, match="BlanesMoanRKN4 is a Runge-Kutta-Nystrom splitting.*Damping"):
        A.work_precision(_scene(DAMPED_SCENE), solvers=["BlanesMoanRKN4"])


def test_one_compilation_per_solver_and_the_runs_are_lierk_solve_s():
    import jax

    with jax.enable_x64(True):
        scene = _scene(GRAVITY_SCENE)
        solvers = ["RKMK(DOP853)", "BlanesMoanRKN4", "DP54"]
        jax.clear_caches()
        rep = A.work_precision(scene, solvers=solvers, max_settings=2, repeats=1)
        # One program per solver and one for DOP853, the reference (DP54,
        # its cross-check, shares the rows' program): every setting, its
        # finer twin for the error estimate and the reference reuse them.
        assert rep.compilations == len(solvers) + 1, rep.compilations
        assert len(rep.rows) == 6 and 0 < rep.compile_time
        assert re.search(rf"s wall \([\d.]+ s of it compiling {len(solvers) + 1} programs\)", rep.summary(wall=9.0))
        ts = np.asarray(rep.ts)
        p = scene.problem

        # The report's solvers unroll their stages (`A.method`): so does the
        # reference.  The report's program takes its settings as traced
        # arguments, and lierk.solve's own program is another compilation of
        # the same steps: the rows match lierk.solve's to rounding.
        R_ref = np.asarray(
            lierk.solve(
                p, lierk.DOP853(compact=False), scene.t1, rtol=1e-13, saveat=lierk.SaveAt(ts=ts), max_steps=2**17
            ).R
        )
        for row in rep.rows:
            m = A.method(row.solver)
            if row.setting == "dt":
                sol = lierk.solve(
                    p, m.solver, scene.t1, dt=row.value, saveat=lierk.SaveAt(ts=ts), estimate_error=True, throw=False
                )
            else:
                sol = lierk.solve(
                    p,
                    m.solver,
                    scene.t1,
                    rtol=row.value,
                    saveat=lierk.SaveAt(ts=ts),
                    max_steps=2**17,
                    estimate_error=True,
                    throw=False,
                )
            assert (row.result, row.num_steps, row.num_fevals) == (
                int(sol.result),
                int(sol.stats["num_steps"]),
                int(sol.stats["num_fevals"]),
            ), row
            if not row.ok:
                continue
            # The same steps as lierk.solve's: the same states to rounding,
            # and the same estimate (computed on the host here).
            err = float(np.max(np.linalg.norm(np.asarray(sol.R) - R_ref, axis=(-2, -1))))
            assert row.error == pytest.approx(err, rel=1e-9, abs=1e-15), row
            assert row.error_estimate == pytest.approx(float(np.max(sol.error_estimate)), rel=1e-6, abs=1e-15), row
