"""The measured tables in README.md and docs/ are generated from benchmarks/results/*.json,
never typed.

    python benchmarks/docs_tables.py           # rewrite every generated block (README, docs)
    python benchmarks/docs_tables.py --check   # exit 1 (with a diff) if any block is stale

A generated block in a Markdown file looks like::

    <!-- table:NAME -->
    ...whatever this script renders for NAME...
    <!-- /table -->

NAME picks a renderer in ``TABLES``; an unknown name is an error. Only the lines between the
markers are touched. This script reads JSON only (no jax, no jaxland), so the check is fast.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import re
import sys
from pathlib import Path
from statistics import NormalDist

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOCS = ROOT / "docs"
Z95 = NormalDist().inv_cdf(0.975)  # a 95 % interval's half-width in standard errors
BLOCK = re.compile(r"(<!-- table:([\w-]+) -->\n)(.*?)(<!-- /table -->)", re.S)


def _load(name: str) -> dict:
    """A committed results summary; a smoke run's (``quick``) is no result to publish."""
    data = json.loads((RESULTS / name).read_text())
    if isinstance(data, dict) and data.get("quick"):
        sys.exit(f"error: {RESULTS.relative_to(ROOT) / name} holds a --quick smoke run; "
                 "rerun the full benchmark or restore the committed file (git checkout)")
    return data


def _g(x, nd=4) -> str:
    """A number to ``nd`` significant digits ('-' for None)."""
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    if 10 ** nd <= abs(x) < 1e9:
        return f"{x:.0f}"  # 13721, not 1.372e+04
    return f"{x:.{nd}g}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


# --- paper comparison (paper_table.json) -------------------------------------------------------

# row key -> label (with unit); keys of one row in different columns are merged through ALIASES.
# A key not listed here still gets a row (at the end), labelled from its name and unit suffix.
PAPER_ROWS = {
    "touchdown_s": "touchdown time [s]",
    "first_impact_end_s": "end of first impact [s]",
    "later_impacts_s": "later impacts [s]",
    "third_impact_start_s": "third impact starts [s]",
    "first_impact_stroke_mm": "first-impact stroke [mm]",
    "max_stroke_mm": "max stroke [mm]",
    "final_stroke_mm": "final stroke [mm]",
    "foot_vz_end_first_impact_mps": "foot velocity at end of first impact [m/s]",
    "peak_foot_accel_normal_mps2": "peak foot acceleration, normal (Fig. 12a) [m/s^2]",
    "peak_foot_accel_mps2": "peak foot acceleration, magnitude [m/s^2]",
    "peak_buffer_velocity_mps": "peak buffer velocity, first impact [m/s]",
    "peak_body_accel_mps2": "peak body acceleration [m/s^2]",
    "secondary_engaged_first_impact": "secondary honeycomb engaged in first impact",
    "energy_closure_rel": "energy ledger closure (of dissipated) [-]",
    "peak_body_accel_measured_mps2": "peak body acceleration, measured [m/s^2]",
    "peak_buffer_force_N": "peak buffer (strut) force [N]",
    "peak_honeycomb_force_N": "peak honeycomb force [N]",
    "peak_ratio_both_stages": "crush peak over plateau, both stages [-]",
    "peak_length_mm": "crush peak length [mm]",
    "no_peak_error_peak_buffer_force_rel": "peak buffer force, error of a run without crush peak "
                                           "(paper: against its measurement; jaxland: against "
                                           "the crush-peak run) [-]",
    "no_peak_error_peak_body_accel_rel": "peak body acceleration, the same error [-]",
}
PAPER_ALIASES = {"second_impact_s": "later_impacts_s"}
PAPER_SKIP = {"n_impacts"}
PAPER_COLUMNS = {"paper": "paper", "jaxland_default": "jaxland (default, rod slides free)",
                 "jaxland_bonded": "jaxland (bonded honeycomb)",
                 "jaxland_crush_peak": "jaxland (with crush peak)"}
UNITS = (("_mps2", "m/s^2"), ("_mps", "m/s"), ("_mm", "mm"), ("_kN", "kN"), ("_N", "N"),
         ("_m", "m"), ("_s", "s"), ("_J", "J"), ("_kg", "kg"), ("_rel", "-"))


def _label(key: str) -> str:
    for suffix, unit in UNITS:
        if key.endswith(suffix):
            return f"{key[: -len(suffix)].replace('_', ' ')} [{unit}]"
    return key.replace("_", " ")


def _name(key: str) -> str:
    """A column name without its unit suffix, in words."""
    for suffix, _ in UNITS:
        if key.endswith(suffix):
            return key[: -len(suffix)].replace("_", " ")
    return key.replace("_", " ")


def _paper_cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if isinstance(v, list):  # impact intervals [[start, end|None], ...]
        return ", ".join(f"{a:.3f}-{'end' if b is None else format(b, '.3f')}" for a, b in v)
    return _g(v)


def paper_table() -> str:
    data = _load("paper_table.json")
    keys: list[str] = list(PAPER_ROWS)
    for col in data.values():
        for k in col:
            k = PAPER_ALIASES.get(k, k)
            if k not in keys and k not in PAPER_SKIP:
                keys.append(k)
    cols = list(data)
    rows = []
    for key in keys:
        cells = []
        for c in cols:
            col = {PAPER_ALIASES.get(k, k): v for k, v in data[c].items()}
            cells.append(_paper_cell(col.get(key)))
        if any(cell != "-" for cell in cells):
            rows.append([PAPER_ROWS.get(key, _label(key)), *cells])
    return _table(["quantity", *(PAPER_COLUMNS.get(c, c.replace("_", " ")) for c in cols)], rows)


# --- integrators (integrators.json) ------------------------------------------------------------

def _cheapest(rows, metric, level):
    ok = [r for r in rows if r.get("errors") and r["errors"].get(metric, math.inf) <= level]
    return min(ok, key=lambda r: r["wall_s"]) if ok else None


def _setting(row) -> str:
    if row.get("setting_text"):
        return row["setting_text"]
    return ", ".join(f"{k} = {v:g}" + (" N s" if k == "impulse" else " s" if k == "dt" else "")
                     for k, v in row.items() if k in ("dt", "impulse", "rtol") and v is not None)


def integrators_accuracy() -> str:
    res = _load("integrators.json")
    out = []
    base = res.get("baselines", {})
    for name, entry in res["work_precision"].items():
        ref = entry["reference"]
        out.append(f"**{name}** (reference: {ref.get('method', 'euler')} at dt = "
                   f"{ref['dt']:g} s; it moved by "
                   f"{ref['change_from_2dt']['max_stroke_m']:.1e} in max stroke from 2 dt)\n")
        labels = list(dict.fromkeys([r["method"] for r in entry["runs"]]
                                    + [r["method"] for r in base.get(name, [])]))
        rows = []
        for label in labels:
            runs = [r for r in entry["runs"] if r["method"] == label] + [
                dict(r, setting_text=str(r.get("setting")).replace("=", " = "))
                for r in base.get(name, []) if r["method"] == label]
            cells = [label]
            for level in (1e-4, 1e-3):
                best = _cheapest(runs, "max_stroke_m", level)
                cells += (["not reached", "-"] if best is None
                          else [_setting(best), f"{best['wall_s'] * 1e3:.3g}"])
            rows.append(cells)
        out.append(_table(["method", "cheapest setting, max-stroke error <= 1e-4", "wall [ms]",
                           "cheapest setting, <= 1e-3", "wall [ms]"], rows))
    return "\n".join(out)


def _ratio(x) -> str:
    """A cost ratio; '-' where the gradient was refused or failed (NaN)."""
    return f"{x:.1f}" if x is not None and math.isfinite(x) else "-"


def integrators_throughput() -> str:
    tg = _load("integrators.json")["throughput"]
    sizes = [r["batch"] for r in next(iter(tg.values()))["batches"]]
    rows = []
    for method, d in tg.items():
        setting = ", ".join(f"{k} = {v:g}" if isinstance(v, float) else f"{k} = {v}"
                            for k, v in d["setting"].items())
        rows.append([method, setting, f"{d['forward_s'] * 1e3:.3g}",
                     *(f"{r['landings_per_s']:.0f}" for r in d["batches"]),
                     _ratio(d["jacfwd_ratio"]), _ratio(d["grad_ratio"]),
                     f"{d['batches'][0]['compile_s']:.2f}"])
    return _table(["method", "setting [s, N s]", "one landing [ms]",
                   *(f"landings/s, batch {n}" for n in sizes), "jacfwd 6 / forward [-]",
                   "grad / forward [-]", "compile [s]"], rows)


def integrators_targets() -> str:
    """The integrator work's targets against integrators.json: the cheapest jaxland run within
    1e-4 in max stroke on the paper drop against scipy's at that accuracy, euler's batch of
    1000 against numba's prange loop, and euler's jacfwd over 6 parameters."""
    res = _load("integrators.json")
    tol = 1e-4
    runs = [r for r in res["work_precision"]["paper"]["runs"]
            if r["ok"] and r["errors"]["max_stroke_m"] <= tol]
    best = min(runs, key=lambda r: r["wall_s"])
    rows = []
    for method, target in (("scipy_LSODA", 50.0), ("scipy_Radau", 1000.0)):
        base = [b for b in res["baselines"]["paper"]
                if b["method"] == method and b["errors"]["max_stroke_m"] <= tol]
        if not base:
            continue
        b = min(base, key=lambda b: b["wall_s"])
        ratio = b["wall_s"] / best["wall_s"]
        rows.append([f"one paper drop within {tol:g} in max stroke: {method[6:]} ({b['setting']}, "
                     f"{b['wall_s'] * 1e3:.3g} ms) / jaxland's cheapest ({best['method']}, "
                     f"dt = {best['dt']:g} s, {best['wall_s'] * 1e3:.3g} ms)", f"{ratio:.0f}x",
                     f">= {target:g}x", "met" if ratio >= target else "not met"])
    nb = {r["batch"]: r for r in res["numba_batch"]["rows"]}
    eu = {r["batch"]: r for r in res["throughput"]["euler"]["batches"]}
    n = max(set(nb) & set(eu))
    ratio = eu[n]["landings_per_s"] / nb[n]["landings_per_s"]
    rows.append([f"batch of {n} paper-drop landings: euler vmapped on one device "
                 f"({eu[n]['landings_per_s']:.0f}/s) / numba prange on "
                 f"{res['numba_batch']['threads']} threads ({nb[n]['landings_per_s']:.0f}/s)",
                 f"{ratio:.2f}x", ">= 1x", "met" if ratio >= 1.0 else "not met"])
    jr = res["throughput"]["euler"]["jacfwd_ratio"]
    rows.append(["euler: jacfwd over 6 parameters / one forward run (a loss of max stroke and "
                 "peak normal force)", f"{jr:.1f}x", "<= 8x", "met" if jr <= 8.0 else "not met"])
    return _table(["measure", "measured", "target", "judged"], rows)


def integrators_full3d() -> str:
    rows = [[f"{r['method']} (batch {r['batch']}, {r['t_end_s']:g} s)", f"{r['dt']:g}",
             f"{r['landings_per_s']:.1f}",
             f"{r['max_stroke_diff_median']:.1e} / {r['max_stroke_diff_max']:.1e}",
             f"{r['peak_accel_diff_median']:.1e}"]
            for r in _load("integrators.json")["full_model"]]
    return _table(["full 3-D, dispersed batch", "dt [s]", "landings/s",
                   "max stroke vs Euler at 2.5e-6 s: median / max [-]",
                   "peak body accel vs the same: median [-]"], rows)


def integrators_stability() -> str:
    rows = []
    for name, runs in _load("integrators.json")["stability"].items():
        for r in runs:
            label = r["method"] + (f" (dI = {r['impulse']:g} N s)" if "impulse" in r else "")
            if r.get("failure_s"):
                rows.append([name, label, f"{r['theory_s']:.3g}", f"{r['survives_s']:.3g}",
                             f"{r['failure_s']:.3g}", f"{r['ratio']:.2f}"])
            else:
                rows.append([name, label, f"{r['theory_s']:.3g}", "-", "-",
                             "not bracketed in [0.5, 2] x theory"])
    return _table(["scene", "method", "theory (stable_step) [s]", "last stable [s]",
                   "first failing [s]", "failure / theory [-]"], rows)


# --- gradient quality (gradient_quality.json) --------------------------------------------------

def gradient_quality() -> str:
    res = _load("gradient_quality.json")
    target = res["target"]
    scenes = list(res["scenes"])
    params = ", ".join(res["params"])
    labels = list(dict.fromkeys(k for s in scenes for k in res["scenes"][s]["variants"]))
    rows = []
    for label in labels:
        first = next(res["scenes"][s]["variants"][label] for s in scenes
                     if label in res["scenes"][s]["variants"])
        window = "whole record" if first["window_s"] is None else f"{first['window_s'] * 1e3:g} ms"
        cells = []
        for s in scenes:
            v = res["scenes"][s]["variants"].get(label)
            if v is None:
                cells.append("-")
                continue
            errs = " ".join(f"{e:.0e}" for e in v["robust_rel_err"])
            cells.append(errs + (" ✓" if max(v["robust_rel_err"]) <= target else ""))
        name = label.replace("DEFAULT ", "").rsplit(" win", 1)[0]
        if label.startswith("DEFAULT"):
            name += " (smoothed option)"
        rows.append([name, window, *cells])
    return _table(["variant", "window", *(f"{s}: {params}" for s in scenes)], rows)


# --- performance (bench_landing.json, bench_montecarlo.json) -----------------------------------

def performance_landing() -> str:
    b = _load("bench_landing.json")
    q, f = b, b["full_model"]
    qb, fb = q["batched"][-1], f["batched"][-1]
    jf, gr = b["gradients"]["jacfwd_6_params"], b["gradients"]["grad_6_params"]
    rows = [
        ["compile one landing [s]", f"{q['single']['compile_s']:.2f}",
         f"{f['single']['compile_s']:.2f}"],
        ["one landing (jit, median) [ms]",
         f"{q['single']['run_s'] * 1e3:.3g} ({q['single']['ns_per_step']:.0f} ns/step)",
         f"{f['single']['run_s'] * 1e3:.3g} ({f['single']['ns_per_step']:.0f} ns/step, "
         f"{f['cost_ratio_single']:.1f}x the quarter)"],
        ["`jl.landings` (vmap) over drop height [landings/s]",
         f"{qb['landings_per_s']:.0f} (batch {qb['batch']}, {qb['run_s']:.2f} s)",
         f"{fb['landings_per_s']:.1f} (batch {fb['batch']}, {fb['run_s']:.2f} s)"],
        ["`jacfwd` over 6 parameters [ms]",
         f"{jf['run_s'] * 1e3:.3g} ({jf['ratio_to_forward']:.1f}x one forward run)", "-"],
        ["`grad` over 6 parameters [ms]",
         f"{gr['run_s'] * 1e3:.3g} ({gr['ratio_to_forward']:.1f}x; reverse mode stores the "
         f"trajectory)", "-"],
    ]
    return _table(["what", "quarter model", "full 3-D model"], rows)


def performance_steps() -> str:
    b = _load("bench_landing.json")["per_landing_step"]
    q, f = b["models"]["quarter"], b["models"]["full"]
    rows = []
    for rq, rf in zip(q, f):
        what = "one landing (jit)" if rq["batch"] == 0 else f"vmapped batch of {rq['batch']}"
        rows.append([what, f"{rq['ns_per_landing_step']:.0f} ({rq['cpu_ns_per_landing_step']:.0f})",
                     f"{rf['ns_per_landing_step']:.0f} ({rf['cpu_ns_per_landing_step']:.0f})",
                     f"{b['full_over_quarter_cpu'][str(rq['batch'])]:.1f}",
                     f"{rq['dispatches_per_step']:.2g} / {rf['dispatches_per_step']:.2g}",
                     "{fusions} / {dots} / {reduces} / {fused_ops}".format(**rq["loop_body"]),
                     "{fusions} / {dots} / {reduces} / {fused_ops}".format(**rf["loop_body"])])
    return _table(["run", "quarter, wall (CPU) [ns per landing-step]",
                   "full 3-D, wall (CPU) [ns per landing-step]", "full / quarter, CPU [-]",
                   "kernel dispatches per step, quarter / full [-]",
                   "quarter step: fusions / dots / reduces / fused ops",
                   "full step: fusions / dots / reduces / fused ops"], rows)


def performance_steps_accelerator() -> str:
    """bench_landing.py --accelerator: the per-landing-step comparison on one GPU, with the
    kernels each compiled time step launches (bench_landing_accelerator.json)."""
    b = _load("bench_landing_accelerator.json")["per_landing_step"]
    q, f = b["models"]["quarter"], b["models"]["full"]
    rows = []
    for rq, rf in zip(q, f):
        what = "one landing (jit)" if rq["batch"] == 0 else f"vmapped batch of {rq['batch']}"
        rows.append([what, _g(rq["ns_per_landing_step"], 3), _g(rf["ns_per_landing_step"], 3),
                     f"{b['full_over_quarter'][str(rq['batch'])]:.1f}",
                     f"{rq['us_per_step']:.1f} / {rf['us_per_step']:.1f}",
                     f"{rq['loop_body']['kernels']} / {rf['loop_body']['kernels']}"])
    return _table(["run", "quarter [ns per landing-step]", "full 3-D [ns per landing-step]",
                   "full / quarter [-]", "one step of the whole batch, quarter / full [us]",
                   "kernels per step, quarter / full [-]"], rows)


def performance_montecarlo() -> str:
    """Per model and setting (the spec's default, the step study's choice), throughput on 1 and
    2 devices, and the issue's target at the chosen step (bench_montecarlo.json)."""
    b = _load("bench_montecarlo.json")
    rows = []
    for model in dict.fromkeys(r["model"] for r in b["runs"]):
        target = b["targets"].get(model)
        for setting in dict.fromkeys((r["method"], r["dt_s"]) for r in b["runs"]
                                     if r["model"] == model):
            runs = {r["devices"]: r for r in b["runs"]
                    if r["model"] == model and (r["method"], r["dt_s"]) == setting}
            one = next(iter(runs.values()))
            cells = [f"{runs[d]['landings_per_s']:.1f}" if d in runs else "-" for d in (1, 2)]
            ratio = (f"{runs[2]['landings_per_s'] / runs[1]['landings_per_s']:.2f}"
                     if 1 in runs and 2 in runs else "-")
            is_chosen = target is not None and list(setting) == target["setting"]
            goal = (f">= {target['target_landings_per_s']:g}: "
                    f"{'met' if target['met'] else 'not met'}" if is_chosen else "")
            retried = sum(r["n_retried"] for r in runs.values())
            rows.append([model, f"{setting[0]}, {setting[1]:g}"
                         + (" (chosen)" if is_chosen else " (default)"), str(one["n"]),
                         *cells, ratio, str(retried), goal])
    return _table(["model", "method, dt [s]", "n [-]", "1 device [landings/s]",
                   "2 devices [landings/s]", "2 / 1 devices [-]", "samples retried [-]",
                   "target, 2 devices [landings/s]"], rows)


def performance_montecarlo_large() -> str:
    """The full 3-D Monte Carlo at the issue's size, 10^4 landings, at the chosen step on two
    devices (``large`` in bench_montecarlo.json)."""
    b = _load("bench_montecarlo.json")["large"]
    t = b["target"]
    rows = [[r["model"], f"{r['method']}, {r['dt_s']:g}", str(r["n"]), str(r["devices"]),
             f"{r['wall_s']:.1f}", f"{r['landings_per_s']:.1f}", str(r["n_retried"]),
             f"{t['n']} in <= {t['wall_s']:g} s: {'met' if b['met'] else 'not met'}"]
            for r in b["runs"]]
    return _table(["model", "method, dt [s]", "n [-]", "devices [-]",
                   "wall, with compilation [s]", "throughput [landings/s]",
                   "samples retried [-]", "target"], rows)


def performance_montecarlo_cached() -> str:
    """The full 3-D Monte Carlo at the chosen step run twice, sharing one empty compilation
    cache (``cached`` in bench_montecarlo.json)."""
    b = _load("bench_montecarlo.json")["cached"]
    rows = [[r["model"], f"{r['method']}, {r['dt_s']:g}", str(r["n"]), str(r["devices"]),
             r["cache"], f"{r['wall_s']:.1f}", f"{r['landings_per_s']:.1f}"]
            for r in b["runs"]]
    for i, r in enumerate(rows):  # the target is judged on the run that read the cache
        r.append(f">= {b['target_landings_per_s']:g}: {'met' if b['met'] else 'not met'}"
                 if i == len(rows) - 1 else "")
    return _table(["model", "method, dt [s]", "n [-]", "devices [-]", "compilation cache",
                   "wall, with compilation or cache read [s]", "throughput [landings/s]",
                   "target [landings/s]"], rows)


def _cpu_rate(model: str, n: int):
    """This CPU's two-device throughput at the chosen step for ``model`` and ``n`` from
    bench_montecarlo.json (the throughput rows and the 10^4 run), or None."""
    b = _load("bench_montecarlo.json")
    target = b["targets"].get(model)
    runs = [r for r in b["runs"] + b["large"]["runs"] if r["model"] == model and r["n"] == n
            and r["devices"] == 2 and target and [r["method"], r["dt_s"]] == target["setting"]]
    return runs[0]["landings_per_s"] if runs else None


def montecarlo_accelerator() -> str:
    """bench_montecarlo.py --accelerator's runs on one GPU, next to this CPU's rate for the same
    model and n where it has one (montecarlo_accelerator.json, bench_montecarlo.json)."""
    b = _load("montecarlo_accelerator.json")
    rows = []
    for r in b["runs"] + b["cached"]:
        cpu = _cpu_rate(r["model"], r["n"])
        rows.append([r["model"], f"{r['method']}, {r['dt_s']:g}", str(r["n"]), str(r["chunk"]),
                     r["cache"] if r["cache"] != "none" else "-", f"{r['wall_s']:.1f}",
                     f"{r['landings_per_s']:.1f}", f"{cpu:.1f}" if cpu else "-",
                     str(r["n_failed"])])
    return _table(["model", "method, dt [s]", "n [-]", "chunk [-]", "compilation cache",
                   "wall, with compilation [s]", f"one {b['runs'][0]['device_kind']} "
                   "[landings/s]", "this CPU, 2 devices [landings/s]", "failed [-]"], rows)


def montecarlo_accelerator_targets() -> str:
    """The issue's Monte Carlo sizes and per-landing cost ratio on the GPU: its fastest rate per
    model over the runs, and the runs at the issue's sizes (montecarlo_accelerator.json)."""
    b = _load("montecarlo_accelerator.json")
    best = {m: max((r for r in b["runs"] if r["model"] == m),
                   key=lambda r: r["landings_per_s"]) for m in ("quarter", "full")}
    rows = []
    for model, n, wall in (("quarter", 100_000, 20.0), ("full", 10_000, 60.0)):
        r = next((r for r in b["runs"] if r["model"] == model and r["n"] == n), None)
        rows.append([f"{n} {model} landings in <= {wall:g} s (the CPU target)",
                     *([f"{r['wall_s']:.1f} s", "met" if r["wall_s"] <= wall else "not met"]
                       if r else ["not measured", "-"])])
    q, f = best["quarter"], best["full"]
    ratio = q["landings_per_s"] / f["landings_per_s"]
    rows.append([f"per landing, full 3-D / quarter <= 6 (fastest runs: n = {f['n']} and "
                 f"{q['n']})", f"{ratio:.1f}", "met" if ratio <= 6 else "not met"])
    return _table(["on one " + b["runs"][0]["device_kind"], "measured", "target"], rows)


def _gpu_run(name: str) -> dict:
    """A results summary whose columns say GPU: refused unless a GPU ran it."""
    data = _load(name)
    if data.get("platform") != "gpu":
        sys.exit(f"error: {RESULTS.relative_to(ROOT) / name} was run on "
                 f"{data.get('platform')!r}, not a GPU; its tables are a GPU's")
    return data


def accelerator_agreement() -> str:
    """One landing per model on the GPU and on the same machine's CPU
    (accelerator_agreement.json, benchmarks/accelerator_agreement.py)."""
    b = _gpu_run("accelerator_agreement.json")["single"]
    rows = [[m, f"{r['gpu']['max_stroke_m']:.12g}", f"{r['cpu']['max_stroke_m']:.12g}",
             f"{r['rel_diff_max_stroke']:.1e}", f"{r['gpu']['run_s'] * 1e3:.0f}",
             f"{r['cpu']['run_s'] * 1e3:.1f}"] for m, r in b.items()]
    return _table(["model", "max stroke, GPU [m]", "max stroke, its CPU [m]",
                   "relative difference [-]", "one landing, GPU [ms]",
                   "one landing, its CPU [ms]"], rows)


def accelerator_samples() -> str:
    """The same Monte Carlo on the GPU and on the same machine's CPU, two chunk sizes each,
    sample by sample: per outcome the largest relative difference and the samples beyond
    1e-6 and 1e-3 (accelerator_agreement.json's ``samples``)."""
    b = _gpu_run("accelerator_agreement.json")
    rows = []
    for model, m in b["samples"].items():
        for p in m["pairs"]:
            diffs = {k: v for k, v in p.items() if isinstance(v, dict) and "max_rel" in v}
            by = p["changes_by_class"]
            rows.append([model, str(m["n"]), f"{p['a']} / {p['b']}",
                         "; ".join(f"{k} {v['max_rel']:.1e} ({v['above_1e6']}, {v['above_1e3']})"
                                   for k, v in diffs.items()),
                         " / ".join(str(by[k]["n"]) for k in ("tipped_over", "bottomed_out",
                                                               "result"))])
    return _table(["model", "n [-]", "runs compared", "per outcome: largest relative difference "
                   "(samples beyond 1e-6, beyond 1e-3)", "samples whose tip-over / bottoming / "
                   "result changed [-]"], rows)


def numba_side_by_side() -> str:
    """One quarter landing in jaxland with each bookkeeping against the numba loop of the same
    scheme (numba_side_by_side.json)."""
    b = _load("numba_side_by_side.json")
    rows = [["numba loop (benchmarks/_baseline_port.py)", f"{b['numba_ms']:.2f}", "1"]]
    rows += [[f"jaxland, {r['bookkeeping']}", f"{r['ms']:.2f}", f"{r['ratio_to_numba']:.2f}"]
             for r in b["jaxland"]]
    return _table([f"one landing ({b['method']}, dt = {b['dt_s']:g} s, {b['t_end_s']:g} s)",
                   "CPU [ms]", "/ numba [-]"], rows)


def fusion() -> str:
    """XLA:CPU multi-output fusion off and on, per kind of work (fusion.json)."""
    b = _load("fusion.json")
    rows = [[r["case"], r["what"], f"{r['ns_per_landing_step']['off']:.4g}",
             f"{r['ns_per_landing_step']['on']:.4g}", f"{r['on_over_off']:.2f}"]
            for r in b["rows"]]
    return _table(["work", "what it stands for", "off [ns CPU per landing-step]",
                   "on [ns CPU per landing-step]", "on / off [-]"], rows)


def cli_cache() -> str:
    """Commands run twice with one compilation cache (cli_cache.json)."""
    b = _load("cli_cache.json")
    rows = [[f"`{r['command']}`", f"{r['first_s']:.1f}", f"{r['second_s']:.1f}"]
            for r in b["rows"]]
    return _table(["command", "first run, compiles [s]", "second run, cache read [s]"], rows)


def montecarlo_side_by_side() -> str:
    """The runs of one bench_montecarlo session side by side: this tree and an earlier one
    (``--before``), and the step the step study chose (bench_montecarlo.json)."""
    b = _load("bench_montecarlo.json")
    before = b.get("before_commit") or b["before_tree"]
    rows = [[r["model"], "this" if r["tree"] == "this" else f"before ({before})",
             f"{r['method']}, {r['dt_s']:g}", str(r["devices"]), str(r["n"]),
             f"{r['wall_s']:.1f}", f"{r['landings_per_s']:.1f}"] for r in b["side_by_side"]]
    return _table(["model", "tree", "method, dt [s]", "devices [-]", "n [-]",
                   "wall, with compilation [s]", "throughput [landings/s]"], rows)


def montecarlo_step() -> str:
    """Per model and method, the largest step whose outcomes stay within the tolerance
    (montecarlo_step.json)."""
    b = _load("montecarlo_step.json")
    tol = b["tolerance"]
    rows = []
    for model, rep in b["models"].items():
        ill = sorted(set().union(*rep["sensitivity"]["ill_conditioned_samples"].values()))
        chosen = rep["chosen"]
        for method in dict.fromkeys(r["method"] for r in rep["rows"]):
            rs = [r for r in rep["rows"] if r["method"] == method]
            ok = [r for r in rs if max(r["worst"], r["ensemble_worst"]) <= tol
                  and r["classification_kept"]]
            best = max(ok, key=lambda r: r["dt_s"]) if ok else None
            rows.append([
                f"{model} ({rep['n']} samples, {len(ill)} ill-conditioned)", method,
                f"{best['dt_s']:g}" if best else "none",
                _g(best["worst"], 2) if best else "-",
                _g(best["ensemble_worst"], 2) if best else "-",
                "yes" if chosen and best and chosen["method"] == method
                and chosen["dt_s"] == best["dt_s"] else ""])
    return _table(["model", "method", f"largest step within {tol:g} [s]",
                   "worst per-sample error there, well-conditioned outcomes [-]",
                   "worst mean/median error there [-]", "chosen (cheapest)"], rows)


def montecarlo_step_check() -> str:
    """The 3-D chosen step and the default step on more samples than the study ran, against
    both converged runs (montecarlo_step_check.json)."""
    b = _load("montecarlo_step_check.json")
    rows = []
    for r in b["rows"]:
        for k, o in r["outcomes"].items():
            if k == "peak_honeycomb_force_N" and not o["worst_where_converged_agree"]:
                continue  # on its plateau in every sample: exact at any step
            rows.append([
                f"{r['method']}, {r['dt_s']:g} ({r['role']})", k,
                f"{_g(o['worst_where_converged_agree'], 2)} (sample {o['worst_sample']})",
                ", ".join(map(str, o["over_tolerance"])) or "none",
                f"{len(o['converged_disagree'])} "
                f"(largest {_g(o['converged_largest_difference'], 2)})",
                f"{_g(o['ensemble_rel_error']['mean'], 2)} / "
                f"{_g(o['ensemble_rel_error']['median'], 2)}",
                f"{_g(o['converged_ensemble_rel_error']['mean'], 2)} / "
                f"{_g(o['converged_ensemble_rel_error']['median'], 2)}"])
    return _table([
        "method, dt [s]", "outcome", "worst per-sample error where the converged runs agree [-]",
        f"samples over {b['tolerance']:g} there",
        f"samples whose converged runs differ by more than {b['agree_within']:g} [-]"
        " (their largest difference)",
        "mean / median error [-]", "converged runs' own mean / median difference [-]"], rows)


# --- calibration (bench_fit.json) ---------------------------------------------------------------

def calibration_fit() -> str:
    b = _load("bench_fit.json")
    variants = b["variants"]

    def opts(v):
        o = v["options"]
        return o["integrator"] + (f", {o['smoothing_m']:g} m / {o['smoothing_N']:g} N"
                                  if o.get("smoothing_m") else "")

    def pct(d):
        return ", ".join(f"{k} {v * 100:+.2g}" for k, v in d.items())

    rows = [
        ["fit, cold (with compilation) / warm [s]",
         *(f"{v['summary']['fit_cold_s']:.2g} / {v['summary']['fit_warm_s']:.2g}"
           for v in variants.values())],
        ["starts converged, crush-peak data / noise-free",
         *(f"{v['summary']['starts_converged_crush_peak']} / "
           f"{v['summary']['starts_recovered_noise_free']}" for v in variants.values())],
        ["noise-free recovery, worst of the starts [%]",
         *(pct(v["summary"]["clean_worst_rel_error"]) for v in variants.values())],
        ["crush-peak data, fitted against truth [%]",
         *(pct(v["summary"]["crush_peak_rel_error"]) for v in variants.values())],
        ["AD against FD of the calibration loss, worst parameter [-]",
         *(f"{max(v['summary']['ad_fd_worst_robust_per_param'].values()):.1e}"
           for v in variants.values())],
        ["targets met: fit under 20 s cold, every start converged",
         *(_g(v["summary"]["meets_targets"]) for v in variants.values())],
    ]
    m = b["machine"]
    load = (f"\nLoad average (1 minute) {m['load_average_1min_at_start']:.1f} at the start of "
            f"the run, {m['load_average_1min_at_end']:.1f} at its end, on {m['cpus']} CPUs.\n"
            if "load_average_1min_at_end" in m else "")
    return _table(["", *(opts(v) for v in variants.values())], rows) + load


def calibration_fit_time() -> str:
    """Cold fits, each in a fresh process (``fit_time`` in bench_fit.json)."""
    ft = _load("bench_fit.json")["fit_time"]
    target = ft["target_s"]
    rows = [[r["case"], f"{r['wall_s']:.1f}", f"{sum(s['wall_s'] for s in r['stages']):.1f}",
             f"{r['cpu_s']:.1f}", f"{r['load_average_1min_at_start']:.1f}", str(r["jacobians"]),
             str(r["starts_tried"]), _g(r["wall_s"] <= target)]
            for r in ft["runs"]]
    mod = ft.get("modified")
    code = (f"\nTimed at commit {ft['commit'][:7]}, "
            + (f"with these library files changed from it: {', '.join(mod)}" if mod
               else "with no library file changed from it") + ".\n") if "commit" in ft else ""
    return _table(["fit (cold, fresh process)", "wall [s]", "of which the optimiser's stages [s]",
                   "CPU, all threads [s]", "load average at start [-]", "Jacobians [-]",
                   "starts [-]", f"wall <= {target:g} s ({ft['cpus']} CPUs)"], rows) + code


def _err_z(run, p) -> str:
    return (f"{run['rel_error'][p] * 100:+.2f} ({run['z_hac'][p]:+.1f} / "
            f"{run['z_total'][p]:+.1f})")


# the peak-recovery studies in bench_fit.json: (key, the rig's peak, the fitted model)
PEAK_RECOVERY_STUDIES = (
    ("peak_recovery", "physical", "linear peak (peak1, L_peak1)"),
    ("peak_recovery_law_rise", "physical", "peak with its rise (+ L_rise1)"),
    ("peak_recovery_true_shape", "physical", "the rig's own shape (its table), 6 parameters"),
    ("peak_recovery_sensor", "on the forces only", "linear peak (peak1, L_peak1)"),
    ("peak_recovery_sensor_site_forces", "on the forces only",
     "linear peak on the force channels (--peak-site forces)"),
)


def calibration_peak_recovery() -> str:
    """The crush-peak model on every rig peak shape: per study (``PEAK_RECOVERY_STUDIES``:
    where the rig's peak acts, which model is fitted) and shape, the errors' mean over the
    seeds, the noise-free fit, and how many seeds meet the issue's targets (``peak_recovery*``
    in bench_fit.json)."""
    b = _load("bench_fit.json")
    rows = []
    for key, where, model in PEAK_RECOVERY_STUDIES:
        if key not in b:
            continue
        rows += _peak_recovery_rows(b[key], where, model)
    return _table(["rig peak", "fitted model", "shape",
                   "error against the truth, mean over the seeds (the counts' total) +/- its "
                   "standard error [%]",
                   "noise-free record (weighted by the rig's noise) [%]",
                   "mean standard error, HAC / total [%]",
                   "seeds with all five within 3 %",
                   "... with the best-supported peak form's values",
                   "seeds with the truth inside 2 SE of all five, HAC / total",
                   "... total without the peak-shape term"], rows)


def _peak_recovery_rows(pr, where, model) -> list:
    checked = pr["targets"]["checked"]
    n = len(pr["seeds"])
    rows = []
    for shape, rec in pr["shapes"].items():
        nf = rec["noise_free"]
        rows.append([
            where, model, shape, ", ".join(f"{p} {rec['mean_rel_error'][p] * 100:+.2f} +/- "
                             f"{rec['sem_rel_error'][p] * 100:.2f}" for p in checked),
            ", ".join(f"{p} {nf['rel_error'][p] * 100:+.2f}" for p in checked),
            ", ".join(f"{p} {rec['mean_se_hac_rel'][p] * 100:.2f} / "
                      f"{rec['mean_se_total_rel'][p] * 100:.2f}" for p in checked),
            f"{rec['seeds_within_3pct']}/{n}",
            f"{rec['seeds_within_3pct_best_form']}/{n}" if "best_form_counts" in rec else "-",
            f"{rec['seeds_within_2se']}/{n} / {rec['seeds_within_2se_total']}/{n}",
            f"{rec['seeds_within_2se_total_without_form']}/{n}" if "best_form_counts" in rec
            else "-"])
    return rows


def calibration_peak_recovery_seeds() -> str:
    """Every seed of ``peak_recovery`` (the physical peak, the linear peak fitted): error
    against the truth and z = error / SE (HAC and total), and the channel whose leaving out
    moves k_b1 most."""
    pr = _load("bench_fit.json")["peak_recovery"]
    checked = pr["targets"]["checked"]

    def most(r):
        sh = {c: d["k_b1"] for c, d in r["channel_shift_rel"].items() if d is not None}
        if not sh:  # not warned of misfit, or every refit failed
            return "-"
        c = max(sh, key=lambda k: abs(sh[k]))
        return f"{c} {sh[c] * 100:+.1f}"

    rows = [[shape, str(r["seed"]), *(_err_z(r, p) for p in checked), f"{r['sigma2']:.2f}",
             f"{r['rho1']:.2f}", f"{r['values']['peak1']:.3f}", most(r)]
            for shape, rec in pr["shapes"].items() for r in rec["runs"]]
    return _table(["shape", "seed", *(f"{p}: error [%] (z HAC / total)" for p in checked),
                   "variance factor [-]", "lag-1 autocorrelation [-]", "peak1 [-]",
                   "k_b1 moves most without [%]"], rows)


def calibration_prediction() -> str:
    b = _load("bench_fit.json")
    name = b["default_integrator"]["integrator"]
    pred = b["variants"][name]["prediction"]
    quantities = list(next(iter(pred.values()))["fitted"])
    rows = [[f"{h} m", *(f"{pred[h]['fitted'][q] * 100:+.2f} / "
                         f"{pred[h]['truth_model'][q] * 100:+.2f}" for q in quantities)]
            for h in pred]
    return _table(["drop height", *(f"{_name(q)}: fitted / true parameters [%]"
                                    for q in quantities)], rows)


def calibration_best_form_prediction() -> str:
    """The physical crush peak fitted in its best-supported form (``best_form_prediction`` in
    bench_fit.json): per rig shape and for the joint fit, the form, the errors against the
    truth, and the predictions of the other heights against the data."""
    b = _load("bench_fit.json")["best_form_prediction"]
    order = ("max_stroke_m", "final_stroke_m", "peak_normal_force_N", "peak_buffer_force_N",
             "peak_body_accel_mps2")
    cases = dict(b["shapes"])
    if "joint_0.15_0.30_bump" in b:
        cases["joint 0.15 + 0.30 m, bump"] = b["joint_0.15_0.30_bump"]
    rows = []
    for label, rec in cases.items():
        rows.append([
            label if label.startswith("joint") else f"0.2 m, {label}", rec["best_form"],
            ", ".join(f"{p} {e * 100:+.2f}" for p, e in rec["rel_error"].items()),
            "yes" if rec["params_met"] else "no",
            "yes" if rec["inside_2se"] else "no", "yes" if rec["F2_met"] else "no",
            "; ".join(f"{h} m: " + " / ".join(f"{p['rel_error'][q] * 100:+.2f}" for q in order)
                      for h, p in rec["prediction"].items()),
            "yes" if all(p["met"] for p in rec["prediction"].values()) else "no"])
    return _table(["fitted drop(s), rig peak shape", "best-supported form (fitted in)",
                   "error against the truth [%]", "five within 3 %",
                   "truth inside 2 total SE of the five", "F2 within 3 %",
                   "predicted drop: " + " / ".join(_name(q) for q in order) + " [%]",
                   "strokes within 1 %, peaks within 5 %"], rows)


def _recovery_checks(runs, names, values: str = "best_form_rel_error") -> tuple:
    """Over peak-recovery runs, how many have ``values`` (relative errors of ``names``) all
    within 3 % of the truth, all inside 2 of the fit's total standard errors
    (``se_total_rel``), and both."""
    w3 = [all(abs(r_[values][n]) <= 0.03 for n in names) for r_ in runs]
    w2 = [all(abs(r_[values][n]) <= 2.0 * r_["se_total_rel"][n] for n in names) for r_ in runs]
    return sum(w3), sum(w2), sum(a and b for a, b in zip(w3, w2))


def _recovery_coverage(runs, names, values: str = "rel_error") -> dict:
    """Over peak-recovery runs, per parameter of ``names``: the fraction whose ``values``
    (relative errors) lie inside the fit's total 95 % interval (1.96 ``se_total_rel``)."""
    return {n: sum(abs(r_[values][n]) <= Z95 * r_["se_total_rel"][n] for r_ in runs) / len(runs)
            for n in names}


def calibration_best_form_coverage() -> str:
    """The refit in the best-supported form (``best_form_coverage`` in bench_fit.json): per
    rig shape, the forms named, the seeds with all five within 3 %, the coverage of the
    refit's own 95 % interval against the first fit's total one, per parameter, and the
    first fit's best-form values as the CLI prints them (the peak-recovery study's first fits
    of the same seeds)."""
    data = _load("bench_fit.json")
    b, pr = data["best_form_coverage"], data["peak_recovery"]
    if b["seeds"] != pr["seeds"]:
        raise SystemExit("best_form_coverage and peak_recovery ran different seeds: rerun one")
    names = b["params"]

    def cov(c):
        return " ".join(f"{c[n]:.2f}" for n in names)

    def width(runs):  # the first fit's total standard error, relative, mean over the seeds
        return " ".join(f"{sum(r_['se_first_total_rel'][n] for r_ in runs) / len(runs) * 100:.2f}"
                        for n in names)

    rows = []
    for shape, rec in b["shapes"].items():
        n_runs = len(rec["runs"])
        printed = _recovery_checks(pr["shapes"][shape]["runs"], names)[2]
        rows.append([shape, ", ".join(f"{f} {n}" for f, n in rec["best_form_counts"].items()),
                     f"{rec['seeds_within_3pct']}/{n_runs}", cov(rec["coverage_refit"]),
                     cov(rec["coverage_first"]), cov(rec["coverage_refit_first_total"]),
                     f"{rec['seeds_within_3pct_and_2se_first_total']}/{n_runs}",
                     f"{printed}/{len(pr['shapes'][shape]['runs'])}", width(rec["runs"]),
                     f"{rec['refits_only_form_supported']}/{n_runs}"])
    per = ", ".join(names)
    return _table(["rig peak shape", "best-supported form (of the seeds)",
                   "refit: five within 3 %", f"refit's own total interval covers ({per}) [-]",
                   f"first fit's total interval covers ({per}) [-]",
                   f"refit's values, first fit's total interval, covers ({per}) [-]",
                   "refit's values: five within 3 % and inside 2 of the first fit's total SE",
                   "the same for the first fit's best-form values (printed)",
                   f"first fit's total SE, mean ({per}) [%]",
                   "refits whose own form is the only one supported (the CLI's caveat)"], rows)


def calibration_peak_location() -> str:
    """Where the fitted peak shows (``peak_location``), per rig peak mode and shape, over the
    peak-recovery study's seeds (``peak_recovery`` and ``peak_recovery_sensor`` in
    bench_fit.json)."""
    b = _load("bench_fit.json")
    rows = []
    for key, label in (("peak_recovery", "in the honeycomb (physical)"),
                       ("peak_recovery_sensor", "on the force channels only (sensor)")):
        for shape, rec in b[key]["shapes"].items():
            kept, z = rec.get("peak_excess_kept_range"), rec.get("peak_z_range")
            named = rec.get("seeds_peak_force_only")
            rows.append([label, shape, "-" if named is None else f"{named}/{len(rec['runs'])}",
                         "-" if kept is None else f"{kept[0]:.2f} to {kept[1]:.2f}",
                         "-" if z is None else f"{z[0]:+.1f} to {z[1]:+.1f}"])
    return _table(["rig peak", "shape", "fits that name the peak the force channels' only",
                   "excess kept by the motion-only step [-]", "z of that step [-]"], rows)


def calibration_peak_site() -> str:
    """The peak fitted on the force channels (``--peak-site forces``), per rig peak mode and
    shape: on the rig's sensor-side records (the right site) and on its honeycomb peaks (the
    wrong one): the fit's and the best-supported form's values within 3 %, the truth inside 2
    of the fit's total standard errors, and the motion check (``peak_site_check``)."""
    b = _load("bench_fit.json")
    rows = []
    for key, label in (("peak_recovery_sensor_site_forces", "on the force channels only"),
                       ("peak_recovery_site_forces", "in the honeycomb")):
        pr = b[key]
        names = pr["targets"]["checked"]
        for shape, rec in pr["shapes"].items():
            runs, n = rec["runs"], len(rec["runs"])
            own3 = _recovery_checks(runs, names, "rel_error")[0]
            best3, best2 = _recovery_checks(runs, names)[:2]
            kb1 = sum(abs(r_["best_form_rel_error"]["k_b1"]) <= 2.0 * r_["se_total_rel"]["k_b1"]
                      for r_ in runs)
            cov = _recovery_coverage(runs, names)
            vf = [r_["peak_site_check"]["variance_factor"] for r_ in runs]
            warned = sum(r_["peak_site_check"]["misfit"] for r_ in runs)
            worst = {p: max(abs(r_["best_form_rel_error"][p]) for r_ in runs)
                     for p in ("k", "gamma", "k_b1")}
            rows.append([label, shape, f"{own3}/{n}", f"{best3}/{n}", f"{best2}/{n}",
                         f"{kb1}/{n}", " ".join(f"{cov[p]:.2f}" for p in names),
                         ", ".join(f"{p} {v * 100:.1f}" for p, v in worst.items()),
                         f"{min(vf):.2f} to {max(vf):.2f}", f"{warned}/{n}",
                         ", ".join(f"{f} {c}" for f, c in rec["best_form_counts"].items())])
    return _table(["rig peak", "shape", "fit's values: all five within 3 %",
                   "best-supported form's values: all five within 3 %",
                   "... the truth inside 2 total SE of all five", "... of k_b1",
                   "fit's values inside its total 95 % interval: " + ", ".join(names),
                   "best form's largest error [%]", "motion channels' variance factor [-]",
                   "fits that warn the motion misfits", "best-supported form (of the seeds)"],
                  rows)


def calibration_noise_response() -> str:
    """The noise's own share of the sensor-side records' errors (``noise_response`` in
    bench_fit.json): per parameter the standard error, the rms of the noise's response in
    standard errors over the seeds, how many lie beyond 2, and which seeds."""
    d = _load("bench_fit.json")["noise_response"]
    n = len(d["seeds"])
    rows = []
    for p in d["params"]:
        far = [f"{seed} ({z:+.2f})" for seed, z in zip(d["seeds"], d["z"][p]) if abs(z) > 2.0]
        rows.append([p, f"{d['se_rel'][p] * 100:.2f}", f"{d['rms_z'][p]:.2f}",
                     f"{d['beyond_2'][p]}/{n}", ", ".join(far) or "-"])
    return _table(["parameter", "standard error [%]", "noise's response, rms [SE]",
                   "beyond 2 SE", "seeds beyond 2 SE (response)"], rows)


def calibration_coverage() -> str:
    """Coverage of the 95 % intervals per rig case (``coverage`` in bench_fit.json): the
    classical, HAC and trusted intervals, the total one (the trusted error with the channel
    spread and, where the fit has the crush peak, the peak-shape term, or, under misfit
    without one, the missing-peak term), the total without that term, the median ratio of the
    two widths and the peak form the data supported best."""
    c = _load("bench_fit.json")["coverage"]
    params = c["params"]
    rows = []
    for name, case in c["cases"].items():
        cov = case["coverage_of_truth"]
        form = case.get("model_form", False)
        term = "form" if form else "peak_term" if case.get("peak_model_term") else None
        best = case.get("best_form", {}).get("counts", {})
        rows.append([name, f"{case['misfit_warned_fraction']:.2f}",
                     f"{cov['classical_all']:.2f}", f"{cov['hac_all']:.2f}",
                     f"{cov['trusted_all']:.2f}",
                     " ".join(f"{cov['trusted'][p]:.2f}" for p in params),
                     f"{cov['total_all']:.2f}",
                     " ".join(f"{cov['total'][p]:.2f}" for p in params),
                     f"{cov[f'total_without_{term}_all']:.2f}" if term else "-",
                     f"{case[f'width_ratio_{term}']['median']:.2f}" if term else "-",
                     ", ".join(f"{f} {k}" for f, k in best.items()) if form else "-"])
    return _table(["rig data", "fits warned of misfit [-]", "classical [-]", "HAC [-]",
                   "the interval the report trusts [-]",
                   f"trusted, per parameter ({', '.join(params)}) [-]",
                   "total: trusted, channel spread and peak-shape or missing-peak term [-]",
                   "total, per parameter [-]", "total without that term [-]",
                   "width, total / without the term, median [-]",
                   f"best-supported peak form (of {c['n_seeds']} seeds)"], rows)


def calibration_offset_coverage() -> str:
    """Coverage of the classical intervals on representable data against the free fall the
    sensors' offsets are taken from (``offset_coverage`` in bench_fit.json)."""
    c = _load("bench_fit.json")["offset_coverage"]
    params = c["params"]
    n = c["seeds"][1] - c["seeds"][0] + 1
    rows = [[f"{case['pre_trigger_s'] * 1e3:.0f} ms ({case['free_fall_samples']} samples)",
             f"{case['coverage_all']:.3f}",
             " ".join(f"{case['coverage'][p]:.2f}" for p in params),
             " ".join(f"{case['spread_over_se'][p]:.2f}" for p in params)]
            for case in c["cases"].values()]
    return _table(["free fall before touchdown (offsets' samples)",
                   f"classical 95 % interval covers the truth, {n} seeds [-]",
                   f"per parameter ({', '.join(params)}) [-]",
                   "scatter over the seeds / mean reported standard error, per parameter [-]"],
                  rows)


def calibration_sample_rate() -> str:
    """The law's own peak fitted with it at two sample rates (``sample_rate_study`` in
    bench_fit.json): per parameter, the total interval's coverage and the scatter over its
    reported error, over all seeds and over each block of seeds."""
    c = _load("bench_fit.json")["sample_rate_study"]
    params = c["params"]
    rows = []
    for r in c["rates"].values():
        parts = [(f"{c['seeds'][0]}-{c['seeds'][1]} (all)", r)]
        parts += [(f"{b['seeds'][0]}-{b['seeds'][1]}", b) for b in r.get("blocks", [])]
        for seeds, x in parts:
            rows.append([f"{r['sample_rate_Hz'] / 1e3:g}", seeds,
                         " ".join(f"{x['coverage'][p]:.2f}" for p in params),
                         " ".join(f"{x['scatter_over_se'][p]:.2f}" for p in params)])
    return _table(["sample rate [kHz]", "seeds",
                   f"total 95 % interval covers the truth, per parameter ({', '.join(params)}) "
                   "[-]",
                   "scatter over the seeds / mean reported standard error, per parameter [-]"],
                  rows)


# --- design (design.json) -----------------------------------------------------------------------

def _p(c) -> str:
    if c.get("modelled") is False:
        return "not modelled"
    if c["probability"] is None:
        return "undefined (no landing)"
    lo, hi = c["ci95_wilson"]
    return f"{c['count']}/{c['n']} = {c['probability']:.3g} [{lo:.3g}, {hi:.3g}]"


def _constraint_g(c) -> str:
    if c["ci95"][1] is None:
        return f"{'-' if c['g'] is None else format(c['g'], '+.3f')} not judged (too few landings)"
    return (f"{c['g']:+.3f} [{c['ci95'][0]:+.3f}, {c['ci95'][1]:+.3f}] "
            f"{'met' if c['met'] else 'NOT met'}")


def _continued(x) -> str:
    runs = x.get("continued")
    if runs is None:  # a report from before the continuation
        return ""
    if not runs:
        return "none cut off"
    return (f"{runs[0]['n']} cut off; run on to "
            + ", then ".join(f"{c['t_end_s']:g} s ({c['n_unfinished_after']} left"
                             + (f", {c['wall_s']:.1f} s" if c.get("wall_s") is not None else "")
                             + ")" for c in runs))


def design_verification() -> str:
    d = _load("design.json")["paper_gear_design"]
    v, s = d["verification"], d["on_design_scenes"]
    b, a = v["before"], v["after"]
    rows = [
        [f"objective ({d['objective']['measure']} {d['objective']['level']:g} of "
         f"{_label(d['objective']['quantity'])}) on the {d['scenes']['n']} design scenes",
         f"{s['before']['objective_measure_mps2']:.4g}",
         f"{s['after']['objective_measure_mps2']:.4g}"],
        ["peak body acceleration, p50 / p99 [m/s^2]",
         f"{b['peak_body_accel_p50_mps2']:.4g} / {b['peak_body_accel_p99_mps2']:.4g}",
         f"{a['peak_body_accel_p50_mps2']:.4g} / {a['peak_body_accel_p99_mps2']:.4g}"],
        ["the same objective on the verification landings", f"{b['objective_measure_mps2']:.4g}",
         f"{a['objective_measure_mps2']:.4g}"],
        ["max stroke (any leg), p50 / p99 / max [mm]",
         *(f"{x['max_stroke_p50_m'] * 1e3:.1f} / {x['max_stroke_p99_m'] * 1e3:.1f} / "
           f"{x['max_stroke_max_m'] * 1e3:.1f}" for x in (b, a))],
        ["P(bottoming out), 95 % Wilson", _p(b["bottoming"]), _p(a["bottoming"])],
        *([[f"P({name} constraint violated), 95 % Wilson", _p(b["constraint_violations"][name]),
            _p(a["constraint_violations"][name])] for name in b.get("constraint_violations", {})]),
        ["P(tip-over), 95 % Wilson", _p(b["tip_over"]), _p(a["tip_over"])],
        ["min stability margin, p01 [m]", f"{b['min_stability_margin_p01_m']:.4g}",
         f"{a['min_stability_margin_p01_m']:.4g}"],
        ["failed samples", str(b["n_failed"]), str(a["n_failed"])],
        *([[f"landings cut off at t_end_s = {v['t_end_s']:g} s", _continued(b), _continued(a)]]
          if "continued" in a else []),
    ]
    ca, cb = v.get("constraints_after") or {}, v.get("constraints_before") or {}
    for name, c in ca.items():  # the constraint's own measure on the fresh landings
        rows.append([f"{name} constraint g ({c['measure']}; <= 0 met), 95 % bootstrap",
                     *(_constraint_g(x[name]) if name in x else "" for x in (cb, ca))])
    if v.get("verified") is not None:
        rounds = len(v.get("rounds") or [1]) - 1
        rows.append(["verified (re-optimisation rounds; landings added)", "",
                     f"{'yes' if v['verified'] else 'NO: ' + str(v['reason'])} ({rounds}; "
                     f"{sum(len(x['samples']) for x in v.get('added_landings') or [])})"])
    return _table([f"quantity (verification: n = {v['n']} fresh landings, seed {v['seed']}, "
                   f"{v['t_end_s']:g} s)", "before (paper gear)", "after (design)"], rows)


def design_step() -> str:
    d = _load("design.json")["design_step"]
    rows = [[r["method"], f"{r['dt_s']:g}", f"{r['forward_s']:.3g}",
             f"{r['objective_rel_diff']:.2g}", f"{r['constraint_diff_g']:.2g}"]
            for r in d["runs"]]
    return _table(["method", "dt [s]", "one forward evaluation [s]",
                   f"objective: relative difference from {d['reference']}",
                   "constraints: largest difference in g (units of the constraint's scale: "
                   "10 mm stroke, 0.1 m margin)"], rows)


def design_wall() -> str:
    d = _load("design.json")["paper_gear_design"]
    runs = [("documented", d["wall"])] + [(f"repeat {i + 1}", w)
                                          for i, w in enumerate(d.get("repeats", []))]
    rows = [[label, f"{w['iterations']}", f"{w['devices']}",
             f"{w['first_evaluation_incl_compile_s']:.1f}", f"{w['per_iteration_s']:.2f}",
             f"{w['optimisation_wall_s']:.1f}", f"{w['verification_wall_s']:.1f}",
             f"{w['setup_and_judging_s']:.1f}", f"**{w['total_wall_s']:.1f}**"]
            for label, w in runs]
    return _table(["run (empty compilation cache)", "iterations", "devices",
                   "first evaluation incl. tracing and compilation [s]", "per iteration [s]",
                   "optimisation [s]", "verification, 2 Monte Carlos [s]",
                   "set-up and judging [s]", "total [s]"], rows)


def design_convergence() -> str:
    d = _load("design.json")["convergence"]
    rows = [[label, f"{r['settings'].get('patience', '-')}", f"{r['iterations_run']}",
             f"{r['best_mps2']:.4g} (iteration {r['best_iteration']})",
             "never" if r["iterations_to_1pct"] is None else
             f"iteration {r['iterations_to_1pct']} ({r['wall_to_1pct_s']:.1f} s)",
             f"{r['wall_s']:.1f}"] for label, r in d["runs"].items()]
    return _table(["run", "patience", "iterations run", "best [m/s^2]",
                   f"within 1 % of the best found ({d['best_overall_mps2']:.4g} m/s^2)",
                   "wall [s]"], rows)


def design_devices() -> str:
    d = _load("design.json")["device_split"]
    rows = [[f"{r['devices']}", f"{r['first_evaluation_s']:.1f}", f"{r['iteration_wall_s']:.2f}",
             f"{r['iteration_cpu_s']:.2f}"] for r in d["rows"]]
    return _table(["devices", "first evaluation, with compilation [s]",
                   "one iteration, wall [s]", "one iteration, CPU [s]"], rows)


def design_variables() -> str:
    d = _load("design.json")["paper_gear_design"]
    rows = [[x["name"], f"[{x['low']:.4g}, {x['high']:.4g}] ({x['scale']})", f"{x['start']:.4g}",
             f"{x['design']:.4g}"] for x in d["variables"]]
    return _table(["variable [unit in the name]", "bounds", "start", "design"], rows)


# --- README: the measured targets at a glance ---------------------------------------------------

def _met(ok: bool) -> str:
    return "met" if ok else "**not met**"


def readme_paper_peak() -> str:
    """The paper's 0.2 m drop without and with the crush peak (paper_table.json), against the
    paper's simulation and measurement."""
    d = _load("paper_table.json")
    paper, plain, peak = d["paper"], d["jaxland_default"], d["jaxland_crush_peak"]
    rows = [["peak body acceleration [m/s^2]",
             f"{paper['peak_body_accel_measured_mps2']:g} measured, "
             f"{paper['peak_body_accel_mps2']:g} simulated",
             f"{plain['peak_body_accel_mps2']:.1f}", f"{peak['peak_body_accel_mps2']:.1f}"],
            ["peak buffer force [N]", "-", f"{plain['peak_buffer_force_N']:.0f}",
             f"{peak['peak_buffer_force_N']:.0f}"],
            ["the run without the peak, off in peak buffer force / peak body acceleration",
             f"{paper['no_peak_error_peak_buffer_force_rel']:.1%} / "
             f"{paper['no_peak_error_peak_body_accel_rel']:.1%} (against the measurement)",
             "-", f"{peak['no_peak_error_peak_buffer_force_rel']:.1%} / "
                  f"{peak['no_peak_error_peak_body_accel_rel']:.1%} (against this run)"]]
    head = (f"jaxland with the crush peak (ratio {peak['peak_ratio_both_stages']:g}, "
            f"{peak['peak_length_mm']:g} mm)")
    return _table(["0.2 m drop", "paper", "jaxland without the crush peak", head], rows)


def readme_calibration_targets() -> str:
    """Issue 12's measured targets on the rig's drops with a crush peak (bench_fit.json)."""
    b = _load("bench_fit.json")
    names = b["peak_recovery"]["targets"]["checked"]

    def seeds(key, values):  # records within 3 %, and inside 2 total SE, of all five
        runs = [r_ for rec in b[key]["shapes"].values() for r_ in rec["runs"]]
        return (*_recovery_checks(runs, names, values)[:2], len(runs))

    p3, p2, pn = seeds("peak_recovery", "best_form_rel_error")
    f3, f2, fn = seeds("peak_recovery", "rel_error")
    s3, s2, sn = seeds("peak_recovery_sensor", "best_form_rel_error")
    site = "peak_recovery_sensor_site_forces"
    t3, t2, tn = seeds(site, "best_form_rel_error")
    o3, o2, on = seeds(site, "rel_error")
    site_runs = [r_ for rec in b[site]["shapes"].values() for r_ in rec["runs"]]
    site_cov = _recovery_coverage(site_runs, names)
    worst_p = min(site_cov, key=site_cov.get)
    pooled = sum(site_cov.values()) / len(site_cov)
    bf = b["best_form_prediction"]
    cases = dict(bf["shapes"], joint=bf["joint_0.15_0.30_bump"])
    # strokes (max and final) against the stroke target, the rest (peaks) against the peak one
    errs = [(k.endswith("stroke_m"), abs(e)) for c in cases.values()
            for pr in c["prediction"].values() for k, e in pr["rel_error"].items()]
    worst = {"stroke": max(e for st, e in errs if st), "peak": max(e for st, e in errs if not st)}
    pred_met = all(pr["met"] for c in cases.values() for pr in c["prediction"].values())
    joint = bf["joint_0.15_0.30_bump"]
    final = joint["prediction"]["0.30 (fitted)"]["rel_error"]["final_stroke_m"]
    ft = b["fit_time"]
    slowest = max(ft["runs"], key=lambda r_: r_["wall_s"])
    in_honeycomb = max((r_ for r_ in ft["runs"] if "--peak-site forces" not in r_["case"]),
                       key=lambda r_: r_["wall_s"])
    cov = min(case["coverage_of_truth"]["total_all"] for case in b["coverage"]["cases"].values())
    rows = [
        ["honeycomb crush peak of 4 shapes unlike the law's, 10 noise seeds each: k, gamma, "
         "D_b, k_b1, F1 within 3 % and the truth inside 2 reported standard errors (the "
         "best-supported form's values, the fit's total interval)", "every record",
         f"3 %: {p3}/{pn}; 2 SE: {p2}/{pn}", _met(p3 == pn and p2 == pn)],
        ["the same, the fit's own values (the law's peak; its fitted vehicle)", "-",
         f"3 %: {f3}/{fn}; 2 SE: {f2}/{fn}", "-"],
        ["the same with the peak on the force channels only (a sensor artefact the motion "
         "does not show), the best-supported form's values", "-",
         f"3 %: {s3}/{sn}; 2 SE: {s2}/{sn}", "see docs"],
        ["the same records fitted with the peak on the force channels (--peak-site forces), "
         "the best-supported form's values", "-",
         f"3 %: {t3}/{tn}; 2 SE: {t2}/{tn}", "see docs"],
        ["... the fit's own values (the law's peak, on the force channels)", "-",
         f"3 %: {o3}/{on}; 2 SE: {o2}/{on}", "-"],
        ["... coverage of the fit's total 95 % intervals there (its own values), lowest of "
         "the five parameters", ">= 0.90",
         f"{site_cov[worst_p]:.2f} ({worst_p}); all five pooled {pooled:.2f}",
         _met(site_cov[worst_p] >= 0.90)],
        ["prediction of the other heights: strokes within 1 %, peaks within 5 %",
         "every shape and height", f"worst {worst['stroke']:.2%} / {worst['peak']:.2%}",
         _met(pred_met)],
        ["joint fit of 0.15 + 0.30 m: F2 within 3 %, the 0.30 m final stroke within 1 %",
         "3 % / 1 %", f"{joint['rel_error']['F2']:+.2%} / {final:+.2%}",
         _met(abs(joint['rel_error']['F2']) <= 0.03 and abs(final) <= 0.01)],
        ["fit time with compilation, slowest case", f"<= {ft['target_s']:g} s",
         f"{slowest['wall_s']:.1f} s ({slowest['case']})" + (
             f"; without the peak on the force channels {in_honeycomb['wall_s']:.1f} s "
             f"({in_honeycomb['case']})" if in_honeycomb is not slowest else ""),
         _met(slowest["wall_s"] <= ft["target_s"])],
        ["coverage of the reported 95 % intervals, worst rig case of "
         f"{len(b['coverage']['cases'])} ({b['coverage']['n_seeds']} seeds each)", ">= 0.90",
         f"{cov:.2f}",
         _met(cov >= 0.90)]]
    return _table(["issue 12 (calibration)", "target", "measured", ""], rows)


def readme_speed_targets() -> str:
    """Issue 13's measured targets (bench_montecarlo.json, montecarlo_step_check.json,
    numba_side_by_side.json, design.json)."""
    m = _load("bench_montecarlo.json")
    q, f = m["targets"]["quarter"], m["targets"]["full"]
    large = m["large"]["runs"][0]
    ratio = q["landings_per_s"] / large["landings_per_s"]
    chk = _load("montecarlo_step_check.json")
    chosen = next(r_ for r_ in chk["rows"] if r_["role"] == "chosen")
    over = sorted({i for o in chosen["outcomes"].values() for i in o["over_tolerance"]})
    numba = _load("numba_side_by_side.json")
    like = next(j["ratio_to_numba"] for j in numba["jaxland"]  # the like-for-like row
                if "about the numba" in j["bookkeeping"])
    design = _load("design.json")["paper_gear_design"]

    def n_of(model, setting):  # the size of the target's run: the chosen step, 2 devices
        return next(r_["n"] for r_ in m["runs"] if r_["model"] == model and r_["devices"] == 2
                    and [r_["method"], r_["dt_s"]] == list(setting))

    quarter_n, full_n = n_of("quarter", q["setting"]), n_of("full", f["setting"])
    rows = [
        [f"quarter Monte Carlo, n = {quarter_n}, {q['setting'][0]} at {q['setting'][1]:g} s",
         f">= {q['target_landings_per_s']:g} landings/s", f"{q['landings_per_s']:.0f}",
         _met(q["met"])],
        [f"full 3-D Monte Carlo, n = {full_n}, cold, {f['setting'][0]} at {f['setting'][1]:g} s",
         f">= {f['target_landings_per_s']:g} landings/s", f"{f['landings_per_s']:.0f}",
         _met(f["met"])],
        [f"full 3-D Monte Carlo, n = {large['n']}", f"<= {m['large']['target']['wall_s']:g} s",
         f"{large['wall_s']:.1f} s", _met(m["large"]["met"])],
        ["per landing, full 3-D / quarter", "<= 6", f"{ratio:.1f}", _met(ratio <= 6.0)],
        [f"outcomes within {chk['tolerance']:g} of the converged reference, every sample",
         f"{chk['n']} of {chk['n']}", f"{chk['n'] - len(over)} of {chk['n']}",
         _met(not over)],
        ["one quarter landing against a compiled numba loop of the same scheme", "<= 1.5x",
         f"{like:.2f}x", _met(like <= 1.5)],
        [f"paper-gear design, {design['wall']['n_scenes']} scenes, {design['iterations']} "
         "iterations, with compilation and verification",
         "<= 60 s", f"{design['total_wall_s']:.1f} s", _met(design["total_wall_s"] <= 60.0)]]
    return _table(["issue 13 (speed), this 2-core CPU, 2 devices", "target", "measured", ""],
                  rows)


TABLES = {
    "paper-table": paper_table,
    "integrators-accuracy": integrators_accuracy,
    "integrators-throughput": integrators_throughput,
    "integrators-targets": integrators_targets,
    "integrators-full3d": integrators_full3d,
    "integrators-stability": integrators_stability,
    "gradient-quality": gradient_quality,
    "performance-landing": performance_landing,
    "numba-side-by-side": numba_side_by_side,
    "cli-cache": cli_cache,
    "fusion": fusion,
    "performance-steps": performance_steps,
    "performance-steps-accelerator": performance_steps_accelerator,
    "performance-montecarlo": performance_montecarlo,
    "performance-montecarlo-side-by-side": montecarlo_side_by_side,
    "montecarlo-step": montecarlo_step,
    "montecarlo-step-check": montecarlo_step_check,
    "calibration-fit": calibration_fit,
    "calibration-fit-time": calibration_fit_time,
    "performance-montecarlo-large": performance_montecarlo_large,
    "performance-montecarlo-cached": performance_montecarlo_cached,
    "montecarlo-accelerator": montecarlo_accelerator,
    "montecarlo-accelerator-targets": montecarlo_accelerator_targets,
    "accelerator-agreement": accelerator_agreement,
    "accelerator-samples": accelerator_samples,
    "calibration-peak-recovery": calibration_peak_recovery,
    "calibration-peak-recovery-seeds": calibration_peak_recovery_seeds,
    "calibration-prediction": calibration_prediction,
    "calibration-best-form-prediction": calibration_best_form_prediction,
    "calibration-best-form-coverage": calibration_best_form_coverage,
    "calibration-peak-location": calibration_peak_location,
    "calibration-peak-site": calibration_peak_site,
    "calibration-noise-response": calibration_noise_response,
    "calibration-coverage": calibration_coverage,
    "calibration-offset-coverage": calibration_offset_coverage,
    "calibration-sample-rate": calibration_sample_rate,
    "design-verification": design_verification,
    "design-variables": design_variables,
    "design-wall": design_wall,
    "design-convergence": design_convergence,
    "design-devices": design_devices,
    "design-step": design_step,
    "readme-paper-peak": readme_paper_peak,
    "readme-calibration-targets": readme_calibration_targets,
    "readme-speed-targets": readme_speed_targets,
}


def render(text: str, where: str = "") -> str:
    """``text`` with every generated block rendered afresh."""
    def sub(m):
        name = m.group(2)
        if name not in TABLES:
            raise SystemExit(f"{where}: unknown table '{name}' (known: {', '.join(TABLES)})")
        return m.group(1) + TABLES[name]() + m.group(4)
    return BLOCK.sub(sub, text)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true",
                   help="change nothing; exit 1 if a generated block differs from the results")
    p.add_argument("files", nargs="*", type=Path,
                   help="Markdown files (default: README.md and docs/*.md)")
    args = p.parse_args(argv)
    files = args.files or [DOCS.parent / "README.md", *sorted(DOCS.glob("*.md"))]
    stale = []
    for path in files:
        old = path.read_text()
        new = render(old, str(path))
        if new == old:
            continue
        if args.check:
            stale.append(path)
            sys.stdout.writelines(difflib.unified_diff(
                old.splitlines(True), new.splitlines(True), f"{path} (committed)",
                f"{path} (from benchmarks/results)"))
        else:
            path.write_text(new)
            print(f"updated {path}")
    if stale:
        print(f"\nstale generated tables in {', '.join(map(str, stale))}: "
              "run python benchmarks/docs_tables.py", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
