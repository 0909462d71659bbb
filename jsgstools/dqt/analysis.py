"""Double JPEG compression: detect an earlier, coarser quantization from the pixels and estimate its table.

A JPEG header holds only the tables of the last encoding. A photo saved at quality q1, decoded and saved
again at q2 > q1 on the same 8x8 grid keeps the trace of the first quantization in its DCT coefficients:
for a coefficient with header step Q2 and earlier step Q1 > Q2, the values it takes are (up to the rounding
noise of the decode in between) ``round(k * Q1 / Q2) * Q2``, so the histogram of its quantized values
``b = round(dct / Q2)`` has periodic gaps: whole bins that a single compression fills and the double one
leaves (almost) empty.

Method (all numpy, vectorised; see docs/double_compression.md):

1. Decode the pixels with Pillow straight to YCbCr (no colour conversion) and take the orthonormal 8x8
   block DCT on the file's own grid (blocks from the top-left corner; partial edge blocks are dropped).
   Chroma (Cb and Cr pooled) is read for 4:4:4 files only: with subsampled chroma the decode and
   re-encode between the two compressions resample it (upsample, then average), which scales each
   coefficient's comb by the filter's gain, so the comb no longer tells the first step.
2. Per coefficient, the histogram of ``b = rint(dct / Q2)`` over ``-NB..NB`` (the zero bin is left out).
3. For every candidate earlier step ``s`` in 1..255, the bins are split into *reachable* ones (the value
   ``b * Q2`` lies within ``Q2 / 2 + DELTA`` of a multiple of ``s``) and *unreachable* ones. The expected
   share ``p`` of the unreachable bins under a single compression comes from the histogram itself smoothed by
   a box of width ``s`` (in value units), which removes any structure of period ``s``. A binomial test of
   the observed count in the unreachable bins against ``n * p``, with a model-error term ``(GAMMA * n p)^2``
   added to the variance, gives a score ``z(s)``: about 0 for a single compression, near ``1 / GAMMA``
   when the unreachable bins are empty.
4. The primary IJG quality is the ``q`` whose luma table maximises the mean of ``z`` over the AC
   coefficients it makes informative, scaled by the square root of their number (``evidence``); the file
   is called double-compressed when the best evidence exceeds ``THRESHOLD``.
5. The primary tables take, per coefficient, the steps of the best IJG quality, except where that
   coefficient's own best step shows a clear comb and scores clearly higher (non-IJG first encoders, e.g.
   cameras; chroma only for 4:4:4); the effective tables are per coefficient the coarser of the primary
   and the header step.

Limits: only aligned recompression is seen (a crop by a non-multiple of 8 or a resize moves the grid and
erases the trace, and then nothing is detected); a first compression finer than the second (q1 >= q2) leaves
no trace and none is needed (the header step is the coarser one).
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from jsgs.base.errors import JsgsError, one_line
from jsgs.base.io import read_regular_bytes
from jsgs.jpeg.noise import blockiness, jpeg_noise_variance, plane_noise_variance
from jsgs.jpeg.noise import plane_dct as block_dct
from jsgs.jpeg.tables import BASE_CHROMA, BASE_LUMA, SAMPLING_FACTORS, ijg_table
from jsgstools.dqt.header import JpegHeader
from jsgstools.dqt.parser import read_header_from

#: Histogram half-width, in bins of the header step.
NB = 64
#: Largest candidate primary step.
S_MAX = 255
#: Noise allowed between the two quantizations (pixel rounding of the decode in between), DCT value units.
DELTA = 0.4
#: Relative error allowed to the smooth single-compression model (caps a coefficient's score at 1 / GAMMA).
GAMMA = 0.1
#: Least expected count in the unreachable bins for a coefficient to count at a candidate step.
MIN_EXPECTED = 4.0
#: Ridge penalty on the shape parameters of the smooth model (counts).
RIDGE = 1.0
#: Evidence above which a file is called double-compressed.
THRESHOLD = 6.0
#: Width of the logistic that turns evidence into confidence, evidence units.
SOFTNESS = 1.5
#: A coefficient's own best step replaces the IJG fit's when it scores this much higher (z units).
OWN_STEP_MARGIN = 3.0
#: ... and only where its own best step scores at least this (half the largest possible score).
OWN_STEP_MIN = 0.5 / GAMMA

_QUALITIES = np.arange(1, 101)
_IJG_LUMA = np.stack([ijg_table(BASE_LUMA, int(q)) for q in _QUALITIES]).reshape(100, 64)
_IJG_CHROMA = np.stack([ijg_table(BASE_CHROMA, int(q)) for q in _QUALITIES]).reshape(100, 64)


def histograms(coef: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(N, 64) DCT coefficients, (64,) header steps -> (64, NB + 1) float64 counts of
    ``|rint(coef / step)|`` = 0..NB (AC coefficients are symmetric about 0, so the two signs are pooled;
    larger values are dropped)."""
    b = np.abs(np.rint(coef * (1.0 / steps.reshape(1, 64).astype(np.float32))))
    np.minimum(b, NB + 1, out=b)  # bin NB + 1 collects the values out of range, dropped below
    idx = b.astype(np.int32) + np.arange(0, 64 * (NB + 2), NB + 2, dtype=np.int32)
    counts = np.bincount(idx.ravel(), minlength=64 * (NB + 2)).reshape(64, NB + 2)
    return counts[:, : NB + 1].astype(np.float64)


def _masks(q2: int) -> np.ndarray:
    """(NB, S_MAX) float64 for header step ``q2``: 1 where histogram bin m = 1..NB is unreachable from a
    first quantization with step s = 1..S_MAX (its value ``m * q2`` lies farther than ``q2 / 2 + DELTA``
    from every multiple of s), else 0."""
    v = np.arange(1, NB + 1, dtype=np.float64)[:, None] * q2
    s = np.arange(1, S_MAX + 1, dtype=np.float64)[None, :]
    dist = np.abs(v - s * np.round(v / s))
    return (dist > q2 / 2 + DELTA).astype(np.float64)


#: ``_masks`` of every header step 1..255 as float32 (filled on first use), so that a table's masks are one
#: gather: (256, NB, S_MAX), 16.7 MB.
_ALL_MASKS = np.zeros((256, NB, S_MAX), dtype=np.float32)
_FILLED = np.zeros(256, dtype=bool)


def _table_masks(steps: np.ndarray) -> np.ndarray:
    """(K,) header steps 1..255 -> (K, NB, S_MAX) float32 masks."""
    steps = np.clip(steps, 1, 255)
    for q in np.unique(steps[~_FILLED[steps]]):
        _ALL_MASKS[q] = _masks(int(q))
        _FILLED[q] = True
    return _ALL_MASKS[steps]


_M = np.arange(1, NB + 1, dtype=np.float64)
#: Design of the smooth single-compression model: log E[count of bin m] = a + b m + c log m.
_DESIGN = np.stack([np.ones(NB), _M / NB, np.log(_M), np.log(_M) ** 2 / 4], axis=1)
_P = _DESIGN.shape[1]
_DESIGN_OUTER = np.einsum("mi,mj->mij", _DESIGN, _DESIGN).reshape(NB, _P * _P)


def smooth_model(hist: np.ndarray, iterations: int = 6) -> np.ndarray:
    """(K, NB + 1) folded histograms -> (K, NB) expected counts of bins 1..NB under the smooth model
    ``exp(a + b m / NB + c log m)`` (a gamma-like density), fitted by Poisson maximum likelihood (Newton).

    A comb left by double compression has about the same envelope, so the fit follows the envelope and
    the comb's empty bins stand out against it."""
    h = hist[:, 1:]
    x = _DESIGN
    ridge = RIDGE * np.diag([0.0] + [1.0] * (_P - 1))  # keeps sparse histograms (a few bins) well posed
    # Start: least squares on log counts weighted by the counts.
    w = h + 0.5
    a = (w @ _DESIGN_OUTER).reshape(-1, _P, _P) + ridge
    beta = np.linalg.solve(a, ((w * np.log(w)) @ x)[:, :, None])[:, :, 0]
    for _ in range(iterations):
        mu = np.exp(np.clip(beta @ x.T, -50, 30))
        grad = (h - mu) @ x - beta @ ridge
        hess = (mu @ _DESIGN_OUTER).reshape(-1, _P, _P) + ridge
        step = np.linalg.solve(hess, grad[:, :, None])[:, :, 0]
        beta = beta + np.clip(step, -2, 2)
    return np.exp(np.clip(beta @ x.T, -50, 30))


def step_scores(hist: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(K, NB + 1) folded histograms with (K,) header steps -> (K, S_MAX) scores ``z``: column s-1 is the
    evidence that the coefficient went through step s before its header step (0 where uninformative)."""
    h = hist[:, 1:]
    mu = smooth_model(hist)
    n = h.sum(axis=1, keepdims=True)
    masks = _table_masks(np.asarray(steps, dtype=np.int64))  # (K, NB, S_MAX)
    o_u = np.matmul(h.astype(np.float32)[:, None, :], masks)[:, 0]
    p = np.matmul(mu.astype(np.float32)[:, None, :], masks)[:, 0] / np.maximum(
        mu.sum(axis=1, keepdims=True), 1e-12
    )
    expect = n * p
    var = expect * (1 - p) + (GAMMA * expect) ** 2 + 1.0
    z = (expect - o_u) / np.sqrt(var)
    z[expect < MIN_EXPECTED] = 0.0
    return z


@dataclass(frozen=True)
class Analysis:
    """What the pixels say about a file's compression history.

    ``confidence`` is the confidence in the verdict ``double_compressed`` (0.5 undecided, 1 certain); a
    "single" verdict means no trace of an earlier, coarser quantization on the file's grid. Tables are
    (8, 8) int64 in natural row-major order [v, u], in quantization steps. ``evidence`` is the score behind
    the verdict (about 0..3 single, up to about 1 / GAMMA * sqrt(63) double).
    """

    double_compressed: bool
    confidence: float
    evidence: float
    primary_quality: int | None
    primary_luma_table: np.ndarray | None
    effective_luma_table: np.ndarray
    effective_chroma_table: np.ndarray | None
    #: estimated quantisation-noise variance of the decoded pixels against the uncompressed original, 8-bit
    #: units², mean over the planes (jsgs.jpeg.noise, with the effective tables); None where not estimated
    noise_variance: float | None = None
    #: how much the decoded luma's 8×8 block grid shows (jsgs.jpeg.noise.blockiness; about 1 where it does
    #: not); None where not measured
    blockiness: float | None = None

    @property
    def psnr_estimate(self) -> float | None:
        """The PSNR (dB, 8-bit) the estimated noise implies: how far the file is from its uncompressed
        original through quantisation alone."""
        if self.noise_variance is None or self.noise_variance <= 0:
            return None
        return float(10.0 * np.log10(255.0**2 / self.noise_variance))

    def to_json(self) -> dict[str, Any]:
        """The ``analysis`` object of ``jsgs/schemas/dqt_report.schema.json``."""

        def tab(t: np.ndarray | None) -> list[list[int]] | None:
            return None if t is None else [[int(x) for x in row] for row in t]

        return {
            "double_compressed": self.double_compressed,
            "confidence": round(self.confidence, 4),
            "evidence": round(self.evidence, 3),
            "primary_quality": self.primary_quality,
            "primary_luma_table": tab(self.primary_luma_table),
            "effective_luma_table": tab(self.effective_luma_table),
            "effective_chroma_table": tab(self.effective_chroma_table),
            "noise_variance": None if self.noise_variance is None else round(self.noise_variance, 3),
            "blockiness": None if self.blockiness is None else round(self.blockiness, 4),
        }


def _ac_informative(z: np.ndarray, header: np.ndarray, ijg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per IJG quality: the summed score of the AC coefficients at that quality's steps, and their count.

    ``z`` (64, S_MAX), ``header`` (64,) steps, ``ijg`` (100, 64) tables -> two (100,) arrays."""
    s = np.clip(ijg, 1, S_MAX) - 1
    zq = z[np.arange(64)[None, :], s]  # (100, 64): z[i, ijg[q, i] - 1]
    informative = (ijg > header[None, :]) & (zq != 0.0)
    informative[:, 0] = False  # DC histograms follow the picture, not a Laplacian: not used for the verdict
    return np.where(informative, zq, 0.0).sum(axis=1), informative.sum(axis=1)


def _primary_table(z: np.ndarray, fit: np.ndarray) -> np.ndarray:
    """(64, S_MAX) scores and (64,) fitted IJG steps -> (64,) primary steps: the fit, or a coefficient's own
    best step where that shows a clear comb (score >= OWN_STEP_MIN) scoring OWN_STEP_MARGIN higher."""
    best = z.argmax(axis=1)
    best_z = z[np.arange(64), best]
    fit_z = z[np.arange(64), np.clip(fit, 1, S_MAX) - 1]
    own = (best_z >= OWN_STEP_MIN) & (best_z > fit_z + OWN_STEP_MARGIN)
    return np.where(own, best + 1, fit).astype(np.int64)


def analyze_planes(
    luma: np.ndarray,
    luma_table: np.ndarray,
    chroma: list[np.ndarray] | None = None,
    chroma_table: np.ndarray | None = None,
) -> Analysis:
    """Analyse decoded planes on their own 8x8 grids.

    ``luma`` (H, W) and each of ``chroma`` (h, w) hold samples 0..255 exactly as decoded (no colour
    conversion); tables are the header's (8, 8) natural-order steps. ``chroma=None`` (or ``[]``) with a
    chroma table: the chroma effective table is derived from the luma verdict alone.
    """
    header = np.asarray(luma_table, dtype=np.int64).reshape(64)
    z = step_scores(histograms(block_dct(luma), header), header)
    total, count = _ac_informative(z, header, _IJG_LUMA)
    score = np.where(count > 0, total / np.sqrt(np.maximum(count, 1)), 0.0)
    qi = int(np.flatnonzero(score == score.max())[-1])  # ties: the highest quality
    evidence = float(score[qi])
    double = evidence > THRESHOLD
    p_double = 1.0 / (1.0 + np.exp(-(evidence - THRESHOLD) / SOFTNESS))
    confidence = float(p_double if double else 1.0 - p_double)
    if count.max() == 0 and (_IJG_LUMA[:, 1:] > header[None, 1:]).any():
        # an earlier, coarser IJG quantization was possible, but no coefficient held enough values to test
        # one (no full 8x8 block, or flat ones): no evidence either way, undecided
        confidence = 0.5
    eff_luma = header.reshape(8, 8)
    primary_luma = None
    primary_q = None
    eff_chroma = None if chroma_table is None else np.asarray(chroma_table, dtype=np.int64).reshape(8, 8)
    if double:
        primary_q = int(_QUALITIES[qi])
        primary_luma = _primary_table(z, _IJG_LUMA[qi]).reshape(8, 8)
        eff_luma = np.maximum(primary_luma, eff_luma)
        if eff_chroma is not None:
            cheader = eff_chroma.reshape(64)
            fit = _IJG_CHROMA[qi]
            if chroma:
                coef = np.concatenate([block_dct(c) for c in chroma])
                primary_chroma = _primary_table(step_scores(histograms(coef, cheader), cheader), fit)
            else:
                primary_chroma = fit
            eff_chroma = np.maximum(primary_chroma.reshape(8, 8), eff_chroma)
    return Analysis(
        double_compressed=double,
        confidence=confidence,
        evidence=evidence,
        primary_quality=primary_q,
        primary_luma_table=primary_luma,
        effective_luma_table=eff_luma,
        effective_chroma_table=eff_chroma,
    )


def _decode(data: bytes, name: str) -> np.ndarray:
    """Decode JPEG bytes to an (H, W, C) uint8 array in the file's own colour space (YCbCr or gray, no
    colour conversion; subsampled chroma comes upsampled)."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            want = "L" if im.mode == "L" else "YCbCr"
            im.draft(want, im.size)
            if im.mode != want:
                raise JsgsError(f"{name}: cannot analyse a {im.mode} JPEG (only YCbCr and gray)")
            arr = np.asarray(im)
    except JsgsError:
        raise
    except Exception as e:  # Pillow's errors on a broken file: one line
        raise JsgsError(f"{name}: cannot decode for --analyze: {one_line(e)}") from None
    return arr if arr.ndim == 3 else arr[:, :, None]


def analyze_bytes(data: bytes, header: JpegHeader) -> Analysis:
    """Analyse a whole JPEG file (its bytes and its parsed header)."""
    name = header.path
    if header.frame == "lossless" or header.luma_table is None:
        raise JsgsError(f"{name}: --analyze needs a lossy JPEG (this one is {header.frame_name})")
    if header.color_space not in ("YCbCr", "gray") or header.sample_precision != 8:
        raise JsgsError(
            f"{name}: --analyze supports 8-bit YCbCr and gray JPEGs (this one is "
            f"{header.sample_precision}-bit {header.color_space})"
        )
    full = _decode(data, name)
    luma = full[:, :, 0]
    chroma_table = None if header.chroma_table is None else header.chroma_table.values
    chroma: list[np.ndarray] = []
    if chroma_table is not None and len(header.components) == 3:
        cr = header.component_table(2)
        same = cr is not None and np.array_equal(cr.values, chroma_table)
        if same and header.sampling == "4:4:4":
            chroma = [full[:, :, 1], full[:, :, 2]]
    a = analyze_planes(luma, header.luma_table.values, chroma, chroma_table)
    return replace(a, noise_variance=_noise(full, a, header.sampling), blockiness=blockiness(luma))


def _noise(full: np.ndarray, a: Analysis, sampling: str) -> float | None:
    """The quantisation-noise estimate (jsgs.jpeg.noise) of decoded planes with the effective tables; None
    for a chroma sampling the estimate does not handle."""
    if full.shape[2] == 1:
        return plane_noise_variance(full[:, :, 0], a.effective_luma_table)
    if a.effective_chroma_table is None or sampling not in SAMPLING_FACTORS:
        return None
    return jpeg_noise_variance(full, a.effective_luma_table, a.effective_chroma_table, sampling)


def analyze_file(path: str | os.PathLike[str]) -> Analysis:
    """Read, parse and analyse the JPEG file at ``path``."""
    name = str(path)
    try:
        data = read_regular_bytes(path)
    except OSError as e:
        raise JsgsError(f"{name}: cannot read: {e.strerror or e}") from None
    header = read_header_from(io.BytesIO(data), name, len(data))
    return analyze_bytes(data, header)
