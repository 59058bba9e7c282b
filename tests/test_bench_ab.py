"""benchmarks/ab.py: a benchmark run under two revisions alternately, in one table (the
worktrees removed afterwards); and benchmarks/_bench.py's shared timing and JSON helpers."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

_REPO = Path(__file__).resolve().parents[1]
_BENCH = _REPO / "benchmarks"


def _git_checkout() -> bool:
    return shutil.which("git") is not None and subprocess.run(
        ["git", "-C", str(_REPO), "rev-parse", "--verify", "HEAD"],
        capture_output=True).returncode == 0


needs_git = pytest.mark.skipif(not _git_checkout(), reason="needs git and a git checkout")


@pytest.fixture()
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(_BENCH))
    import _bench
    import ab

    return _bench, ab


def _ab(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(_BENCH / "ab.py"), "--tmp", str(tmp_path),
                           *args], capture_output=True, text=True, timeout=600)


def _worktrees() -> str:
    return subprocess.run(["git", "-C", str(_REPO), "worktree", "list"], capture_output=True,
                          text=True, check=True).stdout


@needs_git
def test_ab_head_against_this_checkout(tmp_path):
    """HEAD (a temporary worktree) against this checkout on the octree build benchmark: both
    sides ran twice, alternating; the table and the JSON name each metric's medians, ranges
    and ratio; no worktree is left."""
    out = tmp_path / "ab.json"
    res = _ab(tmp_path, "--rev", "HEAD", "--alternate", "2", "--out", str(out), "--",
              "bench_octree_build.py", "--res", "16", "--repeat", "2")
    assert res.returncode == 0, res.stdout + res.stderr
    rep = json.loads(out.read_text())
    head = subprocess.run(["git", "-C", str(_REPO), "rev-parse", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    assert rep["sides"]["A"] == {"rev": "HEAD", "commit": head}
    assert rep["sides"]["B"]["rev"].startswith("working tree")
    assert {k: len(v) for k, v in rep["runs"].items()} == {"A": 2, "B": 2}
    assert all(len(v) == 2 and min(v) > 0 for v in rep["seconds"].values())
    assert res.stderr.count("[ab] round") == 4
    m = rep["metrics"]["rows.0.build_s"]
    for k in "AB":
        assert m[k]["min"] <= m[k]["median"] <= m[k]["max"] and len(m[k]["values"]) == 2
    assert math.isclose(m["ratio_b_over_a"], m["B"]["median"] / m["A"]["median"])
    assert not any(p.startswith("machine") for p in rep["metrics"])
    assert "| metric | A median | A range | B median | B range | B / A |" in res.stdout
    assert "| rows.0.build_s |" in res.stdout
    assert str(tmp_path) not in _worktrees() and not list(tmp_path.glob("ab-*"))


@needs_git
def test_ab_failing_run_is_reported_and_cleaned_up(tmp_path):
    res = _ab(tmp_path, "--rev", "HEAD", "--alternate", "1", "--", "bench_octree_build.py",
              "--no-such-flag")
    assert res.returncode != 0
    assert "bench_octree_build.py failed on side" in res.stderr and "--no-such-flag" in res.stderr
    assert str(tmp_path) not in _worktrees() and not list(tmp_path.glob("ab-*"))
    res = _ab(tmp_path, "--rev", "no-such-revision-xyz", "--", "bench_octree_build.py")
    assert res.returncode != 0 and "is not a revision" in res.stderr
    res = _ab(tmp_path, "--rev", "HEAD", "--", "bench_octree_build.py", "--out", "x.json")
    assert res.returncode != 0 and "--out is ab.py's" in res.stderr


def test_compare_keeps_measurements_only(bench):
    """Numbers that differ between runs are compared, settings (the same everywhere), machine
    information and metrics of one side only are not; list items by index."""
    _, ab = bench
    runs = {"A": [{"rows": [{"s": 2.0, "n": 5}], "machine": {"loadavg": [1.0]}, "x": 1.0},
                  {"rows": [{"s": 4.0, "n": 5}], "machine": {"loadavg": [2.0]}, "x": 1.0}],
            "B": [{"rows": [{"s": 1.0, "n": 5}], "machine": {"loadavg": [3.0]}, "y": 2.0},
                  {"rows": [{"s": 2.0, "n": 5}], "machine": {"loadavg": [4.0]}, "y": 3.0}]}
    m = ab.compare(runs, None)
    assert list(m) == ["rows.0.s"]
    assert m["rows.0.s"]["A"] == {"median": 3.0, "min": 2.0, "max": 4.0, "values": [2.0, 4.0]}
    assert m["rows.0.s"]["ratio_b_over_a"] == 0.5
    assert ab.compare(runs, r"^x") == {}
    assert "| rows.0.s | 3 | 2–4 | 1.5 | 1–2 | 0.500 |" in ab.table(m)


def test_timing_and_json_helpers(bench, tmp_path):
    _bench, _ = bench
    calls = []
    t = _bench.timed(lambda: calls.append(1) or len(calls), 3)
    assert len(calls) == 4 and t.result == 4 and len(t.wall) == len(t.cpu) == 3   # + warm-up
    assert min(t.wall) <= t.median <= max(t.wall) and t.spread >= 0
    assert t.scaled(0.5).median == pytest.approx(t.median / 2)
    order = []
    ts = _bench.interleaved({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, 2)
    assert order == ["a", "b"] * 3 and set(ts) == {"a", "b"}
    path = _bench.write_json(tmp_path / "d" / "r.json",
                             {"x": np.float32(1.5), "a": np.arange(2), "nan": float("nan"),
                              "t": (1, 2), "p": tmp_path})
    assert json.loads(path.read_text()) == {"x": 1.5, "a": [0, 1], "nan": None, "t": [1, 2],
                                            "p": str(tmp_path)}
    info = _bench.machine_info([0.5, 0.5, 0.5])
    assert info["loadavg_before"] == [0.5, 0.5, 0.5] and info["cpu_count"] >= 1
    assert Path(info["plenoctree_path"]).is_dir()


def test_data_root_flag_env_and_error(bench, tmp_path, monkeypatch):
    _bench, _ = bench
    monkeypatch.setenv(_bench.DATA_ENV, str(tmp_path / "env"))
    assert _bench.data_root() == tmp_path / "env"
    assert _bench.data_root(str(tmp_path / "flag")) == tmp_path / "flag"
    assert _bench.data_path(None, "runs", "x") == tmp_path / "env" / "runs" / "x"
    monkeypatch.delenv(_bench.DATA_ENV)
    monkeypatch.setattr(_bench, "REPO", tmp_path / "a" / "b")      # no shared/data above it
    with pytest.raises(SystemExit, match="--data-root DIR or set PLENOCTREE_DATA"):
        _bench.data_path(None, "nerf_synthetic", "lego")
    (tmp_path / "shared" / "data").mkdir(parents=True)
    assert _bench.data_root() == tmp_path / "shared" / "data"


def _summary(psnrs: dict, process_s: float | None) -> dict:
    rows = [{"stage": k, "psnr": v, "ssim": 0.8, "fps": 20.0, "leaves": 1000, "seconds": 60.0}
            for k, v in psnrs.items()]
    times = {"train": 1800.0, **({"process": process_s} if process_s else {})}
    return {"rows": rows, "times_s": times, "total_s": 2400.0 + (process_s or 0),
            "peak_rss_mb": {"train": 900.0, "process": 400.0 if process_s else None},
            "config": {}}


def test_capture_chain_tabulates_finished_chains(monkeypatch, tmp_path, capsys):
    """capture_chain.py: finished chains (summary.json present) are not run again; the table
    puts both side by side with the PSNR difference, the process stage first."""
    monkeypatch.syspath_prepend(str(_BENCH))
    import capture_chain

    work = tmp_path / "work"
    for kind, ps, proc in (("published", {"NeRF-SH": 27.0, "PlenOctree fine-tuned": 27.5}, None),
                           ("process", {"NeRF-SH": 26.8, "PlenOctree fine-tuned": 27.1}, 70.0)):
        (work / f"flower_{kind}").mkdir(parents=True)
        (work / f"flower_{kind}" / "summary.json").write_text(json.dumps(_summary(ps, proc)))
    monkeypatch.setattr(capture_chain, "subprocess", None)      # no chain may run
    out = tmp_path / "r.json"
    assert capture_chain.main(["--real", "flower", "--work", str(work), "--data-root",
                               str(tmp_path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    assert lines[1].startswith("| process (COLMAP) |")
    assert "| PlenOctree fine-tuned | 27.50 |" in text and "| -0.40 |" in text
    res = json.loads(out.read_text())
    assert res["chains"]["process"]["peak_rss_mb"] == 900.0
    cmd = capture_chain.chain_command(tmp_path / "real" / "fox", "images", "process",
                                      tmp_path / "o", ["--train.minutes", "15"])
    assert cmd[3:5] == ["run", "--images"] and cmd[5].endswith("fox/images")
    assert cmd[-2:] == ["--train.minutes", "15"]


def test_frontier_tabulates_a_finished_budget_and_plots_the_points(monkeypatch, tmp_path,
                                                                   capsys):
    """frontier.py: a budget whose folder holds its measurement is not run again; its row
    takes the PSNR per stage, leaves and times from the run's summary, the first preview and
    the gaps from the polled previews; the plot draws the measured and the earlier points."""
    monkeypatch.syspath_prepend(str(_BENCH))
    import frontier

    run = tmp_path / "work" / "5"
    run.mkdir(parents=True)
    (run / "frontier.json").write_text(json.dumps({
        "wall_s": 1200.0, "returncode": 0, "command": "plenoctree run …", "load_before": [0.5],
        "previews": [{"s": 38.0, "tree": "nerf/preview.npz"},
                     {"s": 191.0, "tree": "nerf/preview.npz"},
                     {"s": 373.0, "tree": "tree.npz"}, {"s": 993.0, "tree": "tree_ft.npz"}]}))
    stages = {"NeRF-SH": 29.76, "PlenOctree": 28.75, "PlenOctree refined": 29.34,
              "PlenOctree fine-tuned": 31.25, "compressed": 31.24}
    (run / "summary.json").write_text(json.dumps({
        "rows": [{"stage": k, "psnr": v, "views": 200, "leaves": 7_010_000} for k, v in
                 stages.items()], "times_s": {"train": 313.0, "finetune": 552.0},
        "total_s": 1190.0}))
    monkeypatch.setattr(frontier, "watch", None)                # no chain may run
    out, png = tmp_path / "f.json", tmp_path / "f.png"
    assert frontier.main(["--scene", "lego", "--budgets", "5", "--work", str(tmp_path / "work"),
                          "--data-root", str(tmp_path), "--out", str(out), "--plot", str(png),
                          "--plot-from", str(out),
                          str(_BENCH / "frontier_points" / "earlier.json")]) == 0
    row = json.loads(out.read_text())["rows"][0]
    assert (row["compressed"], row["finetuned"], row["leaves"]) == (31.24, 31.25, 7_010_000)
    assert row["wall_min"] == 20.0 and row["first_preview_s"] == 38.0 and row["scene"] == "lego"
    assert frontier.gaps(row["previews"]) == "38 s, then 153 s (training); trees at 373, 993 s"
    assert "31.24" in capsys.readouterr().out
    assert png.is_file() and png.read_bytes()[:4] == b"\x89PNG"
