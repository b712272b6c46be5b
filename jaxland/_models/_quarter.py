"""Quarter model of a symmetric vertical landing: the paper's experiment (docs/model.md).

A quarter of the body mass moves vertically; one planar inverted-triangle leg carries it; the
foot is a 2-DOF point mass in the leg plane. In a symmetric landing the horizontal loads of
opposite legs cancel on the body, so this is exact for the full vehicle.

Coordinates (world frame, ground at z = 0, r radial outward from the vehicle axis):
    q = (z_body, r_foot, z_foot)  [m],  v = dq/dt  [m/s].

Forces (paper Eqs 1-2): main strut F_strut along u = (foot - P)/|foot - P| (compression pushes
the foot away from P), auxiliary strut F_a along a = (foot - A)/|foot - A|, ground normal N and
tangential F_t on the foot, gravity on both. The body takes the vertical reactions.

State machine (paper Fig. 2) as masks, recorded per sample in ``phase``: 1 = air (no contact,
buffer unloaded), 2 = touchdown (contact and buffering), 3 = impact only, 4 = buffering only.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._laws import (
    aux_strut,
    honeycomb,
    normal_contact,
    safe_hypot,
    strut_force,
    tangential_contact,
)
from .._params import HoneycombCurve, Vehicle
from .._scene import Scene
from ._base import AbstractImpulseModel, AbstractODEModel, Evaluation, Smoothing

# Honeycomb force above which the state machine calls the buffer active [N]; round-off in free
# fall leaves forces of ~1e-6 N on an unloaded leg.
BUFFERING_THRESHOLD_N = 1e-3

# Dissipation channels integrated from their power (the others are closed forms of the memory).
RATE_CHANNELS = ("diss_struct_damping_J", "diss_ground_damping_J")

# Trajectory columns in CSV order (units in the names; phase and slip_indicator are codes).
COLUMNS = (
    "time_s", "body_z_m", "body_vz_mps", "body_az_mps2",
    "foot_r_m", "foot_z_m", "foot_vr_mps", "foot_vz_mps", "foot_ar_mps2", "foot_az_mps2",
    "stroke_m", "stroke_max_m", "plastic_set_m", "buffer_velocity_mps",
    "honeycomb_force_N", "damping_force_N", "strut_force_N", "aux_force_N",
    "normal_force_N", "tangential_force_N", "pit_depth_m", "slip_indicator", "slip_distance_m",
    "phase", "kinetic_J", "potential_J", "elastic_honeycomb_J", "elastic_aux_J",
    "elastic_ground_J", "elastic_tangential_J", "diss_crush_J", "diss_ground_plastic_J",
    "diss_slip_J", *RATE_CHANNELS, "energy_residual_J",
)


class QuarterState(eqx.Module):
    """Integrator state of the quarter model (all SI)."""

    t: jnp.ndarray  # s
    q: jnp.ndarray  # (3,) m: z_body, r_foot, z_foot
    v: jnp.ndarray  # (3,) m/s
    x_max: jnp.ndarray  # m, largest buffer stroke reached (honeycomb memory)
    d_max: jnp.ndarray  # m, deepest foot penetration reached (ground memory)
    anchor: jnp.ndarray  # m, tangential stick point on the ground (radial; lateral is 0)
    diss_rate: jnp.ndarray  # (2,) J, accumulated RATE_CHANNELS
    diss_slip: jnp.ndarray  # J, accumulated friction slip dissipation
    slip_distance: jnp.ndarray  # m, accumulated slip path of the foot
    # N, tangential spring force after the last return map: the slip energy's trapezoid when
    # the model is second order (``AbstractModel``); None in the ODE form
    t_force: jnp.ndarray | None = None


class QuarterDerived(eqx.Module):
    """Parameter-derived numbers of the quarter model's step."""

    curve: HoneycombCurve  # the honeycomb law with its breakpoints evaluated
    k_r: jnp.ndarray  # N/m, ground restitution stiffness k / (1 - gamma)
    L_a0_pair: jnp.ndarray  # m, rest length of each auxiliary strut
    m_quarter: jnp.ndarray  # kg, body mass per leg
    smoothing: Smoothing = Smoothing()


class QuarterModel(AbstractImpulseModel, AbstractODEModel):
    """The quarter model (module docstring). Stateless: parameters are the vehicle's."""

    name: ClassVar[str] = "quarter"
    COLUMNS: ClassVar[tuple[str, ...]] = COLUMNS
    RATE_CHANNELS: ClassVar[tuple[str, ...]] = RATE_CHANNELS

    def leg_mass(self, vehicle):
        return vehicle.m_quarter

    def plateau_scatter(self, plateau_scale):
        """One leg stands for all: the mean scale over the legs."""
        return jnp.mean(plateau_scale, axis=-1)

    def prepare(self, vehicle: Vehicle, scene: Scene,
                smoothing: Smoothing = Smoothing()) -> QuarterDerived:
        """Parameter-derived numbers the step reads, computed once outside the time loop (XLA
        does not hoist divisions, roots and trigonometry out of it: 5x slower with traced
        parameters)."""
        return QuarterDerived(curve=vehicle.honeycomb.curve(), k_r=vehicle.ground.k_r,
                              L_a0_pair=vehicle.leg.L_a0_pair, m_quarter=vehicle.m_quarter,
                              smoothing=smoothing)

    def energy_scale(self, vehicle: Vehicle, scene: Scene):
        """Energy the landing has to absorb, generously bounded [J]: the scale of ledger checks."""
        m = vehicle.m_quarter + vehicle.m_foot  # the quarter ledger's own masses
        # the body sinks about twice the stroke; 2.5 strokes bound it generously (the scale only
        # sets the ledger's tolerance)
        height = scene.drop_height + 2.5 * vehicle.honeycomb.x_L4
        return m * (0.5 * scene.sink_speed**2 + vehicle.g * height)

    def drift(self, q, v, dt):
        """Positions from the new velocities (symplectic Euler's second half)."""
        return q + dt * v

    def initial_state(self, vehicle: Vehicle, scene: Scene) -> QuarterState:
        """Leg at rest, feet ``scene.drop_height`` above the ground, falling at ``sink_speed``."""
        foot = vehicle.leg.foot_rest
        z_foot = scene.drop_height
        q = jnp.stack([z_foot - foot[1], foot[0], z_foot])
        v = -scene.sink_speed * jnp.array([1.0, 0.0, 1.0])
        zero = jnp.zeros(())
        return QuarterState(
            t=zero, q=q, v=v, x_max=zero, d_max=zero, anchor=foot[0],
            diss_rate=jnp.zeros(len(RATE_CHANNELS)), diss_slip=zero, slip_distance=zero,
            t_force=zero,
        )

    def evaluate(self, vehicle: Vehicle, s: QuarterState, scene: Scene | None = None,
                 derived: QuarterDerived | None = None, kick=None) -> Evaluation:
        """Accelerations at state ``s`` (the scene is not needed: level ground, no attitude).

        ``kick`` [s]: when given, the strut damping is implicit, evaluated at the stroke rate after
        a velocity kick of that length (``strut_force``); ``None`` is explicit.

        Returns the ``Evaluation``: accel (3,), the state with updated memories, the record of
        named scalar outputs (CSV columns, units in the names), the two dissipation powers and
        the ledger's stores and closed-form dissipation.
        """
        derived = self.prepare(vehicle, scene) if derived is None else derived
        leg, hc, gr = vehicle.leg, derived.curve, vehicle.ground
        sm, sn = derived.smoothing.length_m, derived.smoothing.force_N
        z_b, r_f, z_f = s.q[0], s.q[1], s.q[2]
        vz_b, vr_f, vz_f = s.v[0], s.v[1], s.v[2]
        # Written on scalar components throughout: XLA then fuses the step into few kernels.
        # Main strut: stroke, stroke rate, honeycomb with memory, structural damping, top-out.
        dr = r_f - leg.R
        dz = z_f - (z_b - leg.H1)
        length = safe_hypot(dr, dz)
        u_r, u_z = dr / length, dz / length
        x_b = leg.L_h0 - length
        v_b = -(u_r * vr_f + u_z * (vz_f - vz_b))
        hco = honeycomb(x_b, s.x_max, hc, sm)

        # Auxiliary struts: a pair with joints at A +/- h laterally; in a symmetric landing their
        # lateral components cancel and each carries half of k_a.
        dz_a = z_f - (z_b - leg.H1 - leg.H2)
        length_a = jnp.sqrt(dr * dr + dz_a * dz_a + leg.h * leg.h)
        a_r, a_z = dr / length_a, dz_a / length_a
        ax = aux_strut(length_a, derived.L_a0_pair, leg.k_a)

        # Ground: normal with pit memory, tangential stick/slip (3-D law, lateral axis unused here).
        nc = normal_contact(-z_f, -vz_f, s.d_max, gr, derived.k_r, sm)
        zero = jnp.zeros_like(r_f)
        second = self.second_order and s.t_force is not None
        tc = tangential_contact((r_f, zero), (s.anchor, zero), nc.force, gr, sm,
                                s.t_force if second else None)

        m_q, m_f, g = derived.m_quarter, vehicle.m_foot, vehicle.g
        if kick is None:
            st = strut_force(hco.force, x_b, v_b, leg.D_b, leg.k_topout, smooth_N=sn, smooth_m=sm)
        else:  # implicit damping: the stroke rate after the kick from the other foot forces
            other_u = (u_r * (ax.force * a_r + tc.force[0])
                       + u_z * (ax.force * a_z + nc.force - m_f * g))
            a = kick / m_f
            free = v_b - a * other_u
            if self.second_order:  # and from the body's kick, its forces with explicit damping:
                # held still, the body's ~4 g deceleration in the crush is an O(dt) error in
                # the damping's rate, which makes a second-order step first order
                st_ex = strut_force(hco.force, x_b, v_b, leg.D_b, leg.k_topout, smooth_N=sn,
                                    smooth_m=sm)
                a_body = (-(st_ex.force * u_z + ax.force * a_z) - m_q * g) / m_q
                free = free + kick * u_z * a_body
            st = strut_force(hco.force, x_b, v_b, leg.D_b, leg.k_topout, a, free, sn, sm)
        f_foot_r = st.force * u_r + ax.force * a_r + tc.force[0]
        f_foot_z = st.force * u_z + ax.force * a_z + nc.force - m_f * g
        f_body = -(st.force * u_z + ax.force * a_z) - m_q * g
        accel = jnp.stack([f_body / m_q, f_foot_r / m_f, f_foot_z / m_f])

        new = eqx.tree_at(
            lambda x: (x.x_max, x.d_max, x.anchor, x.diss_slip, x.slip_distance),
            s,
            (hco.x_max, nc.d_max, tc.anchor[0], s.diss_slip + tc.slip_energy,
             s.slip_distance + tc.slip),
        )
        if second:
            new = eqx.tree_at(lambda x: x.t_force, new, jnp.abs(tc.force[0]))

        contact = nc.force > 0.0
        buffering = hco.force > BUFFERING_THRESHOLD_N
        phase = jnp.where(contact, jnp.where(buffering, 2.0, 3.0), jnp.where(buffering, 4.0, 1.0))
        kinetic = self.kinetic_energy(vehicle, derived, s.v)
        potential = g * (m_q * z_b + m_f * z_f)
        stores = dict(
            kinetic_J=kinetic,
            potential_J=potential,
            elastic_honeycomb_J=hco.elastic_energy + st.topout_energy,
            elastic_aux_J=ax.elastic_energy,
            elastic_ground_J=nc.elastic_energy,
            elastic_tangential_J=tc.elastic_energy,
        )
        dissipated = dict(
            diss_crush_J=hco.crush_energy,
            diss_ground_plastic_J=nc.plastic_energy,
            diss_slip_J=new.diss_slip,
        )
        record = dict(
            body_z_m=z_b,
            body_vz_mps=vz_b,
            foot_r_m=r_f,
            foot_z_m=z_f,
            foot_vr_mps=vr_f,
            foot_vz_mps=vz_f,
            stroke_m=x_b,
            stroke_max_m=hco.x_max,
            plastic_set_m=hco.plastic_set,
            buffer_velocity_mps=v_b,
            honeycomb_force_N=hco.force,
            damping_force_N=st.damping_force,
            strut_force_N=st.force,
            aux_force_N=ax.force,
            normal_force_N=nc.force,
            tangential_force_N=tc.force[0],
            pit_depth_m=nc.pit_depth,
            slip_indicator=jnp.where(contact, jnp.where(tc.slipping, 1.0, 0.0), 0.5),
            slip_distance_m=new.slip_distance,
            phase=phase,
            **stores,
            **dissipated,
        )
        rate_power = jnp.stack([st.damping_power, nc.damping_power])
        return Evaluation(accel, new, record, rate_power, stores, dissipated)

    def kinetic_energy(self, vehicle: Vehicle, derived: QuarterDerived, v):
        """``AbstractModel.kinetic_energy``: the body's quarter share and the foot."""
        return 0.5 * (derived.m_quarter * v[0]**2 + vehicle.m_foot * (v[1]**2 + v[2]**2))

    def accel_record(self, acc):
        """Named acceleration outputs [m/s^2] from the generalised accelerations."""
        return dict(body_az_mps2=acc[0], foot_ar_mps2=acc[1], foot_az_mps2=acc[2])

    def peak_values(self, record, acc):
        """Quantities whose running maximum over all steps is kept (full step resolution)."""
        return dict(
            peak_normal_force_N=record["normal_force_N"],
            peak_tangential_force_N=jnp.abs(record["tangential_force_N"]),
            peak_strut_force_N=record["strut_force_N"],
            peak_honeycomb_force_N=record["honeycomb_force_N"],
            peak_aux_force_N=jnp.abs(record["aux_force_N"]),
            peak_buffer_velocity_mps=record["buffer_velocity_mps"],
            peak_body_accel_mps2=jnp.abs(acc[0]),
            peak_foot_accel_mps2=safe_hypot(acc[1], acc[2]),
            peak_foot_accel_normal_mps2=jnp.abs(acc[2]),
            peak_foot_accel_tangential_mps2=jnp.abs(acc[1]),
        )

    def contact_flag(self, record):
        return record["normal_force_N"] > 0.0

    def tipping(self, record):
        """A symmetric vertical drop cannot tip over."""
        return jnp.zeros((), bool)

    def final_summary(self, s: QuarterState, record) -> dict:
        """Model-specific end-of-landing outcomes."""
        return dict(
            max_stroke_m=record["stroke_max_m"],  # the memory with the end state's stroke
            final_stroke_m=record["stroke_m"],
            final_plastic_set_m=record["plastic_set_m"],
            final_pit_depth_m=record["pit_depth_m"],
            final_normal_force_N=record["normal_force_N"],
            slip_distance_m=s.slip_distance,
        )

    # ---- hooks of the variable-step integrators (quarter model only) ----

    def primary_force(self, record):
        """The force whose impulse is the independent variable of the paper's discrete-impulse
        method (paper 2.4) [N]: the ground normal force while the foot is in contact (states 2
        and 3), the honeycomb force while only the buffer is loaded (state 4), 0 in the air
        (state 1)."""
        f_n, f_h = record["normal_force_N"], record["honeycomb_force_N"]
        return jnp.where(f_n > 0.0, f_n, jnp.where(f_h > BUFFERING_THRESHOLD_N, f_h, 0.0))

    def impulse_step_force(self, record):
        """The force that sets the impulse method's step, dt = dI / F [N]: the primary force, or
        the honeycomb force if larger (a stability guard for the strut damping: the
        ``_impulse`` module's notes)."""
        return jnp.maximum(self.primary_force(record), record["honeycomb_force_N"])

    def ode_state(self, s: QuarterState):
        """The state as one flat vector for an ODE solver (see ``ode_rates``): q (3), v (3),
        x_max, d_max, anchor, RATE_CHANNELS (2), diss_slip, slip_distance."""
        mem = jnp.stack([s.x_max, s.d_max, s.anchor])
        return jnp.concatenate([s.q, s.v, mem, s.diss_rate, jnp.stack([s.diss_slip,
                                                                       s.slip_distance])])

    def from_ode(self, t, y) -> QuarterState:
        return QuarterState(t=t, q=y[0:3], v=y[3:6], x_max=y[6], d_max=y[7], anchor=y[8],
                            diss_rate=y[9:11], diss_slip=y[11], slip_distance=y[12])

    def ode_rates(self, vehicle: Vehicle, t, y, scene: Scene | None, derived: QuarterDerived):
        """The landing as a continuous ODE y' = f(t, y) for adaptive solvers (diffrax, scipy).

        The memories are written in rate form, so that an ODE solver carries them between its
        stages (the laws take max(x_max, x) etc. themselves, so forces are right even where a
        memory lags within a step):
          x_max' = max(v_b, 0) while the stroke is on the virgin curve (x_b >= x_max), else 0;
          d_max' = max(d_dot, 0) while the penetration is at its deepest (d >= d_max), else 0;
          anchor' = foot velocity off the ground; in contact, with the trial spring at its Coulomb
            limit k_tan |r - anchor| >= mu F_n, the slip rate lambda = s v_r - mu dF_s/dt / k_tan
            (s the side of the foot from the anchor; dF_s/dt = k d_dot on virgin loading, k_r d_dot
            on the restitution line) moves the anchor, anchor' = s lambda, if
            lambda > 0 (this holds k_tan |r - anchor| = mu F_n; the rate of the (1 + chi d_dot)
            factor is left out); otherwise the foot sticks (the consistency condition of
            rigid-plastic slip, as in plasticity);
          the dissipation channels from their power; slip energy mu F_n |anchor'| while slipping.
        """
        s = self.from_ode(t, y)
        ev = self.evaluate(vehicle, s, scene, derived)
        acc, rec, power = ev.accel, ev.record, ev.power
        gr = vehicle.ground
        vr_f, vz_f = s.v[1], s.v[2]
        v_b = rec["buffer_velocity_mps"]
        dx_max = jnp.where(rec["stroke_m"] >= s.x_max, jnp.maximum(v_b, 0.0), 0.0)
        d, d_dot = -s.q[2], -vz_f
        dd_max = jnp.where(d >= s.d_max, jnp.maximum(d_dot, 0.0), 0.0)
        f_n = rec["normal_force_N"]
        contact = f_n > 0.0
        gap = s.q[1] - s.anchor
        side = jnp.sign(gap)
        at_limit = gr.k_tan * jnp.abs(gap) >= gr.mu * f_n
        k_now = jnp.where(d >= s.d_max, gr.k, derived.k_r)  # virgin loading, or restitution
        rate = side * vr_f - gr.mu * jnp.where(contact, k_now * d_dot, 0.0) / gr.k_tan
        slip_rate = jnp.where(contact & at_limit, jnp.maximum(rate, 0.0), 0.0)
        anchor_rate = jnp.where(contact, side * slip_rate, vr_f)
        mem = jnp.stack([dx_max, dd_max, anchor_rate])
        return jnp.concatenate([s.v, acc, mem, power,
                                jnp.stack([gr.mu * f_n * slip_rate, slip_rate])])
