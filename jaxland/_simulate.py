"""``simulate``: one landing from a scene and a vehicle, with outcomes and files.

``landing(vehicle, scene, solver)`` is the pure, jittable core (vmap it over scenes or vehicle
parameters, differentiate it). ``simulate(...)`` is the front door: it validates the inputs,
refuses a step above the stability limit, runs the compiled core, raises ``SimulationError`` on a
numerical failure, and returns a ``Landing`` with numpy arrays and a readable summary.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import __version__
from ._checks import as_number, at_most
from ._config import paper_vehicle, validate_vehicle, vehicle_fields
from ._errors import ConfigError, SimulationError
from ._files import atomic_write_csv, atomic_write_text, flat_columns, json_text
from ._models import MODELS, AbstractModel
from ._params import Vehicle
from ._scene import Scene, batch_axes, is_symmetric
from ._solvers import (
    CLOSURE_LIMIT,
    Impulse,
    Result,
    Solver,
    Tsit5,
    integrate,
    integrator,
    scene_force_bound,
    stable_step,
    step_limit_reached,
)
from ._solvers._base import MAX_STEPS, SAVE_DT_MIN
from ._solvers._tsit5 import step_cap

__all__ = ["landing", "landings", "simulate", "Landing", "impacts_from_events", "choose_model",
           "get_model"]


# Contact gaps shorter than this are foot chatter within one impact, not a new impact [s]. The
# paper drop's hops after the first impact last 6-10 ms; chatter within an impact is sub-ms.
IMPACT_GAP_S = 1e-3


def choose_model(scene: Scene) -> str:
    """The smallest model that represents ``scene`` exactly: ``"quarter"`` for a symmetric
    vertical drop (every scene of a batch), else ``"full"``. Needs concrete scene values."""
    try:
        return "quarter" if is_symmetric(scene) else "full"
    except jax.errors.TracerArrayConversionError:
        raise ConfigError("model", "auto", "cannot be chosen from traced scene values (inside "
                          "jit/vmap/grad); pass model='quarter' or model='full'") from None


def get_model(model: str | AbstractModel, scene: Scene | None = None) -> AbstractModel:
    """The model object for a name (``"auto"``: ``choose_model(scene)``), or the object itself."""
    if not isinstance(model, AbstractModel):
        if model == "auto" and scene is not None:
            model = choose_model(scene)
        if model not in MODELS:
            raise ConfigError("model", model, f"must be one of auto, {', '.join(MODELS)}")
        model = MODELS[model]
    if model.name == "quarter" and scene is not None and _asymmetric(scene):
        raise ConfigError("model", model.name, "the quarter model represents only symmetric "
                          "vertical drops; this scene needs model='full'")
    return model


def _asymmetric(scene: Scene) -> bool:
    """``scene`` is concrete and not a symmetric vertical drop (``is_symmetric``); a traced
    scene (inside jit or vmap) cannot be checked here and passes."""
    try:
        return not is_symmetric(scene)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return False


def landing(vehicle: Vehicle, scene: Scene, solver: Solver = Solver(),
            model: str | AbstractModel = "auto"):
    """Pure landing: ``(trajectory, summary)`` dicts of jnp arrays. ``model`` is ``"quarter"``,
    ``"full"``, a model object, or ``"auto"`` (``choose_model``; needs a concrete scene, so
    under jit name it). The summary's ``result`` is a ``Result`` code, ``OUTSIDE_ENVELOPE`` for
    a scene outside the documented envelope (``Scene.inside_envelope``). Each concrete value of
    the vehicle is checked first against its own rule (``validate_vehicle(fields_only=True)``:
    a ``ConfigError`` names the one refused); a traced one (inside jit, vmap or grad) outside
    its rule, or a honeycomb whose stages are out of order, gives ``INVALID_VEHICLE``, with
    NaN derivatives (``follows_rules``). The other rules between fields are ``simulate``'s and
    the loaders': a fit's crush-peak forms may bend them on purpose."""
    scene.check_one().check_shapes(vehicle.n_legs)
    return integrate(get_model(model, scene), validate_vehicle(vehicle, fields_only=True),
                     scene, solver)


def landings(vehicle: Vehicle, scenes: Scene, solver: Solver = Solver(),
             model: str | AbstractModel = "auto"):
    """``landing`` vmapped over a ``Scene.batch``: every output gains a leading batch axis.
    Only the batched fields are mapped; the rest stay constants of the compiled loop."""
    scenes.check_shapes(vehicle.n_legs)  # by value, before the vmap traces them
    axes = batch_axes(scenes)
    if not jax.tree.leaves(axes):
        raise ConfigError("scenes", "<one scene>", "must be a batch (jaxland.Scene.batch); "
                          "for one scene use jaxland.landing")
    model = get_model(model, scenes)
    return jax.vmap(lambda s: landing(vehicle, s, solver, model),
                    in_axes=(axes,))(scenes)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _landing_jit(vehicle, scene, solver, model):
    return landing(vehicle, scene, solver, model)


def effective_vehicle(vehicle: Vehicle, scene: Scene) -> tuple[Vehicle, str | None]:
    """The vehicle as ``scene`` ran it, as one configuration: the scene's friction, mass scale
    and a plateau scale shared by every leg applied. A per-leg plateau scatter has no
    single-leg form: it stays in the scene, and the note returned says so."""
    note = None
    if scene.plateau_scale is not None and not is_symmetric(
            Scene(plateau_scale=scene.plateau_scale)):
        scene = eqx.tree_at(lambda s: s.plateau_scale, scene, None,
                            is_leaf=lambda x: x is None)
        note = ("per-leg honeycomb scatter (the scene's plateau_scale) scales F1_N and F2_N "
                "of each leg; the values below are before that scatter")
    return MODELS["quarter"].apply_scene(vehicle, scene), note


def impacts_from_events(event_times, n_changes, gap=IMPACT_GAP_S):
    """Group contact on/off times into impacts: a contact gap shorter than ``gap`` [s] is foot
    chatter inside one impact. Returns a list of (start_s, end_s or None if still in contact)."""
    n = int(min(n_changes, len(event_times)))
    times = [float(t) for t in event_times[:n]]
    spans = []
    for i in range(0, n, 2):
        start = times[i]
        end = times[i + 1] if i + 1 < n else None
        spans.append([start, end])
    merged = []
    for start, end in spans:
        if merged and merged[-1][1] is not None and start - merged[-1][1] < gap:
            merged[-1][1] = end
        else:
            merged.append([start, end])
    return [(s, e) for s, e in merged]


@dataclass
class Landing:
    """Result of ``simulate``: trajectory (numpy arrays, units in the names) and outcomes."""

    trajectory: dict
    outcomes: dict
    vehicle: Vehicle = field(repr=False)
    scene: Scene = field(repr=False)
    solver: Solver = field(repr=False)

    def to_csv(self, path) -> Path:
        """Write the trajectory as CSV (header: column names with units). Atomic."""
        return atomic_write_csv(Path(path), flat_columns(self.trajectory))

    def to_json(self, path) -> Path:
        """Write the outcomes as JSON. Atomic."""
        return atomic_write_text(Path(path), json_text(self.outcomes))


def _py(x):
    x = np.asarray(x)
    return x.item() if x.ndim == 0 else x.tolist()


def _touchdown_speed(scene: Scene, g: float, t_contact: float | None) -> float | None:
    """Vertical speed [m/s] of the body at first contact. The attitude held (no body rate):
    ``Scene.touchdown_speed``. A turning body lowers a foot sooner or later than that, but its
    centre of mass still falls freely, so its speed is v0 + g t at the first contact the run
    logged (None without one)."""
    if not bool(scene.turning()):
        return float(scene.touchdown_speed(g))
    return None if t_contact is None else float(scene.sink_speed) + g * float(t_contact)


def _outcomes(summary: dict, traj: dict, vehicle: Vehicle, scene: Scene, solver: Solver,
              model: str) -> dict:
    s = {k: np.asarray(v) for k, v in summary.items()}
    impacts = impacts_from_events(s["event_times_s"], s["n_contact_changes"])
    hc = vehicle.honeycomb
    t = traj["time_s"]
    first_end = impacts[0][1] if impacts and impacts[0][1] is not None else None
    stroke = np.asarray(traj["stroke_m"])
    if not impacts:  # no touchdown: no first impact to read
        stroke_first, foot_v = None, None
    elif first_end is not None and not np.any((t >= impacts[0][0]) & (t <= first_end)):
        # no saved sample inside the first impact (save_dt longer than it): nothing to read
        stroke_first, foot_v = None, None
    elif first_end is not None:
        i_end = min(int(np.searchsorted(t, first_end)), len(t) - 1)
        stroke_first = np.max(stroke[: i_end + 1], axis=0)
        foot_v = traj["foot_vz_mps"][max(i_end - 1, 0)] if "foot_vz_mps" in traj else None
    else:
        stroke_first = s["max_stroke_m"]
        foot_v = None
    max_stroke = np.max(s["max_stroke_m"])
    bottomed = bool(s["bottomed"])  # the landing's own flag (integrate)
    out = {
        "model": model,
        "drop_height_m": float(scene.drop_height),
        "sink_speed_mps": float(scene.sink_speed),
        "touchdown_speed_mps": _touchdown_speed(scene, float(vehicle.g),
                                                impacts[0][0] if impacts else None),
        "method": solver.method.name,
        "solver": {k: _py(v) for k, v in solver.method.options().items()},
        "save_dt_s": solver.save_dt,
        "smoothing": {"length_m": solver.smoothing_m, "force_N": solver.smoothing_N},
        "jaxland_version": __version__,
        "result": Result(int(s["result"])).name.lower(),
        "dt_s": solver.dt,
        "n_steps": int(s["n_steps"]),
        # the time reached: the run ends on its last whole save interval, which the request
        # need not be a multiple of
        "t_end_s": float(s["t_end_s"]),
        "t_end_requested_s": solver.t_end,
        "touchdown_time_s": impacts[0][0] if impacts else None,
        "impacts": [{"start_s": a, "end_s": b} for a, b in impacts],
        "n_impacts": len(impacts),
        "n_contact_changes": int(s["n_contact_changes"]),
        # the log keeps the first changes only (Solver.event_log): the impacts are listed from
        # these
        "n_contact_changes_logged": int(min(s["n_contact_changes"],
                                            s["event_times_s"].shape[-1])),
        "first_impact_stroke_m": None if stroke_first is None else _py(stroke_first),
        "secondary_honeycomb_engaged": bool(max_stroke > float(hc.x_L2)),
        "bottomed_out": bottomed,
    }
    if foot_v is not None or model == "quarter":
        out["foot_vz_end_first_impact_mps"] = None if foot_v is None else float(foot_v)
    skip = {"event_times_s", "n_contact_changes", "failed", "failure_time_s", "t_end_s",
            "peak_margin_deficit_m", "energy_scale_J", "tipped", "tip_over_time_s",
            "ledger_error_rel", "result"}
    for k, v in s.items():
        if k not in skip:
            out[k] = _py(v)
    if model == "full":
        out["min_stability_margin_m"] = -float(s["peak_margin_deficit_m"])
    out["legs_off_ground_at_end"] = _legs_off_ground(s)
    out["tipped_over"] = bool(s["tipped"])  # a symmetric vertical drop cannot tip
    out["tip_over_time_s"] = float(s["tip_over_time_s"]) if out["tipped_over"] else None
    code = int(s["result"])
    out["classification"] = ("no_touchdown" if code == Result.NO_TOUCHDOWN else
                             "tipped" if out["tipped_over"] else
                             "unfinished" if code == Result.UNFINISHED else
                             "bottomed_out" if bottomed else "stable")
    # the verdict's measure (CLOSURE_LIMIT judges it): relative to the energy dissipated, or
    # to a tenth of the energy scale where less is dissipated; none without a touchdown
    out["energy_closure_rel"] = (None if out["classification"] == "no_touchdown" else
                                 float(s["ledger_error_rel"]))
    return out


def _check_numerics(summary: dict, vehicle: Vehicle, solver: Solver, model: AbstractModel,
                    scene: Scene) -> None:
    """Refuse to return a landing whose answer is not to be used (``verdict``), saying why and
    what to change."""
    code = Result(int(summary["result"]))
    if not code.failed:
        return
    dt, method = solver.dt, solver.method
    name = method.name
    if code == Result.SOLVER_STOPPED:
        raise SimulationError(
            f"the adaptive solver ({name}) stopped at t = "
            f"{float(summary['failure_time_s']):.6g} s after "
            f"{int(summary['n_steps']) + int(summary['n_rejected_steps'])} steps "
            f"(max_steps = {method.max_steps} reached, or the step size collapsed at a "
            f"discontinuity); loosen rtol = {method.rtol:g} / atol = {method.atol:g}, raise "
            f"max_steps, or use a fixed-step method")
    hc_peak = float(np.max(summary["peak_honeycomb_force_N"]))
    n_peak = float(np.max(summary["peak_normal_force_N"]))
    bottomed = bool(summary["bottomed"])
    fixed = not isinstance(method, Tsit5)
    energy0 = float(summary["energy_initial_J"])
    if fixed and not math.isfinite(energy0):
        # no step helps: the numbers overflow from the start (a value's magnitude, not dt)
        why = (f"the landing's initial energy is {energy0:.4g} J, not a finite number: a "
               "configuration value too large for float64 arithmetic (check the vehicle's and "
               "the scene's magnitudes)")
        setting = f"{name} dt = {dt:.3g} s"
    elif fixed:
        reached = float(step_limit_reached(summary, vehicle, solver, model))
        if math.isfinite(reached):
            why = (f"this landing reached a honeycomb force of {hc_peak:.4g} N and a ground "
                   f"force of {n_peak:.4g} N{' and bottomed out' if bottomed else ''}, which "
                   f"limits dt to {reached:.3g} s for {name}; rerun with dt <= "
                   f"{STEP_SAFETY * reached:.2g} s")
        else:  # the blown-up state's peaks say nothing: the forces its energy can reach
            again = retry_step(vehicle, scene, method, model)
            why = (f"the forces it reached are not finite; those this scene's energy can reach "
                   f"limit dt for {name}: rerun with dt <= {again:.2g} s")
        setting = f"{name} dt = {dt:.3g} s"
    else:
        why = f"tighten rtol = {method.rtol:g} / atol = {method.atol:g}"
        setting = f"{name} rtol = {method.rtol:g}"
    if code in (Result.NONFINITE, Result.LEDGER):
        raise SimulationError(
            f"integration failed at t = {float(summary['failure_time_s']):.6g} s ("
            f"{code.message}) with {setting}; {why}")
    closure = float(summary["ledger_error_rel"])
    raise SimulationError(
        f"{setting} is too {'large' if fixed else 'loose'} for this landing (energy ledger "
        f"closure {closure:.2g} of the energy dissipated, limit {CLOSURE_LIMIT:g}): {why}")


DEFAULT_DT = 1e-5  # s, the accuracy default (docs/integrators.md: every output within 1e-4)
STEP_SAFETY = 0.5  # default step as a fraction of the stability limit, when that is smaller


def default_step(vehicle: Vehicle, method="euler", model: AbstractModel = MODELS["quarter"]):
    """The step ``simulate`` uses when none is given [s]: ``DEFAULT_DT``, or ``STEP_SAFETY``
    times the a-priori stability limit of ``method`` (an integrator or its name) for
    ``vehicle`` (its stiffest spring and damping on the foot) if that is smaller, rounded down
    to a whole fraction of ``SAVE_DT_MIN`` (1e-4 s) so the default output interval is a whole
    number of steps."""
    return _step_below(float(stable_step(vehicle, method=method, model=model)))


def retry_step(vehicle: Vehicle, scene: Scene, method="euler",
               model: AbstractModel = MODELS["quarter"]):
    """The step for a second try of a landing whose default step failed [s]: ``STEP_SAFETY``
    times the limit at the forces the scene's energy can reach (``scene_force_bound``: the
    bottoming stop and the strut damping it loads), rounded as ``default_step``'s."""
    force, bottomed = scene_force_bound(vehicle, scene, model)
    return _step_below(float(stable_step(vehicle, honeycomb_force=force, normal_force=force,
                                         bottomed=bottomed, method=method, model=model)))


def _step_below(limit: float) -> float:
    safe = STEP_SAFETY * limit
    if not safe > 0.0:  # the impulse step itself is beyond its limit: simulate says so
        return DEFAULT_DT
    return DEFAULT_DT if safe >= DEFAULT_DT else SAVE_DT_MIN / math.ceil(SAVE_DT_MIN / safe)


def refuse_unsteppable(vehicle: Vehicle, limit: float, t_end: float) -> None:
    """Refuse ``vehicle`` where its stability limit ``limit`` [s] (a float) would take a
    landing of ``t_end`` [s] more than ``MAX_STEPS`` steps at ``STEP_SAFETY`` times it: a
    step refused against such a limit is no mistake of the step's (``_refuse_stiffness``)."""
    if not t_end <= STEP_SAFETY * limit * MAX_STEPS:
        _refuse_stiffness(vehicle, limit, t_end)


def _refuse_stiffness(vehicle: Vehicle, limit: float, t_end: float) -> None:
    """Refuse a vehicle whose own stability limit ``limit`` [s] would take a landing of
    ``t_end`` more than ``MAX_STEPS`` steps at ``STEP_SAFETY`` times it, naming the stiffness
    (N/m) or mass (kg) furthest from the paper vehicle's (a stiffness of 1e30 N/m, a foot of
    1e-300 kg)."""
    usual = {(s, f.name): float(getattr(m, f.name)) for s, m, f in
             vehicle_fields(paper_vehicle()) if f.metadata["unit"] in ("N/m", "kg")}

    def off_by(section, mod, f) -> float:  # how many times stiffer, or lighter
        unit, val = f.metadata["unit"], np.asarray(getattr(mod, f.name), dtype=float)
        if unit == "N/m":
            return float(np.max(val)) / usual[section, f.name]
        return usual[section, f.name] / float(np.min(val)) if unit == "kg" else 0.0

    section, mod, f = max(vehicle_fields(vehicle), key=lambda t: off_by(*t))
    val = np.asarray(getattr(mod, f.name), dtype=float)
    value = float(np.max(val) if f.metadata["unit"] == "N/m" else np.min(val))
    steps = t_end / (STEP_SAFETY * limit) if limit > 0.0 else math.inf
    about = f"about {limit:.3g} s" if limit > 0.0 else "below the smallest number, 0 s"
    raise ConfigError(f"{section}.{f.metadata['toml']}", value, f"makes the vehicle's stable "
                      f"step {about}, so "
                      f"t_end = {t_end:g} s would take {steps:.3g} steps (at most "
                      f"{MAX_STEPS:.0e}): its stiffest spring on its lightest mass is no "
                      "gear's; check the vehicle's stiffnesses and masses")


def check_step(solver: Solver, vehicle: Vehicle, model: AbstractModel) -> None:
    """Refuse a step above the method's a-priori stability limit for this vehicle, naming it."""
    method = solver.method
    limit = float(stable_step(vehicle, method=method, model=model))
    if isinstance(method, Impulse) and limit <= 0.0:
        leg, chi = vehicle.leg, vehicle.ground.chi
        raise ConfigError("solver.impulse", method.dI, "must be below the stability "
                          f"limit 2 m2 / (D_b + chi) = "
                          f"{float(2 * vehicle.m_foot / (leg.D_b + chi)):.3g} N s")
    if solver.dt > limit:
        what = "its time-step cap" if isinstance(method, Impulse) else "dt"
        raise ConfigError("solver.dt", solver.dt, f"exceeds the stability limit {limit:.3g} s "
                          f"of {method.name} for this vehicle ({method.stability_reason}); use "
                          f"{what} <= {at_most(limit)} s")


def _check_save_interval(solver: Solver, given: float | None) -> None:
    """Refuse a ``save_dt`` the caller gave (``solver`` validated) that would run the landing
    a step or more past ``t_end``: a run ends on a whole save interval, and one that ``t_end``
    does not fill runs on to its end, where a touchdown or an impact after ``t_end`` changes
    the outcome."""
    if given is None:
        return
    reached = solver.n_steps * solver.dt
    if reached - solver.t_end >= solver.dt * (1.0 - 1e-6):
        raise ConfigError("solver.save_dt", given, "must divide t_end = "
                          f"{solver.t_end:g} s into whole intervals (it gives "
                          f"{solver.t_end / given:.6g}): a run ends on a whole save interval, "
                          f"and this one would run to {reached:g} s")


def simulate(scene: Scene | None = None, vehicle: Vehicle | None = None, *,
             dt: float | None = None, t_end: float = 1.2, save_dt: float | None = None,
             model: str = "auto", method="euler", **solver_options) -> Landing:
    """Simulate one landing of ``vehicle`` (default: the paper's) in ``scene`` (default: the
    paper's 0.2 m drop) with ``method`` (an integrator, ``jaxland.Euler()`` ..., or its name:
    "euler", "euler_implicit", "verlet", "leapfrog", "impulse", "tsit5") at step ``dt`` [s]
    for ``t_end`` [s], sampling the trajectory every ``save_dt`` [s] (default: the smallest
    multiple of dt that is at least 1e-4 s; one given must divide ``t_end`` to within a step,
    since a run ends on a whole save interval). ``solver_options`` are the named method's options
    (``impulse``, ``rtol``, ``atol``, ``max_steps``, ``adjoint``) and the switch smoothing
    (``smoothing_m``, ``smoothing_N``).

    ``dt=None`` chooses the step (``default_step``): 1e-5 s, the accuracy default, or the
    method's stability limit for this vehicle times ``STEP_SAFETY`` if that is smaller; if that
    landing fails numerically (a hard landing that bottoms out loads the explicit strut damping
    far beyond the a-priori forces), it is run once more at ``retry_step``, the limit at the
    forces the scene's energy can reach, and the outcomes say so (``retried_from_dt_s``).

    ``model`` is ``"auto"`` (the smallest exact model for the scene: ``choose_model``),
    ``"quarter"`` or ``"full"``. Raises ``ConfigError`` for invalid inputs or a step above the
    method's stability limit (stated in the message) and ``SimulationError`` if the
    integration blows up or an adaptive solver stalls.
    """
    # a concrete 0-d array (jnp.array(0.01)) is the number it holds
    dt, t_end, save_dt = (as_number(x) for x in (dt, t_end, save_dt))
    scene = Scene() if scene is None else scene
    for name, obj, cls in (("scene", scene, Scene), ("vehicle", vehicle, Vehicle)):
        if obj is not None and not isinstance(obj, cls):
            raise ConfigError(name, type(obj).__name__, f"must be a jaxland.{cls.__name__}")
    vehicle = paper_vehicle() if vehicle is None else validate_vehicle(vehicle)
    for section, mod, f in vehicle_fields(vehicle):  # one vehicle has one of each, per leg too
        val = getattr(mod, f.name)  # None: an extension left out; a table is a 1-D array
        table = bool(f.metadata.get("table"))
        if val is not None and jnp.ndim(val) != (1 if table else 0):
            raise ConfigError(f"{section}.{f.metadata['toml']}", jnp.shape(val),
                              ("must be one list of numbers (a table)" if table else
                               "must be one number") + ": simulate takes one vehicle (for a "
                              "batch, jax.vmap over jaxland.landing)")
    scene.validate(vehicle.n_legs)
    if jax.tree.leaves(batch_axes(scene)):  # some field is batched
        raise ConfigError("scene", "<batch>", "simulate takes one scene; for a batch use "
                          "jax.vmap over jaxland.landing (see Scene.batch)")
    mod = get_model(model, scene)  # refuses the quarter model for an asymmetric scene
    smoothing = {k: solver_options.pop(k) for k in ("smoothing_m", "smoothing_N")
                 if k in solver_options}
    method = integrator(method, **solver_options)  # options, before they are used
    method.check_model(mod)
    chosen = dt is None
    if chosen:
        dt = default_step(vehicle, method, mod)
    solver = Solver(dt=dt, t_end=t_end, save_dt=save_dt, method=method, **smoothing)
    solver.validate_values()
    solver.check_smoothing(vehicle)
    if isinstance(method, (Impulse, Tsit5)):
        # their steps follow the springs (tsit5's cap is 1/omega of the foot, the impulse's
        # cap is a spring limit): a vehicle whose springs leave no step is named, before an
        # impulse step beyond its own limit (check_step) or a stalled tsit5
        refuse_unsteppable(vehicle, float(stable_step(vehicle, method="verlet", model=mod)),
                           t_end)
    if not isinstance(method, Tsit5):
        limit = float(stable_step(vehicle, method=method, model=mod))
        if chosen and solver.n_steps > MAX_STEPS:
            _refuse_stiffness(vehicle, limit, t_end)
        # a vehicle no step can run is named before the step it makes too large
        if (chosen or solver.dt > limit) and not isinstance(method, Impulse):
            refuse_unsteppable(vehicle, limit, t_end)
        check_step(solver, vehicle, mod)
    solver.validate()
    if isinstance(method, Tsit5) and not chosen:
        cap = float(step_cap(mod, vehicle))
        if solver.dt > cap:  # its first step, and the default output interval's unit
            raise ConfigError("solver.dt", solver.dt, f"is tsit5's first step and must be <= "
                              f"its step cap {at_most(cap)} s (1/omega of the foot on its "
                              "stiffest springs)")
    _check_save_interval(solver, save_dt)
    traj, summary = _landing_jit(vehicle, scene, solver, mod)
    retried = None
    if chosen and Result(int(summary["result"])).failed and not isinstance(method, Tsit5):
        again = retry_step(vehicle, scene, method, mod)
        if save_dt is not None:  # a whole fraction of the output interval the user gave
            again = save_dt / math.ceil(save_dt / again - 1e-9)
        if again < solver.dt:
            retry = Solver(dt=again, t_end=t_end, save_dt=save_dt, method=method, **smoothing)
            try:
                retry.validate()
            except ConfigError:  # no run can take that step (too many steps, from a force
                retry = None  # bound past float64's range): the first failure is the answer
            if retry is not None:
                retried, solver = solver.dt, retry
                traj, summary = _landing_jit(vehicle, scene, solver, mod)
    traj = {k: np.asarray(traj[k]) for k in mod.COLUMNS}
    _check_numerics(summary, vehicle, solver, mod, scene)
    outcomes = _outcomes(summary, traj, vehicle, scene, solver, mod.name)
    if retried is not None:
        outcomes["retried_from_dt_s"] = retried
    if outcomes["tipped_over"]:
        outcomes["note"] = ("the vehicle tipped over; after tip_over_time_s the body, which has "
                            "no ground contact of its own, is not modelled physically, and "
                            "peaks and checks stop there")
    elif outcomes["classification"] == "no_touchdown":
        h, v = float(scene.drop_height), float(scene.sink_speed)
        fall = float(scene.fall_time(float(vehicle.g)))
        along = " (along the slope's normal)" if float(scene.slope) != 0.0 else ""
        outcomes["note"] = (f"{Result.NO_TOUCHDOWN.message} = {solver.t_end:g} s: the outcomes "
                            f"are the free fall's; the fall from a clearance of {h:g} m"
                            f"{along} at {v:g} m/s takes {fall:.3g} s, so raise t_end")
    elif outcomes["classification"] == "unfinished":
        outcomes["note"] = f"{Result.UNFINISHED.message}; rerun with a longer t_end"
    elif outcomes["legs_off_ground_at_end"]:
        legs = ", ".join(str(i) for i in outcomes["legs_off_ground_at_end"])
        outcomes["note"] = (f"at t_end leg(s) {legs} had left the ground after touching it: the "
                            "landing still moves and comes down again, so its max stroke and "
                            "peaks are those up to t_end, not final; a longer t_end shows "
                            "whether they grow")
    return Landing(traj, outcomes, vehicle, scene, solver)


def _legs_off_ground(summary: dict) -> list[int] | None:
    """The legs (numbered from 0, as the per-leg columns) that touched the ground and are off
    it at t_end: a foot in the air on a rebound or a rocking vehicle lands again and can crush
    further, which ``UNFINISHED`` (a leg still compressing) does not see. None without a
    touchdown."""
    if int(summary["n_contact_changes"]) == 0:
        return None
    touched = np.atleast_1d(np.asarray(summary["peak_normal_force_N"])) > 0.0
    off = np.atleast_1d(np.asarray(summary["final_normal_force_N"])) <= 0.0
    return np.flatnonzero(touched & off).tolist()
