"""One training step, written to compile: draw the inputs, render, loss, backward, update.

Everything random is drawn before `render_and_loss` (`draw_step_inputs`), which takes
tensors only and keeps every shape fixed, so `train.compile` compiles it whole; the step
has no host synchronisation (its metrics stay on the device until a log step).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable

import torch
from torch import Tensor

from neus_l0.bounds.error_map import draw, refresh_interval, refresh_table, update_errors
from neus_l0.bounds.occupancy import OccupancyGrid
from neus_l0.bounds.pixel_pool import PixelPool
from neus_l0.bounds.silhouettes import Silhouettes, in_silhouettes
from neus_l0.bounds.spans import RayBounds, join_bounds
from neus_l0.config.schema import Config
from neus_l0.data.rays import random_picks, random_rays, rays_at
from neus_l0.data.scene import Scene
from neus_l0.fields.linear import clear_weight_cache
from neus_l0.fields.model import NeuSModel
from neus_l0.render.volume import RenderNoise, RenderOutput, draw_noise, render_rays
from neus_l0.sampling.upsample import Sampler, build_sampler
from neus_l0.train.budget import ScheduleWarp
from neus_l0.train.losses import (
    LOSS_NAMES,
    RayDraw,
    curvature,
    eikonal_indices,
    free_space,
    missed_rays,
    neus_loss,
    ray_errors,
)
from neus_l0.train.photometric import PhotoContext, PhotoRays, photometric_term
from neus_l0.train.schedule import cos_anneal_ratio, lr_factor

#: A step's metrics, in the order of `render_and_loss`'s metrics tensor: the losses, then
#: NeuS's sharpness and the samples the step rendered. Every other list of metric names
#: (the log line, TensorBoard) is built from this one.
METRIC_NAMES = (*LOSS_NAMES, "inv_s", "samples")
#: Silhouette filling with `train.fill_silhouettes` tests the samples of at most this many
#: missed rays a step (`silhouette_samples`).
FILL_RAYS = 16


def make_optimizer(model: NeuSModel, cfg: Config) -> torch.optim.Adam:
    """Adam over every network's parameters at the peak learning rate, fused.

    The fused kernel updates every tensor in a few ops (the per-parameter loop dispatched
    155 ops a step for demo's 17 tensors; `tools/count_ops.py`), and with ``train.amp =
    fp16`` on CUDA it takes the gradient scaler's inf check on the device, so
    `GradScaler.step` needs no host synchronisation.
    """
    return torch.optim.Adam(model.parameters(), lr=cfg.train.lr, fused=True)


def amp_enabled(cfg: Config, device: torch.device | str) -> bool:
    """Whether mixed precision applies: `train.amp` is not ``off`` and the device is CUDA."""
    return cfg.train.amp != "off" and torch.device(device).type == "cuda"


def autocast(cfg: Config, device: torch.device | str) -> contextlib.AbstractContextManager:
    """`torch.autocast` for the networks per `train.amp` (a no-op on the CPU or when off)."""
    if not amp_enabled(cfg, device):
        return contextlib.nullcontext()
    dtype = torch.bfloat16 if cfg.train.amp == "bf16" else torch.float16
    return torch.autocast(device_type="cuda", dtype=dtype)


def make_scaler(cfg: Config, device: torch.device | str) -> torch.amp.GradScaler:
    """NeuS's loss scaler for ``train.amp = fp16`` on CUDA (disabled otherwise)."""
    enabled = amp_enabled(cfg, device) and cfg.train.amp == "fp16"
    return torch.amp.GradScaler("cuda", enabled=enabled)


def make_occupancy(cfg: Config, device: torch.device | str) -> OccupancyGrid | None:
    """The occupancy grid of `render.occupancy` (None when it is off)."""
    if not cfg.render.occupancy.enabled:
        return None
    return OccupancyGrid(cfg.render.occupancy, device)


def update_occupancy(grid: OccupancyGrid | None, model: NeuSModel, cfg: Config,
                     iteration: int) -> None:
    """Re-test the grid every `render.occupancy.update_every` iterations from
    `render.occupancy.start` on (before it every cell stays occupied)."""
    c = cfg.render.occupancy
    if grid is not None and iteration >= c.start and (iteration - c.start) % c.update_every == 0:
        grid.update(model.sdf.sdf, model.variance.inv_s())


def schedule_length(cfg: Config) -> int:
    """The iterations the schedule is laid over: ``train.lr_decay_iters``, or ``train.iters``
    when it is 0 (a budget shorter than its config stops part-way down the config's length:
    `neus_l0.train.budget.planned_config`)."""
    return cfg.train.lr_decay_iters or cfg.train.iters


def set_learning_rate(optimizer: torch.optim.Optimizer, cfg: Config,
                      iteration: float) -> float:
    """Apply NeuS's schedule for `iteration` and return the learning rate."""
    t = cfg.train
    lr = t.lr * lr_factor(iteration, t.warm_up, schedule_length(cfg), t.lr_alpha)
    for group in optimizer.param_groups:
        group["lr"] = lr
    return lr


def next_batch_size(rays: int, samples: float, cfg: Config) -> int:
    """The ray count of the next iterations under `train.sample_budget`.

    Args:
        rays: the current ray count; samples: the foreground samples one step at that count
            evaluated.

    Returns:
        ``round(rays * sample_budget / samples)`` within [batch_size / 8, 8 * batch_size]
        (at least 1); `rays` unchanged when the budget is off.
    """
    t = cfg.train
    if t.sample_budget <= 0:
        return rays
    lo, hi = max(1, t.batch_size // 8), 8 * t.batch_size
    if not math.isfinite(samples) or samples <= 0:
        return hi  # no ray got samples: draw as many as allowed
    return int(min(max(round(rays * t.sample_budget / samples), lo), hi))


def resumed_batch_size(rays: int, cfg: Config) -> int:
    """The ray count a resumed run continues with: the checkpoint's `rays` within the
    bounds of `next_batch_size` under the config now in force (``train.batch_size`` itself
    when the budget is off), so that ``--change-config train.batch_size=N`` takes effect and
    a damaged count cannot exhaust memory; the config's batch size when `rays` is 0."""
    t = cfg.train
    if t.sample_budget <= 0 or rays <= 0:
        return t.batch_size
    return int(min(max(rays, max(1, t.batch_size // 8)), 8 * t.batch_size))


@dataclasses.dataclass
class StepInputs:
    """What one step draws and reads before rendering: no generator, no Python number that
    changes between steps, so a compiled `render_and_loss` sees the same kinds of inputs
    every step.

    Attributes:
        origins, dirs: (B, 3) the rays; rgb: (B, 3) their pixels; mask: (B, 1) binary (ones
            when masks are unused).
        noise: the jitter's uniforms (None: no jitter).
        eikonal_idx: (k,) the Eikonal subset's samples (None: all samples).
        anneal: () NeuS's cos-anneal ratio at this iteration; the number 1.0 when
            `train.anneal_end` is 0 (no annealing: constant over the run, so a compiled
            step sees the same input every step, and the slope takes fewer ops).
        mask_scale: the pixel pool's fraction (1: rays drawn from every pixel).
        span: (B, 4) the rays' bounds under the run's static bounds, looked up in the pixel
            pool (`PixelPool.spans`), or None (the step computes them).
        pick: (B,) the rays' pool indices when the pool's error map drew them (None: off).
        ray_weight: (B,) their importance weights 1 / (P p) (None: uniform draws).
        foreground: the pool's share of foreground pixels (with `ray_weight`).
        curvature_idx: (k,) the samples of the curvature term (None: the term is off).
        photo: the run's `PhotoContext` (None: the photometric term is off); view: (B,) the
            rays' views and xy: (B, 2) their pixels (with `photo`).
        photo_wide: () 1 once the term's wider sources count (``train.photo.wide_after``),
            else 0; None when the context has no wider sources.
        empty: (B,) 1 on the rays whose mask is exactly 0 (None: carving is off,
            `train.carve_weight`).
        full: (B,) 1 on the rays whose mask is over 0.5 (None: filling is off,
            `train.fill_weight`).
        silhouettes: the views' masks for filling's point test (None: filling counts every
            sample in the sphere; `train.fill_silhouettes`).
    """

    origins: Tensor
    dirs: Tensor
    rgb: Tensor
    mask: Tensor
    noise: RenderNoise | None
    eikonal_idx: Tensor | None
    anneal: Tensor | float
    mask_scale: float
    span: Tensor | None = None
    pick: Tensor | None = None
    ray_weight: Tensor | None = None
    foreground: float = 1.0
    curvature_idx: Tensor | None = None
    photo: PhotoContext | None = None
    view: Tensor | None = None
    xy: Tensor | None = None
    empty: Tensor | None = None
    full: Tensor | None = None
    silhouettes: Silhouettes | None = None
    photo_wide: Tensor | None = None


def _draw_pool(pool: PixelPool, n_rays: int, generator: torch.Generator,
               device: torch.device) -> tuple[Tensor, Tensor | None]:
    """(n_rays,) pool indices, uniform or from the pool's error map, and their importance
    weights (None: uniform)."""
    if pool.error_map is None:
        return random_picks(pool.pixels.shape[0], n_rays, generator, device), None
    return draw(pool.error_map, n_rays, generator)


def draw_step_inputs(scene: Scene, cfg: Config, iteration: float, n_rays: int,
                     generator: torch.Generator, pool: PixelPool | None,
                     photo: PhotoContext | None = None,
                     silhouettes: Silhouettes | None = None) -> StepInputs:
    """Draw one step's rays and random numbers (`StepInputs`), in a fixed order (`photo`:
    the photometric term's context, passed on with the rays' views and pixels;
    `silhouettes`: filling's point test, passed on when filling is on)."""
    span = pick = weight = None
    if pool is None:
        batch, mask_scale = random_rays(scene, n_rays, generator), 1.0
    else:
        pick, weight = _draw_pool(pool, n_rays, generator, scene.device)
        batch, mask_scale = rays_at(scene, pool.pixels[pick]), pool.fraction
        span = pool.spans[pick] if pool.spans is not None else None
    r = cfg.render
    noise = draw_noise(r, n_rays, generator, scene.device) if r.perturb else None
    eik_idx = curv_idx = None
    n_samples = n_rays * (r.n_samples + (r.n_importance if r.up_sample_steps else 0))
    if cfg.train.eikonal_fraction < 1.0:
        eik_idx = eikonal_indices(n_samples, cfg.train.eikonal_fraction, generator,
                                  scene.device)
    if cfg.train.curvature_weight > 0:
        curv_idx = eikonal_indices(n_samples, cfg.train.curvature_fraction, generator,
                                   scene.device)
    raw = batch["mask"]
    mask = (raw > 0.5).float() if cfg.train.mask_weight > 0 else torch.ones_like(raw)
    empty = (raw[:, 0] == 0).float() if cfg.train.carve_weight > 0 else None
    full = (raw[:, 0] > 0.5).float() if cfg.train.fill_weight > 0 else None
    anneal = (1.0 if cfg.train.anneal_end <= 0 else
              torch.tensor(cos_anneal_ratio(iteration, cfg.train.anneal_end),
                           device=scene.device))
    emap = pool.error_map if pool is not None else None
    on = photo is not None
    return StepInputs(batch["origins"], batch["dirs"], batch["rgb"], mask, noise, eik_idx,
                      anneal, mask_scale, span, pick if emap is not None else None, weight,
                      emap.foreground if emap is not None else 1.0, curv_idx, photo,
                      batch["view"] if on else None, batch["xy"] if on else None, empty, full,
                      silhouettes if full is not None else None,
                      photo_widened(cfg, iteration, scene.device) if on and photo.near else None)


def photo_widened(cfg: Config, at: float, device: torch.device | str) -> Tensor:
    """() 1.0 from schedule iteration ``train.photo.wide_after * L`` on (L the
    `schedule_length`), else 0.0: whether the photometric term's wider sources count."""
    return torch.tensor(float(at >= cfg.train.photo.wide_after * schedule_length(cfg)),
                        device=device)


def curvature_at_samples(model: NeuSModel, origins: Tensor, dirs: Tensor, out: RenderOutput,
                         idx: Tensor) -> Tensor:
    """The `curvature` term at the step's samples `idx` (flat indices into (B, N)): the SDF's
    Laplacian (`SDFNetwork.laplacian`) at the section midpoints, over the samples the
    Eikonal term counts.

    Args:
        origins, dirs: (B, 3); out: the step's render; idx: (k,) indices < B * N.

    Returns:
        () loss.
    """
    n = out.t_mid.shape[1]
    ray = idx // n
    pts = origins[ray] + dirs[ray] * out.t_mid.reshape(-1)[idx, None].detach()  # (k, 3)
    lap = model.sdf.laplacian(pts).float()
    return curvature(lap, out.eikonal_mask.reshape(-1)[idx])


def silhouette_samples(inputs: StepInputs, out: RenderOutput, span: float = 0.0,
                       middle: bool = False) -> Tensor:
    """(B, N) 1 on the samples (section midpoints) inside every view's mask
    (`neus_l0.bounds.silhouettes.in_silhouettes`) of at most `FILL_RAYS` rays whose mask is 1
    and that render below 0.5 (the rays filling pushes), 0 elsewhere; needs
    `inputs.silhouettes` and `inputs.full`. Testing every sample of the batch would cost
    ~15 % of a step; the rays it pushes are a few of each batch.

    `span` > 0 keeps only the rays whose inside samples lie within `span` of each other
    along the ray (normalised units): a ray that sees a thin part against the background
    crosses the silhouettes' intersection in a short segment, one into a pit or along a
    wall in a long one (`train.fill_span`). `middle` keeps, per ray, only the inside sample
    nearest the middle of the inside ones (`train.fill_middle`)."""
    t = out.t_mid.detach()
    missed = inputs.full * (out.weight_sum.detach()[:, 0] < 0.5).to(t.dtype)  # (B,)
    idx = torch.topk(missed, min(FILL_RAYS, t.shape[0])).indices  # (k,)
    pts = inputs.origins[idx, None, :] + inputs.dirs[idx, None, :] * t[idx, :, None]
    inside = in_silhouettes(pts.reshape(-1, 3), inputs.silhouettes).reshape(idx.shape[0], -1)
    keep = missed[idx]  # (k,) a batch with fewer missed rays than k
    ti = t[idx]
    far = torch.full_like(ti, float("inf"))
    lo = torch.where(inside, ti, far).amin(dim=1)  # (k,)
    hi = torch.where(inside, ti, -far).amax(dim=1)
    if span > 0:
        keep = keep * ((hi - lo) <= span).to(t.dtype)
    if middle:
        mid = torch.where(hi >= lo, 0.5 * (lo + hi), torch.zeros_like(lo))  # no inf - inf
        at = torch.where(inside, (ti - mid[:, None]).abs(), far).argmin(dim=1)
        one = torch.zeros_like(inside).scatter(1, at[:, None], True)
        inside = one & inside.any(dim=1, keepdim=True)
    return torch.zeros_like(t).index_copy(0, idx, inside.to(t.dtype) * keep[:, None])


def photo_at_rays(model: NeuSModel, inputs: StepInputs, out: RenderOutput, cfg: Config
                  ) -> Tensor:
    """The photometric term (`neus_l0.train.photometric`) on the step's rays that lie in
    the mask and render opaque (> 0.5), weighted by the rays' importance weights with
    ``train.error_map.weigh_all``; the SDF pass does not count for the hash grid's level
    schedule (it is the step's second).

    Returns:
        () the mean cost over the rays it counted.
    """
    use = (inputs.mask[:, 0] > 0.5) & (out.weight_sum[:, 0].detach() > 0.5) & out.active

    def sdf(x: Tensor) -> Tensor:
        return model.sdf.forward(x, count=False)[:, 0]

    weight = inputs.ray_weight if cfg.train.error_map.weigh_all else None
    rays = PhotoRays(inputs.origins, inputs.dirs, inputs.view, inputs.xy, out.depth,
                     out.normal, use, weight)
    cost, _ = photometric_term(inputs.photo, sdf, rays, cfg.train.photo, inputs.photo_wide)
    return cost


def render_and_loss(model: NeuSModel, inputs: StepInputs, cfg: Config, sampler: Sampler,
                    bounds: tuple[RayBounds, ...]) -> tuple[Tensor, Tensor, Tensor | None]:
    """Render a step's rays and compute its loss (what `train.compile` compiles).

    Returns:
        the loss (), the step's metrics (len(METRIC_NAMES),), detached, and the rays' (B,)
        errors for the pool's error map (`neus_l0.train.losses.ray_errors`; None when the
        rays were drawn uniformly).
    """
    with autocast(cfg, inputs.origins.device):
        out = render_rays(model, inputs.origins, inputs.dirs, cfg.render, sampler,
                          cos_anneal_ratio=inputs.anneal, create_graph=True, bounds=bounds,
                          noise=inputs.noise, span=inputs.span)
    terms = {}
    if inputs.curvature_idx is not None:
        terms["curvature"] = curvature_at_samples(model, inputs.origins, inputs.dirs, out,
                                                  inputs.curvature_idx)
    if inputs.photo is not None:
        terms["photo"] = photo_at_rays(model, inputs, out, cfg)
    if inputs.empty is not None or inputs.full is not None:
        counted = out.inside_sphere * out.active[:, None].to(out.inside_sphere.dtype)
    if inputs.empty is not None:
        terms["carve"] = free_space(out.sdf, inputs.empty, counted, inputs.ray_weight)
    if inputs.full is not None:
        if inputs.silhouettes is not None:
            counted = counted * silhouette_samples(inputs, out, cfg.train.fill_span,
                                                   cfg.train.fill_middle)
        terms["fill"] = missed_rays(out.sdf, inputs.full, counted, out.weight_sum,
                                    inputs.ray_weight, cfg.train.fill_margin / out.inv_s.detach())
    draw = RayDraw(mask_scale=inputs.mask_scale, ray_weight=inputs.ray_weight,
                   foreground=inputs.foreground, eikonal_idx=inputs.eikonal_idx)
    losses = neus_loss(out, inputs.rgb, inputs.mask, cfg.train, draw, terms)
    samples = out.active.sum() * out.t.shape[1]
    values = [losses[k] for k in LOSS_NAMES] + [out.inv_s, samples]  # () each, METRIC_NAMES
    errors = (None if inputs.ray_weight is None else
              ray_errors(out, inputs.rgb, inputs.mask, cfg.train.mask_weight > 0,
                         cfg.train.error_map.signal,
                         None if inputs.span is None else inputs.span[:, 0]))
    return losses["loss"], torch.stack(values).detach().float(), errors  # stack: the count


@dataclasses.dataclass
class StepSetup:
    """What a run builds once and every step uses (all optional).

    Attributes:
        bounds: what narrows the rays besides the sphere (a visual hull), before the grid.
        sampler: the up-sampling draw (None: the config's).
        pool: draw the rays from these pixels only (`neus_l0.bounds.pixel_pool`; None: from
            all), by its error map when it has one.
        compiled: a compiled `render_and_loss` (`neus_l0.train.compile`; None: eager).
        warp: real iteration -> the recorded schedule's iteration, when a budget run
            compressed the rest of its schedule (`neus_l0.train.budget.ScheduleWarp`;
            None: the identity).
        photo: the photometric term's views (`neus_l0.train.photometric.PhotoContext`;
            None: the term is off).
        silhouettes: silhouette filling's point test (`neus_l0.bounds.silhouettes`; None:
            off, `train.fill_silhouettes`).
    """

    bounds: tuple[RayBounds, ...] = ()
    sampler: Sampler | None = None
    pool: PixelPool | None = None
    compiled: Callable[..., tuple[Tensor, Tensor]] | None = None
    warp: ScheduleWarp | None = None
    photo: PhotoContext | None = None
    silhouettes: Silhouettes | None = None


def set_level_steps(model: NeuSModel, steps: int) -> None:
    """Set the hash grids' level counters (their schedule's iteration) to `steps`."""
    from neus_l0.fields.encodings import HashGridEncoding

    for m in model.modules():
        if isinstance(m, HashGridEncoding) and m.start_level < m.n_levels:
            m.steps.fill_(steps)



def view_scale(cfg: Config, at: float) -> float:
    """The view encoding's weight at schedule iteration `at`: ``at / (f * L)`` up to 1, f the
    config's ``model.color.view_warmup`` (1 when it is 0), L the `schedule_length`."""
    return warmup_ramp(cfg.model.color.view_warmup, cfg, at)


def warmup_ramp(share: float, cfg: Config, at: float) -> float:
    """``at / (share * L)`` clipped to [0, 1] (1 when `share` is 0), L the
    `schedule_length`: a weight that rises linearly over the schedule's first `share`."""
    span = share * schedule_length(cfg)
    return 1.0 if span <= 0 else min(1.0, max(0.0, at / span))


def map_fraction(cfg: Config, at: float) -> float:
    """The error map's share of the draw at schedule iteration `at`: ``f * at / (w * L)`` up
    to ``f``, f the config's ``train.error_map.fraction``, w its ``warmup`` (f throughout when
    it is 0), L the `schedule_length`."""
    c = cfg.train.error_map
    return c.fraction * warmup_ramp(c.warmup, cfg, at)


def set_view_scale(model: NeuSModel, cfg: Config, at: float) -> None:
    """Set the colour network's view-encoding weight (`view_scale`) for iteration `at`."""
    if cfg.model.color.view_warmup > 0:
        model.color.view_scale.fill_(view_scale(cfg, at))


def _schedule_position(model: NeuSModel, optimizer: torch.optim.Optimizer, cfg: Config,
                       iteration: int, setup: StepSetup) -> float:
    """Where the step stands on the schedule (the real iteration, unless a budget compressed
    the rest: `StepSetup.warp`), with the learning rate and the hash grids' levels set there;
    at log steps the pool's error map refreshes its draw table, at its share for `at`
    (`map_fraction`). Host-side only."""
    at = iteration
    if setup.warp is not None and setup.warp.warped:
        at = setup.warp.at(iteration)
        set_level_steps(model, int(at))
    set_learning_rate(optimizer, cfg, at)
    set_view_scale(model, cfg, at)
    emap = setup.pool.error_map if setup.pool is not None else None
    if emap is not None and iteration % refresh_interval(emap.prob.numel(),
                                                         cfg.train.log_every) == 0:
        emap.fraction = map_fraction(cfg, at)
        refresh_table(emap)  # the draw table follows the map (and its share's warm-up)
    return at

def train_step(model: NeuSModel, optimizer: torch.optim.Optimizer, scene: Scene, cfg: Config,
               iteration: int, generator: torch.Generator, *,
               occupancy: OccupancyGrid | None = None,
               scaler: torch.amp.GradScaler | None = None,
               batch_size: int | None = None, setup: StepSetup | None = None) -> Tensor:
    """One optimisation step on a random batch of rays.

    Fixed shapes and no host synchronisation, except the occupancy grid's update (once per
    `update_every` steps) when the grid is on.

    Args:
        model, optimizer: the networks and their optimiser.
        scene: the scene, on the training device.
        cfg: the run config.
        iteration: the current iteration (sets the learning rate and the cos annealing).
        generator: the source of the ray batch, the sample jitter and the Eikonal subset.
        occupancy: the occupancy grid (updated here every `update_every` iterations).
        scaler: the fp16 gradient scaler (`make_scaler`); None: none.
        batch_size: rays of this step (None: `train.batch_size`).
        setup: the run's hull bounds, sampler, pixel pool and compiled step (`StepSetup`).
            None: no bounds, no pool, eager, and the config's sampler built for this call
            (a loop should build a `StepSetup` once, so that the sampler and a
            compiled step are built once).

    Returns:
        (len(METRIC_NAMES),) detached metrics of this step, in `METRIC_NAMES` order
        (``samples``: foreground samples evaluated, active rays x samples per ray).
    """
    # learning rate, batch and random numbers, grid update
    setup = setup or StepSetup()
    at = _schedule_position(model, optimizer, cfg, iteration, setup)
    emap = setup.pool.error_map if setup.pool is not None else None
    inputs = draw_step_inputs(scene, cfg, at, batch_size or cfg.train.batch_size,
                              generator, setup.pool, setup.photo, setup.silhouettes)
    update_occupancy(occupancy, model, cfg, iteration)
    # the static bounds are in the looked-up spans when the pool kept them
    static = tuple(setup.bounds) if inputs.span is None else ()
    bounds = join_bounds(static, occupancy)
    # render and loss
    step_fn = setup.compiled or render_and_loss
    sampler = build_sampler(cfg.sampler) if setup.sampler is None else setup.sampler
    loss, metrics, errors = step_fn(model, inputs, cfg, sampler, bounds)
    if emap is not None and errors is not None:
        update_errors(emap, inputs.pick, errors)
    # backward and update
    _drop_grads(optimizer)
    if scaler is not None and scaler.is_enabled():
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
    else:
        loss.backward()
        optimizer.step()
    clear_weight_cache(model)  # the update may not move the version counters it keys on
    return metrics


def _drop_grads(optimizer: torch.optim.Optimizer) -> None:
    """`optimizer.zero_grad(set_to_none=True)` without its profiler record (2 ops a step)."""
    for group in optimizer.param_groups:
        for p in group["params"]:
            p.grad = None
