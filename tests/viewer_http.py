"""Shared helper of the viewer server tests: one GET with a chosen ``Host`` header."""

from __future__ import annotations

import http.client


def get(port: int, path: str, host: str | None = None, timeout: float = 10):
    """``(status, headers, body)`` of ``GET path`` on ``127.0.0.1:port``; ``host`` replaces the
    ``Host`` header (default ``127.0.0.1:port``)."""
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    c.putrequest("GET", path, skip_host=True)
    c.putheader("Host", host if host is not None else f"127.0.0.1:{port}")
    c.endheaders()
    r = c.getresponse()
    body = r.read()
    c.close()
    return r.status, dict(r.getheaders()), body
