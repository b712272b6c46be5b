"""Two-stage aluminium honeycomb buffer (paper section 2.3, Fig. 5), with permanent crush.

The paper's virgin force-stroke curve with ideal plateaus (k_b2 = k_b4 = 0, as in its simulation):

    F_v(x) = k_b1 min(x, x_L1)                    elastic, primary
           + k_b3 clip(x - x_L2, 0, x_L3 - x_L2)   elastic, secondary
           + k_bottom max(x - x_L4, 0)             bottoming out, fully crushed stack

so F_v = F1 on [x_L1, x_L2] and F2 on [x_L3, x_L4]. The crush is permanent. We split the stroke
into a plastic set x_p and an elastic deflection y = x - x_p. The plastic set grows only on the
plateaus and is a function of the largest stroke reached, x_max:

    x_p(x_max) = clip(x_max - x_L1, 0, x_L2 - x_L1) + clip(x_max - x_L3, 0, x_L4 - x_L3).

The stack's elastic law F_e(y) is the virgin curve with its plateaus cut out: slope k_b1 up to
F1, k_b3 from F1 to F2, k_bottom above F2. Then F(x, x_max) = F_e(x - x_p(x_max)): on the virgin
curve at x = x_max, and elastic unloading/reloading below it. Both honeycomb blocks sit in series,
so unloading from the secondary stage first retraces k_b3 down to F1 and then k_b1 (this keeps
the stored elastic energy a continuous function of the state). Below the plastic set the
honeycomb never pulls (``bonded=False``) or pulls along k_b1 (``bonded=True``).

Energy (closed forms, used by the ledger):
    elastic  W(y) = integral_0^y F_e,
    crush    D(x_max) = F1 p1 + F2 p2  (plastic work of the ideal plateaus; p1, p2 the two
             clipped terms of x_p), so that integral_0^x_max F_v dx = W(y_max) + D(x_max).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._params import Honeycomb, HoneycombCurve
from ._smooth import ramp


class HoneycombOut(eqx.Module):
    force: jnp.ndarray  # N, compressive positive (F_bh in the paper)
    x_max: jnp.ndarray  # m, largest stroke reached (updated memory)
    elastic_energy: jnp.ndarray  # J, recoverable energy stored in the stack
    crush_energy: jnp.ndarray  # J, energy dissipated by plastic crushing so far
    plastic_set: jnp.ndarray  # m, permanent crush x_p


def _clip(x, lo, hi):
    return jnp.minimum(jnp.maximum(x, lo), hi)


def honeycomb_virgin_force(x, hc: Honeycomb | HoneycombCurve):
    """Virgin-curve force F_v(x) [N] at stroke x [m] (paper section 2.3), bottoming included."""
    hc = hc.curve() if isinstance(hc, Honeycomb) else hc
    return (
        hc.k_b1 * _clip(x, 0.0, hc.x_L1)
        + hc.k_b3 * _clip(x - hc.x_L2, 0.0, hc.x_L3 - hc.x_L2)
        + hc.k_bottom * jnp.maximum(x - hc.x_L4, 0.0)
    )


def honeycomb(x, x_max_prev, hc: Honeycomb | HoneycombCurve,
              smooth: float = 0.0) -> HoneycombOut:
    """Honeycomb force at stroke ``x`` [m] given the largest stroke reached so far [m].

    Returns the force (compressive positive), the updated memory ``x_max`` and the energies.
    In a time loop pass ``hc.curve()`` computed once outside it. ``smooth`` [m] (static,
    opt-in): every kink is rounded over this much stroke (``_honeycomb_smooth``).
    """
    hc = hc.curve() if isinstance(hc, Honeycomb) else hc
    if smooth != 0.0:
        return _honeycomb_smooth(x, x_max_prev, hc, smooth)
    x_max = jnp.maximum(x_max_prev, x)
    p1 = _clip(x_max - hc.x_L1, 0.0, hc.x_L2 - hc.x_L1)
    p2 = _clip(x_max - hc.x_L3, 0.0, hc.x_L4 - hc.x_L3)
    x_p = p1 + p2
    y = x - x_p
    dy3 = hc.x_L3 - hc.x_L2
    y1 = _clip(y, 0.0, hc.x_L1)
    y2 = _clip(y - hc.x_L1, 0.0, dy3)
    y3 = jnp.maximum(y - hc.x_L1 - dy3, 0.0)
    yt = jnp.minimum(y, 0.0)  # tension side, only used when bonded
    return _stack(hc, y1, y2, y3, yt, p1, p2, x_max)


def _stack(hc: HoneycombCurve, y1, y2, y3, yt, p1, p2, x_max) -> HoneycombOut:
    """Force and energies of the stack from the elastic deflections of its stages (y1, y2 and
    the bottoming y3; yt the tension side, used when bonded) and the crush of each stage."""
    force = hc.k_b1 * y1 + hc.k_b3 * y2 + hc.k_bottom * y3
    elastic = (
        0.5 * hc.k_b1 * y1**2
        + hc.F1 * y2 + 0.5 * hc.k_b3 * y2**2
        + hc.F2 * y3 + 0.5 * hc.k_bottom * y3**2
    )
    if hc.bonded:
        force = force + hc.k_b1 * yt
        elastic = elastic + 0.5 * hc.k_b1 * yt**2
    crush = hc.F1 * p1 + hc.F2 * p2
    return HoneycombOut(force, x_max, elastic, crush, p1 + p2)


def _honeycomb_smooth(x, x_max_prev, hc: HoneycombCurve, w: float) -> HoneycombOut:
    """``honeycomb`` with every kink rounded by ``_smooth.ramp`` over ``w`` [m] (C1 in x and the
    memory; exact outside the bands): the memory advances by ramp(x - x_max_prev), so it may lag
    the largest stroke by < w but never passes it; each clip(u, a, b) is ramp(u - a) - ramp(u -
    b). On a plateau reached by steps longer than w the force is exactly F1 (F2); elsewhere it
    differs from the hard law by at most max(k_b1, k_b3, k_bottom) w. The energies keep the
    hard law's closed forms, off the smoothed force's integral by O(k w^2)."""
    x_max = x_max_prev + ramp(x - x_max_prev, w)
    p1 = ramp(x_max - hc.x_L1, w) - ramp(x_max - hc.x_L2, w)
    p2 = ramp(x_max - hc.x_L3, w) - ramp(x_max - hc.x_L4, w)
    x_p = p1 + p2
    y = x - x_p
    y_2 = hc.x_L1 + hc.x_L3 - hc.x_L2  # elastic deflection at the start of the bottoming stage
    r0, r1, r2 = ramp(y, w), ramp(y - hc.x_L1, w), ramp(y - y_2, w)
    y1, y2, y3 = r0 - r1, r1 - r2, r2
    return _stack(hc, y1, y2, y3, y - r0, p1, p2, x_max)  # y - r0: min(y, 0), rounded alike
