"""Frames drawn by the CPU renderer for the viewer page's CPU mode (``GET /frame?...``).

Where the browser has no GPU (software WebGL: SwiftShader, llvmpipe) the page asks the server
for each frame instead of ray-marching it in WebGL: it sends the camera it would have drawn
(:func:`parse_frame_query`: pose, intrinsics, size, and the options the page's controls set)
and gets back a JPEG. The server renders it with the numba kernel
(:func:`plenoctree.render.render_image` on a :class:`~plenoctree.render.CpuTree` made once, the
same rays as ``plenoctree render``; an NDC tree's cameras go through ``tree.ndc.apply`` as
there) and encodes it with Pillow. One frame renders at a time (the numba kernel uses every
core for one image); the page keeps at most one request in flight, so the latest camera wins
and nothing queues.
"""

from __future__ import annotations

import io
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs

import numpy as np

from ..errors import ConfigError

if TYPE_CHECKING:
    from ..datasets import Cameras
    from ..render import RenderOptions

__all__ = ["RENDER_MODES", "JPEG_QUALITY", "FrameRequest", "FrameRenderer", "parse_frame_query"]

logger = logging.getLogger(__name__)

#: ``plenoctree view --render`` choices: ``auto`` = CPU frames when the page's WebGL is a
#: software renderer (or missing), else WebGL.
RENDER_MODES = ("auto", "cpu", "webgl")
#: Default JPEG quality of a frame: the page's sharp frames (full chroma: 41-43 dB on lego at
#: 800x800, about 6 ms); it asks 80 while the camera moves (2x2 chroma subsampling below 90).
JPEG_QUALITY = 90
_VIEW_MODES = ("rgb", "depth", "alpha")
_MAX_QUERY = 4096            # characters of a /frame query string


@dataclass(frozen=True)
class FrameRequest:
    """One frame the page asks for (the page's camera and the options of its controls).

    Attributes:
        camera: one :class:`~plenoctree.datasets.Cameras` (OpenGL pose: x right, y up, looks
            down -z; intrinsics in pixels of its ``width`` x ``height``).
        options: the validated :class:`~plenoctree.render.RenderOptions` (background,
            stop_thresh, sh_min, sh_max).
        mode: ``rgb``, ``depth`` (grey: white at ``depth_range[0]``, black at ``[1]``, world
            units; NDC lengths for NDC trees) or ``alpha`` (opacity, ink on the background).
        quality: JPEG quality 1..95 (from 90 on without chroma subsampling).
    """

    camera: Cameras
    options: RenderOptions
    mode: str = "rgb"
    depth_range: tuple[float, float] = (0.0, 1.0)
    quality: int = JPEG_QUALITY


def _floats(q: dict[str, list[str]], key: str, n: int, default: Any = None) -> list[float]:
    """``n`` finite numbers from the comma-separated parameter ``key`` (ConfigError else)."""
    if key not in q:
        if default is None:
            raise ConfigError(f"missing parameter {key!r}")
        return list(default)
    parts = q[key][-1].split(",")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"parameter {key!r}: expected {n} number(s), got {q[key][-1]!r}") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"parameter {key!r}: expected {n} finite number(s), got {q[key][-1]!r}")
    return vals


def _int(q: dict[str, list[str]], key: str, default: int | None = None) -> int:
    if key not in q:
        if default is None:
            raise ConfigError(f"missing parameter {key!r}")
        return default
    try:
        return int(q[key][-1])
    except ValueError:
        raise ConfigError(f"parameter {key!r}: expected an integer, got {q[key][-1]!r}") from None


def parse_frame_query(query: str) -> FrameRequest:
    """The :class:`FrameRequest` of a ``/frame`` query string.

    Parameters: ``w``, ``h`` (pixels; at most the image-size policy
    :func:`~plenoctree.datasets.cameras.check_image_size`), ``c2w`` (16 numbers, row-major),
    ``fx``, ``fy``, ``cx``, ``cy``; optional ``bg`` (3 numbers), ``stop``, ``renorm`` (0|1:
    :attr:`~plenoctree.render.RenderOptions.renormalize`), ``sh_min``, ``sh_max``, ``mode``
    (rgb|depth|alpha), ``dr`` (2 numbers: depth range), ``q`` (JPEG quality). Raises
    :class:`ConfigError` (the server answers 400) for anything else: missing, non-numeric or
    non-finite values, a singular pose, implausible intrinsics, a bad size.
    """
    from ..datasets import check_image_size

    if len(query) > _MAX_QUERY:
        raise ConfigError(f"query too long ({len(query)} characters)")
    try:
        q = parse_qs(query, keep_blank_values=True, strict_parsing=False, max_num_fields=32)
    except ValueError as e:
        raise ConfigError(f"bad query ({e})") from None
    w, h = check_image_size(_int(q, "w"), _int(q, "h"), "frame size")
    c2w = np.asarray(_floats(q, "c2w", 16), dtype=np.float64).reshape(4, 4)
    fx, fy, cx, cy = (_floats(q, k, 1)[0] for k in ("fx", "fy", "cx", "cy"))
    mode = q.get("mode", ["rgb"])[-1]
    if mode not in _VIEW_MODES:
        raise ConfigError(f"parameter 'mode' must be one of {', '.join(_VIEW_MODES)}, got {mode!r}")
    quality = _int(q, "q", JPEG_QUALITY)
    if not 1 <= quality <= 95:
        raise ConfigError(f"parameter 'q' (JPEG quality) must be in 1..95, got {quality}")
    from ..datasets import Cameras
    from ..render.options import RenderOptions

    bg = tuple(_floats(q, "bg", 3, (1.0, 1.0, 1.0)))
    dr = tuple(_floats(q, "dr", 2, (0.0, 1.0)))
    stop, sh_min, sh_max = _floats(q, "stop", 1, (0.01,))[0], _int(q, "sh_min", 0), _int(q, "sh_max", -1)
    renorm = _int(q, "renorm", 0)
    if renorm not in (0, 1):
        raise ConfigError(f"parameter 'renorm' must be 0 or 1, got {renorm}")
    opts = RenderOptions(stop_thresh=stop, background=bg, sh_min=sh_min, sh_max=sh_max,
                         renormalize=bool(renorm)).validated()
    camera = Cameras(c2w[None], fx, fy, cx, cy, w, h)
    return FrameRequest(camera, opts, mode=mode, depth_range=dr,  # type: ignore[arg-type]
                        quality=quality)


def _shade(out: Any, req: FrameRequest) -> np.ndarray:
    """uint8 ``[H, W, 3]`` of a render for the request's view mode (the page's shader's
    depth and opacity mappings)."""
    bg = np.asarray(req.options.background, dtype=np.float32)
    if req.mode == "rgb":
        img = out.rgb.numpy()
    else:
        alpha = out.alpha.numpy()[..., None]
        if req.mode == "depth":
            lo, hi = req.depth_range
            g = 1.0 - np.clip((out.depth.numpy()[..., None] - lo) / max(hi - lo, 1e-6), 0, 1)
            img = g * alpha + (1.0 - alpha) * bg
        else:
            ink = 0.0 if float(bg @ np.array([0.299, 0.587, 0.114], np.float32)) > 0.5 else 1.0
            img = bg + (ink - bg) * alpha
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


class FrameRenderer:
    """Renders :class:`FrameRequest` s of one tree with the numba kernel, one at a time.

    Args:
        tree: an :class:`~plenoctree.octree.Octree` (``tree.ndc`` set for forward-facing trees).
    """

    def __init__(self, tree: Any) -> None:
        from ..render import tree_to_device

        self.ndc = getattr(tree, "ndc", None)
        self.tree = tree_to_device(tree, "cpu")
        self.n_leaves = int(getattr(tree, "n_leaves", 0))
        self.max_depth = int(getattr(tree, "max_depth", 0))
        self._lock = threading.Lock()

    @staticmethod
    def threads() -> int:
        """Threads the numba kernel runs on."""
        import numba

        return int(numba.get_num_threads())

    def info(self) -> dict[str, Any]:
        """What the page needs to draw through the server without loading the tree itself
        (``config.json``'s ``cpu``): box, basis count, NDC space, counts, threads."""
        from ..render.options import parse_data_format

        t = self.tree
        fmt = parse_data_format(t.data_format, t.data.shape[-1], t.extra_data)
        return {
            "offset": [float(v) for v in t.offset], "invradius": [float(v) for v in t.invradius],
            "format": t.data_format, "basis_dim": fmt.basis_dim,
            "ndc": None if self.ndc is None else self.ndc.to_json(),
            "n_leaves": self.n_leaves, "max_depth": self.max_depth, "threads": self.threads(),
        }

    def render(self, req: FrameRequest) -> np.ndarray:
        """uint8 ``[H, W, 3]`` image of ``req``. A view is never refused for where the camera
        stands or looks: NDC trees through ``tree.ndc.apply`` (any camera);
        a camera so far away that the renderer cannot step from it
        (:func:`~plenoctree.render.origin_in_reach`) sees the tree smaller than a pixel (any
        focal length the camera checks accept), and gets the background."""
        import torch

        from ..render import RenderOutput, origin_in_reach, render_image

        if self.ndc is None and not origin_in_reach(self.tree, req.camera.c2w[0, :3, 3]):
            h, w = req.camera.height, req.camera.width
            bg = torch.tensor(req.options.background, dtype=torch.float32)
            out = RenderOutput(bg.expand(h, w, 3), torch.zeros(h, w), torch.zeros(h, w))
            return _shade(out, req)
        cams = req.camera if self.ndc is None else self.ndc.apply(req.camera)
        with self._lock:
            out = render_image(self.tree, cams, 0, req.options, backend="numba")
        return _shade(out, req)

    def jpeg(self, req: FrameRequest) -> tuple[bytes, float, float]:
        """``(JPEG bytes, render ms, encode ms)`` of ``req``."""
        from PIL import Image

        t0 = time.perf_counter()
        img = self.render(req)
        t1 = time.perf_counter()
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, "JPEG", quality=req.quality,
                                  subsampling=0 if req.quality >= 90 else 2)
        t2 = time.perf_counter()
        return buf.getvalue(), 1e3 * (t1 - t0), 1e3 * (t2 - t1)

    def warm_up(self) -> None:
        """Render one tiny frame (loads the compiled kernel) so the page's first frame is not
        the slow one."""
        try:
            c2w = np.eye(4)             # NDC trees: the reference camera; else the centre
            if self.ndc is None:
                c2w[:3, 3] = (0.5 - self.tree.offset) / self.tree.invradius
            from ..datasets import Cameras
            from ..render import RenderOptions

            self.render(FrameRequest(Cameras(c2w[None], 8.0, 8.0, 4.0, 4.0, 8, 8), RenderOptions()))
        except Exception as e:        # only a warm-up: the page's own frames report errors
            logger.debug("viewer: CPU warm-up frame failed (%s)", e)
