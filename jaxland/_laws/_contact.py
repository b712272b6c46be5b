"""Foot-ground contact: bi-stiffness normal spring with a permanent pit, tangential stick/slip.

Normal (paper section 2.2, Eq. 4): loading on the virgin line with stiffness k, restitution with
k_r = k / (1 - gamma). We write it as a rate-independent elastic-plastic law with one memory, the
deepest penetration d_max reached (penetration d is measured below the original ground surface):

    F_s = max(0, k_r (d - gamma d_max)),   d_max <- max(d_max, d).

At d = d_max this is k d (compression); below d_max it is the restitution line, which ends at the
pit depth gamma d_max. A fraction gamma of the stored energy is lost per loading (energetic
restitution coefficient sqrt(1 - gamma)), and a later impact starts from the pit, reloading along
k_r until it passes the old depth. Nothing is reset on lift-off (resets make losses
discontinuous, docs/model.md section 6). Damping multiplies by (1 + chi d_dot), d_dot the
penetration rate, floored at 0 so the ground never pulls.

Tangential (paper sections 2.2.2-2.2.4): two springs k_tan on the tangent plane between the foot
and an anchor point on the ground. Stick while k_tan |u| <= mu F_n (the paper's energy test
E_x + E_y < mu^2 (k/k_tan) E_zs (1 + chi z_dot)^2 is the same inequality), otherwise slip: the
anchor is dragged so that k_tan |u| = mu F_n (a return map, exact for Coulomb's law). Off the
ground F_n = 0, so the anchor follows the foot.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._params import Ground
from ._minmax import fmax
from ._smooth import ramp, ramp_integral, soft_min


def safe_sqrt(x2):
    """sqrt(x2) for x2 >= 0 with a finite gradient (0) at zero: both branches of the ``where``
    are finite there."""
    pos = x2 > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x2, 1.0)), 0.0)


def safe_hypot(x, y):
    """sqrt(x^2 + y^2) with a finite gradient at zero, on separate components (no reduction)."""
    return safe_sqrt(x * x + y * y)


class NormalOut(eqx.Module):
    force: jnp.ndarray  # N, ground normal force on the foot, >= 0
    spring_force: jnp.ndarray  # N, F_s before damping
    d_max: jnp.ndarray  # m, deepest penetration reached (updated memory)
    pit_depth: jnp.ndarray  # m, gamma d_max
    elastic_energy: jnp.ndarray  # J
    plastic_energy: jnp.ndarray  # J, dissipated by ground plasticity so far, gamma k d_max^2 / 2
    damping_power: jnp.ndarray  # W, dissipated by contact damping (>= 0)


def normal_contact(d, d_dot, d_max_prev, ground: Ground, k_r=None,
                   smooth: float = 0.0) -> NormalOut:
    """Normal ground force [N] at penetration ``d`` [m] (below the original surface) and
    penetration rate ``d_dot`` [m/s], with memory ``d_max_prev`` [m]. ``k_r`` is the
    restitution stiffness k / (1 - gamma); pass it precomputed in a time loop. ``smooth`` [m]
    (static, opt-in): the spring's on/off kink is rounded over this much of the spring's
    compression, and the virgin/restitution kink over this much penetration beyond the memory
    (``_smooth.ramp``; exact elsewhere; within the bands the spring is softer by at most
    k_r smooth)."""
    k_r = ground.k_r if k_r is None else k_r
    if smooth == 0.0:
        d_max = fmax(d, d_max_prev)
        e = fmax(d - ground.gamma * d_max, 0.0)
        elastic = 0.5 * k_r * e**2
    else:  # the memory advances by ramp(d - d_max_prev) <= max(., 0): it may lag, never creeps
        d_max = d_max_prev + ramp(d - d_max_prev, smooth)
        raw = d - ground.gamma * d_max
        e = ramp(raw, smooth)
        elastic = k_r * ramp_integral(raw, smooth)
    f_s = k_r * e
    factor = fmax(1.0 + ground.chi * d_dot, 0.0)
    f_n = f_s * factor
    return NormalOut(
        force=f_n,
        spring_force=f_s,
        d_max=d_max,
        pit_depth=ground.gamma * d_max,
        elastic_energy=elastic,
        plastic_energy=0.5 * ground.gamma * ground.k * d_max**2,
        damping_power=(f_n - f_s) * d_dot,
    )


class TangentialOut(eqx.Module):
    force: tuple  # N, (f_x, f_y) tangential force on the foot
    anchor: tuple  # m, (x, y) updated anchor (stick point) on the ground
    slipping: jnp.ndarray  # bool, Coulomb limit reached while in contact
    slip: jnp.ndarray  # m, distance the anchor moved (slip) in this evaluation
    elastic_energy: jnp.ndarray  # J
    slip_energy: jnp.ndarray  # J, dissipated by this slip increment


def tangential_contact(foot_t, anchor_prev, normal_force, ground: Ground,
                       smooth: float = 0.0, force_prev=None) -> TangentialOut:
    """Tangential force [N] on the foot at tangent-plane position ``foot_t = (x, y)`` [m], given
    the previous anchor ``(x, y)`` [m] and the current normal force [N]. ``smooth`` [m]
    (static, opt-in): the stick/slip switch is rounded over this much spring stretch beyond the
    Coulomb limit (exact stick below it, exact slip beyond limit + smooth; between them the
    force exceeds mu F_n by at most 0.15 k_tan smooth).

    Tangent-plane vectors are (x, y) pairs of arrays rather than arrays of shape (2,): written on
    components, the law fuses with the rest of a step (a (2,)-vector form with its norm
    reduction made the whole landing ~4x slower on CPU).

    ``force_prev`` [N]: the spring force's magnitude after the previous evaluation's return
    map. Given, the slip energy is the trapezoid (force_prev + force) / 2 x slip, which is what
    a trapezoidal (Verlet) step's work less the spring's energy change leaves, so the ledger
    closes at second order; without it, the force after the slip times the slip (first order).
    """
    ux = foot_t[0] - anchor_prev[0]
    uy = foot_t[1] - anchor_prev[1]
    n = safe_hypot(ux, uy)
    limit = ground.mu * normal_force
    # no normal force holds no stretch: the anchor follows the foot, also where the stretch is
    # exactly 0 (a foot in the air without sideways motion), whose stick branch would give the
    # force, 0 for every stretch, the derivative of a spring
    slipping = (ground.k_tan * n > limit) | ~(limit > 0.0)
    if smooth == 0.0:
        moved = slipping & (n > 0.0)  # n = 0 slips only without a normal force: scale 0
        scale = jnp.where(slipping, limit / (ground.k_tan * jnp.where(moved, n, 1.0)), 1.0)
    else:  # stretch kept: min(n, limit / k_tan), rounded; 0 <= n_kept <= n
        n_kept = soft_min(n, limit / ground.k_tan, smooth)
        pos = n > 0.0
        scale = jnp.where(pos, n_kept / jnp.where(pos, n, 1.0), 1.0)
    ux, uy = ux * scale, uy * scale
    in_contact = normal_force > 0.0
    slip = jnp.where(in_contact, n * (1.0 - scale), 0.0)  # off the ground it is not slip
    return TangentialOut(
        force=(-ground.k_tan * ux, -ground.k_tan * uy),
        anchor=(foot_t[0] - ux, foot_t[1] - uy),
        slipping=slipping & in_contact,
        slip=slip,
        elastic_energy=0.5 * ground.k_tan * (ux * ux + uy * uy),
        slip_energy=(ground.k_tan * n * scale * slip if force_prev is None
                     else 0.5 * (force_prev + ground.k_tan * n * scale) * slip),
    )
