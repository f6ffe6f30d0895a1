"""Input validation shared by the public constructors and `solve`.

A value known while tracing (a NumPy array or Python number) is checked in
Python and raises `ValueError` at once, naming the value.  A traced value
cannot be inspected, so the same condition becomes a run-time check with
`eqx.error_if`, which raises when the compiled program runs.
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def asarray(x, dtype=None, name: str = "value"):
    """``x`` as a NumPy array when its value is known now, so that `check` can
    raise while tracing; as a JAX array when it is traced.  (Inside `jax.jit`,
    even ``jnp.asarray(0.1)`` is a tracer, so NumPy is the only way to keep a
    constant inspectable.)  Integers become the default float type and half
    precision becomes float32; booleans, complex numbers and strings raise
    `ValueError` naming ``name`` (a complex value would lose its imaginary
    part without a word)."""
    if is_traced(x):
        x = jnp.asarray(x)
    else:
        try:
            x = np.asarray(x)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name} must be real numbers, got {x!r} ({e})") from None
    if x.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be real numbers, got {_show(x) if not is_traced(x) else 'a traced value'} of dtype {x.dtype}")
    if dtype is None and (x.dtype.kind != "f" or x.dtype.itemsize < 4):
        dtype = jnp.result_type(float) if x.dtype.kind != "f" else np.float32
    if is_traced(x):
        return x if dtype is None else x.astype(dtype)
    return x if dtype is None else x.astype(jax.dtypes.canonicalize_dtype(dtype))


def all_finite(tree) -> jax.Array:
    """Whether every entry of every array leaf of ``tree`` is finite (a traced bool)."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]))


def is_traced(*xs) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(xs))


def check(x, ok: Callable, message: str):
    """Return ``x``, raising ``ValueError(message)`` if ``ok(x)`` is false.

    ``ok`` must work on NumPy and on JAX arrays (use ``xnp``-agnostic operators or
    the array's own methods).  For traced ``x`` the check is deferred to run time.
    """
    if is_traced(x):
        import jax.numpy as jnp

        # The value is only known at run time; say which check failed.
        return eqx.error_if(x, ~jnp.all(ok(x)), message.replace("{value}", "a traced value that failed the check"))
    if not bool(np.all(ok(np.asarray(x)))):
        raise ValueError(message.format(value=_show(x)) if "{value}" in message else message)
    return x


def _show(x) -> str:
    return np.array2string(np.asarray(x), precision=6, separator=", ")


def check_shape(x, shape: tuple, name: str):
    if np.shape(x) != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {np.shape(x)}")
