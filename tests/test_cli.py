"""The command line: outputs agree with direct library calls, figures decode
with their documented sizes, and every mistake ends in one line on stderr
with a non-zero exit status."""

import io
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import run_inprocess, write
from PIL import Image

import lierk
import lierk.app.scene
import lierk.exact
from lierk import _progress as cli_progress
from lierk.app import cli, plot

TEE_SCENE = """
name = "tee test"
description = "T-handle near the intermediate axis"
[body]
kind = "tee_handle"
[initial]
omega = [1.0, 0.05, 0.3]
[run]
solver = "RKMK4"
dt = 0.01
t1 = 100.0
save_every = 2
"""

DAMPED_SCENE = """
name = "damped"
[body]
kind = "tee_handle"
[initial]
omega = [1.0, 0.05, 0.3]
[[effects]]
kind = "damping"
c = 2e-5
[run]
solver = "CF4"
dt = 0.01
t1 = 0.7
save_every = 3
"""

ADAPTIVE_SCENE = """
name = "adaptive"
[body]
kind = "tensor"
inertia = [1.0, 2.0, 3.0]
[initial]
omega = [0.3, 1.0, 0.2]
[run]
solver = "DP54"
rtol = 1e-10
t1 = 2.0
n_save = 41
"""

# Few saved times (0.5 s apart): the steps a target_error solve tries fit
# between them.
SMALL_TARGET_SCENE = """
name = "small target"
[body]
kind = "tee_handle"
[initial]
omega = [1.0, 0.05, 0.3]
[run]
solver = "RKMK4"
target_error = 1e-10
t1 = 2.0
n_save = 5
"""

LIERK = str(Path(sys.executable).parent / "lierk")
EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def run_subprocess(argv):
    p = subprocess.run([LIERK, *map(str, argv)], capture_output=True, text=True, timeout=600)
    return p.returncode, p.stdout, p.stderr


# ---------------------------------------------------------------------------
# Arguments and errors


@pytest.mark.parametrize(
    "text, expected",
    [("-0.2:0.2:5", (-0.2, 0.2, 5)), ("0.5", (0.5, 0.5, 1)), ("1:2:1", (1.0, 2.0, 1))],
)
def test_parse_range(text, expected):
    assert cli.parse_range(text) == expected


@pytest.mark.parametrize("text", ["1:0:5", "0:1:0", "0:1", "a:b:3", "0:inf:3", "0:1:2.5"])
def test_parse_range_rejects(text):
    with pytest.raises(Exception, match="START|N|finite|expected"):
        cli.parse_range(text)


def test_progress_off_a_terminal_is_a_few_distinct_increasing_lines():
    # It used to print four identical lines, each "1.4 s"; then lines that
    # mixed "0.0 s elapsed" with "00:00 left" and read "12335.99members/s".
    clock = iter(np.arange(0.0, 1000.0, 1.5)).__next__
    stream = io.StringIO()
    p = cli_progress.Progress("run", 100.0, " s", stream=stream, clock=clock)
    with p.compiling():
        pass
    for t in range(5, 101, 5):
        p.update(t)
    lines = stream.getvalue().splitlines()
    assert lines[:2] == ["run: compiling", "run: compiled in 1.5 s"]
    percent = [int(line.split("%")[0].split()[-1]) for line in lines[2:]]
    clocks = [re.search(r"\[(\d\d):(\d\d) elapsed, (\d\d):(\d\d) left, ([\d.]+) s/s\]$", line) for line in lines[2:]]
    assert all(clocks), lines
    elapsed = [60 * int(m[1]) + int(m[2]) for m in clocks]
    left = [60 * int(m[3]) + int(m[4]) for m in clocks]
    assert percent == list(range(10, 101, 10))
    assert all(b > a for a, b in zip(elapsed, elapsed[1:])) and left[-1] == 0 and left[0] > left[-2]
    # The rate with an SI prefix and a space before the unit.
    members = io.StringIO()
    m = cli_progress.Progress(
        "sweep", 20000, "members", stream=members, lines=1, clock=iter([0.0, 1.0, 1.0, 2.0]).__next__
    )
    m.update(20000)
    assert members.getvalue().strip().endswith("20.0k/20.0k members [00:01 elapsed, 00:00 left, 20.0k members/s]"), (
        members.getvalue()
    )
    quiet = io.StringIO()
    q = cli_progress.Progress("run", 1.0, quiet=True, stream=quiet)
    q.update(1.0)
    assert quiet.getvalue() == ""


@pytest.mark.parametrize(
    "argv, status, message",
    [
        ([], 2, "a command is required"),
        (["simulate", "{missing}", "--out", "{out}"], 2, "scene file not found"),
        (["simulate", "{bad_key}", "--out", "{out}"], 2, "unknown key 'colour'"),
        (["simulate", "{bad_toml}", "--out", "{out}"], 2, "not valid TOML"),
        (["simulate", "{scene}", "--out", "{out}", "--t1", "-1"], 2, "--t1 must be a positive"),
        (["simulate", "{scene}", "--out", "{out}", "--frames", "0"], 2, "--frames must be a positive integer"),
        (["simulate", "{too_few_steps}", "--out", "{out}", "--quiet"], 1, "max_steps was reached"),
        (["sweep", "{scene}", "--out", "{out}", "--omega-x", "1:0:5"], 2, "START must be < STOP"),
        (["sweep", "{scene}", "--out", "{out}", "--omega-y", "0:1:x"], 2, "START:STOP:N"),
        (["sweep", "{scene}", "--out", "{out}", "--omega-x", "1"], 2, "nothing to sweep"),
        (
            ["sweep", "{scene}", "--out", "{out}", "--omega-x", "0:1:2", "--omega-y", "0:1:2", "--omega-z", "0:1:2"],
            2,
            "at most two",
        ),
        (["frobnicate"], 2, "invalid choice"),
        (["simulate", "{scene}", "--out", "{out}", "--target-error", "0"], 2, "--target-error must be a positive"),
        (["simulate", "{scene}", "--out", "{out}", "--target-error", "nan"], 2, "--target-error must be a positive"),
        (["simulate", "{bad_target}", "--out", "{out}"], 2, "run.target_error must be > 0"),
        (
            ["simulate", "{unreachable}", "--out", "{out}", "--quiet", "--no-gif"],
            1,
            "target_error = 1e-30 was not reached",
        ),
        (
            ["sweep", "{target}", "--out", "{out}", "--omega-y", "0:0.1:2"],
            2,
            "sweep needs a scene with run.dt or run.rtol",
        ),
        # These used to end in tracebacks (OverflowError) or run for ever.
        (["simulate", "{tiny_dt}", "--out", "{out}"], 2, "is inf steps, more than a run may take"),
        (["simulate", "{huge_t1}", "--out", "{out}"], 2, "is 1e+302 steps, more than a run may take"),
        (["simulate", "{scene}", "--out", "{out}", "--t1", "1e300"], 2, "is 1e+302 steps, more than a run may take"),
        (
            ["sweep", "{scene}", "--out", "{out}", "--t1", "1e300", "--omega-y", "0:0.1:2"],
            2,
            "more than a run may take",
        ),
        (["simulate", "{huge_t1_adaptive}", "--out", "{out}", "--float32"], 2, "outside single precision's range"),
        # Used to exit 0 with six NumPy warnings and "|L|: nan".
        (
            ["simulate", "{huge_inertia}", "--out", "{out}"],
            2,
            "body: body.inertia = [1.e+300, 1.e+300, 1.e+300] kg m^2 with initial.omega = [0.3, 1. , 0.2] rad/s: "
            "det(I), the product of the principal moments, = 1e+900 overflows float64",
        ),
        # Printed as the setting, where lierk.solve refuses it (the same rule).
        (
            ["simulate", "{tiny_rtol}", "--out", "{out}"],
            2,
            "run.rtol = 1e-20, run.atol = 1e-20: rtol + atol = 2e-20 is below the rounding of float64 (eps = 2.2e-16)",
        ),
        (["simulate", "{small_rtol}", "--out", "{out}", "--float32"], 2, "is below the rounding of float32"),
        # Used to fail after the whole run, with OSError: File name too long.
        (["simulate", "{long_name}", "--out", "{out}"], 2, "name: the outputs are named after it"),
        (["simulate", "{scene}", "--out", "{a_file}"], 2, "exists and is not a directory"),
        (["simulate", "{scene}", "--out", "{below_a_file}"], 2, "is not a directory"),
        (["simulate", "{scene_dir}", "--out", "{out}"], 2, "scene file is a directory"),
    ],
)
def test_mistakes_end_in_one_line(tmp_path, capsys, argv, status, message):
    files = {
        "missing": tmp_path / "missing.toml",
        "bad_key": write(tmp_path, TEE_SCENE.replace("[body]", "colour = 'red'\n[body]"), "bad_key.toml"),
        "bad_toml": write(tmp_path, "[body\n", "bad.toml"),
        "scene": write(tmp_path, TEE_SCENE),
        "too_few_steps": write(tmp_path, ADAPTIVE_SCENE.replace("n_save = 41", "max_steps = 2"), "few.toml"),
        "bad_target": write(
            tmp_path,
            TEE_SCENE.replace("dt = 0.01", "target_error = -1e-8").replace("save_every = 2", ""),
            "bad_target.toml",
        ),
        "target": write(
            tmp_path, TEE_SCENE.replace("dt = 0.01", "target_error = 1e-8").replace("save_every = 2", ""), "target.toml"
        ),
        "unreachable": write(
            tmp_path, SMALL_TARGET_SCENE.replace("target_error = 1e-10", "target_error = 1e-30"), "unreachable.toml"
        ),
        "tiny_dt": write(tmp_path, TEE_SCENE.replace("dt = 0.01", "dt = 1e-320"), "tiny_dt.toml"),
        "huge_t1": write(tmp_path, TEE_SCENE.replace("t1 = 100.0", "t1 = 1e300"), "huge_t1.toml"),
        # (rtol 1e-6: float32 cannot meet the scene's 1e-10, which is refused first.)
        "huge_t1_adaptive": write(
            tmp_path, ADAPTIVE_SCENE.replace("t1 = 2.0", "t1 = 1e300").replace("1e-10", "1e-6"), "huge_adaptive.toml"
        ),
        "huge_inertia": write(
            tmp_path, ADAPTIVE_SCENE.replace("[1.0, 2.0, 3.0]", "[1e300, 1e300, 1e300]"), "huge_inertia.toml"
        ),
        "tiny_rtol": write(tmp_path, ADAPTIVE_SCENE.replace("rtol = 1e-10", "rtol = 1e-20"), "tiny_rtol.toml"),
        "small_rtol": write(tmp_path, ADAPTIVE_SCENE.replace("rtol = 1e-10", "rtol = 1e-8"), "small_rtol.toml"),
        "long_name": write(tmp_path, TEE_SCENE.replace('"tee test"', '"' + "x" * 400 + '"'), "long_name.toml"),
        "a_file": write(tmp_path, "", "a_file"),
        "below_a_file": tmp_path / "a_file" / "out",
        "scene_dir": tmp_path,
        "out": tmp_path / "out",
    }
    argv = [a.format(**files) for a in argv]
    code, out, err = run_inprocess(argv, capsys)
    assert code == status
    assert len(err.strip().splitlines()) == 1, err
    assert message in err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()
    assert not list(tmp_path.glob(".*partial"))


def test_out_that_is_a_file_fails_before_anything_runs(tmp_path, capsys, monkeypatch):
    # It used to be found only when writing, after the whole integration.
    monkeypatch.setattr(lierk.app.scene.Scene, "solve", lambda *a, **k: pytest.fail("integrated before checking --out"))
    monkeypatch.setattr(lierk.app.scene, "load", lambda *a, **k: pytest.fail("loaded before checking --out"))
    target = write(tmp_path, "old contents", "results")
    code, out, err = run_inprocess(["simulate", write(tmp_path, TEE_SCENE), "--out", target], capsys)
    assert code == 2 and err == f"lierk simulate: error: --out {target} exists and is not a directory\n"
    assert target.read_text() == "old contents"


def test_a_run_that_fails_while_writing_leaves_the_old_outputs(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    names = ["tee_test.npz", "tee_test_components.png", "tee_test_euler.png", "tee_test_invariants.png"]
    for n in names:
        (out / n).write_bytes(b"old " + n.encode())
    (out / "unrelated.txt").write_text("kept")

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    # The .npz and the first figure are written by then: they used to replace the old ones.
    monkeypatch.setattr(plot, "euler_angles", disk_full)
    argv = ["simulate", write(tmp_path, TEE_SCENE), "--out", out, "--t1", "0.05", "--no-gif", "--quiet"]
    code, stdout, err = run_inprocess(argv, capsys)
    assert code == 1 and err.strip().splitlines() == ["lierk simulate: error: [Errno 28] No space left on device"]
    for n in names:
        assert (out / n).read_bytes() == b"old " + n.encode()
    assert sorted(p.name for p in out.iterdir()) == sorted([*names, "unrelated.txt"])
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # nor beside it

    # A failure under a --out that did not exist leaves nothing behind either.
    fresh = tmp_path / "new" / "deeper"
    code, stdout, err = run_inprocess([*argv[:3], fresh, *argv[4:]], capsys)
    assert code == 1 and not (tmp_path / "new").exists()


def test_unexpected_exceptions_are_one_line(tmp_path, capsys, monkeypatch):
    def bug(*args, **kwargs):
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(lierk.app.scene.Scene, "solve", bug)
    code, out, err = run_inprocess(["simulate", write(tmp_path, TEE_SCENE), "--out", tmp_path / "out"], capsys)
    assert code == 1
    assert err.splitlines() == [
        "lierk simulate: error: ZeroDivisionError: float division by zero (unexpected; please report it)"
    ]


def test_a_step_longer_than_the_run_is_one_step(tmp_path, capsys):
    # dt = 1e12 > t1 used to end in an AttributeError traceback.
    text = TEE_SCENE.replace("dt = 0.01", "dt = 1e12").replace("t1 = 100.0", "t1 = 0.5")
    out = tmp_path / "out"
    code, stdout, err = run_inprocess(["simulate", write(tmp_path, text), "--out", out, "--no-gif", "--quiet"], capsys)
    assert code == 0, err
    data = _npz(out / "tee_test.npz")
    np.testing.assert_array_equal(data["ts"], [0.0, 0.5])
    assert "1 steps" in stdout


@pytest.mark.parametrize("letter, flips", [("a", True), ("b", False), ("c", False)])
def test_flip_interval_only_for_scenes_that_flip(tmp_path, capsys, letter, flips):
    # tee_handle_b and _c spin near the smallest and largest axes ("stable"):
    # they used to print a finite flip interval.
    argv = [
        "simulate",
        EXAMPLES / f"tee_handle_{letter}.toml",
        "--out",
        tmp_path,
        "--t1",
        "0.02",
        "--chunks",
        "1",
        "--no-gif",
        "--quiet",
    ]
    code, out, err = run_inprocess(argv, capsys)
    assert code == 0, err
    assert ("intermediate-axis flip interval (exact): 23.631 s" in out) == flips
    assert ("no flip of the intermediate axis" in out) == (not flips)


def test_explicit_euler_on_an_impossible_asymmetric_body(tmp_path, capsys):
    """Two findings, one run: ExplicitEuler on an asymmetric body exited 1
    ("dense output and events need a Lie-group solver": the flip event is
    added for such bodies); the triangle-inequality warning was printed three
    times.  Now: one warning, and the report says flips are not tracked."""
    text = ADAPTIVE_SCENE.replace("[1.0, 2.0, 3.0]", "[0.5, 0.6, 1.5]")
    text = text.replace('solver = "DP54"\nrtol = 1e-10', 'solver = "ExplicitEuler"\ndt = 0.01')
    text = text.replace("t1 = 2.0\nn_save = 41", "t1 = 0.1")
    argv = ["simulate", write(tmp_path, text), "--out", tmp_path / "out", "--no-gif", "--quiet", "--no-cache"]
    code, out, err = run_inprocess(argv, capsys)
    assert code == 0, err
    assert [line for line in err.splitlines() if "warning" in line] == [
        "lierk simulate: warning: body.inertia [0.5, 0.6, 1.5] breaks the triangle inequality I_max <= I_a + I_b: "
        "no rigid body has these principal moments; the equations are solved as given"
    ]
    assert "  flips not tracked with ExplicitEuler: ExplicitEuler leaves SO(3)" in out
    assert "event_flip" not in _npz(tmp_path / "out" / "adaptive.npz")


def test_console_script_errors_without_traceback(tmp_path):
    bad = write(tmp_path, TEE_SCENE.replace("omega = [1.0, 0.05, 0.3]", "omega = [1.0, 0.05]"))
    code, out, err = run_subprocess(["simulate", bad, "--out", tmp_path / "out"])
    assert code == 2
    assert err.count("\n") == 1 and "initial.omega" in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        ([], ["simulate", "sweep", "accuracy"]),
        (
            ["simulate"],
            [
                "SCENE.toml",
                "--out",
                "--t1",
                "--quiet",
                "--devices",
                ".gif",
                "--target-error",
                "body angular momentum m = I omega",
                "with or without effects",
            ],
        ),
        (["accuracy"], ["SCENE.toml", "--out", "--solvers", "--max-settings", "--quick", "work_precision.png"]),
        (["sweep"], ["--omega-x", "START:STOP:N", "--grid", "--span", "flip interval", "--chunk-size"]),
    ],
)
def test_help(capsys, argv, words):
    code, out, err = run_inprocess([*argv, "--help"], capsys)
    assert code == 0
    out = " ".join(out.split())  # argparse wraps lines
    for w in words:
        assert w in out


@pytest.mark.parametrize("before", [True, False])
def test_common_options_before_or_after_the_command(tmp_path, before):
    # The README's "lierk --devices 2 ..." used to be rejected.
    common = ["--devices", "2", "--float32", "--quiet"]
    cmd = ["simulate", "s.toml", "--out", "o"]
    args = cli.build_parser().parse_args(common + cmd if before else cmd + common)
    assert (args.devices, args.float32, args.quiet) == (2, True, True)
    args = cli.build_parser().parse_args(cmd)
    assert (args.devices, args.float32, args.quiet) == (None, False, False)


def test_devices_before_the_command_takes_effect(tmp_path):
    scene = write(tmp_path, TEE_SCENE)
    code = (
        "import sys; from lierk.app import cli; "
        f"status = cli.main(['--devices', '2', 'simulate', {str(scene)!r}, '--out', {str(tmp_path / 'out')!r}, "
        "'--t1', '0.02', '--no-gif', '--quiet']); "
        "import jax; print('devices', jax.device_count()); sys.exit(status)"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert "devices 2" in p.stdout


def test_devices_after_jax_started_with_another_count_is_refused(tmp_path):
    # JAX reads XLA_FLAGS when it starts: a process that computed before
    # keeps its one CPU device, and --devices 2 would silently not apply.
    scene = write(tmp_path, TEE_SCENE)
    code = (
        "import os, jax, numpy; jax.device_put(numpy.ones(1)); from lierk.app import cli; "
        f"status = cli.main(['--devices', '2', 'simulate', {str(scene)!r}, '--out', {str(tmp_path / 'out')!r}, "
        "'--quiet']); print('flags left', os.environ.get('XLA_FLAGS')); raise SystemExit(status)"
    )
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=env)
    assert p.returncode == 2, p.stderr
    assert "--devices 2 must be set before JAX starts; it already runs with 1 CPU devices" in p.stderr, p.stderr
    assert not (tmp_path / "out").exists() and "flags left None" in p.stdout  # the environment as it was


# ---------------------------------------------------------------------------
# simulate


def _npz(path):
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def test_without_out_a_command_writes_to_out_and_the_scene_files_name(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    scene_path = write(tmp_path, TEE_SCENE, "spinning_tee.toml")
    code, stdout, stderr = run_inprocess(["simulate", scene_path, "--t1", "0.2", "--no-gif", "--quiet"], capsys)
    assert code == 0, stderr
    out = Path("out") / "spinning_tee"
    assert (tmp_path / out / "tee_test.npz").exists()
    assert f"  {out / 'tee_test.npz'}" in stdout


def test_simulate_matches_a_direct_solve(tmp_path):
    scene_path = write(tmp_path, TEE_SCENE)
    out = tmp_path / "out"
    code, stdout, stderr = run_subprocess(
        ["simulate", scene_path, "--out", out, "--t1", "0.5", "--chunks", "3", "--frames", "4"]
    )
    assert code == 0, stderr
    assert (
        "compiled in" in stderr and "t: 100% 0.50/0.50 s" in stderr and "Traceback" not in stderr
    )  # progress, not quiet

    scene = lierk.app.scene.load(scene_path)
    import dataclasses

    direct = dataclasses.replace(scene, t1=0.5).solve()
    data = _npz(out / "tee_test.npz")
    np.testing.assert_allclose(data["ts"], direct.ts, rtol=0, atol=1e-12)
    # Chunks restart from the previous end state on the same step grid: the
    # same steps up to round-off.
    np.testing.assert_allclose(data["R"], direct.R, rtol=0, atol=1e-13)
    np.testing.assert_allclose(data["L"], np.broadcast_to(scene.problem.L, data["L"].shape), atol=1e-15)
    np.testing.assert_allclose(data["omega0"], [1.0, 0.05, 0.3], atol=1e-14)
    assert str(data["solver"]) == "RKMK4"
    e = data["invariant_energy"]
    assert abs(e - e[0]).max() / e[0] < 1e-10

    sizes = {"components": (900, 700), "euler": (800, 650), "invariants": (1000, 450)}
    for what, size in sizes.items():
        path = out / f"tee_test_{what}.png"
        assert str(path) in stdout
        with Image.open(path) as im:
            assert im.format == "PNG" and im.size == size
    with Image.open(out / "tee_test.gif") as im:
        assert im.n_frames == 4 and im.size == tuple(int(s * plot.GIF_DPI) for s in plot.GIF_SIZE)
    assert "max relative change of energy" in stdout and "flip interval" in stdout
    assert not [p for d in (tmp_path, out) for p in d.iterdir() if p.name.startswith(".")]  # no staging left


@pytest.mark.parametrize("text, atol", [(DAMPED_SCENE, 1e-13), (ADAPTIVE_SCENE, 1e-8)])
def test_simulate_with_state_and_adaptive_steps(tmp_path, capsys, text, atol):
    scene_path = write(tmp_path, text)
    out = tmp_path / "out"
    argv = ["simulate", scene_path, "--out", out, "--quiet", "--no-gif", "--chunks", "4"]
    code, stdout, stderr = run_inprocess(argv, capsys)
    assert code == 0, stderr
    assert stderr == ""  # --quiet
    scene = lierk.app.scene.load(scene_path)
    direct = scene.solve()
    (npz,) = out.glob("*.npz")
    data = _npz(npz)
    np.testing.assert_allclose(data["ts"], direct.ts, rtol=0, atol=1e-12)
    # Adaptive chunks restart the step-size control, so they agree to the tolerance only.
    np.testing.assert_allclose(data["R"], direct.R, rtol=0, atol=atol)
    if direct.y is not None:
        np.testing.assert_allclose(data["y"], direct.y, rtol=0, atol=atol * 1e-3)
    # y is the body momentum, as simulate --help says.
    np.testing.assert_allclose(data["y"], data["omega"] @ data["inertia"].T, rtol=1e-12, atol=0)
    assert not list(out.glob("*.gif"))


def _exact_errors(data):
    """``||R(t) - R_exact(t)||_F`` at each saved time of a simulate .npz."""
    R_exact = np.stack(
        [np.asarray(lierk.exact.free_rigid_body(data["inertia"], data["omega0"], t, data["R0"])[0]) for t in data["ts"]]
    )
    return np.linalg.norm(data["R"] - R_exact, axis=(-2, -1))


@pytest.mark.parametrize("solver, eps", [("RKMK4", 1e-9), ("DOP853", 1e-7)])
def test_simulate_target_error_meets_it_against_the_exact_solution(tmp_path, capsys, solver, eps):
    # A fixed-step scene turned into a target_error run by the option: its
    # dt is replaced, and it saves as many points as it did (5, 0.5 s apart).
    text = TEE_SCENE.replace("RKMK4", solver).replace("t1 = 100.0", "t1 = 2.0").replace("dt = 0.01", "dt = 0.5")
    scene_path = write(tmp_path, text.replace("save_every = 2", "save_every = 1"))
    out = tmp_path / "out"
    argv = ["simulate", scene_path, "--out", out, "--target-error", eps, "--quiet", "--no-gif"]
    code, stdout, stderr = run_inprocess(argv, capsys)
    assert code == 0, stderr
    data = _npz(out / "tee_test.npz")
    np.testing.assert_allclose(data["ts"], np.linspace(0.0, 2.0, 5), atol=1e-14)
    err = _exact_errors(data)
    assert err.max() <= eps, err
    assert err[-1] > eps / 1e4  # the target was used: not a needlessly tiny step
    est = data["error_estimate"]
    assert est.max() <= eps and est[-1] > 0
    setting = "dt = " if solver == "RKMK4" else "rtol = atol = "
    assert f"target_error = {eps:g} (chose {setting}" in stdout
    assert f"estimated error at t1 {est[-1]:.2e}" in stdout


def test_simulate_target_error_keeps_the_events(tmp_path, capsys):
    """--target-error with events: the setting is chosen without them, then
    one more solve at that setting finds them.  The flip (added for a body
    with an intermediate axis) against the closed form's; a terminating
    scene event ends the saved run there; the states meet the target."""
    text = TEE_SCENE.replace("t1 = 100.0", "t1 = 30.0").replace("omega = [1.0, 0.05, 0.3]", "omega = [1.0, 0.05, 0.0]")
    eps = 1e-8
    out = tmp_path / "out"
    argv = ["simulate", write(tmp_path, text), "--out", out, "--target-error", eps, "--quiet", "--no-gif"]
    code, stdout, stderr = run_inprocess(argv, capsys)
    assert code == 0, stderr
    data = _npz(out / "tee_test.npz")
    inertia, w0 = data["inertia"], data["omega0"]
    first = float(lierk.exact.flip_interval(inertia, w0)) / 2  # from omega_z = 0, the first flip at half the interval
    np.testing.assert_allclose(data["event_flip"], [first], atol=1e-7)
    assert "  event flip: 1 at t = " in stdout and "events found by one more solve" in stdout
    assert _exact_errors(data).max() <= eps
    # A flip event that ends the run: the saved times stop before it.
    stop = text + '\n[[events]]\nkind = "flip"\nterminate = true\n'
    code, stdout, stderr = run_inprocess(
        ["simulate", write(tmp_path, stop), "--out", out, "--target-error", eps, "--quiet", "--no-gif"], capsys
    )
    assert code == 0, stderr
    data = _npz(out / "tee_test.npz")
    np.testing.assert_allclose(data["event_flip"], [first], atol=1e-7)
    spacing = 30.0 / 1500  # as many saved times as the dt run's 3000 steps, saving every 2nd
    assert first - spacing < data["ts"][-1] <= first, data["ts"][-1]
    assert f"the run ended at the flip event, t = {data['event_flip'][0]:.9g} s" in stdout
    assert _exact_errors(data).max() <= eps and np.isfinite(data["error_estimate"]).all()


def test_simulate_target_error_with_dense_saved_times(tmp_path, capsys):
    text = SMALL_TARGET_SCENE.replace("n_save = 5", "n_save = 41")  # 0.05 s apart
    out = tmp_path / "out"
    code, stdout, stderr = run_inprocess(
        ["simulate", write(tmp_path, text), "--out", out, "--quiet", "--no-gif"], capsys
    )
    assert code == 0, stderr
    data = _npz(out / "small_target.npz")
    assert _exact_errors(data).max() <= 1e-10


def test_simulate_target_error_scene_with_chunks_is_one_solve(tmp_path, capsys):
    # --chunks does not split a target_error run: the output is scene.solve()'s.
    scene_path = write(tmp_path, SMALL_TARGET_SCENE)
    out = tmp_path / "out"
    code, stdout, stderr = run_inprocess(["simulate", scene_path, "--out", out, "--chunks", "4", "--no-gif"], capsys)
    assert code == 0, stderr
    assert "100%" in stderr
    direct = lierk.app.scene.load(scene_path).solve()
    data = _npz(out / "small_target.npz")
    np.testing.assert_array_equal(data["ts"], direct.ts)
    np.testing.assert_allclose(data["R"], direct.R, rtol=0, atol=1e-15)
    np.testing.assert_allclose(data["error_estimate"], direct.error_estimate, rtol=0, atol=1e-18)


# ---------------------------------------------------------------------------
# sweep


def _final_R(omega0, t1=1.0):
    problem = lierk.FreeRigidBody(lierk.inertia.tee_handle(), omega0)
    return np.asarray(lierk.solve(problem, lierk.RKMK4(), t1, dt=0.01).R[-1])


def test_sweep_on_two_devices_matches_exact_and_finite_differences(tmp_path):
    scene_path = write(tmp_path, TEE_SCENE)
    out = tmp_path / "out"
    argv = ["sweep", scene_path, "--out", out, "--t1", "1", "--omega-y", "-0.1:0.1:3", "--omega-z", "0:0.2:2"]
    code, stdout, stderr = run_subprocess([*argv, "--devices", "2", "--quiet", "--chunk-size", "4"])
    assert code == 0, stderr
    assert stderr == ""
    data = _npz(out / "tee_test_sweep.npz")
    np.testing.assert_allclose(data["omega0_y"], [-0.1, 0.0, 0.1])
    np.testing.assert_allclose(data["omega0_z"], [0.0, 0.2])
    grid = data["omega0"]
    assert grid.shape == (3, 2, 3) and np.all(grid[..., 0] == 1.0)

    inertia = lierk.inertia.tee_handle()
    flip = np.vectorize(lambda y, z: float(lierk.exact.flip_interval(inertia, np.array([1.0, y, z]))))
    np.testing.assert_allclose(data["flip_interval"], flip(grid[..., 1], grid[..., 2]), rtol=1e-12)

    i, j = 2, 1
    w = grid[i, j]
    R = _final_R(w)
    assert data["angle"][i, j] == pytest.approx(np.linalg.norm(lierk.so3.log(R)), rel=1e-10)
    h = 1e-6
    J = np.stack([(_final_R(w + h * e) - _final_R(w - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    assert data["sensitivity"][i, j] == pytest.approx(np.linalg.norm(J), rel=1e-6)
    # The Jacobian's error estimate is its error against the exact flow's
    # Jacobian (within the bounds lierk.sensitivity promises), and the
    # Lyapunov exponent is read from the same Jacobian.
    J_exact = np.asarray(jax.jacfwd(lambda v: lierk.exact.free_rigid_body(inertia, v, 1.0)[0])(jnp.asarray(w)))
    J_solve = lierk.sensitivity(lierk.FreeRigidBody(inertia, w), lierk.RKMK4(), 1.0, dt=0.01, estimate_error=False)
    true = np.linalg.norm(np.asarray(J_solve.jacobian_R) - J_exact)
    assert true / 10 <= data["sensitivity_error"][i, j] <= 100 * true
    # The finite-time Lyapunov exponent: of the attitude's and the body
    # angular velocity's Jacobians, by central differences.
    J_alg = np.einsum("ji,jkl->ikl", R, J)[[2, 0, 1], [1, 2, 0]]

    def final_omega(v):
        problem = lierk.FreeRigidBody(inertia, v)
        return np.linalg.solve(inertia, np.asarray(lierk.solve(problem, lierk.RKMK4(), 1.0, dt=0.01).y[-1]))

    J_omega = np.stack([(final_omega(w + h * e) - final_omega(w - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    state = np.vstack([np.linalg.norm(w) * J_alg, J_omega])
    lam = np.log(np.linalg.svd(state, compute_uv=False)[0]) / 1.0
    assert data["lyapunov"][i, j] == pytest.approx(lam, rel=1e-6)

    with Image.open(out / "tee_test_sweep.png") as im:
        assert im.size == (1840, 460)  # four 4.6 x 4.6 inch panels at 100 dpi


def test_sweep_along_one_component_and_default_grid(tmp_path, capsys):
    scene_path = write(tmp_path, TEE_SCENE)
    out = tmp_path / "out"
    code, stdout, stderr = run_inprocess(
        ["sweep", scene_path, "--out", out, "--t1", "0.2", "--omega-z", "-0.3:0.3:4", "--quiet"], capsys
    )
    assert code == 0, stderr
    data = _npz(out / "tee_test_sweep.npz")
    assert data["angle"].shape == (4,)
    np.testing.assert_allclose(data["omega0"][:, :2], np.broadcast_to([1.0, 0.05], (4, 2)), atol=1e-14)
    with Image.open(out / "tee_test_sweep.png") as im:
        assert im.size == (700, 1040)  # four stacked line plots

    # --grid N varies the two smallest components of omega0 over +-span.
    code, stdout, stderr = run_inprocess(
        ["sweep", scene_path, "--out", out, "--t1", "0.2", "--grid", "3", "--span", "0.1", "--quiet"], capsys
    )
    assert code == 0, stderr
    data = _npz(out / "tee_test_sweep.npz")
    np.testing.assert_allclose(data["omega0_y"], [-0.05, 0.05, 0.15], atol=1e-14)
    np.testing.assert_allclose(data["omega0_z"], [0.2, 0.3, 0.4], atol=1e-14)


def test_simulate_shows_top_angles_and_flips(tmp_path, capsys, monkeypatch):
    seen = {}
    real_euler, real_components = plot.euler_angles, plot.components

    def euler(sol, title=None, **kw):
        seen.setdefault("convention", []).append(kw.get("convention"))
        return real_euler(sol, title, **kw)

    def components(sol, title=None, **kw):
        seen.setdefault("events", []).append(kw.get("events"))
        return real_components(sol, title, **kw)

    monkeypatch.setattr(plot, "euler_angles", euler)
    monkeypatch.setattr(plot, "components", components)
    for name, t1 in (("heavy_top", "0.05"), ("tee_handle_a", "50")):
        code, _, stderr = run_inprocess(
            ["simulate", EXAMPLES / f"{name}.toml", "--out", tmp_path / name, "--t1", t1, "--no-gif", "--quiet"], capsys
        )
        assert code == 0, stderr
    assert seen["convention"] == ["zxz", "zyx"]
    flip = float(lierk.exact.flip_interval(lierk.inertia.tee_handle(), [1.0, 0.05, 0.0]))
    # The symmetric top has no intermediate axis: no flip event.
    assert seen["events"][0] == {}
    # Starting on the intermediate axis, the first flip is half an interval in;
    # R11 = m_x/|m| crosses 0 there (measured 11.8 s) and every interval after.
    # The flip event finds them to the solve's accuracy (RKMK4, dt = 0.01 s: 1e-10 s).
    flips = np.asarray(seen["events"][1]["flip"])
    assert len(flips) == 2 and 0.4 * flip < flips[0] < 0.6 * flip
    np.testing.assert_allclose(np.diff(flips), flip, rtol=1e-9)
