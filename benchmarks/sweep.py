"""Sweeps at scale: `lierk.sweep` compiles once, its throughput, and a native anchor.

Part 1, compiled once.  RKMK4 on the momentum-state T-handle, batch 2000,
200 steps, float64, the batch sharded over the host devices.  Side by side in
one loop (interleaved, so that a change of machine load hits all alike):

- a held ``jax.jit(jax.vmap(f))`` given the batch already on the devices (the
  floor), and given the NumPy batch with a ``device_put`` in the timing;
- `lierk.sweep` on the NumPy batch: the same values, new values each call, a
  new `functools.partial` holding a new inertia array each call, and
  `lierk.sweep_chunks` in chunks of 500 copied to the host;
- what `lierk.sweep` did before it cached: a new ``jit(vmap(f))`` per call.

Part 2, throughput.  Batch 10000, 1000 steps (10 s at dt = 0.01 s), float64
and float32, on the T-handle (diagonal inertia): body-steps per second
through `lierk.sweep`, next to the held jit and to the native anchors of
`native.py`: the structure-of-arrays kernel of issue 24 in C (built here with
its own line when a compiler is present, float64, 2 threads and 1) and in
numba (float64 and float32), and the numba kernel that integrates one body at
a time.  lierk's ratio is to the fastest structure-of-arrays anchor of the
dtype; the largest differences of the final attitudes are recorded.

Part 3, every solver.  Batch 10000, 200 steps, float64, through
`lierk.sweep`: RKMK4, RKMK(DOP853) and CF4 on the free T-handle, RKMK4 and
RKMK(DOP853) on a heavy top (`Gravity`, the stage rotation of the vertical).

Part 4, cache blocks.  Batches 8192 and 10000, RKMK4 with fixed steps
(1000 steps) and DOP853 with adaptive steps (rtol = atol = 1e-8 in float64,
1e-5 in float32, over the same 10 s), float64 and float32: a held ``jax.jit(jax.vmap(f))`` given the
batch already on the devices, against `lierk.sweep` with its default
``cache_chunk`` (each device steps its rows in blocks sized to the core's
L2 cache) and with ``cache_chunk=batch`` (one block per device, the plain
vmap inside `lierk.sweep`), interleaved in one loop.

Every time is the minimum of the repeats after compile and warm-up (medians
are in the JSON).  The CPU is split into one XLA host device per core
(``XLA_FLAGS``, set here before jax is imported; the library never does).

Run: ``python benchmarks/sweep.py [--quick] [--only cache-blocks] [--out
DIR]``; writes sweep.json and sweep.md to benchmarks/results (``--quick``:
small sizes, to a temp dir; ``--only cache-blocks``: part 4 alone, to
sweep-cache-blocks.json and .md).
"""

from __future__ import annotations

import os

import host_devices

_DEVICES = host_devices.split()  # one XLA host device per core

import functools  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import common  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import native  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

import lierk  # noqa: E402


def _options(parser):
    parser.add_argument("--only", choices=["cache-blocks"], default=None, help="run part 4 alone")


QUICK, OUT, ARGS = common.cli(
    __doc__, "small sizes (batch 1000, 100 steps), written to a temp dir", __name__ == "__main__", extra=_options
)
DT = 0.01
RTOL = {"float64": 1e-8, "float32": 1e-5}  # DOP853's adaptive cells, per dtype
INERTIA = lierk.inertia.tee_handle()


def final_R(inertia, n_steps, omega0):
    """``R(n_steps DT)`` ``(3, 3)`` of RKMK4 from ``R0 = I``, ``omega0`` ``(3,)`` rad/s."""
    body = lierk.FreeRigidBody(inertia, omega0)
    return lierk.solve(body, lierk.RKMK4(), n_steps * DT, dt=DT, max_steps=n_steps).R[-1]


def omegas(batch: int, dtype) -> np.ndarray:
    """``(batch, 3)`` body angular velocities (rad/s) around the T-handle's spin."""
    return (np.random.default_rng(0).normal(size=(batch, 3)) * [1.0, 0.05, 0.3]).astype(dtype)


def interleaved(calls: dict, repeats: int) -> dict:
    """``{name: [seconds, ...]}``: each call timed once per round, round after round."""
    times = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(call())
            times[name].append(time.perf_counter() - t)
    return times


def summary(ts) -> dict:
    return {"min_s": float(min(ts)), "median_s": float(np.median(ts)), "runs": len(ts)}


def compile_once(batch: int, n_steps: int, repeats: int) -> dict:
    devices = jax.devices()
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    w = omegas(batch, np.float64)

    def f(omega0):
        return final_R(INERTIA, n_steps, omega0)

    held = jax.jit(jax.vmap(f))
    w_dev = jax.device_put(w, sharding)
    t = time.perf_counter()
    jax.block_until_ready(held(w_dev))
    held_first = time.perf_counter() - t
    t = time.perf_counter()
    ref = np.asarray(jax.block_until_ready(lierk.sweep(f, w)))
    sweep_first = time.perf_counter() - t
    fresh = []
    for _ in range(2):  # the old behaviour compiles every call
        t = time.perf_counter()
        jax.block_until_ready(jax.jit(jax.vmap(f))(jax.device_put(w, sharding)))
        fresh.append(time.perf_counter() - t)

    shift = iter(np.linspace(0.0, 1e-3, 10 * repeats + 10))
    scale = iter(np.linspace(1.0, 1.1, 10 * repeats + 10))
    chunk = max(1, batch // 4)
    calls = {
        "held jit, batch on the devices": lambda: held(w_dev),
        "held jit, NumPy batch + device_put": lambda: held(jax.device_put(w, sharding)),
        "lierk.sweep": lambda: lierk.sweep(f, w),
        "lierk.sweep, new values": lambda: lierk.sweep(f, w + next(shift)),
        "lierk.sweep, new partial(inertia)": lambda: lierk.sweep(
            functools.partial(final_R, INERTIA * next(scale), n_steps), w
        ),
        f"lierk.sweep_chunks, chunks of {chunk}, to host": lambda: [
            out for *_, out in lierk.sweep_chunks(f, w, chunk_size=chunk)
        ],
    }
    for name, call in calls.items():  # compile and warm up each (the partial compiles once)
        jax.block_until_ready(call())
    times = interleaved(calls, repeats)
    floor = min(times["held jit, batch on the devices"])
    rows = {name: {**summary(ts), "ratio_to_held": float(min(ts) / floor)} for name, ts in times.items()}
    err = float(np.max(np.abs(np.asarray(lierk.sweep(f, w)) - ref)))
    return {
        "batch": batch,
        "steps": n_steps,
        "dtype": "float64",
        "devices": len(devices),
        "first_call_s": {"held jit": held_first, "lierk.sweep": sweep_first},
        "new jit(vmap) per call (before the cache), s": fresh,
        "calls": rows,
        "max_diff_between_calls": err,
    }


def throughput(batch: int, n_steps: int, repeats: int, dtype, reference=None) -> dict:
    """Body-steps/s of the three ways; ``reference``: R(T) ``(batch, 3, 3)`` of
    a float64 run, to measure a float32 run's error against."""
    devices = jax.devices()
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    w = omegas(batch, dtype)
    inertia = jnp.asarray(INERTIA, dtype)

    def f(omega0):
        return final_R(inertia, n_steps, omega0)

    held = jax.jit(jax.vmap(f))
    w_dev = jax.device_put(w, sharding)
    threads = os.cpu_count() or 1
    calls = {
        "lierk.sweep": lambda: lierk.sweep(f, w),
        "held jit(vmap)": lambda: held(w_dev),
    }
    soa = []
    c_not_built = native.build_c_soa() if dtype == np.float64 else "float64 only"
    if c_not_built is None:
        for k in sorted({threads, 1}, reverse=True):
            name = f"C structure of arrays, {k} thread{'s' if k > 1 else ''}"
            calls[name] = functools.partial(native.c_soa_final_R, INERTIA, w, DT, n_steps, k)
            soa.append(name)
    name = f"numba structure of arrays, {threads} threads"
    calls[name] = functools.partial(native.rkmk4_soa_final_R, INERTIA, w, DT, n_steps, threads)
    soa.append(name)
    one_body = f"numba one body at a time, {threads} threads"
    calls[one_body] = functools.partial(native.rkmk4_final_R, INERTIA, w, DT, n_steps, threads)
    t = time.perf_counter()
    outs = {name: np.asarray(jax.block_until_ready(call())) for name, call in calls.items()}
    warm_s = time.perf_counter() - t
    times = interleaved(calls, repeats)
    steps = batch * n_steps
    rows = {name: {**summary(ts), "body_steps_per_s": steps / min(ts)} for name, ts in times.items()}
    # The fastest structure-of-arrays anchor of this dtype is the one to beat.
    anchor = max(soa, key=lambda name: rows[name]["body_steps_per_s"])
    for r in rows.values():
        r["ratio_to_anchor"] = r["body_steps_per_s"] / rows[anchor]["body_steps_per_s"]
    errors = {}
    if reference is not None:
        errors = {name: float(np.max(np.abs(out - reference))) for name, out in outs.items()}
    return {
        "batch": batch,
        "steps": n_steps,
        "dtype": np.dtype(dtype).name,
        "devices": len(devices),
        "numba_threads": threads,
        "anchor": anchor,
        "c_build": native.c_soa_build_line() if c_not_built is None else None,
        "c_not_built": c_not_built,
        "max_diff_to_float64": errors,
        "R_T": outs["lierk.sweep"],
        "compile_and_warm_up_s": warm_s,
        "calls": rows,
        "max_diff_lierk_vs_native": {
            name: float(np.max(np.abs(outs["lierk.sweep"] - outs[name]))) for name in soa + [one_body]
        },
        "max_diff_sweep_vs_held": float(np.max(np.abs(outs["lierk.sweep"] - outs["held jit(vmap)"]))),
    }


def solvers(batch: int, n_steps: int, repeats: int) -> dict:
    """Body-steps/s of `lierk.sweep` for the solvers on the free T-handle and
    on a heavy top, float64."""
    w = omegas(batch, np.float64)
    R0 = np.asarray(lierk.so3.exp(np.random.default_rng(1).normal(size=(batch, 3)) * 0.3))
    heavy = [lierk.Gravity(np.array([0.0, 0.0, 0.05]), 0.2, 9.81)]
    cases = {
        "RKMK4, free": (lierk.RKMK4(), DT, ()),
        "RKMK(DOP853), free": (lierk.RKMK(lierk.tableaux.DOP853), 4 * DT, ()),
        "CF4, free": (lierk.CF4(), DT, ()),
        "RKMK4, heavy top": (lierk.RKMK4(), DT, heavy),
        "RKMK(DOP853), heavy top": (lierk.RKMK(lierk.tableaux.DOP853), 4 * DT, heavy),
    }

    def final(solver, dt, effects, omega0, R0):
        body = lierk.RigidBodyWithEffects(INERTIA, omega0, R0, effects=effects)
        return lierk.solve(body, solver, n_steps * dt, dt=dt, max_steps=n_steps).R[-1]

    fns = {name: functools.partial(final, *case) for name, case in cases.items()}
    calls = {name: functools.partial(lierk.sweep, fn, w, R0) for name, fn in fns.items()}
    for call in calls.values():
        jax.block_until_ready(call())
    times = interleaved(calls, repeats)
    rows = {
        name: {**summary(ts), "body_steps_per_s": batch * n_steps / min(ts), "dt": cases[name][1]}
        for name, ts in times.items()
    }
    return {"batch": batch, "steps": n_steps, "dtype": "float64", "calls": rows}


def cache_blocks(batches, n_steps: int, repeats: int) -> list[dict]:
    """Per batch, solver and dtype: the held ``jit(vmap)`` against
    `lierk.sweep` in its default cache blocks and in one block per device."""
    from lierk import _batch

    devices = jax.devices()
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    block = _batch._default_cache_chunk(devices[0].platform)
    t1 = n_steps * DT

    def fixed(inertia, omega0):
        sol = lierk.solve(lierk.FreeRigidBody(inertia, omega0), lierk.RKMK4(), t1, dt=DT, max_steps=n_steps)
        return sol.R[-1], sol.stats["num_steps"]

    def adaptive(inertia, omega0):
        body = lierk.FreeRigidBody(inertia, omega0)
        tol = RTOL[jnp.result_type(omega0).name]
        sol = lierk.solve(body, lierk.DOP853(), t1, rtol=tol, atol=tol, max_steps=20 * n_steps)
        return sol.R[-1], sol.stats["num_steps"]

    cells = []
    for solver, fn in (("RKMK4, fixed dt", fixed), ("DOP853, adaptive", adaptive)):
        for dtype in (np.float64, np.float32):
            f = functools.partial(fn, jnp.asarray(INERTIA, dtype))
            for batch in batches:
                w = omegas(batch, dtype)
                held = jax.jit(jax.vmap(f))
                w_dev = jax.device_put(w, sharding)
                calls = {
                    "held jit(vmap)": lambda: held(w_dev),
                    "lierk.sweep, one block": lambda: lierk.sweep(f, w, cache_chunk=batch),
                    f"lierk.sweep, blocks of {block}": lambda: lierk.sweep(f, w),
                }
                outs = {name: jax.block_until_ready(call()) for name, call in calls.items()}
                times = interleaved(calls, repeats)
                steps = {name: float(np.sum(np.asarray(out[1]))) for name, out in outs.items()}
                rows = {name: {**summary(ts), "body_steps_per_s": steps[name] / min(ts)} for name, ts in times.items()}
                floor = min(times["held jit(vmap)"])
                for name, r in rows.items():
                    r["speedup_over_held"] = floor / r["min_s"]
                R = {name: np.asarray(out[0]) for name, out in outs.items()}
                cells.append(
                    {
                        "solver": solver,
                        "dtype": np.dtype(dtype).name,
                        "batch": batch,
                        "steps": n_steps if fn is fixed else "adaptive",
                        "mean_steps": steps["held jit(vmap)"] / batch,
                        "devices": len(devices),
                        "cache_chunk": block,
                        "calls": rows,
                        "max_diff_to_held": {name: float(np.max(np.abs(R[name] - R["held jit(vmap)"]))) for name in R},
                    }
                )
                c = cells[-1]
                print(
                    f"blocks   {solver:17s} {c['dtype']:8s} batch {batch:6d} "
                    + "  ".join(f"{name} {r['speedup_over_held']:.2f}x" for name, r in rows.items()),
                    flush=True,
                )
    return cells


def cache_blocks_markdown(cells: list[dict]) -> list[str]:
    if not cells:
        return []
    c0 = cells[0]
    lines = [
        "",
        f"## Cache blocks: held `jit(vmap)` against `lierk.sweep`, {c0['devices']} devices",
        "",
        f"`lierk.sweep` with its default `cache_chunk` ({c0['cache_chunk']} on this machine: each device steps its "
        "rows in blocks of at most that many) and with `cache_chunk=batch` (one block per device, a plain vmap "
        "inside `lierk.sweep`), beside a held `jax.jit(jax.vmap(f))` given the batch already on the devices. "
        "RKMK4: 1000 steps of 0.01 s; DOP853: adaptive, rtol = atol = 1e-8 (float64) or 1e-5 (float32) over the "
        "same 10 s (body-steps "
        "counted as the steps each member attempted). Speed-ups are the held jit's minimum time over each "
        "call's.",
        "",
        "Each ratio is given for the minimum times (the least disturbed call) and for the medians (a shared "
        "machine's typical call).",
        "",
        "| solver | dtype | batch | held jit (body-steps/s) | one block / held, min (median) "
        "| blocks / held, min (median) | blocks / one block, min (median) | max diff to held |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for c in cells:
        rows = c["calls"]
        blocked = next(name for name in rows if name.startswith("lierk.sweep, blocks"))
        held, one, blk = rows["held jit(vmap)"], rows["lierk.sweep, one block"], rows[blocked]

        def ratio(slow, fast):
            return f"{slow['min_s'] / fast['min_s']:.2f} ({slow['median_s'] / fast['median_s']:.2f})"

        lines.append(
            f"| {c['solver']} | {c['dtype']} | {c['batch']} | {held['body_steps_per_s']:.2e} | "
            f"{ratio(held, one)} | {ratio(held, blk)} | {ratio(one, blk)} | {c['max_diff_to_held'][blocked]:.1e} |"
        )
    return lines


def _cpu_seconds() -> tuple[float, float]:
    """(seconds all CPUs were busy, seconds this process ran) so far: their
    difference over the run is what others took from the machine."""
    try:
        fields = [float(x) for x in open("/proc/stat").readline().split()[1:]]
        busy = (sum(fields) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")  # minus idle, iowait
    except (OSError, ValueError, IndexError):
        busy = float("nan")
    t = os.times()
    return busy, t.user + t.system


def machine() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "cpu_model": common.cpu_model(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numba": getattr(native.numba, "__version__", None),
        "device_count": jax.device_count(),
        **common.backend_info(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_at_start": os.getloadavg(),
    }


def markdown_header(m: dict, title: str = "Sweeps at scale (`benchmarks/sweep.py`)") -> list[str]:
    return [
        f"# {title}",
        "",
        f"{m['cpu_count']} cores ({m['cpu_model']}), {common.backend_text(m)}, jax {m['jax']}, "
        f"numba {m['numba']}. Other processes kept {m['others_cores_busy']:.2f} of the "
        f"{m['cpu_count']} cores busy during the run (load average {m['load_average_at_start'][0]:.1f} at the "
        f"start, {m['load_average_at_end'][0]:.1f} at the end; a shared machine: read the ratios).",
        "",
    ]


def markdown(res: dict) -> str:
    c = res["compile_once"]
    lines = [
        *markdown_header(res["machine"]),
        f"## Compiled once: RKMK4, batch {c['batch']}, {c['steps']} steps, {c['dtype']}",
        "",
        f"First call: held jit {c['first_call_s']['held jit']:.2f} s, `lierk.sweep` "
        f"{c['first_call_s']['lierk.sweep']:.2f} s (compilation). Before the cache every call compiled: "
        + ", ".join(f"{t:.2f} s" for t in c["new jit(vmap) per call (before the cache), s"])
        + ".",
        "",
        "| call (after the first) | time (ms) | / held jit |",
        "|---|---:|---:|",
    ]
    for name, r in c["calls"].items():
        lines.append(f"| {name} | {1e3 * r['min_s']:.1f} | {r['ratio_to_held']:.2f} |")
    for t in res["throughput"]:
        lines += [
            "",
            f"## Throughput: RKMK4, batch {t['batch']}, {t['steps']} steps, {t['dtype']}",
            "",
            f"| | body-steps/s | / {t['anchor']} |",
            "|---|---:|---:|",
        ]
        for name, r in t["calls"].items():
            lines.append(f"| {name} | {r['body_steps_per_s']:.2e} | {r['ratio_to_anchor']:.2f} |")
        lines += [""]
        if t["c_build"]:
            lines += [f"C built with `{t['c_build']}`."]
        elif t["dtype"] == "float64":
            lines += [f"C anchor not run: {t['c_not_built']}."]
        lines += [
            "Largest difference of R(T), lierk against each anchor: "
            + ", ".join(f"{name} {e:.1e}" for name, e in t["max_diff_lierk_vs_native"].items())
            + "."
        ]
        if t["max_diff_to_float64"]:
            lines += [
                "Against the float64 run (rounding, amplified over the steps near the intermediate axis): "
                + ", ".join(f"{name} {e:.1e}" for name, e in t["max_diff_to_float64"].items())
                + "."
            ]
    v = res["solvers"]
    lines += [
        "",
        f"## Every solver: `lierk.sweep`, batch {v['batch']}, {v['steps']} steps, {v['dtype']}",
        "",
        "| solver, body | dt (s) | body-steps/s |",
        "|---|---:|---:|",
    ]
    for name, r in v["calls"].items():
        lines.append(f"| {name} | {r['dt']:g} | {r['body_steps_per_s']:.2e} |")
    lines += cache_blocks_markdown(res["cache_blocks"])
    return "\n".join(lines) + "\n"


def _finish(info: dict, busy0: float, own0: float, wall0: float) -> None:
    info["load_average_at_end"] = os.getloadavg()
    busy1, own1 = _cpu_seconds()
    # Cores' worth of CPU that other processes used during the run (0 = idle machine).
    info["others_cores_busy"] = ((busy1 - busy0) - (own1 - own0)) / (time.perf_counter() - wall0)


def main():
    info = machine()
    print(json.dumps(info))
    wall0, (busy0, own0) = time.perf_counter(), _cpu_seconds()
    batch1, steps1, batch2, steps2, repeats = (1000, 100, 1000, 100, 3) if QUICK else (2000, 200, 10000, 1000, 7)
    block_batches = (1000,) if QUICK else (8192, 10000)
    res = {"machine": info, "quick": QUICK, "dt": DT}
    if ARGS.only == "cache-blocks":
        res["cache_blocks"] = cache_blocks(block_batches, steps2, 2 * repeats)
        _finish(info, busy0, own0, wall0)
        title = "Sweeps in cache blocks (`benchmarks/sweep.py --only cache-blocks`)"
        lines = markdown_header(info, title) + cache_blocks_markdown(res["cache_blocks"])[1:]
        common.write_results(OUT, "sweep-cache-blocks", res, lines)
        return
    res["compile_once"] = compile_once(batch1, steps1, 2 * repeats)
    for name, r in res["compile_once"]["calls"].items():
        print(f"{name:45s} {1e3 * r['min_s']:8.1f} ms  {r['ratio_to_held']:.2f}x held", flush=True)
    res["throughput"] = []
    reference = None
    for dtype in (np.float64, np.float32):
        t = throughput(batch2, steps2, repeats, dtype, reference)
        reference = t.pop("R_T")
        res["throughput"].append(t)
        for name, r in t["calls"].items():
            print(
                f"{t['dtype']:8s} {name:42s} {r['body_steps_per_s']:.3e} body-steps/s  {r['ratio_to_anchor']:.2f}x "
                f"{t['anchor']}",
                flush=True,
            )
        print(f"{t['dtype']:8s} max |R_lierk - R_native| = {t['max_diff_lierk_vs_native']}", flush=True)
    res["solvers"] = solvers(batch2, steps2 // 5, repeats)
    for name, r in res["solvers"]["calls"].items():
        print(f"solvers  {name:42s} {r['body_steps_per_s']:.3e} body-steps/s", flush=True)
    res["cache_blocks"] = cache_blocks(block_batches, steps2, 2 * repeats)
    _finish(info, busy0, own0, wall0)
    common.write_results(OUT, "sweep", res, markdown(res))


if __name__ == "__main__":
    main()
