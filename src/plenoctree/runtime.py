"""Process set-up in one place: OpenMP, malloc, threads, device and AMP.

The CLI calls :func:`configure` before torch or numba are imported (the package root is lazy,
so ``import plenoctree`` loads neither); library functions change none of these process-wide
settings on their own, except the thread count a config asks for (``threads``). A library user
who wants the CLI's set-up calls :func:`configure` first thing::

    import plenoctree.runtime; plenoctree.runtime.configure()
    import plenoctree; plenoctree.train(...)

Why: torch and numba each bring an OpenMP runtime whose idle threads spin; on two cores they
took turns spinning against each other's work (a training step measured 3.6 s instead of
0.28 s). ``OMP_WAIT_POLICY=PASSIVE`` is read when a runtime loads, so it must be in the
environment before torch/numba import. glibc malloc returning big buffers to the OS after every
step made the small MLP 2x slower; :func:`tune_malloc` sets the thresholds with ``mallopt``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import re
import sys
from typing import Any

from .errors import ConfigError

__all__ = ["RUNTIME_ENV", "MALLOC_ENV", "configure", "tune_malloc", "setup_threads",
           "ThreadTuner", "resolve_device", "resolve_amp"]

MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": "1073741824", "MALLOC_TRIM_THRESHOLD_": "2147483647",
              "MALLOC_TOP_PAD_": "1073741824"}
"""The glibc variables :func:`tune_malloc` is equivalent to (for child processes)."""
RUNTIME_ENV = {"OMP_WAIT_POLICY": "PASSIVE", **MALLOC_ENV}
"""Environment :func:`configure` sets (values already in the environment win)."""


def configure(threads: int | None = None) -> dict[str, Any]:
    """Set up this process for plenoctree's work; call before torch/numba are imported.

    Puts :data:`RUNTIME_ENV` into ``os.environ`` (existing values win; child processes
    inherit it), applies the malloc thresholds in-process (:func:`tune_malloc`), and with
    ``threads`` sets the torch/numba thread count. Returns what was done: ``env`` (the
    variables set), ``late`` (runtimes already loaded, so the OpenMP policy came too late),
    ``malloc`` (bool), ``threads``.
    """
    late = [m for m in ("torch", "numba") if m in sys.modules]
    env = {k: v for k, v in RUNTIME_ENV.items() if k not in os.environ}
    os.environ.update(env)
    done: dict[str, Any] = {"env": env, "late": late, "malloc": tune_malloc(), "threads": None}
    if threads is not None:
        done["threads"] = setup_threads(threads)
    return done


def tune_malloc() -> bool:
    """Stop glibc malloc from returning big buffers to the OS after every step.

    Large tensors are otherwise mmap'ed and unmapped each step and page-fault on every touch
    (measured: the small MLP ran 2x slower). Equivalent to :data:`MALLOC_ENV`, applied with
    ``mallopt`` in-process. Returns False where there is no glibc.
    """
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        m_trim, m_top_pad, m_mmap = -1, -2, -3
        ok = libc.mallopt(m_mmap, 1 << 30) == 1
        ok &= libc.mallopt(m_trim, 2**31 - 1) == 1
        ok &= libc.mallopt(m_top_pad, 1 << 30) == 1
        return bool(ok)
    except (OSError, AttributeError):
        return False


def setup_threads(threads: int) -> int:
    """Use ``threads`` CPU threads (0 or -1 = all cores) in torch and numba; returns the count."""
    import numba
    import torch

    n = threads if threads > 0 else (os.cpu_count() or 1)
    torch.set_num_threads(n)
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    return n


class ThreadTuner:
    """``threads = -1``: pick 1 or all cores by measured speed, re-checked periodically.

    On a machine shared with other work, two-thread parallel regions wait for a descheduled
    thread and can run slower than one thread. Every ``period`` steps, ``trial`` steps run
    with each candidate count; the one with the fewest seconds per sample is kept until the
    next check. Thread counts change reduction order, so such runs are not bit-repeatable.
    """

    def __init__(self, n_all: int, period: int = 400, trial: int = 8):
        self.cands = [1, n_all] if n_all > 1 else [1]
        self.period, self.trial = period, trial
        self.cost = [0.0] * len(self.cands)
        self.current = self.best = n_all

    def before_step(self, step: int) -> None:
        k = step % self.period
        if len(self.cands) > 1 and k < self.trial * len(self.cands):
            want = self.cands[k // self.trial]
            if k % self.trial == 0:
                self.cost[k // self.trial] = 0.0
        else:
            want = self.best
        if want != self.current:
            setup_threads(want)
            self.current = want

    def after_step(self, step: int, seconds: float, samples: int) -> None:
        k = step % self.period
        if len(self.cands) > 1 and k < self.trial * len(self.cands) and k % self.trial:
            self.cost[k // self.trial] += seconds / max(samples, 1)   # skip each first step
        if k == self.trial * len(self.cands) - 1:
            self.best = self.cands[min(range(len(self.cands)), key=self.cost.__getitem__)]


def resolve_device(name: str) -> Any:
    """"auto" -> CUDA when available, else CPU; "cuda" without a GPU is a ConfigError.
    Returns a ``torch.device``."""
    import torch

    if isinstance(name, torch.device):
        name = str(name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    m = re.fullmatch(r"(cpu|cuda)(?::(\d+))?", str(name))
    if m is None or (m.group(1) == "cpu" and m.group(2) not in (None, "0")):
        raise ConfigError(f"--device {name!r}: expected auto, cpu, cuda or cuda:N")
    if m.group(1) == "cuda":
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if n == 0:
            raise ConfigError(f"--device {name}: no CUDA GPU is available (use cpu or auto)")
        if m.group(2) is not None and int(m.group(2)) >= n:
            raise ConfigError(f"--device {name}: this machine has {n} CUDA GPU(s), "
                              f"cuda:0 to cuda:{n - 1}")
    return torch.device(name)


def resolve_amp(amp: str, device: Any) -> bool:
    """Whether to run the MLP under bf16 autocast ("auto": where the hardware supports bf16)."""
    import torch

    if amp == "off":
        return False
    if amp == "bf16":
        return True
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover
        return False
