"""Training cameras in the viewer bundle: config.json contents, export-web/view --data (no browser)."""

from __future__ import annotations

import json
import urllib.request

import numpy as np
import pytest

from plenoctree.cli import main
from plenoctree.datasets import load_dataset
from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
from plenoctree.octree.io import save_tree
from plenoctree.viewer import ViewerServer
from plenoctree.viewer.export import add_cameras_to_server, cameras_config


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("vc")
    write_procedural_dataset(d / "data", n_train=5, n_val=1, n_test=1, width=16, height=16)
    save_tree(procedural_tree(16), d / "t.npz")
    return d


def test_cameras_config_layout(scene):
    data = load_dataset(scene / "data", "train")
    cfg = cameras_config(data.cameras, data.names)
    assert cfg["up"] == "+z"
    c = cfg["cameras"]
    assert len(c["c2w"]) == 5 and len(c["c2w"][0]) == 16
    np.testing.assert_allclose(np.reshape(c["c2w"], (5, 4, 4)), data.cameras.c2w, atol=1e-6)
    assert c["fx"] == pytest.approx(float(data.cameras.fx)) and c["width"] == 16
    assert c["names"] == data.names
    few = cameras_config(data.cameras, data.names, max_cameras=2)["cameras"]
    assert few["names"] == [data.names[0], data.names[-1]]


def test_ndc_cameras_add_the_reference_camera(scene):
    import dataclasses

    cams = dataclasses.replace(load_dataset(scene / "data", "train").cameras, ndc=True,
                               ndc_near=1.5)
    cfg = cameras_config(cams)
    fx, fy = cams.ndc_focal
    assert cfg["ndc"] == {"fx": pytest.approx(fx), "fy": pytest.approx(fy), "width": 16,
                          "height": 16, "near": 1.5}
    assert "ndc" not in cameras_config(load_dataset(scene / "data", "train").cameras)


def test_export_web_with_data(scene, tmp_path, capsys):
    out = tmp_path / "site"
    assert main(["export-web", str(scene / "t.npz"), "--out", str(out), "--data",
                 str(scene / "data")]) == 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["tree"] == "data/t.npz" and cfg["up"] == "+z"
    assert len(cfg["cameras"]["c2w"]) == 5
    out2 = tmp_path / "site2"
    assert main(["export-web", str(scene / "t.npz"), "--out", str(out2), "--data",
                 str(scene / "data"), "--split", "test"]) == 0
    assert len(json.loads((out2 / "config.json").read_text())["cameras"]["c2w"]) == 1
    assert main(["export-web", str(scene / "t.npz"), "--out", str(tmp_path / "s3"), "--data",
                 str(tmp_path / "nope")]) == 1
    assert "nope" in capsys.readouterr().err


def test_server_serves_the_cameras(scene):
    data = load_dataset(scene / "data", "train")
    with ViewerServer(scene / "t.npz", port=0) as srv:
        add_cameras_to_server(srv, cameras_config(data.cameras, data.names))
        cfg = json.loads(urllib.request.urlopen(srv.url + "config.json").read())
    assert cfg["tree"] == "data/t.npz" and len(cfg["cameras"]["c2w"]) == 5


def test_bundle_starts_on_the_datasets_background(scene, tmp_path):
    """export-web --data writes the dataset's background into config.json: white for renders,
    black for real photos (an LLFF folder), the colour eval and video use (that the page starts
    on it: test_viewer_browser's bundle test)."""
    from plenoctree.datasets.forward_facing import write_forward_facing_dataset

    ff = write_forward_facing_dataset(tmp_path / "ff", n_images=5, width=16, height=12,
                                      n_samples=8)
    for data, want in ((scene / "data", [1.0, 1.0, 1.0]), (ff, [0.0, 0.0, 0.0])):
        out = tmp_path / f"site_{want[0]:.0f}"
        assert main(["export-web", str(scene / "t.npz"), "--out", str(out), "--data",
                     str(data)]) == 0
        assert json.loads((out / "config.json").read_text())["background"] == want
