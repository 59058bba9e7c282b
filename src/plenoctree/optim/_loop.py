"""The epoch loop of fine-tuning: random ray batches, validation, early stop, divergence, resume.

Used by :func:`plenoctree.optim.finetuning.finetune`; works with every stepper of
:mod:`._steppers`. A host stepper (numba) gets each batch's rays made on the CPU and returns the
step's figures at once; a device stepper (torch, Triton: :mod:`._device_stepper`) gets a slice
of a tile order drawn on the device and writes its figures into a device buffer the loop reads
back every ``read_every`` steps and at the end of an epoch, where the divergence watch runs
over them in order (on host batches, as a host stepper, when the photos do not fit on the
device).
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
from ._best import BestValues, DeviceBestValues, remove_best_files
from ._rules import FIG_BAD, FIG_RAYS, FIG_SSE
from ._events import EventLog
from ._views import ViewSet, render_views_psnr

__all__ = ["ViewSet", "LoopState", "LoopOptions", "FineTuneLoop", "Diverged",
           "render_views_psnr", "remove_best_files"]

_EMA = 0.2            # smoothing of the batch MSE for the divergence test
_DIVERGE_FACTOR = 4.0  # smoothed batch MSE above factor * first-batch MSE + _DIVERGE_ABS ...
_DIVERGE_ABS = 1e-3    # ... means the learning rate diverged
_MIN_BATCHES = 5


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
    terminal). ``read_every``: a device stepper's step figures (error, non-finite values) are
    read back every this many steps and at the end of an epoch (the divergence watch and the
    progress bar follow them; a step itself never waits for the device). ``stop_at`` (a
    ``time.perf_counter()`` value; None: no time limit): from the second epoch on, the epoch
    ends at the step after which the last validation's length would pass it, and the loop
    after it (:meth:`FineTuneLoop.out_of_time`); that epoch is validated as the last one. At
    least one whole epoch runs.
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
    read_every: int = 32
    stop_at: float | None = None


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
        # a device stepper trains on photos uploaded once when they fit, else on host batches
        self._dev = (_DeviceRun(stepper, train, max(1, int(options.read_every)))
                     if hasattr(stepper, "step_tiles") and stepper.fits(train.images.nbytes)
                     else None)
        self._t_mark = time.perf_counter()       # device steps: counted up to here
        self._epoch_s = 0.0                      # the longest epoch so far (seconds)
        self._cut = False                        # an epoch was cut short by stop_at

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
        self.best = self._new_best(None if ckpt is None else ckpt.with_suffix(""))
        self.values_are_best = not (self.opts.resume and ckpt is not None and ckpt.exists())
        if self.values_are_best:
            self.best.store(self._best_source())
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
        self._epoch_s = max(self._epoch_s, seconds)
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
        perm = self.tile_order()
        t_epoch, s_epoch = time.perf_counter(), st.train_seconds
        self.values_are_best = False
        sse = 0.0
        self._t_mark = time.perf_counter()
        for b0 in range(0, self.n_tiles, self.tiles_per_batch):
            if epoch > 1 and self._time_is_up():
                self._cut = True            # the time limit: this epoch ends here
                break
            sse += self.step(perm[b0:b0 + self.tiles_per_batch], epoch)
            if self._dev is not None and self._dev.full:
                sse += self.read_figures(epoch)
        if self._dev is not None and self._dev.pending:
            sse += self.read_figures(epoch)
        return sse, time.perf_counter() - t_epoch, st.train_seconds - s_epoch

    def tile_order(self) -> Any:
        """An epoch's random order of the training tiles, from the loop's generator: a numpy
        permutation, or for a device stepper one drawn on the device (seeded from it)."""
        if self._dev is None:
            return self.rng.permutation(self.n_tiles)
        return self.stepper.tile_order(self.n_tiles, int(self.rng.integers(0, 2 ** 63 - 1)))

    def step(self, tiles: Any, epoch: int) -> float:
        """One optimisation step on the pixels of ``tiles`` (a slice of :meth:`tile_order`);
        returns the batch's sum of squared errors. Raises :class:`Diverged` on non-finite
        values or a blown-up training error. A device stepper's step only queues work on the
        device and returns 0.0: its figures are counted by :meth:`read_figures`."""
        st = self.state
        if self._dev is not None:
            self._dev.step(tiles, self.tile, self.scale)
            st.steps += 1
            return 0.0
        idx = self.train.tile_pixels(tiles, self.tile)
        o, d, tgt = self.train.rays(idx)
        t0 = time.perf_counter()
        sse, bad = self.stepper.step(o, d, tgt, self.scale)
        st.train_seconds += time.perf_counter() - t0
        st.train_rays += idx.shape[0]
        st.steps += 1
        self._watch(sse, idx.shape[0], bad, epoch, st.steps)
        return sse

    def read_figures(self, epoch: int) -> float:
        """A device stepper's figures of the steps since the last read (the host waits for the
        device here, and only here): their time and rays are counted and the divergence watch
        runs over them in order; returns their sum of squared errors."""
        st = self.state
        figs = self._dev.read()
        now = time.perf_counter()
        st.train_seconds += now - self._t_mark
        self._t_mark = now
        first = st.steps - len(figs) + 1
        sse = 0.0
        for i, row in enumerate(figs):
            n = int(row[FIG_RAYS])
            st.train_rays += n
            self._watch(float(row[FIG_SSE]), max(n, 1), int(row[FIG_BAD]), epoch, first + i)
            sse += float(row[FIG_SSE])
        return sse

    def _watch(self, sse: float, n: int, bad: int, epoch: int, step: int) -> None:
        """The divergence watch on step ``step``'s figures: ``sse`` over ``n`` rays, ``bad``
        non-finite values written; raises :class:`Diverged`."""
        self._batches += 1
        mse = sse / (3.0 * n)
        if bad or not math.isfinite(mse):
            raise Diverged(f"non-finite values after step {step} (epoch {epoch})")
        if self._first_mse is None:
            self._first_mse = self._ema = mse
            self._batches = 1
        self._ema = (1 - _EMA) * self._ema + _EMA * mse
        blown = self._ema > _DIVERGE_FACTOR * self._first_mse + _DIVERGE_ABS
        if self._batches >= _MIN_BATCHES and blown:
            raise Diverged(f"training MSE rose from {self._first_mse:.3g} to {self._ema:.3g} "
                           f"(epoch {epoch}, step {step})")
        self._bar.update(1)
        self._bar.set_postfix(epoch=epoch, mse=f"{self._ema:.2e}")

    def validate(self, epoch: int) -> float | None:
        """Mean validation PSNR (dB) of the current values, noted in the history (None
        without validation views)."""
        if self.val is None:
            return None
        t0 = time.perf_counter()
        p = render_views_psnr(self.stepper, self.val, keep=True)
        self.state.history.append({"epoch": epoch, "val_psnr": p,
                                   "val_seconds": time.perf_counter() - t0})
        return p

    def keep_best(self, epoch: int) -> None:
        """After epoch ``epoch``: without validation its values are the best; with it, validate
        when due, keep better values, and on a drop back off or stop; then the checkpoint.
        After the last epoch (``epochs``, or the time limit's: :meth:`out_of_time`) the values
        are validated, better ones are kept as the live values (not copied: the loop ends) and
        no checkpoint is written (the output follows at once)."""
        st, opts = self.state, self.opts
        late = self.out_of_time(epoch)
        last = epoch >= opts.epochs or late
        due = opts.val_every <= 0 or epoch % opts.val_every == 0 or last
        if self.val is None:
            self._take_best(epoch, copy=not last)
            if due and not last:
                self._save_if_due()
        elif opts.val_every > 0 and due:
            p = self.validate(epoch)
            self.events({"event": "val", "epoch": epoch, "val_psnr": p})
            if p > st.best_psnr:
                st.best_psnr, st.drops = p, 0
                self._take_best(epoch, copy=not last)
            elif opts.stop_on_decrease:
                st.drops += 1
                if st.drops >= opts.patience:
                    self._drop(p, epoch)
            if not st.stop_reason and not last:
                self._save_if_due()
        if late and not st.stop_reason:
            st.stop_reason = (f"time limit: stopped {'within' if self._cut else 'after'} "
                              f"epoch {epoch}")

    def out_of_time(self, epoch: int) -> bool:
        """Whether epoch ``epoch`` (just run) must be the last one for ``stop_at``: it was cut
        short, or after this epoch's validation and the next one's there would be time for
        less than a tenth of an epoch. False when ``epochs`` ends the loop anyway."""
        if self._cut:
            return True
        if self.opts.stop_at is None or epoch >= self.opts.epochs:
            return False
        return (time.perf_counter() + 2.0 * self._val_s() + 0.1 * self._epoch_s
                > self.opts.stop_at)

    def _time_is_up(self) -> bool:
        """Whether the next step would leave too little of ``stop_at`` for the validation
        that ends the loop (as long as the last one)."""
        return (self.opts.stop_at is not None
                and time.perf_counter() + self._val_s() > self.opts.stop_at)

    def _val_s(self) -> float:
        """Seconds of the last validation (0 without one)."""
        return self.state.history[-1]["val_seconds"] if self.state.history else 0.0

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

    def _new_best(self, stem: Path | None) -> BestValues:
        """Where the best values are kept: on the device beside the live ones when the stepper
        is a device stepper and a copy fits there, else on disk beside the checkpoint (in
        memory without one)."""
        live = getattr(self.stepper, "device_values", None)
        if live is not None:
            t = live()
            if self.stepper.fits(t.numel() * t.element_size()):
                return DeviceBestValues(t, stem)
        values = self.stepper.values()
        return BestValues(values.shape, values.dtype, stem)

    def _best_source(self) -> Any:
        """The live values as the best copy takes them (a device tensor, or numpy)."""
        if isinstance(self.best, DeviceBestValues):
            return self.stepper.device_values()
        return self.stepper.values()

    def _store_best(self, epoch: int) -> None:
        self.best.store(self._best_source())
        self.values_are_best = True
        self.state.best_epoch = epoch

    def _take_best(self, epoch: int, copy: bool) -> None:
        """Epoch ``epoch``'s values are the best: kept as a copy, or (``copy`` False, after
        the last epoch) only marked as the live values to return."""
        if copy:
            self._store_best(epoch)
        else:
            self.values_are_best = True
            self.state.best_epoch = epoch

    def _save_if_due(self) -> None:
        """Write the checkpoint when ``checkpoint_every_s`` passed since the last one."""
        ckpt = self.opts.checkpoint
        if ckpt is None or time.perf_counter() - self._last_ckpt < self.opts.checkpoint_every_s:
            return
        save_checkpoint(ckpt, self.stepper, self.best, self.state, self.fingerprint)
        self._last_ckpt = time.perf_counter()


class _DeviceRun:
    """A device stepper's side of a run: the training photos on the device (uploaded once),
    the figures buffer (``read_every`` rows) and the steps written to it since the last read."""

    def __init__(self, stepper: Any, train: ViewSet, read_every: int) -> None:
        self.stepper = stepper
        self.views = stepper.device_views(train)
        self.figs = stepper.new_figures(read_every)
        self.pending = 0

    @property
    def full(self) -> bool:
        return self.pending >= self.figs.shape[0]

    def step(self, tiles: Any, k: int, scale: float) -> None:
        self.stepper.step_tiles(self.views, tiles, k, scale, self.figs, self.pending)
        self.pending += 1

    def read(self) -> np.ndarray:
        """float64 ``[pending, 4]`` figures (``_device_twins.FIG_*`` columns); one read back."""
        out = self.stepper.read_figures(self.figs, self.pending)
        self.pending = 0
        return out
