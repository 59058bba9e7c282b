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

**Any camera** (``clip=True``, the viewer's and every tree view's rule: ``tree.ndc.apply``):
a view is never refused for where the camera stands or looks. A camera in front of the near
plane (``o_z > -n``) whose ray points down -z gets NeRF's ray above; one whose ray does not
(``d_z >= 0``) never reaches the NDC volume and becomes a *miss* ray (:data:`MISS_ORIGIN`,
pointing +z', away from every NDC box: it draws the background). A camera inside the volume
(``o_z <= -n``, it flew past the near plane) starts at its own NDC point ``P(o)`` (not at
the near plane behind it) and follows the image of its ray, whose direction is the
derivative of the projection times ``z^2 > 0``:

    d' ∝ (ax (d_x o_z - o_x d_z),  ay (d_y o_z - o_y d_z),  -2 n d_z),   ax = -2 fx / W, ...

Rays whose NDC origin lies beyond :data:`CLIP_EXTENT` across (within a hair of the horizon)
also miss: they meet the NDC box only at infinity.

Functions accept numpy arrays or torch tensors (returned in the same library, dtype and
device; numpy inputs are computed in float64 and returned as float32).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import ConfigError

__all__ = ["to_ndc_rays", "ndc_to_world", "world_to_ndc", "ndc_bounds", "MISS_ORIGIN",
           "CLIP_EXTENT"]

#: NDC origin of a ray that never meets the NDC volume (``clip=True``): far past ``z' = 1``,
#: with direction ``+z'``, so it leaves every NDC tree box untouched (the background).
MISS_ORIGIN = (0.0, 0.0, 1.0e4)
#: ``clip=True``: rays whose NDC origin lies farther than this from the axis in x' or y' miss.
CLIP_EXTENT = 1.0e4
_MIN_DZ = 1.0e-12      # clip=True: NeRF's ray needs d_z below -this (t stays finite)


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
                near: float = 1.0, normalize: bool = True, clip: bool = False) -> tuple[Any, Any]:
    """Convert world rays of a forward-facing scene to NDC rays.

    Args:
        origins: ``[..., 3]`` ray origins, world units (numpy or torch).
        dirs: ``[..., 3]`` ray directions (any length); every ray must point down the world
            -z axis (``d_z < 0``), as in a forward-facing capture (unless ``clip``).
        fx, fy: focal lengths of the NDC reference camera, pixels.
        width, height: its image size, pixels.
        near: world distance of the near plane ``z = -near`` (NeRF: 1).
        normalize: return unit NDC directions (default, the :class:`Cameras` contract);
            ``False`` returns NeRF's ``d'`` whose end point ``o' + d'`` lies on ``z' = 1``.
        clip: any camera (the module's "any camera" rule): rays that never reach the NDC
            volume become miss rays, a camera past the near plane starts where it stands.
            A ray NeRF's rule covers (from in front of the near plane, down -z, its NDC
            origin within :data:`CLIP_EXTENT`) comes out bitwise as without ``clip``. Needs
            ``normalize``.

    Returns:
        ``(origins_ndc [..., 3], dirs_ndc [..., 3])``: origins on the plane ``z' = -1``
        (``clip``: or at the camera's NDC point, or :data:`MISS_ORIGIN`).

    Raises:
        ConfigError: shapes differ / are not ``(..., 3)``, bad parameters, non-finite
            values, or (without ``clip``) a ray with ``d_z >= 0`` (it never reaches the far
            side of the NDC cube).

    >>> o, d = to_ndc_rays(np.zeros((1, 3)), np.array([[0., 0., -1.]]), 1., 1., 2., 2.)
    >>> o.tolist(), d.tolist()
    ([[0.0, 0.0, -1.0]], [[0.0, 0.0, 1.0]])
    """
    _check_params(fx, fy, width, height, near)
    if clip and not normalize:
        raise ConfigError("NDC: clip=True returns unit directions (normalize=True)")
    torch_in = _is_torch(origins) or _is_torch(dirs)
    if torch_in:
        import torch

        o = torch.as_tensor(origins)
        d = torch.as_tensor(dirs, device=o.device)
        out_dtype = o.dtype if o.is_floating_point() else torch.float32
        o, d = o.double(), d.double()
        shape_o, shape_d = tuple(o.shape), tuple(d.shape)
        xp: Any = torch
    else:
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        shape_o, shape_d = o.shape, d.shape
        xp = np
    if shape_o != shape_d or len(shape_o) < 1 or shape_o[-1] != 3:
        raise ConfigError(f"NDC: origins {list(shape_o)} and dirs {list(shape_d)} must both "
                          "have shape (..., 3)")
    dz = d[..., 2]
    if clip:
        if not bool(xp.isfinite(o).all() and xp.isfinite(d).all()):
            raise ConfigError("NDC: rays with NaN or infinite origins or directions")
    elif bool((~(dz < 0)).any()):                       # catches NaN too
        raise ConfigError(f"NDC: {int((~(dz < 0)).sum())} ray(s) do not point down the world "
                          "-z axis (d_z >= 0 or NaN); NDC needs a forward-facing scene whose "
                          "cameras look down -z (LLFF poses after recentring)")
    ax, ay = -2.0 * fx / width, -2.0 * fy / height
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = -(near + o[..., 2]) / dz
        on = o + t[..., None] * d
        ox, oy, oz = on[..., 0], on[..., 1], on[..., 2]
        rx, ry = ox / oz, oy / oz
        o_ndc = xp.stack((ax * rx, ay * ry, 1.0 + 2.0 * near / oz), -1)
        d_ndc = xp.stack((ax * (d[..., 0] / dz - rx), ay * (d[..., 1] / dz - ry),
                          -2.0 * near / oz), -1)
        if clip:
            o_ndc, d_ndc = _clip_rays(xp, o, d, o_ndc, d_ndc, ax, ay, near)
    if not bool(xp.isfinite(o_ndc).all() and xp.isfinite(d_ndc).all()):
        raise ConfigError("NDC: rays produced non-finite NDC coordinates (infinite inputs?)")
    if normalize:
        if torch_in:
            d_ndc = d_ndc / torch.linalg.vector_norm(d_ndc, dim=-1, keepdim=True)
        else:
            d_ndc = d_ndc / np.linalg.norm(d_ndc, axis=-1, keepdims=True)
    if torch_in:
        return o_ndc.to(out_dtype), d_ndc.to(out_dtype)
    return o_ndc.astype(np.float32), d_ndc.astype(np.float32)


def _clip_rays(xp: Any, o: Any, d: Any, o_std: Any, d_std: Any, ax: float, ay: float,
               near: float) -> tuple[Any, Any]:
    """The "any camera" rule of :func:`to_ndc_rays` (``clip=True``): NeRF's rays ``o_std,
    d_std [..., 3]`` (float64, non-finite where the rule does not apply) where they are valid,
    the camera's own NDC point and the projected direction for a camera past the near plane,
    :data:`MISS_ORIGIN` / ``+z'`` for the rest. ``xp``: numpy or torch."""
    def bounded(p: Any) -> Any:
        return (xp.abs(p[..., 0]) <= CLIP_EXTENT) & (xp.abs(p[..., 1]) <= CLIP_EXTENT)

    inside = o[..., 2] <= -near
    std_ok = (~inside & (d[..., 2] < -_MIN_DZ) & xp.isfinite(o_std).all(-1)
              & xp.isfinite(d_std).all(-1) & bounded(o_std))
    oz = xp.where(inside, o[..., 2], -near)      # outside rays: a stand-in, no division by ~0
    o_in = xp.stack((ax * o[..., 0] / oz, ay * o[..., 1] / oz, 1.0 + 2.0 * near / oz), -1)
    d_in = xp.stack((ax * (d[..., 0] * oz - o[..., 0] * d[..., 2]),
                     ay * (d[..., 1] * oz - o[..., 1] * d[..., 2]), -2.0 * near * d[..., 2]), -1)
    in_ok = inside & bounded(o_in) & (xp.abs(d_in).sum(-1) > 0)
    miss_o = xp.zeros_like(o_std)
    miss_o[..., 2] = MISS_ORIGIN[2]
    miss_d = xp.zeros_like(d_std)
    miss_d[..., 2] = 1.0
    o_out = xp.where(std_ok[..., None], o_std, xp.where(in_ok[..., None], o_in, miss_o))
    d_out = xp.where(std_ok[..., None], d_std, xp.where(in_ok[..., None], d_in, miss_d))
    return o_out, d_out


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
