"""Where the fitted crush peak sits (``fit(peak_site=...)``): in the honeycomb (the law's: its
crush work moves the stroke and the body) or on the force channels alone (the drop runs
without it, the force channels carry it as a gain of the crush so far).

A record whose peak sits on the force channels only (the virtual rig's sensor mode, a bump of
the crush) is fitted both ways on one module-scoped pair of fits (short windows, no
peak-shape term).
"""

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import calibration as cal
import jaxland as jl
from calibration import _fit as cal_fit, virtual_rig as vr
from calibration._optim import levenberg_marquardt
from calibration._parameters import FORM_INDEX, PEAK_FORMS, forms_vehicle, get_values, set_values
from calibration._problem import CalibrationProblem, force_channel_gain
from calibration.cli import add_subcommands, peak_site_line

PARAMS = cal.DEFAULT_PARAMS + ("peak1", "L_peak1")
KW = dict(windows=(0.01, 0.03), refine_window_s=0.1, model_form=False)
CHECKED = ("k", "gamma", "D_b", "k_b1", "F1")


@pytest.fixture(scope="module")
def sensor_fits():
    drop = vr.drop_test(0.2, seed=5, peak_mode="sensor")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # on the forces, the law's peak built up (L_rise1): a gain that starts at 1 and
        # peaks after some crush, as the rig's sensor-side bump does
        return dict(honeycomb=cal.fit(drop, PARAMS, **KW),
                    forces=cal.fit(drop, PARAMS + ("L_rise1",), peak_site="forces", **KW))


def test_the_gain_follows_the_peak_over_the_crush_and_is_one_past_it():
    """The gain of the crush p (closed forms): 1 before the crush (p = 0); the law's linear
    peak (ratio r over length L) jumps to r as the crush starts and falls to 1 at p = L;
    built up over L_r, it starts at 1, reaches r at p = L_r and falls to 1 at L_r + L; 1 from
    there on."""
    r, length, rise = 1.3, 1.5e-3, 0.5e-3
    veh = set_values(jl.paper_vehicle(), ("peak1", "L_peak1"), [r, length])
    ps = np.array([0.0, 1e-12, 0.25 * length, length, 2.0 * length, 0.1])
    got = np.asarray(force_channel_gain(veh, jnp.asarray(ps)))
    np.testing.assert_allclose(got, [1.0, r, r - 0.25 * (r - 1.0), 1.0, 1.0, 1.0], rtol=1e-9)
    built = set_values(veh, ("L_rise1",), [rise])
    ps = np.array([0.0, 0.5 * rise, rise, rise + 0.5 * length, rise + length, 0.1])
    got = np.asarray(force_channel_gain(built, jnp.asarray(ps)))
    np.testing.assert_allclose(got, [1.0, 0.5 * (1.0 + r), r, 0.5 * (1.0 + r), 1.0, 1.0],
                               rtol=1e-12)
    # differentiable in the peak's parameters, finite everywhere
    g = jax.grad(lambda p: jnp.sum(force_channel_gain(
        set_values(built, ("peak1", "L_peak1", "L_rise1"), p), jnp.asarray(ps))))(
        jnp.array([r, length, rise]))
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0.0)


def test_the_gain_reads_every_peak_form_as_its_table_does():
    """The gain of a tabulated peak (every one of calibration's forms) read at the one segment
    that holds the crush (the table's node values) equals the table's sum over every segment,
    over the whole crush and past the peak's end."""
    veh = set_values(jl.paper_vehicle(), ("peak1", "L_peak1", "L_rise1"), [1.3, 1.5e-3, 0.6e-3])
    ps = jnp.linspace(0.0, 1e-2, 2001)
    for form in PEAK_FORMS:
        formed = forms_vehicle(veh, FORM_INDEX[form])
        curve = formed.honeycomb.curve()
        assert curve.t1_e is not None, form
        summed = eqx.tree_at(lambda c: (c.t1_e, c.t1_int), curve, (None, None),
                             is_leaf=lambda x: x is None)
        got = np.asarray(jl.laws.primary_peak_excess(ps, curve))
        want = np.asarray(jl.laws.primary_peak_excess(ps, summed))
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9 * float(curve.F1),
                                   err_msg=form)
        assert np.ptp(want) > 0.01 * float(curve.F1), form  # a peak to read


def test_a_peak_on_the_force_channels_moves_no_motion_channel():
    """The site "forces" model: stroke and body acceleration are the drop's without the peak,
    bit for bit; the force channels are that drop's times the gain: 1 before the crush, up to
    the peak ratio as it starts (the law's linear peak) and 1 once the peak has decayed."""
    r = 1.25
    plain = vr.truth_vehicle()
    peaked = set_values(plain, ("peak1", "L_peak1"), [r, 1.5e-3])
    drop = vr.drop_test(0.2, seed=1, peak_mode="sensor")
    forces = CalibrationProblem([drop], PARAMS, vehicle=peaked, peak_site="forces")
    none = CalibrationProblem([drop], cal.DEFAULT_PARAMS, vehicle=plain)

    def model(prob):
        res, failed = prob.robust(None).residuals(prob.theta_from())
        assert not failed
        return prob.data + res.reshape(prob.data.shape) / prob.inv_sigma[:, :, None]

    m_f, m_0 = model(forces), model(none)
    assert forces.channels == none.channels
    for j, c in enumerate(forces.channels):
        on = forces.mask[0, j] > 0
        if c in ("stroke_m", "body_accel_mps2"):
            np.testing.assert_array_equal(m_f[0, j, on], m_0[0, j, on])
            continue
        big = np.abs(m_0[0, j, on]) > 1e3
        ratio = m_f[0, j, on][big] / m_0[0, j, on][big]
        assert 1.0 + 0.8 * (r - 1.0) < ratio.max() <= r + 1e-12, (c, ratio.max())
        assert ratio.min() == pytest.approx(1.0, abs=1e-12)


def test_a_sensor_side_peak_fitted_on_the_forces_recovers_the_honeycomb(sensor_fits):
    """A record whose peak sits on the force channels only: fitted in the honeycomb, the
    residuals show the wrong site (smooth: a misfit, and a larger variance factor); fitted on
    the forces, every checked value lies within 3 % of the truth and the residuals fit the
    noise."""
    p_true = get_values(vr.truth_vehicle(), CHECKED)

    def err(res):
        return np.array([res.value(n) for n in CHECKED]) / p_true - 1.0

    honeycomb, forces = sensor_fits["honeycomb"], sensor_fits["forces"]
    assert np.max(np.abs(err(forces))) < 0.03, err(forces)
    assert forces.sigma2 < 1.1 < honeycomb.sigma2
    assert not forces.diagnostics["misfit"] and honeycomb.diagnostics["misfit"]


def test_a_fit_on_the_forces_says_so_and_its_vehicle_has_no_peak(sensor_fits, tmp_path):
    res = sensor_fits["forces"]
    assert res.settings["peak_site"] == "forces"
    assert res.diagnostics["peak_location"] is None  # the peak sits on the forces already
    path = tmp_path / "fitted_vehicle.toml"
    path.write_text(res.to_toml())
    for veh in (res.vehicle, jl.load_vehicle(path)):
        hc = veh.honeycomb
        assert hc.peak_ratio1 is None and hc.excess1 is None and hc.peak_rise1 is None
        assert float(hc.k_b1) == pytest.approx(res.value("k_b1"), rel=1e-6)
    assert res.report()["settings"]["peak_site"] == "forces"
    check = res.diagnostics["peak_site_check"]  # the drop without the peak follows the motion
    assert not check["misfit"] and check["variance_factor"] < 1.1, check
    assert check["channels"] == ["stroke_m", "body_accel_mps2"]
    assert sensor_fits["honeycomb"].diagnostics["peak_site_check"] is None
    # the honeycomb fit names the force channels and says how to fit them
    loc = sensor_fits["honeycomb"].diagnostics["peak_location"]
    assert loc["force_only"]


def test_the_forces_refits_stop_once_the_loss_stops_moving():
    """``levenberg_marquardt(atol=)``: an accepted step that lowers the loss by less than
    atol ends the fit, where the relative test alone goes on."""

    class Quadratic:  # r = 10 (theta - 1): two capped steps, then one within the damping
        def residuals_and_jacobian(self, theta):
            return 10.0 * (np.asarray(theta) - 1.0), np.eye(1) * 10.0, False

        def residuals(self, theta):
            return 10.0 * (np.asarray(theta) - 1.0), False

        def values(self, theta):
            return np.asarray(theta)

    _, hist_abs, st = levenberg_marquardt(Quadratic(), np.zeros(1), atol=1.0)
    _, hist_rel, _ = levenberg_marquardt(Quadratic(), np.zeros(1))
    assert st["status"] == "converged" and len(hist_abs) == 3 < len(hist_rel)
    assert math.isclose(hist_abs[-1]["values"][0], 1.0, abs_tol=1e-5)


def test_a_bad_peak_site_is_refused_by_name(capsys, tmp_path):
    drop = vr.drop_test(0.2, seed=1)
    for site, params, rule in (("soil", PARAMS, "must be one of honeycomb, forces"),
                               ("forces", cal.DEFAULT_PARAMS, "needs peak1")):
        with pytest.raises(jl.ConfigError, match=rule) as err:
            cal_fit.check_fit(drop, params, peak_site=site)
        assert err.value.field == "peak_site"
    from jaxland.cli import main

    toml, _ = vr.write_drop_test(tmp_path, 0.2, seed=1)
    vr.write_nominal(tmp_path)
    assert main(["fit", str(toml), "--params", ",".join(PARAMS), "--peak-site", "forces",
                 "--compare-models", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--peak-site = 'forces'" in err[0], err
    import argparse

    sub = argparse.ArgumentParser().add_subparsers()
    add_subcommands(sub)
    fit_parser = sub.choices["fit"]
    assert fit_parser.parse_args(["x.toml"]).peak_site == "honeycomb"


def test_a_peak_on_the_forces_is_bound_by_the_plateaus_room_only():
    """The honeycomb's rules for a peak in its dynamics (the falling slope (r - 1) F1 / L at
    most k / 2) do not bind a gain on the force channels: L_peak1 may go far below that
    slope's bound there, while the decay still ends in the plateau's room; every form's
    L_rise1 interval stays open at L_peak1's extremes."""
    from calibration._parameters import GAIN_MIN_LENGTH, PEAK_FORMS, RISE_FORMS, _span, interval

    names = PARAMS + ("L_rise1",)
    veh = set_values(vr.truth_vehicle(), ("peak1", "L_peak1", "L_rise1"), [1.2, 1e-3, 2e-4])
    vals = get_values(veh, names)
    hc, k = veh.honeycomb, float(veh.ground.k)
    room = float(hc.x_L2 - hc.F1 / hc.k_b1)
    slope_lo = 2.0 * 0.2 * float(hc.F1) / k
    for form in PEAK_FORMS:
        lo_h, _ = interval("L_peak1", names, vals, veh, form)
        lo_f, hi_f = interval("L_peak1", names, vals, veh, form, "forces")
        assert lo_h >= slope_lo and lo_f == pytest.approx(GAIN_MIN_LENGTH * room, rel=1e-6)
        assert lo_f < 0.1 * slope_lo and float(_span(form)) * hi_f < room
        if form in RISE_FORMS:
            for lp in (lo_f * 1.000001, hi_f * 0.999999):
                v = vals.copy()
                v[names.index("L_peak1")] = lp
                lo_r, hi_r = interval("L_rise1", names, v, veh, form, "forces")
                assert 0.0 < lo_r < hi_r, (form, lp, lo_r, hi_r)
    assert interval("peak1", names, vals, veh, "exp", "forces")[1] == pytest.approx(
        float(hc.F2 / hc.F1), rel=1e-6)


def test_a_honeycombs_peak_fitted_on_the_forces_is_named_by_the_motion():
    """The wrong site: a record whose peak is the honeycomb's (crush work in the stroke and the
    body acceleration) fitted with the peak on the force channels. The drop without the peak
    cannot follow the motion, the motion channels' variance factor exceeds the misfit test's,
    and the fit warns by name."""
    drop = vr.drop_test(0.2, seed=5, peak_mode="physical")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = cal.fit(drop, PARAMS, peak_site="forces", **KW)
    check = res.diagnostics["peak_site_check"]
    assert check["misfit"] and check["variance_factor"] > 1.3, check
    assert any(issubclass(w.category, cal.MisfitWarning) and "the motion misfits" in str(
        w.message) for w in caught)
    assert "THE MOTION MISFITS" in peak_site_line(check)
    assert peak_site_line(dict(check, misfit=False, variance_factor=1.01)).endswith(
        "the motion fits without it (variance factor 1.01)")
    assert peak_site_line(None).endswith("no motion channel to check it against")
