"""Headline cells: a small fixed set of lierk's headline measurements, one row each, for comparing commits.

Each cell is one measurement that another benchmark makes in full, cut to
what a regression check needs: a batch, one setting, its median wall time
after compilation and a warm-up call (`common.timed`: at least 5 calls, more
until they add up to 0.5 s) and, where there is an independent reference,
its error.  Float64; the CPU is split into one XLA host device per core
(`host_devices`), and every program but the sweep's runs on one of them.

- ``free_rkmk4``, ``free_dop853``: 256 T-handles near the intermediate axis
  (`common.near_axis`), ``T = 10`` s, ``jit(vmap)`` of the solve: RKMK4 at
  dt = 0.01 s and DOP853 at rtol = atol = 1e-10 (`work_precision.py`).
  Error: the largest ``||R(T) - R_exact(T)||_F`` against
  `lierk.exact.free_rigid_body`.
- ``top_dop853``, ``top_rkmk_dop853``: 128 asymmetric heavy tops
  (`torqued.py`'s ``asymmetric`` family: I = diag(0.6, 0.8, 0.3), centre of
  mass (0.02, 0.01, 0.5) m, 1 kg, g = 9.81, spin 30-120 rad/s, tilt 0.3 rad),
  ``T = 2`` s: DOP853 at rtol = atol = 1e-8 and RKMK(DOP853) at dt = 5e-3 s.
  Error against diffrax Dopri8 at rtol = atol = 1e-13 on the 12-component
  ODE (`peers`), independent of lierk.
- ``jac_<solver>_<how>``: the Jacobian ``dR(T)/d omega0`` of 128 T-handles,
  ``T = 10`` s, RKMK(DOP853) at dt = 0.1 s and DOP853 at rtol = atol =
  1e-8 (`sensitivity.py`): ``forward`` (``jit(vmap(final_R))``, the solve
  alone), ``jacfwd`` (``jit(vmap(jacfwd(final_R)))``), ``variational``
  (``jit(vmap(lierk.sensitivity(..., method="variational",
  estimate_error=False)))``) and ``jacfwd_of_vmap`` (``jit(jacfwd(vmap(final_R)))``
  of the first 16: a Jacobian of the whole batch, 48 tangents through 16
  bodies).  Error: the largest ``||J - J_exact||_F / ||J_exact||_F``, against
  `jax.jacfwd` of the closed form.  Each Jacobian's ratio to the forward
  solve (per body for ``jacfwd_of_vmap``) is in its ``extra``.
  ``jac_top_dop853_forward`` and ``..._jacfwd``: 64 of the heavy tops,
  ``T = 0.5`` s, DOP853 at 1e-8 (no reference: time only).
- ``first_solve``, ``first_jacfwd``: the first ``jax.jit`` solve of one heavy
  top (DOP853, rtol = atol = 1e-8, T = 1 s) and the first
  ``jax.jit(jax.jacfwd(...))`` of it, each in a fresh process with the
  persistent compilation cache off: trace, compile and run, in seconds
  (`first_result.py`'s ``top``/``DOP853`` cells, run by its code).
- ``sweep_jit_vmap``, ``sweep_lierk_sweep``: RKMK4, 10,000 T-handles x 1000
  steps of 0.01 s: a held ``jit(vmap)`` given the batch sharded over the
  host devices, and `lierk.sweep` given the NumPy batch (`sweep.py`).
  Body-steps per second in ``extra``.
- ``events_rkmk4_flip``, ``events_dop853_flip``: the ``free_*`` batch and
  settings with ``event=lierk.conditions.flip(body, max_count=4)``, the time
  of each body's first flip returned beside ``R(T)``; their ``extra`` gives
  the ratio to the same batch without the event (the ``free_*`` cell).
  Error: the largest ``|t_event - t_exact|`` (s), ``t_exact`` the first zero
  of the closed form's momentum along the intermediate axis (bracketed on a
  grid and refined on finer ones); a body whose event and reference disagree
  on whether it flips before ``T`` counts as an infinite error.

Every cell uses public API that has been stable for a while, so the script
runs against older commits of lierk (``PYTHONPATH`` pointing at another
checkout): a cell whose API a commit lacks is reported ``"n/a"`` with what
it needs, and a cell that raises is reported ``"failed"`` with the error;
neither stops the others.

Output: ``{cell: {"time": s, "error": x or null, "unit": ..., "extra":
{...}, "what": ...}}``, the key ``"_meta"`` holding the machine record and
the lierk imported.  ``--json PATH`` writes it there (what ``python -m
benchmarks compare`` reads); otherwise ``headline.{json,md}`` go to the
results directory.

Run: ``python benchmarks/headline.py [--quick] [--out DIR] [--json PATH]
[--cells NAME ...]`` (a few minutes on 2 cores; a ``--cells`` argument is a
cell or the prefix of several, e.g. ``jac`` or ``free``); ``--quick`` runs
tiny sizes (4 bodies, short times) only to check that it works.
"""

from __future__ import annotations

import inspect
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import common

# (group, what).  The groups share their batches and references.
CELLS = {
    "free_rkmk4": ("free", "256 T-handles, T = 10 s: RKMK4, dt = 0.01 s"),
    "free_dop853": ("free", "256 T-handles, T = 10 s: DOP853, rtol = 1e-10"),
    "top_dop853": ("top", "128 heavy tops, T = 2 s: DOP853, rtol = 1e-8"),
    "top_rkmk_dop853": ("top", "128 heavy tops, T = 2 s: RKMK(DOP853), dt = 5e-3 s"),
    "jac_rkmk_dop853_forward": ("jac", "128 T-handles, T = 10 s, RKMK(DOP853) dt = 0.1: jit(vmap(final_R))"),
    "jac_rkmk_dop853_jacfwd": ("jac", "... jit(vmap(jacfwd(final_R)))"),
    "jac_rkmk_dop853_variational": ("jac", "... jit(vmap(sensitivity(variational)))"),
    "jac_rkmk_dop853_jacfwd_of_vmap": ("jac", "... jit(jacfwd(vmap(final_R))), 16 bodies"),
    "jac_dop853_forward": ("jac", "128 T-handles, T = 10 s, DOP853 rtol = 1e-8: jit(vmap(final_R))"),
    "jac_dop853_jacfwd": ("jac", "... jit(vmap(jacfwd(final_R)))"),
    "jac_dop853_variational": ("jac", "... jit(vmap(sensitivity(variational)))"),
    "jac_dop853_jacfwd_of_vmap": ("jac", "... jit(jacfwd(vmap(final_R))), 16 bodies"),
    "jac_top_dop853_forward": ("jac_top", "64 heavy tops, T = 0.5 s, DOP853 rtol = 1e-8: jit(vmap(final_R))"),
    "jac_top_dop853_jacfwd": ("jac_top", "... jit(vmap(jacfwd(final_R)))"),
    "first_solve": ("first", "heavy top, DOP853 rtol = 1e-8: first jit solve, fresh process"),
    "first_jacfwd": ("first", "... first jit(jacfwd), fresh process"),
    "sweep_jit_vmap": ("sweep", "10,000 T-handles x 1000 RKMK4 steps: jit(vmap), batch sharded"),
    "sweep_lierk_sweep": ("sweep", "... lierk.sweep, NumPy batch"),
    "events_rkmk4_flip": ("free", "free_rkmk4 with event=flip(body)"),
    "events_dop853_flip": ("free", "free_dop853 with event=flip(body)"),
}


def select(patterns) -> list[str]:
    """The cells named by ``patterns`` (each a cell's name or a prefix of
    names, e.g. ``"jac"``), in `CELLS` order; all for none."""
    if not patterns:
        return list(CELLS)
    unknown = [p for p in patterns if not any(n == p or n.startswith(p + "_") for n in CELLS)]
    if unknown:
        raise ValueError(f"unknown cell(s) {', '.join(unknown)}; valid: {', '.join(CELLS)} (or a prefix)")
    return [n for n in CELLS if any(n == p or n.startswith(p + "_") for p in patterns)]


class Missing(Exception):
    """The lierk being measured lacks an API that a cell needs: that cell is "n/a"."""


def need(module, *names: str) -> None:
    """Raise `Missing` unless every dotted ``name`` resolves on ``module``
    (``"conditions.flip"``) or, written ``"solve(event)"``, the function takes
    that keyword."""
    for name in names:
        path, _, arg = name.partition("(")
        obj = module
        for part in path.split("."):
            if not hasattr(obj, part):
                raise Missing(f"lierk.{path}")
            obj = getattr(obj, part)
        if arg:
            params = inspect.signature(obj).parameters
            if arg.rstrip(")") not in params:
                raise Missing(f"lierk.{name}")


def run_cell(results: dict, name: str, fn, want) -> None:
    """``results[name] = fn()`` if ``name`` is wanted; a `Missing` API gives
    ``{"na": ...}`` and any other exception ``{"failed": ...}`` (its
    traceback printed), so that one cell never stops the others."""
    if name not in want:
        return
    print(f"  {name}", flush=True)
    start = time.perf_counter()
    try:
        rec = fn()
    except Missing as e:
        rec = {"na": f"needs {e}"}
    except Exception as e:  # reported in the cell, the run goes on
        traceback.print_exc()
        first = (str(e).strip().splitlines() or [""])[0]
        rec = {"failed": f"{type(e).__name__}: {first}"[:300]}
    # wall_s: the whole cell, compilation and references included (where a run's time goes)
    rec = {
        "time": None,
        "error": None,
        "unit": "s",
        "extra": {},
        **rec,
        "what": CELLS[name][1],
        "wall_s": time.perf_counter() - start,
    }
    results[name] = rec
    shown = "n/a" if "na" in rec else "FAILED" if "failed" in rec else f"{rec['time']:.4g} s"
    print(
        f"    {shown}"
        + ("" if rec["error"] is None else f", error {rec['error']:.3g}")
        + f" (cell {rec['wall_s']:.1f} s)",
        flush=True,
    )


# --- the groups -------------------------------------------------------------------
#
# Each builds its batch once and runs its wanted cells through `run_cell`.


class Run:
    """What the groups share: sizes, timing settings, the wanted cells, the results."""

    def __init__(self, quick: bool, want):
        self.quick, self.want, self.results = quick, set(want), {}
        self.repeats, self.min_time = (1, 0.0) if quick else (5, 0.5)

    def timed(self, f, *args):
        """``(output, median seconds)`` after a warm-up call."""
        out, seconds, _ = common.timed(f, *args, repeats=self.repeats, min_time=self.min_time)
        return out, seconds

    def cell(self, name, fn):
        run_cell(self.results, name, fn, self.want)


def tee(n: int):
    """``(inertia (3, 3), omega0 (n, 3) rad/s, intermediate axis index)``."""
    import numpy as np

    import lierk

    inertia = np.asarray(lierk.inertia.tee_handle())
    w, axis = common.near_axis(np.diag(inertia), n)
    return inertia, w, axis


HEAVY = dict(moments=(0.6, 0.8, 0.3), chi=(0.02, 0.01, 0.5), mass=1.0, g=9.81)


def heavy_tops(n: int):
    """``(omega0 (n, 3) rad/s, R0 (n, 3, 3))``: `torqued.py`'s asymmetric
    family, spin U(30, 120) rad/s, tilted 0.3 rad about a random horizontal axis."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    w = np.stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(30, 120, n)], axis=1)
    phi = rng.uniform(0, 2 * np.pi, n)
    R0 = Rotation.from_rotvec(0.3 * np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], axis=1)).as_matrix()
    return w, R0


def heavy_top(lierk, w, R0):
    import numpy as np

    return lierk.RigidBodyWithEffects(
        np.asarray(HEAVY["moments"]),
        w,
        R0,
        effects=(lierk.Gravity(np.asarray(HEAVY["chi"]), HEAVY["mass"], HEAVY["g"]),),
    )


def final_R(problem_of, solver, T: float, control: dict, event=None):
    """``f(w, R0) -> R(T)`` (and the first time of ``event(problem)``, if
    given) of one body."""
    import lierk

    def f(w, R0=None):
        problem = problem_of(w, R0)
        kw = dict(control)
        if event is not None:
            kw["event"] = event(problem)
        sol = lierk.solve(problem, solver, T, throw=False, **kw)
        return sol.R[-1] if event is None else (sol.R[-1], sol.events.ts[0])

    return f


def control(T: float, dt=None, rtol=None) -> dict:
    """`lierk.solve`'s keywords: ``dt`` and its step count, or ``rtol = atol``
    (and lierk's default ``max_steps``)."""
    if dt is not None:
        return dict(dt=dt, max_steps=math.ceil(round(T / dt, 9)))
    return dict(rtol=rtol, atol=rtol)


def free_group(run: Run) -> None:
    """``free_*`` and ``events_*``."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import lierk

    N, T = (4, 4.0) if run.quick else (256, 10.0)
    inertia, W, axis = tee(N)
    W = jnp.asarray(W)
    settings = {
        "rkmk4": (lambda: lierk.RKMK4(), control(T, dt=0.01)),
        "dop853": (lambda: lierk.DOP853(), control(T, rtol=1e-10)),
    }
    body = lambda w, R0=None: lierk.FreeRigidBody(inertia, w)  # noqa: E731

    def reference():
        if "R" not in ref:
            need(lierk, "exact.free_rigid_body")
            ref["R"] = np.asarray(jax.jit(jax.vmap(lambda w: lierk.exact.free_rigid_body(inertia, w, T)[0]))(W))
        return ref["R"]

    def crossings():
        """The first zero of the exact momentum along the intermediate
        axis (s), ``inf`` where there is none before ``T``: a grid of ``G``
        points over ``[0, T]`` brackets it, then ``G`` points over each
        bracket, three times more (bracket ``T / (G - 1)^4``)."""
        if "t" not in ref:
            need(lierk, "exact.free_rigid_body")
            G = 1001
            m2 = jax.jit(
                jax.vmap(jax.vmap(lambda w, t: lierk.exact.free_rigid_body(inertia, w, t)[1][axis], in_axes=(None, 0)))
            )
            lo, hi = np.zeros(N), np.full(N, T)
            found = np.ones(N, bool)
            for it in range(4):
                ts = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, G)
                v = np.asarray(m2(W, jnp.asarray(ts)))
                change = np.sign(v[:, 1:]) != np.sign(v[:, :1])
                if it == 0:
                    found = change.any(axis=1)
                k = np.where(found, np.argmax(change, axis=1), 0)
                lo, hi = ts[np.arange(N), k], ts[np.arange(N), k + 1]
            ref["t"] = np.where(found, 0.5 * (lo + hi), np.inf)
        return ref["t"]

    ref = {}
    for key, (make, ctrl) in settings.items():

        def measure(make=make, ctrl=ctrl):
            need(lierk, "solve", "FreeRigidBody", "RKMK4", "DOP853")
            R, seconds = run.timed(jax.jit(jax.vmap(final_R(body, make(), T, ctrl))), W)
            return {"time": seconds, "error": common.max_err(R, reference())}

        def events(make=make, ctrl=ctrl):
            need(lierk, "solve(event)", "conditions.flip")
            flip = lambda problem: lierk.conditions.flip(problem, max_count=4)  # noqa: E731
            (_, t_event), seconds = run.timed(jax.jit(jax.vmap(final_R(body, make(), T, ctrl, event=flip))), W)
            t_event, t_ref = np.asarray(t_event), crossings()
            both = np.isfinite(t_ref) & np.isfinite(t_event)
            agree = np.isfinite(t_ref) == np.isfinite(t_event)
            gap = np.abs(np.where(both, t_event, 0.0) - np.where(both, t_ref, 0.0))
            error = float(np.max(gap)) if agree.all() else float("inf")
            return {"time": seconds, "error": error, "extra": {"flips before T": int(both.sum())}}

        run.cell(f"free_{key}", measure)
        run.cell(f"events_{key}_flip", events)
    for key in settings:
        with_event, without = run.results.get(f"events_{key}_flip"), run.results.get(f"free_{key}")
        if with_event and without and with_event["time"] and without["time"]:
            with_event["extra"]["/ without the event"] = with_event["time"] / without["time"]


def top_group(run: Run) -> None:
    """``top_*``."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    import peers

    import lierk

    N, T = (4, 0.1) if run.quick else (128, 2.0)
    W, R0 = (jnp.asarray(x) for x in heavy_tops(N))
    ref = {}

    def reference():
        if "R" not in ref:
            torque = peers.gravity_torque(HEAVY["mass"], HEAVY["g"], HEAVY["chi"])
            field = peers.rigid_body_field(HEAVY["moments"], torque)

            def one(w, R):
                y0 = peers.initial_state(HEAVY["moments"], w, R)
                return peers.diffrax_solve(field, "Dopri8", T, y0, rtol=1e-13, max_steps=200_000)[0]

            ref["R"] = np.asarray(jax.jit(jax.vmap(one))(W, R0))
        return ref["R"]

    for key, make, ctrl in [
        ("dop853", lambda: lierk.DOP853(), control(T, rtol=1e-8)),
        ("rkmk_dop853", lambda: lierk.RKMK(lierk.tableaux.DOP853), control(T, dt=5e-3)),
    ]:

        def measure(make=make, ctrl=ctrl):
            need(lierk, "solve", "RigidBodyWithEffects", "Gravity", "DOP853", "RKMK", "tableaux.DOP853")
            f = final_R(lambda w, R: heavy_top(lierk, w, R), make(), T, ctrl)
            R, seconds = run.timed(jax.jit(jax.vmap(f)), W, R0)
            return {"time": seconds, "error": common.max_err(R, reference())}

        run.cell(f"top_{key}", measure)


def relative_error(J, J_ref) -> float:
    """The largest ``||J - J_ref||_F / ||J_ref||_F`` over the batch (leading axis)."""
    import numpy as np

    J, J_ref = np.asarray(J).reshape(len(J_ref), -1), np.asarray(J_ref).reshape(len(J_ref), -1)
    return float(np.max(np.linalg.norm(J - J_ref, axis=1) / np.linalg.norm(J_ref, axis=1)))


def jac_group(run: Run) -> None:
    """``jac_rkmk_dop853_*`` and ``jac_dop853_*``."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import lierk

    N, T, n_outer = (4, 1.0, 2) if run.quick else (128, 10.0, 16)
    inertia, W, _ = tee(N)
    W = jnp.asarray(W)
    body = lambda w, R0=None: lierk.FreeRigidBody(inertia, w)  # noqa: E731
    ref = {}

    def reference():
        if "J" not in ref:
            need(lierk, "exact.free_rigid_body")
            exact_R = lambda v: lierk.exact.free_rigid_body(inertia, v, T)[0]  # noqa: E731
            ref["J"] = np.asarray(jax.jit(jax.vmap(jax.jacfwd(exact_R)))(W))
        return ref["J"]

    for key, make, ctrl in [
        ("rkmk_dop853", lambda: lierk.RKMK(lierk.tableaux.DOP853), control(T, dt=0.1)),
        ("dop853", lambda: lierk.DOP853(), control(T, rtol=1e-8)),
    ]:
        base = f"jac_{key}"

        def solver(make=make):
            need(lierk, "solve", "FreeRigidBody", "RKMK", "tableaux.DOP853", "DOP853")
            return make()

        def forward(ctrl=ctrl):
            _, seconds = run.timed(jax.jit(jax.vmap(final_R(body, solver(), T, ctrl))), W)
            return {"time": seconds}

        def jacfwd(ctrl=ctrl):
            J, seconds = run.timed(jax.jit(jax.vmap(jax.jacfwd(final_R(body, solver(), T, ctrl)))), W)
            return {"time": seconds, "error": relative_error(J, reference())}

        def variational(ctrl=ctrl):
            need(lierk, "sensitivity(method)", "sensitivity(estimate_error)")
            s = solver()

            def one(w):
                return lierk.sensitivity(
                    body(w), s, T, method="variational", estimate_error=False, throw=False, **ctrl
                ).jacobian_R

            J, seconds = run.timed(jax.jit(jax.vmap(one)), W)
            return {"time": seconds, "error": relative_error(J, reference())}

        def jacfwd_of_vmap(ctrl=ctrl):
            J, seconds = run.timed(jax.jit(jax.jacfwd(jax.vmap(final_R(body, solver(), T, ctrl)))), W[:n_outer])
            idx = np.arange(n_outer)
            blocks = np.asarray(J)[idx, :, :, idx, :]  # (n, 3, 3, 3): each body's own block
            return {"time": seconds, "error": relative_error(blocks, reference()[:n_outer])}

        run.cell(f"{base}_forward", forward)
        run.cell(f"{base}_jacfwd", jacfwd)
        run.cell(f"{base}_variational", variational)
        run.cell(f"{base}_jacfwd_of_vmap", jacfwd_of_vmap)
        fwd = run.results.get(f"{base}_forward")
        if fwd and fwd["time"]:
            for how, per in [("jacfwd", 1.0), ("variational", 1.0), ("jacfwd_of_vmap", N / n_outer)]:
                rec = run.results.get(f"{base}_{how}")
                if rec and rec["time"]:
                    rec["extra"]["/ forward" + (" per body" if per != 1.0 else "")] = rec["time"] * per / fwd["time"]


def jac_top_group(run: Run) -> None:
    """``jac_top_*``."""
    import jax
    import jax.numpy as jnp

    import lierk

    N, T = (4, 0.1) if run.quick else (64, 0.5)
    W, R0 = (jnp.asarray(x) for x in heavy_tops(N))

    def f():
        need(lierk, "solve", "RigidBodyWithEffects", "Gravity", "DOP853")
        return final_R(lambda w, R: heavy_top(lierk, w, R), lierk.DOP853(), T, control(T, rtol=1e-8))

    run.cell("jac_top_dop853_forward", lambda: {"time": run.timed(jax.jit(jax.vmap(f())), W, R0)[1]})
    run.cell("jac_top_dop853_jacfwd", lambda: {"time": run.timed(jax.jit(jax.vmap(jax.jacfwd(f()))), W, R0)[1]})
    fwd, jac = run.results.get("jac_top_dop853_forward"), run.results.get("jac_top_dop853_jacfwd")
    if fwd and jac and fwd["time"] and jac["time"]:
        jac["extra"]["/ forward"] = jac["time"] / fwd["time"]


def first_group(run: Run, xla_flags: str | None) -> None:
    """``first_*``: `first_result`'s own cells, each in a fresh process
    (which drops the persistent-cache settings from its environment)."""
    import first_result

    def fresh(work):
        def measure():
            saved = os.environ.get("XLA_FLAGS")
            # first_result's children run on one device, as in its own runs
            if xla_flags is None:
                os.environ.pop("XLA_FLAGS", None)
            else:
                os.environ["XLA_FLAGS"] = xla_flags
            try:
                out = first_result._fresh(dict(body="top", solver="DOP853", work=work, peer="lierk", compact=None))
            finally:
                if saved is not None:
                    os.environ["XLA_FLAGS"] = saved
            return {"time": out["first"], "extra": {"trace s": out["trace"], "compile s": out["compile"]}}

        return measure

    run.cell("first_solve", fresh("solve"))
    run.cell("first_jacfwd", fresh("jacfwd"))


def sweep_group(run: Run) -> None:
    """``sweep_*``."""
    import jax
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    import lierk

    N, steps, dt = (64, 10, 0.01) if run.quick else (10_000, 1000, 0.01)
    inertia, W, _ = tee(N)

    def one(w):
        need(lierk, "solve", "FreeRigidBody", "RKMK4")
        return final_R(
            lambda w, R0=None: lierk.FreeRigidBody(inertia, w), lierk.RKMK4(), steps * dt, control(steps * dt, dt=dt)
        )(w)

    def held():
        sharding = NamedSharding(Mesh(np.array(jax.devices()), ("batch",)), PartitionSpec("batch"))
        _, seconds = run.timed(jax.jit(jax.vmap(one)), jax.device_put(W, sharding))
        return {"time": seconds, "extra": {"body-steps/s": N * steps / seconds}}

    def sweep():
        need(lierk, "sweep")
        _, seconds = run.timed(lambda w: lierk.sweep(one, w), W)
        return {"time": seconds, "extra": {"body-steps/s": N * steps / seconds}}

    run.cell("sweep_jit_vmap", held)
    run.cell("sweep_lierk_sweep", sweep)


GROUPS = {
    "first": None,
    "free": free_group,
    "top": top_group,
    "jac": jac_group,
    "jac_top": jac_top_group,
    "sweep": sweep_group,
}


def raising(error: Exception):
    """A cell function that raises ``error`` (its group's setup failed)."""

    def fn():
        raise error

    return fn


def measure(quick: bool, want, xla_flags: str | None) -> dict:
    """Run the wanted cells (jax already configured); the results by cell, in `CELLS` order."""
    run = Run(quick, want)
    for group, fn in GROUPS.items():
        if not any(CELLS[name][0] == group for name in run.want):
            continue
        print(f"{group}:", flush=True)
        try:
            first_group(run, xla_flags) if fn is None else fn(run)
        except Exception as e:  # the group's setup failed; its cells say so
            for name in run.want:
                if CELLS[name][0] == group and name not in run.results:
                    run_cell(run.results, name, raising(e), run.want)
    return {name: run.results[name] for name in CELLS if name in run.results}


def markdown(results: dict) -> list[str]:
    meta = results["_meta"]
    lines = [
        "# Headline cells (`benchmarks/headline.py`)",
        "",
        f"{meta['machine']['cpu_count']} cores ({meta['machine']['cpu']}), "
        f"{common.backend_text(meta['machine'])}, jax {meta['machine']['jax']}; lierk from {meta['lierk_commit']}. "
        "Median wall time after compilation and a warm-up call; the first_* cells are one fresh process each.",
        "",
        "| cell | what | time | error | more |",
        "|---|---|---:|---:|---|",
    ]
    for name, rec in results.items():
        if name == "_meta":
            continue
        shown = "n/a" if "na" in rec else "failed" if "failed" in rec else common.format_seconds(rec["time"])
        error = "" if rec["error"] is None else f"{rec['error']:.2e}"
        more = ", ".join(f"{k} {v:.3g}" for k, v in rec["extra"].items()) or rec.get("na", rec.get("failed", ""))
        lines.append(f"| {name} | {rec['what']} | {shown} | {error} | {more} |")
    return lines


def main(argv=None) -> int:
    def extra(parser):
        parser.add_argument("--json", default=None, help="write the cells' JSON to this file (nothing else is written)")
        parser.add_argument(
            "--cells",
            nargs="*",
            default=None,
            metavar="NAME",
            help=f"cells or prefixes of cells (default: all): {', '.join(CELLS)}",
        )

    quick, out, args = common.cli(
        __doc__, "tiny sizes (4 bodies, short times) to check the script works", extra=extra, argv=argv
    )
    want = select(args.cells)
    xla_flags = os.environ.get("XLA_FLAGS")
    import host_devices

    host_devices.split()  # one XLA host device per core, before jax starts
    import jax

    jax.config.update("jax_enable_x64", True)
    import lierk

    print(f"lierk from {lierk.__file__}", flush=True)
    results = measure(quick, want, xla_flags)
    results["_meta"] = {
        "machine": common.machine_info(),
        "lierk": str(Path(lierk.__file__).resolve().parent),
        "lierk_commit": common.git_commit(Path(lierk.__file__).resolve().parent.parent),
        "quick": quick,
        "cells": want,
    }
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float) + "\n")
        print(f"wrote {args.json}")
    else:
        common.write_results(out, "headline", results, markdown(results))
    return 1 if any("failed" in rec for name, rec in results.items() if name != "_meta") else 0


if __name__ == "__main__":
    sys.exit(main())
