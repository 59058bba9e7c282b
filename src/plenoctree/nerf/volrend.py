"""Volume rendering of NeRF samples, eq. (1)–(2) of the paper, as small functional pieces.

For one ray with samples ``i = 0..N-1`` of density ``σ_i`` over segments of length ``δ_i``::

    α_i = 1 - exp(-σ_i δ_i)
    T_i = exp(-Σ_{j<i} σ_j δ_j)            (transmittance before sample i)
    w_i = T_i α_i                          (eq. 1's weight)
    C   = Σ_i w_i c_i + (1 - Σ_i w_i) · background

Two layouts: dense ``[R, S]`` (every ray has ``S`` samples; the hierarchical sampler) and packed
``[M]`` with a ray index per sample (the occupancy sampler, see
:class:`~plenoctree.nerf.sampling.PackedSamples`). Everything is differentiable.

Example::

    >>> import torch
    >>> w, T = render_weights(torch.tensor([[1.0, 1.0]]), torch.tensor([[1.0, 1.0]]))
    >>> [round(v, 4) for v in w[0].tolist()]
    [0.6321, 0.2325]
"""

from __future__ import annotations

import torch

__all__ = [
    "deltas_from_t",
    "render_weights",
    "composite",
    "render_weights_packed",
    "composite_packed",
    "distortion",
    "distortion_packed",
]


def deltas_from_t(t: torch.Tensor, last: float = 1e10) -> torch.Tensor:
    """Segment lengths ``δ_i = t_{i+1} - t_i`` of sorted samples ``t [R, S]``; the last is ``last``.

    ``last = 1e10`` is NeRF's convention (the last sample absorbs what is left).
    """
    return torch.cat([t[:, 1:] - t[:, :-1], torch.full_like(t[:, :1], last)], dim=-1)


def render_weights(sigma: torch.Tensor, deltas: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights of eq. (1)–(2), dense layout.

    Args:
        sigma: ``[R, S]`` densities ≥ 0 (1/world-length). deltas: ``[R, S]`` lengths (world).

    Returns:
        ``(weights [R, S], transmittance [R, S])``; ``transmittance[:, i]`` is ``T_i``.
    """
    tau = sigma * deltas
    excl = torch.cumsum(tau, dim=-1) - tau
    trans = torch.exp(-excl)
    return trans * (1.0 - torch.exp(-tau)), trans


def composite(weights: torch.Tensor, rgb: torch.Tensor, t: torch.Tensor | None = None,
              background: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Composite sample colours, dense layout.

    Args:
        weights: ``[R, S]``. rgb: ``[R, S, 3]`` in [0, 1]. t: ``[R, S]`` sample distances (for
            depth) or None. background: ``[3]`` or ``[R, 3]`` colour, or None (black).

    Returns:
        ``(rgb [R, 3], acc [R], depth [R] or None)``; depth is ``Σ w t / max(Σ w, 1e-10)``.
    """
    acc = weights.sum(-1)
    color = (weights[..., None] * rgb).sum(-2)
    if background is not None:
        color = color + (1.0 - acc)[:, None] * background
    depth = None if t is None else (weights * t).sum(-1) / acc.clamp(min=1e-10)
    return color, acc, depth


def render_weights_packed(sigma: torch.Tensor, deltas: torch.Tensor | float,
                          ray_idx: torch.Tensor, offsets: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights of eq. (1)–(2) for packed samples.

    Args:
        sigma: ``[M]`` densities of samples stored ray after ray. deltas: ``[M]`` or a scalar
            segment length. ray_idx: int64 ``[M]`` ray of each sample (non-decreasing).
        offsets: int64 ``[R + 1]``; ray ``r`` owns rows ``offsets[r]:offsets[r + 1]``.

    Returns:
        ``(weights [M], transmittance [M])`` float32. The per-ray prefix sums are done in float64
        (a batch-wide cumulative sum would otherwise lose the small optical depths).
    """
    tau = (sigma * deltas).double()
    if tau.numel() == 0:
        return sigma * 0.0, sigma * 0.0 + 1.0
    excl = torch.cumsum(tau, 0) - tau
    first = offsets[:-1].clamp(max=tau.shape[0] - 1)
    base = excl[first]                                               # [R]
    trans = torch.exp(-(excl - base[ray_idx])).float()
    alpha = 1.0 - torch.exp(-tau.float())
    return trans * alpha, trans


def composite_packed(weights: torch.Tensor, values: torch.Tensor, ray_idx: torch.Tensor,
                     n_rays: int) -> torch.Tensor:
    """Per-ray sums ``Σ_i w_i v_i`` of packed samples: ``[M]`` × ``[M, C]`` -> ``[R, C]``.

    With ``values = rgb`` this is the colour before the background; with
    ``values = ones [M, 1]`` the opacity ``Σ w``; with ``t[:, None]`` the unnormalised depth.
    """
    out = torch.zeros((n_rays, values.shape[-1]), dtype=values.dtype, device=values.device)
    return out.index_add(0, ray_idx, weights[:, None].to(values.dtype) * values)


def distortion(weights: torch.Tensor, t: torch.Tensor, delta: float) -> torch.Tensor:
    """Distortion loss of mip-NeRF 360 (Barron et al. 2022, eq. 15) per ray, dense layout; the
    direct O(S²) sum, the twin :func:`distortion_packed` is tested against.

    Each sample stands for the interval of length ``delta`` centred on ``t``::

        L = Σ_i Σ_j w_i w_j |t_i - t_j| + (δ / 3) Σ_i w_i²

    The first term is small when a ray's weight sits in one place (a surface), the second when
    it sits in few samples; a fog spread along the ray pays for every pair of its samples.

    Args:
        weights: ``[R, S]``. t: ``[R, S]`` sample distances (any unit; ``L`` is in that unit).
        delta: the common interval length, same unit as ``t``.

    Returns:
        ``[R]``.
    """
    pair = (weights[:, :, None] * weights[:, None, :]
            * (t[:, :, None] - t[:, None, :]).abs()).sum((1, 2))
    return pair + delta / 3.0 * (weights ** 2).sum(-1)


def distortion_packed(weights: torch.Tensor, t: torch.Tensor, delta: float,
                      ray_idx: torch.Tensor, offsets: torch.Tensor, n_rays: int
                      ) -> torch.Tensor:
    """:func:`distortion` of packed samples in O(M): with the samples of a ray in increasing
    ``t``, ``Σ_ij w_i w_j |t_i - t_j| = 2 Σ_i w_i (t_i W_i - S_i)`` where ``W_i = Σ_{j<i} w_j``
    and ``S_i = Σ_{j<i} w_j t_j`` (per-ray exclusive prefix sums, in float64).

    Args:
        weights, t: ``[M]``, ray after ray, increasing ``t`` within a ray. delta: interval length.
        ray_idx: int64 ``[M]`` (non-decreasing). offsets: int64 ``[R + 1]``. n_rays: ``R``.

    Returns:
        ``[R]`` in the dtype of ``weights`` (0 for rays without samples); differentiable in
        ``weights``.
    """
    if weights.numel() == 0:
        return weights.new_zeros(n_rays)
    w = weights.double()
    wt = w * t.double()
    first = offsets[:-1].clamp(max=w.shape[0] - 1)

    def excl(x: torch.Tensor) -> torch.Tensor:
        c = torch.cumsum(x, 0) - x
        return c - c[first][ray_idx]

    per_sample = 2.0 * w * (t.double() * excl(w) - excl(wt)) + delta / 3.0 * w * w
    out = torch.zeros(n_rays, dtype=torch.float64, device=w.device)
    return out.index_add(0, ray_idx, per_sample).to(weights.dtype)
