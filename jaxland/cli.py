"""The ``jaxland`` command: ``config``, ``simulate``, ``montecarlo``, ``fit``, ``predict``,
``design``. (The benchmarks are scripts in the repository's ``benchmarks/`` folder, not part
of the installed package.)

Exit codes: 0 success, 2 invalid input (the message names field, value and rule), 3 numerical
failure of the integration.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._errors import ConfigError, SimulationError
from ._files import staged
from ._solvers import METHODS


def _cmd_config(args) -> int:
    from ._config import load_vehicle, vehicle_to_toml

    veh = load_vehicle(args.config) if args.config else None
    sys.stdout.write(vehicle_to_toml(veh))
    return 0


def _fmt(v, scale=1.0, unit="", nd=4):
    """A value, or a per-leg list of values, scaled and with its unit."""
    if v is None:
        return "-"
    if isinstance(v, list):
        return (" / ".join(f"{x * scale:.{nd}g}" for x in v) + f" {unit}  (per leg)").strip()
    return f"{v * scale:.{nd}g} {unit}".strip()


def _print_summary(o: dict) -> None:
    rows = [
        ("touchdown", _fmt(o["touchdown_time_s"], 1, "s")),
        ("impacts (start-end, s)", ", ".join(
            f"{i['start_s']:.3f}-{'end' if i['end_s'] is None else format(i['end_s'], '.3f')}"
            for i in o["impacts"][:5]) + (" ..." if o["n_impacts"] > 5 else "")),
        ("first-impact stroke", _fmt(o["first_impact_stroke_m"], 1e3, "mm")),
        ("max stroke", _fmt(o["max_stroke_m"], 1e3, "mm")),
        ("final stroke", _fmt(o["final_stroke_m"], 1e3, "mm")),
        ("secondary honeycomb engaged", str(o["secondary_honeycomb_engaged"])),
        ("outcome", o["classification"]),
        ("peak ground normal force", _fmt(o["peak_normal_force_N"], 1e-3, "kN")),
        ("peak ground tangential force", _fmt(o["peak_tangential_force_N"], 1e-3, "kN")),
        ("peak strut (buffer) force", _fmt(o["peak_strut_force_N"], 1e-3, "kN")),
        ("peak buffer velocity", _fmt(o["peak_buffer_velocity_mps"], 1, "m/s")),
        ("peak body acceleration", _fmt(o["peak_body_accel_mps2"], 1, "m/s^2")),
        ("peak foot acceleration", _fmt(o["peak_foot_accel_mps2"], 1, "m/s^2")),
        ("foot slip distance", _fmt(o["slip_distance_m"], 1e3, "mm")),
        ("energy dissipated", _fmt(o["energy_dissipated_J"], 1, "J")),
        ("energy ledger closure", f"{o['energy_closure_max_J']:.3g} J "
                                  f"({o['energy_closure_rel']:.2e} of dissipated)"),
    ]
    width = max(len(r[0]) for r in rows)
    for name, val in rows:
        print(f"  {name:<{width}}  {val}")


_SCENE_FLAGS = (  # CLI flag -> scene TOML key (units in the names)
    ("drop_height", "drop_height_m"), ("sink_speed", "sink_speed_mps"),
    ("horizontal_speed", "horizontal_speed_mps"), ("heading_deg", "heading_deg"),
    ("roll_deg", "roll_deg"), ("pitch_deg", "pitch_deg"), ("yaw_deg", "yaw_deg"),
    ("roll_rate_degps", "roll_rate_degps"), ("pitch_rate_degps", "pitch_rate_degps"),
    ("yaw_rate_degps", "yaw_rate_degps"), ("slope_deg", "slope_deg"),
    ("slope_direction_deg", "slope_direction_deg"), ("friction", "friction"),
    ("plateau_scale", "plateau_scale"),
)


def _scene_from_args(args):
    from ._scene import scene_from_dict
    from ._toml import read_toml

    table = {}
    if args.scene:
        data = read_toml(args.scene, "--scene")
        table = dict(data.get("scene", data))
    for flag, key in _SCENE_FLAGS:
        val = getattr(args, flag)
        if val is not None:
            table[key] = val
    if args.touchdown_speed is not None:
        if args.drop_height is not None or args.sink_speed is not None:
            raise ConfigError("--touchdown-speed", args.touchdown_speed,
                              "give either --touchdown-speed or --drop-height/--sink-speed")
        table["drop_height_m"], table["sink_speed_mps"] = 0.0, args.touchdown_speed
    return scene_from_dict(table)


def _cmd_simulate(args) -> int:
    from ._config import load_vehicle, paper_vehicle, vehicle_to_toml
    from ._simulate import simulate

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ConfigError("--out", str(out), "exists and is not a folder")
    vehicle = load_vehicle(args.config) if args.config else paper_vehicle()
    scene = _scene_from_args(args)
    options = {k: getattr(args, k) for k in ("impulse", "rtol", "atol", "max_steps")
               if getattr(args, k) is not None}
    result = simulate(scene, vehicle, dt=args.dt, t_end=args.t_end, save_dt=args.save_dt,
                      model=args.model, method=args.method, **options)
    model = result.outcomes["model"]
    with staged(out) as staging:  # written into place only if all succeed
        result.to_csv(staging / "trajectory.csv")
        result.to_json(staging / "summary.json")
        (staging / "vehicle.toml").write_text(vehicle_to_toml(vehicle))
        if not args.no_plots:
            if model == "quarter":
                from ._plots import plot_landing

                hc = vehicle.honeycomb
                bps = {f"x_L{i}": float(getattr(hc, f"x_L{i}")) for i in (1, 2, 3, 4)}
                plot_landing(result.trajectory, result.outcomes, staging / "figures",
                             breakpoints_m=bps)
            else:
                from ._plots3d import plot_landing_3d

                plot_landing_3d(result.trajectory, result.outcomes, staging / "figures",
                                vehicle=vehicle, scene=scene)
    print(f"jaxland simulate: {model} model, drop {float(scene.drop_height):g} m, "
          f"sink {float(scene.sink_speed):g} m/s, {result.solver.method.name} dt "
          f"{result.solver.dt:g} s, {args.t_end:g} s")
    _print_summary(result.outcomes)
    print(f"wrote {out}/trajectory.csv, summary.json, vehicle.toml"
          + ("" if args.no_plots else ", figures/*.png"))
    return 0


def _cmd_montecarlo(args) -> int:
    from ._config import load_vehicle, paper_vehicle
    from ._montecarlo import load_montecarlo_spec, run_montecarlo

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ConfigError("--out", str(out), "exists and is not a folder")
    spec = load_montecarlo_spec(args.spec)
    if args.n is not None:
        spec.n = args.n
    if args.seed is not None:
        spec.seed = args.seed
    spec.__post_init__()  # re-check n and seed after the overrides
    vehicle = load_vehicle(args.config) if args.config else paper_vehicle()
    result = run_montecarlo(spec, vehicle, chunk=args.chunk)
    result.save(out)
    s = result.summary
    tip, bot = s["tip_over"], s["bottoming"]
    print(f"jaxland montecarlo: {s['n']} landings, {s['model']} model, {s['devices']} device(s),"
          f" {s['wall_s']:.1f} s ({s['landings_per_s']:.0f}/s)")
    failures = f"  {s['failures']}" if s["failures"] else ""
    print(f"  failed samples      {s['n_failed']}{failures}")
    print(f"  P(tip-over)         {tip['probability']:.4g}  95% CI [{tip['ci95_wilson'][0]:.4g}, "
          f"{tip['ci95_wilson'][1]:.4g}]  ({tip['count']}/{tip['n']})")
    print(f"  P(bottoming out)    {bot['probability']:.4g}  95% CI [{bot['ci95_wilson'][0]:.4g}, "
          f"{bot['ci95_wilson'][1]:.4g}]  ({bot['count']}/{bot['n']})")
    for name, env in s["envelopes"].items():
        if env:
            print(f"  {name:<30s} p50 {env['p50']:.4g}  p99 {env['p99']:.4g}  max {env['max']:.4g}")
    if s["sensitivity"]["ranking"]:
        top = ", ".join(f"{r['input']} ({r['effect_per_std']:+.3g})"
                        for r in s["sensitivity"]["ranking"][:3])
        print(f"  drivers of {s['sensitivity']['target']}: {top}")
    print(f"wrote {out}/samples.csv, samples.npz, summary.json, figures/*.png")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="jaxland", description="jaxland: landings of a legged vehicle on crushable "
        "honeycomb gear (quarter and full 3-D models), Monte Carlo, calibration, design.")
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("config", help="print the vehicle configuration (default: the paper's) "
                                      "as commented TOML")
    c.add_argument("--config", help="a vehicle TOML to validate and print in full")
    c.set_defaults(func=_cmd_config)

    s = sub.add_parser("simulate", help="simulate one landing, write CSV, summary and figures")
    s.add_argument("--config", help="vehicle TOML (default: the paper's vehicle)")
    s.add_argument("--scene", help="scene TOML ([scene] table, keys as the flags below with "
                                   "their units, e.g. roll_deg = 3); flags override it")
    s.add_argument("--model", default="auto", choices=("auto", "quarter", "full"),
                   help="auto (default): the smallest model that represents the scene exactly")
    s.add_argument("--drop-height", type=float,
                   help="clearance of the lowest foot at release [m] (default 0.2)")
    s.add_argument("--sink-speed", type=float, help="downward speed at release [m/s] (default 0)")
    s.add_argument("--touchdown-speed", type=float,
                   help="start at touchdown with this downward speed [m/s]")
    s.add_argument("--horizontal-speed", type=float, help="horizontal speed [m/s]")
    s.add_argument("--heading-deg", type=float, help="direction of the horizontal speed [deg]")
    for ax in ("roll", "pitch", "yaw"):
        s.add_argument(f"--{ax}-deg", type=float, help=f"body {ax} at release [deg]")
        s.add_argument(f"--{ax}-rate-degps", type=float, help=f"body {ax} rate [deg/s]")
    s.add_argument("--slope-deg", type=float, help="ground slope [deg]")
    s.add_argument("--slope-direction-deg", type=float, help="downhill direction [deg]")
    s.add_argument("--friction", type=float, help="foot-ground friction mu (overrides config)")
    s.add_argument("--plateau-scale", type=float, nargs="+",
                   help="honeycomb plateau-force scale per leg (scatter), one value per leg")
    s.add_argument("--method", default="euler", choices=METHODS,
                   help="integrator (default euler; see docs/integrators.md)")
    s.add_argument("--dt", type=float, default=None,
                   help="integration step [s] (default 1e-5, or half the method's stability "
                        "limit for this vehicle if smaller; impulse: the step cap; tsit5: the "
                        "first step)")
    s.add_argument("--impulse", type=float, help="impulse step dI of --method impulse [N s]")
    s.add_argument("--rtol", type=float, help="relative tolerance of --method tsit5")
    s.add_argument("--atol", type=float, help="absolute tolerance of --method tsit5")
    s.add_argument("--max-steps", type=int, help="step budget of --method tsit5")
    s.add_argument("--t-end", type=float, default=1.2, help="simulated time [s] (default 1.2)")
    s.add_argument("--save-dt", type=float, default=None,
                   help="output sample interval [s] (default max(1e-4, dt))")
    s.add_argument("--out", default="out/simulate", help="output folder (default out/simulate)")
    s.add_argument("--no-plots", action="store_true", help="skip the figures")
    s.set_defaults(func=_cmd_simulate)

    m = sub.add_parser("montecarlo", help="dispersed landings: tip-over and bottoming "
                                          "probabilities, envelopes, sensitivities")
    m.add_argument("spec", help="Monte Carlo spec TOML ([montecarlo], [dispersion.*], [fixed])")
    m.add_argument("--n", type=int, help="number of landings (overrides the spec)")
    m.add_argument("--seed", type=int, help="random seed (overrides the spec)")
    m.add_argument("--chunk", type=int, help="landings per compiled batch (bounds memory)")
    m.add_argument("--config", help="vehicle TOML (default: the paper's vehicle)")
    m.add_argument("--out", default="out/montecarlo", help="output folder")
    m.set_defaults(func=_cmd_montecarlo)

    # calibration (`fit`, `predict`) lives in its own package, built on jaxland's public API
    from calibration.cli import add_subcommands

    add_subcommands(sub)

    from ._design_cli import add_subcommands as add_design  # `design`: gear design

    add_design(sub)

    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ConfigError as err:
        print(f"jaxland: error: {err}", file=sys.stderr)
        return 2
    except SimulationError as err:
        print(f"jaxland: numerical failure: {err}", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
