"""Image quality metrics used in the paper's tables: PSNR, SSIM and (when available) LPIPS.

Images are float arrays in [0, 1], numpy or torch, shaped ``[H, W]``, ``[H, W, C]`` or
``[N, H, W, C]`` (channels last). Every function returns a Python ``float``.

SSIM follows the NeRF / JaxNeRF / PlenOctree evaluation code exactly: an 11x11 Gaussian window
(σ = 1.5 pixels, separable, ``valid`` borders), ``K1 = 0.01``, ``K2 = 0.03``, data range 1,
variances clamped at 0 and the covariance clamped to ``±sqrt(σ_x² σ_y²)``; the SSIM map is
averaged over pixels and channels (and images).

LPIPS needs the ``lpips`` package and its backbone weights already on disk (never downloaded
here); :func:`lpips_available` says whether it can run.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .errors import BackendError

__all__ = ["psnr", "mse", "ssim", "lpips", "lpips_available"]


def _to_numpy(x: Any, name: str) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        raise TypeError(f"{name}: expected a float image in [0, 1], got dtype {x.dtype}")
    return x.astype(np.float64, copy=False)


def _pair(pred: Any, gt: Any) -> tuple[np.ndarray, np.ndarray]:
    p, g = _to_numpy(pred, "pred"), _to_numpy(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred and gt must have the same shape, got {list(p.shape)} and "
                         f"{list(g.shape)}")
    if p.ndim not in (2, 3, 4) or p.size == 0:
        raise ValueError(f"expected an image [H, W], [H, W, C] or [N, H, W, C], got shape "
                         f"{list(p.shape)}")
    return p, g


def mse(pred: Any, gt: Any) -> float:
    """Mean squared error over all pixels, channels (and images)."""
    p, g = _pair(pred, gt)
    return float(np.mean((p - g) ** 2))


def psnr(pred: Any, gt: Any) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]: ``-10 log10(MSE)``.

    The MSE is taken over every element (for ``[N, H, W, C]`` that is the PSNR of the pooled
    error, not the mean of per-image PSNRs). Identical images give ``inf``.
    """
    m = mse(pred, gt)
    return math.inf if m == 0.0 else -10.0 * math.log10(m)


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    hw = size // 2
    shift = (2 * hw - size + 1) / 2
    f = np.exp(-0.5 * ((np.arange(size) - hw + shift) / sigma) ** 2)
    return f / f.sum()


def _blur_valid(z: np.ndarray, filt: np.ndarray) -> np.ndarray:
    """Separable ``valid`` correlation of the last two axes of ``z`` with the 1-D ``filt``
    (as ``conv2d`` with an ``[k, 1]`` then a ``[1, k]`` kernel, ``k`` odd): scipy's
    ``ndimage.correlate1d`` per axis, cropped to the valid region, when scipy is installed
    (one pass in C per axis: a whole SSIM of a lego 400x400 view 1.9x faster, docs/performance.md
    "Scoring"), else :func:`_blur_valid_numpy` (the same values to ~1e-15)."""
    try:
        from scipy import ndimage
    except ImportError:
        return _blur_valid_numpy(z, filt)
    k = filt.shape[0]
    hw = k // 2
    h, w = z.shape[-2] - k + 1, z.shape[-1] - k + 1
    rows = ndimage.correlate1d(z, filt, axis=-2, mode="constant")[..., hw:hw + h, :]
    return ndimage.correlate1d(rows, filt, axis=-1, mode="constant")[..., hw:hw + w]


def _blur_valid_numpy(z: np.ndarray, filt: np.ndarray) -> np.ndarray:
    """:func:`_blur_valid` without scipy: ``k`` shifted multiply-adds per axis (torch's conv2d
    is slower still for one-channel float64 kernels)."""
    k = filt.shape[0]
    h, w = z.shape[-2] - k + 1, z.shape[-1] - k + 1
    rows = filt[0] * z[..., 0:h, :]
    for i in range(1, k):
        rows += filt[i] * z[..., i:i + h, :]
    out = filt[0] * rows[..., 0:w]
    for i in range(1, k):
        out += filt[i] * rows[..., i:i + w]
    return out


def ssim(pred: Any, gt: Any, window: int = 11, sigma: float = 1.5,
         k1: float = 0.01, k2: float = 0.03) -> float:
    """Structural similarity (mean of the SSIM map), NeRF / PlenOctree evaluation variant.

    Args:
        pred, gt: images in [0, 1], ``[H, W]``, ``[H, W, C]`` or ``[N, H, W, C]``, numpy or
            torch; ``H, W >= window``.
        window, sigma: Gaussian window size (pixels) and standard deviation (pixels).
        k1, k2: stabilising constants (data range 1).

    Returns:
        The SSIM map (``valid`` region, ``H - window + 1`` by ``W - window + 1``) averaged over
        pixels, channels and images; 1 for identical images.
    """
    p, g = _pair(pred, gt)
    if p.ndim == 2:
        p, g = p[None, :, :, None], g[None, :, :, None]
    elif p.ndim == 3:
        p, g = p[None], g[None]
    n, h, w, c = p.shape
    if h < window or w < window:
        raise ValueError(f"ssim needs images of at least {window}x{window} pixels, got {h}x{w}")
    filt = _gaussian_window(window, sigma)
    x, y = p.transpose(0, 3, 1, 2), g.transpose(0, 3, 1, 2)       # [N, C, H, W] views
    # one batched blur of the five statistics, [5, N, C, H', W']
    stats = _blur_valid(np.stack([x, y, x * x, y * y, x * y]), filt)
    mu_x, mu_y, exx, eyy, exy = stats
    sxx = np.maximum(exx - mu_x ** 2, 0.0)
    syy = np.maximum(eyy - mu_y ** 2, 0.0)
    sxy = exy - mu_x * mu_y
    sxy = np.sign(sxy) * np.minimum(np.sqrt(sxx * syy), np.abs(sxy))
    c1, c2 = k1 ** 2, k2 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2)
    return float((num / den).mean())


# --- LPIPS ------------------------------------------------------------------------------------
_LPIPS_MODELS: dict[str, Any] = {}
_BACKBONE_FILES = {   # torchvision checkpoints the lpips package loads for its backbones
    "alex": "alexnet-owt-7be5be79.pth",
    "vgg": "vgg16-397923af.pth",
    "squeeze": "squeezenet1_1-b8a52dc0.pth",
}


def _lpips_problem(net: str) -> str | None:
    """Why LPIPS with backbone ``net`` cannot run offline, or ``None`` when it can."""
    import importlib.util

    if net not in _BACKBONE_FILES:
        return f"unknown LPIPS network {net!r} (expected one of {sorted(_BACKBONE_FILES)})"
    if net in _LPIPS_MODELS:
        return None
    for mod in ("lpips", "torchvision"):
        if importlib.util.find_spec(mod) is None:
            return f"the `{mod}` package is not installed"
    import torch

    ckpt = Path(torch.hub.get_dir()) / "checkpoints" / _BACKBONE_FILES[net]
    if not ckpt.is_file():
        return f"the {net} backbone weights are not on disk (expected {ckpt})"
    return None


def lpips_available(net: str = "vgg") -> bool:
    """Whether :func:`lpips` can run with backbone ``net`` without downloading anything."""
    return _lpips_problem(net) is None


def _lpips_model(net: str):
    problem = _lpips_problem(net)
    if problem is not None:
        raise BackendError("LPIPS needs the `lpips` package and its weights available locally "
                           f"(nothing is downloaded): {problem}")
    if net not in _LPIPS_MODELS:
        import lpips as lpips_pkg

        model = lpips_pkg.LPIPS(net=net, verbose=False)
        model.eval()
        _LPIPS_MODELS[net] = model
    return _LPIPS_MODELS[net]


def lpips(pred: Any, gt: Any, net: str = "vgg") -> float:
    """Learned perceptual image patch similarity (lower is better), averaged over images.

    Args:
        pred, gt: RGB images in [0, 1], ``[H, W, 3]`` or ``[N, H, W, 3]``, numpy or torch.
        net: backbone, ``"vgg"`` (the PlenOctree paper's choice), ``"alex"`` or ``"squeeze"``.

    Raises:
        BackendError: the ``lpips`` package or its weights are not available locally.
    """
    import torch

    p, g = _pair(pred, gt)
    if p.ndim == 3:
        p, g = p[None], g[None]
    if p.ndim != 4 or p.shape[-1] != 3:
        raise ValueError(f"lpips expects RGB images [H, W, 3] or [N, H, W, 3], got {list(p.shape)}")
    model = _lpips_model(net)
    to_t = lambda a: torch.from_numpy(  # noqa: E731  [N,H,W,3] in [0,1] -> [N,3,H,W] in [-1,1]
        np.ascontiguousarray(a.transpose(0, 3, 1, 2), dtype=np.float32)) * 2.0 - 1.0
    with torch.no_grad():
        d = model(to_t(p), to_t(g))
    return float(d.mean())
