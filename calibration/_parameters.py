"""The calibration parameters: where each sits in the vehicle, its unit, and the transform that
keeps it physical while the optimiser works on an unconstrained number.

* Positive parameters are fitted as ``log(p)`` (never clipped).
* ``gamma`` in (0, 1) as ``logit(gamma)`` (held below 1 - ``BOUND_MARGIN``, where the
  sigmoid rounds to 1, the rule's open end).
* ``F2`` as ``log(F2 - F1)``: the secondary plateau always exceeds the primary (the vehicle's
  validity rule), whatever the optimiser tries.
* The honeycomb's crush-peak ratios, their decay lengths, the primary's rise length and the
  unloading ratio (``peak1``, ``L_peak1``, ``L_rise1``, ``peak2``, ``L_peak2``, ``unload``)
  within the bounds of the vehicle's rules
  (``jaxland.validate_vehicle``), as logit((x - lo) / (hi - lo)), or log(x - lo) without an
  upper bound: unload in (1, max(k_b1, k_b3) / k_b3); L between 2 (r - 1) F / k (the
  falling slope (r - 1) F / L <= k / 2) and the room left before x_L2 (x_L4), in the
  exponential forms of the primary peak that room over EXP_SPAN (their table spans EXP_SPAN
  L_peak1: the bounds take the peak's form); r in (1, the
  largest peak those leave room for), and r1 F1 < F2; L_rise1 between (r1 - 1) F1 / k_b1 (a
  build-up slower than the elastic rise) and the room the decay (L_peak1, or EXP_SPAN
  L_peak1 in the exponential forms) leaves before x_L2; in the smooth form, whose build-up
  lies inside its table, between a length that keeps its steepest build-up below k_b1
  (conservative by up to a factor e) and SMOOTH_RISE_MAX L_peak1 (L_peak1 there at least
  2 e (r1 - 1) F1 / k_b1, so that interval stays open); in the ripple form, where it is the
  fold length, between the largest of 4 (r1 - 1) F1 / k (its falls), 2 (r1 - 1) F1 / k_b1
  (its rises) and RIPPLE_MIN_FOLD L_peak1, and the room its RIPPLE_SPAN folds leave before
  x_L2 (peak1's bound keeps that open). A sharper
  measured peak than the rule allows ends the fit at the bound (the peak's work, not its
  shape), never at an invalid vehicle: every bound a rule sets is moved inside by
  ``BOUND_MARGIN`` (1e-9) of that rule's own scale (the slope k / 2, the plateau's end x_L2 or
  x_L4, F2, the stiffest stage), far above float64 rounding (1e-16) and far below anything
  measurable (L_peak1's upper bound also leaves ``RISE_ROOM``, 1e-4 of the room, to
  L_rise1), so that a value the optimiser drives onto a bound, where the rule holds with
  equality, still passes the rule after rounding (``at_bound`` names such values). Off in the
  starting vehicle (ratio 1, the paper's law)
  the ratios start from ``START_IF_OFF`` (1.2: the middle of the pre-crushed honeycomb's
  1.0-1.3 x range; 1.1 for the unloading ratio; a rise length that is off starts at 1 mm).

Standard errors and correlations are reported for the physical values, through the Jacobian of
this transform (delta method).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxland as jl

__all__ = ["PARAMS", "DEFAULT_PARAMS", "OPTIONAL_PARAMS", "PEAK_PARAMS", "START_IF_OFF",
           "PEAK_FORMS", "RISE_FORMS", "FORM_INDEX", "SHAPE_PARAMS", "peak_form_vehicle",
           "forms_vehicle", "check_names", "get_values", "at_bound", "interval", "BOUND_MARGIN",
           "set_values", "switch_on", "to_unconstrained", "from_unconstrained", "no_peak_names",
           "value_range", "interval95", "EXTENSION_OF", "acts_in", "Z95"]

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
              "primary honeycomb initial crush peak / F1"),
    "L_peak1": (lambda v: v.honeycomb.peak_length1, "m", "honeycomb.peak_length1_mm", "length",
                "crush over which the primary peak decays to F1"),
    "L_rise1": (lambda v: v.honeycomb.peak_rise1, "m", "honeycomb.peak_rise1_mm", "rise",
                "crush over which the primary peak builds up from F1 (with peak1); in the "
                "ripple form, the fold length"),
    "peak2": (lambda v: v.honeycomb.peak_ratio2, "1", "honeycomb.peak_ratio2", "over1",
              "secondary honeycomb initial crush peak / F2"),
    "L_peak2": (lambda v: v.honeycomb.peak_length2, "m", "honeycomb.peak_length2_mm", "length",
                "crush over which the secondary peak decays to F2"),
    "unload": (lambda v: v.honeycomb.unload_ratio, "1", "honeycomb.unload_ratio", "over1",
               "secondary stage's unloading stiffness / k_b3"),
}
# where an optional law extension is off (None: ratio 1) a fit of it starts here
START_IF_OFF = {"peak1": 1.2, "peak2": 1.2, "unload": 1.1, "L_rise1": 1e-3}
PEAK_PARAMS = ("peak1", "L_peak1")  # the crush-peak model's extra parameters (model selection)
_NONE = dict(is_leaf=lambda x: x is None)  # an extension that is off is a None field
# The primary crush peak's forms, each a different shape for the same two numbers (peak1: the
# peak's height over F1; L_peak1: how fast it goes): ``linear``, the law's linear fall over
# L_peak1; ``rise``, the law's peak built up over L_rise1 before that fall; ``exp``, an
# excess (peak1 - 1) F1 exp(-c / L_peak1) of the crush c past the onset, tabulated
# (``Honeycomb.excess1``) over EXP_SPAN decay lengths at EXP_POINTS nodes (exp(-8): 3e-4 of
# the peak is cut off at the table's end); ``rise_exp``, that exponential decay built up over
# L_rise1 first (the law's rise with a table: ``Honeycomb.peak_rise1`` and ``excess1``, the
# table EXP_POINTS - 1 nodes long so that the rise and the table fill the shared program's
# EXP_POINTS segments). The exp forms' steepest fall, on their first
# segment, is 0.96 of the linear form's slope (peak1 - 1) F1 / L_peak1, so the linear form's
# lower bound on L_peak1 holds for them; their table ends EXP_SPAN L_peak1 past the onset, so
# their room before x_L2 is EXP_SPAN times shorter (``_bounds``' ``form``). ``smooth_exp``,
# an excess that builds up smoothly, A (1 - exp(-c / L_rise1)) exp(-c / L_peak1), A such
# that its top is (peak1 - 1) F1 (``smooth_table``): it starts at 0 with its steepest
# build-up, A / L_rise1, and approaches the decay, with no corner where the build-up ends;
# the EXP_POINTS-node table over EXP_SPAN L_peak1 holds the build-up too. Its steepest fall
# is below (peak1 - 1) F1 / L_peak1 (1 as L_rise1 -> 0, 0.5 at L_rise1 = L_peak1), so the
# linear form's lower bound on L_peak1 holds for it as well.
# ``ripple``, a peak that re-peaks fold by fold (honeycomb walls buckle in folds of a length
# set by the cell, 2H ~ 2.9 mm for the paper's primary cells: Wierzbicki 1983): the excess
# falls linearly from (peak1 - 1) F1 to 0 over half a fold and rises linearly to the next
# fold's peak over the other half, the peaks decaying as exp(-c / L_peak1); L_rise1 is the
# fold length there (``ripple_table``). The table holds RIPPLE_FOLDS folds (2 RIPPLE_FOLDS +
# 1 nodes, half a fold apart, then 0 over the last half fold: RIPPLE_SPAN fold lengths); a
# fold at least RIPPLE_MIN_FOLD L_peak1 long leaves at most exp(-RIPPLE_FOLDS
# RIPPLE_MIN_FOLD) = exp(-4) (1.8 %) of the first peak at the table's end. Its steepest fall,
# 2 (peak1 - 1) F1 / L_rise1, is what the ground's k / 2 bounds (``_bounds``).
PEAK_FORMS = ("linear", "rise", "exp", "rise_exp", "smooth_exp", "ripple")
RISE_FORMS = ("rise", "rise_exp", "smooth_exp", "ripple")  # the forms that fit L_rise1
SHAPE_PARAMS = ("peak1", "L_peak1", "L_rise1")  # their meaning depends on the form
EXP_SPAN, EXP_POINTS = 8.0, 97
# in L_peak1; the law's forms: 1
RIPPLE_FOLDS, RIPPLE_MIN_FOLD = 16, 0.25
RIPPLE_NODES, RIPPLE_SPAN = 2 * RIPPLE_FOLDS + 1, RIPPLE_FOLDS + 0.5  # span in fold lengths
# the tabulated forms' span in L_peak1 (the ripple's at its shortest fold)
EXP_TABLE_SPAN = {"exp": EXP_SPAN, "rise_exp": EXP_SPAN, "smooth_exp": EXP_SPAN,
                  "ripple": RIPPLE_SPAN * RIPPLE_MIN_FOLD}
# the smooth form's longest build-up, in L_peak1: its table's cut at EXP_SPAN L_peak1 then
# leaves under 0.7 % of its top (as L_rise1 / L_peak1 grows the form tends to c exp(-c /
# L_peak1), which the bump-shaped peaks of records ask for)
SMOOTH_RISE_MAX = 16.0
# how far inside each rule-set bound the transform keeps a value, in units of the rule's own
# scale (module docstring): rounding (1e-16) cannot cross it, no measurement can see it
BOUND_MARGIN = 1e-9
# the part of the primary plateau's room that L_peak1's upper bound leaves for L_rise1 beyond
# the elastic rise (a rise no longer than (r1 - 1) F1 / k_b1 is refused): its interval then
# stays open, at least 6 um on the paper vehicle, whatever L_peak1 is
RISE_ROOM = 1e-4
FORM_INDEX = {f: i for i, f in enumerate(PEAK_FORMS)}  # the runtime code of ``forms_vehicle``
# where the primary crush peak sits: in the honeycomb (its crush work moves the stroke and the
# body), or on the force channels alone (a gain of the crush; ``_problem``)
HONEYCOMB, FORCES = "honeycomb", "forces"
PEAK_SITES = (HONEYCOMB, FORCES)
# a peak on the force channels: its shortest length (decay, build-up, fold), as a part of the
# primary plateau's room (about 0.05 mm on the paper vehicle, a quarter sample of the first
# impact at 5 kHz)
GAIN_MIN_LENGTH = 1e-3
DEFAULT_PARAMS = ("k", "gamma", "D_b", "k_b1", "F1", "F2")
OPTIONAL_PARAMS = tuple(n for n in PARAMS if n not in DEFAULT_PARAMS)


def check_peak_site(site, names) -> None:
    """Refuse by name a ``peak_site`` that is not one of ``PEAK_SITES``, or the force
    channels' (``FORCES``) without peak1 among the fitted ``names``."""
    if site not in PEAK_SITES:
        raise jl.ConfigError("peak_site", site, "must be one of " + ", ".join(PEAK_SITES))
    if site == FORCES and "peak1" not in names:
        raise jl.ConfigError("peak_site", site, "needs peak1 among the fitted parameters "
                             "(the peak it puts on the force channels)")


def check_names(names) -> tuple[str, ...]:
    """Validate a parameter selection (order kept, duplicates refused)."""
    if isinstance(names, str):
        if names.strip() and any(not n.strip() for n in names.split(",")):
            raise jl.ConfigError("params", names, "has an empty entry (two commas, or one at an "
                                 "end): a name left out by a typo is refused, not skipped")
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


def exp_table(excess, n: int):
    """The exponential forms' table: ``excess`` (peak1 - 1, ratio of F1) times exp(-c_j /
    L_peak1) at its n nodes c_j = j EXP_SPAN L_peak1 / n (the last axis)."""
    return excess * jnp.exp(-(jnp.arange(n, dtype=jnp.float64) * (EXP_SPAN / n)))


def smooth_top(r):
    """The top of (1 - exp(-x / r)) exp(-x) over x >= 0, r = L_rise1 / L_peak1 > 0: at x =
    r log(1 + 1 / r) it is (r / (1 + r))^r / (1 + r)."""
    return jnp.exp(r * jnp.log(r / (1.0 + r))) / (1.0 + r)


def smooth_table(excess, n: int, r):
    """The smooth form's table: ``excess`` (peak1 - 1, ratio of F1) times (1 - exp(-x_j / r))
    exp(-x_j) / ``smooth_top(r)`` at its n nodes x_j = j EXP_SPAN / n (in L_peak1; the last
    axis), r = L_rise1 / L_peak1: 0 at the onset, ``excess`` at its top."""
    x = jnp.arange(n, dtype=jnp.float64) * (EXP_SPAN / n)
    r = jnp.expand_dims(r, -1)
    return excess * (-jnp.expm1(-x / r)) * jnp.exp(-x) / smooth_top(r)


def ripple_table(excess, q):
    """The ripple form's table: at its RIPPLE_NODES nodes c_j = j L_rise1 / 2 (the last axis),
    ``excess`` (peak1 - 1, ratio of F1) times exp(-c_j / L_peak1) at the fold peaks (even j)
    and 0 between them (odd j); q = L_rise1 / L_peak1."""
    j = jnp.arange(RIPPLE_NODES, dtype=jnp.float64)
    peak = (jnp.arange(RIPPLE_NODES) % 2 == 0).astype(jnp.float64)
    return excess * peak * jnp.exp(-0.5 * j * jnp.expand_dims(q, -1))


def _after(e):
    """Each node's next value along the last axis, 0 past the last."""
    return jnp.concatenate([e[..., 1:], jnp.zeros_like(e[..., :1])], axis=-1)


def peak_form_vehicle(vehicle: jl.Vehicle, form: str) -> jl.Vehicle:
    """``vehicle`` with its primary peak (peak_ratio1, peak_length1, peak_rise1) in ``form``
    (``PEAK_FORMS``); jit-safe. ``linear`` switches the rise off; ``rise`` keeps it (the
    vehicle must have one); ``exp`` replaces the linear peak by its exponential table;
    ``rise_exp`` by that table, EXP_POINTS - 1 nodes long, after the rise (which it keeps);
    ``smooth_exp`` by its table (``smooth_table``), which holds its build-up (the rise is
    read and switched off); ``ripple`` by its table (``ripple_table``; peak_rise1 is read as
    the fold length and switched off)."""
    hc = vehicle.honeycomb
    if form == "rise":
        return vehicle
    if form == "linear":
        return eqx.tree_at(lambda v: v.honeycomb.peak_rise1, vehicle, None, **_NONE)
    if form not in EXP_TABLE_SPAN:
        raise jl.ConfigError("peak_form", form, "must be one of " + ", ".join(PEAK_FORMS))
    if form in RISE_FORMS and hc.peak_rise1 is None:
        raise jl.ConfigError("honeycomb.peak_rise1_mm", 0.0, f"the {form} form builds its "
                             "exponential peak up over this rise: give one (> 0)"
                             if form == "rise_exp" else "the ripple form's fold length: "
                             "give one (> 0)" if form == "ripple" else "the smooth_exp form's "
                             "build-up length scale (1 - exp(-c / L_rise1)): give one (> 0)")
    if form == "ripple":
        fold = jnp.asarray(hc.peak_rise1, dtype=jnp.float64)
        table = ripple_table(jnp.asarray(hc.peak_ratio1, dtype=jnp.float64) - 1.0,
                             fold / jnp.asarray(hc.peak_length1, dtype=jnp.float64))
        return eqx.tree_at(
            lambda v: (v.honeycomb.peak_ratio1, v.honeycomb.peak_rise1, v.honeycomb.excess1,
                       v.honeycomb.excess_length1), vehicle,
            (None, None, table, RIPPLE_SPAN * fold), **_NONE)
    n = EXP_POINTS - 1 if form == "rise_exp" else EXP_POINTS
    excess = jnp.asarray(hc.peak_ratio1, dtype=jnp.float64) - 1.0
    if form == "smooth_exp":
        table = smooth_table(excess, n, jnp.asarray(hc.peak_rise1, dtype=jnp.float64)
                             / jnp.asarray(hc.peak_length1, dtype=jnp.float64))
    else:
        table = exp_table(excess, n)
    rise = hc.peak_rise1 if form == "rise_exp" else None
    return eqx.tree_at(
        lambda v: (v.honeycomb.peak_ratio1, v.honeycomb.peak_rise1, v.honeycomb.excess1,
                   v.honeycomb.excess_length1), vehicle,
        (None, rise, table, EXP_SPAN * jnp.asarray(hc.peak_length1, dtype=jnp.float64)),
        **_NONE)


class _FormsHoneycomb(jl.Honeycomb):
    """``jl.Honeycomb`` whose primary peak (peak_ratio1, peak_length1, peak_rise1) takes the
    form ``form`` (``FORM_INDEX``: a number, traced under jit). Every form is the law's
    tabulated excess with EXP_POINTS segments, each of its own width: ``linear`` one falling
    segment, ``rise`` a rising and a falling one, ``exp`` ``peak_form_vehicle``'s exponential
    table, ``rise_exp`` a rising segment and that table one node shorter, ``smooth_exp`` its
    table (``smooth_table``) on the exponential table's nodes, ``ripple`` its RIPPLE_NODES
    segments (``ripple_table``); the segments a form
    does not use have width and slope 0 and add exactly 0. So one
    compiled program serves every form (``forms_vehicle``); the curve is that of the form's
    own vehicle (``peak_form_vehicle``) up to rounding."""

    form: jnp.ndarray = eqx.field(default=0)

    def curve(self):
        keep = {f.name: getattr(self, f.name) for f in dataclasses.fields(jl.Honeycomb)}
        keep["peak_rise1"] = None
        cv = jl.Honeycomb(**keep).curve()  # the general law with the linear peak
        n, form, length = EXP_POINTS, jnp.asarray(self.form), self.peak_length1

        def col(x):
            return jnp.expand_dims(x, -1)

        def segments(*head):  # the form's segments, then n - len(head) of zero width
            tail = jnp.zeros(jnp.shape(length) + (n - len(head),))
            return jnp.concatenate([col(h) for h in head] + [tail], axis=-1)

        a = cv.a1  # (r1 - 1) F1
        zero = jnp.zeros_like(a)
        is_rise = functools.reduce(jnp.logical_or, [form == FORM_INDEX[f] for f in RISE_FORMS])
        # the rise's width only where the form has one (a finite divisor in every form)
        rise = length if self.peak_rise1 is None else jnp.where(is_rise, self.peak_rise1,
                                                                length)
        # exp: peak_form_vehicle's table (ratios of F1), then Honeycomb.curve's uniform grid
        e = exp_table(col(self.peak_ratio1) - 1.0, n) * col(self.F1)
        span = EXP_SPAN * length
        dc = col(span / n)
        # rise_exp: the rise, then the table of n - 1 nodes over the same span
        e_r = exp_table(col(self.peak_ratio1) - 1.0, n - 1) * col(self.F1)
        dc_r = jnp.broadcast_to(col(span / (n - 1)), e_r.shape)
        w_r = jnp.concatenate([col(rise), dc_r], axis=-1)
        # smooth_exp: its table on the exp table's nodes (r = 1 where the form has no rise)
        e_s = smooth_table(col(self.peak_ratio1) - 1.0, n, rise / length) * col(self.F1)
        # ripple: its table, nodes half a fold (rise) apart, then segments of zero width
        e_p = ripple_table(col(self.peak_ratio1) - 1.0, rise / length) * col(self.F1)
        dc_p = jnp.broadcast_to(col(0.5 * rise), e_p.shape)

        def pad(x):  # a table's columns, then segments of zero width up to n
            return jnp.concatenate([x, jnp.zeros(x.shape[:-1] + (n - x.shape[-1],))], axis=-1)

        w_p = pad(dc_p)

        def starts(widths):  # each segment starts where the ones before it end
            ends = jnp.cumsum(widths, axis=-1)
            return jnp.concatenate([jnp.zeros_like(ends[..., :1]), ends[..., :-1]], axis=-1)

        tables = {  # (a1, L1, starts c_j, widths, slopes, e(c_j)) of each form
            "linear": (a, length, starts(segments(length)), segments(length),
                       segments(-a / length), segments(a)),
            "rise": (zero, rise + length, starts(segments(rise, length)),
                     segments(rise, length), segments(a / rise, -a / length),
                     segments(zero, a)),
            "exp": (e[..., 0], span, dc * jnp.arange(n, dtype=jnp.float64),
                    jnp.broadcast_to(dc, e.shape), (_after(e) - e) / dc, e),
            "rise_exp": (zero, rise + span, starts(w_r), w_r,
                         jnp.concatenate([col(e_r[..., 0] / rise), (_after(e_r) - e_r) / dc_r],
                                         axis=-1),
                         jnp.concatenate([col(zero), e_r], axis=-1)),
            "smooth_exp": (e_s[..., 0], span, dc * jnp.arange(n, dtype=jnp.float64),
                           jnp.broadcast_to(dc, e_s.shape), (_after(e_s) - e_s) / dc, e_s),
            "ripple": (e_p[..., 0], RIPPLE_SPAN * rise, starts(w_p), w_p,
                       pad((_after(e_p) - e_p) / dc_p), pad(e_p)),
        }

        def pick(i):  # every form's numbers are finite: no NaN in the unselected branches
            out = tables["exp"][i]
            # from exp's numbers, each other form's where it is the form; this order sets how
            # XLA contracts the slopes' arithmetic, so the bits of every form's curve
            for f in reversed(PEAK_FORMS):
                if f != "exp":
                    out = _in_form(form, f, lambda f=f: tables[f][i], out)
            return out

        a1, widths, e_c = pick(0), pick(3), pick(5)
        # the integral of e over [0, c_j]: the trapezoids of the segments before (exact)
        area = jnp.cumsum(0.5 * (e_c + _after(e_c)) * widths, axis=-1)
        integral = jnp.concatenate([jnp.zeros_like(area[..., :1]), area[..., :-1]], axis=-1)
        return eqx.tree_at(
            lambda c: (c.a1, c.x_pk1, c.L1, c.t1_c, c.t1_dc, c.t1_slope, c.t1_e, c.t1_int), cv,
            (a1, cv.x_L1 + a1 / self.k_b1, pick(1), pick(2), widths, pick(4), e_c, integral),
            **_NONE)


def forms_vehicle(vehicle: jl.Vehicle, form) -> jl.Vehicle:
    """``vehicle`` (its primary peak on: peak_ratio1, peak_length1, and peak_rise1 where a
    built-up form is wanted) with the peak in the form of code ``form`` (``FORM_INDEX``; a traced
    number under jit), through ``_FormsHoneycomb``: one compiled landing for every form."""
    hc = vehicle.honeycomb
    kw = {f.name: getattr(hc, f.name) for f in dataclasses.fields(jl.Honeycomb)}
    return eqx.tree_at(lambda v: v.honeycomb, vehicle, _FormsHoneycomb(**kw, form=form))


def no_peak_names(names) -> tuple:
    """The parameters of a fit's special case without the primary crush peak: ``names``
    without the peak's (``SHAPE_PARAMS``)."""
    return tuple(n for n in names if n not in SHAPE_PARAMS)


def switch_on(vehicle: jl.Vehicle, names) -> jl.Vehicle:
    """``vehicle`` with every selected law extension that is off (None) set to its
    ``START_IF_OFF`` value: the start of a fit that includes it."""
    off = [n for n in names if n in START_IF_OFF and PARAMS[n][0](vehicle) is None]
    if not off:
        return vehicle
    return jl.validate_vehicle(set_values(vehicle, off, [START_IF_OFF[n] for n in off]))


def _f1_of(names, values, vehicle):
    return values[names.index("F1")] if "F1" in names else PARAMS["F1"][0](vehicle)


def _value(m, names, values, vehicle):
    """A fitted value (``values``, by ``names``) or the vehicle's; 1 for an extension off."""
    if m in names:
        return values[names.index(m)]
    v = PARAMS[m][0](vehicle)
    return 1.0 if v is None else v


def _span(form):
    """How many L_peak1 the primary peak's decay spans in ``form``: a name of PEAK_FORMS (None:
    the vehicle's own law) or a form's code (``FORM_INDEX``, traced under jit). EXP_SPAN for
    the exponential forms (their table), 1 for the law's linear fall, built up or not."""
    out = 1.0
    for f, span in EXP_TABLE_SPAN.items():
        out = _in_form(form, f, lambda span=span: span, out)
    return out


def _in_form(form, name, a, b):
    """``a()`` where the primary peak's ``form`` (``_span``'s argument) is ``name``, else
    ``b``: a name of PEAK_FORMS (or None) picks in Python, calling ``a`` only for ``name``;
    a form's code (traced under jit) selects with ``where`` (``a()``'s value must be finite
    in every form)."""
    if form is None or isinstance(form, str):
        return a() if form == name else b
    return jnp.where(jnp.asarray(form) == FORM_INDEX[name], a(), b)


def _gain_bounds(n, names, values, vehicle, form=None):
    """(lo, hi) of the primary peak's parameters where the peak sits on the force channels
    (``FORCES``: a gain of the crush, ``_problem.force_channel_gain``). None of the rules of a
    peak in the honeycomb's dynamics binds a gain (the falling slope against the ground's
    stiffness, the build-up against k_b1, the elastic rise to the peak); the peak stays in the
    primary plateau's room (its decay, build-up or folds end before x_L2), below the
    secondary plateau (r1 F1 < F2), and no length is shorter than GAIN_MIN_LENGTH of the
    room. L_peak1's upper bound leaves twice that for the build-up, so every interval stays
    open."""
    def v(m):
        return _value(m, names, values, vehicle)

    m, hc = BOUND_MARGIN, vehicle.honeycomb
    room = hc.x_L2 - v("F1") / v("k_b1") - m * hc.x_L2
    floor = GAIN_MIN_LENGTH * room
    if n == "peak1":
        return 1.0, 1.0 + (v("F2") - v("F1") - m * v("F2")) / v("F1")
    if n == "L_peak1":
        return floor, (1.0 - 2.0 * GAIN_MIN_LENGTH) * room / _span(form)
    lp = v("L_peak1")  # L_rise1: the build-up before the decay, the smooth form's, or a fold
    lo, hi = floor, room - _span(form) * lp
    lo = _in_form(form, "ripple", lambda: jnp.maximum(RIPPLE_MIN_FOLD * lp, floor) * (1.0 + m),
                  lo)
    hi = _in_form(form, "smooth_exp", lambda: SMOOTH_RISE_MAX * lp * (1.0 - m), hi)
    return lo, _in_form(form, "ripple", lambda: room / RIPPLE_SPAN, hi)


def _bounds(n, names, values, vehicle, form=None, site=HONEYCOMB):
    """(lo, hi) of a crush-peak or unloading parameter from the vehicle's rules (hi None: no
    upper bound), given the other values (fitted or the vehicle's), the primary peak's form
    (``_span``) and where it sits (``PEAK_SITES``; on the force channels: ``_gain_bounds``);
    each bound that a rule sets lies ``BOUND_MARGIN`` of the rule's scale inside it (module
    docstring)."""
    if site == FORCES and n in SHAPE_PARAMS:
        return _gain_bounds(n, names, values, vehicle, form)

    def v(m):
        return _value(m, names, values, vehicle)

    m = BOUND_MARGIN
    hc = vehicle.honeycomb
    if n == "L_rise1":  # the build-up (r1 - 1) F1 / L_r < k_b1; the rise and fall end in x_L2
        a = (v("peak1") - 1.0) * v("F1")
        lo = a / v("k_b1") * (1.0 + m)
        hi = hc.x_L2 - v("F1") / v("k_b1") - _span(form) * v("L_peak1") - m * hc.x_L2
        # smooth_exp: its steepest build-up a / (L_r smooth_top(L_r / L_p)) < k_b1 holds for
        # L_r >= e a L_p / (k_b1 L_p - e a) (smooth_top(r) >= 1 / (e (1 + r))), which
        # L_peak1's bound keeps below L_p; its table holds the build-up: L_r up to
        # SMOOTH_RISE_MAX L_p. Inside L_peak1's bounds den >= k_b1 L_p / 2; the floor keeps
        # the other forms' derivatives finite where L_p is shorter
        lp = v("L_peak1")

        def smooth_lo():
            den = jnp.maximum(v("k_b1") * lp - math.e * a, 0.5 * v("k_b1") * lp)
            return math.e * a * lp / den * (1.0 + m)

        # ripple, L_rise1 the fold length: its steepest fall 2 a / L_r <= k / 2 and rise
        # 2 a / L_r < k_b1, its folds at least RIPPLE_MIN_FOLD L_peak1 long (the table's end);
        # its RIPPLE_SPAN folds end in x_L2 after the elastic rise to the peak. Inside
        # L_peak1's and peak1's bounds this interval is open
        def ripple_lo():
            return jnp.maximum(jnp.maximum(4.0 * a / v("k"), 2.0 * a / v("k_b1")),
                               RIPPLE_MIN_FOLD * lp) * (1.0 + m)

        def ripple_hi():
            return (hc.x_L2 - (v("F1") + a) / v("k_b1") - m * hc.x_L2) / RIPPLE_SPAN

        lo = _in_form(form, "smooth_exp", smooth_lo, lo)
        hi = _in_form(form, "smooth_exp", lambda: SMOOTH_RISE_MAX * lp * (1.0 - m), hi)
        return _in_form(form, "ripple", ripple_lo, lo), _in_form(form, "ripple", ripple_hi, hi)
    if n == "unload":  # rho k_b3 <= max(k_b1, k_b3)
        return 1.0, jnp.maximum(v("k_b1"), v("k_b3")) / v("k_b3") * (1.0 - m)
    first = n in ("peak1", "L_peak1")
    ratio, length, force, k_el = (("peak1", "L_peak1", "F1", "k_b1") if first
                                  else ("peak2", "L_peak2", "F2", "k_b3"))
    # the plateau's room: from its start (x_L1, x_L3) to its end (x_L2, x_L4), less the margin
    end = hc.x_L2 if first else hc.x_L4
    room = (hc.x_L2 - v("F1") / v("k_b1") if first
            else hc.x_L4 - hc.x_L2 - (v("F2") - v("F1")) / v("k_b3")) - m * end
    span = _span(form) if first else 1.0  # the peak's decay ends span L past its onset
    # the smooth form's L >= smooth a also leaves its build-up room (L_rise1's bound above)
    smooth = (2.0 * math.e / v("k_b1")) if first else None
    if n in ("peak1", "peak2"):  # bound the peak a = (r - 1) F
        if length in names:  # the length's interval below must stay open
            a_hi = 0.999 * room / (2.0 * span / v("k") + 1.0 / v(k_el))
            if first:
                a_hi = _in_form(form, "smooth_exp", lambda: 0.999 * room / (
                    span * jnp.maximum(2.0 / v("k"), smooth) + 1.0 / v(k_el)), a_hi)
        else:  # the fixed length: falling slope a / L <= k / 2, the peak ends in the room
            L = hc.peak_length1 if first else hc.peak_length2
            a_hi = jnp.minimum(0.5 * v("k") * L * (1.0 - m), v(k_el) * (room - span * L))
            if first:
                a_hi = _in_form(form, "smooth_exp",
                                lambda: jnp.minimum(a_hi, L / smooth * (1.0 - m)),
                                a_hi)
        if first:  # the ripple's fold length (L_rise1's bound above) keeps an open interval
            a_hi = _in_form(form, "ripple", lambda: jnp.minimum(a_hi, 0.999 * room / jnp.maximum(
                4.0 * RIPPLE_SPAN / v("k") + 1.0 / v(k_el), (2.0 * RIPPLE_SPAN + 1.0) / v(k_el))),
                a_hi)
        if first:  # r1 F1 < F2: the primary's peak stays below the secondary plateau
            a_hi = jnp.minimum(a_hi, v("F2") - v("F1") - m * v("F2"))
        return 1.0, 1.0 + a_hi / v(force)
    a = (v(ratio) - 1.0) * v(force)
    # falling slope a / L <= k / 2; the peak's rise a / k_el and decay span L end in the room,
    # and the primary's leaves RISE_ROOM of it, so that L_rise1's interval stays open at any L
    lo = 2.0 * a / v("k") * (1.0 + m)
    if first:
        lo = _in_form(form, "smooth_exp", lambda: jnp.maximum(lo, smooth * a * (1.0 + m)),
                      lo)
    return lo, (room - a / v(k_el) - (RISE_ROOM * room if first else 0.0)) / span


def interval(n, names, values, vehicle, form=None,
             site=HONEYCOMB) -> tuple[float, float] | None:
    """(lo, hi) of a bounded parameter's transform: (0, 1) for gamma (logit), ``_bounds`` for
    the crush peaks, rise and unloading ratio (the primary peak in ``form``, sitting at
    ``site``); None for the others (log, gap)."""
    kind = PARAMS[n][3]
    if kind == "logit":
        return 0.0, 1.0
    if kind in ("over1", "length", "rise"):
        lo, hi = _bounds(n, names, values, vehicle, form, site)
        return float(lo), float(hi)
    return None


# the law extension a length belongs to: it acts on nothing while that extension is off
EXTENSION_OF = {"L_peak1": "peak1", "L_rise1": "peak1", "L_peak2": "peak2"}
# the half-width of a 95 % interval in standard errors, as the fit reports it
Z95 = 1.96


def acts_in(n, vehicle: jl.Vehicle) -> bool:
    """Whether the parameter ``n`` acts in ``vehicle``: it is set, and so is the extension it
    belongs to (``EXTENSION_OF``)."""
    return (PARAMS[n][0](vehicle) is not None
            and PARAMS[EXTENSION_OF.get(n, n)][0](vehicle) is not None)


def value_range(n, names, values, vehicle, form=None,
                site=HONEYCOMB) -> tuple[float, float | None]:
    """(lo, hi) a parameter's transform maps onto (hi None: no upper end): (0, None) for the
    positive ones (log), (F1, None) for F2 at the given F1 (gap), ``interval`` for the
    bounded ones."""
    kind = PARAMS[n][3]
    if kind == "log":
        return 0.0, None
    if kind == "gap":
        return float(_f1_of(names, np.asarray(values, dtype=float), vehicle)), None
    lo, hi = interval(n, names, values, vehicle, form, site)
    return lo, (None if hi is None or not math.isfinite(hi) else hi)


def interval95(value: float, std_error: float, lo: float,
               hi: float | None) -> tuple[float, float] | None:
    """The 95 % interval of a fitted value whose standard error ``std_error`` the delta method
    gave: value +/- 1.96 standard errors in the fit's own coordinates (log(x - lo), or
    logit((x - lo) / (hi - lo)) on a closed range), where the fit's curvature was taken, mapped
    back. It lies inside (lo, hi), where value +/- 1.96 standard errors can
    leave the range (gamma 0.994 +/- 0.035); near the middle of a wide range the two agree.
    None without a finite error or for a value outside its open range."""
    if not (math.isfinite(value) and math.isfinite(std_error) and value > lo
            and (hi is None or value < hi)):
        return None
    # an end that rounds onto the range's own end is kept one float inside it
    inside_lo = math.nextafter(lo, math.inf)
    if hi is None:
        dz = std_error / (value - lo)  # d log(x - lo) / dx = 1 / (x - lo)
        up = Z95 * dz
        return (max(lo + (value - lo) * math.exp(-up), inside_lo),
                lo + (value - lo) * math.exp(up) if up < 700.0 else math.inf)
    w = hi - lo
    u = (value - lo) / w
    z = math.log(u / (1.0 - u))
    dz = std_error / (w * u * (1.0 - u))  # d logit(u) / dx = 1 / (w u (1 - u))

    def back(t):
        x = lo + w * (1.0 / (1.0 + math.exp(-t)) if t >= 0 else
                      math.exp(t) / (1.0 + math.exp(t)))
        return min(max(x, inside_lo), math.nextafter(hi, -math.inf))
    return back(z - Z95 * dz), back(z + Z95 * dz)


def at_bound(names, values, vehicle, rel: float = 1e-6, form=None,
             site=HONEYCOMB) -> tuple[str, ...]:
    """The bounded parameters (gamma in (0, 1); ``_bounds``: crush peaks, rise, unloading
    ratio) whose value lies within ``rel`` of its interval's width from a bound (the
    transform's slope is then below ``rel``: |z| > 13.8 for the default): the optimiser ran
    to the limit of the vehicle's rules there, so the value is the rule's, not the data's, and
    the delta-method standard error through the flat transform says nothing about it. The
    primary peak in ``form``, sitting at ``site`` (``_bounds``)."""
    values = np.asarray(values, dtype=float)
    out = []
    for i, n in enumerate(names):
        bounds = interval(n, names, values, vehicle, form, site)
        if bounds is not None and min(values[i] - bounds[0], bounds[1] - values[i]) <= rel * (
                bounds[1] - bounds[0]):
            out.append(n)
    return tuple(out)


_STAGE = {"log": 0, "logit": 0, "gap": 1, "over1": 2, "length": 3, "rise": 4}  # in order


def to_unconstrained(vehicle: jl.Vehicle, names, form=None, site=HONEYCOMB) -> np.ndarray:
    """Unconstrained coordinates z of the selected parameters of ``vehicle``, its primary peak
    in ``form``, sitting at ``site`` (``_bounds``)."""
    p = get_values(vehicle, names)
    for i, n in enumerate(names):  # an extension that is off starts from its documented value
        if (PARAMS[n][3] == "over1" and p[i] == 1.0) or (
                n in START_IF_OFF and PARAMS[n][0](vehicle) is None):
            p[i] = START_IF_OFF[n]
    f1 = float(_f1_of(names, p, vehicle))
    z = np.zeros(len(names))
    for i, (n, x) in enumerate(zip(names, p)):
        kind = PARAMS[n][3]
        if kind == "log":
            if not x > 0:
                raise jl.ConfigError(PARAMS[n][2], x, "must be > 0 to be fitted (log scale)")
            z[i] = np.log(x)
        elif kind == "logit":
            if not 0 < x < 1:
                raise jl.ConfigError(PARAMS[n][2], x, "must be in (0, 1) to be fitted")
            z[i] = np.log(x / (1 - x))
        elif kind == "gap":
            if not x > f1:
                raise jl.ConfigError(PARAMS[n][2], x, f"must exceed F1 = {f1:g} N")
            z[i] = np.log(x - f1)
        else:  # bounded by the vehicle's rules
            lo, hi = (None if b is None else float(b)
                      for b in _bounds(n, names, p, vehicle, form, site))
            if not (x > lo and (hi is None or x < hi)):
                shown, unit = (x * 1e3, " mm") if kind in ("length", "rise") else (x, "")
                raise jl.ConfigError(
                    PARAMS[n][2], shown, f"must lie in ({lo * (1e3 if unit else 1):.4g}, "
                    f"{'inf' if hi is None else format(hi * (1e3 if unit else 1), '.4g')})"
                    f"{unit} to be fitted (the vehicle's rules for the crush peak and the "
                    "unloading stiffness)")
            u = (x - lo) if hi is None else (x - lo) / (hi - lo)
            z[i] = np.log(u) if hi is None else np.log(u / (1.0 - u))
    return z


def from_unconstrained(z, names, vehicle: jl.Vehicle, form=None, site=HONEYCOMB):
    """Physical values (jnp) from unconstrained coordinates; traceable. Every value obeys the
    vehicle's rules: positive, gamma in (0, 1), F2 > F1, the crush peaks and unloading ratio
    inside their bounds (``_bounds``, the primary peak in ``form``: a name, or a form's code
    traced under jit; sitting at ``site``)."""
    out = [None] * len(names)
    for stage in range(5):
        for i, n in enumerate(names):
            kind = PARAMS[n][3]
            if _STAGE[kind] != stage:
                continue
            if kind == "log":
                out[i] = jnp.exp(z[i])
            elif kind == "logit":  # below 1 (the rule's open end) where the sigmoid rounds
                out[i] = jnp.minimum(1.0 / (1.0 + jnp.exp(-z[i])), 1.0 - BOUND_MARGIN)
            elif kind == "gap":
                out[i] = _f1_of(names, out, vehicle) + jnp.exp(z[i])
            else:
                lo, hi = _bounds(n, names, out, vehicle, form, site)
                out[i] = lo + (jnp.exp(z[i]) if hi is None else (hi - lo) * jax.nn.sigmoid(z[i]))
    return jnp.stack([jnp.asarray(o, dtype=jnp.float64) for o in out])
