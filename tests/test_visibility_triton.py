"""The visibility filter's Triton kernel (issue 47) against the numba kernel, in Triton's
interpreter on CPU tensors (``triton_cpu``): the same maxima, the same filter over cameras,
and no read-back per view.

Tolerance: the kernel does the numba kernel's float64 arithmetic in the same order (no fused
multiply-adds on the GPU) and rounds each weight to float32 before its atomic maximum, as the
numba kernel rounds into its rows; the maxima can differ only where the two ``exp``
implementations differ in the last float64 bit *and* that flips a float32 rounding, or a
transmittance within a float64 bit of ``min_weight``. ``atol = 1e-6`` (about 8 float32 ulps
at 1) leaves room for that on the GPU; in the interpreter (NumPy's float64) they are equal.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from plenoctree.convert.grid import GridSpec
from plenoctree.convert.visibility import candidates, max_ray_weights, visibility_weights
from plenoctree.datasets import Cameras
from plenoctree.datasets.procedural import look_at

ATOL = 1e-6

pytestmark = pytest.mark.gpu_sim


def _blobs_case(seed: int, res: int = 12, n: int = 400):
    """A ``res³`` σ grid of sparse noise plus two dense blobs (one opaque: rays stop in it),
    and ``n`` rays: from outside at the box, from inside, axis-parallel (some along cell
    planes), pointing away (misses) and through the box's corner region."""
    rng = np.random.default_rng(seed)
    spec = GridSpec.make(rng.uniform(-0.3, 0.3, 3), rng.uniform(0.6, 1.4, 3), res)
    sigma = ((rng.random((res,) * 3) < 0.15) * rng.exponential(3.0, (res,) * 3))
    g = (np.indices((res,) * 3).transpose(1, 2, 3, 0) + 0.5) / res
    sigma += 40.0 * (np.linalg.norm(g - [0.35, 0.4, 0.5], axis=-1) < 0.2)
    sigma += 800.0 * (np.linalg.norm(g - [0.7, 0.6, 0.45], axis=-1) < 0.15)
    o = spec.center + rng.normal(size=(n, 3)) * 3.0 * spec.radius
    d = spec.center - o + rng.normal(size=(n, 3)) * 0.5 * spec.radius
    o[:50] = spec.center + rng.uniform(-0.9, 0.9, (50, 3)) * spec.radius     # inside
    d[:50] = rng.normal(size=(50, 3))
    axis = rng.integers(0, 3, 60)
    d[50:110] = 0.0
    d[50:110, axis] = rng.choice([-1.0, 1.0], 60)                            # axis-parallel
    o[50:110] = spec.center + rng.uniform(-0.9, 0.9, (60, 3)) * spec.radius - 3.0 * d[50:110]
    o[110:125] = spec.lo + spec.cell * [2.0, 5.0, 7.0] - [4.0, 0.0, 0.0]     # on cell planes
    d[110:125] = [1.0, 0.0, 0.0]
    d[125:145] = o[125:145] - spec.center                                    # pointing away
    o[145:160] = spec.center + spec.radius * rng.choice([-1.05, 1.05], (15, 3))
    d[145:160] = -(o[145:160] - spec.center) + rng.normal(size=(15, 3)) * 0.1  # corners
    return spec, sigma.astype(np.float32), o.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_triton_kernel_matches_numba(triton_cpu, seed):
    spec, sigma, o, d = _blobs_case(seed)
    cand = candidates(sigma, spec, 1e-3)
    want = max_ray_weights(sigma, spec, cand, o, d, backend="numba").max(0)
    out = max_ray_weights(sigma, spec, cand, o, d, backend="triton")
    assert tuple(out.shape) == (1, cand.flat.size)
    got = out.cpu().numpy().max(0)
    assert (want > 0).sum() > 200 and (want == 0).sum() > 20     # seen cells, unreached ones
    np.testing.assert_allclose(got, want, rtol=0, atol=ATOL)


def test_triton_accumulates_into_host_and_device_maxima(triton_cpu):
    spec, sigma, o, d = _blobs_case(3)
    cand = candidates(sigma, spec, 1e-3)
    want = max_ray_weights(sigma, spec, cand, o, d, backend="numba").max(0)
    host = np.zeros((1, cand.flat.size), np.float32)
    max_ray_weights(sigma, spec, cand, o[:200], d[:200], backend="triton", out=host)
    assert max_ray_weights(sigma, spec, cand, o[200:], d[200:], "triton", out=host) is host
    np.testing.assert_allclose(host[0], want, rtol=0, atol=ATOL)
    dev = max_ray_weights(sigma, spec, cand, o[:200], d[:200], backend="triton")
    assert max_ray_weights(sigma, spec, cand, o[200:], d[200:], "triton", out=dev) is dev
    np.testing.assert_allclose(dev.cpu().numpy()[0], want, rtol=0, atol=ATOL)


def _cameras(n: int, size: int = 12) -> Cameras:
    eyes = [[2.5, 0.4, 0.3], [-0.3, 2.6, 0.5], [0.2, -0.4, 2.4], [-2.0, -1.5, -0.8]][:n]
    c2w = np.stack([look_at(e) for e in eyes]).astype(np.float32)
    return Cameras(c2w, 14.0, 14.0, size / 2, size / 2, size, size)


def test_visibility_weights_triton_equals_numba(triton_cpu):
    spec, sigma, _, _ = _blobs_case(4)
    spec = GridSpec.make(0.0, 0.9, spec.res)
    cams = _cameras(4)
    cand, want = visibility_weights(sigma, spec, cams, 1e-3, backend="numba",
                                    show_progress=False)
    cand_t, got = visibility_weights(sigma, spec, cams, 1e-3, backend="triton",
                                     show_progress=False)
    np.testing.assert_array_equal(cand_t.flat, cand.flat)
    assert got.dtype == np.float32 and got.shape == want.shape
    assert (want > 0).sum() > 100
    # the device makes the pinhole rays in float64 as generate_rays does (rounded to float32:
    # equal but for an occasional last bit), so the maxima agree to the same tolerance
    np.testing.assert_allclose(got, want, rtol=0, atol=ATOL)


def test_visibility_weights_triton_reads_back_once(triton_cpu):
    """Uploads (σ, candidates, geometry, cameras) and the one read-back do not grow with the
    views; every view is one launch (counted as benchmarks/step_ops.py does)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import step_ops

    spec, sigma, _, _ = _blobs_case(5, res=8)
    spec = GridSpec.make(0.0, 0.9, spec.res)
    counter, rows = step_ops.Recorder(), []
    for n in (1, 3):
        with counter.region() as c:
            visibility_weights(sigma, spec, _cameras(n, size=6), 1e-3, backend="triton",
                               show_progress=False)
        rows.append((c.triton, dict(c.syncs)))
    (launch1, sync1), (launch3, sync3) = rows
    assert (launch1, launch3) == (1, 3)
    assert sync1 == sync3, rows
    assert sync1.get("host", 0) == 1 and sync1.get("item", 0) == 0, rows


def test_visibility_weights_triton_ndc_views_equal_numba(triton_cpu):
    """Forward-facing views: NDC rays (made on the host, uploaded per view) in the NDC cube."""
    spec, sigma, _, _ = _blobs_case(6)
    spec = GridSpec.make(0.0, 1.0, spec.res)
    c2w = np.tile(np.eye(4, dtype=np.float32), (3, 1, 1))
    c2w[:, :3, 3] = [[0.0, 0.0, 0.0], [0.1, -0.05, 0.0], [-0.08, 0.1, 0.05]]
    cams = Cameras(c2w, 10.0, 10.0, 5.0, 4.0, 10, 8, ndc=True)
    _, want = visibility_weights(sigma, spec, cams, 1e-3, backend="numba", show_progress=False)
    _, got = visibility_weights(sigma, spec, cams, 1e-3, backend="triton", show_progress=False)
    assert (want > 0).sum() > 50
    np.testing.assert_allclose(got, want, rtol=0, atol=ATOL)
