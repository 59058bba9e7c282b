"""Which grid cells matter: the visibility (max ray weight) filter and plain σ thresholding.

Paper §4.2, *Filtering*: render every training view through the dense σ grid and keep, for
each cell, the maximum ray weight ``T_i (1 - exp(-σ_i δ_i))`` it ever received; cells below
``τ_w`` are dropped. Unlike thresholding σ, this removes matter no training view sees (the
inside of solid objects, floaters behind walls), which would otherwise cost leaves.

Rays march the grid exactly from cell boundary to cell boundary (the renderer's model, with
piecewise-constant cells) and stop once ``T < τ_w``. Only *candidate* cells are tracked: a cell
can reach weight ``τ_w`` only if ``1 - exp(-σ δ_max) ≥ τ_w`` (``δ_max``: the cell diagonal),
so the running maxima need ``M`` (candidates) floats per thread instead of ``R³``.

Backends: ``"numba"`` (:mod:`._visibility_numba`, imported on first use, parallel over rays),
``"triton"`` (:mod:`._visibility_triton`: the same kernel on the GPU, one ray per lane, maxima
by atomics; :func:`visibility_weights` keeps σ, the candidates, the rays and the maxima on the
device and reads back once) and ``"torch"`` (:func:`_max_weights_torch`, vectorised, the spec
the kernels are tested against).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._util import progress
from ..errors import ConfigError
from .grid import GridSpec

__all__ = ["Candidates", "candidates", "max_ray_weights", "visibility_weights", "weight_mask",
           "sigma_mask", "unseen_cells", "auto_ray_scale", "rescale_cameras"]


@dataclass
class Candidates:
    """Cells that may reach a weight of ``min_weight``.

    Attributes:
        flat: int64 ``[M]`` C-order flat indices of the candidate cells (sorted).
        index: int32 ``[R, R, R]``: position of each cell in ``flat``, -1 elsewhere.
        min_weight: the weight threshold they were selected for.
    """

    flat: np.ndarray
    index: np.ndarray
    min_weight: float


def candidates(sigma: np.ndarray, spec: GridSpec, min_weight: float) -> Candidates:
    """Cells where one segment can reach weight τ: σ ≥ -log(1 - τ) / |cell diagonal|."""
    if not 0.0 < min_weight < 1.0:
        raise ConfigError(f"weight threshold must be in (0, 1), got {min_weight}")
    diag = float(np.linalg.norm(spec.cell))
    flat = np.flatnonzero(sigma.reshape(-1) >= -np.log1p(-min_weight) / diag)
    if flat.size >= 2 ** 31 - 1:
        raise ConfigError(f"{flat.size} candidate cells exceed the int32 index; use a smaller grid")
    index = np.full(sigma.shape, -1, dtype=np.int32)
    index.reshape(-1)[flat] = np.arange(flat.size, dtype=np.int32)
    return Candidates(flat, index, float(min_weight))


# ------------------------------------------------------------------------------ torch twin
def _max_weights_torch(sigma: Any, index: Any, lo: Any, cell: Any, origins: Any, dirs: Any,
                       min_weight: float, n_cand: int) -> Any:
    """The spec: max ray weight per candidate cell, ``[n_cand]`` float64 (torch).

    Every crossing of the ``R + 1`` planes per axis inside the ray's box interval
    ``[max(t_box_in, 0), t_box_out]`` splits the ray into segments; a segment's cell is the one
    holding its midpoint, its length δ; ``T`` before a segment is ``exp(-Σ σ δ)`` of the
    earlier ones. Segments with ``T < min_weight`` do not count (the kernel stops there).

    Args:
        sigma: ``[R, R, R]`` σ. index: int ``[R, R, R]`` candidate column or -1.
        lo, cell: ``[3]`` grid corner and cell sides (world). origins, dirs: ``[N, 3]`` rays.
    """
    import torch

    f64 = torch.float64
    sig = torch.as_tensor(sigma).to(f64)
    idx = torch.as_tensor(index).long()
    lo_t = torch.as_tensor(np.asarray(lo), dtype=f64)
    cell_t = torch.as_tensor(np.asarray(cell), dtype=f64)
    o = torch.as_tensor(np.asarray(origins)).to(f64)
    d = torch.as_tensor(np.asarray(dirs)).to(f64)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    res = sig.shape[0]
    hi_t = lo_t + cell_t * res
    inv = 1.0 / d                                                       # ±inf where d == 0
    ta = (lo_t - o) * inv
    tb = (hi_t - o) * inv
    tmin = torch.minimum(ta, tb).nan_to_num(nan=-torch.inf)
    tmax = torch.maximum(ta, tb).nan_to_num(nan=torch.inf)
    t0 = tmin.max(-1).values.clamp(min=0.0)
    t1 = tmax.min(-1).values
    planes = lo_t[None, :] + torch.arange(res + 1, dtype=f64)[:, None] * cell_t[None, :]  # [R+1, 3]
    tp = (planes[None] - o[:, None, :]) * inv[:, None, :]               # [N, R+1, 3]
    tp = tp.reshape(len(o), -1)
    tp = torch.where(torch.isfinite(tp), tp, t1[:, None])
    tp = torch.minimum(torch.maximum(tp, t0[:, None]), t1[:, None])    # out of range -> δ = 0
    ts = torch.sort(torch.cat([t0[:, None], tp, t1[:, None]], -1), -1).values
    delta = (ts[:, 1:] - ts[:, :-1]).clamp(min=0.0)                     # [N, S]
    mid = 0.5 * (ts[:, 1:] + ts[:, :-1])
    p = o[:, None, :] + mid[..., None] * d[:, None, :]
    c = ((p - lo_t) / cell_t).floor().long().clamp(0, res - 1)
    s = sig[c[..., 0], c[..., 1], c[..., 2]]
    tau = s * delta
    trans_before = torch.exp(-(torch.cumsum(tau, -1) - tau))
    w = trans_before * (1.0 - torch.exp(-tau))
    col = idx[c[..., 0], c[..., 1], c[..., 2]]
    ok = (delta > 0) & (t1 > t0)[:, None] & (col >= 0) & (trans_before >= min_weight)
    out = torch.zeros(n_cand, dtype=f64)
    if bool(ok.any()):
        out = out.scatter_reduce(0, col[ok], w[ok], reduce="amax", include_self=True)
    return out


# ------------------------------------------------------------------------------ front end
def auto_ray_scale(cameras: Any, spec: GridSpec) -> float:
    """Image scale at which the training views' pixels are no wider than a voxel.

    A voxel no ray passes through gets weight 0 and is dropped, so the rays must be at least
    as dense as the voxels where the content is: the pixel footprint at the box centre,
    ``distance / focal``, is compared with the smallest cell side. Returns ``>= 1``.
    NDC cameras (forward-facing scenes, the grid lives in NDC space): a pixel spans
    ``2 / W`` by ``2 / H`` NDC units.
    """
    if getattr(cameras, "ndc", False):
        foot = 2.0 / float(min(cameras.width, cameras.height))
        return max(1.0, foot / float(spec.cell.min()))
    dist = float(np.median(np.linalg.norm(cameras.centers - spec.center, axis=1)))
    focal = float(min(np.min(np.atleast_1d(cameras.fx)), np.min(np.atleast_1d(cameras.fy))))
    return max(1.0, dist / focal / float(spec.cell.min()))


def rescale_cameras(cameras: Any, scale: float) -> Any:
    """The same cameras with images ``scale`` times as wide and high (more, finer rays)."""
    if scale == 1.0:
        return cameras
    return cameras.resized(max(1, int(round(cameras.width * scale))),
                           max(1, int(round(cameras.height * scale))))


def _backend(name: str) -> str:
    from ..backend import resolve

    return resolve("visibility", name, "cpu")       # numpy grids and rays


def max_ray_weights(sigma: np.ndarray, spec: GridSpec, cand: Candidates, origins: np.ndarray,
                    dirs: np.ndarray, backend: str = "auto", out: np.ndarray | None = None,
                    ray_chunk: int = 1 << 15) -> np.ndarray:
    """Maximum ray weight of each candidate cell over the rays ``origins, dirs [..., 3]``.

    Args:
        sigma: float32 ``[R, R, R]``. spec: its grid. cand: from :func:`candidates`.
        backend: "auto" | "numba" | "torch" | "triton" (the torch twin needs ``O(rays · R)``
            memory; it is processed in ``ray_chunk`` / R rays at a time; triton: the CPU
            arrays are uploaded at each call, see :func:`_max_weights_triton_run`).
        out: running maxima to update in place (numba: float32 ``[n_threads, M]``; torch and
            triton: float32 ``[1, M]``), to accumulate over many views; allocated when ``None``.

    Returns:
        ``out`` (reduce with ``out.max(0)`` for the per-cell maxima ``[M]``).
    """
    name = _backend(backend)
    o = np.ascontiguousarray(np.asarray(origins, dtype=np.float32).reshape(-1, 3))
    d = np.ascontiguousarray(np.asarray(dirs, dtype=np.float32).reshape(-1, 3))
    from ..backend import implementation

    return implementation("visibility", name)(sigma, spec, cand, o, d, out, ray_chunk)


def _max_weights_numba_run(sigma: np.ndarray, spec: GridSpec, cand: Candidates, o: np.ndarray,
                           d: np.ndarray, out: np.ndarray | None, ray_chunk: int) -> np.ndarray:
    """numba kernel: running maxima per thread, ``out`` float32 ``[n_threads, M]``."""
    import numba

    from ._visibility_numba import max_weights_numba

    if out is None:
        out = np.zeros((numba.get_num_threads(), cand.flat.size), dtype=np.float32)
    max_weights_numba(sigma, cand.index, spec.lo, spec.cell, o, d, cand.min_weight, out)
    return out


def _max_weights_torch_run(sigma: np.ndarray, spec: GridSpec, cand: Candidates, o: np.ndarray,
                           d: np.ndarray, out: np.ndarray | None, ray_chunk: int) -> np.ndarray:
    """torch twin in chunks of ``ray_chunk / R`` rays, ``out`` float32 ``[1, M]``."""
    m = cand.flat.size
    if out is None:
        out = np.zeros((1, m), dtype=np.float32)
    step = max(1, ray_chunk // max(1, spec.res))
    for s in range(0, len(o), step):
        w = _max_weights_torch(sigma, cand.index, spec.lo, spec.cell, o[s:s + step],
                               d[s:s + step], cand.min_weight, m).numpy()
        np.maximum(out[0], w.astype(np.float32), out=out[0])
    return out


def _triton_device(*tensors: Any) -> Any:
    """Where the Triton backend runs: the device of the first torch tensor given, else CUDA
    (the CPU in Triton's interpreter, for tests)."""
    import torch

    from .._triton import interpret_mode

    for t in tensors:
        if isinstance(t, torch.Tensor):
            return t.device
    return torch.device("cpu" if interpret_mode() or not torch.cuda.is_available() else "cuda")


def _max_weights_triton_run(sigma: Any, spec: GridSpec, cand: Candidates, o: Any, d: Any,
                            out: Any, ray_chunk: int) -> Any:
    """Triton kernel on the device (:mod:`._visibility_triton`), ``out`` float32 ``[1, M]``.

    ``sigma``, ``o``, ``d`` numpy arrays or torch tensors; ``out`` ``None`` (a torch tensor is
    made on the device), a torch tensor on the device (raised in place, no read-back) or a
    numpy array (raised in place: one upload, one read-back). Runs on ``out``'s (else
    ``sigma``'s) device, CUDA for numpy inputs. ``ray_chunk`` is not used (one launch).
    """
    import torch

    from ._visibility_triton import geometry, max_weights_triton

    dev = _triton_device(out, sigma, o)
    host_out = out if isinstance(out, np.ndarray) else None
    if out is None or host_out is not None:
        out_t = (torch.zeros((1, cand.flat.size), dtype=torch.float32, device=dev)
                 if host_out is None else torch.as_tensor(host_out).to(dev).contiguous())
    else:
        out_t = out
    sig = torch.as_tensor(sigma).to(dev, torch.float32).contiguous()
    idx = torch.as_tensor(cand.index).to(dev, torch.int32).contiguous()
    geom = geometry(spec.lo, spec.cell, spec.res, cand.min_weight, dev)
    o_t = torch.as_tensor(o).to(dev, torch.float32).reshape(-1, 3)
    d_t = torch.as_tensor(d).to(dev, torch.float32).reshape(-1, 3)
    max_weights_triton(sig, idx, geom, o_t, d_t, out_t)
    if host_out is not None:
        host_out[...] = out_t.cpu().numpy()
        return host_out
    return out_t


def _visibility_triton(sigma: np.ndarray, spec: GridSpec, cand: Candidates, cameras: Any,
                       device: Any, show_progress: bool | None,
                       pixels: int = 1 << 20) -> np.ndarray:
    """:func:`visibility_weights`' loop on the device: σ (float32), the candidate index
    (int32) and the cameras uploaded once, the maxima ``[M]`` kept there, every view's rays
    made there by :meth:`~plenoctree.datasets.Cameras.pixel_rays` (pinhole; NDC views: made on
    the host and uploaded, ``to_ndc_rays`` checks its rays on the host) ``pixels`` at a time and marched by one launch each; one read-back at
    the end. Returns float32 ``[M]``."""
    import torch

    from ._visibility_triton import geometry, max_weights_triton

    dev = torch.device(device)
    sig = torch.as_tensor(sigma).to(dev, torch.float32).contiguous()
    idx = torch.as_tensor(cand.index).to(dev, torch.int32).contiguous()
    geom = geometry(spec.lo, spec.cell, spec.res, cand.min_weight, dev)
    out = torch.zeros(cand.flat.size, dtype=torch.float32, device=dev)
    ndc = bool(getattr(cameras, "ndc", False))
    tables = None if ndc else cameras.device_tables(dev)
    w = cameras.width
    step = max(1, pixels // max(1, w)) * w
    for i in progress(range(len(cameras)), desc="visibility", unit="view",
                      disable=None if show_progress is None else not show_progress):
        if ndc:
            o, d = cameras.rays(i)
            max_weights_triton(sig, idx, geom, torch.as_tensor(o.reshape(-1, 3)).to(dev),
                               torch.as_tensor(d.reshape(-1, 3)).to(dev), out)
            continue
        for p0 in range(0, w * cameras.height, step):     # whole pixel rows at a time
            pix = torch.arange(p0, min(w * cameras.height, p0 + step), device=dev)
            o, d = cameras.pixel_rays(torch.full_like(pix, i), pix % w, pix // w, tables)
            max_weights_triton(sig, idx, geom, o, d, out)
    return out.cpu().numpy()


def visibility_weights(sigma: np.ndarray, spec: GridSpec, cameras: Any, min_weight: float,
                       backend: str = "auto", show_progress: bool | None = None,
                       memory_limit: int | None = None, device: Any = None
                       ) -> tuple[Candidates, np.ndarray]:
    """Render every camera through the grid; max ray weight of each candidate cell.

    Args:
        sigma: float32 ``[R, R, R]`` σ grid. spec: its grid.
        cameras: a :class:`~plenoctree.datasets.Cameras` (the training views).
        min_weight: τ_w; only cells that could reach it are tracked (use the smallest τ_w you
            will threshold with).
        backend: "auto" | "numba" | "torch" | "triton" (see the module docstring).
        memory_limit: bytes allowed for the per-thread maxima (``n_threads · M · 4``).
        device: where the filter runs. ``None``: the CPU (``"auto"`` is numba), except that
            ``"triton"`` runs on CUDA (the CPU in Triton's interpreter). A CUDA device: ``"auto"``
            is ``"triton"`` where Triton is usable (:mod:`plenoctree.backend`'s rule), and the
            grid, the candidates and the rays live there (one read-back at the end);
            ``"numba"`` there raises :class:`~plenoctree.errors.BackendError`, ``"torch"``
            runs on the host arrays.

    Returns:
        ``(cand, weights [M] float32)``: candidates and their max weights (0: never reached).
    """
    cand = candidates(sigma, spec, min_weight)
    if cand.flat.size == 0:
        raise ConfigError(
            f"every voxel was removed: no cell of the {spec.res}^3 grid is dense enough to "
            f"reach the weight threshold {min_weight:g} (largest σ {float(sigma.max()):.4g}, "
            f"needs {-np.log1p(-min_weight) / float(np.linalg.norm(spec.cell)):.4g}); lower "
            f"--weight-thresh, or check the box (--bbox, --center/--radius) holds the content")
    if device is not None or str(backend).lower() == "triton":
        from ..backend import resolve

        dev = _triton_device() if device is None else device
        name = resolve("visibility", backend, dev)
    else:
        name = _backend(backend)
    if name == "numba":
        import numba

        rows = numba.get_num_threads()
    else:
        rows = 1
    need = rows * cand.flat.size * 4
    if memory_limit is not None and need > memory_limit:
        raise ConfigError(f"visibility filter: {cand.flat.size} candidate cells x {rows} threads "
                          f"need {need / 2**30:.2f} GiB (budget {memory_limit / 2**30:.2f} GiB); "
                          f"use fewer threads (--threads), a smaller --grid or a higher "
                          f"--weight-thresh")
    if name == "triton":
        return cand, _visibility_triton(sigma, spec, cand, cameras, dev, show_progress)
    out = np.zeros((rows, cand.flat.size), dtype=np.float32)
    for i in progress(range(len(cameras)), desc="visibility", unit="view",
                      disable=None if show_progress is None else not show_progress):
        o, d = cameras.rays(i)
        max_ray_weights(sigma, spec, cand, o, d, name, out)
    return cand, out.max(axis=0)


def weight_mask(spec: GridSpec, cand: Candidates, weights: np.ndarray, weight_thresh: float
                ) -> np.ndarray:
    """Bool ``[R, R, R]``: cells whose max ray weight is ``≥ weight_thresh``.

    ``weight_thresh`` must be ``≥ cand.min_weight`` (cells below that were not tracked).
    """
    if weight_thresh < cand.min_weight:
        raise ConfigError(f"weight threshold {weight_thresh:g} is below the {cand.min_weight:g} "
                          "the weights were computed for")
    mask = np.zeros((spec.res,) * 3, dtype=bool)
    mask.reshape(-1)[cand.flat[weights >= weight_thresh]] = True
    return mask


def unseen_cells(spec: GridSpec, flat: np.ndarray, cameras: Any) -> np.ndarray:
    """Bool ``[M]``: the cells ``flat`` (int ``[M]``, C-order flat indices of ``spec``'s grid)
    whose centre lies in no camera's image: behind every camera or outside every image's
    rectangle (occlusion plays no part: a cell in view behind a wall is *seen*).

    ``cameras``: a :class:`~plenoctree.datasets.Cameras`. NDC cameras (the grid in the NDC
    space of :attr:`~plenoctree.datasets.Cameras.ndc_focal`): centres are mapped back to the
    world first; those outside NDC's depth range ``(-1, 1)`` (before the near plane or at
    infinite depth) count as seen, so they are never added.
    """
    flat = np.asarray(flat, dtype=np.int64).reshape(-1)
    idx = np.stack(np.unravel_index(flat, (spec.res,) * 3), -1)
    pts = spec.lo + (idx + 0.5) * spec.cell
    todo = np.ones(len(flat), dtype=bool)
    if getattr(cameras, "ndc", False):
        from ..octree.ndc import NDCSpace

        todo = np.abs(pts[:, 2]) < 1.0
        pts = np.where(todo[:, None], pts, 0.0)
        pts = NDCSpace.from_cameras(cameras).ndc_to_world(pts)
    left = np.flatnonzero(todo)        # not yet seen: most cells leave after a few cameras
    for i in range(len(cameras)):
        if left.size == 0:
            break
        fx, fy, cx, cy = cameras.intrinsics(i)
        m = np.asarray(cameras.c2w[i], dtype=np.float64)
        pc = (pts[left] - m[:3, 3]) @ m[:3, :3]          # camera space: looks down -z
        depth = -pc[:, 2]
        front = depth > 0.0
        s = np.where(front, depth, 1.0)
        u = cx + fx * pc[:, 0] / s
        v = cy - fy * pc[:, 1] / s
        seen = front & (u >= 0.0) & (u <= cameras.width) & (v >= 0.0) & (v <= cameras.height)
        left = left[~seen]
    out = np.zeros(len(flat), dtype=bool)
    out[left] = True
    return out


def sigma_mask(sigma: np.ndarray, spec: GridSpec, alpha_thresh: float) -> np.ndarray:
    """Bool ``[R, R, R]``: cells with alpha ``1 - exp(-σ δ) ≥ alpha_thresh`` (δ: largest side).

    The original code's ``--masking_mode sigma``: keeps hidden matter too.
    """
    if not 0.0 <= alpha_thresh < 1.0:
        raise ConfigError(f"alpha threshold must be in [0, 1), got {alpha_thresh}")
    if alpha_thresh == 0.0:
        return sigma > 0
    return sigma >= -np.log1p(-alpha_thresh) / float(spec.cell.max())
