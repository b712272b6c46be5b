"""Lab records as labs write them (issue 12, item 5): the SAE J211 CFC filter applied alike to
data and model, records that start at touchdown or mid-fall, several instrumented legs, and a
drop height checked against the record's free fall. Each conversion and each refusal.

The filter is checked against the analog Butterworth response it is defined by (independent
of the code), the JAX filter against the numpy one and against finite differences; the
misfit's use of it by the residual at the truth of a noise-free filtered record (zero only if
the model is filtered alike). Fits here are short: 3 parameters on a 30 ms window.
"""

import math
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import calibration as cal
import jaxland as jl
from calibration import virtual_rig as vr
from calibration._filter import (
    CFC_CLASSES,
    cfc_coefficients,
    filtfilt_jax,
    filtfilt_np,
    min_rate_Hz,
    noise_gain,
    white_lag1,
)
from jaxland.cli import main

RATE = 5000.0
TRUTH = vr.truth_vehicle()
NAMES3 = ("D_b", "k_b1", "F1")  # a 30 ms window never reaches F2
CLEAN = dict(noise=None, stroke_offset_m=0.0, crush_peak=0.0)


# ------------------------------------------------------------------------------ the filter

def _gain_db(cfc, f_Hz, rate=20000.0, n=40000):
    t = np.arange(n) / rate
    x = np.sin(2 * np.pi * f_Hz * t)
    y = filtfilt_np(x, cfc_coefficients(cfc, rate))
    mid = slice(n // 4, 3 * n // 4)  # away from the ends
    return 20 * math.log10(np.std(y[mid]) / np.std(x[mid]))


@pytest.mark.parametrize("cfc", sorted(CFC_CLASSES))
def test_cfc_filter_is_the_j211_four_pole_butterworth(cfc):
    """Forward-backward two-pole Butterworth at f_d = 2.0775 CFC: the pair's amplitude is
    |H|^2 = 1 / (1 + x^4), x = tan(pi f / rate) / tan(pi f_d / rate) (the analog Butterworth
    through the bilinear map); -3 dB at F_H = 1.667 CFC (J211's table); unit DC gain; zero
    phase (a symmetric impulse response)."""
    f_h, rate = CFC_CLASSES[cfc], 20000.0
    f_d = 2.0775 * cfc
    for f in (0.1 * f_h, f_h, 2.0 * f_h):
        x = math.tan(math.pi * f / rate) / math.tan(math.pi * f_d / rate)
        assert _gain_db(cfc, f, rate) == pytest.approx(-20 * math.log10(1 + x**4), abs=0.02), f
    assert _gain_db(cfc, f_h, rate) == pytest.approx(-3.0, abs=0.25)  # bilinear warping
    c = cfc_coefficients(cfc, 20000.0)
    assert np.sum(c[:3]) / (1 - c[3] - c[4]) == pytest.approx(1.0, rel=1e-12)
    x = np.zeros(2001)
    x[1000] = 1.0
    h = filtfilt_np(x, c)
    np.testing.assert_allclose(h[:1000], h[1001:][::-1], rtol=0, atol=1e-11 * h.max())
    assert 0 < noise_gain(c) < 1 and 0 < white_lag1(c) < 1


def test_jax_filter_equals_numpy_and_differentiates():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 3, 120))
    coeffs = np.stack([cfc_coefficients(c, RATE) for c in (60, 180, 1000)])
    y = np.asarray(jax.jit(filtfilt_jax)(jnp.asarray(x), jnp.asarray(coeffs)))
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(y[i, j], filtfilt_np(x[i, j], coeffs[j]), rtol=1e-11,
                                       atol=1e-12)

    def f(a):  # a scalar of a filtered trace that depends on a parameter nonlinearly
        return jnp.sum(filtfilt_jax(jnp.sin(a * jnp.arange(120.0) / 20.0), coeffs[1]) ** 2)

    a, h = 1.3, 1e-6
    fd = (f(a + h) - f(a - h)) / (2 * h)
    assert float(jax.grad(f)(a)) == pytest.approx(float(fd), rel=1e-6)


# ------------------------------------------------------------------- the filter in the misfit

@pytest.fixture(scope="module")
def filtered_drop():
    """A noise-free 0.2 m record the 'lab' delivered CFC 180 filtered (strongly: 300 Hz), with
    its true touchdown time (the zero-phase filter spreads the onset ahead of it)."""
    t_td = vr.record(TRUTH, 0.2, duration_s=0.12, **CLEAN)[2]["touchdown_time_in_record_s"]
    return vr.drop_test(0.2, duration_s=0.12, cfc=180, touchdown_time_s=t_td, **CLEAN)


def test_the_misfit_filters_the_model_alike(filtered_drop):
    """At the truth the filtered model follows the filtered record as closely as the plain
    model follows a plain record (the model's own discretisation, ~10 N); the same filtered
    record compared with the unfiltered model is far off."""
    d = filtered_drop
    assert d.filters == {c: 180 for c in d.channels} and d.filter_data_prefiltered
    prob = cal.CalibrationProblem([d], NAMES3, vehicle=TRUTH, window_s=0.03)
    assert prob.filtered and prob.margin_s > 0.005  # CFC 180 settles in 5.5 ms
    rms = prob.channel_rms(prob.theta_from())[d.name]
    as_plain = cal.DropTest.from_arrays(d.time_s, d.channels, sample_rate_Hz=RATE,
                                        drop_height_m=0.2, name=d.name,
                                        touchdown_time_s=d.touchdown_time_s)
    plain = cal.CalibrationProblem([as_plain], NAMES3, vehicle=TRUTH, window_s=0.03)
    rms_plain = plain.channel_rms(plain.theta_from())[d.name]
    for c in ("normal_force_N", "buffer_force_N", "body_accel_mps2"):
        assert rms[c] < 0.1 * rms_plain[c], (c, rms[c], rms_plain[c])
    assert rms["buffer_force_N"] < 20.0


def test_a_fit_through_the_filter_recovers_the_truth_and_trusts_hac(filtered_drop):
    start = {n: float(cal.PARAMS[n][0](TRUTH)) * 1.1 for n in NAMES3}
    with warnings.catch_warnings():  # noise-free: the smeared onset sets the 'noise'
        warnings.simplefilter("ignore", cal.MisfitWarning)
        res = cal.fit([filtered_drop], NAMES3, windows=(0.03,), refine_window_s=None,
                      multistart=False, vehicle=TRUTH, start=start)
    truth = np.array([float(cal.PARAMS[n][0](TRUTH)) for n in NAMES3])
    np.testing.assert_allclose(res.values, truth, rtol=5e-3)
    rep = res.report()
    assert rep["misfit"]["trust"] == "std_error_hac"  # filtered noise is correlated
    assert rep["settings"]["filter_cfc"] == {filtered_drop.name: filtered_drop.filters}
    assert rep["drops"][0]["filter_cfc"]["stroke_m"] == 180


@pytest.mark.parametrize("spec,needle", [
    (100, "must be one of the SAE J211 channel frequency classes 60, 180, 600, 1000"),
    (True, "must be one of the SAE J211"),
    ({"stroke_mm": 60}, "names no column"),
    (1000, None),  # fine at 5 kHz ...
])
def test_bad_filter_settings_are_refused_by_name(spec, needle):
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.12, **CLEAN)
    kw = dict(sample_rate_Hz=RATE, drop_height_m=0.2, filter_cfc=spec)
    if needle is None:
        assert cal.DropTest.from_arrays(t, ch, **kw).filters["stroke_m"] == 1000
        with pytest.raises(jl.ConfigError, match=f"above {min_rate_Hz(1000):g} Hz"):
            slow = {c: y[::3] for c, y in ch.items()}  # ... not at 1667 Hz
            cal.DropTest.from_arrays(t[::3], slow, sample_rate_Hz=RATE / 3, drop_height_m=0.2,
                                     filter_cfc=1000)
        return
    with pytest.raises(jl.ConfigError, match=needle):
        cal.DropTest.from_arrays(t, ch, **kw)
    with pytest.raises(jl.ConfigError, match="needs filter_cfc"):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 filter_data_prefiltered=True)


@pytest.mark.parametrize("spec,needle", [
    (0.5, "gain_uncertainty_rel = 0.5: must be a number in \\[0, 0.2\\]"),
    (-0.01, "must be a number in"),
    (True, "must be a number in"),
    ({"stroke_mm": 0.01}, "gain_uncertainty_rel.stroke_mm = 0.01: names no column"),
    ({"stroke_m": "1 %"}, "gain_uncertainty_rel.stroke_m = '1 %': must be a number"),
])
def test_bad_gain_uncertainties_are_refused_by_name(spec, needle):
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.12, **CLEAN)
    with pytest.raises(jl.ConfigError, match=needle):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 gain_uncertainty_rel=spec)


def test_a_gain_uncertainty_is_read_from_the_metadata(tmp_path):
    """``gain_uncertainty_rel`` in [drop_test]: one number for every channel, or a table by
    column (a zero is an exact gain); the drop's summary records it."""
    import shutil

    src = Path(cal.__file__).parents[1] / "data" / "synthetic"
    for name in ("drop_h0.20m.csv", "nominal_vehicle.toml"):
        shutil.copy(src / name, tmp_path / name)
    meta = (src / "drop_h0.20m.toml").read_text()
    for line, want in (("gain_uncertainty_rel = 0.004", dict.fromkeys(
            ("normal_force_N", "buffer_force_N", "stroke_m", "body_accel_mps2"), 0.004)),
            ("gain_uncertainty_rel = { stroke_m = 0.002, buffer_force_N = 0.0 }",
             {"stroke_m": 0.002})):
        (tmp_path / "drop_h0.20m.toml").write_text(
            meta.replace("[drop_test]\n", f"[drop_test]\n{line}\n", 1))
        d = cal.load_drop_test(tmp_path / "drop_h0.20m.toml")
        assert d.gain_uncertainty_rel == want
        assert d.summary()["gain_uncertainty_rel"] == want


# -------------------------------------------------------------------------- several legs

@pytest.fixture(scope="module")
def legs_drop():
    return vr.drop_test(0.2, duration_s=0.12, legs=(0, 1, 3), seed=2, crush_peak=0.0)


def test_several_legs_load_as_series_with_their_own_offsets(legs_drop):
    d = legs_drop
    assert set(d.channels) == {"body_accel_mps2", *(f"leg{i}_{c}" for i in (0, 1, 3) for c in
                                                   ("normal_force_N", "buffer_force_N",
                                                    "stroke_m"))}
    for i in (0, 1, 3):  # the rig's stroke offset grows with the leg index
        assert d.offsets[f"leg{i}_stroke_m"] == pytest.approx(
            vr.STROKE_OFFSET_M * (1 + 0.5 * i), abs=2e-5)
    assert d.summary()["legs"]["leg3_stroke_m"] == 3


def test_every_leg_is_compared_with_the_same_quarter_model(legs_drop):
    """At the truth every leg's residual is noise (weighted RMS ~1); with one leg's stroke
    shifted by 1 mm that series alone shows it."""
    prob = cal.CalibrationProblem([legs_drop], NAMES3, vehicle=TRUTH, window_s=0.03)
    th = prob.theta_from()
    rms = prob.channel_rms(th)[legs_drop.name]
    for c, v in rms.items():
        assert v < 1.6 * legs_drop.noise_std[c], (c, v)
    bad = cal.DropTest.from_arrays(
        legs_drop.time_s, {**legs_drop.channels,
                           "leg1_stroke_m": legs_drop.channels["leg1_stroke_m"]
                           + np.where(legs_drop.time_s > legs_drop.touchdown_time_s, 1e-3,
                                      0.0)}, sample_rate_Hz=RATE, drop_height_m=0.2)
    prob_b = cal.CalibrationProblem([bad], NAMES3, vehicle=TRUTH, window_s=0.03)
    rms_b = prob_b.channel_rms(th)[bad.name]
    assert rms_b["leg1_stroke_m"] > 10 * bad.noise_std["leg1_stroke_m"]
    assert rms_b["leg0_stroke_m"] < 1.6 * bad.noise_std["leg0_stroke_m"]
    metrics = cal.predict(TRUTH, legs_drop).metrics
    assert {"leg0_max_stroke_m", "leg3_peak_buffer_force_N", "peak_body_accel_mps2"} <= set(
        metrics)
    assert abs(metrics["leg3_max_stroke_m"]["rel_error"]) < 0.01


@pytest.mark.parametrize("cols,needle", [
    ({"leg4_stroke_m"}, "leg index must be in \\[0, 4\\)"),
    ({"leg1_body_accel_mps2"}, "takes no leg prefix"),
    ({"leg0_stroke_m", "stroke_m"}, "given twice: leg 0's stroke_m"),
    ({"leg2_stroke_mm", "leg2_stroke_m"}, "given twice"),
    ({"leg2_stroke_in"}, "unit suffix missing or wrong"),
])
def test_bad_leg_columns_are_refused_by_name(cols, needle):
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.12, **CLEAN)
    data = {"normal_force_N": ch["normal_force_N"]}
    for c in cols:
        data[c] = ch["stroke_m"]
    with pytest.raises(jl.ConfigError, match=needle):
        cal.DropTest.from_arrays(t, data, sample_rate_Hz=RATE, drop_height_m=0.2)


def test_leg_columns_in_lab_units_are_converted(tmp_path):
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.12, legs=(1, 2), **CLEAN)
    cols = {"time_s": t, "leg1_stroke_mm": ch["leg1_stroke_m"] * 1e3,
            "leg2_normal_force_kN": ch["leg2_normal_force_N"] * 1e-3}
    jl.atomic_write_csv(tmp_path / "lab.csv", cols, digits=12)
    (tmp_path / "lab.toml").write_text("[drop_test]\ndrop_height_m = 0.2\n"
                                       "sample_rate_Hz = 5000.0\n")
    d = cal.load_drop_test(tmp_path / "lab.toml")
    np.testing.assert_allclose(d.channels["leg1_stroke_m"], ch["leg1_stroke_m"], rtol=1e-10)
    assert d.unit_conversions["leg1_stroke_mm"] == "leg1_stroke_mm -> leg1_stroke_m (x 0.001)"


# ---------------------------------------------------- where the record starts, and when

def test_a_record_that_starts_at_touchdown_needs_its_time_and_keeps_the_sensor_zero():
    kw = dict(duration_s=0.12, pre_trigger_s=0.0, **CLEAN)
    t, ch, info = vr.record(TRUTH, 0.2, specific_force=True, **kw)
    assert info["touchdown_time_in_record_s"] == pytest.approx(0.0, abs=1e-5)
    with pytest.raises(jl.ConfigError, match="give drop_test.touchdown_time_s"):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2)
    with pytest.raises(jl.ConfigError, match="body_accel_kind.*too few to tell"):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 touchdown_time_s=0.0)
    with pytest.raises(jl.ConfigError, match="must be one of kinematic, specific_force"):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 touchdown_time_s=0.0, body_accel_kind="g")
    with pytest.raises(jl.ConfigError, match="touchdown_time_s.*must lie in the record"):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 touchdown_time_s=-0.01, body_accel_kind="specific_force")
    d = cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 touchdown_time_s=0.0, body_accel_kind="specific_force")
    assert d.touchdown_time_s == 0.0 and d.offset_source.startswith("none")
    assert all(v == 0.0 for v in d.offsets.values())
    # the specific force is read as the kinematic acceleration: -g at touchdown
    assert d.corrected["body_accel_mps2"][0] == pytest.approx(-float(TRUTH.g), abs=0.5)
    assert "specific force -> kinematic" in " ".join(d.unit_conversions.values())
    prob = cal.CalibrationProblem([d], NAMES3, vehicle=TRUTH, window_s=0.03)
    rms = prob.channel_rms(prob.theta_from())[d.name]
    assert rms["stroke_m"] < 0.01 * float(np.max(ch["stroke_m"]))


def test_a_record_from_mid_fall_on_a_time_axis_from_release():
    """The record starts 60 ms before touchdown, its time counts from release: touchdown is
    found at the free-fall time, and the drop height is checked against it."""
    t, ch, info = vr.record(TRUTH, 0.2, duration_s=0.2, pre_trigger_s=0.06,
                            time_from_release=True, seed=4)
    assert t[0] > 0.1 and info["release_time_in_record_s"] == 0.0
    d = cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 release_time_s=0.0)
    t_ff = math.sqrt(2 * 0.2 / float(TRUTH.g))
    assert d.touchdown_time_s == pytest.approx(t_ff, abs=2e-4)
    assert d.free_fall["implied_drop_height_m"] == pytest.approx(0.2, rel=3e-3)
    assert d.offsets["stroke_m"] == pytest.approx(vr.STROKE_OFFSET_M, abs=2e-5)


@pytest.mark.parametrize("meta,needle", [
    (dict(drop_height_m=0.3, release_time_s=0.0),
     "drop_height_m = 0.3: contradicts the record's free fall.*mean a drop of 0.2"),
    (dict(drop_height_m=0.2, release_time_s=0.05),  # 50 ms late: 0.2 m fall is 202 ms
     "drop_height_m = 0.2: contradicts the record's free fall"),
    (dict(drop_height_m=0.2, release_time_s=0.5), "release_time_s = 0.5: must precede"),
    (dict(touchdown_speed_mps=2.0, release_time_s=0.0), "release_time_s.*needs drop_height_m"),
    (dict(drop_height_m=0.2, release_time_s="0"), "release_time_s.*must be a finite number"),
])
def test_a_drop_height_that_contradicts_the_free_fall_is_refused(meta, needle):
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.2, pre_trigger_s=0.06,
                         time_from_release=True, seed=4)
    with pytest.raises(jl.ConfigError, match=needle):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, **meta)


def test_the_cli_refuses_a_contradicting_drop_height_with_exit_2_and_one_line(tmp_path,
                                                                              capsys):
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.2, pre_trigger_s=0.06,
                         time_from_release=True, seed=4)
    jl.atomic_write_csv(tmp_path / "d.csv", {"time_s": t, **ch}, digits=9)
    (tmp_path / "d.toml").write_text("[drop_test]\ndrop_height_m = 0.25\nrelease_time_s = 0.0\n"
                                     "sample_rate_Hz = 5000.0\n")
    assert main(["fit", str(tmp_path / "d.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "d.toml: drop_test.drop_height_m = 0.25" in err[0], err
    assert "contradicts the record's free fall" in err[0]


def _wrong(ch, col, how):
    out = dict(ch)
    out[col] = how(ch[col])
    return out


@pytest.mark.parametrize("how,needle", [
    (lambda ch: _wrong(ch, "stroke_m", lambda x: x * 1e3),
     r"stroke_m = '\d\d\.\d+ m': exceeds the strut's length.*in mm"),
    (lambda ch: _wrong(ch, "stroke_m", lambda x: -x), r"stroke_m = '-0\.0\d+ m': runs negative"),
    # inches under an _m header: under the strut's length, but far past the crush length
    (lambda ch: _wrong(ch, "stroke_m", lambda x: x / 0.0254),
     r"stroke_m = '\d\.\d+ m': exceeds 2 x the honeycomb's crush length .* in inches"),
    # tenths of a mm under a stroke_mm header: converted, ten times too long
    (lambda ch: {**{k: v for k, v in ch.items() if k != "stroke_m"},
                 "stroke_mm": ch["stroke_m"] * 1e4},
     r"stroke_mm = '\d+\.?\d* mm': exceeds 2 x .* in tenths of a mm or in um under a "
     r"stroke_mm header"),
    (lambda ch: _wrong(ch, "normal_force_N", lambda x: x * 1e-3),
     "normal_force_N = 'peak .*under a tenth of the .* N the leg carries at rest.*kN"),
    (lambda ch: _wrong(ch, "buffer_force_N", lambda x: -x), "buffer_force_N.*sign flipped"),
    (lambda ch: _wrong(ch, "stroke_m", lambda x: np.full_like(x, 1.5e-3)),
     "stroke_m = '0.0015 throughout': is constant over the whole record"),
    (lambda ch: _wrong(ch, "body_accel_mps2", lambda x: np.full_like(x, -9.81)),
     "body_accel_mps2 = '-9.81 throughout': is constant"),  # fit and predict divided by 0

    (lambda ch: _wrong(ch, "body_accel_mps2", lambda x: x / 9.80665),
     r"body_accel_mps2 = 'swing \d\.\d+ m/s\^2': must be at least 0\.25 of .* is 0\.1\d "
     r"of it: an acceleration in g"),
    (lambda ch: _wrong(ch, "body_accel_mps2", lambda x: x * 1e3),
     r"body_accel_mps2 = 'swing [\d.e+]+ m/s\^2': must be at most 10 x .* is [\d.e+]+ x it: an "
     r"acceleration in mm/s\^2"),
    # a flipped sign swings as far: it runs against the forces (it was read without a word)
    (lambda ch: _wrong(ch, "body_accel_mps2", lambda x: -x),
     r"body_accel_mps2 = 'correlation -0\.\d+': with the force channels .* sign flipped"),
    # m/s^2 under a g header: converted, 9.81 times too large, under the 10 x of a mm/s^2
    (lambda ch: {**{k: v for k, v in ch.items() if k != "body_accel_mps2"},
                 "body_accel_g": ch["body_accel_mps2"]},
     r"body_accel_g = 'swing [\d.e+]+ m/s\^2': must be at most 4 x .* values in m/s\^2 under "
     r"a g header"),
])
def test_a_wrong_unit_or_sign_is_refused_by_name(how, needle):
    """What no drop of this vehicle records: a stroke beyond the strut's length, one that runs
    negative through the impact, a force that never reaches a tenth of the leg's weight, a
    body acceleration that swings a tenth as far as the forces say (g under an m/s^2 header)
    or a thousand times as far (mm/s^2; predict compared it, 99.9 % off)."""
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.2, seed=4)
    cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2)  # as recorded
    with pytest.raises(jl.ConfigError, match=needle):
        cal.DropTest.from_arrays(t, how(ch), sample_rate_Hz=RATE, drop_height_m=0.2)


def test_a_glitch_in_a_force_channel_does_not_refuse_the_acceleration():
    """The acceleration's check compares swings of a running median: one sample of the only
    force channel at 20 times its peak leaves a record in m/s^2 accepted."""
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.2, seed=4, channels=("normal_force_N",
                                                                       "body_accel_mps2"))
    f = ch["normal_force_N"].copy()
    f[int(np.argmax(f)) + 40] = 20.0 * f.max()
    cal.DropTest.from_arrays(t, dict(ch, normal_force_N=f), sample_rate_Hz=RATE,
                             drop_height_m=0.2)


def test_a_touchdown_time_after_the_impact_began_is_refused():
    """A given touchdown time sets the free fall the offsets come from: one inside the impact
    would subtract the impact itself. Refused; the true time and one a little early load."""
    t, ch, info = vr.record(TRUTH, 0.2, duration_s=0.2, seed=4)
    t0 = info["touchdown_time_in_record_s"]
    for ok in (t0, t0 - 0.005):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 touchdown_time_s=ok)
    with pytest.raises(jl.ConfigError, match="touchdown_time_s = .*after the impact has begun"):
        cal.DropTest.from_arrays(t, ch, sample_rate_Hz=RATE, drop_height_m=0.2,
                                 touchdown_time_s=t0 + 0.02)


def test_the_cli_refuses_a_drop_given_twice_a_folder_and_bad_fit_flags(tmp_path, capsys):
    """Each with exit 2 and one line, before any fit: a drop given as its TOML and its CSV
    (it would count twice), two drops of one name in predict (one output file each), a folder
    as DATA, flags outside their range (0 means off; below it is refused), and settings the
    fit itself refuses (a step beyond the stability limit, windows out of order, a peak form
    without the peak), without the fit's banner before the error."""
    t, ch, _ = vr.record(TRUTH, 0.2, duration_s=0.2, seed=4)
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        jl.atomic_write_csv(tmp_path / sub / "d.csv", {"time_s": t, **ch}, digits=9)
        (tmp_path / sub / "d.toml").write_text("[drop_test]\ndrop_height_m = 0.2\n"
                                               "sample_rate_Hz = 5000.0\n")
    a, b = str(tmp_path / "a" / "d.toml"), str(tmp_path / "b" / "d.toml")
    cfg = str(tmp_path / "v.toml")
    (tmp_path / "v.toml").write_text(jl.vehicle_to_toml(TRUTH))
    cases = [
        (["fit", a, a.replace(".toml", ".csv")], "are both drop test 'd'"),
        (["predict", "--config", cfg, a, b], "are both drop test 'd'"),
        (["fit", str(tmp_path / "a")], "is a folder"),
        (["fit", a, "--robust", "-1"], "--robust = -1.0: must be a finite number >= 0"),
        (["fit", a, "--refine-window-s", "nan"], "--refine-window-s = nan"),
        (["fit", a, "--max-iter", "0"], "--max-iter = 0: must be at least 1"),
        (["fit", a, "--start", "k=abc"], "--start k = 'abc'"),
        # refused inside the fit's own checks (check_fit), still before its banner
        (["fit", a, "--dt", "1e-3"], "dt = 0.001: must be in (0, "),
        (["fit", a, "--windows", "0.03,0.01"], "--windows = '0.03,0.01': must be increasing"),
        (["fit", a, "--peak-form", "exp"], "--peak-form = 'exp': needs peak1"),
    ]
    for argv, needle in cases:
        out = tmp_path / "out"
        assert main([*argv, "--out", str(out)]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], (argv, err)
        assert not out.exists()


def test_the_bundled_lab_record_loads_with_every_conversion_logged():
    """data/synthetic/drop_h0.20m_lab: four legs in kN and mm, time in ms, the body channel in
    g of specific force, a time axis from release, delivered CFC 600 filtered (SYNTHETIC)."""
    import tomllib
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "data" / "synthetic" / "drop_h0.20m_lab.toml"
    meta = tomllib.loads(path.read_text())
    assert path.with_suffix(".csv").read_text().startswith("# SYNTHETIC")
    d = cal.load_drop_test(path)
    assert d.synthetic and d.filters["leg3_stroke_m"] == 600 and d.filter_data_prefiltered
    assert {leg for leg in d.summary()["legs"].values()} == {0, 1, 2, 3}
    assert d.unit_conversions["time_ms"] == "time_ms -> time_s (x 0.001)"
    assert d.unit_conversions["leg2_buffer_force_kN"].endswith("leg2_buffer_force_N (x 1000)")
    t_true = meta["synthetic_rig"]["touchdown_time_in_record_s"]
    assert abs(d.touchdown_time_s - t_true) < 3e-4  # the zero-phase filter's smeared onset
    assert d.free_fall["implied_drop_height_m"] == pytest.approx(0.2, rel=0.01)
    for i in range(4):
        assert d.offsets[f"leg{i}_stroke_m"] == pytest.approx(
            vr.STROKE_OFFSET_M * (1 + 0.5 * i), abs=2e-5)
    # specific force in g -> kinematic: -g in free fall after the (zero) offset
    pre = d.time_s < d.touchdown_time_s - 0.01
    assert np.mean(d.corrected["body_accel_mps2"][pre]) == pytest.approx(-float(TRUTH.g),
                                                                         abs=0.05)
