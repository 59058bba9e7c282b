"""Issue 37's attack, one test per defect: every output checked before the work and locked while
written, every input bounded, config files typed; each refused with one line naming the file or
flag, never a traceback, a hang or a lost file."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from plenoctree.cli import main
from plenoctree.errors import ConfigError, DatasetError

LONG = "a" * 300


def _fails(capsys, argv, *needles):
    """``main(argv)`` exits 1 with one error line (no traceback) holding every needle."""
    assert main([str(a) for a in argv]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    line = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(line) == 1, err
    for n in needles:
        assert str(n) in line[0], line[0]
    return line[0]


# --- 1. sizes -----------------------------------------------------------------------------------
def test_huge_render_size_is_refused_before_allocating(tiny_scene, tmp_path, capsys):
    _fails(capsys, ["render", tiny_scene / "tree.npz", "--data", tiny_scene / "data", "--views",
                    "1", "--width", "100000", "--height", "100000", "--out", tmp_path / "r"],
           "--width/--height 100000x100000", "MP")
    assert not (tmp_path / "r").exists()
    cp = tmp_path / "path.json"
    cp.write_text(json.dumps({"camera_type": "perspective", "render_width": 100000,
                              "render_height": 100000, "camera_path": [
                                  {"camera_to_world": np.eye(4).ravel().tolist(), "fov": 50}]}))
    _fails(capsys, ["render", tiny_scene / "tree.npz", "--camera-path", cp, "--out",
                    tmp_path / "r"], str(cp), "render size 100000x100000")


# --- 2. concurrent writers ----------------------------------------------------------------------
_HOLDER = """
import sys, time
from plenoctree._util import run_lock
with run_lock(sys.argv[1], "holder", folder=sys.argv[2] == "dir"):
    print("held", flush=True)
    time.sleep(60)
"""


@pytest.fixture
def holder():
    procs = []

    def hold(path, kind):
        p = subprocess.Popen([sys.executable, "-c", _HOLDER, str(path), kind],
                             stdout=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "held"
        procs.append(p)

    yield hold
    for p in procs:
        p.kill()
        p.wait()


@pytest.mark.parametrize("cmd", ["compress", "lod", "export", "decompress"])
def test_a_second_writer_of_one_output_is_refused(tiny_scene, tmp_path, capsys, holder, cmd):
    tree = tiny_scene / "tree.npz"
    if cmd == "decompress":
        assert main(["compress", str(tree), "--out", str(tmp_path / "t.plnz"), "--no-eval"]) == 0
        tree = tmp_path / "t.plnz"
    out = tmp_path / ("c.plnz" if cmd in ("compress", "lod") else "c.npz")
    holder(out, "file")
    extra = ["--no-eval"] if cmd == "compress" else []
    _fails(capsys, [cmd, tree, "--out", out, *extra], str(out), "in use by another plenoctree")
    assert not out.exists()


def test_export_web_into_a_folder_being_written_is_refused(tiny_scene, tmp_path, capsys, holder):
    out = tmp_path / "web"
    holder(out, "dir")
    _fails(capsys, ["export-web", tiny_scene / "tree.npz", "--out", out], "in use by another")
    assert sorted(p.name for p in out.iterdir()) == [".plenoctree.lock"]


# --- 3. --json never overwrites an unrelated file -----------------------------------------------
def test_json_refuses_an_unrelated_file_and_replaces_its_own(tiny_scene, tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("do not overwrite")
    _fails(capsys, ["info", tiny_scene / "tree.npz", "--json", notes], str(notes), "--overwrite")
    assert notes.read_text() == "do not overwrite"
    rep = tmp_path / "rep.json"
    for _ in range(2):                                   # its own report: replaced
        assert main(["info", str(tiny_scene / "tree.npz"), "--json", str(rep)]) == 0
    assert json.loads(rep.read_text())["n_leaves"] > 0
    assert main(["info", str(tiny_scene / "tree.npz"), "--json", str(notes), "--overwrite"]) == 0
    assert "n_leaves" in json.loads(notes.read_text())
    capsys.readouterr()
    notes.write_text("do not overwrite")
    _fails(capsys, ["eval", tiny_scene / "tree.npz", "--data", tiny_scene / "data", "--json",
                    notes, "--out", tmp_path / "ev"], str(notes))
    assert notes.read_text() == "do not overwrite" and not (tmp_path / "ev").exists()


# --- 4. bad output paths: one line, before the work ---------------------------------------------
def _bad_outputs(tmp_path):
    folder = tmp_path / "afolder"
    folder.mkdir(exist_ok=True)
    return {"devnull": "/dev/null/x", "proc": "/proc/x", "long": str(tmp_path / LONG),
            "folder": str(folder)}


_COMMANDS = {   # command -> (argv before the output, output flag, suffix of a file output)
    "render": (["render", "{tree}", "--data", "{data}", "--views", "1"], "--out", ""),
    "eval": (["eval", "{tree}", "--data", "{data}", "--views", "1"], "--out", ""),
    "eval-json": (["eval", "{tree}", "--data", "{data}", "--views", "1"], "--json", ".json"),
    "compress": (["compress", "{tree}", "--no-eval"], "--out", ".plnz"),
    "lod": (["lod", "{tree}"], "--out", ".npz"),
    "export": (["export", "{tree}"], "--out", ".npz"),
    "export-web": (["export-web", "{tree}"], "--out", ""),
    "video": (["video", "{tree}", "--frames", "2", "--width", "16", "--height", "16"], "--out",
              ".mp4"),
    "info": (["info", "{tree}"], "--json", ".json"),
    "process": (["process", "{data}/train"], "--out", ""),
}


@pytest.mark.parametrize("cmd, where", [  # an existing folder is a valid folder output
    (c, w) for c in sorted(_COMMANDS) for w in ("devnull", "proc", "long", "folder")
    if w != "folder" or _COMMANDS[c][2]])
def test_bad_output_paths_get_one_line_naming_the_flag(tiny_scene, tmp_path, capsys, cmd, where):
    head, flag, suffix = _COMMANDS[cmd]
    path = _bad_outputs(tmp_path)[where]
    argv = [a.format(tree=tiny_scene / "tree.npz", data=tiny_scene / "data") for a in head]
    line = _fails(capsys, argv + [flag, path + (suffix if where != "folder" else "")])
    assert flag in line or "too long" in line, line
    assert not list(tmp_path.glob("*.tmp-*"))


# --- 5. typed config files and --device ---------------------------------------------------------
@pytest.mark.parametrize("cmd, values, needle", [
    ("train", {"max_steps": "ten"}, "'max_steps' (--steps) must be an integer, got 'ten'"),
    ("render", {"stop_thresh": "low"}, "'stop_thresh' (--stop-thresh) must be a number"),
    ("eval", {"save_images": "yes"}, "'save_images' (--save-images) must be true or false"),
])
def test_config_values_of_the_wrong_type_name_the_file_and_flag(tiny_scene, tmp_path, capsys,
                                                                cmd, values, needle):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps(values))
    head = {"train": ["train", "--data", tiny_scene / "data", "--out", tmp_path / "run"],
            "render": ["render", tiny_scene / "tree.npz", "--data", tiny_scene / "data"],
            "eval": ["eval", tiny_scene / "tree.npz", "--data", tiny_scene / "data"]}[cmd]
    _fails(capsys, head + ["--config", cfg], str(cfg), needle)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("device, needle", [("tpu", "expected auto, cpu, cuda or cuda:N"),
                                            ("cuda:7", "--device cuda:7"),
                                            ("cpu:3", "expected auto, cpu, cuda or cuda:N")])
def test_bad_devices_are_refused_in_words(tiny_scene, tmp_path, capsys, device, needle):
    import torch

    if device == "cuda:7" and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    _fails(capsys, ["render", tiny_scene / "tree.npz", "--data", tiny_scene / "data", "--views",
                    "1", "--device", device, "--out", tmp_path / "r"], needle)


# --- 6. dataset files stay inside the dataset ----------------------------------------------------
def test_colmap_image_names_outside_the_dataset_are_refused(tmp_path):
    from plenoctree.datasets.colmap import load_colmap
    from test_colmap import write_model

    root = tmp_path / "col"
    (root / "images").mkdir(parents=True)
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[:, 2, 3] = [3.0, 3.5]
    names = ["../../../../etc/passwd", "b.png"]
    write_model(root / "sparse" / "0", c2w, [20.0, 20.0, 8.0, 8.0], 16, 16, names,
                np.random.default_rng(0).uniform(-0.5, 0.5, (20, 3)))
    with pytest.raises(DatasetError, match="points outside the dataset folder"):
        load_colmap(root, "all")


def test_a_symlink_out_of_a_blender_set_is_not_followed(tiny_scene, tmp_path):
    from plenoctree.datasets import load_blender
    from nerf_fixtures import copy_dataset

    root = copy_dataset(tiny_scene / "data", tmp_path)
    secret = tmp_path / "secret.png"
    first = sorted((root / "train").glob("*.png"))[0]
    secret.write_bytes(first.read_bytes())
    first.unlink()
    first.symlink_to(secret)
    with pytest.raises(DatasetError, match=rf"{first.name}: resolves to .*outside the dataset"):
        load_blender(root, "train")


# --- 7. every float field of a tree -------------------------------------------------------------
@pytest.mark.parametrize("lam, axis, needle", [(1e30, (0, 0, 1), "sharpness 1e+30"),
                                               (-1e30, (0, 0, 1), "sharpness -1e+30"),
                                               (2.0, (0, 0, 5), "axis has length 5")])
def test_sg_lobes_out_of_bounds_are_refused_at_load(tmp_path, capsys, lam, axis, needle):
    from plenoctree import Octree, save_tree

    good = tmp_path / "good.npz"
    save_tree(Octree.dense(1, "SG2", seed=0), good)
    arrays = dict(np.load(good, allow_pickle=False))      # a hostile file: written around the
    arrays["extra_data"] = np.array([[1.0, 1, 0, 0], [lam, *axis]], arrays["extra_data"].dtype)
    bad = tmp_path / "sg.npz"                               # checks, lobe 1 out of bounds
    np.savez(bad, **arrays)
    _fails(capsys, ["info", bad], "extra_data[1", needle)
    _fails(capsys, ["render", bad, "--data", tmp_path, "--out", tmp_path / "r"], "extra_data[1")


# --- 8. implausible cameras ---------------------------------------------------------------------
def _ns_copy(tiny_scene, tmp_path, edit):
    from plenoctree.datasets import load_blender
    from plenoctree.datasets.nerfstudio import write_nerfstudio

    data = load_blender(tiny_scene / "data", "train")
    c = data.cameras
    root = write_nerfstudio(tmp_path / "ns", c.c2w, np.round(data.images * 255).astype(np.uint8),
                            (c.fx, c.fy, c.cx, c.cy))
    obj = json.loads((root / "transforms.json").read_text())
    edit(obj)
    (root / "transforms.json").write_text(json.dumps(obj))
    return root


@pytest.mark.parametrize("edit, needle", [
    (lambda o: o.update(camera_model="OPENCV", k1=1e6), "distortion"),
    (lambda o: o.update(camera_model="OPENCV_FISHEYE", k1=1e3), "distortion"),
    (lambda o: o.update(cx=1e308), r"cx = 1e\+308 px is implausible"),
    (lambda o: o["frames"][0].update(transform_matrix=(np.array(o["frames"][0][
        "transform_matrix"]) @ np.diag([3.0, 1, 1, 1])).tolist()), "not a scaled orthonormal"),
])
def test_implausible_cameras_are_refused_naming_the_file(tiny_scene, tmp_path, edit, needle):
    from plenoctree.datasets.nerfstudio import load_nerfstudio

    pytest.importorskip("pycolmap")
    root = _ns_copy(tiny_scene, tmp_path, edit)
    with pytest.raises(DatasetError, match=needle) as info:
        load_nerfstudio(root, "all")
    assert str(root) in str(info.value)


def test_blender_rotation_scaled_by_three(tiny_scene, tmp_path):
    """Uniformly scaled: valid input, loaded with the scale removed (the same rays); scaled on
    one axis only: the rays would be distorted, refused naming the frame."""
    from plenoctree.datasets import load_blender
    from nerf_fixtures import copy_dataset

    root = copy_dataset(tiny_scene / "data", tmp_path)
    path = root / "transforms_train.json"
    obj = json.loads(path.read_text())
    ref = load_blender(root, "train").cameras.c2w
    m = np.array(obj["frames"][1]["transform_matrix"])
    obj["frames"][1]["transform_matrix"] = (m @ np.diag([3.0, 3, 3, 1])).tolist()
    path.write_text(json.dumps(obj))
    np.testing.assert_allclose(load_blender(root, "train").cameras.c2w, ref, atol=1e-6)
    obj["frames"][1]["transform_matrix"] = (m @ np.diag([3.0, 1, 1, 1])).tolist()
    path.write_text(json.dumps(obj))
    with pytest.raises(DatasetError, match=r"frames\[1\].*not a scaled orthonormal"):
        load_blender(root, "train")


def test_ssim_on_images_under_its_window_is_said_in_words(tiny_scene, tmp_path, capsys):
    assert main(["render", str(tiny_scene / "tree.npz"), "--data", str(tiny_scene / "data"),
                 "--views", "1", "--width", "3", "--height", "3", "--out",
                 str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert "SSIM n/a (images under the 11x11 SSIM window)" in out and "SSIM nan" not in out


# --- 9. hangs and leftovers ---------------------------------------------------------------------
def test_a_million_frame_transforms_is_refused_at_once(tiny_scene, tmp_path, monkeypatch):
    from plenoctree.datasets import _files, load_blender
    from nerf_fixtures import copy_dataset

    root = copy_dataset(tiny_scene / "data", tmp_path)
    path = root / "transforms_train.json"
    obj = json.loads(path.read_text())
    obj["frames"] = obj["frames"] * 40_000 + [{"broken": True}]        # 80,001 frames, 12 MB
    path.write_text(json.dumps(obj))
    monkeypatch.setattr(_files, "MAX_FRAMES", 50_000)
    t0 = time.perf_counter()
    with pytest.raises(DatasetError, match="lists 80001 frames; at most 50000"):
        load_blender(root, "train")
    monkeypatch.setattr(_files, "MAX_JSON_BYTES", 1 << 20)
    with pytest.raises(DatasetError, match="MB; a dataset's JSON file may be at most 1 MB"):
        load_blender(root, "train")
    assert time.perf_counter() - t0 < 60      # a bound against a hang, not a speed assertion


def test_a_corrupt_video_gives_one_line_without_the_ffmpeg_banner(tmp_path, capsys):
    pytest.importorskip("imageio_ffmpeg")
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, np.uint8).tobytes())
    line = _fails(capsys, ["process", bad, "--out", tmp_path / "p"], str(bad), "unreadable video")
    assert "configuration:" not in line and "ffmpeg version" not in line
    assert not (tmp_path / "p").exists()


def test_compress_views_zero_blames_views(tiny_scene, tmp_path, capsys):
    _fails(capsys, ["compress", tiny_scene / "tree.npz", "--orbit-views", "0", "--out",
                    tmp_path / "c.plnz"], "--orbit-views must be a positive integer")


def test_check_output_file_kinds(tmp_path):
    from plenoctree._util import check_output_file

    (tmp_path / "r.json").write_text("{}")
    assert check_output_file(tmp_path / "r.json", "--json", kind="json")
    (tmp_path / "r.json").write_text("not json")
    with pytest.raises(ConfigError, match="not a JSON file written by plenoctree"):
        check_output_file(tmp_path / "r.json", "--json", kind="json")
    assert check_output_file(tmp_path / "r.json", "--json", overwrite=True, kind="json")


def test_resume_after_a_kill_in_the_first_checkpoint_write(tmp_path, capsys):
    from test_reliability_runs import _dead_pid

    run = tmp_path / "run"
    run.mkdir()
    partial = run / f"checkpoint.pt.tmp-{_dead_pid()}"
    partial.write_bytes(b"x" * 1000)                  # what kill -9 mid-write leaves
    from plenoctree.nerf.checkpoint import CheckpointError, read_checkpoint

    with pytest.raises(CheckpointError, match="stopped while writing its first one"):
        read_checkpoint(run)
    assert not partial.exists()


def test_a_refused_run_leaves_no_out_folder_and_never_writes_into_its_dataset(tiny_scene,
                                                                               tmp_path, capsys):
    out = tmp_path / "new" / "run"
    _fails(capsys, ["run", "--data", tiny_scene / "data", "--out", out, "--train.steps", "-5"],
           "--train.steps must be >= 0")
    _fails(capsys, ["run", "--data", tmp_path / "missing", "--out", out], "does not exist")
    assert not (tmp_path / "new").exists()
    before = sorted(p.name for p in (tiny_scene / "data").iterdir())
    _fails(capsys, ["run", "--data", tiny_scene / "data", "--out", tiny_scene / "data"],
           "is the dataset folder")
    _fails(capsys, ["train", "--data", tiny_scene / "data", "--out", tiny_scene / "data"],
           "is the dataset folder")
    assert sorted(p.name for p in (tiny_scene / "data").iterdir()) == before


def test_an_orthonormal_rotation_is_kept_bit_for_bit():
    """Valid rotations are not renormalised (a lego tree extracted before and after the bounds
    policy is array-identical only so)."""
    from plenoctree.datasets._files import rigid_rotation

    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r = (q * (1 + 1e-7)).astype(np.float64)           # orthonormal up to rounding
    assert rigid_rotation(r, "x") is r
    np.testing.assert_allclose(rigid_rotation(3 * q, "x"), q, atol=1e-12)


@pytest.mark.parametrize("exc, needle", [
    (PermissionError(13, "Permission denied", "/x/out.npz"), "/x/out.npz: Permission denied"),
    (MemoryError(), "out of memory"),
])
def test_unforeseen_os_and_memory_errors_are_one_line(tiny_scene, monkeypatch, capsys, exc,
                                                       needle):
    """The last net in ``cli.main``: what the up-front checks could not foresee (a disk that
    fills, a permission changed mid-run, an allocation that fails) is one line, exit 1."""
    import plenoctree.cli.info as info

    def boom(path):
        raise exc

    monkeypatch.setattr(info, "tree_info", boom)
    _fails(capsys, ["info", tiny_scene / "tree.npz"], "plenoctree info: error:", needle)
