"""The far field of unbounded captures (issue 50): the NeRF-SH's second network beyond the
scene box, its samples joined with the box's in ray order, and the octree's shells."""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest
import torch

from plenoctree.convert.field import AnalyticField
from plenoctree.convert.shells import ShellOptions, add_shells, shell_levels
from plenoctree.datasets.cameras import Cameras
from plenoctree.nerf.checkpoint import load_nerf, save_checkpoint
from plenoctree.nerf.config import ModelConfig, TrainConfig
from plenoctree.nerf.far import (CONTRACTED_BOX, MAX_LEVELS, MIN_LEVELS, FarField,
                                 composite_far, contract, far_distortion, far_levels_for,
                                 render_far, resolve_far_levels, resolve_render_step)
from plenoctree.nerf.model import NeRFModel, RadianceField
from plenoctree.nerf.renderer import RayBatch, RenderMode, render_rays_occupancy
from plenoctree.nerf.volrend import render_weights
from plenoctree.octree.build import tree_from_grid, tree_from_leaves
from plenoctree.render import RenderOptions, render_rays

TINY = ModelConfig(grid_levels=4, grid_log2_table=12, grid_max_res=64, net_width=16)
BOX = np.array([[-1.0] * 3, [1.0] * 3], np.float32)


def test_contraction_is_the_identity_in_the_box_and_maps_everything_into_2():
    u = torch.tensor([[0.3, -0.9, 1.0], [1.0 + 1e-6, 0.0, 0.0], [4.0, 1.0, -2.0],
                      [-1e9, 3.0, 0.0]])
    c = contract(u)
    assert torch.equal(c[0], u[0])
    assert torch.allclose(c[1], u[1], atol=1e-5)                  # continuous at the surface
    assert torch.allclose(c[2], torch.tensor([1.75, 0.4375, -0.875]))   # (2 - 1/4) u / 4
    assert c.abs().max() <= 2.0 and c[3, 0] == pytest.approx(-2.0)
    r = torch.linspace(1.0, 100.0, 50)[:, None] * torch.tensor([[1.0, 0.2, 0.1]])
    assert (contract(r)[1:, 0] > contract(r)[:-1, 0]).all()       # monotone outwards


def test_far_levels_reach_the_far_bound_within_their_limits():
    cams = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    assert far_levels_for(BOX, cams, 15.0) == 4                    # 1 + 15 = 16 = 2^4
    assert far_levels_for(BOX, cams, 16.5) == 5
    assert far_levels_for(BOX, cams, 0.5) == MIN_LEVELS
    assert far_levels_for(BOX, cams, 1e6) == MAX_LEVELS
    assert far_levels_for(BOX * 4, cams, 60.0) == 4                # in box radii: 0.25 + 15


def _data(unbounded: bool):
    c2w = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
    c2w[1, :3, 3] = [0.5, 0.0, 0.0]
    return types.SimpleNamespace(unbounded=unbounded, scene_bbox=BOX, far=15.0,
                                 cameras=types.SimpleNamespace(c2w=c2w))


def test_far_field_is_automatic_for_captures_of_a_place_only():
    cfg = TrainConfig()
    assert cfg.far_levels == -1
    assert resolve_far_levels(cfg, _data(True)) == 4
    assert resolve_far_levels(cfg, _data(False)) == 0               # lego, flower, fox
    assert resolve_far_levels(dataclasses.replace(cfg, far_levels=0), _data(True)) == 0
    assert resolve_far_levels(dataclasses.replace(cfg, far_levels=6), _data(False)) == 6
    hier = dataclasses.replace(cfg, sampler="hierarchical")
    assert resolve_far_levels(hier, _data(True)) == 0


def test_render_step_follows_the_box_of_a_place_only():
    """The automatic step: 0.01 world units for objects (lego, flower, fox: unchanged), 1/200
    of the box's side for a capture of a place, whatever its poses' units (the same walk in
    units 3.6x larger took 3.6x the samples per ray); an explicit step is kept."""
    cfg = TrainConfig()
    assert cfg.render_step == -1
    assert resolve_render_step(cfg, _data(False)) == 0.01
    assert resolve_render_step(cfg) == 0.01                          # no dataset: renderers
    assert resolve_render_step(cfg, _data(True)) == pytest.approx(0.01)       # side 2
    big = _data(True)
    big.scene_bbox = BOX * 3.6
    assert resolve_render_step(cfg, big) == pytest.approx(0.036)
    assert resolve_render_step(dataclasses.replace(cfg, render_step=0.02), big) == 0.02


def _sequential(sig, rgb, delta):
    """Reference: one ray's samples composited one after the other: ``(rgb, acc)``."""
    w, _ = render_weights(sig[None], delta[None])
    return (w[0, :, None] * rgb).sum(0), w.sum()


@pytest.mark.parametrize("origin", [[0.2, 0.1, -0.3], [3.0, 0.4, 0.2]])
def test_far_samples_join_the_box_in_ray_order(origin):
    """``composite_far`` equals compositing [far before the box, the box, far behind it] as
    one sequence, for a camera inside and one outside the box."""
    torch.manual_seed(0)
    far = FarField(RadianceField(TINY, CONTRACTED_BOX), BOX, 4)
    o = torch.tensor([origin])
    d = torch.nn.functional.normalize(torch.tensor([[-1.0, 0.05, 0.02]]), dim=-1)
    f = render_far(far, o, d, 0.05, torch.as_tensor(BOX), 16, 8, False)
    # the box's own samples: 5 segments of known density and colour
    s_in = torch.tensor([0.5, 3.0, 0.0, 1.0, 2.0])
    c_in = torch.rand(5, 3)
    d_in = torch.full((5,), 0.1)
    w_in, _ = render_weights(s_in[None], d_in[None])
    rgb_in = (w_in[0, :, None] * c_in).sum(0)[None]
    acc_in = w_in.sum()[None]
    j = composite_far(f, rgb_in, acc_in, torch.zeros(1))
    keep = f["sigma"][0] > 0
    before = keep & ~f["after"][0]
    after = keep & f["after"][0]
    sig = torch.cat([f["sigma"][0][before], s_in, f["sigma"][0][after]])
    rgb = torch.cat([f["rgb"][0][before], c_in, f["rgb"][0][after]])
    delta = torch.cat([f["delta"][0][before], d_in, f["delta"][0][after]])
    ref_rgb, ref_acc = _sequential(sig.detach(), rgb.detach(), delta)
    assert torch.allclose(j["rgb"][0].detach(), ref_rgb, atol=1e-5)
    assert float(j["acc"][0].detach()) == pytest.approx(float(ref_acc), abs=1e-5)
    assert bool(before.any()) == (origin[0] > 1.0)        # outside: far samples come first


def test_far_samples_cover_the_outer_cube_in_inverse_distance():
    far = FarField(RadianceField(TINY, CONTRACTED_BOX), BOX, 4)
    o = torch.zeros(3, 3)
    d = torch.eye(3)
    f = render_far(far, o, d, 0.1, torch.as_tensor(BOX), 32, 0, False)
    t = f["t"]
    assert (t[:, 1:] > t[:, :-1]).all()
    assert torch.allclose(f["delta"].sum(1), torch.full((3,), 16.0 - 0.1))
    assert (f["sigma"][t < 1.0] == 0).all() and (f["sigma"][t > 1.0] > 0).all()
    inv = 1.0 / t                                   # bin middles, equal steps in 1 / t
    steps = inv[:, :-1] - inv[:, 1:]
    assert torch.allclose(steps, torch.full_like(steps, (1 / 0.1 - 1 / 16.0) / 32), rtol=1e-3)


def test_model_queries_the_far_field_outside_the_box_and_saves_it(tmp_path):
    torch.manual_seed(0)
    model = NeRFModel(TINY, BOX, occ_res=8, far_levels=5)
    p = torch.tensor([[0.1, 0.2, 0.3], [3.0, 0.0, 0.0], [0.0, -20.0, 1.0]])
    sigma, coeffs = model.query(p)
    s_in, c_in = model.fine(p[:1])
    s_far, c_far = model.far(p[1:])
    assert torch.allclose(sigma, torch.cat([s_in, s_far]))
    assert torch.allclose(coeffs, torch.cat([c_in, c_far]))
    assert torch.allclose(model.density(p), sigma, rtol=1e-5)
    cfg = dataclasses.replace(TrainConfig(model=TINY, occ_res=8), far_levels=5)
    save_checkpoint(tmp_path / "checkpoint.pt", cfg, model)
    back = load_nerf(tmp_path / "checkpoint.pt")
    assert back.far_levels == 5
    assert torch.allclose(back.query(p)[0], sigma)


def test_training_rays_reach_the_far_field_with_gradients():
    torch.manual_seed(0)
    model = NeRFModel(TINY, BOX, occ_res=8, far_levels=4)
    cfg = TrainConfig(model=TINY, occ_res=8, render_step=0.05, far_samples=8, far_fine=8)
    o = torch.zeros(4, 3)
    d = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    rays = RayBatch(o, d, 0.05, 30.0, torch.zeros(3))
    out = render_rays_occupancy(model, rays, cfg, RenderMode(train=True,
                                                             generator=torch.Generator()))
    out["rgb"].sum().backward()
    assert model.far.net.encoder.table.grad.abs().sum() > 0
    assert model.fine.encoder.table.grad.abs().sum() > 0
    assert out["n_samples"] > 4 * 24
    assert (out["acc"] > 0).all() and (out["acc"] <= 1).all()


def test_far_distortion_is_mip_nerf_360s_sum_in_normalised_inverse_distance():
    """The O(S) form equals eq. 15 summed directly over every pair, with distances mapped to
    s = (1/t0 - 1/t) / (1/t0 - 1/t1); a fog over the whole far interval costs more than the
    same weight in one place, and the gradient reaches the weights."""
    g = torch.Generator().manual_seed(3)
    edges = torch.sort(0.5 + 40.0 * torch.rand(5, 13, generator=g, dtype=torch.float64), -1).values
    w = (0.2 * torch.rand(5, 12, generator=g, dtype=torch.float64)).requires_grad_()
    inv = 1.0 / edges
    s = (inv[:, :1] - inv) / (inv[:, :1] - inv[:, -1:])
    m, width = 0.5 * (s[:, 1:] + s[:, :-1]), s[:, 1:] - s[:, :-1]
    direct = ((w[:, :, None] * w[:, None, :] * (m[:, :, None] - m[:, None, :]).abs()).sum((1, 2))
              + (w * w * width).sum(-1) / 3.0)
    got = far_distortion(w, edges)
    assert torch.allclose(got, direct, rtol=1e-12, atol=1e-15)
    got.sum().backward()
    assert w.grad.abs().sum() > 0
    fog = torch.full((1, 12), 0.9 / 12, dtype=torch.float64)
    wall = torch.zeros((1, 12), dtype=torch.float64)
    wall[0, 6] = 0.9
    assert far_distortion(wall, edges[:1]) < 0.5 * far_distortion(fog, edges[:1])


def test_training_penalises_the_far_fields_spread_only_with_the_distortion_loss():
    """A training render with the distortion on returns the far samples' distortion (one per
    ray, >= 0, with a gradient to the far network); without it, none."""
    torch.manual_seed(0)
    model = NeRFModel(TINY, BOX, occ_res=8, far_levels=4)
    cfg = TrainConfig(model=TINY, occ_res=8, render_step=0.05, far_samples=8, far_fine=8)
    d = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    rays = RayBatch(torch.zeros(4, 3), d, 0.05, 30.0, torch.zeros(3))
    with_it = render_rays_occupancy(model, rays, cfg, RenderMode(
        train=True, generator=torch.Generator(), distortion=True))
    fd = with_it["far_distortion"]
    assert fd.shape == (4,) and (fd >= 0).all() and fd.sum() > 0
    fd.sum().backward()
    assert model.far.net.encoder.table.grad.abs().sum() > 0
    without = render_rays_occupancy(model, rays, cfg, RenderMode(
        train=True, generator=torch.Generator()))
    assert "far_distortion" not in without


def test_fixed_steps_add_the_far_distortion_to_their_loss():
    """The fixed-shape step's render carries the far samples' distortion and its loss adds it
    at the photos' weight (normalised distances: no division by the box's extent)."""
    from plenoctree.nerf.fixed import fixed_loss, render_fixed

    torch.manual_seed(0)
    model = NeRFModel(TINY, BOX, occ_res=8, far_levels=4)
    cfg = TrainConfig(model=TINY, occ_res=8, render_step=0.05, far_samples=8, far_fine=8)
    d = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1)
    rays = RayBatch(torch.zeros(6, 3), d, 0.05, 30.0, torch.zeros(3))
    r = render_fixed(model, rays, cfg, RenderMode(train=True, generator=torch.Generator(),
                                                  distortion=True), 4096)
    assert r["complete"].all() and r["far_distortion"].shape == (6,)
    target = torch.rand(6, 3)
    with_it, _ = fixed_loss(r, target, 0.01, 2.0)
    without, _ = fixed_loss(r, target, 0.0, 2.0)
    expected = 0.01 * (r["distortion"].mean() / 2.0 + r["far_distortion"].mean())
    torch.testing.assert_close(with_it - without, expected, rtol=1e-5, atol=1e-9)


# ------------------------------------------------------------------ octree


def test_tree_from_leaves_equals_tree_from_grid():
    rng = np.random.default_rng(0)
    mask = rng.random((8, 8, 8)) < 0.2
    vals = rng.random((8, 8, 8, 4)).astype(np.float32)
    a = tree_from_grid(vals, mask, data_format="RGBA")
    ijk = np.argwhere(mask)
    b = tree_from_leaves(np.full(len(ijk), 2), ijk, vals[mask], data_format="RGBA")
    b.check_integrity()
    pts = rng.uniform(-1, 1, (4000, 3))
    assert np.array_equal(a.query(pts), b.query(pts))
    assert (a.n_nodes, a.n_leaves) == (b.n_nodes, b.n_leaves)


def test_tree_from_leaves_mixes_depths_and_refuses_overlaps():
    t = tree_from_leaves([0, 3, 3], [[1, 1, 1], [0, 0, 0], [5, 2, 1]],
                         np.arange(12, dtype=np.float32).reshape(3, 4), data_format="RGBA")
    t.check_integrity()
    assert t.depth_limit == 3
    q = t.query(np.array([[0.5, 0.5, 0.5], [-0.95, -0.95, -0.95], [-0.7, -0.7, -0.7]]))
    assert q[:, 0].tolist() == [0.0, 4.0, 0.0]
    with pytest.raises(ValueError, match="inside another"):
        tree_from_leaves([0, 1], [[0, 0, 0], [0, 0, 0]], np.ones((2, 4)), data_format="RGBA")
    with pytest.raises(ValueError, match="twice"):
        tree_from_leaves([1, 1], [[0, 0, 0], [0, 0, 0]], np.ones((2, 4)), data_format="RGBA")
    with pytest.raises(ValueError, match=r"\[0, 2\^"):
        tree_from_leaves([0], [[2, 0, 0]], np.ones((1, 4)), data_format="RGBA")


def _room_field():
    """A ball in the box and the walls of a room 3 box radii away (shell 2), SH degree 0."""
    def density(x):
        ball = np.linalg.norm(x - [0.0, 0.0, -0.3], axis=-1) < 0.3
        r = np.abs(x).max(-1)
        return np.where(ball, 40.0, np.where((r > 3.0) & (r < 3.4), 30.0, 0.0))

    def coeffs(x):
        r = np.abs(x).max(-1, keepdims=True)
        c = np.where(r > 2.0, [2.0, -2.0, -2.0], [-2.0, 2.0, -2.0])     # red walls, green ball
        return (c / 0.28209479177387814).astype(np.float32)

    return AnalyticField(density, coeffs, sh_degree=0, scene_bbox=BOX)


def _inward_cameras(n: int = 8, size: int = 24) -> Cameras:
    c2w = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        pos = np.array([0.8 * np.cos(a), 0.8 * np.sin(a), 0.2])
        fwd = -pos / np.linalg.norm(pos)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, up, -fwd], 1)
        m[:3, 3] = pos
        c2w.append(m)
    return Cameras(np.array(c2w, np.float32), size * 0.6, size * 0.6, size / 2, size / 2,
                   size, size)


def room_trees(n: int = 32):
    """``(box, grown, info, cams)``: the room field's ``n³`` tree of the box, the same grown
    with 2 shells, and the cameras inside the box that see the walls."""
    field = _room_field()
    cams = _inward_cameras()
    ax = (np.arange(n) + 0.5) / n * 2 - 1
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    sig, co = field.query(pts)
    mask = (sig > 0).reshape(n, n, n)
    vals = np.concatenate([co, sig[:, None]], 1).reshape(n, n, n, 4)
    box = tree_from_grid(vals, mask, 0.0, 1.0, "SH1")
    levels = shell_levels(box.radius, np.full(3, 4.0), box.max_depth)
    assert levels == 2
    grown, info = add_shells(box, field, cams, levels, ShellOptions(grid=32))
    return box, grown, info, cams


def test_shells_hold_the_room_and_leave_the_box_as_it_was():
    box, grown, info, cams = room_trees()
    grown.check_integrity()
    assert info["far_levels"] == 2 and info["shell_leaves"][0] == 0 < info["shell_leaves"][1]
    assert np.allclose(grown.radius, 4.0) and grown.max_depth == box.max_depth + 2
    rng = np.random.default_rng(1)
    inside = rng.uniform(-0.99, 0.99, (5000, 3))
    assert np.array_equal(grown.query(inside), box.query(inside))
    o, d = cams.rays(0)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    black = RenderOptions(background=(0.0, 0.0, 0.0))
    first = render_rays(box, o, d, black)
    before, alpha = first.rgb.numpy(), first.alpha.numpy()
    after = render_rays(grown, o, d, black).rgb.numpy()
    wall = alpha < 1e-3                                 # the box alone: black behind the ball
    assert 0.3 < wall.mean() < 0.95
    red = after[wall]
    assert (red[:, 0] > 0.8).mean() > 0.95 and (red[:, 1] < 0.2).all()
    ball = alpha > 0.999                                # the ball, drawn as before
    assert ball.any() and np.allclose(after[ball], before[ball], atol=1e-3)


def test_a_360_llff_folder_trains_a_far_field_and_extracts_shells(tmp_path, capsys):
    """The chain on a capture of a place: ``train`` adds the far field by itself (config.json
    records its shells), ``extract`` grows the tree with them, the tree loads and renders."""
    import json

    from plenoctree.cli import main
    from plenoctree.datasets import load_blender, load_dataset
    from plenoctree.datasets.llff import write_llff
    from plenoctree.datasets.procedural import write_procedural_dataset
    from plenoctree.octree import load_tree

    bl = load_blender(write_procedural_dataset(tmp_path / "bl", 8, 1, 1, width=16, height=12,
                                               n_samples=32), "train")
    c = bl.cameras
    root = write_llff(tmp_path / "llff", c.c2w, bl.images, c.fx,
                      np.tile([2.0, 40.0], (len(c), 1)))
    run = tmp_path / "run"
    assert main(["train", "--data", str(root), "--out", str(run), "--steps", "3",
                 "--val-views", "1", "--no-progress"]) == 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["far_levels"] >= 4
    side = float(np.max(np.diff(load_dataset(root, "train").scene_bbox, axis=0)))
    assert cfg["render_step"] == pytest.approx(side / 200)          # resolved, then recorded
    tree_file = tmp_path / "tree.npz"
    assert main(["extract", str(run), "--out", str(tree_file), "--grid", "16", "--far-grid",
                 "8", "--samples", "1", "--bbox", "fixed", "--masking", "sigma",
                 "--mask-alpha-thresh", "1e-12", "--no-eval", "--no-progress"]) == 0
    info = json.loads((tmp_path / "tree.extract.json").read_text())
    tree = load_tree(tree_file)
    inner = np.asarray(info["inner_box"]["radius"])
    assert np.allclose(tree.radius, inner * 2 ** info["far_levels"])
    assert len(info["shell_leaves"]) == info["far_levels"] and sum(info["shell_leaves"]) > 0
    o, d = c.rays(0)
    out = render_rays(tree, o.reshape(-1, 3), d.reshape(-1, 3))
    assert np.isfinite(out.rgb.numpy()).all()


def test_the_torch_twin_draws_the_shells_as_the_kernel():
    _, grown, _, cams = room_trees()
    o, d = cams.rays(3)
    a = render_rays(grown, o, d, backend="numba")
    b = render_rays(grown, o, d, backend="torch")
    assert np.abs(a.rgb.numpy() - b.rgb.numpy()).max() < 1e-4
    assert np.abs(a.depth.numpy() - b.depth.numpy()).max() < 1e-3


def test_process_made_360_datasets_are_captures_of_a_place(tmp_path):
    """``process`` writes 360° photos as nerfstudio files with its ``plenoctree_transform``:
    those train a far field; other nerfstudio / instant-ngp files (fox) do not."""
    from plenoctree.datasets import load_dataset
    from plenoctree.datasets.nerfstudio import write_nerfstudio

    c2w = np.tile(np.eye(4), (8, 1, 1))
    c2w[:, 0, 3] = np.linspace(-1, 1, 8)
    imgs = np.full((8, 8, 8, 3), 128, np.uint8)
    k = (8.0, 8.0, 4.0, 4.0)
    ngp = write_nerfstudio(tmp_path / "ngp", c2w, imgs, k, extra={"aabb_scale": 4})
    mine = write_nerfstudio(tmp_path / "mine", c2w, imgs, k,
                            extra={"plenoctree_transform": np.eye(4).tolist()})
    assert not load_dataset(ngp, "train").unbounded
    assert load_dataset(mine, "train").unbounded


def test_validation_rows_keep_a_pass_inside_its_share():
    from plenoctree.nerf.training import VAL_PIXELS, val_row_stride

    assert val_row_stride(5 * 100 * 100, 100) == 1                     # small views: all rows
    assert val_row_stride(5 * 480 * 270, 270) == math.ceil(5 * 480 * 270 / VAL_PIXELS)
    # a pass of 60 s for a 120-s interval is 5x its 10 % share: 5x fewer rows next time
    assert val_row_stride(5 * 480 * 270, 270, 3, 60.0, 120.0) == 15
    assert val_row_stride(5 * 480 * 270, 270, 3, 6.0, 120.0) == 3      # inside: unchanged
    assert val_row_stride(5 * 480 * 270, 270, 30, 600.0, 120.0) == 270 // 8


def test_shells_leave_thin_fog_empty():
    """Cells the filter keeps but too thin to change a ray (opacity < min_alpha) stay empty:
    a fog of opacity 0.005 per cell between the box and the walls adds no leaf."""
    room = _room_field()

    def density(x):
        r = np.abs(x).max(-1)
        return np.where((r > 2.0) & (r < 3.0), 0.02, room.density(x))

    foggy = AnalyticField(density, room._coeffs, sh_degree=0, scene_bbox=BOX)
    cams = _inward_cameras()
    box = tree_from_grid(np.zeros((4, 4, 4, 4), np.float32), np.zeros((4, 4, 4), bool) | (
        np.arange(4)[:, None, None] == 1), 0.0, 1.0, "SH1")
    kept = {a: add_shells(box, foggy, cams, 2, ShellOptions(grid=32, min_alpha=a))[1]
            for a in (0.0, 0.01)}
    assert kept[0.0]["shell_leaves"][1] > 2 * kept[0.01]["shell_leaves"][1]
    walls = add_shells(box, room, cams, 2, ShellOptions(grid=32))[1]
    assert kept[0.01]["shell_leaves"][1] == walls["shell_leaves"][1]
