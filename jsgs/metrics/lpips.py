"""LPIPS-alex v0.1 (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric") in pure torch, without torchvision or the ``lpips`` package.

The network is the reference implementation's (``lpips.LPIPS(net='alex', version='0.1')``):

1. ScalingLayer: ``(x - shift) / scale`` with shift (-.030, -.088, -.188), scale (.458, .448, .450),
   applied to inputs in [-1, 1];
2. torchvision's AlexNet ``features`` convolutions, tapped after each of the five ReLUs
   (64, 192, 384, 256, 256 channels);
3. per tap: unit-normalise every pixel's channel vector (``f / (||f|| + 1e-10)``), squared difference,
   a learned 1x1 linear head with no bias (dropout is inactive at evaluation), spatial mean;
4. the sum of the five layer scores.

Weights come from two files:

- the AlexNet backbone (ImageNet, ~10 MB, not in the repository): a path given by the caller, else the
  environment variable ``JSGS_LPIPS_WEIGHTS``, else the copy kept in torch's hub cache
  (``$TORCH_HOME/hub/checkpoints/jsgs_lpips_alexnet_features.pth``), else torchvision's ImageNet AlexNet file
  downloaded once with ``torch.hub.load_state_dict_from_url`` (its SHA-256 checked against the prefix in its
  name, as torchvision does), of which only the convolution layers are kept in that cache file. A plain
  ``torch.save`` dict in torchvision's layout, ``features.{0,3,6,8,10}.{weight,bias}``; a full torchvision
  AlexNet state dict works too (``classifier.*`` is ignored). The download is tried at most once per process.
  With no file and no network (or ``JSGS_LPIPS_DOWNLOAD=0``), :func:`load_lpips` and :func:`lpips` return
  ``None`` after one line on stderr saying how to get the weights (once per process; no Python warning, no
  download progress): a missing metric is reported as missing, never replaced by a made-up number.
- the linear heads: ``jsgs/metrics/weights/lpips_v0.1_alex.pth``, the ``lpips`` package's own file
  (BSD-2, see the README next to it), checked against its SHA-256 when loaded.

Input convention: :class:`LpipsAlex` takes images in [-1, 1] like the reference implementation; the
function :func:`lpips` takes images in [0, 1] (what the renderer and the image loaders produce) and maps them
with ``2x - 1``, the reference's ``normalize=True``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import sys
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from jsgs.base.errors import JsgsError, one_line
from jsgs.base.precision import ieee_fp32

ENV_VAR = "JSGS_LPIPS_WEIGHTS"
# "0" turns the download off (tests, air-gapped machines); anything else, or unset, allows it.
DOWNLOAD_ENV_VAR = "JSGS_LPIPS_DOWNLOAD"
# torchvision's AlexNet IMAGENET1K_V1 weights; "7be5be79" is the start of the file's SHA-256, which
# torch.hub checks (check_hash=True).
ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
CACHE_NAME = "jsgs_lpips_alexnet_features.pth"
HEADS_PATH = Path(__file__).resolve().parent / "weights" / "lpips_v0.1_alex.pth"
HEADS_SHA256 = "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0"

# (in, out, kernel, stride, padding) of torchvision's alexnet().features convolutions, and their indices
# in that nn.Sequential (the state-dict keys).
_CONVS: tuple[tuple[int, int, int, int, int], ...] = (
    (3, 64, 11, 4, 2),
    (64, 192, 5, 1, 2),
    (192, 384, 3, 1, 1),
    (384, 256, 3, 1, 1),
    (256, 256, 3, 1, 1),
)
_CONV_KEYS = (0, 3, 6, 8, 10)
CHANNELS = tuple(c[1] for c in _CONVS)
# Smallest image side the AlexNet stack accepts: conv1 (11/4, pad 2) must leave >= 7 px so that both
# 3/2 max-pools still have a full window.
MIN_SIDE = 31

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10  # lpips.normalize_tensor's eps: added to the norm, not under the square root

UNAVAILABLE_MESSAGE = (
    f"LPIPS is reported as null: no AlexNet backbone weights. To get them, set ${ENV_VAR} (or "
    "eval.lpips_weights) to a copy such as ../shared/lpips/alexnet_features.pth, or run once with network "
    f"access to download {ALEXNET_URL} into torch's hub cache"
)


class LpipsAlex(nn.Module):
    """LPIPS-alex v0.1 as an ``nn.Module`` with frozen weights.

    ``forward(x, y)``: x, y are B x 3 x H x W (or 3 x H x W) in **[-1, 1]**, H, W >= 31; returns the B
    distances (float32, dimensionless, 0 for identical images). Differentiable with respect to the inputs.
    """

    def __init__(self, backbone: dict[str, Tensor], heads: list[Tensor]) -> None:
        """``backbone``: ``features.{0,3,6,8,10}.{weight,bias}`` (as from :func:`load_backbone`);
        ``heads``: five tensors of shape 1 x C_l x 1 x 1 (as from :func:`load_heads`)."""
        super().__init__()
        # skip_init: no random initialisation (the weights are copied below), so building the model leaves
        # torch's global random state, and with it the training run that evaluates, untouched
        self.convs = nn.ModuleList(
            nn.utils.skip_init(nn.Conv2d, cin, cout, k, stride=s, padding=p) for cin, cout, k, s, p in _CONVS
        )
        with torch.no_grad():
            for conv, key in zip(self.convs, _CONV_KEYS, strict=True):
                conv.weight.copy_(backbone[f"features.{key}.weight"])
                conv.bias.copy_(backbone[f"features.{key}.bias"])
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        for i, w in enumerate(heads):
            self.register_buffer(f"head{i}", w.detach().clone().float())
        self.requires_grad_(False)
        self.eval()

    def taps(self, x: Tensor) -> list[Tensor]:
        """The five post-ReLU feature maps of a scaled input ``x`` (B x 3 x H x W)."""
        out: list[Tensor] = []
        h = x
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                h = F.max_pool2d(h, kernel_size=3, stride=2)
            h = F.relu(conv(h))
            out.append(h)
        return out

    def forward(self, x: Tensor, y: Tensor, per_layer: bool = False) -> Tensor | tuple[Tensor, list[Tensor]]:
        """Distances (B,) between ``x`` and ``y`` in [-1, 1]; with ``per_layer`` also the five layer terms."""
        x, y = _as_batch(x), _as_batch(y)
        if x.shape != y.shape:
            raise ValueError(f"LPIPS: image shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
        if x.shape[1] != 3:
            raise ValueError(f"LPIPS: expected 3 channels (B x 3 x H x W), got shape {tuple(x.shape)}")
        if min(x.shape[-2:]) < MIN_SIDE:
            raise ValueError(
                f"LPIPS-alex needs images of at least {MIN_SIDE}x{MIN_SIDE} px, "
                f"got {x.shape[-1]}x{x.shape[-2]}"
            )
        dtype = self.shift.dtype
        # full float32: cuDNN's default TF32 moved LPIPS by up to ~5e-5 on an H100 (ex_ref/ex_p1 0.137523
        # instead of 0.137566); without it CUDA matches the CPU to ~1e-7
        with ieee_fp32(x.device):
            fx = self.taps((x.to(dtype) - self.shift) / self.scale)
            fy = self.taps((y.to(dtype) - self.shift) / self.scale)
            return self._compare(fx, fy, per_layer)

    def _compare(
        self, fx: list[Tensor], fy: list[Tensor], per_layer: bool
    ) -> Tensor | tuple[Tensor, list[Tensor]]:
        layers: list[Tensor] = []
        for i, (a, b) in enumerate(zip(fx, fy, strict=True)):
            a = a / (a.pow(2).sum(dim=1, keepdim=True).sqrt() + _EPS)
            b = b / (b.pow(2).sum(dim=1, keepdim=True).sqrt() + _EPS)
            head: Tensor = getattr(self, f"head{i}")
            layers.append(F.conv2d((a - b) ** 2, head).mean(dim=(1, 2, 3)))
        total = torch.stack(layers).sum(dim=0)
        return (total, layers) if per_layer else total


def _as_batch(x: Tensor) -> Tensor:
    if x.dim() == 3:
        return x.unsqueeze(0)
    if x.dim() != 4:
        raise ValueError(f"LPIPS: expected B x 3 x H x W or 3 x H x W, got shape {tuple(x.shape)}")
    return x


def _torch_load(path: Path, what: str) -> dict[str, Tensor]:
    from jsgs.base.io import open_regular

    try:
        # weights_only: a weights file must not be able to run code when loaded
        with open_regular(path) as f:
            obj = torch.load(f, map_location="cpu", weights_only=True)
    except JsgsError:
        raise
    except Exception as e:  # torch raises many types (pickle, zip, runtime) for a bad file
        raise JsgsError(f"{path}: cannot read {what} ({one_line(e)})") from e
    if not isinstance(obj, dict) or not all(isinstance(k, str) for k in obj):
        raise JsgsError(f"{path}: {what} must be a dict of tensors (a state dict), got {type(obj).__name__}")
    return obj


def _check_tensor(path: Path, key: str, t: object, shape: tuple[int, ...]) -> Tensor:
    if not isinstance(t, Tensor):
        raise JsgsError(f"{path}: '{key}' is not a tensor")
    if tuple(t.shape) != shape:
        raise JsgsError(f"{path}: '{key}' has shape {tuple(t.shape)}, expected {shape}")
    if not t.is_floating_point() or not bool(torch.isfinite(t).all()):
        raise JsgsError(f"{path}: '{key}' must hold finite floating-point values")
    return t.float()


def load_backbone(path: str | os.PathLike[str]) -> dict[str, Tensor]:
    """Read AlexNet ``features`` weights (torchvision layout) from ``path``; raise JsgsError if the file is
    unreadable or lacks a tensor of the right shape. Extra keys (e.g. ``classifier.*``) are ignored."""
    path = Path(path)
    state = _torch_load(path, "AlexNet weights")
    out: dict[str, Tensor] = {}
    for (cin, cout, k, _, _), key in zip(_CONVS, _CONV_KEYS, strict=True):
        for name, shape in (("weight", (cout, cin, k, k)), ("bias", (cout,))):
            full = f"features.{key}.{name}"
            if full not in state:
                raise JsgsError(
                    f"{path}: not an AlexNet features state dict (no '{full}'; expected torchvision's "
                    "features.{0,3,6,8,10}.{weight,bias})"
                )
            out[full] = _check_tensor(path, full, state[full], shape)
    return out


def load_heads(path: str | os.PathLike[str] | None = None) -> list[Tensor]:
    """The five LPIPS v0.1 alex linear heads (1 x C_l x 1 x 1 each). ``path`` defaults to the vendored copy,
    whose SHA-256 is checked (a corrupted checkout would otherwise give plausible but wrong numbers)."""
    if path is None:
        p = HEADS_PATH
        if not p.is_file():
            raise JsgsError(f"{p}: vendored LPIPS linear heads missing (broken installation?)")
        digest = hashlib.sha256(p.read_bytes()).hexdigest()
        if digest != HEADS_SHA256:
            raise JsgsError(f"{p}: SHA-256 {digest} differs from the lpips 0.1.4 file's {HEADS_SHA256}")
    else:
        p = Path(path)
    state = _torch_load(p, "LPIPS linear heads")
    heads: list[Tensor] = []
    for i, c in enumerate(CHANNELS):
        key = f"lin{i}.model.1.weight"
        if key not in state:
            raise JsgsError(f"{p}: not an LPIPS alex heads file (no '{key}')")
        heads.append(_check_tensor(p, key, state[key], (1, c, 1, 1)))
    return heads


def cached_backbone_path() -> Path:
    """Where a downloaded backbone's convolution layers are kept: torch's hub cache (``$TORCH_HOME``)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / CACHE_NAME


def download_backbone(url: str | None = None) -> Path | None:
    """Download torchvision's AlexNet weights from ``url`` (hash checked by ``torch.hub`` against the hex
    prefix in the file name), keep only ``features.*`` in :func:`cached_backbone_path` (written atomically)
    and delete the full download. Returns None when the file cannot be fetched (offline; the reason is kept in
    :data:`_download_failure` and no later call tries again); raises JsgsError when it was fetched but its
    hash or content is wrong. torch.hub's ``Downloading:`` line is not shown."""
    global _download_failure
    import tempfile
    import urllib.error

    url = url or ALEXNET_URL
    target = cached_backbone_path()
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".jsgs-download-") as tmp:
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # torch.hub prints "Downloading: ..." to stdout
                state = torch.hub.load_state_dict_from_url(
                    url, model_dir=tmp, map_location="cpu", progress=False, check_hash=True, weights_only=True
                )
        except (urllib.error.URLError, ConnectionError, TimeoutError) as e:
            _download_failure = f"{url}: {one_line(e)}"
            return None
        except RuntimeError as e:  # torch.hub: "invalid hash value (expected ..., got ...)"
            raise JsgsError(f"{url}: download rejected: {one_line(e)}") from None
        features = {k: v for k, v in state.items() if k.startswith("features.")}
        part = Path(tmp) / CACHE_NAME
        torch.save(features, part)
        try:
            load_backbone(part)
        except JsgsError as e:
            raise JsgsError(f"{url}: downloaded file is not torchvision's AlexNet ({e})") from None
        os.replace(part, target)
    return target


def resolve_weights(weights: str | os.PathLike[str] | None = None) -> Path | None:
    """The backbone weights file: ``weights`` if given, else ``$JSGS_LPIPS_WEIGHTS`` if set and non-empty,
    else the hub-cache copy, else a download (unless ``$JSGS_LPIPS_DOWNLOAD`` is ``0``); None when none of
    these gives a file. A file that is *named* but does not exist is an error (JsgsError), not a silent
    null: a typo in a config should not quietly drop a metric."""
    if weights is not None and str(weights) != "":
        p, source = Path(weights), "given path"
    elif os.environ.get(ENV_VAR):
        p, source = Path(os.environ[ENV_VAR]), f"${ENV_VAR}"
    else:
        cached = cached_backbone_path()
        if cached.is_file():
            return cached
        if os.environ.get(DOWNLOAD_ENV_VAR, "1") == "0" or _download_failure is not None:
            return None
        return download_backbone()
    if not p.is_file():
        raise JsgsError(f"{p}: LPIPS AlexNet weights file not found (from the {source})")
    return p


_CACHE: dict[tuple[str, str], LpipsAlex] = {}
_warned: set[str] = set()
#: why the one download of this process failed (None: not tried, or it worked)
_download_failure: str | None = None


def warn_once(message: str) -> None:
    """Write ``message`` to stderr as one line (``note: ...``) the first time it is seen in this process: a
    note for the person running the program, not a Python warning with a source location."""
    if message not in _warned:
        _warned.add(message)
        print(f"note: {message}", file=sys.stderr, flush=True)


def load_lpips(
    weights: str | os.PathLike[str] | None = None, device: str | torch.device | None = None
) -> LpipsAlex | None:
    """The LPIPS-alex model on ``device`` (default CPU), built once per (weights file, device) and cached.

    Returns None, with one line on stderr (once per process; :func:`warn_once`) saying how to get the weights,
    when none are available. Raises JsgsError when named weights are missing or malformed.
    """
    path = resolve_weights(weights)
    if path is None:
        reason = f" (the download failed: {_download_failure})" if _download_failure else ""
        warn_once(UNAVAILABLE_MESSAGE + reason)
        return None
    dev = torch.device(device if device is not None else "cpu")
    key = (str(path.resolve()), str(dev))
    if key not in _CACHE:
        _CACHE[key] = LpipsAlex(load_backbone(path), load_heads()).to(dev)
    return _CACHE[key]


def lpips(pred: Tensor, ref: Tensor, weights: str | os.PathLike[str] | None = None) -> Tensor | None:
    """LPIPS-alex v0.1 distances between images in **[0, 1]**.

    pred, ref: B x 3 x H x W or 3 x H x W, same shape, values in [0, 1] (mapped to [-1, 1] by ``2x - 1``),
    sides >= 31 px. Returns a float32 tensor of B distances on the inputs' device, or None (noted once) when
    no backbone weights are available. Gradients flow to the inputs.
    """
    model = load_lpips(weights, device=pred.device)
    if model is None:
        return None
    result = model(pred * 2 - 1, ref * 2 - 1)
    assert isinstance(result, Tensor)
    return result
