"""The trainer's state and per-step figures (:class:`~.trainer.Trainer`): what a checkpoint
keeps of a run besides its weights (:class:`TrainerState`) and what one step measured."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

__all__ = ["LogWindow", "TrainerState", "StepFigures"]


@dataclass
class LogWindow:
    """Running sums of the steps since the last log row (seconds, rays, samples, loss, MSE,
    steps); checkpointed, so a resumed run's log equals the uninterrupted one's."""

    t: float = 0.0
    rays: int = 0
    samples: int = 0
    loss: float = 0.0
    mse: float = 0.0
    n: int = 0


@dataclass
class TrainerState:
    """The trainer's scalar state, saved as the checkpoint's ``trainer`` entry (JSON).

    Attributes:
        n_rays: rays per step, adapted to ``target_samples`` (occupancy sampler).
        spr: running mean of the samples per ray (0 before the first step); with steps of
            fixed shape, those trained (after early termination).
        spr_marched: steps of fixed shape: running mean of the candidate samples the march
            made per ray (0 before the first adaptation).
        next_val_s: training seconds at which the next timed validation is due.
        last_ckpt_step: step of the last checkpoint written.
        win: the sums of the log row being accumulated.
    """

    n_rays: float
    spr: float = 0.0
    spr_marched: float = 0.0
    next_val_s: float = 0.0
    last_ckpt_step: int = 0
    win: LogWindow = field(default_factory=LogWindow)

    def to_json(self) -> dict:
        return asdict(self)

    def update(self, saved: dict) -> None:
        """Take the entries of a checkpoint's ``trainer`` dict (missing ones keep theirs)."""
        for k, v in saved.items():
            if k == "win":
                self.win = LogWindow(**v) if v else LogWindow()
            elif k in ("n_rays", "spr", "spr_marched", "next_val_s", "last_ckpt_step"):
                setattr(self, k, v)


@dataclass
class StepFigures:
    """What one training step measured (global figures under torchrun).

    ``loss`` and ``mse`` are Python floats under torchrun; in one process they stay detached
    0-d tensors on the device until :meth:`Trainer.read_losses` reads a window of them back
    at once (a host round trip each step would stall a GPU)."""

    lr: float
    loss: float | torch.Tensor
    mse: float | torch.Tensor
    rays: int          # rays whose colour entered the loss
    samples: int       # network evaluations of the rendering
    occupancy_s: float  # seconds spent updating the occupancy grid


@dataclass
class TrainResult:
    """What :func:`~.trainer.train` returns (``model``: the trained
    :class:`~.model.NeRFModel`)."""

    run_dir: Path
    step: int
    train_time_s: float
    val_psnr: float
    model: Any
    log: dict = field(default_factory=dict)
