"""The peers' side of the benchmarks, each written once:

- the rigid body as the ODEs a general solver integrates: the 12-component
  system ``y = (m, R row-major)`` (``m' = m x omega + tau``, ``R' = R
  hat(omega)``, ``omega = I^-1 m``) with the torques written out
  (`gravity_torque`, `orbit_torque`), and the free body's 9-component system
  ``X' = X hat(I^-1 X^T L)`` (``L`` the spatial angular momentum);
- diffrax's solve of them (`diffrax_solution`, `diffrax_solve`) and SciPy's
  (`scipy_solve`);
- MuJoCo's full physics states of one body on a ball joint and its batched
  rollout (`mujoco_*`).

Scripts import it as ``peers`` (they run as ``python benchmarks/NAME.py``, so
this folder is on ``sys.path``); jax, diffrax, SciPy and MuJoCo are imported
only when they are used.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

# --- the ODEs -----------------------------------------------------------------


def rigid_body_field(inertia, torque: Callable | None = None, xp=None) -> Callable:
    """``f(t, y, args=None) -> y'`` of the 12-component system for principal
    moments ``inertia`` ``(3,)`` (kg m^2), with ``torque(xp, t, R, omega)`` the
    body-frame torque (N m) written out by the caller (None: torque-free).
    ``xp``: ``jax.numpy`` (default) or ``numpy`` (SciPy)."""
    if xp is None:
        import jax.numpy as xp
    I_inv = 1.0 / np.asarray(inertia, float)

    def f(t, y, args=None):
        m, R = y[:3], y[3:].reshape(3, 3)
        w = I_inv * m
        W = xp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        dm = xp.cross(m, w)
        if torque is not None:
            dm = dm + torque(xp, t, R, w)
        return xp.concatenate([dm, (R @ W).ravel()])

    return f


def initial_state(inertia, omega0, R0=None, xp=None):
    """``y0`` ``(12,)`` of the 12-component system (``xp``: jax.numpy by default)."""
    if xp is None:
        import jax.numpy as xp

    R0 = xp.eye(3) if R0 is None else xp.asarray(R0)
    return xp.concatenate([xp.asarray(inertia) * xp.asarray(omega0), R0.ravel()])


def gravity_torque(mass: float, g: float, chi) -> Callable:
    """``torque(xp, t, R, omega)`` of gravity on a body hung at a pivot, centre
    of mass at ``chi`` (m, body frame): ``M g (R^T e3) x chi``."""

    def torque(xp, t, R, w):
        return mass * g * xp.cross(R[2], xp.asarray(chi))

    return torque


def orbit_torque(inertia, mean_motion: float, rotor, bdot: float, field_tilt: float) -> Callable:
    """``torque(xp, t, R, omega)`` of a satellite on a circular orbit in the
    space x-y plane (mean motion ``mean_motion``, rad/s): the gravity gradient
    on principal moments ``inertia``, a constant ``rotor`` momentum (kg m^2/s,
    body frame) and B-dot (gain ``bdot``, A m^2 s/T) in Earth's dipole field
    tilted ``field_tilt`` rad, ``B = B0 (R_E/a)^3 (3 (d.u) u - d)``; as
    `lierk.GravityGradient`, `lierk.Rotor` and `lierk.MagneticTorque`."""
    n = mean_motion
    a = (3.986004418e14 / n**2) ** (1 / 3)
    d = -np.array([np.sin(field_tilt), 0.0, np.cos(field_tilt)])

    def torque(xp, t, R, w):
        u = xp.stack([xp.cos(n * t), xp.sin(n * t), 0.0 * t])  # unit position
        ub = R.T @ u
        tau = 3 * n**2 * xp.cross(ub, xp.asarray(inertia) * ub)
        B = R.T @ (3.12e-5 * (6.371e6 / a) ** 3 * (3 * (xp.asarray(d) @ u) * u - xp.asarray(d)))
        return tau + xp.cross(xp.asarray(rotor), w) + bdot * xp.cross(xp.cross(w, B), B)

    return torque


def free_body_field(inertia, L=None, xp=None) -> Callable:
    """``f(t, x, L=L) -> x'`` of the free body's 9-component system ``X' = X
    hat(I^-1 X^T L)``, ``x = X`` row-major, for the inertia matrix ``inertia``
    ``(3, 3)``.  diffrax passes ``L`` as ``args``; SciPy calls ``f(t, x)``
    with the ``L`` given here.  ``xp``: ``jax.numpy`` (default) or ``numpy``."""
    if xp is None:
        import jax.numpy as xp
    I_inv = np.linalg.inv(np.asarray(inertia, float))

    def f(t, x, L=L):
        X = x.reshape(3, 3)
        w = I_inv @ (X.T @ L)
        return (X @ xp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])).ravel()

    return f


def free_body_state(inertia, omega0, R0=None):
    """``(x0 (9,), L (3,))`` of the 9-component system (jax.numpy): ``R0``
    (default the identity) and the spatial momentum ``R0 I omega0``."""
    import jax.numpy as jnp

    L = jnp.asarray(inertia) @ jnp.asarray(omega0)
    if R0 is None:
        return jnp.eye(3).ravel(), L
    R0 = jnp.asarray(R0)
    return R0.ravel(), R0 @ L


# --- diffrax ------------------------------------------------------------------


def diffrax_solution(
    field: Callable,
    solver,
    t1: float,
    y0,
    *,
    dt=None,
    rtol=None,
    max_steps: int = 4096,
    forward_mode: bool = False,
    args=None,
    event=None,
):
    """diffrax's ``diffeqsolve`` of ``field`` from 0 to ``t1`` (s), ``throw=False``,
    with ``solver`` (a diffrax solver, or its name: ``"Tsit5"``, ``"Dopri5"``,
    ``"Dopri8"``): at the constant step ``dt``, or adaptive with
    ``PIDController(rtol, atol=rtol)``.  ``forward_mode``:
    ``adjoint=diffrax.ForwardMode()``, which `jax.jacfwd` through a solve needs
    (diffrax's default adjoint is reverse mode only).  ``args`` go to the
    field, ``event`` (a ``diffrax.Event``) to the solve.  Returns diffrax's
    ``Solution``."""
    import diffrax

    kw = dict(args=args, event=event, max_steps=max_steps, throw=False)
    if dt is not None:
        kw.update(dt0=dt, stepsize_controller=diffrax.ConstantStepSize())
    else:
        kw.update(dt0=None, stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol))
    if forward_mode:
        kw["adjoint"] = diffrax.ForwardMode()
    solver = getattr(diffrax, solver)() if isinstance(solver, str) else solver
    return diffrax.diffeqsolve(diffrax.ODETerm(field), solver, 0.0, t1, y0=y0, **kw)


def diffrax_solve(field: Callable, solver, t1: float, y0, **kw):
    """`diffrax_solution`'s ``(R(t1) (3, 3), steps taken, result code)``, the
    code 0 for success and 1 otherwise (lierk's ``max_steps_reached``).  ``R``
    is the state's last nine components: either system."""
    import diffrax
    import jax.numpy as jnp

    sol = diffrax_solution(field, solver, t1, y0, **kw)
    failed = jnp.where(sol.result == diffrax.RESULTS.successful, 0, 1)
    return sol.ys[-1, -9:].reshape(3, 3), sol.stats["num_steps"], failed


# --- SciPy --------------------------------------------------------------------


def scipy_solve(field: Callable, t1: float, y0, tol: float):
    """SciPy's DOP853 (``solve_ivp``) of ``field(t, y)`` (``xp=numpy``) from 0
    to ``t1`` at ``rtol = atol = tol``: ``(R(t1) (3, 3), evaluations of the
    field)``, ``R`` the state's last nine components."""
    from scipy.integrate import solve_ivp

    sol = solve_ivp(field, (0.0, t1), np.asarray(y0, float), method="DOP853", rtol=tol, atol=tol)
    assert sol.success, sol.message
    return sol.y[-9:, -1].reshape(3, 3), sol.nfev


# --- MuJoCo -------------------------------------------------------------------
#
# One body on a ball joint: qpos is the body -> world quaternion (w, x, y, z),
# i.e. lierk's R, and qvel the BODY-frame angular velocity (checked against
# lierk by work_precision.py's `mujoco_frame_check` and torqued.py's check).
# The models (XML) are the scripts' own.


def _mj_full():
    import mujoco

    return mujoco.mjtState.mjSTATE_FULLPHYSICS.value


def mujoco_initial_states(model, omegas, quats=(1.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    """``(n, nstate)`` full physics states: qpos = ``quats`` (one ``(4,)`` for
    every member, or ``(n, 4)``), qvel = ``omegas`` ``(n, 3)`` (body frame)."""
    import mujoco

    data = mujoco.MjData(model)
    quats = np.broadcast_to(np.asarray(quats, float), (len(omegas), 4))
    init = np.empty((len(omegas), mujoco.mj_stateSize(model, _mj_full())))
    for i, (w, q) in enumerate(zip(omegas, quats)):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = q
        data.qvel[:] = w
        mujoco.mj_getState(model, data, init[i], _mj_full())
    return init


def mujoco_get_state(model, data) -> np.ndarray:
    """``data``'s full physics state ``(nstate,)``."""
    import mujoco

    s = np.empty(mujoco.mj_stateSize(model, _mj_full()))
    mujoco.mj_getState(model, data, s, _mj_full())
    return s


def mujoco_set_state(model, data, state) -> None:
    """Set ``data`` to the full physics state ``state``."""
    import mujoco

    mujoco.mj_setState(model, data, state, _mj_full())


def mujoco_final(model, final_states) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(R (n, 3, 3), body angular velocity (n, 3), time (n,))`` from full physics states."""
    import mujoco

    data = mujoco.MjData(model)
    n = len(final_states)
    R, w, t = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty(n)
    r9 = np.empty(9)
    for i, s in enumerate(final_states):
        mujoco.mj_setState(model, data, s, _mj_full())
        mujoco.mju_quat2Mat(r9, data.qpos)
        R[i], w[i], t[i] = r9.reshape(3, 3), data.qvel, data.time
    return R, w, t


def mujoco_quats(R) -> np.ndarray:
    """``(n, 4)`` quaternions (w, x, y, z) of rotation matrices ``R`` ``(n, 3, 3)``."""
    import mujoco

    out = np.empty((len(R), 4))
    for i, r in enumerate(np.asarray(R, float)):
        mujoco.mju_mat2Quat(out[i], r.ravel())
    return out


def mujoco_rollout(
    model, init, nstep: int, threads: int, control=None, control_spec: int | None = None, chunk: int = 2000
) -> Callable:
    """A function that rolls the batch of full physics states ``init`` ``(n,
    nstate)`` out for ``nstep`` steps with `mujoco.rollout` (one MjData per
    thread, a persistent pool) and returns the final states ``(n, nstate)``.
    The steps go in calls of the largest divisor of ``nstep`` up to ``chunk``
    (bounding the state buffer; one call when ``nstep <= chunk``).
    ``control``: a constant control vector for every member and step, of kind
    ``control_spec`` (an ``mjtState`` mask)."""
    import mujoco
    import mujoco.rollout

    chunk = max(d for d in range(1, min(nstep, chunk) + 1) if nstep % d == 0)
    datas = [mujoco.MjData(model) for _ in range(threads)]
    kw = {}
    if control is not None:
        kw = dict(
            control=np.ascontiguousarray(np.broadcast_to(control, (len(init), chunk, len(control)))),
            control_spec=control_spec,
        )
    state = np.empty((len(init), chunk, init.shape[1]))
    calls = nstep // chunk

    def go():
        s = init
        for i in range(calls):
            mujoco.rollout.rollout(model, datas, s, nstep=chunk, state=state, persistent_pool=True, **kw)
            # The next call reads its start while writing `state`: a copy.
            s = state[:, -1].copy() if i < calls - 1 else state[:, -1]
        return s

    return go
