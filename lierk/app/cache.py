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
traces and lowers each program to look it up; it skips XLA's compilation.
JAX keeps no program that contains a host callback (an ``eqx.error_if``
check of a traced value): such a program is compiled in every run, and
`CacheUse` counts it apart.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import sys
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path

__all__ = ["CacheUse", "compilation_cache_dir", "default_cache_root", "machine_fingerprint", "using_cache"]


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


_CACHE_SETTINGS = (
    "jax_enable_compilation_cache",
    "jax_compilation_cache_dir",
    "jax_persistent_cache_min_compile_time_secs",
)
# JAX's warnings about one entry (a corrupted file, a full disk), by what they count as.
_ENTRY_WARNINGS = (
    ("unreadable", "Error reading persistent compilation cache"),
    ("unwritable", "Error writing persistent compilation cache"),
)


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
        self._requests = 0  # compilations that asked JAX's cache

    def _listen(self, event: str, **_) -> None:
        """One of JAX's cache events: a compilation that asked the cache, a
        hit, a miss (compiled and saved); the rest of those asked were not saved."""
        if event == "/jax/compilation_cache/compile_requests_use_cache":
            self._requests += 1
        elif event == "/jax/compilation_cache/cache_hits":
            self.counts["hits"] += 1
        elif event == "/jax/compilation_cache/cache_misses":
            self.counts["misses"] += 1
        else:
            return
        self.counts["unsaved"] = self._requests - self.counts["hits"] - self.counts["misses"]

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
