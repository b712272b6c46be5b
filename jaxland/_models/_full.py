"""Full 3-D vehicle: a 6-DOF rigid body on n inverted-triangle legs, each foot a 3-D point mass.

Body: position p and velocity v of the centre of mass (world), attitude quaternion (w, x, y, z)
from body to world, angular velocity omega in the body frame, diagonal body inertia. Leg i lies in
the body plane at azimuth psi_i = 2 pi i / n: main strut from P_i = R e_r - H1 e_z to the foot,
carrying the honeycomb with structural damping along its axis; two auxiliary struts (k_a / 2
each) from A_i +/- h e_t, A_i = R e_r - (H1 + H2) e_z, to the foot, which hold it laterally (a
tripod). The feet meet the ground plane (through the origin, tilted by the scene's slope) through
the same laws as the quarter model, per foot in the local ground frame (normal + two tangential
axes). In a symmetric drop this model reduces exactly to the quarter model.

The attitude advances by the exact exponential map
of the body-frame rate, q <- q (x) exp(omega dt / 2), renormalised.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._laws import (
    aux_strut,
    honeycomb,
    normal_contact,
    safe_hypot,
    safe_sqrt,
    strut_force,
    tangential_contact,
)
from .._params import HoneycombCurve, Vehicle
from .._scene import Scene
from ._base import AbstractModel, Evaluation, Smoothing

RATE_CHANNELS = ("diss_struct_damping_J", "diss_ground_damping_J")
MARGIN_SOFTNESS_M = 0.01  # soft-min width over the support-polygon edges [m]
# ``could_still_tip`` takes this multiple of the available energy: its bound neglects the
# slope's tilt of the polygon and a foot in the air (the body then turns about one foot)
TIP_ENERGY_SAFETY = 2.0

PER_LEG = (
    "stroke_m", "stroke_max_m", "buffer_velocity_mps", "honeycomb_force_N", "strut_force_N",
    "aux_force_N", "normal_force_N", "tangential_force_N", "pit_depth_m", "slip_indicator",
    "foot_x_m", "foot_y_m", "foot_z_m",
)
COLUMNS = (
    "time_s", "body_x_m", "body_y_m", "body_z_m", "body_vx_mps", "body_vy_mps", "body_vz_mps",
    "body_ax_mps2", "body_ay_mps2", "body_az_mps2", "roll_deg", "pitch_deg", "yaw_deg",
    "tilt_deg", "omega_x_radps", "omega_y_radps", "omega_z_radps", "stability_margin_m",
    "angular_momentum_x_Nms", "angular_momentum_y_Nms", "angular_momentum_z_Nms",
    *PER_LEG, "kinetic_J", "potential_J", "elastic_honeycomb_J", "elastic_aux_J",
    "elastic_ground_J", "elastic_tangential_J", "diss_crush_J", "diss_ground_plastic_J",
    "diss_slip_J", *RATE_CHANNELS, "energy_residual_J",
)


class Vehicle3DState(eqx.Module):
    t: jnp.ndarray  # s
    q: tuple  # (p (3,) m, quaternion (4,), feet (n, 3) m), world frame
    v: tuple  # (v (3,) m/s, omega_body (3,) rad/s, feet velocities (n, 3) m/s)
    x_max: jnp.ndarray  # (n,) m, largest stroke per leg
    d_max: jnp.ndarray  # (n,) m, deepest penetration per foot
    anchor: tuple  # ((n,), (n,)) m, stick points in the ground's tangent coordinates
    diss_rate: jnp.ndarray  # (2,) J
    diss_slip: jnp.ndarray  # J
    slip_distance: jnp.ndarray  # (n,) m
    # (n,) N, tangential spring force after the last return map: the slip energy's trapezoid
    # when the model is second order (``AbstractModel``)
    t_force: jnp.ndarray | None = None


# ------------------------------------------------------------------------------- rotations

def quat_mul(a, b):
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return jnp.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def quat_to_matrix(q):
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
    ])


def quat_from_euler(roll, pitch, yaw):
    """Yaw-pitch-roll (z-y'-x'') to a body-to-world quaternion."""
    def axis_quat(angle, i):
        half = 0.5 * angle
        v = [jnp.zeros_like(half)] * 3
        v[i] = jnp.sin(half)
        return jnp.stack([jnp.cos(half), *v])

    return quat_mul(quat_mul(axis_quat(yaw, 2), axis_quat(pitch, 1)), axis_quat(roll, 0))


def euler_from_matrix(Rm):
    """(roll, pitch, yaw) [rad] of a body-to-world rotation matrix (z-y'-x'')."""
    pitch = jnp.arcsin(jnp.clip(-Rm[2, 0], -1.0, 1.0))
    roll = jnp.arctan2(Rm[2, 1], Rm[2, 2])
    yaw = jnp.arctan2(Rm[1, 0], Rm[0, 0])
    return roll, pitch, yaw


def _quat_exp(half_angle_vec):
    """exp of a pure quaternion (0, h): (cos|h|, sin|h| h/|h|), smooth at h = 0.

    cos x and sin(x)/x are their Taylor series in x^2 through the x^16 term, so a step takes no
    square root, sine, cosine or division (a batched 3-D step ran 0.9 times as long as with
    them). For |h| <= 1, a rotation of 2 rad in one step, the first term left out is below
    3e-16 of the sum: one rounding. A landing's rates stay far below that (|h| = 1 is a body
    rate of 2 / dt, 5e4 rad/s at dt = 4e-5 s)."""
    x2 = jnp.sum(half_angle_vec * half_angle_vec)
    cos = _series(x2, _COS)
    sinc = _series(x2, _SINC)
    return jnp.concatenate([cos[None], sinc * half_angle_vec])


def _series(x2, coefs):
    """sum_k coefs[k] x2^k, by Horner's rule."""
    acc = coefs[-1]
    for c in coefs[-2::-1]:
        acc = c + x2 * acc
    return acc


_COS = tuple((-1.0) ** k / math.factorial(2 * k) for k in range(9))
_SINC = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(9))


# ------------------------------------------------------------------------------- products
# The step's small products are written as component arithmetic: XLA:CPU runs a `dot` as a
# library call, which keeps a batched time loop from compiling into one kernel (one dispatch
# per kernel and step instead; docs/performance.md). The sums run in the order a dot takes.

def _legsum(x):
    """An (n,) array's sum over the legs as a chain of adds, not a reduction. The body's force
    and torque sums over (n, 3) arrays stay reductions: written as adds, a Monte Carlo chunk
    whose vehicle is a compile-time constant took XLA:CPU 60 s to compile instead of 3.5 s."""
    acc = x[0]
    for i in range(1, x.shape[0]):
        acc = acc + x[i]
    return acc


def _dot(a, b):
    """a . b over the last axis (3 components), broadcasting the leading axes."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _mv(Rm, x):
    """Rm @ x for a (3, 3) matrix and a (3,) vector."""
    return jnp.stack([_dot(Rm[0], x), _dot(Rm[1], x), _dot(Rm[2], x)])


def _mtv(Rm, x):
    """Rm.T @ x for a (3, 3) matrix and a (3,) vector."""
    return jnp.stack([_dot(Rm[:, 0], x), _dot(Rm[:, 1], x), _dot(Rm[:, 2], x)])


def _rotate_rows(r, Rm):
    """r @ Rm.T: each row of an (n, 3) array rotated by Rm."""
    return jnp.stack([_dot(r, Rm[0][None, :]), _dot(r, Rm[1][None, :]),
                      _dot(r, Rm[2][None, :])], axis=-1)


# ------------------------------------------------------------------------------- geometry

def leg_geometry(vehicle: Vehicle):
    """Body-frame points of every leg: P, A+, A-, foot at rest, each (n, 3) [m]."""
    leg, n = vehicle.leg, vehicle.n_legs
    psi = 2.0 * jnp.pi * jnp.arange(n, dtype=jnp.float64) / n
    e_r = jnp.stack([jnp.cos(psi), jnp.sin(psi), jnp.zeros(n)], axis=-1)
    e_t = jnp.stack([-jnp.sin(psi), jnp.cos(psi), jnp.zeros(n)], axis=-1)
    e_z = jnp.array([[0.0, 0.0, 1.0]])
    P = leg.R * e_r - leg.H1 * e_z
    A = leg.R * e_r - (leg.H1 + leg.H2) * e_z
    foot = P + leg.L_h0 * (jnp.cos(leg.theta_b) * e_r - jnp.sin(leg.theta_b) * e_z)
    return P, A + leg.h * e_t, A - leg.h * e_t, foot


def ground_frame(scene: Scene):
    """Ground normal n and tangents t1 (downhill), t2 = n x t1, each (3,)."""
    s, phi = scene.slope, scene.slope_direction
    n = jnp.stack([jnp.sin(s) * jnp.cos(phi), jnp.sin(s) * jnp.sin(phi), jnp.cos(s)])
    t1 = jnp.stack([jnp.cos(s) * jnp.cos(phi), jnp.cos(s) * jnp.sin(phi), -jnp.sin(s)])
    t2 = jnp.stack([-jnp.sin(phi), jnp.cos(phi), jnp.zeros_like(phi)])
    return n, t1, t2


def _norm_rows(d):
    """|d| of each row of an (n, 3) array: one square root, with a finite gradient at zero."""
    return safe_sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])


def _inertia(vehicle: Vehicle):
    return jnp.stack([vehicle.I_xx, vehicle.I_yy, vehicle.I_zz])


# ------------------------------------------------------------------------------- model API

def body_points(vehicle: Vehicle, scene: Scene):
    """Leg points (P, A+, A-, foot at rest) relative to the centre of mass, body frame (n, 3):
    the geometry of ``leg_geometry`` moved by the scene's centre-of-mass offset."""
    points = leg_geometry(vehicle)
    if scene.com_offset is None:
        return points
    return tuple(p - scene.com_offset[None, :] for p in points)


def stability_margin(com, feet, frame):
    """Signed distance [m] of the centre of mass, projected along gravity onto the ground plane,
    from the edges of the feet's polygon (legs in azimuth order), positive inside; a soft-min
    over edges (width MARGIN_SOFTNESS_M), so it is smooth for optimisation. ``frame`` is
    ``ground_frame(scene)``."""
    n_g, t1, t2 = frame
    # a point x projected along gravity onto the ground, x - (x . n_g / n_g_z) e_z, has the
    # in-plane coordinates x . p_i with p_i = t_i - n_g t_iz / n_g_z (fewer operations per step)
    p1, p2 = t1 - n_g * (t1[2] / n_g[2]), t2 - n_g * (t2[2] / n_g[2])
    cx, cy = _dot(com, p1), _dot(com, p2)
    n = feet.shape[-2]
    ax = [_dot(feet[..., i, :], p1) for i in range(n)]
    ay = [_dot(feet[..., i, :], p2) for i in range(n)]
    tau = MARGIN_SOFTNESS_M
    # the soft-min -tau log sum exp(-d_i / tau) over the edges, written leg by leg: as
    # (n,)-arrays with a roll and a logsumexp reduction, the margin cost a batched 3-D step
    # about twice as much
    a = []
    for i in range(n):
        ex, ey = ax[(i + 1) % n] - ax[i], ay[(i + 1) % n] - ay[i]
        a.append(-((ex * (cy - ay[i]) - ey * (cx - ax[i])) / safe_hypot(ex, ey)) / tau)
    a_max = a[0]
    for x in a[1:]:
        a_max = jnp.maximum(a_max, x)
    a_max = jax.lax.stop_gradient(a_max)
    total = jnp.exp(a[0] - a_max)
    for x in a[1:]:
        total = total + jnp.exp(x - a_max)
    return -tau * (jnp.log(total) + a_max)


class FullDerived(eqx.Module):
    """Parameter- and scene-derived numbers of the full model's step."""

    curve: HoneycombCurve  # the honeycomb law with its breakpoints evaluated
    k_r: jnp.ndarray  # N/m, ground restitution stiffness k / (1 - gamma)
    L_a0_pair: jnp.ndarray  # m, rest length of each auxiliary strut
    geometry: tuple  # body-frame leg points P, A+, A-, each (n, 3) m
    ground: tuple  # ground normal and tangents (ground_frame), each (3,)
    inertia: jnp.ndarray  # (3,) kg m^2, principal body inertia
    smoothing: Smoothing = Smoothing()


class FullModel(AbstractModel):
    """The full 3-D model (module docstring). Stateless: parameters are the vehicle's."""

    name: ClassVar[str] = "full"
    COLUMNS: ClassVar[tuple[str, ...]] = COLUMNS
    RATE_CHANNELS: ClassVar[tuple[str, ...]] = RATE_CHANNELS

    def initial_state(self, vehicle: Vehicle, scene: Scene) -> Vehicle3DState:
        """Unloaded vehicle in the scene's attitude, lowest foot ``drop_height`` above the ground
        (measured along the ground normal), moving rigidly with the scene's velocity and rates."""
        n_g, t1, t2 = ground_frame(scene)
        _, _, _, foot_b = body_points(vehicle, scene)
        quat = quat_from_euler(scene.roll, scene.pitch, scene.yaw)
        Rm = quat_to_matrix(quat)
        foot_rel = foot_b @ Rm.T
        z = (scene.drop_height - jnp.min(foot_rel @ n_g)) / n_g[2]
        p = jnp.stack([0.0, 0.0, z])
        feet = p[None, :] + foot_rel
        v = jnp.stack([scene.horizontal_speed * jnp.cos(scene.heading),
                       scene.horizontal_speed * jnp.sin(scene.heading), -scene.sink_speed])
        w_b = jnp.stack([scene.roll_rate, scene.pitch_rate, scene.yaw_rate])
        v_feet = v[None, :] + jnp.cross(jnp.broadcast_to(Rm @ w_b, foot_rel.shape), foot_rel)
        n = vehicle.n_legs
        return Vehicle3DState(
            t=jnp.zeros(()), q=(p, quat, feet), v=(v, w_b, v_feet),
            x_max=jnp.zeros(n), d_max=jnp.zeros(n), anchor=(feet @ t1, feet @ t2),
            diss_rate=jnp.zeros(len(RATE_CHANNELS)), diss_slip=jnp.zeros(()),
            slip_distance=jnp.zeros(n), t_force=jnp.zeros(n),
        )

    def prepare(self, vehicle: Vehicle, scene: Scene,
                smoothing: Smoothing = Smoothing()) -> FullDerived:
        """Parameter- and scene-derived numbers the step reads, computed once outside the loop."""
        P_b, Ap_b, Am_b, _ = body_points(vehicle, scene)
        return FullDerived(curve=vehicle.honeycomb.curve(), k_r=vehicle.ground.k_r,
                           L_a0_pair=vehicle.leg.L_a0_pair, geometry=(P_b, Ap_b, Am_b),
                           ground=ground_frame(scene), inertia=_inertia(vehicle),
                           smoothing=smoothing)

    def energy_scale(self, vehicle: Vehicle, scene: Scene):
        m = vehicle.m_body + vehicle.n_legs * vehicle.m_foot
        w = jnp.stack([scene.roll_rate, scene.pitch_rate, scene.yaw_rate])
        # generous, as the quarter's (the scale only sets the ledger's tolerance): three strokes
        # for the legs, and 1 m of fall for a vehicle that tips
        height = scene.drop_height + 3.0 * vehicle.honeycomb.x_L4 + 1.0
        return (m * (0.5 * (scene.sink_speed**2 + scene.horizontal_speed**2) + vehicle.g * height)
                + 0.5 * jnp.sum(_inertia(vehicle) * w * w))

    def drift(self, q, v, dt):
        p, quat, feet = q
        vb, w_b, vf = v
        quat = quat_mul(quat, _quat_exp(0.5 * dt * w_b))
        quat = quat / jnp.sqrt(jnp.sum(quat * quat))
        return (p + dt * vb, quat, feet + dt * vf)

    def evaluate(self, vehicle: Vehicle, s: Vehicle3DState, scene: Scene | None = None,
                 derived: FullDerived | None = None, kick=None) -> Evaluation:
        """Accelerations at state ``s`` (``AbstractModel.evaluate``)."""
        scene = Scene() if scene is None else scene
        derived = self.prepare(vehicle, scene) if derived is None else derived
        leg, hc, gr = vehicle.leg, derived.curve, vehicle.ground
        sm, sn = derived.smoothing.length_m, derived.smoothing.force_N
        m, m2, g = vehicle.m_body, vehicle.m_foot, vehicle.g
        inertia = derived.inertia
        p, quat, feet = s.q
        vb, w_b, vf = s.v
        Rm = quat_to_matrix(quat)
        w_w = _mv(Rm, w_b)
        P_b, Ap_b, Am_b = derived.geometry

        def attach(r_b):
            r = _rotate_rows(r_b, Rm)
            return p[None, :] + r, vb[None, :] + jnp.cross(jnp.broadcast_to(w_w, r.shape), r), r

        P, vP, rP = attach(P_b)
        d = feet - P
        length = _norm_rows(d)
        u = d * (1.0 / length)[:, None]
        x_b = leg.L_h0 - length
        v_b = -_dot(u, vf - vP)
        hco = honeycomb(x_b, s.x_max, hc, sm)

        aux_force_vecs, aux_torques, aux_energy, aux_axial = 0.0, 0.0, 0.0, 0.0
        for A_b in (Ap_b, Am_b):
            A, _, rA = attach(A_b)
            da = feet - A
            la = _norm_rows(da)
            a = da * (1.0 / la)[:, None]
            ax = aux_strut(la, derived.L_a0_pair, 0.5 * leg.k_a)
            fa = ax.force[:, None] * a
            aux_force_vecs = aux_force_vecs + fa
            aux_torques = aux_torques + jnp.sum(jnp.cross(rA, -fa), axis=0)
            aux_energy = aux_energy + _legsum(ax.elastic_energy)
            aux_axial = aux_axial + ax.force

        n_g, t1, t2 = derived.ground
        nc = normal_contact(-_dot(feet, n_g[None, :]), -_dot(vf, n_g[None, :]), s.d_max, gr,
                            derived.k_r, sm)
        second = self.second_order and s.t_force is not None
        tc = tangential_contact((_dot(feet, t1[None, :]), _dot(feet, t2[None, :])), s.anchor,
                                nc.force, gr, sm, s.t_force if second else None)
        f_ground = (nc.force[:, None] * n_g[None, :] + tc.force[0][:, None] * t1[None, :]
                    + tc.force[1][:, None] * t2[None, :])

        gz = jnp.array([0.0, 0.0, 1.0])

        def body_rates(f_strut):  # the body's force [N] and body-frame angular acceleration
            f_body = -jnp.sum(f_strut + aux_force_vecs, axis=0) - m * g * gz
            torque_b = _mtv(Rm, jnp.sum(jnp.cross(rP, -f_strut), axis=0) + aux_torques)
            return f_body, (torque_b - jnp.cross(w_b, inertia * w_b)) / inertia

        if kick is None:
            st = strut_force(hco.force, x_b, v_b, leg.D_b, leg.k_topout, smooth_N=sn, smooth_m=sm)
        else:  # implicit damping: the stroke rate after the kick from the other foot forces
            other_u = _dot(u, aux_force_vecs + f_ground) - m2 * g * u[:, 2]
            a = kick / m2
            free = v_b - a * other_u
            if self.second_order:  # and the kick of the attachment P (body forces with the
                # damping explicit; the quarter model's note): u . (a_b + w_dot x r_P)
                st_ex = strut_force(hco.force, x_b, v_b, leg.D_b, leg.k_topout, smooth_N=sn,
                                    smooth_m=sm)
                f_body_ex, w_dot_ex = body_rates(st_ex.force[:, None] * u)
                a_P = f_body_ex[None, :] / m + jnp.cross(_mv(Rm, w_dot_ex), rP)
                free = free + kick * _dot(u, a_P)
            st = strut_force(hco.force, x_b, v_b, leg.D_b, leg.k_topout, a, free, sn, sm)
        f_strut = st.force[:, None] * u
        f_feet = f_strut + aux_force_vecs + f_ground - m2 * g * gz[None, :]
        f_body, w_dot = body_rates(f_strut)
        accel = (f_body / m, w_dot, f_feet / m2)

        new = eqx.tree_at(
            lambda x: (x.x_max, x.d_max, x.anchor, x.diss_slip, x.slip_distance), s,
            (hco.x_max, nc.d_max, tc.anchor, s.diss_slip + _legsum(tc.slip_energy),
             s.slip_distance + tc.slip),
        )
        if second:
            new = eqx.tree_at(lambda x: x.t_force, new, safe_hypot(tc.force[0], tc.force[1]))
        kinetic = self.kinetic_energy(vehicle, derived, s.v)
        potential = g * (m * p[2] + m2 * _legsum(feet[:, 2]))
        stores = dict(
            kinetic_J=kinetic,
            potential_J=potential,
            elastic_honeycomb_J=_legsum(hco.elastic_energy + st.topout_energy),
            elastic_aux_J=aux_energy,
            elastic_ground_J=_legsum(nc.elastic_energy),
            elastic_tangential_J=_legsum(tc.elastic_energy),
        )
        dissipated = dict(
            diss_crush_J=_legsum(hco.crush_energy),
            diss_ground_plastic_J=_legsum(nc.plastic_energy),
            diss_slip_J=new.diss_slip,
        )
        roll, pitch, yaw = euler_from_matrix(Rm)
        contact = nc.force > 0.0
        # Angular momentum of body + feet about the system's centre of mass (world frame).
        com = (m * p + m2 * jnp.sum(feet, axis=0)) / (m + m2 * vehicle.n_legs)
        ang_mom = (Rm @ (inertia * w_b) + m * jnp.cross(p - com, vb)
                   + m2 * jnp.sum(jnp.cross(feet - com[None, :], vf), axis=0))
        deg = 180.0 / jnp.pi
        record = dict(
            body_x_m=p[0], body_y_m=p[1], body_z_m=p[2],
            body_vx_mps=vb[0], body_vy_mps=vb[1], body_vz_mps=vb[2],
            roll_deg=roll * deg, pitch_deg=pitch * deg, yaw_deg=yaw * deg,
            tilt_deg=jnp.arctan2(safe_hypot(Rm[2, 0], Rm[2, 1]), Rm[2, 2]) * deg,  # grad-safe at 0
            omega_x_radps=w_b[0], omega_y_radps=w_b[1], omega_z_radps=w_b[2],
            stability_margin_m=stability_margin(p, feet, derived.ground),
            angular_momentum_x_Nms=ang_mom[0], angular_momentum_y_Nms=ang_mom[1],
            angular_momentum_z_Nms=ang_mom[2],
            stroke_m=x_b, stroke_max_m=hco.x_max, buffer_velocity_mps=v_b,
            honeycomb_force_N=hco.force, strut_force_N=st.force, aux_force_N=aux_axial,
            normal_force_N=nc.force, tangential_force_N=safe_hypot(tc.force[0], tc.force[1]),
            pit_depth_m=nc.pit_depth,
            slip_indicator=jnp.where(contact, jnp.where(tc.slipping, 1.0, 0.0), 0.5),
            foot_x_m=feet[:, 0], foot_y_m=feet[:, 1], foot_z_m=feet[:, 2],
            **stores,
            **dissipated,
        )
        rate_power = jnp.stack([_legsum(st.damping_power), _legsum(nc.damping_power)])
        return Evaluation(accel, new, record, rate_power, stores, dissipated)

    def kinetic_energy(self, vehicle: Vehicle, derived: FullDerived, v):
        """``AbstractModel.kinetic_energy``: body translation and rotation, and the feet."""
        vb, w_b, vf = v
        return 0.5 * (vehicle.m_body * jnp.sum(vb * vb) + jnp.sum(derived.inertia * w_b * w_b)
                      + vehicle.m_foot * jnp.sum(vf * vf))

    def accel_record(self, acc):
        a = acc[0]
        return dict(body_ax_mps2=a[0], body_ay_mps2=a[1], body_az_mps2=a[2])

    def peak_values(self, record, acc):
        a = acc[0]
        return dict(
            peak_normal_force_N=record["normal_force_N"],
            peak_tangential_force_N=record["tangential_force_N"],
            peak_strut_force_N=record["strut_force_N"],
            peak_honeycomb_force_N=record["honeycomb_force_N"],
            peak_aux_force_N=jnp.abs(record["aux_force_N"]),
            peak_buffer_velocity_mps=record["buffer_velocity_mps"],
            peak_body_accel_mps2=safe_hypot(safe_hypot(a[0], a[1]), a[2]),
            peak_foot_accel_mps2=_norm_rows(acc[2]),
            peak_tilt_deg=record["tilt_deg"],
            peak_margin_deficit_m=-record["stability_margin_m"],
            # the max stroke as a peak: one that stops at a tip-over (the summary's
            # max_stroke_m), where the memory runs on with the tipped body's motion
            peak_stroke_max_m=record["stroke_max_m"],
        )

    def leg_max(self, x):
        return jnp.max(x, axis=-1)

    def contact_flag(self, record):
        return jnp.any(record["normal_force_N"] > 0.0)

    def tipping(self, record):
        """The centre of mass is outside the polygon of the feet (the integrator counts it only
        after the first touchdown, so a tilted vehicle still in the air is not tipping)."""
        return record["stability_margin_m"] < 0.0

    def could_still_tip(self, vehicle, ev):
        """``TIP_ENERGY_SAFETY`` times the kinetic and elastic energy (the ledger's stores but
        the potential) could lift the body's centre of mass over the nearest edge of the feet's
        polygon: m g (sqrt(h^2 + d^2) - h), the rise of a centre at height h above the lowest
        foot and d (the stability margin) from the edge as it turns about that edge until it
        stands above it. A bound in the energy, not a prediction: energy the gear will still
        dissipate counts as available."""
        record = ev.record
        h = record["body_z_m"] - jnp.min(record["foot_z_m"])
        d = jnp.maximum(record["stability_margin_m"], 0.0)
        rise = safe_hypot(h, d) - h
        available = sum(v for k, v in ev.stores.items() if k != "potential_J")
        return TIP_ENERGY_SAFETY * available >= vehicle.m_body * vehicle.g * rise

    def final_summary(self, s: Vehicle3DState, record) -> dict:
        return dict(
            max_stroke_m=record["stroke_max_m"],  # the memory with the end state's stroke
            final_stroke_m=record["stroke_m"],
            final_pit_depth_m=record["pit_depth_m"],
            final_normal_force_N=record["normal_force_N"],
            slip_distance_m=s.slip_distance,
            final_tilt_deg=record["tilt_deg"],
            final_stability_margin_m=record["stability_margin_m"],
            final_position_m=s.q[0],
        )
