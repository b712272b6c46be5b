"""Verification: an independent Monte Carlo of the baseline and the design, fresh samples."""

from __future__ import annotations

import dataclasses
import functools
import math
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import ConfigError
from .._montecarlo import (
    MonteCarloSpec,
    percentiles,
    proportion,
    run_montecarlo,
    wilson_interval,
)
from .._montecarlo._run import (
    _per_sample,
    _retry,
    _summarise,
    bottomed_out,
    check_run,
    check_touchdown_possible,
    mc_solver,
    retry_method,
)
from .._montecarlo._sample import sample_scenes
from .._montecarlo._spec import SEED_HIGH
from .._montecarlo._stats import Z95, binomial_tail, tip_over_of
from .._params import Vehicle
from .._progress import ProgressLine
from .._solvers import Result
from ._optimise import DesignResult, _summaries, optimise_design
from ._problem import DesignProblem, risk_measure
from ._spec import VARIABLES, DesignSpec

# A verification landing that t_end_s cuts off (still in an impact, or able to tip over) has no
# final stroke or margin yet: it is run again from touchdown to these multiples of t_end_s, the
# next only for those still unfinished (docs/design.md: on the paper-gear example 42 of 300
# design landings are cut off at 1 s; continuing them moved a max stroke by up to 32 mm).
CONTINUE_FACTORS = (3.0, 9.0)


@functools.lru_cache(maxsize=4)
def _continued_program(solver, model):
    """The landings of the continuation, the vehicle an argument: the baseline and the design
    share its compilation (per padded size)."""
    return jax.jit(lambda vehicle, scenes: _per_sample(vehicle, solver, model, scenes))


def _keep(res, idx: np.ndarray, out: dict, t_end: float) -> None:
    """Keep, in place of their own, the outcomes ``out`` (a Monte Carlo's, with "result") of
    ``res``'s landings ``idx``, run to ``t_end`` [s]."""
    out = dict(out)
    res.failure[idx] = out.pop("result").astype(int)
    for k, v in out.items():
        if k in res.outputs:
            res.outputs[k][idx] = v.astype(res.outputs[k].dtype)
    res.outputs["t_end_s"][idx] = t_end


def _bottomed_again(res, idx: np.ndarray) -> None:
    """Whether ``res``'s landings ``idx`` bottomed out, from the max strokes they now keep."""
    res.outputs["bottomed_out"][idx] = bottomed_out(
        {"max_stroke_m": res.outputs["max_stroke_m"][idx]}, res.vehicle)


def _latest_outcomes(vspec: MonteCarloSpec, res, say=None) -> list:
    """The verification Monte Carlo ``res`` (of ``vspec``) with each landing's latest known
    outcomes, kept in place (``res.failure``, ``res.outputs``; ``res.outputs["t_end_s"]``:
    each landing's end) with the summary made again from them. The t_end check's landings take
    their outcomes at the check's end (twice t_end_s): a landing that crushes further,
    bottoms out or tips over after t_end_s is judged so. Then the unfinished landings run
    again, from touchdown, to ``CONTINUE_FACTORS`` x t_end_s, each with the method and step
    it ended with (a retried landing: the retry's); one that fails numerically is retried as
    the Monte Carlo retries its own. Returns, per continuation, its t_end_s and how many it
    ran, retried and left."""
    vehicle, model = res.vehicle, res.summary["model"]
    n = res.failure.size
    res.outputs["t_end_s"] = np.full(n, float(vspec.t_end))
    longer = res.t_end_longer
    if longer is not None and longer["samples"].size:
        _keep(res, longer["samples"], longer["outputs"], longer["t_end_s"])
        _bottomed_again(res, longer["samples"])
    log = []
    for factor in CONTINUE_FACTORS:
        todo = np.flatnonzero(res.failure == int(Result.UNFINISHED))
        if todo.size == 0:
            break
        t_end = float(vspec.t_end) * factor
        t0 = time.perf_counter()
        was_retried = res.outputs["retried"][todo].copy()
        methods = np.where(was_retried, retry_method(vspec.method), vspec.method)
        steps = res.outputs["dt_s"][todo]
        for method, dt in sorted(set(zip(methods.tolist(), steps.tolist()))):
            idx = todo[(methods == method) & (steps == dt)]
            try:
                solver = mc_solver(dataclasses.replace(vspec, t_end=t_end), model, dt, method)
            except ConfigError:  # t_end is no whole multiple of that step: stays unfinished
                continue
            size = 8 * -(-idx.size // 8)  # padded with the last landing: fewer compilations
            padded = np.concatenate([idx, np.full(size - idx.size, idx[-1])])
            scenes, _ = sample_scenes(vspec, 0, 0, vehicle.n_legs, indices=padded)
            out = jax.device_get(_continued_program(solver, model)(vehicle, scenes))
            _keep(res, idx, {k: np.asarray(v)[:idx.size] for k, v in out.items()}, t_end)
        # a continuation that fails numerically is retried as the Monte Carlo retries its own
        # (the arrays are shared: the retry writes its outcomes into res)
        _retry(dataclasses.replace(vspec, t_end=t_end), vehicle, model,
               dict(res.outputs, result=res.failure), ProgressLine("", quiet=True), only=todo)
        _bottomed_again(res, todo)
        left = int((res.failure[todo] == int(Result.UNFINISHED)).sum())
        retried = int((res.outputs["retried"][todo] & ~was_retried).sum())
        log.append(dict(t_end_s=t_end, n=int(todo.size), n_unfinished_after=left,
                        n_retried=retried, wall_s=time.perf_counter() - t0))
        if say is not None:
            say(f"continued {todo.size} unfinished verification landing(s) to t_end_s = "
                f"{t_end:g} s: {left} still unfinished"
                + (f" ({retried} rerun with {retry_method(vspec.method)} after failing "
                   "numerically)" if retried else ""))
    s = res.summary
    res.summary = {**_summarise(vspec, model, res.inputs, res.outputs, res.failure,
                                s["wall_s"], s["devices"], s["chunk"]), "continued": log,
                   "t_end_check": s.get("t_end_check")}
    return log


def _judge(res, vehicle: Vehicle, spec: DesignSpec) -> dict:
    # a landing still unfinished after its continuation (_latest_outcomes) has no final
    # outcome: it is counted (n_unfinished) and the verification is not met
    ok = res.failure == int(Result.SUCCESSFUL)
    o = res.outputs
    n = int(ok.sum())
    stroke = o["max_stroke_m"].max(axis=1)[ok]
    accel = o["peak_body_accel_mps2"][ok]
    out = dict(n=int(res.failure.size), n_ok=n, n_failed=res.summary["n_failed"],
               failures=res.summary["failures"],
               n_unfinished=res.summary["n_unfinished"],
               continued=res.summary.get("continued", []),
               # whether outcomes called final at t_end_s still change (run_montecarlo)
               t_end_check=res.summary.get("t_end_check"),
               seed=res.summary["seed"], model=res.summary["model"],
               peak_body_accel_mps2=percentiles(accel),
               objective_measure_mps2=float(risk_measure(jnp.asarray(accel),
                                                         spec.objective.measure,
                                                         spec.objective.level)) if n else None,
               max_stroke_m=percentiles(stroke),
               slip_distance_m=percentiles(o["slip_distance_m"].max(axis=1)[ok]),
               tip_over=tip_over_of(res.summary["model"], o["tipped_over"][ok]),
               bottoming=proportion(o["bottomed_out"][ok]),
               wall_s=res.summary["wall_s"])
    if "min_stability_margin_m" in o:
        out["min_stability_margin_m"] = percentiles(o["min_stability_margin_m"][ok])
    per = dict(max_stroke_m=stroke, slip_distance_m=o["slip_distance_m"].max(axis=1)[ok])
    if "min_stability_margin_m" in o:
        per["min_stability_margin_m"] = o["min_stability_margin_m"][ok]
    viol, checks = {}, {}
    index = np.flatnonzero(ok)
    for c in spec.constraints:
        bad = np.asarray(c.badness(per, float(vehicle.honeycomb.x_L4)))
        viol[c.name] = proportion(bad > 0)
        checks[c.name] = _check(c, bad, index, res.summary["seed"])
    out["constraint_violations"] = viol
    out["constraints"] = checks
    out["met"] = (all(ch["met"] for ch in checks.values()) and out["n_failed"] == 0
                  and out["n_unfinished"] == 0)
    return out


BOOTSTRAP = 2000  # resamples of the verification landings for the measures' 95 % intervals
# Fewest judged landings for a 95 % bootstrap interval: below, the resamples are a handful of
# values (at 1 landing the "interval" is that landing), and no constraint is called met.
MIN_JUDGED = 20
# The normal measure (mean + z sd at ``level``) <= 0 stands for landings past the limit with a
# probability of at most 1 - level, if the outcome's tail is normal. Its verdict is not met
# where more landings are past the limit than that allows, by an exact binomial test at this
# one-sided significance: a normal tail fitted to a heavy-tailed stroke says "met" where the
# counts say otherwise. (An empirical CVaR <= 0 already keeps the counts within 1 - level.)
EXCEEDANCE_ALPHA = 0.025


def _risk_rows(values: np.ndarray, measure: str, level: float) -> np.ndarray:
    """``risk_measure`` of each row of ``values`` (numpy, for the bootstrap)."""
    n = values.shape[-1]
    if measure == "mean":
        return values.mean(axis=-1)
    if measure == "max":
        return values.max(axis=-1)
    if measure == "normal":
        z = statistics.NormalDist().inv_cdf(level)
        return values.mean(axis=-1) + z * values.std(axis=-1, ddof=1 if n > 1 else 0)
    tail = (1.0 - level) * n
    w = np.clip(tail - np.arange(n), 0.0, 1.0) / tail
    return (-np.sort(-values, axis=-1) * w).sum(axis=-1)


def clean_landings_needed(tolerance: float) -> int:
    """The fewest verification landings, none violating, whose 95 % Wilson upper bound on the
    violation probability, z^2 / (n + z^2) at none in n, is at most ``tolerance``."""
    n = math.ceil(Z95 * Z95 * (1.0 - tolerance) / tolerance - 1e-9)
    while wilson_interval(0, n)[1] > tolerance:  # round-off at the boundary
        n += 1
    return n


def _check(c, bad: np.ndarray, index: np.ndarray, seed: int) -> dict:
    """One constraint judged on the verification landings with the optimiser's own risk
    measure (normalised like g: <= 0 is met), its 95 % bootstrap percentile interval, and the
    violating samples (Monte Carlo indices, the worst first).

    ``judged_by`` names the rule. "bootstrap" (mean, cvar, normal): met when the interval's
    upper end is <= 0, so the fresh landings show it holds, not only that they do not show it
    fails. "violation bound" (max): the bootstrap of a sample maximum never exceeds the largest
    value observed, so its interval shows nothing beyond "no violation seen"; met when no
    landing violates it and the 95 % Wilson upper bound on the violation probability is at
    most ``c.violation_tolerance``. With no violation but a bound above the tolerance the
    landings are too few to judge it (``judged`` false; ``landings_needed`` would do).
    "violation count" (normal): the bootstrap's "met" overruled where more landings violate
    it than a probability of 1 - level allows (``EXCEEDANCE_ALPHA``); a normal measure's
    result always carries ``n_violating``, ``violation_allowed`` and ``p_value_violations``."""
    g = bad / c.scale
    common = dict(measure=c.measure, level=c.level, n=int(g.size))
    if g.size < MIN_JUDGED:  # no interval to judge it by (MIN_JUDGED)
        est = float(_risk_rows(g[None, :], c.measure, c.level)[0]) if g.size else None
        return dict(common, g=est, value_si=None if est is None else est * c.scale,
                    ci95=[None, None], met=False, judged=False, judged_by=None,
                    verdict=f"not judged: {g.size} landing(s), a 95 % interval needs "
                            f"{MIN_JUDGED}",
                    violators=[int(index[i]) for i in np.argsort(-g) if g[i] > 0])
    rng = np.random.default_rng([int(seed), 0x5EED])
    boot = _risk_rows(g[rng.integers(0, g.size, (BOOTSTRAP, g.size))], c.measure, c.level)
    lo, hi = (float(x) for x in np.quantile(boot, [0.025, 0.975]))
    est = float(_risk_rows(g[None, :], c.measure, c.level)[0])
    order = np.argsort(-g)
    out = dict(common, g=est, value_si=est * c.scale, ci95=[lo, hi],
               violators=[int(index[i]) for i in order if g[i] > 0])
    k = int(np.sum(g > 0))
    if c.measure != "max":
        met = bool(hi <= 0.0)
        verdict = (f"{'met' if met else 'not met'} by the 95 % bootstrap interval: "
                   f"g = {est:+.4g}, up to {hi:+.4g} (met: <= 0)")
        if c.measure != "normal":
            return dict(out, met=met, judged=True, judged_by="bootstrap", verdict=verdict)
        allowed = 1.0 - c.level
        p_value = binomial_tail(k, g.size, allowed)
        counted = dict(n_violating=k, violation_allowed=allowed, p_value_violations=p_value)
        if met and p_value < EXCEEDANCE_ALPHA:
            return dict(out, **counted, met=False, judged=True, judged_by="violation count",
                        verdict=f"not met: {k} of {g.size} landings violate it, more than a "
                                f"violation probability of {allowed:g} allows (exact binomial "
                                f"p = {p_value:.2g} < {EXCEEDANCE_ALPHA:g}), although its "
                                f"{c.measure} estimate is g = {est:+.4g}, up to {hi:+.4g}")
        return dict(out, **counted, met=met, judged=True, judged_by="bootstrap",
                    verdict=verdict)
    bound = wilson_interval(k, g.size)[1]
    tol = c.violation_tolerance
    met = bool(k == 0 and bound <= tol)
    judged = bool(k > 0 or met)
    needed = clean_landings_needed(tol)
    state = ("met" if met else "not met" if judged
             else f"not judged: needs {needed} landings without a violation")
    return dict(out, met=met, judged=judged, judged_by="violation bound", n_violating=k,
                p_violation_upper95=bound, violation_tolerance=tol, landings_needed=needed,
                verdict=(f"{state}: worst landing g = {est:+.4g} ({est * c.scale:+.4g} m, > 0 "
                         f"past the limit), {k} of {g.size} landings violate it, 95 % Wilson "
                         f"upper bound on the violation probability {bound:.4g} "
                         f"({'<=' if bound <= tol else '>'} violation_tolerance {tol:g}; met: "
                         "none violates and the bound is within it)"))


def _verification_spec(spec: DesignSpec, n, seed) -> MonteCarloSpec:
    """The verification Monte Carlo of a design spec: its dispersion, ``n`` (default
    ``montecarlo.n``) samples of ``seed``, euler at ``montecarlo.dt_s`` to ``t_end_s``, the
    design's model, retries on (the keys it sets itself: _spec.VERIFICATION_FIXED)."""
    mc = spec.montecarlo
    return MonteCarloSpec(dispersion=mc.dispersion, fixed=mc.fixed,
                          n=mc.n if n is None else int(n), seed=seed, dt=mc.dt, t_end=mc.t_end,
                          model=spec.resolved_model(), t_end_check=mc.t_end_check)


def check_verification(problem: DesignProblem, n: int | None = None) -> None:
    """Refuse, before the optimisation, a verification Monte Carlo that could not run on the
    baseline or on a design inside the bounds (its ``dt_s`` above the stability limit, an
    ``n`` beyond this machine's memory, a ``t_end_s`` before any touchdown): found after the
    optimisation, it would cost the whole design."""
    vspec = _verification_spec(problem.spec, n, problem.spec.montecarlo.seed)
    check_run(vspec, problem.vehicle)
    check_touchdown_possible(vspec, problem.vehicle)
    problem.check_step("montecarlo.dt_s", vspec.dt, vspec.method, vspec.t_end)


def verify_design(result: DesignResult, *, n: int | None = None, seed: int | None = None,
                  progress: bool = False, before: bool = True, say=None) -> dict:
    """Re-check the baseline and the design with an independent Monte Carlo: fresh samples
    (``montecarlo.seed``, never the design's ``scene_seed``), the spec's verification ``dt_s``
    and ``t_end_s`` (landings it cuts off continued to ``CONTINUE_FACTORS`` x t_end_s),
    unsmoothed outcomes. Stores and returns the before/after comparison (``before=False``: the
    design only; ``before`` is then None). ``say(str)``: a line per continuation."""
    spec = result.spec
    mc = spec.montecarlo
    seed = mc.seed if seed is None else seed
    if seed == spec.scene_seed:
        raise ConfigError("seed", seed, "must differ from design.scene_seed (fresh samples)")
    vspec = _verification_spec(result.spec, n, seed)
    before = run_montecarlo(vspec, result.baseline, share_program=True,
                            progress=progress and "verification, before (baseline)"
                            ) if before else None
    after = run_montecarlo(vspec, result.vehicle, share_program=True,
                           progress=progress and "verification, after (design)")
    for res in (before, after):
        if res is not None:
            _latest_outcomes(vspec, res, say)
    result.mc_before, result.mc_after = before, after
    result.verification = dict(
        n=vspec.n, seed=seed, dt_s=vspec.dt, t_end_s=vspec.t_end, model=vspec.model,
        smoothing="none (the optimisation used none either)",
        before=None if before is None else _judge(before, result.baseline, spec),
        after=_judge(after, result.vehicle, spec))
    return result.verification


def _unmet_text(name: str, ch: dict) -> str:
    if ch["ci95"][1] is None:
        return f"{name} (too few landings to judge it on)"
    if ch["judged_by"] == "violation bound":
        return (f"{name} (max) {ch['n_violating']} of {ch['n']} landings violate it (95 % "
                f"upper bound on the violation probability {ch['p_violation_upper95']:.3g})")
    if ch["judged_by"] == "violation count":
        return (f"{name} ({ch['measure']}) {ch['n_violating']} of {ch['n']} landings violate "
                f"it (a probability of {ch['violation_allowed']:g} allows fewer: exact "
                f"binomial p = {ch['p_value_violations']:.2g})")
    return f"{name} g = {ch['g']:+.3g} (95 % up to {ch['ci95'][1]:+.3g})"


def _not_judged(judged: dict, spec: DesignSpec) -> list[str]:
    """Why a verification whose constraints are met on its landings still does not verify:
    landings that failed (by reason) or that no continuation finished."""
    why = [f"{k} verification landing(s): {msg}" for msg, k in judged["failures"].items()]
    if judged["n_unfinished"]:
        why.append(_unfinished_text(judged, spec))
    return why


def _unfinished_text(judged: dict, spec: DesignSpec) -> str:
    factor = CONTINUE_FACTORS[-1] if CONTINUE_FACTORS else 1.0
    return (f"{judged['n_unfinished']} verification landing(s) still in an impact or able to "
            f"tip over at {factor * spec.montecarlo.t_end:g} s ({factor:g} x "
            "montecarlo.t_end_s): their outcomes are not final")


def _fresh_seed(spec: DesignSpec, round_: int) -> int:
    """The verification seed of re-optimisation round ``round_``: fresh samples each round,
    never the design scenes' seed; past the largest seed a spec may give, the count goes on
    from 0 (a spec's seed near it would otherwise be refused only once a round needed it)."""
    span, first = SEED_HIGH + 1, spec.montecarlo.seed
    seed = (first + round_) % span
    if (spec.scene_seed - first) % span <= round_:  # this or an earlier round skipped it
        seed = (seed + 1) % span
    return seed


def design_verified(spec: DesignSpec, vehicle: Vehicle | None = None, *, n: int | None = None,
                    rounds: int | None = None, progress=None, mc_progress: bool = False,
                    say=None, problem: DesignProblem | None = None) -> DesignResult:
    """Optimise, verify on fresh landings, and while a constraint is not met (``_check``: the
    upper end of its 95 % interval on the verification landings above its limit, more
    violations than its level allows, or a max constraint violated) add the violating
    landings to the design scenes and re-optimise from the last design, at most ``rounds``
    (default ``design.verify_rounds``) times, each verified on new fresh samples.

    The result's ``verification`` gains ``verified`` (every constraint met, no failed sample),
    ``rounds`` (what each round added and found) and, when not verified, ``reason``: why the
    loop stopped. ``say(str)`` receives one line per round. ``problem``: the design problem of
    ``spec`` and ``vehicle``, where already built (its construction checks the inputs)."""

    rounds = spec.verify_rounds if rounds is None else int(rounds)
    if rounds < 0:
        raise ConfigError("verify_rounds", rounds, "must be >= 0")
    say = say or (lambda msg: None)
    t0 = time.perf_counter()
    problem = DesignProblem(spec, vehicle) if problem is None else problem
    check_verification(problem, n)
    result = optimise_design(spec, vehicle, progress=progress, problem=problem)
    for rec in result.history:
        rec["round"] = 0
    history, log = list(result.history), []
    if result.status != "feasible":
        return result
    seed = _fresh_seed(spec, 0)
    verify_design(result, n=n, seed=seed, progress=mc_progress, say=say)
    added: tuple = ()
    reason, failed_round = None, None
    for r in range(1, rounds + 2):
        after = result.verification["after"]
        unmet = [name for name, ch in after["constraints"].items() if not ch["met"]]
        log.append(dict(round=r - 1, seed=seed, unmet=unmet, n_failed=after["n_failed"],
                        design=dict(result.values),
                        g={k: ch["g"] for k, ch in after["constraints"].items()},
                        ci95={k: ch["ci95"] for k, ch in after["constraints"].items()},
                        judged_by={k: ch["judged_by"] for k, ch in after["constraints"].items()},
                        p_violation_upper95={k: ch.get("p_violation_upper95")
                                             for k, ch in after["constraints"].items()},
                        n_violating={k: ch.get("n_violating")
                                     for k, ch in after["constraints"].items()},
                        p_value_violations={k: ch.get("p_value_violations")
                                            for k, ch in after["constraints"].items()}))
        if after["n_unfinished"]:  # no outcome to judge them on: re-optimising cannot help
            reason = _unfinished_text(after, spec)
            break
        if after["n_ok"] < MIN_JUDGED:
            reason = (f"{after['n_ok']} verification landing(s) to judge the constraints on: "
                      f"a 95 % interval needs at least {MIN_JUDGED}; raise montecarlo.n")
            break
        short = {k: ch for k, ch in after["constraints"].items() if not ch["judged"]}
        if short:  # a max constraint no violation breaks that these landings cannot confirm
            reason = "; ".join(
                f"{k}: no violation in {ch['n']} verification landings, but the 95 % upper "
                f"bound on its violation probability, {ch['p_violation_upper95']:.3g}, is "
                f"above constraints.{k}.violation_tolerance = {ch['violation_tolerance']:g}: "
                f"a max constraint needs {ch['landings_needed']} landings without a violation; "
                "raise montecarlo.n or the tolerance" for k, ch in short.items())
            break
        if not unmet:
            break
        say(f"verification round {r - 1} (seed {seed}): not met: "
            + ", ".join(_unmet_text(k, after["constraints"][k]) for k in unmet))
        if r > rounds:
            reason = (f"{', '.join(unmet)} not met after {rounds} re-optimisation round(s) "
                      f"(design.verify_rounds)")
            break
        picks: list = []
        for name in unmet:
            ch = after["constraints"][name]
            picks += [i for i in ch["violators"] if i not in picks][:spec.verify_add]
        if not picks:
            reason = (f"{', '.join(unmet)}: not met on the verification landings although none "
                      "of them violates it alone (the measure's tail lies beyond the samples); "
                      "raise montecarlo.n or the constraint's margin")
            break
        trial = added + ((seed, tuple(picks)),)
        problem = DesignProblem(spec, result.baseline, added=trial)
        si = {k: v * VARIABLES[k].to_si for k, v in result.values.items()}  # the last design
        z_prev = problem.to_z(si)
        _, _, per = problem.evaluate(z_prev)
        n_base = spec.n_scenes
        hit = {c.name: int(np.sum(np.asarray(c.badness(
            {k: v[n_base:] for k, v in per.items()},
            float(problem.vehicle_at(jnp.asarray(z_prev)).honeycomb.x_L4))) > 0))
            for c in spec.constraints if c.name in unmet}
        late = [name for name, k in hit.items() if k == 0]
        if late:  # re-optimising on landings that meet the constraint cannot move it
            reason = (f"{', '.join(late)}: the violating verification landings meet the "
                      f"constraint over the design's {spec.t_end:g} s and violate it only later "
                      f"(the verification runs {spec.montecarlo.t_end:g} s): raise "
                      "design.t_end_s")
            break
        say(f"round {r}: re-optimising with {len(picks)} violating landing(s) added "
            f"({sum(len(i) for _, i in trial)} in all, {problem.scenes.sink_speed.shape[0]} "
            "scenes)")
        start_values, verified_last = result.start_values, result
        tagged = None if progress is None else (
            lambda rec, r=r: progress(dict(rec, round=r, of=spec.reoptimise_iterations)))
        result = optimise_design(spec, iterations=spec.reoptimise_iterations, progress=tagged,
                                 problem=problem,
                                 start=si)
        for rec in result.history:  # one numbering over the rounds, as the figure draws them
            rec["round"] = r
            rec["iteration"] += len(history)
        result.best_iteration += len(history)
        history += result.history
        result.start_values = start_values
        vec0, _, per0 = problem.evaluate(problem.z0)
        result.at_start = _summaries(problem, vec0, per0, problem.z0)
        if result.status != "feasible":  # the last verified design stands, not verified
            reason = (f"the re-optimisation of round {r} with {len(picks)} violating "
                      f"landing(s) added found no feasible design; the design of round {r - 1} "
                      "is returned with its verification")
            failed_round = dict(round=r, added_landings=[dict(seed=seed, samples=list(picks))])
            result = verified_last
            break
        added = trial  # the landings the returned design was optimised on
        seed = _fresh_seed(spec, r)
        verify_design(result, n=n, seed=seed, progress=mc_progress, before=False,
                      say=say)
    result.history = history
    ver = result.verification
    if ver is not None:
        if ver["before"] is None:  # the baseline on the same fresh samples as the last round
            vspec = _verification_spec(result.spec, n, ver["seed"])
            result.mc_before = run_montecarlo(
                vspec, result.baseline, share_program=True,
                progress=mc_progress and "verification, before (baseline)")
            _latest_outcomes(vspec, result.mc_before, say)
            ver["before"] = _judge(result.mc_before, result.baseline, spec)
        last = ver["after"]
        ver["verified"] = bool(not reason and result.status == "feasible" and last["met"])
        if not ver["verified"] and reason is None:
            reason = "; ".join(_not_judged(last, spec))
        ver["reason"] = reason
        ver["rounds"] = log
        ver["added_landings"] = [dict(seed=s, samples=list(i)) for s, i in added]
        # a re-optimisation that found no feasible design: its round and the landings it
        # added, which the returned design was not optimised on (None: none failed)
        ver["failed_reoptimisation"] = failed_round
        ver["total_wall_s"] = time.perf_counter() - t0  # every round and verification
    return result

