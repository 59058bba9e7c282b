"""Torch ops and host synchronisations per training step and per fine-tuning step (issue 38).

A GPU runs a step at its own speed only when the host never waits for it: every value the
host reads back (``.item()``, ``float(t)``, ``bool(t)``, ``.cpu()``, ``.numpy()``,
``.tolist()``), every op whose output shape depends on the data (``nonzero``, boolean-mask
indexing, ``unique``, ``bincount``, ``masked_select``) and every blocking host-to-device copy
stops the host until the device has caught up, and every op is one kernel launch the host
must issue. Both can be counted on a machine without a GPU, with CPU tensors:

- a ``TorchDispatchMode`` sees every aten op a step dispatches, forward and backward
  (``ops``; ``views`` of them only alias their input and launch nothing);
- syncs are counted by kind: ``item`` (``aten::_local_scalar_dense``, what ``.item()``,
  ``float()``, ``int()``, ``bool()`` of a tensor dispatch), ``shape`` (an op with a
  data-dependent output shape: on CUDA it reads the size back), ``host`` (``.cpu()``,
  ``.numpy()``, ``.tolist()`` from Python: a device-to-host copy on CUDA), ``upload``
  (``torch.tensor``/``as_tensor`` of host data, ``from_numpy``: a blocking host-to-device copy
  on CUDA); each with the line of the package it came from (``sites`` in the JSON);
- a Triton kernel launch counts as one op (``triton``); the ops inside Triton's interpreter
  are not counted;
- every op is also counted by the package function it came from (``op_sites`` in the JSON,
  ``file function``; the backward's ops are the line that calls ``backward``; ``site_ops``:
  by function and op): where a step's count goes.

Paths: ``cpu`` is what runs on the CPU (numba kernels for the march, the hash grid and the
whole fine-tuning step: those are not torch ops); ``cuda`` is what ``backend="auto"`` runs on
CUDA, run here on CPU tensors: the Triton kernels in Triton's interpreter (``march``,
``hashgrid``, ``finetune``; set up by this script) or, without the ``triton`` package, the
torch twins (the JSON says which). On a CPU machine a ``.cpu()`` of a CPU tensor costs
nothing: the counts say what the same code would do with CUDA tensors. Two exceptions are
marked in ``sites``: ``torch/optim`` (Adam's step counters live on the host in eager mode;
not a device sync) and the Triton wrapper's ``offsets[-1].item()`` (the two-pass march must
know its output size).

Step kinds, each at ``--batches`` rays (4096 and 16384: an op count that grows with the batch
means a Python loop over data):

- ``train``: ``Trainer.iteration`` (the CPU preset's step: sampling, occupancy march, loss,
  backward, Adam) on a step with no log row, no occupancy update and no moment flush;
- ``train+log``: the same on a step that writes a log row (every ``log_every`` steps);
- ``occupancy``: the occupancy grid's update (every ``occ_update_every`` = 16 steps);
- ``finetune``: ``FineTuneLoop.step`` on a slice of ``FineTuneLoop.tile_order`` (the batch's
  rays, the stepper's step with Adam; on the CPU path the divergence watch too); on the
  ``cuda`` path the step's figures stay on the device and the loop reads them back every
  ``read_every`` steps: row ``finetune read`` counts one such read (``read_figures``: the
  host wait, the divergence watch over the steps read).
- ``fixed``: ``Trainer.iteration`` with ``fixed_step`` (the ``gpu`` preset's step of fixed
  shape, :mod:`plenoctree.nerf.fixed`) at ``--batches`` rays in a budget of ``--budget``
  samples, on a step without a log row, occupancy update or ray-count adaptation: its count
  must not depend on the batch or the budget; with ``occupancy`` among the kinds also row
  ``fixed occupancy``, that trainer's grid update (read-back free).

Scenes: ``procedural`` (the analytic scene, written at 64², a CPU-preset model warmed up for
``--warm-steps`` steps, the tree ``procedural_tree(128)``) and ``lego`` (the trained NeRF-SH
``runs/lego_cpu_400`` on ``nerf_synthetic/lego`` at ``--downscale``, the lego tree of
``_trees.py`` extracted once into ``benchmarks/results/cache``).

Usage::

    python benchmarks/step_ops.py [--scene procedural lego] [--batches 4096 16384]
        [--paths cpu cuda] [--kinds train train+log occupancy finetune] [--out FILE.json]

Prints one table per scene and writes JSON (``benchmarks/results/step_ops.json``). The counts
do not depend on the machine's load; the seconds beside them do (not a speed benchmark).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Iterator

from _bench import add_data_root, add_out, data_path, machine_info, markdown_table, write_json

KINDS = ("train", "train+log", "occupancy", "finetune", "fixed")
SYNC_KINDS = ("item", "shape", "host", "upload")
_SHAPE_OPS = {"nonzero", "masked_select", "unique", "_unique", "_unique2", "unique_dim",
              "unique_consecutive", "bincount", "nonzero_numpy", "argwhere"}
_INDEX_OPS = {"index", "index_put", "index_put_", "_index_put_impl_"}
_PKG = os.sep + "plenoctree" + os.sep


def _site() -> str:
    """``file:line function`` of the innermost frame of the package (else of anything outside
    torch and this file), with ``(torch/optim)`` when torch's optimiser made the call."""
    f = sys._getframe(2)
    via_optim = False
    while f is not None:
        name = f.f_code.co_filename
        if _PKG in name:
            rel = name.split(_PKG, 1)[1]
            return f"{rel}:{f.f_lineno} {f.f_code.co_name}" + (" (torch/optim)" if via_optim
                                                                 else "")
        if os.sep + "torch" + os.sep + "optim" in name:
            via_optim = True
        f = f.f_back
    return "outside the package"


class Counts:
    """What one counted region dispatched."""

    def __init__(self) -> None:
        self.ops = 0
        self.views = 0
        self.triton = 0
        self.syncs: Counter = Counter()
        self.sites: Counter = Counter()
        self.by_op: Counter = Counter()
        self.op_sites: Counter = Counter()
        self.site_ops: Counter = Counter()
        self.bytes: Counter = Counter()         # bytes of the host and upload copies

    def sync(self, kind: str, what: str, nbytes: int = 0) -> None:
        self.syncs[kind] += 1
        self.sites[f"{kind}: {what} @ {_site()}"] += 1
        self.bytes[kind] += int(nbytes)

    def as_dict(self, per: int = 1) -> dict:
        d = {"ops": self.ops / per, "views": self.views / per, "triton": self.triton / per,
             "syncs": sum(self.syncs.values()) / per}
        d.update({f"sync_{k}": self.syncs[k] / per for k in SYNC_KINDS})
        d.update({f"bytes_{k}": self.bytes[k] / per for k in ("host", "upload")})
        d["sites"] = {k: v / per for k, v in self.sites.most_common()}
        d["top_ops"] = {k: v / per for k, v in self.by_op.most_common(15)}
        d["op_sites"] = {k: v / per for k, v in self.op_sites.most_common()}
        d["site_ops"] = {k: v / per for k, v in self.site_ops.most_common()}
        return d


def _bool_index(args: tuple) -> bool:
    idx = args[1] if len(args) > 1 else None
    return isinstance(idx, (list, tuple)) and any(
        getattr(t, "dtype", None) is not None and str(t.dtype) in ("torch.bool", "torch.uint8")
        for t in idx)


def _dispatch_mode():
    from torch.utils._python_dispatch import TorchDispatchMode

    class OpCounter(TorchDispatchMode):
        """Counts every aten op into ``self.counts`` (None: counting suspended)."""

        counts: Counts | None = None

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            c = self.counts
            if c is not None:
                name = func.overloadpacket.__name__
                c.ops += 1
                c.by_op[name] += 1
                site = re.sub(r":\d+ ", " ", _site())
                c.op_sites[site] += 1
                c.site_ops[f"{site}: {name}"] += 1
                if func.is_view:
                    c.views += 1
                if name == "_local_scalar_dense":
                    c.sync("item", name)
                elif name in _SHAPE_OPS or (name in _INDEX_OPS and _bool_index(args)):
                    c.sync("shape", name + ("[bool]" if name in _INDEX_OPS else ""))
                elif name == "repeat_interleave" and (kwargs or {}).get("output_size") is None:
                    c.sync("shape", name)
            return func(*args, **(kwargs or {}))

    return OpCounter()


class Recorder:
    """Counts the ops and syncs of regions: ``with counter.region() as c: ...``.

    Installs, while a region is open, the dispatch mode and Python-level wrappers of
    ``Tensor.cpu/numpy/tolist``, ``torch.tensor/as_tensor/from_numpy`` and Triton's kernel
    launch (its insides are not counted)."""

    def __init__(self) -> None:
        self.mode = _dispatch_mode()
        self.counts: Counts | None = None

    def _suspended(self, fn: Callable) -> Callable:
        def run(*a: Any, **k: Any) -> Any:
            c, self.counts, self.mode.counts = self.counts, None, None
            try:
                return fn(*a, **k)
            finally:
                self.counts = self.mode.counts = c
        return run

    def _patches(self) -> list[tuple[Any, str, Callable]]:
        import torch

        me = self

        def host(orig: Callable, what: str) -> Callable:
            # t.cpu().numpy() is one copy: the numpy() of what cpu() returned is not counted
            def wrapped(t, *a, **k):
                c = me.counts
                if c is not None and not (what == "numpy" and
                                          getattr(t, "_step_ops_copy", None) == id(c)):
                    c.sync("host", what, t.nelement() * t.element_size())
                out = me._suspended(orig)(t, *a, **k)
                if what == "cpu" and c is not None:
                    out._step_ops_copy = id(c)
                return out
            return wrapped

        def upload(orig: Callable, what: str) -> Callable:
            def wrapped(data, *a, **k):
                c = me.counts
                if c is not None and not isinstance(data, torch.Tensor):
                    c.sync("upload", what, getattr(data, "nbytes", 0))
                return orig(data, *a, **k)
            return wrapped

        out = [(torch.Tensor, n, host(getattr(torch.Tensor, n), n))
               for n in ("cpu", "numpy", "tolist")]
        out += [(torch, n, upload(getattr(torch, n), n))
                for n in ("tensor", "as_tensor", "from_numpy")]
        if "triton" in sys.modules or _triton_interpreted():
            from triton.runtime import interpreter

            orig = interpreter.GridExecutor.__call__

            def launch(ex, *a, **k):
                if me.counts is not None:
                    me.counts.triton += 1
                return me._suspended(orig)(ex, *a, **k)
            out.append((interpreter.GridExecutor, "__call__", launch))
        return out

    @contextlib.contextmanager
    def region(self) -> Iterator[Counts]:
        c = Counts()
        patches = self._patches()
        saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
        for obj, name, fn in patches:
            setattr(obj, name, fn)
        self.counts = self.mode.counts = c
        try:
            with self.mode:
                yield c
        finally:
            self.counts = self.mode.counts = None
            for obj, name, fn in saved:
                setattr(obj, name, fn)


# --- the NeRF trainer's Triton kernels, computed by stand-ins ------------------------------
# Triton's interpreter takes minutes for one training step (NumPy per block op). The counts
# need the kernels' outputs, not their speed: a launch of the hash-grid, occupancy-march,
# fused-network or early-termination kernel is counted as one launch, its wrapper's ops and
# syncs as they are, and its outputs are computed by the numba kernel of the same op (hash
# grid, march; tested equal in test_triton_kernels.py), the eager network in torch (mlp) or
# the kernel's per-ray loops in numba (terminate) — with counting suspended.
def _hashgrid_stand_in(ex: Any, *a: Any, **k: Any) -> None:
    from plenoctree.nerf import _hashgrid_numba as K

    pts, box, table, res, off, hashed, out, grad, gtable = a[:9]
    x = ((pts.float() - box[0]) / (box[1] - box[0])).clamp(0.0, 1.0).contiguous()
    lay = (res.numpy(), off.numpy(), hashed.numpy().astype(bool))
    if k["BACKWARD"]:
        K.hashgrid_backward(x.numpy(), grad.numpy(), *lay, gtable.numpy())
    else:
        K.hashgrid_forward(x.numpy(), table.numpy(), *lay, out.numpy())


def _march_stand_in(ex: Any, *a: Any, **k: Any) -> None:
    import numpy as np

    from plenoctree.nerf import _march_numba as K

    o, d, t0, t1, jit, k0, mask, step, lox, loy, loz, ivx, ivy, ivz, g, cap, n = a[:17]
    counts, k_next, done, offsets, ray_idx, ts, pts = a[17:24]
    levels = np.empty((g, g, g), np.uint8)
    K.empty_levels(mask.numpy().reshape(g, g, g).astype(bool), levels)
    cs = K.coarse_shift(g)
    coarse = np.empty((g >> cs,) * 3, np.uint8)
    K.coarse_levels(levels, cs, coarse)
    args = (o.numpy(), d.numpy(), t0.numpy(), t1.numpy(), jit.numpy(), k0.numpy(),
            np.float32(step), levels, coarse, np.int64(cs), np.array([lox, loy, loz], np.float32),
            np.array([ivx, ivy, ivz], np.float32))
    if k["FILL"]:
        K.march_fill(*args, offsets.numpy(), ray_idx.numpy(), ts.numpy(), pts.numpy())
    else:
        K.march_count(*args, int(cap), counts.numpy(), k_next.numpy(),
                      done.numpy().view(np.bool_))


def _mlp_stand_in(ex: Any, *a: Any, **k: Any) -> None:
    """The fused network kernel (forward or backward) by torch ops on the CPU (the kernel's
    contract: ``_mlp_triton.FusedField``; the interpreter takes minutes at 2^18 rows)."""
    import torch

    from plenoctree.nerf.model import _sh_colors_torch, trunc_exp

    x, dirs = a[0], a[1]
    ws = [t.detach().clone().requires_grad_() for t in a[2:10]]
    sig, rgb, gsig, grgb, gx = a[10:15]
    grads, n = a[15:23], a[23]
    depth, density = k["DEPTH"], k["DENSITY"]
    xg = x[:n].detach().clone().requires_grad_()
    with torch.enable_grad():
        h = xg
        for i in range(depth):
            h = torch.relu(h @ ws[2 * i].T + ws[2 * i + 1])
        wh, bh = (ws[6][:1], ws[7][:1]) if density else (ws[6], ws[7])
        out = h @ wh.T + bh
        raw = out[:, 0]
        s = trunc_exp(raw - 1.0) if k["ACT"] == 1 else torch.relu(raw)
        c = None if density else _sh_colors_torch(out[:, 1:], dirs[:n], k["DEG"])
    if not k["BACKWARD"]:
        sig[:n] = s.detach()
        if c is not None:
            rgb[:n] = c.detach()
        return
    outs = [s] if density else [s, c]
    gouts = [gsig[:n]] if density else [gsig[:n], grgb[:n]]
    used = [2 * i + j for i in range(depth) for j in (0, 1)] + [6, 7]
    got = torch.autograd.grad(outs, [xg] + [ws[i] for i in used], gouts)
    gx[:n] = got[0]
    for i, g in zip(used, got[1:]):
        grads[i].add_(g)


_TERMINATE_LOOPS: list = []


def _terminate_loops() -> tuple:
    """numba loops of the terminate kernel's two launches (each ray walks its candidates)."""
    if not _TERMINATE_LOOPS:
        import numba
        import numpy as np

        @numba.njit(cache=False)
        def count(off, sig, step, limit, n, out):
            for r in range(n):
                i, c, d = off[r], 0, 0.0
                while i < off[r + 1] and d <= limit:
                    c += 1
                    d += np.float64(sig[i]) * step
                    i += 1
                out[r] = c

        @numba.njit(cache=False)
        def fill(off, ray, t, pts, first, cnt, n, cap, centre, oray, ot, opts):
            for r in range(n):
                dest, i = first[r], off[r]
                for _ in range(cnt[r]):
                    if dest >= cap:
                        break
                    oray[dest], ot[dest], opts[dest] = ray[i], t[i], pts[i]
                    dest += 1
                    i += 1
            for s in range(first[n], cap):
                oray[s], ot[s], opts[s] = n, 0.0, centre
        _TERMINATE_LOOPS.extend([count, fill])
    return tuple(_TERMINATE_LOOPS)


def _terminate_stand_in(ex: Any, *a: Any, **k: Any) -> None:
    """Early termination's kernel (``_terminate_triton``) by the same per-ray loops in numba
    (the interpreter takes minutes at 65,536 rays)."""
    off, sig, ray, t, pts, first, box, cnt, oray, ot, opts, consts, n, cap = a[:14]
    count, fill = _terminate_loops()
    step, limit = consts.tolist()
    if not k["FILL"]:
        count(off.numpy(), sig.numpy(), step, limit, n, cnt.numpy())
        return
    centre = (0.5 * (box[0] + box[1])).numpy()
    fill(off.numpy(), ray.numpy(), t.numpy(), pts.numpy(), first.numpy(), cnt.numpy(), n, cap,
         centre, oray.numpy(), ot.numpy(), opts.numpy())


_STAND_INS = {("plenoctree.nerf._hashgrid_triton", "_hashgrid_kernel"): _hashgrid_stand_in,
              ("plenoctree.nerf._terminate_triton", "_terminate_kernel"): _terminate_stand_in,
              ("plenoctree.nerf._march_triton", "_march_kernel"): _march_stand_in,
              ("plenoctree.nerf._mlp_triton", "_mlp_kernel"): _mlp_stand_in}


# --- paths ---------------------------------------------------------------------------------
def _triton_interpreted() -> bool:
    from plenoctree import _triton

    return _triton.interpret_mode() and _triton.has_triton()


@contextlib.contextmanager
def backends_of(path: str) -> Iterator[None]:
    """Inside: ``backend="auto"`` resolves as on ``path``'s device (``cuda``: Triton where
    registered, else the torch twin), whatever the tensors' device."""
    from plenoctree import backend

    if path == "cpu":
        yield
        return
    orig = backend.resolve

    def resolve(op: str, requested: str = "auto", device: Any = "cpu") -> str:
        if str(requested).lower() != "auto":
            return orig(op, requested, device)
        names = backend.backends(op, "cuda")
        if not names:
            return orig(op, requested, device)
        return names[0] if names[0] != "triton" or _triton_interpreted() else names[-1]

    backend.resolve = resolve
    launch = None
    if _triton_interpreted():
        from triton.runtime import interpreter

        launch = interpreter.GridExecutor.__call__

        def fast(ex: Any, *a: Any, **k: Any) -> Any:
            stand_in = _STAND_INS.get((ex.fn.__module__, ex.fn.__name__))
            return (stand_in or launch)(ex, *a, **k)
        interpreter.GridExecutor.__call__ = fast
    try:
        yield
    finally:
        backend.resolve = orig
        if launch is not None:
            interpreter.GridExecutor.__call__ = launch


def describe_path(path: str) -> dict:
    from plenoctree import backend

    with backends_of(path):
        return {op: backend.resolve(op, "auto", "cpu")
                for op in ("march", "hashgrid", "sh_colors", "render_grad")}


# --- the training step ---------------------------------------------------------------------
def _step_number(start: int, cfg: Any, log_row: bool) -> int:
    """The first step ``>= start`` with a log row (or without one), no occupancy update, no
    moment flush and no adaptation of a fixed-shape step's ray count."""
    s = start
    while True:
        occ = s > 0 and s % cfg.occ_update_every == 0
        adapt = s % cfg.occ_update_every == cfg.occ_update_every - 1
        log = (s + 1) % cfg.log_every == 0
        if not occ and not adapt and s % 100 != 99 and log == log_row:
            return s
        s += 1


def make_trainer(scene: str, root: Path, args: argparse.Namespace, fixed: bool = False) -> Any:
    """A set-up :class:`~plenoctree.nerf.trainer.Trainer` of ``scene`` writing into ``root``
    (``fixed``: with steps of fixed shape)."""
    import torch

    from plenoctree.nerf import preset
    from plenoctree.nerf.trainer import Trainer

    if scene == "lego":
        from plenoctree.nerf.checkpoint import model_from_checkpoint, read_checkpoint

        ck = read_checkpoint(data_path(args.data_root, "runs", "lego_cpu_400"))
        cfg = ck["config"]
        cfg.data = str(data_path(args.data_root, "nerf_synthetic", "lego"))
        cfg.downscale = args.downscale
    else:
        from plenoctree.datasets.procedural import write_procedural_dataset

        ck = None
        cfg = preset("cpu")
        cfg.data = str(write_procedural_dataset(root / "data", n_train=20, n_val=0, n_test=1,
                                                width=64, height=64, n_samples=256))
    cfg.out = str(root / f"run_{scene}")
    if args.distortion_weight is not None:      # the distortion loss (on by default for photos)
        cfg.distortion_weight = args.distortion_weight
    cfg.device, cfg.minutes, cfg.max_steps, cfg.threads = "cpu", 0.0, 10**9, args.threads
    cfg.val_views, cfg.val_every_s, cfg.val_every_steps = 0, 0.0, 0
    cfg.ckpt_every_s, cfg.ckpt_every_steps, cfg.preview_every_s = 0.0, 0, 0.0   # not the step
    cfg.fixed_step = fixed
    if fixed:
        cfg.out += "_fixed"
    tr = Trainer(cfg, quiet=True)
    tr.setup()
    if ck is not None:
        with torch.no_grad():
            tr.model.load_state_dict(model_from_checkpoint(ck, device=tr.device).state_dict())
        tr.step = int(ck["step"])
    return tr


def warm_up(tr: Any, steps: int) -> None:
    """``steps`` steps on the CPU path (JIT, occupancy grid settling)."""
    from plenoctree._util import progress

    bar = progress(total=1, disable=True)
    for _ in range(steps):
        tr.iteration(bar)


def count_train(tr: Any, counter: Recorder, path: str, batch: int, log_row: bool,
                repeat: int, budget: int = 0) -> dict:
    """Counts of ``repeat`` iterations at ``batch`` rays (mean per step); ``budget``: the
    sample budget of a fixed-shape trainer."""
    from plenoctree._util import progress

    bar = progress(total=1, disable=True)
    cfg = tr.cfg
    if budget:
        cfg.target_samples = tr.fixed.capacity = budget
    else:
        cfg.target_samples = max(cfg.target_samples, 64 * batch)  # the sample cap never binds
    total, seconds = Counts(), 0.0
    seen: list[int] = []
    probe = type("Probe", (), {"before_step": lambda self, step: None,
                               "after_step": lambda self, step, dt, n: seen.append(n)})()
    tr.hooks.append(probe)
    with backends_of(path):
        for i in range(repeat + 1):                 # the first: warm-up (JIT, Triton parse)
            tr.step = _step_number(tr.step, cfg, log_row)
            tr.state.n_rays = float(batch)
            t0 = time.perf_counter()
            if i == 0:
                tr.iteration(bar)
                continue
            with counter.region() as c:
                tr.iteration(bar)
            seconds += time.perf_counter() - t0
            _merge(total, c)
    tr.hooks.remove(probe)
    out = total.as_dict(repeat)
    out.update(seconds=seconds / repeat, rays=batch,
               samples_per_ray=sum(seen[1:]) / (repeat * batch), budget=budget)
    return out


def count_occupancy(tr: Any, counter: Recorder, path: str) -> dict:
    """Counts of one occupancy-grid update after the warm-up steps."""
    tr.step = max(tr.step, tr.cfg.occ_warmup_steps)
    tr.step += (-tr.step) % tr.cfg.occ_update_every
    with backends_of(path):
        tr._update_occupancy()                           # warm-up
        t0 = time.perf_counter()
        with counter.region() as c:
            tr._update_occupancy()
    out = c.as_dict()
    out.update(seconds=time.perf_counter() - t0, rays=0)
    return out


def _merge(total: Counts, c: Counts) -> None:
    total.ops += c.ops
    total.views += c.views
    total.triton += c.triton
    total.syncs.update(c.syncs)
    total.sites.update(c.sites)
    total.by_op.update(c.by_op)
    total.op_sites.update(c.op_sites)
    total.site_ops.update(c.site_ops)


# --- the fine-tuning step ------------------------------------------------------------------
def finetune_setup(scene: str, args: argparse.Namespace, root: Path) -> tuple[Any, Any]:
    """``(tree, train view set)`` of ``scene``."""
    from plenoctree.datasets import load_dataset
    from plenoctree.optim._loop import ViewSet

    from _trees import load_bench_tree

    if scene == "lego":
        tree, _ = load_bench_tree("lego", root=args.data_root)
        data = load_dataset(str(data_path(args.data_root, "nerf_synthetic", "lego")), "train",
                            downscale=args.downscale)
    else:
        tree, _ = load_bench_tree("procedural", 128)
        if not (root / "data").exists():         # --kinds finetune alone: no trainer wrote it
            from plenoctree.datasets.procedural import write_procedural_dataset

            write_procedural_dataset(root / "data", n_train=20, n_val=0, n_test=1, width=64,
                                     height=64, n_samples=256)
        data = load_dataset(str(root / "data"), "train")
    return tree, ViewSet.from_dataset(data)


def count_finetune(tree: Any, views: Any, counter: Recorder, path: str, batch: int,
                   repeat: int) -> dict:
    """Counts of ``repeat`` ``FineTuneLoop.step`` calls at ``batch`` rays (the default Adam
    with σ's own rate) on ``path``'s stepper; ``"read"``: the counts of the read of their
    figures (device steppers)."""
    from plenoctree._util import progress
    from plenoctree.optim._loop import FineTuneLoop, LoopOptions
    from plenoctree.optim.finetuning import _make_stepper
    from plenoctree.pipeline_config import FinetuneConfig

    backend = "numba" if path == "cpu" else ("triton" if _triton_interpreted() else "torch")
    cfg = FinetuneConfig(backend=backend, device="cpu")
    stepper, _ = _make_stepper(cfg, tree, (1.0, 1.0, 1.0))
    loop = FineTuneLoop(stepper, views, None,
                        LoopOptions(epochs=1, batch_rays=batch, read_every=repeat + 1), {})
    loop._bar = progress(total=1, disable=True)
    perm = loop.tile_order()          # numpy on the CPU path, on the device on the cuda path
    k = loop.tiles_per_batch
    total, seconds = Counts(), 0.0
    for i in range(repeat + 1):
        tiles = perm[i * k:(i + 1) * k]
        if i == 0:
            loop.step(tiles, 1)
            continue
        t0 = time.perf_counter()
        with counter.region() as c:
            loop.step(tiles, 1)
        seconds += time.perf_counter() - t0
        _merge(total, c)
    out = total.as_dict(repeat)
    out.update(seconds=seconds / repeat, rays=batch, stepper=type(stepper).__name__)
    if getattr(loop, "_dev", None) is not None:         # the figures of those steps, read once
        t0 = time.perf_counter()
        with counter.region() as c:
            loop.read_figures(1)
        out["read"] = c.as_dict()
        out["read"].update(seconds=time.perf_counter() - t0, rays=0,
                           read_every=loop.opts.read_every)
    return out


# --- report --------------------------------------------------------------------------------
def table(rows: list[dict]) -> str:
    head = ["kind", "path", "rays", "ops", "views", "triton", "syncs", *SYNC_KINDS, "s"]
    cells = [[r["kind"] + (f" (S={r['budget']})" if r.get("budget") else ""), r["path"],
              r["rays"] or "–", f"{r['ops']:.0f}", f"{r['views']:.0f}",
              f"{r['triton']:.0f}", f"{r['syncs']:.0f}",
              *(f"{r['sync_' + k]:.0f}" for k in SYNC_KINDS), f"{r['seconds']:.2f}"]
             for r in rows]
    return markdown_table(head, cells)


def run_scene(scene: str, args: argparse.Namespace, counter: Recorder, root: Path) -> list[dict]:
    rows: list[dict] = []

    def add(kind: str, path: str, res: dict) -> None:
        res.update(kind=kind, path=path, scene=scene)
        rows.append(res)
        print(f"  {scene} {kind} {path} {res['rays']}: {res['ops']:.0f} ops, "
              f"{res['syncs']:.0f} syncs ({res['seconds']:.1f} s)", file=sys.stderr, flush=True)

    train_kinds = [k for k in args.kinds if k not in ("finetune", "fixed")]
    if train_kinds:
        tr = make_trainer(scene, root, args)
        warm_up(tr, args.warm_steps if scene == "procedural" else 2)
        for path in args.paths:
            for batch in args.batches:
                for kind in ("train", "train+log"):
                    if kind in args.kinds:
                        add(kind, path, count_train(tr, counter, path, batch, kind != "train",
                                                    args.repeat))
            if "occupancy" in args.kinds:
                add("occupancy", path, count_occupancy(tr, counter, path))
        del tr
    if "fixed" in args.kinds:
        tr = make_trainer(scene, root, args, fixed=True)
        warm_up(tr, args.warm_steps if scene == "procedural" else 2)
        for path in args.paths:
            for batch in args.batches:
                add("fixed", path, count_train(tr, counter, path, batch, False, args.repeat,
                                               args.budget))
            if "occupancy" in args.kinds:
                add("fixed occupancy", path, count_occupancy(tr, counter, path))
        del tr
    if "finetune" in args.kinds:
        tree, views = finetune_setup(scene, args, root)
        for path in args.paths:
            for batch in args.batches:
                res = count_finetune(tree, views, counter, path, batch, args.repeat)
                read = res.pop("read", None)
                add("finetune", path, res)
                if read is not None:
                    add("finetune read", path, read)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", nargs="+", default=["procedural", "lego"],
                    choices=["procedural", "lego"])
    ap.add_argument("--batches", nargs="+", type=int, default=[4096, 16384])
    ap.add_argument("--paths", nargs="+", default=["cpu", "cuda"], choices=["cpu", "cuda"])
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    ap.add_argument("--budget", type=int, default=1 << 18,
                    help="kind fixed: the sample budget of a step (the gpu preset's: 2^18)")
    ap.add_argument("--repeat", type=int, default=1, help="counted steps per row (after one "
                    "warm-up step)")
    ap.add_argument("--warm-steps", type=int, default=40,
                    help="procedural scene: CPU steps before counting (the occupancy grid "
                         "settles)")
    ap.add_argument("--downscale", type=int, default=8, help="lego photos' downscale")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--distortion-weight", type=float, default=None,
                    help="train steps with this distortion-loss weight (default: the run's)")
    add_data_root(ap)
    add_out(ap, "step_ops.json")
    args = ap.parse_args(argv)
    counter = Recorder()
    machine = machine_info()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="step_ops_") as tmp:
        for scene in args.scene:
            rows += run_scene(scene, args, counter, Path(tmp))
    paths = {p: describe_path(p) for p in args.paths}
    lines = [f"Torch ops and host syncs per step (CPU tensors; path cuda = {paths.get('cuda')})"]
    for scene in args.scene:
        lines += ["", f"### {scene}", "", table([r for r in rows if r["scene"] == scene])]
    text = "\n".join(lines)
    print(text)
    out = {"benchmark": "step_ops", "machine": machine_info(machine["loadavg"]),
           "args": vars(args), "paths": paths, "rows": rows, "table": text}
    print(f"\nwrote {write_json(args.out, out)}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("TRITON_INTERPRET", "1")       # before triton is imported
    os.environ.setdefault("PLENOCTREE_TRITON_CPU", "1")
    from plenoctree import runtime

    runtime.configure()
    sys.exit(main())
