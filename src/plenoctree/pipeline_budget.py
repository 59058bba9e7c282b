"""``run --minutes N``: the whole chain within a wall-time budget.

The stages besides training and fine-tuning take about fixed times for a dataset, predicted
here from counts (pixels rendered, views scored, the tree's bytes) at the rates measured on
this project's 2-core machine (:data:`RATES`; a faster machine finishes early). The NeRF-SH
trains for what is left after them and after what fine-tuning needs for its epochs, but for
at least :data:`TRAIN_SHARE` of the time they leave (:func:`split_budget`); fine-tuning then
stops its epochs so that the stages after it still fit (:func:`finetune_minutes`: its
``minutes``, from the predicted tail, :func:`tail_seconds`).

The deadline is the command's start plus ``N`` minutes, less the seconds that the stages this
run skips as up to date took when an earlier run made them (:class:`Budget`, evaluated when a
stage needs it): a resumed run keeps the budget of the chain, not of the command. The NeRF-SH's budget, once decided, is kept in
``OUT/budget.json`` so that a resumed run finds its training stage unchanged.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, NamedTuple

from ._util import atomic_save_json

__all__ = ["RATES", "TRAIN_SHARE", "MIN_TRAIN_S", "Counts", "Budget", "command_start",
           "split_budget", "tail_seconds", "finetune_minutes", "decided_train_minutes",
           "run_counts", "budget_training"]

logger = logging.getLogger("plenoctree.pipeline")

RATES = {
    "train_overhead_s": 25.0,   # the train stage past its budget: loading, compiling, the last
                                # validation (flower, a 270-s budget: 292 s)
    "nerf_s_per_mpx": 13.0,     # the NeRF-SH's test renders (flower's 5 views, 0.9 Mpx: 9 s)
    "extract_s": 60.0,          # extraction at 256³ (lego 400²: 43–49 s, flower: 34–64 s)
    "refine_s": 60.0,           # one refinement pass (lego: 56 s, lounge: 33 s)
    "ft_start_s": 30.0,         # fine-tuning's loading and first validation (lego: 33 s)
    "ft_rays_per_s": 500e3,     # its epochs (lego 800–850 k rays/s, flower 500–830 k, lounge
                                # 440 k)
    "ft_val_rays_per_s": 1.9e6,  # its validations (lego's 100 val views, 16 M rays: 8.5 s)
    "compress_s_per_gb": 21.0,  # of the fine-tuned tree (lego 1.5 GB: 32 s, flower 0.65: 13 s)
    "score_s": 3.0,             # a tree's scoring: a fixed part, per GB of tree loaded and per
    "score_s_per_gb": 4.0,      # megapixel rendered (lego's compressed tree on its 200 views,
    "score_s_per_mpx": 1.4,     # 32 Mpx: 46 s), and the first one's loading of the test
    "score_first_s": 10.0,      # photos (flower's raw tree on 5 views: 17.6 s, the next 4.9)
    "web_s": 2.0,               # the web bundle (lego: 17.5 s, flower: 3.5)
    "web_s_per_gb": 10.0,
    "video_s_per_mpx": 2.0,     # the orbit video's frames, rendered and encoded
    "tree_gb": 1.2,             # a tree's bytes before it exists (flower 0.65–1.26 GB, lego
                                # 1.5 refined)
}
"""Seconds of each stage on the project's 2-core machine, by what it renders and writes
(docs/capture_records.md, "The whole run within --minutes")."""

TRAIN_SHARE = 0.7
"""The NeRF-SH's least share of the time the fixed stages leave; fine-tuning gets the rest,
at most what its epochs need. On flower's photos in ten minutes a NeRF-SH minute paid more
than fine-tuning's epochs past the sixth (docs/capture_records.md, "The whole run within
--minutes": 4.7–4.8 minutes and 6 epochs 28.31–28.57 dB, 3.6 minutes and 8 epochs 27.64)."""
MIN_TRAIN_S = 60.0
"""The shortest NeRF-SH budget a time budget gives (seconds)."""


@dataclass(frozen=True)
class Counts:
    """What the stages of a run render, at its working resolution: ``train_views``,
    ``val_views`` (fine-tuning's validation), ``width`` x ``height`` pixels; the views scored
    (``nerf_views`` by the NeRF-SH, ``stage_views`` for each tree before the result,
    ``result_views`` for the compressed tree), the trees scored (``trees``: raw, [refined],
    fine-tuned, compressed), ``refine_passes``, fine-tuning's ``epochs`` and ``val_every``,
    ``video_frames`` and ``video_px`` (a frame's pixels), ``web``."""

    train_views: int
    val_views: int
    width: int
    height: int
    nerf_views: int
    stage_views: int
    result_views: int
    trees: int
    refine_passes: int
    epochs: int
    val_every: int
    video_frames: int
    video_px: int
    web: bool

    @property
    def mpx(self) -> float:
        """Megapixels of one view."""
        return self.width * self.height / 1e6


def command_start(now: float, within: float = 60.0) -> float:
    """When the command began (a ``time.time()``): this process's start, read from Linux's
    ``/proc``, when it lies less than ``within`` seconds before ``now`` (``plenoctree run``:
    Python's start and the imports count); else, or where ``/proc`` is missing (a Python
    session calling the pipeline), ``now``."""
    try:
        ticks = os.sysconf("SC_CLK_TCK")
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        start = boot + float(fields[19]) / ticks
    except (OSError, ValueError, IndexError, StopIteration):
        return now
    return start if now - within < start <= now else now


class Budget(NamedTuple):
    """A run's time budget: ``deadline()`` (a ``time.time()``, evaluated when a stage needs it)
    and the run's :class:`Counts`."""

    deadline: Callable[[], float]
    counts: Counts


def tail_seconds(c: Counts, tree_gb: float) -> float:
    """Predicted seconds of the stages after fine-tuning for a fine-tuned tree of ``tree_gb``
    GB: compression, the trees' scoring, the web bundle, the video."""
    r = RATES
    views = (c.trees - 1) * c.stage_views + c.result_views
    score = r["score_first_s"] + c.trees * (r["score_s"] + r["score_s_per_gb"] * tree_gb) + \
        r["score_s_per_mpx"] * views * c.mpx
    web = (r["web_s"] + r["web_s_per_gb"] * tree_gb) if c.web else 0.0
    video = r["video_s_per_mpx"] * c.video_frames * c.video_px / 1e6
    return r["compress_s_per_gb"] * tree_gb + score + web + video


def _finetune_seconds(c: Counts, tree_gb: float) -> float:
    """Predicted seconds of all of fine-tuning's epochs and validations."""
    r = RATES
    vals = 1 + (c.epochs // c.val_every if c.val_every > 0 else 0)
    return (r["ft_start_s"] + c.epochs * c.train_views * c.mpx * 1e6 / r["ft_rays_per_s"]
            + vals * c.val_views * c.mpx * 1e6 / r["ft_val_rays_per_s"] + 4.0 * tree_gb)


def split_budget(c: Counts, seconds_left: float) -> tuple[float, dict]:
    """The NeRF-SH's budget (seconds) from the ``seconds_left`` before the deadline at the
    start of training, and the predicted seconds of the other stages (for the log)."""
    r = RATES
    gb = r["tree_gb"]
    fixed = {"training's overhead": r["train_overhead_s"],
             "NeRF-SH scoring": (r["nerf_s_per_mpx"] * c.nerf_views * c.mpx
                                 + (r["score_s"] if c.nerf_views else 0.0)),
             "extraction": r["extract_s"] + r["refine_s"] * c.refine_passes,
             "stages after fine-tuning": tail_seconds(c, gb)}
    free = seconds_left - sum(fixed.values())
    ft = _finetune_seconds(c, gb)
    train = max(free - ft, TRAIN_SHARE * free, MIN_TRAIN_S)
    return train, {**fixed, "fine-tuning (all epochs)": ft}


def finetune_minutes(c: Counts, deadline: float, tree_gb: float, given: float) -> float:
    """Fine-tuning's ``minutes`` for a run ending at ``deadline``: until the predicted tail
    (:func:`tail_seconds` of its ``tree_gb`` input) must start; at most ``given`` (the user's
    own ``--finetune.minutes``, 0: none); at least a second (then one epoch runs)."""
    left = (deadline - time.time() - tail_seconds(c, tree_gb)) / 60.0
    if given > 0:
        left = min(left, given)
    return max(left, 1.0 / 60.0)


def decided_train_minutes(out: Path, minutes: float, decide: Any) -> float:
    """The NeRF-SH's budget under ``run --minutes minutes``: the one ``OUT/budget.json`` keeps
    for the same budget (a resumed run), else ``decide()``'s (minutes), then kept there."""
    path = Path(out) / "budget.json"
    try:
        kept = json.loads(path.read_text())
        if float(kept["minutes"]) == float(minutes):
            return float(kept["train_minutes"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    train = float(decide())
    atomic_save_json(path, {"minutes": float(minutes), "train_minutes": train})
    return train


def run_counts(cfg: Any) -> Counts:
    """:class:`Counts` of a wired, capture-decided :class:`~.pipeline_config.PipelineConfig`
    (its dataset read for the views' number and size, cheaply)."""
    from .datasets import load_cameras, load_dataset
    from .datasets.dataset import has_split
    from .optim.finetuning import TRAIN_VAL_VIEWS
    from .pipeline_config import stage_views

    data, fmt = cfg.train.data, cfg.format
    probe = load_dataset(data, "train", format=fmt, limit=1, downscale=cfg.downscale)
    n_train = len(load_cameras(data, "train", format=fmt).cameras)
    n_test = len(load_cameras(data, "test", format=fmt).cameras) if has_split(data, "test", fmt) \
        else 0
    ft = cfg.finetune
    if ft.val_views:
        n_val = ft.val_views
    elif has_split(data, "val", fmt):
        n_val = len(load_cameras(data, "val", format=fmt).cameras)
    else:
        n_val = max(TRAIN_VAL_VIEWS, n_train // 8)

    def views(n: int) -> int:
        return n_test if n == 0 else min(n, n_test)

    w, h = probe.cameras.width, probe.cameras.height
    size = cfg.video_size
    return Counts(
        train_views=n_train, val_views=n_val, width=w, height=h,
        nerf_views=0 if cfg.nerf or cfg.nerf_eval_views < 0 else views(cfg.nerf_eval_views),
        stage_views=views(stage_views(cfg, "ft")),
        result_views=views(stage_views(cfg, "compressed")),
        trees=3 + (cfg.refine.passes > 0), refine_passes=max(cfg.refine.passes, 0),
        epochs=int(ft.epochs), val_every=int(ft.val_every), video_frames=cfg.video_frames,
        video_px=size * size if size else w * h, web=bool(cfg.web))


def budget_training(cfg: Any, out: Path, deadline: float, counts: Counts) -> Any:
    """``cfg`` with the NeRF-SH's ``minutes`` decided by the run's ``deadline``
    (:func:`split_budget`, kept by :func:`decided_train_minutes`), said on the log."""
    def decide() -> float:
        left = deadline - time.time()
        train_s, others = split_budget(counts, left)
        parts = ", ".join(f"{k} ~{v:.0f} s" for k, v in others.items())
        logger.info(f"[run] --minutes {cfg.minutes:g}: {left / 60:.1f} minutes left; the "
                    f"NeRF-SH gets {train_s / 60:.1f} (the other stages, predicted: {parts})")
        if train_s <= MIN_TRAIN_S and left < train_s + sum(others.values()):
            logger.warning(f"[run] --minutes {cfg.minutes:g} is too short for this dataset: "
                           f"the NeRF-SH gets the least ({MIN_TRAIN_S / 60:g} minute) and the "
                           f"run will take longer")
        return train_s / 60.0

    minutes = decided_train_minutes(out, cfg.minutes, decide)
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, minutes=minutes))
