"""Runge-Kutta-Munthe-Kaas methods driven by any explicit Butcher tableau.

In body form, with ``R(t) = R_n exp(hat(u(t)))``, the attitude equation
``dR/dt = R hat(omega)`` becomes an ODE in the algebra,

    u' = dexpinv(-u, omega(R_n exp(u)))
       = omega + 1/2 u x omega + D(|u|) u x (u x omega),

to which the tableau is applied; the step is ``R_{n+1} = R_n exp(hat(u_1))``.
`so3.dexpinv` is exact, so the method has the tableau's order (Munthe-Kaas,
Appl. Numer. Math. 29, 1999).  Extra state ``y`` is advanced by the same
tableau in R^n.  An embedded pair's error estimate is taken in the algebra
(``e_u``) and in ``y`` (``e_y``); both solutions start from the same base point.
"""

from __future__ import annotations

import copy
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .. import so3
from ..tableaux import DOP853 as _DOP853
from ..tableaux import DOPRI54, FEHLBERG45, RK4, ButcherTableau, blend_estimates
from .base import AbstractSolver, Step


def _stage_sums(h, rows, ks):
    """``[h * sum_j row[j] ks[j] for row in rows]`` as one small matrix
    product: it makes XLA materialise the stage values once instead of
    re-deriving them inside every later stage's fused kernel (which made long
    tableaux several times slower per stage), and one product serves all the
    rows (the step and both error estimates of DOP853).  ``ks``: a list of
    flat stage slopes, or their stack ``(s, n)`` (`AbstractRKMK`'s stage
    loop)."""
    if not isinstance(ks, list):
        # A reduction, not a matrix product: with h folded in, one kernel.
        coeffs = jnp.asarray([list(r) + [0.0] * (ks.shape[0] - len(r)) for r in rows], ks.dtype)
        return list(jnp.sum((h * coeffs)[:, :, None] * ks[None], axis=1))
    idx = [j for j in range(len(ks)) if any(r[j] != 0.0 for r in rows)]
    if len(idx) == 1:
        return [(h * r[idx[0]]) * ks[idx[0]] for r in rows]
    K = jnp.stack([ks[j] for j in idx])
    coeffs = jnp.asarray([[r[j] for j in idx] for r in rows], K.dtype)
    return list(h * (coeffs @ K))


def _add(y, dy):
    return None if y is None else jax.tree_util.tree_map(jnp.add, y, dy)


class AbstractRKMK(AbstractSolver):
    """RKMK stepping for ``self.tableau``; subclasses fix the tableau.

    Attributes:
        compact: how the step is written into the compiled program.  True:
            one body's compact form, the stages in a loop
            (`jax.lax.fori_loop`) and the step's helpers compact, which
            compiles several times faster for the long tableaux and runs
            each step slower; False: every stage written out, the fastest
            to run, above all for a batch; None (default): as
            `lierk._programs`' rule decides for each call (one body's solve
            of at most 4096 steps on the CPU, compact for tableaux of five or
            more stages; a batch, unrolled).  The same numbers to rounding
            either way.  Static: each setting is its own program.
    """

    tableau: eqx.AbstractClassVar[ButcherTableau]
    compact: bool | None = eqx.field(default=None, static=True, kw_only=True)
    # How much of dexpinv the stages apply: None = the exact closed form; an int
    # keeps the series up to ad_u^k (see `so3.dexpinv`).  The report's "RK4"
    # applies none of it (0), which is why it is only order 2.
    dexpinv_terms: ClassVar[int | None] = None

    def __check_init__(self):
        if self.compact not in (None, True, False):
            raise ValueError(f"compact must be True, False or None (automatic), got {self.compact!r}")

    def in_form(self, compact: bool) -> "AbstractRKMK":
        if self.compact is not None:
            return self
        # Not `dataclasses.replace`: that calls the class's own `__init__`,
        # whose arguments a subclass may have changed.
        formed = copy.copy(self)
        object.__setattr__(formed, "compact", compact)
        return formed

    @property
    def order(self) -> int:  # type: ignore[override]
        return self.tableau.order

    @property
    def stages(self) -> int:  # type: ignore[override]
        return self.tableau.stages

    @property
    def adaptive(self) -> bool:  # type: ignore[override]
        return self.tableau.b_error is not None

    @property
    def error_order(self):  # type: ignore[override]
        return self.tableau.error_order

    def _stage(self, problem, base, t, h, y, du, ci, unravel):
        """One stage at node ``ci`` from its stage sum ``du`` (flat, the
        algebra's and y's): its flat slope ``(k, ydot)`` and its field
        ``(omega, ydot)``.  Both forms and the continuous extension's stages
        take it."""
        u, dy = unravel(du)
        # One evaluation serves the effects' rotations and dexpinv.
        coefficients = so3._coefficients(so3._sq(u), bool(self.compact))
        omega, ydot = problem.local(base, t + ci * h, u, _add(y, dy), coefficients)
        k = so3.dexpinv(-u, omega, self.dexpinv_terms, coefficients)
        return ravel_pytree((k, ydot))[0], (omega, ydot)

    def _stages(self, problem, t, h, R, y, fsal, c, a):
        """The stage slopes for nodes ``c`` and rows ``a``: ``(ks, unravel,
        (omega, ydot))``, each ``ks[i]`` the flat ``(k_i, ydot_i)`` of one
        stage (a list; their stack ``(s, n)`` when ``compact``, looped) and
        ``(omega, ydot)`` the last stage's field."""
        base = problem.base(t, R, y)
        omega, ydot = fsal if fsal is not None else problem.at(base, t, y)
        # omega and the algebra slope k share a shape, so one unravel serves
        # both.  Each stage's algebra slope and y slope are one flat vector,
        # so every stage sum (for u and y together) is a single small matrix
        # product (`_stage_sums`).
        k0, unravel = ravel_pytree((omega, ydot))
        if not self.compact:
            ks, last = [k0], (omega, ydot)
            for i in range(1, len(c)):
                (du,) = _stage_sums(h, [a[i]], ks)
                k, last = self._stage(problem, base, t, h, y, du, c[i], unravel)
                ks.append(k)
            return ks, unravel, last
        # The loop holds one stage whatever the tableau; the slopes live in
        # one array ``(s, n)`` that each stage reads through its row of
        # ``a`` (zero-padded, so every row is a product with all ``s``).
        s = len(c)
        rows = np.zeros((s, s))
        for i in range(1, s):
            rows[i, :i] = a[i]
        rows, nodes = jnp.asarray(rows, k0.dtype), jnp.asarray(c, k0.dtype)

        # The stage's row is read and its slope written without JAX's index
        # normalisation and bounds checks (i runs over 1..s-1), and the stage
        # sum is a reduction rather than a matrix product: XLA compiles each
        # of those as a kernel of its own.
        def stage(i, carry):
            ks, _ = carry
            row = jax.lax.dynamic_index_in_dim(rows, i, keepdims=False, allow_negative_indices=False)
            k, last = self._stage(problem, base, t, h, y, jnp.sum((h * row)[:, None] * ks, axis=0), nodes[i], unravel)
            ks = jax.lax.dynamic_update_index_in_dim(ks, k, i, 0, allow_negative_indices=False)
            return ks, ravel_pytree(last)[0]

        ks = jnp.zeros((s,) + k0.shape, k0.dtype).at[0].set(k0)
        ks, last = jax.lax.fori_loop(1, s, stage, (ks, k0))
        return ks, unravel, unravel(last)

    def _step(self, problem, t, h, R, y, fsal):
        tab = self.tableau
        ks, unravel, last = self._stages(problem, t, h, R, y, fsal, tab.c, tab.a)
        rows = [r for r in (tab.b, tab.b_error, tab.b_error3) if r is not None]
        sums = [unravel(x) for x in _stage_sums(h, rows, ks)]
        u1, dy1 = sums[0]
        y1 = _add(y, dy1)
        error = None if tab.b_error is None else tuple(tuple(e) for e in sums[1:])
        R1 = so3._right_exp(R, u1, bool(self.compact))
        return Step(R1, y1, error, last if tab.fsal else None), ks, unravel

    def step(self, problem, t, h, R, y, fsal=None):
        return self._step(problem, t, h, R, y, fsal)[0]

    def dense_node(self, problem, t, R, y):
        return None if self.tableau.dense else super().dense_node(problem, t, R, y)

    @property
    def dense_fevals(self) -> tuple[int, int]:
        """A continuous extension's extra stages, in every step (no node);
        else the Hermite interpolant's (`AbstractSolver.dense_fevals`)."""
        return (len(self.tableau.dense_c), 0) if self.tableau.dense else super().dense_fevals

    @property
    def dense_in_step(self) -> bool:
        """A continuous extension continues the step's own stages."""
        return bool(self.tableau.dense)

    @property
    def dense_serves_first_stage(self) -> bool:  # type: ignore[override]
        """The Hermite node's field serves the first stage; a continuous
        extension keeps no node."""
        return not self.tableau.dense

    @property
    def dense_rebuild_fevals(self) -> int:
        """A continuous extension's: the step again and its extra stages."""
        tab = self.tableau
        return tab.stages + len(tab.dense_c) if tab.dense else super().dense_rebuild_fevals

    def dense_between(self, problem, t, h, R, y, R1, y1):
        """A continuous extension continues the step's own stages: the step
        is taken again (events do not, `dense_in_step`)."""
        if not self.tableau.dense:
            return super().dense_between(problem, t, h, R, y, R1, y1)
        return self.dense_step(problem, t, h, R, y)[1]

    def dense_step(self, problem, t, h, R, y, fsal=None, node=None):
        tab = self.tableau
        if not tab.dense:
            return super().dense_step(problem, t, h, R, y, fsal, node)
        st, ks, unravel = self._step(problem, t, h, R, y, fsal)
        ks = list(ks)
        # The extension's extra stages continue the same RKMK stages (the
        # ODE for u at R_n), after the tableau's own.
        s = tab.stages
        c = tab.c + tab.dense_c
        a = tab.a + tab.dense_a
        base = problem.base(t, R, y)
        for i in range(s, len(c)):
            (du,) = _stage_sums(h, [a[i]], ks)
            ks.append(self._stage(problem, base, t, h, y, du, c[i], unravel)[0])
        F = jnp.stack(_stage_sums(h, list(tab.dense_b), ks))
        Fu, Fy = jax.vmap(unravel)(F)
        return st, (Fu, Fy), None

    def error_norm(self, error, norm):
        if len(error) == 1:
            return norm(*error[0])
        # DOP853's two estimates (`tableaux.blend_estimates`); both 0 give 0.
        # Their norms as one batched reduction: one XLA kernel, not two.
        err, e3 = jax.vmap(norm)(*jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), *error))
        both = (err > 0) | (e3 > 0)
        blend = jnp.where(both, blend_estimates(err, jnp.where(both, e3, 1.0), jnp.sqrt), 0.0)
        # A rejected stage (inf) must stay inf: inf/inf would be NaN.
        return jnp.where(jnp.isfinite(err) & jnp.isfinite(e3), blend, jnp.inf)


class RKMK(AbstractRKMK):
    """RKMK with any explicit `ButcherTableau` (exact dexpinv): order = the tableau's.

    Example:
        >>> solver = lierk.RKMK(lierk.tableaux.RK4)
    """

    tableau: ButcherTableau = eqx.field(static=True)

    @property
    def name(self) -> str:
        """``"RKMK(DOP853)"``: lierk's tableaux by their constant in
        `lierk.tableaux`, others by their own name."""
        from .. import tableaux

        label = next((k for k, v in vars(tableaux).items() if v is self.tableau), self.tableau.name)
        return f"RKMK({label})"


class RKMK4(AbstractRKMK):
    """Munthe-Kaas RK4: the classical tableau with dexpinv up to ``ad_u^2``,

        u' = omega + 1/2 u x omega + 1/12 u x (u x omega),

    which is all that order 4 needs (Munthe-Kaas 1999; stopping after the first
    commutator gives order 3).  Dropping the exact ``D(|u|)`` removes the
    singularity of dexpinv at ``|u| = 2 pi`` and a division per stage.
    `RKMK(tableaux.RK4)` is the same method with exact dexpinv.
    """

    tableau: ClassVar[ButcherTableau] = RK4
    dexpinv_terms: ClassVar[int | None] = 2


class NaiveLieRK4(AbstractRKMK):
    """The report's "RK4" as written (section 3.6.2, oppg4.py): stages at
    ``W exp(c h S)``, step ``W exp(h/6 (S1 + 2 S2 + 2 S3 + S4))``, no dexpinv.

    Order 2 in general.  It is exact on the report's sphere test only because
    there all stages commute; on any non-symmetric body halving ``h`` divides
    the error by 4, not 16.
    """

    tableau: ClassVar[ButcherTableau] = RK4
    dexpinv_terms: ClassVar[int | None] = 0

    @property
    def order(self) -> int:  # type: ignore[override]
        return 2


class RKF45(AbstractRKMK):
    """RKMK with the report's Fehlberg 4(5) pair, advancing with order 5."""

    tableau: ClassVar[ButcherTableau] = FEHLBERG45


class DP54(AbstractRKMK):
    """RKMK with Dormand-Prince 5(4), FSAL: 6 new field evaluations per accepted step."""

    tableau: ClassVar[ButcherTableau] = DOPRI54


class DOP853(AbstractRKMK):
    """RKMK with Dormand-Prince 8(5,3), FSAL: order 8, for tight tolerances."""

    tableau: ClassVar[ButcherTableau] = _DOP853
