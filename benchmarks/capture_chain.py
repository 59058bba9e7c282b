"""The whole chain on a real capture, from its published poses and from its photos.

Two chains, each the command a user types (a child process), with ``run``'s defaults:

* ``published``: ``plenoctree run --data REAL/<capture> --out WORK/<capture>_published``
  (flower: LLFF's ``poses_bounds.npy``; fox: instant-ngp's ``transforms.json``);
* ``process``: ``plenoctree run --images REAL/<capture>/<photos> --out WORK/<capture>_process``
  (COLMAP poses by ``process``, then the same chain).

Both hold out every 8th photo by name (``process`` names the same photos in its split lists
for 360° captures; flower's 34 photos all register, so its LLFF split is the same too). The
table gives, per stage, the held-out PSNR / SSIM, the frame rate measured while scoring, the
leaves and the stage's wall time, from each run's ``summary.json`` (times measured by the
pipeline itself: a chain run by hand into WORK counts the same), then the differences.

    python benchmarks/capture_chain.py --real flower              # both chains, then the table
    python benchmarks/capture_chain.py --real flower --only process
    python benchmarks/capture_chain.py --real fox -- --train.minutes 15   # flags for both runs

A finished chain is not run again (delete its folder to rerun it); one stopped part way
resumes where it stopped, and its stage times are then those of the resumed run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from _bench import (CACHE, add_data_root, add_out, data_path, fmt, machine_info, machine_line,
                    markdown_table, write_json)

CAPTURES = {"flower": "images_8", "fox": "images"}
"""Capture name -> the folder of its photos (the input of ``process``)."""
CHAINS = ("published", "process")
PROCESS_ROW = "process (COLMAP)"


def chain_command(capture: Path, photos: str, kind: str, out: Path, extra: list[str]
                  ) -> list[str]:
    """The ``plenoctree run`` command line of chain ``kind``."""
    src = ["--data", str(capture)] if kind == "published" else \
        ["--images", str(capture / photos)]
    return [sys.executable, "-m", "plenoctree", "run", *src, "--out", str(out), *extra]


def run_chain(cmd: list[str], out: Path) -> dict:
    """Run ``cmd`` unless ``out/summary.json`` exists; returns that summary."""
    summary = out / "summary.json"
    if not summary.is_file():
        print("$ " + " ".join(cmd), flush=True)
        if subprocess.run(cmd).returncode != 0:
            raise SystemExit(f"the chain failed (its message is above): {' '.join(cmd)}")
    return json.loads(summary.read_text())


def stage_rows(s: dict) -> dict[str, dict]:
    """``stage name -> row`` of a run summary (the process stage from ``times_s``)."""
    rows = {r["stage"]: r for r in s["rows"]}
    if s["times_s"].get("process"):
        rows = {PROCESS_ROW: {"seconds": s["times_s"]["process"],
                                     "peak_rss_mb": s["peak_rss_mb"].get("process")}, **rows}
    return rows


def table(res: dict[str, dict]) -> str:
    """Markdown table of both chains' stages, side by side, with the PSNR difference."""
    names = list(res)
    rows_of = {k: stage_rows(v) for k, v in res.items()}
    stages = sorted(dict.fromkeys(st for k in names for st in rows_of[k]),
                    key=lambda st: st != PROCESS_ROW)        # (a stable sort)
    header = ["stage"] + [f"{k}: {c}" for k in names for c in ("PSNR", "SSIM", "FPS", "leaves",
                                                                 "s")]
    if len(names) == 2:
        header.append("PSNR diff")
    out = []
    for st in stages:
        cells = [st]
        for k in names:
            r = rows_of[k].get(st, {})
            cells += [fmt(r.get("psnr"), ".2f"), fmt(r.get("ssim"), ".3f"),
                      fmt(r.get("fps"), ".1f"), fmt(r.get("leaves"), ",d"),
                      fmt(r.get("seconds"), ".0f")]
        if len(names) == 2:
            a, b = (rows_of[k].get(st, {}).get("psnr") for k in names)
            cells.append(fmt(None if a is None or b is None else b - a, "+.2f"))
        out.append(cells)
    total = ["total (wall, min)"]
    for k in names:
        total += ["", "", "", "", fmt(res[k]["total_s"] / 60, ".1f")]
    return markdown_table(header, out + [total + ([""] if len(names) == 2 else [])])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real", choices=sorted(CAPTURES), required=True, help="the capture")
    ap.add_argument("--only", choices=CHAINS, default=None, help="run one chain only")
    ap.add_argument("--work", default=str(CACHE / "capture_chain"),
                    help="folder of the chains (a finished chain is not run again)")
    add_data_root(ap)
    add_out(ap, "capture_chain_{real}.json")
    args = ap.parse_args(argv)
    capture = data_path(args.data_root, "real", args.real)
    work = Path(args.work)
    load_before = os.getloadavg()
    res = {}
    for kind in CHAINS if args.only is None else (args.only,):
        out = work / f"{args.real}_{kind}"
        res[kind] = run_chain(chain_command(capture, CAPTURES[args.real], kind, out, extra), out)
    print(table(res))
    machine = machine_info(load_before)
    print(machine_line(machine) + " (the chains' own times: each run's summary.json)")
    path = write_json(args.out.format(real=args.real), {
        "benchmark": "capture_chain", "capture": args.real, "extra_flags": extra,
        "chains": {k: {"rows": stage_rows(v), "total_s": v["total_s"],
                       "peak_rss_mb": max(x for x in v["peak_rss_mb"].values() if x),
                       "config": v["config"]} for k, v in res.items()},
        "machine": machine})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
