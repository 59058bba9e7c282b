"""The octree renderer: closed-form renders, numba kernel vs torch twin, options and errors."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

import plenoctree
from plenoctree.errors import BackendError, ConfigError, TreeFormatError
from plenoctree.octree import Octree
from plenoctree.render import RenderOptions, available_backends, render_image, render_rays
from plenoctree.sh import eval_sg_bases, eval_sh_bases

BACKENDS = ["torch", "numba"]


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _voxel_tree(res, cells, center=0.0, radius=1.0, fmt="SH1", extra_data=None, rng=None):
    """A ``res^3`` grid tree with the given ``{(i, j, k): values [D]}`` cells occupied."""
    dim = {"RGBA": 4}.get(fmt) or 3 * int(fmt[2:]) + 1
    values = np.zeros((res, res, res, dim), np.float32)
    mask = np.zeros((res, res, res), bool)
    for ijk, v in cells.items():
        values[ijk] = v
        mask[ijk] = True
    return Octree.from_grid(values, mask, center, radius, fmt, extra_data)


def _voxel_box(res, ijk, center, radius):
    """World min corner and size [3] of grid voxel ``ijk``."""
    center = np.broadcast_to(np.asarray(center, float), (3,))
    radius = np.broadcast_to(np.asarray(radius, float), (3,))
    size = 2.0 * radius / res
    return center - radius + np.asarray(ijk) * size, size


def _render(tree, o, d, backend, **kw):
    out = render_rays(tree, np.asarray(o, np.float32), np.asarray(d, np.float32),
                      RenderOptions(**kw), backend=backend)
    return out.rgb.double().numpy(), out.depth.double().numpy(), out.alpha.double().numpy()


# ---------------------------------------------------------------------------- closed forms
@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_tree_gives_background(backend):
    tree = _voxel_tree(8, {}, fmt="SH4")
    rng = np.random.default_rng(0)
    o = rng.normal(size=(50, 3)) * 0.3 + [0, 0, -3]
    d = rng.normal(size=(50, 3)) * 0.2 + [0, 0, 1]
    rgb, depth, alpha = _render(tree, o, d, backend, background=(0.2, 0.5, 0.9))
    assert np.array_equal(rgb, np.broadcast_to(np.float32([0.2, 0.5, 0.9]), rgb.shape))
    assert np.all(alpha == 0) and np.all(depth == 0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("stop", [0.0, 0.01])
def test_single_voxel_axis_aligned(backend, stop):
    res, ijk, sigma = 8, (5, 2, 6), 3.0
    k = np.array([0.7, -1.2, 0.3])                                  # SH1: one coeff per channel
    tree = _voxel_tree(res, {ijk: np.r_[k, sigma]}, fmt="SH1")
    lo, size = _voxel_box(res, ijk, 0.0, 1.0)
    mid = lo + size / 2
    o = np.array([[-3.0, mid[1], mid[2]], [mid[0], mid[1], 5.0]])  # along +x, along -z
    d = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, -0.5]])               # not unit: normalised inside
    rgb, depth, alpha = _render(tree, o, d, backend, stop_thresh=stop, background=(1, 1, 1))
    c = _sigmoid(k * 0.28209479177387814)
    delta = size[0]
    a = 1.0 - math.exp(-sigma * delta)
    t_in = np.array([lo[0] + 3.0, 5.0 - (lo[2] + size[2])])
    np.testing.assert_allclose(alpha, a, atol=1e-5)
    np.testing.assert_allclose(rgb, np.broadcast_to(a * c + (1 - a), rgb.shape), atol=1e-5)
    np.testing.assert_allclose(depth, t_in + delta / 2, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_voxel_sh16_view_dependent(backend):
    res, ijk, sigma = 4, (1, 2, 3), 1.5
    rng = np.random.default_rng(3)
    k = rng.normal(size=48)
    tree = _voxel_tree(res, {ijk: np.r_[k, sigma]}, center=[0.5, -0.2, 0.1], radius=2.0,
                       fmt="SH16")
    lo, size = _voxel_box(res, ijk, [0.5, -0.2, 0.1], 2.0)
    mid = lo + size / 2
    d = np.array([0.0, -1.0, 0.0])
    o = mid - 4.0 * d
    rgb, depth, alpha = _render(tree, o[None], d[None], backend, stop_thresh=0.0,
                                background=(0, 0, 0))
    c = _sigmoid(k.reshape(3, 16) @ eval_sh_bases(3, d))
    a = 1 - math.exp(-sigma * size[1])
    np.testing.assert_allclose(rgb[0], a * c, atol=1e-5)
    np.testing.assert_allclose(depth[0], 4.0, atol=1e-5)            # voxel centre
    np.testing.assert_allclose(alpha[0], a, atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_opaque_wall(backend):
    res = 32
    colour = np.array([2.0, -1.0, 0.5])
    cells = {(20, j, k): np.r_[colour, 1e5] for j in range(res) for k in range(res)}
    tree = _voxel_tree(res, cells, fmt="RGBA")
    lo, size = _voxel_box(res, (20, 0, 0), 0.0, 1.0)
    rng = np.random.default_rng(1)
    o = np.c_[np.full(20, -2.0), rng.uniform(-0.9, 0.9, (20, 2))]
    d = np.tile([1.0, 0.0, 0.0], (20, 1))
    rgb, depth, alpha = _render(tree, o, d, backend, background=(1, 1, 1))
    np.testing.assert_allclose(rgb, np.broadcast_to(_sigmoid(colour), rgb.shape), atol=1e-5)
    np.testing.assert_allclose(alpha, 1.0, atol=1e-6)
    np.testing.assert_allclose(depth, lo[0] + 2.0 + size[0] / 2, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_anisotropic_box(backend):
    center, radius = np.array([0.3, -0.5, 1.0]), np.array([1.0, 2.5, 0.5])
    res, sigma = 4, 0.8
    cells = {(1, 1, 2): np.r_[0.5, 0.5, 0.5, sigma], (1, 2, 2): np.r_[-0.5, 0.0, 1.0, 2 * sigma]}
    tree = _voxel_tree(res, cells, center, radius, fmt="RGBA")
    lo1, size = _voxel_box(res, (1, 1, 2), center, radius)
    mid = lo1 + size / 2
    # Along +y: crosses voxel (1,1,2) then (1,2,2), each size[1] = 1.25 world units long.
    o = np.array([[mid[0], -10.0, mid[2]]])
    d = np.array([[0.0, 1.0, 0.0]])
    rgb, depth, alpha = _render(tree, o, d, backend, stop_thresh=0.0, background=(0, 0, 0))
    a1 = 1 - math.exp(-sigma * size[1])
    a2 = 1 - math.exp(-2 * sigma * size[1])
    w1, w2 = a1, (1 - a1) * a2
    c1, c2 = _sigmoid(np.array([0.5, 0.5, 0.5])), _sigmoid(np.array([-0.5, 0.0, 1.0]))
    t1 = lo1[1] + 10.0
    np.testing.assert_allclose(rgb[0], w1 * c1 + w2 * c2, atol=1e-5)
    np.testing.assert_allclose(alpha[0], w1 + w2, atol=1e-6)
    np.testing.assert_allclose(depth[0], (w1 * (t1 + size[1] / 2) + w2 * (t1 + 1.5 * size[1]))
                               / (w1 + w2), atol=1e-4)
    # Along a diagonal in the x-z plane through the first voxel's centre: chord length is
    # limited by the z extent (0.25) since the voxel is 0.5 wide in x.
    dd = np.array([0.6, 0.0, 0.8])
    rgb, depth, alpha = _render(tree, (mid - 3 * dd)[None], dd[None], backend, stop_thresh=0.0)
    chord = min(size[0] / 0.6, size[2] / 0.8)
    np.testing.assert_allclose(alpha[0], 1 - math.exp(-sigma * chord), atol=1e-5)
    np.testing.assert_allclose(depth[0], 3.0, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rays_missing_or_leaving_the_box(backend):
    tree = _voxel_tree(4, {(i, j, k): [0, 0, 0, 50.0] for i in range(4) for j in range(4)
                           for k in range(4)}, fmt="RGBA")
    o = np.array([[-3.0, 2.0, 0.0], [0.0, 0.0, -3.0], [0.0, 0.0, 3.0], [1.0, 1.0, 1.0]])
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    rgb, depth, alpha = _render(tree, o, d, backend, background=(0.1, 0.2, 0.3))
    # Ray 3 starts exactly on the box corner, leaving it: nothing to integrate.
    np.testing.assert_array_equal(alpha, 0.0)
    np.testing.assert_array_equal(depth, 0.0)
    np.testing.assert_allclose(rgb, np.broadcast_to([0.1, 0.2, 0.3], rgb.shape), atol=1e-7)


@pytest.mark.parametrize("backend", BACKENDS)
def test_ray_starting_inside_a_voxel(backend):
    res, ijk, sigma = 8, (3, 4, 4), 2.0
    tree = _voxel_tree(res, {ijk: [1.0, 1.0, 1.0, sigma]}, fmt="RGBA")
    lo, size = _voxel_box(res, ijk, 0.0, 1.0)
    o = (lo + size / 2)[None]
    d = np.array([[0.0, 0.0, 1.0]])
    rgb, depth, alpha = _render(tree, o, d, backend, stop_thresh=0.0)
    half = size[2] / 2
    np.testing.assert_allclose(alpha[0], 1 - math.exp(-sigma * half), atol=1e-6)
    np.testing.assert_allclose(depth[0], half / 2, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_nonpositive_sigma_contributes_nothing(backend):
    tree = _voxel_tree(4, {(1, 1, 1): [3.0, 3.0, 3.0, 5.0]}, fmt="RGBA")
    tree.data[..., -1] *= -1.0                      # σ = -5 (not buildable, but renderable)
    lo, size = _voxel_box(4, (1, 1, 1), 0.0, 1.0)
    mid = lo + size / 2
    rgb, depth, alpha = _render(tree, [[-3, mid[1], mid[2]]], [[1, 0, 0]], backend)
    assert alpha[0] == 0 and depth[0] == 0
    np.testing.assert_allclose(rgb[0], 1.0)


# ---------------------------------------------------------------------------- twin vs numba
def _random_tree(fmt, seed, res=16, occupancy=0.35):
    rng = np.random.default_rng(seed)
    b = 1 if fmt == "RGBA" else int(fmt[2:])
    dim = 4 if fmt == "RGBA" else 3 * b + 1
    values = rng.normal(size=(res, res, res, dim)).astype(np.float32)
    values[..., -1] = np.abs(values[..., -1]) * rng.uniform(0.5, 12.0)
    mask = rng.random((res, res, res)) < occupancy
    extra = None
    if fmt.startswith("SG"):
        mu = rng.normal(size=(b, 3))
        mu /= np.linalg.norm(mu, axis=1, keepdims=True)
        extra = np.c_[rng.uniform(0.5, 8.0, b), mu].astype(np.float32)
    return Octree.from_grid(values, mask, rng.normal(size=3) * 0.3,
                            rng.uniform(0.6, 1.6, size=3), fmt, extra)


def _random_rays(tree, n, seed):
    rng = np.random.default_rng(seed)
    center, radius = tree.center, tree.radius
    target = center + rng.uniform(-1.1, 1.1, size=(n, 3)) * radius
    start = center + rng.normal(size=(n, 3)) * 3.0 * radius.max()
    inside = rng.random(n) < 0.2                     # some rays start inside the box
    start[inside] = center + rng.uniform(-0.9, 0.9, size=(inside.sum(), 3)) * radius
    d = target - start
    d[inside] = rng.normal(size=(inside.sum(), 3))
    return start.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("fmt", ["SH1", "SH4", "SH9", "SH16", "SH25", "SG5", "SG30", "RGBA"])
@pytest.mark.parametrize("stop", [0.0, 0.01])
def test_numba_matches_twin(fmt, stop):
    tree = _random_tree(fmt, seed=sum(map(ord, fmt)))
    o, d = _random_rays(tree, 300, seed=7)
    opts = RenderOptions(stop_thresh=stop, background=(0.3, 0.6, 0.9))
    fast = render_rays(tree, o, d, opts, backend="numba")
    tree64 = Octree(tree.child, tree.data.astype(np.float64), tree.offset, tree.invradius,
                    tree.data_format, tree.extra_data)
    ref = render_rays(tree64, o, d, opts, backend="torch")
    assert ref.rgb.dtype == torch.float64 and fast.rgb.dtype == torch.float32
    assert float(ref.alpha.max()) > 0.5 and float(ref.alpha.min()) == 0.0   # a real test
    assert (fast.rgb.double() - ref.rgb).abs().max() <= 1e-4
    assert (fast.alpha.double() - ref.alpha).abs().max() <= 1e-4
    assert ((fast.depth.double() - ref.depth).abs() / ref.depth.clamp(min=1)).max() <= 1e-4
    # The float32 twin agrees too.
    ref32 = render_rays(tree, o, d, opts, backend="torch")
    assert (fast.rgb - ref32.rgb).abs().max() <= 1e-4


def test_stack_traversal_equals_root_descent():
    from plenoctree.render import _render_numba
    from plenoctree.render.options import parse_data_format

    tree = _random_tree("SH4", seed=11, res=32, occupancy=0.05)
    o, d = _random_rays(tree, 500, seed=2)
    info = parse_data_format(tree.data_format, tree.data_dim)
    p = _render_numba.prepare(tree, info, RenderOptions(stop_thresh=0.0))
    a = _render_numba.render_rays_numba(p, o, d, use_stack=True)
    b = _render_numba.render_rays_numba(p, o, d, use_stack=False)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_rays_along_voxel_faces_agree():
    """Axis-aligned rays starting on grid planes: both backends pick the same leaves."""
    rng = np.random.default_rng(0)
    tree = _random_tree("SH4", seed=3, res=16, occupancy=0.3)
    c, r, n = tree.center, tree.radius, 300
    o = c + (rng.integers(0, 17, size=(n, 3)) / 8.0 - 1.0) * r
    axis, sign = rng.integers(0, 3, n), rng.choice([-1.0, 1.0], n)
    d = np.zeros((n, 3))
    d[np.arange(n), axis] = sign
    o[np.arange(n), axis] = c[axis] - 3.0 * sign * r[axis]
    fast = render_rays(tree, o.astype(np.float32), d.astype(np.float32), backend="numba")
    twin = render_rays(tree, o.astype(np.float32), d.astype(np.float32), backend="torch")
    assert float(twin.alpha.mean()) > 0.3
    assert float((fast.rgb - twin.rgb).abs().max()) <= 1e-5


@pytest.mark.parametrize("backend", BACKENDS)
def test_early_stop_changes_rgb_by_less_than_thresh(backend):
    tree = _random_tree("SH4", seed=5, occupancy=0.5)
    o, d = _random_rays(tree, 400, seed=3)
    full = render_rays(tree, o, d, RenderOptions(stop_thresh=0.0), backend=backend)
    for thresh in (0.01, 0.1):
        early = render_rays(tree, o, d, RenderOptions(stop_thresh=thresh), backend=backend)
        diff = (early.rgb - full.rgb).abs()
        assert float(diff.max()) < thresh
        assert float(diff.max()) > 0                 # early stop really happened
        assert float((early.alpha - full.alpha).abs().max()) < thresh


@pytest.mark.parametrize("backend", BACKENDS)
def test_renormalize_closed_form(backend):
    """svox's fast rule on two voxels in a row (opacities a1, a2 > 0.9 together): a ray that
    stops early gets Σ w c / (1 - T) and alpha 1; one that ends before the threshold keeps
    the background."""
    res = 8
    k1, k2 = np.array([0.7, -1.2, 0.3]), np.array([-0.4, 0.9, 1.5])
    cells = {(3, 4, 4): np.r_[k1, 2.0], (4, 4, 4): np.r_[k2, 8.0], (3, 1, 1): np.r_[k1, 2.0]}
    tree = _voxel_tree(res, cells, fmt="SH1")
    lo, size = _voxel_box(res, (3, 4, 4), 0.0, 1.0)
    lo_b, _ = _voxel_box(res, (3, 1, 1), 0.0, 1.0)
    o = np.array([[-3.0, *(lo[1:] + size[1:] / 2)], [-3.0, *(lo_b[1:] + size[1:] / 2)]])
    d = np.tile([1.0, 0.0, 0.0], (2, 1))
    c1, c2 = _sigmoid(k1 * 0.28209479177387814), _sigmoid(k2 * 0.28209479177387814)
    a1, a2 = 1 - math.exp(-2.0 * size[0]), 1 - math.exp(-8.0 * size[0])
    trans = (1 - a1) * (1 - a2)
    assert trans < 0.1 < 1 - a1                 # the first ray stops after the second voxel
    acc = a1 * c1 + (1 - a1) * a2 * c2
    bg = (0.2, 0.5, 0.9)
    rgb, _, alpha = _render(tree, o, d, backend, stop_thresh=0.1, background=bg)
    np.testing.assert_allclose(rgb[0], acc + trans * np.array(bg), atol=1e-5)
    np.testing.assert_allclose(alpha[0], 1 - trans, atol=1e-6)
    rgb, _, alpha = _render(tree, o, d, backend, stop_thresh=0.1, background=bg,
                            renormalize=True)
    np.testing.assert_allclose(rgb[0], acc / (1 - trans), atol=1e-5)
    assert alpha[0] == 1.0
    np.testing.assert_allclose(rgb[1], a1 * c1 + (1 - a1) * np.array(bg), atol=1e-5)
    np.testing.assert_allclose(alpha[1], a1, atol=1e-6)


@pytest.mark.parametrize("fmt", ["SH9", "RGBA"])
def test_numba_matches_twin_renormalized(fmt):
    tree = _random_tree(fmt, seed=sum(map(ord, fmt)))
    o, d = _random_rays(tree, 300, seed=7)
    opts = RenderOptions(stop_thresh=0.1, background=(0.3, 0.6, 0.9), renormalize=True)
    fast = render_rays(tree, o, d, opts, backend="numba")
    ref = render_rays(tree, o, d, opts, backend="torch")
    plain = render_rays(tree, o, d, RenderOptions(stop_thresh=0.1, background=(0.3, 0.6, 0.9)),
                        backend="torch")
    early = ref.alpha == 1.0
    assert 0 < int(early.sum()) < early.numel() - 10                   # both kinds of rays
    assert float((ref.rgb - plain.rgb)[early].abs().max()) > 1e-3      # the rule changed them
    assert torch.equal(ref.rgb[~early], plain.rgb[~early])
    assert float((fast.rgb - ref.rgb).abs().max()) <= 1e-4
    assert torch.equal(fast.alpha == 1.0, early)
    assert float((fast.depth - ref.depth).abs().max()) <= 1e-4


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_renormalize_is_for_display_only(backend):
    from plenoctree.optim import render_rays_differentiable

    tree = _random_tree("SH4", seed=1)
    o, d = _random_rays(tree, 8, seed=1)
    data = torch.from_numpy(tree.data.copy())
    with pytest.raises(ConfigError, match="exact colour rule"):
        render_rays_differentiable(data, tree, o, d, RenderOptions(renormalize=True),
                                   backend=backend)
    with pytest.raises(ConfigError, match="renormalize must be True or False"):
        RenderOptions(renormalize=1).validated()


def test_twin_gradcheck_float64():
    from plenoctree.render._torch_impl import render_rays_torch

    tree = _random_tree("SH4", seed=9, res=4, occupancy=0.6)
    o, d = _random_rays(tree, 6, seed=4)
    data = torch.tensor(tree.data, dtype=torch.float64) * 0.3
    data[..., -1] = data[..., -1].abs() + 0.1
    data.requires_grad_(True)

    def f(x):
        out = render_rays_torch(tree, o, d, RenderOptions(stop_thresh=0.0), data=x)
        return out.rgb, out.depth, out.alpha

    assert torch.autograd.gradcheck(f, (data,), eps=1e-6, atol=1e-6, fast_mode=True)
    f(data)[0].sum().backward()
    assert float(data.grad.abs().sum()) > 0


# ---------------------------------------------------------------------------- options, API
@pytest.mark.parametrize("backend", BACKENDS)
def test_basis_range(backend):
    tree = _random_tree("SH9", seed=21)
    o, d = _random_rays(tree, 200, seed=8)
    bg = (0.0, 0.0, 0.0)
    grey = render_rays(tree, o, d, RenderOptions(sh_min=5, sh_max=4, background=bg),
                       backend=backend)
    torch.testing.assert_close(grey.rgb, 0.5 * grey.alpha[:, None].expand(-1, 3),
                               atol=1e-5, rtol=0)
    # Bases 1..3 only == a tree whose other coefficients are zero.
    part = render_rays(tree, o, d, RenderOptions(sh_min=1, sh_max=3, background=bg),
                       backend=backend)
    cut = tree.copy()
    coeffs = cut.data[..., :-1].reshape(*cut.data.shape[:-1], 3, 9)
    coeffs[..., 0] = 0
    coeffs[..., 4:] = 0
    cut.data[..., :-1] = coeffs.reshape(*cut.data.shape[:-1], 27)
    ref = render_rays(cut, o, d, RenderOptions(background=bg), backend=backend)
    torch.testing.assert_close(part.rgb, ref.rgb, atol=1e-6, rtol=0)
    every = render_rays(tree, o, d, RenderOptions(sh_max=100), backend=backend)
    torch.testing.assert_close(every.rgb, render_rays(tree, o, d, backend=backend).rgb)
    rgba = _random_tree("RGBA", seed=22)
    flat = render_rays(rgba, o, d, RenderOptions(sh_min=1, background=bg), backend=backend)
    torch.testing.assert_close(flat.rgb, 0.5 * flat.alpha[:, None].expand(-1, 3),
                               atol=1e-5, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sg_colour_closed_form(backend):
    mu = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    extra = np.c_[[2.0, 5.0], mu]
    k = np.array([1.0, -2.0, 0.5, 0.5, 3.0, -1.0])
    tree = _voxel_tree(2, {(0, 0, 0): np.r_[k, 1e4]}, fmt="SG2", extra_data=extra)
    d = np.array([0.6, 0.0, 0.8])
    rgb, _, alpha = _render(tree, (np.array([-0.5, -0.5, -0.5]) - 3 * d)[None], d[None], backend)
    c = _sigmoid(k.reshape(3, 2) @ eval_sg_bases(mu, extra[:, 0], d[None])[0])
    np.testing.assert_allclose(rgb[0], c, atol=1e-5)
    np.testing.assert_allclose(alpha[0], 1.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_batch_shapes_and_inputs(backend):
    tree = _random_tree("SH1", seed=2)
    o, d = _random_rays(tree, 24, seed=1)
    flat = render_rays(tree, o, d, backend=backend)
    out = render_rays(tree, o.reshape(2, 3, 4, 3), d.reshape(2, 3, 4, 3), backend=backend)
    assert out.rgb.shape == (2, 3, 4, 3) and out.depth.shape == (2, 3, 4)
    assert out.alpha.shape == (2, 3, 4)
    torch.testing.assert_close(out.rgb.reshape(-1, 3), flat.rgb)
    one = render_rays(tree, o[5], d[5] * 7.0, backend=backend)      # [3], unnormalised
    assert one.rgb.shape == (3,) and one.depth.shape == ()
    torch.testing.assert_close(one.rgb, flat.rgb[5], atol=1e-5, rtol=0)
    tt = render_rays(tree, torch.from_numpy(o), torch.from_numpy(d).double(), backend=backend)
    torch.testing.assert_close(tt.rgb.to(flat.rgb.dtype), flat.rgb, atol=1e-5, rtol=0)
    empty = render_rays(tree, np.zeros((0, 3)), np.zeros((0, 3)), backend=backend)
    assert empty.rgb.shape == (0, 3)
    half = tree.astype(np.float16)
    h = render_rays(half, o, d, backend=backend)
    assert h.rgb.dtype == torch.float32 and float((h.rgb - flat.rgb).abs().max()) < 2e-2


def test_bad_inputs_raise():
    tree = _random_tree("SH1", seed=2)
    o, d = _random_rays(tree, 4, seed=1)
    with pytest.raises(ConfigError, match="same shape"):
        render_rays(tree, o, d[:3])
    with pytest.raises(ConfigError, match=r"\(\.\.\., 3\)"):
        render_rays(tree, o[:, :2], d[:, :2])
    bad = o.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ConfigError, match="origins: contains NaN"):
        render_rays(tree, bad, d)
    zero = d.copy()
    zero[0] = 0
    with pytest.raises(ConfigError, match="zero-length"):
        render_rays(tree, o, zero)
    for kw in ({"stop_thresh": -0.1}, {"stop_thresh": float("nan")}, {"sh_min": -1},
               {"background": (1, 1)}, {"step_eps": 0.0}, {"sh_max": -2}):
        with pytest.raises(ConfigError):
            render_rays(tree, o, d, RenderOptions(**kw))
    with pytest.raises(ConfigError, match="RenderOptions"):
        render_rays(tree, o, d, options={"stop_thresh": 0})
    broken = tree.copy()
    broken.data_format = "SH9"
    with pytest.raises(TreeFormatError, match="data_dim"):
        render_rays(broken, o, d)


def test_backend_selection_and_errors():
    from plenoctree._triton import usable_anywhere

    # Triton's kernel sits between numba and the twin where it can run (CUDA with triton)
    usable = ["numba", *(["triton"] if usable_anywhere() else []), "torch"]
    assert available_backends() == usable
    assert available_backends("cuda")[-1] == "torch"     # (triton first where CUDA is)
    tree = _random_tree("SH1", seed=2)
    o, d = _random_rays(tree, 4, seed=1)
    with pytest.raises(BackendError, match="render: unknown backend 'warp'.*"
                                           + ", ".join(usable) + "$"):
        render_rays(tree, o, d, backend="warp")
    out = render_rays(tree, o, d)                    # auto: numba for numpy rays
    assert out.rgb.dtype == torch.float32


@pytest.mark.parametrize("backend", BACKENDS)
def test_render_image_matches_render_rays(backend):
    from plenoctree.datasets import Cameras, generate_rays
    from plenoctree.datasets.procedural import look_at

    tree = _random_tree("SH4", seed=4)
    c2w = np.stack([look_at([3.0, 1.0, 2.0]), look_at([-2.0, 2.5, 1.0])]).astype(np.float32)
    cams = Cameras(c2w=c2w, fx=20.0, fy=20.0, cx=8.0, cy=6.0, width=16, height=12)
    img = render_image(tree, cams, 1, backend=backend)
    assert img.rgb.shape == (12, 16, 3) and img.depth.shape == (12, 16)
    o, d = generate_rays(c2w[1], 20.0, 20.0, 8.0, 6.0, 16, 12)
    torch.testing.assert_close(img.rgb, render_rays(tree, o, d, backend=backend).rgb)
    assert float(img.alpha.max()) > 0


def test_public_api_and_lazy_kernel():
    for name in ("RenderOptions", "RenderOutput", "render_rays", "render_image",
                 "available_backends"):
        assert name in plenoctree.__all__ and getattr(plenoctree, name) is not None
    code = ("import sys, plenoctree, plenoctree.render; "
            "assert 'plenoctree.render._render_numba' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_twin_on_cuda_matches_cpu():
    tree = _random_tree("SH9", seed=6)
    o, d = _random_rays(tree, 200, seed=5)
    cpu = render_rays(tree, o, d, backend="torch")
    gpu = render_rays(tree, torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda())  # auto
    assert gpu.rgb.device.type == "cuda"
    torch.testing.assert_close(gpu.rgb.cpu(), cpu.rgb, atol=1e-5, rtol=0)
    torch.testing.assert_close(gpu.depth.cpu(), cpu.depth, atol=1e-4, rtol=0)
