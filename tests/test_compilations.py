"""How many programs XLA builds for a command (`lierk.app.compilations`).

Every eager ``jax.numpy`` operation on the host path (validation, scene
parsing, diagnostics, figures) is a compilation of its own, tens of
milliseconds each: ``lierk simulate`` once built 97 of them.  These tests pin
the count of a whole command run in-process, so that such operations cannot
creep back.  Each test first clears JAX's in-memory caches, so its count does
not depend on what ran before it."""

from __future__ import annotations

import gc
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
import pytest

import lierk
from lierk.app import cli
from lierk.app.compilations import Compilations, counting
from lierk.app.simulation import simulate

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
        # The pieces' solve, the problem's momentum (its inverse inertia is
        # NumPy's), its omega0, and the diagnostics with the exact flip
        # interval.
        ("tee_handle_a.toml", 4),
        # With gravity, and no flip interval (not torque-free).
        ("heavy_top.toml", 4),
    ],
)
def test_simulate_compiles_a_handful_of_programs(scene, most, tmp_path):
    seen = _simulate([str(EXAMPLES / scene), "--t1", "0.5"], tmp_path)
    assert "jit(piece)" in seen.names
    assert seen.count <= most, f"{seen.count} programs compiled: {seen.names}"
    assert 0 < seen.seconds


@pytest.mark.parametrize(
    "run",
    [
        {"solver": "RKMK4", "dt": 0.01, "save_every": 5},
        {"solver": "DOP853", "rtol": 1e-8, "n_save": 11},
        {"solver": "RKMK4", "target_error": 1e-6, "n_save": 11},
    ],
    ids=["fixed", "adaptive", "target_error"],
)
def test_every_program_of_a_simulation_can_be_kept_in_the_cache(run, tmp_path):
    # A run-time check on a traced value is a host callback, and JAX keeps
    # no program with one: the solve compiled again in every process.
    scene = lierk.app.scene.from_dict(
        {"body": {"kind": "tee_handle"}, "initial": {"omega": [1.0, 0.05, 0.3]}, "run": {**run, "t1": 0.5}}
    )
    before = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.clear_caches()
    try:
        with lierk.app.cache.using_cache() as use:
            simulate(scene, n_pieces=2)
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before)
    assert use.path is not None and use.counts["hits"] + use.counts["misses"] >= 2  # the pieces, the diagnostics
    assert use.counts["unsaved"] == 0, use.counts


def test_seconds_count_nested_phases_once():
    c = Compilations(names=["jit(f)"], spans=[(0.0, 1.0), (0.5, 0.75), (2.0, 2.5), (0.9, 1.2)])
    assert c.count == 1
    assert c.seconds == pytest.approx(1.7)


def _compiles(calls) -> list[int]:
    """The programs compiled by each call of ``calls``, after a fresh start."""
    jax.clear_caches()
    counts = []
    for call in calls:
        with counting() as seen:
            jax.block_until_ready(call())
        counts.append(seen.count)
    return counts


def _body(inertia, omega0):
    return lierk.RigidBodyWithEffects(inertia, omega0, effects=(lierk.Gravity([0.0, 0.1, 0.4], 1.0),))


class _CollectorProbe(lierk.BodyTorque):
    """A constant body torque that records, each time it is traced, whether
    Python's cyclic garbage collector is on, or raises (``fail``).  Each
    ``tag`` is a structure of its own: a solve with it is traced afresh."""

    tag: int = eqx.field(static=True)
    fail: bool = eqx.field(static=True)

    def __init__(self, tag, fail=False):
        super().__init__([0.0, 0.0, 0.1])
        self.tag, self.fail = tag, fail

    def torque_from(self, t, v, m, omega):
        _COLLECTOR_SEEN.append(gc.isenabled())
        if self.fail:
            raise RuntimeError("probe")
        return super().torque_from(t, v, m, omega)


_COLLECTOR_SEEN: list[bool] = []


def test_the_collector_is_held_off_while_lierk_traces_and_left_as_it_was():
    # Tracing allocates objects that live until the trace ends; the
    # collector's passes over them were a tenth of a Jacobian's trace.
    def solve(w, probe):
        problem = lierk.RigidBodyWithEffects([2.0, 3.0, 4.0], w, effects=(probe,))
        return lierk.solve(problem, lierk.RKMK4(), 0.1, dt=0.05).R

    w = np.array([0.3, -0.2, 1.0])
    assert gc.isenabled()
    calls = (
        lambda: solve(w, _CollectorProbe(1)),  # from Python: lierk's own program
        lambda: jax.jit(solve)(w, _CollectorProbe(2)),  # inside a caller's trace
        lambda: jax.jacfwd(solve)(w, _CollectorProbe(3)),
    )
    for call in calls:
        _COLLECTOR_SEEN.clear()
        call()
        assert _COLLECTOR_SEEN and not any(_COLLECTOR_SEEN)
        assert gc.isenabled()
    # A trace that fails turns it back on; a caller's choice to hold it off stays.
    with pytest.raises(RuntimeError, match="probe"):
        solve(w, _CollectorProbe(4, fail=True))
    assert gc.isenabled()
    gc.disable()
    try:
        solve(w, _CollectorProbe(5))
        assert not gc.isenabled()
    finally:
        gc.enable()


def test_new_numbers_reuse_the_compiled_program():
    # Python floats (t0, t1, dt, rtol, atol, target_error, inertia, omega0)
    # are traced at the API boundary: one program per structure.  Before,
    # lierk.sensitivity compiled again for every new t1, and an eager solve
    # compiled each array operation around its loop (61 programs).
    I1, I2 = [2.0, 3.0, 4.0], [2.5, 3.5, 4.1]
    w1, w2 = [0.3, -0.2, 5.0], [0.2, 0.1, 4.0]
    fixed = [
        lambda t0=t0, t1=t1, dt=dt, I=I, w=w: lierk.solve(_body(I, w), lierk.RKMK4(), t1, t0=t0, dt=dt, max_steps=64).R
        for t0, t1, dt, I, w in ((0.0, 0.5, 0.01, I1, w1), (0.1, 0.4, 0.02, I2, w2))
    ]
    assert _compiles(fixed) == [2, 0]  # the solve and the body's inverse inertia (one program each)
    adaptive = [
        lambda t1=t1, r=r, a=a, w=w: lierk.solve(_body(I1, w), lierk.DP54(), t1, rtol=r, atol=a, estimate_error=True).R
        for t1, r, a, w in ((0.5, 1e-6, 1e-8, w1), (0.7, 1e-7, 1e-9, w2))
    ]
    assert _compiles(adaptive) == [2, 0]
    target = [
        lambda t1=t1, e=e: lierk.solve(_body(I1, w1), lierk.DP54(), t1, target_error=e).R
        for t1, e in ((0.3, 1e-5), (0.4, 1e-6))
    ]
    assert _compiles(target) == [2, 0]
    event = lierk.Event(lambda t, R, y: R[2, 2] - 0.5)
    events = [lambda t1=t1: lierk.solve(_body(I1, w1), lierk.DP54(), t1, rtol=1e-6, event=event).R for t1 in (0.3, 0.6)]
    assert _compiles(events) == [2, 0]
    sens = [
        lambda t1=t1, r=r: lierk.sensitivity(_body(I1, w1), lierk.DP54(), t1, rtol=r, estimate_error=False).jacobian
        for t1, r in ((0.3, 1e-6), (0.5, 1e-7))
    ]
    assert _compiles(sens) == [2, 0]
    # A fixed-step count without max_steps sizes the loop: a new count is a
    # new program, the same count is not.
    steps = [
        lambda t1=t1: lierk.sensitivity(_body(I1, w1), lierk.RKMK4(), t1, dt=0.01, estimate_error=False).jacobian
        for t1 in (0.3, 0.3 + 1e-12, 0.5)
    ]
    assert _compiles(steps) == [2, 0, 1]


def test_an_eager_derivative_checks_the_body_in_one_program_per_check():
    # Under an eager jax.jacfwd or jax.grad, omega0 is traced but outside any
    # jit: a check made of jax.numpy operations ran each of them as a program
    # of its own (about 50 for a rigid body, 1.5 s of a first Jacobian).
    # Each check is now one program, compiled once for all the calls that
    # make it (each call site's predicate is a new lambda every time).
    def momentum_jacobian(w):
        return jax.block_until_ready(jax.jacfwd(lambda w: _body([2.0, 3.0, 4.0], w).y0)(jax.numpy.asarray(w)))

    names = [None, None]
    jax.clear_caches()
    for k, w in enumerate(([0.3, -0.2, 5.0], [0.2, 0.1, 4.0])):
        with counting() as seen:
            momentum_jacobian(w)
        names[k] = seen.names
    # omega0's checks (finite, and a state in range) are one program.
    checks = ("jit(_error_unless)", "jit(_state_in_range)")
    assert [names[0].count(n) for n in checks] == [0, 1], names[0]
    for op in ("jit(log10)", "jit(_reduce_max)", "jit(abs)", "jit(matmul)", "jit(branched_error_if_impl)"):
        assert op not in names[0], names[0]
    assert not any(n in checks for n in names[1]), names[1]
    # The checks still run, in the program: a NaN in omega0 makes the state
    # NaN (and a solve of it fails with RESULTS.invalid_problem).
    assert np.isnan(np.asarray(momentum_jacobian([0.1, float("nan"), 1.0]))).all()


@pytest.mark.parametrize(
    "inertia", [(2.0, 3.0, 4.0), ((2.0, 0.1, 0.0), (0.1, 3.0, 0.2), (0.0, 0.2, 4.0))], ids=["diagonal", "full"]
)
def test_a_body_of_constants_inside_jit_inverts_its_inertia_on_the_host(inertia):
    # Inside jit the checked inertia is staged (a tracer) even when given as
    # constants; its inverse was an LU factorisation, a while loop in every
    # program that builds a body.
    import numpy as np

    def inverse(w):
        return lierk.RigidBodyWithEffects(inertia, w).inertia_inv

    text = jax.jit(inverse).lower(jax.numpy.ones(3)).as_text()
    assert "while" not in text and "getrf" not in text, text
    expected = np.linalg.inv(np.diag(inertia) if np.ndim(inertia) == 1 else np.asarray(inertia))
    np.testing.assert_allclose(np.asarray(jax.jit(inverse)(jax.numpy.ones(3))), expected, rtol=1e-15)
    # A traced inertia is still inverted, in the program.
    traced = jax.jit(lambda I: lierk.RigidBodyWithEffects(I, [1.0, 0.0, 0.0]).inertia_inv)(np.asarray(inertia))
    np.testing.assert_allclose(np.asarray(traced), expected, rtol=1e-14)


def test_a_call_with_no_traced_argument_runs_its_own_program_with_the_one_body_options(monkeypatch):
    """`lierk._programs`' rule, where a call runs: `lierk.solve`,
    `lierk.sensitivity` and `lierk.exact` called from Python with no traced
    argument compile a program of their own with
    `lierk.one_body_compiler_options` (XLA's older CPU emitters, which
    compile one body sooner); inside a caller's ``jax.jit`` (on values it
    closes over, where JAX refuses a nested program options of its own) and
    with traced arguments (``jax.vmap``, ``jax.jit``, an eager
    ``jax.jacfwd``'s directions) they are the caller's program, with its
    settings; and every call keeps XLA's defaults when ``XLA_FLAGS`` chooses
    the emitters itself (``make test`` does)."""
    from lierk import _sensitivity, _solve

    monkeypatch.setenv("XLA_FLAGS", "")
    assert lierk.one_body_compiler_options() == {"xla_cpu_use_fusion_emitters": False}
    calls = []
    for name, program in (
        ("solve", _solve._program),
        ("jvp", _solve._program_jvp),
        ("sensitivity", _sensitivity._sensitivity),
        ("exact", lierk.exact._free_motion_program),
    ):
        for kind in ("default", "_own"):

            def spy(*args, _f=getattr(program, kind), _tag=(name, kind), **kwargs):
                calls.append(_tag)
                return _f(*args, **kwargs)

            monkeypatch.setattr(program, kind, spy)
    body = lierk.FreeRigidBody(np.array([2.0, 3.0, 4.0]), np.array([1.0, 0.05, 0.3]))

    def solve(w):
        return lierk.solve(lierk.FreeRigidBody(np.array([2.0, 3.0, 4.0]), w), lierk.RKMK4(), 0.2, dt=0.1).R[-1]

    expected = np.asarray(solve(np.array([1.0, 0.05, 0.3])))
    assert calls == [("solve", "_own")]
    batched = jax.vmap(solve)(np.array([[1.0, 0.05, 0.3], [1.0, 0.05, 0.3]]))
    jitted = jax.jit(solve)(np.array([1.0, 0.05, 0.3]))
    assert calls[1:] == [("solve", "default")] * 2
    np.testing.assert_allclose(batched[0], expected, rtol=1e-14)
    np.testing.assert_allclose(jitted, expected, rtol=1e-14)
    # Inside a caller's jit on a body it closes over: JAX refuses the
    # options there, and the solve is the caller's program.
    closed = jax.jit(lambda: lierk.solve(body, lierk.RKMK4(), 0.2, dt=0.1).R[-1])
    np.testing.assert_allclose(closed(), expected, rtol=1e-14)
    assert calls[3:] == [("solve", "_own"), ("solve", "default")]
    del calls[:]
    lierk.sensitivity(body, lierk.RKMK4(), 0.2, dt=0.1, estimate_error=False)
    # (Its solve's derivative is traced inside its program.)
    assert calls == [("sensitivity", "_own"), ("jvp", "default")]
    # An eager jax.jacfwd: its directions are traced, so the derivative is
    # a program with XLA's defaults (its Jacobian in the one-body form).
    jax.jacfwd(solve)(np.array([1.0, 0.05, 0.3]))
    assert calls[2:] == [("jvp", "default")]
    lierk.exact.free_rigid_body(np.array([2.0, 3.0, 4.0]), np.array([1.0, 0.05, 0.3]), 0.2)
    assert calls[3:] == [("exact", "_own")]
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert lierk.one_body_compiler_options() == {}
    solve(np.array([1.0, 0.05, 0.3]))
    assert calls[4:] == [("solve", "default")]


def _marking_the_stage_loop(monkeypatch):
    """Mark the looped form of an RKMK step in the program with an
    optimization barrier (lierk itself places none)."""
    stages = lierk.AbstractRKMK._stages

    def spy(self, *args):
        out = stages(self, *args)
        if not self.compact:
            return out
        arrays, rest = eqx.partition(out, eqx.is_array)
        return eqx.combine(jax.lax.optimization_barrier(arrays), rest)

    monkeypatch.setattr(lierk.AbstractRKMK, "_stages", spy)


def _loops(f, *args) -> bool:
    return "optimization_barrier" in str(jax.make_jaxpr(f)(*args))


def test_one_body_loops_over_a_long_tableaus_stages_and_a_batch_unrolls_them(monkeypatch):
    """`lierk._programs`' rule, the form: one short solve of one body on
    the CPU (at most 4096 steps), called from Python or inside a caller's
    ``jax.jit``, takes the stage loop of a tableau of five or more stages,
    which compiles several times faster; a batch unrolls the stages, under
    ``jit(vmap)`` and under ``vmap(jit)``, whose batching rule replaces the
    loop that the ``jit`` traced.  So do a longer solve, ``compact=False``
    and four-stage tableaux.  The forms agree to rounding."""
    _marking_the_stage_loop(monkeypatch)

    def solve(w, solver=lierk.DP54(), max_steps=None):
        top = lierk.RigidBodyWithEffects(
            np.array([2.0, 3.0, 4.0]), w, effects=lierk.Gravity([0.1, 0.0, 0.5], 1.0, 9.81)
        )
        return lierk.solve(top, solver, 1.0, rtol=1e-10, atol=1e-10, max_steps=max_steps).R[-1]

    w = np.array([1.0, 0.05, 0.3])
    ws = np.stack([w, w])
    looped = np.asarray(solve(w))
    long = np.asarray(solve(w, max_steps=5000))
    assert _loops(jax.jit(solve), w)
    assert _loops(jax.jit(lambda w: solve(w, max_steps=4096)), w)
    assert _loops(jax.jit(lambda w: solve(w, lierk.DP54(compact=True), max_steps=5000)), w)
    # Every argument concrete, inside a caller's jit (a body built outside
    # it): one body in the caller's program.
    free = lierk.FreeRigidBody(np.array([2.0, 3.0, 4.0]), w)
    assert _loops(jax.jit(lambda: lierk.solve(free, lierk.DP54(), 1.0, rtol=1e-10, atol=1e-10).R[-1]))
    assert not _loops(jax.jit(lambda w: solve(w, max_steps=4097)), w)
    assert not _loops(jax.jit(jax.vmap(solve)), ws)
    assert not _loops(jax.vmap(jax.jit(solve)), ws)
    assert not _loops(jax.jit(lambda w: solve(w, lierk.DP54(compact=False))), w)
    assert not _loops(
        jax.jit(
            lambda w: lierk.solve(lierk.FreeRigidBody(np.array([2.0, 3.0, 4.0]), w), lierk.RKMK4(), 1.0, dt=0.1).R[-1]
        ),
        w,
    )
    # Values made while tracing one program and kept for another broke
    # JAX's dispatch of the next (a cache of device scalars, tried and
    # dropped: the batch's second call failed).
    jitted = np.asarray(jax.jit(solve)(w))
    for batch in (jax.jit(jax.vmap(solve)), jax.vmap(jax.jit(solve))):
        batch(ws)
        np.testing.assert_allclose(
            batch(ws), [jitted, jitted], rtol=0, atol=1e-14
        )  # a second call: JAX's fast dispatch
    # A derivative around a vmap(jit): the batching rule's outputs and the
    # custom derivative's must batch alike (a grad failed to lower: the
    # count of saved states was batched in one and not in the other).
    two = ws + np.array([[0.0], [0.1]])
    grads = jax.grad(lambda ws: jax.numpy.sum(jax.vmap(jax.jit(solve))(ws) ** 3))(two)
    each = jax.jit(jax.vmap(jax.grad(lambda v: jax.numpy.sum(solve(v, lierk.DP54(compact=False)) ** 3))))(two)
    np.testing.assert_allclose(grads, each, rtol=0, atol=1e-12)
    unrolled = np.asarray(solve(w, lierk.DP54(compact=False)))
    for other in (unrolled, jitted, long):
        np.testing.assert_allclose(looped, other, rtol=0, atol=1e-14)


def test_one_bodys_jacobian_loops_over_rkmk4s_stages_and_a_batch_of_them_unrolls(monkeypatch):
    """`lierk._programs`' rule for derivatives: one body's Jacobian
    (``jax.jacfwd``, ``jax.jvp``, ``jax.grad`` inside a caller's
    ``jax.jit``) takes the one-body form, which loops RKMK4's four stages
    too; a batch of Jacobians unrolls them, under ``jit(vmap(jacfwd))`` and
    under ``vmap(jit(jacfwd))``, whose batching rule replaces the loop, and
    so does ``jacfwd`` of a batch.  The forms agree to rounding."""
    _marking_the_stage_loop(monkeypatch)

    def final(w):
        body = lierk.RigidBodyWithEffects(
            np.array([2.0, 3.0, 4.0]), w, effects=lierk.Gravity([0.1, 0.0, 0.5], 1.0, 9.81)
        )
        return lierk.solve(body, lierk.RKMK4(), 1.0, dt=0.1).R[-1]

    w = np.array([1.0, 0.05, 0.3])
    ws = np.stack([w, w + 0.1])
    jacobian = jax.jit(jax.jacfwd(final))
    assert _loops(jacobian, w)
    assert _loops(jax.jit(lambda w: jax.jvp(final, (w,), (np.ones(3),))[1]), w)
    assert _loops(jax.jit(jax.grad(lambda w: jax.numpy.sum(final(w) ** 3))), w)
    assert not _loops(jax.jit(jax.vmap(jax.jacfwd(final))), ws)
    assert not _loops(jax.vmap(jacobian), ws)
    assert not _loops(jax.jit(jax.jacfwd(jax.vmap(final))), ws)
    each = np.stack([np.asarray(jacobian(v)) for v in ws])
    for batch in (jax.jit(jax.vmap(jax.jacfwd(final))), jax.vmap(jacobian)):
        np.testing.assert_allclose(batch(ws), each, rtol=0, atol=1e-13)
    of_batch = jax.jit(jax.jacfwd(jax.vmap(final)))(ws)
    np.testing.assert_allclose(np.stack([of_batch[k, :, :, k] for k in range(2)]), each, rtol=0, atol=1e-13)
    grad = jax.jit(jax.grad(lambda w: jax.numpy.sum(final(w) ** 3)))(w)
    R = np.asarray(final(w))
    np.testing.assert_allclose(grad, np.einsum("ij,ijk->k", 3 * R**2, each[0]), rtol=0, atol=1e-12)


def test_the_rule_reads_no_private_jax_and_no_tracer_class():
    """The rule uses public JAX only: no ``jax._src``, no tracer class
    names or attributes, anywhere in the package."""
    import re
    from pathlib import Path

    root = Path(lierk.__file__).parent
    for path in root.rglob("*.py"):
        text = path.read_text()
        for pattern in (
            r"jax\._src",
            r"BatchTracer",
            r"JaxprTracer",
            r"JVPTracer",
            r"\.batch_dim\b",
            r"trace_state_clean",
        ):
            assert not re.search(pattern, text), f"{path.relative_to(root.parent)} matches {pattern}"


def test_one_bodys_adaptive_solve_compiles_few_kernels():
    # XLA's CPU backend compiles each kernel of a program (a fusion, a matrix
    # product) on its own, about 5 ms apiece whatever its size, so the count
    # decides a first compile (CHANGELOG.md, "A kernel costs about 5 ms to
    # compile").  A heavy top's adaptive DOP853 solve inside
    # jax.jit was 77 kernels; written to fuse, 52 (48 with the suite's quick
    # XLA flags).  diffrax's Dopri8 is 26.
    def final(w, tol):
        top = lierk.RigidBodyWithEffects(
            [2.0, 3.0, 4.0], w, effects=(lierk.Gravity(np.array([0.1, 0.0, 0.5]), 1.0, 9.81),)
        )
        return lierk.solve(top, lierk.DOP853(), 1.0, rtol=tol, atol=tol, throw=False).R[-1]

    text = jax.jit(final).lower(jax.numpy.array([1.0, 0.3, 20.0]), jax.numpy.asarray(1e-8)).compile().as_text()
    kernels = text.count(" fusion(") + text.count(" dot(")
    assert kernels <= 60, f"{kernels} kernels in one body's adaptive DOP853 solve (77 before they were written to fuse)"


def test_one_bodys_jacobian_compiles_one_linearisation_and_few_kernels(monkeypatch):
    # A differentiated adaptive solve bounds its steps by the body's modes
    # (`Controller.resolve_modes`), a linearisation of the effects' torque.
    # Applied where each step starts (`Controller.bound`), it is in the
    # program once, not a second time for the first step; with the other
    # rewrites of 2026-11-28 the heavy top's jit(jacfwd) of an adaptive
    # DOP853 solve went from 133 kernels to 99 (121 -> 89 with the suite's
    # quick XLA flags).
    traced = []
    modes = lierk.RigidBodyWithEffects.modes

    def spy(self, *args):
        traced.append(1)
        return modes(self, *args)

    monkeypatch.setattr(lierk.RigidBodyWithEffects, "modes", spy)

    def final(w, tol):
        top = lierk.RigidBodyWithEffects(
            [2.0, 3.0, 4.0], w, effects=(lierk.Gravity(np.array([0.1, 0.0, 0.5]), 1.0, 9.81),)
        )
        return lierk.solve(top, lierk.DOP853(), 1.0, rtol=tol, atol=tol, throw=False).R[-1]

    lowered = jax.jit(jax.jacfwd(final)).lower(jax.numpy.array([1.0, 0.3, 20.0]), jax.numpy.asarray(1e-8))
    assert len(traced) == 1, f"the mode bounds traced {len(traced)} times"
    text = lowered.compile().as_text()
    kernels = text.count(" fusion(") + text.count(" dot(")
    assert kernels <= 105, f"{kernels} kernels in one body's jit(jacfwd) of an adaptive DOP853 solve (133 before)"
