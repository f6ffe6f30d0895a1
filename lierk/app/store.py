"""Resumable chunked output: each finished chunk of a sweep on disk at once.

A `ChunkStore` is a directory of ``.npz`` chunks and a ``manifest.json``::

    DIR/
      manifest.json          {"format", "key", "key_hash", "n_chunks",
                              "chunks": {"3": {"file", "size", "sha256"}, ...}}
      chunk-000003.npz       chunk 3's arrays (leading axis: its members)

Every file is written to a temporary file in ``DIR``, flushed to disk
(``fsync``) and renamed over its final name (``os.replace``), the chunk
first and then the manifest that lists it.  A chunk counts as done only if
the manifest lists it and its file has the listed size and SHA-256, so a run
killed at any point never leaves a chunk that is read back as complete: at
worst it is computed again.

The manifest's ``key`` describes the run (scene, grid, solver settings,
dtype, chunk size, lierk version: whatever the caller puts in it).  Opening
a directory whose manifest has another key is refused, naming the fields
that differ, so two runs are never mixed.

Example:
    >>> store = ChunkStore.open("out/sweep", key={"grid": "...", "chunk_size": 256}, n_chunks=8)
    >>> for k, start, stop, out in lierk.sweep_chunks(fn, grid, chunk_size=256, skip=store.done):
    ...     store.write(k, out)
    >>> result = store.read_all()   # every chunk, concatenated in order
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ChunkStore", "key_hash", "check_size", "available_memory"]

_FORMAT = "lierk-chunks/1"
MANIFEST = "manifest.json"


def key_hash(key: dict) -> str:
    """SHA-256 of a JSON-serialisable run description (keys sorted)."""
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _atomic_write(path: Path, write) -> None:
    """``write(file)`` into a temporary file beside ``path``, then fsync and
    rename it to ``path``: readers see the old file or the whole new one."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    # The rename itself must reach the disk before the manifest names the file.
    with contextlib.suppress(OSError):
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


class ChunkStore:
    """The chunks of one run in a directory; see the module docstring.

    Attributes:
        directory: the directory (`pathlib.Path`).
        key: the run's description, as stored in the manifest.
        n_chunks: how many chunks the run has.
        done: sorted indices of the chunks on disk and intact.
        resumed: how many chunks were already done when the store was opened.
    """

    def __init__(self, directory: Path, key: dict, n_chunks: int, chunks: dict):
        self.directory, self.key, self.n_chunks = directory, key, n_chunks
        self._chunks = chunks  # index -> {"file", "size", "sha256"}, verified
        self.resumed = len(chunks)

    @classmethod
    def open(cls, directory: str | os.PathLike, *, key: dict, n_chunks: int) -> "ChunkStore":
        """Open (or create) the store of the run described by ``key``.

        Chunks already listed in the manifest are verified (size and SHA-256);
        those that do not check out, and temporary files left by a killed
        run, are dropped and will be computed again.

        Args:
            directory: the directory; created if missing.
            key: a JSON-serialisable description of everything that decides
                the chunks' contents.
            n_chunks: the number of chunks of the run (a positive int).

        Raises:
            ValueError: the directory holds another run (another key or
                chunk count), or a manifest that is not lierk's; the message
                names what differs.
        """
        if not (isinstance(n_chunks, (int, np.integer)) and n_chunks >= 1):
            raise ValueError(f"n_chunks must be a positive int, got {n_chunks!r}")
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        key = json.loads(json.dumps(key, sort_keys=True))
        manifest = directory / MANIFEST
        chunks = {}
        if manifest.exists():
            try:
                m = json.loads(manifest.read_text())
                ok = m.get("format") == _FORMAT
            except (ValueError, AttributeError):
                ok = False
            if not ok:
                raise ValueError(f"{manifest} is not a lierk chunk manifest ({_FORMAT}); use another directory")
            if m["key_hash"] != key_hash(key) or m["n_chunks"] != n_chunks:
                old = m.get("key", {})
                fields = sorted(k for k in set(old) | set(key) if old.get(k) != key.get(k))
                raise ValueError(
                    f"{directory} holds chunks of another run (different {', '.join(fields) or 'chunk count'}); "
                    "refusing to mix them: use another directory, or delete it to start over"
                )
            for index, entry in m["chunks"].items():
                path = directory / entry["file"]
                if path.is_file() and path.stat().st_size == entry["size"] and _sha256(path) == entry["sha256"]:
                    chunks[int(index)] = entry
        for tmp in directory.glob(".*.tmp"):
            with contextlib.suppress(OSError):
                tmp.unlink()
        store = cls(directory, key, int(n_chunks), chunks)
        store._write_manifest()
        return store

    @property
    def done(self) -> list[int]:
        return sorted(self._chunks)

    @property
    def complete(self) -> bool:
        """True when every chunk is done."""
        return len(self._chunks) == self.n_chunks

    def write(self, index: int, arrays: dict[str, Any]) -> None:
        """Store chunk ``index``'s arrays (a dict of name -> array, or a
        pytree flattened to one), then list it in the manifest.

        Raises:
            ValueError: ``index`` is not in ``0 <= index < n_chunks``.
        """
        if not (isinstance(index, (int, np.integer)) and 0 <= index < self.n_chunks):
            raise ValueError(f"chunk index must be in [0, {self.n_chunks}), got {index!r}")
        name = f"chunk-{int(index):06d}.npz"
        path = self.directory / name
        _atomic_write(path, lambda f: np.savez(f, **{k: np.asarray(v) for k, v in arrays.items()}))
        self._chunks[int(index)] = {"file": name, "size": path.stat().st_size, "sha256": _sha256(path)}
        self._write_manifest()

    def read(self, index: int) -> dict[str, np.ndarray]:
        """Chunk ``index``'s arrays."""
        with np.load(self.directory / self._chunks[index]["file"]) as z:
            return {k: z[k] for k in z.files}

    def read_all(self) -> dict[str, np.ndarray]:
        """All chunks' arrays, concatenated along the leading axis in chunk order.

        Raises:
            ValueError: some chunks are missing (the message says which).
        """
        missing = [k for k in range(self.n_chunks) if k not in self._chunks]
        if missing:
            raise ValueError(
                f"{len(missing)} of {self.n_chunks} chunks are missing (first: {missing[0]}); run again to resume"
            )
        parts = [self.read(k) for k in range(self.n_chunks)]
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _write_manifest(self) -> None:
        m = {
            "format": _FORMAT,
            "key": self.key,
            "key_hash": key_hash(self.key),
            "n_chunks": self.n_chunks,
            "chunks": {str(k): v for k, v in sorted(self._chunks.items())},
        }
        text = json.dumps(m, indent=1, sort_keys=True).encode()
        _atomic_write(self.directory / MANIFEST, lambda f: f.write(text))


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``),
    or None where it cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.3g} {unit}"
        n /= 1000


def check_size(memory: int, disk: int, directory: str | os.PathLike, what: str = "this run") -> None:
    """Refuse a run that cannot fit, before it compiles or computes anything.

    Args:
        memory: bytes the run holds in memory at once (saved points per
            member times the members computed at once).
        disk: bytes its output takes on disk.
        directory: where the output goes (the nearest existing parent is
            asked for its free space).
        what: the run, for the message.

    Raises:
        ValueError: one line with the numbers, when ``memory`` exceeds the
            available memory or ``disk`` the free space.
    """
    avail = available_memory()
    if avail is not None and memory > avail:
        raise ValueError(
            f"{what} needs about {_size(memory)} of memory and {_size(avail)} is available: "
            "save fewer points (save_every, n_save), shorten t1, or use a smaller chunk size"
        )
    p = Path(directory).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    free = shutil.disk_usage(p).free
    if disk > free:
        raise ValueError(
            f"{what} writes about {_size(disk)} and {p} has {_size(free)} free: save fewer points or free some space"
        )
