"""The calibration parameters: where each sits in the vehicle, its unit, and the transform that
keeps it physical while the optimiser works on an unconstrained number.

* Positive parameters are fitted as ``log(p)`` (never clipped).
* ``gamma`` in (0, 1) as ``logit(gamma)``.
* ``F2`` as ``log(F2 - F1)``: the secondary plateau always exceeds the primary (the vehicle's
  validity rule), whatever the optimiser tries.
* The honeycomb's crush-peak ratios and unloading ratio (``peak1``, ``peak2``, ``unload``) as
  ``log(r - 1)``: they stay above 1. Off in the starting vehicle (ratio 1, the paper's law) they
  start from ``START_IF_OFF`` (1.2: the middle of the pre-crushed honeycomb's 1.0-1.3 x range;
  1.1 for the unloading ratio).
* The peak lengths as ``log(L - L_min)`` with L_min = 2 (r - 1) F / k, the shortest decay the
  vehicle's rule allows (falling slope (r - 1) F / L <= k / 2, ``jaxland.validate_vehicle``):
  a sharper measured peak than the rule allows ends the fit at the rule's bound (the peak's
  work, not its shape), never at an invalid vehicle.

Standard errors and correlations are reported for the physical values, through the Jacobian of
this transform (delta method).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import jaxland as jl

__all__ = ["PARAMS", "DEFAULT_PARAMS", "OPTIONAL_PARAMS", "PEAK_PARAMS", "START_IF_OFF",
           "check_names", "get_values", "set_values", "switch_on", "to_unconstrained",
           "from_unconstrained"]

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
    "peak1": (lambda v: v.honeycomb.peak_ratio1, "1", "honeycomb.peak_ratio1", "over1",
              "primary honeycomb initial crush peak / F1 (fitted as log(r - 1))"),
    "L_peak1": (lambda v: v.honeycomb.peak_length1, "m", "honeycomb.peak_length1_mm", "length",
                "crush over which the primary peak decays to F1 (fitted as log(L - L_min))"),
    "peak2": (lambda v: v.honeycomb.peak_ratio2, "1", "honeycomb.peak_ratio2", "over1",
              "secondary honeycomb initial crush peak / F2 (fitted as log(r - 1))"),
    "L_peak2": (lambda v: v.honeycomb.peak_length2, "m", "honeycomb.peak_length2_mm", "length",
                "crush over which the secondary peak decays to F2 (fitted as log(L - L_min))"),
    "unload": (lambda v: v.honeycomb.unload_ratio, "1", "honeycomb.unload_ratio", "over1",
               "secondary stage's unloading stiffness / k_b3 (fitted as log(rho - 1))"),
}
# where an optional law extension is off (None: ratio 1) a fit of it starts here
START_IF_OFF = {"peak1": 1.2, "peak2": 1.2, "unload": 1.1}
PEAK_PARAMS = ("peak1", "L_peak1")  # the crush-peak model's extra parameters (model selection)
_NONE = dict(is_leaf=lambda x: x is None)  # an extension that is off is a None field
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
    """Physical values of the selected parameters [SI] (an extension that is off: 1)."""
    return np.array([1.0 if PARAMS[n][0](vehicle) is None else float(PARAMS[n][0](vehicle))
                     for n in names])


def set_values(vehicle: jl.Vehicle, names, values) -> jl.Vehicle:
    """The vehicle with the selected parameters replaced (jnp values allowed: jit-safe); an
    extension that was off is switched on."""
    getters = tuple(PARAMS[n][0] for n in names)
    return eqx.tree_at(lambda v: tuple(g(v) for g in getters), vehicle,
                       tuple(jnp.asarray(x, dtype=jnp.float64) for x in values), **_NONE)


def switch_on(vehicle: jl.Vehicle, names) -> jl.Vehicle:
    """``vehicle`` with every selected law extension that is off (None) set to its
    ``START_IF_OFF`` value: the start of a fit that includes it."""
    off = [n for n in names if n in START_IF_OFF and PARAMS[n][0](vehicle) is None]
    if not off:
        return vehicle
    return jl.validate_vehicle(set_values(vehicle, off, [START_IF_OFF[n] for n in off]))


def _f1_of(names, values, vehicle):
    return values[names.index("F1")] if "F1" in names else PARAMS["F1"][0](vehicle)


_LENGTH_OF = {"L_peak1": ("peak1", "F1"), "L_peak2": ("peak2", "F2")}


def _min_length(n, names, values, vehicle):
    """L_min = 2 (r - 1) F / k of a peak length [m] from the fitted or the vehicle's values."""
    ratio, force = _LENGTH_OF[n]

    def val(m):
        if m in names:
            return values[names.index(m)]
        v = PARAMS[m][0](vehicle)
        return 1.0 if v is None else v

    return 2.0 * (val(ratio) - 1.0) * val(force) / val("k")


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
        elif kind == "over1":
            if x == 1.0:  # off: start from the documented value
                x = START_IF_OFF[n]
            if not x > 1:
                raise jl.ConfigError(PARAMS[n][2], x, "must be >= 1 (1: off) to be fitted")
            z.append(np.log(x - 1.0))
        elif kind == "length":
            continue  # below, once the ratios are known
        else:  # gap over F1
            if not x > f1:
                raise jl.ConfigError(PARAMS[n][2], x, f"must exceed F1 = {f1:g} N")
            z.append(np.log(x - f1))
    z = _fill(z, names)
    phys = from_unconstrained(np.array([0.0 if zi is None else zi for zi in z]), names,
                              vehicle, lengths=False)
    for i, n in enumerate(names):
        if PARAMS[n][3] == "length":
            x = p[i]
            lo = float(_min_length(n, names, np.asarray(phys), vehicle))
            if not x > lo:
                raise jl.ConfigError(PARAMS[n][2], x * 1e3, f"must exceed 2 (r - 1) F / k = "
                                     f"{lo * 1e3:.4g} mm to be fitted (the falling-slope rule)")
            z[i] = np.log(x - lo)
    return np.array(z, dtype=float)


def _fill(z, names):
    """z with a placeholder where a length's coordinate comes later (same length as names)."""
    it = iter(z)
    return [None if PARAMS[n][3] == "length" else next(it) for n in names]


def from_unconstrained(z, names, vehicle: jl.Vehicle, lengths: bool = True):
    """Physical values (jnp) from unconstrained coordinates; traceable. (``lengths=False``:
    the peak lengths are left at 0, for ``to_unconstrained``.)"""
    out = [None] * len(names)
    for i, n in enumerate(names):
        kind = PARAMS[n][3]
        if kind == "log":
            out[i] = jnp.exp(z[i])
        elif kind == "logit":
            out[i] = 1.0 / (1.0 + jnp.exp(-z[i]))
        elif kind == "over1":
            out[i] = 1.0 + jnp.exp(z[i])
    if "F2" in names:
        i = names.index("F2")
        f1 = out[names.index("F1")] if "F1" in names else PARAMS["F1"][0](vehicle)
        out[i] = f1 + jnp.exp(z[i])
    for i, n in enumerate(names):
        if PARAMS[n][3] == "length":
            out[i] = jnp.zeros(()) if not lengths else (
                _min_length(n, names, out, vehicle) + jnp.exp(z[i]))
    return jnp.stack([jnp.asarray(o, dtype=jnp.float64) for o in out])
