"""NeRF-SH → PlenOctree extraction (paper §4.2), the function behind ``plenoctree extract``.

Stages (each timed, with its peak RSS):

1. ``load`` — the trained model (``load_nerf``) and the dataset's training cameras;
2. ``bbox`` — the extraction box: fitted to the content on a coarse grid (``--bbox auto``) or
   fixed (``--center/--radius``, else the model's training box, else the dataset's box);
   a forward-facing scene's box is then stretched along NDC depth (``--ndc-depth-stretch``,
   :func:`~.bbox.stretch_depth`; its grid: :data:`NDC_GRID`);
3. ``grid`` — σ at the centres of the ``grid³`` cells of the box;
4. ``filter`` — keep cells whose maximum ray weight over all training views is ``≥ τ_w``
   (``--masking weight``; and, with ``--unseen keep``, the cells that could reach it but lie
   outside every training view), or whose alpha is ``≥ --mask-alpha-thresh`` (``--masking
   sigma``);
5. ``sample`` — mean of ``S`` random samples of (coefficients, σ) in each kept cell
   (projected onto SH first for a plain NeRF);
6. ``build`` / ``save`` — the octree (kept cells are leaves at the deepest level) and its file;
7. ``eval`` — test-split PSNR/SSIM of the raw tree.

:func:`extract` takes an :class:`ExtractConfig` (its field docstrings are the ``--help``) and
optionally a radiance field object (anything following
:class:`~plenoctree.convert.field.RadianceField`) instead of a run directory.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._bounds import check_bounds
from .._util import atomic_save_json
from ..errors import ConfigError, PlenOctreeError
from .bbox import AutoBoxOptions, BoxResult, auto_bbox, fixed_bbox, stretch_depth
from .field import as_field
from .grid import GridSpec, check_resolution, evaluate_density_grid
from .memory import StageMonitor, check_budget, memory_limit
from .sampling import SampleOptions, SamplingStats, output_format, sample_cells
from .visibility import (auto_ray_scale, rescale_cameras, sigma_mask, unseen_cells,
                         visibility_weights, weight_mask)

logger = logging.getLogger(__name__)

__all__ = ["ExtractConfig", "ExtractResult", "extract", "estimate_grid_memory",
           "clamp_sigma_for_fp16", "extraction_grid", "GRID", "NDC_GRID"]

#: ``--grid 0`` of a 360° scene (the paper's 512 on a GPU is ``--grid 512``).
GRID = 256
#: ``--grid 0`` of a forward-facing (NDC) scene. An NDC ray runs along depth, so a pixel's
#: colour comes from one column of cells: 256 cells across flower's box are 2.8 pixels wide
#: (496 px) and refinement only splits some of them. 512 across with cells 4x deeper than wide
#: (--ndc-depth-stretch) has fewer leaves than 256³ refined and is sharper (docs/capture.md).
NDC_GRID = 512


def extraction_grid(grid: int, ndc: bool) -> int:
    """The grid an extraction runs at: ``grid``, or for 0 :data:`NDC_GRID` (``ndc``: a
    forward-facing scene) else :data:`GRID`."""
    return int(grid) if grid else (NDC_GRID if ndc else GRID)


@dataclass
class ExtractConfig:
    """Conversion of a trained NeRF-SH run into a PlenOctree."""

    run_dir: str = ""
    """Run directory of a trained NeRF-SH (holding checkpoint.pt), or the checkpoint file."""
    out: str = ""
    """Output tree file (.npz); default: RUN_DIR/tree.npz."""
    data: str = ""
    """Dataset folder (default: the one the run was trained on)."""
    grid: int = 0
    """Cells per axis of the extraction grid, a power of two (paper: 512); 0: 256, or 512 for a
    forward-facing (NDC) scene, whose cells are also deeper than wide (--ndc-depth-stretch)."""
    ndc_depth_stretch: float = 4.0
    """Forward-facing (NDC) scenes: stretch the box this many times along depth, so each cell
    is that many times deeper than wide (NDC rays run along depth: what the image resolves is
    in x and y; flower, 512 cells across: +0.2 dB at 26 % fewer leaves and 1.27x the FPS of
    256³ refined); 1 = cubic cells. 360° scenes ignore it."""
    far_grid: int = 0
    """Runs with a far field (360° captures of a place): cells per axis of each shell's grid
    around the box (a power of two; 0: half of --grid). Shell l's cells are 2^l times the size
    of those of this grid over the box."""
    samples: int = 8
    """Random samples averaged per kept voxel (paper: 256)."""
    averaging: str = "opacity"
    """Voxel value from its samples: opacity (the default: σ keeping the samples' mean opacity
    over the voxel side, opacity-weighted colour; lego 256³: +0.4 dB raw) or mean (of σ and
    coefficients, the paper's)."""
    masking: str = "weight"
    """Voxel filter: "weight" (max ray weight over the training views, the paper's) or "sigma"
    (alpha threshold; keeps hidden matter too)."""
    weight_thresh: float = 0.001
    """τ_w: keep voxels whose maximum ray weight is at least this (paper 1.4G variant: 0.01)."""
    unseen: str = "keep"
    """With --masking weight, voxels no training view holds (outside every camera's image),
    which the weight filter cannot judge: "keep" those dense enough to reach τ_w (the
    network's guess: held-out photos see past the training views' edges; flower +0.13 dB) or
    "drop" them (the paper's filter)."""
    mask_alpha_thresh: float = 0.01
    """With --masking sigma: keep voxels whose alpha 1 - exp(-σ δ) (δ = voxel side) is at
    least this."""
    bbox: str = "auto"
    """Extraction box: "auto" (fitted to the content on a coarse grid) or "fixed"."""
    alpha_thresh: float = 0.1
    """τ_a of the auto box: coarse cells with alpha 1 - exp(-σ δ) at least this define the
    content (paper configs: 0.1)."""
    bbox_grid: int = 128
    """Cells per axis of the coarse grid of the auto box (original code: 256)."""
    bbox_scale: float = 1.0
    """Multiply the box's radius by this (paper: 1.1-1.2 for scenes with thin outer parts)."""
    bbox_cube: bool = False
    """Make the box a cube (equal radii)."""
    center: tuple = ()
    """Box centre (x y z) of the fixed box, or the initial box the auto box searches; default:
    the model's training box, else the dataset's."""
    radius: tuple = ()
    """Box half side (one value or x y z) to go with --center."""
    precision: str = "fp32"
    """Stored precision of the tree: fp32 or fp16 (half the file size; σ above the float16
    maximum 65504 is clamped to it, which renders identically)."""
    projection_dirs: int = 10000
    """Plain (view-dependent) NeRFs: Monte-Carlo directions per sample point for the SH
    projection (paper: 10000)."""
    projection_degree: int = 3
    """Plain NeRFs: SH degree the colour is projected onto."""
    vis_scale: float = 0.0
    """Ray density of the visibility filter: the training views are rendered at this multiple
    of the run's image size (0: auto, the smallest scale >= 1 at which a pixel is no wider
    than a voxel at the scene centre, so no visible voxel is missed between rays)."""
    chunk: int = 1 << 17
    """Points per network call (bounds memory besides the grids)."""
    memory_gb: float = 0.0
    """Memory budget in GiB for the grids and leaf values (0: 80% of the available memory)."""
    eval: bool = True
    """Render the test split with the raw tree and report PSNR/SSIM."""
    eval_views: int = 0
    """Test views to evaluate, evenly spaced (0: all)."""
    eval_downscale: int = 0
    """Downscale of the test views (0: the run's)."""
    eval_out: str = ""
    """Folder for the test renders and metrics.json (default: none written)."""
    backend: str = "auto"
    """Kernels for the visibility filter and the evaluation: auto, numba or torch."""
    device: str = "auto"
    """Device of the network: auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N."""
    amp: bool = False
    """Evaluate the network in bf16 autocast (faster on CPUs with bf16 units, less exact)."""
    threads: int = 0
    """CPU threads for torch and numba (0: all cores)."""
    seed: int = 0
    """Random seed of the per-voxel samples and projection directions."""
    show_progress: bool | None = None
    """Progress bars (None: when stderr is a terminal)."""


@dataclass
class ExtractResult:
    """What :func:`extract` produced: the tree, where it went, and the figures of each stage."""

    tree: Any
    out: Path | None
    box: BoxResult
    grid: int
    n_candidates: int
    n_kept: int
    file_bytes: int
    stages: dict
    psnr: float = float("nan")
    ssim: float = float("nan")
    eval_views: int = 0
    nerf_psnr: float | None = None
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        t = self.tree
        return {"out": str(self.out) if self.out else None, "grid": self.grid,
                "box": self.box.to_json(), "n_candidates": self.n_candidates,
                "n_leaves_kept": self.n_kept, "n_nodes": int(t.n_nodes),
                "n_leaves": int(t.n_leaves), "data_format": t.data_format,
                "file_bytes": self.file_bytes, "file_mb": round(self.file_bytes / 2**20, 3),
                "stages": self.stages, "test_psnr": _nan_none(self.psnr),
                "test_ssim": _nan_none(self.ssim), "eval_views": self.eval_views,
                "nerf_val_psnr": self.nerf_psnr, **self.extra}


def _nan_none(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


FP16_MAX = 65504.0


def clamp_sigma_for_fp16(tree: Any) -> int:
    """Clamp σ of ``tree`` (in place) to the float16 maximum; returns how many leaves changed.

    Networks with an exponential density activation produce σ far above 65504 inside solid
    matter. Any σ that large is opaque within 1e-3 world units (alpha = 1 - exp(-65.5) = 1
    in float32), so the clamp leaves renders unchanged while letting the tree be saved in fp16.
    """
    sig = tree.data[..., -1]
    over = sig > FP16_MAX
    n = int(np.count_nonzero(over))
    if n:
        sig[over] = FP16_MAX
    return n


def estimate_grid_memory(res: int) -> int:
    """Bytes for the dense stages at ``res³``: σ (float32), candidate index (int32), mask (bool)
    and the octree builder's occupancy pyramid."""
    return int(res ** 3 * (4 + 4 + 1 + 1.2))


def _validate(cfg: ExtractConfig) -> None:
    if cfg.grid != 0:
        check_resolution("--grid", cfg.grid, low=2, high=4096)
    if not (np.isfinite(cfg.ndc_depth_stretch) and cfg.ndc_depth_stretch >= 1.0):
        raise ConfigError(f"--ndc-depth-stretch must be >= 1, got {cfg.ndc_depth_stretch}")
    check_resolution("--bbox-grid", cfg.bbox_grid, low=2, high=4096)
    for name, v in (("--samples", cfg.samples), ("--projection-dirs", cfg.projection_dirs),
                    ("--chunk", cfg.chunk)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ConfigError(f"{name} must be a positive integer, got {v!r}")
    from .sampling import AVERAGING

    if cfg.averaging not in AVERAGING:
        raise ConfigError(f"--averaging must be one of {', '.join(AVERAGING)}, got "
                          f"{cfg.averaging!r}")
    if cfg.masking not in ("weight", "sigma"):
        raise ConfigError(f"--masking must be weight or sigma, got {cfg.masking!r}")
    if cfg.unseen not in ("keep", "drop"):
        raise ConfigError(f"--unseen must be keep or drop, got {cfg.unseen!r}")
    if cfg.bbox not in ("auto", "fixed"):
        raise ConfigError(f"--bbox must be auto or fixed, got {cfg.bbox!r}")
    if not 0.0 < cfg.weight_thresh < 1.0:
        raise ConfigError(f"--weight-thresh must be in (0, 1), got {cfg.weight_thresh}")
    if not 0.0 <= cfg.mask_alpha_thresh < 1.0:
        raise ConfigError(f"--mask-alpha-thresh must be in [0, 1), got {cfg.mask_alpha_thresh}")
    if not 0.0 < cfg.alpha_thresh < 1.0:
        raise ConfigError(f"--alpha-thresh must be in (0, 1), got {cfg.alpha_thresh}")
    if not (np.isfinite(cfg.bbox_scale) and cfg.bbox_scale > 0):
        raise ConfigError(f"--bbox-scale must be > 0, got {cfg.bbox_scale}")
    if cfg.precision not in ("fp16", "fp32"):
        raise ConfigError(f"--precision must be fp16 or fp32, got {cfg.precision!r}")
    if not 0 <= cfg.projection_degree <= 4:
        raise ConfigError(f"--projection-degree must be in 0..4, got {cfg.projection_degree}")
    if len(cfg.center) not in (0, 3):
        raise ConfigError(f"--center needs 3 numbers, got {list(cfg.center)}")
    if len(cfg.radius) not in (0, 1, 3):
        raise ConfigError(f"--radius needs 1 or 3 numbers, got {list(cfg.radius)}")
    for name, v in (("--vis-scale", cfg.vis_scale), ("--eval-downscale",
                    cfg.eval_downscale), ("--eval-views", cfg.eval_views),
                    ("--threads", cfg.threads)):
        if v < 0:
            raise ConfigError(f"{name} must be >= 0, got {v}")
    check_bounds(cfg)


def _load_run(cfg: ExtractConfig) -> tuple[Any, Any, float | None]:
    """``(field, train_config, nerf_val_psnr)`` of the run directory."""
    from ..nerf.checkpoint import model_from_checkpoint, read_checkpoint
    from .field import NeRFField

    if not cfg.run_dir:
        raise ConfigError("no run directory given (RUN_DIR holding checkpoint.pt)")
    try:
        ck = read_checkpoint(cfg.run_dir)
        model = model_from_checkpoint(ck, device=cfg.device)
    except PlenOctreeError as e:
        raise ConfigError(f"{e} — extraction needs a trained NeRF-SH run directory with a "
                          f"usable checkpoint.pt (train one with `plenoctree train`)") from None
    val = ck["log"].get("val") if isinstance(ck.get("log"), dict) else None
    psnr = None
    if val and isinstance(val[-1], dict) and val[-1].get("psnr") is not None:
        psnr = float(val[-1]["psnr"])
    return NeRFField(model, device=cfg.device, amp=cfg.amp), ck["config"], psnr


def _initial_box(cfg: ExtractConfig, field_: Any, data_bbox: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray, str]:
    if cfg.center or cfg.radius:
        center = np.asarray(cfg.center if cfg.center else (0.0, 0.0, 0.0), dtype=np.float64)
        if not cfg.radius:
            raise ConfigError("--center needs --radius too")
        return center, np.broadcast_to(np.asarray(cfg.radius, np.float64), (3,)).copy(), "user"
    for bbox, src in ((getattr(field_, "scene_bbox", None), "model"), (data_bbox, "dataset")):
        if bbox is not None:
            b = np.asarray(bbox, dtype=np.float64).reshape(2, 3)
            return 0.5 * (b[0] + b[1]), 0.5 * (b[1] - b[0]), src
    raise ConfigError("no box: give --center and --radius (neither the model nor the dataset "
                      "has a scene box)")


def _load_split(root: str, split: str, downscale: int, background: Any) -> Any:
    from ..datasets import load_dataset

    return load_dataset(root, split=split, downscale=downscale, background=background)


def _ndc_space(train: Any, root: str, downscale: int, background: Any) -> Any:
    """The NDC space of the dataset's cameras (None for 360° scenes or without a dataset);
    reads one training image when the split is not loaded anyway."""
    from ..datasets import load_dataset
    from ..octree.ndc import NDCSpace

    if train is None and root:
        train = load_dataset(root, split="train", downscale=downscale, background=background,
                             limit=1)
    return NDCSpace.from_cameras(train.cameras) if train is not None else None


@dataclass
class _Inputs:
    """What the ``load`` stage found: the field, the run's figures and the training views."""

    field: Any
    train_cfg: Any                 # the run's TrainConfig (None for a field given directly)
    nerf_psnr: float | None
    data_root: str
    downscale: int
    background: tuple
    train: Any                     # training views (None unless --masking weight needs them)
    ndc: Any
    fmt: str
    extra_data: Any
    dim: int
    cams: Any = None               # the training views' cameras (kept for the shells)


def _prepare(cfg: ExtractConfig) -> tuple[ExtractConfig, int]:
    """Check the options, the output file, threads and the memory budget before any work;
    returns ``(cfg with the device resolved, memory limit in bytes)``."""
    _validate(cfg)
    from ..device import resolve_device

    cfg = dataclasses.replace(cfg, device=str(resolve_device(cfg.device)))
    if cfg.out:                     # before any work: never overwrite an unrelated file
        from .._util import check_output_file

        check_output_file(Path(cfg.out) / "tree.npz" if Path(cfg.out).is_dir() else cfg.out)
    if cfg.threads > 0:             # only when asked: a library call keeps the process's threads
        from ..runtime import setup_threads

        setup_threads(cfg.threads)
    limit = memory_limit(cfg.memory_gb)
    if cfg.grid:                    # (an automatic grid is checked once the scene is known)
        _check_grid_budget(cfg.grid, limit)
    check_budget(f"the {cfg.bbox_grid}^3 auto-bbox grid", cfg.bbox_grid ** 3 * 5, limit,
                 "use a smaller --bbox-grid")
    return cfg, limit


def _check_grid_budget(grid: int, limit: int) -> None:
    check_budget(f"a {grid}^3 extraction grid", estimate_grid_memory(grid), limit,
                 f"use a smaller --grid (e.g. {max(2, grid // 2)}) or raise --memory-gb")


def _load_inputs(cfg: ExtractConfig, field: Any) -> _Inputs:
    """Stage ``load``: the run's model (or ``field``), its dataset's training views when the
    weight filter needs them, the NDC space, and the output format."""
    train_cfg, nerf_psnr = None, None
    if field is None:
        field, train_cfg, nerf_psnr = _load_run(cfg)
    else:
        field = as_field(field, device=cfg.device, amp=cfg.amp)
    data_root = cfg.data or (train_cfg.data if train_cfg is not None else "")
    run_down = int(train_cfg.downscale) if train_cfg is not None else 1
    background = getattr(train_cfg, "background", None)      # None: the dataset's default
    need_train = cfg.masking == "weight"
    if (need_train or cfg.eval) and not data_root:
        raise ConfigError("no dataset: pass --data (the training views are needed by "
                          "--masking weight and the test views by --eval)")
    if data_root and not Path(data_root).is_dir():
        raise ConfigError(f"{data_root}: dataset folder not found; pass --data")
    train = _load_split(data_root, "train", run_down, background) if need_train else None
    ndc = _ndc_space(train, data_root, run_down, background)
    fmt, extra_data, dim = output_format(field, cfg.projection_degree)
    return _Inputs(field, train_cfg, nerf_psnr, data_root, run_down, background, train, ndc,
                   fmt, extra_data, dim)


def _extraction_box(cfg: ExtractConfig, inp: _Inputs) -> BoxResult:
    """Stage ``bbox``: the auto-fitted or the fixed box."""
    data_bbox = inp.train.scene_bbox if inp.train is not None else None
    c0, r0, src = _initial_box(cfg, inp.field, data_bbox)
    if cfg.bbox == "auto":
        box = auto_bbox(inp.field, c0, r0, AutoBoxOptions(
            res=cfg.bbox_grid, alpha_thresh=cfg.alpha_thresh, scale=cfg.bbox_scale,
            cube=cfg.bbox_cube, chunk=cfg.chunk, show_progress=cfg.show_progress))
    else:
        box = fixed_bbox(c0, r0, src, cfg.bbox_scale, cfg.bbox_cube)
    return stretch_depth(box, cfg.ndc_depth_stretch) if inp.ndc is not None else box


def _filter(cfg: ExtractConfig, sigma: np.ndarray, spec: GridSpec, train: Any,
            limit: int) -> tuple[np.ndarray, int, dict]:
    """Stage ``filter``: ``(mask of kept cells, candidates, visibility figures)``.

    Raises:
        ConfigError: the filter removed every cell.
    """
    if cfg.masking == "weight":
        ray_scale = cfg.vis_scale or auto_ray_scale(train.cameras, spec)
        cams = rescale_cameras(train.cameras, ray_scale)
        vis_info = {"vis_views": len(cams), "vis_size": [cams.width, cams.height],
                    "vis_scale": ray_scale}
        cand, weights = visibility_weights(sigma, spec, cams, cfg.weight_thresh,
                                           cfg.backend, cfg.show_progress, limit,
                                           device=cfg.device)
        n_cand = int(cand.flat.size)
        mask = weight_mask(spec, cand, weights, cfg.weight_thresh)
        if cfg.unseen == "keep":
            dropped = cand.flat[weights < cfg.weight_thresh]
            add = dropped[unseen_cells(spec, dropped, train.cameras)]
            mask.reshape(-1)[add] = True
            vis_info["unseen_kept"] = int(add.size)
        max_w = float(weights.max()) if weights.size else 0.0
        del cand, weights
        what = (f"no voxel reaches the weight threshold {cfg.weight_thresh:g} in any of the "
                f"{len(train)} training views (largest weight {max_w:.3g}); lower "
                f"--weight-thresh or use --masking sigma")
    else:
        vis_info = {}
        mask = sigma_mask(sigma, spec, cfg.mask_alpha_thresh)
        n_cand = int(np.count_nonzero(sigma > 0))
        what = (f"no voxel has alpha >= {cfg.mask_alpha_thresh:g} (largest σ "
                f"{float(sigma.max()):.4g}); lower --mask-alpha-thresh")
    if not np.any(mask):
        raise ConfigError(f"every voxel was removed: {what}")
    return mask, n_cand, vis_info


def _sample_and_build(cfg: ExtractConfig, inp: _Inputs, spec: GridSpec, mask: np.ndarray,
                      mon: StageMonitor) -> tuple[Any, SamplingStats]:
    """Stages ``sample`` and ``build``: the kept cells' values and the octree of them."""
    from ..octree import Octree

    with mon.stage("sample"):
        st = SamplingStats()
        values = sample_cells(inp.field, spec, np.flatnonzero(mask), SampleOptions(
            samples=cfg.samples, chunk=cfg.chunk, seed=cfg.seed, averaging=cfg.averaging,
            projection_degree=cfg.projection_degree, projection_dirs=cfg.projection_dirs,
            show_progress=cfg.show_progress), st)
    with mon.stage("build"):
        tree = Octree.from_grid(values, mask, spec.center, spec.radius, inp.fmt, inp.extra_data)
        tree.ndc = inp.ndc      # forward-facing: the NDC space the box lives in (octree.ndc)
    return tree, st


def _shells(cfg: ExtractConfig, inp: _Inputs, tree: Any, grid: int, limit: int
            ) -> tuple[Any, dict]:
    """Stage ``shells``: the far field around the box (:mod:`.shells`)."""
    from .shells import ShellOptions, add_shells, shell_levels

    far = inp.field.model.far
    outer = (far.radius * float(2 ** far.levels)).detach().cpu().numpy()
    levels = shell_levels(tree.radius, outer, tree.max_depth)
    cams = inp.cams
    if cams is None:                # (--masking sigma: the views were not loaded)
        cams = _load_split(inp.data_root, "train", inp.downscale, inp.background).cameras
    opts = ShellOptions(grid=cfg.far_grid or max(4, grid // 2),
                        weight_thresh=cfg.weight_thresh, backend=cfg.backend,
                        device=cfg.device, show_progress=cfg.show_progress,
                        samples=SampleOptions(samples=cfg.samples, chunk=cfg.chunk,
                                              seed=cfg.seed + 1, averaging=cfg.averaging,
                                              show_progress=cfg.show_progress))
    grown, info = add_shells(tree, inp.field, cams, levels, opts, limit)
    logger.info(f"far field: {levels} shells around the box, {sum(info['shell_leaves'])} "
                f"leaves ({', '.join(map(str, info['shell_leaves']))} per shell)")
    return grown, info


def _output_path(cfg: ExtractConfig, from_run: bool) -> Path | None:
    """``cfg.out`` (a folder: its ``tree.npz``), else ``RUN_DIR/tree.npz`` for a run, else
    None (a field given directly is not saved)."""
    out = Path(cfg.out) if cfg.out else (Path(cfg.run_dir) / "tree.npz"
                                         if cfg.run_dir and from_run else None)
    if out is not None and out.is_dir():
        out = out / "tree.npz"
    return out


def _save(tree: Any, out: Path, precision: str) -> tuple[int, int]:
    """Stage ``save``: ``(file bytes, σ values clamped for fp16)``."""
    from ..octree import save_tree

    n_clamped = clamp_sigma_for_fp16(tree) if precision == "fp16" else 0
    try:
        save_tree(tree, out, precision)
    except ValueError as e:
        raise ConfigError(f"{out}: {e}; save with --precision fp32") from None
    return os.path.getsize(out), n_clamped


def extract(cfg: ExtractConfig, field: Any = None) -> ExtractResult:
    """Convert a trained radiance field into a PlenOctree (see the module docstring).

    Args:
        cfg: the options. ``cfg.run_dir`` names the run unless ``field`` is given.
        field: optional radiance field to convert instead of the run's model (e.g.
            :class:`~plenoctree.convert.field.AnalyticField`); then ``cfg.data`` names the
            dataset (needed for ``masking="weight"`` and ``eval``).

    Returns:
        An :class:`ExtractResult`; the tree is also saved to ``cfg.out`` (default
        ``RUN_DIR/tree.npz``; with ``field`` and no ``out``, not saved) together with
        ``<out stem>.extract.json`` holding the figures.

    Raises:
        ConfigError: bad options, an unusable run directory, a box with nothing in it, a grid
            too large for the memory budget, a threshold that removes every voxel.
    """
    cfg, limit = _prepare(cfg)
    mon = StageMonitor()
    with mon.stage("load"):
        inp = _load_inputs(cfg, field)
    grid = extraction_grid(cfg.grid, inp.ndc is not None)
    if not cfg.grid:
        _check_grid_budget(grid, limit)
    with mon.stage("bbox"):
        box = _extraction_box(cfg, inp)
        spec = GridSpec.make(box.center, box.radius, grid)
    with mon.stage("grid"):
        sigma = evaluate_density_grid(inp.field, spec, cfg.chunk, show_progress=cfg.show_progress)
    with mon.stage("filter"):
        mask, n_cand, vis_info = _filter(cfg, sigma, spec, inp.train, limit)
        del sigma
        if inp.train is not None:   # the images are not needed any more, the cameras are
            inp.cams, inp.train = inp.train.cameras, None
        n_kept = int(np.count_nonzero(mask))
        check_budget(f"{n_kept} leaves x {inp.dim} values (sampling and octree)",
                     int(n_kept * inp.dim * 4 * 3.5), limit,
                     "use a smaller --grid or a higher --weight-thresh")
    tree, st = _sample_and_build(cfg, inp, spec, mask, mon)
    del mask
    far_info = {}
    if getattr(getattr(inp.field, "model", None), "far", None) is not None:
        with mon.stage("shells"):
            tree, far_info = _shells(cfg, inp, tree, grid, limit)
    out = _output_path(cfg, inp.train_cfg is not None)
    file_bytes, n_clamped = 0, 0
    if out is not None:
        with mon.stage("save"):
            file_bytes, n_clamped = _save(tree, out, cfg.precision)
    res = ExtractResult(tree, out, box, grid, n_cand, n_kept, file_bytes, {},
                        nerf_psnr=inp.nerf_psnr,
                        extra={**far_info,
                               "sampled_points": st.points, "nonfinite_values": st.nonfinite,
                               "sigma_clamped_fp16": n_clamped, **_settings(cfg), **vis_info,
                               "config": {k: (list(v) if isinstance(v, tuple) else v)
                                          for k, v in dataclasses.asdict(cfg).items()}})
    if cfg.eval:
        with mon.stage("eval"):
            _evaluate(res, cfg, inp.data_root, cfg.eval_downscale or inp.downscale,
                      inp.background)
    res.stages = mon.to_json()
    if out is not None:
        atomic_save_json(out.with_name(out.stem + ".extract.json"), res.to_json())
    return res


def _settings(cfg: ExtractConfig) -> dict:
    """The options repeated at the top level of ``extract.json``."""
    return {"samples": cfg.samples, "averaging": cfg.averaging, "masking": cfg.masking,
            "device": cfg.device, "weight_thresh": cfg.weight_thresh,
            "unseen": cfg.unseen, "precision": cfg.precision}


def _evaluate(res: ExtractResult, cfg: ExtractConfig, root: str, downscale: int,
              background: Any) -> None:
    """Test-split PSNR/SSIM of the raw tree (evenly spaced ``cfg.eval_views`` views)."""
    from ..datasets import load_dataset
    from ..evaluation import evaluate_tree
    from ..render import RenderOptions

    test = load_dataset(root, split="test", downscale=downscale, background=background,
                        limit=cfg.eval_views or None, spread=True)
    t0 = time.perf_counter()
    ev = evaluate_tree(res.tree, test, cfg.eval_out or None,
                       RenderOptions(background=tuple(float(b) for b in test.background)),
                       cfg.backend, show_progress=cfg.show_progress)
    res.psnr, res.ssim, res.eval_views = ev.mean_psnr, ev.mean_ssim, len(ev.psnr)
    res.extra["eval_ms_per_frame"] = ev.ms_per_frame
    res.extra["eval_seconds"] = time.perf_counter() - t0
    res.extra["eval_size"] = [ev.width, ev.height]
