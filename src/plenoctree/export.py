"""Exports of a PlenOctree to files other tools open: svox ``.npz``, point cloud, coloured mesh.

- :func:`leaf_points` / :func:`export_point_cloud`: one point per occupied leaf (its centre),
  with the leaf's colour, opacity, density and size, written as a binary PLY with ``plyfile``
  (MeshLab, CloudCompare and Blender read the ``x y z red green blue alpha`` vertex fields).
- :func:`sample_sigma_grid` / :func:`extract_mesh` / :func:`export_mesh`: marching cubes
  (scikit-image) on σ sampled from the tree at its finest leaf resolution, vertex colours from
  the SH coefficients, written with ``trimesh`` as ``.ply``, ``.glb`` or ``.obj``.
- svox: :func:`export_svox_file` (:func:`plenoctree.octree.io.export_svox`: the svox /
  volrend layout, float16 data; NDC trees also get volrend's ``<stem>_poses_bounds.npy``).

Forward-facing trees (``tree.ndc`` set: the box lives in NDC space, :mod:`plenoctree.octree.ndc`)
are exported in *world* coordinates: point centres and mesh vertices are mapped back with
``NDCSpace.ndc_to_world`` (point sizes: the extent of the leaf's 8 mapped corners; mesh faces
re-wound, since the map reverses orientation, and normals recomputed). Geometry at NDC depth
``z' >= NDC_MAX_Z`` (world depth beyond ``2 near / (1 - NDC_MAX_Z)`` = 200 near, towards the
NDC far end at infinity) is dropped. Colours are evaluated in NDC space (the tree's SH take NDC
ray directions); densities stay per unit NDC length.

Colour of a leaf (or vertex) seen along a unit ray direction ``d``: ``sigmoid(Σ_b k_b Y_b(d))``
per channel, as the renderer computes it. ``view="dc"`` uses the mean of each basis over the
sphere instead (SH: ``sigmoid(C0 k_0)``, the view-independent "DC" colour; RGBA: its colour;
SG: the lobes averaged over directions). Mesh vertices default to ``view="normal"``: the colour
a camera looking straight at the surface sees (``d = -n``, ``n`` the outward normal).

The optional libraries are the ``plenoctree[export]`` extra; a missing one raises
:class:`~plenoctree.errors.BackendError` naming it, at use, never at import. Every file is
written atomically (temp file + rename).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._util import atomic_write, progress
from .errors import BackendError, ConfigError
from .octree.tree import Octree
from .render.options import KIND_RGBA, KIND_SG, KIND_SH, parse_data_format
from .sh import eval_sg_bases, eval_sh_bases

__all__ = [
    "leaf_points",
    "export_point_cloud",
    "sample_sigma_grid",
    "extract_mesh",
    "export_mesh",
    "MESH_SUFFIXES",
    "point_colors",
    "export_svox_file",
    "NDC_MAX_Z",
]

#: File types :func:`export_mesh` writes (by suffix of the output path).
MESH_SUFFIXES = (".ply", ".glb", ".obj")
#: NDC trees: geometry at NDC depth z' >= this (world depth > 200 near) is not exported.
NDC_MAX_Z = 0.99


def _require(module: str, package: str) -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise BackendError(f"this export needs the '{package}' package: pip install "
                           f"'plenoctree[export]' (or pip install {package})") from None


def _parse_view(view: Any) -> str | np.ndarray:
    """``"dc"``, ``"normal"`` or a unit direction ``[3]`` (float64)."""
    if isinstance(view, str):
        v = view.strip().lower()
        if v in ("dc", "normal"):
            return v
        try:
            view = [float(x) for x in v.split(",")]
        except ValueError:
            raise ConfigError(f"view must be 'dc', 'normal' or a direction 'x,y,z', got {view!r}"
                              ) from None
    d = np.asarray(view, dtype=np.float64).reshape(-1)
    n = float(np.linalg.norm(d)) if d.size == 3 and np.all(np.isfinite(d)) else 0.0
    if n == 0.0:
        raise ConfigError(f"view direction must be 3 finite numbers, not all zero, got {view!r}")
    return d / n


def _mean_basis(info: Any, extra_data: Any) -> np.ndarray:
    """Mean of each basis function over the unit sphere, ``[B]`` float64."""
    if info.kind == KIND_SH:
        out = np.zeros(info.basis_dim)
        out[0] = 0.28209479177387814          # C0; every other SH integrates to zero
        return out
    if info.kind == KIND_RGBA:
        return np.ones(1)
    n = 4096                                   # SG: Fibonacci-sphere average
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + 5 ** 0.5) * i
    r = np.sqrt(1.0 - z * z)
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    e = np.asarray(extra_data, dtype=np.float64)
    return eval_sg_bases(e[:, 1:4], e[:, 0], dirs).mean(0)


def point_colors(tree: Octree, coeffs: np.ndarray, dirs: Any = "dc") -> np.ndarray:
    """Colour in [0, 1] of colour coefficients seen along ``dirs``.

    Args:
        tree: gives the data format (and SG lobes).
        coeffs: ``[N, 3B]`` channel-major pre-sigmoid coefficients (``data[..., :-1]``).
        dirs: ``"dc"`` or unit ray directions ``[3]`` / ``[N, 3]`` (world, pointing from the
            camera into the scene, as the renderer's rays).
    Returns:
        float32 ``[N, 3]``.
    """
    info = parse_data_format(tree.data_format, tree.data_dim, tree.extra_data)
    b = info.basis_dim
    k = np.asarray(coeffs, dtype=np.float64).reshape(-1, 3, b)
    if isinstance(dirs, str):
        basis = np.broadcast_to(_mean_basis(info, tree.extra_data), (k.shape[0], b))
    else:
        d = np.broadcast_to(np.asarray(dirs, dtype=np.float64), (k.shape[0], 3))
        if info.kind == KIND_SH:
            basis = eval_sh_bases(info.sh_degree, d)
        elif info.kind == KIND_SG:
            e = np.asarray(tree.extra_data, dtype=np.float64)
            basis = eval_sg_bases(e[:, 1:4], e[:, 0], d)
        else:
            basis = np.ones((k.shape[0], 1))
    x = np.einsum("ncb,nb->nc", k, basis)
    return (1.0 / (1.0 + np.exp(-x))).astype(np.float32)


# ---------------------------------------------------------------------------- point cloud
@dataclass
class PointCloud:
    """Occupied leaves as points (world units; NDC trees: mapped back to world space).

    Attributes:
        xyz: float32 ``[N, 3]`` leaf centres.
        rgb: float32 ``[N, 3]`` colour in [0, 1].
        opacity: float32 ``[N]`` ``1 - exp(-σ s)``, ``s`` the mean side of the leaf (tree units
            of length: NDC for NDC trees).
        sigma: float32 ``[N]`` density (1 / world length; 1 / NDC length for NDC trees).
        size: float32 ``[N, 3]`` side lengths of the leaf (NDC trees: of the world box around
            its mapped corners).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    opacity: np.ndarray
    sigma: np.ndarray
    size: np.ndarray


_CORNERS = np.stack(np.meshgrid([0.0, 1.0], [0.0, 1.0], [0.0, 1.0], indexing="ij"), -1).reshape(8, 3)


def leaf_points(tree: Octree, view: Any = "dc", min_opacity: float = 0.01) -> PointCloud:
    """One point per leaf with ``opacity >= min_opacity`` (and σ > 0), see :class:`PointCloud`.

    ``view``: ``"dc"`` or a ray direction ``"x,y,z"`` / ``[3]`` for the colour.
    """
    mo = float(min_opacity)
    if not 0.0 <= mo < 1.0:
        raise ConfigError(f"min_opacity must be in [0, 1), got {min_opacity!r}")
    v = _parse_view(view)
    if isinstance(v, str) and v != "dc":
        raise ConfigError("a point cloud's colour view is 'dc' or a direction 'x,y,z'")
    leaf = tree.child == 0
    data = tree.data[leaf]
    sigma = np.maximum(data[:, -1].astype(np.float64), 0.0)
    _, corner, size_t = tree._leaf_geometry()
    size = size_t[:, None] / tree.invradius
    opacity = 1.0 - np.exp(-sigma * size.mean(1))
    keep = (sigma > 0) & (opacity >= mo)
    centre = tree.tree_to_world(corner[keep] + 0.5 * size_t[keep, None])
    if tree.ndc is not None:           # forward-facing: back to world space (module docstring)
        near_end = centre[:, 2] < NDC_MAX_Z
        keep[np.flatnonzero(keep)[~near_end]] = False
        centre = centre[near_end]
        corners = tree.tree_to_world(corner[keep][:, None, :] + size_t[keep, None, None]
                                     * _CORNERS[None])
        world = tree.ndc.ndc_to_world(corners)                        # [n, 8, 3]
        size = np.zeros_like(size)
        size[keep] = world.max(1) - world.min(1)
        centre = tree.ndc.ndc_to_world(centre)
    rgb = point_colors(tree, data[keep, :-1], v)
    return PointCloud(xyz=centre.astype(np.float32), rgb=rgb,
                      opacity=opacity[keep].astype(np.float32),
                      sigma=sigma[keep].astype(np.float32), size=size[keep].astype(np.float32))


def _u8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def export_point_cloud(tree: Octree, path: str | os.PathLike, view: Any = "dc",
                       min_opacity: float = 0.01, ascii: bool = False) -> PointCloud:
    """Write the occupied leaves as a PLY point cloud (binary little-endian unless ``ascii``).

    Vertex fields: ``x y z`` (float32, world), ``red green blue alpha`` (uint8; alpha =
    opacity), ``opacity sigma`` (float32), ``size_x size_y size_z`` (float32 leaf sides).
    Raises :class:`ConfigError` when no leaf passes ``min_opacity``. Returns the points.
    """
    plyfile = _require("plyfile", "plyfile")
    pts = leaf_points(tree, view, min_opacity)
    n = pts.xyz.shape[0]
    if n == 0:
        raise ConfigError(f"{os.fspath(path)}: no leaf has opacity >= {min_opacity} "
                          "(lower --min-opacity)")
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                             ("green", "u1"), ("blue", "u1"), ("alpha", "u1"),
                             ("opacity", "<f4"), ("sigma", "<f4"), ("size_x", "<f4"),
                             ("size_y", "<f4"), ("size_z", "<f4")])
    for i, c in enumerate("xyz"):
        rec[c] = pts.xyz[:, i]
        rec[f"size_{c}"] = pts.size[:, i]
    rgb8 = _u8(pts.rgb)
    rec["red"], rec["green"], rec["blue"] = rgb8[:, 0], rgb8[:, 1], rgb8[:, 2]
    rec["alpha"] = _u8(pts.opacity)
    rec["opacity"], rec["sigma"] = pts.opacity, pts.sigma
    el = plyfile.PlyElement.describe(rec, "vertex")
    ply = plyfile.PlyData([el], text=bool(ascii), byte_order="<",
                          comments=[f"plenoctree point cloud: {tree.data_format}, "
                                    f"colour view {view}"])
    with atomic_write(path, "wb") as f:
        ply.write(f)
    return pts


# ---------------------------------------------------------------------------- mesh
def _grid_shape(tree: Octree, resolution: int | None) -> tuple[int, int, int]:
    """Samples per axis: the finest leaf resolution (``2^(max_depth+1)``), capped to ``resolution``."""
    finest = 2 ** (tree.max_depth + 1)
    r = finest if resolution is None else int(resolution)
    if r < 2:
        raise ConfigError(f"mesh resolution must be >= 2, got {resolution!r}")
    if r ** 3 > 2 ** 31:
        raise ConfigError(f"mesh resolution {r} is too large (at most 1290)")
    return (r, r, r)


def sample_sigma_grid(tree: Octree, resolution: int | None = None,
                      show_progress: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """σ of the tree at the centres of an ``R^3`` grid over its box.

    Args:
        resolution: R (default: the finest leaf resolution, ``2^(max_depth + 1)``).
    Returns:
        ``(sigma float32 [R, R, R] indexed (x, y, z), spacing float64 [3])``; sample
        ``(i, j, k)`` sits at ``bbox_min + (i + 0.5, j + 0.5, k + 0.5) * spacing``.
    """
    shape = _grid_shape(tree, resolution)
    lo, hi = tree.bbox
    spacing = (hi - lo) / np.asarray(shape)
    axes = [lo[a] + (np.arange(shape[a]) + 0.5) * spacing[a] for a in range(3)]
    sigma = np.empty(shape, dtype=np.float32)
    yy, zz = np.meshgrid(axes[1], axes[2], indexing="ij")
    slab = max(1, (1 << 21) // (shape[1] * shape[2]))
    starts = range(0, shape[0], slab)
    for s in progress(starts, total=len(starts), desc="sample sigma", unit="slab",
                      disable=None if show_progress is None else not show_progress):
        xs = axes[0][s:s + slab]
        pts = np.stack(np.broadcast_arrays(xs[:, None, None], yy[None], zz[None]), -1)
        node, i, j, k, inside = tree.query_cells(pts)
        v = tree.data[node, i, j, k, -1].astype(np.float32)
        v[~inside] = 0.0
        sigma[s:s + slab] = np.maximum(v, 0.0)
    return sigma, spacing


@dataclass
class Mesh:
    """A triangle mesh in world units: ``vertices`` float32 [V, 3], ``faces`` int32 [F, 3]
    (counter-clockwise seen from outside), ``normals`` float32 [V, 3] (outward, unit),
    ``colors`` float32 [V, 3] in [0, 1], and the σ ``level`` it was cut at."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    level: float


def default_level(spacing: np.ndarray, alpha: float = 0.5) -> float:
    """σ at which one grid cell (mean side) has opacity ``alpha``: ``-ln(1 - alpha) / side``."""
    return float(-math.log(1.0 - alpha) / float(np.mean(spacing)))


def extract_mesh(tree: Octree, resolution: int | None = None, level: float | None = None,
                 smooth: float = 0.0, view: Any = "normal",
                 show_progress: bool | None = None) -> Mesh:
    """Marching cubes on σ sampled from the tree (scikit-image), colours from the coefficients.

    Args:
        resolution: grid samples per axis (default: the finest leaf resolution).
        level: σ iso-value (1/world length); default :func:`default_level` (a grid cell is
            half opaque).
        smooth: Gaussian blur of the σ grid, in grid cells (0 = none).
        view: vertex colour: ``"normal"`` (looking along the inward normal), ``"dc"`` or a
            ray direction ``"x,y,z"``.
    The grid is padded with one empty cell on each side, so the surface is closed at the box.
    Each vertex colour comes from the leaf one grid cell inside the surface (along -normal).
    Raises :class:`ConfigError` when the level cuts no surface.
    """
    measure = _require("skimage.measure", "scikit-image")
    v = _parse_view(view)
    sigma, spacing = sample_sigma_grid(tree, resolution, show_progress)
    if smooth:
        if not smooth > 0:
            raise ConfigError(f"smooth must be >= 0 (grid cells), got {smooth!r}")
        ndimage = _require("scipy.ndimage", "scipy")
        sigma = ndimage.gaussian_filter(sigma, float(smooth), mode="constant")
    lev = default_level(spacing) if level is None else float(level)
    if not (math.isfinite(lev) and lev > 0):
        raise ConfigError(f"mesh level must be a positive density, got {level!r}")
    smax = float(sigma.max())
    if smax <= lev:
        raise ConfigError(f"mesh level {lev:.4g} is above the tree's largest sampled density "
                          f"{smax:.4g}: no surface (lower --level)")
    padded = np.pad(sigma, 1)
    verts, faces, normals, _ = measure.marching_cubes(padded, level=lev, spacing=tuple(spacing),
                                                      gradient_direction="descent")
    lo = tree.bbox[0]
    verts = verts + lo - spacing * 0.5            # padded sample 0 sits half a cell outside lo
    nrm = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # colours from the leaf one cell inside the surface (σ > 0 there), falling back further in
    probe = verts - nrm * spacing
    data = tree.query(probe)
    deeper = data[:, -1] <= 0
    if deeper.any():
        data[deeper] = tree.query(verts[deeper] - 2.0 * nrm[deeper] * spacing)
    dirs = -nrm if isinstance(v, str) and v == "normal" else v
    colors = point_colors(tree, data[:, :-1], dirs)
    # skimage winds faces clockwise seen along the descent normal; flip to CCW-outward
    faces = faces[:, ::-1]
    if tree.ndc is not None:
        verts, faces, nrm, colors = _unwarp_ndc(tree.ndc, verts, faces, colors)
    return Mesh(vertices=verts.astype(np.float32), faces=np.ascontiguousarray(faces, np.int32),
                normals=nrm.astype(np.float32), colors=colors, level=lev)


def _unwarp_ndc(ndc: Any, verts: np.ndarray, faces: np.ndarray, colors: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An NDC-space mesh in world space: faces touching ``z' >= NDC_MAX_Z`` dropped, unused
    vertices removed, vertices mapped by ``ndc_to_world``, faces re-wound (the map has a
    negative Jacobian determinant) and area-weighted vertex normals recomputed."""
    ok = verts[:, 2] < NDC_MAX_Z
    faces = faces[ok[faces].all(1)]
    if not len(faces):
        raise ConfigError(f"the surface lies entirely at NDC depth >= {NDC_MAX_Z} (at "
                          "infinity in world space): nothing to export")
    used = np.unique(faces)
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(used.size)
    faces = remap[faces][:, ::-1]
    world = ndc.ndc_to_world(verts[used])
    tri = world[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])      # area-weighted, outward
    nrm = np.zeros_like(world)
    for c in range(3):
        np.add.at(nrm, faces[:, c], fn)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    return world, faces, nrm, colors[used]


_UP_TO_Y = {  # rotations taking the scene's up axis to glTF's +Y (right-handed, det +1)
    "+z": [[1, 0, 0], [0, 0, 1], [0, -1, 0]],
    "-z": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
    "+y": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
    "-y": [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
    "+x": [[0, 1, 0], [1, 0, 0], [0, 0, -1]],
    "-x": [[0, 1, 0], [-1, 0, 0], [0, 0, 1]],
}


def export_svox_file(tree: Octree, path: str | os.PathLike) -> Path | None:
    """:func:`~plenoctree.octree.io.export_svox` plus, for an NDC tree, volrend's NDC sidecar
    ``<stem>_poses_bounds.npy`` (one LLFF row: the identity reference pose, ``H W f`` = the
    tree's NDC height, width and fx; volrend maps its world rays to NDC with them, near 1).

    Returns the sidecar's path, or None (world-space tree, or an NDC space volrend cannot
    express: ``near != 1`` or ``fx != fy``; the ``.npz``'s ``ndc_config`` still holds it).
    """
    from .octree.io import export_svox

    export_svox(tree, path)
    ndc = tree.ndc
    if ndc is None or abs(ndc.near - 1.0) > 1e-9 or abs(ndc.fx - ndc.fy) > 1e-6 * ndc.fx:
        return None
    row = np.array([[0.0, 1.0, 0.0, 0.0, ndc.height],      # LLFF columns: down, right, back,
                    [-1.0, 0.0, 0.0, 0.0, ndc.width],      # centre, hwf (identity pose)
                    [0.0, 0.0, 1.0, 0.0, ndc.fx]])
    pb = np.concatenate([row.reshape(-1), [1.0, 100.0]])[None]     # + depth bounds
    side = Path(path).with_name(Path(path).stem + "_poses_bounds.npy")
    with atomic_write(side, "wb") as f:
        np.save(f, pb, allow_pickle=False)
    return side


def export_mesh(tree: Octree, path: str | os.PathLike, resolution: int | None = None,
                level: float | None = None, smooth: float = 0.0, view: Any = "normal",
                up: str | None = None, show_progress: bool | None = None) -> Mesh:
    """Write :func:`extract_mesh`'s mesh with vertex colours as ``.ply``, ``.glb`` or ``.obj``
    (by the suffix of ``path``; via trimesh). Returns the mesh (in world coordinates).

    ``.ply``/``.obj`` keep world coordinates. glTF (``.glb``) is +Y-up by specification, so the
    scene's ``up`` axis (default ``"+z"``, Blender/NeRF-synthetic scenes; ``"+y"`` for NDC
    trees, whose LLFF world is y-up) is rotated onto +Y there (Blender's glTF importer rotates
    it back to +Z).
    """
    if up is None:
        up = "+y" if tree.ndc is not None else "+z"
    path = Path(path)
    kind = path.suffix.lower()
    if kind not in MESH_SUFFIXES:
        raise ConfigError(f"{path}: mesh files end in {', '.join(MESH_SUFFIXES)}")
    trimesh = _require("trimesh", "trimesh")
    if up not in _UP_TO_Y:
        raise ConfigError(f"up must be one of {', '.join(_UP_TO_Y)}, got {up!r}")
    mesh = extract_mesh(tree, resolution, level, smooth, view, show_progress)
    verts, nrm = mesh.vertices, mesh.normals
    if kind == ".glb":
        rot = np.asarray(_UP_TO_Y[up], dtype=np.float32)
        verts, nrm = verts @ rot.T, nrm @ rot.T
    rgba = np.concatenate([_u8(mesh.colors), np.full((len(mesh.colors), 1), 255, np.uint8)], 1)
    tm = trimesh.Trimesh(vertices=verts, faces=mesh.faces, vertex_normals=nrm,
                         vertex_colors=rgba, process=False)
    blob = tm.export(file_type=kind[1:])
    if isinstance(blob, str):
        blob = blob.encode()
    with atomic_write(path, "wb") as f:
        f.write(blob)
    return mesh
