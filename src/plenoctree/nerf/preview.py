"""Coarse preview trees of a NeRF-SH while it trains (issue 49: a live view of the scene).

A preview is not an extraction (no visibility filter, no averaged samples, no far field's
shells): the network is queried once at the centre of every occupied cell of the trainer's
occupancy grid (a 128³ grid over the scene box in the cpu preset; without one, a dense
:data:`DENSE_GRID`³ grid), and the cells whose opacity across one cell reaches
:data:`MIN_ALPHA` become the leaves of a tree of that resolution (:func:`~plenoctree.octree.
build.tree_from_leaves`), with the dataset's NDC space for a forward-facing capture. On lego's
trained model that is ~0.1 M points: well under a second on 2 cores, so a preview every
2.5 minutes costs well under the 5 % of training time a live view may take (the trainer
reports the share: ``preview_s`` in ``summary.json``). Measured on the trained models of
``runs/lego_cpu_400`` (55 k occupied cells, 77 k leaves) and flower (113 k cells, 158 k
leaves, NDC): 0.2 and 0.8 s a preview, 0.1–0.5 % of training at one every 150 s; flower's
preview scores ~20 dB on its test photos (the fine-tuned tree: 28), blocky but recognisable.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["PREVIEW_NAME", "MIN_ALPHA", "DENSE_GRID", "FIRST_S", "preview_tree", "write_preview",
           "LiveView"]

PREVIEW_NAME = "preview.npz"
#: Cells thinner than this opacity (across one cell) are left empty: fog costs a viewer.
MIN_ALPHA = 0.01
#: Cells per axis of the preview of a model without an occupancy grid.
DENSE_GRID = 64
#: Training seconds before the first preview (flower's photos: a recognisable scene at 30 s).
FIRST_S = 30.0


def _cells(model: Any) -> tuple[torch.Tensor, torch.Tensor, int]:
    """``(ijk [M, 3] int64 of the cells to query, box [2, 3], grid side)``."""
    occ = getattr(model, "occupancy", None)
    if occ is not None and int(occ.mask.shape[0]) & (int(occ.mask.shape[0]) - 1) == 0:
        mask = occ.mask.detach().cpu()
        return mask.nonzero(), occ.bbox.detach().cpu().double(), int(mask.shape[0])
    g = DENSE_GRID
    ijk = torch.stack(torch.meshgrid(*[torch.arange(g)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return ijk, model.scene_bbox.detach().cpu().double(), g


@torch.no_grad()
def preview_tree(model: Any, ndc: Any = None, chunk: int = 1 << 16) -> Any:
    """The preview :class:`~plenoctree.octree.Octree` of ``model`` (a
    :class:`~plenoctree.nerf.NeRFModel`; see the module doc), float32, with ``tree.ndc =
    ndc``. None when no cell is opaque enough (an untrained model), and for a plain NeRF (its
    colours need an SH projection: the extraction's work, not a preview's)."""
    from ..octree.build import tree_from_leaves

    if model.basis == "plain":
        return None

    ijk, box, g = _cells(model)
    side = (box[1] - box[0]) / g                                   # [3] world units
    was_training = model.training
    model.eval()
    try:
        dev = next(model.parameters()).device
        vals = []
        for i in range(0, ijk.shape[0], chunk):
            pts = (box[0] + (ijk[i:i + chunk].double() + 0.5) * side).float().to(dev)
            sigma, coeffs = model.query(pts)
            vals.append(torch.cat([coeffs.float(), sigma.float()[:, None]], 1).cpu())
    finally:
        model.train(was_training)
    if not vals:
        return None
    values = torch.cat(vals).numpy()
    alpha = 1.0 - np.exp(-np.maximum(values[:, -1], 0.0) * float(side.max()))
    keep = alpha >= MIN_ALPHA
    if not keep.any():
        return None
    depth = g.bit_length() - 2                        # a 2^(c+1) grid: cells of depth c
    extra = model.sg_extra_data() if model.basis == "sg" else None
    tree = tree_from_leaves(np.full(int(keep.sum()), depth), ijk.numpy()[keep], values[keep],
                            (0.5 * (box[0] + box[1])).numpy(), (0.5 * (box[1] - box[0])).numpy(),
                            model.data_format, extra)
    tree.ndc = ndc
    return tree


def write_preview(model: Any, folder: str | Path, ndc: Any = None) -> dict:
    """Write ``folder/preview.npz`` (atomically) from :func:`preview_tree`; returns ``{"seconds",
    "leaves"}`` (0 leaves: nothing written yet — the model is still see-through)."""
    from ..octree.io import save_tree

    t0 = time.perf_counter()
    tree = preview_tree(model, ndc)
    leaves = 0
    if tree is not None:
        save_tree(tree, Path(folder) / PREVIEW_NAME)
        leaves = int(tree.n_leaves)
    return {"seconds": time.perf_counter() - t0, "leaves": leaves}


class LiveView:
    """A trainer's live view (``plenoctree view RUN``): ``live.json`` at every log row and a
    preview tree every ``every_s`` seconds of training, the first after ``min(FIRST_S,
    every_s)`` seconds (the first minutes show something). ``every_s = 0``: status rows only.

    Attributes:
        seconds: the time spent writing previews (the share of training it costs is
            ``seconds / train_s``, reported as ``preview_s`` in ``summary.json``).
    """

    def __init__(self, folder: str | Path, every_s: float, ndc: Any = None):
        self.folder, self.every_s, self.ndc = Path(folder), float(every_s), ndc
        self.next_s = min(FIRST_S, self.every_s)
        self.seconds = 0.0
        self.tree: str | None = None

    def row(self, step: int, steps: int | None, psnr: float, frac: float,
            train_s: float, stage: str = "training") -> None:
        """The status of a log row: step (of ``steps``; None for a time budget), training
        PSNR (validation PSNR at the end), the seconds left estimated from the share ``frac``
        done after ``train_s``."""
        from ..live import write_live

        eta = train_s * (1.0 - frac) / frac if frac > 0 else None
        write_live(self.folder, stage=stage, step=int(step), steps=steps,
                   psnr=round(float(psnr), 2), eta_s=None if eta is None else round(eta, 1),
                   tree=self.tree)

    def tick(self, model: Any, train_s: float, force: bool = False) -> None:
        """Write a preview when one is due (or ``force``, at the end of training)."""
        if self.every_s <= 0 or not (force or train_s >= self.next_s):
            return
        from ..live import write_live

        out = write_preview(model, self.folder, self.ndc)
        self.seconds += out["seconds"]
        self.next_s = train_s + self.every_s
        if out["leaves"]:
            self.tree = PREVIEW_NAME
            write_live(self.folder, tree=self.tree, **({} if force else {"stage": "training"}))
