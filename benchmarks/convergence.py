"""Global error at T = 10 s against step size for every fixed-step solver.

Problem: the T-handle (`lierk.inertia.tee_handle()`), omega0 = (1, 0.05, 0.3)
rad/s, R0 = I.  Error: Frobenius norm ||R_h(T) - R_ref(T)||.  Reference:
`lierk.exact.free_rigid_body` when it imports and agrees with SciPy's DOP853
(rtol 1e-13) to 1e-9; otherwise SciPy's DOP853 itself.  The output says which.

Each solver is compiled once: its step sizes are swept under `vmap` with a
traced ``dt`` and a static ``max_steps`` (steps past T are exact no-ops).
The fitted order is the least-squares slope of log(error) against log(h) over
the points whose error lies between 1e-11 (round-off) and 1e-1 (pre-asymptotic).

Run: ``python benchmarks/convergence.py [--quick] [--out DIR]``; writes
benchmarks/results/convergence.json, convergence.md and convergence.png
(``--quick``: the three coarsest steps of each solver, into a temporary
directory).
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import platform  # noqa: E402
import time  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import common  # noqa: E402  (benchmarks/common.py: this folder is on sys.path)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402

import lierk  # noqa: E402

QUICK, OUT = common.cli(__doc__, "the three coarsest steps of each solver, into a temp dir", __name__ == "__main__")
T = 10.0
OMEGA0 = np.array([1.0, 0.05, 0.3])
# Errors outside this band are round-off or pre-asymptotic and would bias the fit.
FIT_LO, FIT_HI = 1e-11, 1e-1

# (label, solver, expected order, step counts N with h = T/N)
BASE_N = [20 * 2**k for k in range(8)]  # h = 0.5 ... 0.0039 s
SOLVERS = [
    ("ExplicitEuler", lierk.ExplicitEuler(), 1, [160 * 2**k for k in range(9)]),
    ("LieEuler", lierk.LieEuler(), 1, [160 * 2**k for k in range(9)]),
    ("NaiveLieRK4", lierk.NaiveLieRK4(), 2, BASE_N),
    ("RKMK4", lierk.RKMK4(), 4, BASE_N),
    ("CF4", lierk.CF4(), 4, BASE_N),
    ("RKMK(RK4)", lierk.RKMK(lierk.tableaux.RK4), 4, BASE_N),
    ("DP54 (fixed dt)", lierk.DP54(), 5, [10 * 2**k for k in range(7)]),
    ("DOP853 (fixed dt)", lierk.DOP853(), 8, [10, 14, 20, 28, 40, 56, 80, 113]),
]


def scipy_reference(inertia, omega0, t1):
    field = peers.free_body_field(inertia, L=inertia @ omega0, xp=np)
    return peers.scipy_solve(field, t1, np.eye(3).ravel(), 1e-13)[0]


def reference(inertia, omega0, t1):
    R_scipy = scipy_reference(inertia, omega0, t1)
    try:
        from lierk import exact

        R_exact = np.asarray(exact.free_rigid_body(inertia, jnp.asarray(omega0), jnp.asarray(t1))[0])
        gap = float(np.linalg.norm(R_exact - R_scipy))
        if np.all(np.isfinite(R_exact)) and gap < 1e-9:
            return R_exact, f"lierk.exact.free_rigid_body (agrees with SciPy DOP853 rtol 1e-13 to {gap:.1e})"
        note = f"lierk.exact.free_rigid_body disagrees with SciPy by {gap:.1e}"
    except Exception as e:  # noqa: BLE001 - any failure means: fall back
        note = f"lierk.exact unavailable ({type(e).__name__}: {e})"
    return R_scipy, f"SciPy DOP853 rtol=atol=1e-13 ({note})"


def errors(solver, inertia, steps, R_ref):
    body = lierk.FreeRigidBody(inertia, OMEGA0)
    n_max = max(steps)

    @jax.jit
    @jax.vmap
    def final_R(dt):
        return lierk.solve(body, solver, T, dt=dt, max_steps=n_max).R[-1]

    hs = T / np.asarray(steps, dtype=float)
    R = np.asarray(final_R(jnp.asarray(hs)))
    return hs, np.linalg.norm(R - R_ref, axis=(1, 2))


def fit(hs, errs):
    keep = (errs > FIT_LO) & (errs < FIT_HI)
    if keep.sum() < 2:
        return float("nan"), int(keep.sum())
    return float(np.polyfit(np.log(hs[keep]), np.log(errs[keep]), 1)[0]), int(keep.sum())


def main():
    t_start = time.perf_counter()
    inertia = np.asarray(lierk.inertia.tee_handle())
    R_ref, ref_name = reference(inertia, OMEGA0, T)
    print(f"reference: {ref_name}")
    rows = []
    for label, solver, expected, steps in SOLVERS:
        steps = steps[:3] if QUICK else steps
        hs, errs = errors(solver, inertia, steps, R_ref)
        order, n_fit = fit(hs, errs)
        rows.append(
            {
                "solver": label,
                "expected_order": expected,
                "fitted_order": order,
                "points_in_fit": n_fit,
                "h": hs.tolist(),
                "error": errs.tolist(),
            }
        )
        print(f"{label:20s} expected {expected}  fitted {order:5.2f}  ({n_fit} points)")

    meta = {
        "problem": "T-handle, omega0 = (1, 0.05, 0.3) rad/s, R0 = I",
        "T": T,
        "error": "||R_h(T) - R_ref(T)||_F",
        "reference": ref_name,
        "fit_window": [FIT_LO, FIT_HI],
        "jax": jax.__version__,
        "platform": platform.platform(),
    }
    lines = [
        "# Convergence on the T-handle",
        "",
        f"Error ||R_h(T) - R_ref(T)||_F at T = {T:g} s, omega0 = (1, 0.05, 0.3) rad/s.  ",
        f"Reference: {ref_name}.  ",
        f"Order = slope of log(error) vs log(h) over errors in [{FIT_LO:g}, {FIT_HI:g}].",
        "",
        "| solver | expected order | fitted order | points | smallest h (s) | its error |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['solver']} | {r['expected_order']} | {r['fitted_order']:.2f} | {r['points_in_fit']} "
            f"| {r['h'][-1]:.3g} | {r['error'][-1]:.2e} |"
        )
    common.write_results(OUT, "convergence", {"meta": meta, "results": rows}, lines)

    fig, ax = plt.subplots(figsize=(7, 5))
    for r in rows:
        ax.loglog(r["h"], r["error"], "o-", ms=3, label=f"{r['solver']} ({r['fitted_order']:.2f})")
    ax.axhspan(1e-17, FIT_LO, color="0.9", zorder=0)
    ax.set_ylim(bottom=1e-16)
    ax.set_xlabel("step size h (s)")
    ax.set_ylabel("||R_h(T) - R_ref(T)||_F")
    ax.set_title(f"T-handle, T = {T:g} s (fitted order in legend)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "convergence.png", dpi=120)
    print(f"wrote convergence.{{json,md,png}} in {OUT} in {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
