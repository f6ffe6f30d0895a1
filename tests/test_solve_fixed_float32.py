"""Fixed steps in float32 end exactly at t1 when n * dt equals t1 only up to
float32 rounding (20 * 0.01 is a few ulps short of 0.2 in float32)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import OMEGA_GENERIC, TEE

import lierk


@pytest.mark.parametrize("n", [20, 30])
def test_float32_fixed_steps_reach_t1(n):
    body = lierk.FreeRigidBody(jnp.asarray(TEE, jnp.float32), jnp.asarray(OMEGA_GENERIC, jnp.float32))
    # Under jit t1 and dt are traced, so the step count comes from max_steps.
    sol = jax.jit(lambda b: lierk.solve(b, lierk.RKMK4(), n * 0.01, dt=0.01, max_steps=n, throw=False))(body)
    assert int(sol.result) == lierk.RESULTS.successful
    assert sol.R.dtype == jnp.float32
    assert float(sol.ts[-1]) == np.float32(n * 0.01)


_BOX32 = np.diag([1.0, 2.0, 3.0]).astype(np.float32)
_W32 = np.array([0.3, 1.0, 0.2], np.float32)


def test_float32_fixed_steps_far_from_t0_are_as_accurate_as_from_zero():
    """10 s of motion from t0 = 0, 3e4 and 1e5 in float32 (dt = 2^-6, two
    ulps of t at 1e5).  Before: the end-of-run snap was 64 eps |t1| (0.76 s
    at t1 = 1e5), so the last ~49 steps merged into one, and the error grew
    from 4.0e-6 to 5.8e-4 with result 0."""
    ref = np.asarray(lierk.exact.free_rigid_body(_BOX32.astype(float), _W32.astype(float), 10.0)[0])
    errs = []
    for t0 in (0.0, 3e4, 1e5):
        sol = lierk.solve(
            lierk.FreeRigidBody(_BOX32, _W32), lierk.RKMK4(), np.float32(t0 + 10.0), t0=np.float32(t0), dt=2.0**-6
        )
        assert int(sol.stats["num_steps"]) == 640
        assert float(sol.ts[-1]) == np.float32(t0 + 10.0)
        errs.append(np.linalg.norm(np.asarray(sol.R[-1], float) - ref))
    assert errs[0] < 1e-5
    assert max(errs) < 1.5 * errs[0]


def test_float32_step_below_the_resolution_of_time_is_refused():
    with pytest.raises(ValueError, match="below the resolution of float32 times"):
        lierk.solve(
            lierk.FreeRigidBody(_BOX32, _W32), lierk.RKMK4(), np.float32(1e5 + 1.0), t0=np.float32(1e5), dt=1e-3
        )


def test_steps_add_up_to_the_interval_when_t1_is_not_a_multiple_of_dt():
    """Every step is exactly dt but the last, which is what remains of
    t1 - t0 (here 0.3 dt): the same final state as the solver's own steps
    taken by hand."""
    body = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    solver = lierk.RKMK4()
    sol = lierk.solve(body, solver, 1.003, dt=0.01)
    assert int(sol.stats["num_steps"]) == 101
    step = jax.jit(lambda t, h, R, y: (lambda st: (st.R, st.y))(solver.step(body, t, h, R, y)))
    R, y = body.R0, body.y0
    for k in range(100):
        R, y = step(k * 0.01, 0.01, R, y)
    R, y = step(1.0, 1.003 - 100 * 0.01, R, y)
    np.testing.assert_allclose(np.asarray(sol.R[-1]), np.asarray(R), rtol=0, atol=1e-14)
