"""The Levenberg-Marquardt optimiser on a problem with a known answer (linear least squares):
the minimum, and coordinates held fixed (``free``), which the fit uses to keep the law's
extensions at their start values through the multistart stages; and the multistart's starts
run several at a time taking the same starts as one after the other."""

import numpy as np

from calibration._fit import AGREE_REL, _until_two_agree
from calibration._optim import levenberg_marquardt


class _Linear:
    """r(theta) = A theta - b: the minimum solves the normal equations."""

    def __init__(self, seed=0):
        rng = np.random.default_rng(seed)
        self.a = rng.normal(size=(40, 4))
        self.b = rng.normal(size=40)

    def residuals(self, theta):
        return self.a @ theta - self.b, False

    def residuals_and_jacobian(self, theta):
        return self.a @ theta - self.b, self.a, False

    def values(self, theta):
        return np.asarray(theta)


def test_lm_reaches_the_least_squares_minimum():
    p = _Linear()
    theta, _, status = levenberg_marquardt(p, np.zeros(4), max_iter=100, ftol=1e-14)
    np.testing.assert_allclose(theta, np.linalg.lstsq(p.a, p.b, rcond=None)[0], rtol=1e-8)
    assert status["status"] == "converged"


def test_lm_keeps_the_coordinates_that_are_not_free():
    p = _Linear(1)
    start = np.array([0.3, -0.2, 0.7, 0.1])
    free = np.array([True, False, True, False])
    theta, hist, _ = levenberg_marquardt(p, start, max_iter=100, ftol=1e-14, free=free)
    assert np.all(theta[~free] == start[~free])
    assert all(np.all(np.asarray(h["theta"])[~free] == start[~free]) for h in hist)
    # the free ones at the minimum with the others held: lstsq on the free columns
    cond = np.linalg.lstsq(p.a[:, free], p.b - p.a[:, ~free] @ start[~free], rcond=None)[0]
    np.testing.assert_allclose(theta[free], cond, rtol=1e-8)


def _agree(losses) -> bool:
    return bool(np.sum(losses - min(losses) <= AGREE_REL * min(losses)) >= 2)


def test_the_starts_run_in_batches_take_the_starts_one_after_the_other_would():
    """``_until_two_agree`` with 2 or 3 starts at a time returns the candidates of the
    starts taken one by one until two agree on the lowest loss (written out here), in order,
    on random losses where some agree, and none of a batch's discarded starts."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        n = int(rng.integers(1, 6))
        losses = rng.choice([1.0, 1.0 + 0.5 * AGREE_REL, 1.5, 2.0, 3.0, 4.0], size=n)

        def from_start(j):
            return dict(loss=float(losses[j]), start=j)

        taken = []
        for j in range(n):
            taken.append(j)
            best = min(losses[taken])
            if np.sum(losses[taken] - best <= AGREE_REL * best) >= 2:
                break
        for threads in (1, 2, 3):
            got = [c["start"] for c in _until_two_agree(from_start, n, threads)]
            assert got == taken, (losses.tolist(), threads)
            # the batch's discarded starts, still running, are handed over where asked for
            # (in order: the fit's every-start pass takes them instead of starting them again)
            pending = []
            _until_two_agree(from_start, n, threads, pending)
            last = len(taken) - 1
            rest = list(range(last + 1, min((last // threads + 1) * threads, n))) \
                if len(taken) < n or _agree(losses[taken]) else []
            assert [f.result()["start"] for f in pending] == rest, (losses.tolist(), threads)
