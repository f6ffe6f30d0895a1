"""What `solve` returns, what it saves, and how it reports failure."""

from __future__ import annotations

from typing import Any

import equinox as eqx
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
    }

    @classmethod
    def message(cls, code) -> str:
        return cls.messages[int(code)]


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
        ts: ``(n,)`` non-decreasing times in ``[t0, t1]`` (adaptive solves).
            Steps are shortened to end exactly on each of them, so the saved
            states carry the solver's own accuracy, with no interpolation
            error; dense ``ts`` therefore cost steps.
    """

    t0: bool = eqx.field(default=False, static=True)
    t1: bool = eqx.field(default=False, static=True)
    steps: bool | int = eqx.field(default=False, static=True)
    ts: Array | None = None

    def __check_init__(self):
        if isinstance(self.steps, bool):
            pass
        elif not (isinstance(self.steps, (int, np.integer)) and self.steps >= 1):
            raise ValueError(f"SaveAt(steps=...) must be True, False or a positive int, got {self.steps!r}")
        if not (self.t0 or self.t1 or self.steps or self.ts is not None):
            raise ValueError("SaveAt saves nothing: set t0, t1, steps or ts")
        if self.ts is not None and np.ndim(self.ts) != 1:
            raise ValueError(f"SaveAt(ts=...) must be one-dimensional, got shape {np.shape(self.ts)}")

    @property
    def every(self) -> int:
        """Save every this-many steps (0 for none)."""
        return int(self.steps) if self.steps is not True else 1


class Solution(eqx.Module):
    """A solved trajectory.  Leading batch axes appear in front under `vmap`.

    Attributes:
        ts: ``(..., n_save)`` times (s).
        R: ``(..., n_save, 3, 3)`` attitudes, body -> space.
        y: extra state at the saved times (leaves ``(..., n_save, *shape)``), or None.
        n_saved: ``(...)`` number of valid saved entries (the rest is padding).
        stats: dict of int arrays: ``num_steps`` (attempted), ``num_accepted_steps``,
            ``num_rejected_steps``, ``num_fevals``.
        result: ``(...)`` int code from `RESULTS`; 0 is success.
        error_estimate: ``(..., n_save)`` estimate of the global attitude error
            ``||R(t) - R_exact(t)||_F`` at each saved time, from
            ``solve(..., estimate_error=True)`` or ``target_error=``; None
            otherwise.  ``inf`` where the finer solve behind it failed.
    """

    ts: Array
    R: Array
    y: Any
    n_saved: Array
    stats: dict
    result: Array
    error_estimate: Array | None = None

    @property
    def ok(self) -> Array:
        return self.result == RESULTS.successful

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
    """With ``throw``, turn a non-success result into a run-time error naming it."""
    if not throw:
        return sol
    for code, message in RESULTS.messages.items():
        if code != RESULTS.successful:
            sol = eqx.error_if(sol, jnp.any(sol.result == code), f"lierk.solve failed: {message}")
    return sol
