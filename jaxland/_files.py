"""Writing outputs so that nothing is ever half-written.

One file: ``atomic_write`` writes a temporary file beside the target and ``os.replace``-s it.
A folder of outputs: ``staged(out)`` gives a staging folder inside ``out``; everything written
there is moved into place only when the block finishes without an error (``publish``).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def _replace(tmp: str, path: Path) -> None:
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
    os.replace(tmp, path)


def atomic_write(path, writer, suffix: str = ".tmp") -> Path:
    """Write ``path`` through ``writer(tmp_path)`` on a temporary file beside it, then move it
    into place; on any error the temporary file is removed and ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix)
    os.close(fd)
    try:
        writer(tmp)
        _replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path, text: str) -> Path:
    def write(tmp):
        with open(tmp, "w", newline="") as fh:
            fh.write(text)
    return atomic_write(path, write)


def atomic_savefig(fig, path, dpi: int = 110) -> Path:
    return atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi), suffix=".tmp.png")


def publish(staging: Path, out: Path) -> list[Path]:
    """Move every file under ``staging`` to the same relative path under ``out``."""
    written = []
    for path in sorted(Path(staging).rglob("*")):
        if path.is_file():
            dest = Path(out) / path.relative_to(staging)
            dest.parent.mkdir(parents=True, exist_ok=True)
            path.replace(dest)
            written.append(dest)
    return written


@contextmanager
def staged(out) -> Iterator[Path]:
    """``with staged(out) as staging:`` write into ``staging``; on success the files move into
    ``out`` (created if needed), on an error nothing reaches it. The staging folder is always
    removed."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=out, prefix=".staging-"))
    try:
        yield staging
        publish(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
