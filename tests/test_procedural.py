"""The analytic procedural scene: fields, reference ray marcher, dataset writer, grid/tree."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from plenoctree.datasets import generate_rays
from plenoctree.datasets import procedural as P
from plenoctree.errors import ConfigError
from plenoctree.sh import SH_C0, eval_sh_bases


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def test_density_inside_outside_and_surface():
    centres = np.array([P._BOX_C, P._STRIPE_C, P._GLOSS_C,
                        P._TORUS_C + np.array([P._TORUS_R, 0.0, 0.0])])
    np.testing.assert_allclose(P.density(centres), P.SIGMA_MAX)
    # on a surface (sdf = 0) the ramp is at half height; EDGE_WIDTH/2 outside it is 0
    surf = P._GLOSS_C + np.array([0.0, 0.0, -P._GLOSS_R])
    assert P.density(surf[None])[0] == pytest.approx(P.SIGMA_MAX / 2, rel=1e-9)
    out = P._GLOSS_C + np.array([0.0, 0.0, -P._GLOSS_R - P.EDGE_WIDTH / 2 - 1e-6])
    assert P.density(out[None])[0] == 0.0
    box_face = P._BOX_C + np.array([P._BOX_H[0] - P.EDGE_WIDTH / 4, 0.0, 0.0])
    assert P.density(box_face[None])[0] == pytest.approx(0.75 * P.SIGMA_MAX, rel=1e-9)
    # the torus hole is empty
    assert P.density(P._TORUS_C[None])[0] == 0.0


def test_all_content_inside_scene_box():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.6, 1.6, size=(400_000, 3))
    sig = P.density(x)
    assert sig.dtype == np.float64 and sig.min() >= 0 and sig.max() == P.SIGMA_MAX
    inside = np.all(np.abs(x - P.SCENE_CENTER) <= P.SCENE_RADIUS - 0.05, axis=1)
    assert np.all(sig[~inside] == 0)
    assert 0.03 < np.mean(sig[inside] > 0) < 0.5
    assert P.density(x[:10].astype(np.float32)).dtype == np.float32
    # render_field only evaluates σ inside the bounding spheres: they must hold all content
    occupied = x[sig > 0]
    in_some = np.zeros(len(occupied), bool)
    for c, r in P._bounding_spheres():
        in_some |= np.linalg.norm(occupied - c, axis=1) <= r
    assert in_some.all()


def test_sh_coeffs_layout_and_colours():
    pts = np.array([P._BOX_C + [0.05, 0.05, 0.05], P._STRIPE_C, P._GLOSS_C, [2.0, 2.0, 2.0]])
    k = P.sh_coeffs(pts)
    assert k.shape == (4, 48) and k.dtype == np.float32
    k = k.reshape(4, 3, 16)
    # diffuse objects: only the DC term in every channel (channel-major layout)
    assert np.all(k[[0, 1, 3], :, 1:] == 0)
    # box point (-0.45,-0.45,-0.35): checker cells floor(-4.5)+floor(-4.5)+floor(-3.5) = -14, even
    np.testing.assert_allclose(_sigmoid(k[0, :, 0] * SH_C0), [0.95, 0.9, 0.75], atol=1e-6)
    # the glossy sphere has view-dependent degree 1-3 terms in each channel
    assert np.all(np.abs(k[2, :, 1:]).max(axis=1) > 0.1)
    d_axis = P._GLOSS_AXIS
    c_on = _sigmoid(k[2] @ eval_sh_bases(3, d_axis))
    c_off = _sigmoid(k[2] @ eval_sh_bases(3, -d_axis))
    np.testing.assert_array_less(c_off + 0.2, c_on)  # bright highlight around the lobe axis
    with pytest.raises(ConfigError, match="shape"):
        P.sh_coeffs(np.zeros((3, 2)))


def _reference_march(o, d, near, far, n, bg):
    """Direct per-ray loop of the same quadrature (the slow twin of render_field)."""
    lo, hi = P.SCENE_CENTER - P.SCENE_RADIUS, P.SCENE_CENTER + P.SCENE_RADIUS
    rgb_out, a_out = [], []
    for oi, di in zip(o, d):
        di = di / np.linalg.norm(di)
        with np.errstate(divide="ignore"):
            ta, tb = (lo - oi) / di, (hi - oi) / di
        t0 = max(near, np.minimum(ta, tb).max())
        t1 = min(far, np.maximum(ta, tb).min())
        T, col = 1.0, np.zeros(3)
        if t1 > t0:
            delta = (t1 - t0) / n
            for i in range(n):
                p = oi + (t0 + (i + 0.5) * delta) * di
                sig = P.density(p[None])[0]
                if sig > 0:
                    c = _sigmoid(P.sh_coeffs(p[None])[0].reshape(3, 16).astype(np.float64)
                                 @ eval_sh_bases(3, di))
                    col += T * (1 - math.exp(-sig * delta)) * c
                    T *= math.exp(-sig * delta)
        rgb_out.append(col + T * np.asarray(bg))
        a_out.append(1 - T)
    return np.array(rgb_out), np.array(a_out)


def test_render_field_matches_direct_loop():
    c2w = P.look_at([3.0, -2.5, 1.5])
    fx = 16 / math.tan(0.5 * P.CAMERA_ANGLE_X)
    o, d = generate_rays(c2w, fx, fx, 16, 16, 32, 32)
    sel = (slice(4, 28, 5), slice(3, 30, 4))
    o, d = o[sel].reshape(-1, 3), d[sel].reshape(-1, 3)
    rgb, alpha = P.render_field(o, d, 2.0, 6.0, n_samples=200, background=(0.2, 0.4, 0.6))
    ref_rgb, ref_a = _reference_march(o, d, 2.0, 6.0, 200, (0.2, 0.4, 0.6))
    assert 0 < (alpha > 0.5).sum() < len(alpha)
    np.testing.assert_allclose(alpha, ref_a, atol=2e-6)
    np.testing.assert_allclose(rgb, ref_rgb, atol=2e-6)


def test_render_field_closed_form_glossy_sphere():
    # radial ray into the glossy sphere stopping 0.02 past its surface: optical depth is
    # SIGMA_MAX * EDGE_WIDTH / 2 (the half ramp outside) + SIGMA_MAX * 0.02 (well inside
    # the ramp's inner end at 0.01) -> 1 + 2 = 3; colour is the (spatially constant) glossy colour
    d = np.array([0.0, 1.0, 0.0])
    o = P._GLOSS_C - 4.0 * d
    t_surf = 4.0 - P._GLOSS_R
    depth = P.SIGMA_MAX * P.EDGE_WIDTH / 2 + P.SIGMA_MAX * (0.03 - P.EDGE_WIDTH / 2)
    rgb, alpha = P.render_field(o[None], d[None], near=0.5, far=t_surf + 0.03,
                                n_samples=4000, background=(0.0, 0.0, 0.0))
    expect_a = 1 - math.exp(-depth)
    assert alpha[0] == pytest.approx(expect_a, abs=1e-4)
    c = _sigmoid(P._gloss_coeffs() @ eval_sh_bases(3, d))
    np.testing.assert_allclose(rgb[0], expect_a * c, atol=1e-4)
    # a ray missing everything shows the background, alpha 0; batch shape is kept
    o2 = np.array([[[0.0, 0.0, 5.0], [0.0, 0.0, 5.0]]])
    d2 = np.array([[[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
    rgb2, a2 = P.render_field(o2, d2)
    assert rgb2.shape == (1, 2, 3) and a2.shape == (1, 2)
    np.testing.assert_array_equal(rgb2, 1.0)
    np.testing.assert_array_equal(a2, 0.0)
    with pytest.raises(ConfigError):
        P.render_field(o2, d2[..., :2])
    with pytest.raises(ConfigError):
        P.render_field(o2, d2, near=3.0, far=2.0)


def test_look_at_and_cameras():
    m = P.look_at([4.0, 0.0, 0.0])
    np.testing.assert_allclose(m[:3, 2], [1, 0, 0], atol=1e-12)      # camera +z = backwards
    np.testing.assert_allclose(m[:3, 1], [0, 0, 1], atol=1e-12)      # up stays up
    np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
    top = P.look_at([0.0, 0.0, 3.0])                                 # degenerate up
    np.testing.assert_allclose(top[:3, 2], [0, 0, 1], atol=1e-12)
    for kind in ("random", "orbit"):
        c = P.procedural_cameras(7, kind, seed=3)
        assert c.shape == (7, 4, 4)
        np.testing.assert_allclose(np.linalg.norm(c[:, :3, 3], axis=1), P.CAMERA_DISTANCE)
        # -z axis points at the origin
        np.testing.assert_allclose(-c[:, :3, 2], -c[:, :3, 3] / P.CAMERA_DISTANCE, atol=1e-12)
    with pytest.raises(ConfigError):
        P.procedural_cameras(2, "spiral")


def test_write_procedural_dataset(tmp_path):
    out = P.write_procedural_dataset(tmp_path / "scene", n_train=2, n_val=1, n_test=1,
                                     width=24, height=16, n_samples=128)
    for split, n in (("train", 2), ("val", 1), ("test", 1)):
        meta = json.loads((out / f"transforms_{split}.json").read_text())
        assert meta["camera_angle_x"] == P.CAMERA_ANGLE_X and len(meta["frames"]) == n
        fr = meta["frames"][0]
        assert fr["file_path"] == f"./{split}/r_0"
        m = np.array(fr["transform_matrix"])
        assert m.shape == (4, 4)
        img = Image.open(out / split / "r_0.png")
        assert img.mode == "RGBA" and img.size == (24, 16)
        a = np.asarray(img)[..., 3]
        assert a[0, 0] == 0 and a.max() == 255
    assert not list(out.rglob("*.tmp-*"))
    with pytest.raises(ConfigError):
        P.write_procedural_dataset(tmp_path / "x", n_train=-1)


def test_procedural_grid():
    values, mask, center, radius = P.procedural_grid(16, chunk=1000)
    assert values.shape == (16, 16, 16, 49) and values.dtype == np.float32
    assert mask.shape == (16, 16, 16) and mask.dtype == bool
    np.testing.assert_array_equal(center, [0, 0, 0])
    assert radius == P.SCENE_RADIUS
    np.testing.assert_array_equal(mask, values[..., -1] > 0)
    assert mask.any() and not mask.all()
    assert np.all(values[~mask] == 0)
    i, j, k = np.argwhere(mask)[len(np.argwhere(mask)) // 2]
    c = -1.0 + (np.array([i, j, k]) + 0.5) * 2.0 / 16
    np.testing.assert_allclose(values[i, j, k, -1], P.density(c[None].astype(np.float32))[0],
                               rtol=1e-6)
    np.testing.assert_allclose(values[i, j, k, :-1], P.sh_coeffs(c[None].astype(np.float32))[0],
                               rtol=1e-6)
    v2, m2, _, _ = P.procedural_grid(16)
    np.testing.assert_array_equal(v2, values)
    with pytest.raises(ConfigError):
        P.procedural_grid(0)


def test_procedural_tree():
    octree = pytest.importorskip("plenoctree.octree")
    if not hasattr(octree.Octree, "from_grid"):
        pytest.skip("Octree.from_grid not available")
    with pytest.raises(ConfigError, match="power of two"):
        P.procedural_tree(12)
    tree = P.procedural_tree(16)
    tree.check_integrity()
    assert tree.data_format == "SH16"
    values, mask, _, _ = P.procedural_grid(16)
    idx = np.argwhere(mask)
    pts = -1.0 + (idx + 0.5) * 2.0 / 16
    np.testing.assert_allclose(np.asarray(tree.query(pts)), values[mask], rtol=1e-5, atol=1e-5)
