"""``plenoctree run``: the whole chain as a resumable pipeline on any dataset.

Flags: one per pipeline-wide :class:`~plenoctree.pipeline.PipelineConfig` field, and every
stage option as ``--<stage>.<field>`` (``--train.lr-init``, ``--extract.bbox-scale``,
``--finetune.epochs``, ``--process.frames`` for ``--images``...), shown by ``--help-all`` or
``--help-stage STAGE``; all generated from the config dataclasses, one flag per setting.
Values layer: ``--preset`` → ``--config FILE`` (e.g. a previous run's ``OUT/config.json``)
→ flags.
"""

from __future__ import annotations

import argparse
from typing import Any


def config_from_args(args: argparse.Namespace):
    """The :class:`PipelineConfig`: preset, then ``--config FILE``, then the flags given."""
    from ..pipeline import layer_settings, pipeline_preset
    from ._options import layered

    return layered(args, pipeline_preset(args.run_preset or "cpu"), "run", layer_settings)


def _run(args: argparse.Namespace) -> int:
    from ..pipeline import run_pipeline, wired
    from ._output import quiet_progress

    cfg = quiet_progress(config_from_args(args), args)
    if args.print_config:
        import json

        from .._config import config_dict

        print(json.dumps(config_dict(wired(cfg)), indent=2))
        return 0
    summary = run_pipeline(cfg)
    if summary.get("web"):          # --data: the first view like the dataset's cameras
        print(f"open the viewer: plenoctree view {cfg.out}/tree_ft.plnz --data "
              f"{wired(cfg).train.data}")
    return 0


def add_pipeline_flags(p: argparse.ArgumentParser, shown: Any, skip: tuple[str, ...] = ()
                       ) -> list[str]:
    """The pipeline-wide flags of :class:`PipelineConfig` (or a subclass: the demo's) and, in
    sections shown by ``--help-all`` / ``--help-stage``, ``--<stage>.<field>`` for every
    stage option; returns the dests. ``shown``: the config whose values ``--help`` shows."""
    from ..datasets.dataset import FORMATS
    from ..pipeline import STAGE_OPTIONS
    from ._options import add_config, hidden_sections

    stages = tuple(o.name for o in STAGE_OPTIONS)
    group = p.add_argument_group("pipeline")
    dests = add_config(group, type(shown), shown=shown, skip=stages + skip,
                       fields={"format": {"choices": FORMATS}})
    sections = {}
    for opt in STAGE_OPTIONS:
        sections[opt.name] = p.add_argument_group(f"{opt.name} stage: {opt.title}")
        inner = getattr(shown, opt.name)
        dests += add_config(sections[opt.name], type(inner), prefix=f"{opt.name}.",
                            dest_prefix=f"{opt.name}.", shown=inner, skip=opt.wired,
                            nested={n: {"skip": opt.wired} for n in opt.flat})
    hidden_sections(p, sections)
    return dests


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``run`` command."""
    from ..pipeline import PRESETS, pipeline_preset
    from ._options import add_config_file
    from ._output import add_quiet

    p = sub.add_parser(
        "run", help="photos -> NeRF-SH -> octree -> fine-tuned -> compressed + viewer (resumable)",
        usage="plenoctree run --data DIR --out DIR [--preset NAME] [--config FILE] [options]",
        description="Run the whole chain on a dataset. Each stage writes its artefact "
                    "atomically and is skipped when its artefact and settings are unchanged, "
                    "so a killed run continues where it stopped. Every stage option is a flag "
                    "--<stage>.<option> (--train.*, --extract.*, --refine.*, --finetune.*, "
                    "--compress.*, --process.*; see --help-all or --help-stage STAGE); the "
                    "settings used are saved in OUT/config.json (reuse them with --config).")
    p.add_argument("--preset", dest="run_preset", choices=sorted(PRESETS), default=None,
                   help="settings to start from: cpu (default), paper (the paper's NeRF-SH "
                        "and 512^3; for GPUs), gpu (fixed-shape steps) or quick (the whole "
                        "run within 10 minutes: --minutes 10)")
    add_config_file(p)
    p.add_argument("--print-config", action="store_true",
                   help="print the resolved configuration as JSON and exit")
    add_quiet(p)
    dests = add_pipeline_flags(p, pipeline_preset("cpu"))
    p.set_defaults(func=_run, _dests=dests)
