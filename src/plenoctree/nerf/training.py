"""The parts of a NeRF-SH training step (§3, §4.1) that :class:`~.trainer.Trainer` composes:
the learning-rate schedule, the sparsity prior, the source of ray batches, the validation
views, and the error a diverging run raises."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ..datasets import Dataset, load_dataset
from ..datasets.dataset import holds_photos
from ..errors import PlenOctreeError
from .config import PHOTO_DISTORTION, TrainConfig
from .raygen import BG_ALPHA, BG_DATA, BG_OPAQUE, ray_constants

__all__ = ["opaque_photos", "distortion_weight", "TrainingError", "learning_rate", "flush_tiny_moments", "sparsity_loss", "RaySource",
           "load_val_views", "VAL_SHARE", "VAL_PIXELS", "val_row_stride"]

VAL_SHARE = 0.1
"""Timed validations take at most this share of the wall time: after a validation that took
``t`` seconds the next waits at least ``t (1 - VAL_SHARE) / VAL_SHARE`` training seconds
(5 views of 504x378 take ~40 s on 2 cores, so they come every ~6 minutes, not every 2)."""


VAL_PIXELS = 1 << 18
"""Pixels a validation renders at most, its views together: larger views are validated on
every ``k``-th row (:func:`val_row_stride`; PSNR of a row sample, no SSIM), so that one pass
stays inside its share of the time however large the views and however many samples a ray
takes (a 360° walk-around's far field)."""


def val_row_stride(n_pixels: int, height: int, stride: int = 0, seconds: float = 0.0,
                   interval_s: float = 0.0) -> int:
    """Rows step of the next validation: from the pixel budget (``stride`` 0: none yet), then
    widened after a pass of ``seconds`` that took more than ``VAL_SHARE`` of the validation
    interval ``interval_s``; at least 8 rows of each view stay.

    Args:
        n_pixels: pixels of all validation views at full rows. height: rows of a view.
    """
    if stride <= 0:
        stride = max(1, math.ceil(n_pixels / VAL_PIXELS))
    elif interval_s > 0 and seconds > VAL_SHARE * interval_s:
        stride = math.ceil(stride * seconds / (VAL_SHARE * interval_s))
    return int(max(1, min(stride, height // 8)))


class TrainingError(PlenOctreeError, RuntimeError):
    """Training cannot continue (non-finite loss); the last good checkpoint is kept."""


def learning_rate(cfg: TrainConfig, step: int, progress_frac: float) -> float:
    """jaxnerf's schedule: log-linear ``lr_init -> lr_final`` over ``progress_frac`` in [0, 1],
    times a sine warm-up from ``lr_delay_mult`` over the first ``lr_delay_steps`` steps."""
    p = min(max(progress_frac, 0.0), 1.0)
    lr = math.exp(math.log(cfg.lr_init) * (1 - p) + math.log(cfg.lr_final) * p)
    if cfg.lr_delay_steps > 0:
        s = min(max(step / cfg.lr_delay_steps, 0.0), 1.0)
        lr *= cfg.lr_delay_mult + (1 - cfg.lr_delay_mult) * math.sin(0.5 * math.pi * s)
    return lr


@torch.no_grad()
def flush_tiny_moments(optimizer: torch.optim.Optimizer, tiny: float = 1e-30) -> int:
    """Zero Adam moments that decayed towards denormal floats; returns how many entries.

    Rarely-touched hash-table rows have moments that shrink geometrically; once denormal,
    every Adam step on them is ~3x slower on x86 (and ``torch.set_flush_denormal`` does not
    reach the worker threads). ``exp_avg`` below ``tiny`` is set to 0, then ``exp_avg_sq``
    below ``tiny`` where ``exp_avg`` is 0 — the update of such entries is 0 either way.
    """
    n = 0
    for st in optimizer.state.values():
        m, v = st.get("exp_avg"), st.get("exp_avg_sq")
        if m is None or v is None:
            continue
        small_m = m.abs() < tiny
        m.masked_fill_(small_m, 0.0)
        small_v = (v < tiny) & small_m
        n += int(small_v.sum())
        v.masked_fill_(small_v, 0.0)
    return n


def sparsity_loss(sigma: torch.Tensor, length: float) -> torch.Tensor:
    """Eq. (6): ``mean_k |1 - exp(-λ σ_k)|`` with ``λ = length``.

    Densities are non-negative, so the absolute value is the identity and is left out (its
    zero subgradient at σ = 0 would otherwise stop the prior exactly where it starts).
    """
    return (1.0 - torch.exp(-length * sigma)).mean()


def with_sparsity(loss: torch.Tensor, model: Any, cfg: TrainConfig,
                  generator: torch.Generator, amp: Any) -> torch.Tensor:
    """``loss`` plus ``cfg.sparsity_weight`` times the prior (:func:`sparsity_loss`) at
    ``cfg.sparsity_points`` uniform points of the model's box (drawn from ``generator``)."""
    from .renderer import autocast

    if cfg.sparsity_weight <= 0 or cfg.sparsity_points <= 0:
        return loss
    bbox = model.scene_bbox
    pts = bbox[0] + (bbox[1] - bbox[0]) * torch.rand(
        (cfg.sparsity_points, 3), generator=generator, device=bbox.device)
    with autocast(bbox.device, amp):
        sig = model.fine.density(pts)
    return loss + cfg.sparsity_weight * sparsity_loss(sig, cfg.sparsity_length)


# ------------------------------------------------------------------ data
class RaySource:
    """Random rays over all pixels of all training images, with their target colours.

    Rays are made on the fly by :meth:`plenoctree.datasets.Cameras.pixel_rays` (so per-camera
    intrinsics and NDC rays of forward-facing scenes are honoured, identical to
    ``cameras.rays(i)``); only the images are held in memory. :meth:`pixels` is the torch
    twin of op ``ray_batch`` (:mod:`.raygen`), the fixed step's rays in one launch.
    """

    def __init__(self, data: Dataset, device: torch.device, random_background: bool,
                 opaque_photos: bool = False):
        """``random_background``: composite the pixels with alpha onto random colours;
        ``opaque_photos``: images without alpha are predicted over random colours too (their
        targets stay as they are), so a ray that stays see-through is penalised."""
        cams = data.cameras
        n, h, w = len(cams), cams.height, cams.width
        self.n, self.h, self.w = n, h, w
        self.device = device
        self.cameras = cams
        self.tables = cams.device_tables(device)       # uploaded once, not every step
        self.images = torch.from_numpy(np.ascontiguousarray(data.images)).reshape(-1, 3).to(device)
        self.bg = torch.tensor(data.background, dtype=torch.float32, device=device)
        self.alphas = None
        self.opaque_photos = opaque_photos and data.alphas is None
        if random_background and data.alphas is not None:
            self.alphas = torch.from_numpy(np.ascontiguousarray(data.alphas)).reshape(-1).to(device)
        self.near, self.far = float(data.near), float(data.far)
        if cams.ndc and not cams.ndc_clip:    # NeRF's NDC rays: every pixel's points down -z
            _check_ndc_corners(cams)
        # what op ray_batch's kernels read besides the tables (nerf.raygen), uploaded once
        self.constants = ray_constants(cams, self.near, self.far, device)

    @property
    def background_mode(self) -> int:
        """How a ray's background and target are made: :data:`~.raygen.BG_DATA` (the
        dataset's colour), :data:`~.raygen.BG_ALPHA` (pixels with alpha re-composited over a
        random colour) or :data:`~.raygen.BG_OPAQUE` (opaque photos predicted over a random
        colour, their targets as they are)."""
        if self.opaque_photos:
            return BG_OPAQUE
        return BG_DATA if self.alphas is None else BG_ALPHA

    def rays_of(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(origins [B, 3], unit dirs [B, 3])`` float32 of flat pixel indices ``idx [B]``
        (``img * H * W + row * W + col``), equal to ``cameras.rays(img)[row, col]``."""
        img = idx // (self.h * self.w)
        pix = idx % (self.h * self.w)
        return self.cameras.pixel_rays(img, pix % self.w, pix // self.w, self.tables)

    def sample(self, n: int, generator: torch.Generator):
        """``(origins, dirs, target [n, 3], background [n, 3])`` of ``n`` random pixels (the
        waves' step; the fixed step draws its pixels with :func:`.raygen.draw_uniforms`)."""
        idx = torch.randint(self.n * self.h * self.w, (n,), generator=generator,
                            device=self.device)
        bg = None
        if self.background_mode != BG_DATA:
            bg = torch.rand((n, 3), generator=generator, device=self.device)
        return self.pixels(idx, bg)

    def pixels(self, idx: torch.Tensor, bg: torch.Tensor | None = None):
        """``(origins, dirs, target [B, 3], background [B, 3])`` float32 of flat pixel indices
        ``idx [B]``; ``bg``: float32 ``[B, 3]`` random colours in [0, 1] (used, and needed,
        unless :attr:`background_mode` is :data:`~.raygen.BG_DATA`)."""
        o, d = self.rays_of(idx)
        rgb = self.images[idx]
        mode = self.background_mode
        if mode == BG_OPAQUE:
            return o, d, rgb, bg
        if mode == BG_DATA:
            return o, d, rgb, self.bg.expand(idx.shape[0], 3)
        a = self.alphas[idx][:, None]
        return o, d, rgb - (1.0 - a) * self.bg + (1.0 - a) * bg, bg


def _check_ndc_corners(cams) -> None:
    """ConfigError unless every pixel ray of ``cams`` points down the world -z axis (NDC
    without clipping): the raw direction is affine in the pixel position, so the four corner
    pixels of each camera decide it (the fused kernels of op ``ray_batch`` do not check)."""
    n, w, h = len(cams), cams.width, cams.height
    cols = np.tile(np.array([0, w - 1, 0, w - 1], dtype=np.float64), n)
    rows = np.tile(np.array([0, 0, h - 1, h - 1], dtype=np.float64), n)
    cams.pixel_rays(np.repeat(np.arange(n), 4), cols, rows)     # to_ndc_rays raises


def load_val_views(cfg: TrainConfig) -> Dataset | None:
    """The ``val_views`` evenly spaced views of split ``val_split`` (None when 0 views)."""
    if cfg.val_views <= 0:
        return None
    return load_dataset(cfg.data, cfg.val_split, format=cfg.format, downscale=cfg.downscale,
                        background=cfg.background, limit=cfg.val_views, spread=True)


# ------------------------------------------------------------------ training


def opaque_photos(cfg: TrainConfig) -> bool:
    """Whether images without alpha are trained over random colours (``cfg.photo_background``;
    "auto": when the dataset holds real photos)."""
    if cfg.photo_background != "auto":
        return cfg.photo_background == "random"
    return holds_photos(cfg.data, cfg.format)


def distortion_weight(cfg: TrainConfig) -> float:
    """The distortion loss's weight: ``cfg.distortion_weight``, or when None
    :data:`~plenoctree.nerf.config.PHOTO_DISTORTION` for real photos with the occupancy sampler
    and 0 otherwise."""
    if cfg.distortion_weight is not None:
        return float(cfg.distortion_weight)
    photos = cfg.sampler == "occupancy" and holds_photos(cfg.data, cfg.format)
    return PHOTO_DISTORTION if photos else 0.0
