"""A first call inside your own ``jax.jit``, with and without lierk's one-body compile options.

Called from Python, `lierk.solve` and `lierk.sensitivity` compile their
programs with `lierk.one_body_compiler_options` (XLA's older CPU loop
emitters).  Inside a caller's ``jax.jit`` lierk cannot: JAX takes compile
options only from the outermost ``jit``, so the caller chooses them.  This
measures what passing them buys:

    jax.jit(f, compiler_options=lierk.one_body_compiler_options())

against ``jax.jit(f)``, for one body's adaptive solve and its Jacobian
(``jax.jacfwd`` with respect to omega0), with diffrax's default ``jit`` of
the same problem beside them.  The cells are `first_result`'s (its problems,
its fresh process per cell without the persistent cache, its split of the
first call into trace, XLA compile and first run), plus the compiled
program's median run over 20 later calls with new omega0.

Run: ``python benchmarks/compiler_options.py [--quick] [--repeats N] [--out DIR]``
(``--quick``: the spacecraft's DP54 Jacobian, one repeat).
"""

from __future__ import annotations

import os
import statistics

BODIES = ("top", "spacecraft")
SOLVERS = ("DP54", "DOP853")
WORKS = ("solve", "jacfwd")
QUICK = (("spacecraft", "DP54", "jacfwd"),)
VARIANTS = (("lierk", False), ("lierk", True), ("diffrax", False))


def main(argv=None):
    import common
    import first_result

    def extra(parser):
        parser.add_argument("--repeats", type=int, default=None, help="fresh processes per cell (default 3; --quick 1)")

    quick, out, args = common.cli(
        __doc__, "the spacecraft's DP54 Jacobian, one repeat, into a temp dir", extra=extra, argv=argv
    )
    repeats = args.repeats or (1 if quick else 3)
    cases = QUICK if quick else [(b, s, w) for b in BODIES for s in SOLVERS for w in WORKS]
    meta = {
        "machine": common.machine_info(),
        "commit": common.git_commit(),
        "repeats": repeats,
        "rtol": first_result.RTOL,
        "calls": first_result.CALLS,
    }
    rows = []
    for body, solver, work in cases:
        cells = [
            dict(body=body, solver=solver, work=work, peer=peer, compact=None, options=options)
            for peer, options in VARIANTS
        ]
        # The three take turns, repeat by repeat (this machine's speed drifts).
        runs = [[] for _ in cells]
        for _ in range(repeats):
            for cell, done in zip(cells, runs):
                done.append(first_result._fresh(cell))
        for cell, done in zip(cells, runs):
            rows.append(dict(cell, **{k: statistics.median(r[k] for r in done) for k in done[0]}))
            print(
                f"{body:10s} {solver:7s} {work:7s} {cell['peer']:7s} options={cell['options']!s:5s} "
                f"{rows[-1]['first']:6.2f} s",
                flush=True,
            )
        meta["machine"]["load_average_at_end"] = os.getloadavg()
        common.write_results(out, "compiler_options", {"meta": meta, "rows": rows}, markdown(meta, rows))


def markdown(meta, rows) -> list[str]:
    import common
    import first_result

    m = meta["machine"]
    lines = [
        "# A first call inside your own `jax.jit`, with lierk's one-body compile options",
        "",
        f"{m['cpu_count']} cores ({m['cpu']}), {common.backend_text(m)}; jax {m['jax']}, lierk {m['lierk']}, "
        f"commit {meta['commit']}.  `jax.jit(f)` against `jax.jit(f, compiler_options="
        "lierk.one_body_compiler_options())`, diffrax's `jax.jit(f)` beside them (its adaptive Dopri5 or Dopri8); "
        f"one fresh process per cell without the persistent cache, median of {meta['repeats']} (the three in turn); "
        f"float64, rtol = atol = {meta['rtol']:g}; first call = trace + XLA compile + first run, seconds; run: the "
        f"compiled program's median over {meta['calls']} later calls with new omega0, ms.  Load average at start "
        f"{tuple(round(x, 1) for x in m['load_average_at_start'])}, at end "
        f"{tuple(round(x, 1) for x in m['load_average_at_end'])}.",
        "",
        "| problem | solver | work | lierk `jit` (trace + compile + run) | run (ms) | with the options | run (ms) "
        "| diffrax | run (ms) | lierk / diffrax | with the options / diffrax |",
        "|---|---|---|---|---:|---|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        if r["peer"] != "lierk" or r["options"]:
            continue
        key = dict(body=r["body"], solver=r["solver"], work=r["work"])
        o = first_result._find(rows, peer="lierk", options=True, **key)
        d = first_result._find(rows, peer="diffrax", **key)
        if o is None or d is None:
            continue
        lines.append(
            f"| {r['body']} | {r['solver']} | {r['work']} | {first_result._first(r)} | {1e3 * r['one_steady']:.3f} "
            f"| {first_result._first(o)} | {1e3 * o['one_steady']:.3f} | {first_result._first(d)} "
            f"| {1e3 * d['one_steady']:.3f} | {r['first'] / d['first']:.2f} | {o['first'] / d['first']:.2f} |"
        )
    return lines


if __name__ == "__main__":
    main()
