"""Events in scenes (``[[events]]``) and in ``lierk simulate``: parsed with
messages that name the key, solved in one piece or several with the same
times, printed and marked by the command line."""

from __future__ import annotations

import copy
import pathlib
import tomllib

import numpy as np
import pytest
from helpers import run_inprocess, write

import lierk
from lierk.app import plot
from lierk.app import scene as S

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"
# The example heavy top nutates between tilts of 0.300 and 0.514 rad with
# period 0.3536 s (tests/test_tops.py checks the file against the quadrature).
TOP = tomllib.loads((EXAMPLES / "heavy_top.toml").read_text())
TOP["run"].update(t1=1.0, save_every=10)
PERIOD, LOWEST, HIGHEST = 0.3536, 0.300, 0.514


def _top(events, **run):
    d = copy.deepcopy(TOP)
    d["events"] = events
    d["run"].update(run)
    return S.from_dict(d)


def test_scene_events_are_solved_and_end_the_run():
    scene = _top(
        [
            {"kind": "tilt_extremum", "extremum": "max", "name": "lowest"},
            {"kind": "tilt", "angle": 0.4, "crossing": "up", "terminate": 2, "name": "leans"},
        ]
    )
    assert [name for name, _ in scene.events] == ["lowest", "leans"]
    sol = scene.solve()
    assert int(sol.result) == lierk.RESULTS.event_occurred
    times = scene.event_times(sol)
    # Leaning through 0.4 rad on the way down, twice: once per period.
    assert len(times["leans"]) == 2 and float(sol.ts[-1]) == times["leans"][1]
    assert times["leans"][1] - times["leans"][0] == pytest.approx(PERIOD, abs=1e-4)
    # The lowest point (largest tilt) between them, at the quadrature's tilt.
    (t_low,) = times["lowest"]
    assert times["leans"][0] < t_low < times["leans"][1] and t_low == pytest.approx(PERIOD / 2, abs=1e-4)
    axis = np.asarray(sol.events[0].R)[0] @ np.array([0.0, 0.0, 1.0])
    assert np.arccos(axis[2]) == pytest.approx(HIGHEST, abs=1e-3)


def test_pieces_find_what_one_solve_finds():
    # The next smallest tilt (t = PERIOD) ends the run in the second of three pieces.
    scene = _top(
        [
            {"kind": "tilt_extremum", "extremum": "min", "terminate": True},
            {"kind": "tilt", "angle": 0.4},
            {"kind": "energy", "threshold": 1e-12, "name": "drift"},
        ]
    )
    one, pieces = scene.solve(), scene.solve(n_pieces=3)
    assert int(one.result) == int(pieces.result) == lierk.RESULTS.event_occurred
    assert float(one.ts[-1]) == pytest.approx(PERIOD, abs=1e-4)
    for name, a in scene.event_times(one).items():
        b = scene.event_times(pieces)[name]
        assert len(a) == len(b) and len(a) > 0, name
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12, err_msg=name)
    np.testing.assert_allclose(pieces.ts[-1], one.ts[-1], rtol=1e-13)
    np.testing.assert_allclose(pieces.R[-1], one.R[-1], atol=1e-12)
    # The saved grid stops at the event, then holds the state there.
    ts = np.asarray(pieces.ts)
    assert (np.diff(ts) > 0).all() and ts[-2] < ts[-1]


@pytest.mark.parametrize(
    "table, words",
    [
        ({"kind": "nutation"}, ["events[0].kind", "'tilt_extremum'"]),
        ({"kind": "tilt"}, ["events[0]", "angle"]),
        ({"kind": "tilt", "angle": 4.0}, ["events[0].angle", "[0, pi]"]),
        ({"kind": "tilt", "angle": 0.4, "axis": [0, 0, 0]}, ["events[0].axis", "non-zero"]),
        (
            {"kind": "pointing", "axis": [1, 0, 0], "target": [0, 0, 1], "angle": 0.2, "crossing": "sideways"},
            ["events[0].crossing", "'up'"],
        ),
        ({"kind": "energy", "threshold": -1.0}, ["events[0].threshold", "> 0"]),
        ({"kind": "flip", "terminate": 0}, ["events[0].terminate", "positive integer"]),
        ({"kind": "flip", "colour": "red"}, ["events[0]", "unknown key 'colour'"]),
    ],
)
def test_bad_event_tables_name_the_key(table, words):
    with pytest.raises(ValueError) as e:
        _top([table])
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_two_events_with_one_name_are_refused():
    with pytest.raises(ValueError, match="events\\[1\\].name = 'flip' is taken"):
        _top([{"kind": "flip"}, {"kind": "tilt", "angle": 0.4, "name": "flip"}])


def test_events_with_target_error_are_found_at_the_chosen_setting():
    """A target_error scene chooses its setting without the events, then
    finds them by a solve at that setting: the same times as a dt run to
    the target's order, and a terminating event cuts the saved run there."""
    events = [
        {"kind": "tilt_extremum", "extremum": "max", "name": "lowest"},
        {"kind": "tilt", "angle": 0.4, "crossing": "up", "terminate": 2, "name": "leans"},
    ]
    d = copy.deepcopy(TOP)
    d["events"] = events
    d["run"] = {"solver": "DOP853", "t1": 1.0, "target_error": 1e-8, "n_save": 101}
    scene = S.from_dict(d)
    sol = scene.solve()
    assert int(sol.result) == lierk.RESULTS.event_occurred and "rtol" in sol.stats
    times = scene.event_times(sol)
    reference = _top(events, dt=1e-4, save_every=100)
    want = reference.event_times(reference.solve())
    for name in ("lowest", "leans"):
        np.testing.assert_allclose(times[name], want[name], atol=1e-7, err_msg=name)
    ts, R, _ = sol.trajectory()
    assert ts[-1] <= times["leans"][1] < ts[-1] + 0.01 and np.isfinite(R).all()
    assert np.isfinite(np.asarray(sol.error_estimate)[: len(ts)]).all()


def test_simulate_prints_saves_and_marks_the_events(tmp_path, capsys):
    text = (EXAMPLES / "heavy_top.toml").read_text().replace("t1 = 5.0", "t1 = 1.0")
    text += '\n[[events]]\nkind = "tilt_extremum"\nextremum = "max"\nname = "lowest"\n'
    text += '\n[[events]]\nkind = "tilt"\nangle = 0.45\ncrossing = "down"\nterminate = true\n'
    out = tmp_path / "out"
    code, stdout, err = run_inprocess(["simulate", write(tmp_path, text), "--out", out, "--no-gif", "--quiet"], capsys)
    assert code == 0, err
    data = np.load(out / "heavy_top.npz")
    lowest, tilt = data["event_lowest"], data["event_tilt"]
    assert len(lowest) == 1 and len(tilt) == 1 and lowest[0] < tilt[0]
    assert f"  event lowest: 1 at t = {lowest[0]:.6g} s" in stdout
    assert f"  the run ended at the tilt event, t = {tilt[0]:.9g} s" in stdout
    assert data["ts"][-1] == tilt[0]
    # A symmetric top has no intermediate axis: no flip event was added.
    assert "event flip" not in stdout and "event_flip" not in data


def test_flip_marks_on_the_figures():
    scene = S.load(EXAMPLES / "tee_handle_a.toml").with_t1(30.0).with_flip_event()
    sol = scene.solve()
    (t_flip,) = scene.event_times(sol)["flip"]
    assert t_flip == pytest.approx(11.8154, abs=1e-4)
    fig = plot.components(sol, events=scene.event_times(sol))
    for ax in fig.axes:
        marks = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]
        assert [float(ln.get_xdata()[0]) for ln in marks] == [t_flip]
    fig = plot.euler_angles(sol, events={"flip": [t_flip], "other": [3.0]})
    assert [ln.get_label() for ln in fig.axes[0].get_lines() if ln.get_label() in ("flip", "other")] == [
        "flip",
        "other",
    ]
