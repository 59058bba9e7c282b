"""The radiance-field protocol the conversion step works on, and its adapters.

The conversion (§4.2) needs only two things from a trained model: the density σ at world
points, and the colour coefficients there. :class:`RadianceField` spells that out; three
adapters plug into it:

* :class:`NeRFField` wraps a trained :class:`plenoctree.nerf.NeRFModel` (``load_nerf``) — it
  runs the fine network without gradients, in chunks, and zeroes σ where the NeRF itself never
  samples (outside its scene box and, for the occupancy sampler, outside occupied cells);
* :class:`AnalyticField` wraps the analytic procedural scene (or any numpy ``density`` /
  ``coeffs`` functions) — a NeRF-SH whose answer is known exactly, for tests;
* :class:`AnalyticPlainField` is the same scene seen as a *plain* NeRF: ``query(points, dirs)``
  returns the view-dependent raw colour ``logit(rgb) = Σ_b k_b Y_b(d)``, so SH projection
  (:mod:`plenoctree.convert.projection`) can be checked against the known coefficients.

Every method takes and returns numpy float32 arrays in world units: points ``[N, 3]``, σ ``[N]``
(1 / world length, ≥ 0), coefficients ``[N, 3·B]`` channel-major pre-sigmoid (the octree leaf
layout), and for plain fields raw RGB ``[N, 3]`` (pre-sigmoid) along unit ``dirs [N, 3]``.
"""

from __future__ import annotations

from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from ..errors import ConfigError
from ..sh import eval_sh_bases, num_sh_bases

__all__ = ["RadianceField", "AnalyticField", "AnalyticPlainField", "NeRFField", "as_field"]


@runtime_checkable
class RadianceField(Protocol):
    """What the conversion needs from a radiance field.

    Attributes:
        basis: ``"sh"``, ``"sg"`` (coefficients of a fixed basis; converted by averaging) or
            ``"plain"`` (view-dependent raw RGB; converted by SH projection).
        data_format: octree format of the coefficients (``"SH16"``, ``"SG25"``; plain: ``"RGBA"``).
        extra_data: SG lobes float32 ``[B, 4]`` (sharpness, μ) or ``None``.
        scene_bbox: float ``[2, 3]`` world box the field was trained in, or ``None``.
    """

    basis: str
    data_format: str
    extra_data: np.ndarray | None
    scene_bbox: np.ndarray | None

    def density(self, points: np.ndarray) -> np.ndarray:
        """σ ``[N]`` float32 at world points ``[N, 3]``."""

    def query(self, points: np.ndarray, dirs: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """``(sigma [N], coeffs [N, C])``; ``dirs [N, 3]`` (unit) only for plain fields."""


def _points(x: Any, name: str = "points") -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ConfigError(f"{name}: expected shape (N, 3), got {list(x.shape)}")
    return x


class AnalyticField:
    """A NeRF-SH given by numpy functions (default: the procedural scene's fields).

    Args:
        density_fn: world points ``[N, 3]`` -> σ ``[N]`` (default
            :func:`plenoctree.datasets.procedural.density`).
        coeffs_fn: world points ``[N, 3]`` -> ``[N, 3·(d+1)^2]`` pre-sigmoid SH coefficients
            (default :func:`~plenoctree.datasets.procedural.sh_coeffs`, degree 3).
        sh_degree: SH degree of ``coeffs_fn``.
        scene_bbox: ``[2, 3]`` box holding the content (default: the procedural box ``[-1, 1]^3``).
    """

    basis = "sh"
    extra_data = None

    def __init__(self, density_fn: Callable | None = None, coeffs_fn: Callable | None = None,
                 sh_degree: int = 3, scene_bbox: Any = None):
        from ..datasets import procedural

        self._density = density_fn or procedural.density
        self._coeffs = coeffs_fn or procedural.sh_coeffs
        self.sh_degree = int(sh_degree)
        self.basis_dim = num_sh_bases(self.sh_degree)
        self.data_format = f"SH{self.basis_dim}"
        if scene_bbox is None:
            c, r = procedural.SCENE_CENTER, procedural.SCENE_RADIUS
            scene_bbox = np.stack([c - r, c + r])
        self.scene_bbox = np.asarray(scene_bbox, dtype=np.float64).reshape(2, 3)

    def density(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(self._density(_points(points)), dtype=np.float32)

    def query(self, points: np.ndarray, dirs: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points)
        return self.density(p), np.asarray(self._coeffs(p), dtype=np.float32)


class AnalyticPlainField(AnalyticField):
    """The same analytic scene as a *plain* NeRF: colour depends on a view-direction input.

    ``query(points, dirs)`` returns ``(σ [N], raw [N, 3])`` with
    ``raw_c = Σ_b k_{c,b}(x) Y_b(d)`` — the inverse sigmoid of the colour the NeRF-SH version
    shows along ``d``. Projecting ``raw`` onto SH of degree ≥ ``sh_degree`` recovers ``k``.
    """

    basis = "plain"
    data_format = "RGBA"

    def __init__(self, *args: Any, **kw: Any):
        super().__init__(*args, **kw)
        self.data_format = "RGBA"

    def query(self, points: np.ndarray, dirs: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        if dirs is None:
            raise ConfigError("a plain radiance field needs view directions")
        p = _points(points)
        d = _points(dirs, "dirs")
        k = np.asarray(self._coeffs(p), dtype=np.float32).reshape(len(p), 3, self.basis_dim)
        y = eval_sh_bases(self.sh_degree, d.astype(np.float32))               # [N, B]
        return self.density(p), np.einsum("ncb,nb->nc", k, y).astype(np.float32)

    def query_directions(self, points: np.ndarray, dirs: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """``(σ [P], raw [P, N, 3])`` at ``P`` points along ``N`` shared unit ``dirs``."""
        p = _points(points)
        d = _points(dirs, "dirs")
        k = np.asarray(self._coeffs(p), dtype=np.float32).reshape(len(p), 3, self.basis_dim)
        y = eval_sh_bases(self.sh_degree, d)                                  # [N, B]
        return self.density(p), np.einsum("pcb,nb->pnc", k, y, optimize=True).astype(np.float32)


class NeRFField:
    """Adapter from a trained :class:`~plenoctree.nerf.NeRFModel` to :class:`RadianceField`.

    The fine network is evaluated under ``torch.no_grad`` (optionally in bf16 autocast) on
    ``device``. σ is set to 0 outside the model's ``scene_bbox`` (or, with a far field, outside
    its outer cube) and, when the model has an occupancy grid and ``use_occupancy``, in the
    box's unoccupied cells: the NeRF's own renderer never
    samples there, so whatever the network says in those places is never seen in training.

    Args:
        model: the network (``load_nerf(run_dir)``).
        device: torch device for the network.
        amp: evaluate the MLP in bf16 autocast (faster on CPUs with bf16 units, less exact).
        use_occupancy: apply the occupancy mask (see above).
    """

    def __init__(self, model: Any, device: str = "cpu", amp: bool = False,
                 use_occupancy: bool = True):
        import torch

        self.model = model.eval()
        self.device = torch.device(device)
        self.model.to(self.device)
        self.amp = bool(amp)
        self.basis = model.basis
        self.basis_dim = int(model.basis_dim)
        self.sh_degree = int(model.sh_degree)
        self.data_format = model.data_format
        self.extra_data = model.sg_extra_data() if self.basis == "sg" else None
        self.scene_bbox = model.scene_bbox.detach().cpu().numpy().astype(np.float64)
        occ = getattr(model, "occupancy", None)
        self._occ = None
        if use_occupancy and occ is not None:
            mask = occ.mask.detach().to(self.device)
            self._occ = (mask, occ.bbox.detach().to(self.device),
                         torch.tensor(mask.shape, device=self.device))
        # on the device once, not uploaded at every query
        self._box = torch.as_tensor(self.scene_bbox, dtype=torch.float32, device=self.device)

    def _ctx(self):
        import contextlib

        import torch

        if not self.amp:
            return contextlib.nullcontext()
        return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)

    def _visible(self, p) -> Any:
        """Bool ``[N]``: the NeRF's renderer may sample world points ``p [N, 3]`` (torch)."""
        import torch

        box = self._box.to(p.dtype)
        in_box = ((p >= box[0]) & (p <= box[1])).all(-1)
        ok = in_box
        if self._occ is not None:
            mask, bbox, res = self._occ
            g = ((p - bbox[0]) / (bbox[1] - bbox[0]) * res).floor().long()
            inside = ((g >= 0) & (g < res)).all(-1)
            g = torch.minimum(torch.clamp(g, min=0), res - 1)
            ok = ok & inside & mask[g[:, 0], g[:, 1], g[:, 2]]
        far = getattr(self.model, "far", None)
        if far is not None:             # the far field's shells, up to the outer cube
            outer = far.outer_bbox().to(device=p.device, dtype=p.dtype)
            ok = ok | (~in_box & ((p >= outer[0]) & (p <= outer[1])).all(-1))
        return ok

    def density_torch(self, p: Any) -> Any:
        """σ ``[N]`` (float32 tensor, 0 where the NeRF never samples) at world points
        ``p [N, 3]`` (float32 tensor on :attr:`device`)."""
        import torch

        vis = self._visible(p)
        sigma = torch.zeros(p.shape[0], dtype=torch.float32, device=p.device)
        idx = vis.nonzero()[:, 0]
        if idx.numel():                  # the network runs only where the NeRF samples
            with torch.no_grad(), self._ctx():
                pv = p[idx]
                s = self.model.density(pv) if hasattr(self.model, "density") else \
                    self.model.query(pv)[0]
            sigma[idx] = s.float()
        return sigma

    def query_torch(self, p: Any) -> tuple[Any, Any]:
        """``(σ [N], coefficients [N, 3·B])`` float32 tensors at world points ``p [N, 3]``
        (float32 tensor on :attr:`device`; NeRF-SH / NeRF-SG: no view directions): what
        :meth:`query` returns, left on the device (:mod:`.device_sampling`)."""
        import torch

        if self.basis == "plain":
            raise ConfigError("a plain NeRF (basis 'plain') needs view directions")
        with torch.no_grad(), self._ctx():
            sigma, coeffs = self.model.query(p, None)
        sigma = torch.where(self._visible(p), sigma.float(), torch.zeros((), device=p.device))
        return sigma, coeffs.float()

    def density(self, points: np.ndarray) -> np.ndarray:
        import torch

        p = torch.from_numpy(_points(points)).to(self.device)
        return self.density_torch(p).cpu().numpy()

    def query(self, points: np.ndarray, dirs: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        import torch

        p = torch.from_numpy(_points(points)).to(self.device)
        if dirs is None and self.basis != "plain":
            sigma, coeffs = self.query_torch(p)
            return sigma.cpu().numpy(), coeffs.cpu().numpy()
        d = None if dirs is None else torch.from_numpy(_points(dirs, "dirs")).to(self.device)
        if self.basis == "plain" and d is None:
            raise ConfigError("a plain NeRF (basis 'plain') needs view directions")
        with torch.no_grad(), self._ctx():
            sigma, coeffs = self.model.query(p, d)
        sigma = torch.where(self._visible(p), sigma.float(), torch.zeros((), device=p.device))
        return sigma.cpu().numpy(), coeffs.float().cpu().numpy()

    def query_directions(self, points: np.ndarray, dirs: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Plain NeRFs: ``(σ [P], raw [P, N, 3])`` at ``P`` points seen along ``N`` shared dirs.

        Runs the position trunk once per point and only the small view-dependent head per
        (point, direction) pair when the network has the standard NeRF head layout
        (``bottleneck``, ``view_enc``, ``view_layer``, ``rgb_head``); otherwise it falls back
        to ``query`` on every pair.
        """
        import torch

        p = torch.from_numpy(_points(points)).to(self.device)
        d = torch.from_numpy(_points(dirs, "dirs")).to(self.device)
        f = self.model.fine
        n_p, n_d = p.shape[0], d.shape[0]
        parts = ("_features", "sigma_head", "bottleneck", "view_enc", "view_layer", "rgb_head")
        with torch.no_grad(), self._ctx():
            if all(hasattr(f, a) for a in parts):
                h = f._features(p)[:n_p]                         # (may be padded)
                sigma = f._sigma(f.sigma_head(h)[:, 0])
                b = f.bottleneck(h)                                            # [P, W]
                v = f.view_enc(d.to(b.dtype))                                  # [N, V]
                w = f.view_layer.weight                                        # [Wv, W + V]
                hb = b @ w[:, :b.shape[1]].T.to(b.dtype)                       # [P, Wv]
                hv = v @ w[:, b.shape[1]:].T.to(v.dtype) + f.view_layer.bias.to(v.dtype)
                raw = f.rgb_head(torch.relu(hb[:, None, :] + hv[None, :, :]))  # [P, N, 3]
            else:
                pp = p[:, None, :].expand(n_p, n_d, 3).reshape(-1, 3)
                dd = d[None, :, :].expand(n_p, n_d, 3).reshape(-1, 3)
                sig_all, raw = self.model.query(pp, dd)
                sigma = sig_all.reshape(n_p, n_d)[:, 0]
                raw = raw.reshape(n_p, n_d, 3)
        sigma = torch.where(self._visible(p), sigma.float(), torch.zeros((), device=p.device))
        return sigma.cpu().numpy(), raw.float().cpu().numpy()


def as_field(obj: Any, **kw: Any) -> RadianceField:
    """``obj`` if it already is a :class:`RadianceField`, a :class:`NeRFField` if it is a
    NeRF model (has ``query`` and ``fine``), else :class:`ConfigError`."""
    if hasattr(obj, "fine") and hasattr(obj, "query") and hasattr(obj, "scene_bbox") \
            and not isinstance(obj, NeRFField):
        return NeRFField(obj, **kw)
    if isinstance(obj, RadianceField):
        if obj.basis not in ("sh", "sg", "plain"):
            raise ConfigError(f"radiance field basis must be sh, sg or plain, got {obj.basis!r}")
        return obj
    raise ConfigError(f"expected a radiance field (density/query/basis/data_format), got "
                      f"{type(obj).__name__}")
