"""What every integrator shares: the set-up, the bookkeeping carried beside the state, the saved
record, the end-of-landing summary, and the nested-scan driver of the fixed-step methods.

The bookkeeping runs at full step resolution: running peaks, the contact on/off log and the
tip-over time. The energy ledger's worst residual and the failure checks (ledger blow-up,
non-finite state) run on every ``Solver.ledger_every``-th step (default: every step).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import custom_batching
from jaxtyping import Array

from .._errors import ConfigError
from .._laws._minmax import fmax
from .._models import AbstractModel, Evaluation
from ._base import ENERGY_TOLERANCE, N_EVENTS, Result, forward_only
from ._settle import check_steps, mass_diagonal, settled

UNROLL = 1  # inner-loop unroll factor (unrolling made the fused step slower on CPU)
# m/s: a leg compressing at its largest stroke faster than this at t_end makes the landing
# UNFINISHED. At a strut deceleration of 1 g it would add 5 um of stroke, below 1e-3 of a max
# stroke of 5 mm or more; a leg creeping under a settling vehicle stays below it.
UNFINISHED_RATE_MPS = 0.01
# a model that can tip over keeps its max stroke as this peak: the summary's max_stroke_m then
# stops at the tip, as every peak does, where the stroke memory runs on to t_end
STROKE_PEAK = "peak_stroke_max_m"
# peaks that are always kept when ``Solver.peaks`` names a subset: the verdict judges the step
# limit by the first two, the early-stop bound reads the next two, the summary the last
ALWAYS_KEPT = ("peak_normal_force_N", "peak_honeycomb_force_N", "peak_strut_force_N",
               "peak_body_accel_mps2", STROKE_PEAK)


class Setup(eqx.Module):
    """A landing ready to step: the scene-adjusted vehicle and what the loop reads."""

    vehicle: eqx.Module
    derived: eqx.Module
    state0: eqx.Module
    energy0: Array  # J, the ledger at t = 0
    energy_scale: Array  # J
    peaks0: dict
    ev0: Evaluation  # at state0, no kick: the ledger's and peaks' start, a method's first forces


def setup(model: AbstractModel, vehicle, scene, solver) -> Setup:
    vehicle = model.apply_scene(vehicle, scene)  # scene-level friction and honeycomb scatter
    derived = model.prepare(vehicle, scene, solver.smoothing)  # once, outside the loop
    s0 = model.initial_state(vehicle, scene)
    ev0 = model.evaluate(vehicle, s0, scene, derived)
    e0 = ev0.ledger() + jnp.sum(s0.diss_rate)
    return Setup(vehicle, derived, s0, e0, model.energy_scale(vehicle, scene),
                 kept_peaks(model, solver, model.peak_values(ev0.record, ev0.accel)), ev0)


def kept_peaks(model: AbstractModel, solver, values: dict) -> dict:
    """The running maxima a landing keeps: all of the model's, or ``solver.peaks`` and
    ``ALWAYS_KEPT`` (a Monte Carlo keeps what it reports: each peak is a maximum per step)."""
    if solver.peaks is None:
        return values
    unknown = sorted(set(solver.peaks) - set(values))
    if unknown:
        raise ConfigError("solver.peaks", unknown[0], f"is not a peak of the {model.name} "
                          f"model; its peaks: {', '.join(values)}")
    names = set(solver.peaks) | set(ALWAYS_KEPT)
    return {k: v for k, v in values.items() if k in names}


class Track(eqx.Module):
    """Bookkeeping carried alongside the state."""

    peaks: dict  # running maxima of the model's peak_values
    # (Solver.event_log + 1,) s, contact on/off times: entry i < n_events is the i-th change;
    # a single landing's step writes its time at min(n_events, capacity) unconditionally (one
    # store, no read or select), so the entries from n_events on (the last one a spare slot)
    # hold no change (``events`` reads the log)
    event_times: Array
    # int32, contact changes so far; odd: in contact at the last step (the flag itself is not
    # carried: on XLA:CPU each carried value is one more kernel, buffer and copy per step)
    n_events: Array
    residual_max: Array  # J, worst |ledger residual|
    failure_time: Array  # s, first failure (-1: none)
    failure: Array  # int32 Result code of the first failure
    tip_time: Array  # s, tip-over (-1: none)
    n_steps: Array  # int32

    @classmethod
    def start(cls, peaks0: dict, n_events: int = N_EVENTS) -> Track:
        """Before the first step; ``n_events``: the log's capacity (``Solver.event_log``)."""
        return cls(jax.tree.map(lambda x: jnp.full_like(x, -jnp.inf), peaks0),
                   jnp.full((n_events + 1 if n_events else 0,), jnp.nan),
                   jnp.zeros((), jnp.int32), jnp.zeros(()), -jnp.ones(()),
                   jnp.zeros((), jnp.int32), -jnp.ones(()), jnp.zeros((), jnp.int32))

    def events(self) -> Array:
        """The contact on/off times, (Solver.event_log,) s, NaN past the changes logged."""
        capacity = max(self.event_times.shape[-1] - 1, 0)
        return jnp.where(jnp.arange(capacity, dtype=jnp.int32) < self.n_events[..., None],
                         self.event_times[..., :capacity], jnp.nan)

    def peaks_with(self, model: AbstractModel, ev: Evaluation) -> dict:
        """The running maxima with the values of one evaluated state ``ev``; an upright
        landing's only (after a tip-over the peaks stop, see ``update``)."""
        values = model.peak_values(ev.record, ev.accel)
        upright = self.tip_time < 0.0
        return {k: jnp.where(upright, fmax(values[k], p), p) for k, p in self.peaks.items()}

    def update(self, model: AbstractModel, s, ev: Evaluation, e0, e_scale,
               check: bool = True, count: bool = True) -> Track:
        """With one evaluated state ``s``; ``check``: also the ledger and the failure checks
        (static); ``count``: also the step count (static; off where the driver adds a whole
        scan's steps at once, so the count is not one more value carried and rewritten on
        every step)."""
        # After a tip-over the body (which has no ground contact of its own) is not a landing
        # any more: peaks, the ledger and failure checks stop there; the tip itself counts.
        upright = self.tip_time < 0.0
        peaks = self.peaks_with(model, ev)
        contact = model.contact_flag(ev.record)
        touched = (self.n_events > 0) | contact  # a foot has been on the ground
        tip_t = jnp.where(upright & touched & model.tipping(ev.record), s.t, self.tip_time)
        # contact at the last step: the changes start out of contact, so their count's parity
        changed = contact != ((self.n_events & 1) == 1)
        ev_t = self.event_times
        if ev_t.shape[0]:
            ev_t = _log_write(ev_t, jnp.minimum(self.n_events, ev_t.shape[0] - 1), s.t, changed)
        track = eqx.tree_at(
            lambda x: (x.peaks, x.event_times, x.n_events, x.tip_time, x.n_steps), self,
            (peaks, ev_t, self.n_events + changed.astype(jnp.int32), tip_t,
             self.n_steps + 1 if count else self.n_steps))
        if not check:
            return track
        residual = ev.ledger() + jnp.sum(s.diss_rate) - e0
        res_max = jnp.where(upright, fmax(jnp.abs(residual), self.residual_max),
                            self.residual_max)
        # every component finite: x * 0 is 0 for a finite x and NaN otherwise, so one sum
        # over the components (one reduction, not one per leaf and a stack) is finite iff all are
        state_ok = jnp.isfinite(sum(jnp.sum(x * 0.0) for x in jax.tree.leaves((s.q, s.v))))
        # Judged on the new worst residual, not on this step's: before the first failure of an
        # upright landing the old worst is within the tolerance (else it would have failed), so
        # the two tests agree, NaN included; and the failure time and code then read the worst
        # residual's output instead of each evaluating the ledger once more (XLA fuses a shared
        # producer into every consumer that is not already materialised).
        bad = ~state_ok | ~(res_max <= ENERGY_TOLERANCE * e_scale)
        first = bad & upright & (self.failure_time < 0.0)
        return eqx.tree_at(
            lambda x: (x.residual_max, x.failure_time, x.failure), track,
            (res_max, jnp.where(first, s.t, self.failure_time),
             jnp.where(first, jnp.where(state_ok, int(Result.LEDGER), int(Result.NONFINITE)),
                       self.failure)))


@custom_batching.custom_vmap
def _log_write_raw(log, idx, t, changed):
    # one landing: a plain store, whether or not the contact changed (the slot at n_events
    # holds no change until it does)
    return log.at[idx].set(t)


@_log_write_raw.def_vmap
def _log_write_batched(axis_size, in_batched, log, idx, t, changed):
    # A one-hot select: under vmap, .at[idx].set with a per-landing index is a scatter, and
    # XLA:CPU compiles a while loop that holds a scatter kernel by kernel instead of into one
    # native kernel (the batch then pays one dispatch per fused kernel and step). It selects
    # only where the contact changed: a select on every step costs a batched 3-D step more
    # than the condition does.
    log, idx, t, changed = (x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
                            for x, b in zip((log, idx, t, changed), in_batched))
    hit = (jnp.arange(log.shape[-1], dtype=idx.dtype)[None, :] == idx[:, None]) & changed[:, None]
    return jnp.where(hit, t[:, None], log), True


def per_landing(tree, ref):
    """``tree`` unchanged; under ``vmap``, each leaf batched where any leaf of ``ref`` is. A
    scan's carry that starts unbatched but comes out of the step batched makes JAX trace the
    step's batching once more per such round; a time loop's carry that starts as batched as
    the step leaves it is batched in one (a Monte Carlo chunk traces in about 0.8 of the time).
    A select between a leaf and itself on a flag that depends on every leaf of ``ref``: the
    same values and derivatives (XLA folds it away), batched wherever the flag is."""
    flag = functools.reduce(jnp.logical_or, [jnp.any(x != x) for x in jax.tree.leaves(ref)],
                            jnp.zeros((), bool))
    return jax.tree.map(lambda x: jnp.where(flag, x, x), tree)


def _log_write(log, idx, t, changed):
    """``log`` with ``t`` at ``idx`` (batched: where ``changed``); the same entries below the
    change count batched or not. The log carries no derivatives."""
    return _log_write_raw(jax.lax.stop_gradient(log), idx, jax.lax.stop_gradient(t), changed)


def advance(s_m, s, q1, v1, dt, dissipated):
    """The next state: memories from the evaluation ``s_m``, time, positions, velocities and the
    rate channels advanced."""
    return eqx.tree_at(lambda x: (x.t, x.q, x.v, x.diss_rate), s_m,
                       (s.t + dt, q1, v1, s.diss_rate + dissipated))


def kick(v, acc, h):
    return jax.tree.map(lambda x, a: x + h * a, v, acc)


def record(model: AbstractModel, s, ev: Evaluation, e0) -> dict:
    """The saved outputs at state ``s`` from its evaluation."""
    out = dict(time_s=s.t, **ev.record, **model.accel_record(ev.accel))
    for i, name in enumerate(model.RATE_CHANNELS):
        out[name] = s.diss_rate[i]
    out["energy_residual_J"] = ev.ledger() + jnp.sum(s.diss_rate) - e0
    return out


def unfinished(record: dict) -> Array:
    """The landing is still in an impact at the state of ``record`` (a model's outputs): some
    leg on the ground is compressing at its largest stroke faster than ``UNFINISHED_RATE_MPS``,
    so its max stroke and the peaks can still grow."""
    pressing = ((record["normal_force_N"] > 0.0) & (record["stroke_m"] >= record["stroke_max_m"])
                & (record["buffer_velocity_mps"] > UNFINISHED_RATE_MPS))
    return jnp.any(pressing)


def summary(model: AbstractModel, s_end, track: Track, st: Setup, scene) -> dict:
    """The landing's scalars: peaks, memories, the event log, ledger closure and the result
    (``UNFINISHED`` where an upright landing is still in an impact at its end, or still has
    the energy to tip over)."""
    ev_end = model.evaluate(st.vehicle, s_end, scene, st.derived)
    dissipated = sum(ev_end.dissipated.values()) + jnp.sum(s_end.diss_rate)
    failed = track.failure_time >= 0.0
    cut = ((unfinished(ev_end.record) | model.could_still_tip(st.vehicle, ev_end))
           & (track.tip_time < 0.0))
    result = jnp.where(failed, track.failure,
                       jnp.where(track.n_events > 0,
                                 jnp.where(cut, int(Result.UNFINISHED), int(Result.SUCCESSFUL)),
                                 int(Result.NO_TOUCHDOWN)))
    peaks = track.peaks_with(model, ev_end)
    final = model.final_summary(s_end, ev_end.record)
    if STROKE_PEAK in peaks:  # up to a tip-over (the memory itself for an upright landing)
        final["max_stroke_m"] = peaks.pop(STROKE_PEAK)
    return dict(
        # the end state is a step's state too: its values join the peaks (a landing cut off
        # while compressing peaks there), as its largest stroke does in ``final_summary``
        **peaks,
        **final,
        event_times_s=track.events(),
        n_contact_changes=track.n_events,
        energy_initial_J=st.energy0,
        energy_scale_J=st.energy_scale,
        energy_dissipated_J=dissipated,
        energy_closure_max_J=track.residual_max,
        # the ledger error judged by simulate and Monte Carlo: relative to the energy
        # dissipated, or to a tenth of the energy scale when little is dissipated (free fall)
        ledger_error_rel=track.residual_max / jnp.maximum(dissipated, 0.1 * st.energy_scale),
        failed=failed,
        failure_time_s=track.failure_time,
        tipped=track.tip_time >= 0.0,
        tip_over_time_s=track.tip_time,
        t_end_s=s_end.t,
        n_steps=track.n_steps,
        solver_ok=jnp.ones((), bool),
        n_rejected_steps=jnp.zeros((), jnp.int32),
        result=result.astype(jnp.int32),
    )


def run_fixed(integrator, model: AbstractModel, vehicle, scene, solver):
    """The fixed-step driver: ``integrator.step_carried`` (a step, and what the method carries
    to the next one) in a scan over the steps of one save interval, inside a scan over the
    save points.

    The outputs at a saved state carry the forces as the next step applies them (with the
    method's implicit-damping ``record_kick``). Evaluating the saved state once more is cheaper
    than taking the block's first step (whose evaluation it repeats) out of the inner scan:
    that restructuring measured 1.3-1.7x slower on XLA:CPU.
    """
    st = setup(model, vehicle, scene, solver)
    veh, derived, dt = st.vehicle, st.derived, solver.dt

    def body(carry, _, check=True):
        s, track, carried = carry
        s1, (s_at, ev), carried = integrator.step_carried(model, veh, s, scene, derived, dt,
                                                          carried)
        return (s1, track.update(model, s_at, ev, st.energy0, st.energy_scale, check, False),
                carried), None

    def steps(carry, n):
        s, track, carried = run_steps(body, carry, n, solver.ledger_every)
        return s, eqx.tree_at(lambda t: t.n_steps, track, track.n_steps + n), carried

    kick_save = integrator.record_kick(dt)

    def save_point(s):
        return record(model, s, model.evaluate(veh, s, scene, derived, kick_save), st.energy0)

    def save_block(carry, _):
        out = save_point(carry[0]) if solver.trajectory else {}
        return steps(carry, solver.save_every), out

    # what the step makes per-landing starts so (the time and the step count are the batch's)
    track0 = Track.start(st.peaks0, solver.event_log)
    s0, track = per_landing((st.state0, track0), (veh, scene))
    carry0 = (eqx.tree_at(lambda s: s.t, s0, st.state0.t),
              eqx.tree_at(lambda t: t.n_steps, track, track0.n_steps),
              integrator.start(st.ev0))
    if solver.early_stop:
        traj = (jax.tree.map(lambda x: x[None], save_point(st.state0)) if solver.trajectory
                else {})
        return traj, jax.tree.map(lambda x: forward_only(
            x, "solver.early_stop", True, "has no reverse-mode derivative (jax.grad, "
            "jax.vjp): its while loop differentiates forward only (jax.jacfwd, jax.jvp); for "
            "jax.grad run without early_stop"),
            _run_until_settled(model, st, scene, solver, steps, carry0))
    (s_end, track, _), traj = jax.lax.scan(save_block, carry0,
                                        jnp.arange(solver.n_saves, dtype=jnp.float64))
    return traj, summary(model, s_end, track, st, scene)


def run_steps(body, carry, n: int, every: int):
    """``n`` steps of ``body(carry, _, check)`` in a scan, the ledger and failure checks on
    every ``every``-th step (the last of each block of ``every``; a remainder checks each)."""
    blocks, rest = divmod(n, every)
    if rest:
        carry, _ = jax.lax.scan(body, carry, None, length=rest, unroll=UNROLL)
    if every == 1:
        carry, _ = jax.lax.scan(body, carry, None, length=blocks, unroll=UNROLL)
    elif blocks:
        def block(c, _):
            c, _ = jax.lax.scan(lambda c, x: body(c, x, False), c, None, length=every - 1,
                                unroll=UNROLL)
            return body(c, None)

        carry, _ = jax.lax.scan(block, carry, None, length=blocks)
    return carry


def _run_until_settled(model, st: Setup, scene, solver, steps, carry0) -> dict:
    """The summary of a run without a trajectory (save_dt = t_end) stopped once the landing
    has settled (``_settle``): the steps run in blocks of ``check_steps``, in a ``while_loop``
    that ends at t_end or after the first block at whose end the landing is settled. Under
    ``vmap`` the batch runs until its last member has settled, the settled ones held still.
    The summary gains ``settled_time_s`` (NaN: ran to t_end unsettled); ``t_end_s`` is the time
    reached. A ``while_loop`` has no reverse-mode derivative: ``grad`` needs early_stop off."""
    block = check_steps(solver.dt)
    n_blocks, first = divmod(solver.n_steps, block)
    carry = carry0
    if first:  # the odd steps first: a landing does not settle that early
        carry = steps(carry, first)
    m_diag = mass_diagonal(model, st.vehicle, st.state0, scene, st.derived)

    def cond(c):
        return (c[1] < n_blocks) & ~c[2]

    def step_block(c):
        carry, k, _ = c
        carry = steps(carry, block)
        s, track = carry[:2]
        done = settled(model, st.vehicle, st.derived, scene, s, track.peaks,
                       track.n_events > 0, track.tip_time < 0.0, m_diag)
        return carry, k + 1, done

    (s_end, track, _), _, done = jax.lax.while_loop(
        cond, step_block, (carry, jnp.zeros((), jnp.int32), jnp.zeros((), bool)))
    out = summary(model, s_end, track, st, scene)
    out["settled_time_s"] = jnp.where(done, s_end.t, jnp.nan)
    return out
