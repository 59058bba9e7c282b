"""Triton kernels of the NeRF-SH network after its encoding, one launch each way (issue 47).

The eager network (:meth:`.model.RadianceField.radiance` with the torch backend) runs the trunk
layer by layer: per layer a matmul, a bias, a ReLU, under autocast a cast of the weights,
then the head, σ's activation and the SH colours, three passes a training step (the density
of the candidates, the trained samples, the sparsity prior's points): 61 ops forward and most
of the backward's 101 in the fixed step (``benchmarks/step_ops.py`` at 95bf554). Here one
program takes ``tiles`` tiles of ``BLOCK_M`` rows through the whole network in registers:

* forward: ``h_1 = relu(x W_0ᵀ + b_0)``, ``h_{l+1} = relu(h_l W_lᵀ + b_l)`` (``DEPTH`` layers),
  ``out = h W_hᵀ + b_h``; ``σ = exp(out_0 - 1)`` (``trunc_exp``, ACT 1) or ``relu(out_0)``
  (ACT 0); ``rgb_c = sigmoid(Σ_b out_{1 + cB + b} Y_b(d))`` (the SH basis of
  :mod:`plenoctree._sh_triton`); with ``DENSITY`` only the head's σ row;
* backward: the forward again (recomputed, nothing kept but the inputs), then ``∂L/∂out`` from
  ``∂L/∂σ`` and ``∂L/∂rgb`` (``σ' = exp(min(out_0 - 1, 15))`` as ``model.trunc_exp``;
  ``rgb_c (1 - rgb_c) Y_b``), back through the head and the trunk (``∂/∂h = g W``, ReLU by
  ``h > 0``); each weight's gradient ``gᵀ h`` and each bias's ``Σ g`` summed over the program's
  tiles in registers and added once into the gradient buffers (atomic adds); ``∂L/∂x`` written
  for the encoding's backward. No gradient for the directions (as the numba SH colours).

The twin is the eager network itself (:func:`.model._mlp_torch`); the kernels cover the
cpu/gpu presets' shape family (:func:`.model.mlp_spec`): a hash-grid encoding of ``16..128``
features (a power of two), 1–3 trunk layers of one power-of-two width ``16..128`` without a
skip connection, an SH head of degree ≤ 4. Other networks run the eager path.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from .._sh_triton import _CONSTS, _basis
from .model import MLPSpec

__all__ = ["FusedField", "mlp_backend", "BLOCK_M"]

BLOCK_M = 64
PROGRAMS = 1024          # programs of a launch at most (each takes several tiles)


@triton.jit
def _act(raw, ACT: tl.constexpr):
    if ACT == 1:
        return tl.exp(raw - 1.0)
    return tl.maximum(raw, 0.0)


@triton.jit
def _act_grad(raw, g, ACT: tl.constexpr):
    if ACT == 1:
        return g * tl.exp(tl.minimum(raw - 1.0, 15.0))
    return tl.where(raw > 0.0, g, 0.0)


@triton.jit
def _load_wt(w_ptr, kin, kout, K: tl.constexpr):
    """``Wᵀ [K, N]`` of a weight stored ``[N, K]`` row-major (``kin [K]``, ``kout [N]``)."""
    return tl.load(w_ptr + kout[None, :] * K + kin[:, None])


@triton.jit
def _mlp_kernel(x_ptr, dir_ptr, w0_ptr, b0_ptr, w1_ptr, b1_ptr, w2_ptr, b2_ptr, wh_ptr, bh_ptr,
                sig_ptr, rgb_ptr, gsig_ptr, grgb_ptr, gx_ptr,
                gw0_ptr, gb0_ptr, gw1_ptr, gb1_ptr, gw2_ptr, gb2_ptr, gwh_ptr, gbh_ptr,
                n, tiles,
                c0, c1, c20, c21, c22, c23, c24, c30, c31, c32, c33, c34, c35, c36,
                c40, c41, c42, c43, c44, c45, c46, c47, c48,
                DIN: tl.constexpr, W: tl.constexpr, NOUT: tl.constexpr, NP: tl.constexpr,
                DEPTH: tl.constexpr, DEG: tl.constexpr, B: tl.constexpr, ACT: tl.constexpr,
                DENSITY: tl.constexpr, BACKWARD: tl.constexpr, BLOCK_M: tl.constexpr):
    pid = tl.program_id(0)
    kin = tl.arange(0, DIN)
    kw = tl.arange(0, W)
    cp = tl.arange(0, NP)
    w0t = _load_wt(w0_ptr, kin, kw, DIN)                         # [DIN, W]
    b0 = tl.load(b0_ptr + kw)
    w1t = w0t
    b1 = b0
    w2t = w0t
    b2 = b0
    if DEPTH >= 2:
        w1t = _load_wt(w1_ptr, kw, kw, W)                        # [W, W]
        b1 = tl.load(b1_ptr + kw)
    if DEPTH >= 3:
        w2t = _load_wt(w2_ptr, kw, kw, W)
        b2 = tl.load(b2_ptr + kw)
    col_ok = cp < NOUT
    if DENSITY:
        wh0 = tl.load(wh_ptr + kw)                               # the σ row [W]
        bh0 = tl.load(bh_ptr)
        wht = tl.zeros([W, NP], dtype=tl.float32)
        bh = tl.zeros([NP], dtype=tl.float32)
    else:
        wh0 = tl.zeros([W], dtype=tl.float32)
        bh0 = 0.0
        wht = tl.load(wh_ptr + cp[None, :] * W + kw[:, None], mask=col_ok[None, :], other=0.0)
        bh = tl.load(bh_ptr + cp, mask=col_ok, other=0.0)
    # the head's columns: 0 is σ, 1 + c B + b is channel c's coefficient of basis b
    bc = cp[None, :] - 1
    inb = (bc >= 0) & col_ok[None, :]
    bidx = tl.where(inb, bc % B, -1)
    chan = tl.where(inb, bc // B, -1)
    if BACKWARD:
        a_w0 = tl.zeros([W, DIN], dtype=tl.float32)
        a_b0 = tl.zeros([W], dtype=tl.float32)
        a_w1 = tl.zeros([W, W], dtype=tl.float32)
        a_b1 = tl.zeros([W], dtype=tl.float32)
        a_w2 = tl.zeros([W, W], dtype=tl.float32)
        a_b2 = tl.zeros([W], dtype=tl.float32)
        a_wh = tl.zeros([NP, W], dtype=tl.float32)
        a_bh = tl.zeros([NP], dtype=tl.float32)
        a_wh0 = tl.zeros([W], dtype=tl.float32)
        a_bh0 = tl.zeros([BLOCK_M], dtype=tl.float32)
    for t in range(tiles):
        rows = (pid * tiles + t) * BLOCK_M + tl.arange(0, BLOCK_M)
        valid = rows < n
        r64 = rows.to(tl.int64)
        x = tl.load(x_ptr + r64[:, None] * DIN + kin[None, :], mask=valid[:, None], other=0.0)
        h1 = tl.maximum(tl.dot(x, w0t) + b0[None, :], 0.0)
        h = h1
        h2 = h1
        h3 = h1
        if DEPTH >= 2:
            h2 = tl.maximum(tl.dot(h1, w1t) + b1[None, :], 0.0)
            h = h2
        if DEPTH >= 3:
            h3 = tl.maximum(tl.dot(h2, w2t) + b2[None, :], 0.0)
            h = h3
        if DENSITY:
            raw = tl.sum(h * wh0[None, :], axis=1) + bh0
            out = tl.zeros([BLOCK_M, NP], dtype=tl.float32)
        else:
            out = tl.dot(h, wht) + bh[None, :]
            raw = tl.sum(tl.where(cp[None, :] == 0, out, 0.0), axis=1)
        if not DENSITY:
            dx = tl.load(dir_ptr + r64 * 3 + 0, mask=valid, other=0.0).to(tl.float32)[:, None]
            dy = tl.load(dir_ptr + r64 * 3 + 1, mask=valid, other=0.0).to(tl.float32)[:, None]
            dz = tl.load(dir_ptr + r64 * 3 + 2, mask=valid, other=0.0).to(tl.float32)[:, None]
            basis = _basis(dx, dy, dz, bidx, c0, c1, c20, c21, c22, c23, c24, c30, c31, c32,
                           c33, c34, c35, c36, c40, c41, c42, c43, c44, c45, c46, c47, c48, DEG)
            prod = out * basis
            s0 = 1.0 / (1.0 + tl.exp(-tl.sum(tl.where(chan == 0, prod, 0.0), axis=1)))
            s1 = 1.0 / (1.0 + tl.exp(-tl.sum(tl.where(chan == 1, prod, 0.0), axis=1)))
            s2 = 1.0 / (1.0 + tl.exp(-tl.sum(tl.where(chan == 2, prod, 0.0), axis=1)))
        if not BACKWARD:
            tl.store(sig_ptr + r64, _act(raw, ACT), mask=valid)
            if not DENSITY:
                tl.store(rgb_ptr + r64 * 3 + 0, s0, mask=valid)
                tl.store(rgb_ptr + r64 * 3 + 1, s1, mask=valid)
                tl.store(rgb_ptr + r64 * 3 + 2, s2, mask=valid)
        else:
            gs = tl.load(gsig_ptr + r64, mask=valid, other=0.0).to(tl.float32)
            g_raw = _act_grad(raw, gs, ACT)
            if DENSITY:
                gh = g_raw[:, None] * wh0[None, :]
                a_wh0 += tl.sum(g_raw[:, None] * h, axis=0)
                a_bh0 += g_raw
            else:
                g0 = tl.load(grgb_ptr + r64 * 3 + 0, mask=valid, other=0.0).to(tl.float32)
                g1 = tl.load(grgb_ptr + r64 * 3 + 1, mask=valid, other=0.0).to(tl.float32)
                g2 = tl.load(grgb_ptr + r64 * 3 + 2, mask=valid, other=0.0).to(tl.float32)
                gc = tl.where(chan == 0, (g0 * s0 * (1.0 - s0))[:, None],
                              tl.where(chan == 1, (g1 * s1 * (1.0 - s1))[:, None],
                                       tl.where(chan == 2, (g2 * s2 * (1.0 - s2))[:, None],
                                                0.0)))
                gout = tl.where(cp[None, :] == 0, g_raw[:, None], gc * basis)  # [BM, NP]
                gh = tl.dot(gout, tl.trans(wht))                              # [BM, W]
                a_wh += tl.dot(tl.trans(gout), h)
                a_bh += tl.sum(gout, axis=0)
            if DEPTH >= 3:
                ga = tl.where(h3 > 0.0, gh, 0.0)
                a_w2 += tl.dot(tl.trans(ga), h2)
                a_b2 += tl.sum(ga, axis=0)
                gh = tl.dot(ga, tl.trans(w2t))
            if DEPTH >= 2:
                ga = tl.where(h2 > 0.0, gh, 0.0)
                a_w1 += tl.dot(tl.trans(ga), h1)
                a_b1 += tl.sum(ga, axis=0)
                gh = tl.dot(ga, tl.trans(w1t))
            ga = tl.where(h1 > 0.0, gh, 0.0)
            a_w0 += tl.dot(tl.trans(ga), x)
            a_b0 += tl.sum(ga, axis=0)
            gx = tl.dot(ga, tl.trans(w0t))                                    # [BM, DIN]
            tl.store(gx_ptr + r64[:, None] * DIN + kin[None, :], gx, mask=valid[:, None])
    if BACKWARD:
        tl.atomic_add(gw0_ptr + kw[:, None] * DIN + kin[None, :], a_w0)
        tl.atomic_add(gb0_ptr + kw, a_b0)
        if DEPTH >= 2:
            tl.atomic_add(gw1_ptr + kw[:, None] * W + kw[None, :], a_w1)
            tl.atomic_add(gb1_ptr + kw, a_b1)
        if DEPTH >= 3:
            tl.atomic_add(gw2_ptr + kw[:, None] * W + kw[None, :], a_w2)
            tl.atomic_add(gb2_ptr + kw, a_b2)
        if DENSITY:
            tl.atomic_add(gwh_ptr + kw, a_wh0)
            tl.atomic_add(gbh_ptr, tl.sum(a_bh0, axis=0))
        else:
            tl.atomic_add(gwh_ptr + cp[:, None] * W + kw[None, :], a_wh, mask=col_ok[:, None])
            tl.atomic_add(gbh_ptr + cp, a_bh, mask=col_ok)


def _params(field) -> list[torch.Tensor]:
    """``[W_0, b_0, W_1, b_1, W_2, b_2, W_h, b_h]`` (the unused layers' slots: ``W_0, b_0``)."""
    tr = field.trunk
    out = []
    for i in range(3):
        lay = tr[i] if i < len(tr) else tr[0]
        out += [lay.weight, lay.bias]
    return out + [field.head.weight, field.head.bias]


def _grid(n: int) -> tuple[int, int]:
    """``(programs, tiles per program)`` for ``n`` rows."""
    from .._triton import interpret_mode

    n_tiles = max(1, triton.cdiv(n, BLOCK_M))
    progs = min(n_tiles, 8 if interpret_mode() else PROGRAMS)
    tiles = triton.cdiv(n_tiles, progs)
    return triton.cdiv(n_tiles, tiles), tiles


def _launch(spec: MLPSpec, density: bool, x, dirs, params, sig, rgb, grads=None, gsig=None,
            grgb=None, gx=None) -> None:
    n = x.shape[0]
    if n == 0:
        return
    progs, tiles = _grid(n)
    g = grads if grads is not None else [sig] * 8
    _mlp_kernel[(progs,)](
        x, dirs, *params, sig, rgb, sig if gsig is None else gsig,
        sig if grgb is None else grgb, x if gx is None else gx, *g, n, tiles,
        *map(float, _CONSTS), DIN=spec.din, W=spec.width, NOUT=spec.n_out,
        NP=max(16, triton.next_power_of_2(spec.n_out)), DEPTH=spec.depth,
        DEG=max(spec.degree, 0), B=(spec.n_out - 1) // 3, ACT=spec.act, DENSITY=bool(density),
        BACKWARD=grads is not None, BLOCK_M=BLOCK_M)


class FusedField(torch.autograd.Function):
    """``apply(x [N, DIN] float32, dirs [N, 3] | None, spec, in_place, *params) -> (σ [N],
    rgb [N, 3])`` (``dirs`` None: σ only). Gradients to ``x`` and the parameter slots of
    :func:`_params` (a slot repeated for a missing layer: only its own layer's gradient).

    With ``in_place`` the backward adds the parameters' gradients straight into their
    ``.grad`` (created when None) and returns none for them, as the hash grid's in-place mode
    (:class:`.encoding._HashGridNumba`): the trainer's three passes a step share one buffer
    per parameter, zeroed by ``zero_grad`` (``loss.backward()`` only, not
    ``torch.autograd.grad``)."""

    @staticmethod
    def forward(ctx, x, dirs, spec, in_place, *params):
        # (inside forward nothing is recorded: the inputs are used as they are)
        x = x.contiguous()
        density = dirs is None
        d = x if density else dirs.contiguous()
        sig = torch.empty(x.shape[0], dtype=torch.float32, device=x.device)
        rgb = sig if density else torch.empty((x.shape[0], 3), dtype=torch.float32,
                                              device=x.device)
        _launch(spec, density, x, d, params, sig, rgb)
        ctx.save_for_backward(x, d, *params)
        ctx.spec, ctx.density, ctx.in_place = spec, density, in_place
        if density:
            return sig
        return sig, rgb

    @staticmethod
    def backward(ctx, gsig, grgb=None):
        x, d, *ps = ctx.saved_tensors
        spec, density = ctx.spec, ctx.density
        used = [i < 2 * spec.depth or i >= 6 for i in range(len(ps))]
        if ctx.in_place:
            params = ctx.in_place
            for p, u in zip(params, used):
                if u and p.grad is None:
                    p.grad = torch.zeros_like(p)
            grads = [p.grad if u else None for p, u in zip(params, used)]
        else:
            grads = [torch.zeros_like(p) if u else None for p, u in zip(ps, used)]
        launch = [g if g is not None else grads[i % 2] for i, g in enumerate(grads)]
        gx = torch.empty_like(x)
        _launch(spec, density, x, d, ps, gsig, gsig, launch, gsig.contiguous(),
                None if density else grgb.contiguous(), gx)
        if ctx.in_place:
            grads = [None] * len(ps)
        return (gx, None, None, None, *grads)


def mlp_backend(field, points: torch.Tensor, dirs: torch.Tensor | None):
    """Op ``mlp`` of :mod:`plenoctree.backend` (CUDA tensors, or the CPU in the interpreter):
    ``(σ [N], rgb [N, 3])`` of a :class:`~.model.RadianceField` at world ``points [N, 3]``
    seen along unit ``dirs [N, 3]`` (``dirs`` None: ``σ [N]``): its encoding, then the
    kernel (a network outside :func:`~.model.mlp_spec`'s family:
    :class:`~plenoctree.errors.BackendError`)."""
    from .._triton import require_triton
    from ..errors import BackendError

    require_triton(points.device, "mlp")
    spec = field.spec
    if spec is None:
        raise BackendError("mlp: backend 'triton' covers hash-grid SH networks of 1-3 "
                           "power-of-two layers without a skip connection; use 'torch'")
    params = _params(field)
    in_place = params if field.grad_in_place and torch.is_grad_enabled() else None
    return FusedField.apply(field.encoder(points).float(), dirs, spec, in_place, *params)
