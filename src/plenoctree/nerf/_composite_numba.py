"""numba kernels of op ``composite`` (:mod:`plenoctree.nerf.composite`): eq. (1)–(2) and the
distortion loss of packed samples at a fixed step, forward and analytic backward, one ray per
loop iteration (``prange`` over rays), in float64.

Imported lazily; the maths (and the derivation of the backward pass) is in
:mod:`plenoctree.nerf.composite`'s module doc.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = ["composite_forward", "composite_backward"]


@njit(cache=True, parallel=True)
def composite_forward(sigma, color, t, offsets, step, dist, out):
    """Per ray ``r`` (samples ``offsets[r]:offsets[r + 1]``): ``out[r] = (Σ w c [3], Σ w,
    Σ w t, distortion)``.

    Args: sigma float32 ``[M]``; color float32 ``[M, 3]``; t float32 ``[M]``; offsets int64
    ``[R + 1]``; step: δ; dist: compute column 5 (else 0); out float32 ``[R, 6]``."""
    third = step / 3.0
    for r in prange(out.shape[0]):
        trans = 1.0
        cr = cg = cb = w_sum = wt_sum = loss = 0.0
        for i in range(offsets[r], offsets[r + 1]):
            tau = sigma[i] * step
            att = math.exp(-tau)
            w = trans * (1.0 - att)
            ti = t[i]
            cr += w * color[i, 0]
            cg += w * color[i, 1]
            cb += w * color[i, 2]
            if dist:
                loss += 2.0 * w * (ti * w_sum - wt_sum) + third * w * w
            w_sum += w
            wt_sum += w * ti
            trans *= att
        out[r, 0] = cr
        out[r, 1] = cg
        out[r, 2] = cb
        out[r, 3] = w_sum
        out[r, 4] = wt_sum
        out[r, 5] = loss


@njit(cache=True, inline="always")
def _dl_dw(gr, gg, gb, ga, gd, gl, c0, c1, c2, ti, w, w_before, wt_before, w_tot, wt_tot,
           third):
    """``∂loss/∂w_i`` of one sample (the other weights held fixed)."""
    g = gr * c0 + gg * c1 + gb * c2 + ga + gd * ti
    if gl != 0.0:
        g += gl * (2.0 * (2.0 * (ti * w_before - wt_before) + wt_tot - ti * w_tot)
                   + 2.0 * third * w)
    return g


@njit(cache=True, parallel=True)
def composite_backward(sigma, color, t, offsets, step, grad_out, grad_sigma, grad_color):
    """Gradients of :func:`composite_forward`'s ``out`` w.r.t. ``sigma`` and ``color`` given
    ``grad_out`` float32 ``[R, 6]``; writes ``grad_sigma [M]`` and ``grad_color [M, 3]``
    (float32; slots of no ray untouched). Two passes per ray: the totals ``Σ w``, ``Σ w t``
    and ``G = Σ_j w_j ∂loss/∂w_j``, then ``∂loss/∂τ_i = T_{i+1} ∂loss/∂w_i - Σ_{j>i} w_j
    ∂loss/∂w_j``."""
    third = step / 3.0
    for r in prange(grad_out.shape[0]):
        gr, gg, gb = grad_out[r, 0], grad_out[r, 1], grad_out[r, 2]
        ga, gd, gl = grad_out[r, 3], grad_out[r, 4], grad_out[r, 5]
        a, b = offsets[r], offsets[r + 1]
        # pass 1: totals, and G (the terms of ∂loss/∂w in the totals cancel in G)
        trans = 1.0
        w_sum = wt_sum = big_g = 0.0
        for i in range(a, b):
            att = math.exp(-sigma[i] * step)
            w = trans * (1.0 - att)
            big_g += w * _dl_dw(gr, gg, gb, ga, gd, gl, color[i, 0], color[i, 1],
                                color[i, 2], t[i], w, w_sum, wt_sum, 0.0, 0.0, third)
            w_sum += w
            wt_sum += w * t[i]
            trans *= att
        w_tot, wt_tot = w_sum, wt_sum
        # pass 2: the gradients
        trans = 1.0
        w_sum = wt_sum = done = 0.0
        for i in range(a, b):
            att = math.exp(-sigma[i] * step)
            w = trans * (1.0 - att)
            g = _dl_dw(gr, gg, gb, ga, gd, gl, color[i, 0], color[i, 1], color[i, 2], t[i],
                       w, w_sum, wt_sum, w_tot, wt_tot, third)
            done += w * g
            trans *= att
            grad_sigma[i] = step * (trans * g - (big_g - done))
            grad_color[i, 0] = w * gr
            grad_color[i, 1] = w * gg
            grad_color[i, 2] = w * gb
            w_sum += w
            wt_sum += w * t[i]


def run_forward(sigma: np.ndarray, color: np.ndarray, t: np.ndarray, offsets: np.ndarray,
                step: float, dist: bool) -> np.ndarray:
    """``out [R, 6]`` float32 of :func:`composite_forward` (``R = len(offsets) - 1``)."""
    out = np.zeros((offsets.shape[0] - 1, 6), np.float32)
    composite_forward(sigma, color, t, offsets, float(step), bool(dist), out)
    return out
