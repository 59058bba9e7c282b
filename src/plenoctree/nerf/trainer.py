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

import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .._util import atomic_save_json, atomic_write, progress
from ..datasets import Dataset, load_dataset
from ..errors import ConfigError, PlenOctreeError
from ..runtime import ThreadTuner, resolve_amp, resolve_device, setup_threads
from .checkpoint import CHECKPOINT_NAME, CheckpointError, model_from_checkpoint, \
    read_checkpoint, save_checkpoint
from .config import TrainConfig, config_json, validate
from .encoding import HashGridEncoding
from .evaluate import evaluate_views
from .model import NeRFModel
from .renderer import autocast, render_rays_hierarchical, render_rays_occupancy
from .runlog import RunLog

# Runtime set-up (threads, malloc, device, AMP) is plenoctree.runtime's, not re-exported here.
__all__ = ["TrainingError", "TrainResult", "train", "learning_rate", "flush_tiny_moments",
           "sparsity_loss", "RaySource", "load_val_views"]

class TrainingError(PlenOctreeError, RuntimeError):
    """Training cannot continue (non-finite loss); the last good checkpoint is kept."""


def learning_rate(cfg: TrainConfig, step: int, progress_frac: float) -> float:
    """jaxnerf's schedule: log-linear ``lr_init -> lr_final`` over ``progress_frac`` in [0, 1],
    times a sine warm-up from ``lr_delay_mult`` over the first ``lr_delay_steps`` steps."""
    p = min(max(progress_frac, 0.0), 1.0)
    lr = math.exp(math.log(cfg.lr_init) * (1 - p) + math.log(cfg.lr_final) * p)
    if cfg.lr_delay_steps > 0:
        s = min(max(step / cfg.lr_delay_steps, 0.0), 1.0)
        lr *= cfg.lr_delay_mult + (1 - cfg.lr_delay_mult) * math.sin(0.5 * math.pi * s)
    return lr


@torch.no_grad()
def flush_tiny_moments(optimizer: torch.optim.Optimizer, tiny: float = 1e-30) -> int:
    """Zero Adam moments that decayed towards denormal floats; returns how many entries.

    Rarely-touched hash-table rows have moments that shrink geometrically; once denormal,
    every Adam step on them is ~3x slower on x86 (and ``torch.set_flush_denormal`` does not
    reach the worker threads). ``exp_avg`` below ``tiny`` is set to 0, then ``exp_avg_sq``
    below ``tiny`` where ``exp_avg`` is 0 — the update of such entries is 0 either way.
    """
    n = 0
    for st in optimizer.state.values():
        m, v = st.get("exp_avg"), st.get("exp_avg_sq")
        if m is None or v is None:
            continue
        small_m = m.abs() < tiny
        m.masked_fill_(small_m, 0.0)
        small_v = (v < tiny) & small_m
        n += int(small_v.sum())
        v.masked_fill_(small_v, 0.0)
    return n


def sparsity_loss(sigma: torch.Tensor, length: float) -> torch.Tensor:
    """Eq. (6): ``mean_k |1 - exp(-λ σ_k)|`` with ``λ = length``.

    Densities are non-negative, so the absolute value is the identity and is left out (its
    zero subgradient at σ = 0 would otherwise stop the prior exactly where it starts).
    """
    return (1.0 - torch.exp(-length * sigma)).mean()


# ------------------------------------------------------------------ data
class RaySource:
    """Random rays over all pixels of all training images, with their target colours.

    Rays are made on the fly by :meth:`plenoctree.datasets.Cameras.pixel_rays` (so per-camera
    intrinsics and NDC rays of forward-facing scenes are honoured, identical to
    ``cameras.rays(i)``); only the images are held in memory.
    """

    def __init__(self, data: Dataset, device: torch.device, random_background: bool):
        cams = data.cameras
        n, h, w = len(cams), cams.height, cams.width
        self.n, self.h, self.w = n, h, w
        self.device = device
        self.cameras = cams
        self.images = torch.from_numpy(np.ascontiguousarray(data.images)).reshape(-1, 3).to(device)
        self.bg = torch.tensor(data.background, dtype=torch.float32, device=device)
        self.alphas = None
        if random_background and data.alphas is not None:
            self.alphas = torch.from_numpy(np.ascontiguousarray(data.alphas)).reshape(-1).to(device)

    def rays_of(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(origins [B, 3], unit dirs [B, 3])`` float32 of flat pixel indices ``idx [B]``
        (``img * H * W + row * W + col``), equal to ``cameras.rays(img)[row, col]``."""
        img = idx // (self.h * self.w)
        pix = idx % (self.h * self.w)
        return self.cameras.pixel_rays(img, pix % self.w, pix // self.w)

    def sample(self, n: int, generator: torch.Generator):
        """``(origins, dirs, target [n, 3], background [n, 3])`` of ``n`` random pixels."""
        idx = torch.randint(self.n * self.h * self.w, (n,), generator=generator,
                            device=self.device)
        o, d = self.rays_of(idx)
        rgb = self.images[idx]
        if self.alphas is None:
            return o, d, rgb, self.bg.expand(n, 3)
        a = self.alphas[idx][:, None]
        bg = torch.rand((n, 3), generator=generator, device=self.device)
        return o, d, rgb - (1.0 - a) * self.bg + (1.0 - a) * bg, bg


def load_val_views(cfg: TrainConfig) -> Dataset | None:
    """The ``val_views`` evenly spaced views of split ``val_split`` (None when 0 views)."""
    if cfg.val_views <= 0:
        return None
    return load_dataset(cfg.data, cfg.val_split, format=cfg.format, downscale=cfg.downscale,
                        background=cfg.background, limit=cfg.val_views, spread=True)


# ------------------------------------------------------------------ training
@dataclass
class TrainResult:
    """What :func:`train` returns."""

    run_dir: Path
    step: int
    train_time_s: float
    val_psnr: float
    model: NeRFModel
    log: dict = field(default_factory=dict)


def _prepare_run_dir(cfg: TrainConfig, resume: bool):
    out = Path(cfg.out)
    ck_path = out / CHECKPOINT_NAME
    if resume:
        ck = read_checkpoint(ck_path)
        return out, ck
    if ck_path.exists():
        raise ConfigError(f"{out}: already holds a training run ({CHECKPOINT_NAME}); pass "
                          "--resume to continue it or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    return out, None


def train(cfg: TrainConfig, resume: bool = False,
          on_step: Callable[[int], None] | None = None, quiet: bool | None = None
          ) -> TrainResult:
    """Train a NeRF-SH as configured; see :func:`_train` and the module docstring.

    Holds the run-folder lock (:func:`plenoctree._util.run_lock`) while training: a second
    ``train``/``--resume`` into the same ``--out`` fails at once naming the holder.
    """
    from .._util import check_output_dir, run_lock

    validate(cfg)
    if not cfg.data or not cfg.out:
        raise ConfigError("training needs a dataset folder (--data) and a run directory (--out)")
    check_output_dir(cfg.out)
    # Under torchrun only rank 0 (the one that writes) holds the lock: the other ranks of the
    # same run would otherwise find the folder "in use" by rank 0.
    from .distributed import rank_from_env

    if rank_from_env() != 0:
        return _train(cfg, resume, on_step, quiet)
    with run_lock(cfg.out, "train --resume" if resume else "train"):
        return _train(cfg, resume, on_step, quiet)


def _train(cfg: TrainConfig, resume: bool = False,
           on_step: Callable[[int], None] | None = None, quiet: bool | None = None
           ) -> TrainResult:
    """Train a NeRF-SH as configured; see the module docstring for the outputs.

    Args:
        cfg: the configuration (``cfg.data`` and ``cfg.out`` required). On ``resume`` its
            model options must match the checkpoint's (else :class:`CheckpointError`).
        resume: continue the run in ``cfg.out`` from its checkpoint.
        on_step: called with the step count after every completed step (tests use it to
            interrupt a run).
        quiet: hide the progress bar (default: shown on a terminal).

    Raises:
        TrainingError: the loss became NaN/inf. DatasetError, ConfigError, CheckpointError.
    """
    validate(cfg)
    if not cfg.data or not cfg.out:
        raise ConfigError("training needs a dataset folder (--data) and a run directory (--out)")
    n_threads = setup_threads(cfg.threads)
    tuner = ThreadTuner(n_threads) if cfg.threads == -1 else None
    from .distributed import render_generator, setup_distributed

    dctx = setup_distributed(resolve_device(cfg.device))   # torchrun: one shard per process
    device = dctx.device
    amp = resolve_amp(cfg.amp, device)
    if dctx.is_main:
        out, ck = _prepare_run_dir(cfg, resume)
    dctx.barrier()
    if not dctx.is_main:
        out, ck = _prepare_run_dir(cfg, True) if resume else (Path(cfg.out), None)

    data = load_dataset(cfg.data, "train", format=cfg.format, downscale=cfg.downscale,
                        background=cfg.background)
    val = load_val_views(cfg)
    occ = cfg.sampler == "occupancy"
    torch.manual_seed(cfg.seed)
    if ck is not None:
        model = model_from_checkpoint(ck, expect=cfg, device=device)
    else:
        model = NeRFModel(cfg.model, data.scene_bbox, occ_res=cfg.occ_res if occ else 0).to(device)
    dctx.broadcast_module(model)
    model.train()
    for mod in model.modules():
        if isinstance(mod, HashGridEncoding):
            mod.grad_in_place = True
    fused = device.type == "cpu" or device.type == "cuda"
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr_init, betas=(0.9, cfg.adam_beta2),
                           eps=cfg.adam_eps, fused=fused)
    gen = torch.Generator(device=device)
    gen.manual_seed(cfg.seed + 1)
    step, train_s, wall_before = 0, 0.0, 0.0
    tstate = {"n_rays": float(cfg.batch_rays), "spr": 0.0, "next_val_s": cfg.val_every_s,
              "last_ckpt_step": 0}
    log = RunLog(out)
    if ck is not None:
        try:
            opt.load_state_dict(ck["optimizer"])
            gen.set_state(ck["rng"].to(gen.get_state().device))
        except (ValueError, RuntimeError, KeyError) as e:
            raise CheckpointError(f"{ck['path']}: optimizer / RNG state does not fit ({e})") from None
        step, train_s, wall_before = ck["step"], ck["train_time_s"], ck["wall_time_s"]
        tstate.update(ck["trainer"])
        log = RunLog(out, ck["log"])
    else:
        if occ:
            spr0 = float((model.scene_bbox[1] - model.scene_bbox[0]).norm()) / cfg.render_step / 2
            tstate["n_rays"] = float(min(cfg.batch_rays, max(256, cfg.target_samples / spr0)))

    if dctx.is_main:
        with atomic_write(out / "config.json", "w") as f:
            f.write(config_json(cfg) + "\n")
    else:
        log.write = lambda *a, **k: None           # rank 0 alone writes the logs
    # the rendering noise: the shared generator in one process, one per rank under torchrun
    rgen = gen if not dctx.active else render_generator(cfg.seed, dctx.rank, step, device)

    rays = RaySource(data, device, cfg.random_background)
    bbox = model.scene_bbox
    occ_thresh = -math.log(1.0 - cfg.occ_threshold) / cfg.render_step
    budget_s = cfg.minutes * 60.0
    wall0 = time.perf_counter() - wall_before
    last_ckpt_wall = time.perf_counter()
    # running sums since the last log row (checkpointed, so a resumed log matches)
    win = tstate.pop("win", None) or {"t": 0.0, "rays": 0, "samples": 0, "loss": 0.0,
                                      "mse": 0.0, "n": 0}
    val_psnr = float("nan")
    ckpt_file = out / CHECKPOINT_NAME

    def finished() -> bool:
        return step >= cfg.max_steps or (budget_s > 0 and train_s >= budget_s)

    def frac() -> float:
        p = step / max(cfg.max_steps, 1)
        return max(p, train_s / budget_s) if budget_s > 0 else p

    def checkpoint() -> None:
        nonlocal last_ckpt_wall
        if not dctx.is_main:
            return
        if not all(bool(torch.isfinite(p).all()) for p in model.parameters()):
            raise TrainingError(f"the weights became NaN/inf by step {step}; training stopped "
                                f"without overwriting the last good checkpoint ({ckpt_file}, "
                                f"step {tstate['last_ckpt_step']})")
        tstate["last_ckpt_step"] = step
        tstate["win"] = dict(win)
        save_checkpoint(ckpt_file, config=cfg, step=step, train_time_s=train_s,
                        wall_time_s=time.perf_counter() - wall0, model=model, optimizer=opt,
                        rng=gen.get_state(), trainer=tstate, log=log.as_dict())
        last_ckpt_wall = time.perf_counter()

    def validate_now() -> None:
        nonlocal val_psnr
        if val is None or not dctx.is_main:
            return
        r = evaluate_views(model, val, cfg, out_dir=out / "val", amp=amp, device=device)
        val_psnr = r["mean_psnr"]
        log.val.append({"step": step, "train_s": round(train_s, 3),
                        "wall_s": round(time.perf_counter() - wall0, 3), "psnr": val_psnr,
                        "ssim": r["mean_ssim"], "seconds": float(np.sum(r["seconds"])),
                        "load": round(os.getloadavg()[0], 2)})
        log.write()

    # A time budget counts training seconds (its % and ETA are the budget's), else steps.
    timed = budget_s > 0
    bar = progress(total=round(budget_s) if timed else cfg.max_steps, desc="train",
                   unit="s" if timed else "step",
                   disable=(quiet if quiet is not None else None) if dctx.is_main else True,
                   **({"bar_format": "{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}"
                       "{postfix}]"} if timed and sys.stderr.isatty() else {}))
    bar.update(train_s if timed else step)
    try:
        while not finished():
            if tuner is not None:
                tuner.before_step(step)
            t0 = time.perf_counter()
            lr = learning_rate(cfg, step, frac())
            for g in opt.param_groups:
                g["lr"] = lr
            t_occ = time.perf_counter()
            if occ and step > 0 and step % cfg.occ_update_every == 0:
                with autocast(device, amp):
                    model.occupancy.update(model.fine.density, occ_thresh, cfg.occ_decay,
                                           all_cells=step < cfg.occ_warmup_steps,
                                           generator=gen)
                if dctx.active:     # identical on every rank already; keep it bit-identical
                    dctx.broadcast_module(model.occupancy)
            t_occ = time.perf_counter() - t_occ
            n_rays = int(tstate["n_rays"]) if occ else cfg.batch_rays
            o, d, target, bg = (dctx.shard(x) for x in rays.sample(n_rays, gen))
            if occ:
                r = render_rays_occupancy(model, o, d, data.near, data.far, bg, cfg, True, rgen,
                                          amp, max_samples=2 * cfg.target_samples // dctx.world)
                ok = r["complete"]
                used = int(ok.sum())
                # (used == 0 only if the sample cap cut off every ray: skip the photometric term)
                mse = torch.mean((r["rgb"][ok] - target[ok]) ** 2) if used else r["rgb"].sum() * 0
                loss = mse
            else:
                r = render_rays_hierarchical(model, o, d, data.near, data.far, bg, cfg, True,
                                             rgen, amp)
                used = int(o.shape[0])
                mse = torch.mean((r["rgb"] - target) ** 2)
                loss = mse + torch.mean((r["rgb_coarse"] - target) ** 2)
            if cfg.sparsity_weight > 0 and cfg.sparsity_points > 0:
                pts = bbox[0] + (bbox[1] - bbox[0]) * torch.rand(
                    (cfg.sparsity_points, 3), generator=gen, device=device)
                with autocast(device, amp):
                    sig = model.fine.density(pts)
                loss = loss + cfg.sparsity_weight * sparsity_loss(sig, cfg.sparsity_length)
            n_samples = int(r["n_samples"])
            if dctx.active:       # global figures: every rank logs, adapts and stops alike
                g_loss, g_mse, g_used, g_samples = dctx.sum(
                    [float(loss.detach()), float(mse.detach()), used, n_samples])
                loss_v, mse_v = g_loss / dctx.world, g_mse / dctx.world
                used, n_samples = int(g_used), int(g_samples)
            else:
                loss_v, mse_v = None, None
            if not math.isfinite(float(loss.detach()) if loss_v is None else loss_v):
                kept = (f"the last good checkpoint ({ckpt_file}, step "
                        f"{tstate['last_ckpt_step']}) is kept" if ckpt_file.exists()
                        else "no checkpoint had been written yet")
                bad = loss.item() if loss_v is None else loss_v
                raise TrainingError(f"loss became {bad} at step {step}; training "
                                    f"stopped, {kept}. Try a lower learning rate (--lr-init).")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            dctx.average_gradients(model.parameters())
            opt.step()
            if step % 100 == 99:
                flush_tiny_moments(opt)
            if occ:
                spr = max(n_samples, 1) / max(used, 1)
                tstate["spr"] = spr if tstate["spr"] == 0 else 0.9 * tstate["spr"] + 0.1 * spr
                tstate["n_rays"] = float(min(cfg.max_rays, max(
                    256, round(cfg.target_samples / tstate["spr"]))))
            step += 1
            dt = time.perf_counter() - t0
            if dctx.active:        # rank 0's clock for all (time budgets, validation times)
                dt = dctx.sum([dt if dctx.is_main else 0.0])[0]
            if tuner is not None:
                tuner.after_step(step - 1, dt - t_occ, n_samples)
            train_s += dt
            win["t"] += dt
            win["rays"] += used
            win["samples"] += n_samples
            win["loss"] += float(loss.detach()) if loss_v is None else loss_v
            win["mse"] += float(mse.detach()) if mse_v is None else mse_v
            win["n"] += 1
            bar.update(dt if timed else 1)
            if step % cfg.log_every == 0 or finished():
                m = win["mse"] / win["n"]
                row = {"step": step, "train_s": round(train_s, 3),
                       "wall_s": round(time.perf_counter() - wall0, 3), "lr": lr,
                       "loss": win["loss"] / win["n"], "psnr": -10 * math.log10(max(m, 1e-12)),
                       "rays_per_s": win["rays"] / win["t"],
                       "samples_per_s": win["samples"] / win["t"],
                       "rays": used,
                       "samples_per_ray": win["samples"] / max(win["rays"], 1),
                       "occupancy": model.occupancy.occupancy() if occ else 1.0,
                       "threads": torch.get_num_threads()}
                log.train.append(row)
                bar.set_postfix(loss=f"{row['loss']:.4f}", psnr=f"{row['psnr']:.2f}",
                                rays_s=f"{row['rays_per_s']:.0f}")
                win = dict.fromkeys(win, 0) | {"t": 0.0, "loss": 0.0, "mse": 0.0}
                log.write(plot=False)
            due_val = (cfg.val_every_s > 0 and train_s >= tstate["next_val_s"]) or \
                (cfg.val_every_steps > 0 and step % cfg.val_every_steps == 0)
            if due_val and not finished():
                while tstate["next_val_s"] <= train_s and cfg.val_every_s > 0:
                    tstate["next_val_s"] += cfg.val_every_s
                validate_now()
            if (cfg.ckpt_every_s > 0 and time.perf_counter() - last_ckpt_wall >= cfg.ckpt_every_s) \
                    or (cfg.ckpt_every_steps > 0 and step % cfg.ckpt_every_steps == 0):
                checkpoint()
            if on_step is not None:
                on_step(step)
        validate_now()
        checkpoint()
        log.write()
    finally:
        bar.close()
    summary = {"step": step, "train_time_s": train_s, "wall_time_s": time.perf_counter() - wall0,
               "val_psnr": val_psnr, "val_ssim": log.val[-1]["ssim"] if log.val else None,
               "val_views": list(val.names) if val is not None else [],
               "mean_rays_per_s": _mean(log.train, "rays_per_s"),
               "mean_samples_per_s": _mean(log.train, "samples_per_s"),
               "device": str(device), "amp": amp, "threads": torch.get_num_threads(),
               "world_size": dctx.world}
    if dctx.is_main:
        atomic_save_json(out / "summary.json", summary)
    dctx.barrier()
    dctx.close()
    return TrainResult(out, step, train_s, val_psnr, model, log.as_dict())


def _mean(rows: list[dict], key: str) -> float | None:
    vals = [r[key] for r in rows if key in r]
    return float(np.mean(vals)) if vals else None
