"""Dense output on SO(3): the attitude and state between the steps of a solve.

Within a step from ``(t_n, R_n, y_n)`` of size ``h`` each solver gives the
state at ``t_n + theta h``, ``theta in [0, 1]``, in one of two ways.

Polynomial interpolants (every solver but the splittings).  The attitude is

    R(t_n + theta h) = R_n exp(hat(u(theta))),

with ``u`` a polynomial in the algebra at ``R_n`` (``u(0) = 0``), and the
extra state is ``y(t_n + theta h) = y_n + p(theta)`` with ``p`` a polynomial
in R^n.  The matrix is never interpolated entry by entry (that would leave
SO(3)).  Both polynomials are kept in the nested basis SciPy's DOP853 uses,

    p(theta) = theta (F_0 + (1 - theta)(F_1 + theta (F_2 + (1 - theta)(F_3 + ...)))),

which is well conditioned on ``[0, 1]`` (the monomial form of DOP853's
extension has coefficients up to 545 and lost three digits to cancellation).
``F_0`` is the whole step's increment, so ``theta = 1`` gives the step's end.

- A tableau with a continuous extension (`DOP853`: Hairer, Norsett and
  Wanner's, order 7, three more stages per step) applies it to the RKMK
  stages: they are an ordinary Runge-Kutta solution of the ODE for ``u``
  (``u' = dexpinv(-u, omega)``), so the extension keeps its order on the group.
- The other RKMK and Crouch-Grossman solvers get a quintic Hermite
  interpolant (`hermite`) from the two ends of the step:
  ``u(1) = log(R_n^T R_{n+1})``, and at each end the slope and curvature of
  ``u``, from the body angular velocity and its time derivative there
  (`node`: one field evaluation and one JVP of the field along the motion).
  Its interpolation error is ``O(h^6)``, so the dense output has the
  solver's own local accuracy up to order 5: order 4 for RKMK4 and CF4, 5
  for DP54 and RKF45 (``tests/test_dense.py`` fits the slopes).  Its
  constant grows with the turn per step, ``|omega| h``, and blows up as
  ``|u(1)|`` nears ``2 pi``, the first pole of ``dexpinv`` in the chart at
  ``R_n``: on a fast symmetric body the error between the steps was 1.7
  times that at the steps at 4.5 rad a step, 40 to 2500 times at 5.8 to 6.4
  rad (CF4), 700 times at 12.4 rad (RKMK4).

A shortened step (the splittings, `PartialStep`).  A splitting's drift is
the exact torque-free flow, so on a free body its steps are exact to
rounding and on a torqued one they carry the method's order with small
constants: a polynomial through the ends of the step is far coarser (the
quintic Hermite interpolant was 500 to 10^7 times worse between the steps
than at them on a free body).  Instead the state at ``t_n + theta h`` is a
fresh step of the same method of size ``theta h`` from ``(t_n, R_n, y_n)``:
every kick scaled with the drifts, and the kicks reading the clock where
the drifts have brought it.  It is exact (to rounding) for a free body, has
the method's local error ``O((theta h)^(p+1))`` with torques, equals the
step itself at ``theta = 1`` and the start at ``theta = 0``, and is
continuous in ``theta`` (its time derivative jumps by ``O(h^p)`` from step
to step).  Each evaluation costs one step of the method; nothing is stored
per step beyond the step's start (``d = 0`` coefficients), but the
interpolation keeps the problem and the solver (`PartialStep`).
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import _validation as validation
from . import so3

__all__ = ["DenseInterpolation", "PartialStep", "nested", "node", "hermite", "evaluate_step", "interpolate"]


def nested(F: Array, theta: Array) -> Array:
    """``theta (F[0] + (1 - theta)(F[1] + theta (F[2] + ...)))`` for ``F`` of
    shape ``(d, ...)`` and a scalar ``theta``: shape ``F.shape[1:]``."""
    acc = F[-1]
    for i in range(F.shape[0] - 2, -1, -1):
        # The factor that multiplied F[i + 1] and everything after it.
        acc = F[i] + (theta if i % 2 else 1.0 - theta) * acc
    return theta * acc


def node(problem, t: Array, R: Array, y: Any) -> tuple:
    """What the Hermite interpolant needs at a point of the motion:
    ``((omega, dy/dt), (domega/dt, d^2y/dt^2))``, the field ``(3,)`` (rad/s)
    and its rate of change along the motion (rad/s^2), from one JVP of the
    field in the direction ``(1, R hat(omega), dy/dt)``."""

    def field(t, R, y):
        return problem.at(problem.base(t, R, y), t, y)

    f = field(t, R, y)
    omega, ydot = f
    tangent = (jnp.ones_like(t), so3.compose(R, so3.hat(omega)), ydot)
    return f, jax.jvp(field, (t, R, y), tangent)[1]


def _unwrap(U: Array, estimate: Array) -> Array:
    """The rotation vector of ``exp(hat(U))`` (``|U| <= pi``) closest to
    ``estimate``: ``U`` plus a whole number of turns about its axis.  A step
    that turns the body by more than half a turn still gets its own ``u(1)``."""
    n2 = so3._sq(U)
    safe = jnp.where(n2 > 0, n2, 1.0)
    angle = jnp.sqrt(safe)
    turns = jnp.round((jnp.sum(estimate * U, axis=-1) / angle - angle) / (2 * math.pi))
    return jnp.where(n2 > 0, U * (1.0 + 2 * math.pi * turns / angle), U)


def _quintic(delta, v0, w0, v1, w1):
    """The nested-basis coefficients ``(5, ...)`` of the quintic ``p`` with
    ``p(0) = 0``, ``p(1) = delta``, ``p'(0) = v0``, ``p''(0) = w0``,
    ``p'(1) = v1``, ``p''(1) = w1`` (derivatives in ``theta``)."""
    F1 = v0 - delta
    F2 = 2 * delta - v0 - v1
    F3 = 0.5 * w0 + F1 - F2
    F4 = 0.5 * w1 + F1 + 2 * F2 - F3
    return jnp.stack([delta, F1, F2, F3, F4])


def hermite(h: Array, R0: Array, y0: Any, node0: tuple, R1: Array, y1: Any, node1: tuple) -> tuple[Array, Any]:
    """The quintic Hermite interpolant of one step of size ``h`` (s) from
    ``(R0, y0)`` to ``(R1, y1)``, given `node` at both ends: ``(F_u (5, 3),
    F_y)`` in the nested basis, ``F_y`` like ``y`` with a leading axis of 5.

    In the algebra at ``R0``, with ``u(1) = log(R0^T R1)``:
    ``u'(0) = h omega_0``, ``u''(0) = h^2 omega'_0``,
    ``u'(1) = h dexpinv(-u(1), omega_1)`` and ``u''(1)`` its derivative
    along the motion (body form: ``R = R0 exp(u)``, ``u' = dexpinv(-u, omega)``).
    """
    (w0, g0), (dw0, dg0) = node0
    (w1, g1), (dw1, dg1) = node1
    U = so3.log(so3.compose(jnp.swapaxes(R0, -1, -2), R1))
    # The trapezoid rule's increment is within O(h^3) of u(1): enough to
    # pick the right turn when the step turns the body by more than pi.
    U = _unwrap(U, 0.5 * h * (w0 + w1))
    # u'(1) = h v1 and, differentiating u' = h dexpinv(-u, omega) along the
    # motion, u''(1) = h^2 dv1 with dv1 the JVP in the direction (v1, omega'_1).
    v1 = so3.dexpinv(-U, w1)
    _, dv1 = jax.jvp(lambda u, w: so3.dexpinv(-u, w), (U, w1), (v1, dw1))
    Fu = _quintic(U, h * w0, h * h * dw0, h * v1, h * h * dv1)
    Fy = jax.tree_util.tree_map(
        lambda a, b, da, db, dda, ddb: _quintic(b - a, h * da, h * h * dda, h * db, h * h * ddb),
        y0,
        y1,
        g0,
        g1,
        dg0,
        dg1,
    )
    return Fu, Fy


def evaluate_step(R: Array, y: Any, Fu: Array, Fy: Any, theta: Array) -> tuple[Array, Any]:
    """``(R(theta), y(theta))`` in a step from ``(R, y)`` with coefficients
    ``Fu`` ``(d, 3)`` and ``Fy`` (leaves ``(d, ...)``), ``theta`` a scalar."""
    Rt = so3.right_exp(R, nested(Fu, theta))
    yt = jax.tree_util.tree_map(lambda a, F: a + nested(F, theta), y, Fy)
    return Rt, yt


class PartialStep(eqx.Module):
    """The interpolant of a solver whose own step, shortened, is as accurate
    between the steps as the step is at its end (the splittings): the state
    at ``theta`` in a step from ``(t, R, y)`` of size ``h`` is
    ``solver.step(problem, t, theta h, R, y)``.

    Keeps the problem and the solver: their arrays as leaves (so a batch of
    solutions carries each member's own problem, and the interpolant is
    differentiable in them) and everything else (functions, flags) as static
    data.
    """

    dynamic: Any
    static: Any = eqx.field(static=True)

    def __init__(self, problem, solver):
        self.dynamic, self.static = eqx.partition((problem, solver), eqx.is_array)

    def __call__(self, t: Array, h: Array, R: Array, y: Any, theta: Array) -> tuple[Array, Any]:
        """``(R, y)`` at ``t + theta h`` (s): ``R`` ``(3, 3)``, ``y`` like the state."""
        problem, solver = eqx.combine(self.dynamic, self.static)
        st = solver.step(problem, t, theta * h, R, y)
        return st.R, st.y


def interpolate(step: tuple, theta: Array, partial: PartialStep | None = None) -> tuple[Array, Any]:
    """``(R, y)`` at ``theta`` (a scalar in ``[0, 1]``) in a step ``(t, h, R,
    y, Fu, Fy)`` (start (s), size (s), start state, coefficients): the
    solver's `PartialStep` if it has one, else the polynomial interpolant."""
    t, h, R, y, Fu, Fy = step
    if partial is not None:
        return partial(t, h, R, y, theta)
    return evaluate_step(R, y, Fu, Fy, theta)


class DenseInterpolation(eqx.Module):
    """The dense output of a solve (`lierk.SaveAt` ``dense=True``): every
    accepted step's start, size and interpolant.  `evaluate` gives the
    attitude and state at any time in ``[t0, t1]``.

    Memory: ``N (11 + n_y + d (3 + n_y))`` numbers, with ``N`` the step count
    of a fixed-step solve or ``max_steps`` of an adaptive one, ``n_y`` the
    size of the extra state (3 for a rigid body's momentum) and ``d`` the
    number of coefficients (5 for the Hermite interpolant, 7 for DOP853, 0
    for the splittings, which keep the problem instead): 352 or 448 bytes a
    step for a rigid body in float64 (1.8 MB for an adaptive solve's default
    ``max_steps`` of 4096), 112 for a splitting.  Solves without
    ``dense=True`` keep none of it.

    Accuracy between the steps (`lierk._interpolation`): the solver's own for
    the splittings (a shortened step) and DOP853 (order 7); order
    ``min(p, 5)`` for the other solvers of order ``p`` (quintic Hermite).

    Attributes:
        ts: ``(N,)`` start of each step (s); ``inf`` after the last.
        hs: ``(N,)`` step sizes (s); 0 after the last.
        R: ``(N, 3, 3)`` attitudes at the step starts, body -> space.
        y: extra state at the step starts (leaves ``(N, ...)``), or None.
        Fu: ``(N, d, 3)`` coefficients of ``u`` (rad) in the nested basis.
        Fy: coefficients of ``y`` (leaves ``(N, d, ...)``), or None.
        t0, t1: the interval `evaluate` accepts (s): from the start to where
            the solve ended (``t1``, or the time a terminating event stopped it).
        n: number of valid steps.
        partial: the splittings' `PartialStep` (which then ignores ``Fu``
            and ``Fy``), or None.
    """

    ts: Array
    hs: Array
    R: Array
    y: Any
    Fu: Array
    Fy: Any
    t0: Array
    t1: Array
    n: Array
    partial: PartialStep | None = None

    def evaluate(self, t) -> tuple[Array, Any]:
        """``(R(t), y(t))`` at times ``t`` (s), a scalar or any array shape
        ``S``: ``R`` is ``S + (3, 3)`` and each leaf of ``y`` gains ``S`` in
        front.  Works under `jax.jit` and `jax.vmap` and is differentiable in
        ``t`` and in the solve's inputs.

        Raises:
            ValueError: ``t`` outside ``[t0, t1]`` or NaN (at run time,
                through `eqx.error_if`, when ``t`` or the solution is traced).
        """
        dtype = self.ts.dtype
        t = validation.asarray(t, dtype, "t")
        if not validation.is_traced(t, self.t0, self.t1):
            lo, hi = float(self.t0), float(self.t1)
            tn = np.asarray(t, np.float64)
            bad = ~((tn >= lo) & (tn <= hi))
            if bad.any():
                raise ValueError(
                    f"evaluate(t): t = {float(tn[bad].flat[0])!r} is outside the solved interval [{lo!r}, {hi!r}] s "
                    f"({int(bad.sum())} of {tn.size} times); the dense output covers only the solve's own interval"
                )
        else:
            t = eqx.error_if(
                jnp.asarray(t),
                ~jnp.all((t >= self.t0) & (t <= self.t1)),
                "evaluate(t): t is outside the solved interval [t0, t1] (or NaN); the dense output covers only "
                "the solve's own interval",
            )
        if self.partial is not None and not validation.is_traced(t, self):
            return _evaluate_in_chunks(self, np.asarray(t, dtype))
        return _evaluate(self, jnp.asarray(t, dtype))

    def step_index(self, t: Array) -> Array:
        """Index of the step that holds ``t`` (a scalar): the last step
        starting at or before ``t``."""
        i = jnp.searchsorted(self.ts, t, side="right") - 1
        return jnp.clip(i, 0, jnp.maximum(self.n - 1, 0).astype(i.dtype))

    def _at(self, t: Array) -> tuple[Array, Any]:
        i = self.step_index(t)
        h = self.hs[i]
        theta = jnp.where(h > 0, (t - self.ts[i]) / jnp.where(h > 0, h, 1.0), 0.0)
        pick = lambda x: None if x is None else jax.tree_util.tree_map(lambda a: a[i], x)  # noqa: E731
        step = (self.ts[i], h, self.R[i], pick(self.y), self.Fu[i], pick(self.Fy))
        return interpolate(step, theta, self.partial)


# Times per call of `_partial_steps`: a scalar evaluation wastes 15 shortened
# steps, a long one pays a dispatch per 16.
_CHUNK = 16


@eqx.filter_jit
def _partial_steps(partial: PartialStep, ts: Array, hs: Array, R: Array, y: Any, theta: Array) -> tuple[Array, Any]:
    return jax.vmap(partial)(ts, hs, R, y, theta)


def _evaluate_in_chunks(interp: DenseInterpolation, t: np.ndarray) -> tuple[Array, Any]:
    """`_evaluate` for a `PartialStep` on concrete times and solution: the
    steps are looked up in NumPy and the shortened steps taken
    `_CHUNK` at a time, so that one compiled program (a step of the method,
    large for the elliptic-function drift, seconds to compile) serves
    every number of times and every solve of the same problem type, where
    `_evaluate` compiles anew for each shape of ``t`` and each step count."""
    flat = t.ravel()
    ts, hs = np.asarray(interp.ts), np.asarray(interp.hs)
    n = int(interp.n)
    i = np.clip(np.searchsorted(ts, flat, side="right") - 1, 0, max(n - 1, 0))
    h = hs[i]
    # (In the solution's dtype, as `DenseInterpolation._at` computes it.)
    theta = np.where(h > 0, (flat - ts[i]) / np.where(h > 0, h, 1).astype(h.dtype), 0).astype(h.dtype)
    k = flat.size
    pad = -k % _CHUNK if k else _CHUNK
    rows = np.concatenate([i, np.full(pad, i[-1] if k else 0, i.dtype)])
    theta = np.concatenate([theta, np.zeros(pad, theta.dtype)])
    pick = lambda x, j: jax.tree_util.tree_map(lambda a: a[j], x)  # noqa: E731
    R_all, y_all = np.asarray(interp.R), jax.tree_util.tree_map(np.asarray, interp.y)
    outs = []
    for a in range(0, rows.size, _CHUNK):
        j = rows[a : a + _CHUNK]
        outs.append(_partial_steps(interp.partial, ts[j], hs[j], R_all[j], pick(y_all, j), theta[a : a + _CHUNK]))
    R, y = jax.tree_util.tree_map(lambda *c: jnp.asarray(np.concatenate(c)[:k]), *outs)
    shape = t.shape
    return R.reshape(shape + (3, 3)), jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), y)


@eqx.filter_jit
def _evaluate(interp: DenseInterpolation, t: Array) -> tuple[Array, Any]:
    R, y = jax.vmap(interp._at)(jnp.ravel(t))
    shape = jnp.shape(t)
    return R.reshape(shape + (3, 3)), jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), y)
