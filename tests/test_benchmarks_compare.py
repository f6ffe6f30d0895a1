"""The regression guard: `python -m benchmarks compare` (benchmarks/compare.py)
and the headline cells it runs (benchmarks/headline.py).  No timing: the
table's flags on made-up runs, and one tiny headline run checked for its
errors against the closed form."""

import json
import math
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "benchmarks"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import compare  # noqa: E402
from benchmarks.__main__ import benchmarks as listed  # noqa: E402


def cell(time=None, error=None, **more):
    return {"time": time, "error": error, "unit": "s", "extra": {}, "what": "", **more}


def rows(base_runs, head_runs, **kw):
    flags = compare.compare_cells(compare.aggregate(base_runs), compare.aggregate(head_runs), **kw)
    return {r["cell"]: r for r in flags}


def test_a_cell_more_than_ten_percent_slower_is_flagged_and_five_percent_is_not():
    base = [{"slow": cell(1.0), "same": cell(2.0), "fast": cell(1.0)}]
    head = [{"slow": cell(1.12), "same": cell(2.1), "fast": cell(0.5)}]
    r = rows(base, head)
    assert r["slow"]["flags"] == ["1.12x slower"] and math.isclose(r["slow"]["ratio"], 1.12)
    assert r["same"]["flags"] == [] and r["fast"]["flags"] == []
    lines = {line.split(" | ")[0][2:]: line for line in compare.table(list(r.values())) if line.startswith("| ")}
    assert "**1.12x slower**" in lines["slow"] and "**" not in lines["same"] and "**" not in lines["fast"]
    # the threshold is the caller's
    assert rows(base, head, threshold=0.2)["slow"]["flags"] == []


def test_an_error_more_than_ten_percent_larger_is_flagged_above_the_rounding_floor():
    base = [
        {
            "worse": cell(1.0, 1e-8),
            "close": cell(1.0, 1e-8),
            "rounding": cell(1.0, 1e-15),
            "nan": cell(1.0, 1e-8),
            "better": cell(1.0, 1e-8),
        }
    ]
    head = [
        {
            "worse": cell(1.0, 1.2e-8),
            "close": cell(1.0, 1.05e-8),
            "rounding": cell(1.0, 5e-14),
            "nan": cell(1.0, float("nan")),
            "better": cell(1.0, 1e-9),
        }
    ]
    r = rows(base, head)
    assert r["worse"]["flags"] == ["error 1.20x"]
    assert r["close"]["flags"] == r["rounding"]["flags"] == r["better"]["flags"] == []
    assert r["nan"]["flags"] == ["error not finite"]


def test_failing_or_losing_an_api_at_head_is_flagged_and_a_new_cell_is_not():
    base = [
        {
            "fails": cell(1.0),
            "gone": cell(1.0),
            "new": cell(na="needs lierk.sweep"),
            "never": cell(na="needs lierk.sweep"),
        }
    ]
    head = [
        {
            "fails": cell(failed="RuntimeError: boom"),
            "gone": cell(na="needs lierk.sweep"),
            "new": cell(1.0),
            "never": cell(na="needs lierk.sweep"),
        }
    ]
    r = rows(base, head)
    assert r["fails"]["flags"] == ["fails at HEAD"] and r["gone"]["flags"] == ["gone at HEAD"]
    assert r["new"]["flags"] == [] and r["new"]["notes"] == ["new at HEAD"] and r["never"]["flags"] == []
    text = "\n".join(compare.table(list(r.values())))
    assert "- fails at HEAD: failed: RuntimeError: boom" in text and "- never at BASE: n/a: needs lierk.sweep" in text


def test_a_commits_time_is_its_fastest_run_and_spread_runs_are_noted():
    base = [{"a": cell(1.3), "b": cell(1.0)}, {"a": cell(1.0), "b": cell(1.05)}]
    head = [{"a": cell(1.05), "b": cell(1.0)}, {"a": cell(1.08), "b": cell(1.0)}]
    r = rows(base, head)
    assert r["a"]["base"]["time"] == 1.0 and r["a"]["base"]["times"] == [1.3, 1.0]
    assert r["a"]["flags"] == [] and r["a"]["notes"] == ["BASE runs 1.30x apart"]
    assert r["b"]["notes"] == []


def test_compare_is_a_command_not_a_listed_benchmark():
    names = listed()
    assert "headline" in names and "compare" not in names
    with pytest.raises(SystemExit) as exc:
        compare.main(["no-such-revision-anywhere", "HEAD"])
    assert exc.value.code == 2


def test_a_cell_missing_its_api_is_na_and_one_that_raises_is_failed(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    import headline

    results = {}
    old = types.SimpleNamespace(solve=lambda problem, solver, t1, *, dt=None: None)
    headline.run_cell(results, "sweep_lierk_sweep", lambda: headline.need(old, "sweep"), {"sweep_lierk_sweep"})
    headline.run_cell(results, "events_rkmk4_flip", lambda: headline.need(old, "solve(event)"), {"events_rkmk4_flip"})
    headline.run_cell(results, "first_solve", lambda: 1 / 0, {"first_solve"})
    headline.run_cell(results, "first_jacfwd", lambda: {"time": 1.0}, set())  # not wanted: not run
    assert results["sweep_lierk_sweep"]["na"] == "needs lierk.sweep" and results["sweep_lierk_sweep"]["time"] is None
    assert results["events_rkmk4_flip"]["na"] == "needs lierk.solve(event)"
    assert results["first_solve"]["failed"].startswith("ZeroDivisionError")
    assert "first_jacfwd" not in results
    assert headline.select(["jac_top", "free_rkmk4"]) == [
        "free_rkmk4",
        "jac_top_dop853_forward",
        "jac_top_dop853_jacfwd",
    ]
    with pytest.raises(ValueError, match="unknown cell"):
        headline.select(["jac_to"])


def test_headline_quick_measures_this_checkouts_lierk_against_the_closed_form(tmp_path):
    out = tmp_path / "cells.json"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run(
        [
            sys.executable,
            str(BENCH / "headline.py"),
            "--quick",
            "--json",
            str(out),
            "--cells",
            "free_rkmk4",
            "events_rkmk4_flip",
        ],
        env=env,
        check=True,
        capture_output=True,
        text=True,
    )
    cells = json.loads(out.read_text())
    assert Path(cells["_meta"]["lierk"]) == ROOT / "lierk"
    assert sorted(cells) == ["_meta", "events_rkmk4_flip", "free_rkmk4"]
    free, flips = cells["free_rkmk4"], cells["events_rkmk4_flip"]
    # 4 T-handles, T = 4 s, RKMK4 at dt = 0.01 s: the closed form's error of
    # a fourth-order step, not zero (the reference is not the solve itself)
    assert 1e-12 < free["error"] < 1e-7 and free["time"] > 0
    # half of them flip before T; each flip's time within 1e-8 s of the exact one
    assert flips["extra"]["flips before T"] >= 1 and 0 < flips["error"] < 1e-8
    assert flips["extra"]["/ without the event"] > 0
