"""The calibration parameters: where each sits in the vehicle, its unit, and the transform that
keeps it physical while the optimiser works on an unconstrained number.

* Positive parameters are fitted as ``log(p)`` (never clipped).
* ``gamma`` in (0, 1) as ``logit(gamma)``.
* ``F2`` as ``log(F2 - F1)``: the secondary plateau always exceeds the primary (the vehicle's
  validity rule), whatever the optimiser tries.

Standard errors and correlations are reported for the physical values, through the Jacobian of
this transform (delta method).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import jaxland as jl

__all__ = ["PARAMS", "DEFAULT_PARAMS", "OPTIONAL_PARAMS", "check_names", "get_values",
           "set_values", "to_unconstrained", "from_unconstrained"]

# name -> (getter, unit, TOML key, transform, description)
PARAMS = {
    "k": (lambda v: v.ground.k, "N/m", "ground.k_N_per_m", "log",
          "ground normal contact stiffness"),
    "gamma": (lambda v: v.ground.gamma, "1", "ground.gamma", "logit",
              "ground energy-loss fraction (bi-stiffness restitution)"),
    "D_b": (lambda v: v.leg.D_b, "s/m", "leg.D_b_s_per_m", "log",
            "structural damping of the main strut"),
    "k_b1": (lambda v: v.honeycomb.k_b1, "N/m", "honeycomb.k_b1_N_per_m", "log",
             "primary honeycomb elastic stiffness"),
    "F1": (lambda v: v.honeycomb.F1, "N", "honeycomb.F1_N", "log",
           "primary honeycomb plateau force"),
    "F2": (lambda v: v.honeycomb.F2, "N", "honeycomb.F2_N", "gap",
           "secondary honeycomb plateau force (fitted as log(F2 - F1))"),
    "chi": (lambda v: v.ground.chi, "s/m", "ground.chi_s_per_m", "log",
            "ground normal damping"),
    "mu": (lambda v: v.ground.mu, "1", "ground.mu", "log", "foot-ground friction"),
    "k_a": (lambda v: v.leg.k_a, "N/m", "leg.k_a_N_per_m", "log",
            "auxiliary strut pair stiffness"),
    "k_b3": (lambda v: v.honeycomb.k_b3, "N/m", "honeycomb.k_b3_N_per_m", "log",
             "secondary honeycomb elastic stiffness"),
    "k_tan": (lambda v: v.ground.k_tan, "N/m", "ground.k_tan_N_per_m", "log",
              "tangential contact stiffness"),
}
DEFAULT_PARAMS = ("k", "gamma", "D_b", "k_b1", "F1", "F2")
OPTIONAL_PARAMS = tuple(n for n in PARAMS if n not in DEFAULT_PARAMS)


def check_names(names) -> tuple[str, ...]:
    """Validate a parameter selection (order kept, duplicates refused)."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    names = tuple(names)
    if not names:
        raise jl.ConfigError("params", "", "select at least one parameter; known: "
                             + ", ".join(PARAMS))
    for n in names:
        if n not in PARAMS:
            raise jl.ConfigError("params", n, "unknown parameter; known: " + ", ".join(PARAMS))
    if len(set(names)) != len(names):
        raise jl.ConfigError("params", ",".join(names), "lists a parameter twice")
    return names


def get_values(vehicle: jl.Vehicle, names) -> np.ndarray:
    """Physical values of the selected parameters [SI]."""
    return np.array([float(PARAMS[n][0](vehicle)) for n in names])


def set_values(vehicle: jl.Vehicle, names, values) -> jl.Vehicle:
    """The vehicle with the selected parameters replaced (jnp values allowed: jit-safe)."""
    getters = tuple(PARAMS[n][0] for n in names)
    return eqx.tree_at(lambda v: tuple(g(v) for g in getters), vehicle,
                       tuple(jnp.asarray(x, dtype=jnp.float64) for x in values))


def _f1_of(names, values, vehicle):
    return values[names.index("F1")] if "F1" in names else PARAMS["F1"][0](vehicle)


def to_unconstrained(vehicle: jl.Vehicle, names) -> np.ndarray:
    """Unconstrained coordinates z of the selected parameters of ``vehicle``."""
    p = get_values(vehicle, names)
    f1 = float(_f1_of(names, p, vehicle))
    z = []
    for n, x in zip(names, p):
        kind = PARAMS[n][3]
        if kind == "log":
            if not x > 0:
                raise jl.ConfigError(PARAMS[n][2], x, "must be > 0 to be fitted (log scale)")
            z.append(np.log(x))
        elif kind == "logit":
            if not 0 < x < 1:
                raise jl.ConfigError(PARAMS[n][2], x, "must be in (0, 1) to be fitted")
            z.append(np.log(x / (1 - x)))
        else:  # gap over F1
            if not x > f1:
                raise jl.ConfigError(PARAMS[n][2], x, f"must exceed F1 = {f1:g} N")
            z.append(np.log(x - f1))
    return np.array(z)


def from_unconstrained(z, names, vehicle: jl.Vehicle):
    """Physical values (jnp) from unconstrained coordinates; traceable."""
    out = [None] * len(names)
    for i, n in enumerate(names):
        kind = PARAMS[n][3]
        if kind == "log":
            out[i] = jnp.exp(z[i])
        elif kind == "logit":
            out[i] = 1.0 / (1.0 + jnp.exp(-z[i]))
    if "F2" in names:
        i = names.index("F2")
        f1 = out[names.index("F1")] if "F1" in names else PARAMS["F1"][0](vehicle)
        out[i] = f1 + jnp.exp(z[i])
    return jnp.stack(out)
