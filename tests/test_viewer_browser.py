"""The WebGL2 viewer in a real browser: headless Chromium (SwiftShader) driven by Playwright.

The page's pixels are compared with the CPU renderer for the same camera at 128 px, both on
the same float16 data. Tolerance: mean |Δ| <= 0.5/255 and |Δ| <= 1/255 on 99.9 % of the pixel
channels, i.e. equal up to the 8-bit rounding of the page's output (measured with SwiftShader:
mean 0.07-0.23/255, max 0.5/255).

Skipped, with the reason, when Chromium or the playwright package is missing; CI installs both
(``scripts/install_browser.sh``).
"""

from __future__ import annotations

import base64
import functools
import math
import shutil
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
playwright_api = pytest.importorskip(
    "playwright.sync_api", reason="the playwright package is not installed "
    "(run scripts/install_browser.sh)")
if CHROMIUM is None:
    pytest.skip("no chromium executable (run scripts/install_browser.sh)", allow_module_level=True)

from plenoctree.compression import CompressOptions, compress, load_any_tree, save_compressed  # noqa: E402
from plenoctree.datasets.cameras import generate_rays  # noqa: E402
from plenoctree.datasets.procedural import look_at, procedural_tree  # noqa: E402
from plenoctree.octree import Octree  # noqa: E402
from plenoctree.octree.io import save_tree  # noqa: E402
from plenoctree.render import RenderOptions, render_rays  # noqa: E402
from plenoctree.viewer import ViewerServer, export_web  # noqa: E402

FLAGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync"]
SIZE = 128
C2W = look_at(np.array([2.6, 1.7, 1.6])).astype(np.float32)
FX = 0.5 * SIZE / math.tan(0.5 * 0.6911)


@pytest.fixture(scope="module")
def browser():
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def trees(tmp_path_factory):
    d = tmp_path_factory.mktemp("trees")
    base = procedural_tree(32)
    out = {}
    save_tree(base, d / "proc.npz", precision="fp16")
    out["npz"] = d / "proc.npz"
    save_compressed(compress(base, CompressOptions(bits=12)), d / "proc.plnz")
    out["plnz"] = d / "proc.plnz"
    rng = np.random.default_rng(0)               # SH degree 4: pad the scene with degree-4 terms
    coef = base.data[..., :-1].reshape(base.data.shape[:-1] + (3, 16))
    extra = rng.normal(scale=0.3, size=coef.shape[:-1] + (9,)) * (base.data[..., -1:, None] > 0)
    data25 = np.concatenate([np.concatenate([coef, extra], -1).reshape(coef.shape[:-2] + (75,)),
                             base.data[..., -1:]], -1).astype(np.float32)
    sh25 = Octree(child=base.child, data=data25, offset=base.offset, invradius=base.invradius,
                  data_format="SH25")
    save_tree(sh25, d / "sh25.npz")              # float32 on disk: the page converts to half
    out["sh25"] = d / "sh25.npz"
    from plenoctree.octree.io import export_svox

    export_svox(base, d / "svox.npz")            # the original tools' layout (float32 offsets)
    out["svox"] = d / "svox.npz"
    for fmt in ("RGBA", "SG4"):
        t = Octree.dense(2, fmt, seed=1)
        t.data[..., -1] *= 0.5
        save_tree(t, d / f"{fmt}.npz", precision="fp16")
        out[fmt] = d / f"{fmt}.npz"
    return out


def _open(browser, url, wait_ready=True):
    page = browser.new_page(viewport={"width": 640, "height": 400})
    page.goto(url)
    page.wait_for_function("window.viewer && window.viewer.state !== 'loading'", timeout=90_000)
    if wait_ready:
        assert page.evaluate("window.viewer.state") == "ready", page.evaluate("window.viewer.message")
    return page


def _gpu_image(page, **opts) -> np.ndarray:
    view = {"c2w": C2W.reshape(-1).tolist(), "fx": FX, "fy": FX, "cx": SIZE / 2, "cy": SIZE / 2,
            "width": SIZE, "height": SIZE}
    page.evaluate("v => window.viewer.setView(v)", view)
    page.evaluate("o => window.viewer.setOptions(o)", opts)
    page.evaluate("window.viewer.render()")
    raw = base64.b64decode(page.evaluate("window.viewer.pixels()"))
    return np.frombuffer(raw, np.uint8).reshape(SIZE, SIZE, 4)[..., :3].astype(np.float64) / 255


def _cpu_image(tree, **opts):
    o, d = generate_rays(C2W, FX, FX, SIZE / 2, SIZE / 2, SIZE, SIZE)
    out = render_rays(tree, o, d, RenderOptions(**opts))
    return out


def _close(gpu: np.ndarray, cpu: np.ndarray, what: str) -> None:
    diff = np.abs(gpu - np.clip(cpu, 0, 1))
    mean, p999 = diff.mean(), np.percentile(diff, 99.9)
    assert mean <= 0.5 / 255 and p999 <= 1 / 255, \
        f"{what}: mean {mean * 255:.2f}/255, p99.9 {p999 * 255:.2f}/255"


@pytest.fixture(scope="module")
def proc_page(browser, trees):
    with ViewerServer(trees["npz"], port=0) as srv:
        page = _open(browser, srv.url)
        yield page
        page.close()


@pytest.mark.parametrize("kind", ["npz", "plnz", "svox", "sh25", "RGBA", "SG4"])
def test_pixels_match_cpu_renderer(browser, trees, kind):
    with ViewerServer(trees[kind], port=0) as srv:
        page = _open(browser, srv.url)
        info = page.evaluate("window.viewer.info()")
        gpu = _gpu_image(page)
        page.close()
    tree = load_any_tree(trees[kind])
    assert info["n_leaves"] == int(((tree.child == 0) & (tree.data[..., -1] > 0)).sum())
    assert info["compressed"] == (kind == "plnz") and info["format"] == tree.data_format
    cpu = _cpu_image(tree.astype(np.float16).astype(np.float32)).rgb.numpy()
    _close(gpu, cpu, kind)
    assert gpu.std() > 0.05                               # not a blank image


def test_sh_range_matches_cpu(proc_page, trees):
    tree = load_any_tree(trees["npz"])
    full = _gpu_image(proc_page, sh_min=0, sh_max=-1)
    for lo, hi in ((0, 0), (1, 15), (4, 2)):
        gpu = _gpu_image(proc_page, sh_min=lo, sh_max=hi)
        _close(gpu, _cpu_image(tree, sh_min=lo, sh_max=hi).rgb.numpy(), f"sh {lo}..{hi}")
        assert np.abs(gpu - full).max() > 0.1, f"sh {lo}..{hi} did not change the image"
    _gpu_image(proc_page, sh_min=0, sh_max=-1)


def test_slicing_box_cuts_the_tree(proc_page, trees):
    tree = load_any_tree(trees["npz"])
    full = _gpu_image(proc_page)
    gpu = _gpu_image(proc_page, box_min=[0, 0, 0], box_max=[0.5, 1, 1])
    # x = 0.5 is a cell boundary at every depth: slicing there equals emptying the x >= 0.5 half
    cut = tree.copy()
    node, i, j, k = cut.leaf_indices()
    corner = tree.world_to_tree(tree.leaf_centers())[:, 0]
    cut.data[node[corner > 0.5], i[corner > 0.5], j[corner > 0.5], k[corner > 0.5], -1] = 0
    _close(gpu, _cpu_image(cut).rgb.numpy(), "slice x <= 0.5")
    assert np.abs(gpu - full).max() > 0.1
    empty = _gpu_image(proc_page, box_min=[0.5, 0.5, 0.5], box_max=[0.5, 0.5, 0.5])
    assert np.abs(empty - 1.0).max() < 1e-6               # nothing but background
    _gpu_image(proc_page, box_min=[0, 0, 0], box_max=[1, 1, 1])


def test_background_and_depth_views(proc_page, trees):
    tree = load_any_tree(trees["npz"])
    gpu = _gpu_image(proc_page, background=[0, 0, 0])
    _close(gpu, _cpu_image(tree, background=(0, 0, 0)).rgb.numpy(), "black background")
    near, far = 2.0, 5.0
    gpu = _gpu_image(proc_page, mode="depth", depth_range=[near, far], background=[0, 0, 0])
    ref = _cpu_image(tree, background=(0, 0, 0))
    alpha, depth = ref.alpha.numpy(), ref.depth.numpy()
    grey = (1 - np.clip((depth - near) / (far - near), 0, 1)) * alpha
    diff = np.abs(gpu - grey[..., None])
    assert diff.mean() <= 1 / 255 and np.percentile(diff, 98) <= 3 / 255
    gpu = _gpu_image(proc_page, mode="alpha", background=[0, 0, 0])
    assert np.abs(gpu - alpha[..., None]).mean() <= 1 / 255
    _gpu_image(proc_page, mode="rgb", background=[1, 1, 1])


def test_orbit_controls_and_default_camera(proc_page):
    page = proc_page
    page.evaluate("window.viewer.clearView()")
    page.evaluate("window.viewer.render()")
    before = page.evaluate("window.viewer.pixels()")
    az = page.evaluate("window.viewer.camera().azimuth")
    box = page.locator("#canvas").bounding_box()
    page.mouse.move(box["x"] + 100, box["y"] + 100)
    page.mouse.down()
    page.mouse.move(box["x"] + 160, box["y"] + 110, steps=4)
    page.mouse.up()
    page.mouse.wheel(0, 200)
    assert page.evaluate("window.viewer.camera().azimuth") != az
    page.evaluate("window.viewer.render()")
    after = page.evaluate("window.viewer.pixels()")
    assert after != before
    img = np.frombuffer(base64.b64decode(after), np.uint8)
    assert img.std() > 10                                 # the default view shows the scene
    assert "FPS" in page.locator("#fps").inner_text()


def _expect_message(browser, url, *needles):
    page = _open(browser, url, wait_ready=False)
    try:
        assert page.evaluate("window.viewer.state") == "error"
        assert page.locator("#message").is_visible()
        text = page.locator("#message").inner_text()
        for n in needles:
            assert n in text, f"{n!r} not in {text!r}"
    finally:
        page.close()


def test_oversized_tree_shows_limit_message(browser, trees):
    with ViewerServer(trees["npz"], port=0) as srv:
        _expect_message(browser, srv.url + "?max_texture=64&max_layers=2", "too large",
                        "MAX_TEXTURE_SIZE = 64", "plenoctree lod")
        _expect_message(browser, srv.url + "?max_mb=0.01", "too large", "plenoctree lod")


def test_bad_files_show_message(browser, trees, tmp_path):
    good = trees["plnz"].read_bytes()
    (tmp_path / "cut.plnz").write_bytes(good[: len(good) // 3])
    (tmp_path / "foreign.plnz").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(500))
    z = dict(np.load(trees["plnz"]))
    qm = z["quant_map"].copy()
    qm[3][z["sigma"] > 0] = 5000                          # codebook has 4096 entries
    z["quant_map"] = qm
    with open(tmp_path / "index.plnz", "wb") as f:
        np.savez_compressed(f, **z)
    cases = {"cut.plnz": "truncated", "foreign.plnz": "not a zip",
             "index.plnz": "codebook index 5000 out of range"}
    # ViewerServer and export_web refuse such files up front (check_servable); the page's own
    # checks matter for bundles a user assembles or a file a host serves: a plain static folder
    from plenoctree.viewer.server import static_files

    for name, needle in cases.items():
        site = tmp_path / f"site_{name}"
        (site / "data").mkdir(parents=True)
        for fname, src in static_files().items():
            shutil.copyfile(src, site / fname)
        (site / "config.json").write_text('{"tree": "data/%s"}' % name)
        shutil.copyfile(tmp_path / name, site / "data" / name)
        handler = functools.partial(SimpleHTTPRequestHandler, directory=str(site))
        httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        try:
            _expect_message(browser, f"http://127.0.0.1:{httpd.server_address[1]}/", needle, name)
        finally:
            httpd.shutdown()
            httpd.server_close()


def test_exported_bundle_works_on_a_plain_static_server(browser, trees, tmp_path):
    out = export_web(trees["plnz"], tmp_path / "site", background=(0.0, 0.0, 0.0))
    handler = functools.partial(SimpleHTTPRequestHandler, directory=str(out))
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        page = _open(browser, f"http://127.0.0.1:{httpd.server_address[1]}/")
        assert page.evaluate("window.viewer.info()")["compressed"] is True
        # the page starts on config.json's background (run gives black for real photos)
        assert page.evaluate("document.getElementById('background').value") == "#000000"
        page.close()
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_float16_conversion_matches_numpy(proc_page):
    rng = np.random.default_rng(0)
    vals = np.concatenate([rng.normal(scale=s, size=200) for s in (1e-6, 1e-3, 1.0, 1e3, 1e5)])
    vals = np.concatenate([vals, [0.0, -0.0, 65504.0, 65520.0, 1e9, -1e9, 5.96e-8, 2.98e-8,
                                  1.0 + 2 ** -11, 1.0 + 3 * 2 ** -11, 6.1e-5]]).astype(np.float32)
    got = proc_page.evaluate(
        "async v => { const m = await import('./tree.js'); return v.map(m.toHalfBits); }",
        vals.tolist())
    with np.errstate(over="ignore"):                      # +-1e9 -> +-inf on purpose
        want = vals.astype(np.float16).view(np.uint16)
    np.testing.assert_array_equal(np.asarray(got, dtype=np.uint16), want)
    back = proc_page.evaluate(
        "async v => { const m = await import('./tree.js'); return v.map(m.halfToFloat); }",
        want.tolist())
    np.testing.assert_array_equal(np.asarray(back, np.float32), want.view(np.float16).astype(np.float32))
