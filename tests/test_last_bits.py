"""Claims that hold to the last bits of the program XLA compiles by default.

``make test`` compiles most modules with XLA's quick settings (no LLVM
optimisation, the older loop emitters; see the Makefile): they halve the
suite's compile time and move results by a few units in the last place, since
the machine code contracts and orders operations differently.  The claims
here are about exactly those bits, or depend on them, so this module (like the
pages of the manual, whose printed numbers are what users see) is compiled as
users compile: with XLA's defaults.

- Saving every step takes the same steps as saving the end only: the last
  saved attitude is the plain solve's, bit for bit.
- The loops' tie between the attitude's and the state's tangents is an exact
  zero, so a NaN cotangent (the ``jnp.where`` trap) leaves the gradient
  unchanged, bit for bit.
- An adaptive solve stepping across the kinks of a sampled torque reaches
  2.9e-11 at rtol 1e-12 (bound 1e-10).  Where its steps straddle the kinks
  follows the rounding of every step before: under the quick settings the
  same solve reaches 2.3e-10.
"""

import jax
import jax.numpy as jnp
import numpy as np
from helpers import OMEGA_GENERIC, TEE, TORQUE_IMPULSE, TORQUE_SAMPLES, TORQUE_TIMES

import lierk


def test_saving_every_step_ends_on_the_plain_solve_to_the_bit():
    body = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    end = lierk.solve(body, lierk.DP54(), 10.0, rtol=1e-9)
    steps = lierk.solve(body, lierk.DP54(), 10.0, rtol=1e-9, max_steps=500, saveat=lierk.SaveAt(steps=True))
    n = int(steps.n_saved)
    assert float(steps.ts[n - 1]) == 10.0
    np.testing.assert_array_equal(np.asarray(steps.R[n - 1]), np.asarray(end.R[0]))


def test_a_nan_cotangent_on_the_momentum_stays_out_of_the_attitude_gradient():
    """The loops tie the initial attitude's tangent to the state's, so that
    JAX's loop rules reach their fixed point in one pass.  The tie is an
    exact zero: a NaN cotangent on y (the jnp.where trap) does not reach the
    gradient with respect to R0, which a free body's y does not depend on
    (with a zero times the tangents it was NaN)."""
    theta = jnp.array([0.1, 0.2, 0.3])

    def loss(theta, solver, kw, trap):
        body = lierk.FreeRigidBody(TEE, OMEGA_GENERIC, lierk.so3.exp(theta))
        sol = lierk.solve(body, solver, 2.0, adjoint=lierk.RecursiveCheckpointAdjoint(), **kw)
        m = sol.y[-1]
        nan_cotangent = jnp.where(m[0] > -1e9, 0.0, jnp.sqrt(-jnp.abs(m[1]))) if trap else 0.0
        return sol.R[-1, 0, 1] + nan_cotangent

    for solver, kw in ((lierk.RKMK4(), dict(dt=0.05)), (lierk.DP54(), dict(rtol=1e-9, atol=1e-9))):
        g, g_plain = (
            jax.jit(jax.grad(lambda th, trap=trap: loss(th, solver, kw, trap)))(theta) for trap in (True, False)
        )
        assert np.all(np.isfinite(g)), g
        np.testing.assert_array_equal(g, g_plain)


def test_adaptive_steps_cross_a_sampled_torque_s_kinks_to_its_tolerance():
    """Spin about body z with a piecewise-linear torque along body z: m3 grows
    by the impulse, the other components stay 0 (the fixed-step solvers, with
    the sample times on their grid: tests/test_splitting.py)."""
    torque = lierk.TimedTorque(TORQUE_SAMPLES, times=TORQUE_TIMES)
    body = lierk.RigidBodyWithEffects([1.0, 2.0, 3.0], [0.0, 0.0, 0.7], effects=torque)
    m = np.asarray(lierk.solve(body, lierk.DOP853(), 2.5, rtol=1e-12, atol=1e-12).y[-1])
    assert abs(m[2] - (3.0 * 0.7 + TORQUE_IMPULSE)) < 1e-10
    assert np.abs(m[:2]).max() < 1e-14
