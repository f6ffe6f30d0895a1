"""What ``rtol`` means off the calibration set: error / tolerance by body family.

``rtol``/``atol`` are local tolerances, calibrated (`tableaux`'
``tolerance_calibration``) so that on near-axis bodies over 10 s the global
attitude error is 1 to 10 times ``rtol = atol``.  This script measures the
ratio on families the calibration never saw, next to what
``estimate_error=True`` reports and what ``target_error`` delivers, so the
README can state the scope of each claim.

Families (float64):

- ``near_axis``: 16 T-handles near the intermediate axis, T = 10 s (the
  calibration set).  Reference `lierk.exact`.
- ``fast``: I = diag(1, 2, 3), omega0 = (30, 60, 10) rad/s, T = 20 s.
- ``long``: I = diag(1, 2, 3), omega0 = (0.3, 1, 0.2) rad/s, T = 1000 s.
- ``top``: 8 asymmetric heavy tops (I = diag(0.6, 0.8, 0.3), spin 30 to 120
  rad/s, tilt 0.3 rad, g = 9.81), T = 2 s.  Reference: ``RKMK(DOP853)`` at
  dt = 2e-5 s.

Error = the largest ``||R(T) - R_ref(T)||_F`` over the family.  No timing:
safe to run next to other work.  Writes benchmarks/results/tolerance_scope.{json,md}.
Run: ``python benchmarks/tolerance_scope.py`` (a few minutes); ``--quick``
checks that it works.
"""

from __future__ import annotations


import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lierk  # noqa: E402
from common import cli, machine_info, near_axis, write_results  # noqa: E402

QUICK, OUT = cli(__doc__, "two bodies per family, one tolerance", __name__ == "__main__")
TOLS = [1e-6] if QUICK else [1e-6, 1e-9, 1e-12]
TARGETS = [1e-6] if QUICK else [1e-6, 1e-9]


def families():
    tee = np.asarray(lierk.inertia.tee_handle())
    w, _ = near_axis(np.diag(tee), 2 if QUICK else 16)
    box = np.diag([1.0, 2.0, 3.0])
    out = {
        "near_axis": ([lierk.FreeRigidBody(tee, v) for v in w], 10.0),
        "fast": ([lierk.FreeRigidBody(box, [30.0, 60.0, 10.0])], 20.0),
        "long": ([lierk.FreeRigidBody(box, [0.3, 1.0, 0.2])], 100.0 if QUICK else 1000.0),
    }
    rng = np.random.default_rng(0)
    tops = []
    for _ in range(2 if QUICK else 8):
        phi = rng.uniform(0, 2 * np.pi)
        R0 = lierk.so3.exp(jnp.asarray(0.3 * np.array([np.cos(phi), np.sin(phi), 0.0])))
        w0 = [rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(30, 120)]
        tops.append(lierk.RigidBodyWithEffects([0.6, 0.8, 0.3], w0, R0, effects=(lierk.Gravity([0.02, 0.01, 0.5], 1.0, 9.81),)))
    out["top"] = (tops, 2.0)
    return out


def reference(p, T):
    if isinstance(p, lierk.FreeRigidBody):
        return np.asarray(lierk.exact.free_rigid_body(p.inertia, p.omega0, T, p.R0)[0])
    dt = T / (1000 if QUICK else 100_000)
    return np.asarray(lierk.solve(p, lierk.RKMK(lierk.tableaux.DOP853), T, dt=dt).R[-1])


def main():
    rows = []
    for name, (problems, T) in families().items():
        refs = [reference(p, T) for p in problems]
        for solver in (lierk.DP54(), lierk.DOP853()):
            for tol in TOLS:
                errs, ests = [], []
                for p, ref in zip(problems, refs):
                    sol = lierk.solve(p, solver, T, rtol=tol, atol=tol, estimate_error=True, max_steps=1_000_000, throw=False)
                    errs.append(np.linalg.norm(np.asarray(sol.R[-1]) - ref))
                    ests.append(float(sol.error_estimate[-1]))
                i = int(np.argmax(errs))
                rows.append(dict(family=name, solver=solver.name, mode="rtol", setting=tol, error=errs[i],
                                 ratio=errs[i] / tol, estimate_over_error=ests[i] / errs[i]))
                print(f"{name:9s} {solver.name:7s} rtol {tol:.0e}: error {errs[i]:.2e} ({errs[i] / tol:8.1f} x rtol), "
                      f"estimate / error {ests[i] / errs[i]:.2f}", flush=True)
            for target in TARGETS:
                errs, codes = [], []
                for p, ref in zip(problems, refs):
                    sol = lierk.solve(p, solver, T, target_error=target, max_steps=1_000_000, throw=False)
                    errs.append(np.linalg.norm(np.asarray(sol.R[-1]) - ref))
                    codes.append(int(sol.result))
                rows.append(dict(family=name, solver=solver.name, mode="target_error", setting=target, error=max(errs),
                                 ratio=max(errs) / target, results=sorted(set(codes))))
                print(f"{name:9s} {solver.name:7s} target {target:.0e}: error {max(errs):.2e} "
                      f"({max(errs) / target:.2f} x target), results {sorted(set(codes))}", flush=True)
    lines = [
        "# Error / tolerance by body family (float64)",
        "",
        "Produced by `benchmarks/tolerance_scope.py`. Error: largest ||R(T) - R_ref(T)||_F over the family.",
        "`rtol` rows: rtol = atol = the setting, with `estimate_error=True` (estimate / error of the worst member).",
        "`target_error` rows: the worst member's error over the target, and the result codes returned (0 = success).",
        "",
        "| family | solver | asked | error | error / asked | estimate / error or results |",
        "|---|---|---|---:|---:|---|",
    ]
    for r in rows:
        extra = f"{r['estimate_over_error']:.2f}" if r["mode"] == "rtol" else str(r["results"])
        lines.append(f"| {r['family']} | {r['solver']} | {r['mode']} {r['setting']:.0e} | {r['error']:.2e} | {r['ratio']:.1f} | {extra} |")
    write_results(OUT, "tolerance_scope", dict(machine=machine_info(), rows=rows), lines)


if __name__ == "__main__":
    main()
