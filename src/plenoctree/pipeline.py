"""The whole chain as a resumable pipeline: photos → NeRF-SH → octree → fine-tuned → compressed.

``plenoctree run --data DIR --out DIR`` and ``plenoctree demo`` call :func:`run_pipeline`.
Each stage writes its artefact atomically and records a stamp (its settings plus the size and
modification time of its inputs) in ``OUT/.stages/``; a stage whose artefact exists with an
unchanged stamp is skipped, so a run killed at any point continues where it stopped (the
trainer and the fine-tuner also resume mid-stage from their checkpoints). A failing stage stops
the run with a :class:`PipelineError` naming the stage; finished artefacts are kept.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from ._config import apply
from ._util import atomic_save_json, atomic_write, check_output_dir, run_lock
from .errors import ConfigError, PlenOctreeError
from .optim.finetuning import DEFAULT_EPOCHS

__all__ = ["PipelineConfig", "PipelineError", "run_pipeline", "STAGES", "PRESETS",
           "pipeline_preset", "check_extras"]

STAGES = ("train", "nerf_eval", "extract", "refine", "finetune", "eval", "compress", "web",
          "video")


class PipelineError(PlenOctreeError, RuntimeError):
    """A pipeline stage failed; the message names the stage and what to do."""


@dataclass
class PipelineConfig:
    """Settings of ``plenoctree run`` (and of the demo, which fills them for its scene)."""

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
    downscale: int = 1
    """integer area downscale of the images for every stage (2 = lego at 400²)"""
    preset: str = "cpu"
    """NeRF-SH training preset: cpu or paper"""
    train_minutes: float = 30.0
    """NeRF-SH training budget in minutes (0 = the preset's step count)"""
    train_steps: int = 0
    """NeRF-SH training steps (0 = the preset's)"""
    grid: int = 256
    """octree finest resolution at extraction (power of two)"""
    samples: int = 8
    """random samples averaged per leaf at extraction"""
    weight_thresh: float = 0.001
    """visibility threshold τ_w on the maximum ray weight of a voxel"""
    refine_passes: int = 1
    """adaptive refinement passes after extraction: subdivide leaves where the NeRF-SH varies
    inside them (0 = off; see `plenoctree refine`)"""
    refine_threshold: float = 0.1
    """refinement: subdivide leaves whose sample spread is at least this (pixel units)"""
    finetune_epochs: int = DEFAULT_EPOCHS
    """maximum fine-tuning epochs (the learning rate backs off on a validation drop)"""
    finetune_lr: float | None = None
    """fine-tuning learning rate (default: the fine-tuner's, Adam 2e-2)"""
    compress_bits: int = 16
    """median-cut codebook bits per SH basis"""
    eval_views: int = 0
    """test views scored per stage, evenly spaced over the split (0 = all)"""
    nerf_eval_views: int = 2
    """test views rendered with the NeRF-SH for its PSNR and speed baseline (0 = skip)"""
    video_frames: int = 60
    """frames of the orbit video (0 = no video)"""
    video_size: int = 0
    """orbit video width/height in pixels (0 = the dataset's)"""
    web: bool = True
    """export the static web-viewer bundle"""
    backend: str = "auto"
    """renderer backend: auto, numba, triton or torch"""
    device: str = "auto"
    """device of every stage: auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N"""
    seed: int = 0
    """random seed of training and fine-tuning"""
    extra: dict = field(default_factory=dict)
    """stage overrides: {"train": {...TrainConfig fields, "model": {...}}, "extract": {...},
    "finetune": {...}, "process": {...ProcessConfig fields, "sfm": {...}}} (the CLI's --train.*,
    --extract.*, --finetune.*, --process.* flags)"""


STAGE_OPTIONS = ("process", "train", "extract", "refine", "finetune")
"""Stages whose every config field ``extra`` may set (``plenoctree run --<stage>.<field>``)."""

PRESETS: dict[str, dict[str, Any]] = {
    "cpu": {},
    "paper": {"preset": "paper", "train_minutes": 0.0, "grid": 512, "samples": 256,
              "extra": {"extract": {"bbox_scale": 1.1}}},
    "quick": {"train_minutes": 3.0, "grid": 128, "samples": 4, "finetune_epochs": 2,
              "nerf_eval_views": 1, "eval_views": 5, "video_frames": 0},
}
"""Settings of ``plenoctree run --preset NAME`` over the :class:`PipelineConfig` defaults:
``cpu`` (the defaults: cpu NeRF-SH preset, 256³), ``paper`` (the paper's NeRF-SH, 512³,
256 samples per voxel; for GPUs), ``quick`` (a few minutes end to end, to try a dataset)."""


def pipeline_preset(name: str) -> PipelineConfig:
    """A fresh :class:`PipelineConfig` of preset ``name`` (see :data:`PRESETS`)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown run preset {name!r}; choose one of {sorted(PRESETS)}")
    import copy

    return apply(PipelineConfig(), copy.deepcopy(PRESETS[name]), where=f"preset {name}")


def _check_extra(extra: dict) -> None:
    unknown = sorted(set(extra) - set(STAGE_OPTIONS))
    if unknown:
        raise ConfigError(f"stage overrides for {unknown}: only {', '.join(STAGE_OPTIONS)} "
                          "take options")


def check_extras(cfg: PipelineConfig) -> None:
    """Fail at the start, with the install hint, when a stage needs a missing optional
    package (the orbit video needs ``plenoctree[video]``)."""
    import importlib.util

    if cfg.video_frames > 0:
        missing = [m for m in ("imageio", "imageio_ffmpeg") if importlib.util.find_spec(m) is None]
        if missing:
            raise ConfigError(f"the video stage needs {' and '.join(missing)} (not installed): "
                              "pip install 'plenoctree[video]', or pass --video-frames 0")


def _fingerprint(paths: list[Path]) -> dict:
    out = {}
    for p in paths:
        try:
            st = p.stat()
            out[str(p)] = [st.st_size, st.st_mtime_ns] if p.is_file() else "dir"
        except OSError:
            out[str(p)] = None
    return out


class _Runner:
    """Runs stages with stamps, timing and uniform error reporting."""

    def __init__(self, out: Path, log: Callable[[str], None]):
        self.out, self.log = out, log
        self.stamps = out / ".stages"
        self.times: dict[str, float] = {}
        self.peaks: dict[str, float] = {}     # peak RSS (MB) of each stage
        self.cpu: dict[str, float] = {}       # CPU seconds of each stage (all threads)
        self.skipped: list[str] = []
        self.given_stages: list[str] = []     # artefacts given, not made by this pipeline

    def stage(self, name: str, settings: dict, inputs: list[Path], outputs: list[Path],
              fn: Callable[[], Any], hint: str) -> bool:
        """Run ``fn`` unless its outputs exist with the same stamp. Returns True if it ran."""
        stamp = {"settings": settings, "inputs": _fingerprint(inputs)}
        stamp = json.loads(json.dumps(stamp, default=str))
        path = self.stamps / f"{name}.json"
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError):
            old = None
        if old is not None and old.get("stamp") == stamp and all(p.exists() for p in outputs):
            self.log(f"[{name}] up to date, skipped")
            self.times[name] = float(old.get("seconds", 0.0))
            if old.get("peak_rss_mb") is not None:
                self.peaks[name] = float(old["peak_rss_mb"])
            if old.get("cpu_seconds") is not None:
                self.cpu[name] = float(old["cpu_seconds"])
            self.skipped.append(name)
            return False
        self.log(f"[{name}] running")
        from .convert.memory import StageMonitor

        mon = StageMonitor()
        t0, c0 = time.perf_counter(), _cpu_seconds()
        try:
            with mon.stage(name):
                fn()
        except PlenOctreeError as e:
            raise PipelineError(
                f"stage '{name}' failed: {e}\n  finished artefacts are kept in {self.out}; "
                f"{hint}, then rerun the same command to resume") from e
        except KeyboardInterrupt:
            self.log(f"[{name}] interrupted; rerun the same command to resume")
            raise
        seconds = time.perf_counter() - t0
        self.times[name] = seconds
        self.cpu[name] = _cpu_seconds() - c0
        self.peaks[name] = float(mon.to_json()[name]["peak_rss_mb"])
        atomic_save_json(path, {"stamp": stamp, "seconds": seconds,
                                "cpu_seconds": self.cpu[name],
                                "peak_rss_mb": self.peaks[name]})
        self.log(f"[{name}] done in {seconds:.1f} s")
        return True

    def given(self, name: str, seconds: float | None) -> None:
        """Record a stage not run here (its artefact was given); ``seconds`` as reported."""
        if seconds is not None:
            self.times[name] = float(seconds)
        self.skipped.append(name)
        self.given_stages.append(name)


def _cpu_seconds() -> float:
    """CPU seconds used so far by this process (all threads) and its waited-for children."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _given_nerf(path: str) -> Path:
    """The run folder of ``--nerf`` (a folder holding the checkpoint, or the checkpoint file)."""
    from .nerf.checkpoint import CHECKPOINT_NAME

    p = Path(path)
    if p.is_file() and p.name == CHECKPOINT_NAME:
        p = p.parent
    if not (p / CHECKPOINT_NAME).is_file():
        raise ConfigError(f"--nerf {path}: no {CHECKPOINT_NAME} there (give the run folder of a "
                          "trained NeRF-SH, e.g. the OUT/nerf of an earlier run)")
    return p


@dataclass(frozen=True)
class RunLayout:
    """Where :func:`run_pipeline` writes (and a reader of its output finds) each artefact."""

    nerf: Path          # the NeRF-SH run folder (``OUT/nerf``, or the ``--nerf`` given)
    tree: Path          # extracted octree
    refined: Path       # adaptively refined octree (when ``refine_passes``)
    ft: Path            # fine-tuned octree
    compressed: Path    # its ``.plnz``
    summary: Path       # ``summary.json``


def run_layout(out: Any, nerf: str = "") -> RunLayout:
    """The artefact paths of a run into ``out`` (``nerf``: the ``--nerf`` it was given, checked
    to hold a checkpoint)."""
    out = Path(out)
    return RunLayout(_given_nerf(nerf) if nerf else out / "nerf", out / "tree.npz",
                     out / "tree_refined.npz", out / "tree_ft.npz", out / "tree_ft.plnz",
                     out / "summary.json")


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def run_pipeline(cfg: PipelineConfig, log: Callable[[str], None] = print) -> dict:
    """Run (or resume) the whole chain; returns the summary also written to ``summary.json``.

    Artefacts in ``cfg.out``: ``nerf/`` (run directory), ``nerf_eval.json``, ``tree.npz`` (raw
    extracted octree), ``tree_refined.npz`` (adaptively refined, when ``refine_passes``),
    ``tree_ft.npz`` (fine-tuned, with ``tree_ft.log.jsonl``), ``tree_ft.plnz`` (compressed),
    ``eval_{raw,refined,ft,compressed}/eval.json`` (the fine-tuned tree's renders and depth maps in
    ``eval_ft/renders/``), ``web/`` (viewer bundle), ``orbit.mp4``,
    ``summary.json`` and ``summary.md``.
    """
    if not (cfg.data or cfg.images) or not cfg.out:
        raise ConfigError("--out and one of --data / --images are needed")
    if cfg.data and cfg.images:
        raise ConfigError("give either --data (a dataset) or --images (photos / a video), not both")
    out = check_output_dir(cfg.out)
    check_extras(cfg)
    out.mkdir(parents=True, exist_ok=True)
    with run_lock(out, "run"):      # a second run / resume into OUT fails naming the holder
        return _run_pipeline(cfg, out, log)


def _run_pipeline(cfg: PipelineConfig, out: Path, log: Callable[[str], None]) -> dict:
    atomic_save_json(out / "config.json", _config_dict(cfg))   # `run --config` reads it back
    r = _Runner(out, log)
    _check_extra(cfg.extra)
    # 0. camera poses of the user's photos / video (plenoctree.process) into OUT/data: its
    # options are checked now, the stage runs once every other stage's options are checked.
    if cfg.extra.get("process") and not cfg.images:
        raise ConfigError("--process.* options apply to --images (photos or a video), not --data")
    pcfg = _process_config(cfg, out) if cfg.images else None
    data = Path(pcfg.out) if pcfg else Path(cfg.data)
    if pcfg is None and not data.exists():
        raise ConfigError(f"{data}: dataset folder does not exist")
    common = {"data": str(data.resolve()), "format": cfg.format, "downscale": cfg.downscale}
    lay = run_layout(out, cfg.nerf)
    run_dir, tree_raw, tree_ft, tree_c = lay.nerf, lay.tree, lay.ft, lay.compressed

    # 1. NeRF-SH training (resumes from its checkpoint when a previous run was cut short).
    from .nerf.checkpoint import CHECKPOINT_NAME
    from .nerf.config import preset as train_preset

    tcfg = train_preset(cfg.preset)
    tcfg.data, tcfg.out, tcfg.downscale, tcfg.seed = str(data), str(run_dir), cfg.downscale, cfg.seed
    tcfg.minutes, tcfg.format = cfg.train_minutes, cfg.format
    tcfg.device = cfg.device
    if cfg.train_steps:
        tcfg.max_steps = cfg.train_steps
    elif cfg.train_minutes:
        tcfg.max_steps = 10**9  # the time budget decides
    apply(tcfg, cfg.extra.get("train", {}), where="--train")

    from .nerf.config import validate

    validate(tcfg)

    # Every stage's options are checked now, not after the training (which takes minutes).
    from .convert.extraction import ExtractConfig, extract

    ecfg = ExtractConfig(run_dir=str(run_dir), out=str(tree_raw), data=str(data), grid=cfg.grid,
                         samples=cfg.samples, weight_thresh=cfg.weight_thresh, eval=False,
                         precision="fp32", backend=cfg.backend, device=cfg.device,
                         seed=cfg.seed)
    apply(ecfg, cfg.extra.get("extract", {}), where="--extract")
    from .optim.finetuning import FinetuneConfig, finetune

    tree_in, rcfg = tree_raw, None
    if cfg.refine_passes > 0:
        from .convert.refine import RefineConfig, refine

        tree_in = lay.refined
        rcfg = RefineConfig(tree=str(tree_raw), run_dir=str(run_dir), out=str(tree_in),
                            passes=cfg.refine_passes, threshold=cfg.refine_threshold,
                            data=str(data), seed=cfg.seed, show_progress=False,
                            averaging=ecfg.averaging)     # new leaves valued as extracted
        apply(rcfg, cfg.extra.get("refine", {}), where="--refine")
        rcfg.validated()
    fcfg = FinetuneConfig(tree=str(tree_in), data=str(data), out=str(tree_ft),
                          epochs=cfg.finetune_epochs, lr=cfg.finetune_lr,
                          downscale=cfg.downscale, precision="fp32", backend=cfg.backend,
                          device=cfg.device,
                          seed=cfg.seed, resume=True, test_views=-1, verbose=False)
    apply(fcfg, cfg.extra.get("finetune", {}), where="--finetune")
    from .convert.extraction import _validate as validate_extract

    validate_extract(ecfg)
    fcfg.validated()
    from .compression import CompressOptions

    CompressOptions(bits=cfg.compress_bits).validated()
    if pcfg is not None:
        _process_stage(pcfg, r, log)

    def do_train():
        from .nerf.trainer import train

        resume = (run_dir / CHECKPOINT_NAME).exists()
        if resume:
            log(f"[train] resuming {run_dir}")
        train(tcfg, resume=resume)

    if cfg.nerf:          # a trained NeRF-SH: its training time is read from its summary
        log(f"[train] using the trained NeRF-SH {run_dir} (not trained here)")
        r.given("train", _read_json(run_dir / "summary.json").get("train_time_s"))
    else:
        r.stage("train", {**common, "train": _config_dict(tcfg)}, [],
                [run_dir / CHECKPOINT_NAME], do_train, "check the dataset and training options")

    # 2. NeRF-SH baseline on a few test views: PSNR and seconds per frame.
    nerf_json = out / "nerf_eval.json"
    if cfg.nerf_eval_views > 0:
        def do_nerf_eval():
            from .nerf.evaluate import render_nerf_views

            res = render_nerf_views(run_dir, split="test", views=cfg.nerf_eval_views,
                                    data=str(data), downscale=cfg.downscale,
                                    out=out / "nerf_eval")
            atomic_save_json(nerf_json, res)

        r.stage("nerf_eval", {"views": cfg.nerf_eval_views, **common},
                [run_dir / CHECKPOINT_NAME], [nerf_json], do_nerf_eval,
                "check the training run")

    # 3. Conversion to an octree.
    r.stage("extract", _config_dict(ecfg), [run_dir / CHECKPOINT_NAME], [tree_raw],
            lambda: extract(ecfg), "change the extraction options (--grid, --weight-thresh)")

    # 4. Adaptive refinement against the NeRF-SH.
    if rcfg is not None:
        r.stage("refine", _config_dict(rcfg), [tree_raw, run_dir / CHECKPOINT_NAME], [tree_in],
                lambda: refine(rcfg, log=lambda *_: None),
                "lower --refine-passes or raise --refine-threshold")

    # 5. Fine-tuning of the leaf values on the training photos.
    ft_settings = {k: v for k, v in _config_dict(fcfg).items()
                   if k not in ("resume", "verbose", "show_progress")}
    r.stage("finetune", ft_settings, [tree_in], [tree_ft], lambda: finetune(fcfg),
            "lower --finetune-lr or --finetune-epochs")

    # 6. Compression (median cut + DEFLATE).
    def do_compress():
        from .compression import CompressOptions, compress, save_compressed
        from .octree import load_tree

        save_compressed(compress(load_tree(tree_ft), CompressOptions(bits=cfg.compress_bits)),
                        tree_c)

    r.stage("compress", {"bits": cfg.compress_bits}, [tree_ft], [tree_c], do_compress,
            "try fewer --compress-bits")

    # 7. Scores of every octree stage on the test split (PSNR, SSIM, FPS, MB).
    from .evaluation import EvalConfig, eval_tree_file

    evals = {}
    stages = [("raw", tree_raw)] + ([("refined", tree_in)] if tree_in != tree_raw else []) + [
        ("ft", tree_ft), ("compressed", tree_c)]
    for key, path in stages:
        ev_dir = out / f"eval_{key}"
        ecfg_ = EvalConfig(tree=str(path), data=str(data), format=cfg.format,
                           downscale=cfg.downscale, limit=cfg.eval_views or None, spread=True,
                           out=str(ev_dir),
                           backend=cfg.backend, device=cfg.device, show_progress=False,
                           save_images=(key == "ft"))
        r.stage(f"eval_{key}", {**common, "views": cfg.eval_views,
                                **({"spread": True} if cfg.eval_views else {})}, [path],
                [ev_dir / "eval.json"], lambda c=ecfg_: eval_tree_file(c, log=lambda *_: None),
                "check the tree file")
        evals[key] = _read_json(ev_dir / "eval.json")

    # 8. Static web-viewer bundle and orbit video.
    if cfg.web:
        def do_web():
            from .datasets import load_cameras
            from .viewer.export import export_web

            train = load_cameras(data, split="train", format=cfg.format)
            export_web(tree_c, out / "web", overwrite=True, cameras=train.cameras,
                       camera_names=train.names)        # (NDC scenes: + the NDC camera)

        r.stage("web", {"cameras": 2}, [tree_c], [out / "web" / "index.html"], do_web,
                "use `plenoctree lod` to make a smaller tree")
    if cfg.video_frames > 0:
        def do_video():
            from .video import VideoConfig, make_video

            size = cfg.video_size or None
            make_video(VideoConfig(tree=str(tree_ft), out=str(out / "orbit.mp4"), data=str(data),
                                   format=cfg.format, downscale=cfg.downscale,
                                   frames=cfg.video_frames, width=size, height=size,
                                   backend=cfg.backend, device=cfg.device),
                       log=lambda *_: None)

        r.stage("video", {**common, "frames": cfg.video_frames, "size": cfg.video_size},
                [tree_ft], [out / "orbit.mp4"], do_video, "check the tree file")

    summary = _summary(cfg, out, r, evals, _read_json(nerf_json),
                       _read_json(run_dir / "summary.json"), _finetune_outcome(tree_ft))
    atomic_save_json(lay.summary, summary)
    from .plots import plot_stages               # PSNR against FPS and MB (needs matplotlib)

    plot_stages(summary["rows"], out / "stages.png", title=f"{Path(cfg.data or cfg.images).name}: stages")
    with atomic_write(out / "summary.md", "w") as f:
        f.write(summary_markdown(summary))
    log("")
    log(summary_markdown(summary))
    return summary


def _process_config(cfg: PipelineConfig, out: Path):
    """The checked :class:`~plenoctree.process.ProcessConfig` of ``run --images`` (its
    ``--process.*`` options; the dataset goes to ``OUT/data``)."""
    from .process import ProcessConfig

    pcfg = ProcessConfig(images=str(cfg.images), out=str(out / "data"), overwrite=True)
    apply(pcfg, cfg.extra.get("process", {}), where="--process")
    if pcfg.images != str(cfg.images) or pcfg.out != str(out / "data"):
        raise ConfigError("--process: images and out are set by run (--images, OUT/data)")
    return pcfg.validated()


def _process_stage(pcfg: Any, r: _Runner, log: Callable) -> None:
    """Run ``process`` into ``OUT/data`` (skipped when the photos and options are unchanged)."""
    from .process import process

    src = Path(pcfg.images)
    inputs = sorted(p for p in src.iterdir() if p.is_file()) if src.is_dir() else [src]
    settings = {**_config_dict(pcfg), "images": str(src.resolve())}
    r.stage("process", settings, inputs, [Path(pcfg.out) / "process.json"],
            lambda: process(pcfg, log=log), "check the photos (see the message), change the "
            "--process.* options, or run `plenoctree process` yourself and pass --data")


def _config_dict(cfg: Any) -> dict:
    d = asdict(cfg)
    return json.loads(json.dumps(d, default=str))


def _finetune_outcome(tree_ft: Path) -> dict:
    """The fine-tuner's ``end`` record (validation before / best, best epoch, why it stopped,
    back-offs) from ``<tree_ft stem>.log.jsonl``; ``{}`` when absent."""
    path = tree_ft.with_name(tree_ft.stem + ".log.jsonl")
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return {}
    for line in reversed(lines):
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if rec.get("event") == "end":
            keys = ("val_psnr_before", "val_psnr_best", "best_epoch", "epochs_run",
                    "stop_reason", "backoffs", "wall_seconds")
            return {k: rec.get(k) for k in keys}
    return {}


def _summary(cfg: PipelineConfig, out: Path, r: _Runner, evals: dict, nerf: dict,
             train_info: dict, ft: dict | None = None) -> dict:
    rows = []
    nerf_mean = nerf.get("mean", {})
    nerf_fps = nerf_mean.get("fps")
    rows.append({"stage": "NeRF-SH", "psnr": nerf_mean.get("psnr"), "ssim": nerf_mean.get("ssim"),
                 "fps": nerf_fps, "mb": nerf.get("model_mb"),
                 "seconds": r.times.get("train"), "cpu_seconds": r.cpu.get("train"),
                 "views": nerf.get("n_views"), "peak_rss_mb": r.peaks.get("train"),
                 "given": bool(cfg.nerf)})
    names = {"raw": "PlenOctree", "refined": "PlenOctree refined",
             "ft": "PlenOctree fine-tuned", "compressed": "compressed"}
    stage_time = {"raw": "extract", "refined": "refine", "ft": "finetune",
                  "compressed": "compress"}
    for key, ev in evals.items():
        mean, tree = ev.get("mean", {}), ev.get("tree", {})
        rows.append({"stage": names[key], "psnr": mean.get("psnr"), "ssim": mean.get("ssim"),
                     "fps": mean.get("fps"), "mb": tree.get("file_mb"),
                     "leaves": tree.get("n_leaves"),
                     "peak_rss_mb": r.peaks.get(stage_time[key]),
                     "seconds": r.times.get(stage_time[key]),
                     "cpu_seconds": r.cpu.get(stage_time[key]),
                     "views": ev.get("dataset", {}).get("n_views")})
    ft_fps = evals.get("ft", {}).get("mean", {}).get("fps")
    speedup = (ft_fps / nerf_fps) if (ft_fps and nerf_fps) else None
    return {"config": _config_dict(cfg), "rows": rows, "times_s": r.times,
            "skipped": r.skipped, "speedup_over_nerf": speedup, "peak_rss_mb": r.peaks,
            "cpu_s": r.cpu,
            "total_s": sum(v for k, v in r.times.items() if v and k not in r.given_stages),
            "given": list(r.given_stages),
            "finetune": _finetune_note(evals, ft or {}),
            "web": str(out / "web") if cfg.web else None,
            "video": str(out / "orbit.mp4") if cfg.video_frames else None,
            "train": train_info, "device": _device_json(cfg.device)}


def _device_json(name: str) -> dict:
    from .device import device_report, resolve_device

    return device_report(resolve_device(name))


def _finetune_note(evals: dict, ft: dict) -> dict:
    """Test-PSNR gain of fine-tuning over its input and, when the input tree was kept, why."""
    def psnr(key):
        return evals.get(key, {}).get("mean", {}).get("psnr")

    start = psnr("refined") if "refined" in evals else psnr("raw")
    after = psnr("ft")
    note = dict(ft)
    note["test_gain_db"] = (after - start) if (after is not None and start is not None) else None
    if ft.get("best_epoch") == 0:
        note["kept_input"] = ("no fine-tuning epoch raised the validation PSNR above the input "
                              f"tree's ({ft.get('stop_reason')}), so the input tree was kept")
    return note


def summary_markdown(summary: dict) -> str:
    """One markdown table: PSNR/SSIM, FPS, MB and time per stage, plus the speed-up."""
    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) else "–"

    lines = ["| stage | test views | PSNR (dB) | SSIM | FPS | leaves | MB | wall (s) | CPU (s) | "
             "peak RSS (MB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in summary["rows"]:
        wall = f(row['seconds'], '.0f') + (" (given run)" if row.get("given") else "")
        lines.append(f"| {row['stage']} | {f(row['views'], 'd')} | {f(row['psnr'], '.2f')} | "
                     f"{f(row['ssim'], '.4f')} | {f(row['fps'], '.3g')} | "
                     f"{f(row.get('leaves'), ',d')} | {f(row['mb'], '.1f')} "
                     f"| {wall} | {f(row.get('cpu_seconds'), '.0f')} "
                     f"| {f(row.get('peak_rss_mb'), '.0f')} |")
    ft = summary.get("finetune") or {}
    if ft:
        lines.append("")
        gain = ft.get("test_gain_db")
        text = f"Fine-tuning: {f(gain, '+.2f')} dB on the test views"
        if ft.get("val_psnr_before") is not None:
            text += (f" (validation {f(ft.get('val_psnr_before'), '.2f')} → "
                     f"{f(ft.get('val_psnr_best'), '.2f')} dB, best epoch "
                     f"{ft.get('best_epoch')} of {ft.get('epochs_run')}, "
                     f"{ft.get('backoffs') or 0} learning-rate back-offs; "
                     f"{ft.get('stop_reason')})")
        lines.append(text + ".")
        if ft.get("kept_input"):
            lines.append(f"The fine-tuned tree is the input tree: {ft['kept_input']}.")
    if summary.get("speedup_over_nerf"):
        lines.append("")
        lines.append(f"Render speed-up of the fine-tuned octree over the NeRF-SH: "
                     f"{summary['speedup_over_nerf']:,.0f}x (same views, same machine)")
    given = " (the given NeRF-SH's training not counted)" if summary.get("given") else ""
    lines.append(f"Total wall time of the stages run: {summary['total_s']:.0f} s{given}")
    return "\n".join(lines) + "\n"
