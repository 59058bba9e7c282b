"""Real SH / SG bases: golden values in the svox sign convention, orthonormality, numpy/torch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from plenoctree import sh
from plenoctree.sh import eval_sg_bases, eval_sh_bases, num_sh_bases, sh_degree_from_bases

PI = math.pi


def _reference_sh(d: np.ndarray) -> np.ndarray:
    """All 25 bases written out from the closed-form normalisations (independent of sh.py)."""
    x, y, z = d
    c0 = 1.0 / (2.0 * math.sqrt(PI))
    c1 = math.sqrt(3.0 / (4.0 * PI))
    return np.array([
        c0,
        -c1 * y, c1 * z, -c1 * x,
        # degree 2
        math.sqrt(15 / PI) / 2 * x * y,
        -math.sqrt(15 / PI) / 2 * y * z,
        math.sqrt(5 / PI) / 4 * (2 * z * z - x * x - y * y),
        -math.sqrt(15 / PI) / 2 * x * z,
        math.sqrt(15 / PI) / 4 * (x * x - y * y),
        # degree 3
        -math.sqrt(35 / (2 * PI)) / 4 * y * (3 * x * x - y * y),
        math.sqrt(105 / PI) / 2 * x * y * z,
        -math.sqrt(21 / (2 * PI)) / 4 * y * (4 * z * z - x * x - y * y),
        math.sqrt(7 / PI) / 4 * z * (2 * z * z - 3 * x * x - 3 * y * y),
        -math.sqrt(21 / (2 * PI)) / 4 * x * (4 * z * z - x * x - y * y),
        math.sqrt(105 / PI) / 4 * z * (x * x - y * y),
        -math.sqrt(35 / (2 * PI)) / 4 * x * (x * x - 3 * y * y),
        # degree 4
        3 * math.sqrt(35 / PI) / 4 * x * y * (x * x - y * y),
        -3 * math.sqrt(35 / (2 * PI)) / 4 * y * z * (3 * x * x - y * y),
        3 * math.sqrt(5 / PI) / 4 * x * y * (7 * z * z - 1),
        -3 * math.sqrt(5 / (2 * PI)) / 4 * y * z * (7 * z * z - 3),
        3 / (16 * math.sqrt(PI)) * (35 * z ** 4 - 30 * z * z + 3),
        -3 * math.sqrt(5 / (2 * PI)) / 4 * x * z * (7 * z * z - 3),
        3 * math.sqrt(5 / PI) / 8 * (x * x - y * y) * (7 * z * z - 1),
        -3 * math.sqrt(35 / (2 * PI)) / 4 * x * z * (x * x - 3 * y * y),
        3 * math.sqrt(35 / PI) / 16 * (x ** 4 - 6 * x * x * y * y + y ** 4),
    ])


GOLDEN_DIRS = [
    (0.0, 0.0, 1.0),
    (1.0, 0.0, 0.0),
    (0.0, 1.0, 0.0),
    tuple(np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)),
    tuple(np.array([-0.3, 0.5, -0.8]) / math.sqrt(0.98)),
]


def test_constants_match_closed_forms():
    assert sh.SH_C0 == pytest.approx(1 / (2 * math.sqrt(PI)), rel=1e-15)
    assert sh.SH_C1 == pytest.approx(math.sqrt(3 / (4 * PI)), rel=1e-15)
    assert sh.SH_C2[2] == pytest.approx(math.sqrt(5 / PI) / 4, rel=1e-15)
    assert sh.SH_C3[3] == pytest.approx(math.sqrt(7 / PI) / 4, rel=1e-15)
    assert sh.SH_C4[4] == pytest.approx(3 / (16 * math.sqrt(PI)), rel=1e-15)


@pytest.mark.parametrize("d", GOLDEN_DIRS)
def test_golden_values_all_degrees(d):
    ref = _reference_sh(np.array(d))
    out = eval_sh_bases(4, np.array(d, dtype=np.float64))
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-14)
    # lower degrees are prefixes of the higher ones
    for deg in range(4):
        np.testing.assert_allclose(eval_sh_bases(deg, np.array(d)), ref[: (deg + 1) ** 2], atol=1e-14)


def test_pinned_numbers_sign_convention():
    # +z: Y2 = +C1, Y6 = 2*C2[2], Y12 = 2*C3[3], Y20 = 8*C4[4]; every other basis is 0
    out = eval_sh_bases(4, np.array([0.0, 0.0, 1.0]))
    expect = np.zeros(25)
    expect[[0, 2, 6, 12, 20]] = [0.28209479177387814, 0.4886025119029199, 0.6307831305050401,
                                 0.7463526651802308, 0.8462843753216345]
    np.testing.assert_allclose(out, expect, atol=1e-14)
    # +x: Y3 = -C1 (svox sign), +y: Y1 = -C1
    assert eval_sh_bases(1, np.array([1.0, 0, 0]))[3] == pytest.approx(-0.4886025119029199)
    assert eval_sh_bases(1, np.array([0, 1.0, 0]))[1] == pytest.approx(-0.4886025119029199)
    # (1,2,3)/sqrt(14): Y4 = C2[0]*2/14, Y10 = C3[1]*6/14^1.5
    d = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    out = eval_sh_bases(3, d)
    assert out[4] == pytest.approx(1.0925484305920792 * 2 / 14, rel=1e-12)
    assert out[10] == pytest.approx(2.890611442640554 * 6 / 14 ** 1.5, rel=1e-12)


def _sphere_quadrature(n_theta: int = 24, n_phi: int = 48):
    """Gauss-Legendre in cos(theta) x uniform phi: exact for polynomials of degree < 2*n_theta."""
    u, wu = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) * 2 * PI / n_phi
    cu, cp = np.meshgrid(u, phi, indexing="ij")
    s = np.sqrt(1 - cu ** 2)
    dirs = np.stack([s * np.cos(cp), s * np.sin(cp), cu], -1).reshape(-1, 3)
    w = (wu[:, None] * np.full(n_phi, 2 * PI / n_phi)[None]).reshape(-1)
    return dirs, w


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_orthonormal_quadrature(degree):
    dirs, w = _sphere_quadrature()
    Y = eval_sh_bases(degree, dirs)
    gram = (Y * w[:, None]).T @ Y
    np.testing.assert_allclose(gram, np.eye(num_sh_bases(degree)), atol=1e-12)


def test_orthonormal_monte_carlo():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Y = eval_sh_bases(4, d)
    gram = Y.T @ Y * (4 * PI / len(d))
    np.testing.assert_allclose(gram, np.eye(25), atol=2e-2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_matches_numpy(dtype):
    rng = np.random.default_rng(1)
    d = rng.normal(size=(7, 5, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    for deg in range(5):
        t = eval_sh_bases(deg, torch.tensor(d, dtype=dtype))
        assert isinstance(t, torch.Tensor) and t.dtype == dtype and t.shape == (7, 5, (deg + 1) ** 2)
        n = eval_sh_bases(deg, d)
        assert isinstance(n, np.ndarray) and n.dtype == np.float64
        tol = 1e-6 if dtype == torch.float32 else 1e-13
        np.testing.assert_allclose(t.numpy(), n, atol=tol)
    assert eval_sh_bases(3, d.astype(np.float32)).dtype == np.float32


def test_torch_gradcheck():
    d = torch.nn.functional.normalize(torch.randn(6, 3, dtype=torch.float64), dim=-1)
    d.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: eval_sh_bases(4, x), (d,))


def test_shape_and_degree_errors():
    with pytest.raises(ValueError, match="shape"):
        eval_sh_bases(2, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="shape"):
        eval_sh_bases(2, torch.zeros(4))
    with pytest.raises(ValueError, match="degree"):
        eval_sh_bases(5, np.zeros((4, 3)))
    with pytest.raises(ValueError, match="degree"):
        eval_sh_bases(-1, np.zeros((4, 3)))
    with pytest.raises(TypeError):
        eval_sh_bases(1, [[0.0, 0.0, 1.0]])
    assert [num_sh_bases(d) for d in range(5)] == [1, 4, 9, 16, 25]
    assert [sh_degree_from_bases(n) for n in (1, 4, 9, 16, 25)] == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError):
        sh_degree_from_bases(10)


def test_sg_bases():
    mu = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    lam = np.array([2.0, 5.0, 0.5])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    out = eval_sg_bases(mu, lam, d)
    expect = np.array([
        [1.0, math.exp(-5.0), math.exp(-0.5)],
        [math.exp(-2.0), math.exp(-5.0), math.exp(-1.0)],
    ]) / 3
    np.testing.assert_allclose(out, expect, rtol=1e-12)
    t = eval_sg_bases(torch.tensor(mu), torch.tensor(lam), torch.tensor(d, dtype=torch.float32))
    assert t.dtype == torch.float32 and t.shape == (2, 3)
    np.testing.assert_allclose(t.numpy(), expect, rtol=1e-6)
    with pytest.raises(ValueError, match="sharpness"):
        eval_sg_bases(mu, lam[:2], d)
    with pytest.raises(ValueError, match="lobe_axes"):
        eval_sg_bases(mu[:, :2], lam, d)
