"""Decoding an image file to 8-bit RGB, the same way in every tool (``validate``, ``compress``, ``manifest``,
``train``): Pillow, with every decoding failure one line naming the file, and 16-bit images converted by
value.

- 16-bit greyscale (Pillow modes ``I;16*``, and ``I`` holding 0..65535) is scaled by 255 / 65535 and rounded,
  never clipped (Pillow's own ``convert("RGB")`` clips it to white); 16-bit colour PNGs are decoded by Pillow
  to their high bytes, which is also by value. Other modes (grey, palette, alpha, CMYK) use Pillow's
  conversion; alpha is dropped.
- The pixel limit: Pillow refuses images over twice ``Image.MAX_IMAGE_PIXELS`` (about 179 million pixels by
  default) as decompression bombs; the environment variable ``JSGS_MAX_IMAGE_PIXELS`` sets
  ``MAX_IMAGE_PIXELS`` (so the limit is twice its value).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from jsgs.base.errors import JsgsError

ENV_MAX_PIXELS = "JSGS_MAX_IMAGE_PIXELS"


def apply_pixel_limit() -> None:
    """Set Pillow's MAX_IMAGE_PIXELS from $JSGS_MAX_IMAGE_PIXELS when it is set."""
    from PIL import Image

    raw = os.environ.get(ENV_MAX_PIXELS)
    if raw is None or not raw.strip():
        return
    try:
        n = int(raw)
        if n < 1:
            raise ValueError
    except ValueError:
        raise JsgsError(f"${ENV_MAX_PIXELS}={raw!r}: must be a positive whole number of pixels") from None
    Image.MAX_IMAGE_PIXELS = n


def to_rgb8(im: object, path: str | Path) -> np.ndarray:
    """A loaded Pillow image -> [H, W, 3] uint8 (see the module docstring)."""
    from PIL import Image

    assert isinstance(im, Image.Image)
    if im.mode.startswith("I;16") or im.mode == "I":
        a = np.asarray(im).astype(np.int64)
        if a.size and (a.min() < 0 or a.max() > 65535):
            raise JsgsError(f"{path}: {im.mode} image with values outside 0..65535 (not a 16-bit image)")
        g = np.round(a * (255.0 / 65535.0)).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)
    if im.mode == "F":
        raise JsgsError(f"{path}: floating-point images are not supported (convert to 8 or 16 bits)")
    return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


def _decode(path: str | Path, what: str, read: Any) -> np.ndarray:
    """``read(image)`` of the opened ``path``; JsgsError (one line naming the file) when it is missing,
    truncated, not an image, or over the pixel limit."""
    from PIL import Image, UnidentifiedImageError

    from jsgs.base.io import open_regular

    apply_pixel_limit()
    try:
        with open_regular(path) as f, Image.open(f) as im:
            return read(im)
    except FileNotFoundError:
        raise JsgsError(f"{path}: {what} not found") from None
    except Image.DecompressionBombError as e:
        raise JsgsError(
            f"{path}: {what} exceeds the pixel limit ({e}); raise it with ${ENV_MAX_PIXELS}"
        ) from None
    except UnidentifiedImageError:
        # Pillow's own message names the file object (``<_io.BufferedReader name=3>``), not the file
        raise JsgsError(f"{path}: cannot decode {what} (Pillow cannot identify its format)") from None
    except (OSError, ValueError, SyntaxError) as e:
        raise JsgsError(f"{path}: cannot decode {what} ({e})") from None


def read_rgb8(path: str | Path, what: str = "image") -> np.ndarray:
    """Decode ``path`` to [H, W, 3] uint8. JsgsError (one line naming the file) when it is missing,
    truncated, not an image, or over the pixel limit."""

    def read(im: Any) -> np.ndarray:
        im.load()
        return to_rgb8(im, path)

    return _decode(path, what, read)


def read_ycbcr8(path: str | Path, what: str = "image") -> np.ndarray:
    """Decode the colour JPEG ``path`` to [H, W, 3] uint8 Y, Cb, Cr as its decoder produces them (no colour
    conversion; subsampled chroma upsampled to full size). JsgsError (one line) as :func:`read_rgb8`, and when
    the file is not a YCbCr JPEG."""

    def read(im: Any) -> np.ndarray:
        if im.format != "JPEG" or im.mode != "RGB":
            raise JsgsError(f"{path}: {what} is not a YCbCr colour JPEG ({im.format} {im.mode})")
        im.draft("YCbCr", im.size)
        if im.mode != "YCbCr":
            raise JsgsError(f"{path}: {what}: the decoder gives {im.mode}, not YCbCr")
        return np.asarray(im, dtype=np.uint8).copy()

    return _decode(path, what, read)
