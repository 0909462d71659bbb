"""Double JPEG compression: a labelled corpus from the shared clean scenes, and how well
``jsgstools.dqt.analysis`` detects it, estimates the primary quality, and how fast it runs.

Corpus (built in memory with Pillow, or written with ``--write DIR``: the JPEGs and ``labels.json``, schema
``jsgs/schemas/double_jpeg_corpus.schema.json``, each file's truth), from ``--per-scene`` PNGs of each
clean scene (``../shared/scenes/{llff_flower,llff_fern,custom_kwrous_cup,custom_myhan_mouse}/images``, every
k-th in name order), in 4:2:0 and 4:4:4:

* negatives: saved once at q = 10, 15, ..., 95;
* positives: saved at q1 in {20, 30, ..., 80}, decoded to RGB, saved again at q2 = q1 + 10, q1 + 15, ..., 95
  with the same subsampling (same size, so the 8x8 grids are aligned);
* the camera originals (``../shared/jpeg_samples/camera_originals``) as more negatives.

Printed, and written as markdown with ``--md FILE``: detection rate on positives with q2 >= q1 + 15 (target
>= 95 %) and with q2 = q1 + 10; false alarms on the negatives (target <= 5 %); the share of detected
positives whose primary quality is within +-5 of q1 (target >= 90 %); files/s on the 504x378 files (llff
scenes) on one core (target >= 200), timing header parse + decode + analysis from bytes in memory. Then
the analysis over ``jpeg_cup`` and ``jpeg_mouse`` (``--real``).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_double_jpeg.py [--per-scene 6] [--md FILE] [--real]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core: set before numpy loads its BLAS

import argparse  # noqa: E402
import io  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter, defaultdict  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jsgs.base.errors import JsgsError, reports_user_errors  # noqa: E402
from jsgs.base.io import LOCK_NAME, OutputLock, load_json_record, write_bytes_atomic, write_json_atomic  # noqa: E402
from jsgs.base.schema import validate  # noqa: E402
from jsgstools.dqt.analysis import Analysis, analyze_bytes  # noqa: E402
from jsgstools.dqt.parser import read_header_from  # noqa: E402

SHARED = ROOT.parent / "shared"
CLEAN_SCENES = ("llff_flower", "llff_fern", "custom_kwrous_cup", "custom_myhan_mouse")
SUBSAMPLINGS = {"4:2:0": 2, "4:4:4": 0}
NEG_QUALITIES = tuple(range(10, 100, 5))
Q1S = tuple(range(20, 90, 10))
#: labels.json's ``format``
CORPUS_FORMAT = "jsgs-double-jpeg-corpus"


@dataclass
class Item:
    """One corpus file: its bytes and its truth (q1 None for a single compression)."""

    name: str
    data: bytes
    scene: str
    subsampling: str
    q1: int | None
    q2: int | None
    size: tuple[int, int]


def jpeg(im: Image.Image, quality: int, subsampling: int) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format="JPEG", quality=quality, subsampling=subsampling, optimize=False)
    return buf.getvalue()


def sources(per_scene: int) -> list[tuple[str, Path]]:
    """(scene, png) pairs: ``per_scene`` PNGs spread evenly over each clean scene, in name order."""
    out = []
    for scene in CLEAN_SCENES:
        pngs = sorted((SHARED / "scenes" / scene / "images").glob("*.png"))
        if not pngs:
            continue
        idx = np.linspace(0, len(pngs) - 1, min(per_scene, len(pngs))).round().astype(int)
        out.extend((scene, pngs[i]) for i in sorted(set(idx.tolist())))
    return out


def corpus(per_scene: int) -> list[Item]:
    """The synthetic corpus (negatives and positives) plus the camera originals."""
    items: list[Item] = []
    for scene, png in sources(per_scene):
        with Image.open(png) as im:
            rgb = im.convert("RGB")
        for ss_name, ss in SUBSAMPLINGS.items():
            tag = f"{scene}/{png.stem}/{ss_name.replace(':', '')}"
            for q in NEG_QUALITIES:
                items.append(Item(f"{tag}/q{q}", jpeg(rgb, q, ss), scene, ss_name, None, q, rgb.size))
            for q1 in Q1S:
                with Image.open(io.BytesIO(jpeg(rgb, q1, ss))) as first:
                    once = first.convert("RGB")
                for q2 in range(q1 + 10, 100, 5):
                    data = jpeg(once, q2, ss)
                    items.append(Item(f"{tag}/q{q1}-q{q2}", data, scene, ss_name, q1, q2, rgb.size))
    for f in sorted((SHARED / "jpeg_samples" / "camera_originals").glob("*.JPG")):
        with Image.open(f) as im:
            size = im.size
        items.append(Item(f"camera/{f.name}", f.read_bytes(), "camera", "4:2:0", None, None, size))
    return items


def file_name(item: Item) -> str:
    """The item's file in a written corpus: its name with ``/`` as ``_``, ending in ``.jpg``."""
    return item.name.replace("/", "_") + ("" if item.name.lower().endswith(".jpg") else ".jpg")


def labels_doc(items: list[Item], per_scene: int, command: str | None) -> dict:
    """labels.json of a written corpus: the version, command and settings that made it, each file's truth."""
    import jsgs

    files = [{"file": file_name(it), "scene": it.scene, "subsampling": it.subsampling, "q1": it.q1,
              "q2": it.q2, "width": it.size[0], "height": it.size[1]} for it in items]  # fmt: skip
    settings = {"per_scene": per_scene, "encoder": f"Pillow {Image.__version__}, optimize off"}
    return {"format": CORPUS_FORMAT, "format_version": 1, "version": jsgs.__version__, "command": command,
            "settings": settings, "files": files}  # fmt: skip


def earlier_corpus(folder: Path) -> set[str]:
    """The entries of ``folder`` that an earlier ``--write`` made (its labels.json and the files it lists),
    when the folder holds nothing else; an empty set for a new or empty folder. JsgsError (one line) for a
    folder this tool did not make, or that holds anything besides such a corpus: it is never written into."""
    if folder.exists() and not folder.is_dir():
        raise JsgsError(f"{folder}: exists and is not a folder")
    entries = {p.name for p in folder.iterdir()} - {LOCK_NAME} if folder.is_dir() else set()
    if not entries:
        return set()
    labels = load_json_record(folder / "labels.json", "double_jpeg_corpus", str(folder / "labels.json"))
    if isinstance(labels, str):
        raise JsgsError(
            f"{folder}: not empty and not a corpus of this tool ({labels}); choose an empty or new folder"
        )
    ours = {"labels.json", *(f["file"] for f in labels["files"])}
    if others := sorted(entries - ours):
        raise JsgsError(
            f"{folder}: holds {others[0]}{f' and {len(others) - 1} more' if len(others) > 1 else ''}, not "
            "part of the corpus its labels.json lists, so it is left alone; choose an empty or new folder"
        )
    return entries


def write_corpus(items: list[Item], folder: Path, per_scene: int, command: str | None = None) -> None:
    """The corpus's JPEGs and labels.json into ``folder``, each file atomically, one writer at a time (its
    output lock); labels.json is checked against its schema first (JsgsError, one line naming it, and nothing
    written when it is not valid). Only a new or empty folder, or one holding nothing but a corpus an earlier
    ``--write`` made (:func:`earlier_corpus`), is written: that corpus is replaced whole (its labels.json goes
    first, so a cut-short rewrite leaves a folder refused again rather than mislabelled)."""
    doc = labels_doc(items, per_scene, command)
    validate(doc, "double_jpeg_corpus", str(folder / "labels.json"))
    with OutputLock(folder, f"bench_double_jpeg.py --write (into {folder})"):
        earlier = earlier_corpus(folder)
        (folder / "labels.json").unlink(missing_ok=True)
        for it in items:
            write_bytes_atomic(folder / file_name(it), it.data)
        for name in sorted(earlier - {file_name(it) for it in items} - {"labels.json"}):
            (folder / name).unlink()
        write_json_atomic(folder / "labels.json", doc)


def check_output_file(path: Path) -> None:
    """Refuse at once (JsgsError, one line) an output file that could not be written at the end: a folder
    at ``path``, or a file where one of its folders would go (missing folders are made)."""
    if path.is_dir():
        raise JsgsError(f"{path}: is a folder; --md takes a file name")
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise JsgsError(f"{path}: cannot be written: {parent} is not a folder")


def analyse(item: Item) -> Analysis:
    header = read_header_from(io.BytesIO(item.data), item.name, len(item.data))
    return analyze_bytes(item.data, header)


def pct(k: int, n: int) -> str:
    return f"{100 * k / n:.1f} % ({k}/{n})" if n else "-"


def speed(items: list[Item], rounds: int) -> float:
    """Files per second over the 504x378 items (median of ``rounds`` passes, one core)."""
    sel = [it for it in items if it.size == (504, 378)]
    analyse(sel[0])
    rates = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        for it in sel:
            analyse(it)
        rates.append(len(sel) / (time.perf_counter() - t0))
    return float(np.median(rates))


def real_scenes() -> list[str]:
    """Markdown lines: the analysis over the JPEG-only shared scenes."""
    lines = []
    for scene in ("jpeg_cup", "jpeg_mouse"):
        files = sorted((SHARED / "scenes" / scene / "images").glob("*.jpg"))
        if not files:
            continue
        res = [analyse(Item(f.name, f.read_bytes(), scene, "", None, None, (0, 0))) for f in files]
        header_q = Counter()
        for f in files[:1]:
            data = f.read_bytes()
            h = read_header_from(io.BytesIO(data), f.name, len(data))
            header_q[h.quality.quality if h.quality else None] += 1
        n_double = sum(r.double_compressed for r in res)
        prim = Counter(r.primary_quality for r in res if r.double_compressed)
        ev = np.array([r.evidence for r in res])
        lines.append(
            f"| {scene} | {len(files)} | {next(iter(header_q))} | {n_double} | "
            f"{', '.join(f'{q}: {c}' for q, c in sorted(prim.items())) or '-'} | "
            f"{ev.min():.1f} / {np.median(ev):.1f} / {ev.max():.1f} |"
        )
    return lines


@reports_user_errors
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-scene", type=int, default=6, help="source PNGs per clean scene")
    ap.add_argument("--rounds", type=int, default=3, help="timing passes over the 504x378 files")
    ap.add_argument(
        "--write",
        type=Path,
        help="also write the corpus (JPEGs + labels.json) into this folder: a new or empty one, or one "
        "holding only a corpus an earlier --write made (replaced whole)",
    )
    ap.add_argument("--md", type=Path, help="write the results table (markdown) to this file")
    ap.add_argument("--real", action="store_true", help="also analyse jpeg_cup and jpeg_mouse")
    args = ap.parse_args(argv)
    if args.per_scene < 1:
        raise JsgsError(f"--per-scene: at least 1 source PNG per scene (got {args.per_scene})")
    if args.md:
        check_output_file(args.md)
    if args.write:
        earlier_corpus(args.write)  # refused now rather than after the corpus is built

    t0 = time.perf_counter()
    items = corpus(args.per_scene)
    if args.write:
        given = sys.argv[1:] if argv is None else argv
        command = shlex.join(["python", "benchmarks/bench_double_jpeg.py", *given])
        write_corpus(items, args.write, args.per_scene, command)
    print(f"corpus: {len(items)} files in {time.perf_counter() - t0:.1f} s", flush=True)

    results = [(it, analyse(it)) for it in items]
    pos15 = [(it, a) for it, a in results if it.q1 is not None and it.q2 >= it.q1 + 15]
    pos10 = [(it, a) for it, a in results if it.q1 is not None and it.q2 == it.q1 + 10]
    neg = [(it, a) for it, a in results if it.q1 is None and it.scene != "camera"]
    cam = [(it, a) for it, a in results if it.scene == "camera"]
    det15 = sum(a.double_compressed for _, a in pos15)
    det10 = sum(a.double_compressed for _, a in pos10)
    fa = sum(a.double_compressed for _, a in neg + cam)
    detected = [(it, a) for it, a in results if it.q1 is not None and a.double_compressed]
    close = sum(abs(a.primary_quality - it.q1) <= 5 for it, a in detected)
    exact = sum(a.primary_quality == it.q1 for it, a in detected)
    rate = speed(items, args.rounds)

    rows = [
        ("positives, q2 >= q1 + 15: detected", pct(det15, len(pos15)), ">= 95 %", det15 >= 0.95 * len(pos15)),
        ("positives, q2 = q1 + 10: detected", pct(det10, len(pos10)), "(no target)", None),
        (
            "negatives (single, q 10..95 + camera): false alarms",
            pct(fa, len(neg) + len(cam)),
            "<= 5 %",
            fa <= 0.05 * (len(neg) + len(cam)),
        ),
        ("  of them camera originals", pct(sum(a.double_compressed for _, a in cam), len(cam)), "", None),
        (
            "detected positives: primary quality within +-5 of q1",
            pct(close, len(detected)),
            ">= 90 %",
            close >= 0.9 * len(detected),
        ),
        ("  exactly q1", pct(exact, len(detected)), "", None),
        ("speed, 504x378, one core (files/s)", f"{rate:.0f}", ">= 200", rate >= 200),
    ]
    md = ["| measure | result | target | met |", "|---|---|---|---|"]
    for name, res, target, ok in rows:
        md.append(f"| {name} | {res} | {target} | {'' if ok is None else ('yes' if ok else 'no')} |")

    # Detection by (q1, q2) and by subsampling.
    by_pair: dict[tuple[int, int], list[bool]] = defaultdict(list)
    for it, a in results:
        if it.q1 is not None:
            by_pair[(it.q1, it.q2)].append(a.double_compressed)
    q2s = sorted({q2 for _, q2 in by_pair})
    grid = ["| q1 \\ q2 | " + " | ".join(str(q) for q in q2s) + " |", "|---" * (len(q2s) + 1) + "|"]
    for q1 in Q1S:
        cells = [f"{100 * np.mean(by_pair[(q1, q2)]):.0f}" if (q1, q2) in by_pair else "" for q2 in q2s]
        grid.append(f"| {q1} | " + " | ".join(cells) + " |")
    by_ss = []
    for ss in SUBSAMPLINGS:
        p = [a.double_compressed for it, a in pos15 if it.subsampling == ss]
        n = [a.double_compressed for it, a in neg if it.subsampling == ss]
        by_ss.append(f"| {ss} | {pct(sum(p), len(p))} | {pct(sum(n), len(n))} |")
    fa_by_q = Counter(it.q2 for it, a in neg if a.double_compressed)
    errs = Counter(a.primary_quality - it.q1 for it, a in detected)

    env = (
        f"{len(items)} files from {len(sources(args.per_scene))} PNGs ({args.per_scene} per scene); "
        f"Python {platform.python_version()}, numpy {np.__version__}, Pillow {Image.__version__}, "
        f"{platform.machine()}, one thread"
    )
    out = [
        *md,
        "",
        env,
        "",
        "Detection rate (%) by q1 (rows) and q2 (columns), both subsamplings:",
        "",
        *grid,
        "",
        "| subsampling | detected (q2 >= q1 + 15) | false alarms |",
        "|---|---|---|",
        *by_ss,
        "",
        f"False alarms by quality: {dict(sorted(fa_by_q.items())) or 'none'}; primary quality error "
        f"(estimate - q1) on detected positives: {dict(sorted(errs.items()))}",
    ]
    if args.real:
        out += [
            "",
            "| scene | files | header quality | double | primary quality (files) "
            "| evidence min / median / max |",
            "|---|---|---|---|---|---|",
            *real_scenes(),
        ]
    text = "\n".join(out)
    print(text)
    if args.md:
        write_bytes_atomic(args.md, (text + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
