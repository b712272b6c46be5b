"""Monte Carlo: reproducibility across chunk sizes and device counts, probabilities at the
extremes, interval coverage, failed samples isolated, spec validation."""

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxland as jl
from jaxland import (
    Distribution,
    MonteCarloSpec,
    load_montecarlo_spec,
    run_montecarlo,
    sample_scenes,
    wilson_interval,
)
from jaxland._files import flat_columns
from jaxland._scene import batch_axes

QUARTER_SPEC = dict(
    dispersion={"sink_speed_mps": Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
                "mass_scale": Distribution("normal", 1.0, 0.03)},
    fixed={"drop_height_m": 0.0}, n=12, seed=7, t_end=0.3)


@pytest.fixture(scope="module")
def quarter_run():
    return run_montecarlo(MonteCarloSpec(**QUARTER_SPEC), chunk=12, progress=False)


def _assert_same_outputs(got, ref):
    """Equal up to how XLA compiles each batch shape (it may fuse and reassociate differently;
    measured <= 6e-9 relative, on the accumulated slip): 1e-7 relative, and an absolute 1e-12
    on the ledger residual, a difference of large energies."""
    for k, v in ref.items():
        if k == "energy_closure_rel":
            np.testing.assert_allclose(got[k], v, rtol=0, atol=1e-12, err_msg=k)
        else:
            np.testing.assert_allclose(got[k], v, rtol=1e-7, err_msg=k)


def test_quarter_model_is_chosen_for_symmetric_dispersions(quarter_run):
    assert quarter_run.summary["model"] == "quarter"
    spec = MonteCarloSpec(dispersion={"roll_deg": Distribution("normal", 0.0, 1.0)})
    assert spec.resolved_model() == "full"


def test_same_seed_same_results_for_any_chunk_size(quarter_run):
    assert quarter_run.summary["chunk"] == 12
    big = run_montecarlo(MonteCarloSpec(**QUARTER_SPEC), chunk=100000, progress=False)
    assert big.summary["chunk"] == 12  # no larger than the run: no padded landings run
    np.testing.assert_array_equal(big.outputs["max_stroke_m"], quarter_run.outputs["max_stroke_m"])
    other = run_montecarlo(MonteCarloSpec(**QUARTER_SPEC), chunk=5, progress=False)
    for k, v in quarter_run.inputs.items():
        np.testing.assert_array_equal(other.inputs[k], v)
    _assert_same_outputs(other.outputs, quarter_run.outputs)
    # and sample i does not depend on which chunk drew it
    _, tail = sample_scenes(MonteCarloSpec(**QUARTER_SPEC), 7, 3)
    np.testing.assert_array_equal(tail["sink_speed_mps"],
                                  quarter_run.inputs["sink_speed_mps"][7:10])


def test_inputs_drawn_together_are_the_bits_of_one_draw_per_input():
    """The draw samples the inputs of one kind together; each input keeps the bits of its own
    compiled draw from the key (seed, sample, input name), whatever else the spec disperses.
    (Run op by op instead of compiled, a truncated normal can differ in its last bit.)"""
    import zlib

    import jax

    dists = {"sink_speed_mps": Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
             "horizontal_speed_mps": Distribution("truncnormal", 0.0, 0.7, 0.0, 2.5),
             "heading_deg": Distribution("uniform", low=0.0, high=360.0),
             "friction": Distribution("uniform", low=0.3, high=0.8),
             "roll_deg": Distribution("normal", 0.0, 2.0),
             "pitch_deg": Distribution("normal", 0.5, 1.0),
             "mass_scale": Distribution("constant", 1.02),
             "plateau_scale": Distribution("normal", 1.0, 0.05),
             "com_offset_x_m": Distribution("uniform", low=-0.01, high=0.02)}
    spec = MonteCarloSpec(dispersion=dists, n=40, seed=3)
    _, got = sample_scenes(spec, 5, 30)
    root = jax.random.key(3)
    for name, dist in dists.items():
        salt = zlib.crc32(name.encode()) & 0x7FFFFFFF
        shape = (4,) if name == "plateau_scale" else ()
        want = jax.jit(jax.vmap(lambda i, dist=dist, salt=salt, shape=shape: dist.sample(
            jax.random.fold_in(jax.random.fold_in(root, i), salt), shape)))(np.arange(5, 35))
        np.testing.assert_array_equal(got[name], want, err_msg=name)


def test_same_seed_same_results_on_two_devices(quarter_run, tmp_path):
    """The batch sharded over 2 (forced host) devices gives the 1-device results."""
    out = tmp_path / "two.npz"
    code = textwrap.dedent(f"""
        import numpy as np, jax
        from jaxland import Distribution, MonteCarloSpec, run_montecarlo
        spec = MonteCarloSpec(
            dispersion={{"sink_speed_mps": Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
                         "mass_scale": Distribution("normal", 1.0, 0.03)}},
            fixed={{"drop_height_m": 0.0}}, n=12, seed=7, t_end=0.3)
        assert len(jax.devices()) == 2
        r = run_montecarlo(spec, chunk=6, progress=False)
        np.savez({str(out)!r}, devices=r.summary["devices"], **r.outputs)
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=300)
    two = np.load(out)
    assert int(two["devices"]) == 2
    _assert_same_outputs(two, quarter_run.outputs)


QUARTER_TOML = """
[montecarlo]
n = 12
seed = 7
t_end_s = 0.3
[fixed]
drop_height_m = 0.0
[dispersion.sink_speed_mps]
dist = "truncnormal"
mean = 2.0
std = 0.3
low = 1.0
high = 3.0
[dispersion.mass_scale]
dist = "normal"
mean = 1.0
std = 0.03
"""


def test_cli_shards_over_one_device_per_core(quarter_run, tmp_path):
    """`jaxland montecarlo` splits the CPU into one device per core (a batch's time loop is
    one single-threaded kernel), with the one-device results; a bad count exits 2 first."""
    spec = tmp_path / "quarter.toml"
    spec.write_text(QUARTER_TOML)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # a user's plain shell
    cli = [sys.executable, "-m", "jaxland.cli", "montecarlo", str(spec), "--chunk", "6"]
    bad = subprocess.run([*cli, "--devices", "0", "--out", str(tmp_path / "bad")], env=env,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip() == "jaxland: error: --devices = 0: must be >= 1"
    assert not (tmp_path / "bad").exists()
    subprocess.run([*cli, "--out", str(tmp_path / "mc")], env=env, check=True,
                   capture_output=True, timeout=300)
    def refuse(name):  # strict JSON: no NaN or Infinity (a normal's bounds are infinite)
        raise ValueError(f"not JSON: {name}")

    summary = json.loads((tmp_path / "mc" / "summary.json").read_text(), parse_constant=refuse)
    assert summary["dispersion"]["mass_scale"]["low"] is None
    assert summary["devices"] == len(os.sched_getaffinity(0))
    got = np.load(tmp_path / "mc" / "samples.npz")
    ref = {k: v for k, v in quarter_run.columns().items() if np.asarray(v).dtype.kind in "fiub"}
    assert set(ref) <= set(got.files) and "leg0_max_stroke_m" in ref
    _assert_same_outputs(got, ref)
    # the folder records its inputs: the vehicle run (loadable) and the versions
    assert jl.vehicle_to_toml(jl.load_vehicle(tmp_path / "mc" / "vehicle.toml")) == \
        jl.vehicle_to_toml(jl.paper_vehicle())
    assert summary["environment"]["jaxland"] == jl.__version__
    # flags that cannot hold are refused before any work: several processes without a
    # coordinator (it used to run as one), more samples than the host can hold
    for flags, needle in ((["--num-processes", "2"], "--num-processes = 2: needs --coordinator"),
                          (["--coordinator", "localhost:1234"],
                           "--coordinator = 'localhost:1234': needs --num-processes too"),
                          (["--n", "1000000000000"], "--n = 1000000000000: its "
                                                     "per-sample results take up to"),
                          (["--n", "0"], "--n = 0: must be >= 1"),
                          (["--seed", "-1"], "--seed = -1: must be >= 0"),
                          (["--chunk", "0"], "--chunk = 0: must be >= 1"),
                          (["--coordinator", "bad", "--num-processes", "2", "--process-id",
                            "0"], "--coordinator = 'bad': must be host:port"),
                          # the spec's own bad value is its key's, whatever the flags
                          (["--n", "10", "--spec-n", "0"], "montecarlo.n = 0: must be >= 1")):
        cmd = cli
        if "--spec-n" in flags:
            bad_spec = tmp_path / "bad_n.toml"
            bad_spec.write_text(QUARTER_TOML.replace("n = 12", "n = 0"))
            flags = ["--n", "10"]
            cmd = [str(bad_spec) if a == str(spec) else a for a in cli]
        bad = subprocess.run([*cmd, *flags, "--out", str(tmp_path / "bad")], env=env,
                             capture_output=True, text=True, timeout=120)
        err = bad.stderr.strip().splitlines()
        assert bad.returncode == 2 and len(err) == 1 and needle in err[0], (flags, err)
        assert not (tmp_path / "bad").exists()


def test_a_run_without_a_successful_landing_is_refused_and_writes_nothing(tmp_path, capsys):
    """Every sample outside the documented envelope: no probability exists (0/0), so the run
    is refused by name (exit 2) instead of reporting P = 0; the summary's probability is None."""
    from jaxland.cli import main

    spec = tmp_path / "out_of_envelope.toml"
    # a sink speed of 15 +/- 1000 m/s: about 1 draw in 80 inside [0, 30] m/s; these two are not
    spec.write_text(QUARTER_TOML.replace("n = 12", "n = 2").replace("t_end_s = 0.3",
                                                                     "t_end_s = 0.02")
                    .replace('dist = "truncnormal"\nmean = 2.0\nstd = 0.3\nlow = 1.0\n'
                             'high = 3.0', 'dist = "normal"\nmean = 15.0\nstd = 1000.0'))
    assert main(["montecarlo", str(spec), "--out", str(tmp_path / "mc")]) == 2
    err = [e for e in capsys.readouterr().err.strip().splitlines()
           if not e.startswith("montecarlo: ")]  # the progress line
    assert len(err) == 1 and "no landing succeeded (scene outside the documented envelope" \
        in err[0], err
    assert not (tmp_path / "mc").exists()
    r = run_montecarlo(load_montecarlo_spec(spec), progress=False)
    assert r.summary["tip_over"]["n"] == 0 and r.summary["tip_over"]["probability"] is None


def test_the_earliest_touchdown_bounds_every_sample_and_is_reached_on_level_ground():
    """``earliest_touchdown_s`` is a lower bound on every sample's touchdown (dispersed drop
    heights, sink and horizontal speeds, slopes and attitudes; each sample's time from the
    scene's own free-fall formula) and is the touchdown of the extreme sample on level ground
    (simulated: no touchdown one step before it, a touchdown one step after it)."""
    from jaxland._montecarlo._run import earliest_touchdown_s
    from jaxland._solvers import Result

    veh = jl.paper_vehicle()
    g = float(veh.g)
    spec = MonteCarloSpec(dispersion={
        "drop_height_m": Distribution("uniform", low=0.3, high=0.6),
        "sink_speed_mps": Distribution("uniform", low=0.5, high=1.5),
        "horizontal_speed_mps": Distribution("uniform", low=0.0, high=2.5),
        "heading_deg": Distribution("uniform", low=0.0, high=360.0),
        "slope_deg": Distribution("uniform", low=0.0, high=6.0),
        "slope_direction_deg": Distribution("uniform", low=0.0, high=360.0),
        "roll_deg": Distribution("normal", 0.0, 2.0)}, n=4000, seed=3, t_end=1.0)
    bound = earliest_touchdown_s(spec, veh)
    scenes, _ = sample_scenes(spec, 0, spec.n)
    t_td = (np.asarray(scenes.touchdown_speed(g)) - np.asarray(scenes.sink_speed)) / g
    assert 0.0 < bound <= t_td.min() < 1.3 * bound, (bound, t_td.min())
    # a turning body is not bounded: no refusal can come from a rate
    turning = MonteCarloSpec(dispersion=dict(spec.dispersion, roll_rate_degps=Distribution(
        "uniform", low=-1.0, high=1.0)), n=4, t_end=1.0)
    assert earliest_touchdown_s(turning, veh) == 0.0

    level = MonteCarloSpec(dispersion={"sink_speed_mps": Distribution("constant", 1.5)},
                           fixed={"drop_height_m": 0.6}, n=1, dt=1e-4, t_end=1.0)
    bound = earliest_touchdown_s(level, veh)
    assert bound == pytest.approx((math.sqrt(1.5**2 + 2 * g * 0.6) - 1.5) / g, rel=1e-12)
    scene, _ = sample_scenes(level, 0, 1)
    for steps, want in ((math.floor(bound / 1e-4), Result.NO_TOUCHDOWN),
                        (math.ceil(bound / 1e-4) + 1, Result.UNFINISHED)):
        _, s = jl.landings(veh, scene, jl.Solver(dt=1e-4, t_end=steps * 1e-4,
                                                 method="euler"), "quarter")
        assert int(s["result"][0]) == int(want), (steps, bound)


def test_a_run_that_ends_before_any_touchdown_is_refused_before_it_starts(tmp_path, capsys):
    from jaxland.cli import main

    spec = tmp_path / "high.toml"
    spec.write_text(QUARTER_TOML.replace("drop_height_m = 0.0", "drop_height_m = 2.0"))
    assert main(["montecarlo", str(spec), "--out", str(tmp_path / "mc")]) == 2
    err = capsys.readouterr().err
    assert err == ("jaxland: error: montecarlo.t_end_s = 0.3: ends before the earliest "
                   "touchdown the dispersion allows (0.402 s, from drop_height_m >= 2 at "
                   "sink_speed_mps <= 3): no sample could land; raise it\n")
    assert not (tmp_path / "mc").exists()
    # where only some samples could touch down in time, the run goes ahead, and a run whose
    # landings all end unfinished or untouched is refused after it by the same key
    spec.write_text(QUARTER_TOML.replace("drop_height_m = 0.0", "drop_height_m = 1.0"))
    assert main(["montecarlo", str(spec), "--out", str(tmp_path / "mc")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("montecarlo: 12/12 landings") and len(err) == 2, err
    assert err[1].startswith("jaxland: error: montecarlo.t_end_s = 0.3: no landing succeeded "
                             "(no foot touched the ground before t_end: ")


def test_the_cli_can_skip_the_figures_and_the_progress_line(tmp_path, capsys):
    """--no-plots writes the data without figures/, --quiet prints no progress line; with too
    few landings for the sensitivity regression the command says why there are no drivers."""
    from jaxland.cli import main

    spec = tmp_path / "quarter.toml"
    spec.write_text(QUARTER_TOML.replace("n = 12", "n = 3"))
    out = tmp_path / "mc"
    assert main(["montecarlo", str(spec), "--no-plots", "--quiet", "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "samples.csv", "samples.npz", "spec.toml", "summary.json", "vehicle.toml"]
    assert "montecarlo:" not in printed.err and "figures" not in printed.out
    assert "not estimated (3 successful landings" in printed.out
    assert "retried" not in printed.out  # none was: no line


def test_a_quarter_run_presents_no_tip_over_probability(quarter_run, tmp_path, capsys):
    """The quarter model is one leg of a symmetric drop and cannot tip over: the command says
    so instead of printing P(tip-over) 0 with an interval, summary.json holds no count,
    probability or interval (null, modelled false, the reason), and the tip-over map is not
    drawn; n_succeeded counts the landings."""
    from jaxland._montecarlo import probability_text, proportion
    from jaxland.cli import main

    s = quarter_run.summary
    assert s["n_succeeded"] == int(np.sum(quarter_run.failure == 0)) > 0
    assert s["tip_over"] == dict(modelled=False, reason=s["tip_over"]["reason"], count=None,
                                 n=s["n_succeeded"], probability=None, ci95_wilson=None)
    assert "cannot tip over" in s["tip_over"]["reason"]
    assert probability_text(s["tip_over"]).startswith("not modelled: the quarter model")
    # the map is drawn for a model that tips (here the same samples, marked as tippable)
    tippable = jl.MonteCarloResult(quarter_run.inputs, quarter_run.outputs, quarter_run.failure,
                                   {**s, "tip_over": {**proportion(
                                       quarter_run.outputs["tipped_over"]), "modelled": True}})
    maps = [p.name for r, d in ((tippable, "a"), (quarter_run, "b"))
            for p in jl.plot_montecarlo(r, tmp_path / d) if p.name == "mc_tipover_map.png"]
    assert maps == ["mc_tipover_map.png"]  # the tippable one's only
    spec = tmp_path / "quarter.toml"
    spec.write_text(QUARTER_TOML.replace("n = 12", "n = 3"))
    out = tmp_path / "mc"
    assert main(["montecarlo", str(spec), "--no-plots", "--quiet", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "P(tip-over)         not modelled: the quarter model is one leg of a symmetric " \
        "vertical drop, which cannot tip over" in printed
    assert "95% CI [0" not in printed.split("P(tip-over)")[1].splitlines()[0]
    saved = json.loads((out / "summary.json").read_text())
    assert saved["tip_over"]["modelled"] is False and saved["n_succeeded"] == 3
    assert saved["tip_over"]["probability"] is None and saved["tip_over"]["count"] is None
    assert saved["tip_over"]["ci95_wilson"] is None


TIP_BASE = dict(fixed={"drop_height_m": 0.0, "sink_speed_mps": 1.0, "heading_deg": 45.0,
                       "friction": 2.0}, n=4, seed=0, t_end=1.5)


@pytest.mark.parametrize("low,high,expected", [(5.0, 6.0, 1.0), (0.5, 1.5, 0.0)])
def test_tip_over_probability_is_one_beyond_and_zero_inside_the_boundary(low, high, expected):
    """Sticky ground, heading towards an edge: the tip-over boundary lies between 3.0 and
    3.25 m/s (rigid-body criterion 3.31 m/s, see test_vehicle3d)."""
    spec = MonteCarloSpec(dispersion={"horizontal_speed_mps": Distribution("uniform", low=low,
                                                                            high=high)},
                          **TIP_BASE)
    res = run_montecarlo(spec, progress=False)
    tip = res.summary["tip_over"]
    assert res.summary["model"] == "full" and res.summary["n_failed"] == 0
    assert tip["modelled"] is True and tip["n"] == res.summary["n_succeeded"]
    assert tip["probability"] == expected
    lo, hi = tip["ci95_wilson"]
    assert lo <= expected <= hi


def test_wilson_interval_covers_a_known_probability():
    """Over 4000 simulated experiments of 50 Bernoulli(0.3) trials the 95 % interval covers
    p = 0.3 about 95 % of the time (Wilson's interval is slightly liberal at some n)."""
    rng = np.random.default_rng(0)
    p, n = 0.3, 50
    k = rng.binomial(n, p, size=4000)
    cover = np.mean([lo <= p <= hi for lo, hi in (wilson_interval(int(x), n) for x in k)])
    assert 0.93 <= cover <= 0.97, cover
    assert wilson_interval(0, 10)[0] == 0.0 and wilson_interval(10, 10)[1] == 1.0


def test_a_probability_with_failed_landings_lies_in_its_stated_range():
    """Touchdowns of 4-9 m/s at euler 1.25e-4 s without retries: the hardest landings fail
    numerically, and the probability of bottoming over the others, none of which bottoms,
    is 0. Over all 8 (the same landings with retries, none failed) it is 0.5, inside the
    range the run states with its failed landings counted as not, then as all bottoming."""
    disp = {"sink_speed_mps": Distribution("uniform", low=4.0, high=9.0)}
    runs = {retry: run_montecarlo(MonteCarloSpec(dispersion=disp, fixed={"drop_height_m": 0.0},
                                                 n=8, seed=1, t_end=0.5, dt=1.25e-4,
                                                 retry=retry, t_end_check=0), progress=False)
            for retry in (False, True)}
    bare, retried = runs[False].summary, runs[True].summary
    assert retried["n_failed"] == 0 and bare["n_failed"] > 0 and bare["n_unfinished"] == 0
    p = retried["bottoming"]["probability"]
    cut = bare["bottoming"]
    assert cut["probability"] == 0.0 < p  # the failed hard landings are no sample of all
    lo, hi = cut["all_landings"]["range"]
    assert cut["all_landings"]["n"] == 8 and cut["all_landings"]["n_failed"] == bare["n_failed"]
    assert lo <= p <= hi and hi - lo == pytest.approx(bare["n_failed"] / 8, abs=1e-12)


def test_a_probability_with_unfinished_landings_lies_in_its_stated_range():
    """Touchdowns of 6-11 m/s cut off at 0.1 s: the 28 finished ones all bottomed out (the
    hard ones finish first), so the probability over them, 1, is biased; over all 40 the
    landings run to 0.3 s (none unfinished) give 0.875, inside the range the cut-off run states
    with its 12 unfinished landings: counted as far as they are, then as all bottoming out."""
    disp = {"sink_speed_mps": Distribution("uniform", low=6.0, high=11.0)}
    runs = {t: run_montecarlo(MonteCarloSpec(dispersion=disp, fixed={"drop_height_m": 0.0},
                                             n=40, seed=2, t_end=t), progress=False)
            for t in (0.1, 0.3)}
    short, final = runs[0.1].summary, runs[0.3].summary
    assert final["n_unfinished"] == 0 and short["n_unfinished"] == 12
    p = final["bottoming"]["probability"]
    cut = short["bottoming"]
    assert p == 0.875 and cut["probability"] == 1.0 and cut["n"] == 28  # no sample of all
    lo, hi = cut["all_landings"]["range"]
    already = runs[0.1].outputs["bottomed_out"][runs[0.1].failure == int(jl.Result.UNFINISHED)]
    assert lo <= p <= hi
    assert hi - lo == pytest.approx((short["n_unfinished"] - already.sum()) / 40, abs=1e-12)
    clo, chi = cut["all_landings"]["ci95_wilson"]
    assert clo == wilson_interval(round(lo * 40), 40)[0] and chi == wilson_interval(
        round(hi * 40), 40)[1]


def test_failed_samples_are_counted_and_the_rest_is_intact():
    """Touchdowns of 2-18 m/s at dt = 1e-5 s: those above ~9 m/s bottom out with forces too
    stiff for the step and are recorded as failed (with the reason); every other sample equals
    its own single run."""
    spec = MonteCarloSpec(dispersion={"sink_speed_mps": Distribution("uniform", low=2.0,
                                                                      high=18.0)},
                          fixed={"drop_height_m": 0.0}, n=8, seed=1, t_end=0.1, retry=False)
    res = run_montecarlo(spec, progress=False)
    s = res.summary
    assert 0 < s["n_failed"] < spec.n and sum(s["failures"].values()) == s["n_failed"]
    v = res.inputs["sink_speed_mps"]
    failed = np.array([jl.Result(c).failed for c in res.failure])
    assert v[failed].min() > v[~failed].max()  # the hard ones failed
    # the slow ones are still compressing at 0.1 s: counted apart, not failed
    assert s["n_unfinished"] == int(np.sum(res.failure == jl.Result.UNFINISHED)) > 0
    for i in np.flatnonzero(~failed):
        one = jl.simulate(jl.Scene.from_touchdown_speed(float(v[i])), t_end=0.1).outcomes
        np.testing.assert_allclose(res.outputs["max_stroke_m"][i, 0], one["max_stroke_m"],
                                   rtol=1e-9)
    # what the files hold: a failed sample's outcomes are empty, not its diverged run's
    cols = res.columns()
    outcome = [k for k in cols if k not in ("sample", "failure_code", "dt_s", "retried")
               and k not in res.inputs]
    assert {"leg0_max_stroke_m", "bottomed_out", "tipped_over"} <= set(outcome)
    raw = flat_columns(res.outputs)
    for k in outcome:
        assert np.isnan(cols[k][failed]).all(), k
        np.testing.assert_array_equal(cols[k][~failed], np.asarray(raw[k], float)[~failed])
    assert np.isfinite(cols["dt_s"]).all() and cols["sink_speed_mps"][failed].size


def test_failed_samples_are_retried_with_implicit_damping():
    """The same touchdowns with retries (the default): the hard ones, which failed from
    explicit Euler's explicit strut damping, run again with it implicit (euler_implicit), land
    and bottom out, with the max stroke of simulate's own retry (explicit Euler at the step the
    scene's energy needs) to 1e-3; the others keep their numbers."""
    spec = MonteCarloSpec(dispersion={"sink_speed_mps": Distribution("uniform", low=2.0,
                                                                      high=18.0)},
                          fixed={"drop_height_m": 0.0}, n=8, seed=1, t_end=0.1)
    res = run_montecarlo(spec, progress=False)
    s = res.summary
    assert s["n_failed"] == 0 and 0 < s["n_retried"] < spec.n
    assert s["retry_method"] == "euler_implicit"
    retried = res.outputs["retried"]
    assert res.outputs["bottomed_out"][retried].all()
    v = res.inputs["sink_speed_mps"]
    assert v[retried].min() > v[~retried].max()  # the hard ones
    i = int(np.flatnonzero(retried)[0])
    one = jl.simulate(jl.Scene.from_touchdown_speed(float(v[i])), t_end=0.1)
    assert one.outcomes["retried_from_dt_s"] == spec.dt
    np.testing.assert_allclose(res.outputs["max_stroke_m"][i, 0], one.outcomes["max_stroke_m"],
                               rtol=1e-3)


def test_a_retried_sample_takes_its_own_step_not_the_smallest_of_the_failures(monkeypatch):
    """A retry's step was the smallest any failed sample needed, so a sample's outcome moved
    with which other samples failed (with n). Each now runs at its own step: a hard landing
    given a smaller step by ``retry_step`` (stubbed here: 5e-6 s above 15 m/s, else 1e-5 s)
    leaves the other retried samples at theirs, and their outcomes are those of a run of
    fewer samples that lacks the hard one (to the rounding between batch shapes, 6e-9)."""
    import jaxland._simulate as sim

    def step(vehicle, scene, method, model):
        return 5e-6 if float(scene.sink_speed) > 15.0 else 1e-5

    monkeypatch.setattr(sim, "retry_step", step)
    spec = dict(dispersion={"sink_speed_mps": Distribution("uniform", low=2.0, high=18.0)},
                fixed={"drop_height_m": 0.0}, seed=1, t_end=0.1, dt=1e-4, method="verlet")
    every = run_montecarlo(MonteCarloSpec(n=8, **spec), progress=False)
    v, dt, retried = (every.inputs["sink_speed_mps"], every.outputs["dt_s"],
                      every.outputs["retried"])
    assert every.summary["n_failed"] == 0 and retried[v > 15.0].any()
    np.testing.assert_array_equal(dt[retried], np.where(v[retried] > 15.0, 5e-6, 1e-5))
    first = int(np.flatnonzero(v > 15.0)[0])  # the samples before the hard one, alone
    fewer = run_montecarlo(MonteCarloSpec(n=first, **spec), progress=False)
    assert fewer.outputs["retried"].any()
    np.testing.assert_array_equal(fewer.outputs["dt_s"], dt[:first])
    for k in ("max_stroke_m", "peak_body_accel_mps2"):
        np.testing.assert_allclose(fewer.outputs[k], every.outputs[k][:first], rtol=1e-8,
                                   err_msg=k)


def test_the_cli_names_the_retried_samples_and_what_a_retry_is(tmp_path, capsys):
    """The touchdowns above as a spec file: the command prints how many samples failed
    numerically and ran again, how (implicit strut damping, at the step their forces allow,
    then smaller), the smallest step and how many still failed, as summary.json counts."""
    from jaxland.cli import main

    spec = tmp_path / "hard.toml"
    spec.write_text("[montecarlo]\nn = 8\nseed = 1\nt_end_s = 0.1\n[fixed]\n"
                    "drop_height_m = 0.0\n[dispersion.sink_speed_mps]\ndist = 'uniform'\n"
                    "low = 2.0\nhigh = 18.0\n")
    out = tmp_path / "mc"
    assert main(["montecarlo", str(spec), "--no-plots", "--quiet", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    k = summary["n_retried"]
    assert 0 < k < 8 and summary["n_failed"] == 0
    smallest = np.loadtxt(out / "samples.csv", delimiter=",", skiprows=1, usecols=[
        (out / "samples.csv").read_text().splitlines()[0].split(",").index("dt_s")]).min()
    (line,) = [x for x in capsys.readouterr().out.splitlines() if "retried samples" in x]
    assert line == (f"  retried samples     {k} (failed numerically at dt_s = 1e-05 s; rerun "
                    "with the strut damping implicit (euler_implicit) at the step their forces "
                    "allow (at most dt_s), then at a quarter of that step while failing, up to 3 "
                    f"tries; smallest step {smallest:.3g} s, per sample in samples.csv; 0 still "
                    "failed)")


def test_bad_specs_are_refused_by_name(tmp_path):
    path = tmp_path / "spec.toml"
    cases = [
        ("[dispersion.roll_deg]\ndist = 'gauss'\n", "dispersion.roll_deg.dist"),
        ("[dispersion.roll_deg]\ndist = 'normal'\nmean = 0.0\nstd = -1.0\n",
         "dispersion.roll_deg.std"),
        ("[dispersion.rol_deg]\ndist = 'normal'\nmean = 0.0\nstd = 1.0\n", "dispersion.rol_deg"),
        ("[dispersion.roll_deg]\ndist = 'uniform'\nlow = 2.0\nhigh = 1.0\n",
         "dispersion.roll_deg.high"),
        # a parameter left out is named as missing (it read "std = None: must be a number")
        ("[dispersion.roll_deg]\ndist = 'normal'\nmean = 0.0\n",
         "dispersion.roll_deg.std = None: is required: a normal distribution takes mean, std"),
        ("[montecarlo]\nn = 0\n", "montecarlo.n"),
        ("[montecarlo]\nsamples = 5\n", "montecarlo.samples"),
        ("[montecarlo]\nmethod = 'tsit5'\n", "montecarlo.method"),
        ("[fixed]\ndrop_hieght_m = 0.0\n", "fixed.drop_hieght_m"),  # a typo, in its table
        ("[montecarlo]\ndt_s = 3e-5\nt_end_s = 0.05\n",
         "montecarlo.dt_s = 3e-05: must divide montecarlo.t_end_s = 0.05 s into whole steps"),
        # an integer too large for a float, refused by its key (it overflowed where converted)
        (f"[montecarlo]\nn = {10**400}\n", "montecarlo.n = 1000"),
        (f"[dispersion.roll_deg]\ndist = 'uniform'\nlow = 0.0\nhigh = {10**400}\n",
         "dispersion.roll_deg.high = 1000"),
        (f"[fixed]\nroll_deg = {10**400}\n", "fixed.roll_deg = 1000"),
        # the run's limits, named by the spec's keys (they were named solver.dt, solver.t_end)
        ("[montecarlo]\ndt_s = 1e-300\n", "montecarlo.dt_s = 1e-300: t_end/dt must be <="),
        ("[montecarlo]\nt_end_s = 1e6\n", "montecarlo.t_end_s = 1000000.0: must be <= 100 s"),
        # step counts past float's range: the rule, not an OverflowError
        ("[montecarlo]\nt_end_s = 1e308\n", "montecarlo.t_end_s = 1e+308: must be <= 100 s"),
        ("[montecarlo]\ndt_s = 1e-320\n", "montecarlo.dt_s = 1e-320: t_end/dt must be <="),
    ]
    for text, field in cases:
        path.write_text(text)
        with pytest.raises(jl.ConfigError) as err:
            load_montecarlo_spec(path)
        assert str(err.value).startswith(field), str(err.value)
    with pytest.raises(jl.ConfigError, match="entirely outside the scene envelope"):
        MonteCarloSpec(dispersion={"roll_deg": Distribution("uniform", low=35, high=50)}, n=2)
    # bounds reaching outside: refused before the run (it used to report statistics over the
    # samples inside); a normal is unbounded, its few samples outside count as failures
    from jaxland._montecarlo._spec import envelope

    lo, hi = envelope("mass_scale")
    for dist in (Distribution("uniform", low=0.1, high=0.6),
                 Distribution("truncnormal", mean=1.0, std=0.5, low=lo, high=hi + 0.5)):
        with pytest.raises(jl.ConfigError, match=r"dispersion.mass_scale = .*reaches outside "
                                                 r"the scene envelope"):
            MonteCarloSpec(dispersion={"mass_scale": dist}, n=2)
    MonteCarloSpec(dispersion={"mass_scale": Distribution("uniform", low=lo, high=hi)}, n=2)
    # built in Python, checked as a TOML table is (it used to sample a 'lognormal' as a
    # normal, a uniform from mean/std as NaN, and take a negative std)
    for dist, needle in ((Distribution("lognormal", mean=0.0, std=0.5), "dist = 'lognormal'"),
                         (Distribution("normal", std=-0.5), "std = -0.5: must be > 0"),
                         (Distribution("uniform", low=3.0, high=1.0), "high = 1.0: must exceed"),
                         (Distribution("uniform", mean=2.0, std=0.5), "low = -inf"),
                         ({"dist": "normal"}, "must be a jaxland.Distribution")):
        with pytest.raises(jl.ConfigError, match=needle):
            MonteCarloSpec(dispersion={"sink_speed_mps": dist}, n=2)
    for text, field in [("dispersion = 3\n", "dispersion"), ("montecarlo = 5\n", "montecarlo"),
                        ("[fixed]\nroll_deg = 'abc'\n", "fixed.roll_deg"),
                        ("[montecarlo]\nseed = 9223372036854775807\n", "montecarlo.seed")]:
        path.write_text(text)
        with pytest.raises(jl.ConfigError) as err:
            load_montecarlo_spec(path)
        assert str(err.value).startswith(field), str(err.value)


@pytest.mark.parametrize("key", ["retry", "early_stop"])
@pytest.mark.parametrize("value", ["1", "0", "1.0"])
def test_a_switch_takes_only_true_or_false(tmp_path, capsys, key, value):
    """retry = 1 or early_stop = 0 is no TOML boolean (Python's 1 == True let it pass as
    one): refused by name before any work, exit 2 and one line."""
    from jaxland._checks import Choice
    from jaxland.cli import main

    path = tmp_path / "spec.toml"
    path.write_text(QUARTER_TOML.replace("t_end_s = 0.3", f"t_end_s = 0.3\n{key} = {value}"))
    with pytest.raises(jl.ConfigError) as err:
        load_montecarlo_spec(path)
    assert str(err.value) == f"montecarlo.{key} = {value}: must be true or false"
    assert main(["montecarlo", str(path), "--out", str(tmp_path / "mc")]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"jaxland: error: montecarlo.{key} = {value}: must be true or false"]
    assert not (tmp_path / "mc").exists()
    with pytest.raises(jl.ConfigError, match="must be true or false"):
        MonteCarloSpec(**{**QUARTER_SPEC, key: int(float(value))})
    # a choice that holds booleans takes only booleans
    with pytest.raises(jl.ConfigError, match="must be one of true, false"):
        Choice((True, False))("x", int(float(value)))
    assert Choice((True, False))("x", True) is True


def test_a_spec_file_that_disperses_nothing_is_refused(tmp_path, capsys):
    """No [dispersion] table, an empty one, or only constants: n copies of one landing, not a
    Monte Carlo; refused by name before any work (exit 2, one line, nothing written)."""
    from jaxland.cli import main

    path = tmp_path / "spec.toml"
    head = "[montecarlo]\nn = 4\nt_end_s = 0.3\n[fixed]\ndrop_height_m = 0.0\n"
    const = "[dispersion.sink_speed_mps]\ndist = 'constant'\nvalue = 2.0\n"
    rule = ("disperses nothing{}; a Monte Carlo needs at least one dispersed input (use "
            "jaxland simulate for one landing)")
    for text, shown, why in (
            (head, {}, ""), (head + "[dispersion]\n", {}, ""),
            (head + const, {"sink_speed_mps": {"dist": "constant", "value": 2.0}},
             ' (every entry is dist = "constant")')):
        path.write_text(text)
        with pytest.raises(jl.ConfigError) as err:
            load_montecarlo_spec(path)
        assert str(err.value) == f"dispersion = {shown!r}: {rule.format(why)}"
        assert main(["montecarlo", str(path), "--out", str(tmp_path / "mc")]) == 2
        assert capsys.readouterr().err.strip().splitlines() == [
            f"jaxland: error: dispersion = {shown!r}: {rule.format(why)}"]
        assert not (tmp_path / "mc").exists()
    # one input dispersed beside a constant is a Monte Carlo
    path.write_text(head + const + "[dispersion.mass_scale]\ndist = 'normal'\nmean = 1.0\n"
                    "std = 0.03\n")
    assert set(load_montecarlo_spec(path).dispersion) == {"sink_speed_mps", "mass_scale"}


def test_samples_outside_the_envelope_are_recorded_not_fatal():
    """An unbounded distribution can draw outside the envelope: those samples are failures with
    their reason (code 4), the batch goes on, and padding beyond n is never judged."""
    spec = MonteCarloSpec(dispersion={"sink_speed_mps": Distribution("normal", 0.3, 0.5)},
                          fixed={"drop_height_m": 0.0}, n=6, seed=2, t_end=0.05)
    res = run_montecarlo(spec, chunk=4, progress=False)
    outside = res.inputs["sink_speed_mps"] < 0.0
    assert outside.any() and not outside.all()
    np.testing.assert_array_equal(res.failure == 4, outside)
    assert res.summary["n_failed"] == int(outside.sum())
    # a draw outside the envelope never ran: no landing in the all-landings range either
    every = res.summary["bottoming"]["all_landings"]
    assert every["n_failed"] == 0 and every["n"] == int((~outside).sum())


def test_the_envelope_limits_themselves_are_accepted_and_stay_inside():
    """30 deg of slope or roll is the documented limit, which simulate accepts; the spec
    converted the radian limit back to 29.999999999999996 deg and refused 30 as outside
    [0, 30]. The limits are accepted, and every draw up to them stays inside the scene's
    own (radian) envelope: no sample becomes OUTSIDE_ENVELOPE."""
    spec = MonteCarloSpec(dispersion={"roll_deg": Distribution("uniform", low=-30.0, high=30.0),
                                      "pitch_deg": Distribution("constant", mean=30.0)},
                          fixed={"slope_deg": 30.0, "heading_deg": -720.0}, n=64, seed=3)
    scenes, _ = sample_scenes(spec, 0, 64)
    inside = jax.vmap(lambda s: s.inside_envelope(), in_axes=(batch_axes(scenes),))(scenes)
    assert inside.shape == (64,) and bool(np.all(inside))
    np.testing.assert_array_equal(scenes.slope, 30.0 * math.pi / 180.0)


def test_the_summary_records_each_distribution_by_the_parameters_its_kind_takes():
    """A uniform's summary entry read mean 0 and std 0 (the unused fields' defaults): a
    friction of 0.3 to 0.8 recorded with mean 0 and no spread. What a kind does not take is
    null; what it takes is as given (and the normal's infinite bounds, null, stay strict
    JSON)."""
    spec = MonteCarloSpec(dispersion={
        "friction": Distribution("uniform", low=0.3, high=0.8),
        "sink_speed_mps": Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
        "mass_scale": Distribution("normal", 1.0, 0.03),
        "heading_deg": Distribution("constant", mean=1.5)}, fixed={"drop_height_m": 0.0}, n=2)
    got = run_montecarlo(spec, chunk=2, progress=False).summary["dispersion"]
    assert got["friction"] == dict(kind="uniform", mean=None, std=None, low=0.3, high=0.8)
    assert got["sink_speed_mps"] == dict(kind="truncnormal", mean=2.0, std=0.3, low=1.0,
                                         high=3.0)
    assert got["mass_scale"] == dict(kind="normal", mean=1.0, std=0.03, low=None, high=None)
    assert got["heading_deg"] == dict(kind="constant", mean=1.5, std=None, low=None, high=None)
    json.dumps(got, allow_nan=False)


def test_results_are_saved_with_inputs(quarter_run, tmp_path):
    quarter_run.save(tmp_path)
    header = (tmp_path / "samples.csv").read_text().splitlines()[0].split(",")
    assert {"sink_speed_mps", "mass_scale", "leg0_max_stroke_m", "failure_code"} <= set(header)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["n"] == 12 and summary["sensitivity"]["ranking"][0]["input"] in (
        "sink_speed_mps", "mass_scale")
    # the quarter model cannot tip over: no tip-over map (every sample would read "stable")
    assert sorted(p.name for p in (tmp_path / "figures").glob("*.png")) == [
        "mc_envelopes.png", "mc_histograms.png"]


def test_a_stabilised_method_at_a_larger_step_agrees(quarter_run):
    """euler_implicit at 20x the default step, above explicit Euler's stability limit, gives
    the same envelopes to the accuracy the work-precision chart shows (< 5e-3 on max stroke)."""
    spec = MonteCarloSpec(**{**QUARTER_SPEC, "dt": 2e-4, "method": "euler_implicit"})
    assert spec.dt > float(jl.stable_step(jl.paper_vehicle()))
    res = run_montecarlo(spec, chunk=12, progress=False)
    assert res.summary["n_failed"] == 0 and res.summary["method"] == "euler_implicit"
    np.testing.assert_allclose(res.outputs["max_stroke_m"], quarter_run.outputs["max_stroke_m"],
                               rtol=5e-3)


def test_default_chunk_follows_the_platform():
    """A CPU run keeps small chunks; a run on any accelerator takes the large ones."""
    import jax

    from jaxland._montecarlo._run import DEFAULT_CHUNK, default_chunk

    class Device:
        def __init__(self, platform):
            self.platform = platform

    for model in ("quarter", "full"):
        assert default_chunk(model, [Device("cpu")] * 2) == DEFAULT_CHUNK["cpu"][model]
        assert default_chunk(model, [Device("gpu")]) == DEFAULT_CHUNK["accelerator"][model]
        assert DEFAULT_CHUNK["accelerator"][model] > DEFAULT_CHUNK["cpu"][model]
    here = "cpu" if all(d.platform == "cpu" for d in jax.local_devices()) else "accelerator"
    assert default_chunk("full", jax.local_devices()) == DEFAULT_CHUNK[here]["full"]


def test_a_montecarlo_folder_reruns_its_landings_from_its_own_spec_and_vehicle(tmp_path):
    """The folder records its inputs: spec.toml is the spec as run (--n and --seed applied,
    every default written out) and vehicle.toml the vehicle; run again from those two files,
    the landings are the same, sample by sample, and the spec reads back equal."""
    from jaxland._montecarlo import load_montecarlo_spec
    from jaxland.cli import main

    spec = tmp_path / "spec_in.toml"
    spec.write_text(QUARTER_TOML.replace("[fixed]", "[fixed]\nfriction = 0.6"))
    first, again = tmp_path / "first", tmp_path / "again"
    assert main(["montecarlo", str(spec), "--n", "5", "--seed", "3", "--no-plots", "--quiet",
                 "--out", str(first)]) == 0
    written = load_montecarlo_spec(first / "spec.toml")
    assert (written.n, written.seed, written.t_end_check) == (5, 3, 32)
    assert main(["montecarlo", str(first / "spec.toml"), "--config", str(first / "vehicle.toml"),
                 "--no-plots", "--quiet", "--out", str(again)]) == 0
    assert (again / "samples.csv").read_text() == (first / "samples.csv").read_text()
    assert load_montecarlo_spec(again / "spec.toml") == written


def test_the_sensitivity_ranks_no_rounding_noise():
    """A target the same in every landing up to rounding (a tip-over margin that no dispersion
    moves) has no drivers: the regression is not run and the summary says why, where a
    target that the inputs move is ranked by them."""
    from jaxland._montecarlo._stats import sensitivity

    rng = np.random.default_rng(0)
    inputs = {"sink_speed_mps": rng.uniform(1, 3, 64), "plateau_scale": rng.normal(1, 0.05,
                                                                                   (64, 4))}
    ok = np.ones(64, bool)
    flat = 1.582 + rng.normal(0, 1e-16, 64)  # rounding about one value
    s = sensitivity(inputs, flat, ok)
    assert s["ranking"] == [] and "same in every successful landing" in s["not_estimated"]
    moved = 0.1 * inputs["sink_speed_mps"] + rng.normal(0, 1e-3, 64)
    s = sensitivity(inputs, moved, ok)
    assert s["not_estimated"] is None and s["ranking"][0]["input"] == "sink_speed_mps"
    assert s["ranking"][0]["r2_of_fit"] > 0.99
    # the standard errors against ordinary least squares' own formula, from scratch: the
    # noise 1e-3 over sqrt(n) per standardised input, and t the effect over it
    X = np.column_stack([np.ones(64), (inputs["sink_speed_mps"] - inputs["sink_speed_mps"].mean())
                         / inputs["sink_speed_mps"].std()]
                        + [(c - c.mean()) / c.std() for c in inputs["plateau_scale"].T])
    beta = np.linalg.solve(X.T @ X, X.T @ moved)
    res = moved - X @ beta
    se = np.sqrt(res @ res / (64 - 6) * np.diag(np.linalg.inv(X.T @ X)))
    top = s["ranking"][0]
    assert top["effect_per_std"] == pytest.approx(beta[1], rel=1e-9)
    assert top["std_error"] == pytest.approx(se[1], rel=1e-6)
    assert top["t"] == pytest.approx(beta[1] / se[1], rel=1e-6) and top["t"] > 100
    assert all(abs(r["t"]) < 4 for r in s["ranking"][1:])  # the plateau scales do nothing
    s = sensitivity(inputs, moved, np.arange(64) < 5)  # 5 landings, 5 inputs
    assert s["ranking"] == [] and s["not_estimated"].startswith("5 successful landings")


def test_the_sensitivity_reads_an_azimuth_as_its_sine_and_cosine():
    """A heading drawn over the whole circle moves a target through its cosine: 0 and 360 deg
    are one heading. A line through the angle reads them as its two extremes and finds no
    effect (t about 0); the sine and cosine find it (the effect against ordinary least squares
    on the cosine, from scratch), and the summary and the tip-over map name the heading once."""
    from jaxland._montecarlo._spec import period
    from jaxland._montecarlo._stats import ranked_inputs, sensitivity

    rng = np.random.default_rng(1)
    heading = rng.uniform(0.0, 360.0, 400)
    inputs = {"heading_deg": heading, "sink_speed_mps": rng.uniform(1, 3, 400)}
    y = 0.05 * np.cos(np.radians(heading)) + rng.normal(0, 1e-3, 400)
    ok = np.ones(400, bool)
    assert period("heading_deg") == pytest.approx(360.0) and period("sink_speed_mps") is None
    assert period("slope_direction_deg") == pytest.approx(360.0)
    assert period("yaw_deg") == pytest.approx(360.0) and period("roll_deg") is None
    as_line = sensitivity(inputs, y, ok)  # no period: the angle as a line
    assert abs({r["input"]: r["t"] for r in as_line["ranking"]}["heading_deg"]) < 4
    s = sensitivity(inputs, y, ok, {"heading_deg": period("heading_deg")})
    top = s["ranking"][0]
    c = np.cos(np.radians(heading))
    X = np.column_stack([np.ones(400), (np.sin(np.radians(heading)) - np.sin(np.radians(
        heading)).mean()) / np.sin(np.radians(heading)).std(), (c - c.mean()) / c.std(),
        (inputs["sink_speed_mps"] - inputs["sink_speed_mps"].mean())
        / inputs["sink_speed_mps"].std()])
    beta = np.linalg.lstsq(X, y, rcond=None)[0]
    assert top["input"] == "heading_deg (cos)" and top["t"] > 100
    assert top["effect_per_std"] == pytest.approx(beta[2], rel=1e-9)
    assert top["r2_of_fit"] > 0.99
    assert ranked_inputs(s["ranking"]) == ["heading_deg", "sink_speed_mps"]
    # the heading's rank does not depend on where world x points: its effect at 45 deg splits
    # into a sine and a cosine row each smaller than a third input's effect, and it still
    # ranks first, by their root sum of squares; its two rows stay side by side
    turned = 0.05 * np.cos(np.radians(heading - 45.0)) + rng.normal(0, 1e-3, 400)
    third = {**inputs, "friction": rng.uniform(0.3, 0.8, 400)}
    y3 = turned + 0.03 * (third["friction"] - 0.55) / third["friction"].std()
    s = sensitivity(third, y3, ok, {"heading_deg": 360.0})
    assert [r["input"] for r in s["ranking"]][:3] == ["heading_deg (sin)", "heading_deg (cos)",
                                                      "friction"]
    assert max(abs(r["effect_per_std"]) for r in s["ranking"][:2]) < s["ranking"][2][
        "effect_per_std"]
    # headings of 0 and 360 deg only: the sine varies by rounding (sin 360 deg = -2.4e-16)
    # and is no input; the cosine does not vary
    edge = {"heading_deg": np.where(np.arange(400) % 2 == 0, 0.0, 360.0),
            "sink_speed_mps": inputs["sink_speed_mps"]}
    s = sensitivity(edge, 0.1 * edge["sink_speed_mps"], ok, {"heading_deg": 360.0})
    assert ranked_inputs(s["ranking"]) == ["sink_speed_mps"]
    # the run's summary regresses on them: a heading drawn over the circle in a vertical drop
    spec = MonteCarloSpec(**{**QUARTER_SPEC, "n": 8, "dispersion": {
        **QUARTER_SPEC["dispersion"], "heading_deg": Distribution("uniform", low=0.0,
                                                                  high=360.0)}})
    ranked = run_montecarlo(spec, chunk=8, progress=False).summary["sensitivity"]
    assert {r["input"] for r in ranked["ranking"]} == {
        "sink_speed_mps", "mass_scale", "heading_deg (sin)", "heading_deg (cos)"}
    assert "sine and cosine" in ranked["method"]


def test_spec_toml_writes_numpy_numbers_as_their_values():
    """A spec built in Python with numpy numbers ran with them, but spec.toml truncated each to
    an integer (high = 2.5 as float32 read back 2, dt 1e-4 as 0): the folder's rerun drew other
    landings. Written as float64 values, they read back equal."""
    from jaxland._montecarlo._spec import montecarlo_spec_from_dict, montecarlo_spec_to_toml

    D = jl.Distribution
    spec = jl.MonteCarloSpec(
        dispersion={"sink_speed_mps": D("uniform", low=1.5, high=np.float32(2.5)),
                    "mass_scale": D("normal", mean=1.0, std=np.float16(0.03))},
        fixed={"drop_height_m": np.float64(0.0)}, n=np.int64(4), dt=np.float32(1e-4),
        t_end=np.float32(0.2), t_end_check=0)
    import tomllib

    back = montecarlo_spec_from_dict(tomllib.loads(montecarlo_spec_to_toml(spec)))
    assert back.dispersion["sink_speed_mps"].high == 2.5
    assert back.dispersion["mass_scale"].std == float(np.float16(0.03)) > 0.0
    assert back.dt == float(np.float32(1e-4)) and back.t_end == float(np.float32(0.2))
    assert back.n == 4


@pytest.mark.parametrize("fixed,dispersion,model", [
    # symmetric by the scenes' own rule: a plateau scale equal on every leg, a heading or a
    # slope direction without a speed or a slope, a roll held at 0
    (dict(plateau_scale=0.9), {}, "quarter"),
    (dict(plateau_scale=[0.9, 0.9, 0.9, 0.9]), {}, "quarter"),
    (dict(slope_direction_deg=90.0, heading_deg=45.0), {}, "quarter"),
    ({}, dict(roll_deg=jl.Distribution("constant", mean=0.0)), "quarter"),
    # not: a roll, a plateau scale drawn leg by leg, unequal scales, an offset mass
    ({}, dict(roll_deg=jl.Distribution("constant", mean=1.0)), "full"),
    ({}, dict(plateau_scale=jl.Distribution("normal", mean=1.0, std=0.05)), "full"),
    (dict(plateau_scale=[0.9, 1.0, 0.9, 0.9]), {}, "full"),
    (dict(com_offset_x_m=0.01), {}, "full"),
])
def test_auto_picks_the_quarter_model_exactly_where_the_scenes_are_symmetric(fixed, dispersion,
                                                                           model):
    """model = "auto" and the quarter model's refusal follow the scenes' own symmetry rule
    (is_symmetric on the drawn scenes): a fixed plateau scale of 0.9 or a heading of 45 deg
    ran the full 3-D model, and model = "quarter" was refused for them."""
    from jaxland._montecarlo._sample import sample_scenes
    from jaxland._scene import is_symmetric

    spec = jl.MonteCarloSpec(
        dispersion={"sink_speed_mps": jl.Distribution("uniform", low=1.0, high=2.0),
                    **dispersion}, fixed=dict(drop_height_m=0.0, **fixed), n=16, t_end=0.2)
    assert spec.resolved_model() == model
    scenes, _ = sample_scenes(spec, 0, 16)
    assert is_symmetric(scenes) == (model == "quarter")


def test_retries_run_in_chunks_and_count_in_the_wall_time(monkeypatch):
    """Hard landings at a leapfrog step too long for them fail and are retried: the retries ran
    all at once whatever --chunk said (memory unbounded), and their time was left out of
    wall_s and landings_per_s (a run of 4.7 s reported 1.7 s)."""
    import time

    from jaxland._montecarlo import _run

    sizes = []
    per_sample = _run._per_sample

    def spy(vehicle, solver, model, scenes):  # the retry's program, traced once per size
        sizes.append(int(np.shape(scenes.sink_speed)[0]))
        return per_sample(vehicle, solver, model, scenes)

    monkeypatch.setattr(_run, "_per_sample", spy)
    spec = jl.MonteCarloSpec(
        dispersion={"sink_speed_mps": jl.Distribution("uniform", low=4.0, high=12.0)},
        fixed={"drop_height_m": 0.0}, n=24, dt=4e-4, t_end=0.4, method="leapfrog",
        t_end_check=0, model="quarter")
    t0 = time.perf_counter()
    res = jl.run_montecarlo(spec, chunk=8, progress=False)
    took = time.perf_counter() - t0
    assert int(res.outputs["retried"].sum()) > 8 and sizes and max(sizes) <= 8
    assert res.summary["wall_s"] >= 0.9 * took


def test_a_clean_t_end_check_of_few_landings_bounds_what_it_cannot_see():
    """0 changed of 1 checked read "outcomes final at t_end_s"; the line now says the checked
    landings are final and bounds the rest by the 95 % Wilson upper bound of 0 in n."""
    from jaxland._montecarlo._stats import wilson_interval
    from jaxland.cli._montecarlo import _t_end_check_text

    for n in (1, 4, 32):
        check = dict(n_checked=n, n_changed=0, n_rerun_failed=0, of="finished landings",
                     t_end_s=2.0, tolerance=1e-3,
                     changed=dict(ci95_wilson=list(wilson_interval(0, n))))
        text = _t_end_check_text(dict(t_end_s=1.0, t_end_check=check))
        upper = wilson_interval(0, n)[1]
        assert text.endswith(f"the checked landings are final at t_end_s; up to {upper:.0%} "
                             "of the finished landings may not be (95 % upper bound)"), text


def test_a_seed_past_its_bound_is_told_the_bound_in_full(tmp_path, capsys):
    """--seed 99999999999 read "must be <= 2.14748e+09", a rounded bound that 2147484000
    would seem to meet: the bound is shown in full where its short form is not exact."""
    from jaxland.cli import main

    spec = Path(__file__).parents[1] / "examples" / "montecarlo_dispersed.toml"
    assert main(["montecarlo", str(spec), "--seed", "99999999999", "--out",
                 str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.strip().endswith("--seed = 99999999999: must be <= 2147483647"), err


def test_a_flag_given_for_a_count_is_named_as_written(tmp_path, capsys):
    """n = true read "montecarlo.n = True: must be a finite number": the value as TOML wrote it,
    and the rule the count has."""
    from jaxland.cli import main

    spec = tmp_path / "spec.toml"
    spec.write_text('[montecarlo]\nn = true\n[dispersion.sink_speed_mps]\ndist = "uniform"\n'
                    "low = 1.0\nhigh = 2.0\n")
    assert main(["montecarlo", str(spec), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.strip().endswith("montecarlo.n = 'true': must be an integer"), err


def test_a_distribution_built_in_python_refuses_a_parameter_its_kind_ignores():
    """A uniform given a mean, or a constant a spread, was accepted and the extra value
    silently ignored (the TOML route refuses it): refused by name, as there."""
    for dist, field in ((Distribution("uniform", mean=5.0, low=1.0, high=3.0), "mean"),
                        (Distribution("constant", mean=2.0, std=1.0), "std"),
                        (Distribution("normal", 2.0, 0.3, high=4.0), "high")):
        with pytest.raises(jl.ConfigError, match=rf"^dispersion\.sink_speed_mps\.{field} = .*"
                                                 "not a parameter of a"):
            MonteCarloSpec(dispersion={"sink_speed_mps": dist})
    MonteCarloSpec(dispersion={"sink_speed_mps": Distribution("uniform", low=1.0, high=3.0)})


def test_sample_scenes_refuses_what_is_no_sample():
    """Sample i is drawn from (seed, i): start -3 drew 'samples' no run has, start 0.5 drew
    samples 0 and 1, and a count of -2 an empty batch, all silently. Each is refused by name."""
    spec = MonteCarloSpec(**QUARTER_SPEC)
    for start, count, name in ((-3, 2, "start"), (0.5, 2, "start"), (0, -2, "count"),
                               (0, 0, "count"), (True, 2, "start")):
        with pytest.raises(jl.ConfigError, match=f"^{name} = "):
            sample_scenes(spec, start, count)
    assert sample_scenes(spec, np.int64(3), 2)[1]["sink_speed_mps"].shape == (2,)
