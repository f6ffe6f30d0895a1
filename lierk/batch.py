"""Batched evaluation of one function over many inputs, spread over devices.

`sweep` is `jax.vmap` plus the plumbing that makes large sweeps practical on
a workstation: the batch is sharded across all `jax.devices()` (so on a CPU
started with ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` each core
gets a slice) and can be cut into chunks so that memory stays bounded and a
progress bar can be shown.  The library never sets ``XLA_FLAGS`` itself; a
script that wants several host devices sets it before importing jax.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._progress import Progress

__all__ = ["sweep"]


def sweep(
    fn: Callable[..., Any],
    *batched_args: Any,
    chunk_size: int | None = None,
    progress: bool = False,
    shard: bool = True,
) -> Any:
    """``jax.vmap(fn)(*batched_args)``, sharded over devices and optionally chunked.

    Every leaf of every argument is mapped over its leading axis, and all
    leaves must share that axis's length ``N``.  Arguments that should not be
    mapped belong in ``fn``'s closure (``functools.partial`` or a lambda).

    With ``shard=True`` and more than one device, each chunk is padded to a
    multiple of the device count by repeating its last row, placed with a
    `NamedSharding` that splits the batch axis over a 1-d `Mesh` of
    `jax.devices()`, and the padding is dropped from the result.  Padding rows
    are real inputs (copies), so they cannot produce NaNs or errors of their
    own.  With one device ``shard`` has no effect.

    Args:
        fn: function of one batch member's arguments; jit-compatible.
        *batched_args: pytrees whose leaves have a leading axis of length ``N``.
        chunk_size: evaluate at most this many members per call (the last
            chunk may be smaller and costs one extra compilation).  ``None``:
            all ``N`` at once.
        progress: draw a progress bar on stderr, one tick per chunk.
        shard: split each chunk over all devices.

    Returns:
        ``fn``'s output pytree with a leading axis of length ``N`` on every
        leaf, as JAX arrays (sharded over devices when ``shard`` applied).

    Example:
        >>> import lierk
        >>> from lierk.batch import sweep
        >>> import numpy as np
        >>> I = lierk.inertia.tee_handle()
        >>> omega0s = np.random.default_rng(0).normal(size=(1000, 3))  # rad/s
        >>> def final_R(omega0):
        ...     body = lierk.FreeRigidBody(I, omega0)
        ...     return lierk.solve(body, lierk.RKMK4(), 10.0, dt=0.01, max_steps=1000).R[-1]
        >>> Rs = sweep(final_R, omega0s, chunk_size=500)  # (1000, 3, 3)
    """
    leaves = jax.tree_util.tree_leaves(batched_args)
    if not leaves:
        raise ValueError("sweep needs at least one batched argument")
    sizes = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(f"every leaf of the batched arguments needs the same leading axis, got lengths {sorted(map(str, sizes))}")
    (n,) = sizes
    if n == 0:
        raise ValueError("sweep over an empty batch (leading axis of length 0)")
    if chunk_size is not None and not (isinstance(chunk_size, (int, np.integer)) and chunk_size >= 1):
        raise ValueError(f"chunk_size must be a positive int or None, got {chunk_size!r}")
    chunk = n if chunk_size is None else min(int(chunk_size), n)

    devices = jax.devices()
    sharding = None
    if shard and len(devices) > 1:
        mesh = Mesh(np.array(devices), ("batch",))
        sharding = NamedSharding(mesh, PartitionSpec("batch"))
    n_dev = len(devices) if sharding is not None else 1

    mapped = jax.jit(jax.vmap(fn))
    bar = Progress("sweep", n, " members") if progress else None
    outs = []
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        args = jax.tree_util.tree_map(lambda x: x[start:stop], batched_args)
        m = stop - start
        pad = -m % n_dev
        if pad:
            # Copies of the last member: valid inputs, so no spurious failures.
            args = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), args)
        if sharding is not None:
            args = jax.device_put(args, sharding)
        out = mapped(*args)
        if pad:
            out = jax.tree_util.tree_map(lambda x: x[:m], out)
        outs.append(out)
        if bar is not None:
            jax.block_until_ready(out)
            bar.update(stop)
    if len(outs) == 1:
        return outs[0]
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *outs)
