"""``plenoctree extract``: CLI smoke test on a tiny (untrained) run, help text, bad runs."""

from __future__ import annotations

import dataclasses
import json

import pytest
from nerf_fixtures import tiny_run

from plenoctree.cli import main
from plenoctree.convert import ExtractConfig
from plenoctree.nerf.config import field_docs
from plenoctree.octree import load_tree


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    _, run = tiny_run(tmp_path_factory.mktemp("cli"), val_log=[{"step": 0, "psnr": 11.5}])
    return run


def test_extract_cli_end_to_end(run_dir, tmp_path, capsys):
    out = tmp_path / "tree.npz"
    rc = main(["extract", str(run_dir), "--out", str(out), "--grid", "16", "--samples", "2",
               "--bbox-grid", "16", "--alpha-thresh", "0.01", "--eval-views", "1",
               "--precision", "fp16", "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0
    for stage in ("load", "bbox", "grid", "filter", "sample", "build", "save", "eval", "total"):
        assert stage in text
    assert "leaves" in text and "MB" in text and "test PSNR" in text
    assert "NeRF-SH validation PSNR 11.50" in text
    tree = load_tree(out)
    info = json.loads((tmp_path / "tree.extract.json").read_text())
    assert info["n_leaves"] == tree.n_leaves and info["eval_views"] == 1
    assert info["box"]["source"] == "auto" and info["config"]["grid"] == 16


def test_extract_cli_default_output_in_run_dir(run_dir, capsys):
    rc = main(["extract", str(run_dir), "--grid", "8", "--samples", "1", "--bbox", "fixed",
               "--masking", "sigma", "--mask-alpha-thresh", "0", "--no-eval"])
    assert rc == 0
    assert (run_dir / "tree.npz").is_file() and (run_dir / "tree.extract.json").is_file()
    assert "test PSNR" not in capsys.readouterr().out


def test_extract_cli_bad_run_dir(tmp_path, capsys):
    assert main(["extract", str(tmp_path / "nothing")]) == 1
    err = capsys.readouterr().err
    assert "checkpoint" in err and "plenoctree train" in err and "Traceback" not in err


def test_extract_cli_empty_box(run_dir, capsys):
    rc = main(["extract", str(run_dir), "--grid", "8", "--bbox-grid", "8", "--alpha-thresh",
               "0.9", "--no-eval"])
    assert rc == 1
    assert "--alpha-thresh" in capsys.readouterr().err


def test_every_option_is_documented(capsys):
    docs = field_docs(ExtractConfig)
    names = [f.name for f in dataclasses.fields(ExtractConfig)]
    assert set(names) <= set(docs), set(names) - set(docs)
    with pytest.raises(SystemExit):
        main(["extract", "--help"])
    text = capsys.readouterr().out
    for n in names:
        if n not in ("run_dir", "show_progress"):
            assert "--" + n.replace("_", "-") in text
