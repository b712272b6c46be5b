"""Atomic file output (jaxland's: write a temporary file beside the target, then replace)."""

from __future__ import annotations

from jaxland import atomic_savefig, atomic_write_text

__all__ = ["atomic_write_text", "atomic_savefig"]
