"""Compression for the web (paper B.2) and level of detail.

- :func:`compress` / :func:`decompress`: per-basis median-cut codebooks (float16, 2^bits
  colours, uint16 index per leaf), σ as float16, optional unquantised first bases;
- :func:`save_compressed` / :func:`load_compressed`: the ``.plnz`` file (DEFLATE zip, also
  reads the original PlenOctree compressed files); :func:`load_any_tree` reads every kind;
- :func:`make_lod` / :func:`fit_to_size`: smaller trees (lower SH degree, merged leaves,
  pruning) to a size budget.

Importing this package compiles nothing; the median-cut kernel is compiled on first use.
"""

from __future__ import annotations

from .._lazy import lazy_package

_LAZY = {
    'CompressedTree': '.codec',
    'CompressOptions': '.codec',
    'compress': '.codec',
    'decompress': '.codec',
    'is_compressed_file': '.fileio',
    'load_any_tree': '.fileio',
    'load_compressed': '.fileio',
    'save_compressed': '.fileio',
    'LodOptions': '.lod',
    'fit_to_size': '.lod',
    'make_lod': '.lod',
    'merge_to_depth': '.lod',
    'prune': '.lod',
    'truncate_sh': '.lod',
    'median_cut': '.median_cut',
}
lazy_package(__name__, _LAZY)

__all__ = [
    "CompressOptions", "CompressedTree", "compress", "decompress",
    "save_compressed", "load_compressed", "load_any_tree", "is_compressed_file",
    "LodOptions", "make_lod", "fit_to_size", "truncate_sh", "merge_to_depth", "prune",
    "median_cut",
]
