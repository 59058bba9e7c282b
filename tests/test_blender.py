"""Blender / NeRF-synthetic loader: round trip with the procedural scene, downscale, errors."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from plenoctree.datasets import Dataset, generate_rays, load_blender, load_dataset
from plenoctree.datasets import procedural as P
from plenoctree.errors import ConfigError, DatasetError

LEGO = Path(os.environ.get(
    "PLENOCTREE_LEGO",
    Path(__file__).resolve().parents[1].parent / "shared/data/nerf_synthetic/lego"))


# --- helpers ---------------------------------------------------------------------------------
def _make_dataset(root: Path, n: int = 2, size=(8, 6), split: str = "train", mode="RGBA",
                  seed: int = 0) -> list[np.ndarray]:
    """Write ``n`` random images (w, h = size) and a valid transforms json; return the arrays."""
    rng = np.random.default_rng(seed)
    w, h = size
    ch = {"RGBA": 4, "RGB": 3, "L": 1}[mode]
    (root / split).mkdir(parents=True, exist_ok=True)
    frames, arrays = [], []
    for i in range(n):
        arr = rng.integers(0, 256, size=(h, w, ch), dtype=np.uint8)
        arr = arr[..., 0] if ch == 1 else arr
        Image.fromarray(arr).save(root / split / f"r_{i}.png")
        arrays.append(arr)
        frames.append({"file_path": f"./{split}/r_{i}",
                       "transform_matrix": P.look_at([4.0, float(i), 1.0]).tolist()})
    (root / f"transforms_{split}.json").write_text(
        json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return arrays


def _write_json(root: Path, obj, split="train"):
    (root / f"transforms_{split}.json").write_text(json.dumps(obj))


# --- round trip and basic behaviour -------------------------------------------------------------
@pytest.fixture(scope="module")
def procedural_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("proc")
    P.write_procedural_dataset(root, n_train=3, n_val=1, n_test=2, width=20, height=16,
                               n_samples=256)
    return root


def test_round_trip_procedural(procedural_root):
    ds = load_blender(procedural_root, "train")
    assert isinstance(ds, Dataset) and len(ds) == 3
    assert ds.images.shape == (3, 16, 20, 3) and ds.images.dtype == np.float32
    assert ds.names == ["r_0", "r_1", "r_2"] and ds.split == "train"
    assert (ds.near, ds.far) == (2.0, 6.0)
    np.testing.assert_allclose(ds.scene_bbox, [[-1.5] * 3, [1.5] * 3])
    cams = ds.cameras
    fx = 10.0 / math.tan(0.5 * P.CAMERA_ANGLE_X)
    assert cams.fx == pytest.approx(fx) and cams.fy == pytest.approx(fx)
    assert (cams.cx, cams.cy, cams.width, cams.height) == (10.0, 8.0, 20, 16)
    c2ws = P.procedural_cameras(3, "random", seed=0)
    for i in range(3):
        o, d = cams.rays(i)
        o_ref, d_ref = generate_rays(c2ws[i], fx, fx, 10.0, 8.0, 20, 16)
        np.testing.assert_allclose(o, o_ref, atol=1e-6)
        np.testing.assert_allclose(d, d_ref, atol=1e-6)
        rgb, alpha = P.render_field(o, d, 2.0, 6.0, n_samples=256)
        # 8-bit quantisation of straight colour and alpha: composite error <= 1/255
        np.testing.assert_allclose(ds.images[i], rgb, atol=1.01 / 255)
        np.testing.assert_allclose(ds.alphas[i], alpha, atol=0.51 / 255)
    assert ds.alphas.min() == 0.0 and ds.alphas.max() == 1.0
    assert len(load_dataset(procedural_root, "test")) == 2
    assert len(load_blender(procedural_root, "val")) == 1


def test_downscale_area_average_and_background(tmp_path):
    arrays = _make_dataset(tmp_path, n=3, size=(8, 6))
    bg = np.array([0.2, 0.5, 0.9], dtype=np.float32)
    ds = load_blender(tmp_path, downscale=2, background=tuple(bg), limit=2)
    assert ds.images.shape == (2, 3, 4, 3) and ds.names == ["r_0", "r_1"]
    full = load_blender(tmp_path, background=tuple(bg))
    assert full.cameras.fx == pytest.approx(2 * ds.cameras.fx)
    assert ds.cameras.cx == 2.0 and ds.cameras.cy == 1.5
    for i in range(2):
        a = arrays[i][..., 3:].astype(np.float64) / 255
        pre = arrays[i][..., :3].astype(np.float64) / 255 * a
        pre_b = pre.reshape(3, 2, 4, 2, 3).mean(axis=(1, 3))
        a_b = a.reshape(3, 2, 4, 2, 1).mean(axis=(1, 3))
        np.testing.assert_allclose(ds.images[i], pre_b + (1 - a_b) * bg, atol=1e-6)
        np.testing.assert_allclose(ds.alphas[i], a_b[..., 0], atol=1e-6)
        np.testing.assert_allclose(full.images[i], pre + (1 - a) * bg, atol=1e-6)
    grey = load_blender(tmp_path, background=0.0)
    assert grey.background == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("mode", ["RGB", "L"])
def test_rgb_and_grey_images_have_alpha_one(tmp_path, mode):
    arrays = _make_dataset(tmp_path, n=2, mode=mode)
    ds = load_blender(tmp_path, background=(0.0, 0.0, 0.0), num_threads=1)
    np.testing.assert_array_equal(ds.alphas, 1.0)
    ref = arrays[1].astype(np.float32) / 255
    if mode == "L":
        ref = np.repeat(ref[..., None], 3, axis=-1)
    np.testing.assert_allclose(ds.images[1], ref, atol=1e-6)


def test_png_extension_in_file_path_and_ngp_intrinsics(tmp_path):
    _make_dataset(tmp_path, n=1, size=(8, 6))
    obj = json.loads((tmp_path / "transforms_train.json").read_text())
    obj["frames"][0]["file_path"] = "train/r_0.png"
    obj.update({"fl_x": 9.0, "fl_y": 7.0, "cx": 3.5, "cy": 2.5, "w": 8, "h": 6})
    del obj["camera_angle_x"]
    _write_json(tmp_path, obj)
    cams = load_blender(tmp_path).cameras
    assert (cams.fx, cams.fy, cams.cx, cams.cy) == (9.0, 7.0, 3.5, 2.5)


# --- errors: every bad input is a DatasetError naming the file --------------------------------
def _expect(root: Path, match: str, **kw):
    with pytest.raises(DatasetError, match=match):
        load_blender(root, **kw)


def test_missing_folder_and_json(tmp_path):
    _expect(tmp_path / "nope", "dataset folder does not exist")
    _expect(tmp_path, r"transforms_train\.json: file not found")
    with pytest.raises(DatasetError, match="unknown dataset format"):
        load_dataset(tmp_path, "train")


@pytest.mark.parametrize("content, match", [
    (b"{not json", "not valid JSON"),
    (b"\xff\xfe\x00garbage", "not valid JSON"),
    (b"[1, 2]", "JSON object"),
    (b'{"frames": []}', "camera_angle_x"),
    (b'{"camera_angle_x": 0.7}', "missing key 'frames'"),
    (b'{"camera_angle_x": 0.7, "frames": []}', "empty"),
    (b'{"camera_angle_x": 0.7, "frames": {}}', "must be a list"),
    (b'{"camera_angle_x": "0.7", "frames": [1]}', "camera_angle_x must be a finite number"),
    (b'{"camera_angle_x": NaN, "frames": [1]}', "finite"),
    (b'{"camera_angle_x": 4.0, "frames": [1]}', r"\(0, pi\)"),
    (b'{"camera_angle_x": 0.7, "frames": [1]}', r"frames\[0\]: expected an object"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": "a"}]}', "transform_matrix"),
    (b'{"camera_angle_x": 0.7, "frames": [{"transform_matrix": 1}]}', "file_path"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": 3, "transform_matrix": 1}]}',
     "file_path must be"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": "a", "transform_matrix": [[1]]}]}',
     "4x4"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": "a", "transform_matrix": '
     b'[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,"1"]]}]}', "only numbers"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": "a", "transform_matrix": '
     b'[[1,0,0,0],[0,1,0,0],[0,0,1,Infinity],[0,0,0,1]]}]}', "non-finite"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": "a", "transform_matrix": '
     b'[[1,0,0,0],[0,1,0,0],[0,0,1,1e300],[0,0,0,1]]}]}', "non-finite|c2w"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": "a", "transform_matrix": '
     b'[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', r"a\.png: image file not found"),
    (b'{"camera_angle_x": 0.7, "frames": [{"file_path": "/", "transform_matrix": '
     b'[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', "file_path|not found"),
])
def test_bad_transforms(tmp_path, content, match):
    (tmp_path / "transforms_train.json").write_bytes(content)
    with pytest.raises(DatasetError, match=match) as info:
        load_blender(tmp_path)
    assert str(tmp_path) in str(info.value)


def test_bad_images(tmp_path):
    _make_dataset(tmp_path, n=3, size=(8, 6))
    img = tmp_path / "train" / "r_1.png"
    good = img.read_bytes()
    img.unlink()
    _expect(tmp_path, r"r_1\.png: image file not found")
    img.write_bytes(good[: len(good) // 2])
    _expect(tmp_path, r"r_1\.png: (unreadable image|truncated PNG)")
    img.write_bytes(good[:-12])                      # all pixel data there, IEND chunk missing
    _expect(tmp_path, r"r_1\.png: truncated PNG")
    img.write_bytes(b"")
    _expect(tmp_path, r"r_1\.png: unreadable image")
    Image.fromarray(np.zeros((6, 10, 4), np.uint8)).save(img)
    _expect(tmp_path, r"r_1\.png: image is 10x6, expected 8x6")
    img.write_bytes(good)
    _expect(tmp_path, r"r_0\.png: downscale 4 does not divide", downscale=4)
    obj = json.loads((tmp_path / "transforms_train.json").read_text())
    obj["w"] = 9
    _write_json(tmp_path, obj)
    _expect(tmp_path, "w = 9")


def test_bad_options(tmp_path):
    _make_dataset(tmp_path, n=1)
    for kw in (dict(downscale=0), dict(downscale=1.5), dict(limit=0), dict(background=(2, 0, 0)),
               dict(background="white"), dict(split="../train")):
        with pytest.raises(ConfigError):
            load_blender(tmp_path, **kw)


# --- property-based: arbitrary bytes never escape as another exception ------------------------
_SETTINGS = settings(max_examples=60, deadline=None,
                     suppress_health_check=[HealthCheck.function_scoped_fixture])


@_SETTINGS
@given(data=st.binary(max_size=300))
def test_random_json_bytes_raise_dataset_error(tmp_path, data):
    (tmp_path / "transforms_train.json").write_bytes(data)
    with pytest.raises(DatasetError):
        load_blender(tmp_path)


@pytest.fixture(scope="module")
def valid_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("valid")
    _make_dataset(root, n=2, size=(8, 6))
    return root


@_SETTINGS
@given(frac=st.floats(0.0, 1.0, exclude_max=True))
def test_truncated_json_raises_dataset_error(tmp_path, valid_root, frac):
    raw = (valid_root / "transforms_train.json").read_bytes()
    (tmp_path / "train").mkdir(exist_ok=True)
    for p in (valid_root / "train").iterdir():
        (tmp_path / "train" / p.name).write_bytes(p.read_bytes())
    (tmp_path / "transforms_train.json").write_bytes(raw[: int(frac * len(raw))])
    with pytest.raises(DatasetError):
        load_blender(tmp_path)


def _setup_png(tmp_path: Path, valid_root: Path, payload: bytes) -> None:
    (tmp_path / "train").mkdir(exist_ok=True)
    (tmp_path / "transforms_train.json").write_bytes(
        (valid_root / "transforms_train.json").read_bytes())
    (tmp_path / "train" / "r_0.png").write_bytes((valid_root / "train" / "r_0.png").read_bytes())
    (tmp_path / "train" / "r_1.png").write_bytes(payload)


@_SETTINGS
@given(data=st.binary(max_size=400))
def test_random_png_bytes_raise_dataset_error(tmp_path, valid_root, data):
    _setup_png(tmp_path, valid_root, data)
    with pytest.raises(DatasetError, match="r_1.png"):
        load_blender(tmp_path)


@_SETTINGS
@given(frac=st.floats(0.0, 1.0, exclude_max=True), header=st.booleans())
def test_truncated_png_raises_dataset_error(tmp_path, valid_root, frac, header):
    raw = (valid_root / "train" / "r_1.png").read_bytes()
    cut = raw[: int(frac * len(raw))]
    payload = raw[:8] + cut[8:] if header else cut   # keep the PNG signature or not
    if payload == raw:
        payload = raw[:-1]
    _setup_png(tmp_path, valid_root, payload)
    with pytest.raises(DatasetError, match="r_1.png"):
        load_blender(tmp_path, num_threads=2)


# --- real data ----------------------------------------------------------------------------------
@pytest.mark.lego
@pytest.mark.skipif(not (LEGO / "transforms_test.json").is_file(), reason="lego data not found")
def test_lego_low_resolution():
    ds = load_blender(LEGO, "test", downscale=8, limit=4)
    assert ds.images.shape == (4, 100, 100, 3)
    assert ds.images.min() >= 0.0 and ds.images.max() <= 1.0
    assert ds.images.std() > 0.05
    np.testing.assert_allclose(ds.images[:, :3, :3], 1.0, atol=1e-6)   # white corners
    np.testing.assert_allclose(ds.images[:, -3:, -3:], 1.0, atol=1e-6)
    meta = json.loads((LEGO / "transforms_test.json").read_text())
    fx = 0.5 * 800 / math.tan(0.5 * meta["camera_angle_x"]) / 8
    assert ds.cameras.fx == pytest.approx(fx) and fx == pytest.approx(138.889, abs=1e-2)
    assert (ds.cameras.cx, ds.cameras.cy) == (50.0, 50.0)
    np.testing.assert_allclose(ds.cameras.c2w[0], meta["frames"][0]["transform_matrix"], atol=1e-6)
    # cameras sit about 4 units from the origin and look at it
    dist = np.linalg.norm(ds.cameras.centers, axis=1)
    assert np.all((dist > 3.5) & (dist < 4.5))
    o, d = ds.cameras.rays(0)
    centre_dir = d[50, 50]
    to_origin = -o[50, 50] / np.linalg.norm(o[50, 50])
    assert float(centre_dir @ to_origin) > 0.99
