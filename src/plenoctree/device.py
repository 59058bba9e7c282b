"""Which torch device a stage runs on, and how the device is reported in JSON outputs.

Every stage (train, extract, finetune, render, eval, video, run, demo) takes a ``device``
option: ``"auto"`` (CUDA when a GPU is present, else the CPU), ``"cpu"``, ``"cuda"`` or
``"cuda:N"``. Asking for CUDA without a GPU is a :class:`~plenoctree.errors.ConfigError`.
"""

from __future__ import annotations

import torch

from .errors import ConfigError

__all__ = ["resolve_device", "device_report", "DEVICE_HELP"]

DEVICE_HELP = "auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N"


def resolve_device(name: str | torch.device | None = "auto") -> torch.device:
    """``"auto"``/``None`` -> ``cuda`` when available else ``cpu``; checks explicit names."""
    if isinstance(name, torch.device):
        name = str(name)
    key = "auto" if name is None else str(name).strip().lower()
    if key == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(key)
    except (RuntimeError, ValueError):
        raise ConfigError(f"unknown device {name!r} (expected {DEVICE_HELP})") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device {name!r} requested but no CUDA GPU is available "
                              "(use --device cpu or auto)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"device {name!r}: only {torch.cuda.device_count()} CUDA "
                              "device(s) present")
    elif dev.type != "cpu":
        raise ConfigError(f"unsupported device {name!r} (expected {DEVICE_HELP})")
    return dev


def device_report(device: torch.device | str) -> dict:
    """``{"device": "cuda:0", "device_name": "NVIDIA H200"}`` (CPU: ``"cpu"``, the processor)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        idx = dev.index if dev.index is not None else torch.cuda.current_device()
        return {"device": f"cuda:{idx}", "device_name": torch.cuda.get_device_name(idx)}
    import platform

    return {"device": "cpu", "device_name": platform.processor() or platform.machine()}
