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
from typing import Any

import numpy as np

from .._util import atomic_save_npz, progress
from ..errors import ConfigError
from ._best import BestValues, remove_best_files
from ._events import EventLog

__all__ = ["ViewSet", "LoopState", "LoopOptions", "FineTuneLoop", "Diverged",
           "render_views_psnr", "remove_best_files"]

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
    """Raised inside the loop when the learning rate diverged (caught by
    :meth:`FineTuneLoop.run`)."""


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
    drops: int = 0               # validations in a row below the best since the last reset

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


@dataclass(frozen=True)
class LoopOptions:
    """How :class:`FineTuneLoop` trains (:class:`~.finetune.FinetuneConfig` has the long help).

    ``epochs`` passes over every training pixel, ``batch_rays`` rays a step drawn as
    ``ray_tile × ray_tile`` pixel tiles; validation every ``val_every`` epochs (0: never);
    ``stop_on_decrease``: a validation drop (``patience`` validations in a row below the best)
    backs off (at most ``backoffs`` times, learning rates × ``backoff_factor``), then stops;
    ``lr_decay``: :func:`lr_factor`; ``seed``: the ray order. ``checkpoint`` (None: none) is
    written at a validation when ``checkpoint_every_s`` seconds passed since the last one, and
    on Ctrl-C; ``resume`` continues from it. ``show_progress``: the progress bar (None: on a
    terminal).
    """

    epochs: int
    batch_rays: int = 1 << 16
    ray_tile: int = 4
    val_every: int = 2
    stop_on_decrease: bool = True
    seed: int = 0
    backoffs: int = 0
    backoff_factor: float = 0.5
    patience: int = 1
    lr_decay: float = 1.0
    checkpoint: Path | None = None
    resume: bool = False
    checkpoint_every_s: float = 0.0
    show_progress: bool | None = None


class FineTuneLoop:
    """The fine-tuning loop: optimise ``stepper``'s values on ``train``, validating on ``val``.

    It holds the run's state: the stepper (values and optimiser moments), :class:`LoopState`
    (epoch, step, validation history, best epoch and PSNR, back-offs, ray order), the best
    values (:class:`~._best.BestValues`) and the divergence watch. :meth:`run` returns
    ``(best values, final state)``; the stepper holds the best values then (the returned array
    is ``stepper.values()``). Events go to ``events`` (:class:`~._events.EventLog`).

    One epoch (:meth:`epoch`) is one pass over every training pixel in a random order: the
    images are cut into ``ray_tile × ray_tile`` pixel tiles, the tiles of all images are
    shuffled, and each :meth:`step` takes ``batch_rays / ray_tile²`` of them (``ray_tile = 1``:
    independent random pixels; neighbouring rays of a tile cross the same cells, which makes
    the kernels 2-3x faster).

    The learning rates (``stepper.lr`` and ``stepper.sigma_lr``) follow :func:`lr_factor` with
    ``lr_decay`` over the epochs, times the back-off scale.

    With ``val`` the PSNR is measured before training and every ``val_every`` epochs
    (:meth:`validate`); the best values are kept, the initial ones (epoch 0) being the first
    candidate, so the values returned never validate below the initial ones. A validation no
    better than the best is a drop once ``patience`` of them came in a row (training goes on
    from the current values until then); on a drop, with ``stop_on_decrease``: while fewer
    than ``backoffs`` back-offs were taken, the best values are restored and the learning
    rates multiplied by ``backoff_factor`` (:meth:`back_off`, event ``backoff``); after that the
    loop stops. Without ``val`` the values after the last epoch are returned. A divergence
    (non-finite values or a blown-up training error) restores the best values and backs off
    the same way (by ``backoff_factor²``) while back-offs remain, else ends the loop with
    ``state.stop_reason = "diverged: ..."`` and the best (last good) values restored.

    The best values are kept in files beside ``checkpoint`` (:class:`~._best.BestValues`; in
    memory without a checkpoint); :func:`remove_best_files` deletes them with the checkpoint.

    The checkpoint is written after a validation (each ``val_every`` epochs without ``val``)
    when ``checkpoint_every_s`` seconds passed since the loop started or last wrote one (0:
    after every validation; a large tree's checkpoint, values + best + optimiser moments, is
    gigabytes), and on ``KeyboardInterrupt``; resuming from an interrupt inside an epoch replays
    that epoch (same ray order) from the values reached when it was interrupted.
    """

    def __init__(self, stepper: Any, train: ViewSet, val: ViewSet | None, options: LoopOptions,
                 fingerprint: dict, events: EventLog | None = None) -> None:
        self.stepper, self.train, self.val, self.opts = stepper, train, val, options
        self.fingerprint = fingerprint
        self.events = events if events is not None else EventLog(None)
        self.scale = 1.0 / (3.0 * train.width * train.height)   # per-pixel mean of one image
        self.state = LoopState()
        self.best: BestValues | None = None
        self.values_are_best = True
        self.tile = max(1, int(options.ray_tile))
        self.n_tiles = train.n_tiles(self.tile)
        self.tiles_per_batch = max(1, options.batch_rays // (self.tile * self.tile))
        self.rng = np.random.default_rng(options.seed)
        self._first_mse: float | None = None     # the divergence watch: first batch MSE,
        self._ema: float | None = None           # its smoothed value, batches since a reset
        self._batches = 0
        self._last_ckpt = time.perf_counter()
        self._bar: Any = None
        self._base_lr = float(stepper.lr)
        self._base_sigma = getattr(stepper, "sigma_lr", None)

    @property
    def finished(self) -> bool:
        """All epochs run, or the loop stopped (``state.stop_reason``)."""
        return self.state.epochs_done >= self.opts.epochs or bool(self.state.stop_reason)

    def run(self) -> tuple[np.ndarray, LoopState]:
        """Train until :attr:`finished`; returns ``(best values, final state)``."""
        self._start()
        steps_per_epoch = max(1, math.ceil(self.n_tiles / self.tiles_per_batch))
        show = self.opts.show_progress
        self._bar = progress(total=(self.opts.epochs - self.state.epochs_done) * steps_per_epoch,
                             desc="finetune", disable=None if show is None else not show)
        try:
            while not self.finished:
                self._next_epoch()
        except Diverged as e:
            self.state.stop_reason = f"diverged: {e}"
        except KeyboardInterrupt:
            if self.opts.checkpoint is not None:
                save_checkpoint(self.opts.checkpoint, self.stepper, self.best, self.state,
                                self.fingerprint)
                self.events({"event": "interrupted", "checkpoint": str(self.opts.checkpoint)})
            raise
        finally:
            self._bar.close()
        if not self.state.stop_reason:
            self.state.stop_reason = f"finished {self.state.epochs_done} epochs"
        if not self.values_are_best:
            self.stepper.set_values(self.best.load())
        return self.stepper.values(), self.state

    def _start(self) -> None:
        """Keep the initial values as the best, or resume from the checkpoint; validate the
        initial values (epoch 0) unless resumed past that."""
        ckpt = self.opts.checkpoint
        values = self.stepper.values()   # one read (a copy from the device for torch steppers)
        self.best = BestValues(values.shape, values.dtype,
                               None if ckpt is None else ckpt.with_suffix(""))
        self.values_are_best = not (self.opts.resume and ckpt is not None and ckpt.exists())
        if self.values_are_best:
            self.best.store(values)
        del values                       # freed before a checkpoint's values are loaded
        if not self.values_are_best:
            self.state = load_checkpoint(ckpt, self.stepper, self.best, self.fingerprint)
            self.events({"event": "resume", "checkpoint": str(ckpt),
                         "epochs_done": self.state.epochs_done})
        self._last_ckpt = time.perf_counter()
        if self.state.rng_state is not None:
            self.rng.bit_generator.state = self.state.rng_state
        if self.val is not None and self.state.epochs_done == 0 and not self.state.history:
            p0 = self.validate(0)
            self.state.best_psnr, self.state.best_epoch = p0, 0
            self.events({"event": "val", "epoch": 0, "val_psnr": p0})

    def _next_epoch(self) -> None:
        """Run epoch ``epochs_done + 1``, then keep its values or back off; a divergence backs
        off (and the epoch counts as run) while back-offs remain, else propagates."""
        epoch = self.state.epochs_done + 1
        try:
            sse, seconds, step_seconds = self.epoch(epoch)
        except Diverged as e:
            self.state.epochs_done = epoch
            if not self.back_off(self.opts.backoff_factor ** 2, f"diverged: {e}"):
                raise
            self._first_mse = self._ema = None
            return
        self.state.epochs_done = epoch
        self.state.rng_state = self.rng.bit_generator.state
        n_rays = self.train.n_rays
        train_mse = sse / (3.0 * n_rays)
        self.events({"event": "epoch", "epoch": epoch,
                     "train_psnr": -10 * math.log10(max(train_mse, 1e-20)), "seconds": seconds,
                     "rays_per_s": n_rays / max(step_seconds, 1e-9), "lr": self.stepper.lr})
        self.keep_best(epoch)

    def epoch(self, epoch: int) -> tuple[float, float, float]:
        """One pass over the training tiles in a fresh random order at epoch ``epoch``'s
        learning rates; returns ``(sum of squared errors, seconds, seconds in the steps)``."""
        st = self.state
        f = st.lr_scale * lr_factor(epoch, self.opts.epochs, self.opts.lr_decay)
        self.stepper.lr = self._base_lr * f
        if self._base_sigma is not None:
            self.stepper.sigma_lr = float(self._base_sigma) * f
        st.rng_state = self.rng.bit_generator.state
        perm = self.rng.permutation(self.n_tiles)
        t_epoch, s_epoch = time.perf_counter(), st.train_seconds
        self.values_are_best = False
        sse = 0.0
        for b0 in range(0, self.n_tiles, self.tiles_per_batch):
            sse += self.step(perm[b0:b0 + self.tiles_per_batch], epoch)
        return sse, time.perf_counter() - t_epoch, st.train_seconds - s_epoch

    def step(self, tiles: np.ndarray, epoch: int) -> float:
        """One optimisation step on the pixels of ``tiles``; returns the batch's sum of squared
        errors. Raises :class:`Diverged` on non-finite values or a blown-up training error."""
        st = self.state
        idx = self.train.tile_pixels(tiles, self.tile)
        o, d, tgt = self.train.rays(idx)
        t0 = time.perf_counter()
        sse, bad = self.stepper.step(o, d, tgt, self.scale)
        st.train_seconds += time.perf_counter() - t0
        st.train_rays += idx.shape[0]
        st.steps += 1
        self._batches += 1
        mse = sse / (3.0 * idx.shape[0])
        if bad or not math.isfinite(mse):
            raise Diverged(f"non-finite values after step {st.steps} (epoch {epoch})")
        if self._first_mse is None:
            self._first_mse = self._ema = mse
            self._batches = 1
        self._ema = (1 - _EMA) * self._ema + _EMA * mse
        blown = self._ema > _DIVERGE_FACTOR * self._first_mse + _DIVERGE_ABS
        if self._batches >= _MIN_BATCHES and blown:
            raise Diverged(f"training MSE rose from {self._first_mse:.3g} to {self._ema:.3g} "
                           f"(epoch {epoch}, step {st.steps})")
        self._bar.update(1)
        self._bar.set_postfix(epoch=epoch, mse=f"{self._ema:.2e}")
        return sse

    def validate(self, epoch: int) -> float | None:
        """Mean validation PSNR (dB) of the current values, noted in the history (None
        without validation views)."""
        if self.val is None:
            return None
        t0 = time.perf_counter()
        p = render_views_psnr(self.stepper, self.val)
        self.state.history.append({"epoch": epoch, "val_psnr": p,
                                   "val_seconds": time.perf_counter() - t0})
        return p

    def keep_best(self, epoch: int) -> None:
        """After epoch ``epoch``: without validation its values are the best; with it, validate
        when due, keep better values, and on a drop back off or stop; then the checkpoint."""
        st, opts = self.state, self.opts
        due = opts.val_every <= 0 or epoch % opts.val_every == 0 or epoch == opts.epochs
        if self.val is None:
            self._store_best(epoch)
            if due:
                self._save_if_due()
            return
        if opts.val_every <= 0 or not due:
            return
        p = self.validate(epoch)
        self.events({"event": "val", "epoch": epoch, "val_psnr": p})
        if p > st.best_psnr:
            st.best_psnr, st.drops = p, 0
            self._store_best(epoch)
        elif opts.stop_on_decrease:
            st.drops += 1
            if st.drops >= opts.patience:
                self._drop(p, epoch)
        if not st.stop_reason:
            self._save_if_due()

    def _drop(self, p: float, epoch: int) -> None:
        """Epoch ``epoch``'s validation PSNR ``p`` (dB) is the ``patience``-th in a row below
        the best: back off, or stop when no back-offs are left."""
        st, opts = self.state, self.opts
        why = (f"validation PSNR fell from {st.best_psnr:.3f} dB (epoch {st.best_epoch}) to "
               f"{p:.3f} dB (epoch {epoch})"
               + (f", below its best {st.drops} validations in a row" if opts.patience > 1
                  else ""))
        if not self.back_off(opts.backoff_factor, why):
            st.stop_reason = why + (f" after {st.backoffs} learning-rate back-offs"
                                    if opts.backoffs else "")

    def back_off(self, factor: float, why: str) -> bool:
        """Restore the best values and lower the learning rates by ``factor``; False when no
        back-offs are left."""
        st = self.state
        if st.backoffs >= self.opts.backoffs:
            return False
        st.backoffs += 1
        st.lr_scale *= factor
        st.drops = 0
        self.stepper.set_values(self.best.load())
        self.values_are_best = True
        self.events({"event": "backoff", "epoch": st.epochs_done, "reason": why,
                     "lr_scale": st.lr_scale, "backoffs": st.backoffs})
        return True

    def _store_best(self, epoch: int) -> None:
        self.best.store(self.stepper.values())
        self.values_are_best = True
        self.state.best_epoch = epoch

    def _save_if_due(self) -> None:
        """Write the checkpoint when ``checkpoint_every_s`` passed since the last one."""
        ckpt = self.opts.checkpoint
        if ckpt is None or time.perf_counter() - self._last_ckpt < self.opts.checkpoint_every_s:
            return
        save_checkpoint(ckpt, self.stepper, self.best, self.state, self.fingerprint)
        self._last_ckpt = time.perf_counter()
