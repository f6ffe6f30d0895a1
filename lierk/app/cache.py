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
import threading
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
# lowers every program to find its entry.  `compiled` keys a program by what
# determines it instead (the function with everything it reads, the
# arguments, lierk's source, the machine and JAX's settings) and keeps the
# executable itself.  A stale key would return another program's numbers
# without a word, so whatever the key cannot describe exactly means no key.

_EXECUTABLES = "executables"
# Executables kept at most (a few MB each; every change to lierk's source makes new keys): the least recently used go.
_KEEP = 64
_active: list[CacheUse] = []
# Classes whose objects are described by their fields: their methods are in these packages' source or versions.
_KNOWN = ("lierk.", "equinox.")


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


def _known(cls) -> bool:
    return cls.__module__.startswith(_KNOWN) or cls.__module__ in ("lierk", "equinox")


def _fingerprint(x, h, memo: dict, depth: int = 0) -> None:
    """Feed ``h`` a description of ``x`` that another process gives for an
    equal value: arrays by dtype, weak type, shape, placement and bytes;
    functions by their code object, defaults, closure and the module globals
    they name; containers in the order JAX flattens them; lierk's and
    equinox's dataclasses and objects by class and fields.  Raises
    `_Unkeyable` for anything else (a class of a user's own, whose methods the
    key cannot see; a tracer)."""
    import builtins
    import collections
    import dataclasses
    import enum
    import functools
    import marshal
    import types

    import jax
    import numpy as np

    if depth > 60:
        raise _Unkeyable("too deep")
    if id(x) in memo:
        h.update(f"@{memo[id(x)][0]};".encode())
        return
    if x is None or type(x) in (bool, int, float, complex, str, bytes):
        h.update(f"{type(x).__name__}:{x!r};".encode())
        return
    # The value is held with its number: a temporary freed during the walk
    # could otherwise lend its id to a later, different value.
    memo[id(x)] = (len(memo), x)
    down = functools.partial(_fingerprint, h=h, memo=memo, depth=depth + 1)
    if isinstance(x, jax.core.Tracer):
        raise _Unkeyable("a tracer")
    if isinstance(x, (np.ndarray, np.generic, jax.Array)):
        a = np.asarray(x)
        placed = f"{x.committed}:{x.sharding}" if isinstance(x, jax.Array) else ""
        h.update(f"array:{type(x).__name__}:{a.dtype.str}:{getattr(x, 'weak_type', False)}:{a.shape}:{placed};".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    elif type(x) in (tuple, list) or (isinstance(x, tuple) and hasattr(type(x), "_fields")):
        fields = getattr(type(x), "_fields", ())
        h.update(f"{type(x).__module__}.{type(x).__qualname__}{fields}[{len(x)}];".encode())
        for item in x:
            down(item)
    elif type(x) in (set, frozenset):
        # JAX does not flatten sets: only their members' values matter.
        h.update(f"{type(x).__name__}[{len(x)}];".encode())
        for item in sorted(x, key=repr):
            down(item)
    elif type(x) in (dict, collections.OrderedDict, collections.defaultdict):
        # A dict flattens in sorted key order, the others in insertion order.
        keys = sorted(x, key=repr) if type(x) is not collections.OrderedDict else list(x)
        h.update(f"{type(x).__qualname__}[{len(x)}];".encode())
        if type(x) is collections.defaultdict:
            down(x.default_factory)
        for k in keys:
            down(k)
            down(x[k])
    elif isinstance(x, types.CodeType):
        # Every field of the code, nested code objects included.
        h.update(b"code;")
        h.update(marshal.dumps(x))
    elif isinstance(x, types.FunctionType):
        h.update(f"function:{x.__module__}.{x.__qualname__};".encode())
        down(x.__code__)
        down(x.__defaults__)
        down(x.__kwdefaults__)
        try:
            down(tuple(c.cell_contents for c in (x.__closure__ or ())))
        except ValueError:  # an empty cell
            raise _Unkeyable("an empty closure cell") from None
        if not (x.__module__ or "").startswith(_KNOWN):
            # A global named in the code (an attribute name too: they share
            # co_names) is part of the program: lierk's own are in its source.
            for name in sorted(_names(x.__code__)):
                if name in x.__globals__:
                    h.update(f"global:{name};".encode())
                    down(x.__globals__[name])
                elif not hasattr(builtins, name):
                    h.update(f"unbound:{name};".encode())
    elif isinstance(x, types.MethodType):
        h.update(b"method;")
        down(x.__func__)
        down(x.__self__)
    elif isinstance(x, functools.partial):
        h.update(f"partial:{type(x).__qualname__};".encode())
        down(x.func)
        down(x.args)
        down(x.keywords)
    elif isinstance(x, types.ModuleType):
        h.update(f"module:{x.__name__};".encode())
    elif isinstance(x, (types.BuiltinFunctionType, np.ufunc)):
        # Library code, whose versions are in the key; a bound builtin's object too.
        h.update(f"builtin:{getattr(x, '__module__', None)}.{getattr(x, '__qualname__', x.__name__)};".encode())
        owner = getattr(x, "__self__", None)
        if owner is not None and not isinstance(owner, types.ModuleType):
            down(owner)
    elif isinstance(x, type):
        if not _known(x) and x.__module__ not in ("builtins", "numpy", "jax.numpy"):
            raise _Unkeyable(f"class {x.__module__}.{x.__qualname__}")
        h.update(f"type:{x.__module__}.{x.__qualname__};".encode())
    elif isinstance(x, enum.Enum) and _known(type(x)):
        h.update(f"enum:{type(x).__module__}.{type(x).__qualname__}.{x.name};".encode())
    elif isinstance(getattr(x, "__wrapped__", None), types.FunctionType) and _known(x.__wrapped__):
        # lierk's jitted functions: their options are in lierk's source.
        h.update(f"wrapped:{type(x).__name__};".encode())
        down(x.__wrapped__)
    elif dataclasses.is_dataclass(x) and _known(type(x)):
        # equinox Modules among them: every field, static or not.
        h.update(f"dataclass:{type(x).__module__}.{type(x).__qualname__};".encode())
        for f in dataclasses.fields(x):
            h.update(f"{f.name}=".encode())
            down(getattr(x, f.name, None))
    elif hasattr(x, "__dict__") and _known(type(x)):
        h.update(f"object:{type(x).__module__}.{type(x).__qualname__};".encode())
        down(vars(x))
    else:
        raise _Unkeyable(f"{type(x).__module__}.{type(x).__qualname__}")


def _names(code) -> set:
    """The global (and attribute) names a code object and those nested in it use."""
    import types

    names = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            names |= _names(c)
    return names


def _prune(directory: Path, keep: int = _KEEP) -> None:
    """Delete all but the ``keep`` most recently used executables in
    ``directory``, and temporary files a writer left over an hour ago."""
    entries = []
    for p in directory.iterdir():
        with contextlib.suppress(OSError):
            if p.suffix == ".bin":
                entries.append((p.stat().st_mtime, p))
            elif p.suffix == ".tmp" and time.time() - p.stat().st_mtime > 3600:
                p.unlink()
    for _, p in sorted(entries, reverse=True)[keep:]:
        with contextlib.suppress(OSError):
            p.unlink()


_CACHE_OFF = threading.Lock()


@contextlib.contextmanager
def _jax_cache_off():
    """JAX's persistent cache off for the block (it decides once per process
    whether to use it: `reset_cache` makes it read the setting anew).  One
    block at a time: a thread leaving it must not turn the cache back on
    under another's compilation."""
    import jax
    from jax.experimental.compilation_cache.compilation_cache import reset_cache

    with _CACHE_OFF:
        jax.config.update("jax_enable_compilation_cache", False)
        reset_cache()
        try:
            yield
        finally:
            jax.config.update("jax_enable_compilation_cache", True)
            reset_cache()


def _settings() -> str:
    """JAX's settings that are part of its own jit key (x64, the default
    device, PRNG, dtype promotion, ...) and lierk's host-checking context."""
    import re

    import jax
    from jax._src import config

    from ..checks import checking_on_host

    # Object reprs carry addresses, which differ in every process.
    text = re.sub(r" at 0x[0-9a-f]+", "", repr(config.trace_context()))
    return f"{text} {jax.config.jax_enable_x64} {checking_on_host()}"


def _aval(a) -> str:
    """What an executable sees of an array argument: its type, dtype, weak
    type, shape and placement."""
    import jax
    import numpy as np

    placed = f"{a.committed}:{a.sharding}" if isinstance(a, jax.Array) else ""
    return f"{type(a).__name__}:{np.dtype(a.dtype).str}:{getattr(a, 'weak_type', False)}:{np.shape(a)}:{placed}"


def _executable_key(fun, args, compiler_options=None) -> str | None:
    """The key of ``fun(*args)``'s executable compiled with
    ``compiler_options``, or None where some value in them cannot be
    described exactly."""
    import equinox as eqx
    import jax
    import numpy as np

    h = hashlib.sha256()
    try:
        # XLA's flags, equinox's error mode and JAX's own settings in the environment.
        env = sorted((k, v) for k, v in os.environ.items() if k.startswith(("XLA_", "JAX_", "EQX_")) and "CACHE" not in k)
        h.update(f"{_source_hash()} {machine_fingerprint()} {sys.version} equinox {eqx.__version__} "
                 f"numpy {np.__version__} {jax.default_backend()} {jax.devices()} {env} {_settings()} "
                 f"{sorted((compiler_options or {}).items())}".encode())
        # The order in which the arguments' arrays reach the executable.
        paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(args)[0]]
        h.update(repr(paths).encode())
        # The arguments' arrays are the executable's inputs: their values are
        # not in it, so another trajectory or inertia of the same shapes is
        # the same key (keyed by bytes, every new value compiled again).
        dynamic, static = eqx.partition(args, eqx.is_array)
        h.update(repr([_aval(a) for a in jax.tree_util.tree_leaves(dynamic)]).encode())
        _fingerprint((fun, static), h, {})
    except Exception:  # noqa: BLE001 - _Unkeyable, or anything else the walk meets: no key, no cache
        return None
    return h.hexdigest()[:32]


def keeps_executables() -> bool:
    """Whether `compiled` keeps and loads executables now: inside a
    `using_cache` block with JAX's cache on, in a local directory.
    Elsewhere it compiles on every call, so a function called more than
    once is better jitted."""
    import jax

    directory = jax.config.jax_compilation_cache_dir if _active and jax.config.jax_enable_compilation_cache else None
    return bool(directory) and "://" not in str(directory)


def compiled(fun, *args, compiler_options: dict | None = None):
    """``eqx.filter_jit(fun).lower(*args).compile(compiler_options)``: a callable of arguments
    like ``args`` (the same structure and non-array values, arrays of the
    same shapes and dtypes) returning what ``fun`` returns.

    Inside a `using_cache` block with the cache on, the executable is kept
    in the cache directory (``executables/``) under a key made without
    tracing: ``fun``'s code, everything it closes over and the module
    globals it names, the non-array values in ``args`` and the types,
    shapes, dtypes and placement of its arrays (their values are the
    executable's inputs, not part of it), lierk's source, the versions
    of Python, jax, jaxlib, equinox and NumPy, the machine and its devices,
    JAX's settings and its ``XLA_``, ``JAX_`` and ``EQX_`` environment.  A
    later process with the same key loads it without tracing or lowering
    (counted as loaded in `CacheUse`).  A value the key cannot describe
    exactly (an object of a class of one's own, which may have any methods),
    an executable that cannot be kept (a host callback, a custom call other
    than LAPACK's) and an entry that cannot be read compile as usual,
    through JAX's cache.  The entries are pickles: the cache directory must
    not be writable by anyone the user does not trust.

    ``compiler_options``: XLA's options for this compilation (part of the
    key), e.g. `lierk.one_body_compiler_options` for one body's solve.

    Raises:
        ValueError: the callable was given arguments of another structure or
            other non-array values than ``args``.
    """
    import pickle

    import equinox as eqx
    import jax

    jitted = eqx.filter_jit(fun)
    directory = jax.config.jax_compilation_cache_dir
    key = _executable_key(fun, args, compiler_options) if keeps_executables() else None
    if key is None:
        return jitted.lower(*args).compile(compiler_options)
    if key in _in_process:
        # Called again in this process (a loop of diagnostics): as a jitted
        # function's second call, no reading and loading again.
        return _in_process[key]
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, tree = jax.tree_util.tree_flatten(dynamic)
    path = Path(directory) / _EXECUTABLES / f"{key}.bin"
    name = f"jit({getattr(fun, '__name__', type(fun).__name__)})"
    start = time.time()
    executable = None
    try:
        data = path.read_bytes()
        # The checksum first: a damaged executable must never reach XLA.
        if hashlib.sha256(data[32:]).digest() != data[:32]:
            raise ValueError("checksum")
        payload, in_tree, out_tree, skeleton, lapack, device_ids = pickle.loads(data[32:])
        from jax.experimental.serialize_executable import deserialize_and_load

        if lapack:
            # JAX sets LAPACK's function table up when it lowers a LAPACK
            # call; an executable loaded without lowering finds it empty
            # (a segmentation fault).
            from jaxlib import lapack as jaxlib_lapack

            jaxlib_lapack._lapack.initialize()
        by_id = {d.id: d for d in jax.devices()}
        # On the devices it was compiled for (by default it would be loaded
        # onto every device: a one-device program then refused its arguments).
        executable = deserialize_and_load(payload, in_tree, out_tree,
                                          execution_devices=[by_id[i] for i in device_ids])
    except FileNotFoundError:
        pass
    except Exception:  # noqa: BLE001 - a damaged or foreign entry is a miss
        _active[-1]._count("unreadable")
    if executable is not None:
        from .compilations import LOADED

        with contextlib.suppress(OSError):
            os.utime(path)  # recently used: the last to be pruned
        jax.monitoring.record_event_time_span(LOADED, start, time.time(), fun_name=name)
        _active[-1]._count("hits")
    else:
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
            lowered = jax.jit(flat).lower(leaves)
            keepable = "callback" not in lowered.as_text()
            executable = lowered.compile(compiler_options) if keepable else None
        if not keepable:
            # A host callback (an equinox run-time check) cannot be kept: the
            # program is compiled as without a key, through JAX's cache.
            _active[-1]._count("unsaved")
            _in_process[key] = jitted.lower(*args).compile(compiler_options)
            return _in_process[key]
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
            shardings = jax.tree_util.tree_leaves((executable.input_shardings, executable.output_shardings))
            device_ids = sorted({d.id for s in shardings for d in s.device_set})
            payload, in_tree, out_tree = serialize(executable)
            blob = pickle.dumps((payload, in_tree, out_tree, skeleton, bool(targets), device_ids))
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
            tmp.write_bytes(hashlib.sha256(blob).digest() + blob)
            os.replace(tmp, path)
            _active[-1]._count("misses")
            _prune(path.parent)
        except Exception:  # noqa: BLE001 - not serializable or not writable: compiled, not kept
            _active[-1]._count("unsaved")

    def call(*call_args):
        call_dynamic, call_static = eqx.partition(call_args, eqx.is_array)
        call_leaves, call_tree = jax.tree_util.tree_flatten(call_dynamic)
        if call_tree != tree or not eqx.tree_equal(call_static, static):
            raise ValueError(f"{name}: called with arguments of another structure or other non-array values than it "
                             "was compiled for")
        out = executable(call_leaves)
        return jax.tree_util.tree_map(lambda x: out[x.index] if isinstance(x, _Slot) else x, skeleton)

    _in_process[key] = call
    return call


# Executables `compiled` loaded or compiled in this process, by key.
_in_process: dict = {}
