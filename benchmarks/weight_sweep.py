"""A loss-weight sweep: one ``jsgs bench --methods jsgs --config CONFIG`` per config of
``benchmarks/weight_sweep/*.json`` (on a GPU machine), summarised here against the gsplat baseline and the
clean ceiling of a finished bench (``docs/results/paper_protocol/results.csv``).

    .venv/bin/python benchmarks/weight_sweep.py SWEEP_DIR \
        [--reference docs/results/paper_protocol/results.csv] \
        [--configs benchmarks/weight_sweep] [--scenes llff_flower,...] [--schedule gaussian] [--seed 0]

``SWEEP_DIR/<config name>/results.csv`` are the sweep's benches. Prints, per scene, one markdown row per
config (and the reference's own gsplat and paper-weights JSGS rows): λ_base, λ_obs, λ_low, λ_mid, λ_fro, the
densification threshold grad2d, PSNR / SSIM / LPIPS at the final step, ΔLPIPS against gsplat, the damage
recovered R_LPIPS, R_PSNR (as in ``jsgs bench``'s report) and the number of Gaussians. Configs named
``gsplat_*`` train the baseline (controls: the same loss scale or threshold without the JPEG terms). Two
config sets:
``benchmarks/weight_sweep`` (``docs/results/weight_sweep``) and ``benchmarks/densify_control`` (does JSGS
gain from JPEG awareness or from the extra densification that its larger loss causes?
``docs/results/densification_control``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jsgs.bench.results import read_csv  # noqa: E402
from jsgs.bench.stats import final_rows  # noqa: E402


def final(
    rows: list[dict[str, Any]], scene: str, schedule: str, method: str, seed: int = 0
) -> dict[str, Any] | None:
    """The row of ``method`` and ``seed`` at the bench's final step, or None."""
    return final_rows(rows).get((scene, schedule, method, seed))


def config_method(config: Path) -> str:
    """The method a sweep config trains: ``gsplat_*.json`` the baseline (a control), the others JSGS."""
    return "gsplat" if config.stem.startswith("gsplat_") else "jsgs"


def weights(config: Path | None, method: str = "jsgs") -> dict[str, float | None]:
    """λ's of a sweep config over the paper's defaults (None: not used by ``method``), and the
    densification threshold ``grad2d`` (strategy.grow_grad2d)."""
    from jsgs.method.options import parse_options
    from jsgs.train.config import TrainConfig, load_config_file

    paper = TrainConfig.from_preset("paper")
    cfg = load_config_file(config, paper) if config else paper
    out: dict[str, float | None] = {"base": cfg.loss.base_weight}
    if method == "jsgs":
        o = parse_options(cfg.method_options)
        out.update(obs=o.lambda_obs, low=o.lambda_low, mid=o.lambda_mid, fro=o.lambda_fro)
    else:
        out.update(obs=None, low=None, mid=None, fro=None)
    out["grad2d"] = cfg.strategy.grow_grad2d
    return out


def _cell(v: float | None) -> str:
    return "–" if v is None else f"{v:g}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sweep_dir", type=Path)
    ap.add_argument("--reference", type=Path, default=Path("docs/results/paper_protocol/results.csv"))
    ap.add_argument("--configs", type=Path, default=Path(__file__).resolve().parent / "weight_sweep")
    ap.add_argument("--scenes", default="llff_flower", help="comma list [llff_flower]")
    ap.add_argument("--schedule", default="gaussian")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()

    ref = read_csv(a.reference)
    cols = "config λ_base λ_obs λ_low λ_mid λ_fro grad2d PSNR SSIM LPIPS ΔLPIPS R_LPIPS R_PSNR".split()
    cols.append("#Gaussians")
    for scene in a.scenes.split(","):
        base = final(ref, scene, a.schedule, "gsplat", a.seed)
        clean = final(ref, scene, "clean", "gsplat", a.seed)
        if base is None or clean is None:
            sys.exit(
                f"{a.reference}: no finished gsplat run of {scene}/{a.schedule} and {scene}/clean, "
                f"seed {a.seed}"
            )
        entries: list[tuple[str, dict[str, float | None], dict[str, Any] | None]] = [
            ("gsplat (reference)", weights(None, "gsplat"), base),
            ("jsgs, paper weights (reference)", weights(None), final(ref, scene, a.schedule, "jsgs", a.seed)),
        ]
        for cfg in sorted(a.configs.glob("*.json")):
            m = config_method(cfg)
            csv_path = a.sweep_dir / cfg.stem / "results.csv"
            row = final(read_csv(csv_path), scene, a.schedule, m, a.seed) if csv_path.is_file() else None
            entries.append((cfg.stem, weights(cfg, m), row))

        print(f"{scene}, {a.schedule} schedule, seed {a.seed}; clean ceiling PSNR {clean['psnr']:.2f} LPIPS "
              f"{clean['lpips']:.4f}\n")  # fmt: skip
        print("| " + " | ".join(cols) + " |")
        print("|---|" + "---:|" * (len(cols) - 1))
        for name, w, r in entries:
            lam = [_cell(w[k]) for k in ("base", "obs", "low", "mid", "fro", "grad2d")]
            if r is None:
                print(f"| {name} | {' | '.join(lam)} | not run | | | | | | |")
                continue
            dl = 100 * (1 - r["lpips"] / base["lpips"])
            rl = (base["lpips"] - r["lpips"]) / (base["lpips"] - clean["lpips"])
            rp = (r["psnr"] - base["psnr"]) / (clean["psnr"] - base["psnr"])
            print(f"| {name} | {' | '.join(lam)} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['lpips']:.4f} | "
                  f"{dl:+.1f} % | {rl:.2f} | {rp:.2f} | {int(r['num_gaussians'])} |")  # fmt: skip
        print()


if __name__ == "__main__":
    main()
