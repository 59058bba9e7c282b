"""The training log of a run directory: CSV and JSON tables and a PNG plot of the curve.

Files (all rewritten atomically from the in-memory rows, which also live in the checkpoint, so
a resumed run's log holds exactly the steps that its state has seen):

* ``log.csv`` — one row every ``log_every`` steps: step, train_s, wall_s, lr, loss, psnr
  (training batch), rays_per_s, samples_per_s, rays, samples_per_ray, occupancy;
* ``val.csv`` — one row per validation: step, train_s, wall_s, psnr, ssim, seconds, load;
* ``log.json`` — both tables; ``curve.png`` — PSNR against training minutes.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

from .._util import atomic_save_json, atomic_write

__all__ = ["RunLog"]


class RunLog:
    """Rows of training and validation metrics, written to a run directory."""

    def __init__(self, out_dir: str | os.PathLike, rows: dict | None = None):
        self.dir = Path(out_dir)
        rows = rows or {}
        self.train: list[dict] = list(rows.get("train", []))
        self.val: list[dict] = list(rows.get("val", []))

    def as_dict(self) -> dict:
        return {"train": self.train, "val": self.val}

    @staticmethod
    def _csv(rows: list[dict]) -> str:
        if not rows:
            return ""
        keys = list(rows[0].keys())
        for r in rows[1:]:
            keys += [k for k in r if k not in keys]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
        return buf.getvalue()

    def write(self, plot: bool = True) -> None:
        """Rewrite ``log.csv``, ``val.csv``, ``log.json`` and (optionally) ``curve.png``."""
        for name, rows in (("log.csv", self.train), ("val.csv", self.val)):
            with atomic_write(self.dir / name, "w") as f:
                f.write(self._csv(rows))
        atomic_save_json(self.dir / "log.json", self.as_dict())
        if plot:
            self.plot(self.dir / "curve.png")

    def plot(self, path: str | os.PathLike) -> bool:
        """Plot PSNR vs training minutes (train batches and validation); False without matplotlib."""
        try:
            import matplotlib

            matplotlib.use("Agg", force=False)
            import matplotlib.pyplot as plt
        except ImportError:
            return False
        fig, ax = plt.subplots(figsize=(7, 4.2), dpi=110)
        if self.train:
            ax.plot([r["train_s"] / 60 for r in self.train], [r["psnr"] for r in self.train],
                    lw=0.8, alpha=0.6, label="training batch PSNR")
        if self.val:
            ax.plot([r["train_s"] / 60 for r in self.val], [r["psnr"] for r in self.val], "o-",
                    lw=1.6, label="validation PSNR")
            last = self.val[-1]
            ax.annotate(f"{last['psnr']:.2f} dB", (last["train_s"] / 60, last["psnr"]),
                        textcoords="offset points", xytext=(-30, 8))
        ax.set_xlabel("training time (minutes)")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right")
        ax.set_title(f"NeRF-SH training — {self.dir.name}")
        fig.tight_layout()
        with atomic_write(path, "wb") as f:
            fig.savefig(f, format="png")
        plt.close(fig)
        return True
