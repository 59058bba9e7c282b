"""Reader of COLMAP sparse models (``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``).

Pure numpy (no pycolmap needed): the binary layout is COLMAP's ``src/colmap/scene/
reconstruction_io.cc`` (little-endian; cameras: ``uint64 n`` then per camera ``int32 id,
int32 model, uint64 w, uint64 h, float64 params[k]``; images: ``uint64 n`` then ``int32 id,
float64 qw qx qy qz tx ty tz, int32 camera_id, name\\0, uint64 n2d, n2d x (float64 x, y,
int64 point3D_id)``; points3D: ``uint64 n`` then ``uint64 id, float64 xyz[3], uint8 rgb[3],
float64 error, uint64 len, len x (int32 image_id, int32 idx)``). The text files hold the same
fields, one record a line (two lines per image). Poses are COLMAP's ``cam_from_world``
(OpenCV axes: x right, y down, z forward); :func:`colmap_c2w` turns them into OpenGL
camera-to-world matrices. Every problem raises :class:`DatasetError` naming the file.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError

__all__ = ["ColmapCamera", "ColmapModel", "read_colmap_model", "find_colmap_model",
           "colmap_c2w", "rotation_c2w", "CAMERA_MODELS"]

# model id -> (name, number of parameters), as in COLMAP's sensor/models.h
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_BY_NAME = {name: (i, k) for i, (name, k) in CAMERA_MODELS.items()}


@dataclass
class ColmapCamera:
    """One COLMAP camera: ``model`` name, image ``width``/``height`` (pixels), ``params``
    (float64, COLMAP's order, e.g. OPENCV: fx, fy, cx, cy, k1, k2, p1, p2)."""

    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapModel:
    """A sparse model. ``images`` maps image id to ``(name, camera_id, qvec [4] (w, x, y, z),
    tvec [3])``; ``points`` float64 ``[P, 3]`` world points, ``point_errors`` ``[P]`` mean
    reprojection errors (pixels), ``point_tracks`` ``[P]`` track lengths."""

    path: Path
    cameras: dict[int, ColmapCamera]
    images: dict[int, tuple[str, int, np.ndarray, np.ndarray]]
    points: np.ndarray
    point_errors: np.ndarray
    point_tracks: np.ndarray


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        try:
            self.buf = path.read_bytes()
        except OSError as e:
            raise DatasetError(f"{path}: cannot read ({e.strerror or e})") from None
        self.pos = 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.buf):
            raise DatasetError(f"{self.path}: truncated file (record at byte {self.pos})")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += size
        return out

    def name(self) -> str:
        end = self.buf.find(b"\x00", self.pos)
        if end < 0:
            raise DatasetError(f"{self.path}: truncated image name at byte {self.pos}")
        s = self.buf[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s

    def skip(self, nbytes: int) -> None:
        if self.pos + nbytes > len(self.buf):
            raise DatasetError(f"{self.path}: truncated file (record at byte {self.pos})")
        self.pos += nbytes


def _model_params(path: Path, model: str | int, params: list[float]) -> tuple[str, np.ndarray]:
    if isinstance(model, int):
        if model not in CAMERA_MODELS:
            raise DatasetError(f"{path}: unknown camera model id {model}")
        model = CAMERA_MODELS[model][0]
    if model not in _BY_NAME:
        raise DatasetError(f"{path}: unknown camera model {model!r}")
    k = _BY_NAME[model][1]
    if len(params) != k:
        raise DatasetError(f"{path}: camera model {model} needs {k} parameters, got "
                           f"{len(params)}")
    p = np.asarray(params, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        raise DatasetError(f"{path}: non-finite camera parameters")
    return model, p


def _cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    r = _Reader(path)
    (n,) = r.take("<Q")
    out = {}
    for _ in range(n):
        cid, mid, w, h = r.take("<iiQQ")
        if mid not in CAMERA_MODELS:
            raise DatasetError(f"{path}: unknown camera model id {mid}")
        k = CAMERA_MODELS[mid][1]
        model, p = _model_params(path, mid, list(r.take(f"<{k}d")))
        out[cid] = ColmapCamera(model, int(w), int(h), p)
    return out


def _lines(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror or e})") from None
    return [ln.rstrip("\r\n") for ln in text.split("\n") if not ln.startswith("#")]


def _cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    out = {}
    for i, ln in enumerate(_lines(path)):
        tok = ln.split()
        if not tok:
            continue
        try:
            cid, model, w, h = int(tok[0]), tok[1], int(tok[2]), int(tok[3])
            params = [float(v) for v in tok[4:]]
        except (ValueError, IndexError):
            raise DatasetError(f"{path}: malformed camera line {ln!r}") from None
        model, p = _model_params(path, model, params)
        out[cid] = ColmapCamera(model, w, h, p)
    return out


def _images_bin(path: Path) -> dict:
    r = _Reader(path)
    (n,) = r.take("<Q")
    out = {}
    for _ in range(n):
        iid, *qt, cid = r.take("<i7di")
        name = r.name()
        (n2d,) = r.take("<Q")
        r.skip(24 * n2d)
        out[iid] = (name, cid, np.array(qt[:4]), np.array(qt[4:]))
    return out


def _images_txt(path: Path) -> dict:
    lines = _lines(path)
    out = {}
    i = 0
    while i < len(lines):
        tok = lines[i].split()
        if not tok:
            i += 1
            continue
        if len(tok) < 10:
            raise DatasetError(f"{path}: malformed image line {lines[i]!r}")
        try:
            iid, qt, cid = int(tok[0]), [float(v) for v in tok[1:8]], int(tok[8])
        except ValueError:
            raise DatasetError(f"{path}: malformed image line {lines[i]!r}") from None
        out[iid] = (" ".join(tok[9:]), cid, np.array(qt[:4]), np.array(qt[4:]))
        i += 2                       # the POINTS2D line (possibly empty) follows
    return out


def _points_bin(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r = _Reader(path)
    (n,) = r.take("<Q")
    xyz, err, track = np.zeros((n, 3)), np.zeros(n), np.zeros(n, dtype=np.int64)
    for j in range(n):
        _, x, y, z, _, _, _, e, ln = r.take("<Q3d3BdQ")
        r.skip(8 * ln)
        xyz[j], err[j], track[j] = (x, y, z), e, ln
    return xyz, err, track


def _points_txt(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz, err, track = [], [], []
    for ln in _lines(path):
        tok = ln.split()
        if not tok:
            continue
        try:
            xyz.append([float(v) for v in tok[1:4]])
            err.append(float(tok[7]))
        except (ValueError, IndexError):
            raise DatasetError(f"{path}: malformed point line {ln[:80]!r}") from None
        track.append((len(tok) - 8) // 2)
    return (np.array(xyz, dtype=np.float64).reshape(-1, 3), np.array(err, dtype=np.float64),
            np.array(track, dtype=np.int64))


def find_colmap_model(root: Path) -> Path | None:
    """The model folder of a dataset: ``root`` itself, ``root/sparse/0`` or ``root/sparse``
    (the first holding ``cameras.bin`` or ``cameras.txt``), else ``None``."""
    for d in (root, root / "sparse" / "0", root / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def read_colmap_model(folder: str | Path) -> ColmapModel:
    """Read ``cameras``, ``images`` and ``points3D`` (``.bin`` preferred over ``.txt``) from
    ``folder``; ``points3D`` may be missing (then no points)."""
    folder = Path(folder)

    def pick(stem: str, required: bool = True) -> Path | None:
        for ext in (".bin", ".txt"):
            if (folder / f"{stem}{ext}").is_file():
                return folder / f"{stem}{ext}"
        if required:
            raise DatasetError(f"{folder}: no {stem}.bin or {stem}.txt (a COLMAP model folder "
                               "holds cameras, images and points3D)")
        return None

    pc, pi, pp = pick("cameras"), pick("images"), pick("points3D", required=False)
    cameras = _cameras_bin(pc) if pc.suffix == ".bin" else _cameras_txt(pc)
    images = _images_bin(pi) if pi.suffix == ".bin" else _images_txt(pi)
    if pp is None:
        pts, err, trk = np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
    else:
        pts, err, trk = _points_bin(pp) if pp.suffix == ".bin" else _points_txt(pp)
    if not images:
        raise DatasetError(f"{pi}: the model has no registered images")
    for iid, (name, cid, q, t) in images.items():
        if cid not in cameras:
            raise DatasetError(f"{pi}: image {name!r} refers to camera {cid}, which "
                               f"{pc.name} does not define")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t)) and np.linalg.norm(q) > 0):
            raise DatasetError(f"{pi}: image {name!r} has a non-finite or zero pose")
    return ColmapModel(folder, cameras, images, pts, err, trk)


def _quat_to_rot(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def colmap_c2w(qvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world float64 ``[4, 4]`` of a COLMAP pose (``cam_from_world`` as the
    unit quaternion ``qvec`` (w, x, y, z) and translation ``tvec``): :func:`rotation_c2w`."""
    return rotation_c2w(_quat_to_rot(np.asarray(qvec, dtype=np.float64)), tvec)


def rotation_c2w(r: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world float64 ``[4, 4]`` of ``cam_from_world`` = rotation matrix ``r``
    ``[3, 3]`` and translation ``tvec``: ``R^T``, centre ``-R^T t``, then the y and z axes
    flipped (OpenCV → OpenGL)."""
    r = np.asarray(r, dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = r.T
    m[:3, 3] = -r.T @ np.asarray(tvec, dtype=np.float64)
    return m @ np.diag([1.0, -1.0, -1.0, 1.0])
