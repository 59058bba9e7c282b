"""datasets.has_split: the loaders' own split rules, which the fine-tuner uses for val/test."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from plenoctree.datasets.dataset import has_split, load_dataset
from plenoctree.datasets.nsvf import write_nsvf
from plenoctree.datasets.procedural import look_at, write_procedural_dataset
from plenoctree.errors import DatasetError


def _poses(n):
    return np.stack([look_at([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0])
                     for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]).astype(np.float32)


def _imgs(n):
    return np.full((n, 8, 8, 3), 0.5, np.float32)


def test_blender_and_nsvf_splits(tmp_path):
    root = write_procedural_dataset(tmp_path / "b", n_train=2, n_val=1, n_test=1, width=8,
                                    height=8)
    assert [has_split(root, s) for s in ("train", "val", "test")] == [True, True, True]
    (root / "transforms_val.json").unlink()
    assert not has_split(root, "val")
    full = write_nsvf(tmp_path / "n", {"train": (_poses(3), _imgs(3)),
                                       "val": (_poses(2), _imgs(2)),
                                       "test": (_poses(2), _imgs(2))}, 8, 8, 4, 4)
    assert [has_split(full, s) for s in ("train", "val", "test")] == [True, True, True]
    # without 2_ images the test split falls back to the val ones: val is then not its own
    shared = write_nsvf(tmp_path / "s", {"train": (_poses(3), _imgs(3)),
                                         "val": (_poses(2), _imgs(2))}, 8, 8, 4, 4)
    assert [has_split(shared, s) for s in ("train", "val", "test")] == [True, False, True]
    assert len(load_dataset(shared, "test")) == 2           # the loader's fallback to 1_
    only = write_nsvf(tmp_path / "o", {"train": (_poses(3), _imgs(3))}, 8, 8, 4, 4)
    assert [has_split(only, s) for s in ("train", "val", "test")] == [True, False, False]


def test_nerfstudio_splits_follow_its_filenames_lists(tmp_path):
    src = write_procedural_dataset(tmp_path / "b", n_train=3, n_val=1, n_test=1, width=8,
                                   height=8)
    meta = json.loads((src / "transforms_train.json").read_text())
    frames = [{"file_path": f["file_path"] + ".png", "transform_matrix": f["transform_matrix"]}
              for f in meta["frames"]]
    obj = {"camera_angle_x": meta["camera_angle_x"], "w": 8, "h": 8, "frames": frames,
           "train_filenames": [f["file_path"] for f in frames[:2]],
           "test_filenames": [frames[2]["file_path"]], "val_filenames": []}
    ns = tmp_path / "ns"
    ns.mkdir()
    shutil.copytree(src / "train", ns / "train")
    (ns / "transforms.json").write_text(json.dumps(obj))
    assert has_split(ns, "train", "nerfstudio") and has_split(ns, "test", "nerfstudio")
    assert not has_split(ns, "val", "nerfstudio")
    # val is a split of its own only when its frames are not the test ones: not without a
    # list (every 8th frame is both, as instant-ngp's files), nor with the test's list (as
    # `process` writes it), only with a list of other frames
    bare = {k: v for k, v in obj.items() if not k.endswith("_filenames")}
    for listed, own in ((None, False), ([frames[2]["file_path"]], False),
                        ([frames[1]["file_path"]], True)):
        (ns / "transforms.json").write_text(json.dumps(
            bare if listed is None else {**obj, "val_filenames": listed}))
        assert has_split(ns, "val", "nerfstudio") == own, listed
        assert len(load_dataset(ns, "val", "nerfstudio")) == 1
    (ns / "transforms.json").write_text("{not json")
    with pytest.raises(DatasetError):
        has_split(ns, "val", "nerfstudio")


def test_take_views_first_or_spread_before_reading():
    """Every loader's ``limit``/``spread`` rule (one helper): the first N frames, or N evenly
    spaced ones, for the lists and index arrays the loaders hold; None keeps all."""
    import numpy as np

    from plenoctree.datasets import evenly_spaced
    from plenoctree.datasets._files import take_views

    frames = [f"r_{i}" for i in range(10)]
    assert take_views(frames, None) is frames
    assert take_views(frames, 3) == ["r_0", "r_1", "r_2"]
    assert take_views(frames, 3, spread=True) == ["r_0", "r_3", "r_6"]
    assert take_views(frames, 20, spread=True) == frames
    sel = np.arange(0, 40, 4)
    assert take_views(sel, 2, spread=True).tolist() == [0, 20]
    assert evenly_spaced(200, 5) == [0, 40, 80, 120, 160] and evenly_spaced(5, 0) == []
