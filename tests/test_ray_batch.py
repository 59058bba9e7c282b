"""Op ``ray_batch`` (nerf/raygen.py, issue 47): the fixed step's rays, targets, backgrounds
and box bounds in one launch. The numba and Triton kernels (Triton's interpreter without a
GPU) against the torch twin, the waves' code: pinhole and NDC rays, shared and per-camera
intrinsics, the dataset's background, alpha over random colours, opaque photos over random
colours; the twin against the cameras' own rays; the waves' draw left as it was."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from plenoctree import backend
from plenoctree.datasets import Cameras, Dataset
from plenoctree.errors import ConfigError
from plenoctree.nerf.raygen import (BG_ALPHA, BG_DATA, BG_OPAQUE, draw_uniforms, pixel_index,
                                    ray_batch)
from plenoctree.nerf.renderer import ray_bounds
from plenoctree.nerf.training import RaySource

ON_GPU = torch.cuda.is_available()
DEV = torch.device("cuda" if ON_GPU else "cpu")
N, H, W = 3, 5, 7
BOX = [[-1.5, -1.2, -1.0], [1.0, 1.3, 0.8]]
FIELDS = ("origins", "dirs", "target", "background", "t_min", "t_max")


def _rotations(rng, n: int, tilt: float) -> np.ndarray:
    """``[n, 3, 3]`` rotations by random axis-angles of about ``tilt`` radians."""
    v = rng.normal(size=(n, 3)) * tilt
    out = np.empty((n, 3, 3))
    for i, w in enumerate(v):
        a = np.linalg.norm(w)
        k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / a
        out[i] = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
    return out


def _data(kind: str, seed: int = 0) -> Dataset:
    """``N`` cameras of ``W x H`` images: ``kind`` "pinhole" (looking every way), "per_camera"
    (their own intrinsics), "ndc" / "ndc_per_camera" (forward-facing, NDC rays)."""
    rng = np.random.default_rng(seed)
    ndc = kind.startswith("ndc")
    c2w = np.tile(np.eye(4), (N, 1, 1))
    c2w[:, :3, :3] = _rotations(rng, N, 0.2 if ndc else 2.0)
    c2w[:, :3, 3] = rng.normal(size=(N, 3)) * (0.3 if ndc else 2.0)
    fx, fy, cx, cy = 6.0, 6.5, 3.5, 2.5
    if kind.endswith("per_camera"):
        fx, cy = 6.0 + np.arange(N), 2.5 + 0.3 * np.arange(N)
    cams = Cameras(c2w, fx, fy, cx, cy, W, H, ndc=ndc)
    images = rng.random((N, H, W, 3)).astype(np.float32)
    alphas = rng.random((N, H, W)).astype(np.float32)
    return Dataset(images, cams, 0.3, 5.0, BOX, "train", ".", (0.9, 0.5, 0.1), list("abc"),
                   alphas=alphas)


def _source(kind: str, mode: int) -> RaySource:
    data = _data(kind)
    if mode == BG_OPAQUE:
        data = dataclasses.replace(data, alphas=None)
    src = RaySource(data, DEV, random_background=mode != BG_DATA,
                    opaque_photos=mode == BG_OPAQUE)
    assert src.background_mode == mode
    return src


def _inputs(n: int = 400, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    u = draw_uniforms(n, torch.Generator(DEV).manual_seed(seed), DEV)
    u[:3, 0] = torch.tensor([0.0, 0.5, 1.0 - 2.0 ** -53])          # the first and last pixel
    return u, torch.tensor(BOX, device=DEV)


def _assert_same(kernel, twin, bbox, src):
    """Pixels, targets and backgrounds equal; rays equal to rounding (the twin's matrix
    product and norm may sum in another order: on a GPU); the bounds those of the kernel's
    own rays, to the bit."""
    for f in FIELDS:
        a = getattr(kernel, f)
        assert a.dtype == torch.float32 and a.is_contiguous() and a.device == bbox.device, f
    assert torch.equal(kernel.target, twin.target)
    assert torch.equal(kernel.background, twin.background.expand(len(twin), 3))
    torch.testing.assert_close(kernel.origins, twin.origins, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(kernel.dirs, twin.dirs, atol=1e-6, rtol=1e-6)
    t0, t1 = ray_bounds(kernel.origins, kernel.dirs, bbox, src.near, src.far)
    assert torch.equal(kernel.t_min, t0) and torch.equal(kernel.t_max, t1)
    if not ON_GPU:                              # the interpreter and numba: the twin's order
        for f in FIELDS:
            assert torch.equal(getattr(kernel, f), getattr(twin, f).expand_as(
                getattr(kernel, f))), f


CASES = [("pinhole", BG_DATA), ("pinhole", BG_ALPHA), ("per_camera", BG_OPAQUE),
         ("ndc", BG_DATA), ("ndc_per_camera", BG_ALPHA), ("ndc", BG_OPAQUE)]


@pytest.mark.skipif(ON_GPU, reason="numba runs on CPU tensors")
@pytest.mark.parametrize("kind,mode", CASES)
def test_numba_kernel_equals_the_twin(kind, mode):
    src = _source(kind, mode)
    u, bbox = _inputs()
    twin = ray_batch(src, u, bbox, backend="torch")
    _assert_same(ray_batch(src, u, bbox, backend="numba"), twin, bbox, src)
    assert backend.resolve("ray_batch", "auto", "cpu") == "numba"


@pytest.mark.gpu_sim
@pytest.mark.parametrize("kind,mode", CASES)
def test_triton_kernel_equals_the_twin(kind, mode, triton_cpu):
    src = _source(kind, mode)
    u, bbox = _inputs()
    _assert_same(ray_batch(src, u, bbox, backend="triton"),
                 ray_batch(src, u, bbox, backend="torch"), bbox, src)


@pytest.mark.gpu_sim
def test_triton_kernel_is_one_launch_without_read_backs(triton_cpu):
    """Six allocations and one launch at any batch (counted as benchmarks/step_ops.py does)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import step_ops

    src = _source("ndc_per_camera", BG_ALPHA)
    counter, counts = step_ops.Recorder(), []
    for n in (64, 700):
        u, bbox = _inputs(n)
        with counter.region() as c:
            ray_batch(src, u, bbox, backend="triton")
        counts.append((c.ops, c.triton, sum(c.syncs.values())))
    assert counts == [(6, 1, 0)] * 2, counts


@pytest.mark.parametrize("kind", ["pinhole", "ndc_per_camera"])
def test_the_twin_makes_the_cameras_rays_of_the_pixels_it_picks(kind):
    src = _source(kind, BG_ALPHA)
    u, bbox = _inputs()
    m = N * H * W
    idx = pixel_index(u, m)
    assert idx[:3].tolist() == [0, m // 2, m - 1] and int(idx.min()) >= 0
    rays = ray_batch(src, u, bbox, backend="torch")
    o_all, d_all = src.cameras.all_rays()
    np.testing.assert_allclose(rays.origins.cpu(), o_all.reshape(-1, 3)[idx.cpu()], atol=2e-5)
    np.testing.assert_allclose(rays.dirs.cpu(), d_all.reshape(-1, 3)[idx.cpu()], atol=2e-5)
    a = src.alphas[idx][:, None]
    want = src.images[idx] - (1 - a) * src.bg + (1 - a) * u[:, 1:].float()
    assert torch.equal(rays.target, want)


def test_the_waves_draw_is_unchanged():
    """``RaySource.sample`` (the cpu preset's step) draws as before: the pixels by
    ``randint``, then the random colours."""
    src = _source("pinhole", BG_ALPHA)
    o, d, target, bg = src.sample(300, torch.Generator(DEV).manual_seed(3))
    g = torch.Generator(DEV).manual_seed(3)
    idx = torch.randint(N * H * W, (300,), generator=g, device=DEV)
    want_bg = torch.rand((300, 3), generator=g, device=DEV)
    a = src.alphas[idx][:, None]
    assert torch.equal(bg, want_bg) and torch.equal(o, src.rays_of(idx)[0])
    assert torch.equal(target, src.images[idx] - (1.0 - a) * src.bg + (1.0 - a) * want_bg)


def test_bad_inputs_and_cameras_are_refused():
    src = _source("pinhole", BG_DATA)
    u, bbox = _inputs(10)
    with pytest.raises(ValueError, match=r"u must be float64 \[R, 4\]"):
        ray_batch(src, u.float(), bbox)
    with pytest.raises(ValueError, match=r"bbox must be float32 \[2, 3\]"):
        ray_batch(src, u, bbox.double())
    data = _data("ndc")
    flipped = data.cameras.c2w.copy()
    flipped[0, :3, :3] = np.diag([1.0, -1.0, -1.0])         # camera 0 looks up +z
    cams = dataclasses.replace(data.cameras, c2w=flipped)
    with pytest.raises(ConfigError, match="down the world -z"):
        RaySource(dataclasses.replace(data, cameras=cams), DEV, False)
