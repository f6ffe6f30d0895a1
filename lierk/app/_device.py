"""Concrete values onto the device without compiling anything."""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["to_device"]


def to_device(x, dtype=None) -> jax.Array:
    """``x`` (a concrete value) as a JAX array, in ``dtype`` if given
    (float64 becomes float32 where JAX runs without x64).  NumPy converts it
    and `jax.device_put` moves it: ``jnp.asarray`` with a dtype would compile
    a small program per shape and dtype, and the application's host paths
    (restarts, stitched solutions, a report's settings) make many."""
    if isinstance(x, jax.Array) and (dtype is None or x.dtype == jax.dtypes.canonicalize_dtype(dtype)):
        return x
    x = np.asarray(x)
    return jax.device_put(x if dtype is None else x.astype(jax.dtypes.canonicalize_dtype(dtype)))
