"""Benchmark of the calibration (issue #4): time a 6-parameter fit to one 1.2 s drop test at
5 kHz, check the recovery of the virtual rig's truth and the prediction of other drop heights.

    .venv/bin/python benchmarks/bench_fit.py [--with-lbfgs] [--out benchmarks/results]

Writes ``bench_fit.json`` and ``bench_fit.png``. The data are the bundled SYNTHETIC drop tests
(``data/synthetic``: noise, a 1.5 mm stroke offset and a +20 % honeycomb crush peak that the
model does not have). Targets: fit <= 20 s on the 2-core CPU; fitted at one drop height, the
prediction of another within 1 % on max stroke and 5 % on peak forces. Timings are wall-clock
on whatever machine runs this (noisy on shared machines); tests never assert them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import numpy as np  # noqa: E402

import calibration as cal  # noqa: E402
import jaxland as jl  # noqa: E402
from calibration import virtual_rig as vr  # noqa: E402
from calibration._parameters import get_values  # noqa: E402

DATA = ROOT / "data" / "synthetic"
TARGETS = dict(fit_s=20.0, max_stroke_rel=0.01, peak_force_rel=0.05)


def _fit(drops, **kw):
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cal.IdentifiabilityWarning)
        res = cal.fit(drops, **kw)
    return res, time.perf_counter() - t0


def _summary(res, wall, truth):
    p_true = get_values(truth, res.names)
    return dict(
        wall_s=wall, iterations=sum(s["iterations"] for s in res.stages),
        stages=[{k: s[k] for k in ("stage", "iterations", "status", "wall_s")}
                for s in res.stages],
        multistart=res.settings["multistart"]["n_starts_tried"],
        values=dict(zip(res.names, res.values.tolist())),
        rel_error=dict(zip(res.names, (res.values / p_true - 1).tolist())),
        rel_std_error=dict(zip(res.names, (res.std_errors / res.values).tolist())),
        z=dict(zip(res.names, ((res.values - p_true) / res.std_errors).tolist())),
        residual_variance_factor=res.sigma2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--with-lbfgs", action="store_true",
                    help="also time optax.lbfgs on the same fit (about 2 minutes)")
    ap.add_argument("--replot", action="store_true", help="only redraw the plot from the JSON")
    args = ap.parse_args(argv)
    if args.replot:
        path = Path(args.out) / "bench_fit.json"
        _plot(json.loads(path.read_text()), path.with_suffix(".png"))
        return 0
    truth = jl.load_vehicle(DATA / "truth_vehicle.toml")
    drops = {h: cal.load_drop_test(DATA / f"drop_h{h:.2f}m.toml") for h in vr.HEIGHTS_M}
    fit_drop = drops[0.2]
    names = cal.DEFAULT_PARAMS
    p_true = get_values(truth, names)
    out = dict(
        data="data/synthetic/drop_h0.20m (SYNTHETIC: 1.2 s at 5 kHz, noise, stroke offset, "
             "+20 % crush peak)",
        targets=TARGETS,
        machine=dict(platform=platform.platform(), cpus=os.cpu_count(), jax=jax.__version__,
                     backend=jax.default_backend()))

    # 1. the default fit from the nominal (paper) vehicle, cold (compiles) and warm
    res, cold = _fit([fit_drop])
    res2, warm = _fit([fit_drop])
    out["fit_from_nominal"] = dict(cold=_summary(res, cold, truth),
                                   warm=_summary(res2, warm, truth))
    print(f"fit from nominal: cold {cold:.1f} s, warm {warm:.1f} s", flush=True)

    # 2. prediction of the other heights with the fitted vehicle
    preds = {}
    for h, d in drops.items():
        p = cal.predict(res.vehicle, d)
        ref = cal.predict(truth, d)  # the truth itself against the data: the floor
        preds[f"{h:.2f}"] = dict(
            fitted={k: v["rel_error"] for k, v in p.metrics.items()},
            truth_model={k: v["rel_error"] for k, v in ref.metrics.items()})
        print(f"predict {h} m:", {k: f"{v['rel_error']:+.2%}" for k, v in p.metrics.items()})
    out["prediction"] = preds

    # 3. convergence from starts 30 % and 2x off the truth
    starts = {
        "30% off": [1.3, 0.77, 1.3, 0.77, 1.3, 1.3],
        "30% off (other signs)": [0.77, 1.3, 0.77, 1.3, 0.77, 0.77],
        "2x off": [2.0] * 6,
        "0.5x off": [0.5] * 6,
        "2x off mixed": [0.5, 1.5, 2.0, 0.5, 2.0, 1.5],
    }
    conv = {}
    for label, f in starts.items():
        r, w = _fit([fit_drop], start=dict(zip(names, p_true * np.array(f))),
                    vehicle=jl.paper_vehicle())
        conv[label] = _summary(r, w, truth)
        print(f"start {label}: {w:.1f} s, max |rel err| "
              f"{max(abs(x) for x in conv[label]['rel_error'].values()):.3%}", flush=True)
    out["convergence"] = conv

    # 4. noise-free data: recovery
    clean = vr.drop_test(0.2, noise=None, stroke_offset_m=0.0, crush_peak=0.0)
    r, w = _fit([clean], start=dict(zip(names, p_true * 2.0)), vehicle=jl.paper_vehicle())
    out["clean_recovery_from_2x"] = _summary(r, w, truth)

    # 5. joint fit of two heights, predict the third
    r, w = _fit([drops[0.15], drops[0.3]])
    p = cal.predict(r.vehicle, drops[0.2])
    out["joint_0.15_0.30"] = {"fit": _summary(r, w, truth),
                              "predict_0.20": {k: v["rel_error"] for k, v in p.metrics.items()}}

    if args.with_lbfgs:
        r, w = _fit([fit_drop], method="lbfgs", max_iter=300)
        out["lbfgs_from_nominal"] = _summary(r, w, truth)
        print(f"lbfgs: {w:.1f} s", flush=True)

    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    from calibration._report import atomic_write_text

    atomic_write_text(out_dir / "bench_fit.json", json.dumps(out, indent=2) + "\n")
    _plot(out, out_dir / "bench_fit.png")
    print(f"wrote {out_dir}/bench_fit.json and bench_fit.png")
    return 0


def _plot(out, path):
    from matplotlib.figure import Figure

    from calibration._report import atomic_savefig

    fig = Figure(figsize=(15, 4.5), layout="constrained")
    ax1, ax2, ax3 = fig.subplots(1, 3)
    labels, times = ["nominal (cold)", "nominal (warm)"], [
        out["fit_from_nominal"]["cold"]["wall_s"], out["fit_from_nominal"]["warm"]["wall_s"]]
    for k, v in out["convergence"].items():
        labels.append(k)
        times.append(v["wall_s"])
    if "lbfgs_from_nominal" in out:
        labels.append("L-BFGS (optax)")
        times.append(out["lbfgs_from_nominal"]["wall_s"])
    ax1.barh(labels, times, color="C0")
    ax1.axvline(TARGETS["fit_s"], color="C3", ls="--", label="target 20 s")
    ax1.set_xlabel("fit wall time [s]")
    ax1.set_title("6-parameter fit, 1.2 s drop at 5 kHz")
    ax1.legend()
    names = list(out["fit_from_nominal"]["cold"]["rel_error"])
    x = np.arange(len(names))
    cold = out["fit_from_nominal"]["cold"]
    clean = out["clean_recovery_from_2x"]
    ax2.bar(x - 0.2, [abs(cold["rel_error"][n]) * 100 for n in names], 0.4,
            label="crush-peak data (from nominal)")
    ax2.bar(x + 0.2, [abs(clean["rel_error"][n]) * 100 for n in names], 0.4,
            label="noise-free data (from 2x off)")
    ax2.plot(x - 0.2, [2 * cold["rel_std_error"][n] * 100 for n in names], "k_", ms=14,
             label="2 standard errors")
    ax2.set_yscale("log")
    ax2.set_xticks(x, names)
    ax2.set_ylabel("|fitted / truth - 1| [%]")
    ax2.set_title("recovery of the rig's truth")
    ax2.legend(fontsize=8)
    metrics = list(next(iter(out["prediction"].values()))["fitted"])
    x = np.arange(len(metrics))
    for k, (h, v) in enumerate(out["prediction"].items()):
        ax3.bar(x + (k - 1) * 0.27, [abs(v["fitted"][m]) * 100 for m in metrics], 0.27,
                label=f"{h} m" + (" (fitted here)" if h == "0.20" else ""))
        ax3.plot(x + (k - 1) * 0.27, [abs(v["truth_model"][m]) * 100 for m in metrics], "kx",
                 label="the truth itself vs the data" if k == 0 else None)
    ax3.axhline(TARGETS["peak_force_rel"] * 100, color="C3", ls="--", label="5 % (peaks)")
    ax3.axhline(TARGETS["max_stroke_rel"] * 100, color="C2", ls=":", label="1 % (stroke)")
    ax3.set_xticks(x, [m.replace("_", " ") for m in metrics], rotation=20, fontsize=8)
    ax3.set_ylabel("|model / data - 1| [%]")
    ax3.set_title("prediction, fitted at 0.20 m")
    ax3.legend(fontsize=8)
    atomic_savefig(fig, path)


if __name__ == "__main__":
    sys.exit(main())
