"""PSNR / SSIM / LPIPS: known values, a slow direct SSIM reference, numpy/torch inputs."""

from __future__ import annotations

import math
import sys
import types

import numpy as np
import pytest
import torch

from plenoctree import metrics
from plenoctree.errors import BackendError
from plenoctree.metrics import lpips, lpips_available, mse, psnr, ssim


def test_psnr_known_mse():
    gt = np.full((8, 8, 3), 0.5)
    pred = gt + 0.1                                   # MSE 0.01 -> 20 dB
    assert psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)
    assert mse(pred, gt) == pytest.approx(0.01)
    rng = np.random.default_rng(0)
    a = rng.random((5, 6, 3)).astype(np.float32)
    b = rng.random((5, 6, 3)).astype(np.float32)
    m = np.mean((a.astype(np.float64) - b) ** 2)
    assert psnr(a, b) == pytest.approx(-10 * math.log10(m), rel=1e-9)
    assert psnr(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(psnr(a, b), rel=1e-12)
    assert psnr(a, a) == math.inf
    with pytest.raises(ValueError, match="same shape"):
        psnr(a, b[:4])
    with pytest.raises(TypeError):
        psnr(a.astype(np.uint8), b.astype(np.uint8))


def _ssim_direct(x: np.ndarray, y: np.ndarray) -> float:
    """Slow reference: explicit 11x11 window sums at every valid position, per channel."""
    g1 = np.exp(-0.5 * ((np.arange(11) - 5) / 1.5) ** 2)
    win = np.outer(g1, g1)
    win /= win.sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    h, w, c = x.shape
    vals = []
    for ch in range(c):
        for i in range(h - 10):
            for j in range(w - 10):
                px, py = x[i:i + 11, j:j + 11, ch], y[i:i + 11, j:j + 11, ch]
                mx, my = (win * px).sum(), (win * py).sum()
                vx = max((win * (px - mx) ** 2).sum(), 0.0)
                vy = max((win * (py - my) ** 2).sum(), 0.0)
                cxy = (win * (px - mx) * (py - my)).sum()
                cxy = math.copysign(min(math.sqrt(vx * vy), abs(cxy)), cxy)
                vals.append((2 * mx * my + c1) * (2 * cxy + c2)
                            / ((mx * mx + my * my + c1) * (vx + vy + c2)))
    return float(np.mean(vals))


def test_ssim_matches_direct_reference():
    rng = np.random.default_rng(1)
    x = rng.random((16, 19, 3))
    y = np.clip(x + 0.2 * rng.normal(size=x.shape), 0, 1)
    ref = _ssim_direct(x, y)
    assert 0.1 < ref < 0.95
    assert ssim(x, y) == pytest.approx(ref, abs=1e-10)
    assert ssim(torch.from_numpy(x).float(), torch.from_numpy(y).float()) == pytest.approx(ref, abs=1e-5)
    # batched and 2-D inputs
    assert ssim(np.stack([x, x]), np.stack([y, x])) == pytest.approx((ref + 1) / 2, abs=1e-10)
    assert ssim(x[..., 0], y[..., 0]) == pytest.approx(_ssim_direct(x[..., :1], y[..., :1]),
                                                      abs=1e-10)


def test_ssim_matches_the_direct_reference_without_scipy_too(monkeypatch):
    """The blur has two paths: scipy's ``correlate1d`` (installed here) and plain numpy
    (without scipy); both give the direct reference's SSIM and the same blur."""
    rng = np.random.default_rng(3)
    z = rng.random((2, 3, 23, 17))
    for k in (11, 4, 7):
        filt = metrics._gaussian_window(k, 1.5)
        np.testing.assert_allclose(metrics._blur_valid(z, filt),
                                   metrics._blur_valid_numpy(z, filt), rtol=0, atol=1e-14)
    x = rng.random((16, 19, 3))
    y = np.clip(x + 0.2 * rng.normal(size=x.shape), 0, 1)
    monkeypatch.setitem(sys.modules, "scipy", None)          # import scipy raises ImportError
    assert ssim(x, y) == pytest.approx(_ssim_direct(x, y), abs=1e-10)


def test_ssim_identity_and_monotone_in_noise():
    rng = np.random.default_rng(2)
    img = rng.random((32, 32, 3))
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    scores = [ssim(np.clip(img + s * rng.normal(size=img.shape), 0, 1), img)
              for s in (0.01, 0.05, 0.1, 0.3)]
    assert all(a > b for a, b in zip(scores, scores[1:]))
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(img[:10], img[:10])


def test_lpips_unavailable_raises_backend_error(monkeypatch):
    monkeypatch.setattr(metrics, "_LPIPS_MODELS", {})
    monkeypatch.setattr(metrics, "_lpips_problem", lambda net: "the `lpips` package is not installed")
    assert lpips_available() is False
    with pytest.raises(BackendError, match="LPIPS needs the `lpips` package"):
        lpips(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)))


def test_lpips_available_is_bool_and_consistent():
    ok = lpips_available()
    assert isinstance(ok, bool)
    if not ok:
        with pytest.raises(BackendError, match="locally"):
            lpips(np.zeros((16, 16, 3)), np.ones((16, 16, 3)))
    assert lpips_available("resnet") is False


def test_lpips_adapter_with_fake_package(monkeypatch):
    """The adapter feeds [N, 3, H, W] tensors in [-1, 1] to lpips.LPIPS and averages."""
    seen = {}

    class FakeLPIPS(torch.nn.Module):
        def __init__(self, net, verbose):
            super().__init__()
            seen["net"] = net

        def forward(self, a, b):
            seen["shape"], seen["range"] = tuple(a.shape), (float(a.min()), float(a.max()))
            return ((a - b) ** 2).mean(dim=(1, 2, 3), keepdim=True)

    monkeypatch.setitem(sys.modules, "lpips", types.SimpleNamespace(LPIPS=FakeLPIPS))
    monkeypatch.setattr(metrics, "_LPIPS_MODELS", {})
    monkeypatch.setattr(metrics, "_lpips_problem", lambda net: None)
    a = np.zeros((2, 4, 5, 3), np.float32)
    b = np.ones((2, 4, 5, 3), np.float32)
    b[1] = 0.0
    assert lpips(a, b, net="alex") == pytest.approx(2.0)     # (4 + 0) / 2 in [-1, 1] units
    assert seen == {"net": "alex", "shape": (2, 3, 4, 5), "range": (-1.0, -1.0)}
    with pytest.raises(ValueError, match="RGB"):
        lpips(a[..., :2], b[..., :2])
