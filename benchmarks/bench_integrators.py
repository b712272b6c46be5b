"""Speed against accuracy for every integrator.

    python benchmarks/bench_integrators.py [--quick] [--out DIR]

For two scenes (the paper's 0.2 m drop, and a harsh one with separations: 0.25 m drop and no
strut damping, D_b = 0: 169 of 183 mm of stroke used, 17 contact changes) and a ladder of
settings per method (step dt, impulse step dI, or tolerance rtol), it measures the wall time
per landing (median of repeats after compile) and the error against a converged reference
(velocity Verlet, second order, at the finest step, its convergence checked against the next
coarser one) in
max stroke, final stroke, peak buffer (strut) force, peak
normal force and the RMS of the stroke trace. It also measures landings/s against batch size,
compile time, the cost of gradients (jacfwd over 6 parameters, grad) per method (and for the
smoothed fitting option, Verlet with the switches smoothed at 1 um / 10 N, ``verlet_smooth``),
and the stability map: the step where each method fails, found by bisection, next to the
theory (``stable_step``). The non-JAX baselines (numba, scipy), when ``benchmarks/results/
baselines.json`` exists, are put on the same chart against the same reference.

Writes ``integrators.json`` (every number the tables and charts use, rounded to 4 significant
digits), ``raw/integrators_raw.json`` (full precision, ignored by git) and
``integrators_*.png``; ``benchmarks/docs_tables.py`` renders the tables in
``docs/integrators.md`` from the JSON. Timings are never asserted by tests. ``--quick`` (small
ladders) writes to ``out/bench-quick/`` unless ``--out`` says otherwise, never into
``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _common import (
    RESULTS,
    ROOT,
    add_out_args,
    machine,
    out_dir,
    params as _params,
    raw_dir,
    rounded,
    save_png,
    timed as _timed,
    write_json,
)

import jaxland as jl
from jaxland import CLOSURE_LIMIT, Scene, Solver, landing, landings, stable_step

# "peak buffer force" is the strut load (honeycomb plus damping, what a load cell reads): the
# honeycomb force alone peaks at its plateau F2 in every run
METRICS = ("max_stroke_m", "final_stroke_m", "peak_strut_force_N", "peak_normal_force_N")
COLORS = dict(euler="C0", euler_implicit="C1", verlet="C2", verlet_smooth="C7", leapfrog="C8",
              impulse="C3", tsit5="C4", numba_euler="k", scipy_LSODA="C5", scipy_Radau="C6")
SMOOTH = dict(method="verlet", smoothing_m=1e-6, smoothing_N=10.0)  # smoothed fitting option


def scenes(t_end=1.2):
    """name -> (vehicle, scene, t_end)."""
    veh = jl.paper_vehicle()
    harsh = eqx.tree_at(lambda v: v.leg.D_b, veh, 0.0)
    return {"paper": (veh, Scene(), t_end), "harsh": (harsh, Scene(drop_height=0.25), t_end)}


def ladders(vehicle, small=False):
    """method -> list of Solver keyword sets, coarse to fine."""
    lim_e = float(stable_step(vehicle))
    lim_i = float(stable_step(vehicle, method="verlet"))
    lim_l = float(stable_step(vehicle, method="leapfrog"))

    def steps(limit, n):
        top = 2.0 ** math.floor(math.log2(0.9 * limit / 1e-6)) * 1e-6  # binary ladder in us
        return [top / 2**i for i in range(n)]

    n = 3 if small else 6
    out = {
        "euler": [dict(dt=d) for d in steps(lim_e, n)],
        "euler_implicit": [dict(dt=d) for d in steps(lim_i, n + 1)],
        "verlet": [dict(dt=d) for d in steps(lim_i, n + 1)],
        "verlet_smooth": [dict(dt=d, **SMOOTH) for d in steps(lim_i, n + 1)],
        "leapfrog": [dict(dt=d) for d in steps(lim_l, n)],
        "tsit5": [dict(dt=1e-5, rtol=r, atol=r * 1e-3)
                  for r in (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8)[:n]],
    }
    imp = []
    for d_i in (0.4, 0.2, 0.1, 0.05, 0.025, 0.0125)[:n]:
        cap = float(stable_step(vehicle, method="impulse", impulse=d_i))
        cap = 2.0 ** math.floor(math.log2(0.9 * cap / 1e-6)) * 1e-6
        imp.append(dict(dt=cap, impulse=d_i))
    out["impulse"] = imp
    return out


def _solver(label, t_end, save_dt=1e-3, **kw):
    """A Solver for a chart label (a method, or a label whose settings name the method); the
    method's own options (impulse, rtol, atol, max_steps, adjoint) go to ``jl.integrator``."""
    method = kw.pop("method", label)
    dt = kw.pop("dt")
    save = max(1, round(save_dt / dt)) * dt
    smoothing = {k: kw.pop(k) for k in ("smoothing_m", "smoothing_N") if k in kw}
    return Solver(dt=dt, t_end=t_end, save_dt=save, method=jl.integrator(method, **kw),
                  **smoothing)


def _reverse(solver):
    """The same solver with reverse-mode gradients (the variable-step methods carry an adjoint
    option; the fixed-step ones take jax.grad as they are)."""
    if hasattr(solver.method, "adjoint"):
        return dataclasses.replace(solver,
                                   method=dataclasses.replace(solver.method, adjoint="reverse"))
    return solver


def _run(vehicle, scene, solver, repeats):
    def fn(v):
        traj, s = landing(v, scene, solver, "quarter")
        return traj["time_s"], traj["stroke_m"], s
    (t, stroke, s), compile_s, run_s = _timed(fn, (vehicle,), repeats)
    s = {k: np.asarray(v) for k, v in s.items()}
    ok = (not bool(s["failed"]) and bool(s["solver_ok"])
          and float(s["ledger_error_rel"]) <= CLOSURE_LIMIT)
    return dict(time=np.asarray(t), stroke=np.asarray(stroke), summary=s, ok=ok,
                compile_s=compile_s, run_s=run_s)


def _errors(run, ref):
    out = {m: abs(float(run["summary"][m]) / max(float(ref["summary"][m]), 1e-300) - 1.0)
           for m in METRICS}
    n = min(len(run["stroke"]), len(ref["stroke"]))
    t_ref = ref["time"][:n]
    trace = np.interp(t_ref, run["time"], run["stroke"])
    scale = np.sqrt(np.mean(ref["stroke"][:n] ** 2))
    out["trace_rms"] = float(np.sqrt(np.mean((trace - ref["stroke"][:n]) ** 2)) / scale)
    return out


def work_precision(small=False, repeats=5, progress=print):
    results = {}
    for name, (veh, scene, t_end) in scenes(0.5 if small else 1.2).items():
        # the reference is second order: Euler's error at 1.25e-6 s wandered by 4e-5 in max
        # stroke (3.6e-5 off, its change from 2 dt only 1.5e-5), verlet's settles to 3e-7
        fine_dt = 1e-5 if small else 2.5e-6
        ref = _run(veh, scene, _solver("verlet", t_end, dt=fine_dt), 1)
        check = _run(veh, scene, _solver("verlet", t_end, dt=2 * fine_dt), 1)
        entry = dict(reference=dict(method="verlet", dt=fine_dt,
                                    **{m: float(ref["summary"][m]) for m in METRICS},
                                    change_from_2dt=_errors(check, ref)),
                     runs=[])
        for method, settings in ladders(veh, small).items():
            for kw in settings:
                r = _run(veh, scene, _solver(method, t_end, **kw), repeats)
                row = dict(kw, method=method, solver_method=kw.get("method", method))
                row.update(ok=r["ok"], wall_s=r["run_s"],
                           compile_s=r["compile_s"], n_steps=int(r["summary"]["n_steps"]),
                           ledger_error_rel=float(r["summary"]["ledger_error_rel"]))
                if r["ok"]:
                    row["errors"] = _errors(r, ref)
                entry["runs"].append(row)
                progress(f"  {name:6s} {method:15s} {kw} -> {r['run_s'] * 1e3:8.2f} ms, "
                         f"max-stroke error "
                         f"{row.get('errors', {}).get('max_stroke_m', float('nan')):.2e}")
        entry["baseline_reference"] = dict(
            t=ref["time"].tolist(), stroke_m=ref["stroke"].tolist())
        results[name] = entry
    return results


DEFAULT_SETTINGS = dict(euler=dict(dt=1e-5), euler_implicit=dict(dt=2e-5),
                        verlet=dict(dt=2e-5), verlet_smooth=dict(dt=1e-5, **SMOOTH),
                        leapfrog=dict(dt=2e-5),
                        impulse=dict(dt=5e-5, impulse=0.05),
                        tsit5=dict(dt=1e-5, rtol=1e-6, atol=1e-9))


def throughput_and_gradients(small=False, repeats=3, progress=print):
    """Landings/s against batch size, and gradient cost, at each method's chart setting."""
    veh, scene, _ = scenes()["paper"]
    t_end = 0.3 if small else 1.2
    sizes = (1, 8) if small else (1, 10, 100, 1000)
    out = {}
    for method, kw in DEFAULT_SETTINGS.items():
        solver = _solver(method, t_end, **dict(kw))
        rows = []
        for n in sizes:
            batch = Scene.batch(drop_height=jnp.linspace(0.1, 0.4, n))
            _, c_s, r_s = _timed(
                lambda sc: landings(veh, sc, solver, "quarter")[1]["max_stroke_m"], (batch,),
                1 if n >= 1000 else repeats)
            rows.append(dict(batch=n, compile_s=c_s, run_s=r_s, landings_per_s=n / r_s))

        def loss(theta, solver):
            new = tuple(p * jnp.exp(t) for p, t in zip(_params(veh), theta))
            _, s = landing(eqx.tree_at(_params, veh, new), scene, solver, "quarter")
            return s["max_stroke_m"] + 1e-6 * s["peak_normal_force_N"]

        theta = jnp.zeros(6)
        _, c_f, t_f = _timed(lambda th: loss(th, solver), (theta,), repeats)
        def gradient_cost(mode, fn, solver):
            """(compile, run) of a gradient, NaN where jaxland refuses it (tsit5's gradients
            are wrong, so differentiating through it raises ConfigError) or it fails."""
            try:
                return _timed(fn(lambda th: loss(th, solver)), (theta,), repeats)[1:]
            except jl.ConfigError as err:
                progress(f"  {mode} refused for {method}: {err}")
            except Exception as err:  # noqa: BLE001 - record what failed, keep benchmarking
                progress(f"  {mode} failed for {method}: {type(err).__name__}")
            return float("nan"), float("nan")

        c_j, t_j = gradient_cost("jacfwd", jax.jacfwd, solver)
        c_g, t_g = gradient_cost("grad", jax.grad, _reverse(solver))
        out[method] = dict(setting=kw, batches=rows, forward_s=t_f, compile_forward_s=c_f,
                           jacfwd6_s=t_j, jacfwd_ratio=t_j / t_f, grad_s=t_g,
                           grad_ratio=t_g / t_f, compile_jacfwd_s=c_j, compile_grad_s=c_g)
        progress(f"  {method:15s} forward {t_f * 1e3:.2f} ms, jacfwd {t_j / t_f:.1f}x, "
                 f"grad {t_g / t_f:.1f}x, batch {sizes[-1]}: {rows[-1]['landings_per_s']:.0f}/s")
    return out


def full_model_batch(small=False, progress=print):
    """Full 3-D model, a batch of dispersed landings (the Monte Carlo example spec): landings/s
    of the fixed-step methods against their max-stroke and peak-acceleration difference from
    Euler at a quarter of the default step."""
    spec = jl.load_montecarlo_spec(ROOT / "examples" / "montecarlo_dispersed.toml")
    n, t_end = (8, 0.3) if small else (64, 1.0)
    scenes, _ = jl.sample_scenes(spec, 0, n)
    veh = jl.paper_vehicle()

    def run(method, dt, repeats):
        solver = Solver(dt=dt, t_end=t_end, save_dt=t_end, method=method)
        f = lambda sc: {k: landings(veh, sc, solver, "full")[1][k]  # noqa: E731
                        for k in ("max_stroke_m", "peak_body_accel_mps2", "failed")}
        out, c_s, r_s = _timed(f, (scenes,), repeats)
        return {k: np.asarray(v) for k, v in out.items()}, c_s, r_s

    ref, _, _ = run("euler", 2.5e-6, 1)
    rows = []
    for method, dt in (("euler", 1e-5), ("euler_implicit", 2e-5), ("euler_implicit", 4e-5),
                       ("verlet", 4e-5), ("leapfrog", 4e-5)):
        out, c_s, r_s = run(method, dt, 1 if small else 3)
        d_stroke = np.abs(out["max_stroke_m"].max(axis=1) / ref["max_stroke_m"].max(axis=1) - 1)
        d_acc = np.abs(out["peak_body_accel_mps2"] / ref["peak_body_accel_mps2"] - 1)
        rows.append(dict(method=method, dt=dt, batch=n, t_end_s=t_end, compile_s=c_s,
                         run_s=r_s, landings_per_s=n / r_s, n_failed=int(out["failed"].sum()),
                         max_stroke_diff_median=float(np.median(d_stroke)),
                         max_stroke_diff_max=float(np.max(d_stroke)),
                         peak_accel_diff_median=float(np.median(d_acc))))
        progress(f"  full 3-D {method:15s} dt {dt:g}: {n / r_s:.1f} landings/s, max stroke "
                 f"off by {np.median(d_stroke):.1e} (median), {np.max(d_stroke):.1e} (max)")
    return rows


def _fails(veh, scene, method, t_end, **kw):
    r = _run(veh, scene, _solver(method, t_end, save_dt=kw["dt"], **kw), 1)
    return not r["ok"]


def stability_map(small=False, progress=print):
    """Largest step each fixed-step method survives, by bisection, next to the theory."""
    out = {}
    t_end = 0.4 if small else 0.6
    iters = 4 if small else 7
    for name, (veh, scene, _) in scenes().items():
        rows = []
        cases = [(m, {}, float(stable_step(veh, method=m)))
                 for m in ("euler", "euler_implicit", "verlet", "leapfrog")]
        cases.append(("impulse", {"impulse": 0.05},
                      float(stable_step(veh, method="impulse", impulse=0.05))))
        for method, kw, theory in cases:
            lo, hi = 0.5 * theory, 2.0 * theory
            if _fails(veh, scene, method, t_end, dt=lo, **kw) or not _fails(
                    veh, scene, method, t_end, dt=hi, **kw):
                rows.append(dict(method=method, **kw, theory_s=theory, failure_s=None))
                continue
            for _ in range(iters):
                mid = math.sqrt(lo * hi)
                lo, hi = (lo, mid) if _fails(veh, scene, method, t_end, dt=mid, **kw) \
                    else (mid, hi)
            rows.append(dict(method=method, **kw, theory_s=theory, survives_s=lo,
                             failure_s=hi, ratio=math.sqrt(lo * hi) / theory))
            progress(f"  {name:6s} {method:15s} theory {theory:.3g} s, fails at "
                     f"{math.sqrt(lo * hi):.3g} s ({math.sqrt(lo * hi) / theory:.2f}x)")
        out[name] = rows
    return out


def _baselines(data: dict | None, refs: dict):
    """Numba/scipy runs from benchmarks/baselines.py, with errors against our references (the
    stroke-trace error only where the raw baseline dump with its traces is there)."""
    if not data:
        return {}
    out = {}
    for name, ref in refs.items():
        rows = []
        for run in (data.get("scenes", {}).get(name, {}).get("runs", [])):
            if not run.get("success") or run.get("skipped") or run.get("wall_s") is None:
                continue
            errs = {m: abs(run[m] / ref[m] - 1.0) for m in METRICS if run.get(m) is not None}
            if run.get("stroke_m") is not None:  # the same 1 ms grid from t = 0
                trace = np.asarray(ref["trace"])
                got = np.asarray(run["stroke_m"], dtype=float)[:len(trace)]
                errs["trace_rms"] = float(np.sqrt(np.mean((got - trace[:len(got)]) ** 2))
                                          / np.sqrt(np.mean(trace ** 2)))
            setting = (f"dt={run['dt_s']:g}" if run.get("dt_s") is not None
                       else f"rtol={run['rtol']:g}")
            rows.append(dict(method=run["method"], setting=setting, wall_s=run["wall_s"],
                             errors=errs))
        out[name] = rows
    return out


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    return save_png(fig, path)


def _figure(nrows=1, ncols=1, **kw):
    """A figure without pyplot (no global backend state): (figure, axes)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=kw.pop("figsize"))
    return fig, fig.subplots(nrows, ncols, **kw)


def plot(results: dict, out_dir: Path) -> list[Path]:
    paths = []
    wp = results["work_precision"]
    cols = (*METRICS, "trace_rms")
    fig, axes = _figure(len(wp), len(cols), figsize=(4 * len(cols), 3.6 * len(wp)),
                             squeeze=False)
    for i, (name, entry) in enumerate(wp.items()):
        for j, metric in enumerate(cols):
            ax = axes[i, j]
            for method in COLORS:
                pts = [(r["wall_s"], r["errors"][metric]) for r in entry["runs"]
                       if r["method"] == method and metric in r.get("errors", {})]
                pts += [(r["wall_s"], r["errors"][metric])
                        for r in results.get("baselines", {}).get(name, [])
                        if r["method"] == method and metric in r["errors"]]
                if pts:
                    x, y = zip(*sorted(pts))
                    ax.loglog(x, np.maximum(y, 1e-12), "o-", color=COLORS[method], label=method,
                              ms=4)
            ax.set_xlabel("wall time per landing [s]")
            ax.set_ylabel(f"relative error, {metric}")
            ax.set_title(f"{name}: {metric}", fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    paths.append(_save(fig, out_dir / "integrators_work_precision.png"))

    tg = results["throughput"]
    fig, (a1, a2) = _figure(1, 2, figsize=(11, 4))
    for method, d in tg.items():
        a1.loglog([r["batch"] for r in d["batches"]], [r["landings_per_s"] for r in d["batches"]],
                  "o-", color=COLORS[method], label=f"{method} {d['setting']}")
    nb = results.get("numba_batch")
    if nb:
        a1.loglog([r["batch"] for r in nb["rows"]], [r["landings_per_s"] for r in nb["rows"]],
                  "s--", color="k", label=f"numba Euler dt={nb['dt_s']:g}, "
                                          f"{nb['threads']} threads (prange)")
    a1.set_xlabel("batch size (vmap)")
    a1.set_ylabel("landings per second")
    a1.legend(fontsize=6)
    a1.grid(True, which="both", alpha=0.3)
    names = list(tg)
    x = np.arange(len(names))
    a2.bar(x - 0.2, [tg[m]["jacfwd_ratio"] for m in names], 0.4, label="jacfwd, 6 parameters")
    a2.bar(x + 0.2, [tg[m]["grad_ratio"] for m in names], 0.4, label="grad")
    a2.set_xticks(x, names, rotation=20, fontsize=8)
    a2.set_ylabel("cost / one forward landing [1]")
    a2.legend(fontsize=8)
    paths.append(_save(fig, out_dir / "integrators_throughput.png"))

    sm = results["stability"]
    fig, ax = _figure(figsize=(7, 4))
    for k, (name, rows) in enumerate(sm.items()):
        for i, r in enumerate(rows):
            y = i + 0.2 * k
            ax.plot(r["theory_s"], y, "k|", ms=14)
            if r.get("failure_s"):
                ax.plot([r["survives_s"], r["failure_s"]], [y, y], "-",
                        color="C3" if k else "C0", lw=4, label=name if i == 0 else None)
    ax.set_yticks(range(len(sm["paper"])), [r["method"] for r in sm["paper"]])
    ax.set_xscale("log")
    ax.set_xlabel("step dt (impulse: its cap, dI = 0.05 N s) [s]; | = theory (stable_step)")
    ax.set_title("stability boundary: last stable .. first failing step")
    ax.legend(fontsize=8)
    paths.append(_save(fig, out_dir / "integrators_stability.png"))
    return paths


def _baseline_data() -> dict | None:
    """benchmarks/baselines.py's results: the raw dump (with stroke traces) if it is there,
    else the committed summary."""
    for path in (RESULTS / "raw" / "baselines_raw.json", RESULTS / "baselines.json"):
        if path.exists():
            return json.loads(path.read_text())
    return None


def run_integrator_benchmark(out_dir: Path, *, small: bool = False, progress=print) -> dict:
    out_dir = Path(out_dir)
    progress("work-precision ...")
    wp = work_precision(small, repeats=2 if small else 5, progress=progress)
    progress("throughput and gradient cost ...")
    tg = throughput_and_gradients(small, progress=progress)
    progress("stability map ...")
    sm = stability_map(small, progress=progress)
    progress("full 3-D model, batched ...")
    full = full_model_batch(small, progress=progress)
    refs = {n: dict(e["reference"], trace=e["baseline_reference"]["stroke_m"])
            for n, e in wp.items()}
    base_data = _baseline_data()
    base = _baselines(base_data, refs)
    numba_batch = base_data.get("batch_throughput") if base_data else None
    for e in wp.values():
        e.pop("baseline_reference")
    results = dict(machine=machine(), small=small, work_precision=wp, throughput=tg,
                   stability=sm, full_model=full, baselines=base, numba_batch=numba_batch)
    write_json(raw_dir(out_dir) / "integrators_raw.json", results)
    write_json(out_dir / "integrators.json", rounded(results))
    plot(results, out_dir)
    return results


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_out_args(p)
    args = p.parse_args(argv)
    out = out_dir(args.out, args.quick)
    run_integrator_benchmark(out, small=args.quick)
    print(f"wrote {out / 'integrators.json'}, integrators_*.png and "
          f"{raw_dir(out) / 'integrators_raw.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
