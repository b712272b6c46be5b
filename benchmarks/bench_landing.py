"""Compile time and run time of one landing and of vmapped batches (quarter and full 3-D model),
the cost of gradients, and the cost per landing-step of both models side by side with the
structure of their compiled time step, written as ``bench_landing.json`` plus
``bench_landing.png``.

    python benchmarks/bench_landing.py [--quick] [--batch 1000] [--out DIR]
    python benchmarks/bench_landing.py --accelerator [--quick] [--out DIR]

``--accelerator`` runs only the per-landing-step comparison, on a GPU, at GPU-sized batches,
and writes ``bench_landing_accelerator.json`` plus ``.png``.

Timings are medians of repeats after compile, measured side by side in one run (the machines
are noisy); they are never asserted by tests. The per-landing-step comparison runs the two
models' single landings and batches (64 and 512) interleaved, repeat by repeat, so that both
see the same machine. ``--quick`` (tiny sizes) writes to ``out/bench-quick/`` unless ``--out``
says otherwise, never into ``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import statistics
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _common import add_out_args, machine, out_dir, params, save_png, timed, write_json

import jaxland as jl
from jaxland import Scene, Solver, landing, landings


def _compile_and_time(fn, args, repeats):
    return timed(fn, args, repeats)[1:]


def loop_body_counts(hlo_text: str) -> dict:
    """What the compiled time step is made of: in the innermost while body of an optimised
    XLA module, the number of kernels XLA launches per step (fusions and the unfused copies
    and library calls; ``kernels``, their sum, is what a GPU launches per step, where XLA:CPU
    with batch fusion runs the whole loop as one kernel), the matrix products (``dot``:
    library calls on XLA:CPU), the reductions and all operations inside the fusions (XLA
    duplicates cheap elementwise work into every fusion that consumes it, so this counts the
    work done per step)."""
    comps, cur = {}, None
    for line in hlo_text.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if head:
            cur = head.group(1)
            comps[cur] = []
        elif line.startswith("}"):
            cur = None
        elif cur is not None:
            comps[cur].append(line)

    def ops(name):
        c = collections.Counter()
        for line in comps.get(name, ()):
            m = re.search(r"= (?:\S+|\([^)]*\)) ([a-z][\w\-]*)\(", line)
            if m:
                c[m.group(1)] += 1
        return c

    bodies = [m.group(1) for m in re.finditer(r"while\(.*?body=%?([\w.\-]+)", hlo_text)]
    inner = [b for b in bodies if not any(" while(" in line for line in comps.get(b, ()))]
    if not inner:
        return {}
    body = inner[0]
    top = ops(body)
    fused = collections.Counter()
    for line in comps[body]:
        if " fusion(" in line and "calls=" in line:
            fused.update(ops(re.search(r"calls=%?([\w.\-]+)", line).group(1)))
    trivial = ("parameter", "constant", "broadcast", "bitcast", "get-tuple-element", "tuple")
    return dict(
        fusions=top["fusion"], copies=top["copy"],
        kernels=top["fusion"] + top["copy"] + top["custom-call"], dots=top["dot"] + fused["dot"],
        custom_calls=top["custom-call"], reduces=top["reduce"] + fused["reduce"],
        fused_ops=sum(v for k, v in fused.items() if k not in trivial),
        divides=fused["divide"], sqrts=fused["sqrt"])


def dispatches_per_step(compiled, args, n_steps: int) -> float:
    """Kernel launches per time step of one call of ``compiled``, from a ``jax.profiler``
    trace: XLA:CPU records one ``ThunkExecutor::Execute`` event for each sequence of kernels it
    dispatches, so a time loop compiled into one kernel gives ~0 per step, and a loop run
    kernel by kernel gives one per step or more (its kernels then each count as a launch)."""
    import gzip
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp):
            jax.block_until_ready(compiled(*args))
        events = []
        for f in Path(tmp).rglob("*.trace.json.gz"):
            events += json.loads(gzip.decompress(f.read_bytes()))["traceEvents"]
    return sum(1 for e in events if e.get("ph") == "X"
               and e.get("name") == "ThunkExecutor::Execute") / n_steps


def per_landing_step(vehicle, solver, sizes, repeats, trace_solver=None, dispatches=True):
    """ns per landing-step of both models, single landing (jit) and vmapped batches, run
    interleaved repeat by repeat, in wall time and in the process's CPU time (all threads:
    fairer on a shared machine); with the loop-body counts of each compiled program and its
    kernel dispatches per step (``dispatches_per_step``, on ``trace_solver``'s shorter
    landing when given, so that a loop run kernel by kernel leaves a small trace; not counted
    with ``dispatches`` off: the trace's events are XLA:CPU's)."""
    def compiled_for(model, n, solv):
        tilt = dict(roll=0.01) if model == "full" else {}  # the full model's general path
        if n == 0:
            fn = jax.jit(lambda s: landing(vehicle, s, solv, model)[1]["max_stroke_m"])
            args = (Scene(**tilt),)
        else:
            fn = jax.jit(lambda sc: landings(vehicle, sc, solv, model)[1]["max_stroke_m"])
            args = (Scene.batch(drop_height=jnp.linspace(0.05, 0.5, n),
                                **{k: jnp.full(n, v) for k, v in tilt.items()}),)
        t0 = time.perf_counter()
        compiled = fn.lower(*args).compile()
        return compiled, args, time.perf_counter() - t0

    runs = {}
    for model in ("quarter", "full"):
        for n in sizes:
            compiled, args, compile_s = compiled_for(model, n, solver)
            jax.block_until_ready(compiled(*args))
            runs[(model, n)] = (compiled, args, compile_s, [], [])
    for _ in range(repeats):
        for compiled, args, _, times, cpu in runs.values():
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(compiled(*args))
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    out = {}
    for (model, n), (compiled, args, compile_s, times, cpu) in runs.items():
        run_s, per = statistics.median(times), max(n, 1) * solver.n_steps
        if not dispatches:
            n_dispatches = None
        elif trace_solver is None:
            n_dispatches = dispatches_per_step(compiled, args, solver.n_steps)
        else:
            short, short_args, _ = compiled_for(model, n, trace_solver)
            n_dispatches = dispatches_per_step(short, short_args, trace_solver.n_steps)
        out.setdefault(model, []).append(dict(
            batch=n, compile_s=compile_s, run_s=run_s, cpu_s=statistics.median(cpu),
            us_per_step=run_s / solver.n_steps * 1e6,
            ns_per_landing_step=run_s / per * 1e9,
            cpu_ns_per_landing_step=statistics.median(cpu) / per * 1e9,
            dispatches_per_step=n_dispatches,
            loop_body=loop_body_counts(compiled.as_text())))
    ratio = {str(q["batch"]): f["ns_per_landing_step"] / q["ns_per_landing_step"]
             for q, f in zip(out["quarter"], out["full"])}
    cpu_ratio = {str(q["batch"]): f["cpu_ns_per_landing_step"] / q["cpu_ns_per_landing_step"]
                 for q, f in zip(out["quarter"], out["full"])}
    return dict(t_end_s=solver.t_end, dt_s=solver.dt, n_steps=solver.n_steps,
                note="batch 0 is one landing under jit, without vmap; full-model scenes rolled "
                     "0.01 rad",
                repeats=repeats, models=out, full_over_quarter=ratio,
                full_over_quarter_cpu=cpu_ratio)


def _model_timings(vehicle, solver, model, sizes, repeats):
    scene = Scene()

    def one(s):
        return landing(vehicle, s, solver, model)[1]["max_stroke_m"]

    compile_s, run_s = _compile_and_time(one, (scene,), repeats)
    batched = []
    for n in sizes:
        scenes = Scene.batch(drop_height=jnp.linspace(0.05, 0.5, n))
        c_s, r_s = _compile_and_time(
            lambda sc: landings(vehicle, sc, solver, model)[1]["max_stroke_m"], (scenes,),
            1 if n >= 1000 else repeats)
        batched.append(dict(batch=n, compile_s=c_s, run_s=r_s, landings_per_s=n / r_s))
    single = dict(compile_s=compile_s, run_s=run_s, ns_per_step=run_s / solver.n_steps * 1e9)
    return single, batched


def run_benchmark(out_dir: Path, *, quick: bool = False, batch: int = 1000) -> dict:
    """Run the benchmark and write ``bench_landing.json`` and ``bench_landing.png``."""
    load_before = os.getloadavg()[0]
    vehicle = jl.paper_vehicle()
    t_end = 0.3 if quick else 1.2
    solver = Solver(dt=1e-5, t_end=t_end, save_dt=1e-3)
    repeats = 2 if quick else 5
    scene = Scene()
    # --quick is a smoke run of every code path: one batch size (each one compiles anew)
    sizes = [10] if quick else [s for s in (1, 10, 100, 1000, 10000) if s <= batch]
    single, batched = _model_timings(vehicle, solver, "quarter", sizes, repeats)
    full_sizes = [s for s in sizes if s <= (10 if quick else 100)]
    full_single, full_batched = _model_timings(vehicle, solver, "full", full_sizes, repeats)

    def stroke_of(theta):
        new = tuple(p * jnp.exp(t) for p, t in zip(params(vehicle), theta))
        return landing(eqx.tree_at(params, vehicle, new), scene, solver,
                       "quarter")[1]["max_stroke_m"]

    th0 = jnp.zeros(6)
    run_s = single["run_s"]
    jf_compile, jf_run = _compile_and_time(jax.jacfwd(stroke_of), (th0,), repeats)
    gr_compile, gr_run = _compile_and_time(jax.grad(stroke_of), (th0,), repeats)
    step_solver = Solver(dt=1e-5, t_end=0.02 if quick else 0.3, save_dt=1e-3)
    steps = per_landing_step(vehicle, step_solver, (0, 4) if quick else (0, 64, 512),
                             2 if quick else 5,
                             None if quick else Solver(dt=1e-5, t_end=0.01, save_dt=1e-3))

    result = dict(
        scene="paper 0.2 m drop (symmetric), symplectic Euler; quarter and full 3-D model",
        dt_s=solver.dt, t_end_s=t_end, n_steps=solver.n_steps,
        machine=machine(),
        # the 1-minute load average before and after the run: on a shared machine the timings
        # scale with it, the side-by-side ratios much less
        load_average_1min=[load_before, os.getloadavg()[0]],
        single=single,
        batched=batched,
        full_model=dict(single=full_single, batched=full_batched,
                        cost_ratio_single=full_single["run_s"] / run_s),
        gradients=dict(jacfwd_6_params=dict(compile_s=jf_compile, run_s=jf_run,
                                             ratio_to_forward=jf_run / run_s),
                       grad_6_params=dict(compile_s=gr_compile, run_s=gr_run,
                                           ratio_to_forward=gr_run / run_s)),
        per_landing_step=steps,
        quick=quick,
    )
    write_json(out_dir / "bench_landing.json", result, indent=2)
    _plot(result, out_dir / "bench_landing.png")
    return result


# batch sizes of --accelerator: 0 is one landing under jit; a GPU runs 10^3 to 10^5 landings at
# nearly the same cost per step, so its sizes span that range
ACCEL_SIZES = (0, 1024, 16384, 131072)


def run_accelerator(out_dir: Path, *, quick: bool = False) -> dict:
    """The per-landing-step comparison (``per_landing_step``) on this machine's accelerator,
    with its scenes, step and landing unchanged and GPU-sized batches (``ACCEL_SIZES``):
    ns per landing-step of both models and what each compiled time step is made of. On a GPU
    every fusion, copy and library call left in the loop body is one kernel launch per step
    (XLA:CPU, with batch fusion, runs the whole loop as one kernel instead). Writes
    ``bench_landing_accelerator.json`` and ``.png``."""
    vehicle = jl.paper_vehicle()
    solver = Solver(dt=1e-5, t_end=0.02 if quick else 0.3, save_dt=1e-3)
    steps = per_landing_step(vehicle, solver, (0, 4) if quick else ACCEL_SIZES,
                             2 if quick else 3, dispatches=False)
    result = dict(scene="as bench_landing.json's per_landing_step, on the accelerator",
                  machine=machine(), device_kind=jax.devices()[0].device_kind,
                  xla_flags=os.environ.get("XLA_FLAGS", ""),
                  backend=jax.default_backend(), per_landing_step=steps, quick=quick)
    write_json(out_dir / "bench_landing_accelerator.json", result, indent=2)
    _plot_accelerator(result, out_dir / "bench_landing_accelerator.png")
    return result


def _plot_accelerator(result: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    steps = result["per_landing_step"]
    fig = Figure(figsize=(10, 4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    for model, rows in steps["models"].items():
        batched = [r for r in rows if r["batch"] > 0]
        n = [r["batch"] for r in batched]
        k = batched[-1]["loop_body"]["kernels"]
        ax1.loglog(n, [r["ns_per_landing_step"] for r in batched], "o-", label=f"{model} model")
        ax2.loglog(n, [r["us_per_step"] for r in batched], "o-",
                   label=f"{model} model ({k} kernels per step at {n[-1]})")
    ax1.set_xlabel("batch size [landings]")
    ax1.set_ylabel("time per landing and step [ns]")
    ax2.set_xlabel("batch size [landings]")
    ax2.set_ylabel("time per step of the whole batch [us]")
    for ax in (ax1, ax2):
        ax.legend()
    fig.suptitle(f"{result['device_kind']}: {steps['t_end_s']:g} s landings at "
                 f"dt = {steps['dt_s']:g} s (vmapped batches)")
    save_png(fig, path)


def _plot(result: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 4), layout="constrained")
    ax1, ax2, ax3 = fig.subplots(1, 3)
    for label, res in (("quarter", result), ("full 3-D", result["full_model"])):
        b = res["batched"]
        line, = ax1.loglog([r["batch"] for r in b], [r["landings_per_s"] for r in b], "o-",
                           label=f"{label}: vmapped batch")
        ax1.axhline(1.0 / res["single"]["run_s"], color=line.get_color(), ls=":",
                    label=f"{label}: one landing, jit")
    ax1.set_xlabel("batch size [landings]")
    ax1.set_ylabel("throughput [landings/s]")
    ax1.set_title(f"{result['t_end_s']:g} s landings at dt = {result['dt_s']:g} s")
    ax1.legend()
    labels = ["forward", "jacfwd (6)", "grad (6)"]
    grads = result["gradients"]
    runs = [result["single"]["run_s"], grads["jacfwd_6_params"]["run_s"],
            grads["grad_6_params"]["run_s"]]
    comps = [result["single"]["compile_s"], grads["jacfwd_6_params"]["compile_s"],
             grads["grad_6_params"]["compile_s"]]
    x = np.arange(3)
    ax2.bar(x - 0.2, np.array(runs) * 1e3, 0.4, label="run [ms]")
    ax2.bar(x + 0.2, np.array(comps) * 1e3, 0.4, label="compile [ms]")
    ax2.set_xticks(x, labels)
    ax2.set_yscale("log")
    ax2.set_ylabel("time [ms]")
    ax2.set_title("one landing: run and compile time")
    ax2.legend()
    steps = result["per_landing_step"]
    for k, (model, rows) in enumerate(steps["models"].items()):
        labels = ["one" if r["batch"] == 0 else f"batch {r['batch']}" for r in rows]
        xs = np.arange(len(rows))
        ax3.bar(xs + (k - 0.5) * 0.4, [r["ns_per_landing_step"] for r in rows], 0.4,
                label=f"{model} model")
        ax3.set_xticks(xs, labels)
    ax3.set_yscale("log")
    ax3.set_ylabel("time per landing and step [ns]")
    ax3.set_title(f"cost per landing-step ({steps['t_end_s']:g} s landings, side by side)")
    ax3.legend()
    save_png(fig, path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_out_args(p)
    p.add_argument("--batch", type=int, default=1000, help="largest vmapped batch (default 1000)")
    p.add_argument("--accelerator", action="store_true",
                   help="only the per-landing-step comparison, on this machine's GPU, at batches "
                        f"of {', '.join(str(n) for n in ACCEL_SIZES[1:])} "
                        "(bench_landing_accelerator.json; refused where JAX's backend is the CPU, "
                        "unless --quick)")
    args = p.parse_args(argv)
    if args.batch < 1:
        p.error(f"--batch {args.batch}: must be at least 1")
    if args.accelerator and jax.default_backend() == "cpu" and not args.quick:
        p.error("--accelerator: JAX's backend here is the CPU; run it on a machine with a GPU")
    out = out_dir(args.out, args.quick)
    if args.accelerator:
        result = run_accelerator(out, quick=args.quick)
        print(json.dumps(result["per_landing_step"], indent=2))
        print(f"wrote {out / 'bench_landing_accelerator.json'} and bench_landing_accelerator.png")
        return 0
    result = run_benchmark(out, quick=args.quick, batch=args.batch)
    print(json.dumps(result, indent=2))
    print(f"wrote {out / 'bench_landing.json'} and bench_landing.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
