"""What every solver provides, and the record of one step."""

from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
from jax import Array

from .. import _interpolation as interpolation


class Step(NamedTuple):
    """The outcome of one step from ``(t, R, y)`` with step size ``h``.

    Attributes:
        R: ``(3, 3)`` attitude at ``t + h``.
        y: extra state at ``t + h`` (pytree or None).
        error: the embedded error estimates, a tuple of ``(e_u, e_y)`` pairs
            (in the algebra, rad, and in y), or None for a method without
            one.  Most pairs give one estimate; `AbstractSolver.error_norm`
            turns them into the single norm step control uses.
        fsal: field value at the new point, reusable as the next step's first
            stage (``(omega, dy/dt)``), or None.
    """

    R: Array
    y: Any
    error: tuple | None
    fsal: Any


class AbstractSolver(eqx.Module):
    """An immutable solver with a pure `step`.

    Class attributes:
        order: global order of accuracy on a generic (non-commuting) problem.
        stages: field evaluations per step.
        adaptive: whether `step` returns an embedded error estimate.
    """

    order: ClassVar[int]
    stages: ClassVar[int] = 1
    adaptive: ClassVar[bool] = False
    error_order: ClassVar[int | None] = None
    # Why this solver's steps have no interpolant (so no dense output and no
    # events), or None: tools ask it before they add an event of their own.
    no_interpolant: ClassVar[str | None] = None
    # Whether `dense_step`, given no ``fsal``, serves the step's first stage
    # from the start point's node (the field there), so that a step with its
    # interpolant costs one field evaluation fewer than `step` and the node
    # apart: a solver whose `step` takes a given ``fsal`` as its first stage,
    # with the Hermite `dense_step` (`LieEuler`, `CF4`, an RKMK tableau
    # without a continuous extension).  False by default, so that the counts
    # of a solver of one's own that evaluates its first stage anyway are
    # right.  A fixed-step solve with events or dense output passes no
    # ``fsal``, nor does an adaptive one whose controller keeps no field
    # (``init``'s ``f0`` None).
    dense_serves_first_stage: ClassVar[bool] = False

    @property
    def dense_in_step(self) -> bool:
        """Whether the step's interpolant comes from the step's own stages (a
        continuous extension, `lierk.AbstractRKMK` with DOP853's), so that
        building it apart means taking the step again: events then build it
        in every step.  False here: the Hermite interpolant is built from
        the step's ends, which events do only in a step where a condition
        changed sign (`lierk._event`)."""
        return False

    @property
    def dense_rebuild_fevals(self) -> int:
        """Field evaluations that building one step's interpolant apart costs
        (`dense_between`): what an event adds in each step where a condition
        changed sign, for a solver whose interpolant is not `dense_in_step`.
        Here the Hermite node at both ends: the start's and the end's counts
        in `dense_fevals`."""
        per_step, initial = self.dense_fevals
        return per_step + initial

    def step(self, problem, t: Array, h: Array, R: Array, y: Any, fsal: Any = None) -> Step:
        raise NotImplementedError

    def dense_node(self, problem, t: Array, R: Array, y: Any) -> Any:
        """What `dense_step` needs to know about the point a step starts
        from, computed once per point (the end of one step is the start of
        the next): here `lierk._interpolation.node`, the field and its rate."""
        return interpolation.node(problem, t, R, y)

    def dense_step(self, problem, t: Array, h: Array, R: Array, y: Any, fsal: Any = None, node: Any = None):
        """`step`, and the step's interpolant for dense output and events:
        ``(Step, (F_u, F_y), node)``, with the coefficients of
        `lierk._interpolation` and ``node`` the `dense_node` of the new point.
        Here a quintic Hermite interpolant from the ends of the step
        (`lierk._interpolation.hermite`); a tableau with a continuous extension
        uses that instead (`lierk.AbstractRKMK`), and the splittings keep no
        coefficients and take a shortened step (`dense_partial`).  The node
        holds the field at the start point: given no ``fsal``, the step takes
        its first stage from there (`dense_serves_first_stage`).  A solver
        with a `no_interpolant` reason raises it (ValueError)."""
        self._check_interpolant()
        if fsal is None and node is not None:
            fsal = node[0]
        st = self.step(problem, t, h, R, y, fsal)
        node1 = interpolation.node(problem, t + h, st.R, st.y)
        return st, interpolation.hermite(h, R, y, node, st.R, st.y, node1), node1

    def dense_between(self, problem, t: Array, h: Array, R: Array, y: Any, R1: Array, y1: Any) -> tuple:
        """The interpolant's coefficients ``(F_u, F_y)`` of `dense_step`, for
        the step of size ``h`` (s) from ``(R, y)`` at ``t`` that ended at
        ``(R1, y1)``, built apart from the step (events do so only in a step
        where a condition changed sign).  Here the quintic Hermite interpolant
        from the `dense_node` at both ends, without taking the step again.
        A solver whose `dense_step` builds another interpolant overrides this
        too, or sets `dense_in_step`.  A solver with a `no_interpolant`
        reason raises it (ValueError)."""
        self._check_interpolant()
        node0 = self.dense_node(problem, t, R, y)
        node1 = self.dense_node(problem, t + h, R1, y1)
        return interpolation.hermite(h, R, y, node0, R1, y1, node1)

    def _check_interpolant(self) -> None:
        if self.no_interpolant is not None:
            raise ValueError(self.no_interpolant)

    @property
    def dense_fevals(self) -> tuple[int, int]:
        """Field evaluations that dense output and events add: ``(per step
        attempted, once at the start)``.  Here the Hermite interpolant's
        `dense_node` at each step's end and at ``t0``: the field and its rate
        along the motion (a JVP, counted as one evaluation), 2 each (less
        the first stage the node serves, `dense_serves_first_stage`)."""
        return 2, 2

    def dense_partial(self, problem) -> Any:
        """The interpolant that replaces the coefficients of `dense_step`
        when it is a shortened step of the solver
        (`lierk._interpolation.PartialStep`, the splittings'); None here.
        Read by the fixed-step loop only: no adaptive solver has one."""
        return None

    def error_norm(self, error: tuple, norm) -> Array:
        """One scaled error norm from `Step.error`, with ``norm(e_u, e_y)``
        the controller's (RMS over the scaled components).  One estimate:
        its norm."""
        return norm(*error[0])

    def in_form(self, compact: bool) -> "AbstractSolver":
        """This solver in the form `lierk._programs`' rule chose: ``compact``
        for one body's compact form, else the batch form.  Itself here: only
        a solver with more than one form (`lierk.AbstractRKMK`) changes, and
        only where its form was not fixed by the user."""
        return self

    @property
    def name(self) -> str:
        return type(self).__name__


def field_at(problem, t, R, y):
    """The field ``(omega, dy/dt)`` at ``(t, R, y)``: body angular velocity
    ``(3,)`` (rad/s) and the extra state's rate."""
    return problem.at(problem.base(t, R, y), t, y)


def combine(x, h, coeffs, ks):
    """``x + h * sum_i coeffs[i] * ks[i]`` leaf by leaf over pytrees, skipping
    exact zeros at trace time (tableaux are constants)."""
    terms = [(c, k) for c, k in zip(coeffs, ks) if c != 0.0]

    def leaf(x0, *kk):
        acc = None
        for (c, _), k in zip(terms, kk):
            acc = c * k if acc is None else acc + c * k
        if acc is None:
            return x0
        return h * acc if x0 is None else x0 + h * acc

    if x is None:
        return jax.tree_util.tree_map(lambda *kk: leaf(None, *kk), *[k for _, k in terms]) if terms else None
    return jax.tree_util.tree_map(leaf, x, *[k for _, k in terms])
