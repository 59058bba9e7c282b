"""Constants the fine-tuning steppers share (numba, torch, Triton) and the loop reads.

The optimisers' hyper-parameters (Adam's betas and eps, RMSprop's alpha and eps) and the
columns of a device stepper's figures rows (float64, one row a step, read back by the loop
every few steps): the squared error summed over the batch, the rays inside the images, the
non-finite values written, the rows (cells) updated. Imports nothing.
"""

from __future__ import annotations

__all__ = ["BETAS", "ADAM_EPS", "RMS_ALPHA", "RMS_EPS", "FIG_SSE", "FIG_RAYS", "FIG_BAD",
           "FIG_ROWS", "N_FIGS"]

BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
RMS_ALPHA = 0.99
RMS_EPS = 1e-8

FIG_SSE, FIG_RAYS, FIG_BAD, FIG_ROWS = 0, 1, 2, 3
N_FIGS = 4
