"""The non-JAX quarter model behind benchmarks/baselines.py: a plain-float port of
``QuarterModel.evaluate`` and its laws (``forces``), the numba symplectic Euler loop
(``euler_run`` / ``euler_batch``) and the continuous right-hand side for scipy ``solve_ivp``
(``rhs`` / ``scipy_run``). Items 1-3 of baselines.py's docstring describe them."""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path

import numpy as np

try:
    import numba
    from numba import njit, prange

    NUMBA_AVAILABLE = True
except ImportError:  # the optional bench extra is absent (CI): keep the module importable
    numba = None
    NUMBA_AVAILABLE = False
    prange = range

    def njit(*args, **kwargs):
        """Stand-in for numba.njit: the function stays plain Python."""
        if len(args) == 1 and callable(args[0]) and not kwargs:
            return args[0]
        return lambda f: f

try:
    import scipy
    from scipy.integrate import solve_ivp

    SCIPY_AVAILABLE = True
except ImportError:
    scipy = None
    solve_ivp = None
    SCIPY_AVAILABLE = False

MISSING_MESSAGE = (
    "benchmarks/baselines.py needs the optional 'bench' extra (numba and scipy): "
    'pip install -e ".[bench]"'
)

OUT = Path(__file__).resolve().parent / "results" / "baselines.json"
THREADS = 2
ENERGY_TOLERANCE = 0.1  # jaxland._solvers._loop.ENERGY_TOLERANCE: failure above this x energy scale
SAVE_DT = 1e-3
T_END = 1.2
EULER_DTS = (1.6e-4, 8e-5, 4e-5, 2e-5, 1e-5, 5e-6, 2.5e-6)
REFERENCE_DT = 2.5e-6
FINE_DT = 1.25e-6  # the --check reference for the continuous right-hand side
RTOLS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10)
BATCH_SIZES = (1, 10, 100, 1000)
PEAK_GRID_DT = 1e-5  # dense-output grid for the scipy peaks (plus the accepted steps)
RADAU_CAP_S = 55.0  # once a scipy run takes longer (or fails), tighter tolerances are skipped
RUN_DEADLINE_S = 60.0  # hard cap on one scipy run (checked in the right-hand side)

# Parameter vector layout (float64), filled by ``params_vector``.
(P_R, P_H1, P_H2, P_LH0, P_H, P_KA, P_KTOP, P_DB, P_LA0,
 P_KB1, P_KB3, P_KBOT, P_F1, P_F2, P_XL1, P_XL2, P_XL3, P_XL4, P_BONDED,
 P_K, P_GAMMA, P_CHI, P_MU, P_KTAN, P_KR,
 P_MQ, P_MF, P_G) = range(28)
N_PARAMS = 28

# State layout of the continuous form (and of the recorded Euler states).
Y_NAMES = ("z_body_m", "r_foot_m", "z_foot_m", "vz_body_mps", "vr_foot_mps", "vz_foot_mps",
           "x_max_m", "d_max_m", "anchor_m", "E_struct_damp_J", "E_ground_damp_J", "E_slip_J")
# Typical magnitudes: atol_i = rtol * ATOL_SCALE_i (positions ~0.1 m, speeds ~1 m/s, memories
# ~1 cm of stroke / 1 mm of penetration, the anchor like the foot, energies ~100 J).
ATOL_SCALE = np.array([0.1, 0.1, 0.1, 1.0, 1.0, 1.0, 0.01, 0.001, 0.1, 100.0, 100.0, 100.0])

# Columns of the Euler state record: the first nine of Y_NAMES, then the stroke.
N_REC = 10


def _require():
    if not (NUMBA_AVAILABLE and SCIPY_AVAILABLE):
        raise RuntimeError(MISSING_MESSAGE)


# ------------------------------------------------------------------------------ parameters

def params_vector(vehicle, scene=None) -> np.ndarray:
    """The float64 parameter vector of ``forces`` from a concrete jaxland ``Vehicle``, with the
    scene-level overrides the quarter model applies (friction, mass scale, uniform plateau
    scale). Derived numbers come from jaxland's own properties, so they match bit for bit."""
    import equinox as eqx

    if scene is not None:
        if scene.plateau_scale is not None:
            s = float(np.mean(np.asarray(scene.plateau_scale)))
            vehicle = eqx.tree_at(lambda v: (v.honeycomb.F1, v.honeycomb.F2), vehicle,
                                  (vehicle.honeycomb.F1 * s, vehicle.honeycomb.F2 * s))
        if scene.friction is not None:
            vehicle = eqx.tree_at(lambda v: v.ground.mu, vehicle, scene.friction)
        if scene.mass_scale is not None:
            vehicle = eqx.tree_at(lambda v: v.m_body, vehicle,
                                  vehicle.m_body * scene.mass_scale)
    leg, gr = vehicle.leg, vehicle.ground
    curve = vehicle.honeycomb.curve()
    P = np.zeros(N_PARAMS)
    f = float
    P[P_R], P[P_H1], P[P_H2], P[P_LH0], P[P_H] = f(leg.R), f(leg.H1), f(leg.H2), f(leg.L_h0), \
        f(leg.h)
    P[P_KA], P[P_KTOP], P[P_DB], P[P_LA0] = f(leg.k_a), f(leg.k_topout), f(leg.D_b), \
        f(leg.L_a0_pair)
    P[P_KB1], P[P_KB3], P[P_KBOT] = f(curve.k_b1), f(curve.k_b3), f(curve.k_bottom)
    P[P_F1], P[P_F2] = f(curve.F1), f(curve.F2)
    P[P_XL1], P[P_XL2], P[P_XL3], P[P_XL4] = f(curve.x_L1), f(curve.x_L2), f(curve.x_L3), \
        f(curve.x_L4)
    P[P_BONDED] = 1.0 if curve.bonded else 0.0
    P[P_K], P[P_GAMMA], P[P_CHI], P[P_MU], P[P_KTAN] = f(gr.k), f(gr.gamma), f(gr.chi), \
        f(gr.mu), f(gr.k_tan)
    P[P_KR] = f(gr.k / (1.0 - gr.gamma))
    P[P_MQ], P[P_MF], P[P_G] = f(vehicle.m_quarter), f(vehicle.m_foot), f(vehicle.g)
    return P


def initial_state(vehicle, scene) -> np.ndarray:
    """y0 of the continuous form (the Euler loop uses its first nine entries): the leg at rest,
    the foot ``drop_height`` above the ground, falling at ``sink_speed``; as jaxland."""
    foot = np.asarray(vehicle.leg.foot_rest, dtype=float)
    z_foot = float(scene.drop_height)
    v0 = float(scene.sink_speed)
    y0 = np.zeros(12)
    y0[0], y0[1], y0[2] = z_foot - foot[1], foot[0], z_foot
    y0[3], y0[4], y0[5] = -v0 * 1.0, -v0 * 0.0, -v0 * 1.0
    y0[8] = foot[0]
    return y0


def energy_scale(P, scene) -> float:
    """QuarterModel.energy_scale (jaxland._models._quarter): the energy the landing has to
    absorb, bounded [J]."""
    m = P[P_MQ] + P[P_MF]
    height = float(scene.drop_height) + 2.5 * P[P_XL4]
    return float(m * (0.5 * float(scene.sink_speed) ** 2 + P[P_G] * height))


# ------------------------------------------------------------------------------- the laws

@njit(cache=False, fastmath=False, error_model="numpy")
def _clip(x, lo, hi):
    return min(max(x, lo), hi)


@njit(cache=False, fastmath=False, error_model="numpy")
def forces(zb, rf, zf, vzb, vrf, vzf, xmax_prev, dmax_prev, anchor_prev, P):
    """``jaxland._models._quarter.QuarterModel.evaluate`` on plain floats. Returns a tuple:

    0-2  accelerations (a_body_z, a_foot_r, a_foot_z) [m/s^2]
    3-4  stroke x_b [m], stroke rate v_b [m/s] (compression positive)
    5-7  updated memories x_max, d_max, anchor [m] (return maps)
    8    honeycomb force [N]          9  strut force [N]        10 strut damping power [W]
    11   normal force F_n [N]         12 spring force F_s [N]   13 ground damping power [W]
    14   slipping (1.0 / 0.0, in contact only)                  15 slip increment [m]
    16   slip energy of this return map [J]
    17   stored + closed-form energy: kinetic + potential + elastic (honeycomb, top-out, aux,
         ground, tangential) + crush + ground plastic [J] (without slip and rate channels)
    """
    R, H1, H2, L_h0, h = P[0], P[1], P[2], P[3], P[4]
    k_a, k_top, D_b, L_a0 = P[5], P[6], P[7], P[8]
    k_b1, k_b3, k_bot, F1, F2 = P[9], P[10], P[11], P[12], P[13]
    x_L1, x_L2, x_L3, x_L4, bonded = P[14], P[15], P[16], P[17], P[18]
    k, gamma, chi, mu, k_tan, k_r = P[19], P[20], P[21], P[22], P[23], P[24]
    m_q, m_f, g = P[25], P[26], P[27]

    # Main strut geometry (safe_hypot).
    dr = rf - R
    dz = zf - (zb - H1)
    n2 = dr * dr + dz * dz
    length = math.sqrt(n2) if n2 > 0.0 else 0.0
    u_r = dr / length
    u_z = dz / length
    x_b = L_h0 - length
    v_b = -(u_r * vrf + u_z * (vzf - vzb))

    # Honeycomb with permanent set (jaxland._laws._honeycomb.honeycomb).
    x_max = max(xmax_prev, x_b)
    p1 = _clip(x_max - x_L1, 0.0, x_L2 - x_L1)
    p2 = _clip(x_max - x_L3, 0.0, x_L4 - x_L3)
    x_p = p1 + p2
    y = x_b - x_p
    dy3 = x_L3 - x_L2
    y1 = _clip(y, 0.0, x_L1)
    y2 = _clip(y - x_L1, 0.0, dy3)
    y3 = max(y - x_L1 - dy3, 0.0)
    yt = min(y, 0.0)
    F_bh = k_b1 * y1 + k_b3 * y2 + k_bot * y3
    elastic_hc = (0.5 * k_b1 * y1 ** 2 + F1 * y2 + 0.5 * k_b3 * y2 ** 2
                  + F2 * y3 + 0.5 * k_bot * y3 ** 2)
    if bonded != 0.0:
        F_bh = F_bh + k_b1 * yt
        elastic_hc = elastic_hc + 0.5 * k_b1 * yt ** 2
    crush = F1 * p1 + F2 * p2

    # Strut: structural damping with the floor, top-out stop (jaxland._laws._strut).
    f_raw = F_bh + D_b * v_b * abs(F_bh)
    f_total = max(f_raw, 0.0) if F_bh >= 0.0 else f_raw
    f_damp = f_total - F_bh
    x_ext = min(x_b, 0.0)
    f_top = k_top * x_ext
    F_st = F_bh + f_damp + f_top
    damp_power = f_damp * v_b
    topout_energy = 0.5 * k_top * x_ext ** 2

    # Auxiliary strut pair (jaxland._laws._aux).
    dz_a = zf - (zb - H1 - H2)
    length_a = math.sqrt(dr * dr + dz_a * dz_a + h * h)
    a_r = dr / length_a
    a_z = dz_a / length_a
    e_a = L_a0 - length_a
    F_a = k_a * e_a
    elastic_aux = 0.5 * k_a * e_a ** 2

    # Normal contact with pit memory and chi damping (jaxland._laws._contact.normal_contact).
    d = -zf
    d_dot = -vzf
    d_max = max(dmax_prev, d)
    e = max(d - gamma * d_max, 0.0)
    f_s = k_r * e
    factor = max(1.0 + chi * d_dot, 0.0)
    F_n = f_s * factor
    ground_power = (F_n - f_s) * d_dot
    elastic_ground = 0.5 * k_r * e ** 2
    plastic_ground = 0.5 * gamma * k * d_max ** 2

    # Tangential stick/slip return map (tangential_contact; the lateral axis is 0).
    ux = rf - anchor_prev
    nu2 = ux * ux + 0.0 * 0.0
    nn = math.sqrt(nu2) if nu2 > 0.0 else 0.0
    limit = mu * F_n
    slipping = k_tan * nn > limit
    scale = limit / (k_tan * nn) if slipping else 1.0
    ux = ux * scale
    in_contact = F_n > 0.0
    slip = nn * (1.0 - scale) if in_contact else 0.0
    F_t = -k_tan * ux
    anchor = rf - ux
    elastic_tan = 0.5 * k_tan * (ux * ux + 0.0)
    slip_energy = k_tan * nn * scale * slip

    f_foot_r = F_st * u_r + F_a * a_r + F_t
    f_foot_z = F_st * u_z + F_a * a_z + F_n - m_f * g
    f_body = -(F_st * u_z + F_a * a_z) - m_q * g

    energy = (0.5 * (m_q * vzb ** 2 + m_f * (vrf ** 2 + vzf ** 2))
              + g * (m_q * zb + m_f * zf)
              + (elastic_hc + topout_energy) + elastic_aux + elastic_ground + elastic_tan
              + crush + plastic_ground)
    inv_mq = 1.0 / m_q  # state-independent: hoisted out of the time loop by LLVM
    inv_mf = 1.0 / m_f
    return (f_body * inv_mq, f_foot_r * inv_mf, f_foot_z * inv_mf,
            x_b, v_b, x_max, d_max, anchor,
            F_bh, F_st, damp_power, F_n, f_s, ground_power,
            1.0 if (slipping and in_contact) else 0.0, slip, slip_energy, energy)


@njit(cache=False, fastmath=False, error_model="numpy")
def stroke_of(zb, rf, zf, P):
    """Main-strut stroke x_b [m] at a configuration (compression positive)."""
    dr = rf - P[0]
    dz = zf - (zb - P[1])
    return P[3] - math.sqrt(dr * dr + dz * dz)


# -------------------------------------------------------------------- symplectic Euler loop

@njit(cache=False, fastmath=False, error_model="numpy")
def _store(rec, k, zb, rf, zf, vzb, vrf, vzf, xmax, dmax, anchor, stroke):
    """Row ``k`` of the record: the state, the memories and the stroke."""
    rec[k, 0] = zb
    rec[k, 1] = rf
    rec[k, 2] = zf
    rec[k, 3] = vzb
    rec[k, 4] = vrf
    rec[k, 5] = vzf
    rec[k, 6] = xmax
    rec[k, 7] = dmax
    rec[k, 8] = anchor
    rec[k, 9] = stroke


@njit(cache=False, fastmath=False, error_model="numpy")
def _euler_core(P, y0, dt, n_steps, save_ratio, n_save, e_scale, rec):
    """One landing of jaxland's fixed-step symplectic Euler. ``save_ratio`` = save_dt / dt
    (an integer-valued float when dt divides save_dt: then the record is exact; otherwise
    linear interpolation between steps). ``rec`` (n_save, N_REC) receives the state and
    stroke at t_k = k save_dt, or is ignored when it has 0 rows.

    Returns (max_stroke, final_stroke, peak_F_hc, peak_F_n, max |ledger residual|,
             failure time or -1, steps done, diss_slip, slip distance).
    """
    zb, rf, zf = y0[0], y0[1], y0[2]
    vzb, vrf, vzf = y0[3], y0[4], y0[5]
    xmax, dmax, anchor = y0[6], y0[7], y0[8]
    e_sd = 0.0
    e_gd = 0.0
    diss_slip = 0.0
    slip_dist = 0.0
    out0 = forces(zb, rf, zf, vzb, vrf, vzf, xmax, dmax, anchor, P)
    e0 = out0[17] + diss_slip + (e_sd + e_gd)
    peak_hc = -np.inf
    peak_n = -np.inf
    res_max = 0.0
    fail_t = -1.0
    record = rec.shape[0] > 0
    k_next = 0  # next save index
    n_done = 0
    for n in range(n_steps):
        o = forces(zb, rf, zf, vzb, vrf, vzf, xmax, dmax, anchor, P)
        x_b = o[3]
        # save points t_k in [t_n, t_{n+1}): exact at t_n, interpolated inside the step
        while record and k_next < n_save and k_next * save_ratio < n + 1.0 - 1e-9:
            w = k_next * save_ratio - n
            if w < 1e-9:
                _store(rec, k_next, zb, rf, zf, vzb, vrf, vzf, xmax, dmax, anchor, x_b)
                k_next += 1
            else:
                break  # needs s_{n+1}: recorded after the update
        diss_slip_new = diss_slip + o[16]
        residual = o[17] + diss_slip_new + (e_sd + e_gd) - e0
        if o[8] > peak_hc:
            peak_hc = o[8]
        if o[11] > peak_n:
            peak_n = o[11]
        if abs(residual) > res_max:
            res_max = abs(residual)
        finite = (math.isfinite(zb) and math.isfinite(rf) and math.isfinite(zf)
                  and math.isfinite(vzb) and math.isfinite(vrf) and math.isfinite(vzf))
        if not finite or not (abs(residual) <= ENERGY_TOLERANCE * e_scale):
            fail_t = n * dt
            n_done = n
            break
        # symplectic Euler: memories by return map at (q_n, v_n), then kick and drift
        vzb1 = vzb + dt * o[0]
        vrf1 = vrf + dt * o[1]
        vzf1 = vzf + dt * o[2]
        zb1 = zb + dt * vzb1
        rf1 = rf + dt * vrf1
        zf1 = zf + dt * vzf1
        xmax1, dmax1, anchor1 = o[5], o[6], o[7]
        e_sd += dt * o[10]
        e_gd += dt * o[13]
        diss_slip = diss_slip_new
        slip_dist += o[15]
        while record and k_next < n_save and k_next * save_ratio < n + 1.0 - 1e-9:
            w = k_next * save_ratio - n
            x1 = stroke_of(zb1, rf1, zf1, P)
            _store(rec, k_next, zb + w * (zb1 - zb), rf + w * (rf1 - rf), zf + w * (zf1 - zf),
                   vzb + w * (vzb1 - vzb), vrf + w * (vrf1 - vrf), vzf + w * (vzf1 - vzf),
                   xmax + w * (xmax1 - xmax), dmax + w * (dmax1 - dmax),
                   anchor + w * (anchor1 - anchor), x_b + w * (x1 - x_b))
            k_next += 1
        zb, rf, zf, vzb, vrf, vzf = zb1, rf1, zf1, vzb1, vrf1, vzf1
        xmax, dmax, anchor = xmax1, dmax1, anchor1
        n_done = n + 1
    final_stroke = stroke_of(zb, rf, zf, P)
    if fail_t < 0.0:
        while record and k_next < n_save:  # t_k = t_N (the end of the landing)
            _store(rec, k_next, zb, rf, zf, vzb, vrf, vzf, xmax, dmax, anchor, final_stroke)
            k_next += 1
    while record and k_next < n_save:  # not reached after a failure
        for c in range(N_REC):
            rec[k_next, c] = np.nan
        k_next += 1
    return (xmax, final_stroke, peak_hc, peak_n, res_max, fail_t, n_done, diss_slip,
            slip_dist)


@njit(cache=False, fastmath=False, error_model="numpy")
def euler_run_kernel(P, y0, dt, n_steps, save_ratio, n_save, e_scale):
    rec = np.empty((n_save, N_REC))
    out = _euler_core(P, y0, dt, n_steps, save_ratio, n_save, e_scale, rec)
    return out, rec


@njit(cache=False, fastmath=False, error_model="numpy", parallel=True)
def euler_batch_kernel(P, Y0, dt, n_steps, e_scales):
    """A batch of landings (rows of ``Y0``) in parallel over threads (prange). Returns
    (N, 6): max stroke, final stroke, peak honeycomb force, peak normal force, max |ledger
    residual|, failure time (-1 if none). No trajectory (like jaxland's batch benchmark)."""
    n = Y0.shape[0]
    out = np.empty((n, 6))
    for i in prange(n):
        rec = np.empty((0, N_REC))
        r = _euler_core(P, Y0[i], dt, n_steps, 1.0, 0, e_scales[i], rec)
        out[i, 0] = r[0]
        out[i, 1] = r[1]
        out[i, 2] = r[2]
        out[i, 3] = r[3]
        out[i, 4] = r[4]
        out[i, 5] = r[5]
    return out


def _save_ratio(dt, save_dt):
    r = save_dt / dt
    return float(round(r)) if abs(r - round(r)) < 1e-9 * r else r


def euler_prepare(vehicle, scene, dt, t_end=T_END, save_dt=SAVE_DT):
    """The arguments of ``euler_run_kernel`` (parameter extraction goes through jax: ~1 ms,
    done once outside any timing)."""
    P = params_vector(vehicle, scene)
    y0 = initial_state(vehicle, scene)
    n_steps = int(round(t_end / dt))
    n_save = int(math.floor(t_end / save_dt + 1e-9)) + 1
    return (P, y0, float(dt), n_steps, _save_ratio(dt, save_dt), n_save,
            energy_scale(P, scene))


def euler_result(out, rec, save_dt=SAVE_DT) -> dict:
    (xmax, final, peak_hc, peak_n, res_max, fail_t, n_done, diss_slip, slip_dist) = out
    return dict(max_stroke_m=float(xmax), final_stroke_m=float(final),
                peak_honeycomb_force_N=float(peak_hc), peak_normal_force_N=float(peak_n),
                energy_residual_max_J=float(res_max),
                failure_time_s=None if fail_t < 0 else float(fail_t),
                failed=bool(fail_t >= 0), n_steps=int(n_done), slip_energy_J=float(diss_slip),
                slip_distance_m=float(slip_dist), record=rec,
                time_s=np.arange(rec.shape[0]) * save_dt)


def euler_run(vehicle, scene, dt, t_end=T_END, save_dt=SAVE_DT) -> dict:
    """One numba Euler landing: summary numbers plus the record on t_k = k save_dt for
    k = 0 .. floor(t_end / save_dt) (the last sample is the end state when it falls on t_end)."""
    _require()
    out, rec = euler_run_kernel(*euler_prepare(vehicle, scene, dt, t_end, save_dt))
    return euler_result(out, rec, save_dt)


def euler_batch(vehicle, scenes, dt, t_end=T_END) -> np.ndarray:
    """A list of scenes run in parallel (numba.prange); returns the (N, 6) summary array."""
    _require()
    P = params_vector(vehicle, scenes[0])
    Y0 = np.stack([initial_state(vehicle, s)[:9] for s in scenes])
    es = np.array([energy_scale(P, s) for s in scenes])
    return euler_batch_kernel(P, np.ascontiguousarray(Y0), float(dt), int(round(t_end / dt)), es)


# ------------------------------------------------------------ continuous right-hand side

ANCHOR_SPEC = 0  # the spec as written: anchor' = vr_f - s mu k_r d_dot / k_tan while slipping
ANCHOR_CONSISTENT = 1  # the same, made consistent with the return map (see ``rhs``)


@njit(cache=False, fastmath=False, error_model="numpy")
def rhs(t, y, P, anchor_mode=ANCHOR_CONSISTENT):
    """dy/dt of the continuous form (module docstring, item 3).

    ``anchor_mode`` = ANCHOR_SPEC follows the spec literally: while the law reports slip,
    anchor' = vr_f - s mu k_r d_dot / k_tan whatever its sign. That lets the anchor move away
    from the foot when the normal force rises (|u| grows with the friction cone), which the
    return map never does (it only drags the anchor towards the foot), and counts that motion
    as slip dissipation: the ledger does not close and the landing converges to a different
    answer. ANCHOR_CONSISTENT (the default) fixes both: dF_s/dt is the exact rate of the spring
    force, k_r (d_dot - gamma d_max') (= k_r d_dot on the restitution/reloading line, k d_dot
    on the virgin line), and the slip rate must point along u = r_f - anchor (s anchor' > 0),
    otherwise the foot sticks (anchor' = 0): the Filippov / complementarity form of Coulomb's
    law, whose discrete form is jaxland's return map.
    """
    o = forces(y[0], y[1], y[2], y[3], y[4], y[5], y[6], y[7], y[8], P)
    dy = np.empty(12)
    dy[0] = y[3]
    dy[1] = y[4]
    dy[2] = y[5]
    dy[3] = o[0]
    dy[4] = o[1]
    dy[5] = o[2]
    x_b, v_b = o[3], o[4]
    dy[6] = max(v_b, 0.0) if x_b >= y[6] else 0.0
    d = -y[2]
    d_dot = -y[5]
    dy[7] = max(d_dot, 0.0) if d >= y[7] else 0.0
    F_n, f_s, slipping = o[11], o[12], o[14]
    mu, k_tan, k_r, gamma = P[P_MU], P[P_KTAN], P[P_KR], P[P_GAMMA]
    if not (F_n > 0.0):
        da = y[4]  # off the ground the anchor follows the foot
        p_slip = 0.0
    elif slipping != 0.0:
        u = y[1] - y[8]
        s = 1.0 if u > 0.0 else (-1.0 if u < 0.0 else 0.0)
        if anchor_mode == ANCHOR_SPEC:
            dfs = k_r * d_dot if f_s > 0.0 else 0.0
            da = y[4] - s * mu * dfs / k_tan
        else:
            dfs = k_r * (d_dot - gamma * dy[7]) if f_s > 0.0 else 0.0
            da = y[4] - s * mu * dfs / k_tan
            if s * da < 0.0:
                da = 0.0  # the cone grows faster than the foot pulls: stick
        p_slip = mu * F_n * abs(da)
    else:
        da = 0.0
        p_slip = 0.0
    dy[8] = da
    dy[9] = o[10]
    dy[10] = o[13]
    dy[11] = p_slip
    return dy


@njit(cache=False, fastmath=False, error_model="numpy")
def forces_on_grid(Y, P):
    """Stroke, honeycomb force, normal force and ledger energy at each column of Y (12, M),
    the memories taken as the laws take them (max with the current value)."""
    m = Y.shape[1]
    out = np.empty((4, m))
    for j in range(m):
        o = forces(Y[0, j], Y[1, j], Y[2, j], Y[3, j], Y[4, j], Y[5, j], Y[6, j], Y[7, j],
                   Y[8, j], P)
        out[0, j] = o[3]
        out[1, j] = o[8]
        out[2, j] = o[11]
        out[3, j] = o[17] + Y[9, j] + Y[10, j] + Y[11, j]
    return out


class _Deadline(Exception):
    pass


def scipy_run(vehicle, scene, method, rtol, t_end=T_END, save_dt=SAVE_DT,
              deadline_s=RUN_DEADLINE_S, atol_scale=ATOL_SCALE,
              anchor_mode=ANCHOR_CONSISTENT) -> dict:
    """One ``solve_ivp`` landing on ``rhs`` (dense output). Wall time covers solve_ivp only.
    Peaks are taken over the accepted steps and a PEAK_GRID_DT dense-output grid."""
    _require()
    P = params_vector(vehicle, scene)
    y0 = initial_state(vehicle, scene)
    atol = rtol * np.asarray(atol_scale, dtype=float)
    t_stop = time.perf_counter() + deadline_s

    def fun(t, y):
        if time.perf_counter() > t_stop:
            raise _Deadline(f"wall-time cap {deadline_s:.0f} s exceeded at t = {t:.6g} s")
        return rhs(t, y, P, anchor_mode)

    msgs = []
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            sol = solve_ivp(fun, (0.0, t_end), y0, method=method, rtol=rtol, atol=atol,
                            dense_output=True)
            err = None
        except _Deadline as exc:
            sol, err = None, str(exc)
        except Exception as exc:  # scipy/LSODA internals: record, do not crash the benchmark
            sol, err = None, f"{type(exc).__name__}: {exc}"
    wall = time.perf_counter() - t0
    msgs = sorted({str(w.message) for w in caught})
    res = dict(wall_s=wall, warnings=msgs, atol=atol.tolist(), rtol=rtol)
    if sol is None:
        res.update(success=False, message=err)
        return res
    res.update(success=bool(sol.success) and sol.t[-1] >= t_end * (1 - 1e-12),
               message=str(sol.message), nfev=int(sol.nfev), njev=int(sol.njev),
               nlu=int(sol.nlu), n_steps=int(len(sol.t) - 1))
    if sol.sol is None or not np.all(np.isfinite(sol.y)):
        res["success"] = False
        return res
    t_hi = float(sol.t[-1])
    grid = np.arange(0.0, t_hi + 0.5 * PEAK_GRID_DT, PEAK_GRID_DT)
    grid = grid[grid <= t_hi]
    Yg = np.concatenate([sol.sol(grid), sol.y], axis=1)
    fg = forces_on_grid(np.ascontiguousarray(Yg), P)
    e_end = forces_on_grid(np.ascontiguousarray(sol.y[:, -1:]), P)[3, 0]
    e_start = forces_on_grid(np.ascontiguousarray(y0[:, None]), P)[3, 0]
    n_save = int(math.floor(t_end / save_dt + 1e-9)) + 1
    ts = np.arange(n_save) * save_dt
    ts_ok = ts[ts <= t_hi]
    Ys = sol.sol(ts_ok)
    stroke = np.full(n_save, np.nan)
    stroke[: len(ts_ok)] = [stroke_of(Ys[0, j], Ys[1, j], Ys[2, j], P)
                            for j in range(len(ts_ok))]
    y_end = sol.y[:, -1]
    res.update(
        max_stroke_m=float(max(y_end[6], np.max(fg[0]))),
        final_stroke_m=float(stroke_of(y_end[0], y_end[1], y_end[2], P)),
        peak_honeycomb_force_N=float(np.max(fg[1])),
        peak_normal_force_N=float(np.max(fg[2])),
        energy_residual_max_J=float(abs(e_end - e_start)),
        x_max_state_end_m=float(y_end[6]),
        stroke_m=stroke,
    )
    if not abs(e_end - e_start) <= ENERGY_TOLERANCE * energy_scale(P, scene):
        res["success"] = False
        res["message"] += " | energy ledger residual above tolerance"
    return res
