"""``plenoctree info``: version, compute backends, threads and GPU."""

from __future__ import annotations

import argparse
import os
import platform


def collect_info() -> dict:
    """Return a dict describing the installation: versions, backends, threads, GPU."""
    import numpy
    import torch

    from .. import __version__
    from ..render import available_backends

    try:
        import numba

        numba_version = numba.__version__
        numba_threads = numba.config.NUMBA_NUM_THREADS
    except ImportError:  # pragma: no cover - numba is a core dependency
        numba_version, numba_threads = None, None
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "plenoctree": __version__,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "torch": torch.__version__,
        "numba": numba_version,
        "backends": available_backends(),
        "cpu_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "numba_threads": numba_threads,
        "gpu": gpu,
    }


def _run(args: argparse.Namespace) -> int:
    info = collect_info()
    if args.json:
        import json

        print(json.dumps(info, indent=2))
    else:
        width = max(len(k) for k in info)
        for key, value in info.items():
            if isinstance(value, list):
                value = ", ".join(value)
            print(f"{key:<{width}}  {value if value is not None else 'none'}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``info`` command."""
    p = sub.add_parser("info", help="print version, backends, threads and GPU")
    p.add_argument("--json", action="store_true", help="print as JSON")
    p.set_defaults(func=_run)
