"""The numba CPU kernel of the octree renderer (imported lazily on first use; compiles once,
cached on disk), and its per-ray counters.

Same semantics as the torch twin (:mod:`plenoctree.render._torch_impl`, the spec); the
traversal is :mod:`._march_numba`'s, shared with the fine-tuning kernels. Per ray: the
direction, its tree-space version, its reciprocal and the SH/SG basis are computed once;
leaves with σ ≤ 0 are skipped without touching their colour coefficients (and, with a tree's
empty-space skip tables, :mod:`.empty_skip`, whole empty regions in one segment); early termination
when T < stop_thresh. Rays of an image are processed in 24×24-pixel tiles (neighbouring rays,
also those of the row above, share nodes and leaves in cache), handed to the threads one at a
time from a shared counter (:mod:`._schedule_numba`): numba's ``prange`` gives each thread one
contiguous run of tiles (also with ``numba.set_parallel_chunksize``, under the omp and workqueue
threading layers) and an image's cost sits where the object is: at 16 threads the busiest
thread had twice the mean work on lego (``benchmarks/render_scaling.py`` counts it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numba import njit, prange

from ._march_numba import (MARCH_MATH, MAX_LEVEL, MAX_STEPS, QUEUE, STACK_SIZE, basis_values,
                           leaf_logits, look_ahead, next_leaf, ray_octant, ray_start)
from ._schedule_numba import next_item
from ._spec import TreeSpec, tree_spec
from .empty_skip import SkipTables
from .options import FormatInfo, RenderOptions

__all__ = ["render_rays_numba", "ray_stats_numba", "prepare", "render_prepared", "Launch",
           "pack_camera", "pack_cameras", "render_camera_prepared", "empty_outputs", "TILE",
           "TILE_2D", "STAT_NAMES"]

TILE = 64          # rays per work item when the image width is unknown (one row of rays)
#: Pixels per work item of an image. 8×8 was 1.2× faster than 64×1 rows on lego's 256³ tree;
#: 24×24 is as fast there and 1.09–1.12× faster at 400² on the refined trees (1.5–2 GB of rows:
#: a tile's next pixel row finds the leaves of the row above still in cache).
TILE_2D = (24, 24)

_ONE32 = np.float32(1.0)
_QMASK = QUEUE - 1

#: Columns of :func:`ray_stats_numba`'s output, per ray.
STAT_NAMES = ("leaves", "sigma_leaves", "negligible", "descent", "hit", "stopped")
NEGLIGIBLE_WEIGHT = 1e-4   # a σ > 0 segment with w = T (1 - e^{-σδ}) below this is "negligible"


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _render_one(child, skip, shift, data, offset, invr, ox, oy, oz, dx, dy, dz, kind, n_b, sg,
                b_lo, b_hi, stop, eps, use_stack, max_level, max_steps, basis, st, stack, qc, qe,
                out3):
    """March one ray (at most ``max_steps`` segments, looked up ahead of shading by
    :func:`look_ahead`); returns (T, Σw, Σw t_mid) and writes Σ w c into ``out3``."""
    out3[0] = 0.0
    out3[1] = 0.0
    out3[2] = 0.0
    dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, eps_t = ray_start(
        offset, invr, ox, oy, oz, dx, dy, dz, eps)
    if not t0 < t1:
        return 1.0, 0.0, 0.0
    basis_values(kind, n_b, dx, dy, dz, sg, b_lo, b_hi, basis)
    oc = ray_octant(vx, vy, vz)
    dim = data.shape[1]
    trans = 1.0
    w_sum = 0.0
    wt_sum = 0.0
    t = t0
    st[0] = 0
    st[1] = -1
    stack[0] = 0
    head = 0
    tail = 0
    tq = t0
    steps = 0
    while True:
        tail, tq, steps = look_ahead(child, skip, shift, oc, data, px, py, pz, vx, vy, vz, ix,
                                     iy, iz, eps_t, t1, use_stack, max_level, max_steps, st,
                                     stack, qc, qe, head, tail, tq, steps)
        if head == tail:
            break
        cell = qc[head & _QMASK]
        t_end = qe[head & _QMASK]
        head += 1
        if cell < 0:                    # an empty leaf (look_ahead): T unchanged
            t = t_end
            continue
        sigma = data[cell, dim - 1]
        if sigma > 0.0:
            att = math.exp(-sigma * (t_end - t))
            w = trans * (1.0 - att)
            # Colour in float32 (vectorised dot products, single-precision exp).
            ar, ag, ab = leaf_logits(data, cell, kind, n_b, basis)
            out3[0] += w / (_ONE32 + math.exp(-ar))
            out3[1] += w / (_ONE32 + math.exp(-ag))
            out3[2] += w / (_ONE32 + math.exp(-ab))
            w_sum += w
            wt_sum += w * 0.5 * (t + t_end)
            trans *= att
            if trans < stop:
                break
        t = t_end
    return trans, w_sum, wt_sum


#: ``cam[0]`` of :func:`_render_kernel`: rays read from arrays, or made per pixel from a camera.
CAM_ARRAYS, CAM_PINHOLE, CAM_NDC, CAM_NDC_CLIP = 0, 1, 2, 3
CAM_SIZE = 20
_MISS_Z = 1.0e4              # datasets.ndc.MISS_ORIGIN's z'
_CLIP_EXTENT = 1.0e4         # datasets.ndc.CLIP_EXTENT
_MIN_DZ = 1.0e-12            # datasets.ndc._MIN_DZ (keeps t finite: no isfinite under fastmath)


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _ndc_ray(cam, ox, oy, oz, ex, ey, ez, clip):
    """``to_ndc_rays`` (``clip``: its "any camera" rule) of the world ray ``o + t e``
    (float64 of the float32 ray), rounded to float32: ``(ox, oy, oz, dx, dy, dz)``."""
    near = cam[19]
    ok = True
    if clip and oz <= -near:          # past the near plane: start where the camera stands
        px = cam[17] * ox / oz
        py = cam[18] * oy / oz
        pz = 1.0 + 2.0 * near / oz
        nx = cam[17] * (ex * oz - ox * ez)
        ny = cam[18] * (ey * oz - oy * ez)
        nz = -2.0 * near * ez
        ok = nx != 0.0 or ny != 0.0 or nz != 0.0
    elif clip and not ez < -_MIN_DZ:  # never reaches the NDC volume
        px = py = pz = nx = ny = nz = 0.0
        ok = False
    else:                             # NeRF's ray from the near plane
        t = -(near + oz) / ez
        qx = ox + t * ex
        qy = oy + t * ey
        qz = oz + t * ez
        rx = qx / qz
        ry = qy / qz
        nx = cam[17] * (ex / ez - rx)
        ny = cam[18] * (ey / ez - ry)
        nz = -2.0 * near / qz
        px = cam[17] * rx
        py = cam[18] * ry
        pz = 1.0 + 2.0 * near / qz
    if clip and not (ok and abs(px) <= _CLIP_EXTENT and abs(py) <= _CLIP_EXTENT):
        return (np.float32(0.0), np.float32(0.0), np.float32(_MISS_Z), np.float32(0.0),
                np.float32(0.0), np.float32(1.0))
    nrm = math.sqrt(nx * nx + ny * ny + nz * nz)
    return (np.float32(px), np.float32(py), np.float32(pz), np.float32(nx / nrm),
            np.float32(ny / nrm), np.float32(nz / nrm))


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _camera_ray(cam, u, v):
    """The ray of pixel ``(u, v)`` of the camera packed in ``cam`` (see :func:`pack_camera`),
    float32-rounded as ``datasets.cameras.generate_rays`` (+ ``datasets.ndc.to_ndc_rays`` when
    ``cam[0]`` is ``CAM_NDC``, or ``CAM_NDC_CLIP`` with ``clip=True``) return it: ``(ox, oy, oz, dx, dy, dz)`` float32."""
    a = (u + 0.5 - cam[3]) / cam[1]
    b = -(v + 0.5 - cam[4]) / cam[2]
    x = a * cam[5] + b * cam[6] - cam[7]
    y = a * cam[8] + b * cam[9] - cam[10]
    z = a * cam[11] + b * cam[12] - cam[13]
    nrm = math.sqrt(x * x + y * y + z * z)
    dx = np.float32(x / nrm)
    dy = np.float32(y / nrm)
    dz = np.float32(z / nrm)
    ox = np.float32(cam[14])
    oy = np.float32(cam[15])
    oz = np.float32(cam[16])
    if cam[0] == CAM_NDC or cam[0] == CAM_NDC_CLIP:
        return _ndc_ray(cam, np.float64(ox), np.float64(oy), np.float64(oz), np.float64(dx),
                        np.float64(dy), np.float64(dz), cam[0] == CAM_NDC_CLIP)
    return ox, oy, oz, dx, dy, dz


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _render_kernel(child, skip, shift, data, offset, invr, origins, dirs, cam, kind, n_b, sg, b_lo,
                   b_hi, bg, stop, eps, use_stack, max_level, max_steps, n, width, tile_w, tile_h,
                   threads, renorm, rgb, depth, alpha):
    """``n`` rays ``i = y * width + x`` in tiles of ``tile_w × tile_h`` pixels (one work item
    each, handed out one at a time by :func:`._schedule_numba.next_item` to ``threads``
    workers, ``numba.get_num_threads()``): read from ``origins, dirs [n, 3]`` (``cam[0] ==
    CAM_ARRAYS``) or made for pixel ``(x, y)`` of the camera ``cam`` (:func:`_camera_ray`; the
    arrays are then unused). ``renorm``: a ray stopped early gets ``Σ w c / (1 - T)`` and alpha
    1 instead of the background (:attr:`~.options.RenderOptions.renormalize`)."""
    height = (n + width - 1) // width
    ntx = (width + tile_w - 1) // tile_w
    n_tiles = ntx * ((height + tile_h - 1) // tile_h)
    from_cam = cam[0] != CAM_ARRAYS
    counter = np.zeros(1, dtype=np.int64)
    for _ in prange(max(1, min(threads, n_tiles))):
        basis = np.zeros(max(25, n_b), dtype=np.float32)
        st = np.zeros(4, dtype=np.int64)
        stack = np.zeros(STACK_SIZE, dtype=np.int64)
        acc = np.zeros(3, dtype=np.float64)
        qc = np.zeros(QUEUE, dtype=np.int64)
        qe = np.zeros(QUEUE, dtype=np.float64)
        while True:
            tile = next_item(counter)
            if tile >= n_tiles:
                break
            ty = tile // ntx
            tx = tile - ty * ntx
            for y in range(ty * tile_h, min(height, (ty + 1) * tile_h)):
                for x in range(tx * tile_w, min(width, (tx + 1) * tile_w)):
                    i = y * width + x
                    if i >= n:
                        break
                    if from_cam:
                        ox, oy, oz, dx, dy, dz = _camera_ray(cam, x, y)
                    else:
                        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
                        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
                    trans, w_sum, wt_sum = _render_one(
                        child, skip, shift, data, offset, invr, ox, oy, oz, dx, dy, dz, kind,
                        n_b, sg, b_lo, b_hi, stop, eps, use_stack, max_level, max_steps, basis,
                        st, stack, qc, qe, acc)
                    depth[i] = wt_sum / max(w_sum, 1e-10)
                    if renorm and trans < stop:         # stopped early: svox's fast rule
                        for ch in range(3):
                            rgb[i, ch] = acc[ch] / (1.0 - trans)
                        alpha[i] = 1.0
                    else:
                        for ch in range(3):
                            rgb[i, ch] = acc[ch] + trans * bg[ch]
                        alpha[i] = 1.0 - trans


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _stats_kernel(child, skip, shift, data, offset, invr, origins, dirs, stop, eps, negligible,
                  max_level, max_steps, out):
    """Per-ray counters of the renderer's march (same segments, same early stop): ``out [N, 6]``
    int64 columns :data:`STAT_NAMES`."""
    n = origins.shape[0]
    dim = data.shape[1]
    for i in prange(n):
        st = np.zeros(4, dtype=np.int64)
        stack = np.zeros(STACK_SIZE, dtype=np.int64)
        for k in range(6):
            out[i, k] = 0
        dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, eps_t = ray_start(
            offset, invr, origins[i, 0], origins[i, 1], origins[i, 2], dirs[i, 0], dirs[i, 1],
            dirs[i, 2], eps)
        if not t0 < t1:
            continue
        oc = ray_octant(vx, vy, vz)
        out[i, 4] = 1
        trans = 1.0
        t = t0
        st[1] = -1
        while t < t1 and out[i, 0] < max_steps:
            cell, t_end, n_desc = next_leaf(child, skip, shift, oc, px, py, pz, vx, vy, vz, ix,
                                            iy, iz, t, eps_t, t1, True, max_level, st, stack)
            out[i, 0] += 1
            out[i, 3] += n_desc
            sigma = data[cell, dim - 1]
            if sigma > 0.0:
                att = math.exp(-sigma * (t_end - t))
                out[i, 1] += 1
                if trans * (1.0 - att) < negligible:
                    out[i, 2] += 1
                trans *= att
                if trans < stop:
                    out[i, 5] = 1
                    break
            t = t_end


def prepare(tree: Any, info: FormatInfo, options: RenderOptions) -> TreeSpec:
    """Pack ``tree`` (child, data, box, extra_data, and its ``empty_skip`` tables when it has
    them: see :func:`plenoctree.render.tree_to_device`) and ``options`` for
    :func:`render_prepared`: a :class:`~._spec.TreeSpec` holding the float32 values."""
    return tree_spec(tree, options, info=info, skip=getattr(tree, "empty_skip", None),
                     with_values=True)


def empty_outputs(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uninitialised float32 ``rgb [n, 3], depth [n], alpha [n]``."""
    return (np.empty((n, 3), dtype=np.float32), np.empty(n, dtype=np.float32),
            np.empty(n, dtype=np.float32))


_NO_RAYS = np.zeros((0, 3), dtype=np.float32)
_NO_CAM = np.zeros(CAM_SIZE, dtype=np.float64)


@dataclass(frozen=True)
class Launch:
    """How :func:`_render_kernel` walks the rays: ``width > 0``: they are the pixels of an image
    ``width`` wide (row-major), marched in ``tile = (w, h)`` pixel tiles (default
    :data:`TILE_2D`); ``width = 0``: rows of :data:`TILE` rays. ``use_stack=False`` re-descends
    from the root at every step (the reference the tests compare the ancestor stack against)."""

    width: int = 0
    tile: tuple[int, int] | None = None
    use_stack: bool = True


def _launch(p: TreeSpec, origins: np.ndarray, dirs: np.ndarray, cam: np.ndarray, n: int,
            out: tuple[np.ndarray, np.ndarray, np.ndarray], how: Launch) -> None:
    rgb, depth, alpha = out
    if n == 0:
        return
    width = how.width
    if width <= 0 or width > n:
        width, tw, th = n, TILE, 1
    else:
        tw, th = how.tile if how.tile is not None else TILE_2D
    p.launch(_render_kernel, None, (origins, dirs, cam),
             (bool(how.use_stack), MAX_LEVEL, MAX_STEPS, int(n), int(width), max(1, int(tw)),
              max(1, int(th)), numba.get_num_threads(), p.renorm, rgb.reshape(n, 3),
              depth.reshape(n), alpha.reshape(n)))


def render_prepared(p: TreeSpec, origins: np.ndarray, dirs: np.ndarray,
                    out: tuple[np.ndarray, np.ndarray, np.ndarray], use_stack: bool = True,
                    width: int = 0, tile: tuple[int, int] | None = None) -> None:
    """Render float32 contiguous ``origins, dirs [N, 3]`` with the values of ``p``
    (:func:`prepare`) into ``out = (rgb, depth, alpha)``; the other arguments: :class:`Launch`."""
    _launch(p, origins, dirs, _NO_CAM, int(origins.shape[0]), out,
            Launch(int(width), tile, use_stack))


def pack_camera(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                ndc: tuple[float, float, int, int, float] | None = None,
                clip: bool = False) -> np.ndarray:
    """float64 ``[CAM_SIZE]`` camera of :func:`render_camera_prepared`: ``c2w [4, 4]`` (or
    ``[3, 4]``, OpenGL), intrinsics in pixels, and for NDC rays ``ndc = (fx, fy, width,
    height, near)`` of the NDC reference camera (see :mod:`plenoctree.datasets.ndc`; ``clip``:
    its "any camera" rule, ``Cameras.ndc_clip``)."""
    m = np.asarray(c2w, dtype=np.float64)
    cam = np.zeros(CAM_SIZE, dtype=np.float64)
    cam[0] = CAM_PINHOLE if ndc is None else (CAM_NDC_CLIP if clip else CAM_NDC)
    cam[1:5] = fx, fy, cx, cy
    cam[5:14] = m[:3, :3].reshape(9)
    cam[14:17] = m[:3, 3].astype(np.float32)         # origins are float32, as generate_rays'
    if ndc is not None:
        nfx, nfy, nw, nh, near = (float(v) for v in ndc)
        cam[17:20] = -2.0 * nfx / nw, -2.0 * nfy / nh, near
    return cam


def pack_cameras(cameras: Any, indices: Any = None) -> np.ndarray:
    """float64 ``[M, CAM_SIZE]``: :func:`pack_camera` of each camera ``indices`` (default all)
    of a :class:`~plenoctree.datasets.Cameras`, with its own intrinsics and, for an NDC set,
    the NDC reference camera of the whole set (``cameras.ndc_focal``)."""
    idx = np.arange(len(cameras)) if indices is None else np.asarray(indices, np.int64)
    ndc = ((*cameras.ndc_focal, cameras.width, cameras.height, cameras.ndc_near)
           if cameras.ndc else None)
    out = np.empty((idx.size, CAM_SIZE), np.float64)
    for j, i in enumerate(idx):
        out[j] = pack_camera(cameras.c2w[int(i)], *cameras.intrinsics(int(i)), ndc=ndc,
                             clip=cameras.ndc_clip)
    return out


def render_camera_prepared(p: TreeSpec, cam: np.ndarray, width: int, height: int,
                           out: tuple[np.ndarray, np.ndarray, np.ndarray],
                           tile: tuple[int, int] | None = None) -> None:
    """Render the ``width × height`` image of camera ``cam`` (:func:`pack_camera`) into
    ``out = (rgb, depth, alpha)`` (``[H * W, 3]``/``[H * W]`` or ``[H, W, ...]`` float32
    contiguous): the rays are made per pixel inside the kernel, equal to those of
    ``generate_rays`` (+ ``to_ndc_rays``), so no ray arrays are allocated."""
    _launch(p, _NO_RAYS, _NO_RAYS, np.ascontiguousarray(cam, dtype=np.float64),
            int(width) * int(height), out, Launch(int(width), tile))


def _ray_arrays(origins: Any, dirs: Any) -> tuple[np.ndarray, np.ndarray]:
    return (np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3),
            np.ascontiguousarray(dirs, dtype=np.float32).reshape(-1, 3))


def render_rays_numba(p: TreeSpec, origins: np.ndarray, dirs: np.ndarray,
                      use_stack: bool = True, width: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render ``[N, 3]`` rays with the numba kernel and the values of ``p`` (:func:`prepare`:
    float32 values used in place, the tree's empty-space skip tables when it has them);
    returns float32 ``rgb [N,3], depth [N], alpha [N]`` (numpy). Geometry is float64 inside
    the kernel; ``use_stack``/``width``: see :class:`Launch`.
    """
    o, d = _ray_arrays(origins, dirs)
    out = empty_outputs(o.shape[0])
    render_prepared(p, o, d, out, use_stack, width)
    return out


def ray_stats_numba(tree: Any, origins: np.ndarray, dirs: np.ndarray, options: RenderOptions,
                    negligible: float = NEGLIGIBLE_WEIGHT, skip: SkipTables | None = None
                    ) -> np.ndarray:
    """Per-ray counters of the render march, int64 ``[N, 6]``, columns :data:`STAT_NAMES`:
    leaves visited (segments), leaves with σ > 0, σ > 0 segments of weight < ``negligible``,
    ``child`` reads of the descents, hit the box (0/1), stopped early at ``T < stop_thresh``
    (0/1). For benchmarks: where a real ray's time goes. ``tree``: an Octree (or anything with
    its arrays); ``skip``: count the march with these empty-space skip tables (as the renderer
    does with them; None: every leaf)."""
    p = tree_spec(tree, options, skip=skip, with_values=True)
    o, d = _ray_arrays(origins, dirs)
    out = np.zeros((o.shape[0], len(STAT_NAMES)), dtype=np.int64)
    if o.shape[0]:
        _stats_kernel(*p.tree_args(p.data), o, d, p.stop, p.eps, float(negligible), MAX_LEVEL,
                      MAX_STEPS, out)
    return out
