"""Gaussian-splat export in the standard 3DGS PLY layout (Kerbl et al. 2023, ``GaussianModel.save_ply``),
which common viewers (SIBR, SuperSplat, antimatter15, gsplat's viewer, ...) open.

One ``vertex`` element, binary little-endian, every property ``float`` (float32), in this order::

    x y z                       means (world units)
    nx ny nz                    normals, always 0 (unused; kept because the original layout has them)
    f_dc_0 f_dc_1 f_dc_2        SH degree-0 coefficient of R, G, B
    f_rest_0 .. f_rest_{3(K-1)-1}
                                higher SH coefficients, channel-major: all K-1 coefficients of R, then G,
                                then B (the original's ``features_rest.transpose(1, 2).flatten(1)``)
    opacity                     logit (pre-sigmoid)
    scale_0 scale_1 scale_2     log scales (pre-exp)
    rot_0 rot_1 rot_2 rot_3     quaternion w, x, y, z (unnormalised, as optimised)

K = (degree + 1)^2 is the number of SH coefficients per channel (16 for degree 3: 45 ``f_rest``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from jsgs.base.errors import JsgsError
from jsgs.base.io import atomic_path
from jsgs.base.run_files import check_gaussians

ArrayLike = Any  # numpy array or torch tensor (any device, any float dtype)

# PLY scalar type names (both spellings of the spec) -> numpy little-endian dtype
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4",
    "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4",
    "double": "<f8", "float64": "<f8",
}  # fmt: skip


def _np(x: ArrayLike) -> np.ndarray:
    """A float32 numpy copy of a numpy array or torch tensor (detached, moved to CPU)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float32)


def property_names(num_sh_rest: int) -> list[str]:
    """The vertex property names, in file order, for ``num_sh_rest`` = K - 1 higher SH coefficients per
    channel (15 for degree 3)."""
    return (
        ["x", "y", "z", "nx", "ny", "nz"]
        + [f"f_dc_{i}" for i in range(3)]
        + [f"f_rest_{i}" for i in range(3 * num_sh_rest)]
        + ["opacity"]
        + [f"scale_{i}" for i in range(3)]
        + [f"rot_{i}" for i in range(4)]
    )


def ply_header(num_points: int, num_sh_rest: int) -> bytes:
    """The ASCII header (through ``end_header\\n``) for ``num_points`` Gaussians."""
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {num_points}"]
    lines += [f"property float {name}" for name in property_names(num_sh_rest)]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def splats_to_array(
    means: ArrayLike,
    scales_log: ArrayLike,
    quats: ArrayLike,
    opacities_logit: ArrayLike,
    sh0: ArrayLike,
    shN: ArrayLike | None,
) -> np.ndarray:
    """The N x P float32 table of the file's rows (see the module docstring for the columns).

    means [N,3]; scales_log [N,3]; quats [N,4] wxyz; opacities_logit [N] or [N,1]; sh0 [N,1,3] or [N,3];
    shN [N,K-1,3] (coefficient-major, as gsplat and the 3DGS model store it) or None / [N,0,3] for degree 0.
    Raises ValueError on a shape mismatch or a non-finite value (a NaN in a PLY breaks viewers silently).
    """
    m, s, q, o, d = _np(means), _np(scales_log), _np(quats), _np(opacities_logit), _np(sh0)
    n = m.shape[0] if m.ndim == 2 else -1
    if m.shape != (n, 3):
        raise ValueError(f"save_ply: means must be N x 3, got {m.shape}")
    if o.shape == (n, 1):
        o = o[:, 0]
    if d.shape == (n, 1, 3):
        d = d[:, 0, :]
    r = np.zeros((n, 0, 3), np.float32) if shN is None else _np(shN)
    for name, arr, shape in (
        ("scales_log", s, (n, 3)),
        ("quats", q, (n, 4)),
        ("opacities_logit", o, (n,)),
        ("sh0", d, (n, 3)),
    ):
        if arr.shape != shape:
            raise ValueError(f"save_ply: {name} must have shape {shape}, got {arr.shape}")
    if r.ndim != 3 or r.shape[0] != n or r.shape[2] != 3:
        raise ValueError(f"save_ply: shN must be N x (K-1) x 3, got {r.shape}")
    # channel-major, as the original: [N, K-1, 3] -> [N, 3, K-1] -> [N, 3(K-1)]
    rest = r.transpose(0, 2, 1).reshape(n, -1)
    table = np.concatenate(
        [m, np.zeros((n, 3), np.float32), d, rest, o[:, None], s, q], axis=1, dtype=np.float32
    )
    if not np.isfinite(table).all():
        bad = int((~np.isfinite(table).all(axis=1)).sum())
        raise ValueError(f"save_ply: {bad} of {n} Gaussians have a NaN or Inf parameter")
    return table


def save_ply(
    path: str | os.PathLike[str],
    means: ArrayLike,
    scales_log: ArrayLike,
    quats: ArrayLike,
    opacities_logit: ArrayLike,
    sh0: ArrayLike,
    shN: ArrayLike | None,
) -> None:
    """Write Gaussians to ``path`` in the 3DGS PLY layout, atomically (temp file + rename).

    Arguments as in :func:`splats_to_array` (the optimiser's raw parameters: log scales, logit opacities,
    unnormalised wxyz quaternions; numpy arrays or torch tensors on any device).
    """
    table = splats_to_array(means, scales_log, quats, opacities_logit, sh0, shN)
    header = ply_header(table.shape[0], (table.shape[1] - 17) // 3)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        f.write(table.astype("<f4", copy=False).tobytes())


def read_ply_vertices(path: str | os.PathLike[str]) -> np.ndarray:
    """The ``vertex`` element of a binary little-endian PLY as a numpy structured array (one field per
    scalar property, in file order). Raises JsgsError for anything else (ASCII or big-endian files, list
    properties in or before ``vertex``, a truncated body). Elements declared before ``vertex`` are skipped.
    """
    from jsgs.base.io import read_regular_bytes

    path = Path(path)
    data = read_regular_bytes(path)
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise JsgsError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    body = end + len(b"end_header\n")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1:2]
        elif words[0] == "element" and len(words) == 3 and re.fullmatch(r"\d+", words[2]):
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            elif len(words) == 5 and words[1] == "list":
                elements[-1][2].append((words[4], "list"))  # variable size: fine only after 'vertex'
            else:
                raise JsgsError(f"{path}: unsupported PLY property line '{line}'")
        else:
            raise JsgsError(f"{path}: malformed PLY header line '{line}'")
    if fmt != ["binary_little_endian"]:
        raise JsgsError(f"{path}: only binary_little_endian PLY is supported (format {fmt})")
    offset = body
    for name, count, props in elements:
        if any(t == "list" for _, t in props):
            raise JsgsError(f"{path}: list property in element '{name}' (before or in 'vertex'): unsupported")
        try:
            dtype = np.dtype(props)
        except (ValueError, TypeError) as e:  # a property named twice, or a name numpy cannot take
            raise JsgsError(f"{path}: element '{name}': unusable properties ({e})") from None
        if name == "vertex":
            size = count * dtype.itemsize
            if len(data) - offset < size:
                raise JsgsError(f"{path}: truncated: {count} vertices need {size} bytes after the header")
            return np.frombuffer(data, dtype=dtype, count=count, offset=offset).copy()
        offset += count * dtype.itemsize
    raise JsgsError(f"{path}: no 'vertex' element")


def load_ply(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read a 3DGS-layout PLY (as written by :func:`save_ply` or the original 3DGS) back into the arrays
    :func:`save_ply` takes: ``means`` [N,3], ``scales_log`` [N,3], ``quats`` [N,4] wxyz,
    ``opacities_logit`` [N], ``sh0`` [N,1,3], ``shN`` [N,K-1,3] (coefficient-major again), ``normals`` [N,3]
    (zeros if absent); all float32 (other stored types are converted). Raises JsgsError when a required
    property is missing, and for a model that cannot be rendered
    (:func:`jsgs.base.run_files.check_gaussians`: no Gaussians, a value that is not finite, a centre beyond
    ±:data:`jsgs.base.limits.MAX_COORDINATE`, a zero quaternion)."""
    v = read_ply_vertices(path)
    names = set(v.dtype.names or ())
    n_rest = sum(1 for k in names if re.fullmatch(r"f_rest_\d+", k))
    # normals are optional: gsplat's newer exporter and some tools leave them out
    need = [k for k in property_names(n_rest // 3) if k not in ("nx", "ny", "nz")]
    missing = [k for k in need if k not in names]
    if missing or n_rest % 3:
        raise JsgsError(f"{path}: not a 3DGS PLY (missing {missing[:5]}, {n_rest} f_rest properties)")

    def cols(keys: list[str]) -> np.ndarray:
        if not keys:
            return np.zeros((len(v), 0), np.float32)
        return np.stack([v[k].astype(np.float32) for k in keys], axis=1)

    k1 = n_rest // 3
    rest = cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(len(v), 3, k1).transpose(0, 2, 1)
    arrays = {
        "means": cols(["x", "y", "z"]),
        "normals": cols(["nx", "ny", "nz"]) if "nx" in names else np.zeros((len(v), 3), np.float32),
        "sh0": cols([f"f_dc_{i}" for i in range(3)])[:, None, :],
        "shN": np.ascontiguousarray(rest, dtype=np.float32),
        "opacities_logit": v["opacity"].astype(np.float32),
        "scales_log": cols([f"scale_{i}" for i in range(3)]),
        "quats": cols([f"rot_{i}" for i in range(4)]),
    }
    check_gaussians(arrays, path)
    return arrays
