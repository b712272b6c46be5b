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

Optional extensions (``Honeycomb.peak_ratio1/2``, ``peak_length1/2``, ``peak_rise1``,
``excess1``, ``excess_length1``, ``unload_ratio``), all off by default (None): the law above
then runs on its own code path, bit for bit.

Initial crush peak (virgin material only). A bare honeycomb block resists the start of crushing
more than its plateau: the elastic rise of stage i continues to r_i F_i (a_i = (r_i - 1) F_i over
the plateau, at the stroke x_pk = x_L1 + a1 / k_b1, resp. x_L3 + a2 / k_b3), then the force falls
linearly back to the plateau over the crush length L_i:

    strength  S_i(x_max) = F_i + e_i,   e_i = a_i (1 - clip(x_max - x_pk, 0, L_i) / L_i).

The strength is a function of the largest stroke reached, so a block unloaded and reloaded takes
the elastic line back up to S_i(x_max) (not to the peak again) and, past x_max, continues on the
decaying (or already flat) virgin curve: once crushed, there is no peak. The elastic deflection of
a stage at its strength is S_i / k, so the plastic set is x_max - (its elastic deflection):
p1 = clip(x_max - x_L1 - e1 / k_b1, 0, x_L2 - x_L1), which grows faster than x_max while the
force falls (that is the crush). The falling branch is a negative tangent stiffness -a_i / L_i;
``validate_vehicle`` bounds it by half the ground stiffness so the foot cannot snap through.
The peak's extra crush work (closed form, added to D) is

    (a_i^2 - e_i^2) / (2 k) + a_i c (1 - c / (2 L_i)),   c = clip(x_max - x_pk, 0, L_i),

with k = k_b1 for the primary stage and k_u (below) for the secondary.

Tabulated strength excess of the primary stage (``Honeycomb.excess1``, ``excess_length1``):
the linear fall above replaced by any shape, a table of excess values e_j at the crush
c_j = j dc (dc = L / n), piecewise linear between them and 0 from c = L on. With a = e_0 the
elastic rise goes to F1 + a at x_pk = x_L1 + a / k_b1, and from there the strength is
S1(x_max) = F1 + e(c), c = clip(x_max - x_pk, 0, L); written without a gather as

    e(c) = a + sum_j s_j u_j,   u_j = clip(c - c_j, 0, dc),   s_j = (e_{j+1} - e_j) / dc.

The plastic set p1 = x_max - x_L1 - e / k_b1 grows with x_max while e rises slower than k_b1
(``validate_vehicle``), and the crush work beyond the plateau's is the integral of the strength
over the plastic set, exact in closed form for the piecewise-linear e:

    (a^2 - e^2) / (2 k_b1) + a c + sum_j s_j (u_j^2 / 2 + dc max(c - c_j - dc, 0)),

which for a two-node table (a, 0) over L is the linear peak's work above. A curve that also
carries the node values e(c_j) and integrals (``HoneycombCurve.t1_e``, ``t1_int``; calibration's
peak forms) is read, unsmoothed, at the one segment that holds c: e = e_j + s_j (c - c_j) and
the integral likewise, the same numbers without a sum over every segment.

A peak that builds up (``Honeycomb.peak_rise1`` = L_r, with peak_ratio1): the elastic rise
ends at F1 (a = 0 at the onset x_L1), the strength rises linearly to r1 F1 over the crush L_r,
then falls to F1 over peak_length1: the table's law with two segments, of widths L_r and L.
With ``excess1`` instead of peak_ratio1 the build-up goes from 0 to e_0 over L_r and the table
follows: one segment of width L_r before the table's n.

Unloading after the secondary stage (``unload_ratio`` = rho >= 1). The secondary stage's elastic
stiffness is k_u = rho k_b3 while its virgin rise keeps the slope k_b3: for rho > 1 the fraction
q = 1 - 1/rho of the rise is plastic set (p_rise = q clip(x_max - x_L2, 0, x_pk2 - x_L2), crush
work q (F1 v + k_b3 v^2 / 2) over the rise v), and a crushed stack unloads along k_u down to F1,
then along k_b1. rho = 1 is the law above; rho = k_b1 / k_b3 unloads the whole stack along the
single stiffness k_b1.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._params import Honeycomb, HoneycombCurve
from ._minmax import fclip, fmax, fmin
from ._smooth import ramp


class HoneycombOut(eqx.Module):
    force: jnp.ndarray  # N, compressive positive (F_bh in the paper)
    x_max: jnp.ndarray  # m, largest stroke reached (updated memory)
    elastic_energy: jnp.ndarray  # J, recoverable energy stored in the stack
    crush_energy: jnp.ndarray  # J, energy dissipated by plastic crushing so far
    plastic_set: jnp.ndarray  # m, permanent crush x_p


def honeycomb_virgin_force(x, hc: Honeycomb | HoneycombCurve):
    """Virgin-curve force F_v(x) [N] at stroke x [m] (paper section 2.3), bottoming included."""
    hc = hc.curve() if isinstance(hc, Honeycomb) else hc
    if hc.extended:  # the initial peaks, written independently of the memory law (tests)
        return (
            hc.k_b1 * fclip(x, 0.0, hc.x_L1)
            + jnp.minimum(hc.k_b1 * jnp.maximum(x - hc.x_L1, 0.0),
                          _excess(x, hc.a1, hc.x_pk1, hc.L1) if hc.t1_c is None else
                          _table(_crushed(x, hc.x_pk1, hc.L1), hc, 0.0)[0])
            + hc.k_b3 * fclip(x - hc.x_L2, 0.0, hc.x_L3 - hc.x_L2)
            + jnp.minimum(hc.k_b3 * jnp.maximum(x - hc.x_L3, 0.0),
                          _excess(x, hc.a2, hc.x_pk2, hc.L2))
            + hc.k_bottom * jnp.maximum(x - hc.x_L4, 0.0)
        )
    return (
        hc.k_b1 * fclip(x, 0.0, hc.x_L1)
        + hc.k_b3 * fclip(x - hc.x_L2, 0.0, hc.x_L3 - hc.x_L2)
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
    if hc.extended:
        return _honeycomb_extended(x, x_max_prev, hc, smooth)
    if smooth != 0.0:
        return _honeycomb_smooth(x, x_max_prev, hc, smooth)
    x_max = fmax(x, x_max_prev)
    p1 = fclip(x_max - hc.x_L1, 0.0, hc.x_L2 - hc.x_L1)
    p2 = fclip(x_max - hc.x_L3, 0.0, hc.x_L4 - hc.x_L3)
    x_p = p1 + p2
    y = x - x_p
    dy3 = hc.x_L3 - hc.x_L2
    y1 = fclip(y, 0.0, hc.x_L1)
    y2 = fclip(y - hc.x_L1, 0.0, dy3)
    y3 = fmax(y - hc.x_L1 - dy3, 0.0)
    yt = fmin(y, 0.0)  # tension side, only used when bonded
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


# ------------------------------------------------------------- crush peaks, unloading stiffness
# The general law (module docstring), taken when ``hc.extended`` (static): a separate code path,
# so that the paper's law above keeps its exact expression graph (XLA contracts multiply-adds
# into FMAs, so even exact "+ 0.0" terms would change the last bits of a jitted landing).

def _crushed(x_max, x_pk, length, w: float = 0.0):
    """clip(x_max - x_pk, 0, L) [m]: crush past the peak's stroke, rounded over ``w`` if > 0."""
    if w == 0.0:
        return fclip(x_max - x_pk, 0.0, length)
    return ramp(x_max - x_pk, w) - ramp(x_max - x_pk - length, w)


def _excess(x_max, a, x_pk, length, w: float = 0.0):
    """Strength over the plateau left of a peak a [N]: a (1 - clip(x_max - x_pk, 0, L) / L)."""
    return a - a * _crushed(x_max, x_pk, length, w) / length


def _table(c, hc: HoneycombCurve, w: float):
    """The primary's tabulated excess e(c) [N] at the crush c [m] past its onset, and the
    integral of e over [0, c] [J]; the table's kinks rounded over ``w`` [m] if > 0."""
    d = jnp.expand_dims(c, -1) - hc.t1_c
    if w == 0.0:
        over = jnp.maximum(d - hc.t1_dc, 0.0)
        u = jnp.minimum(jnp.maximum(d, 0.0), hc.t1_dc)
    else:  # the interior nodes rounded; c, clipped to [0, L] (rounded), needs no clip at the ends
        dc = hc.t1_dc[..., :-1] if hc.t1_dc.shape[-1] > 1 else hc.t1_dc  # uniform: one
        over = jnp.concatenate([ramp(d[..., :-1] - dc, w), jnp.zeros_like(d[..., :1])], axis=-1)
        u = jnp.concatenate([d[..., :1], ramp(d[..., 1:], w)], axis=-1) - over
    e = hc.a1 + jnp.sum(hc.t1_slope * u, axis=-1)
    integral = hc.a1 * c + jnp.sum(hc.t1_slope * (0.5 * u * u + hc.t1_dc * over), axis=-1)
    return e, integral


def _table_at(c, hc: HoneycombCurve):
    """``_table`` (unsmoothed) from the segment that holds c, with the node values and
    integrals ``t1_e``, ``t1_int``: e = e_j + s_j v and its integral I_j + e_j v + s_j v^2 / 2,
    v = c - c_j, j the last segment starting at or before c (c in [0, L], so j >= 0; at a
    zero-width segment's start the later one, whose v is 0). The work per derivative
    direction does not grow with the table's length."""
    shape = jnp.broadcast_shapes(jnp.shape(c), hc.t1_c.shape[:-1])
    n = hc.t1_c.shape[-1]
    j = jnp.sum(jnp.expand_dims(c, -1) >= hc.t1_c, axis=-1) - 1
    idx = jnp.broadcast_to(jnp.expand_dims(jnp.clip(j, 0, n - 1), -1), shape + (1,))

    def at(t):
        return jnp.take_along_axis(jnp.broadcast_to(t, shape + (n,)), idx, axis=-1)[..., 0]

    v = c - at(hc.t1_c)
    e_j, s_j = at(hc.t1_e), at(hc.t1_slope)
    return e_j + s_j * v, at(hc.t1_int) + e_j * v + 0.5 * s_j * v * v


def _primary_table(c, hc: HoneycombCurve, w: float):
    """The primary's tabulated excess and its integral at the crush c (``_table``): read at the
    one segment that holds c (``_table_at``) where the curve carries its node values and no
    kink is rounded (``w`` = 0), else summed over every segment."""
    return _table_at(c, hc) if hc.t1_e is not None and w == 0.0 else _table(c, hc, w)


def primary_peak_excess(c, hc: Honeycomb | HoneycombCurve):
    """The primary stage's crush-peak excess over its plateau, e(c) [N], at the crush c [m]
    past the peak's onset: the law's linear fall a1 (1 - c / L1), or its table (a build-up
    included), 0 from the peak's end on and without a primary peak. Pure, like the law."""
    hc = hc.curve() if isinstance(hc, Honeycomb) else hc
    if not hc.extended:
        return jnp.zeros_like(c)
    if hc.t1_c is None:
        return _excess(c, hc.a1, 0.0, hc.L1)
    # c of any shape, one element at a time against the table's nodes (as the law reads it)
    return jnp.vectorize(lambda ci: _primary_table(_crushed(ci, 0.0, hc.L1), hc, 0.0)[0])(c)


def _peak_work(a, e, c, length, k):
    """Crush work of a peak beyond the plateau's [J]: (a^2 - e^2) / (2k) + a c (1 - c / 2L)."""
    return (a * a - e * e) / (2.0 * k) + a * c * (1.0 - c / (2.0 * length))


def _honeycomb_extended(x, x_max_prev, hc: HoneycombCurve, w: float) -> HoneycombOut:
    """``honeycomb`` with the initial crush peaks and the secondary unloading stiffness; ``w``
    [m] > 0 rounds every kink with ``ramp`` as ``_honeycomb_smooth`` does (energies: the hard
    law's closed forms, evaluated on the rounded clips)."""
    dy3 = hc.x_L3 - hc.x_L2
    if w == 0.0:
        x_max = jnp.maximum(x_max_prev, x)
        c_1, c_2 = _crushed(x_max, hc.x_pk1, hc.L1), _crushed(x_max, hc.x_pk2, hc.L2)
    else:
        x_max = x_max_prev + ramp(x - x_max_prev, w)
        c_1, c_2 = _crushed(x_max, hc.x_pk1, hc.L1, w), _crushed(x_max, hc.x_pk2, hc.L2, w)
    if hc.t1_c is None:
        e1 = hc.a1 - hc.a1 * c_1 / hc.L1  # strength left over F1 (the peak fades as it crushes)
        work1 = _peak_work(hc.a1, e1, c_1, hc.L1, hc.k_b1)
    else:  # the tabulated excess
        e1, int1 = _primary_table(c_1, hc, w)
        work1 = (hc.a1 * hc.a1 - e1 * e1) / (2.0 * hc.k_b1) + int1
    e2 = hc.a2 - hc.a2 * c_2 / hc.L2
    cap1 = hc.x_L1 + e1 / hc.k_b1  # elastic capacity of stage 1: strength / k_b1
    cap2 = dy3 * (1.0 - hc.q) + e2 / hc.k_u  # of stage 2: (F2 - F1 + e2) / k_u
    # plastic set: x_max less the elastic deflection at the strength reached, per stage
    u1 = x_max - cap1  # primary crush, to x_L2 - x_L1
    u2 = x_max - hc.x_pk2 + (hc.a2 - e2) / hc.k_u  # secondary plateau crush
    top2 = hc.x_L4 - hc.x_pk2 + hc.a2 / hc.k_u
    if w == 0.0:
        p1 = fclip(u1, 0.0, hc.x_L2 - hc.x_L1)
        rise = fclip(x_max - hc.x_L2, 0.0, hc.x_pk2 - hc.x_L2)
        p2 = fclip(u2, 0.0, top2)
    else:
        p1 = ramp(u1, w) - ramp(u1 - (hc.x_L2 - hc.x_L1), w)
        rise = ramp(x_max - hc.x_L2, w) - ramp(x_max - hc.x_pk2, w)
        p2 = ramp(u2, w) - ramp(u2 - top2, w)
    x_p = p1 + hc.q * rise + p2
    y = x - x_p
    if w == 0.0:
        y1 = fclip(y, 0.0, cap1)
        y2 = fclip(y - cap1, 0.0, cap2)
        y3 = jnp.maximum(y - cap1 - cap2, 0.0)
        yt = jnp.minimum(y, 0.0)
    else:
        r0, r1, r2 = ramp(y, w), ramp(y - cap1, w), ramp(y - cap1 - cap2, w)
        y1, y2, y3, yt = r0 - r1, r1 - r2, r2, y - r0
    force = hc.k_b1 * y1 + hc.k_u * y2 + hc.k_bottom * y3
    elastic = (
        0.5 * hc.k_b1 * y1**2
        + (hc.F1 + e1) * y2 + 0.5 * hc.k_u * y2**2
        + (hc.F2 + e1 + e2) * y3 + 0.5 * hc.k_bottom * y3**2
    )
    if hc.bonded:
        force = force + hc.k_b1 * yt
        elastic = elastic + 0.5 * hc.k_b1 * yt**2
    crush = (hc.F1 * p1 + work1
             + hc.q * (hc.F1 * rise + 0.5 * hc.k_b3 * rise**2)
             + hc.F2 * p2 + _peak_work(hc.a2, e2, c_2, hc.L2, hc.k_u))
    return HoneycombOut(force, x_max, elastic, crush, x_p)
