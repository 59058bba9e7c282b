"""Per-voxel averaging (paper §4.2, *Sampling*): the value each leaf stores.

For every kept cell, ``S`` points are drawn uniformly inside it, the field is evaluated there
and the leaf gets an average of the samples' ``(raw coefficients, σ)`` — a box filter over
the voxel that reduces aliasing (paper: S = 256; original default 8). σ is clamped at 0.
:func:`average_samples` offers two averages:

- ``"mean"`` (the paper's): the plain mean of σ and of the coefficients. Where a surface cuts
  the voxel, half-dense samples give a mean σ that is still opaque over the voxel's side, so
  the whole voxel renders as surface (surfaces grow by up to a voxel);
- ``"opacity"``: σ such that the voxel's opacity over its side ``h`` is the mean of the
  samples' opacities, ``σ = -ln(1 - mean_s(1 - exp(-σ_s h))) / h`` (≤ the mean σ, equal where
  the field is uniform), and the coefficients averaged with the samples' opacities as weights
  (the colour of what a ray sees in the voxel, not of the empty samples; the plain mean where
  every sample is empty).

For a plain NeRF each sample point's colour is first projected onto SH
(:mod:`plenoctree.convert.projection`), then averaged the same way.

Work is done in blocks of cells so that one field call never sees more than ``chunk`` points
(``chunk / n_dirs`` points for projection); memory besides the output ``[M, D]`` is one block.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._util import progress
from ..errors import ConfigError
from ..octree.check import expected_data_dim
from ..sh import num_sh_bases
from . import device_sampling
from .grid import GridSpec, cell_points
from .projection import project_sh

__all__ = ["SamplingStats", "SampleOptions", "sample_cells", "output_format", "average_samples",
           "AVERAGING"]

AVERAGING = ("mean", "opacity")
"""The per-voxel averages of :func:`average_samples`."""


@dataclass
class SamplingStats:
    """Counters of :func:`sample_cells`: points evaluated, non-finite values replaced by 0."""

    points: int = 0
    nonfinite: int = 0


@dataclass(frozen=True)
class SampleOptions:
    """How :func:`sample_cells` samples each cell.

    Attributes:
        samples: S ≥ 1 uniform random points per cell.
        chunk: points per field call (for projection: point-direction pairs per call).
        seed: random seed (points and projection directions).
        averaging: ``"mean"`` or ``"opacity"`` (:func:`average_samples`; the voxel side is the
            mean of the cell's three sides).
        projection_degree, projection_dirs: a plain NeRF's colour is projected onto SH of this
            degree with this many directions per point.
        show_progress: progress bar (None: on a terminal).
    """

    samples: int = 8
    chunk: int = 1 << 16
    seed: int = 0
    averaging: str = "mean"
    projection_degree: int = 3
    projection_dirs: int = 10000
    show_progress: bool | None = None


def output_format(field: Any, projection_degree: int) -> tuple[str, np.ndarray | None, int]:
    """``(data_format, extra_data, data_dim)`` of the tree made from ``field``."""
    if field.basis == "plain":
        b = num_sh_bases(projection_degree)
        return f"SH{b}", None, 3 * b + 1
    fmt = str(field.data_format)
    extra = getattr(field, "extra_data", None)
    return fmt, extra, expected_data_dim(fmt)


def average_samples(vals: np.ndarray, h: np.ndarray | float, averaging: str = "mean"
                    ) -> np.ndarray:
    """One value per voxel from its samples (see the module docstring).

    Args:
        vals: float32 ``[M, S, D]`` samples: coefficients, then σ ≥ 0 (1 / world length).
        h: the voxel side (world units), a scalar or ``[M]``; only ``"opacity"`` uses it.
        averaging: ``"mean"`` or ``"opacity"``.

    Returns:
        float32 ``[M, D]``, σ ≥ 0 last.
    """
    if averaging == "mean":
        out = vals.mean(axis=1)
    elif averaging == "opacity":
        h = np.broadcast_to(np.asarray(h, np.float64), (vals.shape[0],))[:, None]
        sig = np.maximum(vals[..., -1].astype(np.float64), 0.0)
        alpha = -np.expm1(-sig * h)                              # [M, S]
        a_mean = alpha.mean(axis=1)
        out = np.empty((vals.shape[0], vals.shape[2]), np.float32)
        # -log1p(-a) / h, with a = 1 (every sample opaque to float precision) kept finite:
        # σ then stays the largest sample's (the voxel is opaque either way)
        with np.errstate(divide="ignore"):
            s_op = -np.log1p(-np.minimum(a_mean, 1.0)) / h[:, 0]
        out[:, -1] = np.where(np.isfinite(s_op), np.minimum(s_op, sig.mean(axis=1)),
                              sig.max(axis=1))
        w = alpha.sum(axis=1, keepdims=True)
        wn = np.where(w > 0, alpha / np.where(w > 0, w, 1.0), 1.0 / vals.shape[1])
        out[:, :-1] = np.einsum("ms,msd->md", wn, vals[..., :-1].astype(np.float64))
    else:
        raise ConfigError(f"averaging must be one of {', '.join(AVERAGING)}, got {averaging!r}")
    np.maximum(out[:, -1], 0.0, out=out[:, -1])
    return out.astype(np.float32, copy=False)


def sample_cells(field: Any, spec: GridSpec, flat: np.ndarray,
                 opts: SampleOptions = SampleOptions(), stats: SamplingStats | None = None
                 ) -> np.ndarray:
    """Average of ``opts.samples`` random samples of the field in each cell ``flat [M]``.

    Args:
        field: a radiance field; ``basis`` "sh"/"sg" are averaged directly, "plain" is projected
            onto SH of ``opts.projection_degree`` first.
        spec: the grid the flat (C-order) indices refer to.
        opts: samples per cell, chunk, seed, averaging, projection (:class:`SampleOptions`).
        stats: optional counters to fill.

    Returns:
        float32 ``[M, D]``: the coefficients then σ ≥ 0 (the octree leaf layout).
    """
    samples, chunk, averaging = opts.samples, opts.chunk, opts.averaging
    projection_degree, projection_dirs = opts.projection_degree, opts.projection_dirs
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ConfigError(f"samples per cell must be a positive integer, got {samples!r}")
    if chunk < 1:
        raise ConfigError(f"chunk must be >= 1, got {chunk}")
    if averaging not in AVERAGING:
        raise ConfigError(f"averaging must be one of {', '.join(AVERAGING)}, got {averaging!r}")
    h = float(np.mean(2.0 * spec.radius / spec.res))
    _, _, dim = output_format(field, projection_degree)
    plain = field.basis == "plain"
    flat = np.asarray(flat, dtype=np.int64)
    m = flat.size
    out = np.empty((m, dim), dtype=np.float32)
    pts_per_call = max(1, chunk // projection_dirs) if plain else chunk
    cells_per_block = max(1, pts_per_call // samples)
    st = stats if stats is not None else SamplingStats()
    show = opts.show_progress
    on_device = not plain and device_sampling.sampling_device(field) is not None
    rng = device_sampling.make_rng(field, opts.seed) if on_device else \
        np.random.default_rng(opts.seed)
    bad_dev = []                     # the device path's non-finite counts, read at the end
    with progress(total=m, desc="sampling", unit="voxel", unit_scale=True,
                  disable=None if show is None else not show) as bar:
        for s in range(0, m, cells_per_block):
            block = flat[s:s + cells_per_block]
            if on_device:            # points, field, average on the device (.device_sampling)
                out[s:s + len(block)], bad = device_sampling.cell_stats_device(
                    field, spec, block, samples, rng, dim, averaging, h)
                bad_dev.append(bad)
                st.points += len(block) * samples
                bar.update(len(block))
                continue
            pts = cell_points(spec, block, samples, rng).reshape(-1, 3)
            if plain:
                sigma, coeffs = project_sh(field, pts, projection_degree, projection_dirs, rng)
            else:
                sigma, coeffs = field.query(pts)
            sigma = np.asarray(sigma, np.float32).reshape(-1)
            coeffs = np.asarray(coeffs, np.float32)
            if coeffs.shape != (len(pts), dim - 1) or sigma.shape != (len(pts),):
                raise ConfigError(f"field.query returned sigma {list(sigma.shape)} and "
                                  f"coefficients {list(coeffs.shape)} for {len(pts)} points; "
                                  f"expected [{len(pts)}] and [{len(pts)}, {dim - 1}] "
                                  f"({field.data_format})")
            vals = np.concatenate([coeffs, sigma[:, None]], axis=1)
            bad = ~np.isfinite(vals)
            if bad.any():
                st.nonfinite += int(bad.sum())
                vals[bad] = 0.0
            st.points += len(pts)
            out[s:s + len(block)] = average_samples(vals.reshape(len(block), samples, dim), h,
                                                    averaging)
            bar.update(len(block))
    if bad_dev:                      # one read-back for the whole pass
        import torch

        st.nonfinite += int(torch.stack(bad_dev).sum())
    return out
