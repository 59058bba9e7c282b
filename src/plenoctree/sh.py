"""Real spherical harmonics (degree 0-4) and spherical Gaussians, numpy and torch.

Conventions are those of svox / PlenOctree / 3D Gaussian Splatting: real, orthonormal SH with
the signs

    Y_0 = C0
    Y_1, Y_2, Y_3 = -C1*y, C1*z, -C1*x
    Y_4..Y_8 = C2[0]*xy, C2[1]*yz, C2[2]*(2zz-xx-yy), C2[3]*xz, C2[4]*(xx-yy)
    ... (degree 3 and 4 below)

for a unit direction ``d = (x, y, z)``. Each ``Y_b`` integrates to ``δ_ab`` against ``Y_a`` over the
unit sphere. A colour channel is ``sigmoid(Σ_b k_b Y_b(d))``.

Both functions accept either a ``numpy.ndarray`` or a ``torch.Tensor`` and return the same
library, dtype and device. Example::

    >>> import numpy as np
    >>> eval_sh_bases(1, np.array([[0.0, 0.0, 1.0]])).round(6) + 0.0
    array([[0.282095, 0.      , 0.488603, 0.      ]])
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "SH_C0",
    "SH_C1",
    "SH_C2",
    "SH_C3",
    "SH_C4",
    "MAX_SH_DEGREE",
    "num_sh_bases",
    "sh_degree_from_bases",
    "eval_sh_bases",
    "eval_sg_bases",
]

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396]
SH_C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435]
SH_C4 = [2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892,
         0.10578554691520431, -0.6690465435572892, 0.47308734787878004, -1.7701307697799304,
         0.6258357354491761]

MAX_SH_DEGREE = 4


def num_sh_bases(degree: int) -> int:
    """Number of SH basis functions up to ``degree`` (0..4): ``(degree + 1) ** 2``."""
    if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) \
            or not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be an integer in 0..{MAX_SH_DEGREE}, got {degree!r}")
    return (int(degree) + 1) ** 2


def sh_degree_from_bases(n: int) -> int:
    """Inverse of :func:`num_sh_bases`: 1 -> 0, 4 -> 1, 9 -> 2, 16 -> 3, 25 -> 4."""
    for deg in range(MAX_SH_DEGREE + 1):
        if (deg + 1) ** 2 == n:
            return deg
    raise ValueError(f"number of SH bases must be one of 1, 4, 9, 16, 25, got {n!r}")


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _check_dirs(dirs: Any) -> None:
    if not (_is_torch(dirs) or isinstance(dirs, np.ndarray)):
        raise TypeError(f"dirs: expected a numpy array or torch tensor, got {type(dirs).__name__}")
    if dirs.ndim < 1 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs: expected shape (..., 3), got {tuple(dirs.shape)}")


def eval_sh_bases(degree: int, dirs: Any) -> Any:
    """Evaluate the real SH basis up to ``degree`` at unit directions.

    Args:
        degree: SH degree, 0..4.
        dirs: ``[..., 3]`` unit directions (x, y, z), numpy array or torch tensor (float).
            Directions are used as given (not re-normalised).

    Returns:
        ``[..., (degree + 1) ** 2]`` basis values, same library, dtype and device as ``dirs``
        (integer numpy input is promoted to float64). Differentiable for torch inputs.
    """
    n = num_sh_bases(degree)
    _check_dirs(dirs)
    if _is_torch(dirs):
        import torch

        if not torch.is_floating_point(dirs):
            dirs = dirs.to(torch.get_default_dtype())
        stack = lambda cols: torch.stack(cols, dim=-1)  # noqa: E731
        const = lambda v, ref: torch.full_like(ref, v)  # noqa: E731
    else:
        if not np.issubdtype(dirs.dtype, np.floating):
            dirs = dirs.astype(np.float64)
        stack = lambda cols: np.stack(cols, axis=-1)  # noqa: E731
        const = lambda v, ref: np.full_like(ref, v)  # noqa: E731

    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    cols = [const(SH_C0, x)]
    if degree >= 1:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        cols += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        cols += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    if degree >= 4:
        cols += [
            SH_C4[0] * xy * (xx - yy),
            SH_C4[1] * yz * (3.0 * xx - yy),
            SH_C4[2] * xy * (7.0 * zz - 1.0),
            SH_C4[3] * yz * (7.0 * zz - 3.0),
            SH_C4[4] * (zz * (35.0 * zz - 30.0) + 3.0),
            SH_C4[5] * xz * (7.0 * zz - 3.0),
            SH_C4[6] * (xx - yy) * (7.0 * zz - 1.0),
            SH_C4[7] * xz * (xx - 3.0 * yy),
            SH_C4[8] * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy)),
        ]
    assert len(cols) == n
    return stack(cols)


def eval_sg_bases(lobe_axes: Any, sharpness: Any, dirs: Any) -> Any:
    """Evaluate spherical-Gaussian bases (svox ``SG<B>`` convention).

    ``G_b(d) = exp(λ_b (μ_b · d - 1)) / B``.

    Args:
        lobe_axes: ``[B, 3]`` unit lobe axes μ_b.
        sharpness: ``[B]`` sharpness λ_b ≥ 0 (1/radian² scale; larger = narrower lobe).
        dirs: ``[..., 3]`` unit view directions.

    All three must be the same library (numpy or torch); torch inputs are differentiable.

    Returns:
        ``[..., B]`` basis values, same library/dtype/device as ``dirs``.
    """
    _check_dirs(dirs)
    if lobe_axes.ndim != 2 or lobe_axes.shape[1] != 3:
        raise ValueError(f"lobe_axes: expected shape (B, 3), got {tuple(lobe_axes.shape)}")
    n_lobes = lobe_axes.shape[0]
    if tuple(sharpness.shape) != (n_lobes,):
        raise ValueError(f"sharpness: expected shape ({n_lobes},), got {tuple(sharpness.shape)}")
    if n_lobes == 0:
        raise ValueError("lobe_axes: need at least one lobe")
    if _is_torch(dirs):
        import torch

        if not torch.is_floating_point(dirs):
            dirs = dirs.to(torch.get_default_dtype())
        mu = torch.as_tensor(lobe_axes, dtype=dirs.dtype, device=dirs.device)
        lam = torch.as_tensor(sharpness, dtype=dirs.dtype, device=dirs.device)
        cos = torch.matmul(dirs, mu.T)
        return torch.exp(lam * (cos - 1.0)) / n_lobes
    if _is_torch(lobe_axes) or _is_torch(sharpness):
        raise TypeError("eval_sg_bases: dirs is numpy but lobe_axes/sharpness are torch tensors")
    if not np.issubdtype(dirs.dtype, np.floating):
        dirs = dirs.astype(np.float64)
    mu = np.asarray(lobe_axes, dtype=dirs.dtype)
    lam = np.asarray(sharpness, dtype=dirs.dtype)
    cos = dirs @ mu.T
    return (np.exp(lam * (cos - 1.0)) / n_lobes).astype(dirs.dtype, copy=False)
