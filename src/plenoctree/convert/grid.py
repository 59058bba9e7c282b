"""Evaluating σ on a regular grid over a box, in bounded memory.

A :class:`GridSpec` is a ``R³`` grid of cells over the world box ``center ± radius`` (radius
per axis). Cell ``(i, j, k)`` (``i`` along x) spans ``lo + [i, i+1) · cell`` with
``lo = center - radius`` and ``cell = 2 radius / R``; its centre is ``lo + (i + ½) · cell``.
With ``R = 2^d`` it is exactly the grid of the deepest level of an octree over the same box
(``Octree.from_grid``).

:func:`evaluate_density_grid` fills a float32 ``[R, R, R]`` σ array slab by slab, calling the
field on at most ``chunk`` points at a time; besides the output it holds only one chunk of
points and the field's temporaries for them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._util import progress
from ..errors import ConfigError
from . import device_sampling

__all__ = ["GridSpec", "evaluate_density_grid", "cell_points", "check_resolution"]


def check_resolution(name: str, res: Any, power_of_two: bool = True, low: int = 2,
                     high: int = 2048) -> int:
    """``res`` as an int after checking it is an integer in ``[low, high]`` (and a power of 2)."""
    if isinstance(res, bool) or not isinstance(res, (int, np.integer)):
        raise ConfigError(f"{name} must be an integer, got {res!r}")
    r = int(res)
    if not low <= r <= high or (power_of_two and r & (r - 1)):
        kind = "a power of two" if power_of_two else "an integer"
        raise ConfigError(f"{name} must be {kind} in [{low}, {high}], got {r}")
    return r


@dataclass(frozen=True)
class GridSpec:
    """A ``res³`` grid of cells over ``center ± radius`` (world units).

    Attributes:
        center: float64 ``[3]``. radius: float64 ``[3]`` half sides (> 0). res: cells per axis.
    """

    center: np.ndarray
    radius: np.ndarray
    res: int

    @classmethod
    def make(cls, center: Any, radius: Any, res: int) -> "GridSpec":
        c = np.broadcast_to(np.asarray(center, dtype=np.float64), (3,)).copy()
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (3,)).copy()
        if not (np.isfinite(c).all() and np.isfinite(r).all() and (r > 0).all()):
            raise ConfigError(f"box: need a finite center and radius > 0, got center "
                              f"{c.tolist()}, radius {r.tolist()}")
        return cls(c, r, int(res))

    @property
    def lo(self) -> np.ndarray:
        """``[3]`` world corner of cell (0, 0, 0)."""
        return self.center - self.radius

    @property
    def hi(self) -> np.ndarray:
        return self.center + self.radius

    @property
    def cell(self) -> np.ndarray:
        """``[3]`` world side of one cell per axis."""
        return 2.0 * self.radius / self.res

    @property
    def n_cells(self) -> int:
        return self.res ** 3

    def axis(self, a: int) -> np.ndarray:
        """World coordinates ``[res]`` of the cell centres along axis ``a``."""
        return self.lo[a] + (np.arange(self.res) + 0.5) * self.cell[a]

    def centers(self, flat: np.ndarray) -> np.ndarray:
        """World centres ``[M, 3]`` float64 of cells with C-order flat indices ``flat [M]``."""
        ijk = np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), (self.res,) * 3), -1)
        return self.lo + (ijk + 0.5) * self.cell

    def describe(self) -> str:
        lo, hi = self.lo, self.hi
        return (f"{self.res}^3 grid over [{lo[0]:.3f}, {hi[0]:.3f}] x [{lo[1]:.3f}, {hi[1]:.3f}]"
                f" x [{lo[2]:.3f}, {hi[2]:.3f}]")


def cell_points(spec: GridSpec, flat: np.ndarray, samples: int,
                rng: np.random.Generator) -> np.ndarray:
    """``samples`` uniform random world points in each cell ``flat [M]``: float32 ``[M, S, 3]``."""
    ijk = np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), (spec.res,) * 3), -1)
    u = rng.random((len(ijk), samples, 3))
    return (spec.lo + (ijk[:, None, :] + u) * spec.cell).astype(np.float32)


def evaluate_density_grid(field: Any, spec: GridSpec, chunk: int = 1 << 16,
                          desc: str = "sigma grid", show_progress: bool | None = None,
                          out: np.ndarray | None = None) -> np.ndarray:
    """σ at the centres of every cell of ``spec``: float32 ``[R, R, R]`` (x, y, z), ≥ 0.

    Args:
        field: a :class:`~plenoctree.convert.field.RadianceField` (``density(points)``).
        spec: the grid.
        chunk: points per call of ``field.density`` (bounds the field's temporaries).
        out: optional float32 ``[R, R, R]`` array to fill (e.g. a memory map).

    Memory: the output (``4 R³`` bytes) plus one chunk of points and whatever the field needs
    for ``chunk`` points. NaN and negative σ are stored as 0.
    """
    if chunk < 1:
        raise ConfigError(f"chunk must be >= 1, got {chunk}")
    r = spec.res
    if out is None:
        out = np.empty((r, r, r), dtype=np.float32)
    flat_out = out.reshape(-1)
    ax = [spec.axis(a).astype(np.float32) for a in range(3)]
    n = r ** 3
    with progress(total=n, desc=desc, disable=None if show_progress is None
                  else not show_progress, unit="pt", unit_scale=True) as bar:
        if device_sampling.sampling_device(field) is not None:    # points made on the device
            device_sampling.density_grid_device(field, spec, flat_out, chunk, bar)
            return out
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            idx = np.arange(s, e, dtype=np.int64)
            pts = np.empty((e - s, 3), dtype=np.float32)
            pts[:, 0] = ax[0][idx // (r * r)]
            pts[:, 1] = ax[1][(idx // r) % r]
            pts[:, 2] = ax[2][idx % r]
            sig = np.asarray(field.density(pts), dtype=np.float32).reshape(-1)
            if sig.shape[0] != e - s:
                raise ConfigError(f"field.density returned {sig.shape[0]} values for {e - s} "
                                  "points")
            flat_out[s:e] = np.where(sig > 0, sig, 0.0)          # NaN -> 0 as well
            bar.update(e - s)
    return out
