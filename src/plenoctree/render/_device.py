"""One camera's image rendered on a device without the host in the loop (issue 47, item 3).

:func:`plenoctree.render.render_image` with ``device="cuda"`` used to make the image's rays
with numpy on the host (``Cameras.rays``: ~15 MB for 800², then uploaded), check every ray
for NaN and every origin's reach (device reductions read back), upload the tree's box and
evaluate the SH basis in ~50 torch ops; then (2026-12-06) the rays were made on the device in
torch ops (105 a frame). Here, for a tree prepared once
(:func:`~plenoctree.render.tree_to_device`: a :class:`~plenoctree.render.DeviceTree`):

* the camera is packed on the host (``pack_cameras``, the numba renderer's per-pixel camera:
  pinhole, NDC, NDC with the "any camera" rule) and uploaded (20 numbers, the one upload of a
  frame); the tree's box, ``step_eps`` and SG lobes once per tree;
* they are checked as the numba path checks them: the four corner rays, made on the host,
  bound every other one;
* one launch makes every pixel's ray, the march kernel's per-ray geometry and the basis
  values (the rays kernel the fine-tuning loop uses too, ``render._rays_triton.camera_rays``);
* then the march kernel. 11 ops a frame, nothing read back (``benchmarks/render_ops.py``);
  the caller waits for the GPU at the end.

The image is the twin's (the same rays as ``cameras.rays``; max |Δ| within the kernels'
1e-4 spec, tested).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .options import KIND_RGBA, RenderOptions

__all__ = ["render_camera_device"]


def _image_rays(cameras: Any, index: int, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(origins, dirs)`` float32 ``[H*W, 3]`` of camera ``index`` on ``dev``, row-major."""
    w, h = cameras.width, cameras.height
    one = cameras.select([index])
    pix = torch.arange(w * h, device=dev)
    img = torch.zeros_like(pix)
    return one.pixel_rays(img, pix % w, pix // w, one.device_tables(dev))


def _tree_constants(tree: Any, step_eps: float, dev: torch.device
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The tree's float64 box and ``step_eps`` (``geometry_tensor``) and its SG lobes on
    ``dev``, uploaded once per tree and ``step_eps`` (kept on the tree object)."""
    from ._rays_triton import geometry_tensor

    cache = tree.__dict__.setdefault("_device_constants", {})
    key = (float(step_eps), str(dev))
    if key not in cache:
        extra = getattr(tree, "extra_data", None)
        cache[key] = (geometry_tensor(tree.offset, tree.invradius, step_eps, dev),
                      None if extra is None else torch.from_numpy(
                          np.ascontiguousarray(extra, np.float32)).to(dev))
    return cache[key]


def _camera_geometry(tree: Any, info: Any, cameras: Any, index: int, opts: RenderOptions,
                     dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(geo [H W, 14] float64, basis [H W, B])`` of camera ``index``'s pixels in one launch
    (the rays kernel the fine-tuning loop uses too, ``render._rays_triton.camera_rays``): the camera
    packed on the host and uploaded (20 numbers), the tree's constants once per tree."""
    from ._rays_triton import camera_rays
    from ._render_numba import pack_cameras

    cams = torch.from_numpy(pack_cameras(cameras, [index])).to(dev)
    geom, extra = _tree_constants(tree, opts.step_eps, dev)
    n = cameras.width * cameras.height
    geo = torch.empty((n, 14), dtype=torch.float64, device=dev)
    basis = torch.empty((n, info.basis_dim), dtype=tree.data.dtype, device=dev)
    camera_rays(cams, cameras.width, cameras.height, geom, info, extra,
                opts.basis_range(info.basis_dim), (geo, basis))
    return geo, basis


def render_camera_device(tree: Any, info: Any, cameras: Any, index: int, opts: RenderOptions,
                         dev: torch.device, backend: str) -> Any:
    """The :class:`~plenoctree.render.RenderOutput` (``[H, W, ...]`` on ``dev``) of camera
    ``index`` of ``cameras`` through ``tree`` (a ``DeviceTree`` on ``dev``; ``info``: its
    format), with ``backend`` "triton" or "torch" (the twin)."""
    from . import RenderOutput, _check_origins, _check_rays
    from ._torch_impl import render_rays_torch

    w, h = cameras.width, cameras.height
    cols, rows = np.array([0, w - 1, 0, w - 1]), np.array([0, 0, h - 1, h - 1])
    o4, d4 = cameras.pixel_rays(np.full(4, index), cols, rows)     # bound every other ray
    _check_rays(o4, d4)
    _check_origins(o4, tree.offset, tree.invradius)
    if backend == "torch":
        o, d = _image_rays(cameras, index, dev)
        out = render_rays_torch(tree, o, d, opts)
    else:
        from ._triton_impl import march_kernel_call

        geo, basis = _camera_geometry(tree, info, cameras, index, opts, dev)
        n_b = 1 if info.kind == KIND_RGBA else info.basis_dim
        rgb, depth, alpha = march_kernel_call(tree.child.reshape(-1),
                                              tree.data.reshape(tree.child.numel(), -1),
                                              basis.contiguous(), geo, opts, n_b)
        out = RenderOutput(rgb, depth, alpha)
    return RenderOutput(out.rgb.reshape(h, w, 3), out.depth.reshape(h, w),
                        out.alpha.reshape(h, w))
