"""How solves are differentiated.

A solve's loop decides which autodiff modes work through it (the same
trade-off as diffrax's adjoints; adaptive loops are built on
``equinox.internal.while_loop``):

- `ForwardSensitivity` (default): forward sensitivity analysis.  The
  derivatives with respect to the inputs that are differentiated (their
  scalars counted over the problem, times and tolerances) are carried through
  the solve in one pass, and both modes read them: `jax.jvp`/`jax.jacfwd`
  contract them with the input tangents, `jax.grad`/`jax.jacrev` with the
  output cotangents.  Memory does not grow with the steps, and the gradient is
  the derivative of the solve that was run (an adaptive solve's steps held
  fixed) whatever ``max_steps`` is.  With more inputs than ``max_inputs`` it
  hands over to ``fallback``.
- `RecursiveCheckpointAdjoint`: reverse mode through a checkpointed loop
  bounded by ``max_steps``; memory O(checkpoints), recomputation
  O(steps log steps).  Forward mode is not supported through adaptive solves.
  For reverse mode with respect to many inputs (a torque model's weights).
- `ForwardMode`: a plain `lax.while_loop`; `jax.jvp`/`jax.jacfwd` only.  One
  JVP costs one tangent pass, whatever the number of inputs.
- `DirectAdjoint`: a bounded loop of nested scans; both modes, at a run-time
  cost that grows with ``max_steps`` (every member runs the bounded loop),
  plus one forward solve that decides the steps the loop replays.

Fixed-step solves run through `lax.scan`, which both modes go through by
themselves; every adjoint but `ForwardSensitivity` leaves them to it (reverse
mode then recomputes blocks of about sqrt(steps) steps: bounded memory).
Fixed steps that end on save times (``SaveAt(ts=...)``) run loops of traced
length, which only forward mode enters: reverse mode through them needs
`ForwardSensitivity` within its ``max_inputs``.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import types
import warnings
from typing import Any, Callable, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.flatten_util import ravel_pytree

from ._controller import Controller
from ._programs import by_batch, in_form

__all__ = ["AbstractAdjoint", "ForwardSensitivity", "RecursiveCheckpointAdjoint", "ForwardMode", "DirectAdjoint"]


class AbstractAdjoint(eqx.Module):
    """How a solve is differentiated.  ``kind`` names the adaptive loop
    (`equinox.internal.while_loop`'s ``kind``) the adjoint builds."""

    kind: eqx.AbstractClassVar[str]

    @property
    def checkpoints(self) -> int | None:
        return None

    def run(self, loop: Callable, fixed: bool, *args) -> Any:
        """``loop(adjoint, *args)``, the solve, differentiated as this adjoint
        says.  ``fixed``: the loop takes fixed steps (a `lax.scan`)."""
        return loop(self, *args)

    def run_steps(self, loop: Callable, fixed: bool, *args, steps: int) -> Any:
        """`run`, told the loop's most steps ``steps`` (static): what
        `lierk.solve` calls.  An adjoint whose derivative's program depends
        on them overrides this (`ForwardSensitivity`: the form of a
        Jacobian's program, `lierk._programs`); the rest define `run`."""
        return self.run(loop, fixed, *args)


class RecursiveCheckpointAdjoint(AbstractAdjoint):
    """Reverse-mode autodiff with online recursive checkpointing.

    Attributes:
        checkpoints: number of checkpoints (None: derived from ``max_steps``).
    """

    kind: ClassVar[str] = "checkpointed"
    checkpoints: int | None = eqx.field(default=None, static=True)  # type: ignore[assignment]


class ForwardMode(AbstractAdjoint):
    """Forward-mode autodiff (`jax.jacfwd`) through a plain `lax.while_loop`."""

    kind: ClassVar[str] = "lax"


class DirectAdjoint(AbstractAdjoint):
    """Both modes, through a bounded loop of nested scans.

    An adaptive solve with this adjoint runs twice: an undifferentiated solve
    decides the steps (sizes, accepted or rejected), and the differentiated
    loop replays those decisions, so every recomputation in its backward pass
    takes the steps that were taken.  Cost: one more forward solve, plus the
    bounded loop's ``max_steps`` iterations per member.
    """

    kind: ClassVar[str] = "bounded"


class ForwardSensitivity(AbstractAdjoint):
    """Forward sensitivity analysis: the solve carries its Jacobian with
    respect to the inputs that are differentiated, and every autodiff mode
    reads it.

    Under differentiation the solve runs once with one tangent per input
    scalar that has a derivative (a `jax.jvp` through the loop, vmapped over
    the unit directions), which gives its outputs' Jacobian ``J``, ``(...,
    P)``.  `jax.jvp`/`jax.jacfwd` return ``J`` times the input tangent and
    `jax.grad`/`jax.jacrev` ``J^T`` times the output cotangent, so reverse mode
    costs what forward mode costs: no stored or recomputed steps, memory
    independent of the step count, and for adaptive solves the derivative of
    the steps taken (decisions under `stop_gradient`) for any ``max_steps``.
    The inputs are counted as the solve sees them: ``jax.grad`` with respect
    to ``omega0`` of a `FreeRigidBody` perturbs its momentum ``m0``, 3
    scalars; with respect to the inertia also its inverse, 21.  An adaptive
    solve under differentiation takes its steps with
    ``Controller.resolve_modes`` on, so that the tangents are resolved where
    the state does not move (a steady spin); its value comes from those
    steps, and an undifferentiated solve keeps its own.

    Costs: the Jacobian in ``omega0`` costs a few forward solves, and so do
    the gradient of a scalar loss and `jax.jacrev`, less than reverse mode
    through the loop (``benchmarks/results/sensitivity.md``).  A single
    `jax.jvp` costs as much as the whole Jacobian in the perturbed inputs:
    pass `ForwardMode()` for one direction at a time.

    Attributes:
        max_inputs: most perturbed input scalars to carry tangents for
            (None: 6 for fixed steps, 32 for adaptive ones, about where
            ``fallback`` becomes cheaper).
        fallback: the adjoint used beyond ``max_inputs``.  Fixed steps then go
            through the scan itself whatever it is (with ``SaveAt(ts=...)``,
            forward mode only); adaptive ones need an
            adjoint that supports forward mode, `DirectAdjoint` (both modes,
            with a warning: its cost grows with ``max_steps``) or
            `ForwardMode` (forward only).  For reverse mode with respect to
            many inputs, pass ``adjoint=RecursiveCheckpointAdjoint()``.
        resolve_modes: whether a differentiated adaptive solve bounds its
            steps by the body's perturbation modes (default True, see
            above).  False keeps the undifferentiated solve's steps, and its
            value bit for bit, at the cost of derivatives that may not be
            resolved about a steady spin or a body at rest.
    """

    kind: ClassVar[str] = "lax"
    max_inputs: int | None = eqx.field(default=None, static=True)
    fallback: AbstractAdjoint = DirectAdjoint()
    resolve_modes: bool = eqx.field(default=True, static=True)

    def __check_init__(self):
        if self.max_inputs is not None and not (isinstance(self.max_inputs, int) and self.max_inputs >= 1):
            raise ValueError(
                f"ForwardSensitivity(max_inputs=...) must be a positive int or None, got {self.max_inputs!r}"
            )
        if not isinstance(self.resolve_modes, bool):
            raise ValueError(f"ForwardSensitivity(resolve_modes=...) must be True or False, got {self.resolve_modes!r}")
        if isinstance(self.fallback, (ForwardSensitivity, RecursiveCheckpointAdjoint)):
            raise ValueError(
                "ForwardSensitivity(fallback=...) must support forward mode: DirectAdjoint() or ForwardMode(), "
                f"got {type(self.fallback).__name__}()"
            )

    def run(self, loop: Callable, fixed: bool, *args) -> Any:
        return self.run_steps(loop, fixed, *args, steps=None)

    def run_steps(self, loop: Callable, fixed: bool, *args, steps: int | None) -> Any:
        limit = self.max_inputs if self.max_inputs is not None else (6 if fixed else 32)
        # The derivative's loop resolves the body's perturbation modes
        # (`Controller.resolve_modes`): about a steady spin the state's error
        # estimate is 0 and the steps grow until the tangents are unresolved
        # (DP54 on a symmetric body spinning about its axis: 1e10 off).  So a
        # differentiated adaptive solve takes those steps, value included;
        # the undifferentiated one keeps its own.
        tangent = loop if fixed or not self.resolve_modes else _resolving(loop)
        loops = (
            functools.partial(loop, ForwardMode()),
            functools.partial(loop, self.fallback),
            functools.partial(tangent, ForwardMode()),
        )
        converted = _may_capture_tracer(args)
        kw = dict(limit=limit, fallback=type(self.fallback).__name__, fixed=fixed, steps=steps, converted=converted)
        if converted:
            # A function in the problem (a torque profile, an orbit, an event
            # condition) may close over a value that is being differentiated,
            # which the custom rule could not see.  Closure-converted, such
            # values are array leaves of the loop like any input.  Only
            # then: the conversion traces each of the three loops once more
            # (the heavy part of a spacecraft scene's trace, whose field
            # closes over plain numbers).
            loops = tuple(eqx.filter_closure_convert(f, *args) for f in loops)
        return _sensitive((loops, args), **kw)


def _may_capture_tracer(tree) -> bool:
    """Whether a function or other callable sitting anywhere in ``tree``
    (static fields of modules included, where equinox keeps them out of the
    pytree's leaves) may close over a traced value, or a static field holds
    one.  ``tree``'s own array leaves are not looked at: they are the loop's
    inputs already."""
    if isinstance(tree, eqx.Module):
        values = [(getattr(tree, f.name, None), f.metadata.get("static", False)) for f in dataclasses.fields(tree)]
        return any(_captures_tracer(v) if static else _may_capture_tracer(v) for v, static in values)
    if isinstance(tree, (tuple, list)):
        return any(_may_capture_tracer(x) for x in tree)
    if isinstance(tree, dict):
        return any(_may_capture_tracer(x) for x in tree.values())
    if callable(tree) and not isinstance(tree, type):
        return _captures_tracer(tree)
    return False


_PLAIN = (
    type(None),
    bool,
    int,
    float,
    complex,
    str,
    bytes,
    np.generic,
    np.dtype,
    # A shape and dtype only: equinox's closure conversion keeps these as
    # static fields (an event's condition, converted in `lierk.solve`).
    jax.ShapeDtypeStruct,
    jtu.PyTreeDef,
    types.GetSetDescriptorType,
    types.MemberDescriptorType,
    types.WrapperDescriptorType,
    types.MethodDescriptorType,
)
# Top-level functions, classes and modules of these packages (and of the
# standard library) hold no traced values; closures made by them, such as
# `lierk.dipole_field`'s field, are still looked into.
_LIBRARIES = frozenset({"jax", "jaxlib", "numpy", "equinox", "lierk", "builtins"}) | frozenset(sys.stdlib_module_names)
# Builtins that read a function's globals or names by string, out of sight.
_DYNAMIC = frozenset({"globals", "vars", "locals", "eval", "exec", "__import__"})
_MOST_VISITS = 5000


def _captures_tracer(root) -> bool:
    """Whether ``root`` reaches a `jax.core.Tracer` through closures, defaults,
    the globals a function reads, partials, bound objects, their classes,
    user modules, containers and attributes.  Conservative: an object it
    cannot look inside, an attribute that cannot be read, or more than
    ``_MOST_VISITS`` objects count as reaching one."""
    stack, seen = [root], set()
    try:
        while stack:
            x = stack.pop()
            if isinstance(x, jax.core.Tracer):
                return True
            if isinstance(x, (*_PLAIN, jax.Array)) or (isinstance(x, np.ndarray) and x.dtype != object):
                continue
            if id(x) in seen:
                continue
            seen.add(id(x))
            if len(seen) > _MOST_VISITS:
                return True
            inside = _inside(x)
            if inside is None:
                return True
            stack.extend(inside)
    except Exception:  # an object that refuses to be looked at
        return True
    return False


def _library(name) -> bool:
    return (name or "").split(".")[0] in _LIBRARIES


def _inside(x) -> list | None:
    """What ``x`` holds that a call could read, or None if it cannot be said."""
    if isinstance(x, types.FunctionType):
        cells = []
        for cell in x.__closure__ or ():
            try:
                cells.append(cell.cell_contents)
            except ValueError:  # an empty cell: a name not bound yet
                pass
        if _library(x.__module__):
            return cells
        names = _global_names(x.__code__)
        if any(n in _DYNAMIC and n not in x.__globals__ for n in names):
            return None
        defaults = [*(x.__defaults__ or ()), *(x.__kwdefaults__ or {}).values()]
        return cells + defaults + [x.__globals__[n] for n in names if n in x.__globals__]
    if isinstance(x, types.MethodType):
        return [x.__func__, x.__self__]
    if isinstance(x, types.BuiltinFunctionType):  # a bound builtin method keeps its object
        owner = getattr(x, "__self__", None)
        return [] if owner is None or isinstance(owner, types.ModuleType) else [owner]
    if isinstance(x, functools.partial):
        return [x.func, *x.args, *x.keywords.values()]
    if isinstance(x, (tuple, list, set, frozenset)):
        return list(x)
    if isinstance(x, dict):
        return list(x.values())
    if isinstance(x, np.ndarray):  # of objects
        return list(x.ravel())
    if isinstance(x, types.ModuleType):
        return [] if _library(x.__name__) else list(vars(x).values())
    if isinstance(x, (staticmethod, classmethod)):
        return [x.__func__]
    if isinstance(x, property):
        return [x.fget, x.fset, x.fdel]
    if isinstance(x, type):
        if _library(x.__module__):
            return []
        return [v for k, v in vars(x).items() if not (k.startswith("__") and k.endswith("__")) or k == "__call__"]
    if hasattr(x, "__wrapped__") and _library(type(x).__module__):  # jax.jit's wrapper: the function is what it calls
        return [x.__wrapped__]
    inside = [type(x)]
    if dataclasses.is_dataclass(x):  # equinox modules included
        inside += [getattr(x, f.name, None) for f in dataclasses.fields(x)]
    if hasattr(x, "__wrapped__"):  # functools.wraps
        inside.append(x.__wrapped__)
    attributes = getattr(x, "__dict__", None)
    slots = [
        n for c in type(x).__mro__ for n in _names(getattr(c, "__slots__", ())) if n not in ("__dict__", "__weakref__")
    ]
    if attributes is None and not slots and len(inside) == 1:
        return None
    inside += list((attributes or {}).values()) + [getattr(x, n) for n in slots if hasattr(x, n)]
    return inside


def _names(slots) -> tuple:
    return (slots,) if isinstance(slots, str) else tuple(slots)


def _global_names(code: types.CodeType) -> set[str]:
    """The names a function's code (its nested functions' included) may read
    from its globals."""
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _global_names(const)
    return names


def _is_none(x) -> bool:
    return x is None


# The primal and the fallback loop ride in the arguments: plain functions
# are static, closure-converted ones carry their captured values as leaves.
@eqx.filter_custom_jvp
def _sensitive(loops_args, *, limit, fallback, fixed, steps, converted):
    (primal, _, _), args = loops_args
    return primal(*args)


def _resolving(loop: Callable) -> Callable:
    """``loop`` with its `Controller` resolving the perturbation modes."""

    def resolving(*args):
        return loop(*(a.resolving_modes() if isinstance(a, Controller) else a for a in args))

    return resolving


@_sensitive.def_jvp
def _sensitive_jvp(primals, tangents, *, limit, fallback, fixed, steps, converted):
    (loops_args,), (t_loops_args,) = primals, tangents
    live = jtu.tree_map(lambda t, _: t is not None, t_loops_args, loops_args, is_leaf=_is_none)
    inputs, rest = eqx.partition(loops_args, live)
    p0, unravel = ravel_pytree(inputs)
    if p0.size > limit:
        if not fixed and fallback == "DirectAdjoint":
            warnings.warn(
                f"differentiating an adaptive solve with respect to {p0.size} input scalars, more than "
                f"ForwardSensitivity's max_inputs={limit}: through DirectAdjoint, whose cost grows with max_steps. "
                "For reverse mode pass adjoint=lierk.RecursiveCheckpointAdjoint(); for forward mode "
                "adjoint=lierk.ForwardMode(); or raise max_inputs",
                stacklevel=2,
            )
        return eqx.filter_jvp(lambda la: la[0][1](*la[1]), (loops_args,), (t_loops_args,))
    dp, _ = ravel_pytree(t_loops_args)  # the live tangents, in the order of p0 (None leaves are empty)

    def jacobian(p0, rest):
        def solve(p):
            (_, _, tangent), args = eqx.combine(unravel(p), rest)
            return tangent(*args)

        def column(e):
            return eqx.filter_jvp(solve, (p0,), (e,))

        # One pass: the primal is the same for every direction (not
        # batched), the tangents are the Jacobian's columns.
        return jax.vmap(column, out_axes=(None, -1))(jnp.eye(p0.size, dtype=p0.dtype))

    # The Jacobian reads the primal inputs only, so its program's form
    # follows the rule of a call (`lierk._programs`: one body's, unless a
    # `jax.vmap` batches them), and reverse mode never enters it.  The
    # contraction with ``dp`` is the only part that reads the input
    # tangents, so reverse mode transposes just that: J^T times the
    # cotangent.
    def forms(form, p0, rest):
        (primal, fallback, tangent), args = rest
        formed = in_form(args, form, steps, derivative=True)
        if jtu.tree_structure(formed) == jtu.tree_structure(args):
            return p0, rest
        return p0, ((primal, fallback, _InForm(tangent, form, steps)), args)

    # Closure-converted loops have their solver's form traced in already:
    # the batch form, as `lierk._programs` says for such a call.
    out, J = jacobian(p0, rest) if converted else by_batch(jacobian, forms, p0, rest)
    return out, jtu.tree_map(_contract(dp), J)


class _InForm:
    """A loop that runs with its solver in ``form`` (`lierk._programs.in_form`)."""

    def __init__(self, loop: Callable, form, steps: int | None):
        self.loop, self.form, self.steps = loop, form, steps

    def __call__(self, *args):
        return self.loop(*in_form(args, self.form, self.steps, derivative=True))


def _contract(dp):
    def contract(Jl):
        # Outputs that no input moves (padding rows, NaN by convention) are
        # cut out of the transpose: reverse mode would otherwise send their
        # cotangents through 0 * NaN into every gradient.
        moved = jnp.any(Jl != 0, axis=-1)
        # A sum of products, not a tensordot: under `jax.jacfwd` (``dp``
        # batched) XLA made the contraction a dot kernel with a transposed
        # copy on either side; the products fuse with the reduction.
        return jnp.where(moved, jnp.sum(Jl * dp.astype(Jl.dtype), axis=-1), 0)

    return contract
