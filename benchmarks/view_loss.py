"""Which training views dominate the *training loss*? The training-side twin of
``benchmarks/view_damage.py`` (which measures the JPEG damage itself): from the per-view means that
``jsgs train`` logs (metrics.json ``evals[].train.per_view``), the share of each loss term that the
low-quality views contribute, per evaluation interval.

    .venv/bin/python benchmarks/view_loss.py RUN_DIR... --manifest MANIFEST [--low-quality 30]

``MANIFEST``: the manifest the runs trained on (each view's JPEG quality; for a bench run it is
``RESULTS/data/<scene>/<schedule>_s<seed>/manifest.json``, rebuilt bit for bit here by
``jsgs bench SCENE --out DIR --schedules S --fixed= --seeds N --prepare-only``). Prints one markdown row per
run and interval: the low-quality views' share of the training views, of the steps, of the summed weighted
loss and of each logged term (``l1``, ``ssim``, ``photometric`` = ℓ_ph, and JSGS's ``obs``, ``low``, ``mid``,
``fro``), and the mean ℓ_ph per step of the low- and high-quality views. Runs written before the per-view
log existed have no ``per_view`` and are reported as such.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jsgs.base.errors import JsgsError, reports_user_errors  # noqa: E402

TERMS = ("photometric", "obs", "low", "mid", "fro")


def view_qualities(manifest: str | Path) -> dict[str, int | None]:
    """Training view name -> JPEG quality (None: a lossless view). The manifest is read and validated by
    :func:`jsgs.base.manifest.load_manifest` (its images need not be here)."""
    from jsgs.base.manifest import load_manifest

    m = load_manifest(manifest, check_files=False)
    return {v.name: None if v.jpeg is None else v.jpeg.quality for v in m.views if v.split == "train"}


def interval_shares(train: dict[str, Any], quality: dict[str, int | None], low: int) -> dict[str, Any] | None:
    """Shares carried by the views of quality <= ``low`` in one evaluation interval (``evals[i].train``);
    None when the interval has no per-view log."""
    per_view = train.get("per_view")
    if not per_view:
        return None
    unknown = sorted(set(per_view) - set(quality))
    if unknown:
        raise JsgsError(f"views {unknown[:3]} of the run are not training views of the manifest")

    def is_low(name: str) -> bool:
        q = quality[name]
        return q is not None and q <= low

    def total(names: list[str], key: str | None) -> float:
        # a term's mean is over the steps that computed it (``skipped``: the others)
        return sum(
            (per_view[n]["steps"] - (0 if key is None else per_view[n].get("skipped", {}).get(key, 0)))
            * (per_view[n]["loss"] if key is None else per_view[n]["terms"].get(key, 0.0))
            for n in names
        )

    names = list(per_view)
    lows = [n for n in names if is_low(n)]
    highs = [n for n in names if not is_low(n)]
    steps = sum(per_view[n]["steps"] for n in names)
    low_steps = sum(per_view[n]["steps"] for n in lows)
    out: dict[str, Any] = {
        "views": len(lows) / len(quality),
        "steps": low_steps / steps,
        "loss": total(lows, None) / total(names, None),
    }
    for k in TERMS:
        t = total(names, k)
        out[k] = total(lows, k) / t if t > 0 and any(k in per_view[n]["terms"] for n in names) else None
    out["lph_low"] = total(lows, "photometric") / low_steps if low_steps else None
    high_steps = steps - low_steps
    out["lph_high"] = total(highs, "photometric") / high_steps if high_steps else None
    return out


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f} %"


def _num(x: float | None) -> str:
    return "–" if x is None else f"{x:.4f}"


@reports_user_errors
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders (metrics.json)")
    ap.add_argument("--manifest", type=Path, required=True, help="the manifest the runs trained on")
    ap.add_argument("--low-quality", type=int, default=30, help="views of quality <= this are 'low' [30]")
    a = ap.parse_args(argv)
    quality = view_qualities(a.manifest)
    print(
        f"| run | interval | low views | low steps | total loss | ℓ_ph | L_obs | L_low | L_mid | L_fro | "
        f"ℓ_ph / step, q ≤ {a.low_quality} | ℓ_ph / step, q > {a.low_quality} |"
    )
    print("|---|---|" + "---:|" * 10)
    for run in a.runs:
        path = run / "metrics.json"
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise JsgsError(f"{path}: cannot read the run's metrics ({e})") from None
        prev = 0
        for e in doc.get("evals", []):
            interval = f"{prev}–{e['step']}"
            prev = e["step"]
            try:
                s = interval_shares(e["train"], quality, a.low_quality)
            except JsgsError as err:
                raise JsgsError(f"{path}: {err}") from None
            if s is None:
                print(f"| {run} | {interval} | no per-view log |" + " |" * 9)
                continue
            cells = [_pct(s[k]) for k in ("views", "steps", "loss", *TERMS)]
            cells += [_num(s["lph_low"]), _num(s["lph_high"])]
            print(f"| {run} | {interval} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
