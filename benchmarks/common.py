"""What the benchmark scripts share: their command line, timing, the machine
record and the near-intermediate-axis batches.  Scripts import it as
``common`` (they run as ``python benchmarks/NAME.py``, so this folder is on
``sys.path``).  The peers (diffrax, SciPy, MuJoCo) are in ``peers``.

Only argparse and pathlib are imported here at the top: jax, NumPy and the
rest are imported by the functions that use them, so that a script can parse its
command line before jax starts (the XLA host device count) and a timed child
process imports jax itself."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:  # the annotations only: NumPy is imported where it is used
    import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def cli(doc: str, quick_help: str, run: bool = True, extra: Callable | None = None, argv: list[str] | None = None):
    """``(quick, out)`` from ``--quick`` and ``--out``.  Quick runs write to a
    temporary directory unless ``--out`` is given, so they never overwrite
    ``benchmarks/results``.  ``run``: the script runs (``__name__ ==
    "__main__"``) and its command line (``argv``, default ``sys.argv``) is
    parsed; imported, the defaults apply.  ``extra(parser)`` adds a script's
    own arguments; with it, ``(quick, out, args)``, ``args`` the parsed
    namespace."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument(
        "--out", default=None, help="results directory (default benchmarks/results; --quick: a temp dir)"
    )
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv) if run else parser.parse_args([])
    if args.out:
        out = Path(args.out)
    elif args.quick:
        import tempfile

        out = Path(tempfile.gettempdir()) / "lierk-bench-quick"
    else:
        out = RESULTS
    return (args.quick, out) if extra is None else (args.quick, out, args)


def write_results(out: Path, name: str, payload, markdown: str | list[str]) -> None:
    """Write ``out/name.json`` (``payload``, NumPy scalars as floats) and
    ``out/name.md`` (``markdown``: the text, or its lines), creating ``out``,
    and say where."""
    import json

    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(payload, indent=1, default=float) + "\n")
    (out / f"{name}.md").write_text(markdown if isinstance(markdown, str) else "\n".join(markdown) + "\n")
    print(f"wrote {name}.json and {name}.md in {out}")


def timed(f, *args, repeats: int, min_time: float = 0.0, max_repeats: int = 51):
    """``(output, median wall time, time of the first call)``: the first call
    compiles and warms up and is not part of the median.  At least ``repeats``
    timed calls, and more (up to ``max_repeats``) until they add up to
    ``min_time`` seconds: on a shared machine one descheduling can double a
    call of a few milliseconds, and the median of 3 such calls is not robust."""
    import jax
    import numpy as np

    t = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    first = time.perf_counter() - t
    times = []
    while len(times) < repeats or (sum(times) < min_time and len(times) < max_repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t)
    return out, float(np.median(times)), first


def format_seconds(s: float) -> str:
    """``"12.3 ms"`` under a second, else ``"1.23 s"``."""
    return f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s"


def max_err(R, R_ref) -> float:
    """Largest Frobenius norm ``||R - R_ref||`` over the batch."""
    import jax.numpy as jnp

    return float(jnp.max(jnp.linalg.norm(jnp.asarray(R) - R_ref, axis=(-2, -1))))


def cpu_model() -> str:
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def near_axis(moments, n: int, seed: int = 0) -> tuple[np.ndarray, int]:
    """``(n, 3)`` body angular velocities (rad/s), |omega| in [1, 3], within
    ~11 degrees of the intermediate principal axis of a body with principal
    ``moments`` ``(3,)``, and that axis' index."""
    import numpy as np

    axis = int(np.argsort(np.asarray(moments))[1])
    rng = np.random.default_rng(seed)
    mag = rng.uniform(1.0, 3.0, n)
    d = rng.uniform(-0.2, 0.2, (n, 3))
    d[:, axis] = 1.0
    return mag[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True), axis


def interp_time(points, level: float) -> tuple[float, bool] | None:
    """Time to reach error ``level`` along one method's sweep, ``points`` a list
    of ``(error, time)``: ``(time, clamped)`` or None if no point reaches it.

    Only the work-precision front counts (points that no other point beats on
    both error and time).  Between the two front points that bracket
    ``level``, ``log time`` is interpolated linearly in ``log error``.  When
    even the cheapest point is below ``level`` its time is returned with
    ``clamped = True`` (the sweep did not go coarse enough to tell more)."""
    import numpy as np

    pts = sorted((t, e) for e, t in points if np.isfinite(e) and e > 0 and t > 0)
    front = []
    for t, e in pts:  # time ascending: keep each point more accurate than every cheaper one
        if not front or e < front[-1][1]:
            front.append((t, e))
    if not front or front[-1][1] > level:
        return None
    if front[0][1] <= level:
        return front[0][0], True
    for (t0, e0), (t1, e1) in zip(front, front[1:]):
        if e1 <= level < e0:
            w = (np.log(level) - np.log(e0)) / (np.log(e1) - np.log(e0))
            return float(np.exp(np.log(t0) + w * (np.log(t1) - np.log(t0)))), False
    raise AssertionError("unreachable: the front brackets the level")


def series_table(records, kind: str, heading: str, fmt: str = "{:.0e}") -> list[str]:
    """Markdown lines: one row per setting (records whose ``"kind"`` is
    ``kind``, e.g. "tol" or "dt", by ``"param"`` formatted with ``fmt``), one
    column per ``"method"``, cells "max error (time s)"."""
    rs = [r for r in records if r["kind"] == kind]
    methods = list(dict.fromkeys(r["method"] for r in rs))
    params = sorted({r["param"] for r in rs}, reverse=True)
    lines = [f"| {heading} | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for p in params:
        cells = []
        for m in methods:
            hit = [r for r in rs if r["method"] == m and r["param"] == p]
            cells.append(f"{hit[0]['error']:.1e} ({hit[0]['time_s']:.3g} s)" if hit else "")
        lines.append(f"| {fmt.format(p)} | " + " | ".join(cells) + " |")
    return lines


def machine_info(**versions) -> dict:
    """The machine record of a benchmark's JSON: cores, CPU model, platform,
    jax, numpy, lierk, JAX devices, the load average now, and ``versions``
    (other packages, by name)."""
    import os
    import platform

    import jax
    import numpy as np

    import lierk

    return {
        "cpu_count": os.cpu_count(),
        "cpu": cpu_model(),
        "processor": platform.processor() or platform.machine(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "lierk": lierk.__version__,
        **versions,
        **backend_info(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_at_start": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }


def backend_info() -> dict:
    """Where JAX runs the programs: ``backend`` (``"cpu"``, ``"gpu"``, ...),
    ``device_kind`` (the model, e.g. ``"NVIDIA H100 80GB HBM3"``) and
    ``devices``.  A machine with a GPU runs on it by default, even where a
    benchmark splits the CPU into host devices, so every record says which."""
    import jax

    devices = jax.devices()
    return {
        "backend": jax.default_backend(),
        "device_kind": devices[0].device_kind,
        "devices": [str(d) for d in devices],
    }


def backend_text(m: dict) -> str:
    """A results header's words for a machine record's backend: ``"JAX on
    the CPU (2 XLA host devices)"`` or ``"JAX on the GPU (1 x NVIDIA H100
    80GB HBM3)"``; records written before ``backend`` was kept say what they
    hold."""
    n = len(m.get("devices", [])) or m.get("device_count", 1)
    backend = m.get("backend")
    if backend is None:
        return f"JAX on {n} device(s) ({', '.join(m.get('devices', [])) or 'kind not recorded'})"
    if backend == "cpu":
        return f"JAX on the CPU ({n} XLA host device{'s' if n != 1 else ''})"
    return f"JAX on the {backend.upper()} ({n} x {m.get('device_kind', backend)})"


def git_commit(root: Path | None = None) -> str | None:
    """The commit of the checkout ``root`` (default: this one), with
    "+changes" if its ``lierk/`` differs from it, or None outside a git
    checkout: which code a stored row was measured with."""
    import subprocess

    root = Path(__file__).resolve().parent.parent if root is None else Path(root)
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "lierk"], cwd=root, capture_output=True, text=True
        )
    except (OSError, subprocess.CalledProcessError):
        return None
    return rev.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")
