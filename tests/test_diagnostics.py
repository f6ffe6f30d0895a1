"""`lierk.app.diagnostics`: the quantities a report of a solve shows, in one program."""

from __future__ import annotations

import numpy as np
from helpers import TEE

import lierk
from lierk.app.diagnostics import diagnostics


def test_diagnostics_agree_with_the_quantities_one_by_one():
    body = lierk.FreeRigidBody(TEE, [1.0, 0.05, 0.3])
    sol = lierk.solve(body, lierk.RKMK4(), 2.0, dt=0.05, saveat=lierk.SaveAt(t0=True, steps=4))
    d = diagnostics(body, sol)
    n = int(sol.n_saved)
    np.testing.assert_allclose(d.omega, np.asarray(sol.omega(body))[:n], rtol=1e-14)
    L = np.einsum("nij,nj->ni", np.asarray(sol.R), np.asarray(sol.y))
    np.testing.assert_allclose(d.L, L, rtol=1e-13, atol=1e-18)
    inv = body.invariants(sol.R, sol.y)
    for k in ("energy", "|L|"):
        np.testing.assert_allclose(d.invariants[k], np.asarray(inv[k]), rtol=1e-14)
        v = np.asarray(inv[k])
        assert d.drift[k] == np.max(np.abs(v - v[0])) / abs(v[0])
    # RKMK4 at 0.05 s loses energy at its own accuracy, and R stays on SO(3).
    assert 1e-12 < d.drift["energy"] < 1e-4
    assert d.orthogonality == float(np.max(np.asarray(sol.orthogonality_error))) < 1e-14
    # A torque-free body's exact flip interval comes with them (one program).
    np.testing.assert_allclose(d.flip_interval, float(lierk.exact.flip_interval(TEE, [1.0, 0.05, 0.3])), rtol=1e-13)
    assert 1.0 < d.flip_interval < np.inf


def test_flip_interval_only_for_a_torque_free_body():
    top = lierk.RigidBodyWithEffects(TEE, [1.0, 0.05, 0.3], effects=lierk.Damping(1e-8))
    sol = lierk.solve(top, lierk.RKMK4(), 0.2, dt=0.05, saveat=lierk.SaveAt(t0=True, steps=4))
    assert diagnostics(top, sol).flip_interval is None
