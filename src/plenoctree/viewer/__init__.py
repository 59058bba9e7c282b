"""The in-browser PlenOctree viewer: a static WebGL2 page, a local server and a bundle exporter.

The page (``static/``: plain JS modules, no external dependency) reads native, svox and
compressed trees in the browser, packs them into textures within the device's limits and
ray-marches them with the CPU renderer's semantics.
"""

from __future__ import annotations

from .export import export_web
from .server import ViewerServer, static_dir

__all__ = ["ViewerServer", "export_web", "static_dir"]
