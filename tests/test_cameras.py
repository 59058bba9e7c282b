"""Cameras and ray generation: OpenGL convention golden values, scaling, validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plenoctree.datasets import Cameras, generate_rays
from plenoctree.errors import ConfigError


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _c2w(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = t
    return m


def test_identity_camera_golden():
    # odd size so that pixel (2, 2) is exactly on the optical axis
    o, d = generate_rays(_c2w(), fx=10.0, fy=10.0, cx=2.5, cy=2.5, width=5, height=5)
    assert o.shape == d.shape == (5, 5, 3) and o.dtype == d.dtype == np.float32
    np.testing.assert_allclose(d[2, 2], [0, 0, -1], atol=1e-7)
    np.testing.assert_allclose(o, 0.0)
    # one pixel to the right: +x, one pixel up (row above): +y
    np.testing.assert_allclose(d[2, 3], np.array([0.1, 0, -1]) / math.sqrt(1.01), atol=1e-7)
    np.testing.assert_allclose(d[1, 2], np.array([0, 0.1, -1]) / math.sqrt(1.01), atol=1e-7)
    assert d[2, 0, 0] < 0 and d[4, 2, 1] < 0
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)


def test_pixel_centre_offset_and_anisotropic_focal():
    o, d = generate_rays(_c2w(), fx=4.0, fy=8.0, cx=2.0, cy=1.0, width=4, height=2)
    # pixel (u=0, v=0): ((0.5-2)/4, -(0.5-1)/8, -1)
    ref = np.array([-1.5 / 4, 0.5 / 8, -1.0])
    np.testing.assert_allclose(d[0, 0], ref / np.linalg.norm(ref), atol=1e-7)
    ref = np.array([1.5 / 4, -0.5 / 8, -1.0])
    np.testing.assert_allclose(d[1, 3], ref / np.linalg.norm(ref), atol=1e-7)


def test_rotated_translated_camera():
    # camera at (4, 0, 0) turned +90 deg about y looks down -x (towards the origin)
    c2w = _c2w(_rot_y(math.pi / 2), (4.0, 0.0, 0.0))
    o, d = generate_rays(c2w, 100.0, 100.0, 1.5, 1.5, 3, 3)
    np.testing.assert_allclose(o[0, 0], [4, 0, 0])
    np.testing.assert_allclose(d[1, 1], [-1, 0, 0], atol=1e-7)
    # image right (+x_cam) maps to world -z; a point 4 units ahead through pixel (2,1) is the
    # camera-space point (0.01*4, 0, -4) rotated: its world z is negative
    assert d[1, 2, 2] < 0 and abs(d[1, 2, 1]) < 1e-7
    cams = Cameras(c2w[None], 100.0, 100.0, 1.5, 1.5, 3, 3)
    o2, d2 = cams.rays(0)
    np.testing.assert_array_equal(o2, o)
    np.testing.assert_array_equal(d2, d)


def test_cameras_len_rays_all_rays_select():
    c2w = np.stack([_c2w(_rot_y(a), (a, 0, 1)) for a in (0.0, 0.5, 1.0)])
    cams = Cameras(c2w, 20.0, 20.0, 3.0, 2.0, 6, 4)
    assert len(cams) == 3 and cams.c2w.dtype == np.float32
    o, d = cams.all_rays()
    assert o.shape == d.shape == (3, 4, 6, 3)
    for i in range(3):
        oi, di = cams.rays(i)
        np.testing.assert_array_equal(o[i], oi)
        np.testing.assert_array_equal(d[i], di)
    np.testing.assert_array_equal(cams.rays(-1)[1], d[2])
    sub = cams.select([2, 0])
    assert len(sub) == 2
    np.testing.assert_array_equal(sub.rays(0)[1], d[2])
    np.testing.assert_allclose(cams.centers, c2w[:, :3, 3])
    with pytest.raises(ConfigError, match="out of range"):
        cams.rays(3)
    with pytest.raises(ConfigError, match="integer"):
        cams.rays(1.0)


def test_scaled_matches_block_centres():
    c2w = _c2w(_rot_y(0.3), (0.0, 1.0, 4.0))[None]
    cams = Cameras(c2w, 50.0, 40.0, 16.0, 12.0, 32, 24)
    small = cams.scaled(4)
    assert (small.width, small.height) == (8, 6)
    assert (small.fx, small.fy, small.cx, small.cy) == (12.5, 10.0, 4.0, 3.0)
    # the ray of small pixel (u', v') goes through the centre of its 4x4 block: the point
    # between full-res pixels 4u'+1 and 4u'+2 (both axes). Reconstruct it with a shifted cx.
    _, d_small = small.rays(0)
    _, d_shift = generate_rays(c2w[0], 50.0, 40.0, 16.0 - 1.5, 12.0 - 1.5, 32, 24)
    np.testing.assert_allclose(d_small, d_shift[::4, ::4], atol=1e-6)
    assert cams.scaled(1) == cams
    with pytest.raises(ConfigError, match="divide"):
        cams.scaled(5)
    with pytest.raises(ConfigError, match="positive integer"):
        cams.scaled(0)
    with pytest.raises(ConfigError, match="positive integer"):
        cams.scaled(2.0)


@pytest.mark.parametrize("bad", [
    np.eye(4),                       # not batched
    np.zeros((2, 3, 4)),             # 3x4
    np.full((1, 4, 4), np.nan),      # non-finite
    np.array([[[np.inf] * 4] * 4]),
])
def test_cameras_bad_c2w(bad):
    with pytest.raises(ConfigError, match="c2w"):
        Cameras(bad, 10.0, 10.0, 1.0, 1.0, 2, 2)


@pytest.mark.parametrize("kw, what", [
    (dict(fx=0.0), "fx"), (dict(fy=-1.0), "fy"), (dict(fx=float("nan")), "fx"),
    (dict(cx=float("inf")), "cx"), (dict(width=0), "width"), (dict(height=2.5), "height"),
    (dict(width=True), "width"),
])
def test_cameras_bad_intrinsics(kw, what):
    args = dict(fx=10.0, fy=10.0, cx=1.0, cy=1.0, width=2, height=2)
    args.update(kw)
    with pytest.raises(ConfigError, match=what):
        Cameras(np.eye(4)[None], **args)
    with pytest.raises(ConfigError, match=what):
        generate_rays(np.eye(4), **args)


def test_ndc_needs_forward_facing_rays():
    # NDC rays are tested in tests/test_datasets_ndc.py; a camera looking up +z has no NDC rays
    cams = Cameras(_c2w(_rot_y(math.pi))[None], 10.0, 10.0, 1.0, 1.0, 2, 2, ndc=True)
    with pytest.raises(ConfigError, match="NDC"):
        cams.rays(0)
    o, d = Cameras(np.eye(4)[None], 10.0, 10.0, 1.0, 1.0, 2, 2, ndc=True).rays(0)
    np.testing.assert_allclose(o[..., 2], -1.0, atol=1e-6)
