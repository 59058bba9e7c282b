"""A training step of fixed shape (issue 47): every tensor of a step has a size known before
the step runs, and nothing is read back to the host inside it.

The occupancy sampler of the CPU preset (:func:`.renderer.render_rays_occupancy`) marches rays
in waves until their transmittance falls below ``train_stop_thresh``: each wave reads back how
many rays still march and how many samples the march made (host round trips on a GPU, and an
op count that grows with the batch). Here instead, as in nerfacc and instant-ngp:

* the rays of the step are marched once through the occupancy grid into buffers of a fixed
  size, ``k × S`` **candidate** slots (:func:`march_fixed`: one counting pass, a prefix sum,
  one filling pass; a ray's samples are written while they fit, the count stays on the
  device; ``k = cfg.fixed_candidates``, :func:`candidate_factor`);
* early ray termination without a read-back (:func:`terminate_fixed`): the density of every
  candidate without gradients, each candidate's transmittance from a per-ray exclusive prefix
  sum of ``σ δ`` over the packed buffer, the candidates before ``T < train_stop_thresh`` kept
  (a prefix of each ray, the waves path's samples) and compacted into the **sample budget**
  ``S`` by a prefix sum over the kept flags (a scatter, the rest into a spare slot);
* the network runs with gradients on all ``S`` slots; slots no ray filled hold the box's
  centre and belong to a dummy ray ``R`` whose outputs are dropped (so they get no gradient);
* eq. (1)–(2) over each ray's kept sequence, the loss over the rays whose kept samples all fit
  in ``S`` and whose candidates all fit in ``k S`` (``complete``, a mask — never a selection);
* how many rays the next steps take is adapted from the samples per ray, kept and marched,
  read back every ``occ_update_every`` steps (:class:`FixedBatch`); the ray count moves in
  multiples of :data:`RAY_QUANTUM` so that a captured graph (CUDA graphs, ``torch.compile``)
  sees few shapes.

``k = 1`` (or ``train_stop_thresh = 0``) is the step without early termination: the march
goes straight into ``S`` and every marched sample is trained (the samples behind a surface get
weights ~0, the same image, but fill the budget). Lego 400², 2^17 samples, 300 steps
(``benchmarks/fixed_vs_waves.py``, seeds 0–2): ``k = 4`` 0.58 dB under the waves on average
(22.54 against 23.12 dB), ~8,500–9,000 rays a step against the waves' ~8,100 (16 kept of
~24.5 marched samples a ray); ``k = 8`` trains the same as 4 (docs/performance.md).

Backends of op ``march_fixed`` (:mod:`plenoctree.backend`): numba on the CPU, Triton on CUDA
(the two passes of :mod:`._march_triton` into the fixed buffers), and the torch twin
:func:`_march_fixed_torch` (the packed march of :func:`.sampling._march_torch`, cut at ``S``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .sampling import MarchGrid, MarchRays, PackedSamples, _march_torch

__all__ = ["FixedSamples", "march_fixed", "fixed_buffers", "finish_fixed", "candidate_factor",
           "terminate_fixed", "kept_figures", "FixedBatch", "render_fixed", "fixed_loss",
           "RAY_QUANTUM"]

#: The adaptive ray count of a fixed-shape step is a multiple of this.
RAY_QUANTUM = 256


@dataclass
class FixedSamples:
    """The samples of ``R`` rays in a budget of ``S`` slots, ray after ray.

    Attributes:
        ray_idx: int64 ``[S]`` ray of each slot (``R``, the dummy ray, for unfilled slots).
        t: float32 ``[S]`` distance along the ray (0 in unfilled slots).
        points: float32 ``[S, 3]`` world positions (the box's centre in unfilled slots).
        offsets: int64 ``[R + 2]``: ray ``r`` owns slots ``offsets[r]:offsets[r + 1]``, the
            dummy ray the rest (``offsets[R + 1] = S``).
        complete: bool ``[R]``: every sample of the ray fits in the budget.
        n_valid: int64 ``[]`` filled slots; total: int64 ``[]`` samples the march made for
            all rays (also those past the budget; after :func:`terminate_fixed` still the
            candidates'). Device tensors, not read back.
    """

    ray_idx: torch.Tensor
    t: torch.Tensor
    points: torch.Tensor
    offsets: torch.Tensor
    complete: torch.Tensor
    n_valid: torch.Tensor
    total: torch.Tensor


def fixed_buffers(n_rays: int, capacity: int, bbox: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(ray_idx [S], t [S], points [S, 3])`` of unfilled slots (dummy ray ``n_rays``, t 0,
    the centre of ``bbox [2, 3]``) for a march to fill."""
    dev = bbox.device
    ray_idx = torch.full((capacity,), n_rays, dtype=torch.int64, device=dev)
    ts = torch.zeros(capacity, dtype=torch.float32, device=dev)
    pts = (0.5 * (bbox[0] + bbox[1])).float().expand(capacity, 3).contiguous()
    return ray_idx, ts, pts


def finish_fixed(counts: torch.Tensor, capacity: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(offsets [R + 1] cut at the budget, full offsets [R + 1])`` of per-ray sample
    ``counts [R]`` (int64), on the device."""
    full = torch.zeros(counts.shape[0] + 1, dtype=torch.int64, device=counts.device)
    torch.cumsum(counts, 0, out=full[1:])
    return full.clamp(max=capacity), full


def _samples(ray_idx: torch.Tensor, ts: torch.Tensor, pts: torch.Tensor, cut: torch.Tensor,
             full: torch.Tensor, capacity: int) -> FixedSamples:
    end = torch.full((1,), capacity, dtype=torch.int64, device=cut.device)
    return FixedSamples(ray_idx, ts, pts, torch.cat([cut, end]), full[1:] <= capacity,
                        cut[-1], full[-1])


def _march_fixed_numba(rays: MarchRays, grid: MarchGrid, capacity: int) -> FixedSamples:
    """The numba marching kernels (CPU tensors) into the budget's buffers."""
    from . import _march_numba as K
    from .sampling import numba_march_args

    n = rays.origins.shape[0]
    args, (counts, k_next, done) = numba_march_args(rays, grid)
    K.march_count(*args, 0, counts, k_next, done)
    cut, full = finish_fixed(torch.from_numpy(counts), capacity)
    ray_idx, ts, pts = fixed_buffers(n, capacity, grid.bbox)
    K.march_fill(*args, cut.numpy(), ray_idx.numpy(), ts.numpy(), pts.numpy())
    return _samples(ray_idx, ts, pts, cut, full, capacity)


def _march_fixed_torch(rays: MarchRays, grid: MarchGrid, capacity: int) -> FixedSamples:
    """The twin: every sample by :func:`.sampling._march_torch` (a packed march with host
    round trips), the first ``capacity`` of them kept."""
    s: PackedSamples = _march_torch(rays, grid, 0)
    n = rays.origins.shape[0]
    cut, full = finish_fixed(s.counts, capacity)
    ray_idx, ts, pts = fixed_buffers(n, capacity, grid.bbox)
    m = min(len(s), capacity)
    ray_idx[:m], ts[:m], pts[:m] = s.ray_idx[:m], s.t[:m], s.points[:m]
    return _samples(ray_idx, ts, pts, cut, full, capacity)


def march_fixed(rays: MarchRays, grid: MarchGrid, capacity: int,
                backend: str = "auto") -> FixedSamples:
    """March every ray of ``rays`` through ``grid`` (the samples of
    :func:`.sampling.march_rays` without a per-ray limit) into a budget of ``capacity``
    slots, ray after ray, without reading anything back (see the module doc).

    Args:
        rays: the rays (``k_start`` None or zeros). grid: spacing and occupancy.
        capacity: the sample budget ``S`` (>= 1).
        backend: "auto" (numba on CPU, Triton on CUDA), "numba", "triton" or "torch".

    Returns:
        :class:`FixedSamples`.
    """
    from .. import backend as _backend

    rays = rays.contiguous()
    name = _backend.resolve("march_fixed", backend, rays.origins.device)
    return _backend.implementation("march_fixed", name)(rays, grid, int(capacity))


def candidate_factor(cfg, stop_thresh: float | None = None) -> int:
    """``k``, the candidate slots marched per slot of the budget: ``cfg.fixed_candidates``,
    or 1 (no early termination, no density pass) when the threshold (``stop_thresh``; None:
    ``cfg.train_stop_thresh``) is 0."""
    thresh = cfg.train_stop_thresh if stop_thresh is None else stop_thresh
    return int(cfg.fixed_candidates) if thresh > 0 else 1


def terminate_fixed(cand: FixedSamples, sigma: torch.Tensor, grid: MarchGrid,
                    stop_thresh: float, capacity: int, backend: str = "auto") -> FixedSamples:
    """Early ray termination of marched candidates, compacted into a budget, in fixed shapes.

    With ``τ_i = σ_i δ`` (``δ = grid.step``) and the optical depth before candidate ``i`` of
    ray ``r``, ``D_i = Σ_{j<i, j in r} τ_j`` (a batch-wide exclusive prefix sum in float64
    minus its value at the ray's first slot), candidate ``i`` is kept when
    ``T_i = exp(-D_i) >= stop_thresh``: a prefix of each ray, ending with the sample where
    ``T`` falls below the threshold — the samples the waves path trains
    (:func:`.renderer._march_waves`). Kept candidate ``i`` goes to slot
    ``Σ_{j<=i} keep_j - 1`` when that is below ``capacity``; the others to a spare slot that
    is cut off.

    Args:
        cand: :class:`FixedSamples` of ``R`` rays in ``M = k S`` candidate slots.
        sigma: ``[M]`` density of every candidate (1/world-length; any float dtype, no grad).
        grid: the march's grid (``step``, ``bbox``). stop_thresh: in ``(0, 1)``.
        capacity: the budget ``S``.

        backend: op ``terminate``: "auto" (Triton on CUDA: each ray walks its candidates,
            :mod:`._terminate_triton`), "triton" or "torch" (this docstring's prefix sums).

    Returns:
        :class:`FixedSamples` in ``S`` slots; ``complete``: the ray's candidates fit in
        ``M`` and its kept samples in ``S``; ``total``: the candidates' (``cand.total``).
    """
    from .. import backend as _backend

    name = _backend.resolve("terminate", backend, cand.t.device)
    return _backend.implementation("terminate", name)(cand, sigma, grid, stop_thresh,
                                                      int(capacity))


def _terminate_torch(cand: FixedSamples, sigma: torch.Tensor, grid: MarchGrid,
                     stop_thresh: float, capacity: int) -> FixedSamples:
    """Op ``terminate``'s twin (see :func:`terminate_fixed`): batch-wide prefix sums."""
    n, m = cand.complete.shape[0], cand.t.shape[0]
    tau = sigma.detach().double() * float(grid.step)
    excl = torch.cumsum(tau, 0) - tau
    first = cand.offsets[:-1].clamp(max=m - 1)                      # [R + 1], the dummy's too
    before = excl - excl[first][cand.ray_idx]
    # the dummy ray's slots may be kept too: they land after every real one and hold what
    # an unfilled slot holds (ray R, t 0, the box's centre)
    keep = before <= -math.log(stop_thresh)
    ck = torch.zeros(m + 1, dtype=torch.int64, device=tau.device)   # kept in slots < i
    torch.cumsum(keep, 0, out=ck[1:])
    dest = torch.where(keep, ck[1:] - 1, capacity).clamp(max=capacity)
    ray_idx, ts, pts = fixed_buffers(n, capacity + 1, grid.bbox)
    ray_idx.scatter_(0, dest, cand.ray_idx)
    ts.scatter_(0, dest, cand.t)
    pts.index_copy_(0, dest, cand.points)
    full = ck[cand.offsets[:n + 1]]                                 # kept, by ray: [R + 1]
    cut = full.clamp(max=capacity)
    end = torch.full((1,), capacity, dtype=torch.int64, device=tau.device)
    return FixedSamples(ray_idx[:capacity], ts[:capacity], pts[:capacity],
                        torch.cat([cut, end]), cand.complete & (full[1:] <= capacity),
                        cut[-1], cand.total)


def kept_figures(s: FixedSamples) -> torch.Tensor:
    """float64 ``[2]`` on the device: the complete rays of ``s`` and their samples (the
    samples a ray trains, measured where it is known whole)."""
    n = s.complete.shape[0]
    ok = s.complete
    return torch.stack([ok.sum(), ((s.offsets[1:n + 1] - s.offsets[:n]) * ok).sum()]).double()


class FixedBatch:
    """The ray count of fixed-shape steps: the most rays whose samples fit on average, both
    the kept ones in the budget ``S`` and the marched ones in the ``k S`` candidate slots,
    ``min(S / kept per ray, k S / marched per ray)``, rounded down to a multiple of
    :data:`RAY_QUANTUM` within ``[RAY_QUANTUM, max_rays]``.

    Each step adds its marched samples (all of them, also past the buffer) and
    :func:`kept_figures` to device counters (:meth:`add_device`, no read-back) and its rays
    to a host count (:meth:`count`); :meth:`adapt` reads
    them (one host round trip) and updates the trainer's state (``spr``: running mean of the
    kept samples per ray, ``spr_marched``: of the marched ones, ``n_rays``) as the waves path
    does every step, so a checkpoint keeps it: the waves' mean takes 0.1 of each step's figure,
    so a window of ``m`` steps enters with weight ``1 - 0.9^m``."""

    def __init__(self, capacity: int, max_rays: int, device: torch.device,
                 candidates: int = 1):
        self.capacity, self.max_rays = int(capacity), int(max_rays)
        self.candidates = int(candidates)
        # marched samples; complete rays, their kept samples (the rays: a host count)
        self.sums = torch.zeros(3, dtype=torch.float64, device=device)
        self.n_rays = 0
        self.steps = 0                  # in the window (a host count)

    def rays(self, n_rays: float) -> int:
        """The ray count of a step for the state's ``n_rays``."""
        top = max(RAY_QUANTUM, self.max_rays // RAY_QUANTUM * RAY_QUANTUM)
        return max(RAY_QUANTUM, min(int(n_rays) // RAY_QUANTUM * RAY_QUANTUM, top))

    def add_device(self, total: torch.Tensor, kept: torch.Tensor) -> None:
        """Add a step's marched samples ``total`` (device int64, also those past the buffer)
        and :func:`kept_figures` ``kept`` to the device counters (one add, no read-back; also
        inside a captured step, :mod:`.graph`)."""
        self.sums += torch.cat([total.reshape(1), kept])

    def count(self, n_rays: int) -> None:
        """Count a step of ``n_rays`` rays on the host (outside a captured step)."""
        self.n_rays += n_rays
        self.steps += 1

    def adapt(self, state) -> None:
        """Read the counters (one round trip) and set ``state.spr``, ``state.spr_marched``
        and ``state.n_rays`` (``state``: the trainer's :class:`~.trainer.TrainerState`)."""
        marched, done, kept = self.sums.tolist()
        rays, self.n_rays = float(self.n_rays), 0
        self.sums.zero_()
        w, self.steps = 0.9 ** max(self.steps, 1), 0
        mean = (lambda old, new: new if old == 0 else w * old + (1.0 - w) * new)
        if rays > 0:
            state.spr_marched = mean(state.spr_marched, max(marched, 1.0) / rays)
        if done > 0:
            state.spr = mean(state.spr, max(kept, 1.0) / done)
        fits = []                       # the rays whose samples fit, on average
        if state.spr_marched > 0:
            fits.append(self.candidates * self.capacity / state.spr_marched)
        if state.spr > 0:
            fits.append(self.capacity / state.spr)
        if fits:
            state.n_rays = float(min(self.max_rays, max(RAY_QUANTUM, min(fits))))


def _sample_fixed(model, rays, cfg, mode, capacity: int, bounds=None) -> FixedSamples:
    """The samples :func:`render_fixed` trains: the march into ``k S`` candidates, then
    without gradients their density and :func:`terminate_fixed` (``k > 1``), or the march
    straight into ``S`` (``k = 1``)."""
    from .far import resolve_render_step
    from .renderer import autocast, ray_bounds

    n, dev = len(rays), rays.origins.device
    t_min, t_max = bounds if bounds is not None else ray_bounds(
        rays.origins, rays.dirs, model.scene_bbox, rays.near, rays.far)
    jitter = torch.rand(n, generator=mode.generator, device=dev)
    occ = model.occupancy
    grid = MarchGrid(resolve_render_step(cfg), occ.mask, occ.bbox)
    k = candidate_factor(cfg, mode.stop_thresh)
    s = march_fixed(MarchRays(rays.origins, rays.dirs, t_min, t_max, jitter), grid,
                    k * capacity)
    if k == 1:
        return s
    thresh = cfg.train_stop_thresh if mode.stop_thresh is None else mode.stop_thresh
    with torch.no_grad(), autocast(dev, mode.amp):
        sigma = model.fine.density(s.points)
    return terminate_fixed(s, sigma, grid, thresh, capacity)


def render_fixed(model, rays, cfg, mode, capacity: int, bounds=None) -> dict:
    """Training render of ``R`` rays in a fixed sample budget (the fixed-shape counterpart of
    :func:`.renderer.render_rays_occupancy` with ``mode.train``).

    Args:
        model: a :class:`~.model.NeRFModel` with an occupancy grid. rays: a
            :class:`~.renderer.RayBatch`. cfg: its :class:`~.config.TrainConfig`
            (``render_step``, ``fixed_candidates``, ``train_stop_thresh``, far-field
            samples). mode: a training :class:`~.renderer.RenderMode` (``generator``,
            ``amp``, ``distortion``; ``stop_thresh``: None for the config's).
        capacity: the sample budget ``S``.
        bounds: ``(t_min, t_max)`` float32 ``[R]`` of the rays in ``model.scene_bbox`` and
            ``[rays.near, rays.far]`` when known (op ``ray_batch`` makes them with the rays);
            None: :func:`.renderer.ray_bounds`.

    Returns:
        ``rgb [R, 3]`` (over ``rays``' background), ``acc [R]``, ``complete [R]`` bool,
        ``n_samples`` (int, = ``S``: every slot is evaluated with gradients; the density pass
        evaluates ``k S`` more without), ``total`` (int64 ``[]``, the samples the march made,
        also past the buffer), ``kept`` (:func:`kept_figures`) and with ``mode.distortion``
        ``distortion [R]`` (and ``far_distortion [R]`` with a far field).
    """
    from .composite import composite_rays
    from .far import composite_far, far_distortion, render_far, resolve_render_step
    from .renderer import autocast

    n = len(rays)
    dev = rays.origins.device
    step = resolve_render_step(cfg)
    s = _sample_fixed(model, rays, cfg, mode, capacity, bounds)
    d = rays.dirs.index_select(0, s.ray_idx.clamp(max=n - 1))
    with autocast(dev, mode.amp):       # op "mlp": on CUDA one fused launch each way
        sigma, color = model.fine.radiance(s.points, d)
    # one fused launch each way (.composite); the dummy ray's slots lie past offsets[n]
    r = composite_rays(sigma, color, s.t, s.offsets[:n + 1], step, mode.distortion)
    out = {"complete": s.complete, "n_samples": int(capacity), "total": s.total,
           "kept": kept_figures(s)}
    if mode.distortion:
        out["distortion"] = r.pop("distortion")
    if model.far is not None:           # the world beyond the box (nerf.far): fixed samples
        with autocast(dev, mode.amp):
            f = render_far(model.far, rays.origins, rays.dirs, rays.near, model.scene_bbox,
                           cfg.far_samples, cfg.far_fine, True, mode.generator)
        r = {**r, **composite_far(f, r["rgb"], r["acc"], r["dsum"])}
        out["n_samples"] += n * (cfg.far_samples + cfg.far_fine)
        if mode.distortion:
            out["far_distortion"] = far_distortion(r["weights"], f["edges"])
    out.update(rgb=r["rgb"] + (1.0 - r["acc"])[:, None] * rays.bg(), acc=r["acc"])
    return out


def fixed_loss(r: dict, target: torch.Tensor, dist_weight: float, extent: float
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(loss, mse)`` of :func:`render_fixed`'s output ``r`` against ``target [R, 3]``: the
    mean squared error over the complete rays (a mask; 0 when none is complete) plus
    ``dist_weight / extent`` times their mean distortion and ``dist_weight`` times their far
    field's (:func:`~.far.far_distortion`), as the waves path's loss."""
    mask = r["complete"].to(target.dtype)
    used = mask.sum().clamp(min=1.0)
    mse = (((r["rgb"] - target) ** 2).mean(-1) * mask).sum() / used
    loss = mse
    if "distortion" in r and dist_weight > 0:
        loss = loss + dist_weight / extent * (r["distortion"] * mask).sum() / used
    if "far_distortion" in r and dist_weight > 0:     # normalised distances already
        loss = loss + dist_weight * (r["far_distortion"] * mask).sum() / used
    return loss, mse
