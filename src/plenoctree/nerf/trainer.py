"""NeRF-SH training (§3, §4.1): photometric loss + sparsity prior, Adam with exponential decay.

:func:`train` runs a :class:`~plenoctree.nerf.config.TrainConfig` and writes a run directory::

    config.json     the configuration          checkpoint.pt  see :mod:`.checkpoint`
    log.csv/val.csv/log.json/curve.png         see :mod:`.runlog`
    val/<view>.png  the latest validation renders, with metrics.json
    summary.json    final figures

A run killed at any moment resumes from its last checkpoint with ``resume=True`` (CLI
``--resume``), losing at most the steps since it; without a time budget the resumed run is
bit-for-bit the uninterrupted one (all randomness comes from one generator saved in the
checkpoint). A non-finite loss stops training with :class:`TrainingError` before anything is
written, so the last good checkpoint stays.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .._util import atomic_save_json, atomic_write, progress
from ..datasets import load_dataset
from ..errors import ConfigError
from ..octree.ndc import NDCSpace
from ..runtime import ThreadTuner, resolve_amp, resolve_device, setup_threads
from .checkpoint import CHECKPOINT_NAME, CheckpointError, TrainProgress, \
    model_from_checkpoint, open_run_dir, save_checkpoint
from .config import TrainConfig, config_json, validate
from .encoding import HashGridEncoding
from .far import resolve_far_levels, resolve_render_step
from .fixed import FixedBatch, candidate_factor, fixed_loss, render_fixed
from .graph import StepGraphs, lr_tensor, make_capturable
from .occupancy import WARMUP_DECAY
from .raygen import draw_uniforms, ray_batch
from .preview import LiveView
from .trainer_state import LogWindow, StepFigures, TrainerState, TrainResult
from .evaluate import evaluate_views
from .model import NeRFModel, RadianceField
from .renderer import ImageOptions, RayBatch, RenderMode, autocast, render_rays_hierarchical, \
    render_rays_occupancy
from .runlog import RunLog
from .training import (VAL_SHARE, RaySource, TrainingError, distortion_weight,
                       flush_tiny_moments, learning_rate, load_val_views, opaque_photos,
                       val_row_stride, with_sparsity)

# Runtime set-up (threads, malloc, device, AMP) is plenoctree.runtime's, not re-exported here.
__all__ = ["TrainResult", "Trainer", "TrainerState", "train"]

def train(cfg: TrainConfig, resume: bool = False,
          on_step: Callable[[int], None] | None = None, quiet: bool | None = None
          ) -> TrainResult:
    """Train a NeRF-SH as configured; see :class:`Trainer` and the module docstring.

    Args:
        cfg: the configuration (``cfg.data`` and ``cfg.out`` required). On ``resume`` its
            model options must match the checkpoint's (else :class:`CheckpointError`).
        resume: continue the run in ``cfg.out`` from its checkpoint.
        on_step: called with the step count after every completed step (tests use it to
            interrupt a run).
        quiet: hide the progress bar (default: shown on a terminal).

    Holds the run-folder lock (:func:`plenoctree._util.run_lock`) while training: a second
    ``train``/``--resume`` into the same ``--out`` fails at once naming the holder.

    Raises:
        TrainingError: the loss became NaN/inf. DatasetError, ConfigError, CheckpointError.
    """
    from .._util import check_output_dir, run_lock

    trainer = Trainer(cfg, resume, on_step, quiet)     # validates cfg (--data, --out given)
    check_output_dir(cfg.out)
    if Path(cfg.out).resolve() == Path(cfg.data).resolve():
        raise ConfigError(f"--out {cfg.out} is the dataset folder; give the run its own folder")
    # Under torchrun only rank 0 (the one that writes) holds the lock: the other ranks of the
    # same run would otherwise find the folder "in use" by rank 0.
    from .distributed import rank_from_env

    if rank_from_env() != 0:
        return trainer.run()
    with run_lock(cfg.out, "train --resume" if resume else "train"):
        return trainer.run()


class Trainer:
    """One NeRF-SH training run: its state on ``self``, one method per part of a step.

    :meth:`setup` builds everything (devices, run folder, data, model, optimiser, restored
    state); :meth:`run` loops :meth:`iteration` — :meth:`train_step` (the optimisation step
    itself), then the log row, :meth:`maybe_validate` and :meth:`maybe_checkpoint` — until
    :meth:`finished`, then validates, checkpoints and writes ``summary.json``.

    ``hooks`` are called around every step (``before_step(step)``,
    ``after_step(step, seconds, samples)``); the adaptive thread count
    (:class:`~plenoctree.runtime.ThreadTuner`, ``threads = -1``) is one.
    """

    def __init__(self, cfg: TrainConfig, resume: bool = False,
                 on_step: Callable[[int], None] | None = None, quiet: bool | None = None):
        validate(cfg)
        if not cfg.data or not cfg.out:
            raise ConfigError("training needs a dataset folder (--data) and a run directory "
                              "(--out)")
        self.cfg, self.resume, self.on_step, self.quiet = cfg, resume, on_step, quiet
        self.occ = cfg.sampler == "occupancy"
        self.budget_s = cfg.minutes * 60.0
        self.step, self.train_s = 0, 0.0
        self.val_psnr = float("nan")
        self.val_stride = 0                 # validation rows step (training.val_row_stride)
        self.lr = cfg.lr_init
        self.ready = False
        self._pending: list[tuple] = []     # (step, loss, mse) not yet read back

    # ------------------------------------------------------------- set-up
    def setup(self) -> None:
        """Threads, devices, run folder, data, model, optimiser; restores a checkpoint."""
        cfg = self.cfg
        n_threads = setup_threads(cfg.threads)
        self.hooks = [ThreadTuner(n_threads)] if cfg.threads == -1 else []
        from .distributed import render_generator, setup_distributed

        self.dctx = setup_distributed(resolve_device(cfg.device))   # torchrun: one shard each
        if cfg.fixed_step and self.dctx.active:
            raise ConfigError("--fixed-step does not run under torchrun yet; train on one "
                              "device, or without --fixed-step")
        self.device = self.dctx.device
        self.amp = resolve_amp(cfg.amp, self.device)
        ck = self._prepare_run_dir()
        self.data = load_dataset(cfg.data, "train", format=cfg.format, downscale=cfg.downscale,
                                 background=cfg.background)
        self.val = load_val_views(cfg)
        main = self.dctx.is_main
        cfg = self.cfg = dataclasses.replace(
            cfg, far_levels=resolve_far_levels(cfg, self.data, announce=main),
            render_step=resolve_render_step(cfg, self.data, announce=main))
        self._build_model(ck)
        wall_before = self._restore(ck) if ck is not None else self._fresh_state()
        if self.dctx.is_main:
            with atomic_write(self.out / "config.json", "w") as f:
                f.write(config_json(cfg) + "\n")
        else:
            self.log.write = lambda *a, **k: None           # rank 0 alone writes the logs
        # the rendering noise: the shared generator in one process, one per rank under torchrun
        self.rgen = self.gen if not self.dctx.active else render_generator(
            cfg.seed, self.dctx.rank, self.step, self.device)
        self.rays = RaySource(self.data, self.device, cfg.random_background,
                              opaque_photos=opaque_photos(cfg))
        self.dist_weight = distortion_weight(cfg)
        self.fixed = FixedBatch(cfg.target_samples, cfg.max_rays, self.device,
                                candidate_factor(cfg)) if cfg.fixed_step else None
        self.graphs = StepGraphs(self._graph_body, self.device, (self.gen,)) \
            if cfg.cuda_graph else None
        if self.graphs is not None:     # also after a checkpoint's optimiser state
            make_capturable(self.opt, self.device)
        self.live = LiveView(self.out, cfg.preview_every_s, NDCSpace.from_cameras(
            self.data.cameras)) if self.dctx.is_main else None      # plenoctree view RUN
        self.occ_thresh = -math.log(1.0 - cfg.occ_threshold) / cfg.render_step
        self.wall0 = time.perf_counter() - wall_before
        self.last_ckpt_wall = time.perf_counter()
        self.ckpt_file = self.out / CHECKPOINT_NAME
        self.ready = True

    def _prepare_run_dir(self) -> dict | None:
        """Rank 0 checks / creates the run folder first; returns the checkpoint to resume."""
        dctx = self.dctx
        if dctx.is_main:
            self.out, ck = open_run_dir(self.cfg.out, self.resume)
        dctx.barrier()
        if not dctx.is_main:
            self.out, ck = open_run_dir(self.cfg.out, True) if self.resume else \
                (Path(self.cfg.out), None)
        return ck

    def _build_model(self, ck: dict | None) -> None:
        """The model (fresh, or the checkpoint's), its Adam optimiser and the step generator."""
        cfg, device = self.cfg, self.device
        torch.manual_seed(cfg.seed)
        if ck is not None:
            model = model_from_checkpoint(ck, expect=cfg, device=device)
        else:
            model = NeRFModel(cfg.model, self.data.scene_bbox,
                              occ_res=cfg.occ_res if self.occ else 0,
                              far_levels=cfg.far_levels).to(device)
        self.dctx.broadcast_module(model)
        model.train()
        for mod in model.modules():
            if isinstance(mod, (HashGridEncoding, RadianceField)):
                mod.grad_in_place = True
        fused = device.type == "cpu" or device.type == "cuda"
        # a step replayed from a CUDA graph (nerf.graph) reads its learning rate from the
        # device and keeps Adam's step count there
        lr = lr_tensor(cfg.lr_init, device) if cfg.cuda_graph else cfg.lr_init
        self.opt = torch.optim.Adam(model.parameters(), lr=lr, betas=(0.9, cfg.adam_beta2),
                                    eps=cfg.adam_eps, fused=fused, capturable=cfg.cuda_graph)
        self.gen = torch.Generator(device=device)
        self.gen.manual_seed(cfg.seed + 1)
        self.model = model
        box = np.asarray(self.data.scene_bbox, dtype=np.float64).reshape(2, 3)
        self.extent = float((box[1] - box[0]).max())      # distortion loss's unit of length
        self.state = TrainerState(n_rays=float(cfg.batch_rays), next_val_s=cfg.val_every_s)

    def _fresh_state(self) -> float:
        """A new run: first rays per step from the box diagonal; returns 0 wall seconds."""
        cfg = self.cfg
        if self.occ:
            bbox = self.model.scene_bbox
            spr0 = float((bbox[1] - bbox[0]).norm()) / cfg.render_step / 2
            self.state.n_rays = float(min(cfg.batch_rays, max(256, cfg.target_samples / spr0)))
        self.log = RunLog(self.out)
        return 0.0

    def _restore(self, ck: dict) -> float:
        """Optimiser, generator, counters and log of checkpoint ``ck``; returns its wall
        seconds."""
        try:
            self.opt.load_state_dict(ck["optimizer"])
            self.gen.set_state(ck["rng"].to(self.gen.get_state().device))
        except (ValueError, RuntimeError, KeyError) as e:
            raise CheckpointError(f"{ck['path']}: optimizer / RNG state does not fit ({e})"
                                  ) from None
        self.step, self.train_s = ck["step"], ck["train_time_s"]
        self.state.update(ck["trainer"])
        self.log = RunLog(self.out, ck["log"])
        return ck["wall_time_s"]

    # ------------------------------------------------------------- progress
    def finished(self) -> bool:
        """The step count or the time budget (training seconds) is reached."""
        return self.step >= self.cfg.max_steps or (
            self.budget_s > 0 and self.train_s >= self.budget_s)

    def progress_frac(self) -> float:
        """Share of the run done, in steps or (with a budget) seconds, whichever is further."""
        p = self.step / max(self.cfg.max_steps, 1)
        return max(p, self.train_s / self.budget_s) if self.budget_s > 0 else p

    def _wall(self) -> float:
        return time.perf_counter() - self.wall0

    def _progress_bar(self):
        # A time budget counts training seconds (its % and ETA are the budget's), else steps.
        timed = self.budget_s > 0
        quiet = self.quiet if self.dctx.is_main else True
        bar = progress(total=round(self.budget_s) if timed else self.cfg.max_steps,
                       desc="train", unit="s" if timed else "step", disable=quiet,
                       **({"bar_format": "{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<"
                           "{remaining}{postfix}]"} if timed and sys.stderr.isatty() else {}))
        bar.update(self.train_s if timed else self.step)
        return bar

    # ------------------------------------------------------------- the step
    def _update_occupancy(self) -> float:
        """Every ``occ_update_every`` steps, refresh the occupancy grid; returns its seconds."""
        cfg, model = self.cfg, self.model
        t = time.perf_counter()
        if self.occ and self.step > 0 and self.step % cfg.occ_update_every == 0:
            with autocast(self.device, self.amp):
                warm = self.step < cfg.occ_warmup_steps
                model.occupancy.update(model.fine.density, self.occ_thresh,
                                       WARMUP_DECAY if warm else cfg.occ_decay, all_cells=warm,
                                       generator=self.gen, sync_free=self.fixed is not None)
            if self.dctx.active:     # identical on every rank already; keep it bit-identical
                self.dctx.broadcast_module(model.occupancy)
        return time.perf_counter() - t

    def _fixed_loss(self, n_rays: int | None = None):
        """``(loss, mse, rays, samples)`` of a fixed-shape step (:mod:`.fixed`; one process
        only) of ``n_rays`` rays (None: the state's): the rays in one launch (op
        ``ray_batch``), nothing read back inside the step; the rays are counted on the device
        only (:meth:`.FixedBatch.add_device`: the host's count is the caller's)."""
        cfg = self.cfg
        n_rays = self.fixed.rays(self.state.n_rays) if n_rays is None else n_rays
        rays = ray_batch(self.rays, draw_uniforms(n_rays, self.gen, self.device),
                         self.model.scene_bbox)
        mode = RenderMode(train=True, generator=self.rgen, amp=self.amp,
                          distortion=self.dist_weight > 0)
        r = render_fixed(self.model, rays.batch(self.data.near, self.data.far), cfg, mode,
                         cfg.target_samples, rays.bounds)
        loss, mse = fixed_loss(r, rays.target, self.dist_weight, self.extent)
        self.fixed.add_device(r["total"], r["kept"])
        return loss, mse, n_rays, int(r["n_samples"])

    def _graph_body(self, n_rays: int):
        """One whole fixed-shape step of ``n_rays`` rays as :class:`.graph.StepGraphs`
        captures it: ``(stack(loss, mse), samples)``; zeroing, forward, backward, Adam."""
        self.opt.zero_grad(set_to_none=False)
        loss, mse, _, samples = self._fixed_loss(n_rays)
        loss = self._with_sparsity(loss)
        loss.backward()
        self.opt.step()
        return torch.stack([loss.detach(), mse.detach()]), samples

    def _sampled_loss(self):
        """``(loss, mse, rays used, samples)`` of the waves (occupancy sampler) or the
        hierarchical sampler on random pixels (this rank's shard)."""
        cfg, dctx, data = self.cfg, self.dctx, self.data
        n_rays = int(self.state.n_rays) if self.occ else cfg.batch_rays
        o, d, target, bg = (dctx.shard(x) for x in self.rays.sample(n_rays, self.gen))
        batch = RayBatch(o, d, data.near, data.far, bg)
        if not self.occ:
            mode = RenderMode(train=True, generator=self.rgen, amp=self.amp)
            r = render_rays_hierarchical(self.model, batch, cfg, mode)
            mse = torch.mean((r["rgb"] - target) ** 2)
            loss = mse + torch.mean((r["rgb_coarse"] - target) ** 2)
            return loss, mse, int(o.shape[0]), int(r["n_samples"])
        mode = RenderMode(train=True, generator=self.rgen, amp=self.amp,
                          max_samples=2 * cfg.target_samples // dctx.world,
                          distortion=self.dist_weight > 0)
        r = render_rays_occupancy(self.model, batch, cfg, mode)
        rgb, dist, far_dist = r["rgb"], r.get("distortion"), r.get("far_distortion")
        if r["capped"]:         # only the complete rays (one host round trip)
            ok = r["complete"].nonzero()[:, 0]
            used = int(ok.shape[0])
            rgb, target = rgb.index_select(0, ok), target.index_select(0, ok)
            dist = None if dist is None else dist.index_select(0, ok)
            far_dist = None if far_dist is None else far_dist.index_select(0, ok)
        else:
            used = int(rgb.shape[0])
        # (used == 0 only if the sample cap cut off every ray: skip the photometric term)
        mse = torch.mean((rgb - target) ** 2) if used else r["rgb"].sum() * 0
        loss = mse
        if dist is not None and used:
            loss = loss + self.dist_weight / self.extent * dist.mean()
        if far_dist is not None and used:       # in normalised distances (nerf.far)
            loss = loss + self.dist_weight * far_dist.mean()
        return loss, mse, used, int(r["n_samples"])

    def _render_loss(self):
        """``(loss, mse, rays used, samples)`` of a random batch of rays (this rank's shard),
        with the sparsity prior."""
        if self.fixed is not None:
            loss, mse, used, samples = self._fixed_loss()
            self.fixed.count(used)
        else:
            loss, mse, used, samples = self._sampled_loss()
        return self._with_sparsity(loss), mse, used, samples

    def _with_sparsity(self, loss: torch.Tensor) -> torch.Tensor:
        """``loss`` plus the sparsity prior at random points of the box (eq. 6)."""
        return with_sparsity(loss, self.model, self.cfg, self.gen, self.amp)

    def _check_finite(self, loss: float, step: int) -> None:
        if math.isfinite(loss):
            return
        kept = (f"the last good checkpoint ({self.ckpt_file}, step "
                f"{self.state.last_ckpt_step}) is kept" if self.ckpt_file.exists()
                else "no checkpoint had been written yet")
        raise TrainingError(f"loss became {loss} at step {step}; training stopped, "
                            f"{kept}. Try a lower learning rate (--lr-init).")

    def read_losses(self) -> None:
        """Read the losses of the steps since the last call back from the device (one host
        round trip), add them to the log window in step order and stop on a non-finite one
        (:class:`TrainingError` naming its step).

        Called before anything is written (log row, validation, checkpoint), so a non-finite
        loss still stops the run before it writes; the steps after it until then run on
        (with non-finite weights, which :meth:`checkpoint` refuses anyway)."""
        pending, self._pending = self._pending, []
        dev = [x for _, loss, mse in pending for x in (loss, mse) if isinstance(x, torch.Tensor)]
        values = iter(torch.stack(dev).tolist() if dev else [])
        win = self.state.win
        for step, loss, mse in pending:
            loss_v = next(values) if isinstance(loss, torch.Tensor) else loss
            mse_v = next(values) if isinstance(mse, torch.Tensor) else mse
            self._check_finite(loss_v, step)
            win.loss += loss_v
            win.mse += mse_v

    def train_step(self) -> StepFigures:
        """One optimisation step: learning rate, occupancy update, render, loss, Adam step,
        rays-per-step adaptation. Does not advance :attr:`step`."""
        cfg, dctx = self.cfg, self.dctx
        lr = learning_rate(cfg, self.step, self.progress_frac())
        for g in self.opt.param_groups:
            if isinstance(g["lr"], torch.Tensor):
                g["lr"].fill_(lr)           # read by a captured step (nerf.graph)
            else:
                g["lr"] = lr
        t_occ = self._update_occupancy()
        if self.graphs is not None:
            return self._graph_step(lr, t_occ)
        loss, mse, used, n_samples = self._render_loss()
        if dctx.active:       # global figures: every rank logs, adapts and stops alike
            g_loss, g_mse, g_used, g_samples = dctx.sum(
                [float(loss.detach()), float(mse.detach()), used, n_samples])
            loss_v, mse_v = g_loss / dctx.world, g_mse / dctx.world
            used, n_samples = int(g_used), int(g_samples)
            self._check_finite(loss_v, self.step)
        else:                 # read back with the next log row (read_losses)
            loss_v, mse_v = loss.detach(), mse.detach()
        # the fixed step keeps its gradient buffers (one zeroing launch for all, and the
        # kernels add into them) where the waves' step frees them
        self.opt.zero_grad(set_to_none=self.fixed is None)
        loss.backward()
        dctx.average_gradients(self.model.parameters())
        self.opt.step()
        self._after_step()
        if self.fixed is None and self.occ:
            st = self.state
            spr = max(n_samples, 1) / max(used, 1)
            st.spr = spr if st.spr == 0 else 0.9 * st.spr + 0.1 * spr
            st.n_rays = float(min(cfg.max_rays, max(256, round(cfg.target_samples / st.spr))))
        return StepFigures(lr, loss_v, mse_v, used, n_samples, t_occ)

    def _after_step(self) -> None:
        """After the optimiser step, both paths: the moments' flush every 100 steps and, for
        fixed-shape steps, the ray count's adaptation every ``occ_update_every``."""
        if self.step % 100 == 99:
            flush_tiny_moments(self.opt)
        every = self.cfg.occ_update_every
        if self.fixed is not None and self.step % every == every - 1:
            self.fixed.adapt(self.state)

    def _graph_step(self, lr: float, t_occ: float) -> StepFigures:
        """:meth:`train_step`'s rest with ``cuda_graph``: the step of the state's ray count
        from :class:`.graph.StepGraphs` (replayed on CUDA), then the host's bookkeeping."""
        n_rays = self.fixed.rays(self.state.n_rays)
        both, n_samples = self.graphs.step(n_rays)
        self.fixed.count(n_rays)
        self._after_step()
        return StepFigures(lr, both[0], both[1], n_rays, n_samples, t_occ)

    # ------------------------------------------------------------- around the step
    def iteration(self, bar) -> None:
        """:meth:`train_step` with its hooks, clock, log row, validation and checkpoint."""
        for h in self.hooks:
            h.before_step(self.step)
        t0 = time.perf_counter()
        fig = self.train_step()
        self.step += 1
        dt = time.perf_counter() - t0
        if self.dctx.active:        # rank 0's clock for all (time budgets, validation times)
            dt = self.dctx.sum([dt if self.dctx.is_main else 0.0])[0]
        for h in self.hooks:
            h.after_step(self.step - 1, dt - fig.occupancy_s, fig.samples)
        self.train_s += dt
        win = self.state.win
        win.t += dt
        win.rays += fig.rays
        win.samples += fig.samples
        self._pending.append((self.step - 1, fig.loss, fig.mse))    # summed by read_losses
        win.n += 1
        bar.update(dt if self.budget_s > 0 else 1)
        if self.step % self.cfg.log_every == 0 or self.finished():
            self.log_row(fig, bar)
        self.maybe_validate()
        if self.live is not None:
            self.live.tick(self.model, self.train_s)
        self.maybe_checkpoint()
        if self.on_step is not None:
            self.on_step(self.step)

    def log_row(self, fig: StepFigures, bar) -> None:
        """Append the averages since the last row to ``log.csv`` and start a new window."""
        self.read_losses()
        win = self.state.win
        m = win.mse / win.n
        row = {"step": self.step, "train_s": round(self.train_s, 3),
               "wall_s": round(self._wall(), 3), "lr": fig.lr,
               "loss": win.loss / win.n, "psnr": -10 * math.log10(max(m, 1e-12)),
               "rays_per_s": win.rays / win.t,
               "samples_per_s": win.samples / win.t,
               "rays": fig.rays,
               "samples_per_ray": win.samples / max(win.rays, 1),
               "occupancy": self.model.occupancy.occupancy() if self.occ else 1.0,
               "threads": torch.get_num_threads()}
        self.log.train.append(row)
        bar.set_postfix(loss=f"{row['loss']:.4f}", psnr=f"{row['psnr']:.2f}",
                        rays_s=f"{row['rays_per_s']:.0f}")
        self.state.win = LogWindow()
        self.log.write(plot=False)
        if self.live is not None:
            self.live.row(self.step, None if self.budget_s > 0 else self.cfg.max_steps,
                          row["psnr"], self.progress_frac(), self.train_s)

    def maybe_validate(self) -> None:
        """Validate when due by training seconds (``val_every_s``) or steps, unless done."""
        cfg, st = self.cfg, self.state
        due = (cfg.val_every_s > 0 and self.train_s >= st.next_val_s) or \
            (cfg.val_every_steps > 0 and self.step % cfg.val_every_steps == 0)
        if due and not self.finished():
            while st.next_val_s <= self.train_s and cfg.val_every_s > 0:
                st.next_val_s += cfg.val_every_s
            t0 = time.perf_counter()
            self.validate()
            # large validation images must not eat the time budget: at most VAL_SHARE of
            # the wall time goes to timed validations (fewer rows, then a later next one)
            gap = (time.perf_counter() - t0) * (1.0 - VAL_SHARE) / VAL_SHARE
            if cfg.val_every_s > 0:
                st.next_val_s = max(st.next_val_s, self.train_s + gap)

    def maybe_checkpoint(self) -> None:
        """Checkpoint when due by wall seconds (``ckpt_every_s``) or steps."""
        cfg = self.cfg
        if (cfg.ckpt_every_s > 0 and time.perf_counter() - self.last_ckpt_wall >= cfg.ckpt_every_s) \
                or (cfg.ckpt_every_steps > 0 and self.step % cfg.ckpt_every_steps == 0):
            self.checkpoint()

    def validate(self) -> None:
        """Render and score the validation views (rank 0 alone; the other ranks get its PSNR
        at the end, :meth:`_finish`), every ``val_stride``-th row of large views; appends a
        ``val.csv`` row."""
        self.read_losses()
        if self.val is None or not self.dctx.is_main:
            return
        pixels, height = self.val.images[..., 0].size, self.val.cameras.height
        if not self.val_stride:
            self.val_stride = val_row_stride(pixels, height)
        rows = slice(None, None, self.val_stride) if self.val_stride > 1 else None
        t0 = time.perf_counter()
        r = evaluate_views(self.model, self.val, self.cfg, out_dir=self.out / "val",
                           with_ssim=rows is None,
                           opts=ImageOptions(amp=self.amp, device=self.device, rows=rows))
        self.val_stride = val_row_stride(pixels, height, self.val_stride,
                                         time.perf_counter() - t0, self.cfg.val_every_s)
        self.val_psnr = r["mean_psnr"]
        self.log.val.append({"step": self.step, "train_s": round(self.train_s, 3),
                             "wall_s": round(self._wall(), 3), "psnr": self.val_psnr,
                             "ssim": r["mean_ssim"], "seconds": float(np.sum(r["seconds"])),
                             "load": round(os.getloadavg()[0], 2)})
        self.log.write()

    def checkpoint(self) -> None:
        """Write ``checkpoint.pt`` (rank 0); refuses non-finite weights (the last good file
        stays)."""
        self.read_losses()
        if not self.dctx.is_main:
            return
        if not all(bool(torch.isfinite(p).all()) for p in self.model.parameters()):
            raise TrainingError(f"the weights became NaN/inf by step {self.step}; training "
                                f"stopped without overwriting the last good checkpoint "
                                f"({self.ckpt_file}, step {self.state.last_ckpt_step})")
        self.state.last_ckpt_step = self.step
        save_checkpoint(self.ckpt_file, self.cfg, self.model, TrainProgress(
            step=self.step, train_time_s=self.train_s, wall_time_s=self._wall(),
            optimizer=self.opt, rng=self.gen.get_state(), trainer=self.state.to_json(),
            log=self.log.as_dict()))
        self.last_ckpt_wall = time.perf_counter()

    # ------------------------------------------------------------- the run
    def run(self) -> TrainResult:
        """Set up (unless done), train until :meth:`finished`, validate, checkpoint, and write
        ``summary.json``."""
        if not self.ready:
            self.setup()
        bar = self._progress_bar()
        try:
            while not self.finished():
                self.iteration(bar)
            self.validate()
            self.checkpoint()
            self.log.write()
            if self.live is not None:       # the trained model's preview, and its PSNR
                self.live.tick(self.model, self.train_s, force=True)
                self.live.row(self.step, self.step, self.val_psnr, 1.0, self.train_s,
                              "NeRF-SH trained")
        finally:
            bar.close()
        return self._finish()

    def _finish(self) -> TrainResult:
        dctx, log, val = self.dctx, self.log, self.val
        # only rank 0 validated (torchrun): its PSNR is the run's, on every rank
        self.val_psnr = dctx.from_main([self.val_psnr])[0]
        summary = {"step": self.step, "train_time_s": self.train_s, "wall_time_s": self._wall(),
                   "val_psnr": self.val_psnr,
                   "val_ssim": log.val[-1]["ssim"] if log.val else None,
                   "val_views": list(val.names) if val is not None else [],
                   "mean_rays_per_s": _mean(log.train, "rays_per_s"),
                   "mean_samples_per_s": _mean(log.train, "samples_per_s"),
                   "device": str(self.device), "amp": self.amp,
                   "threads": torch.get_num_threads(), "world_size": dctx.world,
                   "preview_s": None if self.live is None else round(self.live.seconds, 3),
                   "cuda_graphs": None if self.graphs is None else
                   {"captures": self.graphs.captures, "replays": self.graphs.replays}}
        if dctx.is_main:
            atomic_save_json(self.out / "summary.json", summary)
        dctx.barrier()
        dctx.close()
        return TrainResult(self.out, self.step, self.train_s, self.val_psnr, self.model,
                           log.as_dict())


def _mean(rows: list[dict], key: str) -> float | None:
    vals = [r[key] for r in rows if key in r]
    return float(np.mean(vals)) if vals else None
