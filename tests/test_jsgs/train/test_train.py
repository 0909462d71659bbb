"""The trainer backbone (jsgs.train): gsplat 1.5.3 defaults, initialisation, world normalisation, an
end-to-end run on a tiny scene, densification as DefaultStrategy specifies, bit-exact resume, NaN handling,
the loss hook.

CPU only, small: scenes of 32x24 px with a few dozen Gaussians."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from _train_scene import make_scene

from jsgs.base.errors import JsgsError
from jsgs.train import checkpoint as ckpt
from jsgs.train.config import TrainConfig, config_schema, from_dict, load_config_file, to_dict
from jsgs.train.hook import HookOutput, LossHook, StepContext
from jsgs.train.model import (
    init_splats,
    knn_sq_dists,
    make_means_scheduler,
    make_optimizers,
    rgb_to_sh,
    sh_degree_at,
)
from jsgs.train.normalize import normalize_world
from jsgs.train.trainer import TrainingDiverged, train

ROOT = Path(__file__).resolve().parents[3]


def tiny_config(**kw: Any) -> TrainConfig:
    """Fast settings: no refinement unless asked, cheap FPS measurement."""
    iterations, eval_at = kw.pop("iterations", 20), kw.pop("eval_at", [])
    cfg = TrainConfig.from_preset("paper", iterations=iterations, eval_at=eval_at, device="cpu")
    cfg.strategy.refine_start_iter = 10_000
    cfg.eval.fps_passes = 1
    cfg.eval.fps_warmup = 0
    cfg.log_every = 5
    for k, v in kw.items():
        section, _, name = k.partition("__")
        if name:
            setattr(getattr(cfg, section), name, v)
        else:
            setattr(cfg, k, v)
    return cfg


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_scene(tmp_path_factory.mktemp("scene"))


# ---------------------------------------------------------------------------------------------------------
# settings


def test_paper_preset_is_gsplat_simple_trainer() -> None:
    cfg = TrainConfig.from_preset("paper")
    # examples/simple_trainer.py @ v1.5.3 (Config and create_splats_with_optimizers)
    assert (cfg.init.type, cfg.init.opacity, cfg.init.scale, cfg.init.knn_neighbors) == ("sfm", 0.1, 1.0, 3)
    o = cfg.optim
    assert (o.means_lr, o.scales_lr, o.quats_lr, o.opacities_lr, o.sh0_lr) == (
        1.6e-4,
        5e-3,
        1e-3,
        5e-2,
        2.5e-3,
    )
    assert o.shN_lr == 2.5e-3 / 20 and o.means_lr_final_factor == 0.01 and o.eps == 1e-15
    assert (o.beta1, o.beta2) == (0.9, 0.999)
    r = cfg.render
    assert (r.sh_degree, r.sh_degree_interval, r.near_plane, r.far_plane) == (3, 1000, 0.01, 1e10)
    assert not r.packed and not r.random_background
    assert cfg.loss.ssim_lambda == 0.2 and cfg.loss.opacity_reg == 0.0 and cfg.loss.scale_reg == 0.0
    assert cfg.loss.ssim_padding == "valid"  # fused_ssim(colors, pixels, padding="valid")
    assert cfg.scene.normalize_world and cfg.scene.scene_scale_margin == 1.1 and cfg.scene.global_scale == 1.0
    assert cfg.seed == 42
    # the paper's protocol
    assert cfg.iterations == 10_000 and cfg.eval_at == [3000, 7000, 10_000]
    # DefaultStrategy (the default type): every field it shares with ours has gsplat's own default; the
    # MCMC-only fields have MCMCStrategy's
    from gsplat.strategy import DefaultStrategy, MCMCStrategy

    assert cfg.strategy.type == "default"
    ref, mcmc = DefaultStrategy(), MCMCStrategy()
    for f in dataclasses.fields(cfg.strategy):
        if f.name in ("cap_max", "noise_lr", "min_opacity"):
            assert getattr(cfg.strategy, f.name) == getattr(mcmc, f.name), f.name
        elif f.name == "cap_max_auto":  # ours: the budget sized to the scene (the paper's: off)
            assert cfg.strategy.cap_max_auto is False
        elif f.name != "type":
            assert getattr(cfg.strategy, f.name) == getattr(ref, f.name), f.name


def test_config_schema_file_is_current() -> None:
    on_disk = json.loads((ROOT / "jsgs" / "schemas" / "config.schema.json").read_text())
    assert on_disk == json.loads(json.dumps(config_schema())), "regenerate: python -m jsgs.train.config"


def test_config_from_dict_and_errors(tmp_path: Path) -> None:
    cfg = from_dict({"iterations": 50, "eval_at": [10, 50], "strategy": {"refine_every": 7}})
    assert cfg.iterations == 50 and cfg.strategy.refine_every == 7 and cfg.strategy.reset_every == 3000
    assert from_dict(to_dict(cfg)) == cfg
    with pytest.raises(JsgsError, match="unknown setting strategy.refine_evry"):
        from_dict({"strategy": {"refine_evry": 7}})
    with pytest.raises(JsgsError, match="iterations must be an integer"):
        from_dict({"iterations": "5"})
    with pytest.raises(JsgsError, match="device must be one of"):
        from_dict({"device": "tpu"})
    bad = tmp_path / "c.json"
    bad.write_text(json.dumps({"iterations": 5, "eval_at": [10]}))
    with pytest.raises(JsgsError, match="eval_at steps must lie in 1..iterations=5"):
        load_config_file(bad)
    bad.write_text("{not json")
    with pytest.raises(JsgsError, match="not a JSON config file"):
        load_config_file(bad)


def test_sh_degree_schedule_and_means_decay() -> None:
    cfg = TrainConfig.from_preset("paper", iterations=100)
    assert [sh_degree_at(s, cfg) for s in (0, 999, 1000, 2999, 3000, 9999)] == [0, 0, 1, 2, 3, 3]
    p = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(2, 3))})
    opt = torch.optim.Adam([{"params": p["means"], "lr": 1.0, "name": "means"}])
    sched = make_means_scheduler(opt, cfg)
    for _ in range(cfg.iterations):
        opt.step()
        sched.step()
    assert math.isclose(opt.param_groups[0]["lr"], 0.01, rel_tol=1e-9)


# ---------------------------------------------------------------------------------------------------------
# initialisation and normalisation


def test_knn_matches_brute_force_with_duplicates() -> None:
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(300, 3, generator=g)
    pts[5] = pts[7]  # an exact duplicate: its nearest other point is at distance 0
    d = knn_sq_dists(pts, 3, chunk=64)
    full = torch.cdist(pts.double(), pts.double()) ** 2
    full.fill_diagonal_(float("inf"))
    want = full.sort(dim=1).values[:, :3]
    want[5] = torch.cat([torch.zeros(1, dtype=torch.float64), full[5].sort().values[1:3]])
    want[7] = torch.cat([torch.zeros(1, dtype=torch.float64), full[7].sort().values[1:3]])
    assert torch.allclose(d, want, atol=1e-12)


def test_init_is_gsplat_recipe() -> None:
    torch.manual_seed(0)
    pts = torch.rand(50, 3)
    rgb = torch.rand(50, 3)
    cfg = TrainConfig.from_preset("paper")
    s = init_splats(pts, rgb, cfg, scene_scale=2.0, device=torch.device("cpu"))
    assert torch.equal(s["means"], pts)
    d2 = (torch.cdist(pts.double(), pts.double()) ** 2).sort(dim=1).values[:, 1:4].mean(-1)
    assert torch.allclose(s["scales"], torch.log(d2.sqrt()).float()[:, None].expand(-1, 3), atol=1e-6)
    assert torch.allclose(torch.sigmoid(s["opacities"]), torch.full((50,), 0.1))
    assert torch.allclose(s["sh0"][:, 0], rgb_to_sh(rgb))
    assert s["shN"].shape == (50, 15, 3) and not s["shN"].any()
    assert s["quats"].shape == (50, 4) and (s["quats"] >= 0).all()  # torch.rand, as gsplat
    lrs = {n: o.param_groups[0]["lr"] for n, o in make_optimizers(s, cfg, 2.0).items()}
    assert lrs == {"means": 3.2e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3,
                   "shN": 2.5e-3 / 20}  # fmt: skip


def test_normalisation_is_a_similarity_that_keeps_images() -> None:
    rng = np.random.default_rng(1)
    from _train_scene import look_at

    c2w = []
    for _ in range(7):
        centre = rng.normal(size=3) * 3 + np.array([10.0, -4.0, 2.0])
        R, t = look_at(
            centre, np.array([10.0, -4.0, 0.0]) + rng.normal(size=3) * 0.2, np.array([0.3, 0.1, 1.0])
        )
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, t
        c2w.append(np.linalg.inv(w2c))
    c2w = np.stack(c2w)
    pts = rng.normal(size=(40, 3)) + np.array([10.0, -4.0, 0.0])
    c2w_n, pts_n, T = normalize_world(c2w, pts)
    # T is a similarity: s * rotation
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, s * s * np.eye(3), atol=1e-9)
    assert np.allclose(pts_n, pts @ T[:3, :3].T + T[:3, 3])
    # every camera sees every point at the same pixel (and its rotation stays a rotation)
    for a, b in zip(c2w, c2w_n, strict=True):
        assert np.allclose(b[:3, :3] @ b[:3, :3].T, np.eye(3), atol=1e-9)
        pa = (np.linalg.inv(a) @ np.c_[pts, np.ones(len(pts))].T)[:3]
        pb = (np.linalg.inv(b) @ np.c_[pts_n, np.ones(len(pts))].T)[:3]
        assert np.allclose(pa[:2] / pa[2], pb[:2] / pb[2], atol=1e-9)
    # gsplat's choices: principal axes on x, y, z by decreasing variance; median below mean in z
    cov = np.cov(pts_n, rowvar=False)
    assert np.allclose(cov - np.diag(np.diag(cov)), 0, atol=1e-9)
    assert cov[0, 0] >= cov[1, 1] >= cov[2, 2]
    assert np.median(pts_n[:, 2]) <= np.mean(pts_n[:, 2])


# ---------------------------------------------------------------------------------------------------------
# training


class Recorder(LossHook):
    """Adds nothing; records what it sees each step."""

    name = "recorder"

    def __init__(self) -> None:
        self.counts: list[int] = []
        self.photometric: list[float] = []

    def losses(self, ctx: StepContext) -> HookOutput:
        self.counts.append(int(ctx.splats["means"].shape[0]))
        self.photometric.append(float(ctx.base_terms["photometric"].detach()))
        return HookOutput(stats={"n": float(ctx.splats["means"].shape[0])})


def test_end_to_end_loss_decreases_and_outputs(scene: Path, tmp_path: Path) -> None:
    from jsgs.base.ply import load_ply
    from jsgs.base.schema import validate

    rec = Recorder()
    run = tmp_path / "run"
    doc = train(scene, run, tiny_config(iterations=24, eval_at=[8, 24]), hook=rec, progress=False)
    first, last = np.mean(rec.photometric[:5]), np.mean(rec.photometric[-5:])
    assert last < 0.9 * first, (first, last)
    assert doc["status"] == "complete" and doc["step"] == 24
    assert [e["step"] for e in doc["evals"]] == [8, 24]
    e8, e24 = doc["evals"]
    assert e24["psnr"] > e8["psnr"]
    assert e24["train"]["steps"] == 16
    assert e24["train"]["terms"]["photometric"] < e8["train"]["terms"]["photometric"]
    assert e24["lpips"] is None and e24["lpips_note"]  # 32x24 is below LPIPS-alex's minimum size
    assert e24["fps"] > 0 and e24["num_gaussians"] == 80 and e24["peak_memory_bytes"] > 0
    assert 0 < e8["train_time_s"] < e24["train_time_s"] == doc["train_time_s"]
    validate(json.loads((run / "metrics.json").read_text()), "metrics", "metrics.json")
    conf = json.loads((run / "config.json").read_text())
    validate(conf, "config", "config.json")
    assert conf["settings"]["iterations"] == 24 and conf["derived"]["initial_gaussians"] == 80
    assert conf["derived"]["backend"] == "torch" and conf["versions"]["gsplat"] == "1.5.3"
    ply = load_ply(run / "point_cloud.ply")
    assert ply["means"].shape == (80, 3) and ply["shN"].shape == (80, 15, 3)
    pngs = sorted((run / "renders" / "step_000024").glob("*.png"))
    assert len(pngs) == 2
    from PIL import Image

    assert Image.open(pngs[0]).size == (32, 24)
    assert [s for s, _ in ckpt.list_checkpoints(run / "checkpoints")] == [8, 24]
    # a finished run refuses to be overwritten, and resuming it is a no-op
    with pytest.raises(JsgsError, match="not empty; pass --resume"):
        train(scene, run, tiny_config(iterations=24, eval_at=[8, 24]), progress=False)
    again = train(scene, run, None, resume=True, progress=False)
    assert again["status"] == "complete" and again["evals"] == doc["evals"]
    # the one reader of a run's config.json: the document, its settings, the manifest it names
    from jsgs.train.config import holds_run_config, read_run_config

    recorded = read_run_config(run)
    assert recorded.doc == conf and recorded.settings == tiny_config(iterations=24, eval_at=[8, 24])
    assert recorded.manifest.resolve() == scene.resolve() and recorded.derived["initial_gaussians"] == 80
    assert recorded.manifest_sha256 == conf["manifest"]["sha256"]
    assert holds_run_config(run) and not holds_run_config(tmp_path)
    with pytest.raises(JsgsError, match=r"not a run folder \(no config.json\)"):
        read_run_config(tmp_path)
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text('{"iterations": 5}')
    with pytest.raises(JsgsError, match="not the config.json of a jsgs train run"):
        read_run_config(other)


def test_densification_as_default_strategy_says(scene: Path, tmp_path: Path) -> None:
    """With refine_start_iter=4, refine_every=4, DefaultStrategy refines after 0-based steps 8, 12 (step >
    start and step % every == 0): the count may change only there, and then by duplicates + splits - prunes
    computed from its own criteria, which we recompute from the running state it kept."""
    from gsplat.strategy import DefaultStrategy

    counts_seen: list[tuple[int, int, int, int]] = []
    orig = DefaultStrategy._grow_gs

    def spy(self: DefaultStrategy, params: Any, optimizers: Any, state: Any, step: int) -> tuple[int, int]:
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads > self.grow_grad2d
        small = torch.exp(params["scales"]).max(dim=-1).values <= self.grow_scale3d * state["scene_scale"]
        n0 = len(params["means"])
        nd, ns = orig(self, params, optimizers, state, step)
        assert (nd, ns) == (int((high & small).sum()), int((high & ~small).sum()))
        assert len(params["means"]) == n0 + nd + ns  # duplicate adds one, split replaces one by two
        counts_seen.append((step, n0, nd, ns))
        return nd, ns

    rec = Recorder()
    cfg = tiny_config(iterations=14, strategy__refine_start_iter=4, strategy__refine_every=4)
    DefaultStrategy._grow_gs = spy  # type: ignore[method-assign]
    try:
        train(scene, tmp_path / "run", cfg, hook=rec, progress=False)
    finally:
        DefaultStrategy._grow_gs = orig  # type: ignore[method-assign]
    assert [c[0] for c in counts_seen] == [8, 12]
    # rec.counts[s] is the count at the start of step s: changes only right after the refine steps
    changes = [s for s in range(1, len(rec.counts)) if rec.counts[s] != rec.counts[s - 1]]
    assert set(changes) <= {9, 13} and changes, rec.counts
    assert sum(nd + ns for _, _, nd, ns in counts_seen) > 0
    # the Adam state follows the parameters
    state = ckpt.load_checkpoint(tmp_path / "run" / "checkpoints" / "step_000014.pt")
    n = state["splats"]["means"].shape[0]
    assert n == rec.counts[-1]
    assert state["optimizers"]["means"]["state"][0]["exp_avg"].shape == (n, 3)


def test_resume_is_bit_exact(scene: Path, tmp_path: Path) -> None:
    """A run split at step 5 and resumed equals the uninterrupted run exactly (parameters, Adam states,
    densification state, metrics), with densification (and its random splits) before and after the cut
    (refinements after 0-based steps 3 and 6) and a random background drawing from the global generator."""

    def cfg() -> TrainConfig:
        return tiny_config(iterations=9, eval_at=[5, 9], strategy__refine_start_iter=1,
                           strategy__refine_every=3, render__random_background=True)  # fmt: skip

    a = train(scene, tmp_path / "a", cfg(), progress=False)
    b1 = train(scene, tmp_path / "b", cfg(), stop_at=5, progress=False)
    assert b1["status"] == "stopped" and b1["step"] == 5
    assert not (tmp_path / "b" / "point_cloud.ply").exists()
    b = train(scene, tmp_path / "b", None, resume=True, progress=False)
    assert b["status"] == "complete"
    ca = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000009.pt")
    cb = ckpt.load_checkpoint(tmp_path / "b" / "checkpoints" / "step_000009.pt")
    n5 = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000005.pt")["splats"]["means"].shape[0]
    assert n5 != 80, "densification should act before the cut"
    assert ca["splats"]["means"].shape[0] != n5, "densification should act after the cut too"
    for name, t in ca["splats"].items():
        assert torch.equal(t, cb["splats"][name]), name
    for name in ca["optimizers"]:
        sa, sb = ca["optimizers"][name]["state"][0], cb["optimizers"][name]["state"][0]
        for k in sa:
            assert torch.equal(sa[k], sb[k]), (name, k)
        assert ca["optimizers"][name]["param_groups"] == cb["optimizers"][name]["param_groups"]
    for k in ("grad2d", "count"):
        assert torch.equal(ca["strategy"][k], cb["strategy"][k])
    assert torch.equal(ca["rng"]["torch"], cb["rng"]["torch"])
    assert ca["sampler"]["perm"] == cb["sampler"]["perm"] and ca["sampler"]["pos"] == cb["sampler"]["pos"]
    strip = ("fps", "render_ms", "eval_time_s", "train_time_s", "time_per_iteration_s", "peak_memory_bytes")
    for ea, eb in zip(a["evals"], b["evals"], strict=True):
        assert {k: v for k, v in ea.items() if k not in strip} == {
            k: v for k, v in eb.items() if k not in strip
        }


def test_a_run_written_before_the_recipes_length_setting_resumes(scene: Path, tmp_path: Path) -> None:
    """A config.json without optim.means_lr_decay_steps (written before it existed) is valid and resumes at
    the length it records, with the means' decay over that length."""
    run = tmp_path / "run"
    train(scene, run, tiny_config(iterations=8, eval_at=[4, 8], method="gsplat"), stop_at=4, progress=False)
    doc = json.loads((run / "config.json").read_text())
    del doc["settings"]["optim"]["means_lr_decay_steps"]
    (run / "config.json").write_text(json.dumps(doc))
    path = run / "checkpoints" / "step_000004.pt"
    state = ckpt.load_checkpoint(path)
    del state["settings"]["optim"]["means_lr_decay_steps"]
    ckpt.save_checkpoint(path, state)
    done = train(scene, run, None, resume=True, progress=False)
    assert (done["status"], done["iterations"], [e["step"] for e in done["evals"]]) == ("complete", 8, [4, 8])
    last = ckpt.load_checkpoint(run / "checkpoints" / "step_000008.pt")
    assert last["optimizers"]["means"]["param_groups"][0]["lr"] == pytest.approx(
        1.6e-4 * json.loads((run / "config.json").read_text())["derived"]["scene_scale"] * 0.01
    )


def test_resume_refuses_changed_settings(scene: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(scene, run, tiny_config(iterations=6, eval_at=[3, 6]), stop_at=3, progress=False)
    with pytest.raises(JsgsError, match=r"differs: iterations \(6 in the run, 8 now\)"):
        train(scene, run, tiny_config(iterations=8, eval_at=[3, 6]), resume=True, progress=False)
    with pytest.raises(JsgsError, match="nothing to resume"):
        train(scene, tmp_path / "empty", None, resume=True, progress=False)


class NanAt(LossHook):
    name = "nan"

    def __init__(self, step: int) -> None:
        self.step = step

    def losses(self, ctx: StepContext) -> HookOutput:
        v = ctx.render.mean() * (float("nan") if ctx.step == self.step else 0.0)
        return HookOutput(terms={"bad_term": v}, weights={"bad_term": 1.0})


def test_nan_stops_with_the_term_and_step_and_keeps_checkpoint(scene: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    with pytest.raises(TrainingDiverged, match=r"iteration 6: loss term 'bad_term' is NaN.*step_000004\.pt"):
        train(scene, run, tiny_config(iterations=10, eval_at=[4, 10]), hook=NanAt(5), progress=False)
    assert [s for s, _ in ckpt.list_checkpoints(run / "checkpoints")] == [4]
    m = json.loads((run / "metrics.json").read_text())
    assert m["status"] == "diverged" and "bad_term" in m["error"] and m["step"] == 5
    good = ckpt.load_checkpoint(run / "checkpoints" / "step_000004.pt")
    assert all(torch.isfinite(t).all() for t in good["splats"].values())


class _BadGradient(torch.autograd.Function):
    """Identity forward (a finite loss); its backward puts ``bad`` into every gradient element."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, bad: float) -> torch.Tensor:
        ctx.bad = bad
        return x.clone()

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor, None]:
        return torch.full_like(g, ctx.bad), None


class BadGradientAt(LossHook):
    name = "badgrad"

    def __init__(self, step: int, bad: float) -> None:
        self.step, self.bad = step, bad

    def losses(self, ctx: StepContext) -> HookOutput:
        if ctx.step != self.step:
            return HookOutput(terms={"probe": ctx.render.mean() * 0.0}, weights={"probe": 1.0})
        opac = _BadGradient.apply(ctx.splats["opacities"], self.bad)
        return HookOutput(terms={"probe": opac.mean() * 0.0}, weights={"probe": 1.0})


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_non_finite_gradient_stops_the_run(scene: Path, tmp_path: Path, bad: float) -> None:
    run = tmp_path / "run"
    with pytest.raises(TrainingDiverged, match=r"iteration 4: the gradient of 'opacities' is not finite"):
        train(scene, run, tiny_config(iterations=10, eval_at=[2, 10]), hook=BadGradientAt(3, bad),
              progress=False)  # fmt: skip
    assert [s for s, _ in ckpt.list_checkpoints(run / "checkpoints")] == [2]
    good = ckpt.load_checkpoint(run / "checkpoints" / "step_000002.pt")
    assert all(torch.isfinite(t).all() for t in good["splats"].values())


def _poison(at_step: int, name: str) -> Any:
    """A callback that puts one NaN into parameter ``name`` after 0-based step ``at_step`` (what an update
    gone wrong leaves), the way nothing in the loss or the gradients shows."""
    from jsgs.train.callbacks import Callback

    class Poison(Callback):
        def on_step_end(self, trainer: Any, result: Any) -> None:
            if result.step == at_step:
                with torch.no_grad():
                    trainer.splats[name].view(-1)[0] = float("nan")

    return Poison()


@pytest.mark.parametrize(("at_step", "name"), [(4, "scales"), (9, "quats")])
def test_a_parameter_that_turns_non_finite_stops_the_run(
    scene: Path, tmp_path: Path, at_step: int, name: str
) -> None:
    """Checked on the step's own host sync (the parameters each step starts from) and at each checkpoint
    point (the state after the last step): the run stops at the iteration that made them, names the
    parameter, keeps the last good checkpoint, writes no checkpoint or model of the broken state, and says
    diverged; the last step (9, 0-based) included."""
    run = tmp_path / "run"
    it = at_step + 1
    with pytest.raises(TrainingDiverged, match=rf"iteration {it}: parameter '{name}' became non-finite.*"
                                               r"step_000003\.pt"):  # fmt: skip
        train(scene, run, tiny_config(iterations=10, eval_at=[3, 10]), progress=False,
              callbacks=[_poison(at_step, name)])  # fmt: skip
    assert [s for s, _ in ckpt.list_checkpoints(run / "checkpoints")] == [3]
    assert not (run / "point_cloud.ply").exists()
    m = json.loads((run / "metrics.json").read_text())
    assert m["status"] == "diverged" and m["step"] == at_step and name in m["error"]


def test_no_run_is_complete_without_its_model(
    scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A model that cannot be written ends the run failed, with its checkpoint; --resume then writes it."""
    from jsgs.train.trainer import RunFailed, Trainer

    run = tmp_path / "run"

    def full_disk(self: Trainer) -> None:
        raise JsgsError(f"{self.paths.ply}: cannot write (No space left on device)")

    with monkeypatch.context() as m:
        m.setattr(Trainer, "export_ply", full_disk)
        with pytest.raises(RunFailed, match=r"point_cloud.ply: the model could not be written .*No space"):
            train(scene, run, tiny_config(iterations=3, eval_at=[3]), progress=False)
    doc = json.loads((run / "metrics.json").read_text())
    assert doc["status"] == "failed" and doc["step"] == 3 and "No space" in doc["error"]
    assert not (run / "point_cloud.ply").exists() and (run / "checkpoints" / "step_000003.pt").is_file()
    lines: list[str] = []
    doc = train(scene, run, None, resume=True, progress=False, log=lines.append)
    assert doc["status"] == "complete" and (run / "point_cloud.ply").is_file()
    assert any("writing the model" in s for s in lines)
    assert json.loads((run / "metrics.json").read_text())["status"] == "complete"
    lines.clear()
    train(scene, run, None, resume=True, progress=False, log=lines.append)
    assert any("already complete" in s for s in lines)


class ExtraTerms(LossHook):
    """A JSGS-like hook: one weighted term, an extra rasterised channel, a statistic."""

    name = "extra"

    def __init__(self) -> None:
        self.max_err = 0.0
        self.saw_jpeg: list[bool] = []

    def extra_channels(self, step: int, view: Any, splats: torch.nn.ParameterDict) -> torch.Tensor:
        return torch.ones(splats["means"].shape[0], 1)

    def losses(self, ctx: StepContext) -> HookOutput:
        assert ctx.extra is not None and ctx.extra.shape == ctx.alpha.shape
        # compositing a constant 1 gives the accumulated opacity
        self.max_err = max(self.max_err, float((ctx.extra - ctx.alpha).detach().abs().max()))
        self.saw_jpeg.append(ctx.view.jpeg is not None)
        opac = torch.sigmoid(ctx.splats["opacities"]).mean()
        return HookOutput(terms={"opac": opac}, weights={"opac": 0.5}, stats={"alpha_mean": ctx.alpha.mean()})


def test_hook_terms_extra_channels_and_logging(tmp_path: Path) -> None:
    manifest = make_scene(tmp_path / "jpeg_scene", jpeg_train=True)
    hook = ExtraTerms()
    doc = train(manifest, tmp_path / "run", tiny_config(iterations=6, eval_at=[6]), hook=hook, progress=False)
    assert hook.max_err < 1e-5
    assert all(hook.saw_jpeg) and len(hook.saw_jpeg) == 6  # every training view is a JPEG here
    tr = doc["evals"][-1]["train"]
    assert set(tr["terms"]) == {"l1", "ssim", "photometric", "opac"} and set(tr["stats"]) == {"alpha_mean"}
    assert math.isclose(tr["loss"], tr["terms"]["photometric"] + 0.5 * tr["terms"]["opac"], rel_tol=1e-5)


def test_bad_hook_output_is_refused(scene: Path, tmp_path: Path) -> None:
    class NoWeight(LossHook):
        name = "noweight"

        def losses(self, ctx: StepContext) -> HookOutput:
            return HookOutput(terms={"x": ctx.render.mean()})

    with pytest.raises(JsgsError, match="loss term 'x' has no weight"):
        train(scene, tmp_path / "run", tiny_config(iterations=2), hook=NoWeight(), progress=False)


def test_unknown_method(scene: Path, tmp_path: Path) -> None:
    with pytest.raises(JsgsError, match=r"unknown method 'nope' \(available: .*gsplat"):
        train(scene, tmp_path / "run", tiny_config(iterations=2, method="nope"), progress=False)


def test_trainer_imports_without_dataset_tools() -> None:
    """A GPU machine needs torch, gsplat and small wheels only: no pycolmap, OpenCV or jsgstools."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "sys.modules['pycolmap'] = None; sys.modules['cv2'] = None\n"
        "import jsgs.train.trainer, jsgs.cli.train, jsgs.cli\n"
        "assert 'jsgstools' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_lpips_from_config_weights(tmp_path: Path) -> None:
    """eval.lpips_weights reaches the metric (uses ../shared/lpips; skipped without it)."""
    weights = ROOT.parent / "shared" / "lpips" / "alexnet_features.pth"
    if not weights.is_file():
        pytest.skip(f"needs {weights} (../shared beside the checkout), which is absent")
    manifest = make_scene(tmp_path / "scene40", width=40, height=32, n_views=3)
    cfg = tiny_config(iterations=2, eval_at=[2], eval__lpips_weights=str(weights))
    e = train(manifest, tmp_path / "run", cfg, progress=False)["evals"][-1]
    assert e["lpips"] is not None and 0.0 < e["lpips"] < 1.0 and e["lpips_note"] is None
    assert e["views"][0]["lpips"] == pytest.approx(e["lpips"])  # one test view


def test_view_camera_tensors_are_made_once_per_device(scene: Path) -> None:
    # the training step reads them every step; a fresh host-to-device copy each time is a GPU sync
    from jsgs.train.data import load_training_scene

    v = load_training_scene(scene, TrainConfig.from_preset("paper")).train_views[0]
    vm, K = v.viewmat_tensor(torch.device("cpu")), v.K_tensor("cpu")
    assert vm is v.viewmat_tensor("cpu") and K is v.K_tensor(torch.device("cpu"))
    assert vm.shape == (1, 4, 4) and K.shape == (1, 3, 3) and vm.dtype == K.dtype == torch.float32
    assert np.array_equal(vm[0].numpy(), v.viewmat.astype(np.float32))
    assert np.array_equal(K[0].numpy(), v.K.astype(np.float32))
    # the JSGS hook's copies in the parameters' dtype come from the same cache, one per dtype
    vm64 = v.viewmat_tensor("cpu", torch.float64)
    assert vm64 is v.viewmat_tensor(torch.device("cpu"), torch.float64) and vm64 is not vm
    assert vm64.dtype == torch.float64 and np.array_equal(vm64[0].numpy(), v.viewmat.astype(np.float64))


def test_ssim_kernel_cuda_is_refused_without_cuda(scene: Path, tmp_path: Path) -> None:
    cfg = TrainConfig.from_preset("paper", iterations=1, eval_at=[], device="cpu")
    cfg.speed.ssim_kernel = "cuda"
    match = r"config: speed.ssim_kernel cuda needs a CUDA device \(training on cpu\)"
    with pytest.raises(JsgsError, match=match):
        train(scene, tmp_path / "run", cfg, progress=False)


def test_callbacks_see_every_event_in_order(scene: Path, tmp_path: Path) -> None:
    """The Trainer calls its callbacks at step boundaries, evaluations, checkpoint points and the end; a
    callback's checkpoint point comes after the standard CheckpointSaver wrote the file."""
    from jsgs.train.callbacks import Callback, StepResult
    from jsgs.train.trainer import Trainer

    events: list[tuple[str, Any]] = []

    class Recorder(Callback):
        def on_setup(self, trainer: Trainer) -> None:
            events.append(("setup", trainer.start_step))

        def on_step_begin(self, trainer: Trainer, step: int) -> None:
            events.append(("begin", step))

        def on_step_end(self, trainer: Trainer, result: StepResult) -> None:
            assert math.isfinite(result.loss) and "photometric" in result.terms
            events.append(("end", result.step))

        def on_eval(self, trainer: Trainer, entry: dict[str, Any]) -> None:
            events.append(("eval", entry["step"]))

        def on_checkpoint(self, trainer: Trainer, step: int) -> None:
            assert trainer.last_checkpoint.endswith(f"step_{step:06d}.pt")
            events.append(("checkpoint", step))

        def on_end(self, trainer: Trainer, doc: dict[str, Any] | None) -> None:
            events.append(("done", None if doc is None else doc["status"]))

    cfg = tiny_config(iterations=4, eval_at=[2], checkpoint_every=3)
    train(scene, tmp_path / "run", cfg, progress=False, callbacks=[Recorder()], log=lambda s: None)
    assert events == [
        ("setup", 0),
        ("begin", 0), ("end", 0), ("begin", 1), ("end", 1), ("eval", 2), ("checkpoint", 2),
        ("begin", 2), ("end", 2), ("checkpoint", 3),
        ("begin", 3), ("end", 3), ("checkpoint", 4),
        ("done", "complete"),
    ]  # fmt: skip
    events.clear()
    # resumed from the last checkpoint of a stopped run: setup knows the step it continues from
    train(scene, tmp_path / "stopped", cfg, progress=False, stop_at=1, log=lambda s: None)
    rec = [Recorder()]
    train(scene, tmp_path / "stopped", progress=False, resume=True, callbacks=rec, log=lambda s: None)
    assert events[0] == ("setup", 1) and events[1] == ("begin", 1) and events[-1] == ("done", "complete")


def test_methods_are_named_not_imported_by_the_trainer() -> None:
    from jsgs.train.method import method_names, options_class

    assert method_names() == ["gsplat", "jsgs"]
    assert options_class("gsplat") is None
    assert options_class("jsgs").__name__ == "JsgsOptions"
    with pytest.raises(JsgsError, match=r"unknown method 'nerf' \(available: gsplat, jsgs\)"):
        options_class("nerf")
    with pytest.raises(JsgsError, match="config: method gsplat takes no method_options"):
        from_dict({"method": "gsplat", "method_options": {"jo": False}}).check()


def test_method_options_are_checked_with_the_method(tmp_path: Path) -> None:
    """A settings file naming its method gets its method_options checked on load; a partial one without a
    method (the method given later, e.g. by `jsgs bench --methods`) when the run starts."""
    named = tmp_path / "named.json"
    named.write_text(json.dumps({"method": "jsgs", "method_options": {"speed": {"cuda_graph": "on"}}}))
    match = r'named.json: method_options.speed.cuda_graph must be true, false or "auto"'
    with pytest.raises(JsgsError, match=match):
        load_config_file(named)
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"method_options": {"lambda_obs": 1.0}}))
    cfg = load_config_file(partial)
    cfg.check()  # the default method, jsgs, takes them
    cfg.method = "gsplat"
    with pytest.raises(JsgsError, match="method gsplat takes no method_options"):
        cfg.check()


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"optim": {"beta1": 5}}, r"optim.beta1 must be < 1.0 \(got 5.0\)"),
        ({"optim": {"means_lr": -1}}, r"optim.means_lr must be >= 0.0 \(got -1.0\)"),
        ({"render": {"near_plane": -1}}, r"render.near_plane must be > 0.0 \(got -1.0\)"),
        ({"render": {"near_plane": 2.0, "far_plane": 1.0}}, "far_plane .* must exceed render.near_plane"),
        ({"log_every": 0}, r"log_every must be >= 1 \(got 0\)"),
        ({"eval_at": [0, 5]}, r"eval_at must be >= 1 \(got 0\)"),
        ({"render": {"sh_degree": 5}}, r"render.sh_degree must be <= 4 \(got 5\)"),
        ({"method": "jsgs", "method_options": {"lambda_obs": -1}}, r"lambda_obs must be >= 0.0"),
    ],
)
def test_settings_out_of_range_are_one_line_errors(settings: dict[str, Any], message: str) -> None:
    """Bounds are checked when settings are read, before anything runs (an optimiser would otherwise fail
    with its own traceback, or a negative near plane train silently)."""
    with pytest.raises(JsgsError, match=message) as e:
        from_dict(settings, "cfg.json").check("cfg.json")
    assert str(e.value).startswith("cfg.json: ") and "\n" not in str(e.value)


def test_bounds_are_in_the_schema_and_hold_for_the_defaults() -> None:
    from jsgs.train.config import check_bounds, config_schema

    check_bounds(TrainConfig.from_preset("paper"), "defaults")
    props = config_schema()["$defs"]["settings"]["properties"]
    assert props["optim"]["properties"]["beta1"]["exclusiveMaximum"] == 1.0
    assert props["render"]["properties"]["near_plane"]["exclusiveMinimum"] == 0.0
    assert props["eval_at"]["items"]["minimum"] == 1


@pytest.mark.parametrize("method", ["gsplat", "jsgs"])
def test_a_view_that_sees_no_gaussian_is_a_counted_step(tmp_path: Path, method: str) -> None:
    """A training camera turned away from the scene renders nothing differentiable: its steps are logged and
    counted (train stats ``empty_view``: their fraction), never a crash; the other views train as usual."""
    manifest = make_scene(tmp_path / "scene", jpeg_train=method == "jsgs")
    doc = json.loads(manifest.read_text())
    away = next(v for v in doc["views"] if v["split"] == "train")
    R = np.asarray(away["R"])
    flip = np.diag([-1.0, 1.0, -1.0])  # half a turn about the camera's y axis: it looks the other way
    away["R"] = (flip @ R).tolist()
    away["t"] = (flip @ np.asarray(away["t"])).tolist()
    manifest.write_text(json.dumps(doc))
    n_train = sum(v["split"] == "train" for v in doc["views"])
    lines: list[str] = []
    cfg = tiny_config(iterations=2 * n_train, eval_at=[2 * n_train], method=method)
    out = train(manifest, tmp_path / "run", cfg, progress=False, log=lines.append)
    assert out["status"] == "complete"
    train_log = out["evals"][-1]["train"]
    assert train_log["stats"]["empty_view"] == pytest.approx(2 / (2 * n_train))  # each view twice
    assert train_log["per_view"][away["name"]]["steps"] == 2
    assert sum("sees no Gaussian" in s for s in lines) == 1


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signal_stops_after_the_step_with_a_checkpoint(scene: Path, tmp_path: Path, signame: str) -> None:
    """Ctrl-C (or SIGTERM) before the first evaluation keeps the training: the step in progress finishes, a
    checkpoint is written, metrics.json says stopped, and --resume ends where an uninterrupted run ends."""
    import os
    import signal

    from jsgs.train.callbacks import Callback
    from jsgs.train.trainer import TrainingInterrupted

    class Kill(Callback):
        def on_step_end(self, trainer: Any, result: Any) -> None:
            if result.step == 3:
                os.kill(os.getpid(), getattr(signal, signame))

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with pytest.raises(TrainingInterrupted, match=f"interrupted by {signame} after step 4 of 10"):
        cfg = tiny_config(iterations=10, eval_at=[10])
        train(scene, tmp_path / "b", cfg, progress=False, callbacks=[Kill()])
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    m = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert m["status"] == "stopped" and m["step"] == 4 and "continue with --resume" in m["error"]
    assert m["error"].endswith(" --resume") and " --out " in m["error"]
    assert (tmp_path / "b" / "checkpoints" / "step_000004.pt").is_file()
    train(scene, tmp_path / "b", None, resume=True, progress=False)
    train(scene, tmp_path / "a", tiny_config(iterations=10, eval_at=[10]), progress=False)
    ca = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000010.pt")
    cb = ckpt.load_checkpoint(tmp_path / "b" / "checkpoints" / "step_000010.pt")
    for name, t in ca["splats"].items():
        assert torch.equal(t, cb["splats"][name]), name


def test_one_writer_per_run_folder(scene: Path, tmp_path: Path) -> None:
    """A run folder is locked while a run writes it: a second writer is refused naming the holder; a lock
    left by a writer that no longer runs is taken over; the lock is gone when the run ends."""
    from jsgs.base.io import LOCK_NAME

    run = tmp_path / "run"
    run.mkdir()
    # a live process holds it (this test's parent stands in for another jsgs command)
    (run / LOCK_NAME).write_text(json.dumps({"pid": os.getppid(), "what": "jsgstools compress (into run)"}))
    holder = rf"in use by jsgstools compress \(into run\) \(PID {os.getppid()}\)"
    with pytest.raises(JsgsError, match=holder) as e:
        train(scene, run, tiny_config(iterations=2), progress=False)
    assert "\n" not in str(e.value) and sorted(p.name for p in run.iterdir()) == [LOCK_NAME]
    (run / LOCK_NAME).write_text(json.dumps({"pid": 2**22 + 12345, "what": "a killed run"}))  # no such PID
    train(scene, run, tiny_config(iterations=2), progress=False)
    assert not (run / LOCK_NAME).exists()
    assert json.loads((run / "metrics.json").read_text())["status"] == "complete"


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="needs /proc for start times")
def test_a_lock_whose_pid_was_reused_is_taken_over(scene: Path, tmp_path: Path) -> None:
    """The lock records its writer's start time: a PID that runs but started at another time is another
    process (the writer crashed and its PID was reused), so the lock is stale; the same start time holds."""
    from jsgs.base.io import LOCK_NAME, _start_time

    run = tmp_path / "run"
    run.mkdir()
    parent, start = os.getppid(), _start_time(os.getppid())
    assert start is not None
    (run / LOCK_NAME).write_text(json.dumps({"pid": parent, "what": "jsgs train (live)", "start": start}))
    with pytest.raises(JsgsError, match=rf"in use by jsgs train \(live\) \(PID {parent}\)"):
        train(scene, run, tiny_config(iterations=2), progress=False)
    (run / LOCK_NAME).write_text(json.dumps({"pid": parent, "what": "a crashed run", "start": start + 1}))
    train(scene, run, tiny_config(iterations=2), progress=False)
    assert not (run / LOCK_NAME).exists()
    assert json.loads((run / "metrics.json").read_text())["status"] == "complete"


def test_force_refuses_a_folder_that_holds_no_run(scene: Path, tmp_path: Path) -> None:
    other = tmp_path / "photos"
    other.mkdir()
    (other / "IMG_0001.jpg").write_bytes(b"not ours")
    (other / "config.json").write_text('{"camera": "mine"}')
    with pytest.raises(JsgsError, match="holds none .* choose another --out"):
        train(scene, other, tiny_config(iterations=2), progress=False, force=True)
    assert (other / "IMG_0001.jpg").read_bytes() == b"not ours"
    assert (other / "config.json").read_text() == '{"camera": "mine"}'


def test_progress_without_a_terminal_is_plain_lines(scene: Path, tmp_path: Path) -> None:
    """Where stderr is not a terminal (a log file), progress is one plain line every twentieth of the run:
    no carriage returns, the step, the time per step, the projected time to the end and the loss."""
    import re

    lines: list[str] = []
    train(scene, tmp_path / "run", tiny_config(iterations=40), progress=True, log=lines.append)
    steps = [s for s in lines if s.startswith("train: step ")]
    # every max(log_every, iterations // 20) = max(5, 2) steps
    assert [s.split()[2] for s in steps] == [f"{k}/40" for k in range(5, 41, 5)]
    assert all("\r" not in s and "loss=" in s and "#G=" in s for s in steps)
    pace = [re.search(r"([0-9.]+) ms/step, ETA (\d+):(\d\d)\b", s) for s in steps]
    assert all(p is not None and float(p[1]) > 0 for p in pace), steps
    # the last line has no step left: nothing to project
    assert pace[-1] is not None and pace[-1].groups()[1:] == ("0", "00")


def test_duration_reads_hours_minutes_seconds() -> None:
    from jsgs.train.callbacks import duration

    assert [duration(x) for x in (0, 59.6, 61, 3600, 3723, -5)] == ["0:00", "1:00", "1:01", "1:00:00",
                                                                     "1:02:03", "0:00"]  # fmt: skip


def test_a_write_that_fails_names_the_file_asked_for(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A full disk (or a read-only file system) shows up on the temporary file of an atomic write: the error
    names the file asked for, in one line, and leaves no temporary file behind."""
    import errno

    from jsgs.base.io import write_json_atomic

    real_replace = os.replace

    def full(src: Any, dst: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(src))

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(JsgsError, match=r"out.json: cannot write \(No space left on device\)$") as e:
        write_json_atomic(tmp_path / "out.json", {"a": 1})
    assert "\n" not in str(e.value) and ".part" not in str(e.value)
    monkeypatch.setattr(os, "replace", real_replace)
    assert list(tmp_path.iterdir()) == []


def test_children_die_with_their_parent(tmp_path: Path) -> None:
    """die_with_parent (the bench's trainings, compress's workers): when the parent is killed (SIGKILL, no
    cleanup of its own), the child gets SIGTERM from the kernel and ends."""
    import subprocess
    import sys
    import time

    pid_file = tmp_path / "child.pid"
    parent = "\n".join(
        [
            "import os, signal, subprocess, sys",
            "from jsgs.base.io import die_with_parent",
            "argv = [sys.executable, '-c', 'import time; time.sleep(60)']",
            "c = subprocess.Popen(argv, preexec_fn=die_with_parent)",
            f"open({str(pid_file)!r}, 'w').write(str(c.pid))",
            "os.kill(os.getpid(), signal.SIGKILL)",
        ]
    )
    subprocess.run([sys.executable, "-c", parent], check=False)
    child = int(pid_file.read_text())
    def ended() -> bool:  # gone, or a zombie that init has not reaped yet (it has ended all the same)
        try:
            stat = Path(f"/proc/{child}/stat").read_text() if Path("/proc").is_dir() else None
            os.kill(child, 0)
        except (ProcessLookupError, FileNotFoundError):
            return True
        return stat is not None and stat.rsplit(")", 1)[1].split()[0] in ("Z", "X")

    for _ in range(100):  # the kernel signals at once; give the child up to 10 s to end
        if ended():
            break
        time.sleep(0.1)
    else:
        os.kill(child, 9)
        pytest.fail("the child outlived its killed parent")


def _poses(rotations: list[np.ndarray], centres: list[np.ndarray]) -> np.ndarray:
    c2w = np.tile(np.eye(4), (len(centres), 1, 1))
    for i, (R, c) in enumerate(zip(rotations, centres, strict=True)):  # R world-to-camera
        c2w[i, :3, :3], c2w[i, :3, 3] = R.T, c
    return c2w


def test_normalisation_of_upright_cameras_is_a_rotation() -> None:
    """Every camera upright in a y-up world: the mean up is exactly camera +y, and the alignment is half a
    turn (det +1, the up onto camera up), not gsplat's mirror for that case; images are kept."""
    from jsgs.train.normalize import similarity_from_cameras

    R = np.diag([1.0, -1.0, -1.0])  # looks along world -z, camera -y (up) is world +y
    c2w = _poses([R] * 5, [np.array([0.4 * i - 1.0, 0.1 * i, 4.0 + 0.2 * i]) for i in range(5)])
    T = similarity_from_cameras(c2w)
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    assert s > 0 and np.allclose(T[:3, :3] @ [0.0, 1.0, 0.0] / s, [0.0, -1.0, 0.0])
    pts = np.random.default_rng(0).normal(size=(30, 3))
    c2w_n, pts_n, T = normalize_world(c2w, pts)
    assert np.linalg.det(T[:3, :3]) > 0
    for a, b in zip(c2w, c2w_n, strict=True):
        pa = (np.linalg.inv(a) @ np.c_[pts, np.ones(len(pts))].T)[:3]
        pb = (np.linalg.inv(b) @ np.c_[pts_n, np.ones(len(pts))].T)[:3]
        assert np.allclose(pa[:2] / pa[2], pb[:2] / pb[2], atol=1e-9) and np.linalg.det(b[:3, :3]) > 0


def _cancelling_ups(doc: dict[str, Any]) -> str:
    R = np.eye(3)
    for i, v in enumerate(doc["views"]):  # every other camera rolled by half a turn: the ups cancel
        Ri = np.diag([-1.0, -1.0, 1.0]) @ R if i % 2 else R
        v["R"], v["t"] = Ri.tolist(), (-Ri @ np.array([0.5 * i, 0.0, -4.0])).tolist()
    return "the cameras' up directions cancel out: their mean is zero"


def _most_on_focus(doc: dict[str, Any]) -> str:
    for i, v in enumerate(doc["views"]):  # four at the origin, the rest behind it on the common axis
        v["R"], v["t"] = np.eye(3).tolist(), [0.0, 0.0, float(max(0, i - 3))]
    return "most cameras sit at their common focus point: their median distance from it is 0"


@pytest.mark.parametrize("edit", [_cancelling_ups, _most_on_focus])
def test_degenerate_cameras_give_one_line_and_no_warning(scene: Path, tmp_path: Path, edit: Any) -> None:
    import shutil
    import warnings

    from _train_scene import edit_manifest
    from click.testing import CliRunner

    from jsgs.cli import main

    shutil.copytree(scene.parent, tmp_path / "s")
    manifest = tmp_path / "s" / scene.name
    why: list[str] = []
    edit_manifest(manifest, lambda d: why.append(edit(d)))
    args = ["train", str(manifest), "--out", str(tmp_path / "run"), "--iterations", "2", "--device", "cpu"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = CliRunner().invoke(main, args)
    assert [str(w.message) for w in caught] == []  # numpy's divide / invalid-value warnings were printed
    assert r.exit_code == 1 and r.output == (
        f"error: {manifest}: world normalisation failed: {why[0]}; set scene.normalize_world to false to "
        "train in the manifest's own units\n"
    )


def test_a_recorded_exchange_auto_reads_as_gsplat(tmp_path: Path) -> None:
    """A run recorded with ``speed.exchange: auto`` (gsplat's distributed rasterisation where it renders
    every training view, else torch) reads as ``gsplat``, which does that: its config.json loads (schema and
    settings) and its checkpoints' settings compare equal; other values and settings are kept."""
    from jsgs.train.config import current_values, recorded_settings

    recorded = ROOT / "docs" / "results" / "scale" / "runs" / "h200" / "llff_flower" / "gsplat" / "g2"
    doc = json.loads((recorded / "config.json").read_text())
    assert doc["settings"]["speed"]["exchange"] == "auto"
    cfg = load_config_file(recorded / "config.json")
    assert cfg.speed.exchange == "gsplat" and cfg.strategy.cap_max == 1_000_000
    assert recorded_settings(doc["settings"], "ckpt") == cfg
    settings = to_dict(TrainConfig())
    assert settings["speed"]["exchange"] == "torch" and current_values(settings) == settings
    assert current_values(None) is None
    with pytest.raises(JsgsError, match="speed.exchange must be one of"):
        from_dict({"speed": {"exchange": "auto"}})  # a --config file of settings says what it means
