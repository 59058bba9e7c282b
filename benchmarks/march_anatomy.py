"""Where a real ray's march time goes, by replacing one part of it at a time (issue 12).

Every variant marches the same rays (orbit views of a real tree) and computes only the
transmittance ``T`` with the renderer's early stop (no colour, no look-ahead): the march is
what the render kernel's time is made of (``render_speed.py``: its kernel takes about as long
as ``march`` here). Variants:

- ``march``: today's traversal, :func:`plenoctree.render._march_numba.next_leaf` with the
  ancestor stack (the reference of the other rows);
- ``empty_skip``: ``march`` with the renderer's empty-space skip tables
  (:mod:`plenoctree.render.empty_skip`): an empty leaf's segment runs to the end of the empty
  cube ahead (same ``T``, fewer segments);
- ``root``: the same, descending from the root at every segment (``use_stack=False``);
- ``interleave4``: ``march`` on four rays at once, round robin (hides latency if the march
  waited on memory);
- ``predict``: the next leaf predicted from the exit face (the neighbour's integer
  coordinates, no float → integer conversion on the dependency chain), verified against the
  twin's lookup point ``p(t + ε)`` and looked up from it when they disagree (exact);
- ``level_loop`` / ``level_clz``: ``march`` written with this file's helpers, the common
  ancestor's level found by ``common_level``'s loop, or without a branch by a count of
  leading zeros (their ratio is the figure: a predicted branch lets the CPU run ahead);
- ``grid``: the leaf looked up in a dense 256³ table of cell indices (64 MiB) instead of the
  descent (one load, no data-dependent loop, the twin's exact lookup);
- ``param``: a parametric top-down traversal (Revelles et al. 2000: child planes by midpoint
  averaging, no float→int conversion; lookups at ``t + ε`` as the twin's);
- ``geometry``: no tree at all — only the per-segment arithmetic of ``next_leaf`` (point →
  integer cell → exit planes → next ``t``), through a uniform 256³ grid, for exactly as many
  segments per ray as the real march made;
- ``dda``: the same count of segments stepped incrementally (3-D DDA, one add per step) — the
  floor of an incremental stepper, not a renderer.

Prints a table (ms per frame, ratio to ``march``, max |ΔT| against it) and writes
``benchmarks/results/march_anatomy.json``. Usage::

    .venv/bin/python benchmarks/march_anatomy.py                 # lego 256³ when found
    .venv/bin/python benchmarks/march_anatomy.py --tree TREE.npz --size 800 --repeats 3
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import leading_zeros

from _bench import add_data_root, add_out, interleaved, machine_info, markdown_table, write_json
from _trees import load_bench_tree, orbit_cameras

from plenoctree.render._march_numba import (MARCH_MATH, MAX_LEVEL, STACK_SIZE, common_level,
                                            next_leaf, ray_octant, ray_start)
from plenoctree.render.empty_skip import NO_SKIP, skip_tables
from plenoctree.render.options import QUANT_BITS

_S = float(2 ** QUANT_BITS)
_G = 8                       # level of the dense table / uniform grid (256³)
_TILE = 64
_STOP = 0.01


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _start_grid(offset, invr, o, d, i, eps):
    """:func:`ray_start` of ray ``i``: origin, direction and reciprocal in grid units (what
    ``next_leaf`` takes)."""
    return ray_start(offset, invr, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], eps)


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _start(offset, invr, o, d, i, eps):
    """The same in tree-space units (divided back by the power-of-two scale: exact), for this
    file's own traversals."""
    dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start_grid(offset, invr, o, d,
                                                                             i, eps)
    return (dx, dy, dz, px / _S, py / _S, pz / _S, vx / _S, vy / _S, vz / _S, ix * _S, iy * _S,
            iz * _S, t0, t1, et)


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _absorb(data, cell, t, te, tr):
    """Transmittance after segment ``[t, te]`` of ``cell`` (σ ≤ 0: unchanged)."""
    s = data[cell, data.shape[1] - 1]
    return tr * math.exp(-s * (te - t)) if s > 0.0 else tr


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _march(child, skip, shift, data, offset, invr, o, d, eps, use_stack, out, nseg):
    n = o.shape[0]
    for tile in prange((n + _TILE - 1) // _TILE):
        st = np.zeros(4, np.int64)
        stack = np.zeros(STACK_SIZE, np.int64)
        for i in range(tile * _TILE, min(n, tile * _TILE + _TILE)):
            _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start_grid(
                offset, invr, o, d, i, eps)
            tr, k, t = 1.0, 0, t0
            st[0], st[1], stack[0] = 0, -1, 0
            oc = ray_octant(vx, vy, vz)
            while t < t1:
                cell, te, _ = next_leaf(child, skip, shift, oc, px, py, pz, vx, vy, vz, ix, iy, iz,
                                        t, et, t1, use_stack, MAX_LEVEL, st, stack)
                k += 1
                tr = _absorb(data, cell, t, te, tr)
                if tr < _STOP:
                    break
                t = te
            out[i] = tr
            nseg[i] = k


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _interleave4(child, data, offset, invr, o, d, eps, out):
    n = o.shape[0]
    for tile in prange((n + _TILE - 1) // _TILE):
        st = np.zeros((4, 4), np.int64)
        stack = np.zeros((4, STACK_SIZE), np.int64)
        r = np.zeros((4, 12))
        idx = np.full(4, -1, np.int64)
        nxt, end = tile * _TILE, min(n, tile * _TILE + _TILE)
        while True:
            for k in range(4):
                while idx[k] < 0 and nxt < end:
                    i = nxt
                    nxt += 1
                    _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start_grid(
                        offset, invr, o, d, i, eps)
                    if not t0 < t1:
                        out[i] = 1.0
                        continue
                    r[k, 0], r[k, 1], r[k, 2], r[k, 3], r[k, 4], r[k, 5] = px, py, pz, vx, vy, vz
                    r[k, 6], r[k, 7], r[k, 8], r[k, 9], r[k, 10], r[k, 11] = ix, iy, iz, t0, t1, et
                    idx[k] = i
                    st[k, 0], st[k, 1], stack[k, 0] = 0, -1, 0
                    out[i] = 1.0
            alive = 0
            for k in range(4):
                if idx[k] < 0:
                    continue
                alive += 1
                t = r[k, 9]
                cell, te, _ = next_leaf(child, NO_SKIP, 0, 0, r[k, 0], r[k, 1], r[k, 2], r[k, 3],
                                        r[k, 4], r[k, 5], r[k, 6], r[k, 7], r[k, 8], t, r[k, 11],
                                        r[k, 10], True, MAX_LEVEL, st[k], stack[k])
                out[idx[k]] = _absorb(data, cell, t, te, out[idx[k]])
                done = te >= r[k, 10] or out[idx[k]] < _STOP
                r[k, 9] = te
                if done:
                    idx[k] = -1
            if alive == 0 and nxt >= end:
                break


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _descend(child, qx, qy, qz, rx, ry, rz, level, lim, stack):
    """``next_leaf``'s descent from ``stack[level]``: bits of ``q`` down to level ``lim``, of
    ``r`` below it. Returns ``(cell, level, the coordinates used last)``."""
    node = stack[level]
    while True:
        if level > lim:
            qx, qy, qz = rx, ry, rz
        sh = QUANT_BITS - 1 - level
        cell = node * 8 + (((qx >> sh) & 1) << 2) + (((qy >> sh) & 1) << 1) + ((qz >> sh) & 1)
        c = child[cell]
        if c <= 0 or level >= MAX_LEVEL:
            return cell, level, qx, qy, qz
        node += c
        level += 1
        stack[level] = node


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _predict(child, data, offset, invr, o, d, eps, out):
    """The next leaf predicted from the exit face (the neighbour's integer coordinates: one
    add, no float → integer conversion on the chain), verified against the twin's lookup point
    ``p(t + ε)`` (computed off the chain) and looked up again from it when they disagree."""
    n = o.shape[0]
    top = (1 << QUANT_BITS) - 1
    for tile in prange((n + _TILE - 1) // _TILE):
        st = np.zeros(5, np.int64)            # level, path coordinates, predicted exit axis
        stack = np.zeros(STACK_SIZE, np.int64)
        for i in range(tile * _TILE, min(n, tile * _TILE + _TILE)):
            _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start(offset, invr, o, d,
                                                                               i, eps)
            tr, t = 1.0, t0
            st[0], st[1], st[4], stack[0] = 0, -1, -1, 0
            while t < t1:
                ts = t + et
                rx, ry, rz = _quant(px, vx, ts), _quant(py, vy, ts), _quant(pz, vz, ts)
                a, lev0, ok = st[4], st[0], False
                if a >= 0:
                    sh = QUANT_BITS - 1 - lev0
                    ax, ay, az = st[1], st[2], st[3]
                    if a == 0:
                        ax = ((ax >> sh) + 1) << sh if vx >= 0.0 else ((ax >> sh) << sh) - 1
                    elif a == 1:
                        ay = ((ay >> sh) + 1) << sh if vy >= 0.0 else ((ay >> sh) << sh) - 1
                    else:
                        az = ((az >> sh) + 1) << sh if vz >= 0.0 else ((az >> sh) << sh) - 1
                    if ((ax | ay | az) & ~top) == 0:
                        up = common_level(lev0, ax, ay, az, st)
                        cell, level, qx, qy, qz = _descend(child, ax, ay, az, rx, ry, rz, up,
                                                           lev0, stack)
                        ok = (((rx ^ ax) | (ry ^ ay) | (rz ^ az))
                              >> (QUANT_BITS - 1 - min(level, lev0))) == 0
                        if not ok:                # the stack now holds the predicted path
                            st[0], st[1], st[2], st[3] = min(level, lev0), ax, ay, az
                if not ok:
                    level = common_level(st[0], rx, ry, rz, st) if st[1] >= 0 else 0
                    cell, level, qx, qy, qz = _descend(child, rx, ry, rz, rx, ry, rz, level,
                                                       MAX_LEVEL, stack)
                st[0], st[1], st[2], st[3] = level, qx, qy, qz
                sh = QUANT_BITS - 1 - level
                bx = ((((qx >> sh) + 1) << sh) if vx >= 0.0 else ((qx >> sh) << sh)) / _S
                by = ((((qy >> sh) + 1) << sh) if vy >= 0.0 else ((qy >> sh) << sh)) / _S
                bz = ((((qz >> sh) + 1) << sh) if vz >= 0.0 else ((qz >> sh) << sh)) / _S
                tx, ty, tz = (bx - px) * ix, (by - py) * iy, (bz - pz) * iz
                m = min(tx, min(ty, tz))
                te = min(max(m, ts), t1)
                st[4] = (0 if tx == m else (1 if ty == m else 2)) if m >= ts else -1
                tr = _absorb(data, cell, t, te, tr)
                if tr < _STOP:
                    break
                t = te
            out[i] = tr


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _level_march(child, data, offset, invr, o, d, eps, use_clz, out):
    """``march`` written with this file's helpers, the common ancestor's level found by
    ``common_level``'s loop (``use_clz=False``, row ``level_loop``) or without a branch from a
    count of leading zeros of the coordinates' difference (row ``level_clz``)."""
    n = o.shape[0]
    for tile in prange((n + _TILE - 1) // _TILE):
        st = np.zeros(4, np.int64)
        stack = np.zeros(STACK_SIZE, np.int64)
        for i in range(tile * _TILE, min(n, tile * _TILE + _TILE)):
            _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start(offset, invr, o, d,
                                                                               i, eps)
            tr, t = 1.0, t0
            st[0], st[1], stack[0] = 0, -1, 0
            while t < t1:
                ts = t + et
                qx, qy, qz = _quant(px, vx, ts), _quant(py, vy, ts), _quant(pz, vz, ts)
                if st[1] < 0:
                    level = 0
                elif use_clz:
                    diff = np.uint64((qx ^ st[1]) | (qy ^ st[2]) | (qz ^ st[3]))
                    level = min(st[0], QUANT_BITS - 64 + np.int64(leading_zeros(diff)))
                else:
                    level = common_level(st[0], qx, qy, qz, st)
                cell, level, qx, qy, qz = _descend(child, qx, qy, qz, qx, qy, qz, level,
                                                   MAX_LEVEL, stack)
                st[0], st[1], st[2], st[3] = level, qx, qy, qz
                te = _exit(qx, qy, qz, QUANT_BITS - 1 - level, px, py, pz, vx, vy, vz, ix, iy,
                           iz, ts, t1)
                tr = _absorb(data, cell, t, te, tr)
                if tr < _STOP:
                    break
                t = te
            out[i] = tr


@njit(cache=True, inline="always")
def _gidx(x, y, z):
    nb = 1 << (_G - 2)
    return ((((x >> 2) * nb + (y >> 2)) * nb + (z >> 2)) << 6) | ((x & 3) << 4) | \
        ((y & 3) << 2) | (z & 3)


@njit(cache=True)
def _build_grid(child, grid):
    """``grid[256³]`` (4³ bricks): ``level << 26 | cell`` of the leaf covering each cell, or
    ``-cell - 1`` of the level-8 cell to descend from when the tree is deeper there."""
    sn, sl = np.empty(512, np.int64), np.empty(512, np.int64)
    sx, sy, sz = np.empty(512, np.int64), np.empty(512, np.int64), np.empty(512, np.int64)
    sn[0] = sl[0] = sx[0] = sy[0] = sz[0] = 0
    n = 1
    while n > 0:
        n -= 1
        node, lev, x0, y0, z0 = sn[n], sl[n], sx[n], sy[n], sz[n]
        for k in range(8):
            cell = node * 8 + k
            cx, cy, cz = 2 * x0 + (k >> 2), 2 * y0 + ((k >> 1) & 1), 2 * z0 + (k & 1)
            c, lv = child[cell], lev + 1
            if c != 0 and lv < _G:
                sn[n], sl[n], sx[n], sy[n], sz[n] = node + c, lv, cx, cy, cz
                n += 1
                continue
            e = (lv << 26) | cell if c == 0 else -cell - 1
            s = _G - lv
            for x in range(cx << s, (cx + 1) << s):
                for y in range(cy << s, (cy + 1) << s):
                    for z in range(cz << s, (cz + 1) << s):
                        grid[_gidx(x, y, z)] = e


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _exit(qx, qy, qz, sh, px, py, pz, vx, vy, vz, ix, iy, iz, ts, t1):
    bx = (((qx >> sh) + (1 if vx >= 0.0 else 0)) << sh) / _S
    by = (((qy >> sh) + (1 if vy >= 0.0 else 0)) << sh) / _S
    bz = (((qz >> sh) + (1 if vz >= 0.0 else 0)) << sh) / _S
    return min(max(min((bx - px) * ix, min((by - py) * iy, (bz - pz) * iz)), ts), t1)


@njit(cache=True, fastmath=MARCH_MATH, inline="always")
def _quant(p, v, ts):
    return int(min(max((p + ts * v) * _S, 0.0), _S - 1.0))


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _grid_march(grid, child, data, offset, invr, o, d, eps, out):
    n = o.shape[0]
    for tile in prange((n + _TILE - 1) // _TILE):
        for i in range(tile * _TILE, min(n, tile * _TILE + _TILE)):
            _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start(offset, invr, o, d,
                                                                               i, eps)
            tr, t = 1.0, t0
            while t < t1:
                ts = t + et
                qx, qy, qz = _quant(px, vx, ts), _quant(py, vy, ts), _quant(pz, vz, ts)
                sh = QUANT_BITS - _G
                e = grid[_gidx(qx >> sh, qy >> sh, qz >> sh)]
                if e >= 0:
                    lv, cell = e >> 26, e & ((1 << 26) - 1)
                else:
                    cell, level = -e - 1, _G - 1
                    while child[cell] != 0 and level < MAX_LEVEL:
                        node = (cell >> 3) + child[cell]
                        level += 1
                        s2 = QUANT_BITS - 1 - level
                        cell = node * 8 + (((qx >> s2) & 1) << 2) + (((qy >> s2) & 1) << 1) + \
                            ((qz >> s2) & 1)
                    lv = level + 1
                te = _exit(qx, qy, qz, QUANT_BITS - lv, px, py, pz, vx, vy, vz, ix, iy, iz, ts,
                           t1)
                tr = _absorb(data, cell, t, te, tr)
                if tr < _STOP:
                    break
                t = te
            out[i] = tr


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _param(child, data, offset, invr, o, d, eps, out):
    """Frames per level: entry / mid / exit plane t per axis (sorted by the ray's direction),
    the node, and the smallest exit; the child holding p(t + ε) is one compare per axis."""
    n = o.shape[0]
    for tile in prange((n + _TILE - 1) // _TILE):
        f = np.zeros((STACK_SIZE, 10))
        node = np.zeros(STACK_SIZE, np.int64)
        for i in range(tile * _TILE, min(n, tile * _TILE + _TILE)):
            _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start(offset, invr, o, d,
                                                                               i, eps)
            tr = 1.0
            if t0 < t1:
                for a in range(3):
                    p = px if a == 0 else (py if a == 1 else pz)
                    v = vx if a == 0 else (vy if a == 1 else vz)
                    iv = ix if a == 0 else (iy if a == 1 else iz)
                    lo, hi = (0.0 - p) * iv, (1.0 - p) * iv
                    f[0, a], f[0, 3 + a], f[0, 6 + a] = (hi, (0.5 - p) * iv, lo) if v < 0.0 \
                        else (lo, (0.5 - p) * iv, hi)
                f[0, 9] = min(f[0, 6], min(f[0, 7], f[0, 8]))
                node[0] = 0
                nx, ny, nz = (4 if vx < 0.0 else 0), (2 if vy < 0.0 else 0), (1 if vz < 0.0 else 0)
                sp, t = 0, t0
                while True:
                    ts = t + et
                    if f[sp, 9] <= ts:
                        sp -= 1
                        if sp < 0:
                            break
                        continue
                    bx, by, bz = f[sp, 3] < ts, f[sp, 4] < ts, f[sp, 5] < ts
                    cell = node[sp] * 8 + (((4 if bx else 0) ^ nx) | ((2 if by else 0) ^ ny)
                                           | ((1 if bz else 0) ^ nz))
                    c = child[cell]
                    ex = f[sp, 6] if bx else f[sp, 3]
                    ey = f[sp, 7] if by else f[sp, 4]
                    ez = f[sp, 8] if bz else f[sp, 5]
                    if c != 0 and sp < MAX_LEVEL:
                        ax = f[sp, 3] if bx else f[sp, 0]
                        ay = f[sp, 4] if by else f[sp, 1]
                        az = f[sp, 5] if bz else f[sp, 2]
                        node[sp + 1] = node[sp] + c
                        sp += 1
                        f[sp, 0], f[sp, 1], f[sp, 2] = ax, ay, az
                        f[sp, 3], f[sp, 4], f[sp, 5] = 0.5 * (ax + ex), 0.5 * (ay + ey), \
                            0.5 * (az + ez)
                        f[sp, 6], f[sp, 7], f[sp, 8] = ex, ey, ez
                        f[sp, 9] = min(ex, min(ey, ez))
                        continue
                    te = min(max(min(ex, min(ey, ez)), ts), t1)
                    tr = _absorb(data, cell, t, te, tr)
                    if tr < _STOP:
                        break
                    t = te
                    if t >= t1:
                        break
            out[i] = tr


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _geometry(offset, invr, o, d, eps, nseg, out):
    n = o.shape[0]
    for tile in prange((n + _TILE - 1) // _TILE):
        for i in range(tile * _TILE, min(n, tile * _TILE + _TILE)):
            _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start(offset, invr, o, d,
                                                                               i, eps)
            t = t0
            for _k in range(nseg[i]):
                ts = t + et
                t = _exit(_quant(px, vx, ts), _quant(py, vy, ts), _quant(pz, vz, ts),
                          QUANT_BITS - _G, px, py, pz, vx, vy, vz, ix, iy, iz, ts, t1)
            out[i] = t


@njit(parallel=True, cache=True, fastmath=MARCH_MATH)
def _dda(offset, invr, o, d, eps, nseg, out):
    n = o.shape[0]
    cs = 1.0 / (1 << _G)
    for tile in prange((n + _TILE - 1) // _TILE):
        for i in range(tile * _TILE, min(n, tile * _TILE + _TILE)):
            _, _, _, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, et = _start(offset, invr, o, d,
                                                                               i, eps)
            ts = t0 + et
            sh = QUANT_BITS - _G
            qx, qy, qz = _quant(px, vx, ts) >> sh, _quant(py, vy, ts) >> sh, \
                _quant(pz, vz, ts) >> sh
            tx = ((qx + (1 if vx >= 0 else 0)) * cs - px) * ix
            ty = ((qy + (1 if vy >= 0 else 0)) * cs - py) * iy
            tz = ((qz + (1 if vz >= 0 else 0)) * cs - pz) * iz
            dx, dy, dz = abs(cs * ix), abs(cs * iy), abs(cs * iz)
            t = t0
            for _k in range(nseg[i]):
                if tx <= ty and tx <= tz:
                    te, tx = tx, tx + dx
                elif ty <= tz:
                    te, ty = ty, ty + dy
                else:
                    te, tz = tz, tz + dz
                t = min(max(te, t + et), t1)
            out[i] = t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tree", default=None, help="lego | procedural | PATH.npz (default lego)")
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    add_data_root(ap)
    add_out(ap, "march_anatomy.json")
    a = ap.parse_args(argv)

    from plenoctree._util import vec3 as _vec
    from plenoctree.render._spec import flat_tree as _flat

    tree, desc = load_bench_tree(a.tree, root=a.data_root)
    child, data = _flat(tree.child, tree.data)
    off, inv, eps = _vec(tree.offset), _vec(tree.invradius), 1e-6
    cams = orbit_cameras(a.views, a.size)
    views = [tuple(np.ascontiguousarray(x.reshape(-1, 3)) for x in cams.rays(i))
             for i in range(a.views)]
    n = a.size * a.size
    grid = np.zeros((1 << _G) ** 3, np.int32)
    t0 = time.perf_counter()
    _build_grid(child, grid)
    grid_s = time.perf_counter() - t0
    sk = skip_tables(child, data)
    segs = [np.zeros(n, np.int64) for _ in views]
    skip_segs = [np.zeros(n, np.int64) for _ in views]
    outs = {k: [np.zeros(n) for _ in views] for k in
            ("march", "empty_skip", "root", "interleave4", "predict", "level_loop", "level_clz",
             "grid", "param", "geometry", "dda")}
    calls = {
        "march": lambda v: _march(child, NO_SKIP, 0, data, off, inv, *views[v], eps, True,
                                  outs["march"][v], segs[v]),
        "empty_skip": lambda v: _march(sk.child, sk.skip, sk.shift, data, off, inv, *views[v],
                                       eps, True, outs["empty_skip"][v], skip_segs[v]),
        "root": lambda v: _march(child, NO_SKIP, 0, data, off, inv, *views[v], eps, False,
                                 outs["root"][v], np.zeros(n, np.int64)),
        "interleave4": lambda v: _interleave4(child, data, off, inv, *views[v], eps,
                                                 outs["interleave4"][v]),
        "predict": lambda v: _predict(child, data, off, inv, *views[v], eps,
                                      outs["predict"][v]),
        "level_loop": lambda v: _level_march(child, data, off, inv, *views[v], eps, False,
                                             outs["level_loop"][v]),
        "level_clz": lambda v: _level_march(child, data, off, inv, *views[v], eps, True,
                                            outs["level_clz"][v]),
        "grid": lambda v: _grid_march(grid, child, data, off, inv, *views[v], eps,
                                         outs["grid"][v]),
        "param": lambda v: _param(child, data, off, inv, *views[v], eps, outs["param"][v]),
        "geometry": lambda v: _geometry(off, inv, *views[v], eps, segs[v],
                                           outs["geometry"][v]),
        "dda": lambda v: _dda(off, inv, *views[v], eps, segs[v], outs["dda"][v]),
    }
    passes = {k: (lambda f=f: [f(v) for v in range(len(views))]) for k, f in calls.items()}
    times = {k: t.scaled(1 / len(views)) for k, t in interleaved(passes, a.repeats).items()}
    seg = np.concatenate(segs)
    hit = seg > 0
    base = times["march"].median
    rows = {}
    for k in calls:
        ms = 1e3 * times[k].median
        diff = (None if k in ("geometry", "dda") else
                max(float(np.abs(outs[k][v] - outs["march"][v]).max()) for v in range(len(views))))
        rows[k] = {"ms_per_frame": ms, "ms_spread": 1e3 * times[k].spread,
                   "ratio_to_march": base * 1e3 / ms, "max_abs_dT": diff,
                   "ns_per_segment_core": ms * 1e6 * (os.cpu_count() or 1)
                   / max(1, seg.sum() / len(views))}
    report = {"benchmark": "march_anatomy", "tree": desc, "size": a.size, "views": a.views,
              "repeats": a.repeats, "segments_per_hit_ray": float(seg[hit].mean()),
              "hit_fraction": float(hit.mean()), "grid_build_s": grid_s,
              "empty_skip_segments_per_hit_ray": float(np.concatenate(skip_segs)[hit].mean()),
              "empty_skip_build_s": sk.seconds, "rows": rows,
              "machine": machine_info()}
    out = write_json(a.out, report)
    print(f"\nMarch anatomy — {desc['source']}: {desc['n_leaves']} leaves, {a.size}², {a.views} "
          f"orbit views; {report['segments_per_hit_ray']:.1f} segments per hit ray, "
          f"{report['hit_fraction']:.0%} of rays hit the box; with empty-space skipping "
          f"{report['empty_skip_segments_per_hit_ray']:.1f} (tables built in "
          f"{sk.seconds:.1f} s)\n")
    print(markdown_table(
        ["variant", "ms/frame (median)", "± ms", "× march", "ns per segment-core",
         "max \\|ΔT\\| vs march"],
        [[k, f"{r['ms_per_frame']:.1f}", f"{r['ms_spread']:.1f}", f"{r['ratio_to_march']:.2f}",
          f"{r['ns_per_segment_core']:.1f}",
          "–" if r["max_abs_dT"] is None else f"{r['max_abs_dT']:.1e}"]
         for k, r in rows.items()]))
    print(f"\nload average {report['machine']['loadavg']}; wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
