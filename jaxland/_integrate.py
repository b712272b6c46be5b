"""Fixed-step integration in ``jax.lax.scan`` with output decimation, running peaks, a contact
event log, the energy ledger and numerical-failure detection.

Scheme: symplectic (semi-implicit) Euler. At each step the model evaluates its forces at
(q_n, v_n), which also advances the constitutive memories (largest crush, deepest pit, stick
point) by return maps; then v_{n+1} = v_n + dt M^-1 f, q_{n+1} = q_n + dt v_{n+1}. It is first
order, explicit, and its stability limit is set by the stiffest spring and the strut damping on
the 1 kg foot (``stable_step``).

A model is any namespace with ``mass``, ``initial_state``, ``evaluate``, ``accel_record``,
``peak_values``, ``contact_flag`` and ``RATE_CHANNELS`` (see ``jaxland._quarter``).
"""

from __future__ import annotations

import math

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
                    isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise ConfigError(f"solver.{name}", val, "must be a finite number > 0 s")
        return self

    def validate(self) -> Solver:
        """All settings, and how they relate."""
        self.validate_values()
        if self.save_dt < self.dt:
            raise ConfigError("solver.save_dt", self.save_dt, f"must be >= dt = {self.dt} s")
        if self.t_end / self.dt > 5e8:
            raise ConfigError("solver.dt", self.dt, "t_end/dt must be <= 5e8 steps")
        return self


def stable_step(vehicle: Vehicle):
    """Estimated stability limit of explicit symplectic Euler on the foot [s].

    The foot (mass m2) is held by the honeycomb's stiffest elastic stage, the auxiliary strut, the
    ground in restitution (k / (1 - gamma)) and the tangential spring at once: omega^2 = sum k / m2.
    The strut damping D_b F_bh acts on it as a viscous coefficient c = D_b F2 / m2 at the second
    plateau. For x'' = -omega^2 x - c x' symplectic Euler is stable while
    dt^2 omega^2 + 2 dt c <= 4, i.e. dt <= (sqrt(c^2 + 4 omega^2) - c) / omega^2
    (= 2/omega without damping, 2/c without stiffness).
    """
    hc, leg, gr = vehicle.honeycomb, vehicle.leg, vehicle.ground
    k_sum = (jnp.maximum(hc.k_b1, hc.k_b3) + leg.k_a + gr.k / (1.0 - gr.gamma) + gr.k_tan)
    w2 = k_sum / vehicle.m_foot
    c = leg.D_b * hc.F2 / vehicle.m_foot
    return (jnp.sqrt(c**2 + 4.0 * w2) - c) / w2


def energy_scale(vehicle: Vehicle, scene: Scene):
    """Energy the landing has to absorb, generously bounded [J]: the scale of ledger checks."""
    m = vehicle.m_body + vehicle.n_legs * vehicle.m_foot
    height = scene.drop_height + 3.0 * vehicle.honeycomb.x_L4
    return m * (0.5 * scene.sink_speed**2 + vehicle.g * height)


def integrate(model, vehicle: Vehicle, scene: Scene, solver: Solver):
    """Run one landing. Pure and jittable; vmap over ``scene`` or ``vehicle`` leaves.

    Returns ``(trajectory, summary)``: ``trajectory`` a dict of (n_saves,) arrays named with
    units (sampled every ``solver.save_dt``), ``summary`` a dict of scalars computed at full step
    resolution (peaks, memories, event log, ledger closure, failure flag).
    """
    dt = solver.dt
    m = model.mass(vehicle)
    s0 = model.initial_state(vehicle, scene)
    _, _, rec0, _, en0 = model.evaluate(vehicle, s0)
    e0 = sum(en0.values()) + jnp.sum(s0.diss_rate)
    e_scale = energy_scale(vehicle, scene)
    peaks0 = jax.tree.map(lambda x: jnp.full_like(x, -jnp.inf), model.peak_values(rec0, m))

    def step(carry, _):
        s, peaks, ev_t, ev_n, prev_c, res_max, fail_t = carry
        f, s_m, rec, power, energy = model.evaluate(vehicle, s)
        acc = f / m
        residual = sum(energy.values()) + jnp.sum(s.diss_rate) - e0
        peaks = jax.tree.map(jnp.maximum, peaks, model.peak_values(rec, acc))
        contact = model.contact_flag(rec)
        changed = contact != prev_c
        idx = jnp.minimum(ev_n, N_EVENTS - 1)
        ev_t = ev_t.at[idx].set(jnp.where(changed & (ev_n < N_EVENTS), s.t, ev_t[idx]))
        ev_n = ev_n + changed.astype(ev_n.dtype)
        res_max = jnp.maximum(res_max, jnp.abs(residual))
        state_ok = jnp.all(jnp.isfinite(s.q)) & jnp.all(jnp.isfinite(s.v))
        bad = ~state_ok | ~(jnp.abs(residual) <= ENERGY_TOLERANCE * e_scale)
        fail_t = jnp.where(bad & (fail_t < 0.0), s.t, fail_t)
        v1 = s.v + dt * acc
        q1 = s.q + dt * v1
        s1 = eqx.tree_at(
            lambda x: (x.t, x.q, x.v, x.diss_rate), s_m,
            (s.t + dt, q1, v1, s.diss_rate + dt * power),
        )
        return (s1, peaks, ev_t, ev_n, contact, res_max, fail_t), None

    def save_block(carry, _):
        s = carry[0]
        f, _, rec, _, energy = model.evaluate(vehicle, s)
        acc = f / m
        out = dict(time_s=s.t, **rec, **model.accel_record(acc))
        for i, name in enumerate(model.RATE_CHANNELS):
            out[name] = s.diss_rate[i]
        out["energy_residual_J"] = sum(energy.values()) + jnp.sum(s.diss_rate) - e0
        carry, _ = jax.lax.scan(step, carry, None, length=solver.save_every, unroll=UNROLL)
        return carry, out

    carry0 = (
        s0, peaks0, jnp.full((N_EVENTS,), jnp.nan), jnp.zeros((), jnp.int32),
        jnp.zeros((), bool), jnp.zeros(()), -jnp.ones(()),
    )
    carry, traj = jax.lax.scan(save_block, carry0, None, length=solver.n_saves)
    s_end, peaks, ev_t, ev_n, _, res_max, fail_t = carry
    _, _, rec_end, _, en_end = model.evaluate(vehicle, s_end)
    dissipated = sum(v for k, v in en_end.items() if k.startswith("diss_"))
    dissipated = dissipated + jnp.sum(s_end.diss_rate)
    summary = dict(
        **peaks,
        max_stroke_m=s_end.x_max,
        final_stroke_m=rec_end["stroke_m"],
        final_plastic_set_m=rec_end["plastic_set_m"],
        final_pit_depth_m=rec_end["pit_depth_m"],
        slip_distance_m=s_end.slip_distance,
        event_times_s=ev_t,
        n_contact_changes=ev_n,
        energy_initial_J=e0,
        energy_dissipated_J=dissipated,
        energy_closure_max_J=res_max,
        failed=fail_t >= 0.0,
        failure_time_s=fail_t,
        t_end_s=s_end.t,
    )
    return traj, summary
