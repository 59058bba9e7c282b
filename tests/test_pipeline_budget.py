"""``run --minutes``: the budget's split between the stages, its deadline, and a tiny run."""

from __future__ import annotations

import json
import time

import pytest

import plenoctree.pipeline_budget as pb
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.errors import ConfigError
from plenoctree.pipeline import layer_settings, run_pipeline
from plenoctree.pipeline_budget import (Counts, command_start, decided_train_minutes,
                                        finetune_minutes, split_budget, tail_seconds)
from test_pipeline import TINY_TRAIN, _tiny_cfg


def _counts(**kw) -> Counts:
    """Flower's photos at the working resolution (29 training views of 504x378, 5 test)."""
    base = dict(train_views=29, val_views=8, width=504, height=378, nerf_views=1,
                stage_views=5, result_views=5, trees=3, refine_passes=0, epochs=12,
                val_every=2, video_frames=0, video_px=0, web=True)
    return Counts(**{**base, **kw})


def test_the_deadline_counts_what_earlier_runs_into_out_finished(tmp_path):
    """The stages a run skips as up to date count with the seconds they took when they ran;
    a given artefact (``--nerf``'s training) and stages that run again do not."""
    from plenoctree.pipeline import _Runner

    r = _Runner(tmp_path)
    r.times.update({"process": 30.0, "train": 12.5, "extract": 40.0})
    r.skipped += ["process", "train"]
    assert r.earlier_seconds() == pytest.approx(42.5)
    r.given_stages.append("train")
    assert r.earlier_seconds() == pytest.approx(30.0)
    # the command's start: this process's when it began within the minute before the call,
    # else the call's own time
    now = time.time()
    assert now - 60 <= command_start(now) <= now and command_start(now, within=1e9) < now
    assert command_start(now + 3600) == now + 3600


def test_the_nerf_sh_gets_what_the_other_stages_leave():
    c = _counts()
    train, others = split_budget(c, 540.0)
    fixed = sum(v for k, v in others.items() if k != "fine-tuning (all epochs)")
    ft = others["fine-tuning (all epochs)"]
    # flower's ten minutes less `process`: the NeRF-SH gets its share, fine-tuning the rest
    free = 540.0 - fixed
    assert train == pytest.approx(pb.TRAIN_SHARE * free) and free - train < ft and 180 < train
    # with more time, fine-tuning gets all its epochs and the NeRF-SH what they leave
    train, others = split_budget(c, 900.0)
    assert train == pytest.approx(900.0 - fixed - ft)
    assert train > pb.TRAIN_SHARE * (900.0 - fixed)
    # lego 400² (100 views of 400², 100 val views, a refinement pass, 200 test views scored)
    lego = _counts(train_views=100, val_views=100, width=400, height=400, stage_views=5,
                   result_views=5, trees=4, refine_passes=1)
    train, others = split_budget(lego, 595.0)
    free = 595.0 - sum(v for k, v in others.items() if k != "fine-tuning (all epochs)")
    assert train == pytest.approx(pb.TRAIN_SHARE * free)      # fine-tuning gets less
    assert others["fine-tuning (all epochs)"] > free - train
    # no time at all: the least budget
    assert split_budget(lego, 10.0)[0] == pb.MIN_TRAIN_S
    # what comes after fine-tuning grows with the tree, the views scored and the video
    assert tail_seconds(c, 1.0) > tail_seconds(c, 0.5)
    assert tail_seconds(_counts(result_views=200), 0.5) > tail_seconds(c, 0.5)
    assert tail_seconds(_counts(video_frames=60, video_px=400 * 400), 0.5) > tail_seconds(c, 0.5)


def test_fine_tuning_stops_in_time_for_the_stages_after_it():
    c = _counts()
    now = time.time()
    left = finetune_minutes(c, now + 600, 0.5, 0.0)
    assert left == pytest.approx((600 - tail_seconds(c, 0.5)) / 60, abs=0.01)
    assert finetune_minutes(c, now + 600, 0.5, 2.0) == 2.0     # the user's own limit, if less
    assert finetune_minutes(c, now - 60, 0.5, 0.0) == pytest.approx(1 / 60)  # past: one epoch


def test_the_decided_budget_is_kept_for_a_resumed_run(tmp_path):
    calls = []

    def decide():
        calls.append(1)
        return 4.25

    assert decided_train_minutes(tmp_path, 10, decide) == 4.25
    assert decided_train_minutes(tmp_path, 10, lambda: 99.0) == 4.25     # resumed: kept
    assert json.loads((tmp_path / "budget.json").read_text()) == {"minutes": 10.0,
                                                                   "train_minutes": 4.25}
    assert decided_train_minutes(tmp_path, 12, lambda: 5.5) == 5.5       # a new budget
    assert calls == [1]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("budget")
    write_procedural_dataset(root / "data", n_train=3, n_val=1, n_test=2, width=16, height=16)
    return root / "data"


def test_a_run_within_minutes(scene, tmp_path, monkeypatch):
    """A tiny run with a budget already spent: the NeRF-SH gets the least budget (shortened
    here), fine-tuning stops after one epoch, the decision is kept and a rerun skips it all."""
    monkeypatch.setattr(pb, "MIN_TRAIN_S", 2.0)
    out = tmp_path / "run"
    train = {k: v for k, v in TINY_TRAIN.items() if k not in ("minutes", "max_steps")}
    cfg = _tiny_cfg(scene, out, {"finetune": {"epochs": 3}}, minutes=0.02, video_frames=0)
    layer_settings(cfg, {"train": {**train, "minutes": -1}}, where="test")
    assert cfg.train.minutes == -1 and cfg.train.max_steps > 10**6
    s = run_pipeline(cfg)
    assert json.loads((out / "budget.json").read_text()) == {"minutes": 0.02,
                                                            "train_minutes": 2.0 / 60}
    assert s["config"]["train"]["minutes"] == pytest.approx(2.0 / 60)
    assert s["finetune"]["stop_reason"].startswith("time limit")
    assert s["finetune"]["epochs_run"] == 1
    again = run_pipeline(cfg)
    assert {"train", "extract", "finetune", "compress"} <= set(again["skipped"])
    with pytest.raises(ConfigError, match="--minutes must be >= 0"):
        run_pipeline(_tiny_cfg(scene, tmp_path / "bad", minutes=-1.0))
