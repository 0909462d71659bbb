"""What a JPEG header says: the result classes, the quality of its tables, its colour space and sampling
name."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from jsgs.base.errors import JsgsError
from jsgs.jpeg.tables import CHROMA_SAMPLINGS, QualityEstimate, estimate_quality, ijg_tables
from jsgstools.dqt.cache import _CACHE_MAX, _ESTIMATE_CACHE

# The result classes are plain slotted dataclasses (cheap to build: this is a hot path); treat them as
# read-only. QuantTable is frozen and its array read-only because headers share them through a cache.


@dataclass(frozen=True, slots=True)
class QuantTable:
    """One DQT table: ``values`` is a read-only (8, 8) int64 array in natural row-major order [v, u],
    entries in quantization steps (1..255 for 8-bit tables, 1..65535 for 16-bit ones)."""

    id: int
    precision: int  # bits per entry: 8 (Pq=0) or 16 (Pq=1)
    values: np.ndarray


@dataclass(slots=True)
class Component:
    """One frame component: id byte from SOF, name (Y, Cb, ...), sampling factors, quantization table id
    (None in lossless frames, which use none)."""

    id: int
    name: str
    h: int
    v: int
    table: int | None


@dataclass(slots=True)
class AppSegment:
    """An APPn segment seen (and skipped) in the header: offset of its marker, total length in bytes
    including the marker, and the printable identifier it starts with (Exif, JFIF, ICC_PROFILE, MPF, ...)."""

    marker: str
    offset: int
    length: int
    identifier: str


@dataclass(slots=True)
class JpegHeader:
    """Everything the header says about a JPEG file up to its first scan.

    Sizes are in bytes; ``header_size`` is the offset of the first entropy-coded byte (end of the first SOS
    segment), or the end of the SOS segment by which every component has begun a scan (``scans`` > 1);
    ``bytes_read`` is how many bytes the parser actually read (skipped segments cost nothing).
    """

    path: str
    file_size: int
    header_size: int
    bytes_read: int
    sof: str  # marker name, e.g. "SOF2"
    frame: str  # baseline | extended | progressive | lossless
    coding: str  # huffman | arithmetic
    sample_precision: int  # bits per sample (8, 12; 2..16 for lossless)
    width: int
    height: int
    color_space: str  # gray | YCbCr | RGB | CMYK | YCCK | unknown
    components: tuple[Component, ...]
    tables: dict[int, QuantTable]
    sampling: str
    restart_interval: int  # MCUs between restart markers; 0 = none
    quality: QualityEstimate | None
    jfif: bool
    adobe_transform: int | None
    app_segments: tuple[AppSegment, ...] = ()
    warnings: tuple[str, ...] = field(default=())
    #: scan headers read: 1, unless the first scan leaves components out (their tables are the ones in force
    #: at their own first scans, so the parser reads on to them; ``bytes_read`` may then pass ``header_size``
    #: by the coded data read ahead)
    scans: int = 1
    #: component index -> the table it decodes with, for a component whose table id a DQT between scans
    #: redefined after an earlier component of that id had begun its first scan (``tables`` holds the earlier
    #: component's); empty for almost every file
    relatched: dict[int, QuantTable] = field(default_factory=dict)

    @property
    def frame_name(self) -> str:
        """``frame`` with ``-arithmetic`` appended for arithmetic coding, e.g. "progressive-arithmetic"."""
        return self.frame if self.coding == "huffman" else f"{self.frame}-arithmetic"

    @property
    def sampling_factors(self) -> str:
        """Per-component HxV factors, e.g. "2x2,1x1,1x1"."""
        return ",".join(f"{c.h}x{c.v}" for c in self.components)

    def component_table(self, i: int) -> QuantTable | None:
        """The table component ``i`` decodes with (the one in force at its first scan); None where there is
        no such component or the frame is lossless."""
        if i >= len(self.components) or self.components[i].table is None:
            return None
        return self.relatched.get(i) or self.tables[self.components[i].table]  # type: ignore[index]

    @property
    def luma_table(self) -> QuantTable | None:
        """Table of the first component (None in lossless frames)."""
        return self.component_table(0)

    @property
    def chroma_table(self) -> QuantTable | None:
        """Table of the second component (Cb), None for gray and lossless frames."""
        return self.component_table(1)

    def table_uses(self) -> list[tuple[QuantTable, list[str]]]:
        """Each table with the names of the components that decode with it: ``tables`` by id, then each
        table in ``relatched`` (an id listed twice, with other values and other components)."""
        used: dict[int, list[str]] = {t: [] for t in self.tables}
        for i, c in enumerate(self.components):
            if c.table is not None and i not in self.relatched:
                used[c.table].append(c.name)
        return [(t, used[t.id]) for t in self.tables.values()] + [
            (t, [self.components[i].name]) for i, t in sorted(self.relatched.items())
        ]

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (the per-file object of ``jsgs/schemas/dqt_report.schema.json``)."""
        q = self.quality
        return {
            "path": self.path,
            "file_size": self.file_size,
            "header_size": self.header_size,
            "bytes_read": self.bytes_read,
            "frame": {
                "marker": self.sof,
                "type": self.frame,
                "coding": self.coding,
                "name": self.frame_name,
                "sample_precision": self.sample_precision,
            },
            "width": self.width,
            "height": self.height,
            "color_space": self.color_space,
            "components": [
                {"id": c.id, "name": c.name, "h": c.h, "v": c.v, "table": c.table} for c in self.components
            ],
            "sampling": self.sampling,
            "sampling_factors": self.sampling_factors,
            "restart_interval": self.restart_interval,
            "tables": [
                {"id": t.id, "precision": t.precision, "used_by": users, "values": t.values.tolist()}
                for t, users in self.table_uses()
            ],
            "quality": None
            if q is None
            else {"estimate": q.quality, "exact": q.exact, "mean_abs_error": round(q.error, 4)},
            "jfif": self.jfif,
            "adobe_transform": self.adobe_transform,
            "app_segments": [
                {"marker": a.marker, "offset": a.offset, "length": a.length, "identifier": a.identifier}
                for a in self.app_segments
            ],
            "warnings": list(self.warnings),
        }

    def manifest_state(self) -> dict[str, Any]:
        """The manifest's ``jpeg`` object (jsgs/schemas/manifest.schema.json, ``$defs/jpeg``).

        ``precision`` is 16 when the luma or chroma table is 16-bit (that of the first and the second
        component); ``cr_table`` is the third component's table when its values differ from the second's (a
        file that quantizes Cr with a table of its own, by another id or by the shared id redefined between
        Cb's and Cr's first scans). Raises JsgsError for lossless frames and for samples
        other than 8-bit (12-bit extended frames).
        """
        luma, chroma = self.luma_table, self.chroma_table
        if luma is None or self.quality is None:
            raise JsgsError(f"{self.path}: {self.frame_name} JPEG ({self.sof}) has no quantization tables")
        if self.sample_precision != 8:
            raise JsgsError(
                f"{self.path}: {self.sample_precision}-bit samples ({self.frame_name} JPEG, {self.sof}); the "
                "JPEG observation operator and Pillow's decoder take 8-bit JPEGs only"
            )
        precision = max(luma.precision, chroma.precision if chroma is not None else 8)
        state: dict[str, Any] = {
            "luma_table": luma.values.tolist(),
            "chroma_table": None if chroma is None else chroma.values.tolist(),
            "sampling": self.sampling,
            "quality": self.quality.quality,
            "quality_exact": self.quality.exact,
            "precision": precision,
            "frame": self.frame_name,
            "color_space": self.color_space,
        }
        cr = self.component_table(2)
        if chroma is not None and cr is not None and not np.array_equal(cr.values, chroma.values):
            state["cr_table"] = cr.values.tolist()
        return state


# Exact IJG tables -> quality, so the common case skips ``estimate_quality``'s 100-level search (~70 us, more
# than the rest of the parse). Built in ascending q, so identical tables map to the highest q, which is
# ``estimate_quality``'s tie rule; the test suite checks the two agree.
_EXACT_PAIR: dict[bytes, int] = {}
_EXACT_LUMA: dict[bytes, int] = {}
for _q in range(1, 101):
    _l, _c = ijg_tables(_q)
    _EXACT_PAIR[_l.astype(np.int64).tobytes() + _c.astype(np.int64).tobytes()] = _q
    _EXACT_LUMA[_l.astype(np.int64).tobytes()] = _q
del _q, _l, _c


def quality_of(luma: np.ndarray, chroma: np.ndarray | None) -> QualityEstimate:
    """``estimate_quality(luma, chroma)`` with a dictionary fast path for tables that are exactly IJG's.

    ``luma``/``chroma``: (8, 8) int64 natural-order tables as stored in ``QuantTable.values``.
    """
    key = luma.tobytes() if chroma is None else luma.tobytes() + chroma.tobytes()
    q = (_EXACT_LUMA if chroma is None else _EXACT_PAIR).get(key)
    if q is not None:
        return QualityEstimate(quality=q, exact=True, error=0.0)
    key += b"gray" if chroma is None else b""  # 512 bytes of luma alone never equal 1024 of luma+chroma
    est = _ESTIMATE_CACHE.get(key)
    if est is None:
        est = estimate_quality(luma, chroma)
        if len(_ESTIMATE_CACHE) >= _CACHE_MAX:
            _ESTIMATE_CACHE.clear()
        _ESTIMATE_CACHE[key] = est
    return est



def _color_space(ids: Sequence[int], jfif: bool, adobe_transform: int | None) -> str:
    n = len(ids)
    if n == 1:
        return "gray"
    if n == 3:
        if jfif:
            return "YCbCr"
        if adobe_transform is not None:
            return "RGB" if adobe_transform == 0 else "YCbCr"
        if tuple(ids) == (82, 71, 66):  # 'R', 'G', 'B'
            return "RGB"
        return "YCbCr"
    if n == 4:
        return "CMYK" if adobe_transform in (None, 0) else "YCCK"
    return "unknown"


#: (luma-to-chroma h, v) -> sampling name
_RATIO_NAMES = {(s.h, s.v): name for name, s in CHROMA_SAMPLINGS.items()}


def sampling_name(factors: Sequence[tuple[int, int]], color_space: str) -> str:
    """Name of a component sampling layout given per-component (h, v) factors (see module docstring)."""
    if len(factors) == 1:
        return "gray"
    if all(f == factors[0] for f in factors):
        return "4:4:4"
    n = len(factors)
    if n == 3 or (n == 4 and color_space == "YCCK" and factors[3] == factors[0]):
        (h, v), (ch, cv), cr = factors[0], factors[1], factors[2]
        if cr != (ch, cv) or h % ch or v % cv:
            return "other"
        return _RATIO_NAMES.get((h // ch, v // cv), "other")
    return "other"


