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


MOST_STEPS_LOOPED = 4096
"""The most steps (``max_steps``, or a fixed-step solve's count) of one
body's solve that takes its solver's faster-compiling form
(`AbstractSolver.for_one_body`).  DOP853's stage loop runs each step of a
heavy top in 9.1 us against 2.7 unrolled (from Python, 2 cores) and
compiles 0.6 to 0.9 s sooner: ahead until about 100,000 steps over all
calls.  At the adaptive solves' default of 4096 steps a call costs at most
26 ms more, and most take far fewer steps."""


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
        its first stage from there (`dense_serves_first_stage`)."""
        if fsal is None and node is not None:
            fsal = node[0]
        st = self.step(problem, t, h, R, y, fsal)
        node1 = interpolation.node(problem, t + h, st.R, st.y)
        return st, interpolation.hermite(h, R, y, node, st.R, st.y, node1), node1

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

    def for_derivatives(self, one_body: bool = False) -> "AbstractSolver":
        """This solver as a differentiated solve takes it: itself, unless a
        form that compiles faster pays there (`lierk.AbstractRKMK`).
        ``one_body``: the derivative of one body's solve, no batch (a
        `jax.jacfwd` of it inside a caller's `jax.jit`, or from Python),
        where a form that compiles faster pays sooner."""
        return self

    def for_one_body(self, max_steps: int | None, derivatives: bool = False) -> "AbstractSolver":
        """This solver as a solve of one body of at most ``max_steps`` steps
        takes it: on the CPU, and for at most 4096 steps
        (``lierk._solvers.base.MOST_STEPS_LOOPED``, the adaptive solves'
        default ``max_steps``), the form a differentiated solve takes
        (`for_derivatives`); otherwise itself (None: a count known only at
        run time).  One body's solve: `lierk.solve` called from Python, or
        traced inside a caller's ``jax.jit`` that no ``jax.vmap`` batches (a
        batch, now or later, takes the solver as given:
        `lierk._own_programs.OwnProgram`).  A short solve pays for compiling
        sooner: from Python lierk's per-call work on the host is most of
        each later call's time, and inside a caller's ``jit`` it would run
        thousands of times before a faster run paid for a slower compile.
        A long one does not.  ``derivatives``: the form for the derivative of
        one body's solve (`for_derivatives` with ``one_body=True``)."""
        if jax.default_backend() != "cpu" or max_steps is None or max_steps > MOST_STEPS_LOOPED:
            return self
        return self.for_derivatives(one_body=derivatives)

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
