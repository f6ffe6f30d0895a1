"""`lierk.app.distributed.initialize` and sweeps across processes.

Two processes on 127.0.0.1 with CPU collectives (gloo) must give the result of
one process with two host devices to the last bit: the same rows run at the
same per-device shape, so nothing may differ but where they run.  Everything
that starts the runtime happens in subprocesses: it can be started once per
process, and a failed start ends the process."""

import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from lierk.app.distributed import initialize

try:  # jaxlib's gloo bindings (private): the CPU collectives a CPU multi-process run needs
    from jax._src.lib import _jax

    _GLOO = hasattr(_jax, "make_gloo_tcp_collectives")
except ImportError:
    _GLOO = False

_SLURM = ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID", "SLURM_LOCALID")
_ENV = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")
for _k in (*_SLURM, "OMPI_MCA_orte_hnp_uri", "XLA_FLAGS", "JAX_COORDINATOR_PORT", "JAX_COORDINATOR_ADDRESS"):
    _ENV.pop(_k, None)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------
# Arguments (checked before anything starts, so safe in this process)


@pytest.mark.parametrize(
    "kwargs, named",
    [
        (dict(coordinator_address="127.0.0.1:1234", num_processes=2, process_id=2), "got 2"),
        (dict(coordinator_address="127.0.0.1:1234", num_processes=2, process_id=-1), "got -1"),
        (dict(coordinator_address="127.0.0.1:1234", num_processes=2, process_id=1.0), "got 1.0"),
        (dict(coordinator_address="127.0.0.1:1234", num_processes=0, process_id=0), "got 0"),
        (dict(coordinator_address="127.0.0.1:1234", num_processes=True, process_id=0), "got True"),
        (dict(coordinator_address="127.0.0.1", num_processes=2, process_id=0), "got '127.0.0.1'"),
        (dict(coordinator_address="127.0.0.1:http", num_processes=2, process_id=0), "got '127.0.0.1:http'"),
        (dict(coordinator_address="127.0.0.1:0", num_processes=2, process_id=0), "got '127.0.0.1:0'"),
        (dict(coordinator_address="127.0.0.1:70000", num_processes=2, process_id=0), "got '127.0.0.1:70000'"),
        (dict(coordinator_address=":1234", num_processes=2, process_id=0), "got ':1234'"),
        (dict(coordinator_address="::1:1234", num_processes=2, process_id=0), "got '::1:1234'"),
        (dict(coordinator_address="my host:1234", num_processes=2, process_id=0), "got 'my host:1234'"),
        (dict(coordinator_address=("h", 1), num_processes=2, process_id=0), r"got \('h', 1\)"),
        (dict(coordinator_address="h:1", num_processes=2, process_id=0, initialization_timeout=0), "got 0"),
        (dict(coordinator_address="127.0.0.1:1234", num_processes=2), "missing process_id"),
        (dict(num_processes=2, process_id=1), "missing coordinator_address"),
    ],
)
def test_bad_arguments_raise_naming_the_value(kwargs, named, monkeypatch):
    for k in _SLURM + ("OMPI_MCA_orte_hnp_uri",):
        monkeypatch.delenv(k, raising=False)
    with pytest.raises(ValueError, match=named):
        initialize(**kwargs)


def test_alone_it_does_nothing(monkeypatch):
    for k in _SLURM + ("OMPI_MCA_orte_hnp_uri",):
        monkeypatch.delenv(k, raising=False)
    assert initialize() is False
    assert initialize("10.0.0.1:8476", 1, 0) is False
    # A SLURM launch of a single task is a single process too.
    for k, v in zip(_SLURM, ("7", "node001", "1", "0", "0")):
        monkeypatch.setenv(k, v)
    assert initialize() is False


def test_a_missing_process_id_names_the_launch_it_needs(monkeypatch):
    for k in _SLURM + ("OMPI_MCA_orte_hnp_uri",):
        monkeypatch.delenv(k, raising=False)
    with pytest.raises(ValueError, match="SLURM or Open MPI"):
        initialize("10.0.0.1:8476", 2)


# --------------------------------------------------------------------------
# Start-up failures: an error within the timeout, not a hang or an abort


def _run(code: str, *args, env=None, timeout=120):
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)], env=env or _ENV, capture_output=True, text=True, timeout=timeout
    )


_START = textwrap.dedent(
    """
    import sys, time
    from lierk.app.distributed import initialize
    t = time.monotonic()
    try:
        initialize(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), initialization_timeout=2)
    except RuntimeError as e:
        print(f"RuntimeError after {time.monotonic() - t:.1f} s: {e}")
    """
)


def test_unreachable_coordinator_is_a_clear_error_within_the_timeout():
    port = _free_port()
    proc = _run(_START, f"127.0.0.1:{port}", 2, 1)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout
    assert out.startswith("RuntimeError after") and f"no coordinator answered at 127.0.0.1:{port} within 2 s" in out, (
        out
    )
    assert float(out.split()[2]) < 10


def test_taken_coordinator_port_is_a_clear_error():
    with socket.socket() as s:
        s.bind(("", 0))
        s.listen()
        port = s.getsockname()[1]
        proc = _run(_START, f"127.0.0.1:{port}", 2, 0)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"cannot start the coordinator on port {port}" in proc.stdout, proc.stdout


# --------------------------------------------------------------------------
# Two processes


_SWEEP = textwrap.dedent(
    """
    import sys
    import lierk.app.distributed
    mode, out = sys.argv[1], sys.argv[2]
    if mode == "args":
        multi = lierk.app.distributed.initialize(sys.argv[3], 2, int(sys.argv[4]), initialization_timeout=60)
    else:  # "env": a SLURM launch, or one process (XLA_FLAGS gives it two devices)
        multi = lierk.app.distributed.initialize(initialization_timeout=60)
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    import lierk
    I = np.diag([9.82271303e-05, 7.22671030e-05, 1.57865031e-04])
    def final(w):
        sol = lierk.solve(lierk.FreeRigidBody(I, w), lierk.RKMK4(), 0.5, dt=0.01, max_steps=50)
        return {"R": sol.R[-1], "result": sol.result}
    w = np.random.default_rng(0).normal(size=(7, 3))  # odd: the padding is split over processes
    whole = lierk.sweep(final, w)
    chunks = list(lierk.sweep_chunks(final, w, chunk_size=3, skip=[1]))
    assert [c[:3] for c in chunks] == [(0, 0, 3), (2, 6, 7)], [c[:3] for c in chunks]
    np.savez(out, R=np.asarray(whole["R"]), result=np.asarray(whole["result"]),
             c0=chunks[0][3]["R"], c2=chunks[1][3]["R"])
    print("OK", multi, jax.process_index(), jax.process_count(), jax.device_count())
    """
)


def _two_processes(tmp_path, env_of, args_of):
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _SWEEP, *map(str, args_of(i, tmp_path / f"p{i}.npz"))],
            env=env_of(i),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outs = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=120)
            assert p.returncode == 0, err[-3000:]
            outs.append(out)  # gloo prints a line of its own first
    finally:
        for p in procs:
            p.kill()
    return outs, [np.load(tmp_path / f"p{i}.npz") for i in range(2)]


@pytest.mark.skipif(not _GLOO, reason="this jaxlib is built without gloo CPU collectives")
def test_two_processes_equal_one_process_bit_for_bit(tmp_path):
    # The reference: one process, the same two devices' worth of rows.
    ref = _run(
        _SWEEP, "env", tmp_path / "ref.npz", env=dict(_ENV, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    )
    assert ref.returncode == 0, ref.stderr[-3000:]
    assert ref.stdout.split() == ["OK", "False", "0", "1", "2"], ref.stdout
    want = np.load(tmp_path / "ref.npz")

    port = _free_port()
    outs, got = _two_processes(tmp_path, lambda i: _ENV, lambda i, out: ("args", out, f"127.0.0.1:{port}", i))
    assert [o.strip().splitlines()[-1].split() for o in outs] == [["OK", "True", str(i), "2", "2"] for i in range(2)], (
        outs
    )
    for g in got:
        for k in want.files:
            np.testing.assert_array_equal(g[k], want[k], err_msg=k)  # 0 ulp
    assert got[0]["R"].shape == (7, 3, 3) and not got[0]["result"].any()
    # Chunks run at another batch shape, which XLA may round differently in the last bits.
    np.testing.assert_allclose(got[0]["c0"], got[0]["R"][:3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(got[0]["c2"], got[0]["R"][6:], rtol=0, atol=1e-14)

    # The same run started as SLURM starts it (srun sets these variables):
    # jax's cluster detection fills in the address, the count and the id.
    port = _free_port()

    def slurm(i):
        return dict(
            _ENV,
            SLURM_JOB_ID="4242",
            SLURM_STEP_NODELIST="127.0.0.1",
            SLURM_NTASKS="2",
            SLURM_PROCID=str(i),
            SLURM_LOCALID=str(i),
            JAX_COORDINATOR_PORT=str(port),
        )

    outs, got = _two_processes(tmp_path, slurm, lambda i, out: ("env", out))
    assert [o.strip().splitlines()[-1].split() for o in outs] == [["OK", "True", str(i), "2", "2"] for i in range(2)], (
        outs
    )
    for g in got:
        np.testing.assert_array_equal(g["R"], want["R"])
