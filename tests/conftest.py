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
jax.config.update("jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))


import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop every compiled program after each test module.  The suite compiles
    hundreds of solves (the splittings' elliptic-function drift is a large
    program); kept for the whole session they grew the process past 5 GB at a
    fifth of the suite, and a full run was killed mid-compile."""
    yield
    jax.clear_caches()
    gc.collect()
