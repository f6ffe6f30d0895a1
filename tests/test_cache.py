"""The persistent compilation cache (`lierk.app.cache`) and the command line's use of it.

Claims: a second run of a command loads every program from the cache and
compiles none, with bit-identical results; corrupted entries are compiled
again, never loaded, and the run's results are unchanged; a cache directory
that cannot be written costs one warning line and nothing else; the
directory is keyed by a machine fingerprint; `lierk.app.cache.using_cache`
(what each command runs in) turns JAX's cache off or on for one block,
counts what it did, and puts the settings back after it; an executable kept
whole (`lierk.app.cache.compiled`) is loaded in a later call without tracing,
under a key that changes with every value the program depends on.
"""

import collections
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
    p = subprocess.run([LIERK, "simulate", scene, "--out", out, "--no-gif"], env=env, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    with np.load(out / "cached.npz") as f:
        return p.stderr, f["R"]


def counts(stderr):
    m = COUNTS.search(stderr)
    assert m, stderr
    return int(m.group(1)), int(m.group(2))


def entries(root):
    """JAX's entries and the kept executables (`lierk.app.cache.compiled`)."""
    return [p for p in (root / lierk.app.cache.machine_fingerprint()).rglob("*") if p.is_file() and not p.name.startswith(".")]


def test_a_second_run_compiles_nothing_and_corrupted_entries_are_compiled_again(tmp_path):
    """Cold, warm, then with every entry overwritten by random bytes, the
    kept executables too.  (One test: JAX's keys depend on the cache
    directory, so a copied cache would not be read at all.)"""
    root = tmp_path / "cache"
    stderr, R = simulate(tmp_path, root, "cold")
    loaded, compiled = counts(stderr)
    # Every program is kept, the solve too (a run-time check in it, a host
    # callback, kept it out of the cache and cost a compilation every run).
    assert compiled >= 4 and len(entries(root)) >= compiled and "not saved" not in stderr, stderr

    # The scene's solve and its diagnostics are kept whole, keyed without tracing.
    assert len(list((root / lierk.app.cache.machine_fingerprint() / "executables").iterdir())) == 2

    stderr, R_warm = simulate(tmp_path, root, "warm")
    loaded_warm, compiled_warm = counts(stderr)
    assert compiled_warm == 0 and loaded_warm >= compiled, stderr
    np.testing.assert_array_equal(R_warm, R)

    rng = np.random.default_rng(0)
    for p in entries(root):
        p.write_bytes(rng.bytes(max(p.stat().st_size, 64)))
    stderr, R_again = simulate(tmp_path, root, "corrupted")
    m = re.search(r"(\d+) cached programs could not be read and were compiled again", stderr)
    assert m and int(m.group(1)) >= compiled and counts(stderr)[0] == 0, stderr
    assert "warning" not in stderr  # counted in one line, not one warning per entry
    np.testing.assert_array_equal(R_again, R)


def test_an_unwritable_cache_is_one_warning_and_a_normal_run(tmp_path):
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    stderr, R2 = simulate(tmp_path, not_a_dir, "out")
    warnings = [line for line in stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "compilation cache off" in warnings[0] and str(not_a_dir) in warnings[0], stderr
    assert not COUNTS.search(stderr)
    assert R2.shape == (11, 3, 3) and np.abs(R2[-1] - lierk.exact.free_rigid_body(lierk.inertia.tee_handle(), [1.0, 0.05, 0.3], 0.5)[0]).max() < 1e-9


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


OFFSET = 1.0  # a module global the function under test reads

LAPACK_PROGRAM = """
import os
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
import jax
import numpy as np
jax.config.update("jax_enable_x64", True)
import lierk.app.cache as cache
a = np.diag([1.0, 2.0, 3.0]) + 0.1
with cache.using_cache() as use:
    w = cache.compiled(lambda a: jax.numpy.linalg.eigh(a)[0], a)(a)
np.testing.assert_allclose(w, np.linalg.eigvalsh(a), rtol=1e-14)
print(use.counts["hits"], use.counts["misses"])
"""


def test_a_kept_executable_with_lapack_calls_runs_in_a_fresh_process(tmp_path):
    """JAX sets LAPACK up when it lowers a LAPACK call: a process that loads
    such an executable without lowering it must set it up itself (it
    crashed).  With two devices, it is loaded onto the one it was compiled
    for (loaded onto both, it refused its arguments)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
    env["LIERK_CACHE_DIR"] = str(tmp_path)
    runs = [subprocess.run([sys.executable, "-c", LAPACK_PROGRAM], env=env, capture_output=True, text=True, timeout=300)
            for _ in range(2)]
    assert [p.returncode for p in runs] == [0, 0], runs[-1].stderr[-2000:]
    assert [p.stdout.split() for p in runs] == [["0", "1"], ["1", "0"]]


@pytest.fixture
def own_cache_dir(tmp_path):
    """JAX's cache directory set to an empty one for the test."""
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "jax"))
    yield tmp_path / "jax"
    jax.config.update("jax_compilation_cache_dir", before)


def test_a_kept_executable_is_loaded_without_tracing_and_keyed_by_every_value(own_cache_dir, monkeypatch):
    """`compiled` twice with equal values: the second loads the kept
    executable without tracing anything (JAX's trace events, counted) and
    returns the same bits.  A different value anywhere in the program (a
    number the function closes over, a module global it names, a weak type,
    the order of an OrderedDict) is another key; an argument's array of the
    same shape is the same key, its values being the executable's input
    (the right answer for the new inertia); an object the key cannot
    describe compiles as before, unkept; other non-array arguments at call
    time are refused."""
    traces = []

    def listen(event, *_, **__):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            traces.append(event)

    jax.monitoring.register_event_time_span_listener(listen)

    def scaled(scale):
        def f(problem, t1):
            # No run-time checks: a host callback cannot be kept (below).
            with lierk.checked_on_host():
                return scale * OFFSET * lierk.solve(problem, lierk.RKMK4(), t1, dt=0.01, max_steps=40, throw=False).R[-1]

        return f

    def body(inertia):
        return lierk.FreeRigidBody(np.asarray(inertia), np.array([1.0, 0.05, 0.3]))

    compiled, t1 = lierk.app.cache.compiled, jax.numpy.asarray(0.4)
    try:
        with lierk.app.cache.using_cache() as use:
            first = compiled(scaled(2.0), body([2.0, 3.0, 4.0]), t1)(body([2.0, 3.0, 4.0]), t1)
            assert traces and use.counts["misses"] == 1
            del traces[:]
            lierk.app.cache._in_process.clear()  # as in a new process
            again = compiled(scaled(2.0), body([2.0, 3.0, 4.0]), t1)
            assert compiled(scaled(2.0), body([2.0, 3.0, 4.0]), t1) is again  # this process's, not loaded again
            np.testing.assert_array_equal(again(body([2.0, 3.0, 4.0]), t1), first)
            # Arguments of the same shapes run through a loaded executable too.
            R = again(body([2.0, 3.0, 5.0]), jax.numpy.asarray(0.3))
            assert not traces and use.counts["hits"] == 1, use.counts
            exact = lierk.exact.free_rigid_body(np.diag([2.0, 3.0, 5.0]), [1.0, 0.05, 0.3], 0.3)[0]
            np.testing.assert_allclose(R, 2.0 * exact, atol=1e-8)
            with pytest.raises(ValueError, match="other non-array values"):
                again(body([2.0, 3.0, 4.0]), 0.4)

            other = compiled(scaled(3.0), body([2.0, 3.0, 4.0]), t1)(body([2.0, 3.0, 4.0]), t1)
            np.testing.assert_allclose(other, 1.5 * first, rtol=1e-15)
            lierk.app.cache._in_process.clear()
            R = compiled(scaled(2.0), body([2.0, 3.0, 4.5]), t1)(body([2.0, 3.0, 4.5]), t1)
            assert use.counts["misses"] == 2 and use.counts["hits"] == 2, use.counts
            exact = lierk.exact.free_rigid_body(np.diag([2.0, 3.0, 4.5]), [1.0, 0.05, 0.3], 0.4)[0]
            np.testing.assert_allclose(R, 2.0 * exact, atol=1e-8)
            monkeypatch.setattr(sys.modules[__name__], "OFFSET", 2.0)
            np.testing.assert_allclose(compiled(scaled(2.0), body([2.0, 3.0, 4.0]), t1)(body([2.0, 3.0, 4.0]), t1),
                                       2.0 * first, rtol=1e-15)
            assert use.counts["misses"] == 3 and use.counts["hits"] == 2, use.counts

            def pair(d):
                return d["a"] - 2.0 * d["b"]

            x, y = jax.numpy.asarray([1.0, 2.0]), jax.numpy.asarray([5.0, 7.0])
            for d in (collections.OrderedDict(a=x, b=y), collections.OrderedDict(b=y, a=x)):
                np.testing.assert_array_equal(compiled(pair, d)(d), x - 2.0 * y)
            # A weak type promotes otherwise (1/3 * float16 is float16 or float64): the same bytes, other keys.
            weak, strong = jax.numpy.asarray(1.0 / 3.0), jax.numpy.asarray(np.float64(1.0 / 3.0))
            assert weak.weak_type and not strong.weak_type
            key = lierk.app.cache._executable_key
            assert key(pair, (weak,)) != key(pair, (strong,)) and key(pair, (weak,)) == key(pair, (weak,))
            # Inside checked_on_host a solve leaves its run-time checks out: another program.
            with lierk.checked_on_host():
                assert lierk.checks.checking_on_host() and key(pair, (weak,)) != key(pair, (strong,))
                inside = key(pair, (weak,))
            assert not lierk.checks.checking_on_host() and inside != key(pair, (weak,))
            # XLA's options are part of the program.
            options = {"xla_cpu_use_fusion_emitters": False}
            assert key(pair, (weak,), options) != key(pair, (weak,)) == key(pair, (weak,), {})
            assert use.counts["misses"] == 5, use.counts

            class Opaque:  # a class of one's own: its methods could be anything
                scale = 1.0

            def g(problem, t1, opaque=Opaque()):
                return opaque.scale * scaled(1.0)(problem, t1)

            np.testing.assert_array_equal(compiled(g, body([2.0, 3.0, 4.0]), t1)(body([2.0, 3.0, 4.0]), t1), first)  # OFFSET 2
            assert use.counts["misses"] == 5

            def checked(problem, t1):  # t1's run-time check is a host callback
                return lierk.solve(problem, lierk.RKMK4(), t1, dt=0.01, max_steps=40, throw=False).R[-1]

            unsaved = use.counts["unsaved"]
            np.testing.assert_array_equal(compiled(checked, body([2.0, 3.0, 4.0]), t1)(body([2.0, 3.0, 4.0]), t1),
                                          first / 2.0)
            assert use.counts["unsaved"] > unsaved  # and not kept: five files below
    finally:
        jax.monitoring.unregister_event_time_span_listener(listen)
    kept = own_cache_dir / "executables"
    assert len(list(kept.iterdir())) == 5
    # The least recently used go first.
    for k, p in enumerate(sorted(kept.iterdir())):
        os.utime(p, (1e9 + k, 1e9 + k))
    newest = sorted(kept.iterdir())[-1]
    lierk.app.cache._prune(kept, keep=1)
    assert list(kept.iterdir()) == [newest]


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
    # A run-time check on a traced value is a host callback: JAX compiles the
    # program and does not save it.  Inside `checked_on_host` it has none.
    import equinox as eqx

    from lierk import _validation as validation

    def f(x):
        return validation.check(x, lambda v: v > 0, "x must be > 0, got {value}") * 2.0

    with lierk.app.cache.using_cache() as use:
        eqx.filter_jit(f)(np.float64(1.5 + np.random.default_rng().random()))
        with validation.checked_on_host():
            eqx.filter_jit(lambda x: f(x) + 1.0)(np.float64(2.5))
    assert use.counts["unsaved"] == 1 and use.counts["hits"] + use.counts["misses"] == 1, use.counts
    assert use.summary().endswith("; 1 compiled and not saved")


def test_using_cache_without_a_directory_keeps_every_program_in_lierk_s(monkeypatch, tmp_path):
    monkeypatch.setenv("LIERK_CACHE_DIR", str(tmp_path))
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    before = {name: getattr(jax.config, name) for name in names}
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        with lierk.app.cache.using_cache() as use:
            assert jax.config.jax_compilation_cache_dir == use.path == str(tmp_path / lierk.app.cache.machine_fingerprint())
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
