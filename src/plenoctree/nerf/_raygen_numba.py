"""numba kernel of op ``ray_batch`` (:mod:`plenoctree.nerf.raygen`): the rays, targets,
backgrounds and box bounds of a training step from its uniform numbers, one ray per loop
iteration (``prange``). The rays in float64 and the colours and bounds in float32, each in
the torch twin's order (no fast-math: no fused multiply-adds). Imported lazily.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = ["ray_batch"]

_F1 = np.float32(1.0)
_TINY = np.float32(1e-12)       # ray_aabb's stand-in for a zero direction component


@njit(cache=True, inline="always")
def _pinhole(c2w, intr, img, col, row):
    """World origin and unit direction (float64) of pixel ``(col, row)`` of camera ``img``,
    as :meth:`~plenoctree.datasets.Cameras.pixel_rays`."""
    x = (col + 0.5 - intr[img, 2]) / intr[img, 0]
    y = -(row + 0.5 - intr[img, 3]) / intr[img, 1]
    dx = c2w[img, 0, 0] * x + c2w[img, 0, 1] * y + c2w[img, 0, 2] * -1.0
    dy = c2w[img, 1, 0] * x + c2w[img, 1, 1] * y + c2w[img, 1, 2] * -1.0
    dz = c2w[img, 2, 0] * x + c2w[img, 2, 1] * y + c2w[img, 2, 2] * -1.0
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return c2w[img, 0, 3], c2w[img, 1, 3], c2w[img, 2, 3], dx / norm, dy / norm, dz / norm


@njit(cache=True, inline="always")
def _ndc(ox, oy, oz, dx, dy, dz, ax, ay, near):
    """NeRF's NDC ray (unit direction) of a world ray pointing down -z, as
    :func:`~plenoctree.datasets.ndc.to_ndc_rays` without clipping."""
    t = -(near + oz) / dz
    px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
    rx, ry = px / pz, py / pz
    nx, ny, nz = ax * (dx / dz - rx), ay * (dy / dz - ry), (-2.0 * near) / pz
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    return ax * rx, ay * ry, 1.0 + (2.0 * near) / pz, nx / norm, ny / norm, nz / norm


@njit(cache=True, inline="always")
def _slab(o, d, lo, hi):
    """``(t_near, t_far)`` of one axis (float32), as :func:`.sampling.ray_aabb`."""
    inv = _F1 / (_TINY if d == 0 else d)
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    return min(t0, t1), max(t0, t1)


@njit(cache=True, parallel=True)
def ray_batch(u, c2w, intr, images, alphas, bg_data, consts, bbox, height, width, mode, ndc,
              out_o, out_d, out_t, out_bg, t_min, t_max):
    """Fill the outputs of ``R = u.shape[0]`` rays.

    Args: u float64 ``[R, 4]``; c2w float64 ``[N, 4, 4]``; intr float64 ``[N, 4]`` (fx, fy,
    cx, cy); images float32 ``[N H W, 3]``; alphas float32 ``[N H W]`` (read in mode 1);
    bg_data float32 ``[3]``; consts float64 ``[5]`` (:func:`~.raygen.ray_constants`); bbox
    float32 ``[2, 3]``; height, width: pixels; mode: ``BG_*`` of :mod:`.raygen`; ndc: NDC rays.
    Outputs float32: out_o, out_d, out_t, out_bg ``[R, 3]``; t_min, t_max ``[R]``."""
    hw = height * width
    total = c2w.shape[0] * hw
    near, far = np.float32(consts[3]), np.float32(consts[4])
    for r in prange(u.shape[0]):
        p = min(np.int64(u[r, 0] * np.float64(total)), total - 1)
        img = p // hw
        row = (p - img * hw) // width
        col = p - img * hw - row * width
        ox, oy, oz, dx, dy, dz = _pinhole(c2w, intr, img, np.float64(col), np.float64(row))
        if ndc:
            ox, oy, oz, dx, dy, dz = _ndc(ox, oy, oz, dx, dy, dz, consts[0], consts[1],
                                          consts[2])
        o3 = (np.float32(ox), np.float32(oy), np.float32(oz))
        d3 = (np.float32(dx), np.float32(dy), np.float32(dz))
        t_near, t_far = -np.inf, np.inf
        for c in range(3):
            out_o[r, c] = o3[c]
            out_d[r, c] = d3[c]
            a, b = _slab(o3[c], d3[c], bbox[0, c], bbox[1, c])
            t_near, t_far = max(t_near, a), min(t_far, b)
            rgb = images[p, c]
            bg = np.float32(u[r, 1 + c]) if mode != 0 else bg_data[c]
            out_bg[r, c] = bg
            if mode == 1:
                oma = _F1 - alphas[p]
                rgb = rgb - oma * bg_data[c] + oma * bg
            out_t[r, c] = rgb
        t_min[r] = max(np.float32(t_near), near)
        t_max[r] = min(np.float32(t_far), far)
