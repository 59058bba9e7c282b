"""Fine-tuning loop, CLI and bad input, on a known tree and datasets rendered from it."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from plenoctree.datasets.procedural import CAMERA_ANGLE_X, procedural_cameras, procedural_tree
from plenoctree.errors import ConfigError, TreeFormatError
from plenoctree.octree import load_tree, save_tree
from plenoctree.optim.finetuning import FinetuneConfig, finetune
from plenoctree.render import RenderOptions, render_rays

SIZE = 24


def known_tree():
    """The procedural scene at 16³, cut down to SH degree 1 (4 bases per channel)."""
    t = procedural_tree(16)
    d = t.data
    cols = [d[..., ch * 16: ch * 16 + 4] for ch in range(3)]
    t.data = np.ascontiguousarray(np.concatenate(cols + [d[..., -1:]], axis=-1))
    t.data_format = "SH4"
    t.check_integrity()
    return t


def write_dataset(tree, root: Path, n_train=40, n_val=4, n_test=4, splits=("train", "val", "test")):
    """A Blender-format dataset of ``tree``'s own renders (white background, alpha 1)."""
    from plenoctree._util import atomic_save_json, save_png
    from plenoctree.datasets import generate_rays

    fx = 0.5 * SIZE / math.tan(0.5 * CAMERA_ANGLE_X)
    counts = {"train": (n_train, "random", 0), "val": (n_val, "random", 1),
              "test": (n_test, "orbit", 0)}
    for split in splits:
        n, kind, seed = counts[split]
        frames = []
        for i, c2w in enumerate(procedural_cameras(n, kind, seed)):
            o, d = generate_rays(c2w, fx, fx, SIZE / 2, SIZE / 2, SIZE, SIZE)
            rgb = render_rays(tree, o, d, RenderOptions(), backend="numba").rgb.numpy()
            rgba = np.concatenate([rgb, np.ones((SIZE, SIZE, 1), np.float32)], -1)
            save_png(root / split / f"r_{i}.png", rgba)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        atomic_save_json(root / f"transforms_{split}.json",
                         {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames})
    return root


def perturbed(tree, seed=0, amount=1.5):
    t = tree.copy()
    rng = np.random.default_rng(seed)
    occ = (t.child == 0) & (t.data[..., -1] > 0)
    t.data[occ, :-1] += rng.normal(size=(int(occ.sum()), t.data_dim - 1)).astype(np.float32) * amount
    t.data[occ, -1] *= rng.uniform(0.5, 1.5, size=int(occ.sum())).astype(np.float32)
    return t


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("ft")
    tree = known_tree()
    write_dataset(tree, root / "data")
    save_tree(tree, root / "true.npz")
    save_tree(perturbed(tree), root / "noisy.npz")
    return root


class _Lines(logging.Handler):
    """Collects the ``plenoctree`` loggers' lines; ``hook(line)`` is called on each first."""

    def __init__(self, hook=None):
        super().__init__(logging.DEBUG)
        self.lines, self.hook = [], hook

    def emit(self, record):
        line = record.getMessage()
        if self.hook is not None:
            self.hook(line)
        self.lines.append(line)


@contextlib.contextmanager
def log_lines(hook=None):
    """The INFO lines the library logs inside the block (whatever the CLI configured)."""
    logger = logging.getLogger("plenoctree")
    handler, level = _Lines(hook), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield handler.lines
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def cfg(scene, out, **kw):
    base = dict(tree=scene / "noisy.npz", data=scene / "data", out=out, epochs=6,
                batch_rays=2048, val_every=2, verbose=False, show_progress=False)
    base.update(kw)
    return FinetuneConfig(**base)


@pytest.mark.parametrize("optimizer,lr", [("sgd", 2e4), ("adam", 0.1)])
def test_finetune_recovers_the_known_tree(scene, tmp_path, optimizer, lr):
    with log_lines() as lines:
        res = finetune(cfg(scene, tmp_path / "ft.npz", optimizer=optimizer, lr=lr))
    assert not any("PSNR" in line for line in lines)     # verbose=False: logged at DEBUG
    assert res.test_psnr_before < 26
    assert res.test_psnr_after > res.test_psnr_before + 8, res
    assert res.val_psnr_best > res.val_psnr_before + 8
    out = load_tree(tmp_path / "ft.npz")
    out.check_integrity()
    truth = load_tree(scene / "true.npz")
    np.testing.assert_array_equal(out.child, truth.child)
    # the log has one line per event and the checkpoint is gone after success
    events = [json.loads(line)["event"] for line in open(tmp_path / "ft.log.jsonl")]
    assert events[0] == "start" and events[-1] == "end" and "val" in events
    assert not (tmp_path / "ft.ckpt.npz").exists()
    assert not list(tmp_path.glob("*.best-*.f32"))      # nor the best values' files
    # Adam says how its steps related to its eps; SGD has nothing to say
    assert ("gradient_scale" in events) == (optimizer == "adam")
    if optimizer == "adam":
        assert 0.0 <= res.gradient_scale["share_below_eps"] <= 1.0
    else:
        assert res.gradient_scale is None


def test_val_and_test_views_are_the_evenly_spaced_ones_read_alone(scene, tmp_path, monkeypatch):
    """``val_views`` / ``test_views`` pick evenly spaced views, and only those are read."""
    import plenoctree.datasets.blender as blender
    from plenoctree.datasets import evenly_spaced, load_dataset

    read = []                                    # the image files each load decodes, in order
    real = blender.load_images

    def spy(paths, *a, **k):
        read.append([Path(p).stem for p in paths])
        return real(paths, *a, **k)

    monkeypatch.setattr(blender, "load_images", spy)
    with log_lines() as lines:
        finetune(cfg(scene, tmp_path / "ft.npz", epochs=1, val_every=1, val_views=2,
                     test_views=3, verbose=True))
    got = read[1:]                               # read[0]: the training split
    full = {s: load_dataset(scene / "data", s) for s in ("val", "test")}
    want = {s: [full[s].names[i] for i in evenly_spaced(len(full[s]), k)]
            for s, k in (("val", 2), ("test", 3))}
    assert got == [want["val"], want["test"]]
    assert any("/ 2 val views" in line for line in lines)
    assert any("(3 views)" in line for line in lines)


def test_gradient_scale_tells_the_sgd_regime_from_the_scale_free_one():
    """``gradient_scale`` compares each touched value's bias-corrected RMS gradient with ε."""
    from plenoctree.optim._steppers import _ADAM_EPS, _BETAS, NumbaStepper, gradient_scale
    from plenoctree.optim._render_grad import kernel_args

    tree = known_tree()
    d2 = tree.data.reshape(-1, tree.data_dim)
    st = NumbaStepper(d2.copy(), kernel_args(tree, RenderOptions()), "adam", 1e-2)
    st.step_count = 10
    bc = 1.0 - _BETAS[1] ** 10
    st.m2[:] = 0.0                               # untouched values do not count
    st.m2[:3] = (0.01 * _ADAM_EPS) ** 2 * bc     # 3 rows far below eps: the SGD regime
    st.m2[3:4] = (100 * _ADAM_EPS) ** 2 * bc     # 1 row far above: scale-free
    gs = gradient_scale(st)
    assert gs["values"] == 4 * tree.data_dim
    assert gs["share_below_eps"] == pytest.approx(0.75)
    assert gs["rms_p50"] == pytest.approx(0.01 * _ADAM_EPS, rel=1e-5)
    st.release()
    assert gradient_scale(st) is None


def test_torch_twin_backend_takes_the_same_steps(scene):
    from plenoctree.optim._render_grad import kernel_args
    from plenoctree.optim._loop import ViewSet
    from plenoctree.optim._steppers import NumbaStepper, TorchStepper, gradient_scale
    from plenoctree.datasets import load_dataset

    tree = load_tree(scene / "noisy.npz")
    views = ViewSet.from_dataset(load_dataset(scene / "data", "train"))
    opts = RenderOptions()
    d2 = tree.data.reshape(-1, tree.data_dim)
    for optimizer, lr, chunks, slr in (("sgd", 2e4, 3, None), ("adam", 1e-2, 1, None),
                                       ("adam", 1e-2, 3, None), ("rmsprop", 1e-3, 2, None),
                                       ("sgd", 2e4, 2, 6e4), ("adam", 1e-2, 3, 0.5),
                                       ("rmsprop", 1e-3, 1, 0.2)):
        fast = NumbaStepper(d2.copy(), kernel_args(tree, opts), optimizer, lr, n_chunks=chunks,
                            sigma_lr=slr)
        twin = TorchStepper(d2.copy(), tree, opts, optimizer, lr, device="cpu", sigma_lr=slr)
        rng = np.random.default_rng(1)
        for _ in range(3):
            o, d, t = views.rays(views.tile_pixels(rng.choice(views.n_tiles(2), 256, False), 2))
            s1, bad = fast.step(o, d, t, 1e-3)
            s2, _ = twin.step(o, d, t, 1e-3)
            assert s1 == pytest.approx(s2, rel=1e-4) and bad == 0
            # slabs, slots and lists are clean after every step; sig mirrors σ
            assert not fast.buf.grad3.any() and (fast.buf.slot == -1).all()
            assert not fast.buf.n_touched.any() and not fast.buf.need.any()
            np.testing.assert_array_equal(fast.sig, fast.values()[:, -1])
        moved = np.abs(fast.values() - d2).max()
        assert moved > 1e-3
        np.testing.assert_allclose(fast.values(), twin.values(), atol=2e-3 * moved)
        # both report the same gradient scale against their optimiser's eps (SGD: none)
        gs_fast, gs_twin = gradient_scale(fast), gradient_scale(twin)
        if optimizer == "sgd":
            assert gs_fast is None and gs_twin is None
        else:
            # (numba flushes moments below 1e-30 to 0: a few more values count as untouched)
            assert gs_fast["values"] == pytest.approx(gs_twin["values"], rel=0.01)
            assert gs_fast["values"] > 0
            assert gs_fast["rms_p50"] == pytest.approx(gs_twin["rms_p50"], rel=0.02)
            assert gs_fast["share_below_eps"] == pytest.approx(gs_twin["share_below_eps"],
                                                               abs=0.02)
        # after training the steppers drop their optimiser state, and still render the same
        before = fast.render(o, d)
        fast.release()
        twin.release()
        assert fast.buf is None and fast.m1 is None and fast.m2 is None
        assert twin.m1 is None and twin.data.grad is None
        np.testing.assert_array_equal(fast.render(o, d), before)


def test_edge_cases_do_not_crash(scene, tmp_path):
    """Rays that miss the tree or see only empty space, fully opaque rays and leaves no ray
    reaches, in one run."""
    tree = load_tree(scene / "noisy.npz")
    big = tree.copy()
    big.invradius = big.invradius * 0.45        # box ~2.2x larger: border rays are empty
    big.offset = np.full(3, 0.5)
    occ = (big.child == 0) & (big.data[..., -1] > 0)
    idx = np.argwhere(occ)[:40]
    big.data[tuple(idx.T) + (-1,)] = 1e5            # opaque cells
    save_tree(big, tmp_path / "big.npz")
    res = finetune(cfg(scene, tmp_path / "o.npz", tree=tmp_path / "big.npz", epochs=2,
                       optimizer="adam", lr=1e-2, test_views=-1))
    assert res.epochs_run >= 1 and math.isfinite(res.val_psnr_best)
    out = load_tree(tmp_path / "o.npz")
    assert np.isfinite(out.data).all() and (out.data[..., -1] >= 0).all()


def test_resume_continues_exactly(scene, tmp_path):
    kw = dict(epochs=4, optimizer="adam", lr=1e-2, continue_on_decrease=True, test_views=-1)
    ref = finetune(cfg(scene, tmp_path / "a.npz", **kw))

    def interrupt(line: str) -> None:
        if line.strip().startswith("epoch   3: train"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt), log_lines(interrupt):
        finetune(cfg(scene, tmp_path / "b.npz", verbose=True, **kw))
    assert (tmp_path / "b.ckpt.npz").exists() and not (tmp_path / "b.npz").exists()
    assert list(tmp_path.glob("b.ckpt.best-*.f32"))     # the checkpoint's best values
    res = finetune(cfg(scene, tmp_path / "b.npz", resume=True, **kw))
    assert res.epochs_run == ref.epochs_run == 4
    np.testing.assert_allclose(load_tree(tmp_path / "b.npz").data,
                               load_tree(tmp_path / "a.npz").data, rtol=1e-4, atol=1e-4)
    assert not (tmp_path / "b.ckpt.npz").exists() and not list(tmp_path.glob("b.ckpt.best-*"))
    # a checkpoint of another run is refused
    save_ck = tmp_path / "c.ckpt.npz"
    shutil.copy(tmp_path / "a.npz", save_ck)
    with pytest.raises(ConfigError, match="checkpoint"):
        finetune(cfg(scene, tmp_path / "c.npz", resume=True, **kw))
    # a checkpoint whose best values' file is gone is refused, naming the file
    with pytest.raises(KeyboardInterrupt), log_lines(interrupt):
        finetune(cfg(scene, tmp_path / "d.npz", verbose=True, **kw))
    (best_file,) = tmp_path.glob("d.ckpt.best-*.f32")
    best_values = best_file.read_bytes()
    best_file.unlink()
    with pytest.raises(ConfigError, match=r"d\.ckpt\.best-\d+\.f32.*missing"):
        finetune(cfg(scene, tmp_path / "d.npz", resume=True, **kw))
    # a checkpoint written before the on-disk best values (the array inside) still resumes
    with np.load(tmp_path / "d.ckpt.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "best_token"}
    arrays["best"] = np.frombuffer(best_values, np.float32).reshape(arrays["values"].shape)
    np.savez(tmp_path / "d.ckpt.npz", **arrays)
    finetune(cfg(scene, tmp_path / "d.npz", resume=True, **kw))
    np.testing.assert_allclose(load_tree(tmp_path / "d.npz").data,
                               load_tree(tmp_path / "a.npz").data, rtol=1e-4, atol=1e-4)


def test_validation_without_a_val_split_and_fp16_precision(scene, tmp_path):
    """Without a val split of its own, ``holdout_every=8`` holds every 8th training view out of
    the updates and validates on those; ``val_fraction`` holds a random share out instead;
    ``holdout_every=0`` trains on every view and validates on 8 of them (a divergence guard),
    as the automatic value does for a scene that is not a capture of a place."""
    data = tmp_path / "data"
    shutil.copytree(scene / "data", data)
    (data / "transforms_val.json").unlink()
    t = load_tree(scene / "noisy.npz")
    save_tree(t, tmp_path / "half.npz", precision="fp16")
    with log_lines() as lines:
        res = finetune(cfg(scene, tmp_path / "h.npz", tree=tmp_path / "half.npz", data=data,
                           epochs=2, optimizer="adam", lr=1e-2, test_views=2, verbose=True,
                           holdout_every=8))
    assert any("[35 train / 5 val views" in line for line in lines), lines[:2]
    assert res.held_out == [f"r_{i}" for i in (4, 12, 20, 28, 36)]
    assert len(res.history) >= 2                       # epoch 0 and epoch 2 validations
    with log_lines() as lines:
        finetune(cfg(scene, tmp_path / "n.npz", data=data, epochs=1, val_every=1,
                     holdout_every=0, test_views=-1, verbose=True))
    assert any("[40 train / 8 val views" in line for line in lines), lines[:2]
    with log_lines() as lines:
        finetune(cfg(scene, tmp_path / "a.npz", data=data, epochs=1, val_every=1,
                     test_views=-1, verbose=True))
    assert any("[40 train / 8 val views" in line for line in lines), lines[:2]
    with log_lines() as lines:
        finetune(cfg(scene, tmp_path / "p.npz", data=data, epochs=1, val_every=1,
                     val_fraction=0.2, test_views=-1, verbose=True))
    assert any("[32 train / 8 val views" in line for line in lines), lines[:2]
    for bad in (-0.1, 1.0):
        with pytest.raises(ConfigError, match="val_fraction"):
            finetune(cfg(scene, tmp_path / "x.npz", data=data, val_fraction=bad))
    assert load_tree(tmp_path / "h.npz", keep_dtype=True).data.dtype == np.float16
    finetune(cfg(scene, tmp_path / "f.npz", tree=tmp_path / "half.npz", epochs=0,
                 precision="fp32", test_views=-1))
    assert load_tree(tmp_path / "f.npz", keep_dtype=True).data.dtype == np.float32


def test_diverging_learning_rate_keeps_the_last_good_tree(scene, tmp_path):
    with pytest.raises(ConfigError, match="diverged.*last good"):
        finetune(cfg(scene, tmp_path / "d.npz", optimizer="sgd", lr=1e12, test_views=-1))
    kept = load_tree(tmp_path / "d.npz")
    np.testing.assert_array_equal(kept.data, load_tree(scene / "noisy.npz").data)


def test_bad_trees_and_boxes(scene, tmp_path):
    t = load_tree(scene / "noisy.npz")
    far = t.copy()
    far.offset = 0.5 - np.array([50.0, 50.0, 50.0]) * far.invradius
    save_tree(far, tmp_path / "far.npz")
    with pytest.raises(ConfigError, match="does not overlap"):
        finetune(cfg(scene, tmp_path / "x.npz", tree=tmp_path / "far.npz"))
    empty = t.copy()
    empty.data[...] = 0
    save_tree(empty, tmp_path / "empty.npz")
    with pytest.raises(ConfigError, match="no leaf has density"):
        finetune(cfg(scene, tmp_path / "x.npz", tree=tmp_path / "empty.npz"))
    # NaN in the leaf data: the loader names the file and the cell
    save_tree(t, tmp_path / "nan.npz")
    with np.load(tmp_path / "nan.npz") as z:
        arrays = {k: z[k] for k in z.files}
    leaf = np.argwhere(arrays["child"] == 0)[0]
    arrays["data"][tuple(leaf) + (0,)] = np.nan
    np.savez(tmp_path / "nan.npz", **arrays)
    with pytest.raises(TreeFormatError, match="nan.npz.*not finite"):
        finetune(cfg(scene, tmp_path / "x.npz", tree=tmp_path / "nan.npz"))
    with pytest.raises(ConfigError, match="optimizer"):
        finetune(cfg(scene, tmp_path / "x.npz", optimizer="lbfgs"))
    with pytest.raises(ConfigError, match="lr"):
        finetune(cfg(scene, tmp_path / "x.npz", lr=-1.0))
    assert not (tmp_path / "x.npz").exists()


def test_cli_prints_psnr_before_and_after(scene, tmp_path, capsys):
    from plenoctree.cli import main

    rc = main(["finetune", str(scene / "noisy.npz"), "--data", str(scene / "data"), "--out",
               str(tmp_path / "cli.npz"), "--epochs", "2", "--optimizer", "adam", "--lr", "0.02",
               "--batch-rays", "4096", "--quiet", "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "test PSNR before" in out and "after" in out
    before, after = [float(x) for x in
                     __import__("re").findall(r"([0-9.]+) dB", out.splitlines()[0])]
    assert after > before
    assert (tmp_path / "cli.npz").exists()
    rc = main(["finetune", str(scene / "noisy.npz"), "--data", str(tmp_path / "nope"),
               "--out", str(tmp_path / "cli2.npz")])
    assert rc == 1 and "error" in capsys.readouterr().err


def test_default_finetune_ends_at_or_above_its_start_on_the_procedural_scene(tmp_path):
    """The defaults (no lr, no optimizer given) on a tree extracted from the procedural NeRF-SH:
    validation and test PSNR end at or above the extracted tree's (validation strictly)."""
    from plenoctree.convert import AnalyticField, ExtractConfig, extract
    from plenoctree.datasets.procedural import write_procedural_dataset

    data = tmp_path / "data"
    write_procedural_dataset(data, n_train=12, n_val=2, n_test=2, width=32, height=32)
    extract(ExtractConfig(out=str(tmp_path / "t.npz"), data=str(data), grid=32, eval=False,
                          show_progress=False), field=AnalyticField())
    res = finetune(FinetuneConfig(tree=tmp_path / "t.npz", data=data, out=tmp_path / "ft.npz",
                                  epochs=4, batch_rays=1024, verbose=False,
                                  show_progress=False))    # 12 steps an epoch
    assert res.val_psnr_best > res.val_psnr_before and res.best_epoch > 0, res
    assert res.test_psnr_after >= res.test_psnr_before, res


def test_checkpoint_interval(scene, tmp_path, monkeypatch):
    """checkpoint_minutes 0 writes one at every validation; a long interval writes none until
    an interrupt (a large tree's checkpoint is gigabytes)."""
    import plenoctree.optim._loop as loop

    calls = []
    real = loop.save_checkpoint
    monkeypatch.setattr(loop, "save_checkpoint", lambda *a, **k: (calls.append(1), real(*a, **k)))
    kw = dict(epochs=4, val_every=1, optimizer="adam", lr=1e-2, continue_on_decrease=True,
              test_views=-1)
    finetune(cfg(scene, tmp_path / "a.npz", checkpoint_minutes=0, **kw))
    assert len(calls) == 3          # none after the last epoch: the tree is written at once
    calls.clear()
    finetune(cfg(scene, tmp_path / "b.npz", checkpoint_minutes=60, **kw))
    assert calls == []
    with pytest.raises(ConfigError, match="checkpoint_minutes"):
        finetune(cfg(scene, tmp_path / "c.npz", checkpoint_minutes=-1, **kw))


def test_a_time_limit_stops_after_the_epoch_that_leaves_too_little(scene, tmp_path):
    """``minutes``: the loop ends after the epoch past which another would end too late, and
    validates it as the last one (here the limit is gone at once: one epoch); a long limit
    changes nothing."""
    kw = dict(epochs=6, val_every=2, optimizer="adam", lr=0.1, test_views=-1)
    res = finetune(cfg(scene, tmp_path / "a.npz", minutes=1e-6, **kw))
    assert res.epochs_run == 1 and res.stop_reason.startswith("time limit")
    assert [h["epoch"] for h in res.history] == [0, 1]       # epoch 1 validated (val_every 2)
    assert res.best_epoch == 1 and res.val_psnr_best > res.val_psnr_before
    ref = finetune(cfg(scene, tmp_path / "ref.npz", **{**kw, "epochs": 1}))
    np.testing.assert_array_equal(load_tree(tmp_path / "a.npz").data,
                                  load_tree(tmp_path / "ref.npz").data)
    res = finetune(cfg(scene, tmp_path / "b.npz", minutes=60, **kw))
    assert res.epochs_run == 6 and res.stop_reason == "finished 6 epochs"
    for bad in (-1, float("inf"), 1e308):
        with pytest.raises(ConfigError, match="minutes"):
            finetune(cfg(scene, tmp_path / "c.npz", minutes=bad, **kw))


def test_the_last_epoch_keeps_its_values_without_a_copy(scene, tmp_path, monkeypatch):
    """After the last epoch better values stay the live ones, returned as they are: no copy
    of a tree-sized array (lego: 4.5 s) nor a checkpoint (16 s) just before the output."""
    import plenoctree.optim._best as best

    stores = []
    real = best.BestValues.store
    monkeypatch.setattr(best.BestValues, "store",
                        lambda self, v: (stores.append(1), real(self, v)))
    res = finetune(cfg(scene, tmp_path / "a.npz", epochs=1, val_every=1, optimizer="adam",
                       lr=0.1, test_views=-1))
    assert res.best_epoch == 1 and len(stores) == 1           # the input tree's copy only


def test_a_time_limit_cuts_a_later_epoch_short(scene, tmp_path, monkeypatch):
    """From the second epoch on the loop stops at the step past which the last validation
    would not fit (a clock that moves one second a step: 12 steps an epoch, 16 s)."""
    import types

    import plenoctree.optim._loop as loop
    import plenoctree.optim.finetuning as ft

    clock = types.SimpleNamespace(t=0.0)
    fake = types.SimpleNamespace(perf_counter=lambda: clock.t, time=lambda: clock.t)
    monkeypatch.setattr(loop, "time", fake)
    monkeypatch.setattr(ft, "time", fake)
    real = loop.FineTuneLoop.step

    def step(self, tiles, epoch):
        clock.t += 1.0
        return real(self, tiles, epoch)

    monkeypatch.setattr(loop.FineTuneLoop, "step", step)
    res = finetune(cfg(scene, tmp_path / "a.npz", minutes=(16 + ft.SAVE_S) / 60, epochs=6,
                       val_every=2, optimizer="adam", lr=0.1, test_views=-1))
    assert res.epochs_run == 2 and res.stop_reason == "time limit: stopped within epoch 2"
    assert res.steps == 16 and [h["epoch"] for h in res.history] == [0, 2]
