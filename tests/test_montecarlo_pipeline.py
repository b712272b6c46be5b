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
        np.testing.assert_allclose(second.outputs[k], v, rtol=1e-9, atol=0, err_msg=k)
