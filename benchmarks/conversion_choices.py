"""What each conversion choice costs against the NeRF-SH (issue 11 item 2), on the same views.

Starting from a tree extracted with the defaults (``--tree``) and the NeRF-SH run it came from
(``--run``), every row changes one choice and scores the tree on ``--views`` evenly spaced
test views (PSNR / SSIM at the run's resolution), with its leaves:

============================  ================================================================
``tree``                      the given tree as it is (the reference)
``s{S}-{avg}``                the same kept voxels re-valued with ``S`` samples per voxel and
                              the ``mean`` (paper) or ``opacity`` average (σ keeping the
                              samples' mean opacity, opacity-weighted colour; see
                              ``plenoctree.convert.sampling``) — what ``extract --samples S
                              --averaging AVG`` stores (the voxel filter does not depend on
                              either)
``tau{τ}`` / ``margin{m}``    a full extraction with ``--weight-thresh τ`` / ``--bbox-scale m``
                              (``--extract``; minutes each)
``refine-t{t}-p{p}-{avg}``    ``plenoctree refine`` of the reference (or of the ``opacity``
                              re-valued tree) with ``--threshold t --passes p`` (``--refine``)
============================  ================================================================

Usage (lego, the shared NeRF-SH of the data folder ``$PLENOCTREE_DATA``, and the tree
``render_speed.py --tree lego`` extracts into ``benchmarks/results/cache``; ``nice -n 19`` on a
shared machine)::

    .venv/bin/python benchmarks/conversion_choices.py --run $PLENOCTREE_DATA/runs/lego_cpu_400 \\
        --tree benchmarks/results/cache/lego_cpu_400_256.npz \\
        --data $PLENOCTREE_DATA/nerf_synthetic/lego --views 20 \\
        [--samples 8 16 32] [--extract tau0.01 margin1.1] [--refine t0.1-p1-opacity]

Writes ``benchmarks/results/conversion_choices.json`` (``--out``; rows are added to an existing
file, so variants can be measured one call at a time) and prints the table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _bench import add_out, machine_info, write_json


def score(tree, data: str, downscale: int, views: int) -> dict:
    """PSNR / SSIM of an in-memory tree on ``views`` evenly spaced test views."""
    from plenoctree.datasets import load_dataset
    from plenoctree.evaluation import evaluate_tree
    from plenoctree.render import RenderOptions

    test = load_dataset(data, split="test", downscale=downscale, limit=views, spread=True)
    ev = evaluate_tree(tree, test, None, RenderOptions(background=tuple(test.background)),
                       show_progress=False)
    return {"psnr": float(ev.mean_psnr), "ssim": float(ev.mean_ssim), "views": len(test),
            "leaves": int(tree.n_leaves)}


def revalue(tree, field_, samples: int, averaging: str, seed: int = 0,
            chunk: int = 1 << 17):
    """The tree with every kept leaf (any value non-zero) re-valued from ``samples`` field
    samples in its box with ``averaging``; empty leaves stay empty."""
    from plenoctree.convert.refine import _blocks, _box_stats, _leaf_boxes

    idx, lo, size, _ = _leaf_boxes(tree)
    vals = tree.data[idx]
    kept = np.flatnonzero(np.any(vals != 0, axis=1))
    rng = np.random.default_rng(seed)
    new = np.array(vals, np.float32)
    for s, e in _blocks(kept.size, samples, chunk):
        b = kept[s:e]
        new[b], _ = _box_stats(field_, lo[b], size[b], tree, samples, rng, averaging)
    data = np.array(tree.data, np.float32)
    data[idx] = new
    return dataclasses.replace(tree, data=data)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, help="trained NeRF-SH run directory")
    ap.add_argument("--tree", required=True, help="tree extracted from it with the defaults")
    ap.add_argument("--data", required=True, help="dataset folder")
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--samples", type=int, nargs="*", default=[8],
                    help="samples per voxel of the re-valued rows (both averages each)")
    ap.add_argument("--averaging", nargs="*", default=["mean", "opacity"])
    ap.add_argument("--extract", nargs="*", default=[],
                    help="full-extraction rows: tau<τ_w> and/or margin<bbox scale>")
    ap.add_argument("--refine", nargs="*", default=[],
                    help="refine rows: t<threshold>-p<passes>-<averaging>")
    ap.add_argument("--seed", type=int, default=0)
    add_out(ap, "conversion_choices.json")
    a = ap.parse_args(argv)

    from plenoctree.convert.extraction import ExtractConfig, _load_run, extract
    from plenoctree.convert.refine import RefineOptions, refine_tree
    from plenoctree.octree import load_tree

    out = Path(a.out)
    res = json.loads(out.read_text()) if out.is_file() else {"rows": {}}
    res.update({"benchmark": "conversion_choices", "run": a.run, "tree": a.tree,
                "views": a.views, "machine": machine_info()})
    rows = res["rows"]
    field_, train_cfg, _ = _load_run(ExtractConfig(run_dir=a.run, device="cpu"))
    down = int(getattr(train_cfg, "downscale", 1) or 1)
    tree = load_tree(a.tree).astype(np.float32)

    def record(name: str, t, t0: float, c0: float, **extra) -> None:
        r = {**score(t, a.data, down, a.views), "seconds": time.perf_counter() - t0,
             "cpu_seconds": time.process_time() - c0, "loadavg": list(os.getloadavg()),
             **extra}
        rows[name] = r
        write_json(out, res)
        print(f"{name:28s} {r['psnr']:7.3f} dB  SSIM {r['ssim']:.4f}  {r['leaves']:>10,d} leaves"
              f"  {r['seconds']:6.0f} s", flush=True)

    if "tree" not in rows:
        record("tree", tree, time.perf_counter(), time.process_time(), what="the given tree")
    for s in a.samples:
        for avg in a.averaging:
            t0, c0 = time.perf_counter(), time.process_time()
            record(f"s{s}-{avg}", revalue(tree, field_, s, avg, a.seed), t0, c0,
                   samples=s, averaging=avg)
    for v in a.extract:
        kw = ({"weight_thresh": float(v[3:])} if v.startswith("tau") else
              {"bbox_scale": float(v[6:])} if v.startswith("margin") else None)
        if kw is None:
            raise SystemExit(f"--extract {v}: use tau<τ_w> or margin<scale>")
        t0, c0 = time.perf_counter(), time.process_time()
        with tempfile.TemporaryDirectory() as tmp:
            r = extract(ExtractConfig(run_dir=a.run, data=a.data, out=str(Path(tmp) / "t.npz"),
                                      eval=False, show_progress=False, **kw))
        record(v, r.tree, t0, c0, **kw)
    for v in a.refine:
        t, p, avg = v.split("-")
        base = tree if avg == "mean" else revalue(tree, field_, 8, avg, a.seed)
        t0, c0 = time.perf_counter(), time.process_time()
        new, recs = refine_tree(base, field_, RefineOptions(passes=int(p[1:]),
                                                            threshold=float(t[1:]),
                                                            seed=a.seed, averaging=avg))
        record(f"refine-{v}", new, t0, c0, threshold=float(t[1:]), passes=int(p[1:]),
               averaging=avg, passes_records=recs)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    from plenoctree import runtime

    runtime.configure()         # as the CLI: before torch / numba load (OMP_WAIT_POLICY, malloc)
    sys.exit(main())
