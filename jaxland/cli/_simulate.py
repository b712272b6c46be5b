"""``jaxland simulate`` and ``jaxland config``."""

from __future__ import annotations

import sys

from .._checks import named_as
from .._errors import ConfigError
from .._files import staged
from .._solvers import CLOSURE_LIMIT
from ._common import fmt as _fmt, out_dir


def cmd_config(args) -> int:
    from .._config import load_vehicle, vehicle_to_toml

    if not args.config:
        sys.stdout.write(vehicle_to_toml())
        return 0
    from .._toml import read_toml

    given = {f"{section}.{key}" for section, table in read_toml(args.config, "--config").items()
             if isinstance(table, dict) for key in table}
    sys.stdout.write(vehicle_to_toml(load_vehicle(args.config, "--config"), given=given,
                                     given_by=args.config))
    return 0


def _print_summary(o: dict) -> None:
    # the quarter model carries a quarter of the body on one leg: its energies are that share
    share = " (one leg's share)" if o["model"] == "quarter" else ""
    rows = [
        ("touchdown", _fmt(o["touchdown_time_s"], 1, "s")),
        ("impacts (start-end, s)", ", ".join(
            f"{i['start_s']:.3f}-{'end' if i['end_s'] is None else format(i['end_s'], '.3f')}"
            for i in o["impacts"][:5]) + (" ..." if o["n_impacts"] > 5 else "")
         + ("" if o["n_contact_changes_logged"] == o["n_contact_changes"] else
            f" (listed: {o['n_impacts']}, from the first {o['n_contact_changes_logged']} of "
            f"{o['n_contact_changes']} contact changes; later impacts are not listed)")),
        ("first-impact stroke", _fmt(o["first_impact_stroke_m"], 1e3, "mm")),
        ("max stroke", _fmt(o["max_stroke_m"], 1e3, "mm")),
        ("final stroke", _fmt(o["final_stroke_m"], 1e3, "mm")),
        ("secondary honeycomb engaged", str(o["secondary_honeycomb_engaged"])),
        # also where the outcome names another class first (tipped, unfinished): a bottoming
        # stays whatever the landing does after it
        ("bottomed out (stroke past x_L4)", str(o["bottomed_out"])),
        ("outcome", o["classification"]),
        ("peak ground normal force", _fmt(o["peak_normal_force_N"], 1e-3, "kN")),
        ("peak ground tangential force", _fmt(o["peak_tangential_force_N"], 1e-3, "kN")),
        ("peak strut (buffer) force", _fmt(o["peak_strut_force_N"], 1e-3, "kN")),
        ("peak buffer velocity", _fmt(o["peak_buffer_velocity_mps"], 1, "m/s")),
        ("peak body acceleration", _fmt(o["peak_body_accel_mps2"], 1, "m/s^2")),
        ("peak foot acceleration", _fmt(o["peak_foot_accel_mps2"], 1, "m/s^2")),
        ("foot slip distance", _fmt(o["slip_distance_m"], 1e3, "mm")),
        ("energy dissipated" + share, _fmt(o["energy_dissipated_J"], 1, "J")),
        ("energy ledger closure" + share, f"{o['energy_closure_max_J']:.3g} J "
                                  + ("(nothing dissipated: no touchdown)"
                                     if o["energy_closure_rel"] is None else
                                     f"({o['energy_closure_rel']:.2e} relative, limit "
                                     f"{CLOSURE_LIMIT:g})")),
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


def _scene_from_args(args, n_legs: int):
    """The scene of --scene and the scene flags, checked against the vehicle's ``n_legs`` (a
    per-leg value), a value of the file named by the file."""
    from .._scene import read_scene_table

    table = read_scene_table(args.scene, "--scene") if args.scene else {}
    from_file = set(table)
    for flag, key in _SCENE_FLAGS:
        val = getattr(args, flag)
        if val is not None:
            table[key] = val
            from_file.discard(key)
    if args.touchdown_speed is not None:
        from_file -= {"drop_height_m", "sink_speed_mps"}
    try:
        return _scene_of(args, table).validate(n_legs)
    except ConfigError as err:  # a value of the file, named by the file (a flag's: by the flag)
        key = err.field.removeprefix("scene.")
        if key in from_file and err.field != key:
            raise ConfigError(f"--scene {args.scene}: {err.field}", err.value, err.rule) from None
        raise


def _scene_of(args, table):
    """The scene of ``table`` (the scene file's keys, the flags' over them) and
    --touchdown-speed."""
    from .._scene import scene_from_dict

    if args.touchdown_speed is not None:
        if args.drop_height is not None or args.sink_speed is not None:
            raise ConfigError("--touchdown-speed", args.touchdown_speed,
                              "give either --touchdown-speed or --drop-height/--sink-speed")
        table["drop_height_m"], table["sink_speed_mps"] = 0.0, args.touchdown_speed
        try:
            return scene_from_dict(table)
        except ConfigError as err:  # the flag the user gave, not the field it set
            if err.field == "scene.sink_speed_mps":
                raise ConfigError("--touchdown-speed", args.touchdown_speed, err.rule) from None
            raise
    return scene_from_dict(table)


def _given_flags(args) -> dict:
    """The fields the command line set -> (flag, value as typed), for named_as."""
    flags = {f"scene.{key}": (f"--{flag.replace('_', '-')}", getattr(args, flag))
             for flag, key in _SCENE_FLAGS if getattr(args, flag) is not None}
    for name in ("dt", "t_end", "save_dt", "impulse", "rtol", "atol", "max_steps"):
        if getattr(args, name) is not None:
            flags[f"solver.{name}"] = (f"--{name.replace('_', '-')}", getattr(args, name))
    flags["model"] = ("--model", args.model)
    return flags


def cmd_simulate(args) -> int:
    from .._config import load_vehicle, named_by_file, paper_vehicle, vehicle_to_toml
    from .._scene import scene_to_toml
    from .._simulate import effective_vehicle, simulate

    out = out_dir(args.out, (args.config, args.scene), "simulate")
    vehicle = load_vehicle(args.config, "--config") if args.config else paper_vehicle()
    options = {k: getattr(args, k) for k in ("impulse", "rtol", "atol", "max_steps")
               if getattr(args, k) is not None}
    with named_as(_given_flags(args)), named_by_file(args.config and "--config", args.config):
        scene = _scene_from_args(args, vehicle.n_legs)
        result = simulate(scene, vehicle, dt=args.dt, t_end=args.t_end, save_dt=args.save_dt,
                          model=args.model, method=args.method, **options)
    model = result.outcomes["model"]
    effective, note = effective_vehicle(vehicle, scene)
    with staged(out, "simulate") as staging:  # replaces out as a whole, only if all succeed
        result.to_csv(staging / "trajectory.csv")
        result.to_json(staging / "summary.json")
        (staging / "scene.toml").write_text(scene_to_toml(scene))
        # vehicle.toml and scene.toml are the run's inputs: fed back (--config, --scene) they
        # rerun it. The scene's friction, mass and plateau scales act on the vehicle, so the
        # vehicle with them applied is written apart: beside scene.toml they would apply twice.
        given = args.config or "the paper's vehicle"
        (staging / "vehicle.toml").write_text(
            f"# the vehicle given ({given}), before the scene's friction, mass_scale and "
            "plateau_scale:\n# with scene.toml (--config vehicle.toml --scene scene.toml) it "
            "reruns this landing\n" + vehicle_to_toml(
                vehicle, changed_by=f"GIVEN BY --config {args.config}" if args.config else None))
        (staging / "effective_vehicle.toml").write_text(
            "# the vehicle as the landing ran it: vehicle.toml with scene.toml's friction, "
            "mass_scale and plateau_scale\n# applied. For reading: beside scene.toml, which "
            "applies them again, it runs another landing\n"
            + (f"# {note}\n" if note else "") + vehicle_to_toml(
                effective, changed_by="APPLIED BY THE SCENE (friction, mass_scale or "
                "plateau_scale)", base=vehicle))
        if not args.no_plots:
            if model == "quarter":
                from .._plots import plot_landing

                hc = effective.honeycomb  # x_L1 = F1 / k_b1 moves with the plateau scale
                bps = {f"x_L{i}": float(getattr(hc, f"x_L{i}")) for i in (1, 2, 3, 4)}
                plot_landing(result.trajectory, result.outcomes, staging / "figures",
                             breakpoints_m=bps)
            else:
                from .._plots import plot_landing_3d

                plot_landing_3d(result.trajectory, result.outcomes, staging / "figures",
                                vehicle=vehicle, scene=scene)
    print(f"jaxland simulate: {model} model, drop {float(scene.drop_height):g} m, "
          f"sink {float(scene.sink_speed):g} m/s, {result.solver.method.name} dt "
          f"{result.solver.dt:g} s, {result.outcomes['t_end_s']:g} s")
    # the run's planned end (whole save intervals), not the time summed step by step, which
    # drifts by rounding over many steps
    planned = result.solver.n_steps * result.solver.dt
    if abs(planned - args.t_end) > 0.5 * result.solver.dt:
        print(f"  note: ran to {planned:g} s, not {args.t_end:g} s: a run ends on a whole save "
              f"interval ({result.solver.save_dt:g} s); give a t_end that is a multiple of it",
              file=sys.stderr)
    _print_summary(result.outcomes)
    if "retried_from_dt_s" in result.outcomes:
        print(f"  note: the landing failed numerically at the default step "
              f"{result.outcomes['retried_from_dt_s']:g} s and ran again at "
              f"{result.solver.dt:g} s: half the stability limit at the largest forces this "
              "scene's energy can reach, a bound that can lie far below the step the landing "
              "needs (--dt runs it at one you choose, and a failure names the step it needs)",
              file=sys.stderr)
    if "note" in result.outcomes:
        print(f"  note: {result.outcomes['note']}", file=sys.stderr)
    print(f"wrote {out}/trajectory.csv, summary.json, scene.toml, vehicle.toml, "
          "effective_vehicle.toml"
          + ("" if args.no_plots else ", figures/*.png"))
    return 0


