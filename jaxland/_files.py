"""Writing outputs so that nothing is ever half-written.

One file: ``atomic_write`` writes a temporary file beside the target and ``os.replace``-s it.
A folder of outputs: ``staged(out)`` gives a staging folder beside ``out``; when the block
finishes without an error the staging folder replaces ``out`` as a whole.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import shutil
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np


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


def json_text(obj) -> str:
    """``obj`` as strict JSON text (indented, with a final newline): numpy and JAX values as
    numbers and lists, a non-finite number as null (JSON has no NaN or infinity, and strict
    readers refuse Python's NaN and Infinity)."""
    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, (np.ndarray, np.generic)) or hasattr(x, "__array__"):
            return clean(np.asarray(x).tolist())
        if isinstance(x, float) and not math.isfinite(x):
            return None
        return x

    return json.dumps(clean(obj), indent=2, allow_nan=False) + "\n"


def run_environment() -> dict:
    """What an output records of the software it ran on: the jaxland, JAX and optax versions,
    JAX's backend and the XLA flags (call it after the run: it starts JAX's backend)."""
    import jax
    import optax

    from . import __version__

    return dict(jaxland=__version__, jax=jax.__version__, optax=optax.__version__,
                backend=jax.default_backend(), xla_flags=os.environ.get("XLA_FLAGS", ""))


def file_record(path) -> dict:
    """A file an output was made from: its path as given, its absolute path and its SHA-256
    (which tells whether the file at that path is still the one used)."""
    import hashlib

    path = Path(path)
    return dict(path=str(path), absolute=str(path.resolve()),
                sha256=hashlib.sha256(path.read_bytes()).hexdigest())


def atomic_write_text(path, text: str) -> Path:
    def write(tmp):
        with open(tmp, "w", newline="") as fh:
            fh.write(text)
    return atomic_write(path, write)


def flat_columns(*groups: dict) -> dict:
    """One column per quantity, in order: a per-leg (n_samples, n_legs) array becomes
    ``leg0_<name>``, ``leg1_<name>``, ..."""
    cols = {}
    for group in groups:
        for name, arr in group.items():
            arr = np.asarray(arr)
            if arr.ndim == 1:
                cols[name] = arr
            else:
                for i in range(arr.shape[1]):
                    cols[f"leg{i}_{name}"] = arr[:, i]
    return cols


def csv_text(columns: dict, *, digits: int = 9, comments=()) -> str:
    """CSV text: ``# comment`` lines, a header of the column names (units in the names), then
    one row per sample with ``digits`` significant digits."""
    data = np.column_stack([np.asarray(v, dtype=float) for v in columns.values()])
    lines = [f"# {c}" for c in comments] + [",".join(columns)]
    lines += [",".join(f"{x:.{digits}g}" for x in row) for row in data]
    return "\n".join(lines) + "\n"


def atomic_write_csv(path, columns: dict, **kw) -> Path:
    """``csv_text`` of ``columns`` written atomically (the one CSV writer)."""
    return atomic_write_text(path, csv_text(columns, **kw))


def atomic_savefig(fig, path, dpi: int = 110) -> Path:
    """Render a matplotlib figure to the PNG ``path`` atomically (the one figure writer)."""
    def write(tmp):
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png", dpi=dpi)
    return atomic_write(path, write, suffix=".tmp.png")


MARKER = ".jaxland-output.json"  # in every output folder jaxland publishes
# files a desktop's file manager writes into any folder it shows, and writes again: replacing
# an output folder may drop them, so they never block a run into it
DESKTOP_FILES = frozenset({".DS_Store", "Thumbs.db", "desktop.ini", ".directory"})
# set by ``interrupt_handler``: a Ctrl-C that landed where Python swallows the exception (a
# weak reference's callback, a finaliser) still stops the run before it publishes
_INTERRUPTED = threading.Event()


def interrupt_handler(signum, frame):
    """SIGINT or SIGTERM: remember the interrupt and its signal (``staged`` then publishes
    nothing, and the command exits 128 + the signal's number), then raise KeyboardInterrupt as
    Python's own SIGINT handler does."""
    _INTERRUPTED.signum = signum
    _INTERRUPTED.set()
    raise KeyboardInterrupt


def quiet_unraisable(hook):
    """``sys.unraisablehook`` that drops the KeyboardInterrupt of a remembered interrupt (one
    that landed in a callback Python cannot raise from: ``staged`` still publishes nothing, and
    the command says it was interrupted, in one line) and passes anything else to ``hook``."""
    def quiet(unraisable):
        if not (_INTERRUPTED.is_set()
                and isinstance(unraisable.exc_value, KeyboardInterrupt)):
            hook(unraisable)
    return quiet


def interrupt_signal(default: int) -> int:
    """The number of the signal that interrupted the command (``default`` where none was
    recorded: a KeyboardInterrupt raised otherwise)."""
    return getattr(_INTERRUPTED, "signum", None) or default


def clear_interrupt() -> None:
    """Forget an earlier interrupt (a command's start)."""
    _INTERRUPTED.clear()
    _INTERRUPTED.signum = None


def check_out(out, inputs=(), command: str | None = None) -> Path:
    """Refuse an output folder that jaxland may not replace: a file, a symbolic link, a path
    below a file, the current folder or one holding it, a folder holding one of the run's
    ``inputs`` (paths; None skipped), a non-empty folder without jaxland's marker (someone
    else's files, hidden ones included; a desktop's ``DESKTOP_FILES`` aside), or the folder of
    another command than ``command`` (a prediction replacing a fit would delete its report and
    its fitted vehicle). Call it before any long computation."""
    from ._errors import ConfigError

    out = Path(out)
    if out.is_symlink():  # the folder's replacement would replace the link, not its target
        raise ConfigError("--out", str(out), f"is a symbolic link (to {os.readlink(out)}): "
                          "give the folder itself, since the whole folder is replaced")
    for p in (out, *out.parents):
        if p.exists():
            if not p.is_dir():
                raise ConfigError("--out", str(out), "exists and is not a folder" if p == out
                                  else f"lies below {p}, which is a file")
            break
    here, where = Path.cwd().resolve(), out.resolve()
    if where == here or where in here.parents:
        raise ConfigError("--out", str(out), "is the current folder or holds it: give a "
                          "subfolder, since the whole folder is replaced")
    for path in inputs:
        if path is not None and where in Path(path).resolve().parents:
            raise ConfigError("--out", str(out), f"holds {path}, an input of this run, and "
                              "would be replaced as a whole: give another folder")
    _check_writable(out, out.parent if p == out else p)  # the staging folder's place
    for p in where.parents:  # a run into that folder would replace this one with it
        if (p / MARKER).is_file():
            raise ConfigError("--out", str(out), f"lies inside {p}, a jaxland output folder "
                              "that its next run replaces as a whole: give a folder outside it")
    if out.is_dir() and not (out / MARKER).exists() and any(
            p.name not in DESKTOP_FILES for p in out.iterdir()):
        raise ConfigError("--out", str(out), "is a folder jaxland did not write (no "
                          f"{MARKER}): give a new or empty folder, its files would be replaced")
    if out.is_dir() and command is not None and (out / MARKER).is_file():
        try:
            other = json.loads((out / MARKER).read_text()).get("command")
        except (OSError, ValueError, AttributeError):
            other = None
        if other is not None and other != command:
            raise ConfigError("--out", str(out), f"holds the output of `jaxland {other}`, which "
                              f"this `jaxland {command}` run would replace as a whole: give "
                              "another folder (or remove that one first)")
    if out.is_dir():
        foreign = _not_written_by_jaxland(out)
        if foreign:
            more = f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else ""
            raise ConfigError("--out", str(out), f"holds {foreign[0]}{more}, which its jaxland "
                              "run did not write: move it out first, since the whole folder "
                              "is replaced")
    return out


def _written(folder: Path) -> list[str]:
    """Every file below ``folder``, as paths relative to it ('/'-separated), sorted; symbolic
    links are listed, not followed."""
    out = []
    for root, dirs, files in os.walk(folder):
        rel = Path(root).relative_to(folder)
        out += [(rel / f).as_posix() for f in files]
        out += [(rel / d).as_posix() for d in dirs if (Path(root) / d).is_symlink()]
    return sorted(out)


def _not_written_by_jaxland(out: Path) -> list[str]:
    """The files in ``out`` (a folder with jaxland's ``MARKER``) that its run did not write:
    those missing from the marker's list of files (markers without one: another jaxland
    output's marker in a subfolder), a desktop's ``DESKTOP_FILES`` aside."""
    try:
        listed = json.loads((out / MARKER).read_text()).get("files")
    except (OSError, ValueError, AttributeError):
        listed = None
    present = _written(out)
    if listed is None:
        return [f for f in present if f.endswith("/" + MARKER)]
    keep = set(listed) | {MARKER}
    return [f for f in present if f not in keep and Path(f).name not in DESKTOP_FILES]


def _check_writable(out: Path, folder: Path) -> None:
    """Refuse ``out`` when nothing can be created in ``folder``, where its staging folder goes
    (``staged``: beside ``out``, or the nearest folder above that exists): tried with an empty
    folder, removed at once, since permission bits say nothing for root or for special file
    systems."""
    from ._errors import ConfigError

    try:
        os.rmdir(tempfile.mkdtemp(prefix=".jaxland-probe-", dir=folder))
    except OSError as err:
        raise ConfigError("--out", str(out), f"cannot be written: creating a folder in {folder} "
                          f"fails ({err.strerror})") from None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _clean_debris(out: Path) -> None:
    """Remove staging and old folders beside ``out`` left by runs that were killed."""
    for p in out.parent.glob(f".{out.name}.*-*"):
        parts = p.name[len(out.name) + 2:].split("-")
        if (p.is_dir() and len(parts) == 3 and parts[0] in ("staging", "old")
                and parts[1].isdigit() and not _alive(int(parts[1]))):
            shutil.rmtree(p, ignore_errors=True)


@contextmanager
def staged(out, command: str | None = None) -> Iterator[Path]:
    """``with staged(out) as staging:`` write the outputs into ``staging``; on success the
    folder ``out`` is replaced by it as a whole (one consistent set: no file of an earlier run
    survives), marked as jaxland's (``MARKER``: the command and the jaxland version); on an
    error ``out`` is untouched. Staging and old folders are siblings of ``out``; those of
    killed runs are removed on the next run."""
    from . import __version__

    out = check_out(out, command=command)
    out.parent.mkdir(parents=True, exist_ok=True)
    _clean_debris(out)
    tag = f"{os.getpid()}-{secrets.token_hex(3)}"
    staging = out.parent / f".{out.name}.staging-{tag}"
    staging.mkdir()
    try:
        yield staging
        if _INTERRUPTED.is_set():  # interrupted, and the exception was swallowed on its way
            raise KeyboardInterrupt
        (staging / MARKER).write_text(json.dumps(
            dict(command=command, jaxland_version=__version__, files=_written(staging)),
            indent=2) + "\n")
        old = out.parent / f".{out.name}.old-{tag}"
        if out.exists():
            out.replace(old)
        staging.replace(out)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
