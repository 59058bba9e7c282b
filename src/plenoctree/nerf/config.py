"""Configuration of NeRF-SH models and training: dataclasses, presets, JSON round trip.

Two dataclasses: :class:`ModelConfig` (everything that fixes the network's parameters — a
checkpoint is only loadable into the same ``ModelConfig``) and :class:`TrainConfig` (data,
sampling, optimisation, logging; holds a ``model``). The docstring under each field is its
``--help`` text on the command line (read by :func:`field_docs`).

Presets (:func:`preset`):

* ``"cpu"`` — the most quality per minute on two CPU cores: a multiresolution hash-grid
  encoding (numba kernels), a tiny bf16 MLP (32 → 64 → 64 → 1 + 48), one network sampled by
  marching a fixed step through a 128³ occupancy grid updated during training, early ray
  termination in training, ~2^17 samples per step, Adam 1e-2 → 5e-4, sparsity prior with
  the paper's β and λ on K = 4096 points.
* ``"gpu"`` — the cpu preset's network on a GPU's terms: steps of fixed shape
  (``fixed_step``, :mod:`plenoctree.nerf.fixed`: no host round trip inside a step) with a
  budget of 2^18 samples, a 2^19-row hash table, 20,000 steps, K = 10000 sparsity points.
* ``"paper"`` — the paper's NeRF-SH (§4.1, jaxnerf settings of the original code): positional
  encoding with 10 frequencies, 8 × 256 MLP with a skip at layer 4, ReLU σ, SH degree 3,
  coarse + fine networks with 64 stratified + 128 importance samples, 1024 rays per batch,
  Adam 5e-4 → 5e-6 over 2,000,000 steps, sparsity prior β = 1e-3, λ = 0.05, K = 10000.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import json
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._bounds import check_bounds
from ..errors import ConfigError

__all__ = ["ModelConfig", "TrainConfig", "preset", "PRESETS", "field_docs", "config_from_dict",
           "config_to_dict"]


@dataclass
class ModelConfig:
    """The NeRF-SH network: encoding, MLP, output basis."""

    encoding: str = "hashgrid"
    """Position encoding: "hashgrid" (multiresolution grid, CPU preset) or "posenc" (NeRF)."""
    pe_freqs: int = 10
    """Positional-encoding frequencies of positions (posenc only; paper: 10)."""
    grid_levels: int = 16
    """Hash grid: number of resolution levels."""
    grid_features: int = 2
    """Hash grid: features per level."""
    grid_base_res: int = 16
    """Hash grid: resolution (cells per axis) of the coarsest level."""
    grid_max_res: int = 1024
    """Hash grid: resolution of the finest level."""
    grid_log2_table: int = 18
    """Hash grid: log2 of the rows of each hashed level (coarse levels that fit are dense)."""
    net_depth: int = 2
    """Hidden layers of the MLP trunk (paper: 8)."""
    net_width: int = 64
    """Width of the MLP trunk (paper: 256)."""
    skip_layer: int = 0
    """Concatenate the encoded input again after this many hidden layers (paper: 4; 0 = none)."""
    basis: str = "sh"
    """Colour basis: "sh" (spherical harmonics), "sg" (learned spherical Gaussians) or "plain"
    (a NeRF head with a view-direction input, for SH projection in the conversion step)."""
    sh_degree: int = 3
    """SH degree 0-4 for basis "sh" ((degree + 1)^2 coefficients per channel; paper: 3)."""
    sg_lobes: int = 25
    """Number of spherical-Gaussian lobes for basis "sg" (paper appendix: 25)."""
    view_freqs: int = 4
    """Positional-encoding frequencies of the view direction (basis "plain" only)."""
    view_width: int = 128
    """Width of the view-dependent layer (basis "plain" only)."""
    sigma_activation: str = "trunc_exp"
    """Density activation: "relu" (paper) or "trunc_exp" (``exp(raw - 1)`` with a clamped
    gradient)."""
    coarse: bool = False
    """Also train a separate coarse network for hierarchical sampling (paper: yes)."""


@dataclass
class TrainConfig:
    """NeRF-SH training: data, sampling, optimisation, logging, checkpoints."""

    data: str = ""
    """Dataset folder (any supported format: Blender, LLFF, NSVF, nerfstudio)."""
    format: str | None = None
    """Dataset format (one of ``plenoctree.datasets.FORMATS``; default: detected from the
    folder's files)."""
    out: str = ""
    """Run directory for checkpoints, logs and plots."""
    preset: str = "cpu"
    """Name of the preset these settings started from (informational)."""
    downscale: int = 1
    """Integer image downscale factor (2: 800x800 -> 400x400)."""
    background: tuple | None = None
    """Background colour that transparent pixels and rays ending see-through are composited
    onto (None: the dataset's, ``datasets.default_background``: black for real photos, white
    for renders)."""
    random_background: bool = True
    """Train on random background colours when the dataset keeps alpha (stops the model from
    explaining the background with white matter); evaluation always uses ``background``."""
    photo_background: str = "auto"
    """Photos without alpha: "random" trains them on random background colours too, so every
    ray must end opaque inside the scene box (nothing in a photo is see-through to a white
    backdrop; unbounded content settles on the box's far walls, or with a far field on its outer
    cube); "fixed" composites them with
    ``background``; "auto": random for real photos (LLFF, COLMAP, nerfstudio formats), fixed
    for Blender and NSVF (renders with a white backdrop baked in)."""
    sampler: str = "occupancy"
    """Ray sampling: "occupancy" (fixed step through an occupancy grid, one network) or
    "hierarchical" (stratified coarse + importance fine samples, the paper's)."""
    n_coarse: int = 64
    """Hierarchical sampler: stratified samples per ray (paper: 64)."""
    n_fine: int = 128
    """Hierarchical sampler: importance samples per ray (paper: 128)."""
    render_step: float = -1.0
    """Occupancy sampler: distance between samples along a ray, world units (-1 = automatic:
    0.01, or for a capture of a place, whose box is a working box about the cameras in the
    arbitrary units of its poses, 1/200 of the box's side: :func:`.far.resolve_render_step`)."""
    occ_res: int = 128
    """Occupancy sampler: cells per axis of the occupancy grid over the scene box."""
    far_levels: int = -1
    """Far field: shells of a second network around the scene box, each twice the size of
    the last (0 = none; -1 = automatic: enough to reach the dataset's far bound, 4 to 7, for
    captures of a place (360° LLFF and COLMAP scenes) with the occupancy sampler, else 0)."""
    far_samples: int = 32
    """Far field: samples per ray, uniform in inverse distance beyond the scene box."""
    far_fine: int = 32
    """Far field: samples per ray drawn from the weights of the ``far_samples`` ones."""
    occ_update_every: int = 16
    """Occupancy sampler: steps between occupancy-grid updates."""
    occ_warmup_steps: int = 256
    """Occupancy sampler: steps during which every update re-evaluates every cell."""
    occ_threshold: float = 0.01
    """Occupancy sampler: a cell is occupied when one step through it has opacity above this."""
    occ_decay: float = 0.8
    """Occupancy sampler: decay of the cells' running density at each update after the
    warm-up (during it: instant-ngp's 0.95, :data:`.occupancy.WARMUP_DECAY`). Not 0.95 after
    it too: a cleared cell then stays in the grid for ~90 updates (from 100x the threshold),
    ~1,400 steps, most of a CPU budget, and rays keep sampling the early fog (flower's photos at
    step 800: 3.3 k rays/s against 12.5 k). At equal steps and time: flower +0.9 dB (1,200
    steps), lego 400² +0.3 dB, fox +0.1 dB; 0.8 from the first update gained more on flower but lost 0.55 dB on fox and
    opacity on a small forward-facing scene: the grid dropped regions the young network had
    not learned yet (docs/capture_records.md "The occupancy grid's decay")."""
    train_stop_thresh: float = 1e-4
    """Early ray termination in training: samples behind transmittance below this are not
    trained (0 = keep every sample)."""
    eval_stop_thresh: float = 1e-4
    """Early ray termination when rendering images (occupancy sampler)."""
    batch_rays: int = field(default=4096, metadata={"flag": "batch-size"})
    """Rays per step (hierarchical sampler; the first steps of the occupancy sampler)."""
    target_samples: int = 1 << 17
    """Occupancy sampler: adapt the rays per step so that about this many samples are trained."""
    max_rays: int = 1 << 16
    """Occupancy sampler: upper bound of the adaptive rays per step."""
    fixed_step: bool = False
    """Occupancy sampler: train in steps of fixed shape (``nerf.fixed``, the ``gpu``
    preset): each step marches its rays once into ``fixed_candidates × target_samples``
    candidate slots, drops the samples behind ``train_stop_thresh`` by a density pass without
    gradients, trains the network on ``target_samples`` slots, and reads nothing back inside
    the step; the rays per step adapt every ``occ_update_every`` steps. Off: marching waves
    with early ray termination (host round trips each wave, the CPU's way)."""
    cuda_graph: bool = False
    """Fixed-shape steps: capture each ray count's step (network, loss, backward, Adam) in a
    CUDA graph after a few eager steps and replay it, one launch instead of ~140
    (``nerf.graph``). Off until measured on a GPU (``benchmarks/gpu_bench.py``, row
    ``train_gpu_graph``); without CUDA the same step runs eagerly."""
    fixed_candidates: int = 4
    """Fixed-shape steps: candidate slots marched per trained slot, for early ray termination
    (nerfacc's and instant-ngp's way; the density of every candidate slot is evaluated, so
    more costs time; lego trains alike at 4 and 8). 1 = no early termination: every marched
    sample is trained (a ray behind a surface keeps its samples, so fewer rays fit a step)."""
    max_steps: int = field(default=30000, metadata={"flag": "steps"})
    """Training steps (the run also stops at ``minutes`` when that is set)."""
    minutes: float = 0.0
    """Training-time budget in minutes (0 = none); `run`'s default -1: 15 for a
    forward-facing capture, 30 for a 360° one. With a budget the learning-rate schedule
    follows elapsed training time, so such runs are not bit-for-bit repeatable."""
    lr_init: float = 1e-2
    """Initial learning rate (paper: 5e-4)."""
    lr_final: float = 5e-4
    """Final learning rate, reached log-linearly at the end (paper: 5e-6)."""
    lr_delay_steps: int = 0
    """Warm-up steps with a reduced learning rate (jaxnerf's lr_delay_steps)."""
    lr_delay_mult: float = 1.0
    """Learning-rate multiplier at step 0 of the warm-up (jaxnerf's lr_delay_mult)."""
    adam_eps: float = 1e-15
    """Adam epsilon."""
    adam_beta2: float = 0.99
    """Adam beta2 (beta1 is 0.9)."""
    sparsity_weight: float = 1e-3
    """β of the sparsity prior β·mean_k |1 - exp(-λ σ_k)| (paper: 1e-3; 0 = off)."""
    sparsity_length: float = 0.05
    """λ of the sparsity prior (the original code's sparsity_length; paper: 0.05)."""
    sparsity_points: int = 10000
    """K, uniform random points in the scene box per step for the sparsity prior (paper: 10000)."""
    distortion_weight: float | None = None
    """Weight of mip-NeRF 360's distortion loss (occupancy sampler; 0 = off), with distances
    measured in units of the scene box's longest side: it gathers each ray's weight into one
    place, against fog and floaters (mip-NeRF 360: 0.01). None: ``PHOTO_DISTORTION`` for real
    photos with the occupancy sampler, else 0."""
    amp: str = "auto"
    """Mixed precision of the MLP: "bf16", "off", or "auto" (bf16 on CPUs that support it)."""
    device: str = "auto"
    """"cpu", "cuda" or "auto" (CUDA when present)."""
    threads: int = 0
    """CPU threads for torch and numba (0 = all cores; -1 = choose 1 or all cores by measured
    speed, re-checked every 400 steps — for machines shared with other work)."""
    seed: int = 0
    """Random seed: weights, ray batches, samples (runs without a time budget repeat exactly)."""
    log_every: int = 25
    """Steps between rows of the training log."""
    val_every_s: float = 120.0
    """Seconds of training between validations (0 = only by steps / at the end); stretched so
    that validations take at most a tenth of the time (``training.VAL_SHARE``), and large
    views are validated on every k-th row (``training.VAL_PIXELS``)."""
    val_every_steps: int = 0
    """Steps between validations (0 = only by time / at the end)."""
    val_split: str = "test"
    """Split the validation views come from."""
    val_views: int = 5
    """Number of validation views, evenly spaced over the split (5 of 200: r_0, r_40, ...)."""
    preview_every_s: float = 150.0
    """Seconds of training between the coarse preview trees of a live view (``plenoctree view
    RUN`` shows the newest; the first after 30 s; 0 = none)."""
    ckpt_every_s: float = 60.0
    """Seconds between checkpoints (0 = only by steps / at the end)."""
    ckpt_every_steps: int = 0
    """Steps between checkpoints (0 = only by time / at the end)."""
    chunk: int = 8192
    """Rays per chunk when rendering images."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """The network."""


def _cpu() -> TrainConfig:
    # K = 4096 instead of the paper's 10000: the same expected prior at a third of the cost
    # (random points miss every cache level of the hash table)
    return TrainConfig(preset="cpu", sparsity_points=4096)


def _paper() -> TrainConfig:
    model = ModelConfig(encoding="posenc", pe_freqs=10, net_depth=8, net_width=256, skip_layer=4,
                        basis="sh", sh_degree=3, sigma_activation="relu", coarse=True)
    return TrainConfig(preset="paper", sampler="hierarchical", n_coarse=64, n_fine=128,
                       batch_rays=1024, max_steps=2_000_000, lr_init=5e-4, lr_final=5e-6,
                       adam_eps=1e-8, adam_beta2=0.999, random_background=False,
                       sparsity_weight=1e-3, sparsity_length=0.05, sparsity_points=10000,
                       amp="off", train_stop_thresh=0.0, val_views=1, ckpt_every_s=600.0,
                       val_every_s=3600.0, log_every=100, chunk=4096, model=model)


def _gpu() -> TrainConfig:
    # nerfacc's recipe for one GPU (2^18 samples a step, 20k steps, a 2^19-row hash table) on
    # the fixed-shape step; the network and schedule otherwise the cpu preset's
    return TrainConfig(preset="gpu", fixed_step=True, target_samples=1 << 18, max_rays=1 << 18,
                       max_steps=20000, sparsity_points=10000,
                       model=ModelConfig(grid_log2_table=19))


PRESETS = {"cpu": _cpu, "paper": _paper, "gpu": _gpu}

PHOTO_DISTORTION = 0.01
"""The distortion weight real photos train with by default (``distortion_weight=None``); with
the random backgrounds of ``photo_background`` it turned flower's NeRF-SH fog into surfaces:
17 samples per training ray instead of 51, fine-tuned tree 7.5 FPS instead of 3.4
(docs/capture.md)."""


def preset(name: str) -> TrainConfig:
    """A fresh :class:`TrainConfig` of preset ``name`` ("cpu", "gpu" or "paper")."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]()


@functools.lru_cache(maxsize=None)
def _class_bodies(filename: str) -> dict[str, list]:
    """The statements of every class in source file ``filename``, by qualified name (one parse
    per module: ``inspect.getsource`` re-parses the whole module for each class)."""
    out: dict[str, list] = {}

    def walk(nodes: list, prefix: str) -> None:
        for node in nodes:
            if isinstance(node, ast.ClassDef):
                out[prefix + node.name] = node.body
                walk(node.body, f"{prefix}{node.name}.")

    walk(ast.parse(Path(filename).read_text(encoding="utf-8")).body, "")
    return out


@functools.lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each field of dataclass ``cls``, by field name."""
    filename = inspect.getsourcefile(cls)
    body = _class_bodies(filename).get(cls.__qualname__) if filename else None
    if body is None:                      # a class defined inside a function
        body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    docs: dict[str, str] = {}
    for node, nxt in zip(body, body[1:]):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)):
            docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def config_to_dict(cfg: TrainConfig | ModelConfig) -> dict[str, Any]:
    """Plain JSON-able dict of a config (nested model included)."""
    d = dataclasses.asdict(cfg)
    if d.get("background") is not None:
        d["background"] = list(d["background"])
    return d


def _fill(cls: type, d: dict[str, Any], where: str) -> Any:
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected an object, got {type(d).__name__}")
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(names))
    if unknown:
        raise ConfigError(f"{where}: unknown option(s) {unknown}")
    kw = {}
    for k, v in d.items():
        if k == "model":
            v = _fill(ModelConfig, v, f"{where}.model")
        elif k == "background" and v is not None:
            v = tuple(float(c) for c in v)
        kw[k] = v
    return cls(**kw)


def config_from_dict(d: dict[str, Any], where: str = "config") -> TrainConfig:
    """Inverse of :func:`config_to_dict` (unknown keys raise :class:`ConfigError`)."""
    cfg = _fill(TrainConfig, d, where)
    validate(cfg)
    return cfg


def config_json(cfg: TrainConfig) -> str:
    """The config as an indented JSON string."""
    return json.dumps(config_to_dict(cfg), indent=2)


def validate(cfg: TrainConfig) -> TrainConfig:
    """Check option values (the ceilings of every count and time: :mod:`plenoctree._bounds`);
    raise :class:`ConfigError` naming the first bad one."""
    m = cfg.model

    def need(ok: bool, msg: str) -> None:
        if not ok:
            raise ConfigError(msg)

    need(m.encoding in ("hashgrid", "posenc"), f"encoding must be hashgrid or posenc, got {m.encoding!r}")
    need(m.basis in ("sh", "sg", "plain"), f"basis must be sh, sg or plain, got {m.basis!r}")
    need(isinstance(m.sh_degree, int) and 0 <= m.sh_degree <= 4,
         f"sh_degree must be in 0..4, got {m.sh_degree!r}")
    need(m.sg_lobes >= 1, f"sg_lobes must be >= 1, got {m.sg_lobes}")
    need(m.net_depth >= 1 and m.net_width >= 1, "net_depth and net_width must be >= 1")
    need(0 <= m.skip_layer < m.net_depth or m.skip_layer == 0,
         f"skip_layer must be in 0..net_depth-1, got {m.skip_layer}")
    need(m.pe_freqs >= 0 and m.view_freqs >= 0, "pe_freqs and view_freqs must be >= 0")
    need(m.grid_features >= 1, "grid_features must be >= 1")
    need(m.sigma_activation in ("relu", "trunc_exp"),
         f"sigma_activation must be relu or trunc_exp, got {m.sigma_activation!r}")
    need(cfg.sampler in ("occupancy", "hierarchical"),
         f"sampler must be occupancy or hierarchical, got {cfg.sampler!r}")
    need(not (m.coarse and cfg.sampler == "occupancy"),
         "a coarse network is only used by the hierarchical sampler (set coarse=False)")
    need(cfg.n_coarse >= 2 and cfg.n_fine >= 0, "n_coarse must be >= 2 and n_fine >= 0")
    need(cfg.render_step > 0 or cfg.render_step == -1,
         f"render_step must be > 0 or -1 (auto), got {cfg.render_step}")
    need(-1 <= cfg.far_levels <= 7, f"far_levels must be -1 (auto), 0 (none) or 1-7, got "
         f"{cfg.far_levels}")
    need(not cfg.fixed_step or cfg.sampler == "occupancy",
         "fixed_step needs the occupancy sampler (--sampler occupancy)")
    need(not cfg.cuda_graph or cfg.fixed_step,
         "cuda_graph needs fixed-shape steps (--fixed-step, or --preset gpu)")
    need(1 <= cfg.fixed_candidates <= 64,
         f"fixed_candidates must be in 1..64, got {cfg.fixed_candidates}")
    need(cfg.preview_every_s >= 0, f"preview_every_s must be >= 0, got {cfg.preview_every_s}")
    need(cfg.far_levels <= 0 or cfg.sampler == "occupancy",
         "far_levels needs the occupancy sampler (--sampler occupancy)")
    need(cfg.far_samples >= 2 and cfg.far_fine >= 0, "far_samples must be >= 2 and far_fine >= 0")
    need(cfg.occ_res >= 1 and cfg.occ_update_every >= 1, "occ_res and occ_update_every must be >= 1")
    need(0 < cfg.occ_threshold < 1 and 0 <= cfg.occ_decay <= 1,
         "occ_threshold must be in (0, 1) and occ_decay in [0, 1]")
    need(0 <= cfg.train_stop_thresh < 1 and 0 <= cfg.eval_stop_thresh < 1,
         "stop thresholds must be in [0, 1)")
    need(cfg.batch_rays >= 1 and cfg.target_samples >= 1 and cfg.max_rays >= 1,
         "batch_rays, target_samples and max_rays must be >= 1")
    need(cfg.max_steps >= 0, "max_steps must be >= 0")
    need(cfg.minutes >= 0, "minutes must be >= 0")
    need(cfg.lr_init > 0 and cfg.lr_final > 0, "learning rates must be > 0")
    need(cfg.sparsity_weight >= 0 and cfg.sparsity_length > 0 and cfg.sparsity_points >= 0,
         "sparsity_weight >= 0, sparsity_length > 0 and sparsity_points >= 0 are required")
    need(cfg.photo_background in ("auto", "random", "fixed"),
         f"photo_background must be auto, random or fixed, got {cfg.photo_background!r}")
    dist = cfg.distortion_weight
    need(dist is None or dist >= 0, f"distortion_weight must be >= 0, got {dist}")
    need(not dist or cfg.sampler == "occupancy",
         "distortion_weight needs the occupancy sampler (set it to 0 with sampler=hierarchical)")
    need(cfg.amp in ("auto", "bf16", "off"), f"amp must be auto, bf16 or off, got {cfg.amp!r}")
    need(cfg.device == "auto" or cfg.device == "cpu" or str(cfg.device).startswith("cuda"),
         f"device must be auto, cpu, cuda or cuda:N, got {cfg.device!r}")
    need(isinstance(cfg.downscale, int) and cfg.downscale >= 1, "downscale must be an integer >= 1")
    need(cfg.threads >= -1, f"threads must be >= -1, got {cfg.threads}")
    need(cfg.val_views >= 0 and cfg.chunk >= 1 and cfg.log_every >= 1,
         "val_views >= 0, chunk >= 1 and log_every >= 1 are required")
    need(cfg.background is None or len(cfg.background) == 3,
         "background must have 3 components")
    from ..datasets.dataset import FORMATS

    need(cfg.format in (None, *FORMATS),
         f"format must be one of {', '.join(FORMATS)}, got {cfg.format!r}")
    return check_bounds(cfg)
