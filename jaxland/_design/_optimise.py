"""The optimiser: an augmented Lagrangian on optax Adam, the best feasible iterate, the result."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._config import validate_vehicle, vehicle_to_toml
from .._errors import ConfigError
from .._files import atomic_write_text, json_text, run_environment
from .._params import Vehicle
from ._problem import DesignProblem
from ._spec import CELL_VARS, CONSTRAINTS, VARIABLES, DesignSpec


def _toml_values(problem: DesignProblem, z) -> dict:
    vals = problem.from_z(jnp.asarray(z))
    return {n: float(vals[n]) / VARIABLES[n].to_si for n in problem.names}


@dataclass
class DesignResult:
    """Outcome of ``optimise_design``: status, the design (TOML units), the designed and the
    baseline vehicle, histories, measures on the design scenes before/after, and (after
    ``verify_design``) the independent Monte Carlo check."""

    problem: DesignProblem
    status: str  # "feasible" or "infeasible"
    z: np.ndarray
    values: dict
    start_values: dict
    vehicle: Vehicle
    history: list
    at_start: dict
    at_design: dict
    violated: dict
    wall_s: float
    compile_s: float
    multipliers: list
    penalty: float
    best_iteration: int = 0  # the iteration whose iterate is returned (history's numbering)
    verification: dict | None = None
    mc_before: object = None
    mc_after: object = None

    @property
    def spec(self) -> DesignSpec:
        return self.problem.spec

    @property
    def baseline(self) -> Vehicle:
        return self.problem.vehicle

    @property
    def rounds_run(self) -> int:
        """Optimisations in the history: the first, and each re-optimisation round."""
        return len({rec.get("round", 0) for rec in self.history})

    @property
    def iterations_run(self) -> int:
        """Optimiser steps over every round: the history less each round's start (its
        iteration 0, the evaluation it steps from)."""
        return len(self.history) - self.rounds_run

    def to_toml(self) -> str:
        """The designed vehicle as a config TOML (``jaxland simulate --config`` loads it)."""
        shown = ", ".join(f"{k} = {v:.6g}" for k, v in self.values.items())
        lines = [f"# jaxland design ({self.status}): {shown}",
                 "# (k_b1 and k_b3 follow F1 and F2 so that x_L1 and x_L3 - x_L2 stay at the "
                 "baseline's)"]
        if any(k in self.values for k in CELL_VARS):
            cells = {**self.spec.cells, **self.values}
            lines.append("# honeycomb cells (Wierzbicki, F1_N / F2_N below derive from them): "
                         + ", ".join(f"{k} = {cells[k]:.6g}" for k in CELL_VARS))
        return "\n".join(lines) + "\n" + vehicle_to_toml(self.vehicle, changed_by="DESIGNED",
                                                         base=self.baseline)

    def report(self) -> dict:
        spec, prob = self.spec, self.problem
        return dict(
            status=self.status,
            violated=self.violated,
            model=prob.model,
            gradient="jax.jacfwd through the vmapped batch of landings (forward mode)",
            method=("augmented Lagrangian (Powell-Hestenes-Rockafellar) for inequalities, inner "
                    "steps optax.clip_by_global_norm + optax.scale_by_adam with a scheduled "
                    "step in the unconstrained coordinates; bounds by sigmoid (linear) or "
                    "sigmoid-of-log transforms"),
            optimiser=dict(learning_rate=spec.learning_rate, lr_schedule=spec.lr_schedule,
                           lr_final=spec.lr_final, clip_norm=spec.clip_norm,
                           adam_b1=spec.adam_b1, adam_b2=spec.adam_b2,
                           outer_every=spec.outer_every, penalty=spec.penalty,
                           penalty_growth=spec.penalty_growth,
                           penalty_max=spec.penalty_max,
                           feasibility_tol=spec.feasibility_tol, patience=spec.patience,
                           stop_rtol=spec.stop_rtol),
            best_iteration=self.best_iteration,
            # the [design] table as run (defaults filled in, --iterations applied)
            design_settings={f.metadata["toml"]: getattr(spec, f.name)
                             for f in dataclasses.fields(spec) if "toml" in f.metadata},
            smoothing=("none: peaks are the integrator's running maxima at every step, "
                       "differentiated at the step where they occur"),
            variables=[dict(name=v.name, unit=VARIABLES[v.name].unit, low=v.low, high=v.high,
                            scale=v.scale, start=self.start_values[v.name],
                            design=self.values[v.name]) for v in prob.variables],
            objective=dict(quantity="peak_body_accel_mps2", measure=spec.objective.measure,
                           level=(spec.objective.level if spec.objective.measure in (
                               "cvar", "normal") else None),
                           mass_weight=spec.objective.mass_weight),
            # [cells]: the gear-mass proxy's flow stress and section; with cell variables also
            # the cells that set F1 and F2
            cells=dict(spec.cells),
            constraints=[dict(name=c.name, rule=CONSTRAINTS[c.name].rule,
                              threshold_si=c.threshold, measure=c.measure,
                              # max and mean take no level (a spec giving one is refused)
                              level=c.level if c.measure in ("cvar", "normal") else None,
                              scale_si=c.scale,
                              **({"violation_tolerance": c.violation_tolerance}
                                 if c.measure == "max" else {}))
                         for c in spec.constraints],
            scenes=dict(n=spec.n_scenes, seed=spec.scene_seed, method=spec.method,
                        dt_s=spec.dt, t_end_s=spec.t_end, devices=prob.devices,
                        dispersion={k: v.record() for k, v in spec.montecarlo.dispersion.items()},
                        fixed=spec.montecarlo.fixed),
            iterations=self.iterations_run,
            wall_s=self.wall_s,
            compile_s=self.compile_s,
            multipliers=self.multipliers,
            penalty=self.penalty,
            at_start=self.at_start,
            at_design=self.at_design,
            verification=self.verification,
            history=self.history,
            # the gear the design started from, loadable as written (jaxland simulate --config)
            baseline_vehicle_toml=vehicle_to_toml(self.baseline),
            environment=run_environment(),
        )

    def to_json(self, path, inputs: dict | None = None) -> Path:
        """Write ``report()`` as strict JSON, with ``inputs`` (what the run was given: the
        spec's path, the command's arguments) first where given."""
        report = self.report() if inputs is None else {"inputs": inputs, **self.report()}
        return atomic_write_text(path, json_text(report))

    def plot(self, out_dir) -> list[Path]:
        from .._plots import plot_design

        return plot_design(self, Path(out_dir))


def _summaries(problem: DesignProblem, vec, per, z) -> dict:
    spec = problem.spec
    out = dict(objective_measure_mps2=float(vec[0]), gear_mass_kg=float(vec[1]),
               values=_toml_values(problem, z),
               mean_peak_body_accel_mps2=float(np.mean(per["peak_body_accel_mps2"])),
               max_peak_body_accel_mps2=float(np.max(per["peak_body_accel_mps2"])),
               max_stroke_m=float(np.max(per["max_stroke_m"])),
               x_L4_m=float(problem.vehicle_at(jnp.asarray(z)).honeycomb.x_L4),
               n_failed=int(np.sum(per["failed"])), n_tipped=int(np.sum(per["tipped"])),
               n_unfinished=int(np.sum(per["unfinished"])))
    if "min_stability_margin_m" in per:
        out["min_stability_margin_m"] = float(np.min(per["min_stability_margin_m"]))
    if "ill_conditioned" in per:  # scenes whose derivatives the gradient replaces
        out["n_ill_conditioned_scenes"] = int(np.sum(per["ill_conditioned"]))
    out["constraints"] = {c.name: dict(g=float(vec[2 + i]), value_si=float(vec[2 + i]) * c.scale)
                          for i, c in enumerate(spec.constraints)}
    return out


def step_schedule(spec: DesignSpec, n_iter: int):
    """The optax schedule of the inner step over ``n_iter`` iterations: ``cosine`` decay or
    ``exponential`` decay from ``learning_rate`` to ``lr_final`` x ``learning_rate``, or
    ``constant``."""
    lr, n = spec.learning_rate, max(int(n_iter), 1)
    if spec.lr_schedule == "cosine":
        return optax.cosine_decay_schedule(lr, decay_steps=n, alpha=spec.lr_final)
    if spec.lr_schedule == "exponential":
        return optax.exponential_decay(lr, transition_steps=n, decay_rate=spec.lr_final)
    return optax.constant_schedule(lr)


def optimise_design(spec: DesignSpec, vehicle: Vehicle | None = None, *,
                    iterations: int | None = None, progress=None,
                    problem: DesignProblem | None = None, start=None) -> DesignResult:
    """Run the augmented-Lagrangian design loop (module docstring); ``progress(dict)`` is called
    once per iteration. ``start``: design values (SI, by name) to start from instead of the
    problem's start point. Raises ``SimulationError`` if a landing fails at the start point."""
    from .._errors import SimulationError

    prob = DesignProblem(spec, vehicle) if problem is None else problem
    n_iter = spec.iterations if iterations is None else int(iterations)
    if n_iter < 0:
        raise ConfigError("iterations", n_iter, "must be >= 0")
    n_con = len(spec.constraints)
    t0 = time.perf_counter()
    z = np.asarray(prob.z0 if start is None else prob.to_z(start), dtype=float).copy()
    vec, jac, per = prob.evaluate(z)
    compile_s = time.perf_counter() - t0
    if np.any(per["no_touchdown"]):
        raise ConfigError("design.t_end_s", spec.t_end,
                          f"{int(np.sum(per['no_touchdown']))} of {prob.count} design scenes do "
                          "not touch down within it: raise it, or start the scenes nearer the "
                          "ground (drop_height_m)")
    if np.any(per["failed"]) or not np.all(np.isfinite(vec)):
        raise SimulationError(
            f"{int(np.sum(per['failed']))} of {spec.n_scenes} design scenes fail numerically at "
            f"the start design (non-finite state or energy ledger); reduce design.dt_s")
    a0, m0 = max(float(vec[0]), 1e-12), max(float(vec[1]), 1e-12)
    w = spec.objective.mass_weight
    start = _summaries(prob, vec, per, z)
    lam, rho = np.zeros(n_con), float(spec.penalty)
    opt = optax.chain(
        optax.clip_by_global_norm(spec.clip_norm) if spec.clip_norm > 0 else optax.identity(),
        optax.scale_by_adam(b1=spec.adam_b1, b2=spec.adam_b2))
    schedule = step_schedule(spec, n_iter)
    # optax mixes int32 counters with floats: allow the standard promotion even where the
    # caller made it strict (as the test suite does)
    with jax.numpy_dtype_promotion("standard"):
        state = opt.init(jnp.asarray(z))
    history: list = []
    best = None  # (J, z, vec, per, iteration)
    least_bad = None  # (max violation, z, vec, per, iteration)
    prev_viol = math.inf
    lr_factor, n_rejected, best_improved = 1.0, 0, 0
    z_prev, state_prev = z, state
    t_loop = time.perf_counter()
    for it in range(n_iter + 1):
        if it > 0:
            vec, jac, per = prob.evaluate(z)
        bad = bool(np.any(per["failed"])) or not (np.all(np.isfinite(vec))
                                                   and np.all(np.isfinite(jac)))
        if bad:  # a trial design whose landings fail: step back with a shorter step
            n_rejected += 1
            lr_factor *= 0.5
            z, state = z_prev, state_prev
            vec, jac, per = prob.evaluate(z)
        g = vec[2:]
        J = vec[0] / a0 + w * vec[1] / m0
        gJ = jac[0] / a0 + w * jac[1] / m0
        shifted = np.maximum(0.0, lam + rho * g)
        L = J + float(np.sum((shifted**2 - lam**2) / (2.0 * rho)))
        gL = gJ + (shifted[:, None] * jac[2:]).sum(axis=0) if n_con else gJ
        viol = float(np.max(np.maximum(g, 0.0))) if n_con else 0.0
        if viol <= spec.feasibility_tol and (best is None or J < best[0]):
            if best is None or J < best[0] * (1.0 - spec.stop_rtol):
                best_improved = it
            best = (J, z.copy(), vec, per, it)
        if least_bad is None or viol < least_bad[0]:
            least_bad = (viol, z.copy(), vec, per, it)
        rec = dict(iteration=it, objective=float(J), objective_measure_mps2=float(vec[0]),
                   gear_mass_kg=float(vec[1]), lagrangian=L,
                   constraints={c.name: float(g[i]) for i, c in enumerate(spec.constraints)},
                   multipliers=lam.tolist(), penalty=rho, max_violation=viol,
                   grad_norm=float(np.linalg.norm(gL)), rejected=bad,
                   values=_toml_values(prob, z), wall_s=time.perf_counter() - t_loop)
        history.append(rec)
        if progress:
            progress(rec)
        if it == n_iter:
            break
        if spec.patience and best is not None and it - best_improved >= spec.patience:
            break  # the best feasible J has not improved by stop_rtol for `patience` iterations
        if it > 0 and it % spec.outer_every == 0 and n_con:
            lam = np.maximum(0.0, lam + rho * g)
            if viol > 0.5 * prev_viol:
                rho = min(rho * spec.penalty_growth, spec.penalty_max)
            prev_viol = viol
        z_prev, state_prev = z, state
        with jax.numpy_dtype_promotion("standard"):
            updates, state = opt.update(jnp.asarray(gL), state)
            lr = float(schedule(it))
        z = z - lr * lr_factor * np.asarray(updates)
    wall = time.perf_counter() - t0
    if best is not None:
        status, (_, z_out, vec_out, per_out, it_out) = "feasible", best
        violated = {}
    else:
        status = "infeasible"
        _, z_out, vec_out, per_out, it_out = least_bad
        violated = {c.name: dict(g=float(vec_out[2 + i]),
                                 value_si=float(vec_out[2 + i]) * c.scale,
                                 rule=CONSTRAINTS[c.name].rule)
                    for i, c in enumerate(spec.constraints)
                    if vec_out[2 + i] > spec.feasibility_tol}
    veh = validate_vehicle(prob.vehicle_at(jnp.asarray(z_out)))
    return DesignResult(
        problem=prob, status=status, z=z_out, values=_toml_values(prob, z_out),
        start_values=_toml_values(prob, prob.z0), vehicle=veh, history=history,
        at_start=start, at_design=_summaries(prob, vec_out, per_out, z_out), violated=violated,
        wall_s=wall, compile_s=compile_s, multipliers=lam.tolist(), penalty=rho,
        best_iteration=it_out)


# ------------------------------------------------------------------------------- verification
