"""Result pictures: Turbo depth / error maps, eval images + raw depth, fine-tuning curve, stage plot."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from plenoctree.plots import (ERROR_VMAX, comparison_image, depth_colormap, error_map,
                              plot_finetune_curve, plot_stages, read_finetune_log, turbo)


def test_turbo_matches_matplotlib_table():
    matplotlib = pytest.importorskip("matplotlib")
    x = np.linspace(0, 1, 256)
    ref = matplotlib.colormaps["turbo"](x)[:, :3]
    assert np.abs(turbo(x) - ref).max() < 3.5 / 255
    assert turbo(np.array([-1.0, 2.0, np.nan])).shape == (3, 3)
    np.testing.assert_allclose(turbo(-1.0), turbo(0.0))


def test_depth_colormap_near_red_far_blue_empty_background():
    depth = np.array([[2.0, 6.0, 4.0]])
    alpha = np.array([[1.0, 1.0, 0.0]])
    img = depth_colormap(depth, alpha, near=2.0, far=6.0, background=(1, 1, 1))
    near, far, empty = img[0]
    assert near[0] > 0.4 and near[2] < 0.05          # dark red
    assert far[2] > 0.2 and far[0] < 0.25            # dark blue
    np.testing.assert_array_equal(empty, [1, 1, 1])


def test_error_map_and_comparison():
    gt = np.zeros((4, 5, 3), np.float32)
    pred = gt.copy()
    pred[0, 0] = ERROR_VMAX                           # mean |d| = vmax -> top of the map
    e = error_map(pred, gt)
    np.testing.assert_allclose(e[0, 0], turbo(1.0), atol=1e-6)
    np.testing.assert_allclose(e[1, 1], turbo(0.0), atol=1e-6)
    c = comparison_image(gt, pred, gap=2)
    assert c.shape == (4, 5 * 3 + 4, 3)
    np.testing.assert_array_equal(c[:, :5], gt)
    np.testing.assert_array_equal(c[:, 7:12], pred)
    np.testing.assert_array_equal(c[:, 14:], e)


def test_render_writes_depth_npy_colour_depth_and_comparison(tmp_path):
    from plenoctree.datasets import load_dataset
    from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
    from plenoctree.evaluation import evaluate_tree
    from plenoctree.render import render_image

    write_procedural_dataset(tmp_path / "data", n_train=1, n_val=1, n_test=2, width=16,
                             height=16)
    data = load_dataset(tmp_path / "data", "test")
    tree = procedural_tree(32)
    evaluate_tree(tree, data, tmp_path / "out", show_progress=False)
    name = data.names[0]
    ref = render_image(tree, data.cameras, 0)
    depth = np.load(tmp_path / "out" / f"{name}_depth.npy")
    alpha = np.load(tmp_path / "out" / f"{name}_alpha.npy")
    assert depth.dtype == np.float32 and depth.shape == (16, 16)
    np.testing.assert_allclose(depth, ref.depth.numpy(), rtol=1e-6)
    np.testing.assert_allclose(alpha, ref.alpha.numpy(), rtol=1e-6)
    png = np.asarray(Image.open(tmp_path / "out" / f"{name}_depth.png"))
    assert png.shape == (16, 16, 3)
    want = depth_colormap(depth, alpha, data.near, data.far, (1, 1, 1))
    assert np.abs(png.astype(float) - want * 255).max() <= 1.0
    cmp = np.asarray(Image.open(tmp_path / "out" / f"{name}_compare.png"))
    assert cmp.shape == (16, 16 * 3 + 4, 3)
    gt8 = (np.clip(data.images[0], 0, 1) * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(cmp[:, :16], gt8)


def _write_log(path, epochs=(1, 2, 3), val=(0, 2, 3)):
    lines = [{"event": "start"}]
    lines += [{"event": "val", "epoch": 0, "val_psnr": 20.0}] if 0 in val else []
    for e in epochs:
        lines.append({"event": "epoch", "epoch": e, "train_psnr": 20.0 + e})
        if e in val:
            lines.append({"event": "val", "epoch": e, "val_psnr": 20.5 + e - (e == 3) * 2})
    path.write_text("\n".join(json.dumps(r) for r in lines) + "\n{trunc")


def test_finetune_curve_from_log(tmp_path):
    pytest.importorskip("matplotlib")
    log = tmp_path / "ft.log.jsonl"
    _write_log(log)
    curve = read_finetune_log(log)
    assert curve["train"] == [(1, 21.0), (2, 22.0), (3, 23.0)]
    assert curve["val"] == [(0, 20.0), (2, 22.5), (3, 21.5)]
    assert plot_finetune_curve(log, tmp_path / "c.png")
    im = Image.open(tmp_path / "c.png")
    assert im.size[0] > 300 and im.size[1] > 200
    empty = tmp_path / "e.log.jsonl"
    empty.write_text('{"event": "start"}\n')
    assert not plot_finetune_curve(empty, tmp_path / "e.png")
    assert not (tmp_path / "e.png").exists()


def test_finetune_writes_its_curve(tmp_path):
    pytest.importorskip("matplotlib")
    from test_optim_finetune import known_tree, perturbed, write_dataset

    from plenoctree.octree import save_tree
    from plenoctree.optim.finetune import FinetuneConfig, finetune

    tree = known_tree()
    write_dataset(tree, tmp_path / "data", n_train=8, n_val=2, n_test=2)
    save_tree(perturbed(tree), tmp_path / "noisy.npz")
    finetune(FinetuneConfig(tree=tmp_path / "noisy.npz", data=tmp_path / "data",
                            out=tmp_path / "ft.npz", epochs=2, val_every=1, batch_rays=2048,
                            lr=0.05, optimizer="adam", verbose=False, show_progress=False))
    assert Image.open(tmp_path / "ft.curve.png").size[0] > 300
    assert len(read_finetune_log(tmp_path / "ft.log.jsonl")["val"]) == 3   # epochs 0, 1, 2


def test_stage_plot(tmp_path):
    pytest.importorskip("matplotlib")
    rows = [{"stage": "NeRF-SH", "psnr": 30.0, "fps": 0.5, "mb": 25.0},
            {"stage": "PlenOctree", "psnr": 31.0, "fps": 3.0, "mb": 600.0},
            {"stage": "compressed", "psnr": 30.9, "fps": 4.0, "mb": None},
            {"stage": "broken", "psnr": None, "fps": 1.0, "mb": 1.0}]
    assert plot_stages(rows, tmp_path / "s.png")
    assert Image.open(tmp_path / "s.png").size[0] > 600
    assert not plot_stages([{"stage": "x", "psnr": None, "fps": None, "mb": None}],
                           tmp_path / "n.png")
    assert not (tmp_path / "n.png").exists()


def test_cli_plot_summary_and_log(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    from plenoctree.cli import main

    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps({"rows": [{"stage": "a", "psnr": 30, "fps": 2, "mb": 10},
                                            {"stage": "b", "psnr": 31, "fps": 3, "mb": 5}]}))
    assert main(["plot", str(summary)]) == 0
    assert (tmp_path / "stages.png").exists() and "stage plot" in capsys.readouterr().out
    log = tmp_path / "ft.log.jsonl"
    _write_log(log)
    assert main(["plot", str(log), "--title", "t"]) == 0
    assert (tmp_path / "ft.curve.png").exists()
    bad = tmp_path / "bad.json"
    bad.write_text('{"rows": 3}')
    assert main(["plot", str(bad)]) == 1
    assert "summary.json" in capsys.readouterr().err
    empty = tmp_path / "empty.json"
    empty.write_text("[]")
    assert main(["plot", str(empty)]) == 1
    assert "nothing to plot" in capsys.readouterr().err
    assert main(["plot", str(tmp_path / "missing.json")]) == 1


def test_cli_eval_save_images_writes_comparison_and_raw_depth(tmp_path):
    from plenoctree.cli import main
    from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
    from plenoctree.octree import save_tree

    write_procedural_dataset(tmp_path / "data", n_train=1, n_val=1, n_test=2, width=16, height=16)
    save_tree(procedural_tree(16), tmp_path / "t.npz")
    out = tmp_path / "ev"
    assert main(["eval", str(tmp_path / "t.npz"), "--data", str(tmp_path / "data"),
                 "--save-images", "--views", "1", "--out", str(out)]) == 0
    names = sorted(p.name for p in (out / "renders").iterdir())
    assert any(n.endswith("_compare.png") for n in names), names
    assert any(n.endswith("_depth.npy") for n in names) and any(n.endswith("_depth.png") for n in names)
    assert any(n.endswith("_alpha.npy") for n in names)


def test_stage_plot_reads_paper_table_json(tmp_path, capsys):
    """`plenoctree plot paper_table.json` (the stage plot of docs/results.md): every row of
    benchmarks/paper_table.py, FPS at the table's size, unmeasured rows left out."""
    import importlib.util
    import json
    from pathlib import Path

    from plenoctree.cli import main
    from plenoctree.plots import PAPER_TABLE_STAGES, stage_rows

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "paper_table.py"
    spec = importlib.util.spec_from_file_location("paper_table_for_plot", path)
    pt = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(pt)
    assert [k for k, _ in PAPER_TABLE_STAGES] == [k for k, _ in pt.ROWS]   # same rows
    rows = {k: {"psnr": 30.0 + i, "ssim": 0.9, "fps_400": 2.0 + i, "fps_800": 0.5 + i,
                "mb": 10.0 * (i + 1)} for i, (k, _) in enumerate(pt.ROWS)}
    rows["refined"] = {"psnr": None, "fps_400": None, "fps_800": None, "mb": None}
    res = {"size": 800, "views": 40, "rows": rows}
    got, title = stage_rows(res)
    assert [r["stage"] for r in got] == [lbl for k, lbl in PAPER_TABLE_STAGES if k != "refined"]
    ft = next(r for r in got if r["stage"] == "fine-tuned")
    i = [k for k, _ in pt.ROWS].index("ft")
    assert ft == {"stage": "fine-tuned", "psnr": 30.0 + i, "fps": 0.5 + i, "mb": 10.0 * (i + 1)}
    assert "lego 800²" in title and "40 test views" in title
    (tmp_path / "paper_table.json").write_text(json.dumps(res))
    pytest.importorskip("matplotlib")
    out = tmp_path / "stages.png"
    assert main(["plot", str(tmp_path / "paper_table.json"), "--out", str(out)]) == 0
    assert Image.open(out).size[0] > 600
    (tmp_path / "bad.json").write_text(json.dumps({"rows": 3}))
    assert main(["plot", str(tmp_path / "bad.json")]) == 1
    assert "paper_table.json" in capsys.readouterr().err
