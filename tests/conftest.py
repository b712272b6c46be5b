"""Strict JAX test configuration (as diffrax/equinox do) and shared compiled functions."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

import jaxland  # noqa: E402,F401  (float64 on import)
