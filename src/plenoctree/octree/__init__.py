"""The sparse octree (svox-compatible arrays), its builders and its file formats.

- :class:`Octree` (``tree.py``): the arrays, geometry helpers and ``query``.
- ``build.py``: ``Octree.from_grid`` / ``Octree.dense`` (vectorised, level by level).
- ``check.py``: ``Octree.check_integrity``.
- ``limits.py``: ``MAX_DEPTH`` (deepest cell depth any tree may have) and the per-ray step cap.
- ``io.py``: ``save_tree`` / ``load_tree`` (native ``.npz``), ``export_svox`` / ``import_svox``.
"""

from __future__ import annotations

from .build import dense_tree, tree_from_grid
from .io import FORMAT_VERSION, export_svox, import_svox, load_tree, save_tree
from .limits import MAX_DEPTH, max_steps
from .tree import Octree, parse_data_format

__all__ = [
    "Octree",
    "tree_from_grid",
    "dense_tree",
    "parse_data_format",
    "save_tree",
    "load_tree",
    "export_svox",
    "import_svox",
    "FORMAT_VERSION",
    "MAX_DEPTH",
    "max_steps",
]
