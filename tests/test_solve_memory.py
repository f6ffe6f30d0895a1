"""Fixed-step solves hold memory in proportion to the saved points, not the steps.

XLA's own accounting (`Compiled.memory_analysis`) is the measure: the
temporaries of a solve that saves only t1 must not grow from 10^3 to 10^9
steps, and with a save every 1000 steps they grow with the saved points only.
"""

import jax
import jax.numpy as jnp
import pytest

import lierk

BODY = lierk.FreeRigidBody(lierk.inertia.tee_handle(), jnp.array([1.0, 0.05, 0.0]))


def temp_bytes(n_steps, saveat, solver=lierk.RKMK4()):
    def final(body):
        return lierk.solve(body, solver, n_steps * 0.01, dt=0.01, saveat=saveat).R[-1]

    return jax.jit(final).lower(BODY).compile().memory_analysis().temp_size_in_bytes


@pytest.mark.parametrize("solver", [lierk.RKMK4(), lierk.CF4()], ids=lambda s: s.name)
def test_temporaries_do_not_grow_with_steps(solver):
    # (Runs of 4096+ steps skip checkpoint blocks past their end, one
    # conditional each: 10^4 and 10^9 steps have the same program structure.)
    small = temp_bytes(10**4, lierk.SaveAt(t1=True), solver)
    # 10^9 steps: before, 8 bytes of step indices and times per step (8 GB).
    assert temp_bytes(10**9, lierk.SaveAt(t1=True), solver) == small
    assert small < 64 * 1024


def test_temporaries_grow_with_saved_points_only():
    every = lierk.SaveAt(steps=1000, t1=True)
    a, b = temp_bytes(10**6, every), temp_bytes(10**7, every)
    # 9000 more saved states of R (72 bytes) and m (24 bytes): a few copies
    # each, never the 9e6 extra steps.
    assert 9000 * 96 <= b - a <= 9000 * 96 * 4
