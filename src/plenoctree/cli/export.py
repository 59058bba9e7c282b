"""``plenoctree export``: a tree as svox ``.npz``, a PLY point cloud or a coloured mesh."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ConfigError

FORMATS = ("svox", "ply", "mesh")


def _infer_format(out: Path) -> str:
    suffix = out.suffix.lower()
    if suffix == ".npz":
        return "svox"
    if suffix == ".ply":
        return "ply"
    if suffix in (".glb", ".obj"):
        return "mesh"
    raise ConfigError(f"--out {out}: cannot tell the format from the suffix; give --format "
                      f"{'|'.join(FORMATS)}")


@dataclass
class ExportConfig:
    """Options of ``plenoctree export``."""

    tree: str = ""
    """tree file (.npz native or svox, or compressed .plnz)"""
    out: str = ""
    """output file (.npz, .ply, .glb or .obj)"""
    format: str | None = field(default=None, metadata={"choices": FORMATS})
    """svox, ply (point cloud) or mesh (default: from the --out suffix; .ply means a point
    cloud)"""
    view: str | None = None
    """colour: 'dc' (view-independent), a ray direction 'x,y,z', or for meshes 'normal' (seen
    looking straight at the surface). Default: dc for points, normal for meshes"""
    min_opacity: float = 0.01
    """ply: keep leaves whose opacity 1-exp(-sigma*size) is at least this"""
    ascii: bool = False
    """ply: write ASCII instead of binary"""
    resolution: int | None = None
    """mesh: density samples per axis (default: the finest leaf resolution)"""
    level: float | None = None
    """mesh: density iso-value, 1/world units (default: where one sample cell is half opaque,
    -ln(0.5)/cell)"""
    smooth: float = 0.0
    """mesh: Gaussian blur of the density grid, in cells"""
    up: str | None = field(default=None,
                           metadata={"choices": ("+z", "-z", "+y", "-y", "+x", "-x")})
    """mesh .glb: the scene's up axis, turned onto glTF's +Y (default +z, Blender scenes; +y for
    forward-facing NDC trees)"""
    show_progress: bool = True
    """progress output (off: --quiet or --no-progress)"""


def _run(cfg: ExportConfig, args: argparse.Namespace) -> int:
    from ..compression import load_any_tree
    from ._output import output_file

    src, out = Path(cfg.tree), Path(cfg.out)
    fmt = cfg.format or _infer_format(out)
    want = {"svox": (".npz",), "ply": (".ply",), "mesh": (".ply", ".glb", ".obj")}[fmt]
    if out.suffix.lower() not in want:
        raise ConfigError(f"--out {out}: --format {fmt} writes {' or '.join(want)} files")
    if out.exists() and src.exists() and out.samefile(src):
        raise ConfigError(f"--out {out} would overwrite the input")
    with output_file(out, "export", overwrite=args.overwrite,
                     kind="tree" if fmt == "svox" else None):
        what = _export(cfg, args, load_any_tree(src), fmt, out)
    print(f"{src} -> {out}: {what}, {out.stat().st_size / 1e6:.2f} MB")
    return 0


def _export(cfg: ExportConfig, args: argparse.Namespace, tree, fmt: str, out: Path) -> str:
    """Write ``tree`` to ``out`` in format ``fmt``; returns what was written, in words."""
    if fmt == "svox":
        from ..export import export_svox_file

        side = export_svox_file(tree, out)
        what = f"svox tree, {tree.n_leaves} leaves (float16)"
        if tree.ndc is not None:
            what += (f"; NDC tree: ndc_config in the file" +
                     (f", volrend's {side.name} beside it" if side else ""))
    elif fmt == "ply":
        from ..export import export_point_cloud

        pts = export_point_cloud(tree, out, view=cfg.view or "dc",
                                 min_opacity=cfg.min_opacity, ascii=cfg.ascii)
        what = f"point cloud, {len(pts.xyz)} points (leaves with opacity >= {cfg.min_opacity})"
    else:
        from ..export import export_mesh

        mesh = export_mesh(tree, out, resolution=cfg.resolution, level=cfg.level,
                           smooth=cfg.smooth, view=cfg.view or "normal", up=cfg.up,
                           show_progress=cfg.show_progress)
        what = (f"mesh, {len(mesh.vertices)} vertices, {len(mesh.faces)} faces "
                f"(sigma level {mesh.level:.4g})")
    if fmt != "svox" and tree.ndc is not None:
        what += "; NDC tree, written in world coordinates"
    return what


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``export`` command (one flag per :class:`ExportConfig` field)."""
    from ._options import add_command
    from ._output import add_overwrite

    p = add_command(
        sub, "export", ExportConfig, _run,
        help="export a tree: svox .npz, PLY point cloud or coloured mesh (.ply/.glb/.obj)",
        description="svox: the svox/volrend .npz layout (float16). ply: one point per occupied "
        "leaf (centre, colour, opacity, density, size). mesh: marching cubes on the density "
        "sampled from the tree, vertex colours from the SH; opens in Blender and MeshLab. "
        "ply and mesh need the 'export' extra (plyfile, trimesh, scikit-image).",
        positional=("tree",), fields={"out": {"required": True}})
    add_overwrite(p)
