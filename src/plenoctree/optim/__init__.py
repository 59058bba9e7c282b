"""Fine-tuning the octree's leaf values on the training photos (paper §4.3, appendix B.3).

- :func:`render_rays_differentiable` / :class:`OctreeRenderFunction` (``autograd.py``):
  rendering differentiable w.r.t. the cell data; numba forward + analytic backward on CPU,
  the torch twin with autograd as the oracle and on CUDA.
- :class:`FinetuneConfig` / :func:`finetune` (``finetuning.py``): the optimisation loop.

Importing this package compiles nothing; the numba kernels (``_render_grad_numba.py``) compile on
first use and are cached on disk.
"""

from __future__ import annotations

from .._lazy import lazy_package

_LAZY = {
    'OctreeRenderFunction': '.autograd',
    'differentiable_backends': '.autograd',
    'render_rays_differentiable': '.autograd',
    'FinetuneConfig': '.finetuning',
    'FinetuneResult': '.finetuning',
    'finetune': '.finetuning',
}
lazy_package(__name__, _LAZY)

__all__ = ["OctreeRenderFunction", "render_rays_differentiable", "differentiable_backends",
           "FinetuneConfig", "FinetuneResult", "finetune"]
