"""Monte Carlo throughput on this machine: quarter and full 3-D model, 1 and 2 devices.

    python benchmarks/bench_montecarlo.py [--quarter-n 100000] [--full-n 512]

Each configuration runs in its own process (the device count is fixed when jax starts:
XLA_FLAGS=--xla_force_host_platform_device_count=K), with the same spec and seed; the wall time
includes compilation. Writes benchmarks/results/bench_montecarlo.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from _common import save_png, write_json

OUT = Path(__file__).resolve().parent / "results"

CHILD = """
import json, sys, time
import jax
from jaxland import Distribution, MonteCarloSpec, run_montecarlo
model, n = sys.argv[1], int(sys.argv[2])
disp = {"sink_speed_mps": Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
        "mass_scale": Distribution("normal", 1.0, 0.03)}
if model == "full":
    disp.update({"horizontal_speed_mps": Distribution("truncnormal", 0.0, 0.7, 0.0, 2.5),
                 "heading_deg": Distribution("uniform", low=0.0, high=360.0),
                 "roll_deg": Distribution("normal", 0.0, 2.0),
                 "pitch_deg": Distribution("normal", 0.0, 2.0)})
spec = MonteCarloSpec(dispersion=disp, fixed={"drop_height_m": 0.0}, n=n, seed=0, t_end=1.0)
t = time.perf_counter()
r = run_montecarlo(spec, progress=False)
wall = time.perf_counter() - t
print(json.dumps(dict(model=r.summary["model"], n=n, devices=len(jax.devices()), wall_s=wall,
                      landings_per_s=n / wall, n_failed=r.summary["n_failed"])))
"""


def run(model: str, n: int, devices: int) -> dict:
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
    out = subprocess.run([sys.executable, "-c", CHILD, model, str(n)], env=env, check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quarter-n", type=int, default=100_000)
    ap.add_argument("--full-n", type=int, default=512)
    args = ap.parse_args()
    rows = []
    for model, n in (("quarter", args.quarter_n), ("full", args.full_n)):
        for devices in (1, 2):
            row = run(model, n, devices)
            print(row, flush=True)
            rows.append(row)
    result = dict(spec="sink speed 2.0+-0.3 m/s, mass +-3 % (quarter); plus horizontal speed, "
                       "heading, roll, pitch (full); 1.0 s landings at dt = 1e-5 s, from "
                       "touchdown; wall time includes compilation", runs=rows,
                  speedup_2_devices={m: next(r["wall_s"] for r in rows if r["model"] == m and
                                             r["devices"] == 1) /
                                     next(r["wall_s"] for r in rows if r["model"] == m and
                                          r["devices"] == 2) for m in ("quarter", "full")})
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / "bench_montecarlo.json", result, indent=2)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    for i, model in enumerate(("quarter", "full")):
        rs = [r for r in rows if r["model"] == model]
        ax.bar([i - 0.2, i + 0.2], [r["landings_per_s"] for r in rs], 0.35,
               color=["C0", "C1"], label=None)
        for r, x in zip(rs, (i - 0.2, i + 0.2)):
            ax.text(x, r["landings_per_s"], f"{r['devices']} dev\n{r['landings_per_s']:.0f}/s",
                    ha="center", va="bottom", fontsize="small")
    ax.set_xticks([0, 1], [f"quarter (n={args.quarter_n})", f"full 3-D (n={args.full_n})"])
    ax.set_yscale("log")
    ax.set_ylabel("throughput [landings/s]")
    ax.set_title("Monte Carlo on this CPU: 1 vs 2 devices")
    save_png(fig, OUT / "bench_montecarlo.png")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
