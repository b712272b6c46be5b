"""Opt-in smoothing of the contact switches (``Solver.smoothing_m`` / ``smoothing_N``).

With hard switches (max(x, 0), min, clip) every force law is continuous but kinked, and a
landing crosses the kinks at step boundaries many times (foot chatter, lift-offs, stick/slip):
the loss of a fit is then exact-but-jagged at small parameter scale and AD disagrees with finite
differences (docs/model.md section 6, ``benchmarks/gradient_quality.py``). Rounding the kinks over a
width ``w`` makes every law C1 and the loss smooth at scales below the width's.

The ramp used is exact outside (0, w): ``ramp(x, w) = max(x, 0)`` for x <= 0 and x >= w, and
x^2 (2w - x) / w^2 in between (value and slope continuous at both ends, 0 <= ramp <= x). So a
force switches on exactly where the hard one does (the contact flag, the event log and the
state machine are unchanged), it is never negative, and it differs from the hard law only
inside the band, by at most 4w/27 (at x = w/3). Polynomial, so it costs a few flops and no
transcendentals. ``w`` is a Python float, static: ``w = 0`` takes the hard code path unchanged.

The memories (largest crush, deepest pit) advance by ramp(x - memory) at each force evaluation,
so with smoothing on, how far they lag depends on how often the forces are evaluated: Verlet
evaluates twice per step, Euler once, and the smoothed model is therefore not exactly the same
across methods and steps (the lag stays below the width w).
"""

from __future__ import annotations

import jax.numpy as jnp

MAX_DEFICIT = 4.0 / 27.0  # max (x - ramp(x, w)) / w, at x = w / 3


def ramp(x, w: float):
    """C1 version of max(x, 0), exact outside (0, w) [same units as x and w]."""
    if w == 0.0:
        return jnp.maximum(x, 0.0)
    xb = jnp.clip(x, 0.0, w)  # every branch finite (no division by a variable)
    band = xb * xb * (2.0 * w - xb) / (w * w)
    return jnp.where(x >= w, x, jnp.where(x <= 0.0, 0.0, band))


def ramp_integral(x, w: float):
    """Antiderivative of ``ramp`` that vanishes for x <= 0 (elastic energies)."""
    if w == 0.0:
        xp = jnp.maximum(x, 0.0)
        return 0.5 * xp * xp
    xb = jnp.clip(x, 0.0, w)
    band = xb**3 * (8.0 * w - 3.0 * xb) / (12.0 * w * w)  # = 5 w^2 / 12 at x = w
    return jnp.where(x >= w, 0.5 * x * x - w * w / 12.0, jnp.where(x <= 0.0, 0.0, band))


def soft_min(a, b, w: float):
    """C1 version of min(a, b): a where a <= b, b where a >= b + w, between them in between."""
    return a - ramp(a - b, w)
