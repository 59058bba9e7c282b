"""What every benchmark shares: where things are, machine facts, timing, JSON and tables.

The method every benchmark follows (kornia's ``benchmarks/README.md`` is the model): a warm-up
call first (JIT compilation, cache loads), then ``repeat`` timed calls; the figure is the
median, the spread is given with it (half the range, or min and max), paths compared with
each other are timed interleaved (pass 1 of each, then pass 2, ...) so that a change of
machine load hits them alike, and the reference (the baseline) is measured in the same run.
Every benchmark prints a table and writes JSON (``--out``) with :func:`machine_info`.

Data: the shared data folder (``nerf_synthetic/lego``, ``runs/lego_cpu_400``) is
``--data-root`` (:func:`add_data_root`), else the environment variable ``PLENOCTREE_DATA``,
else the first ``shared/data`` folder found above the repository.

Old code against new: ``benchmarks/ab.py`` runs a benchmark under two revisions.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

BENCH = Path(__file__).resolve().parent
"""The ``benchmarks`` folder."""
REPO = BENCH.parent
RESULTS = BENCH / "results"
"""Where the benchmarks write their JSON by default (ignored by git)."""
CACHE = RESULTS / "cache"
"""Inputs made once and kept between runs (extracted trees, written datasets)."""
DATA_ENV = "PLENOCTREE_DATA"


# --- paths ---------------------------------------------------------------------------------
def add_data_root(ap: argparse.ArgumentParser) -> None:
    """Add ``--data-root`` (default ``$PLENOCTREE_DATA``) to a benchmark's parser."""
    ap.add_argument("--data-root", default=os.environ.get(DATA_ENV),
                    help=f"the shared data folder (nerf_synthetic/, runs/); default "
                         f"${DATA_ENV}, else the first shared/data found in a folder above "
                         "the repository")


def add_out(ap: argparse.ArgumentParser, name: str) -> None:
    """Add the uniform ``--out FILE.json`` flag (default ``benchmarks/results/<name>``)."""
    ap.add_argument("--out", default=str(RESULTS / name),
                    help=f"JSON results file (default benchmarks/results/{name})")


def data_root(given: str | None = None) -> Path | None:
    """The shared data folder: ``given`` (``--data-root``), else ``$PLENOCTREE_DATA``, else the
    first ``shared/data`` folder above the repository; None when there is none."""
    given = given or os.environ.get(DATA_ENV)
    if given:
        return Path(given)
    for up in REPO.parents:
        if (up / "shared" / "data").is_dir():
            return up / "shared" / "data"
    return None


def data_path(given: str | None, *parts: str) -> Path:
    """``data_root(given) / parts``; a SystemExit naming the flag and variable when there is
    no data root."""
    root = data_root(given)
    if root is None:
        raise SystemExit(f"no shared data folder for {'/'.join(parts)}: pass --data-root DIR "
                         f"or set {DATA_ENV}")
    return root.joinpath(*parts)


# --- machine -------------------------------------------------------------------------------
def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info(loadavg_before: Sequence[float] | None = None) -> dict[str, Any]:
    """Machine, library versions, thread settings and the load average now (with the one of
    the run's start when given): the ``machine`` entry of every benchmark's JSON."""
    import numba
    import numpy
    import torch

    import plenoctree

    try:
        layer = numba.threading_layer()
    except ValueError:
        layer = "not initialised"
    info: dict[str, Any] = {
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": layer,
        "torch_threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "torch": torch.__version__,
        "numba": numba.__version__,
        "plenoctree": plenoctree.__version__,
        "plenoctree_path": str(Path(plenoctree.__file__).parent),
        "platform": platform.platform(),
        "loadavg": list(os.getloadavg()),
    }
    if loadavg_before is not None:
        info["loadavg_before"] = list(loadavg_before)
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    try:
        info["triton"] = importlib.metadata.version("triton")
    except importlib.metadata.PackageNotFoundError:
        pass
    return info


def machine_line(m: dict[str, Any]) -> str:
    """One line for the end of a benchmark's table: CPU, cores, numba and its threads, and the
    load average before and after the run (``m``: :func:`machine_info` given the start's)."""
    before = m.get("loadavg_before", m["loadavg"])
    return (f"machine: {m['cpu_model']}, {m['cpu_count']} cores, numba {m['numba']} "
            f"({m['numba_threading_layer']}, {m['numba_threads']} threads); load average "
            f"before {before[0]:.2f}, after {m['loadavg'][0]:.2f}")


# --- timing --------------------------------------------------------------------------------
@dataclass
class Timing:
    """Timed calls of one function: wall-clock and process CPU seconds (all threads) per call,
    and the last call's return value."""

    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    result: Any = None

    @property
    def median(self) -> float:
        """Median wall seconds per call."""
        return statistics.median(self.wall)

    @property
    def spread(self) -> float:
        """Half the range of the wall seconds (the ``±`` of the tables)."""
        return (max(self.wall) - min(self.wall)) / 2

    @property
    def cpu_median(self) -> float:
        """Median process CPU seconds per call: robust to other jobs sharing the cores."""
        return statistics.median(self.cpu)

    def call(self, fn: Callable[[], Any]) -> None:
        """Time one call of ``fn``."""
        c0, t0 = time.process_time(), time.perf_counter()
        self.result = fn()
        self.wall.append(time.perf_counter() - t0)
        self.cpu.append(time.process_time() - c0)

    def scaled(self, k: float) -> Timing:
        """The same timing with every figure multiplied by ``k`` (per frame, per ray, ...)."""
        return Timing([w * k for w in self.wall], [c * k for c in self.cpu], self.result)

    def summary(self) -> dict[str, float]:
        """``ms`` (median), ``ms_min``, ``ms_max``, ``ms_spread``, ``cpu_ms``, ``repeats``."""
        return {"ms": 1e3 * self.median, "ms_min": 1e3 * min(self.wall),
                "ms_max": 1e3 * max(self.wall), "ms_spread": 1e3 * self.spread,
                "cpu_ms": 1e3 * self.cpu_median, "repeats": len(self.wall)}


def timed(fn: Callable[[], Any], repeat: int, warmup: bool = True) -> Timing:
    """``repeat`` timed calls of ``fn`` after one untimed warm-up call (``warmup``)."""
    if warmup:
        fn()
    t = Timing()
    for _ in range(repeat):
        t.call(fn)
    return t


def interleaved(fns: Mapping[str, Callable[[], Any]], repeat: int,
                warmup: bool = True) -> dict[str, Timing]:
    """Time the functions of ``fns`` in turn, ``repeat`` passes (so a noisy machine slows them
    alike), after one warm-up call of each."""
    if warmup:
        for fn in fns.values():
            fn()
    out = {name: Timing() for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            out[name].call(fn)
    return out


# --- output --------------------------------------------------------------------------------
def jsonable(obj: Any) -> Any:
    """``obj`` with numpy scalars and arrays as Python numbers and lists, tuples as lists,
    NaN / infinity as None (strict JSON) and any other object as its ``str``."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):                       # numpy scalar or array
        return jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if obj is None or isinstance(obj, (str, int, float)):
        return obj
    return str(obj)


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` (through :func:`jsonable`) as indented JSON to ``path``, atomically;
    returns the path."""
    from plenoctree._util import atomic_save_json

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_save_json(path, jsonable(obj))
    return path


def fmt(v: Any, spec: str) -> str:
    """``v`` formatted with ``spec``, or "–" for None."""
    return "–" if v is None else format(v, spec)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A markdown table of already formatted cells (anything else through ``str``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


# --- processes -----------------------------------------------------------------------------
def run_python(args: Sequence[str], env: Mapping[str, str] | None = None,
               capture: bool = False) -> subprocess.CompletedProcess:
    """``python ARGS`` in a fresh process of this interpreter, with ``env`` added to this
    process's environment; raises ``CalledProcessError`` when it fails.

    For what must differ per configuration and be in place before numba or torch load (a
    ``NUMBA_CACHE_DIR``, a ``NUMBA_NUM_THREADS``), or what must not share a process (peak
    memory): the caller's docstring says which. ``capture``: keep stdout/stderr as text.
    """
    return subprocess.run([sys.executable, *map(str, args)], env={**os.environ, **(env or {})},
                          check=True, capture_output=capture, text=capture)


def child_json(args: Sequence[str], env: Mapping[str, str] | None = None) -> Any:
    """:func:`run_python` whose last line of output is a JSON value; returns it."""
    try:
        res = run_python(args, env, capture=True)
    except subprocess.CalledProcessError as e:
        raise RuntimeError(f"{' '.join(map(str, args))} failed:\n{e.stderr[-2000:]}") from None
    return json.loads(res.stdout.strip().splitlines()[-1])
