"""nerfstudio / instant-ngp transforms.json: intrinsics, box, masks, splits, camera models."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from plenoctree.datasets import detect_format, generate_rays, load_blender, load_dataset
from plenoctree.datasets.nerfstudio import load_nerfstudio, read_nerfstudio, write_nerfstudio
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.errors import ConfigError, DatasetError
from nerf_fixtures import copy_dataset as _copy


@pytest.fixture(scope="module")
def blender(tmp_path_factory):
    root = write_procedural_dataset(tmp_path_factory.mktemp("bl"), 10, 0, 0, width=20,
                                    height=16, n_samples=48)
    return load_blender(root, "train")


def _u8(images):
    return np.clip(np.round(images * 255), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def ns_root(blender, tmp_path_factory):
    c = blender.cameras
    return write_nerfstudio(tmp_path_factory.mktemp("ns"), c.c2w, _u8(blender.images),
                            (c.fx, c.fy, c.cx, c.cy), extra={"aabb_scale": 2})


def _edit(root, fn):
    path = root / "transforms.json"
    obj = json.loads(path.read_text())
    fn(obj)
    path.write_text(json.dumps(obj))


def test_round_trip_gives_blender_rays(blender, ns_root):
    assert detect_format(ns_root) == "nerfstudio"
    data = load_dataset(ns_root, "all")
    o_ref, d_ref = blender.cameras.all_rays()
    o, d = data.cameras.all_rays()
    np.testing.assert_allclose(o, o_ref, atol=1e-6)
    np.testing.assert_allclose(d, d_ref, atol=1e-6)
    assert np.abs(data.images - blender.images).max() <= 0.5 / 255 + 1e-6
    assert not data.cameras.per_camera_intrinsics and data.masks is None
    # instant-ngp box: [0.5 - s/2, 0.5 + s/2]^3 in ngp units = ±(s/2)/0.33 here
    np.testing.assert_allclose(data.scene_bbox, np.array([[-1.0] * 3, [1.0] * 3]) / 0.33,
                               rtol=1e-6)
    assert data.names[0] == "frame_00001"


def test_nerfstudio_split_rule(ns_root):
    # every 8th frame by name is held out (LLFF's rule): frames 0 and 8 of 10
    assert load_nerfstudio(ns_root, "train").names == [f"frame_{i + 1:05d}" for i in
                                                        (1, 2, 3, 4, 5, 6, 7, 9)]
    assert load_nerfstudio(ns_root, "val").names == ["frame_00001", "frame_00009"]
    assert load_nerfstudio(ns_root, "test").names == ["frame_00001", "frame_00009"]
    with pytest.raises(ConfigError, match="split"):
        load_nerfstudio(ns_root, "holdout")


def test_explicit_split_lists(ns_root, tmp_path):
    root = _copy(ns_root, tmp_path)
    _edit(root, lambda o: o.update(train_filenames=["images/frame_00002.png",
                                                    "images/frame_00004.png"],
                                   test_filenames=["images/frame_00003.png"]))
    assert load_nerfstudio(root, "train").names == ["frame_00002", "frame_00004"]
    assert load_nerfstudio(root, "test").names == ["frame_00003"]
    _edit(root, lambda o: o.update(test_filenames=["images/nope.png"]))
    with pytest.raises(DatasetError, match="test_filenames lists 1 files but only 0"):
        load_nerfstudio(root, "test")


def test_per_frame_intrinsics(blender, tmp_path):
    c = blender.cameras
    n = len(c)
    k = np.stack([c.fx * (1 + 0.05 * np.arange(n)), np.full(n, c.fy), c.cx + np.arange(n) * 0.5,
                  np.full(n, c.cy - 1.0)], 1)
    root = write_nerfstudio(tmp_path, c.c2w, _u8(blender.images), k)
    data = load_nerfstudio(root, "all")
    assert data.cameras.per_camera_intrinsics
    np.testing.assert_allclose(data.cameras.fx, k[:, 0])
    assert data.cameras.fy == c.fy                            # equal values stay a float
    for i in (0, 7):
        np.testing.assert_allclose(data.cameras.rays(i)[1],
                                   generate_rays(c.c2w[i], *k[i], 20, 16)[1], atol=1e-6)
    half = load_nerfstudio(root, "all", downscale=2)
    np.testing.assert_allclose(half.cameras.cx, k[:, 2] / 2)
    sub = data.cameras.select([3, 1])
    np.testing.assert_allclose(sub.fx, k[[3, 1], 0])
    assert data.cameras.intrinsics(2) == tuple(k[2])


def test_instant_ngp_keys(ns_root, tmp_path):
    root = _copy(ns_root, tmp_path)

    def ngp(o):
        for key in ("fl_x", "fl_y", "cx", "cy", "camera_model"):
            o.pop(key)
        o.update(camera_angle_x=0.6911112070083618, aabb_scale=2, scale=0.5,
                 offset=[0.5, 0.6, 0.7])
    _edit(root, ngp)
    data = load_nerfstudio(root, "all")
    assert data.cameras.fx == pytest.approx(0.5 * 20 / np.tan(0.5 * 0.6911112070083618))
    assert (data.cameras.cx, data.cameras.cy) == (10.0, 8.0)
    # ngp (x, y, z) = file (y, z, x) * scale + offset, ngp box [-0.5, 1.5]^3
    np.testing.assert_allclose(data.scene_bbox, [[-2.4, -2.0, -2.2], [1.6, 2.0, 1.8]], atol=1e-6)
    _edit(root, lambda o: o.pop("aabb_scale"))
    box = load_nerfstudio(root, "all").scene_bbox     # cameras at radius 4 around the origin
    assert np.all(box[0] < -3.0) and np.all(box[1] > 3.0) and np.all(np.abs(box) < 5.0)


def test_instant_ngp_distortion_without_camera_model_is_opencv(ns_root, tmp_path):
    # instant-ngp's colmap2nerf.py writes k1 k2 p1 p2 and no camera_model (real/fox does)
    root = _copy(ns_root, tmp_path)
    coef = {"k1": 0.0578421, "k2": -0.0805099, "p1": -0.000980296, "p2": 0.00015575}
    _edit(root, lambda o: (o.pop("camera_model"), o.update(coef)))
    frames = read_nerfstudio(root / "transforms.json")[1]
    assert frames[0]["raw"][8] == ("OPENCV", list(coef.values()))
    pytest.importorskip("pycolmap")
    data = load_nerfstudio(root, "all")
    _edit(root, lambda o: o.update(camera_model="OPENCV"))
    named = load_nerfstudio(root, "all")
    np.testing.assert_array_equal(data.images, named.images)
    np.testing.assert_allclose(data.cameras.all_rays()[1], named.cameras.all_rays()[1])
    _edit(root, lambda o: (o.pop("camera_model"), o.update(k1=0.0, k2=0.0, p1=0.0, p2=0.0)))
    plain = load_nerfstudio(root, "all")                 # zero coefficients: a pinhole camera
    assert np.abs(plain.images - load_nerfstudio(ns_root, "all").images).max() == 0


def test_masks(blender, tmp_path):
    c = blender.cameras
    rng = np.random.default_rng(0)
    masks = rng.random((len(c), 16, 20)) > 0.3
    root = write_nerfstudio(tmp_path, c.c2w, _u8(blender.images), (c.fx, c.fy, c.cx, c.cy),
                            masks=masks)
    data = load_nerfstudio(root, "all")
    np.testing.assert_array_equal(data.masks, masks.astype(np.float32))
    half = load_nerfstudio(root, "all", downscale=2)
    np.testing.assert_allclose(half.masks, masks.reshape(-1, 8, 2, 10, 2).mean((2, 4)))
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(root / "masks" / "frame_00004.png")
    with pytest.raises(DatasetError, match="frame_00004.png: mask is 8x8, its image is 20x16"):
        load_nerfstudio(root, "all")


def test_prescaled_image_folders(ns_root, tmp_path):
    root = _copy(ns_root, tmp_path)
    (root / "images_2").mkdir()
    for p in (root / "images").iterdir():
        Image.fromarray(np.zeros((8, 10, 3), np.uint8)).save(root / "images_2" / p.name)
    pre = load_nerfstudio(root, "all", downscale=2)
    fly = load_nerfstudio(ns_root, "all", downscale=2)
    assert pre.images.max() == 0.0 and fly.images.max() > 0.5
    np.testing.assert_allclose(pre.cameras.all_rays()[1], fly.cameras.all_rays()[1], atol=1e-6)


@pytest.mark.parametrize("edit, match", [
    (lambda o: o.update(camera_model="EQUIRECTANGULAR"), "'EQUIRECTANGULAR' is not supported"),
    (lambda o: o.update(camera_model="SIMPLE_RADIAL", k2=0.05),
     "k2 = 0.05 is not part of the SIMPLE_RADIAL camera model"),
    (lambda o: o["frames"][3].update(camera_model="OPENCV_FISHEYE", p2=-0.01),
     r"frames\[3\]: distortion coefficient p2"),
    (lambda o: o["frames"][2].update(camera_model="FISHEYE"), r"frames\[2\]: camera model"),
    (lambda o: o.update(k1="x"), "k1 must be a finite number"),
    (lambda o: [o.pop(k) for k in ("fl_x", "fl_y")], "missing intrinsics"),
    (lambda o: o.update(w=21), "w = 21 but the image is 20x16"),
    (lambda o: o["frames"][4].update(transform_matrix=[[1, 0, 0, "x"]] * 4), r"frames\[4\]"),
    (lambda o: o["frames"][5]["transform_matrix"][0].__setitem__(3, float("nan")),
     r"frames\[5\]: transform_matrix contains non-finite"),
    (lambda o: o["frames"][6].pop("file_path"), r"frames\[6\]: missing key 'file_path'"),
    (lambda o: o.update(frames=[]), "empty 'frames'"),
    (lambda o: o.update(aabb_scale=-1), "aabb_scale"),
    (lambda o: o.update(plenoctree_bounds=[2.0]), r"plenoctree_bounds must be \[near, far\]"),
    (lambda o: o.update(plenoctree_bounds=[3.0, 1.0]), "0 < near <= far"),
])
def test_bad_transforms_name_the_file(ns_root, tmp_path, edit, match):
    root = _copy(ns_root, tmp_path)
    _edit(root, edit)
    with pytest.raises(DatasetError, match=match) as info:
        load_nerfstudio(root, "all")
    assert "transforms.json" in str(info.value)


def test_bad_images_name_the_file(ns_root, tmp_path):
    root = _copy(ns_root, tmp_path)
    img = root / "images" / "frame_00003.png"
    Image.fromarray(np.zeros((16, 18, 3), np.uint8)).save(img)
    with pytest.raises(DatasetError, match="frame_00003.png: image is 18x16, expected 20x16"):
        load_nerfstudio(root, "all")
    img.unlink()
    with pytest.raises(DatasetError, match="frame_00003.png: image file not found"):
        load_nerfstudio(root, "all")
    (root / "transforms.json").write_text("{not json")
    with pytest.raises(DatasetError, match="transforms.json: not valid JSON"):
        load_nerfstudio(root, "all")
