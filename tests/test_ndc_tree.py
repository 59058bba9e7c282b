"""Forward-facing (NDC) trees carry their NDC space in every file format (native v2, svox
``ndc_config`` + volrend's sidecar, ``.plnz`` v2), old files still load, and ``info``,
``export``, ``video`` and ``render --camera-path`` use it without ``--data``."""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from plenoctree.cli import main
from plenoctree.compression import compress, load_any_tree, save_compressed
from plenoctree.compression.lod import truncate_sh
from plenoctree.datasets import Cameras, load_dataset
from plenoctree.datasets import ndc as dndc
from plenoctree.errors import TreeFormatError
from plenoctree.octree import export_svox, import_svox, load_tree, save_tree
from plenoctree.octree.ndc import NDCSpace

GOLDEN = Path(__file__).parent / "golden"
GOLDEN_NDC = NDCSpace(48, 36, 40.0, 41.5, 1.0)


def _raw(path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


# ---------------------------------------------------------------------- golden files
def test_golden_v1_file_still_loads_as_a_world_space_tree():
    """tests/golden/tree_v1.npz: format_version 1, as plenoctree 0.1.0 wrote it (no ndc)."""
    assert int(_raw(GOLDEN / "tree_v1.npz")["format_version"]) == 1
    t = load_tree(GOLDEN / "tree_v1.npz")
    assert t.ndc is None and t.data_format == "SH4" and t.n_nodes == 9 and t.n_leaves == 64
    assert float(t.data.sum(dtype=np.float64)) == pytest.approx(94.834137, rel=1e-6)
    np.testing.assert_allclose(t.center, [0.1, -0.2, 0.0])
    np.testing.assert_allclose(t.radius, [1.2, 1.1, 1.0])


def test_golden_v2_ndc_file_and_its_resave(tmp_path):
    raw = _raw(GOLDEN / "ndc_tree_v2.npz")
    assert int(raw["format_version"]) == 2
    header = json.loads(str(raw["header"]))
    assert header["ndc"] == {"width": 48, "height": 36, "fx": 40.0, "fy": 41.5, "near": 1.0}
    t = load_tree(GOLDEN / "ndc_tree_v2.npz")
    v1 = load_tree(GOLDEN / "tree_v1.npz")
    assert t.ndc == GOLDEN_NDC and "ndc=True" in repr(t)
    np.testing.assert_array_equal(t.data, v1.data)
    np.testing.assert_array_equal(t.child, v1.child)
    save_tree(t, tmp_path / "again.npz")
    again = _raw(tmp_path / "again.npz")
    for key in ("child", "data", "offset", "invradius3", "format_version"):
        np.testing.assert_array_equal(again[key], raw[key])
    h2 = json.loads(str(again["header"]))
    h2.pop("package_version"), header.pop("package_version")
    assert h2 == header


# ---------------------------------------------------------------------- every format
def test_ndc_survives_every_file_format_and_copy(tmp_path):
    t = load_tree(GOLDEN / "ndc_tree_v2.npz")
    save_tree(t, tmp_path / "h.npz", precision="fp16", compressed=True)
    assert load_tree(tmp_path / "h.npz").ndc == GOLDEN_NDC
    export_svox(t, tmp_path / "svox.npz")
    raw = _raw(tmp_path / "svox.npz")        # svox's N3Tree.load uses np.load: extra key only
    np.testing.assert_array_equal(raw["ndc_config"], [48, 36, 40.0, 41.5, 1.0])
    assert raw["ndc_config"].dtype == np.float64
    for back in (import_svox(tmp_path / "svox.npz"), load_tree(tmp_path / "svox.npz"),
                 load_any_tree(tmp_path / "svox.npz")):
        assert back.ndc == GOLDEN_NDC
    save_compressed(compress(t), tmp_path / "c.plnz")
    raw = _raw(tmp_path / "c.plnz")
    assert int(raw["plnz_version"]) == 2
    assert json.loads(str(raw["header"]))["ndc"] == GOLDEN_NDC.to_json()
    assert load_any_tree(tmp_path / "c.plnz").ndc == GOLDEN_NDC
    for derived in (t.copy(), t.astype(np.float16), truncate_sh(t, 0),
                    dataclasses.replace(t, data=t.data * 1)):
        assert derived.ndc == GOLDEN_NDC
    plain = load_tree(GOLDEN / "tree_v1.npz")
    export_svox(plain, tmp_path / "w.npz")
    assert "ndc_config" not in _raw(tmp_path / "w.npz")
    assert import_svox(tmp_path / "w.npz").ndc is None


def _rewrite_zip(src: Path, dst: Path, **arrays) -> None:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for name in zin.namelist():
            key = name[:-4]
            if key in arrays:
                if arrays[key] is None:
                    continue
                buf = io.BytesIO()
                np.save(buf, arrays.pop(key), allow_pickle=False)
                zout.writestr(name, buf.getvalue())
            else:
                zout.writestr(name, zin.read(name))
        for key, arr in arrays.items():
            if arr is not None:
                buf = io.BytesIO()
                np.save(buf, arr, allow_pickle=False)
                zout.writestr(key + ".npy", buf.getvalue())


def test_plnz_v1_still_loads_and_bad_ndc_is_one_clear_error(tmp_path):
    t = load_tree(GOLDEN / "ndc_tree_v2.npz")
    save_compressed(compress(t), tmp_path / "c.plnz")
    header = json.loads(str(_raw(tmp_path / "c.plnz")["header"]))
    old = {k: v for k, v in header.items() if k != "ndc"}
    _rewrite_zip(tmp_path / "c.plnz", tmp_path / "v1.plnz", plnz_version=np.int64(1),
                 header=np.array(json.dumps(old)), ndc_config=None)
    assert load_any_tree(tmp_path / "v1.plnz").ndc is None
    bad = {**header, "ndc": {**header["ndc"], "near": 0}}
    _rewrite_zip(tmp_path / "c.plnz", tmp_path / "bad.plnz", header=np.array(json.dumps(bad)))
    with pytest.raises(TreeFormatError, match=r"bad\.plnz: header 'ndc': NDC near must be"):
        load_any_tree(tmp_path / "bad.plnz")
    export_svox(t, tmp_path / "s.npz")
    _rewrite_zip(tmp_path / "s.npz", tmp_path / "s_bad.npz",
                 ndc_config=np.array([48.0, 36.0, np.nan, 41.5, 1.0]))
    with pytest.raises(TreeFormatError, match=r"s_bad\.npz: ndc_config: NDC fx must be"):
        import_svox(tmp_path / "s_bad.npz")
    _rewrite_zip(tmp_path / "s.npz", tmp_path / "s_shape.npz", ndc_config=np.zeros(3))
    with pytest.raises(TreeFormatError, match=r"s_shape\.npz: 'ndc_config' must be 5 numbers"):
        load_tree(tmp_path / "s_shape.npz")


def test_volrend_sidecar_is_the_identity_reference_camera(tmp_path):
    pytest.importorskip("plyfile")
    from plenoctree.export import export_svox_file

    t = load_tree(GOLDEN / "ndc_tree_v2.npz")
    assert export_svox_file(t, tmp_path / "a.npz") is None              # fx != fy: no sidecar
    assert not (tmp_path / "a_poses_bounds.npy").exists()
    t.ndc = NDCSpace(48, 36, 40.0, 40.0, 1.0)
    side = export_svox_file(t, tmp_path / "b.npz")
    assert side == tmp_path / "b_poses_bounds.npy"
    pb = np.load(side)
    assert pb.shape == (1, 17)
    ptr = pb.reshape(-1)                       # volrend's unpack_llff_poses_bounds reads:
    assert (ptr[4], ptr[9], ptr[14]) == (36.0, 48.0, 40.0)              # H, W, focal
    m = pb[0, :15].reshape(3, 5)
    np.testing.assert_array_equal(-m[:, 0], [0, 1, 0])                  # up = -down
    np.testing.assert_array_equal(m[:, 1], [1, 0, 0])                   # right
    np.testing.assert_array_equal(m[:, 2], [0, 0, 1])                   # back
    np.testing.assert_array_equal(m[:, 3], [0, 0, 0])                   # centre
    t.ndc = NDCSpace(48, 36, 40.0, 40.0, 2.0)                           # volrend's near is 1
    assert export_svox_file(t, tmp_path / "c.npz") is None


# ---------------------------------------------------------------------- maps and cameras
def test_ndcspace_maps_match_the_dataset_ndc_functions():
    n = NDCSpace(64, 48, 50.0, 55.0, 1.5)
    rng = np.random.default_rng(0)
    p = rng.uniform([-2, -2, -20], [2, 2, -1.6], (100, 3))
    q = n.world_to_ndc(p)
    np.testing.assert_allclose(q, dndc.world_to_ndc(p, 50.0, 55.0, 64, 48, 1.5), rtol=1e-6)
    np.testing.assert_allclose(n.ndc_to_world(q), p, rtol=1e-9)
    np.testing.assert_allclose(n.ndc_to_world(q), dndc.ndc_to_world(q, 50.0, 55.0, 64, 48, 1.5),
                               rtol=1e-5)
    assert n.same_space(NDCSpace(128, 96, 100.0, 110.0, 1.5))     # same map at twice the size
    assert not n.same_space(NDCSpace(64, 48, 50.0, 55.0, 1.0))
    with pytest.raises(TreeFormatError, match="width"):
        NDCSpace(0, 48, 50.0, 55.0)


def test_apply_renders_any_camera_in_the_trees_ndc_space():
    n = NDCSpace(48, 36, 40.0, 41.5, 1.3)
    c2w = np.tile(np.eye(4, dtype=np.float32), (3, 1, 1))
    c2w[:, :3, 3] = [[0, 0, 0], [0.1, -0.05, 0.2], [-0.1, 0.1, -0.1]]
    world = Cameras(c2w, 30.0, 31.0, 20.0, 14.0, 40, 30)           # not the reference camera
    cams = n.apply(world)
    assert NDCSpace.from_cameras(cams).same_space(n)
    for i in range(3):
        o, d = cams.rays(i)
        wo, wd = world.rays(i)
        ro, rd = dndc.to_ndc_rays(wo, wd, 40.0, 41.5, 48, 36, 1.3)
        np.testing.assert_allclose(o, ro, atol=1e-5)
        np.testing.assert_allclose(d, rd, atol=1e-5)
    b, col, row = np.array([1, 2]), np.array([3.0, 17.0]), np.array([5.0, 29.0])
    po, pd = cams.pixel_rays(b, col, row)
    o1, d1 = cams.rays(1)
    np.testing.assert_allclose(po[0], o1[5, 3], atol=1e-5)
    np.testing.assert_allclose(pd[0], d1[5, 3], atol=1e-5)
    for derived in (cams.resized(80, 60), cams.select([0, 2]), cams.scaled(2)):
        assert derived.ndc_ref == cams.ndc_ref
        assert NDCSpace.from_cameras(derived).same_space(n)


# ---------------------------------------------------------------------- commands
@pytest.fixture(scope="module")
def ff(tmp_path_factory):
    from nerf_fixtures import ff_tree

    d = tmp_path_factory.mktemp("ndc_tree")
    root, tree, path = ff_tree(d, n_images=9, n_samples=64)
    return {"root": root, "tree": tree, "path": path, "dir": d}


def test_forward_facing_tree_knows_its_dataset_ndc_space(ff):
    cams = load_dataset(ff["root"], "train").cameras
    assert cams.ndc and ff["tree"].ndc.same_space(NDCSpace.from_cameras(cams))
    assert load_tree(ff["path"]).ndc == ff["tree"].ndc


def test_cli_info_shows_the_ndc_space(ff, tmp_path, capsys):
    assert main(["info", str(ff["path"])]) == 0
    out = capsys.readouterr().out
    assert "forward-facing, NDC of the reference camera: width 48, height 36, fx 66.6667" in out
    assert main(["info", str(ff["path"]), "--json", str(tmp_path / "i.json")]) == 0
    assert json.loads((tmp_path / "i.json").read_text())["ndc"] == ff["tree"].ndc.to_json()
    assert main(["info", str(GOLDEN / "tree_v1.npz")]) == 0
    assert "no (world-space tree)" in capsys.readouterr().out


def _scene_density(root, world_pts):
    """The procedural scene's density at normalised-LLFF world points (as forward_facing)."""
    from plenoctree.datasets import procedural as proc
    from plenoctree.datasets.llff import read_llff

    inv_t = np.linalg.inv(read_llff(root).transform)
    return proc.density((world_pts @ inv_t[:3, :3].T + inv_t[:3, 3]).astype(np.float32))


def test_cli_export_mesh_and_points_of_an_ndc_tree_are_in_world_space(ff, tmp_path, capsys):
    trimesh = pytest.importorskip("trimesh")
    plyfile = pytest.importorskip("plyfile")
    pytest.importorskip("skimage")
    assert main(["export", str(ff["path"]), "--out", str(tmp_path / "m.ply"),
                 "--format", "mesh"]) == 0
    assert "NDC tree, written in world coordinates" in capsys.readouterr().out
    m = trimesh.load(tmp_path / "m.ply", process=False)
    v = np.asarray(m.vertices, np.float64)
    assert len(v) > 100 and (v[:, 2] < -0.99).all()            # in front of the near plane
    # the surface of the scene: just inside it the scene is dense, just outside empty
    nrm = np.asarray(m.vertex_normals, np.float64)
    step = 0.03 * nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    inside = (_scene_density(ff["root"], v - step) > 0).mean()
    outside = (_scene_density(ff["root"], v + step) > 0).mean()
    assert inside > 0.2 and outside < 0.02, (inside, outside)
    # faces wound counter-clockwise about the outward normals after the un-warp
    fn = np.asarray(m.face_normals)
    vn = nrm[np.asarray(m.faces)].mean(1)
    assert (np.sum(fn * vn, 1) > 0).mean() > 0.95
    assert main(["export", str(ff["path"]), "--out", str(tmp_path / "p.ply")]) == 0
    pts = plyfile.PlyData.read(str(tmp_path / "p.ply"))["vertex"]
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1).astype(np.float64)
    assert (xyz[:, 2] < -0.99).all()
    # projecting the world points with the reference camera gives the leaf centres in NDC
    tree = ff["tree"]
    occupied = tree.leaf_data()[:, -1] > 0
    centres = tree.leaf_centers()[occupied]
    back = tree.ndc.world_to_ndc(xyz)
    near = np.min(np.linalg.norm(centres[None, :, :] - back[:, None, :], axis=2), 1)
    assert near.max() < 1e-5
    assert main(["export", str(ff["path"]), "--out", str(tmp_path / "s.npz")]) == 0
    assert "volrend's s_poses_bounds.npy" in capsys.readouterr().out
    assert (tmp_path / "s_poses_bounds.npy").exists()


def test_video_and_camera_path_of_an_ndc_tree_without_data(ff, tmp_path, capsys):
    from plenoctree.camera_path import write_camera_path
    from plenoctree.render import render_image

    data = load_dataset(ff["root"], "test")
    world = dataclasses.replace(data.cameras, ndc=False)        # the same poses, world rays
    write_camera_path(tmp_path / "path.json", world, fps=10)
    out = tmp_path / "frames"
    assert main(["render", str(ff["path"]), "--camera-path", str(tmp_path / "path.json"),
                 "--out", str(out), "--views", "2"]) == 0
    for i in range(2):          # the NDC tree rendered along world poses = the dataset's view
        ref = render_image(ff["tree"], data.cameras, i).depth.numpy()
        got = np.load(out / f"frame_{i:05d}_depth.npy")
        assert ref.max() > 0
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-5)
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v3 as iio

    v = tmp_path / "v.mp4"
    assert main(["video", str(ff["path"]), "--frames", "3", "--out", str(v)]) == 0
    assert "3 frames (spiral, color)" in capsys.readouterr().out
    frames = iio.imread(v)
    assert frames.shape[:3] == (3, 36, 48) and frames.std() > 5
    assert main(["video", str(ff["path"]), "--path", "orbit", "--out", str(v)]) == 1
    assert "cannot be orbited" in capsys.readouterr().err
