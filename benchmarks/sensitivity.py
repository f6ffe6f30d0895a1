"""Sensitivity work-precision: the Jacobian of R(T) with respect to omega0, lierk against diffrax.

Problems (float64, both cores: one XLA host device per core, half the batch each):

- ``tee``: 256 T-handles (``lierk.inertia.tee_handle()``) near the
  intermediate axis, |omega| in [1, 3] rad/s, ``T = 10`` s (the batch of
  ``common.near_axis``).  Reference: `jax.jacfwd` of the closed form
  `lierk.exact.free_rigid_body`.
- ``top``: 64 asymmetric heavy tops (``benchmarks/torqued.py``'s family:
  I = diag(0.6, 0.8, 0.3), g = 9.81, spin 30 to 120 rad/s, tilt 0.3 rad),
  ``T = 0.5`` s.  Reference: lierk ``RKMK(DOP853)`` at dt = 1/16000 s, checked
  against diffrax ``Dopri8`` at rtol = atol = 1e-13 (their largest
  disagreement is recorded).

Error = the largest ``||J - J_ref||_F / ||J_ref||_F`` over the batch, with
``J = dR(T)/d omega0`` ``(3, 3, 3)``.

Programs:

- lierk forward mode (`lierk.sensitivity`, which is `jax.jacfwd` through
  `lierk.solve`): ``RKMK4`` and ``RKMK(DOP853)`` at fixed steps, ``DOP853``
  adaptive (`ForwardMode`); the same with ``method="variational"`` (the
  variational equations integrated with the body, "(variational)"); reverse mode (`jax.jacrev`, default adjoint,
  `ForwardSensitivity`) for a few of the same settings; the gradient of a
  scalar loss ``sum(W * R(T))`` (`jax.grad`) with the default adjoint and
  with reverse mode through the loop (``adjoint=RecursiveCheckpointAdjoint()``:
  the checkpointed while loop, or for fixed steps the scan's own reverse
  mode).  Each setting's forward solve is timed too, for the ratio "Jacobian
  / forward solve".
- diffrax ``Dopri8`` and ``Tsit5`` (PID controller, rtol = atol = tol) on the
  9-component ODE (tee) or the 12-component one (top), with
  ``diffrax.ForwardMode`` (`jax.jacfwd`) and ``RecursiveCheckpointAdjoint``
  (`jax.jacrev`, and `jax.grad` of the same loss).
- Reverse-mode memory of a fixed-step gradient at 10^4, 10^5 and 10^6 steps
  (one body, RKMK4), with both adjoints: XLA's compiled temporary buffers,
  and the time of one gradient.

Compilation and a warm-up call are excluded; the median of at least 3 calls,
more until they add up to 0.25 s.  Writes benchmarks/results/sensitivity.{json,md,png}.
Run: ``python benchmarks/sensitivity.py`` (over an hour on 2 idle cores, mostly compiling; results are
written after each part);
``--quick`` checks that it works (tiny batches, two settings each).
"""

from __future__ import annotations

import host_devices

host_devices.split()  # one XLA host device per core


import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import peers  # noqa: E402
from common import backend_text, cli, interp_time, machine_info, near_axis, timed, write_results  # noqa: E402
from jax.sharding import Mesh, PartitionSpec  # noqa: E402

import lierk  # noqa: E402

QUICK, OUT = cli(__doc__, "tiny run (8 bodies, two settings each) to check the script works", __name__ == "__main__")

REPEATS = 1 if QUICK else 3
MIN_TIME = 0.0 if QUICK else 0.25
LEVELS = [10.0**-k for k in range(3, 10)]
MESH = Mesh(np.array(jax.devices()), ("batch",))
MAX_STEPS = 4096  # lierk's default for adaptive solves (its reverse-mode record is 8 bytes a step per member)


def pick(values):
    """All settings, or with --quick the coarsest and the finest."""
    return list(values) if not QUICK else [values[0], values[-1]]


def on_devices(one):
    """``one(omega0, R0) -> outputs`` for one body, as a jitted function of the
    batch, half of it on each device.  Reverse mode through equinox's
    checkpointed while loop (adaptive solves, lierk's and diffrax's) fails to
    trace under `jax.shard_map` ("Closure-converted function called with
    different dynamic arguments"): those programs run vmapped on one device,
    and their records say so (``devices``)."""
    spec = PartitionSpec("batch")
    sharded = jax.jit(jax.shard_map(jax.vmap(one), mesh=MESH, in_specs=(spec, spec), out_specs=spec, check_vma=False))
    single = jax.jit(jax.vmap(one))

    def run(W, R0):
        if run.devices == len(MESH.devices.flat):
            try:
                return sharded(W, R0)
            except ValueError as e:
                if "Closure-converted" not in str(e):
                    raise
                run.devices = 1
        return single(W, R0)

    run.devices = len(MESH.devices.flat)
    return run


# --- problems -------------------------------------------------------------------


class Tee:
    name, title = "tee", "T-handle near the intermediate axis, T = 10 s"
    N, T = (8, 2.0) if QUICK else (256, 10.0)
    inertia = np.asarray(lierk.inertia.tee_handle())
    moments = np.diag(inertia)
    rk4_dts = pick([0.04, 0.02, 0.01, 0.005, 0.0025])
    dop_dts = pick([0.2, 0.1, 0.05, 0.025])
    tols = pick([1e-4, 1e-6, 1e-8, 1e-10, 1e-12])
    effects = ()

    def initial(self):
        w, _ = near_axis(self.moments, self.N)
        return w, np.broadcast_to(np.eye(3), (self.N, 3, 3)).copy()

    def problem(self, w, R0):
        return lierk.FreeRigidBody(self.inertia, w, R0)

    # diffrax's 9-component ODE ``X' = X hat(I^-1 X^T L)``, ``args = L``
    field = staticmethod(peers.free_body_field(inertia))

    def peer_state(self, w, R0):
        return peers.free_body_state(self.inertia, w, R0)

    def reference(self, W, R0):
        f = jax.jit(
            jax.vmap(lambda w, R: jax.jacfwd(lambda v: lierk.exact.free_rigid_body(self.inertia, v, self.T, R)[0])(w))
        )
        return np.asarray(f(W, R0)), {"reference": "jax.jacfwd of lierk.exact.free_rigid_body"}


class Top:
    name, title = "top", "asymmetric heavy top, spin 30-120 rad/s, T = 0.5 s"
    N, T = (8, 0.1) if QUICK else (64, 0.5)
    moments = np.array([0.6, 0.8, 0.3])
    inertia = np.diag(moments)
    chi, mass, g = np.array([0.02, 0.01, 0.5]), 1.0, 9.81
    rk4_dts = pick([4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4])
    dop_dts = pick([2e-2, 1e-2, 5e-3, 2.5e-3, 1.25e-3])
    tols = pick([1e-4, 1e-6, 1e-8, 1e-10, 1e-12])
    effects = (lierk.Gravity(jnp.asarray(chi), mass, g),)

    def initial(self):
        rng = np.random.default_rng(0)
        w = np.stack([rng.uniform(-2, 2, self.N), rng.uniform(-2, 2, self.N), rng.uniform(30, 120, self.N)], 1)
        phi = rng.uniform(0, 2 * np.pi, self.N)
        axes = 0.3 * np.stack([np.cos(phi), np.sin(phi), np.zeros(self.N)], 1)
        return w, np.asarray(jax.vmap(lierk.so3.exp)(jnp.asarray(axes)))

    def problem(self, w, R0):
        return lierk.RigidBodyWithEffects(self.moments, w, R0, effects=self.effects)

    # diffrax's 12-component ODE, ``y = (m, R row-major)``
    field = staticmethod(peers.rigid_body_field(moments, peers.gravity_torque(mass, g, chi)))

    def peer_state(self, w, R0):
        return peers.initial_state(self.moments, w, R0), None

    def reference(self, W, R0):
        ref = lierk_jacobian(self, lierk.RKMK(lierk.tableaux.DOP853), dict(dt=self.T / (8 if QUICK else 8000)))
        J, _ = ref(W, R0)
        J_peer, _ = diffrax_jacobian(self, "Dopri8", 1e-13, "forward")(W, R0)
        check = relative_error(np.asarray(J_peer), np.asarray(J))
        return np.asarray(J), {
            "reference": "lierk RKMK(DOP853) at dt = T/8000, jax.jacfwd",
            "reference_vs_diffrax_Dopri8_1e-13": check,
        }


# --- programs -------------------------------------------------------------------


def relative_error(J, J_ref) -> float:
    num = np.sqrt(np.sum((np.asarray(J) - J_ref) ** 2, axis=(1, 2, 3)))
    return float(np.max(num / np.sqrt(np.sum(J_ref**2, axis=(1, 2, 3)))))


def solve_options(fam, kw):
    kw = dict(kw)
    if "dt" in kw:
        kw["max_steps"] = lierk.num_steps(0.0, fam.T, kw["dt"])
    else:
        kw["max_steps"] = MAX_STEPS
    return kw


def lierk_jacobian(fam, solver, kw, mode="forward", method="derivative"):
    kw = solve_options(fam, kw)

    def one(w, R0):
        s = lierk.sensitivity(
            fam.problem(w, R0), solver, fam.T, mode=mode, method=method, estimate_error=False, throw=False, **kw
        )
        return s.jacobian_R, s.stats["num_steps"]

    return on_devices(one)


# The scalar loss of the gradient rows: sum(LOSS_WEIGHTS * R(T)), so its
# gradient is the Jacobian contracted with these weights.
LOSS_WEIGHTS = np.asarray(np.random.default_rng(1).normal(size=(3, 3)))


def lierk_gradient(fam, solver, kw, adjoint=None):
    kw = solve_options(fam, kw)

    def one(w, R0):
        def loss(v):
            sol = lierk.solve(fam.problem(v, R0), solver, fam.T, throw=False, adjoint=adjoint, **kw)
            return jnp.sum(LOSS_WEIGHTS * sol.R[-1]), sol.stats["num_steps"]

        return jax.grad(loss, has_aux=True)(w)

    return on_devices(one)


def lierk_forward(fam, solver, kw):
    kw = solve_options(fam, kw)

    def one(w, R0):
        return lierk.solve(fam.problem(w, R0), solver, fam.T, throw=False, **kw).R[-1]

    return on_devices(one)


def diffrax_run(fam, solver, tol, w, R0, forward_mode=False):
    """``(R(T), steps)`` of diffrax's adaptive solve of ``fam``'s peer ODE."""
    y0, args = fam.peer_state(w, R0)
    return peers.diffrax_solve(
        fam.field, solver, fam.T, y0, rtol=tol, max_steps=MAX_STEPS, forward_mode=forward_mode, args=args
    )[:2]


def diffrax_jacobian(fam, solver, tol, mode):
    """Forward mode: ``jax.jacfwd`` with diffrax's ``ForwardMode``; else
    ``jax.jacrev`` through its default ``RecursiveCheckpointAdjoint``."""
    forward = mode == "forward"
    jac = jax.jacfwd if forward else jax.jacrev

    def one(w, R0):
        J, (_, steps) = jac(
            lambda v: (lambda out: (out[0], out))(diffrax_run(fam, solver, tol, v, R0, forward)), has_aux=True
        )(w)
        return J, steps

    return on_devices(one)


def diffrax_gradient(fam, solver, tol):
    def one(w, R0):
        def loss(v):
            R, steps = diffrax_run(fam, solver, tol, v, R0)
            return jnp.sum(LOSS_WEIGHTS * R), steps

        return jax.grad(loss, has_aux=True)(w)

    return on_devices(one)


def diffrax_forward(fam, solver, tol):
    return on_devices(lambda w, R0: diffrax_run(fam, solver, tol, w, R0)[0])


def run_family(fam) -> dict:
    W, R0 = fam.initial()
    W, R0 = jnp.asarray(W), jnp.asarray(R0)
    J_ref, ref_info = fam.reference(W, R0)
    g_ref = np.einsum("ij,bijk->bk", LOSS_WEIGHTS, J_ref)
    records = []

    def add(method, mode, setting, jac_fn, fwd_fn):
        (J, steps), t_jac, first = timed(jac_fn, W, R0, repeats=REPEATS, min_time=MIN_TIME)
        _, t_fwd, _ = timed(fwd_fn, W, R0, repeats=REPEATS, min_time=MIN_TIME)
        if mode == "gradient":
            err = float(np.max(np.linalg.norm(np.asarray(J) - g_ref, axis=1) / np.linalg.norm(g_ref, axis=1)))
        else:
            err = relative_error(J, J_ref)
        rec = dict(
            method=method,
            mode=mode,
            setting=setting,
            error=err,
            time_s=t_jac,
            forward_s=t_fwd,
            ratio_to_forward=t_jac / t_fwd,
            compile_s=first - t_jac,
            mean_steps=float(np.mean(steps)),
            devices=jac_fn.devices,
        )
        records.append(rec)
        print(
            f"  {fam.name:4s} {method:22s} {mode:8s} {setting:>10s}: error {rec['error']:.2e}  Jacobian {t_jac:.4f} s"
            f"  forward {t_fwd:.4f} s  ({rec['ratio_to_forward']:.1f}x, {rec['devices']} device(s))",
            flush=True,
        )

    dop = lierk.RKMK(lierk.tableaux.DOP853)
    for dt in fam.rk4_dts:
        add(
            "lierk RKMK4",
            "forward",
            f"dt={dt:g}",
            lierk_jacobian(fam, lierk.RKMK4(), dict(dt=dt)),
            lierk_forward(fam, lierk.RKMK4(), dict(dt=dt)),
        )
    for dt in fam.dop_dts:
        add(
            "lierk RKMK(DOP853)",
            "forward",
            f"dt={dt:g}",
            lierk_jacobian(fam, dop, dict(dt=dt)),
            lierk_forward(fam, dop, dict(dt=dt)),
        )
    for tol in fam.tols:
        kw = dict(rtol=tol, atol=tol)
        add(
            "lierk DOP853",
            "forward",
            f"tol={tol:g}",
            lierk_jacobian(fam, lierk.DOP853(), kw),
            lierk_forward(fam, lierk.DOP853(), kw),
        )
    # The variational equations integrated with the body (method="variational").
    for dt in fam.rk4_dts:
        add(
            "lierk RKMK4 (variational)",
            "forward",
            f"dt={dt:g}",
            lierk_jacobian(fam, lierk.RKMK4(), dict(dt=dt), method="variational"),
            lierk_forward(fam, lierk.RKMK4(), dict(dt=dt)),
        )
    for dt in fam.dop_dts:
        add(
            "lierk RKMK(DOP853) (variational)",
            "forward",
            f"dt={dt:g}",
            lierk_jacobian(fam, dop, dict(dt=dt), method="variational"),
            lierk_forward(fam, dop, dict(dt=dt)),
        )
    for tol in fam.tols:
        kw = dict(rtol=tol, atol=tol)
        add(
            "lierk DOP853 (variational)",
            "forward",
            f"tol={tol:g}",
            lierk_jacobian(fam, lierk.DOP853(), kw, method="variational"),
            lierk_forward(fam, lierk.DOP853(), kw),
        )
    # Reverse mode at two settings of each kind: its cost relative to the forward solve.
    for dt in fam.rk4_dts[1::2][:2]:
        add(
            "lierk RKMK4",
            "reverse",
            f"dt={dt:g}",
            lierk_jacobian(fam, lierk.RKMK4(), dict(dt=dt), "reverse"),
            lierk_forward(fam, lierk.RKMK4(), dict(dt=dt)),
        )
    for tol in fam.tols[1::2][:2]:
        kw = dict(rtol=tol, atol=tol)
        add(
            "lierk DOP853",
            "reverse",
            f"tol={tol:g}",
            lierk_jacobian(fam, lierk.DOP853(), kw, "reverse"),
            lierk_forward(fam, lierk.DOP853(), kw),
        )
    # The gradient of a scalar loss of R(T) (reverse mode): the default adjoint
    # (ForwardSensitivity) and, for fixed steps, reverse mode through the scan.
    for dt in fam.rk4_dts[1::2][:2]:
        add(
            "lierk RKMK4",
            "gradient",
            f"dt={dt:g}",
            lierk_gradient(fam, lierk.RKMK4(), dict(dt=dt)),
            lierk_forward(fam, lierk.RKMK4(), dict(dt=dt)),
        )
        add(
            "lierk RKMK4 (scan reverse)",
            "gradient",
            f"dt={dt:g}",
            lierk_gradient(fam, lierk.RKMK4(), dict(dt=dt), lierk.RecursiveCheckpointAdjoint()),
            lierk_forward(fam, lierk.RKMK4(), dict(dt=dt)),
        )
    for dt in fam.dop_dts[1::2][:2]:
        add(
            "lierk RKMK(DOP853)",
            "gradient",
            f"dt={dt:g}",
            lierk_gradient(fam, dop, dict(dt=dt)),
            lierk_forward(fam, dop, dict(dt=dt)),
        )
    for tol in fam.tols[1::2][:2]:
        kw = dict(rtol=tol, atol=tol)
        add(
            "lierk DOP853",
            "gradient",
            f"tol={tol:g}",
            lierk_gradient(fam, lierk.DOP853(), kw),
            lierk_forward(fam, lierk.DOP853(), kw),
        )
        add(
            "lierk DOP853 (checkpointed)",
            "gradient",
            f"tol={tol:g}",
            lierk_gradient(fam, lierk.DOP853(), kw, lierk.RecursiveCheckpointAdjoint()),
            lierk_forward(fam, lierk.DOP853(), kw),
        )
    for solver in (diffrax.Dopri8(), diffrax.Tsit5()):
        for mode in ("forward", "reverse", "gradient"):
            name = f"diffrax {type(solver).__name__}"
            for tol in fam.tols if mode == "forward" else fam.tols[1::2][:2]:
                prog = (
                    diffrax_gradient(fam, solver, tol)
                    if mode == "gradient"
                    else diffrax_jacobian(fam, solver, tol, mode)
                )
                add(name, mode, f"tol={tol:g}", prog, diffrax_forward(fam, solver, tol))

    levels = []
    jacobians = [r for r in records if r["mode"] != "gradient"]
    groups = {
        "lierk": lambda r: r["method"].startswith("lierk"),
        # The derivative of the solve only (method="derivative"), as before
        # the variational equations were measured.
        "lierk_derivative": lambda r: r["method"].startswith("lierk") and "variational" not in r["method"],
        "diffrax": lambda r: r["method"].startswith("diffrax"),
    }
    for level in LEVELS:
        best = {}
        for prog, member in groups.items():
            t = interp_time([(r["error"], r["time_s"]) for r in jacobians if member(r)], level)
            best[prog] = None if t is None else t[0]
        # Which lierk program is the cheapest there, by its own front.
        own = {}
        for method in dict.fromkeys(r["method"] for r in jacobians if groups["lierk"](r)):
            t = interp_time([(r["error"], r["time_s"]) for r in jacobians if r["method"] == method], level)
            if t is not None:
                own[method] = t[0]

        def ratio(a):
            return None if best[a] is None or best["diffrax"] is None else best[a] / best["diffrax"]

        levels.append(
            dict(
                level=level,
                lierk_s=best["lierk"],
                diffrax_s=best["diffrax"],
                ratio=ratio("lierk"),
                lierk_derivative_s=best["lierk_derivative"],
                ratio_derivative=ratio("lierk_derivative"),
                lierk_cheapest=min(own, key=own.get) if own else None,
            )
        )
    return dict(title=fam.title, N=fam.N, T=fam.T, **ref_info, records=records, levels=levels)


def reverse_memory() -> list[dict]:
    """Compiled temporaries and time of one fixed-step gradient (RKMK4, one
    body): the default adjoint (forward sensitivities) and reverse mode
    through the scan (blocks of sqrt(n) steps recomputed)."""
    body = lierk.FreeRigidBody([1.0, 2.0, 3.0], [0.3, 1.0, 0.2])
    out = []
    for n in [10**3, 10**4] if QUICK else [10**4, 10**5, 10**6]:
        for name, adjoint in (
            ("ForwardSensitivity (default)", None),
            ("scan reverse", lierk.RecursiveCheckpointAdjoint()),
        ):

            def loss(w, n=n, adjoint=adjoint):
                return lierk.solve(body.with_omega0(w), lierk.RKMK4(), n * 1e-3, dt=1e-3, adjoint=adjoint).R[-1][0, 1]

            w = jnp.array([0.3, 1.0, 0.2])
            grad = jax.jit(jax.grad(loss)).lower(w).compile()
            fwd = jax.jit(loss).lower(w).compile()
            _, t_grad, _ = timed(grad, w, repeats=REPEATS)
            _, t_fwd, _ = timed(fwd, w, repeats=REPEATS)
            mem = grad.memory_analysis()
            out.append(
                dict(steps=n, adjoint=name, temp_bytes=int(mem.temp_size_in_bytes), gradient_s=t_grad, forward_s=t_fwd)
            )
            print(
                f"  reverse memory: {n:8d} steps, {name}: {mem.temp_size_in_bytes / 1e6:.3f} MB temporaries, "
                f"gradient {t_grad:.3f} s, forward {t_fwd:.3f} s",
                flush=True,
            )
    return out


def reversibility() -> list[dict]:
    """Would a reversible adjoint (states rebuilt by stepping back with -h,
    O(1) memory) be right?  Accuracy only, no timing: run a splitting n steps
    forward, then n steps back from the end, and compare each rebuilt state
    with the one the forward pass had."""
    inertia = np.asarray(lierk.inertia.tee_handle())
    out = []
    for solver in (lierk.Strang(), lierk.BlanesMoan4()):
        for w0, label in (
            ((1.0, 0.05, 0.3), "T-handle near the intermediate axis"),
            ((1.0, 1e-4, 1e-4), "near the separatrix"),
        ):
            for T in (10.0, 100.0) if not QUICK else (1.0,):
                n, body = round(T / 0.01), lierk.FreeRigidBody(inertia, jnp.asarray(w0))

                def sweep(R, m, h, n=n, body=body, solver=solver):
                    def one(c, _):
                        st = solver.step(body, 0.0, h, *c)
                        return (st.R, st.y), (st.R, st.y)

                    return jax.lax.scan(one, (R, m), None, length=n)

                @jax.jit
                def rebuilt_error(sweep=sweep, body=body):
                    (R1, m1), (Rs, ms) = sweep(body.R0, body.y0, 0.01)
                    _, (Rb, mb) = sweep(R1, m1, -0.01)
                    # Stepping back from the end, step k lands on forward state n - 1 - k.
                    Rf = jnp.concatenate([body.R0[None], Rs[:-1]])[::-1]
                    mf = jnp.concatenate([body.y0[None], ms[:-1]])[::-1]
                    return (
                        jnp.max(jnp.linalg.norm(Rb - Rf, axis=(1, 2))),
                        jnp.max(jnp.linalg.norm(mb - mf, axis=1)) / jnp.linalg.norm(body.y0),
                    )

                eR, em = (float(x) for x in rebuilt_error())
                out.append(dict(solver=solver.name, body=label, omega0=list(w0), T=T, steps=n, R_error=eR, m_error=em))
                print(
                    f"  reversibility: {solver.name} {label}, T = {T:g}: rebuilt states off by {eR:.1e} (R), "
                    f"{em:.1e} (m, relative)",
                    flush=True,
                )
    return out


def markdown(p) -> list[str]:
    m = p["machine"]
    lines = [
        "# Sensitivity work-precision: dR(T)/d omega0",
        "",
        f"Machine: {m['cpu_count']} cores, {m['cpu']}, {backend_text(m)}, jax {m['jax']}, diffrax {m['diffrax']}, "
        f"lierk {m['lierk']}; float64. Produced by `benchmarks/sensitivity.py`.",
        "Error: largest ||J - J_ref||_F / ||J_ref||_F over the batch. Time: median wall time of the whole batch (s).",
        "",
    ]
    for fam in p["families"].values():
        lines += [f"## {fam['title']} ({fam['N']} bodies)", "", f"Reference: {fam['reference']}."]
        if "reference_vs_diffrax_Dopri8_1e-13" in fam:
            lines.append(f"Reference against diffrax Dopri8 at 1e-13: {fam['reference_vs_diffrax_Dopri8_1e-13']:.1e}.")
        lines += [
            "",
            "| Jacobian error <= | lierk's cheapest (s) | which | diffrax's cheapest (s) | lierk / diffrax "
            "| derivative of the solve only (s) | its ratio |",
            "|---|---:|---|---:|---:|---:|---:|",
        ]
        for lv in fam["levels"]:
            cell = lambda x, f="{:.4f}": "-" if x is None else f.format(x)  # noqa: E731
            lines.append(
                f"| {lv['level']:.0e} | {cell(lv['lierk_s'])} | {lv.get('lierk_cheapest') or '-'} | "
                f"{cell(lv['diffrax_s'])} | {cell(lv['ratio'], '{:.2f}')} | {cell(lv.get('lierk_derivative_s'))} | "
                f"{cell(lv.get('ratio_derivative'), '{:.2f}')} |"
            )
        lines += [
            "",
            "| method | mode | setting | error | Jacobian (s) | forward solve (s) | Jacobian / forward "
            "| mean steps | devices |",
            "|---|---|---|---:|---:|---:|---:|---:|---:|",
        ]
        for r in fam["records"]:
            lines.append(
                f"| {r['method']} | {r['mode']} | {r['setting']} | {r['error']:.1e} | {r['time_s']:.4f} | "
                f"{r['forward_s']:.4f} | {r['ratio_to_forward']:.1f} | {r['mean_steps']:.0f} | {r['devices']} |"
            )
        lines.append("")
    lines += [
        "## Reverse-mode memory (RKMK4, one body, dt = 1e-3)",
        "",
        "| steps | adjoint | compiled temporaries (MB) | gradient (s) | forward (s) | gradient / forward |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for r in p["reverse_memory"]:
        lines.append(
            f"| {r['steps']} | {r['adjoint']} | {r['temp_bytes'] / 1e6:.3f} | {r['gradient_s']:.3f} | "
            f"{r['forward_s']:.3f} | {r['gradient_s'] / r['forward_s']:.1f} |"
        )
    if p.get("reversibility"):
        lines += [
            "",
            "## Would a reversible adjoint be right? (splittings, dt = 0.01 s, accuracy only)",
            "",
            "States rebuilt by stepping back from t1 with -dt against the states of the forward pass: "
            "the largest difference over the run.",
            "",
            "| solver | body | T (s) | steps | R rebuilt, max error | m rebuilt, max relative error |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for r in p["reversibility"]:
            lines.append(
                f"| {r['solver']} | {r['body']} | {r['T']:g} | {r['steps']} | {r['R_error']:.1e} | {r['m_error']:.1e} |"
            )
    return lines


def plot(p):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fams = list(p["families"].values())
    fig, axs = plt.subplots(1, len(fams), figsize=(6.5 * len(fams), 5.0), squeeze=False)
    for ax, fam in zip(axs[0], fams):
        methods = dict.fromkeys((r["method"], r["mode"]) for r in fam["records"])
        for method, mode in methods:
            rs = [r for r in fam["records"] if r["method"] == method and r["mode"] == mode]
            ax.loglog(
                [r["error"] for r in rs],
                [r["time_s"] for r in rs],
                ("o-" if method.startswith("lierk") else "s--"),
                label=f"{method} ({mode})",
                ms=4,
                lw=1.2 if mode == "forward" else 0.8,
                alpha=1.0 if mode == "forward" else 0.6,
            )
        ax.set_xlabel("Jacobian error, max relative Frobenius")
        ax.set_ylabel(f"wall time for {fam['N']} Jacobians (s)")
        ax.set_title(fam["title"], fontsize=10)
        ax.invert_xaxis()
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    m = p["machine"]
    fig.suptitle(
        f"Sensitivity dR(T)/d$\\omega_0$: work against precision ({m['cpu_count']} cores, {backend_text(m)}, float64)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(OUT / "sensitivity.png", dpi=110)


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    p = dict(machine=machine_info(diffrax=diffrax.__version__), families={}, reverse_memory=[], reversibility=[])

    def save():
        # After every part: a run stopped part-way (the full one takes over
        # an hour, mostly compiling) still leaves what it measured.
        write_results(OUT, "sensitivity", p, markdown(p))
        plot(p)
        print("and sensitivity.png", flush=True)

    fams = [Tee(), Top()]
    print(f"{fams[0].title}:", flush=True)
    p["families"][fams[0].name] = run_family(fams[0])
    save()
    p["reverse_memory"] = reverse_memory()
    save()
    for fam in fams[1:]:
        print(f"{fam.title}:", flush=True)
        p["families"][fam.name] = run_family(fam)
        save()
    # Last: accuracy only, and slow where each of its 10,000 small steps is a
    # kernel launch (a GPU), so a run with a time limit keeps the timings.
    p["reversibility"] = reversibility()
    save()


if __name__ == "__main__":
    main()
