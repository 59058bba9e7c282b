"""GPU vs CPU, the paper-comparable figures: render FPS at 800², fine-tune rays/s, NeRF-SH training
samples/s, extraction time — each GPU figure beside the CPU figure of the same run.

Method (all on the lego scene of ``--data``; ``--data`` and ``--run`` default to
``nerf_synthetic/lego`` and ``runs/lego_cpu_400`` of the data root, ``--data-root``):

- **render**: the tree (``--tree``; default: extracted once from ``--run`` at ``--grid``³ into
  ``benchmarks/results/cache/<run>_<grid>.npz``) is rendered on ``--views`` test cameras at full
  size (800²).
  Rays are generated (and, for the GPU, moved to it) before timing; the tree is moved to the GPU
  once. One warm-up render (Triton / numba compilation), then ``--repeats`` passes; median ms per
  frame. The GPU render is checked against the CPU render (max |Δ rgb|).
- **fine-tune**: ``--ft-steps`` SGD steps of the fine-tuner's stepper (numba on the CPU, the Triton
  forward + analytic backward on the GPU) on random training pixels at 400²; batch
  ``--ft-batch`` rays (CPU: 65536); rays/s over the timed steps after 2 warm-up steps. Rays
  are copied to the device inside each step (the stepper's host API). **fine-tune stage**: one
  epoch of ``FineTuneLoop`` (as ``plenoctree finetune`` runs it: Adam, ``--ft-stage-batch``
  rays a step in 4×4 tiles, no validation) on every training pixel at 400²; on the GPU the
  device-resident loop (photos uploaded once, tiles drawn and rays made on the device, the
  step's figures read every 32 steps); rays/s of the epoch's steps (after a warm-up epoch
  of ``--ft-warm-views`` views: Triton compilation).
- **train**: the ``cpu`` NeRF-SH preset on lego at 400² for ``--train-steps`` steps (CPU:
  ``--cpu-train-steps``); the trainer's mean samples/s (its log rows).
- **train_gpu**: the same with the ``gpu`` preset (the fixed-shape step: rays, march, early
  termination, the fused network and compositing in a fixed number of launches, 2^18
  samples a step; ``nerf/fixed.py``).
- **train_gpu_graph** (CUDA only): ``train_gpu`` with ``--cuda-graph`` (each ray count's step
  replayed from a CUDA graph, ``nerf/graph.py``); its ratio to ``train_gpu`` decides whether
  the ``gpu`` preset turns it on. An error is recorded in the JSON, not raised (the capture has
  never run on a GPU before).
- **extract**: ``plenoctree extract`` of ``--run`` at ``--grid``³ without evaluation; seconds.

Without a CUDA device the script says so and stops (exit status 0), writing a JSON whose
``gpu`` entry gives the reason; ``--cpu-only`` measures the CPU column alone. The JSON records
the machine, the load average, torch/triton versions and the ratios.

Usage (a GPU machine; a few minutes)::

    .venv/bin/python benchmarks/gpu_bench.py                       # writes results/gpu_bench.json
    .venv/bin/python benchmarks/gpu_bench.py --skip extract --views 3

On a machine whose system python already has a CUDA torch with Triton (no install step), from
the repository root: ``PYTHONPATH=src python3 benchmarks/gpu_bench.py --data DATA --run RUN``;
the kernels' tests then run compiled on the GPU with
``PYTHONPATH=src python3 -m pytest tests/test_triton_kernels.py tests/test_render.py -q``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from _bench import CACHE, Timing, add_data_root, add_out, data_path, machine_info, \
    markdown_table, write_json

STAGES = ("render", "finetune", "train", "train_gpu", "train_gpu_graph", "extract")


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _tree(args: argparse.Namespace):
    """The tree of ``--tree``, else the one extracted once from ``--run`` into the cache."""
    from plenoctree.octree import load_tree

    path = Path(args.tree) if args.tree else CACHE / f"{Path(args.run).name}_{args.grid}.npz"
    if not path.is_file():
        from plenoctree.convert.extraction import ExtractConfig, extract

        print(f"[gpu_bench] extracting a tree from {args.run} -> {path}", flush=True)
        path.parent.mkdir(parents=True, exist_ok=True)
        extract(ExtractConfig(run_dir=str(args.run), data=str(args.data), out=str(path),
                              grid=args.grid, eval=False, show_progress=False))
    return load_tree(path), str(path)


def bench_render(tree, data, dev: torch.device, repeats: int) -> dict:
    from plenoctree.render import RenderOptions, render_rays, tree_to_device

    opts = RenderOptions(background=tuple(float(b) for b in data.background))
    rays = [data.cameras.rays(i) for i in range(len(data.cameras))]
    t = tree_to_device(tree, dev)
    if dev.type == "cuda":
        rays = [(torch.from_numpy(o).to(dev), torch.from_numpy(d).to(dev)) for o, d in rays]
    first = render_rays(t, *rays[0], opts)         # warm-up: compilation
    _sync(dev)
    timing = Timing()
    for _ in range(repeats):
        for o, d in rays:
            timing.call(lambda: (render_rays(t, o, d, opts), _sync(dev)))
    med = timing.median * 1e3
    return {"ms_per_frame": med, "ms_spread": timing.spread * 1e3, "fps": 1000.0 / med,
            "frames": len(timing.wall), "width": data.cameras.width,
            "height": data.cameras.height,
            "rgb_view0": first.rgb.detach().float().cpu().numpy()}


def bench_finetune(tree, train, dev: torch.device, batch: int, steps: int) -> dict:
    from plenoctree.optim._steppers import make_stepper
    from plenoctree.render import RenderOptions

    rng = np.random.default_rng(0)
    n, h, w = train.images.shape[:3]
    data2 = np.ascontiguousarray(tree.data, dtype=np.float32).reshape(-1, tree.data_dim).copy()
    opts = RenderOptions(background=tuple(float(b) for b in train.background))
    st = make_stepper("auto", data2, tree, opts, "sgd", None, device=str(dev))
    batches = []
    for _ in range(steps + 2):
        img, row = rng.integers(0, n, batch), rng.integers(0, h, batch)
        col = rng.integers(0, w, batch)
        o, d = train.cameras.pixel_rays(img, col, row)
        batches.append((np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32),
                        np.ascontiguousarray(train.images[img, row, col], np.float32)))
    scale = 1.0 / (3 * h * w)
    for b in batches[:2]:
        st.step(*b, scale)
    _sync(dev)
    t0 = time.perf_counter()
    for b in batches[2:]:
        st.step(*b, scale)
    _sync(dev)
    secs = time.perf_counter() - t0
    return {"backend": st.backend, "batch_rays": batch, "steps": steps, "seconds": secs,
            "rays_per_s": batch * steps / secs}


def bench_finetune_stage(tree, train, dev: torch.device, batch: int, warm_views: int) -> dict:
    """One epoch of the fine-tuning loop over every pixel of ``train`` (see the module doc)."""
    from plenoctree.optim._loop import FineTuneLoop, LoopOptions, ViewSet
    from plenoctree.optim.finetuning import _make_stepper
    from plenoctree.pipeline_config import FinetuneConfig

    views = ViewSet.from_dataset(train)
    warm = ViewSet.from_dataset(train, list(range(min(warm_views, len(views)))))
    cfg = FinetuneConfig(device=str(dev))
    res = {}
    for name, vs in (("warm", warm), ("epoch", views)):
        stepper, _ = _make_stepper(cfg, tree.copy(), tuple(float(b) for b in train.background))
        loop = FineTuneLoop(stepper, vs, None, LoopOptions(epochs=1, batch_rays=batch,
                                                           show_progress=False), {})
        t0 = time.perf_counter()
        _, state = loop.run()
        _sync(dev)
        res[name] = (time.perf_counter() - t0, state)
    secs, state = res["epoch"]
    return {"backend": stepper.backend, "batch_rays": batch, "rays": state.train_rays,
            "steps": state.steps, "seconds": secs, "step_seconds": state.train_seconds,
            "rays_per_s": state.train_rays / max(state.train_seconds, 1e-9)}


def bench_train(data_root: str, dev: torch.device, steps: int, scratch: Path,
                name: str = "cpu", graph: bool = False) -> dict:
    """The NeRF-SH preset ``name`` ("cpu": the marching waves; "gpu": the fixed-shape step
    with its fused kernels, 2^18 samples a step; ``graph``: replayed from CUDA graphs) for
    ``steps`` steps on lego at 400²."""
    from plenoctree.nerf.config import preset
    from plenoctree.nerf.trainer import train

    cfg = preset(name)
    cfg.cuda_graph = graph
    out = scratch / f"train_{name}{'_graph' if graph else ''}_{dev.type}"
    cfg.data, cfg.out, cfg.downscale, cfg.device = data_root, str(out), 2, str(dev)
    cfg.max_steps, cfg.minutes, cfg.val_views = steps, 0.0, 0
    cfg.log_every = max(1, steps // 10)
    cfg.ckpt_every_s, cfg.ckpt_every_steps = 0.0, 0
    if out.exists():
        import shutil

        shutil.rmtree(out)
    t0 = time.perf_counter()
    res = train(cfg, quiet=True)
    rows = res.log["train"][1:] or res.log["train"]      # the first window holds compilation
    import json

    graphs = json.loads((out / "summary.json").read_text()).get("cuda_graphs")
    return {"steps": res.step, "wall_s": time.perf_counter() - t0, "cuda_graphs": graphs,
            "samples_per_s": float(np.mean([r["samples_per_s"] for r in rows])),
            "rays_per_s": float(np.mean([r["rays_per_s"] for r in rows]))}


def bench_extract(run: str, data: str, dev: torch.device, grid: int, scratch: Path) -> dict:
    from plenoctree.convert.extraction import ExtractConfig, extract

    out = scratch / f"extract_{dev.type}.npz"
    t0 = time.perf_counter()
    res = extract(ExtractConfig(run_dir=run, data=data, out=str(out), grid=grid, eval=False,
                                device=str(dev), show_progress=False))
    return {"seconds": time.perf_counter() - t0, "grid": grid, "n_leaves": int(res.tree.n_leaves),
            "stages": res.stages}


def _table(results: dict) -> str:
    cpu, gpu = results.get("cpu", {}), results.get("gpu", {})
    rows = [("render FPS at 800²", "render", "fps", "{:.1f}"),
            ("fine-tune M rays/s", "finetune", "rays_per_s", "{:.2f}", 1e-6),
            ("fine-tune stage M rays/s", "finetune_stage", "rays_per_s", "{:.2f}", 1e-6),
            ("NeRF-SH train M samples/s", "train", "samples_per_s", "{:.2f}", 1e-6),
            ("NeRF-SH train, gpu preset, M samples/s", "train_gpu", "samples_per_s", "{:.2f}",
             1e-6),
            ("the same from CUDA graphs, M samples/s", "train_gpu_graph", "samples_per_s",
             "{:.2f}", 1e-6),
            ("extraction s", "extract", "seconds", "{:.1f}")]
    lines = []
    for name, stage, key, fmt, *mult in rows:
        m = mult[0] if mult else 1.0
        c = cpu.get(stage, {}).get(key)
        g = gpu.get(stage, {}).get(key) if isinstance(gpu, dict) else None
        ratio = "–"
        if c and g:
            ratio = f"{(c / g if key == 'seconds' else g / c):.1f}x"
        lines.append([name, fmt.format(c * m) if c else "–", fmt.format(g * m) if g else "–",
                      ratio])
    return markdown_table(["figure", "CPU", "GPU", "GPU / CPU"], lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None,
                    help="dataset (default: nerf_synthetic/lego of the data root)")
    ap.add_argument("--run", default=None,
                    help="trained NeRF-SH run (extraction, and the tree when none is given; "
                         "default: runs/lego_cpu_400 of the data root)")
    ap.add_argument("--tree", default=None, help="tree to render / fine-tune")
    ap.add_argument("--views", type=int, default=5, help="test views rendered at 800²")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ft-batch", type=int, default=1 << 20, help="GPU fine-tune batch (rays)")
    ap.add_argument("--ft-steps", type=int, default=10)
    ap.add_argument("--ft-stage-batch", type=int, default=1 << 16,
                    help="fine-tune stage: rays a step (plenoctree finetune's default)")
    ap.add_argument("--ft-warm-views", type=int, default=4,
                    help="fine-tune stage: views of the warm-up epoch")
    ap.add_argument("--train-steps", type=int, default=300)
    ap.add_argument("--cpu-train-steps", type=int, default=30)
    ap.add_argument("--grid", type=int, default=256)
    ap.add_argument("--skip", nargs="*", default=[], choices=STAGES)
    ap.add_argument("--cpu-only", action="store_true",
                    help="without a GPU: measure the CPU column anyway")
    ap.add_argument("--no-cpu", action="store_true", help="GPU column only")
    ap.add_argument("--scratch", default=None, help="folder for runs (default: temp)")
    add_data_root(ap)
    add_out(ap, "gpu_bench.json")
    args = ap.parse_args(argv)

    from plenoctree._triton import has_triton

    load_before = os.getloadavg()
    results: dict = {"benchmark": "gpu_bench", "args": vars(args)}
    have_gpu = torch.cuda.is_available()
    if not have_gpu:
        reason = "no CUDA device present: the GPU figures are still to be measured"
        print(f"[gpu_bench] {reason}", flush=True)
        results["gpu"] = {"skipped": reason}
        if not args.cpu_only:
            results["machine"] = machine_info(load_before)
            write_json(args.out, results)
            print(f"[gpu_bench] wrote {args.out} (pass --cpu-only to measure the CPU column)")
            return 0
    elif not has_triton():
        print("[gpu_bench] CUDA is present but triton is not installed: the GPU column uses "
              "the torch twins (pip install triton)", flush=True)
    args.data = args.data or str(data_path(args.data_root, "nerf_synthetic", "lego"))
    if "extract" not in args.skip or not args.tree:
        args.run = args.run or str(data_path(args.data_root, "runs", "lego_cpu_400"))
    for p in (args.data, args.run):
        if p is not None and not Path(p).exists():
            print(f"[gpu_bench] {p}: not found (pass --data / --run)", file=sys.stderr)
            return 2
    scratch = Path(args.scratch) if args.scratch else Path(tempfile.mkdtemp(prefix="gpu_bench_"))
    scratch.mkdir(parents=True, exist_ok=True)

    from plenoctree.datasets import load_dataset

    tree, tree_path = _tree(args)
    results["tree"] = {"path": tree_path, "n_leaves": int(tree.n_leaves),
                       "data_format": tree.data_format}
    need_views = "render" not in args.skip
    test = load_dataset(args.data, "test", limit=args.views) if need_views else None
    train_ds = load_dataset(args.data, "train", downscale=2) if "finetune" not in args.skip \
        else None
    devices = ([] if args.no_cpu or not (args.cpu_only or have_gpu) else [torch.device("cpu")])
    devices += [torch.device("cuda")] if have_gpu else []
    for dev in devices:
        col = "cpu" if dev.type == "cpu" else "gpu"
        res: dict = {}
        results[col] = res
        print(f"[gpu_bench] {col}: ...", flush=True)
        if "render" not in args.skip:
            res["render"] = bench_render(tree, test, dev, args.repeats)
            print(f"  render {res['render']['fps']:.1f} FPS", flush=True)
        if "finetune" not in args.skip:
            batch = args.ft_batch if dev.type == "cuda" else 1 << 16
            res["finetune"] = bench_finetune(tree, train_ds, dev, batch, args.ft_steps)
            print(f"  fine-tune {res['finetune']['rays_per_s'] / 1e6:.2f} M rays/s", flush=True)
            res["finetune_stage"] = bench_finetune_stage(tree, train_ds, dev,
                                                         args.ft_stage_batch, args.ft_warm_views)
            print(f"  fine-tune stage {res['finetune_stage']['rays_per_s'] / 1e6:.2f} M rays/s",
                  flush=True)
        if "train" not in args.skip:
            steps = args.train_steps if dev.type == "cuda" else args.cpu_train_steps
            res["train"] = bench_train(args.data, dev, steps, scratch)
            print(f"  train {res['train']['samples_per_s'] / 1e6:.2f} M samples/s", flush=True)
        if "train_gpu" not in args.skip:
            steps = args.train_steps if dev.type == "cuda" else args.cpu_train_steps
            res["train_gpu"] = bench_train(args.data, dev, steps, scratch, "gpu")
            print(f"  train (gpu preset) {res['train_gpu']['samples_per_s'] / 1e6:.2f} "
                  "M samples/s", flush=True)
        if "train_gpu_graph" not in args.skip and dev.type == "cuda":
            try:
                res["train_gpu_graph"] = bench_train(args.data, dev, args.train_steps, scratch,
                                                     "gpu", graph=True)
                print(f"  train (gpu preset, CUDA graphs) "
                      f"{res['train_gpu_graph']['samples_per_s'] / 1e6:.2f} M samples/s",
                      flush=True)
            except Exception as exc:         # recorded for the next session, not fatal
                res["train_gpu_graph"] = {"error": repr(exc)}
                print(f"  train (gpu preset, CUDA graphs) failed: {exc!r}", flush=True)
        if "extract" not in args.skip:
            res["extract"] = bench_extract(args.run, args.data, dev, args.grid, scratch)
            print(f"  extract {res['extract']['seconds']:.1f} s", flush=True)
    if "cpu" in results and isinstance(results.get("gpu"), dict) and \
            "render" in results["gpu"] and "render" in results["cpu"]:
        diff = np.abs(results["gpu"]["render"]["rgb_view0"] - results["cpu"]["render"]["rgb_view0"])
        results["gpu"]["render"]["max_abs_rgb_diff_vs_cpu"] = float(diff.max())
    for col in ("cpu", "gpu"):
        if isinstance(results.get(col), dict):
            results[col].get("render", {}).pop("rgb_view0", None)
    results["machine"] = machine_info(load_before)
    table = _table(results)
    results["table"] = table
    print(table)
    write_json(args.out, results)
    print(f"[gpu_bench] wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
