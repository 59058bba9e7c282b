"""Fine-tuning's held-out validation: training views kept out of the updates choose the tree.

The scene: a dataset without a val split whose training photos disagree. The views held out
(every 8th from the 4th: ``r_4``, ``r_12``) are renders of the true tree, every other training
view a render of a perturbed one; fine-tuning starts from the tree halfway between the two.
Fitting the training photos moves it away from the truth: the training PSNR rises, the
held-out one falls, and the input tree is the best there is on the held-out views.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from test_optim_finetune import SIZE, known_tree, log_lines, perturbed
from test_optim_finetune import cfg as _cfg

from plenoctree.datasets.procedural import CAMERA_ANGLE_X, procedural_cameras
from plenoctree.errors import ConfigError
from plenoctree.metrics import psnr
from plenoctree.octree import load_tree, save_tree
from plenoctree.optim.finetuning import finetune, held_out_views, holdout_for
from plenoctree.render import RenderOptions, render_rays

N_TRAIN = 16
HELD = [4, 12]                    # held_out_views(16, 8)


def cfg(*args, **kw):
    """The fine-tuning settings of these tests: every 8th training view held out (the
    automatic value for captures of a place; these scenes are renders)."""
    kw.setdefault("holdout_every", 8)
    return _cfg(*args, **kw)


def _camera_rays(c2w):
    from plenoctree.datasets import generate_rays

    fx = 0.5 * SIZE / math.tan(0.5 * CAMERA_ANGLE_X)
    return generate_rays(c2w, fx, fx, SIZE / 2, SIZE / 2, SIZE, SIZE)


def _render(tree, c2w):
    """``tree`` seen from camera ``c2w``: float32 ``[SIZE, SIZE, 3]`` on white."""
    return render_rays(tree, *_camera_rays(c2w), RenderOptions(), backend="numba").rgb.numpy()


def write_split_dataset(root: Path, truth, other, n_train=N_TRAIN, held=HELD):
    """A Blender dataset with train and test splits (no val split): training views ``held`` and
    the test views are renders of ``truth``, the other training views renders of ``other``."""
    from plenoctree._util import atomic_save_json, save_png

    for split, n, kind in (("train", n_train, "random"), ("test", 2, "orbit")):
        frames = []
        for i, c2w in enumerate(procedural_cameras(n, kind, 0)):
            tree = truth if split == "test" or i in held else other
            rgba = np.concatenate([_render(tree, c2w), np.ones((SIZE, SIZE, 1), np.float32)], -1)
            save_png(root / split / f"r_{i}.png", rgba)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        atomic_save_json(root / f"transforms_{split}.json",
                         {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames})
    return root


def held_psnr(tree, truth, held=HELD, n_train=N_TRAIN):
    """Mean PSNR (dB) of ``tree`` against ``truth`` on training views ``held``."""
    cams = procedural_cameras(n_train, "random", 0)
    return float(np.mean([psnr(_render(tree, cams[i]), _render(truth, cams[i])) for i in held]))


@pytest.fixture(scope="module")
def split_scene(tmp_path_factory):
    """``data``: :func:`write_split_dataset`; ``truth.npz``: the true tree; ``start.npz``: the
    input of fine-tuning, halfway between the truth and the other training views' tree."""
    root = tmp_path_factory.mktemp("holdout")
    truth = known_tree()
    other = perturbed(truth, seed=3, amount=1.5)
    write_split_dataset(root / "data", truth, other)
    start = truth.copy()
    start.data = 0.5 * (truth.data + other.data)
    save_tree(truth, root / "truth.npz")
    save_tree(start, root / "start.npz")
    return root


def _log(path: Path) -> list[dict]:
    return [json.loads(line) for line in open(path)]


def test_held_out_views_rule():
    assert held_out_views(40, 8).tolist() == [4, 12, 20, 28, 36]
    assert held_out_views(8, 8).tolist() == [4]                 # at least one
    assert held_out_views(10, 20).tolist() == [5]
    assert held_out_views(7, 8).tolist() == []                  # too few views: none
    assert held_out_views(40, 0).tolist() == []                 # off
    share = held_out_views(40, 8, fraction=0.2, seed=1)         # val_fraction wins
    assert len(share) == 8 and (np.diff(share) > 0).all()
    assert held_out_views(N_TRAIN, 8).tolist() == HELD


def test_training_psnr_rises_held_out_falls_and_the_input_tree_is_kept(split_scene, tmp_path):
    """Training-view PSNR rises every epoch, held-out PSNR falls below the input's: after
    ``patience`` validations in a row below the best the run stops and saves the input."""
    with log_lines() as lines:
        res = finetune(cfg(split_scene, tmp_path / "ft.npz", tree=split_scene / "start.npz",
                           data=split_scene / "data", epochs=3, val_every=1, optimizer="adam",
                           lr=0.1, backoffs=0, patience=3, test_views=-1, verbose=True))
    log = _log(tmp_path / "ft.log.jsonl")
    train = [r["train_psnr"] for r in log if r["event"] == "epoch"]
    val = [r["val_psnr"] for r in log if r["event"] == "val"]
    assert len(train) == 3 and train[2] > train[0], train         # the updates fit the photos
    assert len(val) == 4 and max(val[1:]) < val[0], val           # ... that the held-out ones
    assert res.validation == "held-out training views"            # contradict
    assert res.held_out == [f"r_{i}" for i in HELD]
    assert res.best_epoch == 0 and res.val_psnr_best == res.val_psnr_before == val[0]
    assert "3 validations in a row" in res.stop_reason and res.epochs_run == 3
    # the saved tree is the input, bit for bit
    np.testing.assert_array_equal(load_tree(tmp_path / "ft.npz").data,
                                  load_tree(split_scene / "start.npz").data)
    # the log names the held-out views and their PSNR before and after
    assert any("[14 train / 2 val views" in line for line in lines), lines[:2]
    assert any("held out of the updates: r_4, r_12" in line for line in lines), lines
    assert any(line.startswith("held-out training views PSNR before") for line in lines), lines
    # and so does the run's summary (plenoctree run reads the log's end record)
    from plenoctree.pipeline_summary import finetune_outcome, summary_markdown

    ft = finetune_outcome(tmp_path / "ft.npz")
    assert ft["held_out"] == ["r_4", "r_12"] and ft["validation"] == "held-out training views"
    text = summary_markdown({"rows": [], "finetune": ft, "total_s": 1.0})
    assert "2 training views held out of the updates (r_4, r_12)" in text, text


def test_held_out_views_receive_no_updates(split_scene, tmp_path, monkeypatch):
    """Every training batch's rays come from the other training views, and every one of those
    is used."""
    from plenoctree.optim._loop import ViewSet

    used: set[int] = set()
    real = ViewSet.rays

    def spy(self, index):
        images = np.unique(np.asarray(index) // (self.width * self.height))
        used.update(int(i) for i in self.cam_index[images])   # indices into the train split
        return real(self, index)

    monkeypatch.setattr(ViewSet, "rays", spy)
    res = finetune(cfg(split_scene, tmp_path / "ft.npz", tree=split_scene / "start.npz",
                       data=split_scene / "data", epochs=2, val_every=1, optimizer="adam",
                       lr=0.1, test_views=-1))
    assert res.held_out == ["r_4", "r_12"]
    assert used == set(range(N_TRAIN)) - set(HELD)


def test_holdout_off_validates_on_training_views_and_loses_on_the_held_out_ones(
        split_scene, tmp_path):
    """``holdout_every=0`` (the behaviour before the hold-out): validation on training views
    that stay in training rises, so a tree worse on the held-out views is saved."""
    truth, start = (load_tree(split_scene / f"{n}.npz") for n in ("truth", "start"))
    with log_lines() as lines:
        res = finetune(cfg(split_scene, tmp_path / "off.npz", tree=split_scene / "start.npz",
                           data=split_scene / "data", epochs=3, val_every=1, optimizer="adam",
                           lr=0.1, test_views=-1, holdout_every=0, verbose=True))
    assert any(f"[{N_TRAIN} train / 8 val views" in line for line in lines), lines[:2]
    assert res.validation == "training views (in training)" and res.held_out == []
    assert res.best_epoch > 0 and res.val_psnr_best > res.val_psnr_before, res
    out = load_tree(tmp_path / "off.npz")
    assert held_psnr(out, truth) < held_psnr(start, truth) - 0.5


def test_too_few_views_to_hold_out_behave_as_before(split_scene, tmp_path):
    """Fewer than 8 training views: nothing is held out and the run is the one with the
    hold-out off, byte for byte."""
    truth = load_tree(split_scene / "truth.npz")
    data = write_split_dataset(tmp_path / "data", truth, perturbed(truth, 3, 1.0), n_train=7,
                               held=[3])
    kw = dict(tree=split_scene / "start.npz", data=data, epochs=2, val_every=1,
              optimizer="adam", lr=0.1, test_views=-1)
    res = finetune(cfg(split_scene, tmp_path / "a.npz", **kw))
    off = finetune(cfg(split_scene, tmp_path / "b.npz", holdout_every=0, **kw))
    assert res.held_out == [] and res.validation == "training views (in training)"
    np.testing.assert_array_equal(load_tree(tmp_path / "a.npz").data,
                                  load_tree(tmp_path / "b.npz").data)
    assert [h["val_psnr"] for h in res.history] == [h["val_psnr"] for h in off.history]


def test_bad_holdout_and_patience_values(split_scene, tmp_path):
    for name, bad in (("holdout_every", 1), ("holdout_every", -2), ("holdout_every", 2.5),
                      ("patience", 0), ("patience", True)):
        with pytest.raises(ConfigError, match=name):
            finetune(cfg(split_scene, tmp_path / "x.npz", **{name: bad}))
    assert not (tmp_path / "x.npz").exists()


def test_views_are_held_out_by_default_for_captures_of_a_place_only():
    """-1 (the default): every 8th view for a walk-around (``Dataset.unbounded``), none for
    other captures (flower: holding 4 of its 29 photos out cost 0.35 dB on the test views)."""
    from plenoctree.optim.finetuning import FinetuneConfig

    assert FinetuneConfig().holdout_every == -1
    assert holdout_for(-1, True) == 8 and holdout_for(-1, False) == 0
    assert holdout_for(0, True) == 0 and holdout_for(6, False) == 6
