"""The NeRF renderers: closed forms, wave marching vs one pass, early termination, images."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from plenoctree.nerf.config import ModelConfig, preset
from plenoctree.nerf.model import NeRFModel
from plenoctree.nerf.renderer import (RayBatch, RenderMode, _march_waves,
                                      render_rays_hierarchical, render_rays_occupancy)
from plenoctree.nerf.sampling import MarchGrid, MarchRays

BBOX = np.array([[-1.5] * 3, [1.5] * 3], np.float32)


class Ball(nn.Module):
    """σ = s inside a ball of radius rad, colour sigmoid(k) constant: chords are closed-form."""

    basis, basis_dim = "sh", 1

    def __init__(self, s=3.0, rad=0.8, k=(1.0, -1.0, 0.0)):
        super().__init__()
        self.s, self.rad = s, rad
        self.k = nn.Parameter(torch.tensor(k))

    def density(self, p):
        return self.s * (p.norm(dim=-1) < self.rad).float()

    def forward(self, p, d=None):
        return self.density(p), self.k.expand(len(p), 3) / 0.28209479177387814

    def colors(self, coeffs, d):
        return torch.sigmoid(coeffs * 0.28209479177387814)


def _model_with(field, occ_res=32):
    model = NeRFModel(ModelConfig(grid_levels=2, grid_max_res=32, grid_log2_table=8,
                                  net_width=8), BBOX, occ_res=occ_res)
    model.fine = field
    return model


def _rays(n, seed=0, spread=0.6):
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, 0.0, 4.0]).expand(n, 3).clone()
    tgt = (torch.rand((n, 3), generator=g) - 0.5) * 2 * spread
    tgt[:, 2] = 0
    d = tgt - o
    return o, d / d.norm(dim=-1, keepdim=True), tgt


def test_occupancy_renderer_matches_closed_form():
    cfg = preset("cpu")
    cfg.render_step = 0.002
    ball = Ball()
    model = _model_with(ball)
    o, d, tgt = _rays(64)
    out = render_rays_occupancy(model, RayBatch(o, d, 2.0, 6.0, torch.ones(3)), cfg,
                                RenderMode(train=False, stop_thresh=0.0))
    # chord length of each ray through the ball
    b = (o * d).sum(-1)
    disc = b * b - (o * o).sum(-1) + ball.rad ** 2
    chord = 2 * torch.sqrt(disc.clamp(min=0))
    alpha = 1 - torch.exp(-ball.s * chord)
    torch.testing.assert_close(out["acc"], alpha, atol=0.02, rtol=0)
    c = torch.sigmoid(ball.k.detach())
    torch.testing.assert_close(out["rgb"], alpha[:, None] * c + (1 - alpha[:, None]),
                               atol=0.02, rtol=0)
    hit = alpha > 0.5
    t_in = -b - torch.sqrt(disc.clamp(min=0))
    assert (out["depth"][hit] > t_in[hit] - 0.01).all()


def test_waves_with_gradients_equal_the_gradient_free_pass():
    cfg = preset("cpu")
    model = NeRFModel(ModelConfig(grid_levels=4, grid_base_res=4, grid_max_res=64,
                                  grid_log2_table=12, net_width=16), BBOX, occ_res=16)
    torch.manual_seed(0)
    with torch.no_grad():
        model.fine.encoder.table.uniform_(-1, 1)
    o, d, _ = _rays(300, 1, spread=1.2)
    t_min = torch.full((300,), 2.5)
    t_max = 2.5 + torch.rand(300) * 2.0          # some rays end within the first wave
    jit = torch.rand(300)
    occ = model.occupancy
    args = (model.fine, MarchRays(o, d, t_min, t_max, jit), MarchGrid(0.02, occ.mask, occ.bbox))
    ref = _march_waves(*args, RenderMode(train=False, stop_thresh=1e-3), budget=1 << 16)
    small = _march_waves(*args, RenderMode(train=False, stop_thresh=1e-3), budget=300 * 16)
    tr = _march_waves(*args, RenderMode(train=True, stop_thresh=1e-3), budget=300 * 16)
    for k in ("rgb", "acc", "dsum"):
        torch.testing.assert_close(small[k], ref[k], atol=2e-5, rtol=1e-4)
        torch.testing.assert_close(tr[k].detach(), ref[k], atol=2e-5, rtol=1e-4)
    assert tr["complete"].all() and ref["n_samples"] > 300 * 16
    tr["rgb"].sum().backward()
    assert model.fine.encoder.table.grad.abs().sum() > 0
    # a sample budget cuts rays off and says which
    cut = _march_waves(*args, RenderMode(train=True, stop_thresh=1e-3, max_samples=300 * 16),
                       budget=300 * 16)
    assert not cut["complete"].all() and cut["complete"].any()


def test_early_termination_changes_little():
    cfg = preset("cpu")
    cfg.render_step = 0.005
    model = _model_with(Ball(s=40.0))
    o, d, _ = _rays(100, 2)
    rays = RayBatch(o, d, 2.0, 6.0, torch.ones(3))
    full = render_rays_occupancy(model, rays, cfg, RenderMode(stop_thresh=0))
    stop = render_rays_occupancy(model, rays, cfg, RenderMode(stop_thresh=1e-3))
    assert stop["n_samples"] < 0.75 * full["n_samples"]
    assert (stop["rgb"] - full["rgb"]).abs().max() < 2e-3


def test_training_render_has_gradients_and_jitter():
    cfg = preset("cpu")
    model = _model_with(Ball())
    o, d, _ = _rays(50, 3)
    g = torch.Generator().manual_seed(0)
    rays, mode = RayBatch(o, d, 2.0, 6.0, torch.ones(3)), RenderMode(train=True, generator=g)
    a = render_rays_occupancy(model, rays, cfg, mode)
    b = render_rays_occupancy(model, rays, cfg, mode)
    assert a["complete"].all() and not torch.equal(a["depth"], b["depth"])
    a["rgb"].sum().backward()
    assert ball_grad(model) != 0


def ball_grad(model):
    return float(model.fine.k.grad.abs().sum())


def test_hierarchical_renderer_matches_closed_form():
    cfg = preset("paper")
    cfg.n_coarse, cfg.n_fine = 256, 256
    ball = Ball(s=2.0)
    model = _model_with(ball, occ_res=0)
    o, d, _ = _rays(32, 4)
    out = render_rays_hierarchical(model, RayBatch(o, d, 2.0, 6.0, torch.ones(3)), cfg,
                                   RenderMode(train=False))
    b = (o * d).sum(-1)
    disc = b * b - (o * o).sum(-1) + ball.rad ** 2
    alpha = 1 - torch.exp(-ball.s * 2 * torch.sqrt(disc.clamp(min=0)))
    torch.testing.assert_close(out["acc"], alpha, atol=0.03, rtol=0)
    assert out["rgb_coarse"].shape == (32, 3) and out["n_samples"] == 32 * (256 + 512)
