"""Host round trips and bytes of the conversion's sampling on the GPU path (issue 47, item 3),
counted on the CPU: extraction's per-voxel averages, the σ grid and the refinement's scoring,
each on the host path (numpy points uploaded, every sample's values read back and averaged on
the host) and on the device path (``convert/device_sampling.py``: cells or boxes uploaded,
points drawn, averaged and scored on the device, one row per cell read back), with
``step_ops.py``'s ``Recorder``. On a CPU machine the device path runs on CPU tensors (its
counts are what it does with CUDA tensors); the averages of the two paths are compared on the
same uniform draws (max |Δ|). The network runs as on CUDA in both paths (``step_ops``'
``backends_of("cuda")``: the hash-grid and fused-network Triton launches, their outputs
computed by its stand-ins), so the round trips counted are the sampling's own.

Usage::

    python benchmarks/conversion_ops.py          # lego's NeRF-SH (runs/lego_cpu_400)
    python benchmarks/conversion_ops.py --cells 8192 --samples 8

Writes ``benchmarks/results/conversion_ops.json`` (``--out``) and prints a markdown table.
"""

from __future__ import annotations

import argparse
from contextlib import contextmanager, nullcontext

import numpy as np

from _bench import add_data_root, add_out, data_path, machine_info, markdown_table, write_json


@contextmanager
def device_path_on_cpu():
    """Inside: NeRF fields take the device path (``convert/device_sampling.py``) on CPU
    tensors, drawing the host path's numpy uniforms (the same points, so the two paths'
    results can be compared; also ``tests/test_device_sampling.py``'s switch)."""
    import torch

    from plenoctree.convert import device_sampling as ds

    class Draws:
        device = torch.device("cpu")

        def __init__(self, seed):
            self.rng = np.random.default_rng(seed)

    saved = ds.sampling_device, ds.make_rng, ds.uniforms
    from_numpy = torch.from_numpy           # the stand-in's draws: not counted as an upload
    ds.sampling_device = lambda f: torch.device("cpu") if hasattr(f, "query_torch") else None
    ds.make_rng = lambda f, seed: Draws(seed)
    ds.uniforms = lambda g, m, s: from_numpy(g.rng.random((m, s, 3)))
    try:
        yield
    finally:
        ds.sampling_device, ds.make_rng, ds.uniforms = saved


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default=None, help="NeRF-SH run (default: runs/lego_cpu_400)")
    ap.add_argument("--cells", type=int, default=4096, help="cells sampled")
    ap.add_argument("--samples", type=int, default=8, help="samples per cell (extract's)")
    ap.add_argument("--chunk", type=int, default=1 << 16, help="points per field call")
    add_data_root(ap)
    add_out(ap, "conversion_ops.json")
    args = ap.parse_args(argv)
    import step_ops

    from plenoctree.convert.field import NeRFField
    from plenoctree.convert.grid import GridSpec, evaluate_density_grid
    from plenoctree.convert.refine import leaf_spread
    from plenoctree.convert.sampling import SampleOptions, sample_cells
    from plenoctree.nerf import load_nerf
    from plenoctree.octree import Octree

    run = args.run or str(data_path(args.data_root, "runs", "lego_cpu_400"))
    field = NeRFField(load_nerf(run))
    b = field.scene_bbox
    spec = GridSpec.make((b[0] + b[1]) / 2, (b[1] - b[0]) / 2, 64)
    flat = np.sort(np.random.default_rng(0).choice(64 ** 3, args.cells, replace=False))
    opts = SampleOptions(samples=args.samples, chunk=args.chunk, seed=0, averaging="opacity",
                         show_progress=False)
    small = GridSpec.make(spec.center, spec.radius, 32)
    mask = evaluate_density_grid(field, small, show_progress=False) > 0
    tree = Octree.from_grid(sample_cells(field, small, np.flatnonzero(mask), opts), mask,
                            small.center, small.radius, field.data_format)
    leaves = np.arange(min(args.cells, tree.n_leaves))
    tasks = {   # name: (what it does, units the bytes are divided by)
        "extraction's averages": (lambda: sample_cells(field, spec, flat, opts), flat.size),
        "σ grid (32³)": (lambda: evaluate_density_grid(field, small, show_progress=False),
                         small.res ** 3),
        "refinement's scores": (lambda: leaf_spread(tree, field, args.samples, 0, args.chunk,
                                                    leaves), leaves.size),
    }
    rec, rows, out = step_ops.Recorder(), [], {}
    with step_ops.backends_of("cuda"):      # warm-up: once-per-process set-up not counted
        for fn, _ in tasks.values():
            fn()
    for name, (fn, per) in tasks.items():
        res = {}
        for path in ("host", "device"):
            with device_path_on_cpu() if path == "device" else nullcontext(), \
                    step_ops.backends_of("cuda"):
                with rec.region() as c:
                    res[path] = fn()
            d = c.as_dict()
            out[f"{name}: {path}"] = {k: v for k, v in d.items() if k != "top_ops"}
            rows.append([name, path, d["ops"], d["sync_upload"], d["sync_host"] + d["sync_item"],
                         round(d["bytes_upload"] / per, 1), round(d["bytes_host"] / per, 1)])
        diff = float(np.max(np.abs(np.asarray(res["device"]) - np.asarray(res["host"]))))
        rows[-2].append("")
        rows[-1].append(f"{diff:.1e}")
        out[f"{name}: max_abs_diff"] = diff
    print(f"{args.cells} cells, {args.samples} samples a cell, {args.chunk} points a call, "
          f"{field.data_format} ({run})")
    print(markdown_table(["step", "path", "ops", "uploads", "read-backs", "bytes up / cell",
                          "bytes down / cell", "max |Δ| vs host"], rows))
    write_json(args.out, {"benchmark": "conversion_ops", "machine": machine_info(),
                          "args": vars(args), "results": out})
    return 0


if __name__ == "__main__":
    import os

    os.environ.setdefault("TRITON_INTERPRET", "1")       # before triton is imported
    os.environ.setdefault("PLENOCTREE_TRITON_CPU", "1")
    raise SystemExit(main())
