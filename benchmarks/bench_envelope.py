"""The documented scene envelope, end to end: random scenes over every field's whole range, the
quarter model (symmetric drops) and the full 3-D model (everything dispersed), each landing
judged (jaxland.Result). The claim checked: no unexplained failure and no NaN, i.e. every
sample either lands (stable, bottomed out, tipped) or is an explained outcome (no touchdown
within t_end), after the Monte Carlo's own retry of numerical failures.

    python benchmarks/bench_envelope.py [--quarter-n 10000] [--full-n 10000] [--quick]

Writes envelope.json (counts by outcome and by Result, retries, NaN count, wall time) into
benchmarks/results/ (or out/bench-quick/ with --quick).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import add_out_args, machine, out_dir, write_json

import jaxland as jl

# every dispersible input over its whole documented envelope (TOML units). Landings start at
# touchdown (drop height 0, sink speed over its whole range), so a short t_end sees every
# landing: a drop height only adds free fall before the same touchdown, exact in both models.
FULL_ENVELOPE = {
    "sink_speed_mps": (0.0, 30.0),
    "horizontal_speed_mps": (0.0, 30.0), "heading_deg": (-180.0, 180.0),
    "roll_deg": (-30.0, 30.0), "pitch_deg": (-30.0, 30.0), "yaw_deg": (-180.0, 180.0),
    "roll_rate_degps": (-286.0, 286.0), "pitch_rate_degps": (-286.0, 286.0),
    "yaw_rate_degps": (-286.0, 286.0), "slope_deg": (0.0, 30.0),
    "slope_direction_deg": (-180.0, 180.0), "friction": (0.0, 2.0), "mass_scale": (0.5, 2.0),
    "plateau_scale": (0.2, 5.0), "com_offset_x_m": (-0.3, 0.3), "com_offset_y_m": (-0.3, 0.3),
    "com_offset_z_m": (-0.3, 0.3),
}
QUARTER_KEYS = ("sink_speed_mps", "friction", "mass_scale")


def run(model: str, n: int, t_end: float) -> dict:
    keys = QUARTER_KEYS if model == "quarter" else tuple(FULL_ENVELOPE)
    disp = {k: jl.Distribution("uniform", low=FULL_ENVELOPE[k][0], high=FULL_ENVELOPE[k][1])
            for k in keys}
    spec = jl.MonteCarloSpec(dispersion=disp, fixed={"drop_height_m": 0.0}, n=n, seed=0,
                             t_end=t_end, model=model)
    t0 = time.perf_counter()
    res = jl.run_montecarlo(spec, progress=f"envelope {model}")
    wall = time.perf_counter() - t0
    codes = {jl.Result(int(c)).name.lower(): int(np.sum(res.failure == c))
             for c in np.unique(res.failure)}
    nan = sum(int(np.sum(~np.isfinite(np.asarray(v, dtype=float))))
              for k, v in res.outputs.items() if k != "dt_s")
    ok = res.failure == int(jl.Result.SUCCESSFUL)
    explained = np.isin(res.failure, [int(jl.Result.SUCCESSFUL), int(jl.Result.NO_TOUCHDOWN)])
    return dict(model=model, n=n, t_end_s=t_end, wall_s=wall, results=codes,
                unexplained_failures=int((~explained).sum()), nan_outputs=nan,
                retried=int(res.summary["n_retried"]),
                tipped=int(res.outputs["tipped_over"][ok].sum()),
                bottomed=int(res.outputs["bottomed_out"][ok].sum()),
                smallest_dt_s=float(np.min(res.outputs["dt_s"])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quarter-n", type=int, default=10_000)
    ap.add_argument("--full-n", type=int, default=10_000)
    ap.add_argument("--t-end", type=float, default=1.0, help="simulated time per landing [s]")
    ap.add_argument("--models", nargs="+", default=["quarter", "full"],
                    choices=("quarter", "full"))
    add_out_args(ap)
    args = ap.parse_args()
    out = out_dir(args.out, args.quick)
    if args.quick:
        args.quarter_n, args.full_n, args.t_end = 16, 4, 0.1
    sizes = dict(quarter=args.quarter_n, full=args.full_n)
    rows = [run(model, sizes[model], args.t_end) for model in args.models]
    for r in rows:
        print(r, flush=True)
    write_json(out / "envelope.json", dict(machine=machine(), rows=rows))


if __name__ == "__main__":
    main()
