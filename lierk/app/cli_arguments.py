"""The command line's arguments: the parser of ``lierk`` and its commands,
and the types that check each value (`parse_range`, positive numbers, solver
names) with a one-line message naming the option.

`lierk.app.cli` runs the commands; this module only says what they accept.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

__all__ = ["build_parser", "parse", "parse_range", "version"]

_OUT_HELP = (
    "output directory (default: out/ and the scene file's name without .toml, e.g. out/tee_handle_a; "
    "created if missing); the files are moved into it only when all are written"
)


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        # argparse's default prints the whole usage first; one line is enough,
        # --help has the rest.
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _positive(name, kind=float):
    """An argparse type for a positive finite number (``kind=float``) or a
    positive integer (``kind=int``), with a one-line message naming the option."""
    what = "integer" if kind is int else "finite number"

    def parse(s):
        try:
            x = kind(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a positive {what}, got {s!r}") from None
        if not (x > 0 and math.isfinite(x)):
            raise argparse.ArgumentTypeError(f"{name} must be a positive {what}, got {s!r}")
        return x

    return parse


def parse_range(s: str) -> tuple[float, float, int]:
    """``"A:B:N"`` -> N values from A to B (both included); ``"V"`` -> the single value V."""
    parts = s.split(":")
    try:
        if len(parts) == 1:
            v = float(parts[0])
            lo, hi, n = v, v, 1
        elif len(parts) == 3:
            lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
        else:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP:N (e.g. -0.2:0.2:21) or one value, got {s!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise argparse.ArgumentTypeError(f"range ends must be finite, got {s!r}")
    if n < 1:
        raise argparse.ArgumentTypeError(f"the number of values N must be >= 1, got {s!r}")
    if n > 1 and not lo < hi:
        raise argparse.ArgumentTypeError(f"START must be < STOP when N > 1, got {s!r}")
    return lo, hi, n


def _solver_list(s: str) -> list[str]:
    from .accuracy import method

    try:
        return [method(part.strip()).name for part in s.split(",")]
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def version() -> str:
    """The installed lierk's version, or ``"unknown"`` (run from a source tree)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lierk")
    except PackageNotFoundError:
        return "unknown"


def _add_common(parser: argparse.ArgumentParser, default) -> None:
    """The options every command takes.  The top-level parser gives them their
    defaults; the commands' copies default to ``argparse.SUPPRESS``, so an
    option given before the command is not reset by the command's parser."""
    g = parser.add_argument_group("precision and devices (before or after the command)")
    g.add_argument("--float32", action="store_true", default=default(False), help="single precision (default: double)")
    g.add_argument(
        "--devices",
        type=_positive("--devices", int),
        default=default(None),
        metavar="N",
        help="split the CPU into N XLA devices (sets XLA_FLAGS=--xla_force_host_platform_device_count=N); "
        "sweeps are sharded across devices",
    )
    g.add_argument("--quiet", action="store_true", default=default(False), help="no progress bar on stderr")
    g.add_argument(
        "--no-cache",
        action="store_true",
        default=default(False),
        help="compile everything afresh and keep nothing (default: compiled programs are kept in the user's cache "
        "directory, or $LIERK_CACHE_DIR, and reused by later runs; LIERK_NO_CACHE=1 also turns this off)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``lierk``: the options every command takes, and one
    subparser per command (``args.command``: ``"simulate"``, ``"sweep"``,
    ``"accuracy"``, ``"schema"``, or None when none is given)."""
    common = argparse.ArgumentParser(add_help=False)
    _add_common(common, lambda value: argparse.SUPPRESS)

    parser = _Parser(
        prog="lierk",
        description="Rigid-body rotation with Lie-group Runge-Kutta integrators. "
        "Scenes are TOML files (see examples/; 'lierk schema' prints their format as JSON Schema).",
        epilog="Run 'lierk COMMAND --help' for the options of one command.",
    )
    _add_common(parser, lambda value: value)
    parser.add_argument("--version", action="version", version=f"lierk {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for add in (_add_simulate, _add_sweep, _add_accuracy, _add_schema):
        add(sub, common)
    return parser


def _command(sub, common, name: str) -> argparse.ArgumentParser:
    """The parser of one command, with its texts (`_TEXTS`) and the scene
    file and ``--out`` every command takes (`default_out` when not given)."""
    parser = sub.add_parser(name, parents=[common], **_TEXTS[name])
    parser.add_argument("scene", type=Path, metavar="SCENE.toml", help="scene file")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR", help=_OUT_HELP)
    return parser


def default_out(scene: Path) -> Path:
    """Where a command writes without ``--out``: ``out/<the scene file's
    stem>`` in the working directory (``out/tee_handle_a`` for
    ``examples/tee_handle_a.toml``)."""
    return Path("out") / Path(scene).stem


def _t1(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--t1", type=_positive("--t1"), metavar="T", help="end time in s (overrides [run] t1)")


# The commands' texts.  argparse joins the lines of a description or an
# epilog and wraps them to the terminal's width.

_SIMULATE = """
    Integrate SCENE.toml with the solver and step given in its [run] table, in chunks with a progress bar,
    then write to DIR: <name>.npz (ts; R, the attitude, body -> space; quaternion, its unit quaternion
    (w, x, y, z), w >= 0; y, the state besides R, which for every scene, with or without effects, is the
    body angular momentum m = I omega in kg m^2/s; with reaction wheels also wheel_speeds, rad/s relative
    to the body; omega, the body angular velocity; L = R m, the angular momentum in space; the invariants;
    the inertia, omega0, R0 and t1), <name>_components.png (3x3 grid of R(t)), <name>_euler.png (Euler angles),
    <name>_invariants.png (relative drift of the conserved quantities) and <name>.gif (the body turning,
    with its axes and the angular momentum).
"""

_SWEEP = """
    Solve SCENE.toml for a grid of initial body angular velocities omega0 (rad/s), vmapped and sharded
    across devices, and draw for each: the flip interval of the intermediate axis (exact solution,
    torque-free bodies), the final attitude angle |log R(T)| (rad) and the sensitivity ||dR(T)/d omega0||
    (s, forward mode: the variational equations for RKMK and CF4 solvers, the derivative of the solve for
    the splittings). Near the intermediate axis the flip interval diverges and the sensitivity is
    largest. Writes <name>_sweep.png and <name>_sweep.npz to DIR.
"""

_SWEEP_EPILOG = """
    Each component is a range START:STOP:N, a single value, or (if not given) the scene's omega0
    component. Without any --omega-* option, --grid N varies the two smallest components of the scene's
    omega0 over [w - SPAN, w + SPAN].
    example: lierk sweep examples/tee_handle_a.toml --omega-y -0.2:0.2:41 --omega-z -0.2:0.2:41 --out out
"""

_ACCURACY = """
    Solve SCENE.toml's problem with each solver over a range of steps dt (RKMK4, CF4) and tolerances rtol
    (DP54, DOP853, RKF45), each with its own error estimate, and measure the wall time and the true error
    max_t ||R(t) - R_ref(t)||_F at equally spaced times. The reference is the closed form (lierk.exact) for
    a torque-free body, otherwise a tight DOP853 solve cross-checked by DP54. Writes work_precision.png and
    work_precision.json to DIR and prints, per error decade, the cheapest solver and setting. The scene's
    own [run] settings other than t1 are not used.
"""

_SCHEMA = """
    Print the JSON Schema (2020-12) of scene files on stdout (lierk.app.scene_schema), for an editor to
    complete and check them: each key's type, unit, default and allowed values. With Taplo (Even Better
    TOML): lierk schema > scene.schema.json, then '#:schema scene.schema.json' as a scene file's first line.
    The rules across keys (exactly one of dt, rtol or target_error; one torque row per time) are checked
    when a scene is loaded.
"""

_TEXTS = {
    "simulate": {
        "help": "integrate a scene; write the trajectory, figures and an animation",
        "description": _SIMULATE,
        "epilog": "example: lierk simulate examples/tee_handle_a.toml --out out/a",
    },
    "sweep": {
        "help": "sweep a grid of initial angular velocities; write heatmaps",
        "description": _SWEEP,
        "epilog": _SWEEP_EPILOG,
    },
    "accuracy": {
        "help": "work against precision: which solver and setting reach each error, and how fast",
        "description": _ACCURACY,
        "epilog": "example: lierk accuracy examples/heavy_top.toml --out out/accuracy",
    },
    "schema": {
        "help": "print the JSON Schema of scene files, for editors",
        "description": _SCHEMA,
        "epilog": "example: lierk schema > scene.schema.json",
    },
}


def _add_simulate(sub, common) -> None:
    sim = _command(sub, common, "simulate")
    _t1(sim)
    sim.add_argument(
        "--target-error",
        type=_positive("--target-error"),
        metavar="EPS",
        help="the attitude error ||R - R_exact||_F wanted at every saved time, instead of the scene's dt/rtol: "
        "the scene's solver chooses its own step or tolerances (solved in one piece)",
    )
    sim.add_argument(
        "--chunks",
        type=_positive("--chunks", int),
        metavar="K",
        help="integrate in K pieces, reporting progress between them (default 20, lierk.app.scene.Scene.solve's)",
    )
    sim.add_argument(
        "--frames", type=_positive("--frames", int), default=120, metavar="N", help="GIF frames (default 120)"
    )
    sim.add_argument("--fps", type=_positive("--fps", int), default=20, help="GIF frames per second (default 20)")
    sim.add_argument("--no-gif", action="store_true", help="skip the animation (the slowest output)")
    sim.add_argument("--degrees", action="store_true", help="Euler angles in degrees (default rad)")


def _add_sweep(sub, common) -> None:
    sw = _command(sub, common, "sweep")
    for c in "xyz":
        sw.add_argument(f"--omega-{c}", type=parse_range, metavar="START:STOP:N", help=f"values of omega0_{c} in rad/s")
    sw.add_argument(
        "--grid",
        type=_positive("--grid", int),
        default=21,
        metavar="N",
        help="points per varied component when no --omega-* is given (default 21)",
    )
    sw.add_argument(
        "--span",
        type=_positive("--span"),
        metavar="S",
        help="half-width in rad/s of the --grid ranges (default: 0.25 |omega0|)",
    )
    _t1(sw)
    sw.add_argument(
        "--chunk-size",
        type=_positive("--chunk-size", int),
        default=256,
        metavar="K",
        help="grid points per vmapped batch (default 256); each finished batch is written at once to "
        "DIR/<name>_sweep.chunks/, and running the same command again resumes from there",
    )
    g = sw.add_argument_group(
        "several processes (lierk.app.distributed.initialize; none needed under SLURM or Open MPI)"
    )
    g.add_argument("--coordinator-address", metavar="HOST:PORT", help="process 0's address, the same in every process")
    g.add_argument("--num-processes", type=int, metavar="N", help="how many processes take part")
    g.add_argument("--process-id", type=int, metavar="I", help="this process's id, 0 to N - 1")


def _add_accuracy(sub, common) -> None:
    acc = _command(sub, common, "accuracy")
    _t1(acc)
    acc.add_argument(
        "--solvers",
        type=_solver_list,
        metavar="A,B,...",
        help="comma-separated solvers (default: every one that applies: RKMK4, CF4, RKMK(DOPRI54) and "
        "RKMK(DOP853) at fixed steps, DP54, DOP853, RKF45, and under torques the splittings Strang, BlanesMoan4, "
        "BlanesMoan6, BlanesMoanRKN4 and BlanesMoanRKN6 where they apply)",
    )
    acc.add_argument(
        "--max-settings",
        type=_positive("--max-settings", int),
        metavar="N",
        help="at most N steps or tolerances per solver (default 10); fewer is faster",
    )
    acc.add_argument("--quick", action="store_true", help="a faster, coarser run: same as --max-settings 4")


def _add_schema(sub, common) -> None:
    # No scene, no --out and none of the common options: it only prints.
    sub.add_parser("schema", **_TEXTS["schema"])


def _join_negative_ranges(argv: list[str]) -> list[str]:
    """``--omega-y -0.2:0.2:5`` -> ``--omega-y=-0.2:0.2:5``: argparse would
    otherwise take a range starting with a minus sign for an option."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        if a in ("--omega-x", "--omega-y", "--omega-z") and i + 1 < len(argv) and argv[i + 1].startswith("-"):
            out.append(f"{a}={argv[i + 1]}")
            i += 2
        else:
            out.append(a)
            i += 1
    return out


def parse(argv: list[str]) -> argparse.Namespace:
    """The arguments of ``lierk ARGV`` (`build_parser`); a range of omega0
    that starts with a minus sign may follow its option as a word of its own."""
    return build_parser().parse_args(_join_negative_ranges(argv))
