"""Hard limits every tree must respect, stated once for every reader, writer and renderer.

``MAX_DEPTH``
    The deepest **cell depth** a tree may have (as in :attr:`Octree.depth_limit`: the root's
    cells have depth 0, the leaves of a ``2^d`` grid have depth ``d - 1``; a tree of cell depth
    ``D`` has ``D + 1`` levels of nodes). 21 is what every renderer supports:

    * the WebGL page descends at most 22 levels (float32 positions; ``MAX_VIEWER_DEPTH`` in
      ``viewer/static/tree.js``), i.e. cell depth <= 21: the tightest limit;
    * the torch twin descends at most ``QUANT_BITS - 1 = 29`` levels;
    * the numba renderer and fine-tuning kernels keep the root-to-leaf path on a
      ``QUANT_BITS + 1 = 31``-entry stack (a deeper chain would write past it).

    A 512³ extraction has cell depth 8, so adaptive refinement has 13 levels of headroom.
    (Cells deeper than ~18 are smaller than the default ``RenderOptions.step_eps = 1e-6`` tree
    units; they render, but a ray may step over them.) Checked by
    :meth:`Octree.check_integrity`, hence by every load and save (native, svox, ``.plnz``).
    Kernels must also guard their descent loops with it: ``level <= MAX_DEPTH``.

``MAX_STEPS_CAP`` / :func:`max_steps`
    The most segments one ray may march, as the WebGL shader caps it: a ray crosses at most
    about ``3 * 2^(D + 1)`` cells of a tree of cell depth ``D``; ``+ 64`` slack, and never more
    than ``MAX_STEPS_CAP = 2^20``. Every renderer stops a ray after ``max_steps(D)`` steps, so no
    input (however extreme its geometry) can make a ray march forever.

``MAX_ABS_BOX``
    Bound on ``|invradius|``, ``|offset|`` and ``1 / invradius`` (the world radius) accepted at
    load: ``1e15``. Real scenes are many orders of magnitude inside it; beyond it the world ↔ tree
    transform loses all precision (a ray would never advance, or the step epsilon overflows).
    Within it, ``|invradius * d|`` neither overflows nor underflows in float64.

``MAX_RAY_ORIGIN``
    Bound on a ray origin's tree-space coordinates (the box is ``[0, 1]^3``): ``1e8``. Within
    it ``t + ε_t > t`` always holds in float64 (``ε_t = step_eps / |d'|``, ``t <~ 1e8 / |d'|``),
    so every step advances; farther origins are refused by ``render_rays``.

``MAX_ABS_VALUE``
    Bound on ``|data|`` (colour coefficients and σ) accepted at load: ``1e30``. A basis sum of
    25 such values stays inside float32; larger finite values overflow to ``inf - inf = NaN``.

``MAX_SG_SHARPNESS``, ``SG_AXIS_TOL``
    Bounds on an SG tree's ``extra_data`` (per lobe: sharpness λ, then the axis μ): ``0 <= λ <=
    1e4`` (a lobe 0.01 rad wide; svox's learned values are below 100) and ``| |μ| - 1 | <=
    1e-3``. Within them ``exp(λ (μ·d - 1)) <= exp(λ · 2e-3) < e^20`` stays finite in float32;
    a negative λ or a long axis makes it overflow (``inf · 0 = NaN`` colours).
"""

from __future__ import annotations

__all__ = ["MAX_DEPTH", "MAX_STEPS_CAP", "MAX_ABS_BOX", "MAX_ABS_VALUE", "MAX_RAY_ORIGIN",
           "MAX_SG_SHARPNESS", "SG_AXIS_TOL", "max_steps"]

MAX_DEPTH = 21
MAX_STEPS_CAP = 1 << 20
MAX_ABS_BOX = 1e15
MAX_RAY_ORIGIN = 1e8
MAX_ABS_VALUE = 1e30
MAX_SG_SHARPNESS = 1e4
SG_AXIS_TOL = 1e-3


def max_steps(depth: int) -> int:
    """Most segments a ray may march through a tree of cell depth ``depth`` (``<= 2^20``)."""
    d = min(max(int(depth), 0), MAX_DEPTH)
    return int(min(3 * 2 ** (d + 1) + 64, MAX_STEPS_CAP))
