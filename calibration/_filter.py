"""SAE J211-1 channel frequency class (CFC) filter, in numpy (for data) and in JAX (for the
model's trace inside the misfit, so the fit differentiates through it).

J211-1 (appendix C) defines the CFC filter as a two-pole Butterworth low-pass run forward and
then backward over the record (four poles, no phase shift), with the coefficients

    w_d = 2 pi CFC 2.0775,   w_a = tan(w_d T / 2),   D = 1 + sqrt(2) w_a + w_a^2
    a0 = w_a^2 / D,  a1 = 2 a0,  a2 = a0
    b1 = -2 (w_a^2 - 1) / D,  b2 = (-1 + sqrt(2) w_a - w_a^2) / D
    y[i] = a0 x[i] + a1 x[i-1] + a2 x[i-2] + b1 y[i-1] + b2 y[i-2]

(T the sample interval). The classes and their -3 dB frequencies F_H: CFC 60 (100 Hz), 180
(300 Hz), 600 (1000 Hz), 1000 (1650 Hz). J211 leaves the start of each pass open; here each
pass starts at rest on its first input value (the DC gain is 1), so a record that starts in a
steady state (free fall) is filtered without a start-up transient. The data and the model are
filtered with the same coefficients and the same start rule.

The bilinear design needs w_d T / 2 < pi / 2, i.e. a sample rate above 4.155 CFC.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["CFC_CLASSES", "DESIGN_FACTOR", "cfc_coefficients", "filtfilt_np", "filtfilt_jax",
           "IDENTITY", "noise_gain", "white_lag1", "settle_time_s", "min_rate_Hz"]

CFC_CLASSES = {60: 100.0, 180: 300.0, 600: 1000.0, 1000: 1650.0}  # class -> F_H [Hz]
DESIGN_FACTOR = 2.0775
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0, 0.0])  # (a0, a1, a2, b1, b2) of no filter


def min_rate_Hz(cfc: int) -> float:
    """The lowest sample rate the bilinear design allows for this class [Hz]."""
    return 2.0 * DESIGN_FACTOR * cfc


def cfc_coefficients(cfc: int, rate_Hz: float) -> np.ndarray:
    """(a0, a1, a2, b1, b2) of J211-1's two-pole pass for class ``cfc`` at ``rate_Hz``."""
    wd = 2.0 * math.pi * cfc * DESIGN_FACTOR
    wa = math.tan(0.5 * wd / rate_Hz)
    den = 1.0 + math.sqrt(2.0) * wa + wa * wa
    a0 = wa * wa / den
    return np.array([a0, 2.0 * a0, a0, -2.0 * (wa * wa - 1.0) / den,
                     (-1.0 + math.sqrt(2.0) * wa - wa * wa) / den])


def _pass_np(x: np.ndarray, c) -> np.ndarray:
    a0, a1, a2, b1, b2 = c
    y = np.empty_like(x)
    x1 = x2 = y1 = y2 = x[0]
    for i, xi in enumerate(x):
        v = a0 * xi + a1 * x1 + a2 * x2 + b1 * y1 + b2 * y2
        x2, x1, y2, y1 = x1, xi, y1, v
        y[i] = v
    return y


def filtfilt_np(x, coeffs) -> np.ndarray:
    """Forward then backward pass of one trace (numpy; each pass starts at rest)."""
    x = np.asarray(x, dtype=float)
    if np.array_equal(np.asarray(coeffs), IDENTITY):
        return x.copy()
    return _pass_np(_pass_np(x, coeffs)[::-1], coeffs)[::-1]


def _pass_jax(x, c):
    """One pass along the last axis of ``x`` (..., n); ``c`` (..., 5) per trace."""
    a0, a1, a2, b1, b2 = (c[..., k] for k in range(5))
    x0 = x[..., 0]

    def step(carry, xi):
        x1, x2, y1, y2 = carry
        v = a0 * xi + a1 * x1 + a2 * x2 + b1 * y1 + b2 * y2
        return (xi, x1, v, y1), v

    _, ys = jax.lax.scan(step, (x0, x0, x0, x0), jnp.moveaxis(x, -1, 0))
    return jnp.moveaxis(ys, 0, -1)


def filtfilt_jax(x, coeffs):
    """Forward then backward pass along the last axis (traceable, differentiable); ``coeffs``
    (..., 5) broadcast against ``x``'s leading axes (``IDENTITY`` rows leave a trace as is)."""
    coeffs = jnp.broadcast_to(coeffs, (*x.shape[:-1], 5))
    return _pass_jax(_pass_jax(x, coeffs)[..., ::-1], coeffs)[..., ::-1]


def _impulse_response(coeffs, n: int = 4001) -> np.ndarray:
    x = np.zeros(n)
    x[n // 2] = 1.0  # in the middle, at rest on zero: the start rule does not matter
    return filtfilt_np(x, coeffs)


def noise_gain(coeffs) -> float:
    """Std of filtered white noise of unit std (sqrt of the sum of the squared impulse
    response of the forward-backward filter)."""
    if np.array_equal(np.asarray(coeffs), IDENTITY):
        return 1.0
    return float(np.sqrt(np.sum(_impulse_response(coeffs) ** 2)))


def white_lag1(coeffs) -> float:
    """Lag-1 autocorrelation of filtered white noise (0 without a filter)."""
    if np.array_equal(np.asarray(coeffs), IDENTITY):
        return 0.0
    h = _impulse_response(coeffs)
    return float(np.sum(h[:-1] * h[1:]) / np.sum(h * h))


def settle_time_s(cfc: int) -> float:
    """Time for a pass's response to fall below 1e-4 of its start: 9.2 / (zeta w_d), the
    Butterworth pole's decay rate (zeta = 1/sqrt 2). The model is filtered over this much
    beyond the fit window, so that the window sees no end effect of the backward pass."""
    return 9.2 / (2.0 * math.pi * cfc * DESIGN_FACTOR / math.sqrt(2.0))
