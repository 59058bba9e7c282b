"""A local HTTP server for the web viewer: its own static files and one tree, nothing else.

Bound to 127.0.0.1 unless given another host (``--host``: then anyone who can reach that
address can fetch the tree; see docs/viewer.md for an ``ssh -L`` tunnel instead). The URL
space is a fixed table built at start-up:

- ``/`` and ``/index.html``: the page; ``/<name>`` for each regular file of ``static/``;
- ``/config.json``: ``{"tree": "data/<tree file name>", ...}`` (generated);
- ``/data/<tree file name>``: the tree (raw ``.npz`` or compressed ``.plnz``), streamed;
- ``/frame?...``: with ``render`` ``"cpu"`` or ``"auto"`` only, a JPEG frame of the tree drawn
  by the CPU renderer for the page's camera (:mod:`.frames`); bad parameters answer 400.

Any other path, including every path with ``..``, a backslash, a NUL or an encoded slash, is
answered 404 or 400 without touching the file system; there is no directory listing. Only GET
and HEAD are allowed. Requests whose ``Host`` header is not this server's address (loopback,
or the host it was started on) are refused (403: DNS rebinding); files are opened with
``O_NOFOLLOW`` (a tree swapped for a symlink is not followed). The listen backlog holds
``BACKLOG`` connections and an idle connection is closed after ``IDLE_TIMEOUT_S`` seconds. The
tree is validated before serving (:func:`check_servable`): the page would refuse what the
loaders refuse.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import os
import re
import shutil
import socket
import stat
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from ..errors import ConfigError
from .budget import DEFAULT_MAX_MB
from .frames import RENDER_MODES, FrameRenderer, parse_frame_query
from .live import LiveTrees

__all__ = ["ViewerServer", "static_dir", "static_files", "viewer_config", "check_servable",
           "is_loopback", "BACKLOG", "IDLE_TIMEOUT_S"]

logger = logging.getLogger(__name__)

BACKLOG = 1024           # queued connections (the kernel caps it at net.core.somaxconn)
IDLE_TIMEOUT_S = 20.0    # a connection silent this long (slow or idle client) is closed
_O_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)

_SAFE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
_TYPES = {
    ".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8", ".json": "application/json",
    ".png": "image/png", ".svg": "image/svg+xml", ".ico": "image/x-icon",
}


def static_dir() -> Path:
    """The folder of the page's files (``plenoctree/viewer/static``)."""
    return Path(__file__).resolve().parent / "static"


def static_files() -> dict[str, Path]:
    """``{file name: path}`` of the page's files (regular files with safe names only)."""
    out = {}
    for p in sorted(static_dir().iterdir()):
        if p.is_file() and not p.is_symlink() and _SAFE_NAME.match(p.name) \
                and not p.name.endswith((".pyc", ".tmp")):
            out[p.name] = p
    if "index.html" not in out:
        raise ConfigError(f"{static_dir()}: the viewer's index.html is missing (broken install)")
    return out


def viewer_config(tree_name: str, title: str | None = None,
                  max_mb: float = DEFAULT_MAX_MB) -> dict[str, Any]:
    """The ``config.json`` the page reads: tree URL (relative), title, LOD hint, texture
    budget in MB."""
    stem = tree_name.rsplit(".", 1)[0]
    return {
        "tree": f"data/{tree_name}",
        "title": title or f"{tree_name} - PlenOctree viewer",
        "lod_hint": f"plenoctree lod {tree_name} --target-mb 30 --out {stem}_web.plnz",
        "max_mb": float(max_mb),
    }


def check_servable(path: str | os.PathLike) -> Any:
    """Raise :class:`~plenoctree.errors.TreeFormatError` (naming the file) unless the page can
    show the tree: the full loader checks (topology, ``MAX_DEPTH`` = the page's 22 levels,
    finite values, codebook indices). Loads the tree once and returns it (an ``Octree``)."""
    from ..compression.fileio import load_any_tree

    return load_any_tree(path)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) is this machine's loopback only."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _is_wildcard(host: str) -> bool:
    """Whether ``host`` is the any-interface address (0.0.0.0, ::)."""
    try:
        return ipaddress.ip_address(host.strip("[]")).is_unspecified
    except ValueError:
        return False


def _allowed_hosts(host: str, port: int) -> set[str]:
    """``Host`` header values the server answers: loopback names, the host it listens on and,
    for a wildcard address (0.0.0.0, ::), this machine's names and addresses."""
    names = {"127.0.0.1", "localhost", host.strip("[]").lower()}
    if _is_wildcard(host):
        hostname = socket.gethostname()
        names |= {hostname.lower(), socket.getfqdn().lower()}
        try:
            names |= {str(a[4][0]).lower() for a in socket.getaddrinfo(hostname, None)}
        except OSError:
            pass
    out = set()
    for n in names:
        n = f"[{n}]" if ":" in n else n          # an IPv6 literal in a Host header
        out |= {n, f"{n}:{port}"}
    return out


def _open_regular(path: Path) -> Any:
    """Open ``path`` for reading without following a symlink; None if it is not a regular file."""
    try:
        fd = os.open(path, os.O_RDONLY | _O_NOFOLLOW)
    except OSError:
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            return None
    except OSError:
        os.close(fd)
        return None
    return os.fdopen(fd, "rb")


def _tree_name(path: Path) -> str:
    name = path.name
    if not _SAFE_NAME.match(name):
        name = "tree" + "".join(path.suffixes[-1:]) if path.suffix in (".npz", ".plnz") else "tree.npz"
    return name


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"
    timeout = IDLE_TIMEOUT_S     # socket timeout: idle keep-alive and slow clients are dropped
    # headers and body are two writes: with Nagle's algorithm the body would wait for the
    # client's delayed ACK of the headers (~40 ms per frame on Linux)
    disable_nagle_algorithm = True

    def log_message(self, fmt: str, *args: Any) -> None:      # quiet unless asked
        if self.server.verbose:
            super().log_message(fmt, *args)

    def _error(self, status: HTTPStatus, text: str) -> None:
        body = f"{status.value} {status.phrase}: {text}\n".encode()
        self.send_response(status)
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _resolve(self) -> tuple[bytes | Path, str] | None:
        raw = urlsplit(self.path).path
        if "\\" in raw or "\x00" in raw or "%2f" in raw.lower() or "%5c" in raw.lower():
            self._error(HTTPStatus.BAD_REQUEST, "bad path")
            return None
        path = unquote(raw)
        parts = path.split("/")
        if any(p in ("..", ".") for p in parts) or "\x00" in path or "\\" in path:
            self._error(HTTPStatus.BAD_REQUEST, "bad path")
            return None
        entry = self.server.routes.get(path)
        if entry is None:
            self._error(HTTPStatus.NOT_FOUND, "no such file")
            return None
        return entry

    def _host_ok(self) -> bool:
        host = self.headers.get("Host")
        if host is None or host.strip().lower() in self.server.hosts:
            return True
        self._error(HTTPStatus.FORBIDDEN, "unexpected Host header (this server answers only "
                                          f"{self.server.host_label}:{self.server.server_address[1]})")
        return False

    def _send_frame(self, query: str, head_only: bool) -> None:
        """``/frame``: a JPEG of the CPU renderer (400 for bad parameters, never a traceback)."""
        frames = self.server.frames
        if self.server.live is not None:
            frames, _ = self.server.live.frames()
            if frames is None:
                self._error(HTTPStatus.SERVICE_UNAVAILABLE, "the run has no tree yet")
                return
        try:
            req = parse_frame_query(query)
            body, render_ms, encode_ms = frames.jpeg(req)
        except ConfigError as e:
            self._error(HTTPStatus.BAD_REQUEST, str(e))
            return
        except Exception as e:                  # a bug: say so, keep serving
            logger.error("viewer: /frame failed: %s: %s", type(e).__name__, e)
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"frame failed ({type(e).__name__})")
            return
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "image/jpeg")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("X-Render-Ms", f"{render_ms:.2f}")
        self.send_header("X-Encode-Ms", f"{encode_ms:.2f}")
        self.end_headers()
        if not head_only:
            try:
                self.wfile.write(body)
            except (BrokenPipeError, ConnectionResetError):
                pass

    def _send_live(self, path: str, head_only: bool) -> None:
        """A run folder's dynamic URLs (:mod:`.live`): ``/live.json``, ``/config.json`` and
        ``/data/<the newest tree>``."""
        live = self.server.live
        if path.startswith("/data/"):
            name = unquote(path[len("/data/"):])
            f = live.file(name) if _SAFE_NAME.match(name) else None
            entry: tuple[bytes | Path, str] | None = (f, "application/octet-stream") \
                if f is not None else None
        else:
            status = live.status()
            body = status if path == "/live.json" else self.server.live_config(status)
            entry = (json.dumps(body, indent=1).encode(), _TYPES[".json"])
        if entry is None:
            self._error(HTTPStatus.NOT_FOUND, "not the run's newest tree (it moved on)")
            return
        self._send_entry(entry, head_only)

    def _send(self, head_only: bool) -> None:
        if not self._host_ok():
            return
        url = urlsplit(self.path)
        live = self.server.live
        if url.path == "/frame" and (self.server.frames is not None or
                                     (live is not None and live.cpu)):
            self._send_frame(url.query, head_only)
            return
        if live is not None and (url.path in ("/live.json", "/config.json")
                                 or url.path.startswith("/data/")):
            self._send_live(url.path, head_only)
            return
        entry = self._resolve()
        if entry is not None:
            self._send_entry(entry, head_only)

    def _send_entry(self, entry: tuple[bytes | Path, str], head_only: bool) -> None:
        body, ctype = entry
        if isinstance(body, Path):
            f = _open_regular(body)
            if f is None:
                self._error(HTTPStatus.NOT_FOUND, "file is gone (or replaced by a symlink)")
                return
            with f:
                size = os.fstat(f.fileno()).st_size
                self._headers(ctype, size)
                if not head_only:
                    try:
                        shutil.copyfileobj(f, self.wfile, 1 << 20)
                    except (BrokenPipeError, ConnectionResetError):
                        pass
            return
        self._headers(ctype, len(body))
        if not head_only:
            self.wfile.write(body)

    def _headers(self, ctype: str, size: int) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(size))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()

    def do_GET(self) -> None:  # noqa: N802
        self._send(head_only=False)

    def do_HEAD(self) -> None:  # noqa: N802
        self._send(head_only=True)

    def _not_allowed(self) -> None:
        self._error(HTTPStatus.METHOD_NOT_ALLOWED, "only GET and HEAD")

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _not_allowed  # noqa: N815


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = False
    request_queue_size = BACKLOG
    routes: dict[str, tuple[bytes | Path, str]]
    config_extra: dict[str, Any]
    title: str
    max_mb: float
    render: str
    hosts: set[str]
    host_label: str
    frames: FrameRenderer | None
    live: LiveTrees | None = None
    verbose: bool

    def live_config(self, status: dict[str, Any]) -> dict[str, Any]:
        """``config.json`` of a run folder's newest tree (``status``: :meth:`LiveTrees.status`)."""
        name = status["tree"].split("/")[-1] if status.get("tree") else ""
        cfg = viewer_config(name or "tree.npz", self.title, self.max_mb)
        cfg.update(self.config_extra, live=True, version=status["version"],
                   tree=status.get("tree"), title=self.title)
        if self.live.cpu:
            frames, _ = self.live.frames()
            if frames is not None:
                cfg.update(render=self.render, cpu=frames.info())
        return cfg

    def handle_error(self, request: Any, client_address: Any) -> None:
        if self.verbose:             # a client that vanished or timed out: not our error
            super().handle_error(request, client_address)


class _Server6(_Server):
    address_family = socket.AF_INET6


class ViewerServer:
    """Serve the viewer page and one tree on ``http://<host>:<port>/``.

    Args:
        tree_path: the tree to show (``.npz`` or ``.plnz``); must exist. Or a run folder
            (``run --out``, ``train --out``): its newest tree, swapped as newer ones land
            (:mod:`.live`).
        port: TCP port; 0 picks a free one.
        title: page title (default: the tree's file name).
        max_mb: the page's texture budget in MB (it refuses larger trees with a hint).
        verbose: log every request to stderr.
        check: validate the tree first (:func:`check_servable`; ``TreeFormatError``).
        render: who draws (:data:`~.frames.RENDER_MODES`): ``"webgl"`` (the page, on the
            browser's GPU), ``"cpu"`` (this server, with the numba renderer: ``/frame``) or
            ``"auto"`` (CPU when the page finds only a software WebGL or none). The tree is
            loaded and kept in memory for ``cpu`` and ``auto``.
        host: the address to listen on (default loopback; any other exposes the tree to every
            machine that can reach it: :func:`is_loopback`).

    Use :meth:`start` (background thread) / :meth:`stop`, or :meth:`serve_forever`; or as a
    context manager. :attr:`url` is the page's address.
    """

    def __init__(self, tree_path: str | os.PathLike, port: int = 8000, title: str | None = None,
                 max_mb: float = DEFAULT_MAX_MB, verbose: bool = False,
                 check: bool = True, render: str = "webgl", host: str = "127.0.0.1") -> None:
        tree = Path(tree_path)
        live = tree.is_dir()                 # a run folder: its newest tree, live (.live)
        if not tree.is_file() and not live:
            raise ConfigError(f"{tree}: no such tree file or run folder")
        if not 0 <= int(port) <= 65535:
            raise ConfigError(f"port must be in 0..65535, got {port}")
        if render not in RENDER_MODES:
            raise ConfigError(f"render must be one of {', '.join(RENDER_MODES)}, got {render!r}")
        loaded = check_servable(tree) if not live and (check or render != "webgl") else None
        frames = None if render == "webgl" or live else FrameRenderer(loaded)
        self.tree_path = tree.resolve()
        self.render = render
        self.tree_name = "" if live else _tree_name(tree)
        routes: dict[str, tuple[bytes | Path, str]] = {}
        for name, p in static_files().items():
            routes["/" + name] = (p, _TYPES.get(p.suffix, "application/octet-stream"))
        routes["/"] = routes["/index.html"]
        if not live:
            config = viewer_config(self.tree_name, title, max_mb)
            if frames is not None:
                config.update(render=render, cpu=frames.info())
            routes["/config.json"] = (json.dumps(config, indent=1).encode(), _TYPES[".json"])
            routes["/data/" + self.tree_name] = (self.tree_path, "application/octet-stream")
        self.host = host.strip("[]")
        server_class = _Server6 if ":" in self.host else _Server
        try:
            self.httpd = server_class((self.host, int(port)), _Handler)
        except (OSError, OverflowError) as e:
            raise ConfigError(f"cannot listen on {host}:{port} ({getattr(e, 'strerror', None) or e});"
                              " pass --port 0 to pick a free port") from None
        self.httpd.routes = routes
        self.httpd.verbose = verbose
        self.httpd.frames = frames
        self.httpd.live = LiveTrees(tree, render != "webgl") if live else None
        self.httpd.title = title or f"{tree.name} (live) - PlenOctree viewer"
        self.httpd.max_mb, self.httpd.render, self.httpd.config_extra = max_mb, render, {}
        self.httpd.host_label = self.host
        self.httpd.hosts = _allowed_hosts(self.host, self.port)
        self._thread: threading.Thread | None = None
        if frames is not None:                   # load the compiled kernel before the page asks
            threading.Thread(target=frames.warm_up, daemon=True, name="viewer-warm-up").start()

    @property
    def port(self) -> int:
        return int(self.httpd.server_address[1])

    @property
    def url(self) -> str:
        """The page's address (loopback for a wildcard host)."""
        host = "127.0.0.1" if _is_wildcard(self.host) else self.host
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}/"

    def start(self) -> ViewerServer:
        """Serve in a daemon thread; returns self."""
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True,
                                        name="plenoctree-viewer")
        self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Serve in this thread until :meth:`stop` or KeyboardInterrupt."""
        try:
            self.httpd.serve_forever()
        finally:
            self.httpd.server_close()

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def __enter__(self) -> ViewerServer:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()
