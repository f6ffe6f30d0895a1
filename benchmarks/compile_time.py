"""Compilation time of lierk's main programs beside diffrax's equivalents.

Each program is compiled in a fresh process (nothing cached in memory, JAX's
persistent cache off), so every measurement pays the whole cost once:

- tracing and lowering, ``jax.jit(f).lower(*args)`` (s);
- XLA's compilation, ``.compile()`` (s).

The programs, one body in float64 (``jit(vmap)``: a batch of 64), the
settings (``dt`` or ``rtol = atol``) traced so that no value is baked in:

| program | lierk | diffrax (the 12-component system ``(m, R)``) |
|---|---|---|
| fixed, free body | RKMK4 | Tsit5, constant step |
| fixed, free body | RKMK(DOP853) | Dopri8, constant step |
| adaptive, free body | DOP853 | Dopri8, PID controller |
| fixed, heavy top (gravity) | RKMK(DOP853) | Dopri8, constant step |
| adaptive, heavy top | DOP853 | Dopri8, PID controller |
| jit(vmap), adaptive, heavy top | DOP853 | Dopri8 |
| jacfwd (omega0), fixed, free | RKMK4 | Tsit5, constant step (``ForwardMode``) |
| jacfwd (omega0), adaptive, free | DOP853 | Dopri8 (``ForwardMode``) |

The target (issue 20): adaptive DOP853 with an effect compiles in at most 2x
diffrax's Dopri8.  Repeated ``--repeats`` times (default 3, each in its own
process); the median is reported.

Run: ``python benchmarks/compile_time.py [--quick] [--repeats N] [--out DIR]``
(``--quick``: one repeat of three programs, into a temporary directory);
writes compile_time.{json,md}.  ``--one NAME PEER`` compiles one program in
this process and prints its times as JSON (what the runs above call).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

# name: (description, kind, body, lierk solver, diffrax solver)
PROGRAMS = {
    "fixed_free_rk4": ("fixed, free body", "fixed", "free", "RKMK4", "Tsit5"),
    "fixed_free_dop853": ("fixed, free body", "fixed", "free", "RKMK(DOP853)", "Dopri8"),
    "adaptive_free": ("adaptive, free body", "adaptive", "free", "DOP853", "Dopri8"),
    "fixed_top": ("fixed, heavy top (gravity)", "fixed", "top", "RKMK(DOP853)", "Dopri8"),
    "adaptive_top": ("adaptive, heavy top (gravity)", "adaptive", "top", "DOP853", "Dopri8"),
    "vmap_adaptive_top": ("jit(vmap) x64, adaptive, heavy top", "adaptive", "top", "DOP853", "Dopri8"),
    "jacfwd_fixed_free": ("jacfwd (omega0), fixed, free body", "fixed", "free", "RKMK4", "Tsit5"),
    "jacfwd_adaptive_free": ("jacfwd (omega0), adaptive, free body", "adaptive", "free", "DOP853", "Dopri8"),
}
QUICK = ("fixed_free_rk4", "adaptive_top")
TARGET = "adaptive_top"

T = 1.0  # s
STEPS = 100  # fixed steps
MAX_STEPS = 4096  # adaptive
INERTIA = (2.0, 3.0, 4.0)  # kg m^2, principal (heavy top: about the pivot)
OMEGA0 = (1.0, 0.3, 20.0)  # rad/s
PIVOT_TO_COM = (0.1, 0.0, 0.5)  # m
MASS, G = 1.0, 9.81


def _program(name: str, peer: str):
    """``(f, args)``: the function to jit and example arguments."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    _, kind, body, lierk_solver, diffrax_solver = PROGRAMS[name]
    inertia = np.asarray(INERTIA)
    setting = jnp.asarray(T / STEPS if kind == "fixed" else 1e-8)
    w0 = jnp.asarray(OMEGA0)
    chi = np.asarray(PIVOT_TO_COM)

    if peer == "lierk":
        import lierk
        from lierk.app.accuracy import method

        solver = method(lierk_solver).solver
        effects = (lierk.Gravity(chi, MASS, G),) if body == "top" else ()

        def solve(w, s):
            problem = lierk.RigidBodyWithEffects(inertia, w, effects=effects)
            kw = dict(dt=s, max_steps=STEPS) if kind == "fixed" else dict(rtol=s, atol=s, max_steps=MAX_STEPS)
            return lierk.solve(problem, solver, T, throw=False, **kw).R[-1]
    else:
        import peers

        field = peers.rigid_body_field(inertia, peers.gravity_torque(MASS, G, chi) if body == "top" else None)

        def solve(w, s):
            y0 = peers.initial_state(inertia, w)
            kw = dict(dt=s, max_steps=STEPS + 1) if kind == "fixed" else dict(rtol=s, max_steps=MAX_STEPS)
            # (jacfwd: ForwardMode, as diffrax's default adjoint is reverse mode only)
            return peers.diffrax_solve(field, diffrax_solver, T, y0, forward_mode=name.startswith("jacfwd"), **kw)[0]

    if name.startswith("vmap"):
        return jax.vmap(solve, in_axes=(0, None)), (jnp.tile(w0, (64, 1)), setting)
    if name.startswith("jacfwd"):
        return jax.jacfwd(solve), (w0, setting)
    return solve, (w0, setting)


def compile_one(name: str, peer: str) -> dict:
    """Trace, lower and compile one program in this process: seconds each."""
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)
    f, args = _program(name, peer)
    start = time.perf_counter()
    lowered = jax.jit(f).lower(*args)
    lowered_at = time.perf_counter()
    compiled = lowered.compile()
    done = time.perf_counter()
    jax.block_until_ready(compiled(*args))  # it runs
    return {"trace_and_lower": lowered_at - start, "compile": done - lowered_at, "total": done - start}


def run(name: str, peer: str) -> dict:
    """`compile_one` in a fresh process."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
    p = subprocess.run([sys.executable, __file__, "--one", name, peer], env=env, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{name} ({peer}) failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None):
    import common  # only the standard library: the timed children import jax themselves

    def extra(parser):
        parser.add_argument(
            "--repeats", type=int, default=None, help="fresh processes per program (default 3; --quick 1)"
        )
        parser.add_argument("--one", nargs=2, metavar=("NAME", "PEER"), help=argparse.SUPPRESS)

    quick, out, args = common.cli(__doc__, f"one repeat of {', '.join(QUICK)}, into a temp dir", extra=extra, argv=argv)
    if args.one:
        print(json.dumps(compile_one(*args.one)))
        return
    repeats = args.repeats or (1 if quick else 3)
    names = QUICK if quick else tuple(PROGRAMS)

    import jax

    import lierk

    rows = []
    for name in names:
        row = {
            "program": name,
            "description": PROGRAMS[name][0],
            "lierk_solver": PROGRAMS[name][3],
            "diffrax_solver": PROGRAMS[name][4],
        }
        for peer in ("lierk", "diffrax"):
            runs = [run(name, peer) for _ in range(repeats)]
            row[peer] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            row[peer]["runs"] = runs
        row["ratio"] = row["lierk"]["total"] / row["diffrax"]["total"]
        rows.append(row)
        print(
            f"{name}: lierk {row['lierk']['total']:.2f} s, diffrax {row['diffrax']['total']:.2f} s, "
            f"ratio {row['ratio']:.2f}",
            flush=True,
        )
    import diffrax

    meta = {
        "machine": {
            "cpu_count": os.cpu_count(),
            "load_average_at_end": os.getloadavg(),
            "jax": jax.__version__,
            "diffrax": diffrax.__version__,
            "lierk": lierk.__version__,
        },
        "repeats": repeats,
        "T": T,
        "fixed_steps": STEPS,
        "adaptive_max_steps": MAX_STEPS,
    }
    common.write_results(out, "compile_time", {"meta": meta, "rows": rows}, markdown(meta, rows))


def markdown(meta, rows) -> list[str]:
    m = meta["machine"]
    lines = [
        "# Compilation time: lierk beside diffrax",
        "",
        f"{m['cpu_count']} cores; jax {m['jax']}, diffrax {m['diffrax']}, lierk {m['lierk']}.  "
        "Each program compiled in a "
        f"fresh process, median of {meta['repeats']}; float64, one body (jit(vmap): 64), T = {meta['T']:g} s, "
        f"{meta['fixed_steps']} fixed steps or max_steps {meta['adaptive_max_steps']}.  Trace: tracing and lowering; "
        "compile: XLA.",
        "",
        "| program | lierk | trace (s) | compile (s) | diffrax | trace (s) | compile (s) | lierk / diffrax |",
        "|---|---|---:|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        a, b = r["lierk"], r["diffrax"]
        lines.append(
            f"| {r['description']} | {r['lierk_solver']} | {a['trace_and_lower']:.2f} | {a['compile']:.2f} | "
            f"{r['diffrax_solver']} | {b['trace_and_lower']:.2f} | {b['compile']:.2f} | {r['ratio']:.2f} |"
        )
    target = next((r for r in rows if r["program"] == TARGET), None)
    if target is not None:
        lines += ["", f"Target: adaptive DOP853 with an effect at most 2x diffrax's Dopri8: {target['ratio']:.2f}x."]
    return lines


if __name__ == "__main__":
    main()
