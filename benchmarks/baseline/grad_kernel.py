"""numba CPU kernels for fine-tuning: the renderer's forward plus the paper's analytic backward.

Imported lazily (first differentiable numba render or first fine-tuning step); compiles once and
is cached on disk.

Per ray (``k`` = the ray's σ > 0 segments in marching order, ``C`` = rendered rgb incl. the
background ``c_N`` composited with the transmittance ``T_N`` left at the end):

* pass 1, :func:`_trace_one`: marches exactly like ``render._numba_impl._render_one`` (same
  quantised leaf lookup, same common-ancestor stack, same ``step_eps`` push, same early stop at
  ``T < stop_thresh``) and records, for every segment with σ > 0, its cell, ``δ`` (world
  units), ``exp(-σ δ)`` and its colour ``c`` (after the sigmoid). Segments with σ ≤ 0 add
  nothing to the colour and have zero gradient (σ = relu(σ̃)), so they are not recorded.
* pass 2, :func:`_backprop_one`: walks the record front to back with the running transmittance
  ``T_i`` and prefix ``P_i = Σ_{k≤i} w_k c_k``, given ``g = ∂L/∂C``:

  - colour (paper eq. 15 + chain rule through the sigmoid and the basis, constant per ray):
    ``∂L/∂k_{ch,b} += g_ch · w_i · c_ch (1 - c_ch) · Y_b``;
  - density (eq. 20; the suffix ``Σ_{k>i} w_k c_k + T_N c_N`` is ``C - P_i``):
    ``∂L/∂σ_i += δ_i Σ_ch g_ch (c_ch T_{i+1} - (C_ch - P_ch))``.

  Pass 2 reads only the record (the leaves it scatters into are still in cache from pass 1), so
  the tree is traversed once per ray; the record grows by doubling when a ray has more segments
  than its initial capacity.

Race-free scatter: rays are processed in tiles of :data:`TILE` rays, scheduled dynamically
over the threads; thread ``t`` accumulates into its own dense gradient slab ``grad3[t]`` (the
shape of the cell data), flags each cell it touches in ``flags[t]`` and appends it to
``touched[t]``. (Floating-point sums therefore depend on which thread ran which tile: results
are reproducible to rounding, not bit for bit, with more than one thread.) :func:`merge_chunks` then adds slabs ``1..`` into slab 0 over their touched
cells only (parallel over cells, each list is duplicate-free) and merges the touched lists (the
autograd path needs the merged gradient). The optimiser kernel :func:`step_touched` instead
reads the slabs directly: it visits every touched cell once, sums its slabs, updates it (SGD,
lazy Adam or lazy RMSprop), projects σ onto σ ≥ 0 and re-zeroes the slabs, flags and lists.
No work is proportional to the tree size: one step costs O(touched cells).

Arrays: ``child`` int32 ``[n_cells]`` (flat ``[n_nodes * 8]``), ``data`` float ``[n_cells, D]``
(float32 for training; float64 works too, for ``gradcheck``), ``sig`` ``[n_cells]`` a copy of
``data[:, -1]`` (the marching loop reads σ of every leaf it crosses; the compact copy — 4 bytes
per cell next to ``child`` — stays in cache where the ``D``-wide rows do not; the step kernels
keep it in sync), ``grad3`` same dtype
``[n_chunks, n_cells, D]``, ``flags`` uint8 ``[n_chunks, n_cells]``, ``touched`` int64
``[n_chunks, n_cells]``, ``n_touched`` int64 ``[n_chunks]``. Geometry is computed in float64,
as in the renderer.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from .render_kernel import _basis
from plenoctree.render.options import KIND_RGBA, QUANT_BITS

__all__ = ["TILE", "grad_kernel", "merge_chunks", "step_touched", "OPT_SGD", "OPT_ADAM",
           "OPT_RMSPROP", "pixel_rays", "initial_capacity"]

TILE = 64          # rays per interleaved tile of a chunk
_SCALE = float(2 ** QUANT_BITS)
_INV_SCALE = 1.0 / _SCALE
_BIG = 1e30
_REC = 5           # record columns: delta, att, c_r, c_g, c_b


def initial_capacity(depth_limit: int) -> int:
    """Segments a ray's record holds before it grows: a ray crosses at most about
    ``3 · 2^(depth+1)`` finest cells of the box."""
    return int(3 * (2 << max(0, min(int(depth_limit), 20))) + 64)


@njit(cache=True, fastmath=True, inline="always")
def _trace_one(child, sig, data, offset, invr, ox, oy, oz, dx, dy, dz, kind, n_b, sg, b_lo, b_hi,
               stop, eps, basis, stack, rec_cell, rec, out4):
    """March one ray (the renderer's algorithm) and record its σ > 0 segments.

    Writes ``Σ w c`` into ``out4[:3]`` and ``T_N`` into ``out4[3]``; fills ``basis[:n_b]`` (zero
    outside ``[b_lo, b_hi]``), ``rec_cell[s]`` and ``rec[s] = (δ, exp(-σδ), c_r, c_g, c_b)``.
    Returns the number of recorded segments, or ``-1`` when the record is full (the caller
    grows it and traces again). Colour dot products run in the dtype of ``data`` (float32 in
    training, as in the renderer; float64 for gradcheck).
    """
    out4[0] = 0.0
    out4[1] = 0.0
    out4[2] = 0.0
    out4[3] = 1.0
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
    if not t0 < t1:
        return 0
    ix_ = 1.0 / vx if vx != 0.0 else _BIG
    iy_ = 1.0 / vy if vy != 0.0 else _BIG
    iz_ = 1.0 / vz if vz != 0.0 else _BIG
    eps_t = eps / math.sqrt(vx * vx + vy * vy + vz * vz)
    sx = 1 if vx >= 0.0 else 0
    sy = 1 if vy >= 0.0 else 0
    sz = 1 if vz >= 0.0 else 0
    _basis(kind, n_b, dx, dy, dz, sg, basis)
    for b in range(n_b):
        if b < b_lo or b > b_hi:
            basis[b] = 0.0
    zero = basis[0] - basis[0]          # 0 in the dtype of the colour arithmetic

    cap = rec_cell.shape[0]
    n_seg = 0
    trans = 1.0
    t = t0
    level = 0
    stack[0] = 0
    qx_prev = -1
    qy_prev = 0
    qz_prev = 0
    top = QUANT_BITS - 1
    while t < t1:
        ts = t + eps_t
        qx = int(min(max((px + ts * vx) * _SCALE, 0.0), _SCALE - 1.0))
        qy = int(min(max((py + ts * vy) * _SCALE, 0.0), _SCALE - 1.0))
        qz = int(min(max((pz + ts * vz) * _SCALE, 0.0), _SCALE - 1.0))
        if qx_prev >= 0:
            diff = (qx ^ qx_prev) | (qy ^ qy_prev) | (qz ^ qz_prev)
            while level > 0 and (diff >> (QUANT_BITS - level)) != 0:
                level -= 1
        node = stack[level]
        while True:
            sh = top - level
            cell = node * 8 + (((qx >> sh) & 1) << 2) + (((qy >> sh) & 1) << 1) + ((qz >> sh) & 1)
            c = child[cell]
            if c == 0:
                break
            node += c
            level += 1
            stack[level] = node
        qx_prev = qx
        qy_prev = qy
        qz_prev = qz
        sh = top - level
        bx = (((qx >> sh) + sx) << sh) * _INV_SCALE
        by = (((qy >> sh) + sy) << sh) * _INV_SCALE
        bz = (((qz >> sh) + sz) << sh) * _INV_SCALE
        tx = (bx - px) * ix_
        ty = (by - py) * iy_
        tz = (bz - pz) * iz_
        t_end = min(max(min(tx, min(ty, tz)), ts), t1)
        sigma = sig[cell]
        if sigma > 0.0:
            if n_seg == cap:
                return -1
            delta = t_end - t
            att = math.exp(-sigma * delta)
            w = trans * (1.0 - att)
            if kind == KIND_RGBA:
                ar = data[cell, 0] * basis[0]       # basis[0] = 1, or 0 if excluded
                ag = data[cell, 1] * basis[0]
                ab = data[cell, 2] * basis[0]
            else:
                ar = zero
                ag = zero
                ab = zero
                for b in range(n_b):              # basis is 0 outside [b_lo, b_hi]
                    yb = basis[b]
                    ar += data[cell, b] * yb
                    ag += data[cell, n_b + b] * yb
                    ab += data[cell, 2 * n_b + b] * yb
            cr = 1.0 / (1.0 + math.exp(-ar))    # exp in the data dtype, the rest float64
            cg = 1.0 / (1.0 + math.exp(-ag))
            cb = 1.0 / (1.0 + math.exp(-ab))
            rec_cell[n_seg] = cell
            rec[n_seg, 0] = delta
            rec[n_seg, 1] = att
            rec[n_seg, 2] = cr
            rec[n_seg, 3] = cg
            rec[n_seg, 4] = cb
            out4[0] += w * cr
            out4[1] += w * cg
            out4[2] += w * cb
            n_seg += 1
            trans *= att
            if trans < stop:
                break
        t = t_end
    out4[3] = trans
    return n_seg


@njit(cache=True, fastmath=True, inline="always")
def _backprop_one(n_seg, rec_cell, rec, kind, n_b, b_lo, b_hi, basis, cr, cg, cb, gr, gg, gb,
                  grad, flags, touched, n_touched):
    """Scatter ``∂L/∂data`` of one ray (eq. 15 and 20) into ``grad``; returns the new
    ``n_touched`` of this chunk's touched-cell list."""
    dim = grad.shape[1]
    trans = 1.0
    pr = 0.0
    pg = 0.0
    pb = 0.0
    for s in range(n_seg):
        cell = rec_cell[s]
        delta = rec[s, 0]
        att = rec[s, 1]
        c0 = rec[s, 2]
        c1 = rec[s, 3]
        c2 = rec[s, 4]
        w = trans * (1.0 - att)
        t_next = trans * att
        pr += w * c0
        pg += w * c1
        pb += w * c2
        if flags[cell] == 0:
            flags[cell] = 1
            touched[n_touched] = cell
            n_touched += 1
        # density: δ_i Σ_ch g_ch (c_ch T_{i+1} - suffix_ch), suffix = C - P_i
        gsig = delta * (gr * (c0 * t_next - (cr - pr)) + gg * (c1 * t_next - (cg - pg))
                        + gb * (c2 * t_next - (cb - pb)))
        grad[cell, dim - 1] += gsig
        # colour: g_ch w c (1 - c) Y_b  (Y = basis, 0 outside [b_lo, b_hi])
        g0 = gr * w * c0 * (1.0 - c0)
        g1 = gg * w * c1 * (1.0 - c1)
        g2 = gb * w * c2 * (1.0 - c2)
        if kind == KIND_RGBA:
            yb = basis[0]
            grad[cell, 0] += g0 * yb
            grad[cell, 1] += g1 * yb
            grad[cell, 2] += g2 * yb
        else:
            for b in range(b_lo, b_hi + 1):
                yb = basis[b]
                grad[cell, b] += g0 * yb
                grad[cell, n_b + b] += g1 * yb
                grad[cell, 2 * n_b + b] += g2 * yb
        trans = t_next
    return n_touched


@njit(parallel=True, cache=True, fastmath=True)
def grad_kernel(child, sig, data, offset, invr, origins, dirs, aux, mode, scale, kind, n_b, sg, b_lo,
                b_hi, bg, stop, eps, cap0, rgb_out, grad3, flags, touched, n_touched, sse):
    """Forward + analytic backward for ``[N, 3]`` rays, accumulating into per-chunk slabs.

    ``mode == 0``: ``aux [N, 3]`` is ``∂L/∂rgb`` (autograd backward).
    ``mode == 1``: ``aux [N, 3]`` are target colours and ``L = scale · Σ_rays Σ_ch (C - aux)²``
    (fused MSE step; ``sse[t]`` accumulates thread ``t``'s un-scaled sum of squared errors).
    ``mode == 2``: forward only (``grad3`` is not touched).
    ``rgb_out [N, 3]`` receives the rendered colour ``C`` (background included).

    Work items are tiles of :data:`TILE` rays, scheduled dynamically; a tile runs on one thread
    ``t = numba.get_thread_id()`` and scatters into slab ``t``, so the caller must run at most
    ``n_chunks`` threads (:func:`plenoctree.optim._fast` does).
    """
    n = origins.shape[0]
    n_chunks = grad3.shape[0]
    n_tiles = (n + TILE - 1) // TILE
    # per-thread scratch (thread t uses row t; the caller runs at most n_chunks threads)
    basis_all = np.zeros((n_chunks, max(25, n_b)), dtype=data.dtype)
    stack_all = np.zeros((n_chunks, QUANT_BITS + 1), dtype=np.int64)
    out_all = np.zeros((n_chunks, 4), dtype=np.float64)
    cell_all = np.empty((n_chunks, cap0), dtype=np.int64)
    rec_all = np.empty((n_chunks, cap0, _REC), dtype=np.float64)
    for tile in prange(n_tiles):
        c = numba.get_thread_id()
        basis = basis_all[c]
        stack = stack_all[c]
        out4 = out_all[c]
        rec_cell = cell_all[c]
        rec = rec_all[c]
        grad = grad3[c]
        flg = flags[c]
        tch = touched[c]
        nt = n_touched[c]
        acc_sse = 0.0
        for i in range(tile * TILE, min(n, (tile + 1) * TILE)):
            while True:
                # float64 scalars: the direction is normalised in float64 (as the twin)
                n_seg = _trace_one(child, sig, data, offset, invr, np.float64(origins[i, 0]),
                                   np.float64(origins[i, 1]), np.float64(origins[i, 2]),
                                   np.float64(dirs[i, 0]), np.float64(dirs[i, 1]),
                                   np.float64(dirs[i, 2]), kind, n_b, sg, b_lo, b_hi, stop,
                                   eps, basis, stack, rec_cell, rec, out4)
                if n_seg >= 0:
                    break
                grow = 2 * rec_cell.shape[0]          # rare: a private, larger record
                rec_cell = np.empty(grow, dtype=np.int64)
                rec = np.empty((grow, _REC), dtype=np.float64)
            trans = out4[3]
            cr = out4[0] + trans * bg[0]
            cg = out4[1] + trans * bg[1]
            cb = out4[2] + trans * bg[2]
            rgb_out[i, 0] = cr
            rgb_out[i, 1] = cg
            rgb_out[i, 2] = cb
            if mode == 2:
                continue
            if mode == 1:
                er = cr - aux[i, 0]
                eg = cg - aux[i, 1]
                eb = cb - aux[i, 2]
                acc_sse += er * er + eg * eg + eb * eb
                gr = 2.0 * scale * er
                gg = 2.0 * scale * eg
                gb = 2.0 * scale * eb
            else:
                gr = aux[i, 0]
                gg = aux[i, 1]
                gb = aux[i, 2]
            if gr == 0.0 and gg == 0.0 and gb == 0.0:
                continue
            nt = _backprop_one(n_seg, rec_cell, rec, kind, n_b, b_lo, b_hi, basis, cr, cg,
                               cb, gr, gg, gb, grad, flg, tch, nt)
        n_touched[c] = nt
        sse[c] += acc_sse


@njit(parallel=True, cache=True)
def merge_chunks(grad3, flags, touched, n_touched):
    """Add slabs ``1..`` into slab 0 over their touched cells and merge the touched lists.

    After the call ``grad3[0]`` holds the full gradient, ``touched[0, :n_touched[0]]`` lists
    every touched cell once, and slabs ``1..`` and their flags/lists are zero again.
    """
    n_chunks = grad3.shape[0]
    dim = grad3.shape[2]
    for c in range(1, n_chunks):
        m = n_touched[c]
        for j in prange(m):
            cell = touched[c, j]
            for d in range(dim):
                grad3[0, cell, d] += grad3[c, cell, d]
                grad3[c, cell, d] = 0.0
        cnt = n_touched[0]
        for j in range(m):
            cell = touched[c, j]
            flags[c, cell] = 0
            if flags[0, cell] == 0:
                flags[0, cell] = 1
                touched[0, cnt] = cell
                cnt += 1
        n_touched[c] = 0
        n_touched[0] = cnt


OPT_SGD, OPT_ADAM, OPT_RMSPROP = 0, 1, 2


@njit(parallel=True, cache=True)
def step_touched(data, sig, grad3, flags, touched, n_touched, opt, lr, m1, m2, beta1, beta2, eps,
                 step):
    """Apply one optimiser step to every touched cell, reading the gradient straight from the
    per-thread slabs (no separate merge), then re-zero slabs, flags and lists.

    ``opt``: :data:`OPT_SGD` (``data -= lr g``), :data:`OPT_ADAM` (lazy Adam: moments
    ``m1, m2 [n_cells, D]`` updated only where the batch has a gradient, as
    ``torch.optim.SparseAdam``, bias correction by the global 1-based ``step``) or
    :data:`OPT_RMSPROP` (``m2 = β2 m2 + (1 - β2) g²``, ``data -= lr g / (√m2 + eps)``, lazy).
    Tiny moments are flushed to 0 (no denormals). σ is then projected onto ``σ ≥ 0`` (the
    renderer uses ``relu(σ)``, so no render changes, and the tree stays valid for
    ``save_tree``) and copied to ``sig``.

    Each cell is handled once: by the first chunk whose list holds it, which sums the slabs of
    that chunk and the later ones that flag the cell and clears their flags. Returns the
    number of non-finite values written (0 when all is well).
    """
    n_chunks = grad3.shape[0]
    dim = data.shape[1]
    bc1 = 1.0 - beta1 ** step
    bc2 = 1.0 - beta2 ** step
    bad = 0
    for c in range(n_chunks):
        m = n_touched[c]
        for j in prange(m):
            cell = touched[c, j]
            if flags[c, cell] == 0:
                continue
            for d in range(dim):
                g = 0.0
                for k in range(c, n_chunks):
                    if flags[k, cell] != 0:
                        g += grad3[k, cell, d]
                        grad3[k, cell, d] = 0.0
                if opt == OPT_SGD:
                    v = data[cell, d] - lr * g
                elif opt == OPT_ADAM:
                    a = beta1 * m1[cell, d] + (1.0 - beta1) * g
                    b = beta2 * m2[cell, d] + (1.0 - beta2) * g * g
                    if abs(a) < 1e-30:
                        a = 0.0
                    if b < 1e-30:
                        b = 0.0
                    m1[cell, d] = a
                    m2[cell, d] = b
                    v = data[cell, d] - lr * (a / bc1) / (math.sqrt(b / bc2) + eps)
                else:
                    b = beta2 * m2[cell, d] + (1.0 - beta2) * g * g
                    if b < 1e-30:
                        b = 0.0
                    m2[cell, d] = b
                    v = data[cell, d] - lr * g / (math.sqrt(b) + eps)
                if not math.isfinite(v):
                    bad += 1
                data[cell, d] = v
            for k in range(c, n_chunks):
                flags[k, cell] = 0
            if data[cell, dim - 1] < 0.0:
                data[cell, dim - 1] = 0.0
            sig[cell] = data[cell, dim - 1]
        n_touched[c] = 0
    return bad


@njit(parallel=True, cache=True)
def pixel_rays(c2w, fx, fy, cx, cy, width, height, index, images, origins, dirs, targets):
    """Rays and target colours of flat pixel indices ``index [M]`` (``img * H * W + v * W + u``).

    Same convention and arithmetic as ``datasets.cameras.generate_rays`` (float64, then float32):
    ``d_cam = ((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1)``, rotated by ``c2w[:3, :3]``,
    normalised. Writes ``origins, dirs, targets [M, 3]``.
    """
    hw = height * width
    for j in prange(index.shape[0]):
        k = index[j]
        img = k // hw
        rem = k - img * hw
        v = rem // width
        u = rem - v * width
        a = (u + 0.5 - cx) / fx
        b = -(v + 0.5 - cy) / fy
        x = a * np.float64(c2w[img, 0, 0]) + b * np.float64(c2w[img, 0, 1]) - np.float64(c2w[img, 0, 2])
        y = a * np.float64(c2w[img, 1, 0]) + b * np.float64(c2w[img, 1, 1]) - np.float64(c2w[img, 1, 2])
        z = a * np.float64(c2w[img, 2, 0]) + b * np.float64(c2w[img, 2, 1]) - np.float64(c2w[img, 2, 2])
        nrm = math.sqrt(x * x + y * y + z * z)
        dirs[j, 0] = x / nrm
        dirs[j, 1] = y / nrm
        dirs[j, 2] = z / nrm
        for a3 in range(3):
            origins[j, a3] = c2w[img, a3, 3]
            targets[j, a3] = images[img, v, u, a3]


class DenseSlabs:
    """The slabs these kernels scatter into, as they were: one dense ``[n_cells, D]`` gradient
    slab per thread, uint8 flags and an ``[n_cells]`` touched list each (today's fine-tuner
    keeps compact slabs sized by the cells one batch reaches, ``optim._render_grad.SparseGrad``)."""

    def __init__(self, n_cells, dim, n_chunks):
        self.grad3 = np.zeros((n_chunks, n_cells, dim), dtype=np.float32)
        self.flags = np.zeros((n_chunks, n_cells), dtype=np.uint8)
        self.touched = np.zeros((n_chunks, n_cells), dtype=np.int64)
        self.n_touched = np.zeros(n_chunks, dtype=np.int64)
        self.sse = np.zeros(n_chunks, dtype=np.float64)
