"""`solve_sampled`: a body under a control law that is sampled at a fixed
rate and held in between (a zero-order hold), as flight software runs one.

Each period is one `lierk.solve` of the problem with the command put in
place, started where the last period ended; a `lax.scan` over the periods
keeps the whole run one program, so new commands, gains or states never
recompile it, and `jax.grad` goes through it (each period is recomputed in
the backward pass, so reverse mode holds one state per period, not the
steps inside it).
"""

from __future__ import annotations

from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from . import _validation as validation
from ._loops import num_steps
from ._problems import AbstractProblem
from ._programs import Program
from ._solution import RESULTS, Solution, raise_if_failed
from ._solve import solve
from ._solvers.base import AbstractSolver

__all__ = ["solve_sampled"]

# What each period's solve decides itself.
_OWN_OPTIONS = ("t0", "t1", "saveat", "estimate_error", "target_error", "event", "throw")


def solve_sampled(
    problem: AbstractProblem,
    solver: AbstractSolver,
    law: Callable,
    control: Callable,
    period: ArrayLike,
    n: int,
    *,
    t0: ArrayLike = 0.0,
    throw: bool = True,
    **options,
) -> tuple[Solution, Any]:
    """Solve ``problem`` under a control law sampled every ``period`` seconds
    and held constant until the next sample (a zero-order hold), for ``n``
    periods.

    At each sample time ``t_k = t0 + k period`` (``k = 0 .. n-1``) the law
    computes a command from the state, ``u_k = law(k, t_k, R, y)``, the
    command replaces the leaves of the problem that ``control`` selects
    (as `equinox.tree_at`'s ``where``), and one `lierk.solve` takes the body
    to ``t_{k+1}``.  ``law`` may read the state (a feedback law: an MRP
    proportional-derivative law, a momentum dump) or only ``k`` (an
    open-loop sequence of commands, ``lambda k, t, R, y: U[k]``, whose
    samples ``U`` are then parameters to differentiate).  The periods run in
    a `lax.scan`, so the whole run is one program: inside `jax.jit` (with
    `jax.vmap` for a batch of bodies, `jax.grad` with respect to gains or
    commands) new values of the commands, gains, states or ``period``
    reuse the compiled program.  Called from Python it is one program too,
    kept for the same ``law`` and ``control`` functions and step options (a
    new lambda, or a new ``dt``, compiles again).

    In reverse mode each period is recomputed in the backward pass
    (`jax.checkpoint`), so the memory held is one state per period plus one
    period's steps (fixed steps: blocks of about ``sqrt(steps)`` from 256
    steps on), not every step of the run
    (``tests/test_design.py`` measures it).  The derivative is that of the
    solves that were run, each period's as `lierk.solve` gives it with the
    ``adjoint=`` passed (with a state, a command and maybe gains perturbed,
    a period has more than `lierk.ForwardSensitivity`'s 6 inputs, so fixed
    steps go through the scan's own reverse mode; for adaptive steps pass
    ``adjoint=lierk.RecursiveCheckpointAdjoint()``).

    Args:
        problem: the problem at ``t0`` (its ``R0`` and ``y0``), with the
            leaves ``control`` selects in place (e.g. a
            `lierk.ReactionWheels` built with ``torque=jnp.zeros(k)``: a
            constant motor torque per wheel).
        solver: e.g. `lierk.RKMK4()`, or an adaptive one with ``rtol=``.
        law: ``(k, t, R, y) -> u``: ``k`` the sample's index (an int
            scalar), ``t`` its time (s), ``R`` ``(3, 3)`` the attitude
            (body -> space) and ``y`` the problem's state there (for
            `lierk.RigidBodyWithEffects` the body momentum ``m``, or
            ``(m, wheel_speeds)`` with reaction wheels); ``u`` has the
            structure and shapes of what ``control`` selects.
        control: ``problem -> leaf`` (or a tuple of leaves): where the
            command goes, e.g. ``lambda p: p.effects[0].torques``.
        period: the sampling period (s), ``> 0``.
        n: the number of periods, a Python int ``>= 1``.
        t0: the first sample's time (s).
        throw: raise if a period's solve failed (the result code is the
            first failure's).
        **options: `lierk.solve`'s options for each period: ``dt=`` (fixed
            steps; ``period/dt`` steps a period, counted once here from
            concrete values, or give ``max_steps``), or ``rtol=``/``atol=``
            or ``controller=`` (adaptive), ``adjoint=``, ``max_steps=``.
            ``saveat``, ``t0``, ``t1`` and the error estimates are this
            function's.

    Returns:
        ``(sol, commands)``: a `lierk.Solution` at the ``n + 1`` sample
        times ``t0, t0 + period, ..., t0 + n period`` (``ts`` ``(n + 1,)``,
        ``R`` ``(n + 1, 3, 3)``, each leaf of ``y`` with ``n + 1`` in
        front; ``stats`` summed over the periods), and the commands, each
        leaf with ``n`` in front: ``u_k`` was held from ``ts[k]`` to
        ``ts[k + 1]``.

    Example:
        >>> wheels = lierk.ReactionWheels(jnp.eye(3), jnp.full(3, 0.01), jnp.zeros(3), torque=jnp.zeros(3))
        >>> body = lierk.RigidBodyWithEffects(I, omega0, effects=(wheels,))
        >>> def law(k, t, R, y):            # motor torques from the body momentum, once a second
        ...     return 0.05 * y[0]
        >>> sol, u = lierk.solve_sampled(body, lierk.RKMK4(), law, lambda p: p.effects[0].torques,
        ...                              1.0, 300, dt=0.1)
    """
    if not isinstance(problem, AbstractProblem):
        raise ValueError(f"problem must be a lierk problem such as RigidBodyWithEffects, got {type(problem).__name__}")
    if not callable(law):
        raise ValueError(f"law must be a function (k, t, R, y) -> command, got {law!r}")
    if not callable(control):
        raise ValueError(f"control must be a function problem -> the leaf the command replaces, got {control!r}")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n, the number of periods, must be a Python int >= 1, got {n!r}")
    own = sorted(k for k in options if k in _OWN_OPTIONS)
    if own:
        raise ValueError(f"solve_sampled sets {', '.join(own)} of each period's solve itself; leave them out")
    dtype = problem.R0.dtype
    period = validation.check_scalar(period, "period", dtype, bound="positive")
    t0 = validation.check_scalar(t0, "t0", dtype)
    for name in ("dt", "dt0", "rtol", "atol"):
        if options.get(name) is not None and not validation.is_traced(options[name]):
            # Checked here, and a Python number from here on: the program
            # below keeps it as a constant, so each solve still sees it.
            bound = "positive" if name.startswith("dt") else "non-negative"
            options[name] = float(validation.check_scalar(options[name], name, dtype, bound=bound))
    if options.get("dt") is not None and options.get("max_steps") is None:
        if validation.is_traced(period, options["dt"]):
            raise ValueError(
                "period or dt is traced, so the steps a period takes cannot be counted: pass max_steps=, "
                "a Python int with max_steps * dt >= period"
            )
        options["max_steps"] = num_steps(0.0, period, options["dt"])

    slots = control(problem)
    if any(leaf is None for leaf in jax.tree_util.tree_leaves(slots, is_leaf=lambda x: x is None)):
        raise ValueError(
            "control selects None: build the problem with the command's leaf in place (a ReactionWheels with "
            "torque=jnp.zeros(k), a BodyTorque(jnp.zeros(3))), so that each command replaces it"
        )
    shape = jax.eval_shape(
        law, jax.ShapeDtypeStruct((), jnp.int32), jax.ShapeDtypeStruct((), dtype), problem.R0, problem.y0
    )
    want = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)), slots)
    if jax.tree_util.tree_structure(shape) != jax.tree_util.tree_structure(want) or any(
        a.shape != b.shape for a, b in zip(jax.tree_util.tree_leaves(shape), jax.tree_util.tree_leaves(want))
    ):
        raise ValueError(
            f"law returns {_shapes(shape)}, but control selects {_shapes(want)}: the command must have the "
            "structure and shapes of the leaves it replaces"
        )

    sol, u = _sampled(problem, solver, law, control, slots, period, n, t0, options)
    return raise_if_failed(sol, throw), u


# One program for the whole run when called from Python (the scan and what
# assembles its output; eager, each of those operations compiled a program
# of its own), chosen by `lierk._programs`' rule like `solve`'s.
@Program
def _sampled(problem, solver, law, control, slots, period, n, t0, options):
    dtype = problem.R0.dtype

    def one(state, k):
        R, y = state
        t = t0 + k.astype(dtype) * period
        u = law(k, t, R, y)
        u = jax.tree_util.tree_map(lambda v, s: jnp.asarray(v, jnp.result_type(s)), u, slots)
        sol = solve(eqx.tree_at(control, problem.restart(R, y), u), solver, t + period, t0=t, throw=False, **options)
        end = (sol.R[-1], jax.tree_util.tree_map(lambda a: a[-1], sol.y))
        return end, (end, u, sol.stats, sol.result)

    # Reverse mode keeps each period's starting state and recomputes the
    # period: its steps are never all held at once.
    _, ((R, y), u, stats, results) = jax.lax.scan(
        jax.checkpoint(one, prevent_cse=False), (problem.R0, problem.y0), jnp.arange(n, dtype=jnp.int32)
    )

    def first(a, b):
        return jnp.concatenate([a[None], b])

    failed = results != RESULTS.successful
    result = jnp.where(jnp.any(failed), results[jnp.argmax(failed)], RESULTS.successful).astype(results.dtype)
    sol = Solution(
        ts=t0 + jnp.arange(n + 1, dtype=dtype) * period,
        R=first(problem.R0, R),
        y=jax.tree_util.tree_map(first, problem.y0, y),
        n_saved=jnp.asarray(n + 1),
        stats={key: jnp.sum(v) for key, v in stats.items()},
        result=result,
    )
    return sol, u


def _shapes(tree) -> str:
    return str(jax.tree_util.tree_map(lambda x: tuple(x.shape), tree))
