"""``jsgs export RUN``: a trained run's Gaussians in the scene's own (COLMAP) frame or the training frame, in
the formats of gsplat's exporter (``gsplat.exporter.export_splats``: ``ply`` — the 3DGS layout every viewer
reads —, ``splat``, ``ply-compressed``), with a JSON record beside the file.

The trainer works in a normalised world (gsplat's ``Parser(normalize=True)``): ``y = s R x + t`` maps a
COLMAP point x to it (``config.json`` ``derived.normalization``, a 4x4 similarity). Going back, per Gaussian:

- centre ``x = Rᵀ (y − t) / s``;
- rotation ``q_x = q(Rᵀ) ⊗ q_y`` (its axes turn with the world);
- log-scales ``− log s``; opacity unchanged;
- SH: colour depends on the viewing direction d, and ``SH_x(d) = SH_y(R d)``; each band l ≥ 1 is rotated by
  the (2l+1)² matrix that maps the band's basis at ``R d`` onto its basis at d, solved by least squares on
  sample directions with the renderer's own basis (:func:`jsgs.render.reference.sh.sh_basis`), so the
  convention cannot drift from the renderer's; band 0 is unchanged.
"""

from __future__ import annotations

import datetime
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from jsgs.base.errors import JsgsError
from jsgs.base.rotations import matrix_to_quat

FORMATS = ("ply", "splat", "ply-compressed")
FRAMES = ("colmap", "training")
RECORD_FORMAT = "jsgs-export"
RECORD_VERSION = 1


def split_similarity(T: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """4x4 similarity ``y = s R x + t`` -> (s, R, t). JsgsError when it is not one (a reflection, shear)."""
    T = np.asarray(T, dtype=np.float64)
    A = T[:3, :3]
    det = float(np.linalg.det(A))
    if not (np.isfinite(T).all() and det > 0):
        raise JsgsError(f"the run's normalisation is not a rotation and scale (det {det:g})")
    s = det ** (1.0 / 3.0)
    R = A / s
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise JsgsError("the run's normalisation is not a similarity transform")
    return s, R, T[:3, 3].copy()


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (w, x, y, z), broadcast over leading axes."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)  # fmt: skip


def _sphere(n: int) -> np.ndarray:
    """n roughly uniform unit directions (a Fibonacci sphere), float64 [n, 3]."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sh_band_rotations(R: np.ndarray, degree: int) -> list[np.ndarray]:
    """For bands l = 1..degree, M_l [(2l+1), (2l+1)] with ``c_x = M_l c_y``: the coefficients whose function
    at d equals the original's at ``R d``."""
    from jsgs.render.reference.sh import sh_basis

    d = torch.from_numpy(_sphere(96))
    rd = torch.from_numpy(_sphere(96) @ np.asarray(R, np.float64).T)
    A = sh_basis(degree, d).numpy()
    B = sh_basis(degree, rd).numpy()
    out = []
    for band in range(1, degree + 1):
        sl = slice(band * band, (band + 1) * (band + 1))
        M, *_ = np.linalg.lstsq(A[:, sl], B[:, sl], rcond=None)
        out.append(M)
    return out


def to_colmap_frame(p: dict[str, np.ndarray], normalization: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of :func:`jsgs.base.ply.load_ply` (training frame) -> the same Gaussians in COLMAP's
    frame."""
    s, R, t = split_similarity(normalization)
    q = p["quats"].astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True).clip(min=1e-12)
    shN = p["shN"].astype(np.float64)
    k = shN.shape[1] + 1
    degree = int(round(math.sqrt(k))) - 1
    if (degree + 1) ** 2 != k:
        raise JsgsError(f"{k} SH coefficients per colour is not a full degree")
    new_shN = shN.copy()
    for band, M in enumerate(sh_band_rotations(R, degree), start=1):
        sl = slice(band * band - 1, (band + 1) * (band + 1) - 1)  # shN lacks the band-0 coefficient
        new_shN[:, sl, :] = np.einsum("ij,njc->nic", M, shN[:, sl, :])
    return {
        **p,
        "means": ((p["means"].astype(np.float64) - t) @ R / s).astype(np.float32),
        "quats": quat_multiply(matrix_to_quat(R.T), q).astype(np.float32),
        "scales_log": (p["scales_log"].astype(np.float64) - math.log(s)).astype(np.float32),
        "shN": new_shN.astype(np.float32),
    }


def written_count(data: bytes, fmt: str) -> int:
    """The Gaussians in an exported file's bytes: the PLY header's vertex count, or 32 bytes per splat."""
    if fmt == "splat":
        return len(data) // 32
    head = data[: data.find(b"end_header")].decode("ascii", "replace")
    for line in head.splitlines():
        parts = line.split()
        if parts[:2] == ["element", "vertex"] and len(parts) == 3:
            return int(parts[2])
    raise JsgsError(f"gsplat's {fmt} exporter wrote no vertex count")  # not expected: a library change


def export_run(run: str | Path, out: str | Path, fmt: str = "ply", frame: str = "colmap",
               force: bool = False, run_owned: bool = False) -> dict[str, Any]:  # fmt: skip
    """Write ``out`` (and ``out`` + ``.json``, its record: ``jsgs/schemas/export.schema.json``) from
    ``RUN/point_cloud.ply``; returns the record. The run's own files are never replaced (``run_owned``: the
    trainer's own export, which is one of them). A model without Gaussians, with a non-finite value or a zero
    rotation is refused (:func:`jsgs.base.run_files.check_gaussians`); ``gaussians`` in the record is what the
    file holds (``ply-compressed`` leaves out the nearly transparent ones: ``dropped``)."""
    import os

    import jsgs
    from jsgs.base.io import atomic_path, write_json_atomic
    from jsgs.base.ply import load_ply
    from jsgs.base.run_files import check_gaussians, refuse_run_files
    from jsgs.base.schema import validate
    from jsgs.train.config import read_run_config

    run, out = Path(run), Path(out)
    if fmt not in FORMATS:
        raise JsgsError(f"--format {fmt!r}: choose one of {', '.join(FORMATS)}")
    if frame not in FRAMES:
        raise JsgsError(f"--frame {frame!r}: choose one of {', '.join(FRAMES)}")
    ply = run / "point_cloud.ply"
    recorded = read_run_config(run)  # refuses a folder without a run's config.json
    if not ply.is_file():
        raise JsgsError(
            f"{run}: no point_cloud.ply (the run is not finished: jsgs train --resume continues it)"
        )
    record_path = out.with_name(out.name + ".json")
    if not run_owned:
        refuse_run_files(run, (out, record_path), "export writes only new files (choose another --out)")
    for p in (out, record_path):
        if os.path.lexists(p) and not force:
            raise JsgsError(f"{p}: exists (use --force to replace it)")
        if p.is_dir():
            raise JsgsError(f"{p}: is a folder; give a file name")
    normalization = np.asarray(recorded.derived["normalization"], dtype=np.float64)
    arrays = load_ply(ply)
    n = check_gaussians(arrays, ply)
    if frame == "colmap":
        arrays = to_colmap_frame(arrays, normalization)
        check_gaussians(arrays, f"{ply} in the COLMAP frame")
    from gsplat.exporter import export_splats

    t = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in arrays.items()}
    data = export_splats(
        t["means"], t["scales_log"], t["quats"], t["opacities_logit"], t["sh0"], t["shN"],
        format=fmt.replace("-", "_"),  # type: ignore[arg-type]
    )  # fmt: skip
    written = written_count(data, fmt)
    if written == 0:
        raise JsgsError(f"{ply}: none of its {n} Gaussians is opaque enough for {fmt} (opacity > 1/255)")
    record = {
        "format": RECORD_FORMAT,
        "format_version": RECORD_VERSION,
        "jsgs_version": jsgs.__version__,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "run": str(run),
        "file": out.name,
        "settings": {"format": fmt, "frame": frame},
        "gaussians": written,
        "dropped": n - written,
        "bytes": len(data),
        "normalization": normalization.tolist(),
        "note": "colmap: the training frame's normalisation undone (centres, rotations, scales, SH); "
        "training: as trained",
    }
    validate(record, "export", str(record_path))
    with atomic_path(out) as tmp:  # the file goes into place only once its record is written
        tmp.write_bytes(data)
        write_json_atomic(record_path, record)
    return record
