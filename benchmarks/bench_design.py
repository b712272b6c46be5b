"""Design benchmark: forward (jacfwd) against reverse (grad) mode for the robust objective, the
bias of a smooth maximum over the saved trace, the optimiser's convergence before/after the
gradient clip and step schedule on a small quarter-model case, and the before/after table of a
design run.

    python benchmarks/bench_design.py [--report out/design-paper/design_report.json]

writes benchmarks/results/design.json. The design itself is run by
``jaxland design examples/design_paper_gear.toml --out out/design-paper`` (its report is read
here, not recomputed).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxland as jl
from jaxland import DesignProblem, design_spec_from_dict, optimise_design

ROOT = Path(__file__).resolve().parents[1]

ROBUST = dict(
    design=dict(iterations=0, n_scenes=8, scene_seed=3, dt_s=1e-5, t_end_s=0.15),
    objective=dict(measure="cvar", level=0.75),
    variables={"F1_N": dict(low=2000.0, high=8000.0), "x_L2_mm": dict(low=20.0, high=150.0),
               "k_a_N_per_m": dict(low=1e6, high=2e7)},
    constraints=dict(stroke=dict(margin_mm=20.0, measure="cvar", level=0.75)),
    montecarlo=dict(n=8, seed=4),
    fixed=dict(drop_height_m=0.0),
    dispersion={"sink_speed_mps": dict(dist="uniform", low=1.6, high=2.6),
                "mass_scale": dict(dist="normal", mean=1.0, std=0.05)},
)


# A small constrained case whose stroke constraint binds (as in the paper-gear run): quarter
# model, 8 scenes with the paper's sink-speed dispersion, 0.25 s from touchdown, 4 variables.
CONVERGENCE = copy.deepcopy(ROBUST)
CONVERGENCE["design"].update(iterations=60, t_end_s=0.25)
CONVERGENCE["objective"] = dict(measure="cvar", level=0.8)
CONVERGENCE["variables"]["F2_N"] = dict(low=4000.0, high=20000.0)
CONVERGENCE["constraints"] = dict(stroke=dict(margin_mm=20.0, measure="max"))
CONVERGENCE["dispersion"] = {
    "sink_speed_mps": dict(dist="truncnormal", mean=2.0, std=0.3, low=1.0, high=3.0),
    "mass_scale": dict(dist="normal", mean=1.0, std=0.05)}
# the inner-step settings before (the first paper-gear run) and after
OPTIMISERS = {
    "before: Adam lr 0.1, cosine decay, no clip": dict(learning_rate=0.1, clip_norm=0.0),
    "after: clip_by_global_norm 0.3, Adam lr 0.3, cosine decay": dict(
        learning_rate=0.3, clip_norm=0.3),
    "after, with patience 12 (early stop)": dict(learning_rate=0.3, clip_norm=0.3, patience=12),
}


def _time(fn, *args, repeat=3):
    jax.block_until_ready(fn(*args))  # compile
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t)
    return best


def forward_vs_reverse() -> dict:
    """Cost of the gradient of the robust objective (CVaR of peak acceleration over 8 quarter
    scenes, 0.15 s, 3 variables): jax.jacfwd of all measures vs jax.grad of the objective
    alone (reverse mode stores every step of the scan, and runs without the guard)."""
    from jaxland._design._problem import risk_measure

    prob = DesignProblem(design_spec_from_dict(ROBUST))
    z = jnp.asarray(prob.z0)
    ob = prob.spec.objective

    def objective(z):  # the measure without the ill-conditioned scenes' guard, a forward-mode
        # rule that reverse mode cannot transpose (it selects on the tangent); these short
        # quarter scenes are well-conditioned, so the guard changes no derivative here
        per = prob._per_scene(prob.vehicle_at(z), prob.scenes)
        return risk_measure(per["peak_body_accel_mps2"], ob.measure, ob.level)

    fwd = jax.jit(lambda z: prob._measures(z, prob._inputs)[0])
    jac = jax.jit(jax.jacfwd(lambda z: prob._measures(z, prob._inputs)[0]))
    grad = jax.jit(jax.grad(objective))
    t_f, t_j, t_g = _time(fwd, z), _time(jac, z), _time(grad, z)
    g_j, g_r = np.asarray(jac(z))[0], np.asarray(grad(z))
    return dict(case="quarter model, 8 scenes, 15000 steps, 3 variables, CVaR_0.75",
                forward_s=t_f, jacfwd_all_measures_s=t_j, grad_objective_only_s=t_g,
                jacfwd_over_forward=t_j / t_f, grad_over_forward=t_g / t_f,
                max_rel_difference=float(np.max(np.abs(g_j - g_r)) / np.max(np.abs(g_j))))


STEPS = (("euler", 1e-5), ("euler_implicit", 2e-5), ("euler_implicit", 4e-5),
         ("verlet", 4e-5), ("verlet", 8e-5))


def design_step() -> dict:
    """The design landings' integrator and step for the paper-gear spec (full model, 24 scenes,
    the spec's landing length): its measures (objective, gear mass, constraints) at the
    baseline and one forward evaluation's time, against euler at 1e-5 s (the verification's
    setting), side by side."""
    import tomllib

    base = tomllib.loads((ROOT / "examples/design_paper_gear.toml").read_text())
    rows, ref = [], None
    for method, dt in STEPS:
        d = copy.deepcopy(base)
        d["design"].update(method=method, dt_s=dt)
        prob = DesignProblem(design_spec_from_dict(d))
        z = jnp.asarray(prob.z0)
        fwd = jax.jit(lambda z, prob=prob: prob._measures(z, prob._inputs)[0])
        t = _time(fwd, z, repeat=2)
        vec = np.asarray(fwd(z))
        ref = vec if ref is None else ref
        rows.append(dict(method=method, dt_s=dt, forward_s=t, measures=vec.tolist(),
                         objective_rel_diff=float(abs(vec[0] / ref[0] - 1.0)),
                         constraint_diff_g=float(np.max(np.abs(vec[2:] - ref[2:])))))
    return dict(case="examples/design_paper_gear.toml at its baseline: measures = [objective "
                     "m/s^2, gear mass kg, g_stroke, g_stability] (g in units of the "
                     "constraint scale: 10 mm, 0.1 m)", reference="euler, dt 1e-5 s", runs=rows)


_SPLIT_RUN = """
import json, sys, time, tomllib
import jax
jax.config.update("jax_num_cpu_devices", int(sys.argv[1]))
import jaxland as jl
jl.use_batch_fusion()
from jaxland import DesignProblem, design_spec_from_dict
prob = DesignProblem(design_spec_from_dict(tomllib.loads(open(sys.argv[2]).read())))
t = time.perf_counter()
prob.evaluate(prob.z0)
first = time.perf_counter() - t
runs = []
for _ in range(3):
    t, c = time.perf_counter(), time.process_time()
    prob.evaluate(prob.z0)
    runs.append((time.perf_counter() - t, time.process_time() - c))
wall, cpu = min(runs)
print(json.dumps(dict(devices=prob.devices, first_evaluation_s=first, iteration_wall_s=wall,
                      iteration_cpu_s=cpu)))
"""


def device_split() -> dict:
    """One iteration of the paper-gear spec (measures and forward-mode Jacobian of its 24
    scenes) with the scenes on 1 and on 2 CPU devices, each in a fresh process as
    ``jaxland design`` runs it (batch fusion on), one after the other: the best of 3 in wall
    and CPU time after the first (compiling) evaluation."""
    import subprocess
    import sys

    spec = str(ROOT / "examples/design_paper_gear.toml")
    rows = []
    for devices in (1, 2):
        out = subprocess.run([sys.executable, "-c", _SPLIT_RUN, str(devices), spec],
                             capture_output=True, text=True, check=True,
                             env=dict(os.environ, JAXLAND_CACHE_DIR=""))
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return dict(rows=rows, load_average_1min=os.getloadavg()[0])


def conditioning() -> dict:
    """The paper-gear spec's design scenes at the baseline: per outcome the measures read, each
    scene's largest raw derivative along one unconstrained coordinate z over the scenes' median
    magnitude of that outcome (forward mode), the scenes the design's guard flags, and the
    largest entry of each row of the measures' Jacobian with the guard and without it
    (docs/design.md, "Ill-conditioned scenes")."""
    import tomllib

    from jaxland._design import _problem  # the guard's threshold, switched off for "raw"

    spec = design_spec_from_dict(tomllib.loads(
        (ROOT / "examples/design_paper_gear.toml").read_text()))
    prob = DesignProblem(spec)
    z = jnp.asarray(prob.z0)

    def outcomes(z):
        per = prob._per_scene(prob.vehicle_at(z), prob.scenes)
        return {k: per[k] for k in prob.outcomes}

    val, jac = jax.jit(lambda z: (outcomes(z), jax.jacfwd(outcomes)(z)))(z)
    rel = {k: np.max(np.abs(np.asarray(jac[k])), axis=1) / np.median(np.abs(np.asarray(val[k])))
           for k in val}
    _, jac_guarded, per = prob.evaluate(z)
    threshold = _problem.ILL_CONDITIONED
    _problem.ILL_CONDITIONED = float("inf")  # read when the problem is traced: a fresh one
    try:
        _, jac_raw, _ = DesignProblem(spec).evaluate(z)
    finally:
        _problem.ILL_CONDITIONED = threshold
    return dict(
        case=f"examples/design_paper_gear.toml at its baseline ({spec.n_scenes} scenes, "
             f"{spec.t_end:g} s, {spec.method} at {spec.dt:g} s)",
        threshold=threshold, relative_derivative_sorted={k: sorted(v.tolist())
                                                         for k, v in rel.items()},
        n_ill_conditioned={k: int(np.sum(v > threshold)) for k, v in rel.items()},
        scenes_ill_conditioned=np.flatnonzero(per["ill_conditioned"]).tolist(),
        measures=["objective", "gear mass", *(c.name for c in spec.constraints)],
        jacobian_row_max_abs_guarded=np.max(np.abs(jac_guarded), axis=1).tolist(),
        jacobian_row_max_abs_raw=np.max(np.abs(jac_raw), axis=1).tolist())


def convergence() -> dict:
    """Iterations and wall time of the augmented-Lagrangian loop on ``CONVERGENCE`` for each
    inner-step setting in ``OPTIMISERS`` (one compiled problem shared, compiled beforehand):
    the best feasible CVaR_0.8, the iteration that found it, and the iterations / seconds until
    the best feasible value came within 1 % of the best over all settings."""
    prob = DesignProblem(design_spec_from_dict(copy.deepcopy(CONVERGENCE)))
    prob.evaluate(prob.z0)  # compile
    runs = {}
    for name, opts in OPTIMISERS.items():
        d = copy.deepcopy(CONVERGENCE)
        d["design"].update(opts)
        res = optimise_design(design_spec_from_dict(d), problem=prob)
        h = res.history
        feas = np.array([r["objective_measure_mps2"] if r["max_violation"] <= 1e-3 else np.inf
                         for r in h])
        runs[name] = dict(settings=opts, best_mps2=res.at_design["objective_measure_mps2"],
                          best_iteration=res.best_iteration, iterations_run=len(h) - 1,
                          wall_s=res.wall_s, best_so_far=np.minimum.accumulate(feas),
                          loop_wall=np.array([r["wall_s"] for r in h]))
    ref = min(r["best_mps2"] for r in runs.values())
    for r in runs.values():
        hit = np.flatnonzero(r.pop("best_so_far") <= 1.01 * ref)
        walls = r.pop("loop_wall")
        r["iterations_to_1pct"] = int(hit[0]) if hit.size else None
        r["wall_to_1pct_s"] = float(walls[hit[0]]) if hit.size else None
    return dict(case="quarter model, 8 scenes (sink 2.0 +/- 0.3 m/s in [1, 3], mass +/- 5 %), "
                     "0.25 s, F1/F2/x_L2/k_a, CVaR_0.8 peak accel, stroke max <= x_L4 - 20 mm, "
                     "up to 60 iterations",
                best_overall_mps2=ref, runs=runs)


def smooth_max_bias() -> dict:
    """tau log-sum-exp(|a| / tau) over the saved body-acceleration trace against the running
    peak at every step, for the paper's 0.2 m drop (first 0.4 s, trace every 1e-4 s)."""
    solver = jl.Solver(dt=1e-5, t_end=0.4, save_dt=1e-4)
    tr, s = jax.jit(lambda: jl.landing(jl.paper_vehicle(), jl.Scene(), solver, "quarter"))()
    a = np.abs(np.asarray(tr["body_az_mps2"]))
    peak = float(s["peak_body_accel_mps2"])
    rows = []
    for tau in (5.0, 1.0, 0.3, 0.1, 0.03):
        lse = float(tau * jax.nn.logsumexp(jnp.asarray(a) / tau))
        rows.append(dict(tau_mps2=tau, smooth_max_mps2=lse, bias_rel=lse / peak - 1.0))
    return dict(running_peak_mps2=peak, sampled_max_mps2=float(a.max()),
                sampled_max_bias_rel=float(a.max()) / peak - 1.0, lse=rows)


def table(report: dict) -> dict:
    v = report["verification"]

    def pick(r):
        out = dict(peak_body_accel_p50_mps2=r["peak_body_accel_mps2"]["p50"],
                   peak_body_accel_p99_mps2=r["peak_body_accel_mps2"]["p99"],
                   peak_body_accel_mean_mps2=r["peak_body_accel_mps2"]["mean"],
                   objective_measure_mps2=r["objective_measure_mps2"],
                   max_stroke_p50_m=r["max_stroke_m"]["p50"],
                   max_stroke_p99_m=r["max_stroke_m"]["p99"],
                   max_stroke_max_m=r["max_stroke_m"]["max"],
                   tip_over=r["tip_over"], bottoming=r["bottoming"],
                   constraint_violations=r["constraint_violations"], n_failed=r["n_failed"],
                   n_unfinished=r.get("n_unfinished"), continued=r.get("continued"))
        if "min_stability_margin_m" in r:
            out["min_stability_margin_p01_m"] = r["min_stability_margin_m"]["p01"]
        return out

    return dict(status=report["status"], model=report["model"],
                variables=report["variables"], objective=report["objective"],
                constraints=report["constraints"], scenes=report["scenes"],
                iterations=report["iterations"], best_iteration=report.get("best_iteration"),
                optimiser=report.get("optimiser"), optimisation_wall_s=report["wall_s"],
                first_evaluation_incl_compile_s=report["compile_s"],
                on_design_scenes=dict(before=report["at_start"], after=report["at_design"]),
                verification=dict(n=v["n"], seed=v["seed"], t_end_s=v["t_end_s"],
                                  before=pick(v["before"]), after=pick(v["after"]),
                                  verified=v.get("verified"), reason=v.get("reason"),
                                  rounds=v.get("rounds"), added_landings=v.get("added_landings"),
                                  constraints_after=v["after"].get("constraints"),
                                  constraints_before=v["before"].get("constraints"),
                                  wall_s=v["before"]["wall_s"] + v["after"]["wall_s"]),
                total_wall_s=v.get("total_wall_s"))


def wall_times(report: dict) -> dict:
    """Where a design run's wall time went [s]: the first evaluation (tracing and compilation
    included), the optimiser's iterations, the verification Monte Carlos (compilation
    included), the rest (building the problem, checking the step, running on the verification
    landings cut off at t_end, judging the verification) and the whole run (``total_wall_s``;
    the command's printed total adds the figures)."""
    v = report["verification"]
    total = v.get("total_wall_s")
    ver_wall = v["before"]["wall_s"] + v["after"]["wall_s"]
    return dict(iterations=report["iterations"], devices=report["scenes"].get("devices"),
                n_scenes=report["scenes"]["n"],
                first_evaluation_incl_compile_s=report["compile_s"],
                optimisation_wall_s=report["wall_s"],
                per_iteration_s=(report["wall_s"] - report["compile_s"])
                / max(report["iterations"], 1),
                verification_wall_s=ver_wall,
                verification_n=v["n"], verification_dt_s=v.get("dt_s"),
                rounds=len(v.get("rounds") or []) - 1,
                setup_and_judging_s=None if total is None else total - report["wall_s"] - ver_wall,
                total_wall_s=total)


STUDIES = dict(gradient_modes=forward_vs_reverse, convergence=convergence,
               smooth_max=smooth_max_bias, design_step=design_step, conditioning=conditioning,
               device_split=device_split)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--report", default=str(ROOT / "out/design-paper/design_report.json"))
    p.add_argument("--out", default=str(ROOT / "benchmarks/results/design.json"))
    p.add_argument("--repeats", nargs="*", default=[], metavar="REPORT",
                   help="reports of further runs of the same spec (their wall times are kept "
                        "beside the main run's)")
    p.add_argument("--only", choices=(*STUDIES, "report"),
                   help="run one study and keep the others' stored results ('report': none, "
                        "only the design run's report is read again)")
    args = p.parse_args(argv)
    out = Path(args.out)
    if args.only == "report" and not Path(args.report).exists():
        p.exit(2, f"error: --only report: no design report at {args.report} (run jaxland "
                  "design examples/design_paper_gear.toml --out out/design-paper)\n")
    result = json.loads(out.read_text()) if args.only and out.exists() else {}
    result["machine"] = dict(cpus=os.cpu_count(), platform=platform.platform(),
                             jax=jax.__version__, backend=jax.default_backend())
    for name, study in STUDIES.items():
        if args.only in (None, name):
            result[name] = study()
    rep = Path(args.report)
    if rep.exists() and args.only in (None, "report"):
        result["paper_gear_design"] = table(json.loads(rep.read_text()))
        result["paper_gear_design"]["command"] = (
            "jaxland design examples/design_paper_gear.toml --out out/design-paper")
        result["paper_gear_design"]["wall"] = wall_times(json.loads(rep.read_text()))
        result["paper_gear_design"]["repeats"] = [
            wall_times(json.loads(Path(r).read_text())) for r in args.repeats]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2, default=float) + "\n")
    tmp.replace(out)
    print(json.dumps({k: v for k, v in result.items() if k != "paper_gear_design"}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
