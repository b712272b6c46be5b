"""Mutation check: plant small deliberate bugs in a scratch copy and see which tests catch them.

    .venv/bin/python benchmarks/mutation_check.py                  # all mutations -> JSON on stdout
    .venv/bin/python benchmarks/mutation_check.py --only wilson_centre_p design_stability_sign
    .venv/bin/python benchmarks/mutation_check.py --list
    .venv/bin/python benchmarks/mutation_check.py --only damping_sign --tests tests/test_quarter.py
    .venv/bin/python benchmarks/mutation_check.py --out /tmp/mutations.json --source HEAD

Run on demand, not part of the timed suite (a full pass takes several minutes: each mutation
reruns its test files). Never touches the repository: the working tree (``--source worktree``,
the default, uncommitted files included) or a commit (``--source HEAD``, through ``git
archive``) is copied into a scratch folder under /tmp, each mutation is an exact string
replacement there, and the tests run from the scratch copy (``PYTHONPATH`` puts its packages
first, ahead of the editable install).

A mutation finds its target by searching for the code string across its search folders
(``jaxland/`` unless stated), not by a fixed path, so it survives files moving; where the code
was rewritten, a mutation may list the other spellings it accepts (``also``). Outcomes:
- ``killed``: some test of its files failed (the bug was caught);
- ``survived``: every test passed with the bug in place;
- ``target not found``: the code string is nowhere (the code changed: update the mutation);
- ``ambiguous target``: it occurs more than once (make the string longer);
- ``baseline failed``: its test files fail without any mutation, so the run says nothing;
- ``timeout``.
The exit code is 1 if any mutation survived, 0 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    name: str
    what: str  # the bug, in words
    find: str  # exact code string
    replace: str
    tests: tuple  # pytest targets (files or node ids), relative to the repository
    search: tuple = ("jaxland",)
    also: tuple = ()  # other (find, replace) spellings of the same code, tried in turn


M = Mutation
MUTATIONS = [
    # --- issue 15's list: statistics, calibration errors, design, stability margin
    M("wilson_no_z2_4n2", "Wilson half-width without its z^2/4n^2 term",
      "p * (1 - p) / n + z * z / (4 * n * n)", "p * (1 - p) / n",
      ("tests/test_statistics.py",)),
    M("wilson_centre_p", "Wilson interval centred on k/n (Wald-like)",
      "centre = (p + z * z / (2 * n)) / den", "centre = p",
      ("tests/test_statistics.py",)),
    M("calibration_se_x_sqrt2", "calibration standard errors x sqrt(2)",
      "se = np.sqrt(np.diag(cov_p))", "se = np.sqrt(2.0 * np.diag(cov_p))",
      ("tests/test_calibration_coverage.py",), ("calibration",)),
    M("calibration_se_x2", "calibration standard errors x 2",
      "se = np.sqrt(np.diag(cov_p))", "se = 2.0 * np.sqrt(np.diag(cov_p))",
      ("tests/test_calibration_coverage.py",), ("calibration",)),
    M("calibration_se_div_sqrt2", "calibration standard errors / sqrt(2)",
      "se = np.sqrt(np.diag(cov_p))", "se = np.sqrt(0.5 * np.diag(cov_p))",
      ("tests/test_calibration_coverage.py",), ("calibration",)),
    M("design_stroke_sign", "design stroke constraint with its sign flipped",
      "return value - (x_L4 - self.threshold)", "return (x_L4 - self.threshold) - value",
      ("tests/test_design_constraints.py",)),
    M("design_stability_sign", "design stability constraint with its sign flipped",
      "return self.threshold - value", "return value - self.threshold",
      ("tests/test_design_constraints.py",)),
    M("design_slip_sign", "design slip constraint with its sign flipped",
      "return value - self.threshold\n", "return self.threshold - value\n",
      ("tests/test_design_constraints.py",)),
    M("margin_softmin_x10", "stability margin soft-min width x 10",
      "MARGIN_SOFTNESS_M = 0.01", "MARGIN_SOFTNESS_M = 0.1", ("tests/test_tipover.py",)),
    M("margin_projected_along_normal", "CoM projected along the ground normal, not gravity",
      "p1, p2 = t1 - n_g * (t1[2] / n_g[2]), t2 - n_g * (t2[2] / n_g[2])", "p1, p2 = t1, t2",
      ("tests/test_tipover.py",)),
    M("inertia_x4", "body inertia x 4 in the 3-D dynamics",
      "jnp.stack([vehicle.I_xx, vehicle.I_yy, vehicle.I_zz])",
      "4.0 * jnp.stack([vehicle.I_xx, vehicle.I_yy, vehicle.I_zz])",
      ("tests/test_tipover.py",)),
    M("smoothing_leaks_at_width_0", "width 0 runs the contact law smoothed over 1 um anyway",
      "    if smooth == 0.0:\n        d_max = fmax(d, d_max_prev)",
      "    smooth = smooth or 1e-6\n"
      "    if smooth == 0.0:\n        d_max = fmax(d, d_max_prev)",
      ("tests/test_reference_trajectory.py",)),
    # --- the physics ones the issue lists as caught; pinned here so they stay caught
    M("damping_sign", "structural damping with its sign flipped",
      "f_raw = F_bh + D_b * v_b * jnp.abs(F_bh)", "f_raw = F_bh - D_b * v_b * jnp.abs(F_bh)",
      ("tests/test_laws.py", "tests/test_reference_trajectory.py")),
    M("restitution_stiffness", "restitution stiffness k (1 - gamma) instead of k / (1 - gamma)",
      "return self.k / (1.0 - self.gamma)", "return self.k * (1.0 - self.gamma)",
      ("tests/test_laws.py", "tests/test_reference_trajectory.py")),
    M("friction_cone_x2", "friction limit 2 mu F_n",
      "limit = ground.mu * normal_force", "limit = 2.0 * ground.mu * normal_force",
      ("tests/test_laws.py", "tests/test_reference_trajectory.py")),
    M("plateau_onset", "primary crush starts at 2 x_L1",
      "p1 = fclip(x_max - hc.x_L1, 0.0, hc.x_L2 - hc.x_L1)",
      "p1 = fclip(x_max - 2.0 * hc.x_L1, 0.0, hc.x_L2 - hc.x_L1)",
      ("tests/test_laws.py", "tests/test_quarter.py::test_paper_table_predictions_are_pinned")),
    M("quaternion_order", "body-rate update applied in the space frame",
      "quat = quat_mul(quat, _quat_exp(0.5 * dt * w_b))",
      "quat = quat_mul(_quat_exp(0.5 * dt * w_b), quat)",
      ("tests/test_vehicle3d.py", "tests/test_reference_trajectory.py")),
    M("gyroscopic_sign", "gyroscopic term with its sign flipped",
      "torque_b - jnp.cross(w_b, inertia * w_b)", "torque_b + jnp.cross(w_b, inertia * w_b)",
      ("tests/test_vehicle3d.py", "tests/test_reference_trajectory.py")),
    # --- the honeycomb law's new crush peak (its tests are the law's owner's: test_crush_peak.py)
    M("crush_peak_position", "crush-peak position x_L1 + 2 a1 / k_b1",
      "x_pk1=x_L1 + a1 / self.k_b1", "x_pk1=x_L1 + 2.0 * a1 / self.k_b1",
      ("tests/test_laws.py", "tests/test_crush_peak.py")),
    M("table_rise_half_slope", "a crush peak's build-up over peak_rise1 at half its slope",
      "_cat(jnp.expand_dims(a1, -1) / rise, slope))",
      "_cat(0.5 * jnp.expand_dims(a1, -1) / rise, slope))",
      ("tests/test_crush_peak.py",
       "tests/test_calibration_form.py::test_the_shared_table_lands_as_each_forms_own_vehicle")),
    M("rise_exp_bound_without_span", "the built-up exponential's rise bounded as if its decay "
      "were L_peak1 long", "- _span(form) * v(\"L_peak1\") - m * hc.x_L2\n",
      "- v(\"L_peak1\") - m * hc.x_L2\n",
      ("tests/test_calibration_form.py::"
       "test_the_built_up_exp_forms_rise_is_bounded_by_its_own_tables_room",), ("calibration",)),
    M("smooth_rise_bound_as_linear", "the smooth form's build-up bounded as if it were the "
      "linear rise (a / k_b1)", "math.e * a * lp / den * (1.0 + m)", "a / v(\"k_b1\") * (1.0 + m)",
      ("tests/test_calibration_form.py::test_the_smooth_forms_build_up_stays_below_k_b1",),
      ("calibration",)),
    M("smooth_den_floor_tiny", "the smooth form's rise-bound divisor floored at 1e-300 (its "
      "derivative is 0 * inf where another form is selected)",
      "0.5 * v(\"k_b1\") * lp)", "1e-300)",
      ("tests/test_calibration_form.py::"
       "test_the_smooth_forms_bounds_stay_open_and_differentiable_on_stiff_ground",),
      ("calibration",)),
    M("smooth_peak_bound_without_floor", "peak1's upper bound in the smooth form, L_peak1 "
      "held, without its floor on L_peak1 (2 e a / k_b1)",
      "jnp.minimum(a_hi, L / smooth * (1.0 - m))", "a_hi",
      ("tests/test_calibration_form.py::"
       "test_the_smooth_forms_bounds_stay_open_and_differentiable_on_stiff_ground",),
      ("calibration",)),
    M("smooth_fitted_peak_bound_without_floor", "peak1's upper bound in the smooth form, "
      "L_peak1 fitted, without its floor on L_peak1 (2 e a / k_b1)",
      "span * jnp.maximum(2.0 / v(\"k\"), smooth)", "span * 2.0 / v(\"k\")",
      ("tests/test_calibration_form.py::"
       "test_the_smooth_forms_bounds_stay_open_and_differentiable_on_stiff_ground",),
      ("calibration",)),
    M("smooth_top_without_factor", "the smooth form's top without its 1 / (1 + r)",
      "return jnp.exp(r * jnp.log(r / (1.0 + r))) / (1.0 + r)",
      "return jnp.exp(r * jnp.log(r / (1.0 + r)))",
      ("tests/test_calibration_form.py::test_the_smooth_form_builds_up_from_zero_to_its_height",),
      ("calibration",)),
    M("form_caveat_where_form_plausible", "the CLI's shape caveat wherever the fitted form is "
      "plausible, also where other forms widen the interval",
      'model_form["plausible"] != [model_form["form"]]',
      'model_form["form"] not in model_form["plausible"]',
      ("tests/test_calibration_form.py::"
       "test_the_caveat_names_a_form_that_is_the_only_one_supported",), ("calibration",)),
    M("peak_location_step_sign", "the motion-only Gauss-Newton step taken uphill",
      "step[keep] = -(inv @ (js.T @ r)) / col[keep]", "step[keep] = (inv @ (js.T @ r)) / col[keep]",
      ("tests/test_calibration_form.py::"
       "test_a_peak_in_the_force_channels_only_is_told_from_the_honeycombs",), ("calibration",)),
    M("motion_rows_force", "the peak's location and the peak site's check read on the force "
      "channels instead of the motion",
      "motion = np.array([base_channel(c) in PEAK_MOTION_CHANNELS for c in problem.channels])",
      "motion = np.array([base_channel(c) in PEAK_FORCE_CHANNELS for c in problem.channels])",
      ("tests/test_calibration_form.py::"
       "test_a_peak_in_the_force_channels_only_is_told_from_the_honeycombs",
       "tests/test_calibration_site.py::"
       "test_a_fit_on_the_forces_says_so_and_its_vehicle_has_no_peak"), ("calibration",)),
    M("peak_site_dynamics", "a peak on the force channels run in the honeycomb too",
      'traj, summary = jl.landings(_without_primary_peak(veh), scenes, solver, "quarter")',
      'traj, summary = jl.landings(veh, scenes, solver, "quarter")',
      ("tests/test_calibration_site.py::"
       "test_a_peak_on_the_force_channels_moves_no_motion_channel",), ("calibration",)),
    M("peak_site_no_gain", "a peak on the force channels left out of them",
      "ys = jnp.where(on_forces[None, :, None], ys * gain[:, None, :], ys)", "ys = ys",
      ("tests/test_calibration_site.py::"
       "test_a_peak_on_the_force_channels_moves_no_motion_channel",), ("calibration",)),
    M("peak_site_gain_sign", "the force channels' gain below 1 where the peak is",
      "return 1.0 + jnp.where(plastic_set_m > 0.0, excess, 0.0) / hc.F1",
      "return 1.0 - jnp.where(plastic_set_m > 0.0, excess, 0.0) / hc.F1",
      ("tests/test_calibration_site.py::"
       "test_the_gain_follows_the_peak_over_the_crush_and_is_one_past_it",), ("calibration",)),
    M("peak_site_gain_before_crush", "a peak on the force channels there before the crush",
      "return 1.0 + jnp.where(plastic_set_m > 0.0, excess, 0.0) / hc.F1",
      "return 1.0 + excess / hc.F1",
      ("tests/test_calibration_site.py::"
       "test_the_gain_follows_the_peak_over_the_crush_and_is_one_past_it",), ("calibration",)),
    M("peak_site_bounds_ignored", "a peak on the force channels bound by the honeycomb's rules",
      "if site == FORCES and n in SHAPE_PARAMS:", "if False:",
      ("tests/test_calibration_site.py::"
       "test_a_peak_on_the_forces_is_bound_by_the_plateaus_room_only",), ("calibration",)),
    M("lm_atol_ignored", "the optimiser's absolute loss tolerance ignored",
      "if rel < ftol or decrease < atol or", "if rel < ftol or",
      ("tests/test_calibration_site.py::"
       "test_the_forces_refits_stop_once_the_loss_stops_moving",), ("calibration",)),
    M("peak_excess_segment_off_by_one", "the gain read at the segment before the crush's",
      "_primary_table(_crushed(ci, 0.0, hc.L1), hc, 0.0)[0])(c)",
      "_primary_table(_crushed(ci, 0.0, hc.L1) - 1e-4, hc, 0.0)[0])(c)",
      ("tests/test_calibration_site.py::"
       "test_the_gain_reads_every_peak_form_as_its_table_does",)),
    M("multistart_keeps_discarded_starts", "a batch of starts kept whole, past the agreeing one",
      "        for i, f in enumerate(futures):\n            candidates.append(f.result())\n"
      "            if _starts_agree(candidates):\n",
      "        candidates += [f.result() for f in futures]\n"
      "        for i in range(len(futures)):\n            if _starts_agree(candidates):\n",
      ("tests/test_calibration_optim.py",), ("calibration",)),
    # --- verdicts and output folders a new user's review found wanting
    M("unfinished_never", "a landing cut off during its impact passes as successful",
      "    cut = ((unfinished(ev_end.record) | model.could_still_tip",
      "    cut = ((unfinished(ev_end.record) & False | model.could_still_tip",
      ("tests/test_contracts.py::test_a_landing_cut_off_during_its_impact_is_unfinished_not_stable",)),
    M("envelope_keeps_derivatives", "a scene outside the envelope keeps finite derivatives",
      "    failed = jnp.isin(code, jnp.asarray(FAILED_CODES, code.dtype))",
      "    failed = jnp.isin(verdict(summary, vehicle, solver, model),\n"
      "                      jnp.asarray(FAILED_CODES, code.dtype))",
      ("tests/test_contracts.py::"
       "test_a_scene_the_model_cannot_take_fails_with_nan_derivatives_also_under_jit",)),
    M("out_ignores_hidden_entries", "a folder of hidden entries only is replaced",
      "p.name not in DESKTOP_FILES for p in out.iterdir()",
      "p.name not in DESKTOP_FILES and not p.name.startswith('.') for p in out.iterdir()",
      ("tests/test_contracts.py::test_a_folder_without_the_marker_is_refused_whatever_it_holds",)),
    M("dispersion_bounds_outside_accepted", "bounds reaching outside the envelope pass the spec",
      "    if a < lo or b > hi:\n", "    if False:\n",
      ("tests/test_montecarlo.py::test_bad_specs_are_refused_by_name",)),
    M("landing_skips_vehicle_check", "the pure landing runs an invalid concrete vehicle",
      "integrate(get_model(model, scene), validate_vehicle(vehicle, fields_only=True),",
      "integrate(get_model(model, scene), vehicle,",
      ("tests/test_contracts.py::test_the_pure_landing_checks_the_vehicle_values_it_can_see",)),
    M("traced_vehicle_unchecked", "a traced vehicle outside a field's rule runs as valid",
      "    code = jnp.where(follows_rules(vehicle), code,",
      "    code = jnp.where(True, code,",
      ("tests/test_contracts.py::test_the_pure_landing_checks_the_vehicle_values_it_can_see",)),
    M("tip_energy_ignored", "a 3-D landing that can still tip over passes as decided",
      "return TIP_ENERGY_SAFETY * available >= vehicle.m_body * vehicle.g * rise",
      "return available < 0.0",
      ("tests/test_contracts.py::"
       "test_a_3d_landing_that_can_still_tip_over_is_unfinished_not_upright",)),
    M("fresh_seed_repeats", "a verification round reuses the samples of the round before",
      "    if (spec.scene_seed - first) % span <= round_:",
      "    if (spec.scene_seed - first) % span == round_:",
      ("tests/test_design_verify.py::"
       "test_verification_rounds_draw_distinct_seeds_never_the_scenes",)),
    M("vehicle_header_classical", "the fitted vehicle's header gives the classical errors",
      "for n, v, s, ok, v0 in zip(self.names, self.values, errors,",
      "for n, v, s, ok, v0 in zip(self.names, self.values, self.std_errors,",
      ("tests/test_calibration_honesty.py::"
       "test_a_missing_peak_widens_the_total_to_the_fit_with_the_peak",), ("calibration",)),
    M("worse_peak_fit_used", "a refit with the peak that ends worse still adds its shift",
      "if not chi2_nested <= chi2_own * (1.0 + NESTED_CHI2_RTOL):", "if False:",
      ("tests/test_calibration_honesty.py::"
       "test_a_fit_with_the_peak_that_ends_worse_than_without_it_is_named_failed",),
      ("calibration",)),
    M("metadata_files_not_inputs", "an output folder holding a drop test's traces is replaced",
      "_out_dir(args.out, [f for d in drops for f in d.files])  # the files the metadata named\n"
      "    windows",
      "windows",
      ("tests/test_contracts.py::"
       "test_fit_and_predict_refuse_an_output_folder_holding_a_file_the_metadata_names",),
      ("calibration",)),
    M("unfinished_verification_judged", "verification landings cut off at t_end are judged "
      "on their numbers", "    ok = res.failure == int(Result.SUCCESSFUL)\n",
      "    ok = np.isin(res.failure, [int(Result.SUCCESSFUL), int(Result.UNFINISHED)])\n",
      ("tests/test_design_verify.py::"
       "test_a_landing_no_continuation_finishes_fails_the_verification",)),
    M("verification_not_continued", "verification landings cut off at t_end are not run on",
      "CONTINUE_FACTORS = (3.0, 9.0)", "CONTINUE_FACTORS = ()",
      ("tests/test_design_verify.py::"
       "test_cut_off_verification_landings_are_continued_to_their_final_outcomes",)),
    M("bootstrap_of_one_landing", "a verification of one landing meets its constraints",
      "MIN_JUDGED = 20", "MIN_JUDGED = 1",
      ("tests/test_design_verify.py::test_too_few_verification_landings_meet_no_constraint",
       "tests/test_design_verify.py::"
       "test_a_verification_of_one_landing_is_not_verified_and_says_so")),
    M("quarter_tip_probability", "a quarter-model Monte Carlo presents a tip-over probability",
      "    return not_modelled(np.size(tipped), TIP_OVER_NOT_MODELLED)",
      "    return dict(modelled=True, **proportion(tipped))",
      ("tests/test_montecarlo.py::test_a_quarter_run_presents_no_tip_over_probability",)),
]


def _copy_source(source: str, dest: Path) -> None:
    if source == "worktree":
        ignore = shutil.ignore_patterns(".git", ".venv", "out", "__pycache__", ".pytest_cache",
                                        ".ruff_cache", "*.egg-info")
        shutil.copytree(ROOT, dest, ignore=ignore, symlinks=True)
    else:
        dest.mkdir(parents=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", source],
                                 check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)


def _locate(scratch: Path, m: Mutation) -> tuple[list[tuple[Path, int]], str, str]:
    """Files holding the mutation's code string (the first spelling found, of ``find`` and then
    ``also``), and that spelling's (find, replace)."""
    for find, replace in ((m.find, m.replace), *m.also):
        hits = []
        for folder in m.search:
            for path in sorted((scratch / folder).rglob("*.py")):
                n = path.read_text().count(find)
                if n:
                    hits.append((path, n))
        if hits:
            return hits, find, replace
    return [], m.find, m.replace


def _pytest(scratch: Path, targets, timeout: float) -> tuple[int, float, list[str], str]:
    env = dict(os.environ, PYTHONPATH=str(scratch), PYTHONDONTWRITEBYTECODE="1")
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *targets]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=scratch, env=env, capture_output=True, text=True,
                           timeout=timeout)
    except subprocess.TimeoutExpired:
        return -1, time.perf_counter() - t0, [], "timeout"
    out = p.stdout + p.stderr
    failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", out, flags=re.M)
    return p.returncode, time.perf_counter() - t0, failed, out[-2000:]


def _check_import(scratch: Path) -> str:
    env = dict(os.environ, PYTHONPATH=str(scratch))
    p = subprocess.run([sys.executable, "-c", "import jaxland; print(jaxland.__file__)"],
                       cwd=scratch, env=env, capture_output=True, text=True)
    where = p.stdout.strip()
    if p.returncode or not where.startswith(str(scratch)):
        raise SystemExit(f"the scratch copy's jaxland is not the one imported ({where!r}; "
                         f"{p.stderr[-500:]})")
    return where


def run(mutations, *, source: str, timeout: float, keep: bool, log=print) -> dict:
    scratch = Path(tempfile.mkdtemp(prefix="jaxland-mutants-", dir="/tmp"))
    tree = scratch / "repo"
    try:
        _copy_source(source, tree)
        _check_import(tree)
        baseline: dict = {}
        results = []
        for m in mutations:
            rec = dict(asdict(m), status=None, files=[], seconds=None, failed_tests=[])
            hits, find, replace = _locate(tree, m)
            rec["applied"] = dict(find=find, replace=replace)
            rec["files"] = [str(p.relative_to(tree)) for p, _ in hits]
            if not hits:
                rec["status"] = "target not found"
            elif len(hits) > 1 or hits[0][1] > 1:
                rec["status"] = "ambiguous target"
            else:
                key = tuple(m.tests)
                if key not in baseline:
                    rc, sec, failed, tail = _pytest(tree, m.tests, timeout)
                    baseline[key] = dict(ok=rc == 0, seconds=sec, failed=failed, tail=tail)
                    log(f"baseline {' '.join(m.tests)}: {'ok' if rc == 0 else 'FAILS'} "
                        f"({sec:.0f} s)")
                if not baseline[key]["ok"]:
                    rec["status"] = "baseline failed"
                    rec["failed_tests"] = baseline[key]["failed"]
                else:
                    path = hits[0][0]
                    original = path.read_text()
                    path.write_text(original.replace(find, replace))
                    try:
                        rc, sec, failed, tail = _pytest(tree, m.tests, timeout)
                    finally:
                        path.write_text(original)
                    rec["seconds"] = round(sec, 1)
                    rec["failed_tests"] = failed
                    rec["status"] = ("timeout" if rc == -1 else "killed" if rc != 0
                                     else "survived")
                    if rc not in (-1, 0, 1):  # collection/usage error: show it
                        rec["output_tail"] = tail
            log(f"{m.name:<32} {rec['status']}")
            results.append(rec)
        counts: dict = {}
        for r in results:
            counts[r["status"]] = counts.get(r["status"], 0) + 1
        return dict(source=source, root=str(ROOT), scratch=str(tree) if keep else None,
                    counts=counts, survivors=[r["name"] for r in results
                                              if r["status"] == "survived"],
                    baseline={" ".join(k): dict(ok=v["ok"], seconds=round(v["seconds"], 1),
                                                failed=v["failed"])
                              for k, v in baseline.items()},
                    mutations=results)
    finally:
        if not keep:
            shutil.rmtree(scratch, ignore_errors=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run only these mutations")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--source", default="worktree",
                    help="'worktree' (default: the files as they are now) or a git revision")
    ap.add_argument("--out", help="write the JSON report here (default: stdout)")
    ap.add_argument("--timeout", type=float, default=900.0, help="per pytest run [s]")
    ap.add_argument("--keep", action="store_true", help="keep the scratch copy")
    ap.add_argument("--tests", nargs="+", metavar="TARGET",
                    help="run these pytest targets for every chosen mutation instead of its own "
                         "(to see what one test file catches on its own)")
    args = ap.parse_args(argv)
    if args.list:
        for m in MUTATIONS:
            print(f"{m.name:<32} {m.what}  [{', '.join(m.tests)}]")
        return 0
    chosen = MUTATIONS
    if args.only:
        unknown = set(args.only) - {m.name for m in MUTATIONS}
        if unknown:
            ap.error(f"unknown mutation(s): {', '.join(sorted(unknown))}")
        chosen = [m for m in MUTATIONS if m.name in args.only]
    if args.tests:
        chosen = [Mutation(m.name, m.what, m.find, m.replace, tuple(args.tests), m.search, m.also)
                  for m in chosen]
    report = run(chosen, source=args.source, timeout=args.timeout, keep=args.keep,
                 log=lambda s: print(s, file=sys.stderr, flush=True))
    text = json.dumps(report, indent=2) + "\n"
    if args.out:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 1 if report["survivors"] else 0


if __name__ == "__main__":
    sys.exit(main())
