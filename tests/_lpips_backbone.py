"""A random AlexNet backbone in the layout of torchvision's ``alexnet`` state dict (``features.{i}.weight``
/ ``.bias``), for LPIPS tests that must not depend on the official weights."""

from __future__ import annotations

import math

import torch

from jsgs.metrics import lpips as L


def random_backbone(seed: int = 0) -> dict[str, torch.Tensor]:
    """Weights ~ N(0, 1 / fan_in), biases ~ N(0, 0.01), drawn from their own generator (``seed``)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for (cin, cout, k, _, _), key in zip(L._CONVS, L._CONV_KEYS, strict=True):
        out[f"features.{key}.weight"] = torch.randn(cout, cin, k, k, generator=g) / math.sqrt(cin * k * k)
        out[f"features.{key}.bias"] = torch.randn(cout, generator=g) * 0.1
    return out
