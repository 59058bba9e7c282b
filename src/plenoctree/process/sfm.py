"""Structure from motion with pycolmap: SIFT features, matching, incremental mapping.

:func:`run_sfm` turns a folder of images into a COLMAP reconstruction (the largest model when
COLMAP returns several). Each COLMAP stage shows a progress bar: extraction and matching run
in chunks of images / image pairs, mapping reports every registered image. Every failure a user
can cause (too few images, too few matches, nothing registered) raises
:class:`~plenoctree.errors.ProcessError` naming what to try.

Defaults chosen by measurement on the lego training photos (``benchmarks/colmap_poses.py``):
one camera shared by every image (``single_camera``) and a stricter mapper
(:data:`MAPPER_DEFAULTS`: an image is registered only with >= 100 inliers, >= 50 % inlier
ratio and <= 4 px error; observations over 2 px are filtered; no structure-less fallback
registration), then :func:`drop_weak_images`. With COLMAP's own mapper settings one lego photo
was registered on the wrong side of the nearly symmetric object (165° off); the stricter ones
alone still did so in one of two runs (multi-threaded matching is not deterministic), with
~5x fewer 3D points than the median photo, which the filter removes. A final global bundle
adjustment refines the chosen model.

Cost, measured on the real captures (``benchmarks/colmap_poses.py --real flower|fox``,
docs/capture.md): guided matching took ~3.5x the matching time per pair for 10-30 % more
inliers, and the earlier defaults with it (and SIFT at 1600 px) gained 0.1° on flower's
rotations (0.34° against 0.44° median), so it is on only where the images keep few features
(:data:`GUIDED_MAX_FEATURES`: cheap there, and needed on the lego video); SIFT runs at <= 1024 px
(fox's 1920-px frames: about half the features and matching time of 1600 px; the feature cap
does not bind at these sizes); every pair is matched where that is estimated to take at most
:data:`EXHAUSTIVE_SECONDS`, and ordered images beyond (video frames, photos whose names follow
the capture) with their neighbours, frames 2^k later and the last frames with the first
(:func:`choose_matcher`, :func:`loop_pairs`: the loop of a walk-around closed; pycolmap's loop
detection needs a vocabulary tree, a download, so none). The inlier minimum follows the
features (:func:`min_inliers`). When the largest model holds under 95 % of the images, the
frames left out are matched with more neighbours and registered into it with COLMAP's own
thresholds (:mod:`.register`; on the lounge walk-around 64 of 64 frames in one model where
the first mapping split it, docs/capture_records.md).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError, PlenOctreeError
from .mapping import _disable, global_mapping, incremental_mapping
from .register import largest, retry_registration

__all__ = ["SfmOptions", "SfmResult", "run_sfm", "require_pycolmap", "check_options",
           "ProcessError", "sequential_pairs", "loop_pairs", "min_inliers", "choose_matcher",
           "plan_matching", "in_chunks", "MAPPINGS"]

logger = logging.getLogger(__name__)

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV",
                 "OPENCV_FISHEYE")


MAPPER_DEFAULTS = {"structure_less_registration_fallback": False,
                   "mapper.abs_pose_min_num_inliers": 100, "mapper.abs_pose_max_error": 4.0,
                   "mapper.abs_pose_min_inlier_ratio": 0.5, "mapper.filter_max_reproj_error": 2.0,
                   "mapper.init_min_tri_angle": 8.0}
"""Mapper settings changed from COLMAP's (chosen on lego by ``benchmarks/colmap_poses.py``)."""


MAPPINGS = ("incremental", "global")
"""The mappers of :attr:`SfmOptions.mapping`."""


class ProcessError(PlenOctreeError, RuntimeError):
    """Structure from motion or the dataset writing failed; the message says what to try."""


def require_pycolmap() -> Any:
    """Import pycolmap or raise :class:`ProcessError` naming the extra to install."""
    # Pillow first: imported after pycolmap (whose wheel bundles its own zlib), Pillow's PNG
    # encoder crashes the interpreter (free(): invalid pointer in deflateEnd).
    from PIL import Image  # noqa: F401

    try:
        import pycolmap
    except ImportError:
        raise ProcessError("camera poses from photos need pycolmap: pip install "
                           "'plenoctree[colmap]' (or pip install pycolmap)") from None
    return pycolmap


@dataclass
class SfmOptions:
    """Options of :func:`run_sfm` (the ``plenoctree process`` flags)."""

    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, ...)"""
    single_camera: bool = True
    """one camera (intrinsics) shared by every image; off: one per image"""
    matcher: str = "auto"
    """exhaustive, sequential or auto (every pair where that takes about 2 minutes at most;
    beyond, sequential for video frames and photos named in capture order, exhaustive for
    other photos up to 300)"""
    max_features: int = 8192
    """SIFT features per image"""
    guided_matching: bool | None = None
    """re-match along the estimated epipolar geometry (10-30 % more inliers for ~3.5x the
    matching time); default: where the median image keeps fewer than 2,000 features"""
    max_image_size: int = 1024
    """longest image side used for features (larger images are downscaled for SIFT only)"""
    sequential_overlap: int = 10
    """neighbours matched per frame by the sequential matcher (plus frames 2^k later, and the
    last frames with the first ones, which closes the loop of a walk-around)"""
    retry: bool = True
    """when the largest model holds under 95 % of the images: match the left-out frames with
    more neighbours and map on from it with COLMAP's own registration thresholds"""
    num_threads: int = -1
    """threads (-1: all cores)"""
    seed: int = 0
    """random seed of COLMAP's RANSAC and mapper"""
    focal_factor: float = 1.2
    """initial focal length / longest side when the images carry no EXIF focal length"""
    mapping: str = "incremental"
    """incremental or global: COLMAP's incremental mapper (one image at a time), or its global
    one (GLOMAP: every rotation, then every position at once): 2-3x faster mapping on photo
    sets (flower, lego's photos) with poses as good, but it misplaced video frames (lego's
    video: every frame; fox's: 3 of 5 runs), so not for frames of a video"""
    mapper: dict = field(default_factory=lambda: dict(MAPPER_DEFAULTS))
    """IncrementalPipelineOptions fields ("mapper.<name>" for its mapper's), on top of COLMAP's"""
    refine_principal_point: str = "off"
    """the final bundle adjustment also refines the principal point: on, off, or auto (360°
    captures only: forward-facing photos constrain it poorly, and LLFF assumes it centred).
    Off by default: on lego's photos (centred) it cost 0.07° of median rotation error, and on
    fox it matched instant-ngp's poses better (0.27° against 0.53°) without a better tree"""


@dataclass
class SfmResult:
    """The largest COLMAP model and what happened on the way."""

    reconstruction: Any
    """pycolmap.Reconstruction"""
    n_images: int
    n_registered: int
    n_models: int
    seconds: dict
    pairs: int = 0
    """image pairs matched (the retry's included)"""
    retry: dict = field(default_factory=dict)
    """what :func:`~plenoctree.process.register.retry_registration` did (empty: not needed)"""


def check_options(opts: SfmOptions) -> None:
    """Check the option values; raises :class:`ConfigError` naming the option."""
    if opts.camera_model not in CAMERA_MODELS:
        raise ConfigError(f"camera model must be one of {', '.join(CAMERA_MODELS)}, got "
                          f"{opts.camera_model!r}")
    if opts.refine_principal_point not in ("auto", "on", "off"):
        raise ConfigError("refine_principal_point must be auto, on or off, got "
                          f"{opts.refine_principal_point!r}")
    if opts.mapping not in MAPPINGS:
        raise ConfigError(f"mapping must be one of {', '.join(MAPPINGS)}, got {opts.mapping!r}")
    if opts.matcher not in ("auto", "exhaustive", "sequential"):
        raise ConfigError(f"matcher must be auto, exhaustive or sequential, got {opts.matcher!r}")
    if opts.max_features < 100 or opts.max_image_size < 64:
        raise ConfigError("max_features must be >= 100 and max_image_size >= 64")
    if opts.sequential_overlap < 1:
        raise ConfigError(f"sequential_overlap must be >= 1, got {opts.sequential_overlap}")
    if not opts.focal_factor > 0:
        raise ConfigError(f"focal_factor must be > 0, got {opts.focal_factor}")
    if not isinstance(opts.mapper, dict):
        raise ConfigError(f"mapper must be a dict of COLMAP mapper options, got {opts.mapper!r}")
    try:
        import pycolmap
    except ImportError:
        return                              # (the caller's require_pycolmap() says so)
    _mapper_options(pycolmap, opts)


def _mapper_options(pycolmap: Any, opts: SfmOptions) -> Any:
    """pycolmap.IncrementalPipelineOptions with ``opts.mapper`` set on COLMAP's defaults."""
    popt = pycolmap.IncrementalPipelineOptions()
    popt.num_threads = int(opts.num_threads)
    popt.random_seed = int(opts.seed)
    for k, v in opts.mapper.items():
        obj, name = (popt.mapper, k[7:]) if k.startswith("mapper.") else (popt, k)
        if not hasattr(obj, name):
            raise ConfigError(f"unknown COLMAP mapper option {k!r}")
        try:
            setattr(obj, name, v)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"COLMAP mapper option {k!r}: bad value {v!r} ({e})") from None
    return popt


def run_sfm(image_dir: str | os.PathLike, work_dir: str | os.PathLike, names: Sequence[str],
            opts: SfmOptions | None = None, sequential: bool = False,
            show_progress: bool | None = None,
            label: str | os.PathLike | None = None, scene: str = "auto") -> SfmResult:
    """Features, matches and an incremental reconstruction of ``names`` in ``image_dir``.

    Args:
        image_dir: folder of the images; ``names``: their file names in it (>= 2, in capture
            order for videos).
        work_dir: scratch folder for ``database.db`` (created; emptied of an old database).
        sequential: the images are in capture order (video frames, or photos whose names
            follow it; ``matcher="auto"`` then matches neighbours in time beyond
            :data:`EXHAUSTIVE_MAX_IMAGES`, :func:`choose_matcher`).
        label: what the error messages name (default ``image_dir``; ``process``: the video).
        scene: "auto", "360" or "forward" (``process --scene``): with
            ``refine_principal_point="auto"`` the final bundle adjustment refines the principal
            point of 360° captures (:func:`refines_principal_point`).

    Returns:
        :class:`SfmResult` with the model holding the most registered images.

    Raises:
        ProcessError: pycolmap missing, too few images, no model, too few registered images.
    """
    pycolmap = require_pycolmap()
    opts = opts or SfmOptions()
    check_options(opts)
    label = image_dir if label is None else label
    names = list(names)
    if len(names) < 3:
        raise ProcessError(f"{label}: {len(names)} image(s); structure from motion needs at "
                           "least 3 overlapping photos (20+ recommended)")
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    for p in (db, work / "database.db-wal", work / "database.db-shm"):
        p.unlink(missing_ok=True)
    pycolmap.set_random_seed(int(opts.seed))
    pycolmap.logging.minloglevel = 2          # COLMAP's own log: errors only
    times: dict[str, float] = {}

    # 1. Features (in chunks of about CHUNK_SECONDS, for the progress line).
    t0 = time.perf_counter()
    _extract_features(pycolmap, db, image_dir, names, opts, show_progress)
    times["features"] = time.perf_counter() - t0

    # 2. Matching: the pairs and guided matching chosen from the set (:func:`plan_matching`).
    t0 = time.perf_counter()
    with pycolmap.Database.open(db) as d:
        n_kp = sorted(d.num_keypoints_for_image(im.image_id) for im in d.read_all_images())
    median_kp = n_kp[len(n_kp) // 2]
    matcher, pairs, guided = plan_matching(opts, len(names), sequential, median_kp)
    mopts = replace(opts, guided_matching=guided)
    _match_pairs(pycolmap, db, work, names, pairs, mopts, show_progress,
                 f"colmap matching ({matcher})")
    times["matching"] = time.perf_counter() - t0

    # 3. Mapping: incremental (progress: one tick per registered image) or global.
    t0 = time.perf_counter()
    if opts.mapping == "global":
        models = global_mapping(pycolmap, db, image_dir, work / "sparse", opts, show_progress)
    else:
        popt = _mapper_options(pycolmap, opts)
        cap = popt.mapper.abs_pose_min_num_inliers
        popt.mapper.abs_pose_min_num_inliers = min_inliers(median_kp, cap)
        if popt.mapper.abs_pose_min_num_inliers < cap:
            logger.info(f"colmap: {median_kp} features in the median image: an image is "
                f"registered with >= {popt.mapper.abs_pose_min_num_inliers} inliers")
        models = incremental_mapping(pycolmap, db, image_dir, work / "sparse", popt,
                                     len(names), show_progress)
    times["mapping"] = time.perf_counter() - t0
    if not models:
        raise ProcessError(f"{label}: COLMAP could not reconstruct any cameras from the "
                           f"{len(names)} images (too few matches). Try more photos with more "
                           "overlap (each part of the scene seen from 3+ nearby views), "
                           "sharper or more textured images, or --matcher exhaustive")
    retry: dict = {}
    if opts.retry:          # 4. The images left out of the largest model, again (.register)
        models, retry, dt = _retry(pycolmap, db, image_dir, work, names, models, pairs, mopts,
                                   matcher == "sequential", show_progress)
        times.update(dt)
    n_models, best = len(models), largest(models)
    weak = drop_weak_images(best, WEAK_IMAGE_FRACTION)
    if weak:
        logger.info(f"colmap: {len(weak)} weakly supported image(s) left out: {', '.join(weak)}")
    # A final global bundle adjustment of the chosen model.
    pycolmap.logging.minloglevel = 2          # (the mapper resets COLMAP's log level)
    t0 = time.perf_counter()
    refine_pp = refines_principal_point(opts.refine_principal_point, scene, best)
    _global_ba(pycolmap, best, refine_pp)
    times["final_ba"] = time.perf_counter() - t0
    if refine_pp:
        pp = [f"({c.principal_point_x:.1f}, {c.principal_point_y:.1f})"
              for c in best.cameras.values()][:3]
        logger.info(f"colmap: principal point refined: {', '.join(pp)} px")
    n_reg = best.num_reg_images()
    logger.info(f"colmap: {n_reg} of {len(names)} images registered"
        + (f" (largest of {n_models} models)" if n_models > 1 else ""))
    if n_reg < 3:
        raise ProcessError(f"{label}: only {n_reg} of {len(names)} images could be "
                           "registered; take more overlapping photos of the scene")
    return SfmResult(best, len(names), n_reg, n_models, times,
                     pairs=len(pairs) + retry.get("pairs", 0), retry=retry)


def _extract_features(pycolmap: Any, db: Path, image_dir: str | os.PathLike,
                      names: list[str], opts: SfmOptions, show_progress: bool | None) -> None:
    """SIFT features of ``names`` into ``db`` in chunks (:func:`in_chunks`), one progress tick
    per image; with ``opts.single_camera`` every chunk shares the first one's camera."""
    from .._util import progress

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    reader.default_focal_length_factor = float(opts.focal_factor)
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = int(opts.num_threads)
    ext.max_image_size = int(opts.max_image_size)
    ext.sift.max_num_features = int(opts.max_features)
    mode = pycolmap.CameraMode.SINGLE if opts.single_camera else pycolmap.CameraMode.PER_IMAGE

    def extract(part: Sequence[str]) -> None:
        pycolmap.extract_features(db, image_dir, image_names=list(part), camera_mode=mode,
                                  reader_options=reader, extraction_options=ext,
                                  device=pycolmap.Device.cpu)
        if opts.single_camera and reader.existing_camera_id < 0:   # later chunks share it
            with pycolmap.Database.open(db) as d:
                reader.existing_camera_id = int(d.read_all_cameras()[0].camera_id)

    with progress(total=len(names), desc="colmap features", unit="img",
                  disable=_disable(show_progress)) as bar:
        in_chunks(names, extract, bar.update, first=2)


def _retry(pycolmap: Any, db: Path, image_dir: str | os.PathLike, work: Path, names: list[str],
           models: dict, pairs: list, opts: SfmOptions, ordered: bool,
           show_progress: bool | None) -> tuple[dict, dict, dict]:
    """:func:`~plenoctree.process.register.retry_registration` with this database: pairs
    matched as the first ones (at most as many again), mapping on with
    :data:`~plenoctree.process.register.RETRY_MAPPER`. Returns its ``(models, stats)`` and
    the seconds it spent matching and mapping (``retry_matching``, ``retry_mapping``)."""
    from .register import RETRY_MAPPER

    popt = _mapper_options(pycolmap, replace(opts, mapper={**opts.mapper, **RETRY_MAPPER}))
    seconds = {"retry_matching": 0.0, "retry_mapping": 0.0}
    rounds = [0]

    def match(extra: list[tuple[int, int]]) -> None:
        t0 = time.perf_counter()
        _match_pairs(pycolmap, db, work, names, extra, opts, show_progress,
                     "colmap matching (retry)")
        seconds["retry_matching"] += time.perf_counter() - t0

    def remap(start: Any) -> dict:
        t0 = time.perf_counter()
        rounds[0] += 1
        out = incremental_mapping(pycolmap, db, image_dir, work / f"retry{rounds[0]}", popt,
                           len(names), show_progress, "colmap mapping (retry)", start)
        seconds["retry_mapping"] += time.perf_counter() - t0
        return out

    models, stats = retry_registration(models, names, pairs, ordered, opts.sequential_overlap,
                                       match, remap, max_pairs=len(pairs))
    return models, stats, (seconds if stats else {})


MATCH_SECONDS = 0.015
"""Seconds to match one pair of images of 1,000 SIFT features each on 2 busy cores (the cost
grows with the square of the features): flower's 561 pairs of 3,200 were estimated at 86 s and
took 94 s, fox's 704 of 4,400 at 205 s and took 155-212 s (docs/capture.md)."""
EXHAUSTIVE_SECONDS = 120.0
"""``matcher="auto"``: every pair is matched when that is estimated to take at most this long
(:data:`MATCH_SECONDS`), :func:`choose_matcher`."""
GUIDED_MAX_FEATURES = 2000
"""``guided_matching=None``: guided matching where the median image keeps fewer features
(cheap there, and the lego video's 800-feature frames need it: 2 of 60 registered without)."""
EXHAUSTIVE_MAX_IMAGES = 50
"""Photo folders of more images are checked for capture order (``process``); smaller ones
are matched exhaustively whatever the cost."""
EXHAUSTIVE_MAX_PHOTOS = 300
"""``matcher="auto"``: photos not in capture order are matched exhaustively up to this many
(with no vocabulary tree, nothing else finds their overlapping pairs), sequentially beyond."""
CHUNK_SECONDS = 2.0
"""Target duration of one COLMAP call of the features and matching stages: their progress
lines (per image, per pair) move at least this often (:func:`in_chunks`)."""


def choose_matcher(matcher: str, n: int, ordered: bool, median_features: int) -> str:
    """``"exhaustive"`` or ``"sequential"`` for ``n`` images (``ordered``: in capture order)
    of ``median_features`` SIFT features.

    ``matcher="auto"``: every pair where that is cheap (estimated at most
    :data:`EXHAUSTIVE_SECONDS`); beyond, the sequential pairs (:func:`sequential_pairs`) for
    ordered images, every pair for others up to :data:`EXHAUSTIVE_MAX_PHOTOS`. Measured
    (docs/capture.md): flower's 34 photos, 561 pairs, exhaustive; real/fox's 67 frames make
    2,211 pairs exhaustively (~11 minutes) and 704 sequentially.
    """
    if matcher != "auto":
        return matcher
    cost = n * (n - 1) / 2 * MATCH_SECONDS * (median_features / 1000.0) ** 2
    if cost <= EXHAUSTIVE_SECONDS:
        return "exhaustive"
    return "sequential" if ordered or n > EXHAUSTIVE_MAX_PHOTOS else "exhaustive"


def plan_matching(opts: SfmOptions, n: int, ordered: bool, median_features: int
                  ) -> tuple[str, list[tuple[int, int]], bool]:
    """``(matcher, pairs (i, j), guided)`` for ``n`` images (:func:`choose_matcher`; the
    sequential pairs with the loop's (:func:`loop_pairs`); guided matching by
    :data:`GUIDED_MAX_FEATURES` unless ``opts`` says), said on the log."""
    matcher = choose_matcher(opts.matcher, n, ordered, median_features)
    if matcher == "sequential":
        pairs = sorted(set(sequential_pairs(n, opts.sequential_overlap))
                       | set(loop_pairs(n, opts.sequential_overlap)))
    else:
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    guided = (median_features < GUIDED_MAX_FEATURES if opts.guided_matching is None
              else bool(opts.guided_matching))
    logger.info(f"colmap: {len(pairs)} image pairs to match ({matcher}"
                + (f": {opts.sequential_overlap} neighbours and frames 2^k later each, the "
                   "last frames with the first" if matcher == "sequential" else "")
                + f"{', guided' if guided else ''}; {n} images, {median_features} features "
                  "in the median one)")
    return matcher, pairs, guided


def in_chunks(items: Sequence, run: Any, advance: Any, first: int = 2) -> None:
    """``run(part)`` on consecutive parts of ``items``, then ``advance(len(part))``: the first
    part holds ``first`` items, each later one as many as took :data:`CHUNK_SECONDS` at the
    rate measured on the previous part (at most 4x the previous size)."""
    i, size = 0, max(1, int(first))
    while i < len(items):
        part = items[i:i + size]
        t0 = time.perf_counter()
        run(part)
        dt = time.perf_counter() - t0
        advance(len(part))
        i += len(part)
        size = max(1, min(4 * len(part), int(len(part) * CHUNK_SECONDS / max(dt, 1e-3))))
MIN_INLIER_FRACTION = 0.1
"""An image is registered with at least this fraction of the median image's features as 2D-3D
inliers (:func:`min_inliers`)."""


def min_inliers(median_features: int, cap: int) -> int:
    """The mapper's ``abs_pose_min_num_inliers``: :data:`MIN_INLIER_FRACTION` of the median
    image's features, between COLMAP's default 30 and ``cap`` (the mapper option, 100 by
    default).

    Measured on lego: the 400² training photos keep ~1,200 features each and need the cap of
    100 against a photo registered on the wrong side of the object; frames of a 320² video
    keep ~750, and with 100 a third of them failed to register (56 of 60 do with this rule,
    all within 0.8° of the truth; ``benchmarks/colmap_poses.py --video``).
    """
    return int(max(min(30, cap), min(cap, round(MIN_INLIER_FRACTION * median_features))))


def sequential_pairs(n: int, overlap: int) -> list[tuple[int, int]]:
    """Image pairs of a video's ``n`` frames in time order: each frame with its ``overlap``
    next ones, and (as COLMAP's sequential matcher's quadratic overlap) with the frames
    ``2**k`` later beyond them, which closes loops of orbits and revisits."""
    pairs = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + 1 + overlap))}
    k = 1
    while k < n:
        if k > overlap:
            pairs.update((i, i + k) for i in range(n - k))
        k *= 2
    return sorted(pairs)


def loop_pairs(n: int, overlap: int) -> list[tuple[int, int]]:
    """Pairs ``(i, j)`` that close the loop of a walk-around's ``n`` frames in time order: the
    last frames with the first ones, as if the sequence went on round (``j - i >= n -
    overlap``: each frame with its ``overlap`` neighbours across the end; ``overlap *
    (overlap + 1) / 2`` pairs). An open path's ends just fail to match."""
    if n <= overlap + 1:
        return []                      # sequential_pairs already holds every pair
    return [(i, j) for i in range(overlap) for j in range(n - overlap + i, n)]


def refines_principal_point(option: str, scene: str, rec: Any) -> bool:
    """Whether the final bundle adjustment refines the principal point (``option``: on, off,
    auto = for 360° captures: ``scene`` "360", or "auto" and the registered cameras' optical
    axes spread, :func:`plenoctree.datasets.colmap.capture_kind`).

    COLMAP's mapper keeps the principal point at the image centre; a phone's may sit pixels
    off it (instant-ngp's OPENCV camera of real/fox: 14.6 px right, 5.3 px below), which the
    poses then absorb as a rotation of each camera about its own centre, different for every
    camera. instant-ngp's ``colmap2nerf`` refines it in a last bundle adjustment too.
    """
    if option != "auto":
        return option == "on"
    if scene != "auto":
        return scene == "360"
    from ..datasets.colmap import capture_kind
    from ..datasets.colmap_model import rotation_c2w

    poses = [rec.images[i].cam_from_world() for i in rec.reg_image_ids()]
    return capture_kind(np.stack([rotation_c2w(p.rotation.matrix(), p.translation)
                                  for p in poses])) == "360"


def _global_ba(pycolmap: Any, rec: Any, refine_principal_point: bool = False) -> None:
    """Bundle adjustment of every registered image and point of ``rec`` (in place; through
    the adjuster object, which, unlike ``pycolmap.bundle_adjustment``, keeps COLMAP's log
    level: no INFO lines on the terminal), the principal point too when asked."""
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.print_summary = False
    ba.refine_principal_point = bool(refine_principal_point)
    pycolmap.create_default_bundle_adjuster(ba, config, rec).solve()


WEAK_IMAGE_FRACTION = 0.35
"""Images seeing fewer than this fraction of the median image's 3D points are deregistered."""


def drop_weak_images(rec: Any, fraction: float) -> list[str]:
    """Deregister the images of ``rec`` that observe fewer than ``fraction`` x the median
    number of 3D points per image; returns their names.

    Measured on lego (``benchmarks/colmap_poses.py``): a photo registered on the wrong side of
    the nearly symmetric object (165-170° off) keeps ~110 points where correctly registered
    ones keep 210-670 (median ~500), so these are cut; in a model without such a camera none
    is cut.
    """
    counts = {iid: im.num_points3D for iid, im in rec.images.items() if im.has_pose}
    if len(counts) < 5:
        return []
    limit = fraction * float(sorted(counts.values())[len(counts) // 2])
    weak = [iid for iid, n in counts.items() if n < limit]
    names = sorted(rec.images[iid].name for iid in weak)
    for iid in weak:
        rec.deregister_frame(rec.images[iid].frame_id)
    return names


def _match_pairs(pycolmap: Any, db: Path, work: Path, names: list[str], pairs: list,
                 opts: SfmOptions, show_progress: bool | None, desc: str) -> None:
    """Match image pairs ``(i, j)`` of ``names`` in chunks (:func:`in_chunks`) through a pairs
    file in ``work`` (one progress tick per pair), with ``opts``' threads, guided matching and
    RANSAC seed."""
    from .._util import progress

    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = int(opts.num_threads)
    mopt.guided_matching = bool(opts.guided_matching)
    ver = pycolmap.TwoViewGeometryOptions()
    ver.ransac.random_seed = int(opts.seed)

    pair_file = work / "pairs.txt"

    def match(part: Sequence[tuple[int, int]]) -> None:
        pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in part))
        popt = pycolmap.ImportedPairingOptions()
        popt.match_list_path = pair_file
        pycolmap.match_image_pairs(db, matching_options=mopt, pairing_options=popt,
                                   verification_options=ver, device=pycolmap.Device.cpu)

    with progress(total=len(pairs), desc=desc, unit="pair",
                  disable=_disable(show_progress)) as bar:
        in_chunks(pairs, match, bar.update, first=4)
    pair_file.unlink(missing_ok=True)
