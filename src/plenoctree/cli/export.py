"""``plenoctree export``: a tree as svox ``.npz``, a PLY point cloud or a coloured mesh."""

from __future__ import annotations

import argparse
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


def _run(args: argparse.Namespace) -> int:
    from ..compress import load_any_tree

    src, out = Path(args.tree), Path(args.out)
    fmt = args.format or _infer_format(out)
    want = {"svox": (".npz",), "ply": (".ply",), "mesh": (".ply", ".glb", ".obj")}[fmt]
    if out.suffix.lower() not in want:
        raise ConfigError(f"--out {out}: --format {fmt} writes {' or '.join(want)} files")
    if out.exists() and out.resolve() == src.resolve():
        raise ConfigError(f"--out {out} would overwrite the input")
    tree = load_any_tree(src)
    if fmt == "svox":
        from ..export import export_svox_file

        side = export_svox_file(tree, out)
        what = f"svox tree, {tree.n_leaves} leaves (float16)"
        if tree.ndc is not None:
            what += (f"; NDC tree: ndc_config in the file" +
                     (f", volrend's {side.name} beside it" if side else ""))
    elif fmt == "ply":
        from ..export import export_point_cloud

        pts = export_point_cloud(tree, out, view=args.view or "dc",
                                 min_opacity=args.min_opacity, ascii=args.ascii)
        what = f"point cloud, {len(pts.xyz)} points (leaves with opacity >= {args.min_opacity})"
    else:
        from ..export import export_mesh

        mesh = export_mesh(tree, out, resolution=args.resolution, level=args.level,
                           smooth=args.smooth, view=args.view or "normal", up=args.up,
                           show_progress=not args.quiet)
        what = (f"mesh, {len(mesh.vertices)} vertices, {len(mesh.faces)} faces "
                f"(sigma level {mesh.level:.4g})")
    if fmt != "svox" and tree.ndc is not None:
        what += "; NDC tree, written in world coordinates"
    print(f"{src} -> {out}: {what}, {out.stat().st_size / 1e6:.2f} MB")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``export`` command."""
    p = sub.add_parser(
        "export", help="export a tree: svox .npz, PLY point cloud or coloured mesh (.ply/.glb/.obj)",
        description="svox: the svox/volrend .npz layout (float16). ply: one point per occupied "
        "leaf (centre, colour, opacity, density, size). mesh: marching cubes on the density "
        "sampled from the tree, vertex colours from the SH; opens in Blender and MeshLab. "
        "ply and mesh need the 'export' extra (plyfile, trimesh, scikit-image).")
    p.add_argument("tree", help="tree file (.npz native or svox, or compressed .plnz)")
    p.add_argument("--out", required=True, help="output file (.npz, .ply, .glb or .obj)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="svox, ply (point cloud) or mesh (default: from the --out suffix; "
                   ".ply means a point cloud)")
    p.add_argument("--view", default=None,
                   help="colour: 'dc' (view-independent), a ray direction 'x,y,z', or for meshes "
                   "'normal' (seen looking straight at the surface). Default: dc for points, "
                   "normal for meshes")
    p.add_argument("--min-opacity", type=float, default=0.01,
                   help="ply: keep leaves whose opacity 1-exp(-sigma*size) is at least this "
                   "(default 0.01)")
    p.add_argument("--ascii", action="store_true", help="ply: write ASCII instead of binary")
    p.add_argument("--resolution", type=int, default=None,
                   help="mesh: density samples per axis (default: the finest leaf resolution)")
    p.add_argument("--level", type=float, default=None,
                   help="mesh: density iso-value, 1/world units (default: where one sample "
                   "cell is half opaque, -ln(0.5)/cell)")
    p.add_argument("--smooth", type=float, default=0.0,
                   help="mesh: Gaussian blur of the density grid, in cells (default 0)")
    p.add_argument("--up", default=None, choices=["+z", "-z", "+y", "-y", "+x", "-x"],
                   help="mesh .glb: the scene's up axis, turned onto glTF's +Y (default +z, "
                   "Blender scenes; +y for forward-facing NDC trees)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_run)
