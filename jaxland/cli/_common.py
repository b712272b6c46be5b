"""What every subcommand shares: output folders, CPU devices, value formatting."""

from __future__ import annotations

import os
from pathlib import Path

from .._checks import Number
from .._errors import ConfigError
from .._files import check_out

HOST_DEVICES_FLAG = "xla_force_host_platform_device_count"


DEVICES_MAX = 256  # --devices beyond the machine's cores: at most this many


def use_cpu_cores(devices: int | None) -> int | None:
    """Split this process's CPU into ``devices`` JAX devices, before JAX starts its backend
    (default: one per core this process may run on). A batch of landings compiles into one
    single-threaded loop (docs/performance.md), so a Monte Carlo chunk sharded over several
    CPU devices runs on as many cores. Left alone, when no count is given, if ``XLA_FLAGS``
    sets ``--xla_force_host_platform_device_count`` or JAX already runs in this process (the
    CLI called from Python). Returns the count set (None: left alone). Only the CPU platform
    is split; a GPU run uses its GPUs."""
    import jax

    given = devices is not None
    if given:
        Number(integer=True, lo=1)("--devices", devices)
        # A CPU device is a thread at least (10^5 of them exhaust the system). More devices
        # than cores gain no speed, but repeat a run made on more cores: a design's path
        # depends on how its scenes are split (docs/design.md)
        most = max(os.cpu_count() or 1, DEVICES_MAX)
        if devices > most:
            raise ConfigError("--devices", devices, f"must be <= {most}: a CPU device is a "
                              "thread at least, and more devices than this machine's "
                              f"{os.cpu_count() or 1} cores gain no speed")
    if not given:
        if HOST_DEVICES_FLAG in os.environ.get("XLA_FLAGS", ""):
            return None
        devices = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
            os.cpu_count() or 1)
    try:
        jax.config.update("jax_num_cpu_devices", devices)
    except RuntimeError:  # the backend has started: its devices are fixed
        if given:
            raise ConfigError("--devices", devices, "JAX already runs in this process: set "
                              "jax_num_cpu_devices before any JAX work") from None
        return None
    return devices


CACHE_ENV = "JAXLAND_CACHE_DIR"


def use_compilation_cache() -> str | None:
    """Keep compiled programs on disk between runs of the command (JAX's persistent compilation
    cache), so that a second ``jaxland design`` or ``montecarlo`` of the same shapes skips its
    compilation: in ``$JAXLAND_CACHE_DIR``, default ``$XDG_CACHE_HOME/jaxland/xla`` (else
    ``~/.cache/jaxland/xla``); ``JAXLAND_CACHE_DIR=`` (empty) turns it off, and a
    ``JAX_COMPILATION_CACHE_DIR`` you set is JAX's own and left alone. Returns the folder
    used (None: none set here)."""
    if "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return None
    folder = os.environ.get(CACHE_ENV)
    if folder is None:
        base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        folder = str(Path(base) / "jaxland" / "xla")
    if not folder:
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", folder)
    return folder


def out_dir(path, inputs=(), command: str | None = None) -> Path:
    """The output folder ``--out``, checked before any work against the run's ``inputs``
    and ``command`` (``jaxland._files.check_out``)."""
    return check_out(path, inputs, command)


def fmt(v, scale=1.0, unit="", nd=4):
    """A value, or a per-leg list of values, scaled and with its unit."""
    if v is None:
        return "-"
    if isinstance(v, list):
        return (" / ".join(f"{x * scale:.{nd}g}" for x in v) + f" {unit}  (per leg)").strip()
    return f"{v * scale:.{nd}g} {unit}".strip()

