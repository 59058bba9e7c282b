"""Is the CPU's training unchanged, bit for bit? Hashes of a seeded short training.

Trains the test suite's small scene (``tests/nerf_fixtures.py``: a 24x24 procedural dataset,
the cpu preset shrunk by ``tiny_cpu_config``) for ``--steps`` steps, once with the cpu preset
(marching waves) and once with the fixed-shape step, and prints the SHA-256 of the trained
parameters (their bytes, in order). The same hashes from two revisions mean the change left
the CPU's training bit for bit as it was; run it from each::

    python benchmarks/train_hash.py                               # this checkout
    git worktree add /tmp/old REV
    PYTHONPATH=/tmp/old/src python benchmarks/train_hash.py --out /tmp/old.json

Writes ``benchmarks/results/train_hash.json`` (``--out``) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
from pathlib import Path

from _bench import REPO, add_out, machine_info, markdown_table, write_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40, help="training steps of each run")
    add_out(ap, "train_hash.json")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO / "tests"))
    from nerf_fixtures import tiny_cpu_config, tiny_dataset

    import plenoctree
    from plenoctree.nerf import train

    rows, out = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        data = tiny_dataset(Path(tmp) / "data")
        for name, fixed in (("cpu preset", False), ("fixed step", True)):
            cfg = tiny_cpu_config(data, Path(tmp) / name.replace(" ", "_"), steps=args.steps)
            cfg.fixed_step, cfg.val_views, cfg.amp = fixed, 0, "off"
            res = train(cfg, quiet=True)
            h = hashlib.sha256()
            for p in res.model.parameters():
                h.update(p.detach().cpu().numpy().tobytes())
            out[name] = h.hexdigest()
            rows.append([name, args.steps, h.hexdigest()[:16]])
    print(f"package: {Path(plenoctree.__file__).parent}")
    print(markdown_table(["training", "steps", "SHA-256 of the parameters (first 16)"], rows))
    write_json(args.out, {"benchmark": "train_hash", "machine": machine_info(),
                          "args": vars(args), "package": str(Path(plenoctree.__file__).parent),
                          "hashes": out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
