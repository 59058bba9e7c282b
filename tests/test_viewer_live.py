"""The viewer of a run folder (plenoctree view OUT, viewer/live.py; issue 49): the newest tree
of the run, its status, the swap when a newer tree lands — through the server's URLs, and in
headless Chromium (the page reloads onto the new tree and keeps its camera)."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request

import pytest

from plenoctree.datasets.procedural import procedural_tree
from plenoctree.live import newest_tree, read_live, write_live
from plenoctree.octree.io import save_tree
from plenoctree.viewer import ViewerServer


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def _json(url: str) -> dict:
    code, body = _get(url)
    assert code == 200, body
    return json.loads(body)


FRAME = ("frame?c2w=1,0,0,0,0,1,0,0,0,0,1,3,0,0,0,1&fx=40&fy=40&cx=32&cy=32&w=64&h=64"
         "&q=80")


def test_live_status_files_and_the_newest_tree(tmp_path):
    assert read_live(tmp_path) is None and newest_tree(tmp_path) is None
    save_tree(procedural_tree(16), tmp_path / "tree.npz")
    assert newest_tree(tmp_path) == tmp_path / "tree.npz"         # a run without live.json
    (tmp_path / "nerf").mkdir()
    save_tree(procedural_tree(8), tmp_path / "nerf" / "preview.npz")
    write_live(tmp_path / "nerf", stage="training", step=10, tree="preview.npz")
    assert newest_tree(tmp_path) == tmp_path / "nerf" / "preview.npz"
    time.sleep(0.01)
    write_live(tmp_path, stage="extract done", tree="tree.npz")   # run's own, newer
    live = read_live(tmp_path)
    assert live["stage"] == "extract done" and live["tree"] == tmp_path / "tree.npz"
    write_live(tmp_path, tree="gone.npz")                          # names no file: fall back
    assert read_live(tmp_path)["tree"] is None
    (tmp_path / "secret.txt").write_text("no")
    outside = tmp_path.parent / f"{tmp_path.name}_outside.npz"
    save_tree(procedural_tree(8), outside)
    for bad in ("../" + outside.name, str(outside), "/etc/passwd", "secret.txt", 3):
        write_live(tmp_path, tree=bad)                  # only tree files inside the folder
        assert read_live(tmp_path)["tree"] is None, bad


@pytest.mark.parametrize("render", ["cpu", "webgl"])
def test_server_follows_the_run(tmp_path, render):
    with ViewerServer(tmp_path, port=0, render=render) as srv:
        s = _json(srv.url + "live.json")
        assert s["tree"] is None and s["version"] == ""
        cfg = _json(srv.url + "config.json")
        assert cfg["live"] and cfg["tree"] is None
        if render == "cpu":
            assert _get(srv.url + FRAME)[0] == 503            # no tree yet: said, not a crash
        save_tree(procedural_tree(16), tmp_path / "preview.npz")
        write_live(tmp_path, stage="training", step=120, steps=None, psnr=21.5, eta_s=300.0,
                   tree="preview.npz")
        s = _json(srv.url + "live.json")
        assert s["tree"] == "data/preview.npz" and s["step"] == 120 and s["psnr"] == 21.5
        cfg = _json(srv.url + "config.json")
        assert cfg["version"] == s["version"] != "" and cfg["tree"] == "data/preview.npz"
        code, body = _get(srv.url + "data/preview.npz")
        assert code == 200 and body == (tmp_path / "preview.npz").read_bytes()
        if render == "cpu":
            first = cfg["cpu"]["n_leaves"]
            assert _get(srv.url + FRAME)[0] == 200
        save_tree(procedural_tree(32), tmp_path / "tree.npz")
        write_live(tmp_path, stage="extract done", tree="tree.npz")
        s2 = _json(srv.url + "live.json")
        assert s2["version"] != s["version"] and s2["tree"] == "data/tree.npz"
        assert _get(srv.url + "data/preview.npz")[0] == 404           # not the newest any more
        cfg = _json(srv.url + "config.json")
        assert cfg["version"] == s2["version"]
        if render == "cpu":
            assert cfg["cpu"]["n_leaves"] > first
            (tmp_path / "broken.npz").write_bytes(b"not a tree")
            write_live(tmp_path, stage="finetune done", tree="broken.npz")
            s3 = _json(srv.url + "live.json")      # the last good tree stays, the error is said
            assert s3["version"] == s2["version"] and "broken.npz" in s3["error"]
            assert _get(srv.url + FRAME)[0] == 200


def test_page_reloads_onto_a_newer_tree_and_keeps_its_camera(tmp_path):
    pytest.importorskip("playwright")
    from test_viewer_browser import CHROMIUM, FLAGS, playwright_api

    save_tree(procedural_tree(16), tmp_path / "preview.npz")
    write_live(tmp_path, stage="training", step=50, psnr=18.0, tree="preview.npz")
    with ViewerServer(tmp_path, port=0, render="cpu") as srv, \
            playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        page = b.new_page(viewport={"width": 480, "height": 360})
        page.goto(srv.url)
        page.wait_for_function("window.viewer && window.viewer.state === 'ready'", timeout=90_000)
        page.wait_for_function("document.getElementById('live').textContent.includes('step 50')")
        assert "18.00 dB" in page.inner_text("#live")
        page.keyboard.down("ArrowLeft")
        page.wait_for_timeout(400)
        page.keyboard.up("ArrowLeft")
        page.wait_for_timeout(300)
        before = page.evaluate("window.viewer.currentView(64, 64).c2w")
        save_tree(procedural_tree(32), tmp_path / "tree.npz")
        write_live(tmp_path, stage="extract done", tree="tree.npz")
        page.wait_for_function("document.getElementById('info').textContent.includes('tree.npz')",
                               timeout=60_000)
        page.wait_for_function("window.viewer.state === 'ready'", timeout=60_000)
        after = page.evaluate("window.viewer.currentView(64, 64).c2w")
        assert after == pytest.approx(before, abs=1e-6)
        assert "extract done" in page.inner_text("#live")
        b.close()


def test_training_writes_previews_and_its_status(tmp_path):
    """The trainer's live view: previews from the first seconds on (atomic files a viewer
    can load), live.json at every log row and at the end, the previews' cost in
    summary.json; a trained model's preview shows the scene."""
    from nerf_fixtures import tiny_cpu_config, tiny_dataset

    from plenoctree.datasets import load_dataset
    from plenoctree.metrics import psnr
    from plenoctree.nerf import train
    from plenoctree.octree.io import load_tree
    from plenoctree.render import render_image

    data = tiny_dataset(tmp_path / "data")
    cfg = tiny_cpu_config(data, tmp_path / "run", steps=150)
    cfg.preview_every_s, cfg.val_views = 0.2, 0
    seen = []

    def on_step(step):
        live = read_live(tmp_path / "run")
        if live is not None:
            seen.append((step, live["stage"], live["tree"]))

    train(cfg, quiet=True, on_step=on_step)
    assert seen and all(s == "training" for _, s, _ in seen)
    assert any(t is not None for _, _, t in seen)               # a preview during training
    live = read_live(tmp_path / "run")
    assert live["stage"] == "NeRF-SH trained" and live["step"] == 150
    assert live["tree"] == tmp_path / "run" / "preview.npz"
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert 0 < summary["preview_s"] < summary["train_time_s"]
    tree = load_tree(live["tree"])
    views = load_dataset(data, split="train", limit=2)
    p = psnr(render_image(tree, views.cameras, 0).rgb.numpy(), views.images[0])
    assert p > 16.0, p                          # the untrained model scores ~14 dB here
    assert not list((tmp_path / "run").glob("*.tmp-*"))


def test_a_plain_nerf_or_no_opaque_cell_makes_no_preview():
    import torch

    from plenoctree.nerf import NeRFModel
    from plenoctree.nerf.config import ModelConfig
    from plenoctree.nerf.preview import preview_tree

    box = torch.tensor([[-1.0, -1, -1], [1, 1, 1]])
    cfg = ModelConfig(grid_levels=4, grid_base_res=4, grid_max_res=16, grid_log2_table=10,
                      net_width=16)
    model = NeRFModel(cfg, box, occ_res=16)
    with torch.no_grad():
        for prm in model.fine.parameters():
            prm.zero_()
        model.fine.head.bias.fill_(-10.0)       # σ = exp(-11) everywhere: a thin fog
    assert preview_tree(model) is None          # nothing opaque enough: no tree, no file
    plain = NeRFModel(ModelConfig(basis="plain", grid_levels=4, grid_base_res=4,
                                  grid_max_res=16, grid_log2_table=10, net_width=16), box)
    assert preview_tree(plain) is None
