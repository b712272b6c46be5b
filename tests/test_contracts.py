"""The typed contracts and the rules that keep answers honest: integrator objects and names,
the default output interval, result codes (no touchdown is no "stable"), NaN derivatives of a
failed landing, output folders as one consistent set, and refusals of bad files and specs."""

import dataclasses
import json
import os
import subprocess
import sys

import equinox as eqx
import jax
import numpy as np
import pytest

import jaxland as jl
from jaxland.cli import main

VEH = jl.paper_vehicle()


# ---------------------------------------------------------------------------- integrators

def test_integrators_by_name_and_object():
    assert jl.Solver(method="impulse").method == jl.Impulse()
    assert jl.integrator("impulse", impulse=0.1) == jl.Impulse(dI=0.1)
    assert jl.integrator("tsit5", rtol=1e-5).rtol == 1e-5
    assert isinstance(jl.Solver().method, jl.Euler)
    with pytest.raises(jl.ConfigError, match=r"solver\.rtol.*not an option of euler"):
        jl.integrator("euler", rtol=1e-6)
    with pytest.raises(jl.ConfigError, match=r"solver\.method.*must be one of"):
        jl.integrator("rk4")
    with pytest.raises(jl.ConfigError, match=r"solver\.impulse.*> 0"):
        jl.integrator("impulse", impulse=-1.0)


def test_stable_step_is_the_oscillator_limit_in_closed_form():
    """Symplectic Euler on x'' = -w^2 x - c x' is stable for dt <= (sqrt(c^2 + 4 w^2) - c) /
    w^2 (2/w without damping); the paper gear's numbers by hand: the foot (1 kg) on the
    stiffest strut element, the aux struts, the ground in restitution and the tangential
    spring, damped by D_b F2 and chi F2."""
    hc, leg, gr = VEH.honeycomb, VEH.leg, VEH.ground
    m = float(VEH.m_foot)
    k = (max(float(hc.k_b1), float(hc.k_b3), float(leg.k_topout)) + float(leg.k_a)
         + float(gr.k) / (1 - float(gr.gamma)) + float(gr.k_tan))
    w2 = k / m
    c = (float(leg.D_b) + float(gr.chi)) * float(hc.F2) / m
    assert float(jl.stable_step(VEH)) == pytest.approx((np.sqrt(c * c + 4 * w2) - c) / w2,
                                                       rel=1e-12)
    c_ground = float(gr.chi) * float(hc.F2) / m
    for method in ("euler_implicit", "verlet"):
        assert float(jl.stable_step(VEH, method=method)) == pytest.approx(
            (np.sqrt(c_ground**2 + 4 * w2) - c_ground) / w2, rel=1e-12)
    assert float(jl.stable_step(VEH, method="tsit5")) == np.inf


@pytest.mark.parametrize("m_foot", [1e-30, 1e-300])
def test_stable_step_where_the_damping_dominates_is_the_dashpot_limit_not_zero(m_foot):
    """On a feather of a foot the damping dominates (c^2 >> w^2) and the limit tends to the
    pure dashpot's 2/c from below; a form that subtracts sqrt(c^2 + 4 w^2) - c rounds it to 0
    (1e-30 kg) or, where w^2 overflows, to inf/inf (1e-300 kg)."""
    veh = dataclasses.replace(VEH, m_foot=m_foot)
    hc, gr = veh.honeycomb, veh.ground
    c = (float(veh.leg.D_b) + float(gr.chi)) * float(hc.F2) / m_foot
    limit = float(jl.stable_step(veh))
    assert 0.0 <= limit <= 2.0 / c
    if np.isfinite(c):
        assert limit == pytest.approx(2.0 / c, rel=1e-6)


def test_default_output_interval_is_a_whole_multiple_of_dt():
    assert jl.Solver(dt=1e-5).save_dt == pytest.approx(1e-4)
    assert jl.Solver(dt=4e-5).save_dt == pytest.approx(1.2e-4)
    assert jl.Solver(dt=2e-4).save_dt == pytest.approx(2e-4)
    jl.Solver(dt=4e-5).validate()  # a whole multiple: accepted


# ---------------------------------------------------------------------------- results

def test_a_landing_without_touchdown_is_no_touchdown_not_stable():
    res = jl.simulate(jl.Scene(drop_height=1.0), t_end=0.1)
    assert res.outcomes["classification"] == "no_touchdown"
    assert res.outcomes["result"] == "no_touchdown"
    # no first impact to read a stroke of (it read the run's max stroke, 1e-15 m of preload)
    assert res.outcomes["first_impact_stroke_m"] is None
    # and it says so, with the fall's time: sqrt(2 x 1 m / 9.81 m/s^2) = 0.452 s
    assert res.outcomes["note"].startswith("no foot touched the ground before t_end = 0.1 s")
    assert "takes 0.452 s" in res.outcomes["note"]
    spec = jl.MonteCarloSpec(dispersion={"sink_speed_mps": jl.Distribution("uniform", low=0.0,
                                                                           high=0.5)},
                             fixed={"drop_height_m": 2.0}, n=4, t_end=0.05)
    mc = jl.run_montecarlo(spec, progress=False)
    assert mc.summary["n_no_touchdown"] == 4 and mc.summary["n_failed"] == 0
    assert mc.summary["tip_over"]["n"] == 0  # counted apart, never as safe landings
    # over no landing a probability has no interval either (it read [0, 1] as if computed)
    bot = mc.summary["bottoming"]
    assert bot["probability"] is None and bot["ci95_wilson"] is None
    assert bot["all_landings"]["range"] is None and bot["all_landings"]["ci95_wilson"] is None
    assert mc.summary["sensitivity"]["not_estimated"].startswith("0 successful landing(s)")


def test_a_failed_landing_has_nan_derivatives_and_a_good_one_keeps_them():
    """Three times the stability limit blows up (result LEDGER or NONFINITE): the value stays
    for the diagnosis, its derivative is NaN. Below the limit the derivative is the plain one
    (checked against a central difference)."""
    limit = float(jl.stable_step(VEH))

    def stroke(p, dt):
        veh = eqx.tree_at(lambda v: v.leg.D_b, VEH, VEH.leg.D_b * p)
        solver = jl.Solver(dt=dt, t_end=0.3, save_dt=dt * round(1e-3 / dt) if dt < 1e-3 else dt)
        _, s = jl.landing(veh, jl.Scene(), solver, "quarter")
        return s["max_stroke_m"], s["result"]

    bad = jax.jit(jax.value_and_grad(lambda p: stroke(p, 3 * limit)[0]))(1.0)
    code = int(jax.jit(lambda p: stroke(p, 3 * limit)[1])(1.0))
    assert jl.Result(code).failed and np.isfinite(float(bad[0])) and np.isnan(float(bad[1]))
    f = jax.jit(lambda p: stroke(p, 1e-5)[0])
    g = float(jax.jit(jax.grad(lambda p: stroke(p, 1e-5)[0]))(1.0))
    h = 1e-4
    assert np.isfinite(g)
    assert g == pytest.approx((float(f(1 + h)) - float(f(1 - h))) / (2 * h), rel=0.02)


# ---------------------------------------------------------------------------- output folders

def _simulate(out, *extra):
    return main(["simulate", "--drop-height", "0.02", "--t-end", "0.1", "--out", str(out),
                 *extra])


def test_an_output_folder_is_one_set_and_records_its_inputs(tmp_path, capsys):
    out = tmp_path / "run"
    assert _simulate(out, "--friction", "0.3") == 0
    assert (out / "figures").is_dir()
    marker = json.loads((out / ".jaxland-output.json").read_text())
    assert marker["command"] == "simulate" and marker["jaxland_version"] == jl.__version__
    scene = jl.load_scene(out / "scene.toml")
    assert float(scene.drop_height) == 0.02 and float(scene.friction) == 0.3
    paper_mu = float(jl.paper_vehicle().ground.mu)  # vehicle.toml: as given, the paper's
    assert float(jl.load_vehicle(out / "vehicle.toml").ground.mu) == paper_mu != 0.3
    assert float(jl.load_vehicle(out / "effective_vehicle.toml").ground.mu) == 0.3  # as run
    summary = json.loads((out / "summary.json").read_text())
    assert summary["jaxland_version"] == jl.__version__ and summary["save_dt_s"] == 1e-4
    # a rerun without figures replaces the folder: no figure of the first run survives
    assert _simulate(out, "--no-plots") == 0
    assert not (out / "figures").exists()
    assert not list(tmp_path.glob(".run.*"))  # no staging debris


def test_a_foreign_folder_is_refused_before_running(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert _simulate(tmp_path) == 2
    assert "did not write" in capsys.readouterr().err
    assert (tmp_path / "notes.txt").read_text() == "mine"
    below = tmp_path / "notes.txt" / "out"
    assert _simulate(below) == 2
    assert "lies below" in capsys.readouterr().err
    # a link to a folder jaxland wrote: replacing the folder would replace the link instead
    target, link = tmp_path / "target", tmp_path / "link"
    assert _simulate(target) == 0
    link.symlink_to(target)
    assert _simulate(link) == 2
    assert "is a symbolic link" in capsys.readouterr().err
    assert link.is_symlink() and not list(tmp_path.glob(".link.*"))


def test_a_run_never_deletes_what_its_own_run_did_not_write(tmp_path, capsys):
    """An output folder holds one run's files: a folder inside it is refused (the outer
    folder's next run would delete it), and a rerun is refused where the folder holds a file
    its run did not write (another run's output, a note of the user's), all left in place."""
    outer = tmp_path / "A"
    assert _simulate(outer) == 0
    assert _simulate(outer / "inner") == 2
    err = capsys.readouterr().err
    assert "lies inside" in err and "A" in err and not (outer / "inner").exists()
    (outer / "notes.txt").write_text("mine")
    assert _simulate(outer) == 2
    assert "notes.txt" in capsys.readouterr().err
    assert (outer / "notes.txt").read_text() == "mine"
    (outer / "notes.txt").unlink()
    # what a desktop's file manager drops into a folder it shows blocks no run
    (outer / ".DS_Store").write_bytes(b"\0")
    (outer / "figures").mkdir(exist_ok=True)
    (outer / "figures" / "Thumbs.db").write_bytes(b"\0")
    assert _simulate(outer) == 0
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / ".DS_Store").write_bytes(b"\0")
    assert _simulate(fresh) == 0 and (fresh / "summary.json").is_file()
    # an output folder of an earlier version (no list of files) holding another run's output
    marker = outer / ".jaxland-output.json"
    record = json.loads(marker.read_text())
    assert "summary.json" in record["files"]
    marker.write_text(json.dumps({k: v for k, v in record.items() if k != "files"}))
    (outer / "mc").mkdir()
    (outer / "mc" / ".jaxland-output.json").write_text("{}")
    assert _simulate(outer) == 2
    assert "mc/.jaxland-output.json" in capsys.readouterr().err
    assert (outer / "mc").is_dir()


def test_staging_debris_of_a_killed_run_is_cleaned(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    debris = tmp_path / f".run.staging-{dead}-abcdef"
    debris.mkdir()
    (debris / "trajectory.csv").write_text("half")
    mine = tmp_path / f".run.staging-{os.getpid()}-abcdef"  # a live run's: kept
    mine.mkdir()
    assert _simulate(tmp_path / "run", "--no-plots") == 0
    assert not debris.exists() and mine.exists()


# ---------------------------------------------------------------------------- refusals

@pytest.mark.parametrize("content,rule", [
    (b'drop_height_m = "\xff"\n', "not UTF-8"),
    (None, "is a folder"),
])
def test_unreadable_files_are_refused_by_name(tmp_path, capsys, content, rule):
    path = tmp_path / "scene.toml"
    if content is None:
        path.mkdir()
    else:
        path.write_bytes(content)
    assert main(["simulate", "--scene", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert rule in err and "scene.toml" in err and "Traceback" not in err


def test_a_scene_file_with_other_tables_is_refused(tmp_path, capsys):
    path = tmp_path / "scene.toml"
    path.write_text("[scene]\ndrop_height_m = 0.1\n[ground]\nmu = 0.05\n")
    assert main(["simulate", "--scene", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "ground" in capsys.readouterr().err
    # a key above the [scene] table is named with its value and where it belongs (it read
    # roll_deg = '<table>')
    path.write_text("roll_deg = 3\n[scene]\ndrop_height_m = 0.1\n")
    assert main(["simulate", "--scene", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "roll_deg = 3: stands outside the [scene] table" in capsys.readouterr().err


@pytest.mark.parametrize("fixed,field", [
    ({"roll_deg": 89.0}, "fixed.roll_deg"),
    ({"drop_height_m": -0.5}, "fixed.drop_height_m"),
])
def test_fixed_monte_carlo_inputs_outside_the_envelope_are_refused(fixed, field):
    with pytest.raises(jl.ConfigError, match="envelope") as err:
        jl.MonteCarloSpec(dispersion={}, fixed=fixed, n=2)
    assert err.value.field == field


def test_truncnormal_far_in_a_tail_is_refused_when_read():
    with pytest.raises(jl.ConfigError, match="probability") as err:
        jl.Distribution.from_dict("sink_speed_mps", dict(dist="truncnormal", mean=1.0, std=0.1,
                                                         low=5.0, high=6.0))
    assert err.value.field == "dispersion.sink_speed_mps"
    # a normal far wider than bounds around its mean holds as little, and is nearly uniform
    # on them: it samples well, and is taken (it was refused by its mass alone)
    wide = jl.Distribution.from_dict("sink_speed_mps", dict(dist="truncnormal", mean=2.0,
                                                            std=1e6, low=1.0, high=3.0))
    spec = jl.MonteCarloSpec(dispersion={"sink_speed_mps": wide}, n=20000, seed=3)
    x = jl.sample_scenes(spec, 0, spec.n)[1]["sink_speed_mps"]
    assert 1.0 < x.min() and x.max() < 3.0
    assert abs(x.mean() - 2.0) < 0.02 and abs(x.std() - 2.0 / np.sqrt(12.0)) < 0.01
    # so is one whose mean lies just outside its bounds, within a standard deviation
    jl.Distribution.from_dict("sink_speed_mps", dict(dist="truncnormal", mean=0.99, std=1e6,
                                                     low=1.0, high=3.0))


def test_a_per_leg_value_needs_one_entry_per_leg():
    spec = jl.MonteCarloSpec(dispersion={}, fixed={"plateau_scale": [1.0, 1.0, 1.0]}, n=2)
    with pytest.raises(jl.ConfigError, match=r"one entry per leg \(4\)"):
        jl.run_montecarlo(spec, progress=False)


def test_version_and_interrupt(capsys, monkeypatch):
    with pytest.raises(SystemExit) as ex:
        main(["--version"])
    assert ex.value.code == 0 and jl.__version__ in capsys.readouterr().out

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(jl._simulate, "simulate", interrupted)
    assert main(["simulate", "--out", "unused-never-written"]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert not os.path.exists("unused-never-written")


def test_long_durations_and_huge_outputs_are_refused_before_running():
    with pytest.raises(jl.ConfigError, match=r"solver\.t_end"):
        jl.simulate(t_end=400.0)
    with pytest.raises(jl.ConfigError, match=r"solver\.save_dt.*saved samples"):
        jl.simulate(t_end=90.0, save_dt=1e-5)


def test_config_marks_the_values_a_file_set(tmp_path, capsys):
    cfg = tmp_path / "mine.toml"
    cfg.write_text("[ground]\nmu = 0.3\n")
    assert main(["config", "--config", str(cfg)]) == 0
    lines = capsys.readouterr().out.splitlines()
    mu = next(line for line in lines if line.startswith("mu ="))
    assert mu.startswith("mu = 0.3") and f"SET BY {cfg}" in mu and "paper Table 2" not in mu
    assert "[-]" in mu  # dimensionless, not "1" after the number
    k = next(line for line in lines if line.startswith("k_N_per_m ="))
    assert "SET BY" not in k and "paper Table 2" in k
    # a key the file sets to the paper's own value keeps the paper's source (as formats.md
    # says, and as simulate's vehicle.toml wrote it), where config credited the file
    cfg.write_text("[ground]\nmu = 0.3\n[body]\nm_body_kg = 1120.0\n")
    assert main(["config", "--config", str(cfg)]) == 0
    lines = capsys.readouterr().out.splitlines()
    m = next(line for line in lines if line.startswith("m_body_kg ="))
    assert "SET BY" not in m and "paper section 3.1" in m, m


def test_config_marks_plateau_forces_derived_from_the_files_cells(tmp_path, capsys):
    """Forces derived from the file's cells were credited to the paper's calibration."""
    cfg = tmp_path / "cells.toml"
    cfg.write_text("[honeycomb.cells]\nflow_stress_Pa = 200e6\n")
    assert main(["config", "--config", str(cfg)]) == 0
    lines = capsys.readouterr().out.splitlines()
    for key in ("F1_N", "F2_N"):
        line = next(line for line in lines if line.startswith(f"{key} ="))
        assert f"DERIVED from the [honeycomb.cells] of {cfg}" in line, line
        assert "our calibration" not in line and "SET BY" not in line, line


def test_an_impossible_inertia_is_refused():
    """Principal moments obey the triangle inequality (I_zz = I_xx + I_yy for a flat plate)."""
    veh = eqx.tree_at(lambda v: v.I_zz, VEH, VEH.I_xx + VEH.I_yy + 1.0)
    with pytest.raises(jl.ConfigError, match=r"body\.I_zz_kg_m2.*sum of the other two"):
        jl.validate_vehicle(veh)
    jl.validate_vehicle(eqx.tree_at(lambda v: v.I_zz, VEH, VEH.I_xx + VEH.I_yy))
    # a tiny I_xx breaks I_yy's rule: the refusal shows I_xx's value too, so the mistyped
    # moment is in the message whichever of the two it was
    with pytest.raises(jl.ConfigError, match=r"body\.I_yy_kg_m2 = 1056.5.*I_zz_kg_m2 \+ "
                                             r"I_xx_kg_m2 = 201.6 \+ 1e-06 kg m\^2"):
        jl.validate_vehicle(eqx.tree_at(lambda v: v.I_xx, VEH, 1e-6))


def test_drop_test_data_that_is_not_utf8_is_refused(tmp_path):
    import shutil

    import calibration as cal

    src = jl.__file__.rsplit("/jaxland/", 1)[0] + "/data/synthetic"
    for name in ("drop_h0.20m.toml", "nominal_vehicle.toml"):
        shutil.copy(f"{src}/{name}", tmp_path)
    (tmp_path / "drop_h0.20m.csv").write_bytes(b"time_s,stroke_m\n0.0,\xff\n")
    with pytest.raises(jl.ConfigError, match="not UTF-8") as err:
        cal.load_drop_test(tmp_path / "drop_h0.20m.toml")
    assert err.value.field == "data_file"


def test_a_fit_stopped_at_its_iteration_cap_is_told_apart():
    """jaxland fit prints NOT CONVERGED and a warning instead of "fitted" when its last stage
    ended at the iteration cap (the optimisers' status "max_iter")."""
    from types import SimpleNamespace

    from calibration.cli import stopped_at_cap

    assert stopped_at_cap(SimpleNamespace(stages=[{"status": "converged"},
                                                  {"status": "max_iter"}]))
    assert not stopped_at_cap(SimpleNamespace(stages=[{"status": "max_iter"},
                                                      {"status": "converged"}]))
    assert not stopped_at_cap(SimpleNamespace(stages=[{"status": "no_decrease"}]))


def test_a_folder_without_the_marker_is_refused_whatever_it_holds(tmp_path, capsys):
    """Only a folder jaxland marked (or an empty one) is replaced: file names like jaxland's own,
    or hidden entries alone (a .git, a .env), are someone else's files."""
    named = tmp_path / "named"
    (named / "figures").mkdir(parents=True)
    (named / "summary.json").write_text("{}")
    (named / "figures" / "my_sketch.png").write_bytes(b"")
    hidden = tmp_path / "hidden"
    (hidden / ".git").mkdir(parents=True)
    (hidden / ".env").write_text("secret")
    for out in (named, hidden):
        assert _simulate(out, "--no-plots") == 2
        assert "no .jaxland-output.json" in capsys.readouterr().err
    assert (named / "figures" / "my_sketch.png").exists() and (hidden / ".env").exists()


def test_an_output_folder_holding_an_input_or_the_current_folder_is_refused(
        tmp_path, capsys, monkeypatch):
    """--out is replaced as a whole: never the folder a run reads its inputs from (even one
    jaxland wrote), never the current folder."""
    out = tmp_path / "study"
    assert _simulate(out, "--no-plots") == 0  # a jaxland folder, with its vehicle.toml
    assert main(["simulate", "--config", str(out / "vehicle.toml"), "--t-end", "0.1",
                 "--out", str(out)]) == 2
    assert "an input of this run" in capsys.readouterr().err
    assert (out / "vehicle.toml").exists()
    monkeypatch.chdir(out)
    assert _simulate(".", "--no-plots") == 2
    assert "the current folder" in capsys.readouterr().err


# ------------------------------------------------------------------- verdicts a run can give

@pytest.mark.parametrize("key", ["data_file", "vehicle_config"])
def test_fit_and_predict_refuse_an_output_folder_holding_a_file_the_metadata_names(
        tmp_path, capsys, key):
    """The drop test's metadata names its traces and vehicle: a folder holding either is an
    input's folder too, refused before any work, and the file stays. The file is one the
    folder's run wrote (as a fit's fitted_vehicle.toml is, given to predict): a file it did
    not write is refused as such already."""
    from pathlib import Path

    src = Path(__file__).resolve().parents[1] / "data" / "synthetic"
    out = tmp_path / "study"
    assert _simulate(out, "--no-plots") == 0  # a folder jaxland wrote
    inside = {"data_file": "drop_h0.20m.csv", "vehicle_config": "nominal_vehicle.toml"}[key]
    (out / inside).write_bytes((src / inside).read_bytes())
    marker = out / ".jaxland-output.json"
    record = json.loads(marker.read_text())
    marker.write_text(json.dumps(dict(record, files=[*record["files"], inside])))
    meta = (src / "drop_h0.20m.toml").read_text()
    for k, name in (("data_file", "drop_h0.20m.csv"), ("vehicle_config", "nominal_vehicle.toml")):
        where = out / name if k == key else src / name
        meta = meta.replace(f'{k} = "{name}"', f"{k} = {json.dumps(str(where))}")
    (tmp_path / "drop.toml").write_text(meta)
    for cmd in (["fit"], ["predict", "--config", str(src / "nominal_vehicle.toml")]):
        # the folder as that command's own (another command's folder is refused as such)
        marker.write_text(json.dumps(dict(record, command=cmd[0],
                                          files=[*record["files"], inside])))
        assert main([*cmd, str(tmp_path / "drop.toml"), "--out", str(out)]) == 2
        assert "an input of this run" in capsys.readouterr().err
        assert (out / inside).exists()


def test_a_landing_cut_off_during_its_impact_is_unfinished_not_stable():
    """A 0.4 m drop touches down at 0.286 s: at t_end = 0.3 s its strut is still crushing, so
    its max stroke is not final (the same landing run to 0.8 s ends far deeper). It is
    UNFINISHED: classified so, with a note, counted apart by a Monte Carlo (no failure, no
    statistic). Run to its end, the same landing is successful and its max stroke stays put."""
    scene = jl.Scene(drop_height=0.4)
    cut = jl.simulate(scene, t_end=0.3).outcomes
    full = jl.simulate(scene, t_end=0.8).outcomes
    longer = jl.simulate(scene, t_end=1.2).outcomes
    assert cut["result"] == cut["classification"] == "unfinished" and "not final" in cut["note"]
    assert full["result"] == "successful" and full["classification"] == "stable"
    assert full["max_stroke_m"] > 2 * cut["max_stroke_m"]  # the cut-off stroke was no answer
    assert longer["max_stroke_m"] == pytest.approx(full["max_stroke_m"], rel=1e-9)
    spec = jl.MonteCarloSpec(dispersion={"drop_height_m": jl.Distribution("uniform", low=0.35,
                                                                          high=0.45)},
                             n=4, seed=1, t_end=0.3)
    mc = jl.run_montecarlo(spec, progress=False)
    codes = [jl.Result(c) for c in mc.failure]
    assert mc.summary["n_unfinished"] == codes.count(jl.Result.UNFINISHED) > 0
    assert mc.summary["n_failed"] == 0 and not any(c.failed for c in codes)
    assert mc.summary["bottoming"]["n"] == codes.count(jl.Result.SUCCESSFUL)


def test_a_landing_cut_off_on_its_rebound_says_its_outcomes_are_not_final():
    """The paper drop cut at 0.37 s is on its rebound, the foot in the air: no leg is
    compressing, so it is not UNFINISHED, but it lands again and crushes further (its max
    stroke at 0.6 s is larger). The outcomes name the leg off the ground and the note says the
    max stroke is not final; at 0.6 s the foot is down, nothing is named and no note is added."""
    cut = jl.simulate(t_end=0.37).outcomes
    later = jl.simulate(t_end=0.6).outcomes
    assert cut["classification"] == "stable" and cut["legs_off_ground_at_end"] == [0]
    assert "leg(s) 0 had left the ground" in cut["note"] and "not final" in cut["note"]
    # read at t_end, not at the last saved sample (here t = 0, before the touchdown)
    assert jl.simulate(t_end=0.37, save_dt=0.37).outcomes["legs_off_ground_at_end"] == [0]
    assert jl.simulate(t_end=0.6, save_dt=0.6).outcomes["legs_off_ground_at_end"] == []
    assert later["max_stroke_m"] > cut["max_stroke_m"] + 5e-4  # the note was true
    assert later["legs_off_ground_at_end"] == [] and "note" not in later
    assert jl.simulate(t_end=0.1).outcomes["legs_off_ground_at_end"] is None  # no touchdown


def test_a_retried_landing_keeps_the_output_interval_it_was_given():
    """A 14 m/s touchdown fails at the default step and is run again at the retry step; with
    save_dt = 5e-5 s given, that step is a whole fraction of it (the run returns, sampled
    every 5e-5 s), not refused after the first run for not dividing it."""
    out = jl.simulate(jl.Scene(drop_height=0.0, sink_speed=14.0), t_end=0.05, save_dt=5e-5)
    assert out.outcomes["retried_from_dt_s"] == 1e-5
    dt = out.outcomes["dt_s"]
    assert dt < 1e-5 and 5e-5 / dt == pytest.approx(round(5e-5 / dt), abs=1e-9)
    np.testing.assert_allclose(np.diff(out.trajectory["time_s"]), 5e-5, rtol=1e-6)


def test_a_retry_that_no_run_could_take_is_not_tried():
    """A body of 1e200 kg fails numerically at the default step; the retry step from its
    force bound (4.9e-105 s) would take 1e104 steps, a step the user never gave: simulate
    reports the first run's named failure, not a refusal of that step."""
    veh = eqx.tree_at(lambda v: v.m_body, jl.paper_vehicle(), 1e200)
    with pytest.raises(jl.SimulationError, match="numerical failure|too large for this "
                                                 "landing"):
        jl.simulate(vehicle=veh)


def test_a_first_impact_between_two_saved_samples_has_no_first_impact_stroke():
    """The first-impact stroke and the foot's velocity at its end are read from the saved
    samples: with save_dt = 0.5 s no sample lies inside the paper drop's first impact (0.2 to
    0.27 s), and they are unknown (None), not the 0 of the sample before touchdown; the max
    stroke, a running maximum over every step, is the same as at a fine save_dt."""
    coarse = jl.simulate(t_end=0.5, save_dt=0.5, method="verlet").outcomes
    fine = jl.simulate(t_end=0.5, method="verlet").outcomes
    assert coarse["first_impact_stroke_m"] is None
    assert coarse["foot_vz_end_first_impact_mps"] is None
    assert fine["first_impact_stroke_m"] == pytest.approx(0.0665, abs=5e-4)
    assert coarse["max_stroke_m"] == pytest.approx(fine["max_stroke_m"], rel=1e-12)


def test_a_3d_landing_that_can_still_tip_over_is_unfinished_not_upright():
    """On a 20 deg slope this landing balances on its downhill foot after the impact and tips
    over at 1.02 s. Cut off at 0.3 s, its honeycombs are no longer crushing, but its kinetic
    energy nearly lifts the centre of mass over the nearest edge: its tip-over is not
    decided, so it is UNFINISHED, not a successful upright landing."""
    scene = jl.Scene(drop_height=0.0, sink_speed=1.56, horizontal_speed=1.37,
                     heading=np.radians(194.7), roll_rate=np.radians(-45.4),
                     slope=np.radians(20.3), slope_direction=np.radians(19.7), friction=1.17)
    kw = dict(dt=4e-5, method="leapfrog", model="full")
    cut = jl.simulate(scene, t_end=0.3, **kw).outcomes
    later = jl.simulate(scene, t_end=1.5, **kw).outcomes
    assert later["classification"] == "tipped"
    assert cut["result"] == cut["classification"] == "unfinished", cut["classification"]
    assert "tip over" in cut["note"]


def test_a_scene_the_model_cannot_take_fails_with_nan_derivatives_also_under_jit():
    """Outside the documented envelope (a negative drop height, friction 2.5), or asymmetric
    for the quarter model (which jit keeps simulate's refusal from seeing): OUTSIDE_ENVELOPE,
    and its derivatives NaN like every failure's; the same landing inside is finite."""
    solver = jl.Solver(dt=1e-5, t_end=0.4, save_dt=0.4)

    def stroke(d_b, scene):
        veh = eqx.tree_at(lambda v: v.leg.D_b, VEH, d_b)
        _, s = jl.landing(veh, scene, solver, "quarter")
        return s["max_stroke_m"], s["result"]

    for scene, inside in ((jl.Scene(drop_height=-0.001, sink_speed=2.0), False),
                          (jl.Scene(friction=2.5), False), (jl.Scene(roll=0.05), False),
                          (jl.Scene(horizontal_speed=1.0), False), (jl.Scene(), True)):
        (value, code), grad = jax.jit(jax.value_and_grad(stroke, has_aux=True))(1.5, scene)
        assert np.isfinite(float(value))
        assert (jl.Result(int(code)) == jl.Result.SUCCESSFUL) == bool(inside)
        assert np.isfinite(float(grad)) == bool(inside), scene


def test_refusals_show_the_value_given(tmp_path, capsys):
    """A refusal names the field, the value given (not '?') and the rule, with an extension's
    'off' value where the rule alone would exclude it; a write that fails is one line, exit 1."""
    cases = (("[honeycomb]\npeak_rise1_mm = -1.0\n", ["config", "--config"],
              "honeycomb.peak_rise1_mm = -1.0: must be > 0 or 0 (off)"),
             ("[montecarlo]\nn = 4\n[dispersion.sink_speed_mps]\ndist = 'uniform'\nlow = 1.0\n"
              "high = 2.0\nmode = 3\n", ["montecarlo"], "dispersion.sink_speed_mps.mode = 3: not"),
             ("[montecarlo]\nn = 4\n[fixed]\nsink_speed_mps = 2.0\n[dispersion.sink_speed_mps]\n"
              "dist = 'uniform'\nlow = 1.0\nhigh = 2.0\n", ["montecarlo"],
              "fixed.sink_speed_mps = 2.0: is also dispersed"))
    for text, argv, needle in cases:
        path = tmp_path / "in.toml"
        path.write_text(text)
        out = [] if argv[0] == "config" else ["--out", str(tmp_path / "o")]
        assert main([*argv, str(path), *out]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
    full = subprocess.run(f"{sys.executable} -m jaxland.cli config > /dev/full", shell=True,
                          capture_output=True, text=True, timeout=120)
    assert full.returncode == 1 and full.stderr.strip().startswith("jaxland: cannot write:")
    assert len(full.stderr.strip().splitlines()) == 1


def test_the_pure_landing_checks_the_vehicle_values_it_can_see():
    """Concrete invalid values are refused by name (they used to run to SUCCESSFUL); traced
    ones, as a fit, a design or a user's optimiser moves them, run, and a value outside its
    field's rule gives INVALID_VEHICLE with NaN derivatives (it ran to SUCCESSFUL with a
    finite gradient)."""
    solver = jl.Solver(dt=1e-5, t_end=0.05, save_dt=0.05)
    for get, val, field in ((lambda v: v.ground.gamma, -0.5, "ground.gamma"),
                            (lambda v: v.honeycomb.k_b1, -1e7, "honeycomb.k_b1")):
        with pytest.raises(jl.ConfigError, match=field):
            jl.landing(eqx.tree_at(get, VEH, jax.numpy.asarray(val)), jl.Scene(), solver,
                       "quarter")
    traced = jax.jit(lambda g: jl.landing(eqx.tree_at(lambda v: v.ground.gamma, VEH, g),
                                          jl.Scene(), solver, "quarter")[1]["result"])
    assert int(traced(0.2)) in (int(jl.Result.NO_TOUCHDOWN), int(jl.Result.SUCCESSFUL))

    def stroke(F1):
        s = jl.landing(eqx.tree_at(lambda v: v.honeycomb.F1, VEH, F1),
                       jl.Scene.from_touchdown_speed(2.0), solver, "quarter")[1]
        return s["max_stroke_m"], s["result"]

    grad = jax.jit(jax.grad(stroke, has_aux=True))
    for F1, code in ((-5000.0, jl.Result.INVALID_VEHICLE), (0.0, jl.Result.INVALID_VEHICLE),
                     (float(VEH.honeycomb.F1), jl.Result.UNFINISHED)):  # 50 ms: mid-crush
        g, result = grad(jax.numpy.float64(F1))
        assert int(result) == int(code) and np.isnan(g) == code.failed, (F1, result, g)


def test_a_traced_honeycomb_out_of_order_is_an_invalid_vehicle():
    """F2 below F1 (or x_L2 below x_L1, x_L4 below x_L3) breaks the law itself: its clip's
    width goes negative and the unstroked honeycomb pulls (-5 N, -0.004 J stored). Traced,
    such a vehicle ran to SUCCESSFUL with a gradient of the wrong sign (+2e-4 m/N against
    -1.1e-5 just in order). It is INVALID_VEHICLE with NaN derivatives, and refused by name
    where its values are concrete; just in order it lands, with finite derivatives."""
    solver = jl.Solver(dt=2e-5, t_end=0.05, save_dt=0.05)
    hc = VEH.honeycomb
    x1, x3 = float(hc.x_L1), float(hc.x_L3)
    for get, bad, good in ((lambda v: v.honeycomb.F2, float(hc.F1) - 5.0, float(hc.F1) + 5.0),
                           (lambda v: v.honeycomb.x_L2, x1 - 1e-5, x1 + 1e-5),
                           (lambda v: v.honeycomb.x_L4, x3 - 1e-5, x3 + 1e-5)):
        def stroke(x, get=get):
            s = jl.landing(eqx.tree_at(get, VEH, x), jl.Scene.from_touchdown_speed(2.0),
                           solver, "quarter")[1]
            return s["max_stroke_m"], s["result"]

        grad = jax.jit(jax.grad(stroke, has_aux=True))
        g, result = grad(jax.numpy.float64(bad))
        assert int(result) == int(jl.Result.INVALID_VEHICLE) and np.isnan(g), (bad, result)
        g, result = grad(jax.numpy.float64(good))
        assert not jl.Result(int(result)).failed and np.isfinite(g), (good, result)
        # concrete, the same vehicle is refused by name before it runs
        with pytest.raises(jl.ConfigError, match=r"^honeycomb\.(F2_N|x_L2_mm|x_L4_mm) = "):
            jl.landing(eqx.tree_at(get, VEH, jax.numpy.float64(bad)),
                       jl.Scene.from_touchdown_speed(2.0), solver, "quarter")


def test_concrete_and_traced_vehicles_keep_one_rule_per_field():
    """validate_vehicle (concrete values) and follows_rules (traced ones) judge every value
    alike, an extension's off value included (a rise length of 0 is off in both)."""
    from jaxland._config import follows_rules

    traced = jax.jit(follows_rules)
    for get, values in ((lambda v: v.honeycomb.peak_rise1, (0.0, -1e-3, 1e-3, np.inf)),
                        (lambda v: v.honeycomb.F1, (0.0, -1.0, 5000.0, np.nan)),
                        (lambda v: v.ground.gamma, (0.0, 0.99, 1.0, -0.1))):
        for x in values:
            veh = eqx.tree_at(get, VEH, jax.numpy.float64(x), is_leaf=lambda n: n is None)
            try:
                jl.validate_vehicle(veh, fields_only=True)
                concrete = True
            except jl.ConfigError:
                concrete = False
            assert bool(traced(veh)) == concrete, (x, concrete)


def test_the_pure_landing_checks_its_solver_settings():
    for kw, field in ((dict(dt=0.0, t_end=0.3, save_dt=1e-4), "solver.dt"),
                      (dict(dt=-1e-5, t_end=0.3, save_dt=1e-4), "solver.dt"),
                      (dict(t_end=0.0, save_dt=1e-5), "solver.t_end")):
        with pytest.raises(jl.ConfigError, match=field):
            jl.landing(VEH, jl.Scene(), jl.Solver(**kw), "quarter")


def test_the_exit_3_message_names_a_finite_step_after_a_blow_up():
    """A 20 m/s touchdown at 1e-4 s blows up, so the peaks it reached are NaN; the step to rerun
    at comes from the forces the scene's energy can reach, and rerunning there lands."""
    scene = jl.Scene.from_touchdown_speed(20.0)
    with pytest.raises(jl.SimulationError, match=r"rerun with dt <= ") as err:
        jl.simulate(scene, dt=1e-4, t_end=0.05)
    step = float(str(err.value).rsplit("dt <= ", 1)[1].split(" s")[0])
    assert np.isfinite(step) and 0 < step < 1e-4
    assert jl.simulate(scene, dt=step, t_end=0.05).outcomes["result"] in ("successful",
                                                                         "unfinished")


def test_simulate_and_monte_carlo_report_one_ledger_closure():
    """energy_closure_rel is the verdict's measure in both, relative to the energy dissipated
    or to a tenth of the energy scale where less is dissipated (a 0.2 m/s touchdown)."""
    scene = jl.Scene.from_touchdown_speed(0.2)
    one = jl.simulate(scene, t_end=0.3).outcomes
    spec = jl.MonteCarloSpec(dispersion={"sink_speed_mps": jl.Distribution("constant",
                                                                           mean=0.2)},
                             fixed={"drop_height_m": 0.0}, n=1, t_end=0.3,
                             ledger_check=0.0)  # every step, as simulate checks it
    mc = jl.run_montecarlo(spec, progress=False)
    # the quarter model's energy scale: its ledger's masses over the sink and 2.5 strokes
    scale = 0.1 * float(VEH.m_quarter + VEH.m_foot) * (
        0.5 * 0.2 ** 2 + float(VEH.g) * 2.5 * float(VEH.honeycomb.x_L4))
    assert one["energy_dissipated_J"] < scale  # the case where the two measures differ
    assert one["energy_closure_rel"] == pytest.approx(one["energy_closure_max_J"] / scale,
                                                      rel=1e-9)
    assert mc.outputs["energy_closure_rel"][0] == pytest.approx(one["energy_closure_rel"],
                                                                rel=1e-6)


@pytest.mark.parametrize("model", ["quarter", "full"])
def test_peaks_and_max_stroke_include_the_end_state(model):
    """A landing cut off while a foot is still pressing in peaks at its end: the summary's max
    stroke and peak forces are never below the end state's stroke and force (they missed the
    last step: a max stroke 7.60e-5 m against a final 7.92e-5 m, a peak normal force 2057 N
    against a final 2088 N)."""
    scene = jl.Scene(drop_height=0.2, roll=0.05 if model == "full" else 0.0)
    o = jl.simulate(scene, t_end=0.2025, model=model).outcomes  # 0.6 ms after touchdown
    assert o["result"] == "unfinished"
    stroke, final = np.atleast_1d(o["max_stroke_m"]), np.atleast_1d(o["final_stroke_m"])
    force, f_end = np.atleast_1d(o["peak_normal_force_N"]), np.atleast_1d(o["final_normal_force_N"])
    assert np.all(stroke >= final) and np.all(force >= f_end)
    pressing = f_end > 0.0  # the feet on the ground: still compressing, at their peak now
    assert pressing.any()
    np.testing.assert_array_equal(stroke[pressing], final[pressing])
    np.testing.assert_array_equal(force[pressing], f_end[pressing])


def test_an_interrupt_python_swallowed_still_publishes_nothing(tmp_path, capsys, monkeypatch):
    """Ctrl-C delivered inside a weak reference's callback raises a KeyboardInterrupt that
    Python prints and drops ("Exception ignored in ..."): the run went on and replaced the
    folder. The interrupt is remembered, so the run stops before it publishes; the earlier
    output stays."""
    from jaxland import _files
    from jaxland._simulate import Landing

    out = tmp_path / "run"
    assert _simulate(out, "--no-plots") == 0
    before = (out / "summary.json").read_text()
    to_json = Landing.to_json

    def interrupted_and_swallowed(self, path):
        try:
            _files.interrupt_handler(2, None)
        except KeyboardInterrupt:
            pass  # as in a callback whose exception Python ignores
        return to_json(self, path)

    monkeypatch.setattr(Landing, "to_json", interrupted_and_swallowed)
    assert _simulate(out, "--no-plots", "--drop-height", "0.03") == 130
    assert "interrupted" in capsys.readouterr().err
    assert (out / "summary.json").read_text() == before
    monkeypatch.undo()
    assert _simulate(out, "--no-plots", "--drop-height", "0.03") == 0  # the next run is free


def test_an_interrupt_in_a_finaliser_prints_one_line_not_a_traceback(tmp_path, capsys,
                                                                      monkeypatch):
    """Ctrl-C that lands in a finaliser (XLA's garbage-collection callback) made Python print
    "Exception ignored in ..." and a traceback above the command's one line."""
    from jaxland import _files
    from jaxland._simulate import Landing

    class Finalised:
        def __del__(self):
            _files.interrupt_handler(2, None)

    to_json = Landing.to_json

    def interrupted_in_a_finaliser(self, path):
        Finalised()  # collected at once: its KeyboardInterrupt cannot be raised
        return to_json(self, path)

    monkeypatch.setattr(Landing, "to_json", interrupted_in_a_finaliser)
    seen = []  # what reaches the process's hook (Python's prints the traceback)
    monkeypatch.setattr(sys, "unraisablehook", lambda u: seen.append(u.exc_value))
    assert _simulate(tmp_path / "run", "--no-plots") == 130
    err = capsys.readouterr().err
    assert err == "jaxland: interrupted (nothing was written to the output folder)\n", err
    assert seen == []


def test_a_sigterm_stops_a_command_as_ctrl_c_does(tmp_path, capsys, monkeypatch):
    """A scheduler's SIGTERM killed the command silently (exit 143) and left its staging
    folder behind. The command takes it as Ctrl-C: one line, the output folder as it was,
    exit 128 + 15; afterwards the caller's handler is back."""
    import signal

    from jaxland import _files

    out = tmp_path / "run"
    assert _simulate(out, "--no-plots") == 0
    before = sorted(p.name for p in tmp_path.iterdir())
    seen = []

    def terminated(*a, **k):
        seen.append(signal.getsignal(signal.SIGTERM))
        _files.interrupt_handler(signal.SIGTERM, None)  # as the signal's delivery calls it

    monkeypatch.setattr(jl._simulate, "simulate", terminated)
    assert _simulate(out, "--no-plots") == 128 + signal.SIGTERM
    assert seen == [_files.interrupt_handler]
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("jaxland: interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no staging folder left
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_a_late_interrupt_ends_the_process_with_the_commands_own_exit_code(tmp_path):
    """An interrupt that arrives after the command has ended (during the interpreter's
    shutdown: here an exit handler that interrupts itself and then hangs) ends the process at
    once with the command's code: the folder is published. main itself, called from Python,
    gives the caller's handlers back."""
    import subprocess
    import sys

    out = tmp_path / "run"
    script = (
        "import atexit, os, signal, sys, time\n"
        "from jaxland.cli import console\n"
        "def late():\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        time.sleep(60)\n"
        "    except KeyboardInterrupt:  # as the interpreter's own shutdown takes it\n"
        "        os._exit(130)\n"
        "atexit.register(late)\n"
        f"sys.argv = ['jaxland', 'simulate', '--drop-height', '0.02', '--t-end', '0.05', "
        f"'--no-plots', '--out', {str(out)!r}]\n"
        "console()\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert (out / "summary.json").exists()
    import signal

    before = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    assert main(["simulate", "--out", ""]) == 2  # refused: the handlers come back all the same
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_one_landing_refuses_a_scene_field_holding_several_values():
    """jl.landing given a Scene.batch, or a friction or mass scale as an array, failed deep
    inside the landing with a bare shape error, and four frictions ran, silently, as one per
    leg (leg 0's max stroke 0.0581 m where a friction of 0.3 gives 0.0621). Each is refused
    by its field; jl.landings still runs the batch."""
    solver = jl.Solver(dt=1e-5, t_end=0.02, save_dt=0.02)
    for scene, field in ((jl.Scene.batch(drop_height=[0.1, 0.2]), "scene.drop_height_m"),
                         (jl.Scene(friction=jax.numpy.array([0.3, 0.4, 0.5, 0.6]), roll=0.01),
                          "scene.friction"),
                         (jl.Scene(mass_scale=jax.numpy.array([1.0, 1.1])), "scene.mass_scale"),
                         (jl.Scene(plateau_scale=jax.numpy.ones((2, 4))),
                          "scene.plateau_scale")):
        with pytest.raises(jl.ConfigError, match=rf"^{field} = 'shape \(.*must be one .* for "
                                                 "one landing"):
            jl.landing(VEH, scene, solver, "full")
    out = jl.landings(VEH, jl.Scene.batch(drop_height=[0.1, 0.2]), solver, "quarter")[1]
    assert out["result"].shape == (2,)


def test_a_batch_refuses_one_number_for_a_vector_field():
    """Scene.batch with plateau_scale = 1.1 or com_offset = 0 raised a bare IndexError: a
    vector field takes a row per scene or one row for all, and one number is refused by
    its field; one row for all broadcasts."""
    for name, val in (("plateau_scale", 1.1), ("com_offset", 0.0)):
        with pytest.raises(jl.ConfigError, match=rf"^scene\.{name} = .*one row per scene"):
            jl.Scene.batch(drop_height=[0.1, 0.2], **{name: val})
    batch = jl.Scene.batch(drop_height=[0.1, 0.2], plateau_scale=[1.1, 0.9, 1.0, 1.0])
    assert batch.plateau_scale.shape == (2, 4)


def test_from_touchdown_speed_names_the_field_it_sets_when_given_again():
    """A drop height or sink speed given to from_touchdown_speed raised Python's TypeError
    of a repeated keyword: refused by name, saying what the constructor sets."""
    for name in ("drop_height", "sink_speed"):
        with pytest.raises(jl.ConfigError, match=f"^{name} = 0.1: is set by "
                                                 "from_touchdown_speed"):
            jl.Scene.from_touchdown_speed(2.0, **{name: 0.1})
    assert float(jl.Scene.from_touchdown_speed(2.0, roll=0.01).sink_speed) == 2.0
