"""Checks of user-given values, one place for every spec: a value is refused with a
``ConfigError`` naming the field, the value and the rule.

Spec dataclasses declare their TOML keys with ``spec_field(default, toml=..., check=...)``;
``parse_table`` validates a TOML table against those fields (unknown keys refused, each value
checked), so a spec's rules are data beside its fields rather than a chain of branches.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from ._errors import ConfigError

# An integer beyond this is refused: Python's (and TOML's) integers are unbounded, and one
# past float's range overflows where it is converted (below float's max, so that a unit
# conversion of an accepted one stays finite).
INT_MAX = 1e300


def check_int_size(name: str, val):
    """Refuse an integer too large for a float, by ``name``: the checks of typed numbers run
    it before they convert one."""
    if isinstance(val, numbers.Integral) and not isinstance(val, bool) and abs(val) > INT_MAX:
        raise ConfigError(name, val, "is too large for a float")
    return val


def as_number(x):
    """A concrete 0-d numeric array as its Python number; anything else as it is (the checks
    refuse it by name)."""
    if getattr(x, "ndim", None) == 0 and getattr(x, "dtype", None) is not None \
            and x.dtype.kind in "iuf":
        import jax
        import numpy as np

        try:
            return np.asarray(x).item()
        except (TypeError, jax.errors.TracerArrayConversionError,
                jax.errors.ConcretizationTypeError):
            return x
    return x


def _is_number(val) -> bool:
    """A finite number (a flag is none); call ``check_int_size`` first to name a huge int."""
    if isinstance(val, bool) or not isinstance(val, numbers.Real):
        return False
    if isinstance(val, numbers.Integral):
        return abs(val) <= INT_MAX
    return math.isfinite(val)


@dataclass(frozen=True)
class Number:
    """A finite number, optionally an integer, within [lo, hi] (``lo_open``/``hi_open``:
    the bound itself excluded)."""

    integer: bool = False
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def __call__(self, name: str, val):
        check_int_size(name, val)
        if isinstance(val, (bool, np.bool_)):  # shown as the TOML wrote it
            raise ConfigError(name, "true" if val else "false", "must be an integer"
                              if self.integer else "must be a finite number")
        if not _is_number(val):
            raise ConfigError(name, val, "must be a finite number")
        if self.integer and not isinstance(val, numbers.Integral):
            raise ConfigError(name, val, "must be an integer")
        lo, hi = self.lo, self.hi
        if lo is not None and (val < lo or (self.lo_open and val == lo)):
            raise ConfigError(name, val, f"must be {'>' if self.lo_open else '>='} "
                                         f"{_bound_text(lo)}")
        if hi is not None and (val > hi or (self.hi_open and val == hi)):
            raise ConfigError(name, val, f"must be {'<' if self.hi_open else '<='} "
                                         f"{_bound_text(hi)}")
        return val


def _bound_text(x) -> str:
    """A rule's bound as text: short (``:g``) where that is exact, else in full (2147483647,
    not 2.14748e+09, which the value could exceed and still pass)."""
    short = f"{x:g}"
    return short if float(short) == x else (str(int(x)) if float(x).is_integer() else repr(x))


POSITIVE = Number(lo=0.0, lo_open=True)
NON_NEGATIVE = Number(lo=0.0)
FRACTION = Number(lo=0.0, hi=1.0, hi_open=True)  # [0, 1)


@dataclass(frozen=True)
class Choice:
    """One of a fixed set of values. A boolean matches only a boolean: in Python 1 == True, so
    ``in`` alone would take a TOML 1 or 0 for true or false."""

    choices: tuple

    def __call__(self, name: str, val):
        if not any(isinstance(val, bool) == isinstance(c, bool) and val == c
                   for c in self.choices):
            raise ConfigError(name, val, "must be one of " + ", ".join(
                str(c).lower() if isinstance(c, bool) else str(c) for c in self.choices))
        return val


@dataclass(frozen=True)
class Flag:
    """A boolean, TOML's true or false; 1 and 0 are refused (Python takes them as equal to
    True and False, so an integer would pass as a switch)."""

    def __call__(self, name: str, val):
        if not isinstance(val, bool):
            raise ConfigError(name, val, "must be true or false")
        return val


FLAG = Flag()


@dataclass(frozen=True)
class Text:
    """A string (a path, a name)."""

    what: str = "a string"

    def __call__(self, name: str, val):
        if not isinstance(val, str):
            raise ConfigError(name, val, f"must be {self.what}")
        return val


def spec_field(default, *, toml: str, check, doc: str = "", factory=None):
    """A spec dataclass field read from the TOML key ``toml`` and validated by ``check``."""
    meta = dict(toml=toml, check=check, doc=doc)
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def known_keys(prefix: str, table, keys) -> dict:
    """Refuse a table that is no table, or has a key outside ``keys``."""
    if not isinstance(table, dict):
        raise ConfigError(prefix, table, "must be a table")
    unknown = set(table) - set(keys)
    if unknown:
        bad = sorted(unknown)[0]
        raise ConfigError(f"{prefix}.{bad}", table[bad], f"unknown key; known: {', '.join(keys)}")
    return table


def check_field(cls, name: str, label: str, val):
    """``val`` checked by the rule of ``cls``'s field ``name``, refused as ``label`` (the
    flag that overrides the field)."""
    return cls.__dataclass_fields__[name].metadata["check"](label, val)


def parse_table(cls, section: str, table) -> dict:
    """The keyword arguments of ``cls`` that the TOML ``table`` gives, each checked by its
    field's ``check``; unknown keys are refused."""
    fields = {f.metadata["toml"]: f for f in dataclasses.fields(cls) if "toml" in f.metadata}
    known_keys(section, table, list(fields))
    return {fields[key].name: fields[key].metadata["check"](f"{section}.{key}", val)
            for key, val in table.items()}


@contextmanager
def named_as(names: dict):
    """Refusals of the fields in ``names`` (field -> (name, the value as given)) name what the
    user typed and its value, not the field it set: ``solver.dt`` from ``--dt`` is refused as
    ``--dt``, from a spec's ``dt_s`` as ``montecarlo.dt_s``. A field ``names`` leaves out
    keeps its name."""
    try:
        yield
    except ConfigError as err:
        for field, (name, given) in names.items():
            if err.field == field or err.field.startswith(field + "."):
                raise ConfigError(name, given, err.rule) from None
        raise


def at_most(x: float, digits: int = 3) -> str:
    """``x`` to ``digits`` significant digits, rounded down: a value to use below a limit (the
    euler limit 1.33676e-4 s, rounded to 0.000134 s, refuses that step)."""
    if not (math.isfinite(x) and x > 0.0):
        return f"{x:.{digits}g}"
    unit = 10.0 ** (math.floor(math.log10(x)) - digits + 1)
    return f"{math.floor(x / unit) * unit:.{digits}g}"
