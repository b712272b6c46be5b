"""What every subcommand shares: output folders, value formatting."""

from __future__ import annotations

from pathlib import Path

from .._files import check_out


def out_dir(path) -> Path:
    """The output folder ``--out``, checked before any work (``jaxland._files.check_out``)."""
    return check_out(path)


def fmt(v, scale=1.0, unit="", nd=4):
    """A value, or a per-leg list of values, scaled and with its unit."""
    if v is None:
        return "-"
    if isinstance(v, list):
        return (" / ".join(f"{x * scale:.{nd}g}" for x in v) + f" {unit}  (per leg)").strip()
    return f"{v * scale:.{nd}g} {unit}".strip()
