"""How the device a stage ran on is reported in its JSON output.

Every stage (train, extract, finetune, render, eval, video, run, demo) takes a ``device``
option: ``"auto"`` (CUDA when a GPU is present, else the CPU), ``"cpu"``, ``"cuda"`` or
``"cuda:N"``, resolved by :func:`plenoctree.runtime.resolve_device` (CUDA without a GPU is a
:class:`~plenoctree.errors.ConfigError`).
"""

from __future__ import annotations

from typing import Any

from .runtime import resolve_device

__all__ = ["resolve_device", "device_report", "DEVICE_HELP"]

DEVICE_HELP = "auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N"


def device_report(device: Any) -> dict:
    """``{"device": "cuda:0", "device_name": "NVIDIA H200"}`` (CPU: ``"cpu"``, the processor)."""
    import torch

    dev = torch.device(device)
    if dev.type == "cuda":
        idx = dev.index if dev.index is not None else torch.cuda.current_device()
        return {"device": f"cuda:{idx}", "device_name": torch.cuda.get_device_name(idx)}
    import platform

    return {"device": "cpu", "device_name": platform.processor() or platform.machine()}
