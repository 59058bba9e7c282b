"""The training step of fixed shape (nerf/fixed.py, issue 47): the march into a sample budget
on every backend equals the twin, early termination in fixed shapes keeps the samples a Python
loop keeps, the render equals the waves path's (with and without early termination) on the
rays that fit, the step reads nothing back (counted with CPU tensors on the CUDA path's code),
and a run with it learns."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from nerf_fixtures import tiny_cpu_config, tiny_dataset
from test_nerf_sampling import BOX, _rays

from plenoctree.nerf.fixed import FixedBatch, march_fixed, terminate_fixed
from plenoctree.nerf.sampling import MarchGrid, MarchRays, march_rays

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return tiny_dataset(tmp_path_factory.mktemp("fixed_data"))


def _case(seed: int, n: int = 200):
    o, d, t0, t1, jit, g = _rays(n, seed)
    mask = torch.rand((16, 16, 16), generator=g) < 0.3
    return MarchRays(o, d, t0, t1, jit), MarchGrid(0.05, mask, BOX)


def _assert_fixed_equal(a, b):
    for name in ("ray_idx", "offsets", "complete", "n_valid", "total", "t", "points"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("capacity", [1, 700, 5000, 100000])
def test_march_fixed_numba_equals_twin_and_the_packed_march(capacity):
    rays, grid = _case(1)
    a = march_fixed(rays, grid, capacity, backend="numba")
    _assert_fixed_equal(a, march_fixed(rays, grid, capacity, backend="torch"))
    full = march_rays(rays, grid, backend="torch")
    n, m = rays.origins.shape[0], min(len(full), capacity)
    assert 700 < len(full) < 5000 and int(a.total) == len(full) and int(a.n_valid) == m
    assert a.ray_idx.shape == (capacity,) and a.offsets.shape == (n + 2,)
    assert torch.equal(a.ray_idx[:m], full.ray_idx[:m]) and (a.ray_idx[m:] == n).all()
    assert torch.equal(a.points[:m], full.points[:m])
    assert torch.equal(a.complete, full.offsets[1:] <= capacity)
    assert torch.equal(a.offsets[:-1], full.offsets.clamp(max=capacity))
    centre = 0.5 * (BOX[0] + BOX[1])
    assert (a.points[m:] == centre).all() and (a.t[m:] == 0).all()


def test_march_fixed_triton_equals_twin(triton_cpu):
    rays, grid = _case(2, n=96)
    for capacity in (300, 100000):
        a = march_fixed(rays, grid, capacity, backend="triton")
        _assert_fixed_equal(a, march_fixed(rays, grid, capacity, backend="torch"))


def _slab_sigma(points: torch.Tensor) -> torch.Tensor:
    """A density with an opaque slab (x > 0.1) in a varying fog, 1/world-length."""
    return 30.0 * (points[:, 0] > 0.1) + 2.0 * (torch.sin(7.0 * points[:, 1]) + 1.0)


def _terminated_reference(rays, grid, sigma_fn, thresh: float, k: int, capacity: int):
    """Early termination ray by ray in a Python loop: ``(ray_idx, t, points, complete)`` of
    each ray's marched samples while the optical depth before them is <= -log(thresh),
    packed into ``capacity`` slots; a ray is complete when its marched samples fit in
    ``k * capacity`` and its kept ones in ``capacity``."""
    full = march_rays(rays, grid, backend="torch")
    sigma = sigma_fn(full.points).double()
    rows, complete, used = [], [], 0
    for r in range(rays.origins.shape[0]):
        a, b = int(full.offsets[r]), int(full.offsets[r + 1])
        depth, kept = 0.0, []
        for i in range(a, b):
            if depth > -math.log(thresh):
                break
            kept.append(i)
            depth += float(sigma[i]) * grid.step
        used += len(kept)
        rows += kept
        complete.append(b <= k * capacity and used <= capacity)
    rows = torch.tensor(rows[:capacity], dtype=torch.int64)
    return full.ray_idx[rows], full.t[rows], full.points[rows], torch.tensor(complete)


@pytest.mark.parametrize("k,capacity", [(4, 50), (8, 300), (2, 100000)])
def test_terminate_fixed_keeps_what_a_loop_keeps(k, capacity):
    """The compacted candidates equal the per-ray loop's early-terminated samples on every
    ray that fits (and the packing of those that do not), cut at ``k S`` and at ``S``."""
    rays, grid = _case(3)
    n, thresh = rays.origins.shape[0], 1e-2
    cand = march_fixed(rays, grid, k * capacity, backend="torch")
    s = terminate_fixed(cand, _slab_sigma(cand.points), grid, thresh, capacity)
    ray_idx, t, pts, complete = _terminated_reference(rays, grid, _slab_sigma, thresh, k,
                                                      capacity)
    m = ray_idx.shape[0]
    if k * capacity >= int(cand.total):     # no candidate cut off: the same packing
        assert int(s.n_valid) == m
        assert torch.equal(s.ray_idx[:m], ray_idx) and torch.equal(s.t[:m], t)
        assert torch.equal(s.points[:m], pts)
    assert torch.equal(s.complete, complete)
    ok = complete[s.ray_idx.clamp(max=n - 1)] & (s.ray_idx < n)     # slots of complete rays
    ok_ref = complete[ray_idx]
    assert torch.equal(s.ray_idx[ok], ray_idx[ok_ref]) and torch.equal(s.t[ok], t[ok_ref])
    assert torch.equal(s.points[ok], pts[ok_ref])
    assert s.ray_idx.shape == (capacity,) and s.offsets.shape == (n + 2,)
    assert (s.ray_idx[int(s.n_valid):] == n).all() and int(s.offsets[-1]) == capacity
    counts = s.offsets[1:n + 1] - s.offsets[:n]
    assert torch.equal(torch.bincount(s.ray_idx, minlength=n + 1)[:n], counts)
    assert 0 < int(complete.sum()) and int(s.total) == int(cand.total)


def test_an_opaque_density_drops_the_samples_behind():
    """Opaque everywhere: each ray keeps its first candidate only; no density: every
    candidate, the march straight into the budget."""
    rays, grid = _case(4)
    n, capacity = rays.origins.shape[0], 1000
    cand = march_fixed(rays, grid, 8 * capacity, backend="torch")
    opaque = terminate_fixed(cand, torch.full_like(cand.t, 1e4), grid, 1e-4, capacity)
    counts = cand.offsets[1:n + 1] - cand.offsets[:n]
    assert torch.equal(opaque.offsets[1:n + 1] - opaque.offsets[:n], counts.clamp(max=1))
    firsts = cand.offsets[:n][counts > 0]
    assert torch.equal(opaque.t[:firsts.shape[0]], cand.t[firsts])
    assert bool(opaque.complete.all())
    clear = terminate_fixed(cand, torch.zeros_like(cand.t), grid, 1e-4, capacity)
    direct = march_fixed(rays, grid, capacity, backend="torch")
    assert int(direct.total) > capacity                       # the budget cuts rays off
    _assert_fixed_equal(clear, direct)


def _trainer(data: Path, out: Path, fixed: bool):
    from plenoctree.nerf.trainer import Trainer

    cfg = tiny_cpu_config(data, out, steps=10**6)
    cfg.fixed_step, cfg.val_views, cfg.amp = fixed, 0, "off"
    tr = Trainer(cfg, quiet=True)
    tr.setup()
    return tr


def test_render_fixed_equals_the_waves_without_early_termination(data, tmp_path):
    """The rays that fit in the budget get the colour of the waves path with
    ``stop_thresh = 0`` (the same jitter: both draw it first from the generator)."""
    from plenoctree.nerf.fixed import render_fixed
    from plenoctree.nerf.renderer import RayBatch, RenderMode, render_rays_occupancy

    tr = _trainer(data, tmp_path / "run", True)
    o, d, _, bg = tr.rays.sample(300, tr.gen)
    batch = RayBatch(o, d, tr.data.near, tr.data.far, bg)
    out = {}
    for name, capacity in (("fixed", 12000), ("waves", 0)):
        gen = torch.Generator().manual_seed(5)
        mode = RenderMode(train=True, generator=gen, stop_thresh=0.0, distortion=True)
        out[name] = (render_fixed(tr.model, batch, tr.cfg, mode, capacity) if capacity
                     else render_rays_occupancy(tr.model, batch, tr.cfg, mode))
    ok = out["fixed"]["complete"]
    assert 50 < int(ok.sum()) < 300                  # the budget cut some rays off
    for key in ("rgb", "acc", "distortion"):
        torch.testing.assert_close(out["fixed"][key][ok], out["waves"][key][ok],
                                   atol=2e-6, rtol=1e-5)


def test_render_fixed_with_early_termination_equals_the_waves(data, tmp_path):
    """With a density that stops rays inside the box, the rays that fit get the colour,
    opacity and distortion of the waves path at the same threshold: the same samples."""
    from plenoctree.nerf.fixed import render_fixed
    from plenoctree.nerf.renderer import RayBatch, RenderMode, render_rays_occupancy

    tr = _trainer(data, tmp_path / "run", True)
    with torch.no_grad():
        tr.model.fine.head.bias[0] += 3.0            # σ ~ 7: T falls to 1e-2 in ~20 samples
    o, d, _, bg = tr.rays.sample(300, tr.gen)
    batch = RayBatch(o, d, tr.data.near, tr.data.far, bg)
    out = {}
    for name, capacity in (("fixed", 3000), ("waves", 0)):
        gen = torch.Generator().manual_seed(5)
        mode = RenderMode(train=True, generator=gen, stop_thresh=1e-2, distortion=True)
        out[name] = (render_fixed(tr.model, batch, tr.cfg, mode, capacity) if capacity
                     else render_rays_occupancy(tr.model, batch, tr.cfg, mode))
    ok = out["fixed"]["complete"]
    done, kept = out["fixed"]["kept"].tolist()
    assert 50 < int(ok.sum()) < 300 and done == int(ok.sum())
    assert kept / done < 0.5 * int(out["fixed"]["total"]) / 300     # early termination cut
    for key in ("rgb", "acc", "distortion"):
        torch.testing.assert_close(out["fixed"][key][ok], out["waves"][key][ok],
                                   atol=2e-6, rtol=1e-5)


def test_the_fixed_step_reads_nothing_back(data, tmp_path, triton_cpu):
    """A whole training step (rays, march, network, loss, backward, Adam) on the CUDA path's
    code (Triton in its interpreter, counted with CPU tensors): no host round trip, no
    upload, and the same op count at any batch."""
    sys.path.insert(0, str(_BENCH))
    import step_ops

    from plenoctree._util import progress

    tr = _trainer(data, tmp_path / "run", True)
    bar = progress(total=1, disable=True)
    for _ in range(3):
        tr.iteration(bar)
    counter, seen = step_ops.Recorder(), []
    with step_ops.backends_of("cuda"):
        tr.iteration(bar)                    # once per process: the hash grid's layout
        for batch in (256, 1024, 256):
            tr.step = step_ops._step_number(tr.step, tr.cfg, False)
            tr.state.n_rays = float(batch)
            with counter.region() as c:
                tr.iteration(bar)
            seen.append(c)
    for c in seen:
        assert sum(c.syncs.values()) == 0, dict(c.sites)
        assert c.triton >= 4                    # march (2 passes), hash grid (2 passes)
    assert len({c.ops for c in seen}) == 1, [c.ops for c in seen]


def test_training_with_fixed_steps_learns_and_adapts_its_rays(data, tmp_path):
    from plenoctree.nerf import train

    cfg = tiny_cpu_config(data, tmp_path / "run", steps=150)
    cfg.fixed_step, cfg.val_split, cfg.val_views, cfg.lr_final = True, "train", 2, 5e-3
    res = train(cfg, quiet=True)
    first, last = res.log["train"][0]["psnr"], res.log["train"][-1]["psnr"]
    assert last > first + 5.0 and res.val_psnr > 20.0, (first, last, res.val_psnr)
    rays = {row["rays"] for row in res.log["train"]}
    assert all(r % 256 == 0 for r in rays) and len(rays) > 1      # adapted, in quanta


def _add(fb: FixedBatch, n_rays: int, total: torch.Tensor, kept: torch.Tensor) -> None:
    """A step's counts as the trainer adds them (device sums, host ray count)."""
    fb.add_device(total, kept)
    fb.count(n_rays)


def test_fixed_batch_quantises_and_adapts():
    class State:
        n_rays, spr, spr_marched = 4096.0, 0.0, 0.0

    fb = FixedBatch(1 << 14, 1 << 13, torch.device("cpu"))
    st = State()
    assert fb.rays(st.n_rays) == 4096 and fb.rays(100.0) == 256 and fb.rays(1e9) == 8192
    _add(fb, 1000, torch.tensor(20000), torch.tensor([1000.0, 20000.0], dtype=torch.float64))
    fb.adapt(st)
    assert st.spr == 20.0 and st.n_rays == (1 << 14) / 20.0 and fb.rays(st.n_rays) == 768
    assert fb.sums.sum() == 0
    # early termination (k = 8): 50 marched, 10 kept a ray; then the candidates bind
    fb, st = FixedBatch(1 << 14, 1 << 13, torch.device("cpu"), candidates=8), State()
    _add(fb, 1000, torch.tensor(50000), torch.tensor([900.0, 9000.0], dtype=torch.float64))
    fb.adapt(st)
    assert (st.spr, st.spr_marched) == (10.0, 50.0) and st.n_rays == (1 << 14) / 10.0
    _add(fb, 1000, torch.tensor(10**6), torch.tensor([900.0, 9000.0], dtype=torch.float64))
    fb.adapt(st)
    assert st.spr_marched == pytest.approx(145.0)
    assert st.n_rays == pytest.approx(8 * (1 << 14) / 145.0)
    for _ in range(2):              # a window of two steps enters as two steps of the waves'
        _add(fb, 1000, torch.tensor(245000), torch.tensor([900.0, 9000.0], dtype=torch.float64))
    fb.adapt(st)
    assert st.spr_marched == pytest.approx(0.81 * 145.0 + 0.19 * 245.0) and fb.steps == 0
