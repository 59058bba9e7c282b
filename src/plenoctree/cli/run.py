"""``plenoctree run``: the whole chain as a resumable pipeline on any dataset."""

from __future__ import annotations

import argparse
import dataclasses


def _run(args: argparse.Namespace) -> int:
    from ..pipeline import PipelineConfig, run_pipeline

    cfg = PipelineConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(
        PipelineConfig) if f.name != "extra"})
    summary = run_pipeline(cfg)
    if summary.get("web"):
        print(f"open the viewer: plenoctree view {cfg.out}/tree_ft.plnz")
    return 0


def add_pipeline_flags(p: argparse.ArgumentParser, defaults) -> None:
    """Add one flag per :class:`PipelineConfig` field (help = the field's docstring)."""
    from ..nerf.config import field_docs
    from ..pipeline import PipelineConfig

    docs = field_docs(PipelineConfig)
    for f in dataclasses.fields(PipelineConfig):
        if f.name in ("extra", "data", "out"):
            continue
        flag = "--" + f.name.replace("_", "-")
        default = getattr(defaults, f.name)
        help_ = f"{docs.get(f.name, '')} (default {default})"
        if f.type in ("bool", bool):
            p.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction,
                           default=default, help=help_)
        elif f.name == "finetune_lr":
            p.add_argument(flag, dest=f.name, type=float, default=default, help=help_)
        elif f.name == "format":
            from ..datasets import FORMATS

            p.add_argument(flag, dest=f.name, choices=list(FORMATS), default=default,
                           help=help_)
        else:
            p.add_argument(flag, dest=f.name, type=type(default), default=default, help=help_)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``run`` command."""
    from ..pipeline import PipelineConfig

    p = sub.add_parser(
        "run", help="photos -> NeRF-SH -> octree -> fine-tuned -> compressed + viewer (resumable)",
        description="Run the whole chain on a dataset. Each stage writes its artefact "
                    "atomically and is skipped when its artefact and settings are unchanged, "
                    "so a killed run continues where it stopped.")
    p.add_argument("--data", default="", help="dataset folder (any supported format); or "
                   "--images")
    p.add_argument("--out", required=True, help="output folder")
    add_pipeline_flags(p, PipelineConfig())
    p.set_defaults(func=_run)
