"""Gear design: robust-objective gradients against finite differences, a known optimum from an
energy balance, constraints at the returned design, infeasible specs reported, malformed specs
refused by name, and the CLI writing its files."""

import copy
import csv
import dataclasses
import json
import math
import tomllib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl
from jaxland import (
    DesignProblem,
    apply_design,
    design_spec_from_dict,
    gear_mass_kg,
    optimise_design,
    risk_measure,
)

# ---------------------------------------------------------------------------- (a) gradients

ROBUST = dict(
    design=dict(iterations=0, n_scenes=4, scene_seed=3, dt_s=1e-5, t_end_s=0.15),
    objective=dict(measure="cvar", level=0.5),
    variables={"F1_N": dict(low=2000.0, high=8000.0), "x_L2_mm": dict(low=20.0, high=150.0),
               "k_a_N_per_m": dict(low=1e6, high=2e7)},
    constraints=dict(stroke=dict(margin_mm=20.0, measure="cvar", level=0.5)),
    montecarlo=dict(n=4, seed=4),
    fixed=dict(drop_height_m=0.0),
    dispersion={"sink_speed_mps": dict(dist="uniform", low=1.6, high=2.6),
                "mass_scale": dict(dist="normal", mean=1.0, std=0.05)},
)


@pytest.fixture(scope="module")
def robust_problem():
    return DesignProblem(design_spec_from_dict(copy.deepcopy(ROBUST)))


def _fd(prob, z0, h):
    cols = []
    for i in range(z0.size):
        e = np.zeros_like(z0)
        e[i] = h
        cols.append((prob.evaluate(z0 + e, False)[0] - prob.evaluate(z0 - e, False)[0]) / (2 * h))
    return np.stack(cols, axis=1)


def test_robust_gradient_matches_central_differences(robust_problem):
    """d/dz of [CVaR_0.5 of peak body acceleration over 4 dispersed scenes, gear mass, CVaR_0.5
    stroke constraint] by jacfwd = central differences. Quarter model over the first impact
    (0.15 s from touchdown), in the unconstrained coordinates z.

    h = 1e-6: inside one smooth piece of the discrete map (the step at which each peak occurs
    does not change), AD is its exact derivative; measured agreement 1e-6 relative (round-off
    ~1e-12 / h), asserted 1e-4 of the row's largest entry.
    h = 1e-3 (an optimiser step's scale): the running peaks switch steps and the CVaR switches
    scenes, so the secant differs from the local slope by the kinks: measured <= 3 % (F1, x_L2
    on the peak), asserted 6 %. That is the honest size of the gap between the exact gradient
    and the jagged-at-small-scale landscape the optimiser walks on."""
    prob = robust_problem
    z0 = prob.z0 + np.array([0.1, -0.2, 0.15])  # off the baseline, not at a special point
    vec, jac, per = prob.evaluate(z0)
    assert not per["failed"].any()
    assert np.all(np.isfinite(jac))
    for h, tol in ((1e-6, 1e-4), (1e-3, 6e-2)):
        fd = _fd(prob, z0, h)
        for row in range(jac.shape[0]):
            scale = np.max(np.abs(fd[row]))
            np.testing.assert_allclose(jac[row], fd[row], rtol=0, atol=tol * scale,
                                       err_msg=f"measure {row}, h = {h}")
    # and the measures are what they say: CVaR_0.5 of 4 scenes is the mean of the worst 2
    worst2 = np.sort(per["peak_body_accel_mps2"])[-2:].mean()
    assert vec[0] == pytest.approx(worst2, rel=1e-12)



def test_ill_conditioned_derivatives_are_replaced_by_the_typical_scenes():
    """guard_ill_conditioned: values unchanged; a tangent beyond ILL_CONDITIONED x the median
    |value| becomes the median tangent of the other scenes; well-conditioned tangents are
    bit for bit the same; with every scene ill-conditioned the tangent is 0, not NaN."""
    from jaxland._design._problem import ILL_CONDITIONED, guard_ill_conditioned

    def f(z):
        return jnp.stack([1.0 + 0.1 * z, 2.0 + 0.2 * z, 1.5 + 0.15 * z,
                          1.0 + 1e-7 * jnp.sin(1e10 * z)])  # the last: 1e3 x its size

    v, t = jax.jvp(lambda z: guard_ill_conditioned(f(z)), (0.0,), (1.0,))
    assert np.array_equal(v, f(0.0))
    assert np.array_equal(t, [0.1, 0.2, 0.15, 0.15])
    well = lambda z: f(z)[:3]  # noqa: E731
    assert np.array_equal(jax.jvp(lambda z: guard_ill_conditioned(well(z)), (0.0,), (1.0,))[1],
                          jax.jvp(well, (0.0,), (1.0,))[1])
    _, t_all = jax.jvp(lambda z: guard_ill_conditioned(
        jnp.stack([1.0 + 1e3 * ILL_CONDITIONED * z, 1.0 - 1e3 * ILL_CONDITIONED * z])),
        (0.0,), (1.0,))
    assert np.array_equal(t_all, [0.0, 0.0])


class _Injected(DesignProblem):
    """The robust problem with the max stroke of its worst scene (the one the CVaR weights
    most) made to wiggle 1 um on a uN scale of F1: its derivative (~1e3 m per unit z) dwarfs
    the true response of a stroke."""

    def _per_scene(self, veh, scenes):
        per = super()._per_scene(veh, scenes)
        wiggle = 1e-6 * jnp.sin(1e6 * veh.honeycomb.F1)
        worst = jnp.argmax(per["max_stroke_m"])
        return dict(per, max_stroke_m=per["max_stroke_m"].at[worst].add(wiggle))


def test_an_ill_conditioned_design_scene_is_flagged_and_kept_out_of_the_gradient(
        robust_problem):
    """The design Jacobian of the stroke constraint (CVaR_0.5 over 4 scenes) with one
    ill-conditioned scene stays of the size it has without it (the scene moves as the median
    of the others), where the raw derivative would put ~1e5 into that row; the scene, and only
    it, is reported ill-conditioned. Its value still counts in the measures."""
    z0 = robust_problem.z0 + np.array([0.1, -0.2, 0.15])
    vec, jac, per = robust_problem.evaluate(z0)
    assert not per["ill_conditioned"].any()
    inj = _Injected(design_spec_from_dict(copy.deepcopy(ROBUST)))
    vec_i, jac_i, per_i = inj.evaluate(z0)
    worst = np.argmax(per["max_stroke_m"])
    assert np.flatnonzero(per_i["ill_conditioned"]).tolist() == [worst]
    assert np.all(np.isfinite(jac_i))
    np.testing.assert_allclose(vec_i, vec, rtol=0, atol=1e-4)  # the 1 um wiggle / 0.01 m scale
    row = 2  # the stroke constraint
    assert np.max(np.abs(jac_i[row])) < 2.0 * np.max(np.abs(jac[row]))
    np.testing.assert_array_equal(jac_i[:row], jac[:row])  # objective and mass untouched


def test_design_scenes_split_over_devices_give_the_one_device_evaluation(robust_problem,
                                                                         tmp_path):
    """The design scenes are split over the local devices (``DesignProblem``): with 3 CPU
    devices the 4 scenes are padded to 6 and the copies dropped, so the measures, their
    Jacobian and the per-scene outcomes are the one-device ones (quarter model, a well-posed
    scene set: to round-off)."""
    import subprocess
    import sys
    import textwrap

    z0 = robust_problem.z0 + np.array([0.1, -0.2, 0.15])
    code = textwrap.dedent(f"""
        import copy, numpy as np, jax
        jax.config.update("jax_num_cpu_devices", 3)
        from jaxland import DesignProblem, design_spec_from_dict
        prob = DesignProblem(design_spec_from_dict({ROBUST!r}))
        assert len(jax.local_devices()) == 3 and prob._padded == 6
        vec, jac, per = prob.evaluate(np.array({z0.tolist()!r}))
        np.savez("{tmp_path}/split.npz", vec=vec, jac=jac, **per)
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    got = np.load(tmp_path / "split.npz")
    vec, jac, per = robust_problem.evaluate(z0)
    np.testing.assert_allclose(got["vec"], vec, rtol=1e-9)
    np.testing.assert_allclose(got["jac"], jac, rtol=1e-7, atol=1e-9 * np.abs(jac).max())
    for k, v in per.items():
        assert got[k].shape == v.shape, k
        np.testing.assert_allclose(got[k], v, rtol=1e-9, err_msg=k)


def test_risk_measures_against_direct_definitions():
    x = np.array([3.0, 1.0, 4.0, 1.5, 9.0])
    assert float(risk_measure(x, "mean")) == pytest.approx(x.mean())
    assert float(risk_measure(x, "max")) == 9.0
    # CVaR_0.7 of 5 samples: worst 1.5 samples -> (9 + 0.5 * 4) / 1.5
    assert float(risk_measure(x, "cvar", 0.7)) == pytest.approx((9.0 + 0.5 * 4.0) / 1.5)
    assert float(risk_measure(x, "cvar", 0.0)) == pytest.approx(x.mean())
    # normal at 0.99: mean + Phi^-1(0.99) sample std (N - 1)
    assert float(risk_measure(x, "normal", 0.99)) == pytest.approx(
        x.mean() + 2.3263478740408408 * x.std(ddof=1), rel=1e-12)
    assert float(risk_measure(x, "normal", 0.5)) == pytest.approx(x.mean())


def test_normal_measure_gradient_is_finite_and_exact():
    """d/dx_i (mean + z std) = 1/N + z (x_i - mean) / ((N - 1) std); finite (zero spread term)
    when every value is equal (double where)."""
    import jax

    x = np.array([3.0, 1.0, 4.0, 1.5, 9.0])
    z = 2.3263478740408408
    g = np.asarray(jax.grad(lambda v: risk_measure(v, "normal", 0.99))(x))
    expect = 1 / x.size + z * (x - x.mean()) / ((x.size - 1) * x.std(ddof=1))
    np.testing.assert_allclose(g, expect, rtol=1e-12)
    g0 = np.asarray(jax.grad(lambda v: risk_measure(v, "normal", 0.99))(np.full(4, 2.0)))
    np.testing.assert_allclose(g0, 0.25)


def test_gear_mass_proxy_matches_hand_calculation():
    """Paper gear: aux struts 7850 * 5e6 * L^2 / 2e11 per leg; the honeycomb from Table 1's t/D
    (the Wierzbicki inversion must give back t/D = 0.07/8.66 and 0.06/5.20)."""
    v = jl.paper_vehicle()
    L = float(v.leg.L_a0_pair)
    area = math.pi * 0.098**2 / 4
    hc = v.honeycomb
    honey = 2680 * 8 / (3 * math.sqrt(3)) * area / 0.75 * (
        0.07 / 8.66 * float(hc.x_L2) + 0.06 / 5.20 * float(hc.x_L4 - hc.x_L3))
    expect = 4 * (7850 * 5e6 * L**2 / 2e11 + honey)
    assert float(gear_mass_kg(v)) == pytest.approx(expect, rel=2e-3)  # F rounded to 0.1 N



def test_every_design_variable_reads_its_baseline_and_moves_its_vehicle_field():
    """The variables table (``VARIABLES``), ``baseline_value`` and ``apply_design`` each name
    the variables: one added to the table alone would be optimised while changing nothing.
    Each variable, set to its baseline, gives the baseline vehicle back (to the cells' four
    digits), and set 5 % above it moves the vehicle."""
    from jaxland._config import PAPER_CELLS
    from jaxland._design._gear import baseline_value
    from jaxland._design._spec import VARIABLES

    v = jl.paper_vehicle()
    leaves = lambda x: np.concatenate([np.ravel(a) for a in jax.tree.leaves(x)])  # noqa: E731
    for name in VARIABLES:
        base = baseline_value(v, name, PAPER_CELLS)
        np.testing.assert_allclose(leaves(apply_design(v, {name: base})), leaves(v),
                                   rtol=1e-3, err_msg=name)
        moved = leaves(apply_design(v, {name: 1.05 * base}))
        assert np.max(np.abs(moved - leaves(v)) / np.maximum(np.abs(leaves(v)), 1e-30)) > 1e-3, \
            name

# ---------------------------------------------------------------------------- (b) known optimum

S_AVAIL = 0.120  # m: x_L4 - margin = 200 - 80 mm, inside the primary stage (x_L2 = 190 mm)
V_TD = 6.0  # m/s touchdown speed


def _known_vehicle():
    """A single-stage-like gear for which energy fixes the optimum: no strut damping (D_b = 0),
    no friction and no ground damping (mu = chi = 0), a stiff ground (k = 2e8 N/m) and auxiliary
    strut (k_a = 1e8 N/m), a light foot (0.2 kg), and a primary stage (x_L2 = 190 mm) longer than
    any stroke reached, so only F1 acts."""
    v = jl.paper_vehicle()
    v = eqx.tree_at(lambda v: (v.leg.D_b, v.leg.k_a, v.m_foot, v.ground.k, v.ground.chi,
                               v.ground.mu), v, (0.0, 1e8, 0.2, 2e8, 0.0, 0.0))
    return apply_design(v, {"x_L2_mm": 0.190, "x_L4_mm": 0.200, "F2_N": 2e5, "F1_N": 6e4})


def _energy_optimum(v) -> float:
    """The plateau force that just uses S_AVAIL, from energy alone (no simulation).

    From touchdown at V_TD to the maximum stroke S the quarter body and the foot lose their
    kinetic energy 0.5 (m1/4 + m2) V_TD^2 and the body sinks dz(S) relative to the foot; the
    honeycomb takes F1 (S - x_L1 / 2) (crush plus the elastic energy F1 x_L1 / 2 it holds).
    With the foot on the ground and the auxiliary strut rigid, P, A and the foot form a
    triangle with sides H2, L_a and L_h0 - S, so the foot rises relative to P by
    dz(S) = (L_h0^2 - (L_h0 - S)^2) / (2 H2) (law of cosines; 2.06 mm per mm of stroke).

    What this neglects, each bounded for this vehicle at F1 ~ 48 kN, S = 120 mm against the
    ~5.7 kJ absorbed: the foot's impact energy (at most 0.5 m2 V_TD^2 = 3.6 J, 0.06 %); the
    auxiliary strut's compliance (~0.2 mm of strut at ~25 kN, 0.3 mm of sink, 0.02 %) and its
    elastic energy (3 J, 0.05 %); the ground's penetration (0.2 mm, 0.01 %) and stored or
    plastic energy (at most N^2 / 2k ~ 4 J, 0.07 %); kinetic energy left when the stroke peaks
    (the body stops when the stroke stops). Together < 0.25 %, checked by simulating the
    reference force (its stroke must be S_AVAIL to 0.3 %)."""
    leg = v.leg
    L, H2 = float(leg.L_h0), float(leg.H2)
    m_q, m_f, g = float(v.m_quarter), float(v.m_foot), float(v.g)
    x_l1 = float(v.honeycomb.F1 / v.honeycomb.k_b1)
    dz = (L**2 - (L - S_AVAIL) ** 2) / (2 * H2)
    return (0.5 * (m_q + m_f) * V_TD**2 + m_q * g * dz) / (S_AVAIL - x_l1 / 2)


KNOWN = dict(
    design=dict(iterations=60, n_scenes=1, scene_seed=1, dt_s=1e-5, t_end_s=0.13,
                learning_rate=0.1, outer_every=10),
    objective=dict(measure="mean"),
    variables={"F1_N": dict(low=4e4, high=1.5e5)},
    constraints=dict(stroke=dict(margin_mm=80.0)),
    montecarlo=dict(n=1, seed=2, t_end_s=0.13),
    fixed=dict(drop_height_m=0.0, sink_speed_mps=V_TD),
)


@pytest.fixture(scope="module")
def known():
    v = _known_vehicle()
    spec = design_spec_from_dict(copy.deepcopy(KNOWN))
    prob = DesignProblem(spec, v)
    return v, prob, optimise_design(spec, v, problem=prob)


def test_energy_reference_is_accurate(known):
    """The simulated stroke at the energy-balance force is S_AVAIL to 0.3 % (so the reference
    itself is good to about that in F1, since stroke ~ 1/F1)."""
    v, prob, _ = known
    F_ref = _energy_optimum(v)
    _, _, per = prob.evaluate(prob.to_z({"F1_N": F_ref}), False)
    assert per["max_stroke_m"][0] == pytest.approx(S_AVAIL, rel=3e-3)


def test_optimiser_finds_the_energy_optimum(known):
    """Minimising the peak body acceleration under max stroke <= x_L4 - 80 mm pushes F1 down
    until the stroke constraint binds: the optimum is the energy-balance force, to 1 %."""
    v, _, res = known
    assert res.status == "feasible"
    assert res.values["F1_N"] == pytest.approx(_energy_optimum(v), rel=1e-2)
    assert res.at_design["objective_measure_mps2"] < res.at_start["objective_measure_mps2"]


# ---------------------------------------------------------------------------- (c) constraints

def test_constraints_hold_at_the_returned_design(known):
    """Checked independently: jl.simulate on the returned vehicle (validated, the front door)
    stays within x_L4 - margin, to the feasibility tolerance (1e-3 of the 10 mm scale)."""
    _, prob, res = known
    assert res.at_design["constraints"]["stroke"]["g"] <= prob.spec.feasibility_tol
    out = jl.simulate(jl.Scene.from_touchdown_speed(V_TD), res.vehicle, t_end=0.13,
                      model="quarter").outcomes
    assert out["max_stroke_m"] <= 0.200 - 0.080 + 1e-5
    assert not out["bottomed_out"]
    # and the design file round-trips through the config loader
    text = res.to_toml()
    data = jl.vehicle_from_dict(__import__("tomllib").loads(text))
    assert float(data.honeycomb.F1) == pytest.approx(res.values["F1_N"], rel=1e-9)


def test_infeasible_spec_is_reported(known):
    """A 195 mm margin on 200 mm leaves 5 mm, less than the stroke even at the strongest F1
    allowed: the result says infeasible and names the stroke constraint."""
    v, _, _ = known
    spec = copy.deepcopy(KNOWN)
    spec["constraints"]["stroke"]["margin_mm"] = 195.0
    spec["design"]["iterations"] = 8
    res = optimise_design(design_spec_from_dict(spec), v)
    assert res.status == "infeasible"
    assert "stroke" in res.violated and res.violated["stroke"]["g"] > 1.0
    assert res.report()["violated"]["stroke"]["rule"].startswith("max stroke")


# ---------------------------------------------------------------------------- (d) bad specs

def _with(path, value):
    spec = copy.deepcopy(ROBUST)
    node = spec
    for key in path[:-1]:
        node = node.setdefault(key, {})
    if value is _DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return spec


_DELETE = object()
BAD = [
    (("variables", "F1_N", "high"), 1000.0, "variables.F1_N.high", "must exceed low"),
    (("variables", "F1_N", "high"), _DELETE, "variables.F1_N.high", "is required"),
    (("variables", "bogus_N"), {"low": 1.0, "high": 2.0}, "variables.bogus_N",
     "unknown design variable"),
    (("variables", "k_a_N_per_m", "low"), -1.0, "variables.k_a_N_per_m.low", "> 0"),
    (("variables", "F1_N", "high"), 9500.0, "variables.F1_N.high", "F2 must be able"),
    (("variables", "x_L2_mm", "high"), 190.0, "variables.x_L2_mm.high", "x_L4 must be able"),
    # shown as written (0.45, not its round trip through metres, 0.45000000000000007)
    (("variables", "x_L2_mm", "low"), 0.45, "variables.x_L2_mm.low", "must exceed x_L1"),
    (("variables", "primary_cell_size_mm"), {"low": 5.0, "high": 9.0}, "variables",
     "not both"),
    # a cell with plateau-force variables would be silently unused
    (("cells", "primary_cell_size_mm"), 9.0, "cells.primary_cell_size_mm",
     "only a design with cell variables"),
    (("objective", "measure"), "median", "objective.measure", "must be one of"),
    (("objective", "level"), 1.0, "objective.level", "[0, 1)"),
    (("constraints", "stroke", "margin_mm"), -5.0, "constraints.stroke.margin_mm", ">= 0"),
    (("constraints", "stroke", "margin_mm"), 500.0, "constraints.stroke.margin_mm",
     "must be below the largest x_L4 the design can reach"),
    (("design", "dt_s"), 7e-5, "design.dt_s", "must divide design.t_end_s"),
    (("constraints", "stability"), {"min_margin_m": 0.5}, "constraints.stability",
     "full 3-D model"),
    (("constraints", "bogus"), {}, "constraints.bogus", "unknown key"),
    (("design", "n_scenes"), 0, "design.n_scenes", ">= 1"),
    (("design", "iterations"), 2.5, "design.iterations", "integer"),
    (("design", "scene_seed"), 4, "design.scene_seed", "must differ from montecarlo.seed"),
    (("design", "dt_s"), -1e-5, "design.dt_s", "> 0"),
    (("dispersion", "sink_speed_mps", "dist"), "gauss", "dispersion.sink_speed_mps.dist",
     "must be one of"),
    (("design", "lr_schedule"), "linear", "design.lr_schedule", "must be one of"),
    (("design", "clip_norm"), -1.0, "design.clip_norm", ">= 0"),
    (("design", "lr_final"), 2.0, "design.lr_final", "<= 1"),
    (("design", "patience"), -3, "design.patience", ">= 0"),
    # the run's own limits, named by the key (they were solver.t_end, solver.dt)
    (("design", "t_end_s"), 1e6, "design.t_end_s", "must be <= 100 s"),
    (("constraints", "stroke"), {"margin_mm": 20.0, "measure": "normal", "level": 0.0},
     "constraints.stroke.level", "(0, 1)"),
    # a level the measure does not use (it was refused with CVaR's rule at 1.0, or taken)
    (("constraints", "stroke"), {"margin_mm": 20.0, "measure": "max", "level": 1.0},
     "constraints.stroke.level", "is not used by measure = max"),
    # Monte Carlo settings the verification sets itself: refused, not silently ignored
    (("montecarlo", "model"), "quarter", "montecarlo.model", "design.model"),
    (("montecarlo", "retry"), False, "montecarlo.retry", "always reruns"),
    (("montecarlo", "early_stop"), True, "montecarlo.early_stop", "is not taken here"),
    (("montecarlo", "ledger_check_s"), 0.0, "montecarlo.ledger_check_s", "is not taken here"),
]


def test_cell_bounds_that_allow_a_weak_secondary_name_a_bound_the_spec_gives():
    """Only the secondary foil is a variable: the refusal names its low bound as written, not
    the secondary cell size the spec leaves at its [cells] value."""
    spec = copy.deepcopy(ROBUST)
    del spec["variables"]["F1_N"]
    spec["variables"]["secondary_foil_thickness_mm"] = dict(low=0.01, high=0.2)
    with pytest.raises(jl.ConfigError) as err:
        DesignProblem(design_spec_from_dict(spec))
    assert str(err.value).startswith("variables.secondary_foil_thickness_mm.low = 0.01: the "
                                     "cell bounds allow F2 = "), str(err.value)


def test_cell_variables_refuse_cells_that_do_not_give_the_baseline_gear():
    """A cell variable sets F1 and F2 from the cells: with the paper's cells on a baseline of
    F1 6000 N and F2 12000 N the start was silently the paper's gear (5024 N, 9093 N), and the
    verification credited the design with the swap. Refused by name; the paper's own vehicle,
    whose plateaus those cells give, is taken."""
    spec = copy.deepcopy(ROBUST)
    del spec["variables"]["F1_N"]
    spec["variables"]["primary_foil_thickness_mm"] = dict(low=0.06, high=0.08)
    paper = jl.paper_vehicle()
    problem = DesignProblem(design_spec_from_dict(copy.deepcopy(spec)), paper)
    assert problem.z0.shape == (len(spec["variables"]),)
    other = dataclasses.replace(paper, honeycomb=dataclasses.replace(
        paper.honeycomb, F1=6000.0, k_b1=6000.0 / (paper.honeycomb.F1 / paper.honeycomb.k_b1),
        F2=12000.0, k_b3=6000.0 / ((paper.honeycomb.F2 - paper.honeycomb.F1)
                                   / paper.honeycomb.k_b3)))
    with pytest.raises(jl.ConfigError) as err:
        DesignProblem(design_spec_from_dict(copy.deepcopy(spec)), other)
    assert err.value.field == "cells.primary_foil_thickness_mm", str(err.value)
    assert "where the baseline vehicle has F1 = 6000 N" in err.value.rule
    # a start the spec gives is where its stage starts; the secondary's cells still give F2
    spec["variables"]["primary_foil_thickness_mm"]["start"] = 0.0778646
    with pytest.raises(jl.ConfigError) as err:
        DesignProblem(design_spec_from_dict(copy.deepcopy(spec)), other)
    assert err.value.field == "cells.secondary_foil_thickness_mm", str(err.value)
    spec["variables"]["secondary_foil_thickness_mm"] = dict(low=0.065, high=0.08, start=0.0708669)
    DesignProblem(design_spec_from_dict(spec), other)


def test_design_scenes_that_cannot_touch_down_are_refused_before_compiling():
    """From 1 m at a sink speed of at most 2.6 m/s the fall takes at least 0.26 s, longer than
    design.t_end_s = 0.15 s: refused when the problem is built, as the montecarlo.t_end_s of
    a spec is, instead of after the first compiled evaluation."""
    spec = copy.deepcopy(ROBUST)
    spec["fixed"]["drop_height_m"] = 1.0
    spec["montecarlo"]["t_end_s"] = 1.0
    with pytest.raises(jl.ConfigError) as err:
        DesignProblem(design_spec_from_dict(spec))
    assert err.value.field == "design.t_end_s" and err.value.value == 0.15
    assert err.value.rule.startswith("4 of 4 design scenes do not touch down within it")
    spec["design"]["t_end_s"] = 0.4  # every fall ends by 0.32 s
    DesignProblem(design_spec_from_dict(spec))


def test_a_vehicle_no_step_can_run_is_named_not_the_designs_step():
    """No bound moves a 1e-300 kg foot's stability limit (0 s): the design refuses the
    vehicle's field, not design.dt_s."""
    feather = dataclasses.replace(jl.paper_vehicle(), m_foot=1e-300)
    with pytest.raises(jl.ConfigError) as err:
        DesignProblem(design_spec_from_dict(copy.deepcopy(ROBUST)), feather)
    assert err.value.field == "body.m_foot_kg", str(err.value)
    # a bound (F1_N) moves the limit, but the vehicle's own k_b1 leaves no step either
    stiff = dataclasses.replace(jl.paper_vehicle(), honeycomb=dataclasses.replace(
        jl.paper_vehicle().honeycomb, k_b1=1e30))
    with pytest.raises(jl.ConfigError) as err:
        DesignProblem(design_spec_from_dict(copy.deepcopy(ROBUST)), stiff)
    assert err.value.field == "honeycomb.k_b1_N_per_m", str(err.value)


@pytest.mark.parametrize("path,value,field,rule", BAD, ids=[".".join(b[0]) for b in BAD])
def test_malformed_specs_are_refused_by_name(path, value, field, rule):
    with pytest.raises(jl.ConfigError) as err:
        DesignProblem(design_spec_from_dict(_with(path, value)))
    assert err.value.field == field
    assert rule in err.value.rule
    if value is not _DELETE and not isinstance(value, dict):
        assert repr(value) in str(err.value) or str(value) in str(err.value)
    if isinstance(value, float):  # as written, not after a round trip through SI units
        assert err.value.value == value, err.value


def test_baseline_outside_bounds_is_refused():
    spec = _with(("variables", "F1_N"), {"low": 6000.0, "high": 8000.0})
    with pytest.raises(jl.ConfigError, match=r"variables\.F1_N = 5024.*strictly inside"):
        DesignProblem(design_spec_from_dict(spec))


# ---------------------------------------------------------------------------- (e) CLI

TINY = """
[design]
iterations = 2
n_scenes = 2
scene_seed = 5
t_end_s = 0.1
[objective]
measure = "max"
[variables.F1_N]
low = 2000.0
high = 8000.0
[constraints.stroke]
margin_mm = 20.0
violation_tolerance = 0.2  # 20 clean landings bound the violation probability by 0.161
[montecarlo]
n = 20
seed = 1
t_end_s = 0.1
[fixed]
drop_height_m = 0.0
[dispersion.sink_speed_mps]
dist = "uniform"
low = 1.5
high = 2.5
"""


@pytest.mark.parametrize("old,new,line", [
    ("low = 2000.0\nhigh = 8000.0", "low = 1000.0\nhigh = 4000.0",
     "jaxland: error: variables.F1_N = 5024.4: the start (baseline) value must lie strictly"),
    ("t_end_s = 0.1\n[objective]", "t_end_s = 0.1\ndt_s = 1e-3\n[objective]",
     "jaxland: error: design.dt_s = 0.001: exceeds the stability limit"),
    ('dist = "uniform"\nlow = 1.5\nhigh = 2.5', 'dist = "normal"\nmean = 100.0\nstd = 1.0',
     "jaxland: error: dispersion.sink_speed_mps = "),
    # a verification too small for any verdict (it ran the whole design, then exit 5)
    ("n = 20\nseed = 1", "n = 19\nseed = 1",
     "jaxland: error: montecarlo.n = 19: must be >= 20 (or --verify-n 0: no verification)"),
    # a max constraint 20 clean landings cannot meet at a 5 % tolerance (it ran the whole
    # design, then exit 5: "needs 73 landings without a violation")
    ("violation_tolerance = 0.2 ", "violation_tolerance = 0.05 ",
     "jaxland: error: montecarlo.n = 20: must be >= 73 for constraints.stroke (measure = max)"),
])
def test_cli_refuses_design_inputs_before_the_banner(tmp_path, capsys, old, new, line):
    """The design's input checks (the baseline inside the bounds, the step, the drawn scenes
    inside the envelope) answer in one line, before the banner and any landing."""
    from jaxland.cli import main

    spec = tmp_path / "spec.toml"
    assert old in TINY
    spec.write_text(TINY.replace(old, new))
    assert main(["design", str(spec), "--out", str(tmp_path / "o"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(line) and err.count("\n") == 1, err


@pytest.mark.parametrize("flags,line", [
    (["--iterations", "1000000000"], "--iterations = 1000000000: must be <= 100000"),
    (["--iterations", "-1"], "--iterations = -1: must be >= 0"),
    (["--verify-n", "-1"], "--verify-n = -1: must be >= 0"),
    (["--verify-n", "100000000000"], "--verify-n = 100000000000: its per-sample results"),
    (["--verify-n", "8"], "--verify-n = 8: must be >= 20"),
])
def test_cli_checks_a_flag_by_the_rule_of_the_key_it_overrides(tmp_path, capsys, flags, line):
    """--iterations skipped design.iterations' bound and started the run; --verify-n was
    refused as montecarlo.n, a key the user did not type."""
    from jaxland.cli import main

    spec = tmp_path / "spec.toml"
    spec.write_text(TINY)
    assert main(["design", str(spec), "--out", str(tmp_path / "o"), "--no-plots", *flags]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"jaxland: error: {line}") and err.count("\n") == 1, err


STIFF_BOUNDS = ("high = 8000.0\n", "high = 8000.0\n[variables.k_a_N_per_m]\nlow = 1e6\n"
                "high = 1e9\n")


@pytest.mark.parametrize("key,old,new", [
    ("design.dt_s", "t_end_s = 0.1\n[objective]", "t_end_s = 0.1\ndt_s = 1e-4\n[objective]"),
    ("montecarlo.dt_s", "seed = 1\nt_end_s = 0.1", "seed = 1\nt_end_s = 0.1\ndt_s = 1e-4"),
])
def test_steps_are_checked_on_the_stiffest_design_the_bounds_allow(tmp_path, capsys, key, old,
                                                                   new):
    """A step stable for the start design but not for the stiffest design inside the bounds
    (the auxiliary strut up to 1e9 N/m) is refused before the banner, naming that design:
    the optimiser may go there, and the verification runs the design it returns."""
    from jaxland._design import DesignProblem, design_spec_from_dict
    from jaxland._design._spec import VARIABLES
    from jaxland._models import MODELS
    from jaxland._solvers import stable_step
    from jaxland.cli import main

    text = TINY.replace(*STIFF_BOUNDS)
    prob = DesignProblem(design_spec_from_dict(tomllib.loads(text)))
    method = prob.spec.method if key == "design.dt_s" else "euler"
    at_start = float(stable_step(prob.vehicle_at(jnp.asarray(prob.z0)), method=method,
                                 model=MODELS[prob.model]))
    stiffest, at = prob.stiffest_step(method)
    # independent: the step at the corner the check names, computed from its values
    corner = prob.to_z({n: v * VARIABLES[n].to_si * (1 - 1e-9) for n, v in at.items()})
    assert stiffest == pytest.approx(float(stable_step(
        prob.vehicle_at(jnp.asarray(corner)), method=method, model=MODELS[prob.model])),
        rel=1e-6)
    assert stiffest < 1e-4 < at_start, (stiffest, at_start)
    # no design inside the bounds is stiffer than the stiffest corner (4000 random ones)
    z = np.random.default_rng(0).normal(0.0, 3.0, (4000, len(prob.variables)))
    inside = jax.jit(jax.vmap(lambda z: stable_step(prob.vehicle_at(z), method=method,
                                                    model=MODELS[prob.model])))(z)
    assert float(np.min(inside)) >= stiffest * (1 - 1e-12)
    spec = tmp_path / "spec.toml"
    spec.write_text(text.replace(old, new))
    assert main(["design", str(spec), "--out", str(tmp_path / "o"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"jaxland: error: {key} = 0.0001: exceeds the stability "
                          f"limit {stiffest:.3g} s of {method} for the stiffest design inside "
                          "the bounds (F1_N = 8000, k_a_N_per_m = 1e+09)"), err
    assert err.count("\n") == 1


def test_the_stiffest_corner_bounds_every_design_of_seven_variables():
    """The corner check's premise: no design inside the bounds of seven of the variables
    (4000 random ones) has a smaller stable step than the stiffest corner, for euler and
    verlet."""
    from jaxland._design import DesignProblem, design_spec_from_dict
    from jaxland._models import MODELS
    from jaxland._solvers import stable_step

    bounds = {"F1_N": (2000.0, 9000.0), "F2_N": (4000.0, 20000.0), "x_L2_mm": (20.0, 150.0),
              "x_L4_mm": (160.0, 400.0), "k_a_N_per_m": (1e6, 2e7),
              "theta_b_deg": (52.0, 66.0), "R_m": (0.5, 1.5)}
    data = tomllib.loads(TINY)
    data["variables"] = {k: {"low": lo, "high": hi} for k, (lo, hi) in bounds.items()}
    prob = DesignProblem(design_spec_from_dict(data))
    z = np.random.default_rng(1).normal(0.0, 3.0, (4000, len(bounds)))
    for method in ("euler", "verlet"):
        stiffest, _ = prob.stiffest_step(method)
        steps = jax.jit(jax.vmap(lambda z, m=method: stable_step(
            prob.vehicle_at(z), method=m, model=MODELS[prob.model])))(z)
        assert float(np.min(steps)) >= stiffest * (1 - 1e-12), method


def test_a_verification_that_ends_before_any_touchdown_is_refused_before_the_banner(
        tmp_path, capsys):
    """The design scenes (1 s) touch down from 2 m; the verification's 0.1 s cannot: found
    after the optimisation, every verification landing would come back without touchdown."""
    from jaxland.cli import main

    spec = tmp_path / "spec.toml"
    spec.write_text(TINY.replace("drop_height_m = 0.0", "drop_height_m = 2.0")
                    .replace("t_end_s = 0.1\n[objective]", "t_end_s = 1.0\n[objective]"))
    assert main(["design", str(spec), "--out", str(tmp_path / "o"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxland: error: montecarlo.t_end_s = 0.1: ends before the earliest "
                          "touchdown the dispersion allows (0.433 s") and err.count("\n") == 1


def test_design_scenes_that_never_touch_down_are_named_not_called_numerical(tmp_path, capsys):
    from jaxland.cli import main

    spec = tmp_path / "spec.toml"
    spec.write_text(TINY.replace("drop_height_m = 0.0", "drop_height_m = 0.3"))
    assert main(["design", str(spec), "--out", str(tmp_path / "o"), "--no-plots",
                 "--verify-n", "0"]) == 2
    err = capsys.readouterr().err
    assert ("design.t_end_s = 0.1: 2 of 2 design scenes do not touch down within it" in err
            and "numerical" not in err)
    # before the banner: one line, no compiled evaluation first
    assert err.startswith("jaxland: error: design.t_end_s") and err.count("\n") == 1, err


def test_cli_writes_design_report_and_figures(tmp_path, capsys):
    from jaxland.cli import main

    spec = tmp_path / "spec.toml"
    spec.write_text(TINY)
    out = tmp_path / "out"
    assert main(["design", str(spec), "--out", str(out)]) == 0
    said = capsys.readouterr()
    assert said.err.count("design iter") == 3  # one progress line per iteration (0, 1, 2)
    report = json.loads((out / "design_report.json").read_text())
    # the quarter model cannot tip over: no probability that reads as computed
    for tag in ("before", "after"):
        assert report["verification"][tag]["tip_over"]["modelled"] is False
        assert report["verification"][tag]["tip_over"]["probability"] is None
    assert "P(tip)" not in said.out and "tip-over not modelled" in said.out
    assert report["status"] == "feasible" and len(report["history"]) == 3
    assert report["verification"]["after"]["n"] == 20
    # the report records what it was given and ran with
    assert report["inputs"]["spec"] == str(spec.resolve())
    assert report["inputs"]["baseline_vehicle"] == "the paper's vehicle"
    assert report["inputs"]["arguments"]["out"] == str(out)
    import hashlib

    assert report["inputs"]["files"] == {"spec": dict(
        path=str(spec), absolute=str(spec.resolve()),
        sha256=hashlib.sha256(TINY.encode()).hexdigest())}  # no vehicle file was read
    assert report["environment"]["jaxland"] == jl.__version__
    assert report["scenes"]["method"] == "euler"
    # every [design] setting as run, and a max measure's tolerance instead of a level
    settings = tomllib.loads(TINY)["design"]
    assert {k: report["design_settings"][k] for k in settings} == settings
    assert {"verify_rounds", "verify_add", "reoptimise_iterations",
            "penalty_max"} <= set(report["design_settings"])
    (stroke,) = report["constraints"]
    assert stroke["level"] is None and stroke["violation_tolerance"] == 0.2
    assert report["objective"]["level"] is None  # measure = "max"
    baseline = jl.vehicle_from_dict(tomllib.loads(report["baseline_vehicle_toml"]))
    assert jl.vehicle_to_toml(baseline) == jl.vehicle_to_toml(jl.paper_vehicle())
    veh = jl.load_vehicle(out / "design_vehicle.toml")
    assert float(veh.honeycomb.F1) == pytest.approx(report["variables"][0]["design"], rel=1e-9)
    for name in ("design_history", "design_force_stroke", "design_outcomes"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 1000
    assert not list(out.glob(".staging-*"))
    # every verification landing with its inputs and outcomes, as the report judged them
    for tag, vehicle in (("before", jl.paper_vehicle()), ("after", veh)):
        folder = out / "verification" / tag
        with (folder / "samples.csv").open() as f:
            rows = list(csv.DictReader(f))
        judged = report["verification"][tag]
        assert len(rows) == judged["n"] == 20
        strokes = [max(float(r[f"leg{i}_max_stroke_m"]) for i in range(4)) for r in rows
                   if r["failure_code"] == "0"]
        assert len(strokes) == judged["n_ok"]
        assert max(strokes) == pytest.approx(judged["max_stroke_m"]["max"], rel=1e-9)  # 10 digits
        assert {"sink_speed_mps", "t_end_s"} <= set(rows[0])
        assert json.loads((folder / "summary.json").read_text())["n"] == 20
        assert jl.vehicle_to_toml(jl.load_vehicle(folder / "vehicle.toml")) == \
            jl.vehicle_to_toml(vehicle)
        assert jl.load_montecarlo_spec(folder / "spec.toml").seed == \
            report["verification"]["seed"]
        # its rerun is the first t_end_s: the continued landings ran on beyond it
        assert "runs these landings to t_end_s again; those the verification judged at a " \
               "later end" in (folder / "spec.toml").read_text().splitlines()[0]
    # malformed input: exit code 2 and the field named
    spec.write_text(TINY.replace("margin_mm = 20.0", "margin_mm = -1.0"))
    assert main(["design", str(spec), "--out", str(out)]) == 2
    assert "constraints.stroke.margin_mm = -1.0" in capsys.readouterr().err
    # a verification step above euler's stability limit is refused before the optimisation,
    # in one line (no banner, no iteration)
    spec.write_text(TINY.replace("seed = 1\nt_end_s = 0.1", "seed = 1\nt_end_s = 0.1\ndt_s = 1e-3"))
    assert main(["design", str(spec), "--out", str(tmp_path / "coarse")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxland: error: montecarlo.dt_s = 0.001") and err.count("\n") == 1
    # verification landings cut off in their impact are named, not passed over
    spec.write_text(TINY.replace("seed = 1\nt_end_s = 0.1", "seed = 1\nt_end_s = 0.04"))
    assert main(["design", str(spec), "--out", str(tmp_path / "short")]) in (0, 5)
    err = capsys.readouterr().err
    assert ("20 of the 20 verification landings still in their impact or able to tip over at "
            "t_end_s = 0.04 s were run on to 0.12 s (20 left), then 0.36 s (0 left)") in err
    short = json.loads((tmp_path / "short" / "design_report.json").read_text())
    assert short["verification"]["after"]["n_unfinished"] == 0
    # the baseline vehicle the spec names is an input: its folder is not replaced
    before = (out / "design_vehicle.toml").read_text()
    spec.write_text(TINY.replace("[design]\n", f"[design]\nvehicle = "
                                 f"{json.dumps(str(out / 'design_vehicle.toml'))}\n"))
    assert main(["design", str(spec), "--out", str(out)]) == 2
    assert "an input of this run" in capsys.readouterr().err
    assert (out / "design_vehicle.toml").read_text() == before
