"""Registering the images the first incremental mapping left out (walk-arounds).

COLMAP's incremental mapper grows a model until no remaining image registers against it, then
starts another one from what is left; ``process`` keeps the largest. In an ordered walk-around
one frame that registers poorly (blurred, little texture, too few matches for the strict
thresholds of :data:`~plenoctree.process.sfm.MAPPER_DEFAULTS`) cuts the sequence in two, and
each part becomes a model of its own: the lounge walk-around (64 frames, 347° around a table,
480x270) matched with 2 neighbours per frame fell into two models, the largest of 45 frames,
even with the loop's pairs (:func:`~plenoctree.process.sfm.loop_pairs`).

:func:`retry_registration` then, while the largest model holds fewer than
:data:`RETRY_FRACTION` of the images, for at most :data:`MAX_RETRY_ROUNDS` rounds:

1. matches each left-out frame of an ordered sequence with the frames within
   ``round x`` :data:`RETRY_REACH` ``x overlap`` of it in time, counted round the end of the
   sequence (a walk-around returns to its start), not matched yet, nearest first, at most
   ``max_pairs`` in all (:func:`retry_pairs`; unordered photos were matched in every pair);
2. maps on from the largest model with COLMAP's own registration thresholds
   (:data:`RETRY_MAPPER`): its images stay registered (the mapper's bundle adjustments refine
   them with the rest), the left-out ones (those of the other models among them) are
   registered into it.

A round that registers nothing more ends the retry and its result is dropped. The weak-image
filter and the final bundle adjustment then run on the largest model as before. Measured there
(docs/capture_records.md, "Walk-arounds in one model"): 64 of 64 in one model after the retry
(25 more pairs, 9 s; no camera more than 1.1° off the published poses); the new pairs alone
registered 51, COLMAP's thresholds alone 64. On the lego video (every pair matched: no new
pairs) 56 of 60 frames against 39, no outlier.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Iterable, Sequence

__all__ = ["retry_registration", "retry_pairs", "largest", "RETRY_FRACTION", "RETRY_REACH",
           "MAX_RETRY_ROUNDS", "RETRY_MAPPER"]

logger = logging.getLogger(__name__)

RETRY_FRACTION = 0.95
"""The retry runs while the largest model holds fewer than this fraction of the images (a few
weakly supported frames left out do not start it: fox's 65 of 67, lego's 97 of 100 photos)."""
RETRY_REACH = 2
"""Round ``k`` matches a left-out frame with the frames within ``k x RETRY_REACH x`` the
sequential overlap of it (20 frames each way at the default overlap of 10, the nearest 10
matched already)."""
MAX_RETRY_ROUNDS = 2
"""Rounds of :func:`retry_registration` at most."""
RETRY_MAPPER = {"mapper.abs_pose_min_num_inliers": 30, "mapper.abs_pose_min_inlier_ratio": 0.25,
                "mapper.abs_pose_max_error": 12.0}
"""Registration thresholds of the retry's mapping: COLMAP's defaults (the first mapping uses
:data:`~plenoctree.process.sfm.MAPPER_DEFAULTS`' stricter ones, >= 100 inliers, >= 50 %, <=
4 px)."""


def largest(models: dict) -> Any:
    """The model (``pycolmap.Reconstruction``) of ``models`` with the most registered images."""
    return max(models.values(), key=lambda r: r.num_reg_images())


def _registered(rec: Any, index: dict[str, int]) -> set[int]:
    """Indices (into the image names) of the images registered in ``rec``."""
    return {index[rec.images[i].name] for i in rec.reg_image_ids()}


def retry_pairs(n: int, left_out: Iterable[int], done: set[tuple[int, int]], reach: int,
                limit: int) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, of each frame of ``left_out`` (of ``n`` frames in time
    order) with the frames within ``reach`` of it, counted round the end of the sequence
    (frame ``n - 1`` is next to frame 0), leaving out the pairs in ``done``: nearest in time
    first, at most ``limit``.

    >>> retry_pairs(10, [0], {(0, 1)}, 2, 10)
    [(0, 9), (0, 2), (0, 8)]
    """
    near: dict[tuple[int, int], int] = {}
    for u in left_out:
        for d in range(1, min(reach, n // 2) + 1):
            for v in ((u - d) % n, (u + d) % n):
                p = (min(u, v), max(u, v))
                if v != u and p not in done and d < near.get(p, n):
                    near[p] = d
    return sorted(near, key=lambda p: (near[p], p))[:max(0, int(limit))]


def retry_registration(models: dict, names: Sequence[str], done: Iterable[tuple[int, int]],
                       ordered: bool, overlap: int,
                       match: Callable[[list[tuple[int, int]]], None],
                       remap: Callable[[Any], dict], max_pairs: int) -> tuple[dict, dict]:
    """Register what the mapping left out of the largest of ``models`` (module docstring).

    Args:
        models: the mapper's models (``{id: pycolmap.Reconstruction}``, not empty).
        names: the image names, in capture order when ``ordered``.
        done: the pairs ``(i, j)`` of ``names`` matched already.
        ordered: ``names`` are in capture order (the sequential matcher's pairs); otherwise no
            pairs are added (every pair was matched) and only the mapping is retried.
        overlap: the sequential matcher's neighbours per frame.
        match: matches a list of pairs ``(i, j)`` into the database.
        remap: maps on from a model with :data:`RETRY_MAPPER`'s thresholds; returns the
            models, that one grown among them.
        max_pairs: the pairs matched by the retry at most.

    Returns:
        ``(models, stats)``: the models of the last round that registered more images (or
        ``models`` as given), and ``{"rounds", "pairs", "registered_before",
        "registered_after", "models_before"}`` (empty when no retry was needed).
    """
    n = len(names)
    index = {name: i for i, name in enumerate(names)}
    done = set(done)
    stats: dict = {}
    for k in range(1, MAX_RETRY_ROUNDS + 1):
        best = largest(models)
        reg = _registered(best, index)
        if len(reg) >= RETRY_FRACTION * n:
            break
        left = [i for i in range(n) if i not in reg]
        if not stats:
            stats = {"rounds": 0, "pairs": 0, "registered_before": len(reg),
                     "models_before": len(models)}
        extra = (retry_pairs(n, left, done, k * RETRY_REACH * overlap,
                             max_pairs - stats["pairs"]) if ordered else [])
        if k > 1 and not extra:
            break                       # the same mapping again would register nothing more
        logger.info(f"colmap: the largest of {len(models)} model(s) holds {len(reg)} of {n} "
                    f"images; retry {k}: {len(extra)} more pairs for the {len(left)} left out, "
                    "then mapping on from it with COLMAP's registration thresholds")
        if extra:
            match(extra)
            done.update(extra)
            stats["pairs"] += len(extra)
        stats["rounds"] = k
        new = remap(best)
        if not new or largest(new).num_reg_images() <= len(reg):
            break
        models = new
    if stats:
        stats["registered_after"] = largest(models).num_reg_images()
        logger.info(f"colmap: retry: {stats['registered_after']} of {n} images in the largest "
                    f"model (before {stats['registered_before']}), {stats['pairs']} pairs "
                    "matched")
    return models, stats
