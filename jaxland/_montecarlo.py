"""Monte Carlo over touchdown dispersions: sampled scenes, the smallest adequate model, chunked
``vmap`` sharded over every local device, failed samples recorded (never a crash of the batch),
tip-over and bottoming probabilities with Wilson intervals, envelopes and sensitivities.

Reproducibility: sample i's inputs depend only on (seed, i, input name), via
``fold_in(fold_in(key(seed), i), crc32(name))``, so the same seed gives the same samples for any
chunk size and any number of devices (and adding an input does not change the others' draws).

Scale-out: the batch axis of each chunk is sharded with ``jax.sharding.NamedSharding`` over a
1-D mesh of ``jax.devices()``. On CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=K``
(set before importing jax) makes K devices of the host's cores; on a GPU or TPU host the same
code uses its accelerators; on a multi-host cluster call ``jax.distributed.initialize()`` first
and every process runs the same program (each then holds its addressable shard).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._config import paper_vehicle, validate_vehicle
from ._errors import ConfigError
from ._integrate import FIXED_STEP_METHODS, Solver, stable_step
from ._params import Vehicle
from ._scene import SCENE_FIELDS, Scene
from ._simulate import CLOSURE_LIMIT, landings
from ._toml import read_toml

__all__ = ["Distribution", "MonteCarloSpec", "MonteCarloResult", "load_montecarlo_spec",
           "sample_scenes", "run_montecarlo", "wilson_interval"]

_Z95 = 1.959963984540054

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


def _envelope(key: str) -> tuple[float, float]:
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
            lo, hi = _envelope(key)
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


# ------------------------------------------------------------------------------- sampling

def sample_scenes(spec: MonteCarloSpec, start: int, count: int, n_legs: int = 4):
    """Scenes ``start .. start + count - 1`` of the spec, as a ``Scene.batch``, with the sampled
    inputs (TOML units; per-leg inputs as (count, n_legs))."""
    names = sorted(spec.dispersion)
    root = jax.random.key(spec.seed)
    idx = jnp.arange(start, start + count)

    def one(i):
        k = jax.random.fold_in(root, i)
        out = {}
        for name in names:
            shape = (n_legs,) if DISPERSIBLE[name][2] == "legs" else ()
            key = jax.random.fold_in(k, zlib.crc32(name.encode()) & 0x7FFFFFFF)
            out[name] = spec.dispersion[name].sample(key, shape)
        return out

    inputs = {k: np.asarray(v) for k, v in jax.vmap(one)(idx).items()} if names else {}
    fields: dict = {}
    com = None
    for name, value in [*inputs.items(), *spec.fixed.items()]:
        target, to_si, comp = DISPERSIBLE[name]
        val = np.broadcast_to(np.asarray(value, dtype=float) * to_si,
                              (count, n_legs) if comp == "legs" else (count,))
        if target == "com_offset":
            com = np.zeros((count, 3)) if com is None else com
            com[:, comp] = val
        else:
            fields[target] = val
    if com is not None:
        fields["com_offset"] = com
    if not fields:
        fields["drop_height"] = np.full(count, 0.2)
    scenes = Scene.batch(**{k: jnp.asarray(v) for k, v in fields.items()})
    return scenes, inputs


# ------------------------------------------------------------------------------- statistics

def wilson_interval(k: int, n: int, z: float = _Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion k/n (95 % by default)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    lo = 0.0 if k == 0 else max(0.0, centre - half)  # the bounds at k = 0 and k = n are
    hi = 1.0 if k == n else min(1.0, centre + half)  # exactly 0 and 1 (round-off aside)
    return (lo, hi)


def _percentiles(x):
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return None
    q = np.percentile(x, [1, 5, 50, 95, 99])
    return dict(p01=q[0], p05=q[1], p50=q[2], p95=q[3], p99=q[4], max=float(np.max(x)),
                mean=float(np.mean(x)))


# ------------------------------------------------------------------------------- the run

_FAIL_REASONS = {0: "ok", 1: "non-finite state or energy blow-up during the run",
                 2: "energy ledger did not close (step too large for this landing)",
                 3: "step above the stability limit of the forces reached",
                 4: "sampled scene outside the documented envelope (not simulated as valid)"}


def _per_sample(vehicle, solver, model, scenes):
    traj, s = landings(vehicle, scenes, solver, model)
    del traj
    n = vehicle.n_legs

    def legs(x):
        return jnp.broadcast_to(x[..., None], x.shape + (n,)) if x.ndim == 1 else x

    out = dict(
        max_stroke_m=legs(s["max_stroke_m"]),
        peak_strut_force_N=legs(s["peak_strut_force_N"]),
        peak_normal_force_N=legs(s["peak_normal_force_N"]),
        peak_honeycomb_force_N=legs(s["peak_honeycomb_force_N"]),
        slip_distance_m=legs(s["slip_distance_m"]),
        peak_body_accel_mps2=s["peak_body_accel_mps2"],
        energy_closure_rel=s["ledger_error_rel"],
        failed_in_run=s["failed"],
        tipped_over=s["tipped"],
    )
    if model == "full":
        out["min_stability_margin_m"] = -s["peak_margin_deficit_m"]
        out["peak_tilt_deg"] = s["peak_tilt_deg"]
    return out


@dataclass
class MonteCarloResult:
    """Per-sample inputs and outcomes (numpy), failure reasons, and the summary."""

    inputs: dict
    outputs: dict
    failure: np.ndarray  # (n,) int codes, 0 = ok (see ``reasons``)
    summary: dict
    reasons: dict = field(default_factory=lambda: dict(_FAIL_REASONS))

    def columns(self) -> dict:
        """One flat column per quantity (per-leg arrays as leg{i}_...), units in the names."""
        cols = {"sample": np.arange(self.failure.size)}
        for group in (self.inputs, self.outputs):
            for name, arr in group.items():
                arr = np.asarray(arr)
                if arr.ndim == 1:
                    cols[name] = arr
                else:
                    for i in range(arr.shape[1]):
                        cols[f"leg{i}_{name}"] = arr[:, i]
        cols["failure_code"] = self.failure
        return cols

    def save(self, out_dir) -> list[Path]:
        """Write samples.csv and samples.npz (every sample with its inputs), summary.json and
        the figures into ``out_dir``, all through a staging folder."""
        from ._files import staged

        out = Path(out_dir)
        with staged(out) as staging:
            cols = self.columns()
            names = list(cols)
            data = np.column_stack([np.asarray(cols[c], dtype=float) for c in names])
            np.savetxt(staging / "samples.csv", data, delimiter=",", header=",".join(names),
                       comments="", fmt="%.9g")
            np.savez_compressed(staging / "samples.npz", **cols)
            (staging / "summary.json").write_text(
                json.dumps(self.summary, indent=2, default=float) + "\n")
            from ._plots_mc import plot_montecarlo

            plot_montecarlo(self, staging / "figures")
            written = sorted(out / p.relative_to(staging) for p in staging.rglob("*")
                             if p.is_file())
        return written


def _sensitivity(inputs: dict, target: np.ndarray, ok: np.ndarray) -> list[dict]:
    """Linear regression of ``target`` on the standardised dispersed inputs (per-leg inputs
    enter per leg): the change of the target per standard deviation of each input, ranked."""
    cols, names = [], []
    for name, arr in inputs.items():
        arr = np.asarray(arr, dtype=float)
        arr = arr[:, None] if arr.ndim == 1 else arr
        for i in range(arr.shape[1]):
            x = arr[ok, i]
            if x.size > 1 and np.std(x) > 0:
                cols.append((x - x.mean()) / x.std())
                names.append(name if arr.shape[1] == 1 else f"{name}[leg{i}]")
    y = np.asarray(target, dtype=float)[ok]
    if not cols or y.size <= len(cols) + 1:
        return []
    X = np.column_stack([np.ones(y.size), *cols])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ coef
    r2 = 1.0 - resid.var() / y.var() if y.var() > 0 else 0.0
    ranked = sorted(zip(names, coef[1:]), key=lambda t: -abs(t[1]))
    return [dict(input=n, effect_per_std=float(c), r2_of_fit=float(r2)) for n, c in ranked]


def run_montecarlo(spec: MonteCarloSpec, vehicle: Vehicle | None = None, *,
                   chunk: int | None = None, devices=None, progress: bool = True
                   ) -> MonteCarloResult:
    """Run ``spec.n`` dispersed landings; see the module docstring for reproducibility and
    sharding. ``chunk`` bounds memory (rounded up to a multiple of the device count)."""
    vehicle = paper_vehicle() if vehicle is None else vehicle
    validate_vehicle(vehicle)
    model = spec.resolved_model()
    solver = Solver(dt=spec.dt, t_end=spec.t_end, save_dt=spec.t_end,
                    method=spec.method).validate()
    devices = list(jax.devices() if devices is None else devices)
    n_dev = len(devices)
    chunk = min(spec.n, 512 if model == "quarter" else 64) if chunk is None else int(chunk)
    if chunk < 1:
        raise ConfigError("chunk", chunk, "must be >= 1")
    chunk = int(math.ceil(chunk / n_dev) * n_dev)
    mesh = Mesh(np.array(devices), ("batch",))
    batch_sharding = NamedSharding(mesh, PartitionSpec("batch"))
    limit = float(stable_step(vehicle, method=spec.method))
    if spec.dt > limit:
        raise ConfigError("montecarlo.dt_s", spec.dt,
                          f"exceeds the a-priori stability limit {limit:.3g} s of "
                          f"{spec.method}")

    run = jax.jit(lambda sc: _per_sample(vehicle, solver, model, sc))
    outputs: dict = {}
    inputs: dict = {}
    t0 = time.perf_counter()
    for start in range(0, spec.n, chunk):
        count = min(chunk, spec.n - start)
        scenes, ins = sample_scenes(spec, start, chunk, vehicle.n_legs)  # padded chunk
        scenes = jax.tree.map(
            lambda x: jax.device_put(x, batch_sharding) if np.ndim(x) >= 1 else x, scenes)
        res = jax.device_get(run(scenes))
        for k, v in res.items():
            outputs.setdefault(k, []).append(np.asarray(v)[:count])
        for k, v in ins.items():
            inputs.setdefault(k, []).append(v[:count])
        if progress:
            done = start + count
            rate = done / (time.perf_counter() - t0)
            print(f"\rmontecarlo: {done}/{spec.n} landings ({model} model, {n_dev} device"
                  f"{'s' if n_dev > 1 else ''}, {rate:.0f}/s)", end="", file=sys.stderr,
                  flush=True)
    if progress:
        print(file=sys.stderr)
    wall = time.perf_counter() - t0
    outputs = {k: np.concatenate(v) for k, v in outputs.items()}
    inputs = {k: np.concatenate(v) for k, v in inputs.items()}

    failure = np.zeros(spec.n, dtype=int)
    limits = np.asarray(jax.vmap(lambda h, nf: stable_step(
        vehicle, honeycomb_force=h, normal_force=nf, bottomed=True, method=spec.method))(
        outputs["peak_honeycomb_force_N"].max(axis=1),
        outputs["peak_normal_force_N"].max(axis=1)))
    bottomed = outputs["max_stroke_m"].max(axis=1) > float(vehicle.honeycomb.x_L4)
    limits_nb = np.asarray(jax.vmap(lambda h, nf: stable_step(
        vehicle, honeycomb_force=h, normal_force=nf, method=spec.method))(
        outputs["peak_honeycomb_force_N"].max(axis=1),
        outputs["peak_normal_force_N"].max(axis=1)))
    limits = np.where(bottomed, limits, limits_nb)
    # (the integrator stops peaks, ledger and failure checks at a tip-over, so these judge the
    # landing up to the tip, as simulate does)
    failure[spec.dt > limits] = 3
    failure[outputs["energy_closure_rel"] > CLOSURE_LIMIT] = 2
    failure[outputs.pop("failed_in_run").astype(bool)] = 1
    failure[~_inside_envelope(inputs, spec)] = 4
    outputs["bottomed_out"] = bottomed
    outputs["tipped_over"] = outputs["tipped_over"].astype(bool)
    summary = _summarise(spec, model, inputs, outputs, failure, wall, n_dev, chunk)
    return MonteCarloResult(inputs, outputs, failure, summary)


def _inside_envelope(inputs: dict, spec: MonteCarloSpec) -> np.ndarray:
    """Per sample: every dispersed input within the scene envelope (unbounded distributions can
    draw outside it; such samples are recorded as failures, code 4, not as landings)."""
    ok = np.ones(spec.n, bool)
    for key, arr in inputs.items():
        lo, hi = _envelope(key)
        arr = np.asarray(arr, dtype=float)
        inside = np.isfinite(arr) & (arr >= lo) & (arr <= hi)
        ok &= inside if inside.ndim == 1 else inside.all(axis=1)
    return ok


def _summarise(spec, model, inputs, outputs, failure, wall, n_dev, chunk) -> dict:
    ok = failure == 0
    n_ok = int(ok.sum())
    k_tip = int(outputs["tipped_over"][ok].sum())
    k_bot = int(outputs["bottomed_out"][ok].sum())
    target = (outputs["min_stability_margin_m"] if "min_stability_margin_m" in outputs
              else outputs["max_stroke_m"].max(axis=1))
    reasons = {_FAIL_REASONS[c]: int((failure == c).sum()) for c in (1, 2, 3, 4)
               if (failure == c).any()}
    return dict(
        n=spec.n, seed=spec.seed, model=model, method=spec.method, dt_s=spec.dt,
        t_end_s=spec.t_end,
        devices=n_dev, chunk=chunk, wall_s=wall, landings_per_s=spec.n / wall,
        n_failed=int((~ok).sum()), failures=reasons,
        failed_samples=np.flatnonzero(~ok).tolist()[:100],
        tip_over=dict(count=k_tip, n=n_ok, probability=k_tip / max(n_ok, 1),
                      ci95_wilson=wilson_interval(k_tip, n_ok)),
        bottoming=dict(count=k_bot, n=n_ok, probability=k_bot / max(n_ok, 1),
                       ci95_wilson=wilson_interval(k_bot, n_ok)),
        envelopes={
            "max_stroke_m (any leg)": _percentiles(outputs["max_stroke_m"][ok].max(axis=1)),
            "peak_body_accel_mps2": _percentiles(outputs["peak_body_accel_mps2"][ok]),
            "peak_strut_force_N (any leg)":
                _percentiles(outputs["peak_strut_force_N"][ok].max(axis=1)),
            "slip_distance_m (any leg)":
                _percentiles(outputs["slip_distance_m"][ok].max(axis=1)),
            **({"min_stability_margin_m": _percentiles(outputs["min_stability_margin_m"][ok])}
               if "min_stability_margin_m" in outputs else {}),
        },
        sensitivity=dict(
            target="min_stability_margin_m" if model == "full" else "max_stroke_m",
            method="least squares on standardised inputs: change per standard deviation",
            ranking=_sensitivity(inputs, target, ok)),
        dispersion={k: vars(v) for k, v in spec.dispersion.items()},
        fixed=spec.fixed,
        environment=dict(jax=jax.__version__, backend=jax.default_backend(),
                         xla_flags=os.environ.get("XLA_FLAGS", "")),
    )
