"""tools/results/thumbs.py: a bench's renders at the first and last evaluation, scaled down, as JPEGs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import load_benchmark
from PIL import Image

thumbs = load_benchmark("thumbs", "tools/results")


def _render(path: Path, value: int, size: tuple[int, int] = (40, 24)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((size[1], size[0], 3), value, np.uint8)).save(path)


def test_first_and_last_evaluation_of_each_run_scaled(tmp_path: Path) -> None:
    run = tmp_path / "b" / "runs" / "cup" / "gaussian" / "jsgs" / "mcmc-auto" / "s0"
    for step, value in ((20, 10), (40, 20), (60, 200)):
        _render(run / "renders" / f"step_{step:06d}" / "v1.png", value)
    other = tmp_path / "b" / "runs" / "cup" / "clean" / "gsplat" / "mcmc-auto" / "s0"
    _render(other / "renders" / "step_000020" / "v1.png", 90, size=(3, 2))
    assert thumbs.main([str(tmp_path / "b"), str(tmp_path / "t")]) == 0
    got = sorted(p.relative_to(tmp_path / "t").as_posix() for p in (tmp_path / "t").rglob("*.jpg"))
    assert got == [
        "cup/clean/gsplat/mcmc-auto/s0/step_000020/v1.jpg",
        "cup/gaussian/jsgs/mcmc-auto/s0/step_000020/v1.jpg",
        "cup/gaussian/jsgs/mcmc-auto/s0/step_000060/v1.jpg",
    ]
    with Image.open(tmp_path / "t/cup/gaussian/jsgs/mcmc-auto/s0/step_000060/v1.jpg") as im:
        assert im.format == "JPEG" and im.size == (10, 6)
        assert abs(int(np.asarray(im).mean()) - 200) <= 2  # the last evaluation's, not the middle one's
    with Image.open(tmp_path / "t/cup/clean/gsplat/mcmc-auto/s0/step_000020/v1.jpg") as im:
        assert im.size == (1, 1)  # never 0 px


def test_not_a_bench_or_a_bad_scale_is_one_line(tmp_path: Path, capsys) -> None:
    assert thumbs.main([str(tmp_path), str(tmp_path / "t")]) == 2
    assert capsys.readouterr().err == f"thumbs: {tmp_path}: no runs/ folder (not a bench output)\n"
    (tmp_path / "runs").mkdir()
    assert thumbs.main([str(tmp_path), str(tmp_path / "t"), "--scale", "0"]) == 2
    assert capsys.readouterr().err == "thumbs: --scale 0: must be at least 1\n"
    assert thumbs.main([str(tmp_path), str(tmp_path / "t")]) == 0
    assert "thumbs: 0 render(s)" in capsys.readouterr().out
