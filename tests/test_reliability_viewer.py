"""Viewer server under load and attack: backlog, idle timeout, Host check, symlink swap,
trees the page refuses."""

from __future__ import annotations

import os
import selectors
import socket
import time

import numpy as np
import pytest

from plenoctree import TreeFormatError
from plenoctree.octree import Octree
from plenoctree.octree.io import save_tree
from plenoctree.viewer import ViewerServer, export_web
from plenoctree.viewer import server as server_mod
from viewer_http import get


@pytest.fixture()
def tree_file(tmp_path):
    p = tmp_path / "tree.npz"
    save_tree(Octree.dense(2, "SH4", seed=0), p)
    return p


def _get(port, path, host=None):
    status, _, body = get(port, path, host)
    return status, body


def test_host_header_check_against_dns_rebinding(tree_file):
    with ViewerServer(tree_file, port=0) as srv:
        p = srv.port
        assert _get(p, "/config.json")[0] == 200
        assert _get(p, "/config.json", host=f"localhost:{p}")[0] == 200
        for evil in ("evil.example.com", f"evil.example.com:{p}", "127.0.0.1.nip.io", f"x:{p}"):
            status, body = _get(p, "/data/tree.npz", host=evil)
            assert status == 403 and b"Host" in body


def test_tree_swapped_for_a_symlink_is_not_followed(tree_file, tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_text("private key material")
    with ViewerServer(tree_file, port=0) as srv:
        assert _get(srv.port, "/data/tree.npz")[0] == 200
        os.replace(tree_file, tmp_path / "moved.npz")
        tree_file.symlink_to(secret)                    # was served: followed the link
        status, body = _get(srv.port, "/data/tree.npz")
        assert status == 404 and b"private" not in body


def _chain_file(path, depth):
    n = depth + 1
    child = np.zeros((n, 2, 2, 2), np.int32)
    child[:-1, 0, 0, 0] = 1
    data = np.zeros((n, 2, 2, 2, 4), np.float32)
    np.savez(path, child=child, data=data.astype(np.float16), data_format=np.array("RGBA"),
             invradius3=np.full(3, 0.5, np.float32), offset=np.full(3, 0.5, np.float32),
             depth_limit=np.int64(depth))
    return path


def test_view_and_export_refuse_trees_the_page_refuses(tmp_path, capsys):
    from plenoctree.cli import main

    deep = _chain_file(tmp_path / "deep.npz", 30)       # the page stops at 22 levels
    with pytest.raises(TreeFormatError, match=f"{deep}: .*MAX_DEPTH"):
        ViewerServer(deep, port=0)
    with pytest.raises(TreeFormatError, match="MAX_DEPTH"):
        export_web(deep, tmp_path / "web")
    assert not (tmp_path / "web").exists()
    assert main(["export-web", str(deep), "--out", str(tmp_path / "web2")]) == 1
    assert "MAX_DEPTH" in capsys.readouterr().err
    ok = _chain_file(tmp_path / "ok.npz", 21)
    with ViewerServer(ok, port=0) as srv:
        assert _get(srv.port, "/data/ok.npz")[0] == 200


def test_idle_connections_are_closed(tree_file, monkeypatch):
    assert server_mod._Handler.timeout == server_mod.IDLE_TIMEOUT_S <= 60
    monkeypatch.setattr(server_mod._Handler, "timeout", 0.3)
    with ViewerServer(tree_file, port=0) as srv:
        s = socket.create_connection(("127.0.0.1", srv.port), timeout=10)
        s.sendall(b"GET /config.json HTTP/1.1\r\nHost: 127.0.0.1")   # never finished
        t0 = time.monotonic()
        assert s.recv(100) == b""                       # closed by the server, not by us
        assert time.monotonic() - t0 < 5
        s.close()


def test_1000_concurrent_requests_are_all_answered(tree_file):
    """A burst of 1,000 connections on loopback (was: a 5-connection backlog, up to 69 % of a
    500-request burst timed out)."""
    n = 1000
    with ViewerServer(tree_file, port=0) as srv:
        assert srv.httpd.request_queue_size >= n
        req = (f"GET /config.json HTTP/1.1\r\nHost: 127.0.0.1:{srv.port}\r\n"
               "Connection: close\r\n\r\n").encode()
        sel = selectors.DefaultSelector()
        socks = []
        for _ in range(n):                              # all connect before any is served
            s = socket.socket()
            s.setblocking(False)
            s.connect_ex(("127.0.0.1", srv.port))
            sel.register(s, selectors.EVENT_WRITE, bytearray())
            socks.append(s)
        answered, deadline = 0, time.monotonic() + 20
        while sel.get_map() and time.monotonic() < deadline:
            for key, ev in sel.select(timeout=0.5):
                s, buf = key.fileobj, key.data
                if ev & selectors.EVENT_WRITE:
                    s.sendall(req)
                    sel.modify(s, selectors.EVENT_READ, buf)
                    continue
                try:
                    chunk = s.recv(65536)
                except (ConnectionResetError, BlockingIOError):
                    chunk = b""
                if chunk:
                    buf += chunk
                    continue
                sel.unregister(s)
                if buf.startswith(b"HTTP/1.1 200"):
                    answered += 1
        for s in socks:
            s.close()
    assert answered == n
