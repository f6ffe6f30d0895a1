"""What the global error estimate and accuracy on request cost, and how well they do.

Problem: 1000 bodies near the intermediate axis (|omega| in [1, 3] rad/s,
within ~11 degrees of it), T = 10 s, for the T-handle and for Hairer, Lubich
and Wanner's body I = (2, 1, 2/3).  Reference: `lierk.exact`.

1. ``estimate_error=True`` against the plain solve: time ratio (target <= 3x)
   and the estimate's quality (fraction of members within 10x of the true
   error, smallest estimate/error).
2. ``target_error=eps`` for eps = 1e-4 ... 1e-10: fraction of members whose
   true error is <= eps (target >= 95%), members that report success with an
   error above eps (target: none), solves per call (mean and most), and time
   against the cheapest single setting of the same solver that, checked
   afterwards against the exact solution, reaches eps on 95% of the batch
   (target <= 3x; under vmap the batch runs as many solves as its hardest
   member, so one member that needs a third solve costs the batch a third,
   finer solve).

Everything runs in one process, float64, both solves jitted and vmapped over
the batch; compile and warm-up excluded; median of repeats.
Writes benchmarks/results/error_estimate.{json,md}.
Run: ``python benchmarks/error_estimate.py [--quick]``.
"""

from __future__ import annotations

import os

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from common import cli, cpu_model, near_axis, timed, write_results  # noqa: E402

import lierk  # noqa: E402
import lierk.exact  # noqa: E402

QUICK, OUT = cli(__doc__, "tiny run (40 bodies) to check the script works", __name__ == "__main__")
N = 40 if QUICK else 1000
T = 10.0
REPEATS = 1 if QUICK else 3
BODIES = {"tee_handle": np.diag(np.asarray(lierk.inertia.tee_handle())), "hlw": np.array([2.0, 1.0, 2 / 3])}
ESTIMATE_RUNS = [
    (lierk.RKMK4(), "dt", 0.01),
    (lierk.CF4(), "dt", 0.01),
    (lierk.DP54(), "rtol", 1e-8),
    (lierk.DOP853(), "rtol", 1e-10),
]
TARGETS = [1e-4, 1e-6, 1e-8, 1e-10]
# Settings scanned for the cheapest one that reaches each target.
SCAN = {
    "RKMK4": ("dt", [0.2 / 2 ** (k / 2) for k in range(16)]),
    "DOP853": ("rtol", [10.0 ** (-k / 2) for k in range(6, 28)]),
}


def batch_solver(solver, key, **extra):
    """``f(I, W, value)``: the batch solved with ``key=value``.  A fixed step is
    a compile-time constant, so the scan takes exactly ceil(T/dt) steps (a
    traced dt would need a static max_steps and pay for all of them)."""

    def one(I, w, value):
        kw = {key: value, **extra}
        if key != "dt":
            kw["max_steps"] = 100_000
        sol = lierk.solve(lierk.FreeRigidBody(I, w), solver, T, throw=False, **kw)
        est = sol.error_estimate[-1] if sol.error_estimate is not None else jnp.zeros(())
        return sol.R[-1], est, sol.result, sol.stats.get("num_solves", jnp.ones((), jnp.int32))

    if key == "dt":
        cache = {}

        def fixed(I, W, value):
            if value not in cache:
                cache[value] = jax.jit(jax.vmap(lambda I, w: one(I, w, value), in_axes=(None, 0)))
            return cache[value](I, W)

        return fixed
    return jax.jit(jax.vmap(one, in_axes=(None, 0, None)))


def main():
    rows_est, rows_target = [], []
    for body, I in BODIES.items():
        W, _ = near_axis(I, N)
        Rex = jax.jit(jax.vmap(lambda w: lierk.exact.free_rigid_body(jnp.diag(I), w, T)[0]))(W)

        def errors(R):
            return np.asarray(jnp.linalg.norm(R - Rex, axis=(-2, -1)))

        for solver, key, value in ESTIMATE_RUNS:
            plain = batch_solver(solver, key)
            with_est = batch_solver(solver, key, estimate_error=True)
            (R, _, _, _), t_plain, _ = timed(plain, I, W, value, repeats=REPEATS)
            (R2, est, _, _), t_est, _ = timed(with_est, I, W, value, repeats=REPEATS)
            err = errors(R2)
            big = err > 1e-12
            ratio = np.asarray(est)[big] / err[big]
            rows_est.append(
                dict(
                    body=body,
                    solver=solver.name,
                    setting=f"{key}={value:g}",
                    time_plain=t_plain,
                    time_estimate=t_est,
                    cost_ratio=t_est / t_plain,
                    max_error=float(err.max()),
                    within_10x=float(np.mean((ratio <= 10) & (ratio >= 0.1))),
                    min_ratio=float(ratio.min()),
                    max_ratio=float(ratio.max()),
                )
            )
            print(rows_est[-1], flush=True)

        for name, (key, grid) in SCAN.items():
            solver = getattr(lierk, name)()
            plain = batch_solver(solver, key)
            scanned = []
            for value in grid:
                (R, _, res, _), t, _ = timed(plain, I, W, value, repeats=REPEATS)
                scanned.append((value, t, np.quantile(errors(R), 0.95)))
            target = batch_solver(solver, "target_error")
            for eps in TARGETS:
                (R, est, res, solves), t, _ = timed(target, I, W, eps, repeats=REPEATS)
                err = errors(R)
                solves = np.asarray(solves)
                ok = [(v, tt) for v, tt, e95 in scanned if e95 <= eps]
                cheapest = min(ok, key=lambda x: x[1]) if ok else (None, float("nan"))
                rows_target.append(
                    dict(
                        body=body,
                        solver=name,
                        eps=eps,
                        met=float(np.mean(err <= eps)),
                        codes_ok=float(np.mean(np.asarray(res) == 0)),
                        success_above_eps=int(np.sum((np.asarray(res) == 0) & (err > eps))),
                        solves_mean=float(solves.mean()),
                        solves_max=int(solves.max()),
                        time=t,
                        cheapest_setting=cheapest[0],
                        cheapest_time=cheapest[1],
                        cost_ratio=t / cheapest[1] if ok else None,
                    )
                )
                print(rows_target[-1], flush=True)

    info = {
        "cores": os.cpu_count(),
        "processor": cpu_model(),
        "jax": jax.__version__,
        "platform": "CPU",
        "N": N,
        "T": T,
        "quick": QUICK,
    }
    md = [
        "# Global error estimate and accuracy on request\n\n"
        f"Machine: {info['cores']} cores, {info['processor']}, CPU, jax {info['jax']}; "
        f"batch {N}, T = {T} s, float64, medians of {REPEATS}.\n",
        "## `estimate_error=True` (Richardson against a finer solve)\n",
        "| body | solver | setting | plain (s) | with estimate (s) | cost | max error "
        "| est. within 10x | min est/err |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows_est:
        md.append(
            f"| {r['body']} | {r['solver']} | {r['setting']} | {r['time_plain']:.3f} | {r['time_estimate']:.3f} | "
            f"{r['cost_ratio']:.2f}x | {r['max_error']:.1e} | {100 * r['within_10x']:.0f}% | {r['min_ratio']:.2f} |"
        )
    md += [
        "\n## `target_error=eps`\n",
        "| body | solver | eps | members with error <= eps | success above eps | solves (mean, most) | time (s) | "
        "cheapest single setting reaching eps (95%) | its time (s) | cost |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows_target:
        cost = f"{r['cost_ratio']:.2f}x" if r["cost_ratio"] else "n/a"
        setting = f"{r['cheapest_setting']:.3g}" if r["cheapest_setting"] else "none in scan"
        md.append(
            f"| {r['body']} | {r['solver']} | {r['eps']:.0e} | {100 * r['met']:.1f}% | {r['success_above_eps']} | "
            f"{r['solves_mean']:.2f}, {r['solves_max']} | {r['time']:.3f} | {setting} | "
            f"{r['cheapest_time']:.3f} | {cost} |"
        )
    write_results(OUT, "error_estimate", {"machine": info, "estimate": rows_est, "target": rows_target}, md)
    print("\n".join(md))


if __name__ == "__main__":
    main()
