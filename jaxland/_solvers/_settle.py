"""When a landing's outcomes are final: the bound behind ``Solver(early_stop=True)``.

After the impact the gear rings elastically for seconds, so "quiet" is no criterion: a tilted
landing still swings its feet between 1.4 and 4.5 kN at 1.5 s. The criterion bounds what the
remaining motion can still do, from the energy it carries.

Linearised about its rest state q_r (the memories frozen: no further crush, pit or slip),
the landing is a damped linear oscillator M q'' + C q' + K (q - q_r) = 0, whose energy

    E = 1/2 v^T M v + 1/2 (q - q_r)^T K (q - q_r)

never grows (C is positive semi-definite). Any quantity linear in the positions,
Y = Y_r + g.(q - q_r), then stays within |Y - Y_r| <= sqrt(2 E g^T K^-1 g) (Cauchy-Schwarz in
the K norm), and a rate g.v within sqrt(2 E g^T M^-1 g). Everything here is read from the model
through its contract: K and g are the derivatives of the static forces (M a at v = 0) and of the
record with respect to a displacement (``model.drift(q, delta, 1)``), M the diagonal of the
kinetic energy; E and q_r follow from one Newton step, E = KE + 1/2 f^T K^-1 f with f the static
force imbalance.

The landing is settled when, with ``ENERGY_SAFETY`` times that energy, every foot stays in
contact and sticking and no Monte Carlo outcome can pass the extreme already recorded:

- honeycomb force stays above 0 and below its strength at the memory (no further crush: the max
  stroke and the peak honeycomb force are final), and below F1 while it rests below F1 (the
  springs stay on the linear segment the bound was taken on; beyond it they only soften);
- strut force F_h (1 + D_b v_b) below its peak; ground force F_s (1 + chi d_dot) below its peak,
  and its spring force below the virgin line at the deepest penetration (no pit growth);
- tangential spring force below mu times the least normal force (no slip: the slip distance is
  final);
- body acceleration (springs and strut damping) below its peak;
- with a tilt and a stability margin in the record (3-D): the margin above its recorded minimum
  (no tip-over) and the tilt below its peak (or ``TILT_FLOOR_DEG``, if larger).

Assumptions: small motion about the rest state (the linearisation), switches that only soften
beyond the bounds checked (honeycomb plateaus, the restitution-to-virgin ground line, stick to
slip), and the hard switches (``Solver`` smoothing 0). ``ENERGY_SAFETY`` covers the remaining
nonlinearity; tests/test_early_stop.py checks on dispersed landings of both models that no
outcome changes. A landing that has tipped over never settles.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jax.scipy.linalg import cho_solve

from .._laws import honeycomb

CHECK_INTERVAL_S = 1e-2  # s between two settle checks
ENERGY_SAFETY = 2.0  # the bound is taken with this multiple of the estimated energy
# A level landing's peak tilt is round-off (1e-14 deg), which no energy bound can hold: the
# tilt is bounded by the larger of its peak and this floor [deg].
TILT_FLOOR_DEG = 1e-2

_PER_LEG = ("honeycomb_force_N", "normal_force_N", "stroke_m", "stroke_max_m",
            "tangential_force_N", "pit_depth_m")
_FOOT = ("foot_x_m", "foot_y_m", "foot_z_m", "foot_r_m")
_BODY = ("stability_margin_m", "roll_deg", "pitch_deg", "tilt_deg")


def check_steps(dt: float) -> int:
    """Steps between two settle checks."""
    return max(1, int(round(CHECK_INTERVAL_S / dt)))


def mass_diagonal(model, vehicle, state, scene, derived):
    """The diagonal of the mass matrix [kg, kg m^2] in the flattened velocities: twice the
    kinetic energy at each unit velocity (a model's kinetic energy is diagonal)."""
    v_flat, unravel = ravel_pytree(state.v)

    def kinetic(v):
        return model.kinetic_energy(vehicle, derived, unravel(v))

    return 2.0 * jax.vmap(kinetic)(jnp.eye(v_flat.shape[0], dtype=v_flat.dtype))


def settled(model, vehicle, derived, scene, s, peaks: dict, touched, upright, m_diag):
    """Whether the landing at state ``s`` (``peaks``: the running maxima so far) is settled by
    the bound of the module docstring. A scalar bool."""
    ok = conditions(model, vehicle, derived, scene, s, peaks, touched, upright, m_diag)
    return jnp.all(jnp.stack([jnp.all(c) for k, c in ok.items() if not k.startswith("_")]))


def conditions(model, vehicle, derived, scene, s, peaks: dict, touched, upright, m_diag):
    """``settled``'s conditions by name (for diagnosis)."""
    v_flat, unravel = ravel_pytree(s.v)
    n = v_flat.shape[0]
    still = eqx.tree_at(lambda x: x.v, s, unravel(jnp.zeros_like(v_flat)))

    def static(delta):
        q = model.drift(s.q, unravel(delta), 1.0)
        ev = model.evaluate(vehicle, eqx.tree_at(lambda x: x.q, still, q), scene, derived)
        acc = model.accel_record(ev.accel)
        out = {k: jnp.atleast_1d(ev.record[k]) for k in (*_PER_LEG, *_FOOT, *_BODY)
               if k in ev.record}
        out.update({k: jnp.atleast_1d(a) for k, a in acc.items() if k.startswith("body_a")})
        return m_diag * ravel_pytree(ev.accel)[0], out

    def static_twice(d):  # the values once, as output and as aux
        out = static(d)
        return out, out

    (jf, jy), (f0, y0) = jax.jacfwd(static_twice, has_aux=True)(jnp.zeros(n))
    jf = jf.T  # jf[j] = d f / d delta_j
    jy = {k: jnp.moveaxis(x, -1, 0) for k, x in jy.items()}
    K = -0.5 * (jf + jf.T)
    chol = jnp.linalg.cholesky(K)
    pd = jnp.all(jnp.isfinite(chol)) & jnp.all(jnp.diagonal(chol) > 0.0)
    chol = jnp.where(pd, chol, jnp.eye(n))  # keep the rest finite; pd decides
    d_rest = cho_solve((chol, True), f0)
    energy = ENERGY_SAFETY * (0.5 * jnp.sum(m_diag * v_flat**2) + 0.5 * jnp.dot(f0, d_rest))

    def rest(k):  # Y at the rest state and its reach sqrt(2 E g^T K^-1 g); per element of Y
        g = jy[k].reshape(n, -1)
        quad = jnp.sum(g * cho_solve((chol, True), g), axis=0)
        return (y0[k] + jnp.dot(d_rest, g).reshape(y0[k].shape),
                jnp.sqrt(2.0 * energy * jnp.maximum(quad, 0.0)).reshape(y0[k].shape))

    def rate(k):  # reach of the rate g.v: sqrt(2 E g^T M^-1 g)
        g = jy[k].reshape(n, -1)
        return jnp.sqrt(2.0 * energy * jnp.sum(g * g / m_diag[:, None], axis=0)).reshape(
            y0[k].shape)

    hc, gr, leg = vehicle.honeycomb.curve(), vehicle.ground, vehicle.leg
    ok = dict(stiffness_positive=pd, energy_finite=jnp.isfinite(energy), touched=touched,
              upright=upright)

    # honeycomb: no further crush, on its linear segment
    f_h, df_h = rest("honeycomb_force_N")
    x_max = y0["stroke_max_m"]
    strength = honeycomb(x_max, x_max, hc).force
    top = jnp.where(f_h < hc.F1, jnp.minimum(strength, hc.F1), strength)
    f_h_max = f_h + df_h
    ok.update(honeycomb_loaded=f_h - df_h > 0.0, no_crush=f_h_max < top,
              honeycomb_peak=f_h_max < peaks["peak_honeycomb_force_N"])

    # strut force with its damping at the largest stroke rate
    vb_max = rate("stroke_m")
    f_strut_max = f_h_max * (1.0 + leg.D_b * vb_max)
    ok["strut_peak"] = f_strut_max < peaks["peak_strut_force_N"]

    # ground: normal force with its damping, no pit growth, every foot sticking
    f_n, df_n = rest("normal_force_N")
    dd_max = rate("normal_force_N") / gr.k_r
    f_n_min = (f_n - df_n) * (1.0 - gr.chi * dd_max)
    ok.update(normal_peak=(f_n + df_n) * (1.0 + gr.chi * dd_max) < peaks["peak_normal_force_N"],
              in_contact=f_n_min > 0.0,
              no_pit_growth=(gr.gamma <= 0.0) | (f_n + df_n < gr.k * y0["pit_depth_m"]
                                                 / jnp.where(gr.gamma > 0.0, gr.gamma, 1.0)))
    foot_reach = 0.0
    for k in _FOOT:
        if k in y0:
            y_r, dy = rest(k)
            foot_reach = foot_reach + (jnp.abs(y_r - y0[k]) + dy) ** 2
    f_t_max = jnp.abs(y0["tangential_force_N"]) + gr.k_tan * jnp.sqrt(foot_reach)
    ok["sticking"] = f_t_max < gr.mu * f_n_min

    # body acceleration: springs, and the strut damping on the body
    accel_sq = 0.0
    for k in y0:
        if k.startswith("body_a"):
            a_r, da = rest(k)
            accel_sq = accel_sq + (jnp.abs(a_r) + da) ** 2
    damping = leg.D_b * jnp.sum(f_h_max * vb_max) / model.leg_mass(vehicle)
    ok["body_accel_peak"] = jnp.sqrt(accel_sq) + damping < peaks["peak_body_accel_mps2"]

    # 3-D: no tip-over, margin and tilt within their extremes
    if "stability_margin_m" in y0 and "peak_margin_deficit_m" in peaks:
        m_r, dm = rest("stability_margin_m")
        ok["margin"] = -(m_r - dm) < jnp.minimum(peaks["peak_margin_deficit_m"], 0.0)
    if "tilt_deg" in y0 and "peak_tilt_deg" in peaks:
        reach = 0.0
        for k in ("roll_deg", "pitch_deg"):
            y_r, dy = rest(k)
            reach = reach + jnp.abs(y_r - y0[k]) + dy
        ok["tilt_peak"] = y0["tilt_deg"] + reach < jnp.maximum(peaks["peak_tilt_deg"],
                                                                TILT_FLOOR_DEG)
    ok["_energy_J"] = energy / ENERGY_SAFETY  # diagnostics
    return ok
