"""Time to first result: wall time of the command line, cold and warm.

Each command runs in a fresh process (``python -m lierk.cli`` would measure
the same; the console script is what users run), with its own compilation
cache directory (``LIERK_CACHE_DIR``, JAX's own cache settings removed):

- cold: an empty cache (every program compiled), and ``--no-cache``;
- warm: the same command again, with the cache the cold run filled.

Runs alternate cold and warm, ``--repeats`` times (default 3), and the
medians are reported with their ratio: on a shared machine only numbers
measured side by side compare.  The ``lierk simulate`` summary line says how
many programs were loaded and how many compiled, and the solve's own
"compiled in" time is read from its progress lines.  Import time (``python
-c "import lierk"``) is measured the same way.

Run: ``python benchmarks/latency.py [--repeats N] [--out DIR]``; writes
latency.{json,md} (default benchmarks/results).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import common

ROOT = Path(__file__).resolve().parent.parent
LIERK = str(Path(sys.executable).parent / "lierk")
COMMANDS = {
    "simulate --no-gif": ["simulate", str(ROOT / "examples" / "tee_handle_a.toml"), "--no-gif"],
    "simulate (with GIF)": ["simulate", str(ROOT / "examples" / "tee_handle_a.toml")],
}


def _env(cache: Path | None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
    if cache is not None:
        env["LIERK_CACHE_DIR"] = str(cache)
    return env


def run(argv: list[str], cache: Path | None, out: Path) -> dict:
    """One command in a fresh process: wall time, programs loaded/compiled,
    and the solve's compile time from its progress lines."""
    shutil.rmtree(out, ignore_errors=True)
    extra = ["--no-cache"] if cache is None else []
    start = time.perf_counter()
    p = subprocess.run([LIERK, *argv, "--out", str(out), *extra], env=_env(cache), capture_output=True, text=True)
    wall = time.perf_counter() - start
    if p.returncode != 0:
        raise RuntimeError(f"{argv} failed: {p.stderr[-2000:]}")
    counts = re.search(r"compiled programs: (\d+) loaded from the cache, (\d+) compiled", p.stderr)
    solve = re.search(r"compiled in ([\d.]+) s", p.stderr)
    return dict(
        wall=wall,
        loaded=int(counts.group(1)) if counts else 0,
        compiled=int(counts.group(2)) if counts else None,
        solve_compile=float(solve.group(1)) if solve else None,
    )


def import_time() -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import lierk"], env=_env(None), check=True)
    return time.perf_counter() - start


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="results directory (default benchmarks/results)")
    parser.add_argument("--md", action="store_true", help="only rewrite latency.md from latency.json")
    args = parser.parse_args(argv)
    results = Path(args.out) if args.out else common.RESULTS
    if args.md:
        data = json.loads((results / "latency.json").read_text())
        (results / "latency.md").write_text("\n".join(markdown(data["meta"], data["rows"])) + "\n")
        return
    machine = common.machine_info()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        imports = [import_time() for _ in range(args.repeats)]
        for name, command in COMMANDS.items():
            runs = {"no cache": [], "cold": [], "warm": []}
            for i in range(args.repeats):
                cache = tmp / f"cache-{name}-{i}"
                runs["no cache"].append(run(command, None, tmp / "out"))
                runs["cold"].append(run(command, cache, tmp / "out"))
                runs["warm"].append(run(command, cache, tmp / "out"))
            row = dict(command=f"lierk {name}", runs=runs)
            for kind, rs in runs.items():
                row[f"{kind} wall"] = statistics.median(r["wall"] for r in rs)
                row[f"{kind} solve compile"] = statistics.median(r["solve_compile"] or 0.0 for r in rs)
            row["warm programs loaded"] = runs["warm"][-1]["loaded"]
            row["warm programs compiled"] = runs["warm"][-1]["compiled"]
            row["cold programs compiled"] = runs["cold"][-1]["compiled"]
            rows.append(row)
            print(f"{row['command']}: no cache {row['no cache wall']:.1f} s, cold {row['cold wall']:.1f} s, "
                  f"warm {row['warm wall']:.1f} s ({row['warm programs loaded']} programs loaded, "
                  f"{row['warm programs compiled']} compiled)", flush=True)
    meta = dict(machine=dict(machine, load_average_at_end=os.getloadavg()), repeats=args.repeats,
                import_lierk=statistics.median(imports))
    results.mkdir(parents=True, exist_ok=True)
    (results / "latency.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    (results / "latency.md").write_text("\n".join(markdown(meta, rows)) + "\n")


def markdown(meta, rows) -> list[str]:
    m = meta["machine"]
    load = lambda xs: ", ".join(f"{x:.1f}" for x in xs)  # noqa: E731
    lines = [
        "# Time to first result: the command line, cold and warm",
        "",
        f"Machine: {m['cpu_count']} cores, {m['cpu']}; jax {m['jax']}, lierk {m['lierk']}.  Each command in a fresh "
        f"process, medians of {meta['repeats']} runs taken in turn (no cache, cold, warm), so the columns were measured "
        f"side by side; load average at the start {load(m['load_average_at_start'])}, at "
        f"the end {load(m['load_average_at_end'])} (1, 5, 15 min).  Cold: an empty cache directory; warm: the same command again "
        f"with it.  `import lierk` alone: {meta['import_lierk']:.1f} s.  Solve compile: the `compiled in` time of "
        "the progress lines (tracing and lowering, which a cache cannot skip, plus compiling or loading).",
        "",
        "| command | no cache (s) | cold (s) | warm (s) | warm / no cache | solve compile: cold, warm (s) | programs: compiled cold, loaded warm |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| `{r['command']}` | {r['no cache wall']:.1f} | {r['cold wall']:.1f} | {r['warm wall']:.1f} | "
            f"{r['warm wall'] / r['no cache wall']:.2f} | {r['cold solve compile']:.1f}, {r['warm solve compile']:.1f} | "
            f"{r['cold programs compiled']}, {r['warm programs loaded']} |"
        )
    return lines


if __name__ == "__main__":
    main()
