"""Compiled programs kept on disk between runs, keyed to this machine.

JAX can keep the programs it compiles in a directory (its persistent
compilation cache) and load them in a later process instead of compiling
again.  The library never turns that on by itself.  The command line does
(`lierk --no-cache`, or ``LIERK_NO_CACHE=1``, turns it off), and a script
opts in with one line before its first solve::

    jax.config.update("jax_compilation_cache_dir", str(lierk.compilation_cache_dir()))

Only programs that took at least a second to compile are kept unless
``jax_persistent_cache_min_compile_time_secs`` is lowered too (the command
line keeps every program: its many small ones add up).

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
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
import tempfile
import warnings
from pathlib import Path

__all__ = ["compilation_cache_dir", "default_cache_root", "machine_fingerprint"]


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
