"""Renderer options and output, plus the data-format parsing shared by every backend.

Nothing here compiles or imports a kernel; both the torch twin and the numba kernel read the
same :class:`RenderOptions` and the same :class:`FormatInfo`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigError, TreeFormatError

__all__ = ["RenderOptions", "RenderOutput", "FormatInfo", "parse_data_format", "QUANT_BITS"]

#: Tree-space points are located on a grid of ``2**QUANT_BITS`` cells per axis (integer
#: coordinates); a tree may therefore be at most ``QUANT_BITS - 1`` levels deep.
QUANT_BITS = 30

KIND_SH, KIND_SG, KIND_RGBA = 0, 1, 2


@dataclass
class RenderOptions:
    """Knobs of the octree volume renderer (same names in every backend and in the viewer).

    Attributes:
        stop_thresh: early ray termination: a ray stops as soon as its transmittance T falls
            below this value; ``0`` disables early stopping (march to the box exit).
        background: RGB in [0, 1] composited with the transmittance left at the end of the ray.
        sh_min: first basis index used for colour (SH/SG inspection); ``0`` = from the start.
        sh_max: last basis index used for colour (inclusive); ``-1`` = up to the last basis,
            values past the last basis are clamped to it. ``sh_min > sh_max`` uses no basis at
            all, so every colour channel is ``sigmoid(0) = 0.5`` (flat grey).
        step_eps: push past voxel boundaries, in tree units (the tree box is ``[0, 1]^3``): the
            leaf of a segment is looked up ``step_eps`` past its start, and every segment is at
            least that long (this guarantees progress on degenerate boundaries).
        renormalize: svox's ``fast`` colour rule for a ray stopped early (``T < stop_thresh``):
            its colour is ``Σ w c / (1 - T)`` and its alpha 1 (the background is dropped), as
            if what lies behind looked like what the ray saw; rays that leave the box are
            composited with the background as always. With a larger ``stop_thresh`` this is
            the fast mode: fewer leaves a ray (lounge's far-field tree at ``stop_thresh`` 0.1:
            1.22–1.25x the frame rate for 0.24 dB; docs/results.md). ``False``: the exact rule.
    """

    stop_thresh: float = 0.01
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    sh_min: int = 0
    sh_max: int = -1
    step_eps: float = 1e-6
    renormalize: bool = False

    def validated(self) -> RenderOptions:
        """Return ``self`` after checking every field; raises :class:`ConfigError`."""
        stop = _finite_float("stop_thresh", self.stop_thresh)
        if not 0.0 <= stop < 1.0:
            raise ConfigError(f"RenderOptions.stop_thresh must be in [0, 1), got {stop!r}")
        try:
            bg = tuple(float(v) for v in self.background)
        except (TypeError, ValueError):
            raise ConfigError(
                f"RenderOptions.background must be 3 numbers, got {self.background!r}") from None
        if len(bg) != 3 or not all(math.isfinite(v) for v in bg):
            raise ConfigError(
                f"RenderOptions.background must be 3 finite numbers, got {self.background!r}")
        for name in ("sh_min", "sh_max"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) and not hasattr(v, "__index__"):
                raise ConfigError(f"RenderOptions.{name} must be an integer, got {v!r}")
        if int(self.sh_min) < 0:
            raise ConfigError(f"RenderOptions.sh_min must be >= 0, got {self.sh_min!r}")
        if int(self.sh_max) < -1:
            raise ConfigError(f"RenderOptions.sh_max must be >= -1 (-1 = all), got {self.sh_max!r}")
        eps = _finite_float("step_eps", self.step_eps)
        if not 0.0 < eps <= 1e-2:
            raise ConfigError(f"RenderOptions.step_eps must be in (0, 1e-2], got {eps!r}")
        if not isinstance(self.renormalize, bool):
            raise ConfigError(f"RenderOptions.renormalize must be True or False, got "
                              f"{self.renormalize!r}")
        return self

    def basis_range(self, basis_dim: int) -> tuple[int, int]:
        """``(first, last)`` basis indices used (inclusive), clamped to ``[0, basis_dim - 1]``.

        ``first > last`` means no basis is used.
        """
        last = basis_dim - 1 if int(self.sh_max) < 0 else min(int(self.sh_max), basis_dim - 1)
        return int(self.sh_min), last


def _finite_float(name: str, v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"RenderOptions.{name} must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise ConfigError(f"RenderOptions.{name} must be finite, got {v!r}")
    return f


@dataclass
class RenderOutput:
    """What a render returns (torch tensors, on the device of the input for CUDA rays).

    Attributes:
        rgb: ``[..., 3]`` composited colour in [0, 1] (background included).
        depth: ``[...]`` expected termination distance along the unit ray direction, world
            units, measured from the ray origin; ``0`` where nothing was hit (alpha = 0).
        alpha: ``[...]`` opacity ``1 - T`` (T = transmittance left at the end of the ray).
    """

    rgb: Any
    depth: Any
    alpha: Any


@dataclass(frozen=True)
class FormatInfo:
    """Parsed data format: ``kind`` (SH/SG/RGBA code), ``basis_dim`` B, ``sh_degree`` (SH only)."""

    name: str
    kind: int
    basis_dim: int
    sh_degree: int = -1

    @property
    def data_dim(self) -> int:
        """Values per cell: ``3 * B + 1`` (``4`` for RGBA)."""
        return 4 if self.kind == KIND_RGBA else 3 * self.basis_dim + 1


_SH_DEGREE = {1: 0, 4: 1, 9: 2, 16: 3, 25: 4}


def parse_data_format(data_format: str, data_dim: int | None = None,
                      extra_data: Any = None) -> FormatInfo:
    """Parse ``"SH1".."SH25"``, ``"SG<B>"`` or ``"RGBA"`` (the names
    :func:`plenoctree.octree.parse_data_format` accepts, exactly) and check ``data_dim`` and
    ``extra_data`` against it.

    Raises :class:`TreeFormatError` naming the problem when the format is unknown or
    inconsistent with the data (``data_dim`` must be ``3 * B + 1``; SG needs ``extra_data`` of
    shape ``[B, 4]``).
    """
    from ..octree.tree import parse_data_format as parse_name    # the one naming rule

    kind, b = parse_name(data_format)
    if kind == "RGBA":
        info = FormatInfo(data_format, KIND_RGBA, 1)
    elif kind == "SH":
        info = FormatInfo(data_format, KIND_SH, b, _SH_DEGREE[b])
    else:
        info = FormatInfo(data_format, KIND_SG, b)
    if data_dim is not None and int(data_dim) != info.data_dim:
        raise TreeFormatError(
            f"data format {info.name} needs data_dim {info.data_dim}, but the data has {data_dim}")
    if info.kind == KIND_SG:
        shape = None if extra_data is None else tuple(extra_data.shape)
        if shape != (info.basis_dim, 4):
            raise TreeFormatError(
                f"data format {info.name} needs extra_data of shape ({info.basis_dim}, 4) "
                f"(sharpness, mu_x, mu_y, mu_z), got {shape}")
    return info
