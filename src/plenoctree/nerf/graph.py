"""The fixed-shape training step replayed from a CUDA graph (issue 47, item 1; ``cuda_graph``).

A fixed-shape step (:mod:`.fixed`) launches ~140 kernels and reads nothing back, so on a GPU
the host's time issuing launches can rival the step's own work. A CUDA graph records the
launches of one step once and replays them as one. What that needs, and how the trainer
provides it (``Trainer._graph_body``):

* every tensor the step reads from outside lives at a fixed address and is updated in place:
  parameters, their ``.grad`` buffers (``zero_grad(set_to_none=False)``), Adam's moments and
  its step count (``capturable=True``: on the device), the learning rate (a device tensor
  filled before each replay), the occupancy grid (``copy_``), the photos, the ray-count
  counters of :class:`.fixed.FixedBatch`;
* the same launches with the same arguments at every step of one ray count: shapes come from
  the ray count and the sample budget only; no Python number that changes between steps
  reaches a kernel (tested on the CPU by recording two steps' ops:
  ``tests/test_cuda_graph.py``);
* no host round trip inside (``tests/test_fixed_step.py``), and the random numbers from
  generators registered with the graph (each replay advances their offsets).

:class:`StepGraphs` keeps one graph per ray count (the count moves in multiples of
:data:`.fixed.RAY_QUANTUM` every ``occ_update_every`` steps): a new count runs
:data:`WARMUP` eager steps on a side stream (lazy initialisation, Triton's compilation), the
next step is captured and replayed, later steps of that count replay. At most :data:`KEEP`
graphs are kept (least recently used dropped, with their memory). Without CUDA the body runs
eagerly every step: the same computation (bit for bit the plain fixed step, tested), so the
code path is exercised on the CPU.

What only a GPU can say: whether it measures faster (``benchmarks/gpu_bench.py`` row
``train_gpu_graph`` against ``train_gpu``), hence off by default.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable

import torch

__all__ = ["StepGraphs", "lr_tensor", "make_capturable", "WARMUP", "KEEP"]

#: Eager steps of a new ray count before its graph is captured.
WARMUP = 3
#: Graphs kept at most (one per ray count).
KEEP = 4


def lr_tensor(value: float, device: torch.device) -> torch.Tensor:
    """The learning rate as the device tensor a captured Adam step reads: float32 on CUDA (the
    fused kernel reads it as a float pointer), float64 elsewhere (the CPU's fused Adam then
    steps bit for bit as with a Python number)."""
    dt = torch.float32 if torch.device(device).type == "cuda" else torch.float64
    return torch.tensor(float(value), dtype=dt, device=device)


def make_capturable(opt: torch.optim.Optimizer, device: torch.device) -> None:
    """Set Adam up for a captured step (also after a checkpoint's state replaced its
    settings): ``capturable``, the learning rate a device tensor (:func:`lr_tensor`)."""
    for g in opt.param_groups:
        g["capturable"] = True
        if not isinstance(g["lr"], torch.Tensor):
            g["lr"] = lr_tensor(g["lr"], device)


class _Entry:
    """One ray count: eager steps so far, then its graph and static outputs."""

    def __init__(self) -> None:
        self.runs = 0
        self.graph: Any = None
        self.out: torch.Tensor | None = None
        self.extra: Any = None


class StepGraphs:
    """One training step per call, replayed from a CUDA graph per ray count.

    Args:
        body: ``body(n_rays) -> (out, extra)``: one whole step (forward, backward, optimiser)
            of ``n_rays`` rays; ``out`` a device tensor of the step's figures (copied after
            each step: a graph's outputs are overwritten by the next replay), ``extra``
            Python values that depend on ``n_rays`` only.
        device: the step's device; graphs only on CUDA.
        generators: the ``torch.Generator`` objects the body draws from.
    """

    def __init__(self, body: Callable[[int], tuple[torch.Tensor, Any]], device: torch.device,
                 generators: tuple = ()):
        self.body = body
        self.capture = torch.device(device).type == "cuda"
        self.generators = generators
        self.entries: OrderedDict[int, _Entry] = OrderedDict()
        self.captures = 0               # graphs captured (a figure for the benchmarks)
        self.replays = 0

    def step(self, n_rays: int) -> tuple[torch.Tensor, Any]:
        """Run one step of ``n_rays`` rays; returns ``(a copy of out, extra)``."""
        if not self.capture:
            out, extra = self.body(n_rays)
            return out.clone(), extra
        e = self.entries.pop(n_rays, None) or _Entry()
        self.entries[n_rays] = e                      # most recently used last
        if e.graph is None and e.runs < WARMUP:
            e.runs += 1
            return self._eager(n_rays)
        if e.graph is None:
            self._capture(n_rays, e)
        e.graph.replay()
        self.replays += 1
        return e.out.clone(), e.extra

    def _eager(self, n_rays: int) -> tuple[torch.Tensor, Any]:
        """A warm-up step on a side stream (as CUDA graphs require before a capture)."""
        side, main = torch.cuda.Stream(), torch.cuda.current_stream()
        side.wait_stream(main)
        with torch.cuda.stream(side):
            out, extra = self.body(n_rays)
        main.wait_stream(side)
        return out.clone(), extra

    def _capture(self, n_rays: int, e: _Entry) -> None:
        """Record ``body(n_rays)`` into a new graph (nothing runs until it is replayed)."""
        while len(self.entries) > KEEP:              # drop the least recently used graph
            self.entries.popitem(last=False)
        g = torch.cuda.CUDAGraph()
        for gen in self.generators:
            g.register_generator_state(gen)
        with torch.cuda.graph(g):
            e.out, e.extra = self.body(n_rays)
        e.graph = g
        self.captures += 1
