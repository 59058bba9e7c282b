"""An occupancy grid over the scene box, updated from the network during training.

The occupancy sampler (:func:`plenoctree.nerf.sampling.march_rays`) only evaluates the network
in occupied cells, so empty space costs (almost) nothing. Each cell keeps a running density:
at every update all cells decay by ``decay`` and the evaluated ones take
``max(decayed, σ(random point in the cell))``; a cell is occupied when its density exceeds
``min(threshold, mean density)`` (the rule of instant-ngp's density grid).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from torch import nn

__all__ = ["OccupancyGrid", "WARMUP_DECAY"]

#: Decay of the running densities at the warm-up's updates (every cell re-evaluated;
#: instant-ngp's decay): the grid keeps the regions the young network has not learned yet.
#: After the warm-up the trainer decays by ``TrainConfig.occ_decay`` (0.8).
WARMUP_DECAY = 0.95


class OccupancyGrid(nn.Module):
    """Running densities and an occupancy mask on a ``res³`` grid over ``bbox``.

    Buffers (saved in checkpoints): ``bbox`` float32 ``[2, 3]``; ``density`` float32
    ``[res, res, res]`` (x, y, z); ``mask`` bool ``[res, res, res]``; ``n_updates`` int64 ``[]``.
    A fresh grid is fully occupied.
    """

    def __init__(self, bbox, res: int = 128):
        super().__init__()
        self.res = int(res)
        self.register_buffer("bbox", torch.as_tensor(np.asarray(bbox, np.float32).reshape(2, 3)))
        self.register_buffer("density", torch.zeros((res, res, res), dtype=torch.float32))
        self.register_buffer("mask", torch.ones((res, res, res), dtype=torch.bool))
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.int64))

    @property
    def cell_size(self) -> torch.Tensor:
        """``[3]`` world size of one cell."""
        return (self.bbox[1] - self.bbox[0]) / self.res

    def occupancy(self) -> float:
        """Fraction of occupied cells."""
        return float(self.mask.float().mean())

    def cell_points(self, flat_idx: torch.Tensor, generator: torch.Generator | None = None
                    ) -> torch.Tensor:
        """A uniform random world point ``[M, 3]`` inside each cell ``flat_idx [M]`` (x-major)."""
        r = self.res
        ijk = torch.stack([flat_idx // (r * r), (flat_idx // r) % r, flat_idx % r], -1)
        u = torch.rand(ijk.shape, generator=generator, device=flat_idx.device)
        return self.bbox[0] + (ijk.float() + u) * self.cell_size

    def _occupied_cells(self, m: int, generator: torch.Generator | None,
                        sync_free: bool) -> torch.Tensor:
        """Up to ``m`` cells (int64 flat indices) drawn uniformly from the occupied ones: from
        the mask's ``nonzero`` list (a read-back; none when nothing is occupied), or with
        ``sync_free`` exactly ``m`` by ``multinomial`` over the mask (uniform over all cells
        when nothing is occupied)."""
        flat = self.mask.flatten()
        if sync_free:
            weights = flat.float() + (~flat.any()).float()
            return torch.multinomial(weights, m, replacement=True, generator=generator)
        occ = flat.nonzero()[:, 0]
        if not occ.numel():
            return occ
        pick = torch.randint(occ.numel(), (min(m, occ.numel()),), generator=generator,
                             device=occ.device)
        return occ[pick]

    @torch.no_grad()
    def update(self, density_fn: Callable[[torch.Tensor], torch.Tensor], threshold: float,
               decay: float, all_cells: bool = False, fraction: float = 1 / 16,
               generator: torch.Generator | None = None, chunk: int = 1 << 17,
               sync_free: bool = False) -> None:
        """Re-evaluate cells and refresh the mask.

        Args:
            density_fn: world points ``[N, 3]`` -> σ ``[N]``.
            threshold: density above which a cell counts as occupied (1/world-length).
            decay: multiplier applied to every cell's running density first (the trainer's:
                :data:`WARMUP_DECAY` in the warm-up, ``TrainConfig.occ_decay`` after it).
            all_cells: evaluate every cell (warm-up); otherwise ``fraction`` of the cells drawn
                uniformly plus as many drawn from the occupied ones.
            generator: source of the random cells and points.
            chunk: points per call of ``density_fn``.
            sync_free: read nothing back (the fixed-shape step, :mod:`.fixed`): the occupied
                cells are drawn by ``torch.multinomial`` over the mask (uniform over all
                cells when none is occupied) instead of from its ``nonzero`` list, and the
                threshold ``min(threshold, mean density)`` stays on the device. The same
                distribution of cells, another draw of the generator.
        """
        n = self.res ** 3
        dev = self.density.device
        if all_cells:
            idx = torch.arange(n, device=dev)
        else:
            m = max(1, int(n * fraction))
            idx = torch.cat([torch.randint(n, (m,), generator=generator, device=dev),
                             self._occupied_cells(m, generator, sync_free)])
        pts = self.cell_points(idx, generator)
        sig = torch.cat([density_fn(p).float() for p in pts.split(chunk)]) if len(pts) else pts[:, 0]
        sig = torch.nan_to_num(sig, nan=0.0, posinf=1e6).clamp(min=0.0)
        dens = self.density.flatten() * decay
        dens = dens.scatter_reduce(0, idx, sig, reduce="amax", include_self=True)
        self.density.copy_(dens.view_as(self.density))
        if sync_free:
            self.mask.copy_(self.density > dens.mean().clamp(max=float(threshold)))
        else:
            thresh = min(float(threshold), float(dens.mean()))
            self.mask.copy_(self.density > thresh)
        self.n_updates += 1
