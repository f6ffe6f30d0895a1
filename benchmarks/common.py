"""What the benchmark scripts share: their command line, timing, the machine
record and the near-intermediate-axis batches.  Scripts import it as
``common`` (they run as ``python benchmarks/NAME.py``, so this folder is on
``sys.path``)."""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def cli(doc: str, quick_help: str, run: bool) -> tuple[bool, Path]:
    """``(quick, out)`` from ``--quick`` and ``--out``.  Quick runs write to a
    temporary directory unless ``--out`` is given, so they never overwrite
    ``benchmarks/results``.  ``run``: the script runs (``__name__ ==
    "__main__"``); imported, the defaults apply."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--out", default=None, help="results directory (default benchmarks/results; --quick: a temp dir)")
    args = parser.parse_args() if run else parser.parse_args([])
    if args.out:
        return args.quick, Path(args.out)
    return args.quick, (Path(tempfile.gettempdir()) / "lierk-bench-quick" if args.quick else RESULTS)


def timed(f, *args, repeats: int):
    """``(output, median wall time, time of the first call)``: the first call
    compiles and warms up and is not part of the median."""
    t = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t)
    return out, float(np.median(times)), first


def max_err(R, R_ref) -> float:
    """Largest Frobenius norm ``||R - R_ref||`` over the batch."""
    return float(jnp.max(jnp.linalg.norm(jnp.asarray(R) - R_ref, axis=(-2, -1))))


def cpu_model() -> str:
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
    axis = int(np.argsort(np.asarray(moments))[1])
    rng = np.random.default_rng(seed)
    mag = rng.uniform(1.0, 3.0, n)
    d = rng.uniform(-0.2, 0.2, (n, 3))
    d[:, axis] = 1.0
    return mag[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True), axis
