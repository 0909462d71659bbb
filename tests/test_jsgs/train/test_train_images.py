"""``jsgs.train.data.load_train_images``: one tensor per image size, each view's image a view of it."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from PIL import Image

from jsgs.train.data import load_train_images, stacked_image


def test_training_images_are_views_of_one_tensor_per_size(tmp_path: Path) -> None:
    """Views of two orientations (as a phone scene has) load as two stacks, in no more memory than the
    images themselves; each view's image holds its file's pixels and is found in its stack by index."""
    rng = np.random.default_rng(0)
    views, pixels = [], {}
    for i, (w, h) in enumerate([(20, 12), (12, 20), (20, 12), (20, 12), (12, 20)]):
        arr = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        path = tmp_path / f"{i}.png"
        Image.fromarray(arr).save(path)
        index = 10 + i  # view indices need not start at 0 or be dense
        views.append(SimpleNamespace(index=index, name=f"v{i}", image=path, width=w, height=h))
        pixels[index] = arr
    images = load_train_images(SimpleNamespace(train_views=views), torch.device("cpu"))
    assert list(images) == [v.index for v in views]
    stacks = {}
    for index, image in images.items():
        assert image.dtype == torch.uint8 and np.array_equal(image.numpy(), pixels[index])
        found = stacked_image(image)
        assert found is not None and found[0][found[1]].data_ptr() == image.data_ptr()
        stacks[found[0].data_ptr()] = found[0]
    assert sorted(tuple(s.shape) for s in stacks.values()) == [(2, 20, 12, 3), (3, 12, 20, 3)]
    assert sum(s.nbytes for s in stacks.values()) == sum(a.nbytes for a in pixels.values())
