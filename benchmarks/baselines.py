"""Non-JAX baselines for the quarter model (issue #3): a numba loop and scipy ``solve_ivp``.

    python benchmarks/baselines.py            # full benchmark -> benchmarks/results/baselines.json
                                              #   (+ raw/baselines_raw.json with the traces)
    python benchmarks/baselines.py --check    # quick verification only; exit 1 on mismatch
    python benchmarks/baselines.py --quick    # fewer runs (smoke test) -> out/bench-quick/
    python benchmarks/baselines.py --side-by-side  # one landing against the numba loop
                                              #   -> benchmarks/results/numba_side_by_side.json

Needs the optional ``bench`` extra (``pip install -e ".[bench]"``: numba and scipy). Without it
this module still imports (``NUMBA_AVAILABLE`` is False and the kernels are plain Python); the
runners then raise ``RuntimeError`` naming the extra, and the CLI exits with code 2.

What is here
------------
1. ``forces``: a plain-float scalar port of ``QuarterModel.evaluate``
   (``jaxland._models._quarter``) and every law it calls (two-stage honeycomb with permanent
   set, elastic unloading and bottoming; strut damping with its floor; top-out stop; the
   auxiliary strut pair; normal contact with pit memory and chi damping; tangential stick/slip
   return map). Parameters are one float64 vector (``P_*`` indices) built by ``params_vector``
   from the jaxland ``Vehicle`` with jaxland's own derived numbers (``Honeycomb.curve()``,
   ``Leg.L_a0_pair``, ``Leg.foot_rest``, ``Vehicle.m_quarter``).
2. ``euler_run`` / ``euler_batch``: numba loops of jaxland's fixed-step symplectic Euler (forces
   and return-mapped memories at (q_n, v_n); v_{n+1} = v_n + dt a; q_{n+1} = q_n + dt v_{n+1}),
   the compiled-loop limit. Peaks are running maxima over the evaluated states s_0 .. s_{N-1}
   (full step resolution, as jaxland); max stroke is the x_max memory at the end; the final
   stroke is the stroke at s_N. Failure = non-finite state or an energy-ledger residual above
   0.1 x the energy scale (jaxland's ENERGY_TOLERANCE); the loop stops at the first failure.
   ``euler_batch`` runs landings in parallel with ``numba.prange`` (2 threads).
3. ``rhs``: a continuous right-hand side for ``scipy.integrate.solve_ivp`` with the memories in
   rate form (the spec the JAX diffrax path also uses):
       y = (z_b, r_f, z_f, vz_b, vr_f, vz_f, x_max, d_max, anchor,
            E_struct_damp, E_ground_damp, E_slip)
   q' = v; v' from ``forces`` with the current memories; x_max' = max(v_b, 0) if x_b >= x_max
   else 0; d_max' = max(d_dot, 0) if d >= d_max else 0 (d = -z_f); anchor' = vr_f off the
   ground, 0 while sticking, vr_f - s mu k_r d_dot / k_tan while slipping (s = sign(r_f -
   anchor), spring force > 0); the energies integrate the strut damping power, the ground
   damping power and mu F_n |anchor'| while slipping.
4. ``run_benchmark``: numba Euler over dt, scipy LSODA and Radau over rtol, on the "paper" and
   "harsh" scenes, plus batched numba throughput; writes ``benchmarks/results/baselines.json``
   (the summary: no stroke traces, repeat times or atol vectors; floats to 4 digits) and the
   full dump ``benchmarks/results/raw/baselines_raw.json`` (ignored by git).

JSON schema (benchmarks/results/raw/baselines_raw.json; the summary drops the marked fields)
-----------------------------------------------
{
  "schema": "jaxland-baselines/1",
  "created_utc": str, "machine": {"platform", "python", "numpy", "scipy", "numba", "cpu_count",
                                  "numba_threads"},
  "notes": {str: str},                   # how each number is measured (timing, peaks, atol)
  "save_grid": {"save_dt_s": float, "t_end_s": float, "n": int},   # t_k = k save_dt, k=0..n-1
  "compile_s": {"euler_run": float, "euler_batch": float, "rhs": float, "forces_grid": float},
  "check": {...}                         # the --check verification numbers (see ``check``)
  "scenes": {
    "paper" | "harsh": {
      "description": str, "drop_height_m": float, "D_b_s_per_m": float, "t_end_s": float,
      "energy_scale_J": float,
      "reference": {"method": "numba_euler", "dt_s": 2.5e-6, "max_stroke_m": ..., ...},
      "runs": [                          # one entry per (method, setting)
        {"method": "numba_euler" | "scipy_LSODA" | "scipy_Radau",
         "dt_s": float | null,           # numba Euler step
         "rtol": float | null, "atol": [12 floats] | null,   # scipy tolerances (atol: raw only)
         "success": bool, "message": str, "warnings": [str],
         "skipped": bool,                # Radau beyond the wall-time cap (not run)
         "wall_s": float | null,         # wall time per landing, median of "repeats"
         "repeats": int, "wall_all_s": [float],   # (wall_all_s: raw only)
         "n_steps": int | null,          # Euler steps, or scipy accepted steps
         "nfev": int | null, "njev": int | null, "nlu": int | null,
         "max_stroke_m", "final_stroke_m", "peak_honeycomb_force_N", "peak_normal_force_N",
         "energy_residual_max_J": float | null,   # |ledger residual| (max for Euler, end for scipy)
         "failure_time_s": float | null,
         "rel_err": {"max_stroke_m", "final_stroke_m", "peak_honeycomb_force_N",
                     "peak_normal_force_N", "stroke_trace_rms_m"}   # vs "reference"
                                                                    # (trace RMS is absolute, m)
         "stroke_m": [float] | null},    # stroke on the save grid (null if the run failed early;
                                         # raw only)
      ]
    }
  },
  "batch_throughput": {"scene": "paper", "dt_s": 1e-5, "threads": 2,
                       "drop_heights": "linspace(0.05, 0.5, n)",
                       "rows": [{"batch": n, "wall_s": float, "repeats": int,
                                 "landings_per_s": float}]}
}
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from _baseline_port import (
    ATOL_SCALE,
    BATCH_SIZES,
    ENERGY_TOLERANCE,
    EULER_DTS,
    FINE_DT,
    MISSING_MESSAGE,
    NUMBA_AVAILABLE,
    OUT,
    RADAU_CAP_S,
    REFERENCE_DT,
    RTOLS,
    RUN_DEADLINE_S,
    SAVE_DT,
    SCIPY_AVAILABLE,
    T_END,
    THREADS,
    Y_NAMES,
    _require,
    energy_scale,
    euler_batch_kernel,
    euler_prepare,
    euler_result,
    euler_run,
    euler_run_kernel,
    forces_on_grid,
    initial_state,
    numba,
    params_vector,
    rhs,
    scipy,
    scipy_run,
)

# ---------------------------------------------------------------------------- verification

SUMMARY_KEYS = ("max_stroke_m", "final_stroke_m", "peak_honeycomb_force_N",
                "peak_normal_force_N")


def _rel(a, b):
    return abs(a - b) / max(abs(b), 1e-300)


def check(verbose=True, jax_tol=1e-9, ivp_tol=1e-4, ivp_method="LSODA",
          ivp_deadline_s=RUN_DEADLINE_S) -> dict:
    """Step 2 and 3 verification: numba Euler vs jaxland at dt = 1e-5 s (summary and stroke
    trace, relative), and a tight solve_ivp (rtol 1e-10) vs the fine numba Euler (dt = FINE_DT)
    on max stroke. Returns the numbers with ``ok``."""
    _require()
    import jaxland as jl

    vehicle, scene = jl.paper_vehicle(), jl.Scene()
    solver = jl.Solver(dt=1e-5, t_end=T_END, save_dt=SAVE_DT)
    traj, summ = jl.landing(vehicle, scene, solver, model="quarter")
    traj = {k: np.asarray(v) for k, v in traj.items()}
    ours = euler_run(vehicle, scene, 1e-5)
    rel = {k: _rel(ours[k], float(summ[k])) for k in SUMMARY_KEYS}
    n = len(traj["stroke_m"])
    s_j, s_n = traj["stroke_m"], ours["record"][:n, 9]
    scale = np.max(np.abs(s_j))
    rel["stroke_trace_max_abs_over_max"] = float(np.max(np.abs(s_n - s_j)) / scale)
    for name, col in (("foot_r_m", 1), ("foot_z_m", 2), ("body_z_m", 0)):
        rel[f"{name}_trace_max_abs_m"] = float(np.max(np.abs(ours["record"][:n, col]
                                                             - traj[name])))
    rel["time_grid_max_abs_s"] = float(np.max(np.abs(ours["time_s"][:n] - traj["time_s"])))
    ok_jax = all(rel[k] <= jax_tol for k in SUMMARY_KEYS) and \
        rel["stroke_trace_max_abs_over_max"] <= jax_tol
    out = dict(
        numba_vs_jaxland=dict(
            dt_s=1e-5, tolerance_rel=jax_tol, ok=bool(ok_jax), rel_err=rel,
            jaxland={k: float(summ[k]) for k in SUMMARY_KEYS},
            numba={k: ours[k] for k in SUMMARY_KEYS}),
    )
    if verbose:
        print("numba Euler vs jaxland (dt = 1e-5 s):")
        for k, v in rel.items():
            print(f"  {k:36s} {v:.3e}")
    fine = euler_run(vehicle, scene, FINE_DT)
    ivp = scipy_run(vehicle, scene, ivp_method, 1e-10, deadline_s=ivp_deadline_s)
    e_ivp = _rel(ivp.get("max_stroke_m", np.nan), fine["max_stroke_m"])
    coarse = euler_run(vehicle, scene, 2 * FINE_DT)
    e_coarse = _rel(coarse["max_stroke_m"], fine["max_stroke_m"])
    # first-order extrapolation of the Euler limit (Richardson): 2 x fine - coarse
    extrap = 2 * fine["max_stroke_m"] - coarse["max_stroke_m"]
    e_extrap = _rel(ivp.get("max_stroke_m", np.nan), extrap)
    ok_ivp = bool(ivp["success"]) and e_ivp <= ivp_tol
    out["scipy_vs_fine_euler"] = dict(
        method=ivp_method, rtol=1e-10, euler_dt_s=FINE_DT, tolerance_rel=ivp_tol, ok=ok_ivp,
        success=bool(ivp["success"]), message=ivp.get("message"), wall_s=ivp["wall_s"],
        max_stroke_m_scipy=ivp.get("max_stroke_m"), max_stroke_m_euler=fine["max_stroke_m"],
        max_stroke_m_euler_2dt=coarse["max_stroke_m"],
        max_stroke_m_euler_richardson=extrap,
        rel_err_max_stroke=e_ivp, rel_err_euler_dt_vs_2dt=e_coarse,
        rel_err_scipy_vs_richardson=e_extrap,
        rel_err_final_stroke=_rel(ivp.get("final_stroke_m", np.nan), fine["final_stroke_m"]),
        rel_err_peak_honeycomb_force=_rel(ivp.get("peak_honeycomb_force_N", np.nan),
                                          fine["peak_honeycomb_force_N"]),
        rel_err_peak_normal_force=_rel(ivp.get("peak_normal_force_N", np.nan),
                                       fine["peak_normal_force_N"]),
    )
    if verbose:
        print(f"scipy {ivp_method} rtol 1e-10 vs numba Euler dt = {FINE_DT:g} s:")
        for k, v in out["scipy_vs_fine_euler"].items():
            print(f"  {k:36s} {v}")
    out["ok"] = bool(ok_jax and ok_ivp)
    return out


# ------------------------------------------------------------------------------ benchmark

def scenes():
    """The two benchmark scenes: (name, vehicle, scene, description)."""
    import equinox as eqx

    import jaxland as jl

    paper = jl.paper_vehicle()
    harsh = eqx.tree_at(lambda v: v.leg.D_b, paper, 0.0)
    return [
        ("paper", paper, jl.Scene(), "paper vehicle, Scene() default: 0.2 m drop"),
        ("harsh", harsh, jl.Scene(drop_height=0.25),
         "paper vehicle with leg D_b = 0 (no structural damping), 0.25 m drop (separations, "
         "no bottoming out; benchmarks/bench_integrators.py uses the same scene)"),
    ]


def _timed(fn, long_s=5.0, repeats=3):
    """``fn()`` returns (result, wall_s). Run it once; if that took under ``long_s``, run it
    ``repeats`` more times and report the median of those (the first call is the warm-up).
    Returns (result, median wall, walls)."""
    res, first = fn()
    if first >= long_s:
        return res, first, [first]
    walls = []
    for _ in range(repeats):
        res, w = fn()
        walls.append(w)
    return res, statistics.median(walls), walls


def _clock(fn):
    t0 = time.perf_counter()
    res = fn()
    return res, time.perf_counter() - t0


def _finite_or_none(x):
    return float(x) if x is not None and np.isfinite(x) else None


def _rel_errs(run, ref):
    out = {}
    for k in SUMMARY_KEYS:
        v = run.get(k)
        out[k] = _finite_or_none(_rel(v, ref[k])) if v is not None else None
    s = run.get("stroke_m")
    if s is not None:
        d = np.asarray(s) - np.asarray(ref["stroke_m"])
        out["stroke_trace_rms_m"] = _finite_or_none(float(np.sqrt(np.mean(d * d))))
    else:
        out["stroke_trace_rms_m"] = None
    return out


def _euler_entry(vehicle, scene, dt, t_end):
    args = euler_prepare(vehicle, scene, dt, t_end)
    (out, rec), wall, walls = _timed(lambda: _clock(lambda: euler_run_kernel(*args)))
    res = euler_result(out, rec)
    stroke = res["record"][:, 9]
    ok = not res["failed"]
    msg = "ok" if ok else (f"failed at t = {res['failure_time_s']:.6g} s: non-finite state or "
                           f"|energy residual| > {ENERGY_TOLERANCE} x energy scale")
    return dict(method="numba_euler", dt_s=dt, rtol=None, atol=None, success=ok, message=msg,
                warnings=[], skipped=False, wall_s=wall, repeats=len(walls), wall_all_s=walls,
                n_steps=res["n_steps"], nfev=None, njev=None, nlu=None,
                **{k: _finite_or_none(res[k]) for k in SUMMARY_KEYS},
                energy_residual_max_J=_finite_or_none(res["energy_residual_max_J"]),
                failure_time_s=res["failure_time_s"],
                stroke_m=[_finite_or_none(x) for x in stroke] if ok else None)


def _scipy_entry(vehicle, scene, method, rtol, t_end, deadline_s):
    def once():
        r = scipy_run(vehicle, scene, method, rtol, t_end, deadline_s=deadline_s)
        return r, r["wall_s"]

    res, wall, walls = _timed(once)
    ok = bool(res["success"])
    stroke = res.get("stroke_m")
    return dict(method=f"scipy_{method}", dt_s=None, rtol=rtol, atol=res["atol"], success=ok,
                message=res["message"], warnings=res["warnings"], skipped=False, wall_s=wall,
                repeats=len(walls), wall_all_s=walls, n_steps=res.get("n_steps"),
                nfev=res.get("nfev"), njev=res.get("njev"), nlu=res.get("nlu"),
                **{k: _finite_or_none(res.get(k)) for k in SUMMARY_KEYS},
                energy_residual_max_J=_finite_or_none(res.get("energy_residual_max_J")),
                failure_time_s=None,
                stroke_m=[_finite_or_none(x) for x in stroke] if stroke is not None else None)


def _compile_times():
    """First-call (compile) times of the kernels: each is compiled lazily on first call."""
    import jaxland as jl

    out = {}
    v, s = jl.paper_vehicle(), jl.Scene()
    P, y0 = params_vector(v, s), initial_state(v, s)
    t0 = time.perf_counter()
    euler_run_kernel(P, y0, 1e-5, 10, 100.0, 1, 1.0)
    out["euler_run"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    euler_batch_kernel(P, np.ascontiguousarray(np.stack([y0[:9]] * 2)), 1e-5, 10,
                       np.ones(2))
    out["euler_batch"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rhs(0.0, y0, P)
    out["rhs"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    forces_on_grid(np.ascontiguousarray(y0[:, None]), P)
    out["forces_grid"] = time.perf_counter() - t0
    return out


def batch_throughput(sizes=BATCH_SIZES, dt=1e-5, t_end=T_END):
    import jaxland as jl

    vehicle = jl.paper_vehicle()
    rows = []
    for n in sizes:
        sc = [jl.Scene(drop_height=float(h)) for h in np.linspace(0.05, 0.5, n)]
        P = params_vector(vehicle, sc[0])
        Y0 = np.ascontiguousarray(np.stack([initial_state(vehicle, s)[:9] for s in sc]))
        es = np.array([energy_scale(P, s) for s in sc])
        n_steps = int(round(t_end / dt))
        out, wall, walls = _timed(lambda: _clock(lambda: euler_batch_kernel(P, Y0, dt, n_steps,
                                                                            es)))
        rows.append(dict(batch=n, wall_s=wall, repeats=len(walls), wall_all_s=walls,
                         landings_per_s=n / wall, n_failed=int(np.sum(out[:, 5] >= 0))))
        print(f"  batch {n:5d}: {wall:.4f} s  {n / wall:9.1f} landings/s", flush=True)
    return dict(scene="paper", dt_s=dt, t_end_s=t_end, threads=numba.get_num_threads(),
                drop_heights="linspace(0.05, 0.5, n)", rows=rows)


def _json_clean(x):
    """Non-finite floats (failed runs) become null; numpy scalars become Python numbers."""
    if isinstance(x, dict):
        return {k: _json_clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def run_benchmark(out_path=OUT, quick=False) -> dict:
    _require()
    numba.set_num_threads(THREADS)
    t_end = T_END
    compile_s = _compile_times()
    print("compile times [s]:", {k: round(v, 2) for k, v in compile_s.items()}, flush=True)
    print("verification (--check) ...", flush=True)
    chk = check(verbose=False)
    print(f"  ok = {chk['ok']}", flush=True)
    dts = EULER_DTS if not quick else (1.6e-4, 2e-5, 1e-5, REFERENCE_DT)
    rtols = RTOLS if not quick else (1e-3, 1e-6)
    result = dict(
        schema="jaxland-baselines/1",
        created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
        machine=dict(platform=platform.platform(), python=sys.version.split()[0],
                     numpy=np.__version__, scipy=scipy.__version__,
                     numba=numba.__version__, cpu_count=os.cpu_count(),
                     numba_threads=numba.get_num_threads()),
        notes=dict(
            timing="wall time per landing: one warm-up call, then the median of 3 repeats; "
                   "a run whose first call takes >= 5 s is reported from that single call. "
                   "numba kernels are compiled before (compile_s). scipy: solve_ivp only "
                   "(dense_output=True), post-processing excluded.",
            euler="jaxland's symplectic Euler; peaks over every evaluated step s_0..s_{N-1}; "
                  "max stroke = x_max memory at the end; final stroke at s_N = t_end. "
                  "Failure: non-finite state or |ledger residual| > 0.1 x energy scale; "
                  "the loop stops there.",
            scipy_peaks="max over the accepted steps and a 1e-5 s dense-output grid; "
                        "max_stroke_m = max(x_max state at t_end, stroke on that grid).",
            scipy_atol="atol_i = rtol * ATOL_SCALE_i with ATOL_SCALE = "
                       + json.dumps(dict(zip(Y_NAMES, ATOL_SCALE.tolist()))),
            scipy_rhs="rate-form memories (module docstring item 3) with the anchor rate made "
                      "consistent with the return map (rhs docstring, ANCHOR_CONSISTENT); "
                      "Jacobian by scipy's finite differences; max_step None; first_step None.",
            wall_cap=f"once a scipy run (LSODA or Radau) takes > {RADAU_CAP_S:.0f} s or fails, "
                     f"the tighter tolerances of that method are skipped; a single run is "
                     f"stopped at {RUN_DEADLINE_S:.0f} s (checked in the right-hand side)",
            reference=f"numba Euler at dt = {REFERENCE_DT:g} s per scene; rel_err = "
                      "|x - ref| / |ref|; stroke_trace_rms_m is the RMS difference of the "
                      "stroke on the save grid [m]",
        ),
        save_grid=dict(save_dt_s=SAVE_DT, t_end_s=t_end,
                       n=int(math.floor(t_end / SAVE_DT + 1e-9)) + 1),
        compile_s=compile_s,
        check=chk,
        scenes={},
    )
    for name, vehicle, scene, desc in scenes():
        print(f"scene {name}: {desc}", flush=True)
        P = params_vector(vehicle, scene)
        runs = []
        for dt in dts:
            e = _euler_entry(vehicle, scene, dt, t_end)
            runs.append(e)
            print(f"  euler dt={dt:8.2e}: {e['wall_s'] * 1e3:9.2f} ms  ok={e['success']}  "
                  f"max_stroke={e['max_stroke_m']}", flush=True)
        ref_run = next(r for r in runs if r["dt_s"] == REFERENCE_DT)
        ref = {k: ref_run[k] for k in SUMMARY_KEYS}
        ref["stroke_m"] = ref_run["stroke_m"]
        for method in ("LSODA", "Radau"):
            capped = False
            for rtol in rtols:
                if capped:
                    runs.append(dict(method=f"scipy_{method}", dt_s=None, rtol=rtol, atol=None,
                                     success=False, skipped=True,
                                     message=f"skipped: a looser tolerance took > "
                                             f"{RADAU_CAP_S:.0f} s or failed",
                                     warnings=[], wall_s=None, repeats=0, wall_all_s=[],
                                     n_steps=None, nfev=None, njev=None, nlu=None,
                                     **{k: None for k in SUMMARY_KEYS},
                                     energy_residual_max_J=None, failure_time_s=None,
                                     stroke_m=None))
                    continue
                e = _scipy_entry(vehicle, scene, method, rtol, t_end, RUN_DEADLINE_S)
                runs.append(e)
                print(f"  {method:5s} rtol={rtol:7.0e}: {e['wall_s']:8.3f} s  "
                      f"ok={e['success']}  max_stroke={e['max_stroke_m']}  "
                      f"{e['message'][:60]!r} {e['warnings'][:1]}", flush=True)
                if e["wall_s"] > RADAU_CAP_S or not e["success"]:
                    capped = True
        for r in runs:
            r["rel_err"] = _rel_errs(r, ref)
        result["scenes"][name] = dict(
            description=desc, drop_height_m=float(scene.drop_height),
            D_b_s_per_m=float(vehicle.leg.D_b), t_end_s=t_end,
            energy_scale_J=energy_scale(P, scene),
            reference=dict(method="numba_euler", dt_s=REFERENCE_DT,
                           **{k: ref[k] for k in SUMMARY_KEYS}),
            runs=runs)
    print("batched numba throughput:", flush=True)
    result["batch_throughput"] = batch_throughput(BATCH_SIZES if not quick else (1, 10, 100),
                                                  t_end=t_end)
    from _common import summarise_baselines, write_json

    out_path = Path(out_path)
    result = _json_clean(result)
    raw = out_path.parent / "raw" / f"{out_path.stem}_raw.json"
    write_json(raw, result)
    write_json(out_path, summarise_baselines(result))
    print(f"wrote {out_path} and {raw}")
    return result


# jaxland's bookkeeping settings timed against the numba loop (``side_by_side``)
SIDE_BY_SIDE = {
    "simulate's (every peak, ledger every step, 1 ms trajectory)": dict(save_dt=SAVE_DT),
    "about the numba loop's work (4 peaks, ledger every step, 1 ms trajectory)":
        dict(save_dt=SAVE_DT, peaks=()),
    "a Monte Carlo's (its peaks, ledger every 1e-3 s, no trajectory or event log)":
        dict(save_dt=T_END, peaks=("peak_body_accel_mps2",), ledger_every=100, event_log=0),
}


def side_by_side(repeats: int = 15, dt: float = 1e-5) -> dict:
    """One quarter landing (the paper drop, euler at ``dt``) in jaxland under jit with each
    bookkeeping of ``SIDE_BY_SIDE``, and in the numba loop of the same scheme, interleaved
    repeat by repeat in this process (CPU time, median): how far the compiled JAX loop is
    from a hand-written compiled loop."""
    _require()
    import jax

    import jaxland as jl

    vehicle, scene = jl.paper_vehicle(), jl.Scene()
    args = euler_prepare(vehicle, scene, dt, T_END)
    euler_run_kernel(*args)  # compile
    fns = {}
    for name, kw in SIDE_BY_SIDE.items():
        solver = jl.Solver(dt=dt, t_end=T_END, **kw).validate()
        fn = jax.jit(lambda s, solver=solver: jl.landing(vehicle, s, solver, "quarter"))
        jax.block_until_ready(fn(scene))
        fns[name] = lambda fn=fn: jax.block_until_ready(fn(scene))
    times = {"numba": [], **{k: [] for k in fns}}
    for _ in range(repeats):
        for name, fn in (("numba", lambda: euler_run_kernel(*args)), *fns.items()):
            c0 = time.process_time()
            fn()
            times[name].append(time.process_time() - c0)
    med = {k: statistics.median(v) for k, v in times.items()}
    return dict(scene="paper drop, quarter model", method="euler", dt_s=dt, t_end_s=T_END,
                repeats=repeats, timing="CPU time per landing, median of interleaved repeats",
                machine=dict(platform=platform.platform(), cpu_count=os.cpu_count(),
                             load_average_1min=os.getloadavg()[0]),
                numba_ms=med["numba"] * 1e3,
                jaxland=[dict(bookkeeping=k, ms=med[k] * 1e3, ratio_to_numba=med[k] / med["numba"])
                         for k in fns])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="verify numba vs jaxland and scipy vs fine Euler; exit 1 on mismatch")
    ap.add_argument("--quick", action="store_true", help="fewer settings (smoke test)")
    ap.add_argument("--side-by-side", action="store_true",
                    help="one landing in jaxland (three bookkeepings) against the numba loop "
                         "-> numba_side_by_side.json beside the output")
    ap.add_argument("--out", default=None,
                    help=f"JSON output path (default {OUT.relative_to(OUT.parents[2])}, or "
                         "out/bench-quick/baselines.json with --quick)")
    args = ap.parse_args(argv)
    if not (NUMBA_AVAILABLE and SCIPY_AVAILABLE):
        print(MISSING_MESSAGE, file=sys.stderr)
        return 2
    numba.set_num_threads(THREADS)
    if args.check:
        res = check()
        print("OK" if res["ok"] else "MISMATCH")
        return 0 if res["ok"] else 1
    from _common import out_dir

    out = Path(args.out) if args.out else None
    folder = out_dir(str(out.parent) if out else None, args.quick)  # refuses --quick in results
    if args.side_by_side:
        from _common import write_json

        res = side_by_side(3 if args.quick else 15)
        write_json(folder / "numba_side_by_side.json", res, indent=2)
        print(json.dumps(res, indent=2))
        return 0
    run_benchmark(folder / (out.name if out else OUT.name), quick=args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
