"""Per-thread balance of a parallel loop, counted instead of timed: which thread numba gives each
work item, and how much work (segments marched) each thread then has.

The render kernel's work items are image tiles (:data:`plenoctree.render._render_numba.TILE_2D`
pixels, row-major tile order); a tile's cost is the segments its rays march
(:func:`plenoctree.render._render_numba.ray_stats_numba`, column ``leaves``). With ``T`` threads
a frame takes as long as the busiest thread, so the speed-up over one thread is at most
``T × balance``, ``balance = mean / max`` of the per-thread work (1.0: every thread equally busy).

Schedules (``per_thread_work(..., schedule=...)``):

- ``"static"``: numba's ``prange`` as the omp and workqueue threading layers run it (numba
  0.57–0.6x, ``numba/np/ufunc/gufunc_scheduler.cpp``, ``omppool.cpp``, ``workqueue.c``). The
  ``N`` items are cut into ``D`` contiguous divisions, ``D = T`` or, with
  ``numba.set_parallel_chunksize(c)``, ``D = max(T, N // c)`` (``get_sched_size``); division
  ``i`` of those left gets ``ceil(items left / divisions left)`` items (``create_schedule``).
  The divisions are then handed out statically, contiguous blocks per thread: omp
  (``#pragma omp for``, libgomp's default static schedule) gives each thread ``D // T``
  divisions and the first ``D % T`` threads one more; workqueue gives each ``D // T`` and the
  last thread the rest. So the chunk size does not make the loop dynamic there (numba's docs:
  only the tbb layer schedules chunks dynamically): a thread still gets one contiguous run of
  items, and the image's cost sits in its middle, where the object is.
- ``"cyclic"``: thread ``t`` takes items ``t, t + T, t + 2T, ...`` (an interleaved static order).
- ``"dynamic"``: a shared counter hands the next item to whichever thread is free first
  (what the render kernel does: :func:`plenoctree.render._schedule_numba.next_item`); modelled
  with the counts as durations (list scheduling, ties to the lowest thread).
"""

from __future__ import annotations

import heapq

import numpy as np

SCHEDULES = ("static", "cyclic", "dynamic")
LAYERS = ("omp", "workqueue")


def tile_costs(per_ray: np.ndarray, tile: tuple[int, int]) -> np.ndarray:
    """Work per tile: ``per_ray [H, W]`` summed over ``tile = (w, h)`` pixel tiles, in the
    kernel's order (row-major over tiles; edge tiles are partial); float64 ``[n_tiles]``."""
    h, w = per_ray.shape
    tw, th = tile
    ntx, nty = -(-w // tw), -(-h // th)
    padded = np.zeros((nty * th, ntx * tw), dtype=np.float64)
    padded[:h, :w] = per_ray
    return padded.reshape(nty, th, ntx, tw).sum(axis=(1, 3)).reshape(-1)


def static_owner(n_items: int, threads: int, chunksize: int = 0,
                 layer: str = "omp") -> np.ndarray:
    """The thread numba's static ``prange`` schedule gives each of ``n_items`` items (see the
    module docstring; ``chunksize``: ``numba.set_parallel_chunksize``'s value, 0 = unset);
    int64 ``[n_items]``."""
    if layer not in LAYERS:
        raise ValueError(f"layer must be one of {LAYERS}, got {layer!r}")
    d = threads if chunksize <= 0 else max(threads, n_items // chunksize)
    division = np.empty(n_items, dtype=np.int64)
    if n_items <= d:                     # one item per division, the others empty
        division[:] = np.arange(n_items)
    else:
        cur = 0
        for i in range(d):
            size = (n_items - cur - 1) // (d - i) + 1 if i < d - 1 else n_items - cur
            division[cur:cur + size] = i
            cur += size
    q, r = divmod(d, threads)
    if layer == "omp":                   # the first r threads take q + 1 divisions
        first = np.minimum(np.arange(threads), r) + q * np.arange(threads)
        owner_of_division = np.searchsorted(first, np.arange(d), side="right") - 1
    else:                                # q each, the last thread the rest
        owner_of_division = np.minimum(np.arange(d) // q, threads - 1)
    return owner_of_division[division]


def dynamic_work(costs: np.ndarray, threads: int) -> np.ndarray:
    """Per-thread work when items are taken in order by whichever thread is free first, each
    item lasting its cost (list scheduling; ties go to the lowest thread); float64 ``[T]``."""
    work = np.zeros(threads, dtype=np.float64)
    free = [(0.0, t) for t in range(threads)]
    for c in np.asarray(costs, dtype=np.float64):
        at, t = heapq.heappop(free)
        work[t] += c
        heapq.heappush(free, (at + c, t))
    return work


def per_thread_work(costs: np.ndarray, threads: int, schedule: str, chunksize: int = 0,
                    layer: str = "omp") -> np.ndarray:
    """Work of each of ``threads`` threads for items of cost ``costs [N]`` under ``schedule``
    (:data:`SCHEDULES`; ``chunksize``/``layer``: the static schedule's, see
    :func:`static_owner`); float64 ``[T]``."""
    costs = np.asarray(costs, dtype=np.float64)
    if schedule == "dynamic":
        return dynamic_work(costs, threads)
    if schedule == "cyclic":
        owner = np.arange(costs.size) % threads
    elif schedule == "static":
        owner = static_owner(costs.size, threads, chunksize, layer)
    else:
        raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    return np.bincount(owner, weights=costs, minlength=threads)


def balance(work: np.ndarray) -> float:
    """``mean / max`` of per-thread work (1.0: perfectly even; ``T × balance`` bounds the
    speed-up over one thread); 1.0 when there is no work."""
    top = float(np.max(work))
    return float(np.mean(work)) / top if top > 0 else 1.0
