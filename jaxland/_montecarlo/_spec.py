"""The Monte Carlo spec: which inputs are dispersed and how, which are fixed, the run's settings."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import (
    FLAG,
    NON_NEGATIVE,
    POSITIVE,
    Choice,
    Number,
    check_int_size,
    parse_table,
    spec_field,
)
from .._errors import ConfigError
from .._scene import OPTIONAL_LIMITS, SCENE_FIELDS, ZERO_IN_A_SYMMETRIC_DROP, Scene
from .._solvers import FIXED_STEP_METHODS, check_spec_steps
from .._toml import read_toml, toml_value


class Dispersible(NamedTuple):
    field: str  # the Scene field it sets
    to_si: float  # TOML -> SI factor
    component: int | str | None  # vector component, "legs" (one per leg), or None (scalar)


# Dispersible quantities by TOML key.
DISPERSIBLE = {
    **{v.toml: Dispersible(k, v.to_si, None) for k, v in SCENE_FIELDS.items()},
    "friction": Dispersible("friction", 1.0, None),
    "mass_scale": Dispersible("mass_scale", 1.0, None),
    "plateau_scale": Dispersible("plateau_scale", 1.0, "legs"),
    "com_offset_x_m": Dispersible("com_offset", 1.0, 0),
    "com_offset_y_m": Dispersible("com_offset", 1.0, 1),
    "com_offset_z_m": Dispersible("com_offset", 1.0, 2),
}
_SCENE_DEFAULTS = {f.name: f.default for f in dataclasses.fields(Scene)}
# their envelope in TOML units (the scene's own limits; com_offset per component)
_EXTRA_LIMITS = {
    **{k: OPTIONAL_LIMITS[k] for k in ("friction", "mass_scale", "plateau_scale")},
    **{f"com_offset_{a}_m": OPTIONAL_LIMITS["com_offset"] for a in "xyz"},
}


def period(key: str) -> float | None:
    """The period of a dispersible input in its TOML units (360 for an azimuth in degrees), or
    None for an input that does not repeat."""
    f = SCENE_FIELDS.get(DISPERSIBLE[key].field)
    return 2.0 * math.pi / DISPERSIBLE[key].to_si if f is not None and f.circular else None


def envelope(key: str) -> tuple[float, float]:
    """The scene envelope of a dispersible input, in its TOML units."""
    if key in _EXTRA_LIMITS:
        return _EXTRA_LIMITS[key]
    field_name, to_si, _ = DISPERSIBLE[key]
    f = SCENE_FIELDS[field_name]
    return _as_written(f.lo / to_si), _as_written(f.hi / to_si)


def _as_written(x: float) -> float:
    """A limit converted back from SI as the docs write it: 30 deg, not the
    29.999999999999996 that 30 deg in radians gives back, which refused 30 itself."""
    short = float(f"{x:.12g}")
    return short if abs(short - x) <= 1e-14 * abs(x) else x


def _keeps_symmetry(key: str, value) -> bool:
    """Whether a dispersed (a ``Distribution``) or fixed input keeps a vertical drop
    symmetric, by the scenes' rule (``_scene.ZERO_IN_A_SYMMETRIC_DROP``, and one plateau
    scale on every leg); every other input (height, sink speed, yaw, heading and slope
    direction without a speed or slope, friction, mass) keeps it."""
    field = DISPERSIBLE[key].field
    if isinstance(value, Distribution):
        if value.kind != "constant":  # a per-leg input is drawn leg by leg
            return field not in ZERO_IN_A_SYMMETRIC_DROP and field != "plateau_scale"
        value = value.mean
    vals = np.ravel(np.asarray(value, dtype=float))
    if field in ZERO_IN_A_SYMMETRIC_DROP:
        return bool(np.all(vals == 0.0))
    return field != "plateau_scale" or bool(np.all(vals == vals[0]))


# Least probability of the normal inside a truncnormal's bounds: far in a tail the sampler
# returns the bound itself for every sample.
TRUNCNORMAL_MIN_MASS = 1e-6

SEED_HIGH = 2**31 - 1  # the largest seed a spec may give (a 32-bit signed integer)


def _shown(value):
    """A spec entry as an error message shows it: a distribution by its table."""
    return value.table() if isinstance(value, Distribution) else value


def _check_inside_envelope(key: str, dist) -> None:
    """Refuse a dispersion whose bounds (or constant) leave the scene envelope: its samples
    there would be no landings. A normal is unbounded: its samples outside the envelope are
    counted as failures with their reason (OUTSIDE_ENVELOPE)."""
    if dist.kind == "normal":
        return
    lo, hi = envelope(key)
    where = f"the scene envelope [{lo:.4g}, {hi:.4g}]"
    a, b = (dist.mean, dist.mean) if dist.kind == "constant" else (dist.low, dist.high)
    if b < lo or a > hi:
        raise ConfigError(f"dispersion.{key}", f"[{a}, {b}]", f"lies entirely outside {where}")
    if a < lo or b > hi:
        raise ConfigError(f"dispersion.{key}", f"[{a}, {b}]", f"reaches outside {where}, where "
                          "its samples would be no landings: keep its bounds inside")


def _normal_mass(a: float, b: float) -> float:
    """P(a <= Z <= b) for a standard normal Z, accurate in both tails."""
    if a >= 0.0:
        return 0.5 * (math.erfc(a / math.sqrt(2.0)) - math.erfc(b / math.sqrt(2.0)))
    if b <= 0.0:
        return _normal_mass(-b, -a)
    return 1.0 - 0.5 * (math.erfc(-a / math.sqrt(2.0)) + math.erfc(b / math.sqrt(2.0)))


_UNSET = {"mean": 0.0, "std": 0.0, "low": -math.inf, "high": math.inf}  # Distribution's defaults
# the fields each kind of Distribution takes (a constant's mean is its TOML table's "value")
TAKES = {"normal": ("mean", "std"), "uniform": ("low", "high"),
         "truncnormal": ("mean", "std", "low", "high"), "constant": ("mean",)}


def _toml_key(kind: str, field: str) -> str:
    return "value" if kind == "constant" else field


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
        need = {k: tuple(_toml_key(k, f) for f in fs) for k, fs in TAKES.items()}
        if kind not in need:
            raise ConfigError(f"dispersion.{name}.dist", kind,
                              f"must be one of {', '.join(need)}")
        unknown = set(d) - {"dist", *need[kind]}
        if unknown:
            bad = sorted(unknown)[0]
            raise ConfigError(f"dispersion.{name}.{bad}", d[bad],
                              f"not a parameter of a {kind} distribution ({', '.join(need[kind])})")
        vals = {}
        for key in need[kind]:
            if key not in d:
                raise ConfigError(f"dispersion.{name}.{key}", None, f"is required: a {kind} "
                                  f"distribution takes {', '.join(need[kind])}")
            vals[key] = float(Number()(f"dispersion.{name}.{key}", d[key]))
        if kind == "constant":
            return cls("constant", mean=vals["value"])
        if kind in ("normal", "truncnormal") and not vals["std"] > 0:
            raise ConfigError(f"dispersion.{name}.std", vals["std"], "must be > 0")
        if kind in ("uniform", "truncnormal") and not vals["low"] < vals["high"]:
            raise ConfigError(f"dispersion.{name}.high", vals["high"],
                              f"must exceed low = {vals['low']}")
        if kind == "truncnormal":
            a = (vals["low"] - vals["mean"]) / vals["std"]  # the bounds in standard deviations
            b = (vals["high"] - vals["mean"]) / vals["std"]
            mass = _normal_mass(a, b)
            # an interval within a standard deviation of the mean samples well however little
            # mass it holds (a normal far wider than its bounds is nearly uniform on them);
            # one far in a tail collapses onto its bound
            tail = a * b > 0.0 and min(abs(a), abs(b)) > 1.0
            if tail and mass < TRUNCNORMAL_MIN_MASS:
                raise ConfigError(f"dispersion.{name}", f"[{vals['low']}, {vals['high']}]",
                                  f"holds only {mass:.2g} of the normal's probability "
                                  f"(mean {vals['mean']}, std {vals['std']}); the bounds must "
                                  f"hold at least {TRUNCNORMAL_MIN_MASS:g} (else every sample "
                                  "is the bound)")
        return cls(kind, **{k: v for k, v in vals.items()})

    def table(self) -> dict:
        """The TOML table of this distribution (``from_dict``'s input): what a directly built
        one is checked through."""
        return {"dist": self.kind, **{_toml_key(self.kind, f): getattr(self, f)
                                      for f in TAKES.get(self.kind, ())}}

    def record(self) -> dict:
        """Every parameter by name, as a results file records the distribution: those its
        kind does not take (a uniform's mean and std, a normal's bounds) are None, not the
        0 or the infinity they hold here."""
        return {"kind": self.kind, **{k: getattr(self, k) if k in TAKES[self.kind] else None
                                      for k in _UNSET}}

    def sample(self, key, shape=()):
        return sample_kind(self.kind, key, shape, self.mean, self.std, self.low, self.high)


def sample_kind(kind: str, key, shape, mean, std, low, high):
    """A draw of shape ``shape`` from a ``Distribution`` of ``kind`` whose parameters may be
    arrays (several distributions of one kind sampled together under ``vmap``)."""
    if kind == "constant":
        return jnp.full(shape, mean)
    if kind == "uniform":
        return low + (high - low) * jax.random.uniform(key, shape)
    if kind == "normal":
        return mean + std * jax.random.normal(key, shape)
    lo, hi = (low - mean) / std, (high - mean) / std
    return mean + std * jax.random.truncated_normal(key, lo, hi, shape)


MODEL_CHOICE = Choice(("auto", "quarter", "full"))

# The default ledger check interval per model [s]. Checking on every k-th step compiles the
# step twice (with and without the check): the quarter model's step compiles in a second and
# its ledger is a third of its bookkeeping; the 3-D model's Verlet step compiled 2x longer
# (7 -> 14 s, with batch fusion) to save 5 % of its run time, so it checks every step.
LEDGER_CHECK_S = {"quarter": 1e-3, "full": 0.0}


def _ledger_check(name: str, val):
    return val if val is None else NON_NEGATIVE(name, val)


@dataclass
class MonteCarloSpec:
    """What to disperse (``dispersion``: TOML key -> Distribution), what to fix (``fixed``:
    TOML key -> value), how many samples, the seed and the integration settings (the
    ``[montecarlo]`` table's keys, checked from the fields' metadata)."""

    dispersion: dict
    fixed: dict = field(default_factory=dict)
    n: int = spec_field(1000, toml="n", check=Number(integer=True, lo=1))
    seed: int = spec_field(0, toml="seed", check=Number(integer=True, lo=0, hi=SEED_HIGH))
    dt: float = spec_field(1e-5, toml="dt_s", check=POSITIVE)
    t_end: float = spec_field(1.0, toml="t_end_s", check=POSITIVE)
    model: str = spec_field("auto", toml="model", check=MODEL_CHOICE)
    # fixed-step methods batch without waiting for the slowest sample
    method: str = spec_field("euler", toml="method", check=Choice(FIXED_STEP_METHODS))
    # rerun samples that fail numerically once (with implicit strut damping; run._retry)
    retry: bool = spec_field(True, toml="retry", check=FLAG)
    # stop each landing once no outcome can change any more (Solver.early_stop; docs/
    # montecarlo.md): pays with a t_end_s beyond the settle time (quarter ~2-3 s); off by
    # default, as 1 s landings do not settle provably and the check costs compile time
    early_stop: bool = spec_field(False, toml="early_stop", check=FLAG)
    # the energy ledger and the finiteness of the state are checked every this many seconds
    # (0: every step; None: the model's LEDGER_CHECK_S): a failure is found within it, and
    # energy_closure_rel is the worst over the checks (docs/montecarlo.md). Peaks are maxima
    # over every step regardless.
    ledger_check: float | None = spec_field(None, toml="ledger_check_s", check=_ledger_check)
    # rerun this many landings called finished at t_end_s to twice t_end_s and count those
    # whose max stroke, tip-over or bottoming still changed (0: off; docs/montecarlo.md)
    t_end_check: int = spec_field(32, toml="t_end_check", check=Number(integer=True, lo=0))

    def __post_init__(self):
        for table, keys in (("dispersion", self.dispersion), ("fixed", self.fixed)):
            for key in keys:
                if key not in DISPERSIBLE:
                    raise ConfigError(f"{table}.{key}", _shown(keys[key]), "unknown input; known: "
                                      + ", ".join(sorted(DISPERSIBLE)))
        for key, dist in self.dispersion.items():  # one built in Python, as a TOML one
            if not isinstance(dist, Distribution):
                raise ConfigError(f"dispersion.{key}", type(dist).__name__,
                                  "must be a jaxland.Distribution")
            Distribution.from_dict(key, dist.table())
            unused = [k for k in _UNSET if k not in TAKES[dist.kind]
                      and getattr(dist, k) != _UNSET[k]]
            if unused:  # table() leaves them out: given, they would be ignored
                k = unused[0]
                raise ConfigError(f"dispersion.{key}.{k}", getattr(dist, k), "not a parameter "
                                  f"of a {dist.kind} distribution "
                                  f"({', '.join(k for k in dist.table() if k != 'dist')})")
        for key, val in self.fixed.items():
            per_leg = DISPERSIBLE[key].component == "legs"
            vals = val if isinstance(val, list) and per_leg else [val]
            for v in vals:
                check_int_size(f"fixed.{key}", v)
            if not vals or any(isinstance(v, bool) or not isinstance(v, (int, float))
                               or not math.isfinite(v) for v in vals):
                raise ConfigError(f"fixed.{key}", val, "must be a finite number"
                                  + (" or a list of one per leg" if per_leg else ""))
            lo, hi = envelope(key)
            if any(not lo <= v <= hi for v in vals):
                raise ConfigError(f"fixed.{key}", val,
                                  f"must lie in the scene envelope [{lo:.4g}, {hi:.4g}]")
        for key, dist in self.dispersion.items():
            _check_inside_envelope(key, dist)
        both = set(self.dispersion) & set(self.fixed)
        if both:
            key = sorted(both)[0]
            raise ConfigError(f"fixed.{key}", self.fixed[key], "is also dispersed; give one")
        for f in dataclasses.fields(self):
            if "check" in f.metadata:
                f.metadata["check"](f"montecarlo.{f.metadata['toml']}", getattr(self, f.name))
        check_spec_steps("montecarlo", self.dt, self.t_end, self.method)

    def range_of(self, key: str) -> tuple[float, float]:
        """The values an input takes over the run, in its TOML units: a fixed value, a
        dispersion's bounds (a normal's: the scene envelope, outside which a sample is no
        landing), or the scene's default where the spec leaves it."""
        if key in self.fixed:
            vals = self.fixed[key] if isinstance(self.fixed[key], list) else [self.fixed[key]]
            return float(min(vals)), float(max(vals))
        dist = self.dispersion.get(key)
        if dist is None:
            f = DISPERSIBLE[key]
            default = _SCENE_DEFAULTS[f.field]
            return (math.nan, math.nan) if default is None else (default / f.to_si,) * 2
        lo, hi = envelope(key)
        if dist.kind == "constant":
            return float(dist.mean), float(dist.mean)
        if dist.kind == "normal":
            return lo, hi
        return max(lo, float(dist.low)), min(hi, float(dist.high))

    def smallest_model(self) -> str:
        """The quarter model if every dispersed or fixed input keeps the drop symmetric (the
        scenes' own rule, ``_keeps_symmetry``)."""
        inputs = {**self.fixed, **self.dispersion}
        return ("quarter" if all(_keeps_symmetry(k, v) for k, v in inputs.items())
                else "full")

    def resolved_model(self, where: str = "montecarlo") -> str:
        """The model to run: ``model``, or the smallest adequate one for ``auto``; a quarter
        model asked for dispersions that break the symmetry is refused (as ``where``.model)."""
        model = self.smallest_model() if self.model == "auto" else self.model
        if model == "quarter" and self.smallest_model() == "full":
            raise ConfigError(f"{where}.model", "quarter", "these dispersions break the "
                              "symmetry of a vertical drop; the full model is needed")
        return model


def montecarlo_spec_from_dict(data: dict, *, keys_excluded: dict | None = None,
                              **overrides) -> MonteCarloSpec:
    """A ``MonteCarloSpec`` from the ``montecarlo``, ``dispersion`` and ``fixed`` tables of a
    TOML-shaped dict (other tables are the caller's); ``keys_excluded`` are ``[montecarlo]``
    keys the caller does not take, each with why (the refusal gives it)."""
    for section in ("montecarlo", "dispersion", "fixed"):
        if not isinstance(data.get(section, {}), dict):
            raise ConfigError(section, data[section], f"must be a table ([{section}])")
    mc = dict(data.get("montecarlo", {}))
    for key, reason in (keys_excluded or {}).items():
        if key in mc:
            raise ConfigError(f"montecarlo.{key}", mc[key], f"is not taken here: {reason}")
    kwargs = parse_table(MonteCarloSpec, "montecarlo", mc)
    disp = {}
    for name, table in data.get("dispersion", {}).items():
        if not isinstance(table, dict):
            raise ConfigError(f"dispersion.{name}", table, "must be a table with dist = ...")
        disp[name] = Distribution.from_dict(name, table)
    return MonteCarloSpec(dispersion=disp, fixed=dict(data.get("fixed", {})),
                          **{**kwargs, **overrides})


def montecarlo_spec_to_toml(spec: MonteCarloSpec) -> str:
    """``spec`` as a spec file that ``load_montecarlo_spec`` reads back to the same spec: every
    ``[montecarlo]`` key (the defaults filled in), ``[fixed]`` and ``[dispersion.*]``."""
    lines = ["[montecarlo]"]
    for f in dataclasses.fields(spec):
        if "toml" in f.metadata and getattr(spec, f.name) is not None:
            lines.append(f"{f.metadata['toml']} = {toml_value(getattr(spec, f.name))}")
    if spec.fixed:
        lines += ["", "[fixed]"] + [f"{k} = {toml_value(v)}" for k, v in spec.fixed.items()]
    for key, dist in spec.dispersion.items():
        lines += ["", f"[dispersion.{key}]"] + [f"{k} = {toml_value(v)}"
                                                 for k, v in dist.table().items()]
    return "\n".join(lines) + "\n"


def check_disperses_something(spec: MonteCarloSpec) -> None:
    """Refuse a spec that disperses no input (no ``[dispersion]`` entry, or only constants):
    its n landings would all be one landing, presented as a Monte Carlo. Checked on a spec
    file (``load_montecarlo_spec``), not in ``MonteCarloSpec``: a design spec's tables and
    Python callers may fix every input on purpose (a design over fixed scenes, one landing
    run through the Monte Carlo's outcomes)."""
    if all(d.kind == "constant" for d in spec.dispersion.values()):
        shown = {k: d.table() for k, d in spec.dispersion.items()}
        why = ' (every entry is dist = "constant")' if shown else ""
        raise ConfigError("dispersion", shown, f"disperses nothing{why}; a Monte Carlo needs "
                          "at least one dispersed input (use jaxland simulate for one landing)")


def load_montecarlo_spec(path) -> MonteCarloSpec:
    """Read a Monte Carlo spec TOML: ``[montecarlo]`` (n, seed, dt_s, t_end_s, model, method),
    ``[dispersion.<input>]`` tables (at least one input not constant) and an optional
    ``[fixed]`` table (docs/formats.md)."""
    data = read_toml(path, "spec")
    unknown = set(data) - {"montecarlo", "dispersion", "fixed"}
    if unknown:
        raise ConfigError(sorted(unknown)[0], "<table>",
                          "unknown section; known: montecarlo, dispersion, fixed")
    spec = montecarlo_spec_from_dict(data)
    check_disperses_something(spec)
    return spec
