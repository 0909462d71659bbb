"""jsgs.bench.stats.median_interval: the order statistics chosen, their exact coverage, and that coverage
against a simulation."""

from __future__ import annotations

import numpy as np
import pytest

from jsgs.bench.stats import median_interval


@pytest.mark.parametrize(
    ("n", "j", "coverage"),
    [
        (1, 1, 0.0),  # one value: a point, no coverage
        (5, 1, 1 - 2 / 32),  # below 6 values even (min, max) misses 95 %
        (6, 1, 1 - 2 / 64),
        (9, 2, 1 - 2 * (1 + 9) / 512),  # the textbook (x_(2), x_(8))
        (20, 6, 0.9586105346679688),  # the textbook (x_(6), x_(15))
    ],
)
def test_order_statistics_and_coverage(n: int, j: int, coverage: float) -> None:
    values = [float(v) for v in np.random.default_rng(n).permutation(n) + 1]  # 1..n, shuffled
    lo, hi, cov = median_interval(values)
    assert (lo, hi) == (float(j), float(n + 1 - j))
    assert cov == pytest.approx(coverage, abs=1e-12)
    assert cov >= 0.95 or j == 1


def test_coverage_holds_on_a_skewed_distribution() -> None:
    # 7 draws from a lognormal (median e^0 = 1): (min, max) of 7 covers the median with 1 - 2/128 = 0.984
    rng = np.random.default_rng(0)
    draws = rng.lognormal(0.0, 0.5, size=(20000, 7))
    hits = [median_interval(list(row))[:2] for row in draws]
    covered = np.mean([lo <= 1.0 <= hi for lo, hi in hits])
    assert covered == pytest.approx(1 - 2 / 128, abs=0.004)


def test_no_values_is_an_error() -> None:
    with pytest.raises(ValueError, match="no values"):
        median_interval([])
