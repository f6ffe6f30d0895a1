"""Time to first result: a fresh process's first solve and first Jacobian, lierk beside diffrax.

Every cell runs in a process of its own with JAX's persistent cache off, so
each first call pays the whole cost once, as a user's new script does:

- ``solve``: ``jax.jit`` of a function that builds the problem and returns
  ``R(T)``, called once; split into tracing and lowering
  (``jax.jit(f).lower``), XLA's compilation (``.compile()``) and the first
  run; then the compiled program's median time over later calls, each with
  a new omega0 (one body's run inside a caller's ``jit``);
- ``jacfwd``: the same for ``jax.jit(jax.jacfwd(f))``, the Jacobian of
  ``R(T)`` with respect to ``omega0`` (diffrax with
  ``adjoint=ForwardMode()``, which `jax.jacfwd` needs: its default adjoint
  is a ``custom_vjp``, fixed steps included);
- ``call``: ``lierk.solve(problem, solver, T, ...)`` called from Python
  beside ``diffrax.diffeqsolve(...)`` called from Python, each its
  library's own program (lierk's compiled with
  `lierk.one_body_compiler_options`), problem built outside the timer
  (total time only);
- ``eager``: ``jax.jacfwd(f)(omega0, s)`` called from Python with no
  ``jit``, as most users write it (total time only: the transform runs the
  operations around the solve one at a time, each its own program);
- ``sensitivity``: ``lierk.sensitivity(problem, solver, T, ...)`` called from
  Python (its own program; default method, with its error estimate), lierk
  only;
- ``steady``: the compiled ``jit(vmap(f))`` over a batch of 64 bodies, median
  wall time of repeated calls (compile excluded).

The optimized program's size is the number of instructions in XLA's optimized
HLO (``compiled.as_text()``).  lierk's solvers are measured as a user gets
them (``compact=None``: one body, or a differentiated solve, loops over the
stages of the tableaux of more than four stages on the CPU, a batch unrolls
them; `lierk.AbstractRKMK`) and also, for ``solve``, with ``compact=False``
(the stages unrolled for one body too) and, for ``steady``, with
``compact=True`` (the stage loop in the batch too).

Problems (float64, T = 1 s; fixed steps: 100; adaptive: rtol = atol = 1e-8):

- ``free``: a free body, I = (2, 3, 4) kg m^2, omega0 = (1, 0.3, 20) rad/s;
- ``top``: a heavy top about its pivot, the same inertia, centre of mass at
  (0.1, 0, 0.5) m, 1 kg, g = 9.81 m/s^2;
- ``spacecraft``: I = (10, 14, 6) kg m^2 on a circular orbit (n = 0.0011
  rad/s): gravity gradient, a constant rotor (0, 0.3, 0) kg m^2/s and B-dot
  (1e7 A m^2 s/T) in Earth's dipole field tilted 1.1 rad, omega0 = (0.05,
  -0.03, 0.04) rad/s, T = 60 s.

Solvers and their peers: RKMK4 (fixed) against Tsit5 at the same constant
step, RKMK(DOP853) (fixed) against Dopri8 (constant step), DP54 against Dopri5
and DOP853 against Dopri8 (adaptive, ``PIDController(rtol, atol)``); diffrax
integrates the 12-component system (``peers.rigid_body_field``).

Targets (issue 39): first solve at most 1.5x diffrax's; first Jacobian at
most 2x diffrax's first ``jit(jacfwd)``.

Run: ``python benchmarks/first_result.py [--quick] [--repeats N] [--out DIR]
[--works W,...]`` (``--quick``: the heavy top with DOP853, one repeat;
``--works``: only those cells, written to first_result-W-....{json,md});
writes first_result.{json,md} after each comparison, so a run stopped part-way
keeps what it measured.  ``--one CELL`` runs one cell in this process and
prints its JSON (what the runs above call).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import time

BODIES = ("free", "top", "spacecraft")
# name: (fixed, diffrax peer)
SOLVERS = {
    "RKMK4": (True, "Tsit5"),
    "RKMK(DOP853)": (True, "Dopri8"),
    "DP54": (False, "Dopri5"),
    "DOP853": (False, "Dopri8"),
}
WORKS = ("solve", "call", "jacfwd", "eager", "sensitivity", "steady")
STEPS, RTOL, BATCH, CALLS = 100, 1e-8, 64, 20
QUICK = (("top", "DOP853"),)


def _setup(body: str):
    """``(inertia, omega0, T, lierk effects factory, peer torque)`` of a problem."""
    import numpy as np
    import peers

    if body in ("free", "top"):
        inertia, omega0, T = (2.0, 3.0, 4.0), (1.0, 0.3, 20.0), 1.0
    else:
        inertia, omega0, T = (10.0, 14.0, 6.0), (0.05, -0.03, 0.04), 60.0
    chi, mass, g = np.array([0.1, 0.0, 0.5]), 1.0, 9.81
    n, rotor, bdot, tilt = 0.0011, np.array([0.0, 0.3, 0.0]), 1e7, 1.1

    def effects():
        import lierk

        if body == "free":
            return ()
        if body == "top":
            return (lierk.Gravity(chi, mass, g),)
        return (
            lierk.GravityGradient(np.asarray(inertia), mean_motion=n),
            lierk.Rotor(rotor),
            lierk.MagneticTorque(lierk.dipole_field(n, tilt=tilt), bdot_gain=bdot),
        )

    if body == "free":
        torque = None
    elif body == "top":
        torque = peers.gravity_torque(mass, g, chi)
    else:
        torque = peers.orbit_torque(np.asarray(inertia), n, rotor, bdot, tilt)
    return np.asarray(inertia), np.asarray(omega0), T, effects, torque


def _function(body: str, solver_name: str, peer: str, compact: bool | None):
    """``(f(w, s) -> R(T), s)``: the solve as a function of omega0 and its
    setting ``s`` (``dt`` or ``rtol = atol``, traced)."""
    import jax.numpy as jnp

    inertia, _, T, effects, torque = _setup(body)
    fixed, dx_solver = SOLVERS[solver_name]
    s = jnp.asarray(T / STEPS if fixed else RTOL)
    if peer == "lierk":
        import lierk

        solver = {"RKMK4": lierk.RKMK4, "DP54": lierk.DP54, "DOP853": lierk.DOP853}.get(solver_name)
        solver = (
            lierk.RKMK(lierk.tableaux.DOP853, compact=compact)
            if solver is None
            else (solver() if compact is None else solver(compact=compact))
        )

        def f(w, s):
            problem = lierk.RigidBodyWithEffects(inertia, w, effects=effects())
            kw = dict(dt=s, max_steps=STEPS) if fixed else dict(rtol=s, atol=s)
            return lierk.solve(problem, solver, T, throw=False, **kw).R[-1]

        return f, s, solver
    import peers

    field = peers.rigid_body_field(inertia, torque)

    def f(w, s, forward_mode=False):
        y0 = peers.initial_state(inertia, w)
        kw = dict(dt=s, max_steps=STEPS + 1) if fixed else dict(rtol=s)
        return peers.diffrax_solve(field, dx_solver, T, y0, forward_mode=forward_mode, **kw)[0]

    return f, s, None


def _size(compiled) -> int:
    """Instructions in the optimized HLO (every line that defines a value)."""
    return sum(1 for line in compiled.as_text().splitlines() if " = " in line and not line.lstrip().startswith("//"))


def run_cell(cell: dict) -> dict:
    """Run one cell in this process: seconds for each part of the first call,
    program size, or the steady-state median."""
    t_start = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)
    import jax.numpy as jnp
    import numpy as np

    if cell["peer"] == "lierk":
        import lierk  # noqa: F401
    else:
        import diffrax  # noqa: F401
    imported = time.perf_counter() - t_start
    body, solver_name, work, peer, compact = cell["body"], cell["solver"], cell["work"], cell["peer"], cell["compact"]
    _, omega0, T, effects, _ = _setup(body)
    w0 = jnp.asarray(omega0)
    f, s, solver = _function(body, solver_name, peer, compact)
    fixed = SOLVERS[solver_name][0]
    out = {"import": imported}
    if work == "sensitivity":
        import lierk

        inertia = _setup(body)[0]
        kw = dict(dt=T / STEPS, max_steps=STEPS) if fixed else dict(rtol=RTOL, atol=RTOL)
        t = time.perf_counter()
        sens = lierk.sensitivity(
            lierk.RigidBodyWithEffects(inertia, omega0, effects=effects()), solver, T, throw=False, **kw
        )
        jax.block_until_ready(sens.jacobian)
        out.update(
            first=time.perf_counter() - t,
            method=lierk.sensitivity_method(
                lierk.RigidBodyWithEffects(inertia, omega0, effects=effects()), solver, method="derivative"
            ),
        )
        return out
    if work == "call":
        inertia, _, _, _, torque = _setup(body)
        if peer == "lierk":
            import lierk

            kw = dict(dt=T / STEPS, max_steps=STEPS) if fixed else dict(rtol=RTOL, atol=RTOL)
            built = effects()

            def call(w):
                problem = lierk.RigidBodyWithEffects(inertia, w, effects=built)
                return jax.block_until_ready(lierk.solve(problem, solver, T, throw=False, **kw).R)
        else:
            import peers

            kw = dict(dt=T / STEPS, max_steps=STEPS + 1) if fixed else dict(rtol=RTOL)
            field = peers.rigid_body_field(inertia, torque)

            def call(w):
                y0 = peers.initial_state(inertia, w, xp=np)
                return jax.block_until_ready(peers.diffrax_solution(field, SOLVERS[solver_name][1], T, y0, **kw).ys)

        t = time.perf_counter()
        call(omega0)
        out.update(first=time.perf_counter() - t)
        # Later calls with new initial velocities: the host's work per call
        # beside the compiled program's run.
        times = []
        for i in range(CALLS):
            t = time.perf_counter()
            call(omega0 * (1 + 1e-3 * (i + 1)))
            times.append(time.perf_counter() - t)
        out["call_steady"] = float(np.median(times))
        return out
    if work == "steady":
        rng = np.random.default_rng(0)
        W = jnp.asarray(omega0 * (1 + 0.05 * rng.standard_normal((BATCH, 3))))
        g = jax.jit(jax.vmap(f, in_axes=(0, None)))
        jax.block_until_ready(g(W, s))
        times = []
        while len(times) < 5 or (sum(times) < 1.0 and len(times) < 51):
            t = time.perf_counter()
            jax.block_until_ready(g(W, s))
            times.append(time.perf_counter() - t)
        out["steady"] = float(np.median(times))
        return out
    if work in ("jacfwd", "eager"):
        g = jax.jacfwd(f) if peer == "lierk" else jax.jacfwd(lambda w, s: f(w, s, forward_mode=True))
    else:
        g = f
    if work == "eager":
        t0 = time.perf_counter()
        jax.block_until_ready(g(w0, s))
        out.update(first=time.perf_counter() - t0)
        return out
    # ``options``: the caller's jit passes lierk's one-body compile options
    # (`benchmarks/compiler_options.py`).
    opts = None
    if cell.get("options"):
        import lierk

        opts = lierk.one_body_compiler_options()
    t0 = time.perf_counter()
    lowered = jax.jit(g, compiler_options=opts).lower(w0, s)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    jax.block_until_ready(compiled(w0, s))
    t3 = time.perf_counter()
    out.update(trace=t1 - t0, compile=t2 - t1, run=t3 - t2, first=t3 - t0, size=_size(compiled))
    if work in ("solve", "jacfwd"):
        times = []
        for i in range(CALLS):
            w = w0 * (1 + 1e-3 * (i + 1))
            t = time.perf_counter()
            jax.block_until_ready(compiled(w, s))
            times.append(time.perf_counter() - t)
        out["one_steady"] = float(np.median(times))
    return out


def _fresh(cell: dict) -> dict:
    """`run_cell` in a fresh process."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
    p = subprocess.run([sys.executable, __file__, "--one", json.dumps(cell)], env=env, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{cell} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def cells(pairs, works=WORKS):
    for body, solver in pairs:
        for work in works:
            yield dict(body=body, solver=solver, work=work, peer="lierk", compact=None)
            if work in ("solve", "steady"):
                # One body's solve unrolled; a batch's looped.
                yield dict(body=body, solver=solver, work=work, peer="lierk", compact=work == "steady")
            if work != "sensitivity":
                yield dict(body=body, solver=solver, work=work, peer="diffrax", compact=None)


def main(argv=None):
    import common  # only the standard library: the timed children import jax themselves

    def extra(parser):
        parser.add_argument("--repeats", type=int, default=None, help="fresh processes per cell (default 3; --quick 1)")
        parser.add_argument("--one", default=None, help=argparse.SUPPRESS)
        parser.add_argument(
            "--works",
            default=None,
            help=f"comma-separated subset of {','.join(WORKS)}; writes first_result-<works>.{{json,md}}",
        )
        parser.add_argument("--bodies", default=None, help=f"comma-separated subset of {','.join(BODIES)}")
        parser.add_argument("--solvers", default=None, help=f"comma-separated subset of {','.join(SOLVERS)}")

    quick, out, args = common.cli(
        __doc__, "the heavy top with DOP853, one repeat, into a temp dir", extra=extra, argv=argv
    )
    if args.one:
        print(json.dumps(run_cell(json.loads(args.one))))
        return
    repeats = args.repeats or (1 if quick else 3)
    works = tuple(args.works.split(",")) if args.works else WORKS
    unknown = [w for w in works if w not in WORKS]
    if unknown:
        raise SystemExit(f"--works: unknown {', '.join(unknown)}; choose from {', '.join(WORKS)}")
    name = "first_result" if works == WORKS else "first_result-" + "-".join(works)
    pairs = QUICK if quick else [(b, s) for b in BODIES for s in SOLVERS]
    for option, known, i in ((args.bodies, BODIES, 0), (args.solvers, tuple(SOLVERS), 1)):
        if option:
            chosen = option.split(",")
            unknown = [c for c in chosen if c not in known]
            if unknown:
                raise SystemExit(f"unknown {', '.join(unknown)}; choose from {', '.join(known)}")
            pairs = [p for p in pairs if p[i] in chosen]

    meta = {
        "machine": common.machine_info(),
        "commit": common.git_commit(),
        "repeats": repeats,
        "steps": STEPS,
        "rtol": RTOL,
        "batch": BATCH,
    }
    rows = []
    todo = len(list(cells(pairs, works)))
    meta.update(cells=todo, measured=0)
    for _, group in itertools.groupby(cells(pairs, works), key=lambda c: (c["body"], c["solver"], c["work"])):
        # The cells compared with each other (lierk, compact, diffrax) take
        # turns, repeat by repeat: this 2-core machine's speed drifts by a
        # third over minutes, and a ratio of cells timed minutes apart drifted
        # with it.
        group = list(group)
        runs = [[] for _ in group]
        for _ in range(repeats):
            for cell, done in zip(group, runs):
                done.append(_fresh(cell))
        for cell, done in zip(group, runs):
            row = dict(cell, **{k: statistics.median(r[k] for r in done) for k in done[0] if k != "method"})
            if "method" in done[0]:
                row["method"] = done[0]["method"]
            rows.append(row)
            value = row.get("first", row.get("steady"))
            compact = "" if cell["compact"] is None else f"compact={cell['compact']}"
            print(
                f"{cell['body']:10s} {cell['solver']:13s} {cell['work']:11s} {cell['peer']:7s} "
                f"{compact:13s} {value:8.3f} s",
                flush=True,
            )
        # After every comparison: a run stopped part-way (a time limit on a
        # lent machine) keeps what it measured, and says how much that is.
        meta["measured"] = len(rows)
        meta["machine"]["load_average_at_end"] = os.getloadavg()
        common.write_results(out, name, {"meta": meta, "rows": rows}, markdown(meta, rows))


def _find(rows, **kw):
    return next((r for r in rows if all(r.get(k) == v for k, v in kw.items())), None)


def _first(cell) -> str:
    """A first call as ``total (trace + compile + run)``, seconds."""
    return f"{cell['first']:.2f} ({cell['trace']:.2f} + {cell['compile']:.2f} + {cell['run']:.2f})"


def _verdict(cell, peer, target: float) -> str:
    """``ratio | met (<= target)``: ``cell``'s first call over ``peer``'s."""
    r = cell["first"] / peer["first"]
    return f"{r:.2f} | {'met' if r <= target else 'missed'} (<= {target})"


def _ms_rows(rows, work, key, compact=None, digits=2) -> list[str]:
    """Table rows of ``work``'s times ``key`` (s) in ms, per problem: lierk's,
    lierk's with ``compact`` (None: no such column), diffrax's, then the
    ratios of lierk's to diffrax's; problems without all of them are left out."""
    out = []
    for body in BODIES:
        for solver, (_, peer) in SOLVERS.items():
            ours = [_find(rows, body=body, solver=solver, work=work, peer="lierk", compact=None)]
            if compact is not None:
                ours.append(_find(rows, body=body, solver=solver, work=work, peer="lierk", compact=compact))
            b = _find(rows, body=body, solver=solver, work=work, peer="diffrax")
            if any(r is None or key not in r for r in (*ours, b)):
                continue
            cells = [f"{1e3 * r[key]:.{digits}f}" for r in (*ours, b)] + [f"{r[key] / b[key]:.2f}" for r in ours]
            out.append(f"| {body} | {solver} vs {peer} | " + " | ".join(cells) + " |")
    return out


def markdown(meta, rows) -> list[str]:
    import common

    m = meta["machine"]
    lines = [
        "# Time to first result: lierk beside diffrax",
        "",
        f"{m['cpu_count']} cores ({m['cpu']}), {common.backend_text(m)}; jax {m['jax']}, lierk {m['lierk']}, "
        f"commit {meta['commit']}.  Every cell in a "
        f"fresh process without the persistent cache, median of {meta['repeats']} (the cells of one comparison "
        f"in turn); float64; {meta['steps']} fixed steps or "
        f"rtol = atol = {meta['rtol']:g}.  First call = trace (and lower) + XLA compile + first run, seconds; size: "
        f"instructions of the optimized program; steady: `jit(vmap)` over {meta['batch']} bodies, median ms.  Load "
        f"average at start {tuple(round(x, 1) for x in m['load_average_at_start'])}, at end "
        f"{tuple(round(x, 1) for x in m['load_average_at_end'])}."
        + (
            ""
            if meta.get("measured") == meta.get("cells")
            else f"  Stopped part-way: {meta['measured']} of {meta['cells']} cells measured."
        ),
        "",
        "## First solve and first Jacobian",
        "",
        "| problem | solver | work | lierk (trace + compile + run) | size | diffrax | size | lierk / diffrax "
        "| target |",
        "|---|---|---|---|---:|---|---:|---:|---|",
    ]
    for body in BODIES:
        for solver, (_, peer) in SOLVERS.items():

            def compared(work, label, target):
                """The row of ``work`` (lierk beside diffrax), if both were
                measured: split into its parts where it was; diffrax's cell."""
                a = _find(rows, body=body, solver=solver, work=work, peer="lierk", compact=None)
                b = _find(rows, body=body, solver=solver, work=work, peer="diffrax")
                if a is not None and b is not None:
                    cells = (
                        f"{_first(a)} | {a['size']} | {_first(b)} | {b['size']}"
                        if "trace" in a
                        else f"{a['first']:.2f} | | {b['first']:.2f} |"
                    )
                    lines.append(f"| {body} | {solver} vs {peer} | {label} | {cells} | {_verdict(a, b, target)} |")
                return b

            b = compared("solve", "solve", 1.5)
            c = _find(rows, body=body, solver=solver, work="solve", peer="lierk", compact=False)
            if c is not None and b is not None:
                lines.append(
                    f"| {body} | {solver} `compact=False` | solve | {_first(c)} | {c['size']} | | | "
                    f"{_verdict(c, b, 1.5)} |"
                )
            compared("call", "`lierk.solve` from Python", 1.5)
            b = compared("jacfwd", "jacfwd", 2.0)
            compared("eager", "eager `jax.jacfwd`", 2.0)
            s = _find(rows, body=body, solver=solver, work="sensitivity", peer="lierk")
            if s is not None and b is not None:
                lines.append(
                    f"| {body} | {solver} | `lierk.sensitivity` ({s['method']}, with its error estimate) "
                    f"| {s['first']:.2f} | | | | {_verdict(s, b, 2.0)} |"
                )
    if any("call_steady" in r for r in rows):
        lines += [
            "",
            "## A call from Python once compiled",
            "",
            f"Median of {CALLS} later calls in the same process, each with a new omega0 (the problem or initial "
            "state built in the call), ms: the host's work per call and the one-body program's run.",
            "",
            "| problem | solver | `lierk.solve` (ms) | `diffeqsolve` (ms) | lierk / diffrax |",
            "|---|---|---:|---:|---:|",
        ]
        lines += _ms_rows(rows, "call", "call_steady")
    if any("one_steady" in r for r in rows):
        lines += [
            "",
            "## One body inside `jax.jit`, once compiled",
            "",
            f"The `solve` cells' compiled programs: median of {CALLS} later calls, each with a new omega0, ms "
            "(the run's time and JAX's dispatch).",
            "",
            "| problem | solver | lierk (ms) | lierk `compact=False` (ms) | diffrax (ms) | lierk / diffrax | "
            "`compact=False` / diffrax |",
            "|---|---|---:|---:|---:|---:|---:|",
        ]
        lines += _ms_rows(rows, "solve", "one_steady", compact=False, digits=3)
    if not any(r["work"] == "steady" for r in rows):
        return lines
    lines += [
        "",
        "## Steady state (after compilation)",
        "",
        "| problem | solver | lierk (ms) | lierk `compact=True` (ms) | diffrax (ms) | lierk / diffrax "
        "| compact / diffrax |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    lines += _ms_rows(rows, "steady", "steady", compact=True)
    return lines


if __name__ == "__main__":
    main()
