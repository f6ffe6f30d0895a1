"""Run the benchmarks: ``python -m benchmarks [NAME ...] [--quick] [--out DIR]``.

A benchmark is a script ``benchmarks/NAME.py`` with a ``__main__`` block;
the modules the scripts import (``common``, ``peers``, ``native``,
``host_devices``) have none and are not listed.  Each named benchmark
(default: all, by name) runs in a fresh process, ``python
benchmarks/NAME.py [--quick] [--out DIR]``: several measure a first call or
a compilation, and several set XLA's host device count before jax starts,
so none may share a process.  Without ``--out`` a script writes
``benchmarks/results`` (``--quick``: a temporary directory).  One line per
script says its exit status and wall time; the exit status is non-zero if
any failed.  ``--list`` prints the names with the first sentence of each
script's docstring.  ``make bench`` runs them all.

``python -m benchmarks compare BASE HEAD [--repeat K] [--cells ...] [--out
FILE.md]`` is a command, not a benchmark: it runs ``headline.py`` against two
commits, alternating, and flags the cells more than 10% worse at HEAD
(`compare.py`).
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def benchmarks() -> dict[str, tuple[Path, str]]:
    """``{name: (path, first sentence of its docstring)}`` of every benchmark
    script, by name.  The scripts are read, not imported: importing one parses
    its command line and starts jax."""
    found = {}
    for path in sorted(HERE.glob("*.py")):
        tree = ast.parse(path.read_text())
        if not path.stem.startswith("_") and any(
            isinstance(node, ast.If) and "__name__" in ast.unparse(node.test) for node in tree.body
        ):
            paragraph = " ".join((ast.get_docstring(tree) or "").split("\n\n")[0].split())
            found[path.stem] = (path, paragraph.split(". ")[0].removesuffix("."))
    return found


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["compare"]:
        from .compare import main as compare

        return compare(argv[1:])
    known = benchmarks()
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (default: all; see --list)")
    parser.add_argument("--quick", action="store_true", help="each script's quick run, into a temp dir unless --out")
    parser.add_argument(
        "--out", default=None, help="results directory (default benchmarks/results; --quick: a temp dir)"
    )
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    args = parser.parse_args(argv)
    if args.list:
        width = max(map(len, known))
        for name, (_, doc) in known.items():
            print(f"{name:{width}s}  {doc}")
        return 0
    names = [n.removesuffix(".py") for n in args.names] or list(known)
    unknown = [n for n in names if n not in known]
    if unknown:
        parser.error(
            f"unknown benchmark{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}; valid: {', '.join(known)}"
        )
    # (the scripts run from the repository root: an --out relative to here is made absolute)
    flags = (["--quick"] if args.quick else []) + (["--out", str(Path(args.out).resolve())] if args.out else [])
    status = lambda code: "ok" if code == 0 else f"FAILED (exit {code})"  # noqa: E731

    results = []
    for name in names:
        script = known[name][0].relative_to(HERE.parent)
        print(f"=== {name}: python {' '.join([str(script), *flags])}", flush=True)
        start = time.perf_counter()
        code = subprocess.run([sys.executable, str(script), *flags], cwd=HERE.parent).returncode
        results.append((name, code, time.perf_counter() - start))
        print(f"=== {name}: {status(code)} in {results[-1][2]:.1f} s", flush=True)

    failed = [name for name, code, _ in results if code != 0]
    print(f"\n{len(results)} benchmark(s), {len(failed)} failed:")
    for name, code, seconds in results:
        print(f"  {name:16s} {status(code):18s} {seconds:8.1f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
