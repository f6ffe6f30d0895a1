"""Time to first result: the command line's wall time, split into import,
compilation and run, cold and warm.

Each command runs in a fresh process (this script with ``--one``, which
calls ``lierk.app.cli.main`` as the console script does), with its own
compilation cache directory (``LIERK_CACHE_DIR``; JAX's own cache settings
removed), in three states:

- no cache: ``--no-cache``, every program compiled;
- cold: an empty cache directory (every program compiled and saved);
- warm: the same command again, with the cache the cold run filled.

The process reports its split, and the parent measures the whole:

- start: the interpreter starting, up to the first line of the script;
- import: ``import lierk.app.cli`` and ``import lierk`` (jax, equinox, ...);
- compile: the wall time spent tracing, lowering and compiling (or loading
  from the cache) every program, `lierk.app.compilations.counting`;
- run: the rest of the command (parsing the scene, the solves, diagnostics,
  figures, files).

Runs alternate no cache, cold and warm, ``--repeats`` times (default 3), and
the medians are reported: on a shared machine only numbers measured side by
side compare.  The ``programs`` columns are the compilations counted (cold)
and the cache's own count of programs loaded (warm).

Run: ``python benchmarks/latency.py [--quick] [--repeats N] [--out DIR]``
(``--quick``: one repeat of a 1 s simulation without the GIF and
``accuracy --quick`` of the T-handle, into a temporary directory); writes
latency.{json,md}.  ``--md`` rewrites latency.md from latency.json.
"""

from __future__ import annotations

import time

_STARTED = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
COMMANDS = {
    "simulate --no-gif": ["simulate", str(EXAMPLES / "tee_handle_a.toml"), "--no-gif"],
    "simulate (with GIF)": ["simulate", str(EXAMPLES / "tee_handle_a.toml")],
    "accuracy (heavy top)": ["accuracy", str(EXAMPLES / "heavy_top.toml")],
}
QUICK = {
    "simulate --no-gif, 1 s": ["simulate", str(EXAMPLES / "tee_handle_a.toml"), "--no-gif", "--t1", "1"],
    "accuracy --quick (T-handle, 1 s)": ["accuracy", str(EXAMPLES / "tee_handle_a.toml"), "--quick", "--t1", "1"],
}
STATES = ("no cache", "cold", "warm")
PHASES = ("start", "import", "compile", "run")


def one(argv: list[str]) -> dict:
    """Run ``lierk ARGV`` in this process: its split (s) and what it compiled."""
    import io
    from contextlib import redirect_stderr, redirect_stdout

    begin = time.perf_counter()
    import lierk  # noqa: F401  (the package: what a command imports before it runs)
    import lierk.app.cli

    imported = time.perf_counter()
    import jax

    from lierk.app.compilations import counting

    hits = []
    jax.monitoring.register_event_listener(
        lambda event, **_: hits.append(event) if event.endswith("/cache_hits") else None
    )
    out, err = io.StringIO(), io.StringIO()
    with counting() as c, redirect_stdout(out), redirect_stderr(err):
        code = lierk.app.cli.main([*argv, "--quiet"])
    done = time.perf_counter()
    if code != 0:
        raise RuntimeError(f"lierk {' '.join(argv)} exited with {code}: {err.getvalue()[-2000:]}")
    return dict(
        start=begin - _STARTED,
        import_=imported - begin,
        compile=c.seconds,
        run=done - imported - c.seconds,
        programs=c.count,
        loaded=len(hits),
    )


def _env(cache: Path | None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
    env.pop("LIERK_NO_CACHE", None)
    if cache is not None:
        env["LIERK_CACHE_DIR"] = str(cache)
    return env


def run(argv: list[str], cache: Path | None, out: Path) -> dict:
    """``lierk ARGV --out OUT`` in a fresh process (``cache`` None: ``--no-cache``):
    its wall time and split."""
    shutil.rmtree(out, ignore_errors=True)
    extra = ["--no-cache"] if cache is None else []
    start = time.perf_counter()
    p = subprocess.run(
        [sys.executable, __file__, "--one", json.dumps([*argv, "--out", str(out), *extra])],
        env=_env(cache),
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - start
    if p.returncode != 0:
        raise RuntimeError(f"{argv} failed: {p.stderr[-2000:]}")
    split = json.loads(p.stdout.strip().splitlines()[-1])
    split["import"] = split.pop("import_")
    # What the child cannot see of itself: the interpreter's start, and its exit.
    split["start"] = wall - split["import"] - split["compile"] - split["run"]
    return dict(wall=wall, **split)


def main(argv=None):
    import common  # only the standard library: the timed children import jax themselves

    def extra(parser):
        parser.add_argument("--repeats", type=int, default=None, help="runs of each state (default 3; --quick 1)")
        parser.add_argument("--md", action="store_true", help="only rewrite latency.md from latency.json")
        parser.add_argument("--one", help=argparse.SUPPRESS)

    quick, results, args = common.cli(
        __doc__, "one repeat of two short commands, into a temp dir", extra=extra, argv=argv
    )
    if args.one:
        print(json.dumps(one(json.loads(args.one))))
        return
    if args.md:
        data = json.loads((results / "latency.json").read_text())
        (results / "latency.md").write_text("\n".join(markdown(data["meta"], data["rows"])) + "\n")
        return
    repeats = args.repeats or (1 if quick else 3)
    commands = QUICK if quick else COMMANDS
    start_load = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, command in commands.items():
            runs = {state: [] for state in STATES}
            for i in range(repeats):
                cache = tmp / f"cache-{len(rows)}-{i}"
                runs["no cache"].append(run(command, None, tmp / "out"))
                runs["cold"].append(run(command, cache, tmp / "out"))
                runs["warm"].append(run(command, cache, tmp / "out"))
            row = dict(command=f"lierk {name}", runs=runs)
            for state, rs in runs.items():
                row[state] = {k: statistics.median(r[k] for r in rs) for k in ("wall", *PHASES, "programs", "loaded")}
            rows.append(row)
            print(f"{row['command']}: " + ", ".join(f"{s} {row[s]['wall']:.1f} s" for s in STATES), flush=True)

    import jax

    import lierk

    meta = dict(
        machine=dict(
            cpu_count=os.cpu_count(),
            jax=jax.__version__,
            lierk=lierk.__version__,
            load_average_at_start=start_load,
            load_average_at_end=os.getloadavg(),
        ),
        repeats=repeats,
        quick=quick,
    )
    common.write_results(results, "latency", dict(meta=meta, rows=rows), markdown(meta, rows))


def markdown(meta, rows) -> list[str]:
    m = meta["machine"]
    load = lambda xs: ", ".join(f"{x:.1f}" for x in xs)  # noqa: E731
    lines = [
        "# Time to first result: the command line, cold and warm",
        "",
        f"{m['cpu_count']} cores; jax {m['jax']}, lierk {m['lierk']}.  Each command in a fresh process, medians of "
        f"{meta['repeats']} runs taken in turn (no cache, cold, warm); load average at the start "
        f"{load(m['load_average_at_start'])}, at the end {load(m['load_average_at_end'])} (1, 5, 15 min).  "
        "Start: the interpreter; import: `import lierk`; compile: tracing, lowering and compiling or loading "
        "every program; run: the rest (scene, solves, figures, files).  Cold: an empty cache; warm: the same "
        "command again with it.",
        "",
        "| command | cache | wall (s) | start | import | compile | run | programs compiled / loaded |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        for state in STATES:
            s = r[state]
            count = f"{s['loaded']:.0f} loaded" if state == "warm" else f"{s['programs']:.0f} compiled"
            lines.append(
                f"| `{r['command']}` | {state} | {s['wall']:.1f} | {s['start']:.1f} | {s['import']:.1f} | "
                f"{s['compile']:.1f} | {s['run']:.1f} | {count} |"
            )
    return lines


if __name__ == "__main__":
    main()
