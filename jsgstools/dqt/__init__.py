"""Marker-level JPEG header parser: quantization tables, frame, components, sampling, restart interval.

In the style of Pillow's ``JpegImagePlugin``: it walks the marker segments from SOI to the first SOS and
never decodes pixels. Unlike Pillow it reads only what it needs, segment by segment from the file object,
not past the first SOS segment when the first scan codes every component: APPn payloads (beyond the first
32 bytes, which name them) and other uninterpreted segments over 1 KiB are skipped by their length (a seek,
not a read). A 4000x3000 photo with a 60 KB EXIF block costs about 700 bytes, and the DQT of an EXIF
thumbnail (which lives *inside* APP1) is never seen.

Rules, stated once:

* Frame types (SOFn): SOF0 baseline, SOF1 extended, SOF2 progressive, SOF3 lossless (Huffman coding) and
  SOF9/10/11 the same three with arithmetic coding are reported. Hierarchical frames (SOF5-7, SOF13-15, DHP,
  EXP), JPEG-LS (SOF55) and the reserved JPG marker are refused with an "unsupported frame type" error.
  Lossless frames use no quantization tables: they get ``quality = None`` and ``manifest_state()`` refuses.
* Tables: each component's table is the definition in force when the component's first scan begins (libjpeg
  latches it then; a later DQT with the same id replaces an earlier one). For the components of the first
  scan that is the definition at the first SOS. A first scan that leaves components out (mozjpeg's
  progressive files code each component's DC apart; some encoders write one sequential scan per component)
  makes the parser follow the scans, skipping their entropy-coded data by its markers, until every component
  has begun one: a DQT between scans counts for the components not yet scanned (Pillow's ``quantization``
  misses it). Two components with one table id that latch different tables (the id redefined between their
  first scans) each keep their own (``JpegHeader.relatched``; Cr's becomes ``cr_table``). Values are converted
  from the file's zigzag order to natural row-major 8x8 order, entry ``[v][u]`` (v = vertical frequency).
  Tables may come after SOF; a component's table must be defined before its first scan.
* Colour space (libjpeg's ``default_decompress_parms``): 1 component -> gray; 3 components -> YCbCr when a
  JFIF APP0 is present, else per the Adobe APP14 transform (0 -> RGB, otherwise YCbCr), else by component
  ids (1,2,3 -> YCbCr; 'R','G','B' -> RGB; anything else -> YCbCr, libjpeg's assumption); 4 components ->
  CMYK without Adobe APP14 or with transform 0, YCCK otherwise; 2 components -> unknown (named C1, C2).
* Sampling name: gray for one component; 4:4:4 when all components share their factors; otherwise, for
  3 components (or YCCK with K sampled like Y) whose two chroma components agree, the luma/chroma ratio
  (1,1) 4:4:4, (2,1) 4:2:2, (2,2) 4:2:0, (1,2) 4:4:0, (4,1) 4:1:1; everything else is "other".
* Quality: ``estimate_quality`` on the first component's table (luma) and, with two or more components,
  the second component's table (chroma).

Every failure is a ``JsgsError("<name>: <what>")`` on one line; nothing else escapes (see the fuzz test).
"""


from __future__ import annotations

from jsgstools.dqt.cache import clear_caches
from jsgstools.dqt.header import (
    AppSegment,
    Component,
    JpegHeader,
    QuantTable,
    quality_of,
    sampling_name,
)
from jsgstools.dqt.markers import (
    SAMPLING_NAMES,
    SUPPORTED_SOF,
    TABLE_ORDER_NOTE,
    UNSUPPORTED_FRAME,
    marker_name,
)
from jsgstools.dqt.parser import ParseState, parse_header, read_header, read_header_from
from jsgstools.dqt.report import Inspection, dumps_json, format_table, inspect_files

__all__ = [
    "SAMPLING_NAMES",
    "SUPPORTED_SOF",
    "TABLE_ORDER_NOTE",
    "UNSUPPORTED_FRAME",
    "AppSegment",
    "Component",
    "Inspection",
    "JpegHeader",
    "ParseState",
    "QuantTable",
    "clear_caches",
    "dumps_json",
    "format_table",
    "inspect_files",
    "marker_name",
    "parse_header",
    "quality_of",
    "read_header",
    "read_header_from",
    "sampling_name",
]
