"""Claim: a scene with no effects runs within 10% of `FreeRigidBody` solved directly.

A scene without ``[[effects]]`` builds a plain `lierk.FreeRigidBody`, so both
sides compile the same program; this measures it.  For scale it also times the
same body as `RigidBodyWithEffects` with no effects (momentum carried as
state) and with damping only.

Run: ``python benchmarks/scene_overhead.py [--quick] [--out DIR]`` (writes
``benchmarks/results/scene_overhead.json``; ``--quick``: 3 repeats, into a
temporary directory).  Times are medians over repeats of compiled runs,
interleaved so machine noise hits every variant alike.
"""

from __future__ import annotations

import json
import pathlib
import platform
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import common  # noqa: E402

import lierk  # noqa: E402
from lierk import Damping, RigidBodyWithEffects  # noqa: E402
from lierk.app import scene as scene_mod  # noqa: E402

QUICK, OUT = common.cli(__doc__, "3 repeats, into a temp dir", __name__ == "__main__")
HERE = pathlib.Path(__file__).resolve().parent
EXAMPLE = HERE.parent / "examples" / "tee_handle_a.toml"
REPEATS = 3 if QUICK else 15


def compiled(problem, solver, t1, dt, every):
    saveat = lierk.SaveAt(t0=True, steps=every, t1=True)
    # Under jit t1 and dt are traced, so the step count is passed statically.
    n = lierk.num_steps(0.0, t1, dt)
    f = jax.jit(lambda p: lierk.solve(p, solver, t1, dt=dt, saveat=saveat, max_steps=n).R)
    jax.block_until_ready(f(problem))  # compile
    return lambda: jax.block_until_ready(f(problem))


def main():
    scene = scene_mod.load(EXAMPLE)
    t1, dt, every = scene.t1, scene.solve_kwargs["dt"], scene.saveat_every
    direct = lierk.FreeRigidBody(lierk.inertia.tee_handle(), scene.problem.omega0)
    I, w0 = scene.problem.inertia, scene.problem.omega0
    variants = {
        "scene (no effects)": scene.problem,
        "FreeRigidBody direct": direct,
        "RigidBodyWithEffects, effects=()": RigidBodyWithEffects(I, w0),
        "RigidBodyWithEffects, Damping only": RigidBodyWithEffects(I, w0, effects=(Damping(1e-6),)),
    }
    runs = {k: compiled(p, scene.solver, t1, dt, every) for k, p in variants.items()}
    times = {k: [] for k in runs}
    for _ in range(REPEATS):
        for k, run in runs.items():
            t = time.perf_counter()
            run()
            times[k].append(time.perf_counter() - t)
    med = {k: statistics.median(v) for k, v in times.items()}
    ratio = med["scene (no effects)"] / med["FreeRigidBody direct"]
    result = {
        "claim": "a scene with no effects runs within 10% of FreeRigidBody solved directly",
        "scene": EXAMPLE.name,
        "solver": scene.solver.name,
        "t1": t1,
        "dt": dt,
        "steps": lierk.num_steps(0.0, t1, dt),
        "repeats": REPEATS,
        "median_seconds": med,
        "min_seconds": {k: min(v) for k, v in times.items()},
        "scene_over_direct": ratio,
        "claim_holds": ratio <= 1.10,
        "relative_to_direct": {k: v / med["FreeRigidBody direct"] for k, v in med.items()},
        "machine": {
            "python": platform.python_version(),
            "jax": jax.__version__,
            "cpu": platform.processor() or platform.machine(),
        },
    }
    out = OUT / "scene_overhead.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    for k, v in med.items():
        print(f"{k:40s} {1e3 * v:8.2f} ms  ({v / med['FreeRigidBody direct']:.3f}x)")
    print(f"scene / direct = {ratio:.3f} -> claim {'holds' if result['claim_holds'] else 'FAILS'}; wrote {out}")


if __name__ == "__main__":
    main()
