"""Reproduce the paper's 0.2 m drop (section 3.1) and tabulate paper vs jaxland.

    python benchmarks/paper_reproduction.py              # table -> benchmarks/results/paper_table.*
    python benchmarks/paper_reproduction.py --calibrate  # re-derive the flow stress sigma_0

The table also carries the paper's own largest error, side by side: its experiment's honeycomb
was pre-compressed, which "could not completely eliminate the force peak", and its simulation
(no peak) was off by 19.72 % on the peak buffer force and measured 43.5 m/s^2 peak body
acceleration against 23.8 simulated. The ``jaxland_crush_peak`` column is the same drop with the
honeycomb's initial crush peak on, at ONE ratio chosen from the literature before looking at the
result (``PEAK_RATIO``: the middle of the 1.0-1.3 x range of pre-crushed aluminium honeycomb,
both stages, decaying over the default 2 mm), not tuned to these numbers.

The paper gives no k_b1, k_b3 or plateau forces. jaxland derives the plateau forces from Table 1
with Wierzbicki's crush formula and one effective foil flow stress sigma_0; ``--calibrate``
bisects sigma_0 so that the first-impact stroke is the paper's 66.5 mm (D_b = 1.5 s/m from
Table 2). The value found is the one in jaxland/_config.py (PAPER_FLOW_STRESS_PA).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import jaxland as jl

OUT = Path(__file__).resolve().parent / "results"

PAPER = {  # paper section 3.1, Figs 9, 12, 13
    "touchdown_s": 0.2,
    "first_impact_end_s": 0.38,
    "second_impact_s": "0.43-0.53",
    "third_impact_start_s": 0.54,
    "first_impact_stroke_mm": 66.5,
    "final_stroke_mm": 68.0,
    "foot_vz_end_first_impact_mps": -0.21,
    "peak_foot_accel_normal_mps2": 1489.0,
    "peak_buffer_velocity_mps": 0.8,
    "peak_body_accel_mps2": 23.8,
    "secondary_engaged_first_impact": True,
    # section 3.3 / Fig. 20a: the experiment (the row above is the paper's simulation)
    "peak_body_accel_measured_mps2": 43.5,
    # section 3.3: the paper's simulation (no crush peak) against the measured peaks
    "no_peak_error_peak_buffer_force_rel": 0.1972,
    "no_peak_error_peak_body_accel_rel": round((43.5 - 23.8) / 43.5, 4),
}
# the crush peak of the side-by-side column: the middle of the pre-crushed honeycomb's
# 1.0-1.3 x range (Honeycomb.peak_ratio1's documented literature range), both stages, over the
# default decay length; chosen before running, not fitted to the paper's numbers
PEAK_RATIO = 1.15
PEAK_LENGTH_MM = 2.0


def vehicle_for(sigma0: float, bonded: bool = False):
    f1, f2 = jl.plateau_forces_from_cells(dict(jl.PAPER_CELLS, flow_stress_Pa=sigma0))
    return jl.vehicle_from_dict({"honeycomb": {
        "cells": {"flow_stress_Pa": sigma0}, "bonded": bonded,
        "k_b1_N_per_m": f1 / 0.47e-3, "k_b3_N_per_m": (f2 - f1) / 0.63e-3}})


def calibrate(target=0.0665, lo=250e6, hi=400e6, tol=0.5e6):
    def stroke(s0):
        return jl.simulate(vehicle=vehicle_for(s0), t_end=0.45).outcomes["first_impact_stroke_m"]

    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stroke(mid) > target else (lo, mid)
        print(f"sigma_0 in [{lo / 1e6:.2f}, {hi / 1e6:.2f}] MPa")
    return 0.5 * (lo + hi)


def row(res) -> dict:
    o, tr = res.outcomes, res.trajectory
    imp = o["impacts"]
    if o["n_contact_changes_logged"] < o["n_contact_changes"]:  # the table lists every impact
        raise SystemExit(f"the contact log kept {o['n_contact_changes_logged']} of "
                         f"{o['n_contact_changes']} contact changes: later impacts are not "
                         "listed, and the table would drop them")
    first_end = imp[0]["end_s"] if imp else None
    t = tr["time_s"]
    window = (t >= imp[0]["start_s"]) & (t <= (first_end or t[-1]))
    return {
        "touchdown_s": o["touchdown_time_s"],
        "first_impact_end_s": first_end,
        "later_impacts_s": [(i["start_s"], i["end_s"]) for i in imp[1:]],  # every one
        "n_impacts": o["n_impacts"],
        "first_impact_stroke_mm": o["first_impact_stroke_m"] * 1e3,
        "max_stroke_mm": o["max_stroke_m"] * 1e3,
        "final_stroke_mm": o["final_stroke_m"] * 1e3,
        "foot_vz_end_first_impact_mps": o["foot_vz_end_first_impact_mps"],
        "peak_foot_accel_normal_mps2": o["peak_foot_accel_normal_mps2"],
        "peak_foot_accel_mps2": o["peak_foot_accel_mps2"],
        "peak_buffer_velocity_mps": float(np.max(tr["buffer_velocity_mps"][window])),
        "peak_body_accel_mps2": o["peak_body_accel_mps2"],
        "secondary_engaged_first_impact": o["first_impact_stroke_m"]
        > float(res.vehicle.honeycomb.x_L2),
        "peak_buffer_force_N": float(np.max(tr["strut_force_N"][window])),
        "peak_honeycomb_force_N": float(np.max(tr["honeycomb_force_N"][window])),
        "energy_closure_rel": o["energy_closure_rel"],
    }


def _cell(v):
    if v is None:
        return "none (stays in contact)"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, list):
        return ", ".join(f"{a:.3f}-{'end' if b is None else format(b, '.3f')}" for a, b in v) or "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def peak_vehicle():
    """The paper vehicle with the documented crush peak (``PEAK_RATIO``) on both stages."""
    return jl.vehicle_from_dict({"honeycomb": {
        "peak_ratio1": PEAK_RATIO, "peak_ratio2": PEAK_RATIO,
        "peak_length1_mm": PEAK_LENGTH_MM, "peak_length2_mm": PEAK_LENGTH_MM}})


def peak_column(free: dict) -> dict:
    """The paper drop with the crush peak, and how far the no-peak run falls below it (the
    paper's error measure: |simulated - measured| / measured, the peak run standing in for the
    measurement)."""
    peak = row(jl.simulate(vehicle=peak_vehicle()))
    peak["peak_ratio_both_stages"] = PEAK_RATIO
    peak["peak_length_mm"] = PEAK_LENGTH_MM
    for key, out in (("peak_buffer_force_N", "no_peak_error_peak_buffer_force_rel"),
                     ("peak_body_accel_mps2", "no_peak_error_peak_body_accel_rel")):
        peak[out] = (peak[key] - free[key]) / peak[key]
    return peak


def peak_markdown(free: dict, peak: dict) -> str:
    """The side-by-side rows of the crush peak (README / docs)."""
    lines = [
        "",
        f"Crush peak on (ratio {PEAK_RATIO} of the plateau on both stages, from the pre-crushed "
        f"honeycomb range 1.0-1.3, decaying over {PEAK_LENGTH_MM:g} mm; not tuned), paper drop "
        "0.2 m:",
        "",
        "| quantity | paper, measured | paper, simulated (no peak) | jaxland, no peak "
        "| jaxland, crush peak |",
        "| --- | --- | --- | --- | --- |",
        f"| peak body acceleration [m/s^2] | {PAPER['peak_body_accel_measured_mps2']} | "
        f"{PAPER['peak_body_accel_mps2']} | {free['peak_body_accel_mps2']:.4g} | "
        f"{peak['peak_body_accel_mps2']:.4g} |",
        f"| peak buffer force, first impact [N] | - | - | {free['peak_buffer_force_N']:.5g} | "
        f"{peak['peak_buffer_force_N']:.5g} |",
        "| no-peak simulation below the peak, peak buffer force [%] | "
        f"{PAPER['no_peak_error_peak_buffer_force_rel'] * 100:.2f} (paper: simulation vs "
        f"measured) | - | - | {peak['no_peak_error_peak_buffer_force_rel'] * 100:.2f} "
        "(no peak vs peak) |",
        "| no-peak simulation below the peak, peak body acceleration [%] | "
        f"{PAPER['no_peak_error_peak_body_accel_rel'] * 100:.1f} (paper) | - | - | "
        f"{peak['no_peak_error_peak_body_accel_rel'] * 100:.1f} (no peak vs peak) |",
        f"| first-impact stroke [mm] | {PAPER['first_impact_stroke_mm']} | - | "
        f"{free['first_impact_stroke_mm']:.4g} | {peak['first_impact_stroke_mm']:.4g} |",
        f"| energy ledger closure (of dissipated) | - | - | {free['energy_closure_rel']:.2g} | "
        f"{peak['energy_closure_rel']:.2g} |",
    ]
    return "\n".join(lines) + "\n"


def table() -> dict:
    free = row(jl.simulate())
    bonded = row(jl.simulate(vehicle=jl.vehicle_from_dict({"honeycomb": {"bonded": True}})))
    peak = peak_column(free)
    lines = [
        "| quantity | paper | jaxland (default, rod slides free) | jaxland (bonded honeycomb) |",
        "| --- | --- | --- | --- |",
    ]
    names = [
        ("touchdown time [s]", "touchdown_s", "touchdown_s"),
        ("end of first impact [s]", "first_impact_end_s", "first_impact_end_s"),
        ("later impacts [s]", "second_impact_s", "later_impacts_s"),
        ("third impact starts [s]", "third_impact_start_s", None),
        ("first-impact stroke [mm]", "first_impact_stroke_mm", "first_impact_stroke_mm"),
        ("max stroke [mm]", None, "max_stroke_mm"),
        ("final stroke [mm]", "final_stroke_mm", "final_stroke_mm"),
        ("foot velocity at end of first impact [m/s]", "foot_vz_end_first_impact_mps",
         "foot_vz_end_first_impact_mps"),
        ("peak foot acceleration, normal (Fig. 12a) [m/s^2]", "peak_foot_accel_normal_mps2",
         "peak_foot_accel_normal_mps2"),
        ("peak foot acceleration, magnitude [m/s^2]", None, "peak_foot_accel_mps2"),
        ("peak buffer velocity, first impact [m/s]", "peak_buffer_velocity_mps",
         "peak_buffer_velocity_mps"),
        ("peak body acceleration [m/s^2]", "peak_body_accel_mps2", "peak_body_accel_mps2"),
        ("secondary honeycomb engaged in first impact", "secondary_engaged_first_impact",
         "secondary_engaged_first_impact"),
        ("energy ledger closure (of dissipated)", None, "energy_closure_rel"),
    ]
    for label, pk, jk in names:
        p = _cell(PAPER[pk]) if pk else "-"
        a = _cell(free[jk]) if jk else "-"
        b = _cell(bonded[jk]) if jk else "-"
        lines.append(f"| {label} | {p} | {a} | {b} |")
    md = "\n".join(lines) + "\n" + peak_markdown(free, peak)
    OUT.mkdir(parents=True, exist_ok=True)
    jl.atomic_write_text(OUT / "paper_table.md", md)
    jl.atomic_write_text(OUT / "paper_table.json", json.dumps(
        dict(paper=PAPER, jaxland_default=free, jaxland_bonded=bonded,
             jaxland_crush_peak=peak), indent=2) + "\n")
    print(md)
    return dict(default=free, bonded=bonded, crush_peak=peak)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calibrate", action="store_true")
    args = ap.parse_args()
    if args.calibrate:
        print(f"sigma_0 = {calibrate() / 1e6:.1f} MPa")
    else:
        table()
