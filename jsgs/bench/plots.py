"""The bench's plots (matplotlib, written headless)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

from jsgs.bench.stats import agg
from jsgs.bench.tables import count_label

#: each method's colour and each schedule's line style, in every bench figure
METHOD_COLORS = {"gsplat": "tab:blue", "jsgs": "tab:red"}
SCHEDULE_STYLES = {"uniform": "-", "gaussian": "--", "descending": ":", "clean": "-."}


def write_plots(
    rows: list[dict[str, Any]], seeds: dict[tuple[str, str, str], list[dict[str, Any]]], outdir: Path
) -> list[Path]:
    """One figure per scene of ``rows`` (LPIPS and PSNR against training time and against the number of
    Gaussians, per method and schedule, means over seeds) in ``outdir``, a line for each (scene, schedule,
    method) of ``seeds`` (:func:`jsgs.bench.stats.by_seed`); returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    from jsgs.base.io import write_with_atomic

    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    colors, styles = METHOD_COLORS, SCHEDULE_STYLES
    for sc in sorted({r["scene"] for r in rows}):
        fig, axes = plt.subplots(2, 2, figsize=(11, 8))
        any_line = False
        for (s, sch, m), _ in sorted(seeds.items()):
            if s != sc or m not in colors:
                continue
            steps: dict[int, list[dict[str, Any]]] = defaultdict(list)
            for r in rows:
                if r["scene"] == sc and r["schedule"] == sch and r["method"] == m:
                    steps[r["step"]].append(r)
            pts = sorted(steps)

            def series(key: str, steps: dict[int, list[dict[str, Any]]] = steps, pts: list[int] = pts):
                return [agg([r.get(key) for r in steps[p]]).mean for p in pts]

            color = "gray" if sch == "clean" else colors[m]
            style = styles.get(sch, "-")
            label = f"{m} {sch}"
            for ax, (xk, yk) in zip(
                axes.flat,
                [("train_seconds", "lpips"), ("train_seconds", "psnr"), ("num_gaussians", "lpips"),
                 ("num_gaussians", "psnr")],
                strict=True,
            ):  # fmt: skip
                xs, ys = series(xk), series(yk)
                xy = [(x, y) for x, y in zip(xs, ys, strict=True) if x is not None and y is not None]
                if xy:
                    ax.plot(*zip(*xy, strict=True), style, marker="o", ms=3, color=color, label=label)
                    any_line = True
        if not any_line:
            plt.close(fig)
            continue
        for ax, (xl, yl) in zip(
            axes.flat,
            [("training time (s)", "LPIPS"), ("training time (s)", "PSNR (dB)"), ("#Gaussians", "LPIPS"),
             ("#Gaussians", "PSNR (dB)")],
            strict=True,
        ):  # fmt: skip
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            ax.grid(alpha=0.3)
        for ax in axes[1]:  # 300k, 1.1M rather than matplotlib's 0.3 … 1.1 with "1e6" in the corner
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: count_label(v)))
        if axes[0, 0].get_legend_handles_labels()[0]:  # none for an empty panel (matplotlib warns)
            axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"{sc}: test metrics at each evaluation step (means over seeds)")
        fig.tight_layout()
        path = outdir / f"{sc}.png"
        write_with_atomic(path, lambda p, fig=fig: fig.savefig(p, dpi=110, format="png"))
        plt.close(fig)
        written.append(path)
    return written
