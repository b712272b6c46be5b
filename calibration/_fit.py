"""``fit``: calibrate the quarter model to drop tests, with uncertainty and identifiability.

Strategy (each step measured on the synthetic drops; numbers in data/README.md and
benchmarks/results/bench_fit.json):

1. **Growing first-impact windows** (``windows``: 10 ms, 30 ms, 100 ms after touchdown), each
   stage started from the previous optimum. On the first impact the gradients are exact (AD =
   central differences to ~1e-6, k and gamma included). The foot's contact oscillation makes the
   loss multimodal in k and gamma over long windows, but not over the first 10 ms: fitting the
   100 ms window directly from 2x off ended in wrong basins (gamma -> 0 or 1, k_b1 x 4000).
2. **Multi-start on the short windows**: the 10 and 30 ms stages run from the start and from
   variants of it in k and gamma (``START_VARIANTS``), until two starts agree on the lowest
   loss (every start where the fit from them misfits); the rest continues from the best.
   Without it, 1-2 of ~15 starts up to 2x off failed; with it 105 of 105 (three drop
   heights, noisy and noise-free, a joint fit) converged.
3. **Huber loss on the long stages** (``robust``, threshold 1.5 robust standard deviations):
   the model has no honeycomb crush peak, and plain least squares let the peak pull k_b1 up by
   ~45 %; with Huber 4-5 %, the other parameters within 1 %. Not on the short stages: there it
   made far starts fail.
4. **One refit on a longer window** (``refine_window_s``, 150 ms: still the first impact). A
   refit through lift-off and re-contact (0.3 s) reduces the crush-peak bias further when it
   lands in the right basin, but that loss is jagged and multimodal: from the 100 ms optimum it
   ended in a local minimum (loss 14.5e3 against 9.6e3 reachable from the truth) for one noise
   seed out of two. So it is an option, not the default.
5. **Uncertainty** from the Gauss-Newton covariance at the optimum, cov = s^2 (J^T J)^-1, J the
   Jacobian of the noise-weighted residuals, s^2 the residual variance factor (1 when the noise
   estimates are right and the model fits; larger with model error, which widens the errors),
   mapped to the physical values by the delta method. Measured over 40 noise seeds: 66 % of
   the values within 1 SE, 90 % within 2 SE. That holds for white residuals only; beside it
   every fit reports a HAC sandwich standard error that holds under misfit (autocorrelated
   residuals: ``_uncertainty``), the misfit diagnostics (variance factor, lag-1 residual
   autocorrelation, the worst 10 ms window and channel), and warns (``MisfitWarning``) when the
   data contradict the model: then trust ``std_error_hac``. Coverage of both over many noise
   seeds: benchmarks/bench_fit.py --coverage.
6. **Channel spread** (``channel_spread``), only where the misfit is warned: the final stage
   refitted from the optimum once per measured quantity left out (all legs and drops of it).
   A model that fits gives every channel the same parameters up to the noise; one that cannot
   represent the data makes them pull apart (a crush peak of another shape: the force
   channels and the stroke want different k_b1), and the HAC error, the scatter about the
   wrong model's best fit, does not see it. ``std_errors_total`` is the trusted error with the
   largest shift of each parameter added in quadrature: the interval to quote under misfit.
7. **Peak shape** (``model_form_spread``), whenever the fit has the primary crush peak: the
   final stage refitted from the optimum with the peak in each of its other forms (the law's
   linear fall, the law's built-up peak, an exponential decay, and that decay built up
   linearly or smoothly: ``PEAK_FORMS``). A peak shape
   the law lacks biases every channel alike, so the residuals can look clean and the channels
   agree; the forms the data still support (misfit-adjusted AIC within ``DAIC_PLAUSIBLE`` of
   the least) bracket that bias, and the largest shift among them is added in quadrature to
   ``std_errors_total``. A form the data reject adds nothing. The report names the supported
   form of least misfit-adjusted BIC (``best_supported_form``). The fit and its refits in
   every form share one compiled program (``CalibrationProblem(shared_forms=True)``), and the
   refits share a pool of threads, one per core, with the channel spread's.
8. **Missing peak** (``add_peak_model_term``), where the misfit is warned and the fitted model
   has no crush peak at all: the same fit is run again with the primary peak (``PEAK_PARAMS``,
   the law's linear form) on the final window from the optimum with the peak all but off
   (``peak_off_start``) and from the start through every stage, the one of least chi^2 kept
   (``_least_chi2``), in a second
   thread beside the channel spread's, and each value's shift to that fit is added in
   quadrature to ``std_errors_total``. A peak in the truth's honeycomb puts the same error
   into every channel, so neither the HAC error nor the channel spread sees the bias it
   leaves on k and gamma; the model with the peak is the nearest model that can hold it.
   A fit without any crush peak runs on functions whose linear peak is switched off at run
   time (``CalibrationProblem(peak_switch=True)``), and the fit with the peak on the same
   functions switched on: the term compiles nothing.
9. **Where the peak sits** (``peak_site``): in the honeycomb (the law's) or, for a record
   whose peak the motion does not show (``peak_location``), on the force channels alone:
   the drop runs without the peak and the force channels carry it as a gain of the crush
   so far (``CalibrationProblem``). The peak-shape refits then crawl on a kinked loss, and
   stop once a step lowers it by less than ``FORCES_REFIT_ATOL``.
10. **Parameters left fixed** (``add_fixed_params_term``), where the misfit is warned and the
   fit leaves some of ``DEFAULT_PARAMS`` fixed at the vehicle's values: the fit is run again
   from its optimum with those freed as well (same settings, in a thread of its own beside
   the channel spread's), and each value's shift to it is added in quadrature to
   ``std_errors_total``. A truth that differs in a fixed parameter puts its difference into
   every channel alike, as a missing peak does, and the fitted values take it up; the
   wider model is the nearest that can hold it (docs/calibration.md, item 13).
11. **No trusted interval** (``mark_interval_bounded``): where the misfit calls for the
   missing-peak or the fixed-parameter term or the drop spread and its refit failed, the
   total leaves that bias out, and ``diagnostics["interval_bounded"]`` is False with the
   reason; the report, the fitted vehicle's header and the CLI say so.
12. **Drop spread** (``drop_spread``), where the misfit is warned and the fit has two or more
   drops: the final stage refitted from the optimum once per drop left out (its touchdown
   coordinate held), on the channel spread's pool and compiled program. Drops of one
   campaign differ in what the model holds common to them (each honeycomb block crushes at
   its own plateau), and a joint fit's values then sit where no drop's truth is; the channel
   spread leaves out a quantity of every drop alike and does not see it. Each value's
   largest shift is added in quadrature to ``std_errors_total`` (``misfit.drop_spread``);
   where it exceeds the channel spread of some value the misfit warning says the drops
   disagree. A failed drop refit leaves the interval not bounded (item 11): that bias is
   then covered by nothing else.
"""

from __future__ import annotations

import math
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxland as jl
from jaxland._checks import named_as
from jaxland._files import json_text, run_environment
from jaxland._solvers._base import _whole_steps, smoothing_limits

from ._data import CHANNELS, DropTest, _highpass_noise, article_fingerprint, base_channel
from ._optim import lbfgs, levenberg_marquardt
from ._parameters import (
    DEFAULT_PARAMS,
    EXP_TABLE_SPAN,
    FORCES,
    HONEYCOMB,
    PARAMS,
    PEAK_FORMS,
    PEAK_PARAMS,
    RISE_FORMS,
    SHAPE_PARAMS,
    START_IF_OFF,
    acts_in,
    at_bound,
    check_names,
    check_peak_site,
    get_values,
    interval,
    interval95,
    no_peak_names,
    peak_form_vehicle,
    set_values,
    switch_on,
    value_range,
)
from ._problem import (
    FORCE_CHANNELS,
    INTEGRATORS,
    MS,
    PLAIN,
    SAVE_DT,
    WINDOW_MIN_S,
    CalibrationProblem,
    _without_primary_peak,
    check_integrator,
)
from ._uncertainty import MISFIT_SIGMA2, hac_covariance, misfit

__all__ = ["fit", "FitResult", "IdentifiabilityWarning", "MisfitWarning", "WINDOWS_S",
           "REFINE_WINDOW_S",
           "INTEGRATOR", "INTEGRATORS", "SMOOTHING", "check_integrator"]

WINDOWS_S = (0.01, 0.03, 0.1)
# The fitting integrator (``jaxland.Solver.method``) and, per integrator, the switch-smoothing
# widths (smoothing_m [m], smoothing_N [N]) used when none are given. Chosen from
# benchmarks/bench_fit.py (both variants side by side; docs/calibration-validation.md).
INTEGRATOR = "euler"
SMOOTHING = {"euler": (0.0, 0.0), "euler_implicit": (0.0, 0.0), "verlet": (1e-6, 10.0),
             "leapfrog": (0.0, 0.0)}
REFINE_WINDOW_S = 0.15
# s: the default refine window, shortened to a record, stops this far before its end, where a
# zero-phase (forward-backward) filter's backward pass starts: 5.5 ms to settle at CFC 180
# (_filter.settle_time_s)
REFINE_END_MARGIN_S = 0.006
# fit's refine_window_s default: REFINE_WINDOW_S where every record reaches that far after its
# touchdown, else shortened to the shortest record, and said so (``refine_window``); a window
# given as a number is used as given or refused
AUTO = "auto"
ROBUST_K = 1.5
# Alternative starts of the multi-start phase: (k factor, gamma value) applied to the start.
# From 2x off, one start's continuation can end in a wrong basin of the contact oscillation
# (gamma -> 0 or 1, k off); over 105 random and corner starts up to 2x off, the best of these
# five always continued into the truth's basin.
START_VARIANTS = ((1.0, None), (1.0, 0.2), (1.0, 0.8), (0.5, None), (2.0, None))
# LM stops when a step lowers the loss by less than FTOL relative (MINPACK's and scipy's
# default, sqrt(eps)). At 1e-10, on the smoothed (C1) loss of the verlet option LM creeps
# along a flat valley for 60 iterations per stage, each step gaining ~1e-9 (1.7e-6 in all,
# parameters moving far below their standard errors); euler's results agree to 4 digits at
# both (benchmarks/bench_fit.py).
FTOL = 1e-8
# The multistart stages only pick a basin for the long stages, which refine from it: they stop
# at FTOL_MULTISTART, and two starts agree when their losses lie within AGREE_REL. Measured on
# rig data with a crush peak: starts in one basin end 2e-6 to 3e-4 apart on the 30 ms window
# (the valley is flat along D_b and k_b1), wrong basins 20 % to 40x higher; tolerances of 1e-6
# and 1e-8 make every fit run all five starts to full convergence.
FTOL_MULTISTART = 1e-5
AGREE_REL = 1e-3
# starts run at once, and refits of a fit's uncertainty terms (this project's CI and most
# users' laptops have 2 or more cores)
MULTISTART_THREADS = REFIT_THREADS = 2
EXTENSION_PARAMS = ("peak1", "L_peak1", "peak2", "L_peak2", "unload")
PRE_S = 0.005  # samples this long before the detected touchdown are fitted too (they pin t0)
# a parameter is "not identified" when its Jacobian column is this small against the largest
# (scaled: d r / d log p), or when its relative standard error exceeds REL_SE_LIMIT
COLUMN_NORM_LIMIT = 1e-6
REL_SE_LIMIT = 0.5


class IdentifiabilityWarning(UserWarning):
    """A fitted parameter is not determined by the data."""


class MisfitWarning(UserWarning):
    """The residuals contradict the model (too large or autocorrelated): the classical standard
    errors are too small; use the HAC ones widened by the channel and drop spreads
    (``FitResult.std_errors_total``)."""


# fitted_vehicle.toml's header lines (FitResult.to_toml), which predict reads back
# (``_predict.read_fit_status``)
HEADER_FIT = "# Calibrated by `jaxland fit` (calibration package) against: "
HEADER_VALUES = "# fitted (+/- {interval}, the standard error the fit reports): "
# beside the held parameters, every value the fit cannot fit is taken as exact; an error in
# one of these biases the values beyond their interval before the misfit test sees it
# (tests/test_calibration_honesty.py: a 0.25 % gain on both force channels)
ASSUMED_EXACT = ("the vehicle's masses (body.m_body_kg, body.m_foot_kg)",
                 "each channel's gain (its calibration)",
                 "the touchdown speed the metadata set (drop_height_m, sink_speed_mps or "
                 "touchdown_speed_mps)",
                 "the rest of the vehicle file (its geometry, x_L2_mm, x_L4_mm, g_mps2)")


def assumed_exact(drops, channels=None) -> list:
    """``ASSUMED_EXACT`` for a fit of ``drops`` on ``channels`` (None: every drop's own): a
    channel whose gain uncertainty the metadata states (``gain_uncertainty_rel``) is in the
    interval, and only the others' gains (``ASSUMED_EXACT[1]``) are taken as exact."""
    exact = [f"{d.name}: {c}" for d in drops for c in d.channels
             if c not in d.gain_uncertainty_rel and (channels is None or c in channels)]
    if not any(d.gain_uncertainty_rel for d in drops):
        return list(ASSUMED_EXACT)
    gains = ["the gains with no gain_uncertainty_rel (" + ", ".join(exact) + ")"] if exact \
        else []
    return [ASSUMED_EXACT[0], *gains, *ASSUMED_EXACT[2:]]


# the parameters the fit held (active ones), which every interval is conditional on: predict
# names a file that holds them differently as edited
HEADER_HELD = "# held at the vehicle's values (every interval is conditional on them): "
# the law's extensions the fit held off (its values hold without them): predict names a file
# that switches one on as edited
HEADER_OFF = "# off in the fit (its values hold without them): "
# every other key (``_data.article_fingerprint``): predict names a file that changes one
HEADER_ARTICLE = "# the rest of the vehicle as fitted (test article, peak table), SHA-256: "
# a fit's warnings that its values are biased beyond the misfit (``FitResult.cautions``):
# "# CAUTION (FLAG): text", each FLAG a flag of predict's
HEADER_CAUTION = "# CAUTION ({flag}): "
HEADER_MISFIT = "# MISFIT: "
HEADER_NOT_CONVERGED = "# NOT CONVERGED: "
HEADER_NOT_BOUNDED = "# NO TRUSTED INTERVAL: "
AT_BOUND = "AT A BOUND OF THE VEHICLE'S RULES"
NOT_IDENTIFIED = "NOT IDENTIFIED by these records"


def stopped_at_cap(stages: list[dict]) -> bool:
    """A fit's last stage ended at its iteration cap, not at a minimum."""
    return bool(stages) and stages[-1].get("status") == "max_iter"


@dataclass
class FitResult:
    """The calibrated parameters with their uncertainty, the fitted vehicle and the record of
    the fit. Values are SI; ``report()`` gives everything with units, JSON-ready."""

    names: tuple
    values: np.ndarray
    std_errors: np.ndarray
    correlation: np.ndarray
    covariance: np.ndarray
    identified: np.ndarray
    start_values: np.ndarray
    vehicle: jl.Vehicle = field(repr=False)
    touchdown_times_s: np.ndarray = None
    touchdown_std_errors_s: np.ndarray = None
    residual_rms: dict = None
    sigma2: float = 1.0
    std_errors_hac: np.ndarray = None
    covariance_hac: np.ndarray = None
    std_errors_total: np.ndarray = None
    diagnostics: dict = field(default_factory=dict)
    n_obs: int = 0
    dof: int = 0
    loss: float = 0.0
    stages: list = field(default_factory=list)
    history: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    method: str = "lm"
    wall_s: float = 0.0
    drops: list = field(default_factory=list, repr=False)
    problem: CalibrationProblem = field(default=None, repr=False)
    theta: np.ndarray = field(default=None, repr=False)
    settings: dict = field(default_factory=dict)
    inputs: dict = field(default_factory=dict)  # what a caller ran it from (the CLI's files)
    # name -> (lo, hi) the fit's transform maps onto at the fitted values (hi None: open);
    # ``interval95`` maps the reported errors into it
    ranges: dict = field(default_factory=dict)

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    def std_error(self, name: str) -> float:
        return float(self.std_errors[self.names.index(name)])

    def interval95(self, name: str, std_error: float) -> list[float] | None:
        """The 95 % interval of a fitted value from ``std_error`` (``_parameters.interval95``:
        inside the parameter's range); None where the value is not identified or at a bound
        of the vehicle's rules (no interval holds there) or the range is unknown."""
        i = self.names.index(name)
        if (name not in self.ranges or not self.identified[i]
                or name in self.diagnostics.get("at_bound", ())):
            return None
        out = interval95(float(self.values[i]), float(std_error), *self.ranges[name])
        return None if out is None else [float(x) if math.isfinite(x) else None for x in out]

    def report(self) -> dict:
        """Everything about the fit, JSON-ready, units in the keys."""
        def num(x):
            x = float(x)
            return x if math.isfinite(x) else None

        params = {}
        _, reported = self.reported_errors()
        for i, n in enumerate(self.names):
            unit = PARAMS[n][1]
            params[n] = dict(
                value=num(self.values[i]), std_error=num(self.std_errors[i]), unit=unit,
                # the reported interval's (interval_reported), as predict's fit_status has it
                rel_std_error=num(reported[i] / abs(self.values[i])),
                rel_std_error_classical=num(self.std_errors[i] / abs(self.values[i])),
                std_error_hac=num(self.std_errors_hac[i]) if self.std_errors_hac is not None
                else None,
                std_error_total=num(self.std_errors_total[i])
                if self.std_errors_total is not None else None,
                ci95=self.interval95(n, reported[i]),
                range=(None if n not in self.ranges else
                       [num(self.ranges[n][0]), None if self.ranges[n][1] is None
                        else num(self.ranges[n][1])]),
                start=num(self.start_values[i]), identified=bool(self.identified[i]),
                at_bound=n in self.diagnostics.get("at_bound", ()),
                config_key=PARAMS[n][2], description=PARAMS[n][4])
        return dict(
            # False: the values are no minimum (the last stage stopped at its iteration cap,
            # or the fit with the crush peak ended worse than its model without it)
            converged=self.converged, not_converged=self.not_converged(),
            parameters=params,
            correlation=dict(names=list(self.names),
                             matrix=[[num(x) for x in row] for row in self.correlation]),
            touchdown_time_s={d.name: dict(value=num(t), std_error=num(s), detected=num(
                d.touchdown_time_s)) for d, t, s in zip(self.drops, self.touchdown_times_s,
                                                        self.touchdown_std_errors_s)},
            residual_rms=self.residual_rms,
            noise_std={d.name: d.noise_std for d in self.drops},
            residual_variance_factor=num(self.sigma2),
            misfit=self.diagnostics,
            n_observations=self.n_obs, degrees_of_freedom=self.dof, final_loss=num(self.loss),
            identifiability_warnings=self.warnings,
            method=self.method, stages=self.stages, wall_s=self.wall_s,
            settings=self.settings,
            **({"inputs": self.inputs} if self.inputs else {}),
            # the versions and XLA flags it ran on, as every jaxland output records them
            environment=run_environment(),
            drops=[d.summary() for d in self.drops],
            history=[dict(stage=h["stage"], iteration=h["iteration"], loss=h["loss"],
                          wall_s=h["wall_s"], values=dict(zip(self.names, h["values"])))
                     for h in self.history],
            units=dict(time="s", force="N", stroke="m", acceleration="m/s^2",
                       rel_std_error="1; the reported interval's standard error "
                                     "(interval_reported) over |value|",
                       rel_std_error_classical="1; std_error over |value|",
                       ci95="same unit as the value; the 95 % interval of the reported "
                            "standard error, +/- 1.96 of it in the fit's own coordinates "
                            "(log or logit of the range), so inside range; null where not "
                            "identified or at a bound; an upper end null: unbounded",
                       range="same unit as the value; the values the fit could reach at "
                             "the others' fitted values (upper end null: none)",
                       std_error="same unit as the value; Gauss-Newton, residual-variance "
                                 "scaled (holds for white residuals)",
                       std_error_hac="same unit as the value; HAC sandwich, Bartlett window "
                                     "(holds under misfit: autocorrelated residuals)",
                       std_error_total="same unit as the value; the trusted standard error "
                                       "and, under misfit, the channel spread "
                                       "(misfit.channel_spread) and, of several drops, the "
                                       "drop spread (misfit.drop_spread.spread), with a "
                                       "crush peak in the "
                                       "fit the peak-shape term (misfit.model_form.spread), "
                                       "and under misfit without a crush peak in the model "
                                       "the shift to the model with one "
                                       "(misfit.peak_model_term.term), and under misfit of "
                                       "a fit that leaves default parameters fixed the shift "
                                       "to the fit with them freed "
                                       "(misfit.fixed_params_term.term), added in quadrature"),
            interval_reported=self.diagnostics.get("interval"),
            # the parameters the fit held fixed: every interval is conditional on them
            interval_conditional_on=self.held_fixed(),
            interval_assumes_exact=self.assumes_exact(),
            # False: a bias term the misfit calls for failed (misfit.interval_not_bounded);
            # the interval is then no bound on the values' error
            interval_bounded=self.diagnostics.get("interval_bounded", True),
            interval_not_bounded=self.diagnostics.get("interval_not_bounded"),
        )

    def assumes_exact(self) -> list:
        """What every interval of this fit takes as exact (``assumed_exact``)."""
        return assumed_exact(self.drops, None if self.problem is None else self.problem.channels)

    def held_fixed(self) -> dict:
        """The fittable parameters (``PARAMS``) this fit held at the vehicle's values: per
        name ``value`` (SI; None where that law extension is off), ``unit``,
        ``config_key`` and ``active`` (False where the extension, or the peak whose length
        it is, is off: the value then acts on nothing). Every standard error the fit
        reports is conditional on them: a truth that differs in one biases the fitted
        values, and no term but the fixed-parameter term (the default parameters only,
        under misfit) sees it."""
        out = {}
        for n, (get, unit, key, *_) in PARAMS.items():
            if n in self.names:
                continue
            v = get(self.vehicle)
            out[n] = dict(value=None if v is None else float(v), unit=unit, config_key=key,
                          active=acts_in(n, self.vehicle))
        return out

    def to_json(self, path) -> Path:
        from ._report import atomic_write_text

        return atomic_write_text(Path(path), json_text(self.report()))

    @property
    def converged(self) -> bool:
        """The last stage ended at a minimum, not at its iteration cap, two starts reached it
        (``starts_disagree``), and a fit with the crush peak ended no worse than its special
        case without it (``no_peak_failure``)."""
        return self.not_converged() is None

    def not_converged(self) -> str | None:
        """Why the values are no minimum (the NOT CONVERGED line's text); None where they
        are one."""
        if stopped_at_cap(self.stages):
            return "the last stage stopped at its iteration cap; these values are not a minimum"
        disagree = starts_disagree(self.settings.get("multistart"))
        if disagree:
            return disagree
        return no_peak_failure(self.diagnostics.get("no_peak_check"))

    def cautions(self) -> list[tuple[str, str]]:
        """The fit's warnings that its values are biased beyond what its misfit says, as
        (flag, text) for the header that predict reads: the crush peak in the force channels
        only (the honeycomb's values take up a force the motion does not show), a peak form
        the data reject, and a motion that misfits with the peak on the force channels."""
        d, out = self.diagnostics, []
        where = d.get("peak_location")
        if where is not None and where.get("force_only"):
            out.append(("PEAK IN THE FORCES ONLY", "the crush peak shows in the force channels "
                        "only: the honeycomb's values take up a force the motion does not show "
                        "(fit_report.json, misfit.peak_location)"))
        mform, form = d.get("model_form"), self.settings.get("peak_form")
        if mform is not None and form is not None and form not in mform["plausible"]:
            out.append(("FORM REJECTED", f"the data reject the crush peak's {form} form; the "
                        f"{mform['best_supported']} form is the best supported (fit_report.json, "
                        "misfit.model_form)"))
        site = d.get("peak_site_check")
        if site is not None and site.get("misfit"):
            out.append(("MOTION MISFITS", "the peak sits on the force channels and the motion "
                        "misfits: the motion shows crush work the model lacks, and the values "
                        "are biased (fit_report.json, misfit.peak_site_check)"))
        return out

    def reported_errors(self) -> tuple[str, np.ndarray]:
        """The standard errors the fit reports (``diagnostics["interval"]``): the classical
        ones only where the residuals look like the noise, else the HAC or the total ones."""
        name = self.diagnostics.get("interval", "std_error")
        return name, {"std_error": self.std_errors, "std_error_hac": self.std_errors_hac,
                      "std_error_total": self.std_errors_total}[name]

    def to_toml(self) -> str:
        """The fitted vehicle as a jaxland config (``jaxland simulate --config``); its header
        names the records, the fitted values with the errors the fit reports, the values it
        held, and the residuals' misfit where there is one."""
        interval, errors = self.reported_errors()
        misfit = self.diagnostics.get("misfit") or []
        fixed = self.held_fixed()
        held = {n: h for n, h in fixed.items() if h["active"]}
        off = [n for n, h in fixed.items() if not h["active"]]
        head = [HEADER_FIT + ", ".join(d.source for d in self.drops),
                HEADER_VALUES.format(interval=interval) + ", ".join(
                    f"{n} = {v:.6g} +/- {s:.2g} {PARAMS[n][1]}" if ok else
                    f"{n} = {v:.6g} {PARAMS[n][1]} ({AT_BOUND})"
                    if n in self.diagnostics.get("at_bound", ()) else
                    f"{n} = {v:.6g} {PARAMS[n][1]} ({NOT_IDENTIFIED}; started at {v0:.6g})"
                    for n, v, s, ok, v0 in zip(self.names, self.values, errors,
                                               self.identified, self.start_values)),
                *([HEADER_HELD + ", ".join(f"{n} = {h['value']:.6g} {h['unit']}"
                                           for n, h in held.items())] if held else []),
                *([HEADER_OFF + ", ".join(off)] if off else []),
                HEADER_ARTICLE + article_fingerprint(self.vehicle),
                *([f"{HEADER_MISFIT}{'; '.join(misfit)} (fit_report.json, misfit)"] if misfit
                  else []),
                *([] if self.converged else [HEADER_NOT_CONVERGED + self.not_converged()]),
                *(HEADER_CAUTION.format(flag=flag) + text for flag, text in self.cautions()),
                *([HEADER_NOT_BOUNDED + "; ".join(self.diagnostics["interval_not_bounded"])
                   + " (fit_report.json, misfit.interval_not_bounded)"]
                  if self.diagnostics.get("interval_bounded") is False else []),
                ""]
        # the fitted values against the vehicle the fit started from (a --config's values stay
        # that file's, not fitted)
        base = self.problem.vehicle if self.problem is not None else None
        return "\n".join(head) + jl.vehicle_to_toml(self.vehicle, changed_by="FITTED",
                                                     base=base)

    def traces(self) -> list[dict]:
        """Data and fitted model at the samples of the final window, per drop:
        ``{"name", "time_s" (after the fitted touchdown), "data": {channel: ...},
        "model": {channel: ...}, "noise_std": {channel: ...}}`` (SI units)."""
        prob, theta = self.problem, self.theta
        r, _ = prob.robust(None).residuals(theta)
        model = prob.data + r.reshape(prob.data.shape) / prob.inv_sigma[:, :, None]
        t0 = prob.touchdown_times(theta)
        out = []
        for i, d in enumerate(prob.drops):
            rec = dict(name=d.name, synthetic=d.synthetic, time_s={}, data={}, model={},
                       noise_std={})
            for j, c in enumerate(prob.channels):
                m = prob.mask[i, j] > 0
                if not m.any():
                    continue
                rec["time_s"][c] = prob.rel_t[i, m] + d.touchdown_time_s - t0[i]
                rec["data"][c] = prob.data[i, j, m]
                rec["model"][c] = model[i, j, m]
                rec["noise_std"][c] = d.noise_std[c]
            out.append(rec)
        return out

    def predict(self, drop: DropTest):
        from ._predict import predict

        return predict(self.vehicle, drop)

    def plot(self, out_dir) -> list[Path]:
        from ._plots import plot_fit

        return plot_fit(self, Path(out_dir))


def _start_variants(problem: CalibrationProblem, theta0) -> list:
    """The start and its ``START_VARIANTS`` (k scaled, gamma replaced), without duplicates."""
    names = problem.names
    out = []
    for fk, g in START_VARIANTS:
        th = np.array(theta0, dtype=float)
        if "k" in names:
            th[names.index("k")] += math.log(fk)
        if g is not None and "gamma" in names:
            th[names.index("gamma")] = math.log(g / (1.0 - g))
        if not any(np.allclose(th, o, rtol=0, atol=1e-12) for o in out):
            out.append(th)
    return out


def _starts_agree(candidates) -> bool:
    """Two of the ``candidates`` (dicts with ``loss``) agree on the lowest loss so far: their
    losses lie within AGREE_REL of it."""
    best = min(c["loss"] for c in candidates)
    return sum(c["loss"] - best <= AGREE_REL * max(abs(best), 1e-12) for c in candidates) >= 2


def starts_disagree(info: dict | None) -> str | None:
    """Why a fit's basin is not known to be the best (``settings["multistart"]``): all of its
    starts ran and no second one reached the lowest loss (``_starts_agree``), so that minimum
    may be a local one (a start far from the truth finds a wrong basin, and the record's
    misfit then reads as the model's). None where two agreed, or where one start ran."""
    if not info or info.get("starts_agree", True) or info["n_starts_tried"] < 2:
        return None
    losses = ", ".join(f"{x:.4g}" for x in info["start_losses"])
    return (f"no two of its {info['n_starts_tried']} starts reached the lowest loss "
            f"({info['selected_by']}: {losses}), so it may be a local minimum; give a start "
            "nearer the truth (--start) and see whether two agree")


def _until_two_agree(from_start, n: int, threads: int, pending: list | None = None) -> list:
    """``from_start(j)`` for the starts j = 0, 1, ... in order until two agree
    (``_starts_agree``): the candidates, those of the starts taken. The starts run ``threads``
    at a time (XLA frees the interpreter lock: one per core), so the candidates are those of
    one start after the other: a batch's later starts are discarded where an earlier one
    settles it, and their futures, still running, go to ``pending`` (where given), in
    order, for a caller that wants them after all."""
    candidates = []
    for b in range(0, n, threads):
        futures = [_in_thread(from_start, j) for j in range(b, min(b + threads, n))]
        for i, f in enumerate(futures):
            candidates.append(f.result())
            if _starts_agree(candidates):
                if pending is not None:
                    pending += futures[i + 1:]
                return candidates
    return candidates


def _start_error(err: jl.ConfigError, start: dict) -> jl.ConfigError:
    """A vehicle rule that a start ``{name: value}`` broke, named ``start.<name>`` with the
    start's value: the one whose field it is, else the only start value (the field the rule
    names is then in the rule), else ``start`` as a whole (the base vehicle was valid, so the
    start values broke it together)."""
    mine = [k for k in start if PARAMS[k][2] == err.field
            or err.field.startswith(PARAMS[k][2] + ".")]
    if mine:
        return jl.ConfigError(f"start.{mine[0]}", start[mine[0]], err.rule)
    value = (f"{err.value:.6g}" if isinstance(err.value, float) else repr(err.value))
    rule = f"gives {err.field} = {value}: {err.rule}"
    if len(start) == 1:
        k = next(iter(start))
        return jl.ConfigError(f"start.{k}", start[k], rule)
    return jl.ConfigError("start", start, rule)


def _start_vehicle(base: jl.Vehicle, names, start) -> jl.Vehicle:
    if start is None:
        return base
    if isinstance(start, jl.Vehicle):
        return set_values(base, names, get_values(start, names))
    if isinstance(start, dict):
        unknown = set(start) - set(names)
        if unknown:
            raise jl.ConfigError("start", sorted(unknown)[0], "not a fitted parameter; fitted: "
                                 + ", ".join(names))
        vals = get_values(base, names)
        for k, v in start.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise jl.ConfigError(f"start.{k}", v, "must be a finite number (SI)")
            vals[names.index(k)] = float(v)
        try:
            return jl.validate_vehicle(set_values(base, names, vals))
        except jl.ConfigError as err:  # the vehicle's rule, named by the start value that broke it
            raise _start_error(err, start) from None
    raise jl.ConfigError("start", type(start).__name__, "must be a Vehicle or {name: value}")


def _normal_inverse(jac):
    """(J^T J)^-1 of the column-scaled Jacobian, the columns whose norm is below
    COLUMN_NORM_LIMIT of the largest left out: (that inverse, the scaled kept columns, the
    column norms, the mask of kept columns). The scaling keeps the pseudo-inverse's cut-off
    relative to each parameter's own sensitivity."""
    col = np.linalg.norm(jac, axis=0)
    keep = ~(col < COLUMN_NORM_LIMIT * max(float(col.max()), 1e-300))
    js = jac[:, keep] / col[keep]
    return np.linalg.pinv(js.T @ js, rcond=1e-13, hermitian=True), js, col, keep


def _variance_factor(r: np.ndarray, dof: int, huber_c=None) -> float:
    """s^2 of the active residuals ``r`` (``_uncertainty``'s, and the report's residual
    variance factor): |r|^2 / dof; with a Huber threshold c, [sum psi(r)^2 / dof] /
    mean(psi'(r))^2."""
    if huber_c is None:
        return float(r @ r) / dof
    psi = np.clip(r, -huber_c, huber_c)
    inlier = float(np.mean(np.abs(r) <= huber_c))
    return float(psi @ psi) / dof / max(inlier, 1e-3) ** 2


def _uncertainty(problem: CalibrationProblem, theta, huber_c=None):
    """Gauss-Newton covariance at ``theta``: cov = s^2 (J^T J)^-1 in the unconstrained
    coordinates, J the Jacobian of the noise-weighted residuals, plus the offsets' error:
    (J^T J)^-1 (sum_c v_c J^T u_c u_c^T J) (J^T J)^-1, u_c the indicator of channel c's
    residuals and v_c = 1 / n_c its offset's variance (noise units, the mean of n_c free-fall
    samples; unfiltered channels). Least squares: s^2 = |r|^2 /
    (n - p). Huber (threshold c): s^2 = [sum psi(r)^2 / (n - p)] / mean(psi'(r))^2 (Huber 1981,
    psi(r) = clip(r, -c, c)), which reduces to the former when no residual exceeds c. Mapped to
    the physical values by the delta method. Parameters whose Jacobian column vanishes are left
    out (their standard error is NaN). Each gain with a stated uncertainty
    (``DropTest.gain_uncertainty_rel``) adds its least-squares response the same way, with
    u_c the channel's data about its reference, in noise units, times that uncertainty (one
    error per column over the drops)."""
    r_all, jac_all, _ = problem.robust(None).residuals_and_jacobian(theta)
    n, p = problem.n_obs, problem.n_theta
    dof = max(n - p, 1)
    active = problem.mask.ravel() > 0
    r = r_all[active]
    jac = jac_all[active]
    sigma2 = _variance_factor(r, dof, huber_c)
    n_z = problem.n_z
    cov_s, js, col, keep = _normal_inverse(jac)
    zero = ~keep
    # the offsets' error: each channel's offset is the mean of its free fall, and an error
    # in it shifts all of that channel's residuals alike; its effect on the values is the
    # least-squares response to that shift, added to both covariances
    add_s = np.zeros_like(cov_s)
    mask = problem.mask.reshape(*problem.offset_var.shape, -1)
    rows = []
    for (i, j), v in np.ndenumerate(problem.offset_var):
        if v > 0 and mask[i, j].any():
            u = np.zeros(mask.shape)
            u[i, j] = mask[i, j] * math.sqrt(v)
            rows.append(js.T @ u.ravel()[active])
    # the gains' error (``DropTest.gain_uncertainty_rel``): a gain off by its standard
    # uncertainty scales that channel's data about its reference (``gain_reference``), and so
    # shifts each residual by the datum's distance from it times the uncertainty, in noise
    # units. A column is one sensor with one calibration in every drop of the fit: its
    # drops' shifts are one error, added before the square
    for j in range(problem.gain_sd.shape[1]):
        u = np.zeros(mask.shape)
        for i in np.flatnonzero(problem.gain_sd[:, j] > 0):
            u[i, j] = (mask[i, j] * (problem.data[i, j] - problem.gain_zero[i, j])
                       * problem.inv_sigma[i, j] * problem.gain_sd[i, j])
        if u.any():
            rows.append(js.T @ u.ravel()[active])
    if rows:
        a = np.array(rows)
        add_s = cov_s @ (a.T @ a) @ cov_s
    cov_theta = np.full((p, p), np.nan)
    idx = np.nonzero(keep)[0]
    cov_theta[np.ix_(idx, idx)] = (sigma2 * cov_s + add_s) / np.outer(col[keep], col[keep])
    g = problem.transform_jacobian(theta)  # d values / d z
    cz = cov_theta[:n_z, :n_z]
    cov_p = g @ np.where(np.isfinite(cz), cz, 0.0) @ g.T
    bad = ~np.isfinite(np.diag(cz))
    # a value whose transform involves an unidentified coordinate is unidentified
    bad_p = (np.abs(g[:, bad]) > 0).any(axis=1) if bad.any() else np.zeros(n_z, bool)
    cov_p[bad_p, :] = np.nan
    cov_p[:, bad_p] = np.nan
    se = np.sqrt(np.diag(cov_p))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_p / np.outer(se, se)
    t_se = (np.sqrt(np.diag(cov_theta)[n_z:]) * MS if problem.fit_touchdown
            else np.zeros(len(problem.drops)))
    # the sandwich (HAC) covariance, which holds under misfit (``_uncertainty`` module)
    shape = problem.data.shape
    jac_s = jac_all.reshape(*shape, p)[..., keep] / col[keep]
    hac = hac_covariance(r_all.reshape(shape), jac_s, problem.mask, huber_c)
    cov_theta_h = np.full((p, p), np.nan)
    cov_theta_h[np.ix_(idx, idx)] = (hac["cov"] + add_s) / np.outer(col[keep], col[keep])
    czh = cov_theta_h[:n_z, :n_z]
    cov_h = g @ np.where(np.isfinite(czh), czh, 0.0) @ g.T
    cov_h[bad_p, :] = np.nan
    cov_h[:, bad_p] = np.nan
    rho1 = float(hac["rho"][1]) if hac["rho"].size > 1 else 0.0
    return dict(sigma2=sigma2, dof=dof, cov=cov_p, se=se, corr=corr,
                col_rel=col[:n_z] / max(float(col.max()), 1e-300), zero=zero[:n_z] | bad_p,
                t_se=t_se, cov_hac=cov_h, se_hac=np.sqrt(np.diag(cov_h)), hac_lag=hac["L"],
                rho1=rho1, misfit=misfit(sigma2, rho1, problem.noise_lag1),
                where=misfit_location(problem, r_all.reshape(shape)),
                residuals=r_all, jacobian=jac_all)


# A channel weighted by the loader's noise floor (its free fall flat: noise-free data, or a
# record held or zeroed before touchdown) whose residuals carry white noise above
# FLOOR_NOISE_LIMIT of that floor (their high-pass estimate) is not noise-free. Measured on the
# rig's 0.2 m drop: the noise-free records' residuals 0.0002-0.03 of the floor (with and without
# the crush peak), the bundled noisy record with its free fall flattened 6-83
FLOOR_NOISE_LIMIT = 1.0


def floor_noise(problem: CalibrationProblem, res: np.ndarray) -> list[dict]:
    """The channels weighted by the loader's noise floor (``noise_source`` "floor ...") whose
    residuals ``res`` (noise units, the problem's data shape) carry white noise above
    ``FLOOR_NOISE_LIMIT`` of it: per such channel the drop, the channel and that noise in
    units of the floor (``_data._highpass_noise`` of the residuals)."""
    out = []
    for i, d in enumerate(problem.drops):
        for j, c in enumerate(problem.channels):
            m = problem.mask[i, j] > 0
            if not str(d.noise_source.get(c, "")).startswith("floor") or not m.any():
                continue
            white = _highpass_noise(np.asarray(res[i, j])[m])
            if white > FLOOR_NOISE_LIMIT:
                out.append(dict(drop=d.name, channel=c, white_noise_floor_units=white))
    return out


def misfit_location(problem: CalibrationProblem, res: np.ndarray, width_s: float = 0.01):
    """Where the misfit sits: per drop, the channel and the ``width_s`` time window (after
    touchdown) with the largest RMS weighted residual (noise-std units; 1 = noise)."""
    out = []
    for i, d in enumerate(problem.drops):
        best = None
        for j, c in enumerate(problem.channels):
            m = problem.mask[i, j] > 0
            if not m.any():
                continue
            t = problem.rel_t[i][m]
            rr = res[i, j][m]
            for a in np.arange(t.min(), t.max(), width_s):
                sel = (t >= a) & (t < a + width_s)
                if sel.sum() < 3:
                    continue
                rms = float(np.sqrt(np.mean(rr[sel] ** 2)))
                if best is None or rms > best["rms_noise_units"]:
                    best = dict(drop=d.name, channel=c, window_s=[float(a), float(a + width_s)],
                                rms_noise_units=rms)
        if best is not None:
            out.append(best)
    return out


# Where the primary crush peak shows. A honeycomb's peak is crush work: the stroke and the body
# acceleration carry it as the force channels do. A peak in the force channels alone (a
# load-cell artefact, a load path the model lacks) is no honeycomb's, and fitting it moves the
# honeycomb's parameters. The test: one Gauss-Newton step from the optimum on the motion
# channels alone; the peak counts as the force channels' only where that step keeps less than
# PEAK_MOTION_RATIO of the fitted excess (peak1 - 1) and moves peak1 by more than PEAK_MOTION_Z
# of its motion-only standard error. Over the peak-recovery study's 0.2 m drops (4 peak
# shapes, 10 seeds each) the step kept 0.31 to 0.83 of the excess, 1.7 to 7.4 standard errors
# off, where the peak sat on the force channels only (37 of 40 named), and 0.91 to 1.08,
# within 2.0, where it was the honeycomb's (none named; docs/calibration-validation.md, item 11).
PEAK_MOTION_CHANNELS, PEAK_FORCE_CHANNELS = ("stroke_m", "body_accel_mps2"), FORCE_CHANNELS
PEAK_MOTION_RATIO, PEAK_MOTION_Z = 0.8, 2.0


def _motion_rows(problem: CalibrationProblem):
    """The motion channels (``PEAK_MOTION_CHANNELS``) of ``problem``: a mask over its
    channels, and one over its fitted samples (drops x channels x samples)."""
    motion = np.array([base_channel(c) in PEAK_MOTION_CHANNELS for c in problem.channels])
    return motion, (problem.mask > 0) & motion[None, :, None]


def peak_location(problem: CalibrationProblem, theta, res, jac) -> dict | None:
    """Whether the fitted primary crush peak shows in the motion as in the forces: peak1 after
    one Gauss-Newton step from ``theta`` on the stroke and body-acceleration channels alone
    (``res``, ``jac``: the plain least-squares residuals and Jacobian at ``theta``), its
    standard error from those channels, the share of the fitted excess (peak1 - 1) the step
    keeps, z = (peak1 - its motion value) / that error (scaled by those channels' residual
    variance factor where it exceeds 1), and ``force_only``: the excess
    mostly gone (below PEAK_MOTION_RATIO) and z above PEAK_MOTION_Z. None where peak1 is not
    fitted, sits on the force channels already (``peak_site``) or the record lacks a force or
    a motion channel."""
    if "peak1" not in problem.names or problem.peak_site == FORCES:
        return None
    motion, rows = _motion_rows(problem)
    if not motion.any() or not any(base_channel(c) in PEAK_FORCE_CHANNELS
                                   for c in problem.channels):
        return None
    shape = problem.data.shape
    r = np.asarray(res).reshape(shape)[rows]
    j = np.asarray(jac).reshape(*shape, -1)[rows]
    inv, js, col, keep = _normal_inverse(j)
    step = np.zeros(j.shape[1])
    step[keep] = -(inv @ (js.T @ r)) / col[keep]
    # the motion channels' own residual variance factor, at least 1 (as the classical error
    # scales by it): under misfit their residuals exceed the noise
    s2 = max(float(r @ r) / max(r.size - int(keep.sum()), 1), 1.0)
    cov = np.zeros((j.shape[1], j.shape[1]))
    cov[np.ix_(keep, keep)] = s2 * inv / np.outer(col[keep], col[keep])
    i, n_z = problem.names.index("peak1"), problem.n_z
    g = problem.transform_jacobian(theta)[i]
    p_all = float(problem.values(theta)[i])
    p_motion = float(problem.values(np.asarray(theta) + step)[i])
    se = float(np.sqrt(max(g @ cov[:n_z, :n_z] @ g, 0.0)))
    ratio = (p_motion - 1.0) / (p_all - 1.0) if p_all > 1.0 else None  # no excess fitted
    z = (p_all - p_motion) / se if se > 0 else None

    def finite(x):  # JSON-ready: a step that ran off gives None, not inf or NaN
        return x if x is not None and math.isfinite(x) else None

    ratio, z = finite(ratio), finite(z)
    return dict(peak1=finite(p_all), peak1_motion=finite(p_motion),
                std_error_motion=finite(se), motion_variance_factor=s2, excess_kept=ratio,
                z=z, force_only=bool(ratio is not None and z is not None
                                     and ratio < PEAK_MOTION_RATIO and z > PEAK_MOTION_Z),
                motion_channels=[c for c, m in zip(problem.channels, motion) if m])


def _leave_out(problem: CalibrationProblem, theta, subs: dict, huber_c, max_iter: int, pool):
    """Start the refits of ``problem``'s final window from ``theta``, one per entry of
    ``subs`` (label: ``(channels, drops, free)``, the ``windowed`` arguments and the
    coordinates that move; Levenberg-Marquardt, same Huber threshold, same compiled
    functions), on ``pool`` (None: one after the other, here). Returns a function that waits
    for them: ``{label: shift of each value [SI], or None where that refit failed}``."""
    values = problem.values(theta)

    def without(label):
        channels, drops, free = subs[label]
        sub = problem.windowed(problem.active_window_s, channels=channels,
                               drops=drops).robust(huber_c)
        try:
            th, _, _ = levenberg_marquardt(sub, theta, max_iter=max_iter, ftol=FTOL, free=free)
        except (jl.SimulationError, np.linalg.LinAlgError):
            return None
        shift = sub.values(th) - values
        return shift if np.all(np.isfinite(shift)) else None

    if pool is None:
        done = {g: without(g) for g in subs}
        return lambda: done
    futures = {g: pool.submit(without, g) for g in subs}
    return lambda: {g: f.result() for g, f in futures.items()}


def _largest(problem: CalibrationProblem, theta, shifts: dict) -> np.ndarray:
    """The largest absolute shift of each value over ``shifts`` (None: a failed refit, left
    out); NaN where every refit failed, zeros where there were none."""
    values = problem.values(theta)
    if not shifts:
        return np.zeros_like(values)
    done = [v for v in shifts.values() if v is not None]
    return np.max(np.abs(done), axis=0) if done else np.full_like(values, np.nan)


def channel_subs(problem: CalibrationProblem) -> dict:
    """The channel spread's refits (``_leave_out``): one per base channel, without every leg
    and drop of it; none with fewer than two base channels."""
    groups = list(dict.fromkeys(base_channel(c) for c in problem.channels))
    if len(groups) < 2:
        return {}
    return {g: ([c for c in problem.channels if base_channel(c) != g], None, None)
            for g in groups}


def drop_subs(problem: CalibrationProblem) -> dict:
    """The drop spread's refits (``_leave_out``): one per drop, without it (its touchdown
    coordinate, which no residual then moves, held); none with fewer than two drops."""
    n = len(problem.drops)
    if n < 2:
        return {}
    out = {}
    for i, d in enumerate(problem.drops):
        free = np.ones(problem.n_theta, bool)
        if problem.fit_touchdown:
            free[problem.n_z + i] = False
        out[d.name] = (None, [k for k in range(n) if k != i], free)
    return out


def channel_spread(problem: CalibrationProblem, theta, huber_c=None, max_iter: int = 60,
                   pool=None):
    """How far the fitted values move when one measured quantity is left out: for each base
    channel (every leg and drop of it), the final window refitted from ``theta`` without it
    (Levenberg-Marquardt, same Huber threshold, same compiled functions). Returns ``(spread,
    shifts)``: the largest absolute shift of each parameter [SI] over the channels left out,
    and per channel the shifts (None where that refit failed). Fewer than two base channels:
    no spread (zeros). ``pool``: an executor the refits run on (default: one after the other
    here)."""
    shifts = _leave_out(problem, theta, channel_subs(problem), huber_c, max_iter, pool)()
    return _largest(problem, theta, shifts), shifts


def drop_spread(problem: CalibrationProblem, theta, huber_c=None, max_iter: int = 60,
                pool=None):
    """How far the fitted values move when one drop is left out: for each drop, the final
    window refitted from ``theta`` without it (as ``channel_spread``). Returns ``(spread,
    shifts)``: the largest absolute shift of each parameter [SI] over the drops left out, and
    per drop the shifts (None where that refit failed). A single drop: no spread (zeros)."""
    shifts = _leave_out(problem, theta, drop_subs(problem), huber_c, max_iter, pool)()
    return _largest(problem, theta, shifts), shifts


def check_peak_form(names, peak_form: str | None) -> None:
    """Refuse, by name, a ``fit(peak_form=...)`` that is not one of its choices or does not
    go with the fitted parameters ``names``."""
    if peak_form is None:
        return
    if peak_form not in EXP_TABLE_SPAN:
        *first, last = (f"'{f}'" for f in EXP_TABLE_SPAN)
        raise jl.ConfigError("peak_form", peak_form, "must be None, " + ", ".join(first)
                             + " or " + last)
    if "peak1" not in names:
        raise jl.ConfigError("peak_form", peak_form, "needs peak1 among the fitted "
                             "parameters")
    if ("L_rise1" in names) != (peak_form in RISE_FORMS):
        raise jl.ConfigError("peak_form", peak_form,
                             "needs L_rise1 among the fitted parameters (the ripple's fold "
                             "length)" if peak_form == "ripple" else
                             "needs L_rise1 among the fitted parameters (the exponential "
                             "decay built up over L_rise1)" if peak_form in RISE_FORMS else
                             "cannot be combined with L_rise1 (the built-up forms: "
                             "peak_form='rise_exp' or 'smooth_exp' build up the exponential "
                             "decay; in peak_form='ripple' it is the fold length)")


def peak_form_of(names, peak_form: str | None) -> str | None:
    """The primary crush peak's form a fit of ``names`` uses (None: the fit has no peak)."""
    if "peak1" not in names:
        return None
    if peak_form in EXP_TABLE_SPAN:
        return peak_form
    return "rise" if "L_rise1" in names else "linear"


def _form_names(names, form: str) -> tuple:
    base = tuple(n for n in names if n != "L_rise1")
    return base + ("L_rise1",) if form in RISE_FORMS else base


def _chi2(problem: CalibrationProblem, theta) -> float:
    """Sum of squared noise-weighted residuals (plain least squares) of ``problem``."""
    return 2.0 * problem.robust(None).loss(theta)


# A peak form enters the model-form term when its AIC, misfit-adjusted (divided by a
# long-run variance factor, as in ``_compare``), lies within DAIC_PLAUSIBLE of
# the best form's: Burnham & Anderson's "essentially no support" beyond 10.
DAIC_PLAUSIBLE = 10.0


def _form_problem(problem: CalibrationProblem, vehicle: jl.Vehicle, alt: str):
    """(problem, vehicle) of ``problem``'s fit with the primary peak in form ``alt``, its
    values those of ``vehicle`` (the rise, where it restarts, at its start: ``_rise_start``).
    Its compiled functions serve every form (``shared_forms``): made once per drops, channels
    and solver."""
    names = _form_names(problem.names, alt)
    veh = peak_form_vehicle(vehicle, "linear") if alt not in RISE_FORMS else vehicle
    site = problem.peak_site
    if _restarts_rise(problem, vehicle, alt):
        veh = _rise_start(veh, names, alt, site)
    veh = _inside_form(veh, names, alt, site)
    prob = CalibrationProblem(
        problem.drops, names, vehicle=veh, window_s=problem.window_s, pre_s=problem.pre_s,
        dt=problem.solver.dt, save_dt=problem.solver.save_dt, integrator=problem.integrator,
        smoothing_m=problem.solver.smoothing_m, smoothing_N=problem.solver.smoothing_N,
        fit_touchdown=problem.fit_touchdown, channels=problem.channels, peak_form=alt,
        shared_forms=True, peak_site=problem.peak_site)
    return prob, veh


def _inside_form(vehicle: jl.Vehicle, names, form: str, site: str = HONEYCOMB) -> jl.Vehicle:
    """``vehicle`` with each crush-peak value that lies outside its interval in ``form``
    (``interval``) moved inside, so that a refit in that form starts inside its rules instead
    of failing; values already inside are kept. A value above the interval (the exponential
    forms leave their L_peak1 EXP_SPAN times less room than the linear form whose fit starts
    them) goes to 0.9 of the way from its lower end; a value on its lower end (a fit that ran
    a value onto a bound ends there up to rounding) to ``START_ABOVE_BOUND`` of the way. The
    peak ratio first, then the length, then the rise: each interval depends on the ones
    before."""
    for n in ("peak1", "L_peak1", "L_rise1"):
        if n in names:
            vals = get_values(vehicle, names)
            lo, hi = interval(n, names, vals, vehicle, form, site)
            x = vals[names.index(n)]
            if not lo < x < hi:
                at = START_ABOVE_BOUND if x <= lo else 0.9
                vehicle = set_values(vehicle, (n,), [lo + at * (hi - lo)])
    return vehicle


# where a refit's start moves a value that lies on the lower end of its interval, as a
# fraction of the interval: the transform's slope there is about this (at_bound's limit is
# 1e-6), so the optimiser moves it freely, and it is far below any value's scatter
START_ABOVE_BOUND = 1e-3


def _restarts_rise(problem: CalibrationProblem, vehicle: jl.Vehicle, alt: str) -> bool:
    """Whether the refit in form ``alt`` starts L_rise1 afresh: where it is new, and between
    the ripple and the other forms (a rise length is no fold length)."""
    return alt in RISE_FORMS and (vehicle.honeycomb.peak_rise1 is None
                                  or (alt == "ripple") != (problem.peak_form == "ripple"))


# The ripple's refit needs a start near the record's folds: a fold length one fold's error
# away locks onto the wrong folds (each fold's peak moves by its number times the error), and
# the fit's own peak is a poor start for the other two numbers (a linear fall spreads the
# folds' work over a long L_peak1, where the ripple's rule L_f >= L_peak1 / 4 forbids short
# folds). So it screens starts by chi^2 alone (a run each, no Jacobian), the other values at
# the fit's: fold lengths RIPPLE_START_RATIO apart, each with every decay of RIPPLE_DECAYS
# (L_f / L_peak1: per fold exp(-q), 0.78, 0.61, 0.37) and the peak height that keeps the fit's
# crush work above F1, (peak1 - 1) F1 L_peak1 / 2 in the ripple. A start's chi^2 only points
# near a basin, and the next fold length's basin lies about 8 % away (the third fold moves by
# a sixth of a fold), so the refit probes RIPPLE_PROBE_ITER steps from each of the
# RIPPLE_REFITS best starts whose fold lengths lie RIPPLE_DISTINCT apart and goes on from the
# one of least chi^2 (docs/calibration.md, item 9).
RIPPLE_START_RATIO, RIPPLE_STARTS_MAX, RIPPLE_DECAYS = 1.05, 64, (0.25, 0.5, 1.0)
RIPPLE_REFITS, RIPPLE_DISTINCT, RIPPLE_PROBE_ITER = 3, 1.06, 6


def _excess_work(vehicle: jl.Vehicle) -> float:
    """The crush work of the primary peak of ``vehicle`` (its form applied) above F1 [J]:
    the virgin curve's excess, integrated over the primary plateau."""
    hc = vehicle.honeycomb.curve()
    x = jnp.linspace(float(hc.x_L1), float(hc.x_L2), 8001)
    f = np.asarray(_virgin_force(x, hc)) - float(hc.F1)
    return float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(np.asarray(x))))


_virgin_force = jax.jit(jax.vmap(jl.laws.honeycomb_virgin_force, in_axes=(0, None)))


def ripple_starts(problem: CalibrationProblem, vehicle: jl.Vehicle, work: float) -> list:
    """The (peak1, L_peak1, L_rise1) starts the ripple's refit screens, inside the ripple's
    bounds (``interval``), the other values those of ``vehicle``: for each decay q of
    RIPPLE_DECAYS, fold lengths L_f RIPPLE_START_RATIO apart from the shortest the rule on
    the falls allows (4 a / k with a = 2 work q / L_f; at most RIPPLE_STARTS_MAX of them) to
    the room's end, L_peak1 = L_f / q, peak1 = 1 + 2 work / (L_peak1 F1). None where the fit's
    peak does no work (``work`` <= 0: nothing to keep)."""
    if not work > 0.0:
        return []
    names = _form_names(problem.names, "ripple")
    veh = set_values(vehicle, ("L_rise1",), [START_IF_OFF["L_rise1"]])
    vals = get_values(veh, names)
    f1, k = (float(vals[names.index(n)]) if n in names else float(PARAMS[n][0](veh))
             for n in ("F1", "k"))
    i = {n: names.index(n) for n in ("peak1", "L_peak1", "L_rise1")}
    out = []
    no_peak = vals.copy()
    no_peak[i["peak1"]] = 1.0
    site = problem.peak_site
    hi = float(interval("L_rise1", names, no_peak, veh, "ripple", site)[1])  # the room's end
    for q in RIPPLE_DECAYS:
        lo = max(math.sqrt(8.0 * work * q / k), hi / RIPPLE_START_RATIO ** RIPPLE_STARTS_MAX)
        n = max(math.ceil(math.log(hi / lo) / math.log(RIPPLE_START_RATIO)), 1) if hi > lo else 0
        for j in range(n):
            fold = lo * RIPPLE_START_RATIO ** (j + 0.5)
            v = vals.copy()
            v[i["peak1"]], v[i["L_peak1"]], v[i["L_rise1"]] = (
                1.0 + 2.0 * work * q / (fold * f1), fold / q, fold)
            bounds = {n_: interval(n_, names, v, veh, "ripple", site) for n_ in i}
            if all(lo_ < v[i[n_]] < hi_ for n_, (lo_, hi_) in bounds.items()):
                out.append(tuple(float(v[i[n_]]) for n_ in i))
    return out


def _screen_folds(problem: CalibrationProblem, sub: CalibrationProblem, vehicle: jl.Vehicle,
                  theta) -> list:
    """``vehicle`` at the ripple's starts (``ripple_starts``) of least chi^2 in ``sub`` (the
    ripple's problem in the refit's window), best first: at most RIPPLE_REFITS, their fold
    lengths at least RIPPLE_DISTINCT apart (empty where no start lies inside the bounds or
    runs)."""
    n_t = len(problem.drops) if problem.fit_touchdown else 0
    work = _excess_work(problem.vehicle_at(theta))
    scored = []
    for start in ripple_starts(problem, vehicle, work):
        try:
            veh = set_values(vehicle, ("peak1", "L_peak1", "L_rise1"), start)
            scored.append((_chi2(sub, sub.theta_from(veh, theta[problem.n_z:] if n_t
                                                     else None)), start[2], veh))
        except (jl.SimulationError, jl.ConfigError):
            continue
    picked = []
    for chi2, fold, veh in sorted(scored, key=lambda c: c[0]):
        if all(max(fold / f, f / fold) >= RIPPLE_DISTINCT for _, f, _ in picked):
            picked.append((chi2, fold, veh))
        if len(picked) == RIPPLE_REFITS:
            break
    return [veh for _, _, veh in picked]


def motion_fit(problem: CalibrationProblem, res) -> dict | None:
    """For a fit whose peak sits on the force channels (``peak_site="forces"``): the residual
    variance factor of the motion channels alone (stroke, body acceleration; ``res`` the
    plain least-squares residuals at the optimum), and ``misfit``: above the misfit test's
    MISFIT_SIGMA2. There the drop runs without the peak, so the motion of a record whose peak
    is the honeycomb's (crush work) misfits; a peak on the force channels leaves it at the
    noise. None for a fit in the honeycomb or without motion channels."""
    if problem.peak_site != FORCES:
        return None
    motion, rows = _motion_rows(problem)
    if not rows.any():
        return None
    r = np.asarray(res).reshape(problem.data.shape)[rows]
    s2 = float(r @ r) / r.size
    return dict(variance_factor=s2, misfit=bool(s2 > MISFIT_SIGMA2),
                channels=[c for c, m in zip(problem.channels, motion) if m])


def precompile_forms(problem: CalibrationProblem, form: str):
    """A thread that compiles the functions of the other peak forms (``model_form_spread``),
    for a fit whose own functions do not serve them, while the fit runs (XLA compiles without
    the interpreter lock); join it before the spread."""
    import threading

    def work():
        try:
            for alt in PEAK_FORMS:
                if alt != form:
                    prob, veh = _form_problem(problem, problem.vehicle, alt)
                    prob.compile(prob.theta_from(veh))
        except (jl.SimulationError, jl.ConfigError, np.linalg.LinAlgError):
            pass  # the spread itself records a form that fails

    t = threading.Thread(target=work, daemon=True)
    t.start()
    return t


# the least loss decrease (0.5 chi^2) that continues a refit of a form with the peak on the
# force channels: a thousandth of the AIC differences that decide between forms
FORCES_REFIT_ATOL = 0.01


def _refit_form(problem: CalibrationProblem, base: jl.Vehicle, theta, alt: str, huber_c,
                max_iter: int) -> dict | None:
    """``problem``'s final window refitted from ``base`` (its fitted vehicle) with the primary
    peak in form ``alt`` (``model_form_spread``): its values, chi^2 and shift against the
    fit; None where it failed. The ripple, where its fold length restarts, from its screened
    starts (``_screen_folds``): each probes RIPPLE_PROBE_ITER steps, the best one goes on."""
    names, values = problem.names, problem.values(theta)
    n_t = len(problem.drops) if problem.fit_touchdown else 0
    w = problem.active_window_s
    try:
        prob, veh = _form_problem(problem, base, alt)
        sub = prob.windowed(w)
        starts = [veh]
        if alt == "ripple" and _restarts_rise(problem, base, alt):
            starts = _screen_folds(problem, sub, base, theta) or starts
    except (jl.SimulationError, jl.ConfigError):
        return None
    probe = RIPPLE_PROBE_ITER if len(starts) > 1 else max_iter
    # a peak on the force channels is a kinked gain of the crush: its refits crawl on in
    # steps that change chi^2 by thousandths (tens of iterations), far below what moves the
    # forms' comparison
    atol = FORCES_REFIT_ATOL if problem.peak_site == FORCES else 0.0
    best = None
    for veh in starts:
        try:
            th0 = sub.theta_from(veh, theta[problem.n_z:] if n_t else None)
            th, _, _ = levenberg_marquardt(sub.robust(huber_c), th0, max_iter=probe,
                                           ftol=FTOL, atol=atol)
        except (jl.SimulationError, jl.ConfigError, np.linalg.LinAlgError):
            continue
        chi2 = _chi2(sub, th)
        if np.isfinite(chi2) and (best is None or chi2 < best[1]):
            best = (th, chi2)
    if best is None:
        return None
    try:
        th = best[0]
        if probe < max_iter:
            th, _, _ = levenberg_marquardt(sub.robust(huber_c), th, max_iter=max_iter - probe,
                                           ftol=FTOL, atol=atol)
        v, chi2 = sub.values(th), _chi2(sub, th)
    except (jl.SimulationError, jl.ConfigError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(v)):
        return None
    shift = [0.0 if (n in SHAPE_PARAMS or n not in prob.names)
             else float(v[prob.names.index(n)] - values[i]) for i, n in enumerate(names)]
    return dict(values=dict(zip(prob.names, v.tolist())), chi2=chi2,
                n_params=len(prob.names) + n_t, refit=True, shift=dict(zip(names, shift)),
                starts=len(starts))


def form_refits(problem: CalibrationProblem, theta, form: str, huber_c, max_iter: int,
                pool) -> dict:
    """``model_form_spread``'s refits of ``problem``'s final window in every other peak form,
    submitted to ``pool`` (an executor: XLA frees the interpreter lock, so they share the
    cores): {form: future of ``_refit_form``}, the ripple's (its screen and refits, the
    longest) first."""
    base = set_values(problem.vehicle, problem.names, problem.values(theta))
    alts = (["ripple"] if form != "ripple" else []) + [
        alt for alt in PEAK_FORMS if alt not in (form, "ripple")]
    return {alt: pool.submit(_refit_form, problem, base, theta, alt, huber_c, max_iter)
            for alt in alts}


def model_form_spread(problem: CalibrationProblem, theta, form: str, huber_c=None,
                      max_iter: int = 60, rho1: float = 0.0, refits: dict | None = None) -> dict:
    """How far the fitted values move when the primary crush peak takes another of its forms
    (``PEAK_FORMS``), among the forms the data support: the final window refitted from
    ``theta``'s values in each other form (same drops, channels, window and Huber
    threshold). Per form: its values, chi^2 (plain least squares), AIC = chi^2 + 2 x its
    fitted parameters, dAIC_adjusted = (AIC - the least AIC) / the long-run variance factor
    max(s^2, 1) (1 + rho1) / (1 - rho1) (s^2: the best form's residual variance factor;
    ``rho1``: the lag-1 residual autocorrelation of the fit in ``form``), whether it is
    plausible (dAIC_adjusted <= DAIC_PLAUSIBLE) and its shift against this fit (None where
    the refit failed). ``spread``: per parameter the largest absolute shift over the
    plausible forms (this fit's own form included, shift 0), 0 on the peak's own parameters,
    whose meaning differs between forms (``SHAPE_PARAMS``); ``best_supported``: the plausible
    form of least misfit-adjusted BIC (``best_supported_form``). ``refits``: the refits'
    futures (``form_refits``), where the caller runs them on an executor it shares with other
    work (default: run here on REFIT_THREADS threads)."""
    names = problem.names
    values = problem.values(theta)
    n_t = len(problem.drops) if problem.fit_touchdown else 0
    if refits is None:
        with ThreadPoolExecutor(max_workers=REFIT_THREADS) as pool:
            refits = form_refits(problem, theta, form, huber_c, max_iter, pool)
    forms = {form: dict(values=dict(zip(names, values.tolist())), chi2=_chi2(problem, theta),
                        n_params=len(names) + n_t, refit=False,
                        shift=dict.fromkeys(names, 0.0))}
    forms.update((alt, f.result()) for alt, f in refits.items())
    done = {k: f for k, f in forms.items() if f is not None}
    n_obs = problem.n_obs
    for f in done.values():
        f["aic"] = f["chi2"] + 2 * f["n_params"]
    least_aic = min(done, key=lambda k: done[k]["aic"])
    s2 = done[least_aic]["chi2"] / max(n_obs - done[least_aic]["n_params"], 1)
    rho = min(max(rho1, 0.0), 0.99)
    inflation = max(s2, 1.0) * (1.0 + rho) / (1.0 - rho)
    spread = np.zeros(len(names))
    for f in done.values():
        f["bic_adjusted"] = f["chi2"] / inflation + f["n_params"] * math.log(n_obs)
        f["daic_adjusted"] = (f["aic"] - done[least_aic]["aic"]) / inflation
        f["plausible"] = bool(f["daic_adjusted"] <= DAIC_PLAUSIBLE)
        if f["plausible"]:
            spread = np.maximum(spread, np.abs([f["shift"][n] for n in names]))
    return dict(form=form, forms=forms, spread=dict(zip(names, spread.tolist())),
                best_supported=best_supported_form(done), misfit_inflation=inflation,
                daic_plausible=DAIC_PLAUSIBLE,
                plausible=[k for k, f in done.items() if f["plausible"]],
                failed=[k for k, f in forms.items() if f is None],
                applies_to=[n for n in names if n not in SHAPE_PARAMS])


def best_supported_form(forms: dict) -> str:
    """The form the report names: of the plausible ``forms`` (``model_form_spread``'s), the one
    of least misfit-adjusted BIC, chi^2 / c + p ln n (``bic_adjusted``; c the long-run variance
    factor of the adjusted AIC differences, 1 on data the forms represent). Naming a form asks
    which shape made the record, where AIC's penalty of 2 per parameter over-fits: a built-up
    form (one more parameter, L_rise1) beats the plain one it contains whenever noise lowers
    chi^2 by 2, on about one record in six; ln n (about 8 at 3000 samples) asks for a real
    improvement, and dividing chi^2 by c keeps that true where correlated residuals inflate
    its differences. Which forms are plausible, and so the peak-shape term, stays with the
    adjusted AIC (the wider set). No plausible form (a chi^2 that is not finite): the form of
    least AIC."""
    done = {k: f for k, f in forms.items() if f is not None}
    plausible = [k for k, f in done.items() if f["plausible"]]
    if not plausible:
        return min(done, key=lambda k: done[k]["aic"])
    return min(plausible, key=lambda k: done[k]["bic_adjusted"])


def has_no_peak(names, vehicle: jl.Vehicle) -> bool:
    """The fitted model has no primary crush peak: none of its parameters is fitted and the
    vehicle's honeycomb has neither the law's peak nor a tabulated excess."""
    hc = vehicle.honeycomb
    return (not any(n in names for n in SHAPE_PARAMS) and hc.peak_ratio1 is None
            and hc.excess1 is None)


def wants_peak_model_term(setting, misfit, names, vehicle: jl.Vehicle) -> bool:
    """Whether a fit gets the missing-peak term: ``setting`` "auto" (``fit``'s
    ``peak_model_term``), its residuals show misfit (``misfit``: the misfit messages) and the
    fitted model has no crush peak (``has_no_peak``)."""
    return setting == "auto" and bool(misfit) and has_no_peak(names, vehicle)


# how much worse than the fit without a peak the fit with one may end before it counts as
# failed (rounding of the two chi^2 sums; its model holds the one without the peak)
NESTED_CHI2_RTOL = 1e-6


def _refit_outcome(future):
    """A bias term's refit (a future, or None where none was started): its ``FitResult``, or
    the error it failed with, which the term records."""
    if future is None:
        return None
    try:
        return future.result()
    except (jl.SimulationError, jl.ConfigError, np.linalg.LinAlgError) as err:
        return err


def _nested_term(result: FitResult, nested, *, own: str, other: str, worse: str) -> dict:
    """A bias term's record: ``nested`` (a fit whose model holds ``result``'s, or the
    exception it raised) and, where it reached its optimum, each value's shift to it, added
    in quadrature to ``result.std_errors_total``. Keys: ``chi2_<own>`` and ``chi2_<other>``;
    ``failed`` (why no term: the exception, non-finite values, or ``nested`` ending worse
    than ``worse``: its model holds that one, so its optimum fits at least as well, and a fit
    that ends worse stopped short of it); where added: ``added``, ``params``, ``values``,
    ``std_errors_hac``, ``shift``, ``term``, ``misfit_<other>``,
    ``residual_variance_factor_<other>``, ``at_bound_<other>`` and ``wall_s``."""
    if not isinstance(nested, FitResult):
        return dict(failed=f"{type(nested).__name__}: {nested}")
    names = result.names
    shift = np.array([nested.value(n) for n in names]) - result.values
    chi2_own = _chi2(result.problem, result.theta)
    chi2_nested = _chi2(nested.problem, nested.theta)
    rec = {f"chi2_{own}": chi2_own, f"chi2_{other}": chi2_nested}
    if not chi2_nested <= chi2_own * (1.0 + NESTED_CHI2_RTOL):
        rec["failed"] = (f"it ended worse than {worse} (chi2 {chi2_nested:.6g} against "
                         f"{chi2_own:.6g}), short of its optimum: an optimiser failure, not "
                         "a misfit (its model holds that one)")
    elif not np.all(np.isfinite(shift)):
        rec["failed"] = "non-finite values"
    else:
        term = np.abs(shift)
        result.std_errors_total = np.sqrt(result.std_errors_total**2 + term**2)
        d = nested.diagnostics
        rec.update({
            "added": True, "params": list(nested.names),
            "values": dict(zip(nested.names, nested.values.tolist())),
            "std_errors_hac": dict(zip(nested.names, nested.std_errors_hac.tolist())),
            "shift": dict(zip(names, shift.tolist())), "term": dict(zip(names, term.tolist())),
            f"misfit_{other}": d["misfit"], "started_from": d.get("started_from"),
            f"residual_variance_factor_{other}": d["residual_variance_factor"],
            f"at_bound_{other}": d["at_bound"], "wall_s": nested.wall_s})
    return rec


def add_peak_model_term(result: FitResult, with_peak) -> None:
    """Widen ``result`` (a fit without a crush peak whose residuals show misfit) by the
    missing-peak term: per parameter |value without the peak - value with it|, ``with_peak``
    the same fit with the primary peak (``PEAK_PARAMS``), added in quadrature to
    ``std_errors_total``; recorded in ``diagnostics["peak_model_term"]``. ``with_peak`` an
    exception (the fit with the peak failed): the term is 0 and the failure recorded."""
    names = result.names
    reason = ("the residuals show misfit (" + "; ".join(result.diagnostics["misfit"])
              + ") and the fitted model has no crush peak: the bias a peak leaves is shared "
              "by every channel, so neither the HAC error nor the channel spread covers it; "
              "the fit was repeated with the primary crush peak (" + ", ".join(PEAK_PARAMS)
              + ", the law's linear form: on the final window from this fit's optimum with "
              "the peak all but off, and from the start through every stage, the one of "
              "least chi2 kept) and each value's shift to "
              "that fit is added in quadrature to std_error_total")
    rec = dict(reason=reason, added=False, failed=None, params=None, values=None,
               std_errors_total=None, shift=None, term=dict.fromkeys(names, 0.0))
    # the model with the peak holds the one without it (peak off)
    rec.update(_nested_term(result, with_peak, own="without", other="with",
                            worse="the fit without a peak"))
    result.diagnostics["peak_model_term"] = rec
    mark_interval_bounded(result)


# the missing-peak term's fit starts with peak1 this far into its interval above 1 (its
# interval's lower end, 1, is the model without the peak, which the transform cannot reach)
PEAK_OFF_REL = 1e-3


def peak1_all_but_off(vehicle: jl.Vehicle, names, *form_site) -> float:
    """peak1 ``PEAK_OFF_REL`` into its interval above 1 (``interval`` of a fit of ``names``
    from ``vehicle``, the peak in ``form_site``): the nearest a fit with the peak starts to
    the model without it."""
    lo, hi = interval("peak1", names, get_values(vehicle, names), vehicle, *form_site)
    return lo + PEAK_OFF_REL * (hi - lo)


def peak_off_start(fitted: jl.Vehicle, names) -> dict:
    """The start of the missing-peak term's fit: ``fitted``'s values of ``names`` (the fit
    without a peak's optimum) and the primary peak all but off (``peak1_all_but_off``,
    L_peak1 the vehicle's or its ``START_IF_OFF``), so that the fit with the peak starts
    where the model without it ended."""
    names_p = tuple(names) + PEAK_PARAMS
    on = switch_on(fitted, names_p)
    start = dict(zip(names_p, get_values(on, names_p).tolist()))
    start["peak1"] = peak1_all_but_off(on, names_p)
    return start


def _least_chi2(runs: dict) -> FitResult:
    """Of ``runs`` ({label: callable returning a FitResult}), run in turn, the result of
    least chi^2 (``_chi2`` of its final problem), its label in
    ``diagnostics["started_from"]``; a run that raises counts as none, and where every one
    raised, the last error is raised."""
    best, error = None, None
    for label, run in runs.items():
        try:
            res = run()
        except (jl.SimulationError, jl.ConfigError, np.linalg.LinAlgError) as err:
            error = err
            continue
        res.diagnostics["started_from"] = label
        if best is None or _chi2(res.problem, res.theta) < _chi2(best.problem, best.theta):
            best = res
    if best is None:
        raise error
    return best


def wants_no_peak_check(names, inner: bool) -> bool:
    """Whether a fit is checked against its special case without the crush peak
    (``_against_no_peak``): it fits the primary peak (peak1) and other parameters, and is no
    fit run inside another (those are checked by the term that runs them)."""
    return not inner and "peak1" in names and bool(no_peak_names(names))


def peak_off_theta(problem: CalibrationProblem, vehicle: jl.Vehicle, no_peak: FitResult):
    """``problem``'s theta at the fit without the peak's optimum (``no_peak``: its values and
    touchdowns) with the primary peak all but off (``peak1_all_but_off``) and the peak's
    other parameters at ``vehicle``'s (the fit's start)."""
    veh = set_values(vehicle, no_peak.names, no_peak.values)
    veh = set_values(veh, ("peak1",), [peak1_all_but_off(veh, problem.names, problem.peak_form,
                                                         problem.peak_site)])
    shifts = no_peak.theta[len(no_peak.names):] if problem.fit_touchdown else None
    return problem.theta_from(veh, shifts_ms=shifts)


# how much worse (in chi^2 units: twice the loss) than its model without the peak a fit with
# the peak may end before it counts as no optimum: one unit, far below what a likelihood
# ratio test resolves (2 degrees of freedom at 1 %: 9.2). Run from the no-peak optimum with
# the peak at its bound, the fit stopped 0.004 above it (the rig's 0.2 m drop without a
# peak: the peak's coordinate flat there); the wrong minima it catches lie orders of
# magnitude above (chi2 4.16e6 against 2994)
NO_PEAK_CHI2_ATOL = 1.0
FROM_START, FROM_NO_PEAK = "the fit's start", "the no-peak optimum, the peak all but off"


def no_peak_failure(check: dict | None) -> str | None:
    """Why a fit with the crush peak is no optimum (``diagnostics["no_peak_check"]``): it ended
    worse than its special case without the peak; None where it did not."""
    return None if check is None else check.get("failed")


def fixed_defaults(names) -> tuple:
    """The default fitted parameters (``DEFAULT_PARAMS``) that a fit of ``names`` leaves fixed
    at the vehicle's values: the fixed-parameter term frees them."""
    return tuple(n for n in DEFAULT_PARAMS if n not in names)


def wants_fixed_params_term(setting, misfit, names) -> bool:
    """Whether a fit gets the fixed-parameter term: ``setting`` "auto" (``fit``'s
    ``fixed_params_term``), its residuals show misfit (``misfit``: the misfit messages) and
    it leaves some of the default fitted parameters fixed (``fixed_defaults``)."""
    return setting == "auto" and bool(misfit) and bool(fixed_defaults(names))


def add_fixed_params_term(result: FitResult, wider) -> None:
    """Widen ``result`` (a fit of a subset of the default parameters whose residuals show
    misfit) by the fixed-parameter term: per parameter |value - value with the fixed default
    parameters freed as well|, ``wider`` that fit (run from ``result``'s optimum), added in
    quadrature to ``std_errors_total``; recorded in ``diagnostics["fixed_params_term"]``.
    ``wider`` an exception (that fit failed), or a fit that ended worse than ``result`` (its
    model holds this one: it stopped short of its optimum): the term is 0, the failure
    recorded, and the interval marked as not bounded (``mark_interval_bounded``)."""
    names = result.names
    freed = fixed_defaults(names)
    reason = ("the residuals show misfit (" + "; ".join(result.diagnostics["misfit"])
              + ") and the fit leaves " + ", ".join(freed) + " fixed at the vehicle's values: "
              "where the truth differs in them, every fitted value takes up the difference, "
              "in every channel alike, so neither the HAC error, the channel spread nor the "
              "missing-peak term covers that bias; the fit was repeated with them freed as "
              "well (from this fit's optimum, same settings) and each value's shift to that "
              "fit is added in quadrature to std_error_total")
    rec = dict(reason=reason, added=False, failed=None, freed=list(freed), params=None,
               values=None, std_errors_hac=None, shift=None, term=dict.fromkeys(names, 0.0))
    # the wider model holds this one (its extra values at the vehicle's)
    rec.update(_nested_term(result, wider, own="fit", other="wider",
                            worse="the fit with them fixed"))
    result.diagnostics["fixed_params_term"] = rec
    mark_interval_bounded(result)


# the bias terms a misfit calls for, by their diagnostics key: (name in words, what it covers)
BIAS_TERMS = (("peak_model_term", "missing-peak term", "how far a crush peak moves the values"),
              ("fixed_params_term", "fixed-parameter term",
               "how far the parameters left fixed move the values"),
              ("drop_spread", "drop spread", "how far the drops pull the values apart"))


def drop_spread_record(names, shifts: dict, spread: np.ndarray, channel: np.ndarray,
                       se: np.ndarray) -> dict:
    """The drop spread's record (``misfit.drop_spread``): per drop left out the values'
    shifts (None: that refit failed), ``spread`` (the largest absolute shift of each value
    over the drops that refitted, added in quadrature to ``std_errors_total``; 0 where every
    refit failed), ``largest`` (the drop whose absence moves a value most in units of ``se``,
    the trusted errors: drop, parameter, shift, z), ``dominates`` (the parameters whose drop
    spread exceeds their channel spread ``channel``: then the drops disagree more than the
    channels) and ``failed`` (why the spread is incomplete, or None), ``failed_drops``."""
    spread = np.nan_to_num(spread, nan=0.0)
    failed = [d for d, v in shifts.items() if v is None]
    best = None
    for d, v in shifts.items():
        for i, n in enumerate(names):
            if v is None:
                continue
            z = abs(v[i]) / se[i] if se[i] > 0 else 0.0
            if math.isfinite(z) and (best is None or z > best["z"]):
                best = dict(drop=d, param=n, shift=float(v[i]), z=float(z))
    return dict(
        shifts={d: None if v is None else dict(zip(names, v.tolist())) for d, v in shifts.items()},
        spread=dict(zip(names, spread.tolist())), largest=best,
        dominates=[n for n, a, b in zip(names, spread, np.nan_to_num(channel)) if a > b],
        failed=(f"the refit without the drop {', '.join(failed)} failed" if failed else None),
        failed_drops=failed)


def _drops_disagree(rec: dict) -> str:
    """'; the drops disagree: ...' where the drop spread exceeds the channel spread of some
    parameter (``rec["dominates"]``), naming the drop whose absence moves a value most; ''
    otherwise."""
    best = rec["largest"]
    if not rec["dominates"] or best is None:
        return ""
    n = best["param"]
    unit = "" if PARAMS[n][1] == "1" else f" {PARAMS[n][1]}"
    return (f"; the drops disagree (the values move more when one drop is left out than when "
            f"one channel is, for {', '.join(rec['dominates'])}: the drops' articles or "
            f"conditions differ, e.g. block-to-block scatter of the honeycomb), most without "
            f"{best['drop']}: {n} moves by {best['shift']:+.3g}{unit} ({best['z']:.2g} x its "
            "HAC standard error); std_error_total holds the drop spread "
            "(misfit.drop_spread)")


def mark_interval_bounded(result: FitResult) -> None:
    """Record whether the reported interval bounds the bias the misfit calls for:
    ``diagnostics["interval_bounded"]`` False, with ``interval_not_bounded`` naming each
    bias term that was called for and could not be computed (its refit failed), else True
    (and None). Such an interval is the scatter about a biased fit, not a bound on its error:
    the values can lie many of its standard errors from the truth. A failed missing-peak term
    is not called for where the fit with the fixed parameters freed (the fixed-parameter
    term, added) shows no misfit: the misfit was theirs, and a fit without a peak that fits
    the record gets no missing-peak term either (``peak_not_called_for`` says so)."""
    d = result.diagnostics
    fp = d.get("fixed_params_term")
    explained = bool(fp is not None and fp["added"] and not fp["misfit_wider"])
    why = [f"the {label} could not be computed ({rec['failed']}), so std_error_total leaves "
           f"out {what}"
           for key, label, what in BIAS_TERMS
           if (rec := d.get(key)) is not None and rec.get("failed")
           and not (key == "peak_model_term" and explained)]
    pm = d.get("peak_model_term")
    d["peak_not_called_for"] = (
        "the fit with " + ", ".join(fp["freed"]) + " freed shows no misfit: the misfit comes "
        "from the parameters left fixed, which the fixed-parameter term covers, so the "
        "missing-peak term's failure leaves no bias uncovered"
        if explained and pm is not None and pm.get("failed") else None)
    d["interval_bounded"] = not why
    d["interval_not_bounded"] = why or None


def _rise_start(vehicle: jl.Vehicle, names, form: str | None = None,
                site: str = HONEYCOMB) -> jl.Vehicle:
    """``vehicle`` with the rise switched on at its ``START_IF_OFF`` length, or where that
    lies outside its bounds in ``form``, in the middle of them; in the ripple form, where
    L_rise1 is the fold length, always in the middle of its bounds."""
    veh = set_values(vehicle, ("L_rise1",), [START_IF_OFF["L_rise1"]])
    vals = get_values(veh, names)
    lo, hi = interval("L_rise1", names, vals, veh, form, site)
    if form == "ripple" or not lo < START_IF_OFF["L_rise1"] < hi:
        veh = set_values(vehicle, ("L_rise1",), [0.5 * (lo + hi)])
    return veh


def _bound_message(n, names, values, vehicle, form=None, site=HONEYCOMB) -> str:
    """What a value at a bound of its transform (``at_bound``; the primary peak in ``form``,
    sitting at ``site``) means, for the report."""
    i = names.index(n)
    lo, hi = interval(n, names, values, vehicle, form, site)
    side = "lower" if values[i] - lo < hi - values[i] else "upper"
    return (f"{n} = {values[i]:.6g} {PARAMS[n][1]} ended at the {side} bound of its range "
            f"({lo:.6g}, {hi:.6g}) set by the vehicle's rules (jaxland.validate_vehicle): the "
            "value is the rule's limit, not the data's, and its standard errors (through a "
            "flat transform there) do not hold; the data ask for more than the model allows "
            + ("(a crush peak sharper or higher than the law's rules: the fit reproduces the "
               "peak's work, not its shape)" if n in SHAPE_PARAMS else "here"))


def _disagreement(names, shifts, se) -> str:
    """'; the channels disagree most on P: without C it moves by X (Y x its HAC standard
    error)' for the largest shift in units of ``se``, the HAC errors (called under misfit
    only); '' when there is none."""
    best = None
    for ch, v in shifts.items():
        if v is None:
            continue
        for i, n in enumerate(names):
            z = abs(v[i]) / se[i] if se[i] > 0 else 0.0
            if math.isfinite(z) and (best is None or z > best[0]):
                best = (z, n, ch, v[i])
    if best is None:
        return ""
    z, n, ch, d = best
    unit = "" if PARAMS[n][1] == "1" else f" {PARAMS[n][1]}"
    return (f"; the channels disagree most on {n}: without {ch} it moves by {d:+.3g}{unit} "
            f"({z:.2g} x its HAC standard error)")


def _window_text(a: float, b: float) -> str:
    """A window [a, b] s relative to touchdown, in words."""
    if a < 0.0:
        return f"from {-a * 1e3:.0f} ms before to {b * 1e3:.0f} ms after touchdown"
    return f"{a * 1e3:.0f} to {b * 1e3:.0f} ms after touchdown"


def _in_thread(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` started in a thread of its own; its future (``result()``
    re-raises what it raised). XLA compiles and runs without the interpreter lock, so the
    caller's own work runs beside it."""
    pool = ThreadPoolExecutor(max_workers=1)
    future = pool.submit(fn, *args, **kwargs)
    pool.shutdown(wait=False)
    return future


def _no_warning(*args, **kwargs) -> None:
    """``warnings.warn``'s stand-in for a fit run inside another (``_inner``): the outer fit
    reports what matters, and ``warnings.catch_warnings`` is not thread-safe."""


def robust_threshold(problem: CalibrationProblem, theta, k: float) -> float:
    """Huber threshold: ``k`` times the residuals' robust std (1.4826 MAD), at least ``k``
    (the residuals are in noise-std units, so the noise itself sets the floor)."""
    r, _ = problem.robust(None).residuals(theta)
    r = r[problem.mask.ravel() > 0]
    return k * max(1.4826 * float(np.median(np.abs(r))), 1.0)


def _identifiability(names, values, unc, bound=()) -> tuple[np.ndarray, list]:
    """Which parameters the data identify, and a message for each that they do not. A value
    at a bound (``bound``) is not identified either, and its own message (``_bound_message``)
    says why: its column vanishes because the transform is flat there, not because the data
    ignore it."""
    ok = np.ones(len(names), bool)
    msgs = []
    for i, n in enumerate(names):
        rel = unc["se"][i] / abs(values[i]) if values[i] else math.inf
        if n in bound:
            ok[i] = False
        elif unc["zero"][i]:
            ok[i] = False
            what = "F2 - F1 (F2 is fitted as its excess over F1)" if n == "F2" else "it"
            msgs.append(f"{n} is not identified by the data: the residuals do not depend on it "
                        f"(Jacobian column {unc['col_rel'][i]:.1e} of the largest), so {what} "
                        f"stayed at its start value (now {values[i]:.6g} {PARAMS[n][1]})"
                        + (" (the stroke never reaches x_L2, where the secondary honeycomb "
                           "starts)" if n in ("F2", "k_b3") else "")
                        + "; fix it or add a drop that exercises it")
        elif not math.isfinite(rel) or rel > REL_SE_LIMIT:
            ok[i] = False
            msgs.append(f"{n} is poorly identified: standard error {unc['se'][i]:.3g} "
                        f"{PARAMS[n][1]} is {rel:.0%} of its value (limit "
                        f"{REL_SE_LIMIT:.0%}); the data barely constrain it, or it trades "
                        "off against another parameter (see the correlation matrix)")
    return ok, msgs


@dataclass(frozen=True)
class FitSettings:
    """A fit's arguments, checked (``check_fit``): what ``fit`` runs with."""
    drops: list
    names: tuple
    windows: tuple  # the growing fit windows [s]
    stages_w: list  # the windows of every stage, the refit's included [s]
    refine_note: str | None  # why the refit's window is not refine_window_s as given
    integrator: str
    smoothing_m: float
    smoothing_N: float
    start_vehicle: jl.Vehicle
    start_values: np.ndarray


def _check_start_step(base, names, start: dict, dt: float, integrator: str, peak_form,
                      peak_site) -> None:
    """A step ``dt`` above the start vehicle's stability limit but within the base vehicle's
    is the start values' doing: refused as ``start.<name>`` (the start value whose vehicle
    alone has a limit below ``dt``, with that limit), or ``start`` for several together."""
    def limit_of(values):
        given = _start_vehicle(base, names, values)
        v = switch_on(given, names)
        if peak_form == "ripple" and given.honeycomb.peak_rise1 is None:
            v = _rise_start(v, names, "ripple", peak_site)
        return float(jl.stable_step(v, method=integrator))

    if dt > limit_of(None):
        return  # the base vehicle's own limit: dt is the cause
    for k, v in start.items():
        try:
            lim = limit_of({k: v})
        except jl.ConfigError:  # valid only with the other start values: judged together
            continue
        if dt > lim:
            raise jl.ConfigError(f"start.{k}", v, f"makes {integrator}'s stability limit "
                                 f"{lim:.3g} s, below the step dt = {dt:g} s (the base "
                                 f"vehicle's is {limit_of(None):.3g} s): start lower, or give "
                                 "a step within that limit")
    raise jl.ConfigError("start", start, f"together make {integrator}'s stability limit "
                         f"{limit_of(start):.3g} s, below the step dt = {dt:g} s (the base "
                         f"vehicle's is {limit_of(None):.3g} s)")


def refine_window(refine_window_s, windows, drops) -> tuple[float | None, str | None]:
    """The refit's window [s] (None: no refit) and, where it is not ``refine_window_s`` as
    given, why. A number is used as given, or refused by name where it is no longer than the
    last of ``windows`` (the refit is on a longer window) or longer than a record after its
    touchdown (the rule ``windows`` follow); None or 0: no refit. ``AUTO``:
    ``REFINE_WINDOW_S``, shortened to the shortest record after touchdown where one ends
    before it, and left out where that is no longer than the last window."""
    if refine_window_s is None or (refine_window_s == 0 and not isinstance(refine_window_s,
                                                                           bool)):
        return None, None
    last = windows[-1]
    ends = {d.name: (d.duration_after_touchdown_s, 0.5 / d.sample_rate_Hz) for d in drops}
    name = min(ends, key=lambda n: ends[n][0])
    shortest, half = ends[name]
    if refine_window_s == AUTO:
        w = REFINE_WINDOW_S
        if w <= last:
            return None, (f"no refit on a longer window: the default refine window "
                          f"({w:g} s) is not longer than the last window ({last:g} s)")
        if shortest - REFINE_END_MARGIN_S >= w - half:
            return w, None
        cut = shortest - REFINE_END_MARGIN_S
        if cut <= last:
            return None, (f"no refit on a longer window: the record {name} ends "
                          f"{shortest:.4g} s after touchdown, within the last window "
                          f"({last:g} s) and {REFINE_END_MARGIN_S * 1e3:g} ms, before the "
                          f"default refine window ({w:g} s)")
        return cut, (f"refine window {cut:.4g} s, not the default {w:g} s: the record {name} "
                     f"ends {shortest:.4g} s after touchdown, and the window stops "
                     f"{REFINE_END_MARGIN_S * 1e3:g} ms before its end (the filter's end "
                     "transient)")
    if isinstance(refine_window_s, bool) or not isinstance(refine_window_s, (int, float)) \
            or not (refine_window_s > 0 and math.isfinite(refine_window_s)):
        raise jl.ConfigError("refine_window_s", refine_window_s, "must be a number > 0 s "
                             "(None or 0: no refit)")
    w = float(refine_window_s)
    if w <= last:
        raise jl.ConfigError("refine_window_s", refine_window_s, f"must be longer than the "
                             f"last window ({last:g} s): the refit is on a longer window (0: "
                             "no refit)")
    if shortest < w - half:
        raise jl.ConfigError("refine_window_s", refine_window_s, f"is longer than the record "
                             f"{name} after touchdown ({shortest:.4g} s); give a refine window "
                             f"that ends within every record (<= {shortest:.4g} s), or 0 for "
                             "no refit")
    return w, None


def check_fit(drops, params=DEFAULT_PARAMS, *, vehicle: jl.Vehicle | None = None, start=None,
              windows=WINDOWS_S, refine_window_s: float | str | None = AUTO,
              robust: float | None = ROBUST_K, method: str = "lm", max_iter: int = 60,
              dt: float = 1e-5, integrator: str = INTEGRATOR, smoothing_m: float | None = None,
              smoothing_N: float | None = None, peak_form: str | None = None,
              model_form: bool | str = "auto", peak_model_term: bool | str = "auto",
              peak_site: str = HONEYCOMB, save_dt: float = SAVE_DT) -> FitSettings:
    """``fit``'s arguments checked (each bad one refused by name with ``jaxland.ConfigError``)
    before any compilation, so that a caller can refuse them before it announces a fit.
    ``channels`` and ``fit_touchdown`` are checked where they are used, by
    ``CalibrationProblem``, and ``save_dt`` there too: here only as the interval ``dt``
    must divide."""
    if isinstance(drops, DropTest):
        drops = [drops]
    drops = list(drops)
    if not drops:
        raise jl.ConfigError("drops", "[]", "give at least one drop test")
    names = check_names(params)
    check_peak_site(peak_site, names)
    if method not in ("lm", "lbfgs"):
        raise jl.ConfigError("method", method, "must be 'lm' or 'lbfgs'")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise jl.ConfigError("max_iter", max_iter, "must be an integer >= 1")
    if robust is not None and not (isinstance(robust, (int, float)) and 0 < robust < 1e6):
        raise jl.ConfigError("robust", robust, "must be a number > 0 (robust std units) or None")
    defaults = (smoothing_m is None, smoothing_N is None)
    if isinstance(integrator, str) and integrator in INTEGRATORS:
        default_m, default_n = SMOOTHING[integrator]
        smoothing_m = default_m if smoothing_m is None else smoothing_m
        smoothing_N = default_n if smoothing_N is None else smoothing_N
    integrator, smoothing_m, smoothing_N = check_integrator(integrator, smoothing_m,
                                                            smoothing_N)
    windows = tuple(float(w) for w in windows)
    if not windows or any(not (w >= WINDOW_MIN_S and math.isfinite(w)) for w in windows) or (
            any(b <= a for a, b in zip(windows, windows[1:]))):
        raise jl.ConfigError("windows", list(windows), "must be increasing numbers >= "
                             f"{WINDOW_MIN_S:g} s")
    base = drops[0].vehicle if vehicle is None else vehicle
    jl.validate_vehicle(base)
    check_peak_form(names, peak_form)
    given = _start_vehicle(base, names, start)
    start_vehicle = switch_on(given, names)
    if peak_form == "ripple" and given.honeycomb.peak_rise1 is None:
        start_vehicle = _rise_start(start_vehicle, names, "ripple", peak_site)  # a fold length
    # a default width no wider than the start vehicle's switches take (a stiff ground's give
    # is shorter than verlet's 1e-6 m); a width given is checked as given
    widest = smoothing_limits(start_vehicle)
    smoothing_m = min(smoothing_m, widest.length_m) if defaults[0] else smoothing_m
    smoothing_N = min(smoothing_N, widest.force_N) if defaults[1] else smoothing_N
    with named_as({"solver.smoothing_m": ("smoothing_m", smoothing_m),
                   "solver.smoothing_N": ("smoothing_N", smoothing_N)}):
        jl.Solver(method=integrator, smoothing_m=smoothing_m,
                  smoothing_N=smoothing_N).check_smoothing(start_vehicle)
    limit = float(jl.stable_step(start_vehicle, method=integrator))
    if isinstance(dt, (int, float)) and 0 < dt and dt > limit and isinstance(start, dict):
        _check_start_step(base, names, start, dt, integrator, peak_form, peak_site)
    if not (isinstance(dt, (int, float)) and 0 < dt <= limit):
        raise jl.ConfigError("dt", dt, f"must be in (0, {limit:.3g}] s (the stability limit of "
                             f"{integrator} for the start vehicle)")
    if isinstance(save_dt, (int, float)) and save_dt > 0 and not _whole_steps(save_dt, dt):
        raise jl.ConfigError("dt", dt, f"must divide the model's sampling interval, "
                             f"{save_dt:g} s, into whole steps (e.g. {save_dt:g} or "
                             f"{save_dt / 2:g} s)")
    start_values = get_values(start_vehicle, names)
    for d in drops:  # the fit's problem refuses it too (as window_s), but after the banner
        if d.duration_after_touchdown_s < windows[-1] - 0.5 / d.sample_rate_Hz:
            raise jl.ConfigError("windows", list(windows), f"the last window "
                                 f"({windows[-1]:g} s) is longer than the record {d.name} "
                                 f"after touchdown ({d.duration_after_touchdown_s:.4g} s); "
                                 "give windows that end within the record")
    refine, refine_note = refine_window(refine_window_s, windows, drops)
    stages_w = list(windows) + ([] if refine is None else [refine])
    if model_form not in ("auto", True, False):
        raise jl.ConfigError("model_form", model_form, "must be 'auto', True or False")
    if peak_model_term not in ("auto", False):
        raise jl.ConfigError("peak_model_term", peak_model_term, "must be 'auto' or False")
    if model_form is True and "peak1" not in names:
        raise jl.ConfigError("model_form", model_form, "needs peak1 among the fitted "
                             "parameters (the term spans the crush peak's forms)")
    return FitSettings(drops=drops, names=names, windows=windows, stages_w=stages_w,
                       refine_note=refine_note,
                       integrator=integrator, smoothing_m=smoothing_m, smoothing_N=smoothing_N,
                       start_vehicle=start_vehicle, start_values=start_values)


def fit(drops, params=DEFAULT_PARAMS, *, vehicle: jl.Vehicle | None = None, start=None,
        windows=WINDOWS_S, refine_window_s: float | str | None = AUTO,
        robust: float | None = ROBUST_K, multistart: bool = True, method: str = "lm",
        max_iter: int = 60,
        dt: float = 1e-5, save_dt: float = SAVE_DT, integrator: str = INTEGRATOR,
        smoothing_m: float | None = None, smoothing_N: float | None = None,
        fit_touchdown: bool = True, channels=None, peak_form: str | None = None,
        model_form: bool | str = "auto", peak_model_term: bool | str = "auto",
        fixed_params_term: bool | str = "auto",
        peak_site: str = HONEYCOMB, progress=None, _inner: bool = False,
        _start_shifts_ms=None, _no_peak: FitResult | None = None,
        _program: CalibrationProblem | None = None) -> FitResult:
    """Fit the quarter model's parameters ``params`` to one or more drop tests jointly.

    Parameters
    ----------
    drops : DropTest or list of them (``load_drop_test``)
    params : names to fit (default k, gamma, D_b, k_b1, F1, F2; optional chi, mu, k_a, k_b3,
        k_tan); the rest of the vehicle stays fixed
    vehicle : the vehicle whose other parameters are kept (default: the drops' configuration)
    start : start values, a Vehicle or ``{name: value}`` (default: ``vehicle``'s values)
    windows : growing fit windows after touchdown [s] on the first impact
    refine_window_s : one refit on this window [s], longer than the last of ``windows``
        (None or 0: skip); a number is used as given, or refused where a record ends before
        it after touchdown. ``"auto"`` (default): ``REFINE_WINDOW_S`` (150 ms), shortened to
        the shortest record after touchdown where one ends before, and skipped where that is
        not longer than the last window (``settings.refine_window_note`` in the report says
        so). The default stays inside the first impact (exact gradients); longer windows
        through lift-off and re-contact are allowed but their loss is jagged and multimodal
        (see the module docstring)
    robust : Huber threshold in robust standard deviations of the residuals (None: plain least
        squares). It keeps localised model errors (a honeycomb crush peak) from biasing the fit
    multistart : run the short windows (all but the last of ``windows``) from the start and
        from ``START_VARIANTS`` of it (k and gamma moved), taken in order, two at a time, until
        two agree on the lowest loss, and continue from the best (default True)
    method : ``"lm"`` (Levenberg-Marquardt on the jacfwd Jacobian, default) or ``"lbfgs"``
        (``optax.lbfgs`` on the jacfwd gradient)
    max_iter : iteration limit per stage (and per start)
    dt, save_dt : integration step and model sampling interval [s]
    integrator : the model's integrator (``jaxland.Solver.method``), one of ``euler``,
        ``euler_implicit``, ``verlet`` (default ``INTEGRATOR``)
    smoothing_m, smoothing_N : widths of the rounded force-law switches [m], [N]
        (``jaxland.Solver.smoothing_m`` / ``smoothing_N``; 0: hard switches). None (default):
        ``SMOOTHING[integrator]`` (1e-6 m and 10 N for verlet, 0 otherwise)
    fit_touchdown : fit each drop's touchdown time (else use the detected one)
    channels : channels to fit (default: all present)
    peak_form : the primary crush peak's form when peak1 is fitted: None (the law's: linear,
        or built up when L_rise1 is fitted), ``"exp"`` or, with L_rise1 fitted,
        ``"rise_exp"`` or ``"smooth_exp"`` (``PEAK_FORMS``)
    model_form : the peak-shape (model-form) term of the uncertainty: ``"auto"`` (default)
        computes it when the fit has the primary crush peak (peak1 fitted), True / False
        force it on (with the peak) or off. On: the values are refitted in each other peak
        form (``model_form_spread``) and the largest shift of each parameter is added in
        quadrature to ``std_errors_total``
    peak_model_term : the missing-peak term of the uncertainty: ``"auto"`` (default) computes
        it where the residuals show misfit (``MisfitWarning``) and the fitted model has no
        crush peak (``has_no_peak``): the fit is repeated with the primary peak
        (``PEAK_PARAMS``) and each value's shift to it is added in quadrature to
        ``std_errors_total`` (``add_peak_model_term``); False leaves it out
    fixed_params_term : the fixed-parameter term of the uncertainty: ``"auto"`` (default)
        computes it where the residuals show misfit and ``params`` leave some of the default
        parameters (``DEFAULT_PARAMS``) fixed: the fit is repeated from its optimum with those
        freed as well and each value's shift to it is added in quadrature to
        ``std_errors_total`` (``add_fixed_params_term``); False leaves it out
    peak_site : where the primary crush peak sits (needs peak1): ``"honeycomb"`` (default: the
        law's; its crush work moves the stroke and the body) or ``"forces"``, on the force
        channels alone (the drop runs without it and the force channels carry it as a gain,
        ``CalibrationProblem``): for a record whose peak the motion does not show
        (``misfit.peak_location``). The fitted vehicle then has no primary peak
    progress : called with a dict after every iteration (``stage``, ``iteration``, ``loss``...)

    Warns ``IdentifiabilityWarning`` (and lists it in ``FitResult.warnings``) for each parameter
    the data do not determine.
    """
    t_start = time.perf_counter()
    # _inner: a fit run inside another for its values (the missing-peak term): no warnings,
    # no channel spread (it moves no value), on the outer fit's program (``peak_switch``)
    warn = _no_warning if _inner else warnings.warn
    checked = check_fit(drops, params, vehicle=vehicle, start=start, windows=windows,
                        refine_window_s=refine_window_s, robust=robust, method=method,
                        max_iter=max_iter, dt=dt, save_dt=save_dt, integrator=integrator,
                        smoothing_m=smoothing_m, smoothing_N=smoothing_N,
                        peak_form=peak_form, model_form=model_form,
                        peak_model_term=peak_model_term, peak_site=peak_site)
    if fixed_params_term not in ("auto", False):
        raise jl.ConfigError("fixed_params_term", fixed_params_term, "must be 'auto' or False")
    drops, names, windows, stages_w = (checked.drops, checked.names, checked.windows,
                                       checked.stages_w)
    integrator, smoothing_m, smoothing_N = (checked.integrator, checked.smoothing_m,
                                            checked.smoothing_N)
    start_vehicle, start_values = checked.start_vehicle, checked.start_values
    form = peak_form_of(names, peak_form)
    optimiser = levenberg_marquardt if method == "lm" else lbfgs

    def without_peak(program=None):
        """This fit's special case without the crush peak (peak1 = 1), in a thread of its own
        beside this one: on ``program`` (this fit's problem) with the peak switched off, or,
        where that cannot switch it off, on its own program, the peak off in the vehicle."""
        np_names = no_peak_names(names)
        start_np = ({k: v for k, v in start.items() if k in np_names}
                    if isinstance(start, dict) else
                    dict(zip(np_names, get_values(start, np_names).tolist()))
                    if isinstance(start, jl.Vehicle) else None)
        tagged_np = None if progress is None else (
            lambda rec: progress(dict(rec, stage="without the crush peak " + rec["stage"])))
        return _in_thread(
            fit, drops, np_names,
            vehicle=_without_primary_peak(drops[0].vehicle if vehicle is None else vehicle),
            start=start_np, windows=windows, refine_window_s=refine_window_s, robust=robust,
            multistart=multistart, method=method, max_iter=max_iter, dt=dt, save_dt=save_dt,
            integrator=integrator, smoothing_m=smoothing_m, smoothing_N=smoothing_N,
            fit_touchdown=fit_touchdown, channels=channels, model_form=False,
            peak_model_term=False, fixed_params_term=False, progress=tagged_np, _inner=True,
            _program=program)

    # one problem (one compilation) for every stage: the windows are masks. With the
    # peak-shape term, its functions serve every peak form (``shared_forms``), so that the
    # term's refits compile nothing: a second program for the other forms cost about twice
    # the fit's own compilation in CPU time. Not where the vehicle's rise length stays fixed:
    # the shared functions cannot hold it at a given length
    forms = form is not None and model_form is not False
    shared = forms and ("L_rise1" in names or start_vehicle.honeycomb.peak_rise1 is None)
    # a model without any crush peak runs on functions whose linear peak is switched off at
    # run time (``peak_switch``), so that the missing-peak term's fit (the same functions,
    # switched on) compiles nothing; a second compilation would be a large part of a fit's
    # time. Every fit without a peak does so, whether the term runs or not, so that a fit's
    # values do not depend on the term's setting
    switch = has_no_peak(names, start_vehicle) or (_inner and form == "linear")
    if _program is not None:  # the no-peak check's fit: its caller's program, the peak off
        problem = _program.without_peak(start_vehicle)
    else:
        problem = CalibrationProblem(
            drops, names, vehicle=start_vehicle, window_s=stages_w[-1], pre_s=PRE_S, dt=dt,
            save_dt=save_dt, integrator=integrator, smoothing_m=smoothing_m,
            smoothing_N=smoothing_N, fit_touchdown=fit_touchdown, channels=channels,
            peak_form=form if shared else peak_form, shared_forms=shared, peak_switch=switch,
            peak_site=peak_site)
    theta0 = problem.theta_from(shifts_ms=_start_shifts_ms)
    forms_thread = precompile_forms(problem, form) if forms and not shared else None
    # a fit with the crush peak is checked against its special case without it (peak1 = 1),
    # fitted in a thread of its own beside this one (``_no_peak``: a caller that has that
    # fit, --compare-models, hands it over). On this fit's program with the peak switched
    # off, started once that is compiled, so that it compiles nothing: a program of its own,
    # traced and compiled beside this one, costs more wall time than this fit's optimisation
    check = _no_peak is None and wants_no_peak_check(names, _inner)
    on_program = check and problem.peak_switches_off
    no_peak_future = without_peak() if check and not on_program else None
    problem.compile(theta0)
    if on_program:
        no_peak_future = without_peak(problem)
    history, stages = [], []
    n_ms = len(windows) - 1 if len(windows) > 1 else 0  # stages run from every start

    # the law's extensions (crush peak, unloading ratio) stay at their start values through the
    # multistart stages and are freed for the long ones: the short windows' starts then agree
    # on one optimum of the plain law's parameters (with them free the 10 ms window's flat
    # valleys kept every start apart: all five ran, 3x the iterations)
    ext = np.array([n in EXTENSION_PARAMS for n in names] + [False] * (problem.n_theta
                                                                       - len(names)))
    frozen = ~ext if (ext.any() and not ext[:len(names)].all()) else None

    def run(prob, theta, label, start_label="", free=None, ftol=FTOL):
        t_stage = time.perf_counter()
        kw = dict(ftol=ftol, free=free) if method == "lm" else {}
        theta, hist, status = optimiser(prob, theta, max_iter=max_iter, progress=progress,
                                        stage=label + start_label, t_origin=t_start, **kw)
        rec = dict(stage=label, window_s=prob.active_window_s, iterations=len(hist),
                   huber_c=None if prob.huber_c >= PLAIN else prob.huber_c,
                   wall_s=time.perf_counter() - t_stage, **status)
        return theta, hist, rec

    labels = [f"{k + 1}/{len(stages_w)} ({w * 1e3:g} ms)" for k, w in enumerate(stages_w)]
    starts = _start_variants(problem, theta0) if (multistart and n_ms) else [theta0]

    def from_start(j):
        th, hist_j, recs_j = starts[j], [], []
        tag = f" start {j + 1}/{len(starts)}" if len(starts) > 1 else ""
        for k in range(n_ms):
            th, hist, rec = run(problem.windowed(stages_w[k]), th, labels[k], tag, frozen,
                                FTOL_MULTISTART)
            hist_j += hist
            recs_j.append(dict(rec, start=j + 1))
        loss_j = recs_j[-1]["final_loss"] if recs_j else 0.0
        return dict(theta=th, loss=loss_j, history=hist_j, stages=recs_j)

    running = []  # starts of the last batch still running where an earlier one agreed
    candidates = _until_two_agree(from_start, len(starts), MULTISTART_THREADS, running)
    chosen = min(range(len(candidates)), key=lambda i: candidates[i]["loss"])

    def long_stages(theta):
        huber_c, hist_all, recs = None, [], []
        for k in range(n_ms, len(stages_w)):
            prob = problem.windowed(stages_w[k])
            if robust is not None:
                huber_c = robust_threshold(prob, theta, robust)
                prob = prob.robust(huber_c)
            theta, hist, rec = run(prob, theta, labels[k])
            hist_all += hist
            recs.append(rec)
        return theta, hist_all, recs, huber_c

    theta, hist_long, recs_long, huber_c = long_stages(candidates[chosen]["theta"])
    final = problem.windowed(stages_w[-1])
    r = final.robust(None).residuals(theta)[0][final.mask.ravel() > 0]
    ended_s2 = _variance_factor(r, max(final.n_obs - final.n_theta, 1), huber_c)  # the report's
    every_start = None
    if n_ms and not _inner and len(candidates) < len(starts) and ended_s2 > MISFIT_SIGMA2:
        # two starts agreeing is no proof of the best basin where the fit from it misfits: a
        # wrong basin of the contact oscillation misfits too, and two starts can share it.
        # So the other starts run as well; the long stages run again from one that ends the
        # short windows lower beyond the agreement tolerance, and the lower fit is kept. (A
        # fit inside another, on a record it misfits by construction, does not.)
        candidates += [f.result() for f in running]
        for b in range(len(candidates), len(starts), MULTISTART_THREADS):
            futures = [_in_thread(from_start, j)
                       for j in range(b, min(b + MULTISTART_THREADS, len(starts)))]
            candidates += [f.result() for f in futures]
        lowest = min(range(len(candidates)), key=lambda i: candidates[i]["loss"])
        every_start = (f"the fit from the agreeing starts misfits (variance factor "
                       f"{ended_s2:.3g} > {MISFIT_SIGMA2:g}): every start was run")
        if (candidates[lowest]["loss"] < candidates[chosen]["loss"]
                - AGREE_REL * abs(candidates[chosen]["loss"])):
            other = long_stages(candidates[lowest]["theta"])
            if _chi2(final, other[0]) < _chi2(final, theta):
                chosen = lowest
                theta, hist_long, recs_long, huber_c = other
                every_start += f", and start {lowest + 1}'s fit, lower, was kept"
    history += candidates[chosen]["history"] + hist_long
    stages += candidates[chosen]["stages"] + recs_long
    multistart_info = dict(
        n_starts_tried=len(candidates), chosen_start=chosen + 1,
        starts_agree=len(candidates) < 2 or _starts_agree(candidates),
        start_losses=[c["loss"] for c in candidates],
        starts=[dict(zip(names, problem.values(st).tolist())) for st in starts[:len(candidates)]],
        selected_by=f"loss on the {stages_w[n_ms - 1] * 1e3:g} ms window" if n_ms else None,
        every_start=every_start)
    no_peak_check = None
    if no_peak_future is not None or _no_peak is not None:
        no_peak = _refit_outcome(no_peak_future) if _no_peak is None else _no_peak
        if isinstance(no_peak, FitResult):
            # the same final stage from the no-peak optimum with the peak all but off, the
            # run of least chi^2 kept: from the start alone the fit with the peak ended in
            # a wrong minimum on a record without one (the rig's 0.2 m drop, noise only:
            # chi2 4.16e6 against 2994 without the peak, F2 5568 N against the truth's 8547,
            # the peak at its bound), and its misfit then blamed the data
            theta_off = peak_off_theta(problem, start_vehicle, no_peak)
            huber_off = robust_threshold(final, theta_off, robust) if robust is not None \
                else None
            theta_b, hist_b, rec_b = run(final.robust(huber_off), theta_off, labels[-1],
                                         " from the no-peak optimum")
            rec_b["start"] = FROM_NO_PEAK
            runs = {FROM_START: (theta, huber_c), FROM_NO_PEAK: (theta_b, huber_off)}
            chi2 = {k: _chi2(final, th) for k, (th, _) in runs.items()}
            # each run ends no worse than the model without the peak on its own loss (the
            # Huber loss of its threshold), to NO_PEAK_CHI2_ATOL: the no-peak optimum is a
            # point of its model, so a run whose loss lies above it stopped short of its
            # optimum. Not on chi^2: a Huber optimum's chi^2 may lie a hair above the no-peak
            # one's (1329.80 against 1329.75 on the rig's drop without a peak, the short
            # windows) and be no failure
            ok = {k: 2.0 * final.robust(c).loss(th) <= 2.0 * no_peak.problem.robust(c).loss(
                no_peak.theta) + NO_PEAK_CHI2_ATOL for k, (th, c) in runs.items()}
            # of the runs that end no worse, the one of least chi^2 (of both, where neither)
            kept = min([k for k in runs if ok[k]] or list(runs), key=chi2.get)
            if kept == FROM_NO_PEAK:
                theta, huber_c = theta_b, huber_off
                history += hist_b
                stages.append(rec_b)
            chi2_np = _chi2(no_peak.problem, no_peak.theta)
            no_peak_check = dict(
                chi2_no_peak=chi2_np, chi2_from_start=chi2[FROM_START],
                chi2_from_no_peak=chi2[FROM_NO_PEAK], started_from=kept,
                no_worse_on_its_loss={k: bool(v) for k, v in ok.items()},
                stage_from_no_peak=rec_b,
                values_no_peak=dict(zip(no_peak.names, no_peak.values.tolist())),
                wall_s_no_peak=no_peak.wall_s, failed=None)
            if not ok[kept]:
                no_peak_check["failed"] = (
                    f"the fit with the crush peak ended worse than its special case without "
                    f"the peak (chi2 {chi2[kept]:.6g} against {chi2_np:.6g}, and on its own "
                    "loss beyond its tolerance; peak1 = 1 is in its model), from the start "
                    "and from the no-peak optimum alike: an optimiser failure, not a misfit; "
                    "these values are not its optimum (misfit.no_peak_check)")
        else:  # the check could not run: the fit stands as it ended, and says so
            no_peak_check = dict(failed=None, no_peak_failed=(
                None if no_peak is None else f"{type(no_peak).__name__}: {no_peak}"))
    values = final.values(theta)
    try:
        if not np.all(np.isfinite(np.asarray(theta))):
            raise np.linalg.LinAlgError("non-finite parameters")
        unc = _uncertainty(final, theta, huber_c)
    except np.linalg.LinAlgError as err:  # the model cannot follow the record at all
        raise jl.SimulationError(
            f"the fit found no usable minimum ({err}): the model does not follow the record "
            "at all; check the drop test's metadata against the record (drop_height_m, "
            "sink_speed_mps or touchdown_speed_mps, sensor_leg, units)") from None
    bound = at_bound(names, values, final.vehicle, form=final.peak_form, site=peak_site)
    identified, msgs = _identifiability(names, values, unc, bound)
    msgs += [_bound_message(n, names, values, final.vehicle, final.peak_form, peak_site)
             for n in bound]
    for m in msgs:
        warn(m, IdentifiabilityWarning, stacklevel=2)
    # the misfit test needs a measured noise level: on noise-free records (every channel's
    # noise at the loader's floor) the residuals are the model's own discretisation, smooth by
    # nature; the diagnostics are still reported. A channel at the floor whose residuals carry
    # white noise above it had a flat free fall, not noise-free data: the floor understates its
    # noise, and the misfit test holds
    noisy_floor = floor_noise(final, unc["residuals"].reshape(final.data.shape))
    if noisy_floor:
        unc["misfit"].append(
            "white noise in the residuals of channels weighted by the loader's noise floor ("
            + "; ".join(f"{w['drop']}: {w['channel']} {w['white_noise_floor_units']:.3g} x "
                        "the floor" for w in noisy_floor)
            + "): their free fall is flat (held or zeroed before touchdown), not noise-free, "
            "so their noise is understated (misfit.floor_noise)")
    noise_free = not noisy_floor and all(str(src).startswith("floor") for d in drops
                                         for src in d.noise_source.values())
    if noise_free and unc["misfit"]:
        unc["misfit"] = []
        unc["noise_free"] = True
    # a CFC filter correlates the noise itself: the classical errors never hold then
    trust = "std_error_hac" if unc["misfit"] or final.filtered else "std_error"
    trusted = unc["se_hac"] if trust == "std_error_hac" else unc["se"]
    # the peak-shape refits and the channel spread's share one pool, one thread per core
    # (each refit's time is XLA's, which frees the interpreter lock), the forms' first
    pool = ThreadPoolExecutor(max_workers=REFIT_THREADS)
    try:
        if forms:
            if forms_thread is not None:
                forms_thread.join()
            form_jobs = form_refits(final, theta, form, huber_c, max_iter, pool)
        peak_future = None
        if wants_peak_model_term(peak_model_term, unc["misfit"], names, start_vehicle):
            # the fit with the crush peak runs in a second thread beside the channel spread's
            tagged = None if progress is None else (
                lambda rec: progress(dict(rec, stage="with the crush peak " + rec["stage"])))
            common = dict(robust=robust, method=method, max_iter=max_iter, dt=dt,
                          save_dt=save_dt, integrator=integrator, smoothing_m=smoothing_m,
                          smoothing_N=smoothing_N, fit_touchdown=fit_touchdown,
                          channels=channels, model_form=False, peak_model_term=False,
                          fixed_params_term=False, progress=tagged, _inner=True)
            # a start vehicle's peak is off (read as ratio 1): its fitted values only
            start_p = (dict(zip(names, get_values(start, names).tolist()))
                       if isinstance(start, jl.Vehicle) else start)
            # two runs, the one of least chi^2 kept: from this fit's optimum (values and
            # touchdowns) with the peak all but off, on its final window alone, which starts
            # where the model without the peak ended and only descends from there; and from
            # the start through every stage, as --compare-models fits the peak model, which
            # on the rig's peaks ends lower (chi2 10082 against 10397 on the bundled 0.2 m
            # drop) but on records without a peak in wrong minima (4.6e6 against 3463
            # without the peak: F2 pulled down to F1, the peak at its bound)
            peak_future = _in_thread(_least_chi2, {
                "the fit's optimum, the peak off": lambda: fit(
                    drops, names + PEAK_PARAMS, vehicle=vehicle,
                    start=peak_off_start(final.vehicle_at(theta), names),
                    windows=(stages_w[-1],), refine_window_s=None, multistart=False,
                    _start_shifts_ms=theta[len(names):] if fit_touchdown else None, **common),
                "the fit's start": lambda: fit(
                    drops, names + PEAK_PARAMS, vehicle=vehicle, start=start_p,
                    windows=windows, refine_window_s=refine_window_s, multistart=multistart,
                    **common)})
        wider_future = None
        if wants_fixed_params_term(fixed_params_term, unc["misfit"], names):
            # the same fit with the fixed default parameters freed, from this optimum (they
            # from the vehicle's values), in a thread of its own beside the others
            tagged_w = None if progress is None else (
                lambda rec: progress(dict(rec, stage="with " + ", ".join(fixed_defaults(
                    names)) + " freed " + rec["stage"])))
            wider_future = _in_thread(
                fit, drops, names + fixed_defaults(names), vehicle=vehicle,
                start=dict(zip(names, values.tolist())), windows=windows,
                refine_window_s=refine_window_s, robust=robust, multistart=multistart,
                method=method, max_iter=max_iter, dt=dt, save_dt=save_dt, integrator=integrator,
                smoothing_m=smoothing_m, smoothing_N=smoothing_N, fit_touchdown=fit_touchdown,
                channels=channels, peak_form=peak_form, model_form=False,
                peak_model_term=False, fixed_params_term=False, peak_site=peak_site,
                progress=tagged_w, _inner=True)
        # the drop spread's refits queue on the same pool, beside the channel spread's
        spreads = bool(unc["misfit"]) and not _inner
        drops_done = (_leave_out(final, theta, drop_subs(final), huber_c, max_iter, pool)
                      if spreads and len(drops) > 1 else None)
        spread, shifts = (channel_spread(final, theta, huber_c, max_iter, pool)
                          if spreads else (np.zeros_like(values), {}))
        drop_shifts = drops_done() if drops_done is not None else None
        spread_failed = [g for g, v in shifts.items() if v is None]
        if spread_failed:
            spread = np.nan_to_num(spread, nan=0.0)  # all failed: the total is the trusted error
            warn(f"the fit without {', '.join(spread_failed)} failed, so std_error_total "
                 "leaves out how far those channels pull the fit (channel_spread_failed "
                 "in the report)", MisfitWarning, stacklevel=2)
        mform = (model_form_spread(final, theta, form, huber_c, max_iter, unc["rho1"], form_jobs)
                 if forms else None)
    finally:  # an interruption leaves no queued refit for the interpreter's exit to wait on
        pool.shutdown(wait=False, cancel_futures=True)
    if forms:
        if mform["failed"]:
            warn(f"the refit in the crush peak's {', '.join(mform['failed'])} "
                 "form failed, so std_error_total leaves out how far that form "
                 "moves the values (misfit.model_form.failed in the report)",
                 MisfitWarning, stacklevel=2)
        best = mform["best_supported"]
        if form not in mform["plausible"]:
            rise = best in RISE_FORMS  # how to fit in the best form, from its two traits
            how = (("fit with L_rise1 among the parameters" if rise else "fit without L_rise1")
                   + ((" and " if rise else ", with ")
                      + f"peak_form='{best}' (--peak-form {best})" if best in EXP_TABLE_SPAN
                      else " and without peak_form")
                   + (", and peak_site='forces' (--peak-site forces)"
                      if peak_site == FORCES else ""))
            warn(
                f"the data reject the crush peak's {form} form: its misfit-adjusted AIC is "
                f"{mform['forms'][form]['daic_adjusted']:.3g} behind the least (limit "
                f"{DAIC_PLAUSIBLE:g}), and the {best} form is the best supported; "
                f"std_error_total spans the forms the data support "
                f"({', '.join(mform['plausible'])}); the {best} form's values are in the report "
                f"(misfit.model_form.forms.{best}.values); a refit in that form ({how}) reports "
                "them with an interval that assumes its shape, narrower than std_error_total and "
                "too narrow where the record's peak has a shape outside the forms",
                MisfitWarning, stacklevel=2)
    with_peak, wider = _refit_outcome(peak_future), _refit_outcome(wider_future)
    if isinstance(with_peak, Exception):
        warn(f"the fit with the crush peak failed ({with_peak}), so std_error_total leaves out "
             "how far the peak moves the values (misfit.peak_model_term.failed in the "
             "report)", MisfitWarning, stacklevel=2)
    form_term = (np.array([mform["spread"][n] for n in names]) if mform is not None
                 else np.zeros_like(values))
    drops_rec, drops_term = None, np.zeros_like(values)
    if drop_shifts is not None:
        drops_rec = drop_spread_record(names, drop_shifts, _largest(final, theta, drop_shifts),
                                       spread, trusted)
        drops_term = np.array([drops_rec["spread"][n] for n in names])
        if drops_rec["failed"]:
            warn(f"the fit without the drop {', '.join(drops_rec['failed_drops'])} failed, so "
                 "std_error_total leaves out how far that drop pulls the fit "
                 "(misfit.drop_spread.failed in the report)", MisfitWarning, stacklevel=2)
    if unc["misfit"]:
        worst = "; ".join(
            f"{w['drop']}: {w['channel']} {_window_text(*w['window_s'])} "
            f"({w['rms_noise_units']:.3g} x noise)" for w in unc["where"])
        short = starts_disagree(multistart_info) or no_peak_failure(no_peak_check)
        warn(("the data contradict the model: " if short is None else
              "the residuals misfit, but NOT CONVERGED: " + short + "; so the misfit below "
              "is the optimiser's, not evidence against the model: ") + "; ".join(unc["misfit"])
             + ". The classical standard errors are too small: trust the HAC ones "
             "(std_error_hac), widened by how far the values move when one channel "
             f"is left out (std_error_total){_disagreement(names, shifts, trusted)}"
             + (_drops_disagree(drops_rec) if drops_rec is not None else "")
             + ("; the model has no crush peak, so the fit was repeated with one, and where "
                "that fit succeeded each value's shift to it is in std_error_total too "
                "(misfit.peak_model_term says whether it did; --compare-models says whether "
                "the data support the peak)" if with_peak is not None else "")
             + (f"; the fit leaves {', '.join(fixed_defaults(names))} fixed, so it was "
                "repeated with them freed, and where that fit succeeded each value's shift "
                "to it is in std_error_total too (misfit.fixed_params_term says whether it "
                "did)" if wider is not None else "")
             + f". Largest misfit: {worst}", MisfitWarning, stacklevel=2)
    # an inner fit (the missing-peak term's) reports only its values to the outer one
    where_peak = None if _inner else peak_location(final, theta, unc["residuals"],
                                                   unc["jacobian"])
    if where_peak is not None and where_peak["force_only"]:
        warn(f"the crush peak shows in the force channels only: fitted to "
             f"{' and '.join(PEAK_MOTION_CHANNELS)} alone (one Gauss-Newton step from the "
             f"optimum), peak1 would be {where_peak['peak1_motion']:.4g} +/- "
             f"{where_peak['std_error_motion']:.2g} against {where_peak['peak1']:.4g} with "
             "every channel. A force the motion does not show is no honeycomb's (a load-cell "
             "artefact or a load path the model lacks): the honeycomb's parameters take it up, "
             "and std_error_total, not the values, is what holds (misfit.peak_location); a fit "
             "with the peak on the force channels (peak_site='forces', --peak-site forces) "
             "keeps it out of the honeycomb",
             MisfitWarning, stacklevel=2)
    site_check = None if _inner else motion_fit(final, unc["residuals"])
    if site_check is not None and site_check["misfit"]:
        warn(f"the peak sits on the force channels in this fit, and the motion misfits: "
             f"{' and '.join(site_check['channels'])} have a residual variance factor of "
             f"{site_check['variance_factor']:.3g} (> {MISFIT_SIGMA2:g}), where the drop without "
             "the peak should follow them to the noise. The motion shows crush work the model "
             "lacks: the peak is likely the honeycomb's, and the values here are biased; fit "
             "with the peak in the honeycomb (peak_site='honeycomb') and read its peak location "
             "(misfit.peak_site_check)", MisfitWarning, stacklevel=2)
    fitted = final.vehicle_at(theta)
    result = FitResult(
        names=names, values=values, std_errors=unc["se"], correlation=unc["corr"],
        covariance=unc["cov"], identified=identified, start_values=start_values,
        vehicle=fitted, touchdown_times_s=final.touchdown_times(theta),
        touchdown_std_errors_s=unc["t_se"], residual_rms=final.channel_rms(theta),
        sigma2=unc["sigma2"], n_obs=final.n_obs, dof=unc["dof"],
        std_errors_hac=unc["se_hac"], covariance_hac=unc["cov_hac"],
        std_errors_total=np.sqrt(trusted**2 + spread**2 + drops_term**2 + form_term**2),
        diagnostics=dict(residual_variance_factor=unc["sigma2"], residual_lag1_autocorr=unc[
            "rho1"], hac_bandwidth_samples=unc["hac_lag"], misfit=unc["misfit"],
            worst_window=unc["where"], at_bound=list(bound),
            trust=trust,
            interval=("std_error_total" if (unc["misfit"] or mform is not None) else trust),
            model_form=mform, peak_model_term=None, fixed_params_term=None,
            interval_bounded=True, interval_not_bounded=None,
            filtered_noise_lag1_autocorr=final.noise_lag1,
            channel_spread={g: None if v is None else dict(zip(names, v.tolist()))
                            for g, v in shifts.items()},
            channel_spread_failed=spread_failed,
            **({} if drops_rec is None else {"drop_spread": drops_rec}),
            no_peak_check=no_peak_check,
            noise_free_record=bool(unc.get("noise_free", False)), floor_noise=noisy_floor,
            peak_location=where_peak, peak_site_check=site_check),
        loss=final.robust(huber_c).loss(theta), stages=stages, history=history, warnings=msgs,
        method=method, wall_s=time.perf_counter() - t_start, drops=drops, problem=final,
        theta=theta, ranges={n: value_range(n, names, values, final.vehicle, final.peak_form,
                                            peak_site) for n in names},
        settings=dict(windows_s=list(windows), refine_window_s=stages_w[-1]
                      if len(stages_w) > len(windows) else None,
                      refine_window_requested_s=(REFINE_WINDOW_S if refine_window_s == AUTO
                                                 else refine_window_s or None),
                      refine_window_default=refine_window_s == AUTO,
                      refine_window_note=checked.refine_note, robust_k=robust,
                      huber_c_final=huber_c, multistart=multistart_info, dt_s=dt,
                      model_save_dt_s=save_dt,
                      integrator=dict(method=integrator, dt_s=dt, smoothing_m=smoothing_m,
                                      smoothing_N=smoothing_N),
                      pre_touchdown_s=PRE_S, fit_touchdown=fit_touchdown,
                      channels=list(final.channels), max_iter=max_iter,
                      peak_form=form, model_form=model_form, peak_site=peak_site,
                      peak_model_term=peak_model_term, fixed_params_term=fixed_params_term,
                      model="quarter (jaxland.landing), from touchdown",
                      channel_map={c: CHANNELS[base_channel(c)][1] for c in final.channels},
                      filter_cfc={d.name: dict(d.filters) for d in drops if d.filters} or None,
                      filter_margin_s=final.margin_s))
    if with_peak is not None:
        add_peak_model_term(result, with_peak)
    if wider is not None:
        add_fixed_params_term(result, wider)
    if drops_rec is not None:
        mark_interval_bounded(result)
    if not result.diagnostics["interval_bounded"]:
        warn("NO TRUSTED INTERVAL: " + "; ".join(result.diagnostics["interval_not_bounded"])
             + ". The misfit calls for that term: without it the reported interval is the "
             "scatter about a biased fit, and the values may lie many of its standard errors "
             "from the truth (misfit.interval_not_bounded in the report)",
             MisfitWarning, stacklevel=2)
    return result
