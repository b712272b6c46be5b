"""``jaxland fit`` and ``jaxland predict``: the calibration's command line.

``add_subcommands(subparsers)`` registers both on an ``argparse`` subparsers object; each
handler returns an exit code and raises ``jaxland.ConfigError`` for bad input (the ``jaxland``
command maps it to exit code 2, and ``SimulationError`` to 3). Output files are written into a
staging folder and moved into place only once all of them exist.
"""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import jaxland as jl
from jaxland import staged
from jaxland._checks import named_as
from jaxland._files import file_record

__all__ = ["add_subcommands"]


def _floats(flag: str, text: str) -> list[float]:
    if not text.strip():
        raise jl.ConfigError(flag, text, "must give at least one number")
    try:
        return [float(x) for x in text.split(",")]  # an empty entry is a typo: refused
    except ValueError:
        raise jl.ConfigError(flag, text, "must be comma-separated numbers") from None


def _start(text: str | None) -> dict | None:
    if not text:
        return None
    out = {}
    for item in text.split(","):
        name, sep, val = item.partition("=")
        if not sep:
            raise jl.ConfigError("--start", item, "must be name=value pairs, e.g. k=2e6,F1=5000")
        name = name.strip()
        if name in out:
            raise jl.ConfigError(f"--start {name}", val.strip(), "is given twice")
        try:
            out[name] = float(val)
        except ValueError:
            raise jl.ConfigError(f"--start {name}", val, "must be a number") from None
        if not math.isfinite(out[name]):
            raise jl.ConfigError(f"--start {name}", val.strip(), "must be a finite number (SI)")
    return out


def _start_typed(text: str | None) -> dict:
    """``--start``'s values as typed, by name (``{'k_b1': '1e12'}``): a refusal of one start
    value names it as ``--start k_b1`` with what the user wrote."""
    out = {}
    for item in (text or "").split(","):
        name, sep, val = item.partition("=")
        if sep:
            out.setdefault(name.strip(), val.strip())
    return out


def _out_dir(path: str, inputs=(), command: str | None = None) -> Path:
    # before any work: a file, someone else's folder, another command's, or a folder holding
    # an input
    return jl.check_output_folder(path, inputs, command)


def fit_inputs(args, drops) -> dict:
    """``fit_report.json``'s ``inputs``: the drop tests as given with the files their metadata
    named, the ``--config`` file, and every argument of the command as parsed (defaults
    filled in), so that the fit can be run again as it was (the versions it ran on are the
    report's ``environment``)."""
    def named(files) -> dict:  # the metadata, its traces, its vehicle_config (or None)
        meta, data, *cfg = files
        return dict(metadata=file_record(meta), data_file=file_record(data),
                    vehicle_config=file_record(cfg[0]) if cfg else None)

    return dict(
        data=[dict(given=given, **named(d.files)) for given, d in zip(args.data, drops)],
        config=file_record(args.config) if args.config else None,
        arguments={k: v for k, v in vars(args).items() if k not in ("func", "command")})


def stopped_at_cap(result) -> bool:
    """The fit's last stage ended at its iteration cap, not at a minimum."""
    from ._fit import stopped_at_cap as capped

    return capped(result.stages)


class _Progress:
    """One stderr line per iteration."""

    def __init__(self, quiet: bool):
        self.quiet = quiet

    def __call__(self, rec: dict) -> None:
        if self.quiet:
            return
        extra = (f"  lambda {rec['lambda_']:.1e}" if "lambda_" in rec
                 else f"  |grad| {rec.get('grad_max', float('nan')):.2e}")
        print(f"fit stage {rec['stage']}  iter {rec['iteration']:3d}  loss {rec['loss']:.6e}"
              f"{extra}  {rec['wall_s']:6.1f} s", file=sys.stderr, flush=True)


_INTERVAL_TEXT = {"std_error": "classical (std_error)", "std_error_hac": "HAC (std_error_hac)"}


def form_caveat(model_form: dict | None) -> str | None:
    """The line the CLI adds where the fitted peak form is the only one the data support
    (``model_form``: the report's ``misfit.model_form``): the peak-shape term is then 0, and
    the interval holds only as far as the record's peak has that form's shape. None
    otherwise."""
    if model_form is None or model_form["plausible"] != [model_form["form"]]:
        return None
    return (f"  the data support no other form of the peak: the peak-shape term is 0, and the "
            f"interval assumes the peak has the {model_form['form']} form's shape; a shape "
            "outside the forms can move the values further (docs/calibration.md, the fit, "
            "item 9)")


def peak_location_line(loc: dict) -> str:
    """The CLI's line on where the fitted crush peak shows (``misfit.peak_location``): in the
    force channels only (the fit's test), in the motion too (the motion-only step keeps at
    least PEAK_MOTION_RATIO of the excess), or undecided (less is kept, but within
    PEAK_MOTION_Z of the motion-only error); nothing to tell without a fitted excess."""
    from ._fit import PEAK_MOTION_RATIO

    head = "  peak location: "
    kept, z = loc.get("excess_kept"), loc.get("z")
    if kept is None or z is None or loc.get("peak1_motion") is None:
        return head + "no excess over the plateau fitted (or the motion-only step ran off)"
    head += (f"peak1 {loc['peak1_motion']:.4g} +/- {loc['std_error_motion']:.2g} from the "
             f"motion alone (one Gauss-Newton step), against {loc['peak1']:.4g} with every "
             f"channel (it keeps {kept:.2f} of the excess, z {z:.1f}): ")
    if loc["force_only"]:
        return head + "in the force channels only, no honeycomb's"
    if kept >= PEAK_MOTION_RATIO:
        return head + "the motion shows it too"
    return head + "the motion shows less of it, within its error: undecided"


def peak_site_line(check: dict | None) -> str:
    """The CLI's line for a fit whose peak sits on the force channels, with whether the
    motion channels fit without it (``_fit.motion_fit``)."""
    head = ("  peak site: the force channels alone (fitted as a gain on them; the drop runs "
            "without it, and fitted_vehicle.toml has no primary crush peak); ")
    if check is None:
        return head + "no motion channel to check it against"
    vf = check["variance_factor"]
    if check["misfit"]:
        return head + (f"THE MOTION MISFITS (variance factor {vf:.3g}): the peak is likely the "
                       "honeycomb's, and these values are biased")
    return head + f"the motion fits without it (variance factor {vf:.3g})"


def held_fixed_line(result) -> str:
    """fit's line naming the parameters it held at the vehicle's values
    (``FitResult.held_fixed``), on which every interval it prints is conditional, and what
    else it takes as exact (``FitResult.assumes_exact``)."""
    held = result.held_fixed()
    on = [f"{n} {p['value']:.4g}" + ("" if p["unit"] == "1" else f" {p['unit']}")
          for n, p in held.items() if p["active"]]
    off = [n for n, p in held.items() if not p["active"]]
    return ("  interval conditional on the parameters held at the vehicle's values: "
            + ", ".join(on) + (f"; off: {', '.join(off)}" if off else "")
            + ". A truth that differs in them biases the values by more than the interval "
            "shows, with no misfit to warn of it (fit them with --params where the records "
            "determine them; fit_report.json, interval_conditional_on); so do errors in what "
            "the fit takes as exact: " + ", ".join(result.assumes_exact())
            + " (fit_report.json, interval_assumes_exact)")


def _cmd_fit(args) -> int:
    from . import _fit
    from ._data import load_drop_tests
    from ._parameters import FORCES, HONEYCOMB, PARAMS, SHAPE_PARAMS, Z95, check_names

    out = _out_dir(args.out, (args.config, *args.data), "fit")
    # the fit's arguments refused under the flags that set them
    flags = {field: (flag, getattr(args, dest)) for field, flag, dest in (
        ("params", "--params", "params"), ("start", "--start", "start"),
        ("windows", "--windows", "windows"), ("dt", "--dt", "dt"),
        ("refine_window_s", "--refine-window-s", "refine_window_s"),
        ("integrator", "--integrator", "integrator"),
        ("smoothing_m", "--smoothing-m", "smoothing_m"),
        ("smoothing_N", "--smoothing-n", "smoothing_n"),
        ("peak_form", "--peak-form", "peak_form"), ("peak_site", "--peak-site", "peak_site"))}
    # one start value refused (start.gamma) as the user typed it, before --start as a whole
    flags = {**{f"start.{n}": (f"--start {n}", v) for n, v in _start_typed(args.start).items()},
             **flags}
    with named_as(flags):
        names = check_names(args.params)
    vehicle = jl.load_vehicle(args.config, "--config") if args.config else None
    drops = load_drop_tests(args.data, vehicle=vehicle, vehicle_name=f"--config {args.config}")
    _out_dir(args.out, [f for d in drops for f in d.files])  # the files the metadata named
    windows = _floats("--windows", args.windows)
    for flag, v in (("--refine-window-s", args.refine_window_s), ("--robust", args.robust)):
        if v is not None and not (math.isfinite(v) and v >= 0.0):
            raise jl.ConfigError(flag, v, "must be a finite number >= 0 (0: off)")
    if args.max_iter < 1:
        raise jl.ConfigError("--max-iter", args.max_iter, "must be at least 1")
    if not (math.isfinite(args.dt) and args.dt > 0.0):
        raise jl.ConfigError("--dt", args.dt, "must be a finite step > 0 [s]")
    # not given: the default, which fit shortens to the records where they end before it
    # (and says so); the report's arguments hold it filled in, its settings the window used
    refine = (_fit.AUTO if args.refine_window_s is None else
              args.refine_window_s if args.refine_window_s > 0 else None)
    if args.refine_window_s is None:
        args.refine_window_s = _fit.REFINE_WINDOW_S
    robust = args.robust if args.robust > 0 else None
    with named_as(flags):
        start = _start(args.start)
    peak_form = None if args.peak_form == "law" else args.peak_form
    from ._compare import peak_model_names

    fit_kw = dict(vehicle=vehicle, start=start, windows=windows,
                  refine_window_s=refine, robust=robust, method=args.method,
                  max_iter=args.max_iter, dt=args.dt, integrator=args.integrator,
                  smoothing_m=args.smoothing_m, smoothing_N=args.smoothing_n,
                  model_form=False if args.no_model_form else "auto",
                  peak_model_term=False if args.no_peak_model_term else "auto",
                  peak_site=args.peak_site)
    if args.compare_models and args.peak_site != HONEYCOMB:
        raise jl.ConfigError("--peak-site", args.peak_site, "--compare-models fits the peak "
                             "in the honeycomb; fit with --peak-site forces on its own")
    # every argument refused before the banner; --compare-models fits the peak model
    # (peak_form's) beside the model without the peak
    with named_as(flags):
        checked = _fit.check_fit(drops, peak_model_names(names) if args.compare_models
                                 else names, peak_form=peak_form, **fit_kw)
    print(f"jaxland fit: {len(drops)} drop test(s) ({', '.join(d.name for d in drops)}), "
          f"parameters {', '.join(names)}, method {args.method}, integrator "
          f"{checked.integrator} (dt {args.dt:g} s, smoothing {checked.smoothing_m:g} m / "
          f"{checked.smoothing_N:g} N)", file=sys.stderr)
    if checked.refine_note:
        print(f"jaxland fit: {checked.refine_note} (settings.refine_window_note in the report;"
              " --refine-window-s sets it)", file=sys.stderr)
    # the fit runs with the settings as checked (the integrator's default smoothing filled in)
    fit_kw.update(integrator=checked.integrator, smoothing_m=checked.smoothing_m,
                  smoothing_N=checked.smoothing_N, progress=_Progress(args.quiet),
                  fixed_params_term=False if args.no_fixed_params_term else "auto")
    if peak_form is not None:
        fit_kw["peak_form"] = peak_form
    cmp = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", _fit.IdentifiabilityWarning)
        warnings.simplefilter("always", _fit.MisfitWarning)
        if args.compare_models:
            from ._compare import compare_models

            cmp = compare_models(drops, names, **fit_kw)
            chosen = "peak" if cmp["comparison"]["peak_supported"] else "no_peak"
            result = cmp["_results"][chosen]
            for m in result.warnings:
                warnings.warn(m, _fit.IdentifiabilityWarning, stacklevel=1)
            if result.diagnostics["misfit"]:
                warnings.warn("the data contradict the chosen model: "
                              + "; ".join(result.diagnostics["misfit"]), _fit.MisfitWarning,
                              stacklevel=1)
        else:
            result = _fit.fit(drops, names, **fit_kw)
    for w in caught:
        print(f"jaxland fit: warning: {w.message}", file=sys.stderr)
    result.inputs = fit_inputs(args, drops)
    with staged(out, "fit") as staging:  # replaces out as a whole, only if all succeed
        (staging / "fitted_vehicle.toml").write_text(result.to_toml())
        result.to_json(staging / "fit_report.json")
        if cmp is not None:
            from ._compare import plot_comparison, write_comparison_json

            write_comparison_json(cmp, staging / "model_comparison.json")
            if not args.no_plots:
                plot_comparison(cmp, staging / "figures" / "model_comparison.png")
        if not args.no_plots:
            result.plot(staging / "figures")
    if cmp is not None:
        c = cmp["comparison"]
        print(f"model comparison: {c['verdict']} (likelihood ratio {c['likelihood_ratio']:.4g}"
              f", misfit-adjusted {c['likelihood_ratio_adjusted']:.3g}, p = "
              f"{c['p_value_adjusted']:.2g}; delta BIC {c['delta_bic']:.4g}); reporting the "
              f"{'peak' if c['peak_supported'] else 'no-peak'} model")
        for label in ("no_peak", "peak"):
            w = cmp[label]["worst_window"]
            where = "; ".join(f"{x['channel']} at {x['window_s'][0] * 1e3:.0f}-"
                              f"{x['window_s'][1] * 1e3:.0f} ms ({x['rms_noise_units']:.3g} x "
                              "noise)" for x in w)
            print(f"  {label}: chi2 {cmp[label]['chi2']:.6g}, largest misfit {where}")
    width = max(len(n) for n in result.names)
    diag = result.diagnostics
    capped = stopped_at_cap(result)
    if capped:
        print(f"jaxland fit: warning: the last stage stopped at its iteration cap (--max-iter "
              f"{args.max_iter}) before converging: the values below are not a minimum; "
              "raise --max-iter" + ("" if result.method == "lm" else " or use --method lm"),
              file=sys.stderr)
    from ._fit import starts_disagree

    short = None if capped else result.not_converged()
    if short is not None:  # starts in different minima, or the crush peak's fit ended worse
        advice = ("" if starts_disagree(result.settings.get("multistart")) else
                  "; fit without the peak's parameters, or from a start nearer the record")
        print(f"jaxland fit: warning: NOT CONVERGED: {short}{advice}", file=sys.stderr)
    verb = "fitted" if result.converged else "NOT CONVERGED,"
    print(f"{verb} in {result.wall_s:.1f} s ({sum(s['iterations'] for s in result.stages)} "
          f"iterations); residual variance factor {result.sigma2:.3g}, lag-1 residual "
          f"autocorrelation {diag['residual_lag1_autocorr']:.2f}"
          + ("  MISFIT of a fit short of its optimum, not of the model (above)" if short
             and diag["misfit"] else
             "  MISFIT: trust the HAC standard errors widened by the channel spread"
             + (" and the drop spread" if diag.get("drop_spread") is not None else "")
             + " (total)" if diag["misfit"] else ""))
    trusted = _INTERVAL_TEXT[diag["trust"]]
    pm = diag.get("peak_model_term")
    fp = diag.get("fixed_params_term")
    print("  interval reported: " + (
        f"total (std_error_total) = {trusted}"
        + (" + channel spread" if diag["misfit"] else "")
        + (" + drop spread" if diag.get("drop_spread") is not None else "")
        + (" + peak-shape term" if diag["model_form"] is not None else "")
        + (" + missing-peak term" if pm is not None and pm["added"] else "")
        + (" + fixed-parameter term" if fp is not None and fp["added"] else "")
        if diag["interval"] == "std_error_total" else trusted))
    print(held_fixed_line(result))
    npc = diag.get("no_peak_check")
    if npc is not None and npc.get("chi2_no_peak") is not None:
        print(f"  against the model without the crush peak: chi2 "
              f"{min(npc['chi2_from_start'], npc['chi2_from_no_peak']):.6g} (the run from "
              f"{npc['started_from']} kept; from the other "
              f"{max(npc['chi2_from_start'], npc['chi2_from_no_peak']):.6g}) against "
              f"{npc['chi2_no_peak']:.6g} without the peak")
    elif npc is not None:
        print(f"  the fit without the crush peak, its check, failed ({npc['no_peak_failed']})")
    if pm is not None:
        print("  missing crush peak: the residuals show misfit and the model has no crush "
              + ("peak, so it was fitted again with one ("
                 + ", ".join(f"{k} {v:.4g}" for k, v in pm["values"].items()
                             if k in ("peak1", "L_peak1"))
                 + f"; chi2 {pm['chi2_with']:.6g} against {pm['chi2_without']:.6g} without); "
                 "each value's shift to that fit is added to the total (--no-peak-model-term "
                 "leaves it out; --compare-models says whether the data support the peak)"
                 if pm["added"] else
                 f"peak; the fit with one failed ({pm['failed']}), so the total leaves out "
                 "how far the peak moves the values"
                 + (f"; but {diag['peak_not_called_for']}" if diag.get("peak_not_called_for")
                    else "")))
    if fp is not None:
        freed = ", ".join(fp["freed"])
        print(f"  parameters left fixed: the residuals show misfit and {freed} stayed at the "
              "vehicle's values, " + (
                  "so it was fitted again with them freed ("
                  + ", ".join(f"{k} {fp['values'][k]:.6g}" for k in fp["freed"])
                  + f"; chi2 {fp['chi2_wider']:.6g} against {fp['chi2_fit']:.6g} with them "
                  "fixed); each value's shift to that fit is added to the total "
                  "(--no-fixed-params-term leaves it out; fit them too where the record "
                  "determines them)" if fp["added"] else
                  f"and the fit with them freed failed ({fp['failed']}), so the total leaves "
                  "out how far they move the values"))
    ds = diag.get("drop_spread")
    if ds is not None:
        big = ds["largest"]
        print("  drop spread: the values refitted without each drop in turn"
              + (f"; without {big['drop']} they move most ({big['param']} by "
                 f"{big['shift']:+.4g} {PARAMS[big['param']][1]}, {big['z']:.2g} x its "
                 "HAC standard error)" if big is not None else "")
              + (f"; the drops disagree more than the channels on {', '.join(ds['dominates'])}"
                 if ds["dominates"] else "")
              + (f"; {ds['failed']}, so the total leaves out how far that drop pulls the fit"
                 if ds["failed"] else "")
              + "; each value's largest shift is added to the total")
    if diag.get("interval_bounded") is False:
        print("  NO TRUSTED INTERVAL: " + "; ".join(diag["interval_not_bounded"])
              + ". The misfit calls for it: the +/- below is the scatter about a biased fit, "
              "not a bound on the values' error, which can be many times larger")
    mf = diag["model_form"]
    if mf is not None:
        other = ", ".join(f"{k} (dAIC {f['daic_adjusted']:+.3g}"
                          + (")" if f["plausible"] else ", not supported)")
                          for k, f in mf["forms"].items() if f is not None and k != mf["form"])
        print(f"  peak shape: fitted as {mf['form']}; other forms, misfit-adjusted: {other}"
              + (f"; failed: {', '.join(mf['failed'])}" if mf["failed"] else "")
              + f"; best supported: {mf['best_supported']}")
        caveat = form_caveat(mf)
        if caveat:
            print(caveat)
        best = mf["forms"].get(mf["best_supported"]) or {}
        if mf["best_supported"] != mf["form"] and best.get("values"):
            vals = best["values"]
            print(f"  the {mf['best_supported']} form's values: "
                  + ", ".join(f"{k} {v:.6g}" for k, v in vals.items() if k not in SHAPE_PARAMS)
                  + " (each within the total interval below); its peak: "
                  + ", ".join(f"{k} {v:.6g}" for k, v in vals.items() if k in SHAPE_PARAMS))
    if diag.get("peak_location") is not None:
        print(peak_location_line(diag["peak_location"]))
    if result.settings.get("peak_site") == FORCES:
        print(peak_site_line(diag.get("peak_site_check")))
    interval, errors = result.reported_errors()
    for i, n in enumerate(result.names):
        flag = ("   AT A BOUND OF THE VEHICLE'S RULES" if n in diag.get("at_bound", ())
                else "" if result.identified[i] else "   NOT IDENTIFIED")
        others = {"std_error": f"classical {_pm(result.std_errors[i])}",
                  "std_error_hac": f"HAC {_pm(result.std_errors_hac[i])}"}
        others.pop(interval, None)
        # where the value +/- Z95 errors leaves the range its law allows, the 95 % interval
        # taken in the fit's own coordinates stays inside it
        ci, (lo, hi) = result.interval95(n, errors[i]), result.ranges.get(n, (-math.inf, None))
        outside = ci is not None and (result.values[i] - Z95 * errors[i] <= lo or (
            hi is not None and result.values[i] + Z95 * errors[i] >= hi))
        inside = (f"; 95 % {_end(ci[0], lo, hi)} to {_end(ci[1], lo, hi)}, inside its range"
                  if outside else "")
        print(f"  {n:<{width}} = {result.values[i]:.6g} {_pm(errors[i])} {PARAMS[n][1]} "
              f"({interval}; {', '.join(others.values())}; "
              f"start {result.start_values[i]:.6g}{inside}){flag}")
    print(f"wrote {out}/fitted_vehicle.toml, fit_report.json"
          + (", model_comparison.json" if cmp is not None else "")
          + ("" if args.no_plots else ", figures/*.png"))
    return 0


def _pm(error: float) -> str:
    """A standard error as printed: "+/- 0.012", or "no standard error" where the fit gives
    none (a value at a bound of its rule: NaN, as fit_report.json's null)."""
    return f"+/- {error:.2g}" if math.isfinite(error) else "no standard error"


def _end(x, lo, hi) -> str:
    """An interval's end to 4 digits, or to as many as keep it off the range's ends (lo, hi)
    that it lies strictly inside; None: unbounded."""
    if x is None:
        return "inf"
    for digits in (4, 7, 10, 17):
        text = f"{x:.{digits}g}"
        if float(text) not in (lo, hi):
            return text
    return text


def _cmd_predict(args) -> int:
    from ._data import load_drop_tests
    from ._predict import check_model_step, config_header, predict, read_fit_status

    out = _out_dir(args.out, (args.config, *args.data), "predict")
    vehicle = jl.load_vehicle(args.config, "--config")
    check_model_step(vehicle, f"--config {args.config}")  # the key in the user's file
    # what the fit said of the vehicle, if it is one, and whether the file still holds it
    status = read_fit_status(args.config, vehicle)
    # one vehicle, the drops' own article, different names
    drops = load_drop_tests(args.data, vehicle=vehicle, vehicle_name=f"--config {args.config}")
    _out_dir(args.out, [f for d in drops for f in d.files])  # the files the metadata named
    lines = fit_status_lines(args.config, status)
    if status["from_fit"] and not status["sound"]:
        print(f"jaxland predict: warning: {lines[0]}", file=sys.stderr)
    preds = [predict(vehicle, d) for d in drops]
    from jaxland._files import run_environment

    environment = run_environment()
    for p, path, d in zip(preds, args.data, drops):  # each names what it was run from
        meta, data, *cfg = d.files
        p.inputs = dict(vehicle_config=str(Path(args.config).resolve()),
                        vehicle_as_run="vehicle.toml", data=str(Path(path).resolve()),
                        jaxland_version=jl.__version__,
                        # each file with its SHA-256: whether the file at that path is still
                        # the one used (a refit replaces the fit's folder as a whole)
                        files=dict(vehicle_config=file_record(args.config),
                                   metadata=file_record(meta), data_file=file_record(data),
                                   drop_vehicle_config=file_record(cfg[0]) if cfg else None),
                        environment=environment)
        p.fit_status = status
    # a fitted vehicle keeps what the fit said of it: predict reads its flags from there
    head = "".join(f"{x}\n" for x in config_header(args.config)) if status["from_fit"] else ""
    with staged(out, "predict") as staging:  # replaces out as a whole, only if all succeed
        (staging / "vehicle.toml").write_text(
            head + f"# the vehicle predicted with (--config {args.config})\n"
            + jl.vehicle_to_toml(vehicle))
        for p in preds:
            p.to_json(staging / f"prediction_{p.drop.name}.json")
            if not args.no_plots:
                p.plot(staging / "figures" / f"prediction_{p.drop.name}.png")
    for line in lines:
        print(line)
    for p in preds:
        print(f"jaxland predict: {p.drop.name} with {args.config}")
        for k, v in p.metrics.items():
            print(f"  {k:<22} data {v['data']:<12.6g} model {v['model']:<12.6g} "
                  f"error {v['rel_error']:+.2%}")
    print(f"wrote {out}/" + ", ".join(f"prediction_{p.drop.name}.json" for p in preds)
          + ", vehicle.toml" + ("" if args.no_plots else ", figures/*.png"))
    return 0


def fit_status_lines(config: str, status: dict) -> list[str]:
    """predict's lines on the vehicle's fit (``read_fit_status``): none for a vehicle not
    written by ``jaxland fit``; else whether the fit is sound or which flags it carries, the
    MISFIT, NOT CONVERGED and NO TRUSTED INTERVAL lines' text, and each fitted value's
    standard error (untrusted where the header says so), which the
    predictions do not carry. A file whose values differ from its header's (``edited``) is
    named as edited, each value with the file's and the fitted number, never as sound."""
    from ._predict import EDITED

    if not status["from_fit"]:
        return []
    edited = status.get("edited") or []
    others = [f for f in status["flags"] if not f.startswith(EDITED)]
    if edited:
        head = (f"{config}: fitted vehicle edited since the fit: " + "; ".join(
            "a key the fit does not calibrate (a mass, a length, a peak's table; the header's "
            "SHA-256 of them differs)" if e.get("article") else
            f"{e['key']} = {e['file']:.6g} in the file, "
            + ("off in the fit" if e.get("off_in_fit") else f"{e['fitted']:.6g} "
               + ("held by the fit" if e.get("held") else "fitted"))
            for e in edited) + ": these predictions are for the file's values, not the "
            "fitted ones" + (f"; the fit is also flagged {', '.join(others)}" if others
                             else ""))
    elif status["sound"]:
        head = (f"{config}: fitted vehicle, fit sound (converged, no misfit, every value "
                "identified)")
    else:
        head = (f"{config}: fitted vehicle whose fit is flagged {', '.join(status['flags'])}"
                ": these predictions are not those of a sound fit")
    lines = [head]
    for flag, key in (("MISFIT", "misfit"), ("NOT CONVERGED", "not_converged"),
                      ("NO TRUSTED INTERVAL", "interval_not_bounded")):
        if status[key] is not None:
            lines.append(f"  {flag}: {status[key]}")
    lines += [f"  {flag}: {text}" for flag, text in status.get("cautions", {}).items()]
    params = status["parameters"]
    if params:
        lines.append(f"  fitted values (+/- {status['interval']}): " + ", ".join(
            f"{n} {p['value']:.6g} +/- {p['std_error']:.2g} {p['unit']}"
            + (f" ({p['rel_std_error']:.1%})" if p["rel_std_error"] is not None else "")
            if p["std_error"] is not None and p["value"] is not None else
            f"{n} {p['value'] if p['value'] is None else format(p['value'], '.6g')} "
            f"{p['unit']} ({p['note'] or 'no standard error'})"
            for n, p in params.items()))
    lines.append("  the predictions below carry no uncertainty band: they are for the "
                 + ("file's values alone (not the fitted ones)" if edited
                    else "fitted values alone"))
    return lines


def add_subcommands(subparsers) -> None:
    """Register ``fit`` and ``predict`` on an argparse subparsers object."""
    from ._fit import INTEGRATOR, INTEGRATORS, REFINE_WINDOW_S, ROBUST_K, SMOOTHING, WINDOWS_S
    from ._parameters import DEFAULT_PARAMS, EXP_TABLE_SPAN, HONEYCOMB, PARAMS, PEAK_SITES
    from ._problem import SAVE_DT

    f = subparsers.add_parser(
        "fit", help="calibrate the quarter model to drop-test traces; write the fitted "
                    "config, a report and figures")
    f.add_argument("data", nargs="+", metavar="DATA",
                   help="drop tests: metadata TOML files (or their CSVs, TOML beside them)")
    f.add_argument("--params", default=",".join(DEFAULT_PARAMS),
                   help=f"parameters to fit, comma-separated (default {','.join(DEFAULT_PARAMS)}"
                        f"; known: {','.join(PARAMS)})")
    f.add_argument("--config", help="vehicle TOML for the fixed parameters and the start "
                                     "(default: the drops' vehicle_config)")
    f.add_argument("--start", help="start values, e.g. k=2e6,F1=5000 (SI; default: the config)")
    f.add_argument("--windows", default=",".join(f"{w:g}" for w in WINDOWS_S),
                   help="growing fit windows after touchdown [s] (default "
                        f"{','.join(f'{w:g}' for w in WINDOWS_S)})")
    f.add_argument("--refine-window-s", type=float, default=None,
                   help="one refit on this window after touchdown [s], longer than the last "
                        "of --windows and within every record, or refused (0: skip; default "
                        f"{REFINE_WINDOW_S:g}, shortened to the shortest record where one ends "
                        "before, and said so)")
    f.add_argument("--robust", type=float, default=ROBUST_K,
                   help=f"Huber threshold in robust residual std (default {ROBUST_K:g}; 0: "
                        "plain least squares)")
    f.add_argument("--method", default="lm", choices=("lm", "lbfgs"),
                   help="lm: Levenberg-Marquardt on the jacfwd Jacobian (default); lbfgs: "
                        "optax.lbfgs")
    f.add_argument("--max-iter", type=int, default=60, help="iterations per stage (default 60)")
    f.add_argument("--dt", type=float, default=1e-5, help="integration step [s] (default 1e-5; "
                   f"it must divide the model's {SAVE_DT:g} s sampling: {SAVE_DT:g}, "
                   f"{SAVE_DT / 2:g}, {SAVE_DT / 4:g} ...)")
    f.add_argument("--integrator", default=INTEGRATOR,
                   help=f"the model's integrator, one of {', '.join(INTEGRATORS)} (default "
                        f"{INTEGRATOR})")
    f.add_argument("--smoothing-m", type=float, default=None,
                   help="width of the rounded length switches (contact, unloading, stick/slip) "
                        "[m]; 0: hard switches (default: "
                        + ", ".join(f"{k} {v[0]:g}" for k, v in SMOOTHING.items()) + ")")
    f.add_argument("--smoothing-n", type=float, default=None,
                   help="width of the rounded force switch (the strut's no-pull floor) [N] "
                        "(default: " + ", ".join(f"{k} {v[1]:g}" for k, v in SMOOTHING.items())
                        + ")")
    f.add_argument("--compare-models", action="store_true",
                   help="fit with and without the honeycomb's initial crush peak (peak1, "
                        "L_peak1), report which the data support (likelihood ratio adjusted "
                        "for misfit, AIC, BIC) and where each misfits (model_comparison.json, "
                        "figures/model_comparison.png); the supported model is the fit written")
    f.add_argument("--peak-form", choices=("law", *EXP_TABLE_SPAN), default="law",
                   help="the fitted crush peak's form (with peak1, L_peak1): law, the law's "
                        "linear fall (built up over L_rise1 when that is fitted); exp, an "
                        "exponential decay of length L_peak1; rise_exp, that decay built up "
                        "linearly over L_rise1; smooth_exp, that decay built up smoothly, "
                        "(1 - exp(-c / L_rise1)) exp(-c / L_peak1), peak1 its top and L_rise1 "
                        "the build-up's length scale; ripple, a peak that re-peaks fold by "
                        "fold, falling linearly to F1 over half a fold and rising to the next "
                        "peak over the other half, the peaks decaying as exp(-c / L_peak1), "
                        "L_rise1 the fold length (with L_rise1 fitted for the last three) "
                        "(default law)")
    f.add_argument("--peak-site", choices=PEAK_SITES, default=HONEYCOMB,
                   help="where the fitted crush peak sits (with peak1): honeycomb, the law's "
                        "(its crush work moves the stroke and the body); forces, the force "
                        "channels alone (the drop runs without it; the force channels carry it "
                        "as a gain), for a record whose peak the motion does not show (the "
                        "report's 'peak location' line); the fitted vehicle then has no peak "
                        "(default honeycomb)")
    f.add_argument("--no-model-form", action="store_true",
                   help="leave out the peak-shape (model-form) term, on by default when the "
                        "fit has the crush peak: the values refitted in the peak's other forms "
                        "(linear, built up, exponential, built-up and smoothly built-up "
                        "exponential) and the largest "
                        "shift among those the data support added to the total standard error")
    f.add_argument("--no-peak-model-term", action="store_true",
                   help="leave out the missing-peak term, on by default when the residuals "
                        "show misfit and the fitted model has no crush peak: the fit repeated "
                        "with the crush peak (peak1, L_peak1) and each value's shift to it "
                        "added to the total standard error")
    f.add_argument("--no-fixed-params-term", action="store_true",
                   help="leave out the fixed-parameter term, on by default when the residuals "
                        "show misfit and --params leaves some of the default parameters (k, "
                        "gamma, D_b, k_b1, F1, F2) fixed: the fit repeated from its optimum "
                        "with those freed as well and each value's shift to it added to the "
                        "total standard error")
    f.add_argument("--out", default="out/fit", help="output folder (default out/fit)")
    f.add_argument("--no-plots", action="store_true", help="skip the figures")
    f.add_argument("--quiet", action="store_true", help="no per-iteration progress lines")
    f.set_defaults(func=_cmd_fit)

    p = subparsers.add_parser(
        "predict", help="simulate drop tests with a (fitted) vehicle and compare peaks and "
                        "strokes with the data")
    p.add_argument("data", nargs="+", metavar="DATA", help="drop tests (metadata TOML or CSV)")
    p.add_argument("--config", required=True, help="vehicle TOML, e.g. fitted_vehicle.toml")
    p.add_argument("--out", default="out/predict", help="output folder (default out/predict)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.set_defaults(func=_cmd_predict)
