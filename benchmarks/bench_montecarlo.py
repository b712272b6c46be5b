"""Monte Carlo on this machine: throughput (quarter and full 3-D model, 1 and 2 devices, at the
spec's default step and at the step the step study chose, this tree against an earlier one side
by side) and the choice of the Monte Carlo step.

    python benchmarks/bench_montecarlo.py [--quarter-n 20000] [--full-n 1024] [--before TREE]
    python benchmarks/bench_montecarlo.py --step-study [--step-n 32]
    python benchmarks/bench_montecarlo.py --step-check 128
    python benchmarks/bench_montecarlo.py --cache
    python benchmarks/bench_montecarlo.py --accelerator [--budget-s 420]   (on a GPU machine)
    python benchmarks/bench_montecarlo.py --quick

Throughput: each configuration runs in its own process (the device count is fixed when jax
starts: XLA_FLAGS=--xla_force_host_platform_device_count=K), with the same spec and seed; the
wall time includes compilation. ``--before TREE`` (a checkout of an earlier commit, e.g. from
``git worktree add``) runs the same child on that tree's jaxland, one after the other with this
tree's, so the two can be compared on a shared, noisy machine. The full model at the chosen
step also runs twice with one empty persistent compilation cache (``cached``): the second run
reads its programs back, as a repeated ``jaxland montecarlo`` does. Writes
benchmarks/results/bench_montecarlo.{json,png}.

Step study (``--step-study``): per model, the dispersed samples' outcomes (max stroke, peak
strut, ground and honeycomb forces, per landing the worst leg) at each method and step against
a converged reference (verlet at 2.5e-6 s, itself checked against euler at that step). First it
measures how well-posed each sample's outcome is: the reference again with every sink speed
changed by 1e-12 and by 1e-9 relative. An outcome whose relative change exceeds 100 times the
input's (a condition number above 100) is ill-conditioned: some dispersed 3-D landings rock
and slide after the impact in a way that amplifies any perturbation, a rounding error or a
step's truncation error alike, so no step can reproduce such an outcome per sample; it is
judged on the samples' mean and median instead. The chosen step is the cheapest one
(evaluations per simulated second) whose well-conditioned outcomes stay within 1e-3 per sample
and whose mean and median stay within 1e-3, with every sample's tip-over, bottoming and result
unchanged. Writes benchmarks/results/montecarlo_step.{json,png}.

``--quick`` (tiny sizes) writes to out/bench-quick/, never into benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from _common import RESULTS, ROOT, add_out_args, machine, out_dir, save_png, write_json

CHILD = """
import json, sys, time
import jaxland
getattr(jaxland, "use_batch_fusion", lambda: None)()  # as jaxland montecarlo does
import jax
from jaxland import Distribution, MonteCarloSpec, run_montecarlo, load_montecarlo_spec
model, n, method, dt = sys.argv[1], int(sys.argv[2]), sys.argv[3], float(sys.argv[4])
chunk = int(sys.argv[6]) if len(sys.argv) > 6 and int(sys.argv[6]) > 0 else None
if model == "full":
    spec = load_montecarlo_spec(sys.argv[5])
    spec.n = n
else:
    spec = MonteCarloSpec(
        dispersion={"sink_speed_mps": Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
                    "mass_scale": Distribution("normal", 1.0, 0.03)},
        fixed={"drop_height_m": 0.0}, n=n, seed=0, t_end=1.0)
spec.method, spec.dt = method, dt
# the landings' throughput: the t_end check (a second program, its own landings) is timed
# apart in docs/montecarlo.md, and the run's wall_s leaves it out too
if hasattr(spec, "t_end_check"):  # a --before tree may predate it
    spec.t_end_check = 0
t = time.perf_counter()
r = run_montecarlo(spec, progress=False, chunk=chunk)
wall = time.perf_counter() - t
print(json.dumps(dict(model=r.summary["model"], n=n, devices=len(jax.devices()), wall_s=wall,
                      landings_per_s=n / wall, n_failed=r.summary["n_failed"],
                      n_retried=r.summary["n_retried"], method=method, dt_s=dt,
                      chunk=r.summary["chunk"], device_kind=jax.devices()[0].device_kind,
                      max_stroke_m=r.summary["envelopes"]["max_stroke_m (any leg)"])))
"""
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "montecarlo_dispersed.toml"


def run(model: str, n: int, devices: int, method="euler", dt=1e-5, tree=None,
        cache=None, chunk=0, timeout=None) -> dict:
    """One Monte Carlo in a fresh process; ``cache``: a folder for JAX's persistent compilation
    cache (as ``jaxland montecarlo`` keeps one), else none; ``chunk``: landings per compiled
    chunk (0: run_montecarlo's default for the platform); ``timeout`` [s]: the child is
    stopped after it (subprocess.TimeoutExpired)."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    state = "none"  # the compilation cache as the run finds it
    if cache is not None:
        env["JAX_COMPILATION_CACHE_DIR"] = str(cache)
        state = "filled" if Path(cache).is_dir() and any(Path(cache).iterdir()) else "empty"
    if tree is not None:
        env["PYTHONPATH"] = str(Path(tree).resolve())
    example = EXAMPLE if tree is None else Path(tree).resolve() / EXAMPLE.relative_to(ROOT)
    out = subprocess.run([sys.executable, "-c", CHILD, model, str(n), method, str(dt),
                          str(example), str(chunk)], env=env, check=True, capture_output=True,
                         text=True, cwd=tree or None, timeout=timeout)
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row["tree"] = "before" if tree is not None else "this"
    row["cache"] = state
    print(row, flush=True)
    return row


# the throughput targets [landings/s] on this 2-core CPU, at the chosen step
TARGETS = {"quarter": 5000.0, "full": 167.0}
LARGE_TARGET = (10_000, 60.0)  # full 3-D landings, seconds: "10^4 full landings in 60 s"
DEFAULT = ("euler", 1e-5)  # the spec's default method and step


def step_file_of(out: Path) -> Path:
    """The step study's results: ``out``'s montecarlo_step.json where a run wrote one there,
    else the tracked one."""
    path = out / "montecarlo_step.json"
    return path if path.exists() else RESULTS / "montecarlo_step.json"


def chosen_steps(path: Path = RESULTS / "montecarlo_step.json") -> dict:
    """{model: (method, dt_s)} the step study in ``path`` chose."""
    return {m: (r["chosen"]["method"], r["chosen"]["dt_s"])
            for m, r in json.loads(Path(path).read_text())["models"].items() if r.get("chosen")}


def throughput(args, out: Path) -> dict:
    """In one session: each model at the spec's default step on 1 and 2 devices, at the step
    the step study chose (montecarlo_step.json) on 1 and 2 devices, and with ``--before`` that
    tree at its own study's chosen step on one device, next to this tree again."""
    sizes = {"quarter": args.quarter_n, "full": args.full_n}
    step_file = step_file_of(out)
    chosen = chosen_steps(step_file)
    # the earlier tree at its own study's choice (it may lack this tree's methods)
    chosen_before = (chosen_steps(Path(args.before) / "benchmarks" / "results"
                                  / "montecarlo_step.json") if args.before else {})
    rows, compare = [], []
    for model, n in sizes.items():
        for devices in (1, 2):
            rows.append(run(model, n, devices, *DEFAULT))
        if model in chosen:
            for devices in (1, 2):
                rows.append(run(model, n, devices, *chosen[model]))
            if args.before:  # the earlier tree, then this one again, one device each
                compare.append(run(model, n, 1, *chosen_before[model], tree=args.before))
                compare.append(run(model, n, 1, *chosen[model]))
    # the "10^4 full landings in 60 s", at the chosen step on two devices
    large = ([run("full", args.full_n_large, 2, *chosen["full"])]
             if args.full_n_large and "full" in chosen else [])
    # a repeated run: the full model at the chosen step twice, sharing one empty compilation
    # cache, as a user's second `jaxland montecarlo` of the same spec and chunk finds it
    cached = []
    if "full" in chosen:
        import tempfile

        with tempfile.TemporaryDirectory(prefix="jaxland-mc-cache-") as tmp:
            cached = [run("full", args.full_n, 2, *chosen["full"], cache=Path(tmp) / "xla")
                      for _ in range(2)]
    load = os.getloadavg()[0]

    def rate(model, devices, setting):
        return next((r["landings_per_s"] for r in rows if r["model"] == model
                     and r["devices"] == devices and (r["method"], r["dt_s"]) == setting), None)

    speed = {m: rate(m, 2, DEFAULT) / rate(m, 1, DEFAULT) for m in sizes}
    targets = {m: dict(target_landings_per_s=TARGETS[m], setting=list(chosen[m]),
                       landings_per_s=rate(m, 2, chosen[m]),
                       met=bool(rate(m, 2, chosen[m]) >= TARGETS[m]))
               for m in sizes if m in chosen}
    result = dict(spec="quarter: sink speed 2.0+-0.3 m/s, mass +-3 %; full: "
                       "examples/montecarlo_dispersed.toml; 1.0 s landings from touchdown; "
                       "wall time includes compilation",
                  machine=machine(), load_average_1min_at_end=load, runs=rows,
                  speedup_2_devices=speed, targets=targets, chosen_step_file=str(
                      step_file.relative_to(ROOT) if ROOT in step_file.parents else step_file),
                  side_by_side=compare, before_tree=args.before,
                  cached=dict(runs=cached, target_landings_per_s=TARGETS["full"],
                              met=bool(cached and cached[-1]["cache"] == "filled"
                                       and cached[-1]["landings_per_s"] >= TARGETS["full"])),
                  large=dict(runs=large, target=dict(n=LARGE_TARGET[0], wall_s=LARGE_TARGET[1]),
                             met=bool(large and large[0]["n"] >= LARGE_TARGET[0]
                                      and large[0]["wall_s"] <= LARGE_TARGET[1])),
                  before_commit=subprocess.run(
                      ["git", "rev-parse", "--short", "HEAD"], cwd=args.before,
                      capture_output=True, text=True).stdout.strip() if args.before else None,
                  note="a shared 2-core machine: timings are noisy; compare rows of one run")
    write_json(out / "bench_montecarlo.json", result, indent=2)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 4), layout="constrained")
    ax = fig.subplots()
    bars = [(f"{r['model']}\n{r['method']} {r['dt_s']:g}\n{r['devices']} dev", r)
            for r in rows] + [(f"{r['model']}\n{r['tree']}\n{r['method']} {r['dt_s']:g}", r)
                              for r in compare]
    ax.bar(range(len(bars)), [r["landings_per_s"] for _, r in bars],
           color=["C0" if r["tree"] == "this" else "C1" for _, r in bars])
    for i, m in enumerate(TARGETS):
        ax.axhline(TARGETS[m], color=f"C{i + 2}", ls="--", lw=1, label=f"{m} target")
    ax.set_xticks(range(len(bars)), [b for b, _ in bars], fontsize="x-small")
    ax.set_yscale("log")
    ax.set_ylabel("throughput, with compilation [landings/s]")
    ax.set_title("Monte Carlo on this CPU (orange: the earlier tree)")
    ax.legend(fontsize="small")
    save_png(fig, out / "bench_montecarlo.png")
    return result


# ---------------------------------------------------------------- on an accelerator

# (model, n, chunk) in the order they run, most wanted first: the sizes (10^4 3-D in a
# minute, 10^5 quarter in 20 s), the n = 1024 3-D row of the CPU table, then 10x larger runs and
# the chunk sweeps behind run_montecarlo's accelerator default (chunk 0: that default)
ACCEL_RUNS = (("full", 10_000, 0), ("quarter", 100_000, 0), ("full", 1024, 0),
              ("quarter", 20_000, 0), ("full", 100_000, 0), ("quarter", 1_000_000, 0),
              ("full", 16_384, 1024), ("full", 16_384, 4096), ("full", 16_384, 16_384),
              ("full", 131_072, 32_768), ("full", 131_072, 131_072),
              ("quarter", 1_000_000, 1_000_000))


def accelerator(args, out: Path) -> dict:
    """The throughput runs of ``throughput`` on this machine's accelerator, unchanged: the same
    child, spec, seed and chosen steps, one process per run, wall time with compilation. The
    3-D model at 10^4 also runs twice with one empty compilation cache, which separates its
    compilation from its run. Runs stop being started once ``--budget-s`` has passed (each is
    stopped at the budget's end). Writes montecarlo_accelerator.{json,png} once every run of
    the plan has finished; until then, and for good where one did not,
    montecarlo_accelerator.partial.json. Refused (exit 2) on a machine without a GPU, unless
    ``--quick``."""
    import tempfile

    chosen = chosen_steps(step_file_of(out))
    t0 = time.perf_counter()
    plan = ACCEL_RUNS[:2] if args.quick else ACCEL_RUNS
    sizes = {"quarter": 64, "full": 4} if args.quick else {}
    rows, cached, skipped = [], [], []

    def left():
        return args.budget_s - (time.perf_counter() - t0)

    def attempt(model, n, chunk, **kw):
        if left() < 10:
            skipped.append(dict(model=model, n=n, chunk=chunk, why="budget spent"))
            return None
        try:
            return run(model, sizes.get(model, n), 1, *chosen[model], chunk=chunk,
                       timeout=left(), **kw)
        except subprocess.TimeoutExpired:
            skipped.append(dict(model=model, n=n, chunk=chunk, why="stopped at the budget"))
        except subprocess.CalledProcessError as e:
            tail = (e.stderr or "").strip().splitlines()[-3:]
            skipped.append(dict(model=model, n=n, chunk=chunk, why="failed", stderr=tail))
        return None

    partial = out / "montecarlo_accelerator.partial.json"

    def save():
        write_json(partial, dict(
            spec="as bench_montecarlo.json: quarter dispersion in the CHILD, full 3-D "
                 "examples/montecarlo_dispersed.toml; 1.0 s landings; one device; wall time "
                 "includes compilation", chosen_steps={m: list(c) for m, c in chosen.items()},
            runs=rows, cached=cached, skipped=skipped, budget_s=args.budget_s,
            wall_total_s=time.perf_counter() - t0), indent=2)

    for i, (model, n, chunk) in enumerate(plan):
        row = attempt(model, n, chunk)
        if row is not None:
            rows.append(row)
        save()
        if i == 0 and row is not None:  # the same 3-D run twice with one compilation cache
            with tempfile.TemporaryDirectory(prefix="jaxland-mc-cache-") as tmp:
                for _ in range(2):
                    r = attempt(model, n, chunk, cache=Path(tmp) / "xla")
                    if r is not None:
                        cached.append(r)
            save()
    result = json.loads(partial.read_text())
    result["machine"] = machine()  # after the runs: the backend takes the device's memory
    if skipped:
        write_json(partial, result, indent=2)
        print(f"{len(skipped)} run(s) did not finish: results left in {partial}",
              file=sys.stderr)
        return result
    write_json(out / "montecarlo_accelerator.json", result, indent=2)
    partial.unlink()
    plot_accelerator(result, out)
    return result


def plot_accelerator(result: dict, out: Path) -> None:
    """Throughput against n per model and chunk, from montecarlo_accelerator.json."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4), layout="constrained")
    ax = fig.subplots()
    for i, model in enumerate(("quarter", "full")):
        rs = sorted((r for r in result["runs"] if r["model"] == model), key=lambda r: r["n"])
        for chunks, marker in ((lambda r: r["chunk"] >= r["n"], "o"),
                               (lambda r: r["chunk"] < r["n"], "x")):
            pick = [r for r in rs if chunks(r)]
            if pick:
                ax.plot([r["n"] for r in pick], [r["landings_per_s"] for r in pick], marker,
                        color=f"C{i}", label=f"{model}, " + (
                            "one chunk" if marker == "o" else "several chunks"))
        ax.axhline(TARGETS[model], color=f"C{i}", ls="--", lw=1,
                   label=f"{model}: the issue's CPU target")
    kind = next((r["device_kind"] for r in result["runs"]), "accelerator")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("landings in the run, n [-]")
    ax.set_ylabel("throughput, with compilation [landings/s]")
    ax.set_title(f"Monte Carlo on one {kind}")
    ax.legend(fontsize="small")
    save_png(fig, out / "montecarlo_accelerator.png")


# ---------------------------------------------------------------- the CLI's compilation cache

DESIGN_EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "design_paper_gear.toml"
CACHE_RUNS = {  # what a user runs twice, as CLI arguments (short: the compile share shows)
    "montecarlo, 3-D example, n = 64":
        ["montecarlo", str(EXAMPLE), "--n", "64"],
    "design, paper gear, 2 iterations, verification n = 32":
        ["design", str(DESIGN_EXAMPLE), "--iterations", "2", "--verify-n", "32"],
}


def cli_cache(out: Path, quick: bool) -> dict:
    """Each command of ``CACHE_RUNS`` twice in fresh processes sharing one empty compilation
    cache folder (``JAXLAND_CACHE_DIR``): the first run compiles and stores, the second reads
    the compiled programs back. Writes cli_cache.json."""
    import tempfile

    rows = []
    runs = dict(list(CACHE_RUNS.items())[:1]) if quick else CACHE_RUNS
    for argv in runs.values():
        argv = [a if a != "64" or not quick else "8" for a in argv]
        with tempfile.TemporaryDirectory(prefix="jaxland-cache-bench-") as tmp:
            env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
            env["JAXLAND_CACHE_DIR"] = str(Path(tmp) / "xla")
            walls = []
            for i in range(2):
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "jaxland.cli", *argv, "--out",
                                str(Path(tmp) / f"out{i}")], env=env, check=True,
                               capture_output=True, text=True)
                walls.append(time.perf_counter() - t0)
        rows.append(dict(command="jaxland " + " ".join(
            a.replace(str(EXAMPLE.parents[1]) + "/", "") for a in argv),
            first_s=walls[0], second_s=walls[1]))
        print(rows[-1], flush=True)
    result = dict(machine=machine(), load_average_1min_at_end=os.getloadavg()[0], rows=rows,
                  note="wall time of the whole command (process start, import, compile or "
                       "cache read, run, outputs); one empty cache folder per command")
    write_json(out / "cli_cache.json", result, indent=2)
    return result


# ---------------------------------------------------------------- the Monte Carlo step (2c)

STEP_METHODS = {"euler": (1e-5, 2e-5, 2.5e-5, 4e-5, 5e-5, 8e-5, 1e-4, 1.25e-4),
                "euler_implicit": (1e-5, 2e-5, 2.5e-5, 4e-5, 5e-5, 1e-4),
                "verlet": (1e-5, 2e-5, 2.5e-5, 4e-5, 5e-5, 1e-4),
                "leapfrog": (1e-5, 2e-5, 2.5e-5, 3.2e-5, 4e-5, 5e-5, 6.25e-5)}
REFERENCE = ("verlet", 2.5e-6)  # the converged reference; checked against euler at that step
STEP_TOL = 1e-3  # largest relative error of an outcome accepted
STEP_KEYS = ("max_stroke_m", "peak_strut_force_N", "peak_normal_force_N",
             "peak_honeycomb_force_N")
PERTURBATIONS = (1e-12, 1e-9)  # relative changes of every sink speed that probe conditioning
CONDITION_MAX = 100.0  # relative outcome change / relative input change beyond which an outcome
#                        is compared over the ensemble only


def _spec(model: str, n: int):
    import jaxland as jl

    if model == "full":
        spec = jl.load_montecarlo_spec(Path(__file__).resolve().parents[1] / "examples"
                                       / "montecarlo_dispersed.toml")
        spec.n = n
        return spec
    return jl.MonteCarloSpec(dispersion=quarter_dispersion(), fixed={"drop_height_m": 0.0},
                             n=n, seed=0, t_end=1.0)


def quarter_dispersion():
    import jaxland as jl

    return {"sink_speed_mps": jl.Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
            "mass_scale": jl.Distribution("normal", 1.0, 0.03)}


def _outcomes(model, spec, method, dt, perturb=0.0):
    import dataclasses

    import jax
    import numpy as np

    import jaxland as jl

    scenes, _ = jl.sample_scenes(spec, 0, spec.n)
    if perturb:
        scenes = dataclasses.replace(scenes, sink_speed=scenes.sink_speed * (1.0 + perturb))
    from jaxland._montecarlo._run import mc_solver

    solver = mc_solver(spec, model, dt, method)  # the landings as jaxland montecarlo runs them
    v = jl.paper_vehicle()
    t0 = time.perf_counter()
    s = jax.device_get(jax.jit(lambda sc: jl.landings(v, sc, solver, model)[1])(scenes))
    out = {k: np.max(np.reshape(s[k], (spec.n, -1)), axis=1) for k in STEP_KEYS}
    out.update(result=np.asarray(s["result"]), tipped=np.asarray(s["tipped"]),
               bottomed=np.asarray(s["bottomed"]), wall_s=time.perf_counter() - t0)
    return out


def same_classes(got: dict, ref: dict) -> bool:
    """Every sample keeps its tip-over, bottoming and result (``_outcomes`` of two runs)."""
    import numpy as np

    return bool(all(np.array_equal(got[k], ref[k]) for k in ("tipped", "bottomed", "result")))


def step_study(models, n: int) -> dict:
    """Per model and method, each step's largest relative error of the outcomes against the
    converged reference over ``n`` dispersed samples (per sample where the outcome is
    well-conditioned, on the mean and median otherwise), and whether every sample keeps its
    classification (tip-over, bottoming) and result; the chosen step: the cheapest one within
    ``STEP_TOL`` with every classification kept."""
    import numpy as np

    report = dict(tolerance=STEP_TOL, reference=dict(method=REFERENCE[0], dt_s=REFERENCE[1]),
                  outcomes=list(STEP_KEYS), perturbations_rel=list(PERTURBATIONS),
                  condition_max=CONDITION_MAX, models={})
    for model in models:
        spec = _spec(model, n)
        ref = _outcomes(model, spec, *REFERENCE)
        cond = {k: np.zeros(spec.n) for k in STEP_KEYS}  # per sample, the larger of the probes
        for eps in PERTURBATIONS:
            probe = _outcomes(model, spec, *REFERENCE, perturb=eps)
            for k in STEP_KEYS:
                cond[k] = np.maximum(cond[k], np.abs(probe[k] / ref[k] - 1.0) / eps)
        ill = {k: cond[k] > CONDITION_MAX for k in STEP_KEYS}
        sensitivity = dict(
            max_condition={k: float(np.max(cond[k])) for k in STEP_KEYS},
            median_condition={k: float(np.median(cond[k])) for k in STEP_KEYS},
            ill_conditioned_samples={k: np.flatnonzero(ill[k]).tolist() for k in STEP_KEYS})
        print(model, "sensitivity", sensitivity, flush=True)
        rows = []

        def compare(method, dt, ref=ref, spec=spec, model=model, ill=ill):
            got = _outcomes(model, spec, method, dt)
            rel = {k: np.abs(got[k] - ref[k]) / np.abs(ref[k]) for k in STEP_KEYS}
            err = {k: float(np.max(rel[k][~ill[k]], initial=0.0)) for k in STEP_KEYS}
            ens = {k: float(max(abs(f(got[k]) / f(ref[k]) - 1.0) for f in (np.mean, np.median)))
                   for k in STEP_KEYS}
            same = same_classes(got, ref)
            row = dict(method=method, dt_s=dt, max_rel_error=err, worst=max(err.values()),
                       ensemble_rel_error=ens, ensemble_worst=max(ens.values()),
                       max_rel_error_every_sample={k: float(np.max(rel[k])) for k in STEP_KEYS},
                       classification_kept=same, n_failed=int(np.sum(got["result"] != 0)),
                       wall_s=got["wall_s"])
            print(model, row, flush=True)
            return row

        check = compare("euler", REFERENCE[1])  # the reference against another method
        for method, dts in STEP_METHODS.items():
            rows += [compare(method, dt) for dt in dts]
        for r in rows:  # force evaluations per simulated second (verlet: two per step)
            r["evaluations_per_s"] = (2.0 if r["method"] == "verlet" else 1.0) / r["dt_s"]
        ok = [r for r in rows if max(r["worst"], r["ensemble_worst"]) <= STEP_TOL
              and r["classification_kept"]]
        best = min(ok, key=lambda r: (r["evaluations_per_s"], -r["dt_s"])) if ok else None
        report["models"][model] = dict(
            n=n, spec="examples/montecarlo_dispersed.toml" if model == "full" else
            "sink speed 2.0+-0.3 m/s, mass +-3 %", t_end_s=spec.t_end,
            reference_check=check, sensitivity=sensitivity, rows=rows, chosen=best,
            n_tipped=int(np.sum(ref["tipped"])), n_bottomed=int(np.sum(ref["bottomed"])))
    return report


# steps finer than the chosen one that the step check runs too: whether a smaller step meets
# the per-sample tolerance where the chosen one misses it
FINER_STEPS = (("leapfrog", 2e-5), ("leapfrog", 1e-5), ("verlet", 2e-5), ("verlet", 1e-5))


def step_check(n: int, out: Path) -> dict:
    """The 3-D model's chosen step (montecarlo_step.json), the spec's default step and
    ``FINER_STEPS`` checked on ``n`` samples, more than the study ran, against both converged
    runs (verlet and euler at the reference step): per outcome, the worst per-sample error
    where the two agree within a tenth of the tolerance (the sample with the largest), the
    samples that miss the tolerance there, the samples on which the two converged runs
    themselves disagree, and the mean and median errors next to the converged runs' own.
    Writes montecarlo_step_check.json."""
    import numpy as np

    step_file = step_file_of(out)
    chosen = chosen_steps(step_file)["full"]
    spec = _spec("full", n)
    ref = _outcomes("full", spec, *REFERENCE)
    other = _outcomes("full", spec, "euler", REFERENCE[1])
    rows = []
    for role, (method, dt) in (("chosen", chosen), ("default", DEFAULT),
                               *(("finer", st) for st in FINER_STEPS)):
        got = _outcomes("full", spec, method, dt)
        per = {}
        for k in STEP_KEYS:
            agree = np.abs(other[k] - ref[k]) <= 0.1 * STEP_TOL * np.abs(ref[k])
            rel = np.abs(got[k] - ref[k]) / np.abs(ref[k])
            worst = int(np.argmax(np.where(agree, rel, -1.0)))
            per[k] = dict(
                worst_where_converged_agree=float(rel[worst]), worst_sample=worst,
                over_tolerance=np.flatnonzero(agree & (rel > STEP_TOL)).tolist(),
                converged_disagree=np.flatnonzero(~agree).tolist(),
                converged_largest_difference=float(np.max(np.abs(other[k] / ref[k] - 1.0))),
                ensemble_rel_error={f.__name__: float(abs(f(got[k]) / f(ref[k]) - 1.0))
                                    for f in (np.mean, np.median)},
                converged_ensemble_rel_error={f.__name__: float(abs(f(other[k]) / f(ref[k])
                                                                    - 1.0))
                                              for f in (np.mean, np.median)})
        rows.append(dict(method=method, dt_s=dt, role=role, outcomes=per,
                         classification_kept=same_classes(got, ref)))
        print(rows[-1], flush=True)
    report = dict(n=n, spec="examples/montecarlo_dispersed.toml", tolerance=STEP_TOL,
                  reference=dict(method=REFERENCE[0], dt_s=REFERENCE[1]),
                  second_converged=dict(method="euler", dt_s=REFERENCE[1]),
                  agree_within=0.1 * STEP_TOL, chosen_step_file=str(
                      step_file.relative_to(ROOT) if ROOT in step_file.parents else step_file),
                  rows=rows)
    write_json(out / "montecarlo_step_check.json", report, indent=2)
    return report


def plot_steps(report: dict, out: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 3.6), layout="constrained")
    axes = fig.subplots(1, len(report["models"]), squeeze=False)[0]
    for ax, (model, rep) in zip(axes, report["models"].items()):
        for i, method in enumerate(STEP_METHODS):
            rs = [r for r in rep["rows"] if r["method"] == method]
            ax.loglog([r["dt_s"] for r in rs], [max(r["worst"], 1e-16) for r in rs], "o-",
                      color=f"C{i}", label=method)
            ax.loglog([r["dt_s"] for r in rs], [max(r["ensemble_worst"], 1e-16) for r in rs],
                      ":", color=f"C{i}")
            for r in rs:
                if not r["classification_kept"]:
                    ax.plot(r["dt_s"], max(r["worst"], 1e-16), "x", color="k", ms=9)
        ax.axhline(report["tolerance"], color="grey", ls="--", lw=1)
        ax.set_xlabel("step dt [s]")
        ax.set_ylabel("worst relative error of the outcomes [-]")
        n_ill = len(set().union(*rep["sensitivity"]["ill_conditioned_samples"].values()))
        ax.set_title(f"{model} (n = {rep['n']}, {n_ill} ill-conditioned)\n"
                     "solid: per sample; dotted: mean and median; x: a classification changed",
                     fontsize="small")
        ax.legend(fontsize="small")
    save_png(fig, out / "montecarlo_step.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quarter-n", type=int, default=20_000)
    ap.add_argument("--full-n", type=int, default=1024)
    ap.add_argument("--full-n-large", type=int, default=LARGE_TARGET[0],
                    help="one more full 3-D run of this size at the chosen step on 2 devices "
                         "(0: none)")
    ap.add_argument("--before", default=None, help="an earlier checkout to run side by side")
    ap.add_argument("--step-study", action="store_true")
    ap.add_argument("--step-n", type=int, default=32)
    ap.add_argument("--step-check", type=int, default=0, metavar="N",
                    help="check the 3-D chosen step on N samples (montecarlo_step_check.json)")
    ap.add_argument("--accelerator", action="store_true",
                    help="the throughput runs on this machine's GPU, one device "
                         "(montecarlo_accelerator.json)")
    ap.add_argument("--budget-s", type=float, default=420.0,
                    help="with --accelerator: start no run after this many seconds [s]")
    ap.add_argument("--cache", action="store_true",
                    help="the CLI run twice with one compilation cache (cli_cache.json)")
    add_out_args(ap)
    args = ap.parse_args()
    out = out_dir(args.out, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    if args.quick:
        args.quarter_n, args.full_n, args.step_n, args.full_n_large = 64, 4, 4, 0
    if args.accelerator:
        if not (math.isfinite(args.budget_s) and args.budget_s > 0):
            ap.error(f"--budget-s: {args.budget_s}: must be a finite number of seconds > 0")
        backend = subprocess.run([sys.executable, "-c", "import jax; print(jax.default_backend())"],
                                 capture_output=True, text=True, check=True).stdout.strip()
        if backend == "cpu" and not args.quick:
            ap.error("--accelerator: this machine's JAX backend is the CPU: the GPU throughput "
                     "needs a GPU (the CPU's is the default run)")
        print(json.dumps(accelerator(args, out), indent=2))
        return
    if args.cache:
        print(json.dumps(cli_cache(out, args.quick), indent=2))
        return
    if args.step_check:
        import jaxland as jl

        jl.use_batch_fusion()
        step_check(4 if args.quick else args.step_check, out)
        return
    if args.step_study:
        import jaxland as jl

        jl.use_batch_fusion()  # compiled as jaxland montecarlo compiles them
        report = step_study(("quarter", "full"), args.step_n)
        write_json(out / "montecarlo_step.json", report, indent=2)
        plot_steps(report, out)
        return
    print(json.dumps(throughput(args, out), indent=2))


if __name__ == "__main__":
    main()
