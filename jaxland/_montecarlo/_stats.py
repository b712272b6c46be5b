"""Statistics of a Monte Carlo: Wilson intervals, percentiles, linear sensitivities."""

from __future__ import annotations

import math

import numpy as np

Z95 = 1.959963984540054  # two-sided 95 % standard normal quantile


def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion k/n (95 % by default)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    lo = 0.0 if k == 0 else max(0.0, centre - half)  # the bounds at k = 0 and k = n are
    hi = 1.0 if k == n else min(1.0, centre + half)  # exactly 0 and 1 (round-off aside)
    return (lo, hi)


def binomial_pmf(n: int, p: float) -> np.ndarray:
    """P(B = j), j = 0..n, for B binomial(n, p) with 0 < p < 1: from the ratio of successive
    terms, in logs (no factorial overflows; a term below float's range is 0)."""
    i = np.arange(n)
    steps = np.log((n - i) / (i + 1.0)) + math.log(p / (1.0 - p))
    return np.exp(n * math.log1p(-p) + np.concatenate([[0.0], np.cumsum(steps)]))


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(X >= k) for X binomial(n, p): the exact one-sided p-value of seeing ``k`` or more of
    ``n`` landings where each has probability ``p``."""
    if k <= 0:
        return 1.0
    if k > n or p <= 0.0:
        return 0.0
    if p >= 1.0:
        return 1.0
    # the tail's own terms, not 1 minus the others: a small tail keeps its digits
    return min(1.0, float(binomial_pmf(n, p)[k:].sum()))


def proportion(flags) -> dict:
    """How many of some landings carry a flag (a boolean array): count, n, probability (None
    over no landing: 0/0 is no probability) and its 95 % Wilson interval (None with it)."""
    k, n = int(np.sum(flags)), int(np.size(flags))
    return dict(count=k, n=n, probability=k / n if n else None,
                ci95_wilson=wilson_interval(k, n) if n else None)


# why the quarter model has no tip-over probability (a summary's tip_over["reason"])
TIP_OVER_NOT_MODELLED = ("the quarter model is one leg of a symmetric vertical drop, which "
                         "cannot tip over; model = \"full\" computes it")


def not_modelled(n: int, reason: str) -> dict:
    """``proportion``'s fields for an outcome the model cannot produce: no count, probability
    or interval (null in summary.json, never a 0 that reads as computed), ``n`` the landings it
    would be taken over, ``modelled`` false and the ``reason``."""
    return dict(modelled=False, reason=reason, count=None, n=int(n), probability=None,
                ci95_wilson=None)


def tip_over_of(model: str, tipped) -> dict:
    """The tip-over proportion of some landings (``tipped``: their flags) as a summary gives
    it: ``proportion``'s fields with ``modelled`` true for the full 3-D model; for the quarter
    model, which cannot tip, ``not_modelled``."""
    if model == "full":
        return dict(modelled=True, **proportion(tipped))
    return not_modelled(np.size(tipped), TIP_OVER_NOT_MODELLED)


def over_all_landings(p: dict, flags_unfinished, n_failed: int = 0) -> dict:
    """``p`` (a ``proportion`` over the successful landings) with ``all_landings``: where the
    probability over them, the unfinished ones and the ``n_failed`` that failed numerically
    lies (``flags_unfinished``: the flag each unfinished landing carries so far; one it has
    may stay, one it lacks may still come; a failed landing's flags are unknown). Neither is
    a sample of all (the unfinished are those still in an impact or able to tip, the failed
    the hard landings a step is too large for), so the probability over the successful ones
    alone is biased, either way. ``range`` [-] counts the unfinished as flagged as far as
    they are and the failed as not, then both as all flagged; ``ci95_wilson`` widens it by
    the Wilson intervals of both ends."""
    if p.get("modelled") is False or p["count"] is None:
        return p
    u, f = int(np.size(flags_unfinished)), int(n_failed)
    now, n = p["count"] + int(np.sum(flags_unfinished)), p["n"] + u + f
    most = p["count"] + u + f
    return dict(p, all_landings=dict(
        n=n, n_unfinished=u, n_failed=f, range=[now / n, most / n] if n else None,
        ci95_wilson=[wilson_interval(now, n)[0], wilson_interval(most, n)[1]] if n else None))


def probability_text(p: dict, nd: int = 3) -> str:
    """A probability with its 95 % interval for a report line (``p``: the summary's
    count/n/probability/ci95_wilson); a probability over no landing is none, one the model
    cannot produce (``modelled`` false) says so."""
    if p.get("modelled") is False:
        return f"not modelled: {p['reason']}"
    if p["probability"] is None:
        return "undefined (no successful landing)"
    lo, hi = p["ci95_wilson"]
    return f"{p['probability']:.{nd}g} [{lo:.{nd}g}, {hi:.{nd}g}]"


def all_landings_text(p: dict) -> str:
    """Where a probability lies with the unfinished and the failed landings
    (``over_all_landings``), to follow its report line or title; nothing where there is
    none."""
    a = p.get("all_landings")
    if not a or not (a["n_unfinished"] or a["n_failed"]):
        return ""
    (lo, hi), (clo, chi) = a["range"], a["ci95_wilson"]
    which = " and ".join(f"{k} {name}" for k, name in ((a["n_unfinished"], "unfinished"),
                                                        (a["n_failed"], "failed")) if k)
    return (f"; with the {which}: {lo:.4g} to {hi:.4g} (95% CI [{clo:.4g}, {chi:.4g}])")


PERCENTILES = (1, 5, 50, 95, 99)  # the envelopes' percentiles [%]


def percentiles(x) -> dict | None:
    """Tails and centre of a sample: p01, p05, p50, p95, p99, min, max, mean (None if empty)."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return None
    return {**{f"p{q:02d}": v for q, v in zip(PERCENTILES, np.percentile(x, PERCENTILES))},
            "min": float(np.min(x)), "max": float(np.max(x)), "mean": float(np.mean(x))}


def percentile_intervals(x) -> dict | None:
    """A 95 % interval of each of the envelopes' percentiles (``PERCENTILES``), free of any
    distribution: order statistics l and u of the sorted sample with P(l <= B < u) >= 0.95,
    B binomial(n, q) the count below the true q-quantile. ``{"p01": [lo, hi], ...}``; a bound
    the sample is too small to give is None (the p99 of 120 landings has no upper bound: all
    120 lie below it with probability 0.99^120 = 0.30). None for an empty sample."""
    x = np.sort(np.asarray(x, dtype=float))
    n = x.size
    if n == 0:
        return None
    out = {}
    for q in PERCENTILES:
        cdf = np.cumsum(binomial_pmf(n, q / 100.0))  # P(B <= j), j = 0..n
        below = int(np.searchsorted(cdf, 0.025, side="right"))  # l: P(B <= l - 1) <= 0.025
        above = int(np.searchsorted(cdf, 0.975, side="left"))  # u - 1: P(B >= u) <= 0.025
        out[f"p{q:02d}"] = [float(x[below - 1]) if below >= 1 else None,
                            float(x[above]) if above <= n - 1 else None]
    return out


# a target whose spread over the landings is at most this fraction of its size is the same in
# every landing up to rounding (a tip-over margin no dispersion moves: spread 1e-16 of 1.58 m);
# a regression on it ranks rounding noise
CONSTANT_REL = 1e-9
# the spread of an azimuth's sine or cosine that rounding alone leaves (sin 360 deg = -2.4e-16)
AZIMUTH_ROUNDING = 1e-12


def sensitivity(inputs: dict, target: np.ndarray, ok: np.ndarray,
                periods: dict | None = None) -> dict:
    """Linear regression of ``target`` [m] (a stroke or a margin) on the standardised
    dispersed inputs (per-leg inputs enter per leg): {"ranking": the change of the target per
    standard deviation of each input, ranked, with its standard error [m] and t (the effect
    over it) and the fit's R^2; "not_estimated": None, or why there is no
    ranking (too few landings ``ok``, no input dispersed, or a target the same in every
    landing up to rounding)}.

    An input with a period (``periods``: name -> period in its units, e.g. 360 for a heading
    in degrees) enters as its sine and cosine, ranked as ``name (sin)`` and ``name (cos)``:
    0 and 360 deg are one heading, which a line through the angle would read as its two
    extremes."""
    periods = periods or {}
    cols, names = [], []
    for name, arr in inputs.items():
        arr = np.asarray(arr, dtype=float)
        arr = arr[:, None] if arr.ndim == 1 else arr
        for i in range(arr.shape[1]):
            label = name if arr.shape[1] == 1 else f"{name}[leg{i}]"
            x = arr[ok, i]
            if name in periods:
                phase = 2.0 * np.pi * x / periods[name]
                parts = [(f"{label} (sin)", np.sin(phase)), (f"{label} (cos)", np.cos(phase))]
            else:
                parts = [(label, x)]
            for part, x in parts:
                # a sine or cosine that varies by rounding only (headings of 0 and 360 deg)
                # is no input: its regression would rank the rounding
                if x.size > 1 and np.std(x) > (AZIMUTH_ROUNDING if name in periods else 0.0):
                    cols.append((x - x.mean()) / x.std())
                    names.append(part)
    y = np.asarray(target, dtype=float)[ok]
    if y.size <= 1:  # before "no input varies": over no landing nothing can
        return dict(ranking=[], not_estimated=(
            f"{y.size} successful landing(s); the regression needs more than one per "
            "dispersed input and leg"))
    if not cols:
        return dict(ranking=[], not_estimated="no dispersed input varies over the successful "
                    "landings")
    if y.size <= len(cols) + 1:
        return dict(ranking=[], not_estimated=(
            f"{y.size} successful landings; the regression on {len(cols)} columns (one per "
            f"input, per leg for a per-leg input, two for an azimuth) needs at least "
            f"{len(cols) + 2}"))
    spread = float(y.max() - y.min())
    if spread <= CONSTANT_REL * float(np.abs(y).max()):
        return dict(ranking=[], not_estimated=(
            f"the target is the same in every successful landing up to rounding, a spread "
            f"of {spread:.2g} m: no dispersed input moves it"))
    X = np.column_stack([np.ones(y.size), *cols])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ coef
    r2 = 1.0 - resid.var() / y.var()
    # each effect's standard error (ordinary least squares): an effect within about two of
    # them is not told apart from none
    s2 = float(resid @ resid) / (y.size - X.shape[1])
    se = np.sqrt(s2 * np.diag(np.linalg.pinv(X.T @ X)))[1:]
    # ranked by the size of each input's effect: an azimuth's by its sine's and cosine's
    # together (sqrt of the sum of their squares), which no choice of the world's x axis
    # changes; its two rows stay side by side
    size = {}
    for n, c in zip(names, coef[1:]):
        size[_input_of(n)] = size.get(_input_of(n), 0.0) + c * c
    ranked = sorted(zip(names, coef[1:], se), key=lambda t: (-size[_input_of(t[0])],
                                                             _input_of(t[0]), -abs(t[1])))
    return dict(ranking=[dict(input=n, effect_per_std=float(c), std_error=float(e),
                              t=float(c / e) if e > 0 else None, r2_of_fit=float(r2))
                         for n, c, e in ranked], not_estimated=None)


def _input_of(row_name: str) -> str:
    """The input of a sensitivity row: an azimuth's sine and cosine rows are one input."""
    return row_name.removesuffix(" (sin)").removesuffix(" (cos)")


def ranked_inputs(ranking: list) -> list:
    """The inputs of a sensitivity ``ranking`` in its order, each once: an azimuth's sine and
    cosine rows are one input, and a per-leg row names its leg (``plateau_scale[leg2]``)."""
    return list(dict.fromkeys(_input_of(r["input"]) for r in ranking))
