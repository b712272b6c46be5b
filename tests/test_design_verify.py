"""The design loop that closes on its own verification: a constraint judged on fresh landings
with the optimiser's own risk measure and a bootstrap 95 % interval; when it is not met, the
violating landings join the design scenes and the design is re-optimised until the fresh
landings meet it, or the loop says plainly why it cannot."""
import copy

import numpy as np
import pytest

import jaxland as jl
from jaxland._design._verify import _check, _risk_rows

# Quarter model, two design scenes and a stroke limit that the dispersion's hard landings
# exceed: the design fitted to two scenes fails on fresh ones.
SPEC = dict(
    design=dict(iterations=8, n_scenes=2, scene_seed=3, dt_s=2e-5, t_end_s=0.15,
                learning_rate=0.3, verify_rounds=3, reoptimise_iterations=6, verify_add=3),
    objective=dict(measure="max"),
    variables={"F1_N": dict(low=2000.0, high=8000.0), "x_L2_mm": dict(low=20.0, high=150.0)},
    # 32 fresh landings without a violation bound its probability by 0.107 (95 % Wilson): the
    # tolerance lets a clean verification of that size meet the constraint
    constraints=dict(stroke=dict(margin_mm=100.0, measure="max", violation_tolerance=0.15)),
    montecarlo=dict(n=32, seed=4, dt_s=2e-5, t_end_s=0.15),
    fixed=dict(drop_height_m=0.0),
    dispersion={"sink_speed_mps": dict(dist="uniform", low=1.6, high=2.6),
                "mass_scale": dict(dist="normal", mean=1.0, std=0.05)},
)


@pytest.fixture(scope="module")
def closed():
    rounds = []
    res = jl.design_verified(jl.design_spec_from_dict(copy.deepcopy(SPEC)), say=rounds.append)
    return res, rounds


def test_a_failed_verification_adds_its_violators_and_the_loop_closes(closed):
    res, said = closed
    v = res.verification
    log = v["rounds"]
    assert log[0]["unmet"] == ["stroke"], "the spec must start with a failed verification"
    assert len(log) >= 2 and v["verified"] and v["reason"] is None
    # the landings added in round r are the violators found by round r - 1's verification
    # (at most verify_add of them: round 0 finds 15, a later round may find one)
    for (added, rnd) in zip(v["added_landings"], log):
        assert added["seed"] == rnd["seed"]
        assert 1 <= len(added["samples"]) <= SPEC["design"]["verify_add"]
    assert len(v["added_landings"][0]["samples"]) == SPEC["design"]["verify_add"]
    # each round verifies on fresh samples, never the design scenes' seed
    seeds = [r["seed"] for r in log]
    assert len(set(seeds)) == len(seeds) and SPEC["design"]["scene_seed"] not in seeds
    # the last verification: every fresh landing within the limit, recounted here from the
    # per-sample outcomes of that Monte Carlo
    stroke = res.mc_after.outputs["max_stroke_m"].max(axis=1)
    limit = float(res.vehicle.honeycomb.x_L4) - 0.1
    assert np.all(stroke <= limit) and v["after"]["constraints"]["stroke"]["met"]
    # the baseline is judged on the same fresh samples as the final design
    assert v["before"]["seed"] == v["after"]["seed"] == seeds[-1]
    assert any("re-optimising" in s for s in said)


def test_the_history_runs_across_rounds(closed):
    res, _ = closed
    its = [h["iteration"] for h in res.history]
    assert its == list(range(len(its)))
    assert {h["round"] for h in res.history} == set(range(len(res.verification["rounds"])))
    # the returned iterate in the history's numbering, and the steps taken over the rounds
    # (each round's iteration 0 evaluates the design it starts from)
    assert res.history[res.best_iteration]["values"] == res.values
    rounds = len(res.verification["rounds"])
    assert res.iterations_run == len(its) - rounds == res.report()["iterations"]
    assert res.iterations_run <= (SPEC["design"]["iterations"] + (rounds - 1)
                                  * SPEC["design"]["reoptimise_iterations"])


def test_a_reoptimisation_that_ends_infeasible_returns_the_last_verified_design():
    """Round 0's design is feasible on its 4 scenes and 11 of 40 fresh landings violate a
    tight max stroke limit; 2 re-optimisation steps on the 6 scenes end infeasible. The loop
    returned that infeasible result with no verification at all (its record and its reason
    lost); it returns round 0's design with its verification, not verified, saying why."""
    spec = dict(
        design=dict(iterations=4, n_scenes=4, scene_seed=0, model="quarter", method="verlet",
                    dt_s=8e-5, t_end_s=0.2, learning_rate=0.2, verify_rounds=1, verify_add=2,
                    reoptimise_iterations=2),
        objective=dict(measure="cvar", level=0.5),
        variables={"F1_N": dict(low=2000.0, high=8000.0), "x_L2_mm": dict(low=20.0, high=150.0)},
        constraints=dict(stroke=dict(margin_mm=108.0, measure="max")),
        montecarlo=dict(n=40, seed=1, dt_s=2e-5, t_end_s=0.2),
        fixed=dict(drop_height_m=0.0),
        dispersion={"sink_speed_mps": dict(dist="truncnormal", mean=2.0, std=0.3, low=1.0,
                                           high=3.0)})
    res = jl.design_verified(jl.design_spec_from_dict(spec))
    v = res.verification
    assert res.status == "feasible" and v is not None and not v["verified"]
    assert v["reason"].startswith("the re-optimisation of round 1 with 2 violating landing(s) "
                                  "added found no feasible design")
    # the landings that round added are its own: the returned design never saw them
    assert v["rounds"][0]["unmet"] == ["stroke"] and v["added_landings"] == []
    failed = v["failed_reoptimisation"]
    assert failed["round"] == 1 and len(failed["added_landings"]) == 1
    assert failed["added_landings"][0]["seed"] == v["rounds"][0]["seed"]
    assert len(failed["added_landings"][0]["samples"]) == spec["design"]["verify_add"]
    assert v["after"]["seed"] == v["rounds"][0]["seed"] and v["before"] is not None
    # round 0's design, on round 0's scenes; the failed round stays in the history
    assert res.problem.count == 4 and res.history[res.best_iteration]["round"] == 0
    assert res.history[res.best_iteration]["values"] == res.values
    assert {h["round"] for h in res.history} == {0, 1}


def test_bootstrap_interval_of_the_mean_matches_the_normal_theory():
    """The 95 % bootstrap interval of a mean measure against mean +/- 1.96 s / sqrt(n): a
    planted error (a one-sided interval, the wrong quantiles) moves it by ~s / sqrt(n)."""
    rng = np.random.default_rng(0)
    g = rng.normal(-1.0, 2.0, 400)
    c = jl.DesignSpec.__dataclass_fields__  # noqa: F841  (the spec type exists)
    from jaxland._design._spec import Constraint

    ch = _check(Constraint("stroke", 0.02, measure="mean", scale=1.0), g, np.arange(400), 7)
    half = 1.96 * g.std(ddof=1) / np.sqrt(g.size)
    assert ch["g"] == pytest.approx(g.mean(), abs=1e-12)
    assert ch["ci95"][0] == pytest.approx(g.mean() - half, abs=0.08 * half)
    assert ch["ci95"][1] == pytest.approx(g.mean() + half, abs=0.08 * half)
    assert ch["met"] == (ch["ci95"][1] <= 0)
    assert ch["violators"] == [int(i) for i in np.argsort(-g) if g[i] > 0]


def test_the_binomial_tail_is_the_sum_of_its_terms():
    """The exact one-sided p-value against its definition in rational arithmetic (1 minus the
    terms below k, exact), down to tails of 1e-14, where a float 1 - sum loses every digit."""
    from fractions import Fraction
    from math import comb

    from jaxland._montecarlo._stats import binomial_tail

    for k, n, p in ((0, 10, 0.3), (1, 100, 0.001), (3, 100, 0.001), (2, 160, 0.001),
                    (5, 5, 0.5), (7, 40, 0.2), (11, 10, 0.5), (20, 2000, 0.001),
                    (8, 200, 0.001), (1, 5000, 0.001)):
        q = Fraction(p).limit_denominator(10**6)
        exact = float(1 - sum(comb(n, i) * q**i * (1 - q) ** (n - i) for i in range(k)))
        assert binomial_tail(k, n, p) == pytest.approx(exact, rel=1e-9, abs=1e-300), (k, n, p)


def test_a_normal_measure_is_not_met_where_its_landings_count_more_violations_than_it_allows():
    """A stroke constraint at level 0.999 allows a landing past the limit with probability
    0.001. A normal tail fitted to 200 landings met it while 3 of them were past the limit (a
    heavy right tail): 3 or more of 200 at 0.001 has p = 1.1e-3. The counts decide it; one
    violation in 200 (p = 0.18) leaves the bootstrap's verdict."""
    from jaxland._design._spec import Constraint

    c = Constraint("stroke", 0.02, measure="normal", level=0.999, scale=1.0)
    rng = np.random.default_rng(1)
    body = rng.normal(-60.0, 3.0, 200)  # the normal tail sits far inside the limit
    for k, met in ((3, False), (1, True)):
        g = body.copy()
        g[:k] = 0.5  # k landings just past the limit
        ch = _check(c, g, np.arange(g.size), 3)
        assert ch["n_violating"] == k and ch["violation_allowed"] == pytest.approx(1e-3)
        assert ch["ci95"][1] <= 0.0  # the measure alone would meet it
        assert ch["met"] is met, ch["verdict"]
        assert ch["judged_by"] == ("bootstrap" if met else "violation count")
        if not met:
            assert ch["p_value_violations"] < 0.025
            assert ch["verdict"].startswith(f"not met: {k} of 200 landings violate it")


@pytest.mark.parametrize("measure, level", [("mean", 0.9), ("max", 0.9), ("cvar", 0.8),
                                            ("normal", 0.99)])
def test_numpy_risk_rows_equal_the_optimisers_measure(measure, level):
    v = np.random.default_rng(1).normal(size=(3, 37))
    want = [float(jl.risk_measure(row, measure, level)) for row in v]
    assert _risk_rows(v, measure, level) == pytest.approx(want, rel=1e-12, abs=1e-12)


def test_violations_after_the_design_horizon_are_named_not_looped():
    """A design horizon too short to see the maximum stroke: the violating fresh landings meet
    the constraint over the design's 0.02 s, so re-optimising cannot help; the loop says so."""
    spec = copy.deepcopy(SPEC)
    spec["design"].update(iterations=0, t_end_s=0.02)
    spec["variables"]["F1_N"]["start"] = 2500.0  # soft enough to exceed the limit
    res = jl.design_verified(jl.design_spec_from_dict(spec))
    v = res.verification
    assert not v["verified"] and "design.t_end_s" in v["reason"]
    assert len(v["rounds"]) == 1 and v["added_landings"] == []


def test_design_method_is_the_design_landings_integrator_and_refused_by_name():
    spec = copy.deepcopy(SPEC)
    spec["design"]["method"] = "euler_implicit"
    prob = jl.DesignProblem(jl.design_spec_from_dict(spec))
    assert isinstance(prob.solver.method, jl.EulerImplicit)
    spec["design"]["method"] = "tsit5"  # adaptive: no fixed step to differentiate through
    with pytest.raises(jl.ConfigError, match=r"design\.method = 'tsit5': must be one of"):
        jl.design_spec_from_dict(spec)


@pytest.mark.parametrize("mc_seed,scene_seed", [(1, 2), (4, 3), (0, 7), (6, 8),
                                                 (2**31 - 3, 1), (2**31 - 2, 2**31 - 1)])
def test_verification_rounds_draw_distinct_seeds_never_the_scenes(mc_seed, scene_seed):
    """Every round verifies on samples no earlier round saw and that are not the design
    scenes' (a seed that skipped the scenes' once gave rounds 1 and 2 the same samples)."""
    from jaxland._design._spec import design_spec_from_dict
    from jaxland._design._verify import _fresh_seed

    data = copy.deepcopy(SPEC)
    data["montecarlo"]["seed"], data["design"]["scene_seed"] = mc_seed, scene_seed
    spec = design_spec_from_dict(data)
    seeds = [_fresh_seed(spec, r) for r in range(6)]
    assert len(set(seeds)) == 6 and scene_seed not in seeds, seeds
    assert seeds[0] == mc_seed
    # a spec's largest seeds too: past it the rounds go on from 0, each a seed a spec may
    # give (one past it was refused, naming a seed the file never held, once a round ran)
    assert all(0 <= s <= 2**31 - 1 for s in seeds), seeds
    jl.MonteCarloSpec(dispersion=spec.montecarlo.dispersion, n=4, seed=max(seeds))


def _cut_short_verification(t_end):
    """Quarter-model verification landings at 2.0-2.6 m/s, as in SPEC: at ``t_end`` = 0.04 s
    every one is still compressing its strut."""
    return jl.MonteCarloSpec(dispersion={"sink_speed_mps": jl.Distribution("uniform", low=2.0,
                                                                          high=2.6)},
                             fixed={"drop_height_m": 0.0}, n=6, seed=5, dt=2e-5, t_end=t_end,
                             model="quarter")


def test_cut_off_verification_landings_are_continued_to_their_final_outcomes():
    """A verification landing that t_end_s cuts off in its impact is run on (3 x, then 9 x
    t_end_s) and judged on the outcomes of a Monte Carlo run that long from the start."""
    from jaxland._design._verify import CONTINUE_FACTORS, _latest_outcomes
    from jaxland._montecarlo import run_montecarlo

    short = _cut_short_verification(0.04)
    res = run_montecarlo(short, progress=False, share_program=True)
    assert res.summary["n_unfinished"] == short.n, "the scene must cut every landing off"
    log = _latest_outcomes(short, res)
    assert [c["t_end_s"] for c in log] == pytest.approx([0.04 * f for f in CONTINUE_FACTORS])
    assert res.summary["n_unfinished"] == 0 and log[-1]["n_unfinished_after"] == 0
    longest = run_montecarlo(_cut_short_verification(0.04 * CONTINUE_FACTORS[-1]),
                             progress=False)
    ran_long = np.isclose(res.outputs["t_end_s"], 0.04 * CONTINUE_FACTORS[-1], rtol=1e-12)
    assert ran_long.any()
    for key in ("max_stroke_m", "peak_body_accel_mps2", "peak_strut_force_N"):
        assert res.outputs[key][ran_long] == pytest.approx(longest.outputs[key][ran_long],
                                                           rel=1e-9)
    assert np.all(res.failure == longest.failure)


def test_the_t_end_checks_landings_are_judged_on_their_longer_run():
    """A landing called finished at t_end_s may crush further later: cut at 0.37 s, 0.2 m
    drops are on their rebound, a foot in the air. The verification judges the t_end check's
    landings (here 3 of 4) on their outcomes at twice t_end_s, sample by sample those of a
    Monte Carlo run that long from the start; the unchecked landing keeps its own."""
    import dataclasses

    from jaxland._design._verify import _latest_outcomes
    from jaxland._montecarlo import run_montecarlo

    spec = jl.MonteCarloSpec(dispersion={"mass_scale": jl.Distribution("normal", 1.0, 0.03)},
                             fixed={"drop_height_m": 0.2}, n=4, seed=3, t_end=0.37, dt=1e-4,
                             t_end_check=3, model="quarter")
    res = run_montecarlo(spec, progress=False, share_program=True)
    assert res.summary["t_end_check"]["changed_samples"] == [0, 1, 2]
    at_t_end = {k: v.copy() for k, v in res.outputs.items()}
    assert _latest_outcomes(spec, res) == []  # none unfinished at 0.74 s
    longer = run_montecarlo(dataclasses.replace(spec, t_end=0.74, t_end_check=0),
                            progress=False)
    np.testing.assert_array_equal(res.outputs["t_end_s"], [0.74, 0.74, 0.74, 0.37])
    assert np.all(res.outputs["max_stroke_m"][:3] > at_t_end["max_stroke_m"][:3])
    for key, v in longer.outputs.items():
        np.testing.assert_allclose(res.outputs[key][:3], v[:3], rtol=1e-9, err_msg=key)
        np.testing.assert_array_equal(res.outputs[key][3], at_t_end[key][3], err_msg=key)
    np.testing.assert_array_equal(res.failure, longer.failure)
    key = "max_stroke_m (any leg)"  # the summary is made again from the outcomes judged
    assert res.summary["envelopes"][key]["max"] == pytest.approx(
        res.outputs["max_stroke_m"].max(), rel=1e-12)
    assert res.summary["envelopes"][key]["max"] > at_t_end["max_stroke_m"].max()


def test_a_continuation_that_fails_numerically_is_retried(monkeypatch):
    """A continued landing that fails numerically is rerun as the Monte Carlo reruns its own
    failures (with the damping implicit): its outcomes are those of a Monte Carlo of that
    method and step run as long from the start, not a failure of the verification."""
    import dataclasses

    from jaxland._design import _verify
    from jaxland._montecarlo import run_montecarlo

    program, calls = _verify._continued_program, []

    def failing_first(solver, model):  # the first landing of the first continuation "fails"
        run = program(solver, model)

        def wrapped(vehicle, scenes):
            out = dict(run(vehicle, scenes))
            if not calls:
                out["result"] = out["result"].at[0].set(int(jl.Result.NONFINITE))
            calls.append(1)
            return out
        return wrapped

    monkeypatch.setattr(_verify, "_continued_program", failing_first)
    short = _cut_short_verification(0.04)
    res = run_montecarlo(short, progress=False, share_program=True)
    log = _verify._latest_outcomes(short, res)
    assert log[0]["n_retried"] == 1 and np.all(res.failure == int(jl.Result.SUCCESSFUL))
    assert res.outputs["retried"][0] and not res.outputs["retried"][1:].any()
    t_end, dt = float(res.outputs["t_end_s"][0]), float(res.outputs["dt_s"][0])
    alone = run_montecarlo(dataclasses.replace(short, t_end=t_end, dt=dt,
                                               method="euler_implicit"), progress=False)
    for key in ("max_stroke_m", "peak_body_accel_mps2", "peak_strut_force_N"):
        assert res.outputs[key][0] == pytest.approx(alone.outputs[key][0], rel=1e-9), key


def test_a_landing_no_continuation_finishes_fails_the_verification(monkeypatch):
    """Without the continuations the cut-off landings stay unfinished: their numbers are not
    judged as outcomes, and the verification is not met, for a reason that says so."""
    from jaxland._design import _verify

    monkeypatch.setattr(_verify, "CONTINUE_FACTORS", ())
    spec = copy.deepcopy(SPEC)
    spec["design"].update(iterations=0, verify_rounds=0)
    spec["montecarlo"].update(n=4, t_end_s=0.04)
    spec["constraints"]["stroke"]["margin_mm"] = 10.0
    res = jl.design_verified(jl.design_spec_from_dict(spec))
    v = res.verification
    assert v["after"]["n_unfinished"] == 4 and v["after"]["n_ok"] == 0
    assert not v["after"]["met"] and not v["verified"]
    assert "not final" in v["reason"]


@pytest.mark.parametrize("measure", ["max", "mean", "cvar", "normal"])
def test_too_few_verification_landings_meet_no_constraint(measure):
    """A bootstrap of a handful of landings is no 95 % interval (at one landing, the landing
    itself): below MIN_JUDGED no constraint is met, however far inside its limit, and the
    loop says why instead of re-optimising."""
    from jaxland._design._spec import Constraint
    from jaxland._design._verify import MIN_JUDGED

    # max: 20 landings without a violation bound its probability by 0.161 (95 % Wilson)
    c = Constraint("stroke", 0.02, measure=measure, level=0.9, scale=1.0,
                   violation_tolerance=0.2)
    well_inside = -5.0 + 0.1 * np.random.default_rng(1).standard_normal(MIN_JUDGED)
    few = _check(c, well_inside[:MIN_JUDGED - 1], np.arange(MIN_JUDGED - 1), 3)
    assert not few["met"] and few["ci95"] == [None, None] and few["g"] < 0
    enough = _check(c, well_inside, np.arange(MIN_JUDGED), 3)
    assert enough["met"] and enough["ci95"][1] < 0


def test_a_verification_of_one_landing_is_not_verified_and_says_so():
    spec = copy.deepcopy(SPEC)
    spec["design"].update(iterations=0, verify_rounds=2)
    spec["montecarlo"].update(n=1)
    spec["constraints"]["stroke"]["margin_mm"] = 10.0
    res = jl.design_verified(jl.design_spec_from_dict(spec))
    v = res.verification
    assert not v["verified"] and "at least 20" in v["reason"]
    assert len(v["rounds"]) == 1 and v["added_landings"] == []


def test_one_unfinished_landing_among_enough_judged_ones_fails_the_verification():
    """25 landings well inside the stroke limit meet it; one more landing still unfinished
    after the continuations leaves the verification not met (its outcome is unknown)."""
    from types import SimpleNamespace

    from jaxland._design._verify import _judge
    from jaxland._solvers import Result

    spec = jl.design_spec_from_dict(copy.deepcopy(SPEC))
    veh = jl.paper_vehicle()
    n = 26
    outputs = dict(max_stroke_m=np.full((n, 1), 0.05), peak_body_accel_mps2=np.full(n, 20.0),
                   slip_distance_m=np.zeros((n, 1)), tipped_over=np.zeros(n, bool),
                   bottomed_out=np.zeros(n, bool))

    def judged(last_code):
        failure = np.zeros(n, int)
        failure[-1] = last_code
        res = SimpleNamespace(failure=failure, outputs=outputs, summary=dict(
            n_unfinished=int((failure == int(Result.UNFINISHED)).sum()), n_failed=0,
            failures={}, seed=1, model="quarter", wall_s=0.0, continued=[]))
        return _judge(res, veh, spec)

    assert judged(int(Result.SUCCESSFUL))["met"]
    cut = judged(int(Result.UNFINISHED))
    assert cut["constraints"]["stroke"]["met"] and cut["n_unfinished"] == 1
    assert not cut["met"]


def _wilson_upper(k, n, z=1.959963984540054):
    """The 95 % Wilson upper bound from its definition: the larger root p of
    (k/n - p)^2 = z^2 p (1 - p) / n (1 at k = n)."""
    if k == n:
        return 1.0
    p_hat, a = k / n, z * z / n
    roots = np.roots([1.0 + a, -(2.0 * p_hat + a), p_hat * p_hat])
    return float(np.max(roots.real))


def test_a_max_constraint_without_violations_in_too_few_landings_is_not_judged():
    """The bootstrap interval of a sample maximum never exceeds the largest value observed, so
    it called 40 clean landings "met"; their violation probability is only bounded by 8.8 %
    (95 % Wilson). Judged by the bound against violation_tolerance (default 1 %): not judged,
    the bound and the landings needed stated; through the loop, not verified, saying why."""
    from jaxland._design._spec import Constraint

    g = -5.0 + 0.1 * np.random.default_rng(2).standard_normal(40)
    ch = _check(Constraint("stroke", 0.02, measure="max", scale=1.0), g, np.arange(40), 3)
    assert ch["ci95"][1] <= 0.0  # what the bootstrap alone would have called met
    assert not ch["met"] and not ch["judged"] and ch["judged_by"] == "violation bound"
    assert ch["n_violating"] == 0 and ch["violation_tolerance"] == 0.01
    assert ch["p_violation_upper95"] == pytest.approx(_wilson_upper(0, 40), rel=1e-12)
    assert ch["p_violation_upper95"] == pytest.approx(0.0876, abs=5e-5)
    assert ch["g"] == pytest.approx(g.max(), rel=1e-12)  # the observed maximum
    assert "0 of 40 landings violate it" in ch["verdict"] and "0.0876" in ch["verdict"]
    assert "needs 381 landings" in ch["verdict"]

    spec = copy.deepcopy(SPEC)
    spec["design"].update(iterations=0, verify_rounds=2)
    spec["montecarlo"].update(n=40)
    spec["constraints"]["stroke"] = dict(margin_mm=10.0, measure="max")  # default tolerance
    res = jl.design_verified(jl.design_spec_from_dict(spec))
    v = res.verification
    stroke = v["after"]["constraints"]["stroke"]
    assert stroke["n_violating"] == 0 and v["after"]["constraint_violations"]["stroke"][
        "count"] == 0
    assert not v["verified"] and len(v["rounds"]) == 1 and v["added_landings"] == []
    assert ("no violation in 40 verification landings" in v["reason"]
            and "0.0876" in v["reason"] and "violation_tolerance = 0.01" in v["reason"]
            and "381" in v["reason"] and "montecarlo.n" in v["reason"])
    assert v["rounds"][0]["judged_by"]["stroke"] == "violation bound"


def test_a_max_constraint_is_met_by_enough_clean_landings_and_broken_by_one_violation():
    """At violation_tolerance 1 %, 381 landings without a violation bound the probability by
    0.998 % (met), 380 by 1.0005 % (not judged); one violation in 1000 is not met, whatever
    its bound (0.56 %): a maximum past the limit was observed."""
    from jaxland._design._spec import Constraint
    from jaxland._design._verify import clean_landings_needed

    c = Constraint("stroke", 0.02, measure="max", scale=1.0)
    g = -5.0 + 0.1 * np.random.default_rng(3).standard_normal(1000)
    met = _check(c, g[:381], np.arange(381), 3)
    assert met["met"] and met["judged"] and met["p_violation_upper95"] <= 0.01
    short = _check(c, g[:380], np.arange(380), 3)
    assert not short["met"] and not short["judged"] and short["p_violation_upper95"] > 0.01
    # the fewest clean landings for a tolerance, against a direct search of the definition
    for tol in (0.2, 0.05, 0.01, 0.003):
        first = next(n for n in range(1, 10**5) if _wilson_upper(0, n) <= tol)
        assert clean_landings_needed(tol) == first, tol
    assert clean_landings_needed(0.01) == 381
    one = g.copy()
    one[17] = 0.4
    broken = _check(c, one, np.arange(1000), 3)
    assert not broken["met"] and broken["judged"] and broken["n_violating"] == 1
    assert broken["p_violation_upper95"] == pytest.approx(_wilson_upper(1, 1000), rel=1e-9)
    assert broken["violators"] == [17] and broken["g"] == pytest.approx(0.4)


@pytest.mark.parametrize("k,n", [(0, 20), (0, 300), (3, 40), (12, 50), (50, 50)])
def test_the_violation_bound_is_the_wilson_upper_bound(k, n):
    from jaxland._design._spec import Constraint

    g = np.full(n, -1.0)
    g[:k] = 0.5
    ch = _check(Constraint("stroke", 0.02, measure="max", scale=1.0), g, np.arange(n), 3)
    assert ch["n_violating"] == k
    assert ch["p_violation_upper95"] == pytest.approx(_wilson_upper(k, n), rel=1e-9, abs=1e-15)
    if k == 0:  # the closed form at no violation, z^2 / (n + z^2)
        z2 = 1.959963984540054**2
        assert ch["p_violation_upper95"] == pytest.approx(z2 / (n + z2), rel=1e-12)


@pytest.mark.parametrize("extra,line", [
    ("violation_tolerance = 0.0", "constraints.stroke.violation_tolerance = 0.0: must be in "
                                  "(0, 1)"),
    ("violation_tolerance = 1.0", "constraints.stroke.violation_tolerance = 1.0: must be in "
                                  "(0, 1)"),
    ('violation_tolerance = "1%"', "constraints.stroke.violation_tolerance = '1%': must be a "
                                   "finite number"),
    ('violation_tolerance = 0.05\nmeasure = "cvar"',
     'constraints.stroke.violation_tolerance = 0.05: applies to measure = "max" only'),
])
def test_a_bad_violation_tolerance_exits_2_in_one_line(tmp_path, capsys, extra, line):
    from jaxland.cli import main

    path = tmp_path / "spec.toml"
    path.write_text(f"""
[design]
n_scenes = 2
scene_seed = 3
t_end_s = 0.15
[variables.F1_N]
low = 2000.0
high = 8000.0
[constraints.stroke]
margin_mm = 10.0
{extra}
[montecarlo]
seed = 4
t_end_s = 0.15
[fixed]
drop_height_m = 0.0
[dispersion.sink_speed_mps]
dist = "uniform"
low = 1.6
high = 2.6
""")
    assert main(["design", str(path), "--out", str(tmp_path / "o"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and line in err, err
    good = copy.deepcopy(SPEC)
    good["constraints"]["stroke"]["violation_tolerance"] = 0.05
    assert jl.design_spec_from_dict(good).constraints[0].violation_tolerance == 0.05


def test_the_verification_records_whether_its_outcomes_at_t_end_are_final(closed):
    """The verification Monte Carlo's t_end check (run_montecarlo: finished landings rerun to
    twice t_end_s) is kept in each side's judgement, across the continuation of the unfinished
    landings, so the command can say when the constraints were judged on outcomes that still
    change after t_end_s."""
    res, _ = closed
    for side in ("before", "after"):
        check = res.verification[side]["t_end_check"]
        assert check is not None and check["t_end_s"] == pytest.approx(2 * 0.15)
        assert 0 < check["n_checked"] <= 32 and check["n_rerun_failed"] == 0
        assert check["n_changed"] == len(check["changed_samples"])
