"""Viewer page controls in real Chromium (Playwright, SwiftShader): first-view framing, reset,
training cameras (listed, drawn, jumped to), keyboard fly, field of view, hints, dismissable
errors, file:// message, opacity mode on white. Pictures with a right answer are compared with
the CPU renderer at 128 px (same tolerance as tests/test_viewer_browser.py)."""

from __future__ import annotations

import base64
import functools
import math
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from test_viewer_browser import CHROMIUM, FLAGS, _close, playwright_api  # noqa: F401 (skips)

from plenoctree.datasets.cameras import Cameras, generate_rays
from plenoctree.datasets.procedural import procedural_cameras, procedural_tree
from plenoctree.octree.io import save_tree
from plenoctree.render import RenderOptions, render_rays
from plenoctree.viewer import ViewerServer, export_web

SIZE = 128
FOV_X = 0.6911112070083618


@pytest.fixture(scope="module")
def browser():
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("ui")
    tree = procedural_tree(32)
    save_tree(tree, d / "proc.npz", precision="fp16")
    f = 0.5 * 64 / math.tan(0.5 * FOV_X)
    cams = Cameras(c2w=procedural_cameras(6, "random", seed=3).astype(np.float32), fx=f, fy=f,
                   cx=32.0, cy=32.0, width=64, height=64)
    return {"dir": d, "tree": tree.astype(np.float16).astype(np.float32), "path": d / "proc.npz",
            "cams": cams}


class _Static:
    """A plain static HTTP server over a folder (as a user would serve a bundle)."""

    def __init__(self, folder):
        handler = functools.partial(SimpleHTTPRequestHandler, directory=str(folder))
        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/"

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture(scope="module")
def bundle(scene, browser):
    out = export_web(scene["path"], scene["dir"] / "site", cameras=scene["cams"],
                     camera_names=[f"cam{i}" for i in range(6)])
    srv = _Static(out)
    page = browser.new_page(viewport={"width": 640, "height": 400})
    page.goto(srv.url)
    page.wait_for_function("window.viewer && window.viewer.state !== 'loading'", timeout=90_000)
    assert page.evaluate("window.viewer.state") == "ready", page.evaluate("window.viewer.message")
    yield page
    page.close()
    srv.close()


def _pixels(page, view) -> np.ndarray:
    page.evaluate("v => window.viewer.setView(v)", view)
    page.evaluate("window.viewer.render()")
    raw = base64.b64decode(page.evaluate("window.viewer.pixels()"))
    page.evaluate("window.viewer.clearView()")
    h, w = view["height"], view["width"]
    return np.frombuffer(raw, np.uint8).reshape(h, w, 4)[..., :3].astype(np.float64) / 255


def _cpu(tree, view, **opts) -> np.ndarray:
    c2w = np.asarray(view["c2w"], np.float32).reshape(4, 4)
    o, d = generate_rays(c2w, view["fx"], view["fy"], view["cx"], view["cy"], view["width"],
                         view["height"])
    return render_rays(tree, o, d, RenderOptions(**opts)).rgb.numpy()


def _view(page):
    return page.evaluate(f"window.viewer.currentView({SIZE}, {SIZE})")


def test_first_view_is_framed_like_the_training_cameras(bundle, scene):
    """Camera 0's direction at the cameras' median distance (all at 4), their fov, +z up."""
    view = _view(bundle)
    c0 = scene["cams"].c2w[0]
    np.testing.assert_allclose(np.reshape(view["c2w"], (4, 4)), c0, atol=2e-5)
    fy = 0.5 * SIZE / math.tan(0.5 * FOV_X)        # square images: vertical fov = horizontal
    assert view["fy"] == pytest.approx(fy, rel=1e-4)
    _close(_pixels(bundle, view), _cpu(scene["tree"], view), "first view")
    assert bundle.evaluate("window.viewer.cameras()") == 6
    assert bundle.locator("#camera_select option").count() == 6
    assert bundle.locator("#camera_select option").nth(2).inner_text() == "2: cam2"


def test_jump_to_training_camera_next_key_and_reset(bundle, scene):
    first = _view(bundle)
    bundle.evaluate("window.viewer.jumpToCamera(3)")
    view = _view(bundle)
    np.testing.assert_allclose(np.reshape(view["c2w"], (4, 4)), scene["cams"].c2w[3], atol=1e-6)
    _close(_pixels(bundle, view), _cpu(scene["tree"], view), "training camera 3")
    bundle.locator("#canvas").focus()
    bundle.keyboard.press("BracketRight")
    assert bundle.locator("#camera_select").input_value() == "4"
    np.testing.assert_allclose(np.reshape(_view(bundle)["c2w"], (4, 4)), scene["cams"].c2w[4],
                               atol=1e-6)
    bundle.keyboard.press("KeyR")                   # reset = the first view again
    np.testing.assert_allclose(_view(bundle)["c2w"], first["c2w"], atol=1e-6)
    bundle.evaluate("window.viewer.jumpToCamera(1)")
    bundle.locator("#reset_view").click()
    np.testing.assert_allclose(_view(bundle)["c2w"], first["c2w"], atol=1e-6)


def test_training_cameras_are_drawn_and_can_be_hidden(bundle):
    count = ("() => { const c = document.getElementById('overlay'); const d = c.getContext('2d')"
             ".getImageData(0, 0, c.width, c.height).data; let n = 0;"
             " for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }")
    bundle.evaluate("window.viewer.clearView(); window.viewer.render()")
    assert bundle.evaluate(count) > 50
    bundle.locator("#show_cameras").uncheck()
    bundle.evaluate("window.viewer.render()")
    assert bundle.evaluate(count) == 0
    bundle.locator("#show_cameras").check()


def test_keyboard_fly_turn_and_fov(bundle):
    bundle.evaluate("window.viewer.resetView()")
    bundle.locator("#canvas").focus()
    v0 = _view(bundle)
    eye0 = np.reshape(v0["c2w"], (4, 4))[:3, 3]
    fwd0 = -np.reshape(v0["c2w"], (4, 4))[:3, 2]
    bundle.keyboard.down("KeyW")
    bundle.wait_for_timeout(400)
    bundle.keyboard.up("KeyW")
    m1 = np.reshape(_view(bundle)["c2w"], (4, 4))
    step = m1[:3, 3] - eye0
    assert np.linalg.norm(step) > 0.05                       # moved ...
    np.testing.assert_allclose(step / np.linalg.norm(step), fwd0, atol=1e-4)   # ... forward
    np.testing.assert_allclose(m1[:3, :3], np.reshape(v0["c2w"], (4, 4))[:3, :3], atol=1e-5)
    bundle.keyboard.down("KeyE")
    bundle.wait_for_timeout(300)
    bundle.keyboard.up("KeyE")
    m2 = np.reshape(_view(bundle)["c2w"], (4, 4))
    up = (m2[:3, 3] - m1[:3, 3]) / np.linalg.norm(m2[:3, 3] - m1[:3, 3])
    np.testing.assert_allclose(up, m1[:3, 1], atol=1e-4)    # E: along the camera's up
    bundle.keyboard.down("ArrowLeft")
    bundle.wait_for_timeout(300)
    bundle.keyboard.up("ArrowLeft")
    m3 = np.reshape(_view(bundle)["c2w"], (4, 4))
    np.testing.assert_allclose(m3[:3, 3], m2[:3, 3], atol=1e-4)   # turning keeps the eye
    assert np.linalg.norm(m3[:3, 2] - m2[:3, 2]) > 0.05
    bundle.locator("#fov").fill("60")
    assert _view(bundle)["fy"] == pytest.approx(0.5 * SIZE / math.tan(math.radians(30)), rel=1e-6)
    bundle.evaluate("window.viewer.resetView()")


def test_control_hints_are_visible_and_toggle(bundle):
    hints = bundle.locator("#hints")
    assert hints.is_visible()
    box, stage = hints.bounding_box(), bundle.locator("#stage").bounding_box()
    assert box["y"] + box["height"] <= stage["y"] + stage["height"]      # above the fold
    assert "W A S D" in hints.inner_text()
    bundle.locator("#canvas").focus()
    bundle.keyboard.press("KeyH")
    assert not hints.is_visible()
    bundle.keyboard.press("KeyH")
    assert hints.is_visible()


def test_opacity_mode_shows_on_white(bundle, scene):
    view = _view(bundle)
    bundle.evaluate("window.viewer.setOptions({mode: 'alpha', background: [1, 1, 1]})")
    gpu = _pixels(bundle, view)
    bundle.evaluate("window.viewer.setOptions({mode: 'rgb'})")
    c2w = np.asarray(view["c2w"], np.float32).reshape(4, 4)
    o, d = generate_rays(c2w, view["fx"], view["fy"], view["cx"], view["cy"], SIZE, SIZE)
    alpha = render_rays(scene["tree"], o, d, RenderOptions()).alpha.numpy()
    assert np.abs(gpu - (1 - alpha)[..., None]).mean() <= 1 / 255      # black ink on white
    assert gpu.std() > 0.1


def test_bounding_sphere_framing_without_cameras(browser, scene):
    with ViewerServer(scene["path"], port=0) as srv:
        page = browser.new_page(viewport={"width": 640, "height": 400})
        page.goto(srv.url)
        page.wait_for_function("window.viewer && window.viewer.state !== 'loading'",
                               timeout=90_000)
        w, h = page.evaluate("[document.getElementById('canvas').clientWidth,"
                             " document.getElementById('canvas').clientHeight]")
        view = page.evaluate(f"window.viewer.currentView({w}, {h})")
        page.close()
    m = np.reshape(view["c2w"], (4, 4))
    tree = scene["tree"]
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    corners = tree.bbox[0] + corners * (tree.bbox[1] - tree.bbox[0])
    cam = (corners - m[:3, 3]) @ m[:3, :3]
    u = view["cx"] + view["fx"] * cam[:, 0] / -cam[:, 2]
    v = view["cy"] - view["fy"] * cam[:, 1] / -cam[:, 2]
    assert np.all(cam[:, 2] < 0) and np.all((u > 0) & (u < w) & (v > 0) & (v < h)), (u, v)
    # the bounding sphere just fits the vertical fov (5 % margin), not 2.6 r as before
    r = np.linalg.norm(tree.radius)
    dist = np.linalg.norm(m[:3, 3] - tree.center)
    assert dist == pytest.approx(1.05 * r / math.sin(0.5 * math.radians(40)), rel=1e-4)


def test_error_card_can_be_dismissed_and_the_canvas_works_again(browser, scene, tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip at all")
    with ViewerServer(scene["path"], port=0) as srv:
        page = browser.new_page(viewport={"width": 640, "height": 400})
        page.goto(srv.url)
        page.wait_for_function("window.viewer && window.viewer.state === 'ready'", timeout=90_000)
        view = _view(page)
        before = _pixels(page, view)
        page.set_input_files("#file", str(bad))
        page.wait_for_function("window.viewer.state === 'error'", timeout=30_000)
        assert page.locator("#message").is_visible()
        assert "bad.npz" in page.locator("#message").inner_text()
        page.locator("#message-close").click()
        assert not page.locator("#message").is_visible()
        assert page.evaluate("window.viewer.state") == "ready"
        after = _pixels(page, view)                          # the previous tree renders again
        np.testing.assert_array_equal(after, before)
        page.evaluate("window.viewer.jumpToCamera(0)")       # no cameras here: a no-op
        page.close()


def test_file_url_says_to_serve_the_folder(browser, scene):
    out = export_web(scene["path"], scene["dir"] / "site_file")
    page = browser.new_page()
    page.goto((out / "index.html").as_uri())
    page.wait_for_function("window.viewer && window.viewer.state === 'error'", timeout=30_000)
    msg = page.locator("#message")
    assert msg.is_visible()
    assert "web server" in msg.inner_text() and "http.server" in msg.inner_text()
    assert page.locator("#status").inner_text() == ""
    page.close()


def test_radiance_probe_matches_the_tree(bundle, scene):
    """The probe picks the max-weight leaf along the ray (checked by the same march in numpy)
    and its lumisphere shows sigmoid(sum k Y(-n)) for each sphere normal n."""
    from plenoctree.export import point_colors

    tree = scene["tree"]
    bundle.evaluate("window.viewer.resetView()")
    origin = np.array([0.05, 3.0, -0.15])             # from above onto the glossy sphere
    target = np.array([0.0, 0.35, -0.2])
    d = (target - origin) / np.linalg.norm(target - origin)
    S = 32
    hit = bundle.evaluate("([o, d, s]) => window.viewer.probeRay(o, d, s)",
                          [origin.tolist(), d.tolist(), S])
    assert hit is not None and hit["sigma"] > 0 and hit["weight"] > 0.05
    # the same uniform march in numpy
    o_t = tree.world_to_tree(origin)
    d_t = d * tree.invradius
    with np.errstate(divide="ignore"):
        a, b = (0 - o_t) / d_t, (1 - o_t) / d_t
    t0, t1 = max(0.0, np.minimum(a, b).max()), np.maximum(a, b).min()
    n = 2048
    t = t0 + (np.arange(n) + 0.5) * (t1 - t0) / n
    sig = np.maximum(tree.query(origin + t[:, None] * d)[:, -1], 0)
    alpha = 1 - np.exp(-sig * (t1 - t0) / n)
    T = np.concatenate([[1.0], np.cumprod(1 - alpha)[:-1]])
    w = T * alpha
    w[T <= 1e-3] = 0
    i = int(np.argmax(w))
    assert hit["weight"] == pytest.approx(w[i], rel=1e-3)
    want = tree.query(origin + t[i] * d)
    got = np.asarray(hit["coeffs"], np.float64).T.reshape(-1)        # [B][3] -> channel-major
    np.testing.assert_allclose(got, want[:-1], atol=1e-6)
    np.testing.assert_allclose(hit["point"], origin + hit["t"] * d if "t" in hit else
                               origin + t[i] * d, atol=1e-3)
    # lumisphere pixels
    img = np.frombuffer(base64.b64decode(hit["image"]), np.uint8).reshape(S, S, 4)
    rot = np.reshape(_view(bundle)["c2w"], (4, 4))[:3, :3]
    u = (np.arange(S) + 0.5) * 2 / S - 1
    x, y = np.meshgrid(u, -u)
    inside = x ** 2 + y ** 2 <= 1
    z = np.sqrt(np.clip(1 - x ** 2 - y ** 2, 0, 1))
    nrm = np.stack([x, y, z], -1)[inside] @ rot.T
    col = point_colors(tree, np.broadcast_to(want[:-1], (len(nrm), want.size - 1)), -nrm)
    assert np.abs(img[inside][:, :3].astype(float) - col * 255).max() <= 1.0
    assert (img[~inside][:, 3] == 0).all()
    assert np.ptp(img[inside][:, :3].astype(float), 0).max() > 5     # view-dependent colour


def test_alt_click_probes_the_scene(bundle):
    bundle.evaluate("window.viewer.resetView()")
    box = bundle.locator("#canvas").bounding_box()
    bundle.locator("#canvas").click(position={"x": box["width"] / 2, "y": box["height"] / 2},
                                    modifiers=["Alt"])
    info = bundle.evaluate("document.getElementById('probe_info').textContent")
    assert "sigma" in info, info
    assert bundle.locator("#probe_box").get_attribute("open") is not None


@pytest.fixture(scope="module")
def ff(tmp_path_factory):
    from plenoctree.datasets import load_dataset
    from plenoctree.datasets.forward_facing import forward_facing_tree, write_forward_facing_dataset

    d = tmp_path_factory.mktemp("ff")
    root = write_forward_facing_dataset(d / "ff", n_images=9, width=48, height=36, n_samples=64)
    tree = forward_facing_tree(root, 32)
    save_tree(tree, d / "ff.npz", precision="fp16")
    data = load_dataset(root, "train")
    assert data.cameras.ndc and tree.ndc is not None
    # the same scene in a box 4x deeper (extraction's --ndc-depth-stretch): every 4th depth
    # cell of the 32³ grid, centred in 32 cells along the stretched depth
    from plenoctree.datasets.forward_facing import forward_facing_grid
    from plenoctree.octree import Octree

    values, mask, center, radius = forward_facing_grid(root, 32)
    full = np.zeros(mask.shape + (4,), np.float32)
    full[mask] = values
    s_mask = np.zeros_like(mask)
    s_vals = np.zeros_like(full)
    s_mask[..., 12:20], s_vals[..., 12:20, :] = mask[..., 2::4], full[..., 2::4, :]
    stretched = Octree.from_grid(s_vals[s_mask], s_mask, center, radius * [1, 1, 4],
                                 data_format="RGBA")
    stretched.ndc = tree.ndc
    save_tree(stretched, d / "ff_stretched.npz", precision="fp16")
    return {"dir": d, "tree": tree.astype(np.float16).astype(np.float32), "path": d / "ff.npz",
            "cams": data.cameras, "stretched": stretched.astype(np.float16).astype(np.float32)}


def _open_bundle(browser, out):
    srv = _Static(out)
    page = browser.new_page(viewport={"width": 640, "height": 400})
    page.goto(srv.url)
    page.wait_for_function("window.viewer && window.viewer.state !== 'loading'", timeout=90_000)
    assert page.evaluate("window.viewer.state") == "ready", page.evaluate("window.viewer.message")
    return srv, page


@pytest.mark.parametrize("source", ["bundle_cameras", "tree_file", "svox_file", "plnz_file",
                                    "stretched_file"])
def test_ndc_forward_facing_tree_matches_cpu(browser, ff, source):
    """An LLFF (NDC) tree: the page maps world rays to NDC like Cameras(ndc=True).rays(), with
    the NDC space from the bundle's cameras or, without them, from the tree file itself
    (native header, svox ndc_config, .plnz header); also a box stretched 4x along depth (what
    extraction makes of a forward-facing scene: the rays start inside the box)."""
    from plenoctree.compression import compress, decompress, save_compressed
    from plenoctree.octree.io import export_svox

    tree, path = ff["tree"], ff["path"]
    if source == "svox_file":
        path = ff["dir"] / "ff_svox.npz"
        export_svox(tree, path)
    elif source == "plnz_file":
        path = ff["dir"] / "ff.plnz"
        ctree = compress(tree)
        save_compressed(ctree, path)
        tree = decompress(ctree)
    elif source == "stretched_file":
        tree, path = ff["stretched"], ff["dir"] / "ff_stretched.npz"
        assert tree.bbox[0, 2] < -1 and tree.bbox[1, 2] > 1     # NDC's [-1, 1] inside the box
    out = export_web(path, ff["dir"] / f"site_{source}", overwrite=True,
                     cameras=ff["cams"] if source == "bundle_cameras" else None)
    assert ("ndc" in (out / "config.json").read_text()) == (source == "bundle_cameras")
    srv, page = _open_bundle(browser, out)
    try:
        first = page.evaluate("window.viewer.currentView(48, 36)")
        np.testing.assert_allclose(np.reshape(first["c2w"], (4, 4)), np.eye(4), atol=1e-6)
        cams = ff["cams"]
        for i in (0, 3):
            fx, fy, cx, cy = cams.intrinsics(i)
            view = {"c2w": cams.c2w[i].reshape(-1).tolist(), "fx": fx, "fy": fy, "cx": cx,
                    "cy": cy, "width": cams.width, "height": cams.height}
            gpu = _pixels(page, view)
            o, d = cams.rays(i)
            cpu = render_rays(tree, o, d, RenderOptions()).rgb.numpy()
            diff = np.abs(gpu - np.clip(cpu, 0, 1))
            assert diff.mean() <= 1 / 255 and np.percentile(diff, 99) <= 3 / 255, \
                (i, diff.mean() * 255, np.percentile(diff, 99) * 255)
            assert gpu.std() > 0.05
        page.close()
    finally:
        srv.close()


def test_ndc_tree_any_camera_matches_cpu(browser, ff):
    """Cameras the NDC rays of a dataset cannot make: turned far from -z (part of the view
    misses the NDC volume and shows the background), turned away (all background), flown past
    the near plane (the rays start at the camera): the page equals the CPU renderer of the same
    camera (``tree.ndc.apply``: ``to_ndc_rays(clip=True)``)."""
    from test_ndc_any_camera import POSES, _c2w

    out = export_web(ff["path"], ff["dir"] / "site_any", overwrite=True, cameras=ff["cams"])
    srv, page = _open_bundle(browser, out)
    try:
        page.evaluate("window.viewer.setOptions({background: [0.2, 0.4, 0.6]})")
        cams = ff["cams"]
        fx, fy, cx, cy = cams.intrinsics(0)
        for name in ("turned 20 degrees", "turned away", "past the near plane",
                     "past the near plane, looking back"):
            c2w = _c2w(*POSES[name]).astype(np.float32)
            view = {"c2w": c2w.reshape(-1).tolist(), "fx": fx, "fy": fy, "cx": cx, "cy": cy,
                    "width": cams.width, "height": cams.height}
            gpu = _pixels(page, view)
            one = ff["tree"].ndc.apply(Cameras(c2w[None], fx, fy, cx, cy, cams.width,
                                               cams.height))
            o, d = one.rays(0)
            cpu = render_rays(ff["tree"], o, d, RenderOptions(background=(0.2, 0.4, 0.6)))
            diff = np.abs(gpu - np.clip(cpu.rgb.numpy(), 0, 1))
            assert diff.mean() <= 1 / 255 and np.percentile(diff, 99) <= 3 / 255, \
                (name, diff.mean() * 255, np.percentile(diff, 99) * 255)
            assert page.evaluate("window.viewer.state") == "ready"
            if name != "turned away":
                assert cpu.alpha.numpy().max() > 0.5, name            # something to see
        page.close()
    finally:
        srv.close()


def _plane_obj(x0=0.0, color=(0.2, 0.6, 0.3), half=4.0) -> str:
    c = " ".join(str(v) for v in color)
    vs = [(x0, -half, -half), (x0, half, -half), (x0, half, half), (x0, -half, half)]
    return "\n".join([f"v {x} {y} {z} {c}" for x, y, z in vs] + ["f 1 2 3 4", ""])


MESH_AMBIENT = 0.3      # mesh.js: shade = A + (1 - A) |n . d| (headlight Lambert)


def _shaded(color, normal, dirs) -> np.ndarray:
    """The mesh colour the page draws for a surface of ``normal`` seen along unit ``dirs``."""
    lam = np.abs(np.asarray(dirs, np.float64) @ np.asarray(normal, np.float64))
    return np.asarray(color)[None, None] * (MESH_AMBIENT + (1 - MESH_AMBIENT) * lam)[..., None]


def _cpu_over(tree, o, d, background) -> np.ndarray:
    """CPU render of rays (o, d) over a per-pixel background [H, W, 3]."""
    out = render_rays(tree, o, d, RenderOptions(background=(0.0, 0.0, 0.0)))
    return out.rgb.numpy() + (1 - out.alpha.numpy())[..., None] * background


def test_inserted_mesh_is_occluded_by_the_volume(bundle, scene):
    """A plane at world x = 0 (a cell boundary of the tree): in front of it the volume
    composites over the plane's (shaded) colour, behind it nothing shows; equals the CPU render
    of the tree with its x < 0 half emptied over a background of the shaded plane colour."""
    tree = scene["tree"]
    view = {"c2w": np.linalg.inv(np.linalg.inv(
        __import__("plenoctree.datasets.procedural", fromlist=["look_at"]).look_at(
            np.array([2.6, 1.7, 1.6])))).reshape(-1).tolist(),
            "fx": 0.5 * SIZE / math.tan(0.5 * FOV_X), "fy": 0.5 * SIZE / math.tan(0.5 * FOV_X),
            "cx": SIZE / 2, "cy": SIZE / 2, "width": SIZE, "height": SIZE}
    color = (0.2, 0.6, 0.3)
    info = bundle.evaluate("t => window.viewer.addMesh(t, 'plane.obj')", _plane_obj(0.0, color))
    assert info == {"vertices": 4, "triangles": 2}
    try:
        gpu = _pixels(bundle, view)
    finally:
        bundle.evaluate("window.viewer.clearMeshes()")
    cut = tree.copy()
    node, i, j, k = cut.leaf_indices()
    behind = cut.leaf_centers()[:, 0] < 0
    cut.data[node[behind], i[behind], j[behind], k[behind], -1] = 0
    c2w = np.asarray(view["c2w"], np.float32).reshape(4, 4)
    o, d = generate_rays(c2w, view["fx"], view["fy"], view["cx"], view["cy"], SIZE, SIZE)
    cpu = _cpu_over(cut, o, d, _shaded(color, [1, 0, 0], d))
    _close(gpu, cpu, "mesh occlusion")
    plain = _pixels(bundle, view)                      # removed again: the plain render
    _close(plain, _cpu(tree, view), "after clearMeshes")
    assert np.abs(gpu - plain).max() > 0.2


def test_exported_glb_mesh_loads_into_the_viewer(bundle, tmp_path):
    pytest.importorskip("trimesh")
    from plenoctree.export import export_mesh

    tree = procedural_tree(16)
    mesh = export_mesh(tree, tmp_path / "m.glb")
    b64 = base64.b64encode((tmp_path / "m.glb").read_bytes()).decode()
    info = bundle.evaluate("b => window.viewer.addMesh(b, 'm.glb')", b64)
    bundle.evaluate("window.viewer.clearMeshes()")
    assert info == {"vertices": len(mesh.vertices), "triangles": len(mesh.faces)}


def _cube_obj(center, half, color) -> str:
    """An axis-aligned cube with 4 vertices per face (so each face keeps its own normal)."""
    c, lines, faces = np.asarray(center, float), [], []
    for axis in range(3):
        for sign in (-1, 1):
            u, w = [a for a in range(3) if a != axis]
            quad = []
            for su, sw in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = c.copy()
                p[axis] += sign * half
                p[u] += su * half
                p[w] += sw * half
                quad.append(p)
            n0 = len(lines)
            lines += [f"v {p[0]} {p[1]} {p[2]} {color[0]} {color[1]} {color[2]}" for p in quad]
            faces.append(f"f {n0 + 1} {n0 + 2} {n0 + 3} {n0 + 4}")
    return "\n".join(lines + faces + [""])


def test_inserted_mesh_is_shaded_by_a_headlight(bundle, scene):
    """A cube away from the volume: every pixel of a face shows the colour times
    A + (1 - A)|n . d| for that face's normal and the pixel's ray (CPU ray-cast of the cube);
    the three visible faces differ in brightness; unlit mode draws the flat colour."""
    from plenoctree.datasets.procedural import look_at

    center, half, color = np.array([0.0, -4.0, 0.0]), 0.6, (0.9, 0.8, 0.7)
    eye = np.array([2.2, -6.4, 1.9])
    c2w = look_at(eye, center)
    f = 0.5 * SIZE / math.tan(0.5 * FOV_X)
    view = {"c2w": c2w.reshape(-1).tolist(), "fx": f, "fy": f, "cx": SIZE / 2, "cy": SIZE / 2,
            "width": SIZE, "height": SIZE}
    o, d = generate_rays(c2w.astype(np.float32), f, f, SIZE / 2, SIZE / 2, SIZE, SIZE)
    o, d = o.astype(np.float64), d.astype(np.float64)
    # CPU ray-cast: entry distance and entry face of the box
    with np.errstate(divide="ignore"):
        ta, tb = (center - half - o) / d, (center + half - o) / d
    lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
    axis = np.argmax(lo, -1)
    hit = lo.max(-1) < hi.min(-1)
    normal = np.zeros_like(d)
    np.put_along_axis(normal, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None],
                                                                            -1)), -1)
    lam = np.abs(np.sum(normal * d, -1))
    want = np.asarray(color) * (MESH_AMBIENT + (1 - MESH_AMBIENT) * lam)[..., None]
    # pixels away from the silhouette and the face edges (no sampling ambiguity)
    label = np.where(hit, axis, -1)
    pad = np.pad(label, 1, mode="edge")
    interior = np.ones_like(hit)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            interior &= pad[1 + dy:1 + dy + SIZE, 1 + dx:1 + dx + SIZE] == label
    bundle.evaluate("t => window.viewer.addMesh(t, 'cube.obj')", _cube_obj(center, half, color))
    try:
        gpu = _pixels(bundle, view)
        bundle.evaluate("window.viewer.setMeshShading(false)")
        flat = _pixels(bundle, view)
    finally:
        bundle.evaluate("window.viewer.setMeshShading(true)")
        bundle.evaluate("window.viewer.clearMeshes()")
    m = interior & hit
    assert m.sum() > 500
    diff = np.abs(gpu[m] - want[m])
    assert diff.mean() <= 0.5 / 255 and diff.max() <= 1.5 / 255, (diff.mean() * 255,
                                                                   diff.max() * 255)
    faces = [gpu[m & (axis == a)].mean(0) for a in range(3) if (m & (axis == a)).sum() > 50]
    assert len(faces) == 3
    assert min(abs(faces[a][0] - faces[b][0]) for a, b in ((0, 1), (0, 2), (1, 2))) > 0.03
    np.testing.assert_allclose(flat[m], np.broadcast_to(color, flat[m].shape), atol=1 / 255)
    rest = ~hit & interior                      # elsewhere: the volume as the CPU renders it
    assert np.abs(gpu[rest] - np.clip(_cpu(scene["tree"], view), 0, 1)[rest]).max() <= 2 / 255


def test_inserted_mesh_is_occluded_in_an_ndc_tree(browser, ff):
    """NDC trees: a world plane z = -2 (the NDC plane z' = 0, a cell boundary of the tree)
    hides what lies behind it; equals the CPU render of the tree with its z' > 0 part emptied,
    over the shaded plane. Mesh distances are mapped to NDC distances along each ray."""
    tree = ff["tree"]
    out = export_web(ff["path"], ff["dir"] / "site_mesh", overwrite=True)
    srv, page = _open_bundle(browser, out)
    try:
        color = (0.3, 0.5, 0.8)
        half, z0 = 1.5, -2.0
        obj = "\n".join([f"v {x} {y} {z0} {color[0]} {color[1]} {color[2]}"
                         for x, y in ((-half, -half), (half, -half), (half, half), (-half, half))]
                        + ["f 1 2 3 4", ""])
        page.evaluate("t => window.viewer.addMesh(t, 'plane.obj')", obj)
        cams = ff["cams"]
        i = 2
        fx, fy, cx, cy = cams.intrinsics(i)
        view = {"c2w": cams.c2w[i].reshape(-1).tolist(), "fx": fx, "fy": fy, "cx": cx,
                "cy": cy, "width": cams.width, "height": cams.height}
        gpu = _pixels(page, view)
        page.evaluate("window.viewer.clearMeshes()")
        plain = _pixels(page, view)
        page.close()
    finally:
        srv.close()
    assert tree.ndc.world_to_ndc([0.0, 0.0, z0])[2] == pytest.approx(0.0)
    cut = tree.copy()
    node, i_, j, k = cut.leaf_indices()
    behind = cut.leaf_centers()[:, 2] > 0
    assert behind.any() and (~behind).any()
    cut.data[node[behind], i_[behind], j[behind], k[behind], -1] = 0
    wo, wd = generate_rays(cams.c2w[i], fx, fy, cx, cy, cams.width, cams.height)
    o, d = cams.rays(i)
    cpu = _cpu_over(cut, o, d, _shaded(color, [0, 0, 1], wd))
    _close(gpu, cpu, "NDC mesh occlusion")
    assert np.abs(gpu - plain).max() > 0.2


def test_a_large_glb_mesh_loads(bundle):
    """A GLB of 160 k vertices (an exported lego mesh has more) loads without exhausting the
    JS stack (no argument spreading of vertex arrays)."""
    trimesh = pytest.importorskip("trimesh")
    n = 400
    y, x = np.mgrid[0:n, 0:n].astype(np.float32) / n
    verts = np.stack([x.ravel() + 3.0, y.ravel(), np.zeros(n * n, np.float32)], 1)
    q = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]).ravel()
    faces = np.concatenate([np.stack([q, q + 1, q + n], 1), np.stack([q + 1, q + n + 1, q + n], 1)])
    glb = trimesh.Trimesh(verts, faces, process=False).export(file_type="glb")
    info = bundle.evaluate("b => window.viewer.addMesh(b, 'big.glb')",
                           base64.b64encode(glb).decode())
    bundle.evaluate("window.viewer.clearMeshes()")
    assert info == {"vertices": n * n, "triangles": len(faces)}


def test_far_field_shells_draw_as_on_the_cpu(browser, tmp_path):
    """A tree grown with far-field shells (a ball in the box, a room's walls in shell 2): the
    page equals the CPU renderer from a camera inside the box and one outside it."""
    from test_far_field import room_trees

    _, grown, _, cams = room_trees()
    path = tmp_path / "room.npz"
    save_tree(grown, path)
    out = export_web(path, tmp_path / "site", overwrite=True, cameras=cams)
    srv, page = _open_bundle(browser, out)
    try:
        fx, fy, cx, cy = cams.intrinsics(0)
        outside = cams.c2w[0].copy()
        outside[:3, 3] *= 2.5                               # in shell 2, looking inwards
        for c2w in (cams.c2w[0], outside):
            view = {"c2w": np.asarray(c2w, np.float32).reshape(-1).tolist(), "fx": fx,
                    "fy": fy, "cx": cx, "cy": cy, "width": cams.width, "height": cams.height}
            gpu = _pixels(page, view)
            one = Cameras(np.asarray(c2w, np.float32)[None], fx, fy, cx, cy, cams.width,
                          cams.height)
            o, d = one.rays(0)
            cpu = render_rays(grown, o, d, RenderOptions(background=(1.0, 1.0, 1.0)))
            diff = np.abs(gpu - np.clip(cpu.rgb.numpy(), 0, 1))
            assert diff.mean() <= 1 / 255 and np.percentile(diff, 99) <= 3 / 255, \
                (diff.mean() * 255, np.percentile(diff, 99) * 255)
            assert (cpu.alpha.numpy() > 0.99).mean() > 0.5    # walls (where the views saw)
        page.close()
    finally:
        srv.close()
