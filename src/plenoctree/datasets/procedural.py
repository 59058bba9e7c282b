"""An analytic test scene: density and SH-colour fields, a fine ray marcher, a dataset writer.

The scene holds four disjoint objects inside the box ``SCENE_CENTER ± SCENE_RADIUS``
(``[-1, 1]^3``, z up as in Blender):

- a box with a 3-D checker texture (orange / cream, cells 0.1 wide), diffuse;
- a sphere with smooth red / white stripes along z, diffuse;
- a glossy blue sphere whose colour depends on the view direction through SH degree 1-3 terms
  (a zonal lobe around a fixed axis, so a bright highlight moves over it as the camera moves);
- a thin torus with a rainbow hue around its ring, diffuse.

Fields (numpy, vectorised, world units):

- ``density(x [N, 3]) -> σ [N]``: ``SIGMA_MAX`` inside each object, 0 outside, with a linear
  ramp of width ``EDGE_WIDTH`` across the surface (``σ = SIGMA_MAX * clip(0.5 - sdf / EDGE_WIDTH,
  0, 1)`` of the object's signed distance);
- ``sh_coeffs(x [N, 3]) -> [N, 48]``: SH degree-3 pre-sigmoid coefficients, channel-major
  ``[R_0..R_15, G_0..G_15, B_0..B_15]``, of the nearest object (defined everywhere);
  colour seen along unit direction ``d`` is ``sigmoid(Σ_b k_b Y_b(d))`` per channel.

:func:`render_field` composites these exactly like the octree renderer (weight
``T (1 - exp(-σ δ))``, background added with the remaining ``T``), with a fine midpoint
quadrature. :func:`write_procedural_dataset` writes a Blender-format dataset of the scene and
:func:`procedural_grid` / :func:`procedural_tree` sample it on a voxel grid.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..sh import SH_C0, eval_sh_bases
from .trajectories import look_at

__all__ = [
    "SCENE_CENTER",
    "SCENE_RADIUS",
    "SIGMA_MAX",
    "EDGE_WIDTH",
    "SH_DEGREE",
    "CAMERA_ANGLE_X",
    "CAMERA_DISTANCE",
    "NEAR",
    "FAR",
    "density",
    "sh_coeffs",
    "render_field",
    "look_at",
    "procedural_cameras",
    "write_procedural_dataset",
    "procedural_grid",
    "procedural_tree",
]

SCENE_CENTER = np.zeros(3, dtype=np.float64)
"""Centre of the box holding all content (world units)."""
SCENE_RADIUS = 1.0
"""Half side of the content box: everything with σ > 0 lies in ``SCENE_CENTER ± SCENE_RADIUS``."""
SIGMA_MAX = 100.0
"""Density inside the objects, 1 / world length."""
EDGE_WIDTH = 0.02
"""Width of the linear density ramp across each surface, world units."""
SH_DEGREE = 3
N_BASES = (SH_DEGREE + 1) ** 2
CAMERA_ANGLE_X = 0.6911112070083618
"""Horizontal field of view of the dataset cameras, radians (the NeRF-synthetic value)."""
CAMERA_DISTANCE = 4.0
"""Distance of the dataset cameras from the origin, world units."""
NEAR, FAR = 2.0, 6.0

# --- objects -------------------------------------------------------------------------------
_BOX_C = np.array([-0.5, -0.5, -0.4])
_BOX_H = np.array([0.3, 0.25, 0.3])
_STRIPE_C = np.array([0.45, -0.45, 0.35])
_STRIPE_R = 0.35
_GLOSS_C = np.array([0.0, 0.35, -0.2])
_GLOSS_R = 0.4
_TORUS_C = np.array([-0.35, 0.1, 0.45])
_TORUS_R, _TORUS_r = 0.3, 0.07           # ring radius, tube radius; ring in the xy plane
_N_OBJECTS = 4

_GLOSS_BASE = np.array([0.15, 0.3, 0.75])
_GLOSS_AXIS = np.array([-0.8, 0.4, -0.45]) / np.linalg.norm([-0.8, 0.4, -0.45])
_GLOSS_BAND_GAIN = np.array([0.0, 4.0, 3.0, 2.0])   # per SH band l = 0..3, pre-sigmoid scale
_GLOSS_TINT = np.array([1.0, 0.8, 0.5])             # highlight strength per channel


def _logit(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.02, 0.98)
    return np.log(c / (1.0 - c))


def _as_points(x: np.ndarray, name: str = "x") -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ConfigError(f"{name}: expected shape (N, 3), got {list(x.shape)}")
    return x


def _sdfs(x: np.ndarray) -> np.ndarray:
    """Signed distances of points ``[N, 3]`` to the four objects: ``[N, 4]`` (world units)."""
    out = np.empty((_N_OBJECTS, x.shape[0]), dtype=x.dtype)
    px, py, pz = (np.ascontiguousarray(x[:, i]) for i in range(3))
    # box: |outside part of q| + min(max(q), 0), q = |p - c| - h
    qx = np.abs(px - _BOX_C[0]) - _BOX_H[0]
    qy = np.abs(py - _BOX_C[1]) - _BOX_H[1]
    qz = np.abs(pz - _BOX_C[2]) - _BOX_H[2]
    outside = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2 + np.maximum(qz, 0) ** 2)
    out[0] = outside + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0.0)
    for row, c, r in ((1, _STRIPE_C, _STRIPE_R), (2, _GLOSS_C, _GLOSS_R)):
        out[row] = np.sqrt((px - c[0]) ** 2 + (py - c[1]) ** 2 + (pz - c[2]) ** 2) - r
    ring = np.sqrt((px - _TORUS_C[0]) ** 2 + (py - _TORUS_C[1]) ** 2) - _TORUS_R
    out[3] = np.sqrt(ring ** 2 + (pz - _TORUS_C[2]) ** 2) - _TORUS_r
    return out.T


def density(x: np.ndarray) -> np.ndarray:
    """Volume density σ at world points ``x [N, 3]``: ``[N]`` (1 / world length), same float dtype.

    ``SIGMA_MAX`` inside the objects, 0 farther than ``EDGE_WIDTH / 2`` outside, linear between.
    """
    x = _as_points(x)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    sdf = _sdfs(x).min(axis=1)
    return (SIGMA_MAX * np.clip(0.5 - sdf / EDGE_WIDTH, 0.0, 1.0)).astype(x.dtype, copy=False)


def _gloss_coeffs() -> np.ndarray:
    """Constant ``[3, 16]`` coefficients of the glossy sphere (zonal lobe around its axis)."""
    y_axis = eval_sh_bases(SH_DEGREE, _GLOSS_AXIS)                  # [16]
    band = np.repeat(np.arange(SH_DEGREE + 1), [2 * l + 1 for l in range(SH_DEGREE + 1)])
    lobe = _GLOSS_BAND_GAIN[band] * y_axis                           # Σ_b lobe_b Y_b(d) peaks at d = axis
    k = _GLOSS_TINT[:, None] * lobe[None, :]
    k[:, 0] = _logit(_GLOSS_BASE) / SH_C0
    return k


def _diffuse_colours(x: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """RGB in (0, 1) of the diffuse objects at points ``x [N, 3]`` given object ids ``[N]``."""
    rgb = np.empty((x.shape[0], 3), dtype=np.float64)
    xd = x.astype(np.float64)
    # 0: box, 3-D checker of 0.1 cells
    checker = (np.floor(xd / 0.1).astype(np.int64).sum(axis=1) & 1).astype(bool)
    box_rgb = np.where(checker[:, None], [0.92, 0.5, 0.1], [0.95, 0.9, 0.75])
    # 1: striped sphere, smooth stripes along z (period 0.14)
    s = 0.5 + 0.5 * np.sin(2.0 * math.pi * (xd[:, 2] - _STRIPE_C[2]) / 0.14)
    stripe_rgb = s[:, None] * np.array([0.85, 0.12, 0.12]) + (1 - s[:, None]) * 0.93
    # 3: torus, hue around the ring
    p = xd - _TORUS_C
    hue = np.arctan2(p[:, 1], p[:, 0])[:, None]
    torus_rgb = 0.5 + 0.4 * np.cos(hue + np.array([0.0, 2.0 * math.pi / 3, 4.0 * math.pi / 3]))
    rgb[:] = 0.5
    for oid, val in ((0, box_rgb), (1, stripe_rgb), (3, torus_rgb)):
        sel = obj == oid
        rgb[sel] = val[sel]
    return rgb


def sh_coeffs(x: np.ndarray) -> np.ndarray:
    """SH degree-3 colour coefficients at world points ``x [N, 3]``: float32 ``[N, 48]``.

    Channel-major ``[R_0..R_15, G_0..G_15, B_0..B_15]``, pre-sigmoid, taken from the object
    nearest to each point (so the field is defined everywhere, also where σ = 0).
    """
    x = _as_points(x)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    obj = _sdfs(x).argmin(axis=1)
    out = np.zeros((x.shape[0], 3, N_BASES), dtype=np.float32)
    out[:, :, 0] = _logit(_diffuse_colours(x, obj)) / SH_C0
    gloss = obj == 2
    out[gloss] = _gloss_coeffs().astype(np.float32)
    return out.reshape(x.shape[0], 3 * N_BASES)


def _box_interval(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Slab test: entry/exit distances ``[N]`` of rays ``o + t d`` with the box [lo, hi]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t_a = (lo - o) * inv
        t_b = (hi - o) * inv
    t_a = np.where(np.isnan(t_a), -np.inf, t_a)
    t_b = np.where(np.isnan(t_b), np.inf, t_b)
    return np.minimum(t_a, t_b).max(axis=1), np.maximum(t_a, t_b).min(axis=1)


def _bounding_spheres() -> list[tuple[np.ndarray, float]]:
    """(centre, radius) of a sphere around each object's σ > 0 region."""
    pad = EDGE_WIDTH
    return [(_BOX_C, float(np.linalg.norm(_BOX_H)) + pad), (_STRIPE_C, _STRIPE_R + pad),
            (_GLOSS_C, _GLOSS_R + pad), (_TORUS_C, _TORUS_R + _TORUS_r + pad)]


def _bounding_mask(o: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Bool ``[C, S]``: sample ``t [C, S]`` of unit ray ``(o, d) [C, 3]`` is inside a bounding sphere."""
    mask = np.zeros(t.shape, dtype=bool)
    for c, r in _bounding_spheres():
        oc = o - c
        b = np.einsum("ij,ij->i", d, oc)
        disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
        hit = disc > 0
        if not hit.any():
            continue
        root = np.sqrt(np.where(hit, disc, 0.0))
        lo = np.where(hit, -b - root, np.inf)[:, None]
        hi = np.where(hit, -b + root, -np.inf)[:, None]
        mask |= (t >= lo) & (t <= hi)
    return mask


def render_field(origins: np.ndarray, dirs: np.ndarray, near: float = NEAR, far: float = FAR,
                 n_samples: int = 512, background=(1.0, 1.0, 1.0),
                 chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Ray-march the analytic fields with a fine midpoint rule (reference renders).

    Each ray's interval ``[near, far]`` is clipped to the content box and split into
    ``n_samples`` equal segments of length δ; sample ``i`` at the segment midpoint gets weight
    ``T_i (1 - exp(-σ_i δ))`` with ``T_i = exp(-Σ_{j<i} σ_j δ)``; ``rgb = Σ w c + T background``.
    Colours are evaluated only where σ > 0 and ``T > 1e-7``.

    Args:
        origins: ``[..., 3]`` ray origins, world units. dirs: ``[..., 3]`` directions
            (normalised here; ``t`` is distance along the unit direction).
        near, far: sampling bounds along the ray, world units.
        n_samples: segments per ray inside the content box.
        background: RGB composited with the remaining transmittance.
        chunk: rays processed at once (memory ~ chunk * n_samples * 60 bytes).

    Returns:
        ``rgb [..., 3]`` float32 in [0, 1] and opacity ``alpha [...]`` float32
        (``1 - T`` at the end of the ray).
    """
    origins = np.asarray(origins, dtype=np.float64)
    dirs = np.asarray(dirs, dtype=np.float64)
    if origins.shape != dirs.shape or origins.shape[-1:] != (3,):
        raise ConfigError(f"origins {list(origins.shape)} and dirs {list(dirs.shape)} must both "
                          "have shape (..., 3)")
    if not n_samples >= 1 or not (0 <= near < far):
        raise ConfigError(f"need n_samples >= 1 and 0 <= near < far, got {n_samples}, {near}, {far}")
    batch = origins.shape[:-1]
    o = origins.reshape(-1, 3)
    d = dirs.reshape(-1, 3)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    bg = np.asarray(background, dtype=np.float64).reshape(3)
    lo = SCENE_CENTER - SCENE_RADIUS
    hi = SCENE_CENTER + SCENE_RADIUS
    t0, t1 = _box_interval(o, d, lo, hi)
    t0 = np.maximum(t0, near)
    t1 = np.minimum(t1, far)
    n = o.shape[0]
    rgb = np.empty((n, 3), dtype=np.float64)
    alpha = np.zeros(n, dtype=np.float64)
    rgb[:] = bg
    hit = np.nonzero(t1 > t0)[0]
    frac = (np.arange(n_samples, dtype=np.float64) + 0.5) / n_samples
    for s in range(0, hit.size, chunk):
        idx = hit[s:s + chunk]
        oc, dc = o[idx], d[idx]
        span = t1[idx] - t0[idx]
        delta = span / n_samples                                      # [C]
        t = t0[idx, None] + frac[None, :] * span[:, None]             # [C, S]
        pts = oc[:, None, :] + t[..., None] * dc[:, None, :]          # [C, S, 3]
        # σ is evaluated only inside the objects' bounding spheres (elsewhere it is exactly 0)
        cand = _bounding_mask(oc, dc, t)
        sigma = np.zeros(t.shape, dtype=np.float64)
        sigma[cand] = density(pts[cand].astype(np.float32))
        tau = sigma * delta[:, None]
        trans_after = np.exp(-np.cumsum(tau, axis=1))
        trans_before = np.concatenate([np.ones((len(idx), 1)), trans_after[:, :-1]], axis=1)
        w = trans_before - trans_after                                # = T_i (1 - exp(-σ δ))
        ri, si = np.nonzero((sigma > 0) & (trans_before > 1e-7))
        col = np.zeros((len(idx), 3))
        if ri.size:
            k = sh_coeffs(pts[ri, si]).reshape(-1, 3, N_BASES).astype(np.float64)
            basis = eval_sh_bases(SH_DEGREE, dc)[ri]                  # [M, 16]
            c = 1.0 / (1.0 + np.exp(-np.einsum("mcb,mb->mc", k, basis)))
            np.add.at(col, ri, w[ri, si, None] * c)
        t_final = trans_after[:, -1]
        rgb[idx] = col + t_final[:, None] * bg
        alpha[idx] = 1.0 - t_final
    return (rgb.reshape(*batch, 3).astype(np.float32), alpha.reshape(batch).astype(np.float32))


# --- cameras and dataset -------------------------------------------------------------------
def procedural_cameras(n: int, kind: str, seed: int = 0, distance: float = CAMERA_DISTANCE
                       ) -> np.ndarray:
    """``[n, 4, 4]`` camera-to-world matrices on a sphere around the origin, looking at it.

    ``kind="random"``: directions uniform on the sphere (``seed``); ``kind="orbit"``: evenly
    spaced azimuths at 30° elevation (a turntable, for test views).
    """
    if kind == "random":
        rng = np.random.default_rng(seed)
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
    elif kind == "orbit":
        az = 2.0 * math.pi * (np.arange(n) + 0.5) / max(n, 1)
        el = math.radians(30.0)
        v = np.stack([np.cos(az) * math.cos(el), np.sin(az) * math.cos(el),
                      np.full(n, math.sin(el))], axis=1)
    else:
        raise ConfigError(f"unknown camera layout {kind!r} (expected 'random' or 'orbit')")
    return np.stack([look_at(distance * vi) for vi in v]) if n else np.zeros((0, 4, 4))


def write_procedural_dataset(out_dir: str | os.PathLike, n_train: int = 20, n_val: int = 4,
                             n_test: int = 8, width: int = 64, height: int = 64, seed: int = 0,
                             n_samples: int = 512) -> Path:
    """Write the scene as a Blender / NeRF-synthetic dataset under ``out_dir``.

    Layout: ``transforms_{train,val,test}.json`` (``camera_angle_x`` and per frame
    ``file_path`` ``"./<split>/r_<i>"`` and a 4x4 ``transform_matrix``) and RGBA PNGs
    ``<split>/r_<i>.png`` whose alpha is the accumulated opacity and whose RGB is the
    un-premultiplied colour, so compositing onto white gives :func:`render_field`'s image.
    Train and val cameras are random on the sphere of radius ``CAMERA_DISTANCE`` (different
    seeds), test cameras a 30° orbit. Files are written atomically; returns ``Path(out_dir)``.
    """
    from .._util import atomic_save_json, save_png
    from .cameras import generate_rays

    for name, val in (("n_train", n_train), ("n_val", n_val), ("n_test", n_test)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 0:
            raise ConfigError(f"{name} must be a non-negative integer, got {val!r}")
    out = Path(out_dir)
    fx = 0.5 * width / math.tan(0.5 * CAMERA_ANGLE_X)
    layouts = {"train": (n_train, "random", seed), "val": (n_val, "random", seed + 1),
               "test": (n_test, "orbit", seed)}
    for split, (n, kind, sd) in layouts.items():
        c2ws = procedural_cameras(n, kind, sd)
        frames = []
        for i, c2w in enumerate(c2ws):
            o, d = generate_rays(c2w, fx, fx, width / 2.0, height / 2.0, width, height)
            rgb, alpha = render_field(o, d, NEAR, FAR, n_samples=n_samples)
            premult = rgb - (1.0 - alpha[..., None])          # Σ w c (white background removed)
            with np.errstate(divide="ignore", invalid="ignore"):
                straight = np.where(alpha[..., None] > 0, premult / alpha[..., None], 0.0)
            rgba = np.concatenate([np.clip(straight, 0, 1), alpha[..., None]], axis=-1)
            save_png(out / split / f"r_{i}.png", rgba)
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0,
                           "transform_matrix": c2w.tolist()})
        atomic_save_json(out / f"transforms_{split}.json",
                         {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames})
    return out


# --- voxel grid and tree -------------------------------------------------------------------
def procedural_grid(resolution: int = 128, chunk: int = 1 << 20, sparse: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Sample the fields at the voxel centres of a ``resolution^3`` grid over the content box.

    Voxel ``(i, j, k)`` (``i`` along x) is centred at
    ``SCENE_CENTER - SCENE_RADIUS + (i + 0.5, j + 0.5, k + 0.5) * 2 SCENE_RADIUS / resolution``.

    Returns:
        ``values`` float32 ``[R, R, R, 49]`` (48 SH coefficients then σ; zero where σ = 0),
        ``mask`` bool ``[R, R, R]`` (σ > 0), ``center`` float64 ``[3]`` and ``radius`` (float,
        half side of the box) — the arguments of ``Octree.from_grid``. Memory: ``196 R^3``
        bytes for ``values``. With ``sparse=True`` ``values`` is ``[mask.sum(), 49]`` in
        ``np.nonzero(mask)`` order instead (what ``Octree.from_grid`` also accepts), so a
        256³ grid needs ~100 MB instead of 3.3 GB.
    """
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) \
            or resolution < 1:
        raise ConfigError(f"resolution must be a positive integer, got {resolution!r}")
    r = int(resolution)
    axis = SCENE_CENTER[0] - SCENE_RADIUS + (np.arange(r) + 0.5) * (2.0 * SCENE_RADIUS / r)
    values = None if sparse else np.zeros((r, r, r, 3 * N_BASES + 1), dtype=np.float32)
    parts = []
    mask = np.zeros((r, r, r), dtype=bool)
    offs = SCENE_CENTER - SCENE_CENTER[0]
    slab = max(1, chunk // (r * r))
    for i0 in range(0, r, slab):
        gx, gy, gz = np.meshgrid(axis[i0:i0 + slab] + offs[0], axis + offs[1], axis + offs[2],
                                 indexing="ij")
        pts = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3).astype(np.float32)
        sig = density(pts)
        occ = sig > 0
        occ_vals = np.empty((int(occ.sum()), 3 * N_BASES + 1), dtype=np.float32)
        occ_vals[:, -1] = sig[occ]
        occ_vals[:, :-1] = sh_coeffs(pts[occ])
        if sparse:
            parts.append(occ_vals)
        else:
            values[i0:i0 + slab].reshape(-1, values.shape[-1])[occ] = occ_vals
        mask[i0:i0 + slab] = occ.reshape(gx.shape)
    if sparse:
        values = (np.concatenate(parts) if parts
                  else np.zeros((0, 3 * N_BASES + 1), dtype=np.float32))
    return values, mask, SCENE_CENTER.copy(), float(SCENE_RADIUS)


def procedural_tree(resolution: int = 128):
    """The scene as an ``SH16`` :class:`~plenoctree.octree.Octree` built from
    :func:`procedural_grid` (``resolution`` must be a power of two)."""
    from ..octree import Octree

    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) \
            or resolution < 2 or resolution & (resolution - 1):
        raise ConfigError(f"resolution must be a power of two >= 2, got {resolution!r}")
    values, mask, center, radius = procedural_grid(resolution, sparse=True)
    return Octree.from_grid(values, mask, center, radius, data_format="SH16")
