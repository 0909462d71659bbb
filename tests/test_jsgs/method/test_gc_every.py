"""``method_options.gc_every``: the Gaussian Controller on every k-th step only, weighted k·λ_fro there.

On the controller's steps it is the exact controller with weight k·λ_fro, bit for bit; on the steps between
it renders no probe and the step is the one without the controller, bit for bit; over a short training run
it keeps most of the exact controller's effect on the opacities and scales (k = 2)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from test_jsgs_method import make_splats, make_view, new_hook, render, target_for

from jsgs.base.errors import JsgsError
from jsgs.jpeg.losses import photometric_loss
from jsgs.method.hook import STAT_NAMES, JsgsHook
from jsgs.method.options import parse_options
from jsgs.train.hook import StepContext
from jsgs.train.trainer import weighted_loss

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def step_at(hook: JsgsHook, step: int) -> dict[str, Any]:
    """One training step at 0-based ``step`` on the tiny scene's JPEG view, as the trainer takes it."""
    view = make_view(50, "4:2:0")
    splats = make_splats()
    target = target_for(view)
    extra = hook.extra_channels(step, view, splats)
    out = render(splats, extra)
    ctx = StepContext(step, view, out.rgb, out.alpha, target, out.info, splats, out.extra, {}, 0)
    h = hook.losses(ctx)
    h.check("jsgs")
    x, y = out.rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    terms = {"photometric": photometric_loss(x, y, 0.2, padding="valid"), **h.terms}
    weighted_loss(terms, {"photometric": 1.0, **h.weights}, h.folded, h.folded_loss).backward()
    return {
        "probe": extra is not None,
        "terms": {k: v.item() for k, v in h.terms.items()},
        "weights": dict(h.weights),
        "stats": {k: float(v) for k, v in h.stats.items()},
        "grads": {k: p.grad.clone() for k, p in splats.items() if p.grad is not None},
    }


def assert_same_step(a: dict[str, Any], b: dict[str, Any], skip: tuple[str, ...] = ()) -> None:
    for key in ("probe", "terms", "weights", "stats"):
        if key not in skip:
            assert a[key] == b[key], key
    assert a["grads"].keys() == b["grads"].keys()
    for n in a["grads"]:
        assert torch.equal(a["grads"][n], b["grads"][n]), n


@pytest.mark.parametrize("route", ["deferred", "now"])
def test_on_its_steps_the_controller_is_the_exact_one_weighted_k_times(route: str) -> None:
    view = make_view(50, "4:2:0")
    for step in (0, 4, 8):
        cheap = step_at(new_hook(view, gc_every=4, gc_pooling=route), step)
        exact = step_at(new_hook(view, lambda_fro=0.05 * 4, gc_pooling=route), step)
        assert cheap["probe"] and cheap["weights"]["fro"] == 0.2 and cheap["stats"]["gc_damped"] > 0
        assert_same_step(cheap, exact)


def test_between_its_steps_there_is_no_probe_and_no_controller() -> None:
    view = make_view(50, "4:2:0")
    for step in (1, 2, 3, 5):
        cheap = step_at(new_hook(view, gc_every=4), step)
        off = step_at(new_hook(view, gc=False), step)
        assert not cheap["probe"]
        assert cheap["terms"]["fro"] == 0.0 and cheap["stats"] == dict.fromkeys(STAT_NAMES, 0.0)
        assert {k: v for k, v in cheap["terms"].items() if k != "fro"} == off["terms"]
        assert_same_step(cheap, off, skip=("terms", "weights", "stats"))


def test_the_steps_between_share_one_kept_zero_tensor() -> None:
    """The zeros logged between the controller's steps (``fro`` and the statistics) are one tensor the hook
    keeps, read only: no new tensor (and no fill kernel) per step, still 0 after the steps' backwards."""
    view = make_view(50, "4:2:0")
    hook = new_hook(view, gc_every=4)
    splats = make_splats()
    target = target_for(view)
    seen = set()
    for step in (1, 2, 3, 5, 6):
        out = render(splats, hook.extra_channels(step, view, splats))
        ctx = StepContext(step, view, out.rgb, out.alpha, target, out.info, splats, out.extra, {}, 0)
        h = hook.losses(ctx)
        x, y = out.rgb.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
        terms = {"photometric": photometric_loss(x, y, 0.2, padding="valid"), **h.terms}
        weighted_loss(terms, {"photometric": 1.0, **h.weights}, h.folded, h.folded_loss).backward()
        zeros = [h.terms["fro"], *(h.stats[n] for n in STAT_NAMES)]
        seen |= {t.untyped_storage().data_ptr() for t in zeros}
        assert all(t.item() == 0.0 for t in zeros), step
    assert len(seen) == 1


def test_gc_every_is_validated() -> None:
    assert parse_options({}).gc_every == 1
    assert parse_options({"gc_every": 3}).gc_every == 3
    for bad, msg in ((0, "must be >= 1"), (1.5, "integer"), ("2", "integer")):
        with pytest.raises(JsgsError, match=f"method_options.gc_every.*{msg}"):
            parse_options({"gc_every": bad})


def test_a_short_run_keeps_most_of_the_controllers_effect(tmp_path: Path) -> None:
    """30 steps on the synthetic JPEG scene without densification (the Gaussians stay matched one to one),
    λ_fro = 1 so that the controller's effect is well above rounding: with k = 2 the opacities and scales
    end nearer the exact controller's than half the distance the run without the controller ends at, and
    the controller damps about as many Gaussians per controller step."""
    from _train_scene import short_jsgs_runs

    runs = short_jsgs_runs(tmp_path, {"exact": {}, "every2": {"gc_every": 2}, "off": {"gc": False}})
    exact, cheap, off = (runs[n][1] for n in ("exact", "every2", "off"))
    for n in ("opacities", "scales"):
        d_off = (off[n] - exact[n]).norm().item()
        assert d_off > 1e-3, n  # the controller did something
        assert (cheap[n] - exact[n]).norm().item() < 0.5 * d_off, n
    damped = runs["exact"][0]["train"]["stats"]["gc_damped"]
    damped_cheap = runs["every2"][0]["train"]["stats"]["gc_damped"]  # a mean over the controller's steps
    assert damped > 0 and damped_cheap == pytest.approx(damped, rel=0.3)


def _gc_every_run(root: Path, stop_at: int | None = None, resume: bool = False) -> tuple[Any, ...]:
    """The mcmc preset's recipe (``gc_every`` 4) for 10 steps on the synthetic JPEG scene (the controller at
    0-based steps 0, 4 and 8; the run ends on a step between): the metrics document, each step's
    StepResult and the plain progress lines."""
    from _train_scene import make_scene

    from jsgs.train.callbacks import Callback, ProgressBar, StepResult
    from jsgs.train.config import TrainConfig
    from jsgs.train.trainer import train

    class Record(Callback):
        def on_step_end(self, trainer: Any, result: StepResult) -> None:
            steps.append(result)

    steps: list[StepResult] = []
    lines: list[str] = []
    manifest = root / "scene" / "manifest.json"
    if not manifest.exists():
        make_scene(root / "scene", jpeg_train=True, n_views=9, n_gaussians=60)
    cfg = None
    if not resume:
        cfg = TrainConfig.from_preset("mcmc", method="jsgs", iterations=10, eval_at=[10], device="cpu")
        cfg.eval.fps_passes, cfg.eval.fps_warmup, cfg.eval.save_renders = 1, 0, False
        assert cfg.method_options["gc_every"] == 4
    callbacks = [ProgressBar(True, terminal=False), Record()]
    doc = train(
        manifest, root / "run", cfg, resume=resume, stop_at=stop_at, progress=False, callbacks=callbacks,
        log=lines.append,
    )  # fmt: skip
    return doc, steps, [s for s in lines if s.startswith("train: step")]


def test_between_the_controllers_steps_the_logs_show_its_values_not_zeros(tmp_path: Path) -> None:
    """The steps between the controller's name its term and statistics skipped (their values, 0, are left out
    of the logs; the loss and the parameters are the ones without logging, which the checkpoints' tests
    check): the progress line shows the latest controller step's values with that step, and the
    evaluation's means of them are over the controller's steps (nonzero where it damped Gaussians)."""
    doc, steps, lines = _gc_every_run(tmp_path)
    gc_names = {"fro", *STAT_NAMES}
    assert [s.skipped == (set() if s.step % 4 == 0 else gc_names) for s in steps] == [True] * 10
    ran = [s for s in steps if not s.skipped]
    assert [s.step for s in ran] == [0, 4, 8] and all(s.stats["gc_damped"] > 0 for s in ran)
    train = doc["evals"][-1]["train"]
    assert train["steps"] == 10 and train["skipped"] == dict.fromkeys(gc_names, 7)
    for n in STAT_NAMES:
        assert train["stats"][n] == pytest.approx(sum(s.stats[n] for s in ran) / 3, rel=1e-12), n
    assert train["terms"]["fro"] == pytest.approx(sum(s.terms["fro"] for s in ran) / 3, rel=1e-12)
    assert train["stats"]["gc_damped"] > 0 and train["terms"]["fro"] > 0
    # the loss mean is over every step (the steps between add λ_fro·0)
    assert train["loss"] == pytest.approx(sum(s.loss for s in steps) / 10, rel=1e-12)
    assert sum(v["skipped"]["fro"] for v in train["per_view"].values() if "skipped" in v) == 7
    last = lines[-1]
    assert last.startswith("train: step 10/10") and steps[-1].step == 9
    for n in STAT_NAMES:
        assert f" {n}={ran[-1].stats[n]:.4g}@9" in last, (n, last)
    assert f" fro={ran[-1].terms['fro']:.4g}@9" in last and "=0 " not in last + " "


def test_a_resumed_run_logs_the_same_means(tmp_path: Path) -> None:
    """The skipped counts travel in the checkpoint: stopped after 6 steps and resumed, the evaluation's means
    are the uninterrupted run's."""
    whole = _gc_every_run(tmp_path / "a")[0]["evals"][-1]["train"]
    _gc_every_run(tmp_path / "b", stop_at=6)
    resumed = _gc_every_run(tmp_path / "b", resume=True)[0]["evals"][-1]["train"]
    assert resumed == whole


def test_skipping_changes_the_logs_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same run with nothing skipped (the controller's 0s logged as values): every step's loss, term and
    statistic value and the final checkpoint (Gaussians, optimizer state) are the same, bit for bit; only the
    logged means of the skipped names differ."""
    from jsgs.train import checkpoint as ckpt

    doc, steps, _ = _gc_every_run(tmp_path / "skip")
    monkeypatch.setattr(JsgsHook, "_skipped", lambda self, step: frozenset())
    doc0, steps0, _ = _gc_every_run(tmp_path / "zeros")
    assert [(s.loss, s.terms, s.stats) for s in steps] == [(s.loss, s.terms, s.stats) for s in steps0]
    assert all(s.skipped for s in steps if s.step % 4) and not any(s.skipped for s in steps0)
    a, b = (
        ckpt.load_checkpoint(p / "run/checkpoints/step_000010.pt")
        for p in (tmp_path / "skip", tmp_path / "zeros")
    )

    def same(x: Any, y: Any, where: str) -> None:
        if isinstance(x, dict):
            assert x.keys() == y.keys(), where
            for k in x:
                same(x[k], y[k], f"{where}.{k}")
        elif isinstance(x, list | tuple):
            assert len(x) == len(y), where
            for i, (u, v) in enumerate(zip(x, y, strict=True)):
                same(u, v, f"{where}[{i}]")
        else:
            assert torch.equal(x, y) if isinstance(x, torch.Tensor) else x == y, where

    same(a["splats"], b["splats"], "splats")
    same(a["optimizers"], b["optimizers"], "optimizers")
    train, train0 = doc["evals"][-1]["train"], doc0["evals"][-1]["train"]
    assert train["loss"] == train0["loss"] and "skipped" not in train0
    assert train["stats"]["gc_damped"] == pytest.approx(10 / 3 * train0["stats"]["gc_damped"], rel=1e-12)
