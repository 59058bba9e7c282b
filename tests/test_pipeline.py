"""The resumable pipeline (``plenoctree run``) and the demo on a tiny procedural scene."""

from __future__ import annotations

import json
import logging

import pytest

from plenoctree.cli import main
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.errors import ConfigError
from plenoctree.pipeline import PipelineConfig, PipelineError, layer_settings, run_pipeline

# A tiny network and budget: the chain's plumbing, not its quality, is under test here.
TINY_TRAIN = {"val_views": 1, "chunk": 1024, "target_samples": 4096, "sparsity_points": 256,
              "minutes": 0, "max_steps": 4, "occ_res": 16, "render_step": 0.05,
              "model": {"grid_levels": 4, "grid_max_res": 32, "grid_log2_table": 10,
                        "net_width": 16}}
# An (almost) untrained model renders nothing: keep every voxel of the full box.
TINY_EXTRACT = {"grid": 16, "samples": 2, "bbox": "fixed", "masking": "sigma",
                "mask_alpha_thresh": 1e-12}


def _tiny_cfg(data, out, stages: dict | None = None, **kw) -> PipelineConfig:
    """The tiny chain; ``stages``: stage settings over it (``{"finetune": {"epochs": 2}}``)."""
    cfg = PipelineConfig(data=str(data), out=str(out), nerf_eval_views=1, video_frames=2)
    layer_settings(cfg, {"train": TINY_TRAIN, "extract": TINY_EXTRACT,
                         "finetune": {"epochs": 1}}, where="test")
    layer_settings(cfg, stages or {}, where="test")
    for k, v in kw.items():
        setattr(cfg, k, v)
    return cfg


@pytest.fixture
def logs():
    """The messages of the ``plenoctree`` logger (whatever the CLI configured before)."""
    records: list[str] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = lambda r: records.append(r.getMessage())  # type: ignore[method-assign]
    logger = logging.getLogger("plenoctree")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield records
    logger.removeHandler(handler)
    logger.setLevel(level)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipe")
    write_procedural_dataset(root / "data", n_train=3, n_val=1, n_test=2, width=16, height=16)
    return root / "data"


def test_pipeline_runs_resumes_and_reruns_changed_stages(scene, tmp_path, logs, capsys):
    out = tmp_path / "run"
    s = run_pipeline(_tiny_cfg(scene, out))
    for name in ("nerf/checkpoint.pt", "tree.npz", "tree_refined.npz", "tree_ft.npz", "tree_ft.plnz",
                 "eval_ft/eval.json", "web/index.html", "orbit.mp4", "summary.json",
                 "summary.md", "nerf_eval.json", "stages.png"):
        assert (out / name).exists(), name
    stages = [r["stage"] for r in s["rows"]]
    assert stages == ["NeRF-SH", "PlenOctree", "PlenOctree refined", "PlenOctree fine-tuned",
                      "compressed"]
    assert all(r["psnr"] is not None and r["psnr"] > 5 for r in s["rows"])
    # The table says how many test views each row scored (NeRF-SH: nerf_eval_views).
    assert [r["views"] for r in s["rows"]] == [1, 2, 2, 2, 2]
    md = (out / "summary.md").read_text()
    assert "| test views |" in md
    # the summary states fine-tuning's gain and, when it kept its input tree, why
    ft = s["finetune"]
    assert ft["test_gain_db"] is not None and "Fine-tuning:" in md
    assert ft["stop_reason"] and (ft["best_epoch"] > 0 or "input tree was kept" in md)
    assert s["speedup_over_nerf"] and s["speedup_over_nerf"] > 0
    assert not s["skipped"]

    logs.clear()
    s2 = run_pipeline(_tiny_cfg(scene, out))
    assert set(s2["skipped"]) >= {"train", "extract", "refine", "finetune", "compress", "eval_ft"}
    # OUT/config.json is the nested config; `run --config` of it is the same config
    saved = json.loads((out / "config.json").read_text())
    assert saved["finetune"]["epochs"] == 1 and saved["extract"]["run_dir"] == str(out / "nerf")
    capsys.readouterr()
    assert main(["run", "--config", str(out / "config.json"), "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out) == saved == s2["config"]

    # Changing a fine-tuning setting reruns fine-tuning and what depends on it only.
    logs.clear()
    s3 = run_pipeline(_tiny_cfg(scene, out, {"finetune": {"epochs": 2}}))
    assert "train" in s3["skipped"] and "extract" in s3["skipped"]
    assert "finetune" not in s3["skipped"] and "compress" not in s3["skipped"]
    # every stage records its CPU seconds beside the wall time
    assert s3["cpu_s"]["finetune"] > 0 and "| CPU (s) |" in (out / "summary.md").read_text()

    # --nerf: a second chain from the trained NeRF-SH of the first, which is only read
    ck = out / "nerf" / "checkpoint.pt"
    before = ck.stat().st_mtime_ns
    out2 = tmp_path / "from_nerf"
    s4 = run_pipeline(_tiny_cfg(scene, out2, nerf=str(out / "nerf"), video_frames=0, web=False))
    assert not (out2 / "nerf").exists() and ck.stat().st_mtime_ns == before
    assert "train" in s4["skipped"] and s4["rows"][0]["given"]
    assert (out2 / "tree_ft.npz").exists() and "(given run)" in (out2 / "summary.md").read_text()
    # the given NeRF-SH's training time is shown on its row, not added to this chain's total
    assert s4["given"] == ["train"] and s4["rows"][0]["seconds"] > 0
    assert s4["total_s"] == pytest.approx(sum(v for k, v in s4["times_s"].items()
                                              if v and k != "train"))
    assert "training not counted" in (out2 / "summary.md").read_text()
    with pytest.raises(ConfigError, match="no checkpoint.pt"):
        run_pipeline(_tiny_cfg(scene, tmp_path / "x", nerf=str(tmp_path)))


def test_the_trees_are_scored_on_one_load_of_the_test_split(scene, tmp_path, monkeypatch):
    """The four scoring stages decode each view subset once (the trees before the result share
    theirs), and score as a fresh load does."""
    from plenoctree import evaluation

    loads: list[str] = []
    real = evaluation.eval_dataset
    monkeypatch.setattr(evaluation, "eval_dataset",
                        lambda cfg: loads.append(str(cfg.tree)) or real(cfg))
    out = tmp_path / "run"
    run_pipeline(_tiny_cfg(scene, out, video_frames=0, web=False))
    assert len(loads) == 2 and loads[0].endswith("tree.npz") and loads[1].endswith(".plnz")
    for key, tree in (("raw", "tree.npz"), ("compressed", "tree_ft.plnz")):
        saved = json.loads((out / f"eval_{key}" / "eval.json").read_text())
        fresh = evaluation.eval_tree_file(evaluation.EvalConfig(
            tree=out / tree, data=scene, out=tmp_path / f"again_{key}"))
        assert fresh["mean"]["psnr"] == pytest.approx(saved["mean"]["psnr"], abs=1e-9)
        assert fresh["mean"]["ssim"] == pytest.approx(saved["mean"]["ssim"], abs=1e-12)
        assert fresh["tree"]["n_occupied_leaves"] == saved["tree"]["n_occupied_leaves"] > 0
    assert len(loads) == 4                   # each call of eval_tree_file alone loads its own


def test_the_result_is_scored_on_every_view_and_the_trees_before_it_on_fewer(scene, tmp_path):
    """--stage-eval-views: the raw, refined and fine-tuned trees on that many evenly spaced test
    views, the compressed tree (the chain's result) on --eval-views (0 = all); never more views
    for a tree before it than for the result."""
    from plenoctree.pipeline import stage_views

    cfg = PipelineConfig(eval_views=0, stage_eval_views=25)
    assert [stage_views(cfg, k) for k in ("raw", "ft", "compressed")] == [25, 25, 0]
    cfg = PipelineConfig(eval_views=5, stage_eval_views=25)
    assert [stage_views(cfg, k) for k in ("raw", "ft", "compressed")] == [5, 5, 5]
    cfg = PipelineConfig(eval_views=40, stage_eval_views=0)
    assert [stage_views(cfg, k) for k in ("raw", "ft", "compressed")] == [40, 40, 40]

    out = tmp_path / "run"
    s = run_pipeline(_tiny_cfg(scene, out, video_frames=0, web=False, stage_eval_views=1))
    assert [r["views"] for r in s["rows"]] == [1, 1, 1, 1, 2]
    with pytest.raises(ConfigError, match="--stage-eval-views must be >= 0"):
        run_pipeline(_tiny_cfg(scene, tmp_path / "bad", stage_eval_views=-1))


def test_bad_stage_options_fail_before_training(scene, tmp_path):
    out = tmp_path / "early"
    with pytest.raises(ConfigError, match="--extract.grid must be a power of two"):
        run_pipeline(_tiny_cfg(scene, out, {"extract": {"grid": 3}}))
    with pytest.raises(ConfigError, match="--finetune.optimizer must be"):
        run_pipeline(_tiny_cfg(scene, out, {"finetune": {"optimizer": "lbfgs"}}))
    with pytest.raises(ConfigError, match="test: unknown option 'extract.gird'"):
        run_pipeline(_tiny_cfg(scene, out, {"extract": {"gird": 64}}))
    assert not (out / "nerf").exists()


def test_failing_stage_names_itself_keeps_artefacts_and_resumes(scene, tmp_path, monkeypatch,
                                                                logs):
    import plenoctree.convert.extraction as ex

    def broken(cfg, field=None):
        raise ConfigError("extraction broke")

    out = tmp_path / "run"
    monkeypatch.setattr(ex, "extract", broken)
    with pytest.raises(PipelineError, match="stage 'extract' failed") as e:
        run_pipeline(_tiny_cfg(scene, out))
    monkeypatch.undo()
    assert "rerun the same command to resume" in str(e.value)
    assert (out / "nerf" / "checkpoint.pt").exists() and not (out / "tree.npz").exists()
    logs.clear()
    run_pipeline(_tiny_cfg(scene, out))
    assert "[train] up to date, skipped" in logs
    assert (out / "tree_ft.npz").exists()


def test_run_cli_bad_data(tmp_path, capsys):
    assert main(["run", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 1
    assert "missing" in capsys.readouterr().err


def test_demo_cli_tiny(tmp_path, capsys):
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--image-size", "32", "--n-train", "6", "--n-test", "2",
            "--train.minutes", "0", "--train.steps", "200", "--extract.grid", "16",
            "--finetune.epochs", "1", "--video-frames", "0"]
    assert main(args) == 0
    s = json.loads((out / "summary.json").read_text())
    assert len(s["rows"]) == 5 and (out / "tree_ft.plnz").exists()
    text = capsys.readouterr().out
    assert "PlenOctree fine-tuned" in text and "plenoctree view" in text
    assert main(args) == 0
    assert "[dataset] up to date, skipped" in capsys.readouterr().out


def test_demo_on_a_user_dataset(scene, tmp_path, capsys):
    out = tmp_path / "demo_data"
    args = ["demo", "--data", str(scene), "--out", str(out), "--train.minutes", "0",
            "--train.steps", "200", "--extract.grid", "16", "--finetune.epochs", "1",
            "--video-frames", "0"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "downscale 1 (16 px), grid 16" in text and "plenoctree view" in text
    assert not (out / "data").exists()  # the user's data is used, no procedural scene written
    assert (out / "eval_ft" / "renders").is_dir()


def test_pipeline_on_llff_capture_whose_size_4_does_not_divide(tmp_path):
    """A forward-facing LLFF capture 18×12 px (like LLFF's 504×378: 4 divides neither 18 nor
    378): every stage runs, the web bundle's training cameras load at a dividing downscale;
    no refinement pass (``--refine.passes`` -1 decides by capture: the 360° scene of the
    test above gets one), and the extraction box is stretched along NDC depth."""
    from plenoctree.datasets.forward_facing import write_forward_facing_dataset

    data = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=18, height=12,
                                        n_samples=8)
    out = tmp_path / "run"
    run_pipeline(_tiny_cfg(data, out, video_frames=0))
    cfg = json.loads((out / "web" / "config.json").read_text())
    assert cfg["cameras"]["width"] == 3 and cfg["ndc"]["width"] == 3
    assert (out / "summary.md").exists()
    assert not (out / "tree_refined.npz").exists()
    assert json.loads((out / "config.json").read_text())["refine"]["passes"] == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [r["stage"] for r in summary["rows"] if "refined" in r["stage"]] == []
    assert json.loads((out / "tree.extract.json").read_text())["box"]["depth_stretch"] == 4


def test_refinement_passes_by_capture():
    """``run``'s ``--refine.passes`` default (-1) is one pass for a 360° capture and none for a
    forward-facing one; a number given is kept."""
    from plenoctree.pipeline_config import AUTO_PASSES, scene_refine_passes

    assert PipelineConfig().refine.passes == AUTO_PASSES
    assert scene_refine_passes(AUTO_PASSES, forward=False) == 1
    assert scene_refine_passes(AUTO_PASSES, forward=True) == 0
    assert scene_refine_passes(2, forward=True) == 2 and scene_refine_passes(0, False) == 0


def test_training_budget_by_capture():
    """``run``'s ``--train.minutes`` default (-1) is 15 minutes for a forward-facing capture
    and 30 for a 360° one, with no step limit; a budget given is kept, also 0 (steps)."""
    from plenoctree.pipeline_config import AUTO_MINUTES, UNLIMITED_STEPS, scene_train_minutes

    cfg = PipelineConfig()
    assert cfg.train.minutes == AUTO_MINUTES and cfg.train.max_steps == UNLIMITED_STEPS
    assert scene_train_minutes(AUTO_MINUTES, forward=True) == 15.0
    assert scene_train_minutes(AUTO_MINUTES, forward=False) == 30.0
    assert scene_train_minutes(7.5, forward=True) == 7.5 and scene_train_minutes(0, False) == 0
    # -1 given as a flag still means "by capture", with the budget deciding (no step limit)
    cfg = layer_settings(PipelineConfig(), {"train": {"minutes": AUTO_MINUTES}}, where="test")
    assert cfg.train.max_steps == UNLIMITED_STEPS


@pytest.mark.parametrize("forward", [True, False])
def test_scene_settings_read_the_capture_only_when_left_to_it(monkeypatch, forward):
    """With ``--downscale``, ``--refine.passes`` and ``--train.minutes`` given nothing is
    decided by the capture, so no image is read to probe it; with any left open the probe
    runs and decides it by the capture's kind."""
    import dataclasses

    import plenoctree.pipeline as pl

    probes = []

    def probe(cfg):
        probes.append(cfg.train.data)
        return ("llff" if forward else "blender"), 800, 800, forward

    monkeypatch.setattr(pl, "_capture", probe)
    given = PipelineConfig(data="scene", out="o", downscale=2)
    given = dataclasses.replace(given, refine=dataclasses.replace(given.refine, passes=1),
                                train=dataclasses.replace(given.train, minutes=12.0))
    done = pl._scene_settings(pl.wired(given))
    assert (done.refine.passes, done.train.minutes) == (1, 12.0) and probes == []
    auto = pl._scene_settings(pl.wired(PipelineConfig(data="scene", out="o", downscale=2)))
    assert len(probes) == 1
    assert (auto.refine.passes, auto.train.minutes) == ((0, 15.0) if forward else (1, 30.0))
    budget_only = dataclasses.replace(given, train=PipelineConfig().train)
    assert pl._scene_settings(pl.wired(budget_only)).train.minutes == (15.0 if forward else 30.0)
    assert len(probes) == 2


@pytest.mark.parametrize("scene,forward", [("flower", True), ("lounge", False)])
def test_run_reads_an_llff_folder_as_the_capture_it_is(scene, forward):
    """``run``'s working resolution and refinement passes follow the capture's kind: an LLFF
    folder whose cameras surround the scene (lounge) is a 360° capture, not forward-facing."""
    import plenoctree.pipeline as pl
    from plenoctree.datasets.llff import POSES_FILE

    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / scene
    if not (root / POSES_FILE).is_file():
        pytest.skip(f"{root} not available")
    cfg = pl.wired(PipelineConfig(data=str(root), out="o"))
    fmt, w, h, fwd = pl._capture(cfg)
    assert (fmt, fwd) == ("llff", forward)
