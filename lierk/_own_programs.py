"""XLA's settings and the solver's form for the programs that solve one body.

A call of `lierk.solve`, `lierk.sensitivity` or `lierk.exact`'s closed
forms from Python, outside any JAX transform, compiles a program of lierk's
own; inside a caller's `jax.jit` the solve is part of the caller's program,
compiled with the caller's settings.  Such a call solves one body, and for one body XLA's older CPU
loop emitters compile the program in about 60% of the time of the default
fusion emitters and run it as fast; for a batch (``jax.vmap``) they run 1.2
to 1.6x slower (docs/guides/contributing.md, "One body compiles with XLA's
older emitters").  So a program called with traced arguments keeps XLA's
defaults.

A solve of one body also loops over the stages of the long RKMK tableaux
(`lierk.AbstractSolver.for_one_body`), called from Python or traced inside
a caller's ``jax.jit``: it compiles about twice as fast and runs slower,
while a batch runs 1.6 to 2x slower in the loop.  Tracing a ``jax.jit``,
lierk cannot tell one body from a batch (``jax.vmap`` of a jitted function
batches the program traced for one body), so the solve goes through a
batching rule (``jax.custom_batching.custom_vmap``): a ``jax.vmap`` of it,
now or later, solves the batch with the stages unrolled.  One body's
Jacobian (``jax.jacfwd``, whose directions batch the tangents alone) takes
the one-body form too (RKMK4's stages loop there as well), through a second
such rule for a batch of bodies; its directions batch only the linearised
program (`jax.linearize`), as JAX's rules batch a nested program or loop
whether or not an input of it is batched.

While it traces, a call holds Python's cyclic garbage collector off
(`_without_collection`).
"""

from __future__ import annotations

import contextlib
import functools
import gc
import os
from typing import Callable

import equinox as eqx
import jax

__all__ = ["one_body_compiler_options"]

# A CPU setting: other backends keep their defaults.
_ONE_BODY = {"xla_cpu_use_fusion_emitters": False}


def one_body_compiler_options() -> dict:
    """XLA's compile options for a program that solves one body: what lierk
    passes when it compiles `lierk.solve` or `lierk.sensitivity` called from
    Python (no transform), and what a caller's own ``jax.jit`` of one body's
    solve can pass too: ``jax.jit(f, compiler_options=lierk.one_body_compiler_options())``.

    On the CPU these are XLA's older loop emitters
    (``xla_cpu_use_fusion_emitters=False``): a heavy top's first adaptive
    DOP853 solve compiles in 0.90 s instead of 1.52 and runs in 4.3 ms
    instead of 4.7 (2 cores).  Not for a batch: a ``jax.vmap`` of 64 bodies
    runs 1.2 to 1.6x slower with them.  Empty (XLA's defaults) on other
    backends, and where ``XLA_FLAGS`` chooses the emitters itself.

    Returns:
        A new ``dict`` of option names and values for ``jax.jit``'s or
        ``Lowered.compile``'s ``compiler_options``.
    """
    if "xla_cpu_use_fusion_emitters" in os.environ.get("XLA_FLAGS", "") or jax.default_backend() != "cpu":
        return {}
    return dict(_ONE_BODY)


# Directions of an eager `jax.jacfwd` that still compile with the one-body
# settings: a heavy top's DOP853 sensitivity to its inertia (9 directions)
# compiled in 2.2 s instead of 2.9 and ran in 47 ms instead of 64, where a
# `jax.vmap` of 8 bodies ran as fast or 24% slower (the primal, one body,
# is most of a Jacobian's program).
_MOST_DIRECTIONS = 12


def _directions(tree) -> int | None:
    """1 for concrete values; under one eager `jax.vmap` of concrete values
    (`jax.jacfwd`'s directions), their count; None under anything else."""
    counts = set()
    for x in jax.tree_util.tree_leaves(tree):
        if not isinstance(x, jax.core.Tracer):
            continue
        val, axis = getattr(x, "val", None), getattr(x, "batch_dim", None)
        if type(x).__name__ != "BatchTracer" or isinstance(val, jax.core.Tracer) or not isinstance(axis, int):
            return None
        counts.add(val.shape[axis])
    return max(counts, default=1) if len(counts) <= 1 else None


try:
    from jax._src.core import trace_state_clean as _trace_state_clean
except ImportError:  # a JAX release without it
    _trace_state_clean = None


def at_top_level() -> bool:
    """Whether no JAX trace is under way (no ``jax.jit``, ``jax.vmap``,
    ``jax.grad``, ``lax.scan`` body... around the call): a call made here
    runs a program of its own.  JAX's own test, a private function; without
    it, as if a trace were under way (XLA's defaults, as before)."""
    return _trace_state_clean is not None and bool(_trace_state_clean())


def _is_jax_value(x) -> bool:
    """A JAX array or a tracer: a value a program takes as an argument (NumPy
    arrays and Python numbers in a pytree stay part of its structure)."""
    return isinstance(x, (jax.Array, jax.core.Tracer))


def _is_batched(tree) -> bool:
    """Whether a ``jax.vmap`` batches some leaf of ``tree`` (at any level of
    nesting)."""
    for x in jax.tree_util.tree_leaves(tree):
        while isinstance(x, jax.core.Tracer):
            if type(x).__name__ == "BatchTracer":
                return True
            x = getattr(x, "val", getattr(x, "primal", None))
    return False


@contextlib.contextmanager
def _without_collection():
    """Python's cyclic garbage collector held off while lierk traces a
    program (and, called from Python, lowers, compiles and starts it):
    tracing allocates hundreds of thousands of objects that live until the
    trace ends, so the collector's passes find little to free and scan all
    of them (the whole process's heap in its oldest generation).  They were
    0.07 to 0.1 s of a heavy top's 0.6 s `jit(jacfwd)` trace.  What the
    call leaves for collection is collected at the next pass after it.
    Nested calls leave the collector as the outermost found it."""
    if not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


class OwnProgram:
    """``eqx.filter_jit(fun)``, compiled with `one_body_compiler_options`
    when called on the CPU with no traced argument (one body, no transform),
    with XLA's defaults otherwise (``.default``: always).  ``tangents``: the
    position of an argument that an eager `jax.jacfwd` may batch (its
    directions) while the others stay concrete, which keeps the one-body
    settings for up to 12 directions.  ``one_body``: a function of the
    positional arguments giving those a one-body call passes on (the
    solver's one-body form, `lierk.AbstractSolver.for_one_body`), also
    inside a caller's trace where no batch is in sight, with a batching rule
    that passes the arguments as given to a ``jax.vmap``.  ``jit``
    (``jax.jit`` or equinox's) builds both programs, with ``jit_kwargs``.
    ``.__wrapped__`` is ``fun``, to be traced inside another program."""

    def __init__(
        self,
        fun: Callable,
        tangents: int | None = None,
        jit: Callable = eqx.filter_jit,
        one_body: Callable | None = None,
        **jit_kwargs,
    ):
        self.__wrapped__ = fun
        self.default = jit(fun, **jit_kwargs)
        self._one_body = jit(fun, compiler_options=_ONE_BODY, **jit_kwargs)
        self._tangents = tangents
        self._prepare = one_body
        functools.update_wrapper(self, fun)

    def _is_one_body(self, args, kwargs) -> bool:
        # Off the CPU a one-body call is the default program anyway: the
        # options are empty and the solver's one-body form is itself.
        rest = [a for i, a in enumerate(args) if i != self._tangents]
        if _directions((rest, kwargs)) != 1:
            return False
        if self._tangents is not None and self._tangents < len(args):
            directions = _directions(args[self._tangents])
            if directions is None or directions > _MOST_DIRECTIONS:
                return False
            if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(args[self._tangents])):
                return True  # an eager `jax.jacfwd`'s directions, over concrete values
        # Concrete arguments inside a caller's trace (a problem built outside
        # its `jax.jit`) make a nested program, which takes no options of
        # its own: the caller's program.
        return at_top_level()

    def __call__(self, *args, **kwargs):
        with _without_collection():
            return self._call(args, kwargs)

    def _call(self, args, kwargs):
        if not self._is_one_body(args, kwargs):
            if self._prepare is not None and (
                not _is_batched((args, kwargs)) if self._tangents is None else self._directions_only(args, kwargs)
            ):
                return self._one_body_unless_batched(args, kwargs)
            return self.default(*args, **kwargs)
        if self._prepare is not None:
            args = self._prepare(*args)
        return (self._one_body if one_body_compiler_options() else self.default)(*args, **kwargs)

    def _directions_only(self, args, kwargs) -> bool:
        """Whether the tangents alone are batched (`jax.jacfwd`'s directions
        over one body) and nothing else transforms the call: one body's
        derivative.  A single direction (a `jax.jvp`, or `jax.grad`'s
        linearisation, which cannot go through a batching rule) and a
        derivative of the derivative keep the program as given."""
        if self._tangents >= len(args) or not _is_batched(args[self._tangents]):
            return False
        given = [a for i, a in enumerate(args) if i != self._tangents]
        return all(
            type(x).__name__ == "DynamicJaxprTracer"
            for x in jax.tree_util.tree_leaves((given, kwargs))
            if isinstance(x, jax.core.Tracer)
        )

    def _one_body_unless_batched(self, args, kwargs):
        """Inside a caller's trace with no batch in sight (its ``jax.jit``,
        a ``lax.scan`` body...): the one-body form of the arguments, unless
        a ``jax.vmap`` later batches this call (``jax.vmap`` of the caller's
        jitted function), whose batching rule then solves the batch with
        the arguments as given.  One body's first ``jit`` of a heavy top's
        DOP853 solve: 1.57 -> 0.70 s; a batch keeps the program that runs
        fastest (docs/guides/contributing.md)."""
        leaves, tree = jax.tree_util.tree_flatten((args, kwargs))
        leaves_one, tree_one = jax.tree_util.tree_flatten((self._prepare(*args), kwargs))
        where = [i for i, x in enumerate(leaves) if _is_jax_value(x)]
        if tree == tree_one or [i for i, x in enumerate(leaves_one) if _is_jax_value(x)] != where or any(
            leaves[i] is not leaves_one[i] for i in where
        ):
            # The one-body form is the same program, or it differs in its
            # numbers (nothing a batching rule could pass both ways).
            return self.default(*args, **kwargs)
        out_static = []
        # Which of the dynamic leaves are the tangents' (`tangents`): their
        # batch alone is `jax.jacfwd`'s directions over one body.
        tangent = [False] * len(leaves)
        if self._tangents is not None and self._tangents < len(args):
            start = len(jax.tree_util.tree_leaves(args[: self._tangents]))
            stop = start + len(jax.tree_util.tree_leaves(args[self._tangents]))
            tangent[start:stop] = [True] * (stop - start)
        tangent = [tangent[i] for i in where]

        def solve(dynamic, leaves, tree):
            leaves = list(leaves)
            for i, x in zip(where, dynamic):
                leaves[i] = x
            a, kw = jax.tree_util.tree_unflatten(tree, leaves)
            out_dynamic, s = eqx.partition(self.default(*a, **kw), _is_jax_value)
            out_static.append(s)
            return out_dynamic

        @jax.custom_batching.custom_vmap
        def one_body(dynamic):
            return solve(dynamic, leaves_one, tree_one)

        @one_body.def_vmap
        def batch(axis_size, in_batched, dynamic):
            del axis_size
            axes = [0 if b else None for b in in_batched[0]]
            if not any(b and not t for b, t in zip(in_batched[0], tangent)):
                return directions(axes, dynamic)
            out = jax.vmap(lambda d: solve(d, leaves, tree), in_axes=(axes,))(dynamic)
            return out, jax.tree_util.tree_map(lambda _: True, out)

        def directions(axes, dynamic):
            """One body's derivative in a batch of directions (the tangents
            batched, ``axes``), in the one-body form, unless a ``jax.vmap``
            later batches the body too: then, as for a batch, the arguments
            as given.  The output is ``(primal, tangent)``, the primal the
            same in every direction."""

            @jax.custom_batching.custom_vmap
            def one_body_directions(dynamic):
                # The tangent is linear in the directions and the primal does
                # not read them: linearised, the batch goes through the
                # linear map alone.  A `jax.vmap` of the whole program
                # batched every nested program and loop in it (JAX's rules
                # for those run whether or not an input is batched: 0.27 s
                # of a heavy top's 0.7 s trace).
                batched = [i for i, a in enumerate(axes) if a is not None]

                def at(directions):
                    d = list(dynamic)
                    for i, x in zip(batched, directions):
                        d[i] = x
                    return solve(d, leaves_one, tree_one)

                (primal, _), linear = jax.linearize(at, [dynamic[i][0] for i in batched])
                _, t_out = jax.vmap(linear)([dynamic[i] for i in batched])
                return primal, t_out

            @one_body_directions.def_vmap
            def bodies(axis_size, in_batched, dynamic):
                del axis_size
                inner = jax.vmap(lambda d: solve(d, leaves, tree), in_axes=(axes,), out_axes=(None, 0))
                if not any(in_batched[0]):  # (as JAX's derivative of this rule calls it)
                    out = inner(dynamic)
                    return out, jax.tree_util.tree_map(lambda _: False, out)
                out = jax.vmap(inner, in_axes=([0 if b else None for b in in_batched[0]],))(dynamic)
                return out, jax.tree_util.tree_map(lambda _: True, out)

            out = one_body_directions(dynamic)
            return out, (jax.tree_util.tree_map(lambda _: False, out[0]), jax.tree_util.tree_map(lambda _: True, out[1]))

        out_dynamic = one_body([leaves[i] for i in where])
        return eqx.combine(out_dynamic, out_static[0])
