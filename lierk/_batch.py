"""Batched evaluation of one function over many inputs, spread over devices.

`sweep` and `sweep_chunks` are `jax.vmap` plus the plumbing that makes large
sweeps practical: the batch is sharded across all `jax.devices()` (on a CPU
started with ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` each core
gets a slice; after `lierk.app.distributed.initialize` the devices of every
process), cut into chunks of one compiled shape so that memory stays bounded,
stepped inside the program in blocks that fit a core's cache, and compiled
once per function.  The library never sets ``XLA_FLAGS`` itself;
a script that wants several host devices sets it before importing jax.

What counts as the same function for the compile cache is in `sweep`'s
docstring.
"""

from __future__ import annotations

import collections
import functools
import inspect
import math
import os
import weakref
from typing import Any, Callable, Iterable, Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec, SingleDeviceSharding

__all__ = ["sweep", "sweep_chunks"]

_STRUCTURAL_CACHE_SIZE = 64


# --------------------------------------------------------------------------
# One compiled jit(vmap(fn)) per function


class _WeakIdentityCache:
    """Values keyed on the identity of a few objects, each held weakly: an
    entry disappears as soon as one of its objects is collected.  The values
    must not refer to the objects (or they would keep them alive)."""

    def __init__(self):
        self._entries: dict[tuple[int, ...], tuple[tuple[weakref.ref, ...], Any]] = {}

    def get(self, objs: tuple, make: Callable[[], Any]) -> Any:
        key = tuple(map(id, objs))
        hit = self._entries.get(key)
        if hit is not None:
            return hit[1]

        def drop(_ref, key=key):
            self._entries.pop(key, None)

        refs = tuple(weakref.ref(o, drop) for o in objs)  # TypeError if not weak-referenceable
        value = make()
        self._entries[key] = (refs, value)
        return value

    def __len__(self) -> int:
        return len(self._entries)


_BY_IDENTITY = _WeakIdentityCache()
_BY_STRUCTURE: collections.OrderedDict = collections.OrderedDict()


def _in_blocks(batched_fn: Callable, block: int | None, rows: tuple) -> Any:
    """``batched_fn(*rows)``, the rows taken ``block`` at a time inside the
    program: ``lax.map`` over a ``(n_blocks, size, ...)`` reshape of the
    rows, the blocks as equal as can be (``size = ceil(n / n_blocks)`` with
    ``n_blocks = ceil(n / block)``, at most ``block``), the last block
    padded with copies of the last row (valid inputs) and the padding's
    output dropped.  ``block`` None or ``>= n``: one call on all rows."""
    n = jax.tree_util.tree_leaves(rows)[0].shape[0]
    if block is None or block >= n:
        return batched_fn(*rows)
    n_blocks = -(-n // block)
    size = -(-n // n_blocks)
    pad = n_blocks * size - n

    def split(x):
        if pad:
            x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad, *x.shape[1:]))])
        return x.reshape(n_blocks, size, *x.shape[1:])

    out = jax.lax.map(lambda r: batched_fn(*r), jax.tree_util.tree_map(split, rows))
    return jax.tree_util.tree_map(lambda y: y.reshape(n_blocks * size, *y.shape[2:])[:n], out)


def _jit_vmap(rebuild: Callable[[Any], Callable]) -> Callable:
    """``jit`` of ``(mesh, block, dynamic, *args) -> vmap(rebuild(dynamic))(*args)``:
    the batched arguments are mapped over axis 0, the function's own arrays
    (``dynamic``) are not, and each device's rows run ``block`` at a time
    (`_in_blocks`; ``mesh`` and ``block`` are static).

    With a ``mesh`` (static) the vmap runs under ``shard_map``: each device
    runs its own rows as a program of its own.  Left to the SPMD partitioner,
    the batch-wide reductions of the vmapped solve (an adaptive loop's "is any
    member still running", every run-time check's "did any member fail")
    became all-reduces between the devices, so the devices stepped in lockstep
    and a failed check, whose error callback runs on one device only, left the
    others waiting in the next all-reduce until XLA aborted the process (after
    a minute) instead of raising the error.  (``check_vma=False``: equinox's
    error branches do not declare how their values vary over the mesh.)
    """

    def batched(mesh, block, dynamic, *args):
        def local(dyn, *rows):
            return _in_blocks(jax.vmap(rebuild(dyn)), block, rows)

        if mesh is None:
            return local(dynamic, *args)
        specs = (PartitionSpec(),) + (PartitionSpec("batch"),) * len(args)
        return jax.shard_map(local, mesh=mesh, in_specs=specs, out_specs=PartitionSpec("batch"), check_vma=False)(
            dynamic, *args
        )

    return jax.jit(batched, static_argnums=(0, 1))


def _compiled(fn: Callable) -> tuple[Callable, list]:
    """``(jitted, dynamic)``: the cached ``jit(vmap)`` for ``fn`` and the array
    leaves of ``fn`` to pass to it (empty unless ``fn`` is a pytree)."""
    tree = fn
    if type(fn) is functools.partial:
        # functools.partial is a pytree leaf to jax; jax's Partial flattens it.
        tree = jax.tree_util.Partial(fn.func, *fn.args, **fn.keywords)
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    if treedef.num_nodes > 1:
        is_dynamic = [eqx.is_array(x) for x in leaves]
        dynamic = [x for x, d in zip(leaves, is_dynamic) if d]
        static = tuple(None if d else (type(x), x) for x, d in zip(leaves, is_dynamic))
        key = (treedef, static)
        try:
            jitted = _BY_STRUCTURE.get(key)
        except TypeError:  # an unhashable non-array part: fall back to identity
            pass
        else:
            if jitted is None:

                def rebuild(dyn):
                    it = iter(dyn)
                    return jax.tree_util.tree_unflatten(treedef, [next(it) if s is None else s[1] for s in static])

                jitted = _BY_STRUCTURE[key] = _jit_vmap(rebuild)
                if len(_BY_STRUCTURE) > _STRUCTURAL_CACHE_SIZE:
                    _BY_STRUCTURE.popitem(last=False)
            _BY_STRUCTURE.move_to_end(key)
            return jitted, dynamic

    if inspect.ismethod(fn):
        # A bound method is a new object at every attribute access; its
        # function and instance are what stay the same.
        objs, ref = (fn.__func__, fn.__self__), weakref.WeakMethod(fn)
    else:
        objs, ref = (fn,), None
    try:
        ref = ref or weakref.ref(fn)
        return _BY_IDENTITY.get(objs, lambda: _jit_vmap(lambda _: ref())), []
    except TypeError:  # not weak-referenceable: compiled for this call only
        return _jit_vmap(lambda _: fn), []


# --------------------------------------------------------------------------
# Placing chunks on devices


@functools.lru_cache(maxsize=8)
def _mesh(devices: tuple) -> Mesh:
    return Mesh(np.array(devices), ("batch",))


def _shardings(shard: bool) -> tuple[Any, Any, int]:
    """``(batch sharding, replicated sharding, device count)`` of a sweep.
    ``shard=False`` (or one device): one local device, no mesh."""
    devices = tuple(jax.devices())
    if shard and len(devices) > 1:
        mesh = _mesh(devices)
        return NamedSharding(mesh, PartitionSpec("batch")), NamedSharding(mesh, PartitionSpec()), len(devices)
    one = SingleDeviceSharding(jax.local_devices()[0])
    return one, one, 1


def _place(x: np.ndarray, sharding) -> jax.Array:
    """The global array ``x`` (the same on every process) on ``sharding``: each
    process puts only the slices its own devices hold."""
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def _host_leaf(x: Any) -> np.ndarray:
    """A batched argument's leaf as a host array of jax's dtype for it (float64
    becomes float32 unless x64 is enabled, as `jnp.asarray` would do)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        raise ValueError(
            f"a batched argument of shape {x.shape} lives partly on other processes; pass the whole batch "
            "(a NumPy array, the same on every process) and the sweep feeds each process its own rows"
        )
    a = np.asarray(x)
    return a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False)


def _to_host(out: Any, m: int) -> Any:
    """The first ``m`` rows of a chunk's output as NumPy arrays, gathered from
    every process when some rows live on other processes."""

    def get(x):
        a = np.asarray(x) if x.is_fully_addressable else multihost_utils.process_allgather(x, tiled=True)
        return a[:m]

    return jax.tree_util.tree_map(get, out)


# --------------------------------------------------------------------------
# The chunks


def _check_chunk_size(chunk_size: Any, name: str = "chunk_size") -> int:
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"{name} must be a positive int, got {chunk_size!r}")
    return int(chunk_size)


# A step's working set per member, in bytes, that the default cache chunk
# budgets for.  The compiled RKMK4 step of the free body (float64) is about 22
# kernels that write about 100 numbers per member (0.8 KB): stages, their sums,
# the exponential's coefficients.  A block also pays a fixed cost per step (a
# few microseconds of loop and kernel dispatch), which blocks of a few hundred
# members amortise.  With a 512 KiB L2 this gives blocks of 512; measurements
# in benchmarks/results/sweep-cache-blocks.md.
_WORKING_SET_PER_MEMBER = 1024
_CACHE_CHUNK_FALLBACK = 512  # when the L2 size cannot be read
_CACHE_CHUNK_RANGE = (32, 4096)


@functools.lru_cache(maxsize=1)
def _l2_bytes(base: str = "/sys/devices/system/cpu/cpu0/cache") -> int | None:
    """The L2 (data or unified) cache of the first CPU core in bytes, from
    Linux's sysfs (``base``); None where it cannot be read."""
    try:
        for index in sorted(os.listdir(base)):
            if not index.startswith("index"):
                continue

            def read(name, index=index):
                with open(os.path.join(base, index, name)) as f:
                    return f.read().strip()

            if read("level") == "2" and read("type") in ("Unified", "Data"):
                size = read("size")
                scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(size[-1:].upper(), 1)
                value = int(size.rstrip("KMGkmg")) * scale
                return value if value > 0 else None
    except (OSError, ValueError):
        pass
    return None


def _cores_per_cpu_device() -> float:
    """The cores this process may run on, over its CPU devices (1 when the
    CPU is split into one XLA host device per core)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        cores = os.cpu_count() or 1
    return cores / max(1, len(jax.local_devices(backend="cpu")))


def _default_cache_chunk(platform: str) -> int | None:
    """The members a CPU core steps together by default: the largest power of
    two whose working set fits the L2 cache (`_WORKING_SET_PER_MEMBER` each),
    within `_CACHE_CHUNK_RANGE`; `_CACHE_CHUNK_FALLBACK` when the L2 size is
    unknown.

    None (the whole share at once) on a CPU device that spans several cores:
    XLA splits a large batch's loops over the device's cores (the compiled
    ops' ``outer_dimension_partitions``), which a block of a few hundred
    members is too small for, so blocks would trade every core but one for
    the cache.  None on other devices too: a GPU wants every member in
    flight."""
    if platform != "cpu" or _cores_per_cpu_device() > 1:
        return None
    l2 = _l2_bytes()
    if l2 is None:
        return _CACHE_CHUNK_FALLBACK
    lo, hi = _CACHE_CHUNK_RANGE
    members = max(1, l2 // _WORKING_SET_PER_MEMBER)
    return min(hi, max(lo, 1 << (members.bit_length() - 1)))


def _check_cache_chunk(cache_chunk: Any) -> int | None:
    return None if cache_chunk is None else _check_chunk_size(cache_chunk, "cache_chunk")


def _batch_size(batched_args: tuple) -> int:
    leaves = jax.tree_util.tree_leaves(batched_args)
    if not leaves:
        raise ValueError("sweep needs at least one batched argument")
    sizes = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(
            f"every leaf of the batched arguments needs the same leading axis, got lengths {sorted(map(str, sizes))}"
        )
    (n,) = sizes
    if n == 0:
        raise ValueError("sweep over an empty batch (leading axis of length 0)")
    return n


def _dispatch(
    fn, batched_args, n: int, chunk: int, skip: frozenset, shard: bool, compiling=None, cache_chunk=None
) -> Iterator[tuple[int, int, int, Any]]:
    """``(index, start, stop, out)`` per chunk not in ``skip``, where ``out`` is
    the padded chunk's output on the devices, dispatched but not waited for.
    With ``compiling`` (a context-manager factory, e.g. `Progress.compiling`),
    the program is compiled ahead of the first chunk inside it, so that a
    progress display shows compilation as its own phase (jit's cache then
    serves the first call).

    Every chunk is padded to the same ``padded`` rows (the chunk size rounded
    up to a multiple of the device count) with copies of its last member, so
    one compiled shape serves them all.  The copies are valid inputs: they
    cannot fail or produce NaNs of their own.  Inside the program each
    device runs its rows ``cache_chunk`` at a time (`_in_blocks`; None: the
    device's default, `_default_cache_chunk`).
    """
    chunk = min(chunk, n)
    batch_sharding, replicated, n_dev = _shardings(shard)
    mesh = batch_sharding.mesh if n_dev > 1 else None
    padded = -(-chunk // n_dev) * n_dev
    block = cache_chunk or _default_cache_chunk(next(iter(batch_sharding.device_set)).platform)
    if block is not None and block >= padded // n_dev:
        block = None  # one block holds a device's share: the plain vmap, one program for all such values
    jitted, dynamic = _compiled(fn)
    dynamic = [_place(_host_leaf(x), replicated) if n_dev > 1 else x for x in dynamic]

    leaves, treedef = jax.tree_util.tree_flatten(batched_args)
    if chunk == n == padded and all(
        isinstance(x, jax.Array) and x.sharding.is_equivalent_to(batch_sharding, x.ndim) for x in leaves
    ):
        # Already where the sweep would put it (e.g. a previous sweep's output).
        yield 0, 0, n, jitted(mesh, block, dynamic, *jax.tree_util.tree_unflatten(treedef, leaves))
        return
    leaves = [_host_leaf(x) for x in leaves]
    for index in range(math.ceil(n / chunk)):
        if index in skip:
            continue
        start, stop = index * chunk, min(index * chunk + chunk, n)
        if stop - start == padded:
            rows = slice(start, stop)  # a view, no copy
        else:
            rows = np.minimum(np.arange(start, start + padded), stop - 1)
        args = jax.tree_util.tree_unflatten(treedef, [_place(x[rows], batch_sharding) for x in leaves])
        if compiling is not None:
            with compiling():
                jitted.lower(mesh, block, dynamic, *args).compile()
            compiling = None
        yield index, start, stop, jitted(mesh, block, dynamic, *args)


def sweep_chunks(
    fn: Callable[..., Any],
    *batched_args: Any,
    chunk_size: int,
    skip: Iterable[int] = (),
    shard: bool = True,
    compiling: Callable[[], Any] | None = None,
    cache_chunk: int | None = None,
) -> Iterator[tuple[int, int, int, Any]]:
    """``jax.vmap(fn)`` over the batch, one chunk at a time, results on the host.

    Yields ``(chunk_index, start, stop, out)`` for the members ``start:stop``
    of chunk ``chunk_index = start // chunk_size``, in order, where ``out`` is
    ``fn``'s output pytree for those members as NumPy arrays with a leading
    axis of length ``stop - start``.  Chunk ``k`` always covers members
    ``k * chunk_size`` to ``min((k + 1) * chunk_size, N)``, so a resumed run
    with the same ``chunk_size`` can ``skip`` the chunks it already has.

    Every chunk, the last included, runs at the same padded shape (the chunk
    size rounded up to a multiple of the device count, padded with copies of
    the chunk's last member, which are dropped), so a sweep compiles once, and
    a later sweep of ``fn`` with the same chunk size, dtypes and devices
    compiles nothing (see `sweep` for what "the same ``fn``" means).  The
    next chunk is dispatched before the current one is copied to the host,
    so at most two chunks' outputs exist at a time: memory is bounded by the
    chunk size, not by ``N``.  Inside the program, each device steps its
    share of a chunk ``cache_chunk`` members at a time, as in `sweep`.

    After `lierk.app.distributed.initialize`, every process calls this with the
    same arguments, ``skip`` included (the whole batch, e.g. a grid computed
    on each process): each chunk is computed by all processes together, each
    feeding only the rows of its own devices, and every process receives
    every chunk's whole output (gathered over the processes).

    Args:
        fn: function of one batch member's arguments; jit-compatible.
            Unbatched values belong in its closure, a `functools.partial` or
            an `equinox.Module` (their arrays are not recompiled for).
        *batched_args: pytrees whose leaves (array-likes) have a leading axis
            of the same length ``N``: the whole batch, on every process.
        chunk_size: members per chunk, a positive int (``>= N``: one chunk).
        skip: chunk indices to leave out, e.g. the ones a resumed run has
            already written; each must be a chunk index ``0 <= k < ceil(N /
            chunk_size)``.
        shard: split each chunk over all devices (of all processes).  With
            ``False`` each process runs every chunk on its first local device.
        compiling: a context-manager factory (e.g. a progress display's
            "compiling" phase) inside which the program is compiled before
            the first chunk runs; None compiles at the first chunk's call.
        cache_chunk: members each device steps together inside the
            program, a positive int or None (the default for the device),
            as in `sweep`.

    Raises:
        ValueError: ``chunk_size`` or ``cache_chunk`` not a positive int
            (``cache_chunk`` None is the default); ``skip`` holding
            something that is not a chunk index; batched arguments without a
            common leading axis, or an empty batch.

    Example:
        With ``final_R`` and ``omega0s`` of `sweep`'s example:

        >>> for k, start, stop, R in lierk.sweep_chunks(final_R, omega0s, chunk_size=256):
        ...     np.save(f"out/R_{k:04d}.npy", R)  # (stop - start, 3, 3)
    """
    chunk = _check_chunk_size(chunk_size)
    block = _check_cache_chunk(cache_chunk)
    n = _batch_size(batched_args)
    n_chunks = math.ceil(n / chunk)
    skip = frozenset(skip)
    bad = [k for k in skip if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k < n_chunks]
    if bad:
        raise ValueError(
            f"skip holds {bad[0]!r}, which is not a chunk index: {n} members in chunks of {chunk} "
            f"make chunks 0 to {n_chunks - 1}"
        )
    return _host_chunks(_dispatch(fn, batched_args, n, chunk, skip, shard, compiling, block))


def _host_chunks(dispatched: Iterator) -> Iterator[tuple[int, int, int, Any]]:
    # A generator of its own, so that sweep_chunks checks its arguments when
    # called, not at the first next().
    pending = None
    for item in dispatched:
        if pending is not None:
            k, start, stop, out = pending
            yield k, start, stop, _to_host(out, stop - start)
        pending = item
    if pending is not None:
        k, start, stop, out = pending
        yield k, start, stop, _to_host(out, stop - start)


def sweep(
    fn: Callable[..., Any],
    *batched_args: Any,
    chunk_size: int | None = None,
    progress: bool = False,
    shard: bool = True,
    cache_chunk: int | None = None,
) -> Any:
    """``jax.vmap(fn)(*batched_args)``, sharded over devices, compiled once per
    function, optionally in chunks.

    Every leaf of every argument is mapped over its leading axis, and all
    leaves must share that axis's length ``N``.  Arguments that should not be
    mapped belong in ``fn``'s closure, a `functools.partial` or an
    `equinox.Module` (whose array leaves can change without recompiling).

    The batch (or each chunk) is padded to a multiple of the device count with
    copies of its last member, split over a 1-d `Mesh` of `jax.devices()` with
    a `NamedSharding`, and the padding is dropped from the result.  The chunks
    run on `sweep_chunks`' machinery, all at one compiled shape.

    Inside the compiled program, each device steps its rows ``cache_chunk``
    members at a time (a ``lax.map`` over ``vmap(fn)`` of blocks of equal
    size, at most ``cache_chunk``; the last block padded with copies of its
    last row, whose output is dropped), so that a step's temporaries stay in
    the core's cache instead of streaming through memory for the whole
    batch.  The default (``None``), where each CPU device has a core of its
    own (the CPU split into one XLA host device per core, as ``lierk
    --devices N`` does), is the largest power of two whose members' working
    set (budgeted at 1 KiB each) fits the L2 cache of a core, read on Linux
    from ``/sys/devices/system/cpu``, and 512 where that cannot be read;
    between 32 and 4096.  Elsewhere the default is the device's whole share
    at once: on a CPU device that spans several cores (JAX's default of one
    CPU device), XLA spreads a large batch's loops over its cores, which
    blocks would undo; a GPU wants every member in flight.  Results equal an
    unblocked ``vmap`` of ``fn`` to rounding (the members are computed
    independently; a vectorised loop of another length can round a member's
    last bit differently); an adaptive solve stops each block when its own
    members are done.  Measurements: ``benchmarks/results/sweep.md``.

    Compiled once: the compiled ``jit(vmap(fn))`` is cached per function, and
    jit's own cache adds the shapes, dtypes and shardings, so a second call
    with the same ``fn``, shapes, dtypes and devices compiles nothing.  What
    counts as the same ``fn``:

    - A plain function, method or callable object is keyed on its identity
      and held only weakly: its compiled code is freed with it.  A lambda or
      closure created anew for each call is a new function every time and is
      compiled every time.  Define it once, outside the loop, and pass what
      changes as arrays: in a batched argument, a `functools.partial` or an
      `equinox.Module`.
    - A `functools.partial` or a pytree callable (an `equinox.Module` with a
      ``__call__``) is keyed on its structure and its non-array parts; its
      array leaves (inertia, step sizes, ...) are traced arguments.  A new
      partial or module that differs only in array *values* reuses the
      compiled code.  Python numbers in it are structure (as in
      `equinox.filter_jit`): a new number compiles again.  These entries keep
      their function alive, so a small least-recently-used cache holds them
      (the last 64 structures).

    After `lierk.app.distributed.initialize`, every process calls ``sweep`` with
    the same arguments; each process computes the rows of its own devices, and
    every process gets the whole result back.

    Args:
        fn: function of one batch member's arguments; jit-compatible.
        *batched_args: pytrees whose leaves (array-likes) have a leading axis
            of length ``N``.
        chunk_size: evaluate at most this many members per call, so that the
            intermediate memory of ``fn`` (saved trajectories) is bounded;
            ``None``: all ``N`` at once.
        progress: draw a progress bar on stderr, one tick per chunk.
        shard: split each chunk over all devices.  With ``False``: one local
            device.
        cache_chunk: members each device steps together inside the
            program, a positive int; ``>=`` the device's share of a chunk:
            all of them at once (a plain ``vmap``); ``None``: the default
            above.  Each value is a static part of the compiled program.

    Returns:
        The output pytree of ``fn`` with a leading axis of length ``N`` on
            every leaf, as JAX arrays (sharded over the devices in a single
            process; on a multi-process run, gathered onto this process's
            first device).

    Raises:
        ValueError: ``chunk_size`` or ``cache_chunk`` not a positive int
            or None; batched arguments without a common leading axis, or an
            empty batch.

    Example:
        >>> I = lierk.inertia.tee_handle()
        >>> omega0s = np.random.default_rng(0).normal(size=(1000, 3))  # rad/s
        >>> def final_R(omega0):
        ...     body = lierk.FreeRigidBody(I, omega0)
        ...     return lierk.solve(body, lierk.RKMK4(), 10.0, dt=0.01, max_steps=1000).R[-1]
        >>> Rs = lierk.sweep(final_R, omega0s, chunk_size=500)  # (1000, 3, 3)
    """
    n = _batch_size(batched_args)
    chunk = n if chunk_size is None else _check_chunk_size(chunk_size)
    block = _check_cache_chunk(cache_chunk)
    bar = None
    if progress:
        from ._progress import Progress

        bar = Progress("sweep", n, " members")
    pieces = []
    compiling = None if bar is None else bar.compiling
    for _, start, stop, out in _dispatch(fn, batched_args, n, chunk, frozenset(), shard, compiling, block):
        pieces.append((stop - start, out))
        if bar is not None:
            jax.block_until_ready(out)
            bar.update(stop)
    if not all(x.is_fully_addressable for _, out in pieces for x in jax.tree_util.tree_leaves(out)):
        parts = [_to_host(out, m) for m, out in pieces]
        return jax.tree_util.tree_map(lambda *xs: jnp.asarray(np.concatenate(xs)), *parts)
    parts = [jax.tree_util.tree_map(lambda x, m=m: x if x.shape[0] == m else x[:m], out) for m, out in pieces]
    if len(parts) == 1:
        return parts[0]
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *parts)
