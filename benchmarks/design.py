"""What a gradient of a design cost costs against one evaluation of the cost.

The two costs of the design examples (docs/examples/tuned-controller.md and
docs/examples/optimal-slew.md), written out here as the pages write them:

- the fleet: the mean over 64 dispersed spacecraft (`jax.vmap`) of an MRP
  proportional-derivative law's smoothed settling time plus its effort,
  two minutes at 1 Hz through `lierk.solve_sampled` (two RK4 steps a
  period), a function of the two gains;
- the slew: the augmented Lagrangian of one spacecraft's 24 held wheel
  commands (72 inputs), through `lierk.solve_sampled` (four RK4 steps a
  period).

For each: one evaluation (``jax.jit(cost)``), its gradient in reverse mode
(``jax.jit(jax.grad(cost))``, what the examples' BFGS uses), and the
Jacobian in forward mode (``jax.jit(jax.jacfwd(cost))``: as many tangents as
inputs), median wall time of later calls, the first call (compile) apart.

Run: ``python benchmarks/design.py [--quick] [--out DIR]`` (``--quick``: a
batch of 8 and 30 periods, into a temp dir).
"""

from __future__ import annotations

import os

REPEATS = 15


def fleet_cost(batch: int, periods: int):
    """``(cost, log_gains, data)``: the tuned-controller example's cost."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import lierk

    so3 = lierk.so3
    I_nominal = np.array([12.0, 10.0, 8.0])
    Js = jnp.full(3, 0.05)
    period = 1.0
    keys = jax.random.split(jax.random.key(0), 5)
    moments = I_nominal * jax.random.uniform(keys[0], (batch, 3), minval=0.8, maxval=1.2)
    tilt = so3.exp(0.1 * jax.random.normal(keys[1], (batch, 3)))
    inertia = tilt @ (moments[:, :, None] * jnp.swapaxes(tilt, -1, -2))
    axis = jax.random.normal(keys[2], (batch, 3))
    angle = jax.random.uniform(keys[3], (batch, 1), minval=0.2, maxval=1.2)
    R0 = so3.exp(angle * axis / jnp.linalg.norm(axis, axis=-1, keepdims=True))
    data = (inertia, R0, 0.01 * jax.random.normal(keys[4], (batch, 3)))

    def fly(gains, inertia, R0, omega0):
        K, P = gains
        wheels = lierk.ReactionWheels(jnp.eye(3), Js, jnp.zeros(3), torque=jnp.zeros(3))
        body = lierk.RigidBodyWithEffects(inertia, omega0, R0=R0, effects=(wheels,))
        inertia_inv = jnp.linalg.inv(inertia)

        def law(k, t, R, y):
            return K * so3.to_mrp(R) + P * (inertia_inv @ y[0])

        sol, u = lierk.solve_sampled(
            body, lierk.RKMK4(), law, lambda p: p.effects[0].torques, period, periods, dt=period / 2, throw=False
        )
        return jnp.linalg.norm(so3.log(sol.R), axis=-1), u

    def cost(log_gains, data):
        errors, u = jax.vmap(fly, in_axes=(None, 0, 0, 0))(jnp.exp(log_gains), *data)
        outside = period * jnp.sum(jax.nn.sigmoid((errors - 0.01) / 0.003), axis=1)
        return jnp.mean(outside + 1000.0 * period * jnp.sum(u**2, axis=(1, 2)))

    P_book = 2 * 12.0 / 10.0
    return cost, jnp.log(jnp.array([P_book**2 / 12.0, P_book])), data


def slew_cost(periods: int):
    """``(cost, V, args)``: the optimal-slew example's augmented Lagrangian."""
    import jax.numpy as jnp
    import numpy as np

    import lierk

    so3 = lierk.so3
    T, theta = 60.0, np.pi / 2
    period = T / periods
    target = so3.exp(theta * jnp.array([1.0, 1.0, 1.0]) / np.sqrt(3.0))
    inertia = jnp.array([[4.0, 0.3, -0.2], [0.3, 6.0, 0.4], [-0.2, 0.4, 5.0]])
    Js = jnp.full(3, 0.1)
    scale = 6 * 5.0 * theta / T**2

    def cost(V, lam):
        U = scale * V
        wheels = lierk.ReactionWheels(jnp.eye(3), Js, jnp.zeros(3), torque=jnp.zeros(3))
        body = lierk.RigidBodyWithEffects(inertia, jnp.zeros(3), effects=(wheels,))
        sol, _ = lierk.solve_sampled(
            body,
            lierk.RKMK4(),
            lambda k, t, R, y: U[k],
            lambda p: p.effects[0].torques,
            period,
            periods,
            dt=period / 4,
            throw=False,
        )
        c = jnp.concatenate([so3.log(target.T @ sol.R[-1]), T * jnp.linalg.solve(inertia, sol.y[0][-1])])
        return period * jnp.sum(U**2) / (T * scale**2) + lam @ c + 50.0 * (c @ c)

    V = 0.1 * jnp.asarray(np.random.default_rng(0).standard_normal((periods, 3)))
    return cost, V, jnp.full(6, 0.01)


def measure(name, cost, x, args, inputs) -> dict:
    import common
    import jax

    row = {"cost": name, "inputs": inputs}
    for label, f in (("forward", cost), ("grad", jax.grad(cost)), ("jacfwd", jax.jacfwd(cost))):
        _, median, first = common.timed(jax.jit(f), x, args, repeats=REPEATS, min_time=1.0)
        row[f"{label}_s"], row[f"{label}_first_s"] = median, first
        print(f"{name:28s} {label:8s} {1e3 * median:9.2f} ms (first call {first:.1f} s)", flush=True)
    return row


def main(argv=None):
    import jax

    jax.config.update("jax_enable_x64", True)
    import common

    quick, out = common.cli(__doc__, "a batch of 8 and 30 periods, into a temp dir", argv=argv)
    batch, periods = (8, 30) if quick else (64, 120)
    meta = {
        "machine": common.machine_info(),
        "commit": common.git_commit(),
        "repeats": REPEATS,
        "batch": batch,
        "periods": periods,
    }
    cost, x, data = fleet_cost(batch, periods)
    rows = [measure(f"fleet of {batch}, {periods} periods", cost, x, data, 2)]
    cost, V, lam = slew_cost(24)
    rows.append(measure("slew, 24 held commands", cost, V, lam, 72))
    meta["machine"]["load_average_at_end"] = os.getloadavg()
    common.write_results(out, "design", {"meta": meta, "rows": rows}, markdown(meta, rows))


def markdown(meta, rows) -> list[str]:
    import common

    m = meta["machine"]
    lines = [
        "# The gradient of a design cost against one evaluation",
        "",
        f"{m['cpu_count']} cores ({m['cpu']}), {common.backend_text(m)}; jax {m['jax']}, lierk {m['lierk']}, "
        f"commit {meta['commit']}.  Float64; median of at least {meta['repeats']} later calls of each compiled "
        "program (the first call apart); the costs of docs/examples/tuned-controller.md (a batch's mean over "
        "`jax.vmap`, two gains) and docs/examples/optimal-slew.md (one spacecraft, 72 held commands), both "
        "through `lierk.solve_sampled`.  Load average at start "
        f"{tuple(round(x, 1) for x in m['load_average_at_start'])}, at end "
        f"{tuple(round(x, 1) for x in m['load_average_at_end'])}: a shared machine, so the times are noisy.",
        "",
        "| cost | inputs | forward (ms) | `jax.grad` (ms) | grad / forward | `jax.jacfwd` (ms) | jacfwd / forward |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['cost']} | {r['inputs']} | {1e3 * r['forward_s']:.2f} | {1e3 * r['grad_s']:.2f} "
            f"| {r['grad_s'] / r['forward_s']:.1f} | {1e3 * r['jacfwd_s']:.2f} | {r['jacfwd_s'] / r['forward_s']:.1f} |"
        )
    return lines


if __name__ == "__main__":
    main()
