"""Peak memory of ``plenoctree finetune`` on a real tree, with and without releasing the
optimiser state before the final save.

Usage: ``python benchmarks/finetune_memory.py TREE.npz --data DATASET [--downscale 2]
[--epochs 1] [--out benchmarks/results/finetune_memory.json]``

Each mode runs in its own subprocess (so one's pages do not count for the other): ``release``
is ``finetune`` as shipped (the Adam moments and gradient slabs are dropped once training is
over, :meth:`NumbaStepper.release`); ``keep`` is the same run with ``release`` made a no-op (the
behaviour before). A thread samples the process RSS every 50 ms and notes the last line
``finetune`` printed, so the table says in which phase the peak fell. Checkpoints are written
at every validation (``checkpoint_minutes=0``), as a long run does. Prints a table, writes JSON.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

from _trees import machine_info


def _rss_mb() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) // 1024
    return 0


def child(tree: str, data: str, downscale: int, epochs: int, keep: bool, out: str) -> None:
    """One fine-tuning run; prints a JSON line with its peak RSS and the phase it fell in."""
    from plenoctree.optim import _steppers
    from plenoctree.optim.finetune import FinetuneConfig, finetune

    if keep:
        _steppers.NumbaStepper.release = lambda self: None
    peak, phase = [0, "start"], ["start"]

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
                            show_progress=False, verbose=True),
             log_fn=lambda s: phase.__setitem__(0, s.strip()[:60]))
    time.sleep(0.1)
    print(json.dumps({"peak_rss_mb": peak[0], "peak_after": peak[1],
                      "seconds": time.perf_counter() - t0}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tree")
    ap.add_argument("--data", required=True)
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--epochs", type=int, default=1)
    ap.add_argument("--out", default="benchmarks/results/finetune_memory.json")
    ap.add_argument("--child", choices=("keep", "release"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    scratch = Path(args.out).with_suffix(".ft.npz")
    if args.child:
        child(args.tree, args.data, args.downscale, args.epochs, args.child == "keep",
              str(scratch))
        return
    rows = {}
    for mode in ("keep", "release"):
        res = subprocess.run([sys.executable, __file__, args.tree, "--data", args.data,
                              "--downscale", str(args.downscale), "--epochs", str(args.epochs),
                              "--out", args.out, "--child", mode],
                             capture_output=True, text=True, check=True)
        rows[mode] = json.loads(res.stdout.strip().splitlines()[-1])
    for p in (scratch, scratch.with_name(scratch.stem + ".log.jsonl"),
              scratch.with_name(scratch.stem + ".curve.png")):
        p.unlink(missing_ok=True)
    print(f"{'mode':<8} {'peak RSS MB':>12} {'s':>7}  peak after")
    for mode, r in rows.items():
        print(f"{mode:<8} {r['peak_rss_mb']:>12} {r['seconds']:>7.1f}  {r['peak_after']}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine_info(), "tree": args.tree,
                               "epochs": args.epochs, "results": rows}, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
