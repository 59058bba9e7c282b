"""A reliability attack on the counts and times of every command: a value past its ceiling
(``plenoctree._bounds``), from a flag or a config file, is one error line naming the setting
and the limit, before any work; ``compress --views`` (the old orbit-view count) without
``--data`` is refused; abbreviated flags are refused everywhere.

(Under torchrun only rank 0 reports the validation PSNR: ``test_nerf_distributed.py``.)
"""

from __future__ import annotations

import argparse
import json
import math

import pytest

from plenoctree._bounds import (MAX_BATCH, MAX_COUNT, MAX_MINUTES, bound_error, check_bounds)
from plenoctree.cli import build_parser, main
from plenoctree.errors import ConfigError
from test_hardening import _fails

HUGE = 10**30


def _config(tmp_path, values) -> str:
    path = tmp_path / "c.json"
    path.write_text(json.dumps(values))        # float("inf") is written as Infinity
    return str(path)


# --- 1. times ------------------------------------------------------------------------------------
@pytest.mark.parametrize("minutes", [1e308, math.inf, 20000])
def test_train_minutes_from_a_config_file_past_a_week(tiny_scene, tmp_path, capsys, minutes):
    """``{"minutes": 1e308}`` crashed in the progress bar (OverflowError, a traceback)."""
    cfg = _config(tmp_path, {"minutes": minutes})
    _fails(capsys, ["train", "--data", tiny_scene / "data", "--out", tmp_path / "run",
                    "--config", cfg], cfg, "'minutes' (--minutes) must be at most 10080 (a week)")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("argv, needle", [
    (["--minutes", "1e400"], "'minutes' (--minutes) must be at most 10080"),
    (["--steps", str(HUGE)], f"'max_steps' (--steps) must be at most {MAX_COUNT}"),
    (["--batch-size", str(2**40)], f"'batch_rays' (--batch-size) must be at most {MAX_BATCH}"),
    (["--val-every-s", "1e12"], "'val_every_s' (--val-every-s) must be at most 604800"),
    (["--net-width", str(HUGE)], f"must be at most {MAX_COUNT}"),
    (["--lr-init", "nan"], "'lr_init' (--lr-init) must be a finite number, got nan"),
])
def test_train_flags_past_their_ceiling(tiny_scene, tmp_path, capsys, argv, needle):
    _fails(capsys, ["train", "--data", tiny_scene / "data", "--out", tmp_path / "run", *argv],
           needle)
    assert not (tmp_path / "run").exists()


# --- 2. counts of every command -----------------------------------------------------------------
def test_finetune_refuses_absurd_batches_and_epochs(tiny_scene, tmp_path, capsys):
    """``{"batch_rays": 10**30, "epochs": 10**30}`` was accepted and ran without a word."""
    for values, needle in (({"batch_rays": HUGE, "epochs": HUGE}, "'batch_rays'"),
                           ({"epochs": HUGE}, "'epochs' (--epochs) must be at most"),
                           ({"checkpoint_minutes": 1e9}, "must be at most 10080")):
        cfg = _config(tmp_path, values)
        _fails(capsys, ["finetune", tiny_scene / "tree.npz", "--data", tiny_scene / "data",
                        "--out", tmp_path / "ft.npz", "--config", cfg], cfg, needle)
    _fails(capsys, ["finetune", tiny_scene / "tree.npz", "--data", tiny_scene / "data", "--out",
                    tmp_path / "ft.npz", "--batch-rays", str(MAX_BATCH + 1)],
           f"'batch_rays' (--batch-rays) must be at most {MAX_BATCH}")
    assert not (tmp_path / "ft.npz").exists()


@pytest.mark.parametrize("argv, needle", [
    (["extract", "{run}", "--samples", HUGE], "'samples' (--samples) must be at most"),
    (["refine", "{tree}", "--run-dir", "{run}", "--passes", HUGE], "'passes' (--passes)"),
    (["run", "--data", "{data}", "--out", "{out}", "--train.minutes", "1e308"],
     "'train.minutes' must be at most 10080 (a week)"),
    (["run", "--data", "{data}", "--out", "{out}", "--finetune.epochs", HUGE],
     f"'finetune.epochs' must be at most {MAX_COUNT}"),
    (["run", "--data", "{data}", "--out", "{out}", "--finetune.batch-rays", HUGE],
     "'finetune.batch_rays' must be at most"),
    (["run", "--data", "{data}", "--out", "{out}", "--video-frames", HUGE],
     "'video_frames' (--video-frames) must be at most"),
    (["compress", "{tree}", "--orbit-views", HUGE], "'views' (--orbit-views) must be at most"),
    (["lod", "{tree}", "--out", "{out}.npz", "--max-depth", HUGE], "'lod.max_depth' (--max-depth)"),
    (["render", "{tree}", "--data", "{data}", "--views", HUGE], "'limit' (--views) must be at"),
    (["video", "{tree}", "--frames", HUGE], "'frames' (--frames) must be at most"),
    (["video", "{tree}", "--fps", "1e9"], "'fps' (--fps) must be at most 1000"),
])
def test_every_command_bounds_its_counts(tiny_scene, tmp_path, capsys, argv, needle):
    names = {"run": tmp_path / "norun", "tree": tiny_scene / "tree.npz",
             "data": tiny_scene / "data", "out": tmp_path / "out"}
    _fails(capsys, [str(a).format(**names) for a in argv], needle)
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.npz").exists()


def test_run_config_file_nested_settings_are_bounded(tiny_scene, tmp_path, capsys):
    for values, needle in (({"train": {"minutes": 1e308}}, "'train.minutes' must be at most"),
                           ({"finetune": {"batch_rays": HUGE, "epochs": HUGE}},
                            "'finetune.batch_rays' must be at most"),
                           ({"extract": {"samples": HUGE}}, "'extract.samples'")):
        cfg = _config(tmp_path, values)
        _fails(capsys, ["run", "--data", tiny_scene / "data", "--out", tmp_path / "out",
                        "--config", cfg], cfg, needle)
    assert not (tmp_path / "out").exists()


def test_configs_built_in_python_are_held_to_the_same_ceilings():
    """The configs' own checks (the API, and configs read back from a checkpoint) use the same
    policy: one message per setting, naming the limit."""
    from plenoctree.convert.refine import RefineConfig
    from plenoctree.nerf.config import TrainConfig, config_from_dict, config_to_dict, validate
    from plenoctree.optim.finetuning import FinetuneConfig

    with pytest.raises(ConfigError, match=r"^minutes must be at most 10080 \(a week\)"):
        validate(TrainConfig(minutes=1e308))
    with pytest.raises(ConfigError, match="net_width must be at most"):
        config_from_dict({**config_to_dict(TrainConfig()), "model": {"net_width": HUGE}})
    with pytest.raises(ConfigError, match="finetune: epochs must be at most 2147483647"):
        FinetuneConfig(tree="t", data="d", out="o", epochs=HUGE).validated()
    with pytest.raises(ConfigError, match="refine: samples must be at most"):
        RefineConfig(samples=HUGE).validated()
    assert check_bounds(TrainConfig(minutes=MAX_MINUTES, max_steps=MAX_COUNT))


@pytest.mark.parametrize("name, value, problem", [
    ("minutes", 10080, None), ("minutes", 10080.5, "must be at most 10080 (a week)"),
    ("epochs", MAX_COUNT, None), ("epochs", MAX_COUNT + 1, "must be at most 2147483647"),
    ("threads", -HUGE, "must be at least -2147483647"),
    ("seed", 2**40, None), ("seed", 2**64, "must be at most 9223372036854775807"),
    ("lr", 1e300, None), ("lr", math.inf, "must be a finite number, got inf"),
    ("lr", 10**400, "must be a finite number, got an integer of 401 digits"),
    ("occ_res", 2048, "must be at most 1024"), ("name", "text", None), ("flag", True, None),
])
def test_bound_error(name, value, problem):
    got = bound_error(name, value, integer=isinstance(value, int) and name != "lr")
    assert got == problem or (problem and got.startswith(problem)), got


# --- 3. the validation PSNR is reported, never as nan ------------------------------------------
def test_train_without_validation_views_says_so(tmp_path, capsys):
    from nerf_fixtures import tiny_cpu_config, tiny_dataset
    from plenoctree.nerf.config import config_json

    cfg = tiny_cpu_config(tiny_dataset(tmp_path / "data", size=16, n_train=4), tmp_path / "x",
                          steps=2)
    cfg.val_views = 0
    (tmp_path / "c.json").write_text(config_json(cfg))
    assert main(["train", "--config", str(tmp_path / "c.json"), "--out", str(tmp_path / "run"),
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "trained 2 steps" in out and "no validation views" in out and "nan" not in out, out


# --- 4. compress --views is the split's views, never the orbit's ---------------------------------
def test_compress_views_without_data_is_refused(tiny_scene, tmp_path, capsys):
    """``--views N`` (the old spelling of ``--orbit-views``) was taken as a view limit of a
    dataset and silently ignored without ``--data``."""
    out = tmp_path / "c.plnz"
    line = _fails(capsys, ["compress", tiny_scene / "tree.npz", "--views", "8", "--out", out],
                  "--views 8", "--data", "--orbit-views")
    assert "orbit views" in line and not out.exists()
    cfg = _config(tmp_path, {"limit": 3})
    _fails(capsys, ["compress", tiny_scene / "tree.npz", "--config", cfg, "--out", out],
           "--views 3", "--orbit-views")
    assert main(["compress", str(tiny_scene / "tree.npz"), "--views", "1", "--data",
                 str(tiny_scene / "data"), "--no-eval", "--out", str(out)]) == 0


def _parsers(parser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_no_parser_takes_abbreviated_flags(capsys):
    """An abbreviation never maps silently onto another flag (``--view`` onto ``--views``,
    ``--orbit`` onto ``--orbit-views``): every parser of the CLI refuses them."""
    parsers = list(_parsers(build_parser()))
    assert len(parsers) > 15 and not [p.prog for p in parsers if p.allow_abbrev]
    for typed in ("--view", "--orbit", "--orbit-view"):
        with pytest.raises(SystemExit) as e:
            main(["compress", "t.npz", typed, "3"])
        assert e.value.code == 2
        assert f"unrecognized arguments: {typed}" in capsys.readouterr().err
