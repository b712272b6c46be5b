"""XLA:CPU's multi-output fusion (``jaxland.use_batch_fusion``) on and off, side by side: what
it does to the kinds of work jaxland runs, so that where it is on follows from a measurement.

    python benchmarks/bench_fusion.py [--quick] [--repeats 3]

Each case runs in fresh processes (the option is read when XLA's backend starts), alternating
off and on, ``--repeats`` times; each process compiles, runs once to warm up, then reports the
median process CPU time of 3 runs. Writes benchmarks/results/fusion.{json,png}; ``--quick``
writes to out/bench-quick/.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from _common import add_out_args, machine, out_dir, save_png, write_json

# name -> (what it stands for, code that defines ``work()`` and ``per`` (the unit it is per))
CASES = {
    "quarter batch, Monte Carlo bookkeeping": (
        "a Monte Carlo chunk: 512 quarter landings vmapped, 1 s at euler 1e-4 s, no trajectory",
        """
B = 512
sc = jl.Scene.batch(drop_height=np.zeros(B), sink_speed=np.linspace(1.5, 2.5, B))
solver = jl.Solver(dt=1e-4, t_end=1.0, save_dt=1.0, peaks=(), event_log=0,
                   ledger_every=10).validate()
f = jax.jit(lambda s: jl.landings(veh, s, solver, "quarter")[1])
work, per = (lambda: f(sc)), B * solver.n_steps
"""),
    "3-D batch, Monte Carlo bookkeeping": (
        "a Monte Carlo chunk: 64 tilted full 3-D landings vmapped, 0.2 s at verlet 4e-5 s",
        """
B = 64
sc = jl.Scene.batch(drop_height=np.zeros(B), sink_speed=np.linspace(1.5, 2.5, B),
                    roll=np.deg2rad(np.linspace(-3, 3, B)))
solver = jl.Solver(dt=4e-5, t_end=0.2, save_dt=0.2, method="verlet",
                   peaks=("peak_tilt_deg", "peak_margin_deficit_m"), event_log=0).validate()
f = jax.jit(lambda s: jl.landings(veh, s, solver, "full")[1])
work, per = (lambda: f(sc)), B * solver.n_steps
"""),
    "one quarter landing with a trajectory": (
        "jl.simulate's landing: the paper drop, 1.2 s at euler 1e-5 s, saved every 1e-4 s",
        """
solver = jl.Solver(dt=1e-5, t_end=1.2)
f = jax.jit(lambda s: jl.landing(veh, s, solver, "quarter"))
work, per = (lambda: f(jl.Scene())), solver.n_steps
"""),
    "jacfwd of a trajectory (a fit's Jacobian)": (
        "calibration's Jacobian: jacfwd over 6 parameters of 0.35 s of the paper drop's "
        "trajectory, euler 1e-5 s, saved every 2e-4 s",
        """
import equinox as eqx, jax.numpy as jnp
solver = jl.Solver(dt=1e-5, t_end=0.35, save_dt=2e-4)
get = lambda v: (v.ground.k, v.ground.gamma, v.leg.D_b, v.honeycomb.k_b1, v.honeycomb.F1,
                 v.honeycomb.F2)
def traces(theta):
    v = eqx.tree_at(get, veh, tuple(p * jnp.exp(t) for p, t in zip(get(veh), theta)))
    tr = jl.landing(v, jl.Scene(), solver, "quarter")[0]
    return jnp.stack([tr["normal_force_N"], tr["strut_force_N"], tr["stroke_m"]])
f = jax.jit(jax.jacfwd(traces))
work, per = (lambda: f(jnp.zeros(6))), solver.n_steps
"""),
}

CHILD = """
import json, statistics, sys, time
import jaxland as jl
if sys.argv[1] == "on":
    assert jl.use_batch_fusion()
import jax, numpy as np
veh = jl.paper_vehicle()
exec(sys.argv[2])
t0 = time.process_time(); jax.block_until_ready(work()); compile_s = time.process_time() - t0
cpu = []
for _ in range(3):
    t0 = time.process_time(); jax.block_until_ready(work()); cpu.append(time.process_time() - t0)
print(json.dumps(dict(compile_and_first_s=compile_s, cpu_s=statistics.median(cpu), per=per)))
"""


def _child(mode: str, code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, mode, code], capture_output=True,
                         text=True, check=True, env=dict(os.environ))
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(repeats: int, cases=CASES) -> dict:
    rows = []
    for name, (what, code) in cases.items():
        runs = {"off": [], "on": []}
        for _ in range(repeats):
            for mode in runs:
                runs[mode].append(_child(mode, code))
        med = {m: statistics.median(r["cpu_s"] for r in rs) for m, rs in runs.items()}
        comp = {m: statistics.median(r["compile_and_first_s"] for r in rs)
                for m, rs in runs.items()}
        per = runs["off"][0]["per"]
        rows.append(dict(case=name, what=what, repeats=repeats,
                         ns_per_landing_step={m: v / per * 1e9 for m, v in med.items()},
                         compile_and_first_run_s=comp, on_over_off=med["on"] / med["off"]))
        print(rows[-1], flush=True)
    return dict(machine=machine(), load_average_1min_at_end=os.getloadavg()[0],
                timing="process CPU time: median of 3 runs after compilation, then the "
                       "median over repeats of alternating fresh processes (off, on)",
                rows=rows)


def plot(result: dict, out: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.5), layout="constrained")
    ax = fig.subplots()
    rows = result["rows"]
    ax.barh(range(len(rows)), [r["on_over_off"] for r in rows], color="C0")
    ax.axvline(1.0, color="k", lw=1)
    ax.set_yticks(range(len(rows)), [r["case"] for r in rows], fontsize="small")
    ax.set_xscale("log")
    ax.set_xlabel("CPU time with multi-output fusion / without [-]")
    ax.set_title("XLA:CPU multi-output fusion (< 1: faster with it)")
    save_png(fig, out / "fusion.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    add_out_args(ap)
    args = ap.parse_args()
    out = out_dir(args.out, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    cases = dict(list(CASES.items())[:1]) if args.quick else CASES
    result = run(1 if args.quick else args.repeats, cases)
    write_json(out / "fusion.json", result, indent=2)
    plot(result, out)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
