"""Compiled programs kept on disk between runs, keyed to this machine.

JAX can keep the programs it compiles in a directory (its persistent
compilation cache) and load them in a later process instead of compiling
again.  The library never turns that on by itself.  The command line does
(`lierk --no-cache`, or ``LIERK_NO_CACHE=1``, turns it off), and a script
opts in with one line before its first solve::

    jax.config.update("jax_compilation_cache_dir", str(lierk.app.cache.compilation_cache_dir()))

Only programs that took at least a second to compile are kept unless
``jax_persistent_cache_min_compile_time_secs`` is lowered too (the command
line keeps every program: its many small ones add up).  `using_cache` does
what the command line does, for one block, and puts the settings back
after it::

    with lierk.app.cache.using_cache() as use:
        sol = scene.solve()
    print(use.summary())  # compiled programs: 3 loaded from the cache, 12 compiled and saved (...)

The directory is ``$LIERK_CACHE_DIR``, else the platform's user cache
directory (``$XDG_CACHE_HOME/lierk`` or ``~/.cache/lierk`` on Linux,
``~/Library/Caches/lierk`` on macOS, ``%LOCALAPPDATA%\\lierk\\Cache`` on
Windows), and within it one subdirectory per machine fingerprint: the jax
and jaxlib versions, the processor architecture and its instruction-set
features.  JAX's own key covers the program, the compile options and the
backend, but on a CPU not the instruction-set features, so a cache shared
between machines (a home directory on a cluster) could otherwise hand a
program built for one CPU to another.  JAX reads a corrupted entry as a miss
and compiles again.

JAX finds a program in its cache by the lowered program, so a warm run still
traces and lowers it.  `compiled` keeps a whole executable instead, under a
key made without tracing (what the function closes over, the arguments'
values, lierk's source, the machine, JAX's settings): the command line's
scene solves go through it, and a warm run loads them without tracing.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

__all__ = ["CacheUse", "compilation_cache_dir", "compiled", "default_cache_root", "machine_fingerprint", "using_cache"]


def default_cache_root() -> Path:
    """``$LIERK_CACHE_DIR``, else the platform's user cache directory for lierk."""
    if os.environ.get("LIERK_CACHE_DIR"):
        return Path(os.environ["LIERK_CACHE_DIR"]).expanduser()
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or str(Path.home() / "AppData" / "Local")
        return Path(base) / "lierk" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "lierk"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lierk"


def _cpu_features() -> str:
    """The processor's instruction-set features (Linux: the ``flags`` of
    /proc/cpuinfo), or its name where they cannot be read."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return " ".join(sorted(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return platform.processor()


def machine_fingerprint() -> str:
    """16 hex digits naming the jax and jaxlib versions, the architecture and
    the CPU's features: programs compiled under one fingerprint run under it."""
    import jax
    import jaxlib

    text = f"{jax.__version__} {jaxlib.__version__} {platform.machine()} {_cpu_features()}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def compilation_cache_dir(root: str | os.PathLike | None = None) -> Path | None:
    """The directory for this machine's compiled programs, created:
    ``root/<machine_fingerprint()>`` (``root`` defaults to
    `default_cache_root`).

    Returns ``None`` after one warning when the directory cannot be created
    or written (read-only, full, not a directory): a run then compiles as if
    there were no cache, and never fails for it.
    """
    root = Path(root).expanduser() if root is not None else default_cache_root()
    path = root / machine_fingerprint()
    try:
        path.mkdir(parents=True, exist_ok=True)
        # Creating the directory is not enough: a full disk or a read-only
        # mount shows only when a file is written.
        with tempfile.NamedTemporaryFile(dir=path, prefix=".probe-") as f:
            f.write(b"0" * 4096)
            f.flush()
    except OSError as e:
        warnings.warn(f"compilation cache off: {path} is not writable ({e.strerror or e})", stacklevel=2)
        return None
    return path


_CACHE_SETTINGS = ("jax_enable_compilation_cache", "jax_compilation_cache_dir",
                   "jax_persistent_cache_min_compile_time_secs")
# JAX's warnings about one entry (a corrupted file, a full disk), by what they count as.
_ENTRY_WARNINGS = (("unreadable", "Error reading persistent compilation cache"),
                   ("unwritable", "Error writing persistent compilation cache"))


class CacheUse:
    """What the compilation cache did in a `using_cache` block.

    Attributes:
        path: the cache directory, as text; None while the cache is off.
        counts: ``"hits"`` (programs loaded), ``"misses"`` (programs compiled
            and saved), ``"unsaved"`` (programs compiled and not saved: JAX
            keeps no program with a host callback, such as an
            ``eqx.error_if`` check on a traced value, nor one quicker to
            compile than its threshold), ``"unreadable"`` (entries that could
            not be read and were compiled again) and ``"unwritable"``
            (programs that could not be saved).
    """

    def __init__(self):
        self.path: str | None = None
        self.counts = {"hits": 0, "misses": 0, "unsaved": 0, "unreadable": 0, "unwritable": 0}
        # JAX's events, and `compiled`'s own executables, counted apart.
        self._jax = {"requests": 0, "hits": 0, "misses": 0}
        self._own = {"hits": 0, "misses": 0, "unsaved": 0}

    def _listen(self, event: str, **_) -> None:
        for name, key in (("compile_requests_use_cache", "requests"), ("cache_hits", "hits"),
                          ("cache_misses", "misses")):
            if event == f"/jax/compilation_cache/{name}":
                self._jax[key] += 1
        self._tally()

    def _count(self, key: str) -> None:
        """One of `compiled`'s executables: ``"hits"``, ``"misses"``,
        ``"unsaved"`` or ``"unreadable"``."""
        if key == "unreadable":
            self.counts[key] += 1
        else:
            self._own[key] += 1
        self._tally()

    def _tally(self) -> None:
        j, o = self._jax, self._own
        self.counts.update(hits=j["hits"] + o["hits"], misses=j["misses"] + o["misses"],
                           unsaved=j["requests"] - j["hits"] - j["misses"] + o["unsaved"])

    def _count_warning(self, message) -> bool:
        """Count JAX's warning about one entry it could not read or write;
        False for any other warning."""
        text = str(message)
        for key, start in _ENTRY_WARNINGS:
            if text.startswith(start):
                self.counts[key] += 1
                return True
        return False

    def summary(self) -> str | None:
        """One line: programs loaded, compiled and saved, the directory, and
        entries that could not be read or written; None if the cache was off."""
        if self.path is None:
            return None
        c = self.counts
        line = f"compiled programs: {c['hits']} loaded from the cache, {c['misses']} compiled and saved ({self.path})"
        if c["unsaved"]:
            line += f"; {c['unsaved']} compiled and not saved"
        if c["unreadable"]:
            line += f"; {c['unreadable']} cached programs could not be read and were compiled again"
        if c["unwritable"]:
            line += f"; {c['unwritable']} could not be saved"
        return line


@contextlib.contextmanager
def using_cache(enabled: bool = True) -> Iterator[CacheUse]:
    """Keep compiled programs between runs for the duration of a block, and
    count what the cache did (the `CacheUse` yielded).  JAX's settings are
    put back after the block.

    JAX's cache settings are process-wide, which is why the library never
    changes them outside such a block; the command line runs each command in
    one.  With ``enabled=False``, or ``LIERK_NO_CACHE`` set (other than
    ``0``), JAX's cache is off in the block.  Otherwise a directory the user
    gave JAX (``jax_compilation_cache_dir``, ``JAX_COMPILATION_CACHE_DIR``)
    is used with its own settings; without one, `compilation_cache_dir`'s
    (after one warning, none if it cannot be written: the block then runs
    uncached) keeps every program, however quickly it compiled: many small
    programs add up to seconds.  Nothing happens if JAX's cache was turned
    off (``jax_enable_compilation_cache``).  The settings hold for the block
    even in a process that compiled before it, with or without a cache.

    JAX's warning about each entry it cannot read (then compiles again) or
    write is counted in the `CacheUse` instead of shown; other warnings pass
    through.
    """
    import jax
    from jax.experimental.compilation_cache.compilation_cache import reset_cache

    before = {name: getattr(jax.config, name) for name in _CACHE_SETTINGS}
    use = CacheUse()
    _active.append(use)
    listening = False
    try:
        with warnings.catch_warnings():
            shown = warnings.showwarning

            def show(message, *args, **kwargs):
                if not use._count_warning(message):
                    shown(message, *args, **kwargs)

            warnings.showwarning = show
            # Every unreadable entry counts, not only the first of each name.
            warnings.filterwarnings("always", message="Error (reading|writing) persistent compilation cache")
            if not enabled or os.environ.get("LIERK_NO_CACHE", "") not in ("", "0"):
                jax.config.update("jax_enable_compilation_cache", False)
            elif before["jax_enable_compilation_cache"]:
                use.path = _cache_path(before["jax_compilation_cache_dir"])
                if use.path is not None:
                    jax.monitoring.register_event_listener(use._listen)
                    listening = True
            # JAX decides at its first compilation whether a process uses the
            # cache, and keeps to that: make it read the settings anew.
            reset_cache()
            yield use
    finally:
        _active.remove(use)
        if listening:
            jax.monitoring.unregister_event_listener(use._listen)
        for name, value in before.items():
            if getattr(jax.config, name) != value:
                jax.config.update(name, value)
        reset_cache()


def _cache_path(given: str | None) -> str | None:
    """The directory JAX was given, else `compilation_cache_dir`'s, set in
    JAX's config to keep every program; None if that cannot be written."""
    import jax

    if given:
        return str(given)
    path = compilation_cache_dir()
    if path is None:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return str(path)


# --------------------------------------------------------------------------
# Whole executables, keyed without tracing

# JAX's cache is keyed by the lowered program, so a warm run still traces and
# lowers every program to find its entry (0.65 s of a warm T-handle simulate's
# 2.5).  `compiled` keys a program by what determines it instead (the function
# with everything it closes over, the arguments, lierk's source, the machine
# and JAX's settings) and keeps the executable itself.

_EXECUTABLES = "executables"
# Executables kept at most (a few MB each; every change to lierk's source makes new keys): the least recently used go.
_KEEP = 64
_active: list[CacheUse] = []


class _Slot:
    """Where an output array goes in a kept executable's output."""

    def __init__(self, index: int):
        self.index = index


class _Unkeyable(Exception):
    """A value `_fingerprint` cannot describe exactly: no key, no cache."""


def _source_hash() -> str:
    """The hash of lierk's Python sources: any change to the library is a new key."""
    if not hasattr(_source_hash, "value"):
        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for path in sorted(root.rglob("*.py")):
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
        _source_hash.value = h.hexdigest()
    return _source_hash.value


def _fingerprint(x, h, memo: dict, depth: int = 0) -> None:
    """Feed ``h`` a description of ``x`` that another process gives for an
    equal value: arrays by dtype, shape and bytes; functions by code,
    defaults and closure; modules, dataclasses and plain objects by class and
    fields.  Raises `_Unkeyable` for anything else."""
    import dataclasses
    import enum
    import functools
    import types

    import numpy as np

    if depth > 60:
        raise _Unkeyable("too deep")
    if id(x) in memo:
        h.update(f"@{memo[id(x)][0]}".encode())
        return
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
        h.update(f"{type(x).__name__}:{x!r};".encode())
        return
    # The value is held with its number: a temporary freed during the walk
    # could otherwise lend its id to a later, different value.
    memo[id(x)] = (len(memo), x)
    down = functools.partial(_fingerprint, h=h, memo=memo, depth=depth + 1)
    if hasattr(x, "__array__") and hasattr(x, "dtype") and hasattr(x, "shape"):
        a = np.asarray(x)
        h.update(f"array:{a.dtype.str}:{a.shape}:{type(x).__name__};".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    elif isinstance(x, (np.generic,)):
        h.update(f"{x.dtype.str}:{x!r};".encode())
    elif isinstance(x, (tuple, list, frozenset, set)):
        items = sorted(x, key=repr) if isinstance(x, (set, frozenset)) else x
        h.update(f"{type(x).__name__}[{len(items)}];".encode())
        for item in items:
            down(item)
    elif isinstance(x, dict):
        h.update(f"dict[{len(x)}];".encode())
        for k in sorted(x, key=repr):
            down(k)
            down(x[k])
    elif isinstance(x, type):
        h.update(f"type:{x.__module__}.{x.__qualname__};".encode())
    elif isinstance(x, types.CodeType):
        h.update(f"code:{x.co_qualname if hasattr(x, 'co_qualname') else x.co_name}:{x.co_names}:{x.co_varnames};".encode())
        h.update(x.co_code)
        for c in x.co_consts:
            down(c)
    elif isinstance(x, types.FunctionType):
        h.update(f"function:{x.__module__}.{x.__qualname__};".encode())
        down(x.__code__)
        down(x.__defaults__)
        down(x.__kwdefaults__)
        down(tuple(c.cell_contents for c in (x.__closure__ or ())))
    elif isinstance(x, types.MethodType):
        h.update(b"method;")
        down(x.__func__)
        down(x.__self__)
    elif isinstance(x, functools.partial):
        h.update(b"partial;")
        down(x.func)
        down(x.args)
        down(x.keywords)
    elif isinstance(x, (types.BuiltinFunctionType, types.ModuleType, np.ufunc)):
        # Library code, whose versions are in the key.
        h.update(f"named:{getattr(x, '__module__', '')}.{getattr(x, '__qualname__', x.__name__)};".encode())
    elif isinstance(getattr(x, "__wrapped__", None), types.FunctionType) and x.__module__.startswith("lierk."):
        # lierk's jitted functions: their options are in lierk's source.
        h.update(f"wrapped:{type(x).__name__};".encode())
        down(x.__wrapped__)
    elif isinstance(x, enum.Enum):
        h.update(f"enum:{type(x).__qualname__}.{x.name};".encode())
    elif dataclasses.is_dataclass(x):
        # equinox Modules among them: every field, static or not.
        h.update(f"dataclass:{type(x).__module__}.{type(x).__qualname__};".encode())
        for f in dataclasses.fields(x):
            h.update(f.name.encode())
            down(getattr(x, f.name, None))
    elif hasattr(x, "__dict__") and type(x).__module__.startswith("lierk"):
        h.update(f"object:{type(x).__module__}.{type(x).__qualname__};".encode())
        down(vars(x))
    else:
        raise _Unkeyable(f"{type(x).__module__}.{type(x).__qualname__}")


@contextlib.contextmanager
def _jax_cache_off():
    """JAX's persistent cache off for the block (it decides once per process
    whether to use it: `reset_cache` makes it read the setting anew)."""
    import jax
    from jax.experimental.compilation_cache.compilation_cache import reset_cache

    jax.config.update("jax_enable_compilation_cache", False)
    reset_cache()
    try:
        yield
    finally:
        jax.config.update("jax_enable_compilation_cache", True)
        reset_cache()


def _prune(directory: Path, keep: int = _KEEP) -> None:
    """Delete all but the ``keep`` most recently used executables in ``directory``."""
    entries = []
    for p in directory.glob("*.bin"):
        with contextlib.suppress(OSError):
            entries.append((p.stat().st_mtime, p))
    for _, p in sorted(entries, reverse=True)[keep:]:
        with contextlib.suppress(OSError):
            p.unlink()


def _executable_key(fun, args) -> str | None:
    """The key of ``fun(*args)``'s executable, or None where some value in
    them cannot be described exactly."""
    import jax

    import equinox as eqx
    import numpy as np

    h = hashlib.sha256()
    settings = {name: getattr(jax.config, name) for name in ("jax_enable_x64", "jax_default_matmul_precision",
                                                              "jax_numpy_rank_promotion", "jax_debug_nans",
                                                              "jax_numpy_dtype_promotion")}
    # XLA's flags, equinox's error mode and JAX's own settings in the environment.
    env = sorted((k, v) for k, v in os.environ.items()
                 if k.startswith(("XLA_", "JAX_", "EQX_")) and "CACHE" not in k)
    h.update(f"{_source_hash()} {machine_fingerprint()} equinox {eqx.__version__} numpy {np.__version__} "
             f"{jax.default_backend()} "
             f"{[d.device_kind for d in jax.devices()]} {env} {settings}".encode())
    try:
        _fingerprint((fun, args), h, {})
    except _Unkeyable:
        return None
    return h.hexdigest()[:32]


def compiled(fun, *args):
    """``eqx.filter_jit(fun).lower(*args).compile()``: a callable of arguments
    like ``args`` (the same structure and non-array values, arrays of the
    same shapes and dtypes) returning what ``fun`` returns.

    Inside a `using_cache` block with the cache on, the executable is kept
    in the cache directory (``executables/``) under a key made without
    tracing: ``fun``'s code and everything it closes over, every value in
    ``args``, lierk's source, the versions of jax, jaxlib, equinox and NumPy,
    the machine, JAX's settings and its ``XLA_``, ``JAX_`` and ``EQX_``
    environment.  A later process with the same key loads it without tracing
    or lowering (counted as loaded in `CacheUse`).  Module globals that
    ``fun`` reads are not in the key: only lierk's own, through its source.
    A value the key cannot describe exactly (an object of a class outside
    lierk that is no dataclass), an executable that cannot be kept (a host
    callback, a custom call other than LAPACK's) and an entry that cannot be
    read compile as usual, through JAX's cache."""
    import pickle

    import equinox as eqx
    import jax

    jitted = eqx.filter_jit(fun)
    directory = jax.config.jax_compilation_cache_dir if _active and jax.config.jax_enable_compilation_cache else None
    key = _executable_key(fun, args) if directory else None
    if key is None:
        return jitted.lower(*args).compile()
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, tree = jax.tree_util.tree_flatten(dynamic)
    path = Path(directory) / _EXECUTABLES / f"{key}.bin"
    start = time.time()
    try:
        data = path.read_bytes()
        # The checksum first: a damaged executable must never reach XLA.
        if hashlib.sha256(data[32:]).digest() != data[:32]:
            raise ValueError("checksum")
        payload, in_tree, out_tree, skeleton, lapack = pickle.loads(data[32:])
        from jax.experimental.serialize_executable import deserialize_and_load

        if lapack:
            # JAX sets LAPACK's function table up when it lowers a LAPACK
            # call; an executable loaded without lowering finds it empty
            # (a segmentation fault).
            from jaxlib import lapack as jaxlib_lapack

            jaxlib_lapack._lapack.initialize()

        executable = deserialize_and_load(payload, in_tree, out_tree)
        _active[-1]._count("hits")
        with contextlib.suppress(OSError):
            os.utime(path)  # recently used: the last to be pruned
        from .compilations import LOADED

        jax.monitoring.record_event_time_span(LOADED, start, time.time(), fun_name=f"jit({fun.__name__})")
    except FileNotFoundError:
        executable = None
    except Exception:  # noqa: BLE001 - a damaged entry is a miss
        _active[-1]._count("unreadable")
        executable = None
    if executable is None:
        shapes = {}

        def flat(leaves):
            out = fun(*eqx.combine(jax.tree_util.tree_unflatten(tree, leaves), static))
            out_dynamic, shapes["static"] = eqx.partition(out, eqx.is_array)
            out_leaves, shapes["tree"] = jax.tree_util.tree_flatten(out_dynamic)
            return out_leaves

        # Compiled here, not loaded from JAX's cache: an executable that JAX
        # loaded from its cache serializes without its kernels' code (jax
        # 0.10: "Function ... not found" when the copy runs).
        with _jax_cache_off():
            executable = jax.jit(flat).lower(leaves).compile()
        # The output's structure travels as the output itself with a slot
        # for each array: a pickled PyTreeDef of equinox Modules does not
        # unflatten in another process.
        slots = [_Slot(i) for i in range(shapes["tree"].num_leaves)]
        skeleton = eqx.combine(jax.tree_util.tree_unflatten(shapes["tree"], slots), shapes["static"])
        try:
            import re

            from jax.experimental.serialize_executable import serialize

            # Kept only with the custom calls a load can set up (LAPACK's),
            # or none: others may need set-up that only lowering does.
            targets = set(re.findall(r'custom_call_target="([^"]+)"', executable.as_text()))
            if any(not t.startswith("lapack_") for t in targets):
                raise ValueError(f"custom calls {sorted(targets)}")
            payload, in_tree, out_tree = serialize(executable)
            blob = pickle.dumps((payload, in_tree, out_tree, skeleton, bool(targets)))
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(hashlib.sha256(blob).digest() + blob)
            os.replace(tmp, path)
            _active[-1]._count("misses")
            _prune(path.parent)
        except Exception:  # noqa: BLE001 - not serializable or not writable: compiled, not kept
            _active[-1]._count("unsaved")

    def call(*call_args):
        call_leaves = jax.tree_util.tree_leaves(eqx.filter(call_args, eqx.is_array))
        out = executable(call_leaves)
        return jax.tree_util.tree_map(lambda x: out[x.index] if isinstance(x, _Slot) else x, skeleton)

    return call
