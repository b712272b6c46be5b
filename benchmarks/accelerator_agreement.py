"""Does a GPU compute the same landings as the CPU? On a machine with a GPU:

1. one landing per model on the GPU and on the same machine's CPU: the outcomes, and each
   one's time for a single landing;
2. the same Monte Carlo (each model's benchmark spec, fixed seed: identical samples) on the
   GPU in two chunk sizes and on the machine's CPU in two chunk sizes, compared sample by
   sample: the largest relative difference of each outcome, how many samples differ by more
   than 1e-9, 1e-6 and 1e-3, and whether any sample's class (tip-over, bottoming, result)
   changes. The CPU against itself is the control: compiled batch shapes reassociate sums.

    python benchmarks/accelerator_agreement.py OUT.json [--commit HASH] [--quick]

Writes OUT.json (benchmarks/results/accelerator_agreement.json holds a lent H200's run; the
docs tables accelerator-agreement and accelerator-samples read it). Refused (exit 2) on a
machine without a GPU, unless --quick.
"""
import argparse
import json
import os
import sys
import time
from pathlib import Path

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("out", help="the JSON file to write")
ap.add_argument("--commit", default=None, help="the commit measured, recorded in the JSON")
ap.add_argument("--quick", action="store_true", help="tiny sizes; allowed on a CPU")
ap.add_argument("--samples", default=None, metavar="NPZ",
                help="also write every run's per-sample outcomes to this .npz (model, run, key)")
args = ap.parse_args()
out_path = Path(args.out).resolve()
if not out_path.parent.is_dir():
    ap.error(f"out: {args.out}: its folder must exist")
RESULTS = Path(__file__).resolve().parent / "results"
if args.quick and (out_path.parent == RESULTS or RESULTS in out_path.parents):
    ap.error(f"--quick writes smoke-test numbers; refusing {args.out} inside "
             "benchmarks/results/ (give another folder)")
CPU_DEVICES = 8  # the GPU machine's CPU side of the comparison, split like `jaxland montecarlo`

import jax  # noqa: E402

jax.config.update("jax_num_cpu_devices", min(CPU_DEVICES, os.cpu_count() or 1))
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxland as jl  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_montecarlo import _spec, chosen_steps  # noqa: E402  (each model's benchmark spec)

CHOSEN = chosen_steps()

gpu = [d for d in jax.devices() if d.platform != "cpu"]
cpu = jax.devices("cpu")
if not gpu and not args.quick:
    ap.error("no GPU here (jax.devices() are CPUs): this compares a GPU with the CPU")
gpu = gpu or cpu[:1]
print("jax", jax.__version__, gpu, len(cpu), "CPU devices", flush=True)

# 1. one landing per model
v = jl.paper_vehicle()
solver = jl.Solver(dt=4e-5, t_end=0.6, save_dt=1e-3, method="leapfrog")
scenes = {"quarter": jl.Scene(drop_height=0.2),
          "full": jl.Scene(drop_height=0.2, horizontal_speed=1.0, heading=0.5, roll=0.05)}
single = {}
for model, sc in scenes.items():
    row = {}
    for dev, d in (("gpu", gpu[0]), ("cpu", cpu[0])):
        with jax.default_device(d):
            f = jax.jit(lambda s, model=model: jl.landing(v, s, solver, model)[1])
            t = time.perf_counter()
            s = jax.block_until_ready(f(sc))
            t1 = time.perf_counter()
            s = jax.block_until_ready(f(sc))
            t2 = time.perf_counter()
        row[dev] = dict(compile_and_run_s=t1 - t, run_s=t2 - t1,
                        max_stroke_m=jnp.max(s["max_stroke_m"]).item(),
                        peak_strut_force_N=jnp.max(s["peak_strut_force_N"]).item())
    row["rel_diff_max_stroke"] = abs(row["gpu"]["max_stroke_m"] / row["cpu"]["max_stroke_m"] - 1)
    single[model] = row
    print(model, row, flush=True)

# 2. a Monte Carlo, sample by sample
KEYS = ("max_stroke_m", "peak_strut_force_N", "peak_normal_force_N", "peak_body_accel_mps2",
        "min_stability_margin_m")
CLASSES = ("tipped_over", "bottomed_out")
CHANGES_SHOWN = 40  # changed samples listed per class and pair
SIZES = {"quarter": (16384, (16384, 2048), (2048, 512)), "full": (4096, (4096, 512), (512, 64))}
if args.quick:
    SIZES = {"quarter": (16, (16, 8), (8, 4)), "full": (4, (4, 2), (2, 1))}


def outcomes(model, n, chunk, devices):
    spec = _spec(model, n)
    spec.method, spec.dt = CHOSEN[model]
    t = time.perf_counter()
    r = jl.run_montecarlo(spec, chunk=chunk, devices=devices, progress=False)
    wall = time.perf_counter() - t
    o = {k: np.asarray(r.outputs[k], float).reshape(n, -1).max(axis=1)
         for k in KEYS if k in r.outputs}
    o.update({k: np.asarray(r.outputs[k], bool) for k in CLASSES})
    o["result"] = np.asarray(r.failure)
    print(model, n, chunk, devices[0].platform, f"{wall:.1f} s", flush=True)
    return o, wall


def compare(a, b) -> dict:
    out = {}
    for k in KEYS:
        if k in a:
            rel = np.abs(a[k] - b[k]) / np.maximum(np.abs(b[k]), 1e-300)
            out[k] = dict(max_rel=float(rel.max()), above_1e9=int((rel > 1e-9).sum()),
                          above_1e6=int((rel > 1e-6).sum()), above_1e3=int((rel > 1e-3).sum()))
    out["class_changes"] = int(sum((a[k] != b[k]).sum() for k in (*CLASSES, "result")))
    # which class moved, and on which samples (the first CHANGES_SHOWN of each): a changed
    # result code between finished and unfinished is a landing still moving at t_end; a
    # changed tip-over or bottoming is a verdict
    out["changes_by_class"] = {}
    for k in (*CLASSES, "result"):
        idx = np.flatnonzero(a[k] != b[k])
        out["changes_by_class"][k] = dict(
            n=int(idx.size), samples=[
                dict(sample=int(i), a=int(a[k][i]), b=int(b[k][i]),
                     max_stroke_m=[float(a["max_stroke_m"][i]), float(b["max_stroke_m"][i])])
                for i in idx[:CHANGES_SHOWN]])
    return out


samples, raw = {}, {}
for model, (n, gpu_chunks, cpu_chunks) in SIZES.items():
    runs = {f"gpu chunk {c}": outcomes(model, n, c, gpu[:1]) for c in gpu_chunks}
    runs.update({f"cpu chunk {c}": outcomes(model, n, c, cpu) for c in cpu_chunks})
    names = list(runs)
    for run_name, (o, _) in runs.items():
        raw[f"{model}|{run_name}"] = o
    ref = names[-1]  # the CPU at its default-sized chunk
    samples[model] = dict(
        n=n, cpu_devices=len(cpu), reference=ref,
        wall_s={k: w for k, (_, w) in runs.items()},
        pairs=[dict(a=a, b=b, **compare(runs[a][0], runs[b][0]))
               for a, b in ((names[0], names[1]), (names[2], names[3]), (names[0], ref),
                            (names[1], ref))])
    for p in samples[model]["pairs"]:
        print(model, p["a"], "vs", p["b"], {k: v for k, v in p.items() if k not in "ab"},
              flush=True)

result = dict(commit=args.commit, jax=jax.__version__, device_kind=gpu[0].device_kind,
              platform=gpu[0].platform, quick=args.quick, single=single, samples=samples,
              note="one landing: leapfrog 4e-5 s, 0.6 s, 0.2 m drop (full: 1 m/s, heading "
                   "0.5 rad, roll 0.05 rad); samples: bench_montecarlo's spec per model at its "
                   "chosen step, fixed seed; relative differences per sample, the worst leg")
with open(out_path, "w") as f:
    json.dump(result, f, indent=1)
if args.samples:
    np.savez_compressed(args.samples, **{f"{run}|{k}": v for run, o in raw.items()
                                          for k, v in o.items()})
