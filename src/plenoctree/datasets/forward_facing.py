"""A forward-facing version of the procedural scene, written as an LLFF capture, and its
exact-as-possible PlenOctree in NDC space.

:func:`write_forward_facing_dataset` renders :mod:`~plenoctree.datasets.procedural`'s analytic
scene from a rig of cameras in front of it (all on one side, looking at the scene centre, like a
hand-held LLFF capture) and writes ``poses_bounds.npy`` + ``images/`` (lossless PNG, composited
on white). Loading it with :func:`~plenoctree.datasets.llff.load_llff` exercises the LLFF pose
conversion, normalisation and NDC rays end to end.

:func:`forward_facing_grid` / :func:`forward_facing_tree` sample the same scene on a voxel grid
over the dataset's NDC box (``Dataset.scene_bbox``), giving the tree an NDC renderer should
reproduce. Each voxel centre ``p'`` is mapped back to the normalised world ``p``
(:func:`~plenoctree.datasets.ndc.ndc_to_world`) and to the scene's own frame; there:

- density: NDC rays measure length in NDC space, so ``σ' = σ |dp| / |dp'|``. Along the ray of
  the NDC reference camera (at the normalised-world origin) through ``p`` the ratio is
  ``|p| |p_z| / (2 n)`` (``n`` = near plane), which is used everywhere. It is exact for the
  reference camera and, since the rig's cameras sit close to it, a close approximation for them;
- colour: the SH colour seen from the reference camera along the direction of ``p``, stored as
  a direction-independent ``RGBA`` (pre-sigmoid) value.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..sh import eval_sh_bases
from . import procedural as proc
from .ndc import ndc_bounds, ndc_to_world

__all__ = ["forward_facing_cameras", "write_forward_facing_dataset", "forward_facing_grid",
           "forward_facing_tree", "RIG_DISTANCE"]

RIG_DISTANCE = 4.0
"""Distance of the rig's plane from the scene centre, world units (scene frame)."""


def forward_facing_cameras(n: int, seed: int = 0, spread: float = 0.5,
                           distance: float = RIG_DISTANCE) -> np.ndarray:
    """``[n, 4, 4]`` OpenGL c2w: a jittered grid of cameras in the plane ``y = distance`` (the
    scene frame, z up), within ``±spread`` of the axis, all looking at the scene centre."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"n must be a positive integer, got {n!r}")
    rng = np.random.default_rng(seed)
    cols = int(math.ceil(math.sqrt(n * 4.0 / 3.0)))
    rows = int(math.ceil(n / cols))
    gx, gz = np.meshgrid(np.linspace(-1, 1, cols), np.linspace(-1, 1, rows))
    pts = np.stack([gx.ravel(), gz.ravel()], 1)[:n] * spread * 0.8
    pts += rng.uniform(-0.2, 0.2, size=pts.shape) * spread
    eyes = np.stack([pts[:, 0], np.full(n, distance), pts[:, 1]], 1)
    return np.stack([proc.look_at(e, proc.SCENE_CENTER) for e in eyes])


def _content_bounds(c2w: np.ndarray) -> np.ndarray:
    """``[N, 2]`` near / far depth of the content box's corners in each camera."""
    lo = proc.SCENE_CENTER - proc.SCENE_RADIUS
    hi = proc.SCENE_CENTER + proc.SCENE_RADIUS
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    depth = -np.einsum("nji,nkj->nki", c2w[:, :3, :3], corners[None] - c2w[:, None, :3, 3])[..., 2]
    return np.stack([depth.min(1), depth.max(1)], 1)


def write_forward_facing_dataset(out_dir: str | os.PathLike, n_images: int = 24,
                                 width: int = 64, height: int = 48, seed: int = 0,
                                 n_samples: int = 256, spread: float = 0.5) -> Path:
    """Render the procedural scene from :func:`forward_facing_cameras` and write it as an
    LLFF capture (``poses_bounds.npy`` + ``images/NNN.png``) under ``out_dir``.

    The focal length gives the procedural datasets' field of view (``CAMERA_ANGLE_X``); the
    depth bounds are those of the content box. With ``llffhold = 8`` images 0, 8, ... are the
    test split. Returns ``Path(out_dir)``.
    """
    from .cameras import generate_rays
    from .llff import write_llff

    if isinstance(width, bool) or not isinstance(width, (int, np.integer)) or width < 1 \
            or isinstance(height, bool) or not isinstance(height, (int, np.integer)) or height < 1:
        raise ConfigError(f"width and height must be positive integers, got {width!r}, {height!r}")
    c2w = forward_facing_cameras(n_images, seed, spread)
    focal = 0.5 * width / math.tan(0.5 * proc.CAMERA_ANGLE_X)
    images = np.empty((n_images, height, width, 3), dtype=np.float32)
    for i, m in enumerate(c2w):
        o, d = generate_rays(m, focal, focal, width / 2.0, height / 2.0, width, height)
        images[i], _ = proc.render_field(o, d, 0.0, 2.0 * RIG_DISTANCE, n_samples=n_samples)
    return write_llff(out_dir, c2w, images, focal, _content_bounds(c2w), suffix=".png")


def forward_facing_grid(root: str | os.PathLike, resolution: int = 128, chunk: int = 1 << 19
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sample the scene on a ``resolution^3`` grid over the NDC box of the LLFF capture at
    ``root`` (written by :func:`write_forward_facing_dataset`; default LLFF normalisation).

    Returns:
        ``values`` float32 ``[mask.sum(), 4]`` (pre-sigmoid RGB, NDC density) for the
        occupied cells in ``np.nonzero(mask)`` order, ``mask`` bool ``[R, R, R]``, ``center``
        ``[3]`` and ``radius`` ``[3]`` of the NDC box — arguments of ``Octree.from_grid``.
    """
    from .llff import read_llff

    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) \
            or resolution < 2 or resolution & (resolution - 1):
        raise ConfigError(f"resolution must be a power of two >= 2, got {resolution!r}")
    scene = read_llff(root)
    h, w, f = scene.hwf[0]
    k = np.tile([f, f, w / 2.0, h / 2.0], (len(scene.c2w), 1))
    _, bbox = ndc_bounds(scene.c2w, k, int(w), int(h), f, f)
    bbox = bbox.astype(np.float64)
    center, radius = bbox.mean(0), (bbox[1] - bbox[0]) / 2.0
    inv_t = np.linalg.inv(scene.transform)
    rot_back = inv_t[:3, :3] * scene.scale          # rotation part of the inverse
    r = int(resolution)
    axes = [bbox[0, a] + (np.arange(r) + 0.5) * (2.0 * radius[a] / r) for a in range(3)]
    flat = np.arange(r ** 3)
    mask = np.zeros(r ** 3, dtype=bool)
    parts = []
    for s in range(0, r ** 3, chunk):
        ids = flat[s:s + chunk]
        i, j, kk = np.unravel_index(ids, (r, r, r))
        p_ndc = np.stack([axes[0][i], axes[1][j], axes[2][kk]], 1)
        p = ndc_to_world(p_ndc, f, f, w, h)                          # normalised world
        p_scene = p @ inv_t[:3, :3].T + inv_t[:3, 3]
        sigma = proc.density(p_scene.astype(np.float32)).astype(np.float64) / scene.scale
        occ = sigma > 0
        if not occ.any():
            continue
        po, ps = p[occ], p_scene[occ]
        sig_ndc = sigma[occ] * np.linalg.norm(po, axis=1) * np.abs(po[:, 2]) / 2.0
        u = po / np.linalg.norm(po, axis=1, keepdims=True) @ rot_back.T
        coeffs = proc.sh_coeffs(ps.astype(np.float32)).reshape(-1, 3, proc.N_BASES)
        logits = np.einsum("ncb,nb->nc", coeffs.astype(np.float64),
                           eval_sh_bases(proc.SH_DEGREE, u))
        parts.append(np.concatenate([logits, sig_ndc[:, None]], 1).astype(np.float32))
        mask[ids[occ]] = True
    values = np.concatenate(parts) if parts else np.zeros((0, 4), dtype=np.float32)
    return values, mask.reshape(r, r, r), center, radius


def forward_facing_tree(root: str | os.PathLike, resolution: int = 128):
    """The NDC-space ``RGBA`` :class:`~plenoctree.octree.Octree` of :func:`forward_facing_grid`
    (``tree.ndc``: the capture's NDC reference camera)."""
    from ..octree import Octree
    from ..octree.ndc import NDCSpace
    from .llff import read_llff

    values, mask, center, radius = forward_facing_grid(root, resolution)
    tree = Octree.from_grid(values, mask, center, radius, data_format="RGBA")
    h, w, f = read_llff(root).hwf[0]
    tree.ndc = NDCSpace(int(w), int(h), float(f), float(f), 1.0)
    return tree
