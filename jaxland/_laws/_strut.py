"""Main-strut axial force: honeycomb with structural damping, plus the top-out stop.

Structural damping (paper section 3.1): F_bd = D_b v_b |F_bh|, so a compressed strut carries
F_bh (1 + D_b v_b), with v_b the stroke rate (compression positive). For F_bh >= 0 the total is
floored at 0 so the damping never turns the honeycomb into a puller on fast extension; a bonded
honeycomb in tension (F_bh < 0) is damped by the same law on |F_bh|. The dissipated power
(F - F_bh) v_b is >= 0 in every regime.

Implicit damping (for the stabilised integrators): the damping coefficient c = D_b |F_bh| acting on
the 1 kg foot sets the explicit step limit 2 m2 / c. ``strut_force(..., kick_per_mass=a,
free_rate=w)`` instead evaluates the damping at the stroke rate the foot will have after a
velocity kick of length ``kick`` (``a = kick / m2``): with ``w`` the stroke rate after the kick
from every other force (a first-order step holds the body still, it is 280 times heavier; a
second-order one adds the kick of the strut's body attachment), the rate v' solves
v' = w - a F_bd(v'); F_bd is piecewise linear and monotone in v', so v' = w / (1 + a c) unless
the floor binds. The power returned is F_bd v', the work the damping does over the kick.

Top-out stop (our assumption): the strut cannot extend beyond its rest length; for stroke x < 0 a
stiff elastic stop pulls the foot back with k_topout x.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._minmax import fmax, fmin
from ._smooth import ramp


class StrutOut(eqx.Module):
    force: jnp.ndarray  # N, total axial force, compressive positive (what a strut load cell reads)
    damping_force: jnp.ndarray  # N, F_bd, structural damping part
    damping_power: jnp.ndarray  # W, dissipated by structural damping (>= 0)
    topout_force: jnp.ndarray  # N, top-out stop part (<= 0)
    topout_energy: jnp.ndarray  # J, elastic energy in the top-out stop


def strut_force(F_bh, x, v_b, D_b, k_topout, kick_per_mass=None, free_rate=None,
                smooth_N: float = 0.0, smooth_m: float = 0.0) -> StrutOut:
    """Axial force of the main strut [N] from the honeycomb force ``F_bh`` [N], stroke ``x``
    [m], stroke rate ``v_b`` [m/s], structural damping ``D_b`` [s/m] and top-out stiffness.

    Explicit by default; with ``kick_per_mass`` [s/kg] the damping is implicit: ``free_rate``
    [m/s] is then the stroke rate after the kick from all forces on the foot except the strut's
    (see the module notes). ``smooth_N`` [N] and ``smooth_m`` [m] (static, opt-in) round the
    no-pull floor of the damped force and the top-out kink (``_smooth.ramp``)."""
    x_ext = fmin(x, 0.0) if smooth_m == 0.0 else -ramp(-x, smooth_m)
    f_top = k_topout * x_ext
    if kick_per_mass is None:
        rate = v_b
        f_raw = F_bh + D_b * v_b * jnp.abs(F_bh)
    else:
        c = D_b * jnp.abs(F_bh)
        w = free_rate - kick_per_mass * (F_bh + f_top)
        f_raw = F_bh + c * (w / (1.0 + kick_per_mass * c))
    floored = fmax(f_raw, 0.0) if smooth_N == 0.0 else ramp(f_raw, smooth_N)
    f_total = jnp.where(F_bh >= 0.0, floored, f_raw)
    f_damp = f_total - F_bh
    if kick_per_mass is not None:
        rate = w - kick_per_mass * f_damp
    return StrutOut(
        force=F_bh + f_damp + f_top,
        damping_force=f_damp,
        damping_power=f_damp * rate,
        topout_force=f_top,
        topout_energy=0.5 * k_topout * x_ext**2,
    )
