"""The NeRF-SH network (§4.1): position -> (σ, SH / SG coefficients), and its variants.

:class:`RadianceField` is one network: an encoding of the world position (NeRF positional
encoding or a multiresolution hash grid), an MLP trunk (optionally with a skip connection), and
one of three heads:

* ``basis="sh"`` — σ and ``3·(d+1)^2`` SH coefficients (the paper's NeRF-SH, eq. 4–5);
* ``basis="sg"`` — σ and ``3·B`` coefficients of ``B`` spherical Gaussians whose lobe axes and
  sharpness are learned parameters shared by all points (appendix A.2, B.1);
* ``basis="plain"`` — a plain NeRF head whose colour also depends on the view direction (for
  the SH-projection path of the conversion step); its "coefficients" are the pre-sigmoid RGB.

Coefficients are channel-major ``[R_0..R_{B-1}, G_0.., B_0..]`` and pre-sigmoid, exactly the
layout of an octree leaf (``docs/format.md``). Colour is ``sigmoid(Σ_b k_b·Y_b(d))``
with ``Y`` from :func:`plenoctree.sh.eval_sh_bases` or :func:`plenoctree.sh.eval_sg_bases`.

:class:`NeRFModel` bundles the fine network, the optional coarse one, the occupancy grid and
the scene box — what a checkpoint stores and what :func:`plenoctree.nerf.load_nerf` returns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..errors import ConfigError
from ..sh import eval_sg_bases, eval_sh_bases, num_sh_bases
from .config import ModelConfig
from .encoding import HashGridEncoding, HashGridLayout, PositionalEncoding
from .far import CONTRACTED_BOX, FarField
from .occupancy import OccupancyGrid

__all__ = ["RadianceField", "NeRFModel", "trunc_exp", "fibonacci_sphere", "sh_colors",
           "MLPSpec", "mlp_spec"]


class _TruncExp(torch.autograd.Function):
    """``exp(x)`` whose gradient uses ``exp(min(x, 15))`` (keeps early training stable)."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """``exp(x)`` with a gradient clamped at ``x = 15`` (the CPU preset's σ is
    ``trunc_exp(raw - 1)``)."""
    return _TruncExp.apply(x)


def _sh_colors_torch(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Twin of the numba SH-colour kernels: ``sigmoid(Σ_b k_b Y_b(d))`` per channel."""
    y = eval_sh_bases(degree, dirs.float())                                # [N, B]
    k = coeffs.float().reshape(coeffs.shape[0], 3, y.shape[-1])
    return torch.sigmoid((k * y[:, None, :]).sum(-1))


class _SHColorsNumba(torch.autograd.Function):
    """Fused numba SH colours; gradient w.r.t. the coefficients only."""

    @staticmethod
    def forward(ctx, coeffs, dirs, degree):
        from . import _shcolor_numba as K

        c = coeffs.detach().float().contiguous()
        d = dirs.detach().float().contiguous()
        n_b = (degree + 1) ** 2
        basis = torch.empty((c.shape[0], n_b), dtype=torch.float32)
        rgb = torch.empty((c.shape[0], 3), dtype=torch.float32)
        K.sh_color_forward(c.numpy(), d.numpy(), int(degree), basis.numpy(), rgb.numpy())
        ctx.save_for_backward(rgb, basis)
        ctx.in_dtype = coeffs.dtype
        return rgb

    @staticmethod
    def backward(ctx, grad_rgb):
        from . import _shcolor_numba as K

        rgb, basis = ctx.saved_tensors
        grad = torch.empty((rgb.shape[0], 3 * basis.shape[1]), dtype=torch.float32)
        K.sh_color_backward(grad_rgb.float().contiguous().numpy(), rgb.numpy(), basis.numpy(),
                            grad.numpy())
        return grad.to(ctx.in_dtype), None, None


def sh_colors(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int, backend: str = "auto"
              ) -> torch.Tensor:
    """RGB ``[N, 3] = sigmoid(Σ_b k_b Y_b(d))`` from SH coefficients ``[N, 3·(degree+1)^2]``
    (channel-major, pre-sigmoid) and unit directions ``[N, 3]``.

    ``backend``: "auto" (fused numba kernels for CPU tensors), "numba" or "torch" (the twin).
    Gradients flow to ``coeffs`` (not to ``dirs`` on the numba path, so "auto" takes the twin
    when ``dirs`` requires a gradient).
    """
    from .. import backend as _backend

    if dirs.requires_grad and _backend.check_name("sh_colors", backend) == "auto":
        backend = "torch"
    name = _backend.resolve("sh_colors", backend, coeffs.device)
    return _backend.implementation("sh_colors", name)(coeffs, dirs, degree)


def _sh_colors_numba_run(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    return _SHColorsNumba.apply(coeffs, dirs, degree)


def _bucket(n: int) -> int:
    """Round a batch size up so that few distinct sizes occur (≤ 1/16 padding).

    oneDNN builds a matmul kernel per input shape; with a new sample count every step, the
    bf16 MLP spent more time building kernels than running them (measured 2.5x slower).
    """
    if n <= 1024:
        return 1024 if n > 0 else 0
    q = 1 << max(10, n.bit_length() - 5)
    return -(-n // q) * q


@dataclass(frozen=True)
class MLPSpec:
    """A network's shape as the fused kernels' constants (:mod:`._mlp_triton`): encoding
    width ``din``, trunk ``width`` and ``depth``, head outputs ``n_out = 1 + 3 B``, SH
    ``degree``, σ activation ``act`` (1: ``trunc_exp(raw - 1)``, 0: relu)."""

    din: int
    width: int
    depth: int
    n_out: int
    degree: int
    act: int


def _pow2(v: int) -> bool:
    return 16 <= v <= 128 and v & (v - 1) == 0


def mlp_spec(field: "RadianceField") -> MLPSpec | None:
    """The fused kernels' :class:`MLPSpec` of ``field``, or None outside their family: a
    hash-grid SH network of 1–3 trunk layers of one power-of-two width in ``16..128``, a
    power-of-two encoding width in ``16..128``, no skip connection, SH degree ≤ 4."""
    cfg = field.cfg
    if (field.basis != "sh" or cfg.encoding != "hashgrid" or cfg.skip_layer
            or not 1 <= cfg.net_depth <= 3 or field.sh_degree > 4):
        return None
    din = field.encoder.out_dim
    if not (_pow2(din) and _pow2(cfg.net_width)):
        return None
    return MLPSpec(din, cfg.net_width, cfg.net_depth, 1 + 3 * field.basis_dim,
                   field.sh_degree, 1 if cfg.sigma_activation == "trunc_exp" else 0)


def _mlp_torch(field: "RadianceField", points: torch.Tensor, dirs: torch.Tensor | None):
    """Op ``mlp``'s twin, the eager network layer by layer (on the CPU its encoding and
    colours are numba kernels): ``σ [N]`` (``dirs`` None) or ``(σ [N], rgb [N, 3])``."""
    if dirs is None:
        return field._density_eager(points)
    sigma, coeffs = field.forward(points, dirs)
    return sigma, field.colors(coeffs, dirs)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``[n, 3]`` unit vectors spread evenly over the sphere (initial SG lobe axes)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


class RadianceField(nn.Module):
    """One NeRF-SH / NeRF-SG / NeRF network.

    Args:
        cfg: the :class:`~plenoctree.nerf.config.ModelConfig`.
        bbox: ``[2, 3]`` world box of the scene (the hash grid covers it).

    Attributes:
        basis: "sh", "sg" or "plain". basis_dim: ``B`` (SH: ``(d+1)^2``; SG: lobes; plain: 1).
        sh_degree: the SH degree (``-1`` unless ``basis == "sh"``).
    """

    def __init__(self, cfg: ModelConfig, bbox):
        super().__init__()
        self.cfg = cfg
        self.basis = cfg.basis
        if cfg.basis == "sh":
            self.basis_dim = num_sh_bases(cfg.sh_degree)
        elif cfg.basis == "sg":
            self.basis_dim = int(cfg.sg_lobes)
        elif cfg.basis == "plain":
            self.basis_dim = 1
        else:
            raise ConfigError(f"basis must be sh, sg or plain, got {cfg.basis!r}")
        self.sh_degree = cfg.sh_degree if cfg.basis == "sh" else -1
        self.mlp_backend = "auto"      # op "mlp" (density, radiance): "auto", "triton", "torch"
        self.grad_in_place = False     # the fused kernels' in-place gradients (_mlp_triton)
        if cfg.encoding == "hashgrid":
            self.encoder = HashGridEncoding(bbox, HashGridLayout(
                cfg.grid_levels, cfg.grid_features, cfg.grid_base_res, cfg.grid_max_res,
                cfg.grid_log2_table))
        elif cfg.encoding == "posenc":
            self.encoder = PositionalEncoding(3, cfg.pe_freqs)
        else:
            raise ConfigError(f"encoding must be hashgrid or posenc, got {cfg.encoding!r}")
        d_in, w = self.encoder.out_dim, cfg.net_width
        layers = []
        for i in range(cfg.net_depth):
            fan_in = d_in if i == 0 else w
            if cfg.skip_layer and i == cfg.skip_layer:
                fan_in += d_in
            layers.append(nn.Linear(fan_in, w))
        self.trunk = nn.ModuleList(layers)
        n_col = 3 * self.basis_dim
        if cfg.basis == "plain":
            self.view_enc = PositionalEncoding(3, cfg.view_freqs)
            self.sigma_head = nn.Linear(w, 1)
            self.bottleneck = nn.Linear(w, w)
            self.view_layer = nn.Linear(w + self.view_enc.out_dim, cfg.view_width)
            self.rgb_head = nn.Linear(cfg.view_width, 3)
        else:
            self.head = nn.Linear(w, 1 + n_col)          # σ then the coefficients
        if cfg.basis == "sg":
            self.sg_axes_raw = nn.Parameter(torch.as_tensor(fibonacci_sphere(self.basis_dim),
                                                            dtype=torch.float32))
            self.sg_log_sharpness = nn.Parameter(torch.full((self.basis_dim,), math.log(5.0)))
        for mod in self.modules():
            if isinstance(mod, nn.Linear):
                nn.init.xavier_uniform_(mod.weight)
                nn.init.zeros_(mod.bias)
        self.spec = mlp_spec(self)      # the fused kernels' constants, None: the eager network

    # ---------------------------------------------------------------- basis
    @property
    def data_format(self) -> str:
        """The octree ``data_format`` this network converts to ("SH16", "SG25", "RGBA")."""
        if self.basis == "sh":
            return f"SH{self.basis_dim}"
        if self.basis == "sg":
            return f"SG{self.basis_dim}"
        return "RGBA"

    def sg_lobes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(axes [B, 3] unit, sharpness [B] > 0)`` of the SG basis (basis "sg" only)."""
        if self.basis != "sg":
            raise ConfigError(f"sg_lobes: the model's basis is {self.basis!r}, not 'sg'")
        axes = nn.functional.normalize(self.sg_axes_raw, dim=-1)
        return axes, torch.exp(self.sg_log_sharpness)

    def basis_values(self, dirs: torch.Tensor) -> torch.Tensor:
        """``[N, B]`` basis functions at unit directions ``[N, 3]`` (float32)."""
        if self.basis == "sh":
            return eval_sh_bases(self.sh_degree, dirs.float())
        if self.basis == "sg":
            axes, sharp = self.sg_lobes()
            return eval_sg_bases(axes, sharp, dirs.float())
        raise ConfigError("basis_values: a plain NeRF has no basis")

    # ---------------------------------------------------------------- network
    def _features(self, points: torch.Tensor) -> torch.Tensor:
        """Trunk output ``[M, width]`` with ``M >= N`` (rows past ``N`` are padding)."""
        h0 = self.encoder(points)
        n = h0.shape[0]
        m = _bucket(n) if h0.device.type == "cpu" else n
        if m > n:
            h0 = nn.functional.pad(h0, (0, 0, 0, m - n))
        h = h0
        for i, layer in enumerate(self.trunk):
            if self.cfg.skip_layer and i == self.cfg.skip_layer:
                h = torch.cat([h, h0.to(h.dtype)], dim=-1)
            h = layer(h).relu_()                 # in place: saves a pass over [M, W]
        return h

    def _sigma(self, raw: torch.Tensor) -> torch.Tensor:
        raw = raw.float()
        if self.cfg.sigma_activation == "relu":
            return torch.relu(raw)
        # shifted by -1 so that the untrained field (raw ≈ 0) is a thin fog, σ ≈ 0.37
        return trunc_exp(raw - 1.0)

    def forward(self, points: torch.Tensor, dirs: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Evaluate the network.

        Args:
            points: ``[N, 3]`` world positions.
            dirs: ``[N, 3]`` unit view directions; required for ``basis="plain"`` only.

        Returns:
            ``(sigma [N] >= 0 in 1/world-length, coeffs [N, 3·B])`` float32; ``coeffs`` are the
            raw pre-sigmoid colour coefficients (channel-major); for ``plain`` the raw RGB.
        """
        h = self._features(points)
        if self.basis == "plain":
            if dirs is None:
                raise ConfigError("a plain NeRF (basis 'plain') needs view directions")
            n = points.shape[0]
            sigma = self._sigma(self.sigma_head(h)[:n, 0])
            b = self.bottleneck(h)
            v = self.view_enc(dirs.to(b.dtype))
            if b.shape[0] > n:
                v = nn.functional.pad(v, (0, 0, 0, b.shape[0] - n))
            rgb = self.rgb_head(torch.relu(self.view_layer(torch.cat([b, v], dim=-1))))
            return sigma, rgb[:n].float()
        out = self.head(h)[:points.shape[0]]
        return self._sigma(out[:, 0]), out[:, 1:].float()

    def _mlp(self, points: torch.Tensor, dirs: torch.Tensor | None):
        """Op ``mlp`` (:mod:`plenoctree.backend`): the fused kernels (:mod:`._mlp_triton`)
        where ``mlp_backend`` resolves to them for ``points``' device and the network is in
        :func:`mlp_spec`'s family, else the eager network."""
        from .. import backend as _backend

        name = "torch"
        if self.spec is not None:
            name = _backend.resolve("mlp", self.mlp_backend, points.device)
        return _backend.implementation("mlp", name)(self, points, dirs)

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """σ ``[N]`` at world points ``[N, 3]`` (no view direction needed for any basis)."""
        return self._mlp(points, None)

    def _density_eager(self, points: torch.Tensor) -> torch.Tensor:
        h = self._features(points)
        n = points.shape[0]
        if self.basis == "plain":
            return self._sigma(self.sigma_head(h)[:n, 0])
        # only the σ row of the output layer (the colour rows are a third of the MLP's work)
        raw = nn.functional.linear(h, self.head.weight[:1], self.head.bias[:1])
        return self._sigma(raw[:n, 0])

    def colors(self, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """RGB ``[N, 3]`` in (0, 1) from raw coefficients ``[N, 3·B]`` and unit dirs ``[N, 3]``."""
        if self.basis == "plain":
            return torch.sigmoid(coeffs.float())
        if self.basis == "sh":
            return sh_colors(coeffs, dirs, self.sh_degree)
        y = self.basis_values(dirs)                                        # [N, B]
        k = coeffs.float().reshape(-1, 3, self.basis_dim)
        return torch.sigmoid((k * y[:, None, :]).sum(-1))

    def radiance(self, points: torch.Tensor, dirs: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(sigma [N], rgb [N, 3])`` at points ``[N, 3]`` seen along unit ``dirs [N, 3]``
        (op ``mlp``: on CUDA one fused launch each way after the encoding)."""
        if self.basis == "plain" or dirs.requires_grad:
            return _mlp_torch(self, points, dirs)
        return self._mlp(points, dirs)


class NeRFModel(nn.Module):
    """A trained (or training) NeRF-SH: fine network, optional coarse one, occupancy grid.

    This is what :func:`plenoctree.nerf.load_nerf` returns to the conversion step:

    * ``query(points [N, 3] world, dirs=None) -> (sigma [N], coeffs [N, 3·B])`` — the fine
      network; ``dirs`` only for ``basis == "plain"``;
    * ``basis`` ("sh" | "sg" | "plain"), ``basis_dim`` (B), ``sh_degree``, ``data_format``
      ("SH16", "SG25", "RGBA"), ``sg_lobes()`` / ``sg_extra_data()`` for SG models;
    * ``scene_bbox`` — float32 ``[2, 3]`` world box used in training (the grid's extent);
    * ``occupancy`` — the :class:`OccupancyGrid` (occupancy sampler) or ``None``;
    * ``far`` — the :class:`~plenoctree.nerf.far.FarField` beyond the box (``far_levels``
      shells) or ``None``.
    """

    def __init__(self, cfg: ModelConfig, scene_bbox, occ_res: int = 0, far_levels: int = 0):
        super().__init__()
        bbox = np.asarray(scene_bbox, dtype=np.float32).reshape(2, 3)
        if not np.all(np.isfinite(bbox)) or not np.all(bbox[1] > bbox[0]):
            raise ConfigError(f"scene_bbox must be finite with max > min, got {bbox.tolist()}")
        self.cfg = cfg
        self.register_buffer("scene_bbox", torch.as_tensor(bbox))
        self.fine = RadianceField(cfg, bbox)
        self.coarse = RadianceField(cfg, bbox) if cfg.coarse else None
        self.occupancy = OccupancyGrid(bbox, occ_res) if occ_res else None
        self.far = (FarField(RadianceField(cfg, CONTRACTED_BOX), bbox, far_levels)
                    if far_levels > 0 else None)

    @property
    def basis(self) -> str:
        return self.fine.basis

    @property
    def basis_dim(self) -> int:
        return self.fine.basis_dim

    @property
    def sh_degree(self) -> int:
        return self.fine.sh_degree

    @property
    def data_format(self) -> str:
        return self.fine.data_format

    def sg_lobes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(axes [B, 3] unit, sharpness [B])`` of the SG basis."""
        return self.fine.sg_lobes()

    def sg_extra_data(self) -> np.ndarray:
        """float32 ``[B, 4]`` rows ``(sharpness, μx, μy, μz)``: the octree's ``extra_data``."""
        axes, sharp = self.sg_lobes()
        return torch.cat([sharp[:, None], axes], dim=1).detach().cpu().numpy().astype(np.float32)

    @property
    def far_levels(self) -> int:
        """Shells of the far field around the scene box (0: none; :mod:`.far`)."""
        return self.far.levels if self.far is not None else 0

    def _route(self, points: torch.Tensor, run) -> tuple[torch.Tensor, ...]:
        """``run(net, idx)`` (a tuple of ``[len(idx), ...]`` tensors) of the fine network for
        the points in the scene box and of the far field for those outside it, gathered back
        into point order (``[N, ...]`` each)."""
        u = self.far.box_coords(points)
        parts = [(idx, run(net, idx)) for net, idx in
                 ((self.fine, (u.abs().amax(-1) <= 1.0).nonzero()[:, 0]),
                  (self.far, (u.abs().amax(-1) > 1.0).nonzero()[:, 0])) if idx.numel()]
        outs = []
        for k, first in enumerate(parts[0][1]):
            o = first.new_empty((points.shape[0], *first.shape[1:]))
            for idx, res in parts:
                o[idx] = res[k].to(o.dtype)
            outs.append(o)
        return tuple(outs)

    def query(self, points: torch.Tensor, dirs: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(sigma [N], coeffs [N, 3·B])`` at world points ``[N, 3]``: the fine network in the
        scene box, the far field (when there is one) outside it."""
        if self.far is None or points.shape[0] == 0:
            return self.fine(points, dirs)
        return self._route(points, lambda net, i: net(points[i],
                                                      None if dirs is None else dirs[i]))

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """σ ``[N]`` at world points ``[N, 3]`` (the far field outside the box, as ``query``)."""
        if self.far is None or points.shape[0] == 0:
            return self.fine.density(points)
        return self._route(points, lambda net, i: (net.density(points[i]),))[0]

    def forward(self, points: torch.Tensor, dirs: torch.Tensor | None = None):
        return self.fine(points, dirs)
