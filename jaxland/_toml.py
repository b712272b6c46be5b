"""Reading input files with errors that name the file and what is wrong, and writing TOML values
that read back exactly."""

from __future__ import annotations

import json
import numbers
import tomllib
from pathlib import Path

import numpy as np

from ._errors import ConfigError


def read_text(path, what: str) -> str:
    """The UTF-8 text of the file ``path``, without the byte-order mark Windows editors and
    spreadsheets save first (no TOML or CSV reader wants it); refuse a missing file, a folder,
    a path below a file, an unreadable file or one that is not UTF-8 text, naming ``what``."""
    path = Path(path)
    try:
        return path.read_bytes().decode("utf-8").removeprefix("\ufeff")
    except FileNotFoundError:
        raise ConfigError(what, str(path), "file does not exist") from None
    except IsADirectoryError:
        raise ConfigError(what, str(path), "is a folder, not a file") from None
    except NotADirectoryError:
        raise ConfigError(what, str(path), "lies below a file, not in a folder") from None
    except PermissionError:
        raise ConfigError(what, str(path), "cannot be read (permission denied)") from None
    except UnicodeDecodeError as err:
        raise ConfigError(what, str(path), f"is not UTF-8 text (byte {err.start}: "
                          f"{err.object[err.start:err.start + 1]!r})") from None


def read_toml(path, what: str) -> dict:
    """Parse the TOML file ``path`` (``read_text``'s refusals, and bad TOML), naming ``what``."""
    text = read_text(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(what, str(path), f"is not valid TOML: {err}") from None


def toml_value(v) -> str:
    """``v`` (a flag, text, number, or a list of them) as TOML that reads back to the same
    value: floats by ``repr``, the shortest text that round-trips."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, numbers.Integral) or (isinstance(v, np.ndarray) and v.ndim == 0
                                           and np.issubdtype(v.dtype, np.integer)):
        return repr(int(v))
    # any other real (a numpy float32, a 0-d array): its value as a float64, never truncated
    return repr(float(v))
