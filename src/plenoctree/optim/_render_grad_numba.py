"""numba CPU kernels for fine-tuning: the renderer's forward plus the paper's analytic backward.

Imported lazily (first differentiable numba render or first fine-tuning step); compiles once and
is cached on disk.

Per ray (``k`` = the ray's σ > 0 segments in marching order, ``C`` = rendered rgb incl. the
background ``c_N`` composited with the transmittance ``T_N`` left at the end):

* pass 1, :func:`_trace_one`: marches with the renderer's traversal (``render._march_numba``:
  same quantised leaf lookup, same common-ancestor stack, same look-ahead with prefetched rows,
  same ``step_eps`` push, same early stop at ``T < stop_thresh``, the same leaf-colour dot
  product ``leaf_logits``) and records, for every segment with σ > 0, its cell, ``δ`` (world
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

Race-free scatter into compact slabs: rays are processed in tiles of :data:`TILE` rays by a
``prange``; thread ``t`` owns slab ``t``. A slab holds rows only for the cells its thread
touched in this batch, in touch order: ``slot[t, cell]`` is the cell's row (``-1``
untouched), ``touched[t, row]`` the row's cell, ``grad3[t, row]`` its gradient. (So the
gradient memory is set by the cells one batch reaches, ~10⁵, not by the tree, ~10⁷ cells: a
dense slab per thread was 1.6 GB on lego's 800² tree.) A cell that finds its slab full gets
``slot = -2``, is counted once in ``need[t]`` and gets no gradient; the caller then grows the
slabs and runs the batch again (:mod:`._render_grad`). (Floating-point sums depend on which
thread ran which tile: results are reproducible to rounding, not bit for bit, across thread
counts or threading layers.) :func:`merge_chunks` adds every slab into a dense
``[n_cells, D]`` gradient (the autograd path needs one). The optimiser kernel
:func:`step_touched` instead reads the slabs directly: it visits every touched cell once, sums
its slabs, updates it (SGD, lazy Adam or lazy RMSprop), projects σ onto σ ≥ 0 and re-zeroes
the slabs, slots and lists. No work is proportional to the tree size: one step costs
O(touched cells).

The ``prange`` is static under numba's omp and workqueue threading layers, also with
``set_parallel_chunksize``: each thread one contiguous run of tiles. Unlike an image's tiles
(the renderer hands those out from a shared counter, :mod:`plenoctree.render._schedule_numba`)
that run is balanced, because a batch's rays come in random order: 0.90 of linear at 16 threads
on lego by ``benchmarks/render_scaling.py``'s count (0.98 with the counter, which would make
the slab sums, and so the values, depend on timing from one run to the next).

Arrays: ``child`` int32 ``[n_cells]`` (flat ``[n_nodes * 8]``), ``data`` float ``[n_cells, D]``
(float32 for training; float64 works too, for ``gradcheck``; the march reads σ from the rows
its look-ahead prefetched), ``sig`` ``[n_cells]`` the step kernels' copy of ``data[:, -1]``
(kept in sync for their callers), ``grad3`` same dtype
``[n_chunks, cap, D]``, ``slot`` int32 ``[n_chunks, n_cells]``, ``touched`` int64
``[n_chunks, cap]``, ``n_touched`` and ``need`` int64 ``[n_chunks]``. Geometry is computed in float64,
as in the renderer.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from ..render._march_numba import (MARCH_MATH, MAX_LEVEL, MAX_STEPS, QUEUE, STACK_SIZE,
                                   _prefetch, basis_values, leaf_logits, look_ahead,
                                   pad_scratch, prefetch_row, ray_octant, ray_start)
from ..render._render_numba import _camera_ray
from ..render.options import KIND_RGBA

__all__ = ["TILE", "grad_kernel", "merge_chunks", "step_touched", "OPT_SGD", "OPT_ADAM",
           "OPT_RMSPROP", "pixel_rays"]

TILE = 64          # rays per interleaved tile of a chunk
_REC = 5           # record columns: delta, att, c_r, c_g, c_b
_QMASK = QUEUE - 1


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _trace_one(child, skip, shift, data, offset, invr, origins, dirs, i, kind, n_b, sg, b_lo,
               b_hi, stop, eps, basis, st, stack, qc, qe, rec_cell, rec, out4, slot, chunk,
               want_grad):
    """March ray ``i`` of ``origins, dirs`` (the renderer's traversal,
    :mod:`plenoctree.render._march_numba`, with its look-ahead and, when ``child`` carries
    them, empty-space skips) and record its σ > 0 segments.

    Writes ``Σ w c`` into ``out4[:3]`` and ``T_N`` into ``out4[3]``; fills ``basis[:n_b]`` (zero
    outside ``[b_lo, b_hi]``), ``rec_cell[s]`` and ``rec[s] = (δ, exp(-σδ), c_r, c_g, c_b)``.
    Returns the number of recorded segments, or ``-1`` when the record is full (the caller
    grows it and traces again). With ``want_grad`` the slot ``slot[chunk, cell]`` of every
    recorded segment is prefetched, so that the backward pass finds its slab row at once.
    Colour dot products run in the dtype of ``data`` (float32 in training, as in the
    renderer; float64 for gradcheck).
    """
    out4[0] = 0.0
    out4[1] = 0.0
    out4[2] = 0.0
    out4[3] = 1.0
    # float64 scalars: the direction is normalised in float64 (as the twin)
    dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, eps_t = ray_start(
        offset, invr, np.float64(origins[i, 0]), np.float64(origins[i, 1]),
        np.float64(origins[i, 2]), np.float64(dirs[i, 0]), np.float64(dirs[i, 1]),
        np.float64(dirs[i, 2]), eps)
    if not t0 < t1:
        return 0
    basis_values(kind, n_b, dx, dy, dz, sg, b_lo, b_hi, basis)
    oc = ray_octant(vx, vy, vz)
    dim = data.shape[1]
    cap = rec_cell.shape[0]
    n_seg = 0
    trans = 1.0
    t = t0
    st[0] = 0
    st[1] = -1
    stack[0] = 0
    head = 0
    tail = 0
    tq = t0
    steps = 0
    while True:
        tail, tq, steps = look_ahead(child, skip, shift, oc, data, px, py, pz, vx, vy, vz, ix,
                                     iy, iz, eps_t, t1, True, MAX_LEVEL, MAX_STEPS, st, stack,
                                     qc, qe, head, tail, tq, steps)
        if head == tail:
            break
        cell = qc[head & _QMASK]
        t_end = qe[head & _QMASK]
        head += 1
        if cell < 0:                        # an empty leaf (look_ahead): no segment recorded
            t = t_end
            continue
        sigma = data[cell, dim - 1]         # the row look_ahead prefetched
        if sigma > 0.0:
            if n_seg == cap:
                return -1
            delta = t_end - t
            att = math.exp(-sigma * delta)
            w = trans * (1.0 - att)
            ar, ag, ab = leaf_logits(data, cell, kind, n_b, basis)
            cr = 1.0 / (1.0 + math.exp(-ar))    # exp in the data dtype, the rest float64
            cg = 1.0 / (1.0 + math.exp(-ag))
            cb = 1.0 / (1.0 + math.exp(-ab))
            if want_grad:
                _prefetch(slot, chunk, cell)
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


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _backprop_one(n_seg, rec_cell, rec, kind, n_b, b_lo, b_hi, basis, cr, cg, cb, gr, gg, gb,
                  grad, slot, touched, n_touched, need):
    """Scatter ``∂L/∂data`` of one ray (eq. 15 and 20) into this chunk's compact slab ``grad``
    (row ``slot[cell]``, given to a cell on its first touch); returns the new ``(n_touched,
    need)``. A cell that finds the slab full is marked ``-2``, counted once in ``need`` and
    gets nothing (the caller grows the slabs and runs the batch again)."""
    dim = grad.shape[1]
    cap = grad.shape[0]
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
        row = slot[cell]
        if row == -1:
            if n_touched < cap:
                row = n_touched
                slot[cell] = row
                touched[row] = cell
                n_touched += 1
            else:
                slot[cell] = -2
                need += 1
        if row >= 0:
            # density: δ_i Σ_ch g_ch (c_ch T_{i+1} - suffix_ch), suffix = C - P_i
            gsig = delta * (gr * (c0 * t_next - (cr - pr)) + gg * (c1 * t_next - (cg - pg))
                            + gb * (c2 * t_next - (cb - pb)))
            grad[row, dim - 1] += gsig
            # colour: g_ch w c (1 - c) Y_b  (Y = basis, 0 outside [b_lo, b_hi])
            g0 = gr * w * c0 * (1.0 - c0)
            g1 = gg * w * c1 * (1.0 - c1)
            g2 = gb * w * c2 * (1.0 - c2)
            if kind == KIND_RGBA:
                yb = basis[0]
                grad[row, 0] += g0 * yb
                grad[row, 1] += g1 * yb
                grad[row, 2] += g2 * yb
            else:
                for b in range(b_lo, b_hi + 1):
                    yb = basis[b]
                    grad[row, b] += g0 * yb
                    grad[row, n_b + b] += g1 * yb
                    grad[row, 2 * n_b + b] += g2 * yb
        trans = t_next
    return n_touched, need


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def grad_kernel(child, skip, shift, data, offset, invr, origins, dirs, aux, mode, scale, kind, n_b,
                sg, b_lo, b_hi, bg, stop, eps, cap0, rgb_out, grad3, slot, touched, n_touched,
                need, sse):
    """Forward + analytic backward for ``[N, 3]`` rays, accumulating into per-chunk slabs.

    ``mode == 0``: ``aux [N, 3]`` is ``∂L/∂rgb`` (autograd backward).
    ``mode == 1``: ``aux [N, 3]`` are target colours and ``L = scale · Σ_rays Σ_ch (C - aux)²``
    (fused MSE step; ``sse[t]`` accumulates thread ``t``'s un-scaled sum of squared errors).
    ``mode == 2``: forward only (``grad3`` is not touched).
    Slab ``t`` (``grad3[t]``, ``slot[t]``, ``touched[t]``, ``n_touched[t]``, ``need[t]``) as in
    the module docstring; ``need.any()`` after the call means the batch must be run again with
    larger slabs.
    ``rgb_out [N, 3]`` receives the rendered colour ``C`` (background included).

    Work items are tiles of :data:`TILE` rays (``prange``); a tile runs on one thread
    ``t = numba.get_thread_id()`` and scatters into slab ``t``, so the caller must run at most
    ``n_chunks`` threads (:mod:`plenoctree.optim._render_grad` does).
    """
    n = origins.shape[0]
    n_chunks = grad3.shape[0]
    n_tiles = (n + TILE - 1) // TILE
    # Per-thread scratch: thread t uses row t (the caller runs at most n_chunks threads); rows
    # padded by pad_scratch, so no two threads write one cache line (st, the look-ahead queue
    # and out4 are written at every segment: sharing lines made two threads as slow as one).
    basis_all = np.zeros((n_chunks, pad_scratch(max(25, n_b), 4)), dtype=data.dtype)
    stack_all = np.zeros((n_chunks, pad_scratch(STACK_SIZE, 8)), dtype=np.int64)
    st_all = np.zeros((n_chunks, pad_scratch(4, 8)), dtype=np.int64)
    out_all = np.zeros((n_chunks, pad_scratch(4, 8)), dtype=np.float64)
    qc_all = np.zeros((n_chunks, pad_scratch(QUEUE, 8)), dtype=np.int64)
    qe_all = np.zeros((n_chunks, pad_scratch(QUEUE, 8)), dtype=np.float64)
    cell_all = np.empty((n_chunks, pad_scratch(cap0, 8)), dtype=np.int64)
    rec_all = np.empty((n_chunks, pad_scratch(cap0 * _REC, 8)), dtype=np.float64)
    for tile in prange(n_tiles):
        c = numba.get_thread_id()
        basis = basis_all[c]
        stack = stack_all[c]
        st = st_all[c]
        out4 = out_all[c]
        qc = qc_all[c]
        qe = qe_all[c]
        rec_cell = cell_all[c][:cap0]
        rec = rec_all[c][:cap0 * _REC].reshape(cap0, _REC)
        grad = grad3[c]
        slt = slot[c]
        tch = touched[c]
        nt = n_touched[c]
        nd = need[c]
        acc_sse = 0.0
        for i in range(tile * TILE, min(n, (tile + 1) * TILE)):
            while True:
                n_seg = _trace_one(child, skip, shift, data, offset, invr, origins, dirs, i,
                                   kind, n_b, sg, b_lo, b_hi, stop, eps, basis, st, stack, qc,
                                   qe, rec_cell, rec, out4, slot, c, mode != 2)
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
            nt, nd = _backprop_one(n_seg, rec_cell, rec, kind, n_b, b_lo, b_hi, basis, cr, cg,
                                   cb, gr, gg, gb, grad, slt, tch, nt, nd)
        n_touched[c] = nt
        need[c] = nd
        sse[c] += acc_sse


@njit(parallel=True, cache=True)
def merge_chunks(grad3, slot, touched, n_touched, dense):
    """Add every slab into the dense gradient ``dense [n_cells, D]`` (zeroed by the caller) and
    clear the slabs, slots and lists (each list is duplicate-free, so the cells of one chunk
    are added in parallel)."""
    n_chunks = grad3.shape[0]
    dim = grad3.shape[2]
    for c in range(n_chunks):
        m = n_touched[c]
        for j in prange(m):
            cell = touched[c, j]
            for d in range(dim):
                dense[cell, d] += grad3[c, j, d]
                grad3[c, j, d] = 0.0
            slot[c, cell] = -1
        n_touched[c] = 0


OPT_SGD, OPT_ADAM, OPT_RMSPROP = 0, 1, 2
_AHEAD = 8         # touched cells between a prefetch and the update that reads it


#: fastmath flags of the optimiser: reassociation, contraction, approximate reciprocals; not
#: ``nnan`` / ``ninf`` (the kernel counts non-finite values, which those flags would fold away).
_OPT_MATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, fastmath=_OPT_MATH, inline="always")
def _adam_span(row, m1r, m2r, g, lo, hi, b1, b2, c1, c2, lr_c, ib2, eps, tiny):
    """Lazy Adam on ``row[lo:hi]`` in float32 (the dtype of the values and moments, as
    ``torch.optim.Adam`` computes): ``lr_c`` is the learning rate over the first moment's bias
    correction, ``ib2`` the reciprocal of the second's; moments below ``tiny`` flush to 0."""
    zero = np.float32(0.0)
    for d in range(lo, hi):
        a = b1 * m1r[d] + c1 * g[d]
        b = b2 * m2r[d] + c2 * (g[d] * g[d])
        a = a if abs(a) >= tiny else zero
        b = b if b >= tiny else zero
        m1r[d] = a
        m2r[d] = b
        row[d] -= lr_c * a / (math.sqrt(b * ib2) + eps)


@njit(cache=True, fastmath=_OPT_MATH, inline="always")
def _rmsprop_span(row, m2r, g, lo, hi, b2, c2, lr, eps, tiny):
    """Lazy RMSprop on ``row[lo:hi]`` in float32 (see :func:`_adam_span`)."""
    zero = np.float32(0.0)
    for d in range(lo, hi):
        b = b2 * m2r[d] + c2 * (g[d] * g[d])
        b = b if b >= tiny else zero
        m2r[d] = b
        row[d] -= lr * g[d] / (math.sqrt(b) + eps)


@njit(parallel=True, cache=True, fastmath=_OPT_MATH)
def step_touched(data, sig, grad3, slot, touched, n_touched, opt, lr, lr_sig, m1, m2, beta1,
                 beta2, eps, step):
    """Apply one optimiser step to every touched cell, reading the gradient straight from the
    per-thread slabs (no separate merge), then re-zero slabs, slots and lists.

    ``opt``: :data:`OPT_SGD` (``data -= lr g``), :data:`OPT_ADAM` (lazy Adam: moments
    ``m1, m2 [n_cells, D]`` updated only where the batch has a gradient, as
    ``torch.optim.SparseAdam``, bias correction by the global 1-based ``step``) or
    :data:`OPT_RMSPROP` (``m2 = β2 m2 + (1 - β2) g²``, ``data -= lr g / (√m2 + eps)``, lazy).
    σ (the last column) steps with ``lr_sig`` instead of ``lr`` (world σ units; pass ``lr`` for
    one rate). The updates run in float32, the dtype of the values and moments, and vectorise
    over a row. Tiny moments are flushed to 0 (no denormals). σ is then projected onto
    ``σ ≥ 0`` (the renderer uses ``relu(σ)``, so no render changes, and the tree stays valid for
    ``save_tree``) and copied to ``sig``.

    The rows of the cell :data:`_AHEAD` places further down the list are prefetched (the list
    is in touch order, so every row is a cache miss otherwise). Each cell is handled once: by
    the first chunk whose list holds it, which sums its row of that chunk's slab and of the
    later slabs that hold the cell and clears their slots. Returns the number of non-finite
    values written (0 when all is well).
    """
    n_chunks = grad3.shape[0]
    dim = data.shape[1]
    f32 = np.float32
    # Adam's bias corrections (1 for the others), folded into the rates
    bc1 = 1.0 - beta1 ** step if opt == OPT_ADAM else 1.0
    bc2 = 1.0 - beta2 ** step if opt == OPT_ADAM else 1.0
    lr_c, lrs_c, ib2 = f32(lr / bc1), f32(lr_sig / bc1), f32(1.0 / bc2)
    b1, b2, c1, c2 = f32(beta1), f32(beta2), f32(1.0 - beta1), f32(1.0 - beta2)
    e, tiny = f32(eps), f32(1e-30)
    bad = 0
    for c in range(n_chunks):
        m = n_touched[c]
        gc = grad3[c]
        for j in prange(m):
            if j + _AHEAD < m:              # the rows this thread updates a few cells later
                ahead = touched[c, j + _AHEAD]
                prefetch_row(data, ahead)
                if opt != OPT_SGD:
                    prefetch_row(m2, ahead)
                    if opt == OPT_ADAM:
                        prefetch_row(m1, ahead)
            cell = touched[c, j]
            if slot[c, cell] < 0:           # an earlier chunk's list held it: done
                continue
            g = gc[j]
            # Fold the later slabs that hold this cell into slab c (0 + a + b, as before), so
            # the update loops below are slot-free and vectorise over the D values.
            for k in range(c + 1, n_chunks):
                r = slot[k, cell]
                if r >= 0:
                    gk = grad3[k, r]
                    for d in range(dim):
                        g[d] += gk[d]
                        gk[d] = 0.0
                    slot[k, cell] = -1
            row = data[cell]
            if opt == OPT_SGD:
                for d in range(dim - 1):
                    row[d] -= lr_c * g[d]
                row[dim - 1] -= lrs_c * g[dim - 1]
            elif opt == OPT_ADAM:
                _adam_span(row, m1[cell], m2[cell], g, 0, dim - 1, b1, b2, c1, c2, lr_c, ib2,
                           e, tiny)
                _adam_span(row, m1[cell], m2[cell], g, dim - 1, dim, b1, b2, c1, c2, lrs_c,
                           ib2, e, tiny)
            else:
                _rmsprop_span(row, m2[cell], g, 0, dim - 1, b2, c2, lr_c, e, tiny)
                _rmsprop_span(row, m2[cell], g, dim - 1, dim, b2, c2, lrs_c, e, tiny)
            nonfinite = 0
            for d in range(dim):
                g[d] = 0.0
                if not math.isfinite(row[d]):
                    nonfinite += 1
            bad += nonfinite
            slot[c, cell] = -1
            if row[dim - 1] < 0.0:
                row[dim - 1] = 0.0
            sig[cell] = row[dim - 1]
        n_touched[c] = 0
    return bad


@njit(parallel=True, cache=True)
def pixel_rays(cams, width, height, index, images, unit, origins, dirs, targets):
    """Rays and target colours of flat pixel indices ``index [M]`` (``img * H * W + v * W + u``).

    Image ``img`` is seen by the camera packed in ``cams[img]`` (``render._render_numba
    .pack_cameras``: its own intrinsics, NDC rays for an NDC set); each ray is made by the
    renderer's ``_camera_ray``, so it equals ``Cameras.rays(img)[v, u]`` (pinhole and NDC, shared
    or per-camera intrinsics). Writes ``origins, dirs, targets [M, 3]`` float32; a target is
    ``images[img, v, u] * unit`` (``images`` float32, ``unit`` 1, or uint16, ``unit`` 1 / 65535).
    """
    hw = height * width
    for j in prange(index.shape[0]):
        k = index[j]
        img = k // hw
        rem = k - img * hw
        v = rem // width
        u = rem - v * width
        ox, oy, oz, dx, dy, dz = _camera_ray(cams[img], u, v)
        origins[j, 0] = ox
        origins[j, 1] = oy
        origins[j, 2] = oz
        dirs[j, 0] = dx
        dirs[j, 1] = dy
        dirs[j, 2] = dz
        for a3 in range(3):
            targets[j, a3] = images[img, v, u, a3] * unit
