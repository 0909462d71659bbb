"""The manifest records each JPEG's colour transform, and JSGS refuses the states its observation operator
cannot represent (CMYK, YCCK, RGB-coded; greyscale and unnamed samplings), naming the view."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgs.base.manifest import JpegState
from jsgs.method.image_terms import view_tables
from jsgstools.dqt import parse_header


def _jpeg(mode: str) -> bytes:
    rng = np.random.default_rng(0)
    im = Image.fromarray(rng.integers(0, 255, (16, 16, 3), dtype=np.uint8)).convert(mode)
    buf = io.BytesIO()
    im.save(buf, format="JPEG", quality=60)
    return buf.getvalue()


def test_colour_transform_is_recorded() -> None:
    assert parse_header(_jpeg("RGB"), "a.jpg").manifest_state()["color_space"] == "YCbCr"
    assert parse_header(_jpeg("CMYK"), "c.jpg").manifest_state()["color_space"] in ("CMYK", "YCCK")


class _View:
    def __init__(self, name: str, jpeg: JpegState) -> None:
        self.index, self.name, self.jpeg = 0, name, jpeg


@pytest.mark.parametrize("space", ["CMYK", "YCCK", "RGB"])
def test_jsgs_refuses_what_jo_cannot_represent(space: str, tmp_path: Path) -> None:
    t = np.full((8, 8), 4, dtype=np.int32)
    state = JpegState(t, t, "4:2:0", 90, False, 8, "baseline", color_space=space)
    with pytest.raises(JsgsError, match=f"view 'v.jpg' is a {space} JPEG"):
        view_tables([_View("v.jpg", state)], torch.device("cpu"), "m.json")  # type: ignore[list-item]
    ok = JpegState(t, t, "4:2:0", 90, False, 8, "baseline", color_space="YCbCr")
    assert 0 in view_tables([_View("v.jpg", ok)], torch.device("cpu"), "m.json")  # type: ignore[list-item]


@pytest.mark.parametrize(
    ("sampling", "chroma", "expected"),
    [
        ("gray", None, "view 'v.jpg' is a greyscale JPEG"),
        ("other", "table", "view 'v.jpg' has chroma sampling other; the JPEG observation operator supports"),
    ],
)
def test_jsgs_refuses_samplings_jo_cannot_represent(sampling: str, chroma: str | None, expected: str) -> None:
    """JO models h1v1, h2v1, h2v2, h1v2 and h4v1 chroma; a greyscale file or a layout without a name is
    refused naming the view rather than simulated wrongly."""
    t = np.full((8, 8), 4, dtype=np.int32)
    state = JpegState(t, None if chroma is None else t, sampling, 90, False, 8, "baseline",
                      color_space="gray" if chroma is None else "YCbCr")
    with pytest.raises(JsgsError, match=f"^m.json: {expected}"):
        view_tables([_View("v.jpg", state)], torch.device("cpu"), "m.json")  # type: ignore[list-item]
    for ok in ("4:4:0", "4:1:1"):
        state = JpegState(t, t, ok, 90, False, 8, "baseline", color_space="YCbCr")
        assert view_tables([_View("v.jpg", state)], torch.device("cpu"), "m.json")[0].sampling == ok  # type: ignore[list-item]


def test_jsgs_refuses_a_cr_table_of_its_own() -> None:
    t = np.full((8, 8), 4, dtype=np.int32)
    state = JpegState(t, t, "4:2:0", 90, False, 8, "baseline", color_space="YCbCr", cr_table=t + 1)
    with pytest.raises(JsgsError, match="^m.json: view 'v.jpg' quantizes Cr with a table of its own"):
        view_tables([_View("v.jpg", state)], torch.device("cpu"), "m.json")  # type: ignore[list-item]
