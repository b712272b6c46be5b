"""The `jaxland` command: config, simulate (files, errors, nothing half-written)."""

import csv
import json
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import jaxland as jl
from jaxland import QuarterModel
from jaxland.cli import main

# The README's simulate examples' length (0.5 s at the default step and save interval): their
# compiled landings are shared with these (and test_vehicle3d's) through the compilation cache.
T_END = "0.5"


def test_config_prints_loadable_toml(capsys):
    assert main(["config"]) == 0
    text = capsys.readouterr().out
    veh = jl.vehicle_from_dict(tomllib.loads(text))
    assert float(veh.honeycomb.F1) == float(jl.paper_vehicle().honeycomb.F1)


def test_a_landing_run_again_at_a_smaller_step_says_so(tmp_path, capsys):
    """A 30 m/s touchdown fails at the default step and runs again at a step safe for the
    forces its energy can reach: the summary records it (retried_from_dt_s), and the screen
    says it too, and that the step is a bound's."""
    assert main(["simulate", "--touchdown-speed", "30", "--t-end", "0.02", "--no-plots",
                 "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["retried_from_dt_s"] == 1e-5 > summary["dt_s"]
    assert (f"failed numerically at the default step 1e-05 s and ran again at "
            f"{summary['dt_s']:g} s") in err
    assert "a bound that can lie far below the step the landing needs" in err


def test_a_stdout_its_reader_closes_is_named_not_called_a_refused_write(tmp_path):
    """`jaxland simulate | head -1`: the folder is written whole before the report, so a pipe
    closed by its reader was wrongly reported as "cannot write: Broken pipe" (the folder
    untouched, the docs said). It says what happened, without a traceback."""
    out = tmp_path / "o"
    # block-buffered, as a pipe's stdout is unless PYTHONUNBUFFERED says otherwise: the report
    # meets the closed pipe at its flush
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    with subprocess.Popen([sys.executable, "-m", "jaxland.cli", "simulate", "--t-end", "0.25",
                           "--no-plots", "--out", str(out)], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True, env=env) as proc:
        proc.stdout.close()  # the reader stops before the report, as head does after a line
        err = proc.stderr.read()
        assert proc.wait() == 1
    assert err.strip().endswith(
        "\njaxland: standard output closed by its reader: the printed report stops here (an "
        "output folder is written whole before its report, or not at all)"), err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert (out / "summary.json").exists()


def test_console_script_entry_point():
    out = subprocess.run([sys.executable, "-m", "jaxland.cli", "config"], capture_output=True,
                         text=True, check=True)
    assert "[honeycomb]" in out.stdout


def test_simulate_writes_csv_summary_config_and_figures(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", "--drop-height", "0.1", "--t-end", T_END, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "first-impact stroke" in printed and "energy ledger closure" in printed
    # the quarter model's energies are one leg's: the screen says so
    assert "energy dissipated (one leg's share)" in printed
    with (out / "trajectory.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == QuarterModel.COLUMNS
    assert len(rows) == 1 + 5000  # t_end / save_dt (default 1e-4 s)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["drop_height_m"] == 0.1 and summary["max_stroke_m"] > 0.01
    jl.load_vehicle(out / "vehicle.toml")
    figs = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert figs == ["fig09_foot_velocity.png", "fig10_foot_position.png",
                    "fig12_foot_acceleration.png", "fig13_buffer.png", "fig14_body.png",
                    "fig15_forces.png", "fig16_energy.png"]
    assert not list(out.glob(".staging-*"))


@pytest.mark.parametrize("args,needle", [
    # a refusal names the flag the user typed and the value as typed, not the field it set
    (["--drop-height", "-1"], "--drop-height = -1.0: must be finite and in"),
    (["--touchdown-speed", "2", "--drop-height", "0.1"], "give either"),
    (["--dt", "1e-3"], "stability limit"),
    (["--touchdown-speed", "-1"], "--touchdown-speed = -1.0: must be finite and in [0, 30]"),
    # a negative value in scientific notation reaches its rule (argparse took it for an option)
    (["--dt", "-1e-5"], "--dt = -1e-05: must be a finite number > 0 s"),
    (["--dt=-1E-5"], "--dt = -1e-05: must be a finite number > 0 s"),
    (["--t-end", "1e400"], "--t-end = inf: must be a finite number > 0 s"),
    (["--t-end", "1e-9"], "--t-end = 1e-09: must be >= dt = 1e-05 s (one step)"),
    (["--friction", "3"], "--friction = 3.0: must be finite and in [0, 2]"),
    (["--roll-rate-degps", "1000"], "--roll-rate-degps = 1000.0: must be finite and in"),
    (["--model", "quarter", "--roll-deg", "5"], "--model = 'quarter': the quarter model"),
    (["--plateau-scale", "1", "1"], "--plateau-scale = [1.0, 1.0]: must have one entry per leg"),
    (["--method", "tsit5", "--max-steps", "1" + "0" * 20],
     "--max-steps = 100000000000000000000: must be <= 5e+08"),
    # tsit5's dt is its first step: one longer than the run may be the dt's mistake
    (["--method", "tsit5", "--dt", "1"], "--t-end = 0.05: must be >= dt = 1.0 s (tsit5's first "
     "step: or give a smaller dt)"),
    (["--method", "tsit5", "--t-end", "5e-6"], "--t-end = 5e-06: must be >= dt = 1e-05 s "
     "(tsit5's first step: or give a smaller dt)"),
    # step counts past float's range: the rule, not an OverflowError's traceback
    (["--t-end", "1e308"], "--t-end = 1e+308: must be <= 100 s"),
    (["--save-dt", "1e308"], "--save-dt = 1e+308: must be <= t_end = 0.05 s"),
    (["--dt", "1e-320"], "--dt = 1e-320: t_end/dt must be <= 5e+08 steps"),
])
def test_simulate_refuses_bad_input_and_writes_nothing(tmp_path, capsys, args, needle):
    out = tmp_path / "run"
    t_end = [] if "--t-end" in args else ["--t-end", "0.05"]
    assert main(["simulate", "--out", str(out), *t_end, *args]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1, err
    assert not out.exists() or not any(out.iterdir())


def test_a_run_shorter_than_the_save_interval_saves_at_its_end(tmp_path, capsys):
    """The default save interval (1e-4 s) is no refusal of a 5e-5 s run (it named the
    save_dt nobody gave): the run saves every 5e-5 s, at its end."""
    out = tmp_path / "short"
    assert main(["simulate", "--t-end", "5e-5", "--no-plots", "--out", str(out)]) == 0
    o = json.loads((out / "summary.json").read_text())
    assert o["save_dt_s"] == pytest.approx(5e-5, rel=1e-12) and o["t_end_s"] == o["save_dt_s"]


def test_an_output_folder_that_cannot_be_written_is_refused_before_the_run(capsys):
    """Not after the simulation, as a traceback: nothing can be created in /proc (a file
    system that refuses new folders even to root, where permission bits say nothing)."""
    assert main(["simulate", "--t-end", "0.05", "--out", "/proc/jaxland-out"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out = '/proc/jaxland-out': cannot be written" in err[0], err


@pytest.mark.parametrize("dt,t_end", [(4e-6, 0.05), (1e-4 / 13, 0.4), (1e-6, 0.01)])
def test_a_t_end_on_a_save_point_runs_exactly_to_it(dt, t_end):
    """A save interval of dt x save_every that rounds to a hair below 1e-4 s (9.999999999999999e-05)
    filled t_end to rounding and ran one interval more (0.0501 s for 0.05 s)."""
    solver = jl.Solver(dt=dt, t_end=t_end)
    assert solver.n_steps * dt == pytest.approx(t_end, rel=1e-9)
    assert solver.n_saves * solver.save_dt == pytest.approx(t_end, rel=1e-9)


def test_a_t_end_between_save_points_is_recorded_as_the_time_reached(tmp_path, capsys):
    """A run ends on a whole save interval: 1.5 steps of 1e-4 s run 2. The summary records
    the time reached beside the request, and the command says so."""
    out = tmp_path / "run"
    assert main(["simulate", "--dt", "1e-4", "--t-end", "0.00015", "--no-plots",
                 "--out", str(out)]) == 0
    assert "note: ran to 0.0002 s, not 0.00015 s" in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["t_end_s"] == pytest.approx(2e-4, rel=1e-12)
    assert summary["t_end_requested_s"] == 1.5e-4 and summary["n_steps"] == 2
    # nothing touched down, nothing was dissipated: no ledger error relative to it (was 1e8)
    assert summary["classification"] == "no_touchdown" and summary["energy_closure_rel"] is None


def test_impacts_beyond_the_contact_log_are_said_to_be_missing(tmp_path, capsys):
    """An 8 m/s landing chatters for 20 s: more contact changes than the log holds (256). The
    impacts are listed from the logged ones, and the summary and the printout say that later
    ones are missing; the trajectory shows the foot still in contact after the last listed."""
    out = tmp_path / "long"
    assert main(["simulate", "--touchdown-speed", "8", "--t-end", "20", "--method", "verlet",
                 "--save-dt", "1e-3", "--no-plots", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    o = json.loads((out / "summary.json").read_text())
    assert o["n_contact_changes"] > o["n_contact_changes_logged"] == jl.Solver().event_log
    assert (f"(listed: {o['n_impacts']}, from the first 256 of {o['n_contact_changes']} "
            "contact changes; later impacts are not listed)") in said
    with (out / "trajectory.csv").open() as f:
        rows = list(csv.DictReader(f))
    in_contact = [float(r["time_s"]) for r in rows if float(r["normal_force_N"]) > 0]
    assert in_contact[-1] > o["impacts"][-1]["end_s"] + 1.0


def test_a_config_that_overflows_is_named_not_blamed_on_the_step(tmp_path, capsys):
    """A body of 1e308 kg passes the config's rules (> 0), but its energy overflows: the
    failure says so instead of asking for a step of 'nan s'."""
    cfg = tmp_path / "huge.toml"
    cfg.write_text("[body]\nm_body_kg = 1e308\n")
    assert main(["simulate", "--config", str(cfg), "--t-end", "0.01", "--no-plots",
                 "--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err
    assert "initial energy is inf J, not a finite number" in err and "nan s" not in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text,line", [
    ("[ground]\nk_N_per_m = 1e30\n", "ground.k_N_per_m = 1e+30: makes the vehicle's stable "
                                      "step about 1.41e-15 s, so t_end = 0.01 s would take"),
    ("[leg]\nk_a_N_per_m = 1e25\n", "leg.k_a_N_per_m = 1e+25: makes the vehicle's stable"),
    ("[body]\nm_foot_kg = 1e-30\n", "body.m_foot_kg = 1e-30: makes the vehicle's stable step "
                                    "about 1.47e-34 s"),
    ("[body]\nm_foot_kg = 1e-300\n", "body.m_foot_kg = 1e-300: makes the vehicle's stable "
                                     "step below the smallest number, 0 s"),
])
def test_a_stiffness_no_gear_has_is_named_not_blamed_on_the_step(tmp_path, capsys, text,
                                                                line):
    """Without --dt the step follows the vehicle's stability limit; a spring of 1e30 N/m
    passes the config's rules (> 0) but makes that step absurd: the refusal names the
    spring, not the solver.dt the user never gave, by the file that set it, as a refusal
    of its value by the value's own rule is named."""
    cfg = tmp_path / "stiff.toml"
    cfg.write_text(text)
    assert main(["simulate", "--config", str(cfg), "--t-end", "0.01", "--no-plots",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    line = f"--config {cfg}: {line}"
    assert err.startswith(f"jaxland: error: {line}") and err.count("\n") == 1, err
    # a step given by hand is too large for such a vehicle too, but the vehicle is the error
    assert main(["simulate", "--config", str(cfg), "--t-end", "0.01", "--dt", "1e-5",
                 "--no-plots", "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.startswith(f"jaxland: error: {line}")
    for method in ("impulse", "tsit5"):  # steps set by the springs: the vehicle is named too
        assert main(["simulate", "--config", str(cfg), "--t-end", "0.01", "--method", method,
                     "--model", "quarter", "--no-plots", "--out", str(tmp_path / "o")]) == 2
        field = line.split(": makes")[0]  # its limit is the springs', not euler's
        assert capsys.readouterr().err.startswith(
            f"jaxland: error: {field}: makes the vehicle's stable step"), method


@pytest.mark.parametrize("command,spec", [("montecarlo", "montecarlo_dispersed.toml"),
                                          ("design", "design_paper_gear.toml")])
def test_a_vehicle_no_step_can_run_is_named_by_montecarlo_and_design(tmp_path, capsys, command,
                                                                    spec):
    """A Monte Carlo's or a design's step is checked against the vehicle's stability limit;
    where the vehicle itself leaves no step (a foot of 1e-300 kg: limit 0 s), the refusal names
    the vehicle's field, not the spec's dt_s, and the file that set it."""
    cfg = tmp_path / "feather.toml"
    cfg.write_text("[body]\nm_foot_kg = 1e-300\n")
    examples = Path(__file__).parents[1] / "examples"
    assert main([command, str(examples / spec), "--config", str(cfg),
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"jaxland: error: --config {cfg}: body.m_foot_kg = 1e-300: makes "
                          "the vehicle's stable step below the smallest number")
    assert err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()
    if command == "design":  # the spec's own vehicle key names it as that key
        text = (examples / spec).read_text().replace(
            "[design]\n", f"[design]\nvehicle = {json.dumps(str(cfg))}\n", 1)
        (tmp_path / spec).write_text(text)
        assert main([command, str(tmp_path / spec), "--out", str(tmp_path / "o")]) == 2
        assert capsys.readouterr().err.startswith(
            f"jaxland: error: design.vehicle {cfg}: body.m_foot_kg = 1e-300: makes")


def test_simulate_refuses_bad_config_file(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[ground]\ngamma = 1.5\n")
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "ground.gamma = 1.5" in err and "[0, 1)" in err


@pytest.mark.parametrize("argv", [
    ["config", "--config", ""], ["simulate", "--config", ""], ["simulate", "--scene", ""],
    ["fit", "DATA", "--config", ""], ["design", "SPEC", "--config", ""],
    ["montecarlo", "SPEC", "--config", ""]])
def test_an_empty_file_flag_is_refused_not_taken_as_none(tmp_path, capsys, argv):
    """An unset shell variable (--config "$VEHICLE") ran the paper's vehicle or the default
    scene: the empty flag is refused before any work."""
    examples = Path(__file__).parents[1] / "examples"
    spec = {"design": "design_paper_gear.toml"}.get(argv[0], "montecarlo_dispersed.toml")
    argv = [str(Path(__file__).parents[1] / "data" / "synthetic" / "drop_h0.20m.toml")
            if a == "DATA" else str(examples / spec) if a == "SPEC" else a for a in argv]
    out = [] if argv[0] == "config" else ["--out", str(tmp_path / "o")]
    assert main([*argv, *out]) == 2
    flag = "--scene" if "--scene" in argv else "--config"
    assert capsys.readouterr().err == f"jaxland: error: {flag} = '': is empty: give a file, " \
                                      "or leave the flag out\n"
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv,line", [
    (["simulate", "--out", ""], "--out = '': is empty: give a folder"),
    (["montecarlo", ""], "spec = '': is empty: give the spec's TOML file"),
    (["design", ""], "spec = '': is empty: give the spec's TOML file"),
    (["fit", ""], "DATA = '': is empty: give a drop test's"),
    (["predict", "--config", "CFG", ""], "DATA = '': is empty: give a drop test's")])
def test_an_empty_path_is_refused_as_empty_not_as_the_current_folder(tmp_path, capsys, argv,
                                                                      line):
    """An empty path read as '.': "--out = '.': is the current folder", "spec = '.': is a
    folder"."""
    cfg = str(Path(__file__).parents[1] / "data" / "paper_vehicle.toml")
    assert main([cfg if a == "CFG" else a for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"jaxland: error: {line}") and err.count("\n") == 1, err


@pytest.mark.parametrize("text", ["", "# the paper's gear\n", "[ground]\n[body]\n"])
def test_a_vehicle_file_that_sets_nothing_is_refused_by_the_flag_that_named_it(tmp_path, capsys,
                                                                              text):
    """Every key a vehicle file leaves out takes the paper's value: an empty one would run,
    silently, as the paper vehicle."""
    cfg = tmp_path / "empty.toml"
    cfg.write_text(text)
    for argv in (["simulate", "--config", str(cfg), "--out", str(tmp_path / "o")],
                 ["config", "--config", str(cfg)],
                 ["montecarlo", "--config", str(cfg),
                  str(Path(__file__).parents[1] / "examples" / "montecarlo_dispersed.toml"),
                  "--out", str(tmp_path / "m")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--config = {str(cfg)!r}: sets no vehicle" in err
    spec = tmp_path / "design.toml"
    spec.write_text('[design]\nvehicle = "nope.toml"\nscene_seed = 5\n'
                    '[variables.F1_N]\nlow = 2000.0\nhigh = 8000.0\n'
                    '[constraints.stroke]\nmargin_mm = 20.0\n'
                    '[dispersion.sink_speed_mps]\ndist = "uniform"\nlow = 1.5\nhigh = 2.5\n')
    assert main(["design", str(spec), "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("jaxland: error: design.vehicle = "), err


# a vehicle file's content each rule refuses: (file text, the refusal after the file's name)
BAD_VEHICLE_FILES = [
    ("[body]\nm_body_kg = -1000\n", "body.m_body_kg = -1000.0: must be > 0 (mass of the main"),
    ("[bodyx]\nm_body_kg = 1000\n", "bodyx = '<table>': unknown section; known: body, "),
    ("[ground]\nfriction = 0.5\n", "ground.friction = 0.5: unknown key; known: "),
    ('[ground]\nmu = "high"\n', "ground.mu = 'high': must be a number"),
    ("[honeycomb]\nx_L2_mm = 0.3\n", "honeycomb.x_L2_mm = 0.3: breakpoints must increase"),
    ("[honeycomb.cells]\nsecondary_cell_size_mm = 100.0\n",
     "honeycomb.F2_N (from [honeycomb.cells]) = "),
]


@pytest.mark.parametrize("text,refusal", BAD_VEHICLE_FILES,
                         ids=[b[1].split(" ")[0] for b in BAD_VEHICLE_FILES])
def test_a_bad_vehicle_files_refusal_names_the_file_by_what_gave_it(tmp_path, capsys, text,
                                                                     refusal):
    """docs/formats.md: a refusal of a vehicle file's content names the file by what gave it
    (--config, design.vehicle), in one line (exit 2), with the field, value and rule: one
    without it named only `body.m_body_kg`, as if the flags or a spec had set it."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    examples = Path(__file__).parents[1] / "examples"
    spec = tmp_path / "design.toml"
    spec.write_text(f"[design]\nvehicle = {json.dumps(str(cfg))}\n"
                    + (examples / "design_paper_gear.toml").read_text().split("[design]\n", 1)[1])
    for argv, by in (
            (["config", "--config", str(cfg)], "--config"),
            (["simulate", "--config", str(cfg), "--out", str(tmp_path / "o")], "--config"),
            (["montecarlo", str(examples / "montecarlo_dispersed.toml"), "--config", str(cfg),
              "--out", str(tmp_path / "o")], "--config"),
            (["design", str(spec), "--out", str(tmp_path / "o")], "design.vehicle")):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(f"jaxland: error: {by} {cfg}: {refusal}") and \
            err.count("\n") == 1, (argv, err)
        assert not (tmp_path / "o").exists()
    with pytest.raises(jl.ConfigError) as caught:  # Python: named by the caller's `what`
        jl.load_vehicle(cfg, "--config")
    assert caught.value.field.startswith(f"--config {cfg}: ")


@pytest.mark.parametrize("text", ["", "# a scene\n", "[scene]\n"])
def test_a_scene_file_that_sets_nothing_is_refused_by_the_flag_that_named_it(tmp_path, capsys,
                                                                            text):
    """Every key a scene file leaves out takes its default: an empty one ran, silently, the
    default 0.2 m drop."""
    scene = tmp_path / "empty.toml"
    scene.write_text(text)
    assert main(["simulate", "--scene", str(scene), "--drop-height", "0.1", "--t-end", "0.01",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--scene = {str(scene)!r}: sets no scene key" in err, err
    assert not (tmp_path / "o").exists()
    with pytest.raises(jl.ConfigError, match="sets no scene key"):
        jl.load_scene(scene)


@pytest.mark.parametrize("text", ["scene = 3\n", 'scene = "ab"\n', "scene = [1, 2]\n"])
def test_a_scene_key_that_is_no_table_is_refused_in_one_line(tmp_path, capsys, text):
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    assert main(["simulate", "--scene", str(scene), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and ": scene = " in err and "must be a table" in err, err


def test_a_scene_files_refusal_names_the_file_and_a_flags_the_flag(tmp_path, capsys):
    """A bad value or unknown key in a --scene file is refused as the file's (it read as if a
    flag had set scene.drop_height_m); a flag that overrides the file's value is named as
    the flag."""
    scene = tmp_path / "scene.toml"
    out = ["--t-end", "0.01", "--no-plots", "--out", str(tmp_path / "o")]
    for text, field in (("drop_height_m = -1.0\n", "scene.drop_height_m = -1.0"),
                        ("drop_heigt_m = 1.0\n", "scene.drop_heigt_m = 1.0: unknown key"),
                        # a per-leg value whose count only the vehicle decides
                        ("plateau_scale = [1, 1]\n",
                         "scene.plateau_scale = [1.0, 1.0]: must have one entry per leg")):
        scene.write_text(text)
        assert main(["simulate", "--scene", str(scene), *out]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(
            f"jaxland: error: --scene {scene}: {field}"), err
    scene.write_text("drop_height_m = 0.1\n")
    assert main(["simulate", "--scene", str(scene), "--drop-height", "-2", *out]) == 2
    assert capsys.readouterr().err.startswith("jaxland: error: --drop-height = -2")
    assert not (tmp_path / "o").exists()


BIG = 10**400  # a TOML integer too large for a float


@pytest.mark.parametrize("argv,text,needle", [
    (["simulate", "--scene"], f"[scene]\ndrop_height_m = {BIG}\n",
     "--scene {path}: scene.drop_height_m"),  # a scene file's refusal names the file
    (["simulate", "--scene"], f"[scene]\nplateau_scale = [1, {BIG}, 1, 1]\n",
     "--scene {path}: scene.plateau_scale"),
    (["config", "--config"], f"[honeycomb]\nexcess1 = [{BIG}]\n",
     "--config {path}: honeycomb.excess1"),  # a vehicle file's refusal names the file
    (["montecarlo", "--n", str(BIG), str(Path(__file__).parents[1] / "examples"
                                         / "montecarlo_dispersed.toml"), "--config"],
     "[ground]\nmu = 0.5\n", "--n"),
])
def test_an_integer_too_large_for_a_float_is_refused_by_name(tmp_path, capsys, argv, text,
                                                            needle):
    """Python's integers are unbounded: one beyond float's range overflowed where it was
    converted (a traceback, exit 1)."""
    path = tmp_path / "in.toml"
    path.write_text(text)
    out = [] if argv[0] == "config" else ["--out", str(tmp_path / "o")]
    assert main([*argv, str(path), *out]) == 2
    err = capsys.readouterr().err
    needle = needle.format(path=path)
    assert err.count("\n") == 1 and err.startswith(f"jaxland: error: {needle} = 1000"), err
    assert err.endswith(": is too large for a float\n"), err


@pytest.mark.parametrize("spec", ["montecarlo_dispersed.toml", "design_paper_gear.toml"])
@pytest.mark.parametrize("devices,rule", [("0", "must be >= 1"), ("100000", "must be <= ")])
def test_a_device_count_beyond_the_cores_is_refused_before_any_work(tmp_path, capsys, spec,
                                                                   devices, rule):
    """100000 CPU devices aborted the process (a thread each: pthread_create failed, exit
    134) minutes into the run."""
    command = "montecarlo" if spec.startswith("montecarlo") else "design"
    path = Path(__file__).parents[1] / "examples" / spec
    assert main([command, str(path), "--devices", devices, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"jaxland: error: --devices = {devices}: "
                                                    f"{rule}"), err
    assert not (tmp_path / "o").exists()


def test_bench_is_not_a_subcommand(capsys):
    """The benchmarks are scripts in benchmarks/ (tests/test_benchmarks.py), not the library."""
    with pytest.raises(SystemExit) as exc:
        main(["bench"])
    assert exc.value.code == 2 and "invalid choice: 'bench'" in capsys.readouterr().err


@pytest.mark.parametrize("argv,needle", [
    (["simulate", "--drop-height", "abc"], "argument --drop-height: invalid float value"),
    (["predict"], "the following arguments are required: DATA, --config"),
    (["simulate", "--max-steps", "5.5"], "argument --max-steps: invalid int value"),
])
def test_argparse_errors_are_one_line_and_exit_2(capsys, argv, needle):
    """Like every other refusal: one line (field, value, rule), no usage block in front."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and needle in err[0], err


def test_simulate_3d_scene_from_file_and_flags(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text("[scene]\nroll_deg = 3.0\nhorizontal_speed_mps = 0.5\nheading_deg = 30\n")
    out = tmp_path / "run3d"
    assert main(["simulate", "--scene", str(scene), "--pitch-deg", "-2", "--t-end", T_END,
                 "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "full model" in printed.out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["model"] == "full" and len(summary["max_stroke_m"]) == 4
    # this landing rocks onto leg 0 at 0.5 s (its max stroke grows 76 -> 80 mm by 1 s): the
    # summary and the printed note say its outcomes are not final
    assert summary["classification"] == "unfinished" and "not final" in summary["note"]
    assert "not final" in printed.err
    header = (out / "trajectory.csv").read_text().splitlines()[0].split(",")
    assert "leg3_stroke_m" in header and "roll_deg" in header
    figs = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert figs == ["fig3d_attitude.png", "fig3d_body.png", "fig3d_energy.png", "fig3d_legs.png",
                    "fig3d_views.png"]
    assert main(["simulate", "--roll-deg", "3", "--model", "quarter", "--out",
                 str(tmp_path / "x")]) == 2
    assert "needs model='full'" in capsys.readouterr().err


def test_compiled_programs_are_kept_between_runs(tmp_path):
    """The command keeps JAX's compiled programs on disk (``$XDG_CACHE_HOME/jaxland/xla`` by
    default) so that the next run of the same shapes skips compiling; ``JAXLAND_CACHE_DIR=``
    turns it off. (The test session's own cache, ``JAX_COMPILATION_CACHE_DIR``, is taken away
    from these two runs.)"""
    import os

    def run(name, **env_set):
        env = {k: v for k, v in os.environ.items()
               if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXLAND_CACHE_DIR")}
        env.update(JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                   XDG_CACHE_HOME=str(tmp_path / name), **env_set)
        subprocess.run([sys.executable, "-m", "jaxland.cli", "simulate", "--t-end", "0.01",
                        "--no-plots", "--out", str(tmp_path / name / "out")], env=env,
                       check=True, capture_output=True)
        return tmp_path / name / "jaxland" / "xla"

    kept = run("on")
    assert kept.is_dir() and any(kept.iterdir())
    assert not run("off", JAXLAND_CACHE_DIR="").exists()


def test_a_simulate_folder_reruns_its_landing_from_its_own_files(tmp_path, capsys):
    """vehicle.toml and scene.toml fed back rerun the landing: the scene's mass, plateau and
    friction scales act once (vehicle.toml held the scaled vehicle while scene.toml kept the
    scales, so the rerun scaled twice: 1.5^2 the mass). The scaled vehicle is
    effective_vehicle.toml, checked against the paper's values times the scales."""
    scene = tmp_path / "s.toml"
    scene.write_text("[scene]\ndrop_height_m = 0.0\nsink_speed_mps = 2.0\nmass_scale = 1.5\n"
                     "plateau_scale = [0.8, 0.8, 0.8, 0.8]\nfriction = 0.5\n")
    first, again = tmp_path / "r1", tmp_path / "r2"
    assert main(["simulate", "--scene", str(scene), "--t-end", "0.1", "--no-plots",
                 "--out", str(first)]) == 0
    assert main(["simulate", "--config", str(first / "vehicle.toml"), "--scene",
                 str(first / "scene.toml"), "--t-end", "0.1", "--no-plots",
                 "--out", str(again)]) == 0
    capsys.readouterr()
    s1, s2 = (json.loads((d / "summary.json").read_text()) for d in (first, again))
    assert s1["max_stroke_m"] > 0.01
    assert s2 == s1
    paper = jl.paper_vehicle()
    assert jl.vehicle_to_toml(jl.load_vehicle(first / "vehicle.toml")) == jl.vehicle_to_toml(paper)
    eff = jl.load_vehicle(first / "effective_vehicle.toml")
    assert float(eff.m_body) == pytest.approx(1.5 * float(paper.m_body), rel=1e-12)
    assert float(eff.I_xx) == pytest.approx(1.5 * float(paper.I_xx), rel=1e-12)
    assert float(eff.honeycomb.F1) == pytest.approx(0.8 * float(paper.honeycomb.F1), rel=1e-12)
    assert float(eff.honeycomb.F2) == pytest.approx(0.8 * float(paper.honeycomb.F2), rel=1e-12)
    assert float(eff.ground.mu) == 0.5
    # the scaled values are the scene's, not the paper's: their source is not cited as theirs
    lines = {line.split(" = ")[0]: line for line in
             (first / "effective_vehicle.toml").read_text().splitlines() if " = " in line}
    for key, paper_source in (("m_body_kg", "paper section 3.1"), ("I_xx_kg_m2", None),
                              ("F1_N", "our calibration"), ("F2_N", "our calibration")):
        assert "; APPLIED BY THE SCENE (friction, mass_scale or plateau_scale): not the paper " \
               "vehicle's value " in lines[key], lines[key]
        assert paper_source is None or f"]; {paper_source}" not in lines[key], lines[key]
    for key in ("k_N_per_m", "mu"):  # left alone, and set by the scene to the paper's 0.5
        assert "]; paper Table 2; rule" in lines[key], lines[key]


def test_the_stroke_figures_mark_the_breakpoints_of_the_honeycomb_run(tmp_path, capsys,
                                                                      monkeypatch):
    """x_L1 = F1 / k_b1 moves with a plateau scale: the stroke figures mark the honeycomb the
    landing ran, not the one given before the scene scaled it."""
    import jaxland._plots as plots

    seen = {}
    monkeypatch.setattr(plots, "plot_landing",
                        lambda *a, breakpoints_m, **k: seen.update(breakpoints_m) or [])
    assert main(["simulate", "--touchdown-speed", "2", "--plateau-scale", "0.8", "0.8", "0.8",
                 "0.8", "--t-end", "0.05", "--out", str(tmp_path / "run")]) == 0
    capsys.readouterr()
    hc = jl.paper_vehicle().honeycomb
    assert seen["x_L1"] == pytest.approx(0.8 * float(hc.F1) / float(hc.k_b1), rel=1e-12)
    assert seen["x_L4"] == pytest.approx(float(hc.x_L4), rel=1e-12)


def test_a_t_end_beyond_its_rule_is_named_before_the_vehicle_is_blamed(tmp_path, capsys):
    """A t_end of 1e9 s would take more steps than a run may, at any step: the refusal is
    t_end's own rule, not the paper vehicle's stiffness; a scene speed outside its envelope
    prints its unit as written in the TOML key's suffix (m/s)."""
    assert main(["simulate", "--t-end", "1e9", "--no-plots", "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == ("jaxland: error: --t-end = 1000000000.0: must be <= 100 s "
                                       "(a landing settles within seconds)\n")
    assert main(["simulate", "--touchdown-speed", "40", "--no-plots",
                 "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.rstrip().endswith("must be finite and in [0, 30] m/s")


def test_the_printed_report_says_a_bottoming_the_outcome_names_another_class_for(tmp_path,
                                                                                 capsys):
    """A heavy body dropped 0.5 m bottoms out (max stroke 183.8 mm past x_L4 = 183.2 mm) and
    t_end cuts the landing off: summary.json held bottomed_out true under the outcome
    'unfinished', and the printed report had no line for it. It now prints the flag, as the
    file holds it, beside the max stroke it follows from."""
    cfg = tmp_path / "heavy.toml"
    cfg.write_text("[body]\nm_body_kg = 4000\n")
    out = tmp_path / "o"
    assert main(["simulate", "--config", str(cfg), "--drop-height", "0.5", "--t-end", "0.46",
                 "--no-plots", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["bottomed_out"] and summary["classification"] == "unfinished"
    assert summary["max_stroke_m"] > float(jl.paper_vehicle().honeycomb.x_L4)
    lines = capsys.readouterr().out.splitlines()
    assert [x.split()[-1] for x in lines if x.strip().startswith("bottomed out")] == ["True"]


def test_simulate_help_gives_each_value_option_its_default():
    """The README says `--help` lists every option with its unit and default; the scene's
    attitude, slope and speed flags and the tsit5 and impulse settings gave none (tsit5's
    tolerances appeared only in a failure message)."""
    import argparse

    from jaxland.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    simulate = sub.choices["simulate"]
    # --scene and --touchdown-speed have no default: each replaces other values when given
    none = {"--scene", "--touchdown-speed"}
    for action in simulate._actions:
        flag = action.option_strings[-1] if action.option_strings else None
        if flag is None or action.nargs == 0 or flag in none or flag == "--help":
            continue
        assert "default" in (action.help or ""), flag


def test_the_no_touchdown_note_on_a_slope_says_how_the_clearance_is_measured(tmp_path, capsys):
    """On a 30 deg slope the 0.2 m clearance lies along the ground's normal, a vertical gap of
    0.2 / cos 30 deg = 0.231 m: the note read 'a vertical fall of 0.2 m takes 0.217 s', where
    0.2 m falls in 0.202 s. It names the clearance and its measure, and its time is the fall
    through the vertical gap (computed here from the free-fall law)."""
    assert main(["simulate", "--slope-deg", "30", "--t-end", "0.1", "--no-plots",
                 "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    fall = math.sqrt(2.0 * 0.2 / math.cos(math.radians(30.0)) / float(jl.paper_vehicle().g))
    assert (f"the fall from a clearance of 0.2 m (along the slope's normal) at 0 m/s takes "
            f"{fall:.3g} s") in err, err


def test_one_commands_output_folder_is_not_replaced_by_another_command(tmp_path, capsys):
    """`predict --out` pointed at a fit's folder replaced it as a whole: the fit's report and
    fitted vehicle were gone, exit 0. Another command's folder is refused before any work,
    and keeps its files; the same command replaces its own folder as before."""
    out = tmp_path / "run"
    assert main(["simulate", "--t-end", "0.01", "--no-plots", "--out", str(out)]) == 0
    before = sorted(p.name for p in out.iterdir())
    spec = Path(__file__).parents[1] / "examples" / "montecarlo_dispersed.toml"
    capsys.readouterr()
    assert main(["montecarlo", str(spec), "--n", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f"jaxland: error: --out = '{out}': holds the output of `jaxland simulate`, "
                   "which this `jaxland montecarlo` run would replace as a whole: give another "
                   "folder (or remove that one first)\n")
    assert sorted(p.name for p in out.iterdir()) == before
    assert main(["simulate", "--t-end", "0.01", "--no-plots", "--out", str(out)]) == 0
