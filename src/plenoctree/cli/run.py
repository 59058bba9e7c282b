"""``plenoctree run``: the whole chain as a resumable pipeline on any dataset.

Flags: one per :class:`~plenoctree.pipeline.PipelineConfig` field, and every option of the
stages in :data:`~plenoctree.pipeline.STAGE_OPTIONS` as ``--<stage>.<field>``
(``--train.lr-init``, ``--train.net-width``, ``--extract.bbox-scale``,
``--finetune.optimizer``, ``--process.frames`` for ``--images``...), all generated from the config dataclasses. Values layer:
``--preset`` → ``--config FILE`` (e.g. a previous run's ``OUT/config.json``) → flags.
"""

from __future__ import annotations

import argparse

# Stage config fields the pipeline sets itself (paths between the stages).
_STAGE_SKIP = {"train": ("data", "out", "preset", "model"),
               "extract": ("run_dir", "out", "data"),
               "refine": ("tree", "run_dir", "out", "data"),
               "finetune": ("tree", "data", "out"),
               "process": ("images", "out", "overwrite", "sfm")}


def config_from_args(args: argparse.Namespace):
    """The :class:`PipelineConfig`: preset, then ``--config FILE``, then the flags given."""
    from .._config import apply, load_config_file
    from ..pipeline import STAGE_OPTIONS, pipeline_preset
    from ._options import given

    file = load_config_file(args._config_file)
    cfg = pipeline_preset(args.run_preset or "cpu")
    apply(cfg, file, where=str(args._config_file))
    flags = given(args, args._dests)
    stages = {k: flags.pop(k) for k in STAGE_OPTIONS if k in flags}
    apply(cfg, flags, where="run")
    for stage, values in stages.items():
        merged = dict(cfg.extra.get(stage, {}))
        for k, v in values.items():
            if isinstance(v, dict):
                merged[k] = {**merged.get(k, {}), **v}
            else:
                merged[k] = v
        cfg.extra[stage] = merged
    return cfg


def _run(args: argparse.Namespace) -> int:
    from ..pipeline import run_pipeline

    cfg = config_from_args(args)
    if args.print_config:
        from .._config import config_dict
        import json

        print(json.dumps(config_dict(cfg), indent=2))
        return 0
    summary = run_pipeline(cfg)
    if summary.get("web"):
        print(f"open the viewer: plenoctree view {cfg.out}/tree_ft.plnz")
    return 0


def add_stage_flags(p: argparse.ArgumentParser) -> list[str]:
    """``--<stage>.<field>`` for every field of the stage configs; returns the dests."""
    from ..convert.extraction import ExtractConfig
    from ..nerf.config import ModelConfig, TrainConfig, preset
    from ..optim.finetuning import FinetuneConfig
    from ._options import add_config

    dests = add_config(p, TrainConfig, prefix="train.", shown=preset("cpu"),
                       skip=_STAGE_SKIP["train"], title="training stage (--train.*)")
    dests += add_config(p, ModelConfig, prefix="train.", dest_prefix="train.model.",
                        title="network of the training stage (--train.*)")
    dests += add_config(p, ExtractConfig, prefix="extract.", skip=_STAGE_SKIP["extract"],
                        title="extraction stage (--extract.*)")
    from ..convert.refine import RefineConfig

    dests += add_config(p, RefineConfig, prefix="refine.", skip=_STAGE_SKIP["refine"],
                        title="refinement stage (--refine.*)")
    dests += add_config(p, FinetuneConfig, prefix="finetune.", skip=_STAGE_SKIP["finetune"],
                        title="fine-tuning stage (--finetune.*)")
    from ..process import ProcessConfig, SfmOptions

    dests += add_config(p, ProcessConfig, prefix="process.", skip=_STAGE_SKIP["process"],
                        title="camera poses of --images (--process.*, as `plenoctree "
                              "process`'s options)", choices={"scene": ("auto", "360", "forward")})
    dests += add_config(p, SfmOptions, prefix="process.", dest_prefix="process.sfm.",
                        title="COLMAP options of --images (--process.*)")
    return dests


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``run`` command."""
    from ..datasets.dataset import FORMATS
    from ..pipeline import PRESETS, PipelineConfig
    from ._options import add_config, add_config_file

    p = sub.add_parser(
        "run", help="photos -> NeRF-SH -> octree -> fine-tuned -> compressed + viewer (resumable)",
        usage="plenoctree run --data DIR --out DIR [--preset NAME] [--config FILE] [options]",
        description="Run the whole chain on a dataset. Each stage writes its artefact "
                    "atomically and is skipped when its artefact and settings are unchanged, "
                    "so a killed run continues where it stopped. Every stage option is a flag "
                    "(--train.*, --extract.*, --finetune.*); the options used are saved in "
                    "OUT/config.json (reuse them with --config).")
    p.add_argument("--preset", dest="run_preset", choices=sorted(PRESETS), default=None,
                   help="settings to start from: cpu (default), paper (the paper's NeRF-SH "
                        "and 512^3; for GPUs) or quick (a few minutes end to end)")
    add_config_file(p)
    p.add_argument("--print-config", action="store_true",
                   help="print the resolved configuration as JSON and exit")
    dests = add_config(p, PipelineConfig, skip=("extra", "preset"),
                       title="pipeline (PipelineConfig)", choices={"format": FORMATS})
    dests += add_stage_flags(p)
    p.set_defaults(func=_run, _dests=dests)
