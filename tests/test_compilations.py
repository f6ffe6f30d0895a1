"""How many programs XLA builds for a command (`lierk.compilations`).

Every eager ``jax.numpy`` operation on the host path (validation, scene
parsing, diagnostics, figures) is a compilation of its own, tens of
milliseconds each: ``lierk simulate`` once built 97 of them.  These tests pin
the count of a whole command run in-process, so that such operations cannot
creep back.  Each test first clears JAX's in-memory caches, so its count does
not depend on what ran before it."""

from __future__ import annotations

from pathlib import Path

import jax
import pytest

from lierk import cli
from lierk.compilations import Compilations, counting

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _simulate(argv, tmp_path) -> Compilations:
    jax.clear_caches()
    with counting() as seen:
        code = cli.main(["simulate", *argv, "--out", str(tmp_path / "out"), "--no-gif", "--quiet", "--no-cache"])
    assert code == 0
    return seen


@pytest.mark.parametrize(
    "scene, most",
    [
        # The pieces' solve, the problem's inverse inertia and momentum, its
        # omega0, the diagnostics and the exact flip interval.
        ("tee_handle_a.toml", 5),
        # With gravity, and no flip interval (not torque-free).
        ("heavy_top.toml", 4),
    ],
)
def test_simulate_compiles_a_handful_of_programs(scene, most, tmp_path):
    seen = _simulate([str(EXAMPLES / scene), "--t1", "0.5"], tmp_path)
    assert "jit(piece)" in seen.names
    assert seen.count <= most, f"{seen.count} programs compiled: {seen.names}"
    assert 0 < seen.seconds


def test_seconds_count_nested_phases_once():
    c = Compilations(names=["jit(f)"], spans=[(0.0, 1.0), (0.5, 0.75), (2.0, 2.5), (0.9, 1.2)])
    assert c.count == 1
    assert c.seconds == pytest.approx(1.7)
