"""Shared test fixtures: every solver, reference solutions, and problems."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import lierk
import lierk.exact

FIXED_SOLVERS = [
    lierk.ExplicitEuler(),
    lierk.LieEuler(),
    lierk.NaiveLieRK4(),
    lierk.RKMK4(),
    lierk.CF4(),
    lierk.RKMK(lierk.tableaux.RK4),
]
# Kick-drift splittings: fixed step, exact free flow as the drift.
SPLITTING_SOLVERS = [
    lierk.Strang(),
    lierk.Yoshida4(),
    lierk.BlanesMoan4(),
    lierk.Yoshida6(),
    lierk.BlanesMoan6(),
    lierk.BlanesMoanRKN4(),
    lierk.BlanesMoanRKN6(),
]
FIXED_SOLVERS = FIXED_SOLVERS + SPLITTING_SOLVERS
LIE_SOLVERS = [s for s in FIXED_SOLVERS if not isinstance(s, lierk.ExplicitEuler)]
ADAPTIVE_SOLVERS = [lierk.RKF45(), lierk.DP54(), lierk.DOP853()]
ALL_SOLVERS = FIXED_SOLVERS + ADAPTIVE_SOLVERS

TEE = np.diag([9.82271303e-05, 7.22671030e-05, 1.57865031e-04])
# A non-commuting test problem: the T-handle off its axes.
OMEGA_GENERIC = np.array([1.0, 0.05, 0.3])

# A piecewise-linear torque profile along body z (N m) at its sample times (s),
# and its impulse, the area under it (N m s: 0.1 + 0.4 + 0.1).
TORQUE_TIMES = [0.0, 0.5, 1.5, 2.0]
TORQUE_SAMPLES = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.4], [0.0, 0.0, 0.4], [0.0, 0.0, 0.0]]
TORQUE_IMPULSE = 0.6


_exact_R = jax.jit(lambda inertia, omega0, t1, R0: lierk.exact.free_rigid_body(inertia, omega0, t1, R0)[0])


def reference_R(inertia, omega0, t1, R0=None):
    """R(t1) of the torque-free body from the closed form `lierk.exact`
    (agrees with `scipy_reference_R` to ~1e-12 on these problems)."""
    R0 = np.eye(3) if R0 is None else np.asarray(R0, dtype=float)
    return np.asarray(_exact_R(np.asarray(inertia, float), np.asarray(omega0, float), float(t1), R0))


def scipy_reference_R(inertia, omega0, t1, R0=None, rtol=1e-13):
    """R(t1) of the torque-free body from SciPy's DOP853 on the 9-component ODE:
    an independent check of `reference_R`."""
    inertia = np.asarray(inertia, dtype=float)
    R0 = np.eye(3) if R0 is None else np.asarray(R0, dtype=float)
    L = R0 @ inertia @ np.asarray(omega0, dtype=float)
    Iinv = np.linalg.inv(inertia)

    def f(t, x):
        R = x.reshape(3, 3)
        w = Iinv @ R.T @ L
        W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return (R @ W).ravel()

    sol = solve_ivp(f, (0.0, t1), R0.ravel(), method="DOP853", rtol=rtol, atol=rtol)
    return sol.y[:, -1].reshape(3, 3)


def fd_points(x, h=1e-3) -> np.ndarray:
    """The inputs `fd_jacobian` evaluates, ``(4 n, n)``: ``x + k h e_j`` for
    each direction ``j`` and ``k = 2, 1, -1, -2``.  Evaluate them in one
    batch (``jax.vmap`` inside a program that computes more) and pass the
    values to `fd_from_values`."""
    x = np.asarray(x, dtype=float)
    return np.stack([x + k * h * e for e in np.eye(x.size) for k in (2, 1, -1, -2)])


def fd_from_values(values, h=1e-3) -> np.ndarray:
    """Fourth-order central differences from ``f`` at `fd_points` ``(4 n,
    ...)``: one column per input direction (the last axis)."""
    v = np.asarray(values).reshape(-1, 4, *np.shape(values)[1:])
    return np.stack([(-c[0] + 8 * c[1] - 8 * c[2] + c[3]) / (12 * h) for c in v], -1)


def fd_jacobian(f, x, h=1e-3):
    """Fourth-order central differences of ``f`` at ``x`` ``(n,)``, one column
    per input direction (the last axis): truncation ~h^4, rounding ~1e-16/h."""
    return fd_from_values([np.asarray(f(p)) for p in fd_points(x, h)], h)


def derivatives_and_differences(f, modes=("jacfwd", "jacrev"), h=1e-3):
    """``(x, *args) -> ([jax.<mode>(f)(x, *args) for mode in modes], fd)``,
    ``fd`` `fd_jacobian`'s differences of ``f`` in ``x``, all from one
    compiled program (``args`` traced, not differentiated): compiled apart,
    the modes and the value cost about a third more compile time (a
    splitting's elliptic drift differentiated is the suite's largest
    program)."""

    @jax.jit
    def program(x, *args):
        points = x + jnp.asarray(fd_points(np.zeros(x.shape[0]), h), x.dtype)
        jacobians = [getattr(jax, mode)(f)(x, *args) for mode in modes]
        return jacobians, jax.vmap(lambda p: f(p, *args))(points)

    def run(x, *args):
        jacobians, values = program(jnp.asarray(x, float), *(jnp.asarray(a, float) for a in args))
        return [np.asarray(J) for J in jacobians], fd_from_values(values, h)

    return run


def final_attitudes(problem, solver, t1, dts) -> np.ndarray:
    """``R(t1)`` ``(len(dts), 3, 3)`` of fixed-step solves of ``problem``,
    one per step ``dt`` (s) in ``dts``: one program for all, a vmap over dt
    with ``max_steps`` the largest count (the steps past ``t1`` are no-ops),
    where a solve per dt would compile once per step count."""
    dts = np.asarray(dts, dtype=float)
    n = int(np.ceil(t1 / dts.min()))
    R, results = _final_attitudes(problem, solver, np.float64(t1), dts, n)
    assert np.all(np.asarray(results) == 0), results
    return np.asarray(R)


@eqx.filter_jit
def _final_attitudes(problem, solver, t1, dts, n):
    def one(dt):
        sol = lierk.solve(problem, solver, t1, dt=dt, max_steps=n)
        return sol.R[-1], sol.result

    return jax.vmap(one)(dts)


def order_fit(hs, errs) -> float:
    """Slope of log(error) against log(h)."""
    return float(np.polyfit(np.log(hs), np.log(errs), 1)[0])


def write(tmp_path, text, name="scene.toml"):
    """Write a scene's TOML ``text`` to ``tmp_path/name`` and return the path."""
    path = tmp_path / name
    path.write_text(text)
    return path


def run_inprocess(argv, capsys):
    """``lierk ARGV`` in this process: (exit status, stdout, stderr)."""
    from lierk.app import cli

    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as e:  # argparse's own exits (--help, bad syntax)
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err
