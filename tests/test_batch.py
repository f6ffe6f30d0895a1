"""`lierk.batch.sweep`: same numbers as a Python loop, with or without
sharding over several host devices."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lierk
from lierk.batch import sweep

from helpers import TEE


def _final_R(omega0, dt):
    body = lierk.FreeRigidBody(TEE, omega0)
    return lierk.solve(body, lierk.RKMK4(), 0.5, dt=dt, max_steps=50).R[-1]


# The loop reference runs one compiled member at a time.
_final_R_jit = jax.jit(_final_R)


def _inputs(n):
    rng = np.random.default_rng(3)
    return rng.normal(size=(n, 3)), rng.uniform(0.01, 0.02, size=n)


@pytest.mark.parametrize("chunk_size", [None, 3])
def test_sweep_matches_python_loop(chunk_size):
    omegas, dts = _inputs(7)
    got = sweep(_final_R, omegas, dts, chunk_size=chunk_size)
    want = np.stack([np.asarray(_final_R_jit(w, h)) for w, h in zip(omegas, dts)])
    assert got.shape == (7, 3, 3)
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-14)


def test_sweep_pytree_arguments_and_outputs():
    omegas, dts = _inputs(5)

    def fn(args):
        R = _final_R(args["w"], args["dt"])
        return {"R": R, "trace": jnp.trace(R)}

    got = sweep(fn, {"w": omegas, "dt": dts}, chunk_size=2)
    for i in range(5):
        R = np.asarray(_final_R_jit(omegas[i], dts[i]))
        np.testing.assert_allclose(np.asarray(got["R"][i]), R, atol=1e-14, rtol=0)
        assert float(got["trace"][i]) == pytest.approx(np.trace(R), abs=1e-14)


def test_sweep_rejects_mismatched_batch():
    with pytest.raises(ValueError, match="same leading axis"):
        sweep(_final_R, np.zeros((3, 3)), np.full(4, 0.01))


_TWO_DEVICES = textwrap.dedent(
    """
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    assert len(jax.devices()) == 2, jax.devices()
    import lierk
    from lierk.batch import sweep
    I = np.diag([9.82271303e-05, 7.22671030e-05, 1.57865031e-04])
    def f(w):
        return lierk.solve(lierk.FreeRigidBody(I, w), lierk.RKMK4(), 0.5, dt=0.01, max_steps=50).R[-1]
    w = np.random.default_rng(0).normal(size=(7, 3))  # odd: exercises the padding
    sharded = sweep(f, w, chunk_size=5)
    assert len(sharded.sharding.device_set) == 2, sharded.sharding
    plain = sweep(f, w, shard=False)
    assert len(plain.sharding.device_set) == 1
    err = float(np.max(np.abs(np.asarray(sharded) - np.asarray(plain))))
    assert sharded.shape == (7, 3, 3) and err <= 1e-14, err
    print("OK", len(jax.devices()), err)
    """
)


def test_sweep_sharded_over_two_host_devices_equals_unsharded():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", _TWO_DEVICES], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().startswith("OK 2"), proc.stdout
