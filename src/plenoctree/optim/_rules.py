"""Constants the fine-tuning steppers share (numba, torch, Triton) and the loop reads.

The optimisers' hyper-parameters (Adam's betas and eps, RMSprop's alpha and eps) and the
columns of a device stepper's figures rows (float64, one row a step, read back by the loop
every few steps): the squared error summed over the batch, the rays inside the images, the
non-finite values written, the rows (cells) updated; and the check of a checkpoint's
optimiser moments every stepper's ``load_state`` makes (:func:`saved_moment`). Imports
nothing of the package but its errors.
"""

from __future__ import annotations

from typing import Any

from ..errors import ConfigError

__all__ = ["BETAS", "ADAM_EPS", "RMS_ALPHA", "RMS_EPS", "FIG_SSE", "FIG_RAYS", "FIG_BAD",
           "FIG_ROWS", "N_FIGS", "saved_moment"]

BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
RMS_ALPHA = 0.99
RMS_EPS = 1e-8

FIG_SSE, FIG_RAYS, FIG_BAD, FIG_ROWS = 0, 1, 2, 3
N_FIGS = 4


def saved_moment(state: dict[str, np.ndarray], key: str, shape: Any) -> np.ndarray:
    """``state[key]``, an optimiser moment of a checkpoint, checked to have ``shape``
    (:class:`ConfigError` naming it otherwise): every stepper's ``load_state``."""
    if key not in state or tuple(state[key].shape) != tuple(shape):
        raise ConfigError(f"checkpoint: optimiser state {key!r} missing or of the wrong shape")
    return state[key]
