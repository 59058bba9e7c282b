"""numba kernels for NeRF-SH colours: ``rgb = sigmoid(Σ_b k_b Y_b(d))`` and its gradient.

Imported lazily by :func:`plenoctree.nerf.model.sh_colors`. The twin is
:func:`plenoctree.nerf.model._sh_colors_torch` (built on :func:`plenoctree.sh.eval_sh_bases`,
the package's SH convention: svox / PlenOctree / 3DGS signs).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..sh import SH_C0, SH_C1, SH_C2, SH_C3, SH_C4

_C2 = np.array(SH_C2, np.float32)
_C3 = np.array(SH_C3, np.float32)
_C4 = np.array(SH_C4, np.float32)


@nb.njit(inline="always")
def _basis(x, y, z, degree, out, c2, c3, c4):
    out[0] = np.float32(SH_C0)
    if degree < 1:
        return
    c1 = np.float32(SH_C1)
    out[1] = -c1 * y
    out[2] = c1 * z
    out[3] = -c1 * x
    if degree < 2:
        return
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    out[4] = c2[0] * xy
    out[5] = c2[1] * yz
    out[6] = c2[2] * (np.float32(2.0) * zz - xx - yy)
    out[7] = c2[3] * xz
    out[8] = c2[4] * (xx - yy)
    if degree < 3:
        return
    out[9] = c3[0] * y * (np.float32(3.0) * xx - yy)
    out[10] = c3[1] * xy * z
    out[11] = c3[2] * y * (np.float32(4.0) * zz - xx - yy)
    out[12] = c3[3] * z * (np.float32(2.0) * zz - np.float32(3.0) * xx - np.float32(3.0) * yy)
    out[13] = c3[4] * x * (np.float32(4.0) * zz - xx - yy)
    out[14] = c3[5] * z * (xx - yy)
    out[15] = c3[6] * x * (xx - np.float32(3.0) * yy)
    if degree < 4:
        return
    out[16] = c4[0] * xy * (xx - yy)
    out[17] = c4[1] * yz * (np.float32(3.0) * xx - yy)
    out[18] = c4[2] * xy * (np.float32(7.0) * zz - np.float32(1.0))
    out[19] = c4[3] * yz * (np.float32(7.0) * zz - np.float32(3.0))
    out[20] = c4[4] * (zz * (np.float32(35.0) * zz - np.float32(30.0)) + np.float32(3.0))
    out[21] = c4[5] * xz * (np.float32(7.0) * zz - np.float32(3.0))
    out[22] = c4[6] * (xx - yy) * (np.float32(7.0) * zz - np.float32(1.0))
    out[23] = c4[7] * xz * (xx - np.float32(3.0) * yy)
    out[24] = c4[8] * (xx * (xx - np.float32(3.0) * yy) - yy * (np.float32(3.0) * xx - yy))


@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def sh_color_forward(coeffs, dirs, degree, basis, rgb):  # pragma: no cover - compiled
    """``rgb[m, c] = sigmoid(Σ_b coeffs[m, c·B + b] · Y_b(dirs[m]))``; also fills
    ``basis [M, B]`` (kept for the backward pass). float32 throughout."""
    nb_ = basis.shape[1]
    c2, c3, c4 = _C2, _C3, _C4
    for m in nb.prange(coeffs.shape[0]):
        row = basis[m]
        _basis(dirs[m, 0], dirs[m, 1], dirs[m, 2], degree, row, c2, c3, c4)
        for c in range(3):
            acc = np.float32(0.0)
            for b in range(nb_):
                acc += coeffs[m, c * nb_ + b] * row[b]
            rgb[m, c] = np.float32(1.0) / (np.float32(1.0) + np.exp(-acc))


@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def sh_color_backward(grad_rgb, rgb, basis, grad_coeffs):  # pragma: no cover - compiled
    """``grad_coeffs[m, c·B + b] = grad_rgb[m, c] · s (1 - s) · Y_b`` with ``s = rgb[m, c]``."""
    nb_ = basis.shape[1]
    for m in nb.prange(rgb.shape[0]):
        for c in range(3):
            s = rgb[m, c]
            g = grad_rgb[m, c] * s * (np.float32(1.0) - s)
            for b in range(nb_):
                grad_coeffs[m, c * nb_ + b] = g * basis[m, b]
