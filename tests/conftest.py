"""Tests run in float64 unless a test says otherwise (library code never
enables it itself)."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


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
