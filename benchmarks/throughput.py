"""Body-steps per second of the batched fixed-step solve.

For every fixed-step solver, batch sizes 1 ... 10000 and float64/float32, a
jitted ``vmap`` over omega0 of ``lierk.solve(FreeRigidBody(tee_handle, omega0),
solver, n*dt, dt=dt, max_steps=n)`` is compiled (timed separately), warmed up,
and run at least ``--repeats`` times with ``block_until_ready``, more (up to
51) until the runs add up to 0.5 s (``--quick``: no minimum); the median run
time gives
``batch * n / t`` body-steps per second.

The CPU is split into ``--devices`` XLA host devices (default: one per core),
which the script must set through ``XLA_FLAGS`` before jax is imported; the
library itself never does this.  A batch that divides evenly among the devices
is sharded over them (`NamedSharding` over the batch axis, as
`lierk.sweep` does); batch 1000 is also timed on a single device for
comparison.  Fewer steps are used for large batches to bound the run time.

``--through-sweep`` times every cell a second time through `lierk.sweep`
(the same per-member function, the NumPy batch, each device stepping its
rows in the default cache blocks; ``shard=False`` for the one-device
cells), interleaved with the ``jit(vmap)`` run, and adds a table of the
ratio sweep / ``jit(vmap)``.  ``--batches``, ``--solvers`` and ``--steps``
narrow a run, e.g. ``--through-sweep --batches 8192 10000 --solvers RKMK4
DOP853 --steps 1000``.

Run: ``python benchmarks/throughput.py [--quick] [--devices N] [--repeats N]
[--through-sweep] [--batches B ...] [--solvers NAME ...] [--steps N] [--out DIR]``;
writes benchmarks/results/throughput.json and throughput.md (``--quick``: a
temporary directory; a run narrowed by ``--batches``, ``--solvers`` or
``--steps``: throughput-narrowed.json and .md).
"""

from __future__ import annotations

import os

import common


def _options(parser):
    parser.add_argument(
        "--devices", type=int, default=os.cpu_count() or 1, help="XLA host devices (default: CPU count)"
    )
    parser.add_argument("--repeats", type=int, default=5, help="timed runs at least (default 5)")
    parser.add_argument("--through-sweep", action="store_true", help="time each cell through lierk.sweep too")
    parser.add_argument("--batches", type=int, nargs="+", default=None, help="batch sizes (default 1 ... 10000)")
    parser.add_argument("--solvers", nargs="+", default=None, help="solver names, e.g. RKMK4 DOP853 (default all)")
    parser.add_argument("--steps", type=int, default=None, help="steps per run (default: a budget per batch)")


QUICK, OUT, ARGS = common.cli(
    __doc__, "tiny run: batches 1 and 1000, few steps, two solvers", __name__ == "__main__", extra=_options
)

import host_devices  # noqa: E402

host_devices.split(ARGS.devices)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import json  # noqa: E402
import time  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

import lierk  # noqa: E402

DT = 0.01
# Runs of a few ms are repeated until they add up to this (common.timed): the
# median of a handful of such runs moved 2x between two runs of this script.
MIN_TIME = 0.0 if QUICK else 0.5
SOLVERS = [
    lierk.ExplicitEuler(),
    lierk.LieEuler(),
    lierk.NaiveLieRK4(),
    lierk.RKMK4(),
    lierk.CF4(),
    lierk.RKMK(lierk.tableaux.RK4),
    lierk.DP54(),
    lierk.DOP853(),
]


def label(solver) -> str:
    if isinstance(solver, lierk.RKMK):
        return "RKMK(RK4)"
    return solver.name + (" (fixed dt)" if solver.adaptive else "")


def budget_steps(solver, batch: int, quick: bool) -> int:
    # About 1e6 stage evaluations per timed run (2e5 with --quick), 20 to 1000 steps.
    budget = (2e5 if quick else 1e6) / solver.stages
    return int(min(1000, max(20, budget // batch)))


def measure(solver, batch: int, dtype, n: int, devices: list, repeats: int, through_sweep: bool = False) -> dict:
    inertia = jnp.asarray(lierk.inertia.tee_handle(), dtype)
    rng = np.random.default_rng(0)
    host = (rng.normal(size=(batch, 3)) * [1.0, 0.05, 0.3]).astype(dtype)
    omegas = jnp.asarray(host)
    if len(devices) > 1:
        omegas = jax.device_put(omegas, NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch")))
    else:
        omegas = jax.device_put(omegas, devices[0])

    def one(omega0):
        body = lierk.FreeRigidBody(inertia, omega0)
        return lierk.solve(body, solver, n * DT, dt=DT, max_steps=n).R[-1]

    final_R = jax.jit(jax.vmap(one))
    t = time.perf_counter()
    compiled = final_R.lower(omegas).compile()
    compile_s = time.perf_counter() - t
    sweep = {}
    if through_sweep:
        # Each timed twice, alternating, the better median kept: a change of
        # load during the cell hits both.
        def through(_):
            return lierk.sweep(one, host, shard=len(devices) > 1)

        jax.block_until_ready(through(None))
        (out, run_a, first_s), (out_s, sweep_a, _), (_, run_b, _), (_, sweep_b, _) = [
            common.timed(f, x, repeats=repeats, min_time=MIN_TIME / 2)
            for _ in range(2)
            for f, x in ((compiled, omegas), (through, None))
        ]
        run_s, sweep_s = min(run_a, run_b), min(sweep_a, sweep_b)
        diff = float(jnp.max(jnp.abs(out_s - out)))
        sweep = {"sweep_run_s_median": sweep_s, "sweep_body_steps_per_s": batch * n / sweep_s, "sweep_max_diff": diff}
    else:
        out, run_s, first_s = common.timed(compiled, omegas, repeats=repeats, min_time=MIN_TIME)
    assert out.dtype == dtype and bool(jnp.all(jnp.isfinite(out)))
    return {
        "solver": label(solver),
        "dtype": jnp.dtype(dtype).name,
        "batch": batch,
        "devices": len(devices),
        "steps": n,
        "compile_s": compile_s,
        "first_run_s": first_s,
        "run_s_median": run_s,
        "body_steps_per_s": batch * n / run_s,
        **sweep,
    }


def main():
    quick = QUICK
    batches = ARGS.batches or ([1, 1000] if quick else [1, 10, 100, 1000, 10000])
    solvers = [lierk.LieEuler(), lierk.RKMK4()] if quick else SOLVERS
    if ARGS.solvers:
        by_name = {label(s).split(" ")[0].upper(): s for s in SOLVERS}
        unknown = [name for name in ARGS.solvers if name.upper() not in by_name]
        if unknown:
            raise SystemExit(f"--solvers: unknown {unknown}; choose from {sorted(by_name)}")
        solvers = [by_name[name.upper()] for name in ARGS.solvers]
    narrowed = ARGS.batches is not None or ARGS.solvers is not None or ARGS.steps is not None
    all_devices = jax.devices()
    info = common.machine_info()
    info["device_count"] = len(all_devices)
    print(json.dumps(info))
    t_start = time.perf_counter()
    rows = []
    for dtype in (jnp.float64, jnp.float32):
        for solver in solvers:
            for batch in batches:
                configs = []
                if len(all_devices) > 1 and batch % len(all_devices) == 0 and batch >= 100:
                    configs.append(all_devices)
                if not configs or batch == 1000:
                    configs.append(all_devices[:1])
                for devs in configs:
                    steps = ARGS.steps or budget_steps(solver, batch, quick)
                    r = measure(solver, batch, dtype, steps, devs, ARGS.repeats, ARGS.through_sweep)
                    rows.append(r)
                    print(
                        f"{r['solver']:18s} {r['dtype']:8s} batch {batch:6d} dev {r['devices']}  "
                        f"{r['body_steps_per_s']:.3e} body-steps/s  (compile {r['compile_s']:.2f} s, "
                        f"run {r['run_s_median'] * 1e3:.1f} ms, {r['steps']} steps)"
                        + (f"  sweep {r['sweep_body_steps_per_s']:.3e}" if "sweep_body_steps_per_s" in r else ""),
                        flush=True,
                    )
    info["total_s"] = time.perf_counter() - t_start
    info["load_average_at_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None

    common.write_results(
        OUT,
        "throughput-narrowed" if narrowed else "throughput",
        {"machine": info, "dt": DT, "quick": quick, "results": rows},
        markdown(rows, info, batches),
    )
    print(f"({info['total_s']:.0f} s)")


def markdown(rows, info, batches) -> str:
    lines = [
        "# Throughput: body-steps per second",
        "",
        f"jax {info['jax']}, {info['cpu_count']} CPUs, {info['device_count']} XLA host device(s), "
        f"{info['platform']}.  Load average at start {info['load_average_at_start']}.",
        "",
        f"Median of at least {ARGS.repeats} runs after compile and warm-up, more until they add up to {MIN_TIME} s.",
        "Batches that divide evenly among the devices are sharded over all of them; `batch 1000 (1 dev)` is the",
        "same run on one device.",
        "",
    ]
    for dtype in ("float64", "float32"):
        sub = [r for r in rows if r["dtype"] == dtype]
        if not sub:
            continue
        cols = [(b, None) for b in batches]
        if any(r["batch"] == 1000 and r["devices"] == 1 for r in sub) and info["device_count"] > 1:
            cols.append((1000, 1))
        head = " | ".join(f"batch {b}" + (" (1 dev)" if d == 1 else "") for b, d in cols)
        lines += [f"## {dtype}", "", f"| solver | {head} | compile (s) |", "|---|" + "---:|" * (len(cols) + 1)]
        for name in dict.fromkeys(r["solver"] for r in sub):
            cells = []
            for b, d in cols:
                cand = [r for r in sub if r["solver"] == name and r["batch"] == b and (d is None or r["devices"] == d)]
                # Without a device filter, report the most-devices configuration.
                cand.sort(key=lambda r: -r["devices"])
                cells.append(f"{cand[0]['body_steps_per_s']:.2e}" if cand else "-")
            comp = [r["compile_s"] for r in sub if r["solver"] == name]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {np.median(comp):.2f} |")
        lines.append("")
        timed_both = [r for r in sub if "sweep_body_steps_per_s" in r]
        if timed_both:
            lines += [
                f"### {dtype} through `lierk.sweep` (default cache blocks) against `jit(vmap)`",
                "",
                "| solver | batch | devices | steps | jit(vmap) body-steps/s | lierk.sweep body-steps/s | ratio "
                "| max diff |",
                "|---|---:|---:|---:|---:|---:|---:|---:|",
            ]
            for r in timed_both:
                ratio = r["sweep_body_steps_per_s"] / r["body_steps_per_s"]
                lines.append(
                    f"| {r['solver']} | {r['batch']} | {r['devices']} | {r['steps']} | {r['body_steps_per_s']:.2e} | "
                    f"{r['sweep_body_steps_per_s']:.2e} | {ratio:.2f} | {r['sweep_max_diff']:.1e} |"
                )
            lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
