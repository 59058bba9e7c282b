"""Does the numba renderer draw the same image whether it compiled its kernel or loaded it from
numba's disk cache, and is each within the spec (max |Δ rgb| ≤ 1e-4) of the torch twin?

With ``fastmath=True`` the render kernel loaded from the cache was optimised differently from
the freshly compiled one (reassociation) and a few lookups landed in the neighbouring leaf
(4.6e-3 from the twin on a lego view); the marching kernels now compile with
``_march_numba.MARCH_MATH``. This check renders views of a real tree in two child processes
sharing an empty ``NUMBA_CACHE_DIR`` (the first compiles and writes the cache, the second loads
it), renders the same views with the twin in this process, and prints the differences.

Usage (~1-2 min: one compile of the kernel)::

    .venv/bin/python benchmarks/kernel_cache_check.py                  # lego when found
    .venv/bin/python benchmarks/kernel_cache_check.py --tree TREE.npz --size 400 --views 4

Writes ``benchmarks/results/kernel_cache_check.json`` (``--out``); exits 1 when the two states
differ or either is more than 1e-4 from the twin.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from _bench import add_data_root, add_out, machine_info, markdown_table, run_python, write_json
from _trees import load_bench_tree, orbit_cameras

SPEC = 1e-4


def _images(tree, size: int, views: int, backend: str) -> np.ndarray:
    """``[views, size, size, 3]`` float32 images of ``views`` orbit cameras."""
    from plenoctree.render import RenderOptions, render_image, tree_to_device

    if backend == "numba":
        tree = tree_to_device(tree, "cpu")             # as eval / video render
    cams = orbit_cameras(views, size)
    return np.stack([np.asarray(render_image(tree, cams, i, RenderOptions(),
                                             backend=backend).rgb) for i in range(views)])


def numba_states(a: argparse.Namespace) -> dict[str, np.ndarray]:
    """The numba images of a process that compiles the kernel (``fresh``) and of one that
    loads it (``cached``): two child processes of this script (``--child``) sharing an empty
    ``NUMBA_CACHE_DIR``, which numba reads when it loads, so it cannot be set in-process."""
    imgs = {}
    with tempfile.TemporaryDirectory(prefix="numba-cache-") as tmp:
        for state in ("fresh", "cached"):
            path = Path(tmp) / f"{state}.npy"
            run_python([__file__, "--size", a.size, "--views", a.views, "--child", path]
                       + (["--tree", a.tree] if a.tree else [])
                       + (["--data-root", a.data_root] if a.data_root else []),
                       env={"NUMBA_CACHE_DIR": tmp})
            imgs[state] = np.load(path)
    return imgs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tree", default=None, help="lego | procedural | PATH.npz (default lego)")
    ap.add_argument("--size", type=int, default=400)
    ap.add_argument("--views", type=int, default=2)
    add_data_root(ap)
    add_out(ap, "kernel_cache_check.json")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)   # internal: save numba
    a = ap.parse_args(argv)
    # (Here first: lego is extracted once, before the children load it.)
    tree, desc = load_bench_tree(a.tree, root=a.data_root)
    if a.child:
        np.save(a.child, _images(tree, a.size, a.views, "numba"))
        return 0
    imgs = numba_states(a)
    twin = _images(tree, a.size, a.views, "torch")
    rows = {}
    for state, img in imgs.items():
        d = np.abs(img - twin)
        rows[state] = {"max_abs_vs_twin": float(d.max()), "over_spec": int((d > SPEC).sum()),
                       "over_1e-5": int((d > 1e-5).sum())}
    print()
    print(markdown_table(["kernel", "max \\|Δ rgb\\| vs twin", f"values > {SPEC:g}",
                          "values > 1e-5"],
                         [[state, f"{r['max_abs_vs_twin']:.2e}", r["over_spec"], r["over_1e-5"]]
                          for state, r in rows.items()]))
    between = float(np.abs(imgs["fresh"] - imgs["cached"]).max())
    ok = between == 0.0 and all(r["over_spec"] == 0 for r in rows.values())
    print(f"\nfresh vs cached: max |Δ| {between:.2e} ({'same image' if between == 0 else 'DIFFER'})"
          f"; {a.views} views at {a.size}²; {'OK' if ok else 'FAIL'}")
    out = write_json(a.out, {"benchmark": "kernel_cache_check", "tree": desc["source"],
                             "size": a.size, "views": a.views, "states": rows,
                             "fresh_vs_cached": between, "ok": ok, "machine": machine_info()})
    print(f"wrote {out}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
