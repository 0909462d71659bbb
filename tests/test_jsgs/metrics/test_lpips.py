"""LPIPS-alex v0.1: the official distances, the network's structure, and honest failure without weights."""

from __future__ import annotations

import hashlib
import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from _lpips_backbone import random_backbone
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.metrics import lpips as L

SHARED = Path(__file__).resolve().parents[4] / "shared" / "lpips"
WEIGHTS = SHARED / "alexnet_features.pth"
REF = SHARED / "reference"
needs_shared = pytest.mark.skipif(
    not WEIGHTS.is_file(), reason=f"LPIPS backbone weights not available ({WEIGHTS} absent)"
)

# ../shared/lpips/README.md (= reference/pyiqa/results_official.csv): original implementation, real weights
OFFICIAL = {"I03": 0.7237, "I04": 0.2572, "I06": 0.05079, "I08": 0.05205, "I19": 0.4253}
# same README: the lpips project's example images, regression values (6 decimals)
EXAMPLES = {"ex_p0": 0.721881, "ex_p1": 0.137566}


def load_png(path: Path) -> torch.Tensor:
    """1 x 3 x H x W float32 in [0, 1]."""
    arr = np.array(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0
    return torch.from_numpy(arr).permute(2, 0, 1)[None]


def round_sig(x: float, digits: int) -> float:
    return round(x, digits - 1 - math.floor(math.log10(abs(x))))


@pytest.fixture(autouse=True)
def _fresh_state(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test sees no environment variable, an empty note-once memory and no failed download."""
    monkeypatch.delenv(L.ENV_VAR, raising=False)
    monkeypatch.setattr(L, "_warned", set())
    monkeypatch.setattr(L, "_download_failure", None)


@pytest.fixture(scope="module")
def model() -> L.LpipsAlex:
    if not WEIGHTS.is_file():
        pytest.skip(f"LPIPS backbone weights not available ({WEIGHTS} absent)")
    m = L.load_lpips(WEIGHTS)
    assert m is not None
    return m


@needs_shared
@pytest.mark.parametrize("name", sorted(OFFICIAL))
def test_official_values(model: L.LpipsAlex, name: str) -> None:
    """Both criteria hold: |ours - official| <= 1e-4, and ours rounded to the table's 4 significant digits
    is the table's value."""
    ref = load_png(REF / "pyiqa" / "ref" / f"{name}.png")
    dist = load_png(REF / "pyiqa" / "dist" / f"{name}.png")
    with torch.no_grad():
        ours = float(model(ref * 2 - 1, dist * 2 - 1)[0])
    assert abs(ours - OFFICIAL[name]) <= 1e-4, (name, ours)
    assert round_sig(ours, 4) == pytest.approx(OFFICIAL[name], abs=1e-12), (name, ours)


@needs_shared
def test_example_pairs_regression() -> None:
    """The public function (inputs in [0, 1]) on the lpips project's example images, to 1e-5."""
    ref = load_png(REF / "ex_ref.png")
    for name, expected in EXAMPLES.items():
        d = L.lpips(ref, load_png(REF / f"{name}.png"), weights=WEIGHTS)
        assert d is not None and d.shape == (1,)
        assert abs(float(d[0]) - expected) <= 1e-5, (name, float(d[0]))


@needs_shared
def test_env_var_batch_symmetry_identity(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(L.ENV_VAR, str(WEIGHTS))
    ref, p0, p1 = (load_png(REF / f"{n}.png") for n in ("ex_ref", "ex_p0", "ex_p1"))
    with torch.no_grad():
        batch = L.lpips(torch.cat([ref, ref, ref]), torch.cat([p0, p1, ref]))
        swapped = L.lpips(torch.cat([p0, p1]), torch.cat([ref, ref]))
    assert batch is not None and swapped is not None
    assert batch[0].item() == pytest.approx(EXAMPLES["ex_p0"], abs=1e-5)
    assert batch[1].item() == pytest.approx(EXAMPLES["ex_p1"], abs=1e-5)
    assert batch[2].item() == 0.0
    assert torch.allclose(swapped, batch[:2], atol=1e-6)


@needs_shared
def test_gradient_matches_finite_differences(model: L.LpipsAlex) -> None:
    """The input gradient (what a perceptual loss would use) equals central differences, in float64."""
    import copy

    m = copy.deepcopy(model).double()
    g64 = torch.Generator().manual_seed(0)
    x = (torch.rand(1, 3, 40, 48, generator=g64, dtype=torch.float64) * 2 - 1).requires_grad_()
    y = torch.rand(1, 3, 40, 48, generator=g64, dtype=torch.float64) * 2 - 1
    m(x, y).sum().backward()
    assert x.grad is not None
    eps = 1e-6
    for idx in [(0, 0, 5, 7), (0, 1, 20, 30), (0, 2, 39, 47), (0, 0, 33, 2)]:
        xp, xm = x.detach().clone(), x.detach().clone()
        xp[idx] += eps
        xm[idx] -= eps
        with torch.no_grad():
            fd = float((m(xp, y).sum() - m(xm, y).sum()) / (2 * eps))
        assert abs(fd - float(x.grad[idx])) <= 1e-5 * max(1e-3, abs(fd)), (idx, fd, float(x.grad[idx]))


def test_no_weights_notes_once_and_returns_none(capsys: pytest.CaptureFixture[str]) -> None:
    x = torch.rand(1, 3, 32, 32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert L.lpips(x, x) is None
        assert L.lpips(x, x) is None
        assert L.load_lpips() is None
    assert caught == []  # a note for the user, not a Python warning with a source location
    out = capsys.readouterr()
    assert out.out == "" and out.err == f"note: {L.UNAVAILABLE_MESSAGE}\n"
    assert L.ENV_VAR in out.err and "alexnet_features.pth" in out.err


def _hub_file(tmp_path: Path, state: dict[str, torch.Tensor], corrupt: bool = False) -> str:
    """A weights file named as torchvision names its downloads (``-<SHA-256 prefix>.pth``); ``corrupt``
    names it with a prefix that does not match. Returns its file:// URL."""
    raw = tmp_path / "raw.pth"
    torch.save(state, raw)
    digest = hashlib.sha256(raw.read_bytes()).hexdigest()[:8]
    if corrupt:
        digest = "0" * 8 if digest != "0" * 8 else "1" * 8
    named = tmp_path / "srv" / f"alexnet-owt-{digest}.pth"
    named.parent.mkdir()
    raw.rename(named)
    return named.as_uri()


def test_download_keeps_the_convolutions_in_the_hub_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No path and no variable: the backbone is downloaded once (hash checked), its ``features.*`` kept in
    torch's hub cache, the full file deleted; the next call reads the cache without downloading."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "home"))
    monkeypatch.setenv(L.DOWNLOAD_ENV_VAR, "1")
    full = {**random_backbone(3), "classifier.1.weight": torch.zeros(4, 4)}
    monkeypatch.setattr(L, "ALEXNET_URL", _hub_file(tmp_path, full))
    path = L.resolve_weights()
    assert path == tmp_path / "home" / "hub" / "checkpoints" / L.CACHE_NAME
    kept = torch.load(path, weights_only=True)
    assert sorted(kept) == sorted(k for k in full if k.startswith("features."))
    for k, v in kept.items():
        assert torch.equal(v, full[k])
    assert [p.name for p in path.parent.iterdir()] == [L.CACHE_NAME]  # no full copy, no temp folder left
    monkeypatch.setattr(L, "download_backbone", lambda *a: pytest.fail("downloaded twice"))
    assert L.resolve_weights() == path


def test_download_with_a_wrong_hash_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "home"))
    url = _hub_file(tmp_path, random_backbone(4), corrupt=True)
    with pytest.raises(JsgsError, match="download rejected: .*invalid hash value"):
        L.download_backbone(url)
    assert not (tmp_path / "home" / "hub" / "checkpoints" / L.CACHE_NAME).exists()


def test_download_offline_is_tried_once_and_noted_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Offline: one failed download per process, no ``Downloading:`` line, no Python warning, and one line
    saying how to get the weights, with the reason."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "home"))
    monkeypatch.setenv(L.DOWNLOAD_ENV_VAR, "1")
    missing = (tmp_path / "nowhere" / "alexnet-owt-7be5be79.pth").as_uri()
    monkeypatch.setattr(L, "ALEXNET_URL", missing)
    real = L.download_backbone
    calls: list[str | None] = []
    monkeypatch.setattr(L, "download_backbone", lambda url=None: calls.append(url) or real(url))
    x = torch.rand(1, 3, 32, 32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):  # three evaluations of one run
            assert L.lpips(x, x) is None
    assert caught == [] and len(calls) == 1
    out = capsys.readouterr()
    assert out.out == ""  # torch.hub's "Downloading: ..." is not shown
    lines = out.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"note: {L.UNAVAILABLE_MESSAGE} (the download failed: ")
    assert missing in lines[0]


def test_download_off_gives_null(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "home"))
    monkeypatch.setenv(L.DOWNLOAD_ENV_VAR, "0")
    monkeypatch.setattr(L, "download_backbone", lambda *a: pytest.fail("download attempted"))
    assert L.resolve_weights() is None


def test_named_missing_weights_is_an_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(JsgsError, match="not found"):
        L.load_lpips(tmp_path / "nope.pth")
    monkeypatch.setenv(L.ENV_VAR, str(tmp_path / "nope.pth"))
    with pytest.raises(JsgsError, match=r"\$JSGS_LPIPS_WEIGHTS"):
        L.load_lpips()


def test_malformed_backbone_files(tmp_path: Path) -> None:
    good = random_backbone()
    bad_shape = dict(good, **{"features.3.weight": torch.zeros(192, 64, 3, 3)})
    torch.save(bad_shape, tmp_path / "shape.pth")
    with pytest.raises(JsgsError, match="features.3.weight"):
        L.load_backbone(tmp_path / "shape.pth")
    torch.save({k: v for k, v in good.items() if k != "features.10.bias"}, tmp_path / "missing.pth")
    with pytest.raises(JsgsError, match="features.10.bias"):
        L.load_backbone(tmp_path / "missing.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(JsgsError, match="cannot read"):
        L.load_backbone(tmp_path / "junk.pth")
    # a full torchvision AlexNet state dict (with the classifier) is accepted; extra keys are ignored
    torch.save(dict(good, **{"classifier.1.weight": torch.zeros(8, 8)}), tmp_path / "full.pth")
    assert set(L.load_backbone(tmp_path / "full.pth")) == set(good)


def test_vendored_heads() -> None:
    assert hashlib.sha256(L.HEADS_PATH.read_bytes()).hexdigest() == L.HEADS_SHA256
    assert (L.HEADS_PATH.parent / "LICENSE.lpips").is_file()
    heads = L.load_heads()
    assert [h.shape[1] for h in heads] == [64, 192, 384, 256, 256]
    assert sum(h.numel() for h in heads) == 1152
    assert all(float(h.min()) >= 0 for h in heads)  # lpips clamps the heads to be non-negative


def test_tampered_heads_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    copy = tmp_path / "alex.pth"
    shutil.copy(L.HEADS_PATH, copy)
    data = bytearray(copy.read_bytes())
    data[-20] ^= 0x01
    copy.write_bytes(bytes(data))
    monkeypatch.setattr(L, "HEADS_PATH", copy)
    with pytest.raises(JsgsError, match="SHA-256"):
        L.load_heads()


class ReferenceLpips(torch.nn.Module):
    """The lpips package's structure written out independently (torchvision-style ``features`` Sequential
    sliced at the same indices as ``lpips.pretrained_networks.alexnet``), in float64."""

    def __init__(self, backbone: dict[str, torch.Tensor], heads: list[torch.Tensor]) -> None:
        super().__init__()
        nn = torch.nn
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        )  # fmt: skip
        self.features.load_state_dict({k.removeprefix("features."): v for k, v in backbone.items()})
        self.heads = [h.double() for h in heads]
        self.double()

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64)[None, :, None, None]
        scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64)[None, :, None, None]
        x, y = (x.double() - shift) / scale, (y.double() - shift) / scale
        total = torch.zeros(x.shape[0], dtype=torch.float64)
        bounds = [(0, 2), (2, 5), (5, 8), (8, 10), (10, 12)]
        for (a, b), head in zip(bounds, self.heads, strict=True):
            x, y = self.features[a:b](x), self.features[a:b](y)
            nx = x / (torch.sqrt((x**2).sum(1, keepdim=True)) + 1e-10)
            ny = y / (torch.sqrt((y**2).sum(1, keepdim=True)) + 1e-10)
            total = total + F.conv2d((nx - ny) ** 2, head).mean(dim=(2, 3))[:, 0]
        return total


def test_structure_matches_independent_reference() -> None:
    """Without the real backbone (CI without ../shared): random backbone, real heads, non-square image;
    our float32 module agrees with a float64 transcription of the lpips package's network."""
    backbone, heads = random_backbone(3), L.load_heads()
    ours = L.LpipsAlex(backbone, heads)
    ref = ReferenceLpips(backbone, heads)
    g = torch.Generator().manual_seed(7)
    x = torch.rand(2, 3, 67, 45, generator=g) * 2 - 1
    y = (x + 0.3 * torch.randn(2, 3, 67, 45, generator=g)).clamp(-1, 1)
    with torch.no_grad():
        d_ours, layers = ours(x, y, per_layer=True)
        d_ref = ref(x, y)
    assert d_ours.dtype == torch.float32 and d_ours.shape == (2,)
    assert torch.allclose(d_ours.double(), d_ref, rtol=1e-5, atol=1e-7), (d_ours, d_ref)
    assert torch.allclose(torch.stack(layers).sum(0), d_ours)
    assert all(float(v.min()) >= 0 for v in layers)


def test_input_checks() -> None:
    m = L.LpipsAlex(random_backbone(), L.load_heads())
    with pytest.raises(ValueError, match="at least 31"):
        m(torch.zeros(1, 3, 30, 64), torch.zeros(1, 3, 30, 64))
    m(torch.zeros(1, 3, 31, 31), torch.zeros(1, 3, 31, 31))  # the smallest accepted size runs
    with pytest.raises(ValueError, match="differ"):
        m(torch.zeros(1, 3, 32, 32), torch.zeros(1, 3, 32, 33))
    with pytest.raises(ValueError, match="3 channels"):
        m(torch.zeros(1, 1, 32, 32), torch.zeros(1, 1, 32, 32))


@pytest.mark.gpu
@needs_shared
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu_despite_tf32() -> None:
    """cuDNN's default TF32 would move LPIPS by ~5e-5; the module turns it off for its own convolutions."""
    ref, p1 = load_png(REF / "ex_ref.png"), load_png(REF / "ex_p1.png")
    before = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = True
    try:
        with torch.no_grad():
            d = L.lpips(ref.cuda(), p1.cuda(), weights=WEIGHTS)
        assert torch.backends.cudnn.allow_tf32  # the caller's setting is restored
    finally:
        torch.backends.cudnn.allow_tf32 = before
    assert d is not None and d.device.type == "cuda"
    assert abs(float(d[0]) - EXAMPLES["ex_p1"]) <= 1e-5


def test_building_the_model_leaves_the_global_random_state_alone() -> None:
    """The first evaluation of a run builds the model: it must not draw from torch's global generator, or
    the training steps after it (MCMC's noise, relocation) would depend on when, and whether, LPIPS ran."""
    backbone = random_backbone()
    torch.manual_seed(7)
    before = torch.get_rng_state()
    model = L.LpipsAlex(backbone, L.load_heads())
    assert torch.equal(torch.get_rng_state(), before)
    for conv, key in zip(model.convs, L._CONV_KEYS, strict=True):
        assert torch.equal(conv.weight, backbone[f"features.{key}.weight"])
