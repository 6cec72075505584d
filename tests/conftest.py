"""Test set-up: float64 and strict dtype promotion, as in the JAX libraries we learn from."""

import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
# The command line keeps compiled code in ~/.cache; tests that want it name a temporary folder.
os.environ.setdefault("SINKJAX_CACHE_DIR", "off")

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "standard")
