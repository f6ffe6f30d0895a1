"""The report's T-handle experiment (its figures 14-16), as a script.

    python -m lierk.app.demo --out out

Three initial body angular velocities (rad/s) of the torque-free T-handle
(`lierk.inertia.tee_handle`), each integrated for 100 s with `RKMK4` at
``dt = 0.01`` s; one 3x3 grid of the components of ``R(t)`` per case:

    a  (1, 0.05, 0)    spin about x, the intermediate axis: it flips
    b  (0, 1, 0.05)    spin about y, the smallest inertia: stable
    c  (0.05, 0, 1)    spin about z, the largest inertia: stable

For case a the time between flips predicted by the exact solution
(`lierk.exact.flip_interval`) is printed next to the figure.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

CASES = {
    "a": ((1.0, 0.05, 0.0), "spin about x, the intermediate axis"),
    "b": ((0.0, 1.0, 0.05), "spin about y, the smallest inertia"),
    "c": ((0.05, 0.0, 1.0), "spin about z, the largest inertia"),
}
T1 = 100.0
DT = 0.01


def run(out: Path, t1: float = T1, dt: float = DT, cases=tuple(CASES)) -> dict[str, Path]:
    """Solve and plot the chosen cases; returns ``{case: png path}``."""
    import jax.numpy as jnp

    import lierk
    from lierk.app import plot

    out.mkdir(parents=True, exist_ok=True)
    inertia = lierk.inertia.tee_handle()
    solver = lierk.RKMK4()
    paths = {}
    for case in cases:
        omega0, what = CASES[case]
        problem = lierk.FreeRigidBody(inertia, jnp.asarray(omega0, dtype=inertia.dtype))
        sol = lierk.solve(problem, solver, t1, dt=dt, saveat=lierk.SaveAt(t0=True, steps=True))
        w = ", ".join(f"{x:g}" for x in omega0)
        title = f"T-handle case {case}: $\\omega_0$ = ({w}) rad/s, {what}\n{solver.name}, dt = {dt:g} s"
        fig = plot.components(sol, title)
        path = out / f"tee_handle_{case}.png"
        fig.savefig(path, dpi=100)
        paths[case] = path
        print(f"case {case}: omega0 = ({w}) rad/s -> {path}")
        if case == "a":
            try:
                from lierk.exact import flip_interval
            except ImportError:
                continue
            T = float(flip_interval(inertia, problem.omega0))
            print(f"  intermediate-axis flip every {T:.2f} s (exact solution): {int(t1 // T)} flips in {t1:g} s")
    return paths


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m lierk.app.demo",
        description="The report's T-handle cases a, b, c (figures 14-16): "
        "3x3 grids of R(t) components, one PNG per case.",
    )
    parser.add_argument("--out", type=Path, default=Path("out"), help="output directory (default: out)")
    parser.add_argument("--t1", type=float, default=T1, help=f"end time in s (default: {T1:g})")
    parser.add_argument("--float32", action="store_true", help="run in single precision (default: double)")
    args = parser.parse_args(argv)
    if not args.t1 > 0:
        parser.error(f"--t1 must be > 0, got {args.t1}")
    import jax

    # This script is an application, like the benchmarks: it picks its own
    # precision, scoped to this call; the global config is left alone.
    with jax.enable_x64(not args.float32):
        run(args.out, t1=args.t1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
