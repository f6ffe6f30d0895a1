"""The ``lierk`` command line.

    lierk simulate SCENE.toml --out DIR      trajectory (.npz), figures and a GIF
    lierk sweep SCENE.toml --out DIR ...     a grid of initial angular velocities
    lierk accuracy SCENE.toml --out DIR      work against precision of the solvers
    lierk schema > scene.schema.json         the JSON Schema of scene files, for editors

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
chunk at once to ``DIR/<name>_sweep.chunks/`` (`lierk.app.store.ChunkStore`), so
running the same command again resumes an interrupted sweep; the directory
is removed once the outputs are written.

The arguments are `lierk.app.cli_arguments`'s; each command calls one library
function (`lierk.app.simulation.simulate`, `lierk.app.omega_sweep.sweep_omega0`,
`lierk.app.accuracy.work_precision`) inside `lierk.app.cache.using_cache`, prints
its summary and writes its files.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import hashlib
import os
import re
import shutil
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

from .cli_arguments import build_parser, default_out, parse, parse_range, version

__all__ = ["main", "build_parser", "parse_range"]


class CLIError(Exception):
    """A user mistake: reported as one line, exit status 2."""


# --------------------------------------------------------------------------
# Set-up shared by the commands


def _configure(args) -> None:
    """Devices must be settled before JAX computes anything."""
    given_flags = os.environ.get("XLA_FLAGS")
    if args.devices is not None:
        flags = re.sub(r"--xla_force_host_platform_device_count=\S+", "", os.environ.get("XLA_FLAGS", ""))
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={args.devices}".strip()
    if args.command == "sweep":
        from . import distributed

        try:
            distributed.initialize(args.coordinator_address, args.num_processes, args.process_id)
        except ValueError as e:
            raise CLIError(_one_line(e)) from None
    if args.devices is not None:
        import jax

        # JAX reads XLA_FLAGS when it starts its CPU backend (here, unless it
        # already has): a backend started before runs with its own count.
        found = jax.local_device_count("cpu")
        if found != args.devices:
            if given_flags is None:
                del os.environ["XLA_FLAGS"]
            else:
                os.environ["XLA_FLAGS"] = given_flags
            raise CLIError(
                f"--devices {args.devices} must be set before JAX starts; it already runs with {found} "
                "CPU devices: run lierk in a fresh process"
            )


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


def _wrote(paths) -> None:
    print("wrote:")
    for p in paths:
        print(f"  {p}")


# --------------------------------------------------------------------------
# simulate


def simulate(args) -> int:
    scene = _load(args)
    from .segments import N_PIECES
    from .simulation import simulate as run
    from .store import check_size

    if args.target_error is not None:
        scene = scene.with_target_error(args.target_error)
    saved = scene.saved_count() * scene.bytes_per_saved()
    try:
        # The pieces, their concatenation and the derived omega, L and
        # invariants hold about 4 copies of the saved points; the .npz 2.
        check_size(
            memory=4 * saved, disk=2 * saved, directory=args.out, what=f"simulating {scene.saved_count()} saved points"
        )
    except ValueError as e:
        raise CLIError(_one_line(e)) from None
    # matplotlib's import (a noticeable part of a warm run) runs beside the solve,
    # whose XLA compilation and run release the GIL.
    preload = threading.Thread(target=_import_plotting, daemon=True)
    preload.start()
    sim = run(scene, n_pieces=args.chunks or N_PIECES, progress=not args.quiet)
    preload.join()
    with _staged_output(args.out) as tmp:
        names = _write_simulation(sim, tmp, args)
    print(sim.summary())
    _wrote(args.out / name for name in names)
    return 0


def _import_plotting() -> None:
    """Import what `_write_simulation` draws with (errors surface there)."""
    with contextlib.suppress(Exception):
        import matplotlib.backends.backend_agg  # noqa: F401
        import matplotlib.ticker  # noqa: F401

        from . import plot  # noqa: F401


def _write_simulation(sim, tmp: Path, args) -> list[str]:
    """The .npz, the figures and (unless --no-gif) the animation of ``sim``
    in ``tmp``: the names written."""
    import numpy as np

    from . import plot

    scene, sol, problem = sim.scene, sim.solution, sim.scene.problem
    stem, settings = scene.file_stem, scene.describe_run(sol)
    title = f"{scene.name}: {scene.description}\n{settings}" if scene.description else f"{scene.name} — {settings}"
    np.savez(tmp / f"{stem}.npz", **sim.record())
    # Pillow quantizes and encodes the GIF mostly without the GIL, beside the
    # figures' drawing, which holds it: the two overlap
    # (benchmarks/results/latency.md).
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        gif = None
        if not args.no_gif:
            images = plot.animation_frames(
                sol,
                scene.body_parts,
                L=sim.diagnostics.L,
                frames=args.frames,
                title=f"{scene.name} — {settings}",
                inertia=problem.inertia,
                origin=scene.fixed_point,
            )
            gif = pool.submit(plot.write_gif, images, tmp / f"{stem}.gif", args.fps)
        names = [f"{stem}.npz"] + _write_figures(sim, tmp, args, title)
        return names if gif is None else names + [gif.result().name]


def _write_figures(sim, tmp: Path, args, title: str) -> list[str]:
    """The figures of ``sim`` as PNGs in ``tmp``: the names written."""
    from . import plot

    scene, sol, problem, diag = sim.scene, sim.solution, sim.scene.problem, sim.diagnostics
    stem, names = scene.file_stem, []
    figures = {
        "components": plot.components(sol, title, events=sim.event_times),
        "euler": plot.euler_angles(
            sol,
            title,
            degrees=args.degrees,
            convention=scene.euler_convention,
            events=sim.event_times,
            angles=diag.euler_angles,
        ),
        "invariants": plot.invariants(sol, problem, title, quantities=diag.invariants),
    }
    for what, fig in figures.items():
        names.append(f"{stem}_{what}.png")
        fig.savefig(tmp / names[-1], dpi=100)
    return names


# --------------------------------------------------------------------------
# sweep


def sweep(args) -> int:
    scene = _load(args)
    import numpy as np

    from lierk import Progress

    from . import plot
    from .omega_sweep import omega_grid, open_sweep_store, sweep_omega0

    omega0 = np.asarray(scene.problem.omega0, dtype=float)
    ranges = [getattr(args, f"omega_{c}") for c in "xyz"]
    stem = scene.file_stem
    try:
        axes = omega_grid(omega0, ranges, args.span, args.grid)
    except ValueError as e:
        raise CLIError(f"{e} (--span, --omega-x/-y/-z START:STOP:N)") from None
    try:
        key = {"scene": hashlib.sha256(args.scene.read_bytes()).hexdigest(), "lierk": version()}
        store = open_sweep_store(scene, axes, args.out / f"{stem}_sweep.chunks", chunk_size=args.chunk_size, key=key)
    except ValueError as e:
        raise CLIError(_one_line(e)) from None
    if store.resumed:
        print(f"lierk sweep: resuming: {store.resumed} of {store.n_chunks} chunks already done", file=sys.stderr)
    n_points = int(np.prod([len(a) for a in axes]))
    bar = Progress("sweep", n_points, "members", quiet=args.quiet or store.complete)
    start = time.perf_counter()
    res = sweep_omega0(
        scene, axes, chunk_size=args.chunk_size, store=store, compiling=bar.compiling, on_chunk=bar.update
    )
    wall = time.perf_counter() - start
    if res is None:
        return 0

    varied, settings = res.varied, scene.describe_run()
    names = [f"omega0_{'xyz'[k]}" for k in varied]
    title = f"{scene.name}: sweep of $\\omega_0$, T = {res.t1:g} s\n{settings}"
    with _staged_output(args.out) as tmp:
        np.savez(
            tmp / f"{stem}_sweep.npz",
            **{n: res.axes[k] for n, k in zip(names, varied)},
            omega0=res.grid,
            t1=res.t1,
            **res.values,
        )
        fig = plot.omega_sweep(res, omega0, title)
        fig.savefig(tmp / f"{stem}_sweep.png", dpi=100)
    # The chunks are in the .npz now; only an unfinished run's are kept (to
    # resume, and to refuse another run in their place).
    shutil.rmtree(store.directory, ignore_errors=True)

    print(
        f"scene {scene.name}: {n_points} initial angular velocities ({' x '.join(map(str, res.shape))}), "
        f"{settings}, T = {res.t1:g} s, {wall:.2f} s wall (incl. compilation)"
    )
    print(res.summary())
    _wrote([args.out / f"{stem}_sweep.npz", args.out / f"{stem}_sweep.png"])
    return 0


# --------------------------------------------------------------------------
# accuracy


def accuracy(args) -> int:
    scene = _load(args)
    from . import accuracy as _accuracy

    start = time.perf_counter()
    max_settings = args.max_settings if args.max_settings is not None else (4 if args.quick else None)
    report = _accuracy.work_precision(scene, solvers=args.solvers, progress=not args.quiet, max_settings=max_settings)
    wall = time.perf_counter() - start

    with _staged_output(args.out) as tmp:
        _accuracy.figure(report).savefig(tmp / "work_precision.png", dpi=100)
        (tmp / "work_precision.json").write_text(_accuracy.to_json(report) + "\n")
    print(report.summary(wall))
    _wrote([args.out / "work_precision.png", args.out / "work_precision.json"])
    return 0


# --------------------------------------------------------------------------
# schema


def schema() -> int:
    """Print the JSON Schema of scene files (`lierk.app.scene_schema.json_schema`)."""
    import json

    from .scene_schema import json_schema

    try:
        print(json.dumps(json_schema(), indent=2), flush=True)
    except BrokenPipeError:  # `lierk schema | head`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


# --------------------------------------------------------------------------


def main(argv=None) -> int:
    args = parse(sys.argv[1:] if argv is None else list(argv))
    if args.command is None:
        print(
            "lierk: error: a command is required: simulate, sweep, accuracy or schema (see lierk --help)",
            file=sys.stderr,
        )
        return 2
    if args.command == "schema":
        return schema()
    prog = f"lierk {args.command}"

    def show(message, *a, **k):
        print(f"{prog}: warning: {' '.join(str(message).split())}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = show
        code, cache_summary = _dispatch(args, prog)
    if cache_summary and code == 0 and not args.quiet:
        print(f"{prog}: {cache_summary}", file=sys.stderr)
    return code


def _dispatch(args, prog: str) -> tuple[int, str | None]:
    """Run the command: ``(exit status, the compilation cache's summary)``."""
    try:
        if args.out is None:
            args.out = default_out(args.scene)
        _check_out(args.out)
        _configure(args)
        import jax

        from .cache import using_cache

        # The command line is an application: it picks its precision and
        # keeps compiled programs, scoped to this call (the global config is
        # left as it was).
        with using_cache(not args.no_cache) as use, jax.enable_x64(not args.float32):
            code = {"simulate": simulate, "sweep": sweep, "accuracy": accuracy}[args.command](args)
        return code, use.summary()
    except CLIError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2, None
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130, None
    except (ValueError, OSError, RuntimeError) as e:
        # eqx.error_if messages carry a long explanation after the first line.
        print(f"{prog}: error: {_one_line(e)}", file=sys.stderr)
        return 1, None
    except Exception as e:  # a bug: still one line, naming the exception
        print(f"{prog}: error: {type(e).__name__}: {_one_line(e)} (unexpected; please report it)", file=sys.stderr)
        return 1, None


def run() -> None:
    """The ``lierk`` program: `main`, then exit at once.  Everything a command
    writes is closed by then; what remains of the process is the teardown of
    the XLA runtime and of the modules, a noticeable part of a short
    ``lierk simulate``, which ``os._exit`` skips once the output is flushed."""
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
