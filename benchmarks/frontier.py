"""Time against quality: the whole chain at several NeRF-SH budgets (issue 49's frontier).

For each budget B (minutes) one child process, the command a user types:

    plenoctree run <source> --out WORK/B --train.minutes B --video-frames 0 [flags after --]

with <source> ``--images REAL/flower/images_8`` (``--scene flower``: COLMAP poses by
``process``, then the chain) or ``--data nerf_synthetic/lego --downscale 2`` (``--scene lego``:
400²: the compressed tree scored on all 200 test views by ``run``'s default ``--eval-views 0``,
the trees before it on 25, ``--stage-eval-views``). It measures the wall
time of the whole command, polls the run's newest tree (:func:`plenoctree.live.newest_tree`)
once a second for when the first preview appeared and the gaps between previews, and reads the
run's ``summary.json`` for the PSNR of each stage (NeRF-SH, raw, refined, fine-tuned,
compressed), the leaves and the fine-tuning seconds. The budgets run one after the other; run
nothing else on the machine meanwhile (the figure is a wall time).

    python benchmarks/frontier.py --scene flower --budgets 2 20 --work /tmp/frontier/flower
    python benchmarks/frontier.py --scene lego --budgets 2 5 20 --work /tmp/frontier/lego
    python benchmarks/frontier.py --scene lego --budgets 10 -- --eval-views 5   # flags for run
    python benchmarks/frontier.py --plot docs/frontier.png --plot-from \\
        benchmarks/frontier_points/flower.json benchmarks/frontier_points/lego.json \\
        benchmarks/frontier_points/earlier.json benchmarks/frontier_points/flower_decay.json \\
        benchmarks/frontier_points/lego_decay.json

(``benchmarks/frontier_points/``: the docs' points, kept in the repository; a new run writes
``benchmarks/results/frontier_<scene>.json``, to be copied there with the docs' table.)

How long: the sum of the chains, one after the other: on the 2-core CPU flower took 40 min at
B = 2 (a foggy NeRF-SH: 23 M leaves, 21 min of fine-tuning), 17-18 min at 5 and 10, 31 min at
20; lego 400² ~11 min after training at B = 10. A budget whose WORK/B holds this script's
``frontier.json`` is not run again (delete the folder to rerun it).

``--plot FILE.png`` draws the compressed PSNR against wall minutes, one line per scene of the
``--plot-from`` files (this script's JSON). A file with ``"earlier": true`` at its top holds
points from earlier runs, written by hand from docs/capture_records.md's tables (``rows`` with
``scene``, ``budget_min``, ``compressed``, ``wall_min``): drawn as open markers.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _bench import (CACHE, add_data_root, add_out, data_path, fmt, machine_info, machine_line,
                    markdown_table, write_json)

STAGES = {"NeRF-SH": "nerf", "PlenOctree": "raw", "PlenOctree refined": "refined",
          "PlenOctree fine-tuned": "finetuned", "compressed": "compressed"}
"""``summary.json`` stage name -> the row's key."""
RESULT = "frontier.json"
"""What this script keeps in each run folder (the measurement of that run)."""


def source_flags(scene: str, root: str | None) -> list[str]:
    """The ``run`` flags that name the scene's input."""
    if scene == "flower":
        return ["--images", str(data_path(root, "real", "flower", "images_8"))]
    return ["--data", str(data_path(root, "nerf_synthetic", "lego")), "--downscale", "2"]


def run_command(src: list[str], out: Path, budget: float, extra: list[str]) -> list[str]:
    """The ``plenoctree run`` command line of one budget."""
    return [sys.executable, "-m", "plenoctree", "run", *src, "--out", str(out),
            "--train.minutes", f"{budget:g}", "--video-frames", "0", *extra]


def watch(cmd: list[str], out: Path) -> dict:
    """Run ``cmd``, polling ``newest_tree(out)`` once a second: wall seconds, return code and
    the seconds (from the start) at which each new preview (a new tree or a rewritten one)
    appeared."""
    from plenoctree.live import newest_tree

    seen, previews = None, []
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    while proc.poll() is None:
        time.sleep(1.0)
        try:
            tree = newest_tree(out)
            key = None if tree is None else (str(tree), tree.stat().st_mtime_ns)
        except (OSError, ValueError):
            continue
        if key is not None and key != seen:
            seen = key
            previews.append({"s": round(time.perf_counter() - t0, 1),
                             "tree": str(Path(key[0]).relative_to(out))})
    return {"wall_s": time.perf_counter() - t0, "returncode": proc.returncode,
            "previews": previews}


def row_of(budget: float, measured: dict, summary: dict) -> dict:
    """One row of the table: PSNR per stage, leaves, fine-tuning and wall seconds, previews."""
    rows = {r["stage"]: r for r in summary["rows"]}
    row = {"budget_min": budget, "wall_min": measured["wall_s"] / 60,
           "wall_s": measured["wall_s"], "previews": measured["previews"],
           "first_preview_s": measured["previews"][0]["s"] if measured["previews"] else None,
           "finetune_s": summary["times_s"].get("finetune"), "times_s": summary["times_s"],
           "total_s": summary["total_s"], "command": measured["command"],
           "load_before": measured.get("load_before")}
    for stage, key in STAGES.items():
        r = rows.get(stage, {})
        row[key] = r.get("psnr")
        row[f"{key}_views"] = r.get("views")
    row["leaves"] = rows.get("PlenOctree fine-tuned", {}).get("leaves")
    return row


def run_budget(budget: float, src: list[str], work: Path, extra: list[str]) -> dict:
    """Run one budget (unless WORK/B/frontier.json exists) and return its row."""
    out = work / f"{budget:g}"
    done = out / RESULT
    if not done.is_file():
        if out.exists():
            print(f"note: {out} exists: the run resumes, its wall time is not the chain's",
                  flush=True)
        cmd = run_command(src, out, budget, extra)
        print("$ " + " ".join(cmd), flush=True)
        load = os.getloadavg()
        measured = {**watch(cmd, out), "command": " ".join(cmd), "load_before": list(load)}
        if measured["returncode"] != 0:
            raise SystemExit(f"the chain failed (its message is above): {' '.join(cmd)}")
        write_json(done, measured)
    measured = json.loads(done.read_text())
    return row_of(budget, measured, json.loads((out / "summary.json").read_text()))


def gaps(previews: list[dict]) -> str:
    """"first s, then gap–gap s (training); trees at s, s" of the previews' times: the
    training's previews (``nerf/preview.npz``) apart from the stages' trees."""
    if not previews:
        return "–"
    train = [p["s"] for p in previews if p["tree"].startswith("nerf/")]
    trees = [f"{p['s']:.0f}" for p in previews if p["tree"].endswith(".npz")
             and not p["tree"].startswith("nerf/")]
    d = [b - a for a, b in zip(train, train[1:])]
    text = f"{train[0]:.0f} s" if train else "–"
    if d:
        text += f", then {min(d):.0f}" + (f"–{max(d):.0f}" if max(d) - min(d) >= 1 else "") + \
            " s"
    return text + " (training); trees at " + ", ".join(trees) + " s" if trees else text


def table(rows: list[dict]) -> str:
    """The markdown table of the budgets (PSNR in dB on the views the views column names)."""
    header = ["budget (min)", "NeRF-SH dB", "raw", "refined", "fine-tuned", "compressed",
              "test views", "leaves", "fine-tuning s", "wall min", "first preview, then every"]
    out = []
    for r in rows:
        out.append([f"{r['budget_min']:g}", fmt(r["nerf"], ".2f"), fmt(r["raw"], ".2f"),
                    fmt(r["refined"], ".2f"), fmt(r["finetuned"], ".2f"),
                    fmt(r["compressed"], ".2f"),
                    f"{fmt(r['compressed_views'], 'd')} (NeRF-SH {fmt(r['nerf_views'], 'd')})",
                    fmt(None if r["leaves"] is None else r["leaves"] / 1e6, ".2f") + " M",
                    fmt(r["finetune_s"], ".0f"), f"{r['wall_min']:.1f}",
                    gaps(r["previews"])])
    return markdown_table(header, out)


def plot(path: str, files: list[str]) -> bool:
    """Compressed PSNR against wall minutes, one line per scene joining its budgets in order;
    earlier runs as open markers.
    False (nothing written) without matplotlib."""
    from plenoctree._util import atomic_write
    from plenoctree.plots import _pyplot

    plt = _pyplot()
    if plt is None:
        print("no matplotlib: no plot (pip install matplotlib)")
        return False
    points: dict[str, list[tuple[float, float, float, bool]]] = {}
    for f in files:
        d = json.loads(Path(f).read_text())
        for r in (r for r in d["rows"] if r.get("compressed") is not None):
            scene = r.get("scene", d.get("scene"))
            points.setdefault(scene, []).append(
                (r["wall_min"], r["compressed"], r["budget_min"], bool(d.get("earlier"))))
    fig, ax = plt.subplots(figsize=(7.0, 4.4), dpi=110)
    for i, (scene, pts) in enumerate(sorted(points.items())):
        pts.sort(key=lambda p: p[2])          # in budget order: the path the budget walks
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "-", color=f"C{i}", alpha=0.6,
                label=scene)
        for wall, psnr, budget, earlier in pts:
            ax.scatter([wall], [psnr], s=50, zorder=3, color=f"C{i}",
                       facecolors="none" if earlier else f"C{i}")
            ax.annotate(f"{budget:g} min", (wall, psnr), textcoords="offset points",
                        xytext=(5, -11), fontsize=8, color=f"C{i}")
    ax.scatter([], [], s=50, facecolors="none", color="gray", label="earlier runs")
    ax.scatter([], [], s=50, color="gray", label="this benchmark")
    ax.set_xlabel("wall time of the whole chain (min)")
    ax.set_ylabel("compressed tree PSNR (dB)")
    ax.set_title("NeRF-SH budget against quality (labels: training minutes)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return True


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=("flower", "lego"), help="flower's photos or lego 400²")
    ap.add_argument("--budgets", type=float, nargs="+", default=[2, 5, 10, 20, 30],
                    help="NeRF-SH budgets in minutes, run one after the other")
    ap.add_argument("--work", default=None, help="folder of the runs (default "
                    "benchmarks/results/cache/frontier/<scene>; a finished run is kept)")
    ap.add_argument("--plot", default=None, help="draw the --plot-from files to this PNG")
    ap.add_argument("--plot-from", nargs="+", default=[], help="JSON files of this script")
    add_data_root(ap)
    add_out(ap, "frontier_{scene}.json")
    args = ap.parse_args(argv)
    if args.scene:
        src = source_flags(args.scene, args.data_root)
        work = Path(args.work or CACHE / "frontier" / args.scene)
        load_before = os.getloadavg()
        rows = [run_budget(b, src, work, extra) for b in args.budgets]
        for r in rows:
            r["scene"] = args.scene
        print(table(rows))
        machine = machine_info(load_before)
        print(machine_line(machine) + " (the load before each run: its row's load_before)")
        path = write_json(args.out.format(scene=args.scene), {
            "benchmark": "frontier", "scene": args.scene, "extra_flags": extra,
            "rows": rows, "machine": machine})
        print(f"wrote {path}")
    if args.plot:
        if plot(args.plot, args.plot_from):
            print(f"wrote {args.plot}")
    elif not args.scene:
        ap.error("give --scene (runs) or --plot (a plot), or both")
    return 0


if __name__ == "__main__":
    sys.exit(main())
