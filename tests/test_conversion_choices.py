"""benchmarks/conversion_choices.py on a tiny untrained NeRF-SH run (no lego needed)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "conversion_choices.py"


def test_rows_on_a_tiny_run(tmp_path, monkeypatch):
    from nerf_fixtures import tiny_run_and_tree

    from plenoctree.octree import load_tree

    data, _, tree = tiny_run_and_tree(tmp_path)
    spec = importlib.util.spec_from_file_location("conversion_choices", _PATH)
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.syspath_prepend(str(_PATH.parent))     # its sibling modules (_bench)
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
