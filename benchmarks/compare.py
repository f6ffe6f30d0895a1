"""``python -m benchmarks compare BASE HEAD``: two commits' headline cells side by side, in one run on this machine.

BASE and HEAD are any git revisions (``main``, ``HEAD``, a hash), or ``.``
for this checkout's working tree as it is.  Each is checked out into a
temporary ``git worktree add --detach`` (removed afterwards), and this
checkout's ``benchmarks/headline.py`` runs against each in turn with
``PYTHONPATH`` set to that worktree, so that ``import lierk`` imports that
commit's lierk while the script, its problems and its references stay the
same for both: one environment, one machine, one script.  The two
alternate, ``--repeat K`` times (default 2), BASE first in odd rounds and
HEAD first in even ones, so that both see the machine in the same states.
A cell's time for a commit is the smallest of its K medians (a busy
machine only ever adds time, and one program can run at one of two speeds
drawn per process: `process_spread.py`); where a commit's K medians are
more than the threshold apart the table says so, and that cell cannot
resolve a change of that size.

The table gives each cell's time for BASE and HEAD, HEAD/BASE, and the
errors where a cell has a reference.  A cell is flagged when HEAD is more
than ``--threshold`` (default 10%) slower, when its error grows by more than
that (errors under 1e-13 are rounding and not compared), when it fails at
HEAD, or when HEAD lacks an API BASE has.  The exit status is 1 if any cell
is flagged, else 0.  ``--out FILE.md`` also writes the table, with the
machine it ran on, and ``FILE.json`` the raw runs.

Why not asv (airspeed velocity), the tool numpy, SciPy and astropy use for
this (``asv continuous``): asv builds a virtual environment per commit and
installs the project and its dependencies into each, so jax and jaxlib would
be reinstalled for every commit compared, and a difference in what got
installed would read as a difference in lierk.  Its harness times functions
in its own worker processes by its own rules, where several of these cells
need their own: a first call in a fresh process with the compilation cache
off (``first_*``), and a batch sharded over XLA host devices that must be
set before jax starts (``sweep_*``).  The worktrees run both commits in the
environment that is already here, alternating, with the benchmarks' own
timing (`common.timed`), and need nothing installed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import common

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
THRESHOLD = 0.10
ERROR_FLOOR = 1e-13  # errors below this are rounding: not compared


def git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


def resolve(rev: str) -> tuple[str, str]:
    """``(full hash, "short hash subject")`` of a revision, or of this
    checkout's HEAD with "+ working tree" for ``"."``."""
    sha = git("rev-parse", "--verify", ("HEAD" if rev == "." else rev) + "^{commit}")
    label = git("log", "-1", "--format=%h %s", sha)
    label = label if len(label) <= 64 else label[:61] + "..."
    return sha, label + (" + working tree" if rev == "." else "")


def aggregate(runs: list[dict]) -> dict:
    """One commit's cells over its runs (each a headline JSON): ``time`` the
    smallest median, ``times`` all of them, ``error`` the largest, ``extra``
    that of the fastest run, ``na``/``failed`` if no run measured it."""
    cells: dict[str, dict] = {}
    for run in runs:
        for name, rec in run.items():
            if name == "_meta":
                continue
            cell = cells.setdefault(
                name,
                {
                    "what": rec.get("what", ""),
                    "unit": rec.get("unit", "s"),
                    "times": [],
                    "errors": [],
                    "extra": {},
                    "status": [],
                },
            )
            if rec.get("time") is not None:
                if not cell["times"] or rec["time"] < min(cell["times"]):
                    cell["extra"] = rec.get("extra", {})
                cell["times"].append(rec["time"])
                if rec.get("error") is not None:
                    cell["errors"].append(rec["error"])
            else:
                cell["status"].append(("n/a: " + rec["na"]) if "na" in rec else ("failed: " + rec.get("failed", "?")))
    for cell in cells.values():
        cell["time"] = min(cell["times"]) if cell["times"] else None
        cell["error"] = max(cell["errors"], key=lambda e: math.inf if math.isnan(e) else e) if cell["errors"] else None
        cell["na"] = cell["time"] is None and all(s.startswith("n/a") for s in cell["status"])
    return cells


def compare_cells(base: dict, head: dict, threshold: float = THRESHOLD, floor: float = ERROR_FLOOR) -> list[dict]:
    """Rows of the table, one per cell of either side (`aggregate`'s
    output), with ``ratio`` (HEAD/BASE time), ``error_ratio`` and ``flags``:
    what makes the cell worse at HEAD (more than ``threshold`` slower, error
    more than ``threshold`` larger and above ``floor``, failing, or an API
    gone), and ``notes`` (times too spread to resolve ``threshold``, a cell
    new at HEAD)."""
    rows = []
    for name in list(dict.fromkeys([*base, *head])):
        b, h = base.get(name), head.get(name)
        row = {
            "cell": name,
            "what": (h or b)["what"],
            "base": b,
            "head": h,
            "ratio": None,
            "error_ratio": None,
            "flags": [],
            "notes": [],
        }
        if h is None or h["time"] is None:
            if b is not None and b["time"] is not None:
                row["flags"].append("gone at HEAD" if h is not None and h["na"] else "fails at HEAD")
            elif h is not None and not h["na"]:
                row["flags"].append("fails at HEAD")
        elif b is None or b["time"] is None:
            row["notes"].append("new at HEAD")
        else:
            row["ratio"] = h["time"] / b["time"]
            if row["ratio"] > 1 + threshold:
                row["flags"].append(f"{row['ratio']:.2f}x slower")
            eb, eh = b["error"], h["error"]
            if eh is not None and not math.isfinite(eh) and (eb is None or math.isfinite(eb)):
                row["flags"].append("error not finite")
            elif eb is not None and eh is not None and math.isfinite(eh):
                row["error_ratio"] = eh / eb if eb > 0 else (math.inf if eh > floor else 1.0)
                if eh > floor and eh > (1 + threshold) * max(eb, floor):
                    row["flags"].append(f"error {row['error_ratio']:.2f}x")
        for side, rec in (("BASE", b), ("HEAD", h)):
            if rec is not None and len(rec["times"]) > 1 and max(rec["times"]) > (1 + threshold) * min(rec["times"]):
                row["notes"].append(f"{side} runs {max(rec['times']) / min(rec['times']):.2f}x apart")
        rows.append(row)
    return rows


def _time(rec: dict | None) -> str:
    if rec is None:
        return "-"
    if rec["time"] is None:
        return "n/a" if rec["na"] else "failed"
    return common.format_seconds(rec["time"])


def _error(rec: dict | None) -> str:
    return "" if rec is None or rec["error"] is None else f"{rec['error']:.2e}"


def table(rows: list[dict]) -> list[str]:
    """Markdown lines: the cells, then each cell's derived numbers (``extra``)
    side by side, then why any cell failed or is n/a."""
    lines = ["| cell | BASE | HEAD | HEAD/BASE | error BASE | error HEAD | |", "|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}"
        mark = "; ".join([f"**{f}**" for f in r["flags"]] + r["notes"])
        lines.append(
            f"| {r['cell']} | {_time(r['base'])} | {_time(r['head'])} | {ratio} | {_error(r['base'])} | "
            f"{_error(r['head'])} | {mark} |"
        )
    extras = []
    for r in rows:
        b, h = (r["base"] or {}).get("extra", {}), (r["head"] or {}).get("extra", {})
        extras += [(r["cell"], k, b.get(k), h.get(k)) for k in dict.fromkeys([*b, *h])]
    if extras:
        lines += ["", "| cell | derived | BASE | HEAD |", "|---|---|---:|---:|"]
        lines += [
            f"| {c} | {k} | {'' if b is None else f'{b:.3g}'} | {'' if h is None else f'{h:.3g}'} |"
            for c, k, b, h in extras
        ]
    why = [
        f"- {r['cell']} at {side}: {s}"
        for r in rows
        for side, rec in (("BASE", r["base"]), ("HEAD", r["head"]))
        if rec is not None and rec["time"] is None
        for s in dict.fromkeys(rec["status"])
    ]
    return lines + (["", *why] if why else [])


def run_headline(root: Path, out: Path, args, env: dict) -> dict:
    """This checkout's headline.py against the lierk in ``root``; its JSON
    (``{}`` if it wrote none)."""
    cmd = [sys.executable, str(HERE / "headline.py"), "--json", str(out)]
    cmd += (["--quick"] if args.quick else []) + (["--cells", *args.cells] if args.cells else [])
    code = subprocess.run(cmd, cwd=root, env={**env, "PYTHONPATH": str(root)}).returncode
    if not out.exists():
        print(f"headline.py wrote nothing (exit {code})", flush=True)
        return {}
    result = json.loads(out.read_text())
    imported = Path(result["_meta"]["lierk"])
    if imported != (root / "lierk").resolve():
        raise RuntimeError(
            f"headline.py imported lierk from {imported}, not from {root}: is lierk installed "
            "somewhere that comes before PYTHONPATH?"
        )
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks compare", description=__doc__.split("\n")[0])
    parser.add_argument(
        "base", metavar="BASE", help="revision to compare against (e.g. main), or . for the working tree"
    )
    parser.add_argument("head", metavar="HEAD", help="revision to check (e.g. HEAD), or . for the working tree")
    parser.add_argument("--repeat", type=int, default=2, metavar="K", help="runs of each, alternating (default 2)")
    parser.add_argument(
        "--cells", nargs="*", default=None, metavar="NAME", help="headline cells or prefixes (default all)"
    )
    parser.add_argument("--threshold", type=float, default=THRESHOLD, help="flag a cell this much worse (default 0.10)")
    parser.add_argument("--quick", action="store_true", help="headline.py's tiny sizes: checks the machinery only")
    parser.add_argument(
        "--out", default=None, metavar="FILE.md", help="also write the table here (raw runs: FILE.json)"
    )
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    sys.path.insert(0, str(HERE))
    import headline

    try:
        headline.select(args.cells)
    except ValueError as e:
        parser.error(str(e))
    sides = {}
    for side, rev in (("BASE", args.base), ("HEAD", args.head)):
        try:
            sides[side] = (rev, *resolve(rev))
        except subprocess.CalledProcessError:
            parser.error(f"{side} {rev!r} is not a revision of this repository")

    start = time.perf_counter()
    runs: dict[str, list[dict]] = {"BASE": [], "HEAD": []}
    with tempfile.TemporaryDirectory(prefix="lierk-compare-") as tmp:
        tmp = Path(tmp)
        env = dict(os.environ)
        # later rounds reuse the first round's compiled programs (only warm calls are timed
        # in-process; the first_* cells' fresh processes turn the cache off)
        env.setdefault("JAX_COMPILATION_CACHE_DIR", str(tmp / "jax-cache"))
        roots, added = {}, []
        try:
            for side, (rev, sha, _) in sides.items():
                if rev == ".":
                    roots[side] = ROOT
                else:
                    roots[side] = tmp / side.lower()
                    git("worktree", "add", "--detach", "--quiet", str(roots[side]), sha)
                    added.append(roots[side])
            for k in range(args.repeat):
                for side in ("BASE", "HEAD") if k % 2 == 0 else ("HEAD", "BASE"):
                    print(f"=== {side} ({sides[side][2]}), round {k + 1} of {args.repeat}", flush=True)
                    runs[side].append(run_headline(roots[side], tmp / f"{side}-{k}.json", args, env))
        finally:
            for path in added:
                subprocess.run(["git", "worktree", "remove", "--force", str(path)], cwd=ROOT, capture_output=True)
    subprocess.run(["git", "worktree", "prune"], cwd=ROOT, capture_output=True)

    rows = compare_cells(aggregate(runs["BASE"]), aggregate(runs["HEAD"]), args.threshold)
    flagged = [r["cell"] for r in rows if r["flags"]]
    meta = next((r["_meta"] for side in ("HEAD", "BASE") for r in runs[side] if r), None)
    lines = [
        f"# {args.base} against {args.head}: headline cells (`python -m benchmarks compare`)",
        "",
        f"BASE = {sides['BASE'][2]}; HEAD = {sides['HEAD'][2]}.",
        "",
        machine_line(meta) + f" {args.repeat} run(s) of each, alternating; a time is the smallest of a cell's "
        f"medians. Flagged: more than {args.threshold:.0%} worse (time, or error above {ERROR_FLOOR:g}). "
        "The cells are described in `benchmarks/headline.py`.",
        "",
        *table(rows),
        "",
        (f"{len(flagged)} cell(s) flagged: {', '.join(flagged)}." if flagged else "No cell flagged.")
        + f" ({time.perf_counter() - start:.0f} s)",
    ]
    print("\n" + "\n".join(lines))
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text("\n".join(lines) + "\n")
        out.with_suffix(".json").write_text(
            json.dumps({"base": sides["BASE"], "head": sides["HEAD"], "runs": runs}, indent=1, default=float) + "\n"
        )
        print(f"wrote {out} and {out.with_suffix('.json')}")
    return 1 if flagged else 0


def machine_line(meta: dict | None) -> str:
    """The machine the runs were on, from a run's machine record."""
    if meta is None:
        return "No run wrote results."
    m = meta["machine"]
    return (
        f"{m['cpu_count']} cores ({m['cpu']}), {common.backend_text(m)}, jax {m['jax']}, load average "
        f"{m['load_average_at_start'][0]:.1f} at the start of a run."
        if m.get("load_average_at_start")
        else f"{m['cpu_count']} cores ({m['cpu']}), {common.backend_text(m)}, jax {m['jax']}."
    )
