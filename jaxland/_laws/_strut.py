"""Main-strut axial force: honeycomb with structural damping, plus the top-out stop.

Structural damping (paper section 3.1): F_bd = D_b v_b |F_bh|, so a compressed strut carries
F_bh (1 + D_b v_b), with v_b the stroke rate (compression positive). For F_bh >= 0 the total is
floored at 0 so the damping never turns the honeycomb into a puller on fast extension; a bonded
honeycomb in tension (F_bh < 0) is damped by the same law on |F_bh|. The dissipated power
(F - F_bh) v_b is >= 0 in every regime.

Top-out stop (our assumption): the strut cannot extend beyond its rest length; for stroke x < 0 a
stiff elastic stop pulls the foot back with k_topout x.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


class StrutOut(eqx.Module):
    force: jnp.ndarray  # N, total axial force, compressive positive (what a strut load cell reads)
    damping_force: jnp.ndarray  # N, F_bd, structural damping part
    damping_power: jnp.ndarray  # W, dissipated by structural damping (>= 0)
    topout_force: jnp.ndarray  # N, top-out stop part (<= 0)
    topout_energy: jnp.ndarray  # J, elastic energy in the top-out stop


def strut_force(F_bh, x, v_b, D_b, k_topout) -> StrutOut:
    """Axial force of the main strut [N] from the honeycomb force ``F_bh`` [N], stroke ``x``
    [m], stroke rate ``v_b`` [m/s], structural damping ``D_b`` [s/m] and top-out stiffness."""
    f_raw = F_bh + D_b * v_b * jnp.abs(F_bh)
    f_total = jnp.where(F_bh >= 0.0, jnp.maximum(f_raw, 0.0), f_raw)
    f_damp = f_total - F_bh
    x_ext = jnp.minimum(x, 0.0)
    f_top = k_topout * x_ext
    return StrutOut(
        force=F_bh + f_damp + f_top,
        damping_force=f_damp,
        damping_power=f_damp * v_b,
        topout_force=f_top,
        topout_energy=0.5 * k_topout * x_ext**2,
    )
