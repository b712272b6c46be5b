"""Plateau (mean crush) force of a hexagonal aluminium honeycomb from its cell geometry.

Wierzbicki, T. (1983) "Crushing analysis of metal honeycombs", Int. J. Impact Engng 1(2),
157-174: mean crush stress sigma_m = 6.6 sigma_0 (t / D)^(5/3), with t the foil thickness, D the
cell size and sigma_0 the flow stress of the foil. The plateau force of a buffer of circular
section of diameter d is sigma_m pi d^2 / 4. Works on arrays and under grad, so a design can
move cell size and foil thickness (something one can buy) instead of the forces.
"""

from __future__ import annotations

import jax.numpy as jnp

WIERZBICKI_COEFF = 6.6


def wierzbicki_crush_stress(cell_size_m, foil_thickness_m, flow_stress_Pa):
    """Mean crush stress [Pa] of a hexagonal metal honeycomb (Wierzbicki 1983)."""
    return WIERZBICKI_COEFF * flow_stress_Pa * (foil_thickness_m / cell_size_m) ** (5.0 / 3.0)


def plateau_force(cell_size_m, foil_thickness_m, section_diameter_m, flow_stress_Pa):
    """Plateau force [N] of a honeycomb buffer of circular section (Wierzbicki 1983)."""
    area = jnp.pi * section_diameter_m**2 / 4.0
    return wierzbicki_crush_stress(cell_size_m, foil_thickness_m, flow_stress_Pa) * area


def foil_ratio(plateau_force_N, section_diameter_m, flow_stress_Pa):
    """The inverse: foil thickness over cell size t/D [1] that gives ``plateau_force_N``."""
    area = jnp.pi * section_diameter_m**2 / 4.0
    return (plateau_force_N / (area * WIERZBICKI_COEFF * flow_stress_Pa)) ** 0.6
