"""The design spec: design variables, objective, constraints, the dispersion and the optimiser's
settings, read from a TOML-shaped dict and validated field by field (docs/design.md)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from .._checks import (
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    Choice,
    Number,
    Text,
    known_keys,
    parse_table,
    spec_field,
)
from .._config import PAPER_CELLS
from .._errors import ConfigError
from .._montecarlo import MODEL_CHOICE, MonteCarloSpec, montecarlo_spec_from_dict
from .._montecarlo._spec import SEED_HIGH
from .._solvers import FIXED_STEP_METHODS, check_spec_steps
from .._toml import read_toml

_DEG = math.pi / 180.0


class VariableInfo(NamedTuple):
    unit: str  # unit of the TOML name
    to_si: float  # TOML -> SI factor
    scale: str  # default transform: "linear" or "log"
    doc: str


VARIABLES = {
    "F1_N": VariableInfo("N", 1.0, "log", "plateau force of the primary honeycomb (k_b1 keeps "
                         "x_L1)"),
    "F2_N": VariableInfo("N", 1.0, "log", "plateau force of the secondary honeycomb (k_b3 "
                         "keeps x_L3 - x_L2); its lower bound is at least 1.02 F1"),
    "primary_cell_size_mm": VariableInfo("mm", 1e-3, "log",
                                         "cell size D of the primary honeycomb"),
    "primary_foil_thickness_mm": VariableInfo("mm", 1e-3, "log",
                                              "foil thickness t of the primary honeycomb"),
    "secondary_cell_size_mm": VariableInfo("mm", 1e-3, "log",
                                           "cell size D of the secondary honeycomb"),
    "secondary_foil_thickness_mm": VariableInfo("mm", 1e-3, "log",
                                                "foil thickness t of the secondary honeycomb"),
    "x_L2_mm": VariableInfo("mm", 1e-3, "linear", "stroke at the end of the primary stage"),
    "x_L4_mm": VariableInfo("mm", 1e-3, "linear", "available stroke, end of the secondary "
                            "stage; its lower bound is at least x_L3 + 1 mm"),
    "k_a_N_per_m": VariableInfo("N/m", 1.0, "log",
                                "axial stiffness of the pair of auxiliary struts"),
    "theta_b_deg": VariableInfo("deg", _DEG, "linear", "main strut angle below the horizontal "
                                "(sets the footprint radius R + L_h0 cos theta_b)"),
    "R_m": VariableInfo("m", 1.0, "linear",
                        "radial offset of the strut joints (moves the footprint)"),
}
CELL_VARS = ("primary_cell_size_mm", "primary_foil_thickness_mm", "secondary_cell_size_mm",
             "secondary_foil_thickness_mm")
FORCE_VARS = ("F1_N", "F2_N")
ORDER_RATIO = 1.02  # F2 >= 1.02 F1 (a distinct secondary stage)
ORDER_GAP_M = 1e-3  # x_L4 >= x_L3 + 1 mm

MEASURES = ("mean", "cvar", "max", "normal")
SCHEDULES = ("cosine", "exponential", "constant")


class ConstraintInfo(NamedTuple):
    key: str  # the threshold's TOML key
    to_si: float  # its TOML -> SI factor
    scale: float  # default normalisation [SI]
    rule: str
    outcome: str  # the per-scene outcome it reads


CONSTRAINTS = {
    "stroke": ConstraintInfo("margin_mm", 1e-3, 0.01,
                             "max stroke (any leg) <= x_L4 - margin: no bottoming out",
                             "max_stroke_m"),
    "stability": ConstraintInfo("min_margin_m", 1.0, 0.1, "minimum stability margin >= "
                                "threshold: no tip-over (full 3-D model)",
                                "min_stability_margin_m"),
    "slip": ConstraintInfo("max_slip_mm", 1e-3, 0.01, "foot slip distance (any leg) <= limit",
                           "slip_distance_m"),
}


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
        return VARIABLES[self.name].to_si


@dataclass(frozen=True)
class Objective:
    """Peak body acceleration under a risk measure, plus ``mass_weight`` x the normalised gear
    mass proxy."""

    measure: str = "cvar"
    level: float = 0.9
    mass_weight: float = 0.0


# The largest violation probability the verification accepts for a measure = "max" constraint
# (its violation_tolerance): met when no verification landing violates it and the 95 % Wilson
# upper bound on the probability, 3.84 / (n + 3.84) at none in n, is at most this. At 1 % that
# takes 381 landings, within montecarlo.n's default of 1000.
VIOLATION_TOLERANCE = 0.01


@dataclass(frozen=True)
class Constraint:
    """``name`` in ``CONSTRAINTS``; ``threshold`` in SI; risk measure over the scenes;
    ``scale`` [SI] normalises the constraint for the augmented Lagrangian;
    ``violation_tolerance``: for ``measure = "max"``, the largest violation probability whose
    95 % upper bound the verification accepts (``VIOLATION_TOLERANCE``)."""

    name: str
    threshold: float
    measure: str = "max"
    level: float = 0.9
    scale: float = 0.01
    violation_tolerance: float = VIOLATION_TOLERANCE

    def badness(self, per: dict, x_L4):
        """Per-scene violation (positive = violated, SI) from the per-scene outcomes ``per``
        (worst-leg ``max_stroke_m`` and ``slip_distance_m``, ``min_stability_margin_m``) and
        the design's available stroke ``x_L4`` [m]."""
        value = per[CONSTRAINTS[self.name].outcome]
        if self.name == "stroke":
            return value - (x_L4 - self.threshold)
        if self.name == "stability":
            return self.threshold - value
        return value - self.threshold


_COUNT = Number(integer=True, lo=1, hi=100000)


@dataclass
class DesignSpec:
    """Everything a design run needs (see ``design_spec_from_dict`` for the TOML form; the
    ``[design]`` table's keys and rules are the fields' metadata)."""

    variables: list
    objective: Objective
    constraints: list
    montecarlo: MonteCarloSpec  # the dispersion; its n, seed, dt, t_end drive the verification
    n_scenes: int = spec_field(16, toml="n_scenes", check=_COUNT)
    scene_seed: int = spec_field(0, toml="scene_seed",
                                 check=Number(integer=True, lo=0, hi=SEED_HIGH))
    iterations: int = spec_field(60, toml="iterations", check=Number(integer=True, lo=0,
                                                                     hi=100000))
    dt: float = spec_field(1e-5, toml="dt_s", check=POSITIVE)
    t_end: float = spec_field(0.5, toml="t_end_s", check=POSITIVE)
    model: str = spec_field("auto", toml="model", check=MODEL_CHOICE)
    # fixed-step method of the design landings (the verification runs euler at montecarlo.dt_s)
    method: str = spec_field("euler", toml="method", check=Choice(FIXED_STEP_METHODS))
    learning_rate: float = spec_field(0.1, toml="learning_rate", check=POSITIVE)
    outer_every: int = spec_field(10, toml="outer_every", check=_COUNT)
    penalty: float = spec_field(10.0, toml="penalty", check=POSITIVE)
    penalty_growth: float = spec_field(3.0, toml="penalty_growth", check=Number(lo=1.0))
    penalty_max: float = spec_field(1e4, toml="penalty_max", check=POSITIVE)
    feasibility_tol: float = spec_field(1e-3, toml="feasibility_tol", check=POSITIVE)
    adam_b1: float = spec_field(0.5, toml="adam_b1", check=FRACTION)
    adam_b2: float = spec_field(0.9, toml="adam_b2", check=FRACTION)
    # global-norm clip of the Lagrangian's gradient (0: none)
    clip_norm: float = spec_field(0.3, toml="clip_norm", check=NON_NEGATIVE)
    lr_schedule: str = spec_field("cosine", toml="lr_schedule", check=Choice(SCHEDULES))
    # final step / learning_rate
    lr_final: float = spec_field(0.02, toml="lr_final", check=Number(lo=0.0, lo_open=True,
                                                                     hi=1.0))
    # stop when the best feasible J has not improved by stop_rtol for this many iterations
    # (0: run all iterations)
    patience: int = spec_field(0, toml="patience", check=Number(integer=True, lo=0,
                                                                hi=100000))
    stop_rtol: float = spec_field(1e-3, toml="stop_rtol", check=POSITIVE)
    # after a verification that does not meet every constraint: re-optimise with its violating
    # landings added to the design scenes, at most this many times (0: verify only)
    verify_rounds: int = spec_field(2, toml="verify_rounds",
                                    check=Number(integer=True, lo=0, hi=10))
    # landings added per violated constraint and round (the worst first)
    verify_add: int = spec_field(4, toml="verify_add", check=Number(integer=True, lo=1, hi=100))
    # optimiser iterations of each re-optimisation (from the previous design)
    reoptimise_iterations: int = spec_field(15, toml="reoptimise_iterations",
                                            check=Number(integer=True, lo=1, hi=100000))
    cells: dict = field(default_factory=lambda: dict(PAPER_CELLS))
    # path of the baseline vehicle TOML (default: the paper's)
    vehicle: str | None = spec_field(None, toml="vehicle", check=Text("a path (string)"))

    @property
    def names(self) -> tuple:
        return tuple(v.name for v in self.variables)

    def resolved_model(self) -> str:
        """``design.model`` (not the verification's ``montecarlo.model``), or the smallest
        adequate model for the dispersion."""
        return dataclasses.replace(self.montecarlo, model=self.model).resolved_model("design")


def _measure(prefix, table) -> tuple[str, float]:
    measure = table.get("measure", "max" if prefix.startswith("constraints") else "cvar")
    Choice(MEASURES)(f"{prefix}.measure", measure)
    if measure in ("max", "mean") and "level" in table:
        raise ConfigError(f"{prefix}.level", table["level"], f"is not used by measure = "
                          f"{measure} (only cvar and normal take a level): leave it out")
    level = Number()(f"{prefix}.level", table.get("level", 0.9))
    if not 0.0 <= level < 1.0:
        raise ConfigError(f"{prefix}.level", level, "must be in [0, 1) (CVaR: the mean of the "
                          "worst 1 - level fraction of the scenes)")
    if measure == "normal" and not level > 0.0:
        raise ConfigError(f"{prefix}.level", level, "must be in (0, 1) for measure = normal "
                          "(the quantile mean + z_level std)")
    return measure, float(level)


def _variable(name: str, t) -> DesignVariable:
    if name not in VARIABLES:
        raise ConfigError(f"variables.{name}", "<table>",
                          f"unknown design variable; known: {', '.join(VARIABLES)}")
    known_keys(f"variables.{name}", t, ["low", "high", "scale", "start"])
    for k in ("low", "high"):
        if k not in t:
            raise ConfigError(f"variables.{name}.{k}", None, "is required (a bound in "
                              f"{VARIABLES[name].unit})")
    lo = Number()(f"variables.{name}.low", t["low"])
    hi = Number()(f"variables.{name}.high", t["high"])
    if not hi > lo:
        raise ConfigError(f"variables.{name}.high", hi, f"must exceed low = {lo:g}")
    scale = Choice(("linear", "log"))(f"variables.{name}.scale",
                                      t.get("scale", VARIABLES[name].scale))
    if scale == "log" and not lo > 0:
        raise ConfigError(f"variables.{name}.low", lo, "must be > 0 for scale = log")
    start = t.get("start")
    if start is not None:
        Number()(f"variables.{name}.start", start)
        if not lo < start < hi:
            raise ConfigError(f"variables.{name}.start", start,
                              f"must lie strictly inside (low, high) = ({lo:g}, {hi:g})")
    return DesignVariable(name, float(lo), float(hi), scale,
                          None if start is None else float(start))


def _constraint(name: str, t) -> Constraint:
    info = CONSTRAINTS[name]
    skey = "scale_" + info.key.rsplit("_")[-1]
    known_keys(f"constraints.{name}", t, [info.key, "measure", "level", skey,
                                          "violation_tolerance"])
    if info.key not in t:
        raise ConfigError(f"constraints.{name}.{info.key}", None, "is required")
    check = NON_NEGATIVE if name in ("stroke", "slip") else Number()
    thr = check(f"constraints.{name}.{info.key}", t[info.key])
    measure, level = _measure(f"constraints.{name}", t)
    scale = (POSITIVE(f"constraints.{name}.{skey}", t[skey]) * info.to_si if skey in t
             else info.scale)
    tol = VIOLATION_TOLERANCE
    if "violation_tolerance" in t:
        key = f"constraints.{name}.violation_tolerance"
        tol = Number()(key, t["violation_tolerance"])
        if not 0.0 < tol < 1.0:
            raise ConfigError(key, tol, "must be in (0, 1): the largest violation probability "
                              "the verification accepts")
        if measure != "max":
            raise ConfigError(key, tol, f'applies to measure = "max" only (measure = '
                              f'"{measure}" is judged by its 95 % bootstrap interval)')
    return Constraint(name, float(thr) * info.to_si, measure, level, float(scale), float(tol))


# [montecarlo] keys of a Monte Carlo spec that the verification sets itself, and why
VERIFICATION_FIXED = {
    "method": "the verification integrates with euler (design.method sets the design "
              "landings' integrator)",
    "model": "the verification runs the design's model (design.model)",
    "retry": "the verification always reruns its numerical failures",
    "early_stop": "the verification runs each landing to t_end_s and continues those it cuts "
                  "off",
    "ledger_check_s": "the verification checks the ledger at its model's default interval",
}


def design_spec_from_dict(data: dict, base_dir: Path | None = None) -> DesignSpec:
    """Build and validate a ``DesignSpec`` from a TOML-shaped dict (docs/design.md)."""
    known_keys("spec", data, ("design", "objective", "variables", "constraints", "cells",
                              "montecarlo", "dispersion", "fixed"))
    kw = parse_table(DesignSpec, "design", dict(data.get("design", {})))
    if "vehicle" in kw and base_dir is not None and not Path(kw["vehicle"]).is_absolute():
        kw["vehicle"] = str(base_dir / kw["vehicle"])

    obj = known_keys("objective", dict(data.get("objective", {})),
                     ["quantity", "measure", "level", "mass_weight"])
    if obj.get("quantity", "peak_body_accel_mps2") != "peak_body_accel_mps2":
        raise ConfigError("objective.quantity", obj["quantity"],
                          "must be peak_body_accel_mps2 (the overload)")
    measure, level = _measure("objective", obj)
    mass_weight = NON_NEGATIVE("objective.mass_weight", obj.get("mass_weight", 0.0))
    objective = Objective(measure, level, float(mass_weight))

    vtab = data.get("variables", {})
    if not isinstance(vtab, dict) or not vtab:
        raise ConfigError("variables", vtab, "give at least one [variables.<name>] table; "
                          f"known: {', '.join(VARIABLES)}")
    variables = [_variable(name, t) for name, t in vtab.items()]
    names = {v.name for v in variables}
    if names & set(FORCE_VARS) and names & set(CELL_VARS):
        raise ConfigError("variables", sorted(names & set(FORCE_VARS))[0],
                          "give plateau forces (F1_N, F2_N) or honeycomb cells "
                          "(*_cell_size_mm, *_foil_thickness_mm) as variables, not both")

    cells = dict(PAPER_CELLS)
    for k, v in known_keys("cells", data.get("cells", {}), list(PAPER_CELLS)).items():
        cells[k] = float(POSITIVE(f"cells.{k}", v))
        # the flow stress and section set the gear-mass proxy's honeycomb in every design; a
        # cell's size or foil only sets F1/F2, which only cell variables derive from cells
        if k in CELL_VARS and not names & set(CELL_VARS):
            raise ConfigError(f"cells.{k}", v, "sets a honeycomb cell, which only a design "
                              "with cell variables (*_cell_size_mm, *_foil_thickness_mm) uses; "
                              "here F1_N and F2_N are the variables' or the vehicle's")

    ctabs = known_keys("constraints", data.get("constraints", {}), list(CONSTRAINTS))
    constraints = [_constraint(name, t) for name, t in ctabs.items()]

    mc_spec = montecarlo_spec_from_dict(data, keys_excluded=VERIFICATION_FIXED)
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
    check_spec_steps("design", spec.dt, spec.t_end, spec.method)
    return spec


def load_design_spec(path) -> DesignSpec:
    """Read and validate a design spec TOML (docs/design.md)."""
    path = Path(path)
    return design_spec_from_dict(read_toml(path, "spec"), base_dir=path.parent)
