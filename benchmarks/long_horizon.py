"""Global error, energy and |L| drift over 1000 s for every Lie solver.

Problem: the T-handle (`lierk.inertia.tee_handle()`), omega0 = (1, 0.05, 0.3)
rad/s, R0 = I.  Fixed-step solvers use h = 0.01 s (10^5 steps) and save every
10th step; the adaptive DP54 and DOP853 save on a log-spaced grid.  The error
is the Frobenius norm ||R(t) - R_exact(t)|| against
`lierk.exact.free_rigid_body` evaluated on the same grid; the drifts are
relative, |E(t)/E(0) - 1| and ||m(t)|/|m(0)| - 1| with m = R^T L.

The growth exponent p of the error (error ~ t^p) is the least-squares slope of
log(running maximum of the error) against log(t) over the second half of the run (t in [500, 1000] s),
where the start-up transient is gone.  p = 1 is the linear phase-error growth
expected of a method that keeps energy bounded; p = 2 means the energy itself
drifts linearly, which then shears the phase quadratically.

Run: ``python benchmarks/long_horizon.py``; writes benchmarks/results/
long_horizon.json, long_horizon.md and long_horizon.png.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import lierk  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
T = 1000.0
DT = 0.01
SAVE_EVERY = 10
OMEGA0 = np.array([1.0, 0.05, 0.3])
FIT_FROM = 0.5 * T

FIXED = [
    ("LieEuler", lierk.LieEuler()),
    ("NaiveLieRK4", lierk.NaiveLieRK4()),
    ("RKMK4", lierk.RKMK4()),
    ("CF4", lierk.CF4()),
    ("RKMK(DOP853)", lierk.RKMK(lierk.tableaux.DOP853)),
]
ADAPTIVE = [
    ("DP54 (rtol 1e-8)", lierk.DP54(), 1e-8),
    ("DOP853 (rtol 1e-10)", lierk.DOP853(), 1e-10),
]
# The adaptive solvers end a step on each save time, so keep the grid sparse.
TS_ADAPTIVE = np.geomspace(0.1, T, 300)


def growth_exponent(t, err):
    keep = (t >= FIT_FROM) & np.isfinite(err) & (err > 0)
    if keep.sum() < 3:
        return float("nan")
    # Fit the running maximum: the raw error oscillates with the motion.
    env = np.maximum.accumulate(np.where(np.isfinite(err), err, 0.0))
    return float(np.polyfit(np.log(t[keep]), np.log(env[keep]), 1)[0])


def main():
    inertia = np.asarray(lierk.inertia.tee_handle())
    problem = lierk.FreeRigidBody(inertia, OMEGA0)
    exact = jax.jit(lambda t: lierk.exact.free_rigid_body(inertia, OMEGA0, t)[0])

    runs = []
    for name, solver in FIXED:
        start = time.perf_counter()
        sol = lierk.solve(problem, solver, T, dt=DT, saveat=lierk.SaveAt(steps=SAVE_EVERY))
        sol.R.block_until_ready()
        runs.append((name, sol, time.perf_counter() - start, int(sol.stats["num_steps"])))
    for name, solver, rtol in ADAPTIVE:
        start = time.perf_counter()
        sol = lierk.solve(problem, solver, T, rtol=rtol, saveat=lierk.SaveAt(ts=TS_ADAPTIVE), max_steps=400_000)
        sol.R.block_until_ready()
        runs.append((name, sol, time.perf_counter() - start, int(sol.stats["num_steps"])))

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    rows = []
    E0 = L0 = None
    for name, sol, seconds, steps in runs:
        t = np.asarray(sol.ts)
        R = np.asarray(sol.R)
        err = np.linalg.norm(R - np.asarray(exact(jnp.asarray(t))), axis=(-2, -1))
        inv = sol.invariants(problem)
        if E0 is None:
            R0_inv = problem.invariants(jnp.eye(3), None)
            E0, L0 = float(R0_inv["energy"]), float(R0_inv["|L|"])
        dE = np.abs(np.asarray(inv["energy"]) / E0 - 1)
        dL = np.abs(np.asarray(inv["|L|"]) / L0 - 1)
        p = growth_exponent(t, err)
        # An exponent means nothing once the error saturates (||R1 - R2|| <= 2 sqrt 2)
        # or sits at the reference's own accuracy (~1e-12 over many periods).
        note = "saturated" if err[-1] > 1.0 else ("at reference floor" if err.max() < 1e-10 else "")
        pE = growth_exponent(t, dE)
        rows.append(
            dict(
                solver=name,
                steps=steps,
                seconds=round(seconds, 2),
                error_at_T=float(err[-1]),
                error_exponent=p,
                note=note,
                max_energy_drift=float(dE.max()),
                energy_drift_exponent=pE,
                max_L_drift=float(dL.max()),
                max_orthogonality_error=float(np.asarray(sol.orthogonality_error).max()),
            )
        )
        for ax, y in zip(axes, (err, dE, dL)):
            ax.loglog(t, np.maximum(y, 1e-17), label=name, lw=1)

    for ax, title in zip(axes, ("||R(t) - R_exact(t)||_F", "|E(t)/E(0) - 1|", "| |L|(t)/|L|(0) - 1 |")):
        ax.set_title(title)
        ax.set_xlabel("t (s)")
        ax.grid(True, which="both", alpha=0.3)
    tt = np.array([FIT_FROM, T])
    for pw, style in ((1, ":"), (2, "--")):
        axes[0].loglog(tt, 1e-10 * (tt / FIT_FROM) ** pw, "k" + style, lw=0.8, label=f"~ t^{pw}")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"T-handle, omega0 = {tuple(OMEGA0.tolist())} rad/s; fixed h = {DT} s; fit of error ~ t^p over t >= {FIT_FROM:g} s")
    fig.tight_layout()
    RESULTS.mkdir(exist_ok=True)
    fig.savefig(RESULTS / "long_horizon.png", dpi=110)

    meta = dict(
        problem="T-handle (lierk.inertia.tee_handle()), R0 = I",
        omega0=OMEGA0.tolist(),
        T=T,
        dt_fixed=DT,
        fit_window=[FIT_FROM, T],
        reference="lierk.exact.free_rigid_body",
        machine=platform.platform(),
        jax=jax.__version__,
    )
    (RESULTS / "long_horizon.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=2))
    lines = [
        "# Long horizon on the T-handle",
        "",
        f"omega0 = {tuple(OMEGA0.tolist())} rad/s, T = {T:g} s, fixed h = {DT} s, reference lierk.exact.free_rigid_body.  ",
        f"Exponents: least-squares slope of log(running max of quantity) vs log(t) over t in [{FIT_FROM:g}, {T:g}] s.",
        "",
        "| solver | steps | error at T | error exponent | note | max energy drift | energy exponent | max abs(L) drift | max orth. error |",
        "|---|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['solver']} | {r['steps']} | {r['error_at_T']:.2e} | {r['error_exponent']:.2f} | {r['note']} | "
            f"{r['max_energy_drift']:.2e} | {r['energy_drift_exponent']:.2f} | {r['max_L_drift']:.2e} | "
            f"{r['max_orthogonality_error']:.1e} |"
        )
    (RESULTS / "long_horizon.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
