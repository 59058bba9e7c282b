"""COLMAP: model reader, pose convention, undistortion, the COLMAP dataset format, scene kinds."""

from __future__ import annotations

import numpy as np
import pytest

from plenoctree.datasets import detect_format, load_blender, load_dataset
from plenoctree.datasets.dataset import has_split
from plenoctree.datasets.colmap import (CAMERA_RADIUS, ColmapOptions, capture_kind, load_colmap,
                                       normalize_scene)
from plenoctree.datasets.colmap_model import colmap_c2w, read_colmap_model
from plenoctree.datasets.forward_facing import write_forward_facing_dataset
from plenoctree.datasets.llff import read_poses_bounds
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.errors import DatasetError

pycolmap = pytest.importorskip("pycolmap")


def _synthetic(model="OPENCV", params=(1280, 1250, 512, 384, 0.01, -0.02, 0.001, 0.002)):
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig, o.num_points3D = 1, 1, 6, 40
    o.camera_model_id = getattr(pycolmap.CameraModelId, model)
    o.camera_params = list(params)
    return pycolmap.synthesize_dataset(o)


@pytest.mark.parametrize("text", [False, True])
def test_reader_matches_a_model_written_by_pycolmap(tmp_path, text):
    rec = _synthetic()
    (rec.write_text if text else rec.write)(tmp_path)
    m = read_colmap_model(tmp_path)
    assert set(m.cameras) == set(rec.cameras)
    for cid, cam in rec.cameras.items():
        got = m.cameras[cid]
        assert (got.model, got.width, got.height) == (cam.model_name, cam.width, cam.height)
        np.testing.assert_allclose(got.params, cam.params, rtol=1e-12)
    assert set(m.images) == set(rec.images)
    for iid, im in rec.images.items():
        name, cid, q, t = m.images[iid]
        assert (name, cid) == (im.name, im.camera_id)
        ref = np.eye(4)
        ref[:3] = im.cam_from_world().matrix()
        c2w = colmap_c2w(q, t) @ np.diag([1.0, -1.0, -1.0, 1.0])   # back to OpenCV axes
        np.testing.assert_allclose(np.linalg.inv(c2w), ref, atol=1e-9)
    ids = sorted(rec.points3D)
    ref_xyz = np.array([rec.points3D[i].xyz for i in ids])
    np.testing.assert_allclose(m.points, ref_xyz, atol=1e-9)
    assert (m.point_tracks == [rec.points3D[i].track.length() for i in ids]).all()


def test_c2w_projects_points_like_colmap(tmp_path):
    rec = _synthetic("PINHOLE", (300.0, 310.0, 512.0, 384.0))
    rec.write(tmp_path)
    m = read_colmap_model(tmp_path)
    fx, fy, cx, cy = m.cameras[1].params
    pts = np.array([p.xyz for p in rec.points3D.values()])
    for iid, im in rec.images.items():
        w2c = np.linalg.inv(colmap_c2w(*m.images[iid][2:]))      # OpenGL: looks down -z, y up
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        uv = np.stack([cx + fx * pc[:, 0] / -pc[:, 2], cy - fy * pc[:, 1] / -pc[:, 2]], 1)
        ref = np.array([rec.cameras[1].img_from_cam(im.cam_from_world() * p) for p in pts])
        np.testing.assert_allclose(uv, ref, atol=1e-6)


def _pattern(x, y):
    """A smooth test image as a function of normalised pinhole coordinates."""
    return np.stack([0.5 + 0.4 * np.sin(6 * x), 0.5 + 0.4 * np.cos(5 * y),
                     0.5 + 0.3 * np.sin(4 * (x + y))], -1).astype(np.float32)


@pytest.mark.parametrize("model, params", [
    ("OPENCV", [60.0, 62.0, 40.5, 30.0, -0.15, 0.03, 0.002, -0.001]),
    ("OPENCV_FISHEYE", [55.0, 55.0, 40.0, 30.0, 0.05, -0.02, 0.01, 0.0]),
    ("SIMPLE_RADIAL", [58.0, 40.0, 30.0, 0.1]),
])
def test_undistortion_round_trip(model, params):
    """Distort a known pinhole image through COLMAP's lens model, undistort it, compare."""
    from types import SimpleNamespace

    from plenoctree.datasets.undistort import undistort_images

    w, h = 80, 60
    cam = pycolmap.Camera(model=model, width=w, height=h, params=params)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = cam.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))   # normalised, undistorted
    distorted = _pattern(xy[:, 0], xy[:, 1]).reshape(h, w, 3)
    cams = [SimpleNamespace(model=model, params=np.array(params), width=w, height=h)]
    out, k = undistort_images(distorted[None], cams)
    fx, fy, cx, cy = k[0]
    hh, ww = out.shape[1:3]
    uu, vv = np.meshgrid(np.arange(ww) + 0.5, np.arange(hh) + 0.5)
    ref = _pattern((uu - cx) / fx, (vv - cy) / fy)
    err = np.abs(out[0] - ref)[3:-3, 3:-3]          # borders: interpolation against the edge
    assert np.median(err) < 0.01 and err.mean() < 0.02, (np.median(err), err.mean())
    # without undistortion the same comparison fails: the distortion matters at this size
    if (hh, ww) == (h, w):
        naive = np.abs(distorted - _pattern((u - cx) / fx, (v - cy) / fy))[3:-3, 3:-3]
        assert naive.mean() > 3 * err.mean()


def _rot_to_quat(r):
    """(w, x, y, z) of a rotation matrix (Shepperd)."""
    t = np.trace(r)
    if t > 0:
        s = 2 * np.sqrt(1 + t)
        return np.array([s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s,
                         (r[1, 0] - r[0, 1]) / s])
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2 * np.sqrt(1 + r[i, i] - r[j, j] - r[k, k])
    q = np.zeros(4)
    q[0] = (r[k, j] - r[j, k]) / s
    q[1 + i] = s / 4
    q[1 + j] = (r[j, i] + r[i, j]) / s
    q[1 + k] = (r[k, i] + r[i, k]) / s
    return q


def _num(v):
    return repr(float(v))


def write_model(folder, c2w, k, w, h, names, points, model="PINHOLE"):
    """Write cameras/images/points3D.txt for OpenGL cameras ``c2w`` (one shared camera)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text(f"1 {model} {w} {h} {' '.join(map(_num, k))}\n")
    lines = ["# comment"]
    for i, (m, name) in enumerate(zip(c2w, names)):
        cv = m @ np.diag([1.0, -1.0, -1.0, 1.0])
        w2c = np.linalg.inv(cv)
        q, t = _rot_to_quat(w2c[:3, :3]), w2c[:3, 3]
        lines.append(f"{i + 1} {' '.join(map(_num, q))} {' '.join(map(_num, t))} 1 {name}")
        lines.append("")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text("".join(
        f"{j + 1} {float(p[0])!r} {float(p[1])!r} {float(p[2])!r} 128 128 128 0.5 1 0 2 0\n"
        for j, p in enumerate(points)))


def test_quaternion_helper_round_trips():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        r = colmap_c2w(q, np.zeros(3))[:3, :3] @ np.diag([1.0, -1.0, -1.0])
        q2 = _rot_to_quat(r.T)
        assert np.allclose(q2, q) or np.allclose(q2, -q)


@pytest.fixture(scope="module")
def blender_scene(tmp_path_factory):
    root = write_procedural_dataset(tmp_path_factory.mktemp("bl"), 12, 0, 0, width=24,
                                    height=20, n_samples=32)
    return root, load_blender(root, "train")


def test_colmap_dataset_is_the_blender_scene_up_to_a_similarity(blender_scene, tmp_path):
    from PIL import Image

    src, data = blender_scene
    c = data.cameras
    root = tmp_path / "col"
    (root / "images").mkdir(parents=True)
    names = []
    for i, img in enumerate(data.images):
        names.append(f"im_{i:02d}.png")
        Image.fromarray(np.round(img * 255).astype(np.uint8)).save(root / "images" / names[-1])
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.8, 0.8, (200, 3))                 # "sparse points" on the content
    write_model(root / "sparse" / "0", c.c2w.astype(np.float64), [c.fx, c.fy, c.cx, c.cy],
                c.width, c.height, names, pts)
    assert detect_format(root) == "colmap"
    got = load_dataset(root, "all")
    assert len(got) == 12 and got.cameras.ndc is False
    np.testing.assert_allclose(got.images, np.round(data.images * 255) / 255, atol=1e-6)
    frame = normalize_scene(c.c2w.astype(np.float64), pts)
    assert frame.kind == "360"
    # same rays up to the similarity: directions rotate, origins map through the transform
    o0, d0 = c.all_rays()
    o1, d1 = got.cameras.all_rays()
    t = frame.transform
    np.testing.assert_allclose(o0 @ t[:3, :3].T + t[:3, 3], o1, atol=1e-4)
    np.testing.assert_allclose(d0 @ (t[:3, :3] / frame.scale).T, d1, atol=1e-5)
    # the box holds the points but outliers (0.5-99.5 % percentiles, padded), inside the
    # camera sphere
    p1 = pts @ t[:3, :3].T + t[:3, 3]
    inside = np.all((p1 >= got.scene_bbox[0]) & (p1 <= got.scene_bbox[1]), axis=1)
    assert inside.mean() > 0.98
    assert got.scene_bbox[1, 0] < CAMERA_RADIUS
    # splits: every 8th image is a test image
    assert load_colmap(root, "test").names == ["im_00", "im_08"]
    assert len(load_colmap(root, "train")) == 10
    # ... and of val too, so val is not a split of its own (the fine-tuner validates elsewhere)
    assert load_colmap(root, "val").names == ["im_00", "im_08"]
    assert [has_split(root, s) for s in ("train", "val", "test")] == [True, False, True]


def test_forward_facing_model_gets_ndc(tmp_path):
    from PIL import Image

    ff = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=16, height=12,
                                      n_samples=16)
    c2w, bounds, hwf = read_poses_bounds(ff / "poses_bounds.npy")
    assert capture_kind(c2w) == "forward"
    root = tmp_path / "col"
    (root / "images").mkdir(parents=True)
    names = sorted(p.name for p in (ff / "images").iterdir())
    for n in names:
        Image.open(ff / "images" / n).save(root / "images" / n)
    # points spread between the depth bounds in front of the middle camera
    rng = np.random.default_rng(2)
    mid = c2w[len(c2w) // 2]
    z = rng.uniform(bounds.min(), bounds.max(), 300)
    xy = rng.uniform(-0.3, 0.3, (300, 2)) * z[:, None]
    pts = mid[:3, 3] + (xy[:, :1] * mid[:3, 0] + xy[:, 1:] * mid[:3, 1]) - z[:, None] * mid[:3, 2]
    f = float(hwf[0, 2])
    write_model(root / "sparse", c2w, [f, f, 8.0, 6.0], 16, 12, names, pts)
    got = load_colmap(root, "all")
    assert got.cameras.ndc and got.near == 0.0
    assert got.scene_bbox[0, 2] == pytest.approx(-1.0) and got.scene_bbox[1, 2] == pytest.approx(1.0)
    as360 = load_colmap(root, "all", options=ColmapOptions(scene="360"))
    assert as360.cameras.ndc is False
    # loaded as 360°, the rays start before the content (0.9 of the nearest point depth, in
    # the normalised units), not at the cameras
    from plenoctree.datasets.colmap import normalize_scene

    scale = normalize_scene(c2w, pts, "360").scale
    depth = ((pts[None] - c2w[:, None, :3, 3]) * -c2w[:, None, :3, 2]).sum(-1)
    lo = min(np.percentile(d[d > 0], 0.1) for d in depth)
    assert as360.near == pytest.approx(0.9 * lo * scale, rel=1e-4) and as360.near > 0


def test_distorted_model_is_undistorted_on_load(blender_scene, tmp_path):
    from PIL import Image

    _, data = blender_scene
    c = data.cameras
    root = tmp_path / "col"
    (root / "images").mkdir(parents=True)
    names = [f"im_{i:02d}.png" for i in range(len(data))]
    for n, img in zip(names, data.images):
        Image.fromarray(np.round(img * 255).astype(np.uint8)).save(root / "images" / n)
    params = [c.fx, c.fy, c.cx, c.cy, -0.1, 0.0, 0.0, 0.0]
    write_model(root / "sparse" / "0", c.c2w.astype(np.float64), params, c.width, c.height,
                names, np.random.default_rng(0).uniform(-0.8, 0.8, (100, 3)), model="OPENCV")
    got = load_colmap(root, "all")
    ref = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), pycolmap.Camera(
        model="OPENCV", width=c.width, height=c.height, params=params))
    assert (got.cameras.width, got.cameras.height) == (ref.width, ref.height)
    np.testing.assert_allclose(got.cameras.intrinsics(0), ref.params[:4], rtol=1e-9)


def test_bad_models_name_the_file(tmp_path):
    d = tmp_path / "sparse" / "0"
    d.mkdir(parents=True)
    (d / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5\n")
    (d / "images.txt").write_text("")
    with pytest.raises(DatasetError, match="cameras.txt: camera model PINHOLE needs 4"):
        read_colmap_model(d)
    (d / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5 5\n")
    with pytest.raises(DatasetError, match="images.txt: the model has no registered images"):
        read_colmap_model(d)
    (d / "images.txt").write_text("1 1 0 0 0 0 0 0 2 a.png\n\n")
    with pytest.raises(DatasetError, match="refers to camera 2"):
        read_colmap_model(d)
    (d / "cameras.txt").unlink()
    (d / "cameras.bin").write_bytes(b"\x01\x00\x00\x00\x00\x00\x00\x00\x01\x00")
    with pytest.raises(DatasetError, match="cameras.bin: truncated"):
        read_colmap_model(d)


def test_weakly_supported_images_are_dropped():
    from plenoctree.process.sfm import drop_weak_images

    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig, o.num_points3D = 1, 1, 8, 60
    rec = pycolmap.synthesize_dataset(o)
    assert drop_weak_images(rec, 0.35) == []             # equal support: none dropped
    victim = sorted(rec.images)[3]
    im = rec.images[victim]
    obs = [i for i, p in enumerate(im.points2D) if p.has_point3D()]
    for i in obs[: int(0.8 * len(obs))]:                 # keep 20 % of its observations
        rec.delete_observation(victim, i)
    assert drop_weak_images(rec, 0.35) == [rec.images[victim].name]
    assert not rec.images[victim].has_pose and rec.num_reg_images() == 7


def _ring_cameras(n: int = 16, radius: float = 3.0) -> np.ndarray:
    """OpenGL c2w ``[n, 4, 4]`` on a horizontal ring, each looking at the origin (z up)."""
    out = np.zeros((n, 4, 4))
    for k in range(n):
        a = 2 * np.pi * k / n
        c = radius * np.array([np.cos(a), np.sin(a), 0.3])
        back = c / np.linalg.norm(c)                       # OpenGL: the camera looks along -z
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        out[k, :3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        out[k, :3, 3], out[k, 3, 3] = c, 1.0
    return out


def test_box_of_an_object_and_of_a_room_around_the_cameras():
    """An object in the middle keeps the box of its points (well inside the cameras); points
    all around and beyond the cameras (a room, as real/fox) give a box holding every camera
    with a 10 % margin (before: the cube was cut at the camera distance and a third of fox's
    cameras sat outside it)."""
    c2w = _ring_cameras()
    rng = np.random.default_rng(0)
    obj = rng.uniform(-0.6, 0.6, (500, 3))
    frame = normalize_scene(c2w, obj)
    assert frame.kind == "360" and frame.bbox[1, 0] < 0.6 * CAMERA_RADIUS
    d = rng.normal(size=(3000, 3))
    room = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(1.0, 6.0, (3000, 1))
    frame = normalize_scene(c2w, room)
    cams = frame.c2w[:, :3, 3]
    half = frame.bbox[1, 0]
    np.testing.assert_allclose(half, 1.1 * np.abs(cams).max(), rtol=1e-9)
    assert half > CAMERA_RADIUS and np.all(np.abs(cams) < half)
