"""Peak memory of ``plenoctree finetune`` on a real tree, as shipped and with the gradient
slabs as they were (dense).

Usage: ``python benchmarks/finetune_memory.py TREE.npz --data DATASET [--downscale 2]
[--epochs 1] [--out benchmarks/results/finetune_memory.json]``

Each mode runs in its own subprocess (``_bench.child_json``: so one's pages do not count for
the other), with the settings of ``plenoctree run``'s fine-tuning stage (no test split):

- ``shipped``: ``finetune`` as it is: compact per-thread gradient slabs sized by the cells one
  batch reaches (:class:`plenoctree.optim._render_grad.SparseGrad`);
- ``dense_slabs``: the same run with every slab as large as the tree (``capacity = n_cells``)
  and its pages touched at the start — the memory of the dense per-thread slabs used before,
  whose pages a long run touches all of.

A thread samples the process RSS every 50 ms and notes the last line ``finetune`` printed, so
the table says in which phase the peak fell; the JSON also gives the sizes of the big arrays
(values, Adam moments, slabs, training and validation images). Checkpoints are written at
every validation (``checkpoint_minutes=0``), as a long run does. Prints a table, writes JSON.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from pathlib import Path

from _bench import add_out, child_json, machine_info, markdown_table, write_json


def _rss_mb() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) // 1024
    return 0


def child(tree: str, data: str, downscale: int, epochs: int, dense: bool, out: str) -> None:
    """One fine-tuning run; prints a JSON line with its peak RSS and the phase it fell in."""
    from plenoctree.optim import _loop, _render_grad, _steppers
    from plenoctree.optim.finetuning import FinetuneConfig, finetune

    sizes: dict[str, int] = {}
    make = _steppers.NumbaStepper.__init__

    def init(self, data2, *a, **kw):
        make(self, data2, *a, **kw)
        if dense:
            self.buf = _render_grad.SparseGrad(*data2.shape, data2.dtype, capacity=data2.shape[0])
            self.buf.grad3.fill(0.0)
        sizes.update(values=data2.nbytes, moments=sum(m.nbytes for m in (self.m1, self.m2)
                                                      if m is not None),
                     slabs=self.buf.nbytes)

    _steppers.NumbaStepper.__init__ = init
    make_loop = _loop.FineTuneLoop.__init__

    def init_loop(self, stepper, train, val, *a, **kw):
        sizes.update(train_images=train.images.nbytes,
                     val_images=0 if val is None else val.images.nbytes)
        make_loop(self, stepper, train, val, *a, **kw)

    _loop.FineTuneLoop.__init__ = init_loop
    peak, phase = [0, "start"], ["start"]

    class Phase(logging.Handler):          # the fine-tuner's last progress line
        def emit(self, record: logging.LogRecord) -> None:
            phase[0] = record.getMessage().strip()[:60]

    logging.getLogger("plenoctree").addHandler(Phase())
    logging.getLogger("plenoctree").setLevel(logging.INFO)

    def sample() -> None:
        while True:
            r = _rss_mb()
            if r > peak[0]:
                peak[0], peak[1] = r, phase[0]
            time.sleep(0.05)

    threading.Thread(target=sample, daemon=True).start()
    t0 = time.perf_counter()
    finetune(FinetuneConfig(tree=tree, data=data, out=out, downscale=downscale, epochs=epochs,
                            val_every=1, checkpoint_minutes=0, test_views=-1,
                            show_progress=False, verbose=True))
    time.sleep(0.1)
    print(json.dumps({"peak_rss_mb": peak[0], "peak_after": peak[1],
                      "seconds": time.perf_counter() - t0,
                      "array_mb": {k: round(v / 2**20) for k, v in sizes.items()}}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tree")
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--epochs", type=int, default=1)
    add_out(ap, "finetune_memory.json")
    ap.add_argument("--child", choices=("dense_slabs", "shipped"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    scratch = Path(args.out).with_suffix(".ft.npz")
    if args.child:
        child(args.tree, args.data, args.downscale, args.epochs, args.child == "dense_slabs",
              str(scratch))
        return 0
    rows = {mode: child_json([__file__, args.tree, "--data", args.data, "--downscale",
                              args.downscale, "--epochs", args.epochs, "--out", args.out,
                              "--child", mode])            # a process each: its own peak
            for mode in ("dense_slabs", "shipped")}
    for p in (scratch, scratch.with_name(scratch.stem + ".log.jsonl"),
              scratch.with_name(scratch.stem + ".curve.png")):
        p.unlink(missing_ok=True)
    print(markdown_table(["mode", "peak RSS MB", "s", "peak after", "arrays (MB)"],
                         [[mode, r["peak_rss_mb"], f"{r['seconds']:.1f}", r["peak_after"],
                           r["array_mb"]] for mode, r in rows.items()]))
    out = write_json(args.out, {"benchmark": "finetune_memory", "machine": machine_info(),
                                "tree": args.tree, "epochs": args.epochs, "results": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
