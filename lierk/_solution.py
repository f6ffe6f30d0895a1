"""What `solve` returns, what it saves, and how it reports failure."""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

__all__ = ["RESULTS", "SaveAt", "Solution"]


class RESULTS:
    """Result codes carried by `Solution.result` (an int array, one per batch member)."""

    successful = 0
    max_steps_reached = 1
    dt_min_reached = 2
    nonfinite = 3
    target_error_not_reached = 4
    invariant_drift = 5
    event_occurred = 6
    event_condition_nan = 7
    invalid_times = 8
    invalid_step = 9
    invalid_save_times = 10
    invalid_tolerances = 11
    invalid_target = 12
    invalid_problem = 13

    _traced = (
        "is NaN, or is traced (inside jax.jit or jax.vmap) and failed the check that raises at once, with "
        "the value, for a known value: "
    )
    messages = {
        0: "successful",
        1: "max_steps was reached before t1; raise max_steps or loosen the tolerances",
        2: "the step size fell below dtmin (or below machine precision relative to t): "
        "the tolerance is unreachable here; loosen rtol/atol or lower dtmin",
        3: "the solution became non-finite (NaN or inf)",
        4: "target_error was not reached: the estimated error stayed above it (below rounding, "
        "or more steps than max_steps allow); see Solution.error_estimate",
        5: "a quantity the exact flow conserves (energy, |L|, ...) drifted by more than 10%: the run is "
        "under-resolved (steps too long for the spin) or stiff; take smaller steps or an adaptive solver, "
        "or pass estimate_error=True to see the error",
        6: "a terminating event stopped the solve at the event time (not a failure): the last saved state is the "
        "one at the event; Solution.events says which event and when",
        7: "an event condition returned NaN: cond(t, R, y) must be a finite real number along the motion",
        8: "t0 or t1 " + _traced + "t1 must be >= t0, both finite; the states are NaN",
        9: "dt or dt0 " + _traced + "dt must be > 0, a finite number (dt0 too); the states are NaN",
        10: "a save time " + _traced + "SaveAt(ts=...) must be non-decreasing and lie in [t0, t1]; the states are NaN",
        11: "a tolerance " + _traced + "rtol must be >= 0 and finite, atol must be >= 0 and finite, rtol + atol "
        "must be > 0, and safety, facmin, facmax, dtmin, dtmax, max_angle within their bounds (lierk.Controller); "
        "the states are NaN",
        12: "target_error " + _traced + "target_error must be > 0; the states are NaN",
        13: "a value of the problem " + _traced + "inertia must be positive definite (symmetric, finite); R0 must be "
        "a rotation matrix; omega0 must be finite, and a traced inertia and omega0 give a body state outside "
        "{dtype}'s range otherwise (lierk.checks.state_range_error); an effect's parameters must be in range "
        "(positive masses and gains, non-negative damping, positive-definite spin inertias, increasing sample "
        "times). The states are NaN; build the problem from the concrete values to see which",
    }
    # Bad inputs, in the order `solve` looks for them (`lierk._solve`).
    invalid = (invalid_times, invalid_step, invalid_save_times, invalid_tolerances, invalid_target, invalid_problem)
    # Codes that are not failures: `raise_if_failed` passes them and `Solution.ok` is true.
    finished = (successful, event_occurred)

    @classmethod
    def message(cls, code, dtype=None) -> str:
        """The message of ``code``; ``dtype``: the solve's float type, which
        `invalid_problem`'s names (default float64)."""
        return cls.messages[int(code)].replace("{dtype}", np.dtype(dtype or np.float64).name)


class SaveAt(eqx.Module):
    """Which states `solve` returns.  Several may be combined; they are stored in
    time order.

    Attributes:
        t0: the initial state.
        t1: the final state.
        steps: ``True`` for every step, or an int ``k`` for every k-th step
            (fixed-step solves).  Adaptive solves store every accepted step in
            buffers of length ``max_steps``, padded with ``inf`` times and NaN
            states; `Solution.n_saved` counts the valid entries.
        ts: ``(n,)`` non-decreasing times in ``[t0, t1]``.
            Steps are shortened to end exactly on each of them, so the saved
            states carry the solver's own accuracy, with no interpolation
            error; dense ``ts`` therefore cost steps.  With fixed steps
            (``dt=``) each gap between save times takes ``ceil(gap/dt)``
            steps, the last one shortened; the counts are computed at run
            time, so every ``dt`` and every ``ts`` of a length share one
            compilation and no ``max_steps`` is needed.  For many times, or an
            animation, ``dense=True`` and `Solution.evaluate` cost no steps.
        dense: keep every step's interpolant, for `Solution.evaluate` at any
            time (`lierk._interpolation`).  Memory O(steps): 352 to 448
            bytes a step for a rigid body in float64 (112 and the problem,
            once, for a splitting), for ``max_steps`` steps in an adaptive
            solve (see `lierk._interpolation.DenseInterpolation`); nothing is
            kept without it.  ``SaveAt(dense=True)`` alone also
            saves the final state, as ``t1=True`` does.
    """

    t0: bool = eqx.field(default=False, static=True)
    t1: bool = eqx.field(default=False, static=True)
    steps: bool | int = eqx.field(default=False, static=True)
    ts: Array | None = None
    dense: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        if isinstance(self.steps, bool):
            pass
        elif not (isinstance(self.steps, (int, np.integer)) and self.steps >= 1):
            raise ValueError(f"SaveAt(steps=...) must be True, False or a positive int, got {self.steps!r}")
        if not isinstance(self.dense, bool):
            raise ValueError(f"SaveAt(dense=...) must be True or False, got {self.dense!r}")
        if not (self.t0 or self.t1 or self.steps or self.ts is not None or self.dense):
            raise ValueError("SaveAt saves nothing: set t0, t1, steps, ts or dense")
        if self.ts is not None and np.ndim(self.ts) != 1:
            raise ValueError(f"SaveAt(ts=...) must be one-dimensional, got shape {np.shape(self.ts)}")

    @property
    def every(self) -> int:
        """Save every this-many steps (0 for none)."""
        return int(self.steps) if self.steps is not True else 1


class _Bound(eqx.Module):
    """``instance.method`` for `_plain_method`: a pytree like equinox's bound
    methods (the instance is its child), but hashed and compared by the
    instance's identity, as Python's bound methods are.  Equinox's hashes the
    instance's fields, and a solution's arrays cannot be hashed, so
    ``jax.jit(sol.evaluate)``, which hashes the function it compiles, raised
    ``TypeError: unhashable type``."""

    method: Any = eqx.field(static=True)
    instance: Any

    def __post_init__(self):
        # The method's name and docstring, for help() and tracebacks.
        for name in ("__module__", "__name__", "__qualname__", "__doc__"):
            setattr(self, name, getattr(self.method, name))

    def __call__(self, *args, **kwargs):
        return self.method(self.instance, *args, **kwargs)

    @property
    def __wrapped__(self):
        # For inspect.signature (jax.jit reads it): the method's own arguments.
        return self.method.__get__(self.instance, type(self.instance))

    def __hash__(self):
        return hash((id(self.instance), self.method))

    def __eq__(self, other):
        return isinstance(other, _Bound) and other.instance is self.instance and other.method is self.method


class _plain_method:
    """A method of an `eqx.Module` whose bound form is a `_Bound`: callable
    under ``jax.jit(instance.method)`` as any Python bound method is."""

    def __init__(self, method):
        self.method = method
        functools.update_wrapper(self, method)

    def __get__(self, instance, owner=None):
        return self.method if instance is None else _Bound(self.method, instance)


class Solution(eqx.Module):
    """A solved trajectory.  Leading batch axes appear in front under `vmap`.

    Attributes:
        ts: ``(..., n_save)`` times (s).
        R: ``(..., n_save, 3, 3)`` attitudes, body -> space.
        y: extra state at the saved times (leaves ``(..., n_save, *shape)``), or None.
        n_saved: ``(...)`` number of valid saved entries (the rest is padding).
        stats: dict of int arrays: ``num_steps`` (attempted), ``num_accepted_steps``,
            ``num_rejected_steps``, ``num_fevals``: evaluations of the
            vector field, those of the interpolants that dense output and
            events build included (`lierk.AbstractSolver.dense_fevals`; a
            JVP of the field counts as one); for the splittings, drifts
            (exact torque-free flows: each step also runs one kick more, and
            locating an event runs shortened steps, not counted).
        result: ``(...)`` int code from `RESULTS`; 0 is success.
        error_estimate: ``(..., n_save)`` estimate of the global attitude error
            ``||R(t) - R_exact(t)||_F`` at each saved time, from
            ``solve(..., estimate_error=True)`` or ``target_error=``; None
            otherwise.  ``inf`` where the finer solve behind it failed.
        interpolation: the dense output (`lierk._interpolation.DenseInterpolation`)
            with ``SaveAt(dense=True)``, else None; read it with `evaluate`.
        events: with ``solve(..., event=...)``, a `lierk.EventRecord` per
            event, shaped like the ``event`` argument (one record, or a tuple
            of them); else None.
    """

    ts: Array
    R: Array
    y: Any
    n_saved: Array
    stats: dict
    result: Array
    error_estimate: Array | None = None
    interpolation: Any = None
    events: Any = None

    @property
    def ok(self) -> Array:
        """Whether the solve finished: it reached ``t1``, or a terminating
        event stopped it (`RESULTS.finished`)."""
        return (self.result == RESULTS.successful) | (self.result == RESULTS.event_occurred)

    @_plain_method
    def evaluate(self, t) -> tuple[Array, Any]:
        """The attitude and extra state ``(R(t), y(t))`` at any time(s) ``t``
        (s) in ``[t0, t1]`` (to the event time if a terminating event stopped
        the solve), from the dense output: ``R(t) = R_n exp(hat(u(theta)))``
        with ``u`` the step's interpolant in the algebra, so ``R(t)`` is a
        rotation to rounding.  ``t`` is a scalar or an array of shape ``S``:
        ``R`` is ``S + (3, 3)``, each leaf of ``y`` gains ``S`` in front.
        Works under `jax.jit` and `jax.vmap` (for a batch of solutions, vmap
        over the solution: ``jax.vmap(lambda s, t: s.evaluate(t))(sol, t)``),
        and is differentiable in ``t`` and in the solve's inputs.

        Accuracy (`lierk._interpolation`):

        - The splittings: a fresh step of the method, of size ``t - t_n``,
          from the step's start.  Exact to rounding for a free body (1e-14,
          as at the steps), the method's own order with torques; between
          the steps the error is that at the steps (within 1.5 times in
          ``tests/test_dense.py``).  Each time evaluated costs a step of the
          method, and the first call compiles one (seconds for an
          asymmetric body's elliptic-function drift; concrete times share
          that program whatever their number).
        - DOP853: its order-7 continuous extension.
        - The other solvers: a quintic Hermite interpolant, order
          ``min(p, 5)``: order 4 for RKMK4 and CF4, 5 for DP54 and RKF45.
          Between the steps the error stays within a few times that at the
          steps while the body turns by well under 2 pi a step (up to 4.5
          rad: 1.7 times); at 5.8 to 6.4 rad a step it was 40 to 2500 times.

        Raises:
            ValueError: the solve was not asked for ``SaveAt(dense=True)``,
                or ``t`` lies outside the solved interval or is NaN.

        Example:
            >>> sol = lierk.solve(body, lierk.DOP853(), 10.0, rtol=1e-10,
            ...                   saveat=lierk.SaveAt(dense=True))
            >>> R, m = sol.evaluate(jnp.linspace(0.0, 10.0, 1000))   # (1000, 3, 3), (1000, 3)
        """
        if self.interpolation is None:
            raise ValueError(
                "Solution.evaluate needs the dense output: solve with saveat=lierk.SaveAt(dense=True, ...)"
            )
        return self.interpolation.evaluate(t)

    def invariants(self, problem) -> dict[str, Array]:
        """The problem's conserved quantities at each saved point."""
        return problem.invariants(self.R, self.y)

    def omega(self, problem) -> Array:
        """Body angular velocity (rad/s) at each saved point: ``(..., n_save, 3)``."""
        return problem.angular_velocity(self.R, self.y)

    def euler_angles(self, convention: str = "zyx") -> Array:
        """Euler angles (rad) at each saved point, ``(..., n_save, 3)``: see
        `lierk.so3.to_euler` (``"zyx"``, the report's, or ``"zxz"`` for tops)."""
        from .so3 import to_euler

        return to_euler(self.R, convention)

    def quaternion(self, scalar_first: bool = True) -> Array:
        """Unit quaternions of the saved attitudes, ``(..., n_save, 4)``:
        ``(w, x, y, z)``, or ``(x, y, z, w)`` (SciPy's default order) with
        ``scalar_first=False``; the sign with ``w >= 0`` (`lierk.so3.to_quaternion`)."""
        from .so3 import to_quaternion

        q = to_quaternion(self.R)
        return q if scalar_first else jnp.concatenate([q[..., 1:], q[..., :1]], axis=-1)

    def mrp(self) -> Array:
        """Modified Rodrigues parameters of the saved attitudes, ``(...,
        n_save, 3)``, Basilisk's ``sigma_BN``, switched to the shadow set so
        that ``|sigma| <= 1`` (`lierk.so3.to_mrp`)."""
        from .so3 import to_mrp

        return to_mrp(self.R)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, Any]:
        """The valid saved entries of one (unbatched) solve, in time order, as
        NumPy arrays for figures, files and diagnostics: ``ts`` ``(n,)`` (s),
        ``R`` ``(n, 3, 3)`` body -> space and ``y`` (leaves ``(n, ...)``),
        ``n = n_saved``.

        A solve cut short (a terminating event, ``max_steps``) keeps its
        final state in the last row when ``SaveAt(t1=True)`` asked for it
        (``sol.R[-1]`` is where it ended), after the rows it never reached
        (padding: NaN states); those rows are left out here.
        """
        ts = np.asarray(self.ts)
        if ts.ndim != 1:
            raise ValueError(f"this needs one trajectory, got a batch of solutions (ts has shape {ts.shape})")
        n, total = int(np.asarray(self.n_saved)), ts.shape[0]
        R = np.asarray(self.R)
        rows = np.arange(n)
        if 0 < n < total and np.isfinite(R[-1]).all() and not np.isfinite(R[n - 1]).all():
            # Row n - 1 is padding and the last row is the final state.
            rows = np.r_[np.arange(n - 1), total - 1]
        y = jax.tree_util.tree_map(lambda x: np.asarray(x)[rows], self.y)
        return ts[rows], R[rows], y

    def chosen_setting(self) -> str | None:
        """The setting a ``target_error=`` solve chose, as text (``"dt = 0.01
        s"`` or ``"rtol = atol = 1e-08"``); None for other solves.  Reads
        concrete values: call it outside `jax.jit`, on one solve."""
        if "dt" in self.stats:
            return f"dt = {float(self.stats['dt']):.4g} s"
        if "rtol" in self.stats:
            return f"rtol = atol = {float(self.stats['rtol']):.3g}"
        return None

    @property
    def orthogonality_error(self) -> Array:
        """``||R^T R - I||`` at each saved point: ``(..., n_save)``."""
        from .so3 import orthogonality_error

        return orthogonality_error(self.R)


def raise_if_failed(sol: Solution, throw: bool) -> Solution:
    """With ``throw``, turn a failed result into an error naming it (the
    event codes only when the solve had events): a `RuntimeError` at once
    when the result is known (read on the host, nothing compiled), one
    run-time check (`eqx.branched_error_if`) when it is traced."""
    if not throw:
        return sol
    failures = [
        (code, RESULTS.message(code, sol.R.dtype))
        for code in RESULTS.messages
        if code not in RESULTS.finished and not (code == RESULTS.event_condition_nan and sol.events is None)
    ]
    if not isinstance(sol.result, jax.core.Tracer):
        result = np.asarray(sol.result)
        for code, message in failures:
            if np.any(result == code):
                raise RuntimeError(f"lierk.solve failed: {message}")
        return sol
    codes = jnp.asarray([code for code, _ in failures], sol.result.dtype)
    hit = jnp.ravel(sol.result)[:, None] == codes  # (members, failures)
    index = jnp.argmax(jnp.any(hit, axis=0))
    messages = tuple(f"lierk.solve failed: {message}" for _, message in failures)
    return eqx.branched_error_if(sol, jnp.any(hit), index, messages)
