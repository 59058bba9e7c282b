"""Data-parallel NeRF-SH training with torch.distributed (``torchrun``), NCCL on GPUs, gloo on CPUs.

Launch the ordinary training command under ``torchrun``; every process trains the same model
on its share of each step's rays::

    torchrun --nproc_per_node 4 -m plenoctree train --data DATA --out RUN      # one machine
    torchrun --nnodes 2 --nproc_per_node 8 --rdzv_backend c10d \
        --rdzv_endpoint HOST:29500 -m plenoctree train --data DATA --out RUN   # two machines

How a step is split (``world`` processes, ``rank`` 0…world-1):

* every rank draws the *same* global batch of rays from the shared generator (the one that is
  checkpointed; all ranks keep it in step, so the sparsity-prior points and the occupancy-grid
  updates are identical everywhere) and keeps rows ``rank::world`` of it;
* the rendering noise (stratified jitter, marching offsets) comes from a per-rank generator
  seeded from ``(seed, rank, step)``, so ranks do not repeat each other's jitter;
* each rank's loss is the mean over its shard; the gradients are summed with ``all_reduce``
  and divided by ``world`` (with equal shards this is the gradient of the global batch's mean
  loss). The averaging is done by hand on ``p.grad`` after ``backward()`` rather than by
  ``DistributedDataParallel``: the numba hash-grid encoding writes its table gradient straight
  into ``table.grad`` (no autograd hook for DDP to see), and the hand-made reduction treats it
  like every other parameter;
* the step's loss, MSE, ray and sample counts and its duration are reduced too, so every rank
  logs, adapts its ray count and stops at the same step (a time budget cannot make ranks
  disagree);
* rank 0 alone validates and writes ``config.json``, the logs, validation renders, the
  checkpoint and ``summary.json``; at the end every rank gets its validation PSNR, and
  ``plenoctree train`` prints its summary line on rank 0 only; resuming (``--resume``)
  loads that checkpoint on every rank.

The result is the single-process run with the same global batch up to the rendering noise
(checked by ``tests/test_nerf_distributed.py``); a run may be resumed with another number of
processes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Iterable

import torch

__all__ = ["DistContext", "rank_from_env", "setup_distributed", "world_from_env"]


def world_from_env() -> int:
    """``WORLD_SIZE`` set by ``torchrun`` (1 when not launched by it)."""
    try:
        return max(1, int(os.environ.get("WORLD_SIZE", "1")))
    except ValueError:
        return 1


def rank_from_env() -> int:
    """``RANK`` set by ``torchrun`` (0 when not launched by it)."""
    try:
        return max(0, int(os.environ.get("RANK", "0") or 0))
    except ValueError:
        return 0


@dataclass
class DistContext:
    """This process's place in the run: ``rank`` of ``world``, its ``device``."""

    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")
    owns_group: bool = False

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1

    def shard(self, x: torch.Tensor) -> torch.Tensor:
        """Rows ``rank::world`` of ``x`` (``x`` itself for one process)."""
        return x if self.world == 1 else x[self.rank::self.world]

    def average_gradients(self, params: Iterable[torch.nn.Parameter]) -> None:
        """``p.grad = sum over ranks / world`` for every parameter (missing grads count as 0)."""
        if not self.active:
            return
        import torch.distributed as dist

        for p in params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            dist.all_reduce(p.grad, op=dist.ReduceOp.SUM)
            p.grad.div_(self.world)

    def sum(self, values: list[float]) -> list[float]:
        """Element-wise sum of ``values`` over the ranks (the values themselves for one)."""
        if not self.active:
            return list(values)
        import torch.distributed as dist

        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
        return t.tolist()

    def from_main(self, values: list[float]) -> list[float]:
        """Rank 0's ``values`` on every rank (the values themselves for one process)."""
        if not self.active:
            return list(values)
        import torch.distributed as dist

        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        dist.broadcast(t, src=0)
        return t.tolist()

    def broadcast_module(self, module: torch.nn.Module) -> None:
        """Copy rank 0's parameters and buffers to every rank."""
        if not self.active:
            return
        import torch.distributed as dist

        with torch.no_grad():
            for t in list(module.parameters()) + list(module.buffers()):
                dist.broadcast(t.data, src=0)

    def barrier(self) -> None:
        if self.active:
            import torch.distributed as dist

            dist.barrier()

    def close(self) -> None:
        """Leave the process group (only when :func:`setup_distributed` created it)."""
        if self.owns_group:
            import torch.distributed as dist

            dist.destroy_process_group()
            self.owns_group = False


def setup_distributed(device: torch.device) -> DistContext:
    """Join the ``torchrun`` process group when ``WORLD_SIZE > 1`` (else a one-process context).

    ``device``: the resolved training device. On CUDA each process takes ``cuda:LOCAL_RANK``
    and the NCCL backend; on the CPU gloo. An existing process group is reused.
    """
    world = world_from_env()
    if world == 1:
        return DistContext(device=device)
    import torch.distributed as dist

    from ..errors import ConfigError

    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device.type == "cuda":
        if local >= torch.cuda.device_count():
            raise ConfigError(f"torchrun: LOCAL_RANK {local} but only "
                              f"{torch.cuda.device_count()} CUDA device(s) on this machine")
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
    owns = False
    if not dist.is_initialized():
        # torch._dynamo, imported lazily by the first optimiser, keeps ~10 references to the
        # default process group when it is imported after the group exists: then
        # destroy_process_group() does not free the group, its gloo worker threads outlive
        # close(), and one still releasing a collective's tensors when the interpreter shuts
        # down aborts the process ("terminate called without an active exception", SIGABRT
        # or SIGSEGV at exit, seen under load). Imported first, it holds none.
        import torch._dynamo  # noqa: F401

        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
        owns = True
    return DistContext(rank=dist.get_rank(), world=dist.get_world_size(), device=device,
                       owns_group=owns)


def render_generator(seed: int, rank: int, step: int, device: Any) -> torch.Generator:
    """The per-rank generator of the rendering noise (see the module docstring)."""
    g = torch.Generator(device=device)
    g.manual_seed((int(seed) * 1_000_003 + 7919 * (int(rank) + 1) + int(step)) % (2 ** 63))
    return g
