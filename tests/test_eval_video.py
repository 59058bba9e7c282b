"""`plenoctree eval` and `plenoctree video` on the tiny procedural scene (16 px, 32^3 tree)."""

from __future__ import annotations

import json
import logging
import math
import shutil

import numpy as np
import pytest

import plenoctree.evaluation as evaluation
import plenoctree.metrics as metrics
import plenoctree.video as video
from plenoctree._util import save_png
from plenoctree.cli import main
from plenoctree.compression import compress, save_compressed
from plenoctree.datasets import load_dataset
from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
from plenoctree.errors import BackendError, ConfigError, TreeFormatError
from plenoctree.evaluation import EvalConfig, eval_tree_file
from plenoctree.octree import load_tree, save_tree
from plenoctree.render import RenderOptions, render_image
from plenoctree.video import (VideoConfig, depth_bounds, detect_up_axis, make_video,
                              orbit_poses, video_cameras, write_video)

iio = pytest.importorskip("imageio.v2")
pytest.importorskip("imageio_ffmpeg")

W = 16


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Procedural data, its 32^3 tree, a perturbed copy, a compressed copy, and a copy of the
    data whose test images are the tree's own renders (PNG-quantised)."""
    root = tmp_path_factory.mktemp("scene")
    write_procedural_dataset(root / "data", n_train=2, n_val=1, n_test=3, width=W, height=W)
    tree = procedural_tree(32)
    save_tree(tree, root / "tree.npz", precision="fp32")
    bad = tree.copy()
    rng = np.random.default_rng(0)
    bad.data[..., :-1] += rng.normal(0.0, 1.0, bad.data[..., :-1].shape).astype(np.float32)
    save_tree(bad, root / "perturbed.npz", precision="fp32")
    save_compressed(compress(tree), root / "tree.plnz")
    shutil.copytree(root / "data", root / "self")
    test = load_dataset(root / "self", "test")
    for i, name in enumerate(test.names):
        rgb = render_image(tree, test.cameras, i, RenderOptions()).rgb.numpy()
        save_png(root / "self" / "test" / f"{name}.png", rgb)
    return root


def _no_lpips(monkeypatch):
    monkeypatch.setattr(metrics, "_lpips_problem", lambda net: "no weights in this test")


# --- eval -----------------------------------------------------------------------------------
def test_eval_json_fields_and_self_psnr(scene, tmp_path, monkeypatch, caplog):
    _no_lpips(monkeypatch)
    monkeypatch.setattr(logging.getLogger("plenoctree"), "propagate", True)  # CLI or not
    caplog.set_level("INFO", logger="plenoctree")
    rep = eval_tree_file(EvalConfig(scene / "tree.npz", scene / "self", out=tmp_path / "e",
                                    json_path=tmp_path / "copy.json"))
    tree = load_tree(scene / "tree.npz")
    t = rep["tree"]
    assert t["n_leaves"] == tree.n_leaves and t["n_nodes"] == tree.n_nodes
    assert t["file_bytes"] == (scene / "tree.npz").stat().st_size
    assert t["file_mb"] == pytest.approx(t["file_bytes"] / 1e6)
    assert t["memory_mb"] == pytest.approx(tree.nbytes / 1e6)
    assert 0 < t["n_occupied_leaves"] < t["n_leaves"] and t["kind"] == "npz"
    assert rep["dataset"] == {"root": str(scene / "self"), "format": "blender", "split": "test",
                              "n_views": 3, "width": W, "height": W, "downscale": 1}
    m = rep["mean"]
    # ground truth = the tree's own renders, up to 8-bit quantisation (~59 dB)
    assert m["psnr"] > 50.0 and all(v["psnr"] > 50.0 for v in rep["views"])
    assert m["ssim"] > 0.999
    assert m["fps"] > 0 and m["ms_per_frame"] == pytest.approx(1000.0 / m["fps"])
    assert m["lpips"] == "skipped: no weights in this test"
    assert rep["lpips"]["status"] == m["lpips"]
    assert all("lpips" not in v for v in rep["views"])
    on_disk = json.loads((tmp_path / "e" / "eval.json").read_text())
    assert on_disk == rep == json.loads((tmp_path / "copy.json").read_text())
    md = (tmp_path / "e" / "eval.md").read_text()
    assert "| PSNR (dB) |" in md and "r_0" in md and "skipped" in md
    assert "LPIPS skipped: no weights in this test" in caplog.messages


def test_eval_perturbed_tree_scores_lower(scene, tmp_path, monkeypatch):
    _no_lpips(monkeypatch)
    good = eval_tree_file(EvalConfig(scene / "tree.npz", scene / "self", out=tmp_path / "a"))
    bad = eval_tree_file(EvalConfig(scene / "perturbed.npz", scene / "self", out=tmp_path / "b"))
    assert bad["mean"]["psnr"] < good["mean"]["psnr"] - 15.0
    assert bad["mean"]["psnr"] < 40.0
    assert bad["mean"]["ssim"] < good["mean"]["ssim"]


def test_eval_lpips_when_available(scene, tmp_path, monkeypatch):
    # The LPIPS plumbing, with a stand-in scorer (the real one needs weights on disk).
    monkeypatch.setattr(metrics, "_lpips_problem", lambda net: None)
    calls = []

    def fake(pred, gt, net):
        calls.append(net)
        return float(np.abs(pred - gt).mean())

    monkeypatch.setattr(evaluation, "lpips_score", fake)
    rep = eval_tree_file(EvalConfig(scene / "perturbed.npz", scene / "self", out=tmp_path / "e",
                                    lpips_net="alex", limit=2))
    assert calls == ["alex", "alex"]
    lp = [v["lpips"] for v in rep["views"]]
    assert all(x > 0 for x in lp) and rep["mean"]["lpips"] == pytest.approx(np.mean(lp))
    assert rep["lpips"] == {"net": "alex", "status": "computed"}
    assert "LPIPS" in (tmp_path / "e" / "eval.md").read_text()


def test_eval_compressed_tree(scene, tmp_path, monkeypatch):
    _no_lpips(monkeypatch)
    raw = eval_tree_file(EvalConfig(scene / "tree.npz", scene / "data", out=tmp_path / "a"))
    rep = eval_tree_file(EvalConfig(scene / "tree.plnz", scene / "data", out=tmp_path / "b",
                                    format="blender"))
    assert rep["tree"]["kind"] == "compressed"
    assert rep["tree"]["file_mb"] < raw["tree"]["file_mb"]
    assert rep["tree"]["n_leaves"] == raw["tree"]["n_leaves"]
    assert abs(rep["mean"]["psnr"] - raw["mean"]["psnr"]) < 1.0
    assert raw["mean"]["psnr"] > 18.0     # the tree vs the analytic renders (empty: ~10 dB)


def test_eval_cli(scene, tmp_path, capsys):
    out = tmp_path / "e"
    rc = main(["eval", str(scene / "tree.npz"), "--data", str(scene / "data"), "--out", str(out),
               "--views", "2", "--format", "blender", "--backend", "torch", "--save-images",
               "--background", "black", "--stop-thresh", "0"])
    assert rc == 0
    rep = json.loads((out / "eval.json").read_text())
    assert rep["dataset"]["n_views"] == 2 and rep["render"] == {
        "backend": "torch", "stop_thresh": 0.0, "renormalize": False,
        "background": [0.0, 0.0, 0.0]}
    assert (out / "renders" / "r_0.png").exists() and (out / "renders" / "r_0_depth.png").exists()
    text = capsys.readouterr().out
    assert "| PSNR (dB) |" in text
    if metrics.lpips_available():     # not on this machine: no lpips package / weights
        assert isinstance(rep["mean"]["lpips"], float)
    else:
        assert rep["mean"]["lpips"].startswith("skipped: ") and "LPIPS skipped" in text


def test_eval_spread_views(scene, tmp_path, monkeypatch):
    """--views N --spread scores N views evenly spaced over the split (as render-nerf picks
    them), the same as scoring the whole split and keeping those; plain --views the first N."""
    from plenoctree.datasets import evenly_spaced, load_dataset

    _no_lpips(monkeypatch)
    data = tmp_path / "data"
    write_procedural_dataset(data, n_train=1, n_val=1, n_test=5, width=W, height=W)
    names = load_dataset(data, "test").names
    want = [names[i] for i in evenly_spaced(len(names), 2)]          # views 0 and 2
    assert main(["eval", str(scene / "tree.npz"), "--data", str(data), "--views", "2",
                 "--spread", "--out", str(tmp_path / "s")]) == 0
    spread = json.loads((tmp_path / "s" / "eval.json").read_text())
    full = eval_tree_file(EvalConfig(scene / "tree.npz", data, out=tmp_path / "a"))
    first = eval_tree_file(EvalConfig(scene / "tree.npz", data, limit=2, out=tmp_path / "f"))
    assert [v["name"] for v in spread["views"]] == want != [v["name"] for v in first["views"]]
    by_name = {v["name"]: v["psnr"] for v in full["views"]}
    assert [v["psnr"] for v in spread["views"]] == pytest.approx([by_name[n] for n in want])


def test_eval_bad_inputs(scene, tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nope.npz"), "--data", str(scene / "data")]) == 1
    assert "nope.npz" in capsys.readouterr().err
    assert main(["eval", str(scene / "tree.npz"), "--data", str(scene / "data"),
                 "--format", "llff", "--out", str(tmp_path / "e")]) == 1
    assert "poses_bounds.npy" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["eval", str(scene / "tree.npz"), "--data", str(scene / "data"), "--format", "x"])
    with pytest.raises(ConfigError, match="--limit"):
        eval_tree_file(EvalConfig(scene / "tree.npz", scene / "data", limit=0))
    with pytest.raises(TreeFormatError, match="data"):
        eval_tree_file(EvalConfig(scene / "data" / "transforms_test.json", scene / "data"))


def test_render_format_option(scene, tmp_path, capsys):
    args = ["render", str(scene / "tree.npz"), "--data", str(scene / "data"), "--views", "1"]
    assert main([*args, "--format", "blender", "--out", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / "metrics.json").exists()
    assert main([*args, "--format", "nsvf", "--out", str(tmp_path / "s")]) == 1
    assert "data" in capsys.readouterr().err


# --- camera paths ---------------------------------------------------------------------------
def _pose_spherical(theta, phi, radius):
    """The original gen_video.py / NeRF camera (z up): degrees, world units."""
    t = np.eye(4)
    t[2, 3] = radius
    p, q = math.radians(phi), math.radians(theta)
    rp = np.array([[1, 0, 0, 0], [0, math.cos(p), -math.sin(p), 0],
                   [0, math.sin(p), math.cos(p), 0], [0, 0, 0, 1]])
    rt = np.array([[math.cos(q), 0, -math.sin(q), 0], [0, 1, 0, 0],
                   [math.sin(q), 0, math.cos(q), 0], [0, 0, 0, 1]])
    swap = np.array([[-1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
    return swap @ rt @ rp @ t


def test_orbit_matches_original_gen_video():
    ref = np.stack([_pose_spherical(a, -30.0, 4.0) for a in np.linspace(-180, 180, 9)[:-1]])
    np.testing.assert_allclose(orbit_poses(np.zeros(3), 4.0, 8, 30.0, "+z"), ref, atol=1e-6)


@pytest.mark.parametrize("up, first", [
    ("+z", [0.0, -math.cos(math.radians(30)), 0.5]),
    ("+y", [-math.cos(math.radians(30)), 0.5, 0.0]),
    ("-z", [0.0, 0.0, 0.0]),   # checked by geometry only
])
def test_orbit_cameras_look_at_the_centre(up, first):
    c = np.array([0.1, -0.2, 0.3])
    poses = orbit_poses(c, 2.5, 12, 30.0, up).astype(np.float64)
    if up != "-z":
        np.testing.assert_allclose(poses[0, :3, 3], c + 2.5 * np.array(first), atol=1e-6)
    u = video.axis_vector(up)
    eye = poses[:, :3, 3]
    to_c = (c - eye) / np.linalg.norm(c - eye, axis=1, keepdims=True)
    np.testing.assert_allclose(-poses[:, :3, 2], to_c, atol=1e-6)        # -z looks at the centre
    np.testing.assert_allclose(np.linalg.norm(eye - c, axis=1), 2.5, atol=1e-5)
    np.testing.assert_allclose((eye - c) @ u, 2.5 * 0.5, atol=1e-5)       # 30° above
    assert (poses[:, :3, 1] @ u > 0).all()                                # camera up ~ u
    rot = poses[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3),
                               rot.shape), atol=1e-6)
    assert np.linalg.det(rot) == pytest.approx(np.ones(12), abs=1e-5)


def test_orbit_defaults_from_dataset_and_tree(scene):
    tree = load_tree(scene / "tree.npz")
    cams, info = video_cameras(VideoConfig(scene / "tree.npz", data=scene / "data", frames=4),
                               tree)
    assert info == {"path": "orbit", "up": "+z", "radius": pytest.approx(4.0)}
    assert (cams.width, cams.height, len(cams)) == (W, W, 4)
    data = load_dataset(scene / "data", "test")
    assert cams.fx == pytest.approx(data.cameras.fx)
    cams, info = video_cameras(VideoConfig(scene / "tree.npz", frames=3), tree)
    fov = 0.6911112070083618
    assert info["up"] == "+z" and cams.width == 800
    assert cams.fx == pytest.approx(400 / math.tan(0.5 * fov))
    # the box's bounding sphere (radius sqrt(3)) just fits the field of view
    assert info["radius"] == pytest.approx(math.sqrt(3) / math.sin(0.5 * fov))
    assert video.fit_radius(np.ones(3), fov, 800, 400) > info["radius"]   # narrower fov_y
    d = np.linalg.norm(cams.centers - tree.center, axis=1)
    np.testing.assert_allclose(d, info["radius"], rtol=1e-5)
    flipped = data.cameras.c2w.copy()
    flipped[:, :3, 1] = flipped[:, :3, 1][:, [0, 2, 1]]
    assert detect_up_axis(flipped) == "+y" and detect_up_axis(np.zeros((0, 4, 4))) == "+z"


def test_dataset_path_and_depth_bounds(scene):
    tree = load_tree(scene / "tree.npz")
    data = load_dataset(scene / "data", "test")
    cams, info = video_cameras(VideoConfig(scene / "tree.npz", data=scene / "data",
                                           path="dataset"), tree)
    assert info["path"] == "dataset"
    np.testing.assert_array_equal(cams.c2w, data.cameras.c2w)
    cams, _ = video_cameras(VideoConfig(scene / "tree.npz", data=scene / "data", path="dataset",
                                        frames=2, width=8, height=6), tree)
    np.testing.assert_array_equal(cams.c2w, data.cameras.c2w[[0, 2]])
    assert (cams.width, cams.height) == (8, 6) and cams.fx == pytest.approx(data.cameras.fx / 2)
    near, far = depth_bounds(tree, data.cameras)       # cameras at distance 4, box ±1
    assert 4.0 - math.sqrt(3) <= near < 3.0 and 5.0 < far <= 4.0 + math.sqrt(3)


def test_path_errors(scene, tmp_path):
    tree = load_tree(scene / "tree.npz")
    for cfg, msg in [
        (VideoConfig(scene / "tree.npz", path="dataset"), "needs --data"),
        (VideoConfig(scene / "tree.npz", data=scene / "data", path="spiral"), "LLFF"),
        (VideoConfig(scene / "tree.npz", data=scene / "data", path="dataset", frames=9),
         "only 3 cameras"),
        (VideoConfig(scene / "tree.npz", frames=0), "--frames"),
        (VideoConfig(scene / "tree.npz", width=8), "--width and --height"),
        (VideoConfig(scene / "tree.npz", elevation=90.0, frames=2, width=4, height=4),
         "--elevation"),
        (VideoConfig(scene / "tree.npz", radius=-1.0, frames=2, width=4, height=4), "--radius"),
    ]:
        with pytest.raises(ConfigError, match=msg):
            video_cameras(cfg, tree)


# --- video files ----------------------------------------------------------------------------
def _read(path):
    with iio.get_reader(str(path)) as r:
        return np.stack([np.asarray(f) for f in r])


def test_video_orbit_colour_depth_both(scene, tmp_path):
    base = dict(tree=scene / "tree.npz", frames=5, width=W, height=W, fps=10)
    res = {m: make_video(VideoConfig(**base, out=tmp_path / f"{m}.mp4", mode=m))
           for m in ("color", "depth", "both")}
    frames = {m: _read(tmp_path / f"{m}.mp4") for m in res}
    assert frames["color"].shape == (5, W, W, 3) and frames["depth"].shape == (5, W, W, 3)
    assert frames["both"].shape == (5, W, 2 * W, 3)
    assert res["both"].width == 2 * W and res["color"].n_frames == 5
    assert res["color"].render_fps > 0 and res["color"].path == "orbit"
    c, d = frames["color"].astype(float), frames["depth"].astype(float)
    assert np.abs(c - d).mean() > 20.0              # white background vs black empty depth
    # side by side: left half ~ colour, right half ~ depth (lossy codec)
    assert np.abs(frames["both"][:, :, :W].astype(float) - c).mean() < 12.0
    assert np.abs(frames["both"][:, :, W:].astype(float) - d).mean() < 12.0
    # the colour video matches the renders (H.264 at 16 px: loose)
    cams, _ = video_cameras(VideoConfig(**base), load_tree(scene / "tree.npz"))
    ref = render_image(load_tree(scene / "tree.npz"), cams, 2).rgb.numpy() * 255
    assert np.abs(c[2] - ref).mean() < 12.0
    assert not list(tmp_path.glob(".*tmp*"))


def test_video_cli_odd_size_is_padded(scene, tmp_path, capsys):
    out = tmp_path / "odd.mp4"
    rc = main(["video", str(scene / "tree.npz"), "--frames", "3", "--width", "15", "--height",
               "11", "--out", str(out), "--elevation", "20", "--up", "+z"])
    assert rc == 0
    assert _read(out).shape == (3, 12, 16, 3)
    text = capsys.readouterr().out
    assert "padded to even size 16x12" in text and "frames/s" in text


def test_video_dataset_path_cli(scene, tmp_path):
    out = tmp_path / "ds.mp4"
    assert main(["video", str(scene / "tree.npz"), "--data", str(scene / "data"), "--path",
                 "dataset", "--out", str(out), "--mode", "depth"]) == 0
    assert _read(out).shape == (3, W, W, 3)


def test_video_spiral_on_llff(tmp_path):
    from plenoctree.datasets import llff_render_cameras
    from plenoctree.datasets.forward_facing import forward_facing_tree, write_forward_facing_dataset

    root = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=12, height=8,
                                        n_samples=16)
    save_tree(forward_facing_tree(root, 16), tmp_path / "ff.npz")
    cfg = VideoConfig(tmp_path / "ff.npz", data=root, frames=4, out=tmp_path / "s.mp4")
    cams, info = video_cameras(cfg, load_tree(tmp_path / "ff.npz"))
    assert info["path"] == "spiral" and cams.ndc
    np.testing.assert_array_equal(cams.c2w, llff_render_cameras(root, 4).c2w)
    res = make_video(cfg)
    assert _read(res.out).shape == (4, 8, 12, 3)
    with pytest.raises(ConfigError, match="NDC"):
        video_cameras(VideoConfig(tmp_path / "ff.npz", data=root, path="orbit"),
                      load_tree(tmp_path / "ff.npz"))


def test_video_bad_inputs(scene, tmp_path, capsys, monkeypatch):
    assert main(["video", str(tmp_path / "nope.npz"), "--out", str(tmp_path / "v.mp4")]) == 1
    assert "nope.npz" in capsys.readouterr().err
    assert main(["video", str(scene / "tree.npz"), "--frames", "0",
                 "--out", str(tmp_path / "v.mp4")]) == 1
    assert "--frames" in capsys.readouterr().err
    assert main(["video", str(scene / "tree.npz"), "--frames", "2", "--width", "4", "--height",
                 "4", "--out", str(tmp_path / "v.gif")]) == 1
    assert "v.gif" in capsys.readouterr().err
    assert main(["video", str(scene / "tree.npz"), "--frames", "2", "--width", "4", "--height",
                 "4", "--backend", "magic", "--out", str(tmp_path / "v.mp4")]) == 1
    assert "backend" in capsys.readouterr().err
    assert not (tmp_path / "v.mp4").exists() and not list(tmp_path.glob(".*tmp*"))
    with pytest.raises(ConfigError, match="no frames"):
        write_video(tmp_path / "e.mp4", [])
    with pytest.raises(ConfigError, match="--fps"):
        write_video(tmp_path / "e.mp4", [np.zeros((4, 4, 3))], fps=0)

    def broken():
        yield np.zeros((4, 4, 3))
        yield np.zeros((4, 4, 3))
        raise RuntimeError("render failed")

    with pytest.raises(RuntimeError, match="render failed"):
        write_video(tmp_path / "e.mp4", broken())
    with pytest.raises(ConfigError, match="frame 1 is 6x4"):
        write_video(tmp_path / "e.mp4", [np.zeros((4, 4, 3)), np.zeros((4, 6, 3))])
    assert not list(tmp_path.glob("*e.*"))          # no partial file, no temp file left
    real = video.importlib.util.find_spec
    monkeypatch.setattr(video.importlib.util, "find_spec",
                        lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    with pytest.raises(BackendError, match=r"plenoctree\[video\]"):
        write_video(tmp_path / "e.mp4", [np.zeros((4, 4, 3))])


def test_eval_and_video_default_to_the_datasets_background(scene, tmp_path):
    from plenoctree.datasets.forward_facing import forward_facing_tree, write_forward_facing_dataset

    root = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=12, height=8,
                                        n_samples=16)
    save_tree(forward_facing_tree(root, 16), tmp_path / "ff.npz")
    common = dict(backend="torch", limit=1, save_images=False, show_progress=False)
    photos = eval_tree_file(EvalConfig(tmp_path / "ff.npz", data=str(root),
                                       out=str(tmp_path / "e_ff"), **common))
    assert photos["render"]["background"] == [0.0, 0.0, 0.0]          # an LLFF folder: black
    renders = eval_tree_file(EvalConfig(scene / "tree.npz", data=str(scene / "data"),
                                        out=str(tmp_path / "e_bl"), **common))
    assert renders["render"]["background"] == [1.0, 1.0, 1.0]         # Blender: white
    # the video's empty pixels: black on the LLFF folder unless asked otherwise
    empty = tmp_path / "empty.npz"
    tree = load_tree(tmp_path / "ff.npz")
    tree.data[..., -1] = 0.0                                          # σ = 0 everywhere
    save_tree(tree, empty)
    dark = make_video(VideoConfig(empty, data=root, frames=2, out=tmp_path / "d.mp4"))
    light = make_video(VideoConfig(empty, data=root, frames=2, out=tmp_path / "l.mp4",
                                   background=(1.0, 1.0, 1.0)))
    assert _read(dark.out).mean() < 20 and _read(light.out).mean() > 235
