"""The two torque-free formulations side by side: FreeRigidBody against SpatialFreeRigidBody.

`lierk.FreeRigidBody` carries the body momentum ``m`` as state (Euler's
equations advanced by the tableau, attitude by RKMK); `lierk.SpatialFreeRigidBody`
is the report's formulation (spatial ``L`` fixed, ``m = R^T L``).  Both are
run with the same solvers on the same batches and compared with the closed
form `lierk.exact.free_rigid_body`.

Bodies (principal moments on the diagonal, kg m^2):

- the report's T-handle, ``lierk.inertia.tee_handle()`` (intermediate axis x);
- a 1:2:3 box, ``lierk.inertia.box(1.0, 1.0, 2.0, 3.0)`` (mass 1 kg, edges
  1, 2, 3 m: moments (13, 10, 5)/12, intermediate axis y);
- Hairer-Lubich-Wanner's body, ``I = (2, 1, 2/3)`` (Geometric Numerical
  Integration, VII.5; intermediate axis y);
- a satellite, ``diag(310, 420, 560)`` (intermediate axis y).

For each: 1000 initial body angular velocities within ~11 degrees of the
intermediate axis, ``|omega|`` in [1, 3] rad/s, ``R0 = I``, ``T = 10`` s.
Error = the largest ``||R(T) - R_exact(T)||_F`` over the batch.  Measured for
each formulation: RKMK4 at dt 0.02 and 0.01 s, CF4 at dt 0.01 s, DOP853 at
rtol = atol = 1e-12 (error, time, steps), and RKMK4's throughput in
body-steps/s.  Every time is the median of 3 calls after a compiling warm-up
call, with ``block_until_ready``; the inertia is an argument of the jitted
functions, so each (formulation, solver, dt) compiles once for all bodies.

Long horizon: the T-handle with omega0 = (1, 0.05, 0) rad/s over 1000 s with
RKMK4 at dt 0.01 s (10^5 steps), error against lierk.exact at t = 1000 s.

Writes benchmarks/results/formulation.{json,md}.
Run: ``python benchmarks/formulation.py`` (about 1 minute on 2 idle cores).
``--quick`` runs a tiny version (20 bodies, T = 2 s, long horizon 20 s, no
repeats) only to check that everything works; it writes to a temporary
directory unless ``--out`` is given.
"""

from __future__ import annotations

import os
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from common import cli, cpu_model, max_err, near_axis, timed, write_results  # noqa: E402

import lierk  # noqa: E402
import lierk.exact  # noqa: E402

QUICK, OUT = cli(__doc__, "tiny run (20 bodies, T = 2 s) to check the script works", __name__ == "__main__")

N = 20 if QUICK else 1000
T = 2.0 if QUICK else 10.0
SEED = 0
REPEATS = 1 if QUICK else 3
DOP853_TOL = 1e-12
MAX_STEPS = 16384  # adaptive bound (accepted + rejected steps)
LONG_OMEGA0 = [1.0, 0.05, 0.0]
LONG_T = 20.0 if QUICK else 1000.0
LONG_DT = 0.01

BODIES = {
    "T-handle": lierk.inertia.tee_handle(),
    "box 1:2:3": lierk.inertia.box(1.0, 1.0, 2.0, 3.0),
    "HLW (2, 1, 2/3)": jnp.diag(jnp.array([2.0, 1.0, 2.0 / 3.0])),
    "satellite (310, 420, 560)": jnp.diag(jnp.array([310.0, 420.0, 560.0])),
}
FORMULATIONS = {"FreeRigidBody": lierk.FreeRigidBody, "SpatialFreeRigidBody": lierk.SpatialFreeRigidBody}
# (key, solver, dt): the fixed-step runs.
FIXED = [
    ("RKMK4 dt 0.02", lierk.RKMK4(), 0.02),
    ("RKMK4 dt 0.01", lierk.RKMK4(), 0.01),
    ("CF4 dt 0.01", lierk.CF4(), 0.01),
]
ADAPTIVE_KEY = f"DOP853 rtol {DOP853_TOL:.0e}"
THROUGHPUT_KEY = "RKMK4 dt 0.01"


def initial_velocities(inertia) -> tuple[np.ndarray, int]:
    return near_axis(np.diag(np.asarray(inertia)), N, SEED)


def fixed_fn(problem, solver, dt, t1):
    n = lierk.num_steps(0.0, t1, dt)

    @jax.jit
    def run(inertia, omegas):
        def one(w):
            return lierk.solve(problem(inertia, w), solver, t1, dt=dt, max_steps=n).R[-1]

        return jax.vmap(one)(omegas)

    return run


def adaptive_fn(problem, solver, t1):
    @jax.jit
    def run(inertia, omegas, tol):
        def one(w):
            sol = lierk.solve(problem(inertia, w), solver, t1, rtol=tol, atol=tol, max_steps=MAX_STEPS, throw=False)
            return sol.R[-1], sol.stats["num_steps"], sol.result

        return jax.vmap(one)(omegas)

    return run


exact_final = jax.jit(jax.vmap(lambda I, w, t: lierk.exact.free_rigid_body(I, w, t)[0], in_axes=(None, 0, None)))
flip_intervals = jax.jit(jax.vmap(lierk.exact.flip_interval, in_axes=(None, 0)))


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg() if hasattr(os, "getloadavg") else None
    t_start = time.perf_counter()
    # One jitted function per (formulation, solver, dt), shared by all bodies.
    fns = {
        (fname, key): fixed_fn(problem, solver, dt, T)
        for fname, problem in FORMULATIONS.items()
        for key, solver, dt in FIXED
    }
    fns.update(
        {(fname, ADAPTIVE_KEY): adaptive_fn(problem, lierk.DOP853(), T) for fname, problem in FORMULATIONS.items()}
    )

    bodies = []
    for bname, inertia in BODIES.items():
        inertia = jnp.asarray(inertia, jnp.float64)
        omegas_np, axis = initial_velocities(inertia)
        omegas = jnp.asarray(omegas_np)
        R_ref = exact_final(inertia, omegas, T)
        frac_flip = float(np.mean(np.asarray(flip_intervals(inertia, omegas)) / 2 < T))
        body = {
            "body": bname,
            "moments": np.diag(np.asarray(inertia)).tolist(),
            "intermediate_axis": "xyz"[axis],
            "fraction_flipping_within_T": frac_flip,
            "formulations": {},
        }
        for fname in FORMULATIONS:
            res = {}
            for key, _, dt in FIXED:
                R, s, first = timed(fns[(fname, key)], inertia, omegas, repeats=REPEATS)
                res[key] = {
                    "error": max_err(R, R_ref),
                    "time_s": s,
                    "first_call_s": first,
                    "body_steps_per_s": N * lierk.num_steps(0.0, T, dt) / s,
                }
            (R, steps, result), s, first = timed(
                fns[(fname, ADAPTIVE_KEY)], inertia, omegas, DOP853_TOL, repeats=REPEATS
            )
            res[ADAPTIVE_KEY] = {
                "error": max_err(R, R_ref),
                "time_s": s,
                "first_call_s": first,
                "max_steps": int(jnp.max(steps)),
                "mean_steps": float(jnp.mean(steps)),
                "results": np.bincount(np.asarray(result)).tolist(),
            }
            body["formulations"][fname] = res
            print(
                f"{bname:26s} {fname:21s} "
                + "  ".join(f"{k}: {v['error']:.2e}" for k, v in res.items())
                + f"  DOP853 {res[ADAPTIVE_KEY]['time_s']:.4f} s"
                + f"  RKMK4 {res[THROUGHPUT_KEY]['body_steps_per_s']:.2e} body-steps/s",
                flush=True,
            )
        free, spatial = body["formulations"]["FreeRigidBody"], body["formulations"]["SpatialFreeRigidBody"]
        body["error_ratio_spatial_over_free"] = {k: spatial[k]["error"] / free[k]["error"] for k in free}
        bodies.append(body)

    # Long horizon: one T-handle, 1000 s, RKMK4 at dt 0.01.
    inertia = jnp.asarray(lierk.inertia.tee_handle(), jnp.float64)
    w0 = jnp.asarray([LONG_OMEGA0])
    R_ref = exact_final(inertia, w0, LONG_T)
    long = {
        "omega0": LONG_OMEGA0,
        "T": LONG_T,
        "dt": LONG_DT,
        "steps": lierk.num_steps(0.0, LONG_T, LONG_DT),
        "formulations": {},
    }
    for fname, problem in FORMULATIONS.items():
        R, s, first = timed(fixed_fn(problem, lierk.RKMK4(), LONG_DT, LONG_T), inertia, w0, repeats=REPEATS)
        long["formulations"][fname] = {"error": max_err(R, R_ref), "time_s": s, "first_call_s": first}
        print(
            f"long horizon {fname:21s} error at t = {LONG_T:g}: {long['formulations'][fname]['error']:.2e}  "
            f"time {s:.3f} s",
            flush=True,
        )
    long["error_ratio_spatial_over_free"] = (
        long["formulations"]["SpatialFreeRigidBody"]["error"] / long["formulations"]["FreeRigidBody"]["error"]
    )

    machine = {
        "cpu_count": os.cpu_count(),
        "cpu": cpu_model(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "lierk": lierk.__version__,
        "devices": [str(d) for d in jax.devices()],
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }
    total = time.perf_counter() - t_start
    payload = {
        "quick": QUICK,
        "problem": {
            "batch": N,
            "T": T,
            "seed": SEED,
            "omega": "|omega| ~ U(1, 3) rad/s, direction: 1 along the intermediate axis, U(-0.2, 0.2) along "
            "the other two, normalised",
            "R0": "identity",
        },
        "reference": "lierk.exact.free_rigid_body (closed form)",
        "error": "max over the batch of ||R(T) - R_exact(T)||_F",
        "timing": f"median of {REPEATS} calls after a compiling warm-up call, block_until_ready; "
        "body-steps/s = batch * steps / time",
        "machine": machine,
        "total_runtime_s": total,
        "bodies": bodies,
        "long_horizon": long,
    }
    write_results(OUT, "formulation", payload, markdown(payload))
    print(f"total {total:.0f} s")


def markdown(p) -> list[str]:
    m = p["machine"]
    n, T_ = p["problem"]["batch"], p["problem"]["T"]
    keys = [k for k, _, _ in FIXED] + [ADAPTIVE_KEY]
    lines = [
        "# Formulations: FreeRigidBody (m as state) against SpatialFreeRigidBody (L fixed, m = R^T L)",
        "",
        ("**QUICK RUN (tiny size, timings meaningless).**\n" if p["quick"] else "")
        + f"{n} bodies per inertia within ~11 degrees of the intermediate axis, |omega| in [1, 3] rad/s, "
        f"R0 = I, T = {T_:g} s. Error: {p['error']}, reference {p['reference']}. Timing: {p['timing']}.",
        f"Machine: {m['cpu_count']} cores, {m['cpu']}, jax {m['jax']}. Load average at start "
        f"{m['load_average_at_start']}. Total runtime {p['total_runtime_s']:.0f} s.",
        "",
        "## Max error at T, time of DOP853, throughput of RKMK4",
        "",
        "| body | formulation | "
        + " | ".join(f"{k} error" for k in keys)
        + f" | {ADAPTIVE_KEY} time (s) | DOP853 max steps | {THROUGHPUT_KEY} body-steps/s |",
        "|---|---|" + "---:|" * (len(keys) + 3),
    ]
    for b in p["bodies"]:
        for fname, res in b["formulations"].items():
            a = res[ADAPTIVE_KEY]
            lines.append(
                f"| {b['body']} | {fname} | "
                + " | ".join(f"{res[k]['error']:.2e}" for k in keys)
                + f" | {a['time_s']:.4f} | {a['max_steps']} | {res[THROUGHPUT_KEY]['body_steps_per_s']:.2e} |"
            )
    lines += [
        "",
        "## Error ratio SpatialFreeRigidBody / FreeRigidBody (> 1: the momentum formulation is more accurate)",
        "",
        "| body | moments (kg m^2) | intermediate axis | fraction flipping within T | " + " | ".join(keys) + " |",
        "|---|---|---|---:|" + "---:|" * len(keys),
    ]
    for b in p["bodies"]:
        moments = ", ".join(f"{x:.4g}" for x in b["moments"])
        lines.append(
            f"| {b['body']} | ({moments}) | {b['intermediate_axis']} | {b['fraction_flipping_within_T']:.2f} | "
            + " | ".join(f"{b['error_ratio_spatial_over_free'][k]:.3g}" for k in keys)
            + " |"
        )
    lg = p["long_horizon"]
    lines += [
        "",
        f"## Long horizon: T-handle, omega0 = {tuple(lg['omega0'])} rad/s, RKMK4 dt {lg['dt']:g} s, "
        f"t = {lg['T']:g} s ({lg['steps']} steps)",
        "",
        f"| formulation | error at t = {lg['T']:g} s | time (s) |",
        "|---|---:|---:|",
    ]
    for fname, r in lg["formulations"].items():
        lines.append(f"| {fname} | {r['error']:.2e} | {r['time_s']:.3f} |")
    lines.append(f"| ratio Spatial / Free | {lg['error_ratio_spatial_over_free']:.3g} | |")
    return lines


if __name__ == "__main__":
    main()
