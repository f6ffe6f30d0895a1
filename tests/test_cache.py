"""The persistent compilation cache (`lierk.app.cache`) and the command line's use of it.

Claims: a second run of a command loads every program from the cache and
compiles none, with bit-identical results; corrupted entries are compiled
again, never loaded, and the run's results are unchanged; a cache directory
that cannot be written costs one warning line and nothing else; the
directory is keyed by a machine fingerprint; `lierk.app.cache.using_cache`
(what each command runs in) turns JAX's cache off or on for one block,
counts what it did, and puts the settings back after it.
"""

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import write

import lierk
import lierk.exact

LIERK = str(Path(sys.executable).parent / "lierk")

SCENE = """
name = "cached"
[body]
kind = "tee_handle"
[initial]
omega = [1.0, 0.05, 0.3]
[run]
solver = "RKMK4"
dt = 0.01
t1 = 0.5
save_every = 5
"""
COUNTS = re.compile(r"compiled programs: (\d+) loaded from the cache, (\d+) compiled and saved")


def simulate(tmp_path, root, name):
    """``lierk simulate`` in a fresh process with the cache under ``root``
    (JAX's own cache settings, which the tests set, removed):
    ``(stderr, saved R)``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
    env["LIERK_CACHE_DIR"] = str(root)
    out = tmp_path / name
    scene = write(tmp_path, SCENE)
    p = subprocess.run(
        [LIERK, "simulate", scene, "--out", out, "--no-gif"], env=env, capture_output=True, text=True, timeout=600
    )
    assert p.returncode == 0, p.stderr
    with np.load(out / "cached.npz") as f:
        return p.stderr, f["R"]


def counts(stderr):
    m = COUNTS.search(stderr)
    assert m, stderr
    return int(m.group(1)), int(m.group(2))


def entries(root):
    """JAX's entries (named ``<program>-<key>-cache``)."""
    return [
        p
        for p in (root / lierk.app.cache.machine_fingerprint()).rglob("*")
        if p.is_file() and not p.name.startswith(".")
    ]


def test_a_second_run_compiles_nothing_and_corrupted_entries_are_compiled_again(tmp_path):
    """Cold, warm, then with every entry overwritten by random bytes.  (One
    test: JAX's keys depend on the cache directory, so a copied cache would
    not be read at all.)"""
    root = tmp_path / "cache"
    stderr, R = simulate(tmp_path, root, "cold")
    loaded, compiled = counts(stderr)
    # Every program is kept, the solve too (a run-time check in it, a host
    # callback, kept it out of the cache and cost a compilation every run).
    assert loaded == 0 and compiled >= 4 and "not saved" not in stderr, stderr
    kept = sorted(p.name for p in entries(root))
    assert len(kept) == compiled, kept
    # The scene's solve and the diagnostics among them.
    assert any(n.startswith("jit_piece-") for n in kept) and any(n.startswith("jit__compute-") for n in kept), kept

    # Warm: every program, the solve's included, loaded from JAX's cache; none
    # compiled, none left unsaved, no entry added.
    stderr, R_warm = simulate(tmp_path, root, "warm")
    assert counts(stderr) == (compiled, 0) and "not saved" not in stderr, stderr
    assert sorted(p.name for p in entries(root)) == kept
    np.testing.assert_array_equal(R_warm, R)

    rng = np.random.default_rng(0)
    for p in entries(root):
        p.write_bytes(rng.bytes(max(p.stat().st_size, 64)))
    stderr, R_again = simulate(tmp_path, root, "corrupted")
    m = re.search(r"(\d+) cached programs could not be read and were compiled again", stderr)
    assert m and int(m.group(1)) == compiled and counts(stderr)[0] == 0, stderr
    assert "warning" not in stderr  # counted in one line, not one warning per entry
    np.testing.assert_array_equal(R_again, R)


def test_an_unwritable_cache_is_one_warning_and_a_normal_run(tmp_path):
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    stderr, R2 = simulate(tmp_path, not_a_dir, "out")
    warnings = [line for line in stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "compilation cache off" in warnings[0] and str(not_a_dir) in warnings[0], stderr
    assert not COUNTS.search(stderr)
    assert (
        R2.shape == (11, 3, 3)
        and np.abs(R2[-1] - lierk.exact.free_rigid_body(lierk.inertia.tee_handle(), [1.0, 0.05, 0.3], 0.5)[0]).max()
        < 1e-9
    )


def test_the_directory_is_keyed_by_the_machine(tmp_path):
    fp = lierk.app.cache.machine_fingerprint()
    assert re.fullmatch(r"[0-9a-f]{16}", fp) and fp == lierk.app.cache.machine_fingerprint()
    path = lierk.app.cache.compilation_cache_dir(tmp_path)
    assert path == tmp_path / fp and path.is_dir() and not list(path.iterdir())  # the write probe is gone
    plain = tmp_path / "plain"
    plain.write_text("")
    with pytest.warns(UserWarning, match="compilation cache off"):
        assert lierk.app.cache.compilation_cache_dir(plain) is None


def test_no_cache_turns_jax_s_cache_off_for_the_block_only(monkeypatch):
    before = jax.config.jax_enable_compilation_cache
    with lierk.app.cache.using_cache(False) as use:
        assert jax.config.jax_enable_compilation_cache is False
    assert jax.config.jax_enable_compilation_cache == before and use.summary() is None
    monkeypatch.setenv("LIERK_NO_CACHE", "1")
    with lierk.app.cache.using_cache() as use:
        assert jax.config.jax_enable_compilation_cache is False
    assert jax.config.jax_enable_compilation_cache == before and use.summary() is None


@pytest.fixture
def keep_every_program():
    """JAX counts a program it compiled only when it saves it: keep even small ones."""
    before = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    yield
    jax.config.update("jax_persistent_cache_min_compile_time_secs", before)


def test_using_cache_counts_what_the_cache_did_and_passes_other_warnings_on(keep_every_program):
    """JAX's own directory (the tests set one) is used as it is; programs
    loaded or saved are counted, each unreadable entry too (not shown), and
    any other warning is shown as usual."""
    names = ("jax_enable_compilation_cache", "jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    before = {name: getattr(jax.config, name) for name in names}
    entry = "Error reading persistent compilation cache entry for 'jit_f': ValueError: bad"
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        with lierk.app.cache.using_cache() as use:
            jax.jit(lambda x: 3.0 * x + 1.0)(np.arange(7.0)).block_until_ready()
            for _ in range(2):  # every one counts, not only the first from this line
                warnings.warn(entry)
            warnings.warn("Error writing persistent compilation cache entry for 'jit_f': OSError: full")
            warnings.warn("something else")
    assert [str(w.message) for w in shown] == ["something else"]
    assert use.path == str(before["jax_compilation_cache_dir"])
    assert use.counts["hits"] + use.counts["misses"] == 1
    assert (use.counts["unreadable"], use.counts["unwritable"]) == (2, 1)
    assert use.summary() == (
        f"compiled programs: {use.counts['hits']} loaded from the cache, {use.counts['misses']} compiled and saved "
        f"({use.path}); 2 cached programs could not be read and were compiled again; 1 could not be saved"
    )
    assert {name: getattr(jax.config, name) for name in names} == before


def test_programs_jax_cannot_keep_are_counted_apart(keep_every_program):
    # A host callback (equinox's run-time error) keeps JAX from saving a
    # program.  A solve's checks of traced inputs are made in the program,
    # so with throw=False it has none and is kept.
    import equinox as eqx

    body = lierk.FreeRigidBody(np.array([1.0, 2.0, 3.0]), np.array([0.3, 1.0, 0.2]))
    rng = np.random.default_rng()
    with lierk.app.cache.using_cache() as use:
        eqx.filter_jit(lambda x: eqx.error_if(x, x <= 0, "x must be > 0") * 2.0)(np.float64(1.5 + rng.random()))
        run = eqx.filter_jit(lambda dt: lierk.solve(body, lierk.RKMK4(), 0.1, dt=dt, max_steps=20, throw=False).result)
        assert int(run(np.float64(0.01 + 1e-3 * rng.random()))) == 0
        assert int(run(np.float64(-0.01))) == lierk.RESULTS.invalid_step
    assert use.counts["unsaved"] == 1 and use.counts["hits"] + use.counts["misses"] == 1, use.counts
    assert use.summary().endswith("; 1 compiled and not saved")


def test_using_cache_without_a_directory_keeps_every_program_in_lierk_s(monkeypatch, tmp_path):
    monkeypatch.setenv("LIERK_CACHE_DIR", str(tmp_path))
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    before = {name: getattr(jax.config, name) for name in names}
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        with lierk.app.cache.using_cache() as use:
            assert (
                jax.config.jax_compilation_cache_dir
                == use.path
                == str(tmp_path / lierk.app.cache.machine_fingerprint())
            )
            assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0
        assert jax.config.jax_compilation_cache_dir is None
    finally:
        for name, value in before.items():
            jax.config.update(name, value)


def test_default_root_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("LIERK_CACHE_DIR", str(tmp_path / "mine"))
    assert lierk.app.cache.default_cache_root() == tmp_path / "mine"
    monkeypatch.delenv("LIERK_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert lierk.app.cache.default_cache_root() == tmp_path / "xdg" / "lierk"
