"""Multi-process runs on JAX's own distributed runtime (several hosts, or
several processes on one host).

One call, `initialize`, at the start of every process, before anything else
touches JAX.  After it, `jax.devices()` lists the devices of all processes,
and `lierk.sweep` / `lierk.sweep_chunks` split each batch over all of them:
every process runs the same script with the same arguments, computes the rows
of its own devices, and receives the whole result.
"""

from __future__ import annotations

import os
import socket
import time

import jax

__all__ = ["initialize"]

# The variables jax's own cluster detection requires (its SLURM and Open MPI
# clusters): with them present it can fill in the coordinator address, the
# process count and this process's id.
_SLURM = ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID", "SLURM_LOCALID")
_OMPI = "OMPI_MCA_orte_hnp_uri"


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    *,
    initialization_timeout: int = 60,
) -> bool:
    """Join this process to a multi-process JAX run; returns whether one was set up.

    Call it first thing in every process, before any JAX computation (even
    ``jax.devices()``), with the same ``coordinator_address`` and
    ``num_processes`` everywhere and a distinct ``process_id`` in each::

        # on host a (10.0.0.1) and host b, one process each:
        lierk.app.distributed.initialize("10.0.0.1:8476", 2, 0)   # on a
        lierk.app.distributed.initialize("10.0.0.1:8476", 2, 1)   # on b
        Rs = lierk.sweep(final_R, omega0s)   # the same call in both

    Process 0 runs the coordinator on that port (any free port that all
    processes can reach).  Under SLURM (``srun``) or Open MPI (``mpirun``) give
    no arguments: they are read from the launcher's environment, exactly as
    `jax.distributed.initialize` reads them (SLURM_NTASKS, SLURM_PROCID, the
    first host of SLURM_STEP_NODELIST and a port derived from SLURM_JOB_ID, or
    Open MPI's OMPI_COMM_WORLD_* and OMPI_MCA_orte_hnp_uri; JAX_COORDINATOR_PORT
    overrides the port).  On GPUs jax then gives each process the one GPU of
    its local rank.

    With no arguments and no such launcher, or with one process in all, it
    does nothing and returns ``False``: the same script runs alone unchanged.

    What it changes, since it is the caller's explicit request to set up the
    runtime: it calls `jax.distributed.initialize`.  CPU devices of different
    processes exchange data (the gather of a sweep's results) through JAX's
    CPU collectives, ``jax_cpu_collectives_implementation``, whose default is
    ``"gloo"``; lierk sets no JAX configuration, here or on import.

    Args:
        coordinator_address: ``"HOST:PORT"`` of process 0 (``"[IPv6]:PORT"``
            for an IPv6 address), e.g. the command line's
            ``--coordinator-address``.  Use an address the other hosts can
            reach, not ``127.0.0.1``, unless all processes share one host.
        num_processes: the number of processes, ``>= 1``.
        process_id: this process's id, ``0 <= process_id < num_processes``.
        initialization_timeout: seconds (a positive int) to wait for the
            coordinator and the other processes.

    Returns:
        ``True`` if this process is now one of several in a distributed run,
        ``False`` if it runs alone.  A second call returns the first call's
        answer and changes nothing.

    Raises:
        ValueError: a malformed ``coordinator_address``, ``num_processes < 1``,
            a ``process_id`` out of range or not an int, a non-positive
            ``initialization_timeout``, or some but not all three settings
            given outside a SLURM or Open MPI launch; the message names the
            value.
        RuntimeError: the coordinator could not be reached within
            ``initialization_timeout`` (from a process other than 0), its
            port is taken (on process 0), or JAX was already running.

    If the coordinator is reached but another process never arrives, JAX
    itself ends every waiting process after ``initialization_timeout`` with a
    ``DEADLINE_EXCEEDED`` message; that cannot be turned into an exception.
    """
    if jax.distributed.is_initialized():
        return jax.process_count() > 1
    if (
        isinstance(initialization_timeout, bool)
        or not isinstance(initialization_timeout, int)
        or initialization_timeout < 1
    ):
        raise ValueError(f"initialization_timeout must be a positive int (seconds), got {initialization_timeout!r}")
    if num_processes is not None and (
        isinstance(num_processes, bool) or not isinstance(num_processes, int) or num_processes < 1
    ):
        raise ValueError(f"num_processes must be an int >= 1, got {num_processes!r}")
    if process_id is not None and (isinstance(process_id, bool) or not isinstance(process_id, int) or process_id < 0):
        raise ValueError(f"process_id must be an int >= 0, got {process_id!r}")
    if process_id is not None and num_processes is not None and process_id >= num_processes:
        raise ValueError(
            f"process_id must be below num_processes = {num_processes} (0 to {num_processes - 1}), got {process_id}"
        )
    host, port = _parse_address(coordinator_address) if coordinator_address is not None else (None, None)

    given = (coordinator_address, num_processes, process_id)
    if None in given:
        launcher = _launcher()
        if launcher is None:
            if all(v is None for v in given):
                return False
            missing = [k for k, v in zip(("coordinator_address", "num_processes", "process_id"), given) if v is None]
            raise ValueError(
                f"a multi-process run needs coordinator_address, num_processes and process_id, or a SLURM or "
                f"Open MPI launch to read them from; missing {', '.join(missing)} "
                f"(got coordinator_address={coordinator_address!r}, num_processes={num_processes!r}, "
                f"process_id={process_id!r})"
            )
        if num_processes is None and launcher[1] == 1:
            return False
    elif num_processes == 1:
        return False

    # (CPU collectives across processes: gloo, the default of every jax lierk supports.)
    if host is not None and process_id is not None:
        if process_id == 0:
            _check_port_free(port)
        else:
            _wait_for_coordinator(host, port, initialization_timeout)
    jax.distributed.initialize(
        coordinator_address, num_processes, process_id, initialization_timeout=initialization_timeout
    )
    return jax.process_count() > 1


def _parse_address(address: object) -> tuple[str, int]:
    """``"HOST:PORT"`` or ``"[IPv6]:PORT"`` -> ``(host, port)``."""
    if not isinstance(address, str):
        raise ValueError(f"coordinator_address must be a string HOST:PORT, got {address!r}")
    host, sep, port = address.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        host = ""  # an IPv6 address needs brackets, or its last group reads as the port
    if not sep or not host or any(c.isspace() for c in host) or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(
            f"coordinator_address must be HOST:PORT (e.g. 10.0.0.1:8476 or [::1]:8476, port 1 to 65535), "
            f"got {address!r}"
        )
    return host, int(port)


def _launcher() -> tuple[str, int] | None:
    """``(name, number of processes)`` of the SLURM or Open MPI launch this
    process is part of, or None."""
    if all(v in os.environ for v in _SLURM):
        return "SLURM", _env_int("SLURM_NTASKS")
    if _OMPI in os.environ and "OMPI_COMM_WORLD_SIZE" in os.environ:
        return "Open MPI", _env_int("OMPI_COMM_WORLD_SIZE")
    return None


def _env_int(name: str) -> int:
    value = os.environ[name]
    try:
        return int(value)
    except ValueError:
        raise ValueError(f"the launcher's {name} must be an integer, got {value!r}") from None


def _check_port_free(port: int) -> None:
    # JAX's coordinator binds every interface; a taken port would end the
    # process from C++ instead of raising.
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("", port))
        except OSError as e:
            raise RuntimeError(
                f"process 0 cannot start the coordinator on port {port}: {e.strerror or e}; "
                f"pick another free port in coordinator_address"
            ) from None


def _wait_for_coordinator(host: str, port: int, timeout: int) -> None:
    # JAX ends the process (a C++ fatal error, not an exception) when the
    # coordinator does not answer in time; probing the port first turns the
    # common mistakes (wrong address, process 0 not started) into an error.
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host, port), timeout=max(0.1, min(2.0, deadline - time.monotonic()))):
                return
        except OSError as e:
            if time.monotonic() >= deadline:
                raise RuntimeError(
                    f"no coordinator answered at {host}:{port} within {timeout} s ({e.strerror or e}): is process 0 "
                    f"running with the same coordinator_address, and is the port reachable from this host?"
                ) from None
            time.sleep(0.2)
