"""The visibility (max ray weight) filter: numba kernel vs torch twin, closed forms, masks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plenoctree.convert.grid import GridSpec
from plenoctree.convert.visibility import (auto_ray_scale, candidates, max_ray_weights,
                                           rescale_cameras, sigma_mask, unseen_cells,
                                           weight_mask)
from plenoctree.datasets import Cameras
from plenoctree.datasets.procedural import look_at
from plenoctree.errors import ConfigError


def _random_case(seed: int, res: int = 12):
    rng = np.random.default_rng(seed)
    spec = GridSpec.make(rng.uniform(-0.3, 0.3, 3), rng.uniform(0.6, 1.4, 3), res)
    occupied = rng.random((res,) * 3) < 0.3
    sigma = (occupied * rng.exponential(6.0, (res,) * 3)).astype(np.float32)
    n = 600
    o = rng.normal(size=(n, 3)) * 3.0
    d = spec.center - o + rng.normal(size=(n, 3)) * 0.6
    # rays starting inside the box, axis-aligned rays, rays along grid planes, misses
    o[:60] = spec.center + rng.uniform(-0.5, 0.5, (60, 3)) * spec.radius
    d[60:90] = 0.0
    d[60:90, rng.integers(0, 3, 30)] = rng.choice([-1.0, 1.0], 30)
    o[60:90] = spec.center + rng.uniform(-0.9, 0.9, (30, 3)) * spec.radius - 4.0 * d[60:90]
    o[90:100] = spec.lo + spec.cell * 3.0 - np.array([5.0, 0, 0])       # on cell planes
    d[90:100] = [1.0, 0.0, 0.0]
    d[100:110] = o[100:110]                                            # pointing away: misses
    return spec, sigma, o.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numba_matches_torch_twin(seed):
    spec, sigma, o, d = _random_case(seed)
    cand = candidates(sigma, spec, 1e-3)
    a = max_ray_weights(sigma, spec, cand, o, d, backend="numba").max(0)
    b = max_ray_weights(sigma, spec, cand, o, d, backend="torch").max(0)
    assert (b > 0).sum() > 50                     # the rays do hit many candidate cells
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def test_numba_accumulates_over_calls_like_one_call():
    spec, sigma, o, d = _random_case(3)
    cand = candidates(sigma, spec, 1e-3)
    once = max_ray_weights(sigma, spec, cand, o, d, backend="numba").max(0)
    out = max_ray_weights(sigma, spec, cand, o[:300], d[:300], backend="numba")
    max_ray_weights(sigma, spec, cand, o[300:], d[300:], backend="numba", out=out)
    np.testing.assert_array_equal(out.max(0), once)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_closed_form_two_cells_along_x(backend):
    """A ray along x through cells (1, 2, 2) then (3, 2, 2): w1 = 1 - e^{-σ1 δ},
    w2 = e^{-σ1 δ} (1 - e^{-σ2 δ}); cells behind T < τ are not reached."""
    res = 8
    spec = GridSpec.make(0.0, [1.0, 2.0, 0.5], res)           # cell sides 0.25, 0.5, 0.125
    sigma = np.zeros((res,) * 3, np.float32)
    sigma[1, 2, 2], sigma[3, 2, 2], sigma[5, 2, 2] = 2.0, 5.0, 1000.0
    sigma[6, 2, 2] = 3.0                                       # hidden behind the opaque cell
    cand = candidates(sigma, spec, 1e-3)
    y = spec.lo[1] + 2.3 * spec.cell[1]
    z = spec.lo[2] + 2.6 * spec.cell[2]
    o = np.array([[-3.0, y, z]], np.float32)
    d = np.array([[2.0, 0.0, 0.0]], np.float32)                # not unit: normalised inside
    w = max_ray_weights(sigma, spec, cand, o, d, backend=backend).max(0)
    got = dict(zip(map(tuple, np.argwhere(cand.index >= 0)), w[cand.index[cand.index >= 0]]))
    dx = spec.cell[0]
    t1 = math.exp(-2.0 * dx)
    t2 = t1 * math.exp(-5.0 * dx)
    assert got[(1, 2, 2)] == pytest.approx(1 - t1, rel=1e-6)
    assert got[(3, 2, 2)] == pytest.approx(t1 * (1 - math.exp(-5.0 * dx)), rel=1e-6)
    assert got[(5, 2, 2)] == pytest.approx(t2 * (1 - math.exp(-1000.0 * dx)), rel=1e-6)
    assert got[(6, 2, 2)] == 0.0                               # T < 1e-3 before it: stopped


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_ray_starting_inside_a_cell_counts_only_the_part_ahead(backend):
    res = 4
    spec = GridSpec.make(0.0, 1.0, res)                        # cells 0.5 wide
    sigma = np.zeros((res,) * 3, np.float32)
    sigma[2, 1, 1] = 4.0
    cand = candidates(sigma, spec, 1e-4)
    o = np.array([[0.2, -0.25, -0.25]], np.float32)            # 0.3 before the cell's far side
    d = np.array([[1.0, 0.0, 0.0]], np.float32)
    w = max_ray_weights(sigma, spec, cand, o, d, backend=backend).max(0)
    assert w[cand.index[2, 1, 1]] == pytest.approx(1 - math.exp(-4.0 * 0.3), rel=1e-6)


def test_candidates_are_cells_that_can_reach_the_threshold():
    spec = GridSpec.make(0.0, 1.0, 4)
    diag = float(np.linalg.norm(spec.cell))
    tau = 0.01
    need = -math.log(1 - tau) / diag
    sigma = np.zeros((4, 4, 4), np.float32)
    sigma[0, 0, 0] = need * 1.01
    sigma[1, 1, 1] = need * 0.99
    cand = candidates(sigma, spec, tau)
    assert cand.flat.tolist() == [0]
    assert cand.index[0, 0, 0] == 0 and (cand.index >= 0).sum() == 1


def test_weight_and_sigma_masks():
    spec = GridSpec.make(0.0, 1.0, 4)
    sigma = np.zeros((4, 4, 4), np.float32)
    sigma[1, 2, 3] = 50.0
    sigma[0, 0, 1] = 0.1
    cand = candidates(sigma, spec, 1e-3)
    w = np.array([0.5] * cand.flat.size, np.float32)
    assert weight_mask(spec, cand, w, 0.01).sum() == cand.flat.size
    assert weight_mask(spec, cand, w, 0.6).sum() == 0
    with pytest.raises(ConfigError, match="below"):
        weight_mask(spec, cand, w, 1e-4)
    m = sigma_mask(sigma, spec, 0.01)                          # alpha(0.1 * 0.5) = 0.049
    assert m[1, 2, 3] and m[0, 0, 1] and m.sum() == 2
    assert sigma_mask(sigma, spec, 0.2).sum() == 1
    with pytest.raises(ConfigError):
        sigma_mask(sigma, spec, 1.5)


def test_auto_ray_scale_makes_pixels_no_wider_than_voxels():
    c2w = np.stack([look_at([4.0, 0, 0]), look_at([0, 4.0, 0])]).astype(np.float32)
    cams = Cameras(c2w, 40.0, 40.0, 16.0, 16.0, 32, 32)
    spec = GridSpec.make(0.0, 1.0, 64)                         # voxel 1/32, pixel 4/40 = 0.1
    s = auto_ray_scale(cams, spec)
    assert s == pytest.approx(0.1 * 32, rel=1e-6)
    big = rescale_cameras(cams, s)
    assert big.width == round(32 * s) and 4.0 / big.fx <= 1 / 32 * 1.02
    assert auto_ray_scale(cams, GridSpec.make(0.0, 1.0, 8)) == 1.0
    o, d = big.rays(0)
    o0, d0 = cams.rays(0)
    np.testing.assert_allclose(d[big.height // 2, big.width // 2], d0[16, 16], atol=0.02)


def _flat(spec, centers):
    """C-order flat indices of the cells holding ``centers``."""
    ijk = np.floor((np.asarray(centers, np.float64) - spec.lo) / spec.cell).astype(np.int64)
    return np.ravel_multi_index(ijk.T, (spec.res,) * 3)


def test_unseen_cells_golden_pinhole():
    # one camera at the origin looking down -z; its 4x2 image spans x/depth in [-1, 1] and
    # y/depth in [-0.5, 0.5]
    cams = Cameras(np.eye(4, dtype=np.float32)[None], 2.0, 2.0, 2.0, 1.0, 4, 2)
    spec = GridSpec.make([0.0, 0.0, -3.0], 4.0, 4)              # cells of side 2: centres ±1, ±3
    centers = [(1, 1, -4),        # x/depth 0.25, y/depth 0.25: in the image
               (-3, -1, -4),      # -0.75, -0.25: in
               (1, 3, -6),        # y/depth exactly 0.5: on the image's edge, in
               (3, 1, -2),        # x/depth 1.5: outside the image
               (1, 1, 0),         # level with the camera: not in front of it
               (-1, 3, -2)]       # y/depth 1.5: outside
    got = unseen_cells(spec, _flat(spec, centers), cams)
    assert got.tolist() == [False, False, False, True, True, True]
    # a second camera turned to look along +x sees the first's outside cell (3, 1, -2)
    c2w = np.stack([np.eye(4), look_at([-2.0, 1.0, -2.0], target=[3.0, 1.0, -2.0])])
    both = Cameras(c2w.astype(np.float32), 2.0, 2.0, 2.0, 1.0, 4, 2)
    assert unseen_cells(spec, _flat(spec, centers), both).tolist() == [
        False, False, False, False, True, True]
    assert unseen_cells(spec, np.zeros(0, np.int64), cams).shape == (0,)


def test_unseen_cells_ndc_are_those_outside_the_reference_image():
    # NDC space of the reference camera (identity pose): x', y' in [-1, 1] is its image, so
    # with that camera alone a cell is unseen exactly when its centre has |x'| or |y'| > 1;
    # centres outside NDC's depth range (-1, 1) are never reported
    cams = Cameras(np.eye(4, dtype=np.float32)[None], 30.0, 30.0, 20.0, 15.0, 40, 30,
                   ndc=True)
    spec = GridSpec.make([0.0, 0.0, 0.0], [2.0, 2.0, 1.5], 8)
    flat = np.arange(8 ** 3)
    c = spec.lo + (np.stack(np.unravel_index(flat, (8,) * 3), -1) + 0.5) * spec.cell
    want = (np.abs(c[:, :2]).max(1) > 1.0) & (np.abs(c[:, 2]) < 1.0)
    got = unseen_cells(spec, flat, cams)
    assert want.sum() > 100 and (~want).sum() > 100
    np.testing.assert_array_equal(got, want)
