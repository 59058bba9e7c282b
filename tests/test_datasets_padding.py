"""Black padding at the photos' borders (datasets/padding.py): found on every photo of a
folder, cropped from both opposite edges by the LLFF loader, its cameras and its video path
cropped alike; photos without it load as they are."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from plenoctree.datasets import load_dataset
from plenoctree.datasets.forward_facing import write_forward_facing_dataset
from plenoctree.datasets.llff import llff_render_cameras
from plenoctree.datasets.padding import border_padding, crop_padding


def _photos(n: int = 6, h: int = 40, w: int = 56, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [(rng.uniform(0.3, 0.9, (h, w, 3)) * 255).astype(np.uint8) for _ in range(n)]


def _write(folder: Path, imgs: list[np.ndarray]) -> list[Path]:
    folder.mkdir()
    paths = []
    for i, im in enumerate(imgs):
        p = folder / f"{i:03d}.png"
        Image.fromarray(im).save(p)
        paths.append(p)
    return paths


def test_black_and_darkened_rows_are_padding(tmp_path):
    imgs = _photos()
    for im in imgs:
        im[-1] = 1                                     # a video's black last row
    assert border_padding(_write(tmp_path / "a", imgs)) == (1, 0)
    half = _photos(seed=1)
    for im in half:
        im[-1] = (im[-1] * 0.26).astype(np.uint8)      # a downscaled copy: a quarter as bright
        im[:, :2] = 0                                  # and two black columns on the left
    assert border_padding(_write(tmp_path / "b", half)) == (1, 2)


def test_photos_without_padding_or_with_a_dark_edge_on_some_load_as_they_are(tmp_path):
    assert border_padding(_write(tmp_path / "a", _photos())) == (0, 0)
    some = _photos(seed=2)
    for im in some[:3]:                                # a dark floor on half of the photos
        im[-1] = 0
    assert border_padding(_write(tmp_path / "b", some)) == (0, 0)


def test_crop_keeps_the_principal_point_centred():
    from plenoctree.datasets.cameras import Cameras

    cams = Cameras(np.eye(4, dtype=np.float32)[None].repeat(2, 0), 50.0, 50.0, 28.0, 20.0, 56, 40)
    imgs = np.zeros((2, 40, 56, 3), np.float32)
    out, alphas, c = crop_padding(imgs, None, cams, 1, 0)
    assert out.shape == (2, 38, 56, 3) and alphas is None
    assert (c.width, c.height, c.cx, c.cy) == (56, 38, 28.0, 19.0)
    out, _, c = crop_padding(imgs[:, ::2, ::2], None, cams.scaled(2), 3, 1, factor=2)
    assert out.shape == (2, 16, 26, 3) and (c.width, c.height, c.cx, c.cy) == (26, 16, 13.0, 8.0)


def _padded_llff(tmp_path: Path, pad: bool) -> Path:
    root = write_forward_facing_dataset(tmp_path / ("pad" if pad else "plain"), n_images=9,
                                        width=64, height=48, n_samples=8)
    if pad:
        for p in sorted((root / "images").iterdir()):
            im = np.asarray(Image.open(p)).copy()
            im[-1] = 0
            Image.fromarray(im).save(p)
    return root


def test_llff_loader_crops_padding_in_every_split_and_the_video_path(tmp_path):
    plain = _padded_llff(tmp_path, False)
    padded = _padded_llff(tmp_path, True)
    for split in ("train", "test"):
        a = load_dataset(plain, split=split)
        b = load_dataset(padded, split=split)
        assert a.images.shape[1:3] == (48, 64) and a.cameras.height == 48
        assert b.images.shape[1:3] == (46, 64) and b.cameras.height == 46
        assert b.cameras.cy == pytest.approx(23.0) and b.cameras.cx == pytest.approx(a.cameras.cx)
        np.testing.assert_array_equal(b.images, a.images[:, 1:47])   # the same pixels, cropped
        # rays of the cropped image are the plain image's rays one row down
        ra, rb = a.cameras.rays(0), b.cameras.rays(0)
        np.testing.assert_allclose(rb[0], ra[0][1:47], atol=1e-6)
        np.testing.assert_allclose(rb[1], ra[1][1:47], atol=1e-6)
    assert llff_render_cameras(padded, n_frames=3).height == 46
    assert llff_render_cameras(plain, n_frames=3).height == 48
