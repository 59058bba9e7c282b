"""Screenshot of the web viewer in headless Chromium (the Playwright set-up of the tests), as in
docs/viewer.md: the tree served by ``ViewerServer`` with the dataset's training cameras, optionally
a mesh (``plenoctree export``) inserted beside it, seen from a fixed camera.

    .venv/bin/python scripts/viewer_screenshot.py lego_web.plnz --data DATASET \\
        --mesh lego128.glb --shift 0,2.6,0 --out docs/viewer_mesh.png

Needs ``scripts/install_browser.sh`` (run by ``./run test``).
"""

from __future__ import annotations

import argparse
import base64
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tree")
    ap.add_argument("--data", default=None, help="dataset whose training cameras to list")
    ap.add_argument("--mesh", default=None, help="a .glb to insert (plenoctree export)")
    ap.add_argument("--shift", default="0,2.6,0", help="world translation of the mesh")
    ap.add_argument("--direction", default="0.80,-0.42,0.43",
                    help="from the look-at point towards the eye")
    ap.add_argument("--distance", type=float, default=7.2)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)

    import trimesh
    from playwright.sync_api import sync_playwright

    from plenoctree.datasets import load_dataset
    from plenoctree.datasets.procedural import look_at
    from plenoctree.viewer import ViewerServer
    from plenoctree.viewer.export import add_cameras_to_server, cameras_config

    sys.path.insert(0, str(ROOT / "tests"))
    from test_viewer_browser import CHROMIUM, FLAGS

    shift = np.array([float(v) for v in a.shift.split(",")]) if a.mesh else np.zeros(3)
    glb = None
    if a.mesh:
        scene = trimesh.load(a.mesh)
        mesh = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
        mesh.apply_translation([shift[0], shift[2], -shift[1]])    # glTF +Y up: (x, z, -y)
        glb = base64.b64encode(mesh.export(file_type="glb")).decode()
    target = shift / 2
    d = np.array([float(v) for v in a.direction.split(",")])
    c2w = look_at(target + a.distance * d / np.linalg.norm(d), target)
    with ViewerServer(a.tree, port=0) as srv:
        if a.data:
            data = load_dataset(a.data, "train", downscale=4)
            add_cameras_to_server(srv, cameras_config(data.cameras, data.names))
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
            page = b.new_page(viewport={"width": 900, "height": 560})
            page.goto(srv.url + "?scale=1")
            page.wait_for_function("window.viewer && window.viewer.state !== 'loading'",
                                   timeout=600_000)
            if page.evaluate("window.viewer.state") != "ready":
                print(page.evaluate("window.viewer.message"), file=sys.stderr)
                return 1
            if glb:
                page.evaluate("b => window.viewer.addMesh(b, 'mesh.glb')", glb)
            w, h = page.evaluate("[document.getElementById('canvas').clientWidth, "
                                 "document.getElementById('canvas').clientHeight]")
            f = 0.5 * h / np.tan(np.radians(20))
            page.evaluate("v => window.viewer.setView(v)",
                          {"c2w": c2w.reshape(-1).tolist(), "fx": f, "fy": f, "cx": w / 2,
                           "cy": h / 2, "width": w, "height": h})
            page.evaluate("window.viewer.render()")
            page.keyboard.press("h")                  # hide the hints
            page.wait_for_timeout(500)
            page.screenshot(path=a.out)
            b.close()
    print(f"-> {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
