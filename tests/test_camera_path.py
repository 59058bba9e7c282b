"""nerfstudio camera-path JSON: parsing, conventions, dataparser transform, render/video CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from plenoctree.camera_path import load_camera_path, load_dataparser_transform, write_camera_path
from plenoctree.cli import main
from plenoctree.datasets.procedural import procedural_tree
from plenoctree.errors import ConfigError
from plenoctree.octree import save_tree
from plenoctree.render import render_image
from plenoctree.video import orbit_cameras


def _path_json(path, frames, w=4, h=2, **extra):
    path.write_text(json.dumps({"camera_type": "perspective", "render_width": w,
                                "render_height": h, "fps": 12, "seconds": 1,
                                "camera_path": frames, **extra}))
    return path


def test_golden_frame_conventions(tmp_path):
    """Row-major 4x4 camera_to_world, vertical fov in degrees, centred principal point."""
    m = np.eye(4)
    m[:3, 3] = [1, 2, 3]
    p = _path_json(tmp_path / "p.json", [{"camera_to_world": m.reshape(-1).tolist(), "fov": 90,
                                          "aspect": 2.0}])
    cp = load_camera_path(p)
    cams = cp.cameras
    assert len(cp) == 1 and cp.fps == 12.0
    assert (cams.width, cams.height) == (4, 2)
    assert cams.fx == pytest.approx(1.0) and cams.fy == pytest.approx(1.0)   # 0.5*2/tan(45°)
    assert (cams.cx, cams.cy) == (2.0, 1.0)
    np.testing.assert_allclose(cams.c2w[0], m)
    # the corner pixel's ray: ((0.5 - 2)/1, -(0.5 - 1)/1, -1) in camera space (OpenGL)
    o, d = cams.rays(0)
    want = np.array([-1.5, 0.5, -1.0])
    np.testing.assert_allclose(d[0, 0], want / np.linalg.norm(want), rtol=1e-6)
    np.testing.assert_allclose(o[0, 0], [1, 2, 3])
    # --width/--height keep the vertical fov: focal follows the height
    big = load_camera_path(p, width=40, height=20).cameras
    assert big.fy == pytest.approx(10.0) and big.cx == 20.0


def test_write_load_round_trip_renders_the_same(tmp_path):
    tree = procedural_tree(32)
    cams = orbit_cameras(np.zeros(3), 4.0, 3, 24, 16, math.radians(40), 30.0, "+z")
    write_camera_path(tmp_path / "orbit.json", cams, fps=24)
    back = load_camera_path(tmp_path / "orbit.json").cameras
    np.testing.assert_allclose(back.c2w, cams.c2w, atol=1e-6)
    assert back.fy == pytest.approx(cams.fy) and back.fx == pytest.approx(cams.fy)
    for i in range(3):
        a = render_image(tree, cams, i).rgb.numpy()
        b = render_image(tree, back, i).rgb.numpy()
        np.testing.assert_allclose(a, b, atol=1e-4)


def test_dataparser_transform_maps_nerfstudio_world_back(tmp_path):
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    t = np.concatenate([q, rng.normal(size=(3, 1))], 1)
    s = 0.37
    (tmp_path / "dp.json").write_text(json.dumps({"transform": t.tolist(), "scale": s}))
    orig = np.eye(4)
    orig[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]
    orig[:3, :3] *= np.sign(np.linalg.det(orig[:3, :3]))
    orig[:3, 3] = [0.5, -2.0, 3.0]
    ns = np.eye(4)
    ns[:3] = t @ orig                       # nerfstudio: poses = transform @ poses
    ns[:3, 3] *= s                          #             poses[:, :3, 3] *= scale
    p = _path_json(tmp_path / "p.json", [{"camera_to_world": ns.reshape(-1).tolist(), "fov": 50}])
    back = load_camera_path(p, dataparser_transforms=tmp_path / "dp.json").cameras
    np.testing.assert_allclose(back.c2w[0], orig, atol=1e-5)
    inv = load_dataparser_transform(tmp_path / "dp.json")
    # a point map: positions come back exactly, rotations up to the uniform scale 1/s
    np.testing.assert_allclose((inv @ ns)[:3, 3], orig[:3, 3], atol=1e-9)
    np.testing.assert_allclose((inv @ ns)[:3, :3] * s, orig[:3, :3], atol=1e-9)


@pytest.mark.parametrize("content,match", [
    ("not json", "not a JSON file"),
    ("[]", "no 'camera_path' list"),
    ('{"camera_path": [], "render_width": 4, "render_height": 2}', "empty"),
    ('{"camera_type": "fisheye", "camera_path": [{}]}', "only perspective"),
    ('{"camera_path": [{"fov": 50}], "render_width": 4, "render_height": 2}',
     r"camera_path\[0\] needs"),
    ('{"camera_path": [{"camera_to_world": [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1], "fov": 0}],'
     ' "render_width": 4, "render_height": 2}', "fov must be in"),
    ('{"camera_path": [{"camera_to_world": [1,1,0,0,0,1,0,0,0,0,1,0,0,0,0,1], "fov": 50}],'
     ' "render_width": 4, "render_height": 2}', "not orthogonal"),
    ('{"camera_path": [{"camera_to_world": [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1], "fov": 50}]}',
     "render_width"),
])
def test_bad_files_name_the_file_and_problem(tmp_path, content, match):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(ConfigError, match=match) as e:
        load_camera_path(p)
    assert str(p) in str(e.value)
    with pytest.raises(ConfigError, match="no such file"):
        load_camera_path(tmp_path / "missing.json")


@pytest.fixture()
def tree_and_path(tmp_path):
    save_tree(procedural_tree(32), tmp_path / "t.npz")
    cams = orbit_cameras(np.zeros(3), 4.0, 4, 16, 16, math.radians(40), 30.0, "+z")
    write_camera_path(tmp_path / "path.json", cams, fps=12)
    return tmp_path / "t.npz", tmp_path / "path.json", cams


def test_cli_render_camera_path(tree_and_path, tmp_path, capsys):
    tree, path, cams = tree_and_path
    out = tmp_path / "frames"
    assert main(["render", str(tree), "--camera-path", str(path), "--out", str(out),
                 "--views", "3"]) == 0
    assert "3 frames at 16x16" in capsys.readouterr().out
    for i in range(3):
        assert (out / f"frame_{i:05d}.png").exists()
        assert (out / f"frame_{i:05d}_depth.png").exists()
    d = np.load(out / "frame_00001_depth.npy")
    np.testing.assert_allclose(d, render_image(procedural_tree(32), cams, 1).depth.numpy(),
                               rtol=1e-5)
    assert not (out / "frame_00003.png").exists()
    assert main(["render", str(tree), "--camera-path", str(path), "--data", str(tmp_path)]) == 1
    assert "leave out --data" in capsys.readouterr().err
    assert main(["render", str(tree)]) == 1
    assert "--data is needed" in capsys.readouterr().err


def test_cli_video_camera_path(tree_and_path, tmp_path, capsys):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v3 as iio

    tree, path, _ = tree_and_path
    out = tmp_path / "v.mp4"
    assert main(["video", str(tree), "--camera-path", str(path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "4 frames (camera_path, color)" in text and "12 fps" in text
    frames = iio.imread(out)
    assert frames.shape[:3] == (4, 16, 16)
    assert main(["video", str(tree), "--camera-path", str(path), "--path", "orbit",
                 "--out", str(out)]) == 1
    assert "not both" in capsys.readouterr().err
