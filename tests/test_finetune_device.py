"""The device-resident fine-tuning step and loop (issue 47, item 2), counted and compared on the
CPU: the Triton kernels run in Triton's interpreter (as in ``test_triton_kernels.py``), each
against its torch twin; the twins against the CPU path's rays; a step on the CUDA path's code
(CPU tensors) dispatches a handful of ops, reads nothing back and uploads nothing
(``benchmarks/step_ops.py``'s ``Recorder``); and the numba path steps as it did before."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from plenoctree.datasets import load_dataset
from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
from plenoctree.octree import load_tree, save_tree
from plenoctree.optim._loop import FineTuneLoop, LoopOptions
from plenoctree.optim._views import ViewSet
from plenoctree.render import RenderOptions

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
ON_GPU = torch.cuda.is_available()
DEV = torch.device("cuda" if ON_GPU else "cpu")
W, H = 18, 14                     # not multiples of the tiles: border tiles have fewer pixels


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """3 train / 1 val / 1 test views of the procedural scene at 18x14 and a noisy 16³ tree."""
    root = tmp_path_factory.mktemp("ftdev")
    write_procedural_dataset(root / "data", n_train=3, n_val=1, n_test=1, width=W, height=H,
                             n_samples=64)
    t = procedural_tree(16)
    rng = np.random.default_rng(0)
    occ = (t.child == 0) & (t.data[..., -1] > 0)
    t.data[occ, :-1] += rng.normal(size=(int(occ.sum()), t.data_dim - 1)).astype(np.float32)
    save_tree(t, root / "noisy.npz", precision="fp32")
    return root


@pytest.fixture()
def triton_cpu(monkeypatch):
    """Triton on CPU tensors (Triton's interpreter) inside the test; the GPU when present."""
    pytest.importorskip("triton")
    if not ON_GPU:
        if os.environ.get("TRITON_INTERPRET") != "1":
            pytest.skip("TRITON_INTERPRET=1 must be set before triton is imported (conftest.py)")
        monkeypatch.setenv("PLENOCTREE_TRITON_CPU", "1")


@pytest.fixture()
def recorder(monkeypatch):
    monkeypatch.syspath_prepend(str(_BENCH))
    from step_ops import Recorder

    return Recorder()


def _views(root, split="train"):
    return ViewSet.from_dataset(load_dataset(root / "data", split))


def _stepper(backend, tree, optimizer="adam", lr=2e-2, **kw):
    from plenoctree.optim._steppers import make_stepper

    d2 = np.ascontiguousarray(tree.data.reshape(-1, tree.data_dim), np.float32).copy()
    opts = RenderOptions(background=(1.0, 1.0, 1.0), **kw)
    return make_stepper(backend, d2, tree, opts, optimizer, lr,
                        sigma_lr=None if optimizer == "sgd" else lr * 16,
                        device="cpu" if backend == "numba" else str(DEV))


def _ndc_views(tmp_path):
    from plenoctree.datasets.forward_facing import write_forward_facing_dataset

    root = write_forward_facing_dataset(tmp_path / "ff", n_images=4, width=13, height=10,
                                        n_samples=8)
    return ViewSet.from_dataset(load_dataset(root, "train"))


def _clip_cams(cams):
    """NDC cameras under the "any camera" rule, one behind the near plane, one looking away."""
    c = cams.copy()
    c[:, 0] = 3
    c[1, 16] = -5.0 * c[1, 19]
    c[2, 5:14] *= -1.0
    return c


# ----------------------------------------------------------------------------- rays, twins
@pytest.mark.parametrize("case", ["pinhole_u16_k4", "ndc_k3", "ndc_clip_k2", "float32_k1"])
def test_twin_rays_equal_the_cpu_path_rays(scene, tmp_path, case):
    """The twins make the rays and targets the CPU path makes (``ViewSet.tile_pixels`` and the
    numba ``pixel_rays``) in the same order; pixels past the border are flagged, not dropped."""
    from plenoctree.optim._device_stepper import DeviceViews
    from plenoctree.optim._device_twins import (batch_pixels_torch, camera_rays_torch,
                                                pixel_targets_torch)
    from plenoctree.optim._render_grad_numba import pixel_rays

    views = _views(scene) if case.startswith(("pinhole", "float32")) else _ndc_views(tmp_path)
    if case == "float32_k1":
        views = dataclasses.replace(views, images=np.stack(
            [views.image(i) for i in range(len(views))]), cameras=views.cameras,
            cam_index=views.cam_index)
    cams = _clip_cams(views.packed_cameras) if case == "ndc_clip_k2" else views.packed_cameras
    k = int(case[-1])
    tiles = np.random.default_rng(1).permutation(views.n_tiles(k))[:23]
    idx = views.tile_pixels(tiles, k)
    o, d, t = (np.empty((idx.size, 3), np.float32) for _ in range(3))
    pixel_rays(cams, views.width, views.height, idx, views.images, views.unit, o, d, t)
    dv = DeviceViews(views, DEV)
    img, u, v, outside = batch_pixels_torch(torch.from_numpy(tiles).to(DEV), k, views.width,
                                            views.height)
    assert img.shape == (23 * k * k,) and int((~outside).sum()) == idx.size
    inside = ~outside
    flat = (img * views.height + v) * views.width + u
    np.testing.assert_array_equal(flat[inside].cpu().numpy(), idx)
    o2, d2 = camera_rays_torch(torch.from_numpy(cams).to(DEV), img, u, v)
    t2 = pixel_targets_torch(dv.images, dv.unit_value, img, u, v)
    np.testing.assert_allclose(o2[inside].cpu().numpy(), o, rtol=0, atol=2e-6)
    np.testing.assert_allclose(d2[inside].cpu().numpy(), d, rtol=0, atol=2e-6)
    np.testing.assert_array_equal(t2[inside].cpu().numpy(), t)
    if case == "ndc_clip_k2":                    # both clip branches were taken
        assert (o[:, 2] == 1e4).any() and (o[:, 2] != 1e4).any()


@pytest.mark.parametrize("fmt,cam,srange", [("SH16", "pinhole", (0, -1)),
                                            ("SH25", "ndc", (1, 7)), ("SG3", "ndc_clip", (0, -1)),
                                            ("RGBA", "pinhole", (0, -1)),
                                            ("SH9", "pinhole", (2, 5))])
def test_rays_kernel_matches_its_twin(scene, tmp_path, triton_cpu, fmt, cam, srange):
    """One launch makes what the twins and ``prepare_rays`` + ``ray_basis_torch`` make: the
    march kernel's geometry rows (a miss and the border flag past the border), the basis
    values (SH 0-4, SG, RGBA, a basis range) and the targets."""
    from plenoctree.render._rays_triton import COL_OUTSIDE, batch_rays, geometry_tensor
    from plenoctree.optim._device_stepper import DeviceViews
    from plenoctree.optim._device_twins import (batch_pixels_torch, camera_rays_torch,
                                                pixel_targets_torch)
    from plenoctree.render._torch_impl import ray_basis_torch
    from plenoctree.render._triton_impl import prepare_rays
    from plenoctree.render.options import parse_data_format

    views = _views(scene) if cam == "pinhole" else _ndc_views(tmp_path)
    dv = DeviceViews(views, DEV)
    if cam == "ndc_clip":
        dv.cams = torch.from_numpy(_clip_cams(views.packed_cameras)).to(DEV)
    b = 1 if fmt == "RGBA" else int(fmt[2:])
    rng = np.random.default_rng(3)
    extra = None
    if fmt.startswith("SG"):
        mu = rng.normal(size=(b, 3))
        mu /= np.linalg.norm(mu, axis=1, keepdims=True)
        extra = np.c_[rng.uniform(0.5, 8.0, b), mu].astype(np.float32)
    info = parse_data_format(fmt, 4 if fmt == "RGBA" else 3 * b + 1, extra)
    opts = RenderOptions(sh_min=srange[0], sh_max=srange[1])
    off, inv = np.array([0.5, 0.45, 0.52]), np.array([0.21, 0.25, 0.19])
    k, n_tiles = 3, 19
    tiles = torch.from_numpy(rng.permutation(views.n_tiles(k))[:n_tiles]).to(DEV)
    n = n_tiles * k * k
    cap = max(n, dv.width * dv.height) + 5
    geo = torch.full((cap, 14), -7.0, dtype=torch.float64, device=DEV)
    basis = torch.full((cap, b), -7.0, device=DEV)
    tgt = torch.full((cap, 3), -7.0, device=DEV)
    ext = None if extra is None else torch.from_numpy(extra).to(DEV)
    assert batch_rays(tiles, n_tiles, 0, k, dv, geometry_tensor(off, inv, opts.step_eps, DEV),
                      info, ext, opts.basis_range(b), (geo, basis, tgt)) == n
    assert (geo[n:] == -7).all() and (basis[n:] == -7).all()        # nothing past n written
    img, u, v, outside = batch_pixels_torch(tiles, k, dv.width, dv.height)
    o, d = camera_rays_torch(dv.cams, img, u, v)
    ref_geo, unit = prepare_rays(off, inv, o, d, opts.step_eps)
    ref_basis = ray_basis_torch(info, unit, ext, opts).to(torch.float32)
    inside = ~outside
    assert outside.any() and inside.any()
    # (a GPU may fuse the camera's multiply-adds: a float32 ray one ulp apart, rarely)
    tol = 1e-6 if ON_GPU else 1e-12
    torch.testing.assert_close(geo[:n][inside, :12], ref_geo[inside, :12], rtol=tol, atol=tol)
    assert (geo[:n, COL_OUTSIDE] == outside.double()).all()
    assert (geo[:n][outside, 9] >= geo[:n][outside, 10]).all()      # past the border: a miss
    torch.testing.assert_close(basis[:n][inside], ref_basis[inside], rtol=3e-7, atol=3e-7)
    lo, hi = opts.basis_range(b)
    assert (basis[:n, :lo] == 0).all() and (basis[:n, hi + 1:] == 0).all()
    torch.testing.assert_close(tgt[:n][inside],
                               pixel_targets_torch(dv.images, dv.unit_value, img, u, v)[inside],
                               rtol=0, atol=0)
    # contiguous pixels (k = 1, no tile list): a whole view's rays, as validation makes them
    hw = dv.width * dv.height
    batch_rays(None, hw, hw, 1, dv, geometry_tensor(off, inv, opts.step_eps, DEV), info, ext,
               opts.basis_range(b), (geo[:hw], basis[:hw], tgt[:hw]))
    o1, d1 = views.view_rays(1)
    ref1, _ = prepare_rays(off, inv, torch.from_numpy(o1).to(DEV), torch.from_numpy(d1).to(DEV),
                           opts.step_eps)
    if cam == "pinhole":
        torch.testing.assert_close(geo[:hw, :12], ref1[:, :12], rtol=1e-6, atol=1e-6)
    # (ViewSet.image scales in float32, pixel_rays in float64: one float32 ulp apart at most)
    torch.testing.assert_close(tgt[:hw].cpu(), torch.from_numpy(views.image(1).reshape(-1, 3)),
                               rtol=0, atol=6e-8)


@pytest.mark.parametrize("optimizer", ["sgd", "adam", "rmsprop"])
def test_update_and_loss_kernels_match_their_twins(triton_cpu, optimizer):
    """The lazy optimiser kernel updates the rows with a gradient (a NaN one counts, and is
    reported as non-finite) and leaves the others alone, values and moments; it zeroes the
    gradient rows it read. The loss kernel adds the squared error of the rays inside the
    images and writes ``dL/dC``."""
    from plenoctree.optim._device_kernels import loss, update
    from plenoctree.optim._device_twins import OPT_CODES, loss_torch, update_torch

    gen = torch.Generator().manual_seed(0)
    n, d = 300, 13
    p = (torch.randn(n, d, generator=gen)).to(DEV)
    g = (torch.randn(n, d, generator=gen) * 1e-3).to(DEV)
    g[torch.rand(n, generator=gen).to(DEV) < 0.5] = 0.0
    g[7, 2] = float("nan")
    m1 = (torch.rand(n, d, generator=gen) * 1e-3).to(DEV)
    m2 = (torch.rand(n, d, generator=gen) * 1e-6).to(DEV)
    hyper = (0.9, 0.999, 1 - 0.9 ** 3, 1 - 0.999 ** 3, 1e-8) if optimizer == "adam" else \
        (0.0, 0.99, 1.0, 1.0, 1e-8)
    out = {}
    for name, fn in (("kernel", update), ("twin", update_torch)):
        pp, gg, a, b = p.clone(), g.clone(), m1.clone(), m2.clone()
        figs = torch.zeros(3, 4, dtype=torch.float64, device=DEV)
        fn(pp, gg, a, b, OPT_CODES[optimizer], 0.3, 2.0, hyper, figs, 1)
        out[name] = (pp, gg, a, b, figs)
    (pk, gk, ak, bk, fk), (pt, _, at, bt, ft) = out["kernel"], out["twin"]
    touched = (g != 0).any(dim=1)
    assert 0 < int(touched.sum()) < n
    torch.testing.assert_close(pk, pt, rtol=1e-6, atol=1e-7, equal_nan=True)
    assert (pk[~touched] == p[~touched]).all() and (pk[:, -1][touched & ~pk[:, -1].isnan()] >= 0).all()
    if optimizer != "sgd":
        torch.testing.assert_close(bk, bt, rtol=1e-6, atol=0, equal_nan=True)
        assert (bk[~touched] == m2[~touched]).all()
    if optimizer == "adam":
        torch.testing.assert_close(ak, at, rtol=1e-6, atol=0, equal_nan=True)
    assert (gk[touched] == 0).all() and (gk[~touched] == 0).all()   # ready for the next step
    assert fk[1, 2] == ft[1, 2] == int((~torch.isfinite(pt[touched])).sum()) >= 1
    assert fk[1, 3] == ft[1, 3] == int(touched.sum()) and (fk[0] == 0).all()
    # the loss
    rgb, tgt = torch.rand(50, 3, generator=gen).to(DEV), torch.rand(50, 3, generator=gen).to(DEV)
    geo = torch.zeros(50, 14, dtype=torch.float64, device=DEV)
    geo[::7, 12] = 1.0                                        # past the border
    figs_k = torch.zeros(2, 4, dtype=torch.float64, device=DEV)
    figs_t = figs_k.clone()
    grad = torch.full((50, 3), 9.0, device=DEV)
    loss(rgb, tgt, geo, 50, 0.25, figs_k, 1, grad)
    sse, grad_t = loss_torch(rgb, tgt, geo[:, 12] > 0, 0.25, figs_t, 1)
    torch.testing.assert_close(figs_k, figs_t, rtol=1e-12, atol=0)
    assert figs_k[1, 1] == 50 - 8 and (grad[::7] == 0).all()
    torch.testing.assert_close(grad, grad_t, rtol=0, atol=0)


# ----------------------------------------------------------------------------- the step
def _loop(stepper, views, batch, val=None, **kw):
    from plenoctree._util import progress

    loop = FineTuneLoop(stepper, views, val, LoopOptions(epochs=kw.pop("epochs", 1),
                                                         batch_rays=batch, **kw), {})
    loop._bar = progress(total=1, disable=True)
    return loop


def test_device_step_reads_nothing_back_and_uploads_nothing(scene, triton_cpu, recorder):
    """A fine-tuning step on the CUDA path (Triton kernels; here CPU tensors in Triton's
    interpreter) is five kernel launches and one view, the same at every batch size: no value
    read back, no data-dependent shape, no upload. The figures are read every ``read_every``
    steps (one read back); validation reads back once and uploads its photos once."""
    tree = load_tree(scene / "noisy.npz")
    views, val = _views(scene), _views(scene, "val")
    counts = []
    for batch in (64, 256):
        loop = _loop(_stepper("triton", tree), views, batch)
        order = loop.tile_order()
        k = loop.tiles_per_batch
        loop.step(order[:k], 1)                                     # buffers allocated
        for i in (1, 2):
            with recorder.region() as c:
                loop.step(order[i * k:(i + 1) * k], 1)
            counts.append(c)
        with recorder.region() as r:
            sse = loop.read_figures(1)
        assert sse > 0 and loop.state.train_rays > 0
        assert sum(r.syncs.values()) == r.syncs["host"] == 1, dict(r.sites)
    for c in counts:
        assert sum(c.syncs.values()) == 0, dict(c.sites)            # no item/shape/host/upload
        assert c.triton == 5 and c.ops + c.triton <= 20, (c.ops, dict(c.by_op))
    assert len({(c.ops, c.triton) for c in counts}) == 1            # whatever the batch size
    st = loop.stepper
    st.views_psnr(val, keep=True)                                   # uploads val's photos
    with recorder.region() as v:
        p = st.views_psnr(val, keep=True)
    assert math.isfinite(p) and v.syncs["upload"] == 0 and v.syncs["host"] == 1, dict(v.sites)
    assert sum(v.syncs.values()) == 1


def test_device_loop_matches_the_torch_twin_loop(scene, triton_cpu):
    """Two epochs on the Triton path and on the torch twin: the same tile orders, values and
    validation PSNR (to float32 rounding); every training pixel counted once an epoch."""
    from plenoctree.optim._views import render_views_psnr

    tree = load_tree(scene / "noisy.npz")
    views, val = _views(scene), _views(scene, "val")
    res = {}
    for backend in ("triton", "torch"):
        st = _stepper(backend, tree)
        loop = FineTuneLoop(st, views, None, LoopOptions(epochs=2, batch_rays=256, read_every=2,
                                                         show_progress=False), {})
        values, state = loop.run()
        res[backend] = (values.copy(), state, render_views_psnr(st, val))
    (vk, sk, pk), (vt, stt, pt) = res["triton"], res["torch"]
    assert sk.train_rays == stt.train_rays == 2 * views.n_rays and sk.steps == stt.steps
    moved = np.abs(vt - tree.data.reshape(vt.shape)).max()
    assert moved > 1e-3
    np.testing.assert_allclose(vk, vt, rtol=2e-5, atol=1e-4 * moved)   # Adam: lr/eps · rounding
    assert pk == pytest.approx(pt, abs=1e-4)


# ----------------------------------------------------------------------------- the loop
def _cfg(scene, out, **kw):
    from plenoctree.optim.finetuning import FinetuneConfig

    base = dict(tree=scene / "noisy.npz", data=scene / "data", out=out, epochs=4,
                batch_rays=128, ray_tile=2, val_every=2, backend="torch", device="cpu",
                optimizer="adam", lr=5e-2, test_views=-1, verbose=False, show_progress=False)
    base.update(kw)
    return FinetuneConfig(**base)


def test_device_loop_keeps_the_best_on_the_device_and_resumes(scene, tmp_path):
    """A device stepper keeps the best values on the device (no host copy per store); the
    checkpoint writes them to the best values' file, and a resumed run ends where an
    uninterrupted one does."""
    import logging

    from plenoctree.optim import _loop as loop_mod
    from plenoctree.optim._best import DeviceBestValues
    from plenoctree.optim.finetuning import finetune

    kw = dict(continue_on_decrease=True)
    made = []
    orig = loop_mod.FineTuneLoop._new_best

    def spy(self, stem):
        best = orig(self, stem)
        made.append(best)
        return best

    loop_mod.FineTuneLoop._new_best = spy
    try:
        ref = finetune(_cfg(scene, tmp_path / "a.npz", **kw))
        assert isinstance(made[-1], DeviceBestValues)

        class Stop(logging.Handler):
            def emit(self, record):
                if record.getMessage().strip().startswith("epoch   3: train"):
                    raise KeyboardInterrupt

        logger = logging.getLogger("plenoctree")
        handler, level = Stop(), logger.level
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        try:
            with pytest.raises(KeyboardInterrupt):
                finetune(_cfg(scene, tmp_path / "b.npz", verbose=True, **kw))
        finally:
            logger.removeHandler(handler)
            logger.setLevel(level)
        assert list(tmp_path.glob("b.ckpt.best-*.f32"))       # pinned: written for the checkpoint
        res = finetune(_cfg(scene, tmp_path / "b.npz", resume=True, **kw))
    finally:
        loop_mod.FineTuneLoop._new_best = orig
    assert res.epochs_run == ref.epochs_run == 4 and res.best_epoch == ref.best_epoch
    np.testing.assert_allclose(load_tree(tmp_path / "b.npz").data,
                               load_tree(tmp_path / "a.npz").data, rtol=1e-5, atol=1e-5)


def test_device_divergence_is_caught_at_the_read_and_backs_off(scene):
    """A diverging rate is seen when the figures are read (every ``read_every`` steps), step by
    step as the host path sees it: the best values come back from the device copy, and the
    optimiser moments are cleared of non-finite values."""
    tree = procedural_tree(16)
    d0 = tree.data.reshape(-1, tree.data_dim)
    for backoffs in (0, 1):
        seen = []
        loop = FineTuneLoop(_stepper("torch", tree, "sgd", 1e20), _views(scene), None,
                            LoopOptions(epochs=2, batch_rays=128, ray_tile=2, read_every=4,
                                        backoffs=backoffs, show_progress=False), {})
        loop.events = seen.append
        values, state = loop.run()
        assert state.backoffs == backoffs
        if backoffs == 0:       # stopped, the initial values kept
            assert state.stop_reason.startswith("diverged: training MSE rose"), state.stop_reason
            assert "(epoch 1, step " in state.stop_reason
            np.testing.assert_array_equal(values, d0)
        else:                   # backed off from the device copy and went on
            (off,) = [e for e in seen if e["event"] == "backoff"]
            assert off["reason"].startswith("diverged") and off["epoch"] == 1
    # restoring values clears the moments a diverged step left non-finite, and only those
    st = _stepper("torch", load_tree(scene / "noisy.npz"), "adam", 1e-2)
    good = st.values().copy()
    st.m1[3, 1], st.m2[4, 0], st.m2[5, 2] = float("nan"), float("inf"), 0.5
    st.set_values(torch.from_numpy(good).to(DEV))
    assert torch.isfinite(st.m1).all() and torch.isfinite(st.m2).all()
    assert st.m1[3, 1] == 0 and st.m2[4, 0] == 0 and st.m2[5, 2] == 0.5


# ----------------------------------------------------------------------------- the CPU path
def test_numba_loop_steps_as_before(scene):
    """The loop feeds the numba stepper exactly as before the device path: a numpy permutation
    of the tiles an epoch from the loop's generator, each step's rays made on the CPU; the
    values equal, bit for bit, a replay of that algorithm."""
    tree = load_tree(scene / "noisy.npz")
    views = _views(scene)
    loop_st, replay_st = _stepper("numba", tree), _stepper("numba", tree)
    FineTuneLoop(loop_st, views, None, LoopOptions(epochs=2, batch_rays=64, ray_tile=2, seed=5,
                                                   show_progress=False), {}).run()
    rng = np.random.default_rng(5)
    scale = 1.0 / (3.0 * views.width * views.height)
    per = 64 // 4
    for _ in range(2):
        perm = rng.permutation(views.n_tiles(2))
        for b0 in range(0, len(perm), per):
            replay_st.step(*views.rays(views.tile_pixels(perm[b0:b0 + per], 2)), scale)
    np.testing.assert_array_equal(loop_st.values(), replay_st.values())


def test_numba_fine_tuning_values_are_pinned(tmp_path):
    """A seeded numba fine-tuning run (one numba thread: the gradient slabs follow the thread
    count) gives the values it gave before the device loop (b959ca9, the commit before it), to
    the rounding in which machines differ: the fine-tuning kernels' fast-math sums are
    vectorised by the CPU's instruction set and by what numba's cache held when they were
    compiled (an AMD EPYC and an AVX-512 Xeon, fresh or warm cache: values within 7.6e-6,
    three different SHA-256 digests). Pinned are the non-zero count, the sum of |values| and
    four fixed random projections (magnitudes 200-4,800; rounding moves them by ~2e-5, a
    value wrong by 1e-3 moves them by that much). A deliberate change of the kernels'
    numerics changes them: re-pin then and say why in the commit."""
    import numba

    from plenoctree.optim.finetuning import FinetuneConfig, finetune

    write_procedural_dataset(tmp_path / "data", n_train=4, n_val=1, n_test=1, width=20,
                             height=18)
    t = procedural_tree(16)
    noise = np.random.default_rng(0).normal(scale=0.3, size=t.data.shape).astype(np.float32)
    save_tree(dataclasses.replace(t, data=(t.data + noise * (t.data != 0)).astype(np.float32)),
              tmp_path / "tree.npz", precision="fp32")
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        res = finetune(FinetuneConfig(
            tree=tmp_path / "tree.npz", data=tmp_path / "data", out=tmp_path / "ft.npz",
            epochs=3, batch_rays=96, ray_tile=2, val_every=0, backend="numba", device="cpu",
            seed=3, lr=5e-2, test_views=-1, precision="fp32", continue_on_decrease=True,
            show_progress=False, verbose=False))
    finally:
        numba.set_num_threads(threads)
    v = load_tree(tmp_path / "ft.npz").data.astype(np.float64).ravel()
    assert res.steps == 45 and res.best_epoch == 3
    w = np.random.default_rng(7).standard_normal((4, v.size))
    assert int((v != 0).sum()) == 14836
    np.testing.assert_allclose(np.abs(v).sum(), 42814.71766, rtol=0, atol=2e-3)
    np.testing.assert_allclose(w @ v, [-234.936007, -4791.168428, -2055.04467, -3511.149099],
                               rtol=0, atol=2e-3)


def test_photos_too_large_for_the_device_train_on_host_batches(scene, monkeypatch):
    """A device stepper whose device cannot hold the photos falls back to host batches (its
    step API: rays made on the CPU and uploaded each step), and still trains."""
    from plenoctree.optim._device_stepper import TorchStepper

    monkeypatch.setattr(TorchStepper, "fits", lambda self, nbytes: False)
    tree = load_tree(scene / "noisy.npz")
    st = _stepper("torch", tree)
    loop = FineTuneLoop(st, _views(scene), None, LoopOptions(epochs=1, batch_rays=256,
                                                             show_progress=False), {})
    assert loop._dev is None and not st._views
    values, state = loop.run()
    assert state.train_rays == _views(scene).n_rays and not np.array_equal(
        values, tree.data.reshape(values.shape))
