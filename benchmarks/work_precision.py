"""Work-precision: lierk against diffrax, SciPy and the report's NumPy loop.

Problem: the report's T-handle (``lierk.inertia.tee_handle()``), a batch of
1000 initial body angular velocities near the intermediate (x) axis with
``|omega|`` in [1, 3] rad/s (most of them flip within the run), ``R0 = I``,
``T = 10`` s.  Error = the largest Frobenius norm ``||R(T) - R_ref(T)||`` over
the batch; reference = the closed-form solution `lierk.exact.free_rigid_body`
(cross-checked against SciPy's DOP853 at rtol 1e-13 on a few members).

Everything runs in one process in float64.  Batched methods (lierk, diffrax)
are vmapped over the batch and jitted; compilation and a warm-up call are
excluded and the median of repeated calls is reported.  SciPy and the report's
NumPy loop integrate ONE trajectory (member 0); their time is multiplied by
the batch size and their error is that member's.

Writes benchmarks/results/work_precision.{png,json,md}.
Run: ``python benchmarks/work_precision.py`` (about 5 minutes on 2 cores).
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import lierk  # noqa: E402
import lierk.exact  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"
N = 1000
T = 10.0
SEED = 0
TOLS = [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
LIERK_TOLS = TOLS + [1e-13, 1e-14]
DTS = [0.04, 0.02, 0.01, 0.005, 0.0025]
HIGH_DTS = [0.2, 0.1, 0.0625, 0.05, 0.04]
LEVELS = [10.0**-k for k in range(4, 12)]
REPEATS = 3

INERTIA = lierk.inertia.tee_handle()
INERTIA_INV = jnp.linalg.inv(INERTIA)


def initial_velocities() -> np.ndarray:
    """``(N, 3)`` body angular velocities (rad/s) within ~11 degrees of +x."""
    rng = np.random.default_rng(SEED)
    mag = rng.uniform(1.0, 3.0, N)
    d = np.stack([np.ones(N), rng.uniform(-0.2, 0.2, N), rng.uniform(-0.2, 0.2, N)], axis=1)
    return mag[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)


def timed(f, *args, repeats=REPEATS):
    """Median wall time of ``f(*args)`` after a warm-up call (which compiles)."""
    out = jax.block_until_ready(f(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t)
    return out, float(np.median(times))


def max_err(R, R_ref) -> float:
    return float(jnp.max(jnp.linalg.norm(R - R_ref, axis=(-2, -1))))


def max_orth(R) -> float:
    return float(jnp.max(lierk.so3.orthogonality_error(R)))


# --- peers -------------------------------------------------------------------


def nine_component_field(t, x, L):
    """The 9-component ODE dX/dt = X hat(I^{-1} X^T L), X row-major."""
    X = x.reshape(3, 3)
    return (X @ lierk.so3.hat(INERTIA_INV @ (X.T @ L))).ravel()


def diffrax_fn(solver):
    @jax.jit
    def run(omegas, tol):
        def one(w):
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(nine_component_field),
                solver,
                0.0,
                T,
                None,
                jnp.eye(3).ravel(),
                args=INERTIA @ w,
                stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
                max_steps=100_000,
                throw=False,
            )
            return sol.ys[-1].reshape(3, 3), sol.stats["num_steps"]

        return jax.vmap(one)(omegas)

    return run


def scipy_one(w, tol):
    I = np.asarray(INERTIA)
    Iinv = np.linalg.inv(I)
    L = I @ w

    def f(t, x):
        X = x.reshape(3, 3)
        v = Iinv @ (X.T @ L)
        W = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
        return (X @ W).ravel()

    sol = solve_ivp(f, (0.0, T), np.eye(3).ravel(), method="DOP853", rtol=tol, atol=tol)
    return sol.y[:, -1].reshape(3, 3), sol.nfev


def report_rk4_one(w, h):
    """The report's oppg4.py "RK4": stages at W exp(c h S), no dexpinv (NumPy)."""
    I = np.asarray(INERTIA)
    I_inv = np.linalg.inv(I)
    L = I @ w

    def hat(s):
        return np.array([[0.0, -s[2], s[1]], [s[2], 0.0, -s[0]], [-s[1], s[0], 0.0]])

    def expo(h, S):  # oppg1.exponent_function: Rodrigues for exp(h S)
        wx, wy, wz = S[2, 1], S[0, 2], S[1, 0]
        om = np.sqrt(wx**2 + wy**2 + wz**2)
        if om == 0.0:
            return np.eye(3)
        return np.eye(3) + (1 - np.cos(om * h)) * (S @ S) / om**2 + np.sin(om * h) * S / om

    W = np.eye(3)
    for _ in range(int(round(T / h))):
        Wt = W.T
        S1 = hat(I_inv @ Wt @ L)
        S2 = hat(I_inv @ expo(-h / 2, S1) @ Wt @ L)
        S3 = hat(I_inv @ expo(-h / 2, S2) @ Wt @ L)
        S4 = hat(I_inv @ expo(-h, S3) @ Wt @ L)
        W = W @ expo(h / 6, S1 + 2 * S2 + 2 * S3 + S4)
    return W


# --- lierk -------------------------------------------------------------------


def lierk_adaptive_fn(solver, adjoint=None):
    @jax.jit
    def run(omegas, tol):
        def one(w):
            sol = lierk.solve(lierk.FreeRigidBody(INERTIA, w), solver, T, rtol=tol, throw=False, adjoint=adjoint)
            return sol.R[-1], sol.stats["num_steps"], sol.result

        return jax.vmap(one)(omegas)

    return run


def lierk_fixed_fn(solver, dt):
    @jax.jit
    def run(omegas):
        def one(w):
            sol = lierk.solve(lierk.FreeRigidBody(INERTIA, w), solver, T, dt=dt, max_steps=round(T / dt))
            return sol.R[-1], sol.stats["num_steps"]

        return jax.vmap(one)(omegas)

    return run


def best_time(records, level, family):
    ok = [r for r in records if r["family"] == family and r["error"] <= level]
    return min(ok, key=lambda r: r["time_s"]) if ok else None


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    omegas_np = initial_velocities()
    omegas = jnp.asarray(omegas_np)
    t_start = time.perf_counter()

    # Reference (closed form, eager: jitting it compiles for minutes).
    R_ref = jax.vmap(lambda w: lierk.exact.free_rigid_body(INERTIA, w, T)[0])(omegas)
    flips = np.asarray(jax.vmap(lambda w: lierk.exact.flip_interval(INERTIA, w))(omegas))
    # From near the x axis the first sign change of omega_x comes half a flip interval in.
    frac_flip = float(np.mean(flips / 2 < T))
    check_ids = [0, 1, 2]
    check = []
    for i in check_ids:
        R_sp, _ = scipy_one(omegas_np[i], 1e-13)
        check.append(float(np.linalg.norm(R_sp - np.asarray(R_ref[i]))))
    print(f"reference: lierk.exact; |exact - scipy DOP853(1e-13)| on members {check_ids}: {check}")

    records = []

    def add(name, family, param, R, seconds, steps=None, err_R_ref=R_ref, note=""):
        rec = {
            "method": name,
            "family": family,
            "param": param,
            "time_s": seconds,
            "error": max_err(R, err_R_ref),
            "orthogonality": max_orth(R),
            "note": note,
        }
        if steps is not None:
            rec["max_steps"] = int(jnp.max(steps))
            rec["mean_steps"] = float(jnp.mean(steps))
        records.append(rec)
        print(f"{name:24s} {param:>9.1e}  err {rec['error']:.2e}  time {seconds:8.4f} s  orth {rec['orthogonality']:.1e}")

    for solver in (lierk.RKF45(), lierk.DP54(), lierk.DOP853()):
        run = lierk_adaptive_fn(solver)
        for tol in LIERK_TOLS:
            (R, steps, res), s = timed(run, omegas, tol)
            add(f"lierk {solver.name}", "lierk", tol, R, s, steps, note=f"results {np.bincount(np.asarray(res)).tolist()}")
    # The loop kind of the adjoint, measured without differentiating.
    for solver in (lierk.DOP853(),):
        run = lierk_adaptive_fn(solver, lierk.ForwardMode())
        for tol in LIERK_TOLS:
            (R, steps, _), s = timed(run, omegas, tol)
            add(f"lierk {solver.name} (lax loop)", "lierk-lax", tol, R, s, steps)
    for solver in (lierk.RKMK4(), lierk.CF4()):
        for dt in DTS:
            (R, steps), s = timed(lierk_fixed_fn(solver, dt), omegas)
            add(f"lierk {solver.name} fixed", "lierk", dt, R, s, steps)
    # High-order tableaux with fixed steps.  Near the separatrix the error that
    # matters is the energy error made during the slow phases, where a Lie
    # method's local error estimate is tiny (it integrates the fast spin about
    # the near-fixed axis almost exactly) and the controller lengthens the step;
    # uniform steps spend the work where the global error is made.
    for tableau, dts in ((lierk.tableaux.DOPRI54, HIGH_DTS[:4]), (lierk.tableaux.DOP853, HIGH_DTS)):
        for dt in dts:
            (R, steps), s = timed(lierk_fixed_fn(lierk.RKMK(tableau), dt), omegas)
            add(f"lierk RKMK({tableau.name}) fixed", "lierk", dt, R, s, steps)

    for solver in (diffrax.Tsit5(), diffrax.Dopri5(), diffrax.Dopri8()):
        run = diffrax_fn(solver)
        for tol in TOLS:
            (R, steps), s = timed(run, omegas, tol)
            add(f"diffrax {type(solver).__name__}", "diffrax", tol, R, s, steps)

    one_ref = R_ref[0]
    for tol in TOLS:
        t = time.perf_counter()
        R, nfev = scipy_one(omegas_np[0], tol)
        s = (time.perf_counter() - t) * N
        add("scipy DOP853 (x1000)", "scipy", tol, jnp.asarray(R), s, err_R_ref=one_ref, note=f"one trajectory, nfev {nfev}")
    for h in (0.01, 0.001):
        t = time.perf_counter()
        R = report_rk4_one(omegas_np[0], h)
        s = (time.perf_counter() - t) * N
        add("report NumPy RK4 (x1000)", "numpy", h, jnp.asarray(R), s, err_R_ref=one_ref, note="one trajectory")

    table = []
    for level in LEVELS:
        lb, db = best_time(records, level, "lierk"), best_time(records, level, "diffrax")
        row = {"level": level}
        for key, rec in (("lierk", lb), ("diffrax", db)):
            row[key] = None if rec is None else {"method": rec["method"], "param": rec["param"], "time_s": rec["time_s"]}
        row["ratio_lierk_over_diffrax"] = lb["time_s"] / db["time_s"] if lb and db else None
        table.append(row)

    machine = {
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "diffrax": diffrax.__version__,
        "lierk": lierk.__version__,
        "devices": [str(d) for d in jax.devices()],
    }
    total = time.perf_counter() - t_start
    payload = {
        "problem": {
            "inertia": np.asarray(INERTIA).tolist(),
            "batch": N,
            "T": T,
            "seed": SEED,
            "omega": "|omega| ~ U(1, 3) rad/s, direction (1, U(-0.2,0.2), U(-0.2,0.2)) normalised",
            "fraction_flipping_within_T": frac_flip,
        },
        "reference": "lierk.exact.free_rigid_body (closed form)",
        "reference_vs_scipy_dop853_1e-13": dict(zip(map(str, check_ids), check)),
        "error": "max over the batch of ||R(T) - R_ref(T)||_F (scipy and NumPy: member 0 only)",
        "timing": f"median of {REPEATS} calls after warm-up; scipy/NumPy: one trajectory x {N}",
        "machine": machine,
        "total_runtime_s": total,
        "records": records,
        "table": table,
    }
    (OUT / "work_precision.json").write_text(json.dumps(payload, indent=1))
    write_markdown(payload)
    plot(records)
    print(f"total {total:.0f} s")


def write_markdown(p):
    lines = [
        "# Work-precision: T-handle, 1000 bodies near the intermediate axis, T = 10 s",
        "",
        f"Reference: {p['reference']}; against SciPy DOP853 at rtol 1e-13: "
        + ", ".join(f"{v:.1e}" for v in p["reference_vs_scipy_dop853_1e-13"].values())
        + f". Fraction of the batch that flips within T: {p['problem']['fraction_flipping_within_T']:.2f}.",
        f"Error: {p['error']}. Timing: {p['timing']}.",
        f"Machine: {p['machine']['cpu_count']} cores, {p['machine']['processor']}, jax {p['machine']['jax']}, "
        f"diffrax {p['machine']['diffrax']}. Total runtime {p['total_runtime_s']:.0f} s.",
        "",
        "## Best time to reach each error level",
        "",
        "| error <= | best lierk | time (s) | best diffrax | time (s) | lierk / diffrax |",
        "|---|---|---|---|---|---|",
    ]
    for row in p["table"]:
        def cell(x):
            return ("-", "-") if x is None else (f"{x['method']} ({x['param']:.0e})", f"{x['time_s']:.3f}")

        lm, lt = cell(row["lierk"])
        dm, dt = cell(row["diffrax"])
        ratio = "-" if row["ratio_lierk_over_diffrax"] is None else f"{row['ratio_lierk_over_diffrax']:.2f}"
        lines.append(f"| {row['level']:.0e} | {lm} | {lt} | {dm} | {dt} | {ratio} |")
    lines += [
        "",
        "## All runs",
        "",
        "| method | tol or dt | max error | time (s) | max steps | max orthogonality error | note |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in p["records"]:
        lines.append(
            f"| {r['method']} | {r['param']:.0e} | {r['error']:.2e} | {r['time_s']:.4f} | "
            f"{r.get('max_steps', '')} | {r['orthogonality']:.1e} | {r['note']} |"
        )
    (OUT / "work_precision.md").write_text("\n".join(lines) + "\n")


def plot(records):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 6))
    for name in dict.fromkeys(r["method"] for r in records):
        rs = sorted((r for r in records if r["method"] == name), key=lambda r: r["time_s"])
        style = "-" if name.startswith("lierk") else "--"
        ax.loglog([r["time_s"] for r in rs], [max(r["error"], 1e-16) for r in rs], style, marker="o", ms=3, label=name)
    ax.set_xlabel("wall time for 1000 bodies (s)")
    ax.set_ylabel("max error ||R(T) - R_ref(T)||_F")
    ax.set_title("T-handle near the intermediate axis, T = 10 s, float64")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "work_precision.png", dpi=120)


if __name__ == "__main__":
    main()
