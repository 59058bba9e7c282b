"""The viewer's local server (only its own files and the tree) and the static bundle export."""

from __future__ import annotations

import http.client
import json
import re

import numpy as np
import pytest

from plenoctree.cli import main
from plenoctree.errors import ConfigError
from plenoctree.octree import Octree
from plenoctree.octree.io import save_tree
from plenoctree.viewer import ViewerServer, export_web, static_dir
from plenoctree.viewer.server import static_files


@pytest.fixture(scope="module")
def tree_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("viewer") / "my tree.npz"     # a name that needs escaping
    save_tree(Octree.dense(1, "SH4", seed=0), path, precision="fp16")
    (path.parent / "secret.txt").write_text("do not serve")
    return path


@pytest.fixture(scope="module")
def server(tree_file):
    with ViewerServer(tree_file, port=0) as srv:
        yield srv


def _get(srv, path, method="GET"):
    conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=10)
    conn.putrequest(method, path, skip_host=False, skip_accept_encoding=True)
    conn.endheaders()
    resp = conn.getresponse()
    body = resp.read()
    conn.close()
    return resp.status, dict(resp.getheaders()), body


def test_serves_page_config_and_tree(server, tree_file):
    assert server.url == f"http://127.0.0.1:{server.port}/"
    assert server.httpd.server_address[0] == "127.0.0.1"
    status, headers, body = _get(server, "/")
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert b'type="module"' in body and b"main.js" in body
    for name in ("main.js", "renderer.js", "tree.js", "npz.js", "camera.js"):
        status, headers, body = _get(server, "/" + name)
        assert status == 200 and headers["Content-Type"].startswith("text/javascript")
        assert body == (static_dir() / name).read_bytes()
    status, _, body = _get(server, "/config.json")
    cfg = json.loads(body)
    assert status == 200 and cfg["tree"] == "data/tree.npz" and "plenoctree lod" in cfg["lod_hint"]
    status, headers, body = _get(server, "/data/tree.npz")
    assert status == 200 and body == tree_file.read_bytes()
    assert int(headers["Content-Length"]) == len(body)
    status, headers, body = _get(server, "/data/tree.npz", method="HEAD")
    assert status == 200 and body == b"" and int(headers["Content-Length"]) > 0


@pytest.mark.parametrize("path", [
    "/../secret.txt", "/data/../secret.txt", "/..%2fsecret.txt", "/%2e%2e/secret.txt",
    "/data/%2E%2E/%2E%2E/etc/passwd", "/data/..\\secret.txt", "/./index.html",
    "/data/tree.npz/../../secret.txt", "/%00index.html",
])
def test_rejects_traversal(server, path):
    status, _, body = _get(server, path)
    assert status == 400, path
    assert b"do not serve" not in body


@pytest.mark.parametrize("path", [
    "/secret.txt", "/data/", "/data", "/static/", "/static/main.js", "/data/secret.txt",
    "/__init__.py", "/server.py", "/data/my%20tree.npz", "/index.html/", "//etc/passwd",
])
def test_unknown_files_are_404_and_no_listing(server, path):
    status, _, body = _get(server, path)
    assert status == 404, path
    assert b"<a href" not in body and b"do not serve" not in body


def test_only_get_and_head(server):
    assert _get(server, "/", method="POST")[0] == 405
    assert _get(server, "/", method="DELETE")[0] == 405


def test_server_errors(tree_file, tmp_path, server):
    with pytest.raises(ConfigError, match="no such tree"):
        ViewerServer(tmp_path / "missing.npz", port=0)
    with pytest.raises(ConfigError, match="--port 0"):
        ViewerServer(tree_file, port=server.port)          # already taken
    names = static_files()
    assert "index.html" in names and all(re.fullmatch(r"[\w.\-]+", n) for n in names)
    assert not any(n.endswith(".py") for n in names)


def test_no_external_urls_in_the_page():
    for name, path in static_files().items():
        text = path.read_text()
        assert not re.search(r"(src|href)=[\"']?(https?:)?//", text), name
        assert not re.search(r"import[^;]*from\s*[\"']https?:", text), name


def test_export_web(tree_file, tmp_path):
    out = export_web(tree_file, tmp_path / "site", title="Lego")
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert "index.html" in files and "config.json" in files and "data/tree.npz" in files
    assert set(static_files()) <= set(files)
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["tree"] == "data/tree.npz" and cfg["title"] == "Lego"
    assert (out / "data/tree.npz").read_bytes() == tree_file.read_bytes()
    with pytest.raises(ConfigError, match="not empty"):
        export_web(tree_file, out)
    export_web(tree_file, out, overwrite=True)
    with pytest.raises(ConfigError, match="no such tree"):
        export_web(tmp_path / "nope.npz", tmp_path / "x")


def test_cli_export_and_view_errors(tree_file, tmp_path, capsys):
    assert main(["export-web", str(tree_file), "--out", str(tmp_path / "b")]) == 0
    assert "http.server" in capsys.readouterr().out
    garbage = tmp_path / "garbage.plnz"
    garbage.write_bytes(np.arange(100, dtype=np.uint8).tobytes())
    assert main(["view", str(garbage), "--port", "0"]) == 1
    assert "garbage.plnz" in capsys.readouterr().err
    assert main(["export-web", str(garbage), "--out", str(tmp_path / "c")]) == 1


def test_texture_budget(tree_file, tmp_path, capsys):
    from plenoctree.compression import CompressOptions, compress, save_compressed
    from plenoctree.octree.io import load_tree
    from plenoctree.viewer.budget import (check_texture_budget, texels_per_leaf,
                                          viewer_texture_bytes)

    assert [texels_per_leaf(b) for b in (1, 4, 9, 16, 25)] == [1, 4, 7, 13, 19]
    t = load_tree(tree_file)
    kept = int(((t.child == 0) & (t.data[..., -1] > 0)).sum())
    plnz = tmp_path / "t.plnz"
    save_compressed(compress(t, CompressOptions(bits=8)), plnz)
    cells = t.n_nodes * 8
    assert viewer_texture_bytes(plnz) == cells * 4 + kept * 4 * 8
    assert viewer_texture_bytes(tree_file) == cells * 4 + cells * 4 * 8     # upper bound
    assert check_texture_budget(plnz) > 0
    with pytest.raises(ConfigError, match="plenoctree lod"):
        check_texture_budget(plnz, max_mb=1e-4)
    assert main(["view", str(plnz), "--port", "0", "--max-mb", "0.0001"]) == 1
    err = capsys.readouterr().err
    assert "budget" in err and "plenoctree lod" in err
    assert main(["export-web", str(plnz), "--out", str(tmp_path / "x"), "--max-mb", "1e-4"]) == 1
