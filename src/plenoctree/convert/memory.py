"""Memory accounting for the conversion: available memory, budgets, per-stage peak RSS.

:class:`StageMonitor` times the stages of an extraction and records each stage's peak resident
set size (RSS) by polling ``/proc/self/statm`` from a background thread (every 5 ms), so a
stage's peak is its own, not the process's lifetime maximum (which ``getrusage`` reports).
"""

from __future__ import annotations

import contextlib
import os
import resource
import threading
import time
from dataclasses import dataclass, field
from typing import Iterator

from ..errors import ConfigError

__all__ = ["available_memory", "current_rss", "memory_limit", "check_budget", "StageMonitor",
           "StageStats"]

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def current_rss() -> int:
    """Resident set size of this process now, bytes (peak so far where /proc is missing)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def available_memory() -> int:
    """Memory the system can still give this process, bytes (``MemAvailable``)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * _PAGE
    except (ValueError, OSError, AttributeError):  # pragma: no cover - exotic platforms
        return 8 << 30


def memory_limit(memory_gb: float = 0.0) -> int:
    """The budget in bytes: ``memory_gb`` GiB, or 80 % of the available memory when 0."""
    if memory_gb < 0:
        raise ConfigError(f"memory_gb must be >= 0, got {memory_gb}")
    if memory_gb > 0:
        return int(memory_gb * (1 << 30))
    return int(0.8 * available_memory())


def check_budget(what: str, need: int, limit: int, advice: str) -> None:
    """Raise :class:`ConfigError` if ``need`` bytes exceed ``limit``, naming what and the fix."""
    if need > limit:
        raise ConfigError(f"{what} needs about {need / 2**30:.2f} GiB of memory but the budget is "
                          f"{limit / 2**30:.2f} GiB; {advice}")


@dataclass
class StageStats:
    """Wall time and memory of one stage: seconds, RSS at the start and peak RSS (bytes)."""

    seconds: float = 0.0
    rss_start: int = 0
    peak_rss: int = 0

    def to_json(self) -> dict:
        return {"seconds": round(self.seconds, 3), "rss_start_mb": round(self.rss_start / 2**20, 1),
                "peak_rss_mb": round(self.peak_rss / 2**20, 1)}


@dataclass
class StageMonitor:
    """Times named stages and tracks each one's peak RSS.

    >>> mon = StageMonitor()
    >>> with mon.stage("grid"):
    ...     pass
    >>> sorted(mon.stages)
    ['grid']
    """

    interval: float = 0.005
    stages: dict[str, StageStats] = field(default_factory=dict)

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[StageStats]:
        st = StageStats(rss_start=current_rss())
        st.peak_rss = st.rss_start
        stop = threading.Event()

        def poll() -> None:
            while not stop.wait(self.interval):
                st.peak_rss = max(st.peak_rss, current_rss())

        th = threading.Thread(target=poll, daemon=True)
        th.start()
        t0 = time.perf_counter()
        try:
            yield st
        finally:
            st.seconds = time.perf_counter() - t0
            stop.set()
            th.join()
            st.peak_rss = max(st.peak_rss, current_rss())
            self.stages[name] = st

    def to_json(self) -> dict:
        return {k: v.to_json() for k, v in self.stages.items()}
