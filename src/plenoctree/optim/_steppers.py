"""One optimisation step on a batch of rays, for each backend, with SGD / Adam / RMSprop.

Both steppers minimise ``L = scale · Σ_rays Σ_ch (C - target)²`` over the cell values (the
fine-tuning loop passes ``scale = 1 / (3 H W)``, the per-pixel mean of one training image).

- :class:`NumbaStepper` (CPU): one fused numba kernel renders the batch and scatters the
  analytic gradient (eq. 15 / 20) into per-thread slabs; the optimiser kernels then update
  only the touched cells. Adam and RMSprop are *lazy*: moments of cells the batch does not
  reach are left alone (``torch.optim.SparseAdam`` semantics), so a step costs O(touched cells).
- :class:`TorchStepper` (CPU or CUDA): the renderer's torch twin with autograd, then the same
  update rules in torch (SGD dense — identical to the sparse one; Adam/RMSprop lazy over cells
  with a non-zero gradient, as a dense masked update). :class:`TritonStepper` (CUDA) is the
  same with Triton kernels for the rays, the march's forward and analytic backward, the loss
  and the update: five launches a step, nothing read back (``optim/_device_stepper.py``; the
  fine-tuning loop drives both on the device: photos, tile order, figures and validation stay
  there).

Both take an optional separate σ learning rate ``sigma_lr`` (world σ units; ``None`` = ``lr``):
σ's values are in 1 / world length (hundreds on lego), not in the units of the pre-sigmoid
colour coefficients; the fine-tuner sets ``sigma_lr = lr_sigma / h`` (``h`` the finest leaf
side), which makes a scale-free step change a leaf's opacity by about ``lr_sigma``. Adam and
RMSprop are scale-free only where a value's RMS gradient is large against their ε (1e-8); with
this loss nearly none is (lego's refined tree at 400²: median ~2e-11, 99.999 % below ε), and
there the step is ``(lr / ε) · m̂``: SGD with momentum (:func:`gradient_scale` measures which
regime a run was in; ``finetune`` logs it). A truly scale-free Adam (ε 1e-14, lr 1e-3) scored
lower on lego (test 33.25 against 33.38 dB, 12 epochs), so ε stays. ``lr`` and ``sigma_lr`` may
be changed between steps (learning-rate schedules and back-off).

After every step σ is projected onto ``σ ≥ 0`` (the renderer uses ``relu(σ)``; nothing that
renders changes, and the tree stays valid for ``save_tree``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import ConfigError
from ._rules import ADAM_EPS, BETAS, RMS_ALPHA, RMS_EPS, saved_moment

__all__ = ["OPTIMIZERS", "DEFAULT_LR", "NumbaStepper", "TorchStepper", "TritonStepper",
           "make_stepper", "gradient_scale"]

OPTIMIZERS = ("sgd", "adam", "rmsprop")
#: Default learning rates: SGD in the paper's units (per-pixel mean loss); Adam/RMSprop would
#: move each value by about ``lr`` a step if the gradients were large against ε, but with this
#: loss they mostly are not (:func:`gradient_scale`): chosen by measurement, not by units.
DEFAULT_LR = {"sgd": 1e7, "adam": 2e-2, "rmsprop": 1e-3}
_BETAS, _ADAM_EPS, _RMS_ALPHA, _RMS_EPS = BETAS, ADAM_EPS, RMS_ALPHA, RMS_EPS


class NumbaStepper:
    """Fused numba forward + analytic backward + sparse optimiser step.

    Args:
        data2: float32 ``[n_cells, D]`` cell values, updated in place.
        args: :class:`~plenoctree.render._spec.TreeSpec` of the tree and render options
            (:func:`~plenoctree.optim._render_grad.kernel_args`).
        optimizer: ``"sgd" | "adam" | "rmsprop"``; ``lr`` its learning rate.
    """

    backend = "numba"

    def __init__(self, data2: np.ndarray, args: Any, optimizer: str, lr: float,
                 n_chunks: int | None = None, sigma_lr: float | None = None) -> None:
        from ._render_grad import SparseGrad

        if data2.dtype != np.float32 or not data2.flags.c_contiguous:
            raise ConfigError("NumbaStepper: data must be a contiguous float32 [n_cells, D] array")
        self.data2, self.args, self.optimizer, self.lr = data2, args, optimizer, float(lr)
        self.sigma_lr = None if sigma_lr is None else float(sigma_lr)
        self.buf = SparseGrad(data2.shape[0], data2.shape[1], np.float32, n_chunks)
        self.sig = np.ascontiguousarray(data2[:, -1])
        self.step_count = 0
        self.m1 = np.zeros_like(data2) if optimizer == "adam" else None
        self.m2 = np.zeros_like(data2) if optimizer in ("adam", "rmsprop") else None
        self._dummy = np.zeros((1, 1), np.float32)
        self.last_touched = 0

    def step(self, origins: np.ndarray, dirs: np.ndarray, targets: np.ndarray,
             scale: float) -> tuple[float, int]:
        """One step on a batch; returns ``(sum of squared errors, non-finite values written)``."""
        sse = self.accumulate(origins, dirs, targets, scale)
        return sse, self.apply()

    def accumulate(self, origins: np.ndarray, dirs: np.ndarray, targets: np.ndarray,
                   scale: float) -> float:
        """First half of :meth:`step`: forward + analytic backward of the batch into the
        per-thread slabs (the fused kernel); returns the sum of squared errors."""
        from ._render_grad import fused_mse_numba

        sse = fused_mse_numba(self.args, self.data2, origins, dirs, targets, scale, self.buf,
                              merge=False)
        self.last_touched = int(self.buf.n_touched.sum())     # upper bound: lists may overlap
        return sse

    def apply(self) -> int:
        """Second half of :meth:`step`: the optimiser kernel over the touched cells (σ at
        ``sigma_lr``); returns the number of non-finite values written."""
        from . import _render_grad_numba as k

        b = self.buf
        self.step_count += 1
        opt = {"sgd": k.OPT_SGD, "adam": k.OPT_ADAM, "rmsprop": k.OPT_RMSPROP}[self.optimizer]
        beta1, beta2, eps = (_BETAS[0], _BETAS[1], _ADAM_EPS) if self.optimizer == "adam" \
            else (0.0, _RMS_ALPHA, _RMS_EPS)
        m1 = self.m1 if self.m1 is not None else self._dummy
        m2 = self.m2 if self.m2 is not None else self._dummy
        lr_sig = self.lr if self.sigma_lr is None else self.sigma_lr
        return int(k.step_touched(self.data2, self.sig, b.grad3, b.slot, b.touched,
                                  b.n_touched, opt, self.lr, lr_sig, m1, m2, beta1, beta2, eps,
                                  float(self.step_count)))

    def render(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Render rays with the current values (no gradient): float32 ``[N, 3]``."""
        from ._render_grad import forward_numba

        return forward_numba(self.args, self.data2, origins, dirs).astype(np.float32, copy=False)

    def values(self) -> np.ndarray:
        """The current ``[n_cells, D]`` float32 values (a view; copy before keeping)."""
        return self.data2

    def set_values(self, values: np.ndarray) -> None:
        np.copyto(self.data2, values)
        np.copyto(self.sig, self.data2[:, -1])

    def release(self) -> None:
        """Drop the optimiser moments and gradient slabs (gigabytes on a large tree) once
        training is over; :meth:`render` and :meth:`values` still work, :meth:`step` not."""
        self.buf = None
        self.m1 = self.m2 = None

    def state(self) -> dict[str, np.ndarray]:
        """Optimiser state for checkpoints."""
        out = {"step_count": np.int64(self.step_count)}
        if self.m1 is not None:
            out["m1"] = self.m1
        if self.m2 is not None:
            out["m2"] = self.m2
        return out

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.step_count = int(state["step_count"])
        for key in ("m1", "m2"):
            mine = getattr(self, key)
            if mine is not None:
                np.copyto(mine, saved_moment(state, key, mine.shape))


def __getattr__(name: str) -> Any:
    """:class:`TorchStepper` and :class:`TritonStepper` live in :mod:`._device_stepper` (torch
    is imported on first use, not with this module)."""
    if name in ("TorchStepper", "TritonStepper"):
        from . import _device_stepper

        return getattr(_device_stepper, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def gradient_scale(stepper: Any, max_rows: int = 100_000) -> dict | None:
    """How Adam / RMSprop actually stepped: the RMS gradient ``√v̂`` of the touched values
    against the optimiser's ε (None for SGD or once the moments are released).

    The update is ``lr · m̂ / (√v̂ + ε)``: scale-free (each value moves by about ``lr``) only
    where ``√v̂ ≫ ε``; where ``√v̂ ≪ ε`` it is ``(lr / ε) · m̂``, SGD (Adam: with momentum). With
    the per-pixel-mean loss the gradient of one leaf value is tiny (lego's refined tree at 400²:
    median ``√v̂`` ~2e-11, 99th percentile ~9e-10, 99.999 % below ε = 1e-8), so this says
    which of the two the run was. Computed on at most ``max_rows`` evenly strided cells.

    Returns ``{"eps", "values", "share_below_eps", "rms_p50", "rms_p99"}`` (``values``: touched
    values in the sample).
    """
    m2 = getattr(stepper, "m2", None)
    if m2 is None:
        return None
    stride = max(1, m2.shape[0] // max_rows)
    v = m2[::stride]
    v = np.asarray(v.cpu().numpy() if hasattr(v, "cpu") else v, np.float64)
    if stepper.optimizer == "adam":
        eps = _ADAM_EPS
        v = v / (1.0 - _BETAS[1] ** max(int(stepper.step_count), 1))
    else:
        eps = _RMS_EPS
    rms = np.sqrt(v[v > 0])
    if rms.size == 0:
        return {"eps": eps, "values": 0, "share_below_eps": None, "rms_p50": None,
                "rms_p99": None}
    p50, p99 = np.percentile(rms, [50, 99])
    return {"eps": eps, "values": int(rms.size), "share_below_eps": float((rms < eps).mean()),
            "rms_p50": float(p50), "rms_p99": float(p99)}


def make_stepper(backend: str, data2: np.ndarray, tree: Any, options: Any, optimizer: str,
                 lr: float | None, sigma_lr: float | None = None, device: Any = "auto"
                 ) -> NumbaStepper | TorchStepper:
    """Build the stepper for ``backend`` (op ``"finetune"`` of :mod:`plenoctree.backend`).

    ``device``: ``"auto"`` (CUDA when available, else the CPU), ``"cpu"``, ``"cuda[:N]"``.
    ``backend="auto"`` takes the policy's choice for that device: numba on the CPU, the Triton
    kernel on CUDA (the torch twin where Triton is missing); an explicit name runs that backend
    (an explicit ``numba`` with ``device="auto"`` runs on the CPU).
    """
    from .. import backend as _backend
    from ..device import resolve_device

    name = _backend.check_name("finetune", backend)
    if optimizer not in OPTIMIZERS:
        raise ConfigError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {optimizer!r}")
    lr = DEFAULT_LR[optimizer] if lr is None else float(lr)
    if not (math.isfinite(lr) and lr > 0):
        raise ConfigError(f"learning rate must be a finite number > 0, got {lr!r}")
    auto_dev = device is None or str(device).lower() == "auto"
    dev = resolve_device("cpu" if auto_dev and name == "numba" else device)
    name = _backend.resolve("finetune", name, dev)
    kw = {} if sigma_lr is None else {"sigma_lr": float(sigma_lr)}
    return _backend.implementation("finetune", name)(data2, tree, options, optimizer, lr,
                                                      device=dev, **kw)


def _numba_stepper(data2: np.ndarray, tree: Any, options: Any, optimizer: str,
                   lr: float, sigma_lr: float | None = None, device: Any = None) -> NumbaStepper:
    from ._render_grad import kernel_args

    # Empty leaves stay empty in fine-tuning (no gradient reaches σ ≤ 0): rays may skip them.
    return NumbaStepper(data2, kernel_args(tree, options, skip_from=data2), optimizer, lr,
                        sigma_lr=sigma_lr)
