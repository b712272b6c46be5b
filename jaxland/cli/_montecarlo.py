"""``jaxland montecarlo``."""

from __future__ import annotations

from .. import use_batch_fusion
from .._checks import named_as
from .._montecarlo._stats import all_landings_text, ranked_inputs
from ._common import out_dir, use_cpu_cores

# envelopes whose low tail is the danger (the others: the high tail)
LOW_SIDE = ("min_stability_margin_m",)


def _no_successful_landing(s: dict) -> None:
    """Refuse a run in which no landing succeeded, before anything is written: its
    probabilities and envelopes would be 0/0. Bad input (exit 2) where every landing was
    outside the documented envelope or did not touch down, a numerical failure (exit 3) where
    any failed numerically."""
    from .._errors import ConfigError, SimulationError
    from .._solvers import Result

    why = dict(s["failures"])
    for code, key in ((Result.NO_TOUCHDOWN, "n_no_touchdown"), (Result.UNFINISHED, "n_unfinished")):
        if s[key]:
            why[code.message] = s[key]
    text = ", ".join(f"{k}: {v}" for k, v in why.items())
    if set(why) <= {Result.NO_TOUCHDOWN.message, Result.UNFINISHED.message}:
        raise ConfigError("montecarlo.t_end_s", s["t_end_s"], f"no landing succeeded ({text}), "
                          "so there is no probability or envelope to report: raise it so that "
                          "the landings touch down and finish their impact")
    if set(why) <= {Result.OUTSIDE_ENVELOPE.message, Result.NO_TOUCHDOWN.message,
                    Result.UNFINISHED.message}:
        raise ConfigError("dispersion", f"{s['n']} samples", f"no landing succeeded ({text}), so "
                          "there is no probability or envelope to report: keep the dispersions "
                          "inside the documented envelope and t_end_s long enough to touch down "
                          "and finish the impact")
    again = ("" if s["n_retried"] else
             "; retry = true reruns numerical failures at the steps they need")
    raise SimulationError(f"none of the {s['n']} landings succeeded ({text}): there is no "
                          f"probability or envelope to report; rerun with montecarlo.dt_s "
                          f"below {s['dt_s']:g} s{again}")


def _retried_text(result) -> str:
    """What the retries did (``_montecarlo._run._retry``): how many samples failed
    numerically and ran again, how, down to which step, and how many still failed."""
    import numpy as np

    from .._montecarlo._run import RETRY_STEPS
    from .._solvers import FAILED_CODES

    s, o = result.summary, result.outputs
    retried = o["retried"]
    how = ("with the strut damping implicit (euler_implicit) at the step their forces allow "
           "(at most dt_s)" if s["method"] == "euler" else
           f"with {s['retry_method']} at the smaller step their forces allow, or a quarter "
           "of dt_s where that is no smaller")
    still = int(np.isin(result.failure[retried], FAILED_CODES).sum())
    return (f"{s['n_retried']} (failed numerically at dt_s = {s['dt_s']:g} s; rerun {how}, "
            f"then at a quarter of that step while failing, up to {RETRY_STEPS} tries; "
            f"smallest step {float(o['dt_s'][retried].min()):.3g} s, per sample in "
            f"samples.csv; {still} still failed)")


def cmd_montecarlo(args) -> int:
    from .._config import load_vehicle, named_by_file, paper_vehicle
    from .._errors import ConfigError
    from .._montecarlo import init_distributed, load_montecarlo_spec, run_montecarlo
    from .._montecarlo._run import check_touchdown_possible

    if args.coordinator is None:
        for flag, v in (("--num-processes", args.num_processes),
                        ("--process-id", args.process_id)):
            if v is not None:
                raise ConfigError(flag, v, "needs --coordinator HOST:PORT (a run of several "
                                  "processes); without it the run is one process")
    else:
        for flag, v in (("--num-processes", args.num_processes),
                        ("--process-id", args.process_id)):
            if v is None:
                raise ConfigError("--coordinator", args.coordinator,
                                  f"needs {flag} too (each process of the run gives the count "
                                  "and its own rank)")
    out = out_dir(args.out, (args.spec, args.config), "montecarlo")
    use_cpu_cores(args.devices)  # before any JAX work
    use_batch_fusion()  # batches without trajectories (jaxland.use_batch_fusion)
    flags = {field: (flag, v) for field, flag, v in (
        ("montecarlo.n", "--n", args.n), ("montecarlo.seed", "--seed", args.seed),
        ("chunk", "--chunk", args.chunk), ("num_processes", "--num-processes",
                                           args.num_processes),
        ("process_id", "--process-id", args.process_id),
        ("coordinator", "--coordinator", args.coordinator)) if v is not None}
    with named_as(flags):
        if args.coordinator is not None:  # one of several processes; process 0 writes outputs
            init_distributed(args.coordinator, args.num_processes, args.process_id)
    spec = load_montecarlo_spec(args.spec)  # its own values are refused by their keys
    with named_as(flags):
        if args.n is not None:
            spec.n = args.n
        if args.seed is not None:
            spec.seed = args.seed
        spec.__post_init__()  # re-check n and seed after the overrides
        vehicle = load_vehicle(args.config, "--config") if args.config else paper_vehicle()
        with named_by_file(args.config and "--config", args.config):
            check_touchdown_possible(spec, vehicle)
            result = run_montecarlo(spec, vehicle, chunk=args.chunk, progress=not args.quiet)
    import jax

    if jax.process_index() != 0:
        return 0
    s = result.summary
    if s["n_succeeded"] == 0:
        _no_successful_landing(s)
    result.save(out, plots=not args.no_plots)
    tip, bot = s["tip_over"], s["bottoming"]
    print(f"jaxland montecarlo: {s['n']} landings, {s['model']} model, {s['devices']} device(s),"
          f" {s['wall_s']:.1f} s ({s['landings_per_s']:.3g}/s)")
    failures = f"  {s['failures']}" if s["failures"] else ""
    print(f"  failed samples      {s['n_failed']}{failures}")
    if s["n_retried"]:
        print(f"  retried samples     {_retried_text(result)}")
    if s["early_stop"]:
        settled = s["settled_time_s"]
        print(f"  settled before t_end {s['n_settled']}"
              + (f" (median {settled['p50']:.3g} s)" if settled else ""))
    if s["n_no_touchdown"]:
        print(f"  no touchdown        {s['n_no_touchdown']} (counted apart; raise t_end_s)")
    if s["n_unfinished"]:
        print(f"  unfinished          {s['n_unfinished']} (t_end_s came during an impact or "
              "before the tip-over was decided: counted apart; raise t_end_s)")
    if tip["modelled"]:
        print(f"  P(tip-over)         {tip['probability']:.4g}  95% CI "
              f"[{tip['ci95_wilson'][0]:.4g}, {tip['ci95_wilson'][1]:.4g}]  "
              f"({tip['count']}/{tip['n']}){all_landings_text(tip)}")
    else:  # no probability to print: a 0 would read as computed
        print(f"  P(tip-over)         not modelled: {tip['reason']}")
    print(f"  P(bottoming out)    {bot['probability']:.4g}  95% CI [{bot['ci95_wilson'][0]:.4g}, "
          f"{bot['ci95_wilson'][1]:.4g}]  ({bot['count']}/{bot['n']}){all_landings_text(bot)}")
    for name, env in s["envelopes"].items():
        if not env:
            continue
        if name in LOW_SIDE:  # the side that matters: a small margin is the danger
            print(f"  {name:<30s} min {env['min']:.4g}  p01 {env['p01']:.4g}  p50 {env['p50']:.4g}")
        else:
            lo, hi = s["envelopes_ci95"][name]["p99"]
            print(f"  {name:<30s} p50 {env['p50']:.4g}  p99 {env['p99']:.4g} (95 % "
                  + ("-" if lo is None else f"{lo:.4g}") + " to "
                  + ("beyond the sample" if hi is None else f"{hi:.4g}")
                  + f")  max {env['max']:.4g}")
    if s.get("t_end_check"):
        print(f"  t_end check         {_t_end_check_text(s)}")
    if s["sensitivity"]["ranking"]:
        top = ", ".join(f"{r['input']} ({r['effect_per_std']:+.3g}"
                        + ("" if r["t"] is None else f", t {r['t']:+.1f}") + ")"
                        for r in s["sensitivity"]["ranking"][:3])
        print(f"  drivers of {s['sensitivity']['target']}: {top}")
    else:
        print(f"  drivers of {s['sensitivity']['target']}: not estimated "
              f"({s['sensitivity']['not_estimated']})")
    if not args.no_plots and s["tip_over"].get("modelled", True) \
            and len(ranked_inputs(s["sensitivity"]["ranking"])) < 2:
        print("  no tip-over map: it is drawn over the two most influential inputs, and the "
              "drivers rank fewer")
    print(f"wrote {out}/samples.csv, samples.npz, summary.json, spec.toml, vehicle.toml"
          + ("" if args.no_plots else ", figures/*.png"))
    return 0


def _t_end_check_text(s: dict) -> str:
    """The t_end check's line: how many landings called finished at t_end_s still changed by
    the check's end (``jaxland._montecarlo._run.check_t_end``)."""
    c = s["t_end_check"]
    if c.get("skipped"):
        return f"skipped: {c['skipped']}"
    failed = (f"; {c['n_rerun_failed']} rerun(s) failed numerically and judge nothing"
              if c["n_rerun_failed"] else "")
    if not c["n_checked"]:
        return f"no landing could be checked{failed}"
    head = (f"{c['n_changed']} of {c['n_checked']} {c['of']} at t_end_s = {s['t_end_s']:g} s "
            f"still changed before {c['t_end_s']:g} s")
    lo, hi = c["changed"]["ci95_wilson"]
    if not c["n_changed"]:  # final on the landings checked; how many more may not be, their
        # count bounds
        return (head + f" (each max stroke within {c['tolerance']:.1%} of itself){failed}: "
                f"the checked landings are final at t_end_s; up to {hi:.0%} of the "
                f"{c['of']} may not be (95 % upper bound)")
    what = ([f"max stroke grew on {c['n_max_stroke_grew']} (up to "
             f"{c['max_stroke_growth_m'] * 1e3:.3g} mm)"] if c["n_max_stroke_grew"] else [])
    what += [f"{c[k]} {name}" for k, name in (("n_tipped_later", "tipped over later"),
                                               ("n_bottomed_later", "bottomed out later"))
             if c[k]]
    return (head + f": {', '.join(what)}{failed}. For {lo:.0%} to {hi:.0%} of the {c['of']} "
            "(95 % CI) the outcomes above are not final at t_end_s: raise t_end_s")
