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

from .codec import CompressedTree, CompressOptions, compress, decompress
from .fileio import is_compressed_file, load_any_tree, load_compressed, save_compressed
from .lod import LodOptions, fit_to_size, make_lod, merge_to_depth, prune, truncate_sh
from .quantize import median_cut

__all__ = [
    "CompressOptions", "CompressedTree", "compress", "decompress",
    "save_compressed", "load_compressed", "load_any_tree", "is_compressed_file",
    "LodOptions", "make_lod", "fit_to_size", "truncate_sh", "merge_to_depth", "prune",
    "median_cut",
]
