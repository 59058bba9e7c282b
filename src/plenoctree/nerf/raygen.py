"""The rays of a training step of fixed shape in one launch (issue 47): op ``ray_batch``.

The step draws ``U``, float64 ``[R, 4]`` uniform in ``[0, 1)``, with its generator in one op
(:func:`draw_uniforms`); from ``U`` and the tables a :class:`~.training.RaySource` keeps on
the device (cameras, images, alphas, constants), ray ``r`` is

* pixel ``p = min(floor(U[r, 0] N H W), N H W - 1)`` of the flat index of ``N`` images of
  ``H x W`` (image ``p // (H W)``, row ``(p % H W) // W``, column ``p % W``; float64 resolves
  2^53 values, so every pixel stays reachable, where a float32 draw would skip most of lego's
  2^26);
* its origin and unit direction: the ray through the pixel centre of
  :meth:`~plenoctree.datasets.Cameras.pixel_rays` (pinhole, per-camera intrinsics, NeRF's NDC
  rays of forward-facing scenes), in float64, rounded to float32;
* its background ``[3]``: ``U[r, 1:4]`` rounded to float32 where the source trains over random
  colours (:attr:`~.training.RaySource.background_mode`), else the dataset's colour;
* its target: the pixel's colour, with alpha re-composited over the random colour
  (``rgb - (1 - a) bg_data + (1 - a) bg``, float32 in this order) where the images have alpha;
* ``t_min, t_max``: :func:`.renderer.ray_bounds` of the float32 ray against the model's box
  within the dataset's ``[near, far]``.

Backends: the numba kernel (:mod:`._raygen_numba`, CPU), the Triton kernel
(:mod:`._raygen_triton`, CUDA; one launch), and the twin :func:`_ray_batch_torch`, the torch
code of the waves' step (:meth:`~.training.RaySource.pixels` and :func:`.renderer.ray_bounds`,
about 50 ops). The kernels compute in the twin's order (no fused multiply-adds), so pixels,
targets and backgrounds are equal, the rays equal to rounding (the twin's matrix product and
norm may sum in another order) and the bounds those of the kernel's own rays.

>>> import numpy as np, torch
>>> from plenoctree.datasets import Cameras, Dataset
>>> cams = Cameras(np.eye(4)[None], 2.0, 2.0, 1.5, 1.5, 2, 2)
>>> data = Dataset(np.zeros((1, 2, 2, 3), np.float32), cams, 0.5, 4.0, [[-1] * 3, [1] * 3],
...                "train", ".", (1.0, 1.0, 1.0), ["a"])
>>> from plenoctree.nerf.training import RaySource
>>> src = RaySource(data, torch.device("cpu"), random_background=False)
>>> rays = ray_batch(src, torch.tensor([[0.75, 0.1, 0.2, 0.3]], dtype=torch.float64),
...                  torch.tensor([[-1.0] * 3, [1.0] * 3]), backend="torch")
>>> rays.dirs.tolist(), rays.t_min.tolist(), rays.t_max.tolist()     # pixel 3: row 1, col 1
([[0.0, 0.0, -1.0]], [0.5], [1.0])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["TrainRays", "ray_batch", "draw_uniforms", "pixel_index", "ray_constants",
           "UNIFORMS", "BG_DATA", "BG_ALPHA", "BG_OPAQUE"]

#: Uniform numbers a ray takes (pixel, three background channels).
UNIFORMS = 4
#: Background modes of a :class:`~.training.RaySource`: the dataset's colour; pixels with alpha
#: re-composited over a random colour; opaque photos predicted over a random colour.
BG_DATA, BG_ALPHA, BG_OPAQUE = 0, 1, 2


@dataclass
class TrainRays:
    """``R`` training rays and what the step compares them with.

    Attributes:
        origins, dirs: float32 ``[R, 3]`` (unit dirs; NDC space for forward-facing scenes).
        target: float32 ``[R, 3]`` the pixels' colours (over ``background``).
        background: float32 ``[R, 3]`` the colour behind the scene.
        t_min, t_max: float32 ``[R]`` the part of ``[near, far]`` inside the model's box
            (empty: ``t_max <= t_min``).
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    target: torch.Tensor
    background: torch.Tensor
    t_min: torch.Tensor
    t_max: torch.Tensor

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    @property
    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(t_min, t_max)``."""
        return self.t_min, self.t_max

    def batch(self, near: float, far: float):
        """The :class:`~.renderer.RayBatch` of these rays."""
        from .renderer import RayBatch

        return RayBatch(self.origins, self.dirs, near, far, self.background)


def draw_uniforms(n: int, generator: torch.Generator, device: Any) -> torch.Tensor:
    """float64 ``[n, UNIFORMS]`` uniform in ``[0, 1)``: the random numbers of ``n`` rays of
    :func:`ray_batch`, in one op."""
    return torch.rand((int(n), UNIFORMS), generator=generator, dtype=torch.float64,
                      device=device)


def pixel_index(u: torch.Tensor, n_pixels: int) -> torch.Tensor:
    """int64 ``[R]`` flat pixel ``min(floor(u[:, 0] n_pixels), n_pixels - 1)`` of the uniform
    numbers ``u [R, UNIFORMS]`` (float64) among ``n_pixels``."""
    return (u[:, 0] * float(n_pixels)).long().clamp_(max=int(n_pixels) - 1)


def ray_constants(cameras, near: float, far: float, device: Any) -> torch.Tensor:
    """float64 ``[5]`` on ``device``: ``(ax, ay, ndc_near, near, far)``, what the kernels read
    besides the tables (``ax = -2 fx / W``, ``ay = -2 fy / H`` of the NDC reference camera,
    as :func:`~plenoctree.datasets.ndc.to_ndc_rays`; 0 without NDC). A tensor, not scalar
    arguments: a Triton kernel takes a Python float as float32."""
    ax = ay = 0.0
    if cameras.ndc:
        nfx, nfy = cameras.ndc_focal
        ax, ay = -2.0 * nfx / cameras.width, -2.0 * nfy / cameras.height
    return torch.tensor([ax, ay, cameras.ndc_near, float(near), float(far)],
                        dtype=torch.float64, device=device)


def _check(source, u: torch.Tensor, bbox: torch.Tensor) -> None:
    if u.dim() != 2 or u.shape[1] != UNIFORMS or u.dtype != torch.float64:
        raise ValueError(f"ray_batch: u must be float64 [R, {UNIFORMS}], got {u.dtype} "
                         f"{list(u.shape)}")
    if bbox.shape != (2, 3) or bbox.dtype != torch.float32:
        raise ValueError(f"ray_batch: bbox must be float32 [2, 3], got {bbox.dtype} "
                         f"{list(bbox.shape)}")
    dev = source.images.device
    if u.device != dev or bbox.device != dev:
        raise ValueError(f"ray_batch: u on {u.device} and bbox on {bbox.device}, the source's "
                         f"tables on {dev}")


def empty_rays(n: int, device: Any) -> TrainRays:
    """Uninitialised outputs of ``n`` rays for a kernel to fill."""
    def e(*shape: int) -> torch.Tensor:
        return torch.empty(shape, dtype=torch.float32, device=device)
    return TrainRays(e(n, 3), e(n, 3), e(n, 3), e(n, 3), e(n), e(n))


def _check_kernel(source, what: str) -> None:
    from ..errors import BackendError

    if source.cameras.ndc and source.cameras.ndc_clip:
        raise BackendError(f"ray_batch: backend {what!r} makes NeRF's NDC rays only (cameras "
                           "without ndc_clip, as datasets load them); use backend 'torch'")


def _ray_batch_torch(source, u: torch.Tensor, bbox: torch.Tensor) -> TrainRays:
    """The twin: the waves' step's torch code on the pixels :func:`pixel_index` picks."""
    from .renderer import ray_bounds

    bg = u[:, 1:].float() if source.background_mode != BG_DATA else None
    o, d, target, bg = source.pixels(pixel_index(u, source.n * source.h * source.w), bg)
    t_min, t_max = ray_bounds(o, d, bbox, source.near, source.far)
    return TrainRays(o, d, target, bg, t_min, t_max)


def _ray_batch_numba(source, u: torch.Tensor, bbox: torch.Tensor) -> TrainRays:
    """The numba kernel (CPU tensors)."""
    from . import _raygen_numba as K

    _check_kernel(source, "numba")
    out = empty_rays(u.shape[0], u.device)
    c2w, intr = source.tables
    alphas = source.alphas if source.alphas is not None else source.images[:1, 0]
    K.ray_batch(u.numpy(), c2w.numpy(), intr.numpy(), source.images.numpy(), alphas.numpy(),
                source.bg.numpy(), source.constants.numpy(), bbox.numpy(), source.h, source.w,
                source.background_mode, bool(source.cameras.ndc), out.origins.numpy(),
                out.dirs.numpy(), out.target.numpy(), out.background.numpy(),
                out.t_min.numpy(), out.t_max.numpy())
    return out


def ray_batch(source, u: torch.Tensor, bbox: torch.Tensor, backend: str = "auto") -> TrainRays:
    """The rays of a training step from its uniform numbers (see the module doc).

    Args:
        source: a :class:`~.training.RaySource` (its tables on the device of ``u``).
        u: float64 ``[R, UNIFORMS]`` in ``[0, 1)`` (:func:`draw_uniforms`).
        bbox: float32 ``[2, 3]`` the model's box (``model.scene_bbox``), world units.
        backend: "auto" (numba on CPU, Triton on CUDA), "numba", "triton" or "torch".

    Returns:
        :class:`TrainRays` of ``R`` rays; nothing is read back to the host.
    """
    from .. import backend as _backend

    _check(source, u, bbox)
    name = _backend.resolve("ray_batch", backend, u.device)
    return _backend.implementation("ray_batch", name)(source, u.contiguous(),
                                                       bbox.contiguous())
