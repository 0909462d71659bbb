"""The loss-weight sweep of the reproduction issue: one `jsgs bench --methods jsgs` per config of
``benchmarks/weight_sweep/*.json`` (run by ``SWEEP=1 scripts/gpu_bench.sh`` on the GPU), summarised here
against the gsplat baseline and the clean ceiling of a finished bench (``docs/results/results.csv``).

    .venv/bin/python benchmarks/weight_sweep.py SWEEP_DIR [--reference docs/results/results.csv] \
        [--scene llff_flower] [--schedule gaussian]

``SWEEP_DIR/<config name>/results.csv`` are the sweep's benches. Prints one markdown row per config (and the
reference's own gsplat and paper-weights JSGS rows): λ_base, λ_obs, λ_low, λ_mid, λ_fro, PSNR / SSIM / LPIPS
at the final step, ΔLPIPS against gsplat and the damage recovered R_LPIPS, R_PSNR (issue 7's definitions).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jsgs.bench.report import final_rows  # noqa: E402
from jsgs.bench.results import read_csv  # noqa: E402


def final(rows: list[dict[str, Any]], scene: str, schedule: str, method: str) -> dict[str, Any] | None:
    """The seed-0 row of ``method`` at the bench's final step, or None."""
    return final_rows(rows).get((scene, schedule, method, 0))


def weights(config: Path | None) -> dict[str, float]:
    """λ's of a sweep config over the paper's defaults."""
    from jsgs.train.config import load_config_file
    from jsgs.train.jsgs_method import parse_options

    cfg = load_config_file(config) if config else None
    base = cfg.loss.base_weight if cfg else 1.0
    o = parse_options(cfg.method_options if cfg else {})
    return {"base": base, "obs": o.lambda_obs, "low": o.lambda_low, "mid": o.lambda_mid, "fro": o.lambda_fro}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sweep_dir", type=Path)
    ap.add_argument("--reference", type=Path, default=Path("docs/results/results.csv"))
    ap.add_argument("--configs", type=Path, default=Path(__file__).resolve().parent / "weight_sweep")
    ap.add_argument("--scene", default="llff_flower")
    ap.add_argument("--schedule", default="gaussian")
    a = ap.parse_args()

    ref = read_csv(a.reference)
    base = final(ref, a.scene, a.schedule, "gsplat")
    clean = final(ref, a.scene, "clean", "gsplat")
    if base is None or clean is None:
        sys.exit(f"{a.reference}: no finished gsplat run of {a.scene}/{a.schedule} and {a.scene}/clean")
    entries: list[tuple[str, dict[str, float], dict[str, Any] | None]] = [
        ("gsplat (reference)", {}, base),
        ("jsgs, paper weights (reference)", weights(None), final(ref, a.scene, a.schedule, "jsgs")),
    ]
    for cfg in sorted(a.configs.glob("*.json")):
        csv_path = a.sweep_dir / cfg.stem / "results.csv"
        row = final(read_csv(csv_path), a.scene, a.schedule, "jsgs") if csv_path.is_file() else None
        entries.append((cfg.stem, weights(cfg), row))

    print(f"{a.scene}, {a.schedule} schedule, seed 0; clean ceiling PSNR {clean['psnr']:.2f} LPIPS "
          f"{clean['lpips']:.4f}\n")  # fmt: skip
    cols = "config λ_base λ_obs λ_low λ_mid λ_fro PSNR SSIM LPIPS ΔLPIPS R_LPIPS R_PSNR".split()
    print("| " + " | ".join(cols) + " |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, w, r in entries:
        lam = [f"{w[k]:g}" if w else "–" for k in ("base", "obs", "low", "mid", "fro")]
        if r is None:
            print(f"| {name} | {' | '.join(lam)} | not run | | | | | |")
            continue
        dl = 100 * (1 - r["lpips"] / base["lpips"])
        rl = (base["lpips"] - r["lpips"]) / (base["lpips"] - clean["lpips"])
        rp = (r["psnr"] - base["psnr"]) / (clean["psnr"] - base["psnr"])
        print(f"| {name} | {' | '.join(lam)} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['lpips']:.4f} | "
              f"{dl:+.1f} % | {rl:.2f} | {rp:.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
