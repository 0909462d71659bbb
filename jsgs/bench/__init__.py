"""``jsgs bench``: the reproduction harness for the paper's tables.

- :mod:`jsgs.bench.plan`: which datasets and training runs a bench needs, where they live, their commands;
- :mod:`jsgs.bench.workers`: N ``jsgs train`` subprocesses per GPU, skip-if-finished, failures;
- :mod:`jsgs.bench.results`: ``RESULTS/results.csv`` from the runs' ``metrics.json``;
- :mod:`jsgs.bench.stats` (seed means, damage recovered), :mod:`jsgs.bench.markdown` (``RESULTS/report.md``:
  Tables 1-4 layout, per scene), :mod:`jsgs.bench.plots` (``RESULTS/plots/``);
- :mod:`jsgs.bench.harness`: :func:`bench`, all of it in order, with ``RESULTS/bench.json``.
"""

from __future__ import annotations

from jsgs.bench.harness import bench

__all__ = ["bench"]
