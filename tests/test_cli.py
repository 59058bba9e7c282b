"""CLI smoke tests on a tiny procedural scene (16x16 images, 32^3 tree)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plenoctree.cli import main
from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
from plenoctree.octree import save_tree


def test_render_writes_pngs_and_metrics(tiny_scene, tmp_path, capsys):
    out = tmp_path / "r"
    rc = main(["render", str(tiny_scene / "tree.npz"), "--data", str(tiny_scene / "data"),
               "--split", "test", "--out", str(out), "--views", "2"])
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["views"]) == 2
    assert m["width"] == 16 and m["height"] == 16
    # A 32^3 tree of the analytic scene at 16^2 is close to the ground truth.
    assert m["mean"]["psnr"] > 18.0, m["mean"]  # an empty tree scores ~10 dB
    assert 0.6 < m["mean"]["ssim"] <= 1.0
    for v in m["views"]:
        assert (out / f"{v['name']}.png").exists() and (out / f"{v['name']}_depth.png").exists()
    assert "PSNR" in capsys.readouterr().out


def test_render_width_height_and_torch_backend(tiny_scene, tmp_path):
    out = tmp_path / "r"
    rc = main(["render", str(tiny_scene / "tree.npz"), "--data", str(tiny_scene / "data"),
               "--out", str(out), "--views", "1", "--width", "8", "--height", "8",
               "--backend", "torch", "--stop-thresh", "0", "--background", "black"])
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["width"] == 8 and m["backend"] == "torch"


@pytest.mark.parametrize("extra, needle", [
    (["--backend", "cuda-magic"], "backend"),
    (["--width", "8"], "--width and --height"),
    (["--background", "purple"], "--background"),
    (["--stop-thresh", "2"], "--stop-thresh"),
])
def test_render_bad_options_give_clear_errors(tiny_scene, tmp_path, capsys, extra, needle):
    rc = main(["render", str(tiny_scene / "tree.npz"), "--data", str(tiny_scene / "data"),
               "--out", str(tmp_path / "r"), "--views", "1", *extra])
    assert rc == 1
    assert needle in capsys.readouterr().err


def test_render_missing_tree_and_bad_data(tiny_scene, tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope.npz"), "--data", str(tiny_scene / "data")]) == 1
    assert "nope.npz" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["render", str(tiny_scene / "tree.npz"), "--data", str(tmp_path / "empty")]) == 1
    assert "empty" in capsys.readouterr().err
