"""Normalised device coordinates (NDC) for forward-facing scenes, as in the NeRF paper.

A forward-facing capture looks down the world -z axis (LLFF poses are recentred so that the
average camera is the identity). The perspective projection of a reference pinhole camera at
the world origin with focal lengths ``fx, fy`` over a ``W x H`` image maps the frustum between
the near plane ``z = -n`` and infinity onto the cube ``[-1, 1]^3``:

    x' = -(2 fx / W) x / z,    y' = -(2 fy / H) y / z,    z' = 1 + 2 n / z

Straight world rays stay straight in NDC. A ray ``o + t d`` (``d_z < 0``) is first moved to
the near plane, ``o_n = o + t_n d`` with ``t_n = -(n + o_z) / d_z``; its NDC origin is the
projection of ``o_n`` (so ``o'_z = -1``) and its NDC direction is

    d' = (-(2 fx / W) (d_x / d_z - o_x / o_z),  -(2 fy / H) (d_y / d_z - o_y / o_z),  -2 n / o_z)

(evaluated at ``o = o_n``), so ``o' + d'`` is the vanishing point of the ray (``z' = 1``).
NeRF samples ``o' + s d'`` for ``s`` in ``[0, 1]`` and measures segment lengths in NDC space
(``δ = Δs |d'|``); our rays carry the *unit* NDC direction ``d' / |d'|``, so the distance
``t`` along it runs over ``[0, |d'|]`` and the same NDC-space δ results. Densities learned or
stored for NDC rays are therefore per unit NDC length.

Functions accept numpy arrays or torch tensors (returned in the same library, dtype and
device; numpy inputs are computed in float64 and returned as float32).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import ConfigError

__all__ = ["to_ndc_rays", "ndc_to_world", "world_to_ndc", "ndc_bounds"]


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _check_params(fx: float, fy: float, width: float, height: float, near: float) -> None:
    for name, v in (("fx", fx), ("fy", fy), ("width", width), ("height", height),
                    ("near", near)):
        try:
            ok = np.isfinite(float(v)) and float(v) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ConfigError(f"NDC: {name} must be a finite positive number, got {v!r}")


def to_ndc_rays(origins: Any, dirs: Any, fx: float, fy: float, width: float, height: float,
                near: float = 1.0, normalize: bool = True) -> tuple[Any, Any]:
    """Convert world rays of a forward-facing scene to NDC rays.

    Args:
        origins: ``[..., 3]`` ray origins, world units (numpy or torch).
        dirs: ``[..., 3]`` ray directions (any length); every ray must point down the world
            -z axis (``d_z < 0``), as in a forward-facing capture.
        fx, fy: focal lengths of the NDC reference camera, pixels.
        width, height: its image size, pixels.
        near: world distance of the near plane ``z = -near`` (NeRF: 1).
        normalize: return unit NDC directions (default, the :class:`Cameras` contract);
            ``False`` returns NeRF's ``d'`` whose end point ``o' + d'`` lies on ``z' = 1``.

    Returns:
        ``(origins_ndc [..., 3], dirs_ndc [..., 3])``: origins on the plane ``z' = -1``.

    Raises:
        ConfigError: shapes differ / are not ``(..., 3)``, bad parameters, or a ray with
            ``d_z >= 0`` or non-finite values (it never reaches the far side of the NDC cube).

    >>> o, d = to_ndc_rays(np.zeros((1, 3)), np.array([[0., 0., -1.]]), 1., 1., 2., 2.)
    >>> o.tolist(), d.tolist()
    ([[0.0, 0.0, -1.0]], [[0.0, 0.0, 1.0]])
    """
    _check_params(fx, fy, width, height, near)
    torch_in = _is_torch(origins) or _is_torch(dirs)
    if torch_in:
        import torch

        o = torch.as_tensor(origins)
        d = torch.as_tensor(dirs, device=o.device)
        out_dtype = o.dtype if o.is_floating_point() else torch.float32
        o, d = o.double(), d.double()
        shape_o, shape_d = tuple(o.shape), tuple(d.shape)
    else:
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        shape_o, shape_d = o.shape, d.shape
    if shape_o != shape_d or len(shape_o) < 1 or shape_o[-1] != 3:
        raise ConfigError(f"NDC: origins {list(shape_o)} and dirs {list(shape_d)} must both "
                          "have shape (..., 3)")
    dz = d[..., 2]
    bad = ~(dz < 0)                       # catches NaN too
    if bool(bad.any()):
        raise ConfigError(f"NDC: {int(bad.sum())} ray(s) do not point down the world -z axis "
                          "(d_z >= 0 or NaN); NDC needs a forward-facing scene whose cameras "
                          "look down -z (LLFF poses after recentring)")
    t = -(near + o[..., 2]) / dz
    o = o + t[..., None] * d
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    ax, ay = -2.0 * fx / width, -2.0 * fy / height
    rx, ry = ox / oz, oy / oz
    parts_o = (ax * rx, ay * ry, 1.0 + 2.0 * near / oz)
    parts_d = (ax * (d[..., 0] / dz - rx), ay * (d[..., 1] / dz - ry), -2.0 * near / oz)
    if torch_in:
        o_ndc = torch.stack(parts_o, -1)
        d_ndc = torch.stack(parts_d, -1)
        finite = bool(torch.isfinite(o_ndc).all() and torch.isfinite(d_ndc).all())
    else:
        o_ndc = np.stack(parts_o, -1)
        d_ndc = np.stack(parts_d, -1)
        finite = bool(np.isfinite(o_ndc).all() and np.isfinite(d_ndc).all())
    if not finite:
        raise ConfigError("NDC: rays produced non-finite NDC coordinates (infinite inputs?)")
    if normalize:
        if torch_in:
            d_ndc = d_ndc / torch.linalg.vector_norm(d_ndc, dim=-1, keepdim=True)
        else:
            d_ndc = d_ndc / np.linalg.norm(d_ndc, axis=-1, keepdims=True)
    if torch_in:
        return o_ndc.to(out_dtype), d_ndc.to(out_dtype)
    return o_ndc.astype(np.float32), d_ndc.astype(np.float32)


def world_to_ndc(points: np.ndarray, fx: float, fy: float, width: float, height: float,
                 near: float = 1.0) -> np.ndarray:
    """Project world points ``[..., 3]`` (``z < 0``) to NDC, float64 (``z = -near`` → ``z' = -1``)."""
    _check_params(fx, fy, width, height, near)
    p = np.asarray(points, dtype=np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([-2.0 * fx / width * p[..., 0] / z, -2.0 * fy / height * p[..., 1] / z,
                         1.0 + 2.0 * near / z], -1)


def ndc_to_world(points: np.ndarray, fx: float, fy: float, width: float, height: float,
                 near: float = 1.0) -> np.ndarray:
    """Inverse of :func:`world_to_ndc` for NDC points ``[..., 3]`` with ``z' < 1``, float64.

    ``z = 2 near / (z' - 1)``, ``x = -x' z W / (2 fx)``, ``y = -y' z H / (2 fy)``; points with
    ``z' >= 1`` (at or past infinity) map to non-finite values.
    """
    _check_params(fx, fy, width, height, near)
    p = np.asarray(points, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(p[..., 2] < 1.0, 2.0 * near / (p[..., 2] - 1.0), np.nan)
        return np.stack([-p[..., 0] * z * width / (2.0 * fx),
                         -p[..., 1] * z * height / (2.0 * fy), z], -1)


def ndc_bounds(c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
               ndc_fx: float, ndc_fy: float, near: float = 1.0) -> tuple[float, np.ndarray]:
    """Sampling bound and NDC box covering every pixel ray of some cameras.

    NDC rays are straight and, per camera, the raw NDC direction is affine in the pixel
    position, so the rays through the four image *corners* (pixel edges, independent of any
    downscaling) bound all others: their segments from ``z' = -1`` to ``z' = 1`` span the box.

    Args:
        c2w: ``[N, 4, 4]`` camera-to-world matrices (OpenGL). intrinsics: ``[N, 4]``
            ``(fx, fy, cx, cy)`` per camera. width, height: image size, pixels.
        ndc_fx, ndc_fy, near: the NDC reference camera (see :func:`to_ndc_rays`).

    Returns:
        ``far``: the largest NDC length ``|d'|`` of a ray from ``z' = -1`` to ``z' = 1`` (the
        distance along unit NDC directions at which every ray has left the cube), and
        ``bbox`` float32 ``[2, 3]``: min/max NDC corner holding every ray segment, z in
        ``[-1, 1]``, x and y at least ``[-1, 1]``.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    k = np.asarray(intrinsics, dtype=np.float64).reshape(-1, 4)
    us = np.array([0.0, width, 0.0, width])
    vs = np.array([0.0, 0.0, height, height])
    d_cam = np.stack([(us[None] - k[:, 2:3]) / k[:, 0:1], -(vs[None] - k[:, 3:4]) / k[:, 1:2],
                      -np.ones((len(k), 4))], -1)                          # [N, 4, 3]
    dirs = np.einsum("nij,nkj->nki", c2w[:, :3, :3], d_cam)
    origins = np.broadcast_to(c2w[:, None, :3, 3], dirs.shape)
    o, d = to_ndc_rays(origins, dirs, ndc_fx, ndc_fy, width, height, near, normalize=False)
    o = o.astype(np.float64).reshape(-1, 3)
    d = d.astype(np.float64).reshape(-1, 3)
    ends = np.concatenate([o, o + d])
    lo = np.minimum(ends.min(0), -1.0)
    hi = np.maximum(ends.max(0), 1.0)
    lo[2], hi[2] = -1.0, 1.0
    far = float(np.linalg.norm(d, axis=1).max())
    return far, np.stack([lo, hi]).astype(np.float32)
