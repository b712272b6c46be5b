"""Gradient-based landing-gear design, robust over a fixed set of dispersed touchdowns.

The problem (see the README section "Design" for the spec format)::

    minimise    J(x) = R_obj[a_peak(x, s)] / a0  +  w_m * m_gear(x) / m0
    subject to  g_i(x) = R_i[b_i(x, s)] / scale_i <= 0,       x in [low, high]

* ``x`` are the design variables (``VARIABLES``): plateau forces F1, F2, or the cell size and
  foil thickness of each stage through Wierzbicki's crush formula (something one can buy), the
  stage lengths x_L2 and x_L4, the auxiliary strut stiffness k_a, the strut angle theta_b and
  the joint radius R. Each is mapped from an unconstrained ``z`` by a smooth transform,
  ``x = low + (high - low) sigmoid(z)`` (or the same in log x): bounds hold exactly and are
  never enforced by clipping. Orderings the honeycomb law needs (F2 > F1, x_L4 > x_L3) are
  built into the transform: the lower bound of F2 (x_L4) moves with F1 (x_L2).
* ``s`` are ``n_scenes`` scenes drawn once from the Monte Carlo dispersion with ``scene_seed``
  (``jaxland._montecarlo.sample_scenes``); they stay fixed through the optimisation (sample
  average approximation), so the robust objective is a deterministic function of ``x``.
* ``R`` is a risk measure over those scenes: ``mean``, ``cvar`` at ``level`` (the mean of the
  worst (1 - level) fraction, with the fractional sample weighted), ``max``, or ``normal`` at
  ``level``: mean + z_level std, the level-quantile of a normal fitted to the scenes. ``max``
  and ``cvar`` of N scenes cannot see beyond the N-th worst outcome (a fresh landing exceeds
  the max of N with probability 1/(N + 1)); ``normal`` extrapolates to quantiles the scenes do
  not reach, and every scene carries gradient (no switching of the worst scene).
* ``a_peak`` is the peak body acceleration of each landing as the integrator keeps it: the
  running maximum at every step. Its gradient is the slope at the step where the maximum
  occurs, which is the derivative of the maximum wherever that step is unique (Danskin). We
  measured a smooth maximum (log-sum-exp over the saved trace) and did not use it: see
  ``benchmarks/bench_design.py`` for its bias. So no smoothing enters, and the verification
  Monte Carlo judges the same quantities the optimiser saw.
* The constraints' per-scene "badness" ``b_i`` (positive = violated):
  ``stroke``: max stroke (any leg) - (x_L4 - margin), no bottoming out with a margin;
  ``stability``: threshold - minimum stability margin over the landing (full 3-D model);
  ``slip``: foot slip distance (any leg) - limit.
* ``m_gear`` is a documented mass proxy (``gear_mass_kg``).

Method: the augmented Lagrangian of Powell-Hestenes-Rockafellar for inequalities,

    L(z; lam, rho) = J + sum_i (rho / 2) [max(0, g_i + lam_i / rho)^2 - (lam_i / rho)^2],

minimised in ``z`` by optax: ``clip_by_global_norm(clip_norm)`` then ``scale_by_adam``, with
the step from an optax schedule (``lr_schedule``: cosine or exponential decay to
``lr_final`` x ``learning_rate``, or constant). The clip matters: one step across a stroke
constraint returns a penalty gradient ~100x the objective's, and Adam's second moment would
remember it for ~100 iterations (b2 = 0.9), shrinking every later step (measured in
``benchmarks/bench_design.py``). Every ``outer_every`` iterations the multipliers are updated,
``lam_i <- max(0, lam_i + rho g_i)``,
and ``rho`` grows by ``penalty_growth`` when the worst violation did not at least halve. The
gradients of J and every g_i come from one forward-mode Jacobian (``jax.jacfwd`` through the
vmapped batch of landings, no trajectory memory), and L's gradient is assembled from them on the
host, so changing multipliers never recompiles.

The returned design is the best iterate that satisfies every constraint to ``feasibility_tol``
(in the normalised units of g). If no iterate does, the result's ``status`` is
``"infeasible"`` and ``violated`` names each violated constraint with its value.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._config import PAPER_CELLS, paper_vehicle, validate_vehicle, vehicle_to_toml
from ._crush import foil_ratio, plateau_force
from ._errors import ConfigError
from ._files import atomic_write_text
from ._models import MODELS
from ._montecarlo import (
    Distribution,
    MonteCarloSpec,
    percentiles,
    run_montecarlo,
    sample_scenes,
    wilson_interval,
)
from ._params import Vehicle
from ._simulate import _py, landings
from ._solvers import Result, Solver, stable_step, verdict
from ._toml import read_toml

__all__ = ["VARIABLES", "DesignVariable", "Objective", "Constraint", "DesignSpec",
           "DesignProblem", "DesignResult", "load_design_spec", "design_spec_from_dict",
           "optimise_design", "verify_design", "gear_mass_kg", "risk_measure", "apply_design"]

_DEG = math.pi / 180.0

# name: (unit in the TOML key, TOML -> SI factor, default transform, meaning)
VARIABLES = {
    "F1_N": ("N", 1.0, "log", "plateau force of the primary honeycomb (k_b1 keeps x_L1)"),
    "F2_N": ("N", 1.0, "log", "plateau force of the secondary honeycomb (k_b3 keeps "
             "x_L3 - x_L2); its lower bound is at least 1.02 F1"),
    "primary_cell_size_mm": ("mm", 1e-3, "log", "cell size D of the primary honeycomb"),
    "primary_foil_thickness_mm": ("mm", 1e-3, "log", "foil thickness t of the primary honeycomb"),
    "secondary_cell_size_mm": ("mm", 1e-3, "log", "cell size D of the secondary honeycomb"),
    "secondary_foil_thickness_mm": ("mm", 1e-3, "log",
                                    "foil thickness t of the secondary honeycomb"),
    "x_L2_mm": ("mm", 1e-3, "linear", "stroke at the end of the primary stage"),
    "x_L4_mm": ("mm", 1e-3, "linear", "available stroke, end of the secondary stage; its "
                "lower bound is at least x_L3 + 1 mm"),
    "k_a_N_per_m": ("N/m", 1.0, "log", "axial stiffness of the pair of auxiliary struts"),
    "theta_b_deg": ("deg", _DEG, "linear", "main strut angle below the horizontal (sets the "
                    "footprint radius R + L_h0 cos theta_b)"),
    "R_m": ("m", 1.0, "linear", "radial offset of the strut joints (moves the footprint)"),
}
_CELL_VARS = ("primary_cell_size_mm", "primary_foil_thickness_mm", "secondary_cell_size_mm",
              "secondary_foil_thickness_mm")
_FORCE_VARS = ("F1_N", "F2_N")
ORDER_RATIO = 1.02  # F2 >= 1.02 F1 (a distinct secondary stage)
ORDER_GAP_M = 1e-3  # x_L4 >= x_L3 + 1 mm

MEASURES = ("mean", "cvar", "max", "normal")
SCHEDULES = ("cosine", "exponential", "constant")
CONSTRAINTS = {  # name: (threshold key, its unit factor to SI, default scale [SI], meaning)
    "stroke": ("margin_mm", 1e-3, 0.01,
               "max stroke (any leg) <= x_L4 - margin: no bottoming out"),
    "stability": ("min_margin_m", 1.0, 0.1,
                  "minimum stability margin >= threshold: no tip-over (full 3-D model)"),
    "slip": ("max_slip_mm", 1e-3, 0.01, "foot slip distance (any leg) <= limit"),
}

# Gear-mass proxy constants (documented in ``gear_mass_kg``).
RHO_FOIL_KG_M3 = 2680.0  # Al 5052
RHO_STEEL_KG_M3 = 7850.0
E_STEEL_PA = 2.0e11
# relative density of a hexagonal honeycomb per unit t/D
HEX_DENSITY_FACTOR = 8.0 / (3.0 * math.sqrt(3.0))
STROKE_EFFICIENCY = 0.75  # usable crush stroke / block length


# ------------------------------------------------------------------------------- the spec

@dataclass(frozen=True)
class DesignVariable:
    """One design variable: TOML name (``VARIABLES``), bounds in the name's units, transform
    (``linear`` or ``log``) and an optional start value (default: the baseline vehicle's)."""

    name: str
    low: float
    high: float
    scale: str = "linear"
    start: float | None = None

    @property
    def to_si(self) -> float:
        return VARIABLES[self.name][1]


@dataclass(frozen=True)
class Objective:
    """Peak body acceleration under a risk measure, plus ``mass_weight`` x the normalised gear
    mass proxy."""

    measure: str = "cvar"
    level: float = 0.9
    mass_weight: float = 0.0


@dataclass(frozen=True)
class Constraint:
    """``name`` in ``CONSTRAINTS``; ``threshold`` in SI; risk measure over the scenes;
    ``scale`` [SI] normalises the constraint for the augmented Lagrangian."""

    name: str
    threshold: float
    measure: str = "max"
    level: float = 0.9
    scale: float = 0.01


@dataclass
class DesignSpec:
    """Everything a design run needs (see ``design_spec_from_dict`` for the TOML form)."""

    variables: list
    objective: Objective
    constraints: list
    montecarlo: MonteCarloSpec  # the dispersion; its n, seed, dt, t_end drive the verification
    n_scenes: int = 16
    scene_seed: int = 0
    iterations: int = 60
    dt: float = 1e-5
    t_end: float = 0.5
    model: str = "auto"
    learning_rate: float = 0.1
    outer_every: int = 10
    penalty: float = 10.0
    penalty_growth: float = 3.0
    penalty_max: float = 1e4
    feasibility_tol: float = 1e-3
    adam_b1: float = 0.5
    adam_b2: float = 0.9
    clip_norm: float = 0.3  # global-norm clip of the Lagrangian's gradient (0: none)
    lr_schedule: str = "cosine"
    lr_final: float = 0.02  # final step / learning_rate
    patience: int = 0  # stop when the best feasible J has not improved by stop_rtol for this
    stop_rtol: float = 1e-3  # many iterations (0: run all iterations)
    cells: dict = field(default_factory=lambda: dict(PAPER_CELLS))
    vehicle: str | None = None  # path of the baseline vehicle TOML (default: the paper's)

    @property
    def names(self) -> tuple:
        return tuple(v.name for v in self.variables)

    def resolved_model(self) -> str:
        model = self.montecarlo.smallest_model() if self.model == "auto" else self.model
        if model == "quarter" and self.montecarlo.smallest_model() == "full":
            raise ConfigError("design.model", "quarter", "these dispersions break the symmetry "
                              "of a vertical drop; the full model is needed")
        return model


def _num(field_name, val, *, positive=False, integer=False, lo=None, hi=None):
    if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
        raise ConfigError(field_name, val, "must be a finite number")
    if integer and (not isinstance(val, int)):
        raise ConfigError(field_name, val, "must be an integer")
    if positive and not val > 0:
        raise ConfigError(field_name, val, "must be > 0")
    if lo is not None and val < lo:
        raise ConfigError(field_name, val, f"must be >= {lo:g}")
    if hi is not None and val > hi:
        raise ConfigError(field_name, val, f"must be <= {hi:g}")
    return val


def _measure(prefix, table) -> tuple[str, float]:
    measure = table.get("measure", "max" if prefix.startswith("constraints") else "cvar")
    if measure not in MEASURES:
        raise ConfigError(f"{prefix}.measure", measure, f"must be one of {', '.join(MEASURES)}")
    level = table.get("level", 0.9)
    _num(f"{prefix}.level", level)
    if not 0.0 <= level < 1.0:
        raise ConfigError(f"{prefix}.level", level, "must be in [0, 1) (CVaR: the mean of the "
                          "worst 1 - level fraction of the scenes)")
    if measure == "normal" and not level > 0.0:
        raise ConfigError(f"{prefix}.level", level, "must be in (0, 1) for measure = normal "
                          "(the quantile mean + z_level std)")
    return measure, float(level)


def _known(prefix, table, keys):
    if not isinstance(table, dict):
        raise ConfigError(prefix, table, "must be a table")
    unknown = set(table) - set(keys)
    if unknown:
        bad = sorted(unknown)[0]
        raise ConfigError(f"{prefix}.{bad}", table[bad], f"unknown key; known: {', '.join(keys)}")


_DESIGN_KEYS = {"iterations": "iterations", "n_scenes": "n_scenes", "scene_seed": "scene_seed",
                "dt_s": "dt", "t_end_s": "t_end", "model": "model",
                "learning_rate": "learning_rate", "outer_every": "outer_every",
                "penalty": "penalty", "penalty_growth": "penalty_growth",
                "penalty_max": "penalty_max", "feasibility_tol": "feasibility_tol",
                "adam_b1": "adam_b1", "adam_b2": "adam_b2", "clip_norm": "clip_norm",
                "lr_schedule": "lr_schedule", "lr_final": "lr_final", "patience": "patience",
                "stop_rtol": "stop_rtol",
                "vehicle": "vehicle"}


def design_spec_from_dict(data: dict, base_dir: Path | None = None) -> DesignSpec:
    """Build and validate a ``DesignSpec`` from a TOML-shaped dict (see the README)."""
    sections = ("design", "objective", "variables", "constraints", "cells", "montecarlo",
                "dispersion", "fixed")
    _known("spec", data, sections)
    d = dict(data.get("design", {}))
    _known("design", d, list(_DESIGN_KEYS))
    kw = {}
    for key, attr in _DESIGN_KEYS.items():
        if key not in d:
            continue
        val = d[key]
        if key in ("iterations", "n_scenes", "outer_every", "patience"):
            _num(f"design.{key}", val, integer=True,
                 lo=0 if key in ("iterations", "patience") else 1, hi=100000)
        elif key == "scene_seed":
            _num(f"design.{key}", val, integer=True, lo=0, hi=2**31 - 1)
        elif key == "model":
            if val not in ("auto", "quarter", "full"):
                raise ConfigError("design.model", val, "must be auto, quarter or full")
        elif key == "vehicle":
            if not isinstance(val, str):
                raise ConfigError("design.vehicle", val, "must be a path (string)")
            p = Path(val)
            val = str(p if p.is_absolute() or base_dir is None else base_dir / p)
        elif key == "penalty_growth":
            _num(f"design.{key}", val, lo=1.0)
        elif key in ("adam_b1", "adam_b2"):
            _num(f"design.{key}", val, lo=0.0)
            if not val < 1.0:
                raise ConfigError(f"design.{key}", val, "must be in [0, 1)")
        elif key == "clip_norm":
            _num(f"design.{key}", val, lo=0.0)
        elif key == "lr_schedule":
            if val not in SCHEDULES:
                raise ConfigError("design.lr_schedule", val,
                                  f"must be one of {', '.join(SCHEDULES)}")
        elif key == "lr_final":
            _num(f"design.{key}", val, positive=True, hi=1.0)
        else:
            _num(f"design.{key}", val, positive=True)
        kw[attr] = val

    obj = dict(data.get("objective", {}))
    _known("objective", obj, ["quantity", "measure", "level", "mass_weight"])
    if obj.get("quantity", "peak_body_accel_mps2") != "peak_body_accel_mps2":
        raise ConfigError("objective.quantity", obj["quantity"],
                          "must be peak_body_accel_mps2 (the overload)")
    measure, level = _measure("objective", obj)
    mw = _num("objective.mass_weight", obj.get("mass_weight", 0.0), lo=0.0)
    objective = Objective(measure, level, float(mw))

    variables = []
    vtab = data.get("variables", {})
    if not isinstance(vtab, dict) or not vtab:
        raise ConfigError("variables", vtab, "give at least one [variables.<name>] table; "
                          f"known: {', '.join(VARIABLES)}")
    for name, t in vtab.items():
        if name not in VARIABLES:
            raise ConfigError(f"variables.{name}", "<table>",
                              f"unknown design variable; known: {', '.join(VARIABLES)}")
        _known(f"variables.{name}", t, ["low", "high", "scale", "start"])
        for k in ("low", "high"):
            if k not in t:
                raise ConfigError(f"variables.{name}.{k}", None, "is required (a bound in "
                                  f"{VARIABLES[name][0]})")
        lo = _num(f"variables.{name}.low", t["low"])
        hi = _num(f"variables.{name}.high", t["high"])
        if not hi > lo:
            raise ConfigError(f"variables.{name}.high", hi, f"must exceed low = {lo:g}")
        scale = t.get("scale", VARIABLES[name][2])
        if scale not in ("linear", "log"):
            raise ConfigError(f"variables.{name}.scale", scale, "must be linear or log")
        if scale == "log" and not lo > 0:
            raise ConfigError(f"variables.{name}.low", lo, "must be > 0 for scale = log")
        start = t.get("start")
        if start is not None:
            _num(f"variables.{name}.start", start)
            if not lo < start < hi:
                raise ConfigError(f"variables.{name}.start", start,
                                  f"must lie strictly inside (low, high) = ({lo:g}, {hi:g})")
        variables.append(DesignVariable(name, float(lo), float(hi), scale,
                                        None if start is None else float(start)))
    names = {v.name for v in variables}
    if names & set(_FORCE_VARS) and names & set(_CELL_VARS):
        raise ConfigError("variables", sorted(names & set(_FORCE_VARS))[0],
                          "give plateau forces (F1_N, F2_N) or honeycomb cells "
                          "(*_cell_size_mm, *_foil_thickness_mm) as variables, not both")

    cells = dict(PAPER_CELLS)
    ctab = data.get("cells", {})
    _known("cells", ctab, list(PAPER_CELLS))
    for k, v in ctab.items():
        cells[k] = float(_num(f"cells.{k}", v, positive=True))

    constraints = []
    ctabs = data.get("constraints", {})
    _known("constraints", ctabs, list(CONSTRAINTS))
    for name, t in ctabs.items():
        key, to_si, default_scale, _ = CONSTRAINTS[name]
        _known(f"constraints.{name}", t, [key, "measure", "level", "scale_" + key.rsplit("_")[-1]])
        if key not in t:
            raise ConfigError(f"constraints.{name}.{key}", None, "is required")
        thr = _num(f"constraints.{name}.{key}", t[key])
        if name in ("stroke", "slip") and thr < 0:
            raise ConfigError(f"constraints.{name}.{key}", thr, "must be >= 0")
        measure, level = _measure(f"constraints.{name}", t)
        skey = "scale_" + key.rsplit("_")[-1]
        scale = _num(f"constraints.{name}.{skey}", t[skey], positive=True) * to_si \
            if skey in t else default_scale
        constraints.append(Constraint(name, float(thr) * to_si, measure, level, float(scale)))

    mc = dict(data.get("montecarlo", {}))
    keys = {"n": "n", "seed": "seed", "dt_s": "dt", "t_end_s": "t_end", "model": "model"}
    _known("montecarlo", mc, list(keys))
    disp = {}
    dtab = data.get("dispersion", {})
    _known("dispersion", dtab, list(dtab))
    for name, table in dtab.items():
        if not isinstance(table, dict):
            raise ConfigError(f"dispersion.{name}", table, "must be a table with dist = ...")
        disp[name] = Distribution.from_dict(name, table)
    fixed = data.get("fixed", {})
    if not isinstance(fixed, dict):
        raise ConfigError("fixed", fixed, "must be a table ([fixed])")
    mc_spec = MonteCarloSpec(dispersion=disp, fixed=dict(fixed),
                             **{keys[k]: v for k, v in mc.items()})
    spec = DesignSpec(variables=variables, objective=objective, constraints=constraints,
                      montecarlo=mc_spec, cells=cells, **kw)
    if spec.scene_seed == spec.montecarlo.seed:
        raise ConfigError("design.scene_seed", spec.scene_seed,
                          "must differ from montecarlo.seed: the verification Monte Carlo "
                          "needs fresh samples, not the design scenes")
    model = spec.resolved_model()
    if model == "quarter" and any(c.name == "stability" for c in constraints):
        raise ConfigError("constraints.stability", "<table>", "needs the full 3-D model (a "
                          "symmetric drop cannot tip); set design.model = \"full\"")
    Solver(dt=spec.dt, t_end=spec.t_end, save_dt=spec.t_end).validate()
    return spec


def load_design_spec(path) -> DesignSpec:
    """Read and validate a design spec TOML (format in the README section "Design")."""
    path = Path(path)
    return design_spec_from_dict(read_toml(path, "spec"), base_dir=path.parent)


# ------------------------------------------------------------------------------- mapping

def risk_measure(values, measure: str, level: float = 0.9):
    """A risk measure of per-scene values (larger = worse): ``mean``, ``max``, ``cvar`` at
    ``level``: the mean of the worst (1 - level) N values, the boundary sample weighted by its
    fraction (Rockafellar-Uryasev's CVaR of the empirical distribution), differentiable almost
    everywhere (through a sort); or ``normal`` at ``level``: mean + z std (sample std, N - 1),
    z = Phi^-1(level), the level-quantile of a normal with the scenes' mean and spread, smooth
    in every scene's value."""
    values = jnp.asarray(values)
    if measure == "mean":
        return jnp.mean(values)
    if measure == "max":
        return jnp.max(values)
    n = values.shape[0]
    if measure == "normal":
        z = statistics.NormalDist().inv_cdf(level)
        mean = jnp.mean(values)
        var = jnp.sum((values - mean) ** 2) / max(n - 1, 1)
        pos = var > 0.0  # double where: sqrt's gradient stays finite for equal values
        sd = jnp.where(pos, jnp.sqrt(jnp.where(pos, var, 1.0)), 0.0)
        return mean + z * sd
    tail = (1.0 - level) * n
    worst = -jnp.sort(-values)  # descending
    w = jnp.clip(tail - jnp.arange(n, dtype=values.dtype), 0.0, 1.0) / tail
    return jnp.sum(w * worst)


def _cells_force(cell_size_m, foil_m, cells):
    return plateau_force(cell_size_m, foil_m, cells["section_diameter_mm"] * 1e-3,
                         cells["flow_stress_Pa"])


def gear_mass_kg(vehicle: Vehicle, cells: dict | None = None):
    """Gear-mass proxy [kg] for the parts the design variables change, all legs:

    * each honeycomb stage: foil density x relative density x section area x block length.
      Relative density of a hexagonal honeycomb 8/(3 sqrt 3) t/D, with t/D from the plateau
      force by inverting Wierzbicki, t/D = (F / (A 6.6 sigma_0))^(3/5); block length = the
      stage's crush stroke (x_L2, x_L4 - x_L3) / 0.75 (usable stroke fraction);
    * the pair of auxiliary struts: steel tubes of axial stiffness k_a / 2 each over their rest
      length L: mass = rho L (k L / E) = rho k_a L^2 / E for the pair.

    The main strut (fixed length) and body are not counted. With the paper's gear: 0.02 kg of
    honeycomb and 0.81 kg of auxiliary struts per leg; the struts dominate.
    """
    cells = PAPER_CELLS if cells is None else cells
    hc, leg = vehicle.honeycomb, vehicle.leg
    diameter = cells["section_diameter_mm"] * 1e-3
    area = math.pi * diameter**2 / 4.0

    def stage(force, stroke):
        t_over_d = foil_ratio(force, diameter, cells["flow_stress_Pa"])
        return RHO_FOIL_KG_M3 * HEX_DENSITY_FACTOR * t_over_d * area * stroke / STROKE_EFFICIENCY

    honey = stage(hc.F1, hc.x_L2) + stage(hc.F2, hc.x_L4 - hc.x_L3)
    aux = RHO_STEEL_KG_M3 * leg.k_a * leg.L_a0_pair**2 / E_STEEL_PA
    return vehicle.n_legs * (honey + aux)


def apply_design(vehicle: Vehicle, values: dict, cells: dict | None = None) -> Vehicle:
    """``vehicle`` with design variables set (``values``: TOML name -> SI value).

    Plateau forces keep the elastic strokes: k_b1 = F1 / x_L1 and k_b3 = (F2 - F1) / (x_L3 -
    x_L2) with the baseline's x_L1 and x_L3 - x_L2. Cell variables set F1 / F2 by Wierzbicki with
    ``cells`` (flow stress, section, and the cells that are not designed)."""
    cells = PAPER_CELLS if cells is None else cells
    hc, leg = vehicle.honeycomb, vehicle.leg
    x_l1 = hc.F1 / hc.k_b1
    dx3 = (hc.F2 - hc.F1) / hc.k_b3
    F1, F2 = values.get("F1_N", hc.F1), values.get("F2_N", hc.F2)
    if any(k in values for k in _CELL_VARS):
        si = {k: values.get(k, cells[k] * 1e-3) for k in _CELL_VARS}
        F1 = _cells_force(si["primary_cell_size_mm"], si["primary_foil_thickness_mm"], cells)
        F2 = _cells_force(si["secondary_cell_size_mm"], si["secondary_foil_thickness_mm"], cells)
    new_hc = (F1, F1 / x_l1, F2, (F2 - F1) / dx3, values.get("x_L2_mm", hc.x_L2),
              values.get("x_L4_mm", hc.x_L4))
    vehicle = eqx.tree_at(lambda v: (v.honeycomb.F1, v.honeycomb.k_b1, v.honeycomb.F2,
                                     v.honeycomb.k_b3, v.honeycomb.x_L2, v.honeycomb.x_L4),
                          vehicle, tuple(jnp.asarray(x, jnp.float64) for x in new_hc))
    return eqx.tree_at(lambda v: (v.leg.k_a, v.leg.theta_b, v.leg.R), vehicle,
                       tuple(jnp.asarray(x, jnp.float64) for x in (
                           values.get("k_a_N_per_m", leg.k_a),
                           values.get("theta_b_deg", leg.theta_b), values.get("R_m", leg.R))))


def _baseline_value(vehicle: Vehicle, name: str, cells: dict) -> float:
    hc, leg = vehicle.honeycomb, vehicle.leg
    si = {"F1_N": hc.F1, "F2_N": hc.F2, "x_L2_mm": hc.x_L2, "x_L4_mm": hc.x_L4,
          "k_a_N_per_m": leg.k_a, "theta_b_deg": leg.theta_b, "R_m": leg.R}
    if name in si:
        return float(si[name])
    return cells[name] * 1e-3


class DesignProblem:
    """The compiled robust design problem: design variables <-> unconstrained ``z``, the fixed
    scenes, and ``evaluate(z)`` -> measures, their Jacobian and per-scene outcomes."""

    def __init__(self, spec: DesignSpec, vehicle: Vehicle | None = None):
        self.spec = spec
        self.vehicle = validate_vehicle(paper_vehicle() if vehicle is None else vehicle)
        self.model = spec.resolved_model()
        self.solver = Solver(dt=spec.dt, t_end=spec.t_end, save_dt=spec.t_end).validate()
        self.variables = list(spec.variables)
        self.names = spec.names
        self.cells = spec.cells
        mc = spec.montecarlo
        scene_spec = MonteCarloSpec(dispersion=mc.dispersion, fixed=mc.fixed, n=spec.n_scenes,
                                    seed=spec.scene_seed, dt=spec.dt, t_end=spec.t_end,
                                    model=self.model)
        self.scenes, self.scene_inputs = sample_scenes(scene_spec, 0, spec.n_scenes,
                                                       self.vehicle.n_legs)
        self.scenes.validate(self.vehicle.n_legs)
        self._check_bounds()
        self.z0 = self.to_z({v.name: (v.start * v.to_si if v.start is not None else
                                      _baseline_value(self.vehicle, v.name, self.cells))
                             for v in self.variables}, check=True)
        self._fn = jax.jit(self._measures)
        self._jac = jax.jit(self._measures_and_jac)

    # --- variables
    def _check_bounds(self):
        """Refuse bound boxes that could produce an invalid vehicle (the orderings the
        honeycomb and leg need), naming the bound and the rule."""
        hc, leg = self.vehicle.honeycomb, self.vehicle.leg
        b = {v.name: (v.low * v.to_si, v.high * v.to_si) for v in self.variables}
        x_l1 = float(hc.F1 / hc.k_b1)
        dx3 = float((hc.F2 - hc.F1) / hc.k_b3)
        if any(n in b for n in _CELL_VARS):
            c = {n: (self.cells[n] * 1e-3,) * 2 for n in _CELL_VARS} | b
            f1_max = float(_cells_force(c["primary_cell_size_mm"][0],
                                        c["primary_foil_thickness_mm"][1], self.cells))
            f2_min = float(_cells_force(c["secondary_cell_size_mm"][1],
                                        c["secondary_foil_thickness_mm"][0], self.cells))
            if not f2_min > ORDER_RATIO * f1_max:
                raise ConfigError("variables.secondary_cell_size_mm.high",
                                  c["secondary_cell_size_mm"][1] * 1e3,
                                  f"the cell bounds allow F2 = {f2_min:.4g} N <= {ORDER_RATIO} "
                                  f"x F1 = {ORDER_RATIO * f1_max:.4g} N; the secondary stage "
                                  "must be stronger than the primary over the whole box")
        else:
            f1_hi = b.get("F1_N", (float(hc.F1),) * 2)[1]
            f2_hi = b.get("F2_N", (float(hc.F2),) * 2)[1]
            if not f2_hi > ORDER_RATIO * f1_hi:
                key = "F2_N.high" if "F2_N" in b else "F1_N.high"
                raise ConfigError(f"variables.{key}", (f2_hi if "F2_N" in b else f1_hi),
                                  f"F2 must be able to exceed {ORDER_RATIO} x F1 over the whole "
                                  f"box: F2 max {f2_hi:.4g} N vs F1 max {f1_hi:.4g} N")
        if "x_L2_mm" in b and b["x_L2_mm"][0] <= x_l1:
            raise ConfigError("variables.x_L2_mm.low", b["x_L2_mm"][0] * 1e3,
                              f"must exceed x_L1 = {x_l1 * 1e3:.4g} mm")
        x2_hi = b.get("x_L2_mm", (float(hc.x_L2),) * 2)[1]
        x4_hi = b.get("x_L4_mm", (float(hc.x_L4),) * 2)[1]
        if not x4_hi > x2_hi + dx3 + ORDER_GAP_M:
            key = "x_L4_mm.high" if "x_L4_mm" in b else "x_L2_mm.high"
            raise ConfigError(f"variables.{key}", (x4_hi if "x_L4_mm" in b else x2_hi) * 1e3,
                              f"x_L4 must be able to exceed x_L2 + (x_L3 - x_L2) + 1 mm over "
                              f"the whole box (x_L2 max {x2_hi * 1e3:.4g} mm, x_L4 max "
                              f"{x4_hi * 1e3:.4g} mm)")
        if x4_hi >= float(leg.L_h0):
            raise ConfigError("variables.x_L4_mm.high", x4_hi * 1e3,
                              f"must be shorter than the main strut, L_h0 = "
                              f"{float(leg.L_h0) * 1e3:.4g} mm")
        if "theta_b_deg" in b:
            lo, hi = b["theta_b_deg"]
            if not (0 < lo and hi < math.pi / 2):
                raise ConfigError("variables.theta_b_deg", f"[{lo / _DEG:g}, {hi / _DEG:g}]",
                                  "must lie in (0, 90) deg")
            if not float(leg.L_h0) * math.sin(lo) > 1.05 * float(leg.H2):
                raise ConfigError("variables.theta_b_deg.low", lo / _DEG,
                                  "L_h0 sin theta_b must exceed 1.05 H2 (the leg triangle "
                                  "degenerates)")
        if "R_m" in b and not b["R_m"][0] > 0:
            raise ConfigError("variables.R_m.low", b["R_m"][0], "must be > 0")
        for n in ("k_a_N_per_m", *_FORCE_VARS, *_CELL_VARS):
            if n in b and not b[n][0] > 0:
                raise ConfigError(f"variables.{n}.low", b[n][0] / VARIABLES[n][1], "must be > 0")

    def _bounds(self, vals: dict, v: DesignVariable):
        lo, hi = v.low * v.to_si, v.high * v.to_si
        hc = self.vehicle.honeycomb
        if v.name == "F2_N":  # coupled: F2 >= ORDER_RATIO F1
            lo = jnp.maximum(lo, ORDER_RATIO * vals.get("F1_N", hc.F1))
        elif v.name == "x_L4_mm":  # coupled: x_L4 >= x_L3 + gap
            dx3 = (hc.F2 - hc.F1) / hc.k_b3
            lo = jnp.maximum(lo, vals.get("x_L2_mm", hc.x_L2) + dx3 + ORDER_GAP_M)
        return lo, hi

    def from_z(self, z) -> dict:
        """Design values (SI) from the unconstrained coordinates, through the bounded smooth
        transforms (in declaration order, so coupled bounds see F1 and x_L2 first)."""
        vals: dict = {}
        order = sorted(range(len(self.variables)),
                       key=lambda i: self.variables[i].name in ("F2_N", "x_L4_mm"))
        for i in order:
            v = self.variables[i]
            lo, hi = self._bounds(vals, v)
            s = jax.nn.sigmoid(z[i])
            if v.scale == "log":
                vals[v.name] = jnp.exp(jnp.log(lo) + (jnp.log(hi) - jnp.log(lo)) * s)
            else:
                vals[v.name] = lo + (hi - lo) * s
        return vals

    def to_z(self, values: dict, check: bool = False) -> np.ndarray:
        """Unconstrained coordinates of design values (SI)."""
        z = np.zeros(len(self.variables))
        vals = {}
        order = sorted(range(len(self.variables)),
                       key=lambda i: self.variables[i].name in ("F2_N", "x_L4_mm"))
        for i in order:
            v = self.variables[i]
            lo, hi = (float(x) for x in self._bounds(vals, v))
            x = float(values[v.name])
            if v.scale == "log":
                frac = (math.log(x) - math.log(lo)) / (math.log(hi) - math.log(lo))
            else:
                frac = (x - lo) / (hi - lo)
            if check and not 1e-6 < frac < 1 - 1e-6:
                raise ConfigError(f"variables.{v.name}", x / v.to_si,
                                  f"the start (baseline) value must lie strictly inside the "
                                  f"bounds [{lo / v.to_si:.6g}, {hi / v.to_si:.6g}] "
                                  f"(give variables.{v.name}.start or widen the bounds)")
            frac = min(max(frac, 1e-12), 1 - 1e-12)
            z[i] = math.log(frac / (1 - frac))
            vals[v.name] = x
        return z

    def vehicle_at(self, z) -> Vehicle:
        return apply_design(self.vehicle, self.from_z(z), self.cells)

    # --- outcomes
    def _per_scene(self, veh):
        model = MODELS[self.model]
        _, s = landings(veh, self.scenes, self.solver, model)
        legmax = model.leg_max

        out = dict(peak_body_accel_mps2=s["peak_body_accel_mps2"],
                   max_stroke_m=legmax(s["max_stroke_m"]),
                   slip_distance_m=legmax(s["slip_distance_m"]),
                   peak_honeycomb_force_N=legmax(s["peak_honeycomb_force_N"]),
                   failed=verdict(s, veh, self.solver, model) != int(Result.SUCCESSFUL),
                   tipped=s["tipped"])
        if "peak_margin_deficit_m" in s:
            out["min_stability_margin_m"] = -s["peak_margin_deficit_m"]
        return out

    def _badness(self, c: Constraint, veh, per):
        if c.name == "stroke":
            return per["max_stroke_m"] - (veh.honeycomb.x_L4 - c.threshold)
        if c.name == "stability":
            return c.threshold - per["min_stability_margin_m"]
        return per["slip_distance_m"] - c.threshold

    def _measures(self, z):
        """(measures [objective measure, gear mass, g_1..g_m], per-scene outcomes)."""
        veh = self.vehicle_at(z)
        per = self._per_scene(veh)
        ob = self.spec.objective
        vec = [risk_measure(per["peak_body_accel_mps2"], ob.measure, ob.level),
               gear_mass_kg(veh, self.cells)]
        for c in self.spec.constraints:
            vec.append(risk_measure(self._badness(c, veh, per), c.measure, c.level) / c.scale)
        return jnp.stack(vec), per

    def _measures_and_jac(self, z):
        def f(z):
            vec, per = self._measures(z)
            return vec, (vec, per)

        jac, (vec, per) = jax.jacfwd(f, has_aux=True)(z)
        return vec, jac, per

    def evaluate(self, z, jacobian: bool = True):
        """``(measures, Jacobian d measures / d z or None, per-scene outcomes)``, numpy.
        ``measures`` = [objective's risk measure, gear mass proxy [kg], g_1 .. g_m]."""
        z = jnp.asarray(z, jnp.float64)
        if jacobian:
            vec, jac, per = self._jac(z)
            jac = np.asarray(jac)
        else:
            vec, per = self._fn(z)
            jac = None
        return np.asarray(vec), jac, {k: np.asarray(v) for k, v in per.items()}


# ------------------------------------------------------------------------------- optimiser

def _toml_values(problem: DesignProblem, z) -> dict:
    vals = problem.from_z(jnp.asarray(z))
    return {n: float(vals[n]) / VARIABLES[n][1] for n in problem.names}


@dataclass
class DesignResult:
    """Outcome of ``optimise_design``: status, the design (TOML units), the designed and the
    baseline vehicle, histories, measures on the design scenes before/after, and (after
    ``verify_design``) the independent Monte Carlo check."""

    problem: DesignProblem
    status: str  # "feasible" or "infeasible"
    z: np.ndarray
    values: dict
    start_values: dict
    vehicle: Vehicle
    history: list
    at_start: dict
    at_design: dict
    violated: dict
    wall_s: float
    compile_s: float
    multipliers: list
    penalty: float
    best_iteration: int = 0  # the iteration whose iterate is returned
    verification: dict | None = None
    mc_before: object = None
    mc_after: object = None

    @property
    def spec(self) -> DesignSpec:
        return self.problem.spec

    @property
    def baseline(self) -> Vehicle:
        return self.problem.vehicle

    def to_toml(self) -> str:
        """The designed vehicle as a config TOML (``jaxland simulate --config`` loads it)."""
        shown = ", ".join(f"{k} = {v:.6g}" for k, v in self.values.items())
        lines = [f"# jaxland design ({self.status}): {shown}",
                 "# (k_b1 and k_b3 follow F1 and F2 so that x_L1 and x_L3 - x_L2 stay at the "
                 "baseline's)"]
        if any(k in self.values for k in _CELL_VARS):
            cells = {**self.spec.cells, **self.values}
            lines.append("# honeycomb cells (Wierzbicki, F1_N / F2_N below derive from them): "
                         + ", ".join(f"{k} = {cells[k]:.6g}" for k in _CELL_VARS))
        return "\n".join(lines) + "\n" + vehicle_to_toml(self.vehicle)

    def report(self) -> dict:
        spec, prob = self.spec, self.problem
        return dict(
            status=self.status,
            violated=self.violated,
            model=prob.model,
            gradient="jax.jacfwd through the vmapped batch of landings (forward mode)",
            method=("augmented Lagrangian (Powell-Hestenes-Rockafellar) for inequalities, inner "
                    "steps optax.clip_by_global_norm + optax.scale_by_adam with a scheduled "
                    "step in the unconstrained coordinates; bounds by sigmoid (linear) or "
                    "sigmoid-of-log transforms"),
            optimiser=dict(learning_rate=spec.learning_rate, lr_schedule=spec.lr_schedule,
                           lr_final=spec.lr_final, clip_norm=spec.clip_norm,
                           adam_b1=spec.adam_b1, adam_b2=spec.adam_b2,
                           outer_every=spec.outer_every, penalty=spec.penalty,
                           penalty_growth=spec.penalty_growth,
                           feasibility_tol=spec.feasibility_tol, patience=spec.patience,
                           stop_rtol=spec.stop_rtol),
            best_iteration=self.best_iteration,
            smoothing=("none: peaks are the integrator's running maxima at every step, "
                       "differentiated at the step where they occur"),
            variables=[dict(name=v.name, unit=VARIABLES[v.name][0], low=v.low, high=v.high,
                            scale=v.scale, start=self.start_values[v.name],
                            design=self.values[v.name]) for v in prob.variables],
            objective=dict(quantity="peak_body_accel_mps2", measure=spec.objective.measure,
                           level=spec.objective.level, mass_weight=spec.objective.mass_weight),
            constraints=[dict(name=c.name, rule=CONSTRAINTS[c.name][3],
                              threshold_si=c.threshold, measure=c.measure, level=c.level,
                              scale_si=c.scale) for c in spec.constraints],
            scenes=dict(n=spec.n_scenes, seed=spec.scene_seed, dt_s=spec.dt,
                        t_end_s=spec.t_end,
                        dispersion={k: vars(v) for k, v in spec.montecarlo.dispersion.items()},
                        fixed=spec.montecarlo.fixed),
            iterations=len(self.history) - 1,
            wall_s=self.wall_s,
            compile_s=self.compile_s,
            multipliers=self.multipliers,
            penalty=self.penalty,
            at_start=self.at_start,
            at_design=self.at_design,
            verification=self.verification,
            history=self.history,
        )

    def to_json(self, path) -> Path:
        return atomic_write_text(path, json.dumps(self.report(), indent=2, default=_py) + "\n")

    def plot(self, out_dir) -> list[Path]:
        from ._plots_design import plot_design

        return plot_design(self, Path(out_dir))


def _summaries(problem: DesignProblem, vec, per, z) -> dict:
    spec = problem.spec
    out = dict(objective_measure_mps2=float(vec[0]), gear_mass_kg=float(vec[1]),
               values=_toml_values(problem, z),
               mean_peak_body_accel_mps2=float(np.mean(per["peak_body_accel_mps2"])),
               max_peak_body_accel_mps2=float(np.max(per["peak_body_accel_mps2"])),
               max_stroke_m=float(np.max(per["max_stroke_m"])),
               x_L4_m=float(problem.vehicle_at(jnp.asarray(z)).honeycomb.x_L4),
               n_failed=int(np.sum(per["failed"])), n_tipped=int(np.sum(per["tipped"])))
    if "min_stability_margin_m" in per:
        out["min_stability_margin_m"] = float(np.min(per["min_stability_margin_m"]))
    out["constraints"] = {c.name: dict(g=float(vec[2 + i]), value_si=float(vec[2 + i]) * c.scale)
                          for i, c in enumerate(spec.constraints)}
    return out


def step_schedule(spec: DesignSpec, n_iter: int):
    """The optax schedule of the inner step over ``n_iter`` iterations: ``cosine`` decay or
    ``exponential`` decay from ``learning_rate`` to ``lr_final`` x ``learning_rate``, or
    ``constant``."""
    import optax

    lr, n = spec.learning_rate, max(int(n_iter), 1)
    if spec.lr_schedule == "cosine":
        return optax.cosine_decay_schedule(lr, decay_steps=n, alpha=spec.lr_final)
    if spec.lr_schedule == "exponential":
        return optax.exponential_decay(lr, transition_steps=n, decay_rate=spec.lr_final)
    return optax.constant_schedule(lr)


def optimise_design(spec: DesignSpec, vehicle: Vehicle | None = None, *,
                    iterations: int | None = None, progress=None,
                    problem: DesignProblem | None = None) -> DesignResult:
    """Run the augmented-Lagrangian design loop (module docstring); ``progress(dict)`` is called
    once per iteration. Raises ``SimulationError`` if a landing fails at the start point."""
    import optax

    from ._errors import SimulationError

    prob = DesignProblem(spec, vehicle) if problem is None else problem
    n_iter = spec.iterations if iterations is None else int(iterations)
    if n_iter < 0:
        raise ConfigError("iterations", n_iter, "must be >= 0")
    n_con = len(spec.constraints)
    limit = float(stable_step(prob.vehicle_at(jnp.asarray(prob.z0))))
    if spec.dt > limit:
        raise ConfigError("design.dt_s", spec.dt, f"exceeds the stability limit {limit:.3g} s of "
                          "the start design")
    t0 = time.perf_counter()
    z = np.asarray(prob.z0, dtype=float).copy()
    vec, jac, per = prob.evaluate(z)
    compile_s = time.perf_counter() - t0
    if np.any(per["failed"]) or not np.all(np.isfinite(vec)):
        raise SimulationError(
            f"{int(np.sum(per['failed']))} of {spec.n_scenes} design scenes fail numerically at "
            f"the start design (non-finite state or energy ledger); reduce design.dt_s")
    a0, m0 = max(float(vec[0]), 1e-12), max(float(vec[1]), 1e-12)
    w = spec.objective.mass_weight
    start = _summaries(prob, vec, per, z)
    lam, rho = np.zeros(n_con), float(spec.penalty)
    opt = optax.chain(
        optax.clip_by_global_norm(spec.clip_norm) if spec.clip_norm > 0 else optax.identity(),
        optax.scale_by_adam(b1=spec.adam_b1, b2=spec.adam_b2))
    schedule = step_schedule(spec, n_iter)
    # optax mixes int32 counters with floats: allow the standard promotion even where the
    # caller made it strict (as the test suite does)
    with jax.numpy_dtype_promotion("standard"):
        state = opt.init(jnp.asarray(z))
    history: list = []
    best = None  # (J, z, vec, per, iteration)
    least_bad = None  # (max violation, z, vec, per, iteration)
    prev_viol = math.inf
    lr_factor, n_rejected, best_improved = 1.0, 0, 0
    z_prev, state_prev = z, state
    t_loop = time.perf_counter()
    for it in range(n_iter + 1):
        if it > 0:
            vec, jac, per = prob.evaluate(z)
        bad = bool(np.any(per["failed"])) or not (np.all(np.isfinite(vec))
                                                   and np.all(np.isfinite(jac)))
        if bad:  # a trial design whose landings fail: step back with a shorter step
            n_rejected += 1
            lr_factor *= 0.5
            z, state = z_prev, state_prev
            vec, jac, per = prob.evaluate(z)
        g = vec[2:]
        J = vec[0] / a0 + w * vec[1] / m0
        gJ = jac[0] / a0 + w * jac[1] / m0
        shifted = np.maximum(0.0, lam + rho * g)
        L = J + float(np.sum((shifted**2 - lam**2) / (2.0 * rho)))
        gL = gJ + (shifted[:, None] * jac[2:]).sum(axis=0) if n_con else gJ
        viol = float(np.max(np.maximum(g, 0.0))) if n_con else 0.0
        if viol <= spec.feasibility_tol and (best is None or J < best[0]):
            if best is None or J < best[0] * (1.0 - spec.stop_rtol):
                best_improved = it
            best = (J, z.copy(), vec, per, it)
        if least_bad is None or viol < least_bad[0]:
            least_bad = (viol, z.copy(), vec, per, it)
        rec = dict(iteration=it, objective=float(J), objective_measure_mps2=float(vec[0]),
                   gear_mass_kg=float(vec[1]), lagrangian=L,
                   constraints={c.name: float(g[i]) for i, c in enumerate(spec.constraints)},
                   multipliers=lam.tolist(), penalty=rho, max_violation=viol,
                   grad_norm=float(np.linalg.norm(gL)), rejected=bad,
                   values=_toml_values(prob, z), wall_s=time.perf_counter() - t_loop)
        history.append(rec)
        if progress:
            progress(rec)
        if it == n_iter:
            break
        if spec.patience and best is not None and it - best_improved >= spec.patience:
            break  # the best feasible J has not improved by stop_rtol for `patience` iterations
        if it > 0 and it % spec.outer_every == 0 and n_con:
            lam = np.maximum(0.0, lam + rho * g)
            if viol > 0.5 * prev_viol:
                rho = min(rho * spec.penalty_growth, spec.penalty_max)
            prev_viol = viol
        z_prev, state_prev = z, state
        with jax.numpy_dtype_promotion("standard"):
            updates, state = opt.update(jnp.asarray(gL), state)
            lr = float(schedule(it))
        z = z - lr * lr_factor * np.asarray(updates)
    wall = time.perf_counter() - t0
    if best is not None:
        status, (_, z_out, vec_out, per_out, it_out) = "feasible", best
        violated = {}
    else:
        status = "infeasible"
        _, z_out, vec_out, per_out, it_out = least_bad
        violated = {c.name: dict(g=float(vec_out[2 + i]),
                                 value_si=float(vec_out[2 + i]) * c.scale,
                                 rule=CONSTRAINTS[c.name][3])
                    for i, c in enumerate(spec.constraints)
                    if vec_out[2 + i] > spec.feasibility_tol}
    veh = validate_vehicle(prob.vehicle_at(jnp.asarray(z_out)))
    return DesignResult(
        problem=prob, status=status, z=z_out, values=_toml_values(prob, z_out),
        start_values=_toml_values(prob, prob.z0), vehicle=veh, history=history,
        at_start=start, at_design=_summaries(prob, vec_out, per_out, z_out), violated=violated,
        wall_s=wall, compile_s=compile_s, multipliers=lam.tolist(), penalty=rho,
        best_iteration=it_out)


# ------------------------------------------------------------------------------- verification

def _judge(res, vehicle: Vehicle, spec: DesignSpec) -> dict:
    ok = res.failure == int(Result.SUCCESSFUL)
    o = res.outputs
    n = int(ok.sum())
    stroke = o["max_stroke_m"].max(axis=1)[ok]
    accel = o["peak_body_accel_mps2"][ok]
    out = dict(n=int(res.failure.size), n_ok=n, n_failed=res.summary["n_failed"],
               seed=res.summary["seed"], model=res.summary["model"],
               peak_body_accel_mps2=percentiles(accel),
               objective_measure_mps2=float(risk_measure(jnp.asarray(accel),
                                                         spec.objective.measure,
                                                         spec.objective.level)) if n else None,
               max_stroke_m=percentiles(stroke),
               slip_distance_m=percentiles(o["slip_distance_m"].max(axis=1)[ok]),
               tip_over=res.summary["tip_over"], bottoming=res.summary["bottoming"],
               wall_s=res.summary["wall_s"])
    if "min_stability_margin_m" in o:
        out["min_stability_margin_m"] = percentiles(o["min_stability_margin_m"][ok])
    viol = {}
    for c in spec.constraints:
        if c.name == "stroke":
            b = stroke - (float(vehicle.honeycomb.x_L4) - c.threshold)
        elif c.name == "stability":
            b = c.threshold - o["min_stability_margin_m"][ok]
        else:
            b = o["slip_distance_m"].max(axis=1)[ok] - c.threshold
        k = int(np.sum(b > 0))
        viol[c.name] = dict(count=k, n=n, probability=k / max(n, 1),
                            ci95_wilson=wilson_interval(k, n))
    out["constraint_violations"] = viol
    return out


def verify_design(result: DesignResult, *, n: int | None = None, seed: int | None = None,
                  progress: bool = False) -> dict:
    """Re-check the baseline and the design with an independent Monte Carlo: fresh samples
    (``montecarlo.seed``, never the design's ``scene_seed``), the spec's verification ``dt_s``
    and ``t_end_s``, unsmoothed outcomes. Stores and returns the before/after comparison."""
    spec = result.spec
    mc = spec.montecarlo
    seed = mc.seed if seed is None else seed
    if seed == spec.scene_seed:
        raise ConfigError("seed", seed, "must differ from design.scene_seed (fresh samples)")
    vspec = MonteCarloSpec(dispersion=mc.dispersion, fixed=mc.fixed,
                           n=mc.n if n is None else int(n), seed=seed, dt=mc.dt, t_end=mc.t_end,
                           model=result.problem.model)
    before = run_montecarlo(vspec, result.baseline, progress=progress)
    after = run_montecarlo(vspec, result.vehicle, progress=progress)
    result.mc_before, result.mc_after = before, after
    result.verification = dict(
        n=vspec.n, seed=seed, dt_s=vspec.dt, t_end_s=vspec.t_end, model=vspec.model,
        smoothing="none (the optimisation used none either)",
        before=_judge(before, result.baseline, spec), after=_judge(after, result.vehicle, spec))
    return result.verification
