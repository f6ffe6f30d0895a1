"""The ``lierk`` command line.

    lierk simulate SCENE.toml --out DIR      trajectory (.npz), figures and a GIF
    lierk sweep SCENE.toml --out DIR ...     a grid of initial angular velocities
    lierk accuracy SCENE.toml --out DIR      work against precision of the solvers

All run in double precision unless ``--float32`` is given: the command line
is an application and picks its precision itself (the library never touches
JAX's global configuration).  ``--devices N`` splits the CPU into N XLA
devices (``--xla_force_host_platform_device_count``) for sharded sweeps; it
must be set before JAX starts its backend, which is why only the command line
may do it.  These options (and ``--quiet``) may come before or after the
command: ``lierk --devices 2 sweep ...`` and ``lierk sweep ... --devices 2``.

Mistakes in arguments or scene files end with one line on stderr and exit
status 2; a failed integration exits with status 1.  No command prints a
traceback.

Outputs are all or nothing: ``--out`` is checked before anything runs, the
files are written into a temporary directory beside it and moved into it only
when all of them are complete, so a failed run leaves earlier outputs as
they were.  The exception is by design: ``sweep`` writes each finished
chunk at once to ``DIR/<name>_sweep.chunks/`` (`lierk.store.ChunkStore`), so
running the same command again resumes an interrupted sweep; the directory
is removed once the outputs are written.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import math
import os
import re
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path


__all__ = ["main"]

_OUT_HELP = "output directory (created if missing); the files are moved into it only when all are written"


class CLIError(Exception):
    """A user mistake: reported as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        # argparse's default prints the whole usage first; one line is enough,
        # --help has the rest.
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# --------------------------------------------------------------------------
# Arguments


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
    common = argparse.ArgumentParser(add_help=False)
    _add_common(common, lambda value: argparse.SUPPRESS)

    parser = _Parser(
        prog="lierk",
        description="Rigid-body rotation with Lie-group Runge-Kutta integrators. "
        "Scenes are TOML files (see examples/ and lierk.scene for the format).",
        epilog="Run 'lierk COMMAND --help' for the options of one command.",
    )
    _add_common(parser, lambda value: value)
    parser.add_argument("--version", action="version", version=f"lierk {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    sim = sub.add_parser(
        "simulate",
        parents=[common],
        help="integrate a scene; write the trajectory, figures and an animation",
        description="Integrate SCENE.toml with the solver and step given in its [run] table, in chunks with a "
        "progress bar, then write to DIR: <name>.npz (ts; R, the attitude, body -> space; y, the state besides "
        "R, which for every scene, with or without effects, is the body angular momentum m = I omega in "
        "kg m^2/s; omega, the body angular velocity; L = R m, the angular momentum in space; the invariants; "
        "the inertia, omega0, R0 and t1), "
        "<name>_components.png (3x3 grid of R(t)), <name>_euler.png (Euler angles), "
        "<name>_invariants.png (relative drift of the conserved quantities) and "
        "<name>.gif (the body turning, with its axes and the angular momentum).",
        epilog="example: lierk simulate examples/tee_handle_a.toml --out out/a",
    )
    sim.add_argument("scene", type=Path, metavar="SCENE.toml", help="scene file")
    sim.add_argument("--out", type=Path, required=True, metavar="DIR", help=_OUT_HELP)
    sim.add_argument("--t1", type=_positive("--t1"), metavar="T", help="end time in s (overrides [run] t1)")
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
        help="integrate in K pieces, reporting progress between them (default 20, lierk.scene.Scene.solve's)",
    )
    sim.add_argument(
        "--frames", type=_positive("--frames", int), default=120, metavar="N", help="GIF frames (default 120)"
    )
    sim.add_argument("--fps", type=_positive("--fps", int), default=20, help="GIF frames per second (default 20)")
    sim.add_argument("--no-gif", action="store_true", help="skip the animation (the slowest output)")
    sim.add_argument("--degrees", action="store_true", help="Euler angles in degrees (default rad)")

    sw = sub.add_parser(
        "sweep",
        parents=[common],
        help="sweep a grid of initial angular velocities; write heatmaps",
        description="Solve SCENE.toml for a grid of initial body angular velocities omega0 (rad/s), vmapped "
        "and sharded across devices, and draw for each: the flip interval of the intermediate axis (exact "
        "solution, torque-free bodies), the final attitude angle |log R(T)| (rad) and the sensitivity "
        "||dR(T)/d omega0|| (s, forward-mode derivative through the solver). Near the intermediate axis "
        "the flip interval diverges and the sensitivity is largest. Writes <name>_sweep.png and "
        "<name>_sweep.npz to DIR.",
        epilog="Each component is a range START:STOP:N, a single value, or (if not given) the scene's omega0 "
        "component. Without any --omega-* option, --grid N varies the two smallest components of the "
        "scene's omega0 over [w - SPAN, w + SPAN]. "
        "example: lierk sweep examples/tee_handle_a.toml --omega-y -0.2:0.2:41 --omega-z -0.2:0.2:41 --out out",
    )
    sw.add_argument("scene", type=Path, metavar="SCENE.toml", help="scene file")
    sw.add_argument("--out", type=Path, required=True, metavar="DIR", help=_OUT_HELP)
    for c in "xyz":
        sw.add_argument(
            f"--omega-{c}",
            type=parse_range,
            metavar="START:STOP:N",
            help=f"values of omega0_{c} in rad/s",
        )
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
    sw.add_argument("--t1", type=_positive("--t1"), metavar="T", help="end time in s (overrides [run] t1)")
    sw.add_argument(
        "--chunk-size",
        type=_positive("--chunk-size", int),
        default=256,
        metavar="K",
        help="grid points per vmapped batch (default 256); each finished batch is written at once to "
        "DIR/<name>_sweep.chunks/, and running the same command again resumes from there",
    )
    g = sw.add_argument_group("several processes (lierk.distributed.initialize; none needed under SLURM or Open MPI)")
    g.add_argument("--coordinator-address", metavar="HOST:PORT", help="process 0's address, the same in every process")
    g.add_argument("--num-processes", type=int, metavar="N", help="how many processes take part")
    g.add_argument("--process-id", type=int, metavar="I", help="this process's id, 0 to N - 1")

    acc = sub.add_parser(
        "accuracy",
        parents=[common],
        help="work against precision: which solver and setting reach each error, and how fast",
        description="Solve SCENE.toml's problem with each solver over a range of steps dt (RKMK4, CF4) "
        "and tolerances rtol (DP54, DOP853, RKF45), each with its own error estimate, and measure the wall "
        "time and the true error max_t ||R(t) - R_ref(t)||_F at equally spaced times. The reference is the "
        "closed form (lierk.exact) for a torque-free body, otherwise a tight DOP853 solve cross-checked by "
        "DP54. Writes work_precision.png and work_precision.json to DIR and prints, per error decade, the "
        "cheapest solver and setting. The scene's own [run] settings other than t1 are not used.",
        epilog="example: lierk accuracy examples/heavy_top.toml --out out/accuracy",
    )
    acc.add_argument("scene", type=Path, metavar="SCENE.toml", help="scene file")
    acc.add_argument("--out", type=Path, required=True, metavar="DIR", help=_OUT_HELP)
    acc.add_argument("--t1", type=_positive("--t1"), metavar="T", help="end time in s (overrides [run] t1)")
    acc.add_argument(
        "--solvers",
        type=_solver_list,
        metavar="A,B,...",
        help="comma-separated solvers (default: RKMK4,CF4,DP54,DOP853,RKF45)",
    )
    acc.add_argument(
        "--max-settings",
        type=_positive("--max-settings", int),
        metavar="N",
        help="at most N steps or tolerances per solver (default 10); fewer is faster",
    )
    acc.add_argument("--quick", action="store_true", help="a faster, coarser run: same as --max-settings 4")
    return parser


def _solver_list(s: str) -> list[str]:
    from .solvers import solver_class

    try:
        return [solver_class(part.strip()).__name__ for part in s.split(",")]
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lierk")
    except PackageNotFoundError:
        return "unknown"


# --------------------------------------------------------------------------
# Set-up shared by the commands


def _configure(args) -> None:
    """Devices must be settled before JAX computes anything."""
    if args.devices is not None:
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            raise CLIError("--devices must be set before JAX starts; run lierk in a fresh process")
        flags = re.sub(r"--xla_force_host_platform_device_count=\S+", "", os.environ.get("XLA_FLAGS", ""))
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={args.devices}".strip()
    if args.command == "sweep":
        from . import distributed

        try:
            distributed.initialize(args.coordinator_address, args.num_processes, args.process_id)
        except ValueError as e:
            raise CLIError(_one_line(e)) from None


class _CacheUse:
    """What the persistent compilation cache did in this run: the directory
    (None: off), programs loaded and programs compiled and saved, and entries
    JAX could not read or write (each recompiled or left unsaved)."""

    def __init__(self):
        self.path = None
        self.counts = {"hits": 0, "misses": 0, "unreadable": 0, "unwritable": 0}

    def listen(self, event: str, **_) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            self.counts["hits"] += 1
        elif event == "/jax/compilation_cache/cache_misses":
            self.counts["misses"] += 1

    def swallow(self, message) -> bool:
        """Count JAX's warning about one unreadable or unwritable entry
        (a corrupted file, a full disk) instead of printing it."""
        text = str(message)
        for key, start in (("unreadable", "Error reading persistent compilation cache"),
                           ("unwritable", "Error writing persistent compilation cache")):
            if text.startswith(start):
                self.counts[key] += 1
                return True
        return False

    def summary(self) -> str | None:
        if self.path is None:
            return None
        c = self.counts
        line = f"compiled programs: {c['hits']} loaded from the cache, {c['misses']} compiled and saved ({self.path})"
        if c["unreadable"]:
            line += f"; {c['unreadable']} cached programs could not be read and were compiled again"
        if c["unwritable"]:
            line += f"; {c['unwritable']} could not be saved"
        return line


@contextlib.contextmanager
def _use_cache(args, use: _CacheUse):
    """Keep compiled programs between runs (`lierk.cache`), unless turned off,
    for the duration of one command; the settings are restored after it
    (``main`` can be called in a process that goes on).

    The command line owns its process, so, as with ``--devices``, it sets
    process-wide options the library leaves alone.  A directory the user gave
    JAX (``JAX_COMPILATION_CACHE_DIR``) is kept with its own settings;
    otherwise every program is kept, however quickly it compiled: a command's
    many small programs add up to seconds."""
    import jax

    names = ("jax_enable_compilation_cache", "jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    before = {name: getattr(jax.config, name) for name in names}
    listening = False
    try:
        if args.no_cache or os.environ.get("LIERK_NO_CACHE", "") not in ("", "0"):
            jax.config.update("jax_enable_compilation_cache", False)
        elif before["jax_enable_compilation_cache"]:
            from . import cache

            path = before["jax_compilation_cache_dir"]
            if not path:
                path = cache.compilation_cache_dir()  # None (warned once): not writable, run uncached
                if path is not None:
                    jax.config.update("jax_compilation_cache_dir", str(path))
                    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
            if path is not None:
                use.path = str(path)
                jax.monitoring.register_event_listener(use.listen)
                listening = True
        yield
    finally:
        if listening:
            jax.monitoring.unregister_event_listener(use.listen)
        for name, value in before.items():
            if getattr(jax.config, name) != value:
                jax.config.update(name, value)


def _load(args):
    from . import scene as _scene

    if args.scene.is_dir():
        raise CLIError(f"scene file is a directory: {args.scene}")
    if not args.scene.is_file():
        raise CLIError(f"scene file not found: {args.scene}")
    try:
        scene = _scene.load(args.scene)
        if args.t1 is not None:
            scene = scene.with_t1(args.t1)
    except ValueError as e:
        raise CLIError(_one_line(e)) from None
    except OSError as e:
        raise CLIError(f"cannot read the scene file {args.scene}: {e.strerror or e}") from None
    if args.float32:
        try:
            scene.check_single_precision()
        except ValueError as e:
            raise CLIError(f"{e}; drop --float32") from None
    return scene


def _check_out(out: Path) -> None:
    """Fail before anything runs if ``--out`` cannot become a directory."""
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out} exists and is not a directory")
    p = out
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir():
        raise CLIError(f"--out {out}: {p} is not a directory")
    if not os.access(p, os.W_OK | os.X_OK):
        raise CLIError(f"--out {out}: cannot write in {p}")


@contextlib.contextmanager
def _staged_output(out: Path):
    """Yield a temporary directory to write the outputs into.  When the block
    completes, its files are moved into ``out`` (created if missing),
    replacing files of the same names; if it fails, ``out`` is left as it was
    and the temporary directory is removed.

    The temporary directory is on the same file system as ``out``, so the
    moves are renames: inside ``out`` (a hidden ``.lierk-*.partial``) if it
    exists, which `_check_out` found writable, else beside it."""
    out = Path(os.path.realpath(out))
    created = None  # the first directory this call creates, removed on failure
    if out.exists():
        where = out
    else:
        where = out.parent
        p = where
        while not p.exists():
            created, p = p, p.parent
        where.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".lierk-", suffix=".partial", dir=where))
    try:
        yield tmp
        out.mkdir(exist_ok=True)
        for f in sorted(tmp.iterdir()):
            os.replace(f, out / f.name)
    except BaseException:
        if created is not None:
            shutil.rmtree(created, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _one_line(e: BaseException) -> str:
    text = str(e).strip()
    first = text.splitlines()[0] if text else type(e).__name__
    return first


def _run_settings(scene, sol=None) -> str:
    """The scene's run settings; with the `Solution` of a target_error run,
    the step or tolerance it chose too."""
    kw = scene.solve_kwargs
    if "dt" in kw:
        return f"dt = {kw['dt']:g} s"
    if "target_error" in kw:
        text = f"target_error = {kw['target_error']:g}"
        if sol is None:
            return text
        return f"{text} (chose {sol.chosen_setting()})"
    return f"rtol = {kw['rtol']:g}, atol = {kw['atol']:g}"


# --------------------------------------------------------------------------
# simulate


def _key(name: str) -> str:
    name = re.sub(r"\|(\w+)\|", r"abs_\1", name)
    return re.sub(r"\W+", "_", name).strip("_")


def simulate(args) -> int:
    scene = _load(args)
    import numpy as np

    from . import plot
    from .diagnostics import diagnostics
    from .exact import flip_times
    from .segments import N_PIECES
    from .store import check_size

    if args.target_error is not None:
        scene = scene.with_target_error(args.target_error)
    problem, solver = scene.problem, scene.solver
    saved = scene.saved_count() * scene.bytes_per_saved()
    try:
        # The pieces, their concatenation and the derived omega, L and
        # invariants hold about 4 copies of the saved points; the .npz 2.
        check_size(memory=4 * saved, disk=2 * saved, directory=args.out,
                   what=f"simulating {scene.saved_count()} saved points")
    except ValueError as e:
        raise CLIError(_one_line(e)) from None
    start = time.perf_counter()
    sol = scene.solve(n_pieces=args.chunks or N_PIECES, progress=not args.quiet)
    wall = time.perf_counter() - start

    ts, R, y = plot.trajectory(sol)
    diag = diagnostics(problem, sol)
    omega, L, inv, drift, orth = diag.omega, diag.L, diag.invariants, diag.drift, diag.orthogonality

    stem = _key(scene.name) or "scene"
    data = {
        "ts": ts,
        "R": R,
        "omega": omega,
        "L": L,
        "inertia": np.asarray(problem.inertia),
        "omega0": np.asarray(problem.omega0),
        "R0": np.asarray(problem.R0),
        "t1": np.asarray(scene.t1),
        "solver": np.asarray(solver.name),
        "scene": np.asarray(scene.name),
        **{f"invariant_{_key(k)}": v for k, v in inv.items()},
    }
    if y is not None:
        data["y"] = y
    if sol.error_estimate is not None:
        data["error_estimate"] = np.asarray(sol.error_estimate)[: len(ts)]

    settings = f"{solver.name}, {_run_settings(scene, sol)}"
    title = f"{scene.name}: {scene.description}\n{settings}" if scene.description else f"{scene.name} — {settings}"
    with _staged_output(args.out) as tmp:
        npz = tmp / f"{stem}.npz"
        np.savez(npz, **data)
        convention = scene.euler_convention
        flips = flip_times(problem, sol)
        figures = {
            "components": plot.components(sol, title, flips=flips),
            "euler": plot.euler_angles(sol, title, degrees=args.degrees, convention=convention),
            "invariants": plot.invariants(sol, problem, title),
        }
        paths = [npz]
        for what, fig in figures.items():
            path = tmp / f"{stem}_{what}.png"
            fig.savefig(path, dpi=100)
            paths.append(path)
        if not args.no_gif:
            gif = plot.animate(
                sol,
                scene.body_parts,
                tmp / f"{stem}.gif",
                L=L,
                frames=args.frames,
                fps=args.fps,
                title=f"{scene.name} — {settings}",
                inertia=problem.inertia,
                origin=scene.fixed_point,
            )
            paths.append(Path(gif))
    paths = [args.out / p.name for p in paths]

    st = sol.stats
    print(f"scene {scene.name}" + (f": {scene.description}" if scene.description else ""))
    print(
        f"{settings}, t1 = {scene.t1:g} s: {st['num_accepted_steps']} steps"
        + (f" ({st['num_rejected_steps']} rejected)" if st.get("num_rejected_steps") else "")
        + f", {st['num_fevals']} field evaluations, {wall:.2f} s wall (incl. compilation)"
    )
    if scene.target_error is not None:
        est = np.asarray(sol.error_estimate)
        print(
            f"  target_error {scene.target_error:.3g}: chose {sol.chosen_setting()} "
            f"after {st['num_solves']} solves (steps above: the last, finest solve); "
            f"estimated error at t1 {est[-1]:.2e}, max over saved times {est.max():.2e}"
        )
    conserved = problem.conserved()
    for k, v in drift.items():
        note = "" if k in conserved else "  (not conserved by this scene)"
        print(f"  max relative change of {k}: {v:.2e}{note}")
    print(f"  max ||R^T R - I||: {orth:.2e}")
    flip = _flip_interval(problem)
    if flip is not None:
        if math.isfinite(flip):
            print(f"  intermediate-axis flip interval (exact): {flip:.3f} s")
        else:
            print("  no flip of the intermediate axis (exact solution: lierk.exact.flip_interval is inf)")
    print("wrote:")
    for p in paths:
        print(f"  {p}")
    return 0


def _flip_interval(problem) -> float | None:
    """`lierk.exact.flip_interval` of a torque-free body (``inf``: it never flips), else None."""
    from .exact import flip_interval

    return float(flip_interval(problem.inertia, problem.omega0)) if problem.torque_free else None


# --------------------------------------------------------------------------
# sweep


def sweep(args) -> int:
    scene = _load(args)
    import numpy as np

    from . import plot
    from ._progress import Progress
    from .omega_sweep import omega_grid, open_sweep_store, sweep_omega0

    omega0 = np.asarray(scene.problem.omega0, dtype=float)
    ranges = [getattr(args, f"omega_{c}") for c in "xyz"]
    stem = _key(scene.name) or "scene"
    try:
        axes = omega_grid(omega0, ranges, args.span, args.grid)
    except ValueError as e:
        raise CLIError(f"{e} (--span, --omega-x/-y/-z START:STOP:N)") from None
    try:
        key = {"scene": hashlib.sha256(args.scene.read_bytes()).hexdigest(), "lierk": _version()}
        store = open_sweep_store(scene, axes, args.out / f"{stem}_sweep.chunks", chunk_size=args.chunk_size, key=key)
    except ValueError as e:
        raise CLIError(_one_line(e)) from None
    if store.resumed:
        print(f"lierk sweep: resuming: {store.resumed} of {store.n_chunks} chunks already done", file=sys.stderr)
    n_points = int(np.prod([len(a) for a in axes]))
    bar = Progress("sweep", n_points, "members", quiet=args.quiet or store.complete)
    start = time.perf_counter()
    res = sweep_omega0(scene, axes, chunk_size=args.chunk_size, store=store, compiling=bar.compiling, on_chunk=bar.update)
    wall = time.perf_counter() - start
    if res is None:
        return 0

    solver, t1, varied = scene.solver, res.t1, res.varied
    names = [f"omega0_{'xyz'[k]}" for k in varied]
    title = f"{scene.name}: sweep of $\\omega_0$, T = {t1:g} s\n{solver.name}, {_run_settings(scene)}"
    with _staged_output(args.out) as tmp:
        np.savez(tmp / f"{stem}_sweep.npz", **{n: res.axes[k] for n, k in zip(names, varied)},
                 omega0=res.grid, t1=t1, **res.values)
        fig = plot.omega_sweep(res.values, [res.axes[k] for k in varied], varied, omega0, title)
        fig.savefig(tmp / f"{stem}_sweep.png", dpi=100)
    # The chunks are in the .npz now; only an unfinished run's are kept (to
    # resume, and to refuse another run in their place).
    shutil.rmtree(store.directory, ignore_errors=True)
    npz, png = args.out / f"{stem}_sweep.npz", args.out / f"{stem}_sweep.png"

    print(f"scene {scene.name}: {n_points} initial angular velocities ({' x '.join(map(str, res.shape))}), "
          f"{solver.name}, {_run_settings(scene)}, T = {t1:g} s, {wall:.2f} s wall (incl. compilation)")
    if res.failed.any():
        print(f"  {int(res.failed.sum())} points failed to integrate (NaN in the outputs)")
    v = res.values
    s = v["sensitivity"]
    print(f"  ||dR(T)/d omega0||: {np.nanmin(s):.3g} .. {np.nanmax(s):.3g} s "
          f"(estimated error of it: up to {np.nanmax(v['sensitivity_error'] / s):.1g} relative)")
    lam = v["lyapunov"]
    print(f"  finite-time Lyapunov exponent: {np.nanmin(lam):.3g} .. {np.nanmax(lam):.3g} 1/s")
    if "flip_interval" in v:
        f = v["flip_interval"][np.isfinite(v["flip_interval"])]
        if f.size:
            print(f"  flip interval: {f.min():.3g} .. {f.max():.3g} s")
    print("wrote:")
    for p in (npz, png):
        print(f"  {p}")
    return 0


# --------------------------------------------------------------------------
# accuracy


def accuracy(args) -> int:
    scene = _load(args)
    from . import accuracy as _accuracy

    start = time.perf_counter()
    max_settings = args.max_settings if args.max_settings is not None else (4 if args.quick else None)
    report = _accuracy.work_precision(
        scene, solvers=args.solvers, progress=not args.quiet, max_settings=max_settings
    )
    wall = time.perf_counter() - start

    with _staged_output(args.out) as tmp:
        _accuracy.figure(report).savefig(tmp / "work_precision.png", dpi=100)
        (tmp / "work_precision.json").write_text(_accuracy.to_json(report) + "\n")
    png, js = args.out / "work_precision.png", args.out / "work_precision.json"

    print(
        f"scene {report.scene}: {len(report.rows)} runs of {', '.join(report.solvers)}, T = {report.t1:g} s, "
        f"errors max_t ||R - R_ref||_F at {len(report.ts)} equally spaced times, {wall:.1f} s wall (incl. compilation)"
    )
    print(f"  reference: {report.reference}, error about {report.reference_error:.1e}")
    if report.check is not None:
        d = report.check_disagreement
        print(f"  cross-check: {report.check}" + (f", disagrees by {d:.1e}" if d is not None else ""))
    header = f"{'error <=':>9}  {'cheapest':<8}  {'setting':<18}  {'time (s)':>9}  {'error':>8}  {'estimate':>8}"
    print(header)
    for decade, row in report.best_per_decade().items():
        if row is not None:
            print(
                f"{decade:>9.0e}  {row.solver:<8}  {row.label:<18}  {row.time:>9.3g}  {row.error:>8.1e}  "
                f"{row.error_estimate:>8.1e}"
            )
        elif decade < report.floor:
            print(f"{decade:>9.0e}  (below the reference's accuracy, {report.floor:.1e})")
        else:
            print(f"{decade:>9.0e}  (no run reached it)")
    print("wrote:")
    for p in (png, js):
        print(f"  {p}")
    return 0


# --------------------------------------------------------------------------


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


def main(argv=None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(_join_negative_ranges(argv))
    if args.command is None:
        print("lierk: error: a command is required: simulate, sweep or accuracy (see lierk --help)", file=sys.stderr)
        return 2
    prog = f"lierk {args.command}"

    use = _CacheUse()

    def show(message, *a, **k):
        if not use.swallow(message):
            print(f"{prog}: warning: {' '.join(str(message).split())}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = show
        # Every unreadable entry counts, not only the first of each name.
        warnings.filterwarnings("always", message="Error (reading|writing) persistent compilation cache")
        code = _dispatch(args, prog, use)
    summary = use.summary()
    if summary and code == 0 and not args.quiet:
        print(f"{prog}: {summary}", file=sys.stderr)
    return code


def _dispatch(args, prog: str, use: _CacheUse) -> int:
    try:
        _check_out(args.out)
        _configure(args)
        import jax

        # The command line is an application: it picks its precision, scoped to
        # this call, and leaves the global config alone.
        with _use_cache(args, use), jax.enable_x64(not args.float32):
            return {"simulate": simulate, "sweep": sweep, "accuracy": accuracy}[args.command](args)
    except CLIError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as e:
        # eqx.error_if messages carry a long explanation after the first line.
        print(f"{prog}: error: {_one_line(e)}", file=sys.stderr)
        return 1
    except Exception as e:  # a bug: still one line, naming the exception
        print(f"{prog}: error: {type(e).__name__}: {_one_line(e)} (unexpected; please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
