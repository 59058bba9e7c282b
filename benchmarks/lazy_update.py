"""What the lazy optimiser step costs without a data-dependent ``nonzero`` (issue 47, item 2).

The device fine-tuning step updates only the cells a batch reached (lazy Adam / RMSprop,
``torch.optim.SparseAdam`` semantics). Before, the CUDA path found them with ``nonzero`` (a
host wait for the count) and gathered / scattered their rows; now one kernel passes over every
row of the gradient and updates the touched ones in place (a dense masked update), clearing the
gradient rows it read so the backward needs no zeroed buffer. Compared here, on one tree size
and share of touched cells:

- ``nonzero``: the old torch code (``(g != 0).any(1)``, ``nonzero``, gathers, Adam on the rows,
  scatters), plus the ``zeros_like`` gradient the old backward allocated every step;
- ``masked twin``: :func:`plenoctree.optim._device_twins.update_torch` (the kernel's torch twin,
  dense ``torch.where`` over every row: the CPU reference, not what runs on CUDA);
- bytes each moves per step (the measure of a bandwidth-bound GPU kernel): the fused kernel
  reads the gradient once (``n·D·4``) and reads and writes values, moments and gradient only of
  the touched rows; the old path wrote the zeroed gradient, read it for the mask, then gathered
  and scattered the touched rows of values, moments and gradient.

CPU seconds are the torch ops on this machine's cores (median of ``--repeat``); the GPU
seconds of the Triton kernel are measured only where a GPU is lent (``gpu_bench.py``).

Usage::

    python benchmarks/lazy_update.py [--cells 2000000] [--dim 49] [--touched 0.05]
"""

from __future__ import annotations

import argparse
import os
import sys

from _bench import add_out, interleaved, machine_info, markdown_table, write_json


def _old_adam(p, g, m1, m2, lr, step):
    """The CUDA path's lazy Adam before the device loop (TorchStepper, nonzero rows)."""
    import torch

    b1, b2 = 0.9, 0.999
    rows = torch.nonzero((g != 0).any(dim=1)).reshape(-1)
    gr = g[rows]
    a = m1[rows].mul_(b1).add_((1 - b1) * gr)
    b = m2[rows].mul_(b2).add_((1 - b2) * gr * gr)
    m1[rows], m2[rows] = a, b
    bc1, bc2 = 1 - b1 ** step, 1 - b2 ** step
    p[rows] -= lr * (a / bc1) / ((b / bc2).sqrt() + 1e-8)
    p[:, -1].clamp_(min=0.0)


def bytes_per_step(n: int, d: int, touched: float) -> dict[str, float]:
    """Bytes moved per step by the fused masked kernel and by the old path (float32)."""
    row, t = 4 * d, touched * n
    fused = n * row + t * row * (3 * 2 + 1)          # read g; r/w p, m1, m2; write g = 0
    old = (n * row                                    # zeros_like(grad) (the old backward)
           + n * row                                  # (g != 0).any(1)
           + t * row * (1 + 2 * 2 + 2 * 3))           # g[rows]; m1, m2 gather+scatter; p r/w
    return {"fused_masked_gb": fused / 1e9, "old_nonzero_gb": old / 1e9}


def main(argv: list[str] | None = None) -> int:
    import torch

    from plenoctree.optim._device_twins import OPT_CODES, update_torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=2_000_000)
    ap.add_argument("--dim", type=int, default=49, help="values a cell (SH16: 49)")
    ap.add_argument("--touched", type=float, default=0.05, help="share of cells a batch reaches")
    ap.add_argument("--repeat", type=int, default=5)
    add_out(ap, "lazy_update.json")
    args = ap.parse_args(argv)
    n, d = args.cells, args.dim
    gen = torch.Generator().manual_seed(0)
    p = torch.randn(n, d, generator=gen)
    m1, m2 = torch.zeros(n, d), torch.zeros(n, d)
    g = torch.zeros(n, d)
    rows = torch.randperm(n, generator=gen)[:int(args.touched * n)]
    g_rows = torch.randn(rows.numel(), d, generator=gen) * 1e-6
    figs = torch.zeros(1, 4, dtype=torch.float64)

    def old() -> None:
        grad = torch.zeros_like(p)                    # the old backward's fresh gradient
        grad[rows] = g_rows
        _old_adam(p, grad, m1, m2, 0.02, 3)

    def masked() -> None:
        g[rows] = g_rows                              # (the kernel clears them after reading)
        update_torch(p, g, m1, m2, OPT_CODES["adam"], 0.02, 0.3,
                     (0.9, 0.999, 1 - 0.9 ** 3, 1 - 0.999 ** 3, 1e-8), figs, 0)
        g[rows] = 0.0

    t = interleaved({"nonzero": old, "masked twin": masked}, args.repeat)
    b = bytes_per_step(n, d, args.touched)
    rows_out = [[name, f"{1e3 * tm.median:.1f} ± {1e3 * tm.spread:.1f}"] for name, tm in t.items()]
    table = markdown_table(["lazy Adam step (CPU torch)", "ms"], rows_out)
    text = (f"{n} cells x {d} values, {100 * args.touched:g} % touched; bytes a step: fused "
            f"masked kernel {b['fused_masked_gb']:.2f} GB, old nonzero path "
            f"{b['old_nonzero_gb']:.2f} GB\n\n{table}")
    print(text)
    out = {"benchmark": "lazy_update", "machine": machine_info(), "args": vars(args),
           "ms": {k: tm.summary() for k, tm in t.items()}, "bytes": b, "table": text}
    print(f"\nwrote {write_json(args.out, out)}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from plenoctree import runtime

    runtime.configure()
    sys.exit(main())
