"""Verification: an independent Monte Carlo of the baseline and the design, fresh samples."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._errors import ConfigError
from .._montecarlo import MonteCarloSpec, percentiles, run_montecarlo, wilson_interval
from .._params import Vehicle
from .._solvers import Result
from ._optimise import DesignResult
from ._problem import risk_measure
from ._spec import DesignSpec


def _judge(res, vehicle: Vehicle, spec: DesignSpec) -> dict:
    ok = res.failure == int(Result.SUCCESSFUL)
    o = res.outputs
    n = int(ok.sum())
    stroke = o["max_stroke_m"].max(axis=1)[ok]
    accel = o["peak_body_accel_mps2"][ok]
    out = dict(n=int(res.failure.size), n_ok=n, n_failed=res.summary["n_failed"],
               seed=res.summary["seed"], model=res.summary["model"],
               peak_body_accel_mps2=percentiles(accel),
               objective_measure_mps2=float(risk_measure(jnp.asarray(accel),
                                                         spec.objective.measure,
                                                         spec.objective.level)) if n else None,
               max_stroke_m=percentiles(stroke),
               slip_distance_m=percentiles(o["slip_distance_m"].max(axis=1)[ok]),
               tip_over=res.summary["tip_over"], bottoming=res.summary["bottoming"],
               wall_s=res.summary["wall_s"])
    if "min_stability_margin_m" in o:
        out["min_stability_margin_m"] = percentiles(o["min_stability_margin_m"][ok])
    per = dict(max_stroke_m=stroke, slip_distance_m=o["slip_distance_m"].max(axis=1)[ok])
    if "min_stability_margin_m" in o:
        per["min_stability_margin_m"] = o["min_stability_margin_m"][ok]
    viol = {}
    for c in spec.constraints:
        k = int(np.sum(c.badness(per, float(vehicle.honeycomb.x_L4)) > 0))
        viol[c.name] = dict(count=k, n=n, probability=k / max(n, 1),
                            ci95_wilson=wilson_interval(k, n))
    out["constraint_violations"] = viol
    return out


def verify_design(result: DesignResult, *, n: int | None = None, seed: int | None = None,
                  progress: bool = False) -> dict:
    """Re-check the baseline and the design with an independent Monte Carlo: fresh samples
    (``montecarlo.seed``, never the design's ``scene_seed``), the spec's verification ``dt_s``
    and ``t_end_s``, unsmoothed outcomes. Stores and returns the before/after comparison."""
    spec = result.spec
    mc = spec.montecarlo
    seed = mc.seed if seed is None else seed
    if seed == spec.scene_seed:
        raise ConfigError("seed", seed, "must differ from design.scene_seed (fresh samples)")
    vspec = MonteCarloSpec(dispersion=mc.dispersion, fixed=mc.fixed,
                           n=mc.n if n is None else int(n), seed=seed, dt=mc.dt, t_end=mc.t_end,
                           model=result.problem.model)
    before = run_montecarlo(vspec, result.baseline,
                            progress=progress and "verification, before (baseline)")
    after = run_montecarlo(vspec, result.vehicle,
                           progress=progress and "verification, after (design)")
    result.mc_before, result.mc_after = before, after
    result.verification = dict(
        n=vspec.n, seed=seed, dt_s=vspec.dt, t_end_s=vspec.t_end, model=vspec.model,
        smoothing="none (the optimisation used none either)",
        before=_judge(before, result.baseline, spec), after=_judge(after, result.vehicle, spec))
    return result.verification
