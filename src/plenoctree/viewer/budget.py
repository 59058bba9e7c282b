"""How much GPU texture memory the web viewer needs for a tree file, checked before serving.

Mirrors the page's packing (``static/tree.js``): one int32 texel per cell, and per leaf with
σ > 0 ``1 + 3 ceil((B - 1) / 4)`` RGBA16F texels (8 bytes each). The page refuses trees over
its budget (``DEFAULT_MAX_MB``, ``max_mb`` in ``config.json``); the CLI says so first.
"""

from __future__ import annotations

import math
import os

import numpy as np

from ..errors import ConfigError, TreeFormatError
from .._npz import NpzReader

__all__ = ["DEFAULT_MAX_MB", "texels_per_leaf", "viewer_texture_bytes",
           "check_texture_budget"]

#: The page's default texture budget in MB (main.js uses the same default).
DEFAULT_MAX_MB = 2048


def texels_per_leaf(basis_dim: int) -> int:
    """RGBA16F texels the page uses per non-empty leaf of a ``basis_dim``-basis tree."""
    return 1 + 3 * math.ceil((int(basis_dim) - 1) / 4)


def viewer_texture_bytes(path: str | os.PathLike) -> int:
    """Bytes of textures the page will allocate for the tree file ``path`` (.npz or .plnz).

    Counts leaves with σ > 0 exactly when the file holds σ separately (compressed files) or
    when the cheap upper bound (every cell a leaf) exceeds :data:`DEFAULT_MAX_MB`.
    """
    with NpzReader(path) as r:
        r.require("child")
        n_cells = int(np.prod(r.shape("child")))
        if "quant_colors" in r:
            qc = r.shape("quant_colors")
            ret = r.shape("data_retained")[0] if "data_retained" in r else 0
            b = qc[0] + ret
            n_leaves = int(np.count_nonzero(r.read("sigma") > 0))
        elif "data" in r:
            ds = r.shape("data")
            if len(ds) != 5:
                r.fail(f"'data' must have shape [n, 2, 2, 2, D], got {list(ds)}")
            b = (ds[4] - 1) // 3                       # D = 3B + 1 (RGBA: D = 4, B = 1)
            n_leaves = n_cells
            if n_cells * texels_per_leaf(b) * 8 > DEFAULT_MAX_MB * 1e6:
                data = r.read("data")
                n_leaves = int(np.count_nonzero((r.read("child") == 0) & (data[..., -1] > 0)))
        else:
            raise TreeFormatError(f"{path}: not a tree file (no 'data' or 'quant_colors')")
    return int(n_cells * 4 + n_leaves * texels_per_leaf(max(b, 1)) * 8)


def check_texture_budget(path: str | os.PathLike, max_mb: float = DEFAULT_MAX_MB) -> int:
    """Raise :class:`ConfigError` with a level-of-detail hint when the tree needs more than
    ``max_mb`` MB of textures; returns the bytes needed."""
    need = viewer_texture_bytes(path)
    if need > max_mb * 1e6:
        name = os.path.basename(os.fspath(path))
        stem = name.rsplit(".", 1)[0]
        raise ConfigError(
            f"{path}: the viewer would need {need / 1e6:.0f} MB of GPU textures, more than its "
            f"{max_mb:g} MB budget. Make a smaller tree for the web, e.g.\n"
            f"  plenoctree lod {path} --target-mb 30 --out {stem}_web.plnz\n"
            f"(or raise the budget with --max-mb if the GPU has the memory)")
    return need
