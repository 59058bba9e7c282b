"""The viewer's CPU mode (``plenoctree view --render cpu|auto``): the server draws frames with the
numba renderer and streams them as JPEG (``GET /frame``); ``--host`` and its warning.

Correctness only (speed: ``benchmarks/viewer_fps.py``): a streamed frame equals the renderer's
image of the same camera (as ``plenoctree render`` makes it: ``render_image`` of a
``Cameras``, NDC trees through ``tree.ndc.apply``) within JPEG error; bad parameters answer 400,
never a traceback. The browser tests (headless Chromium with SwiftShader, skipped without
playwright) check that ``--render auto`` picks the CPU under software GL and that the WebGL
frame loop never reads pixels back synchronously.
"""

from __future__ import annotations

import base64
import http.client
import io
import math
import socket
import sys

import numpy as np
import pytest
from PIL import Image

from plenoctree.cli import main
from plenoctree.compression import load_any_tree
from plenoctree.datasets import Cameras
from plenoctree.datasets.procedural import look_at, procedural_tree
from plenoctree.errors import ConfigError
from plenoctree.octree.io import save_tree
from plenoctree.render import RenderOptions, render_image
from plenoctree.viewer import ViewerServer
from plenoctree.viewer.frames import parse_frame_query
from viewer_http import get

SIZE = 96
C2W = look_at(np.array([2.6, 1.7, 1.6]))
FX = 0.5 * SIZE / math.tan(0.5 * 0.6911)


@pytest.fixture(scope="module")
def proc(tmp_path_factory):
    path = tmp_path_factory.mktemp("cpuview") / "proc.npz"
    save_tree(procedural_tree(32), path)
    return path


@pytest.fixture(scope="module")
def cpu_server(proc):
    with ViewerServer(proc, port=0, render="cpu") as srv:
        yield srv


def _get(port, path, host=None):
    return get(port, path, host, timeout=120)          # a frame may compile the kernel


def _query(c2w, fx, fy, cx, cy, w, h, **extra) -> str:
    q = {"w": w, "h": h, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
         "c2w": ",".join(repr(float(v)) for v in np.asarray(c2w).reshape(-1))}
    q.update(extra)
    return "&".join(f"{k}={v}" for k, v in q.items())


def _frame(port, query) -> np.ndarray:
    status, headers, body = _get(port, "/frame?" + query)
    assert status == 200, body
    assert headers["Content-Type"] == "image/jpeg" and float(headers["X-Render-Ms"]) >= 0
    return np.asarray(Image.open(io.BytesIO(body)).convert("RGB"), np.float64) / 255


def _psnr(a, b) -> float:
    return float(-10 * np.log10(np.mean((a - np.clip(b, 0, 1)) ** 2)))


def test_streamed_frame_equals_the_render_of_the_same_camera(cpu_server, proc):
    from plenoctree.compression import load_any_tree

    tree = load_any_tree(proc)
    cams = Cameras(C2W[None], FX, FX, SIZE / 2, SIZE / 2, SIZE, SIZE)
    for opts, extra in ((RenderOptions(), {}),
                        (RenderOptions(background=(0, 0, 0), sh_min=1, sh_max=3),
                         {"bg": "0,0,0", "sh_min": 1, "sh_max": 3}),
                        (RenderOptions(background=(0, 0, 0), stop_thresh=0.3, renormalize=True),
                         {"bg": "0,0,0", "stop": 0.3, "renorm": 1})):
        got = _frame(cpu_server.port, _query(C2W, FX, FX, SIZE / 2, SIZE / 2, SIZE, SIZE, **extra))
        want = render_image(tree, cams, 0, opts).rgb.numpy()
        assert got.shape == want.shape
        assert _psnr(got, want) > 35 and np.abs(got - want).mean() < 2 / 255, _psnr(got, want)
        assert got.std() > 0.05                                   # not a blank frame
    ref = render_image(tree, cams, 0, RenderOptions())
    depth = _frame(cpu_server.port, _query(C2W, FX, FX, SIZE / 2, SIZE / 2, SIZE, SIZE,
                                           mode="depth", dr="2,5", bg="0,0,0"))
    alpha, d = ref.alpha.numpy(), ref.depth.numpy()
    grey = (1 - np.clip((d - 2) / 3, 0, 1)) * alpha
    assert np.abs(depth - grey[..., None]).mean() < 2 / 255


def test_a_camera_too_far_to_step_from_sees_the_background(cpu_server):
    """No view is refused for where the camera stands: from 1e12 units away the tree is far
    smaller than a pixel (the renderer cannot step from there), so the frame is background."""
    status, _, body = _get(cpu_server.port, "/frame?" + _query(
        look_at(np.array([1e12, 0, 0])), FX, FX, 4, 4, 8, 8, bg="0.2,0.4,0.6", q=95))
    assert status == 200, body
    img = np.asarray(Image.open(io.BytesIO(body)).convert("RGB"), np.float64) / 255
    np.testing.assert_allclose(img, np.broadcast_to((0.2, 0.4, 0.6), img.shape), atol=3 / 255)


def test_ndc_tree_frame_equals_the_render_of_its_camera(tmp_path):
    from nerf_fixtures import ff_tree

    from plenoctree.datasets import load_dataset

    root, tree, _ = ff_tree(tmp_path)
    cams = load_dataset(root, "train").cameras                    # NDC cameras
    with ViewerServer(tmp_path / "ff.npz", port=0, render="auto") as srv:
        status, _, body = _get(srv.port, "/config.json")
        assert status == 200 and b'"ndc"' in body and b'"render": "auto"' in body
        fx, fy, cx, cy = cams.intrinsics(1)
        got = _frame(srv.port, _query(cams.c2w[1], fx, fy, cx, cy, cams.width, cams.height,
                                      q=95))            # a tiny image: JPEG's best quality
    want = render_image(tree, cams, 1, RenderOptions()).rgb.numpy()
    assert _psnr(got, want) > 35 and np.abs(got - want).mean() < 2 / 255
    assert got.std() > 0.02


BAD = {
    "missing c2w": "w=8&h=8&fx=8&fy=8&cx=4&cy=4",
    "zero size": _query(C2W, FX, FX, 4, 4, 0, 8),
    "over the size policy": _query(C2W, FX, FX, 4, 4, 200_000, 200_000),
    "size not an int": _query(C2W, FX, FX, 4, 4, "8.5", 8),
    "nan focal": _query(C2W, "nan", FX, 4, 4, 8, 8),
    "inf in pose": _query(C2W, FX, FX, 4, 4, 8, 8).replace("c2w=", "c2w=inf,", 1),
    "15 pose numbers": _query(np.eye(4).reshape(-1)[:15], FX, FX, 4, 4, 8, 8),
    "singular pose": _query(np.zeros((4, 4)), FX, FX, 4, 4, 8, 8),
    "implausible focal": _query(C2W, 1e-9, 1e-9, 4, 4, 8, 8),
    "bad mode": _query(C2W, FX, FX, 4, 4, 8, 8, mode="x"),
    "bad quality": _query(C2W, FX, FX, 4, 4, 8, 8, q=0),
    "bad stop": _query(C2W, FX, FX, 4, 4, 8, 8, stop=1.5),
    "negative sh_min": _query(C2W, FX, FX, 4, 4, 8, 8, sh_min=-1),
    "renorm not 0 or 1": _query(C2W, FX, FX, 4, 4, 8, 8, renorm=2),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_frame_endpoint_refuses_bad_parameters(cpu_server, case):
    status, headers, body = _get(cpu_server.port, "/frame?" + BAD[case])
    assert status == 400, (case, status, body)
    assert headers["Content-Type"].startswith("text/plain")
    assert b"Traceback" not in body and body.startswith(b"400 Bad Request: ")
    with pytest.raises(ConfigError):                  # refused by parsing, not by drawing
        parse_frame_query(BAD[case])


def test_render_choices_and_webgl_serves_no_frames(proc, capsys):
    with pytest.raises(ConfigError, match="render must be one of"):
        ViewerServer(proc, port=0, render="gpu")
    with pytest.raises(SystemExit):
        main(["view", str(proc), "--port", "0", "--render", "gpu"])
    assert "invalid choice" in capsys.readouterr().err
    with ViewerServer(proc, port=0) as srv:                      # the library default: webgl
        assert srv.render == "webgl"
        assert _get(srv.port, "/frame?" + _query(C2W, FX, FX, 4, 4, 8, 8))[0] == 404
        status, _, body = _get(srv.port, "/config.json")
        assert status == 200 and b'"cpu"' not in body


def test_host_warning_and_host_check(proc, monkeypatch, capsys):
    monkeypatch.setattr(ViewerServer, "serve_forever", lambda self: self.httpd.server_close())
    assert main(["view", str(proc), "--port", "0", "--render", "webgl"]) == 0
    out = capsys.readouterr()
    assert "warning" not in out.err and "http://127.0.0.1:" in out.out
    assert main(["view", str(proc), "--port", "0", "--render", "webgl", "--host", "0.0.0.0"]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "anyone who can reach" in err and "ssh -L" in err
    # CPU mode: the page holds no textures, so the texture budget does not apply
    assert main(["view", str(proc), "--port", "0", "--render", "webgl", "--max-mb", "1e-6"]) == 1
    assert "budget" in capsys.readouterr().err
    assert main(["view", str(proc), "--port", "0", "--render", "cpu", "--max-mb", "1e-6"]) == 0
    assert "drawn by the CPU renderer" in capsys.readouterr().out
    with ViewerServer(proc, port=0, host="0.0.0.0") as srv:       # every interface
        p = srv.port
        assert srv.httpd.server_address[0] == "0.0.0.0"
        for host in (f"127.0.0.1:{p}", f"{socket.gethostname()}:{p}", "localhost"):
            assert _get(p, "/config.json", host=host)[0] == 200, host
        for evil in ("evil.example.com", f"evil.example.com:{p}", f"x:{p}"):
            assert _get(p, "/config.json", host=evil)[0] == 403
    with ViewerServer(proc, port=0, host="127.0.0.2") as srv:     # one given address
        p = srv.port
        assert srv.url == f"http://127.0.0.2:{p}/"
        c = http.client.HTTPConnection("127.0.0.2", p, timeout=10)
        c.request("GET", "/config.json")
        assert c.getresponse().status == 200
        c.close()


# ---------------------------------------------------------------- in the browser
def _browser_mod():
    pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    import test_viewer_browser as tvb

    return tvb


@pytest.fixture(scope="module")
def playwright():
    tvb = _browser_mod()
    with tvb.playwright_api.sync_playwright() as p:
        yield p


@pytest.fixture(scope="module")
def browser(playwright):
    tvb = _browser_mod()
    b = playwright.chromium.launch(executable_path=tvb.CHROMIUM, headless=True, args=tvb.FLAGS)
    yield b
    b.close()


def _open(browser, url, size=(640, 400)):
    """A page of the viewer at ``url`` (``size`` = viewport), loaded and ready."""
    page = browser.new_page(viewport={"width": size[0], "height": size[1]})
    page.goto(url)
    page.wait_for_function("window.viewer && window.viewer.state !== 'loading'", timeout=120_000)
    assert page.evaluate("window.viewer.state") == "ready", page.evaluate("window.viewer.message")
    return page


def test_auto_picks_the_cpu_under_software_gl_and_matches_the_renderer(browser, proc):
    from plenoctree.compression import load_any_tree

    with ViewerServer(proc, port=0, render="auto") as srv:
        page = _open(browser, srv.url)
        try:
            who = page.evaluate("window.viewer.renderer()")
            assert who["mode"] == "cpu" and who["software"], who
            assert who["label"].startswith("CPU (numba, ")
            page.wait_for_function("window.viewer.stats().last && window.viewer.stats().last.full",
                                   timeout=120_000)
            assert "FPS @" in page.locator("#fps").inner_text()
            for tool in ("#probe_mode", "#mesh_file", "#box_min_0", "#file"):
                assert page.locator(tool).is_disabled(), tool
                assert "WebGL only" in page.locator(tool).get_attribute("title")
            view = {"c2w": C2W.reshape(-1).tolist(), "fx": FX, "fy": FX, "cx": SIZE / 2,
                    "cy": SIZE / 2, "width": SIZE, "height": SIZE}
            page.evaluate("v => window.viewer.setView(v)", view)
            page.evaluate("window.viewer.render()")               # a Promise: awaited
            raw = base64.b64decode(page.evaluate("window.viewer.pixels()"))
            got = np.frombuffer(raw, np.uint8).reshape(SIZE, SIZE, 4)[..., :3] / 255.0
            # the page controls: SH range, background
            page.evaluate("window.viewer.setOptions({background: [0, 0, 0], sh_max: 0})")
            page.evaluate("window.viewer.render()")
            raw0 = base64.b64decode(page.evaluate("window.viewer.pixels()"))
            got0 = np.frombuffer(raw0, np.uint8).reshape(SIZE, SIZE, 4)[..., :3] / 255.0
            # an orbit drag moves the camera and a new sharp frame arrives
            page.evaluate("window.viewer.clearView()")
            n = len(page.evaluate("window.viewer.stats().log"))
            box = page.locator("#canvas").bounding_box()
            page.mouse.move(box["x"] + 100, box["y"] + 100)
            page.mouse.down()
            page.mouse.move(box["x"] + 180, box["y"] + 120, steps=6)
            page.mouse.up()
            page.wait_for_function(f"window.viewer.stats().log.length > {n} && "
                                   "window.viewer.stats().last.full", timeout=60_000)
        finally:
            page.close()
    tree = load_any_tree(proc)
    cams = Cameras(C2W[None], FX, FX, SIZE / 2, SIZE / 2, SIZE, SIZE)
    want = render_image(tree, cams, 0).rgb.numpy()
    assert _psnr(got, want) > 35, _psnr(got, want)
    want0 = render_image(tree, cams, 0, RenderOptions(background=(0, 0, 0), sh_max=0)).rgb.numpy()
    assert _psnr(got0, want0) > 35, _psnr(got0, want0)


def test_moving_frames_ask_for_the_fast_rule_and_get_it(browser, proc, cpu_server):
    """The page's query for a moving frame (scale < 1) asks for svox's renormalised rule at
    stop 0.1, its sharp frame for the page's exact options; the server draws what was asked."""
    page = _open(browser, cpu_server.url)
    try:
        queries = page.evaluate("""async (view) => {
            const m = await import("./frames.js");
            const o = {background: [0, 0, 0], stop_thresh: 0.01, sh_min: 0, sh_max: -1};
            return [m.frameQuery(view, m.frameOptions(o, 0.5)),
                    m.frameQuery(view, m.frameOptions(o, 1))];
        }""", {"c2w": C2W.reshape(-1).tolist(), "fx": FX, "fy": FX, "cx": SIZE / 2,
               "cy": SIZE / 2, "width": SIZE, "height": SIZE})
    finally:
        page.close()
    moving, sharp = (parse_frame_query(q).options for q in queries)
    assert moving.renormalize and moving.stop_thresh == 0.1
    assert not sharp.renormalize and sharp.stop_thresh == 0.01
    tree = load_any_tree(proc)
    cams = Cameras(C2W[None], FX, FX, SIZE / 2, SIZE / 2, SIZE, SIZE)
    got = _frame(cpu_server.port, queries[0].replace("q=80", "q=95").replace("q=90", "q=95"))
    want = render_image(tree, cams, 0, moving).rgb.numpy()
    assert _psnr(got, want) > 35, _psnr(got, want)


def test_webgl_mode_label_and_no_sync_readback_in_the_frame_loop(browser, proc):
    with ViewerServer(proc, port=0, render="auto") as srv:
        page = browser.new_page(viewport={"width": 640, "height": 400})
        # count read-backs from the start (the page's own scripts call none while drawing)
        page.add_init_script("""(() => {
          window.__readPixels = 0;
          const orig = WebGL2RenderingContext.prototype.readPixels;
          WebGL2RenderingContext.prototype.readPixels = function (...a) {
            window.__readPixels += 1; return orig.apply(this, a); };
        })();""")
        page.goto(srv.url + "?render=webgl")
        page.wait_for_function("window.viewer && window.viewer.state !== 'loading'",
                               timeout=120_000)
        try:
            assert page.evaluate("window.viewer.state") == "ready"
            who = page.evaluate("window.viewer.renderer()")
            assert who["mode"] == "webgl" and who["label"].startswith("WebGL (")
            box = page.locator("#canvas").bounding_box()
            page.mouse.move(box["x"] + 100, box["y"] + 100)
            page.mouse.down()
            page.mouse.move(box["x"] + 160, box["y"] + 110, steps=4)
            page.mouse.up()
            page.wait_for_function("window.viewer.stats().log.length >= 3 && "
                                   "window.viewer.stats().last.full", timeout=60_000)
            assert page.evaluate("window.__readPixels") == 0
        finally:
            page.close()


def test_webgl_full_frame_refined_in_bands_equals_the_direct_frame(browser, proc):
    """A slow full frame is drawn in bands into an offscreen target over several animation
    frames (the page never stalls for a whole frame), then shown: the same pixels as drawing
    it at once. ``?band_ms=0.5`` makes every full frame banded."""
    with ViewerServer(proc, port=0) as srv:
        page = _open(browser, srv.url + "?band_ms=0.5")
        try:
            box = page.locator("#canvas").bounding_box()
            page.mouse.move(box["x"] + 100, box["y"] + 100)
            page.mouse.down()
            page.mouse.move(box["x"] + 150, box["y"] + 120, steps=3)
            page.mouse.up()
            n = len(page.evaluate("window.viewer.stats().log"))
            page.wait_for_function(f"window.viewer.stats().log.slice({n}).some(e => e.bands)",
                                   timeout=60_000)
            last = page.evaluate("window.viewer.stats().last")
            assert last["full"] and last["bands"]
            banded = page.evaluate("window.viewer.pixels()")
            page.evaluate("window.viewer.render()")                   # the same view at once
            direct = page.evaluate("window.viewer.pixels()")
        finally:
            page.close()
    a = np.frombuffer(base64.b64decode(banded), np.uint8)
    b = np.frombuffer(base64.b64decode(direct), np.uint8)
    assert a.shape == b.shape and np.abs(a.astype(int) - b).max() <= 1
    assert b.std() > 10


if __name__ == "__main__":                 # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))


@pytest.fixture(scope="module")
def no_webgl_browser(playwright):
    """Chromium with WebGL switched off entirely (as Chrome without its software WebGL)."""
    tvb = _browser_mod()
    b = playwright.chromium.launch(executable_path=tvb.CHROMIUM, headless=True,
                                   args=tvb.FLAGS + ["--disable-webgl", "--disable-3d-apis"])
    yield b
    b.close()


@pytest.fixture(scope="module")
def llff_tree(tmp_path_factory):
    from nerf_fixtures import ff_tree

    return ff_tree(tmp_path_factory.mktemp("lookaround"))[2]


def _frames(page) -> int:
    return len(page.evaluate("window.viewer.stats().log"))


def test_llff_look_around_never_stops_the_page(no_webgl_browser, llff_tree):
    """The user's path on a forward-facing tree in CPU mode: look around with the arrow keys
    held for seconds (the camera turns past 180°: most rays miss the NDC volume), then reset:
    frames keep arriving, no frame is refused, nothing stops the page."""
    with ViewerServer(llff_tree, port=0, render="auto") as srv:
        page = _open(no_webgl_browser, srv.url, (775, 800))
        try:
            assert page.evaluate("window.viewer.renderer()")["mode"] == "cpu"
            page.wait_for_function("window.viewer.stats().last && window.viewer.stats().last.full",
                                   timeout=120_000)
            page.locator("#canvas").focus()
            for key, seconds in (("ArrowLeft", 3.5), ("ArrowUp", 1.0), ("ArrowRight", 1.5)):
                n = _frames(page)
                page.keyboard.down(key)
                page.wait_for_timeout(seconds * 1000)
                page.keyboard.up(key)
                assert _frames(page) > n + 3, key                  # frames kept arriving
                assert page.evaluate("window.viewer.state") == "ready"
                assert page.evaluate("window.viewer.notice") == "", page.evaluate("window.viewer.notice")
            fwd = page.evaluate("window.viewer.currentView(8, 8)")["c2w"]
            assert fwd[10] > -0.5                                  # looked away from -z
            n = _frames(page)
            page.click("#reset_view")
            page.wait_for_function(f"window.viewer.stats().log.length > {n} && "
                                   "window.viewer.stats().last.full", timeout=60_000)
            c2w = page.evaluate("window.viewer.currentView(8, 8)")["c2w"]
            np.testing.assert_allclose(np.reshape(c2w, (4, 4)), np.eye(4), atol=1e-6)
        finally:
            page.close()


# Move away and back to the pose of the sharp frame on screen without pausing (a sweep, or
# Reset while moving): the camera ends where the last full-resolution frame was drawn.
_AWAY_AND_BACK = """() => new Promise((done) => {
  const cam = window.viewer.camera(), s0 = cam.state();
  let k = 0;
  function tick() {
    if (k < 12) { cam.orbit(k % 2 ? -2 : 5, 0); k += 1; requestAnimationFrame(tick); }
    else { cam.setState(s0); done(performance.now()); }
  }
  requestAnimationFrame(tick);
})"""


def test_back_at_the_last_sharp_pose_draws_sharp_again(no_webgl_browser, llff_tree):
    """A moving frame replaces the sharp one on screen: coming back to the pose of the last
    sharp frame while moving still ends in a full-resolution frame (it used to keep the blurry
    moving frame for good, as the page thought the sharp one was still shown)."""
    with ViewerServer(llff_tree, port=0, render="cpu") as srv:
        page = _open(no_webgl_browser, srv.url, (775, 800))
        try:
            page.wait_for_function("window.viewer.stats().last && window.viewer.stats().last.full",
                                   timeout=120_000)
            for _ in range(3):
                t_back = page.evaluate(_AWAY_AND_BACK)
                page.wait_for_function(
                    "t => window.viewer.stats().log.some((e) => e.full && e.t - e.ms >= t - 1)",
                    arg=t_back, timeout=20_000)
                page.wait_for_timeout(200)
                assert page.evaluate("window.viewer.stats().last.full")
        finally:
            page.close()


def test_a_failed_frame_is_a_notice_and_the_next_change_draws(no_webgl_browser, llff_tree):
    """A frame the server cannot draw (here: the first answered 400 on the way) shows a
    notice, the page stays ready, the next camera change draws; benchmark() works in CPU mode;
    the FPS label never runs under the Controls box."""
    with ViewerServer(llff_tree, port=0, render="cpu") as srv:
        page = no_webgl_browser.new_page(viewport={"width": 775, "height": 800})
        failed = []

        def once(route):
            if failed:
                route.continue_()
            else:
                failed.append(route.request.url)
                route.fulfill(status=400, body="400 Bad Request: injected", content_type="text/plain")

        page.route("**/frame?*", once)
        page.goto(srv.url)
        page.wait_for_function("window.viewer && window.viewer.state !== 'loading'",
                               timeout=120_000)
        try:
            page.wait_for_function("window.viewer.notice !== ''", timeout=60_000)
            assert "injected" in page.evaluate("window.viewer.notice")
            assert page.locator("#notice").is_visible()
            assert page.evaluate("window.viewer.state") == "ready"
            assert page.locator("#message").is_hidden()
            n = _frames(page)
            page.locator("#canvas").focus()
            page.keyboard.down("KeyW")
            page.wait_for_timeout(300)
            page.keyboard.up("KeyW")
            page.wait_for_function(f"window.viewer.stats().log.length > {n}", timeout=60_000)
            ms = page.evaluate("window.viewer.benchmark(3)")           # a Promise: awaited
            assert isinstance(ms, (int, float)) and ms > 0
            page.wait_for_function("document.getElementById('fps').textContent.includes('FPS')")
            a = page.locator("#fps").bounding_box()
            b = page.locator("#hints").bounding_box()
            assert a["x"] + a["width"] <= b["x"] or a["y"] + a["height"] <= b["y"], (a, b)
        finally:
            page.close()

