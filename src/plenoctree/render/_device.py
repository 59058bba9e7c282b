"""One camera's image rendered on a device without the host in the loop (issue 47, item 3).

:func:`plenoctree.render.render_image` with ``device="cuda"`` used to make the image's rays
with numpy on the host (``Cameras.rays``: ~15 MB for 800², then uploaded), check every ray
for NaN and every origin's reach (device reductions read back), upload the tree's box and
evaluate the SH basis in ~50 torch ops. Here, for a tree prepared once
(:func:`~plenoctree.render.tree_to_device`: a :class:`~plenoctree.render.DeviceTree`, which
keeps its box on the device too):

* the rays are made on the device (``Cameras.pixel_rays`` over the image's pixel indices,
  the camera's pose and intrinsics uploaded: two uploads of 16 and 4 numbers);
* they are checked as the numba path checks them: the four corner rays, made on the host,
  bound every other one;
* the SH basis is one Triton launch (:func:`plenoctree._sh_triton.sh_basis`) where
  Triton runs (SG and RGBA trees: the twin's ops);
* then the march kernel. Nothing is read back; the caller waits for the GPU at the end.

The image is the twin's (the same rays as ``cameras.rays``; max |Δ| within the kernels'
1e-4 spec, tested).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .options import KIND_RGBA, KIND_SH, RenderOptions

__all__ = ["render_camera_device"]


def _image_rays(cameras: Any, index: int, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(origins, dirs)`` float32 ``[H*W, 3]`` of camera ``index`` on ``dev``, row-major."""
    w, h = cameras.width, cameras.height
    one = cameras.select([index])
    pix = torch.arange(w * h, device=dev)
    img = torch.zeros_like(pix)
    return one.pixel_rays(img, pix % w, pix // w, one.device_tables(dev))


def render_camera_device(tree: Any, info: Any, cameras: Any, index: int, opts: RenderOptions,
                         dev: torch.device, backend: str) -> Any:
    """The :class:`~plenoctree.render.RenderOutput` (``[H, W, ...]`` on ``dev``) of camera
    ``index`` of ``cameras`` through ``tree`` (a ``DeviceTree`` on ``dev``; ``info``: its
    format), with ``backend`` "triton" or "torch" (the twin)."""
    from . import RenderOutput, _check_origins, _check_rays
    from ._torch_impl import ray_basis_torch, render_rays_torch

    w, h = cameras.width, cameras.height
    cols, rows = np.array([0, w - 1, 0, w - 1]), np.array([0, 0, h - 1, h - 1])
    o4, d4 = cameras.pixel_rays(np.full(4, index), cols, rows)     # bound every other ray
    _check_rays(o4, d4)
    _check_origins(o4, tree.offset, tree.invradius)
    o, d = _image_rays(cameras, index, dev)
    if backend == "torch":
        out = render_rays_torch(tree, o, d, opts)
    else:
        from ._triton_impl import march_kernel_call, prepare_rays

        geo, unit = prepare_rays(tree.offset, tree.invradius, o, d, opts.step_eps,
                                 getattr(tree, "box", None))
        if info.kind == KIND_SH and tree.data.dtype == torch.float32:
            from .._sh_triton import sh_basis

            basis = sh_basis(unit, info.sh_degree, opts.basis_range(info.basis_dim))
        else:
            basis = ray_basis_torch(info, unit, tree.extra_data, opts).to(tree.data.dtype)
        n_b = 1 if info.kind == KIND_RGBA else info.basis_dim
        rgb, depth, alpha = march_kernel_call(tree.child.reshape(-1),
                                              tree.data.reshape(tree.child.numel(), -1),
                                              basis.contiguous(), geo, opts, n_b)
        out = RenderOutput(rgb, depth, alpha)
    return RenderOutput(out.rgb.reshape(h, w, 3), out.depth.reshape(h, w),
                        out.alpha.reshape(h, w))
