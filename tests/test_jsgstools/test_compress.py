"""``jsgstools compress``: schedule arithmetic, the split, seeded assignment, outputs, refusals, atomicity,
undistortion (synthetic: exact pinhole rendering; real: LLFF fern against OpenCV and pycolmap)."""

from __future__ import annotations

import json
import shutil
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import shared_scene
from PIL import Image

from jsgs.base.errors import JsgsError
from jsgstools import compress as C
from jsgstools.cli import main
from jsgstools.compress import QUALITIES, compress, largest_remainder, plan, schedule_weights


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


def _no_parts(root: Path) -> None:
    assert not [p for p in root.rglob("*") if ".part" in p.name]


# ----------------------------------------------------------------------------------------------------
# Counts


def test_counts_hand_computed() -> None:
    # uniform, 17 train views: quotas 17/9 = 1.89 each; floors 9, 8 left, all tied -> all but q=10 get one.
    assert largest_remainder(schedule_weights("uniform"), 17) == [1, 2, 2, 2, 2, 2, 2, 2, 2]
    # descending, 17: quotas 17*w/45 for w = 1..9 (q10..q90)
    # = .378 .756 1.133 1.511 1.889 2.267 2.644 3.022 3.4; floors sum to 13; the 4 largest fractions are
    # .889 (q50) .756 (q20) .644 (q70) .511 (q40).
    assert largest_remainder(schedule_weights("descending"), 17) == [0, 1, 1, 2, 2, 2, 3, 3, 3]
    # gaussian, 17: quotas .4697 1.127 2.105 3.063 3.4707 3.063 2.105 1.127 .4697; floors 15;
    # q50 (.4707) first, then q10 and q90 tie exactly (.4697) and the tie goes to the higher quality, q90.
    assert largest_remainder(schedule_weights("gaussian"), 17) == [0, 1, 2, 3, 4, 3, 2, 1, 1]
    # the tie rule alone
    assert largest_remainder([1] * 9, 1) == [0] * 8 + [1]
    assert largest_remainder([1, 1, 1], 2) == [0, 1, 1]
    assert largest_remainder([Fraction(1, 3), Fraction(2, 3)], 3) == [1, 2]
    assert largest_remainder(schedule_weights("uniform"), 0) == [0] * 9
    assert largest_remainder(schedule_weights("uniform"), 18) == [2] * 9
    assert largest_remainder(schedule_weights("descending"), 45) == list(range(1, 10))


@pytest.mark.parametrize("schedule", ["uniform", "gaussian", "descending"])
def test_counts_sum_and_stay_within_one_of_the_quota(schedule: str) -> None:
    w = schedule_weights(schedule)
    total = sum(w)
    for n in range(0, 400):
        counts = largest_remainder(w, n)
        assert sum(counts) == n
        for c, wk in zip(counts, w, strict=True):
            quota = n * wk / total
            assert quota - 1 < c < quota + 1


def test_gaussian_weights_are_the_papers() -> None:
    x = np.linspace(-2, 2, 9)
    assert np.allclose([float(v) for v in schedule_weights("gaussian")], np.exp(-(x**2) / 2))
    w = schedule_weights("gaussian")
    assert all(w[k] == w[8 - k] for k in range(9))  # exactly symmetric, so the q10/q90 ties are exact


def test_largest_remainder_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        largest_remainder([0, 0], 3)
    with pytest.raises(ValueError):
        largest_remainder([1, -1], 3)
    with pytest.raises(ValueError):
        largest_remainder([1], -1)


# ----------------------------------------------------------------------------------------------------
# Split and assignment


def test_split_is_every_nth_by_sorted_name() -> None:
    names = [f"img_{i:02d}.png" for i in range(20)][::-1]  # given unsorted
    p = plan(names, "uniform", seed=0, test_every=8)
    test = sorted(n for n, s in p.split.items() if s == "test")
    assert test == ["img_00.png", "img_08.png", "img_16.png"]
    assert all(p.quality[n] is None for n in test)
    train_q = sorted(q for n, q in p.quality.items() if p.split[n] == "train")
    assert train_q == sorted(q for q, c in p.counts.items() for _ in range(c))
    assert sum(p.counts.values()) == 17


def test_assignment_is_seeded() -> None:
    names = [f"v{i:03d}" for i in range(50)]
    a = plan(names, "gaussian", seed=3)
    b = plan(names, "gaussian", seed=3)
    c = plan(names, "gaussian", seed=4)
    assert a.quality == b.quality
    assert a.quality != c.quality
    assert a.counts == c.counts
    # the documented rule, spelled out
    train = [n for n in sorted(names) if a.split[n] == "train"]
    pool = np.array([q for q in sorted(a.counts) for _ in range(a.counts[q])])
    dealt = np.random.default_rng(3).permutation(pool)
    assert [a.quality[n] for n in train] == dealt.tolist()


def test_fixed_and_clean_plans() -> None:
    names = [f"v{i}" for i in range(10)]
    p = plan(names, "fixed", quality=30)
    assert {q for n, q in p.quality.items() if p.split[n] == "train"} == {30}
    assert p.counts == {30: 8}
    p = plan(names, "clean")
    assert all(q is None for q in p.quality.values())
    assert p.counts == {}


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"schedule": "linear"}, "--schedule 'linear'"),
        ({"schedule": "fixed"}, "needs --quality"),
        ({"schedule": "fixed", "quality": 0}, "--quality 0"),
        ({"schedule": "fixed", "quality": 101}, "--quality 101"),
        ({"schedule": "uniform", "quality": 50}, "applies to --schedule fixed only"),
        ({"schedule": "uniform", "test_every": 0}, "--test-every 0"),
    ],
)
def test_plan_rejects(kwargs: dict, message: str) -> None:
    with pytest.raises(JsgsError, match=message.replace("(", r"\(")):
        plan(["a", "b"], **kwargs)


# ----------------------------------------------------------------------------------------------------
# Outputs


def test_outputs_of_a_synthetic_scene(synth_scene: Path, compressed_scene: Path) -> None:
    out = compressed_scene
    rec = json.loads((out / "compress.json").read_text())
    man = json.loads((out / "manifest.json").read_text())
    views = rec["views"]
    assert len(views) == 12
    assert [v["source_name"] for v in views] == sorted(v["source_name"] for v in views)
    assert [v["split"] for v in views] == ["test" if i % 8 == 0 else "train" for i in range(12)]
    assert rec["settings"]["counts"] == {
        str(q): c for q, c in zip(QUALITIES, largest_remainder(schedule_weights("gaussian"), 10), strict=True)
    }
    for v, mv in zip(views, man["views"], strict=True):
        assert mv["name"] == v["name"] and mv["split"] == v["split"]
        ref = np.asarray(Image.open(out / v["reference"]))
        src = np.asarray(Image.open(synth_scene / "images" / v["source_name"]))
        assert np.array_equal(ref, src)  # pinhole scene: no resampling
        if v["split"] == "test":
            assert v["quality"] is None and v["image"].endswith(".png")
            assert (out / v["image"]).read_bytes() == (out / v["reference"]).read_bytes()
            assert mv["jpeg"] is None
        else:
            assert v["image"].endswith(".jpg")
            with Image.open(out / v["image"]) as im:
                assert im.format == "JPEG" and "progressive" not in im.info and im.size == (64, 48)
            assert mv["jpeg"]["quality"] == v["quality"] and mv["jpeg"]["quality_exact"]
            assert mv["jpeg"]["sampling"] == "4:2:0" and mv["jpeg"]["frame"] == "baseline"
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(v["name"] for v in views)
    assert {p.name for p in (out / "sparse" / "0").iterdir()} >= {"cameras.bin", "images.bin", "points3D.bin"}
    assert man["producer"]["settings"]["per_view_quality"] == {v["name"]: v["quality"] for v in views}
    assert man["scene"]["schedule"] == "gaussian" and man["scene"]["seed"] == 0
    _no_parts(out)


def test_output_model_matches(synth_scene: Path, compressed_scene: Path) -> None:
    import pycolmap

    src = pycolmap.Reconstruction(str(synth_scene / "sparse" / "0"))
    out = pycolmap.Reconstruction(str(compressed_scene / "sparse" / "0"))
    assert out.num_points3D() == src.num_points3D()
    for iid, im in src.images.items():
        o = out.images[iid]
        assert Path(o.name).stem == Path(im.name).stem
        assert np.allclose(o.cam_from_world().matrix(), im.cam_from_world().matrix())
    assert out.cameras[1].model_name == "PINHOLE"
    assert np.allclose(out.cameras[1].params, src.cameras[1].params)


def test_subsampling_and_fixed(synth_scene: Path, tmp_path: Path) -> None:
    res = compress(synth_scene, tmp_path / "o", "fixed", quality=35, subsampling="444", jobs=1)
    jp = [v["jpeg"] for v in res.manifest["views"] if v["jpeg"] is not None]
    assert len(jp) == 10
    assert {(j["quality"], j["sampling"]) for j in jp} == {(35, "4:4:4")}
    assert res.manifest["scene"]["quality"] == 35 and res.manifest["scene"]["subsampling"] == "4:4:4"


def test_clean_keeps_train_views_lossless(synth_scene: Path, tmp_path: Path) -> None:
    res = compress(synth_scene, tmp_path / "o", "clean", jobs=1)
    assert all(v["jpeg"] is None and v["image"].endswith(".png") for v in res.manifest["views"])
    assert all(v["quality"] is None for v in res.record["views"])
    assert not list((tmp_path / "o" / "images").glob("*.jpg"))


def test_deterministic_and_parallel_equal_serial(synth_scene: Path, tmp_path: Path) -> None:
    a = compress(synth_scene, tmp_path / "a", "descending", seed=7, jobs=1)
    b = compress(synth_scene, tmp_path / "b", "descending", seed=7, jobs=2)
    for v in a.record["views"]:
        for key in ("image", "reference"):
            assert (tmp_path / "a" / v[key]).read_bytes() == (tmp_path / "b" / v[key]).read_bytes()
    assert a.record["views"] == b.record["views"]
    assert a.manifest["views"] == b.manifest["views"] and a.manifest["points"] == b.manifest["points"]


def test_never_writes_into_scene(synth_scene: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(synth_scene, scene)
    before = _tree(scene)
    compress(scene, tmp_path / "out", "uniform", jobs=1)
    assert _tree(scene) == before
    with pytest.raises(JsgsError, match="inside the input scene"):
        compress(scene, scene / "out", "uniform", jobs=1)
    with pytest.raises(JsgsError, match="inside the input scene"):
        compress(scene, scene, "uniform", jobs=1, force=True)
    with pytest.raises(JsgsError, match="contains the input scene"):
        compress(scene, tmp_path, "uniform", jobs=1, force=True)
    assert _tree(scene) == before


def test_refuses_non_empty_out_unless_force(synth_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    (out / "images").mkdir(parents=True)
    (out / "images" / "stale.jpg").write_bytes(b"old")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(JsgsError, match="not empty.*--force"):
        compress(synth_scene, out, "uniform", jobs=1)
    # --force replaces only a folder compress made: this one has no marker, so nothing is touched
    with pytest.raises(JsgsError, match="not made by jsgstools"):
        compress(synth_scene, out, "uniform", jobs=1, force=True)
    assert (out / "images" / "stale.jpg").exists() and (out / "notes.txt").exists()
    shutil.rmtree(out / "images")
    (out / "notes.txt").unlink()
    compress(synth_scene, out, "uniform", jobs=1)
    (out / "images" / "stale.jpg").write_bytes(b"old")
    (out / "notes.txt").write_text("mine")
    compress(synth_scene, out, "gaussian", jobs=1, force=True)
    assert not (out / "images" / "stale.jpg").exists()  # what compress owns is replaced...
    assert (out / "notes.txt").read_text() == "mine"  # ...and nothing else is touched
    # another tool's folder, a COLMAP scene (synth's) or a photo folder: refused in one line
    with pytest.raises(JsgsError, match="made by jsgstools synth"):
        from jsgstools.synth import synth

        synth(tmp_path / "syn", views=2, size=(16, 12))
        compress(synth_scene, tmp_path / "syn", "uniform", jobs=1, force=True)
    assert len(list((tmp_path / "syn" / "images").iterdir())) == 2
    (tmp_path / "file").write_text("x")
    with pytest.raises(JsgsError, match="not a folder"):
        compress(synth_scene, tmp_path / "file", "uniform", jobs=1, force=True)


def test_interrupted_run_leaves_no_partial_files(
    synth_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = {"n": 0}
    real = C.jpeg_bytes

    def failing(arr: np.ndarray, quality: int, subsampling: int) -> bytes:
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt  # as if Ctrl-C arrived mid-run
        return real(arr, quality, subsampling)

    monkeypatch.setattr(C, "jpeg_bytes", failing)
    with pytest.raises(KeyboardInterrupt):
        compress(synth_scene, tmp_path / "out", "uniform", jobs=1)
    _no_parts(tmp_path / "out")
    assert not (tmp_path / "out" / "manifest.json").exists()  # the mark of a complete run
    for p in (tmp_path / "out").rglob("*.jpg"):
        with Image.open(p) as im:
            im.load()  # every file present is whole


def test_refuses_bad_scenes_and_options(synth_scene: Path, compressed_scene: Path, tmp_path: Path) -> None:
    with pytest.raises(JsgsError, match="no COLMAP model"):
        compress(tmp_path, tmp_path / "o", "uniform")
    with pytest.raises(JsgsError, match="lossless source images"):
        compress(compressed_scene, tmp_path / "o2", "uniform", jobs=1)
    with pytest.raises(JsgsError, match="--subsampling"):
        compress(synth_scene, tmp_path / "o3", "uniform", subsampling="411")
    with pytest.raises(JsgsError, match="--jobs"):
        compress(synth_scene, tmp_path / "o4", "uniform", jobs=0)
    with pytest.raises(JsgsError, match="needs --quality"):
        compress(synth_scene, tmp_path / "o5", "fixed")
    assert not any((tmp_path / n).exists() for n in ("o", "o2", "o3", "o4", "o5"))


def test_cli(synth_scene: Path, tmp_path: Path) -> None:
    r = CliRunner().invoke(
        main,
        [
            "compress",
            str(synth_scene),
            "--out",
            str(tmp_path / "o"),
            "--schedule",
            "descending",
            "--seed",
            "1",
            "--jobs",
            "1",
        ],
    )
    assert r.exit_code == 0, r.output
    assert "views: 12 = 10 train + 2 test" in r.output
    assert "quality  10  20  30  40  50  60  70  80  90" in r.output
    rec = json.loads((tmp_path / "o" / "compress.json").read_text())
    assert (
        rec["producer"]["command"].startswith("jsgstools compress")
        or "compress" in rec["producer"]["command"]
    )
    r = CliRunner().invoke(
        main, ["compress", str(synth_scene), "--out", str(tmp_path / "o"), "--schedule", "uniform"]
    )
    assert r.exit_code == 1 and "not empty" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(
        main, ["compress", str(synth_scene), "--out", str(tmp_path / "p"), "--schedule", "bad"]
    )
    assert r.exit_code == 2 and "Invalid value for '--schedule'" in r.output
    r = CliRunner().invoke(
        main,
        ["compress", str(synth_scene), "--out", str(tmp_path / "p"), "--schedule", "fixed", "--quality", "0"],
    )
    assert r.exit_code == 1 and "error: --quality 0" in r.output
    r = CliRunner().invoke(
        main,
        [
            "compress",
            str(synth_scene),
            "--out",
            str(tmp_path / "p"),
            "--schedule",
            "uniform",
            "--quality",
            "50",
        ],
    )
    assert r.exit_code == 1 and "applies to --schedule fixed only" in r.output
    r = CliRunner().invoke(
        main,
        [
            "compress",
            str(synth_scene),
            "--out",
            str(tmp_path / "p"),
            "--schedule",
            "fixed",
            "--quality",
            "abc",
        ],
    )
    assert r.exit_code == 2
    assert not (tmp_path / "p").exists()


# ----------------------------------------------------------------------------------------------------
# Downscale + undistortion


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    """Correlation of the grey levels of two RGB images."""
    ga, gb = a.astype(np.float64).mean(axis=2).ravel(), b.astype(np.float64).mean(axis=2).ravel()
    return float(np.corrcoef(ga, gb)[0, 1])


def test_undistortion_matches_an_exact_pinhole_rendering(tmp_path: Path) -> None:
    """Render through SIMPLE_RADIAL (k1 = 0.08) with the model's camera at 4x the image size; compress must
    detect the factor, scale, undistort, and give what an exact pinhole rendering at the output camera
    shows."""
    import pycolmap

    from jsgs.base.camera import Camera
    from jsgstools.synth import default_scene, render, synth

    synth(tmp_path / "scene", views=2, size=(160, 120), k1=0.08, camera_scale=4)
    res = compress(tmp_path / "scene", tmp_path / "out", "clean", jobs=1)
    cam = res.record["cameras"][0]
    assert cam["source"]["model"] == "SIMPLE_RADIAL" and cam["source"]["width"] == 640
    assert cam["output"]["model"] == "PINHOLE" and cam["output"]["width"] == 160
    assert cam["undistorted"] and cam["zoom"] > 1.0  # pincushion: zoom in to avoid black borders
    assert res.manifest["scene"]["downscale"] == 4.0 and res.manifest["scene"]["undistorted"]
    assert res.manifest["views"][0]["camera"]["distortion"] is None

    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    c = rec.cameras[1]
    boxes = default_scene(np.random.default_rng(0))
    for iid in (1, 2):
        im = rec.images[iid]
        pose = im.cam_from_world()
        ref = np.asarray(Image.open(tmp_path / "out" / "reference" / (Path(im.name).stem + ".png")))
        corr = []
        for dx in (0.0, 0.5):  # the right camera, and the half-pixel convention mistake
            fx, fy, cx, cy = c.params
            pin = Camera("PINHOLE", c.width, c.height, fx, fy, cx + dx, cy)
            corr.append(_corr(render(boxes, pin, pose.rotation.matrix(), pose.translation, 2), ref))
        raw = np.asarray(Image.open(tmp_path / "scene" / "images" / (Path(im.name).stem + ".png")))
        # Textures of 3-6 px periods: a half-pixel error or no undistortion costs a lot of correlation.
        assert corr[0] > 0.94, corr
        assert corr[0] > corr[1] + 0.03, corr
        assert (
            corr[0]
            > _corr(
                render(
                    boxes,
                    Camera("PINHOLE", c.width, c.height, *c.params),
                    pose.rotation.matrix(),
                    pose.translation,
                    1,
                ),
                raw,
            )
            - 0.5
        )  # sanity: renders are comparable
        assert corr[0] > _corr(raw, ref) + 0.1, (corr, _corr(raw, ref))


def test_keypoints_follow_scaling_and_undistortion(tmp_path: Path) -> None:
    """Add keypoints (projections of points3D through the distorted, 4x camera) and tracks to a synthetic
    model; after compress each keypoint must be its point's projection through the output pinhole camera."""
    import pycolmap

    from jsgstools.synth import synth

    scene = tmp_path / "scene"
    synth(scene, views=2, size=(80, 60), k1=0.05, camera_scale=4)
    rec = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    cam = rec.cameras[1]
    pids = sorted(rec.points3D)[::10]
    new = pycolmap.Reconstruction()
    new.add_camera_with_trivial_rig(cam)
    tracks: dict[int, list] = {p: [] for p in pids}
    for iid, im in rec.images.items():
        pose = im.cam_from_world()
        xyz = np.array([rec.points3D[p].xyz for p in pids])
        xc = xyz @ pose.rotation.matrix().T + pose.translation
        uv = cam.img_from_cam(xc)
        keep = [
            i
            for i in range(len(pids))
            if xc[i, 2] > 0 and 0 <= uv[i, 0] < cam.width and 0 <= uv[i, 1] < cam.height
        ]
        ni = pycolmap.Image(name=im.name, keypoints=uv[keep], camera_id=1, image_id=iid)
        new.add_image_with_trivial_frame(ni, pose)
        for k, i in enumerate(keep):
            tracks[pids[i]].append(pycolmap.TrackElement(iid, k))
    for p in pids:
        q = pycolmap.Point3D()
        q.xyz = rec.points3D[p].xyz
        q.color = rec.points3D[p].color
        q.track = pycolmap.Track(tracks[p])
        new.add_point3D_with_id(p, q)
    shutil.rmtree(scene / "sparse" / "0")
    (scene / "sparse" / "0").mkdir()
    new.write_binary(str(scene / "sparse" / "0"))

    compress(scene, tmp_path / "out", "clean", jobs=1)
    out = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    oc = out.cameras[1]
    assert oc.model_name == "PINHOLE" and oc.width == 80
    assert out.compute_num_observations() == new.compute_num_observations() > 0
    n = 0
    for im in out.images.values():
        pose = im.cam_from_world()
        for p2 in im.points2D:
            if not p2.has_point3D():
                continue
            xc = pose.rotation.matrix() @ out.points3D[p2.point3D_id].xyz + pose.translation
            assert np.allclose(oc.img_from_cam(xc[None])[0], p2.xy, atol=1e-6)
            n += 1
    assert n > 20
    assert out.compute_mean_reprojection_error() < 1e-5  # errors recomputed on the new pixel grid


def test_undistortion_of_llff_fern(tmp_path: Path) -> None:
    """The real case: SIMPLE_RADIAL cameras at 4032x3024, PNGs at 504x378."""
    import cv2
    import pycolmap

    from jsgstools.scene import ColmapCamera, opencv_intrinsics, undistort_maps, undistort_points

    fern = shared_scene("llff_fern")
    before = _tree(fern)
    res = compress(fern, tmp_path / "out", "gaussian", seed=0, jobs=2)
    assert _tree(fern) == before
    rec = res.record
    assert rec["source"]["downscale"] == 8.0 and rec["settings"]["undistorted"]
    cam = rec["cameras"][0]
    src = ColmapCamera.from_params(1, "SIMPLE_RADIAL", 504, 378, tuple(cam["scaled"]["params"]))
    out = ColmapCamera.from_params(1, "PINHOLE", 504, 378, tuple(cam["output"]["params"]))
    assert src.params[0] == pytest.approx(3260.5263328805895 / 8)
    assert 1.0 < cam["zoom"] < 1.03
    counts = largest_remainder(schedule_weights("gaussian"), 17)
    assert rec["settings"]["counts"] == {str(q): c for q, c in zip(QUALITIES, counts, strict=True)}

    # 1. Our maps agree with COLMAP's own model: output pixel -> pinhole ray -> distorted pixel.
    mx, my = undistort_maps(src, out)
    pc_src = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 1.0, 504, 378)
    pc_src.params = list(src.params)
    pc_out = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 1.0, 504, 378)
    pc_out.params = list(out.params)
    ys, xs = np.mgrid[0:378:17, 0:504:23]
    centres = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1).astype(np.float64)
    want = pc_src.img_from_cam(np.concatenate([pc_out.cam_from_img(centres), np.ones((len(centres), 1))], 1))
    got = np.stack([mx[ys.ravel(), xs.ravel()], my[ys.ravel(), xs.ravel()]], 1) + 0.5
    assert np.abs(got - want).max() < 2e-3
    # no black borders: every output pixel samples inside the source
    assert mx.min() >= -1e-3 and my.min() >= -1e-3 and mx.max() <= 503 + 1e-3 and my.max() <= 377 + 1e-3

    # 2. A straight 3D line, imaged by the distorted camera (curved), is straight after undistortion.
    pts3 = np.stack([np.linspace(-0.6, 0.6, 40), np.full(40, -0.44), np.ones(40)], 1)
    curved = pc_src.img_from_cam(pts3)
    sag = np.abs(curved[:, 1] - np.linspace(curved[0, 1], curved[-1, 1], 40)).max()
    assert sag > 0.5  # the distortion bends it visibly
    straight = undistort_points(curved, src, out)
    fit = np.polyfit(straight[:, 0], straight[:, 1], 1)
    assert np.abs(np.polyval(fit, straight[:, 0]) - straight[:, 1]).max() < 1e-3

    # 3. The reference images are what OpenCV's own cv2.undistort gives, up to interpolation (bilinear there,
    # Lanczos-4 here): much closer to it than to the raw image or to cv2.undistort with a half-pixel error.
    K, dist = opencv_intrinsics(src)
    Kn, _ = opencv_intrinsics(out)
    Kh = Kn.copy()
    Kh[0, 2] += 0.5
    inner = (slice(4, -4), slice(4, -4))
    for v in rec["views"][:3]:
        raw = np.asarray(Image.open(fern / "images" / (Path(v["source_name"]).stem + ".png")).convert("RGB"))
        ref = np.asarray(Image.open(tmp_path / "out" / v["reference"])).astype(float)[inner]
        d_cv = np.abs(cv2.undistort(raw, K, dist, None, Kn)[inner] - ref).mean()
        d_half = np.abs(cv2.undistort(raw, K, dist, None, Kh)[inner] - ref).mean()
        d_raw = np.abs(raw[inner] - ref).mean()
        assert d_cv < 0.6 * d_half and d_cv < 0.3 * d_raw, (d_cv, d_half, d_raw)
    _no_parts(tmp_path / "out")


def test_pinhole_real_scene_is_not_resampled(tmp_path: Path) -> None:
    """custom_myhan_mouse: PINHOLE, one camera per image, portrait and landscape, factor 3 — compress only
    scales the intrinsics (checked on a few views: the scene is copied down to its first 9 images)."""
    import pycolmap

    mouse = shared_scene("custom_myhan_mouse")
    rec = pycolmap.Reconstruction(str(mouse / "sparse" / "0"))
    names = sorted(im.name for im in rec.images.values())[:9]
    scene = tmp_path / "mouse"
    (scene / "images").mkdir(parents=True)
    for n in names:
        shutil.copy(mouse / "images" / (Path(n).stem + ".png"), scene / "images")
    # A 9-image model: same cameras and poses.
    keep = {im.image_id for im in rec.images.values() if im.name in names}
    small = pycolmap.Reconstruction()
    for iid in sorted(keep):
        im = rec.images[iid]
        small.add_camera_with_trivial_rig(rec.cameras[im.camera_id])
        small.add_image_with_trivial_frame(
            pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=iid), im.cam_from_world()
        )
    for pid in sorted(rec.points3D)[:500]:
        small.add_point3D(rec.points3D[pid].xyz, pycolmap.Track(), rec.points3D[pid].color)
    (scene / "sparse" / "0").mkdir(parents=True)
    small.write_binary(str(scene / "sparse" / "0"))

    res2 = compress(scene, tmp_path / "out", "uniform", seed=0, jobs=1)
    assert res2.record["source"]["downscale"] == 3.0 and not res2.record["settings"]["undistorted"]
    for cam in res2.record["cameras"]:
        w, h = cam["source"]["width"] // 3, cam["source"]["height"] // 3
        assert (cam["output"]["width"], cam["output"]["height"]) == (w, h)
        assert cam["zoom"] == 1.0
    for v in res2.record["views"]:
        src = np.asarray(Image.open(scene / "images" / (Path(v["source_name"]).stem + ".png")).convert("RGB"))
        assert np.array_equal(np.asarray(Image.open(tmp_path / "out" / v["reference"])), src)
    sizes = {(v["camera"]["width"], v["camera"]["height"]) for v in res2.manifest["views"]}
    assert sizes <= {(640, 480), (480, 640)}


def test_a_split_with_no_training_view_is_refused() -> None:
    from jsgstools.compress import split_names

    with pytest.raises(JsgsError, match="--test-every 1: every one of the 3 views would be a test view"):
        split_names(["a.png", "b.png", "c.png"], 1)
    assert split_names(["a.png", "b.png", "c.png"], 2) == {"a.png": "test", "b.png": "train", "c.png": "test"}


def test_a_second_writer_is_refused(synth_scene: Path, tmp_path: Path) -> None:
    """compress holds its output folder's lock: while another live process holds it, the command refuses
    in one line naming that process, and writes nothing."""
    import json
    import os

    from jsgs.base.io import LOCK_NAME

    out = tmp_path / "data"
    out.mkdir()
    (out / LOCK_NAME).write_text(json.dumps({"pid": os.getppid(), "what": "jsgstools compress (into data)"}))
    r = CliRunner().invoke(main, ["compress", str(synth_scene), "--out", str(out), "--schedule", "gaussian"])
    assert r.exit_code == 1
    assert f"in use by jsgstools compress (into data) (PID {os.getppid()})" in r.output
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
