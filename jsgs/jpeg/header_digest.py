"""The digest of a JPEG file's header: what the manifest records of each JPEG (``jpeg.header_sha256``) so that
the trainer can tell a file changed since its manifest was written.

SHA-256 over the marker segments before the first scan that fix how the file decodes, in file order, each
as it is stored (marker, length field, payload): DQT (the quantization tables), DHT and DAC (the entropy
coding tables), the frame header SOFn, DRI, APP0 (JFIF) and APP14 (Adobe: the colour transform), and the
first scan's header SOS. Metadata the decoder ignores is left out (APP1 to APP13 and APP15: Exif, XMP, ICC
profiles, ...; COM), and so are the pixels (the entropy-coded data after SOS). A file saved again with other
tables, another sampling or another frame type gets another digest; editing its Exif does not change it. A
file re-encoded with the very same header bytes keeps its digest: its JPEG state (what the trainer reads
from the manifest) is then still the file's.

The walk follows T.81 B.1 as libjpeg does (fill bytes before a marker; RSTn and TEM carry no length; up to
``MAX_JUNK`` stray bytes between segments are skipped, as the toolkit's header parser tolerates them). Only
the header bytes are read. Numpy-free and torch-free: the manifest writer and the trainer share it.
"""

from __future__ import annotations

import hashlib
import os
from typing import BinaryIO

from jsgs.base.errors import JsgsError

SOS = 0xDA
#: segments left out of the digest: APP1..APP13, APP15 and COM (metadata; no effect on decoding)
METADATA = frozenset([*range(0xE1, 0xEE), 0xEF, 0xFE])
#: markers without a length field: TEM and RST0..RST7
STANDALONE = frozenset([0x01, *range(0xD0, 0xD8)])
#: stray non-marker bytes tolerated between two segments (the toolkit's parser allows as many)
MAX_JUNK = 1024


def _walk(f: BinaryIO, size: int, name: str) -> str:
    def take(n: int) -> bytes:
        data = f.read(n)
        if len(data) != n:
            raise JsgsError(f"{name}: truncated JPEG header (the file ends before the first scan)")
        return data

    if size < 4 or take(2) != b"\xff\xd8":
        raise JsgsError(f"{name}: not a JPEG file (it does not start with FF D8)")
    h = hashlib.sha256()
    pos = 2
    while True:
        junk = 0
        c = take(1)[0]
        pos += 1
        while True:  # find FF followed by a code that is neither FF (fill) nor 00 (a stuffed byte)
            if c != 0xFF:
                junk += 1
                if junk > MAX_JUNK:
                    raise JsgsError(
                        f"{name}: no JPEG marker where a header segment should begin (offset {pos})"
                    )
                c = take(1)[0]
                pos += 1
                continue
            code = take(1)[0]
            pos += 1
            while code == 0xFF:
                code = take(1)[0]
                pos += 1
            if code != 0x00:
                break
            junk += 2
            c = take(1)[0]
            pos += 1
        if code in STANDALONE:
            continue
        if code in (0xD8, 0xD9):
            raise JsgsError(f"{name}: {'SOI' if code == 0xD8 else 'EOI'} marker before any scan")
        length_field = take(2)
        length = (length_field[0] << 8) | length_field[1]
        if length < 2 or pos + length > size:
            raise JsgsError(f"{name}: a header segment at offset {pos - 2} has an invalid length {length}")
        if code in METADATA:
            f.seek(length - 2, os.SEEK_CUR)
        else:
            h.update(bytes((0xFF, code)) + length_field + take(length - 2))
        pos += length
        if code == SOS:
            return h.hexdigest()


def header_digest(path: str | os.PathLike[str]) -> str:
    """The SHA-256 (hex) of the decoding segments of the JPEG file ``path`` (module docstring). JsgsError
    naming the file when it cannot be read, is not a regular file (refused at once, a FIFO included:
    :func:`jsgs.base.io.open_regular`) or has no valid header up to its first scan."""
    from jsgs.base.io import open_regular

    name = str(path)
    try:
        with open_regular(path) as f:
            return _walk(f, os.fstat(f.fileno()).st_size, name)
    except OSError as e:
        raise JsgsError(f"{name}: cannot read: {e.strerror or e}") from None


def header_digest_bytes(data: bytes, name: str = "<bytes>") -> str:
    """:func:`header_digest` of a JPEG held in memory."""
    import io

    return _walk(io.BytesIO(data), len(data), name)
