"""Split the CPU into XLA host devices, one per core by default.  Import and
call `split` before jax is imported: the device count is fixed when jax's
CPU backend starts."""

from __future__ import annotations

import os


def split(devices: int | None = None) -> int:
    """Ask for ``devices`` XLA host devices (default: one per core) through
    ``XLA_FLAGS``; returns the count asked for."""
    n = devices or os.cpu_count() or 1
    if n > 1:
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={n}"
        ).strip()
    return n
