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
