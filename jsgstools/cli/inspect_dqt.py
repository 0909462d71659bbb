"""``jsgstools inspect-dqt``: the JPEG header report; its logic lives in ``jsgstools.dqt``."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, user_errors


def _emit(text: str, err: bool = False) -> None:
    """Echo that survives a closed pipe (``inspect-dqt *.jpg | head``) without a traceback."""
    try:
        click.echo(text, err=err)
    except BrokenPipeError:
        # Point stdout at /dev/null so the interpreter's final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(1)


@click.command(
    "inspect-dqt",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgstools inspect-dqt --analyze scene/images/*.jpg"),
)
@click.argument("images", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print one JSON document (jsgs/schemas/dqt_report.schema.json) instead of the table; tables in "
    "natural "
    "row-major order.",
)
@click.option("--tables", "show_tables", is_flag=True, help="Also print every 8x8 table below the summary.")
@click.option(
    "--analyze",
    is_flag=True,
    help="Also decode each image and look for an earlier, coarser quantization on its 8x8 grid (double "
    "compression), and estimate its quantisation noise and how much its block grid shows: DOUBLE, EST. "
    "PSNR and BLOCKS columns in the table, an "
    "`analysis` object per file in --json (docs/double_compression.md).",
)
@user_errors
def inspect_dqt(images: tuple[Path, ...], as_json: bool, show_tables: bool, analyze: bool) -> None:
    """Report the JPEG header of each IMG without decoding it.

    Per file: every quantization table (DQT: id, 8- or 16-bit, 64 values), which component (Y, Cb, Cr,
    ...) uses which table, frame type (baseline / extended / progressive / lossless, Huffman or
    arithmetic), size, sampling factors and their name (4:4:4, 4:2:2, 4:2:0, 4:4:0, 4:1:1, gray, other),
    restart interval, and the IJG (libjpeg) quality whose tables are closest: "75" when the tables are
    exactly IJG's at 75, "~75" when 75 is only the nearest (camera/phone encoders use their own tables).

    All tables, with --tables and in --json, are 8x8 in NATURAL ROW-MAJOR order: values[v][u], v = vertical
    frequency (row), u = horizontal frequency (column); files store them in zigzag order.

    Only the header is read (markers up to the first scan); APPn segments such as EXIF are skipped by
    length, so an EXIF thumbnail's tables are never mistaken for the image's. Hierarchical (SOF5-7,
    SOF13-15) and JPEG-LS files are refused. A bad file gets "error: FILE: what" on stderr, the other
    files are still reported, and the exit code is 1.

    With --analyze the pixels are decoded too: the histogram of each DCT coefficient on the file's own grid
    shows whether the image went through a coarser quantization before the one in its header (a photo
    saved, then saved again at a higher quality). The DOUBLE column reads "no", or "yes qNN" with the
    closest IJG quality of the earlier tables, and the confidence in that verdict; --json adds the earlier
    and the effective tables (per coefficient the coarser of the two steps). EST. PSNR is how far the file
    is from its uncompressed original through quantisation, estimated from its own DCT coefficients with
    the effective tables (--json: noise_variance, in 8-bit units squared). BLOCKS is the blockiness of the
    decoded luma: the mean step between neighbouring samples across the 8x8 block edges over the same inside
    the blocks, about 1 where no grid shows (--json: blockiness).
    """
    from jsgstools.dqt import dumps_json, format_table, inspect_files

    result = inspect_files(images, analyze=analyze)
    if as_json:
        _emit(dumps_json(result.to_json()))
    else:
        _emit(format_table(result, show_tables=show_tables, analyze=analyze))
    for err in result.errors:  # after the report, so they are the last lines a terminal shows
        _emit(f"error: {err}", err=True)
    if result.errors:
        sys.exit(1)


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    group.add_command(inspect_dqt)
