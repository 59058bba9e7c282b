"""The far field: everything of an unbounded capture beyond the scene box (issue 50).

A 360° walk-around sees the object in the scene box and the world around it (the far end of
a room, houses, sky). The octree holds that world as **shells**: its root is the scene box
grown ``2^L`` times about the box's centre, shell ``l`` (``1 <= l <= L``) is the box grown
``2^l`` times minus the box grown ``2^(l-1)`` times, and each shell is cut into cells
``2^l`` times the size of those of a ``far_grid^3`` grid over the box (a constant angle seen
from the centre; see :mod:`plenoctree.convert.shells`). The octree's traversal, fine-tuning
and compression do not change: shells are ordinary leaves.

The NeRF-SH learns the far field with a second network, :class:`FarField`, evaluated at
points contracted into ``[-2, 2]^3`` box units (the L∞ form of mip-NeRF 360's contraction:
``u`` if ``|u|∞ <= 1`` else ``(2 - 1/|u|∞) u / |u|∞``, ``u = (x - centre) / radius``). Its
samples along a ray lie uniformly in inverse distance between ``near`` and the exit of the
outer cube (a fixed count per ray whatever the world's size: ``far_samples`` stratified
ones, then ``far_fine`` drawn from their weights), the inner box's part of the ray left to the
inner network and its occupancy march. :func:`composite_far` joins the two in ray order:
far samples before the box, the box, far samples behind it.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch
from torch import nn

from .sampling import pdf_samples, ray_aabb

__all__ = ["FarField", "CONTRACTED_BOX", "contract", "far_levels_for", "resolve_far_levels",
           "resolve_render_step", "PLACE_STEP", "DEFAULT_STEP",
           "render_far", "composite_far", "far_distortion", "MIN_LEVELS", "MAX_LEVELS"]

logger = logging.getLogger(__name__)

CONTRACTED_BOX = np.array([[-2.0] * 3, [2.0] * 3], np.float32)
"""The box the far network's encoding covers: contracted box units."""
MIN_LEVELS = 4
"""Fewest shells of an automatic far field: the outer cube is >= 16x the scene box."""
MAX_LEVELS = 7
"""Most shells (128x the box): the inner box's cells keep >= 8 levels of depth headroom
under ``MAX_DEPTH``."""


def contract(u: torch.Tensor) -> torch.Tensor:
    """L∞ scene contraction of box coordinates ``u [N, 3]`` (the box is ``|u|∞ <= 1``) into
    ``[-2, 2]^3``; identity inside the box, continuous at its surface."""
    r = u.abs().amax(-1, keepdim=True).clamp(min=1e-12)
    return torch.where(r <= 1.0, u, (2.0 - 1.0 / r) * (u / r))


def far_levels_for(bbox: np.ndarray, origins: np.ndarray, far: float) -> int:
    """Shells needed so that the outer cube holds every point within ``far`` of a camera.

    Args:
        bbox: ``[2, 3]`` scene box. origins: ``[N, 3]`` camera centres. far: the dataset's
            far bound (world units).

    Returns:
        ``L`` in ``[MIN_LEVELS, MAX_LEVELS]``: the smallest with ``2^L`` box radii >= the
        largest ``|o - centre|∞ + far`` in box units.
    """
    lo, hi = np.asarray(bbox, np.float64).reshape(2, 3)
    c, r = 0.5 * (lo + hi), 0.5 * (hi - lo)
    reach = float(np.max(np.abs(np.asarray(origins, np.float64) - c) / r, initial=0.0))
    reach += float(far) / float(r.min())
    need = math.ceil(math.log2(max(reach, 1.0)))
    return int(min(max(need, MIN_LEVELS), MAX_LEVELS))


def resolve_far_levels(cfg, data, announce: bool = False) -> int:
    """``cfg.far_levels`` with "automatic" (-1) decided for dataset ``data``: shells
    (:func:`far_levels_for`) for a capture of a place (``data.unbounded``) trained with the
    occupancy sampler, else none (``announce``: log the decision)."""
    if cfg.far_levels >= 0:
        return int(cfg.far_levels)
    if cfg.sampler != "occupancy" or not getattr(data, "unbounded", False):
        return 0
    levels = far_levels_for(data.scene_bbox, data.cameras.c2w[:, :3, 3], data.far)
    if announce:
        logger.info(f"far field: {levels} shells around the scene box (to {2 ** levels}x its "
                    "size): the world beyond it is trained too")
    return levels


#: The automatic render step of a capture of a place: this fraction of its box's side (0.01
#: on the ±1 box of an LLFF 360° scene, as measured on the lounge; a box of ±3.6 made by
#: ``process`` for the same frames took 3.6x the samples per ray at 0.01).
PLACE_STEP = 1.0 / 200
#: The automatic render step of everything else (world units; lego's ±1.5 box: 300 a side).
DEFAULT_STEP = 0.01


def resolve_render_step(cfg, data=None, announce: bool = False) -> float:
    """``cfg.render_step`` with "automatic" (-1) decided for dataset ``data``:
    :data:`PLACE_STEP` of the box's side for a capture of a place (``data.unbounded``: the box
    follows the cameras, so the samples per ray do not depend on the poses' units),
    :data:`DEFAULT_STEP` otherwise and without a dataset (the renderers: the trainer writes
    the resolved step into the run's config). ``announce``: log the decision."""
    if cfg.render_step > 0:
        return float(cfg.render_step)
    if data is None or not getattr(data, "unbounded", False):
        return DEFAULT_STEP
    box = np.asarray(data.scene_bbox, np.float64).reshape(2, 3)
    step = float((box[1] - box[0]).max()) * PLACE_STEP
    if announce:
        logger.info(f"render step {step:.4g} (1/{round(1 / PLACE_STEP)} of the scene box's "
                    "side, a capture of a place); --train.render-step overrides")
    return step


class FarField(nn.Module):
    """The far field's network: a :class:`~plenoctree.nerf.model.RadianceField` over the
    contracted box coordinates ``[-2, 2]^3``.

    Args:
        net: the network (``RadianceField(cfg, CONTRACTED_BOX)``, the inner network's basis
            and degree). bbox: ``[2, 3]`` scene box (the inner network's). levels: ``L``,
            shells around it.
    """

    def __init__(self, net: nn.Module, bbox, levels: int):
        super().__init__()
        b = np.asarray(bbox, np.float32).reshape(2, 3)
        self.levels = int(levels)
        self.register_buffer("centre", torch.as_tensor(0.5 * (b[0] + b[1])))
        self.register_buffer("radius", torch.as_tensor(0.5 * (b[1] - b[0])))
        self.net = net

    def box_coords(self, points: torch.Tensor) -> torch.Tensor:
        """World ``[N, 3]`` -> box units ``[N, 3]`` (the box is ``|u|∞ <= 1``)."""
        return (points.float() - self.centre) / self.radius

    def outer_bbox(self) -> torch.Tensor:
        """``[2, 3]`` world box of the outer cube (``2^L`` box radii about the centre)."""
        half = self.radius * float(2 ** self.levels)
        return torch.stack([self.centre - half, self.centre + half])

    def forward(self, points: torch.Tensor, dirs: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(sigma [N] in 1/world-length, coeffs [N, 3·B])`` at world ``points [N, 3]``.

        σ is the network's per contracted length divided by the stretch of the contraction
        along the coordinate that decides it (``|u|∞^2``): the field is smooth in contracted
        space, its world density falls with distance as the cells grow.
        """
        u = self.box_coords(points)
        sigma, coeffs = self.net(contract(u), dirs)
        return sigma / self._stretch(u), coeffs

    def density(self, points: torch.Tensor) -> torch.Tensor:
        u = self.box_coords(points)
        return self.net.density(contract(u)) / self._stretch(u)

    def _stretch(self, u: torch.Tensor) -> torch.Tensor:
        """``[N]`` world length per contracted length along the deciding coordinate
        (``|u|∞^2`` box radii; 1 box radius inside the box)."""
        r = u.abs().amax(-1).clamp(min=1.0)
        return r * r * self.radius.min()

    def colors(self, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        return self.net.colors(coeffs, dirs)


def _disparity_samples(t0: torch.Tensor, t1: torch.Tensor, n: int, perturb: bool,
                       generator: torch.Generator | None) -> torch.Tensor:
    """``[R, n]`` increasing distances, one in each of ``n`` bins of equal width in ``1/t``
    between ``t0`` and ``t1`` (> 0): at its middle, or uniform within it (``perturb``)."""
    u = torch.linspace(0.0, 1.0, n + 1, device=t0.device)
    s = (1.0 / t0)[:, None] * (1.0 - u) + (1.0 / t1)[:, None] * u            # [R, n + 1]
    if perturb:
        j = torch.rand((t0.shape[0], n), generator=generator, device=t0.device)
    else:
        j = torch.full((t0.shape[0], n), 0.5, device=t0.device)
    return 1.0 / (s[:, :-1] + (s[:, 1:] - s[:, :-1]) * j)


def render_far(far: FarField, origins: torch.Tensor, dirs: torch.Tensor, near: float,
               inner_bbox: torch.Tensor, n_coarse: int, n_fine: int, train: bool,
               generator: torch.Generator | None = None) -> dict:
    """The far field's samples of ``R`` rays (outside the inner box, inside the outer cube).

    Args:
        far: the network. origins, dirs: ``[R, 3]`` (unit dirs). near: start distance.
        inner_bbox: ``[2, 3]`` the inner network's box. n_coarse, n_fine: samples per ray
            (``n_fine`` > 0: drawn from the coarse samples' weights, evaluated with them).
        train: jittered samples (else evenly spaced); gradients follow the caller's mode.

    Returns:
        ``sigma [R, S]`` (0 inside the inner box), ``rgb [R, S, 3]``, ``t [R, S]``,
        ``delta [R, S]``, ``edges [R, S + 1]`` (the samples' intervals, from the start to the
        outer cube's exit), ``after [R, S]`` bool (behind the inner box), ``n_samples``.
    """
    n = origins.shape[0]
    t_in, t_out_box = ray_aabb(origins, dirs, inner_bbox)
    _, t_end = ray_aabb(origins, dirs, far.outer_bbox())
    t0 = torch.full((n,), max(float(near), 1e-4), device=origins.device)
    t1 = torch.maximum(t_end, t0 * 1.001)
    hits = t_out_box > t_in

    def points(t: torch.Tensor) -> torch.Tensor:
        return (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)

    def outside(t: torch.Tensor) -> torch.Tensor:
        return ~(hits[:, None] & (t > t_in[:, None]) & (t < t_out_box[:, None]))

    def edges(t: torch.Tensor) -> torch.Tensor:
        """``[R, S + 1]``: each sample's interval, from ``t0`` to ``t1`` split at midpoints."""
        return torch.cat([t0[:, None], 0.5 * (t[:, 1:] + t[:, :-1]), t1[:, None]], -1)

    def deltas(t: torch.Tensor) -> torch.Tensor:
        e = edges(t)
        return e[:, 1:] - e[:, :-1]

    t = _disparity_samples(t0, t1, n_coarse, train, generator)
    if n_fine > 0:
        with torch.no_grad():
            sig_c = far.density(points(t)).reshape(t.shape) * outside(t)
            tau = sig_c * deltas(t)
            w = torch.exp(-(torch.cumsum(tau, -1) - tau)) * (1.0 - torch.exp(-tau))
            t_f = pdf_samples(edges(t), w, n_fine, train, generator)
        t = torch.sort(torch.cat([t, t_f], -1), -1).values
    d = dirs[:, None, :].expand(n, t.shape[1], 3).reshape(-1, 3)
    sigma, coeffs = far(points(t), d)
    sigma = sigma.reshape(t.shape) * outside(t)
    rgb = far.colors(coeffs, d).reshape(n, t.shape[1], 3)
    after = hits[:, None] & (t >= t_out_box[:, None])
    n_eval = n * (n_coarse + (n_coarse + n_fine if n_fine > 0 else 0))
    return {"sigma": sigma, "rgb": rgb, "t": t, "delta": deltas(t), "edges": edges(t),
            "after": after, "n_samples": n_eval}


def composite_far(f: dict, rgb_in: torch.Tensor, acc_in: torch.Tensor, dsum_in: torch.Tensor
                  ) -> dict:
    """Join the far samples ``f`` (:func:`render_far`) and the inner box's result in ray order.

    Args:
        rgb_in ``[R, 3]``, acc_in ``[R]``, dsum_in ``[R]`` (``Σ w t``): the inner box's
            composite, without background (its transmittance is ``1 - acc_in``).

    Returns:
        ``rgb [R, 3]`` (without background: add ``(1 - acc) * bg``), ``acc [R]``,
        ``dsum [R]``, ``weights [R, S]`` of the far samples.
    """
    tau = f["sigma"] * f["delta"]
    after = f["after"]
    excl = torch.cumsum(tau, -1) - tau
    t_box = (1.0 - acc_in).clamp(min=0.0)
    before_box = torch.exp(-(tau * (~after)).sum(-1))             # far transmittance before
    trans = torch.exp(-excl) * torch.where(after, t_box[:, None], torch.ones_like(excl))
    w = trans * (1.0 - torch.exp(-tau))
    t_end = torch.exp(-tau.sum(-1)) * t_box
    rgb = (w[..., None] * f["rgb"]).sum(1) + before_box[:, None] * rgb_in
    acc = 1.0 - t_end
    dsum = (w * f["t"]).sum(1) + before_box * dsum_in
    return {"rgb": rgb, "acc": acc, "dsum": dsum, "weights": w}


def far_distortion(weights: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360's distortion loss (Barron et al. 2022, eq. 15) of the far samples, per ray.

    Distances are measured as the far samples are drawn: in inverse distance, normalised to
    ``s = (1/t0 - 1/t) / (1/t0 - 1/t1)`` in ``[0, 1]`` over each ray's far interval (mip-NeRF
    360's normalised distance with ``g = 1/x``), so a sample of the far end counts as much as
    one near the box. With the ``S`` intervals ``[s_i, s_{i+1}]``, midpoints ``m_i``::

        L = Σ_i Σ_j w_i w_j |m_i - m_j| + 1/3 Σ_i w_i² (s_{i+1} - s_i)

    computed in ``O(S)`` (``2 Σ_i w_i (m_i W_i - M_i)``, ``W``, ``M``: exclusive prefix sums of
    ``w`` and ``w m``). Without it the far network may spread a wall or the sky over several
    shells; with it, on the lounge's frames, the extracted shells held a third fewer leaves
    and the fine-tuned tree scored 0.9 dB better held out (its NeRF-SH 0.4 dB worse;
    docs/results.md).

    Args:
        weights: ``[R, S]`` the far samples' weights (:func:`composite_far`'s ``weights``).
        edges: ``[R, S + 1]`` increasing distances (:func:`render_far`'s ``edges``).

    Returns:
        ``[R]``, differentiable in ``weights``.
    """
    inv = 1.0 / edges.double()
    s = (inv[:, :1] - inv) / (inv[:, :1] - inv[:, -1:]).clamp(min=1e-12)
    mid = 0.5 * (s[:, 1:] + s[:, :-1])
    w = weights.double()
    before_w = torch.cumsum(w, -1) - w
    before_wm = torch.cumsum(w * mid, -1) - w * mid
    pair = 2.0 * (w * (mid * before_w - before_wm)).sum(-1)
    return (pair + (w * w * (s[:, 1:] - s[:, :-1])).sum(-1) / 3.0).to(weights.dtype)
