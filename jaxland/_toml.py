"""Reading TOML files with errors that name the file and what is wrong."""

from __future__ import annotations

import tomllib
from pathlib import Path

from ._errors import ConfigError


def read_toml(path, what: str) -> dict:
    """Parse the TOML file ``path``; refuse a missing file or bad TOML naming ``what``."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(what, str(path), "file does not exist") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(what, str(path), f"is not valid TOML: {err}") from None
