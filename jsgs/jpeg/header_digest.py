"""The digest of a JPEG file's header: what the manifest records of each JPEG (``jpeg.header_sha256``, with
``jpeg.header_digest_scheme``) so that the trainer can tell a file changed since its manifest was written.

SHA-256 over the marker segments that fix how the file decodes, in file order, each as it is stored (marker,
length field, payload): DQT (the quantization tables), DHT and DAC (the entropy coding tables), the frame
header SOFn, DRI, DNL, APP0 (JFIF) and APP14 (Adobe: the colour transform), and the scan headers SOS. Metadata
the decoder ignores is left out (APP1 to APP13 and APP15: Exif, XMP, ICC profiles, ...; COM), and so are the
pixels (the entropy-coded data after each SOS). A file saved again with other tables, another sampling or
another frame type gets another digest; editing its Exif does not change it. A file re-encoded with the very
same header bytes keeps its digest: its JPEG state (what the trainer reads from the manifest) is then still
the file's.

Two schemes, which differ only where they stop:

* 2 (:data:`SCHEME`, what ``jsgstools manifest`` records): at the scan header by which every component of the
  frame has begun a scan. Where the first scan leaves components out (mozjpeg's progressive files, one
  sequential scan per component), the walk goes on over the scans' entropy-coded data to the segments between
  them, so that a DQT between scans (the table such a component decodes with) is covered, as the toolkit's
  header parser reads it. A file whose first scan codes every component (almost every file) gets the same
  digest under both schemes.
* 1 (manifests that record no scheme): at the first scan header.

The walk follows T.81 B.1 as libjpeg does (fill bytes before a marker; RSTn and TEM carry no length; up to
``MAX_JUNK`` stray bytes between segments are skipped, as the toolkit's header parser tolerates them). Only
the header bytes are read, and under scheme 2 the coded data of the scans before every component's first.
Numpy-free and torch-free: the manifest writer and the trainer share it.
"""

from __future__ import annotations

import hashlib
import os
import re
from typing import BinaryIO

from jsgs.base.errors import JsgsError

SOS = 0xDA
#: the scheme ``jsgstools manifest`` records (``jpeg.header_digest_scheme``); a manifest without one used 1
SCHEME = 2
SCHEMES = (1, 2)
#: frame headers SOF0..SOF15 (not DHT C4, JPG C8, DAC CC): the walk reads their component ids
SOF = frozenset(set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC})
#: segments left out of the digest: APP1..APP13, APP15 and COM (metadata; no effect on decoding)
METADATA = frozenset([*range(0xE1, 0xEE), 0xEF, 0xFE])
#: markers without a length field: TEM and RST0..RST7
STANDALONE = frozenset([0x01, *range(0xD0, 0xD8)])
#: stray non-marker bytes tolerated between two segments (the toolkit's parser allows as many)
MAX_JUNK = 1024
#: a marker inside entropy-coded data: FF then a code that is not 00 (a stuffed FF), FF (fill) or RSTn
MARKER_IN_DATA = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
#: bytes of entropy-coded data read at a time while looking for the next marker
SCAN_CHUNK = 16384


def coded_data_end(chunk: bytes) -> tuple[int, bool]:
    """Where a scan's entropy-coded data in ``chunk`` (read from inside it) ends: the offset of the FF of the
    first marker in it and True; with no marker, the bytes that are surely coded data (all but a last FF,
    which may begin a marker the next read completes) and False. The toolkit's header parser and
    :class:`_Reader` both move over coded data with it."""
    m = MARKER_IN_DATA.search(chunk)
    if m is not None:
        return m.start(), True
    return len(chunk) - (chunk[-1:] == b"\xff"), False


class _Reader:
    """``f`` read forward with its offset; ``where`` names the part of the file being read, for the
    truncation message."""

    def __init__(self, f: BinaryIO, size: int, name: str) -> None:
        self.f, self.size, self.name, self.pos = f, size, name, 0
        self.where = "the first scan"

    def take(self, n: int) -> bytes:
        data = self.f.read(n)
        if len(data) != n:
            raise JsgsError(f"{self.name}: truncated JPEG header (the file ends before {self.where})")
        self.pos += n
        return data

    def next_marker(self) -> int:
        """The code of the next marker (fill bytes, stuffed bytes and up to ``MAX_JUNK`` stray bytes
        skipped), the reader after it."""
        junk = 0
        c = self.take(1)[0]
        while True:  # find FF followed by a code that is neither FF (fill) nor 00 (a stuffed byte)
            if c != 0xFF:
                junk += 1
                if junk > MAX_JUNK:
                    raise JsgsError(
                        f"{self.name}: no JPEG marker where a header segment should begin (offset {self.pos})"
                    )
                c = self.take(1)[0]
                continue
            code = self.take(1)[0]
            while code == 0xFF:
                code = self.take(1)[0]
            if code != 0x00:
                return code
            junk += 2
            c = self.take(1)[0]

    def skip_coded_data(self) -> None:
        """Move over a scan's entropy-coded data (bytes, stuffed FF 00, RSTn) to the FF of the next marker."""
        while True:
            start = self.pos
            chunk = self.f.read(SCAN_CHUNK)
            keep, found = coded_data_end(chunk)
            if not found and len(chunk) < SCAN_CHUNK:
                raise JsgsError(f"{self.name}: truncated JPEG (the file ends before {self.where})")
            self.pos = start + keep
            self.f.seek(self.pos)
            if found:
                return


def _walk(f: BinaryIO, size: int, name: str, scheme: int) -> str:
    r = _Reader(f, size, name)
    if size < 4 or r.take(2) != b"\xff\xd8":
        raise JsgsError(f"{name}: not a JPEG file (it does not start with FF D8)")
    h = hashlib.sha256()
    frame: set[int] | None = None  # the frame's component ids
    scanned: set[int] = set()  # the components that have begun a scan
    while True:
        code = r.next_marker()
        if code in STANDALONE:
            continue
        if code in (0xD8, 0xD9):
            raise JsgsError(f"{name}: {'SOI' if code == 0xD8 else 'EOI'} marker before {r.where}")
        length_field = r.take(2)
        length = (length_field[0] << 8) | length_field[1]
        if length < 2 or r.pos + length - 2 > size:
            raise JsgsError(f"{name}: a header segment at offset {r.pos - 4} has an invalid length {length}")
        if code in METADATA:
            f.seek(length - 2, os.SEEK_CUR)
            r.pos += length - 2
            continue
        payload = r.take(length - 2)
        h.update(bytes((0xFF, code)) + length_field + payload)
        if code in SOF and frame is None and len(payload) >= 6:
            frame = set(payload[6 : 6 + 3 * payload[5] : 3])
        if code == SOS:
            scanned.update(payload[1 : 1 + 2 * payload[0] : 2] if payload else ())
            if scheme == 1 or frame is None or frame <= scanned:
                return h.hexdigest()
            r.where = "every component's first scan"
            r.skip_coded_data()


def header_digest(path: str | os.PathLike[str], scheme: int = SCHEME) -> str:
    """The SHA-256 (hex) of the decoding segments of the JPEG file ``path`` under ``scheme`` (module
    docstring). JsgsError naming the file when it cannot be read, is not a regular file (refused at once, a
    FIFO included: :func:`jsgs.base.io.open_regular`) or has no valid header up to where the scheme stops."""
    from jsgs.base.io import open_regular

    name = str(path)
    try:
        with open_regular(path) as f:
            return _walk(f, os.fstat(f.fileno()).st_size, name, scheme)
    except OSError as e:
        raise JsgsError(f"{name}: cannot read: {e.strerror or e}") from None


def header_digest_bytes(data: bytes, name: str = "<bytes>", scheme: int = SCHEME) -> str:
    """:func:`header_digest` of a JPEG held in memory."""
    import io

    return _walk(io.BytesIO(data), len(data), name, scheme)
