"""What `import jaxland` does to the process: its XLA:CPU options, and a warning when they come
too late to apply."""

import os
import subprocess
import sys


def _python(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    return subprocess.run([sys.executable, "-W", "error", "-c", code], env=env,
                          capture_output=True, text=True, timeout=120)


def test_options_are_set_and_a_late_import_is_warned():
    first = _python("import os, jaxland, jax; jax.numpy.ones(1); print(os.environ['XLA_FLAGS'])")
    assert first.returncode == 0, first.stderr  # imported first: no warning
    for option in ("xla_cpu_small_while_loop_byte_threshold=100000000",
                   "--xla_cpu_use_xnnpack=false"):
        assert option in first.stdout
    late = _python("import jax; jax.numpy.ones(1); import jaxland")
    assert late.returncode != 0 and "imported after JAX started its backend" in late.stderr


def test_batch_fusion_is_opt_in_and_only_before_the_backend_starts():
    """Multi-output fusion speeds batches up but slows landings that save a trajectory (and
    fits) several-fold: off after ``import jaxland``, on through ``jl.use_batch_fusion()``
    (which ``jaxland montecarlo`` and ``jaxland design`` call) before any JAX work, and
    refused (False) after it."""
    default = _python("import os, jaxland; print(os.environ['XLA_FLAGS'])")
    assert "multi_output_fusion" not in default.stdout
    on = _python("import os, jaxland as jl; ok = jl.use_batch_fusion(); import jax; "
                 "jax.numpy.ones(1); print(ok, os.environ['XLA_FLAGS'])")
    assert on.returncode == 0, on.stderr
    assert on.stdout.startswith("True") and ("xla_cpu_small_while_loop_byte_threshold=100000000,"
                                             "xla_cpu_use_multi_output_fusion") in on.stdout
    late = _python("import jaxland as jl, jax; jax.numpy.ones(1); print(jl.use_batch_fusion())")
    assert late.stdout.strip() == "False"
