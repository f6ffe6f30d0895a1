"""Which program a call compiles: the rule, decided here and nowhere else.

`lierk.solve`, `lierk.sensitivity` and the closed forms of `lierk.exact`
choose their program from the call's arguments alone, never from how the
caller reached them:

+----------------------------------------------+---------------------------------------------------+-------------------+
| the call                                     | where it runs                                     | the solver's form |
+==============================================+===================================================+===================+
| no argument is a JAX tracer, called from     | lierk's own program, compiled once per argument   | one body          |
| Python (or under an eager transform of a     | structure, on the CPU with                        |                   |
| function closing over it)                    | `one_body_compiler_options`                       |                   |
+----------------------------------------------+---------------------------------------------------+-------------------+
| no argument is a JAX tracer, inside a        | part of the caller's program, with its compile    | one body          |
| caller's ``jax.jit`` (values it closes over) | options (JAX gives a nested program no options of |                   |
|                                              | its own)                                          |                   |
+----------------------------------------------+---------------------------------------------------+-------------------+
| some argument is traced: inside ``jax.jit``, | part of the caller's program                      | one body          |
| ``jax.grad``, ``jax.jacfwd``, a ``lax.scan`` |                                                   |                   |
| body                                         |                                                   |                   |
+----------------------------------------------+---------------------------------------------------+-------------------+
| a ``jax.vmap`` batches the call, now or      | part of the caller's program, traced again by a   | batch             |
| later (``jax.vmap`` of the caller's jitted   | batching rule                                     |                   |
| function too)                                | (``jax.custom_batching.custom_vmap``)             |                   |
+----------------------------------------------+---------------------------------------------------+-------------------+
| a function in the problem closes over a      | part of the caller's program                      | batch             |
| traced value                                 |                                                   |                   |
+----------------------------------------------+---------------------------------------------------+-------------------+

The two forms compute the same numbers to rounding; they differ in how the
program is written, which trades compile time against run time:

- **one body**: in a solve of at most `MOST_STEPS_COMPACT` steps on the
  CPU, an RKMK tableau of five or more stages (four or more in a Jacobian's
  program) loops over its stages (``lax.fori_loop``) and the step's helpers
  take their compact forms: a much smaller program, which compiles several
  times faster and runs each step slower.  Longer solves, other backends and
  the other solvers keep the batch form.
- **batch**: every stage written out, the fastest to run, above all for a
  batch.

Derivatives follow the same rule.  With the default adjoint,
`lierk.ForwardSensitivity`, a differentiated solve computes its Jacobian in
one program of its own inputs (`lierk._adjoint`), decided like a call: one
body's Jacobian (``jax.jacfwd``, ``jax.grad``) takes the one-body form, a
batch of them (``jax.vmap`` of ``jax.jacfwd``) the batch form.  Adjoints
whose tangents run through the loop (`lierk.ForwardMode`,
`lierk.RecursiveCheckpointAdjoint`, `lierk.DirectAdjoint`, and a fixed-step
scan past ``max_inputs``) take the batch form.

Inside either form, one operation has a batching rule of its own: an
event's location of its crossings (`lierk._event`), a
``jax.custom_batching.custom_vmap``.  One body locates a crossing in a
conditional; under ``jax.vmap`` the rule gathers the members whose
condition changed sign and locates them as a small batch.  Nothing else is
chosen by how the call was batched.

To fix the form, pass it to the solver: ``lierk.RKMK4(compact=True)`` (one
body's form) or ``compact=False`` (the batch form), for any RKMK solver;
every call then compiles that form.  The default, ``compact=None``, follows
the rule.  The measurements behind it are in
``benchmarks/results/first_result-solve-jacfwd.md`` (compile times) and
``benchmarks/results/sensitivity.md`` (batches).

While it traces a program, a call holds Python's cyclic garbage collector
off (`without_collection`).
"""

from __future__ import annotations

import contextlib
import functools
import gc
import os
from typing import Callable, Literal

import equinox as eqx
import jax

__all__ = ["one_body_compiler_options"]

Form = Literal["one body", "batch"]

# A CPU setting: other backends keep their defaults.
_ONE_BODY_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

MOST_STEPS_COMPACT = 4096
"""The most steps (``max_steps``, or a fixed-step solve's count) of a solve
that takes the compact one-body form: at the adaptive solves' default
``max_steps``, the loop's slower steps cost less than its faster compile
saves (``benchmarks/results/first_result-solve-jacfwd.md``)."""


def one_body_compiler_options() -> dict:
    """XLA's compile options for a program that solves one body: what lierk
    passes when it compiles a program of its own (a call with no traced
    argument), and what a caller's own ``jax.jit`` of one body's solve can
    pass too: ``jax.jit(f, compiler_options=lierk.one_body_compiler_options())``.

    On the CPU these are XLA's older loop emitters
    (``xla_cpu_use_fusion_emitters=False``), which compile one body's solve
    faster and run it as fast; a batch runs slower with them
    (``benchmarks/results/compiler_options.md``).  Empty (XLA's defaults) on
    other backends, and where ``XLA_FLAGS`` chooses the emitters itself.

    Returns:
        A new ``dict`` of option names and values for ``jax.jit``'s or
        ``Lowered.compile``'s ``compiler_options``.
    """
    if "xla_cpu_use_fusion_emitters" in os.environ.get("XLA_FLAGS", "") or jax.default_backend() != "cpu":
        return {}
    return dict(_ONE_BODY_OPTIONS)


def in_form(tree, form: Form, max_steps: int | None, *, derivative: bool = False):
    """``tree`` with every solver in it in ``form`` (`lierk.AbstractSolver.in_form`):
    for ``"one body"``, the compact form where the rule above takes it (at
    most ``max_steps`` steps on the CPU; ``derivative``: a Jacobian's
    program), else the batch form.  A solver whose form is fixed keeps it."""
    from ._solvers.base import AbstractSolver

    def resolve(solver):
        compact = (
            form == "one body"
            and jax.default_backend() == "cpu"
            and max_steps is not None
            and max_steps <= MOST_STEPS_COMPACT
            and solver.stages >= (4 if derivative else 5)
        )
        return solver.in_form(compact)

    return jax.tree_util.tree_map(
        lambda x: resolve(x) if isinstance(x, AbstractSolver) else x,
        tree,
        is_leaf=lambda x: isinstance(x, AbstractSolver),
    )


def _is_jax_value(x) -> bool:
    """A JAX array or a tracer: what a program takes as an argument (NumPy
    arrays and Python numbers in a pytree stay part of its structure)."""
    return isinstance(x, (jax.Array, jax.core.Tracer))


def by_batch(fun: Callable, forms: Callable, *args):
    """``fun(*forms("one body", *args))``, traced now; under a ``jax.vmap``,
    now or later, ``fun(*forms("batch", *args))`` over the batch instead
    (``jax.custom_batching.custom_vmap``).  ``forms`` may change static
    parts of the arguments only (the solver's form), never their arrays."""
    one, batch = forms("one body", *args), forms("batch", *args)
    (leaves, tree_one), (leaves_batch, tree_batch) = (jax.tree_util.tree_flatten(a) for a in (one, batch))
    if tree_one == tree_batch and all(a is b for a, b in zip(leaves, leaves_batch)):
        return fun(*one)
    where = [i for i, x in enumerate(leaves) if _is_jax_value(x)]
    out_static = []

    def run(leaves, tree, dynamic):
        full = list(leaves)
        for i, x in zip(where, dynamic):
            full[i] = x
        out_dynamic, static = eqx.partition(fun(*jax.tree_util.tree_unflatten(tree, full)), _is_jax_value)
        out_static.append(static)
        return out_dynamic

    @jax.custom_batching.custom_vmap
    def one_body(dynamic):
        return run(leaves, tree_one, dynamic)

    @one_body.def_vmap
    def rule(axis_size, in_batched, dynamic):
        del axis_size
        if not any(in_batched[0]):
            # Nothing batched: JAX's derivative of this rule calls it so, and
            # batches the derivative's own directions itself.
            out = run(leaves, tree_one, dynamic)
            return out, jax.tree_util.tree_map(lambda _: False, out)
        axes = [0 if b else None for b in in_batched[0]]
        out = jax.vmap(lambda d: run(leaves_batch, tree_batch, d), in_axes=(axes,))(dynamic)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    out_dynamic = one_body([leaves[i] for i in where])
    return eqx.combine(out_dynamic, out_static[0])


@contextlib.contextmanager
def without_collection():
    """Python's cyclic garbage collector held off while lierk traces a
    program (and, called from Python, lowers, compiles and starts it):
    tracing allocates many objects that live until the trace ends, so the
    collector's passes find little to free and scan all of them.  What the
    call leaves is collected at the next pass after it; nested calls leave
    the collector as the outermost found it."""
    if not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


class Program:
    """``fun`` run by the rule above.  ``forms(form, *args)``: the arguments
    in a form (`in_form`), for a function whose program has forms; None for
    one that has none.  ``jit`` (``eqx.filter_jit`` or ``jax.jit``) builds the
    programs, with ``jit_kwargs``.  ``.default`` is ``fun`` jitted with
    XLA's defaults, in the arguments' form as given; ``.__wrapped__`` is
    ``fun``, to be traced inside another program."""

    def __init__(self, fun: Callable, forms: Callable | None = None, jit: Callable = eqx.filter_jit, **jit_kwargs):
        self.__wrapped__ = fun
        self.default = jit(fun, **jit_kwargs)
        self._own = jit(fun, compiler_options=_ONE_BODY_OPTIONS, **jit_kwargs)
        self._forms = forms
        functools.update_wrapper(self, fun)

    def __call__(self, *args, **kwargs):
        from ._adjoint import _may_capture_tracer

        with without_collection():
            # A function closing over a traced value hides it from the
            # batching rule: such a call takes the batch form.
            if _may_capture_tracer((args, kwargs)):
                return self.default(*args, **kwargs)
            if not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs))):
                if self._forms is not None:
                    args = self._forms("one body", *args)
                if one_body_compiler_options():
                    try:
                        return self._own(*args, **kwargs)
                    except ValueError as e:
                        # Inside a caller's trace JAX refuses a nested
                        # program its own options: it is the caller's.
                        if "compiler_options" not in str(e):
                            raise
                return self.default(*args, **kwargs)
            if self._forms is None:
                return self.default(*args, **kwargs)
            return by_batch(lambda *a: self.default(*a, **kwargs), self._forms, *args)
