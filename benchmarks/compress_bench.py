"""Web compression (paper B.2) and viewer frame time: the figures of the compression issue.

Usage::

    python benchmarks/compress_bench.py [--tree TREE.npz] [--data DATASET_DIR] [--bits 16]
        [--sizes 256 800] [--out benchmarks/results/compress_bench.json]

Without ``--tree`` the benchmark tree is the procedural scene at ``--resolution`` (saved as a
float16 native tree). Its colours take few distinct values, so it compresses far better than a
trained tree. Two stand-ins until a lego tree exists: ``--texture S`` adds to every SH
coefficient of band ``l`` of every occupied leaf a smooth random field (4 random sinusoids of
position) of amplitude ``S / (l + 1)`` plus 5 % of that as i.i.d. noise (continuous, spatially
coherent colour, no two leaves equal: like a fitted tree); ``--noise S`` adds only i.i.d.
Gaussian noise of std ``S / (l + 1)`` (no spatial coherence at all: the worst case). ``--procedural-data N``
renders N test views of the procedural scene (ground truth for the PSNR change).
Measured, for each ``--bits``:

- raw file MB; compressed ``.plnz`` MB, ratio, compress seconds (median cut + DEFLATE + write)
  and decompress seconds (read + inflate + decode);
- PSNR change on the ``--split`` views of ``--data`` (ground truth), or without data the PSNR
  of the compressed tree's renders against the raw tree's (orbit views);
- baseline measured in the same run: DEFLATE alone (``np.savez_compressed`` of the raw arrays,
  the original script's ``--noquant``): MB, ratio, seconds.

Viewer: median ms per frame of the page in headless Chromium (SwiftShader software GL unless
the browser has a GPU) at each ``--sizes`` px, for the compressed tree; baseline: the numba CPU
renderer on the same camera. Skipped with a note when Chromium or playwright is missing.
Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import io
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _bench import add_out, machine_info, timed, write_json
from plenoctree.compression import CompressOptions
from plenoctree.compression_report import compression_report


def perturb(tree, noise: float, texture: float, seed: int = 0) -> None:
    """Add i.i.d. noise and/or a smooth random field to the SH coefficients (in place)."""
    on = (tree.child == 0) & (tree.data[..., -1] > 0)
    leaf_on = tree.data[tree.child == 0][:, -1] > 0
    x = tree.world_to_tree(tree.leaf_centers()[leaf_on])                # [M, 3] in [0, 1]
    band = np.sqrt(np.arange(tree.basis_dim)).astype(int)               # l of basis b
    amp = np.tile(1.0 / (band + 1.0), 3)                                # channel-major
    rng = np.random.default_rng(seed)
    rows = tree.data[on]
    for c in range(rows.shape[1] - 1):
        if texture > 0:
            f = np.zeros(len(x))
            for _ in range(4):
                f += np.sin(x @ (rng.normal(size=3) * 12.0) + rng.uniform(0, 2 * np.pi))
            rows[:, c] += texture * amp[c] * (0.5 * f + 0.05 * rng.normal(size=len(x)))
        if noise > 0:
            rows[:, c] += noise * amp[c] * rng.normal(size=len(x))
    tree.data[on] = rows


def deflate_baseline(path: Path) -> dict:
    z = np.load(path, allow_pickle=False)
    arrays = {k: z[k] for k in z.files}
    t0 = time.perf_counter()
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    secs = time.perf_counter() - t0
    size = buf.getbuffer().nbytes
    return dict(bytes=size, ratio=path.stat().st_size / size, seconds=secs)


def viewer_frame_times(tree_path: Path, sizes: list[int], frames: int) -> dict:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return {"skipped": "playwright is not installed (scripts/install_browser.sh)"}
    if chromium is None:
        return {"skipped": "no chromium executable (scripts/install_browser.sh)"}
    from plenoctree.compression import load_any_tree
    from plenoctree.compression_report import tree_orbit_cameras
    from plenoctree.render import render_image
    from plenoctree.viewer import ViewerServer

    tree = load_any_tree(tree_path)
    flags = ["--no-sandbox", "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync"]
    out: dict = {"browser": chromium, "frames": frames, "rows": []}
    with sync_playwright() as p, ViewerServer(tree_path, port=0) as srv:
        browser = p.chromium.launch(executable_path=chromium, headless=True, args=flags)
        out["browser_version"] = browser.version
        page = browser.new_page()
        page.goto(srv.url)
        page.wait_for_function("window.viewer && window.viewer.state !== 'loading'",
                               timeout=600_000)
        if page.evaluate("window.viewer.state") != "ready":
            return {"skipped": "page error: " + page.evaluate("window.viewer.message")}
        out["gl_renderer"] = page.evaluate(
            "(() => { const gl = document.createElement('canvas').getContext('webgl2');"
            " const e = gl.getExtension('WEBGL_debug_renderer_info');"
            " return e ? gl.getParameter(e.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER); })()")
        for size in sizes:
            cams = tree_orbit_cameras(tree, n=1, size=size)
            view = dict(c2w=cams.c2w[0].reshape(-1).tolist(), fx=cams.fx, fy=cams.fy,
                        cx=cams.cx, cy=cams.cy, width=size, height=size)
            page.evaluate("v => window.viewer.setView(v)", view)
            ms = page.evaluate(f"window.viewer.benchmark({frames})")
            cpu = timed(lambda: render_image(tree, cams, 0), 3)   # after a warm-up (JIT)
            out["rows"].append(dict(size=size, viewer_ms=ms, cpu_numba_ms=cpu.median * 1e3))
        browser.close()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", default=None, help="tree file (default: procedural scene)")
    ap.add_argument("--resolution", type=int, default=256, help="procedural grid resolution")
    ap.add_argument("--noise", type=float, default=0.0, help="i.i.d. SH noise (procedural only)")
    ap.add_argument("--texture", type=float, default=0.0,
                    help="smooth random SH field amplitude (procedural only)")
    ap.add_argument("--procedural-data", type=int, default=0,
                    help="render this many procedural test views as ground truth")
    ap.add_argument("--view-size", type=int, default=200, help="procedural test view size")
    ap.add_argument("--data", default=None, help="dataset folder for the PSNR change")
    ap.add_argument("--split", default="test")
    ap.add_argument("--downscale", type=int, default=4)
    ap.add_argument("--limit", type=int, default=5, help="views of the split (default 5)")
    ap.add_argument("--bits", type=int, nargs="+", default=[16])
    ap.add_argument("--retain", type=int, default=0)
    ap.add_argument("--sizes", type=int, nargs="*", default=[256], help="viewer sizes in px")
    ap.add_argument("--frames", type=int, default=5)
    add_out(ap, "compress_bench.json")
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="compress_bench_"))
    try:
        if args.tree:
            src = Path(args.tree)
            label = src.name
        else:
            from plenoctree.datasets.procedural import procedural_tree
            from plenoctree.octree.io import save_tree

            src = tmp / f"procedural_{args.resolution}.npz"
            tree = procedural_tree(args.resolution)
            label = f"procedural {args.resolution}^3 (fp16 native)"
            if args.noise > 0 or args.texture > 0:
                perturb(tree, args.noise, args.texture)
                label += f" + SH noise {args.noise}" if args.noise else ""
                label += f" + SH texture {args.texture}" if args.texture else ""
            save_tree(tree, src, precision="fp16")
        data = None
        if args.procedural_data and not args.data:
            from plenoctree.datasets.procedural import write_procedural_dataset

            args.data = str(write_procedural_dataset(
                tmp / "procedural_data", n_train=0, n_val=0, n_test=args.procedural_data,
                width=args.view_size, height=args.view_size))
            args.downscale = 1
        if args.data:
            from plenoctree.datasets import load_dataset

            data = load_dataset(args.data, split=args.split, downscale=args.downscale,
                                limit=args.limit)
        base = deflate_baseline(src)
        rows = []
        for bits in args.bits:
            rep = compression_report(src, tmp / f"bits{bits}.plnz",
                                     CompressOptions(bits=bits, retain=args.retain), data=data)
            rows.append(rep)
        viewer = viewer_frame_times(tmp / f"bits{args.bits[0]}.plnz", args.sizes, args.frames) \
            if args.sizes else {"skipped": "no --sizes"}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"tree: {label}, {rows[0]['n_leaves']} leaves ({rows[0]['n_leaves_kept']} with sigma > 0), "
          f"{rows[0]['data_format']}, raw {rows[0]['raw_bytes'] / 1e6:.2f} MB")
    print(f"baseline DEFLATE only: {base['bytes'] / 1e6:.2f} MB, ratio {base['ratio']:.1f}x, "
          f"{base['seconds']:.2f} s")
    print(f"{'bits':>4} {'MB':>8} {'ratio':>7} {'comp s':>7} {'decomp s':>8} {'PSNR':>26}")
    for r in rows:
        if r.get("eval") == "dataset":
            q = f"{r['psnr_raw']:.2f} -> {r['psnr_compressed']:.2f} ({r['psnr_change']:+.3f})"
        else:
            q = f"fidelity {r['psnr_fidelity']:.2f} dB"
        print(f"{r['options']['bits']:>4} {r['compressed_bytes'] / 1e6:>8.2f} {r['ratio']:>6.1f}x "
              f"{r['compress_s']:>7.2f} {r['decompress_s']:>8.2f} {q:>26}")
    if "rows" in viewer:
        print(f"viewer ({viewer.get('gl_renderer')}):")
        for v in viewer["rows"]:
            print(f"  {v['size']}^2: {v['viewer_ms']:.1f} ms/frame in the browser, "
                  f"numba CPU renderer {v['cpu_numba_ms']:.1f} ms")
    else:
        print(f"viewer: skipped ({viewer['skipped']})")
    for r in rows:
        r.pop("output", None)
    out = write_json(args.out, dict(benchmark="compress_bench", machine=machine_info(),
                                    tree=label, deflate_baseline=base, rows=rows,
                                    viewer=viewer))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
