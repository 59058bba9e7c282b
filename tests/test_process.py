"""``plenoctree process``: bad inputs, SfM failure, no half-written output, video frames."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from plenoctree.cli import main
from plenoctree.errors import ConfigError
from plenoctree.process import ProcessConfig, ProcessError, process
from plenoctree.process.frames import sharpness, video_frames

pytest.importorskip("pycolmap")

LEGO = Path(__file__).resolve().parents[1].parent / "shared/data/nerf_synthetic/lego"


def _noise(path, size=(48, 40), seed=0):
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(path)


def _no_output(out: Path):
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


def test_empty_folder(tmp_path):
    (tmp_path / "imgs").mkdir()
    with pytest.raises(ProcessError, match="imgs: the folder is empty"):
        process(ProcessConfig(images=str(tmp_path / "imgs"), out=str(tmp_path / "out")))
    _no_output(tmp_path / "out")


def test_one_image(tmp_path):
    (tmp_path / "imgs").mkdir()
    _noise(tmp_path / "imgs" / "a.png")
    with pytest.raises(ProcessError, match=r"imgs: 1 photo\(s\); camera poses need at least 3"):
        process(ProcessConfig(images=str(tmp_path / "imgs"), out=str(tmp_path / "out")))
    _no_output(tmp_path / "out")


def test_non_images(tmp_path):
    (tmp_path / "imgs").mkdir()
    (tmp_path / "imgs" / "notes.txt").write_text("hello")
    (tmp_path / "imgs" / "data.bin").write_bytes(b"\x00" * 10)
    with pytest.raises(ProcessError, match="none of its 2 files is a photo"):
        process(ProcessConfig(images=str(tmp_path / "imgs"), out=str(tmp_path / "out")))
    _no_output(tmp_path / "out")


def test_corrupt_jpeg_is_named(tmp_path):
    d = tmp_path / "imgs"
    d.mkdir()
    for i in range(4):
        Image.fromarray(np.full((32, 32, 3), 40 * i, np.uint8)).save(d / f"{i}.jpg")
    data = (d / "2.jpg").read_bytes()
    (d / "2.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(ProcessError, match=r"2\.jpg: unreadable or corrupt image"):
        process(ProcessConfig(images=str(d), out=str(tmp_path / "out")))
    _no_output(tmp_path / "out")


def test_mixed_sizes_and_existing_output(tmp_path):
    d = tmp_path / "imgs"
    d.mkdir()
    for i in range(3):
        _noise(d / f"{i}.png", (32, 32) if i else (40, 32), seed=i)
    with pytest.raises(ProcessError, match=r"1\.png: 32x32 pixels but 0\.png is 40x32"):
        process(ProcessConfig(images=str(d), out=str(tmp_path / "out")))
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("x")
    with pytest.raises(ConfigError, match="not empty; choose another --out or pass --overwrite"):
        process(ProcessConfig(images=str(d), out=str(tmp_path / "out")))


def test_sfm_failure_leaves_nothing(tmp_path, capsys):
    """Unrelated noise images: nothing registers; one clear error, no output, via the CLI."""
    d = tmp_path / "imgs"
    d.mkdir()
    for i in range(4):
        _noise(d / f"{i}.png", (64, 48), seed=10 + i)
    out = tmp_path / "out"
    rc = main(["process", str(d), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1
    assert "plenoctree process: error:" in err and "Traceback" not in err
    assert "could not reconstruct" in err or "could be registered" in err
    _no_output(out)


def test_missing_pycolmap_names_the_extra(tmp_path, monkeypatch):
    d = tmp_path / "imgs"
    d.mkdir()
    for i in range(3):
        _noise(d / f"{i}.png", seed=i)
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(ProcessError, match=r"pip install 'plenoctree\[colmap\]'"):
        process(ProcessConfig(images=str(d), out=str(tmp_path / "out")))
    _no_output(tmp_path / "out")


def test_video_frames_even_and_blurriest_dropped(tmp_path):
    iio = pytest.importorskip("imageio.v2")
    pytest.importorskip("imageio_ffmpeg")
    yy, xx = np.mgrid[0:64, 0:64]
    frames, blurry = [], {5, 12}
    for i in range(20):
        f = np.where(((xx + 2 * i) // 8 + yy // 8) % 2 == 0, 230.0, 25.0)   # moving checkerboard
        f[48:] = 10 * i + 20          # a strip whose grey level tells the frame index
        if i in blurry:               # a box blur
            f = sum(np.roll(np.roll(f, a, 0), b, 1) for a in range(-2, 3) for b in range(-2, 3)) / 25
        frames.append(np.repeat(np.clip(f, 0, 255).astype(np.uint8)[..., None], 3, -1))
    video = tmp_path / "v.mp4"
    iio.mimwrite(video, frames, fps=10, quality=10, macro_block_size=16)
    assert sharpness(frames[5]) < 0.5 * sharpness(frames[4])
    # 18 frames kept of 20 evenly spaced candidates: the two blurred ones go
    paths = video_frames(video, tmp_path / "f", n_frames=18, drop=0.1, log=lambda *_: None)
    assert len(paths) == 18
    idx = [int(round((np.asarray(Image.open(p))[52:60, 8:56].mean() - 20) / 10)) for p in paths]
    assert idx == [i for i in range(20) if i not in blurry]


@pytest.mark.lego
@pytest.mark.slow
@pytest.mark.skipif(not (LEGO / "transforms_test.json").is_file(), reason="lego data not found")
def test_lego_video_end_to_end(tmp_path):
    """A video of the lego test orbit (smooth path) → process → poses close to the truth."""
    iio = pytest.importorskip("imageio.v2")
    meta = json.loads((LEGO / "transforms_test.json").read_text())
    frames, gt = [], []
    for fr in meta["frames"][::5]:                 # 40 frames around the orbit
        im = Image.open(LEGO / (fr["file_path"] + ".png")).convert("RGBA").resize((160, 160),
                                                                               Image.BOX)
        a = np.asarray(im).astype(np.float32) / 255
        frames.append(np.round((a[..., :3] * a[..., 3:] + 1 - a[..., 3:]) * 255).astype(np.uint8))
        gt.append(np.array(fr["transform_matrix"]))
    video = tmp_path / "lego.mp4"
    iio.mimwrite(video, frames, fps=10, quality=9, macro_block_size=16)
    out = tmp_path / "data"
    s = process(ProcessConfig(images=str(video), out=str(out), frames=36, drop_blurry=0.1),
                log=lambda *_: None)
    assert s["format"] == "nerfstudio" and s["kind"] == "360" and s["video"]
    assert s["n_registered"] >= 32
    from plenoctree.datasets import load_dataset

    data = load_dataset(out, "all")
    assert len(data) == s["n_registered"] and data.images.shape[1:3] == (160, 160)
    assert (out / "images_2").is_dir() and (out / "colmap" / "sparse" / "0").is_dir()
