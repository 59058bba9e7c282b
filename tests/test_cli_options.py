"""The config → CLI mechanism and the CLI's shared conventions (issue 14 CLI/packaging items)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from plenoctree.cli import build_parser, main
from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
from plenoctree.pipeline_config import PipelineConfig
from plenoctree.octree import save_tree

ROOT = Path(__file__).resolve().parents[1]


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_version_and_python_dash_m(capsys):
    from plenoctree import __version__

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"plenoctree {__version__}"
    out = subprocess.run([sys.executable, "-m", "plenoctree", "--help"], capture_output=True,
                         text=True, check=True).stdout
    assert "finetune" in out and "COMMAND" in out


def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    return capsys.readouterr().out


def test_every_help_shows_real_defaults(capsys):
    for name, sub in _subparsers(build_parser()).items():
        text = sub.format_help()
        assert "(default None)" not in text and "default: None" not in text, name
        assert "%%" not in text, name
    run_help = _help(["run", "--help-all"], capsys)
    assert "--finetune.epochs" in run_help and "--train.net-width" in run_help
    assert "--extract.bbox-scale" in run_help
    assert "(default None)" not in run_help and "%%" not in run_help
    train_help = _subparsers(build_parser())["train"].format_help()
    assert "(default: 0.01)" in train_help            # lr_init of the cpu preset


def test_a_new_config_field_becomes_a_flag_with_no_other_edit():
    from plenoctree._config import apply
    from plenoctree.cli._options import add_config, given

    @dataclasses.dataclass
    class Cfg:
        epochs: int = 20
        """Passes over the data."""
        lr: float | None = None
        """Learning rate (default: the optimiser's)."""
        box: tuple = ()
        """Box centre x y z."""
        smooth: bool = False
        """Smooth the result."""
        background: tuple = (1.0, 1.0, 1.0)
        """Background colour."""

    p = argparse.ArgumentParser()
    dests = add_config(p, Cfg, prefix="stage.")
    args = p.parse_args(["--stage.epochs", "3", "--stage.box", "1", "2", "3", "--stage.smooth",
                         "--stage.background", "black"])
    values = given(args, dests, prefix="stage.")
    assert values == {"epochs": 3, "box": [1.0, 2.0, 3.0], "smooth": True,
                      "background": "black"}
    cfg = apply(Cfg(), values)
    assert cfg.box == (1.0, 2.0, 3.0) and cfg.lr is None and cfg.epochs == 3
    assert cfg.background == (0.0, 0.0, 0.0)
    assert "Passes over the data. (default: 20)" in p.format_help()
    args = p.parse_args(["--stage.background", "pink"])
    with pytest.raises(Exception, match="--background: expected white, black or R,G,B"):
        apply(Cfg(), given(args, dests, prefix="stage."))
    assert apply(Cfg(), {"background": "0.5"}).background == (0.5, 0.5, 0.5)   # config files


def test_train_config_file_then_flags(tmp_path, capsys):
    cfg_file = tmp_path / "c.json"
    cfg_file.write_text(json.dumps({"preset": "paper", "lr_init": 1e-3,
                                    "model": {"net_width": 128}}))
    assert main(["train", "--out", str(tmp_path / "r"), "--config", str(cfg_file),
                 "--net-width", "96", "--format", "blender", "--print-config"]) == 0
    cfg = json.loads(capsys.readouterr().out)
    assert cfg["preset"] == "paper" and cfg["lr_init"] == 1e-3 and cfg["format"] == "blender"
    assert cfg["model"]["net_width"] == 96 and cfg["model"]["net_depth"] == 8
    cfg_file.write_text(json.dumps({"lr_inti": 1.0}))
    assert main(["train", "--out", str(tmp_path / "r"), "--config", str(cfg_file),
                 "--print-config"]) == 1
    assert "unknown option 'lr_inti'" in capsys.readouterr().err


def test_run_nested_stage_flags_presets_and_saved_config(tmp_path, capsys):
    args = ["run", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "quick",
            "--finetune.epochs", "3", "--train.net-width", "32", "--extract.center", "0", "0",
            "0", "--print-config"]
    assert main(args) == 0
    cfg = json.loads(capsys.readouterr().out)
    # the quick preset: the whole run within 10 minutes (the NeRF-SH's budget decided by it
    # once the capture is read), the default stages after it, no video
    assert cfg["minutes"] == 10.0 and cfg["train"]["minutes"] == -1 and cfg["video_frames"] == 0
    defaults = PipelineConfig()
    assert (cfg["extract"]["grid"], cfg["extract"]["samples"]) == (
        defaults.extract.grid, defaults.extract.samples) and cfg["eval_views"] == 5
    assert (cfg["finetune"]["epochs"], cfg["train"]["model"]["net_width"],
            cfg["extract"]["center"]) == (3, 32, [0.0, 0.0, 0.0])
    saved = tmp_path / "config.json"
    saved.write_text(json.dumps(cfg))
    assert main(["run", "--config", str(saved), "--extract.grid", "64", "--print-config"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["extract"]["grid"] == 64 and again["finetune"]["epochs"] == 3
    # the saved config alone is the same config (save, reload, equal)
    assert main(["run", "--config", str(saved), "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out) == cfg


def test_run_help_is_short_and_shows_the_stages_on_demand(capsys):
    text = _help(["run", "--help"], capsys)
    assert len(text.splitlines()) <= 150, len(text.splitlines())
    assert "--help-all" in text and "--finetune.epochs" not in text
    stage = _help(["run", "--help-stage", "finetune"], capsys)
    assert "--finetune.epochs" in stage and "--train.net-width" not in stage
    assert len(_help(["run", "--help-all"], capsys).splitlines()) > 150


def test_one_flag_per_setting_of_run():
    """No two flags of `run` set the same value: each dest has one flag (a boolean's --no-x
    aside), and no pipeline-wide setting is also a stage flag."""
    run = _subparsers(build_parser())["run"]
    by_dest: dict[str, list[str]] = {}
    for action in run._actions:
        names = [s for s in action.option_strings if not s.startswith("--no-")]
        if names and action.dest != "help":
            by_dest.setdefault(action.dest, []).extend(names)
    assert all(len(v) == 1 for v in by_dest.values()), {k: v for k, v in by_dest.items()
                                                         if len(v) > 1}
    from plenoctree.pipeline import STAGE_OPTIONS

    for opt in STAGE_OPTIONS:           # what the pipeline sets (paths, --seed...) has no flag
        for name in opt.wired:
            assert f"{opt.name}.{name}" not in by_dest, (opt.name, name)
    for wide in ("seed", "device", "backend", "downscale", "threads", "format", "data", "out"):
        assert wide in by_dest
    for removed in ("--finetune-epochs", "--grid", "--train-minutes", "--compress-bits"):
        assert removed not in run._option_string_actions


@pytest.mark.parametrize("argv, typed, meant", [
    (["run", "--data", "d", "--out", "o", "--finetune-epochs", "3"], "--finetune-epochs",
     "--finetune.epochs"),
    (["run", "--data", "d", "--out", "o", "--finetune.epo", "3"], "--finetune.epo",
     "--finetune.epochs"),
    (["eval", "t.npz", "--limit", "2"], "--limit", None),
    (["train", "--out", "o", "--max-steps", "2"], "--max-steps", "--steps"),
    (["demo", "--grid", "16"], "--grid", None),
])
def test_abbreviated_and_unknown_flags_are_refused_by_their_command(argv, typed, meant, capsys):
    """An abbreviation or an old alias is refused: the error is the sub-command's (its usage),
    names the flag typed and, when one is close, the flag meant."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert f"usage: plenoctree {argv[0]}" in err and f"plenoctree {argv[0]}: error" in err, err
    assert f"unrecognized arguments: {typed}" in err
    if meant:
        assert f"did you mean {meant}?" in err


def test_every_long_command_has_quiet_and_progress():
    subs = _subparsers(build_parser())
    for name in ("train", "extract", "refine", "finetune", "eval", "render", "video", "export",
                 "run", "demo"):
        flags = subs[name]._option_string_actions
        assert {"--quiet", "--progress", "--no-progress"} <= set(flags), name
    train = subs["train"]._option_string_actions["--preset"].choices
    assert set(train) == set(subs["run"]._option_string_actions["--preset"].choices)


def test_views_means_views_of_the_split_everywhere(tiny_scene, tmp_path, capsys):
    """--views N: N views of the split, 0 = all (eval, render, compress, render-nerf)."""
    subs = _subparsers(build_parser())
    for name in ("eval", "render", "compress", "render-nerf"):
        assert "--views" in subs[name]._option_string_actions, name
    assert main(["render", str(tiny_scene / "tree.npz"), "--data", str(tiny_scene / "data"),
                 "--views", "0", "--out", str(tmp_path / "r")]) == 0
    n = len(json.loads((tmp_path / "r" / "metrics.json").read_text())["views"])
    assert n > 1
    assert main(["render", str(tiny_scene / "tree.npz"), "--data", str(tiny_scene / "data"),
                 "--views", "-1", "--out", str(tmp_path / "s")]) == 1
    assert "--views must be >= 0 (0 = all)" in capsys.readouterr().err


def test_run_checks_the_video_extra_first(tmp_path, monkeypatch, capsys):
    import importlib.util

    from plenoctree.pipeline import PipelineConfig, check_extras

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    with pytest.raises(Exception, match=r"plenoctree\[video\]'.*--video-frames 0"):
        check_extras(PipelineConfig(video_frames=10))
    check_extras(PipelineConfig(video_frames=0))
    write_procedural_dataset(tmp_path / "d", n_train=1, n_val=1, n_test=1, width=8, height=8)
    assert main(["run", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "o")]) == 1
    assert "plenoctree[video]" in capsys.readouterr().err
    assert not (tmp_path / "o" / "nerf").exists()


def test_eval_and_render_take_data_from_the_trees_provenance(tiny_scene, tmp_path, capsys):
    tree = tmp_path / "tree.npz"
    tree.write_bytes((tiny_scene / "tree.npz").read_bytes())
    assert main(["eval", str(tree), "--views", "1"]) == 1
    assert "--data is needed" in capsys.readouterr().err
    (tmp_path / "tree.extract.json").write_text(json.dumps(
        {"config": {"data": str(tiny_scene / "data"), "run_dir": ""}}))
    assert main(["eval", str(tree), "--views", "1", "--out", str(tmp_path / "e"),
                 "--json", str(tmp_path / "e.json")]) == 0
    out = capsys.readouterr().out
    assert f"--data {tiny_scene / 'data'}" in out
    assert json.loads((tmp_path / "e.json").read_text())["dataset"]["n_views"] == 1
    assert main(["render", str(tree), "--views", "1", "--out", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / "metrics.json").exists()


def test_info_describes_a_tree(tiny_scene, capsys):
    assert main(["info", str(tiny_scene / "tree.npz"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["data_format"] == "SH16" and info["n_leaves"] > 0 and info["max_depth"] >= 1
    assert main(["info", str(tiny_scene / "missing.npz")]) == 1


def test_license_is_an_spdx_string():
    text = (ROOT / "pyproject.toml").read_text()
    assert 'license = "MIT"' in text and "license = {" not in text


# Commands on add_command: (argv without --config, a config file, what it must resolve to,
# a flag that overrides the file and the value it gives).
_CONFIG_CASES = {
    "process": (["process", "imgs", "--out", "o"],
                {"frames": 12, "sfm": {"max_features": 100}},
                lambda c: (c.frames, c.sfm.max_features, c.sfm.single_camera) == (12, 100, True),
                ["--max-features", "7"], lambda c: c.sfm.max_features == 7),
    "export": (["export", "t.npz", "--out", "o.ply"], {"min_opacity": 0.5, "up": "+y"},
               lambda c: (c.min_opacity, c.up, c.tree) == (0.5, "+y", "t.npz"),
               ["--min-opacity", "0.25"], lambda c: c.min_opacity == 0.25),
    "plot": (["plot", "summary.json"], {"title": "T"}, lambda c: c.title == "T",
             ["--title", "U"], lambda c: c.title == "U"),
    "video": (["video", "t.npz"], {"frames": 3, "depth_range": [1, 2], "mode": "both"},
              lambda c: (c.frames, c.depth_range, c.mode) == (3, (1, 2), "both"),
              ["--depth-range", "0.5,4"], lambda c: c.depth_range == (0.5, 4.0)),
    "compress": (["compress", "t.npz"], {"codec": {"bits": 4}, "evaluate": False},
                 lambda c: (c.codec.bits, c.codec.level, c.evaluate) == (4, 6, False),
                 ["--bits", "5", "--eval"], lambda c: c.codec.bits == 5 and c.evaluate),
    "decompress": (["decompress", "t.plnz"], {"precision": "fp16"},
                   lambda c: c.precision == "fp16", ["--precision", "fp32"],
                   lambda c: c.precision == "fp32"),
    "lod": (["lod", "t.npz", "--out", "o.plnz"], {"lod": {"sh_degree": 1}, "target_mb": 2},
            lambda c: (c.lod.sh_degree, c.target_mb, c.codec.bits) == (1, 2, 16),
            ["--sh-degree", "0"], lambda c: c.lod.sh_degree == 0),
    "view": (["view", "t.npz"], {"port": 0, "split": "test"},
             lambda c: (c.port, c.split, c.max_mb) == (0, "test", 2048.0),
             ["--port", "9"], lambda c: c.port == 9),
    "extract": (["extract", "run"], {"grid": 64, "samples": 2},
                lambda c: (c.grid, c.samples, c.run_dir) == (64, 2, "run"),
                ["--grid", "32"], lambda c: c.grid == 32),
    "refine": (["refine", "t.npz"], {"passes": 3}, lambda c: c.passes == 3,
               ["--passes", "2"], lambda c: c.passes == 2),
    "finetune": (["finetune", "t.npz"], {"epochs": 2, "optimizer": "sgd"},
                 lambda c: (c.epochs, c.optimizer) == (2, "sgd"),
                 ["--epochs", "1"], lambda c: c.epochs == 1),
    "eval": (["eval", "t.npz"], {"split": "val", "limit": 2},
             lambda c: (c.split, c.limit, c.tree) == ("val", 2, "t.npz"),
             ["--views", "1"], lambda c: c.limit == 1),
    "demo": (["demo"], {"n_train": 5}, lambda c: c.n_train == 5,
             ["--n-train", "6"], lambda c: c.n_train == 6),
    "render": (["render", "t.npz"], {"split": "val", "background": "black", "limit": 2},
               lambda c: (c.split, c.background, c.limit) == ("val", (0.0, 0.0, 0.0), 2),
               ["--background", "0,0,1"], lambda c: c.background == (0.0, 0.0, 1.0)),
    "render-nerf": (["render-nerf", "run"], {"views": 3, "ssim": False},
                    lambda c: (c.views, c.ssim, c.run_dir) == (3, False, "run"),
                    ["--ssim"], lambda c: c.ssim),
    "export-web": (["export-web", "t.npz", "--out", "o"], {"title": "T", "overwrite": True},
                   lambda c: (c.title, c.overwrite) == ("T", True),
                   ["--no-overwrite"], lambda c: not c.overwrite),
}


@pytest.mark.parametrize("command", sorted(_CONFIG_CASES))
def test_config_file_then_flags_on_every_config_command(command, tmp_path):
    argv, values, check, flags, check_flags = _CONFIG_CASES[command]
    cfg_file = tmp_path / "c.json"
    cfg_file.write_text(json.dumps(values))
    parser = build_parser()
    args = parser.parse_args(argv + ["--config", str(cfg_file)])
    assert check(args._resolve(args))
    args = parser.parse_args(argv + ["--config", str(cfg_file)] + flags)
    cfg = args._resolve(args)
    assert check_flags(cfg)
    cfg_file.write_text(json.dumps({"no_such_option": 1}))
    args = parser.parse_args(argv + ["--config", str(cfg_file)])
    with pytest.raises(Exception, match="unknown option 'no_such_option'"):
        args._resolve(args)


def test_fixed_length_tuple_flags_are_checked(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["video", "t.npz", "--depth-range", "1,2,3"])
    assert "--depth-range: expected 2 numbers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        build_parser().parse_args(["video", "t.npz", "--depth-range", "near,far"])
    assert "expected numbers" in capsys.readouterr().err


def test_compress_runs_from_a_config_file(tiny_scene, tmp_path, capsys):
    cfg_file = tmp_path / "c.json"
    cfg_file.write_text(json.dumps({"codec": {"bits": 3}, "evaluate": False}))
    out = tmp_path / "t.plnz"
    assert main(["compress", str(tiny_scene / "tree.npz"), "--out", str(out), "--config",
                 str(cfg_file), "--json", str(tmp_path / "r.json")]) == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["options"]["bits"] == 3 and "psnr_fidelity" not in rep and out.is_file()
