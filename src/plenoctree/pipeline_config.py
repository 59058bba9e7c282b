"""The settings of the pipeline: :class:`PipelineConfig` (pipeline-wide settings plus one typed
config per stage), its presets, and how ``run`` exposes each stage as ``--<stage>.*`` flags.

Each setting has one place: the stage configs' paths between the stages and their copies of
pipeline-wide settings (``train.seed`` ← ``seed``) are set by :func:`wired`, never given.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ._config import apply, flag_name, spell_flags
from .compression.codec import CompressOptions
from .convert.extraction import ExtractConfig
from .convert.refine import RefineConfig
from .errors import ConfigError
from .nerf.config import TrainConfig
from .optim.finetuning import FinetuneConfig
from .process import ProcessConfig

__all__ = ["PipelineConfig", "StageOptions", "STAGE_OPTIONS", "PRESETS", "UNLIMITED_STEPS",
           "pipeline_preset", "train_preset", "time_budget", "layer_settings", "wired",
           "stage_flags", "name_the_flags", "nerf_run_dir", "working_downscale",
           "WORKING_PIXELS", "RunLayout", "artefact_layout", "AUTO_PASSES",
           "scene_refine_passes", "AUTO_MINUTES", "scene_train_minutes", "stage_views"]

UNLIMITED_STEPS = 10**9
"""``train.max_steps`` when the time budget (``train.minutes``) decides."""
WORKING_PIXELS = {("forward", "cpu"): 200_000, ("360", "cpu"): 250_000,
                  ("forward", "gpu"): 800_000, ("360", "gpu"): 1_000_000}
"""Pixels per image that ``run`` works at when ``--downscale`` is not given, by capture kind
and device: on a CPU, LLFF's forward-facing convention (504x378, NeRF's flower) and about
lego's 400² for 360° captures, which keep a CPU budget's training, fine-tuning epochs and the
evaluation frames within the CPU budget; on a GPU LLFF's factor 4 (1008x756) and lego's
800²."""


#: ``run``'s ``--refine.passes`` default: decided by the capture (:func:`scene_refine_passes`).
AUTO_PASSES = -1


def scene_refine_passes(passes: int, forward: bool) -> int:
    """``run``'s refinement passes: ``passes``, or for :data:`AUTO_PASSES` one pass for a 360°
    capture and none for a forward-facing one, whose extraction grid is already finer across
    the image than one pass makes 256³ (``convert.extraction.NDC_GRID``; flower: 29.56 dB with
    2.55 M leaves against 29.34 with 3.45 M, docs/capture.md)."""
    return int(passes) if passes != AUTO_PASSES else (0 if forward else 1)


def working_downscale(width: int, height: int, forward: bool, gpu: bool,
                      loads: Callable[[int], bool] | None = None) -> int:
    """The downscale of ``run`` for ``width x height`` photos: the smallest factor bringing
    them to at most :data:`WORKING_PIXELS` for the capture kind (``forward``: NDC) and device
    with which the dataset ``loads`` (default: the factor divides both sides, as the loaders'
    area downscale needs), searched up to twice that; else the largest factor below it that
    divides both sides. 1 for small images. E.g. 4032x3024 forward-facing on a CPU: 8
    (504x378); 1080x1920 360° on a CPU: 3 (360x640)."""
    target = WORKING_PIXELS["forward" if forward else "360", "gpu" if gpu else "cpu"]
    factor = max(1, math.ceil(math.sqrt(width * height / target) - 1e-9))
    if factor == 1:
        return 1
    loads = loads or (lambda f: width % f == 0 and height % f == 0)
    return next((f for f in range(factor, 2 * factor + 1) if loads(f)),
                max(d for d in range(1, factor) if width % d == 0 and height % d == 0))


#: ``run``'s ``--train.minutes`` default: decided by the capture (:func:`scene_train_minutes`).
AUTO_MINUTES = -1.0


def scene_train_minutes(minutes: float, forward: bool) -> float:
    """``run``'s NeRF-SH budget: ``minutes``, or for :data:`AUTO_MINUTES` 15 minutes for a
    forward-facing capture and 30 for a 360° one: where more minutes stop paying on the
    time-quality frontier (docs/capture_records.md "The whole flower frontier with the faster
    decay"). On flower's photos (2 cores) the NeRF-SH's held-out validation levels off at
    ~29.6 dB from ~4,000 steps (~13 minutes) whatever the budget, and the chains give 29.58 dB
    in 20.3 minutes at 15, 29.48 in 24.4 at 20, 29.29 in 34.3 at 30; on lego 400² more minutes
    keep paying up to 30 (31.52 dB at 5, 32.88 at 20, 33.51 at 30 on the 200 test views)."""
    if minutes != AUTO_MINUTES:
        return float(minutes)
    return 15.0 if forward else 30.0


QUICK_RUN_MINUTES = 10.0
"""The ``quick`` preset of ``run``: the whole run within 10 minutes (``PipelineConfig.minutes``),
the 10-minute point of the time-quality frontier (docs/capture_records.md)."""

QUICK_MINUTES = 10.0
"""NeRF-SH budget of ``plenoctree train --preset quick`` (``run --preset quick`` budgets the
whole run instead, :data:`QUICK_RUN_MINUTES`): on flower's photos a 10-minute NeRF-SH gave
29.35 dB compressed in 13.9 minutes of ``run --images`` against 29.58 in 20.3 at the
forward-facing default of 15 (:func:`scene_train_minutes`; docs/capture_records.md "The whole
flower frontier with the faster decay")."""


def train_preset(name: str) -> TrainConfig:
    """The NeRF-SH training settings of preset ``name``: ``cpu``, ``gpu`` and ``paper`` (the
    trainer's presets) or ``quick`` (cpu with a :data:`QUICK_MINUTES` budget). ``plenoctree
    train --preset`` and ``run --preset`` take the same names (``run``'s ``quick`` trains for
    what its whole-run budget leaves)."""
    from .nerf.config import preset

    if name == "quick":
        return dataclasses.replace(preset("cpu"), minutes=QUICK_MINUTES,
                                   max_steps=UNLIMITED_STEPS)
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return preset(name)


def _run_train() -> TrainConfig:
    """``run``'s default training: the cpu preset for the capture's budget
    (:func:`scene_train_minutes`; the budget decides, not a step count)."""
    return dataclasses.replace(train_preset("cpu"), minutes=AUTO_MINUTES,
                               max_steps=UNLIMITED_STEPS)


@dataclass
class PipelineConfig:
    """Settings of ``plenoctree run`` (and of the demo, which fills them for its scene).

    The stage configs' paths between the stages (``extract.run_dir``, ``finetune.tree``...)
    and the fields that copy a pipeline-wide setting (``train.seed`` ← ``seed``...) are set by
    the pipeline (:func:`wired`, :data:`STAGE_OPTIONS`); ``config.json`` shows them as run.
    """

    data: str = ""
    """dataset folder (any supported format)"""
    images: str = ""
    """your photos (a folder) or a video instead of --data: the first stage, `process`
    (COLMAP poses), writes the dataset OUT/data"""
    out: str = ""
    """output folder: every artefact of the chain goes there"""
    format: str | None = None
    """dataset format (default: detected from the folder)"""
    nerf: str = ""
    """a trained NeRF-SH (run folder holding checkpoint.pt, or the checkpoint) to start from:
    the train stage is skipped and the folder is only read"""
    downscale: int = 0
    """integer area downscale of the images for every stage (2 = lego at 400²); 0 = the
    working resolution for the capture kind and device (forward-facing ~0.2 MP, 360° ~0.25 MP
    on a CPU; 4x that on a GPU)"""
    backend: str = "auto"
    """renderer backend: auto, numba, triton or torch"""
    device: str = "auto"
    """device of every stage but refinement (--refine.device): auto (CUDA when a GPU is
    present, else cpu), cpu, cuda or cuda:N"""
    threads: int = 0
    """CPU threads of training and extraction (0 = all)"""
    seed: int = 0
    """random seed of training, extraction, refinement and fine-tuning"""
    show_progress: bool | None = None
    """progress bars of the stages (default: training, extraction and fine-tuning when stderr
    is a terminal)"""
    eval_views: int = 0
    """test views the chain's result (the compressed tree) is scored on, evenly spaced over
    the split (0 = all)"""
    stage_eval_views: int = 25
    """test views the trees before it (raw, refined, fine-tuned) are scored on, evenly spaced
    (0 = as many as the result; never more): enough to follow the stages, without scoring
    lego's 200 views four times (~45 s a tree on 2 cores)"""
    nerf_eval_views: int = 5
    """test views rendered with the NeRF-SH for its PSNR and speed baseline, evenly spaced
    (0 = all, -1 = skip; 5 = all of an LLFF capture's held-out photos)"""
    video_frames: int = 60
    """frames of the orbit video (0 = no video)"""
    video_size: int = 0
    """orbit video width/height in pixels (0 = the dataset's)"""
    web: bool = True
    """export the static web-viewer bundle"""
    minutes: float = 0.0
    """wall-time budget of the whole run in minutes, from the command's start (0 = none):
    the NeRF-SH trains for what the other stages leave (--train.minutes decides instead when
    given) and fine-tuning stops its epochs in time for the stages after it; stages an
    earlier run into OUT finished, and this run skips, count with their time"""
    process: ProcessConfig = field(default_factory=lambda: ProcessConfig(overwrite=True))
    """camera poses of --images (`plenoctree process`)"""
    train: TrainConfig = field(default_factory=_run_train)
    """NeRF-SH training (`plenoctree train`; --train.minutes -1 = by capture: 15 for a
    forward-facing one, 30 for a 360° one, :func:`scene_train_minutes`)"""
    extract: ExtractConfig = field(default_factory=lambda: ExtractConfig(eval=False))
    """octree extraction (`plenoctree extract`)"""
    refine: RefineConfig = field(default_factory=lambda: RefineConfig(passes=AUTO_PASSES))
    """adaptive refinement (`plenoctree refine`; --refine.passes 0 = off, -1 = by capture:
    :func:`scene_refine_passes`)"""
    finetune: FinetuneConfig = field(default_factory=lambda: FinetuneConfig(
        precision="fp32", test_views=-1, resume=True, verbose=False))
    """fine-tuning (`plenoctree finetune`)"""
    compress: CompressOptions = field(default_factory=CompressOptions)
    """compression of the fine-tuned tree (`plenoctree compress`)"""


@dataclass(frozen=True)
class StageOptions:
    """How one stage config of :class:`PipelineConfig` becomes ``run``'s ``--<name>.*`` flags."""

    name: str
    """the field of :class:`PipelineConfig` and the flag prefix"""
    wired: tuple[str, ...]
    """fields set by the pipeline (paths, copies of pipeline-wide settings) or by ``--preset``
    (``train.preset``): no flag"""
    title: str
    """the help section"""
    flat: tuple[str, ...] = ()
    """nested config fields whose own fields are flags under the same prefix (train.model)"""


STAGE_OPTIONS = (
    StageOptions("process", ("images", "out", "overwrite"), "camera poses of --images "
                 "(as `plenoctree process`)", ("sfm",)),
    StageOptions("train", ("data", "out", "preset", "format", "downscale", "device", "threads",
                           "seed"), "NeRF-SH training (as `plenoctree train`)", ("model",)),
    StageOptions("extract", ("run_dir", "out", "data", "eval", "eval_views", "eval_downscale",
                             "eval_out", "backend", "device", "threads", "seed",
                             "show_progress"), "octree extraction (as `plenoctree extract`)"),
    StageOptions("refine", ("tree", "run_dir", "out", "data", "averaging", "eval_views", "seed",
                            "show_progress"), "adaptive refinement (as `plenoctree refine`)"),
    StageOptions("finetune", ("tree", "data", "out", "downscale", "backend", "device", "seed",
                              "test_views", "resume", "verbose", "show_progress", "checkpoint",
                              "log"), "fine-tuning (as `plenoctree finetune`)"),
    StageOptions("compress", (), "compression (as `plenoctree compress`)"),
)
"""The stages whose settings ``run`` exposes as ``--<stage>.<field>`` flags."""


def _preset_paper() -> PipelineConfig:
    cfg = PipelineConfig(train=train_preset("paper"))
    cfg.extract.grid, cfg.extract.samples, cfg.extract.bbox_scale = 512, 256, 1.1
    return cfg


def _preset_quick() -> PipelineConfig:
    # the whole run in QUICK_RUN_MINUTES (the NeRF-SH's budget decided by it); fewer views
    # scored, no video
    return PipelineConfig(minutes=QUICK_RUN_MINUTES, nerf_eval_views=1, eval_views=5,
                          video_frames=0)


def _preset_gpu() -> PipelineConfig:
    return PipelineConfig(train=train_preset("gpu"))


PRESETS: dict[str, Callable[[], PipelineConfig]] = {
    "cpu": PipelineConfig, "paper": _preset_paper, "quick": _preset_quick, "gpu": _preset_gpu}
"""``plenoctree run --preset NAME``: ``cpu`` (the defaults: cpu NeRF-SH preset for 15 minutes
on a forward-facing capture and 30 on a 360° one, 256³), ``gpu`` (the gpu NeRF-SH preset:
fixed-shape steps of 2^18 samples, 20,000 steps, then the cpu pipeline's stages), ``paper``
(the paper's NeRF-SH, 512³, 256 samples per voxel; for GPUs), ``quick`` (the whole run within
:data:`QUICK_RUN_MINUTES` minutes, ``--minutes``; 5 test views scored, no video)."""


def pipeline_preset(name: str) -> PipelineConfig:
    """A fresh :class:`PipelineConfig` of preset ``name`` (see :data:`PRESETS`)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown run preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]()


def time_budget(train: TrainConfig, given: dict) -> None:
    """A training budget given without a step count decides alone: ``minutes > 0`` (or
    :data:`AUTO_MINUTES`, the capture's budget) lifts the step limit, ``minutes == 0`` restores
    the preset's steps (``given``: the values set)."""
    if "minutes" in given and "max_steps" not in given:
        train.max_steps = (UNLIMITED_STEPS if train.minutes > 0 or train.minutes == AUTO_MINUTES
                           else train_preset(train.preset).max_steps)


def layer_settings(cfg: PipelineConfig, values: dict, where: str) -> PipelineConfig:
    """Set ``values`` (nested dicts, e.g. a ``config.json`` or the flags given) on ``cfg``,
    with the training-budget rule of :func:`time_budget`; unknown names raise ConfigError."""
    apply(cfg, values, where=where)
    time_budget(cfg.train, values.get("train") or {})
    return cfg


def nerf_run_dir(nerf: str) -> Path:
    """The run folder of ``--nerf`` (a folder holding the checkpoint, or the checkpoint)."""
    from .nerf.checkpoint import CHECKPOINT_NAME

    p = Path(nerf)
    return p.parent if p.name == CHECKPOINT_NAME and p.is_file() else p


@dataclass(frozen=True)
class RunLayout:
    """Where :func:`~plenoctree.pipeline.run_pipeline` writes (and a reader of its output finds)
    each artefact: the one place for these file names."""

    nerf: Path          # the NeRF-SH run folder (``OUT/nerf``, or the ``--nerf`` given)
    tree: Path          # extracted octree
    refined: Path       # adaptively refined octree (when ``refine.passes``)
    ft: Path            # fine-tuned octree
    compressed: Path    # its ``.plnz``
    summary: Path       # ``summary.json``


def artefact_layout(out: Any, nerf: str = "") -> RunLayout:
    """The artefact paths of a run into ``out`` (``nerf``: the ``--nerf`` it was given; not
    checked here, :func:`~plenoctree.pipeline.run_layout` checks it)."""
    out = Path(out)
    return RunLayout(nerf_run_dir(nerf) if nerf else out / "nerf", out / "tree.npz",
                     out / "tree_refined.npz", out / "tree_ft.npz", out / "tree_ft.plnz",
                     out / "summary.json")


def wired(cfg: PipelineConfig) -> PipelineConfig:
    """A copy of ``cfg`` whose stage configs hold what each stage runs with: the paths between
    the stages and the pipeline-wide settings (the :data:`STAGE_OPTIONS` ``wired`` fields)."""
    c = copy.deepcopy(cfg)
    out = Path(c.out)
    data = str(out / "data") if c.images else c.data
    lay = artefact_layout(out, c.nerf)
    run_dir, tree, refined = str(lay.nerf), str(lay.tree), str(lay.refined)
    shared = {"seed": c.seed, "device": c.device, "backend": c.backend, "threads": c.threads,
              "downscale": c.downscale, "format": c.format}
    paths = {
        "process": {"images": c.images, "out": str(out / "data"), "overwrite": True},
        "train": {"data": data, "out": run_dir},
        "extract": {"run_dir": run_dir, "out": tree, "data": data, "eval": False,
                    "show_progress": c.show_progress},
        "refine": {"tree": tree, "run_dir": run_dir, "out": refined, "data": data,
                   "averaging": c.extract.averaging, "eval_views": 0,
                   "show_progress": bool(c.show_progress)},   # bars only when asked
        "finetune": {"tree": refined if c.refine.passes > 0 else tree, "data": data,
                     "out": str(lay.ft), "test_views": -1, "resume": True,
                     "verbose": False, "show_progress": c.show_progress, "checkpoint": None,
                     "log": None},
    }
    for opt in STAGE_OPTIONS:
        stage_cfg = getattr(c, opt.name)
        for name in opt.wired:
            if name in paths.get(opt.name, {}):
                setattr(stage_cfg, name, paths[opt.name][name])
            elif name in shared:
                setattr(stage_cfg, name, shared[name])
    return c


def stage_flags(opt: StageOptions) -> dict[str, str]:
    """``{field name: flag}`` of one stage's ``run`` flags (``max_steps`` → ``--train.steps``)."""
    cfg = getattr(PipelineConfig(), opt.name)
    flags = {}
    for owner in [cfg] + [getattr(cfg, n) for n in opt.flat]:
        for f in dataclasses.fields(owner):
            if f.name not in opt.wired and f.name not in opt.flat and f.metadata.get("cli", True):
                flags[f.name] = flag_name(f, opt.name + ".")
    return flags


def name_the_flags(opt: StageOptions, message: str) -> str:
    """``message`` with the stage's fields and bare flags spelled as ``run``'s flags
    (``--grid`` / ``finetune: lr_decay must`` → ``--extract.grid`` / ``--finetune.lr-decay
    must``)."""
    flags = stage_flags(opt)
    dashed = {f"--{name.replace('_', '-')}": flag for name, flag in flags.items()}
    dashed.update({flag.replace(f"--{opt.name}.", "--"): flag for flag in flags.values()})
    return spell_flags(message, flags, dashed)


def stage_views(cfg: PipelineConfig, key: str) -> int:
    """Test views tree stage ``key`` is scored on (0 = all): ``eval_views`` for the result
    (the compressed tree), ``stage_eval_views`` (at most as many) for the trees before it."""
    final, inter = cfg.eval_views, cfg.stage_eval_views
    if key == "compressed" or inter == 0:
        return final
    return inter if final == 0 else min(final, inter)
