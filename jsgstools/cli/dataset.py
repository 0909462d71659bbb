"""``jsgstools synth | compress | validate | manifest | downscale``: thin wrappers over
``jsgstools.{synth,compress,validate,manifest,downscale}`` (the logic and its rules live there)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, SEED, WORKERS, invocation, user_errors
from jsgs.base.io import OutputLock
from jsgs.base.limits import MAX_INT_SETTING

SCHEDULE_HELP = (
    "uniform: the nine qualities 10..90 equally; gaussian: weights exp(-x^2/2) at x = -2..2 (q=10..90); "
    "descending: weights 9:8:...:1 from q=90 down to q=10; fixed: every training view at --quality; "
    "clean: training views stay lossless PNG (the ceiling baseline)."
)


@click.command(
    "synth",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgstools synth demo_scene --views 24 --size 96x72"),
)
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--views", default=32, show_default=True, help="Number of cameras on the ring (2..1000).")
@click.option("--size", default="160x120", show_default=True, help="Image size WIDTHxHEIGHT in pixels.")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Seed of the textures and the camera jitter.")  # fmt: skip
@click.option("--supersample", default=2, show_default=True, help="Rays per pixel side (2 = 2x2 per pixel).")
@click.option(
    "--point-density",
    default=1.0,
    show_default=True,
    help="Scale of the number of points3D (one initial Gaussian each; 0.3 for a quick CPU demo).",
)
@click.option(
    "--texture-scale",
    default=1.0,
    show_default=True,
    help="Multiplier on every texture's period (0.1..100; 4 gives detail a few hundred Gaussians can learn).",
)
@click.option(
    "--force",
    is_flag=True,
    help=(
        "Replace images/ and sparse/ of an earlier synth in OUT (.jsgstools.json) once the new ones are "
        "complete."
    ),
)
@user_errors
def synth_cmd(
    out: Path,
    views: int,
    size: str,
    seed: int,
    supersample: int,
    point_density: float,
    texture_scale: float,
    force: bool,
) -> None:
    """Write a small synthetic COLMAP scene into OUT: a textured room with three boxes (checkers, stripes,
    random mosaics: the high frequencies JPEG destroys), rendered exactly with numpy from VIEWS cameras on a
    ring looking at the centre. OUT/images/*.png (lossless), OUT/sparse/0/ (binary model, one PINHOLE camera,
    points3D sampled on the surfaces with their colours). Deterministic given the options."""
    from jsgstools.synth import parse_size, synth

    with OutputLock(out, f"jsgstools synth (into {out})"):
        res = synth(
            out,
            views=views,
            size=parse_size(size),
            seed=seed,
            supersample=supersample,
            force=force,
            progress=sys.stderr.isatty(),
            point_density=point_density,
            texture_scale=texture_scale,
        )
    c = res.camera
    click.echo(
        f"synth: {res.views} views of {res.width}x{res.height} (PINHOLE fx={c.fx:g} cx={c.cx:g} "
        f"cy={c.cy:g}), {res.points} points3D, seed {seed}"
    )
    click.echo(f"wrote {out}/images/ ({res.views} PNG) and {out}/sparse/0/")


@click.command(
    "compress",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format(
        "jsgstools compress ../shared/scenes/llff_flower --out flower_gaussian --schedule gaussian"
    ),
)
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output folder DIR.")
@click.option(
    "--schedule",
    required=True,
    type=click.Choice(["uniform", "gaussian", "descending", "fixed", "clean"]),
    help=SCHEDULE_HELP,
)
@click.option("--quality", type=int, default=None, help="The quality of --schedule fixed (1..100).")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Seed of the quality-to-view assignment.")  # fmt: skip
@click.option(
    "--test-every",
    type=click.IntRange(max=MAX_INT_SETTING),
    default=8,
    show_default=True,
    help="View i (sorted by image name) is a test view when i % N == 0 (N at least 1); test views are never "
    "compressed.",
)
@click.option(
    "--subsampling",
    type=click.Choice(["444", "422", "420"]),
    default="420",
    show_default=True,
    help="JPEG chroma subsampling.",
)
@click.option(
    "--force",
    is_flag=True,
    help=(
        "Replace the outputs of an earlier compress in DIR (its .jsgstools.json) once the new ones are "
        "complete; other files are kept."
    ),
)
@click.option("--jobs", type=WORKERS, default=None, help="Worker processes [default: all cores].")
@click.option(
    "--recompress",
    type=int,
    default=None,
    help="Save each JPEG training view once more at this quality, as an app re-saving a photo does (a "
    "double-compressed dataset: its headers say this quality).",
)
@user_errors
def compress_cmd(
    scene: Path,
    out: Path,
    schedule: str,
    quality: int | None,
    seed: int,
    test_every: int,
    subsampling: str,
    force: bool,
    jobs: int | None,
    recompress: int | None,
) -> None:
    """Build a mixed-quality JPEG dataset in DIR from the clean scene SCENE (COLMAP model + lossless images).

    Counts per quality: largest remainder of n*w/sum(w) (ties to the higher quality), dealt to the training
    views by a seeded shuffle. Distorted cameras are undistorted to PINHOLE (OpenCV) before encoding; the
    intrinsics are scaled to the image files. Writes DIR/images/ (train .jpg, test .png), DIR/reference/
    (lossless .png of every view), DIR/sparse/0/, DIR/compress.json and, last, DIR/manifest.json. SCENE is
    never written to."""
    from jsgstools.compress import QUALITIES, compress
    from jsgstools.scene import fmt_factor

    with OutputLock(out, f"jsgstools compress (into {out})"):
        res = compress(
            scene,
            out,
            schedule,
            quality=quality,
            seed=seed,
            test_every=test_every,
            subsampling=subsampling,
            force=force,
            jobs=jobs,
            progress=sys.stderr.isatty(),
            command=invocation(click.get_current_context(), "jsgstools"),
            recompress=recompress,
        )
    rec = res.record
    st = rec["settings"]
    views = rec["views"]
    n_train = sum(v["split"] == "train" for v in views)
    click.echo(
        f"compress: {rec['source']['name']} -> {out} (schedule {schedule}"
        + (f" q={quality}" if quality is not None else "")
        + f", seed {seed}, test every {test_every}, {st['subsampling']})"
    )
    cams = rec["cameras"]
    for cam in cams[:3]:
        s, o = cam["source"], cam["output"]
        what = f"undistorted, zoom {cam['zoom']:.4f}" if cam["undistorted"] else "no resampling"
        click.echo(
            f"  camera {cam['camera_id']}: {s['model']} {s['width']}x{s['height']} -> PINHOLE "
            f"{o['width']}x{o['height']} fx={o['params'][0]:.2f} ({what})"
        )
    if len(cams) > 3:
        click.echo(f"  ... and {len(cams) - 3} more cameras (see compress.json)")
    click.echo(f"  downscale: {fmt_factor(st['downscale'] or 1.0)}")
    click.echo(f"  views: {len(views)} = {n_train} train + {len(views) - n_train} test")
    if schedule == "clean":
        click.echo("  train views kept lossless (PNG)")
    else:
        qs = list(QUALITIES) if schedule != "fixed" else [quality]
        click.echo("  quality " + " ".join(f"{q:>3}" for q in qs))
        click.echo("  views   " + " ".join(f"{st['counts'].get(str(q), 0):>3}" for q in qs))
    n_jpg = sum(v["quality"] is not None for v in views)
    click.echo(
        f"wrote {out}/images/ ({n_jpg} JPEG, {len(views) - n_jpg} PNG), {out}/reference/ ({len(views)} "
        f"PNG), {out}/sparse/0/, {out}/compress.json, {out}/manifest.json"
    )


@click.command(
    "validate",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgstools validate flower_gaussian"),
)
@click.argument("scene", type=click.Path(path_type=Path))
@click.option(
    "--test-every",
    type=click.IntRange(0, MAX_INT_SETTING),
    default=8,
    show_default=True,
    help="The split the summary describes (as manifest --test-every; 0: no test views).",
)
@click.option("--analyze", is_flag=True, help="Also warn about JPEG views compressed twice (decodes them).")
@user_errors
def validate_cmd(scene: Path, test_every: int, analyze: bool) -> None:
    """Check the COLMAP scene SCENE (model in sparse/0/ or sparse/, binary or text; images in images/).

    Checks: every registered image exists (exact name, or the only file with the same stem), its size matches
    its camera at one downscale factor for the whole scene (reported), camera models are pinhole
    (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV are a warning: compress undistorts them; the trainer renders
    the first three on the photos' own grid), poses are finite, names are unique, points3D is non-empty.
    Prints a summary and exits 0, or lists every problem, one line each, and exits 1."""
    from jsgstools.validate import validate_scene

    report = validate_scene(scene, decode=True, analyze=analyze, test_every=test_every)
    for w in report.warnings:
        click.echo(f"warning: {w}")
    if report.problems:
        for p in report.problems:
            click.echo(f"problem: {p.message}")
        click.echo(f"error: {scene}: {len(report.problems)} problem(s)", err=True)
        sys.exit(1)
    click.echo(report.format_summary(test_every))
    click.echo("ok")


@click.command(
    "manifest",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgstools manifest my_scene --out my_scene/manifest.json"),
)
@click.argument("scene", type=click.Path(path_type=Path))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(path_type=Path),
    help="Manifest file to write (image paths in it are relative to its folder).",
)
@click.option(
    "--test-every",
    type=click.IntRange(max=MAX_INT_SETTING),
    default=None,
    help="View i (sorted by image name) is a test view when i % N == 0; 0: every view trains, no test "
    "views [default: 8, or the value a compressed scene was made with].",
)
@click.option(
    "--analyze",
    is_flag=True,
    help="Also record what each JPEG's pixels say about its compression history (double compression: "
    "inspect-dqt --analyze), for method_options.tables effective.",
)
@click.option("--force", is_flag=True, help="Replace an existing manifest (never another file).")
@user_errors
def manifest_cmd(scene: Path, out: Path, test_every: int | None, analyze: bool, force: bool) -> None:
    """Write the training manifest of SCENE (one made by compress, or your own JPEG/PNG collection with its
    COLMAP cameras) to OUT, validated against jsgs/schemas/manifest.schema.json.

    Per view: image path, split, camera scaled to the file (distortion recorded, not removed), world-to-camera
    R and t (x_cam = R x_world + t, OpenCV axes), the JPEG state read from the header (null for lossless) and
    the reference/<stem>.png path when it exists; points3D and provenance per scene."""
    from jsgstools.manifest_writer import manifest

    command = invocation(click.get_current_context(), "jsgstools")
    with OutputLock(out.parent, f"jsgstools manifest (into {out})"):
        doc = manifest(
            scene, out, test_every=test_every, force=force, command=command,
            say=lambda s: click.echo(f"warning: {s}"), analyze=analyze,
        )  # fmt: skip
    views = doc["views"]
    n_jpeg = sum(v["jpeg"] is not None for v in views)
    n_train = sum(v["split"] == "train" for v in views)
    n_dist = sum(v["camera"]["distortion"] is not None for v in views)
    s = doc["scene"]
    click.echo(
        f"manifest: {s['name']}: {len(views)} views ({n_train} train, {len(views) - n_train} test; "
        f"{n_jpeg} JPEG, {len(views) - n_jpeg} lossless), {doc['points']['count']} points3D, "
        f"schedule {s['schedule'] or 'none (own collection)'}, test every {s['test_every']}"
    )
    if n_dist:
        click.echo(
            f"  {n_dist} view(s) have distorted cameras (recorded; the trainer renders SIMPLE_RADIAL, RADIAL "
            "and OPENCV on the photos' own grid; compress undistorts clean scenes)"
        )
    refs = sum(v["reference"] is not None for v in views)
    if refs:
        n = len(views)
        click.echo(f"  {refs} of {n} views have a separate lossless reference (evaluation compares with it)")
    else:
        click.echo("  no separate lossless references: evaluation compares with the images themselves")
    double = [v for v in views if v["jpeg"] and (v["jpeg"].get("analysis") or {}).get("double_compressed")]
    if analyze:
        click.echo(f"  {len(double)} JPEG view(s) compressed twice (the earlier, coarser tables recorded)")
        for v in double[:10]:
            q = v["jpeg"]["analysis"]["primary_quality"]
            hq = v["jpeg"]["quality"]
            click.echo(f"warning: {v['name']}: compressed twice (earlier quality about {q}, header {hq})")
    click.echo(f"wrote {out}")


@click.command(
    "downscale",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgstools downscale cup --out cup_half"),
)
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output folder DIR.")
@click.option(
    "--factor", type=click.Choice(["2", "3", "4", "8"]), default="2", show_default=True,
    help="Divide width and height by this.",
)  # fmt: skip
@click.option(
    "--force",
    is_flag=True,
    help=(
        "Replace the outputs of an earlier downscale in DIR (its .jsgstools.json) once the new ones are "
        "complete."
    ),
)
@user_errors
def downscale_cmd(scene: Path, out: Path, factor: str, force: bool) -> None:
    """Copy the COLMAP scene SCENE into DIR at 1/FACTOR of its size, for `jsgs train --preset preview`: each
    view cropped to a multiple of FACTOR and block-averaged (Pillow's reduce) into DIR/images/<stem>.png, the
    model in DIR/sparse/0/ with its cameras rescaled as COLMAP does and its keypoints divided by FACTOR, and
    DIR/downscale.json recording how. SCENE is never written to; a DIR not made by downscale is refused."""
    from jsgstools.downscale import downscale

    command = invocation(click.get_current_context(), "jsgstools")
    with OutputLock(out, f"jsgstools downscale (into {out})"):
        record = downscale(scene, out, factor=int(factor), force=force, command=command)
    (w0, h0), (w, h) = record["views"][0]["source_size"], record["views"][0]["size"]
    click.echo(f"downscale: {len(record['views'])} views, {w0}x{h0} -> {w}x{h} (factor {factor})")
    click.echo(f"wrote {out}/images/, {out}/sparse/0/, {out}/downscale.json")
    click.echo(f"next: jsgstools manifest {out} --out {out}/manifest.json")


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    for cmd in (synth_cmd, compress_cmd, validate_cmd, manifest_cmd, downscale_cmd):
        group.add_command(cmd)
