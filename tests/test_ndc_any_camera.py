"""Any camera draws a forward-facing (NDC) tree: ``to_ndc_rays(..., clip=True)``, the rule of
every view of a tree (``tree.ndc.apply``: the viewer, ``render``, videos).

- a ray that never reaches the NDC volume (a camera in front of the near plane looking up +z
  or sideways) is a miss ray: it draws the background; nothing else misses;
- every other NDC ray is the image of the world ray: its points map back onto the world ray,
  in front of the camera, in order; a camera past the near plane starts where it stands;
- rays NeRF's rule covers are bitwise those of a dataset (``ndc_clip=False``), which still
  refuses a ray that does not point down -z;
- the numba kernel's per-pixel rays and the torch sampler's equal ``Cameras.rays``; the numba
  image equals the torch twin's; the viewer's ``/frame`` answers every such camera.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from PIL import Image

from plenoctree.datasets import Cameras
from plenoctree.datasets.ndc import MISS_ORIGIN, to_ndc_rays
from plenoctree.errors import ConfigError
from plenoctree.octree.ndc import NDCSpace
from plenoctree.render import RenderOptions, render_image, render_rays
from plenoctree.render._render_numba import _camera_ray, pack_cameras
from nerf_fixtures import ff_tree
from viewer_http import get

SPACE = NDCSpace(64, 48, 50.0, 50.0, 1.0)
W, H, F = 64, 48, 50.0

#: name -> (yaw degrees about +y, pitch degrees about x, camera centre)
POSES = {
    "reference": (0.0, 0.0, (0.0, 0.0, 0.0)),
    "turned 20 degrees": (20.0, 0.0, (0.0, 0.0, 0.0)),
    "turned 70 degrees": (70.0, 5.0, (0.1, -0.05, 0.2)),
    "sideways": (90.0, 0.0, (0.0, 0.0, 0.0)),
    "turned away": (180.0, 10.0, (0.1, 0.0, 0.0)),
    "looking up": (0.0, 80.0, (0.0, 0.0, 0.3)),
    "past the near plane": (10.0, -3.0, (0.05, 0.02, -1.3)),
    "past the near plane, looking back": (160.0, 0.0, (0.0, 0.0, -3.0)),
}


def _c2w(yaw: float, pitch: float, pos) -> np.ndarray:
    y, p = math.radians(yaw), math.radians(pitch)
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    m = np.eye(4)
    m[:3, :3] = ry @ rx
    m[:3, 3] = pos
    return m


def _cams(name: str, ndc: bool = True) -> Cameras:
    cams = Cameras(_c2w(*POSES[name])[None].astype(np.float32), F, F, W / 2, H / 2, W, H)
    return SPACE.apply(cams) if ndc else cams


@pytest.mark.parametrize("name", sorted(POSES))
def test_ndc_rays_of_any_camera_are_the_world_rays(name):
    cams, world = _cams(name), _cams(name, ndc=False)
    o, d = cams.rays(0)
    wo, wd = (a.astype(np.float64) for a in world.rays(0))
    miss = o[..., 2] > 1e3
    should_miss = (wo[..., 2] > -SPACE.near) & (wd[..., 2] >= 0)
    np.testing.assert_array_equal(miss, should_miss)
    np.testing.assert_array_equal(o[miss], np.broadcast_to(MISS_ORIGIN, o[miss].shape))
    np.testing.assert_array_equal(d[miss], np.broadcast_to((0, 0, 1), d[miss].shape))
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-6)
    if name == "turned away":
        assert miss.all()
    if name in ("reference", "past the near plane"):
        assert not miss.any()
    hit = ~miss
    if not hit.any():
        return
    o, d, wo, wd = o[hit].astype(np.float64), d[hit].astype(np.float64), wo[hit], wd[hit]
    ts = []
    for s in (0.0, 0.02, 0.1):
        q = o + s * d
        keep = q[:, 2] < 0.999
        w = np.full_like(q, np.nan)
        w[keep] = SPACE.ndc_to_world(q[keep])
        rel = w - wo
        t = np.einsum("ij,ij->i", rel, wd)                       # along the world ray
        off = np.linalg.norm(rel - t[:, None] * wd, axis=-1)     # off it
        assert np.nanmax(off / np.maximum(1.0, np.abs(t))) < 2e-3, (name, s)
        ts.append(t)
    assert np.nanmin(ts[0]) > -1e-4                              # never behind the camera
    assert (ts[1] > ts[0] - 1e-6)[~np.isnan(ts[1])].all() and (ts[2] > ts[1])[~np.isnan(ts[2])].all()
    if POSES[name][2][2] <= -SPACE.near:                         # starts where it stands
        np.testing.assert_allclose(o, np.broadcast_to(SPACE.world_to_ndc(wo[0]), o.shape),
                                   rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", sorted(POSES))
def test_numba_and_torch_rays_equal_the_cameras_rays(name):
    cams = _cams(name)
    o, d = cams.rays(0)
    cam = pack_cameras(cams, [0])[0]
    got = np.array([[_camera_ray(cam, u, v) for u in range(W)] for v in range(H)], np.float32)
    np.testing.assert_array_equal(got[..., :3], o)
    np.testing.assert_array_equal(got[..., 3:], d)
    rows, cols = torch.tensor([0, 5, 24, 47, 47]), torch.tensor([0, 63, 32, 0, 63])
    to, td = cams.pixel_rays(torch.zeros(5, dtype=torch.long), cols, rows)
    np.testing.assert_allclose(to.numpy(), o[rows, cols], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(td.numpy(), d[rows, cols], rtol=1e-6, atol=1e-6)


def test_dataset_rays_are_unchanged_and_still_strict():
    plain = Cameras(_c2w(*POSES["turned 70 degrees"])[None].astype(np.float32), F, F, W / 2,
                    H / 2, W, H, ndc=True, ndc_ref=(2 * F / W, 2 * F / H))
    with pytest.raises(ConfigError, match="do not point down"):
        plain.rays(0)
    ref = Cameras(np.eye(4, dtype=np.float32)[None], F, F, W / 2, H / 2, W, H, ndc=True)
    o1, d1 = ref.rays(0)
    o2, d2 = SPACE.apply(ref).rays(0)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(d1, d2)
    with pytest.raises(ConfigError, match="normalize"):
        to_ndc_rays(np.zeros((1, 3)), np.array([[0, 0, -1.0]]), F, F, W, H, normalize=False,
                    clip=True)
    with pytest.raises(ConfigError, match="NaN or infinite"):
        to_ndc_rays(np.zeros((1, 3)), np.array([[0, np.nan, -1.0]]), F, F, W, H, clip=True)


@pytest.fixture(scope="module")
def ff(tmp_path_factory):
    _, tree, path = ff_tree(tmp_path_factory.mktemp("ffany"))
    return tree, path


@pytest.mark.parametrize("name", sorted(POSES))
def test_any_camera_renders_and_the_kernel_equals_the_twin(ff, name):
    tree = ff[0]
    cams = tree.ndc.apply(Cameras(_c2w(*POSES[name])[None].astype(np.float32), 40.0, 40.0, 24.0,
                                  18.0, 48, 36))
    opts = RenderOptions(background=(0.2, 0.4, 0.6))
    fast = render_image(tree, cams, 0, opts, backend="numba")
    o, d = cams.rays(0)
    twin = render_rays(tree, torch.from_numpy(o), torch.from_numpy(d), opts, backend="torch")
    np.testing.assert_allclose(fast.rgb.numpy(), twin.rgb.numpy(), atol=2e-4)
    miss = o[..., 2] > 1e3
    np.testing.assert_allclose(fast.rgb.numpy()[miss], np.broadcast_to((0.2, 0.4, 0.6),
                                                                       (int(miss.sum()), 3)))
    if name in ("reference", "turned 20 degrees", "past the near plane"):
        assert fast.alpha.numpy().max() > 0.5                     # the scene is there


def test_viewer_frame_answers_a_camera_turned_away(ff):
    from plenoctree.viewer import ViewerServer

    c2w = _c2w(*POSES["turned away"])
    q = "&".join([f"w=48&h=36&fx=40&fy=40&cx=24&cy=18&bg=0,0,0&q=95",
                  "c2w=" + ",".join(repr(float(v)) for v in c2w.reshape(-1))])
    with ViewerServer(ff[1], port=0, render="cpu") as srv:
        status, _, body = get(srv.port, "/frame?" + q, None, timeout=120)
    assert status == 200, body
    img = np.asarray(Image.open(io.BytesIO(body)).convert("RGB"))
    assert img.shape == (36, 48, 3) and img.max() <= 2                # the black background
