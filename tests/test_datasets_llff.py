"""LLFF loader: pose conversion, normalisation, splits, downscaling, render path, bad input."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from plenoctree.datasets import detect_format, llff_render_cameras, load_blender, load_dataset
from plenoctree.datasets.forward_facing import write_forward_facing_dataset
from plenoctree.datasets.llff import LLFFOptions, average_pose, load_llff, read_llff, write_llff
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.errors import ConfigError, DatasetError
from nerf_fixtures import copy_dataset as _copy

NO_NDC = LLFFOptions(ndc=False)


@pytest.fixture(scope="module")
def blender(tmp_path_factory):
    root = write_procedural_dataset(tmp_path_factory.mktemp("bl"), 10, 1, 1, width=24,
                                    height=16, n_samples=48)
    return load_blender(root, "train")


@pytest.fixture(scope="module")
def llff_root(blender, tmp_path_factory):
    """The procedural Blender scene written as an LLFF capture (lossless PNGs)."""
    c = blender.cameras
    bounds = np.tile([2.0, 6.0], (len(c), 1)) + np.linspace(0, 0.5, len(c))[:, None]
    return write_llff(tmp_path_factory.mktemp("llff"), c.c2w, blender.images, c.fx, bounds)


@pytest.fixture(scope="module")
def ff_root(tmp_path_factory):
    return write_forward_facing_dataset(tmp_path_factory.mktemp("ff"), n_images=10, width=16,
                                        height=12, n_samples=32)


def test_round_trip_gives_blender_rays(blender, llff_root):
    assert detect_format(llff_root) == "llff"
    data = load_dataset(llff_root, "all", options=LLFFOptions(recenter=False, bd_factor=None,
                                                                 ndc=False))
    o_ref, d_ref = blender.cameras.all_rays()
    o, d = data.cameras.all_rays()
    np.testing.assert_allclose(o, o_ref, atol=2e-6)
    np.testing.assert_allclose(d, d_ref, atol=2e-6)
    assert np.abs(data.images - blender.images).max() <= 0.5 / 255 + 1e-6
    assert data.alphas is None and data.names[0] == "000"
    assert data.near == pytest.approx(0.9 * 2.0) and data.far == pytest.approx(6.5)


def test_normalisation_is_a_similarity_of_the_file_world(blender, llff_root):
    data = load_llff(llff_root, "all", options=NO_NDC)
    scene = read_llff(llff_root)
    np.testing.assert_allclose(average_pose(scene.c2w), np.eye(4), atol=1e-6)
    assert scene.bounds.min() == pytest.approx(1.0 / 0.75)
    assert scene.scale == pytest.approx(1.0 / (2.0 * 0.75))
    t = scene.transform
    o_ref, d_ref = blender.cameras.all_rays()
    o, d = data.cameras.all_rays()
    np.testing.assert_allclose(o, o_ref @ t[:3, :3].T + t[:3, 3], atol=1e-5)
    d_exp = d_ref @ t[:3, :3].T
    np.testing.assert_allclose(d, d_exp / np.linalg.norm(d_exp, axis=-1, keepdims=True), atol=1e-5)


def test_golden_llff_axes(tmp_path):
    # LLFF stores (down, right, backwards) columns. A camera at (1, 2, 3) whose backwards axis
    # is world +x looks down world -x, with image right = world -z and image up = world +y.
    down, right, back = [0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]
    m = np.stack([down, right, back, [1.0, 2.0, 3.0], [16.0, 20.0, 10.0]], 1)   # H, W, focal
    np.save(tmp_path / "poses_bounds.npy", np.concatenate([m.reshape(-1), [1.0, 5.0]])[None])
    (tmp_path / "images").mkdir()
    Image.fromarray(np.zeros((16, 20, 3), np.uint8)).save(tmp_path / "images" / "a.png")
    data = load_llff(tmp_path, "all", options=LLFFOptions(recenter=False, bd_factor=None,
                                                            ndc=False))
    np.testing.assert_allclose(data.cameras.c2w[0, :3, :3],
                               np.stack([right, [0, 1, 0], back], 1), atol=1e-7)
    o, d = data.cameras.rays(0)
    np.testing.assert_allclose(o[0, 0], [1, 2, 3])
    centre = d[7:9, 9:11].mean((0, 1))
    np.testing.assert_allclose(centre / np.linalg.norm(centre), [-1, 0, 0], atol=1e-6)
    assert d[0, 10, 1] > 0 and d[10, 0, 2] > 0          # top row looks up, left column to +z
    assert (data.cameras.fx, data.cameras.cx, data.cameras.cy) == (10.0, 10.0, 8.0)


def test_llffhold_splits(llff_root):
    names = {s: load_llff(llff_root, s, options=NO_NDC).names
             for s in ("train", "test", "val", "all")}
    assert names["test"] == ["000", "008"] == names["val"]
    assert names["train"] == [f"{i:03d}" for i in range(10) if i % 8]
    assert len(names["all"]) == 10
    hold3 = LLFFOptions(ndc=False, llffhold=3)
    assert load_llff(llff_root, "test", options=hold3).names == ["000", "003", "006", "009"]
    assert load_llff(llff_root, "train", limit=2, options=NO_NDC).names == ["001", "002"]
    with pytest.raises(DatasetError, match="empty"):
        load_llff(llff_root, "test", options=LLFFOptions(ndc=False, llffhold=0))
    with pytest.raises(ConfigError, match="split"):
        load_llff(llff_root, "holdout", options=NO_NDC)


def test_forward_facing_defaults_to_ndc_and_spherify_does_not(ff_root):
    data = load_dataset(ff_root, "train")
    assert data.cameras.ndc and data.near == 0.0 and 2.0 < data.far < 4.0
    np.testing.assert_allclose(data.scene_bbox[:, 2], [-1, 1])
    o, d = data.cameras.rays(0)
    np.testing.assert_allclose(o[..., 2], -1.0, atol=1e-5)
    sph = load_dataset(ff_root, "train", options=LLFFOptions(spherify=True))
    assert not sph.cameras.ndc
    r = np.linalg.norm(read_llff(ff_root, spherify=True).c2w[:, :3, 3], axis=1)
    assert np.sqrt(np.mean(r ** 2)) == pytest.approx(1.0)
    np.testing.assert_allclose(sph.scene_bbox, [[-1] * 3, [1] * 3])
    with pytest.raises(ConfigError, match="spherify"):
        load_llff(ff_root, options=LLFFOptions(ndc=True, spherify=True))


def test_inward_facing_scene_is_detected_and_refuses_ndc(llff_root, ff_root, caplog):
    """A folder whose cameras surround the scene is a 360° capture: spherified, no NDC, and
    the loader says so, once a file however often a run loads it; forward-facing folders keep
    NDC; NDC asked for is still refused."""
    import plenoctree.datasets.llff as llff_mod

    llff_mod._SAID_360.discard(str(Path(llff_root) / "poses_bounds.npy"))
    with caplog.at_level("INFO", logger="plenoctree.datasets.llff"):
        assert read_llff(llff_root, spherify=None).spherify       # decided by the cameras
        assert not read_llff(ff_root, spherify=None).spherify
        data = load_llff(llff_root, "train")
        load_llff(llff_root, "test")
    assert caplog.text.count("a 360° capture") == 1 and "poses_bounds.npy" in caplog.text
    assert not data.cameras.ndc
    np.testing.assert_allclose(data.scene_bbox, [[-1] * 3, [1] * 3])
    same = load_llff(llff_root, "train", options=LLFFOptions(spherify=True))
    np.testing.assert_array_equal(data.cameras.c2w, same.cameras.c2w)
    assert llff_render_cameras(llff_root, n_frames=4).ndc is False          # a circle
    caplog.clear()
    with caplog.at_level("INFO", logger="plenoctree.datasets.llff"):
        assert load_llff(ff_root, "train").cameras.ndc
    assert "360" not in caplog.text
    with pytest.raises(DatasetError, match="forward-facing"):
        load_llff(llff_root, "train", options=LLFFOptions(ndc=True))   # NDC impossible


@pytest.mark.parametrize("scene,kind", [("flower", "forward"), ("lounge", "360")])
def test_real_captures_are_detected(scene, kind):
    """LLFF's flower is forward-facing; lounge (a 347° walk-around in mip-NeRF 360's layout)
    is a 360° capture: spherified, no NDC rays."""
    from pathlib import Path

    from plenoctree.datasets.camera_sets import capture_kind
    from plenoctree.datasets.llff import read_poses_bounds

    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / scene
    if not (root / "poses_bounds.npy").is_file():
        pytest.skip(f"{root} is not here")
    assert capture_kind(read_poses_bounds(root / "poses_bounds.npy")[0]) == kind
    assert read_llff(root, spherify=None).spherify == (kind == "360")
    data = load_dataset(root, "test", downscale=8 if scene == "flower" else 4, limit=1)
    assert data.cameras.ndc == (kind == "forward")


def test_render_path(ff_root):
    data = load_dataset(ff_root, "train")
    path = llff_render_cameras(ff_root, n_frames=12)
    assert len(path) == 12 and path.ndc and (path.width, path.height) == (16, 12)
    assert path.fx == pytest.approx(data.cameras.fx)
    scene = read_llff(ff_root)
    rads = np.percentile(np.abs(scene.c2w[:, :3, 3]), 90, axis=0)
    assert np.all(np.abs(path.centers) <= rads * 1.0001 + 1e-6)
    assert np.all(path.c2w[:, 2, 2] > 0.9)       # still looking down -z
    for i in range(len(path)):
        o, d = path.rays(i)
        assert np.isfinite(o).all() and np.isfinite(d).all()
    # the spiral turns twice: frames k and k + 6 share x, y
    np.testing.assert_allclose(path.centers[0, :2], path.centers[6, :2], atol=1e-6)
    circ = llff_render_cameras(ff_root, n_frames=8, downscale=2,
                               options=LLFFOptions(spherify=True))
    assert not circ.ndc and circ.width == 8
    np.testing.assert_allclose(np.linalg.norm(circ.centers[:, :2], axis=1),
                               np.linalg.norm(circ.centers[0, :2]), rtol=1e-6)


def test_prescaled_folder_and_on_the_fly_downscale(ff_root, tmp_path):
    root = _copy(ff_root, tmp_path)
    fly = load_llff(root, "train", downscale=2)
    assert fly.images.shape[1:] == (6, 8, 3)
    full = load_llff(root, "train")
    np.testing.assert_allclose(fly.images, full.images.reshape(-1, 6, 2, 8, 2, 3).mean((2, 4)),
                               atol=1e-6)
    (root / "images_2").mkdir()
    for p in sorted((root / "images").iterdir()):       # a pre-shrunk (black) copy is preferred
        Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(root / "images_2" / p.name)
    pre = load_llff(root, "train", downscale=2)
    assert pre.images.max() == 0.0
    np.testing.assert_allclose(pre.cameras.all_rays()[1], fly.cameras.all_rays()[1], atol=1e-6)
    with pytest.raises(DatasetError, match="does not divide"):
        load_llff(root, "train", downscale=3)


def test_cameras_of_a_folder_with_only_downscaled_images(ff_root, tmp_path):
    """LLFF's flower ships only images_8/: the viewer's and the web stage's camera loading
    (load_cameras) must not need images/ (the flower chain's web stage failed on it)."""
    from plenoctree.datasets import load_cameras

    root = _copy(ff_root, tmp_path)
    (root / "images_2").mkdir()
    for p in sorted((root / "images").iterdir()):
        with Image.open(p) as im:
            im.resize((8, 6), Image.BOX).save(root / "images_2" / p.name)
        p.unlink()
    (root / "images").rmdir()
    with pytest.raises(DatasetError, match="image folder not found"):
        load_llff(root, "train")
    cams = load_cameras(root, "train")
    assert (cams.cameras.width, cams.cameras.height) == (8, 6)
    ref = load_llff(ff_root, "train", downscale=2).cameras
    np.testing.assert_allclose(cams.cameras.all_rays()[1], ref.all_rays()[1], atol=1e-6)


def test_bad_inputs_name_the_file(ff_root, tmp_path):
    root = _copy(ff_root, tmp_path)
    pb = root / "poses_bounds.npy"
    good = np.load(pb)

    def expect(arr, match):
        np.save(pb, arr)
        with pytest.raises(DatasetError, match=match):
            load_llff(root, "train")
        np.save(pb, good)

    expect(good[:-1], "9 poses but .*images.* holds 10 images")
    bad = good.copy()
    bad[3, 3] = np.nan
    expect(bad, "poses_bounds.npy: pose/bounds row 3 contains non-finite")
    expect(good[:, :15], r"expected shape \[N, 17\]")
    bad = good.copy()
    bad[2, 15] = -1.0
    expect(bad, "row 2: depth bounds")
    bad = good.copy()
    bad[1, 0:3] *= 2.0
    expect(bad, "not orthonormal")
    bad = good.copy()
    bad[4, 4] = 100.0                                   # row 4 claims another height
    expect(bad, "mixed sizes: row 4")
    bad = good.copy()
    bad[:, 4] = 30.0
    expect(bad, "aspect ratio")
    np.save(pb, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DatasetError, match="poses_bounds.npy: not a readable"):
        load_llff(root)
    pb.write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="poses_bounds.npy: not a readable"):
        load_llff(root)
    np.save(pb, good)
    img = root / "images" / "005.png"
    Image.fromarray(np.zeros((12, 15, 3), np.uint8)).save(img)
    with pytest.raises(DatasetError, match=r"005.png: image is 15x12, expected 16x12"):
        load_llff(root, "all")
    img.write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    with pytest.raises(DatasetError, match="005.png"):
        load_llff(root, "all")
    shutil.rmtree(root / "images")
    with pytest.raises(DatasetError, match="image folder not found"):
        load_llff(root)
    with pytest.raises(DatasetError, match="does not exist"):
        load_llff(tmp_path / "nowhere")
    with pytest.raises(ConfigError, match="downscale"):
        load_llff(ff_root, downscale=0)
    assert math.isfinite(load_llff(ff_root).far)          # the source is intact


def test_photo_formats_default_to_a_black_background(blender, llff_root, tmp_path):
    from plenoctree.datasets.dataset import default_background, holds_photos

    bl_root = write_procedural_dataset(tmp_path / "bl", 2, 1, 1, width=8, height=8,
                                       n_samples=8)
    assert holds_photos(llff_root) and not holds_photos(bl_root)
    assert default_background(llff_root) == (0.0, 0.0, 0.0)
    assert load_dataset(llff_root, "train", limit=1, options=NO_NDC).background == (0, 0, 0)
    assert load_dataset(bl_root, "train", limit=1).background == (1.0, 1.0, 1.0)
    asked = load_dataset(llff_root, "train", limit=1, options=NO_NDC, background=(0.2, 0.4, 0.6))
    assert asked.background == pytest.approx((0.2, 0.4, 0.6))
