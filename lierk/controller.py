"""Step-size control for embedded pairs (Hairer, Norsett, Wanner I, II.4).

The error is measured in the Lie algebra: a step's estimate ``e_u`` is the
difference of the two solutions' increments ``u_high - u_low`` from the same
base point.  Attitude entries are O(1), so ``e_u`` is scaled by
``atol + rtol``; extra state ``y`` is scaled per component by
``atol + rtol * max(|y_0|, |y_1|)``.  All controller arithmetic runs under
`jax.lax.stop_gradient`: step sizes are not differentiated (otherwise
``0 * inf`` turns into NaN on the backward pass).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from . import _checks

__all__ = ["Controller"]


def _leaves(tree) -> list[Array]:
    return [jnp.ravel(x) for x in jax.tree_util.tree_leaves(tree)]


class Controller(eqx.Module):
    """Error-per-step controller ``h_new = h min(facmax, max(facmin, safety err^(-1/(q+1))))``.

    Every field is an array leaf, so sweeping tolerances never recompiles.

    Attributes:
        rtol, atol: relative and absolute tolerances (dimensionless; the
            attitude is O(1)).
        safety: 0.9 by default.
        facmin, facmax: bounds on the step-size ratio; ``facmax`` is 1 right
            after a rejection.
        dtmin: smallest allowed step (s); below it the solve stops with
            `RESULTS.dt_min_reached`.  Machine precision relative to ``t`` is
            always a floor.
        dtmax: largest allowed step (s).
    """

    rtol: Array
    atol: Array
    safety: Array
    facmin: Array
    facmax: Array
    dtmin: Array
    dtmax: Array

    def __init__(
        self,
        rtol: ArrayLike = 1e-6,
        atol: ArrayLike = 1e-9,
        *,
        safety: ArrayLike = 0.9,
        facmin: ArrayLike = 0.2,
        facmax: ArrayLike = 10.0,
        dtmin: ArrayLike = 0.0,
        dtmax: ArrayLike = float("inf"),
    ):
        def positive(name, x, allow_zero=False):
            x = _checks.asarray(x)
            if x.ndim != 0:
                raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(x)}")
            ok = (lambda v: v >= 0) if allow_zero else (lambda v: v > 0)
            return jnp.asarray(_checks.check(x, ok, f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {{value}}"))

        self.rtol = positive("rtol", rtol, allow_zero=True)
        self.atol = positive("atol", atol, allow_zero=True)
        _checks.check(self.rtol + self.atol, lambda v: v > 0, "rtol + atol must be > 0, got {value}")
        self.safety = positive("safety", safety)
        self.facmin = positive("facmin", facmin)
        self.facmax = positive("facmax", facmax)
        self.dtmin = positive("dtmin", dtmin, allow_zero=True)
        self.dtmax = positive("dtmax", dtmax)

    def norm(self, e_u: Array, e_y, y0, y1) -> Array:
        """RMS of the scaled error over the algebra's 3 components and y's."""
        terms = [e_u / (self.atol + self.rtol)]
        for e, a, b in zip(_leaves(e_y), _leaves(y0), _leaves(y1)):
            terms.append(e / (self.atol + self.rtol * jnp.maximum(jnp.abs(a), jnp.abs(b))))
        x = jnp.concatenate(terms)
        return jnp.sqrt(jnp.mean(x * x))

    def factor(self, err: Array, error_order: int, after_reject: Array) -> Array:
        """Step-size ratio for the next attempt from a step's error norm."""
        err = jax.lax.stop_gradient(err)
        safe = jnp.where(err > 0, err, 1.0)
        fac = jnp.where(err > 0, self.safety * safe ** (-1.0 / (error_order + 1)), self.facmax)
        facmax = jnp.where(after_reject, 1.0, self.facmax)
        return jnp.clip(jnp.where(jnp.isfinite(fac), fac, self.facmin), self.facmin, facmax)
