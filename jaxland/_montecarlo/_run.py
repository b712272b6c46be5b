"""The run: chunks of sampled scenes through the compiled batch, sharded over devices."""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._config import paper_vehicle, validate_vehicle, vehicle_to_toml
from .._errors import ConfigError
from .._files import atomic_write_csv, flat_columns, json_text, run_environment, staged
from .._models import MODELS
from .._params import Vehicle
from .._progress import ProgressLine
from .._scene import Scene
from .._simulate import landings, refuse_unsteppable
from .._solvers import FAILED_CODES, Result, Solver, stable_step
from .._solvers._base import T_END_MAX
from ._sample import check_fixed, draw, sample_scenes, scene_fields
from ._spec import LEDGER_CHECK_S, MonteCarloSpec, montecarlo_spec_to_toml, period
from ._stats import (
    over_all_landings,
    percentile_intervals,
    percentiles,
    proportion,
    sensitivity,
    tip_over_of,
)

# the running maxima a Monte Carlo reports (each costs a maximum per step; the others are not
# kept): per model, the quarter's and the 3-D model's attitude peaks
REPORTED_PEAKS = {
    "quarter": ("peak_strut_force_N", "peak_normal_force_N", "peak_honeycomb_force_N",
                "peak_body_accel_mps2"),
}
REPORTED_PEAKS["full"] = REPORTED_PEAKS["quarter"] + ("peak_tilt_deg", "peak_margin_deficit_m")


def ledger_check_s(spec: MonteCarloSpec, model: str) -> float:
    """The ledger check interval [s] of a run (0: every step)."""
    return LEDGER_CHECK_S[model] if spec.ledger_check is None else float(spec.ledger_check)


def mc_solver(spec: MonteCarloSpec, model: str, dt: float, method: str, *,
              t_end: float | None = None) -> Solver:
    """The run settings of a Monte Carlo's landings: without a trajectory, the reported peaks
    only, no contact event times (their count decides touchdown), the ledger checked every
    ``ledger_check_s`` seconds. ``t_end`` (the t_end check's longer run): to that time,
    saving the state at ``spec.t_end``, without early stop."""
    longer = t_end is not None
    return Solver(dt=dt, t_end=t_end if longer else spec.t_end, save_dt=spec.t_end,
                  method=method, early_stop=spec.early_stop and not longer,
                  peaks=REPORTED_PEAKS[model], event_log=0, trajectory=longer,
                  ledger_every=max(1, round(ledger_check_s(spec, model) / dt))).validate()


def _per_sample(vehicle, solver, model, scenes):
    traj, s = landings(vehicle, scenes, solver, MODELS[model])
    del traj
    return _outcomes(s, vehicle, model)


def _outcomes(s: dict, vehicle, model: str) -> dict:
    """A Monte Carlo's outcomes per sample from the landings' summary ``s``."""
    n = vehicle.n_legs

    def legs(x):
        return jnp.broadcast_to(x[..., None], x.shape + (n,)) if x.ndim == 1 else x

    out = dict(
        max_stroke_m=legs(s["max_stroke_m"]),
        peak_strut_force_N=legs(s["peak_strut_force_N"]),
        peak_normal_force_N=legs(s["peak_normal_force_N"]),
        peak_honeycomb_force_N=legs(s["peak_honeycomb_force_N"]),
        slip_distance_m=legs(s["slip_distance_m"]),
        peak_body_accel_mps2=s["peak_body_accel_mps2"],
        energy_closure_rel=s["ledger_error_rel"],
        result=s["result"],
        tipped_over=s["tipped"],
    )
    if "settled_time_s" in s:
        out["settled_time_s"] = s["settled_time_s"]
    if model == "full":
        out["min_stability_margin_m"] = -s["peak_margin_deficit_m"]
        out["peak_tilt_deg"] = s["peak_tilt_deg"]
    return out


def _chunk(spec, vehicle, solver, model, inputs, count):
    """One chunk's outcomes per sample from its drawn inputs; a sample outside the envelope
    (unbounded distributions can draw there) carries Result.OUTSIDE_ENVELOPE from its landing
    (``jaxland.landing``), a failure, not a landing."""
    scenes = Scene.batch(**scene_fields(spec, inputs, count, vehicle.n_legs))
    return _per_sample(vehicle, solver, model, scenes)


# run_montecarlo(share_program=True): the last compiled chunk, by spec, settings and chunk
# size, with the vehicle an argument (a design's verification runs the baseline and the design
# through it)
_COMPILED: dict = {}


def _compiled_chunk(spec, solver, model, count):
    # n and seed only choose the samples, not the program
    key = (repr(dataclasses.replace(spec, n=1, seed=0)), solver, model, count)
    fn = _COMPILED.get(key)
    if fn is None:
        fn = jax.jit(lambda vehicle, ins: _chunk(spec, vehicle, solver, model, ins, count))
        _COMPILED.clear()  # one entry: a program holds its compiled code and constants
        _COMPILED[key] = fn
    return fn


def _compile(fn, shapes, sharding):
    """``fn`` lowered and compiled for inputs shaped like ``shapes``, placed on ``sharding``."""
    return fn.lower(jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), shapes)).compile()


# per-sample columns that describe how a sample ran, not its outcome: kept for a failed one
RUN_COLUMNS = ("dt_s", "retried", "t_end_s")


@dataclass
class MonteCarloResult:
    """Per-sample inputs and outcomes (numpy), failure reasons, and the summary. A failed
    sample's ``outputs`` (``failure`` in ``FAILED_CODES``) are the numbers its failed run left,
    which no statistic uses; ``columns``, what the files hold, leaves them empty."""

    inputs: dict
    outputs: dict
    failure: np.ndarray  # (n,) jaxland.Result codes, 0 = successful (see ``reasons``)
    summary: dict
    reasons: dict = field(default_factory=lambda: {int(r): r.message for r in Result})
    vehicle: Vehicle | None = None  # the vehicle the landings ran (save: vehicle.toml)
    spec: MonteCarloSpec | None = None  # the spec run (save: spec.toml)
    # the t_end check's landings run to its end (check_t_end): "samples" (indices), "t_end_s"
    # and "outputs" (as ``outputs``, with "result"); None where no check ran
    t_end_longer: dict | None = None

    def columns(self) -> dict:
        """One flat column per quantity (per-leg arrays as leg{i}_...), units in the names.
        A failed sample's outcomes are NaN (a flag column then holds 0/1 and NaN): its run
        diverged or left the envelope, and its numbers are no landing's; the step it ran
        with (``dt_s``) and ``retried`` stay."""
        failed = np.isin(self.failure, FAILED_CODES)
        outputs = self.outputs
        if failed.any():
            outputs = {}
            for key, v in self.outputs.items():
                v = np.asarray(v)
                if key not in RUN_COLUMNS:
                    v = v.astype(float)  # a copy: the result keeps its own
                    v[failed] = np.nan
                outputs[key] = v
        return {"sample": np.arange(self.failure.size),
                **flat_columns(self.inputs, outputs), "failure_code": self.failure}

    def save(self, out_dir, plots: bool = True, rerun: str | None = None) -> list[Path]:
        """Write samples.csv and samples.npz (every sample with its inputs), summary.json,
        vehicle.toml (the vehicle run, where known), spec.toml (the spec run, where known;
        ``rerun``: what rerunning it gives, where that is not these landings) and the
        figures (``plots``) into ``out_dir``, all through a staging folder."""
        out = Path(out_dir)
        with staged(out, "montecarlo") as staging:
            if self.vehicle is not None:
                (staging / "vehicle.toml").write_text(
                    "# the vehicle the landings ran, before each sample's dispersions\n"
                    + vehicle_to_toml(self.vehicle))
            if self.spec is not None:
                (staging / "spec.toml").write_text(
                    "# the spec as run (--n and --seed applied, defaults filled in): "
                    "jaxland montecarlo spec.toml --config vehicle.toml runs "
                    + (rerun or "these landings again") + "\n"
                    + montecarlo_spec_to_toml(self.spec))
            cols = self.columns()
            atomic_write_csv(staging / "samples.csv", cols)
            np.savez_compressed(staging / "samples.npz", **cols)
            (staging / "summary.json").write_text(json_text(self.summary))
            if plots:
                from .._plots import plot_montecarlo

                plot_montecarlo(self, staging / "figures")
            written = sorted(out / p.relative_to(staging) for p in staging.rglob("*")
                             if p.is_file())
        return written


def init_distributed(coordinator: str, num_processes: int, process_id: int) -> None:
    """Join a Monte Carlo run of ``num_processes`` processes (one per machine, or several on one)
    before any JAX computation: ``coordinator`` is ``host:port`` of process 0, reachable by all.
    CPU processes exchange results over gloo; on GPUs JAX picks its own collectives."""
    for name, val, ok in (("num_processes", num_processes, num_processes >= 1),
                          ("process_id", process_id, 0 <= process_id < max(num_processes, 1))):
        if isinstance(val, bool) or not isinstance(val, int) or not ok:
            raise ConfigError(name, val, "must be an integer >= 1" if name == "num_processes"
                              else f"must be an integer in [0, {num_processes})")
    if ":" not in coordinator:
        raise ConfigError("coordinator", coordinator, "must be host:port")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator, num_processes=num_processes, process_id=process_id)


# Landings per compiled chunk when none is given, by the devices' platform. A CPU device runs a
# chunk's time loop as one single-threaded kernel whose cost per landing does not fall with the
# batch, so small chunks bound memory and give the progress line its steps. On a GPU a chunk's
# time grows far less than its size up to about 10^5 landings, so it takes the chunk that ran
# fastest in a sweep on an H200 (docs/montecarlo.md, "On a GPU"; no other GPU was measured),
# about 350 MiB of device memory for the 3-D model.
DEFAULT_CHUNK = {"cpu": {"quarter": 512, "full": 64},
                 "accelerator": {"quarter": 131072, "full": 131072}}


def default_chunk(model: str, devices) -> int:
    """``DEFAULT_CHUNK`` for ``model`` on ``devices`` (a list of JAX devices)."""
    kind = "cpu" if all(d.platform == "cpu" for d in devices) else "accelerator"
    return DEFAULT_CHUNK[kind][model]


# host memory a sample's results take at most (inputs, outcomes, failure code, its samples.csv
# row), a generous bound: the full model's come to about 0.5 KiB
HOST_BYTES_PER_SAMPLE = 1024


def _check_host_memory(n: int) -> None:
    """Refuse, before any work, a run whose per-sample results cannot fit in this machine's
    memory (they are gathered on the host)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # no sysconf here: not checked
        return
    need = n * HOST_BYTES_PER_SAMPLE
    if need > total:
        raise ConfigError("montecarlo.n", n, f"its per-sample results take up to "
                          f"{need / 2**30:.3g} GiB on the host, more than this machine's "
                          f"{total / 2**30:.3g} GiB: run fewer samples")


def check_run(spec: MonteCarloSpec, vehicle: Vehicle) -> str:
    """Refuse, before any work, a run this machine cannot hold, a step above the method's
    a-priori stability limit for ``vehicle`` or a fixed per-leg input of the wrong length;
    returns the model the run takes."""
    _check_host_memory(spec.n)
    model = spec.resolved_model()
    limit = float(stable_step(vehicle, method=spec.method, model=MODELS[model]))
    if spec.dt > limit:
        refuse_unsteppable(vehicle, limit, spec.t_end)
        raise ConfigError("montecarlo.dt_s", spec.dt,
                          f"exceeds the a-priori stability limit {limit:.3g} s of "
                          f"{spec.method}")
    check_fixed(spec, vehicle.n_legs)
    return model


def earliest_touchdown_s(spec: MonteCarloSpec, vehicle: Vehicle) -> float:
    """A lower bound [s] on the first touchdown of every sample: the lowest foot's clearance
    (the least drop height) closes at most at the largest sink speed plus the largest
    horizontal speed times the sine of the steepest slope (the ground rising under a body
    that crosses it), and gravity. 0 where the body turns (a rate given): a turning body can
    lower a foot faster."""
    if any(spec.range_of(k) != (0.0, 0.0)
           for k in ("roll_rate_degps", "pitch_rate_degps", "yaw_rate_degps")):
        return 0.0
    h = spec.range_of("drop_height_m")[0]
    rate = (spec.range_of("sink_speed_mps")[1] + spec.range_of("horizontal_speed_mps")[1]
            * math.sin(math.radians(spec.range_of("slope_deg")[1])))
    g = float(vehicle.g)
    return (math.sqrt(rate * rate + 2.0 * g * h) - rate) / g


def check_touchdown_possible(spec: MonteCarloSpec, vehicle: Vehicle) -> None:
    """Refuse, before any landing, a run none of whose samples can touch down by t_end_s
    (``jaxland montecarlo``; ``run_montecarlo`` runs it and returns each sample's
    NO_TOUCHDOWN)."""
    t = earliest_touchdown_s(spec, vehicle)
    if t > spec.t_end:
        across = spec.range_of("horizontal_speed_mps")[1] * spec.range_of("slope_deg")[1]
        slope = (f", horizontal_speed_mps <= {spec.range_of('horizontal_speed_mps')[1]:g} "
                 f"across slope_deg <= {spec.range_of('slope_deg')[1]:g}" if across else "")
        raise ConfigError("montecarlo.t_end_s", spec.t_end,
                          f"ends before the earliest touchdown the dispersion allows ({t:.3g} s,"
                          f" from drop_height_m >= {spec.range_of('drop_height_m')[0]:g} at "
                          f"sink_speed_mps <= {spec.range_of('sink_speed_mps')[1]:g}{slope}): "
                          "no sample could land; raise it")


def run_montecarlo(spec: MonteCarloSpec, vehicle: Vehicle | None = None, *,
                   chunk: int | None = None, devices=None, progress: bool | str = True,
                   share_program: bool = False) -> MonteCarloResult:
    """Run ``spec.n`` dispersed landings; see the module docstring for reproducibility and
    sharding. ``chunk`` bounds memory (rounded up to a multiple of the device count; default
    ``DEFAULT_CHUNK`` by the devices' platform);
    ``progress``: a progress line on stderr (a string: the line's label). ``share_program``:
    the vehicle is an argument of the compiled chunk, kept for the next run of the same spec
    with this flag, so that one compilation serves several vehicles (a design's verification);
    otherwise the vehicle is a constant of the program, which steps faster than the shared one."""
    vehicle = paper_vehicle() if vehicle is None else validate_vehicle(vehicle)
    model = check_run(spec, vehicle)
    solver = mc_solver(spec, model, spec.dt, spec.method)
    devices = list(jax.local_devices() if devices is None else devices)
    n_dev = len(devices)
    chunk = min(spec.n, default_chunk(model, devices)) if chunk is None else int(chunk)
    if chunk < 1:
        raise ConfigError("chunk", chunk, "must be >= 1")
    # no larger than the run (padding beyond it is work for nothing), a whole number per device
    chunk = int(math.ceil(min(chunk, spec.n) / n_dev) * n_dev)
    mesh = Mesh(np.array(devices), ("batch",))
    batch_sharding = NamedSharding(mesh, PartitionSpec("batch"))

    # Several processes (jax.distributed): process p runs chunks p, p + P, ...; every sample's
    # inputs depend only on (seed, index), so the gathered result is the one-process result.
    n_proc, rank = jax.process_count(), jax.process_index()
    starts = list(range(0, spec.n, chunk))[rank::n_proc]
    def inputs_of(start):  # a padded chunk's drawn inputs, on the devices (no wait)
        return jax.device_put(draw(spec, jnp.arange(start, start + chunk), vehicle.n_legs),
                              batch_sharding)

    # One compiled program per chunk: the scenes from the drawn inputs, the landings, the
    # outcomes per sample and the envelope check; the host only copies the results out.
    t0 = time.perf_counter()  # the wall time counts the compilation, as the run's did
    prepared = {}  # start -> inputs drawn ahead
    if share_program:
        run = functools.partial(_compiled_chunk(spec, solver, model, chunk), vehicle)
    else:  # the chunk compiles in a second thread while the first draw compiles and runs
        shapes = jax.eval_shape(lambda i: draw(spec, i, vehicle.n_legs), jnp.arange(chunk))
        with ThreadPoolExecutor(max_workers=1) as pool:
            compiling = pool.submit(
                _compile, jax.jit(lambda ins: _chunk(spec, vehicle, solver, model, ins, chunk)),
                shapes, batch_sharding)
            if starts:
                prepared[starts[0]] = inputs_of(starts[0])
            run = compiling.result()
    outputs: dict = {}
    inputs: dict = {}
    label = progress if isinstance(progress, str) else "montecarlo"
    line = ProgressLine(f"{label}:", quiet=not progress or rank != 0, in_place=True)
    done = 0

    def dispatch(start):  # no wait for the device: returns the chunk's arrays being computed
        ins = prepared.pop(start) if start in prepared else inputs_of(start)
        return start, ins, run(ins)

    pending = [dispatch(starts[0])] if starts else []
    for k in range(len(starts)):
        if k + 1 < len(starts):  # enqueue the next chunk before waiting for this one
            pending.append(dispatch(starts[k + 1]))
        start, ins, res = pending.pop(0)
        count = min(chunk, spec.n - start)
        res, ins = jax.device_get((res, ins))
        for group, new in ((outputs, res), (inputs, ins)):
            for key, v in new.items():
                v = np.asarray(v)[:count]
                if key not in group:
                    group[key] = np.zeros((spec.n, *v.shape[1:]), v.dtype)
                group[key][start:start + count] = v
        done += count
        line(f"{done}/{spec.n} landings ({model} model, {n_dev} device"
             f"{'s' if n_dev > 1 else ''}{_of_processes(n_proc)}, "
             f"{done / (time.perf_counter() - t0):.3g}/s)")
    line.close()
    if n_proc > 1:
        outputs, inputs = _gather(outputs, inputs, spec.n, chunk, n_proc)

    outputs["dt_s"] = np.full(spec.n, float(spec.dt))
    outputs["retried"] = np.zeros(spec.n, bool)
    if spec.retry:
        _retry(spec, vehicle, model, outputs, line, chunk=chunk)
    wall = time.perf_counter() - t0  # the landings', retries included
    bottomed = bottomed_out(outputs, vehicle)
    failure = outputs.pop("result").astype(int)  # a Result code per sample (verdict)
    outputs["bottomed_out"] = bottomed
    outputs["tipped_over"] = outputs["tipped_over"].astype(bool)
    summary = _summarise(spec, model, inputs, outputs, failure, wall, n_dev, chunk)
    summary["t_end_check"], longer = check_t_end(spec, vehicle, model, outputs, failure, line)
    return MonteCarloResult(inputs, outputs, failure, summary, vehicle=vehicle,
                            spec=dataclasses.replace(spec), t_end_longer=longer)


T_END_CHECK_FACTOR = 2.0  # the t_end check's landings run to this multiple of t_end_s
# a max stroke growing by more than this fraction after t_end_s counts as changed: the
# Monte Carlo's accuracy target (docs/montecarlo.md, choosing the step)
T_END_CHECK_TOL = 1e-3


def check_t_end(spec: MonteCarloSpec, vehicle: Vehicle, model: str, outputs: dict,
                failure: np.ndarray, line=None) -> tuple[dict | None, dict | None]:
    """Whether the outcomes at ``t_end_s`` are final, measured: the first ``t_end_check``
    landings called finished (SUCCESSFUL; with early stop, those that did not settle) run
    again, each with the method and step it ended with, to ``T_END_CHECK_FACTOR`` x t_end_s,
    saving the state at t_end_s. A landing has changed where, after t_end_s in that same run,
    a leg's max stroke grew by more than ``T_END_CHECK_TOL`` of it, or it tipped over or
    bottomed out. ``UNFINISHED`` catches a leg still compressing at t_end; a vehicle rocking
    on its legs or a foot in the air comes down and crushes again later, which this counts.
    The changed fraction's 95 % Wilson interval estimates it over the landings it was drawn
    from (``of``: the finished ones, or with early stop those that did not settle). None where
    the check is off or no landing finished; where twice t_end_s is beyond the longest run
    (``T_END_MAX``), a dict saying it was ``skipped``.

    Also returns the checked landings' outcomes at the check's end (``MonteCarloResult.
    t_end_longer``; those whose rerun failed numerically left out), or None: a design's
    verification judges them on these."""
    ok = failure == int(Result.SUCCESSFUL)
    of = "finished landings"
    if "settled_time_s" in outputs:  # a settled landing's outcomes are final (the bound)
        ok &= ~np.isfinite(outputs["settled_time_s"])
        of = "finished landings that did not settle"
    idx = np.flatnonzero(ok)[:spec.t_end_check]
    if idx.size == 0:
        return None, None
    t_check = T_END_CHECK_FACTOR * spec.t_end
    if t_check > T_END_MAX:
        return dict(n_checked=0, t_end_s=t_check, skipped=(
            f"twice t_end_s ({t_check:g} s) is beyond the longest run ({T_END_MAX:g} s)")), None
    t0 = time.perf_counter()
    methods = np.where(outputs["retried"][idx], retry_method(spec.method), spec.method)
    steps = outputs["dt_s"][idx]
    at_end = np.zeros((idx.size, vehicle.n_legs))  # max stroke at t_end_s
    tip_time = np.zeros(idx.size)
    longer: dict = {}  # the outcomes at t_check
    if line is not None:
        line(f"t_end check: {idx.size} landing(s) to {t_check:g} s")
    for method, dt in sorted(set(zip(methods.tolist(), steps.tolist()))):
        sel = (methods == method) & (steps == dt)
        solver = mc_solver(spec, model, dt, method, t_end=t_check)
        size = 8 * -(-int(sel.sum()) // 8)  # padded with the last landing: fewer compilations
        rows = np.concatenate([idx[sel], np.full(size - sel.sum(), idx[sel][-1])])
        scenes, _ = sample_scenes(spec, 0, 0, vehicle.n_legs, indices=rows)
        s = jax.device_get(_t_end_program(solver, model)(vehicle, scenes))
        k = int(sel.sum())
        at_end[sel] = np.broadcast_to(np.asarray(s.pop("at_t_end"))[:k].reshape(k, -1),
                                      (k, vehicle.n_legs))
        tip_time[sel] = np.asarray(s.pop("tip_over_time_s"))[:k]
        for key, v in s.items():
            v = np.asarray(v)[:k]
            longer.setdefault(key, np.zeros((idx.size, *v.shape[1:]), v.dtype))[sel] = v
    if line is not None:
        line.close()
    later, result = longer["max_stroke_m"], longer["result"]
    tipped = longer["tipped_over"].astype(bool) & (tip_time > spec.t_end)
    ran = ~np.isin(result, FAILED_CODES)  # a rerun that failed numerically judges nothing
    growth = (later - at_end).max(axis=1)
    bottomed = (bottomed_out({"max_stroke_m": later}, vehicle)
                & ~bottomed_out({"max_stroke_m": at_end}, vehicle))
    # relative to the stroke, and at least 1 um on a leg that barely crushed (under 1 mm)
    grew = (later - at_end > T_END_CHECK_TOL * np.maximum(at_end, 1e-3)).any(axis=1)
    changed = ran & (grew | tipped | bottomed)
    return dict(
        n_checked=int(ran.sum()), of=of, t_end_s=t_check, tolerance=T_END_CHECK_TOL,
        n_changed=int(changed.sum()), changed=proportion(changed[ran]),
        changed_samples=idx[changed].tolist(),
        n_max_stroke_grew=int((ran & grew).sum()),
        max_stroke_growth_m=float(growth[ran].max()) if ran.any() else None,
        n_tipped_later=int((ran & tipped).sum()), n_bottomed_later=int((ran & bottomed).sum()),
        n_rerun_failed=int((~ran).sum()),
        # not in the run's wall_s: the check's compilation and landings
        wall_s=time.perf_counter() - t0), dict(
        samples=idx[ran], t_end_s=t_check, outputs={k: v[ran] for k, v in longer.items()})


@functools.lru_cache(maxsize=2)
def _t_end_program(solver, model):
    """The t_end check's landings, the vehicle an argument: the max stroke at t_end_s (the
    trajectory's last saved state), the tip-over time and the Monte Carlo's outcomes at the
    end. Of the trajectory only the max stroke leaves the program, so XLA compiles none of the
    rest of the record (a third of its compilation)."""
    def run(vehicle, scenes):
        traj, s = landings(vehicle, scenes, solver, MODELS[model])
        return dict(_outcomes(s, vehicle, model), at_t_end=traj["stroke_max_m"][:, -1],
                    tip_over_time_s=s["tip_over_time_s"])
    return jax.jit(run)


RETRIED = (Result.NONFINITE, Result.LEDGER, Result.CLOSURE, Result.STEP_ABOVE_LIMIT)


RETRY_STEPS = 3  # tries after the first: the retry step, then a quarter of it, then a 16th


def retry_method(method: str) -> str:
    """The method a numerical failure of ``method`` is rerun with: explicit Euler's failures
    come from its explicit strut damping, so euler is rerun as euler_implicit; a method that
    already takes it implicitly reruns as itself (at a smaller step)."""
    return "euler_implicit" if method == "euler" else method


def _retry(spec: MonteCarloSpec, vehicle: Vehicle, model: str, outputs: dict, line,
           only: np.ndarray | None = None, chunk: int | None = None) -> None:
    """Run the samples that failed numerically again (of ``only``, sample indices, if given)
    and keep the new outcomes with the step used (``dt_s``; ``retried``). Explicit Euler's
    failures on hard landings come from its explicit strut damping, which grows with the
    force: they are rerun with the damping implicit (``euler_implicit``, whose limit does not
    depend on the force); a method that already takes it implicitly is rerun at
    ``retry_step``, the limit at the forces the sample's energy can reach, or at a quarter of
    its step where that limit is no smaller (the same method at the same step would fail the
    same way). Samples still failing are rerun at a quarter of their last step, up to
    ``RETRY_STEPS`` tries. Each sample's step is its own (samples that share one run
    together), so its outcome depends on its inputs alone, not on which other samples
    failed. Every process runs the same retries (same results). At most ``chunk`` samples
    run at once, on one device (None: all at once): a chunk's memory, where the run spreads
    one over the devices; the retries are few where the step suits the spec."""
    from .._simulate import retry_step

    method = retry_method(spec.method)
    stuck = np.zeros(outputs["result"].shape, bool)  # no step divides t_end: failures stand
    for attempt in range(RETRY_STEPS):
        failed = np.flatnonzero(np.isin(outputs["result"], [int(r) for r in RETRIED]) & ~stuck)
        if only is not None:
            failed = np.intersect1d(failed, only)
        if failed.size == 0:
            break
        scenes, _ = sample_scenes(spec, 0, 0, vehicle.n_legs, indices=failed)
        if attempt == 0:
            steps = np.array([min(spec.dt, retry_step(vehicle, jax.tree.map(
                lambda x, i=i: x[i] if np.ndim(x) >= 1 else x, scenes), method, MODELS[model]))
                for i in range(failed.size)])
            if method == spec.method:
                steps = np.where(steps < spec.dt, steps, spec.dt / 4.0)
        else:
            steps = outputs["dt_s"][failed] / 4.0
        for dt in sorted(set(steps.tolist()), reverse=True):
            mine = np.flatnonzero(steps == dt)
            try:
                solver = mc_solver(spec, model, dt, method)
            except ConfigError:  # t_end is no whole multiple of that step: the failures stand
                stuck[failed[mine]] = True
                continue
            line(f"retry {attempt + 1}: {mine.size} failed sample(s) with {method} at "
                 f"dt = {dt:.3g} s")
            run = jax.jit(lambda sc, solver=solver: _per_sample(vehicle, solver, model, sc))
            step = mine.size if chunk is None else int(chunk)
            for start in range(0, mine.size, step):
                part = mine[start:start + step]
                res = jax.device_get(run(jax.tree.map(
                    lambda x, part=part: x[part] if np.ndim(x) >= 1 else x, scenes)))
                for k, v in res.items():
                    outputs[k][failed[part]] = np.asarray(v)
            outputs["dt_s"][failed[mine]] = dt
            outputs["retried"][failed[mine]] = True
    line.close()


def bottomed_out(outputs: dict, vehicle: Vehicle) -> np.ndarray:
    """Per landing: a leg's max stroke went past the end of the honeycomb's stroke (x_L4)."""
    return np.asarray(outputs["max_stroke_m"]).max(axis=1) > float(vehicle.honeycomb.x_L4)


def _of_processes(n_proc: int) -> str:
    return f" in each of {n_proc} processes" if n_proc > 1 else ""


def _gather(outputs: dict, inputs: dict, n: int, chunk: int, n_proc: int):
    """Every process's samples, from all processes (``process_allgather``): sample i comes from
    the process that ran its chunk."""
    from jax.experimental import multihost_utils

    owner = (np.arange(n) // chunk) % n_proc
    both = multihost_utils.process_allgather((outputs, inputs), tiled=False)
    return jax.tree.map(lambda x: x[owner, np.arange(n)], both)


def _summarise(spec, model, inputs, outputs, failure, wall, n_dev, chunk) -> dict:
    ok = failure == int(Result.SUCCESSFUL)
    unfinished = failure == int(Result.UNFINISHED)
    failed = np.isin(failure, FAILED_CODES)
    # a draw outside the envelope was never run: no landing, unlike a numerical failure
    landed_failed = failed & (failure != int(Result.OUTSIDE_ENVELOPE))
    target = (outputs["min_stability_margin_m"] if "min_stability_margin_m" in outputs
              else outputs["max_stroke_m"].max(axis=1))
    reasons = {r.message: int((failure == r).sum()) for r in Result
               if r.failed and (failure == r).any()}
    envelope_samples = {
        "max_stroke_m (any leg)": outputs["max_stroke_m"][ok].max(axis=1),
        "peak_body_accel_mps2": outputs["peak_body_accel_mps2"][ok],
        "peak_strut_force_N (any leg)": outputs["peak_strut_force_N"][ok].max(axis=1),
        "slip_distance_m (any leg)": outputs["slip_distance_m"][ok].max(axis=1),
        **({"min_stability_margin_m": outputs["min_stability_margin_m"][ok]}
           if "min_stability_margin_m" in outputs else {}),
    }
    return dict(
        n=spec.n, seed=spec.seed, model=model, method=spec.method, dt_s=spec.dt,
        t_end_s=spec.t_end, ledger_check_s=ledger_check_s(spec, model),
        devices=n_dev, processes=jax.process_count(), chunk=chunk, wall_s=wall,
        landings_per_s=spec.n / wall,
        n_failed=int(failed.sum()), failures=reasons,
        failed_samples=np.flatnonzero(failed).tolist()[:100],
        n_no_touchdown=int((failure == int(Result.NO_TOUCHDOWN)).sum()),
        # still in an impact at t_end: outcomes not final, counted apart (raise t_end_s)
        n_unfinished=int(unfinished.sum()),
        n_retried=int(outputs["retried"].sum()),
        early_stop=spec.early_stop,
        n_settled=(int(np.isfinite(outputs["settled_time_s"]).sum())
                   if "settled_time_s" in outputs else None),
        settled_time_s=(percentiles(outputs["settled_time_s"][
            np.isfinite(outputs["settled_time_s"])]) if "settled_time_s" in outputs else None),
        retry_method=retry_method(spec.method) if outputs["retried"].any() else None,
        n_succeeded=int(ok.sum()),
        # over the successful landings; None where there is none (0/0 is no probability).
        # The quarter model cannot tip: no probability, not a computed-looking 0
        # (all_landings: where it lies with the unfinished and the failed landings, which
        # could still tip or bottom out)
        tip_over=over_all_landings(tip_over_of(model, outputs["tipped_over"][ok]),
                                 outputs["tipped_over"][unfinished], int(landed_failed.sum())),
        bottoming=over_all_landings(proportion(outputs["bottomed_out"][ok]),
                                  outputs["bottomed_out"][unfinished], int(landed_failed.sum())),
        envelopes={k: percentiles(v) for k, v in envelope_samples.items()},
        # each percentile's 95 % interval: a p99 of a few hundred landings is about their
        # largest, and the interval says how far it may lie from the truth
        envelopes_ci95={k: percentile_intervals(v) for k, v in envelope_samples.items()},
        sensitivity=dict(
            target="min_stability_margin_m" if model == "full" else "max_stroke_m",
            method="least squares on standardised inputs: change per standard deviation; "
                   "an azimuth enters as its sine and cosine",
            **sensitivity(inputs, target, ok,
                          {k: p for k in inputs if (p := period(k)) is not None})),
        dispersion={k: v.record() for k, v in spec.dispersion.items()},
        fixed=spec.fixed,
        environment=run_environment(),
    )
