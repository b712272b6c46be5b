"""The compiled robust design problem: design variables <-> unconstrained z, the fixed
scenes, and the measures with their Jacobian."""

from __future__ import annotations

import dataclasses
import itertools
import math
import statistics

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._config import paper_vehicle, validate_vehicle
from .._errors import ConfigError
from .._laws import safe_sqrt
from .._models import MODELS
from .._montecarlo import MonteCarloSpec
from .._montecarlo._sample import check_fixed, draw, scene_fields
from .._params import Vehicle
from .._scene import Scene
from .._simulate import landings, refuse_unsteppable
from .._solvers import Result, Solver, stable_step
from ._gear import apply_design, baseline_value, cells_force, check_cells, gear_mass_kg
from ._spec import (
    CELL_VARS,
    CONSTRAINTS,
    FORCE_VARS,
    ORDER_GAP_M,
    ORDER_RATIO,
    VARIABLES,
    DesignSpec,
    DesignVariable,
)

# the unconstrained coordinate of a bound: sigmoid(30) is 1 to 1e-13
BOX_Z = 30.0


def risk_measure(values, measure: str, level: float = 0.9):
    """A risk measure of per-scene values (larger = worse): ``mean``, ``max``, ``cvar`` at
    ``level``: the mean of the worst (1 - level) N values, the boundary sample weighted by its
    fraction (Rockafellar-Uryasev's CVaR of the empirical distribution), differentiable almost
    everywhere (through a sort); or ``normal`` at ``level``: mean + z std (sample std, N - 1),
    z = Phi^-1(level), the level-quantile of a normal with the scenes' mean and spread, smooth
    in every scene's value."""
    values = jnp.asarray(values)
    if measure == "mean":
        return jnp.mean(values)
    if measure == "max":
        return jnp.max(values)
    n = values.shape[0]
    if measure == "normal":
        z = statistics.NormalDist().inv_cdf(level)
        mean = jnp.mean(values)
        var = jnp.sum((values - mean) ** 2) / max(n - 1, 1)
        sd = safe_sqrt(var)  # its gradient stays finite for equal values
        return mean + z * sd
    tail = (1.0 - level) * n
    worst = -jnp.sort(-values)  # descending
    w = jnp.clip(tail - jnp.arange(n, dtype=values.dtype), 0.0, 1.0) / tail
    return jnp.sum(w * worst)


# A design scene's outcome is ill-conditioned in the design when its derivative along one
# unconstrained coordinate z exceeds this many times the scenes' median magnitude of that
# outcome: a well-posed outcome changes by a fraction of itself over a change of z that spans a
# good part of a variable's range (measured on the paper gear's 1 s scenes: at most 12), while
# a 3-D landing that rocks and slides after its impact amplifies any change exponentially in
# time (1e3 to 1e10 there for the max stroke and the stability margin of about a third of the
# scenes). Such a derivative is true but useless: it holds for changes too small to matter and
# would swamp the gradient of every measure that scene enters.
ILL_CONDITIONED = 100.0


def _ill_conditioned(values, tangents):
    """Per scene, whether ``tangents`` (d values / d z, one or more directions in the last
    axis) exceed ``ILL_CONDITIONED`` x the median |value|."""
    scale = jnp.median(jnp.abs(values))
    t = tangents if tangents.ndim == values.ndim else jnp.max(jnp.abs(tangents), axis=-1)
    return jnp.abs(t) > ILL_CONDITIONED * scale


@jax.custom_jvp
def guard_ill_conditioned(values):
    """``values`` (one per scene) unchanged; in a forward-mode derivative, the tangent of an
    ill-conditioned scene (``ILL_CONDITIONED``) is replaced by the median tangent of the
    well-conditioned scenes (zero if there are none): that scene's outcome then counts in
    every measure with its value, and moves with the design as a typical scene does."""
    return values


@guard_ill_conditioned.defjvp
def _guard_jvp(primals, tangents):
    (v,), (t,) = primals, tangents
    ill = _ill_conditioned(v, t)
    typical = jnp.nanmedian(jnp.where(ill, jnp.nan, t))
    typical = jnp.where(jnp.all(ill), 0.0, typical)  # all ill: nanmedian is nan, not used
    return v, jnp.where(ill, typical, t)




def check_bounds(spec: DesignSpec, vehicle: Vehicle) -> None:
    """Refuse bound boxes that could produce an invalid vehicle (the orderings the
    honeycomb and leg need) and constraints no design in the box can meet, naming the bound
    and the rule; before any work (``DesignProblem`` and the command call it)."""
    hc, leg = vehicle.honeycomb, vehicle.leg
    b = {v.name: (v.low * v.to_si, v.high * v.to_si) for v in spec.variables}
    typed = {v.name: {"low": v.low, "high": v.high} for v in spec.variables}  # as written

    def bound(name: str, end: str):
        """A refusal of ``variables.<name>.<end>`` for a rule, the value as the spec gives it."""
        return lambda rule: ConfigError(f"variables.{name}.{end}", typed[name][end], rule)
    x_l1 = float(hc.F1 / hc.k_b1)
    dx3 = float((hc.F2 - hc.F1) / hc.k_b3)
    if any(n in b for n in CELL_VARS):
        c = {n: (spec.cells[n] * 1e-3,) * 2 for n in CELL_VARS} | b
        f1_max = float(cells_force(c["primary_cell_size_mm"][0],
                                    c["primary_foil_thickness_mm"][1], spec.cells))
        f2_min = float(cells_force(c["secondary_cell_size_mm"][1],
                                    c["secondary_foil_thickness_mm"][0], spec.cells))
        if not f2_min > ORDER_RATIO * f1_max:
            # the first bound given of those that set the weakest F2 and the strongest F1
            name, end = next((n, e) for n, e in (
                ("secondary_cell_size_mm", "high"), ("secondary_foil_thickness_mm", "low"),
                ("primary_foil_thickness_mm", "high"), ("primary_cell_size_mm", "low"))
                if n in b)
            raise bound(name, end)(
                f"the cell bounds allow F2 = {f2_min:.4g} N <= {ORDER_RATIO} x F1 = "
                f"{ORDER_RATIO * f1_max:.4g} N; the secondary stage must be stronger than the "
                "primary over the whole box")
    else:
        f1_hi = b.get("F1_N", (float(hc.F1),) * 2)[1]
        f2_hi = b.get("F2_N", (float(hc.F2),) * 2)[1]
        if not f2_hi > ORDER_RATIO * f1_hi:
            raise bound("F2_N" if "F2_N" in b else "F1_N", "high")(
                f"F2 must be able to exceed {ORDER_RATIO} x F1 over the whole box: F2 max "
                f"{f2_hi:.4g} N vs F1 max {f1_hi:.4g} N")
    if "x_L2_mm" in b and b["x_L2_mm"][0] <= x_l1:
        raise bound("x_L2_mm", "low")(f"must exceed x_L1 = {x_l1 * 1e3:.4g} mm")
    x2_hi = b.get("x_L2_mm", (float(hc.x_L2),) * 2)[1]
    x4_hi = b.get("x_L4_mm", (float(hc.x_L4),) * 2)[1]
    if not x4_hi > x2_hi + dx3 + ORDER_GAP_M:
        raise bound("x_L4_mm" if "x_L4_mm" in b else "x_L2_mm", "high")(
            f"x_L4 must be able to exceed x_L2 + (x_L3 - x_L2) + 1 mm over the whole box "
            f"(x_L2 max {x2_hi * 1e3:.4g} mm, x_L4 max {x4_hi * 1e3:.4g} mm)")
    if x4_hi >= float(leg.L_h0) and "x_L4_mm" in b:
        raise bound("x_L4_mm", "high")(f"must be shorter than the main strut, L_h0 = "
                                       f"{float(leg.L_h0) * 1e3:.4g} mm")
    for c in spec.constraints:  # max stroke <= x_L4 - margin needs x_L4 > margin
        if c.name == "stroke" and not c.threshold < x4_hi:
            shown = float(f"{c.threshold * 1e3:.12g}")  # as written, not its round trip
            raise ConfigError("constraints.stroke.margin_mm", shown,
                              f"must be below the largest x_L4 the design can reach "
                              f"({x4_hi * 1e3:.4g} mm): no landing can keep its stroke "
                              "that far from bottoming out")
    if "theta_b_deg" in b:
        lo, hi = b["theta_b_deg"]
        if not (0 < lo and hi < math.pi / 2):
            raise ConfigError("variables.theta_b_deg", [typed["theta_b_deg"]["low"],
                                                        typed["theta_b_deg"]["high"]],
                              "must lie in (0, 90) deg")
        if not float(leg.L_h0) * math.sin(lo) > 1.05 * float(leg.H2):
            raise bound("theta_b_deg", "low")("L_h0 sin theta_b must exceed 1.05 H2 (the leg "
                                              "triangle degenerates)")
    if "R_m" in b and not b["R_m"][0] > 0:
        raise bound("R_m", "low")("must be > 0")
    for n in ("k_a_N_per_m", *FORCE_VARS, *CELL_VARS):
        if n in b and not b[n][0] > 0:
            raise bound(n, "low")("must be > 0")


class DesignProblem:
    """The compiled robust design problem: design variables <-> unconstrained ``z``, the fixed
    scenes, and ``evaluate(z)`` -> measures, their Jacobian and per-scene outcomes."""

    def __init__(self, spec: DesignSpec, vehicle: Vehicle | None = None,
                 added: tuple = ()):
        """``added``: landings joined to the design scenes, as ``(seed, indices)`` pairs of
        Monte Carlo samples of the spec's dispersion (the verification's violators)."""
        self.spec = spec
        self.added = tuple((int(seed), tuple(int(i) for i in idx)) for seed, idx in added)
        self.vehicle = paper_vehicle() if vehicle is None else validate_vehicle(vehicle)
        self.model = spec.resolved_model()
        # only the running maxima _per_scene reads (the always-kept forces and acceleration,
        # and the 3-D margin), no contact-time log and no trajectory (less to trace: the
        # Jacobian's program traces in about 0.7 of the time and compiles to the same program)
        self.solver = Solver(dt=spec.dt, t_end=spec.t_end, save_dt=spec.t_end,
                             method=spec.method, event_log=0, trajectory=False,
                             peaks=("peak_margin_deficit_m",) if self.model == "full" else ()
                             ).validate()
        self.variables = list(spec.variables)
        self.names = spec.names
        # the per-scene outcomes the measures read
        self.outcomes = ("peak_body_accel_mps2",
                         *dict.fromkeys(CONSTRAINTS[c.name].outcome for c in spec.constraints))
        self.cells = spec.cells
        mc = spec.montecarlo
        scene_spec = MonteCarloSpec(dispersion=mc.dispersion, fixed=mc.fixed, n=spec.n_scenes,
                                    seed=spec.scene_seed, dt=spec.dt, t_end=spec.t_end,
                                    model=self.model)
        self._scene_spec = scene_spec
        n_legs = self.vehicle.n_legs
        check_fixed(scene_spec, n_legs)
        draws = [draw(scene_spec, jnp.arange(spec.n_scenes), n_legs)]
        draws += [draw(dataclasses.replace(scene_spec, seed=seed), jnp.asarray(idx), n_legs)
                  for seed, idx in self.added]  # sample_scenes' draws, joined
        self.scene_inputs = {k: np.concatenate([np.asarray(d[k]) for d in draws])
                             for k in draws[0]}
        self.count = spec.n_scenes + sum(len(idx) for _, idx in self.added)
        try:
            self.scenes = Scene.batch(**scene_fields(scene_spec, self.scene_inputs, self.count,
                                                     n_legs))
            self.scenes.validate(self.vehicle.n_legs)
        except ConfigError as err:  # a drawn scene outside the envelope: name the dispersion
            key = err.field.removeprefix("scene.")
            if key not in mc.dispersion:
                raise
            raise ConfigError(f"dispersion.{key}", mc.dispersion[key].table(),
                              f"draws design scenes outside the scene envelope (one at "
                              f"{err.value}; {err.rule}): a design scene must be a landing; "
                              "keep the dispersion inside the envelope (truncnormal, uniform)"
                              ) from None
        check_bounds(spec, self.vehicle)
        check_cells(self.vehicle, spec.variables, self.cells)
        self._check_touchdown()
        self._stiffest: dict = {}  # per method: stiffest_step's answer
        self.z0 = self.to_z({v.name: (v.start * v.to_si if v.start is not None else
                                      baseline_value(self.vehicle, v.name, self.cells))
                             for v in self.variables}, check=True)
        self.check_step("design.dt_s", spec.dt, spec.method, spec.t_end)
        self._fn = jax.jit(self._measures)
        self._jac = jax.jit(self._measures_and_jac)
        # the scenes' devices: the optimiser's path depends on their count through rounding
        self.devices = min(len(jax.local_devices()), self.count)
        self._inputs = self._device_inputs()

    # --- variables
    def _bounds(self, vals: dict, v: DesignVariable):
        lo, hi = v.low * v.to_si, v.high * v.to_si
        hc = self.vehicle.honeycomb
        if v.name == "F2_N":  # coupled: F2 >= ORDER_RATIO F1
            lo = jnp.maximum(lo, ORDER_RATIO * vals.get("F1_N", hc.F1))
        elif v.name == "x_L4_mm":  # coupled: x_L4 >= x_L3 + gap
            dx3 = (hc.F2 - hc.F1) / hc.k_b3
            lo = jnp.maximum(lo, vals.get("x_L2_mm", hc.x_L2) + dx3 + ORDER_GAP_M)
        return lo, hi

    def from_z(self, z) -> dict:
        """Design values (SI) from the unconstrained coordinates, through the bounded smooth
        transforms (in declaration order, so coupled bounds see F1 and x_L2 first)."""
        vals: dict = {}
        order = sorted(range(len(self.variables)),
                       key=lambda i: self.variables[i].name in ("F2_N", "x_L4_mm"))
        for i in order:
            v = self.variables[i]
            lo, hi = self._bounds(vals, v)
            s = jax.nn.sigmoid(z[i])
            if v.scale == "log":
                vals[v.name] = jnp.exp(jnp.log(lo) + (jnp.log(hi) - jnp.log(lo)) * s)
            else:
                vals[v.name] = lo + (hi - lo) * s
        return vals

    def _check_touchdown(self) -> None:
        """Refuse, before any compilation, design scenes whose free fall outlasts
        design.t_end_s. Exact for a body that does not turn (``Scene.fall_time``); a turning
        one can lower a foot sooner, so its scenes are left to the first evaluation's check."""
        sc = self.scenes
        still = ~np.asarray(sc.turning())
        fall = np.asarray(sc.fall_time(float(self.vehicle.g)))
        late = still & (fall > self.spec.t_end)
        if np.any(late):
            raise ConfigError("design.t_end_s", self.spec.t_end,
                              f"{int(np.sum(late))} of {self.count} design scenes do not touch "
                              f"down within it (the first of them at {np.min(fall[late]):.3g} "
                              "s): raise it, or start the scenes nearer the ground "
                              "(drop_height_m)")

    def to_z(self, values: dict, check: bool = False) -> np.ndarray:
        """Unconstrained coordinates of design values (SI)."""
        z = np.zeros(len(self.variables))
        vals = {}
        order = sorted(range(len(self.variables)),
                       key=lambda i: self.variables[i].name in ("F2_N", "x_L4_mm"))
        for i in order:
            v = self.variables[i]
            lo, hi = (float(x) for x in self._bounds(vals, v))
            x = float(values[v.name])
            if v.scale == "log":
                frac = (math.log(x) - math.log(lo)) / (math.log(hi) - math.log(lo))
            else:
                frac = (x - lo) / (hi - lo)
            if check and not 1e-6 < frac < 1 - 1e-6:
                raise ConfigError(f"variables.{v.name}", x / v.to_si,
                                  f"the start (baseline) value must lie strictly inside the "
                                  f"bounds [{lo / v.to_si:.6g}, {hi / v.to_si:.6g}] "
                                  f"(give variables.{v.name}.start or widen the bounds)")
            frac = min(max(frac, 1e-12), 1 - 1e-12)
            z[i] = math.log(frac / (1 - frac))
            vals[v.name] = x
        return z

    def vehicle_at(self, z) -> Vehicle:
        return apply_design(self.vehicle, self.from_z(z), self.cells)

    def stiffest_step(self, method: str) -> tuple[float, dict]:
        """The smallest a-priori stable step [s] of ``method`` over the designs the bounds
        allow, and the bounds that set it (TOML units: the variables at that corner whose
        other bound gives a larger step). The stiffnesses and masses move monotonically with
        each variable, so the least stable design is a corner of the bounds: each corner's
        step is computed (2^variables of them)."""
        if method not in self._stiffest:
            k = len(self.variables)
            corners = np.array(list(itertools.product((-BOX_Z, BOX_Z), repeat=k)))
            steps = jax.jit(jax.vmap(lambda z: stable_step(
                self.vehicle_at(z), method=method, model=MODELS[self.model])))
            lim = np.asarray(steps(jnp.asarray(corners)))
            i = int(np.argmin(lim))
            flipped = np.repeat(corners[i][None], k, axis=0)
            flipped[np.arange(k), np.arange(k)] *= -1.0
            moves = np.asarray(steps(jnp.asarray(flipped))) > lim[i] * (1.0 + 1e-9)
            vals = self.from_z(jnp.asarray(corners[i]))
            self._stiffest[method] = (float(lim[i]), {
                n: float(vals[n]) / VARIABLES[n].to_si
                for j, n in enumerate(self.names) if moves[j]})
        return self._stiffest[method]

    def check_step(self, key: str, dt: float, method: str, t_end: float) -> None:
        """Refuse a step ``dt`` [s] (the TOML ``key``) above ``method``'s stability limit
        for any design inside the bounds: the optimiser may go anywhere inside them, and
        the verification runs the design it returns. Where the vehicle itself leaves no
        step that could run landings of ``t_end`` [s], its field is refused instead: no step
        and no bound would help."""
        limit, at = self.stiffest_step(method)
        if dt > limit:
            if at:  # bounds move the limit: is it the bounds, or the vehicle they start from?
                limit_of_vehicle = float(stable_step(self.vehicle, method=method,
                                                     model=MODELS[self.model]))
            else:
                limit_of_vehicle = limit
            refuse_unsteppable(self.vehicle, limit_of_vehicle, t_end)
            where = ("the stiffest design inside the bounds ("
                     + ", ".join(f"{n} = {v:.4g}" for n, v in at.items())
                     + "): lower it, or narrow the bounds" if at else
                     "every design inside the bounds (no variable moves it): lower it")
            raise ConfigError(key, dt, f"exceeds the stability limit {limit:.3g} s of "
                              f"{method} for {where}")

    # --- outcomes
    @property
    def _padded(self) -> int:
        """The scene count rounded up to a multiple of the devices."""
        return -(-self.count // self.devices) * self.devices

    def _device_inputs(self) -> dict:
        """The scenes' drawn inputs split over the local devices along the scenes: each device
        runs its share of the landings and their tangents, and the measures gather them.
        Padded to ``_padded`` with copies of the last scene, which ``_measures`` drops."""
        devices = jax.local_devices()[:self.devices]
        rows = np.minimum(np.arange(self._padded), self.count - 1)
        sharding = NamedSharding(Mesh(np.array(devices), ("scenes",)), PartitionSpec("scenes"))
        return jax.device_put({k: jnp.asarray(v[rows]) for k, v in self.scene_inputs.items()},
                              sharding)

    def scenes_of(self, inputs: dict) -> Scene:
        """The ``Scene.batch`` of the device inputs (traced or concrete) with the spec's fixed
        inputs."""
        return Scene.batch(**scene_fields(self._scene_spec, inputs, self._padded,
                                          self.vehicle.n_legs))

    def _per_scene(self, veh, scenes: Scene):
        model = MODELS[self.model]
        _, s = landings(veh, scenes, self.solver, model)
        legmax = model.leg_max

        out = dict(peak_body_accel_mps2=s["peak_body_accel_mps2"],
                   max_stroke_m=legmax(s["max_stroke_m"]),
                   slip_distance_m=legmax(s["slip_distance_m"]),
                   peak_honeycomb_force_N=legmax(s["peak_honeycomb_force_N"]),
                   # an UNFINISHED scene (still in its impact at t_end) keeps its numbers, as
                   # a landing record does; the summaries count it (raise design.t_end_s)
                   failed=((s["result"] != int(Result.SUCCESSFUL))
                           & (s["result"] != int(Result.UNFINISHED))),
                   unfinished=s["result"] == int(Result.UNFINISHED),
                   no_touchdown=s["result"] == int(Result.NO_TOUCHDOWN),
                   tipped=s["tipped"])
        if "peak_margin_deficit_m" in s:
            out["min_stability_margin_m"] = -s["peak_margin_deficit_m"]
        return out

    def _measures(self, z, inputs: dict):
        """(measures [objective measure, gear mass, g_1..g_m], per-scene outcomes) over the
        scenes of the drawn ``inputs`` (``_device_inputs``: the padding dropped here)."""
        veh = self.vehicle_at(z)
        per = {k: v[:self.count]
               for k, v in self._per_scene(veh, self.scenes_of(inputs)).items()}
        guarded = dict(per, **{k: guard_ill_conditioned(per[k]) for k in self.outcomes})
        ob = self.spec.objective
        vec = [risk_measure(guarded["peak_body_accel_mps2"], ob.measure, ob.level),
               gear_mass_kg(veh, self.cells)]
        for c in self.spec.constraints:
            bad = c.badness(guarded, veh.honeycomb.x_L4)
            vec.append(risk_measure(bad, c.measure, c.level) / c.scale)
        return jnp.stack(vec), per

    def _measures_and_jac(self, z, inputs: dict):
        """Measures, their Jacobian (ill-conditioned scenes guarded: ``guard_ill_conditioned``)
        and the per-scene outcomes, with ``ill_conditioned``: per scene, whether any outcome's
        raw derivative (of the outcomes the measures read) is ill-conditioned."""
        def f(z):
            vec, per = self._measures(z, inputs)
            return (vec, {k: per[k] for k in self.outcomes}), (vec, per)

        (jac, jac_per), (vec, per) = jax.jacfwd(f, has_aux=True)(z)
        ill = [_ill_conditioned(per[k], t) for k, t in jac_per.items()]
        per = dict(per, ill_conditioned=jnp.any(jnp.stack(ill), axis=0))
        return vec, jac, per

    def evaluate(self, z, jacobian: bool = True):
        """``(measures, Jacobian d measures / d z or None, per-scene outcomes)``, numpy.
        ``measures`` = [objective's risk measure, gear mass proxy [kg], g_1 .. g_m]."""
        z = jnp.asarray(z, jnp.float64)
        if jacobian:
            vec, jac, per = self._jac(z, self._inputs)
            jac = np.asarray(jac)
        else:
            vec, per = self._fn(z, self._inputs)
            jac = None
        return np.asarray(vec), jac, {k: np.asarray(v) for k, v in per.items()}


# ------------------------------------------------------------------------------- optimiser
