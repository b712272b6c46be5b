"""The Monte Carlo pipeline: early stop per sample (spec key early_stop) gives the outcomes of
the landings run to t_end, and the spec key is read and checked like the others."""

import numpy as np
import pytest

import jaxland as jl
from jaxland import Distribution, MonteCarloSpec, run_montecarlo
from jaxland._montecarlo import montecarlo_spec_from_dict

SPEC = dict(dispersion={"sink_speed_mps": Distribution("truncnormal", 2.0, 0.5, 1.0, 3.5),
                        "mass_scale": Distribution("normal", 1.0, 0.03)},
            fixed={"drop_height_m": 0.0}, n=5, seed=11, t_end=3.0)


def test_early_stop_keeps_every_sample_outcome():
    """5 dispersed quarter landings for 3 s (2 chunks): with early stop most settle before
    3 s, and every sample's outcomes and verdict are the run-to-the-end ones."""
    full = run_montecarlo(MonteCarloSpec(**SPEC), chunk=3, progress=False)
    early = run_montecarlo(MonteCarloSpec(**SPEC, early_stop=True), chunk=3, progress=False)
    settled = early.outputs.pop("settled_time_s")
    assert np.isfinite(settled).sum() >= 3 and np.nanmax(settled) < SPEC["t_end"]
    np.testing.assert_array_equal(early.failure, full.failure)
    for k, v in full.outputs.items():
        if k == "energy_closure_rel":  # judged up to the settle time (tests/test_early_stop.py)
            np.testing.assert_allclose(early.outputs[k], v, rtol=0.05)
        else:  # the same up to how XLA compiles either program
            np.testing.assert_allclose(early.outputs[k], v, rtol=1e-9, atol=0, err_msg=k)
    assert early.summary["tip_over"] == full.summary["tip_over"]


def test_early_stop_spec_key():
    spec = montecarlo_spec_from_dict({"montecarlo": {"early_stop": True},
                                         "dispersion": {"sink_speed_mps": {
                                             "dist": "uniform", "low": 1.0, "high": 2.0}}})
    assert spec.early_stop is True
    assert MonteCarloSpec(dispersion={}).early_stop is False
    with pytest.raises(jl.ConfigError, match="early_stop"):
        montecarlo_spec_from_dict({"montecarlo": {"early_stop": "yes"}})


def test_a_second_vehicle_reuses_the_compiled_chunk_with_its_own_outcomes():
    """``share_program``: a design's verification runs the baseline and the design through
    one compiled chunk (the vehicle is its argument): the second vehicle's outcomes are its
    own, sample by sample those of a Monte Carlo compiled for it alone (the vehicle a
    constant), and the program is not recompiled."""
    from jaxland._montecarlo import _run

    spec = MonteCarloSpec(**dict(SPEC, n=3, t_end=0.2))
    paper = jl.paper_vehicle()
    stiff = jl.vehicle_from_dict({"honeycomb": {"F1_N": 1.2 * float(paper.honeycomb.F1)}})
    first = run_montecarlo(spec, paper, progress=False, share_program=True)
    second = run_montecarlo(spec, stiff, progress=False, share_program=True)
    (program,) = _run._COMPILED.values()
    assert program._cache_size() == 1
    _run._COMPILED.clear()
    alone = run_montecarlo(spec, stiff, progress=False)
    a1, a2 = first.outputs["peak_body_accel_mps2"], second.outputs["peak_body_accel_mps2"]
    assert np.all(np.abs(a2 - a1) > 0.01 * a1)  # every sample saw the stiffer honeycomb
    for k, v in alone.outputs.items():  # up to how XLA compiles either program
        # the ledger's closure is a difference of energies, relative to the landing's energy:
        # its rounding is absolute in those units (7.6e-14 between the two programs on a GPU,
        # 2.2e-9 of the closure itself), not relative to the closure
        atol = 1e-12 if k == "energy_closure_rel" else 0.0
        np.testing.assert_allclose(second.outputs[k], v, rtol=1e-9, atol=atol, err_msg=k)


def _drop_spec(t_end, **kw):
    """Quarter landings from 0.2 m (touchdown at about 0.2 s), mass dispersed 3 %."""
    return MonteCarloSpec(**{**dict(dispersion={"mass_scale": Distribution("normal", 1.0, 0.03)},
                                    fixed={"drop_height_m": 0.2}, n=4, seed=3, t_end=t_end,
                                    dt=1e-4), **kw})


def test_the_t_end_check_measures_what_a_longer_run_adds():
    """Cut at 0.37 s the landings are on their rebound, a foot in the air: UNFINISHED (a leg
    still compressing at its largest stroke) does not catch them, but they land again and
    crush further. The t_end check reruns them to 0.74 s and reports the growth of their max
    stroke, which independent single landings to 0.37 s and 0.74 s give too; cut at 1 s the
    same landings are over (nothing changes by 2 s)."""
    from jaxland._montecarlo._sample import sample_scenes

    spec = _drop_spec(0.37, t_end_check=3)
    res = run_montecarlo(spec, progress=False)
    assert np.all(res.failure == 0)
    c = res.summary["t_end_check"]
    assert (c["n_checked"], c["t_end_s"], c["n_rerun_failed"]) == (3, 0.74, 0)
    scenes, _ = sample_scenes(spec, 0, 3, 4)
    stroke = [np.asarray(jl.landings(jl.paper_vehicle(), scenes, jl.Solver(
        dt=1e-4, t_end=t, save_dt=t, method="euler"), "quarter")[1]["max_stroke_m"])
        for t in (0.37, 0.74)]
    growth = stroke[1] - stroke[0]
    assert growth.max() > 5e-4  # the second impact crushes by most of a millimetre
    assert c["max_stroke_growth_m"] == pytest.approx(growth.max(), rel=1e-6)
    assert c["changed_samples"] == np.flatnonzero(growth > 1e-3 * stroke[0]).tolist()
    assert c["n_changed"] == c["n_max_stroke_grew"] == len(c["changed_samples"]) >= 1
    over = run_montecarlo(_drop_spec(1.0, t_end_check=4), progress=False).summary["t_end_check"]
    assert (over["n_checked"], over["n_changed"]) == (4, 0)


def test_the_t_end_check_spec_key():
    assert MonteCarloSpec(dispersion={}).t_end_check == 32
    assert run_montecarlo(_drop_spec(0.37, n=2, t_end_check=0),
                          progress=False).summary["t_end_check"] is None
    with pytest.raises(jl.ConfigError, match=r"montecarlo\.t_end_check = -1"):
        montecarlo_spec_from_dict({"montecarlo": {"t_end_check": -1}})


def test_the_t_end_check_is_skipped_by_name_beyond_the_longest_run():
    """Twice a t_end_s of 60 s is beyond the longest run a solver takes (100 s): the check is
    skipped and says why, instead of failing the whole run after its landings."""
    res = run_montecarlo(_drop_spec(60.0, n=2, t_end_check=2), progress=False)
    c = res.summary["t_end_check"]
    assert c["n_checked"] == 0 and "beyond the longest run (100 s)" in c["skipped"]


def test_the_t_end_check_line_says_what_was_checked():
    """The command's line names what changed, and claims no final outcome from a check whose
    reruns all failed."""
    from jaxland._montecarlo._stats import proportion
    from jaxland.cli._montecarlo import _t_end_check_text

    none = dict(n_checked=0, of="finished landings", t_end_s=2.0, tolerance=1e-3, n_changed=0,
                changed=proportion(np.zeros(0, bool)), n_max_stroke_grew=0,
                max_stroke_growth_m=None, n_tipped_later=0, n_bottomed_later=0,
                n_rerun_failed=32)
    line = _t_end_check_text({"t_end_s": 1.0, "t_end_check": none})
    assert line.startswith("no landing could be checked") and "final" not in line
    tipped = dict(none, n_checked=30, n_rerun_failed=0, n_changed=2, n_tipped_later=2,
                  max_stroke_growth_m=0.0,
                  changed=proportion(np.r_[np.ones(2, bool), np.zeros(28, bool)]))
    line = _t_end_check_text({"t_end_s": 1.0, "t_end_check": tipped})
    assert "2 tipped over later" in line and "max stroke grew" not in line
    assert "raise t_end_s" in line
    calm = dict(tipped, n_changed=0, n_tipped_later=0, changed=proportion(np.zeros(30, bool)))
    assert "within 0.1% of itself" in _t_end_check_text({"t_end_s": 1.0, "t_end_check": calm})
