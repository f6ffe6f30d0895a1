"""Tests run in float64 unless a test says otherwise (library code never
enables it itself).

Compiled programs that took at least half a second to build are kept on disk in
``.jax-cache/`` (or ``$JAX_COMPILATION_CACHE_DIR``): most of the suite's time is
compilation, and the modules, each in a process of its own (``make test``),
build many of the same solves; a second run reuses all of them."""

import os
from pathlib import Path

# Set in the environment before jax is imported, so that the command-line
# runs the tests start as subprocesses share the cache too.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parent.parent / ".jax-cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
# (Again through the config, in case a plugin imported jax first.)
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update(
    "jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
)


import gc  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import pytest  # noqa: E402

import lierk.app.compilations  # noqa: E402

# Python's cyclic collector, tuned for a process that traces JAX programs:
# what is loaded by now (jax, lierk, pytest) is never garbage, so frozen it
# is not scanned again, and a young generation of 100,000 objects (700 by
# default) is not collected over and over while a trace allocates its
# long-lived equations.  test_adjoint alone: 52-57 s -> 47 s (one run each),
# the same peak memory (1.18 GB).  lierk itself holds the collector off while it traces
# (lierk._own_programs).
gc.freeze()
gc.set_threshold(100_000, 20, 100)

# Programs each module may build (compiled, or loaded from the persistent
# cache: the count does not depend on the cache), with headroom; compile time
# is reported beside it, never asserted (machines are shared).  A module over
# its budget fails: a test that stopped sharing programs, or a change that
# made a solve build more of them, shows up here.  Regenerate the file with
# ``python tests/compile_budget.py`` after a deliberate change.
_BUDGET = json.loads((Path(__file__).parent / "compile_budget.json").read_text())
_SEEN: list[tuple[str, int, float, float]] = []


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs(request):
    """Count the module's compilations against its budget, then drop every
    compiled program when other modules run in the same process.  The suite
    compiles hundreds of solves (the splittings' elliptic-function drift is a
    large program); kept for the whole session they grew the process past
    5 GB at a fifth of the suite, and a full run was killed mid-compile.  A
    process with one module (``make test``) ends instead: clearing cost a
    second or more a module."""
    name = Path(str(request.path)).stem
    start = time.perf_counter()
    with lierk.app.compilations.counting() as seen:
        yield
    _SEEN.append((name, seen.count, seen.seconds, time.perf_counter() - start))
    if len({item.path for item in request.session.items}) > 1:
        jax.clear_caches()
        gc.collect()
    budget = _BUDGET.get(name)
    if budget is not None and seen.count > budget:
        pytest.fail(f"{name} built {seen.count} programs, over its budget of {budget} (tests/compile_budget.json)")


def pytest_terminal_summary(terminalreporter):
    """One line per module: programs built (and the budget), compile seconds
    and wall seconds; also appended to ``.test-logs/compilations.tsv`` when
    that folder exists (``make test``)."""
    log = Path(__file__).resolve().parent.parent / ".test-logs"
    for name, count, seconds, wall in _SEEN:
        budget = _BUDGET.get(name, "none")
        terminalreporter.write_line(
            f"compilations: {name}: {count} programs (budget {budget}), {seconds:.1f} s of {wall:.1f} s compiling"
        )
        if log.is_dir():
            with open(log / "compilations.tsv", "a") as f:
                f.write(f"{name}\t{count}\t{seconds:.2f}\t{wall:.2f}\n")
