"""Event times against cost: lierk's events against diffrax's `Event` on the same heavy top.

The family: Simo and Wong's fast Lagrange top (I = diag(5, 5, 1) kg m^2
about the pivot, mass 1 kg, g = 10 m/s^2, centre of mass chi = (0, 0, 2) m:
M g l = 20 N m), released at rest in its nutation (body omega0 = (0, 0, s),
spin s ~ U(45, 55) rad/s) tilted by U(0.2, 0.6) rad about a horizontal axis
at azimuth U(0, 2 pi); a batch of 256 (``--quick``: 4) from a fixed seed, in
float64.  The event: the symmetry axis first leans to the middle of its
nutation range, ``theta_c = (theta_min + theta_max)/2``, per member.

Reference: the Lagrange top's quadrature (``tests/lagrange.py``): with
``u = cos(theta) = u1 + (u2 - u1) sin^2(s)`` the top, released at ``u2``,
reaches ``u_c`` at ``t_c = 2 I1 int_{s_c}^{pi/2} ds/sqrt(c3 (u3 - u(s)))``,
a smooth integral computed to 1e-13 relative.

Programs, one jitted vmapped program per setting on one device:

- lierk (`lierk.RigidBodyWithEffects` with `lierk.Gravity`): adaptive DOP853
  and DP54 over ``rtol = atol``, fixed-step RKMK4 over dt, each with
  ``event=lierk.conditions.tilt(theta_c, terminate=True, direction=1)``: the
  crossing found on the step's interpolant on SO(3) (`lierk._event`); the
  event time is ``sol.ts[-1]``.
- diffrax Dopri8 and Tsit5, ``PIDController(rtol, atol)``, on the 12-component
  ODE (``m' = m x omega + M g (Gamma x chi)``, ``R' = R hat(omega)``), with
  ``diffrax.Event(cond_fn, optimistix.Newton(rtol=atol=1e-14))``,
  ``cond_fn = cos(theta_c) - R_zz``, ``direction=True``: its root finder on
  diffrax's own dense output; the event time is ``sol.ts[-1]``.

Error: the largest ``|t_event - t_c|`` (s) over the batch.  Timing: compile
and a warm-up call excluded, median of 3 calls (more, up to 51, until they
add up to 0.25 s).

Writes benchmarks/results/events.{json,md}.  Run:
``python benchmarks/events.py``; ``--quick`` (4 bodies, two settings per
program, no repeats) only checks that the script works, and writes to a
temporary directory unless ``--out`` is given.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
import peers  # noqa: E402
from common import cli, git_commit, interp_time, machine_info, series_table, timed, write_results  # noqa: E402
from scipy.integrate import quad  # noqa: E402

import lierk  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import lagrange  # noqa: E402

QUICK, OUT = cli(
    __doc__,
    "tiny run (4 bodies, two settings per program, no repeats) to check the script works",
    __name__ == "__main__",
)

N = 4 if QUICK else 256
SEED = 0
REPEATS = 1 if QUICK else 3
MIN_TIME = 0.0 if QUICK else 0.25
MAX_STEPS = 100_000
# (s) Every member's event comes within its first half nutation period (< 0.2 s).  A
# fixed-step solve's scan runs all of its ceil(T_MAX/dt) steps (those after
# the event are no-ops), so T_MAX is kept short; adaptive loops stop at the event.
T_MAX = 0.3
INERTIA, MASS, G, CHI = (5.0, 5.0, 1.0), 1.0, 10.0, (0.0, 0.0, 2.0)
LEVELS = [10.0**-k for k in range(4, 12)]


def sweep(values):
    """The whole sweep, or with --quick its coarsest and finest settings."""
    return tuple(values) if not QUICK else (values[0], values[-1])


TOLS_DOP853 = sweep((1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13))
TOLS_DP54 = sweep((1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11))
DTS_RKMK4 = sweep((4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4))


def family():
    """``(omega0 (N, 3), R0 (N, 3, 3), theta_c (N,), t_c (N,))``."""
    rng = np.random.default_rng(SEED)
    spin = rng.uniform(45.0, 55.0, N)
    tilt = rng.uniform(0.2, 0.6, N)
    azimuth = rng.uniform(0.0, 2 * math.pi, N)
    omega0 = np.stack([np.zeros(N), np.zeros(N), spin], axis=1)
    # A turn by `tilt` about the horizontal axis at `azimuth`.
    axes = np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(N)], axis=1)
    R0 = np.asarray(jax.vmap(lierk.so3.exp)(jnp.asarray(tilt[:, None] * axes)))
    theta_c, t_c = np.empty(N), np.empty(N)
    for i in range(N):
        q = lagrange.lagrange_top(np.diag(INERTIA), CHI, MASS * G, R0[i], omega0[i])
        theta_c[i] = 0.5 * (q.theta_min + q.theta_max)
        d, c3 = q.u2 - q.u1, 2 * q.I1 * q.mgl
        s_c = math.asin(math.sqrt((math.cos(theta_c[i]) - q.u1) / d))
        t_c[i] = (
            2
            * q.I1
            * quad(
                lambda s: 1 / math.sqrt(c3 * (q.u3 - q.u1 - d * math.sin(s) ** 2)),
                s_c,
                math.pi / 2,
                epsabs=0.0,
                epsrel=1e-13,
            )[0]
        )
    return omega0, R0, theta_c, t_c


def lierk_fn(solver, dt: float | None = None):
    """Adaptive (``dt`` None; the setting is ``rtol = atol``) or fixed-step solve."""
    gravity = lierk.Gravity(jnp.asarray(CHI), MASS, G)

    def one(w, R0, theta_c, setting):
        problem = lierk.RigidBodyWithEffects(np.asarray(INERTIA), w, R0, effects=(gravity,))
        event = lierk.conditions.tilt(theta_c, terminate=True, direction=1)
        control = dict(dt=dt) if dt is not None else dict(rtol=setting, atol=setting, max_steps=MAX_STEPS)
        sol = lierk.solve(problem, solver, T_MAX, event=event, throw=False, **control)
        return sol.ts[-1], sol.stats["num_steps"], sol.result != lierk.RESULTS.event_occurred

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, None)))


def diffrax_fn(solver):
    field = peers.rigid_body_field(INERTIA, peers.gravity_torque(MASS, G, CHI))
    root_finder = optx.Newton(rtol=1e-14, atol=1e-14)

    def one(w, R0, theta_c, tol):
        # R_zz, the cosine of the symmetry axis's tilt, is y[11] (R row-major).
        event = diffrax.Event(lambda t, y, args, **kw: jnp.cos(theta_c) - y[11], root_finder, direction=True)
        sol = peers.diffrax_solution(
            field, solver, T_MAX, peers.initial_state(INERTIA, w, R0), rtol=tol, max_steps=MAX_STEPS, event=event
        )
        return sol.ts[-1], sol.stats["num_steps"], sol.result != diffrax.RESULTS.event_occurred

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, None)))


def main():
    omega0, R0, theta_c, t_c = family()
    args = (jnp.asarray(omega0), jnp.asarray(R0), jnp.asarray(theta_c))
    print(f"{N} Lagrange tops; event times t_c from {t_c.min():.4f} to {t_c.max():.4f} s (quadrature)")
    # (A fixed step is structure: one program per dt.)
    programs = [
        ("lierk DOP853", "tol", lambda p: lierk_fn(lierk.DOP853()), TOLS_DOP853),
        ("lierk DP54", "tol", lambda p: lierk_fn(lierk.DP54()), TOLS_DP54),
        ("lierk RKMK4", "dt", lambda p: lierk_fn(lierk.RKMK4(), p), DTS_RKMK4),
        ("diffrax Dopri8", "tol", lambda p: diffrax_fn(diffrax.Dopri8()), TOLS_DOP853),
        ("diffrax Tsit5", "tol", lambda p: diffrax_fn(diffrax.Tsit5()), TOLS_DP54),
    ]
    records = []
    for method, kind, make, settings in programs:
        fn = None
        for p in settings:
            fn = make(p) if fn is None or kind == "dt" else fn
            (t_event, steps, missed), seconds, first = timed(fn, *args, p, repeats=REPEATS, min_time=MIN_TIME)
            missed = int(np.sum(np.asarray(missed)))
            err = float(np.max(np.abs(np.asarray(t_event) - t_c))) if not missed else float("inf")
            records.append(
                dict(
                    method=method,
                    kind=kind,
                    param=p,
                    error=err,
                    time_s=seconds,
                    first_call_s=first,
                    mean_steps=float(np.mean(np.asarray(steps))),
                    missed=missed,
                )
            )
            print(
                f"  {method:15s} {kind} {p:.0e}: event time error {err:.2e} s, {seconds * 1e3:.2f} ms, "
                f"{records[-1]['mean_steps']:.0f} steps" + (f", {missed} members without the event" if missed else "")
            )
    ratios = []
    for level in LEVELS:
        best = {}
        for prog in ("lierk", "diffrax"):
            hits = [
                interp_time([(r["error"], r["time_s"]) for r in records if r["method"] == m], level)
                for m in dict.fromkeys(r["method"] for r in records)
                if m.startswith(prog)
            ]
            hits = [h for h in hits if h is not None]
            best[prog] = min(hits, key=lambda h: h[0]) if hits else None
        if best["lierk"] and best["diffrax"]:
            ratios.append(
                dict(
                    level=level,
                    lierk_s=best["lierk"][0],
                    diffrax_s=best["diffrax"][0],
                    ratio=best["lierk"][0] / best["diffrax"][0],
                    clamped=best["lierk"][1] or best["diffrax"][1],
                )
            )
    result = dict(
        machine=machine_info(diffrax=diffrax.__version__, optimistix=optx.__version__),
        commit=git_commit(),
        n=N,
        quick=QUICK,
        records=records,
        ratios=ratios,
        t_c_range=[float(t_c.min()), float(t_c.max())],
    )
    lines = [
        "# Event times against cost (`benchmarks/events.py`)",
        "",
        f"{N} fast Lagrange tops (Simo-Wong, spin 45-55 rad/s, tilt 0.2-0.6 rad, released at rest in their "
        "nutation); the event: the axis first leans to the middle of its nutation range. Error: largest "
        "|t_event - t_quadrature| (s) over the batch; time: median wall time of the batch (one device).",
        "",
        *series_table(records, "tol", "rtol = atol"),
        "",
        *series_table(records, "dt", "dt (s)", fmt="{:.2g}"),
        "",
        "| event-time error <= | lierk best (s) | diffrax best (s) | lierk / diffrax |",
        "|---|---:|---:|---:|",
        *[
            f"| {r['level']:.0e} | {r['lierk_s']:.3g} | {r['diffrax_s']:.3g} | "
            f"{r['ratio']:.2f}{' *' if r['clamped'] else ''} |"
            for r in ratios
        ],
        "",
        "(* a program's cheapest setting is already below the level: the ratio is an upper bound on its time.)",
    ]
    write_results(OUT, "events", result, lines)


if __name__ == "__main__":
    main()
