"""The statistics of a bench's rows: per scene × schedule × method the mean over seeds and its spread,
the final (or a common) evaluation step, the damage recovered against the clean run and the
"worse beyond the seed spread" rule.

Numbers at the bench's **final evaluation step** (runs that stopped earlier are listed apart, and the
main tables are repeated at the last step every run reached); per scene x schedule x method the mean over
seeds (and its spread: max - min over seeds, "sd" the sample standard deviation); tables over scenes are
means of the per-scene means, over the scenes where every method of the table has a result (their count is
shown).

"Damage recovered", per scene x schedule, on seed means:
``R_LPIPS = (baseline - JSGS) / (baseline - clean)``, ``R_PSNR = (JSGS - baseline) / (clean - baseline)``,
where baseline = gsplat on the schedule and clean = gsplat on the uncompressed training views. The noise
rule: when ``|baseline - clean|`` is not larger than the seed spread (the larger of the baseline's and the
clean run's max - min over seeds), R is not computed and the table says "within noise"; with a single seed
there is no spread, R is computed and marked "1 seed".
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from dataclasses import dataclass
from typing import Any

METRICS = ("psnr", "ssim", "lpips")
HIGHER_BETTER = {"psnr": True, "ssim": True, "lpips": False}
DIGITS = {"psnr": 2, "ssim": 4, "lpips": 4}
NAMES = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips": "LPIPS↓"}
METHOD_NAMES = {"gsplat": "gsplat", "jsgs": "JSGS"}


@dataclass
class Agg:
    """A quantity over seeds."""

    values: list[float]

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def mean(self) -> float | None:
        return statistics.fmean(self.values) if self.values else None

    @property
    def sd(self) -> float | None:
        return statistics.stdev(self.values) if len(self.values) > 1 else None

    @property
    def spread(self) -> float | None:
        """max - min over seeds; None with fewer than two seeds."""
        return max(self.values) - min(self.values) if len(self.values) > 1 else None


def agg(values: list[Any]) -> Agg:
    return Agg([float(v) for v in values if v is not None and math.isfinite(float(v))])


RunKey = tuple[str, str, str, int]


def _key(r: dict[str, Any]) -> RunKey:
    return (r["scene"], r["schedule"], r["method"], int(r["seed"]))


def last_step(rows: list[dict[str, Any]]) -> int:
    """The bench's final step: the largest evaluation step of any run."""
    return max((int(r["step"]) for r in rows), default=0)


def steps_by_run(rows: list[dict[str, Any]]) -> dict[RunKey, set[int]]:
    """(scene, schedule, method, seed) -> the steps it was evaluated at."""
    steps: dict[RunKey, set[int]] = defaultdict(set)
    for r in rows:
        steps[_key(r)].add(int(r["step"]))
    return steps


def common_step(rows: list[dict[str, Any]]) -> int:
    """The largest evaluation step that every run reached (0: none)."""
    steps = steps_by_run(rows)
    return max(set.intersection(*steps.values()) if steps else set(), default=0)


def unfinished(rows: list[dict[str, Any]]) -> list[tuple[RunKey, int]]:
    """Runs without an evaluation at the final step, with the last step they reached."""
    final = last_step(rows)
    return sorted((k, max(s)) for k, s in steps_by_run(rows).items() if max(s) < final)


def final_rows(rows: list[dict[str, Any]], step: int | None = None) -> dict[RunKey, dict[str, Any]]:
    """(scene, schedule, method, seed) -> the run's row at ``step`` (default: the bench's final step). A run
    that stopped earlier is left out: comparing it at its own last step with finished runs would mix
    training lengths."""
    step = last_step(rows) if step is None else step
    return {_key(r): r for r in rows if int(r["step"]) == step}


def by_seed(
    rows: list[dict[str, Any]], step: int | None = None
) -> dict[tuple[str, str, str], list[dict[str, Any]]]:
    """(scene, schedule, method) -> the rows of its seeds at ``step`` (default: the final step)."""
    out: dict[tuple[str, str, str], list[dict[str, Any]]] = defaultdict(list)
    for (sc, sch, m, _), r in sorted(final_rows(rows, step).items()):
        out[(sc, sch, m)].append(r)
    return out


@dataclass
class Recovered:
    value: float | None  # R, or None where not computed
    gap: float | None  # clean's advantage over the baseline (positive: clean better)
    spread: float | None
    note: str  # "", "within noise", "1 seed", "no clean run", "clean no better"


def damage_recovered(baseline: Agg, method: Agg, clean: Agg, higher_is_better: bool) -> Recovered:
    """R for one scene x schedule and one metric (see the module docstring for the noise rule)."""
    b, m, c = baseline.mean, method.mean, clean.mean
    if b is None or m is None:
        return Recovered(None, None, None, "missing runs")
    if c is None:
        return Recovered(None, None, None, "no clean run")
    sign = 1.0 if higher_is_better else -1.0
    gap = sign * (c - b)
    spreads = [s for s in (baseline.spread, clean.spread) if s is not None]
    spread = max(spreads) if spreads else None
    if spread is not None and abs(gap) <= spread:
        return Recovered(None, gap, spread, "within noise")
    if gap == 0:
        return Recovered(None, gap, spread, "within noise")
    value = sign * (m - b) / gap
    note = "1 seed" if spread is None else ""
    if gap < 0:
        note = (note + "; " if note else "") + "clean no better"
    return Recovered(value, gap, spread, note)


def worse_beyond_spread(baseline: Agg, method: Agg, higher_is_better: bool) -> bool | None:
    """Is the method worse than the baseline by more than the seed spread? None: one seed (unknown)."""
    b, m = baseline.mean, method.mean
    if b is None or m is None:
        return None
    worse = (b - m) if higher_is_better else (m - b)
    spreads = [s for s in (baseline.spread, method.spread) if s is not None]
    if not spreads:
        return None
    return worse > max(spreads)



def mean_of(xs: list[float | None]) -> float | None:
    ys = [x for x in xs if x is not None]
    return statistics.fmean(ys) if ys else None


def median_interval(values: list[float], level: float = 0.95) -> tuple[float, float, float]:
    """A distribution-free interval for the median of the distribution ``values`` were drawn from
    (independently): the order statistics ``(x_(j), x_(n+1-j))`` with the largest j whose coverage
    ``1 - 2 P(Binomial(n, 1/2) < j)`` is at least ``level``, or ``(min, max)`` when even that falls short
    (n < 6 at 0.95). Returns ``(low, high, coverage)``; coverage is exact for continuous values.
    ValueError when ``values`` is empty."""
    x = sorted(values)
    n = len(x)
    if n == 0:
        raise ValueError("median_interval of no values")

    def coverage(j: int) -> float:
        return 1.0 - 2.0 * sum(math.comb(n, i) for i in range(j)) / 2.0**n

    j = 1
    while j + 1 <= (n + 1) // 2 and coverage(j + 1) >= level:
        j += 1
    return x[j - 1], x[n - j], coverage(j)
