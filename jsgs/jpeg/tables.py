"""JPEG's constant tables: IJG (libjpeg) quantization tables, quality scaling and its inverse, the chroma
sampling layouts and the 8x8 DCT basis (numpy only, so the toolkit reads them without torch).

All tables are 8x8 in natural row-major order (entry [v, u]: v vertical, u horizontal frequency). The JPEG
file stores them in zigzag order; ``ZIGZAG`` maps zigzag position k to the natural index.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np


@dataclass(frozen=True)
class ChromaSampling:
    """A chroma sampling layout: the luma-to-chroma ratio ``h`` horizontally and ``v`` vertically, Pillow's
    ``subsampling=`` code where Pillow writes it, and whether the observation operator, DCT supervision and
    the noise estimate handle it."""

    h: int
    v: int
    pillow: int | None = None
    observable: bool = False


#: Every named chroma sampling of a three-component JPEG (the names ``jsgstools.dqt`` reports), the one table
#: of them; the views below derive from it.
CHROMA_SAMPLINGS: dict[str, ChromaSampling] = {
    "4:4:4": ChromaSampling(1, 1, pillow=0, observable=True),
    "4:2:2": ChromaSampling(2, 1, pillow=1, observable=True),
    "4:2:0": ChromaSampling(2, 2, pillow=2, observable=True),
    "4:4:0": ChromaSampling(1, 2, observable=True),
    "4:1:1": ChromaSampling(4, 1, observable=True),
}
#: chroma sampling name -> (h, v), for the samplings the observation operator and the noise estimate handle.
SAMPLING_FACTORS: dict[str, tuple[int, int]] = {
    name: (s.h, s.v) for name, s in CHROMA_SAMPLINGS.items() if s.observable
}


@cache
def dct_basis() -> np.ndarray:
    """The orthonormal 8x8 DCT-II matrix ``D`` in float64 (``D[k, n] = c_k cos((2n + 1) k pi / 16)``, c_0 =
    sqrt(1/8), c_k = 1/2), ``coef = D @ block @ D.T``; read-only, shared by every caller."""
    k = np.arange(8)[:, None]
    n = np.arange(8)[None, :]
    d = np.cos((2 * n + 1) * k * math.pi / 16) * 0.5
    d[0, :] = math.sqrt(1 / 8)
    d.flags.writeable = False
    return d

# ITU-T T.81 Annex K, tables K.1 (luminance) and K.2 (chrominance), natural order.
BASE_LUMA = np.array(
    [
        [16, 11, 10, 16, 24, 40, 51, 61],
        [12, 12, 14, 19, 26, 58, 60, 55],
        [14, 13, 16, 24, 40, 57, 69, 56],
        [14, 17, 22, 29, 51, 87, 80, 62],
        [18, 22, 37, 56, 68, 109, 103, 77],
        [24, 35, 55, 64, 81, 104, 113, 92],
        [49, 64, 78, 87, 103, 121, 120, 101],
        [72, 92, 95, 98, 112, 100, 103, 99],
    ],
    dtype=np.int64,
)
BASE_CHROMA = np.array(
    [
        [17, 18, 24, 47, 99, 99, 99, 99],
        [18, 21, 26, 66, 99, 99, 99, 99],
        [24, 26, 56, 99, 99, 99, 99, 99],
        [47, 66, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
        [99, 99, 99, 99, 99, 99, 99, 99],
    ],
    dtype=np.int64,
)


def _zigzag() -> np.ndarray:
    order: list[int] = []
    for s in range(15):
        diag = [(v, s - v) for v in range(8) if 0 <= s - v < 8]
        # Even diagonals run bottom-left -> top-right, odd ones the other way (T.81 figure A.6).
        if s % 2 == 0:
            diag.reverse()
        order.extend(v * 8 + u for v, u in diag)
    return np.array(order, dtype=np.int64)


#: ZIGZAG[k] = natural (row-major) index of the k-th coefficient in file order.
ZIGZAG = _zigzag()


def zigzag_to_natural(values: np.ndarray | list[int]) -> np.ndarray:
    """64 values in file (zigzag) order -> 8x8 natural-order int64 array."""
    out = np.empty(64, dtype=np.int64)
    out[ZIGZAG] = np.asarray(values, dtype=np.int64)
    return out.reshape(8, 8)


def quality_scale(quality: int) -> int:
    """libjpeg's ``jpeg_quality_scaling``: quality 1..100 -> percentage scale factor."""
    if not 1 <= quality <= 100:
        raise ValueError(f"quality must be in 1..100, got {quality}")
    return 5000 // quality if quality < 50 else 200 - 2 * quality


def ijg_table(base: np.ndarray, quality: int, force_baseline: bool = True) -> np.ndarray:
    """The table libjpeg's ``jpeg_set_quality(quality, force_baseline)`` derives from ``base`` (8x8)."""
    t = (base.astype(np.int64) * quality_scale(quality) + 50) // 100
    return np.clip(t, 1, 255 if force_baseline else 32767)


def ijg_tables(quality: int) -> tuple[np.ndarray, np.ndarray]:
    """(luma, chroma) 8x8 natural-order tables Pillow/libjpeg write for ``quality=``."""
    return ijg_table(BASE_LUMA, quality), ijg_table(BASE_CHROMA, quality)


@dataclass(frozen=True)
class QualityEstimate:
    """The IJG quality whose tables are nearest to a file's tables.

    ``exact`` is True only when every given table equals IJG's at ``quality`` bit for bit; camera and phone
    encoders use their own tables, for which ``quality`` is only the closest IJG level (``error`` is the mean
    absolute difference per entry, in quantization steps).
    """

    quality: int
    exact: bool
    error: float


_ALL_LUMA = np.stack([ijg_table(BASE_LUMA, q) for q in range(1, 101)]).astype(np.float64)
_ALL_CHROMA = np.stack([ijg_table(BASE_CHROMA, q) for q in range(1, 101)]).astype(np.float64)


def estimate_quality(luma: np.ndarray, chroma: np.ndarray | None = None) -> QualityEstimate:
    """Invert libjpeg's quality scaling: the q in 1..100 whose IJG tables are closest (mean |diff|).

    Ties (possible for non-IJG tables, whose distance can be equal to two neighbouring levels) go to the
    highest quality. Pass ``chroma=None`` for grayscale.
    """
    luma = np.asarray(luma, dtype=np.float64).reshape(8, 8)
    err = np.abs(_ALL_LUMA - luma).mean(axis=(1, 2))
    exact = np.all(_ALL_LUMA == luma, axis=(1, 2))
    if chroma is not None:
        chroma = np.asarray(chroma, dtype=np.float64).reshape(8, 8)
        err = (err + np.abs(_ALL_CHROMA - chroma).mean(axis=(1, 2))) / 2
        exact &= np.all(_ALL_CHROMA == chroma, axis=(1, 2))
    best = float(err.min())
    # Highest quality among the minimisers.
    q_index = int(np.flatnonzero(err == best)[-1])
    return QualityEstimate(quality=q_index + 1, exact=bool(exact[q_index]), error=best)


def checked_steps(table: np.ndarray | list, name: str) -> np.ndarray:
    """``table`` as a float64 array of quantization steps (integers 1..65535; ValueError naming the first
    entry that is not one)."""
    try:
        a = np.asarray(table, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: not an array of numbers") from None
    bad = ~(np.isfinite(a) & (a >= 1) & (a <= 65535) & (a == np.round(a)))
    if bad.any():
        at = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"{name}: entry {a[at]!r} at {list(at)} is not a quantization step (an integer 1..65535)"
        )
    return a
