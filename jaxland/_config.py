"""TOML <-> parameters, validation, and the bundled paper vehicle.

The TOML format has one table per parameter Module, keys carry their unit
(``k_b1_N_per_m``, ``theta_b_deg``, ``x_L2_mm``), and every key is documented by the field
metadata in ``jaxland._params``. A file may give any subset: missing keys take the paper vehicle's
value, unknown keys are refused (they are usually typos). Plateau forces may instead be derived
from honeycomb cell data with Wierzbicki's crush formula (``[honeycomb.cells]``).
"""

from __future__ import annotations

import contextlib
import math
import numbers
from collections.abc import Iterator

import numpy as np

from ._checks import check_int_size
from ._crush import plateau_force
from ._errors import ConfigError
from ._params import Ground, Honeycomb, Leg, Vehicle, concrete, field_info
from ._toml import read_toml

__all__ = ["paper_vehicle", "load_vehicle", "vehicle_from_dict", "vehicle_to_toml",
           "validate_vehicle", "PAPER_CELLS"]

# Table 1 of the paper, and the flow stress we calibrated (docs/paper-comparison.md).
# Effective foil flow stress sigma_0 that makes the 0.2 m drop reproduce the paper's 66.5 mm
# first-impact stroke (with D_b = 1.5 s/m from Table 2). Calibrated by
# `python benchmarks/paper_reproduction.py --calibrate` (310.2 MPa); for comparison, Al 5052-H38
# foil has sigma_0 ~ 270 MPa.
PAPER_FLOW_STRESS_PA = 310e6
PAPER_CELLS = dict(
    flow_stress_Pa=PAPER_FLOW_STRESS_PA,
    section_diameter_mm=98.0,
    primary_cell_size_mm=8.66,
    primary_foil_thickness_mm=0.07,
    secondary_cell_size_mm=5.20,
    secondary_foil_thickness_mm=0.06,
)

# Paper's x_L1 and x_L3 - x_L2 (Table 2, mm), used to set the elastic stiffnesses.
_PAPER_X_L1_MM = 0.47
_PAPER_DX_L3_MM = 58.23 - 57.60


def plateau_forces_from_cells(cells: dict) -> tuple[float, float]:
    """(F1, F2) [N] of the two honeycomb stages from their cells (``PAPER_CELLS``'s keys) by
    Wierzbicki's crush formula."""
    d = cells["section_diameter_mm"] * 1e-3
    s0 = cells["flow_stress_Pa"]
    f1 = plateau_force(cells["primary_cell_size_mm"] * 1e-3,
                       cells["primary_foil_thickness_mm"] * 1e-3, d, s0)
    f2 = plateau_force(cells["secondary_cell_size_mm"] * 1e-3,
                       cells["secondary_foil_thickness_mm"] * 1e-3, d, s0)
    return float(f1), float(f2)


def _paper_dict() -> dict:
    f1, f2 = plateau_forces_from_cells(PAPER_CELLS)
    return {
        "body": dict(m_body_kg=1120.0, m_foot_kg=1.0, g_mps2=9.81,
                     I_xx_kg_m2=round(1120.0 * (3 * 0.6**2 + 3.2**2) / 12.0, 3),
                     I_yy_kg_m2=round(1120.0 * (3 * 0.6**2 + 3.2**2) / 12.0, 3),
                     I_zz_kg_m2=round(1120.0 * 0.6**2 / 2.0, 3), n_legs=4),
        "leg": dict(R_m=0.60, H1_m=0.25, H2_m=1.55, L_h0_m=3.19, theta_b_deg=58.70, h_m=0.092,
                    k_a_N_per_m=5e6, k_topout_N_per_m=1e7, D_b_s_per_m=1.5),
        "honeycomb": dict(
            k_b1_N_per_m=round(f1 / (_PAPER_X_L1_MM * 1e-3), -3), F1_N=round(f1, 1),
            x_L2_mm=57.60,
            k_b3_N_per_m=round((f2 - f1) / (_PAPER_DX_L3_MM * 1e-3), -3), F2_N=round(f2, 1),
            x_L4_mm=183.23, k_bottom_N_per_m=1e8, peak_ratio1=1.0, peak_length1_mm=2.0,
            peak_rise1_mm=0.0, peak_ratio2=1.0, peak_length2_mm=2.0, excess1=[],
            excess_length1_mm=10.0, unload_ratio=1.0, bonded=False),
        "ground": dict(k_N_per_m=2e6, gamma=0.5, chi_s_per_m=2e-4, mu=0.5, k_tan_N_per_m=7e4),
    }


_SECTIONS = {"leg": Leg, "honeycomb": Honeycomb, "ground": Ground}
_TABLE_KEYS = {f.metadata["toml"] for cls in _SECTIONS.values() for f in field_info(cls)
               if f.metadata.get("table")}
_CELL_KEYS = set(PAPER_CELLS)


def _build(cls, section: str, values: dict):
    kwargs = {}
    for f in field_info(cls):
        key = f.metadata["toml"]
        if f.metadata.get("table"):  # a list of numbers; [] is off
            kwargs[f.name] = [float(v) * f.metadata["to_si"] for v in values[key]] or None
            continue
        kwargs[f.name] = float(values[key]) * f.metadata["to_si"]
        if "off" in f.metadata and float(values[key]) == f.metadata["off"]:
            kwargs[f.name] = None  # an optional extension, off: the paper's law, bit for bit
    if cls is Honeycomb:
        bonded = values.get("bonded", False)
        if not isinstance(bonded, bool):
            raise ConfigError("honeycomb.bonded", bonded, "must be true or false")
        kwargs["bonded"] = bonded
    return cls(**kwargs)


def vehicle_from_dict(data: dict, *, validate: bool = True) -> Vehicle:
    """Build a Vehicle from a TOML-shaped dict; missing keys take the paper's values."""
    merged = _paper_dict()
    if not isinstance(data, dict):
        raise ConfigError("config", type(data).__name__, "must be a table of tables")
    for section, table in data.items():
        if section not in merged:
            raise ConfigError(section, "<table>",
                              f"unknown section; known: {', '.join(sorted(merged))}")
        if not isinstance(table, dict):
            raise ConfigError(section, table, "must be a table")
        for key, val in table.items():
            if section == "honeycomb" and key == "cells":
                continue
            if key not in merged[section]:
                raise ConfigError(f"{section}.{key}", val,
                                  f"unknown key; known: {', '.join(merged[section])}")
            if key in _TABLE_KEYS:
                if not isinstance(val, list) or any(
                        isinstance(v, bool) or not isinstance(v, (int, float)) for v in val):
                    raise ConfigError(f"{section}.{key}", val, "must be a list of numbers")
            elif key not in ("bonded", "n_legs") and (
                    isinstance(val, bool) or not isinstance(val, (int, float))):
                raise ConfigError(f"{section}.{key}", val, "must be a number")
            merged[section][key] = val
    cells = data.get("honeycomb", {}).get("cells")
    if cells is not None and not isinstance(cells, dict):
        raise ConfigError("honeycomb.cells", cells, "must be a table ([honeycomb.cells])")
    if cells is not None:
        given = {"F1_N", "F2_N"} & set(data["honeycomb"])
        if given:
            raise ConfigError("honeycomb.cells", "<table>",
                              f"give either [honeycomb.cells] or {sorted(given)}, not both")
        unknown = set(cells) - _CELL_KEYS
        if unknown:
            bad = sorted(unknown)[0]
            raise ConfigError(f"honeycomb.cells.{bad}", cells[bad],
                              f"unknown key; known: {', '.join(sorted(_CELL_KEYS))}")
        full = {**PAPER_CELLS, **cells}
        for key, val in full.items():
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not val > 0:
                raise ConfigError(f"honeycomb.cells.{key}", val, "must be a number > 0")
            check_int_size(f"honeycomb.cells.{key}", val)
        merged["honeycomb"]["F1_N"], merged["honeycomb"]["F2_N"] = plateau_forces_from_cells(full)
    body = merged["body"]
    n_legs = body["n_legs"]
    check_n_legs(n_legs)
    for section in ("body", "leg", "honeycomb", "ground"):
        for key, val in merged[section].items():
            for v in val if isinstance(val, list) else [val]:  # a list: each entry
                check_int_size(f"{section}.{key}", v)
    veh = Vehicle(
        m_body=float(body["m_body_kg"]), m_foot=float(body["m_foot_kg"]), g=float(body["g_mps2"]),
        I_xx=float(body["I_xx_kg_m2"]), I_yy=float(body["I_yy_kg_m2"]),
        I_zz=float(body["I_zz_kg_m2"]),
        leg=_build(Leg, "leg", merged["leg"]),
        honeycomb=_build(Honeycomb, "honeycomb", merged["honeycomb"]),
        ground=_build(Ground, "ground", merged["ground"]),
        n_legs=n_legs,
    )
    if not validate:
        return veh
    try:
        return validate_vehicle(veh)
    except ConfigError as err:  # a plateau force the cells gave: name the cells too
        if cells is not None and err.field in ("honeycomb.F1_N", "honeycomb.F2_N"):
            raise ConfigError(f"{err.field} (from [honeycomb.cells])", err.value,
                              err.rule) from None
        raise


def load_vehicle(path, what: str | None = None) -> Vehicle:
    """Load and validate a vehicle TOML file. ``what`` is the flag or key that gave the path
    (``--config``, ``design.vehicle``): every refusal names the file by it, a refusal of a
    value as ``WHAT PATH: section.key = value: rule``. Without ``what`` (a caller that names
    the file itself) a value's refusal names the key alone, and the file's own as ``config``.
    A file that sets no parameter (empty, comments, empty tables) is refused: every key a file
    leaves out takes the paper's value, so it would load, silently, as the paper vehicle."""
    name = "config" if what is None else what
    data = read_toml(path, name)
    if all(isinstance(t, dict) and not t for t in data.values()):
        raise ConfigError(name, str(path), "sets no vehicle parameter, and would run as the "
                          "paper vehicle (every key left out takes the paper's value); give "
                          "the vehicle's values (`jaxland config` prints the paper vehicle's, "
                          "to edit)")
    try:
        return vehicle_from_dict(data)
    except ConfigError as err:
        if what is None:
            raise
        raise ConfigError(f"{what} {path}: {err.field}", err.value, err.rule) from None


@contextlib.contextmanager
def named_by_file(what: str | None, path) -> Iterator[None]:
    """A refusal of one of the vehicle's own keys raised after the file loaded (a stable step
    no run can take: ``refuse_unsteppable``) names the file as ``load_vehicle(path, what)``
    names it; ``what`` None (the paper vehicle) leaves refusals as they are."""
    try:
        yield
    except ConfigError as err:
        keys = {f"{s}.{f.metadata['toml']}" for s, _, f in vehicle_fields(paper_vehicle())}
        if what is None or err.field not in keys:
            raise
        raise ConfigError(f"{what} {path}: {err.field}", err.value, err.rule) from None


def _breakpoint_error(hc: Honeycomb, names: tuple[str, ...], rule: str):
    """Raise the honeycomb breakpoint rule ``rule`` naming the likeliest culprit of the
    fields it involves (``names``): ``_culprit_error``."""
    _culprit_error({"honeycomb": hc}, [("honeycomb", n) for n in names], rule)


def _culprit_error(modules: dict, fields: list[tuple[str, str]], rule: str):
    """Raise the cross-field rule ``rule`` naming, of the ``(section, field)`` pairs it
    involves (all positive by their own rules; ``modules``: section -> the vehicle's module),
    the one furthest from the paper vehicle's value by ratio either way: the likeliest slip
    (a stiffness typed in the wrong unit), not a field the user left alone. A tie names the
    first."""
    paper = paper_vehicle()
    paper_mods = {"body": paper, "leg": paper.leg, "honeycomb": paper.honeycomb,
                  "ground": paper.ground}

    def off(pair):
        section, name = pair
        val = np.asarray(concrete(getattr(modules[section], name)), dtype=float)
        return float(np.max(np.abs(np.log(val / float(getattr(paper_mods[section], name))))))

    section, name = max(fields, key=off)
    f = {f.name: f for f in field_info(type(modules[section]))}[name]
    val = np.asarray(concrete(getattr(modules[section], name)), dtype=float)
    val = val.flat[0] / f.metadata["to_si"]
    raise ConfigError(f"{section}.{f.metadata['toml']}", float(f"{val:.12g}"), rule)


def paper_vehicle() -> Vehicle:
    """The paper's vehicle (Tables 1-2) with our documented choices for what it leaves open."""
    return vehicle_from_dict({})


# ----------------------------------------------------------------------------------- checks

# A field's rule is one of these value rules (checked here, field by field) or a cross-field
# rule (checked in ``validate_vehicle`` below). ``_check_rules`` refuses any other text at
# import, so a mistyped rule cannot silently turn its check off.
VALUE_RULES = {
    "> 0": lambda v: v > 0,
    ">= 0": lambda v: v >= 0,
    ">= 1": lambda v: v >= 1,
    "in [0, 1)": lambda v: (v >= 0) & (v < 1),
    "in (0, 90) deg": lambda v: (v > 0) & (v < math.pi / 2),
}
CROSS_FIELD_RULES = {"> F1", "> x_L1", "> x_L3"}


def _check_rules() -> None:
    for cls in (Vehicle, *_SECTIONS.values()):
        for f in field_info(cls):
            rule = f.metadata["rule"]
            if rule not in VALUE_RULES and rule not in CROSS_FIELD_RULES:
                raise RuntimeError(f"{cls.__name__}.{f.name}: unknown validity rule {rule!r}; "
                                   "add it to VALUE_RULES or CROSS_FIELD_RULES")


_check_rules()


def _rule_ok(rule: str, val: np.ndarray) -> np.ndarray | None:
    check = VALUE_RULES.get(rule)
    return None if check is None else check(val)  # None: a cross-field rule, checked below


def vehicle_fields(veh: Vehicle):
    """``(section, module, field)`` of every documented parameter of ``veh``, in TOML order:
    the body's, then the leg's, the honeycomb's and the ground's."""
    for section, mod in (("body", veh), ("leg", veh.leg), ("honeycomb", veh.honeycomb),
                         ("ground", veh.ground)):
        for f in field_info(type(mod)):
            yield section, mod, f


def field_ok(f, val, xp=np):
    """Per element, whether a value of the parameter field ``f`` keeps its own rule: finite,
    and within the rule or at the extension's "off" value (the one rule for concrete values,
    ``validate_vehicle``, and traced ones, ``follows_rules``; ``xp``: numpy or jax.numpy)."""
    good = xp.isfinite(val)
    ok = _rule_ok(f.metadata["rule"], val)
    if ok is not None:
        good = good & ok
    off = f.metadata.get("off")  # "not used": a TOML file's is read as None, a traced one stays
    if isinstance(off, float):
        good = good | (val == off)
    return good


def _fail(section, f, val, rule):
    md = f.metadata
    shown = float(val) / md["to_si"]
    off = md.get("off")  # an extension's "not used" value, allowed beside the rule
    ok = None if off is None else _rule_ok(rule, np.asarray(off))
    either = "" if ok is None or np.all(ok) else f" or {off / md['to_si']:g} (off)"
    # inf keeps a rule such as ">= 0" by its letter: the rule says finite too
    finite = "" if math.isfinite(float(val)) else "finite and "
    raise ConfigError(f"{section}.{md['toml']}", shown,
                      f"must be {finite}{rule}{either} ({md['doc']})")


# the leg counts the models hold: the legs stand evenly around the axis, and fewer than three
# stand on no area
N_LEGS_RANGE = (3, 12)


def check_n_legs(n_legs) -> None:
    """Refuse a leg count outside ``N_LEGS_RANGE``."""
    lo, hi = N_LEGS_RANGE
    if (isinstance(n_legs, bool) or not isinstance(n_legs, numbers.Integral)
            or not lo <= n_legs <= hi):
        raise ConfigError("body.n_legs", n_legs, f"must be an integer in [{lo}, {hi}]")


def validate_vehicle(veh: Vehicle, *, fields_only: bool = False) -> Vehicle:
    """Check every field against its rule and the cross-field rules (``fields_only``: each
    field against its own rule, and the honeycomb's stages in order, ``stages_in_order``,
    without which the law itself breaks); return ``veh`` if valid.

    Raises ``ConfigError`` naming the TOML key, the value (in TOML units) and the rule. Leaves
    that are tracers (inside jit/grad) are skipped; batched leaves are checked element-wise.
    """
    check_n_legs(veh.n_legs)
    for section, mod, f in vehicle_fields(veh):
        val = concrete(getattr(mod, f.name))
        if val is None:
            continue
        bad = ~field_ok(f, val)
        if np.any(bad):
            _fail(section, f, val[bad].flat[0], f.metadata["rule"])
    hc = veh.honeycomb
    F1, F2, k1, k3 = (concrete(x) for x in (hc.F1, hc.F2, hc.k_b1, hc.k_b3))
    x2, x4 = concrete(hc.x_L2), concrete(hc.x_L4)
    known = all(x is not None for x in (F1, F2, k1, k3, x2, x4))
    if known:  # the law's own structure: checked with the fields (follows_rules too)
        x1 = F1 / k1
        x3 = x2 + (F2 - F1) / k3
        f2_ok, x2_ok, x4_ok = stages_in_order(F1, F2, x1, x2, x3, x4)
        if np.any(~f2_ok):
            raise ConfigError("honeycomb.F2_N", float(np.max(F2)),
                              f"must exceed F1_N = {float(np.min(F1))} (the secondary stage "
                              "crushes after the primary)")
        if np.any(~x2_ok):
            _breakpoint_error(hc, ("x_L2", "F1", "k_b1"),
                              f"breakpoints must increase: x_L1 = F1/k_b1 = "
                              f"{float(np.max(x1)) * 1e3:.4g} mm must be < x_L2 = "
                              f"{float(np.min(x2)) * 1e3:.4g} mm")
        if np.any(~x4_ok):
            _breakpoint_error(hc, ("x_L4", "x_L2", "F1", "F2", "k_b3"),
                              f"breakpoints must increase: x_L3 = x_L2 + (F2-F1)/k_b3 = "
                              f"{float(np.max(x3)) * 1e3:.4g} mm must be < x_L4 = "
                              f"{float(np.min(x4)) * 1e3:.4g} mm")
    if fields_only:
        return veh
    if known:
        _check_peaks_and_unloading(hc, veh.ground, F1, F2, k1, k3, x2, x4)
    inertia = [concrete(x) for x in (veh.I_xx, veh.I_yy, veh.I_zz)]
    if all(x is not None for x in inertia):
        names = ("I_xx_kg_m2", "I_yy_kg_m2", "I_zz_kg_m2")
        moments = [np.ravel(x) for x in np.broadcast_arrays(*inertia)]  # one vehicle per entry
        for i, name in enumerate(names):
            j, k = (i + 1) % 3, (i + 2) % 3
            bad = np.flatnonzero(~(moments[i] <= moments[j] + moments[k]))
            if bad.size:  # the other two by name: one of them may be the mistyped one
                at = bad[0]
                raise ConfigError(f"body.{name}", float(moments[i][at]),
                                  f"must be <= the sum of the other two principal moments, "
                                  f"{names[j]} + {names[k]} = {moments[j][at]:.6g} + "
                                  f"{moments[k][at]:.6g} kg m^2: no rigid body has such an "
                                  "inertia")
    leg = veh.leg
    L, th, H2 = concrete(leg.L_h0), concrete(leg.theta_b), concrete(leg.H2)
    if x4 is not None and L is not None and np.any(~(x4 < L)):
        _culprit_error({"honeycomb": hc, "leg": leg}, [("honeycomb", "x_L4"), ("leg", "L_h0")],
                       f"the buffer stroke x_L4 = {float(np.max(x4)) * 1e3:.6g} mm must be "
                       f"shorter than the main strut L_h0 = {float(np.min(L)) * 1e3:.6g} mm")
    if all(x is not None for x in (L, th, H2)) and np.any(~(L * np.sin(th) > H2 * 1.05)):
        raise ConfigError("leg.L_h0_m", float(np.min(L)),
                          "the foot must lie clearly below the auxiliary joint A "
                          "(L_h0 sin theta_b > 1.05 H2), or the inverted triangle degenerates")
    return veh


def follows_rules(veh: Vehicle):
    """Whether every field of ``veh`` is finite and keeps its own rule, and the honeycomb's
    stages come in order (``stages_in_order``), as a jnp bool (also for traced values,
    inside jit and grad, where ``validate_vehicle`` cannot look). The other rules between
    fields stay the loaders' and ``simulate``'s: a fit's crush-peak forms may bend them on
    purpose."""
    import jax.numpy as jnp

    ok = jnp.ones((), bool)
    for _, mod, f in vehicle_fields(veh):
        val = getattr(mod, f.name)
        if val is not None:
            ok = ok & jnp.all(field_ok(f, jnp.asarray(val), jnp))
    hc = veh.honeycomb
    for in_order in stages_in_order(hc.F1, hc.F2, hc.x_L1, hc.x_L2, hc.x_L3, hc.x_L4):
        ok = ok & jnp.all(in_order)
    return ok


def stages_in_order(F1, F2, x_L1, x_L2, x_L3, x_L4):
    """Per element (numpy or jax values alike): F2 > F1, x_L1 < x_L2 and x_L3 < x_L4, the
    honeycomb's stages in order. Out of order the law's clip has a negative width and an
    unstroked honeycomb pulls, so these hold wherever the law runs: ``validate_vehicle``
    checks them with each field's own rule (also with ``fields_only``), ``follows_rules``
    on traced values."""
    return F2 > F1, x_L1 < x_L2, x_L3 < x_L4


def _check_peaks_and_unloading(hc, ground, F1, F2, k1, k3, x2, x4):
    """Cross-field rules of the honeycomb's optional crush peaks and unloading stiffness (each
    checked only where the extension is on: a peak ratio above 1, an unloading ratio above 1)."""
    def value(x, off=1.0):  # None: the extension is off
        return np.asarray(off) if x is None else concrete(x)

    r1, L1, r2, L2, rho = (value(x) for x in (hc.peak_ratio1, hc.peak_length1, hc.peak_ratio2,
                                              hc.peak_length2, hc.unload_ratio))
    k = concrete(ground.k)
    if any(x is None for x in (r1, L1, r2, L2, rho, k)):
        return
    x1, x3 = F1 / k1, x2 + (F2 - F1) / k3
    stages = (("1", r1, L1, F1, k1, x1, x2, "x_L2", "F2_N", F2),
              ("2", r2, L2, F2, k3, x3, x4, "x_L4", None, None))
    rise = concrete(hc.peak_rise1) if hc.peak_rise1 is not None else None
    if hc.peak_rise1 is not None and rise is None:  # a tracer: not checked
        return
    for i, r, length, F, k_el, start, end, end_name, above, F_above in stages:
        on = r > 1
        a = (r - 1) * F
        up = a / k_el  # crush (stroke) of the rise to the peak: elastic, or the rise length
        if i == "1" and rise is not None:
            up = rise
            if np.any(on & ~(a / rise < k1)):
                raise ConfigError("honeycomb.peak_rise1_mm", float(np.min(rise)) * 1e3,
                                  f"the peak builds up at (r1 - 1) F1 / rise = "
                                  f"{float(np.max(a / rise)):.4g} N/m, which must be < k_b1 = "
                                  f"{float(np.min(k1)):.6g} N/m (a faster rise is elastic, not "
                                  "crushing): a longer rise")
        done = start + up + length  # stroke where the peak has decayed to the plateau
        if np.any(on & ~(done < end)):
            raise ConfigError(f"honeycomb.peak_length{i}_mm", float(np.max(length)) * 1e3,
                              f"the peak must end before {end_name}: its rise to r F and decay "
                              f"end at {float(np.max(done)) * 1e3:.4g} mm, not < "
                              f"{end_name} = {float(np.min(end)) * 1e3:.4g} mm")
        if above is not None and np.any(on & ~(r * F < F_above)):
            raise ConfigError(f"honeycomb.peak_ratio{i}", float(np.max(r)),
                              f"the primary peak r1 F1 = {float(np.max(r * F)):.6g} N must stay "
                              f"below {above} = {float(np.min(F_above)):.6g} N (or the "
                              "secondary block would crush first)")
        slope = a / length  # N/m, the negative stiffness of the falling branch
        if np.any(on & ~(slope <= 0.5 * k)):
            raise ConfigError(f"honeycomb.peak_length{i}_mm", float(np.min(length)) * 1e3,
                              f"the falling slope (r - 1) F / L = {float(np.max(slope)):.4g} N/m "
                              f"is a negative stiffness and must be <= k / 2 = "
                              f"{float(np.min(k)) * 0.5:.4g} N/m (ground.k_N_per_m): a longer "
                              "decay or a smaller ratio, or the foot snaps through")
    if hc.excess1 is not None:
        _check_excess_table(hc, k, F1, F2, k1, x1, x2, rise)
    if np.any(~(rho * k3 <= np.maximum(k1, k3))):
        raise ConfigError("honeycomb.unload_ratio", float(np.max(rho)),
                          f"the unloading stiffness unload_ratio k_b3 = "
                          f"{float(np.max(rho * k3)):.6g} N/m must be <= max(k_b1, k_b3) = "
                          f"{float(np.min(np.maximum(k1, k3))):.6g} N/m (the stack cannot unload "
                          "stiffer than its stiffest stage; the stable step assumes it)")


def _check_excess_table(hc, k, F1, F2, k1, x1, x2, rise=None):
    """Cross-field rules of the primary's tabulated strength excess (``Honeycomb.excess1``),
    built up over the crush ``rise`` [m] first where ``peak_rise1`` is on."""
    t, length = concrete(hc.excess1), concrete(hc.excess_length1)
    if t is None or length is None:
        return
    if hc.peak_ratio1 is not None:
        raise ConfigError("honeycomb.excess1", "[...]", "give either peak_ratio1 or excess1, "
                          "not both (each sets the primary's crush peak)")
    e = t * np.expand_dims(F1, -1)  # N, at the nodes
    n = e.shape[-1]
    dc = np.expand_dims(length / n, -1)
    slope = np.diff(np.concatenate([e, np.zeros_like(e[..., :1])], axis=-1), axis=-1) / dc
    if rise is not None and np.any(~(e[..., 0] / rise < k1)):  # the build-up 0 -> e_0
        raise ConfigError("honeycomb.peak_rise1_mm", float(np.min(rise)) * 1e3,
                          f"the excess builds up at e_0 F1 / rise = "
                          f"{float(np.max(e[..., 0] / rise)):.4g} N/m, which must be < k_b1 = "
                          f"{float(np.min(k1)):.6g} N/m (a faster rise is elastic, not "
                          "crushing): a longer rise")
    # stroke where the excess has ended: past the elastic rise to F1 + e_0, or to F1 and the
    # build-up
    done = x1 + (e[..., 0] / k1 if rise is None else rise) + length
    if np.any(~(done < x2)):
        raise ConfigError("honeycomb.excess_length1_mm", float(np.max(length)) * 1e3,
                          "the excess must end before x_L2: its onset"
                          + (" and length" if rise is None else ", build-up (peak_rise1_mm) "
                             "and length") + " end at "
                          f"{float(np.max(done)) * 1e3:.4g} mm, not < x_L2 = "
                          f"{float(np.min(x2)) * 1e3:.4g} mm")
    if np.any(~(F1 + e.max(axis=-1) < F2)):
        raise ConfigError("honeycomb.excess1", float(np.max(t)),
                          f"the primary's strength F1 (1 + excess) = "
                          f"{float(np.max(F1 + e.max(axis=-1))):.6g} N must stay below F2_N = "
                          f"{float(np.min(F2)):.6g} N (or the secondary block would crush first)")
    k1_ = np.expand_dims(k1, -1)
    if np.any(~(slope < k1_)):
        raise ConfigError("honeycomb.excess1", float(np.max(t)),
                          f"the excess rises at {float(np.max(slope)):.4g} N/m of crush, which "
                          f"must be < k_b1 = {float(np.min(k1)):.6g} N/m (a faster rise is "
                          "elastic, not crushing: the plastic set would shrink); refine the "
                          "table or lengthen excess_length1_mm")
    if np.any(~(-slope <= 0.5 * np.expand_dims(k, -1))):
        raise ConfigError("honeycomb.excess_length1_mm", float(np.min(length)) * 1e3,
                          f"the excess falls at {float(np.max(-slope)):.4g} N/m of crush, a "
                          f"negative stiffness that must be <= k / 2 = "
                          f"{float(np.min(k)) * 0.5:.4g} N/m (ground.k_N_per_m): a longer "
                          "table or a smaller excess, or the foot snaps through")


# ----------------------------------------------------------------------------------- output

def _fmt(val) -> str:
    if isinstance(val, bool):
        return "true" if val else "false"
    if isinstance(val, int):
        return str(val)
    text = f"{float(val):.12g}"
    return text if any(c in text for c in ".e") else text + ".0"


def _unit(md) -> str:
    """The unit shown for a field: its TOML key's, and "-" for a dimensionless one."""
    unit = "deg" if md["toml"].endswith("_deg") else (
        "mm" if md["toml"].endswith("_mm") else md["unit"])
    return "-" if unit == "1" else unit


def _value_text(md, val) -> str:
    """A field's value as the TOML writes it (in the key's units; an extension that is off, at
    its "off" value)."""
    if val is None:  # an extension, off
        val = md["off"] if md.get("table") else md["off"] * md["to_si"]
    if md.get("table"):
        return "[" + ", ".join(_fmt(float(v) / md["to_si"])
                               for v in np.ravel(np.asarray(val, dtype=float))) + "]"
    return _fmt(float(val) / md["to_si"])


def _texts(veh: Vehicle) -> dict:
    """``"section.key" -> value as written`` of every documented parameter of ``veh``."""
    return {f"{section}.{f.metadata['toml']}": _value_text(f.metadata, getattr(mod, f.name))
            for section, mod, f in vehicle_fields(veh)}


def vehicle_to_toml(veh: Vehicle | None = None, *, given: set | None = None,
                    given_by: str = "the configuration file", changed_by: str | None = None,
                    base: Vehicle | None = None) -> str:
    """Render a vehicle (default: the paper's) as a commented TOML document.

    Each key cites the source of its value. A key whose value, as written, is the paper
    vehicle's cites the paper vehicle's source; any other never does: keys in ``given``
    ("section.key") are marked as set by ``given_by``; with ``honeycomb.cells`` given, F1_N and
    F2_N as derived from its cells; a key whose value differs from ``base``'s (default: the
    paper vehicle) as ``changed_by`` (who changed it: "FITTED", "DESIGNED", ...), where given;
    and every other key that differs from the paper vehicle as differing from it, with the
    paper vehicle's value and that value's source."""
    veh = paper_vehicle() if veh is None else veh
    given = set() if given is None else given
    paper = _texts(paper_vehicle())
    start = paper if base is None else _texts(base)
    lines = [
        "# jaxland vehicle configuration (SI units unless the key says otherwise).",
        "# Each key: value, then its meaning, source and validity rule.",
        "",
        "[body]",
    ]

    def line(section, md, val):
        key = f"{section}.{md['toml']}"
        text = _value_text(md, val)
        if key in ("honeycomb.F1_N", "honeycomb.F2_N") and "honeycomb.cells" in given:
            source = f"DERIVED from the [honeycomb.cells] of {given_by} (Wierzbicki 1983)"
        elif text == paper[key]:  # set by the file or not, the paper's value has its source
            source = md["source"]
        elif key in given:
            source = f"SET BY {given_by}"
        else:  # not the paper's value: its source is not the paper vehicle's
            was = f"the paper vehicle's value {paper[key]}, whose source is {md['source']}"
            source = (f"{changed_by}: not {was}" if changed_by is not None
                      and text != start[key] else f"NOT {was}")
        return (f"{md['toml']} = {text}"
                f"  # {md['doc']} [{_unit(md)}]; {source}; rule {md['rule']}")

    for f in field_info(Vehicle):
        lines.append(line("body", f.metadata, getattr(veh, f.name)))
    lines.append(f"n_legs = {veh.n_legs}  # number of legs, equally spaced in azimuth; "
                 f"an integer in [{N_LEGS_RANGE[0]}, {N_LEGS_RANGE[1]}]")
    for section, mod in (("leg", veh.leg), ("honeycomb", veh.honeycomb), ("ground", veh.ground)):
        lines += ["", f"[{section}]"]
        for f in field_info(type(mod)):
            lines.append(line(section, f.metadata, getattr(mod, f.name)))
        if section == "honeycomb":
            bonded_doc = Honeycomb.__dataclass_fields__["bonded"].metadata["doc"]
            lines.append(f"bonded = {_fmt(mod.bonded)}  # {bonded_doc}")
            lines.append(f"# derived: x_L1 = F1/k_b1 = {float(mod.x_L1) * 1e3:.4f} mm, "
                         f"x_L3 = x_L2 + (F2-F1)/k_b3 = {float(mod.x_L3) * 1e3:.4f} mm")
            lines.append("# Instead of F1_N/F2_N you may give the cell data and let jaxland derive")
            lines.append("# the plateau forces with Wierzbicki (1983), e.g. (paper Table 1):")
            lines.append("# [honeycomb.cells]")
            for k, v in PAPER_CELLS.items():
                lines.append(f"# {k} = {_fmt(v)}")
    return "\n".join(lines) + "\n"
