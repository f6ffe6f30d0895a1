"""Fixed steps in float32 end exactly at t1 when n * dt equals t1 only up to
float32 rounding (20 * 0.01 is a few ulps short of 0.2 in float32)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lierk

from helpers import OMEGA_GENERIC, TEE


@pytest.mark.parametrize("n", [20, 30])
def test_float32_fixed_steps_reach_t1(n):
    body = lierk.FreeRigidBody(jnp.asarray(TEE, jnp.float32), jnp.asarray(OMEGA_GENERIC, jnp.float32))
    # Under jit t1 and dt are traced, so the step count comes from max_steps.
    sol = jax.jit(lambda b: lierk.solve(b, lierk.RKMK4(), n * 0.01, dt=0.01, max_steps=n, throw=False))(body)
    assert int(sol.result) == lierk.RESULTS.successful
    assert sol.R.dtype == jnp.float32
    assert float(sol.ts[-1]) == np.float32(n * 0.01)
