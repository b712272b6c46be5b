"""Writing outputs all at once: commands write into a staging folder, then ``publish`` moves
every file into place, so a failed run leaves nothing half-written in the output folder."""

from __future__ import annotations

from pathlib import Path


def publish(staging: Path, out: Path) -> None:
    """Move every file under ``staging`` to the same relative path under ``out``."""
    for path in sorted(Path(staging).rglob("*")):
        if path.is_file():
            dest = Path(out) / path.relative_to(staging)
            dest.parent.mkdir(parents=True, exist_ok=True)
            path.replace(dest)
