"""Exports: svox .npz, PLY point cloud, coloured mesh (golden files, plyfile/trimesh round trips)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from plenoctree.cli import main
from plenoctree.errors import BackendError, ConfigError
from plenoctree.export import (export_mesh, export_point_cloud, extract_mesh, leaf_points,
                               point_colors, sample_sigma_grid)
from plenoctree.octree import Octree, save_tree
from plenoctree.octree.io import import_svox
from plenoctree.sh import SH_C0, eval_sh_bases

plyfile = pytest.importorskip("plyfile")
trimesh = pytest.importorskip("trimesh")
pytest.importorskip("skimage")

GOLDEN = Path(__file__).parent / "golden"


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _tiny_tree() -> Octree:
    """A 2^3 SH4 grid (depth 0) with fixed values; two cells empty, one faint."""
    vals = np.zeros((2, 2, 2, 13), np.float32)
    rng = np.random.default_rng(3)
    vals[..., :12] = np.round(rng.normal(size=(2, 2, 2, 12)), 2)
    vals[..., 12] = [[[4.0, 0.0], [2.0, 1.0]], [[0.0, 8.0], [0.001, 3.0]]]
    return Octree.from_grid(vals, np.ones((2, 2, 2), bool), center=[0.5, 0, 0],
                            radius=[1.0, 1.0, 2.0], data_format="SH4")


def _ball_tree(res=32, radius=0.6, coeff=None) -> Octree:
    """A ball of constant density 200 and (SH4) colour coefficients ``coeff [12]``."""
    g = (np.arange(res) + 0.5) / res * 2 - 1
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    mask = x ** 2 + y ** 2 + z ** 2 <= radius ** 2
    vals = np.zeros((res, res, res, 13), np.float32)
    vals[..., :12] = 0.0 if coeff is None else coeff
    vals[..., 12] = 200.0
    vals[~mask] = 0
    return Octree.from_grid(vals, mask, center=0.0, radius=1.0, data_format="SH4")


# ------------------------------------------------------------------ point cloud
def test_point_cloud_golden_ascii(tmp_path):
    """The ASCII PLY of a fixed tree matches the committed golden file byte for byte."""
    out = tmp_path / "p.ply"
    export_point_cloud(_tiny_tree(), out, min_opacity=0.01, ascii=True)
    assert out.read_text() == (GOLDEN / "points_sh4.ply").read_text()


def test_point_cloud_values_round_trip(tmp_path):
    tree = _tiny_tree()
    out = tmp_path / "p.ply"
    export_point_cloud(tree, out)
    v = plyfile.PlyData.read(str(out))["vertex"]
    # 8 leaves: two have sigma 0, one has opacity 1-exp(-0.001*1.333) < 0.01
    assert len(v) == 5
    sig = np.asarray(v["sigma"])
    np.testing.assert_allclose(np.sort(sig), [1, 2, 3, 4, 8])
    leaf = tree.child == 0
    data = tree.data[leaf]
    centres = tree.leaf_centers()
    sizes = tree.leaf_sizes()
    for row in v.data:
        i = int(np.argmin(np.abs(data[:, -1] - row["sigma"])))
        np.testing.assert_allclose([row["x"], row["y"], row["z"]], centres[i], atol=1e-6)
        np.testing.assert_allclose([row["size_x"], row["size_y"], row["size_z"]], sizes[i])
        assert sizes[i].tolist() == [1.0, 1.0, 2.0]
        op = 1 - np.exp(-data[i, -1] * sizes[i].mean())
        assert row["opacity"] == pytest.approx(op, rel=1e-6)
        dc = _sigmoid(SH_C0 * data[i, [0, 4, 8]])       # channel-major: R0, G0, B0
        np.testing.assert_array_equal([row["red"], row["green"], row["blue"]],
                                      (dc * 255 + 0.5).astype(np.uint8))
        assert row["alpha"] == int(op * 255 + 0.5)


def test_point_colors_view_direction_matches_sh():
    tree = _tiny_tree()
    k = tree.data[tree.child == 0][:, :-1]
    d = np.array([0.3, -0.5, 0.8])
    d /= np.linalg.norm(d)
    got = point_colors(tree, k, d)
    y = eval_sh_bases(1, d[None])[0]
    want = _sigmoid(k.reshape(-1, 3, 4) @ y)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    pts = leaf_points(tree, view="0.3,-0.5,0.8")
    assert not np.allclose(pts.rgb, leaf_points(tree).rgb)


def test_point_cloud_errors(tmp_path):
    with pytest.raises(ConfigError, match="min-opacity"):
        export_point_cloud(_tiny_tree(), tmp_path / "p.ply", min_opacity=0.99999999)
    assert not (tmp_path / "p.ply").exists()
    with pytest.raises(ConfigError, match="direction"):
        leaf_points(_tiny_tree(), view="0,0,0")
    with pytest.raises(ConfigError, match="min_opacity"):
        leaf_points(_tiny_tree(), min_opacity=1.5)


def test_missing_extra_names_it(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "plyfile", None)      # import plyfile -> ImportError
    with pytest.raises(BackendError, match=r"plenoctree\[export\]"):
        export_point_cloud(_tiny_tree(), tmp_path / "p.ply")
    monkeypatch.setitem(sys.modules, "skimage.measure", None)
    with pytest.raises(BackendError, match="scikit-image"):
        extract_mesh(_tiny_tree())


# ------------------------------------------------------------------ mesh
def test_sigma_grid_matches_query():
    tree = _ball_tree(16)
    sigma, spacing = sample_sigma_grid(tree)
    assert sigma.shape == (16, 16, 16)
    np.testing.assert_allclose(spacing, [2 / 16] * 3)
    g = -1 + (np.arange(16) + 0.5) * spacing[0]
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    np.testing.assert_array_equal(sigma, tree.query(pts)[..., -1])


def test_mesh_of_a_ball_is_closed_round_and_outward():
    r = 0.6
    mesh = extract_mesh(_ball_tree(32, r), level=100.0, smooth=1.0)   # half the ball's sigma
    rad = np.linalg.norm(mesh.vertices, axis=1)
    cell = 2 / 32
    assert abs(np.median(rad) - r) < cell and rad.min() > r - 2 * cell and rad.max() < r + 2 * cell
    tri = mesh.vertices[mesh.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.mean(np.sum(fn * tri.mean(1), 1) > 0) > 0.99          # CCW seen from outside
    assert np.mean(np.sum(mesh.normals * mesh.vertices, 1) > 0) > 0.99
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
    assert tm.is_watertight
    assert tm.volume == pytest.approx(4 / 3 * np.pi * r ** 3, rel=0.1)


def test_mesh_vertex_colours_seen_along_normal():
    coeff = np.zeros(12, np.float32)
    coeff[[0, 4, 8]] = [1.0, -0.5, 0.2]
    coeff[3] = 2.0            # R varies with -C1*x
    mesh = extract_mesh(_ball_tree(32, 0.6, coeff), view="normal")
    d = -mesh.normals.astype(np.float64)
    y = eval_sh_bases(1, d / np.linalg.norm(d, axis=1, keepdims=True))
    want = _sigmoid(coeff.reshape(3, 4) @ y.T).T
    np.testing.assert_allclose(mesh.colors, want, atol=1e-5)
    dc = extract_mesh(_ball_tree(32, 0.6, coeff), view="dc").colors
    np.testing.assert_allclose(dc, np.broadcast_to(_sigmoid(SH_C0 * coeff[[0, 4, 8]]), dc.shape),
                               atol=1e-6)


def test_mesh_golden(tmp_path):
    """A 4^3 block mesh: vertex set, face count and colours pinned in a golden JSON."""
    vals = np.zeros((4, 4, 4, 4), np.float32)
    vals[1:3, 1:3, 1:3] = [0.5, -1.0, 2.0, 50.0]
    mask = vals[..., -1] > 0
    tree = Octree.from_grid(vals, mask, 0.0, 1.0, "RGBA")
    mesh = extract_mesh(tree, level=25.0)
    got = {"n_vertices": len(mesh.vertices), "n_faces": len(mesh.faces),
           "vertices": sorted(np.round(mesh.vertices, 5).tolist()),
           "color": np.round(mesh.colors[0], 6).tolist()}
    want = json.loads((GOLDEN / "mesh_block.json").read_text())
    assert got == want
    # level 25 is halfway between the block's samples (50) and empty ones: the surface is the
    # block's boundary, the cube [-0.5, 0.5]^3 (edges chamfered by marching cubes)
    np.testing.assert_allclose(np.abs(mesh.vertices).max(1), 0.5, atol=1e-6)
    np.testing.assert_allclose(mesh.colors, _sigmoid(np.array([0.5, -1.0, 2.0]))[None]
                               .repeat(len(mesh.colors), 0), atol=1e-6)


@pytest.mark.parametrize("suffix", [".ply", ".glb", ".obj"])
def test_mesh_file_round_trip(tmp_path, suffix):
    coeff = np.zeros(12, np.float32)
    coeff[[0, 4, 8]] = [1.0, -0.5, 0.2]
    tree = _ball_tree(16, 0.6, coeff)
    out = tmp_path / f"m{suffix}"
    mesh = export_mesh(tree, out)
    loaded = trimesh.load(str(out), process=False)
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
    v = np.asarray(loaded.vertices)
    assert len(v) == len(mesh.vertices) and len(loaded.faces) == len(mesh.faces)
    want = mesh.vertices
    if suffix == ".glb":                        # +Z up turned onto glTF's +Y: (x, z, -y)
        want = np.stack([want[:, 0], want[:, 2], -want[:, 1]], 1)
    np.testing.assert_allclose(v, want, atol=1e-5)
    if suffix != ".obj":                        # OBJ has no standard vertex colours
        col = np.asarray(loaded.visual.vertex_colors)[:, :3]
        np.testing.assert_array_equal(col, (np.clip(mesh.colors, 0, 1) * 255 + 0.5).astype(np.uint8))


def test_mesh_errors(tmp_path):
    tree = _ball_tree(8)
    with pytest.raises(ConfigError, match="no surface"):
        extract_mesh(tree, level=1e6)
    with pytest.raises(ConfigError, match="mesh files end in"):
        export_mesh(tree, tmp_path / "m.stl")
    with pytest.raises(ConfigError, match="resolution"):
        extract_mesh(tree, resolution=1)
    with pytest.raises(ConfigError, match="up must be"):
        export_mesh(tree, tmp_path / "m.glb", up="z")
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ CLI
@pytest.fixture()
def tree_file(tmp_path):
    path = tmp_path / "t.npz"
    save_tree(_ball_tree(16, 0.6), path, precision="fp32")
    return path


def test_cli_export_svox_round_trip(tree_file, tmp_path, capsys):
    out = tmp_path / "svox.npz"
    assert main(["export", str(tree_file), "--format", "svox", "--out", str(out)]) == 0
    back = import_svox(out)
    tree = _ball_tree(16, 0.6)
    np.testing.assert_array_equal(back.child, tree.child)
    np.testing.assert_allclose(back.data, tree.data, rtol=1e-3)
    assert "svox tree" in capsys.readouterr().out


def test_cli_export_format_from_suffix_and_flags(tree_file, tmp_path, capsys):
    ply = tmp_path / "p.ply"
    assert main(["export", str(tree_file), "--out", str(ply), "--min-opacity", "0.5",
                 "--ascii", "--view", "0,0,-1"]) == 0
    assert ply.read_bytes().startswith(b"ply\nformat ascii")
    n = len(plyfile.PlyData.read(str(ply))["vertex"])
    assert n == int((_ball_tree(16, 0.6).data[..., -1] > 0).sum())
    glb = tmp_path / "m.glb"
    assert main(["export", str(tree_file), "--out", str(glb), "--resolution", "24",
                 "--smooth", "0.5", "--level", "50", "--up", "+y", "--quiet"]) == 0
    assert "sigma level 50" in capsys.readouterr().out
    mply = tmp_path / "m.ply"
    assert main(["export", str(tree_file), "--format", "mesh", "--out", str(mply)]) == 0
    assert "face" in plyfile.PlyData.read(str(mply))


def test_cli_export_errors(tree_file, tmp_path, capsys):
    assert main(["export", str(tree_file), "--out", str(tmp_path / "x.stl")]) == 1
    assert "cannot tell the format" in capsys.readouterr().err
    assert main(["export", str(tree_file), "--format", "svox", "--out",
                 str(tmp_path / "x.ply")]) == 1
    assert "writes .npz" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    assert main(["export", str(bad), "--out", str(tmp_path / "x.ply")]) == 1
    assert str(bad) in capsys.readouterr().err
    assert main(["export", str(tree_file), "--out", str(tmp_path / "m.glb"),
                 "--level", "1e9"]) == 1
    assert "no surface" in capsys.readouterr().err
    assert not (tmp_path / "x.ply").exists() and not (tmp_path / "m.glb").exists()
