"""One compiled program, timed in several fresh processes: how far its speed
moves between processes, with XLA's default threading and with the flags
that turn its intra-op threads off.

Every other benchmark times each program once, in its own process.  While
checking an apparent slowdown of the fixed-step ``RKMK(DOP853)`` in
`work_precision.py` (no commit was slower), the same program ran at two
speeds, about 2x apart, in different processes.  This script records that
spread so the other tables can be read with it.

Programs: 1000 T-handles near the intermediate axis, 50 fixed steps of
0.2 s, ``jit(vmap(solve))`` on one device, float64: ``RKMK4``,
``RKMK(DOPRI54)`` and ``RKMK(DOP853)``.  Each process compiles, warms up and
takes the median of 30 calls (`common.timed`).

Writes benchmarks/results/process_spread.{json,md}.  Run:
``python benchmarks/process_spread.py``; ``--quick`` (two processes per
setting, into a temporary directory) only checks that the script works.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

if __name__ == "__main__" and len(sys.argv) > 2 and sys.argv[1] == "--one":
    os.environ["XLA_FLAGS"] = sys.argv[2]

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import lierk  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402

SETTINGS = {
    "default": "",
    "--xla_cpu_multi_thread_eigen=false": "--xla_cpu_multi_thread_eigen=false",
    "the same and intra_op_parallelism_threads=1": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
}
SOLVERS = {
    "RKMK4": lambda: lierk.RKMK4(),
    "RKMK(DOPRI54)": lambda: lierk.RKMK(lierk.tableaux.DOPRI54),
    "RKMK(DOP853)": lambda: lierk.RKMK(lierk.tableaux.DOP853),
}
N, DT, STEPS = 1000, 0.2, 50


def one() -> dict:
    """This process's median time (s) of each program."""
    inertia = lierk.inertia.tee_handle()
    omegas = jax.numpy.asarray(common.near_axis(np.diag(np.asarray(inertia)), N)[0])
    out = {}
    for name, make in SOLVERS.items():
        solver = make()

        @jax.jit
        def run(ws, solver=solver):
            return jax.vmap(
                lambda w: lierk.solve(lierk.FreeRigidBody(inertia, w), solver, DT * STEPS, dt=DT, max_steps=STEPS).R[-1]
            )(ws)

        _, out[name], _ = common.timed(run, omegas, repeats=30)
    return out


def main() -> None:
    quick, out_dir = common.cli(__doc__, "two processes per setting, into a temp dir", run=True)
    processes = 2 if quick else 6
    runs = {}
    for label, flags in SETTINGS.items():
        runs[label] = []
        for i in range(processes):
            p = subprocess.run([sys.executable, __file__, "--one", flags], capture_output=True, text=True, check=True)
            runs[label].append(json.loads(p.stdout.strip().splitlines()[-1]))
            print(label, i, {k: f"{v * 1e3:.2f} ms" for k, v in runs[label][-1].items()}, flush=True)
    record = {
        "machine": common.machine_info(),
        "commit": common.git_commit(),
        "n": N,
        "dt": DT,
        "steps": STEPS,
        "flags": SETTINGS,
        "processes": processes,
        "median_s": runs,
    }
    lines = [
        "# One program, several processes (`benchmarks/process_spread.py`)",
        "",
        f"{os.cpu_count()} cores, {common.cpu_model()}, {common.backend_text(record['machine'])}; "
        f"jax {jax.__version__}.  {N} T-handles near the intermediate axis, "
        f"{STEPS} fixed steps of {DT} s, jit(vmap) on one device, float64.  Each cell: the median of 30 calls "
        f"in one fresh process (ms); {processes} processes per setting, taken in turn.",
        "",
        "| setting | " + " | ".join(SOLVERS) + " |",
        "|---|" + "---|" * len(SOLVERS),
    ]
    for label, rows in runs.items():
        cells = []
        for name in SOLVERS:
            ms = sorted(r[name] * 1e3 for r in rows)
            cells.append(", ".join(f"{x:.1f}" for x in ms) + f" (max/min {ms[-1] / ms[0]:.2f})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    common.write_results(out_dir, "process_spread", record, lines)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        print(json.dumps(one()))
    else:
        main()
