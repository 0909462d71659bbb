"""PLY export in the original 3DGS layout: header, column order (f_rest channel-major), round trip."""

from __future__ import annotations

import contextlib
import io
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from jsgs.base.errors import JsgsError
from jsgs.base.ply import load_ply, ply_header, property_names, read_ply_vertices, save_ply

# The header the original 3DGS (GaussianModel.save_ply via plyfile) writes for SH degree 3, spelled out.
EXPECTED_HEADER_DEG3 = (
    "ply\n"
    "format binary_little_endian 1.0\n"
    "element vertex 7\n"
    "property float x\nproperty float y\nproperty float z\n"
    "property float nx\nproperty float ny\nproperty float nz\n"
    "property float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n"
    + "".join(f"property float f_rest_{i}\n" for i in range(45))
    + "property float opacity\n"
    "property float scale_0\nproperty float scale_1\nproperty float scale_2\n"
    "property float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\n"
    "end_header\n"
)


def random_splats(n: int, k_rest: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "means": rng.normal(size=(n, 3)).astype(np.float32),
        "scales_log": rng.normal(-3, 1, size=(n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "opacities_logit": rng.normal(size=n).astype(np.float32),
        "sh0": rng.normal(size=(n, 1, 3)).astype(np.float32),
        "shN": rng.normal(size=(n, k_rest, 3)).astype(np.float32),
    }


def test_header_is_the_3dgs_layout(tmp_path: Path) -> None:
    s = random_splats(7, 15)
    path = tmp_path / "point_cloud.ply"
    save_ply(path, **s)
    data = path.read_bytes()
    header = EXPECTED_HEADER_DEG3.encode()
    assert data[: len(header)] == header
    assert ply_header(7, 15) == header
    assert len(data) == len(header) + 7 * 62 * 4  # 62 float32 properties per Gaussian
    assert len(property_names(15)) == 62
    assert [p.name for p in tmp_path.iterdir()] == ["point_cloud.ply"]  # no temp file left behind


def test_columns_and_channel_major_f_rest(tmp_path: Path) -> None:
    """Decode the body independently of load_ply and check each column's meaning."""
    n, k = 4, 15
    s = random_splats(n, k, seed=1)
    coeff, chan = np.meshgrid(np.arange(k), np.arange(3), indexing="ij")
    s["shN"] = (100.0 * chan + coeff + np.arange(n)[:, None, None]).astype(np.float32)  # [n, k, 3]
    path = tmp_path / "a.ply"
    save_ply(path, **s)
    data = path.read_bytes()
    body = np.frombuffer(data[len(ply_header(n, k)) :], dtype="<f4").reshape(n, 62)
    np.testing.assert_array_equal(body[:, 0:3], s["means"])
    np.testing.assert_array_equal(body[:, 3:6], 0.0)
    np.testing.assert_array_equal(body[:, 6:9], s["sh0"][:, 0])
    rest = body[:, 9:54]
    for c in range(3):
        for j in range(k):
            # the original: f_rest_{c*(K-1)+j} is coefficient j+1 of channel c
            np.testing.assert_array_equal(rest[:, c * k + j], 100.0 * c + j + np.arange(n))
    np.testing.assert_array_equal(body[:, 54], s["opacities_logit"])
    np.testing.assert_array_equal(body[:, 55:58], s["scales_log"])
    np.testing.assert_array_equal(body[:, 58:62], s["quats"])


def test_round_trip_numpy_and_torch(tmp_path: Path) -> None:
    s = random_splats(50, 15, seed=2)
    save_ply(tmp_path / "np.ply", **s)
    t = {k: torch.from_numpy(v).double().requires_grad_() for k, v in s.items()}  # any float dtype, grads ok
    t["sh0"] = t["sh0"][:, 0]  # the [N, 3] form is accepted too
    t["opacities_logit"] = t["opacities_logit"][:, None]  # and [N, 1]
    save_ply(tmp_path / "torch.ply", **t)
    assert (tmp_path / "np.ply").read_bytes() == (tmp_path / "torch.ply").read_bytes()
    back = load_ply(tmp_path / "np.ply")
    for key, value in s.items():
        assert back[key].dtype == np.float32
        np.testing.assert_array_equal(back[key], value, err_msg=key)
    np.testing.assert_array_equal(back["normals"], 0.0)


@pytest.mark.parametrize("shn", ["none", "empty"])
def test_degree_zero(tmp_path: Path, shn: str) -> None:
    s = random_splats(3, 0, seed=3)
    if shn == "none":
        s["shN"] = None  # type: ignore[assignment]
    save_ply(tmp_path / "d0.ply", **s)
    assert b"f_rest" not in (tmp_path / "d0.ply").read_bytes()[:1000]
    back = load_ply(tmp_path / "d0.ply")
    assert back["shN"].shape == (3, 0, 3)
    np.testing.assert_array_equal(back["sh0"], s["sh0"])


def test_matches_gsplat_reference_writer(tmp_path: Path) -> None:
    """gsplat 1.5.3's (deprecated) ``utils.save_ply`` writes the original 3DGS layout too: same bytes."""
    gutils = pytest.importorskip("gsplat.utils")
    s = random_splats(5, 15, seed=4)
    save_ply(tmp_path / "ours.ply", **s)
    splats = torch.nn.ParameterDict({k: torch.nn.Parameter(torch.from_numpy(v)) for k, v in s.items()})
    splats["opacities"] = splats.pop("opacities_logit")
    splats["scales"] = splats.pop("scales_log")
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore", DeprecationWarning)
        gutils.save_ply(splats, str(tmp_path / "gsplat.ply"))
    assert (tmp_path / "ours.ply").read_bytes() == (tmp_path / "gsplat.ply").read_bytes()


def test_reads_gsplat_exporter_without_normals(tmp_path: Path) -> None:
    """gsplat's newer exporter drops nx ny nz; load_ply still reads it."""
    exporter = pytest.importorskip("gsplat.exporter")
    s = random_splats(6, 15, seed=5)
    t = {k: torch.from_numpy(v) for k, v in s.items()}
    data = exporter.splat2ply_bytes(
        t["means"], t["scales_log"], t["quats"], t["opacities_logit"], t["sh0"][:, 0],
        t["shN"].transpose(1, 2).reshape(6, -1),
    )  # fmt: skip
    (tmp_path / "g.ply").write_bytes(data)
    back = load_ply(tmp_path / "g.ply")
    for key, value in s.items():
        np.testing.assert_array_equal(back[key], value, err_msg=key)


def test_bad_values_and_shapes_write_nothing(tmp_path: Path) -> None:
    path = tmp_path / "keep.ply"
    s = random_splats(4, 15)
    save_ply(path, **s)
    before = path.read_bytes()
    bad = dict(s, means=s["means"].copy())
    bad["means"][2, 1] = np.nan
    with pytest.raises(ValueError, match="1 of 4 Gaussians"):
        save_ply(path, **bad)
    with pytest.raises(ValueError, match="quats"):
        save_ply(path, **dict(s, quats=s["quats"][:, :3]))
    with pytest.raises(ValueError, match="shN"):
        save_ply(path, **dict(s, shN=s["shN"][:, :, :2]))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.ply"]


def test_reader_errors(tmp_path: Path) -> None:
    s = random_splats(4, 15)
    save_ply(tmp_path / "ok.ply", **s)
    data = (tmp_path / "ok.ply").read_bytes()
    (tmp_path / "trunc.ply").write_bytes(data[:-4])
    with pytest.raises(JsgsError, match="truncated"):
        read_ply_vertices(tmp_path / "trunc.ply")
    (tmp_path / "ascii.ply").write_bytes(data.replace(b"binary_little_endian", b"ascii", 1))
    with pytest.raises(JsgsError, match="binary_little_endian"):
        read_ply_vertices(tmp_path / "ascii.ply")
    (tmp_path / "junk.ply").write_bytes(b"hello")
    with pytest.raises(JsgsError, match="not a PLY"):
        load_ply(tmp_path / "junk.ply")
    (tmp_path / "mesh.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" + np.zeros(3, "<f4").tobytes()
    )
    with pytest.raises(JsgsError, match="not a 3DGS PLY"):
        load_ply(tmp_path / "mesh.ply")
