"""The fine-tuning steppers of torch tensors (CUDA, or the CPU): device-resident steps.

:class:`TorchStepper` (the renderer's torch twin with autograd) and :class:`TritonStepper`
(the Triton kernels, ``optim/_device_kernels.py``) share the host API of
:class:`~plenoctree.optim._steppers.NumbaStepper` (``step(origins, dirs, targets, scale)`` on
numpy rays, ``render``, ``values``, ``set_values``, ``state``, ``release``) and add the one
:class:`~plenoctree.optim._loop.FineTuneLoop` drives on the device:

- :meth:`~_DeviceStepper.device_views`: a view set's photos and packed cameras uploaded once
  (:class:`DeviceViews`); the tree's geometry is uploaded once, when the stepper is made;
- :meth:`~_DeviceStepper.tile_order`: an epoch's tile order drawn on the device;
- :meth:`~_DeviceStepper.step_tiles`: one step on a slice of that order — rays made on the
  device, forward, loss, analytic backward, the lazy optimiser (a dense masked update: no
  ``nonzero``) — writing its figures (squared error, rays, non-finite values, rows updated)
  into a row of a device buffer (:meth:`~_DeviceStepper.new_figures`) that the loop reads back
  every few steps (:meth:`~_DeviceStepper.read_figures`); on the Triton path a step is five
  kernel launches and no host synchronisation;
- :meth:`~_DeviceStepper.views_psnr`: validation rendered and scored on the device, one read
  back per validation; :meth:`~_DeviceStepper.device_values` for a best copy kept there.

The update rules are those of :mod:`._steppers` (lazy Adam / RMSprop, σ's own rate, σ ≥ 0).
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from ..render.options import KIND_RGBA, parse_data_format
from ._device_twins import OPT_CODES
from ._rules import (ADAM_EPS, BETAS, FIG_BAD, FIG_ROWS, FIG_SSE, N_FIGS, RMS_ALPHA, RMS_EPS,
                     saved_moment)

__all__ = ["DeviceViews", "TorchStepper", "TritonStepper"]

_MIN_CAPACITY = 1 << 16      # rays of the per-batch buffers (grown to the largest batch)


class DeviceViews:
    """A :class:`~plenoctree.optim._views.ViewSet`'s photos and cameras on ``device``, uploaded
    once: ``images`` ``[N, H, W, 3]`` (float32, or int16 holding the uint16 photo's bits),
    ``cams`` float64 ``[N, 20]`` (``packed_cameras``), ``unit`` float64 ``[1]`` (the value of
    one step of ``images``), ``width``, ``height``."""

    def __init__(self, views: Any, device: torch.device) -> None:
        imgs = np.ascontiguousarray(views.images)
        if imgs.dtype == np.uint16:
            imgs = imgs.view(np.int16)              # the bits: torch kernels lack uint16
        self.images = torch.from_numpy(imgs).to(device)
        self.cams = torch.from_numpy(np.ascontiguousarray(views.packed_cameras,
                                                          np.float64)).to(device)
        self.unit_value = float(views.unit)
        self.unit = torch.from_numpy(np.array([self.unit_value], np.float64)).to(device)
        self.width, self.height, self.n = int(views.width), int(views.height), len(views)


def _psnr_mean(sse: np.ndarray, per_view: int) -> float:
    """Mean over views of ``min(PSNR, 100)`` (dB) from each view's squared error summed over
    its ``per_view`` values (``metrics.psnr``: ``inf`` for a perfect view)."""
    vals = [100.0 if s == 0 else min(-10.0 * math.log10(s / per_view), 100.0) for s in sse]
    return float(np.mean(vals)) if vals else float("nan")


class _DeviceStepper:
    """What both torch steppers share; subclasses make batches and train on them."""

    backend = "?"

    def __init__(self, data2: np.ndarray, tree: Any, options: Any, optimizer: str, lr: float,
                 device: Any = None, sigma_lr: float | None = None) -> None:
        self.device = torch.device(device if device is not None else
                                   ("cuda" if torch.cuda.is_available() else "cpu"))
        self.tree, self.options, self.optimizer, self.lr = tree, options, optimizer, float(lr)
        self.sigma_lr = None if sigma_lr is None else float(sigma_lr)
        self.shape = tuple(tree.child.shape) + (data2.shape[1],)
        self.dim = int(data2.shape[1])
        self.data = torch.tensor(data2, dtype=torch.float32, device=self.device
                                 ).reshape(self.shape)
        self._flat = self.data.detach().view(-1, self.dim)   # the same storage, [n_cells, D]
        self.step_count = 0
        z = lambda: torch.zeros(data2.shape, dtype=torch.float32, device=self.device)  # noqa: E731
        self.m1 = z() if optimizer == "adam" else None
        self.m2 = z() if optimizer in ("adam", "rmsprop") else None
        self.last_touched = 0
        extra = getattr(tree, "extra_data", None)
        self.info = parse_data_format(tree.data_format, self.dim, extra)
        self.basis_range = options.basis_range(self.info.basis_dim)
        self._views: dict[int, tuple[Any, DeviceViews]] = {}
        self._host_figs: torch.Tensor | None = None

    # --- what the loop drives on the device -------------------------------------------------
    def device_views(self, views: Any, keep: bool = True) -> DeviceViews:
        """``views``' photos and cameras on the device: uploaded at the first call and kept
        while the stepper lives (``keep=False``: not kept)."""
        hit = self._views.get(id(views))
        if hit is not None and hit[0] is views:
            return hit[1]
        dv = DeviceViews(views, self.device)
        if keep:
            self._views[id(views)] = (views, dv)
        return dv

    def tile_order(self, n_tiles: int, seed: int) -> torch.Tensor:
        """A random permutation of ``range(n_tiles)`` (int64, on the device) drawn with a
        device generator seeded with ``seed``."""
        gen = torch.Generator(device=self.device)
        gen.manual_seed(int(seed))
        return torch.randperm(int(n_tiles), generator=gen, device=self.device)

    def new_figures(self, n: int) -> torch.Tensor:
        """A zeroed float64 ``[n, 4]`` figures buffer on the device (one row a step)."""
        return torch.zeros(int(n), N_FIGS, dtype=torch.float64, device=self.device)

    @staticmethod
    def read_figures(figs: torch.Tensor, n: int) -> np.ndarray:
        """Rows ``0 … n-1`` of ``figs`` (one read back: the host waits for the device), then
        zeroed for reuse: float64 ``[n, 4]`` = squared error, rays, non-finite values, rows
        updated of each step."""
        out = figs[:n].cpu().numpy().copy()
        figs[:n].zero_()
        return out

    def step_tiles(self, views: DeviceViews, tiles: torch.Tensor, k: int, scale: float,
                   figs: torch.Tensor, slot: int) -> None:
        """One optimisation step on the pixels of ``k × k`` tiles ``tiles`` (int64 ``[T]`` on
        the device) of ``views``, loss ``scale · Σ (C - C*)²``; its figures go to row ``slot``
        of ``figs``. Reads nothing back."""
        batch = self._batch(views, tiles, int(tiles.shape[0]), 0, int(k))
        self._train(batch, float(scale), figs, int(slot))

    def views_psnr(self, views: Any, keep: bool = False) -> float:
        """Mean over ``views`` of the per-view PSNR (dB, each at most 100) of the current
        values, rendered and scored on the device; one read back."""
        dv = self.device_views(views, keep)
        hw = dv.width * dv.height
        chunk = max(1, min(hw, self._capacity()))
        figs = self.new_figures(dv.n)
        with torch.no_grad():
            for i in range(dv.n):
                for c0 in range(0, hw, chunk):
                    batch = self._batch(dv, None, min(chunk, hw - c0), i * hw + c0, 1)
                    self._score(batch, figs, i)
        sse = figs[:, FIG_SSE].cpu().numpy()
        return _psnr_mean(sse, 3 * hw)

    def device_values(self) -> torch.Tensor:
        """The live values ``[n_cells, D]`` (a view of the device tensor, not a copy)."""
        return self._flat

    def fits(self, nbytes: int) -> bool:
        """Whether ``nbytes`` more fit in the device's free memory with room to spare (1 GiB
        or a tenth of the device; the CPU: always)."""
        if self.device.type != "cuda":
            return True
        free, total = torch.cuda.mem_get_info(self.device)
        return free - nbytes >= max(1 << 30, total // 10)

    # --- host API (NumbaStepper's) ------------------------------------------------------------
    def step(self, origins: np.ndarray, dirs: np.ndarray, targets: np.ndarray,
             scale: float) -> tuple[float, int]:
        """One step on host rays (uploaded); returns ``(sum of squared errors, non-finite
        values written)`` (read back)."""
        if self._host_figs is None:
            self._host_figs = self.new_figures(1)
        figs = self._host_figs
        self._train(self._host_batch(origins, dirs, targets), float(scale), figs, 0)
        read = self.read_figures(figs, 1)[0]
        self.last_touched = int(read[FIG_ROWS])
        return float(read[FIG_SSE]), int(read[FIG_BAD])

    def _t(self, x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(self.device)

    def _hyper(self) -> tuple[int, float, tuple[float, float, float, float, float]]:
        """``(optimiser code, σ's rate, (b1, b2, bc1, bc2, eps))`` of step ``step_count``."""
        t = self.step_count
        if self.optimizer == "adam":
            b1, b2 = BETAS
            hyper = (b1, b2, 1 - b1 ** t, 1 - b2 ** t, ADAM_EPS)
        else:
            hyper = (0.0, RMS_ALPHA, 1.0, 1.0, RMS_EPS)
        lr_sig = self.lr if self.sigma_lr is None else self.sigma_lr
        return OPT_CODES[self.optimizer], lr_sig, hyper

    def _capacity(self) -> int:
        return _MIN_CAPACITY

    def values(self) -> np.ndarray:
        return self.data.detach().reshape(-1, self.dim).cpu().numpy()

    def set_values(self, values: Any) -> None:
        """Copy ``values`` ``[n_cells, D]`` (numpy, or a tensor: device to device) in, and clear
        non-finite optimiser moments (a divergence's, left by the steps before it was read)."""
        with torch.no_grad():
            src = values if isinstance(values, torch.Tensor) else self._t(values)
            self._flat.copy_(src)
            for m in (self.m1, self.m2):
                if m is not None:
                    torch.nan_to_num_(m, nan=0.0, posinf=0.0, neginf=0.0)

    def release(self) -> None:
        """Drop the optimiser moments, gradient buffers and uploaded photos once training is
        over (see :meth:`NumbaStepper.release <plenoctree.optim._steppers.NumbaStepper.release>`)."""
        self.m1 = self.m2 = None
        self.data.grad = None
        self._views.clear()

    def state(self) -> dict[str, np.ndarray]:
        out = {"step_count": np.int64(self.step_count)}
        for key in ("m1", "m2"):
            v = getattr(self, key)
            if v is not None:
                out[key] = v.cpu().numpy()
        return out

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.step_count = int(state["step_count"])
        for key in ("m1", "m2"):
            mine = getattr(self, key)
            if mine is not None:
                mine.copy_(self._t(saved_moment(state, key, mine.shape)))

    # --- per backend ----------------------------------------------------------------------------
    def _batch(self, views: DeviceViews, tiles: torch.Tensor | None, n_tiles: int, base: int,
               k: int) -> Any:
        raise NotImplementedError

    def _host_batch(self, origins: np.ndarray, dirs: np.ndarray, targets: np.ndarray) -> Any:
        raise NotImplementedError

    def _train(self, batch: Any, scale: float, figs: torch.Tensor, slot: int) -> None:
        raise NotImplementedError

    def _score(self, batch: Any, figs: torch.Tensor, slot: int) -> None:
        raise NotImplementedError


class TorchStepper(_DeviceStepper):
    """The step with the renderer's torch twin and autograd (CPU or CUDA): the oracle of
    :class:`TritonStepper`; its march reads values back (the twin's loop), the rest does not."""

    backend = "torch"

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.torch = torch
        self.data.requires_grad_(True)
        t = self.tree
        dev = self.device
        extra = getattr(t, "extra_data", None)
        self._dtree = SimpleNamespace(          # the geometry on the device, once per tree
            child=torch.from_numpy(np.ascontiguousarray(t.child, np.int64)).to(dev),
            offset=torch.from_numpy(np.asarray(t.offset, np.float64).reshape(-1)).to(dev),
            invradius=torch.from_numpy(np.asarray(t.invradius, np.float64).reshape(-1)).to(dev),
            data_format=t.data_format, data=None,
            extra_data=None if extra is None else torch.from_numpy(
                np.asarray(extra, np.float64)).to(dev))

    def _batch(self, views: DeviceViews, tiles: torch.Tensor | None, n_tiles: int, base: int,
               k: int) -> Any:
        from ._device_twins import batch_pixels_torch, camera_rays_torch, pixel_targets_torch

        if tiles is None:
            tiles = torch.arange(n_tiles, device=self.device)
        img, u, v, outside = batch_pixels_torch(tiles, k, views.width, views.height, base)
        o, d = camera_rays_torch(views.cams, img, u, v)
        return o, d, pixel_targets_torch(views.images, views.unit_value, img, u, v), outside

    def _host_batch(self, origins: np.ndarray, dirs: np.ndarray, targets: np.ndarray) -> Any:
        o = self._t(origins)
        return o, self._t(dirs), self._t(targets), torch.zeros(o.shape[0], dtype=torch.bool,
                                                               device=self.device)

    def _rgb(self, o: torch.Tensor, d: torch.Tensor, data: torch.Tensor) -> torch.Tensor:
        from ..render._torch_impl import render_rays_torch

        return render_rays_torch(self._dtree, o, d, self.options, data=data).rgb

    def _train(self, batch: Any, scale: float, figs: torch.Tensor, slot: int) -> None:
        from ._device_twins import loss_torch, update_torch

        o, d, tgt, outside = batch
        rgb = self._rgb(o, d, self.data)
        _, grad_rgb = loss_torch(rgb, tgt, outside, scale, figs, slot)
        self.data.grad = None
        rgb.backward(grad_rgb.detach())
        self.step_count += 1
        opt, lr_sig, hyper = self._hyper()
        with torch.no_grad():
            update_torch(self.data.view(-1, self.dim), self.data.grad.view(-1, self.dim),
                         self.m1, self.m2, opt, self.lr, lr_sig, hyper, figs, slot)
        self.data.grad = None

    def _score(self, batch: Any, figs: torch.Tensor, slot: int) -> None:
        from ._device_twins import loss_torch

        o, d, tgt, outside = batch
        loss_torch(self._rgb(o, d, self.data.detach()), tgt, outside, 0.0, figs, slot)

    def render(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            rgb = self._rgb(self._t(origins), self._t(dirs), self.data.detach())
        return rgb.float().cpu().numpy()


class TritonStepper(_DeviceStepper):
    """The step with the Triton kernels on CUDA (or the CPU in Triton's interpreter): five
    launches a step on buffers allocated once (``optim/_device_kernels.py``), the tree's
    gradient in a persistent buffer that the optimiser kernel clears row by row."""

    backend = "triton"

    def __init__(self, *args: Any, **kw: Any) -> None:
        from .._triton import require_triton

        super().__init__(*args, **kw)
        require_triton(self.device, "fine-tuning")
        from ..render._rays_triton import geometry_tensor

        t, dev = self.tree, self.device
        self._child = torch.from_numpy(np.ascontiguousarray(t.child, np.int32).reshape(-1)
                                       ).to(dev)
        self._geom = geometry_tensor(t.offset, t.invradius, self.options.step_eps, dev)
        extra = getattr(t, "extra_data", None)
        self._extra = None if extra is None else torch.from_numpy(
            np.ascontiguousarray(extra, np.float32)).to(dev)
        self._grad: torch.Tensor | None = None
        self._buf: dict[str, torch.Tensor] = {}
        self._cap = 0

    def _capacity(self) -> int:
        return max(self._cap, _MIN_CAPACITY)

    def _buffers(self, n: int) -> dict[str, torch.Tensor]:
        """Per-ray buffers for at least ``n`` rays (grown, never shrunk)."""
        if n > self._cap:
            dev, f32 = self.device, torch.float32
            self._cap = n
            self._buf = {"geo": torch.empty(n, 14, dtype=torch.float64, device=dev),
                         "basis": torch.empty(n, self.info.basis_dim, dtype=f32, device=dev),
                         "tgt": torch.empty(n, 3, dtype=f32, device=dev),
                         "rgb": torch.empty(n, 3, dtype=f32, device=dev),
                         "depth": torch.empty(n, dtype=f32, device=dev),
                         "alpha": torch.empty(n, dtype=f32, device=dev),
                         "grad_rgb": torch.empty(n, 3, dtype=f32, device=dev)}
        return self._buf

    def _batch(self, views: DeviceViews, tiles: torch.Tensor | None, n_tiles: int, base: int,
               k: int) -> int:
        from ..render._rays_triton import batch_rays

        b = self._buffers(n_tiles * k * k)
        return batch_rays(tiles, n_tiles, base, k, views, self._geom, self.info, self._extra,
                          self.basis_range, (b["geo"], b["basis"], b["tgt"]))

    def _host_batch(self, origins: np.ndarray, dirs: np.ndarray, targets: np.ndarray) -> int:
        from ..render._torch_impl import ray_basis_torch
        from ..render._triton_impl import prepare_rays

        geo, unit = prepare_rays(self.tree.offset, self.tree.invradius, self._t(origins),
                                 self._t(dirs), self.options.step_eps)
        n = geo.shape[0]
        b = self._buffers(n)
        b["geo"][:n].copy_(geo)
        b["basis"][:n].copy_(ray_basis_torch(self.info, unit, self._extra, self.options))
        b["tgt"][:n].copy_(self._t(targets))
        return n

    def _march(self, n: int, backward: bool) -> None:
        """The render kernel (``render/_triton_impl._march_kernel``) on rays ``0 … n-1`` of the
        buffers: the forward into ``rgb``, or the backward of ``grad_rgb`` into the gradient."""
        import triton

        from ..render import _triton_impl as k

        if n == 0:
            return
        b, d2 = self._buf, self._flat
        n_b = 1 if self.info.kind == KIND_RGBA else self.info.basis_dim
        bg = [float(v) for v in self.options.background]
        block = k._block()
        grid = (triton.cdiv(n, block),)
        g = b["grad_rgb"] if backward else b["rgb"]
        k._march_kernel[grid](self._child, d2, b["basis"], b["geo"], g, b["rgb"], b["rgb"],
                              b["depth"], b["alpha"], self._grad if backward else d2, n,
                              float(self.options.stop_thresh), bg[0], bg[1], bg[2],
                              D=self.dim, B=n_b, BP=max(triton.next_power_of_2(n_b), 2),
                              QB=k.QUANT_BITS, BACKWARD=backward, BLOCK=block,
                              **k._launch_opts())

    def _train(self, n: int, scale: float, figs: torch.Tensor, slot: int) -> None:
        from ._device_kernels import loss, update

        if self._grad is None:
            self._grad = torch.zeros(self._flat.shape[0], self.dim, dtype=torch.float32,
                                     device=self.device)
        b = self._buf
        self._march(n, backward=False)
        loss(b["rgb"], b["tgt"], b["geo"], n, scale, figs, slot, b["grad_rgb"])
        self._march(n, backward=True)
        self.step_count += 1
        opt, lr_sig, hyper = self._hyper()
        update(self._flat, self._grad, self.m1, self.m2, opt,
               self.lr, lr_sig, hyper, figs, slot)

    def _score(self, n: int, figs: torch.Tensor, slot: int) -> None:
        from ._device_kernels import loss

        b = self._buf
        self._march(n, backward=False)
        loss(b["rgb"], b["tgt"], b["geo"], n, 0.0, figs, slot, None)

    def release(self) -> None:
        super().release()
        self._grad = None
        self._buf, self._cap = {}, 0

    def render(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        from ..render._triton_impl import render_rays_triton

        with torch.no_grad():
            out = render_rays_triton(self.tree, self._t(origins), self._t(dirs), self.options,
                                     data=self.data.detach())
        return out.rgb.float().cpu().numpy()
