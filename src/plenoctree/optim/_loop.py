"""The epoch loop of fine-tuning: random ray batches, validation, early stop, divergence, resume.

Used by :func:`plenoctree.optim.finetuning.finetune`; works with either stepper of
:mod:`._steppers`.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .._util import atomic_save_npz, progress
from ..errors import ConfigError
from ._best import BestValues, remove_best_files

__all__ = ["ViewSet", "LoopState", "Diverged", "render_views_psnr", "run_loop",
           "remove_best_files"]

_EMA = 0.2            # smoothing of the batch MSE for the divergence test
_DIVERGE_FACTOR = 4.0  # smoothed batch MSE above factor * first-batch MSE + _DIVERGE_ABS ...
_DIVERGE_ABS = 1e-3    # ... means the learning rate diverged
_MIN_BATCHES = 5


@dataclass
class ViewSet:
    """Posed images to train or validate on: ``c2w [N, 4, 4]``, the intrinsics of the first
    camera, ``images [N, H, W, 3]``, and their names.

    ``images`` are float32 in [0, 1], or uint16 holding ``round(65535 · value)`` (what
    :meth:`from_dataset` keeps: half the memory, 0.77 GB less for lego's 2 × 100 views at 800²,
    within 7.6e-6 of the photo's values); :meth:`image` gives a view in float32.

    ``cameras`` (the dataset's :class:`~plenoctree.datasets.Cameras`; default: pinhole cameras
    from ``c2w`` and the intrinsics) and ``cam_index`` (int64 ``[N]``, view ``i`` is camera
    ``cam_index[i]``) are the source of truth for rays: each view's camera is packed once into
    ``packed_cameras`` (its own intrinsics; for an NDC set the NDC reference camera of all the
    cameras, which is why they are all kept) and one numba kernel makes a batch's rays, equal to
    ``cameras.rays(i)`` — pinhole or NDC, shared or per-camera intrinsics alike.
    """

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    images: np.ndarray
    names: list[str]
    cameras: Any = None
    cam_index: np.ndarray | None = None
    packed_cameras: np.ndarray = field(init=False, repr=False)   # float64 [N, CAM_SIZE]

    def __post_init__(self) -> None:
        from ..datasets import Cameras
        from ..render._render_numba import pack_cameras

        if self.cameras is None:
            self.cameras = Cameras(self.c2w, float(self.fx), float(self.fy), float(self.cx),
                                   float(self.cy), int(self.width), int(self.height))
            self.cam_index = np.arange(len(self), dtype=np.int64)
        self.packed_cameras = pack_cameras(self.cameras, self.cam_index)
        if self.images.dtype not in (np.float32, np.uint16):
            raise TypeError(f"ViewSet images must be float32 or uint16, got {self.images.dtype}")

    @property
    def unit(self) -> float:
        """The value of one step of ``images`` (1 for float32, 1 / 65535 for uint16)."""
        return 1.0 / 65535.0 if self.images.dtype == np.uint16 else 1.0

    def image(self, i: int) -> np.ndarray:
        """View ``i``'s image, float32 ``[H, W, 3]`` in [0, 1]."""
        img = self.images[i]
        return img if img.dtype == np.float32 else img.astype(np.float32) * np.float32(self.unit)

    @classmethod
    def from_dataset(cls, data: Any, indices: Any = None) -> ViewSet:
        cams = data.cameras
        idx = np.arange(len(cams)) if indices is None else np.asarray(indices, dtype=np.int64)
        fx, fy, cx, cy = cams.intrinsics(int(idx[0]) if len(idx) else 0)
        images = np.empty((len(idx), cams.height, cams.width, 3), np.uint16)
        for j, i in enumerate(idx):          # one image at a time: no float-sized temporary
            np.rint(np.clip(np.asarray(data.images[i], np.float32), 0.0, 1.0) * 65535.0,
                    out=images[j], casting="unsafe")
        return cls(np.ascontiguousarray(cams.c2w[idx], dtype=np.float32), fx, fy, cx, cy,
                   cams.width, cams.height, images,
                   [data.names[i] for i in idx] if data.names else [f"view_{i}" for i in idx],
                   cams, idx)

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def n_rays(self) -> int:
        return len(self) * self.width * self.height

    def rays(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``origins, dirs, targets`` float32 ``[M, 3]`` of flat pixel indices ``index [M]``
        (``img * H * W + row * W + col``); the rays equal ``cameras.rays(img)[row, col]``."""
        from ._render_grad_numba import pixel_rays

        index = np.ascontiguousarray(index, np.int64)
        m = index.shape[0]
        o = np.empty((m, 3), np.float32)
        d = np.empty((m, 3), np.float32)
        t = np.empty((m, 3), np.float32)
        pixel_rays(self.packed_cameras, int(self.width), int(self.height), index, self.images,
                   self.unit, o, d, t)
        return o, d, t

    def n_tiles(self, k: int) -> int:
        """Number of ``k × k`` pixel tiles covering every image (partial tiles at the borders)."""
        return len(self) * (-(-self.height // k)) * (-(-self.width // k))

    def tile_pixels(self, tiles: np.ndarray, k: int) -> np.ndarray:
        """Flat pixel indices (``img * H * W + v * W + u``) of tiles ``tiles [T]``, tile by tile
        in raster order within each tile; pixels past the image border are dropped."""
        nty, ntx = -(-self.height // k), -(-self.width // k)
        tiles = np.asarray(tiles, dtype=np.int64)
        img, rem = np.divmod(tiles, nty * ntx)
        ty, tx = np.divmod(rem, ntx)
        dy, dx = np.divmod(np.arange(k * k, dtype=np.int64), k)
        v = ty[:, None] * k + dy
        u = tx[:, None] * k + dx
        flat = img[:, None] * (self.height * self.width) + v * self.width + u
        if self.height % k or self.width % k:
            return flat[(v < self.height) & (u < self.width)]
        return flat.reshape(-1)

    def view_rays(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``origins, dirs [H * W, 3]`` of view ``i`` (``cameras.rays``)."""
        o, d = self.cameras.rays(int(self.cam_index[i]))
        return o.reshape(-1, 3), d.reshape(-1, 3)


def render_views_psnr(stepper: Any, views: ViewSet) -> float:
    """Mean over views of the per-view PSNR (dB) of ``stepper``'s current values."""
    from ..evaluation import score_views

    res = score_views(lambda i: stepper.render(*views.view_rays(i)).reshape(
        views.height, views.width, 3), _Images(views), with_ssim=False)
    vals = [min(p, 100.0) for p in res.psnr]
    return float(np.mean(vals)) if vals else float("nan")


class _Images:
    """``views``' images as a sequence of float32 ``[H, W, 3]`` arrays, made one at a time."""

    def __init__(self, views: ViewSet) -> None:
        self.views = views

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.views.image(i)


class Diverged(Exception):
    """Raised inside the loop when the learning rate diverged (caught by ``run_loop``)."""


@dataclass
class LoopState:
    """Where the loop stands (also what a checkpoint holds, with the values)."""

    epochs_done: int = 0
    steps: int = 0
    best_psnr: float = -math.inf
    best_epoch: int = 0
    history: list[dict] = field(default_factory=list)
    stop_reason: str = ""
    train_seconds: float = 0.0
    train_rays: int = 0
    rng_state: dict | None = None
    lr_scale: float = 1.0        # product of the back-off factors applied so far
    backoffs: int = 0            # back-offs taken (validation drops and divergences)

    def to_json(self) -> str:
        d = dict(self.__dict__)
        d["best_psnr"] = None if not math.isfinite(self.best_psnr) else self.best_psnr
        return json.dumps(d)

    @classmethod
    def from_json(cls, text: str) -> LoopState:
        d = json.loads(text)
        if d.get("best_psnr") is None:
            d["best_psnr"] = -math.inf
        return cls(**d)


def save_checkpoint(path: Path, stepper: Any, best: BestValues, state: LoopState,
                    fingerprint: dict) -> None:
    """Write values, optimiser state, loop state and the number of the best values' file
    (:class:`~._best.BestValues`, made durable first) atomically to ``path``."""
    opt = {f"opt_{k}": np.asarray(v) for k, v in stepper.state().items()}
    token = best.pin()
    atomic_save_npz(path, values=stepper.values(), best_token=np.int64(token),
                    state=np.array(state.to_json()), fingerprint=np.array(json.dumps(fingerprint)),
                    **opt)
    best.pinned_by(token)


def load_checkpoint(path: Path, stepper: Any, best: BestValues, fingerprint: dict) -> LoopState:
    """Restore what :func:`save_checkpoint` wrote; ``ConfigError`` when it belongs to another run
    or its best values' file is gone."""
    try:
        with np.load(path, allow_pickle=False) as z:
            fp = json.loads(str(z["fingerprint"]))
            if fp != fingerprint:
                diff = {k: (fp.get(k), v) for k, v in fingerprint.items() if fp.get(k) != v}
                raise ConfigError(f"{path}: checkpoint belongs to a different run "
                                  f"(checkpoint vs now: {diff}); delete it or drop --resume")
            values = z["values"]
            if values.shape != stepper.values().shape:
                raise ConfigError(f"{path}: checkpoint arrays have shape {values.shape}, the "
                                  f"tree needs {stepper.values().shape}")
            stepper.set_values(values)
            del values
            if "best" in z.files:            # written before the on-disk best values: the array
                best.store(z["best"])
            else:
                best.adopt(int(z["best_token"]))
            stepper.load_state({k[4:]: z[k] for k in z.files if k.startswith("opt_")})
            return LoopState.from_json(str(z["state"]))
    except (OSError, ValueError, KeyError) as e:
        if isinstance(e, ConfigError):
            raise
        raise ConfigError(f"{path}: unreadable checkpoint ({e})") from None


def lr_factor(epoch: int, epochs: int, decay: float) -> float:
    """Exponential schedule: the learning rate of epoch ``epoch`` (1-based) is the base one
    times ``decay ** ((epoch - 1) / (epochs - 1))`` (``decay`` at the last epoch)."""
    if epochs <= 1 or decay == 1.0:
        return 1.0
    return float(decay) ** ((epoch - 1) / (epochs - 1))


def run_loop(stepper: Any, train: ViewSet, val: ViewSet | None, *, epochs: int, batch_rays: int,
             ray_tile: int, val_every: int, stop_on_decrease: bool, seed: int, checkpoint: Path | None,
             resume: bool, fingerprint: dict, log: Callable[[dict], None],
             show_progress: bool | None = None, backoffs: int = 0, backoff_factor: float = 0.5,
             lr_decay: float = 1.0, checkpoint_every_s: float = 0.0
             ) -> tuple[np.ndarray, LoopState]:
    """Optimise ``stepper``'s values on ``train``; return ``(best values, final state)`` (the
    stepper holds the best values then; the returned array is ``stepper.values()``).

    One epoch is one pass over every training pixel in a random order: the images are cut into
    ``ray_tile × ray_tile`` pixel tiles, the tiles of all images are shuffled, and each batch
    takes ``batch_rays / ray_tile²`` of them (``ray_tile = 1``: independent random pixels;
    neighbouring rays of a tile cross the same cells, which makes the kernels 2-3x faster).

    The learning rates (``stepper.lr`` and ``stepper.sigma_lr``) follow :func:`lr_factor` with
    ``lr_decay`` over the epochs, times the back-off scale.

    With ``val`` the PSNR is measured before training and every ``val_every`` epochs; the best
    values are kept. On a drop, with ``stop_on_decrease``: while fewer than ``backoffs``
    back-offs were taken, the best values are restored and the learning rates multiplied by
    ``backoff_factor`` (event ``backoff`` in the log); after that the loop stops. Without
    ``val`` the values after the last epoch are returned. A divergence (non-finite values or a
    blown-up training error) restores the best values and backs off the same way (by
    ``backoff_factor²``) while back-offs remain, else ends the loop with
    ``state.stop_reason = "diverged: ..."`` and the best (last good) values restored.

    The best values are kept in files beside ``checkpoint`` (:class:`~._best.BestValues`; in
    memory without a checkpoint); :func:`remove_best_files` deletes them with the checkpoint.

    The checkpoint is written after a validation (each ``val_every`` epochs without ``val``)
    when ``checkpoint_every_s`` seconds passed since the loop started or last wrote one (0:
    after every validation; a large tree's checkpoint, values + best + optimiser moments, is
    gigabytes), and on ``KeyboardInterrupt``; resuming from an interrupt inside an epoch replays that epoch
    (same ray order) from the values reached when it was interrupted.
    """
    scale = 1.0 / (3.0 * train.width * train.height)
    values = stepper.values()          # one read (a copy from the device for torch steppers)
    best = BestValues(values.shape, values.dtype,
                      None if checkpoint is None else checkpoint.with_suffix(""))
    state = LoopState()
    values_are_best = not (resume and checkpoint is not None and checkpoint.exists())
    if values_are_best:
        best.store(values)
    del values                         # freed before a checkpoint's values are loaded
    if not values_are_best:
        state = load_checkpoint(checkpoint, stepper, best, fingerprint)
        log({"event": "resume", "checkpoint": str(checkpoint), "epochs_done": state.epochs_done})
    rng = np.random.default_rng(seed)
    last_ckpt = time.perf_counter()

    def save_if_due() -> None:
        nonlocal last_ckpt
        if checkpoint is None or time.perf_counter() - last_ckpt < checkpoint_every_s:
            return
        save_checkpoint(checkpoint, stepper, best, state, fingerprint)
        last_ckpt = time.perf_counter()

    if state.rng_state is not None:
        rng.bit_generator.state = state.rng_state

    def validate(epoch: int) -> float | None:
        if val is None:
            return None
        t0 = time.perf_counter()
        p = render_views_psnr(stepper, val)
        state.history.append({"epoch": epoch, "val_psnr": p,
                              "val_seconds": time.perf_counter() - t0})
        return p

    if val is not None and state.epochs_done == 0 and not state.history:
        p0 = validate(0)
        state.best_psnr, state.best_epoch = p0, 0
        log({"event": "val", "epoch": 0, "val_psnr": p0})

    n_rays = train.n_rays
    k = max(1, int(ray_tile))
    n_tiles = train.n_tiles(k)
    tiles_per_batch = max(1, batch_rays // (k * k))
    steps_per_epoch = max(1, math.ceil(n_tiles / tiles_per_batch))
    bar = progress(total=(epochs - state.epochs_done) * steps_per_epoch, desc="finetune",
                   disable=None if show_progress is None else not show_progress)
    first_mse = None
    ema = None
    batches_run = 0
    base_lr = float(stepper.lr)
    base_sigma = getattr(stepper, "sigma_lr", None)

    def set_lr(epoch: int) -> None:
        f = state.lr_scale * lr_factor(epoch, epochs, lr_decay)
        stepper.lr = base_lr * f
        if base_sigma is not None:
            stepper.sigma_lr = float(base_sigma) * f

    def back_off(factor: float, why: str) -> bool:
        """Restore the best values and lower the learning rates; False when none are left."""
        if state.backoffs >= backoffs:
            return False
        nonlocal values_are_best
        state.backoffs += 1
        state.lr_scale *= factor
        stepper.set_values(best.load())
        values_are_best = True
        log({"event": "backoff", "epoch": state.epochs_done, "reason": why,
             "lr_scale": state.lr_scale, "backoffs": state.backoffs})
        return True

    def run_epoch(epoch: int, perm: np.ndarray) -> float:
        """One pass over the tiles in order ``perm``; returns the epoch's sum of squared errors."""
        nonlocal first_mse, ema, batches_run
        sse_epoch = 0.0
        for b0 in range(0, n_tiles, tiles_per_batch):
            idx = train.tile_pixels(perm[b0:b0 + tiles_per_batch], k)
            o, d, tgt = train.rays(idx)
            t0 = time.perf_counter()
            sse, bad = stepper.step(o, d, tgt, scale)
            state.train_seconds += time.perf_counter() - t0
            state.train_rays += idx.shape[0]
            state.steps += 1
            batches_run += 1
            mse = sse / (3.0 * idx.shape[0])
            sse_epoch += sse
            if bad or not math.isfinite(mse):
                raise Diverged(f"non-finite values after step {state.steps} (epoch {epoch})")
            if first_mse is None:
                first_mse = ema = mse
                batches_run = 1
            ema = (1 - _EMA) * ema + _EMA * mse
            if batches_run >= _MIN_BATCHES and ema > _DIVERGE_FACTOR * first_mse + _DIVERGE_ABS:
                raise Diverged(f"training MSE rose from {first_mse:.3g} to {ema:.3g} "
                               f"(epoch {epoch}, step {state.steps})")
            bar.update(1)
            bar.set_postfix(epoch=epoch, mse=f"{ema:.2e}")
        return sse_epoch

    try:
        while state.epochs_done < epochs and not state.stop_reason:
            epoch = state.epochs_done + 1
            set_lr(epoch)
            state.rng_state = rng.bit_generator.state
            perm = rng.permutation(n_tiles)
            sse_epoch, t_epoch, s_epoch = 0.0, time.perf_counter(), state.train_seconds
            values_are_best = False
            try:
                sse_epoch = run_epoch(epoch, perm)
            except Diverged as e:
                state.epochs_done = epoch
                if not back_off(backoff_factor ** 2, f"diverged: {e}"):
                    raise
                first_mse = ema = None
                continue
            state.epochs_done = epoch
            state.rng_state = rng.bit_generator.state
            train_mse = sse_epoch / (3.0 * n_rays)
            rec = {"event": "epoch", "epoch": epoch,
                   "train_psnr": -10 * math.log10(max(train_mse, 1e-20)),
                   "seconds": time.perf_counter() - t_epoch,
                   "rays_per_s": n_rays / max(state.train_seconds - s_epoch, 1e-9),
                   "lr": stepper.lr}
            log(rec)
            due = val_every <= 0 or epoch % val_every == 0 or epoch == epochs
            if val is None:
                best.store(stepper.values())
                values_are_best = True
                state.best_epoch = epoch
                if due:
                    save_if_due()
            elif val_every > 0 and due:
                p = validate(epoch)
                log({"event": "val", "epoch": epoch, "val_psnr": p})
                if p > state.best_psnr:
                    state.best_psnr, state.best_epoch = p, epoch
                    best.store(stepper.values())
                    values_are_best = True
                elif stop_on_decrease:
                    why = (f"validation PSNR fell from {state.best_psnr:.3f} dB "
                           f"(epoch {state.best_epoch}) to {p:.3f} dB (epoch {epoch})")
                    if not back_off(backoff_factor, why):
                        state.stop_reason = why + (f" after {state.backoffs} learning-rate "
                                                   "back-offs" if backoffs else "")
                if not state.stop_reason:
                    save_if_due()
    except Diverged as e:
        state.stop_reason = f"diverged: {e}"
    except KeyboardInterrupt:
        if checkpoint is not None:
            save_checkpoint(checkpoint, stepper, best, state, fingerprint)
            log({"event": "interrupted", "checkpoint": str(checkpoint)})
        raise
    finally:
        bar.close()
    if not state.stop_reason:
        state.stop_reason = f"finished {state.epochs_done} epochs"
    if not values_are_best:
        stepper.set_values(best.load())
    return stepper.values(), state

