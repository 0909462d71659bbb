"""The preview preset (docs/training.md, "A preview on a CPU") resolves to its documented settings, and a run
prints its time estimate after the first steps."""

from __future__ import annotations

import json
from pathlib import Path

from _train_scene import make_scene
from click.testing import CliRunner

from jsgs.cli import main
from jsgs.train.callbacks import ProgressBar
from jsgs.train.config import PREVIEW_ITERATIONS, TrainConfig, command_settings, to_dict


def test_preview_preset_is_the_documented_baseline_recipe() -> None:
    cfg = command_settings(preset_name="preview")
    assert cfg.method == "gsplat" and cfg.method_options == {}
    assert cfg.iterations == PREVIEW_ITERATIONS == 1000
    assert cfg.eval_at == [PREVIEW_ITERATIONS]
    # everything else is the paper preset's recipe (DefaultStrategy, its init and losses)
    own = ("method", "iterations", "eval_at")
    rest = {k: v for k, v in to_dict(cfg).items() if k not in own}
    default = {k: v for k, v in to_dict(TrainConfig.from_preset("paper")).items() if k not in own}
    assert rest == default and cfg.strategy.type == "default"
    # the command line still applies over it
    assert command_settings(preset_name="preview", overrides={"method": "jsgs"}).method == "jsgs"


def test_preview_run_records_the_preset_and_prints_a_start_estimate(tmp_path: Path) -> None:
    manifest = make_scene(tmp_path / "scene")
    steps = ProgressBar.ESTIMATE_AFTER + 4
    args = ["train", str(manifest), "--out", str(tmp_path / "run"), "--preset", "preview", "--device", "cpu",
            "--iterations", str(steps)]  # fmt: skip
    r = CliRunner().invoke(main, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output
    text = r.output  # stdout and stderr
    estimates = [ln for ln in text.splitlines() if ln.startswith("train: estimate after")]
    assert len(estimates) == 1, text
    assert f"after {ProgressBar.ESTIMATE_AFTER} steps" in estimates[0]
    assert f"remaining {steps - ProgressBar.ESTIMATE_AFTER} steps" in estimates[0]
    settings = json.loads((tmp_path / "run" / "config.json").read_text())["settings"]
    assert settings["method"] == "gsplat" and settings["eval_at"] == [steps]
    assert settings["strategy"]["type"] == "default"
