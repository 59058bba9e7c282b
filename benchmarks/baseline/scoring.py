"""Frozen copies of what scoring used before: the torch ``conv2d`` SSIM and the ``zipfile``
member reads of the ``.npz`` reader (before the direct reads), kept only so
``benchmarks/scoring_speed.py`` can measure today's code against them in the same run."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np


def read_members_zipfile(path: Path) -> None:
    """Read every member the way the reader did before: ``ZipExtFile.readinto``."""
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():
            with z.open(info) as f:
                f.readinto(bytearray(info.file_size))


def ssim_torch(pred: np.ndarray, gt: np.ndarray, window: int = 11, sigma: float = 1.5) -> float:
    """The SSIM of the previous release (torch conv2d blur)."""
    import torch

    from plenoctree.metrics import _gaussian_window

    p, g = pred.astype(np.float64)[None], gt.astype(np.float64)[None]
    n, h, w, c = p.shape
    filt = torch.from_numpy(_gaussian_window(window, sigma))
    x = torch.from_numpy(np.ascontiguousarray(p.transpose(0, 3, 1, 2))).reshape(n * c, 1, h, w)
    y = torch.from_numpy(np.ascontiguousarray(g.transpose(0, 3, 1, 2))).reshape(n * c, 1, h, w)
    kh, kw = filt.view(1, 1, window, 1), filt.view(1, 1, 1, window)
    conv = torch.nn.functional.conv2d
    mu_x, mu_y, exx, eyy, exy = conv(conv(torch.cat([x, y, x * x, y * y, x * y]), kh),
                                     kw).split(n * c)
    sxx = torch.clamp(exx - mu_x ** 2, min=0.0)
    syy = torch.clamp(eyy - mu_y ** 2, min=0.0)
    sxy = exy - mu_x * mu_y
    sxy = torch.sign(sxy) * torch.minimum(torch.sqrt(sxx * syy), sxy.abs())
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2)
    return float((num / den).mean())
