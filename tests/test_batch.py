"""`lierk.sweep` and `lierk.sweep_chunks`: the same numbers as a Python loop,
chunked or not, sharded or not; one compilation per function; bad input
named."""

import functools
import gc
import os
import subprocess
import sys
import textwrap
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TEE

import lierk
from lierk import _batch as batch
from lierk import sweep, sweep_chunks


def _final_R(omega0, dt):
    body = lierk.FreeRigidBody(TEE, omega0)
    return lierk.solve(body, lierk.RKMK4(), 0.5, dt=dt, max_steps=50).R[-1]


# The loop reference runs one compiled member at a time.
_final_R_jit = jax.jit(_final_R)

# Members of a vmapped batch can differ from the loop in the last bits: XLA's
# vectorised loops round some members (lane position, batch size) differently.
ATOL = 1e-14


def _inputs(n):
    rng = np.random.default_rng(3)
    return rng.normal(size=(n, 3)), rng.uniform(0.01, 0.02, size=n)


def _loop(omegas, dts):
    return np.stack([np.asarray(_final_R_jit(w, h)) for w, h in zip(omegas, dts)])


@pytest.mark.parametrize("chunk_size", [None, 3])
def test_sweep_matches_python_loop(chunk_size):
    omegas, dts = _inputs(7)
    got = sweep(_final_R, omegas, dts, chunk_size=chunk_size)
    assert got.shape == (7, 3, 3)
    np.testing.assert_allclose(np.asarray(got), _loop(omegas, dts), rtol=0, atol=ATOL)


def test_sweep_chunks_match_python_loop_and_sweep():
    omegas, dts = _inputs(7)
    chunks = list(sweep_chunks(_final_R, omegas, dts, chunk_size=3))
    assert [c[:3] for c in chunks] == [(0, 0, 3), (1, 3, 6), (2, 6, 7)]
    assert all(type(out) is np.ndarray and out.shape == (stop - start, 3, 3) for _, start, stop, out in chunks)
    got = np.concatenate([out for *_, out in chunks])
    np.testing.assert_allclose(got, _loop(omegas, dts), rtol=0, atol=ATOL)
    np.testing.assert_allclose(got, np.asarray(sweep(_final_R, omegas, dts)), rtol=0, atol=ATOL)


def test_sweep_chunks_skip_leaves_out_exactly_those_chunks():
    x = np.arange(10.0)

    def fn(v):
        return {"v": v, "sq": v * v}

    everything = {k: (a, b, out) for k, a, b, out in sweep_chunks(fn, x, chunk_size=4)}
    resumed = list(sweep_chunks(fn, x, chunk_size=4, skip={0, 2}))
    assert [r[:3] for r in resumed] == [(1, 4, 8)]
    np.testing.assert_array_equal(resumed[0][3]["v"], x[4:8])
    np.testing.assert_array_equal(resumed[0][3]["sq"], everything[1][2]["sq"])
    assert everything[2][:2] == (8, 10)
    np.testing.assert_array_equal(everything[2][2]["v"], x[8:10])  # padding dropped
    assert list(sweep_chunks(fn, x, chunk_size=4, skip=range(3))) == []


@pytest.mark.parametrize("chunk_size", [1, 3, 4, 9, 100])
def test_chunks_cover_the_batch_exactly_in_order(chunk_size):
    # Row i's output is its own input: a shifted, repeated or padded row shows.
    x = np.arange(9.0) + 1.0
    chunks = list(sweep_chunks(lambda v: v, x, chunk_size=chunk_size))
    np.testing.assert_array_equal(np.concatenate([out for *_, out in chunks]), x)
    assert chunks[-1][2] == 9
    assert all(stop - start == out.shape[0] for _, start, stop, out in chunks)
    np.testing.assert_array_equal(np.asarray(sweep(lambda v: v, x, chunk_size=chunk_size)), x)


def test_padding_rows_are_valid_inputs():
    # 7 members in chunks of 3: the last chunk is padded to 3.  A padding row of
    # zeros would trip the check; copies of a real member cannot.
    x = np.arange(1.0, 8.0)

    def fn(v):
        return eqx.error_if(jnp.log(v), v <= 0, "padding reached fn")

    out = np.concatenate([o for *_, o in sweep_chunks(fn, x, chunk_size=3)])
    np.testing.assert_allclose(out, np.log(x), rtol=1e-15)


def test_sweep_pytree_arguments_and_outputs():
    omegas, dts = _inputs(5)

    def fn(args):
        R = _final_R(args["w"], args["dt"])
        return {"R": R, "trace": jnp.trace(R)}

    got = sweep(fn, {"w": omegas, "dt": dts}, chunk_size=2)
    for i in range(5):
        R = np.asarray(_final_R_jit(omegas[i], dts[i]))
        np.testing.assert_allclose(np.asarray(got["R"][i]), R, atol=ATOL, rtol=0)
        assert float(got["trace"][i]) == pytest.approx(np.trace(R), abs=ATOL)


def test_float64_inputs_follow_jax_precision_setting():
    # The command line runs --float32 under jax.enable_x64(False): NumPy float64
    # inputs become float32, as jnp.asarray would make them.
    with jax.enable_x64(False):
        out = sweep(lambda v: v * 2.0, np.arange(4.0))
        ((*_, chunk),) = sweep_chunks(lambda v: {"a": v * 2.0}, np.arange(3.0), chunk_size=3)
    assert out.dtype == jnp.float32 and chunk["a"].dtype == np.float32
    np.testing.assert_array_equal(np.asarray(out), [0.0, 2.0, 4.0, 6.0])


# --------------------------------------------------------------------------
# Blocks that fit the cache: the same members, stepped a block at a time

BOX = np.diag([1.0, 2.0, 3.0])  # kg m^2, a 1:2:3 box


def _fixed(inertia, omega0):
    body = lierk.FreeRigidBody(inertia, omega0)
    sol = lierk.solve(body, lierk.RKMK4(), 3.0, dt=0.05, max_steps=60)
    return sol.R[-1], sol.stats["num_steps"]


def _adaptive(inertia, omega0):
    body = lierk.FreeRigidBody(inertia, omega0)
    sol = lierk.solve(body, lierk.DOP853(), 3.0, rtol=1e-6, atol=1e-6, max_steps=400)
    return sol.R[-1], sol.stats["num_steps"]


def _omegas(n, dtype):
    # Spins of 0.3 to 3 rad/s in all directions: the adaptive members take
    # 3 to 9 steps, so most blocks end before the slowest member.
    rng = np.random.default_rng(11)
    w = rng.normal(size=(n, 3))
    return (w * rng.uniform(0.3, 3.0, size=(n, 1)) / np.linalg.norm(w, axis=1, keepdims=True)).astype(dtype)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("fn", [_fixed, _adaptive])
def test_cache_blocks_give_the_unblocked_results(fn, dtype):
    # 10 members in blocks of at most 4: three blocks of 4, the last padded
    # with 2 copies of member 9.  A shifted, repeated or dropped member, or a
    # block that stopped early, shows as an O(1) difference or a step count.
    w = _omegas(10, dtype)
    f = functools.partial(fn, jnp.asarray(BOX, dtype))
    R_whole, steps_whole = sweep(f, w, cache_chunk=10)  # one block: a plain vmap
    R_blocks, steps_blocks = sweep(f, w, cache_chunk=4)
    assert R_blocks.shape == (10, 3, 3) and R_blocks.dtype == dtype
    assert len(set(np.asarray(steps_whole).tolist())) > 1 or fn is _fixed  # the members differ
    np.testing.assert_array_equal(np.asarray(steps_blocks), np.asarray(steps_whole))
    atol = 1e-13 if dtype == np.float64 else 1e-5
    np.testing.assert_allclose(np.asarray(R_blocks), np.asarray(R_whole), rtol=0, atol=atol)
    if fn is _adaptive:
        return  # (its compilations are the slow ones)
    # Host chunks of 7 (the second padded by 4) and blocks of 3 inside them.
    chunks = list(sweep_chunks(f, w, chunk_size=7, cache_chunk=3))
    assert [c[:3] for c in chunks] == [(0, 0, 7), (1, 7, 10)]
    R_chunks = np.concatenate([out[0] for *_, out in chunks])
    np.testing.assert_allclose(R_chunks, np.asarray(R_whole), rtol=0, atol=atol)


def test_cache_blocks_of_a_jacobian():
    # d R(T) / d omega0 of each member, blocks of 3 over 7 members.
    def jac(omega0):
        return jax.jacfwd(lambda w: _fixed(BOX, w)[0])(omega0)

    w = _omegas(7, np.float64)
    whole = np.asarray(sweep(jac, w, cache_chunk=7))
    blocks = np.asarray(sweep(jac, w, cache_chunk=3))
    assert blocks.shape == (7, 3, 3, 3)
    np.testing.assert_allclose(blocks, whole, rtol=0, atol=1e-12)
    # Against a central difference (errors O(eps^2) ~ 1e-8 here).
    eps = 1e-5
    i, k = 6, 1  # a member of the padded last block
    e = np.eye(3)[k] * eps
    fd = (np.asarray(_fixed(BOX, w[i] + e)[0]) - np.asarray(_fixed(BOX, w[i] - e)[0])) / (2 * eps)
    np.testing.assert_allclose(blocks[i, :, :, k], fd, rtol=0, atol=1e-6)


def test_cache_chunk_not_smaller_than_the_batch_is_the_plain_program():
    count = _Counted()
    f = count(lambda v: v * 2.0)
    x = np.arange(5.0)
    for cache_chunk in (5, 6, 1000):
        np.testing.assert_array_equal(np.asarray(sweep(f, x, cache_chunk=cache_chunk)), 2.0 * x)
    assert count.traces == 1
    # Blocks of 2, whatever the values, chunks of the same size: one more.
    sweep(f, x, cache_chunk=2)
    sweep(f, x + 1.0, cache_chunk=2)
    list(sweep_chunks(f, x, chunk_size=5, cache_chunk=2))
    assert count.traces == 2


def test_default_cache_chunk_reaches_the_program(monkeypatch):
    seen = []
    monkeypatch.setattr(batch, "_default_cache_chunk", lambda platform: seen.append(platform) or 3)
    blocks = []
    in_blocks = batch._in_blocks
    monkeypatch.setattr(batch, "_in_blocks", lambda f, block, rows: blocks.append(block) or in_blocks(f, block, rows))
    x = np.arange(1.0, 9.0)
    np.testing.assert_array_equal(np.asarray(sweep(lambda v: v + 0.5, x)), x + 0.5)
    assert seen == ["cpu"] and blocks == [3]
    ((*_, out),) = sweep_chunks(lambda v: v - 0.5, x, chunk_size=8)
    np.testing.assert_array_equal(out, x - 0.5)
    assert seen == ["cpu"] * 2 and blocks == [3] * 2


@pytest.mark.parametrize(
    "l2, chunk", [("512K", 512), ("2048K", 2048), ("1M", 1024), ("48K", 32), ("1536K", 1024), ("1G", 4096), (None, 512)]
)
def test_default_cache_chunk_follows_the_l2_size(tmp_path, l2, chunk):
    # A sysfs cache directory: L1 data and instruction, L2, L3.
    for i, (level, kind, size) in enumerate(
        [(1, "Data", "32K"), (1, "Instruction", "32K"), (2, "Unified", l2), (3, "Unified", "32768K")]
    ):
        d = tmp_path / f"index{i}"
        d.mkdir()
        (d / "level").write_text(f"{level}\n")
        (d / "type").write_text(f"{kind}\n")
        if size is not None:
            (d / "size").write_text(f"{size}\n")
    read = batch._l2_bytes(str(tmp_path))
    assert read == (None if l2 is None else int(l2[:-1]) << {"K": 10, "M": 20, "G": 30}[l2[-1]])
    assert batch._l2_bytes(str(tmp_path / "missing")) is None
    with pytest.MonkeyPatch.context() as m:
        m.setattr(batch, "_l2_bytes", lambda: read)
        m.setattr(batch, "_cores_per_cpu_device", lambda: 1.0)
        assert batch._default_cache_chunk("cpu") == chunk
        assert batch._default_cache_chunk("gpu") is None
        # A CPU device over several cores: XLA splits the whole share's loops
        # over them, so no blocks.
        m.setattr(batch, "_cores_per_cpu_device", lambda: 2.0)
        assert batch._default_cache_chunk("cpu") is None


def test_cores_per_cpu_device_counts_this_process_cores():
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert batch._cores_per_cpu_device() == cores / len(jax.local_devices(backend="cpu"))


# --------------------------------------------------------------------------
# Compiled once


class _Counted:
    """Counts how often ``fn`` is traced: a compilation traces it once."""

    def __init__(self):
        self.traces = 0

    def __call__(self, fn):
        @functools.wraps(fn)
        def counted(*args, **kwargs):
            self.traces += 1
            return fn(*args, **kwargs)

        return counted


def test_second_call_and_new_values_do_not_recompile():
    count = _Counted()
    f = count(_final_R)
    omegas, dts = _inputs(7)
    sweep(f, omegas, dts)
    sweep(f, omegas + 1.0, dts * 1.5)
    sweep(f, jnp.asarray(omegas), dts)  # a JAX array instead of NumPy
    assert count.traces == 1
    # Chunks, the last one padded, share one shape: one more compilation
    # (chunks of 3), for both entry points.
    sweep(f, omegas, dts, chunk_size=3)
    list(sweep_chunks(f, omegas, dts, chunk_size=3))
    list(sweep_chunks(f, omegas[:5], dts[:5], chunk_size=3))
    assert count.traces == 2
    sweep(f, omegas[:5], dts[:5])  # a new shape does compile
    assert count.traces == 3


_BODY_TRACES = []


class _Body(eqx.Module):
    inertia: jax.Array
    t1: float

    def __call__(self, omega0):
        _BODY_TRACES.append(1)
        body = lierk.FreeRigidBody(self.inertia, omega0)
        return lierk.solve(body, lierk.RKMK4(), self.t1, dt=0.01, max_steps=50).R[-1]


def test_partial_and_module_with_new_array_values_do_not_recompile():
    count = _Counted()
    g = count(lambda inertia, omega0: lierk.FreeRigidBody(inertia, omega0).omega0)
    omegas, _ = _inputs(4)
    a = sweep(functools.partial(g, TEE), omegas)
    b = sweep(functools.partial(g, 2.0 * TEE), omegas)  # a new partial, new values
    assert count.traces == 1
    np.testing.assert_allclose(np.asarray(a), omegas, atol=ATOL)
    np.testing.assert_allclose(np.asarray(b), omegas, atol=ATOL)

    _BODY_TRACES.clear()
    R1 = sweep(_Body(jnp.asarray(TEE), 0.5), omegas)
    R2 = sweep(_Body(jnp.asarray(2.0 * TEE), 0.5), omegas)
    assert len(_BODY_TRACES) == 1
    sweep(_Body(jnp.asarray(TEE), 0.4), omegas)  # a Python number is structure
    assert len(_BODY_TRACES) == 2
    # Scaling the inertia leaves omega(t) and so R(t) unchanged: the second
    # module's values were really used (not the first's, baked in).
    np.testing.assert_allclose(np.asarray(R1), np.asarray(R2), atol=ATOL)
    np.testing.assert_allclose(np.asarray(R1), _loop(omegas, np.full(4, 0.01)), atol=ATOL)


def test_bound_method_is_cached_on_its_function_and_instance():
    class Model:
        def __init__(self):
            self.traces = 0

        def run(self, v):
            self.traces += 1
            return 2.0 * v

    m = Model()
    sweep(m.run, np.arange(3.0))  # m.run is a new object at each access
    sweep(m.run, np.arange(3.0) + 1)
    assert m.traces == 1


def test_fresh_lambda_compiles_again_and_functions_are_not_kept_alive():
    # As documented: a lambda made anew for each call is a new function.
    count = _Counted()
    x = np.arange(4.0)
    for _ in range(2):
        sweep(count(lambda v: v + 1.0), x)
    assert count.traces == 2

    def f(v):
        return v * 3.0

    ref = weakref.ref(f)
    cached = len(batch._BY_IDENTITY)
    np.testing.assert_array_equal(np.asarray(sweep(f, x)), 3.0 * x)
    assert len(batch._BY_IDENTITY) == cached + 1
    del f
    gc.collect()
    assert ref() is None, "the sweep cache keeps the function (and its compiled code) alive"
    assert len(batch._BY_IDENTITY) == cached


# --------------------------------------------------------------------------
# Bad input


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "4", 4.0])
def test_bad_chunk_size_is_named(bad):
    x = np.arange(5.0)
    with pytest.raises(ValueError, match=f"chunk_size must be a positive int, got {bad!r}"):
        sweep(lambda v: v, x, chunk_size=bad)
    with pytest.raises(ValueError, match=f"chunk_size must be a positive int, got {bad!r}"):
        sweep_chunks(lambda v: v, x, chunk_size=bad)  # raises at the call, not at next()
    with pytest.raises(ValueError, match=f"cache_chunk must be a positive int, got {bad!r}"):
        sweep(lambda v: v, x, cache_chunk=bad)
    with pytest.raises(ValueError, match=f"cache_chunk must be a positive int, got {bad!r}"):
        sweep_chunks(lambda v: v, x, chunk_size=2, cache_chunk=bad)


@pytest.mark.parametrize("bad", [3, -1, "1", 1.0])
def test_bad_skip_is_named(bad):
    with pytest.raises(ValueError, match=f"skip holds {bad!r}.*chunks 0 to 2"):
        sweep_chunks(lambda v: v, np.arange(5.0), chunk_size=2, skip=[0, bad])


def test_sweep_rejects_mismatched_or_empty_batch():
    with pytest.raises(ValueError, match="same leading axis"):
        sweep(_final_R, np.zeros((3, 3)), np.full(4, 0.01))
    with pytest.raises(ValueError, match="same leading axis"):
        sweep(_final_R, np.zeros(3), 0.01)  # an unbatched scalar
    with pytest.raises(ValueError, match="empty batch"):
        sweep_chunks(lambda v: v, np.zeros((0, 3)), chunk_size=2)
    with pytest.raises(ValueError, match="at least one batched argument"):
        sweep(lambda: 0.0)


# --------------------------------------------------------------------------
# Two host devices


_TWO_DEVICES = textwrap.dedent(
    """
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert len(jax.devices()) == 2, jax.devices()
    import lierk
    I = np.diag([9.82271303e-05, 7.22671030e-05, 1.57865031e-04])
    traces = []
    def f(w):
        traces.append(1)
        return lierk.solve(lierk.FreeRigidBody(I, w), lierk.RKMK4(), 0.5, dt=0.01, max_steps=50).R[-1]
    w = np.random.default_rng(0).normal(size=(7, 3))  # odd: exercises the padding
    sharded = lierk.sweep(f, w, chunk_size=5)
    assert len(sharded.sharding.device_set) == 2, sharded.sharding
    again = lierk.sweep(f, w + 0.5, chunk_size=5)
    chunks = np.concatenate([R for *_, R in lierk.sweep_chunks(f, w, chunk_size=5)])
    assert len(traces) == 1, len(traces)
    whole = lierk.sweep(f, w)
    assert len(whole.sharding.device_set) == 2, whole.sharding
    w6 = jax.device_put(w[:6], whole.sharding)  # already where the sweep puts it
    assert np.array_equal(np.asarray(lierk.sweep(f, w6)), np.asarray(lierk.sweep(f, w[:6])))
    plain = lierk.sweep(f, w, shard=False)
    assert len(plain.sharding.device_set) == 1
    err = max(float(np.max(np.abs(np.asarray(x) - np.asarray(plain)))) for x in (sharded, chunks, whole))
    assert sharded.shape == (7, 3, 3) and err <= 1e-14, err
    print("OK", len(jax.devices()), err)
    """
)


# Added to the caller's XLA flags (make test's quick compile settings).
_TWO_HOST_DEVICES = " ".join([*os.environ.get("XLA_FLAGS", "").split(), "--xla_force_host_platform_device_count=2"])


def test_sweep_sharded_over_two_host_devices_equals_unsharded():
    env = dict(os.environ, XLA_FLAGS=_TWO_HOST_DEVICES, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", _TWO_DEVICES], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().startswith("OK 2"), proc.stdout


_FAILURE_ON_ONE_DEVICE = textwrap.dedent(
    """
    import time
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert len(jax.devices()) == 2, jax.devices()
    import lierk
    I = np.diag([1.0, 2.0, 3.0])
    def fixed(w):  # 20 steps of 0.5 s: blows up at |omega| = 30 rad/s
        return lierk.solve(lierk.FreeRigidBody(I, w), lierk.RKMK4(), 10.0, dt=0.5, max_steps=20).R[-1]
    def adaptive(w):  # 8 steps are too few at rtol 1e-8 for the fast member
        return lierk.solve(lierk.FreeRigidBody(I, w), lierk.DP54(), 10.0, rtol=1e-8, atol=1e-8, max_steps=8).R[-1]
    w = np.array([[0.01, 0.01, 0.01]] * 3 + [[30.0, 1.0, 1.0]])  # the failing member is on the second device
    for fn, what in ((fixed, "non-finite"), (adaptive, "max_steps")):
        t = time.perf_counter()
        try:
            np.asarray(lierk.sweep(fn, w))  # the error surfaces when the result is read
        except Exception as e:
            assert what in str(e), str(e)[:500]
            print("RAISED", fn.__name__, round(time.perf_counter() - t, 1))
        else:
            raise AssertionError(f"{fn.__name__}: no error")
    """
)


def test_a_failed_member_on_one_device_raises_its_error():
    """A run-time check that fails on one device raises the solve's error,
    promptly: under the SPMD partitioner the other device waited for it in
    an all-reduce, and XLA aborted the process after a minute."""
    env = dict(os.environ, XLA_FLAGS=_TWO_HOST_DEVICES, JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-c", _FAILURE_ON_ONE_DEVICE], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [line.split() for line in proc.stdout.splitlines() if line.startswith("RAISED")]
    assert [line[1] for line in lines] == ["fixed", "adaptive"], proc.stdout
    assert all(float(line[2]) < 30.0 for line in lines), proc.stdout  # the abort came after 60 s


def test_compiling_phase_runs_once_before_the_first_chunk():
    """`sweep_chunks(..., compiling=)` compiles inside the given context, once,
    before any chunk is computed; the chunks then reuse that program."""
    import contextlib

    events, traces = [], []

    def fn(x):
        traces.append(1)
        return 2.0 * x

    @contextlib.contextmanager
    def compiling():
        events.append("enter")
        yield
        events.append(f"exit after {len(traces)} trace(s)")

    xs = np.arange(10.0)
    outs = []
    for k, a, b, out in lierk.sweep_chunks(fn, xs, chunk_size=4, compiling=compiling):
        events.append(f"chunk {k}")
        outs.append(out)
    assert events == ["enter", "exit after 1 trace(s)", "chunk 0", "chunk 1", "chunk 2"]
    assert len(traces) == 1
    np.testing.assert_array_equal(np.concatenate(outs), 2.0 * xs)
