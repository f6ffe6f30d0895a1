"""How fast XLA on CPU can run RKMK4 when the step is written per component:
the ceiling of issue 24 (sweeps at the structure-of-arrays limit).

`lierk.sweep` runs ``jit(vmap(solve))``.  Under ``vmap`` every vector of the
step is a ``(B, 3)`` array whose minor dimension is the component, so the
cross products and the stage sums shuffle components inside each fused loop,
and XLA on CPU splits a step into about 20 kernels (the loop-body kernels are
counted below).  The C anchor (``anchors/rkmk4_soa.c``) keeps each component
of each body in its own array, ``(3, B)``, so that one loop over the bodies
does a whole step in SIMD registers.

This script writes lierk's RKMK4 (the same method, coefficients and
Newton-Schulz step as `lierk.solve(FreeRigidBody(...), RKMK4())`, with
`lierk.so3.exp_coefficients` for the exponential) directly on ``(B,)``
component arrays inside one ``lax.fori_loop``, two ways:

- ``plain``: as written.  XLA on CPU has no multi-output loop fusion, so a
  value that several outputs need is either stored or recomputed; here it
  recomputes the whole RK4 chain inside each of the 12 state updates.
- ``stage boundaries``: each stage's results pass through a ``lax.cond``
  whose predicate XLA cannot fold, so they are stored once (an
  ``optimization_barrier`` is removed before fusion on CPU and does not
  do this).

Side by side in one run, each on both cores (2 host devices): `lierk.sweep`,
the two component-wise programs and the structure-of-arrays anchors of
`native.py` (C when a compiler is present, numba), batch 10000, 1000 steps of
0.01 s on the T-handle, float64 and float32, with the largest difference of
R(T) from `lierk.sweep`.

Run: ``python benchmarks/xla_soa.py [--quick] [--out DIR]``; writes
xla_soa.json and xla_soa.md to benchmarks/results.
"""

from __future__ import annotations

import functools
import os
import re

# First: sweep.py splits the CPU into one XLA host device per core before jax
# is imported, and holds the RKMK4 program and batch this script compares.
import sweep  # isort: skip

import common
import jax
import jax.numpy as jnp
import native
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import lierk

QUICK, OUT = common.cli(__doc__, "small sizes (batch 1000, 100 steps), written to a temp dir", __name__ == "__main__")
DT = sweep.DT
INERTIA = np.asarray(sweep.INERTIA, np.float64)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _stage(inv, y, u):
    """``(k, m')`` at momentum ``y`` and algebra point ``u``, per component:
    ``k = omega + u x omega / 2 + u x (u x omega) / 12``, ``m' = y x omega``."""
    w = tuple(inv[i] * y[i] for i in range(3))
    a = _cross(u, w)
    b = _cross(u, a)
    return tuple(w[i] + 0.5 * a[i] + b[i] / 12.0 for i in range(3)), _cross(y, w)


def _step(inv, m, r, h, boundary):
    """One RKMK4 step on component tuples: ``m`` 3 arrays, ``r`` 3x3 arrays."""
    z = tuple(jnp.zeros_like(m[0]) for _ in range(3))
    k1, d1 = boundary(_stage(inv, m, z))
    k2, d2 = boundary(_stage(inv, tuple(m[i] + 0.5 * h * d1[i] for i in range(3)), tuple(0.5 * h * k for k in k1)))
    k3, d3 = boundary(_stage(inv, tuple(m[i] + 0.5 * h * d2[i] for i in range(3)), tuple(0.5 * h * k for k in k2)))
    k4, d4 = _stage(inv, tuple(m[i] + h * d3[i] for i in range(3)), tuple(h * k for k in k3))
    u, m = boundary(
        (
            tuple(h / 6 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i]) for i in range(3)),
            tuple(m[i] + h / 6 * (d1[i] + 2 * d2[i] + 2 * d3[i] + d4[i]) for i in range(3)),
        )
    )
    x = u[0] * u[0] + u[1] * u[1] + u[2] * u[2]
    A, B, _ = boundary(lierk.so3.exp_coefficients(x))
    c = 1.0 - B * x
    e = (
        (c + B * u[0] * u[0], B * u[0] * u[1] - A * u[2], B * u[0] * u[2] + A * u[1]),
        (B * u[0] * u[1] + A * u[2], c + B * u[1] * u[1], B * u[1] * u[2] - A * u[0]),
        (B * u[0] * u[2] - A * u[1], B * u[1] * u[2] + A * u[0], c + B * u[2] * u[2]),
    )
    r = tuple(tuple(r[i][0] * e[0][j] + r[i][1] * e[1][j] + r[i][2] * e[2][j] for j in range(3)) for i in range(3))
    if jnp.finfo(m[0].dtype).bits < 64:  # lierk.so3.reorthonormalize: R (3 I - R^T R) / 2
        s = [[sum(r[k][i] * r[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        r = tuple(
            tuple(1.5 * r[i][j] - 0.5 * sum(r[i][k] * s[k][j] for k in range(3)) for j in range(3)) for i in range(3)
        )
    return m, r


def final_R_components(omega0, n_steps: int, barriers: bool):
    """``R(n_steps DT)`` ``(B, 3, 3)`` from ``R0 = I`` for ``omega0`` ``(B, 3)``."""
    dtype = omega0.dtype
    inertia = np.diag(INERTIA).astype(dtype)
    inv = tuple(1.0 / inertia)
    one, zero = jnp.ones_like(omega0[:, 0]), jnp.zeros_like(omega0[:, 0])

    def body(i, carry):
        if barriers:
            pred = i >= 0  # always true, but XLA cannot fold it

            def boundary(values):
                return jax.lax.cond(pred, lambda v: v, lambda v: jax.tree.map(jnp.negative, v), values)
        else:

            def boundary(values):
                return values

        return _step(inv, *carry, jnp.asarray(DT, dtype), boundary)

    m = tuple(omega0[:, i] * inertia[i] for i in range(3))
    r = ((one, zero, zero), (zero, one, zero), (zero, zero, one))
    _, r = jax.lax.fori_loop(0, n_steps, body, (m, r))
    return jnp.stack([jnp.stack(row, -1) for row in r], -2)


def loop_body_fusions(compiled) -> int:
    """Kernels (fusions and dots) in the largest while-loop body of a
    compiled program: the step, run once per step."""
    text = compiled.as_text()
    names = set(re.findall(r"while\(.*?body=%?([\w.\-]+)", text))
    computations = {c.split(" ", 1)[0].lstrip("%"): c for c in re.split(r"\n(?=\S)", text)}
    return max(len(re.findall(r" (?:fusion|dot)\(", computations[n])) for n in names if n in computations)


def run(batch: int, n_steps: int, repeats: int, dtype) -> dict:
    sharding = NamedSharding(Mesh(np.array(jax.devices()), ("batch",)), PartitionSpec("batch"))
    w = sweep.omegas(batch, dtype)
    w_dev = jax.device_put(w, sharding)
    inertia = jnp.asarray(INERTIA, dtype)
    lierk_fn = jax.jit(jax.vmap(functools.partial(sweep.final_R, inertia, n_steps)))
    programs = {
        "lierk.sweep (jit(vmap(solve)))": lierk_fn,
        "components, plain": jax.jit(functools.partial(final_R_components, n_steps=n_steps, barriers=False)),
        "components, stage boundaries": jax.jit(functools.partial(final_R_components, n_steps=n_steps, barriers=True)),
    }
    fusions = {name: loop_body_fusions(f.lower(w_dev).compile()) for name, f in programs.items()}
    threads = os.cpu_count() or 1
    calls = {name: functools.partial(f, w_dev) for name, f in programs.items()}
    if dtype == np.float64 and native.build_c_soa() is None:
        calls[f"C structure of arrays, {threads} threads"] = functools.partial(
            native.c_soa_final_R, INERTIA, w, DT, n_steps, threads
        )
    calls[f"numba structure of arrays, {threads} threads"] = functools.partial(
        native.rkmk4_soa_final_R, INERTIA, w, DT, n_steps, threads
    )
    outs = {name: np.asarray(jax.block_until_ready(call())) for name, call in calls.items()}
    times = sweep.interleaved(calls, repeats)
    ref = outs["lierk.sweep (jit(vmap(solve)))"]
    anchor = max((n for n in calls if "structure of arrays" in n), key=lambda n: -min(times[n]))
    rows = {}
    for name, ts in times.items():
        rate = batch * n_steps / min(ts)
        rows[name] = {
            "min_s": min(ts),
            "median_s": float(np.median(ts)),
            "body_steps_per_s": rate,
            "ratio_to_anchor": rate * min(times[anchor]) / (batch * n_steps),
            "loop_body_fusions": fusions.get(name),
            "max_diff_to_lierk": float(np.max(np.abs(outs[name] - ref))),
        }
    return {"batch": batch, "steps": n_steps, "dtype": np.dtype(dtype).name, "anchor": anchor, "rows": rows}


def markdown(res: dict) -> str:
    lines = [
        "# RKMK4 per component in XLA: the ceiling (`benchmarks/xla_soa.py`)",
        "",
        f"{res['machine']['cpu_count']} cores ({res['machine']['cpu_model']}), {res['machine']['devices']} XLA host "
        f"devices, jax {res['machine']['jax']}; load average {res['machine']['load_start'][0]:.1f} at the start, "
        f"{res['machine']['load_end'][0]:.1f} at the end. Minimum of {res['repeats']} interleaved calls.",
    ]
    for t in res["runs"]:
        lines += [
            "",
            f"## Batch {t['batch']}, {t['steps']} steps, {t['dtype']}",
            "",
            f"| program | loop-body kernels | body-steps/s | / {t['anchor']} | max diff of R(T) to lierk |",
            "|---|---:|---:|---:|---:|",
        ]
        for name, r in t["rows"].items():
            k = "" if r["loop_body_fusions"] is None else str(r["loop_body_fusions"])
            lines.append(
                f"| {name} | {k} | {r['body_steps_per_s']:.2e} | {r['ratio_to_anchor']:.2f} | "
                f"{r['max_diff_to_lierk']:.1e} |"
            )
    return "\n".join(lines) + "\n"


def main():
    batch, steps, repeats = (1000, 100, 3) if QUICK else (10000, 1000, 5)
    machine = {
        "cpu_count": os.cpu_count(),
        "cpu_model": common.cpu_model(),
        "devices": jax.device_count(),
        "jax": jax.__version__,
        "load_start": os.getloadavg(),
    }
    runs = []
    for dtype in (np.float64, np.float32):
        runs.append(run(batch, steps, repeats, dtype))
        for name, r in runs[-1]["rows"].items():
            print(
                f"{runs[-1]['dtype']:8s} {name:40s} {r['body_steps_per_s']:.3e} body-steps/s  "
                f"{r['ratio_to_anchor']:.2f}x anchor  kernels {r['loop_body_fusions']}  "
                f"diff {r['max_diff_to_lierk']:.1e}",
                flush=True,
            )
    machine["load_end"] = os.getloadavg()
    res = {"machine": machine, "quick": QUICK, "repeats": repeats, "runs": runs}
    common.write_results(OUT, "xla_soa", res, markdown(res))


if __name__ == "__main__":
    main()
