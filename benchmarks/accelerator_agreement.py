"""One landing per model on the default device (a GPU where there is one) and on the same
machine's CPU: the same outcomes to rounding, and each one's time for a single landing.

    python benchmarks/accelerator_agreement.py OUT.json

Writes OUT.json (benchmarks/results/accelerator_agreement.json holds the lent H200's run; the
docs table accelerator-agreement reads it). On a machine without a GPU both rows are the CPU.
"""
import argparse
import json
import time

import jax
import jax.numpy as jnp

import jaxland as jl

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("out", help="the JSON file to write")
args = ap.parse_args()
print("jax", jax.__version__, jax.devices(), flush=True)
v = jl.paper_vehicle()
solver = jl.Solver(dt=4e-5, t_end=0.6, save_dt=1e-3, method="leapfrog")
scenes = {"quarter": jl.Scene(drop_height=0.2),
          "full": jl.Scene(drop_height=0.2, horizontal_speed=1.0, heading=0.5, roll=0.05)}
out = {}
for model, sc in scenes.items():
    row = {}
    for dev in ("gpu", "cpu"):  # "gpu": the default device
        d = jax.devices(dev)[0] if dev == "cpu" else jax.devices()[0]
        with jax.default_device(d):
            f = jax.jit(lambda s: jl.landing(v, s, solver, model)[1])
            t = time.perf_counter()
            s = jax.block_until_ready(f(sc))
            t1 = time.perf_counter()
            s = jax.block_until_ready(f(sc))
            t2 = time.perf_counter()
        row[dev] = dict(compile_and_run_s=t1 - t, run_s=t2 - t1,
                        max_stroke_m=jnp.max(s["max_stroke_m"]).item(),
                        peak_strut_force_N=jnp.max(s["peak_strut_force_N"]).item())
    row["rel_diff_max_stroke"] = abs(row["gpu"]["max_stroke_m"] / row["cpu"]["max_stroke_m"] - 1)
    out[model] = row
    print(model, row, flush=True)
with open(args.out, "w") as f:
    json.dump(out, f, indent=1)
