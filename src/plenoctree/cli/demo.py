"""``plenoctree demo``: the main job on the embedded procedural scene."""

from __future__ import annotations

import argparse
from pathlib import Path


def _run(args: argparse.Namespace) -> int:
    from ..demo import DemoConfig, run_demo

    cfg = DemoConfig(out=Path(args.out), image_size=args.image_size, grid=args.grid,
                     n_test=args.n_test, backend=args.backend, seed=args.seed)
    run_demo(cfg)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` command."""
    from ..demo import DemoConfig

    d = DemoConfig()
    p = sub.add_parser("demo", help="run the main job on the embedded procedural scene")
    p.add_argument("--out", default=str(d.out), help=f"output folder (default {d.out})")
    p.add_argument("--image-size", type=int, default=d.image_size,
                   help=f"image width/height in pixels (default {d.image_size})")
    p.add_argument("--grid", type=int, default=d.grid,
                   help=f"octree finest resolution, a power of two (default {d.grid})")
    p.add_argument("--n-test", type=int, default=d.n_test,
                   help=f"test views (default {d.n_test})")
    p.add_argument("--backend", default=d.backend, help="auto, numba or torch (default auto)")
    p.add_argument("--seed", type=int, default=d.seed, help="camera seed (default 0)")
    p.set_defaults(func=_run)
