"""The conversion's sampling on the field's device (issue 47, item 3;
``convert/device_sampling.py``), run on CPU tensors: the σ grid, extraction's per-voxel
averages and the refinement's scores and new leaves equal the host path's when both draw the
same uniforms, and a block reads back one row per cell instead of every sample.

The device path is chosen for fields on a GPU; here ``sampling_device`` is pointed at the CPU
and the device path's generator replaced by the host's numpy one (same seed, same draws in the
same order), so any difference is the path's arithmetic: float32 sums in another order
(``rtol = 1e-5``)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from plenoctree.convert import device_sampling as ds
from plenoctree.convert.field import NeRFField
from plenoctree.convert.grid import GridSpec, evaluate_density_grid
from plenoctree.convert.refine import _spread, leaf_spread, subdivide_leaves
from plenoctree.convert.sampling import SampleOptions, SamplingStats, average_samples, sample_cells
from plenoctree.nerf import ModelConfig, NeRFModel
from plenoctree.octree import Octree

BBOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.fixture
def on_device():
    """``enable()`` sends NeRF fields down the device path on CPU tensors, with the host's
    numpy draws (``benchmarks/conversion_ops.device_path_on_cpu``), until the test ends."""
    from contextlib import ExitStack

    from conversion_ops import device_path_on_cpu

    with ExitStack() as stack:
        yield lambda: stack.enter_context(device_path_on_cpu())


def _field(seed: int = 0) -> NeRFField:
    torch.manual_seed(seed)
    cfg = ModelConfig(encoding="posenc", pe_freqs=3, net_depth=2, net_width=32, basis="sh",
                      sh_degree=1, sigma_activation="relu")
    m = NeRFModel(cfg, BBOX, occ_res=4)
    with torch.no_grad():
        m.fine.head.bias[0] = 0.5               # most points have σ > 0, some not
    m.occupancy.mask[0, 0, :] = False           # and some cells the NeRF never samples
    return NeRFField(m)


def _values(rng, m=40, s=6, dim=13):
    vals = rng.normal(0.0, 2.0, (m, s, dim)).astype(np.float32)
    vals[..., -1] = np.maximum(vals[..., -1], 0.0) * rng.choice([0.0, 1.0, 300.0], (m, 1))
    vals[:3, :, -1] = 1e4               # opaque to float64 precision: σ from the largest sample
    return vals


@pytest.mark.parametrize("averaging", ["mean", "opacity"])
def test_the_twins_average_and_score_as_the_host(averaging):
    rng = np.random.default_rng(1)
    vals = _values(rng)
    h = rng.uniform(0.01, 0.2, vals.shape[0])
    want = average_samples(vals, h, averaging)
    got = ds.average_samples_torch(torch.from_numpy(vals), torch.from_numpy(h), averaging)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-5, atol=1e-6)
    assert (vals[..., -1].max(axis=1) == 0).any() and (vals[..., -1].min(axis=1) > 100).any()
    assert np.isfinite(got.numpy()).all()
    want_e = _spread(vals, want, h, "SH4", 4)
    got_e = ds.spread_torch(torch.from_numpy(vals), torch.from_numpy(want), torch.from_numpy(h),
                            "SH4", 4)
    np.testing.assert_allclose(got_e.numpy(), want_e, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("averaging", ["mean", "opacity"])
def test_extraction_sampling_on_the_device_equals_the_host(on_device, averaging):
    f = _field()
    spec = GridSpec.make([0.1, 0.0, -0.1], 0.9, 6)
    flat = np.flatnonzero(np.random.default_rng(2).random(6 ** 3) < 0.6)
    opts = SampleOptions(samples=5, chunk=60, seed=3, averaging=averaging, show_progress=False)
    st_host, st_dev = SamplingStats(), SamplingStats()
    sigma_host = evaluate_density_grid(f, spec, chunk=50, show_progress=False)
    host = sample_cells(f, spec, flat, opts, st_host)
    on_device()
    sigma_dev = evaluate_density_grid(f, spec, chunk=50, show_progress=False)
    dev = sample_cells(f, spec, flat, opts, st_dev)
    np.testing.assert_array_equal(sigma_dev, sigma_host)
    assert (sigma_host == 0).mean() > 0.02 and (sigma_host > 0).mean() > 0.5
    np.testing.assert_allclose(dev, host, rtol=1e-5, atol=1e-6)
    assert (st_dev.points, st_dev.nonfinite) == (st_host.points, st_host.nonfinite)


def test_refinement_on_the_device_equals_the_host(on_device):
    f = _field(1)
    spec = GridSpec.make(0.0, 1.0, 4)
    mask = evaluate_density_grid(f, spec, show_progress=False) > 0
    vals = sample_cells(f, spec, np.flatnonzero(mask), SampleOptions(samples=4))
    tree = Octree.from_grid(vals, mask, spec.center, spec.radius, f.data_format)
    leaves = np.arange(0, tree.n_leaves, 2)
    host_e = leaf_spread(tree, f, samples=6, seed=4, chunk=40, leaves=leaves)
    host_t, host_ce = subdivide_leaves(tree, leaves[:5], f, samples=6, seed=5, chunk=40,
                                       averaging="opacity")
    on_device()
    dev_e = leaf_spread(tree, f, samples=6, seed=4, chunk=40, leaves=leaves)
    dev_t, dev_ce = subdivide_leaves(tree, leaves[:5], f, samples=6, seed=5, chunk=40,
                                     averaging="opacity")
    assert host_e.max() > 0.01
    np.testing.assert_allclose(dev_e, host_e, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(dev_t.child, host_t.child)
    np.testing.assert_allclose(dev_t.data, host_t.data, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dev_ce, host_ce, rtol=1e-5, atol=1e-7)


def test_a_device_block_reads_back_one_row_per_cell(on_device):
    """Counted as benchmarks/step_ops.py counts: per block one upload (the cells) and one
    read-back of ``M`` rows, against the host path's points up and every sample down."""
    import step_ops

    f = _field()
    spec = GridSpec.make(0.0, 1.0, 8)
    flat = np.arange(0, 8 ** 3, 2)                      # 256 cells
    opts = SampleOptions(samples=8, chunk=512, seed=0, averaging="opacity",   # extract's
                         show_progress=False)                                 # 64 a block
    rec, rows = step_ops.Recorder(), {}
    for name in ("host", "device"):
        if name == "device":
            on_device()
        with rec.region() as c:
            sample_cells(f, spec, flat, opts)
        rows[name] = (dict(c.syncs), dict(c.bytes))
    (h_sync, h_bytes), (d_sync, d_bytes) = rows["host"], rows["device"]
    dim = 3 * 4 + 1
    assert h_sync == {"upload": 4, "host": 8}, rows              # 4 blocks: points; σ, coeffs
    assert h_bytes["host"] == 256 * 8 * dim * 4, rows
    assert d_sync == {"upload": 4, "host": 4, "item": 1}, rows   # the non-finite count, once
    assert d_bytes["host"] == 256 * dim * 4, rows                # one row per cell
    assert d_bytes["upload"] == (256 + 4 * 6) * 8 < h_bytes["upload"] / 10, rows
