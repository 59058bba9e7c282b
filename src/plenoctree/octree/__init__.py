"""The sparse octree (svox-compatible arrays), its builders and its file formats.

- :class:`Octree` (``tree.py``): the arrays, geometry helpers and ``query``.
- ``build.py``: ``Octree.from_grid`` / ``Octree.dense`` (vectorised, level by level).
- ``check.py``: ``Octree.check_integrity``.
- ``io.py``: ``save_tree`` / ``load_tree`` (native ``.npz``), ``export_svox`` / ``import_svox``.
"""

from __future__ import annotations

from .._lazy import lazy_package

_LAZY = {
    'dense_tree': '.build',
    'tree_from_grid': '.build',
    'FORMAT_VERSION': '.io',
    'export_svox': '.io',
    'import_svox': '.io',
    'load_tree': '.io',
    'save_tree': '.io',
    'Octree': '.tree',
    'parse_data_format': '.tree',
}
lazy_package(__name__, _LAZY)

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
]
