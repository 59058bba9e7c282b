"""Torch twins of the device-resident fine-tuning step's kernels (``optim/_device_kernels.py``).

Each function here is the spec of one Triton kernel, with the same inputs and outputs, and the
path :class:`~plenoctree.optim._device_stepper.TorchStepper` runs (the renderer's torch twin
with autograd in the middle). None of them reads a value back to the host or has an output
whose shape depends on the data, so a step made of them issues a fixed sequence of ops.

- :func:`batch_pixels_torch`: ``k × k`` pixel tiles (or contiguous pixels) → image, column and
  row of each ray, and which rays fall past the image border (kept, with weight 0, so every
  batch of ``T`` tiles has ``T k²`` rays: a fixed shape);
- :func:`camera_rays_torch`: the rays of those pixels from the packed cameras
  (:func:`plenoctree.render._render_numba.pack_cameras`: pinhole or NDC, per-camera
  intrinsics), float32 ``[N, 3]`` as :func:`~plenoctree.optim._render_grad_numba.pixel_rays`
  makes them on the CPU, and :func:`pixel_targets_torch` their photo colours;
- :func:`loss_torch`: the step's squared error (into a figures row) and ``dL/dC``;
- :func:`update_torch`: the lazy optimiser step (SGD, Adam, RMSprop) as a dense masked update:
  rows whose gradient is all zero keep their values and moments (``torch.optim.SparseAdam``
  semantics, as the CPU kernel), without a data-dependent ``nonzero``.

Figures rows (float64 ``[4]`` per step, :data:`FIG_SSE` …): the squared error summed over the
batch, the rays inside the images, the non-finite values written, the rows updated.
"""

from __future__ import annotations

import torch

from ._rules import FIG_BAD, FIG_RAYS, FIG_ROWS, FIG_SSE, N_FIGS

__all__ = ["FIG_SSE", "FIG_RAYS", "FIG_BAD", "FIG_ROWS", "N_FIGS", "OPT_CODES",
           "batch_pixels_torch", "camera_rays_torch", "pixel_targets_torch", "loss_torch",
           "update_torch"]

#: Optimiser codes shared with the kernel.
OPT_CODES = {"sgd": 0, "adam": 1, "rmsprop": 2}

_CAM_NDC, _CAM_NDC_CLIP = 2, 3          # render._render_numba.CAM_NDC / CAM_NDC_CLIP
_MISS_Z = 1.0e4                          # datasets.ndc.MISS_ORIGIN's z'
_CLIP_EXTENT = 1.0e4
_MIN_DZ = 1.0e-12


def batch_pixels_torch(tiles: torch.Tensor, k: int, width: int, height: int,
                       base: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                torch.Tensor]:
    """Pixels of tiles: ``(img, u, v, outside)``, int64 ``[T k²]`` and bool ``[T k²]``.

    ``tiles`` int64 ``[T]`` numbers ``k × k`` tiles (``img · nty · ntx + ty · ntx + tx``,
    ``nty = ⌈H / k⌉``, ``ntx = ⌈W / k⌉``); ray ``j`` is pixel ``j mod k²`` of tile
    ``tiles[j // k²]`` in raster order, as :meth:`ViewSet.tile_pixels
    <plenoctree.optim._views.ViewSet.tile_pixels>` lists them. ``outside`` marks pixels past
    the image's right or bottom border (``u, v`` are clamped into the image for them).
    ``k = 1`` and ``tiles = base + arange(N)`` give the flat pixels ``base … base + N - 1``.
    """
    kk = k * k
    nty, ntx = -(-height // k), -(-width // k)
    j = torch.arange(tiles.shape[0] * kk, device=tiles.device)
    tile = tiles.repeat_interleave(kk, output_size=tiles.shape[0] * kk) + base
    within = j % kk
    img = torch.div(tile, nty * ntx, rounding_mode="floor")
    rem = tile - img * (nty * ntx)
    ty = torch.div(rem, ntx, rounding_mode="floor")
    v = ty * k + torch.div(within, k, rounding_mode="floor")
    u = (rem - ty * ntx) * k + within % k
    outside = (v >= height) | (u >= width)
    return img, u.clamp(max=width - 1), v.clamp(max=height - 1), outside


def camera_rays_torch(cams: torch.Tensor, img: torch.Tensor, u: torch.Tensor, v: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays ``origins, dirs`` float32 ``[N, 3]`` of pixels ``(u, v)`` of images ``img``
    seen by the packed cameras ``cams`` float64 ``[M, 20]`` (pinhole, or NDC rays of the NDC
    reference camera for ``cam[0]`` = 2, 3): the numba ``_camera_ray`` in torch ops."""
    c = cams[img]                                            # [N, 20]
    a = (u.to(torch.float64) + 0.5 - c[:, 3]) / c[:, 1]
    b = -(v.to(torch.float64) + 0.5 - c[:, 4]) / c[:, 2]
    x = a * c[:, 5] + b * c[:, 6] - c[:, 7]
    y = a * c[:, 8] + b * c[:, 9] - c[:, 10]
    z = a * c[:, 11] + b * c[:, 12] - c[:, 13]
    nrm = torch.sqrt(x * x + y * y + z * z)
    d = torch.stack([x / nrm, y / nrm, z / nrm], -1).to(torch.float32)
    o = c[:, 14:17].to(torch.float32)
    kind = c[:, 0]
    ndc = (kind == _CAM_NDC) | (kind == _CAM_NDC_CLIP)
    no, nd = _ndc_rays(c, o.to(torch.float64), d.to(torch.float64), kind == _CAM_NDC_CLIP)
    return torch.where(ndc[:, None], no, o), torch.where(ndc[:, None], nd, d)


def _ndc_rays(c: torch.Tensor, o: torch.Tensor, e: torch.Tensor, clip: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """NDC rays (float32) of world rays ``o + t e`` (float64 ``[N, 3]``); the numba
    ``_ndc_ray`` with its three cases selected per ray (``clip``: the "any camera" rule)."""
    near, fx, fy = c[:, 19], c[:, 17], c[:, 18]
    ox, oy, oz = o.unbind(-1)
    ex, ey, ez = e.unbind(-1)
    behind = clip & (oz <= -near)                       # past the near plane
    away = clip & ~behind & ~(ez < -_MIN_DZ)            # never reaches the NDC volume
    t = -(near + oz) / ez                               # NeRF's ray from the near plane
    qx, qy, qz = ox + t * ex, oy + t * ey, oz + t * ez
    rx, ry = qx / qz, qy / qz
    px = torch.where(behind, fx * ox / oz, fx * rx)
    py = torch.where(behind, fy * oy / oz, fy * ry)
    pz = torch.where(behind, 1.0 + 2.0 * near / oz, 1.0 + 2.0 * near / qz)
    nx = torch.where(behind, fx * (ex * oz - ox * ez), fx * (ex / ez - rx))
    ny = torch.where(behind, fy * (ey * oz - oy * ez), fy * (ey / ez - ry))
    nz = torch.where(behind, -2.0 * near * ez, -2.0 * near / qz)
    ok = ~away & (~behind | (nx != 0.0) | (ny != 0.0) | (nz != 0.0))
    miss = clip & ~(ok & (px.abs() <= _CLIP_EXTENT) & (py.abs() <= _CLIP_EXTENT))
    nrm = torch.sqrt(nx * nx + ny * ny + nz * nz)
    p = torch.stack([px, py, pz], -1).to(torch.float32)
    n = torch.stack([nx / nrm, ny / nrm, nz / nrm], -1).to(torch.float32)
    # a missing ray: origin (0, 0, MISS_Z), direction (0, 0, 1), made on the device
    axis_z = torch.arange(3, device=p.device) == 2
    return (torch.where(miss[:, None], axis_z * _MISS_Z, p),
            torch.where(miss[:, None], axis_z.to(torch.float32), n))


def pixel_targets_torch(images: torch.Tensor, unit: float, img: torch.Tensor, u: torch.Tensor,
                        v: torch.Tensor) -> torch.Tensor:
    """Photo colours float32 ``[N, 3]`` of pixels ``(u, v)`` of images ``img``: ``images``
    ``[M, H, W, 3]`` float32 (``unit`` 1) or int16 holding uint16 bits (``unit`` 1 / 65535)."""
    px = images[img, v, u]
    if px.dtype == torch.float32:
        return px
    return ((px.to(torch.int32) & 0xFFFF).to(torch.float64) * unit).to(torch.float32)


def loss_torch(rgb: torch.Tensor, targets: torch.Tensor, outside: torch.Tensor, scale: float,
               figs: torch.Tensor, slot: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sse, dL/dC)``: the squared error ``Σ (C - C*)²`` over the rays inside the images
    (``outside`` bool ``[N]`` marks the others; float32 squares summed in float64: a scalar
    tensor) and ``2 · scale · (C - C*)`` (0 outside) ``[N, 3]`` in ``rgb``'s dtype. Row
    ``slot`` of the figures ``figs`` (float64 ``[S, 4]``) gets ``sse`` and the rays inside."""
    err = torch.where(outside[:, None], torch.zeros_like(rgb), rgb - targets)
    sse = (err * err).to(torch.float64).sum()
    row = figs[slot]
    row[FIG_SSE] += sse.detach()
    row[FIG_RAYS] += (~outside).sum()
    return sse, err * (2.0 * scale)


def update_torch(p: torch.Tensor, g: torch.Tensor, m1: torch.Tensor | None,
                 m2: torch.Tensor | None, opt: int, lr: float, lr_sigma: float,
                 hyper: tuple[float, float, float, float, float], figs: torch.Tensor,
                 slot: int) -> None:
    """The lazy optimiser step on ``p`` float32 ``[n, D]`` (in place) with gradient ``g [n, D]``;
    rows with an all-zero gradient are left alone (values and moments).

    ``opt``: :data:`OPT_CODES`; ``lr`` for the colour columns, ``lr_sigma`` for σ (the last);
    ``hyper = (b1, b2, bc1, bc2, eps)``: Adam's ``β₁, β₂`` and bias corrections
    ``1 - β^t`` (RMSprop: ``b2`` its α; SGD: unused). σ of the updated rows is then clamped to
    ``≥ 0``.
    Adds the non-finite values written and the rows updated to row ``slot`` of ``figs``."""
    b1, b2, bc1, bc2, eps = hyper
    touched = (g != 0).any(dim=1, keepdim=True)                     # NaN counts as touched
    lrv = torch.full((p.shape[1],), lr, dtype=p.dtype, device=p.device)
    lrv[-1] = lr_sigma
    if opt == OPT_CODES["sgd"]:
        new = p - lrv * g
    elif opt == OPT_CODES["adam"]:
        n1 = torch.where(touched, m1 * b1 + (1 - b1) * g, m1)
        n2 = torch.where(touched, m2 * b2 + (1 - b2) * g * g, m2)
        new = torch.where(touched, p - lrv * (n1 / bc1) / ((n2 / bc2).sqrt() + eps), p)
        m1.copy_(n1)
        m2.copy_(n2)
    else:
        n2 = torch.where(touched, m2 * b2 + (1 - b2) * g * g, m2)
        new = torch.where(touched, p - lrv * g / (n2.sqrt() + eps), p)
        m2.copy_(n2)
    row = figs[slot]
    row[FIG_BAD] += (~torch.isfinite(new) & touched).sum()
    row[FIG_ROWS] += touched.sum()
    sig = new[:, -1]
    new[:, -1] = torch.where(touched[:, 0] & (sig < 0), torch.zeros_like(sig), sig)   # NaN stays
    p.copy_(new)
