"""The one ray traversal of the numba kernels: box entry, leaf lookup, exit face, SH/SG basis.

Shared by the renderer (:mod:`._render_numba`) and the fine-tuning kernels
(:mod:`plenoctree.optim._render_grad_numba`), so every numba kernel marches exactly the same
segments as the torch twin (:mod:`._torch_impl`, the spec: read its docstring for the maths).

How a ray marches (tree space ``p(t) = o' + t d'``, ``t`` in world units):

* :func:`ray_start` normalises the direction, maps the ray to tree space and clips it to the
  box ``[0, 1]^3`` (``t0 < t1`` when it hits); the origin, direction and reciprocal it returns
  are in grid units (tree space × ``2^QUANT_BITS``, a power of two: every product and sum is
  the tree-space one scaled exactly), so the lookups below need no multiplication by the scale.
* :func:`next_leaf` finds the leaf holding ``p(t + ε_t)`` and the end of its segment. Points are
  quantised to integer coordinates (``QUANT_BITS`` bits per axis), so the cell at level ``l``
  is one bit of each coordinate and the descent is integer-only. The nodes of the current
  root-to-leaf path stay on a stack: when the ray leaves a leaf, the highest bit that differs
  between the old and the new integer point names the deepest common ancestor and the descent
  restarts there (most exits cross into a sibling or a cousin: one or two levels, not the
  whole depth). The descent never goes below ``max_level`` (``octree.limits.MAX_DEPTH``: a
  deeper tree cannot write past the stack), and every kernel stops a ray after
  ``octree.limits.max_steps(depth)`` segments (no geometry can make a ray march forever).

State between calls lives in ``st`` (int64 ``[4]``: level, previous integer point; set
``st[1] = -1`` at the start of every ray) and ``stack`` (int64 ``[STACK_SIZE]``, ``max_level < STACK_SIZE``).
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import binding as _llvm
from llvmlite import ir as _ir
from numba import njit
from numba.core import cgutils as _cgutils
from numba.core import types as _types
from numba.extending import intrinsic

from .. import sh as _sh
from ..octree.limits import MAX_DEPTH, max_steps
from .options import KIND_RGBA, KIND_SG, KIND_SH, QUANT_BITS

__all__ = ["ray_start", "ray_octant", "common_level", "next_leaf", "look_ahead", "prefetch_row",
           "basis_values", "leaf_logits", "pad_scratch", "SCRATCH_PAD",
           "STACK_SIZE", "MAX_LEVEL", "MAX_STEPS", "LOOKAHEAD", "QUEUE"]

#: Deepest node level a descent reaches (= the deepest cell depth a tree may have; deeper
#: cells are never looked up, so no tree can make a descent write past the stack).
MAX_LEVEL = MAX_DEPTH
#: Entries of the path stack (levels ``0..MAX_LEVEL`` plus one spare).
STACK_SIZE = MAX_LEVEL + 2
#: Segments one ray may march at most (``octree.limits.max_steps`` of the deepest tree any
#: loader accepts): only rays that could never finish are cut.
MAX_STEPS = max_steps(MAX_DEPTH)

#: Leaves looked up ahead of the one being shaded (:func:`look_ahead`), and the size of the
#: ring buffer holding them (a power of two > LOOKAHEAD).
LOOKAHEAD = 6
QUEUE = 8
_QMASK = QUEUE - 1

#: fastmath flags of every kernel that marches: none that changes a finite value (no
#: reassociation, contraction or approximate functions), so the segments are the twin's
#: whatever LLVM's pipeline makes of the code. (With ``fastmath=True`` the render kernel loaded
#: from numba's disk cache was optimised differently from the freshly compiled one, and a few
#: lookups landed in the neighbouring leaf: 4.6e-3 on 3 of 480 k values of a lego view.)
MARCH_MATH = {"nnan", "ninf", "nsz"}

_SCALE = float(2 ** QUANT_BITS)
_INV_SCALE = 1.0 / _SCALE
_BIG = 1e30
_TOP = QUANT_BITS - 1
_QMAX = (1 << QUANT_BITS) - 1

_C0 = _sh.SH_C0
_C1 = _sh.SH_C1
_C20, _C21, _C22, _C23, _C24 = _sh.SH_C2
_C30, _C31, _C32, _C33, _C34, _C35, _C36 = _sh.SH_C3
_C40, _C41, _C42, _C43, _C44, _C45, _C46, _C47, _C48 = _sh.SH_C4


#: Bytes every per-thread scratch array of the parallel kernels is padded to (two 64-byte
#: lines): the march state is written at every segment, and two threads writing one cache
#: line (false sharing) made two threads no faster than one.
SCRATCH_PAD = 128


@njit(cache=True, inline="always")
def pad_scratch(n, itemsize):
    """``n`` elements of ``itemsize`` bytes, rounded up to whole :data:`SCRATCH_PAD` bytes."""
    per = SCRATCH_PAD // itemsize
    return (n + per - 1) // per * per


_PREFETCH = "llvm.prefetch.p0" if _llvm.llvm_version_info[0] >= 17 else "llvm.prefetch.p0i8"


@intrinsic
def _prefetch(typingctx, arr, i, j):
    """Hint the CPU to fetch ``arr[i, j]``'s cache line (``llvm.prefetch``: read, keep in all
    cache levels); no effect on values, no fault on any address."""
    sig = _types.void(arr, i, j)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = _cgutils.get_item_pointer(context, builder, aryty, ary, [args[1], args[2]],
                                        wraparound=False)
        i8p = builder.bitcast(ptr, _ir.IntType(8).as_pointer())
        i32 = _ir.IntType(32)
        fnty = _ir.FunctionType(_ir.VoidType(), [i8p.type, i32, i32, i32])
        fn = _cgutils.get_or_insert_function(builder.module, fnty, _PREFETCH)
        builder.call(fn, [i8p, _ir.Constant(i32, 0), _ir.Constant(i32, 3), _ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, inline="always")
def prefetch_row(data, cell):
    """Prefetch every cache line of row ``data[cell, :]`` (2-D C-contiguous ``data``)."""
    dim = data.shape[1]
    for k in range(0, dim - 1, 16):          # 16 float32 = one 64-byte line
        _prefetch(data, cell, k)
    _prefetch(data, cell, dim - 1)


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def basis_values(kind, n_b, x, y, z, sg, b_lo, b_hi, out):
    """Write the ``n_b`` basis values at unit direction (x, y, z) into ``out[:n_b]`` (in the
    dtype of ``out``), zero outside ``[b_lo, b_hi]``."""
    if kind == KIND_SG:
        for b in range(n_b):
            cos = sg[b, 1] * x + sg[b, 2] * y + sg[b, 3] * z
            out[b] = math.exp(sg[b, 0] * (cos - 1.0)) / n_b
    else:
        out[0] = _C0 if kind == KIND_SH else 1.0
        if n_b > 1:
            out[1] = -_C1 * y
            out[2] = _C1 * z
            out[3] = -_C1 * x
        if n_b > 4:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            out[4] = _C20 * xy
            out[5] = _C21 * yz
            out[6] = _C22 * (2.0 * zz - xx - yy)
            out[7] = _C23 * xz
            out[8] = _C24 * (xx - yy)
            if n_b > 9:
                out[9] = _C30 * y * (3.0 * xx - yy)
                out[10] = _C31 * xy * z
                out[11] = _C32 * y * (4.0 * zz - xx - yy)
                out[12] = _C33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
                out[13] = _C34 * x * (4.0 * zz - xx - yy)
                out[14] = _C35 * z * (xx - yy)
                out[15] = _C36 * x * (xx - 3.0 * yy)
            if n_b > 16:
                out[16] = _C40 * xy * (xx - yy)
                out[17] = _C41 * yz * (3.0 * xx - yy)
                out[18] = _C42 * xy * (7.0 * zz - 1.0)
                out[19] = _C43 * yz * (7.0 * zz - 3.0)
                out[20] = _C44 * (zz * (35.0 * zz - 30.0) + 3.0)
                out[21] = _C45 * xz * (7.0 * zz - 3.0)
                out[22] = _C46 * (xx - yy) * (7.0 * zz - 1.0)
                out[23] = _C47 * xz * (xx - 3.0 * yy)
                out[24] = _C48 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy))
    for b in range(n_b):
        if b < b_lo or b > b_hi:
            out[b] = 0.0


@njit(cache=True, fastmath=True)
def leaf_logits(data, cell, kind, n_b, basis):
    """The colour of ``cell`` before the sigmoid: ``(Σ_b k_{r,b} Y_b, …g, …b)`` in the dtype of
    ``basis`` (float32 in the renderer and in training, float64 for gradcheck); ``basis`` is 0
    outside the used range, ``basis[0]`` scales RGBA's plain values (1, or 0 if excluded)."""
    if kind == KIND_RGBA:
        return data[cell, 0] * basis[0], data[cell, 1] * basis[0], data[cell, 2] * basis[0]
    zero = basis[0] - basis[0]
    ar = zero
    ag = zero
    ab = zero
    for b in range(n_b):
        yb = basis[b]
        ar += data[cell, b] * yb
        ag += data[cell, n_b + b] * yb
        ab += data[cell, 2 * n_b + b] * yb
    return ar, ag, ab


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def ray_start(offset, invr, ox, oy, oz, dx, dy, dz, eps):
    """Unit direction, origin, direction and its reciprocal in grid units (tree space ×
    ``2^QUANT_BITS``: the arguments of :func:`next_leaf`), the box interval and the step push
    ``ε_t = eps / |d'|`` (``d'``: the tree-space direction) of one ray.

    Returns ``(dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, eps_t)`` (float64; the
    ray misses the box when ``not t0 < t1``)."""
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx /= norm
    dy /= norm
    dz /= norm
    px = offset[0] + invr[0] * ox
    py = offset[1] + invr[1] * oy
    pz = offset[2] + invr[2] * oz
    vx = invr[0] * dx
    vy = invr[1] * dy
    vz = invr[2] * dz
    t0 = 0.0
    t1 = _BIG
    for a in range(3):
        p = px if a == 0 else (py if a == 1 else pz)
        v = vx if a == 0 else (vy if a == 1 else vz)
        if v == 0.0:
            if p < 0.0 or p > 1.0:
                t1 = -_BIG
        else:
            ta = (0.0 - p) / v
            tb = (1.0 - p) / v
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    ix = 1.0 / vx if vx != 0.0 else _BIG
    iy = 1.0 / vy if vy != 0.0 else _BIG
    iz = 1.0 / vz if vz != 0.0 else _BIG
    eps_t = eps / math.sqrt(vx * vx + vy * vy + vz * vz)
    return (dx, dy, dz, px * _SCALE, py * _SCALE, pz * _SCALE, vx * _SCALE, vy * _SCALE,
            vz * _SCALE, ix * _INV_SCALE, iy * _INV_SCALE, iz * _INV_SCALE, t0, t1, eps_t)


@njit(cache=True, inline="always")
def ray_octant(vx, vy, vz):
    """Octant of a direction, ``4·[vx ≥ 0] + 2·[vy ≥ 0] + [vz ≥ 0]`` (the column of
    :mod:`.empty_skip`'s tables)."""
    return (4 if vx >= 0.0 else 0) + (2 if vy >= 0.0 else 0) + (1 if vz >= 0.0 else 0)


@njit(cache=True, inline="always")
def common_level(level, qx, qy, qz, st):
    """Deepest level ``<= level`` whose node on the previous lookup's path (integer point
    ``st[1:4]``) also holds the integer point ``q``: the highest bit in which the two points
    differ names it."""
    diff = (qx ^ st[1]) | (qy ^ st[2]) | (qz ^ st[3])
    while level > 0 and (diff >> (QUANT_BITS - level)) != 0:
        level -= 1
    return level


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def next_leaf(child, skip, shift, oc, px, py, pz, vx, vy, vz, ix, iy, iz, t, eps_t, t1,
              use_stack, max_level, st, stack):
    """The leaf holding ``p(t + eps_t)`` and the end of its segment.

    Returns ``(cell, t_end, n_desc)``: the flat cell index (``node * 8 + i*4 + j*2 + k``), the
    segment end ``min(max(exit, t + eps_t), t1)`` and the number of ``child`` reads this lookup
    made. ``use_stack=False`` descends from the root every time (the reference the tests
    compare the stack against).

    Empty-space skipping (:mod:`.empty_skip`): an empty leaf whose ``child`` entry is
    ``-(row + 1)`` pushes its exit planes forward by ``skip[row, oc] << (shift - skip[row, 8])``
    integer units (``oc``: :func:`ray_octant`; column 8: the row's nested grid, each one level
    finer), so the segment runs to the end of the empty region ahead;
    with a plain ``child`` (no negative entries) nothing changes."""
    ts = t + eps_t
    # Truncate, then clamp in integers: the floor of the point clamped to the box (truncation
    # differs from the floor only below 0, where the clamp gives 0 either way; the point is
    # within ε of the box, far inside the int64 range).
    qx = min(max(int(px + ts * vx), 0), _QMAX)
    qy = min(max(int(py + ts * vy), 0), _QMAX)
    qz = min(max(int(pz + ts * vz), 0), _QMAX)
    level = st[0]
    if use_stack and st[1] >= 0:
        level = common_level(level, qx, qy, qz, st)
    else:
        level = 0
        stack[0] = 0
    node = stack[level]
    n_desc = 0
    while True:
        sh = _TOP - level
        cell = node * 8 + (((qx >> sh) & 1) << 2) + (((qy >> sh) & 1) << 1) + ((qz >> sh) & 1)
        c = child[cell]
        n_desc += 1
        if c <= 0 or level >= max_level:
            break
        node += c
        level += 1
        stack[level] = node
    st[0] = level
    st[1] = qx
    st[2] = qy
    st[3] = qz
    sh = _TOP - level
    r = 0
    if c < 0:
        r = np.int64(skip[-c - 1, oc]) << (shift - skip[-c - 1, 8])
    # Exit face of the leaf (pushed by r): its low (d < 0) or high (d >= 0) side per axis.
    bx = np.float64((((qx >> sh) + 1) << sh) + r if vx >= 0.0 else ((qx >> sh) << sh) - r)
    by = np.float64((((qy >> sh) + 1) << sh) + r if vy >= 0.0 else ((qy >> sh) << sh) - r)
    bz = np.float64((((qz >> sh) + 1) << sh) + r if vz >= 0.0 else ((qz >> sh) << sh) - r)
    tx = (bx - px) * ix
    ty = (by - py) * iy
    tz = (bz - pz) * iz
    t_end = min(max(min(tx, min(ty, tz)), ts), t1)
    return cell, t_end, n_desc


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def look_ahead(child, skip, shift, oc, data, px, py, pz, vx, vy, vz, ix, iy, iz, eps_t, t1,
               use_stack, max_level, max_steps, st, stack, qc, qe, head, tail, tq, steps):
    """Look up leaves ahead of the one being shaded, up to :data:`LOOKAHEAD` queued.

    The queue ``qc`` (cells, int64 ``[QUEUE]``), ``qe`` (segment ends, float64 ``[QUEUE]``)
    holds the leaves ``head .. tail - 1`` (ring indices ``& (QUEUE - 1)``) of the segments
    after the current one; ``tq`` is where the next lookup starts and ``steps`` counts the
    lookups of this ray (at most ``max_steps``). Each leaf found gets its ``data`` row
    prefetched, so that by the time the ray shades it (reads σ, and the colour when σ > 0) the
    row is in cache: the memory latency of the next leaves overlaps the work on this one. A ray
    that stops early has looked up a few leaves it never shades (their values are not used).
    The segments are exactly those of repeated :func:`next_leaf` calls (``use_stack``,
    ``skip``: see there). A leaf whose ``child`` entry is negative (empty, :mod:`.empty_skip`)
    is queued as ``-1 - cell`` and its row not prefetched: the caller skips a negative cell
    without reading its σ (with a plain ``child`` every leaf is queued as itself). Start a ray
    with ``head = tail = steps = 0``, ``tq = t0`` and :func:`next_leaf`'s ``st[1] = -1``.

    Returns ``(tail, tq, steps)``."""
    while tail - head < LOOKAHEAD and tq < t1 and steps < max_steps:
        steps += 1
        cell, t_end, _ = next_leaf(child, skip, shift, oc, px, py, pz, vx, vy, vz, ix, iy, iz,
                                   tq, eps_t, t1, use_stack, max_level, st, stack)
        # An empty leaf of the skip tables: its row is not needed. (Re-reading child[cell], an
        # L1 hit, measured 2-3 % faster than next_leaf returning the entry it read.)
        if child[cell] < 0:
            cell = -1 - cell
        else:
            prefetch_row(data, cell)
        qc[tail & _QMASK] = cell
        qe[tail & _QMASK] = t_end
        tail += 1
        tq = t_end
    return tail, tq, steps
