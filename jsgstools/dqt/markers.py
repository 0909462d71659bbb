"""JPEG marker codes, their names, and which markers the header parser reads, skips or refuses (T.81 B.1).
"""

from __future__ import annotations

import re

from jsgs.jpeg.tables import CHROMA_SAMPLINGS

#: named marker codes (the byte after 0xFF)
SOI, EOI, SOS, DQT, DHT, DRI = 0xD8, 0xD9, 0xDA, 0xDB, 0xC4, 0xDD
APP0, APP14, APP15 = 0xE0, 0xEE, 0xEF

# SOFn marker code -> (frame type, entropy coding).
SUPPORTED_SOF: dict[int, tuple[str, str]] = {
    0xC0: ("baseline", "huffman"),
    0xC1: ("extended", "huffman"),
    0xC2: ("progressive", "huffman"),
    0xC3: ("lossless", "huffman"),
    0xC9: ("extended", "arithmetic"),
    0xCA: ("progressive", "arithmetic"),
    0xCB: ("lossless", "arithmetic"),
}
UNSUPPORTED_FRAME: dict[int, str] = {
    0xC5: "hierarchical (differential sequential DCT)",
    0xC6: "hierarchical (differential progressive DCT)",
    0xC7: "hierarchical (differential lossless)",
    0xCD: "hierarchical (differential sequential DCT, arithmetic)",
    0xCE: "hierarchical (differential progressive DCT, arithmetic)",
    0xCF: "hierarchical (differential lossless, arithmetic)",
    0xDE: "hierarchical (DHP marker)",
    0xDF: "hierarchical (EXP marker)",
    0xC8: "reserved JPEG extension (JPG marker)",
    0xF7: "JPEG-LS (SOF55)",
}
# Markers without a length field (T.81 B.1.1.3): RSTn and TEM; SOI/EOI are handled on their own.
_STANDALONE = frozenset([0x01, *range(0xD0, 0xD8)])
# Segments skipped by length without interpretation.
_SKIPPED = frozenset(
    [0xC4, 0xCC, 0xDC, 0xFE, 0xF0, 0xF1, 0xF2, 0xF3, 0xF4, 0xF5, 0xF6, 0xF8, 0xF9, 0xFA, 0xFB, 0xFC, 0xFD]
)
_APP_PEEK = 32  # bytes of an APPn payload read to name it (and to parse JFIF/Adobe, which need 14 and 12)
_READ_THROUGH = 1024  # uninterpreted non-APP segments up to this size are read through rather than skipped
_PRINTABLE = re.compile(rb"[\x20-\x7e]*")
_MAX_JUNK = 1024  # non-marker bytes tolerated between segments (libjpeg warns and skips them too)

_NAMES = {
    0xC4: "DHT",
    0xC8: "JPG",
    0xCC: "DAC",
    0xD8: "SOI",
    0xD9: "EOI",
    0xDA: "SOS",
    0xDB: "DQT",
    0xDC: "DNL",
    0xDD: "DRI",
    0xDE: "DHP",
    0xDF: "EXP",
    0xFE: "COM",
    0x01: "TEM",
}

_COMPONENT_NAMES = {
    "gray": ("gray",),
    "YCbCr": ("Y", "Cb", "Cr"),
    "RGB": ("R", "G", "B"),
    "CMYK": ("C", "M", "Y", "K"),
    "YCCK": ("Y", "Cb", "Cr", "K"),
}
#: Every sampling name a header can report: the named layouts of ``jsgs.jpeg.tables.CHROMA_SAMPLINGS``, then
#: one component, then any other layout.
SAMPLING_NAMES = (*CHROMA_SAMPLINGS, "gray", "other")

TABLE_ORDER_NOTE = (
    "Quantization tables are 8x8 in natural row-major order: values[v][u], v = vertical frequency (row), "
    "u = horizontal frequency (column); the file stores them in zigzag order."
)


def marker_name(code: int) -> str:
    """Human name of marker ``0xFF<code>``: SOF0, DQT, APP1, RST3, ... or ``0xFFxx``."""
    if code in _NAMES:
        return _NAMES[code]
    if 0xC0 <= code <= 0xCF:
        return f"SOF{code - 0xC0}"
    if 0xD0 <= code <= 0xD7:
        return f"RST{code - 0xD0}"
    if 0xE0 <= code <= 0xEF:
        return f"APP{code - 0xE0}"
    if code == 0xF7:
        return "SOF55"
    if 0xF0 <= code <= 0xFD:
        return f"JPG{code - 0xF0}"
    return f"0xFF{code:02X}"


_MARKER_NAMES = [marker_name(c) for c in range(256)]
# Markers that begin a segment with a length field and that the parser accepts before SOS.
_SEGMENT_MARKERS = frozenset([*SUPPORTED_SOF, *_SKIPPED, 0xDA, 0xDB, 0xDD, *range(0xE0, 0xF0)])
# Segments that may come between two scans (T.81 B.2.4, B.5): tables, DRI, DNL, COM, APPn and the next SOS.
_BETWEEN_SCANS = frozenset([DQT, DHT, 0xCC, DRI, 0xDC, 0xFE, SOS, *range(APP0, APP15 + 1)])


