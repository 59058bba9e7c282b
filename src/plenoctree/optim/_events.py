"""The fine-tuner's record of a run: a JSON-lines log of events plus the lines people read.

Every event (``start``, ``resume``, ``val``, ``epoch``, ``backoff``, ``interrupted``,
``gradient_scale``, ``end``) is a dict written as one JSON line (with ``time``, seconds since the
run started) to the run's ``.log.jsonl``, the file ``plenoctree.plots.plot_finetune_curve``
draws; ``epoch``, ``val`` and ``backoff`` are also logged as a readable line through the
``plenoctree.optim`` logger, at ``level`` (INFO when the run is ``verbose``, else DEBUG).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

__all__ = ["EventLog"]

logger = logging.getLogger(__name__)


def _line(rec: dict) -> str | None:
    """The readable line of event ``rec``, None for events only the file keeps."""
    event = rec["event"]
    if event == "val":
        return f"  epoch {rec['epoch']:3d}: val PSNR {rec['val_psnr']:.3f} dB"
    if event == "backoff":
        return (f"  back-off {rec['backoffs']}: {rec['reason']}; best values restored, "
                f"learning rate x{rec['lr_scale']:g}")
    if event == "epoch":
        return (f"  epoch {rec['epoch']:3d}: train PSNR {rec['train_psnr']:.3f} dB, "
                f"{rec['seconds']:.1f} s, {rec['rays_per_s'] / 1e6:.2f} M rays/s in the steps")
    return None


class EventLog:
    """Append events to ``path`` (None: keep no file) and log their readable lines.

    ``t_start``: ``time.perf_counter()`` when the run started; ``level``: the logging level of
    the readable lines (and of :meth:`note`).
    """

    def __init__(self, path: Path | None, t_start: float | None = None,
                 level: int = logging.INFO) -> None:
        self.path = path
        self.t_start = time.perf_counter() if t_start is None else t_start
        self.level = level

    def __call__(self, rec: dict) -> None:
        """Record event ``rec`` (a dict with ``"event"``)."""
        rec = {"time": round(time.perf_counter() - self.t_start, 3), **rec}
        if self.path is not None:
            with open(self.path, "a") as f:
                f.write(json.dumps(rec) + "\n")
        line = _line(rec)
        if line is not None:
            self.note(line)

    def note(self, message: str) -> None:
        """Log a readable line at this log's level."""
        logger.log(self.level, message)
