"""Densification strategies (jsgs.train.strategy): gsplat's MCMCStrategy on the CPU through the torch twins of
its CUDA ops, the Gaussian budget, the mcmc preset, resume, and the twins against float64 and gsplat's
kernels."""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from pathlib import Path
from typing import Any

import pytest
import torch
from _lpips_backbone import random_backbone
from _train_scene import make_scene
from test_train import tiny_config

from jsgs.base.errors import JsgsError
from jsgs.kernels import compute_relocation, cpu_twins, quat_scale_to_covar
from jsgs.train import checkpoint as ckpt
from jsgs.train.callbacks import Callback
from jsgs.train.config import PRESETS, TrainConfig, from_dict, to_dict
from jsgs.train.strategy import Densifier, initial_subset
from jsgs.train.trainer import train


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_scene(tmp_path_factory.mktemp("scene"))


@pytest.fixture(scope="module")
def jpeg_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_scene(tmp_path_factory.mktemp("jscene"), jpeg_train=True)


def binoms(n_max: int = 51, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    b = torch.zeros(n_max, n_max, dtype=dtype)
    for n in range(n_max):
        for k in range(n + 1):
            b[n, k] = math.comb(n, k)
    return b


def relocation_direct(o: float, n: int) -> tuple[float, float]:
    """Equation (9) of the MCMC paper, term by term in Python floats (float64), as gsplat's kernel loops."""
    new_o = 1.0 - (1.0 - o) ** (1.0 / n)
    denom = 0.0
    for i in range(1, n + 1):
        for k in range(i):
            denom += math.comb(i - 1, k) * (-1.0) ** k / math.sqrt(k + 1) * new_o ** (k + 1)
    return new_o, o / denom


# ---------------------------------------------------------------------------------------------------------
# the twins


def test_relocation_twin_equals_the_formula_in_float64() -> None:
    g = torch.Generator().manual_seed(0)
    o = torch.rand(200, generator=g, dtype=torch.float64) * 0.98 + 0.01
    scales = torch.rand(200, 3, generator=g, dtype=torch.float64) + 0.01
    ratios = torch.randint(1, 30, (200,), generator=g)
    ratios[:3] = torch.tensor([1, 2, 29])
    new_o, new_s = compute_relocation(o, scales, ratios.clone(), binoms(dtype=torch.float64))
    for i in range(200):
        eo, coeff = relocation_direct(float(o[i]), int(ratios[i]))
        assert float(new_o[i]) == pytest.approx(eo, rel=1e-12, abs=1e-15)
        assert torch.allclose(new_s[i], coeff * scales[i], rtol=1e-10, atol=0)
    # n = 1 leaves a Gaussian as it is
    one = ratios == 1
    assert torch.allclose(new_o[one], o[one], rtol=1e-14) and torch.allclose(new_s[one], scales[one])


def test_relocation_twin_clamps_ratios_and_keeps_dtype() -> None:
    o = torch.tensor([0.5, 0.5, 0.999], dtype=torch.float32)
    s = torch.ones(3, 3)
    r = torch.tensor([0, 80, 51])
    new_o, new_s = compute_relocation(o, s, r, binoms())
    assert r.tolist() == [1, 51, 51]  # in place, as gsplat's wrapper does
    assert new_o.dtype == torch.float32 and new_s.dtype == torch.float32
    assert torch.isfinite(new_o).all() and torch.isfinite(new_s).all() and (new_s > 0).all()
    assert float(new_o[0]) == 0.5
    with pytest.raises(ValueError, match="expected"):
        compute_relocation(o, torch.ones(3, 2), r, binoms())


def test_covariance_twin_is_r_s2_rt() -> None:
    g = torch.Generator().manual_seed(1)
    q = torch.randn(50, 4, generator=g, dtype=torch.float64)
    s = torch.rand(50, 3, generator=g, dtype=torch.float64) + 0.05
    cov = quat_scale_to_covar(q, s)
    qn = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = qn.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(50, 3, 3)  # fmt: skip
    ref = R @ torch.diag_embed(s * s) @ R.transpose(1, 2)
    assert torch.allclose(cov, ref, rtol=1e-12, atol=1e-14)


def test_cpu_twins_are_routed_and_restored() -> None:
    from gsplat.strategy import ops

    before = ops.compute_relocation, ops.quat_scale_to_covar_preci
    with cpu_twins():
        o, s = ops.compute_relocation(
            opacities=torch.tensor([0.3]), scales=torch.ones(1, 3), ratios=torch.tensor([2]), binoms=binoms()
        )
        cov, preci = ops.quat_scale_to_covar_preci(
            torch.tensor([[1.0, 0, 0, 0]]), torch.ones(1, 3) * 2, compute_covar=True, compute_preci=False
        )
        assert preci is None and torch.allclose(cov, torch.eye(3) * 4)
        assert float(o[0]) == pytest.approx(1 - 0.7**0.5, rel=1e-6)
    assert (ops.compute_relocation, ops.quat_scale_to_covar_preci) == before


@pytest.mark.gpu
def test_relocation_twin_matches_gsplat_cuda() -> None:
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    from gsplat.relocation import compute_relocation as gsplat_relocation

    g = torch.Generator().manual_seed(2)
    o = (torch.rand(5000, generator=g) * 0.98 + 0.01).cuda()
    s = (torch.rand(5000, 3, generator=g) + 0.01).cuda()
    r = torch.randint(1, 20, (5000,), generator=g).cuda()
    b = binoms().cuda()
    go, gs = gsplat_relocation(o.clone(), s.clone(), r.clone(), b)
    to, ts = compute_relocation(o.clone(), s.clone(), r.clone(), b)
    assert torch.allclose(go, to, rtol=1e-5, atol=1e-7)
    assert torch.allclose(gs, ts, rtol=1e-4, atol=1e-7)


# ---------------------------------------------------------------------------------------------------------
# settings


def test_mcmc_preset_is_gsplat_simple_trainer_mcmc() -> None:
    from gsplat.strategy import MCMCStrategy

    cfg = TrainConfig.from_preset("mcmc")
    ref = MCMCStrategy()
    assert cfg.strategy.type == "mcmc"
    assert (cfg.init.opacity, cfg.init.scale) == (0.5, 0.1)
    assert (cfg.loss.opacity_reg, cfg.loss.scale_reg) == (0.01, 0.01)
    s = cfg.strategy
    # gsplat's MCMC values except the budget: sized to the scene (measured on the shared scenes; 300,000
    # when cap_max_auto is off) for its 1,000,000
    assert (s.noise_lr, s.min_opacity) == (ref.noise_lr, ref.min_opacity)
    assert s.cap_max_auto and s.cap_max == 300_000
    assert (s.refine_start_iter, s.refine_stop_iter, s.refine_every) == (
        ref.refine_start_iter, ref.refine_stop_iter, ref.refine_every,
    )  # fmt: skip
    assert set(PRESETS) == {"paper", "mcmc", "preview"}


def test_the_api_and_the_command_line_share_one_default() -> None:
    """TrainConfig() is the default preset's settings, JSGS's recipe included: what `jsgs train` gives
    without options. Another method gets its own recipe; a preset is asked for by name."""
    from jsgs.method.recipes import RECIPES
    from jsgs.train.config import DEFAULT_PRESET, command_settings

    assert TrainConfig() == command_settings() == TrainConfig.from_preset(DEFAULT_PRESET)
    assert TrainConfig().method_options == RECIPES[DEFAULT_PRESET] and TrainConfig().strategy.type == "mcmc"
    assert TrainConfig(method="gsplat") == command_settings(overrides={"method": "gsplat"})
    assert TrainConfig(method="gsplat").method_options == {}
    assert from_dict({"method": "gsplat"}) == TrainConfig(method="gsplat")  # a document changing the method
    assert from_dict({"method": "jsgs"}, base=TrainConfig(method="gsplat")) == TrainConfig()
    for name in PRESETS:
        assert TrainConfig.from_preset(name) == command_settings(preset_name=name)
    paper = TrainConfig.from_preset("paper", method="gsplat", iterations=20)
    assert (paper.method, paper.method_options, paper.iterations) == ("gsplat", {}, 20)
    assert paper.strategy.type == "default" and TrainConfig.from_preset("paper").method_options == {}
    with pytest.raises(JsgsError, match="--preset: 'fast' is not one of mcmc, paper, preview"):
        TrainConfig.from_preset("fast")


def test_a_recorded_run_missing_a_newer_key_reads_it_as_the_paper_value(tmp_path: Path) -> None:
    """A config.json written before a setting existed lacks it: it meant the value of that time (the strategy:
    the paper preset's DefaultStrategy, not the mcmc default of today). A setting every version recorded
    that changes what a run trains is not guessed: one line names the file and the setting."""
    from jsgs.train.config import recorded_settings

    settings = to_dict(TrainConfig.from_preset("paper"))
    del settings["strategy"]["type"], settings["strategy"]["cap_max_auto"]
    del settings["optim"]["means_lr_decay_steps"]
    cfg = recorded_settings(settings, "old/config.json")
    assert cfg == TrainConfig.from_preset("paper") and cfg.strategy.type == "default"
    del settings["loss"]["opacity_reg"]
    with pytest.raises(JsgsError, match=r"^old/config.json: lacks the setting loss.opacity_reg, which chan"):
        recorded_settings(settings, "old/config.json")


def test_the_mcmc_preset_trains_simple_trainers_length() -> None:
    """simple_trainer's Config: max_steps 30,000, eval_steps [7,000, 30,000]; the means' learning rate decays
    over the whole run (its ExponentialLR with gamma 0.01 ** (1 / max_steps)); MCMC refines until 25,000.
    The paper's preset keeps the paper's 10,000 steps."""
    from jsgs.train.config import command_settings, preset_iterations

    cfg = command_settings()
    assert (cfg.iterations, cfg.eval_at) == (30_000, [7_000, 30_000])
    assert cfg.strategy.refine_stop_iter == 25_000 and cfg.optim.means_lr_decay_steps == 0
    paper = command_settings(preset_name="paper")
    assert (paper.iterations, paper.eval_at) == (10_000, [3000, 7000, 10_000])
    assert (preset_iterations("mcmc"), preset_iterations("paper")) == (30_000, 10_000)
    # --iterations N without --eval-at: the preset's steps below N, and N
    assert command_settings(overrides={"iterations": 12_000}).eval_at == [7000, 12_000]
    assert command_settings(overrides={"iterations": 40_000}).eval_at == [7000, 30_000, 40_000]
    assert command_settings(overrides={"iterations": 500}, preset_name="paper").eval_at == [500]
    given = command_settings(overrides={"iterations": 12_000, "eval_at": [100]}, eval_at_given=True)
    assert given.eval_at == [100]


def test_a_config_file_that_shortens_the_run_cuts_the_presets_evaluations(tmp_path: Path) -> None:
    from jsgs.train.config import command_settings

    part = tmp_path / "part.json"
    part.write_text('{"iterations": 1500}')
    cfg = command_settings(config_file=part)
    assert (cfg.iterations, cfg.eval_at) == (1500, [1500])
    cfg.check()
    part.write_text('{"iterations": 1500, "eval_at": [700, 1500]}')
    assert command_settings(config_file=part).eval_at == [700, 1500]


def test_the_means_decay_reaches_its_floor_at_the_recipes_length_and_goes_on() -> None:
    """means_lr_decay_steps = N: a run of 2N steps follows a run of N steps' learning rates exactly up to N
    (where it reaches the final factor), then decays on at the same rate."""
    from jsgs.train.model import make_means_scheduler

    def lrs(iterations: int, decay: int) -> list[float]:
        cfg = TrainConfig.from_preset("paper", iterations=iterations)
        cfg.optim.means_lr_decay_steps = decay
        opt = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
        sched = make_means_scheduler(opt, cfg)
        out = []
        for _ in range(iterations):
            opt.step()
            sched.step()
            out.append(sched.get_last_lr()[0])
        return out

    short, long = lrs(50, 0), lrs(100, 50)
    assert long[:50] == short and short[-1] == pytest.approx(0.01)
    assert long[-1] == pytest.approx(1e-4) and lrs(100, 0)[:50] != short


def test_a_new_run_starts_from_the_mcmc_preset(tmp_path: Path) -> None:
    from jsgs.method.recipes import RECIPES
    from jsgs.train.config import DEFAULT_PRESET, command_settings

    assert DEFAULT_PRESET == "mcmc"
    # a new run trains JSGS, with the preset's recipe for it
    new = command_settings()
    assert new.method == "jsgs" and new.method_options == RECIPES["mcmc"]
    assert new == TrainConfig.from_preset("mcmc") == TrainConfig()
    assert command_settings(preset_name="paper") == TrainConfig.from_preset("paper")
    baseline = command_settings(overrides={"method": "gsplat"})
    assert baseline == dataclasses.replace(TrainConfig(), method="gsplat", method_options={})
    part = tmp_path / "part.json"
    part.write_text('{"iterations": 50, "eval_at": [50]}')
    cfg = command_settings(config_file=part)
    assert cfg.strategy.type == "mcmc" and cfg.iterations == 50  # a partial file over the default preset
    resumed = command_settings(resume_settings=TrainConfig.from_preset("paper"))
    assert resumed.strategy.type == "default"  # a resumed run keeps its own settings


def test_each_method_brings_its_recipes_and_switches_through_the_registry() -> None:
    """JSGS's recipes and switches live in its package and reach the settings through the method registry;
    the baseline has neither."""
    from jsgs.method.options import parse_options
    from jsgs.method.recipes import RECIPES
    from jsgs.train.config import command_settings
    from jsgs.train.method import method_flags, method_recipe

    assert set(RECIPES) <= set(PRESETS) and method_flags("gsplat") == ()
    assert all(method_recipe("gsplat", p) == {} for p in PRESETS)
    recipe = method_recipe("jsgs", "mcmc")
    assert recipe == RECIPES["mcmc"] and recipe is not RECIPES["mcmc"]  # a copy: callers may change it
    flags = method_flags("jsgs")
    names = ["--jpeg-mode", "--tables", "--compile", "--no-jo", "--no-ds", "--no-gc"]
    assert [f.flag for f in flags] == names
    for f in flags:  # each switch sets a real option to a value it takes; a choice switch offers them all
        opts = parse_options({"ds": False, "gc": False, **f.options(f.choices[-1] if f.choices else True)})
        section, name = (opts.speed, "compile") if f.option == "speed.compile" else (opts, f.option)
        assert getattr(section, name) == (f.choices[-1] if f.choices else f.value)
        if f.choices:
            assert set(f.choices) == set(typing.get_args(typing.get_type_hints(type(section))[name]))
    with pytest.raises(JsgsError, match="^--jpeg-mode, --tables, .* and --no-gc apply to --method jsgs"):
        command_settings(preset_name="preview", switches={"--tables": "effective"})
    from jsgs.cli.train import recipes_text  # the help of --preset names each method's recipe

    words = "lambda_obs 1, base_by_view, base_noise pixels, base_noise_ref 2, base_noise_exponent 2"
    words += ", gc_every 4"
    assert recipes_text("mcmc") == f"; for --method jsgs: method_options {words}"
    assert recipes_text("paper") == recipes_text("preview") == ""


def test_the_mcmc_preset_gives_jsgs_its_recipe_under_the_users_options(tmp_path: Path) -> None:
    from jsgs.method.options import parse_options
    from jsgs.method.recipes import RECIPES
    from jsgs.train.config import command_settings

    recipe = RECIPES["mcmc"]
    assert command_settings(overrides={"method": "jsgs"}).method_options == recipe
    opts = parse_options(recipe)
    assert (opts.lambda_obs, opts.base_by_view, opts.base_noise) == (1.0, True, "pixels")
    assert (opts.base_noise_ref, opts.base_noise_exponent, opts.gc_every) == (2.0, 2.0, 4)
    # gsplat takes no options; the paper preset keeps the paper's weights (the options' own defaults)
    assert command_settings(overrides={"method": "gsplat"}).method_options == {}
    assert command_settings(overrides={"method": "jsgs"}, preset_name="paper").method_options == {}
    # the config file and the switches apply over the recipe
    part = tmp_path / "part.json"
    part.write_text('{"method": "jsgs", "method_options": {"base_noise_ref": 4.0}}')
    cfg = command_settings(config_file=part, switches={"--no-ds": True, "--compile": "aot_eager"})
    speed = {"speed": {"compile": "aot_eager"}}
    assert cfg.method_options == {**recipe, "base_noise_ref": 4.0, "ds": False, **speed}
    # an earlier run's config.json is complete: nothing is added to it, and a resumed run keeps its own
    run_cfg = tmp_path / "config.json"
    run_cfg.write_text(json.dumps({"format": "x", "settings": {"method": "jsgs"}}))
    from jsgs.train.config import is_run_config

    assert is_run_config(json.loads(run_cfg.read_text())) and not is_run_config(json.loads(part.read_text()))
    resumed = command_settings(resume_settings=TrainConfig.from_preset("paper", method="jsgs"))
    assert resumed.method_options == {}


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"strategy": {"type": "mcmc", "cap_max": 0}}, "strategy.cap_max must be >= 1"),
        ({"strategy": {"type": "mcmc", "noise_lr": -1.0}}, r"strategy.noise_lr must be >= 0.0 \(got -1.0\)"),
        ({"strategy": {"min_opacity": 1.0}}, r"strategy.min_opacity must be < 1.0"),
        ({"strategy": {"type": "relocate"}}, "strategy.type"),
    ],
)
def test_bad_strategy_settings_are_one_line_errors(settings: dict[str, Any], message: str) -> None:
    with pytest.raises(JsgsError, match=message) as e:
        from_dict(settings, "cfg.json").check("cfg.json")
    assert "\n" not in str(e.value) and "cfg.json" in str(e.value)


def test_preset_under_config_file_and_cli(scene: Path, tmp_path: Path) -> None:
    from click.testing import CliRunner

    from jsgs.cli import main

    cfg_file = tmp_path / "c.json"
    cfg_file.write_text(json.dumps({"strategy": {"cap_max": 90}, "init": {"opacity": 0.2}}))
    r = CliRunner().invoke(
        main,
        ["train", str(scene), "--out", str(tmp_path / "run"), "--preset", "mcmc", "--config", str(cfg_file),
         "--iterations", "3", "--eval-at", "", "--device", "cpu", "--quiet"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "run" / "config.json").read_text())["settings"]
    assert s["strategy"]["type"] == "mcmc" and s["strategy"]["cap_max"] == 90  # the file over the preset
    assert s["strategy"]["cap_max_auto"] is False  # a budget written in a file is that fixed budget
    assert s["init"]["opacity"] == 0.2 and s["init"]["scale"] == 0.1 and s["loss"]["scale_reg"] == 0.01
    r = CliRunner().invoke(main, ["train", str(scene), "--out", str(tmp_path / "run"), "--preset", "mcmc",
                                  "--resume"])  # fmt: skip
    assert r.exit_code == 1 and "--preset applies to a new run" in r.output


def test_initial_subset() -> None:
    assert initial_subset(10, None, 0) is None and initial_subset(10, 10, 0) is None
    keep = initial_subset(100, 30, 3)
    assert keep is not None and len(keep) == 30 and len(set(keep.tolist())) == 30
    assert keep.tolist() == sorted(keep.tolist()) and torch.equal(keep, initial_subset(100, 30, 3))


# ---------------------------------------------------------------------------------------------------------
# training


class Counts(Callback):
    def __init__(self) -> None:
        self.counts: list[int] = []

    def on_step_end(self, trainer: Any, result: Any) -> None:
        self.counts.append(len(trainer.splats["means"]))


def mcmc_config(**kw: Any) -> TrainConfig:
    # the mcmc preset's init, losses and strategy (where they differ from the paper's), the tiny run's length
    mcmc = to_dict(TrainConfig.from_preset("mcmc"))
    sections = {k: v for k, v in PRESETS["paper"].items() if k not in ("iterations", "eval_at")}
    recipe = {name: {k: mcmc[name][k] for k in section} for name, section in sections.items()}
    cfg = from_dict(recipe, "preset", base=tiny_config(**kw))
    cfg.strategy.refine_start_iter = 1
    cfg.strategy.refine_every = 2
    cfg.strategy.cap_max_auto = False  # the tests' fixed budgets (cap_max), not the scene's
    return cfg


def test_mcmc_grows_to_the_cap_and_no_further(scene: Path, tmp_path: Path) -> None:
    """Each refinement adds 5 % (at least one) until cap_max; dead Gaussians are relocated, never removed."""
    start = len(json.loads(Path(scene).read_text())["points"]["xyz"])
    cap = start + 6
    cfg = mcmc_config(iterations=16)
    cfg.strategy.cap_max = cap
    cb = Counts()
    train(scene, tmp_path / "run", cfg, progress=False, callbacks=[cb])
    assert cb.counts[0] == start
    assert max(cb.counts) == cap and cb.counts[-1] == cap
    assert cb.counts == sorted(cb.counts)  # never pruned
    for a, b in zip(cb.counts, cb.counts[1:], strict=False):
        assert b in (a, min(cap, int(1.05 * a))), (a, b)  # gsplat's rule: +5 % per refinement, up to the cap
    state = ckpt.load_checkpoint(tmp_path / "run" / "checkpoints" / "step_000016.pt")
    assert state["optimizers"]["means"]["state"][0]["exp_avg"].shape == (cap, 3)
    assert "binoms" in state["strategy"]


def test_budget_below_the_initial_points_starts_from_a_subset(scene: Path, tmp_path: Path) -> None:
    cfg = mcmc_config(iterations=4)
    cfg.strategy.cap_max = 25
    lines: list[str] = []
    cb = Counts()
    train(scene, tmp_path / "run", cfg, progress=False, callbacks=[cb], log=lines.append)
    assert cb.counts and max(cb.counts) <= 25
    assert any("exceed strategy.cap_max = 25" in s for s in lines), lines


def test_mcmc_resume_is_bit_exact(scene: Path, tmp_path: Path) -> None:
    """Relocation and sampling draw from the global generator and change the optimizer states' shapes: a
    run cut at step 7 and resumed equals the uninterrupted one exactly."""

    def cfg() -> TrainConfig:
        c = mcmc_config(iterations=14, eval_at=[7, 14])
        c.strategy.cap_max = 120
        c.strategy.min_opacity = 0.3  # relocations happen in these few steps
        return c

    train(scene, tmp_path / "a", cfg(), progress=False)
    train(scene, tmp_path / "b", cfg(), stop_at=7, progress=False)
    train(scene, tmp_path / "b", None, resume=True, progress=False)
    ca = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000014.pt")
    cb = ckpt.load_checkpoint(tmp_path / "b" / "checkpoints" / "step_000014.pt")
    n7 = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000007.pt")["splats"]["means"].shape[0]
    assert n7 < ca["splats"]["means"].shape[0], "the model should grow after the cut"
    for name, t in ca["splats"].items():
        assert torch.equal(t, cb["splats"][name]), name
    for name in ca["optimizers"]:
        sa, sb = ca["optimizers"][name]["state"][0], cb["optimizers"][name]["state"][0]
        for k in sa:
            assert torch.equal(sa[k], sb[k]), (name, k)


def test_mcmc_resume_is_bit_exact_across_a_first_lpips_evaluation(tmp_path: Path) -> None:
    """A resumed run is a new process: its first evaluation builds the LPIPS model again, where the run
    that went on had it already. Building it must not touch the global generator that MCMC's noise and
    relocation draw from, or the steps after that evaluation differ."""
    from jsgs.metrics import lpips as L

    scene = make_scene(tmp_path / "scene", width=40, height=32)  # LPIPS needs sides >= 31
    weights = tmp_path / "alexnet.pth"
    torch.save(random_backbone(), weights)

    def cfg() -> TrainConfig:
        c = mcmc_config(iterations=14, eval_at=[4, 10, 14])
        c.strategy.cap_max = 120
        c.strategy.min_opacity = 0.3
        c.eval.lpips_weights = str(weights)
        return c

    L._CACHE.clear()
    doc = train(scene, tmp_path / "a", cfg(), progress=False)
    assert doc["evals"][-1]["lpips"] is not None
    L._CACHE.clear()
    train(scene, tmp_path / "b", cfg(), stop_at=7, progress=False)
    L._CACHE.clear()  # the resumed run's process has no model yet: its evaluation at step 10 builds one
    train(scene, tmp_path / "b", None, resume=True, progress=False)
    ca = ckpt.load_checkpoint(tmp_path / "a" / "checkpoints" / "step_000014.pt")
    cb = ckpt.load_checkpoint(tmp_path / "b" / "checkpoints" / "step_000014.pt")
    for name, t in ca["splats"].items():
        assert torch.equal(t, cb["splats"][name]), name


def test_jsgs_trains_with_relocated_gaussians(jpeg_scene: Path, tmp_path: Path) -> None:
    """The JSGS method (JO, DS and the Gaussian Controller) on a model whose Gaussians are relocated and
    added every other step: finite terms, the GC active, the budget kept."""
    cfg = mcmc_config(iterations=12, eval_at=[12])
    cfg.method = "jsgs"
    cfg.strategy.cap_max = 90
    cfg.strategy.min_opacity = 0.3
    cb = Counts()
    doc = train(jpeg_scene, tmp_path / "run", cfg, progress=False, callbacks=[cb])
    assert doc["status"] == "complete"
    assert max(cb.counts) == 90
    e = doc["evals"][-1]
    assert math.isfinite(e["psnr"]) and e["num_gaussians"] == 90
    assert all(math.isfinite(v) for v in e["train"]["terms"].values()), e["train"]


def test_densifier_refuses_an_unknown_type() -> None:
    cfg = TrainConfig.from_preset("paper")
    cfg.strategy.type = "relocate"  # type: ignore[assignment]
    with pytest.raises(JsgsError, match="strategy.type"):
        Densifier(cfg.strategy)
