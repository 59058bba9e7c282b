"""Input encodings of the NeRF-SH network: NeRF positional encoding and a multiresolution grid.

* :class:`PositionalEncoding` — NeRF's ``γ(x) = (x, sin(2^0 x), cos(2^0 x), …, sin(2^{L-1} x),
  cos(2^{L-1} x))`` per coordinate (the paper's encoding; 10 frequencies for positions, 4 for
  view directions).
* :class:`HashGridEncoding` — a multiresolution feature grid (coarse levels dense, fine levels
  hashed into a fixed-size table, trilinear interpolation). The CPU preset's encoding: on two
  cores it decides everything (see ``/work/shared/reference/cpu-measurements.md``). Two
  interchangeable backends with the same numbers: compiled numba kernels
  (:mod:`._hashgrid_numba`, CPU) and the pure-torch twin :func:`_hashgrid_encode_torch`
  (the specification, the autograd oracle, and the CUDA path).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from .. import backend as _backend
from ..errors import ConfigError

__all__ = [
    "PositionalEncoding",
    "HashGridEncoding",
    "HashGridLayout",
    "hashgrid_levels",
]

_P1 = 2654435761
_P2 = 805459861


class PositionalEncoding(nn.Module):
    """NeRF positional encoding.

    ``forward(x [..., D]) -> [..., D * (2 * n_freqs + include_input)]``, laid out as
    ``[x, sin(2^0 x), …, sin(2^{L-1} x), cos(2^0 x), …, cos(2^{L-1} x)]`` where each block is
    ``D`` wide (the jaxnerf ordering). ``n_freqs = 0`` gives ``x`` itself.
    """

    def __init__(self, in_dim: int = 3, n_freqs: int = 10, include_input: bool = True):
        super().__init__()
        if n_freqs < 0:
            raise ConfigError(f"positional encoding: n_freqs must be >= 0, got {n_freqs}")
        self.in_dim = in_dim
        self.n_freqs = n_freqs
        self.include_input = include_input
        self.register_buffer("scales", 2.0 ** torch.arange(n_freqs, dtype=torch.float32),
                             persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (2 * self.n_freqs + int(self.include_input))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        parts = [x] if self.include_input else []
        if self.n_freqs:
            xb = (x[..., None, :] * self.scales.to(x.dtype)[:, None]).flatten(-2)  # [..., L*D]
            parts += [torch.sin(xb), torch.cos(xb)]
        return torch.cat(parts, dim=-1)


def hashgrid_levels(n_levels: int, base_res: int, max_res: int, log2_table: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-level layout of a multiresolution grid.

    Resolutions grow geometrically: ``r_l = floor(base_res · b^l)``, ``b = (max_res /
    base_res)^(1 / (n_levels - 1))``. A level whose ``(r_l + 1)^3`` vertices fit in
    ``2^log2_table`` rows is stored densely, the others are hashed into exactly
    ``2^log2_table`` rows.

    Returns:
        ``(res int64 [L], offsets int64 [L + 1], hashed bool [L])``; level ``l`` owns table rows
        ``offsets[l] : offsets[l + 1]``.
    """
    if n_levels < 1 or base_res < 1 or max_res < base_res or not 4 <= log2_table <= 30:
        raise ConfigError(
            f"hash grid: need n_levels >= 1, 1 <= base_res <= max_res, 4 <= log2_table <= 30; "
            f"got n_levels={n_levels}, base_res={base_res}, max_res={max_res}, "
            f"log2_table={log2_table}")
    growth = (max_res / base_res) ** (1.0 / max(n_levels - 1, 1))
    res = np.array([int(math.floor(base_res * growth ** lev + 1e-6)) for lev in range(n_levels)],
                   dtype=np.int64)
    cap = 1 << log2_table
    dense = (res + 1) ** 3
    hashed = dense > cap
    sizes = np.where(hashed, cap, dense)
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    return res, offsets, hashed


def _hashgrid_encode_torch(x: torch.Tensor, table: torch.Tensor, res: np.ndarray,
                           offsets: np.ndarray, hashed: np.ndarray) -> torch.Tensor:
    """Pure-torch twin of the grid encoding (the spec; differentiable in ``x`` and ``table``).

    Args:
        x: ``[N, 3]`` points in the unit cube (values outside are treated as on its faces).
        table: ``[T, F]`` feature table.
        res, offsets, hashed: level layout from :func:`hashgrid_levels`.

    Returns:
        ``[N, L * F]`` features, level-major.
    """
    outs = []
    corners = torch.tensor([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)],
                           device=x.device)                                       # [8, 3]
    for lev in range(len(res)):
        r = int(res[lev])
        off = int(offsets[lev])
        size = int(offsets[lev + 1]) - off
        p = x * r
        i = torch.floor(p).clamp(0, r - 1)
        f = p - i                                                                 # [N, 3]
        iv = i.long()[:, None, :] + corners                                       # [N, 8, 3]
        if hashed[lev]:
            idx = (iv[..., 0] ^ (iv[..., 1] * _P1) ^ (iv[..., 2] * _P2)) & (size - 1)
        else:
            idx = iv[..., 0] + iv[..., 1] * (r + 1) + iv[..., 2] * (r + 1) ** 2
        w3 = torch.where(corners.bool(), f[:, None, :], 1.0 - f[:, None, :])      # [N, 8, 3]
        w = w3.prod(-1)                                                           # [N, 8]
        feats = table[off + idx]                                                  # [N, 8, F]
        outs.append((w[..., None] * feats).sum(1))
    return torch.cat(outs, dim=-1)


class _HashGridNumba(torch.autograd.Function):
    """numba forward/backward; gradient w.r.t. the table only (points are not learnable).

    With ``in_place`` the backward pass adds the table gradient straight into ``table.grad``
    (creating it when ``None``) and returns no gradient for the table: several encodings per
    step (the trainer's marching waves) then share one gradient buffer instead of each
    zero-filling and adding a table-sized tensor. That mode serves ``loss.backward()`` only,
    not ``torch.autograd.grad``.
    """

    @staticmethod
    def forward(ctx, x, table, res, offsets, hashed, in_place):
        from . import _hashgrid_numba as K

        x = x.detach().contiguous()
        n_feat = table.shape[1]
        out = torch.empty((x.shape[0], len(res) * n_feat), dtype=torch.float32)
        K.hashgrid_forward(x.numpy(), table.detach().contiguous().numpy(), res, offsets, hashed,
                           out.numpy())
        ctx.save_for_backward(x)
        ctx.layout = (res, offsets, hashed, table.shape)
        ctx.table = table if in_place else None
        return out

    @staticmethod
    def backward(ctx, grad_out):
        from . import _hashgrid_numba as K

        (x,) = ctx.saved_tensors
        res, offsets, hashed, tshape = ctx.layout
        g = grad_out.float().contiguous()                                    # [N, L * F]
        table = ctx.table
        if table is not None:
            if table.grad is None:
                table.grad = torch.zeros(tshape, dtype=torch.float32)
            K.hashgrid_backward(x.numpy(), g.numpy(), res, offsets, hashed, table.grad.numpy())
            return None, None, None, None, None, None
        grad_table = torch.zeros(tshape, dtype=torch.float32)
        K.hashgrid_backward(x.numpy(), g.numpy(), res, offsets, hashed, grad_table.numpy())
        return None, grad_table, None, None, None, None


def _hashgrid_numba_run(enc: "HashGridEncoding", points: torch.Tensor) -> torch.Tensor:
    x = enc.normalize(points)
    return _HashGridNumba.apply(x, enc.table, enc.res, enc.offsets, enc.hashed,
                                enc.grad_in_place and torch.is_grad_enabled())


def _hashgrid_torch_run(enc: "HashGridEncoding", points: torch.Tensor) -> torch.Tensor:
    x = enc.normalize(points)
    return _hashgrid_encode_torch(x, enc.table, enc.res, enc.offsets, enc.hashed)


@dataclass(frozen=True)
class HashGridLayout:
    """The levels of a :class:`HashGridEncoding` (see :func:`hashgrid_levels`).

    Attributes:
        n_levels, n_features: levels and features per level (16 × 2 by default).
        base_res, max_res: resolution of the coarsest and finest level (cells per axis).
        log2_table: rows per hashed level, as a power of two.
    """

    n_levels: int = 16
    n_features: int = 2
    base_res: int = 16
    max_res: int = 1024
    log2_table: int = 18


class HashGridEncoding(nn.Module):
    """Multiresolution grid encoding over an axis-aligned box.

    ``forward(points [N, 3] world) -> [N, n_levels * n_features]`` (float32). Points are mapped
    to the unit cube by ``bbox`` (``[2, 3]`` min/max corner) and clamped to it.

    Args:
        bbox: ``[2, 3]`` world box covered by the grid.
        layout: levels, features, resolutions, table size (:class:`HashGridLayout`).
        backend: ``"auto"`` (numba for CPU tensors, torch otherwise), ``"numba"`` or ``"torch"``.
        init_scale: table entries start uniform in ``[-init_scale, init_scale]``.
        generator: the noise of the initial table.
    """

    def __init__(self, bbox, layout: HashGridLayout = HashGridLayout(), backend: str = "auto",
                 init_scale: float = 1e-4, generator: torch.Generator | None = None):
        super().__init__()
        backend = _backend.check_name("hashgrid", backend)
        n_levels, n_features = layout.n_levels, layout.n_features
        self.res, self.offsets, self.hashed = hashgrid_levels(n_levels, layout.base_res,
                                                              layout.max_res, layout.log2_table)
        self.n_levels, self.n_features = n_levels, n_features
        self.backend = backend
        self.grad_in_place = False   # see _HashGridNumba; the trainer turns it on
        self.register_buffer("bbox", torch.as_tensor(np.asarray(bbox, dtype=np.float32)))
        table = torch.empty((int(self.offsets[-1]), n_features), dtype=torch.float32)
        table.uniform_(-init_scale, init_scale, generator=generator)
        self.table = nn.Parameter(table)

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    def extra_repr(self) -> str:
        return (f"levels={self.n_levels}, features={self.n_features}, res={self.res.tolist()}, "
                f"dense_levels={int((~self.hashed).sum())}, rows={int(self.offsets[-1])}")

    def resolve_backend(self, device: torch.device) -> str:
        """The backend :meth:`forward` uses for tensors on ``device``."""
        return _backend.resolve("hashgrid", self.backend, device)

    def normalize(self, points: torch.Tensor) -> torch.Tensor:
        """World ``[N, 3]`` -> unit cube ``[N, 3]`` (clamped), float32."""
        lo, hi = self.bbox[0], self.bbox[1]
        return ((points.float() - lo) / (hi - lo)).clamp(0.0, 1.0)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        # op "hashgrid" takes the world points: each backend maps them to the unit cube
        # (normalize; the Triton kernel in its own launch)
        return _backend.implementation("hashgrid", self.resolve_backend(points.device))(
            self, points)
