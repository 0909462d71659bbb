"""How much of ℓ_ph each JPEG training view keeps under a JSGS recipe, by quality: the weights the trainer
applies (``jsgs.method.image_terms.view_tables`` and ``base_weight``, the same code), without training.

    .venv/bin/python tools/diagnostics/view_weights.py DATA/cup_gaussian/manifest.json [MANIFEST ...] \
        [--recipe 'b0.5={"base_block_ref": 0.5}' ...]

Each recipe is a ``method_options`` object over the ``mcmc`` preset's (``jsgs.method.recipes.RECIPES``,
the row ``default``). Per manifest, a markdown table: by the views' IJG quality, the median of the file's
estimated noise variance σ² (8-bit²), of the blockiness B of the decoded luma
(``jsgs.jpeg.noise.blockiness``), and of each recipe's weight; the last column over all the JPEG training
views. CPU only; reads every file once.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import torch

from jsgs.base.errors import JsgsError, reports_user_errors
from jsgs.method.image_terms import ViewJpeg, base_weight, view_tables
from jsgs.method.options import JsgsOptions, parse_options
from jsgs.method.recipes import RECIPES
from jsgs.train.config import TrainConfig
from jsgs.train.data import load_training_scene


def parse_recipe(text: str) -> tuple[str, dict]:
    """``NAME=JSON`` -> (name, method_options over the preset's); JsgsError (one line) on a bad one."""
    name, sep, raw = text.partition("=")
    if not sep or not name:
        raise JsgsError(f"--recipe {text!r}: expected NAME=JSON, e.g. 'b0.5={{\"base_block_ref\": 0.5}}'")
    try:
        extra = json.loads(raw)
    except json.JSONDecodeError as e:
        raise JsgsError(f"--recipe {name}: not JSON ({e.msg})") from None
    if not isinstance(extra, dict):
        raise JsgsError(f"--recipe {name}: expected a JSON object of method_options")
    return name, {**RECIPES["mcmc"], **extra}


def view_table(manifest: Path, recipes: dict[str, JsgsOptions]) -> list[dict]:
    """One dict per JPEG training view: ``quality``, ``noise``, ``blockiness`` and each recipe's weight."""
    cfg = TrainConfig.from_preset("paper", device="cpu", eval_at=[])
    views = load_training_scene(manifest, cfg).train_views
    cpu = torch.device("cpu")
    measured: dict[tuple[str, str], dict[int, ViewJpeg]] = {}
    for o in recipes.values():  # σ² and B read from the files once per (tables, noise) kind
        key = (o.tables, o.base_noise)
        if key not in measured:
            measured[key] = view_tables(views, cpu, str(manifest), o.tables, o.base_noise, blocks=True)
    first = next(iter(measured.values()))
    rows = []
    for v in views:
        if v.index not in first:
            continue
        row = {"quality": v.jpeg.quality, "noise": first[v.index].noise_variance,
               "blockiness": first[v.index].blockiness}  # fmt: skip
        for name, o in recipes.items():
            row[name] = base_weight(o, measured[(o.tables, o.base_noise)][v.index])
        rows.append(row)
    return rows


def markdown(manifest: Path, rows: list[dict], names: list[str]) -> str:
    qualities = sorted({r["quality"] for r in rows})
    head = "| | " + " | ".join(f"q = {q}" for q in qualities) + " | all |"
    lines = [f"{manifest} ({len(rows)} JPEG training views)", "", head,
             "|---|" + "---:|" * (len(qualities) + 1)]  # fmt: skip
    labels = {"noise": "σ² (8-bit²)", "blockiness": "blockiness B", **{n: f"weight, {n}" for n in names}}
    for col, label in labels.items():
        fmt = "{:.1f}" if col == "noise" else "{:.2f}"
        cells = [fmt.format(statistics.median(r[col] for r in rows if r["quality"] == q)) for q in qualities]
        cells.append(fmt.format(statistics.median(r[col] for r in rows)))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


@reports_user_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("manifests", nargs="+", type=Path)
    ap.add_argument(
        "--recipe", action="append", default=[], help="NAME=JSON: method_options over the preset's"
    )
    a = ap.parse_args(argv)
    raw = {"default": dict(RECIPES["mcmc"])}
    raw.update(parse_recipe(t) for t in a.recipe)
    recipes = {n: parse_options(o, f"--recipe {n}") for n, o in raw.items()}
    for m in a.manifests:
        rows = view_table(m, recipes)
        if not rows:
            raise JsgsError(f"{m}: no JPEG training view")
        print(markdown(m, rows, list(recipes)) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
