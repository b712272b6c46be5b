"""Strict JAX test configuration (as diffrax/equinox do) and shared compiled functions."""

import atexit
import os
import shutil
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

# One persistent compilation cache per test session: a fresh temporary folder (removed at exit),
# also used by the pytest-xdist workers (`make test` runs two) and the Python processes the tests
# start (the CLI, the README examples, benchmark scripts), which compile landings that other
# tests compiled before them. XLA compilation is
# most of the suite's time. Fresh each session, so every run compiles what a fresh machine does;
# a cache folder set by the caller is used as it is. Every compilation is cached, the short ones
# too: each CLI and script process compiles the same few dozen small programs (0.01-0.4 s each),
# and reading them back makes test_readme.py and test_cli.py ~7 % faster (in-process tests are
# unchanged).
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="jaxland-tests-xla-cache-")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" in os.environ:
    jax.config.update("jax_persistent_cache_min_compile_time_secs",
                      float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))

import jaxland  # noqa: E402,F401  (float64 on import)
