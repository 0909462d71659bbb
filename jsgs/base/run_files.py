"""What a run folder holds, for the commands that read a finished run and write beside it (``jsgs export``,
``jsgs render``): the names a run owns, which those commands never replace, and the check that the run's
model can be used at all (Gaussians, all finite, with a rotation)."""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jsgs.base.errors import JsgsError
from jsgs.base.limits import MAX_COORDINATE

#: the trainer's own export of the model in the scene's COLMAP frame
COLMAP_PLY = "point_cloud_colmap.ply"
#: every entry of RUN that jsgs train, jsgs view or the lock write (files and folders); a path equal to one
#: of them, or inside one of the folders, belongs to the run
RUN_OWNED = (
    "config.json", "metrics.json", "point_cloud.ply", COLMAP_PLY, f"{COLMAP_PLY}.json", "renders",
    "checkpoints", "viewer_cameras.json", ".jsgs.lock",
)  # fmt: skip


@dataclass
class RunPaths:
    """The places of a run folder's own files (``root`` the folder)."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / "config.json"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def ply(self) -> Path:
        return self.root / "point_cloud.ply"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    def renders(self, step: int) -> Path:
        return self.root / "renders" / f"step_{step:06d}"



def _resolved(path: Path) -> Path:
    # the folder resolved (links in it followed), the last name kept: a link named like a run file is the
    # link's own path, which is what a rename would replace
    return Path(os.path.realpath(path.parent)) / path.name


def refuse_run_files(run: str | os.PathLike[str], outputs: Iterable[Path], hint: str) -> None:
    """JsgsError (one line) when any of ``outputs`` is RUN itself, one of the run's own entries
    (:data:`RUN_OWNED`) or lies inside one of them, or contains RUN. ``hint``: what to do instead."""
    root = Path(os.path.realpath(run))
    for out in outputs:
        p = _resolved(Path(out))
        if p == root or p in root.parents:
            raise JsgsError(f"{out}: is or contains the run folder {run}; {hint}")
        if root in p.parents:
            first = p.relative_to(root).parts[0]
            if first in RUN_OWNED:
                raise JsgsError(f"{out}: is the run's own {first}; {hint}")


def check_gaussians(arrays: Mapping[str, Any], source: str | os.PathLike[str]) -> int:
    """The number of Gaussians in ``arrays`` (``means`` [N, 3], ``quats`` [N, 4] and the other parameters,
    numpy arrays or torch tensors), or JsgsError (one line naming ``source``) when there are none, when any
    has a non-finite parameter (NaN, ±inf), a centre beyond ±:data:`jsgs.base.limits.MAX_COORDINATE` or a zero
    rotation quaternion: such a model renders black or exports rows that viewers drop, so it is refused
    rather than written."""
    arr = {k: np.asarray(v.detach().cpu() if hasattr(v, "detach") else v) for k, v in arrays.items()}
    n = int(arr["means"].shape[0])
    if n == 0:
        raise JsgsError(f"{source}: holds no Gaussians; there is nothing to draw or export")
    bad = np.zeros(n, dtype=bool)
    names = []
    for k, v in arr.items():
        rows = ~np.isfinite(v.reshape(n, -1)).all(axis=1)
        if rows.any():
            names.append(k)
            bad |= rows
    if bad.any():
        raise JsgsError(
            f"{source}: {int(bad.sum())} of {n} Gaussians have non-finite values (in {', '.join(names)}); "
            "the model is damaged: train again, or resume from a checkpoint"
        )
    far = int((~(np.abs(arr["means"].reshape(n, 3)) <= MAX_COORDINATE).all(axis=1)).sum())
    if far:
        raise JsgsError(
            f"{source}: {far} of {n} Gaussians lie beyond ±{MAX_COORDINATE:g} (world units); the model is "
            "damaged: train again, or resume from a checkpoint"
        )
    zero = int((np.abs(arr["quats"].reshape(n, 4)).sum(axis=1) == 0).sum())
    if zero:
        raise JsgsError(
            f"{source}: {zero} of {n} Gaussians have a zero rotation quaternion; the model is damaged: train "
            "again, or resume from a checkpoint"
        )
    return n
