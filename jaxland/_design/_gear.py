"""The gear a design describes: design values on a vehicle, and the gear-mass proxy."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._config import PAPER_CELLS
from .._crush import foil_ratio, plateau_force
from .._errors import ConfigError
from .._params import Vehicle
from ._spec import CELL_VARS

# Gear-mass proxy constants (documented in ``gear_mass_kg``).
RHO_FOIL_KG_M3 = 2680.0  # Al 5052
RHO_STEEL_KG_M3 = 7850.0
E_STEEL_PA = 2.0e11
# relative density of a hexagonal honeycomb per unit t/D
HEX_DENSITY_FACTOR = 8.0 / (3.0 * math.sqrt(3.0))
STROKE_EFFICIENCY = 0.75  # usable crush stroke / block length


def cells_force(cell_size_m, foil_m, cells):
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

    The main strut (fixed length) and body are not counted. With the paper's gear: 0.08 kg of
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
    if any(k in values for k in CELL_VARS):
        si = {k: values.get(k, cells[k] * 1e-3) for k in CELL_VARS}
        F1 = cells_force(si["primary_cell_size_mm"], si["primary_foil_thickness_mm"], cells)
        F2 = cells_force(si["secondary_cell_size_mm"], si["secondary_foil_thickness_mm"], cells)
    new_hc = (F1, F1 / x_l1, F2, (F2 - F1) / dx3, values.get("x_L2_mm", hc.x_L2),
              values.get("x_L4_mm", hc.x_L4))
    vehicle = eqx.tree_at(lambda v: (v.honeycomb.F1, v.honeycomb.k_b1, v.honeycomb.F2,
                                     v.honeycomb.k_b3, v.honeycomb.x_L2, v.honeycomb.x_L4),
                          vehicle, tuple(jnp.asarray(x, jnp.float64) for x in new_hc))
    return eqx.tree_at(lambda v: (v.leg.k_a, v.leg.theta_b, v.leg.R), vehicle,
                       tuple(jnp.asarray(x, jnp.float64) for x in (
                           values.get("k_a_N_per_m", leg.k_a),
                           values.get("theta_b_deg", leg.theta_b), values.get("R_m", leg.R))))


CELLS_RTOL = 1e-3  # the cells' plateau forces against the baseline's: a force given to four
# digits (the paper's F1 5024.4 N, its cells' 5024.37 N)


def check_cells(vehicle: Vehicle, variables, cells: dict) -> None:
    """Refuse cell variables whose cells (``cells``: the spec's ``[cells]``, the paper's where
    not given) do not give the baseline vehicle's plateau forces: a cell variable sets both F1
    and F2 from the cells (``apply_design``), so the start would silently be another gear. A
    stage one of whose cell variables has a ``start`` starts where the spec says."""
    if not any(v.name in CELL_VARS for v in variables):
        return
    started = {v.name for v in variables if v.start is not None}
    hc = vehicle.honeycomb
    for stage, given in (("primary", hc.F1), ("secondary", hc.F2)):
        if {f"{stage}_cell_size_mm", f"{stage}_foil_thickness_mm"} & started:
            continue
        force = float(cells_force(cells[f"{stage}_cell_size_mm"] * 1e-3,
                                  cells[f"{stage}_foil_thickness_mm"] * 1e-3, cells))
        have = np.asarray(given, dtype=float)
        if not np.all(np.abs(have - force) <= CELLS_RTOL * np.abs(have)):
            name = "F1" if stage == "primary" else "F2"
            raise ConfigError(
                f"cells.{stage}_foil_thickness_mm", cells[f"{stage}_foil_thickness_mm"],
                f"the [cells] (the paper's where not given) give the {stage} plateau force "
                f"{force:.6g} N where the baseline vehicle has {name} = "
                f"{float(np.max(have)):.6g} N: a cell variable starts from these cells, so "
                "give the baseline's cells in [cells] (or the variable a start, or design "
                "F1_N and F2_N instead)")


def baseline_value(vehicle: Vehicle, name: str, cells: dict) -> float:
    hc, leg = vehicle.honeycomb, vehicle.leg
    si = {"F1_N": hc.F1, "F2_N": hc.F2, "x_L2_mm": hc.x_L2, "x_L4_mm": hc.x_L4,
          "k_a_N_per_m": leg.k_a, "theta_b_deg": leg.theta_b, "R_m": leg.R}
    if name in si:
        return float(si[name])
    return cells[name] * 1e-3
