"""benchmarks/paper_table.py: the table and plot functions on fake inputs (no lego needed)."""

from __future__ import annotations

import copy
import importlib.util
import json
from pathlib import Path

import pytest

from plenoctree.errors import ConfigError

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "paper_table.py"


@pytest.fixture(scope="module")
def pt():
    spec = importlib.util.spec_from_file_location("paper_table", _PATH)
    mod = importlib.util.module_from_spec(spec)
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(_PATH.parent))          # its sibling modules (_bench)
        spec.loader.exec_module(mod)
    return mod


def _fake(pt) -> dict:
    rows = {}
    for i, (key, _) in enumerate(pt.ROWS):
        rows[key] = {"psnr": 30.0 + 0.25 * i, "ssim": 0.95 + 0.001 * i,
                     "fps_400": 5.0 + i, "fps_800": 1.5 + i, "mb": 100.0 * (i + 1),
                     "stage_s": 10.0 * (i + 1), "stage_src": "read: fake"}
    rows["nerf_sh"].update(fps_400=1.0, fps_800=0.25)
    return {"views": 7, "rows": rows,
            "paper_nerf": {"fps_400": 1 / 250.0, "fps_800": 1 / 1000.0},
            "speedup": {"paper_nerf_400": 1750.0, "paper_nerf_800": 3500.0,
                        "cpu_nerf_400": 7.0, "cpu_nerf_800": 14.0}}


def test_table_has_every_row_and_paper_numbers(pt):
    md = pt.markdown_table(_fake(pt))
    lines = md.splitlines()
    for key, label in pt.ROWS:
        row = [ln for ln in lines if ln.startswith(f"| {label} |")]
        assert len(row) == 1, f"no table row for {key}"
    ft = next(ln for ln in lines if ln.startswith("| PlenOctree after fine-tuning |"))
    cells = [c.strip() for c in ft.strip("|").split("|")]
    i = [k for k, _ in pt.ROWS].index("ft")
    assert cells[1] == f"{30.0 + 0.25 * i:.2f}" and cells[4] == f"{5 + i}"
    assert cells[7] == f"{100.0 * (i + 1):.1f}"
    assert cells[8] == f"{10.0 * (i + 1) / 60:.1f} (read: fake)"        # minutes
    assert cells[10] == "32.95" and cells[12] == "186.8"     # paper lego, Table 5
    assert "| leaves |" in md and "| peak RSS MB |" in md
    nerf = next(ln for ln in lines if ln.startswith("| NeRF-SH (CPU preset"))
    assert "| 32.77 |" in nerf and "| 0.051 |" in nerf
    assert "| 1750× | 3500× |" in md and "| 7× | 14× |" in md
    assert "lego, 7 test views" in md


@pytest.mark.parametrize("drop", ["nerf_sh", "raw", "refined", "ft", "compressed", "sh1", "sh2"])
def test_missing_row_is_an_error(pt, drop):
    res = copy.deepcopy(_fake(pt))
    del res["rows"][drop]
    with pytest.raises(ConfigError, match=drop):
        pt.markdown_table(res)


def test_plot_writes_png_with_variants(pt, tmp_path):
    t3 = tmp_path / "extract_table3.json"
    t3.write_text(json.dumps({"rows": {
        "base": {"psnr": 30.7, "render": {"fps": 3.3}},
        "tau0.01": {"psnr": 30.9, "render": {"fps": 3.8}},
        "broken": {"psnr": None, "render": {}}}}))
    variants = pt.table3_variants(t3)
    assert variants == {"base": {"psnr": 30.7, "fps": 3.3}, "tau0.01": {"psnr": 30.9, "fps": 3.8}}
    assert pt.table3_variants(tmp_path / "missing.json") == {}
    out = tmp_path / "plot.png"
    pt.plot(_fake(pt), out, variants)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 5000


def test_read_stage_times(pt, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"train_time_s": 1800.5, "val_psnr": 34.3}))
    tree = tmp_path / "ex" / "tree.npz"
    tree.parent.mkdir()
    (tree.parent / "tree.extract.json").write_text(json.dumps(
        {"stages": {"load": {"seconds": 2.0}, "sample": {"seconds": 3.0},
                    "eval": {"seconds": 100.0}}, "test_psnr": 30.76}))
    ft = tmp_path / "ft" / "tree_ft.npz"
    ft.parent.mkdir()
    (ft.parent / "log.txt").write_text(
        "test PSNR after:  31.774 dB (best epoch 8)\n"
        "10 epochs (2450 steps), best epoch 8, 889.6 s, 0.26 M rays/s (numba)\n")
    got = pt.read_stage_times(run, tree, ft)
    assert got == {"train_s": 1800.5, "nerf_val_psnr": 34.3, "extract_s": 5.0,
                   "raw_psnr_all_views": 30.76, "finetune_s": 889.6,
                   "ft_psnr_all_views": 31.774}


def test_stage_rows_are_what_plenoctree_plot_reads(pt, tmp_path):
    import json

    from plenoctree.plots import plot_stages

    res = _fake(pt)
    res["rows"]["refined"]["psnr"] = None             # a row not run is left out
    rows = pt.stage_rows(res)
    assert [r["stage"] for r in rows] == [pt._SHORT[k] for k, _ in pt.ROWS if k != "refined"]
    ft = next(r for r in rows if r["stage"] == pt._SHORT["ft"])
    i = [k for k, _ in pt.ROWS].index("ft")
    assert ft["fps"] == 1.5 + i and ft["psnr"] == 30.0 + 0.25 * i
    json.dumps(rows)
    pytest.importorskip("matplotlib")
    assert plot_stages(rows, tmp_path / "s.png") and (tmp_path / "s.png").stat().st_size > 0


def test_read_run_dir_layout_and_errors(pt, tmp_path):
    """--run-dir: the artefacts of a finished `plenoctree run` folder, its own NeRF-SH or the
    one it was given, and a clear error naming the folder when the run is incomplete."""
    run = tmp_path / "chain"
    run.mkdir()
    with pytest.raises(ConfigError, match="no summary.json"):
        pt.read_run_dir(run)
    (run / "summary.json").write_text(json.dumps({"config": {"nerf": "", "downscale": 1}}))
    (run / "tree.npz").write_bytes(b"x")
    with pytest.raises(ConfigError, match="tree_ft.npz missing"):
        pt.read_run_dir(run)
    (run / "tree_ft.npz").write_bytes(b"x")
    nerf, tree, ref, ft, plnz, summary = pt.read_run_dir(run)
    assert (nerf, tree, ref, ft, plnz) == (run / "nerf", run / "tree.npz", None,
                                            run / "tree_ft.npz", None)
    assert summary["config"]["downscale"] == 1
    (run / "tree_refined.npz").write_bytes(b"x")
    (run / "tree_ft.plnz").write_bytes(b"x")
    given = tmp_path / "given"
    (run / "summary.json").write_text(json.dumps({"config": {"nerf": str(given)}}))
    with pytest.raises(ConfigError, match="checkpoint"):       # the run's --nerf is gone
        pt.read_run_dir(run)
    given.mkdir()
    (given / "checkpoint.pt").write_bytes(b"x")
    nerf, _, ref, _, plnz, _ = pt.read_run_dir(run)
    assert nerf == given and ref == run / "tree_refined.npz"
    assert plnz == run / "tree_ft.plnz"


def test_lpips_skip_note_is_not_a_number(pt):
    assert pt._number("skipped: lpips not installed") is None
    assert pt._number(float("nan")) is None and pt._number(0.25) == 0.25
    res = copy.deepcopy(_fake(pt))
    res["rows"]["ft"]["lpips"] = 0.031
    assert "| 0.031 |" in pt.markdown_table(res)


@pytest.mark.parametrize("downscale", [1, 2])
def test_nerf_timing_at_400_is_a_400_render(pt, tmp_path, monkeypatch, downscale):
    """The NeRF-SH's 400² seconds come from a 400² render even when the views are scored at
    800² (a --run-dir of an 800² run): the 400² speed-up is 400² against 400²."""
    from plenoctree.nerf import evaluate

    calls = []

    def fake(run, split, views, downscale, out, data=None, with_ssim=True):
        calls.append(downscale)
        sec = {1: 4.0, 2: 1.0}[downscale]          # an 800² frame takes 4× a 400² one
        return {"mean_psnr": 33.0, "mean_ssim": 0.97, "n_views": views,
                "seconds": [sec] * views, "seconds_per_full_frame": sec, "model_mb": 23.6}

    monkeypatch.setattr(evaluate, "render_nerf_views", fake)
    r = pt.measure_nerf_cpu(tmp_path, 3, tmp_path, downscale, None)
    assert (r["s_400"], r["s_800"], r["views"]) == (1.0, 4.0, 3)
    assert calls[0] == downscale and sorted(set(calls)) == [1, 2]
