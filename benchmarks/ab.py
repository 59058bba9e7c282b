"""Old code against new: one benchmark run under two revisions, alternately, in one table.

Usage::

    python benchmarks/ab.py --rev REV [--rev2 REV2] [--alternate N] -- render_speed.py --tree T ...

Side A is ``--rev``, checked out as a temporary ``git worktree`` (in a temporary folder under
``--tmp``, default ``benchmarks/results/``, removed afterwards, also on Ctrl-C); side B is ``--rev2`` the same
way, or by default this checkout as it is (uncommitted changes included). The benchmark script
(a path relative to ``benchmarks/``) is taken from each side's own tree and run with
``PYTHONPATH=<that tree>/src``, so each side runs its own package; ``--same-script`` runs this
checkout's script on both (for a revision older than the script). Each run gets ``--out FILE``
and writes its JSON there (every benchmark takes ``--out``). The sides alternate ``N`` rounds,
the order flipping every round (A B, B A, ...), so that a drift of the machine's load hits both
alike. Both sides share this checkout's ``benchmarks/results/cache`` (the same extracted trees)
and the data root (``--data-root``, passed on as ``$PLENOCTREE_DATA``).

The table: every number in the JSONs (a dotted path: ``results.numba.400x400.fps``) that is not
machine information and is not the same in every run, with each side's median and range over
its runs and the ratio of the medians B / A; ``--metrics REGEX`` keeps only the matching paths.
Written as JSON to ``--out`` (default ``benchmarks/results/ab_<script>.json``) with every run's
JSON. These subprocesses are the comparison itself: each side must import its own package.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Iterator, NamedTuple, Sequence

from _bench import CACHE, DATA_ENV, REPO, RESULTS, add_data_root, data_root, markdown_table, \
    write_json

SKIP = re.compile(r"^(machine|args|settings)(\.|$)")
"""JSON paths that describe the run, not a measurement."""


class Side(NamedTuple):
    """One side of the comparison: its label, the revision asked for, its commit and the tree
    its package and script come from."""

    key: str
    rev: str
    commit: str
    root: Path


def git(*args: str) -> str:
    """``git -C REPO ARGS``'s output (stripped); raises ``CalledProcessError``."""
    return subprocess.run(["git", "-C", str(REPO), *args], check=True, capture_output=True,
                          text=True).stdout.strip()


def commit_of(rev: str) -> str:
    """The full commit id of ``rev``; a SystemExit naming it when git does not know it."""
    try:
        return git("rev-parse", "--verify", f"{rev}^{{commit}}")
    except subprocess.CalledProcessError:
        raise SystemExit(f"ab.py: {rev!r} is not a revision of {REPO}") from None


def worktree(stack: ExitStack, key: str, rev: str, folder: Path) -> Side:
    """A detached worktree of ``rev`` in ``folder / key``, removed when ``stack`` closes, with
    this checkout's benchmark cache (when there is one) linked in."""
    commit = commit_of(rev)
    root = folder / key
    git("worktree", "add", "--detach", "--quiet", str(root), commit)
    stack.callback(remove_worktree, root)
    if CACHE.is_dir():
        (root / "benchmarks" / "results").mkdir(parents=True, exist_ok=True)
        (root / "benchmarks" / "results" / "cache").symlink_to(CACHE, target_is_directory=True)
    return Side(key, rev, commit, root)


def remove_worktree(root: Path) -> None:
    """Unlink the cache link (never its target), then ``git worktree remove --force``."""
    link = root / "benchmarks" / "results" / "cache"
    if link.is_symlink():
        link.unlink()
    try:
        git("worktree", "remove", "--force", str(root))
    except subprocess.CalledProcessError:
        shutil.rmtree(root, ignore_errors=True)
        git("worktree", "prune")


def this_checkout() -> Side:
    """Side B by default: this checkout as it is."""
    dirty = " + uncommitted changes" if git("status", "--porcelain", "--untracked-files=no") \
        else ""
    return Side("B", f"working tree (HEAD{dirty})", commit_of("HEAD"), REPO)


def script_path(side: Side, script: str, same_script: bool) -> Path:
    """The benchmark script of ``side`` (this checkout's with ``same_script``)."""
    rel = Path(script)
    if rel.parts and rel.parts[0] == "benchmarks":
        rel = rel.relative_to("benchmarks")
    path = (REPO if same_script else side.root) / "benchmarks" / rel
    if not path.is_file():
        raise SystemExit(f"ab.py: {path} not found (at {side.rev}; --same-script runs this "
                         "checkout's script on both sides)")
    return path


def run_once(side: Side, script: Path, args: Sequence[str], out: Path, log: Path) -> float:
    """One run of the benchmark on ``side``; returns its wall seconds. Its output goes to
    ``log``, whose tail is shown when it fails."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(side.root / "src"),
                                                    env.get("PYTHONPATH")) if p)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        res = subprocess.run([sys.executable, str(script), *args, "--out", str(out)], env=env,
                             stdout=f, stderr=subprocess.STDOUT, check=False)
    if res.returncode != 0 or not out.is_file():
        tail = "".join(log.read_text().splitlines(keepends=True)[-30:])
        raise SystemExit(f"ab.py: {script.name} failed on side {side.key} ({side.rev}), exit "
                         f"status {res.returncode}:\n{tail}")
    return time.perf_counter() - t0


def numbers(obj: Any, prefix: str = "") -> Iterator[tuple[str, float]]:
    """The numeric leaves of a JSON value as ``(dotted path, value)``, list items by their
    index (booleans left out)."""
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) \
        if isinstance(obj, list) else None
    if items is not None:
        for k, v in items:
            yield from numbers(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield prefix, float(obj)


def compare(runs: dict[str, list[dict]], keep: str | None) -> dict[str, dict]:
    """Per metric (see the module docstring): each side's values, median, min, max, and the
    ratio of the medians B / A (None when A's median is 0)."""
    flat = {k: [dict(numbers(r)) for r in rs] for k, rs in runs.items()}
    paths = [p for p in flat["A"][0] if not SKIP.match(p) and (keep is None or re.search(keep, p))
             and all(p in f for fs in flat.values() for f in fs)]
    out = {}
    for p in paths:
        vals = {k: [f[p] for f in fs] for k, fs in flat.items()}
        if len({v for vs in vals.values() for v in vs}) == 1:
            continue                                     # a setting, not a measurement
        row = {k: {"median": statistics.median(vs), "min": min(vs), "max": max(vs),
                   "values": vs} for k, vs in vals.items()}
        a = row["A"]["median"]
        row["ratio_b_over_a"] = row["B"]["median"] / a if a else None
        out[p] = row
    return out


def table(metrics: dict[str, dict]) -> str:
    """The markdown table of :func:`compare`'s result."""
    def side(r: dict) -> list[str]:
        return [f"{r['median']:.4g}", f"{r['min']:.4g}–{r['max']:.4g}"]

    return markdown_table(
        ["metric", "A median", "A range", "B median", "B range", "B / A"],
        [[p, *side(r["A"]), *side(r["B"]),
          "–" if r["ratio_b_over_a"] is None else f"{r['ratio_b_over_a']:.3f}"]
         for p, r in metrics.items()])


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    """ab.py's own options (before ``--``) and the benchmark command (after it)."""
    cut = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 usage="%(prog)s --rev REV [options] -- SCRIPT.py [ARGS...]")
    ap.add_argument("--rev", required=True, help="side A: the revision to compare against")
    ap.add_argument("--rev2", default=None,
                    help="side B: a second revision (default: this checkout as it is)")
    ap.add_argument("--alternate", type=int, default=3, help="runs of each side")
    ap.add_argument("--same-script", action="store_true",
                    help="run this checkout's script on both sides (only the package differs)")
    ap.add_argument("--metrics", default=None, help="keep the JSON paths matching this regex")
    ap.add_argument("--tmp", default=str(RESULTS),
                    help="where the temporary folder of the worktrees and runs goes (default "
                         "benchmarks/results: inside the checkout, so that an old revision's "
                         "scripts find the shared data above it as they did)")
    add_data_root(ap)
    ap.add_argument("--out", default=None,
                    help="JSON of the comparison (default benchmarks/results/ab_<script>.json)")
    args = ap.parse_args(argv[:cut])
    bench = argv[cut + 1:]
    if not bench:
        ap.error("no benchmark command: -- SCRIPT.py [ARGS...] comes last")
    if "--out" in bench:
        ap.error("the benchmark's --out is ab.py's to set (a file per run)")
    if args.alternate < 1:
        ap.error("--alternate must be >= 1")
    return args, bench


def run_sides(args: argparse.Namespace, bench: list[str], stack: ExitStack, folder: Path
              ) -> tuple[list[Side], dict[str, list[dict]], dict[str, list[float]]]:
    """Check the sides out and run the benchmark alternately; each run's JSON and seconds."""
    import json

    sides = [worktree(stack, "A", args.rev, folder),
             worktree(stack, "B", args.rev2, folder) if args.rev2 else this_checkout()]
    scripts = {s.key: script_path(s, bench[0], args.same_script) for s in sides}
    runs: dict[str, list[dict]] = {s.key: [] for s in sides}
    seconds: dict[str, list[float]] = {s.key: [] for s in sides}
    for i in range(args.alternate):
        for s in (sides if i % 2 == 0 else sides[::-1]):
            out = folder / f"{s.key}{i}.json"
            sec = run_once(s, scripts[s.key], bench[1:], out, folder / f"{s.key}{i}.log")
            runs[s.key].append(json.loads(out.read_text()))
            seconds[s.key].append(sec)
            print(f"[ab] round {i + 1}/{args.alternate}: {s.key} ({s.commit[:9]}) {sec:.1f} s",
                  file=sys.stderr, flush=True)
    return sides, runs, seconds


def main(argv: list[str] | None = None) -> int:
    args, bench = parse_args(sys.argv[1:] if argv is None else argv)
    if shutil.which("git") is None:
        raise SystemExit("ab.py needs git")
    root = data_root(args.data_root)
    if root is not None:
        os.environ[DATA_ENV] = str(root)          # the same data for both sides
    signal.signal(signal.SIGTERM, signal.default_int_handler)   # clean up as on Ctrl-C
    Path(args.tmp).mkdir(parents=True, exist_ok=True)
    with ExitStack() as stack:
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="ab-",
                                                                      dir=args.tmp)))
        sides, runs, seconds = run_sides(args, bench, stack, folder)
    metrics = compare(runs, args.metrics)
    one_side = {k: sorted({p for r in rs for p, _ in numbers(r) if not SKIP.match(p)}
                          - {p for r in runs[o] for p, _ in numbers(r)})
                for k, rs in runs.items() for o in runs if o != k}
    text = table(metrics)
    print(f"\nA = {sides[0].rev} ({sides[0].commit[:9]}), B = {sides[1].rev} "
          f"({sides[1].commit[:9]}); {' '.join(bench)}; {args.alternate} runs each, "
          "alternating\n")
    print(text)
    for k, paths in one_side.items():
        if paths:
            print(f"only on side {k} (not compared): {', '.join(paths[:8])}"
                  + (f" and {len(paths) - 8} more" if len(paths) > 8 else ""))
    out = write_json(args.out or RESULTS / f"ab_{Path(bench[0]).stem}.json", {
        "benchmark": "ab", "command": bench, "alternate": args.alternate,
        "same_script": args.same_script,
        "sides": {s.key: {"rev": s.rev, "commit": s.commit} for s in sides},
        "seconds": seconds, "metrics": metrics, "only_on_one_side": one_side, "table": text,
        "runs": runs})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
