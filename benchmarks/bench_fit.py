"""Benchmark of the calibration (issue #4), per fitting integrator side by side: time a
6-parameter fit to one 1.2 s drop test at 5 kHz, check convergence from a set of starts, the
recovery of the virtual rig's truth, the prediction of other drop heights, and AD against
central finite differences of the calibration loss.

    .venv/bin/python benchmarks/bench_fit.py [--with-lbfgs] [--variants euler,verlet_smooth]
                                             [--out benchmarks/results]
    .venv/bin/python benchmarks/bench_fit.py --coverage 20 [--quick]
    .venv/bin/python benchmarks/bench_fit.py --fit-time [--quick]

``--coverage N`` measures, over N noise seeds, how often the reported 95 % intervals (value +/-
1.96 standard errors, the classical and the HAC one) contain the truth, on rig data the model
can represent and on rig data with artefacts it lacks (the rig's crush-peak shape; that peak
with a 500 Hz two-pole low-pass on every sensor), and how often they contain the pseudo-truth
(the same fit on the artefact record without noise, weighted by the rig's noise: what the wrong
model converges to; intervals that are honest about the scatter cover it even where the model's
bias keeps them off the truth). It stores its result under "coverage" in bench_fit.json (the
rest of the file kept); ``--quick`` (3 seeds) writes out/bench_fit_quick.json instead and never
touches the committed results. ``--peak-model`` (``peak_model_study``) fits the crush-peak
model to rig records whose peak shape differs from the law's, into "peak_model". ``--fit-time``
times cold fits (``FIT_TIME_CASES``: the default fit, the crush-peak model on rig records, a
joint fit, the lab-format record), each in a fresh process so that the compilation counts, with
the optimiser's work and the load average of the shared machine, into "fit_time".

Variants (``VARIANTS``): ``euler`` (symplectic Euler, hard switches) and ``verlet_smooth``
(velocity Verlet with 1e-6 m / 10 N switch smoothing, the gradient-quality study's fitting
method, benchmarks/gradient_quality.py), both at dt = 1e-5 s on calibration's growing
first-impact windows. Each variant's cold fit (compiling its own functions) runs before either
warm fit; the warm time is the best of two.

Writes ``bench_fit.json`` and ``bench_fit.png``. The data are the bundled SYNTHETIC drop tests
(``data/synthetic``: noise, a 1.5 mm stroke offset and a +20 % honeycomb crush peak that the
model does not have), and noise-free drops from the same rig. Targets: fit <= 20 s including
compilation on the 2-core CPU; noise-free recovery within 0.5 %; fitted at one drop height, the
prediction of another within 1 % on max stroke and 5 % on peak forces; AD = FD to 1e-4 (issue
#3). Timings are wall-clock on whatever machine runs this (noisy on shared machines); tests
never assert them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import numpy as np  # noqa: E402

import calibration as cal  # noqa: E402
import jaxland as jl  # noqa: E402
from calibration import virtual_rig as vr  # noqa: E402
from calibration._parameters import (  # noqa: E402
    EXP_TABLE_SPAN,
    FORCES,
    HONEYCOMB,
    PEAK_SITES,
    get_values,
    set_values,
)

jax.config.update("jax_enable_x64", True)

DATA = ROOT / "data" / "synthetic"
TARGETS = dict(fit_s=20.0, clean_recovery_rel=0.005, max_stroke_rel=0.01, peak_force_rel=0.05,
               ad_fd_rel=1e-4)
VARIANTS = {
    "euler": dict(integrator="euler", smoothing_m=0.0, smoothing_N=0.0),
    "verlet_smooth": dict(integrator="verlet", smoothing_m=1e-6, smoothing_N=10.0),
}
STARTS = {  # factors on the truth of k, gamma, D_b, k_b1, F1, F2
    "30% off": [1.3, 0.77, 1.3, 0.77, 1.3, 1.3],
    "30% off (other signs)": [0.77, 1.3, 0.77, 1.3, 0.77, 0.77],
    "2x off": [2.0] * 6,
    "0.5x off": [0.5] * 6,
    "2x off mixed": [0.5, 1.5, 2.0, 0.5, 2.0, 1.5],
}
FD_STEPS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
FD_WINDOWS_S = (0.03, 0.15)  # a multi-start stage and the final stage of the default fit
SAME_OPTIMUM_REL = 1e-3  # a start "converged" when it ends within this of the nominal fit


def _fit(drops, **kw):
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cal.IdentifiabilityWarning)
        res = cal.fit(drops, **kw)
    return res, time.perf_counter() - t0


def _summary(res, wall, truth):
    p_true = get_values(truth, res.names)
    return dict(
        wall_s=wall, iterations=sum(s["iterations"] for s in res.stages),
        stages=[{k: s[k] for k in ("stage", "iterations", "status", "wall_s")}
                for s in res.stages],
        multistart=res.settings["multistart"]["n_starts_tried"],
        integrator=res.settings["integrator"], loss=res.loss,
        values=dict(zip(res.names, res.values.tolist())),
        rel_error=dict(zip(res.names, (res.values / p_true - 1).tolist())),
        rel_std_error=dict(zip(res.names, (res.std_errors / res.values).tolist())),
        z=dict(zip(res.names, ((res.values - p_true) / res.std_errors).tolist())),
        residual_variance_factor=res.sigma2)


def ad_vs_fd(drop, opts, vehicle):
    """AD (jacfwd, J^T r) against central differences of the calibration loss (plain least
    squares) on the fit's windows, at ``vehicle``'s values and at a start 10-30 % off, per
    parameter (and the touchdown shift t0, in ms) and FD step h (in the unconstrained
    coordinates). ``robust``: the better of two neighbouring steps a decade apart must both
    agree (benchmarks/gradient_quality.py), so a lucky secant on a jagged loss does not count."""
    out = {}
    names = [*cal.DEFAULT_PARAMS, "t0"]
    for w in FD_WINDOWS_S:
        prob = cal.CalibrationProblem([drop], cal.DEFAULT_PARAMS, vehicle=vehicle, window_s=w,
                                      pre_s=0.005, **opts)
        loss = jax.jit(prob.loss_fn())
        th_fit = prob.theta_from()
        points = {"fitted": th_fit,
                  "start": th_fit + np.array([0.2, -0.3, -0.15, -0.2, -0.1, 0.1, 0.05])}
        for label, th in points.items():
            r, jac, _ = prob.residuals_and_jacobian(th)
            g = jac.T @ r
            fd = np.zeros((len(FD_STEPS), th.size))
            for j, h in enumerate(FD_STEPS):
                for i in range(th.size):
                    e = np.zeros(th.size)
                    e[i] = h
                    fd[j, i] = (float(loss(th + e)) - float(loss(th - e))) / (2 * h)
            rel = np.abs(fd - g[None]) / np.maximum(np.abs(g[None]), 1e-300)
            robust = np.maximum(rel[:-1], rel[1:]).min(axis=0)
            out[f"{w * 1e3:g} ms, {label}"] = dict(
                ad=dict(zip(names, g.tolist())),
                rel_err=dict(zip(names, rel.T.tolist())),
                rel_err_at_1e6=dict(zip(names, rel[FD_STEPS.index(1e-6)].tolist())),
                robust_rel_err=dict(zip(names, robust.tolist())),
                worst_robust=float(robust.max()),
                worst_robust_param=names[int(np.argmax(robust))])
    worst = {n: max(v["robust_rel_err"][n] for v in out.values()) for n in names}
    return dict(steps=list(FD_STEPS), cases=out, worst_robust_per_param=worst,
                worst_robust=max(worst.values()),
                meets_target=bool(max(worst.values()) <= TARGETS["ad_fd_rel"]))


COVERAGE_CASES = {
    "representable": dict(crush_peak=0.0),
    "artefact: crush peak": dict(),
    "artefact: crush peak + 500 Hz low-pass": dict(lowpass_Hz=500.0),
    # a crush peak in the truth's honeycomb itself (the law's own shape, +10 % over 1 mm), in
    # every channel alike, which the fitted model (no peak) lacks
    "physical crush peak (+10 %, 1 mm), not in the model": dict(crush_peak=0.0,
                                                                truth_peak=(1.1, 1e-3)),
    # the same drop fitted with the crush-peak model: the data are then representable
    "physical crush peak (+10 %, 1 mm), fitted with the peak": dict(
        crush_peak=0.0, truth_peak=(1.1, 1e-3), fit_extra=("peak1", "L_peak1")),
    # the rig's physical bump (+20 %, built up over 1.2 mm of crush) in the truth's honeycomb:
    # not in the model; fitted with the law's linear peak; with its rise length too
    "physical bump peak, not in the model": dict(peak_mode="physical"),
    "physical bump peak, fitted with the linear peak": dict(
        peak_mode="physical", fit_extra=("peak1", "L_peak1")),
    "physical bump peak, fitted with the peak and its rise": dict(
        peak_mode="physical", fit_extra=("peak1", "L_peak1", "L_rise1")),
    # the rig's other physical shapes (+20 %): a jump decaying exponentially; a fold ripple
    "physical exp peak, fitted with the linear peak": dict(
        peak_mode="physical", peak_shape="exp", fit_extra=("peak1", "L_peak1")),
    "physical folds peak, fitted with the linear peak": dict(
        peak_mode="physical", peak_shape="folds", fit_extra=("peak1", "L_peak1")),
    # a bump that starts flat, which no peak form is near: with the linear peak, with its rise
    "physical slow peak, fitted with the linear peak": dict(
        peak_mode="physical", peak_shape="slow", fit_extra=("peak1", "L_peak1")),
    "physical slow peak, fitted with the peak and its rise": dict(
        peak_mode="physical", peak_shape="slow", fit_extra=("peak1", "L_peak1", "L_rise1")),
    # --compare-models: the model the data support (no peak, or the linear peak with its
    # peak-shape term) is the one reported
    "representable, --compare-models": dict(crush_peak=0.0, compare=True),
    "physical crush peak (+10 %, 1 mm), --compare-models": dict(
        crush_peak=0.0, truth_peak=(1.1, 1e-3), compare=True),
    "physical bump peak, --compare-models": dict(peak_mode="physical", compare=True),
}
Z95 = 1.959964


def _fit_or_compare(drops, params, compare: bool):
    """``_fit``, or with ``compare`` the fit ``--compare-models`` reports (the peak model where
    the data support the peak, else the one without)."""
    if not compare:
        return _fit(drops, params=params)
    from calibration._compare import compare_models

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cal.IdentifiabilityWarning)
        cmp = compare_models(drops, params)
    chosen = "peak" if cmp["comparison"]["peak_supported"] else "no_peak"
    return cmp["_results"][chosen], time.perf_counter() - t0


def _clean_drop(height: float, **kw):
    """The rig's noise-free record weighted as its noisy ones are (by the rig's noise, not the
    loader's floor, whose ratios between the channels differ): what the fit converges to
    without the scatter, its pseudo-truth."""
    clean = vr.drop_test(height, noise=None, **kw)
    clean.noise_std.update({c: vr.NOISE[c] for c in clean.noise_std})
    return clean


def _coverage_case(rig: dict, truth, names):
    """(drop_test keywords, fitted parameters, compare) of a ``COVERAGE_CASES`` entry."""
    kw = {k: v for k, v in rig.items() if k not in ("truth_peak", "fit_extra", "compare")}
    if "truth_peak" in rig:
        kw["vehicle"] = set_values(truth, ("peak1", "L_peak1"), np.array(rig["truth_peak"]))
    return kw, names + tuple(rig.get("fit_extra", ())), bool(rig.get("compare"))


def _pseudo_truth(height: float, kw: dict, params, compare: bool, n: int) -> np.ndarray:
    """The first ``n`` values of the case's fit (``_coverage_case``) to ``_clean_drop``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cal.MisfitWarning)
        pseudo, _ = _fit_or_compare([_clean_drop(height, **kw)], params, compare)
    return pseudo.values[:n]


def coverage(n_seeds: int, height: float = 0.2, only: str | None = None) -> dict:
    """Coverage of the 95 % intervals over ``n_seeds`` noise seeds per ``COVERAGE_CASES``
    (``only``: the cases whose label contains it)."""
    truth = vr.truth_vehicle()
    names = cal.DEFAULT_PARAMS
    p_true = get_values(truth, names)
    out = dict(n_seeds=n_seeds, drop_height_m=height, level=0.95, z=Z95,
               params=list(names), cases={})
    n = len(names)
    for label, rig in COVERAGE_CASES.items():
        if only and only not in label:
            continue
        kw, params, compare = _coverage_case(rig, truth, names)  # the coverage: of names
        p_pseudo = _pseudo_truth(height, kw, params, compare, n)
        rows = []
        for seed in range(n_seeds):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cal.MisfitWarning)
                r, w = _fit_or_compare([vr.drop_test(height, seed=1000 + seed, **kw)], params,
                                       compare)
            rows.append(dict(seed=1000 + seed, wall_s=w, values=r.values[:n].tolist(),
                             se=r.std_errors[:n].tolist(), se_hac=r.std_errors_hac[:n].tolist(),
                             se_total=r.std_errors_total[:n].tolist(), **_form_row(r, n),
                             sigma2=r.sigma2, rho1=r.diagnostics["residual_lag1_autocorr"],
                             misfit_warned=bool(r.diagnostics["misfit"]),
                             at_bound=r.diagnostics["at_bound"]))
            print(f"[coverage] {label}, seed {seed}: {w:.1f} s, rho1 "
                  f"{rows[-1]['rho1']:.2f}", flush=True)
        out["cases"][label] = dict(rig=rig, truth=dict(zip(names, p_true.tolist())),
                                   pseudo_truth=dict(zip(names, p_pseudo.tolist())), runs=rows)
        out["cases"][label].update(coverage_summary(out["cases"][label], names))
        c = out["cases"][label]
        print(f"[coverage] {label}: truth classical {c['coverage_of_truth']['classical_all']:.2f}"
              f" hac {c['coverage_of_truth']['hac_all']:.2f} trusted "
              f"{c['coverage_of_truth']['trusted_all']:.2f}", flush=True)
    return out


def _form_row(r, n: int) -> dict:
    """The peak-shape (model-form) term of a fit's first ``n`` parameters: the total standard
    error without it, the best-supported form and its values, the plausible forms."""
    mf = r.diagnostics.get("model_form")
    if mf is None:
        row = dict(model_form=False, se_total_without_form=r.std_errors_total[:n].tolist(),
                   best_form="no peak", best_form_values=r.values[:n].tolist())
        pm = r.diagnostics.get("peak_model_term")
        if pm is not None and pm["added"]:  # the missing-peak term (no peak in the fit)
            term = np.array([pm["term"][p] for p in r.names[:n]])
            row.update(peak_model_term=True, peak_term=term.tolist(),
                       se_total_without_peak_term=np.sqrt(np.maximum(
                           r.std_errors_total[:n] ** 2 - term ** 2, 0.0)).tolist())
        return row
    term = np.array([mf["spread"][p] for p in r.names[:n]])
    best = mf["forms"][mf["best_supported"]]
    return dict(model_form=True,
                se_total_without_form=np.sqrt(np.maximum(
                    r.std_errors_total[:n] ** 2 - term ** 2, 0.0)).tolist(),
                form_term=term.tolist(), best_form=mf["best_supported"],
                plausible_forms=mf["plausible"], failed_forms=mf["failed"],
                best_form_values=[best["values"][p] for p in r.names[:n]],
                best_form_shape={p: best["values"][p] for p in ("peak1", "L_peak1", "L_rise1")
                                 if p in best["values"]},
                forms=_forms_scores(mf), n_obs=r.n_obs)


def _forms_scores(mf) -> dict:
    """Each peak form's chi^2, fitted parameters, scores and plausibility (None: its refit
    failed), so that another reading of which form is best can be judged from the stored
    runs."""
    keys = ("chi2", "n_params", "daic_adjusted", "bic_adjusted", "plausible")
    return {k: None if f is None else {x: f[x] for x in keys} for k, f in mf["forms"].items()}


def coverage_summary(case: dict, names) -> dict:
    """Coverage of the 95 % intervals from a case's stored runs: classical, HAC, the
    'trusted' one the fit report points to (HAC where it warned of misfit, else classical) and
    the total one (the trusted error with the channel spread, where the runs have it)."""
    rows = case["runs"]
    p_true = np.array([case["truth"][n] for n in names])
    p_pseudo = np.array([case["pseudo_truth"][n] for n in names])
    v = np.array([r_["values"] for r_ in rows])
    se, seh = np.array([r_["se"] for r_ in rows]), np.array([r_["se_hac"] for r_ in rows])
    warned = np.array([r_["misfit_warned"] for r_ in rows])[:, None]
    trusted = np.where(warned, seh, se)

    kinds = [("classical", se), ("hac", seh), ("trusted", trusted)]
    if all("se_total" in r_ for r_ in rows):  # the trusted error with the channel spread
        kinds.append(("total", np.array([r_["se_total"] for r_ in rows])))
    form = any(r_.get("model_form") for r_ in rows)
    if form:  # the total without the peak-shape term: the interval before it
        kinds.append(("total_without_form",
                      np.array([r_["se_total_without_form"] for r_ in rows])))

    peak_term = any(r_.get("peak_model_term") for r_ in rows)
    if peak_term:  # the total without the missing-peak term (fits that have it)
        kinds.append(("total_without_peak_term", np.array(
            [r_.get("se_total_without_peak_term", r_["se_total"]) for r_ in rows])))

    def cov(ref):
        out = {}
        for label, s in kinds:
            inside = np.abs(v - ref[None]) <= Z95 * s
            out[label] = dict(zip(names, inside.mean(axis=0).tolist()))
            out[f"{label}_all"] = float(inside.mean())
        return out

    extra = {}
    if len(kinds) > 3:
        extra["mean_se_total_rel"] = dict(zip(names, (kinds[3][1].mean(axis=0)
                                                      / p_true).tolist()))
    extra["peak_model_term"] = peak_term
    extra["peak_model_term_fraction"] = float(np.mean([bool(r_.get("peak_model_term"))
                                                       for r_ in rows]))
    if peak_term:
        ratio = kinds[3][1] / kinds[-1][1]
        extra["width_ratio_peak_term"] = dict(
            median=float(np.median(ratio)), max=float(np.max(ratio)),
            per_param_median=dict(zip(names, np.median(ratio, axis=0).tolist())))
    extra["model_form"] = form
    extra["model_form_fraction"] = float(np.mean([bool(r_.get("model_form")) for r_ in rows]))
    if form:
        ratio = kinds[3][1] / kinds[4][1]
        extra["width_ratio_form"] = dict(
            median=float(np.median(ratio)), max=float(np.max(ratio)),
            per_param_median=dict(zip(names, np.median(ratio, axis=0).tolist())))
        best = np.array([r_["best_form_values"] for r_ in rows])
        err = best / p_true[None] - 1
        extra["best_form"] = dict(
            counts={f: sum(r_["best_form"] == f for r_ in rows)
                    for f in dict.fromkeys(r_["best_form"] for r_ in rows)},
            seeds_within_3pct_five=int(np.sum(np.all(np.abs(err[:, :5]) <= 0.03, axis=1))),
            mean_rel_error=dict(zip(names, err.mean(axis=0).tolist())))
        nominal = v / p_true[None] - 1
        extra["seeds_within_3pct_five"] = int(np.sum(np.all(np.abs(nominal[:, :5]) <= 0.03,
                                                            axis=1)))
    return dict(
        **extra,
        bias_of_pseudo_truth_rel=dict(zip(names, (p_pseudo / p_true - 1).tolist())),
        spread_rel=dict(zip(names, (v.std(axis=0, ddof=1) / p_true).tolist())),
        mean_se_rel=dict(zip(names, (se.mean(axis=0) / p_true).tolist())),
        mean_se_hac_rel=dict(zip(names, (seh.mean(axis=0) / p_true).tolist())),
        coverage_of_truth=cov(p_true), coverage_of_pseudo_truth=cov(p_pseudo),
        misfit_warned_fraction=float(warned.mean()),
        mean_sigma2=float(np.mean([r_["sigma2"] for r_ in rows])),
        mean_rho1=float(np.mean([r_["rho1"] for r_ in rows])))


def peak_model_study(quick: bool = False) -> dict:
    """The crush-peak model (default parameters + peak1, L_peak1) fitted to rig records whose
    peak shape differs from the law's (each of ``vr.PEAK_SHAPES``, at 0.2 m), against the
    no-peak fit: recovery of the truth (with the HAC errors: z = error / SE_hac), the
    prediction of the other heights, and a joint fit of 0.15 m + 0.30 m (the latter reaches the
    secondary stage) with its prediction of 0.20 m."""
    truth = vr.truth_vehicle()
    base = cal.DEFAULT_PARAMS
    names = base + ("peak1", "L_peak1")
    p_true = get_values(truth, base)
    out = dict(params=list(names), shapes={})

    def summary(r, wall):
        vals = r.values[: len(base)]
        se_h = r.std_errors_hac[: len(base)]
        return dict(wall_s=wall, values=dict(zip(r.names, r.values.tolist())),
                    rel_error=dict(zip(base, (vals / p_true - 1).tolist())),
                    z_hac=dict(zip(base, ((vals - p_true) / se_h).tolist())),
                    z_classical=dict(zip(base, ((vals - p_true)
                                                / r.std_errors[: len(base)]).tolist())),
                    sigma2=r.sigma2, rho1=r.diagnostics["residual_lag1_autocorr"])

    shapes = vr.PEAK_SHAPES[:1] if quick else vr.PEAK_SHAPES
    for shape in shapes:
        drops = {h: vr.drop_test(h, peak_shape=shape, seed=200 + i)
                 for i, h in enumerate(vr.HEIGHTS_M)}
        rec = {}
        for label, ps in (("no_peak", base), ("peak", names)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cal.MisfitWarning)
                r, w = _fit([drops[0.2]], params=ps)
            rec[label] = summary(r, w)
            rec[label]["prediction"] = {f"{h:.2f}": {k: v["rel_error"] for k, v in
                                                     cal.predict(r.vehicle, d).metrics.items()}
                                        for h, d in drops.items() if h != 0.2}
            print(f"[peak model] {shape}, {label}: {w:.1f} s, "
                  + ", ".join(f"{n} {e:+.2%}" for n, e in rec[label]["rel_error"].items()),
                  flush=True)
        out["shapes"][shape] = rec
    if not quick:
        drops = {h: vr.drop_test(h, seed=300 + i) for i, h in enumerate(vr.HEIGHTS_M)}
        joint = {}
        for label, ps in (("no_peak", base), ("peak", names)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cal.MisfitWarning)
                r, w = _fit([drops[0.15], drops[0.3]], params=ps)
            joint[label] = summary(r, w)
            joint[label]["predict_0.20"] = {k: v["rel_error"] for k, v in
                                            cal.predict(r.vehicle, drops[0.2]).metrics.items()}
            joint[label]["refit_0.30"] = {k: v["rel_error"] for k, v in
                                          cal.predict(r.vehicle, drops[0.3]).metrics.items()}
            print(f"[peak model] joint 0.15 + 0.30, {label}: {w:.1f} s, F2 "
                  f"{joint[label]['rel_error']['F2']:+.2%}", flush=True)
        out["joint_0.15_0.30_bump"] = joint
    return out


PREDICTION_TARGETS = dict(stroke=0.01, peak=0.05, F2=0.03)  # the issue's, relative
PREDICTED = dict(max_stroke_m="stroke", final_stroke_m="stroke", peak_normal_force_N="peak",
                 peak_buffer_force_N="peak", peak_body_accel_mps2="peak")


def _fit_in_best_form(drops) -> tuple:
    """A user's path on a record with a crush peak: fit with the law's peak (the default
    parameters + peak1, L_peak1), then, where the fit names another form best supported,
    refit in that form as its warning advises (``--peak-form``, and L_rise1 where the form
    has it), started from that form's refit. (first fit, its wall time, best form, the fit in
    it, its wall time)."""
    first, w1 = _fit(drops, params=cal.DEFAULT_PARAMS + ("peak1", "L_peak1"))
    best = first.diagnostics["model_form"]["best_supported"]
    if best == "linear":
        return first, w1, best, first, 0.0
    vals = first.diagnostics["model_form"]["forms"][best]["values"]
    r, w = _fit(drops, params=tuple(vals), start=vals,
                peak_form=best if best in EXP_TABLE_SPAN else None)
    return first, w1, best, r, w


def best_form_prediction(quick: bool = False) -> dict:
    """Recovery and prediction where the crush peak is physical (in the truth's honeycomb:
    force, stroke and acceleration carry it) and the fit takes the best-supported form
    (``_fit_in_best_form``): for each rig peak shape, the 0.2 m drop fitted, the 0.15 and
    0.30 m drops of the same gear predicted (each drop its own noise seed, as
    ``peak_model_study``); and the joint fit of 0.15 + 0.30 m of the bump (0.30 m reaches the
    secondary stage) predicting 0.20 m and the 0.30 m drop's final stroke. Errors of the five
    checked parameters and F2 against the truth, of the predictions against the data, and
    whether each meets ``PREDICTION_TARGETS``."""
    truth = vr.truth_vehicle()
    names = RECOVERY_CHECKED + ("F2",)
    p_true = get_values(truth, names)
    rig = dict(peak_mode="physical", peak_length_m=vr.PHYSICAL_PEAK_LENGTH_M)
    out = dict(rig=rig, targets=dict(PREDICTION_TARGETS, params=0.03), shapes={})

    def result(first, w1, best, r, w):
        err = get_values(r.vehicle, names) / p_true - 1
        idx = [r.names.index(n) for n in names]
        z = (r.values[idx] - p_true) / r.std_errors_total[idx]
        return dict(first_wall_s=w1, best_form=best, wall_s=w, values=dict(zip(
            r.names, r.values.tolist())), rel_error=dict(zip(names, err.tolist())),
            z_total=dict(zip(names, z.tolist())),
            params_met=bool(np.all(np.abs(err[:len(RECOVERY_CHECKED)]) <= 0.03)),
            inside_2se=bool(np.all(np.abs(z[:len(RECOVERY_CHECKED)]) <= 2.0)),
            F2_met=bool(abs(err[-1]) <= PREDICTION_TARGETS["F2"]))

    def prediction(r, drop):
        errs = {k: v["rel_error"] for k, v in cal.predict(r.vehicle, drop).metrics.items()
                if k in PREDICTED}
        return dict(rel_error=errs, met=bool(all(abs(e) <= PREDICTION_TARGETS[PREDICTED[k]]
                                                 for k, e in errs.items())))

    for shape in vr.PEAK_SHAPES[:1] if quick else vr.PEAK_SHAPES:
        drops = {h: vr.drop_test(h, peak_shape=shape, seed=200 + i, **rig)
                 for i, h in enumerate(vr.HEIGHTS_M)}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cal.MisfitWarning)
            fits = _fit_in_best_form([drops[0.2]])
        rec = result(*fits)
        rec["prediction"] = {f"{h:.2f}": prediction(fits[3], d) for h, d in drops.items()
                             if h != 0.2}
        out["shapes"][shape] = rec
        print(f"[best-form prediction] {shape}: {rec['best_form']}, "
              + ", ".join(f"{n} {e:+.2%}" for n, e in rec["rel_error"].items())
              + "; predictions " + ", ".join(f"{h} {'met' if p['met'] else 'missed'}"
                                             for h, p in rec["prediction"].items()), flush=True)
    if not quick:
        drops = {h: vr.drop_test(h, seed=300 + i, **rig) for i, h in enumerate(vr.HEIGHTS_M)}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cal.MisfitWarning)
            fits = _fit_in_best_form([drops[0.15], drops[0.3]])
        joint = result(*fits)
        joint["prediction"] = {"0.20": prediction(fits[3], drops[0.2]),
                               "0.30 (fitted)": prediction(fits[3], drops[0.3])}
        out["joint_0.15_0.30_bump"] = joint
        print(f"[best-form prediction] joint 0.15 + 0.30: {joint['best_form']}, F2 "
              f"{joint['rel_error']['F2']:+.2%}, 0.30 m final stroke "
              f"{joint['prediction']['0.30 (fitted)']['rel_error']['final_stroke_m']:+.2%}",
              flush=True)
    return out


def best_form_coverage(n_seeds: int, height: float = 0.2) -> dict:
    """How often the refit in the best-supported form (``_fit_in_best_form``, a user's path)
    covers the truth with its own interval: per rig peak shape (physical peak), over
    ``n_seeds`` noise seeds (the peak-recovery study's seeds, so its first fits are that
    study's), the refit's error against the truth of the five checked parameters and z =
    error / its total standard error, the same z of the first fit (the law's linear peak),
    and the refit's error over the first fit's total standard error (the refit's values
    quoted with the first fit's interval, as the CLI prints them). Per shape: the forms
    named, the seeds with all five within 3 % (and with them also inside 2 of the first fit's
    total standard errors), and each interval's coverage at 95 % per parameter."""
    truth = vr.truth_vehicle()
    names = RECOVERY_CHECKED
    p_true = get_values(truth, names)
    seeds = list(range(PEAK_RECOVERY_SEEDS, PEAK_RECOVERY_SEEDS + n_seeds))
    rig = dict(peak_mode="physical", peak_length_m=vr.PHYSICAL_PEAK_LENGTH_M)
    out = dict(params=list(names), drop_height_m=height, seeds=seeds, rig=rig, z=Z95,
               shapes={})

    def total_se(r):  # the fit's total standard errors of the checked parameters
        return r.std_errors_total[[r.names.index(n) for n in names]]

    def z_of(r, se):
        return (r.values[[r.names.index(n) for n in names]] - p_true) / se

    for shape in vr.PEAK_SHAPES:
        runs = []
        for seed in seeds:
            drop = vr.drop_test(height, peak_shape=shape, seed=seed, **rig)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cal.MisfitWarning)
                first, w1, best, r, w = _fit_in_best_form([drop])
            err = get_values(r.vehicle, names) / p_true - 1
            runs.append(dict(seed=seed, best_form=best, wall_s=w1 + w,
                             rel_error=dict(zip(names, err.tolist())),
                             z_total=dict(zip(names, z_of(r, total_se(r)).tolist())),
                             z_first_fit=dict(zip(names, z_of(first, total_se(first)).tolist())),
                             z_refit_over_first_se=dict(zip(names, z_of(
                                 r, total_se(first)).tolist())),
                             se_first_total_rel=dict(zip(names, (total_se(first)
                                                                 / p_true).tolist())),
                             only_form_supported=bool(
                                 r.diagnostics["model_form"]["plausible"]
                                 == [r.diagnostics["model_form"]["form"]])))
            print(f"[best-form coverage] {shape}, seed {seed}: {best}, "
                  + ", ".join(f"{n} {e:+.2%} ({runs[-1]['z_total'][n]:+.1f})"
                              for n, e in runs[-1]["rel_error"].items()), flush=True)
        err = np.array([[r_["rel_error"][n] for n in names] for r_ in runs])
        z = np.array([[r_["z_total"][n] for n in names] for r_ in runs])
        z1 = np.array([[r_["z_first_fit"][n] for n in names] for r_ in runs])
        z2 = np.array([[r_["z_refit_over_first_se"][n] for n in names] for r_ in runs])
        out["shapes"][shape] = dict(
            runs=runs,
            best_form_counts={f: sum(r_["best_form"] == f for r_ in runs)
                              for f in dict.fromkeys(r_["best_form"] for r_ in runs)},
            seeds_within_3pct=int(np.sum(np.all(np.abs(err) <= 0.03, axis=1))),
            coverage_refit=dict(zip(names, np.mean(np.abs(z) <= Z95, axis=0).tolist())),
            coverage_first=dict(zip(names, np.mean(np.abs(z1) <= Z95, axis=0).tolist())),
            coverage_refit_first_total=dict(zip(names, np.mean(np.abs(z2) <= Z95,
                                                              axis=0).tolist())),
            seeds_within_3pct_and_2se_first_total=int(np.sum(
                np.all(np.abs(err) <= 0.03, axis=1) & np.all(np.abs(z2) <= 2.0, axis=1))),
            mean_rel_error=dict(zip(names, err.mean(axis=0).tolist())),
            mean_abs_z_refit=dict(zip(names, np.abs(z).mean(axis=0).tolist())),
            refits_only_form_supported=int(sum(r_["only_form_supported"] for r_ in runs)))
    return out


def plot_best_form_coverage(result: dict, path) -> None:
    """z = error / total standard error of each seed, the refit in the best-supported form's
    own against the first fit's, per rig shape and checked parameter (``best_form_coverage``'s
    result), with the 95 % band."""
    from matplotlib.figure import Figure

    from calibration._report import atomic_savefig

    shapes, names = list(result["shapes"]), result["params"]
    fig = Figure(figsize=(4.2 * len(shapes), 4.2), layout="constrained")
    axes = fig.subplots(1, len(shapes), sharey=True)
    for ax, shape in zip(np.atleast_1d(axes), shapes):
        runs = result["shapes"][shape]["runs"]
        x = np.arange(len(names))
        for dx, key, label in ((-0.15, "z_first_fit", "first fit (law's linear peak)"),
                               (0.15, "z_total", "refit in the best-supported form")):
            z = np.array([[r_[key][n] for n in names] for r_ in runs])
            ax.plot(np.repeat(x + dx, len(runs)), z.T.ravel(), "o", ms=4, alpha=0.7,
                    label=label)
        ax.axhspan(-result["z"], result["z"], color="0.9", zorder=0, label="95 % interval")
        ax.set_xticks(x, names)
        forms = ", ".join(f"{f} {n}" for f, n in result["shapes"][shape]["best_form_counts"]
                          .items())
        ax.set_title(f"rig peak: {shape} (named: {forms})", fontsize=10)
    np.atleast_1d(axes)[0].set_ylabel("error / total standard error [-]")
    np.atleast_1d(axes)[0].legend(fontsize=8, loc="lower left")
    atomic_savefig(fig, path)


OFFSET_STUDY_SEEDS = 20000  # first noise seed of --offset-coverage
OFFSET_STUDY_PRE_TRIGGER_S = (0.05, 0.18)  # the rig's default, and 3.6 times as long


RATE_STUDY_RATES_HZ = (5000.0, 20000.0)  # the rig's rate, and 4 times it
RATE_STUDY_CASE = "physical crush peak (+10 %, 1 mm), fitted with the peak"
RATE_STUDY_SEEDS = 1000  # first noise seed of --sample-rate-study (the coverage study's too)
RATE_STUDY_BLOCK = 40  # seeds per block of the study's per-block figures


def sample_rate_study(n_seeds: int, height: float = 0.2) -> dict:
    """The coverage case ``RATE_STUDY_CASE`` (the law's own peak in the truth and the model:
    representable data) over ``n_seeds`` noise seeds at each of ``RATE_STUDY_RATES_HZ``: per
    parameter, the reported (total) interval's coverage and the values' scatter over the
    seeds against their mean reported standard error (1 where the error is right)."""
    truth = vr.truth_vehicle()
    names = cal.DEFAULT_PARAMS
    p_true = get_values(truth, names)
    kw, params, _ = _coverage_case(COVERAGE_CASES[RATE_STUDY_CASE], truth, names)
    n = len(names)
    first = RATE_STUDY_SEEDS
    out = dict(case=RATE_STUDY_CASE, params=list(names), drop_height_m=height, z=Z95,
               seeds=[first, first + n_seeds - 1], rates={})
    for rate in RATE_STUDY_RATES_HZ:
        vals, se = [], []
        for seed in range(first, first + n_seeds):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r, _ = _fit([vr.drop_test(height, seed=seed, sample_rate_Hz=rate, **kw)],
                            params=params)
            vals.append(r.values[:n])
            se.append(r.std_errors_total[:n])
        vals, se = np.array(vals), np.array(se)
        inside = np.abs(vals - p_true) <= Z95 * se

        def summary(sel):
            return dict(coverage=dict(zip(names, inside[sel].mean(axis=0).tolist())),
                        scatter_over_se=dict(zip(names, (vals[sel].std(axis=0, ddof=1)
                                                         / se[sel].mean(axis=0)).tolist())),
                        bias_over_scatter=dict(zip(names, ((vals[sel] - p_true).mean(axis=0)
                                                           / vals[sel].std(axis=0, ddof=1))
                                                   .tolist())))
        # the same figures per block of RATE_STUDY_BLOCK seeds: how far a block's own
        # coverage and scatter wander from the whole study's (their sampling error)
        blocks = [dict(seeds=[first + b, first + b + RATE_STUDY_BLOCK - 1],
                       **summary(slice(b, b + RATE_STUDY_BLOCK)))
                  for b in range(0, n_seeds - RATE_STUDY_BLOCK + 1, RATE_STUDY_BLOCK)]
        out["rates"][f"{rate:g}"] = dict(
            sample_rate_Hz=rate, **summary(slice(None)), blocks=blocks,
            mean_se_rel=dict(zip(names, (se.mean(axis=0) / p_true).tolist())))
        print(f"[sample rate] {rate:g} Hz: k_b1 coverage {inside[:, 3].mean():.2f}, scatter / "
              f"SE {vals[:, 3].std(ddof=1) / se[:, 3].mean():.2f}", flush=True)
    return out


def offset_coverage(n_seeds: int, height: float = 0.2) -> dict:
    """Coverage of the classical 95 % intervals on representable rig data (no peak) over
    ``n_seeds`` noise seeds, with the record starting ``OFFSET_STUDY_PRE_TRIGGER_S`` before
    touchdown: the sensors' offsets are the means of that free fall, and their error (the
    noise over the square root of its samples) is part of the reported standard errors
    (``calibration._fit._uncertainty``); a short and a long free fall check that it is
    counted right."""
    truth = vr.truth_vehicle()
    names = cal.DEFAULT_PARAMS
    p_true = get_values(truth, names)
    seeds = list(range(OFFSET_STUDY_SEEDS, OFFSET_STUDY_SEEDS + n_seeds))
    out = dict(params=list(names), drop_height_m=height, seeds=[seeds[0], seeds[-1]], z=Z95,
               cases={})
    for pre in OFFSET_STUDY_PRE_TRIGGER_S:
        err, se = [], []
        for seed in seeds:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r, _ = _fit([vr.drop_test(height, crush_peak=0.0, seed=seed, pre_trigger_s=pre)])
            err.append(r.values - p_true)
            se.append(r.std_errors)
        err, se = np.array(err), np.array(se)
        inside = np.abs(err) <= Z95 * se
        out["cases"][f"{pre:g}"] = dict(
            pre_trigger_s=pre, free_fall_samples=int(round(pre * vr.SAMPLE_RATE_HZ)),
            coverage=dict(zip(names, inside.mean(axis=0).tolist())),
            coverage_all=float(inside.mean()),
            spread_over_se=dict(zip(names, (err.std(axis=0, ddof=1)
                                            / se.mean(axis=0)).tolist())))
        print(f"[offset coverage] pre-trigger {pre:g} s: {inside.mean():.3f}", flush=True)
    return out


PEAK_RECOVERY_SEEDS = 3000  # first noise seed of --peak-recovery (none of the other studies')


def peak_recovery(n_seeds: int, height: float = 0.2, peak_mode: str = "physical",
                  model: str = "law", peak_site: str = HONEYCOMB) -> dict:
    """The crush-peak model (default parameters + peak1, L_peak1) on rig records of every
    ``vr.PEAK_SHAPES`` at ``height``, over ``n_seeds`` noise seeds each: per parameter the
    error against the truth and z = error / SE (HAC, total: with the channel spread, and
    classical), the shifts when one channel is left out, and the same fit on the noise-free
    record (what the model converges to on that shape: its bias, no scatter). ``peak_mode``:
    the rig's (``vr.PEAK_MODES``): ``physical``, the shape in the truth's honeycomb (every
    channel carries it), or ``sensor``, the force channels multiplied by it. ``model``:
    ``law``, the law's linear peak fitted (peak1, L_peak1); ``law_rise``, with its rise
    length too (L_rise1: the peak builds up over a crush length); ``true_shape``, the default
    parameters fitted with the rig's own peak table in the model (physical mode only: the data
    are then representable, which tells the law's shape from everything else). ``peak_site``:
    ``fit``'s, where the fitted peak sits (``forces``: on the force channels alone)."""
    truth = vr.truth_vehicle()
    base = cal.DEFAULT_PARAMS
    names = base + {"law": ("peak1", "L_peak1"), "law_rise": ("peak1", "L_peak1", "L_rise1"),
                    "true_shape": ()}[model]
    p_true = get_values(truth, base)
    n = len(base)
    seeds = list(range(PEAK_RECOVERY_SEEDS, PEAK_RECOVERY_SEEDS + n_seeds))
    rig = dict(peak_mode=peak_mode)
    if peak_mode == "physical":
        rig.update(peak_length_m=vr.PHYSICAL_PEAK_LENGTH_M)
    out = dict(params=list(names), drop_height_m=height, seeds=seeds, rig=rig, model=model,
               peak_site=peak_site, shapes={},
               targets=dict(rel_error=0.03, z=2.0, checked=list(RECOVERY_CHECKED)))

    def row(r, wall):
        v = r.values[:n]
        return dict(wall_s=wall, values=dict(zip(r.names, r.values.tolist())),
                    rel_error=dict(zip(base, (v / p_true - 1).tolist())),
                    z_hac=dict(zip(base, ((v - p_true) / r.std_errors_hac[:n]).tolist())),
                    z_total=dict(zip(base, ((v - p_true) / r.std_errors_total[:n]).tolist())),
                    se_total_rel=dict(zip(base, (r.std_errors_total[:n] / p_true).tolist())),
                    z_classical=dict(zip(base, ((v - p_true) / r.std_errors[:n]).tolist())),
                    sigma2=r.sigma2, rho1=r.diagnostics["residual_lag1_autocorr"],
                    misfit_warned=bool(r.diagnostics["misfit"]),
                    at_bound=r.diagnostics["at_bound"],
                    channel_shift_rel={c: None if d is None else
                                       {p: d[p] / float(t) for p, t in zip(base, p_true)}
                                       for c, d in r.diagnostics["channel_spread"].items()},
                    peak_location=r.diagnostics.get("peak_location"),
                    peak_site_check=r.diagnostics.get("peak_site_check"),
                    **_recovery_form(r, base, p_true))

    for shape in vr.PEAK_SHAPES:
        clean = _clean_drop(height, peak_shape=shape, **rig)
        kw = dict(params=names)
        if peak_site != HONEYCOMB:
            kw.update(peak_site=peak_site)
        if model == "true_shape":  # the rig's table in the model; started at the truth (at
            # the nominal k the folds table's fall is steeper than the rule's k / 2): this
            # measures where the optimum lies, not the convergence
            kw.update(vehicle=vr.physical_peak(truth, vr.CRUSH_PEAK, shape))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cal.MisfitWarning)
            r, w = _fit([clean], **kw)
            rec = dict(noise_free=row(r, w), runs=[])
            for seed in seeds:
                r, w = _fit([vr.drop_test(height, peak_shape=shape, seed=seed, **rig)], **kw)
                rec["runs"].append(dict(seed=seed, **row(r, w)))
                print(f"[peak recovery] {shape}, seed {seed}: {w:.1f} s, "
                      + ", ".join(f"{k} {e:+.2%} ({rec['runs'][-1]['z_hac'][k]:+.1f})"
                                  for k, e in rec["runs"][-1]["rel_error"].items()),
                      flush=True)
        rec.update(peak_recovery_summary(rec))
        out["shapes"][shape] = rec
    return out


RECOVERY_CHECKED = ("k", "gamma", "D_b", "k_b1", "F1")  # the five


def noise_response(n_seeds: int, height: float = 0.2, shape: str = "exp") -> dict:
    """How far each sensor-side record's noise alone moves the values of the fit with the peak
    on the force channels, in units of their standard errors: at the fit of the noise-free
    record (the rig's sensor mode, ``shape``; weighted by the rig's noise), the least-squares
    response pinv(J) (y_noisy - y_clean) / sigma of each parameter to the noise of the
    peak-recovery study's seeds, over the standard error from the same J (with the offsets'
    error: each channel's offset is the mean of its free fall). No model error enters: this
    is the noise's share of each record's error, which lies beyond 2 on about 1 record in 20
    whatever the model."""
    names = cal.DEFAULT_PARAMS + ("peak1", "L_peak1")
    base = cal.DEFAULT_PARAMS
    rig = dict(peak_mode="sensor", peak_shape=shape)
    clean = _clean_drop(height, **rig)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cal.MisfitWarning)
        res, _ = _fit([clean], params=names, peak_site=FORCES, model_form=False)
    prob = res.problem.robust(None)
    theta = np.asarray(res.theta)
    _, jac, _ = prob.residuals_and_jacobian(theta)
    act = prob.mask.ravel() > 0
    # d values / d (noise-weighted data) of the default parameters: (parameters, samples)
    rows = (prob.transform_jacobian(theta) @ np.linalg.pinv(jac[act])[:prob.n_z])[:len(base)]
    chan = np.broadcast_to(np.arange(prob.data.shape[1])[None, :, None],
                           prob.data.shape).ravel()[act]
    offsets = sum(np.sum(rows[:, chan == j], axis=1) ** 2
                  for j in range(prob.data.shape[1])) / clean.offset_samples
    sd = np.sqrt(np.sum(rows ** 2, axis=1) + offsets)
    sel = prob._in_window(clean)
    seeds = list(range(PEAK_RECOVERY_SEEDS, PEAK_RECOVERY_SEEDS + n_seeds))
    z = []
    for seed in seeds:
        noisy = vr.drop_test(height, seed=seed, **rig)
        eps = np.zeros(prob.data.shape)
        for j, c in enumerate(prob.channels):
            eps[0, j, :int(sel.sum())] = (noisy.corrected[c][sel]
                                          - clean.corrected[c][sel]) / vr.NOISE[c]
        z.append(rows @ eps.ravel()[act] / sd)
        print(f"[noise response] {shape}, seed {seed}: "
              + ", ".join(f"{n} {v:+.2f}" for n, v in zip(base, z[-1])), flush=True)
    z = np.array(z)
    values = res.values[:len(base)]
    return dict(shape=shape, drop_height_m=height, rig=rig, params=list(base), seeds=seeds,
                values_noise_free=dict(zip(base, values.tolist())),
                se_rel=dict(zip(base, (sd / values).tolist())),
                z={n: z[:, i].tolist() for i, n in enumerate(base)},
                rms_z=dict(zip(base, np.sqrt(np.mean(z ** 2, axis=0)).tolist())),
                beyond_2=dict(zip(base, np.sum(np.abs(z) > 2.0, axis=0).tolist())))


def _recovery_form(r, base, p_true) -> dict:
    """The peak-shape term's part of a recovery row: the best-supported form, its values'
    error against the truth, the z against the total error without the term."""
    row = _form_row(r, len(base))
    if not row["model_form"]:
        return dict(model_form=False)
    v = r.values[:len(base)]
    return dict(model_form=True, best_form=row["best_form"],
                best_form_shape=row["best_form_shape"], forms=row["forms"], n_obs=row["n_obs"],
                plausible_forms=row["plausible_forms"], failed_forms=row["failed_forms"],
                best_form_rel_error=dict(zip(base, (np.array(row["best_form_values"])
                                                    / p_true - 1).tolist())),
                z_total_without_form=dict(zip(base, ((v - p_true) / np.array(
                    row["se_total_without_form"])).tolist())),
                form_term_rel=dict(zip(base, (np.array(row["form_term"]) / p_true).tolist())))


def peak_recovery_summary(rec: dict) -> dict:
    """Per shape: how many seeds meet the issue's two targets on the five checked parameters
    (each within 3 % of the truth; the truth within 2 standard errors of each, HAC and
    total), and the
    errors' mean over the seeds with its standard error (the model's bias on this shape: the
    noise averages out) against the mean HAC standard error (the scatter the fit reports)."""
    runs = rec["runs"]
    err = np.array([[r_["rel_error"][p] for p in RECOVERY_CHECKED] for r_ in runs])
    z = np.array([[r_["z_hac"][p] for p in RECOVERY_CHECKED] for r_ in runs])
    zt = np.array([[r_["z_total"][p] for p in RECOVERY_CHECKED] for r_ in runs])
    se = err / z  # relative HAC standard error of each fit
    return dict(
        seeds_within_3pct=int(np.sum(np.all(np.abs(err) <= 0.03, axis=1))),
        seeds_within_2se=int(np.sum(np.all(np.abs(z) <= 2.0, axis=1))),
        seeds_within_2se_total=int(np.sum(np.all(np.abs(zt) <= 2.0, axis=1))),
        inside_2se_per_param=dict(zip(RECOVERY_CHECKED,
                                      np.mean(np.abs(z) <= 2.0, axis=0).tolist())),
        inside_2se_total_per_param=dict(zip(RECOVERY_CHECKED,
                                            np.mean(np.abs(zt) <= 2.0, axis=0).tolist())),
        mean_se_total_rel=dict(zip(RECOVERY_CHECKED, np.abs(err / zt).mean(axis=0).tolist())),
        worst_rel_error=dict(zip(RECOVERY_CHECKED, err[np.argmax(np.abs(err), axis=0),
                                                       range(err.shape[1])].tolist())),
        mean_rel_error=dict(zip(RECOVERY_CHECKED, err.mean(axis=0).tolist())),
        sem_rel_error=dict(zip(RECOVERY_CHECKED,
                               (err.std(axis=0, ddof=1) / np.sqrt(len(runs))).tolist())),
        spread_rel=dict(zip(RECOVERY_CHECKED, err.std(axis=0, ddof=1).tolist())),
        mean_se_hac_rel=dict(zip(RECOVERY_CHECKED, np.abs(se).mean(axis=0).tolist())),
        **_recovery_form_summary(runs), **_peak_location_summary(runs))


def _peak_location_summary(runs) -> dict:
    """How many fits named the peak the force channels' only (``peak_location``), and the
    range of the excess the motion-only step kept and of its z."""
    locs = [r_.get("peak_location") for r_ in runs]
    if not locs or any(loc is None for loc in locs):
        return {}
    out = dict(seeds_peak_force_only=int(sum(loc["force_only"] for loc in locs)))
    for key, field in (("peak_excess_kept_range", "excess_kept"), ("peak_z_range", "z")):
        got = [loc[field] for loc in locs if loc[field] is not None]
        if got:
            out[key] = [min(got), max(got)]
    return out


def _recovery_form_summary(runs) -> dict:
    """Seeds meeting the targets with the best-supported form's values (3 %), and with the
    total error without the peak-shape term (2 SE); which forms were best."""
    if not all(r_.get("model_form") for r_ in runs):
        return {}
    err = np.array([[r_["best_form_rel_error"][p] for p in RECOVERY_CHECKED] for r_ in runs])
    z0 = np.array([[r_["z_total_without_form"][p] for p in RECOVERY_CHECKED] for r_ in runs])
    return dict(
        best_form_counts={f: sum(r_["best_form"] == f for r_ in runs)
                          for f in dict.fromkeys(r_["best_form"] for r_ in runs)},
        seeds_within_3pct_best_form=int(np.sum(np.all(np.abs(err) <= 0.03, axis=1))),
        mean_rel_error_best_form=dict(zip(RECOVERY_CHECKED, err.mean(axis=0).tolist())),
        seeds_within_2se_total_without_form=int(np.sum(np.all(np.abs(z0) <= 2.0, axis=1))))


FIT_TIME_CASES = {
    "default 6 parameters, bundled 0.2 m drop": dict(data="bundled", heights=(0.2,)),
    "with the crush peak (8 parameters), rig 0.2 m, exp peak": dict(
        data="rig", heights=(0.2,), peak=True, rig=dict(peak_shape="exp", seed=200)),
    "with the crush peak (8 parameters), rig 0.2 m, folds peak": dict(
        data="rig", heights=(0.2,), peak=True, rig=dict(peak_shape="folds", seed=200)),
    "with the crush peak, joint 0.15 + 0.30 m (bump peak)": dict(
        data="rig", heights=(0.15, 0.3), peak=True, rig=dict(seed=300)),
    "lab record: 4 legs, CFC 600, from release (bundled)": dict(data="lab", heights=(0.2,)),
    "the crush peak on the force channels (--peak-site forces), bundled 0.2 m drop": dict(
        data="bundled", heights=(0.2,), peak=True, peak_site=FORCES),
}


def one_fit(case: str) -> dict:
    """One cold fit of ``FIT_TIME_CASES[case]`` in this (fresh) process: wall time with
    compilation, the process's CPU time (all threads: on a shared machine the wall time grows
    with the other jobs, the CPU time much less), the optimiser's work (Jacobians, forward
    runs, iterations, starts) and the recovery of the truth (value / truth - 1 and z against
    the HAC standard error)."""
    from calibration import _problem

    spec = FIT_TIME_CASES[case]
    names = cal.DEFAULT_PARAMS + (("peak1", "L_peak1") if spec.get("peak") else ())
    if spec["data"] == "bundled":
        drops = [cal.load_drop_test(DATA / f"drop_h{h:.2f}m.toml") for h in spec["heights"]]
    elif spec["data"] == "lab":
        drops = [cal.load_drop_test(DATA / "drop_h0.20m_lab.toml")]
    else:
        drops = [vr.drop_test(h, **spec["rig"]) for h in spec["heights"]]
    count = dict(jacobians=0, forward=0)
    jac0, res0 = (_problem.CalibrationProblem.residuals_and_jacobian,
                  _problem.CalibrationProblem.residuals)

    def jac(self, th):
        count["jacobians"] += 1
        return jac0(self, th)

    def res(self, th):
        count["forward"] += 1
        return res0(self, th)

    _problem.CalibrationProblem.residuals_and_jacobian = jac
    _problem.CalibrationProblem.residuals = res
    load = os.getloadavg()[0]
    cpu0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cal.MisfitWarning)
        r, wall = _fit(drops, params=names, peak_site=spec.get("peak_site", HONEYCOMB))
    cpu = time.process_time() - cpu0  # all of the process's threads
    truth = vr.truth_vehicle()
    p_true = get_values(truth, cal.DEFAULT_PARAMS)
    n = len(cal.DEFAULT_PARAMS)
    pm = r.diagnostics.get("peak_model_term")
    return dict(case=case, wall_s=wall, cpu_s=cpu, load_average_1min_at_start=load, **count,
                misfit_warned=bool(r.diagnostics["misfit"]),
                peak_model_term_fit_s=pm["wall_s"] if pm is not None and pm["added"] else None,
                iterations=sum(s["iterations"] for s in r.stages),
                starts_tried=r.settings["multistart"]["n_starts_tried"],
                stages=[{k: s[k] for k in ("stage", "iterations", "status", "wall_s")}
                        for s in r.stages],
                values=dict(zip(r.names, r.values.tolist())),
                rel_error=dict(zip(cal.DEFAULT_PARAMS, (r.values[:n] / p_true - 1).tolist())),
                z_hac=dict(zip(cal.DEFAULT_PARAMS, ((r.values[:n] - p_true)
                                                    / r.std_errors_hac[:n]).tolist())))


def fit_time(quick: bool = False) -> dict:
    """Every ``FIT_TIME_CASES`` fit cold, each in a fresh process (so the compilation counts),
    one after the other."""
    import subprocess

    cases = list(FIT_TIME_CASES)[:2] if quick else list(FIT_TIME_CASES)

    def git(*a):
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout

    # the code that was timed: the commit, and the library files that differ from it
    out = dict(target_s=TARGETS["fit_s"], cpus=os.cpu_count(), commit=git("rev-parse",
                                                                          "HEAD").strip(),
               modified=[line[3:] for line in git("status", "--porcelain", "--", "jaxland",
                                                  "calibration", "pyproject.toml").splitlines()],
               runs=[])
    for case in cases:
        proc = subprocess.run([sys.executable, __file__, "--one-fit", case], check=True,
                              capture_output=True, text=True)
        run = json.loads(proc.stdout.strip().splitlines()[-1])
        out["runs"].append(run)
        load = run["load_average_1min_at_start"]
        print(f"[fit time] {case}: {run['wall_s']:.1f} s (load {load:.1f}; CPU "
              f"{run['cpu_s']:.1f} s), "
              f"{run['jacobians']} Jacobians, {run['forward']} forward runs, "
              + ", ".join(f"{k} {v:+.2%}" for k, v in run["rel_error"].items()), flush=True)
    return out


def main_coverage(args) -> int:
    if args.coverage_summary and args.coverage_pseudo_truth:
        raise SystemExit("--coverage-summary and --coverage-pseudo-truth: give one (the "
                         "second recomputes the summaries too)")
    if args.coverage_summary or args.coverage_pseudo_truth:
        # the stored runs' summaries recomputed (no fits); with --coverage-pseudo-truth each
        # case's pseudo-truth refitted first (not its seeds)
        path = Path(args.out) / "bench_fit.json"
        data = json.loads(path.read_text())
        cov_ = data["coverage"]
        truth, names = vr.truth_vehicle(), tuple(cov_["params"])
        for label, case in cov_["cases"].items():
            if args.coverage_pseudo_truth:
                p = _pseudo_truth(cov_["drop_height_m"],
                                  *_coverage_case(case["rig"], truth, names), len(names))
                case["pseudo_truth"] = dict(zip(names, p.tolist()))
            case.update(coverage_summary(case, cov_["params"]))
            if args.coverage_pseudo_truth:
                print(f"[coverage] {label}: pseudo-truth "
                      + ", ".join(f"{n} {e:+.2%}" for n, e in
                                  case["bias_of_pseudo_truth_rel"].items()), flush=True)
        from calibration._report import atomic_write_text

        atomic_write_text(path, json.dumps(data, indent=2) + "\n")
        print(f"rewrote the coverage {'pseudo-truths and ' if args.coverage_pseudo_truth else ''}"
              f"summaries of {path}")
        return 0
    key = ("peak_model" if args.peak_model else "fit_time" if args.fit_time
           else "best_form_prediction" if args.best_form_prediction
           else "best_form_coverage" if args.best_form_coverage
           else "peak_recovery" if args.peak_recovery
           else "offset_coverage" if args.offset_coverage
           else "noise_response" if args.noise_response
           else "sample_rate_study" if args.sample_rate_study else "coverage")
    if args.sample_rate_study:
        result = sample_rate_study(3 if args.quick else args.sample_rate_study)
    elif args.offset_coverage:
        result = offset_coverage(5 if args.quick else args.offset_coverage)
    elif args.noise_response:
        result = noise_response(3 if args.quick else args.noise_response)
    elif args.peak_recovery:
        result = peak_recovery(2 if args.quick else args.peak_recovery,
                               peak_mode=args.rig_peak_mode, model=args.peak_model_kind,
                               peak_site=args.peak_site)
        if args.rig_peak_mode != "physical":
            key = f"peak_recovery_{args.rig_peak_mode}"
        if args.peak_model_kind != "law":
            key = f"{key}_{args.peak_model_kind}"
        if args.peak_site != HONEYCOMB:
            key = f"{key}_site_{args.peak_site}"
    elif args.peak_model:
        result = peak_model_study(args.quick)
    elif args.best_form_prediction:
        result = best_form_prediction(args.quick)
    elif args.best_form_coverage:
        result = best_form_coverage(2 if args.quick else args.best_form_coverage)
    elif args.fit_time:
        result = fit_time(args.quick)
    else:
        result = coverage(3 if args.quick else args.coverage, only=args.coverage_cases)
    if args.quick:  # never overwrite the committed results
        path = ROOT / "out" / "bench_fit_quick.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        data = {key: result}
    else:
        path = Path(args.out) / "bench_fit.json"
        data = json.loads(path.read_text()) if path.exists() else {}
        if key == "coverage" and args.coverage_cases and "coverage" in data:
            if data["coverage"]["n_seeds"] != result["n_seeds"]:
                raise SystemExit("--coverage-cases: the stored cases have "
                                 f"{data['coverage']['n_seeds']} seeds, not {result['n_seeds']}")
            cases = dict(data["coverage"]["cases"], **result["cases"])  # kept in their order
            result["cases"] = {k: cases[k] for k in COVERAGE_CASES if k in cases}
        data[key] = result
    from calibration._report import atomic_write_text

    atomic_write_text(path, json.dumps(data, indent=2) + "\n")
    print(f"wrote {path}")
    if key == "best_form_coverage":
        fig = path.with_name(path.stem + "_best_form_coverage.png")
        plot_best_form_coverage(result, fig)
        print(f"wrote {fig}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--with-lbfgs", action="store_true",
                    help="also time optax.lbfgs on the default variant's fit (minutes)")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--replot", action="store_true", help="only redraw the plot from the JSON")
    ap.add_argument("--coverage", type=int, default=0, metavar="N",
                    help="only the interval-coverage study over N noise seeds (into "
                         "bench_fit.json's 'coverage')")
    ap.add_argument("--coverage-cases", metavar="TEXT", default=None,
                    help="with --coverage: only the cases whose label contains TEXT, merged "
                         "into the stored coverage (same seed count)")
    ap.add_argument("--quick", action="store_true",
                    help="with --coverage: 3 seeds, written to out/bench_fit_quick.json")
    ap.add_argument("--coverage-summary", action="store_true",
                    help="recompute the coverage summaries from the runs stored in "
                         "bench_fit.json (no fits)")
    ap.add_argument("--coverage-pseudo-truth", action="store_true",
                    help="refit each stored coverage case's pseudo-truth (the noise-free "
                         "record weighted by the rig's noise) and recompute its summary; the "
                         "seeds' fits are kept")
    ap.add_argument("--peak-model", action="store_true",
                    help="only the crush-peak model study (into bench_fit.json's "
                         "'peak_model'): rig peak shapes unlike the law's, prediction, joint fit")
    ap.add_argument("--best-form-prediction", action="store_true",
                    help="only the physical crush peak fitted in its best-supported form: "
                         "recovery, prediction of the other heights, joint fit (into "
                         "bench_fit.json's 'best_form_prediction')")
    ap.add_argument("--best-form-coverage", type=int, default=0, metavar="N",
                    help="the refit in the best-supported form on every rig peak shape over N "
                         "noise seeds: coverage of its own total interval (bench_fit.json's "
                         "'best_form_coverage')")
    ap.add_argument("--fit-time", action="store_true",
                    help="only the cold fit times (FIT_TIME_CASES, each in a fresh process; into"
                         " bench_fit.json's 'fit_time')")
    ap.add_argument("--peak-recovery", type=int, default=0, metavar="N",
                    help="fit the crush-peak model to every rig peak shape over N noise seeds"
                         " (bench_fit.json's 'peak_recovery')")
    ap.add_argument("--rig-peak-mode", choices=vr.PEAK_MODES, default="physical",
                    help="with --peak-recovery: where the rig's peak acts (physical: in the "
                         "truth's honeycomb, into 'peak_recovery'; sensor: on the force "
                         "channels only, into 'peak_recovery_sensor')")
    ap.add_argument("--peak-model-kind", choices=("law", "law_rise", "true_shape"),
                    default="law",
                    help="with --peak-recovery: fit the law's linear peak (peak1, L_peak1), "
                         "with its rise length (law_rise: + L_rise1), or the default "
                         "parameters with the rig's own peak table in the model (true_shape); "
                         "into 'peak_recovery[_KIND]'")
    ap.add_argument("--peak-site", choices=PEAK_SITES, default=HONEYCOMB,
                    help="with --peak-recovery: where the fitted peak sits (fit's peak_site; "
                         "forces: on the force channels alone, into "
                         "'peak_recovery[_MODE][_KIND]_site_forces')")
    ap.add_argument("--offset-coverage", type=int, default=0, metavar="N",
                    help="coverage of the classical intervals on representable data over N "
                         "seeds, with a short and a long free fall before touchdown (the "
                         "sensors' offsets; bench_fit.json's 'offset_coverage')")
    ap.add_argument("--sample-rate-study", type=int, default=0, metavar="N",
                    help="the law's own peak fitted with it (representable data) over N seeds "
                         "at 5 and 20 kHz: each parameter's coverage and scatter over its "
                         "reported error (bench_fit.json's 'sample_rate_study')")
    ap.add_argument("--noise-response", type=int, default=0, metavar="N",
                    help="how far the noise alone of N sensor-side records (the peak-recovery "
                         "seeds, exp shape) moves the values of the fit on the force channels, "
                         "in standard errors (bench_fit.json's 'noise_response')")
    ap.add_argument("--one-fit", metavar="CASE", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one_fit:
        print(json.dumps(one_fit(args.one_fit)))
        return 0
    if args.coverage or args.quick or args.coverage_summary or args.coverage_pseudo_truth or \
            args.peak_model or args.best_form_prediction or args.best_form_coverage or \
            args.fit_time or args.peak_recovery or args.offset_coverage or \
            args.sample_rate_study or args.noise_response:
        return main_coverage(args)
    if args.replot:
        path = Path(args.out) / "bench_fit.json"
        _plot(json.loads(path.read_text()), path.with_suffix(".png"))
        return 0
    labels = [v.strip() for v in args.variants.split(",") if v.strip()]
    for v in labels:
        if v not in VARIANTS:
            raise SystemExit(f"--variants: unknown variant {v!r}; known: {', '.join(VARIANTS)}")
    truth = jl.load_vehicle(DATA / "truth_vehicle.toml")
    drops = {h: cal.load_drop_test(DATA / f"drop_h{h:.2f}m.toml") for h in vr.HEIGHTS_M}
    fit_drop = drops[0.2]
    names = cal.DEFAULT_PARAMS
    p_true = get_values(truth, names)
    clean = vr.drop_test(0.2, noise=None, stroke_offset_m=0.0, crush_peak=0.0)
    out = dict(
        data="data/synthetic/drop_h0.20m (SYNTHETIC: 1.2 s at 5 kHz, noise, stroke offset, "
             "+20 % crush peak); noise-free: the rig's 0.2 m drop without noise, offset or "
             "crush peak",
        targets=TARGETS, default_integrator=dict(
            integrator=cal.INTEGRATOR, smoothing_m=cal.SMOOTHING[cal.INTEGRATOR][0],
            smoothing_N=cal.SMOOTHING[cal.INTEGRATOR][1]),
        machine=dict(platform=platform.platform(), cpus=os.cpu_count(), jax=jax.__version__,
                     backend=jax.default_backend(),
                     load_average_1min_at_start=os.getloadavg()[0]),
        variants={v: dict(options=VARIANTS[v]) for v in labels})
    res_of = {}

    # 1. the fit from the nominal (paper) vehicle: every variant cold first, then warm
    for v in labels:
        res, cold = _fit([fit_drop], **VARIANTS[v])
        res_of[v] = res
        out["variants"][v]["fit_from_nominal"] = dict(cold=_summary(res, cold, truth))
        print(f"[{v}] fit from nominal: cold {cold:.1f} s", flush=True)
    for v in labels:
        runs = [_fit([fit_drop], **VARIANTS[v]) for _ in range(2)]
        res2, warm = min(runs, key=lambda rw: rw[1])
        out["variants"][v]["fit_from_nominal"]["warm"] = _summary(res2, warm, truth)
        print(f"[{v}] fit from nominal: warm {warm:.1f} s", flush=True)

    for v in labels:
        o, opts, res = out["variants"][v], VARIANTS[v], res_of[v]
        # 2. prediction of the other heights with the fitted vehicle
        preds = {}
        for h, d in drops.items():
            p = cal.predict(res.vehicle, d)
            ref = cal.predict(truth, d)  # the truth itself against the data: the floor
            preds[f"{h:.2f}"] = dict(
                fitted={k: v_["rel_error"] for k, v_ in p.metrics.items()},
                truth_model={k: v_["rel_error"] for k, v_ in ref.metrics.items()})
        o["prediction"] = preds

        # 3. convergence from the starts on the crush-peak data (same optimum as from nominal)
        conv = {}
        for label, f in STARTS.items():
            r, w = _fit([fit_drop], start=dict(zip(names, p_true * np.array(f))),
                        vehicle=jl.paper_vehicle(), **opts)
            s = _summary(r, w, truth)
            s["max_rel_diff_from_nominal_fit"] = float(np.max(np.abs(r.values / res.values
                                                                      - 1)))
            s["converged"] = s["max_rel_diff_from_nominal_fit"] <= SAME_OPTIMUM_REL
            conv[label] = s
            print(f"[{v}] crush-peak data, start {label}: {w:.1f} s, "
                  f"{s['max_rel_diff_from_nominal_fit']:.2e} from the nominal fit", flush=True)
        o["convergence"] = conv

        # 4. noise-free data: recovery from every start
        rec = {}
        for label, f in STARTS.items():
            r, w = _fit([clean], start=dict(zip(names, p_true * np.array(f))),
                        vehicle=jl.paper_vehicle(), **opts)
            s = _summary(r, w, truth)
            s["max_abs_rel_error"] = float(max(abs(x) for x in s["rel_error"].values()))
            s["converged"] = s["max_abs_rel_error"] <= TARGETS["clean_recovery_rel"]
            rec[label] = s
            print(f"[{v}] noise-free, start {label}: {w:.1f} s, max |rel err| "
                  f"{s['max_abs_rel_error']:.3%}", flush=True)
        o["clean_recovery"] = rec
        o["clean_recovery_from_2x"] = rec["2x off"]

        # 5. joint fit of two heights, predict the third
        r, w = _fit([drops[0.15], drops[0.3]], **opts)
        p = cal.predict(r.vehicle, drops[0.2])
        o["joint_0.15_0.30"] = {"fit": _summary(r, w, truth),
                                "predict_0.20": {k: v_["rel_error"]
                                                 for k, v_ in p.metrics.items()}}

        # 6. AD against FD of the calibration loss (the bundled noisy crush-peak drop)
        o["ad_vs_fd"] = ad_vs_fd(fit_drop, opts, res.vehicle)
        print(f"[{v}] AD vs FD: worst robust {o['ad_vs_fd']['worst_robust']:.1e}",
              {k: f"{x:.1e}" for k, x in o["ad_vs_fd"]["worst_robust_per_param"].items()},
              flush=True)

        fn = o["fit_from_nominal"]
        o["summary"] = dict(
            fit_cold_s=fn["cold"]["wall_s"], fit_warm_s=fn["warm"]["wall_s"],
            crush_peak_rel_error=fn["cold"]["rel_error"],
            clean_worst_rel_error={n: max(abs(s["rel_error"][n]) for s in rec.values())
                                   for n in names},
            starts_converged_crush_peak=f"{sum(s['converged'] for s in conv.values())}"
                                        f"/{len(conv)}",
            starts_recovered_noise_free=f"{sum(s['converged'] for s in rec.values())}"
                                        f"/{len(rec)}",
            ad_fd_worst_robust_per_param=o["ad_vs_fd"]["worst_robust_per_param"],
            meets_targets=bool(fn["cold"]["wall_s"] <= TARGETS["fit_s"]
                               and all(s["converged"] for s in rec.values())
                               and all(s["converged"] for s in conv.values())))
        print(f"[{v}] summary:", json.dumps(o["summary"]), flush=True)

    if args.with_lbfgs:
        v = cal.INTEGRATOR if cal.INTEGRATOR in labels else labels[0]
        r, w = _fit([fit_drop], method="lbfgs", max_iter=300, **VARIANTS[v])
        out["variants"][v]["lbfgs_from_nominal"] = _summary(r, w, truth)
        print(f"[{v}] lbfgs: {w:.1f} s", flush=True)

    out["machine"]["load_average_1min_at_end"] = os.getloadavg()[0]
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    from calibration._report import atomic_write_text

    old = out_dir / "bench_fit.json"  # the other studies' results are kept
    if old.exists():
        for key, val in json.loads(old.read_text()).items():
            if key in ("coverage", "peak_model", "fit_time", "peak_recovery"):
                out.setdefault(key, val)
    atomic_write_text(out_dir / "bench_fit.json", json.dumps(out, indent=2) + "\n")
    _plot(out, out_dir / "bench_fit.png")
    print(f"wrote {out_dir}/bench_fit.json and bench_fit.png")
    return 0


def _plot(out, path):
    from matplotlib.figure import Figure

    from calibration._report import atomic_savefig

    variants = out["variants"]
    labels = list(variants)
    default = out["default_integrator"]["integrator"]
    main_v = next((v for v in labels if VARIANTS.get(v, {}).get("integrator") == default),
                  labels[0])
    fig = Figure(figsize=(20, 4.8), layout="constrained")
    ax1, ax2, ax4, ax3 = fig.subplots(1, 4)
    width = 0.8 / len(labels)
    rows = ["nominal (cold)", "nominal (warm)", *STARTS]
    y = np.arange(len(rows))
    for k, v in enumerate(labels):
        o = variants[v]
        times = [o["fit_from_nominal"]["cold"]["wall_s"], o["fit_from_nominal"]["warm"]["wall_s"],
                 *[o["convergence"][s_]["wall_s"] for s_ in STARTS]]
        ax1.barh(y + (k - (len(labels) - 1) / 2) * width, times, width, label=v)
    ax1.set_yticks(y, rows)
    ax1.invert_yaxis()
    ax1.axvline(TARGETS["fit_s"], color="C3", ls="--", label="target 20 s")
    ax1.set_xlabel("fit wall time [s] (crush-peak data)")
    ax1.set_title("6-parameter fit, 1.2 s drop at 5 kHz")
    ax1.legend(fontsize=8)
    names = list(variants[labels[0]]["fit_from_nominal"]["cold"]["rel_error"])
    x = np.arange(len(names))
    width = 0.8 / (2 * len(labels))
    for k, v in enumerate(labels):
        o = variants[v]
        crush = o["fit_from_nominal"]["cold"]
        clean = o["summary"]["clean_worst_rel_error"]
        ax2.bar(x + (2 * k - len(labels) + 0.5) * width,
                [abs(crush["rel_error"][n]) * 100 for n in names], width, color=f"C{k}",
                label=f"{v}: crush-peak data")
        ax2.bar(x + (2 * k + 1 - len(labels) + 0.5) * width, [clean[n] * 100 for n in names],
                width, color=f"C{k}", alpha=0.5, hatch="//",
                label=f"{v}: noise-free, worst of {len(STARTS)} starts")
    ax2.axhline(TARGETS["clean_recovery_rel"] * 100, color="C3", ls="--",
                label="0.5 % (noise-free target)")
    ax2.set_yscale("log")
    ax2.set_xticks(x, names)
    ax2.set_ylabel("|fitted / truth - 1| [%]")
    ax2.set_ylim(top=30)
    ax2.set_title("recovery of the rig's truth")
    ax2.legend(fontsize=7, ncol=2, loc="upper left")
    fd_names = list(variants[labels[0]]["ad_vs_fd"]["worst_robust_per_param"])
    x = np.arange(len(fd_names))
    width = 0.8 / len(labels)
    for k, v in enumerate(labels):
        w = variants[v]["ad_vs_fd"]["worst_robust_per_param"]
        ax4.bar(x + (k - (len(labels) - 1) / 2) * width,
                [max(w[n], 1e-12) for n in fd_names], width, label=v)
    ax4.axhline(TARGETS["ad_fd_rel"], color="C3", ls="--", label="1e-4 (issue #3)")
    ax4.set_yscale("log")
    ax4.set_xticks(x, fd_names)
    ax4.set_ylabel("|AD - FD| / |AD| (robust, worst case)")
    ax4.set_title(f"calibration loss gradient ({', '.join(f'{w:g}' for w in FD_WINDOWS_S)} s)")
    ax4.legend(fontsize=8)
    pred = variants[main_v]["prediction"]
    metrics = list(next(iter(pred.values()))["fitted"])
    x = np.arange(len(metrics))
    for k, (h, v) in enumerate(pred.items()):
        ax3.bar(x + (k - 1) * 0.27, [abs(v["fitted"][m]) * 100 for m in metrics], 0.27,
                label=f"{h} m" + (" (fitted here)" if h == "0.20" else ""))
        ax3.plot(x + (k - 1) * 0.27, [abs(v["truth_model"][m]) * 100 for m in metrics], "kx",
                 label="the truth itself vs the data" if k == 0 else None)
    ax3.axhline(TARGETS["peak_force_rel"] * 100, color="C3", ls="--", label="5 % (peaks)")
    ax3.axhline(TARGETS["max_stroke_rel"] * 100, color="C2", ls=":", label="1 % (stroke)")
    ax3.set_xticks(x, [m.replace("_", " ") for m in metrics], rotation=20, fontsize=8)
    ax3.set_ylabel("|model / data - 1| [%]")
    ax3.set_title(f"prediction, fitted at 0.20 m ({main_v})")
    ax3.legend(fontsize=8)
    atomic_savefig(fig, path)


if __name__ == "__main__":
    sys.exit(main())
