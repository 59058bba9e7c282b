"""Exports on real data (marked ``lego``; skipped without ../shared): a small 64^3 tree
extracted from the shared lego NeRF-SH run, exported as a mesh (.glb, .ply), a point cloud
and an svox file; the geometry is checked against the lego test photos' alpha masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

_HERE = Path(__file__).resolve().parents[1]          # the checkout (a worktree: one deeper)
SHARED = next((d / "shared" for d in (_HERE.parent, _HERE.parent.parent)
               if (d / "shared/data").is_dir()), _HERE.parent / "shared")
LEGO = SHARED / "data/nerf_synthetic/lego"
RUN = SHARED / "data/runs/lego_cpu_400"

pytestmark = [
    pytest.mark.lego,
    pytest.mark.skipif(not ((LEGO / "transforms_test.json").is_file()
                            and (RUN / "checkpoint.pt").is_file()),
                       reason="shared lego data / NeRF-SH run not found"),
]


@pytest.fixture(scope="module")
def lego(tmp_path_factory):
    from plenoctree.convert.extraction import ExtractConfig, extract
    from plenoctree.datasets import load_dataset

    d = tmp_path_factory.mktemp("lego_export")
    ex = extract(ExtractConfig(run_dir=str(RUN), data=str(LEGO), out=str(d / "t64.npz"),
                               grid=64, samples=1, masking="sigma", bbox="fixed", eval=False,
                               show_progress=False))
    test = load_dataset(LEGO, "test", downscale=8, limit=40)       # 100 x 100, with alpha
    idx = [0, 13, 27, 39]
    return {"dir": d, "tree": ex.tree, "path": d / "t64.npz", "test": test, "views": idx}


def _project(cams, i, pts):
    """Pixel (col, row) and depth of world points in camera ``i`` (OpenGL camera)."""
    c2w = cams.c2w[i].astype(np.float64)
    pc = (pts - c2w[:3, 3]) @ c2w[:3, :3]
    fx, fy, cx, cy = cams.intrinsics(i)
    z = -pc[:, 2]
    return cx + fx * pc[:, 0] / z, cy - fy * pc[:, 1] / z, z


def _inside_mask(alpha, col, row, grow=1):
    """Whether each projected point lands on (or within ``grow`` px of) the object's mask."""
    from scipy.ndimage import binary_dilation

    mask = binary_dilation(alpha > 0.5, iterations=grow)
    h, w = mask.shape
    c, r = np.floor(col).astype(int), np.floor(row).astype(int)
    ok = (c >= 0) & (c < w) & (r >= 0) & (r < h)
    out = np.zeros(len(col), bool)
    out[ok] = mask[r[ok], c[ok]]
    return out


def test_lego_mesh_matches_the_photos_silhouettes(lego):
    trimesh = pytest.importorskip("trimesh")
    pytest.importorskip("skimage")
    from plenoctree.cli import main

    out = lego["dir"] / "lego.glb"
    assert main(["export", str(lego["path"]), "--out", str(out), "--quiet"]) == 0
    scene = trimesh.load(out)
    mesh = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    # glTF is +Y up: back to the dataset's +Z-up world
    v = np.asarray(mesh.vertices, np.float64) @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    assert 5_000 < len(v) < 500_000
    assert (np.abs(v) <= 1.5 + 1e-4).all()                            # inside the lego box
    test, cams = lego["test"], lego["test"].cameras
    world = trimesh.Trimesh(vertices=v, faces=np.asarray(mesh.faces), process=False)
    surf = trimesh.sample.sample_surface(world, 200_000, seed=0)[0]
    covered = []
    for i in lego["views"]:
        col, row, z = _project(cams, i, surf)
        assert (z > 0).all()
        assert _inside_mask(test.alphas[i], col, row).mean() > 0.97    # nothing off the object
        # and the object is covered: the surface's projection fills the photo's mask
        hit = np.zeros(test.alphas[i].shape, bool)
        c, r = np.clip(col.astype(int), 0, 99), np.clip(row.astype(int), 0, 99)
        hit[r, c] = True
        covered.append(hit[test.alphas[i] > 0.5].mean())
    assert min(covered) > 0.95, covered
    # vertex colours: the lego's yellow/grey palette, close to the photos' mean colour
    rgba = np.asarray(mesh.visual.vertex_colors, np.float64)[:, :3] / 255
    fg = np.concatenate([test.images[i][test.alphas[i] > 0.5] for i in lego["views"]])
    np.testing.assert_allclose(rgba.mean(0), fg.mean(0), atol=0.08)
    ply = lego["dir"] / "lego_mesh.ply"
    assert main(["export", str(lego["path"]), "--out", str(ply), "--format", "mesh",
                 "--quiet"]) == 0
    m2 = trimesh.load(ply, process=False)
    assert len(m2.vertices) == len(v) and len(m2.faces) == len(mesh.faces)
    np.testing.assert_allclose(np.asarray(m2.vertices), v, atol=1e-5)


def test_lego_point_cloud_and_svox_round_trip(lego):
    plyfile = pytest.importorskip("plyfile")
    pytest.importorskip("scipy")
    from plenoctree.cli import main
    from plenoctree.octree import import_svox

    out = lego["dir"] / "lego_points.ply"
    assert main(["export", str(lego["path"]), "--out", str(out), "--min-opacity", "0.5"]) == 0
    el = plyfile.PlyData.read(str(out))["vertex"]
    xyz = np.stack([el["x"], el["y"], el["z"]], 1).astype(np.float64)
    assert len(xyz) > 2000 and (np.asarray(el["opacity"]) >= 0.5).all()
    test, cams = lego["test"], lego["test"].cameras
    for i in lego["views"]:
        col, row, _ = _project(cams, i, xyz)
        assert _inside_mask(test.alphas[i], col, row).mean() > 0.97
    rgb = np.stack([el["red"], el["green"], el["blue"]], 1) / 255
    fg = np.concatenate([test.images[i][test.alphas[i] > 0.5] for i in lego["views"]])
    np.testing.assert_allclose(rgb.mean(0), fg.mean(0), atol=0.08)
    svox = lego["dir"] / "lego_svox.npz"
    assert main(["export", str(lego["path"]), "--out", str(svox)]) == 0
    back = import_svox(svox)
    tree = lego["tree"]
    assert back.ndc is None and back.n_leaves == tree.n_leaves
    np.testing.assert_array_equal(back.child, tree.child)
    np.testing.assert_allclose(back.data, tree.data, rtol=1e-3, atol=1e-3)
