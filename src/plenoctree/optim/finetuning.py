"""Fine-tune a PlenOctree's leaf values on the training photos (paper §4.3).

The tree structure stays fixed; σ and the colour coefficients of every leaf are optimised with
the NeRF loss on batches of random rays drawn from all training images (as random
``ray_tile × ray_tile`` pixel tiles: an epoch still uses every pixel once, and neighbouring rays
share the cells they cross, which makes the kernels 2-3x faster than independent pixels).

Loss and learning-rate units: a batch of rays ``R`` contributes
``L = Σ_{r∈R} Σ_ch (C_r - C*_r)² / (3 H W)`` (H×W = training image size after
``downscale``): the per-pixel mean squared error of one image, as in the original code, which
took one step per whole image. So an epoch of batches applies the same total gradient as the
original's epoch of per-image steps, and ``lr = 1e7`` is the paper's SGD learning rate whatever
``batch_rays`` is. Adam / RMSprop (defaults 2e-2 / 1e-3) are lazy (only cells a batch reaches
are updated); σ gets its own rate ``lr_sigma / h`` (h = finest leaf side). They would be
scale-free (a step moving each value by about ``lr``, each leaf's opacity by about
``lr_sigma``) where a value's RMS gradient is large against their ε = 1e-8, but with this loss
it rarely is: on lego's refined tree at 400² the median is ~2e-11 (99.999 % of the values
below ε), and Adam steps as SGD with momentum at ``lr / ε`` for nearly every value. The run
logs which (event ``gradient_scale``).

Validation picks the tree that is saved: the best of the input tree and the validated epochs.
It runs on the dataset's own val split where there is one; else, for a capture of a place
(``Dataset.unbounded``: a walk-around, where validation on views that stayed in training rose
while the test PSNR fell), on every ``holdout_every``-th training view (8, with at least
:data:`HOLDOUT_MIN_VIEWS` views), held out of the updates so a drop shows overfitting; else on
training views (flower: holding 4 of its 29 photos out gained +0.41 dB on the test views
instead of +0.76); never on the test split.

Defaults (Adam 2e-2 for colour and opacity, constant, 3 back-offs) chosen by measurement: on
the procedural demo scene the paper's SGD 1e7 diverges (validation 34.97 → 27.46 dB, the input
kept; with back-offs +0.16 dB) while Adam gains +2.1 dB in 6 epochs; on lego's refined tree
(400², 100 validation views) Adam 2e-2 beats 1e-2 (epoch 10: 33.93 vs 33.79 dB) and a ×0.1
decay over 20 epochs loses (epoch 16: 33.68 vs 33.91 dB); see docs/tuning.md, "Fine-tuning".

>>> cfg = FinetuneConfig(tree="tree.npz", data="data/lego", out="tree_ft.npz", epochs=4)  # doctest: +SKIP
>>> result = finetune(cfg)                                                          # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .._bounds import check_bounds
from ..errors import ConfigError, DatasetError

__all__ = ["FinetuneConfig", "FinetuneResult", "finetune", "held_out_views"]

_PRECISIONS = ("auto", "fp16", "fp32")

DEFAULT_EPOCHS = 12
"""The one fine-tuning epoch default (``finetune``, ``run``, ``demo``): on lego's refined tree
Adam 2e-2 has 99 % of its validation gain by epoch 12 (32.06 → 33.955 dB; best 33.971 at epoch
18). A validation drop backs the learning rate off (``backoffs``), then stops."""

#: Training views validated on when the dataset has no val split of its own and none are held
#: out (``holdout_every`` 0, or too few views): a guard against divergence, not a measure of
#: generalisation.
TRAIN_VAL_VIEWS = 8

#: Training views a dataset needs before ``holdout_every`` holds any out of the updates; with
#: fewer, validation is on :data:`TRAIN_VAL_VIEWS` training views that stay in training.
HOLDOUT_MIN_VIEWS = 8

#: ``holdout_every``'s automatic value for a capture of a place: one training view in 8 is
#: held out for validation.
DEFAULT_HOLDOUT_EVERY = 8


def _f(default: Any, help: str, **kw: Any) -> Any:
    return field(default=default, metadata={"help": help}, **kw)


@dataclass
class FinetuneConfig:
    """Options of :func:`finetune`; each field's ``help`` metadata is its ``--help`` text."""

    tree: str | os.PathLike = _f(None, "input tree (.npz, native or svox layout)")
    data: str | os.PathLike = _f(None, "dataset folder (Blender / NeRF-synthetic format)")
    out: str | os.PathLike = _f(None, "output tree (.npz), written atomically")
    epochs: int = _f(DEFAULT_EPOCHS, "maximum number of epochs (passes over every training "
                                     "pixel; stops earlier on validation drops: see patience "
                                     "and backoffs)")
    lr: float | None = _f(None, "learning rate; default 1e7 for sgd (paper units: per-pixel mean "
                                "loss of one image), 2e-2 for adam, 1e-3 for rmsprop")
    optimizer: str = _f("adam", "adam (default; with its eps 1e-8 against this loss's tiny "
                                "gradients it mostly steps as SGD with momentum, lr/eps: the "
                                "log says how much), rmsprop or sgd (the paper's; lazy: "
                                "touched cells only)")
    lr_sigma: float | None = _f(None, "adam / rmsprop: learning rate of σ in opacity units (a step "
                                      "changes σ·h by about this, h = the finest leaf side); "
                                      "default: the same number as lr (sgd: σ uses lr)")
    lr_decay: float = _f(1.0, "multiply the learning rate by this over the epochs (exponential "
                              "schedule; 1 = constant)")
    minutes: float = _f(0.0, "time limit in minutes from the command's start (0 = none): the "
                             "epochs stop in time for a last validation and saving the tree "
                             "(the test PSNR after it not counted; at least one epoch runs)")
    backoffs: int = _f(3, "on a validation drop (see patience; or a divergence) restore the "
                          "best values and halve the learning rate, up to this many times, "
                          "before stopping")
    batch_rays: int = _f(1 << 16, "rays per optimisation step, drawn at random from all images")
    ray_tile: int = _f(4, "draw rays as random k x k pixel tiles (1 = independent pixels); "
                          "every pixel is still used once per epoch, and tiles run 2-3x faster")
    downscale: int = _f(1, "downscale the images by this integer factor (area averaging)")
    val_every: int = _f(2, "validate every this many epochs (0 = never: keep the last values)")
    holdout_every: int = _f(
        -1,
        "when the dataset has no val split of its own (none, or its val views are the test "
        "views: LLFF, COLMAP, nerfstudio, instant-ngp): hold every this-many-th training view "
        "out of the updates and validate on those (at least one; only with at least "
        f"{HOLDOUT_MIN_VIEWS} training views), so the best epoch, which is kept (the input tree "
        "too), is chosen on views fine-tuning cannot overfit; 0 = off: validate on "
        f"{TRAIN_VAL_VIEWS} training views that stay in training (a guard against divergence "
        f"only, as with fewer views); -1 = {DEFAULT_HOLDOUT_EVERY} for a capture of a place "
        "(a 360° walk-around), else 0. A dataset's own val split is used as it is; the test "
        "split never")
    val_fraction: float = _f(0.0, "when the dataset has no val split of its own: a share in "
                                  "(0, 1) holds that share of the training images, drawn at "
                                  "random (seed), out for validation instead of every "
                                  "holdout_every-th; 0 = by holdout_every")
    val_views: int = _f(0, "validate on this many evenly spaced views (0 = all of a val split or "
                           f"of the held-out views, {TRAIN_VAL_VIEWS} training views)")
    patience: int = _f(1, "a validation drop counts once the validation PSNR stayed below its "
                          "best for this many validations in a row (each val_every epochs "
                          "apart); then back off, or stop when the back-offs are spent "
                          "(1 = at the first drop)")
    test_views: int = _f(0, "measure test PSNR on this many evenly spaced views (0 = all; "
                            "-1 = skip the test split)")
    continue_on_decrease: bool = _f(False, "keep going when the validation PSNR drops (the best "
                                           "values are still the ones saved)")
    precision: str = _f("auto", "saved precision: fp16, fp32 or auto (that of the input file)")
    stop_thresh: float = _f(0.01, "early ray termination when transmittance < this (0 = off)")
    background: tuple[float, float, float] | None = _f(
        None, "background colour R,G,B in [0,1] (default: the dataset's: black for real photos, "
              "white for renders)")
    backend: str = _f("auto", "auto (numba on the CPU, the Triton kernel on CUDA), numba, "
                              "triton or torch (the twin)")
    device: str = _f("auto", "auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N")
    seed: int = _f(0, "random seed (ray order, hold-out split)")
    checkpoint: str | os.PathLike | None = _f(
        None, "checkpoint file (default: <out stem>.ckpt.npz), written at a validation (see "
              "checkpoint_minutes) and on Ctrl-C")
    checkpoint_minutes: float = _f(5.0, "write the checkpoint at a validation only when this "
                                        "many minutes passed since the last one (0 = at every "
                                        "validation); on lego's refined tree one costs ~18 s")
    resume: bool = _f(False, "continue from the checkpoint if it exists")
    log: str | os.PathLike | None = _f(None, "JSON-lines log (default: <out stem>.log.jsonl); "
                                             "its curve goes to <out stem>.curve.png")
    show_progress: bool | None = _f(None, "progress bar (default: when stderr is a terminal)")
    verbose: bool = _f(True, "log one line per epoch / validation at INFO (off: at DEBUG)")

    def validated(self) -> FinetuneConfig:
        """Check value ranges (upper ends: :mod:`plenoctree._bounds`); raises
        :class:`ConfigError`."""
        for name in ("tree", "data", "out"):
            if getattr(self, name) in (None, ""):
                raise ConfigError(f"finetune: {name} is required")
        for name, lo in (("epochs", 0), ("batch_rays", 1), ("ray_tile", 1), ("downscale", 1),
                         ("val_every", 0), ("backoffs", 0), ("patience", 1),
                         ("val_views", 0), ("test_views", -1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ConfigError(f"finetune: {name} must be an integer >= {lo}, got {v!r}")
        if self.optimizer not in ("sgd", "adam", "rmsprop"):
            raise ConfigError(f"finetune: optimizer must be sgd, adam or rmsprop, got "
                              f"{self.optimizer!r}")
        if self.lr is not None and not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr)
                                        and self.lr > 0):
            raise ConfigError(f"finetune: lr must be a finite number > 0, got {self.lr!r}")
        if self.lr_sigma is not None and not (isinstance(self.lr_sigma, (int, float))
                                              and math.isfinite(self.lr_sigma)
                                              and self.lr_sigma > 0):
            raise ConfigError(f"finetune: lr_sigma must be a finite number > 0, got "
                              f"{self.lr_sigma!r}")
        if not (isinstance(self.lr_decay, (int, float)) and 0.0 < float(self.lr_decay) <= 1.0):
            raise ConfigError(f"finetune: lr_decay must be in (0, 1], got {self.lr_decay!r}")
        if not (isinstance(self.minutes, (int, float)) and math.isfinite(self.minutes)
                and self.minutes >= 0):
            raise ConfigError(f"finetune: minutes must be a number >= 0, got {self.minutes!r}")
        if not (isinstance(self.checkpoint_minutes, (int, float))
                and math.isfinite(self.checkpoint_minutes) and self.checkpoint_minutes >= 0):
            raise ConfigError(f"finetune: checkpoint_minutes must be a number >= 0, got "
                              f"{self.checkpoint_minutes!r}")
        h = self.holdout_every
        if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < -1 or h == 1:
            raise ConfigError(f"finetune: holdout_every must be -1 (auto), 0 (off) or an integer "
                              f">= 2 (1 would hold every training view out), got {h!r}")
        if not 0.0 <= float(self.val_fraction) < 1.0:
            raise ConfigError(f"finetune: val_fraction must be in [0, 1), got {self.val_fraction!r}")
        if self.precision not in _PRECISIONS:
            raise ConfigError(f"finetune: precision must be one of {_PRECISIONS}, got "
                              f"{self.precision!r}")
        if not 0.0 <= float(self.stop_thresh) < 1.0:
            raise ConfigError(f"finetune: stop_thresh must be in [0, 1), got {self.stop_thresh!r}")
        return check_bounds(self, "finetune: ")


@dataclass
class FinetuneResult:
    """What :func:`finetune` did. PSNRs in dB (``None`` when not measured).

    ``val_psnr_before`` / ``val_psnr_best``: the validation PSNR of the input tree and of the
    tree saved (the best validated, the input included), on the views ``validation`` names:
    ``"val split"`` (the dataset's own), ``"held-out training views"`` (``held_out``, kept out
    of the updates), ``"training views (in training)"`` or ``"none"``.
    """

    out: Path
    test_psnr_before: float | None
    test_psnr_after: float | None
    val_psnr_before: float | None
    val_psnr_best: float | None
    best_epoch: int
    epochs_run: int
    steps: int
    stop_reason: str
    backoffs: int
    wall_seconds: float
    train_rays_per_second: float
    backend: str
    history: list[dict] = field(default_factory=list)
    device: str = "cpu"
    #: Adam / RMSprop: the touched values' RMS gradient against ε (``gradient_scale``).
    gradient_scale: dict | None = None
    #: What validation ran on (see above).
    validation: str = "none"
    #: Names of the training views held out of the updates for validation.
    held_out: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        d = asdict(self)
        d["out"] = str(self.out)
        return d


def _check_tree(tree: Any, path: Any) -> None:
    if tree.n_leaves == 0:
        raise ConfigError(f"{path}: the tree has no leaves: nothing to fine-tune")
    leaves = tree.child == 0
    vals = tree.data[leaves]
    if not np.isfinite(vals).all():
        bad = int((~np.isfinite(vals)).any(axis=-1).sum())
        raise ConfigError(f"{path}: {bad} leaves hold NaN or infinite values; fix or rebuild "
                          "the tree before fine-tuning")
    if not (vals[:, -1] > 0).any():
        raise ConfigError(f"{path}: no leaf has density > 0 (an empty tree): nothing to fine-tune")


def _check_overlap(tree: Any, data: Any, tree_path: Any) -> None:
    tb = np.asarray(tree.bbox, dtype=np.float64)
    db = np.asarray(data.scene_bbox, dtype=np.float64)
    if np.any(tb[1] <= db[0]) or np.any(db[1] <= tb[0]):
        raise ConfigError(f"{tree_path}: the tree's box {tb.round(3).tolist()} does not overlap "
                          f"the scene box {db.round(3).tolist()} of dataset {data.root}: wrong "
                          "tree or dataset?")


def _load_split(root: Any, split: str, cfg: FinetuneConfig, views: int = 0) -> Any:
    """Split ``split`` of ``root``: all views, or ``views`` evenly spaced ones (only those read)."""
    from ..datasets import load_dataset

    kw: dict[str, Any] = {"downscale": int(cfg.downscale), "limit": views if views > 0 else None,
                          "spread": True}
    if cfg.background is not None:
        kw["background"] = tuple(float(v) for v in cfg.background)
    return load_dataset(root, split, **kw)


def finetune(config: FinetuneConfig) -> FinetuneResult:
    """Fine-tune ``config.tree`` on ``config.data`` and write ``config.out`` (see :func:`_finetune`).

    Before any work: ``out`` must be a writable file name that is not a directory nor an
    unrelated file (:func:`plenoctree._util.check_output_file`); the run holds a lock on
    ``out`` (``.<name>.lock`` beside it) so two fine-tunings into one file cannot race.
    Progress lines go to the ``plenoctree.optim`` loggers (INFO, DEBUG unless ``verbose``).
    """
    from .._util import check_output_file, run_lock

    cfg = config.validated()
    out = check_output_file(cfg.out)
    with run_lock(out, "finetune", folder=False):
        return _finetune(cfg)


@dataclass
class _Files:
    """Where a run writes: ``out``, the checkpoint, the JSON-lines log and the curve."""

    out: Path
    checkpoint: Path
    log: Path
    curve: Path

    @classmethod
    def of(cls, cfg: FinetuneConfig) -> _Files:
        out = Path(cfg.out)
        stem = out.with_suffix("") if out.suffix == ".npz" else out
        at = lambda suffix: stem.with_name(stem.name + suffix)  # noqa: E731
        return cls(out, Path(cfg.checkpoint) if cfg.checkpoint else at(".ckpt.npz"),
                   Path(cfg.log) if cfg.log else at(".log.jsonl"), at(".curve.png"))


def _load_tree(cfg: FinetuneConfig) -> tuple[Any, str]:
    """The checked tree in float32 and the precision to save it in."""
    from ..octree import load_tree

    stored = load_tree(Path(cfg.tree), keep_dtype=True)
    precision = cfg.precision if cfg.precision != "auto" else (
        "fp16" if stored.data.dtype == np.float16 else "fp32")
    tree = stored.astype(np.float32) if stored.data.dtype != np.float32 else stored
    _check_tree(tree, Path(cfg.tree))
    return tree, precision


def holdout_for(holdout_every: int, unbounded: bool) -> int:
    """``holdout_every`` with -1 (automatic) decided: :data:`DEFAULT_HOLDOUT_EVERY` for a
    capture of a place (``unbounded``), else 0 (validation on training views).

    >>> holdout_for(-1, True), holdout_for(-1, False), holdout_for(4, False)
    (8, 0, 4)
    """
    if holdout_every >= 0:
        return int(holdout_every)
    return DEFAULT_HOLDOUT_EVERY if unbounded else 0


def held_out_views(n_train: int, every: int, fraction: float = 0.0, seed: int = 0
                   ) -> np.ndarray:
    """Which of ``n_train`` training views fine-tuning holds out of its updates to validate on:
    sorted int64 indices ``[K]`` into the training split (empty: none held out).

    ``fraction`` in (0, 1): ``round(fraction · n_train)`` views drawn at random (``seed``),
    at least 1 and at most ``n_train - 1``. Else every ``every``-th view from ``every // 2``
    on (views ``4, 12, 20, …`` for ``every = 8``: each held-out view has trained neighbours on
    both sides, as the test views interleaved with a capture's training views do), at least
    one (the middle view when ``every > n_train``); none when ``every`` is 0 or there are fewer
    than :data:`HOLDOUT_MIN_VIEWS` views. ``every`` >= 2, so at least half the views stay in
    training.

    >>> held_out_views(20, 8).tolist(), held_out_views(7, 8).tolist(), held_out_views(9, 0).tolist()
    ([4, 12], [], [])
    """
    if float(fraction) > 0.0:
        if n_train < 2:
            raise DatasetError("a single training image: cannot hold out a validation view "
                               "(use --val-every 0)")
        n_hold = min(n_train - 1, max(1, round(float(fraction) * n_train)))
        return np.sort(np.random.default_rng(seed).permutation(n_train)[:n_hold]).astype(np.int64)
    if every <= 0 or n_train < HOLDOUT_MIN_VIEWS:
        return np.zeros(0, np.int64)
    hold = np.arange(every // 2, n_train, every, dtype=np.int64)
    return hold if len(hold) else np.array([n_train // 2], np.int64)


class _Views(NamedTuple):
    """What fine-tuning trains and validates on (:func:`_view_sets`)."""

    train: Any                       # ViewSet: the views the updates see
    val: Any                         # ViewSet or None: the views validated on
    background: tuple[float, float, float]
    validation: str                  # "val split", "held-out training views",
    #                                  "training views (in training)" or "none"
    held_out: list[str]              # names of the training views kept out of the updates


def _view_sets(cfg: FinetuneConfig, tree: Any) -> _Views:
    """The training views and the validation views: the dataset's val split when it has one of
    its own (``has_split``: not when its val views are its test views, as LLFF's, COLMAP's and
    instant-ngp's are: the best epoch would be chosen on the photos the test PSNR is measured
    on); else the training views :func:`held_out_views` holds out (``holdout_every``, -1:
    8 for a capture of a place, else none; ``val_fraction``), which leave the training set;
    else (hold-out off, or too few views) ``TRAIN_VAL_VIEWS`` (or ``val_views``) evenly
    spaced training views that stay in training.
    No validation when ``val_every`` is 0. ``val_views`` > 0 validates on that many evenly
    spaced ones of the chosen views. The test split is never read here."""
    from ..datasets import evenly_spaced, take_views
    from ..datasets.dataset import has_split
    from ._loop import ViewSet

    train = _load_split(cfg.data, "train", cfg)
    _check_overlap(tree, train, Path(cfg.tree))
    bg = tuple(float(v) for v in (cfg.background if cfg.background is not None
                                  else train.background))
    if cfg.val_every <= 0:
        return _Views(ViewSet.from_dataset(train), None, bg, "none", [])
    if has_split(Path(cfg.data), "val"):
        val_data = _load_split(cfg.data, "val", cfg, cfg.val_views)
        val_set = ViewSet.from_dataset(val_data)
        del val_data                   # the view set holds its own copy of the images
        return _Views(ViewSet.from_dataset(train), val_set, bg, "val split", [])
    every = holdout_for(int(cfg.holdout_every), bool(getattr(train, "unbounded", False)))
    try:
        hold = held_out_views(len(train), every, float(cfg.val_fraction), int(cfg.seed))
    except DatasetError as e:
        raise DatasetError(f"{cfg.data}: no val split and {e}") from None
    if not len(hold):
        seen = evenly_spaced(len(train), cfg.val_views or TRAIN_VAL_VIEWS)
        return _Views(ViewSet.from_dataset(train), ViewSet.from_dataset(train, seen), bg,
                      "training views (in training)", [])
    keep = np.setdiff1d(np.arange(len(train)), hold)
    val_set = ViewSet.from_dataset(train, take_views(hold, cfg.val_views or None, spread=True))
    held = [train.names[i] if train.names else f"view_{i}" for i in hold]
    return _Views(ViewSet.from_dataset(train, keep), val_set, bg, "held-out training views",
                  held)


def _make_stepper(cfg: FinetuneConfig, tree: Any, bg: tuple[float, float, float]
                  ) -> tuple[Any, dict]:
    """The stepper training ``tree``'s values in place, and the learning rates
    ``{"lr", "sigma_lr", "h"}`` (``h`` the finest leaf side)."""
    from ..render import RenderOptions
    from ._steppers import DEFAULT_LR, make_stepper

    # The values trained in place: a view of the loaded tree's float32 data when it can be one
    # (no second copy of a gigabyte-sized array; ``tree`` serves only its geometry from here on).
    data2 = np.ascontiguousarray(tree.data, dtype=np.float32).reshape(-1, tree.data_dim)
    if not data2.flags.writeable:
        data2 = data2.copy()
    lr = DEFAULT_LR[cfg.optimizer] if cfg.lr is None else float(cfg.lr)
    h = float(tree.leaf_sizes().min())
    sigma_lr = None if cfg.optimizer == "sgd" else (
        lr if cfg.lr_sigma is None else float(cfg.lr_sigma)) / h
    opts = RenderOptions(stop_thresh=float(cfg.stop_thresh), background=bg)
    stepper = make_stepper(cfg.backend, data2, tree, opts, cfg.optimizer, lr, sigma_lr,
                           device=cfg.device)
    return stepper, {"lr": lr, "sigma_lr": sigma_lr, "h": h}


def _describe(cfg: FinetuneConfig, tree: Any, views: _Views, stepper: Any, rates: dict) -> str:
    """The run's first line: tree, data, views, optimiser, batches, backend and device."""
    train, val = views.train, views.val
    lr, sigma_lr, h = rates["lr"], rates["sigma_lr"], rates["h"]
    return (f"finetune: {Path(cfg.tree)} ({tree.n_leaves} leaves, {tree.data_format}) on {cfg.data} "
            f"[{len(train)} train / {len(val) if val else 0} val views, "
            f"{train.width}x{train.height}], {cfg.optimizer} lr={lr:g}"
            f"{'' if sigma_lr is None else f' (σ {sigma_lr:g} = {sigma_lr * h:g}/h)'}"
            f"{'' if cfg.lr_decay == 1 else f' decaying x{cfg.lr_decay:g}'}, "
            f"batch {cfg.batch_rays} rays in {cfg.ray_tile}x{cfg.ray_tile} tiles, "
            f"backend {stepper.backend} on {getattr(stepper, 'device', 'cpu')}")


def _test_views(cfg: FinetuneConfig) -> Any:
    """The test split's view set (``test_views`` evenly spaced ones), None when skipped or
    missing."""
    from ..datasets.dataset import has_split
    from ._loop import ViewSet

    if cfg.test_views < 0 or not has_split(Path(cfg.data), "test"):
        return None
    return ViewSet.from_dataset(_load_split(cfg.data, "test", cfg, cfg.test_views))


#: Seconds kept from ``minutes`` for saving the tree after the loop: a fixed part and per GB
#: of its values (lego's 1.5 GB refined tree: 2.6 s from the last validation to the end).
SAVE_S, SAVE_S_PER_GB = 1.0, 2.0


def _loop_options(cfg: FinetuneConfig, checkpoint: Path, t_start: float, nbytes: int) -> Any:
    """The loop's options; with ``minutes``, its ``stop_at`` counts from ``t_start``
    (``time.perf_counter()`` at the command's start) and keeps the time to save ``nbytes``."""
    from ._loop import LoopOptions

    stop_at = None
    if cfg.minutes > 0:
        stop_at = t_start + 60.0 * float(cfg.minutes) - SAVE_S - SAVE_S_PER_GB * nbytes / 1e9
    return LoopOptions(epochs=int(cfg.epochs), batch_rays=int(cfg.batch_rays),
                       ray_tile=int(cfg.ray_tile), val_every=int(cfg.val_every),
                       stop_on_decrease=not cfg.continue_on_decrease, seed=int(cfg.seed),
                       backoffs=int(cfg.backoffs), patience=int(cfg.patience),
                       lr_decay=float(cfg.lr_decay),
                       checkpoint=checkpoint, resume=bool(cfg.resume),
                       checkpoint_every_s=60.0 * float(cfg.checkpoint_minutes),
                       show_progress=cfg.show_progress, stop_at=stop_at)


def _fingerprint(cfg: FinetuneConfig, tree: Any, rates: dict, backend: str,
                 held_out: list[str]) -> dict:
    """What a checkpoint must match to be resumed by this run (``held_out``: the names of the
    training views held out of the updates, recorded only when there are some)."""
    held = {"held_out": list(held_out)} if held_out else {}
    return {**held, "tree": str(Path(cfg.tree).resolve()),
            "n_cells": int(np.prod(tree.data.shape[:-1])), "data_dim": int(tree.data_dim), "optimizer": cfg.optimizer, "lr": rates["lr"],
            "sigma_lr": rates["sigma_lr"], "lr_decay": float(cfg.lr_decay),
            "backoffs": int(cfg.backoffs), "batch_rays": int(cfg.batch_rays),
            "ray_tile": int(cfg.ray_tile), "downscale": int(cfg.downscale),
            "seed": int(cfg.seed), "backend": backend}


def _report_gradient_scale(cfg: FinetuneConfig, stepper: Any, events: Any) -> dict | None:
    """Adam / RMSprop: log how the steps related to the optimiser's eps."""
    from ._steppers import gradient_scale

    scale = gradient_scale(stepper)
    if scale is not None and scale["values"]:
        events({"event": "gradient_scale", **scale})
        events.note(f"  {cfg.optimizer}: {100 * scale['share_below_eps']:.3f} % of the touched "
                   f"values had an RMS gradient below its eps {scale['eps']:g} (median "
                   f"{scale['rms_p50']:.2g}): there it stepped as SGD"
                   f"{' with momentum' if cfg.optimizer == 'adam' else ''} at lr/eps")
    return scale


def _finetune(cfg: FinetuneConfig) -> FinetuneResult:
    """Fine-tune ``cfg.tree`` on ``cfg.data`` and write ``cfg.out``.

    Steps: load and check the tree (leaves, finite values, some σ > 0) and the dataset (its box
    must overlap the tree's); choose the validation views (:func:`_view_sets`: held-out
    training views when the dataset has no val split of its own), logging which were held
    out; measure test PSNR; run the :class:`~._loop.FineTuneLoop` (validation every
    ``val_every`` epochs, back-offs and stop on drops, keep the best, the input included); save
    the best values in the requested precision; measure test PSNR again; log the validation
    PSNR before and after.

    A diverging learning rate (non-finite values, or the training error blowing up) stops the
    loop: the last good values (best validated, or the initial ones) are saved to ``out`` and a
    :class:`ConfigError` explains what happened. The JSON-lines log and the checkpoint are
    written next to ``out`` unless configured otherwise; the checkpoint is removed on success.
    """
    from ..octree import save_tree
    from ._events import EventLog
    from ._loop import FineTuneLoop, remove_best_files, render_views_psnr

    t_start = time.perf_counter()
    files = _Files.of(cfg)
    events = EventLog(files.log, t_start, logging.INFO if cfg.verbose else logging.DEBUG)
    tree, precision = _load_tree(cfg)
    views = _view_sets(cfg, tree)
    stepper, rates = _make_stepper(cfg, tree, views.background)
    events.note(_describe(cfg, tree, views, stepper, rates))
    if views.held_out:
        events.note(f"validation on {len(views.val)} of {len(views.held_out)} training views "
                    f"held out of the updates: {', '.join(views.held_out)}")
    test_set = _test_views(cfg)
    test_before = render_views_psnr(stepper, test_set) if test_set is not None else None
    if test_before is not None:
        events.note(f"test PSNR before: {test_before:.3f} dB ({len(test_set)} views)")

    files.log.parent.mkdir(parents=True, exist_ok=True)
    if not cfg.resume and files.log.exists():
        files.log.unlink()
    events({"event": "start", "config": {k: (str(v) if isinstance(v, os.PathLike) else v)
                                         for k, v in asdict(cfg).items()}})
    if not cfg.resume:
        remove_best_files(files.checkpoint)   # an earlier run's: its checkpoint is replaced
    loop = FineTuneLoop(stepper, views.train, views.val,
                        _loop_options(cfg, files.checkpoint, t_start, tree.data.nbytes),
                        _fingerprint(cfg, tree, rates, stepper.backend, views.held_out), events)
    best, state = loop.run()
    scale = _report_gradient_scale(cfg, stepper, events)
    stepper.release()        # the moments and gradient slabs are not needed to save and score

    try:
        save_tree(dataclasses.replace(tree, data=best.reshape(tree.data.shape)), files.out,
                  precision=precision)
    except ValueError as e:  # fp16 overflow
        raise ConfigError(f"{files.out}: cannot save in {precision}: {e}") from None
    test_after = None
    if test_set is not None:
        test_after = render_views_psnr(stepper, test_set)
        events.note(f"test PSNR after:  {test_after:.3f} dB (best epoch {state.best_epoch}; "
                   f"{state.stop_reason})")
    result = FinetuneResult(
        out=files.out, test_psnr_before=test_before, test_psnr_after=test_after,
        val_psnr_before=state.history[0]["val_psnr"] if state.history else None,
        val_psnr_best=state.best_psnr if math.isfinite(state.best_psnr) else None,
        best_epoch=state.best_epoch, epochs_run=state.epochs_done, steps=state.steps,
        stop_reason=state.stop_reason, backoffs=state.backoffs,
        wall_seconds=time.perf_counter() - t_start,
        train_rays_per_second=state.train_rays / max(state.train_seconds, 1e-9),
        backend=stepper.backend, history=state.history,
        device=str(getattr(stepper, "device", "cpu")), gradient_scale=scale,
        validation=views.validation, held_out=views.held_out)
    if result.val_psnr_before is not None:
        events.note(f"{views.validation} PSNR before {result.val_psnr_before:.3f} dB, after "
                    f"{result.val_psnr_best:.3f} dB (best epoch {state.best_epoch})")
    events({"event": "end", **result.to_json()})
    from ..plots import plot_finetune_curve      # train/val PSNR per epoch (needs matplotlib)

    plot_finetune_curve(files.log, files.curve)
    if state.stop_reason.startswith("diverged"):
        raise ConfigError(f"learning rate {rates['lr']:g} ({cfg.optimizer}) diverged: "
                          f"{state.stop_reason[len('diverged: '):]}. Kept the last good values "
                          f"(epoch {state.best_epoch}) in {files.out}; try a smaller --lr")
    if files.checkpoint.exists():
        files.checkpoint.unlink()
    remove_best_files(files.checkpoint)
    return result
