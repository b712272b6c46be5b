"""Fixed-step integration in ``jax.lax.scan`` with output decimation, running peaks, a contact
event log, the energy ledger and numerical-failure detection.

Scheme: symplectic (semi-implicit) Euler. At each step the model evaluates its forces at
(q_n, v_n), which also advances the constitutive memories (largest crush, deepest pit, stick
point) by return maps; then v_{n+1} = v_n + dt M^-1 f, q_{n+1} = q_n + dt v_{n+1}. It is first
order, explicit, and its stability limit is set by the stiffest spring and the strut damping on
the 1 kg foot (``stable_step``).

A model is any namespace with ``initial_state``, ``prepare`` (parameter-derived numbers,
computed once before the loop), ``evaluate`` (generalised accelerations at a state, with the
memories advanced), ``drift`` (positions from the new velocities: plain q + dt v, or a rotation
update for an attitude), ``energy_scale``, ``apply_scene``, ``accel_record``, ``peak_values``,
``contact_flag``, ``tipping``, ``final_summary``, ``RATE_CHANNELS`` and ``COLUMNS`` (see
``jaxland._quarter`` and ``jaxland._vehicle3d``).
"""

from __future__ import annotations

import math
import numbers

import equinox as eqx
import jax
import jax.numpy as jnp

from ._errors import ConfigError
from ._params import Vehicle
from ._scene import Scene

N_EVENTS = 256  # capacity of the contact on/off log (later transitions are counted, not stored)
UNROLL = 1  # inner-loop unroll factor (unrolling made the fused step slower on CPU)
ENERGY_TOLERANCE = 0.1  # |ledger residual| above this fraction of the energy scale = failure


class Solver(eqx.Module):
    """Fixed-step settings (static: they set the loop lengths, so they are compile-time)."""

    dt: float = eqx.field(static=True, default=1e-5)  # s, integration step
    t_end: float = eqx.field(static=True, default=1.2)  # s, simulated duration
    save_dt: float = eqx.field(static=True, default=1e-4)  # s, output sample interval

    @property
    def save_every(self) -> int:
        return max(1, int(round(self.save_dt / self.dt)))

    @property
    def n_saves(self) -> int:
        return int(math.ceil(self.t_end / (self.dt * self.save_every)))

    @property
    def n_steps(self) -> int:
        return self.n_saves * self.save_every

    def validate_values(self) -> Solver:
        """Each setting on its own: a finite number > 0."""
        for name in ("dt", "t_end", "save_dt"):
            val = getattr(self, name)
            if isinstance(val, bool) or not (
                    isinstance(val, numbers.Real) and math.isfinite(val) and val > 0):
                raise ConfigError(f"solver.{name}", val, "must be a finite number > 0 s")
        return self

    def validate(self) -> Solver:
        """All settings, and how they relate."""
        self.validate_values()
        if self.save_dt < self.dt:
            raise ConfigError("solver.save_dt", self.save_dt, f"must be >= dt = {self.dt} s")
        if self.save_dt > self.t_end:
            raise ConfigError("solver.save_dt", self.save_dt, f"must be <= t_end = {self.t_end} s")
        ratio = self.save_dt / self.dt
        if abs(ratio - round(ratio)) > 1e-6 * ratio:
            raise ConfigError("solver.save_dt", self.save_dt,
                              f"must be a whole multiple of dt = {self.dt} s")
        if self.n_steps > 5e8:
            raise ConfigError("solver.dt", self.dt, "t_end/dt must be <= 5e8 steps")
        return self


def stable_step(vehicle: Vehicle, *, honeycomb_force=None, normal_force=None,
                bottomed: bool = False):
    """Estimated stability limit of explicit symplectic Euler [s].

    The lightest mass (the foot, m2) is held at once by the stiffest elastic element of the strut
    (k_b1, k_b3, the top-out stop, and k_bottom once the stack has bottomed out), the auxiliary
    struts, the ground in restitution (k / (1 - gamma)) and the tangential spring:
    omega^2 = sum k / m2. The strut damping D_b F_bh and the ground damping chi F_n act on it as a
    viscous coefficient c = (D_b F_bh + chi F_n) / m2; both grow with the force, so the limit
    depends on the landing. For x'' = -omega^2 x - c x' symplectic Euler is stable while
    dt^2 omega^2 + 2 dt c <= 4, i.e. dt <= (sqrt(c^2 + 4 omega^2) - c) / omega^2
    (= 2/omega without damping, 2/c without stiffness).

    Without forces given, the a-priori limit assumes the second plateau F2 for both; after a run,
    pass the peak honeycomb and normal forces it reached (and whether it bottomed out).
    """
    hc, leg, gr = vehicle.honeycomb, vehicle.leg, vehicle.ground
    k_el = jnp.maximum(jnp.maximum(hc.k_b1, hc.k_b3), leg.k_topout)
    if bottomed:
        k_el = jnp.maximum(k_el, hc.k_bottom)
    k_sum = k_el + leg.k_a + gr.k / (1.0 - gr.gamma) + gr.k_tan
    m = jnp.minimum(vehicle.m_foot, vehicle.m_quarter)
    f_hc = hc.F2 if honeycomb_force is None else jnp.maximum(hc.F2, honeycomb_force)
    f_n = hc.F2 if normal_force is None else jnp.maximum(hc.F2, normal_force)
    w2 = k_sum / m
    c = (leg.D_b * f_hc + gr.chi * f_n) / m
    return jnp.min((jnp.sqrt(c**2 + 4.0 * w2) - c) / w2)


def integrate(model, vehicle: Vehicle, scene: Scene, solver: Solver):
    """Run one landing. Pure and jittable; vmap over ``scene`` or ``vehicle`` leaves.

    Returns ``(trajectory, summary)``: ``trajectory`` a dict of (n_saves,) arrays named with
    units (sampled every ``solver.save_dt``), ``summary`` a dict of scalars computed at full step
    resolution (peaks, memories, event log, ledger closure, failure flag).
    """
    dt = solver.dt
    vehicle = model.apply_scene(vehicle, scene)  # scene-level friction and honeycomb scatter
    derived = model.prepare(vehicle, scene)  # parameter-derived numbers, once, outside the loop
    s0 = model.initial_state(vehicle, scene)
    acc0, _, rec0, _, en0 = model.evaluate(vehicle, s0, scene, derived)
    e0 = sum(en0.values()) + jnp.sum(s0.diss_rate)
    e_scale = model.energy_scale(vehicle, scene)
    peaks0 = jax.tree.map(lambda x: jnp.full_like(x, -jnp.inf), model.peak_values(rec0, acc0))

    def step(carry, _):
        s, peaks, ev_t, ev_n, prev_c, res_max, fail_t, tip_t = carry
        acc, s_m, rec, power, energy = model.evaluate(vehicle, s, scene, derived)
        residual = sum(energy.values()) + jnp.sum(s.diss_rate) - e0
        # After a tip-over the body (which has no ground contact of its own) is not a landing
        # any more: peaks, the ledger and failure checks stop there; the tip itself counts.
        upright = tip_t < 0.0
        peaks = jax.tree.map(lambda p, x: jnp.where(upright, jnp.maximum(p, x), p), peaks,
                             model.peak_values(rec, acc))
        touched = (ev_n > 0) | model.contact_flag(rec)  # a foot has been on the ground
        tip_t = jnp.where(upright & touched & model.tipping(rec), s.t, tip_t)
        contact = model.contact_flag(rec)
        changed = contact != prev_c
        idx = jnp.minimum(ev_n, N_EVENTS - 1)
        ev_t = ev_t.at[idx].set(jnp.where(changed & (ev_n < N_EVENTS), s.t, ev_t[idx]))
        ev_n = ev_n + changed.astype(ev_n.dtype)
        res_max = jnp.where(upright, jnp.maximum(res_max, jnp.abs(residual)), res_max)
        state_ok = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x))
                                      for x in jax.tree.leaves((s.q, s.v))]))
        bad = ~state_ok | ~(jnp.abs(residual) <= ENERGY_TOLERANCE * e_scale)
        fail_t = jnp.where(bad & upright & (fail_t < 0.0), s.t, fail_t)
        v1 = jax.tree.map(lambda v, a: v + dt * a, s.v, acc)
        q1 = model.drift(s.q, v1, dt)
        s1 = eqx.tree_at(
            lambda x: (x.t, x.q, x.v, x.diss_rate), s_m,
            (s.t + dt, q1, v1, s.diss_rate + dt * power),
        )
        return (s1, peaks, ev_t, ev_n, contact, res_max, fail_t, tip_t), None

    def save_block(carry, _):
        s = carry[0]
        acc, _, rec, _, energy = model.evaluate(vehicle, s, scene, derived)
        out = dict(time_s=s.t, **rec, **model.accel_record(acc))
        for i, name in enumerate(model.RATE_CHANNELS):
            out[name] = s.diss_rate[i]
        out["energy_residual_J"] = sum(energy.values()) + jnp.sum(s.diss_rate) - e0
        carry, _ = jax.lax.scan(step, carry, None, length=solver.save_every, unroll=UNROLL)
        return carry, out

    carry0 = (
        s0, peaks0, jnp.full((N_EVENTS,), jnp.nan), jnp.zeros((), jnp.int32),
        jnp.zeros((), bool), jnp.zeros(()), -jnp.ones(()), -jnp.ones(()),
    )
    carry, traj = jax.lax.scan(save_block, carry0, None, length=solver.n_saves)
    s_end, peaks, ev_t, ev_n, _, res_max, fail_t, tip_t = carry
    _, _, rec_end, _, en_end = model.evaluate(vehicle, s_end, scene, derived)
    dissipated = sum(v for k, v in en_end.items() if k.startswith("diss_"))
    dissipated = dissipated + jnp.sum(s_end.diss_rate)
    summary = dict(
        **peaks,
        **model.final_summary(s_end, rec_end),
        event_times_s=ev_t,
        n_contact_changes=ev_n,
        energy_initial_J=e0,
        energy_scale_J=e_scale,
        energy_dissipated_J=dissipated,
        energy_closure_max_J=res_max,
        # the ledger error judged by simulate and Monte Carlo: relative to the energy
        # dissipated, or to a tenth of the energy scale when little is dissipated (free fall)
        ledger_error_rel=res_max / jnp.maximum(dissipated, 0.1 * e_scale),
        failed=fail_t >= 0.0,
        failure_time_s=fail_t,
        tipped=tip_t >= 0.0,
        tip_over_time_s=tip_t,
        t_end_s=s_end.t,
    )
    return traj, summary
