"""``jsgstools sfm PHOTOS --out SCENE``: a thin wrapper over :func:`jsgstools.sfm.sfm`."""

from __future__ import annotations

from pathlib import Path

import click

from jsgs.base.commands import CONTEXT, EXAMPLE, invocation, user_errors

#: the ranges pycolmap takes (its options are C++ ints)
_SIDE, _FEATURES = click.IntRange(16, 65_535), click.IntRange(1, 10_000_000)
_THREADS, _SEED = click.IntRange(-1, 4096), click.IntRange(0, 2**31 - 1)


@click.command(
    "sfm",
    context_settings=CONTEXT,
    epilog=EXAMPLE.format("jsgstools sfm ~/photos/cup --out cup_scene"),
)
@click.argument("photos", type=click.Path(path_type=Path, file_okay=False))
@click.option("--out", "out", required=True, type=click.Path(path_type=Path, file_okay=False),
              help="Scene folder to write (images/, sparse/0/, database.db, sfm.json).")  # fmt: skip
@click.option("--matcher", type=click.Choice(["exhaustive", "sequential"]), default="exhaustive",
              show_default=True,
              help="exhaustive: every pair; sequential: neighbours by name (video).")  # fmt: skip
@click.option("--camera-model", "camera_model", default="SIMPLE_PINHOLE", show_default=True,
              type=click.Choice(["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]),
              help="COLMAP camera model (the trainer renders each on the photos' own grid).")  # fmt: skip
@click.option("--per-photo-camera", "per_photo", is_flag=True,
              help="One camera per photo [default: one shared camera for photos of one size].")  # fmt: skip
@click.option("--max-image-size", "max_image_size", type=_SIDE, default=1600, show_default=True,
              help="Longest side the features are extracted at (the photos are never changed).")  # fmt: skip
@click.option("--max-features", "max_features", type=_FEATURES, default=1024,
              show_default=True,
              help="SIFT features per photo (more: slower matching, more robust).")  # fmt: skip
@click.option("--threads", type=_THREADS, default=-1, help="CPU threads [default: all cores].")
@click.option("--link", is_flag=True, help="Hard-link the photos into SCENE/images instead of copying them.")
@click.option("--seed", type=_SEED, default=0, show_default=True, help="Seed of the mapper.")
@click.option(
    "--force",
    is_flag=True,
    help="Replace an earlier sfm output in SCENE (its .jsgstools.json) once the new one is complete.",
)
@user_errors
def sfm_command(
    photos: Path, out: Path, matcher: str, camera_model: str, per_photo: bool, max_image_size: int,
    max_features: int, threads: int, link: bool, seed: int, force: bool,
) -> None:  # fmt: skip
    """Build a COLMAP model for the photos in PHOTOS with pycolmap (SIFT features, matching, incremental
    mapping) into SCENE, copying the photos byte for byte into SCENE/images (a JPEG keeps its tables and its
    8x8 grid). Keeps the largest model as SCENE/sparse/0 and names the photos it could not register."""
    from jsgstools.sfm import sfm

    rec = sfm(
        photos, out, matcher=matcher, camera_model=camera_model, single_camera=False if per_photo else None,
        max_image_size=max_image_size, max_features=max_features, threads=threads, link=link, force=force,
        seed=seed, say=lambda s: click.echo(s, err=True),
        command=invocation(click.get_current_context(), "jsgstools"),
    )  # fmt: skip
    total = sum(rec["seconds"].values())
    click.echo(f"sfm: {rec['registered']} of {rec['photos']} photos registered, {rec['points3D']} points3D, "
               f"{total:.1f} s; wrote {out}/images/, {out}/sparse/0/, {out}/sfm.json")  # fmt: skip
    if rec["unregistered"]:
        names = ", ".join(rec["unregistered"][:10]) + (" ..." if len(rec["unregistered"]) > 10 else "")
        click.echo(f"warning: not registered ({len(rec['unregistered'])}): {names}")


def register(group: click.Group) -> None:
    """Add this module's commands to ``group``."""
    group.add_command(sfm_command)
