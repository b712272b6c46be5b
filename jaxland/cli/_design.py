"""``jaxland design``: robust gradient-based gear design from a spec TOML.

``add_subcommands(subparsers)`` registers it on an ``argparse`` subparsers object. The handler
writes, through a staging folder moved into place only once every file exists:
``design_vehicle.toml`` (loadable by ``jaxland simulate --config``; only for a feasible design),
``design_report.json``, ``figures/design_*.png`` and, where a verification ran, its
landings, ``verification/before/`` and ``verification/after/`` (Monte Carlo folders). Exit
codes: 0 feasible design that passed its verification, 4 no feasible design found (the
report names the violated constraints), 5 a design feasible on its scenes that the
verification Monte Carlo does not confirm after the re-optimisation rounds (the report and
stderr say why), 2 invalid input, 3 numerical failure.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from .. import use_batch_fusion
from .._checks import named_as
from .._config import named_by_file
from .._files import file_record, staged
from .._montecarlo._stats import probability_text
from .._progress import ProgressLine
from ._common import out_dir, use_cpu_cores
from ._montecarlo import _t_end_check_text

__all__ = ["add_subcommands", "EXIT_INFEASIBLE", "EXIT_UNVERIFIED"]

EXIT_INFEASIBLE = 4
EXIT_UNVERIFIED = 5


def _progress(quiet: bool, total: int):
    """One stderr line per design iteration."""
    line = ProgressLine("design", quiet=quiet)

    def show(rec: dict) -> None:
        cons = "  ".join(f"{k} {v:+.3f}" for k, v in rec["constraints"].items())
        vals = "  ".join(f"{k} {v:.5g}" for k, v in rec["values"].items())
        # a re-optimisation round counts its own iterations (``of``)
        head = f"round {rec['round']} " if rec.get("round") else ""
        line(f"{head}iter {rec['iteration']:3d}/{rec.get('of', total)}  objective "
             f"{rec['objective_measure_mps2']:.4g} m/s^2  g: {cons}  rho {rec['penalty']:.3g}"
             f"{'  REJECTED' if rec['rejected'] else ''}  |  {vals}  {rec['wall_s']:6.1f} s")
    return show


def _g_units(c) -> str:
    """What a constraint's g counts: its violation (positive: violated) over its scale,
    in the threshold key's units (g = -9.98 of a 10 mm scale is 99.8 mm to spare)."""
    from .._design._spec import CONSTRAINTS

    info = CONSTRAINTS[c.name]
    unit = info.key.rsplit("_", 1)[-1]
    return f"in units of {c.scale / info.to_si:g} {unit}, negative: met"


def _cmd_design(args) -> int:
    import jaxland as jl

    from .._checks import check_field
    from .._design import (
        DesignProblem,
        DesignSpec,
        check_verification,
        design_verified,
        load_design_spec,
        optimise_design,
    )
    from .._design._verify import MIN_JUDGED, clean_landings_needed
    from .._montecarlo import MonteCarloSpec

    out = out_dir(args.out, (args.spec, args.config), "design")
    use_cpu_cores(args.devices)  # before any JAX work: the design scenes and the
    # verification Monte Carlo are split over them
    use_batch_fusion()  # batches without trajectories (jaxland.use_batch_fusion)
    spec = load_design_spec(args.spec)
    files = dict(spec=file_record(args.spec))  # as read, before the long run
    out_dir(args.out, (spec.vehicle,))  # the baseline vehicle the spec names is an input too
    # a flag's value is checked by the rule of the spec's key it overrides, named by the flag
    if args.iterations is not None:
        spec.iterations = check_field(DesignSpec, "iterations", "--iterations", args.iterations)
    if args.verify_n is not None:
        if args.verify_n < 0:
            raise jl.ConfigError("--verify-n", args.verify_n, "must be >= 0 (0: no verification)")
        spec.montecarlo.n = (check_field(MonteCarloSpec, "n", "--verify-n", args.verify_n)
                             if args.verify_n else 1)  # 0: no verification runs
    vehicle = (jl.load_vehicle(args.config, "--config") if args.config else
               jl.load_vehicle(spec.vehicle, "design.vehicle") if spec.vehicle
               else jl.paper_vehicle())
    if args.config or spec.vehicle:
        files["baseline_vehicle"] = file_record(args.config or spec.vehicle)
    # every input check (bounds, scenes, steps) before the banner: one line if bad
    vehicle_by = ("--config", args.config) if args.config else (
        ("design.vehicle", spec.vehicle) if spec.vehicle else (None, None))
    with named_by_file(*vehicle_by):
        problem = DesignProblem(spec, jl.validate_vehicle(vehicle))
    if args.verify_n != 0:
        with named_as({} if args.verify_n is None else
                            {"montecarlo.n": ("--verify-n", args.verify_n)}), \
                named_by_file(*vehicle_by):
            check_verification(problem)
            # a verification too small for any verdict could only end "not verified" (exit
            # 5) after the whole design; a Python caller may still run one, to look at it
            if spec.montecarlo.n < MIN_JUDGED:
                raise jl.ConfigError(
                    "montecarlo.n", spec.montecarlo.n, f"must be >= {MIN_JUDGED} (or "
                    f"--verify-n 0: no verification): a constraint's 95 % interval needs "
                    f"{MIN_JUDGED} landings, so fewer can never confirm the design")
            # likewise a max constraint, met only by enough landings none of which violates it
            for c in spec.constraints:
                need = clean_landings_needed(c.violation_tolerance)
                if c.measure == "max" and spec.montecarlo.n < need:
                    raise jl.ConfigError(
                        "montecarlo.n", spec.montecarlo.n,
                        f"must be >= {need} for constraints.{c.name} (measure = max), or "
                        "--verify-n 0: no verification: it is met only where no verification "
                        "landing violates it and the 95 % upper bound on its violation "
                        f"probability is within violation_tolerance = "
                        f"{c.violation_tolerance:g}, which takes {need} landings (or raise the "
                        "tolerance)")
    print(f"jaxland design: {len(spec.variables)} variables ({', '.join(spec.names)}), "
          f"{spec.n_scenes} scenes, {spec.resolved_model()} model, {spec.iterations} iterations",
          file=sys.stderr)
    t0 = time.perf_counter()
    if args.verify_n == 0:
        result = optimise_design(spec, vehicle, progress=_progress(args.quiet, spec.iterations),
                                 problem=problem)
    else:
        result = design_verified(spec, vehicle, progress=_progress(args.quiet, spec.iterations),
                                 problem=problem,
                                 mc_progress=not args.quiet,
                                 say=lambda msg: print(f"jaxland design: {msg}",
                                                       file=sys.stderr))
    with staged(out, "design") as staging:  # replaces out as a whole, only if all succeed
        if result.status == "feasible":
            (staging / "design_vehicle.toml").write_text(result.to_toml())
        result.to_json(staging / "design_report.json", inputs=dict(
            spec=str(Path(args.spec).resolve()),
            baseline_vehicle=(str(Path(args.config or spec.vehicle).resolve())
                              if args.config or spec.vehicle else "the paper's vehicle"),
            arguments={k: v for k, v in vars(args).items() if k not in ("func", "command")},
            files=files))
        if not args.no_plots:
            result.plot(staging / "figures")
        # every verification landing, the baseline's and the design's, as a Monte Carlo
        # folder: inputs and outcomes per sample (t_end_s: where each one ended, continued)
        for tag, res in (("before", result.mc_before), ("after", result.mc_after)):
            if res is not None:
                res.save(staging / "verification" / tag, plots=False, rerun=(
                    "these landings to t_end_s again; those the verification judged at a "
                    "later end (samples.csv, t_end_s) ran on from there"))
    total = time.perf_counter() - t0
    print(f"jaxland design: total {total:.1f} s (last optimisation {result.wall_s:.1f} s)")
    print(f"design {result.status} after {result.iterations_run} iterations in "
          f"{result.wall_s:.1f} s (compile {result.compile_s:.1f} s)")
    for v in result.problem.variables:
        print(f"  {v.name:<28} {result.start_values[v.name]:<12.6g} -> "
              f"{result.values[v.name]:.6g}   bounds [{v.low:g}, {v.high:g}]")
    s0, s1 = result.at_start, result.at_design
    print(f"  objective on the design scenes: {s0['objective_measure_mps2']:.4g} -> "
          f"{s1['objective_measure_mps2']:.4g} m/s^2")
    units = {c.name: _g_units(c) for c in spec.constraints}
    for name, c in s1["constraints"].items():
        print(f"  constraint {name:<10} g {s0['constraints'][name]['g']:+.4f} -> {c['g']:+.4f}"
              f" ({units[name]})")
    if s1["n_unfinished"]:
        print(f"  note: {s1['n_unfinished']} design scene(s) still in their impact at "
              f"t_end_s = {spec.t_end:g} s: their strokes and peaks are not final; raise "
              "design.t_end_s", file=sys.stderr)
    if result.verification:
        v = result.verification
        print(f"  verification Monte Carlo: n = {v['n']}, seed {v['seed']} (fresh samples), "
              f"{result.rounds_run - 1} re-optimisation round(s)"
              + (" (the last found no feasible design)" if v.get("failed_reoptimisation")
                 else ""))
        for name, ch in v["after"]["constraints"].items():
            if ch["ci95"][1] is None:
                print(f"    constraint {name:<10} {ch['measure']} on the verification landings: "
                      f"not judged ({v['after']['n_ok']} landings; a 95 % interval needs "
                      f"{MIN_JUDGED})")
                continue
            if ch.get("judged_by") in ("violation bound", "violation count"):
                print(f"    constraint {name:<10} {ch['measure']} on the verification landings: "
                      f"{ch['verdict']}")
                continue
            print(f"    constraint {name:<10} {ch['measure']} on the verification landings: g "
                  f"{ch['g']:+.4f}, 95 % [{ch['ci95'][0]:+.4f}, {ch['ci95'][1]:+.4f}] "
                  f"({units[name]}): {'met' if ch['met'] else 'NOT MET'}")
        for tag in ("before", "after"):  # the baseline gear, then the design
            r = v[tag]
            label = f"{tag} ({'baseline' if tag == 'before' else 'design'})"
            if r["max_stroke_m"] is None:  # no successful landing: no percentile either
                print(f"    {label:<17} no successful landing")
                continue
            print(f"    {label:<17} peak accel p50 {r['peak_body_accel_mps2']['p50']:.4g} p99 "
                  f"{r['peak_body_accel_mps2']['p99']:.4g} m/s^2; max stroke p99 "
                  f"{r['max_stroke_m']['p99'] * 1e3:.4g} mm; "
                  + ("tip-over not modelled (quarter model)"
                     if r["tip_over"].get("modelled") is False
                     else f"P(tip) {probability_text(r['tip_over'])}") + "; P(bottom) "
                  f"{probability_text(r['bottoming'])}")
        continued = v["after"]["continued"]
        if continued:
            print(f"  note: {continued[0]['n']} of the {v['after']['n']} verification landings "
                  f"still in their impact or able to tip over at t_end_s = "
                  f"{spec.montecarlo.t_end:g} s were run on to "
                  + ", then ".join(f"{c['t_end_s']:g} s ({c['n_unfinished_after']} left)"
                                   for c in continued)
                  + (": judged on their final outcomes" if not continued[-1]["n_unfinished_after"]
                     else ": those left have no final outcome, and the verification is not met"),
                  file=sys.stderr)
        check = v["after"].get("t_end_check")
        if check and check.get("n_changed"):
            print("  note: the t_end check of the design's verification: " + _t_end_check_text(
                {"t_end_s": spec.montecarlo.t_end, "t_end_check": check})
                + f" (montecarlo.t_end_s); the constraints judged the checked landings on "
                f"their outcomes at {check['t_end_s']:g} s", file=sys.stderr)
    if result.status != "feasible":
        for name, c in result.violated.items():
            print(f"jaxland design: INFEASIBLE: constraint {name} violated, g = {c['g']:+.4g} "
                  f"({units[name]}; {c['rule']})", file=sys.stderr)
        print(f"wrote {out}/design_report.json" + ("" if args.no_plots else ", figures/*.png")
              + (", verification/{before,after}/" if result.mc_after is not None else "")
              + " (no design_vehicle.toml: no feasible design)")
        return EXIT_INFEASIBLE
    print(f"wrote {out}/design_vehicle.toml, design_report.json"
          + ("" if args.no_plots else ", figures/*.png")
          + (", verification/{before,after}/" if result.mc_after is not None else ""))
    if result.verification and not result.verification["verified"]:
        print(f"jaxland design: NOT VERIFIED: {result.verification['reason']}",
              file=sys.stderr)
        return EXIT_UNVERIFIED
    return 0


def add_subcommands(subparsers) -> None:
    """Register ``design`` on an argparse subparsers object."""
    d = subparsers.add_parser(
        "design", help="robust gradient-based gear design: cut peak overload under stroke, "
                       "stability and slip constraints over dispersed touchdowns")
    d.add_argument("spec", help="design spec TOML ([design], [objective], [variables.*], "
                                "[constraints.*], Monte Carlo dispersion)")
    d.add_argument("--out", default="out/design", help="output folder (default out/design)")
    d.add_argument("--iterations", type=int, help="optimiser iterations (overrides the spec)")
    d.add_argument("--verify-n", type=int,
                   help="verification Monte Carlo size (overrides montecarlo.n; 0: skip)")
    d.add_argument("--config", help="baseline vehicle TOML (default: design.vehicle or the "
                                    "paper's vehicle)")
    d.add_argument("--no-plots", action="store_true", help="skip the figures")
    d.add_argument("--quiet", action="store_true", help="no per-iteration progress lines")
    d.add_argument("--devices", type=int, default=None,
                   help="CPU devices the design scenes and the verification Monte Carlo are "
                        "split over (default: one per core; the optimiser's path depends on "
                        "the count through rounding)")
    d.set_defaults(func=_cmd_design)
