"""The NDC space a forward-facing (LLFF) tree lives in, carried by the tree itself.

A tree extracted from a NeRF trained on NDC rays (:mod:`plenoctree.datasets.ndc`) has its box in
NeRF's normalised device coordinates of a *reference camera*: the identity pose at the world
origin looking down ``-z``, focal lengths ``fx, fy`` (pixels) for a ``width`` x ``height``
image, near plane ``z = -near``. A world ray ``o + t d`` becomes the NDC ray of
``to_ndc_rays(o, d, fx, fy, width, height, near)``; a world point ``(x, y, z)`` (``z < 0``) maps
to ``(-2 fx x / (W z), -2 fy y / (H z), 1 + 2 near / z)``. Only ``2 fx / W``, ``2 fy / H`` and
``near`` matter (the space does not change with the image size).

:class:`NDCSpace` is ``Octree.ndc`` (None for ordinary, world-space trees) and is stored in every
tree file: the native ``.npz`` header (``format_version`` 2), the ``.plnz`` header and the svox
layout's extra ``ndc_config`` key (float64 ``[5]``: width, height, fx, fy, near; svox and volrend
ignore unknown keys; ``svox.NDCConfig(width, height, focal=fx)`` is the svox renderer's
equivalent). Octree layer: imports nothing from :mod:`plenoctree.datasets`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import TreeFormatError

__all__ = ["NDCSpace"]

_KEYS = ("width", "height", "fx", "fy", "near")


@dataclass(frozen=True)
class NDCSpace:
    """NDC reference camera of a forward-facing tree.

    Attributes:
        width, height: reference image size, pixels (> 0).
        fx, fy: reference focal lengths, pixels (> 0).
        near: world distance of the near plane ``z = -near`` (NeRF: 1).
    """

    width: int
    height: int
    fx: float
    fy: float
    near: float = 1.0

    def __post_init__(self) -> None:
        for key in ("width", "height"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) \
                    and not (isinstance(v, (float, np.floating)) and float(v).is_integer()):
                raise TreeFormatError(f"NDC {key} must be a positive integer, got {v!r}")
            if int(v) <= 0:
                raise TreeFormatError(f"NDC {key} must be a positive integer, got {v!r}")
            object.__setattr__(self, key, int(v))
        for key in ("fx", "fy", "near"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(float(v)) or float(v) <= 0:
                raise TreeFormatError(f"NDC {key} must be a finite positive number, got {v!r}")
            object.__setattr__(self, key, float(v))

    # ------------------------------------------------------------------ conversions
    def to_json(self) -> dict:
        """``{"width", "height", "fx", "fy", "near"}`` (the viewer bundle's ``config.ndc``)."""
        return {k: getattr(self, k) for k in _KEYS}

    @classmethod
    def from_json(cls, obj: Any, what: str = "ndc") -> NDCSpace:
        """Parse :meth:`to_json`'s dict; ``TreeFormatError("<what>: ...")`` when malformed."""
        if not isinstance(obj, dict) or any(k not in obj for k in _KEYS):
            raise TreeFormatError(f"{what}: NDC settings must be an object with keys "
                                  f"{list(_KEYS)}, got {obj!r}")
        try:
            return cls(*(obj[k] for k in _KEYS))
        except TreeFormatError as e:
            raise TreeFormatError(f"{what}: {e}") from None

    def as_array(self) -> np.ndarray:
        """float64 ``[5]``: width, height, fx, fy, near (the svox layout's ``ndc_config``)."""
        return np.array([getattr(self, k) for k in _KEYS], dtype=np.float64)

    @classmethod
    def from_array(cls, a: Any, what: str = "ndc_config") -> NDCSpace:
        a = np.asarray(a, dtype=np.float64).reshape(-1)
        if a.shape != (5,):
            raise TreeFormatError(f"{what}: must be 5 numbers (width, height, fx, fy, near), "
                                  f"got {a.size}")
        try:
            return cls(*a.tolist())
        except TreeFormatError as e:
            raise TreeFormatError(f"{what}: {e}") from None

    @classmethod
    def from_cameras(cls, cameras: Any) -> NDCSpace | None:
        """The NDC space of :class:`~plenoctree.datasets.Cameras` (None unless ``ndc``)."""
        if cameras is None or not getattr(cameras, "ndc", False):
            return None
        fx, fy = cameras.ndc_focal
        return cls(int(cameras.width), int(cameras.height), fx, fy, float(cameras.ndc_near))

    def apply(self, cameras: Any) -> Any:
        """``cameras`` (world-space :class:`~plenoctree.datasets.Cameras`, any intrinsics) made
        to return this space's NDC rays: ``ndc=True``, ``ndc_near``, ``ndc_ref``, and
        ``ndc_clip`` (any camera draws: a view is never refused for where it looks)."""
        import dataclasses

        return dataclasses.replace(cameras, ndc=True, ndc_near=self.near, ndc_clip=True,
                                   ndc_ref=(2.0 * self.fx / self.width,
                                            2.0 * self.fy / self.height))

    def same_space(self, other: NDCSpace, rtol: float = 1e-5) -> bool:
        """Whether ``other`` defines the same NDC map (``2 fx / W``, ``2 fy / H``, ``near``)."""
        a = (2 * self.fx / self.width, 2 * self.fy / self.height, self.near)
        b = (2 * other.fx / other.width, 2 * other.fy / other.height, other.near)
        return all(abs(x - y) <= rtol * abs(x) for x, y in zip(a, b))

    # ------------------------------------------------------------------ point maps
    def world_to_ndc(self, p: Any) -> np.ndarray:
        """World points ``[..., 3]`` (``z < 0``) -> NDC points ``[..., 3]``, float64."""
        p = np.asarray(p, dtype=np.float64)
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        return np.stack([-2.0 * self.fx / self.width * x / z,
                         -2.0 * self.fy / self.height * y / z,
                         1.0 + 2.0 * self.near / z], -1)

    def ndc_to_world(self, q: Any) -> np.ndarray:
        """NDC points ``[..., 3]`` (``z' < 1``) -> world points ``[..., 3]``, float64
        (inverse of :meth:`world_to_ndc`; ``z' -> 1`` goes to infinite depth)."""
        q = np.asarray(q, dtype=np.float64)
        z = 2.0 * self.near / (q[..., 2] - 1.0)
        return np.stack([-q[..., 0] * z * self.width / (2.0 * self.fx),
                         -q[..., 1] * z * self.height / (2.0 * self.fy), z], -1)
