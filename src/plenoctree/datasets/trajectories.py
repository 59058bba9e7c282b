"""Camera trajectories: ``look_at``, turntable orbits around a box, the NDC spiral; the up axis.

Orbit convention (the original ``gen_video.py``'s ``pose_spherical``, z up): frame ``i`` of
``n`` sits at azimuth ``a = 2π i / n`` and elevation ``el`` above the plane through the centre
normal to the up axis ``u``, at ``eye = c + r (cos(el) (−sin a e1 − cos a e2) + sin(el) u)``
with ``(e1, e2, u)`` right-handed (``+z`` up: ``e1 = +x``, ``e2 = +y``), looking at ``c`` with
camera +y as close to ``u`` as possible. Positive elevations look down from above; our ``30``
is the original's ``--elevation -30``.

>>> cams = orbit_cameras(np.zeros(3), 4.0, 120, 400, 400)     # doctest: +SKIP

Used by :mod:`plenoctree.video` (orbit and spiral videos), the compression report's orbit
views and the web viewer's up axis; pure numpy (no torch).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ConfigError
from .cameras import Cameras, check_image_size

__all__ = ["UP_AXES", "DEFAULT_FOV_X", "DEFAULT_FRAMES", "look_at", "axis_vector",
           "detect_up_axis", "orbit_poses", "fit_radius", "orbit_cameras", "ndc_spiral_cameras",
           "check_frames", "check_size"]

UP_AXES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")
DEFAULT_FOV_X = 0.6911112070083618   # radians: NeRF-synthetic's camera_angle_x
DEFAULT_FRAMES = 120                 # orbit / spiral frames


def look_at(eye: np.ndarray, target: np.ndarray = (0.0, 0.0, 0.0),
            up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world ``[4, 4]`` (float64) of a camera at ``eye`` looking at ``target``.

    Camera -z points at the target, +y is as close to ``up`` as possible (another axis is used
    when the view direction is parallel to ``up``).
    """
    eye = np.asarray(eye, dtype=np.float64)
    back = eye - np.asarray(target, dtype=np.float64)
    norm = np.linalg.norm(back)
    if not norm > 0:
        raise ConfigError("look_at: eye and target coincide")
    back /= norm
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(np.array([0.0, 1.0, 0.0]), back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, back, eye
    return m


def axis_vector(name: str) -> np.ndarray:
    """``"+x"`` ... ``"-z"`` -> the unit world axis, float64 ``[3]``."""
    if name not in UP_AXES[1:]:
        raise ConfigError(f"--up: expected one of {', '.join(UP_AXES)}, got {name!r}")
    v = np.zeros(3)
    v["xyz".index(name[1])] = 1.0 if name[0] == "+" else -1.0
    return v


def detect_up_axis(c2w: np.ndarray) -> str:
    """The signed world axis nearest the mean camera up vector (``c2w[:, :3, 1]``).

    Blender / NeRF-synthetic captures give ``"+z"``, recentred LLFF ones ``"+y"``; no cameras
    or a zero mean give ``"+z"``.
    """
    c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    mean = c2w[:, :3, 1].mean(axis=0) if len(c2w) else np.zeros(3)
    if not np.linalg.norm(mean) > 1e-6:
        return "+z"
    k = int(np.argmax(np.abs(mean)))
    return ("+" if mean[k] > 0 else "-") + "xyz"[k]


def orbit_poses(center: np.ndarray, radius: float, n_frames: int, elevation_deg: float = 30.0,
                up: str = "+z") -> np.ndarray:
    """Camera-to-world matrices float32 ``[n_frames, 4, 4]`` of a turntable orbit (module
    docstring): radius world units from ``center`` [3], elevation degrees in (−90, 90)."""
    check_frames(n_frames)
    if not (np.isfinite(radius) and radius > 0):
        raise ConfigError(f"--radius must be a positive number, got {radius}")
    if not -90.0 < elevation_deg < 90.0:
        raise ConfigError(f"--elevation must be in (-90, 90) degrees, got {elevation_deg}")
    u = axis_vector(up)
    k = int(np.argmax(np.abs(u)))
    e1 = np.zeros(3)
    e1[(k + 1) % 3] = 1.0
    e2 = np.cross(u, e1)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    el = math.radians(elevation_deg)
    poses = []
    for i in range(n_frames):
        a = 2.0 * math.pi * i / n_frames
        eye = c + radius * (math.cos(el) * (-math.sin(a) * e1 - math.cos(a) * e2)
                            + math.sin(el) * u)
        poses.append(look_at(eye, c, u))
    return np.stack(poses).astype(np.float32)


def fit_radius(half_sides: np.ndarray, fov_x: float, width: int, height: int) -> float:
    """Orbit radius (world units) at which the sphere around a box of ``half_sides`` [3] just
    fits the narrower field of view of a ``width`` x ``height`` camera with horizontal field of
    view ``fov_x`` radians: nothing inside the box is ever cut off."""
    fov_y = 2.0 * math.atan(math.tan(0.5 * fov_x) * height / width)
    return float(np.linalg.norm(half_sides)) / math.sin(0.5 * min(fov_x, fov_y))


def orbit_cameras(center: np.ndarray, radius: float, n_frames: int, width: int, height: int,
                  fov_x: float = DEFAULT_FOV_X, elevation_deg: float = 30.0,
                  up: str = "+z") -> Cameras:
    """:func:`orbit_poses` as :class:`Cameras`: square pixels, horizontal field of view
    ``fov_x`` radians, principal point at the image centre."""
    if not 0.0 < fov_x < math.pi:
        raise ConfigError(f"--fov must be in (0, 180) degrees, got {math.degrees(fov_x)}")
    check_size(width, height)
    f = 0.5 * width / math.tan(0.5 * fov_x)
    return Cameras(orbit_poses(center, radius, n_frames, elevation_deg, up), f, f,
                   width / 2.0, height / 2.0, int(width), int(height))


def ndc_spiral_cameras(ndc, n_frames: int = DEFAULT_FRAMES) -> Cameras:
    """A spiral video path for an NDC tree without its dataset: LLFF's :func:`spiral_path`
    for a rig of offsets ±(0.1, 0.1, 0.05)·near about the reference camera with content depths
    4/3 to 40/3·near (LLFF's normalisation puts the closest content at 4/3 near), so it looks
    at a point ~4.5 near ahead; the reference camera's intrinsics, NDC rays of ``ndc``."""
    from .llff import spiral_path

    check_frames(n_frames)
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    rig = np.tile(np.eye(4), (8, 1, 1))
    rig[:, :3, 3] = s * np.array([0.1, 0.1, 0.05]) * ndc.near
    bounds = np.array([[4.0 / 3.0, 40.0 / 3.0]]) * ndc.near
    path = spiral_path(rig, bounds, n_frames)
    cams = Cameras(path.astype(np.float32), ndc.fx, ndc.fy, ndc.width / 2.0, ndc.height / 2.0,
                   ndc.width, ndc.height)
    return ndc.apply(cams)


def check_frames(n: object) -> None:
    """``ConfigError`` unless ``n`` (``--frames``) is a positive integer."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"--frames must be a positive integer, got {n!r}")


def check_size(width: object, height: object) -> None:
    """``ConfigError`` unless ``width`` and ``height`` (pixels) are positive integers within
    the image-size bounds of :func:`~plenoctree.datasets.cameras.check_image_size`."""
    for name, v in (("--width", width), ("--height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ConfigError(f"{name} must be a positive integer, got {v!r}")
    check_image_size(width, height, "--width/--height")
