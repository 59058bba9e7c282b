"""The whole chain as a resumable pipeline: photos → NeRF-SH → octree → fine-tuned → compressed.

``plenoctree run --data DIR --out DIR`` and ``plenoctree demo`` call :func:`run_pipeline`.
The chain is a list of :class:`Stage` objects (:func:`plan_stages`), each with its inputs, its
artefacts, the fingerprint of its settings and ``run()``. Each stage writes its artefact
atomically and records a stamp (its settings plus the size and modification time of its
inputs) in ``OUT/.stages/``; a stage whose artefacts exist with an unchanged stamp is skipped,
so a run killed at any point continues where it stopped (the trainer and the fine-tuner also
resume mid-stage from their checkpoints). A failing stage stops the run with a
:class:`PipelineError` naming the stage; finished artefacts are kept.

Settings: :class:`PipelineConfig` holds the pipeline-wide settings and one typed config per
stage (``train: TrainConfig``, ``extract: ExtractConfig``...); each setting has one place, and
``run`` one flag for it (``--seed``, ``--finetune.epochs``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ._bounds import check_bounds
from ._config import config_dict
from ._util import atomic_save_json, atomic_write, check_output_dir, run_lock
from .compression.codec import CompressOptions
from .errors import ConfigError, DatasetError, PlenOctreeError
from .nerf.config import TrainConfig
from .pipeline_config import (AUTO_MINUTES, AUTO_PASSES, PRESETS, STAGE_OPTIONS,
                              PipelineConfig, RunLayout, artefact_layout, layer_settings,
                              name_the_flags, nerf_run_dir, pipeline_preset,
                              scene_refine_passes, scene_train_minutes, stage_views,
                              train_preset, wired, working_downscale)
from .pipeline_budget import (Budget, budget_training, command_start, finetune_minutes,
                              run_counts)
from .pipeline_summary import finetune_outcome, pipeline_summary, summary_markdown

__all__ = ["PipelineConfig", "PipelineError", "Stage", "run_pipeline", "plan_stages",
           "STAGES", "STAGE_OPTIONS", "PRESETS", "pipeline_preset", "train_preset",
           "layer_settings", "wired", "check_extras", "run_layout", "summary_markdown"]

logger = logging.getLogger(__name__)

STAGES = ("process", "train", "nerf_eval", "extract", "refine", "finetune", "compress",
          "eval", "web", "video")
"""The stages of the chain, in their order (``eval`` is one stage per octree file)."""


class PipelineError(PlenOctreeError, RuntimeError):
    """A pipeline stage failed; the message names the stage and what to do."""


def check_extras(cfg: PipelineConfig) -> None:
    """Fail at the start, with the install hint, when a stage needs a missing optional
    package (the orbit video needs ``plenoctree[video]``)."""
    import importlib.util

    if cfg.video_frames > 0:
        missing = [m for m in ("imageio", "imageio_ffmpeg") if importlib.util.find_spec(m) is None]
        if missing:
            raise ConfigError(f"the video stage needs {' and '.join(missing)} (not installed): "
                              "pip install 'plenoctree[video]', or pass --video-frames 0")


def _given_nerf(path: str) -> Path:
    """:func:`nerf_run_dir`, checked to hold a checkpoint."""
    from .nerf.checkpoint import CHECKPOINT_NAME

    p = nerf_run_dir(path)
    if not (p / CHECKPOINT_NAME).is_file():
        raise ConfigError(f"--nerf {path}: no {CHECKPOINT_NAME} there (give the run folder of a "
                          "trained NeRF-SH, e.g. the OUT/nerf of an earlier run)")
    return p


def run_layout(out: Any, nerf: str = "") -> RunLayout:
    """The artefact paths of a run into ``out`` (``nerf``: the ``--nerf`` it was given, checked
    to hold a checkpoint)."""
    if nerf:
        _given_nerf(nerf)
    return artefact_layout(out, nerf)


def _checked(opt_name: str, check: Callable[[], Any]) -> None:
    """Run one stage's option check; its ConfigError names ``run``'s flags."""
    try:
        check()
    except ConfigError as e:
        opt = next(o for o in STAGE_OPTIONS if o.name == opt_name)
        raise ConfigError(name_the_flags(opt, str(e))) from None


def _validate(cfg: PipelineConfig) -> None:
    """Check every stage's options now, not after the training (which takes minutes)."""
    from .convert.extraction import _validate as validate_extract
    from .nerf.config import validate

    if isinstance(cfg.downscale, bool) or not isinstance(cfg.downscale, int) or cfg.downscale < 0:
        raise ConfigError(f"--downscale must be an integer >= 1 (0 = the working resolution), "
                          f"got {cfg.downscale!r}")
    if not cfg.downscale:           # the stages' own checks, at any resolution
        cfg = wired(dataclasses.replace(cfg, downscale=1))
    if cfg.images:
        _checked("process", cfg.process.validated)
    elif config_dict(cfg.process) != config_dict(wired(PipelineConfig(out=cfg.out)).process):
        raise ConfigError("--process.* options apply to --images (photos or a video), not --data")
    train = cfg.train                 # (AUTO: a budget the capture decides, checked as 30)
    if train.minutes == AUTO_MINUTES:
        train = dataclasses.replace(train, minutes=scene_train_minutes(AUTO_MINUTES, False))
    _checked("train", lambda: validate(train))
    _checked("extract", lambda: validate_extract(cfg.extract))
    if cfg.refine.passes not in (0, AUTO_PASSES):     # (AUTO: checked once decided)
        _checked("refine", cfg.refine.validated)
    _checked("finetune", cfg.finetune.validated)
    _checked("compress", cfg.compress.validated)
    for name in ("eval_views", "stage_eval_views", "video_frames", "video_size", "minutes"):
        if getattr(cfg, name) < 0:
            raise ConfigError(f"--{name.replace('_', '-')} must be >= 0, got "
                              f"{getattr(cfg, name)}")
    if cfg.nerf_eval_views < -1:
        raise ConfigError(f"--nerf-eval-views must be >= -1 (0 = all, -1 = skip), got "
                          f"{cfg.nerf_eval_views}")
    check_bounds(cfg, nested=False)           # the pipeline-wide settings (stages: above)


@dataclass
class Stage:
    """One step of the chain: skipped when its ``outputs`` exist and its stamp (``settings`` and
    the size and modification time of ``inputs``) is the one recorded when it last ran."""

    name: str
    settings: dict
    """what decides the artefact (a stage config, minus progress and logging fields)"""
    inputs: list[Path]
    outputs: list[Path]
    run: Callable[[], Any]
    hint: str
    """what to change when it fails"""


def _fingerprint(paths: list[Path]) -> dict:
    out = {}
    for p in paths:
        try:
            st = p.stat()
            out[str(p)] = [st.st_size, st.st_mtime_ns] if p.is_file() else "dir"
        except OSError:
            out[str(p)] = None
    return out


def _cpu_seconds() -> float:
    """CPU seconds used so far by this process (all threads) and its waited-for children."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


class _Runner:
    """Runs stages with stamps, timing and uniform error reporting."""

    def __init__(self, out: Path):
        self.out = out
        self.stamps = out / ".stages"
        self.times: dict[str, float] = {}
        self.peaks: dict[str, float] = {}     # peak RSS (MB) of each stage
        self.cpu: dict[str, float] = {}       # CPU seconds of each stage (all threads)
        self.skipped: list[str] = []
        self.given_stages: list[str] = []     # artefacts given, not made by this pipeline

    def _up_to_date(self, stage: Stage, stamp: dict) -> bool:
        old = _read_json(self.stamps / f"{stage.name}.json") or None
        if old is None or old.get("stamp") != stamp or not all(p.exists() for p in stage.outputs):
            return False
        logger.info(f"[{stage.name}] up to date, skipped")
        self.times[stage.name] = float(old.get("seconds", 0.0))
        for key, into in (("peak_rss_mb", self.peaks), ("cpu_seconds", self.cpu)):
            if old.get(key) is not None:
                into[stage.name] = float(old[key])
        self.skipped.append(stage.name)
        return True

    def run(self, stage: Stage) -> bool:
        """Run ``stage`` unless it is up to date. Returns True if it ran."""
        stamp = json.loads(json.dumps({"settings": stage.settings,
                                       "inputs": _fingerprint(stage.inputs)}, default=str))
        if self._up_to_date(stage, stamp):
            return False
        logger.info(f"[{stage.name}] running")
        from .convert.memory import StageMonitor
        from .live import write_live

        write_live(self.out, stage=stage.name, step=None, steps=None, psnr=None, eta_s=None)

        mon, name = StageMonitor(), stage.name
        t0, c0 = time.perf_counter(), _cpu_seconds()
        try:
            with mon.stage(name):
                stage.run()
        except PlenOctreeError as e:
            raise PipelineError(
                f"stage '{name}' failed: {e}\n  finished artefacts are kept in {self.out}; "
                f"{stage.hint}, then rerun the same command to resume") from e
        except KeyboardInterrupt:
            logger.info(f"[{name}] interrupted; rerun the same command to resume")
            raise
        seconds = time.perf_counter() - t0
        self.times[name], self.cpu[name] = seconds, _cpu_seconds() - c0
        self.peaks[name] = float(mon.to_json()[name]["peak_rss_mb"])
        atomic_save_json(self.stamps / f"{name}.json",
                         {"stamp": stamp, "seconds": seconds, "cpu_seconds": self.cpu[name],
                          "peak_rss_mb": self.peaks[name]})
        logger.info(f"[{name}] done in {seconds:.1f} s")
        trees = [p for p in stage.outputs if p.suffix in (".npz", ".plnz") and p.is_file()
                 and p.resolve().parent == self.out.resolve()]
        write_live(self.out, stage=f"{name} done", **({"tree": trees[0].name} if trees else {}))
        return True

    def earlier_seconds(self) -> float:
        """Seconds the stages skipped as up to date took when an earlier run made them (given
        artefacts, such as ``--nerf``'s training, not counted)."""
        return sum(self.times.get(s, 0.0) for s in self.skipped if s not in self.given_stages)

    def given(self, name: str, seconds: float | None) -> None:
        """Record a stage not run here (its artefact was given); ``seconds`` as reported."""
        if seconds is not None:
            self.times[name] = float(seconds)
        self.skipped.append(name)
        self.given_stages.append(name)


def _settings(stage_cfg: Any) -> dict:
    """A stage config as its stamp: every field but progress and logging switches."""
    return {k: v for k, v in config_dict(stage_cfg).items()
            if k not in ("resume", "verbose", "show_progress")}


def run_pipeline(cfg: PipelineConfig) -> dict:
    """Run (or resume) the whole chain; returns the summary also written to ``summary.json``.

    Artefacts in ``cfg.out``: ``nerf/`` (run directory), ``nerf_eval.json``, ``tree.npz`` (raw
    extracted octree), ``tree_refined.npz`` (adaptively refined, when ``refine.passes``),
    ``tree_ft.npz`` (fine-tuned, with ``tree_ft.log.jsonl``), ``tree_ft.plnz`` (compressed),
    ``eval_{raw,refined,ft,compressed}/eval.json`` (the fine-tuned tree's renders and depth maps in
    ``eval_ft/renders/``), ``web/`` (viewer bundle), ``orbit.mp4``, ``config.json`` (the
    settings, for ``run --config``), ``summary.json`` and ``summary.md``. Progress lines go to
    the ``plenoctree.pipeline`` logger.
    """
    if not (cfg.data or cfg.images) or not cfg.out:
        raise ConfigError("--out and one of --data / --images are needed")
    if cfg.data and cfg.images:
        raise ConfigError("give either --data (a dataset) or --images (photos / a video), not both")
    out = check_output_dir(cfg.out)
    check_extras(cfg)
    if cfg.data and Path(cfg.data).resolve() == out.resolve():
        raise ConfigError(f"--out {out} is the dataset folder; give the run its own folder")
    # The lock creates OUT; a refused run (bad options, missing data) removes it again.
    with run_lock(out, "run"):      # a second run / resume into OUT fails naming the holder
        return _run(cfg, out)


def _run(cfg: PipelineConfig, out: Path) -> dict:
    start = time.time()
    cfg = wired(cfg)
    if cfg.data and not Path(cfg.data).exists():
        raise ConfigError(f"{cfg.data}: dataset folder does not exist")
    lay = run_layout(out, cfg.nerf)
    _validate(cfg)
    r = _Runner(out)
    t0 = command_start(start)

    def deadline() -> float:      # --minutes: the stages this run skips count as they took
        return t0 + 60.0 * cfg.minutes - r.earlier_seconds()

    logger.info(f"[run] watch it as it goes: plenoctree view {out}")
    if cfg.images:                # its dataset decides the working resolution
        r.run(_process_stage(cfg))
    budgeted = cfg.minutes > 0 and cfg.train.minutes == AUTO_MINUTES and not cfg.nerf
    cfg = _scene_settings(cfg)
    budget = None
    if cfg.minutes > 0:           # --minutes: the NeRF-SH's budget, fine-tuning's time limit
        budget = Budget(deadline, run_counts(cfg))
        if budgeted:
            cfg = wired(budget_training(cfg, out, deadline(), budget.counts))
    stages = plan_stages(cfg, lay, budget)[1 if cfg.images else 0:]
    atomic_save_json(out / "config.json", config_dict(cfg))   # `run --config` reads it back
    if cfg.nerf:          # a trained NeRF-SH: its training time is read from its summary
        logger.info(f"[train] using the trained NeRF-SH {lay.nerf} (not trained here)")
        r.given("train", _read_json(lay.nerf / "summary.json").get("train_time_s"))
    for stage in stages:
        r.run(stage)
    evals = {key: _read_json(out / f"eval_{key}" / "eval.json") for key, _ in _trees(cfg, lay)}
    summary = pipeline_summary(cfg, out, r, evals, _read_json(out / "nerf_eval.json"),
                               _read_json(lay.nerf / "summary.json"), finetune_outcome(lay.ft))
    atomic_save_json(lay.summary, summary)
    from .plots import plot_stages               # PSNR against FPS and MB (needs matplotlib)

    plot_stages(summary["rows"], out / "stages.png",
                title=f"{Path(cfg.data if not cfg.images else cfg.images).name}: stages")
    with atomic_write(out / "summary.md", "w") as f:
        f.write(summary_markdown(summary))
    logger.info("")
    logger.info(summary_markdown(summary))
    return summary


def _trees(cfg: PipelineConfig, lay: RunLayout) -> list[tuple[str, Path]]:
    """The octree stages scored on the test split: ``(key, tree file)``."""
    refined = [("refined", lay.refined)] if cfg.refine.passes > 0 else []
    return [("raw", lay.tree), *refined, ("ft", lay.ft), ("compressed", lay.compressed)]


def plan_stages(cfg: PipelineConfig, lay: RunLayout,
                budget: Budget | None = None) -> list[Stage]:
    """The stages of the chain, in order, for a :func:`wired` and checked ``cfg``; ``budget``
    (``run --minutes``: its deadline and the run's counts) sets
    fine-tuning's time limit when it starts (:func:`_finetune`)."""
    from .nerf.checkpoint import CHECKPOINT_NAME

    common = {"data": str(Path(cfg.train.data).resolve()), "format": cfg.format,
              "downscale": cfg.downscale}
    ckpt = lay.nerf / CHECKPOINT_NAME
    stages = [_process_stage(cfg)] if cfg.images else []
    if not cfg.nerf:
        stages.append(Stage("train", {**common, "train": config_dict(cfg.train)}, [], [ckpt],
                            lambda: _train(cfg.train), "check the dataset and training options"))
    if cfg.nerf_eval_views >= 0:
        stages.append(_nerf_eval_stage(cfg, lay, ckpt, common))
    stages.append(Stage("extract", _settings(cfg.extract), [ckpt], [lay.tree],
                        lambda: _call("convert.extraction", "extract", cfg.extract),
                        "change the extraction options (--extract.grid, "
                        "--extract.weight-thresh)"))
    if cfg.refine.passes > 0:
        stages.append(Stage("refine", _settings(cfg.refine), [lay.tree, ckpt], [lay.refined],
                            lambda: _call("convert.refine", "refine", cfg.refine),
                            "lower --refine.passes or raise --refine.threshold"))
    stages.append(Stage("finetune", _settings(cfg.finetune), [Path(cfg.finetune.tree)],
                        [lay.ft], lambda: _finetune(cfg, budget),
                        "lower --finetune.lr or --finetune.epochs"))
    stages.append(Stage("compress", config_dict(cfg.compress), [lay.ft], [lay.compressed],
                        lambda: _compress(lay, cfg.compress), "try fewer --compress.bits"))
    stages += _eval_stages(cfg, lay, common)
    if cfg.web:
        stages.append(Stage("web", {"cameras": 2}, [lay.compressed],
                            [Path(cfg.out) / "web" / "index.html"], lambda: _web(cfg, lay),
                            "use `plenoctree lod` to make a smaller tree"))
    if cfg.video_frames > 0:
        stages.append(_video_stage(cfg, lay, common))
    return stages


def _finetune(cfg: PipelineConfig, budget: Budget | None) -> Any:
    """Fine-tuning; under ``run --minutes`` with the time limit that leaves the stages after
    it their predicted time (:func:`~.pipeline_budget.finetune_minutes`). The limit is not part
    of the stage's stamp: a finished fine-tuning is not redone for it."""
    fcfg = cfg.finetune
    if budget is not None:
        gb = Path(fcfg.tree).stat().st_size / 1e9       # the fine-tuned tree's size (fp32)
        minutes = finetune_minutes(budget.counts, budget.deadline(), gb, fcfg.minutes)
        logger.info(f"[finetune] --minutes {cfg.minutes:g}: its epochs stop within "
                    f"{minutes:.1f} minutes")
        fcfg = dataclasses.replace(fcfg, minutes=minutes)
    return _call("optim.finetuning", "finetune", fcfg)


def _call(module: str, name: str, stage_cfg: Any) -> Any:
    """``plenoctree.<module>.<name>(stage_cfg)``, looked up when the stage runs."""
    import importlib

    return getattr(importlib.import_module(f"{__package__}.{module}"), name)(stage_cfg)


def _capture(cfg: PipelineConfig) -> tuple[str, int, int, bool]:
    """``(format, width, height, forward)`` of the dataset's full-size images (LLFF: the size in
    ``poses_bounds.npy``, whose ``images/`` may be absent); ``forward``: NDC (forward-facing)."""
    from .datasets import detect_format, load_dataset
    from .datasets.camera_sets import capture_kind
    from .datasets.llff import POSES_FILE, read_poses_bounds

    data = cfg.train.data
    fmt = cfg.format or detect_format(data)
    if fmt == "llff":               # forward-facing unless its cameras surround the scene
        poses, _, hwf = read_poses_bounds(Path(data) / POSES_FILE)[:3]
        h, w = (int(v) for v in hwf[0, :2])
        return fmt, w, h, capture_kind(poses) == "forward"
    probe = load_dataset(data, "train", format=fmt, limit=1)
    return fmt, probe.cameras.width, probe.cameras.height, bool(probe.cameras.ndc)


def _working_resolution(cfg: PipelineConfig, fmt: str, w: int, h: int, forward: bool
                        ) -> PipelineConfig:
    """``cfg`` with ``downscale`` 0 replaced by :func:`working_downscale` of its dataset's
    (format ``fmt``) ``w x h`` full-size images, said on the log."""
    import torch

    from .datasets import load_dataset

    sizes: dict[int, tuple[int, int]] = {}

    def loads(f: int) -> bool:           # (undistorted images: the files' size must divide)
        try:
            d = load_dataset(cfg.train.data, "train", format=fmt, limit=1, downscale=f)
        except (ConfigError, DatasetError):
            return False
        sizes[f] = (d.cameras.width, d.cameras.height)    # after any padding crop
        return True

    gpu = cfg.device.startswith("cuda") or (cfg.device == "auto" and torch.cuda.is_available())
    f = working_downscale(w, h, forward, gpu, loads)
    ww, hh = sizes.get(f, (w // f, h // f))
    logger.info(f"working resolution {ww}x{hh} (downscale {f}) for a "
                f"{'forward-facing' if forward else '360°'} capture on the "
                f"{'GPU' if gpu else 'CPU'}; --downscale overrides")
    return dataclasses.replace(cfg, downscale=f)


def _scene_settings(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` with what depends on the capture decided: the working resolution (``downscale``
    0), the NeRF-SH's budget (:data:`AUTO_MINUTES`) and the refinement passes
    (:data:`AUTO_PASSES`); wired and checked."""
    if (cfg.downscale and cfg.refine.passes != AUTO_PASSES
            and cfg.train.minutes != AUTO_MINUTES):
        return cfg                       # nothing left to the capture (no probe read)
    fmt, w, h, forward = _capture(cfg)
    kind = "forward-facing" if forward else "360°"
    if not cfg.downscale:
        cfg = _working_resolution(cfg, fmt, w, h, forward)
    if cfg.train.minutes == AUTO_MINUTES:
        minutes = scene_train_minutes(AUTO_MINUTES, forward)
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, minutes=minutes))
        if not cfg.nerf and not cfg.minutes:      # (--minutes: decided by the run's budget)
            logger.info(f"NeRF-SH budget: {minutes:g} minutes for a {kind} capture; "
                        f"--train.minutes overrides")
    passes = scene_refine_passes(cfg.refine.passes, forward)
    if passes != cfg.refine.passes:
        cfg = dataclasses.replace(cfg, refine=dataclasses.replace(cfg.refine, passes=passes))
        logger.info(f"refinement passes: {passes} for a {kind} capture; --refine.passes "
                    f"overrides")
    cfg = wired(cfg)
    if cfg.refine.passes > 0:
        _checked("refine", cfg.refine.validated)
    return cfg


def _process_stage(cfg: PipelineConfig) -> Stage:
    """``process`` into ``OUT/data`` (skipped when the photos and options are unchanged)."""
    src = Path(cfg.process.images)
    inputs = sorted(p for p in src.iterdir() if p.is_file()) if src.is_dir() else [src]
    settings = {**config_dict(cfg.process), "images": str(src.resolve())}
    return Stage("process", settings, inputs, [Path(cfg.process.out) / "process.json"],
                 lambda: _call("process", "process", cfg.process),
                 "check the photos (see the message), change the --process.* options, or run "
                 "`plenoctree process` yourself and pass --data")


def _train(tcfg: TrainConfig) -> None:
    """Train, resuming from the run folder's checkpoint when a previous run was cut short."""
    from .nerf.checkpoint import CHECKPOINT_NAME
    from .nerf.trainer import train

    resume = (Path(tcfg.out) / CHECKPOINT_NAME).exists()
    if resume:
        logger.info(f"[train] resuming {tcfg.out}")
    train(tcfg, resume=resume)


def _nerf_eval_stage(cfg: PipelineConfig, lay: RunLayout, ckpt: Path, common: dict) -> Stage:
    """The NeRF-SH baseline on a few test views: PSNR and seconds per frame."""
    out = Path(cfg.out)

    def run() -> None:
        from .nerf.evaluate import render_nerf_views

        res = render_nerf_views(lay.nerf, split="test", views=cfg.nerf_eval_views,
                                data=cfg.train.data, downscale=cfg.downscale,
                                out=out / "nerf_eval")
        atomic_save_json(out / "nerf_eval.json", res)

    return Stage("nerf_eval", {"views": cfg.nerf_eval_views, **common},
                 [ckpt], [out / "nerf_eval.json"], run,
                 "check the training run")


def _compress(lay: RunLayout, options: CompressOptions) -> None:
    from .compression import compress, save_compressed
    from .octree import load_tree

    save_compressed(compress(load_tree(lay.ft), options), lay.compressed)


def _eval_stages(cfg: PipelineConfig, lay: RunLayout, common: dict) -> list[Stage]:
    """Scores of each octree stage on the test split (PSNR, SSIM, FPS, MB), sharing one load of
    each view subset (:func:`stage_views`): the first stage that scores a subset loads it, the
    last stage lets them go (decoding lego's 200 test photos took ~6 s of each ~40-s scoring)."""
    trees = _trees(cfg, lay)
    shared: dict[int, Any] = {}
    return [_eval_stage(cfg, key, tree, common, shared, last=k == len(trees) - 1)
            for k, (key, tree) in enumerate(trees)]


def _eval_stage(cfg: PipelineConfig, key: str, tree: Path, common: dict, shared: dict[int, Any],
                last: bool) -> Stage:
    """Scores of one octree stage on its test views; ``shared[views]``: that subset of the
    split, loaded once for the stages of :func:`_eval_stages` (dropped after the ``last``)."""
    from .evaluation import EvalConfig

    views = stage_views(cfg, key)
    ev_dir = Path(cfg.out) / f"eval_{key}"
    ecfg = EvalConfig(tree=str(tree), data=cfg.train.data, format=cfg.format,
                      downscale=cfg.downscale, limit=views or None, spread=True,
                      out=str(ev_dir), backend=cfg.backend, device=cfg.device,
                      show_progress=bool(cfg.show_progress), save_images=(key == "ft"))
    settings = {**common, "views": views, **({"spread": True} if views else {})}

    def score() -> dict:
        from .evaluation import eval_dataset, eval_tree_file

        try:
            if views not in shared:
                shared[views] = eval_dataset(ecfg)
            return eval_tree_file(ecfg, shared[views])
        finally:
            if last:
                shared.clear()

    return Stage(f"eval_{key}", settings, [tree], [ev_dir / "eval.json"], score,
                 "check the tree file")


def _web(cfg: PipelineConfig, lay: RunLayout) -> None:
    """The static web-viewer bundle, with the training cameras (NDC scenes: + the NDC one)."""
    from .datasets import load_cameras
    from .viewer.export import export_web

    train = load_cameras(cfg.train.data, split="train", format=cfg.format)
    export_web(lay.compressed, Path(cfg.out) / "web", overwrite=True, cameras=train.cameras,
               camera_names=train.names, background=train.background)


def _video_stage(cfg: PipelineConfig, lay: RunLayout, common: dict) -> Stage:
    """The orbit video of the fine-tuned tree."""
    from .video import VideoConfig

    size = cfg.video_size or None
    out = Path(cfg.out) / "orbit.mp4"
    vcfg = VideoConfig(tree=str(lay.ft), out=str(out), data=cfg.train.data, format=cfg.format,
                       downscale=cfg.downscale, frames=cfg.video_frames, width=size, height=size,
                       backend=cfg.backend, device=cfg.device, show_progress=cfg.show_progress)
    return Stage("video", {**common, "frames": cfg.video_frames, "size": cfg.video_size},
                 [lay.ft], [out], lambda: _call("video", "make_video", vcfg),
                 "check the tree file")
