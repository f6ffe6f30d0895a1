"""What an event costs: the same solve with and without one, for one body and a batch.

Free 1:2:3 boxes (I = diag(1, 2, 3) kg m^2) spun near their intermediate
axis, omega0 = (U(-0.05, 0.05), 1, U(-0.05, 0.05)) rad/s from a fixed seed,
over 60 s in float64: one body, and a `jax.vmap` of 500 (``--quick``: 50
bodies over 10 s).  Solvers: fixed-step RKMK4 (dt = 0.01 s) and adaptive
DOP853 (rtol = atol = 1e-8).  Events, each recording every crossing:

- none;
- ``lierk.conditions.flip(body)``: the intermediate-axis flip (about four
  crossings per body in 60 s);
- ``lierk.conditions.tilt(1.0, axis=(0, 1, 0))``: the intermediate axis
  leaning 1 rad from space z (a condition on the attitude);
- a user's own condition, ``Event(lambda t, R, m: m[1] - 0.5 m0[1])``;
- the tilt read at 4 points of each step (``samples=4``), which builds
  every step's interpolant.

Each program is one ``jax.jit`` (of the ``jax.vmap`` for the batch).  Times:
compile and first call together, then the median of later calls (at least
3, up to 51, until they add up to 0.5 s), with the ratio to the same solve
without an event.  Each cell keeps its smallest later time over
``--runs`` rounds (default 3), every program compiled anew in each round,
and the first call of the first round.

Writes benchmarks/results/event_cost.{json,md}.  Run:
``python benchmarks/event_cost.py``; ``--quick`` (50 bodies over 10 s, one
repeat) only checks that the script works, and writes to a temporary
directory unless ``--out`` is given.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from common import backend_text, cli, git_commit, machine_info, timed, write_results  # noqa: E402

import lierk  # noqa: E402

QUICK, OUT, ARGS = cli(
    __doc__,
    "tiny run (50 bodies over 10 s, one repeat) to check the script works",
    __name__ == "__main__",
    extra=lambda p: p.add_argument(
        "--runs", type=int, default=None, help="rounds of every cell, each compiled anew; the smallest kept (default 3)"
    ),
)

BATCH = 50 if QUICK else 500
T1 = 10.0 if QUICK else 60.0
REPEATS = 1 if QUICK else 3
# Rounds of every cell, each program compiled anew: a one-body program runs
# at one of two speeds drawn per compilation on a shared machine (about
# 1.7x apart), so each cell keeps its smallest later time over the rounds.
RUNS = ARGS.runs or (1 if QUICK else 3)
MIN_TIME = 0.0 if QUICK else 0.5
INERTIA = np.array([1.0, 2.0, 3.0])
SOLVERS = {
    "RKMK4, dt 0.01": (lierk.RKMK4(), dict(dt=0.01)),
    "DOP853, rtol 1e-8": (lierk.DOP853(), dict(rtol=1e-8, atol=1e-8, max_steps=20_000)),
}
EVENTS = {
    "none": lambda body, w: None,
    "flip": lambda body, w: lierk.conditions.flip(body),
    "tilt": lambda body, w: lierk.conditions.tilt(1.0, axis=(0.0, 1.0, 0.0)),
    "own": lambda body, w: lierk.Event(lambda t, R, m: m[1] - 0.5 * body.inertia[1, 1] * w[1]),
    "tilt, samples 4": lambda body, w: lierk.Event(lierk.conditions.tilt(1.0, axis=(0.0, 1.0, 0.0)).cond, samples=4),
}


def omegas(n: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    return np.stack([rng.uniform(-0.05, 0.05, n), np.ones(n), rng.uniform(-0.05, 0.05, n)], axis=1)


def program(solver, control: dict, event: str, batched: bool):
    def one(w):
        body = lierk.FreeRigidBody(INERTIA, w)
        ev = EVENTS[event](body, w)
        sol = lierk.solve(body, solver, T1, event=ev, throw=False, **control)
        return sol.R[-1], (sol.events.count if ev is not None else jnp.zeros((), jnp.int32))

    return jax.jit(jax.vmap(one)) if batched else jax.jit(one)


def main():
    cells = [
        (batched, w, label, solver, control, event)
        for batched, w in ((False, jnp.asarray(omegas(1)[0])), (True, jnp.asarray(omegas(BATCH))))
        for label, (solver, control) in SOLVERS.items()
        for event in EVENTS
    ]
    best = {}  # (bodies, solver, event) -> [first, later, crossings]
    for run in range(RUNS):
        print(f"round {run + 1} of {RUNS}", flush=True)
        for batched, w, label, solver, control, event in cells:
            (_, count), later, first = timed(
                program(solver, control, event, batched), w, repeats=REPEATS, min_time=MIN_TIME
            )
            key = (BATCH if batched else 1, label, event)
            # The first call from the first round only: later rounds find
            # JAX's caches of the inner programs' traces warm.
            old = best.get(key, [first, np.inf, 0])
            best[key] = [old[0], min(old[1], later), int(np.sum(np.asarray(count)))]
            print(
                f"  {key[0]:4d} bodies, {label}, {event:15s}: first {first:.2f} s, later {later * 1e3:.2f} ms",
                flush=True,
            )
    records = []
    for (size, label, event), (first, later, crossings) in best.items():
        base = best[(size, label, "none")]
        records.append(
            dict(
                bodies=size,
                solver=label,
                event=event,
                first_call_s=first,
                later_s=later,
                first_ratio=first / base[0],
                later_ratio=later / base[1],
                crossings=crossings,
            )
        )
    result = dict(
        machine=machine_info(), commit=git_commit(), quick=QUICK, batch=BATCH, t1=T1, runs=RUNS, records=records
    )
    lines = [
        "# What an event costs (`benchmarks/event_cost.py`)",
        "",
        f"Free 1:2:3 boxes near their intermediate axis over {T1:g} s, float64: one body and a `jax.vmap` of "
        f"{BATCH}; each event records every crossing. First: compile and first call; later: median of later "
        f"calls, the smallest of {RUNS} rounds (every program compiled anew in each; first calls from the first "
        "round); ratios to the same solve without an event.",
        "",
        f"Machine: {result['machine']['cpu_count']} cores, {result['machine']['cpu']}, "
        f"{backend_text(result['machine'])}, jax {result['machine']['jax']}; lierk at {result['commit']}.",
        "",
        "| bodies | solver | event | first (s) | first ratio | later (ms) | later ratio | crossings |",
        "|---:|---|---|---:|---:|---:|---:|---:|",
        *[
            f"| {r['bodies']} | {r['solver']} | {r['event']} | {r['first_call_s']:.2f} | {r['first_ratio']:.2f} | "
            f"{r['later_s'] * 1e3:.3g} | {r['later_ratio']:.2f} | {r['crossings']} |"
            for r in records
        ],
    ]
    write_results(OUT, "event_cost", result, lines)


if __name__ == "__main__":
    main()
