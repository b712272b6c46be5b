"""Design constraints on the full 3-D model: each one's sign and value against an independent
simulation, each one active and respected at the returned design, and the infeasible path with
its CLI exit code.

The case is tiny on purpose (one symmetric 3 m/s vertical landing on the full 3-D model, 0.14 s
from touchdown: the stroke peaks at 0.128 s). The references:
- the rules as the README states them (section "Design"): max stroke (any leg) <= x_L4 - margin,
  minimum stability margin >= threshold, foot slip (any leg) <= limit; normalised by 10 mm,
  0.1 m and 10 mm; g > 0 means violated;
- the outcomes of the same landings run by ``jl.landings`` outside the design code;
- for the stability constraint, geometry: in a symmetric vertical landing the smallest margin is
  the one at release, (R + L_h0 cos theta_b) / sqrt(2) - tau log 4 (tests/test_tipover.py), so
  the steepest strut angle that keeps it >= threshold follows in closed form.
A flipped sign in any constraint makes the optimiser push the wrong way: the returned design
then violates the rule in the independent run, and the sign test sees it directly.
"""

import copy
import json
import math

import jax
import numpy as np
import pytest

import jaxland as jl

VEH = jl.paper_vehicle()
T_END = 0.14
SCALE = dict(stroke=0.01, stability=0.1, slip=0.01)  # README: 10 mm, 0.1 m, 10 mm
TAU_LOG4 = 0.01 * math.log(4.0)  # the margin's soft-min offset at rest (README, 1 cm width)

BASE = dict(
    design=dict(iterations=30, n_scenes=1, scene_seed=1, dt_s=1e-5, t_end_s=T_END,
                model="full", learning_rate=0.2, outer_every=5),
    objective=dict(measure="max"),
    montecarlo=dict(n=1, seed=2, t_end_s=T_END),
    fixed=dict(drop_height_m=0.0, sink_speed_mps=3.0),
)
STROKE_MARGIN_MM = 85.0  # limit x_L4 - 85 mm = 98.2 mm: reached at F2 ~ 7.6 kN (start 9.09 kN)
MIN_MARGIN_M = 1.45  # reached at theta_b = 62.55 deg (start 58.7 deg, margin 1.582 m)
SLIP_LIMIT_MM = 85.0  # reached at F2 ~ 7.5 kN (start: 80.9 mm of slip over the 0.14 s)

# A: F2 and theta_b; the objective (peak acceleration, plus the gear-mass proxy, which falls as
# theta_b steepens: the aux strut gets shorter) pushes F2 down onto the stroke limit and theta_b
# up onto the stability limit. Slip is loose here (1 m) but its sign and value are checked.
SPEC_A = copy.deepcopy(BASE) | dict(
    variables={"F2_N": dict(low=5300.0, high=14000.0), "theta_b_deg": dict(low=50.0, high=68.0)},
    constraints=dict(stroke=dict(margin_mm=STROKE_MARGIN_MM),
                     stability=dict(min_margin_m=MIN_MARGIN_M), slip=dict(max_slip_mm=1000.0)))
SPEC_A["objective"] = dict(measure="max", mass_weight=5.0)
# B: F2 alone against the slip limit (the stroke limit, 20 mm margin, stays loose)
SPEC_B = copy.deepcopy(BASE) | dict(
    variables={"F2_N": dict(low=5300.0, high=14000.0)},
    constraints=dict(stroke=dict(margin_mm=20.0), slip=dict(max_slip_mm=SLIP_LIMIT_MM)))


@pytest.fixture(scope="module")
def outcomes():
    """Independent outcomes: the design scenes run by jl.landings (one compiled function)."""
    solver = jl.Solver(dt=1e-5, t_end=T_END, save_dt=T_END)
    fn = jax.jit(lambda v, s: jl.landings(v, s, solver, "full")[1])

    def run(vehicle, scenes):
        o = {k: np.asarray(v) for k, v in fn(vehicle, scenes).items()}
        return dict(stroke=o["max_stroke_m"].max(axis=1), slip=o["slip_distance_m"].max(axis=1),
                    margin=-o["peak_margin_deficit_m"], tipped=o["tipped"])
    return run


@pytest.fixture(scope="module")
def problem_a():
    return jl.DesignProblem(jl.design_spec_from_dict(copy.deepcopy(SPEC_A)))


@pytest.fixture(scope="module")
def result_a(problem_a):
    return jl.optimise_design(problem_a.spec, problem=problem_a)


@pytest.fixture(scope="module")
def result_b():
    spec = jl.design_spec_from_dict(copy.deepcopy(SPEC_B))
    return jl.optimise_design(spec)


def _limits(vehicle):
    x_l4 = float(vehicle.honeycomb.x_L4)
    return dict(stroke=x_l4 - STROKE_MARGIN_MM * 1e-3, stability=MIN_MARGIN_M,
                slip=SLIP_LIMIT_MM * 1e-3)


def test_constraint_values_and_signs_against_an_independent_run(problem_a, outcomes):
    """At the start design (the paper gear): g = (stroke - (x_L4 - margin)) / 10 mm,
    (threshold - min margin) / 0.1 m and (slip - limit) / 10 mm, from the independent run's
    outcomes, to round-off. Then the Jacobian's signs and one value from geometry: a stronger
    F2 shortens the stroke (dg_stroke/dz_F2 < 0); a steeper strut narrows the footprint, and
    d margin / d theta_b = -L_h0 sin(theta_b) / sqrt(2), times dtheta/dz = (hi - lo) s (1 - s)
    of the documented sigmoid transform."""
    prob = problem_a
    vec, jac, per = prob.evaluate(prob.z0)
    ref = outcomes(VEH, prob.scenes)
    assert not ref["tipped"].any()
    x_l4 = float(VEH.honeycomb.x_L4)
    expect = [(ref["stroke"].max() - (x_l4 - STROKE_MARGIN_MM * 1e-3)) / SCALE["stroke"],
              (MIN_MARGIN_M - ref["margin"].min()) / SCALE["stability"],
              (ref["slip"].max() - 1.0) / SCALE["slip"]]
    np.testing.assert_allclose(vec[2:], expect, rtol=1e-9, atol=1e-9)
    assert vec[2] < 0 and vec[3] < 0 and vec[4] < 0  # the paper gear meets all three here
    # the margin in this landing is the margin at rest: the geometry fixes it
    leg = VEH.leg
    rest = (float(leg.R) + float(leg.L_h0) * math.cos(float(leg.theta_b))) / math.sqrt(2.0)
    assert ref["margin"].min() == pytest.approx(rest - TAU_LOG4, abs=1e-6)
    i_f2, i_th = prob.names.index("F2_N"), prob.names.index("theta_b_deg")
    assert jac[2, i_f2] < 0  # stroke badness falls as F2 rises
    lo, hi = math.radians(50.0), math.radians(68.0)
    th = float(leg.theta_b)
    s = (th - lo) / (hi - lo)
    dmargin_dz = -float(leg.L_h0) * math.sin(th) / math.sqrt(2.0) * (hi - lo) * s * (1 - s)
    assert jac[3, i_th] == pytest.approx(-dmargin_dz / SCALE["stability"], rel=1e-6)
    assert jac[3, i_f2] == pytest.approx(0.0, abs=1e-9)  # F2 does not move the footprint


def test_stroke_and_stability_constraints_active_and_respected(result_a, outcomes):
    """The objective wants a softer, steeper gear; the returned design sits on both limits: in
    an independent run its stroke is within 2 mm below x_L4 - 85 mm (and not above it by more
    than the feasibility tolerance, 1e-3 of 10 mm) and its margin within 2 cm above 1.45 m (not
    below by more than 1e-3 of 0.1 m). theta_b is the closed-form angle where the margin at
    rest equals the threshold, to 0.3 deg."""
    res = result_a
    assert res.status == "feasible", res.violated
    v = res.vehicle
    out = outcomes(v, res.problem.scenes)
    lim = _limits(v)
    tol = res.spec.feasibility_tol
    assert out["stroke"].max() <= lim["stroke"] + tol * SCALE["stroke"]
    assert out["stroke"].max() >= lim["stroke"] - 0.002, (out["stroke"], lim["stroke"])
    assert out["margin"].min() >= lim["stability"] - tol * SCALE["stability"]
    assert out["margin"].min() <= lim["stability"] + 0.02, out["margin"]
    assert res.values["F2_N"] < 0.9 * float(VEH.honeycomb.F2)  # it moved towards the limit
    leg = VEH.leg
    cos_star = ((MIN_MARGIN_M + TAU_LOG4) * math.sqrt(2.0) - float(leg.R)) / float(leg.L_h0)
    assert res.values["theta_b_deg"] == pytest.approx(math.degrees(math.acos(cos_star)), abs=0.3)
    assert res.at_design["objective_measure_mps2"] < res.at_start["objective_measure_mps2"]


def test_slip_constraint_active_and_respected(result_b, outcomes):
    """Softening F2 lowers the peak acceleration and lengthens the foot's outward slide: the
    returned design sits on the slip limit (within 2 mm below 85 mm, never above it by more
    than the feasibility tolerance) with the stroke limit slack."""
    res = result_b
    assert res.status == "feasible", res.violated
    out = outcomes(res.vehicle, res.problem.scenes)
    tol = res.spec.feasibility_tol
    limit = SLIP_LIMIT_MM * 1e-3
    assert out["slip"].max() <= limit + tol * SCALE["slip"]
    assert out["slip"].max() >= limit - 0.002, out["slip"]
    assert out["stroke"].max() < float(res.vehicle.honeycomb.x_L4) - 0.020 - 0.01  # slack
    assert res.values["F2_N"] < float(VEH.honeycomb.F2)


INFEASIBLE = """
[design]
iterations = 2
n_scenes = 1
scene_seed = 5
t_end_s = 0.14
[objective]
measure = "max"
[variables.F2_N]
low = 6000.0
high = 14000.0
[constraints.stroke]
margin_mm = 175.0
[montecarlo]
n = 1
seed = 1
t_end_s = 0.14
[fixed]
drop_height_m = 0.0
sink_speed_mps = 3.0
"""


def test_infeasible_design_exits_4_with_a_report_and_no_vehicle(tmp_path, capsys):
    """A 175 mm margin on x_L4 = 183 mm leaves 8 mm, less than any F2 in the box allows (the
    stroke passes 57.6 mm in the primary stage alone): exit code 4, the report says infeasible
    and names the stroke constraint with g > 0, and no design_vehicle.toml is written."""
    from jaxland.cli import main

    spec = tmp_path / "spec.toml"
    spec.write_text(INFEASIBLE)
    out = tmp_path / "out"
    code = main(["design", str(spec), "--out", str(out), "--verify-n", "0", "--no-plots",
                 "--quiet"])
    assert code == 4
    report = json.loads((out / "design_report.json").read_text())
    assert report["status"] == "infeasible"
    g = report["violated"]["stroke"]["g"]
    assert g > (0.0576 - 0.008) / SCALE["stroke"]  # the primary stage alone overshoots
    assert report["violated"]["stroke"]["rule"].startswith("max stroke")
    assert not (out / "design_vehicle.toml").exists()
    printed = capsys.readouterr()
    # g counts the constraint's scale, and says so: a bare -9.98 read as 9.98 mm, not 99.8
    assert (f"INFEASIBLE: constraint stroke violated, g = {g:+.4g} (in units of 10 mm, "
            "negative: met; max stroke") in printed.err
    (line,) = [x for x in printed.out.splitlines() if x.strip().startswith("constraint stroke")]
    assert line.endswith(f"-> {g:+.4f} (in units of 10 mm, negative: met)"), line
