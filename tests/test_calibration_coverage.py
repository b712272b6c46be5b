"""Calibration standard errors against the spread of the estimates over noise realisations.

A standard error claims to be the standard deviation of the estimate over repeated experiments.
So repeat the experiment: one noise-free 0.2 m drop of the rig's truth (calibration.virtual_rig,
no offset, no crush peak), plus N_SEEDS independent draws of white Gaussian noise of the rig's
documented levels (virtual_rig.NOISE), added here, each fitted by cal.fit. The reference is the
sample standard deviation of those estimates about their own mean (so a bias of the model, which
a standard error does not claim to cover, does not enter).

Affordable: three parameters (D_b, F1, F2; the rest held at the truth), one 0.1 s first-impact
window, least squares, no multistart, started at the truth: about 0.15 s per fit once compiled.

Measured (80 seeds): the sample standard deviation is 1.01, 1.01 and 1.02 x the mean reported
standard error for D_b, F1 and F2; pooled, the rms of (estimate - mean) / SE is 1.02. Without
the sensors' offsets' error in the standard errors (each offset is the mean of the record's
50 ms of free fall) it was 1.20. The band on the pooled rms is [0.9, 1.35]: with 240 z values
(80 seeds x 3) its own sampling error is about 1 / sqrt(2 x 237) = 0.046. Standard errors off
by sqrt(2) fall outside it either way: x sqrt(2) gives 0.72, / sqrt(2) gives 1.44.
"""

import copy

import numpy as np
import pytest

import calibration as cal
import jaxland as jl
from calibration import virtual_rig as vr

NAMES = ("D_b", "F1", "F2")
N_SEEDS = 80
RATE = 5000.0
BAND = (0.9, 1.35)


@pytest.fixture(scope="module")
def estimates():
    truth = vr.truth_vehicle()
    t, clean, _ = vr.record(truth, 0.2, duration_s=0.16, noise=None, stroke_offset_m=0.0,
                            crush_peak=0.0)
    est, se, sigma2 = [], [], []
    for seed in range(N_SEEDS):
        rng = np.random.default_rng(20_000 + seed)
        ch = {c: y + rng.normal(0.0, vr.NOISE[c], size=y.size) for c, y in clean.items()}
        drop = cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                        vehicle=jl.paper_vehicle(), name=f"seed{seed}",
                                        synthetic=True)
        res = cal.fit([drop], NAMES, windows=(0.1,), refine_window_s=None, robust=None,
                      multistart=False, start=truth, vehicle=truth)
        est.append(res.values)
        se.append(res.std_errors)
        sigma2.append(res.sigma2)
    return np.array(est), np.array(se), np.array(sigma2)


def test_noise_level_is_estimated(estimates):
    """The residuals' variance, in units of the channels' noise, is 1 on average: the fit
    weights the channels by the right noise (the SEs scale with it)."""
    _, _, sigma2 = estimates
    assert 0.9 < float(np.mean(sigma2)) < 1.15, np.mean(sigma2)


def test_standard_errors_match_the_spread_over_noise_seeds(estimates):
    est, se, _ = estimates
    assert np.all(np.isfinite(se)) and np.all(se > 0)
    z = (est - est.mean(axis=0)) / se
    rms = float(np.sqrt(np.sum(z**2) / ((N_SEEDS - 1) * len(NAMES))))
    assert BAND[0] <= rms <= BAND[1], rms
    # and per parameter, a looser band (80 values each: sampling error ~0.08)
    ratio = est.std(axis=0, ddof=1) / se.mean(axis=0)
    assert np.all((ratio > 0.75) & (ratio < 1.45)), dict(zip(NAMES, ratio))
    # the standard errors are stable from seed to seed (they depend on the noise only weakly)
    assert np.all(se.std(axis=0) < 0.1 * se.mean(axis=0))


def test_offsets_error_term_is_the_fits_response_to_an_offset_shift():
    """The reported variance carries the offsets' error: each channel's offset is the mean of
    its n free-fall samples (variance sigma_c^2 / n), and shifting a channel's data by delta
    moves the refitted values by d_c delta. So the reported variance less the variance
    without that term (offset_samples = 0) is sum_c d_c^2 sigma_c^2 / n, with d_c from
    central-difference refits here."""
    truth = vr.truth_vehicle()
    drop = vr.drop_test(0.2, duration_s=0.16, seed=11, stroke_offset_m=0.0, crush_peak=0.0)
    kw = dict(params=NAMES, windows=(0.1,), refine_window_s=None, robust=None,
              multistart=False, vehicle=truth)
    res = cal.fit([drop], start=truth, **kw)
    none = copy.copy(drop)
    none.offset_samples = 0
    res0 = cal.fit([none], start=truth, **kw)
    np.testing.assert_allclose(res0.values, res.values, rtol=1e-12)
    n = drop.offset_samples
    assert n == int(round(0.05 * RATE))  # the rig's 50 ms of free fall before touchdown
    expected = np.zeros(len(NAMES))
    for c, sigma in drop.noise_std.items():
        delta = 5.0 * sigma / np.sqrt(n)
        moved = []
        for sign in (1.0, -1.0):
            shifted = copy.deepcopy(drop)
            shifted.offsets[c] -= sign * delta  # the corrected data move by +delta
            moved.append(cal.fit([shifted], start=res.vehicle, **kw).values)
        d_c = (moved[0] - moved[1]) / (2.0 * delta)
        expected += d_c**2 * sigma**2 / n
    term = res.std_errors**2 - res0.std_errors**2
    assert np.all(term > 0.05 * res0.std_errors**2)  # it matters at 50 ms of free fall
    np.testing.assert_allclose(term, expected, rtol=0.1)
