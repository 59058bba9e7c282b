"""Format detection, load_dataset(format=...), per-camera intrinsics, Dataset.masks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plenoctree.datasets import FORMATS, Cameras, Dataset, detect_format, load_dataset
from plenoctree.datasets.forward_facing import write_forward_facing_dataset
from plenoctree.errors import ConfigError, DatasetError


def _touch(root, *names):
    for n in names:
        p = root / n
        if n.endswith("/"):
            p.mkdir(parents=True, exist_ok=True)
        else:
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text("{}")


@pytest.mark.parametrize("files, fmt", [
    (["transforms_train.json"], "blender"),
    (["transforms_test.json"], "blender"),
    (["transforms.json"], "nerfstudio"),
    (["poses_bounds.npy", "images/"], "llff"),
    (["intrinsics.txt", "pose/", "rgb/"], "nsvf"),
])
def test_detect_each_format(tmp_path, files, fmt):
    _touch(tmp_path, *files)
    assert detect_format(tmp_path) == fmt and fmt in FORMATS


def test_detect_unknown_and_ambiguous(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        detect_format(tmp_path / "nope")
    _touch(tmp_path, "intrinsics.txt")                       # no pose/ folder: not NSVF
    with pytest.raises(DatasetError, match="unknown dataset format.*poses_bounds.npy"):
        detect_format(tmp_path)
    _touch(tmp_path, "transforms.json", "poses_bounds.npy")
    with pytest.raises(DatasetError, match="ambiguous.*nerfstudio and llff.*format="):
        load_dataset(tmp_path)


def test_format_forces_the_loader(tmp_path):
    root = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=8, height=6,
                                        n_samples=16)
    (root / "transforms.json").write_text(json.dumps({"frames": []}))   # a decoy
    with pytest.raises(DatasetError, match="ambiguous"):
        load_dataset(root, "train")
    data = load_dataset(root, "train", format="llff", downscale=2)
    assert len(data) == 7 and data.images.shape[1:3] == (3, 4) and data.cameras.ndc
    with pytest.raises(DatasetError, match="transforms.json: missing or empty 'frames'"):
        load_dataset(root, format="nerfstudio")
    with pytest.raises(ConfigError, match="unknown dataset format 'colmap2'"):
        load_dataset(root, format="colmap2")
    with pytest.raises(DatasetError, match="ff: no COLMAP model"):
        load_dataset(root, format="colmap")
    with pytest.raises(ConfigError, match="nsvf loader.*llffhold"):
        load_dataset(root, format="nsvf", llffhold=8)


def test_cameras_per_camera_intrinsics_validation():
    c2w = np.tile(np.eye(4), (3, 1, 1))
    cams = Cameras(c2w, [10.0, 11.0, 12.0], 10.0, [4.0, 4.0, 4.0], 3.0, 8, 6)
    assert cams.cx == 4.0 and isinstance(cams.cx, float)      # equal values collapse
    assert cams.per_camera_intrinsics and not cams.fx.flags.writeable
    assert cams == Cameras(c2w, np.array([10.0, 11.0, 12.0]), 10.0, 4.0, 3.0, 8, 6)
    assert cams != Cameras(c2w, np.array([10.0, 11.0, 12.5]), 10.0, 4.0, 3.0, 8, 6)
    np.testing.assert_allclose(cams.intrinsics_array()[:, 0], [10, 11, 12])
    assert cams.scaled(2).fx.tolist() == [5.0, 5.5, 6.0]
    assert cams.select(1).fx == 11.0 and len(cams.select(1)) == 1
    with pytest.raises(ConfigError, match="fx must be a number or an array of 3"):
        Cameras(c2w, [10.0, 11.0], 10.0, 4.0, 3.0, 8, 6)
    with pytest.raises(ConfigError, match="fy must be a finite positive"):
        Cameras(c2w, 10.0, [10.0, -1.0, 10.0], 4.0, 3.0, 8, 6)
    with pytest.raises(ConfigError, match="cy must be a finite number"):
        Cameras(c2w, 10.0, 10.0, 4.0, [3.0, np.nan, 3.0], 8, 6)
    with pytest.raises(ConfigError, match="ndc_near"):
        Cameras(c2w, 10.0, 10.0, 4.0, 3.0, 8, 6, ndc=True, ndc_near=0.0)


def test_dataset_masks_shape_checked(tmp_path):
    cams = Cameras(np.eye(4)[None], 4.0, 4.0, 2.0, 2.0, 4, 4)
    kw = dict(images=np.zeros((1, 4, 4, 3), np.float32), cameras=cams, near=0.0, far=1.0,
              scene_bbox=[[-1] * 3, [1] * 3], split="train", root=tmp_path,
              background=(1.0, 1.0, 1.0), names=["a"])
    assert Dataset(**kw, masks=np.ones((1, 4, 4), np.float32)).masks.shape == (1, 4, 4)
    with pytest.raises(DatasetError, match="masks have shape"):
        Dataset(**kw, masks=np.ones((1, 4, 5), np.float32))


@pytest.mark.parametrize("size, target, want", [
    ((800, 800), 4, 4), ((504, 378), 4, 6), ((504, 378), 2, 2), ((1000, 750), 3, 5),
    ((18, 12), 4, 6), ((1001, 750), 4, 1), ((13, 13), 4, 13), ((20, 12), 8, 4)])
def test_common_downscale_divides_both_sizes(size, target, want):
    from plenoctree.datasets import common_downscale

    f = common_downscale(*size, target)
    assert f == want and size[0] % f == 0 and size[1] % f == 0


def test_load_cameras_where_4_does_not_divide(tmp_path):
    """An LLFF capture 18×12 px (4 does not divide 18): the cameras load small (downscale 6)
    with the poses and field of view of the full-size load."""
    from plenoctree.datasets import load_cameras

    root = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=18, height=12,
                                        n_samples=8)
    with pytest.raises(DatasetError, match="downscale 4 does not divide"):
        load_dataset(root, "train", downscale=4)
    small, full = load_cameras(root, "train"), load_dataset(root, "train")
    c, f = small.cameras, full.cameras
    assert (c.width, c.height) == (3, 2) and small.names == full.names
    np.testing.assert_allclose(c.c2w, f.c2w)
    np.testing.assert_allclose([c.fx / c.width, c.fy / c.height, c.ndc_focal[0] / c.width],
                               [f.fx / f.width, f.fy / f.height, f.ndc_focal[0] / f.width])
    assert c.ndc and f.ndc


def test_llff_with_a_colmap_model_of_the_same_photos_is_llff(tmp_path, caplog):
    """mip-NeRF 360's layout: ``poses_bounds.npy`` + ``images_N/`` and COLMAP's ``sparse/0``.
    The same photos posed twice (up to a similarity): one dataset, read as LLFF, and said so;
    different cameras (or photos the model lacks): still ambiguous, naming both choices."""
    from test_colmap import write_model

    from plenoctree.datasets.llff import read_poses_bounds

    root = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=8, height=6,
                                        n_samples=16)
    c2w, _, hwf = read_poses_bounds(root / "poses_bounds.npy")
    names = [f"{i:03d}.png" for i in range(len(c2w))]
    assert sorted(p.name for p in (root / "images").iterdir()) == names
    # COLMAP's world: another frame and scale (a similarity of the LLFF file's)
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    sim = np.eye(4)
    sim[:3, :3], sim[:3, 3] = 2.5 * rot, [1.0, -2.0, 0.5]
    other = sim @ c2w
    other[:, :3, :3] /= 2.5
    f = float(hwf[0, 2])
    write_model(root / "sparse" / "0", other, [f, f, 4.0, 3.0], 8, 6, names, np.zeros((0, 3)))
    with caplog.at_level("INFO", logger="plenoctree.datasets.dataset"):
        assert detect_format(root) == "llff"
    assert "pose the same photos" in caplog.text
    assert load_dataset(root, "train").cameras.ndc               # loads with no flag
    moved = other.copy()
    moved[3, :3, 3] += 0.5                                       # one camera elsewhere
    write_model(root / "sparse" / "0", moved, [f, f, 4.0, 3.0], 8, 6, names, np.zeros((0, 3)))
    with pytest.raises(DatasetError, match="do not pose the same photos.*--format llff"):
        detect_format(root)
    write_model(root / "sparse" / "0", other[:5], [f, f, 4.0, 3.0], 8, 6, names[:5],
                np.zeros((0, 3)))                                # a model of 5 of the 9 photos
    with pytest.raises(DatasetError, match="ambiguous"):
        detect_format(root)
