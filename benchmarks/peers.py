"""The peers' side of a benchmark, written once: the rigid body as the
12-component ODE ``y = (m, R row-major)`` that a general ODE solver integrates
(``m' = m x omega + tau``, ``R' = R hat(omega)``, ``omega = I^-1 m``), and
diffrax's solve of it.

Scripts import it as ``peers`` (they run as ``python benchmarks/NAME.py``, so
this folder is on ``sys.path``); diffrax is imported only when it is used.
"""

from __future__ import annotations

from typing import Callable

import numpy as np


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


def initial_state(inertia, omega0, R0=None):
    """``y0`` ``(12,)`` of the 12-component system (jax.numpy)."""
    import jax.numpy as jnp

    R0 = jnp.eye(3) if R0 is None else jnp.asarray(R0)
    return jnp.concatenate([jnp.asarray(inertia) * jnp.asarray(omega0), R0.ravel()])


def diffrax_solve(field: Callable, solver: str, t1: float, y0, *, dt=None, rtol=None, max_steps: int = 4096,
                  forward_mode: bool = False):
    """diffrax's ``diffeqsolve`` of ``field`` from 0 to ``t1`` (s) with the
    solver named ``solver`` (``"Tsit5"``, ``"Dopri5"``, ``"Dopri8"``): at the
    constant step ``dt``, or adaptive with ``PIDController(rtol, atol=rtol)``.
    ``forward_mode``: ``adjoint=diffrax.ForwardMode()``, which `jax.jacfwd`
    through an adaptive solve needs (diffrax's default adjoint is reverse
    mode only).  Returns ``(R(t1) (3, 3), result code)``, 0 for success."""
    import diffrax
    import jax.numpy as jnp

    kw = dict(max_steps=max_steps, throw=False)
    if dt is not None:
        kw.update(dt0=dt, stepsize_controller=diffrax.ConstantStepSize())
    else:
        kw.update(dt0=None, stepsize_controller=diffrax.PIDController(rtol=rtol, atol=rtol))
    if forward_mode:
        kw["adjoint"] = diffrax.ForwardMode()
    sol = diffrax.diffeqsolve(diffrax.ODETerm(field), getattr(diffrax, solver)(), 0.0, t1, y0=y0, **kw)
    failed = jnp.where(sol.result == diffrax.RESULTS.successful, 0, 1)
    return sol.ys[-1, 3:].reshape(3, 3), failed
