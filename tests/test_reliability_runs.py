"""Run folders: locks naming their holder, stale temp files, output paths checked before work."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from plenoctree._util import atomic_write, check_output_file, clean_stale_tmp, run_lock
from plenoctree.errors import ConfigError

_HOLD = """
import sys, time
from plenoctree._util import run_lock
with run_lock(sys.argv[1], "holder", folder=sys.argv[2] == "dir"):
    print("held", flush=True)
    time.sleep(60)
"""


def _holder(target, kind="dir"):
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(target), kind], stdout=subprocess.PIPE,
                         text=True)
    assert p.stdout.readline().strip() == "held"
    return p


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_lock_names_holder_and_dead_holder_is_taken_over(tmp_path):
    run = tmp_path / "run"
    p = _holder(run)
    try:
        with pytest.raises(ConfigError, match=rf"{run}: in use by another plenoctree process: "
                                              rf"pid {p.pid} on .* since .*\(holder\)"):
            with run_lock(run, "train"):
                pass
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait()
    assert (run / ".plenoctree.lock").exists()        # kill -9 leaves the file ...
    with run_lock(run, "train"):                       # ... and the lock is taken over
        with run_lock(run, "nested"):                  # same process: re-entrant
            pass
    assert not (run / ".plenoctree.lock").exists()


def test_two_trainings_into_one_out(tmp_path):
    """Two runs into one --out both 'succeeded' and one result was lost."""
    from plenoctree.nerf.config import preset
    from plenoctree.nerf.trainer import train

    run = tmp_path / "run"
    cfg = preset("cpu")
    cfg.data, cfg.out = str(tmp_path / "no_data_needed"), str(run)
    p = _holder(run)
    try:
        for resume in (False, True):
            with pytest.raises(ConfigError, match=f"in use by another plenoctree process: pid "
                                                  f"{p.pid}"):
                train(cfg, resume=resume)
    finally:
        p.kill()
        p.wait()


def test_finetune_lock_and_output_checks_before_work(tmp_path):
    from plenoctree.optim.finetuning import FinetuneConfig, finetune

    cfg = FinetuneConfig(tree=str(tmp_path / "missing.npz"), data=str(tmp_path), out="")
    outdir = tmp_path / "outdir"
    outdir.mkdir()
    cfg.out = str(outdir)          # was: failed only after the fine-tuning (result lost)
    with pytest.raises(ConfigError, match=f"{outdir}: --out is a directory"):
        finetune(cfg)
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    cfg.out = str(notes)
    with pytest.raises(ConfigError, match="not a tree file written by plenoctree; refusing"):
        finetune(cfg)
    assert notes.read_text() == "my notes"
    out = tmp_path / "ft.npz"
    cfg.out = str(out)
    p = _holder(out, "file")
    try:
        with pytest.raises(ConfigError, match=f"in use by another plenoctree process: pid {p.pid}"):
            finetune(cfg)
    finally:
        p.kill()
        p.wait()


def test_extract_refuses_to_overwrite_unrelated_file(tmp_path, capsys):
    from plenoctree.cli import main

    notes = tmp_path / "notes.txt"
    notes.write_text("do not overwrite")
    assert main(["extract", str(tmp_path / "run"), "--out", str(notes)]) == 1
    err = capsys.readouterr().err
    assert f"{notes}: exists and is not a tree file" in err and "Traceback" not in err
    assert notes.read_text() == "do not overwrite"


def test_check_output_file_accepts_our_trees(tmp_path):
    from plenoctree import Octree, save_tree

    t = tmp_path / "t.npz"
    save_tree(Octree.dense(1, "RGBA"), t)
    assert check_output_file(t) == t                 # rerunning into our own tree file is fine
    (tmp_path / "f").write_text("x")
    with pytest.raises(ConfigError, match="is a file, not a folder"):
        check_output_file(tmp_path / "f" / "t.npz")


def test_stale_tmp_files_of_dead_processes_are_cleaned(tmp_path):
    dead = _dead_pid()
    stale = [tmp_path / f"tree.npz.tmp-{dead}", tmp_path / f".orbit.tmp-{dead}.mp4"]
    live = tmp_path / f"other.npz.tmp-{os.getppid()}"
    mine = tmp_path / "unrelated.tmp-notapid"
    for f in stale + [live, mine]:
        f.write_bytes(b"x" * 1000)
    with atomic_write(tmp_path / "new.json", "w") as f:     # every atomic write cleans its folder
        f.write("{}")
    assert not any(f.exists() for f in stale)
    assert live.exists() and mine.exists() and (tmp_path / "new.json").exists()
    assert clean_stale_tmp(tmp_path) == []


def test_kill_9_during_atomic_write_leaves_nothing_behind_after_next_write(tmp_path):
    code = ("import sys, time\nfrom plenoctree._util import atomic_write\n"
            "with atomic_write(sys.argv[1]) as f:\n    f.write(b'x' * 100000); f.flush()\n"
            "    print('writing', flush=True); time.sleep(60)\n")
    p = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "big.npz")],
                         stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "writing"
    p.kill()
    p.wait()
    assert [f.name for f in tmp_path.iterdir()] == [f"big.npz.tmp-{p.pid}"]
    time.sleep(0.05)
    with atomic_write(tmp_path / "big.npz") as f:
        f.write(b"ok")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["big.npz"]


def test_run_checks_every_stage_and_locks_its_folder(tmp_path):
    """``run --grid 100`` (or bad compression bits) failed after the whole training; a second
    ``run`` into a live run's folder raced it."""
    from plenoctree.datasets.procedural import write_procedural_dataset
    from plenoctree.pipeline import PipelineConfig, layer_settings, run_pipeline

    data = tmp_path / "scene"
    write_procedural_dataset(data, n_train=2, n_val=1, n_test=1, width=8, height=8, seed=0)
    out = tmp_path / "run"
    for kw, msg in (({"extract": {"grid": 100}}, "--extract.grid must be a power of two"),
                    ({"compress": {"bits": 40}}, "bits must be an integer in 1..")):
        with pytest.raises(ConfigError, match=msg):
            run_pipeline(layer_settings(PipelineConfig(data=str(data), out=str(out),
                                                       video_frames=0), kw, "test"))
    assert not (out / "nerf").exists()
    p = _holder(out)
    try:
        with pytest.raises(ConfigError, match=f"in use by another plenoctree process: pid {p.pid}"):
            run_pipeline(PipelineConfig(data=str(data), out=str(out), video_frames=0))
    finally:
        p.kill()
        p.wait()
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="must be a folder"):
        run_pipeline(PipelineConfig(data=str(data), out=str(tmp_path / "file")))
