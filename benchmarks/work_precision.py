"""Work-precision: lierk against lierk.exact, diffrax, MuJoCo, SciPy and the report's NumPy loop.

Problem: the report's T-handle (``lierk.inertia.tee_handle()``), a batch of
1000 initial body angular velocities near the intermediate (x) axis with
``|omega|`` in [1, 3] rad/s (most of them flip within the run), ``R0 = I``,
``T = 10`` s.  Error = the largest Frobenius norm ``||R(T) - R_ref(T)||`` over
the batch; reference = the closed-form solution `lierk.exact.free_rigid_body`.

Programs:

- lierk with its default formulation `lierk.FreeRigidBody` (body momentum as
  state), adaptive and fixed-step, and with the report's formulation
  `lierk.SpatialFreeRigidBody` (spatial L fixed, m = R^T L) for RKMK4 at a few
  dt and DOP853 at a few tolerances, so both are measured in one run.
- lierk.exact itself, the "ceiling": the jitted, vmapped closed form for the
  whole batch.  Its error is measured against a second, independent
  reference: SciPy's DOP853 at rtol = atol = 1e-13 on the first few members
  (the 9-component ODE, see `scipy_one`), so that row's error is the largest
  disagreement between the two references on those members, not a batch max.
- diffrax on the 9-component ODE ``dX/dt = X hat(I^{-1} X^T L)``.
- MuJoCo: one body on a ball joint, no gravity, RK4, the whole batch through
  `mujoco.rollout` with one thread (and one MjData) per core.
- SciPy's DOP853 and the report's NumPy loop on ONE trajectory (member 0);
  their time is multiplied by the batch size and their error is that member's.

Everything runs in one process in float64.  Batched JAX methods are vmapped
over the batch and jitted; compilation and a warm-up call are excluded and the
median of at least 3 calls is reported, more (up to 51) until they add up to
0.25 s (MuJoCo likewise: warm-up rollout, then the median of repeated
rollouts into a preallocated state array).

Writes benchmarks/results/work_precision.{png,json,md}.
Run: ``python benchmarks/work_precision.py`` (3 to 4 minutes on 2 idle cores).
``--quick`` runs a tiny version (20 bodies, T = 2 s, fewer settings, no
repeats) only to check that everything works; it writes to a temporary
directory unless ``--out`` is given.
"""

from __future__ import annotations

import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402
import scipy  # noqa: E402
from common import cli, machine_info, max_err, series_table, timed, write_results  # noqa: E402

import lierk  # noqa: E402
import lierk.exact  # noqa: E402

QUICK, OUT = cli(__doc__, "tiny run (20 bodies, T = 2 s) to check the script works", __name__ == "__main__")

N = 20 if QUICK else 1000
T = 2.0 if QUICK else 10.0
SEED = 0
TOLS = [1e-6, 1e-10] if QUICK else [1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
LIERK_TOLS = TOLS + ([1e-13] if QUICK else [1e-13, 1e-14])
DTS = [0.02, 0.01] if QUICK else [0.04, 0.02, 0.01, 0.005, 0.0025]
HIGH_DTS = [0.1, 0.05] if QUICK else [0.2, 0.1, 0.0625, 0.05, 0.04]
# The report's formulation, next to the default one.
SPATIAL_DTS = [0.02, 0.01] if QUICK else [0.02, 0.01, 0.005]
SPATIAL_TOLS = [1e-8, 1e-12] if QUICK else [1e-8, 1e-10, 1e-12, 1e-14]
MUJOCO_DTS = [0.04, 0.02, 0.01, 0.005]
MUJOCO_THREADS = os.cpu_count() or 1  # one thread (and one MjData) per core
LEVELS = [10.0**-k for k in range(4, 12)]
REPEATS = 1 if QUICK else 3
# Calls of a few ms are repeated until they add up to this (common.timed): a
# median of 3 such calls is not robust on a shared machine.
MIN_TIME = 0.0 if QUICK else 0.25
# Members on which lierk.exact is checked against SciPy DOP853 at 1e-13.
CHECK_IDS = [0, 1] if QUICK else [0, 1, 2, 3, 4]
CHECK_TOL = 1e-13

INERTIA = lierk.inertia.tee_handle()
# diffrax's ODE: the 9-component X' = X hat(I^{-1} X^T L), args = L.
FIELD = peers.free_body_field(INERTIA)


def initial_velocities() -> np.ndarray:
    """``(N, 3)`` body angular velocities (rad/s) within ~11 degrees of +x."""
    rng = np.random.default_rng(SEED)
    mag = rng.uniform(1.0, 3.0, N)
    d = np.stack([np.ones(N), rng.uniform(-0.2, 0.2, N), rng.uniform(-0.2, 0.2, N)], axis=1)
    return mag[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)


def max_orth(R) -> float:
    return float(jnp.max(lierk.so3.orthogonality_error(jnp.asarray(R))))


# --- peers -------------------------------------------------------------------


def diffrax_fn(solver):
    @jax.jit
    def run(omegas, tol):
        def one(w):
            x0, L = peers.free_body_state(INERTIA, w)
            return peers.diffrax_solve(FIELD, solver, T, x0, rtol=tol, max_steps=100_000, args=L)[:2]

        return jax.vmap(one)(omegas)

    return run


def scipy_one(w, tol):
    """SciPy's DOP853 on the 9-component ODE: ``(R(T), nfev)``."""
    return peers.scipy_solve(
        peers.free_body_field(INERTIA, L=np.asarray(INERTIA) @ w, xp=np), T, np.eye(3).ravel(), tol
    )


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
    for _ in range(lierk.num_steps(0.0, T, h)):
        Wt = W.T
        S1 = hat(I_inv @ Wt @ L)
        S2 = hat(I_inv @ expo(-h / 2, S1) @ Wt @ L)
        S3 = hat(I_inv @ expo(-h / 2, S2) @ Wt @ L)
        S4 = hat(I_inv @ expo(-h, S3) @ Wt @ L)
        W = W @ expo(h / 6, S1 + 2 * S2 + 2 * S3 + S4)
    return W


# --- MuJoCo ------------------------------------------------------------------
#
# One body on a ball joint at its centre of mass, no gravity, MuJoCo's RK4.
# The inertial frame is the body frame (no quat on <inertial>), so the body's
# principal moments are exactly the T-handle's diagonal inertia; the mass does
# not enter the rotation.  qpos is the body -> world quaternion (w, x, y, z),
# i.e. lierk's R.  For a ball joint qvel is the angular velocity in the BODY
# frame: checked against lierk.exact by `mujoco_frame_check` (one body started
# at a non-identity attitude, dt = 1e-3, t = 1 s; mujoco 4.0.0): qvel(t)
# matches the exact body angular velocity to 7e-15 and is 2.0 rad/s off the
# spatial one R omega, and R(t) matches to 1e-14.  The check runs on every
# invocation and is recorded in the JSON.
#
# MuJoCo's RK4 (mj_RungeKutta) advances qvel (= I^{-1} m: the same Euler
# equations as lierk.FreeRigidBody) with the classical tableau, and qpos by
# mj_integratePos, the exponential of h sum_j a_ij v_j: RKMK4 without the
# dexpinv correction.  In a --quick run its R(T) differed from lierk RKMK4's by
# O(dt^5) (1.4e-9, 4.3e-11, 1.3e-12 at dt 0.04, 0.02, 0.01; errors 3.8e-7,
# 2.4e-8, 1.5e-9), so the two reach the same error and the comparison is one of cost.
# The model keeps MuJoCo's default pipeline; disabling the unused stages
# (<flag constraint="disable" contact="disable" .../>) gave bit-identical states
# about 20% faster in a small test.


def mujoco_xml(dt: float) -> str:
    I = np.asarray(INERTIA)
    d = np.diag(I)
    assert np.max(np.abs(I - np.diag(d))) <= 1e-14 * np.max(d), "the T-handle's inertia must be diagonal"
    return f"""<mujoco model="tee_handle">
  <option gravity="0 0 0" integrator="RK4" timestep="{float(dt)!r}"/>
  <worldbody>
    <body name="handle">
      <joint name="rot" type="ball"/>
      <inertial pos="0 0 0" mass="1" diaginertia="{d[0]:.17g} {d[1]:.17g} {d[2]:.17g}"/>
    </body>
  </worldbody>
</mujoco>
"""


def mujoco_frame_check(w) -> dict:
    """Is a ball joint's qvel the body-frame angular velocity?  One body, started
    at a non-identity attitude (1 rad about (1, 1, 1)), dt = 1e-3, t = 1 s,
    against lierk.exact."""
    dt, n = 1e-3, 1000
    axis = np.ones(3) / np.sqrt(3.0)
    quat0 = np.concatenate([[np.cos(0.5)], np.sin(0.5) * axis])
    R0 = np.empty(9)
    mujoco.mju_quat2Mat(R0, quat0)
    R0 = R0.reshape(3, 3)
    model = mujoco.MjModel.from_xml_string(mujoco_xml(dt))
    data = mujoco.MjData(model)
    peers.mujoco_set_state(model, data, peers.mujoco_initial_states(model, [w], quat0)[0])
    for _ in range(n):
        mujoco.mj_step(model, data)
    R_mj, w_mj, t_mj = peers.mujoco_final(model, [peers.mujoco_get_state(model, data)])
    R_ex, w_ex = lierk.exact.free_rigid_body(INERTIA, w, n * dt, R0=R0)
    R_ex, w_ex = np.asarray(R_ex), np.asarray(w_ex)
    return {
        "t": float(t_mj[0]),
        "R_error": float(np.linalg.norm(R_mj[0] - R_ex)),
        "qvel_minus_exact_body_omega": float(np.linalg.norm(w_mj[0] - w_ex)),
        "qvel_minus_exact_spatial_omega": float(np.linalg.norm(w_mj[0] - R_ex @ w_ex)),
    }


def mujoco_batch(omegas_np, dt):
    """Roll the batch out to ``T``; ``(R, w, t, median s, first s)``."""
    model = mujoco.MjModel.from_xml_string(mujoco_xml(dt))
    init = peers.mujoco_initial_states(model, omegas_np)
    go = peers.mujoco_rollout(model, init, lierk.num_steps(0.0, T, dt), MUJOCO_THREADS)
    final, seconds, first = timed(go, repeats=REPEATS, min_time=MIN_TIME)
    R, w, t = peers.mujoco_final(model, final)
    assert np.all(np.abs(t - T) <= 1e-9 * T), f"MuJoCo ended at t = {t.min()}..{t.max()}, not T = {T}"
    return R, w, t, seconds, first


# --- lierk -------------------------------------------------------------------


def lierk_adaptive_fn(solver, adjoint=None, problem=lierk.FreeRigidBody):
    @jax.jit
    def run(omegas, tol):
        def one(w):
            sol = lierk.solve(problem(INERTIA, w), solver, T, rtol=tol, throw=False, adjoint=adjoint)
            return sol.R[-1], sol.stats["num_steps"], sol.result

        return jax.vmap(one)(omegas)

    return run


def lierk_fixed_fn(solver, dt, problem=lierk.FreeRigidBody):
    @jax.jit
    def run(omegas):
        def one(w):
            sol = lierk.solve(problem(INERTIA, w), solver, T, dt=dt, max_steps=lierk.num_steps(0.0, T, dt))
            return sol.R[-1], sol.stats["num_steps"]

        return jax.vmap(one)(omegas)

    return run


# Columns of the "cheapest time per error level" table: (family, heading).
PROGRAMS = [
    ("lierk", "lierk best (FreeRigidBody)"),
    ("lierk-spatial", "lierk best (SpatialFreeRigidBody)"),
    ("exact", "lierk.exact"),
    ("diffrax", "diffrax best"),
    ("mujoco", "MuJoCo RK4"),
    ("scipy", "SciPy DOP853 (x N)"),
]


def best_time(records, level, family):
    ok = [r for r in records if r["family"] == family and r["error"] <= level]
    return min(ok, key=lambda r: r["time_s"]) if ok else None


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    omegas_np = initial_velocities()
    omegas = jnp.asarray(omegas_np)
    machine = machine_info(diffrax=diffrax.__version__, mujoco=mujoco.__version__, scipy=scipy.__version__)
    t_start = time.perf_counter()

    # Reference and ceiling: the closed form, jitted and vmapped over the batch.
    exact_batch = jax.jit(jax.vmap(lambda w: lierk.exact.free_rigid_body(INERTIA, w, T)[0]))
    t = time.perf_counter()
    exact_batch = exact_batch.lower(omegas).compile()
    exact_compile_s = time.perf_counter() - t
    R_ref, exact_s, _ = timed(exact_batch, omegas, repeats=REPEATS, min_time=MIN_TIME)
    flips = np.asarray(jax.vmap(lambda w: lierk.exact.flip_interval(INERTIA, w))(omegas))
    # From near the x axis the first sign change of omega_x comes half a flip interval in.
    frac_flip = float(np.mean(flips / 2 < T))
    check = []
    for i in CHECK_IDS:
        R_sp, _ = scipy_one(omegas_np[i], CHECK_TOL)
        check.append(float(np.linalg.norm(R_sp - np.asarray(R_ref[i]))))
    print(f"reference: lierk.exact; |exact - scipy DOP853({CHECK_TOL:.0e})| on members {CHECK_IDS}: {check}")

    records = []

    def add(name, family, param, R, seconds, steps=None, err_R_ref=R_ref, note="", kind=None, first=None, error=None):
        rec = {
            "method": name,
            "family": family,
            "kind": kind,  # "tol", "dt" or None: what `param` is
            "param": param,
            "time_s": seconds,
            "first_call_s": first,
            "error": max_err(R, err_R_ref) if error is None else error,
            "orthogonality": max_orth(R),
            "note": note,
        }
        if steps is not None:
            rec["max_steps"] = int(jnp.max(steps))
            rec["mean_steps"] = float(jnp.mean(steps))
        records.append(rec)
        p = "-" if param is None else f"{param:.1e}"
        print(
            f"{name:34s} {p:>9s}  err {rec['error']:.2e}  time {seconds:8.4f} s  orth {rec['orthogonality']:.1e}",
            flush=True,
        )

    add(
        "lierk.exact (closed form)",
        "exact",
        None,
        R_ref,
        exact_s,
        first=exact_compile_s,
        error=max(check),
        note=f"error: max |exact - SciPy DOP853(rtol=atol={CHECK_TOL:.0e})| over members {CHECK_IDS}; "
        f"compile {exact_compile_s:.1f} s",
    )

    for solver in (lierk.RKF45(), lierk.DP54(), lierk.DOP853()):
        run = lierk_adaptive_fn(solver)
        for tol in LIERK_TOLS:
            (R, steps, res), s, first = timed(run, omegas, tol, repeats=REPEATS, min_time=MIN_TIME)
            add(
                f"lierk {solver.name}",
                "lierk",
                tol,
                R,
                s,
                steps,
                kind="tol",
                first=first,
                note=f"results {np.bincount(np.asarray(res)).tolist()}",
            )
    # The loop kind of the adjoint, measured without differentiating.
    for solver in (lierk.DOP853(),):
        run = lierk_adaptive_fn(solver, lierk.ForwardMode())
        for tol in LIERK_TOLS:
            (R, steps, _), s, first = timed(run, omegas, tol, repeats=REPEATS, min_time=MIN_TIME)
            add(f"lierk {solver.name} (lax loop)", "lierk-lax", tol, R, s, steps, kind="tol", first=first)
    for solver in (lierk.RKMK4(), lierk.CF4()):
        for dt in DTS:
            (R, steps), s, first = timed(lierk_fixed_fn(solver, dt), omegas, repeats=REPEATS, min_time=MIN_TIME)
            add(f"lierk {solver.name} fixed", "lierk", dt, R, s, steps, kind="dt", first=first)
    # High-order tableaux with fixed steps.  Near the separatrix the error that
    # matters is the energy error made during the slow phases, where a Lie
    # method's local error estimate is tiny (it integrates the fast spin about
    # the near-fixed axis almost exactly) and the controller lengthens the step;
    # uniform steps spend the work where the global error is made.
    for tableau, dts in ((lierk.tableaux.DOPRI54, HIGH_DTS[:4]), (lierk.tableaux.DOP853, HIGH_DTS)):
        for dt in dts:
            (R, steps), s, first = timed(
                lierk_fixed_fn(lierk.RKMK(tableau), dt), omegas, repeats=REPEATS, min_time=MIN_TIME
            )
            add(f"lierk RKMK({tableau.name}) fixed", "lierk", dt, R, s, steps, kind="dt", first=first)

    # The report's formulation (spatial L fixed, m = R^T L), same solvers.
    for dt in SPATIAL_DTS:
        (R, steps), s, first = timed(
            lierk_fixed_fn(lierk.RKMK4(), dt, lierk.SpatialFreeRigidBody), omegas, repeats=REPEATS, min_time=MIN_TIME
        )
        add("lierk RKMK4 fixed (Spatial)", "lierk-spatial", dt, R, s, steps, kind="dt", first=first)
    run = lierk_adaptive_fn(lierk.DOP853(), problem=lierk.SpatialFreeRigidBody)
    for tol in SPATIAL_TOLS:
        (R, steps, res), s, first = timed(run, omegas, tol, repeats=REPEATS, min_time=MIN_TIME)
        add(
            "lierk DOP853 (Spatial)",
            "lierk-spatial",
            tol,
            R,
            s,
            steps,
            kind="tol",
            first=first,
            note=f"results {np.bincount(np.asarray(res)).tolist()}",
        )

    for solver in (diffrax.Tsit5(), diffrax.Dopri5(), diffrax.Dopri8()):
        run = diffrax_fn(solver)
        for tol in TOLS:
            (R, steps), s, first = timed(run, omegas, tol, repeats=REPEATS, min_time=MIN_TIME)
            add(f"diffrax {type(solver).__name__}", "diffrax", tol, R, s, steps, kind="tol", first=first)

    frame_check = mujoco_frame_check(omegas_np[0])
    print(f"MuJoCo ball-joint qvel frame check: {frame_check}")
    for dt in MUJOCO_DTS:
        R, _, t_end, s, first = mujoco_batch(omegas_np, dt)
        add(
            "MuJoCo RK4 (ball joint)",
            "mujoco",
            dt,
            R,
            s,
            np.full(N, lierk.num_steps(0.0, T, dt)),
            kind="dt",
            first=first,
            note=f"rollout, {MUJOCO_THREADS} threads, |t_end - T| <= {np.max(np.abs(t_end - T)):.0e}",
        )

    one_ref = R_ref[0]
    for tol in TOLS:
        t = time.perf_counter()
        R, nfev = scipy_one(omegas_np[0], tol)
        s = (time.perf_counter() - t) * N
        add(
            f"scipy DOP853 (x{N})",
            "scipy",
            tol,
            R,
            s,
            err_R_ref=one_ref,
            kind="tol",
            note=f"one trajectory, nfev {nfev}",
        )
    for h in (0.01, 0.001):
        t = time.perf_counter()
        R = report_rk4_one(omegas_np[0], h)
        s = (time.perf_counter() - t) * N
        add(f"report NumPy RK4 (x{N})", "numpy", h, R, s, err_R_ref=one_ref, kind="dt", note="one trajectory")

    table = []
    for level in LEVELS:
        row = {"level": level}
        for family, _ in PROGRAMS:
            rec = best_time(records, level, family)
            row[family] = (
                None if rec is None else {"method": rec["method"], "param": rec["param"], "time_s": rec["time_s"]}
            )
        for peer in ("diffrax", "mujoco"):
            a, b = row["lierk"], row[peer]
            row[f"ratio_lierk_over_{peer}"] = a["time_s"] / b["time_s"] if a and b else None
        table.append(row)

    machine["load_average_at_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
    total = time.perf_counter() - t_start
    payload = {
        "quick": QUICK,
        "problem": {
            "inertia": np.asarray(INERTIA).tolist(),
            "batch": N,
            "T": T,
            "seed": SEED,
            "omega": "|omega| ~ U(1, 3) rad/s, direction (1, U(-0.2,0.2), U(-0.2,0.2)) normalised",
            "fraction_flipping_within_T": frac_flip,
        },
        "reference": "lierk.exact.free_rigid_body (closed form)",
        f"reference_vs_scipy_dop853_{CHECK_TOL:.0e}": dict(zip(map(str, CHECK_IDS), check)),
        "exact_ceiling": {
            "time_s": exact_s,
            "compile_s": exact_compile_s,
            "error": max(check),
            "error_measured_against": f"SciPy DOP853 rtol=atol={CHECK_TOL:.0e} (9-component ODE) "
            f"on members {CHECK_IDS}",
        },
        "mujoco": {
            "version": mujoco.__version__,
            "model": mujoco_xml(MUJOCO_DTS[0]),
            "threads": MUJOCO_THREADS,
            "qvel_frame_check": frame_check,
            "qvel_frame": "body",
        },
        "error": f"max over the batch of ||R(T) - R_ref(T)||_F (scipy and NumPy: member 0 only; "
        f"lierk.exact: against SciPy on members {CHECK_IDS})",
        "timing": f"median of at least {REPEATS} calls (more until they add up to {MIN_TIME} s) after warm-up; "
        f"scipy/NumPy: one trajectory x {N}",
        "machine": machine,
        "total_runtime_s": total,
        "records": records,
        "table": table,
    }
    write_results(OUT, "work_precision", payload, markdown(payload))
    plot(records)
    print(f"and work_precision.png; total {total:.0f} s")


def _param(x) -> str:
    return "-" if x is None else f"{x:.0e}"


def markdown(p) -> list[str]:
    m = p["machine"]
    ceiling = p["exact_ceiling"]
    frame = p["mujoco"]["qvel_frame_check"]
    n, T_ = p["problem"]["batch"], p["problem"]["T"]
    lines = [
        f"# Work-precision: T-handle, {n} bodies near the intermediate axis, T = {T_:g} s",
        "",
        ("**QUICK RUN (tiny size, timings meaningless).**\n" if p["quick"] else "")
        + f"Reference: {p['reference']}. Fraction of the batch that flips within T: "
        f"{p['problem']['fraction_flipping_within_T']:.2f}.",
        f"Error: {p['error']}. Timing: {p['timing']}.",
        f"Ceiling, lierk.exact for the whole batch: {ceiling['time_s']:.4f} s (jitted, vmapped; compile "
        f"{ceiling['compile_s']:.1f} s); its error against {ceiling['error_measured_against']}: "
        + ", ".join(f"{v:.1e}" for v in p[f"reference_vs_scipy_dop853_{CHECK_TOL:.0e}"].values())
        + ".",
        f"MuJoCo {p['mujoco']['version']}: one body on a ball joint, gravity off, RK4, `mujoco.rollout` with "
        f"{p['mujoco']['threads']} threads. Ball-joint qvel is the body-frame angular velocity: after 1 s at "
        f"dt 1e-3 from a tilted start, |qvel - omega_body| = {frame['qvel_minus_exact_body_omega']:.1e}, "
        f"|qvel - R omega_body| = {frame['qvel_minus_exact_spatial_omega']:.1e}, "
        f"|R - R_exact| = {frame['R_error']:.1e}.",
        f"Machine: {m['cpu_count']} cores, {m['cpu']}, jax {m['jax']}, diffrax {m['diffrax']}, mujoco {m['mujoco']}, "
        f"scipy {m['scipy']}. Load average at start {m['load_average_at_start']}. "
        f"Total runtime {p['total_runtime_s']:.0f} s.",
        "",
        "## Error reached at each tolerance",
        "",
        "Max error over the batch (median time for the batch). Adaptive lierk runs use `rtol = atol = tol`",
        "(lierk measures the momentum error relative to its size); diffrax and SciPy `rtol = atol = tol`.",
        "",
        *series_table(p["records"], "tol", "tol"),
        "",
        "## Error reached at each step size",
        "",
        *series_table(p["records"], "dt", "dt (s)"),
        "",
        "## Cheapest time to reach each error level, per program",
        "",
        "Each cell: time (s) for the batch, and the setting that reached the level at that cost.",
        "",
        "| error <= | " + " | ".join(h for _, h in PROGRAMS) + " | lierk / diffrax | lierk / MuJoCo |",
        "|---" * (len(PROGRAMS) + 3) + "|",
    ]
    for row in p["table"]:
        cells = []
        for family, _ in PROGRAMS:
            x = row[family]
            if x is None:
                cells.append("-")
            else:
                setting = "" if x["param"] is None else f", {_param(x['param'])}"
                cells.append(f"{x['time_s']:.3g} ({x['method']}{setting})")
        ratios = [
            "-" if row[k] is None else f"{row[k]:.2f}" for k in ("ratio_lierk_over_diffrax", "ratio_lierk_over_mujoco")
        ]
        lines.append(f"| {row['level']:.0e} | " + " | ".join(cells) + " | " + " | ".join(ratios) + " |")
    lines += [
        "",
        "## All runs",
        "",
        "| method | tol or dt | max error | time (s) | first call (s) | max steps | max orthogonality error | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in p["records"]:
        first = "" if r["first_call_s"] is None else f"{r['first_call_s']:.2f}"
        lines.append(
            f"| {r['method']} | {_param(r['param'])} | {r['error']:.2e} | {r['time_s']:.4f} | {first} | "
            f"{r.get('max_steps', '')} | {r['orthogonality']:.1e} | {r['note']} |"
        )
    return lines


def plot(records):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["method"] for r in records))
    colours = plt.get_cmap("tab20").colors
    markers = ["o", "s", "^", "v", "D", "P", "X", "<", ">", "h", "p", "d", "H", "8", "x", "+", "1", "2", "3", "4"]
    assert len(names) <= min(len(colours), len(markers)), "more series than distinct colours/markers"
    fig, ax = plt.subplots(figsize=(9, 6.5))
    for k, name in enumerate(names):
        rs = sorted((r for r in records if r["method"] == name), key=lambda r: r["time_s"])
        family = rs[0]["family"]
        style = {"lierk": "-", "lierk-lax": "-", "lierk-spatial": ":", "exact": ""}.get(family, "--")
        ms = 12 if family == "exact" else 4
        marker = "*" if family == "exact" else markers[k % len(markers)]
        ax.loglog(
            [r["time_s"] for r in rs],
            [max(r["error"], 1e-16) for r in rs],
            linestyle=style or "none",
            marker=marker,
            ms=ms,
            color=colours[k],
            label=name,
        )
    ax.set_xlabel(f"wall time for {N} bodies (s)")
    ax.set_ylabel("max error ||R(T) - R_ref(T)||_F")
    ax.set_title(f"T-handle near the intermediate axis, T = {T:g} s, float64")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(OUT / "work_precision.png", dpi=120)


if __name__ == "__main__":
    main()
