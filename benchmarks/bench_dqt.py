"""Header parsing speed: ``jsgstools.dqt.read_header`` vs Pillow's ``Image.open(f).quantization``.

Two folders of JPEGs made from the shared scenes (``../shared/scenes/*/images/*.png``; a synthetic texture
when they are absent), parsed by both in the same run, interleaved round by round:

* ``photo``: real-size photos, 4000x3000 (the scene images upscaled), q=85..95 4:2:0, each with a camera-like
  ~60 KB EXIF APP1 (MakerNote filler plus a 160x120 thumbnail JPEG) right after SOI;
* ``native``: the scene images at their own size (400x300 .. 640x480), q=75, JFIF only.

It prints files/second for each parser and their ratio, and the bytes each one takes from the OS per file
(counted on an instrumented unbuffered file object), to show that ``read_header`` stops at the header.

    .venv/bin/python benchmarks/bench_dqt.py [--data DIR] [--count 12] [--rounds 15] [--inner 40]

Timings are with the files in the page cache (every file is read once before timing).
"""

from __future__ import annotations

import argparse
import io
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the test-file builders live with the tests

from jpeg_builders import exif_app1, insert_after_soi  # noqa: E402

from jsgstools.dqt import clear_caches, read_header, read_header_from  # noqa: E402

SHARED_SCENES = ROOT.parent / "shared" / "scenes"


def source_images(count: int) -> list[Image.Image]:
    """``count`` RGB images, round-robin over the shared scenes, or synthetic ones when they are absent."""
    pngs_by_scene = (
        [sorted((s / "images").glob("*.png")) for s in sorted(SHARED_SCENES.iterdir())]
        if SHARED_SCENES.is_dir()
        else []
    )
    pngs_by_scene = [p for p in pngs_by_scene if p]
    images: list[Image.Image] = []
    for i in range(count):
        if pngs_by_scene:
            scene = pngs_by_scene[i % len(pngs_by_scene)]
            with Image.open(scene[(i // len(pngs_by_scene)) % len(scene)]) as im:
                images.append(im.convert("RGB"))
        else:
            rng = np.random.default_rng(i)
            yy, xx = np.mgrid[0:378, 0:504]
            arr = np.stack([np.sin(xx / (3 + i)) * 100 + 128, yy % 255, (xx * yy) % 255], -1)
            images.append(
                Image.fromarray(np.clip(arr + rng.normal(0, 10, arr.shape), 0, 255).astype(np.uint8))
            )
    return images


def encode(im: Image.Image, **kw: object) -> bytes:
    buf = io.BytesIO()
    im.save(buf, "JPEG", **kw)
    return buf.getvalue()


def make_folders(data: Path, count: int) -> dict[str, list[Path]]:
    """Create (once) the two benchmark folders; returns their files."""
    folders = {"photo": data / "photo_4000x3000_exif60k", "native": data / "native"}
    done = data / f".complete-{count}"
    if not done.exists():
        print(f"generating {count} + {count} JPEGs in {data} (once) ...", flush=True)
        for folder in folders.values():
            folder.mkdir(parents=True, exist_ok=True)
            for old in folder.glob("*.jpg"):
                old.unlink()
        for i, im in enumerate(source_images(count)):
            (folders["native"] / f"native_{i:03d}.jpg").write_bytes(encode(im, quality=75))
            big = im.resize((4000, 3000), Image.Resampling.BICUBIC)
            thumb = encode(big.resize((160, 120), Image.Resampling.BILINEAR), quality=70)
            app1 = exif_app1(thumb, maker_note_bytes=60_000 - len(thumb))
            photo = insert_after_soi(encode(big, quality=85 + i % 11, subsampling="4:2:0"), app1)
            (folders["photo"] / f"photo_{i:03d}.jpg").write_bytes(photo)
        done.touch()
    return {k: sorted(v.glob("*.jpg")) for k, v in folders.items()}


class CountingRaw(io.FileIO):
    """Unbuffered file counting the bytes that ``read``/``readinto`` hand out (= bytes taken from the OS)."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, "rb")
        self.count = 0

    def read(self, size: int = -1) -> bytes:  # type: ignore[override]
        data = super().read(size)
        self.count += len(data)
        return data

    def readinto(self, buffer: bytearray | memoryview) -> int:  # type: ignore[override]
        n = super().readinto(buffer)
        self.count += n or 0
        return n  # type: ignore[return-value]


def ours(path: Path) -> object:
    return read_header(path).tables


def ours_cold(path: Path) -> object:
    clear_caches()  # every table decoded and every quality estimated afresh
    return read_header(path).tables


def pillow(path: Path) -> object:
    with Image.open(path) as im:
        return im.quantization


PARSERS: dict[str, Callable[[Path], object]] = {
    "jsgstools read_header": ours,
    "read_header, caches cleared per file": ours_cold,
    "Pillow Image.open(f).quantization": pillow,
}


def bytes_read(files: list[Path]) -> tuple[list[int], list[int], list[int]]:
    """Per file: our bytes, Pillow's bytes (through a normal buffered reader), header size. Also checks
    that both parsers report the same tables."""
    our, pil, header = [], [], []
    for p in files:
        with CountingRaw(p) as raw:
            h = read_header_from(raw, str(p), p.stat().st_size)
            our.append(raw.count)
            header.append(h.header_size)
        with CountingRaw(p) as raw, Image.open(io.BufferedReader(raw)) as im:
            q = im.quantization
            pil.append(raw.count)
        same = {k: v.values.ravel().tolist() for k, v in h.tables.items()} == {
            k: list(v) for k, v in q.items()
        }
        assert same, f"{p}: the two parsers disagree"
    return our, pil, header


def one_pass(fn: Callable[[Path], object], files: list[Path], inner: int) -> tuple[float, float]:
    """(CPU seconds, wall seconds) for ``inner`` passes over ``files``."""
    c0, w0 = time.process_time(), time.perf_counter()
    for _ in range(inner):
        for p in files:
            fn(p)
    return time.process_time() - c0, time.perf_counter() - w0


def bench(files: list[Path], rounds: int, inner: int) -> dict[str, tuple[float, float]]:
    """Median files/s (by CPU time, by wall time) per parser; rounds interleave the parsers in rotating
    order so that none always runs first or on a colder cache."""
    for p in files:  # warm the page cache and every code path
        for fn in PARSERS.values():
            fn(p)
    names = list(PARSERS)
    cpu: dict[str, list[float]] = {n: [] for n in names}
    wall: dict[str, list[float]] = {n: [] for n in names}
    for r in range(rounds):
        for n in names[r % len(names) :] + names[: r % len(names)]:
            c, w = one_pass(PARSERS[n], files, inner)
            cpu[n].append(inner * len(files) / c)
            wall[n].append(inner * len(files) / w)
    return {n: (statistics.median(cpu[n]), statistics.median(wall[n])) for n in names}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("/tmp/jsgs_bench_dqt"), help="folder for the JPEGs")
    ap.add_argument("--count", type=int, default=12, help="files per folder")
    ap.add_argument("--rounds", type=int, default=15, help="timed rounds per parser (median reported)")
    ap.add_argument("--inner", type=int, default=40, help="passes over the folder per round")
    args = ap.parse_args()

    folders = make_folders(args.data, args.count)
    import PIL

    print(
        f"python {platform.python_version()}, Pillow {PIL.__version__}, {platform.machine()}, "
        f"{os.cpu_count()} CPUs; {args.rounds} rounds x {args.inner} passes per parser; page cache warm"
    )
    for name, files in folders.items():
        our_bytes, pil_bytes, header = bytes_read(files)
        assert all(b <= h for b, h in zip(our_bytes, header, strict=True)), "read past the header"
        size = statistics.mean(p.stat().st_size for p in files)
        print()
        print(
            f"{name}: {len(files)} files, mean size {size / 1e6:.2f} MB, mean header (SOI..end of SOS) "
            f"{statistics.mean(header):,.0f} B"
        )
        print("| parser | files/s (CPU time) | files/s (wall) | bytes read per file |")
        print("|---|---:|---:|---:|")
        rates = bench(files, args.rounds, args.inner)
        for n, (c, w) in rates.items():
            read = pil_bytes if n.startswith("Pillow") else our_bytes
            print(f"| {n} | {c:,.0f} | {w:,.0f} | {statistics.mean(read):,.0f} |")
        ours_c = rates["jsgstools read_header"][0]
        cold_c = rates["read_header, caches cleared per file"][0]
        pil_c = rates["Pillow Image.open(f).quantization"][0]
        print(f"ratio read_header / Pillow: {ours_c / pil_c:.2f}x (caches cleared: {cold_c / pil_c:.2f}x)")
    print()
    print("Both parsers report the same tables for every file (checked). Bytes read are counted on an")
    print("unbuffered file object; Pillow's go through the default buffered reader, as in Image.open(path).")


if __name__ == "__main__":
    main()
