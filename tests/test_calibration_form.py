"""The peak-shape (model-form) term of the uncertainty: a fit with the crush peak is
refitted in the peak's other forms, and the largest shift among the forms the data support
widens the total standard error.

Two fits share the compiled functions (module scope, short windows): a drop whose truth has
the law's own linear peak (the data are representable: the term must stay small) and the
rig's physical bump, a peak that builds up (the law's linear peak mis-shapes it: the term
must widen k_b1's interval to the built-up form's estimate).
"""

import argparse
import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import calibration as cal
import jaxland as jl
from calibration import _fit as cal_fit, virtual_rig as vr
from calibration._parameters import (
    BOUND_MARGIN,
    EXP_POINTS,
    EXP_SPAN,
    FORM_INDEX,
    PEAK_FORMS,
    RIPPLE_NODES,
    RIPPLE_SPAN,
    RISE_FORMS,
    SHAPE_PARAMS,
    SMOOTH_RISE_MAX,
    at_bound,
    forms_vehicle,
    from_unconstrained,
    get_values,
    interval,
    peak_form_vehicle,
    ripple_table,
    set_values,
    switch_on,
    to_unconstrained,
)
from calibration._problem import CalibrationProblem
from calibration.cli import add_subcommands, form_caveat, peak_location_line
from jaxland import laws

PARAMS = cal.DEFAULT_PARAMS + ("peak1", "L_peak1")
KW = dict(windows=(0.01, 0.03), refine_window_s=0.1)


@pytest.fixture(scope="module")
def form_fits():
    law = set_values(vr.truth_vehicle(), ("peak1", "L_peak1"), np.array([1.1, 1e-3]))
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out["law's peak"] = cal.fit(vr.drop_test(0.2, seed=5, crush_peak=0.0, vehicle=law),
                                    PARAMS, **KW)
        out["bump"] = cal.fit(vr.drop_test(0.2, seed=5, peak_mode="physical"), PARAMS, **KW)
        out["folds"] = cal.fit(vr.drop_test(0.2, seed=5, peak_mode="physical",
                                            peak_shape="folds"), PARAMS, **KW)
    return out


def _trusted(res):
    return res.std_errors_hac if res.diagnostics["trust"] == "std_error_hac" else \
        res.std_errors


def _channel_spread(res):
    shifts = [v for v in res.diagnostics["channel_spread"].values() if v is not None]
    if not shifts:
        return np.zeros(len(res.names))
    return np.max([[abs(s[n]) for n in res.names] for s in shifts], axis=0)


def test_the_peak_shape_term_is_added_to_the_total_error(form_fits):
    for res in form_fits.values():
        mf = res.diagnostics["model_form"]
        assert mf is not None and res.diagnostics["interval"] == "std_error_total"
        term = np.array([mf["spread"][n] for n in res.names])
        expect = np.sqrt(_trusted(res) ** 2 + _channel_spread(res) ** 2 + term ** 2)
        np.testing.assert_allclose(res.std_errors_total, expect, rtol=1e-12)
        # the term is the largest shift over the plausible forms, none from the others,
        # and none on the peak's own parameters (their meaning differs between forms)
        plausible = [f for f in mf["forms"].values() if f is not None and f["plausible"]]
        largest = np.max([[abs(f["shift"][n]) for n in res.names] for f in plausible], axis=0)
        np.testing.assert_allclose(term, largest, rtol=0, atol=0)
        assert all(term[res.names.index(n)] == 0.0 for n in SHAPE_PARAMS if n in res.names)


def test_the_term_stays_small_where_the_laws_peak_is_the_truth(form_fits):
    res = form_fits["law's peak"]
    mf = res.diagnostics["model_form"]
    assert mf["form"] == "linear" and not mf["failed"]
    assert mf["best_supported"] == "linear"  # the form that generated the record is named
    term = np.array([mf["spread"][n] for n in cal.DEFAULT_PARAMS])
    # every form that fits this record as well moves the values by less than their scatter
    assert np.all(term <= 1.0 * _trusted(res)[:len(cal.DEFAULT_PARAMS)])


def _scored(forms: dict, n: int, c: float) -> dict:
    """``model_form_spread``'s scores of forms given as (chi^2, fitted parameters)."""
    out = {k: None if f is None else dict(chi2=f[0], n_params=f[1]) for k, f in forms.items()}
    done = [f for f in out.values() if f is not None]
    for f in done:
        f["aic"] = f["chi2"] + 2 * f["n_params"]
    least = min(f["aic"] for f in done)
    for f in done:
        f["daic_adjusted"] = (f["aic"] - least) / c
        f["plausible"] = f["daic_adjusted"] <= cal_fit.DAIC_PLAUSIBLE
        f["bic_adjusted"] = f["chi2"] / c + f["n_params"] * np.log(n)
    return out


def test_the_named_form_is_the_plausible_one_of_least_adjusted_bic():
    """A built-up form containing the plain one (one more parameter) and 6.1 lower in chi^2
    (the rig's exponential peak, seed 3003, where the plain exponential form is the truth):
    AIC would name the built-up form, BIC (ln 3100 = 8.0 per parameter) names the plain one. A
    form of less BIC that the adjusted AIC rejects is never named; where correlated residuals
    inflate chi^2 differences 4-fold, a built-up form 20 lower is not named either."""
    n = 3100
    forms = _scored({"exp": (3057.84, 9), "rise_exp": (3051.73, 10), "linear": (3100.0, 3),
                     "smooth_exp": None}, n, 1.0)
    assert forms["rise_exp"]["aic"] < forms["exp"]["aic"]
    assert forms["linear"]["bic_adjusted"] < forms["exp"]["bic_adjusted"]
    assert not forms["linear"]["plausible"]
    assert cal_fit.best_supported_form(forms) == "exp"
    inflated = {"exp": (3057.84, 9), "rise_exp": (3037.84, 10)}
    assert cal_fit.best_supported_form(_scored(inflated, n, 1.0)) == "rise_exp"
    assert cal_fit.best_supported_form(_scored(inflated, n, 4.0)) == "exp"


def test_the_term_widens_k_b1_to_the_better_form_on_a_mis_shaped_peak(form_fits):
    res = form_fits["bump"]
    mf = res.diagnostics["model_form"]
    i = res.names.index("k_b1")
    # a peak that builds up fits the bump far better than the linear fall
    assert mf["best_supported"] in ("rise", "rise_exp", "smooth_exp")
    assert mf["best_supported"] in mf["plausible"]
    assert mf["forms"]["linear"]["daic_adjusted"] > cal_fit.DAIC_PLAUSIBLE
    term = mf["spread"]["k_b1"]
    assert term > 2.0 * _trusted(res)[i]  # the shape moves k_b1 beyond its scatter
    assert res.std_errors_total[i] > 2.0 * _trusted(res)[i]
    # ... and the widened interval reaches the truth, which the trusted one misses
    truth = get_values(vr.truth_vehicle(), ("k_b1",))[0]
    assert abs(res.values[i] - truth) > 1.96 * _trusted(res)[i]
    assert abs(res.values[i] - truth) <= 1.96 * res.std_errors_total[i]
    # a refitted form the data reject does not widen anything (the exp form moves k, gamma
    # and D_b further than the term)
    rejected = [f for f in mf["forms"].values()
                if f is not None and f["refit"] and not f["plausible"]]
    assert any(any(abs(f["shift"][n]) > mf["spread"][n] for n in res.names)
               for f in rejected)


def test_the_exp_form_is_an_exponential_peak_of_the_same_height_and_slope():
    veh = set_values(vr.truth_vehicle(), ("peak1", "L_peak1"), np.array([1.2, 1.5e-3]))
    hc = peak_form_vehicle(veh, "exp").honeycomb
    assert hc.peak_ratio1 is None and hc.peak_rise1 is None
    table, length = np.asarray(hc.excess1), float(hc.excess_length1)
    assert table.shape == (EXP_POINTS,) and length == pytest.approx(EXP_SPAN * 1.5e-3)
    c = np.arange(EXP_POINTS) * length / EXP_POINTS  # the table's nodes [m]
    np.testing.assert_allclose(table, 0.2 * np.exp(-c / 1.5e-3), rtol=1e-12)
    # the linear form takes a built-up peak's rise off; the rise form keeps it
    risen = set_values(veh, ("L_rise1",), [1e-3])
    assert peak_form_vehicle(risen, "linear").honeycomb.peak_rise1 is None
    assert float(peak_form_vehicle(risen, "rise").honeycomb.peak_rise1) == 1e-3


def _top(r):
    """max over x of (1 - exp(-x / r)) exp(-x), on a dense grid (not the closed form)."""
    x = np.linspace(0.0, 3.0 * r * np.log(1.0 + 1.0 / r) + 1e-3, 2_000_001)
    return float(np.max(-np.expm1(-x / r) * np.exp(-x)))


def test_the_smooth_form_builds_up_from_zero_to_its_height():
    """``smooth_exp``: the excess (peak1 - 1) (1 - exp(-c / L_rise1)) exp(-c / L_peak1),
    scaled to its top, tabulated over EXP_SPAN L_peak1 (its build-up inside the table, the
    rise switched off); the vehicle validates; without a rise it is refused by name."""
    veh = set_values(vr.truth_vehicle(), ("peak1", "L_peak1", "L_rise1"),
                     np.array([1.2, 1.5e-3, 1.0e-3]))
    hc = peak_form_vehicle(veh, "smooth_exp").honeycomb
    assert hc.peak_ratio1 is None and hc.peak_rise1 is None
    table, length = np.asarray(hc.excess1), float(hc.excess_length1)
    assert table.shape == (EXP_POINTS,) and length == pytest.approx(EXP_SPAN * 1.5e-3)
    c = np.arange(EXP_POINTS) * length / EXP_POINTS
    expect = 0.2 * -np.expm1(-c / 1.0e-3) * np.exp(-c / 1.5e-3) / _top(1.0 / 1.5)
    np.testing.assert_allclose(table, expect, rtol=1e-10, atol=0)
    assert table[0] == 0.0 and 0.199 < table.max() <= 0.2
    jl.validate_vehicle(peak_form_vehicle(veh, "smooth_exp"))
    with pytest.raises(jl.ConfigError, match="peak_rise1_mm"):
        peak_form_vehicle(set_values(vr.truth_vehicle(), ("peak1", "L_peak1"),
                                     np.array([1.2, 1.5e-3])), "smooth_exp")


def test_the_smooth_forms_build_up_stays_below_k_b1():
    """The smooth form's steepest build-up, at its onset, is (peak1 - 1) F1 / (L_rise1
    top(L_rise1 / L_peak1)): L_rise1's lower bound keeps it below k_b1 (within e of it: the
    bound uses top >= 1 / (e (1 + r))), its upper bound is SMOOTH_RISE_MAX L_peak1, and
    L_peak1's lower bound leaves that interval open where the ground is stiff (2 e a / k_b1
    above the falling slope's 2 a / k). Coordinates run onto either bound give vehicles the
    table's rules accept, in the form's own functions and the shared ones alike."""
    names = PARAMS + ("L_rise1",)
    drop = vr.drop_test(0.2, seed=5, crush_peak=0.0)
    veh = switch_on(set_values(drop.vehicle, ("L_rise1",), [1e-3]), names)
    vals = get_values(veh, names)
    a = (vals[names.index("peak1")] - 1.0) * vals[names.index("F1")]
    k_b1, L = vals[names.index("k_b1")], vals[names.index("L_peak1")]
    lo, hi = interval("L_rise1", names, vals, veh, "smooth_exp")
    steepest = a / (lo * _top(lo / L))
    assert k_b1 / np.e < steepest < k_b1
    assert hi == pytest.approx(SMOOTH_RISE_MAX * L, rel=1e-8)
    assert lo < interval("L_rise1", names, vals, veh, "rise")[0] * np.e * 2
    stiff = set_values(veh, ("k",), [20.0 * k_b1])
    v_s = get_values(stiff, names)
    lo_exp = interval("L_peak1", names, v_s, stiff, "exp")[0]
    lo_smooth = interval("L_peak1", names, v_s, stiff, "smooth_exp")[0]
    assert lo_exp < lo_smooth == pytest.approx(2.0 * np.e * a / k_b1 * (1 + BOUND_MARGIN))

    kw = dict(window_s=0.03, pre_s=cal_fit.PRE_S)
    j = names.index("L_rise1")
    for shared in (False, True):
        prob = CalibrationProblem([drop], names, vehicle=veh, peak_form="smooth_exp",
                                  shared_forms=shared, **kw)
        for z, bound in ((-40.0, lo), (40.0, hi)):
            theta = prob.theta_from(veh, [0.0])
            theta[j] = z
            assert prob.values(theta)[j] == pytest.approx(bound, rel=1e-9)
            hc = prob.vehicle_at(theta).honeycomb  # validated
            assert hc.peak_rise1 is None and hc.excess1.shape == (EXP_POINTS,)
            r, failed = prob.residuals(theta)
            assert not failed and np.all(np.isfinite(r))


def test_the_smooth_forms_bounds_stay_open_and_differentiable_on_stiff_ground():
    """Where the ground is much stiffer than k_b1 the smooth form's own floor on L_peak1
    (2 e a / k_b1) binds: peak1's upper bound keeps the intervals after it open, with L_peak1
    fitted and with it fixed, and the transform's reverse-mode derivatives stay finite in
    every form, also where L_peak1 lies below the smooth form's floor (its branch unselected)."""
    names = PARAMS + ("L_rise1",)
    drop = vr.drop_test(0.2, seed=5, crush_peak=0.0)
    veh = switch_on(set_values(drop.vehicle, ("L_rise1",), [1e-3]), names)
    k_b1, f1 = get_values(veh, ("k_b1", "F1"))
    # a secondary stage far stronger, so that its rule (r1 F1 < F2) leaves peak1 to the room
    stiff = set_values(veh, ("k", "F2"), [20.0 * k_b1, 20.0 * f1])
    i_r, i_l = names.index("peak1"), names.index("L_peak1")

    def steepest(ratio, length, rise):  # the smooth form's build-up at its onset [N/m]
        return (ratio - 1.0) * f1 / (rise * _top(rise / length))

    top = get_values(stiff, names)
    top[i_r] = interval("peak1", names, top, stiff, "smooth_exp")[1]
    lo_l, hi_l = interval("L_peak1", names, top, stiff, "smooth_exp")
    assert lo_l < hi_l
    top[i_l] = lo_l * (1 + 1e-9)
    lo_r, hi_r = interval("L_rise1", names, top, stiff, "smooth_exp")
    assert lo_r < hi_r and steepest(top[i_r], top[i_l], lo_r) < k_b1
    fixed = cal.DEFAULT_PARAMS + ("peak1", "L_rise1")  # L_peak1 held at 1 mm
    short = set_values(stiff, ("L_peak1",), [1e-3])
    v_f = get_values(short, fixed)
    v_f[fixed.index("peak1")] = interval("peak1", fixed, v_f, short, "smooth_exp")[1]
    lo_r, hi_r = interval("L_rise1", fixed, v_f, short, "smooth_exp")
    assert lo_r < hi_r and steepest(v_f[fixed.index("peak1")], 1e-3, lo_r) < k_b1

    z = to_unconstrained(stiff, names, "linear")
    z[i_l] = -12.0  # L_peak1 near the linear form's floor 2 a / k, far below 2 e a / k_b1
    jac = jax.jit(jax.jacrev(lambda z, code: from_unconstrained(z, names, stiff, code)))
    for form in PEAK_FORMS:
        j = np.asarray(jac(jnp.asarray(z), jnp.asarray(FORM_INDEX[form])))
        assert np.all(np.isfinite(j)), form


def test_bad_peak_form_and_model_form_are_refused_by_name():
    drop = vr.drop_test(0.2, seed=5, crush_peak=0.0)
    for kw, rule in ((dict(params=cal.DEFAULT_PARAMS, peak_form="exp"), "needs peak1"),
                     (dict(params=PARAMS + ("L_rise1",), peak_form="exp"), "L_rise1"),
                     (dict(params=PARAMS, peak_form="cosine"),
                      "None, 'exp', 'rise_exp', 'smooth_exp' or 'ripple'"),
                     (dict(params=PARAMS, peak_form="rise_exp"), "needs L_rise1"),
                     (dict(params=PARAMS, model_form="yes"), "'auto', True or False"),
                     (dict(params=cal.DEFAULT_PARAMS, model_form=True), "needs peak1")):
        field = next(k for k in ("peak_form", "model_form") if k in kw)
        with pytest.raises(cal_fit.jl.ConfigError, match=field) as err:
            cal.fit(drop, **kw)
        assert rule in str(err.value), (kw, str(err.value))


def test_the_cli_says_which_interval_it_reports(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_subcommands(parser.add_subparsers(dest="command", required=True))
    toml, _ = vr.write_drop_test(tmp_path, 0.2, seed=5, artefacts=dict(peak_mode="physical"))
    vr.write_nominal(tmp_path)
    out = tmp_path / "fit"
    args = parser.parse_args(
        ["fit", str(toml), "--params", ",".join(PARAMS), "--windows", "0.01,0.03",
         "--refine-window-s", "0.1", "--no-plots", "--quiet", "--out", str(out)])
    assert args.func(args) == 0
    cap = capsys.readouterr()
    text = cap.out
    # the linear form is rejected: the warning gives its own distance to the least adjusted AIC
    rep = json.loads((out / "fit_report.json").read_text())
    d = rep["misfit"]["model_form"]["forms"]["linear"]["daic_adjusted"]
    assert d > cal_fit.DAIC_PLAUSIBLE
    assert (f"the data reject the crush peak's linear form: its misfit-adjusted AIC is {d:.3g} "
            "behind the least (limit 10), and the smooth_exp form is the best supported") in cap.err
    assert "interval reported: total (std_error_total)" in text and "+ peak-shape term" in text
    assert "peak shape: fitted as linear" in text and "best supported: smooth_exp" in text
    assert "the motion shows it too" in text  # a physical peak
    # the best-supported form's values, printed and named in the warning, without a refit
    best = rep["misfit"]["model_form"]["forms"]["smooth_exp"]["values"]
    assert f"the smooth_exp form's values: k {best['k']:.6g}, " in text
    assert f"; its peak: peak1 {best['peak1']:.6g}, " in text  # apart: not in the interval
    assert "(misfit.model_form.forms.smooth_exp.values)" in cap.err
    assert rep["interval_reported"] == "std_error_total"
    assert rep["misfit"]["model_form"]["best_supported"] == "smooth_exp"
    k_b1 = rep["parameters"]["k_b1"]
    assert k_b1["std_error_total"] > 2.0 * max(k_b1["std_error"], k_b1["std_error_hac"])


@pytest.mark.parametrize("form", ["rise_exp", "smooth_exp", "ripple"])
def test_the_cli_fits_the_built_up_exponential_form_and_refuses_it_without_the_rise(
        tmp_path, capsys, form):
    """``jaxland fit --peak-form rise_exp`` (or ``smooth_exp``, ``ripple``): with L_rise1
    among the parameters the fitted vehicle is the law's rise with the exponential table (the
    smooth form: its table, which holds the build-up; the ripple: its table of folds, L_rise1
    long each; they load and validate), and the report names the form; without L_rise1, exit
    2 and one line naming the field."""
    from jaxland.cli import main

    toml, _ = vr.write_drop_test(tmp_path, 0.2, seed=5, artefacts=dict(peak_mode="physical"))
    vr.write_nominal(tmp_path)
    params = ",".join(PARAMS + ("L_rise1",))
    out = tmp_path / "fit"
    assert main(["fit", str(toml), "--params", params, "--peak-form", form,
                 "--windows", "0.01,0.03", "--refine-window-s", "0.1", "--no-plots", "--quiet",
                 "--out", str(out)]) == 0
    hc = jl.load_vehicle(out / "fitted_vehicle.toml").honeycomb
    assert hc.peak_ratio1 is None and (hc.peak_rise1 is not None) == (form == "rise_exp")
    nodes = dict(rise_exp=EXP_POINTS - 1, smooth_exp=EXP_POINTS, ripple=RIPPLE_NODES)[form]
    assert hc.excess1.shape == (nodes,)
    rep = json.loads((out / "fit_report.json").read_text())
    if form == "ripple":
        fold = rep["parameters"]["L_rise1"]["value"]
        assert float(hc.excess_length1) == pytest.approx(RIPPLE_SPAN * fold, rel=1e-9)
    assert rep["misfit"]["model_form"]["form"] == form
    # the caveat is printed exactly where the fitted form is the only one the data support
    line, text = form_caveat(rep["misfit"]["model_form"]), capsys.readouterr().out
    assert (line in text) if line else ("support no other form" not in text)
    assert main(["fit", str(toml), "--params", ",".join(PARAMS), "--peak-form", form,
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--peak-form = '{form}': needs L_rise1" in err[0], err


def test_a_peak_in_the_force_channels_only_is_told_from_the_honeycombs(form_fits):
    """``misfit.peak_location``: where the peak is the honeycomb's (the law's own, the bump and
    the fold ripple in the truth), the motion-only step keeps the fitted excess; where it sits
    on the force channels only (the rig's sensor mode), the step drops most of it and the fit
    warns by name."""
    for label, res in form_fits.items():
        loc = res.diagnostics["peak_location"]
        assert not loc["force_only"] and loc["excess_kept"] > 0.9, (label, loc)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = cal.fit(vr.drop_test(0.2, seed=5, peak_mode="sensor"), PARAMS, model_form=False,
                      **KW)
    assert any(issubclass(w.category, cal.MisfitWarning) and str(w.message).startswith(
        "the crush peak shows in the force channels only") for w in caught)
    loc = res.diagnostics["peak_location"]
    assert loc["force_only"] and loc["excess_kept"] < 0.8 and loc["z"] > 2.0, loc
    assert loc["motion_channels"] == ["stroke_m", "body_accel_mps2"]
    assert cal_fit.peak_location(res.problem, res.theta, *res.problem.robust(None)
                                 .residuals_and_jacobian(res.theta)[:2]) == loc
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        no_peak = cal.fit(vr.drop_test(0.2, seed=5, crush_peak=0.0), cal.DEFAULT_PARAMS, **KW)
    assert no_peak.diagnostics["peak_location"] is None


def test_the_cli_says_where_the_peak_shows_in_each_case():
    base = dict(peak1=1.2, peak1_motion=1.19, std_error_motion=0.005, force_only=False)
    assert peak_location_line(dict(base, excess_kept=0.95, z=2.0)).endswith(
        "the motion shows it too")
    assert peak_location_line(dict(base, peak1_motion=1.1, excess_kept=0.5, z=6.0,
                                   force_only=True)).endswith("no honeycomb's")
    assert peak_location_line(dict(base, excess_kept=0.5, z=1.5)).endswith("undecided")
    assert "no excess" in peak_location_line(dict(base, excess_kept=None, z=None))


def test_the_caveat_names_a_form_that_is_the_only_one_supported():
    """The CLI's caveat: only where the data support the fitted form alone (its peak-shape
    term is then 0), never where another form is plausible too or the fitted form is
    rejected (the term then spans the plausible forms' shift)."""
    line = form_caveat(dict(form="ripple", plausible=["ripple"]))
    assert "peak-shape term is 0" in line and "the ripple form's shape" in line
    assert form_caveat(dict(form="linear", plausible=["smooth_exp"])) is None
    assert form_caveat(dict(form="exp", plausible=["exp", "rise_exp"])) is None
    assert form_caveat(None) is None


def test_compare_models_checks_the_peak_form_against_its_peak_model(tmp_path, capsys):
    """``--compare-models`` fits the peak model (its peak parameters added), so the form is
    checked against that model's parameters: ``--peak-form exp`` goes with the default
    parameters, ``rise_exp`` needs L_rise1 and is refused, by name, before any fit."""
    from calibration._compare import compare_models, peak_model_names
    from jaxland.cli import main

    assert peak_model_names(cal.DEFAULT_PARAMS) == PARAMS
    cal_fit.check_peak_form(peak_model_names(cal.DEFAULT_PARAMS), "exp")
    with pytest.raises(jl.ConfigError, match="needs L_rise1"):
        compare_models([vr.drop_test(0.2, seed=5)], cal.DEFAULT_PARAMS, peak_form="rise_exp")
    toml, _ = vr.write_drop_test(tmp_path, 0.2, seed=5)
    vr.write_nominal(tmp_path)
    capsys.readouterr()
    assert main(["fit", str(toml), "--compare-models", "--peak-form", "rise_exp",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--peak-form = 'rise_exp': needs L_rise1" in err[0], err


def test_the_shared_table_lands_as_each_forms_own_vehicle():
    """``forms_vehicle`` (one compiled landing for every form, the form a runtime code) lands
    as the vehicle in that form (``peak_form_vehicle``) up to rounding. Its derivatives are
    finite in every form, also with a rise length of 0 where the form has no rise, and the
    rise length moves only the rise form."""
    veh = set_values(vr.truth_vehicle(), ("peak1", "L_peak1", "L_rise1"),
                     np.array([1.2, 1.5e-3, 0.8e-3]))
    solver = jl.Solver(dt=1e-5, t_end=0.05, save_dt=1e-4)
    scene = jl.Scene(drop_height=0.0, sink_speed=2.2)
    cols = ("strut_force_N", "stroke_m", "body_az_mps2", "normal_force_N")

    def land(v, code):
        traj = jl.landing(forms_vehicle(v, code), scene, solver, "quarter")[0]
        return jnp.stack([traj[c] for c in cols])

    shared = jax.jit(land)
    refs = []
    for form in PEAK_FORMS:
        traj = jl.landing(peak_form_vehicle(veh, form), scene, solver, "quarter")[0]
        ref = np.stack([np.asarray(traj[c]) for c in cols])
        refs.append(ref[0])
        got = np.asarray(shared(veh, jnp.asarray(FORM_INDEX[form])))
        for c, g, r in zip(cols, got, ref):
            np.testing.assert_allclose(g, r, rtol=0, atol=1e-9 * np.max(np.abs(r)),
                                       err_msg=f"{form}: {c}")
    for i in range(len(refs)):  # the forms themselves land apart (the peak is in the window)
        for j in range(i):
            assert np.max(np.abs(refs[i] - refs[j])) > 1e-3 * np.max(np.abs(refs[i]))

    def force_sum(p, code, rise):  # p: (peak1, L_peak1, L_rise1) relative
        v = set_values(veh, ("peak1", "L_peak1", "L_rise1"),
                       p * jnp.array([1.2, 1.5e-3, rise]))
        return jnp.sum(land(v, code)[0])

    grad = jax.jit(jax.grad(force_sum), static_argnums=2)
    for form in PEAK_FORMS:
        rise = 0.8e-3 if form in RISE_FORMS else 0.0
        g = np.asarray(grad(jnp.ones(3), jnp.asarray(FORM_INDEX[form]), rise))
        assert np.all(np.isfinite(g)), (form, g)
        assert (g[2] != 0.0) == (form in RISE_FORMS), (form, g)


def test_the_ripple_form_re_peaks_fold_by_fold_within_the_rules():
    """The ripple form: the excess peaks at every fold length L_f past the onset, decaying as
    exp(-c / L_peak1), and is 0 half a fold later; its steepest fall 2 a / L_f meets the
    vehicle's rule (<= k / 2) at the lower end of L_rise1's interval, which the rule itself
    would refuse a little further down."""
    names = PARAMS + ("L_rise1",)
    veh = set_values(vr.truth_vehicle(), ("peak1", "L_peak1", "L_rise1"), [1.25, 4.8e-3, 2.4e-3])
    hc = veh.honeycomb
    a = 0.25 * float(hc.F1)
    rip = jl.validate_vehicle(peak_form_vehicle(veh, "ripple"))
    onset = float(hc.x_L1) + a / float(hc.k_b1)
    folds = np.arange(6)
    c = np.concatenate([folds * 2.4e-3, (folds + 0.5) * 2.4e-3])
    force = np.asarray(jax.vmap(lambda x: laws.honeycomb_virgin_force(x, rip.honeycomb))(
        jnp.asarray(onset + c)))
    expect = float(hc.F1) + np.concatenate([a * np.exp(-folds * 0.5), np.zeros(6)])
    np.testing.assert_allclose(force, expect, rtol=1e-12)
    table = np.asarray(ripple_table(jnp.asarray(0.25), jnp.asarray(0.5)))
    np.testing.assert_allclose(table[::2], 0.25 * np.exp(-0.5 * np.arange(len(table[::2]))))
    assert np.all(table[1::2] == 0.0)
    assert float(rip.honeycomb.excess_length1) == pytest.approx(RIPPLE_SPAN * 2.4e-3)

    lo, hi = interval("L_rise1", names, get_values(veh, names), veh, "ripple")
    k = float(veh.ground.k)
    assert lo == pytest.approx(4.0 * a / k, rel=1e-8) and lo < 2.4e-3 < hi
    at_lo = peak_form_vehicle(set_values(veh, ("L_rise1",), [lo]), "ripple")
    jl.validate_vehicle(at_lo)  # the bound holds the rule
    with pytest.raises(jl.ConfigError, match="snaps through"):
        jl.validate_vehicle(peak_form_vehicle(set_values(veh, ("L_rise1",), [0.99 * lo]),
                                              "ripple"))


def test_a_fold_ripple_is_named_the_ripple_form_and_its_values_recover_the_truth(form_fits):
    """On the rig's fold-by-fold ripple (|cos| folds, not the form's linear ones) the ripple
    form is the best-supported one, and its values put k_b1 within 3 % of the truth, where
    the linear peak's fit, which no re-peak can follow, is several percent off."""
    mf = form_fits["folds"].diagnostics["model_form"]
    assert mf["best_supported"] == "ripple"
    truth = float(vr.truth_vehicle().honeycomb.k_b1)
    assert abs(mf["forms"]["ripple"]["values"]["k_b1"] / truth - 1.0) < 0.03
    assert abs(mf["forms"]["linear"]["values"]["k_b1"] / truth - 1.0) > 0.03


def test_the_ripple_refit_starts_at_the_records_fold_length(form_fits):
    """A fold length started one fold-error away locks onto the wrong folds, so the ripple's
    refit screens its interval by chi^2 first: on the rig's fold ripple (folds 2.4 mm long)
    the screen's pick lies within 10 % of them, where the interval's middle does not."""
    res = form_fits["folds"]
    prob, _ = cal_fit._form_problem(res.problem, res.vehicle, "ripple")
    sub = prob.windowed(res.problem.active_window_s)
    veh = cal_fit._screen_folds(res.problem, sub, res.vehicle, res.theta)[0]
    assert abs(float(veh.honeycomb.peak_rise1) / (2.0 * vr.PHYSICAL_PEAK_LENGTH_M) - 1) < 0.1


def test_the_ripple_screen_has_nothing_to_keep_where_the_fits_peak_does_no_work(form_fits):
    """A fit whose crush peak does no work (peak1 = 1, as on records without a peak) leaves
    the ripple's screen no peak height to keep: no starts (the refit starts from the middle of
    its interval), and a peak with almost none spans a bounded number of fold lengths."""
    res = form_fits["law's peak"]
    assert cal_fit.ripple_starts(res.problem, res.vehicle, 0.0) == []
    tiny = cal_fit.ripple_starts(res.problem, res.vehicle, 1e-12)
    assert 0 < len(tiny) <= cal_fit.RIPPLE_STARTS_MAX * len(cal_fit.RIPPLE_DECAYS)


def test_a_fit_and_its_form_refits_share_one_compiled_program(form_fits):
    """With the peak-shape term on, the fit's problem and its refits in the other forms use
    the same compiled functions: the refits compile nothing."""
    for res in form_fits.values():
        mf = res.diagnostics["model_form"]
        assert not mf["failed"] and set(mf["forms"]) == set(PEAK_FORMS)
        assert res.problem.shared_forms and res.problem.peak_form == mf["form"] == "linear"
        for alt in PEAK_FORMS:
            prob, _ = cal_fit._form_problem(res.problem, res.vehicle, alt)
            assert prob.peak_form == alt
            assert prob._res_jit is res.problem._res_jit


def test_the_shared_jacobian_has_each_forms_own_columns():
    """A shared problem's Jacobian holds its own parameters' columns in its own order, the
    rise length's dropped where its form has none: the rise form's with L_rise1 listed
    before L_peak1 is the one with L_rise1 last, permuted; the linear form's L_peak1 and k_b1
    columns are the central differences of its residuals."""
    drop = vr.drop_test(0.2, seed=5, peak_mode="physical")
    veh = switch_on(set_values(drop.vehicle, ("L_rise1",), [1e-3]), PARAMS)
    kw = dict(vehicle=veh, window_s=0.1, pre_s=cal_fit.PRE_S, shared_forms=True)
    names_a = PARAMS[:-1] + ("L_rise1", "L_peak1")
    names_b = PARAMS + ("L_rise1",)
    a, b = CalibrationProblem([drop], names_a, **kw), CalibrationProblem([drop], names_b, **kw)
    assert a._res_jit is b._res_jit and a.peak_form == b.peak_form == "rise"
    theta_b = b.theta_from(veh, [0.05])
    perm = [names_b.index(n) for n in names_a] + [len(names_b)]
    theta_a = theta_b[perm]
    _, ja, _ = a.residuals_and_jacobian(theta_a)
    _, jb, _ = b.residuals_and_jacobian(theta_b)
    np.testing.assert_array_equal(ja, jb[:, perm])
    np.testing.assert_array_equal(a.values(theta_a), b.values(theta_b)[perm[:-1]])

    lin = CalibrationProblem([drop], PARAMS, **dict(kw, vehicle=peak_form_vehicle(veh,
                                                                                    "linear")))
    assert lin._res_jit is b._res_jit and lin.peak_form == "linear"
    theta = lin.theta_from(None, [0.05])
    _, jac, _ = lin.residuals_and_jacobian(theta)
    assert jac.shape[1] == len(PARAMS) + 1
    for n in ("k_b1", "L_peak1"):
        i, h = PARAMS.index(n), 1e-6
        step = np.zeros_like(theta)
        step[i] = h
        fd = (lin.residuals(theta + step)[0] - lin.residuals(theta - step)[0]) / (2 * h)
        assert np.linalg.norm(jac[:, i] - fd) < 1e-3 * np.linalg.norm(fd), n


def test_the_exp_forms_length_is_bounded_by_its_own_tables_room():
    """The exponential form's table spans EXP_SPAN L_peak1 past the onset, so its L_peak1 has
    EXP_SPAN times less room before x_L2 than the linear peak's. The transforms, at_bound and
    a fit's problems in that form (its own functions and the ones shared by every form) bound
    it by that room: a coordinate run onto the upper bound gives a vehicle the table's rule
    accepts, and the same residuals as the model with that table built in (fails with the
    linear form's bound, where the excess would end past x_L2)."""
    drop = vr.drop_test(0.2, seed=5, crush_peak=0.0)
    veh = switch_on(drop.vehicle, PARAMS)
    vals, j = get_values(veh, PARAMS), PARAMS.index("L_peak1")
    lo_lin, hi_lin = interval("L_peak1", PARAMS, vals, veh)
    lo_exp, hi_exp = interval("L_peak1", PARAMS, vals, veh, "exp")
    assert lo_exp == lo_lin and hi_exp == pytest.approx(hi_lin / EXP_SPAN, rel=1e-12)
    too_long = set_values(veh, ("L_peak1",), [0.5 * (hi_exp + hi_lin)])
    with pytest.raises(jl.ConfigError, match="excess must end before x_L2"):
        jl.validate_vehicle(peak_form_vehicle(too_long, "exp"))  # inside the linear bounds

    z = to_unconstrained(veh, PARAMS, "exp")
    z[j] = 40.0  # onto the upper bound: the sigmoid rounds to 1
    v = np.asarray(from_unconstrained(jnp.asarray(z), PARAMS, veh, "exp"))
    assert v[j] == pytest.approx(hi_exp, rel=1e-12)
    table = jl.validate_vehicle(peak_form_vehicle(set_values(veh, PARAMS, v), "exp"))
    assert at_bound(PARAMS, v, veh, form="exp") == ("L_peak1",)
    assert at_bound(PARAMS, v, veh) == ()  # the linear peak has EXP_SPAN times the room

    kw = dict(window_s=0.03, pre_s=cal_fit.PRE_S)
    built_in = CalibrationProblem([drop], cal.DEFAULT_PARAMS, vehicle=table, **kw)
    r_table, _ = built_in.residuals(built_in.theta_from(table, [0.0]))
    for shared in (False, True):
        prob = CalibrationProblem([drop], PARAMS, vehicle=veh, peak_form="exp",
                                  shared_forms=shared, **kw)
        theta = prob.theta_from(veh, [0.0])
        theta[j] = 40.0
        np.testing.assert_allclose(prob.values(theta), v, rtol=1e-12)
        assert float(prob.vehicle_at(theta).honeycomb.excess_length1) == pytest.approx(
            EXP_SPAN * hi_exp, rel=1e-12)
        r, failed = prob.residuals(theta)
        assert not failed
        np.testing.assert_allclose(r, r_table, rtol=0, atol=1e-9 * np.max(np.abs(r_table)))


def test_the_built_up_exp_forms_rise_is_bounded_by_its_own_tables_room():
    """In the built-up exponential form (``rise_exp``) the rise and the table of EXP_SPAN
    L_peak1 must end before x_L2, so L_rise1's upper bound is EXP_SPAN L_peak1 lower than in
    the law's built-up form: a coordinate run onto it gives a vehicle the table's rule
    accepts, in the form's own functions and the shared ones alike, and the fitted vehicle
    is the law's rise with the table (fails with the built-up form's bound)."""
    names = PARAMS + ("L_rise1",)
    drop = vr.drop_test(0.2, seed=5, crush_peak=0.0)
    veh = switch_on(set_values(drop.vehicle, ("L_rise1",), [1e-3]), names)
    vals, j = get_values(veh, names), names.index("L_rise1")
    lo_r, hi_r = interval("L_rise1", names, vals, veh, "rise")
    lo_x, hi_x = interval("L_rise1", names, vals, veh, "rise_exp")
    L = vals[names.index("L_peak1")]
    assert lo_x == lo_r and hi_x == pytest.approx(hi_r - (EXP_SPAN - 1.0) * L, rel=1e-12)
    too_long = set_values(veh, ("L_rise1",), [0.5 * (hi_x + hi_r)])
    with pytest.raises(jl.ConfigError, match="excess must end before x_L2"):
        jl.validate_vehicle(peak_form_vehicle(too_long, "rise_exp"))

    kw = dict(window_s=0.03, pre_s=cal_fit.PRE_S)
    for shared in (False, True):
        prob = CalibrationProblem([drop], names, vehicle=veh, peak_form="rise_exp",
                                  shared_forms=shared, **kw)
        theta = prob.theta_from(veh, [0.0])
        theta[j] = 40.0  # onto the upper bound: the sigmoid rounds to 1
        assert prob.values(theta)[j] == pytest.approx(hi_x, rel=1e-12)
        hc = prob.vehicle_at(theta).honeycomb  # validated
        assert float(hc.peak_rise1) == pytest.approx(hi_x, rel=1e-12)
        assert hc.excess1.shape == (EXP_POINTS - 1,) and hc.peak_ratio1 is None
        r, failed = prob.residuals(theta)
        assert not failed and np.all(np.isfinite(r))


def test_an_exp_refit_starts_inside_its_own_bounds():
    """A linear fit whose L_peak1 lies beyond the exponential form's room (inside the linear
    form's) starts the exp refit at a length inside the exp interval, where it would otherwise
    be refused by the table's rule; a start already inside is kept."""
    drop = vr.drop_test(0.2, seed=5, crush_peak=0.0)
    veh = switch_on(drop.vehicle, PARAMS)
    vals = get_values(veh, PARAMS)
    _, hi_lin = interval("L_peak1", PARAMS, vals, veh)
    lo_exp, hi_exp = interval("L_peak1", PARAMS, vals, veh, "exp")
    long_peak = set_values(veh, ("L_peak1",), [0.5 * (hi_exp + hi_lin)])
    kw = dict(window_s=0.03, pre_s=cal_fit.PRE_S)
    base = CalibrationProblem([drop], PARAMS, vehicle=long_peak, **kw)
    prob, start = cal_fit._form_problem(base, long_peak, "exp")
    L = float(start.honeycomb.peak_length1)
    assert lo_exp < L < hi_exp
    prob.theta_from(start, [0.0])  # inside: no ConfigError
    inside = set_values(veh, ("L_peak1",), [0.5 * (lo_exp + hi_exp)])
    _, kept = cal_fit._form_problem(base, inside, "exp")
    assert float(kept.honeycomb.peak_length1) == 0.5 * (lo_exp + hi_exp)
    # a fit that ended with L_peak1 on its lower bound (up to rounding): every form's refit
    # starts just inside it, where its transform would otherwise refuse the value
    lo_lin = interval("L_peak1", PARAMS, vals, veh)[0]
    on_bound = set_values(veh, ("L_peak1",), [lo_lin * (1.0 - 1e-15)])
    for alt in PEAK_FORMS:
        prob, start = cal_fit._form_problem(base, on_bound, alt)
        names = prob.names
        lo, hi = interval("L_peak1", names, get_values(start, names), start, alt)
        L = float(start.honeycomb.peak_length1)
        assert lo < L <= lo + cal_fit.START_ABOVE_BOUND * (hi - lo) * (1 + 1e-12), alt
        prob.theta_from(start, [0.0])  # inside: no ConfigError
