"""benchmarks/conversion_choices.py on a tiny untrained NeRF-SH run (no lego needed)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "conversion_choices.py"


def test_rows_on_a_tiny_run(tmp_path):
    import torch

    from plenoctree.cli import main
    from plenoctree.datasets import procedural
    from plenoctree.nerf.checkpoint import save_checkpoint
    from plenoctree.nerf.config import ModelConfig, preset
    from plenoctree.nerf.model import NeRFModel
    from plenoctree.octree import load_tree

    data = procedural.write_procedural_dataset(tmp_path / "data", n_train=3, n_val=0, n_test=2,
                                               width=16, height=16, n_samples=64)
    cfg = preset("cpu")
    cfg.data, cfg.out, cfg.occ_res = str(data), str(tmp_path / "run"), 8
    cfg.model = ModelConfig(encoding="posenc", pe_freqs=2, net_depth=1, net_width=16)
    torch.manual_seed(0)
    model = NeRFModel(cfg.model, [[-1.5] * 3, [1.5] * 3], occ_res=cfg.occ_res)
    save_checkpoint(tmp_path / "run" / "checkpoint.pt", config=cfg, step=0, train_time_s=0.0,
                    wall_time_s=0.0, model=model, optimizer=None, rng=None, trainer={},
                    log={"train": [], "val": []})
    tree = tmp_path / "tree.npz"
    assert main(["extract", str(tmp_path / "run"), "--out", str(tree), "--grid", "16",
                 "--samples", "2", "--bbox", "fixed", "--masking", "sigma",
                 "--mask-alpha-thresh", "1e-12", "--no-eval", "--no-progress"]) == 0
    spec = importlib.util.spec_from_file_location("conversion_choices", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "cc.json"
    args = ["--run", str(tmp_path / "run"), "--tree", str(tree), "--data", str(data),
            "--views", "2", "--samples", "2", "--out", str(out)]
    assert mod.main(args + ["--refine", "t0-p1-opacity"]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert set(rows) == {"tree", "s2-mean", "s2-opacity", "refine-t0-p1-opacity"}
    n = load_tree(tree).n_leaves
    assert rows["tree"]["leaves"] == rows["s2-mean"]["leaves"] == n
    assert rows["refine-t0-p1-opacity"]["leaves"] > n
    assert all(np.isfinite(r["psnr"]) and r["views"] == 2 for r in rows.values())
    # a second call adds its rows to the file
    assert mod.main(args[:-4] + ["--samples", "4", "--averaging", "mean", "--out", str(out)]) == 0
    assert "s4-mean" in json.loads(out.read_text())["rows"] and len(
        json.loads(out.read_text())["rows"]) == 5
