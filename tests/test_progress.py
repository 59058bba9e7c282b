"""Progress to a non-terminal: one line every few seconds with % and ETA, nothing for short steps."""

from __future__ import annotations

import re

import pytest

from plenoctree._util import LogProgress, progress


class _Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_log_progress_lines_at_interval_with_percent_and_eta(capsys):
    clock = _Clock()
    bar = LogProgress(total=100, desc="render", interval=5.0, unit="view", clock=clock)
    for _ in range(9):                  # 9 updates, 1 s apart: one line at t = 5 s
        clock.t += 1.0
        bar.update(1)
    err = capsys.readouterr().err.splitlines()
    assert err == ["render:   5% 5/100 view [0:05 elapsed, ETA 1:35, 1.00 view/s]"]
    bar.set_postfix(psnr="30.1")
    clock.t += 1.0
    bar.update(1)                       # 6 s after the last line
    bar.close()
    bar.close()                         # closing twice prints once
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("render:  10% 10/100 view [0:10 elapsed, ETA 1:30")
    assert lines[0].endswith("psnr=30.1")
    assert len(lines) == 2              # the final line on close
    assert lines[1] == lines[0]


def test_log_progress_short_step_prints_nothing(capsys):
    clock = _Clock()
    with LogProgress(range(3), desc="x", interval=10.0, clock=clock) as bar:
        for _ in bar:
            clock.t += 1.0
    assert capsys.readouterr().err == ""
    assert bar.n == 3 and bar.total == 3


def test_log_progress_without_total_and_float_budget(capsys):
    clock = _Clock()
    bar = LogProgress(desc="train", interval=2.0, unit="step", clock=clock)
    clock.t += 3.0
    bar.update(30)
    assert capsys.readouterr().err.strip() == "train: 30 step [0:03 elapsed, 10.00 step/s]"
    budget = LogProgress(total=1800, desc="train", interval=2.0, unit="s", clock=clock)
    clock.t += 3.0
    budget.update(2.5)                  # seconds of training out of a 30-minute budget
    line = capsys.readouterr().err.strip()
    assert line.startswith("train:   0% 2.5/1800 s [0:03 elapsed, ETA 35:57, 0.83 s/s")   # (1800 - 2.5) / (2.5 / 3)


def test_log_progress_unit_scale_and_iterable_length(capsys):
    clock = _Clock()
    bar = LogProgress(total=2_000_000, desc="sampling", unit="voxel", unit_scale=True,
                      interval=1.0, clock=clock)
    clock.t += 2.0
    bar.update(1_000_000)
    assert "50% 1.00M/2.00M voxel [0:02 elapsed, ETA 0:02, 500.00k voxel/s]" in \
        capsys.readouterr().err


def test_progress_picks_log_lines_off_a_terminal(capsys, monkeypatch):
    # pytest's captured stderr is not a terminal
    bar = progress(total=10, desc="d")
    assert isinstance(bar, LogProgress)
    assert not isinstance(progress(total=10, disable=True), LogProgress)
    monkeypatch.setenv("PLENOCTREE_PROGRESS_INTERVAL", "0")
    for _ in progress(range(4), desc="fast"):
        pass
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 5 and lines[-1].startswith("fast: 100% 4/4 it")


def test_training_with_time_budget_reports_percent_and_eta(tmp_path, monkeypatch, capsys):
    """A --minutes run off a terminal logs '% ... ETA' lines (it used to print nothing)."""
    from nerf_fixtures import tiny_cpu_config, tiny_dataset
    from plenoctree.nerf import train

    data = tiny_dataset(tmp_path / "data", size=16, n_train=4)
    cfg = tiny_cpu_config(data, tmp_path / "run", steps=10 ** 6)
    cfg.minutes, cfg.val_views = 0.05, 0            # 3 s of training
    monkeypatch.setenv("PLENOCTREE_PROGRESS_INTERVAL", "1")
    train(cfg)
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("train:")]
    assert len(lines) >= 2, lines
    assert all(re.match(r"train: +\d+% [\d.]+/3 s \[.* elapsed, ETA ", ln) for ln in lines), lines
    assert lines[-1].startswith("train: 100%")
