"""Model selection: does the record support the honeycomb's initial crush peak?

``compare_models`` fits the same drops twice, with the default parameters and with the
primary stage's crush peak added (``peak1``, ``L_peak1``: the two models are nested, the peak
off being ratio 1), and compares them on the plain least-squares misfit of the final window,
chi^2 = sum of squared noise-weighted residuals (= -2 log-likelihood + const for Gaussian noise
of the stated size):

* likelihood ratio LR = chi^2(no peak) - chi^2(peak), chi^2-distributed with 2 degrees of
  freedom if the peak is absent and the residuals are independent;
* AIC = chi^2 + 2 p and BIC = chi^2 + p ln n;
* the same LR **adjusted for misfit**: divided by the peak model's long-run variance factor
  s^2 (1 + rho_1) / (1 - rho_1) (s^2 = chi^2 / (n - p) its plain residual variance factor,
  rho_1 its lag-1 residual autocorrelation; AR(1) reading of the residuals), because
  correlated residuals make n samples count as far fewer and inflate every chi^2 difference.

The record supports the peak when the adjusted LR's p-value is below ``ALPHA`` and the peak
model's BIC is the lower. Where each model's misfit sits (drop, channel, 10 ms window) comes
from the fits' diagnostics.

The peak model's fit also runs its final stage from the model without the peak's optimum
(the peak all but off) and keeps the run of least chi^2 (``fit``'s check against the model
without the peak, handed the no-peak fit): from the start alone it ended in wrong minima on
records without a peak, far worse than the model it holds.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from ._fit import (
    IdentifiabilityWarning,
    MisfitWarning,
    add_peak_model_term,
    check_peak_form,
    fit,
    has_no_peak,
    wants_peak_model_term,
)
from ._parameters import DEFAULT_PARAMS, PEAK_PARAMS

__all__ = ["compare_models", "peak_model_names", "chi2_sf", "ALPHA"]

ALPHA = 0.01


def chi2_sf(x: float, df: int) -> float:
    """Survival function of the chi^2 distribution with integer ``df`` (closed forms)."""
    if x <= 0:
        return 1.0
    h = 0.5 * x
    if df % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, df // 2):
            term *= h / i
            total += term
        return math.exp(-h) * total
    total = math.erfc(math.sqrt(h))
    term = math.sqrt(h) / math.gamma(1.5)
    for i in range(1, (df - 1) // 2 + 1):
        if i > 1:
            term *= h / (i - 0.5)
        total += math.exp(-h) * term
    return total


def _chi2(result) -> float:
    prob = result.problem.robust(None)
    return 2.0 * prob.loss(result.theta)


def peak_model_names(params) -> tuple:
    """The parameters of ``compare_models``' peak model: ``params`` without the peak's, then
    PEAK_PARAMS, then L_rise1 where ``params`` has it (the built-up peak joins the peak)."""
    rise = ("L_rise1",) if "L_rise1" in params else ()
    return tuple(p for p in params if p not in PEAK_PARAMS + rise) + PEAK_PARAMS + rise


def compare_models(drops, params=DEFAULT_PARAMS, **fit_kw) -> dict:
    """Fit without and with the primary crush peak; JSON-ready comparison (see the module
    docstring). ``fit_kw`` go to both fits (``peak_form`` to the peak model's only; L_rise1
    in ``params`` goes to the peak model). The peak model's fit carries the peak-shape term
    in its total standard errors (``fit``'s ``model_form``); the model without the peak, where
    its residuals show misfit, the shift to the peak model (``fit``'s ``peak_model_term``,
    here from the peak model fitted below, so nothing is fitted twice; it is the same fit
    unless ``peak_form`` is given)."""
    peak_names = peak_model_names(params)
    params = tuple(p for p in params if p not in PEAK_PARAMS + ("L_rise1",))
    peak_form = fit_kw.pop("peak_form", None)
    check_peak_form(peak_names, peak_form)  # before the first fit
    peak_term = fit_kw.pop("peak_model_term", "auto")
    results = {}
    for label, names in (("no_peak", params), ("peak", peak_names)):
        kw = (dict(fit_kw, peak_form=peak_form) if label == "peak" else
              dict({k: v for k, v in fit_kw.items() if k != "model_form"},  # no peak: no
                   peak_model_term=False))  # peak-shape term; the missing-peak one below
        if label == "peak" and has_no_peak(results["no_peak"].names,
                                           results["no_peak"].problem.vehicle):
            # the peak model's fit is checked against (and run again from) the model without
            # the peak's optimum: the one just fitted, so that nothing is fitted twice
            kw["_no_peak"] = results["no_peak"]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IdentifiabilityWarning)
            warnings.simplefilter("ignore", MisfitWarning)
            results[label] = fit(drops, names, **kw)
    base = results["no_peak"]
    if wants_peak_model_term(peak_term, base.diagnostics["misfit"], base.names,
                             base.problem.vehicle):
        add_peak_model_term(base, results["peak"])
    out = {}
    for label, res in results.items():
        d = res.diagnostics
        chi2 = _chi2(res)
        k = len(res.names) + (len(res.drops) if res.problem.fit_touchdown else 0)
        n = res.n_obs
        out[label] = dict(
            params=list(res.names), values=dict(zip(res.names, res.values.tolist())),
            std_errors_hac=dict(zip(res.names, res.std_errors_hac.tolist())),
            std_errors_total=dict(zip(res.names, res.std_errors_total.tolist())),
            interval_reported=d["interval"], model_form=d["model_form"],
            peak_model_term=d["peak_model_term"],
            chi2=chi2, n_params=k, n_obs=n, aic=chi2 + 2 * k, bic=chi2 + k * math.log(n),
            residual_variance_factor=d["residual_variance_factor"],
            residual_lag1_autocorr=d["residual_lag1_autocorr"], misfit=d["misfit"],
            worst_window=d["worst_window"], wall_s=res.wall_s)
    df = len(PEAK_PARAMS)
    lr = out["no_peak"]["chi2"] - out["peak"]["chi2"]
    # plain least-squares variance factor of the peak model (the fits' own is Huber's)
    s2 = out["peak"]["chi2"] / max(out["peak"]["n_obs"] - out["peak"]["n_params"], 1)
    rho = out["peak"]["residual_lag1_autocorr"]
    rho = min(max(rho, 0.0), 0.99)
    inflation = max(s2, 1.0) * (1.0 + rho) / (1.0 - rho)
    lr_adj = lr / inflation
    p_adj = chi2_sf(lr_adj, df)
    supported = bool(p_adj < ALPHA and out["peak"]["bic"] < out["no_peak"]["bic"])
    out["comparison"] = dict(
        likelihood_ratio=lr, df=df, p_value=chi2_sf(lr, df),
        misfit_inflation=inflation, likelihood_ratio_adjusted=lr_adj, p_value_adjusted=p_adj,
        delta_aic=out["peak"]["aic"] - out["no_peak"]["aic"],
        delta_bic=out["peak"]["bic"] - out["no_peak"]["bic"], alpha=ALPHA,
        peak_supported=supported,
        verdict=("the data support the crush peak" if supported else
                 "the data do not support the crush peak"))
    out["_results"] = results  # the FitResults (not JSON; dropped by ``to_json``)
    return out


def comparison_json(cmp: dict) -> dict:
    return {k: v for k, v in cmp.items() if not k.startswith("_")}


def write_comparison_json(cmp: dict, path: Path) -> Path:
    """``model_comparison.json``: strict JSON, as ``fit_report.json`` (a missing error is
    null, not NaN)."""
    from jaxland._files import json_text

    Path(path).write_text(json_text(comparison_json(cmp)))
    return Path(path)


def plot_comparison(cmp: dict, path: Path, width_s: float = 0.01) -> Path:
    """Residual RMS (noise-std units) per channel in ``width_s`` windows after touchdown, both
    models: where the misfit sits."""
    from matplotlib.figure import Figure

    from ._report import atomic_savefig

    results = cmp["_results"]
    base = results["no_peak"]
    chans = list(base.problem.channels)
    fig = Figure(figsize=(10, 2.2 * len(chans) + 0.6), layout="constrained")
    axs = np.atleast_1d(fig.subplots(len(chans), 1, sharex=True, squeeze=False)[:, 0])
    for label, res in results.items():
        prob = res.problem
        r, _ = prob.robust(None).residuals(res.theta)
        r = r.reshape(prob.data.shape)
        for j, c in enumerate(chans):
            m = prob.mask[0, j] > 0
            t, rr = prob.rel_t[0][m], r[0, j][m]
            edges = np.arange(t.min(), t.max() + width_s, width_s)
            rms = [np.sqrt(np.mean(rr[(t >= a) & (t < a + width_s)] ** 2))
                   if np.any((t >= a) & (t < a + width_s)) else np.nan for a in edges[:-1]]
            axs[j].step(edges[:-1] * 1e3, rms, where="post",
                        label=f"{label} (chi2 {cmp[label]['chi2']:.4g})")
            axs[j].set_ylabel(f"{c}\nRMS residual / noise")
            axs[j].axhline(1.0, color="0.5", lw=0.8, ls=":")
            axs[j].set_yscale("log")
    axs[0].legend(fontsize=8)
    axs[-1].set_xlabel(f"time after touchdown [ms] ({base.drops[0].name}; {width_s * 1e3:g} ms "
                       "windows)")
    c = cmp["comparison"]
    fig.suptitle(f"{c['verdict']}: LR {c['likelihood_ratio']:.4g}, misfit-adjusted "
                 f"{c['likelihood_ratio_adjusted']:.3g} (p = {c['p_value_adjusted']:.2g}), "
                 f"dBIC {c['delta_bic']:.4g}")
    return atomic_savefig(fig, path)
