"""Where a tree came from: the dataset it was made from, read from the files written next to
it, so ``render`` / ``eval`` / ``finetune`` need no ``--data`` again.

Looked up, in order, for a tree ``DIR/NAME.<ext>`` (``.npz``, ``.plnz``; a decompressed
``NAME_decompressed.npz`` also tries ``NAME``): ``NAME.log.jsonl`` (the fine-tuner's log, its
``start`` record), ``NAME.extract.json`` (the extractor's report; its ``data``, else the
training run's ``config.json``), then ``DIR/config.json`` (``plenoctree run``'s saved config).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from ..errors import ConfigError

__all__ = ["dataset_of", "data_from_provenance"]

logger = logging.getLogger(__name__)


def _read(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _finetune_log(path: Path) -> str | None:
    try:
        with open(path) as f:
            for line in f:
                rec = json.loads(line)
                if rec.get("event") == "start":
                    return (rec.get("config") or {}).get("data") or None
    except (OSError, ValueError, AttributeError):
        return None
    return None


def _from_run_dir(run_dir: str) -> str | None:
    cfg = _read(Path(run_dir) / "config.json") if run_dir else None
    return cfg.get("data") or None if isinstance(cfg, dict) else None


def dataset_of(tree: str | Path) -> tuple[str, Path] | None:
    """``(dataset folder, file it was read from)`` of ``tree``, or ``None`` when unknown."""
    tree = Path(tree)
    stems = [tree.stem]
    if tree.stem.endswith("_decompressed"):
        stems.append(tree.stem[: -len("_decompressed")])
    for stem in stems:
        log = tree.with_name(stem + ".log.jsonl")
        data = _finetune_log(log)
        if data:
            return data, log
        rep = tree.with_name(stem + ".extract.json")
        ex = _read(rep)
        if isinstance(ex, dict):
            cfg = ex.get("extra", {}).get("config") or ex.get("config") or {}
            data = cfg.get("data") or _from_run_dir(cfg.get("run_dir", ""))
            if data:
                return data, rep
    run_cfg = tree.parent / "config.json"
    cfg = _read(run_cfg)
    if isinstance(cfg, dict) and cfg.get("data"):
        return cfg["data"], run_cfg
    return None


def data_from_provenance(tree: str | Path, command: str) -> str:
    """The dataset of ``tree`` (logged), or a ConfigError asking for ``--data``."""
    found = dataset_of(tree)
    if found is None:
        raise ConfigError(f"{tree}: --data is needed (no record of the dataset this tree was "
                          f"made from next to it)")
    data, source = found
    if not Path(data).exists():
        raise ConfigError(f"{tree}: the dataset recorded in {source} ({data}) does not exist; "
                          f"pass --data")
    logger.info(f"plenoctree {command}: --data {data} (from {source})")
    return str(data)
