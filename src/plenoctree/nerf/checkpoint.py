"""NeRF-SH checkpoints: one ``checkpoint.pt`` per run directory, written atomically.

File format (``torch.save`` zip archive, loadable with ``torch.load(weights_only=True)``; a dict):

=================  ==========================================================================
``format``         ``"plenoctree.nerf.checkpoint"``
``format_version`` ``1`` (int)
``package``        plenoctree version that wrote it
``config``         the full :class:`~plenoctree.nerf.config.TrainConfig` as a JSON string
``step``           completed training steps (int)
``train_time_s``   training seconds so far (validation and checkpointing excluded)
``wall_time_s``    wall-clock seconds so far
``model``          ``NeRFModel.state_dict()``: ``fine.*``, ``coarse.*`` (hierarchical),
                   ``occupancy.{bbox,density,mask,n_updates}`` (occupancy sampler),
                   ``scene_bbox`` [2, 3]
``signature``      JSON ``{name: shape}`` of ``model`` (checked before loading)
``optimizer``      ``torch.optim.Adam.state_dict()``
``rng``            state of the training ``torch.Generator`` (uint8 tensor)
``trainer``        JSON of the trainer's scalar state (adaptive rays per step, timers)
``log``            JSON ``{"train": [rows], "val": [rows]}`` up to ``step``
=================  ==========================================================================

Every problem — missing, truncated or foreign file, other format version, a model of another
configuration — raises :class:`CheckpointError` naming the file; nothing is loaded half-way.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from .._util import atomic_write, clean_stale_tmp
from ..errors import ConfigError, PlenOctreeError
from .config import TrainConfig, config_from_dict, config_to_dict
from .model import NeRFModel

__all__ = ["CheckpointError", "CHECKPOINT_NAME", "TrainProgress", "save_checkpoint",
           "read_checkpoint", "model_from_checkpoint", "NeRFRun", "load_run", "load_nerf",
           "model_signature", "FORMAT", "FORMAT_VERSION", "open_run_dir"]

FORMAT = "plenoctree.nerf.checkpoint"
FORMAT_VERSION = 1
CHECKPOINT_NAME = "checkpoint.pt"


class CheckpointError(PlenOctreeError, ValueError):
    """A NeRF checkpoint is missing, truncated, of another format, or of another model."""


def model_signature(state: dict[str, torch.Tensor]) -> dict[str, list[int]]:
    """``{name: shape}`` of a state dict."""
    return {k: list(v.shape) for k, v in state.items()}


@dataclass(frozen=True)
class TrainProgress:
    """Where a run stands: what a checkpoint holds besides the configuration and the weights.

    Attributes:
        step: completed training steps. train_time_s / wall_time_s: seconds so far.
        optimizer: the Adam optimiser (None: an empty state is saved).
        rng: the training generator's state (None: an empty tensor is saved).
        trainer: the trainer's scalar state (JSON-able). log: ``{"train": [rows], "val": [rows]}``.
    """

    step: int = 0
    train_time_s: float = 0.0
    wall_time_s: float = 0.0
    optimizer: torch.optim.Optimizer | None = None
    rng: torch.Tensor | None = None
    trainer: dict[str, Any] = field(default_factory=dict)
    log: dict[str, list] = field(default_factory=lambda: {"train": [], "val": []})


def save_checkpoint(path: str | os.PathLike, config: TrainConfig, model: NeRFModel,
                    progress: TrainProgress = TrainProgress()) -> None:
    """Write a checkpoint atomically (temp file + rename: a kill never leaves half a file)."""
    from .. import __version__

    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    opt, rng = progress.optimizer, progress.rng
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "package": __version__,
        "config": json.dumps(config_to_dict(config)),
        "step": int(progress.step),
        "train_time_s": float(progress.train_time_s),
        "wall_time_s": float(progress.wall_time_s),
        "model": state,
        "signature": json.dumps(model_signature(state)),
        "optimizer": opt.state_dict() if opt is not None else {},
        "rng": rng.cpu() if rng is not None else torch.zeros(0, dtype=torch.uint8),
        "trainer": json.dumps(progress.trainer),
        "log": json.dumps(progress.log),
    }
    with atomic_write(path, "wb") as f:
        torch.save(payload, f)


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Load and validate a checkpoint file; JSON fields are decoded, ``config`` is a TrainConfig."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        partial = [p for p in clean_stale_tmp(path.parent) if p.name.startswith(path.name)]
        if partial:
            raise CheckpointError(f"{path}: no checkpoint yet: the run was stopped while "
                                  f"writing its first one (the partial {partial[0].name} was "
                                  "removed); start the training again without --resume")
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError, KeyError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise CheckpointError(f"{path}: truncated or corrupt checkpoint ({msg})") from None
    except Exception as e:  # pickle.UnpicklingError and friends from a foreign file
        raise CheckpointError(f"{path}: not a plenoctree checkpoint ({type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else ''})") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a plenoctree NeRF checkpoint")
    if ck.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {ck.get('format_version')!r} "
                              f"is not supported (this version reads {FORMAT_VERSION})")
    need = ("config", "step", "model", "signature", "optimizer", "rng", "trainer", "log",
            "train_time_s", "wall_time_s")
    missing = [k for k in need if k not in ck]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {missing}")
    try:
        ck["config"] = config_from_dict(json.loads(ck["config"]), where=f"{path}: config")
        for k in ("signature", "trainer", "log"):
            ck[k] = json.loads(ck[k])
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"{path}: bad checkpoint metadata ({e})") from None
    if model_signature(ck["model"]) != ck["signature"]:
        raise CheckpointError(f"{path}: model tensors do not match the recorded signature")
    ck["path"] = path
    return ck


def _check_same_model(path: Path, have: dict, want: dict) -> None:
    diff = [f"{k}: checkpoint has {have[k]!r}, expected {want.get(k)!r}"
            for k in have if have[k] != want.get(k)]
    if diff:
        raise CheckpointError(f"{path}: checkpoint is of another model configuration ("
                              + "; ".join(diff) + ")")


def model_from_checkpoint(ck: dict[str, Any], expect: TrainConfig | None = None,
                          device: str | torch.device = "cpu") -> NeRFModel:
    """Build the :class:`NeRFModel` of a :func:`read_checkpoint` result and load its weights.

    ``expect`` (optional): the configuration the caller wants; a checkpoint of another model
    configuration (basis, SH degree, encoding, sizes, sampler) raises :class:`CheckpointError`.
    """
    path = ck["path"]
    cfg: TrainConfig = ck["config"]
    if expect is not None:
        _check_same_model(path, {**config_to_dict(cfg.model), "sampler": cfg.sampler,
                                 "occ_res": cfg.occ_res, "far_levels": cfg.far_levels},
                          {**config_to_dict(expect.model), "sampler": expect.sampler,
                           "occ_res": expect.occ_res, "far_levels": expect.far_levels})
    state = ck["model"]
    bbox = state.get("scene_bbox")
    if bbox is None or tuple(bbox.shape) != (2, 3):
        raise CheckpointError(f"{path}: checkpoint has no scene_bbox [2, 3]")
    try:
        model = NeRFModel(cfg.model, bbox.numpy(),
                          occ_res=cfg.occ_res if cfg.sampler == "occupancy" else 0,
                          far_levels=max(cfg.far_levels, 0))    # (-1: a run from before)
    except ConfigError as e:
        raise CheckpointError(f"{path}: {e}") from None
    want = model_signature(model.state_dict())
    if want != ck["signature"]:
        missing = sorted(set(want) - set(ck["signature"]))[:5]
        extra = sorted(set(ck["signature"]) - set(want))[:5]
        shape = sorted(k for k in set(want) & set(ck["signature"])
                       if want[k] != ck["signature"][k])[:5]
        raise CheckpointError(f"{path}: weights do not fit the recorded configuration "
                              f"(missing {missing}, unexpected {extra}, other shape {shape})")
    model.load_state_dict(state, strict=True)
    return model.to(device)


@dataclass
class NeRFRun:
    """A trained run as :func:`load_run` reads it: the network, its training configuration and
    the steps it was trained for."""

    model: NeRFModel
    config: TrainConfig
    step: int


def load_run(run_dir: str | os.PathLike, device: str | torch.device = "cpu") -> NeRFRun:
    """The network of a run directory (or a ``checkpoint.pt`` path) in eval mode, with the
    configuration it was trained with and its step count."""
    ck = read_checkpoint(run_dir)
    model = model_from_checkpoint(ck, device=device)
    return NeRFRun(model.eval(), ck["config"], int(ck["step"]))


def load_nerf(run_dir: str | os.PathLike, device: str | torch.device = "cpu") -> NeRFModel:
    """Load the trained NeRF-SH of a run directory (or a ``checkpoint.pt`` path) for inference.

    Returns a :class:`~plenoctree.nerf.model.NeRFModel` in eval mode with ``query``,
    ``basis``, ``sh_degree``, ``basis_dim``, ``data_format``, ``sg_lobes()`` and ``scene_bbox``.
    Its training configuration and step count: :func:`load_run`.
    """
    return load_run(run_dir, device).model


def open_run_dir(out: str | os.PathLike, resume: bool) -> tuple[Path, dict | None]:
    """The run folder ``out`` of a training: with ``resume`` its checkpoint (read, checked),
    else created, refused (:class:`~plenoctree.errors.ConfigError`) when it already holds a
    run. Returns ``(folder, checkpoint or None)``."""
    out = Path(out)
    ck_path = out / CHECKPOINT_NAME
    if resume:
        return out, read_checkpoint(ck_path)
    if ck_path.exists():
        raise ConfigError(f"{out}: already holds a training run ({CHECKPOINT_NAME}); pass "
                          "--resume to continue it or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    return out, None
