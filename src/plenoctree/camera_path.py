"""Camera paths from files: the nerfstudio camera-path JSON (``ns-render camera-path`` input).

Format (what the nerfstudio viewer's "Render" panel exports)::

    {"camera_type": "perspective", "render_width": 1920, "render_height": 1080,
     "fps": 24, "seconds": 4,
     "camera_path": [{"camera_to_world": [16 numbers, row-major 4x4], "fov": 50.0,
                      "aspect": 1.777}, ...]}

``camera_to_world`` is an OpenGL camera-to-world matrix (x right, y up, looking down -z), the
package's convention. ``fov`` is the vertical field of view in degrees (three.js), so
``fx = fy = 0.5 H / tan(fov / 2)``, principal point at the image centre. Only perspective
cameras are supported. Poses made in the nerfstudio viewer live in nerfstudio's normalised
world; its ``dataparser_transforms.json`` (``{"transform": 3x4, "scale": s}``, a pose maps as
``c2w_ns = s ∘ (T @ c2w)`` with the scale on the translation) maps them back to the dataset's
world, the one our trees use (``dataparser_transforms=``).

Same layer as :mod:`plenoctree.video` (datasets only).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .datasets import Cameras
from .errors import ConfigError, DatasetError

__all__ = ["load_camera_path", "load_dataparser_transform", "CameraPath"]


class CameraPath:
    """A loaded camera path: ``cameras`` (:class:`Cameras`) and the file's ``fps`` (or None)."""

    def __init__(self, cameras: Cameras, fps: float | None, source: str) -> None:
        self.cameras, self.fps, self.source = cameras, fps, source

    def __len__(self) -> int:
        return len(self.cameras)


def _fail(path: Any, problem: str) -> ConfigError:
    return ConfigError(f"{os.fspath(path)}: {problem}")


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise _fail(path, "no such file") from None
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise _fail(path, f"not a JSON file ({e})") from None


def load_dataparser_transform(path: str | os.PathLike) -> np.ndarray:
    """The 4x4 point map from nerfstudio world back to dataset world, ``inv(S @ T)`` with
    ``S = diag(s, s, s, 1)`` (float64), from a ``dataparser_transforms.json``.

    Applied to a nerfstudio camera-to-world it gives the dataset pose with its rotation block
    scaled by ``1/s``; :func:`load_camera_path` removes that uniform scale."""
    path = Path(path)
    obj = _read_json(path)
    try:
        t = np.asarray(obj["transform"], dtype=np.float64)
        s = float(obj["scale"])
    except (KeyError, TypeError, ValueError):
        raise _fail(path, "expected {'transform': 3x4 matrix, 'scale': number}") from None
    if t.shape == (4, 4):
        t = t[:3]
    if t.shape != (3, 4) or not np.all(np.isfinite(t)) or not (math.isfinite(s) and s > 0):
        raise _fail(path, f"transform must be a finite 3x4 matrix and scale > 0, got shape "
                          f"{list(t.shape)} and scale {s}")
    fwd = np.eye(4)
    fwd[:3] = t
    fwd[:3] *= s                  # scale after the transform: translation and rotation rows
    return np.linalg.inv(fwd)


def load_camera_path(path: str | os.PathLike, width: int | None = None,
                     height: int | None = None,
                     dataparser_transforms: str | os.PathLike | None = None) -> CameraPath:
    """Read a nerfstudio camera-path JSON into :class:`Cameras` (see the module docstring).

    Args:
        width, height: render size (default the file's ``render_width``/``render_height``);
            the focal length follows the height so the vertical field of view is kept.
        dataparser_transforms: nerfstudio's ``dataparser_transforms.json`` when the path was
            made in the nerfstudio viewer of a nerfstudio-processed dataset.
    Raises:
        ConfigError naming the file and the problem (missing keys, non-finite or non-rigid
        poses, bad field of view, unsupported camera type, empty path).
    """
    path = Path(path)
    obj = _read_json(path)
    if not isinstance(obj, dict) or not isinstance(obj.get("camera_path"), list):
        raise _fail(path, "not a nerfstudio camera path (no 'camera_path' list)")
    ctype = str(obj.get("camera_type", "perspective")).lower()
    if ctype != "perspective":
        raise _fail(path, f"camera_type {ctype!r} is not supported (only perspective)")
    frames = obj["camera_path"]
    if not frames:
        raise _fail(path, "'camera_path' is empty")
    try:
        w = int(width if width is not None else obj["render_width"])
        h = int(height if height is not None else obj["render_height"])
    except (KeyError, TypeError, ValueError):
        raise _fail(path, "needs render_width and render_height (or give --width/--height)"
                    ) from None
    from .datasets import check_frame_count, check_image_size

    try:
        check_image_size(w, h, "render size" if width is None else "--width/--height")
        check_frame_count(len(frames), "camera_path")
    except (ConfigError, DatasetError) as e:
        raise _fail(path, str(e)) from None
    c2w = np.empty((len(frames), 4, 4), dtype=np.float64)
    focal = np.empty(len(frames), dtype=np.float64)
    for i, fr in enumerate(frames):
        try:
            m = np.asarray(fr["camera_to_world"], dtype=np.float64).reshape(4, 4)
            fov = float(fr["fov"])
        except (KeyError, TypeError, ValueError):
            raise _fail(path, f"camera_path[{i}] needs 'camera_to_world' (16 numbers) and "
                        "'fov' (degrees)") from None
        if not np.all(np.isfinite(m)):
            raise _fail(path, f"camera_path[{i}]: camera_to_world is not finite")
        if not 0.0 < fov < 180.0:
            raise _fail(path, f"camera_path[{i}]: fov must be in (0, 180) degrees, got {fov}")
        c2w[i] = m
        focal[i] = 0.5 * h / math.tan(math.radians(fov) / 2.0)
    if dataparser_transforms is not None:
        c2w = load_dataparser_transform(dataparser_transforms)[None] @ c2w
    rot = c2w[:, :3, :3]
    scale = np.linalg.norm(rot, axis=1).mean(1, keepdims=True)[..., None]     # [N,1,1]
    r = rot / scale
    bad = np.abs(np.einsum("nij,nkj->nik", r, r) - np.eye(3)).max((1, 2)) > 1e-3
    if bad.any():
        raise _fail(path, f"camera_path[{int(np.argmax(bad))}]: camera_to_world's rotation is "
                    "not orthogonal")
    c2w[:, :3, :3] = r                     # drop a uniform scale of the rotation block
    c2w[:, 3] = [0, 0, 0, 1]
    fx = focal if np.ptp(focal) > 0 else float(focal[0])
    cams = Cameras(c2w=c2w.astype(np.float32), fx=fx, fy=fx, cx=w / 2.0, cy=h / 2.0, width=w,
                   height=h)
    fps = obj.get("fps")
    fps = float(fps) if isinstance(fps, (int, float)) and fps > 0 else None
    return CameraPath(cams, fps, str(path))


def write_camera_path(path: str | os.PathLike, cameras: Cameras, fps: float = 30.0) -> None:
    """Write ``cameras`` as a nerfstudio camera-path JSON (vertical fov from ``fy``), atomically.

    Per-camera focal lengths are kept per frame; the principal point must be the image centre
    (the format has no other).
    """
    from ._util import atomic_save_json

    n = len(cameras)
    fy = np.broadcast_to(np.asarray(cameras.fy, dtype=np.float64), (n,))
    frames = [{"camera_to_world": cameras.c2w[i].astype(np.float64).reshape(-1).tolist(),
               "fov": math.degrees(2.0 * math.atan(0.5 * cameras.height / fy[i])),
               "aspect": cameras.width / cameras.height} for i in range(n)]
    atomic_save_json(path, {"camera_type": "perspective", "render_width": cameras.width,
                            "render_height": cameras.height, "fps": fps,
                            "seconds": n / fps, "camera_path": frames})
