"""Render rays and images with a NeRF-SH (training and evaluation).

Two samplers share one output format, a dict with ``rgb [R, 3]``, ``acc [R]`` (opacity),
``depth [R]`` (expected distance, normalised by ``acc``) and ``n_samples`` (network points):

* :func:`render_rays_hierarchical` — the paper's: ``n_coarse`` stratified samples evaluated by
  the coarse network, ``n_fine`` importance samples from its weights, the fine network on the
  sorted union (also returns ``rgb_coarse``);
* :func:`render_rays_occupancy` — the CPU preset's: fixed steps through the occupancy grid.
  Rays are marched in waves of a few samples; a ray stops once its transmittance falls below
  ``stop_thresh`` (early ray termination), so the samples behind a surface are never
  evaluated, in training as in rendering.

:func:`render_image` renders a whole camera in chunks of rays without gradients.

The rays travel as a :class:`RayBatch` (origins, directions, bounds, background), how they are
rendered as a :class:`RenderMode` (training or evaluation, noise, bf16, early stop), and a whole
image's knobs as :class:`ImageOptions`.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from ..datasets import Dataset
from .config import TrainConfig
from .far import composite_far, far_distortion, render_far, resolve_render_step
from .model import NeRFModel, RadianceField
from .occupancy import OccupancyGrid
from .sampling import MarchGrid, MarchRays, march_rays, pdf_samples, ray_aabb, \
    stratified_samples
from .composite import composite_rays
from .volrend import composite, deltas_from_t, render_weights

__all__ = ["RayBatch", "RenderMode", "ImageOptions", "autocast", "render_rays",
           "render_rays_hierarchical", "render_rays_occupancy", "render_image", "ray_bounds"]


@dataclass(frozen=True)
class RayBatch:
    """``R`` rays to render.

    Attributes:
        origins, dirs: float32 ``[R, 3]`` (unit dirs), world units.
        near, far: distance bounds along every ray.
        background: ``[3]`` or ``[R, 3]`` colour behind the scene.
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    near: float
    far: float
    background: torch.Tensor

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def bg(self) -> torch.Tensor:
        """The background as ``[R, 3]``."""
        b = self.background
        return b.expand(len(self), 3) if b.dim() == 1 else b


@dataclass(frozen=True)
class RenderMode:
    """How rays are rendered.

    Attributes:
        train: jitter the samples with ``generator`` and keep gradients (training); otherwise
            samples sit at fixed places and everything runs without gradients.
        generator: the noise of training samples.
        amp: evaluate the network in bf16 autocast.
        stop_thresh: occupancy sampler: early termination at ``T < stop_thresh`` (None: the
            config's ``train_stop_thresh`` / ``eval_stop_thresh``; 0 = march to the box's end).
        max_samples: occupancy sampler, training only: stop marching once this many samples
            were evaluated; rays not finished by then are marked incomplete (0 = no limit).
        distortion: occupancy sampler, training only: also return each ray's distortion loss
            (:func:`~plenoctree.nerf.volrend.distortion_packed`, in world units).
    """

    train: bool = False
    generator: torch.Generator | None = None
    amp: bool = False
    stop_thresh: float | None = None
    max_samples: int = 0
    distortion: bool = False


@dataclass(frozen=True)
class ImageOptions:
    """Knobs of :func:`render_image` (no effect on the result but ``rows``).

    Attributes:
        amp: bf16 autocast for the network. chunk: rays per call (None: the config's ``chunk``).
        device: where to render. rows: render only these image rows (timing part of a frame).
    """

    amp: bool = False
    chunk: int | None = None
    device: torch.device | str = "cpu"
    rows: slice | None = None


def autocast(device: torch.device, enabled: bool):
    """bf16 autocast context for the network on ``device`` (a no-op when not ``enabled``)."""
    if not enabled:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16)


def ray_bounds(origins: torch.Tensor, dirs: torch.Tensor, bbox: torch.Tensor, near: float,
               far: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(t_min [R], t_max [R])``: the part of ``[near, far]`` inside ``bbox`` (empty: max <= min)."""
    t0, t1 = ray_aabb(origins, dirs, bbox)
    return t0.clamp(min=near), t1.clamp(max=far)


def render_rays_hierarchical(model: NeRFModel, rays: RayBatch, cfg: TrainConfig,
                             mode: RenderMode = RenderMode()) -> dict:
    """The paper's coarse-to-fine rendering of ``R`` rays (``n_coarse`` and ``n_fine`` from
    ``cfg``). In training (``mode.train``) the samples are jittered with ``mode.generator``.
    Returns ``rgb [R, 3], acc [R], depth [R], rgb_coarse [R, 3], n_samples``.
    """
    origins, dirs = rays.origins, rays.dirs
    n = len(rays)
    dev = origins.device
    bg = rays.bg()
    train, generator, amp = mode.train, mode.generator, mode.amp
    near_t = torch.full((n,), float(rays.near), device=dev)
    far_t = torch.full((n,), float(rays.far), device=dev)
    t_c = stratified_samples(near_t, far_t, cfg.n_coarse, train, generator)        # [R, Sc]
    coarse = model.coarse if model.coarse is not None else model.fine

    def run(field: RadianceField, t: torch.Tensor):
        s = t.shape[1]
        pts = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)
        d = dirs[:, None, :].expand(n, s, 3).reshape(-1, 3)
        with autocast(dev, amp):
            sigma, coeffs = field(pts, d)
        rgb = field.colors(coeffs, d).reshape(n, s, 3)
        w, _ = render_weights(sigma.reshape(n, s), deltas_from_t(t))
        return w, composite(w, rgb, t, bg)

    w_c, (rgb_c, _, _) = run(coarse, t_c)
    out = {"rgb_coarse": rgb_c, "n_samples": n * cfg.n_coarse}
    if cfg.n_fine > 0:
        mids = 0.5 * (t_c[:, 1:] + t_c[:, :-1])
        t_f = pdf_samples(mids, w_c[:, 1:-1], cfg.n_fine, train, generator)
        t_all = torch.sort(torch.cat([t_c, t_f], -1), -1).values
        _, (rgb, acc, depth) = run(model.fine, t_all)
        out["n_samples"] += n * t_all.shape[1]
    else:
        _, (rgb, acc, depth) = run(model.fine, t_c)
    out.update(rgb=rgb, acc=acc, depth=depth)
    return out


def _first_per_ray(flag: torch.Tensor, ray_idx: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Index of the first sample with ``flag`` in each ray, ``M`` (= none) otherwise: ``[R]``."""
    m = flag.shape[0]
    pos = torch.where(flag, torch.arange(m, device=flag.device), torch.full_like(ray_idx, m))
    return torch.full((n_rays,), m, dtype=torch.int64, device=flag.device).scatter_reduce(
        0, ray_idx, pos, reduce="amin")


def _wave_bookkeeping(tau: torch.Tensor, ridx: torch.Tensor, offsets: torch.Tensor,
                      opt_before: torch.Tensor, log_thresh: float):
    """Early termination within one wave (no gradients).

    Args:
        tau: float64 ``[M]`` optical depths ``σ δ`` of the wave's samples (packed, ray-major).
        ridx, offsets: the packing (local ray index per sample; ``[A + 1]`` offsets).
        opt_before: float64 ``[A]`` optical depth each ray accumulated in earlier waves.
        log_thresh: ``-log(stop_thresh)`` (``inf`` = never stop).

    Returns:
        ``(before [M], keep [M] bool, first_term [A])``: optical depth before each sample,
        whether the sample is at or before its ray's termination, and the index of the
        terminating sample of each ray (``M`` when the ray goes on).
    """
    incl = torch.cumsum(tau, 0)
    first = offsets[:-1].clamp(max=max(len(tau) - 1, 0))
    base = (incl - tau)[first]
    before = incl - tau - base[ridx] + opt_before[ridx]
    first_term = _first_per_ray(before + tau > log_thresh, ridx, offsets.shape[0] - 1)
    keep = torch.arange(len(tau), device=tau.device) <= first_term[ridx]
    return before, keep, first_term


def _march_waves(field: RadianceField, rays: MarchRays, grid: MarchGrid, mode: RenderMode,
                 budget: int = 1 << 16) -> dict:
    """March ``rays`` through ``grid`` in waves of a few samples each, stopping rays whose
    ``T < mode.stop_thresh`` (a float here: 0 = never stop).

    Each wave marches every unfinished ray for up to ``budget / rays`` more samples (at most
    32, 64, 128, … in the successive waves), evaluates
    them, and retires the rays that terminated or left the box. Samples past a ray's
    termination (the rest of its last wave) are dropped.

    Without ``mode.train`` everything runs without gradients and is composited on the fly:
    returns ``rgb [R, 3], acc [R], dsum [R] (Σ w t), n_samples``. With ``mode.train`` the
    network runs with gradients and the kept samples are composited at the end (eq. 1–2 over
    each ray's whole sequence): returns ``rgb, acc, dsum, n_samples, complete [R] bool,
    capped`` where ``complete`` is False for rays cut off because more than
    ``mode.max_samples`` (> 0) samples were evaluated, and ``capped`` (a Python bool) says
    whether that happened (else ``complete`` is all True); with ``mode.distortion`` also
    ``distortion [R]``.

    Host round trips (issue 38): one per wave (the rays still marching, a data-dependent
    shape) and the marching kernel's own; in training the kept samples of all waves are
    selected once at the end (one ``nonzero``), not wave by wave.
    """
    origins, dirs, step = rays.origins, rays.dirs, grid.step
    train, amp, max_samples, stop_thresh = mode.train, mode.amp, mode.max_samples, \
        mode.stop_thresh
    n = origins.shape[0]
    dev = origins.device
    opt = torch.zeros(n, dtype=torch.float64, device=dev)             # optical depth so far
    k = torch.zeros(n, dtype=torch.int64, device=dev)
    complete = torch.ones(n, dtype=torch.bool, device=dev)
    rgb = torch.zeros((n, 3), device=dev)
    acc = torch.zeros(n, device=dev)
    dsum = torch.zeros(n, device=dev)
    parts: list[tuple] = []
    active = torch.arange(n, device=dev)
    evaluated = n_waves = 0
    capped = False
    log_thresh = -np.log(stop_thresh) if stop_thresh > 0 else np.inf
    grad_ctx = torch.enable_grad() if train else torch.no_grad()
    while active.numel():
        if max_samples and evaluated >= max_samples:
            complete[active] = False
            capped = True
            break
        # about `budget` samples per wave, but short first waves: most rays end early
        wave = int(min(512, 32 << n_waves, max(16, budget // active.numel())))
        n_waves += 1
        with torch.no_grad():
            s = march_rays(rays.select(active, k[active]), grid, max_per_ray=wave)
        finished = s.done.clone()
        if len(s):
            d = dirs[active][s.ray_idx]
            gidx = active[s.ray_idx]
            with grad_ctx, autocast(dev, amp):
                sigma, coeffs = field(s.points, d)
            with grad_ctx:
                color = field.colors(coeffs, d)
            evaluated += len(s)
            with torch.no_grad():
                tau = sigma.detach().double() * step
                before, keep, first_term = _wave_bookkeeping(tau, s.ray_idx, s.offsets,
                                                             opt[active], log_thresh)
                opt.index_add_(0, gidx, tau * keep)
                finished |= first_term < len(s)
            if train:
                parts.append((gidx, s.t, sigma, color, keep))
            else:
                w = (torch.exp(-before) * (1.0 - torch.exp(-tau))).float() * keep
                acc.index_add_(0, gidx, w)
                dsum.index_add_(0, gidx, w * s.t)
                rgb.index_add_(0, gidx, w[:, None] * color)
        k[active] = s.k_next
        active = active[~finished]
    out = {"rgb": rgb, "acc": acc, "dsum": dsum, "n_samples": evaluated}
    if not train:
        return out
    out.update(complete=complete, capped=capped)
    if not parts:                   # nothing evaluated: the zeros above, no distortion
        if mode.distortion:
            out["distortion"] = torch.zeros_like(acc)
        return out
    gidx, t, sigma, color, keep = (torch.cat(x) for x in zip(*parts))
    kept = keep.nonzero()[:, 0]                             # the waves' kept samples, in order
    order = kept[torch.sort(gidx[kept], stable=True).indices]   # ray-major; waves keep k order
    gidx, t = gidx[order], t[order]
    sigma, color = sigma.index_select(0, order), color.index_select(0, order)
    # offsets of the sorted rays without a host round trip (bincount reads its size back)
    offsets = torch.searchsorted(gidx, torch.arange(n + 1, device=dev))
    out.update(composite_rays(sigma, color, t, offsets, step, distortion=mode.distortion))
    return out


def render_rays_occupancy(model: NeRFModel, rays: RayBatch, cfg: TrainConfig,
                          mode: RenderMode = RenderMode()) -> dict:
    """Fixed-step rendering (``cfg.render_step``) through the occupancy grid of ``model``, in
    waves (see :func:`_march_waves`) so that rays stop at ``T < mode.stop_thresh``.

    In training (``mode.train``) the samples are jittered with ``mode.generator`` and keep
    gradients; otherwise they sit at the middle of each step.

    Returns:
        ``rgb [R, 3], acc [R], depth [R]``, ``n_samples`` (network evaluations) and, in
        training, ``complete [R]`` (rays whose colour is final; use only those in a loss),
        ``capped`` (a Python bool: some ray is not complete) and, with ``mode.distortion``,
        ``distortion [R]``.
    """
    n = len(rays)
    dev = rays.origins.device
    t_min, t_max = ray_bounds(rays.origins, rays.dirs, model.scene_bbox, rays.near, rays.far)
    if mode.train:
        jitter = torch.rand(n, generator=mode.generator, device=dev)
    else:
        jitter = torch.full((n,), 0.5, device=dev)
    if mode.stop_thresh is None:
        mode = dataclasses.replace(mode, stop_thresh=cfg.train_stop_thresh if mode.train
                                   else cfg.eval_stop_thresh)
    occ: OccupancyGrid = model.occupancy
    r = _march_waves(model.fine, MarchRays(rays.origins, rays.dirs, t_min, t_max, jitter),
                     MarchGrid(resolve_render_step(cfg), occ.mask, occ.bbox), mode)
    if model.far is not None:           # the world beyond the box, in ray order (nerf.far)
        with autocast(dev, mode.amp):
            f = render_far(model.far, rays.origins, rays.dirs, rays.near, model.scene_bbox,
                           cfg.far_samples, cfg.far_fine, mode.train, mode.generator)
        r = {**r, **composite_far(f, r["rgb"], r["acc"], r["dsum"]),
             "n_samples": r["n_samples"] + f["n_samples"]}
        if mode.train and mode.distortion:
            r["far_distortion"] = far_distortion(r["weights"], f["edges"])
    acc = r["acc"]
    out = {"rgb": r["rgb"] + (1.0 - acc)[:, None] * rays.bg(), "acc": acc,
           "depth": r["dsum"] / acc.clamp(min=1e-10), "n_samples": r["n_samples"]}
    for key in ("complete", "capped", "distortion", "far_distortion"):   # training only
        if key in r:
            out[key] = r[key]
    return out


def render_rays(model: NeRFModel, rays: RayBatch, cfg: TrainConfig,
                mode: RenderMode = RenderMode()) -> dict:
    """Dispatch on ``cfg.sampler`` ("occupancy" or "hierarchical")."""
    if cfg.sampler == "occupancy":
        return render_rays_occupancy(model, rays, cfg, mode)
    return render_rays_hierarchical(model, rays, cfg, mode)


@torch.no_grad()
def render_image(model: NeRFModel, views: Dataset, index: int, cfg: TrainConfig,
                 opts: ImageOptions = ImageOptions()) -> dict:
    """Render camera ``index`` of ``views`` (its cameras, near/far and background) without
    gradients, ``opts.chunk`` rays at a time.

    Returns ``rgb [H, W, 3]``, ``acc [H, W]``, ``depth [H, W]`` (numpy float32) and
    ``n_samples`` (network evaluations).
    """
    dev = torch.device(opts.device)
    o, d = views.cameras.rays(index)
    if opts.rows is not None:
        o, d = o[opts.rows], d[opts.rows]
    h, w = o.shape[:2]
    o = torch.from_numpy(np.ascontiguousarray(o.reshape(-1, 3))).to(dev)
    d = torch.from_numpy(np.ascontiguousarray(d.reshape(-1, 3))).to(dev)
    bg = torch.as_tensor(np.asarray(views.background, np.float32), device=dev)
    chunk = int(opts.chunk or cfg.chunk)
    mode = RenderMode(amp=opts.amp)
    outs = {"rgb": [], "acc": [], "depth": []}
    n_samples = 0
    was_training = model.training
    model.eval()
    try:
        for i in range(0, o.shape[0], chunk):
            r = render_rays(model, RayBatch(o[i:i + chunk], d[i:i + chunk], views.near,
                                            views.far, bg), cfg, mode)
            n_samples += int(r["n_samples"])
            for k in outs:
                outs[k].append(r[k].float().cpu())
    finally:
        model.train(was_training)
    res = {k: torch.cat(v).reshape(h, w, *v[0].shape[1:]).numpy() for k, v in outs.items()}
    res["n_samples"] = n_samples
    return res
