"""NDC rays: the closed-form NeRF formula, pixel rays, bounds, and the octree renderer in NDC."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from plenoctree.datasets import Cameras, LLFFOptions, load_dataset, to_ndc_rays
from plenoctree.datasets.forward_facing import (forward_facing_tree,
                                                write_forward_facing_dataset)
from plenoctree.datasets.ndc import ndc_bounds, ndc_to_world, world_to_ndc
from plenoctree.datasets.procedural import look_at
from plenoctree.errors import ConfigError
from plenoctree.metrics import psnr


def _nerf_ndc(h, w, focal, near, rays_o, rays_d):
    """NeRF's closed form, written from the paper's appendix: shift to the near plane, then
    project with a single focal (``W / (2 focal)`` scaling)."""
    t = -(near + rays_o[..., 2]) / rays_d[..., 2]
    rays_o = rays_o + t[..., None] * rays_d
    o0 = -1.0 / (w / (2.0 * focal)) * rays_o[..., 0] / rays_o[..., 2]
    o1 = -1.0 / (h / (2.0 * focal)) * rays_o[..., 1] / rays_o[..., 2]
    o2 = 1.0 + 2.0 * near / rays_o[..., 2]
    d0 = -1.0 / (w / (2.0 * focal)) * (rays_d[..., 0] / rays_d[..., 2]
                                       - rays_o[..., 0] / rays_o[..., 2])
    d1 = -1.0 / (h / (2.0 * focal)) * (rays_d[..., 1] / rays_d[..., 2]
                                       - rays_o[..., 1] / rays_o[..., 2])
    d2 = -2.0 * near / rays_o[..., 2]
    return np.stack([o0, o1, o2], -1), np.stack([d0, d1, d2], -1)


def _get_rays(h, w, focal, c2w):
    """NeRF's pixel rays (unnormalised directions, camera z = -1), pixel centres +0.5."""
    i, j = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5, indexing="xy")
    d = np.stack([(i - w / 2) / focal, -(j - h / 2) / focal, -np.ones_like(i)], -1)
    return np.broadcast_to(c2w[:3, 3], d.shape), d @ c2w[:3, :3].T


def _ff_cams(n=3, seed=0):
    rng = np.random.default_rng(seed)
    c2w = []
    for _ in range(n):
        eye = rng.uniform(-0.3, 0.3, 3)
        c2w.append(look_at(eye, eye + np.array([rng.uniform(-.2, .2), rng.uniform(-.2, .2), -3]),
                           up=(0, 1, 0)))
    return np.stack(c2w)


def test_cameras_ndc_match_nerf_closed_form():
    h, w, focal = 12, 20, 17.0
    c2w = _ff_cams()
    cams = Cameras(c2w, focal, focal, w / 2, h / 2, w, h, ndc=True)
    for i in range(len(c2w)):
        o_ref, d_ref = _nerf_ndc(h, w, focal, 1.0, *_get_rays(h, w, focal, c2w[i]))
        o, d = cams.rays(i)
        assert o.dtype == d.dtype == np.float32 and o.shape == (h, w, 3)
        np.testing.assert_allclose(o, o_ref, atol=2e-6)
        np.testing.assert_allclose(d, d_ref / np.linalg.norm(d_ref, axis=-1, keepdims=True),
                                   atol=2e-6)
        np.testing.assert_allclose(o[..., 2], -1.0, atol=1e-6)
        # unnormalised: the end point o' + d' is the vanishing point, on z' = 1
        o2, d2 = to_ndc_rays(*_get_rays(h, w, focal, c2w[i]), focal, focal, w, h,
                             normalize=False)
        np.testing.assert_allclose(d2, d_ref, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose((o2 + d2)[..., 2], 1.0, atol=1e-5)
    # anisotropic focal: x uses fx, y uses fy
    o, d = to_ndc_rays(np.array([[0.5, 0.25, 0.0]]), np.array([[0.0, 0.0, -1.0]]), 10.0, 20.0,
                       40.0, 10.0)
    np.testing.assert_allclose(o, [[0.25, 1.0, -1.0]], atol=1e-6)


def test_ndc_points_round_trip_and_straight_rays():
    rng = np.random.default_rng(1)
    p = np.concatenate([rng.uniform(-2, 2, (50, 2)), -rng.uniform(1.0, 20.0, (50, 1))], 1)
    q = world_to_ndc(p, 30.0, 25.0, 64, 48)
    np.testing.assert_allclose(ndc_to_world(q, 30.0, 25.0, 64, 48), p, rtol=1e-10)
    assert np.all(np.abs(q[:, 2]) <= 1.0)
    # world points along a ray map onto the NDC ray o' + s d'
    o, d = np.array([0.2, -0.1, 0.3]), np.array([0.1, 0.05, -1.0])
    on, dn = to_ndc_rays(o[None], d[None], 30.0, 25.0, 64, 48, normalize=False)
    for t in (2.0, 5.0, 40.0):
        x = world_to_ndc(o + t * d, 30.0, 25.0, 64, 48)
        s = (x[2] - on[0, 2]) / dn[0, 2]
        np.testing.assert_allclose(x, on[0] + s * dn[0], atol=1e-5)


def test_pixel_rays_match_rays_numpy_and_torch():
    c2w = _ff_cams(4)
    for ndc in (False, True):
        cams = Cameras(c2w, np.array([15.0, 16, 17, 18]), 16.0, 9.5, np.array([6, 6.5, 7, 5.0]),
                       20, 12, ndc=ndc)
        assert cams.per_camera_intrinsics
        rng = np.random.default_rng(2)
        img, col, row = rng.integers(0, 4, 64), rng.integers(0, 20, 64), rng.integers(0, 12, 64)
        o, d = cams.pixel_rays(img, col, row)
        ref = [cams.rays(int(i)) for i in range(4)]
        o_ref = np.stack([ref[i][0][r, c] for i, c, r in zip(img, col, row)])
        d_ref = np.stack([ref[i][1][r, c] for i, c, r in zip(img, col, row)])
        np.testing.assert_allclose(o, o_ref, atol=1e-5)
        np.testing.assert_allclose(d, d_ref, atol=1e-5)
        ot, dt = cams.pixel_rays(torch.from_numpy(img), torch.from_numpy(col),
                                 torch.from_numpy(row))
        assert isinstance(ot, torch.Tensor) and ot.dtype == torch.float32
        np.testing.assert_allclose(ot.numpy(), o_ref, atol=1e-5)
        np.testing.assert_allclose(dt.numpy(), d_ref, atol=1e-5)


def test_ndc_bounds_contain_every_ray():
    c2w = _ff_cams(5, seed=3)
    h, w = 10, 16
    cams = Cameras(c2w, 14.0, 14.0, w / 2, h / 2, w, h, ndc=True)
    far, bbox = ndc_bounds(c2w, cams.intrinsics_array(), w, h, 14.0, 14.0)
    assert bbox[0, 2] == -1 and bbox[1, 2] == 1 and np.all(bbox[0] <= -1) and np.all(bbox[1] >= 1)
    o, d = cams.all_rays()
    o_raw, d_raw = to_ndc_rays(*Cameras(c2w, 14.0, 14.0, w / 2, h / 2, w, h).all_rays(),
                               14.0, 14.0, w, h, normalize=False)
    length = np.linalg.norm(d_raw, axis=-1)
    assert length.max() <= far + 1e-5 and length.max() > 0.97 * far
    for s in (0.0, 0.5, 1.0):               # points of every ray segment inside the box
        pts = (o + s * length[..., None] * d).reshape(-1, 3)
        assert np.all(pts >= bbox[0] - 1e-5) and np.all(pts <= bbox[1] + 1e-5)


def test_ndc_refuses_rays_not_facing_minus_z():
    with pytest.raises(ConfigError, match="-z"):
        to_ndc_rays(np.zeros((2, 3)), np.array([[0, 0, -1.0], [0, 0, 1.0]]), 1, 1, 2, 2)
    with pytest.raises(ConfigError, match="-z"):
        to_ndc_rays(np.zeros((1, 3)), np.array([[1.0, 0, 0]]), 1, 1, 2, 2)
    with pytest.raises(ConfigError, match="shape"):
        to_ndc_rays(np.zeros((2, 3)), np.zeros((3, 3)), 1, 1, 2, 2)
    with pytest.raises(ConfigError, match="near"):
        to_ndc_rays(np.zeros((1, 3)), np.array([[0, 0, -1.0]]), 1, 1, 2, 2, near=0.0)


@pytest.fixture(scope="module")
def ff_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("ff")
    return write_forward_facing_dataset(root, n_images=17, width=48, height=36, n_samples=192)


def test_renderer_in_ndc_matches_torch_twin(ff_root):
    from plenoctree.octree import Octree
    from plenoctree.render import render_rays

    data = load_dataset(ff_root, "test")
    box = data.scene_bbox.astype(np.float64)
    tree = Octree.dense(4, "SH4", center=box.mean(0), radius=(box[1] - box[0]) / 2, seed=0)
    tree.data[..., -1] = np.abs(tree.data[..., -1]) * 2.0          # NDC-length densities
    o, d = data.cameras.rays(1)
    a = render_rays(tree, o, d, backend="numba")
    b = render_rays(tree, o, d, backend="torch")
    assert float(a.alpha.mean()) > 0.2                               # the rays do cross the tree
    for x, y in ((a.rgb, b.rgb), (a.depth, b.depth), (a.alpha, b.alpha)):
        np.testing.assert_allclose(x.numpy(), y.numpy().astype(np.float32), atol=2e-4)


def test_octree_built_in_ndc_renders_forward_facing_scene(ff_root):
    from plenoctree.render import render_rays

    data = load_dataset(ff_root, "test")
    assert data.cameras.ndc and data.names == ["000", "008", "016"] and data.near == 0.0
    scores = {}
    for res in (64, 128):
        tree = forward_facing_tree(ff_root, res)
        tree.check_integrity()
        np.testing.assert_allclose(tree.bbox, data.scene_bbox, atol=1e-6)
        scores[res] = [psnr(render_rays(tree, *data.cameras.rays(i)).rgb.numpy(), data.images[i])
                       for i in range(len(data))]
    # the NDC tree reproduces the photographs, better and better with resolution
    assert min(scores[128]) > 23.5, scores
    assert min(scores[128]) > max(scores[64]) + 3.0, scores
    # the same tree seen through world-space rays (no NDC conversion) is wrong
    world = load_dataset(ff_root, "test", options=LLFFOptions(ndc=False))
    o, d = world.cameras.rays(0)
    bad = psnr(render_rays(tree, o, d).rgb.numpy(), data.images[0])
    assert bad < min(scores[128]) - 8.0, (bad, scores)


def test_downscaled_ndc_space_is_the_same(ff_root):
    full = load_dataset(ff_root, "train")
    half = load_dataset(ff_root, "train", downscale=2)
    assert half.cameras.ndc_focal[0] * 2 == pytest.approx(full.cameras.ndc_focal[0])
    np.testing.assert_allclose(half.scene_bbox, full.scene_bbox, atol=1e-6)
    o_h, d_h = half.cameras.rays(0)
    # half-res pixel (u, v) looks through the centre of its 2x2 block, full-res (2u+1, 2v+1)
    u, v = np.meshgrid(np.arange(half.cameras.width), np.arange(half.cameras.height))
    o_f, d_f = full.cameras.pixel_rays(np.zeros(u.size, int), 2 * u.ravel() + 0.5,
                                       2 * v.ravel() + 0.5)
    np.testing.assert_allclose(o_h.reshape(-1, 3), o_f, atol=1e-5)
    np.testing.assert_allclose(d_h.reshape(-1, 3), d_f, atol=1e-5)
    assert math.isclose(half.far, full.far, rel_tol=1e-6)
