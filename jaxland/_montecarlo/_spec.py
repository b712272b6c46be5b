"""The Monte Carlo spec: which inputs are dispersed and how, which are fixed, the run's settings."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp

from .._errors import ConfigError
from .._scene import SCENE_FIELDS
from .._solvers import FIXED_STEP_METHODS
from .._toml import read_toml

# Dispersible quantities: TOML key -> (Scene field, TOML->SI factor, component count or None).
_SCENE_KEYS = {v[4]: (k, v[5], None) for k, v in SCENE_FIELDS.items()}
DISPERSIBLE = {
    **_SCENE_KEYS,
    "friction": ("friction", 1.0, None),
    "mass_scale": ("mass_scale", 1.0, None),
    "plateau_scale": ("plateau_scale", 1.0, "legs"),
    "com_offset_x_m": ("com_offset", 1.0, 0),
    "com_offset_y_m": ("com_offset", 1.0, 1),
    "com_offset_z_m": ("com_offset", 1.0, 2),
}
_EXTRA_LIMITS = {"friction": (0.0, 2.0), "mass_scale": (0.5, 2.0), "plateau_scale": (0.2, 5.0),
                 "com_offset_x_m": (-0.3, 0.3), "com_offset_y_m": (-0.3, 0.3),
                 "com_offset_z_m": (-0.3, 0.3)}


def envelope(key: str) -> tuple[float, float]:
    """The scene envelope of a dispersible input, in its TOML units."""
    if key in _EXTRA_LIMITS:
        return _EXTRA_LIMITS[key]
    field_name, to_si, _ = DISPERSIBLE[key]
    _, _, lo, hi, _, _ = SCENE_FIELDS[field_name]
    return lo / to_si, hi / to_si


# Dispersions that keep a symmetric vertical drop symmetric (the quarter model suffices).
_SYMMETRIC_KEYS = {"drop_height_m", "sink_speed_mps", "yaw_deg", "friction", "mass_scale"}


@dataclass(frozen=True)
class Distribution:
    """One input's distribution, in the TOML key's units.

    ``normal(mean, std)``, ``uniform(low, high)``, ``truncnormal(mean, std, low, high)`` (a
    normal conditioned on [low, high]) or ``constant(value)``."""

    kind: str
    mean: float = 0.0
    std: float = 0.0
    low: float = -math.inf
    high: float = math.inf

    @classmethod
    def from_dict(cls, name: str, d: dict) -> Distribution:
        kind = d.get("dist")
        need = {"normal": ("mean", "std"), "uniform": ("low", "high"),
                "truncnormal": ("mean", "std", "low", "high"), "constant": ("value",)}
        if kind not in need:
            raise ConfigError(f"dispersion.{name}.dist", kind,
                              f"must be one of {', '.join(need)}")
        unknown = set(d) - {"dist", *need[kind]}
        if unknown:
            raise ConfigError(f"dispersion.{name}.{sorted(unknown)[0]}", "?",
                              f"not a parameter of a {kind} distribution ({', '.join(need[kind])})")
        vals = {}
        for key in need[kind]:
            v = d.get(key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"dispersion.{name}.{key}", v, "must be a finite number")
            vals[key] = float(v)
        if kind == "constant":
            return cls("constant", mean=vals["value"])
        if kind in ("normal", "truncnormal") and not vals["std"] > 0:
            raise ConfigError(f"dispersion.{name}.std", vals["std"], "must be > 0")
        if kind in ("uniform", "truncnormal") and not vals["low"] < vals["high"]:
            raise ConfigError(f"dispersion.{name}.high", vals["high"],
                              f"must exceed low = {vals['low']}")
        return cls(kind, **{k: v for k, v in vals.items()})

    def sample(self, key, shape=()):
        if self.kind == "constant":
            return jnp.full(shape, self.mean)
        if self.kind == "uniform":
            return self.low + (self.high - self.low) * jax.random.uniform(key, shape)
        if self.kind == "normal":
            return self.mean + self.std * jax.random.normal(key, shape)
        lo, hi = (self.low - self.mean) / self.std, (self.high - self.mean) / self.std
        return self.mean + self.std * jax.random.truncated_normal(key, lo, hi, shape)


@dataclass
class MonteCarloSpec:
    """What to disperse (``dispersion``: TOML key -> Distribution), what to fix (``fixed``:
    TOML key -> value), how many samples, the seed and the integration settings."""

    dispersion: dict
    fixed: dict = field(default_factory=dict)
    n: int = 1000
    seed: int = 0
    dt: float = 1e-5
    t_end: float = 1.0
    model: str = "auto"
    method: str = "euler"  # a fixed-step integrator (FIXED_STEP_METHODS)

    def __post_init__(self):
        for key in [*self.dispersion, *self.fixed]:
            if key not in DISPERSIBLE:
                raise ConfigError(f"dispersion.{key}", "?",
                                  "unknown input; known: " + ", ".join(sorted(DISPERSIBLE)))
        for key, val in self.fixed.items():
            vals = val if isinstance(val, list) and DISPERSIBLE[key][2] == "legs" else [val]
            if not vals or any(isinstance(v, bool) or not isinstance(v, (int, float))
                               or not math.isfinite(v) for v in vals):
                raise ConfigError(f"fixed.{key}", val, "must be a finite number"
                                  + (" or a list of one per leg" if DISPERSIBLE[key][2] == "legs"
                                     else ""))
        for key, dist in self.dispersion.items():
            lo, hi = envelope(key)
            support = ((dist.mean, dist.mean) if dist.kind == "constant" else
                       (dist.low, dist.high) if dist.kind != "normal" else (-math.inf, math.inf))
            if support[1] < lo or support[0] > hi:
                raise ConfigError(f"dispersion.{key}", f"[{support[0]}, {support[1]}]",
                                  f"lies entirely outside the scene envelope [{lo:.4g}, {hi:.4g}]")
        both = set(self.dispersion) & set(self.fixed)
        if both:
            raise ConfigError(f"fixed.{sorted(both)[0]}", "?", "is also dispersed; give one")
        if isinstance(self.n, bool) or not isinstance(self.n, int) or self.n < 1:
            raise ConfigError("montecarlo.n", self.n, "must be an integer >= 1")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or \
                not 0 <= self.seed < 2**31:
            raise ConfigError("montecarlo.seed", self.seed, "must be an integer in [0, 2^31)")
        if self.model not in ("auto", "quarter", "full"):
            raise ConfigError("montecarlo.model", self.model, "must be auto, quarter or full")
        if self.method not in FIXED_STEP_METHODS:
            raise ConfigError("montecarlo.method", self.method,
                              f"must be one of {', '.join(FIXED_STEP_METHODS)} (fixed-step "
                              "methods batch without waiting for the slowest sample)")

    def smallest_model(self) -> str:
        """The quarter model if every dispersed or fixed input keeps the drop symmetric."""
        keys = set(self.dispersion) | {k for k, v in self.fixed.items()
                                       if not (isinstance(v, (int, float)) and v == 0.0)}
        return "quarter" if keys <= _SYMMETRIC_KEYS else "full"

    def resolved_model(self) -> str:
        model = self.smallest_model() if self.model == "auto" else self.model
        if model == "quarter" and self.smallest_model() == "full":
            raise ConfigError("montecarlo.model", "quarter", "these dispersions break the "
                              "symmetry of a vertical drop; the full model is needed")
        return model


def load_montecarlo_spec(path) -> MonteCarloSpec:
    """Read a Monte Carlo spec TOML: ``[montecarlo]`` (n, seed, dt_s, t_end_s, model, method),
    ``[dispersion.<input>]`` tables and an optional ``[fixed]`` table (see the README)."""
    data = read_toml(path, "spec")
    unknown = set(data) - {"montecarlo", "dispersion", "fixed"}
    if unknown:
        raise ConfigError(sorted(unknown)[0], "<table>",
                          "unknown section; known: montecarlo, dispersion, fixed")
    for section in ("montecarlo", "dispersion", "fixed"):
        if not isinstance(data.get(section, {}), dict):
            raise ConfigError(section, data[section], f"must be a table ([{section}])")
    mc = dict(data.get("montecarlo", {}))
    keys = {"n": "n", "seed": "seed", "dt_s": "dt", "t_end_s": "t_end", "model": "model",
            "method": "method"}
    bad = set(mc) - set(keys)
    if bad:
        raise ConfigError(f"montecarlo.{sorted(bad)[0]}", "?",
                          f"unknown key; known: {', '.join(keys)}")
    disp = {}
    for name, table in data.get("dispersion", {}).items():
        if not isinstance(table, dict):
            raise ConfigError(f"dispersion.{name}", table, "must be a table with dist = ...")
        disp[name] = Distribution.from_dict(name, table)
    return MonteCarloSpec(dispersion=disp, fixed=dict(data.get("fixed", {})),
                          **{keys[k]: v for k, v in mc.items()})
