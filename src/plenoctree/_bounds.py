"""The ceilings of every count and time setting: one policy that every config checks.

A count (steps, epochs, views, frames, batch sizes, resolutions, passes...) or a time (minutes,
seconds) far past anything meaningful used to be taken as given and failed deep inside the
work (``minutes = 1e308``: a progress bar of infinitely many seconds) or ran without a word
(``epochs = 10**30``). Every setting is checked here instead, where it enters:

* :func:`bound_error` for one value, called by ``_config.check_value`` on every value a
  config file or a command-line flag sets (every command, ``run``'s ``--<stage>.*`` too);
* :func:`check_bounds` for a whole config (nested configs included), called by the configs'
  own checks (``nerf.config.validate``, ``FinetuneConfig.validated``, extraction's and
  refinement's checks, ``CompressOptions.validated``), so configs built in Python, or read
  back from a checkpoint, are held to the same limits.

The limits (docs/usage.md, "Input bounds"):

* a time: at most a week (:data:`MAX_MINUTES` minutes, :data:`MAX_SECONDS` seconds);
* rays, points or samples per batch, step or chunk: at most :data:`MAX_BATCH` (2^26 rays'
  origins, directions and colours alone take 2.4 GB);
* the occupancy grid's cells per axis: at most :data:`MAX_OCC_RES` (1024³ cells: 4 GB of
  float32 density);
* frames per second: at most :data:`MAX_FPS`;
* a seed: :data:`MAX_SEED` in magnitude (torch's seed range);
* any other integer: at most :data:`MAX_COUNT` (2^31 - 1) in magnitude;
* any other number: finite (NaN and infinity, which JSON files and ``float()`` accept, are
  refused).

The configs' own checks keep their lower bounds and ranges (``epochs >= 0``, ``lr_decay`` in
(0, 1]); this module adds the upper ends (and an integer's magnitude). Imports nothing but
:mod:`.errors`.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from typing import Any

from .errors import ConfigError

__all__ = ["MAX_COUNT", "MAX_MINUTES", "MAX_SECONDS", "MAX_BATCH", "MAX_OCC_RES", "MAX_FPS",
           "MAX_SEED", "LIMITS", "is_integer_type", "bound_error", "check_bounds"]

MAX_COUNT = 2**31 - 1
"""Any integer setting without a tighter limit (the int32 index range)."""
MAX_MINUTES = 7 * 24 * 60
"""A time in minutes: a week (10080)."""
MAX_SECONDS = MAX_MINUTES * 60
"""A time in seconds: a week (604800)."""
MAX_BATCH = 2**26
"""Rays, points or samples per batch, step or chunk (67,108,864)."""
MAX_OCC_RES = 1024
"""Cells per axis of the training's occupancy grid."""
MAX_FPS = 1000
"""Frames per second of a video."""
MAX_SEED = 2**63 - 1
"""A random seed, in magnitude."""

_WEEK_MIN = (MAX_MINUTES, "a week")
_WEEK_S = (MAX_SECONDS, "a week")
_BATCH = (MAX_BATCH, "2^26 per batch")

LIMITS: dict[str, tuple[int, str]] = {
    "minutes": _WEEK_MIN, "checkpoint_minutes": _WEEK_MIN,
    "val_every_s": _WEEK_S, "ckpt_every_s": _WEEK_S, "preview_every_s": _WEEK_S,
    "batch_rays": _BATCH, "max_rays": _BATCH, "target_samples": _BATCH,
    "sparsity_points": _BATCH, "chunk": _BATCH,
    "occ_res": (MAX_OCC_RES, "1024^3 cells"),
    "fps": (MAX_FPS, "frames per second"),
    "seed": (MAX_SEED, "2^63 - 1"),
}
"""The settings with a limit of their own, by field name: ``(limit, why)``. Every other
integer setting is bounded by :data:`MAX_COUNT`, every other number only to be finite."""


def is_integer_type(tp: Any) -> bool:
    """Whether annotation ``tp`` is an integer setting: ``int`` or ``int | None``."""
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    return tp is int or (typing.get_origin(tp) in (typing.Union, types.UnionType)
                         and args == [int])


def bound_error(name: str, value: Any, integer: bool | None = None) -> str | None:
    """What is wrong with ``value`` for setting ``name`` (``integer``: an integer setting;
    default: whether ``value`` is an integer) against the ceilings, e.g. ``"must be at most
    10080 (a week), got 1e+308"``; None when it is within them. Values that are not numbers
    (text, None, tuples) are left to the type checks; lower bounds (``epochs >= 0``) to the
    configs, but for an integer's magnitude."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    value = int(value) if isinstance(value, numbers.Integral) else float(value)  # numpy too
    integer = isinstance(value, int) if integer is None else integer
    high, why = LIMITS.get(name) or ((MAX_COUNT, "2^31 - 1") if integer else (None, ""))
    if high is not None and value == value and value > high:    # (NaN: not finite, below)
        return f"must be at most {high} ({why}), got {_shown(value)}"
    low = -(MAX_SEED if name == "seed" else MAX_COUNT)
    if integer and value < low:
        return f"must be at least {low}, got {_shown(value)}"
    try:
        finite = math.isfinite(value)
    except OverflowError:                     # an integer too large for any float
        finite = False
    return None if finite else f"must be a finite number, got {_shown(value)}"


def _shown(value: int | float) -> str:
    """``value`` for an error message: a huge integer by its number of digits."""
    text = repr(value)
    return text if len(text) <= 40 else f"an integer of {len(text.lstrip('-'))} digits"


def check_bounds(cfg: Any, prefix: str = "", nested: bool = True) -> Any:
    """Raise :class:`ConfigError` for the first field of dataclass ``cfg`` past its ceiling, as
    ``<prefix><field> must be at most ...``; ``nested``: the fields of nested dataclasses too
    (``TrainConfig.model``). Returns ``cfg``."""
    try:
        hints = typing.get_type_hints(type(cfg))
    except Exception:  # noqa: BLE001 - an annotation that cannot be resolved: by the values
        hints = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            if nested:
                check_bounds(value, prefix)
            continue
        integer = is_integer_type(hints[f.name]) if f.name in hints else None
        problem = bound_error(f.name, value, integer)
        if problem:
            raise ConfigError(f"{prefix}{f.name} {problem}")
    return cfg
