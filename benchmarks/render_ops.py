"""Torch ops, host read-backs and uploads of one ``render_image`` frame on the GPU path
(issue 47, item 3), counted on the CPU: the device path (``render/_device.py``: rays made on
the device, the tree's box kept there, the SH basis in one Triton launch) against the path
before it (numpy rays from ``Cameras.rays`` uploaded, then ``render_rays``), both through the
Triton kernels in Triton's interpreter, with ``step_ops.py``'s ``Recorder``. The counts do not
depend on the frame's size (a small one keeps the interpreter quick); the image is checked
against the numba renderer.

Usage::

    python benchmarks/render_ops.py            # lego's 256³ tree (extracted once into the cache)
    python benchmarks/render_ops.py --tree procedural --size 32

Writes ``benchmarks/results/render_ops.json`` (``--out``) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import os
import sys

from _bench import add_data_root, add_out, machine_info, markdown_table, write_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", default=None, help="lego (default when found), procedural, or a file")
    ap.add_argument("--size", type=int, default=24, help="frame side in pixels")
    add_data_root(ap)
    add_out(ap, "render_ops.json")
    args = ap.parse_args(argv)
    import torch

    import step_ops
    from _trees import load_bench_tree, orbit_cameras

    from plenoctree.render import DeviceTree, RenderOptions, render_image, render_rays
    from plenoctree.render._device import render_camera_device
    from plenoctree.render.options import parse_data_format

    tree, desc = load_bench_tree(args.tree, root=args.data_root)
    cams = orbit_cameras(1, args.size)
    fast, dev, opts = DeviceTree(tree, "cpu"), torch.device("cpu"), RenderOptions()
    info = parse_data_format(tree.data_format, tree.data_dim, tree.extra_data)

    def device_path():
        return render_camera_device(fast, info, cams, 0, opts, dev, "triton")

    def before():
        o, d = cams.rays(0)
        return render_rays(fast, torch.from_numpy(o), torch.from_numpy(d), opts, "triton")

    rec, rows = step_ops.Recorder(), {}
    ref = render_image(tree, cams, 0, opts, backend="numba").rgb
    for name, fn in (("before: host rays + render_rays", before), ("device path", device_path)):
        out = fn()                                     # warm-up (the interpreter's parse)
        with rec.region() as c:
            fn()
        rows[name] = {**{k: v for k, v in c.as_dict().items() if k != "top_ops"},
                      "max_abs_diff_rgb_vs_numba": float((out.rgb.reshape(ref.shape) - ref)
                                                         .abs().max())}
    head = ["path", "ops", "triton", "read-backs", "uploads", "max |Δ rgb| vs numba"]
    cells = [[k, f"{r['ops']:.0f}", f"{r['triton']:.0f}",
              f"{r['sync_item'] + r['sync_shape'] + r['sync_host']:.0f}",
              f"{r['sync_upload']:.0f}", f"{r['max_abs_diff_rgb_vs_numba']:.1e}"]
             for k, r in rows.items()]
    name = f"{desc.get('kind', args.tree)}, {desc.get('n_leaves', '?')} leaves"
    print(f"One render_image frame on the GPU path ({name}, {args.size}², counted on the "
          "CPU)\n")
    print(markdown_table(head, cells))
    report = {"benchmark": "render_ops", "tree": desc, "size": args.size,
              "machine": machine_info(), "rows": rows}
    print(f"\nwrote {write_json(args.out, report)}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("TRITON_INTERPRET", "1")       # before triton is imported
    os.environ.setdefault("PLENOCTREE_TRITON_CPU", "1")
    sys.exit(main())
