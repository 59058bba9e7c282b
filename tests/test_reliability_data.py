"""Dataset values: singular rotations, paths escaping the dataset folder, 1x1 images."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plenoctree.datasets.blender import load_blender
from plenoctree.datasets.cameras import Cameras
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.errors import ConfigError, DatasetError


@pytest.fixture()
def scene(tmp_path):
    root = tmp_path / "scene"
    write_procedural_dataset(root, n_train=3, n_val=1, n_test=1, width=8, height=8, seed=0)
    return root


def _edit_frame(root, key, value, index=1):
    p = root / "transforms_train.json"
    obj = json.loads(p.read_text())
    obj["frames"][index][key] = value
    p.write_text(json.dumps(obj))
    return p


def test_blender_all_zero_rotation_is_refused(scene):
    m = np.eye(4)
    m[:3, :3] = 0.0                                         # was accepted silently
    p = _edit_frame(scene, "transform_matrix", m.tolist())
    with pytest.raises(DatasetError, match=rf"{p}: frames\[1\]: transform_matrix rotation .* "
                                           "singular"):
        load_blender(scene, "train")
    flat = np.eye(4)
    flat[2, :3] = flat[1, :3]                               # rank 2
    _edit_frame(scene, "transform_matrix", flat.tolist())
    with pytest.raises(DatasetError, match="singular"):
        load_blender(scene, "train")
    scaled = np.diag([2.0, -2.0, 2.0, 1.0])                # scaled / mirrored axes are fine
    _edit_frame(scene, "transform_matrix", scaled.tolist())
    assert len(load_blender(scene, "train")) == 3


def test_cameras_refuse_singular_rotation():
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[1, :3, :3] = 0.0
    with pytest.raises(ConfigError, match=r"c2w\[1\]: the rotation part .* singular"):
        Cameras(c2w=c2w, fx=10.0, fy=10.0, cx=4.0, cy=4.0, width=8, height=8)


@pytest.mark.parametrize("fp", ["../../../etc/passwd", "/etc/passwd", "train/../../x",
                                "..", "C:/Windows/x"])
def test_file_paths_must_stay_inside_the_dataset(scene, fp):
    p = _edit_frame(scene, "file_path", fp)
    with pytest.raises(DatasetError, match=rf"{p}: frames\[1\]: file_path .* points outside the "
                                           "dataset folder"):
        load_blender(scene, "train")


def test_inside_paths_load_and_symlinks_out_of_the_folder_are_refused(scene, tmp_path):
    obj = json.loads((scene / "transforms_train.json").read_text())
    fp = obj["frames"][0]["file_path"]
    _edit_frame(scene, "file_path", "./train/../" + fp.lstrip("./"), index=0)
    assert len(load_blender(scene, "train")) == 3
    _edit_frame(scene, "file_path", fp, index=0)
    moved = tmp_path / "elsewhere"
    (scene / "train").rename(moved)
    (scene / "train").symlink_to(moved)     # followed before issue 37; the dataset's files
    with pytest.raises(DatasetError, match="outside the dataset folder"):   # must lie inside it
        load_blender(scene, "train")


def test_nerfstudio_mask_path_outside_is_refused(tmp_path):
    from plenoctree.datasets.nerfstudio import load_nerfstudio, write_nerfstudio

    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[:, 2, 3] = 3.0
    imgs = np.full((2, 8, 8, 3), 0.5, np.float32)
    root = tmp_path / "ns"
    write_nerfstudio(root, c2w, imgs, [10.0, 10.0, 4.0, 4.0])
    p = root / "transforms.json"
    obj = json.loads(p.read_text())
    obj["frames"][0]["mask_path"] = "../../secret.png"
    p.write_text(json.dumps(obj))
    with pytest.raises(DatasetError, match="mask_path '../../secret.png' points outside"):
        load_nerfstudio(root, "train")


def test_training_on_1x1_images(tmp_path):
    """1x1 images crashed training (SSIM of the validation views)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from nerf_fixtures import tiny_cpu_config

    from plenoctree.nerf.trainer import train

    root = tmp_path / "one"
    write_procedural_dataset(root, n_train=3, n_val=1, n_test=1, width=1, height=1, seed=0)
    cfg = tiny_cpu_config(root, tmp_path / "run", steps=3)
    res = train(cfg, quiet=True)
    assert np.isfinite(res.val_psnr) or np.isnan(res.val_psnr)
    assert (tmp_path / "run" / "checkpoint.pt").exists()
