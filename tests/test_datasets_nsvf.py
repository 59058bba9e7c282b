"""NSVF / Tanks&Temples loader: OpenCV poses, intrinsics forms, bbox, splits, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from plenoctree.datasets import detect_format, load_blender, load_dataset
from plenoctree.datasets.nsvf import load_nsvf, read_intrinsics, write_nsvf
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.errors import ConfigError, DatasetError
from nerf_fixtures import copy_dataset as _copy


@pytest.fixture(scope="module")
def blender(tmp_path_factory):
    root = write_procedural_dataset(tmp_path_factory.mktemp("bl"), 5, 2, 3, width=20,
                                    height=14, n_samples=48)
    return {s: load_blender(root, s) for s in ("train", "val", "test")}


def _rgba(ds):
    """The dataset's images with their alpha, as straight (un-premultiplied) uint8 RGBA."""
    a = ds.alphas[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        rgb = np.where(a > 0, (ds.images - (1 - a)) / a, 0.0)
    return np.clip(np.round(np.concatenate([rgb, a], -1) * 255), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def nsvf_root(blender, tmp_path_factory):
    c = blender["train"].cameras
    return write_nsvf(tmp_path_factory.mktemp("nsvf"),
                      {s: (d.cameras.c2w, _rgba(d)) for s, d in blender.items()},
                      c.fx, c.fy, c.cx, c.cy, bbox=[[-1.2, -1.1, -1.0], [1.0, 1.1, 1.2]])


def test_round_trip_gives_blender_rays(blender, nsvf_root):
    assert detect_format(nsvf_root) == "nsvf"
    for split in ("train", "val", "test"):
        ref = blender[split]
        data = load_dataset(nsvf_root, split)
        assert data.names == [f"{'012'[['train', 'val', 'test'].index(split)]}_{i:04d}"
                              for i in range(len(ref))]
        o_ref, d_ref = ref.cameras.all_rays()
        o, d = data.cameras.all_rays()
        np.testing.assert_allclose(o, o_ref, atol=1e-6)
        np.testing.assert_allclose(d, d_ref, atol=1e-6)
        assert np.abs(data.images - ref.images).max() < 3.0 / 255
        assert np.abs(data.alphas - ref.alphas).max() <= 0.5 / 255 + 1e-6
    np.testing.assert_allclose(data.scene_bbox, [[-1.2, -1.1, -1.0], [1.0, 1.1, 1.2]])
    # near/far bound every ray segment inside the box (cameras at distance 4)
    assert 0 < data.near < 4.0 - 1.0 and 4.0 + 1.2 < data.far < 4.0 + 2.1
    assert len(load_nsvf(nsvf_root, "all")) == 10


def test_golden_opencv_pose_and_matrix_intrinsics(tmp_path):
    # OpenCV camera at (0, 0, 5) looking at the origin: camera z = world -z, camera y (down)
    # = world -y, camera x = world +x
    (tmp_path / "pose").mkdir()
    (tmp_path / "rgb").mkdir()
    (tmp_path / "pose" / "0_a.txt").write_text("1 0 0 0\n0 -1 0 0\n0 0 -1 5\n0 0 0 1\n")
    (tmp_path / "intrinsics.txt").write_text("20 0 10 0\n0 25 6 0\n0 0 1 0\n0 0 0 1\n")
    Image.fromarray(np.full((12, 20, 3), 255, np.uint8)).save(tmp_path / "rgb" / "0_a.png")
    data = load_nsvf(tmp_path)
    c = data.cameras
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (20.0, 25.0, 10.0, 6.0, 20, 12)
    np.testing.assert_allclose(c.c2w[0], [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]])
    o, d = c.rays(0)
    centre = d[5:7, 9:11].mean((0, 1))
    np.testing.assert_allclose(centre / np.linalg.norm(centre), [0, 0, -1], atol=1e-6)
    assert d[0, 10, 1] > 0                                # image top row looks up (+y)
    # no bbox.txt: the box holds the camera centres, near/far from it
    assert np.all(data.scene_bbox[0] <= [0, 0, 5]) and np.all(data.scene_bbox[1] >= [0, 0, 5])
    assert data.alphas is None and data.near == 0.0


@pytest.mark.parametrize("text, want", [
    ("20 0 10 0\n0 25 6 0\n0 0 1 0\n0 0 0 1\n", (20.0, 25.0, 10.0, 6.0)),
    ("20 0 10\n0 25 6\n0 0 1\n", (20.0, 25.0, 10.0, 6.0)),
    ("555.5 400 300 0.\n0. 0. 0.\n1.\n800 600\n", (555.5, 555.5, 400.0, 300.0)),
    ("555.5 400 300\n", (555.5, 555.5, 400.0, 300.0)),
])
def test_intrinsics_forms(tmp_path, text, want):
    (tmp_path / "intrinsics.txt").write_text(text)
    assert read_intrinsics(tmp_path / "intrinsics.txt") == want


def test_splits_and_test_fallback(nsvf_root, tmp_path):
    root = _copy(nsvf_root, tmp_path)
    for p in list((root / "rgb").glob("2_*")) + list((root / "pose").glob("2_*")):
        p.unlink()
    assert load_nsvf(root, "test").names == load_nsvf(root, "val").names   # falls back to 1_
    assert load_nsvf(root, "train", limit=2).names == ["0_0000", "0_0001"]
    with pytest.raises(ConfigError, match="split"):
        load_nsvf(root, "holdout")


def test_downscale(nsvf_root):
    full = load_nsvf(nsvf_root, "test")
    half = load_nsvf(nsvf_root, "test", downscale=2)
    assert half.images.shape == (3, 7, 10, 3) and half.cameras.fx == full.cameras.fx / 2
    with pytest.raises(DatasetError, match="does not divide"):
        load_nsvf(nsvf_root, "test", downscale=3)


def test_bad_inputs_name_the_file(nsvf_root, tmp_path):
    root = _copy(nsvf_root, tmp_path)
    pose = root / "pose" / "0_0002.txt"
    good = pose.read_text()
    pose.write_text("1 0 0 0\n0 1 0 nan\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DatasetError, match="0_0002.txt: pose contains non-finite"):
        load_nsvf(root)
    pose.write_text("1 0 0\n0 1 0\n")
    with pytest.raises(DatasetError, match="0_0002.txt: expected a 4x4"):
        load_nsvf(root)
    pose.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 2\n")
    with pytest.raises(DatasetError, match="0_0002.txt: last row"):
        load_nsvf(root)
    pose.write_text("a b c d\n")
    with pytest.raises(DatasetError, match="0_0002.txt: line 1"):
        load_nsvf(root)
    pose.unlink()
    with pytest.raises(DatasetError, match=r"9 poses but 10 images; image .*0_0002.png has no pose"):
        load_nsvf(root)
    pose.write_text(good)
    extra = root / "pose" / "0_0099.txt"
    extra.write_text(good)
    with pytest.raises(DatasetError, match=r"pose .*0_0099.txt has no image"):
        load_nsvf(root)
    extra.unlink()
    img = root / "rgb" / "0_0001.png"
    orig = img.read_bytes()
    Image.fromarray(np.zeros((14, 22, 3), np.uint8)).save(img)
    with pytest.raises(DatasetError, match="0_0001.png: image is 22x14, expected 20x14"):
        load_nsvf(root)
    img.write_bytes(orig[:-12])
    with pytest.raises(DatasetError, match="0_0001.png: truncated"):
        load_nsvf(root)
    img.write_bytes(orig)
    (root / "bbox.txt").write_text("1 1 1 0 0 0\n")
    with pytest.raises(DatasetError, match="bbox.txt: box must be finite with max > min"):
        load_nsvf(root)
    (root / "bbox.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="bbox.txt: expected"):
        load_nsvf(root)
    (root / "bbox.txt").unlink()
    (root / "intrinsics.txt").write_text("0 0 10\n0 0 6\n0 0 1\n")
    with pytest.raises(DatasetError, match="intrinsics.txt: focal lengths"):
        load_nsvf(root)
    (root / "intrinsics.txt").write_text("1 2\n3 4 5 6 7\n")
    with pytest.raises(DatasetError, match="intrinsics.txt: expected"):
        load_nsvf(root)
    (root / "intrinsics.txt").unlink()
    with pytest.raises(DatasetError, match="intrinsics.txt: intrinsics file not found"):
        load_nsvf(root)
    assert len(load_nsvf(nsvf_root)) == 5                 # the source is intact
