"""The conversion's sampling on the field's device (issue 47, item 3): the σ grid, the per-voxel
averages of extraction and the refinement's scores and new leaves, computed where the network
runs.

On the host path (numpy, the CPU's, unchanged) every block of ``M`` cells makes its ``M S``
random points with numpy, uploads them (``12 M S`` bytes), and reads back every sample's
values (``4 M S D`` bytes: 3 GB for lego's 256³ grid at ``S = 8``, SH16) to average them on the
host. Here, for a field that evaluates on a GPU (:func:`sampling_device`), a block uploads only
its cell indices or boxes, draws the points on the device (a ``torch.Generator`` seeded like
the host's numpy one), evaluates the field, averages (:func:`average_samples_torch`, the twin
of :func:`.sampling.average_samples`) and scores (:func:`spread_torch`, the twin of the
refinement's ``_spread``) there, and reads back one row per cell: ``S`` times fewer bytes
and no per-sample work on the host. The σ grid's points are made on the device from the
grid's axes.

The same uniforms give the host's values to float32 rounding (tested); different generators
give different random points, so a GPU extraction is not bit-identical to a CPU one (as
before: the network's float sums differ anyway). A field without ``query_torch``
(:class:`~.field.AnalyticField`) and plain NeRFs (SH projection) stay on the host.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..sh import SH_C0

__all__ = ["sampling_device", "make_rng", "uniforms", "average_samples_torch", "spread_torch",
           "values_torch", "box_stats_device", "cell_stats_device", "density_grid_device"]


def sampling_device(field: Any) -> Any:
    """The torch device the conversion samples ``field`` on, or None for the host path: a
    field evaluated on a GPU that has ``query_torch`` (:class:`~.field.NeRFField`) is
    sampled there; everything on the CPU stays on numpy (its results unchanged)."""
    dev = getattr(field, "device", None)
    if dev is None or not hasattr(field, "query_torch") or getattr(dev, "type", "cpu") == "cpu":
        return None
    return dev


def make_rng(field: Any, seed: int) -> Any:
    """The random source of a sampling pass: a ``torch.Generator`` on the sampling device
    (:func:`sampling_device`), else ``np.random.default_rng(seed)``."""
    dev = sampling_device(field)
    if dev is None:
        return np.random.default_rng(seed)
    import torch

    gen = torch.Generator(device=dev)
    gen.manual_seed(int(seed))
    return gen


def uniforms(gen: Any, m: int, samples: int) -> Any:
    """float64 ``[m, samples, 3]`` uniforms in [0, 1) from ``gen`` on its device (the host
    path's ``rng.random((m, samples, 3))``)."""
    import torch

    return torch.rand((m, samples, 3), generator=gen, dtype=torch.float64, device=gen.device)


def average_samples_torch(vals: Any, h: Any, averaging: str = "mean") -> Any:
    """Twin of :func:`.sampling.average_samples` on tensors: float32 ``vals [M, S, D]``
    (σ ≥ 0 last), the voxel side ``h`` (world units, a float or ``[M]`` tensor) -> float32
    ``[M, D]``. The opacity average runs in float64 as the host's."""
    import torch

    if averaging == "mean":
        out = vals.mean(dim=1)
    else:
        m = vals.shape[0]
        # a tensor side per voxel, or one float for all (no upload)
        h = h.double()[:, None] if isinstance(h, torch.Tensor) else float(h)
        sig = vals[..., -1].double().clamp(min=0.0)
        alpha = -torch.expm1(-sig * h)                                   # [M, S]
        a_mean = alpha.mean(dim=1)
        s_op = (-torch.log1p(-a_mean.clamp(max=1.0))[:, None] / h)[:, 0]
        out = torch.empty((m, vals.shape[2]), dtype=torch.float32, device=vals.device)
        out[:, -1] = torch.where(torch.isfinite(s_op), torch.minimum(s_op, sig.mean(dim=1)),
                                 sig.amax(dim=1)).float()
        w = alpha.sum(dim=1, keepdim=True)
        wn = torch.where(w > 0, alpha / torch.where(w > 0, w, torch.ones_like(w)),
                         torch.full_like(alpha, 1.0 / vals.shape[1]))
        out[:, :-1] = torch.einsum("ms,msd->md", wn, vals[..., :-1].double()).float()
    out[:, -1].clamp_(min=0.0)
    return out


def _base_colour_torch(coeffs: Any, data_format: str, basis_dim: int) -> Any:
    c = coeffs.reshape(coeffs.shape[:-1] + (3, basis_dim))
    raw = SH_C0 * c[..., 0] if data_format.startswith("SH") else c.mean(dim=-1)
    return 1.0 / (1.0 + (-raw).exp())


def spread_torch(vals: Any, mean: Any, h: Any, data_format: str, basis_dim: int) -> Any:
    """Twin of the refinement's spread score: ``[M]`` float32 of samples ``vals [M, S, D]``
    around ``mean [M, D]`` with leaf side ``h [M]`` (world units), in float64 as the host's."""
    vals, mean, h = vals.double(), mean.double(), h.double()
    a = 1.0 - (-vals[..., -1] * h[:, None]).exp()
    a_mean = 1.0 - (-mean[:, -1] * h).exp()
    c = _base_colour_torch(vals[..., :-1], data_format, basis_dim)
    c_mean = _base_colour_torch(mean[:, :-1], data_format, basis_dim)
    e_sigma = (a - a_mean[:, None]).abs().mean(dim=1)
    e_col = (a * (c - c_mean[:, None, :]).abs().mean(dim=-1)).mean(dim=1)
    return (e_sigma + e_col).float()


def values_torch(field: Any, pts: Any, dim: int) -> tuple[Any, Any]:
    """``(values [N, dim], non-finite count [])`` of the field at float32 points ``pts [N, 3]``:
    the coefficients, then σ ≥ 0; non-finite values are 0 (the count stays on the device)."""
    import torch

    from ..errors import ConfigError

    sigma, coeffs = field.query_torch(pts)
    if coeffs.shape != (pts.shape[0], dim - 1) or sigma.shape != (pts.shape[0],):
        raise ConfigError(f"field.query returned sigma {list(sigma.shape)} and coefficients "
                          f"{list(coeffs.shape)} for {pts.shape[0]} points; expected "
                          f"[{pts.shape[0]}] and [{pts.shape[0]}, {dim - 1}]")
    vals = torch.cat([coeffs.float(), sigma.float()[:, None]], dim=1)
    bad = ~torch.isfinite(vals)
    vals = torch.where(bad, torch.zeros((), device=vals.device), vals)
    vals[:, -1].clamp_(min=0.0)
    return vals, bad.sum()


def _points(lo: Any, size: Any, u: Any) -> Any:
    """``lo [M, 3] + u [M, S, 3] * size [M, 3]`` in float64, as float32 ``[M S, 3]``."""
    return (lo[:, None, :] + u * size[:, None, :]).float().reshape(-1, 3)


def box_stats_device(field: Any, lo: np.ndarray, size: np.ndarray, samples: int, gen: Any,
                     tree: Any, averaging: str = "mean", spread: bool = True
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """The refinement's ``_box_stats`` on the field's device: average ``[M, D]`` and spread
    ``[M]`` (None without ``spread``) of ``samples`` uniform points (``gen``) in each world box
    ``lo [M, 3] + [0, size [M, 3]]``; ``tree`` gives the value layout. Uploads the boxes,
    reads back one row per box."""
    import torch

    boxes = torch.from_numpy(np.concatenate([lo, size], axis=1).astype(np.float64)).to(
        gen.device)                                                      # one upload
    lo_t, size_t = boxes[:, :3], boxes[:, 3:]
    m = boxes.shape[0]
    vals, _ = values_torch(field, _points(lo_t, size_t, uniforms(gen, m, samples)),
                           tree.data_dim)
    vals = vals.reshape(m, samples, -1)
    h = size_t.mean(dim=1)
    mean = average_samples_torch(vals, h, averaging)
    if not spread:
        return mean.cpu().numpy(), None
    e = spread_torch(vals, mean, h, tree.data_format, tree.basis_dim)
    both = torch.cat([mean, e[:, None]], dim=1).cpu().numpy()          # one read-back
    return np.ascontiguousarray(both[:, :-1]), np.ascontiguousarray(both[:, -1])


def cell_stats_device(field: Any, spec: Any, flat: np.ndarray, samples: int, gen: Any,
                      dim: int, averaging: str, h: float) -> tuple[np.ndarray, Any]:
    """:func:`.sampling.sample_cells`' block on the field's device: the averages ``[M, dim]``
    of cells ``flat [M]`` (C-order indices of ``spec``) from ``samples`` points each
    (``gen``), and the non-finite count (a device tensor). Uploads the indices, reads back one
    row per cell."""
    import torch

    # one upload: the indices (exact in float64 below 2^53), then the grid's corner and cell
    packed = torch.from_numpy(np.concatenate([np.asarray(flat, np.float64), spec.lo,
                                              spec.cell])).to(gen.device)
    idx, lo, cell = packed[:-6].long(), packed[-6:-3], packed[-3:]
    r = spec.res
    ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], dim=-1).double()
    u = uniforms(gen, idx.shape[0], samples)
    pts = (lo + (ijk[:, None, :] + u) * cell).float().reshape(-1, 3)   # as grid.cell_points
    vals, bad = values_torch(field, pts, dim)
    mean = average_samples_torch(vals.reshape(idx.shape[0], samples, dim), h, averaging)
    return mean.cpu().numpy(), bad


def density_grid_device(field: Any, spec: Any, flat_out: np.ndarray, chunk: int, bar: Any
                        ) -> None:
    """:func:`.grid.evaluate_density_grid` on the field's device: σ ≥ 0 at every cell centre
    of ``spec`` into ``flat_out [R³]`` (C order), ``chunk`` points per call; the points are
    made on the device from the grid's axes (uploaded once), σ read back per chunk."""
    import torch

    dev = sampling_device(field)
    r = spec.res
    ax = [torch.from_numpy(spec.axis(a).astype(np.float32)).to(dev) for a in range(3)]
    n = r ** 3
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        idx = torch.arange(s, e, dtype=torch.int64, device=dev)
        pts = torch.stack([ax[0][idx // (r * r)], ax[1][(idx // r) % r], ax[2][idx % r]], -1)
        sig = field.density_torch(pts)
        flat_out[s:e] = torch.where(sig > 0, sig, torch.zeros((), device=dev)).cpu().numpy()
        bar.update(e - s)
