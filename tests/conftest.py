"""Tests run in float64 unless a test says otherwise (library code never
enables it itself)."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
