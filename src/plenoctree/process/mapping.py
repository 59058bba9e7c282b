"""COLMAP's mappers for :func:`.sfm.run_sfm` (:attr:`.sfm.SfmOptions.mapping`): incremental
(one image at a time, a progress tick per registered image; the default) and global (GLOMAP:
every rotation, then every position, then one bundle adjustment).

Measured (``benchmarks/colmap_poses.py --mapping incremental global``, docs/capture_records.md
"Global mapping"): on photo sets matched in every pair, global mapping took a third to a half
of the incremental mapper's time with poses as good (flower's 34 photos 46 → 20 s, 0.44° →
0.27° median rotation error, right in 5 of 5 runs; lego's 100 photos 29 → 10 s, 0.13° → 0.19°);
on video frames it misplaced the cameras: lego's video, every one of 56 frames (19° median),
and fox's frames in 3 of 5 runs (rotations right, positions flattened: 39 % centre error with a
reprojection error as low as a right model's, so nothing in the model tells). Hence not the
default, and not for frames of a video.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

__all__ = ["global_mapping", "incremental_mapping"]


def _disable(show_progress: bool | None) -> bool | None:
    """tqdm's ``disable`` for ``show_progress`` (None: only on a terminal)."""
    return None if show_progress is None else not show_progress


def global_mapping(pycolmap: Any, db: Path, image_dir: str | os.PathLike, out: Path,
                   opts: Any, show_progress: bool | None) -> dict:
    """COLMAP's global mapping (GLOMAP) of ``db`` into ``out`` (created): rotation averaging,
    global positioning, bundle adjustment, retriangulation; with ``opts``' threads and seed.
    One progress tick when done (the stage reports nothing on the way)."""
    from .._util import progress

    out.mkdir(parents=True, exist_ok=True)
    gopt = pycolmap.GlobalPipelineOptions()
    gopt.num_threads = int(opts.num_threads)
    gopt.random_seed = int(opts.seed)
    with progress(total=1, desc="colmap mapping (global)", unit="model",
                  disable=_disable(show_progress)) as bar:
        models = pycolmap.global_mapping(db, image_dir, out, options=gopt)
        bar.update(1)
    return dict(models)


def incremental_mapping(pycolmap: Any, db: Path, image_dir: str | os.PathLike, out: Path,
                        popt: Any, n: int, show_progress: bool | None,
                        desc: str = "colmap mapping", start: Any = None) -> dict:
    """COLMAP's incremental mapping of ``db`` into ``out`` (created), one progress tick per
    registered image; from the model ``start`` on (written to ``out/start``) when given."""
    from .._util import progress

    out.mkdir(parents=True, exist_ok=True)
    input_path = ""
    if start is not None:
        input_path = out / "start"
        input_path.mkdir(exist_ok=True)
        start.write(input_path)
    with progress(total=n, desc=desc, unit="img", disable=_disable(show_progress)) as bar:
        if start is not None:
            bar.update(start.num_reg_images())
        return pycolmap.incremental_mapping(db, image_dir, out, options=popt,
                                            input_path=input_path,
                                            next_image_callback=lambda: bar.update(1))
