"""Configuration: round trips, the bundled paper file, and every refused input."""

import dataclasses
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxland as jl

ROOT = Path(__file__).resolve().parents[1]


def _leaves(v):
    return [float(x) for x in jax.tree.leaves(v)]


def test_paper_vehicle_geometry_matches_design_reading():
    """docs/model.md section 2: foot rest at (2.257, -2.976) m, auxiliary rest length 2.032 m."""
    leg = jl.paper_vehicle().leg
    np.testing.assert_allclose(np.asarray(leg.foot_rest), [2.257, -2.976], atol=1e-3)
    np.testing.assert_allclose(float(leg.L_a0), 2.032, atol=1e-3)


def test_toml_round_trip_and_bundled_file():
    text = jl.vehicle_to_toml()
    again = jl.vehicle_from_dict(tomllib.loads(text))
    assert _leaves(again) == _leaves(jl.paper_vehicle())
    assert (ROOT / "data" / "paper_vehicle.toml").read_text() == text, (
        "stale: regenerate with `jaxland config > data/paper_vehicle.toml`")


def _comments(text: str) -> dict:
    """``"section.key" -> the comment`` of every key line of a vehicle TOML."""
    out, section = {}, None
    for line in text.splitlines():
        if line.startswith("["):
            section = line.strip("[]")
        elif " = " in line and not line.startswith("#"):
            out[f"{section}.{line.split(' = ')[0]}"] = line.split("  # ", 1)[1]
    return out


def test_a_value_that_is_not_the_papers_does_not_cite_the_papers_source():
    """A fitted, designed or scaled vehicle's file cited the paper vehicle's source for values
    that are not the paper's (a fitted k_b1 "F1 / x_L1 with the paper's x_L1 = 0.47 mm", a
    fitted D_b "paper Table 2", a scaled m_body "paper section 3.1"). Each key that differs
    from the paper vehicle says so, with the paper's value and its source; ``changed_by``
    names who changed the keys that differ from ``base``; a paper value keeps its source."""
    from jaxland._config import vehicle_fields

    paper = jl.paper_vehicle()
    start = dataclasses.replace(paper, m_body=1344.0)  # a start vehicle off the paper's
    veh = dataclasses.replace(start, leg=dataclasses.replace(paper.leg, D_b=1.2),
                              honeycomb=dataclasses.replace(paper.honeycomb, k_b1=9028070.40609,
                                                            F1=5427.06))
    changed = {"body.m_body_kg", "leg.D_b_s_per_m", "honeycomb.k_b1_N_per_m", "honeycomb.F1_N"}
    papers = tomllib.loads(jl.vehicle_to_toml())
    for kwargs, fitted in (({}, set()), (dict(changed_by="FITTED", base=start),
                                         changed - {"body.m_body_kg"})):
        text = jl.vehicle_to_toml(veh, **kwargs)
        assert _leaves(jl.vehicle_from_dict(tomllib.loads(text))) == _leaves(veh)
        comments = _comments(text)
        for section, _, f in vehicle_fields(veh):
            md = f.metadata
            key = f"{section}.{md['toml']}"
            own = f"]; {md['source']}; rule"  # the paper's source, cited as the value's
            if key not in changed:
                assert own in comments[key], (key, comments[key])
                continue
            was = (f"the paper vehicle's value {papers[section][md['toml']]!r}, whose source "
                   f"is {md['source']}; rule")
            said = f"FITTED: not {was}" if key in fitted else f"NOT {was}"
            assert said in comments[key] and own not in comments[key], (key, comments[key])


def test_a_toml_file_with_a_byte_order_mark_loads(tmp_path):
    """Windows editors start a UTF-8 file with a byte-order mark, which TOML does not allow:
    such a vehicle file was refused as 'not valid TOML ... line 1, column 1'. It loads as
    the same file without the mark (the data CSVs already did)."""
    plain, marked = tmp_path / "plain.toml", tmp_path / "marked.toml"
    plain.write_text("[ground]\nmu = 0.3\n")
    marked.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    assert jl.load_vehicle(marked) == jl.load_vehicle(plain)
    assert float(jl.load_vehicle(marked).ground.mu) == 0.3


@pytest.mark.parametrize("text,value", [("inf", "inf"), ("nan", "nan"), ("1e400", "inf")])
def test_a_value_that_is_not_finite_is_refused_by_its_finiteness(tmp_path, text, value):
    """mu = inf was refused as 'must be >= 0', which inf is: the refusal says finite."""
    path = tmp_path / "v.toml"
    path.write_text(f"[ground]\nmu = {text}\n")
    with pytest.raises(jl.ConfigError, match=f"^ground.mu = {value}: must be finite and >= 0 "):
        jl.load_vehicle(path)
    path.write_text("[ground]\nmu = -1\n")  # a finite value outside the rule: the rule alone
    with pytest.raises(jl.ConfigError, match="^ground.mu = -1.0: must be >= 0 "):
        jl.load_vehicle(path)


def test_partial_config_and_cells_derivation(tmp_path):
    path = tmp_path / "v.toml"
    path.write_text("[ground]\nmu = 0.3\n\n[honeycomb.cells]\nflow_stress_Pa = 250e6\n")
    veh = jl.load_vehicle(path)
    assert float(veh.ground.mu) == 0.3
    expected = jl.plateau_force(8.66e-3, 0.07e-3, 0.098, 250e6)
    np.testing.assert_allclose(float(veh.honeycomb.F1), float(expected))


BAD = [
    ({"body": {"m_body_kg": -5.0}}, "body.m_body_kg", "-5.0", "> 0"),
    ({"body": {"m_foot_kg": 0.0}}, "body.m_foot_kg", "0.0", "> 0"),
    ({"ground": {"gamma": 1.0}}, "ground.gamma", "1.0", "[0, 1)"),
    ({"ground": {"gamma": -0.1}}, "ground.gamma", "-0.1", "[0, 1)"),
    ({"ground": {"mu": -0.2}}, "ground.mu", "-0.2", ">= 0"),
    ({"ground": {"k_N_per_m": float("nan")}}, "ground.k_N_per_m", "nan", "> 0"),
    ({"leg": {"D_b_s_per_m": -1.0}}, "leg.D_b_s_per_m", "-1.0", ">= 0"),
    ({"leg": {"theta_b_deg": 95.0}}, "leg.theta_b_deg", "95", "(0, 90)"),
    ({"leg": {"L_h0_m": 1.6}}, "leg.L_h0_m", "1.6", "below the auxiliary joint"),
    ({"honeycomb": {"x_L2_mm": 0.3}}, "honeycomb.x_L2_mm", "0.3", "breakpoints must increase"),
    ({"honeycomb": {"x_L4_mm": 58.0}}, "honeycomb.x_L4_mm", "58", "breakpoints must increase"),
    # a cross-field rule names the field furthest from the paper's (a stiffness in kN/m)
    ({"honeycomb": {"k_b1_N_per_m": 8.552}}, "honeycomb.k_b1_N_per_m", "8.552",
     "x_L1 = F1/k_b1 = 5.875e+05 mm must be < x_L2 = 57.6 mm"),
    ({"honeycomb": {"k_b3_N_per_m": 50.0}}, "honeycomb.k_b3_N_per_m", "50.0",
     "must be < x_L4"),
    ({"honeycomb": {"F2_N": 4000.0}}, "honeycomb.F2_N", "4000", "must exceed F1_N"),
    ({"honeycomb": {"bonded": 1}}, "honeycomb.bonded", "1", "true or false"),
    ({"honeycomb": {"F1_N": 5000.0, "cells": {"flow_stress_Pa": 3e8}}}, "honeycomb.cells", "",
     "not both"),
    ({"honeycomb": {"cells": {"flow_stress_Pa": -3e8}}}, "honeycomb.cells.flow_stress_Pa", "-3",
     "> 0"),
    ({"ground": {"friction": 0.5}}, "ground.friction", "0.5", "unknown key"),
    ({"wheels": {"n": 3}}, "wheels", "", "unknown section"),
    ({"ground": {"mu": "high"}}, "ground.mu", "high", "must be a number"),
    ({"body": {"n_legs": 2}}, "body.n_legs", "2", "[3, 12]"),
    ({"body": {"n_legs": 1000}}, "body.n_legs", "1000", "[3, 12]"),
    ({"honeycomb": {"k_b1_N_per_m": 0.0}}, "honeycomb.k_b1_N_per_m", "0.0", "> 0"),
    ({"ground": {"k_tan_N_per_m": -5.0}}, "ground.k_tan_N_per_m", "-5.0", "> 0"),
    ({"honeycomb": {"x_L4_mm": 5000.0}}, "honeycomb.x_L4_mm", "5000", "shorter than the main"),
    # the strut shortened, not the buffer: named by what the user changed (it blamed x_L4_mm)
    ({"leg": {"L_h0_m": 0.1}}, "leg.L_h0_m", "0.1", "x_L4 = 183.23 mm must be shorter than the "
                                                     "main strut L_h0 = 100 mm"),
    ({"honeycomb": {"cells": 5}}, "honeycomb.cells", "5", "must be a table"),
    ({"honeycomb": {"cells": {"secondary_cell_size_mm": 100.0}}},
     "honeycomb.F2_N (from [honeycomb.cells])", "65.8", "must exceed F1_N"),
    ({"ground": {"k_N_per_m": 10**400}}, "ground.k_N_per_m", "", "too large"),
    ({"honeycomb": {"excess1": [10**400]}}, "honeycomb.excess1", "", "too large"),
    ({"honeycomb": {"cells": {"flow_stress_Pa": 10**400}}}, "honeycomb.cells.flow_stress_Pa",
     "", "too large"),
]


@pytest.mark.parametrize("data,field,value,rule", BAD, ids=[b[1] + ":" + b[3] for b in BAD])
def test_bad_config_is_refused_by_name(data, field, value, rule):
    with pytest.raises(jl.ConfigError) as err:
        jl.vehicle_from_dict(data)
    msg = str(err.value)
    assert msg.startswith(field), msg
    assert value in msg and rule in msg, msg


def test_bad_toml_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[ground\nmu = 1")
    with pytest.raises(jl.ConfigError, match="not valid TOML"):
        jl.load_vehicle(bad)
    with pytest.raises(jl.ConfigError, match="does not exist"):
        jl.load_vehicle(tmp_path / "missing.toml")


@pytest.mark.parametrize("kwargs,field", [
    (dict(drop_height=-0.1), "scene.drop_height"),
    (dict(drop_height=float("nan")), "scene.drop_height"),
    (dict(sink_speed=-1.0), "scene.sink_speed"),
    (dict(sink_speed=float("inf")), "scene.sink_speed"),
    (dict(drop_height=60.0), "scene.drop_height"),
    (dict(com_offset=0.0), "scene.com_offset_m = 0.0: must be three"),  # was an IndexError
])
def test_bad_scene_is_refused(kwargs, field):
    with pytest.raises(jl.ConfigError, match=field.replace(".", r"\.")):
        jl.Scene(**kwargs).validate()


@pytest.mark.parametrize("kwargs", [dict(drop_height=True), dict(sink_speed="2.0"),
                                    dict(friction=False), dict(roll=np.array([True, False])),
                                    dict(slope=None), dict(drop_height=[True, False]),
                                    dict(sink_speed=[1.0, "2"])])
def test_a_flag_or_a_text_is_no_scene_value(kwargs):
    """True would run as 1.0 and "2.0" as 2.0: refused when the scene is made, by name, also
    in a list and in a batch."""
    (name, value), = kwargs.items()
    for batch in (False, True):
        if batch and value is None:
            continue  # a batch leaves a field out with None
        with pytest.raises(jl.ConfigError) as err:
            if batch:
                jl.Scene.batch(**kwargs, yaw=np.zeros(2))
            else:
                jl.Scene(**kwargs)
        assert str(err.value).startswith(f"scene.{name} = {value!r}: must be a number")


@pytest.mark.parametrize("make,needle", [
    # was a ValueError from inside the broadcast
    (lambda: jl.Scene.batch(drop_height=[[0.1, 0.2]]),
     "scene.drop_height = [[0.1, 0.2]]: a batch gives one value per scene (a 1-D array); "
     "this has shape (1, 2)"),
    (lambda: jl.Scene.batch(drop_height=[0.1, 0.2], com_offset=np.zeros((2, 1, 3))),
     "scene.com_offset = [[[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]]]: a batch gives one row per "
     "scene"),
    # three plateau scales for the paper's four legs: was a shape error from inside the vmap
    (lambda: jl.landings(jl.paper_vehicle(), jl.Scene.batch(
        drop_height=[0.1, 0.2], plateau_scale=[1.0, 1.0, 1.0]), jl.Solver(t_end=0.01), "full"),
     "scene.plateau_scale = [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]: must have one entry per leg "
     "(4)"),
    (lambda: jl.landing(jl.paper_vehicle(), jl.Scene(plateau_scale=[1.0, 1.0]),
                        jl.Solver(t_end=0.01), "full"),
     "scene.plateau_scale = [1.0, 1.0]: must have one entry per leg (4)"),
    # a concrete 0-d array is its number (it was refused as no number, showing the number)
    (lambda: jl.simulate(t_end=jnp.array(1e6)), "solver.t_end = 1000000.0: must be <= 100 s"),
    (lambda: jl.Solver(t_end=jnp.array(1e6)).validate(),
     "solver.t_end = 1000000.0: must be <= 100 s"),
    # an int too large for a float: was an OverflowError from math.isfinite
    (lambda: jl.simulate(dt=10**400), f"solver.dt = {10**400}: is too large for a float"),
    (lambda: jl.Solver(t_end=10**400).validate(),
     f"solver.t_end = {10**400}: is too large for a float"),
])
def test_a_scene_or_setting_of_the_wrong_shape_is_refused_by_name(make, needle):
    with pytest.raises(jl.ConfigError) as err:
        make()
    assert str(err.value).startswith(needle), str(err.value)


def test_a_save_interval_that_runs_past_t_end_is_refused():
    """A run ends on a whole save interval: a given save_dt that t_end does not fill would run
    on (0.21 s asked, 0.4 s run, and a touchdown at 0.23 s reported for a drop that has none
    by 0.21 s). One within a step of t_end is a step's rounding, as a dt that does not divide
    t_end."""
    with pytest.raises(jl.ConfigError, match=r"solver\.save_dt = 0\.2: must divide t_end = "
                       r"0\.21 s .* would run to 0\.4 s"):
        jl.simulate(jl.Scene(drop_height=0.25), t_end=0.21, save_dt=0.2)
    out = jl.simulate(t_end=0.01, dt=3e-5, save_dt=3e-5).outcomes
    assert 0.01 < out["t_end_s"] < 0.01 + 3e-5


def test_bad_solver_is_refused():
    with pytest.raises(jl.ConfigError, match=r"solver\.dt"):
        jl.simulate(dt=-1e-5)
    with pytest.raises(jl.ConfigError, match=r"solver\.save_dt"):
        jl.simulate(dt=1e-5, save_dt=1e-6)
    with pytest.raises(jl.ConfigError, match=r"solver\.save_dt.*<= t_end"):
        jl.simulate(t_end=0.01, save_dt=1.0)
    with pytest.raises(jl.ConfigError, match="whole multiple of dt"):
        jl.simulate(dt=1e-5, t_end=0.01, save_dt=3.5e-5)
    with pytest.raises(jl.ConfigError, match="one scene"):
        jl.simulate(jl.Scene.batch(drop_height=[0.1, 0.2]))
    limit = float(jl.stable_step(jl.paper_vehicle()))
    with pytest.raises(jl.ConfigError, match="stability limit") as err:
        jl.simulate(dt=2 * limit, save_dt=10 * limit)
    assert f"{limit:.3g}" in str(err.value)
