"""Statistics behind every "k/n [lo, hi]" the docs print: jl.wilson_interval against the closed
form, and its exact binomial coverage at small p, where a Wald interval fails.

References, independent of the code under test:
- the Wilson score interval is the set of p0 with |k/n - p0| <= z sqrt(p0 (1 - p0) / n)
  (Wilson 1927); its ends are the roots of the quadratic
  (1 + z^2/n) p0^2 - (2 k/n + z^2/n) p0 + (k/n)^2 = 0, solved here with numpy.roots;
- at k = 0 the upper end is z^2 / (n + z^2): 0/300 -> 0.012643 (the README's design table);
- coverage is exact: sum over k of Binomial(n, p) probabilities of the k whose interval holds p
  (no sampling, so no sampling band to hide a wrong interval in).
"""

import math
from statistics import NormalDist

import numpy as np
import pytest

import jaxland as jl

Z95 = NormalDist().inv_cdf(0.975)  # 1.959963984540054


def _wilson_roots(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Ends of {p0 : (k/n - p0)^2 <= z^2 p0 (1 - p0) / n}: roots of a quadratic in p0."""
    ph = k / n
    a = 1.0 + z * z / n
    b = -(2.0 * ph + z * z / n)
    c = ph * ph
    r = np.sort(np.real(np.roots([a, b, c])))
    return max(0.0, float(r[0])), min(1.0, float(r[1]))


def _binom_pmf(n: int, p: float) -> np.ndarray:
    k = np.arange(n + 1)
    logc = np.array([math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) for i in k])
    with np.errstate(divide="ignore"):
        return np.exp(logc + k * np.log(p) + (n - k) * np.log1p(-p))


def _coverage(interval, n: int, p: float) -> float:
    """Exact probability that the interval of k ~ Binomial(n, p) contains p."""
    pmf = _binom_pmf(n, p)
    hit = np.array([lo <= p <= hi for lo, hi in (interval(k, n) for k in range(n + 1))])
    return float(np.sum(pmf[hit]))


def _wald(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    ph = k / n
    half = z * math.sqrt(ph * (1 - ph) / n)
    return max(0.0, ph - half), min(1.0, ph + half)


@pytest.mark.parametrize("k,n,lo,hi", [
    (0, 300, 0.0, 0.012643),  # README design table: 0/300 = 0 [0, 0.0126]
    (1, 300, 0.000589, 0.018637),  # README design table: 1/300 [0.000589, 0.0186]
])
def test_wilson_bounds_quoted_in_the_docs(k, n, lo, hi):
    got = jl.wilson_interval(k, n)
    assert got[0] == pytest.approx(lo, abs=5e-7)
    assert got[1] == pytest.approx(hi, abs=5e-7)


def test_wilson_zero_successes_upper_bound_is_z2_over_n_plus_z2():
    """k = 0: the interval is [0, z^2 / (n + z^2)] exactly (the bound every 0/n in the docs
    uses); the lower end is exactly 0, and k = n mirrors it."""
    for n in (10, 50, 300, 2000):
        lo, hi = jl.wilson_interval(0, n)
        assert lo == 0.0
        assert hi == pytest.approx(Z95**2 / (n + Z95**2), rel=1e-12)
        lo_n, hi_n = jl.wilson_interval(n, n)
        assert hi_n == 1.0
        assert lo_n == pytest.approx(n / (n + Z95**2), rel=1e-12)


@pytest.mark.parametrize("n", [7, 50, 300])
def test_wilson_interval_equals_the_roots_of_the_score_quadratic(n):
    for k in range(n + 1):
        got = jl.wilson_interval(k, n)
        ref = _wilson_roots(k, n)
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12, err_msg=f"{k}/{n}")
    # another level: z is honoured (90 %)
    z90 = NormalDist().inv_cdf(0.95)
    np.testing.assert_allclose(jl.wilson_interval(3, 40, z90), _wilson_roots(3, 40, z90),
                               rtol=1e-9)


# Small-p grid. The score interval's exact coverage oscillates in p (the binomial is
# discrete): on this grid the reference gives 0.910 (n = 50, p = 0.01) to 0.977 (n = 300,
# p = 0.002). Wald's coverage here is 0.22-0.80.
SMALL_P = [(50, 0.005), (50, 0.01), (50, 0.02), (100, 0.005), (100, 0.01), (300, 0.002),
           (300, 0.005), (300, 0.01)]


def test_wilson_coverage_at_small_p_where_wald_fails():
    """Exact coverage at small p (the tip-over and bottoming probabilities the Monte Carlo
    reports are this small). The Wald interval p +/- z sqrt(p (1 - p) / n), the classic wrong
    one, covers < 0.85 on the whole grid (at k = 0 it is [0, 0]); Wilson's covers within
    [0.90, 0.985]: not too short (a dropped z^2/4n^2 term gives 0.61-0.87 here) and not padded
    (an interval centred on k/n instead of the score centre over-covers, 0.9991-1.0 at
    p <= 0.005), and equals the reference's coverage."""
    for n, p in SMALL_P:
        wald = _coverage(_wald, n, p)
        assert wald < 0.85, (n, p, wald)  # the reference discriminates
        ref = _coverage(_wilson_roots, n, p)
        got = _coverage(jl.wilson_interval, n, p)
        assert 0.90 <= got <= 0.985, (n, p, got)
        assert got == pytest.approx(ref, abs=1e-9), (n, p)


def test_wilson_mean_coverage_is_nominal():
    """Averaged over p in [0.01, 0.3] (n = 50), Wilson's coverage is 0.95 +/- 0.01 (its known
    property: near-nominal on average, Brown, Cai & DasGupta 2001; the reference gives 0.952).
    Wald's is 0.893; without the z^2/4n^2 term 0.905; centred on k/n 0.938."""
    ps = np.linspace(0.01, 0.3, 59)
    wilson = np.mean([_coverage(jl.wilson_interval, 50, p) for p in ps])
    wald = np.mean([_coverage(_wald, 50, p) for p in ps])
    assert abs(wilson - 0.95) < 0.01, wilson
    assert wald < 0.92, wald


def test_a_probability_over_no_landing_is_reported_as_none():
    """0/0 is no probability: the summaries say None and the reports say so in words, where
    they used to print 0."""
    from jaxland._montecarlo import probability_text

    assert probability_text(dict(count=0, n=0, probability=None,
                                 ci95_wilson=jl.wilson_interval(0, 0))) == \
        "undefined (no successful landing)"
    p = dict(count=3, n=10, probability=0.3, ci95_wilson=jl.wilson_interval(3, 10))
    assert probability_text(p) == "0.3 [0.108, 0.603]"


def test_percentile_intervals_are_the_order_statistics_the_binomial_law_gives():
    """Each envelope percentile's 95 % interval: the order statistics l, u with P(B <= l - 1)
    <= 0.025 and P(B >= u) <= 0.025 for B binomial(n, q), found here by exact rational sums;
    a bound past the sample is None; and over 400 normal samples of 100 each interval holds
    the true quantile at least 94 % of the time."""
    from fractions import Fraction
    from math import comb
    from statistics import NormalDist

    from jaxland._montecarlo._stats import PERCENTILES, percentile_intervals

    rng = np.random.default_rng(3)
    for n in (7, 60, 120, 333):
        x = rng.normal(size=n)
        got = percentile_intervals(x)
        xs = np.sort(x)
        for q in PERCENTILES:
            p = Fraction(q, 100)
            cdf = [sum(comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(j + 1))
                   for j in range(n + 1)]
            below = sum(1 for c in cdf if c <= Fraction(1, 40))
            above = next(j for j, c in enumerate(cdf) if c >= Fraction(39, 40))
            want = [float(xs[below - 1]) if below >= 1 else None,
                    float(xs[above]) if above <= n - 1 else None]
            assert got[f"p{q:02d}"] == want, (n, q)
    assert percentile_intervals(rng.normal(size=120))["p99"][1] is None  # 0.99^120 = 0.30
    assert percentile_intervals([]) is None
    truth = {f"p{q:02d}": NormalDist().inv_cdf(q / 100) for q in PERCENTILES}
    held = dict.fromkeys(truth, 0)
    for _ in range(400):
        iv = percentile_intervals(rng.normal(size=100))
        for k, t in truth.items():
            lo, hi = iv[k]
            held[k] += (lo is None or lo <= t) and (hi is None or t <= hi)
    assert all(h / 400 >= 0.94 for h in held.values()), held
