"""The NeuS training loop: Adam with warm-up and cosine decay, NeuS's losses, checkpoints.

`train(scene, cfg, run_dir)` writes into ``run_dir``:

* ``config.yaml``: the resolved config;
* ``metrics.jsonl``: one JSON line every ``train.log_every`` iterations (means over them);
* ``validation/NNNNNNN_vVVV.png``: ground truth | colour | normals of a downscaled view;
* ``checkpoints/ckpt_NNNNNNN.pt``: atomic checkpoints (see `neus_l0.checkpoint`), among
  them the snapshots that ``train(..., snapshots=[...])`` asks for at given loop times.

Randomness: the networks are initialised from ``train.seed`` (without touching torch's
global generator), and every random draw of the loop (ray batches, sample jitter) comes from
one `torch.Generator` whose state is checkpointed, so ``resume=True`` continues with exactly
the draws an uninterrupted run makes. The training step has no host synchronisation; the
accumulated metrics are read back every ``train.log_every`` iterations only.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neus_l0.atomic import atomic_write_json, atomic_write_text
from neus_l0.callbacks import (
    Checkpoints,
    Hook,
    HookCallback,
    MetricsFile,
    ProgressBar,
    Snapshots,
    TensorBoard,
    TrainingCallback,
    Validation,
    synchronize,
)
from neus_l0.checkpoint import (
    checkpoint_path,
    latest_checkpoint,
    load_newest_checkpoint,
    load_trained_model,  # noqa: F401 (its home is neus_l0.checkpoint)
    prune_checkpoints,
    restore_training,
    rng_state,
    save_checkpoint,
)
from neus_l0.compile_step import compiled_step
from neus_l0.config import Config, dump_config, to_dict
from neus_l0.data.rays import random_picks, random_rays, rays_at
from neus_l0.data.scene import Scene
from neus_l0.errors import ConfigError, NeusL0Error
from neus_l0.fields import NeuSModel, build_model
from neus_l0.fields.linear import clear_weight_cache
from neus_l0.interrupt import StopOnSignal
from neus_l0.losses import eikonal_indices, neus_loss
from neus_l0.occupancy import OccupancyGrid
from neus_l0.pixel_pool import PixelPool, reachable_pixels
from neus_l0.point_bound import PointBound
from neus_l0.rendering import RenderNoise, draw_noise, render_rays
from neus_l0.runlock import RunLock
from neus_l0.samplers import build_sampler
from neus_l0.schedule import cos_anneal_ratio, lr_factor
from neus_l0.validation import validation_image, validation_views  # noqa: F401 (moved)

__all__ = ["Hook", "TrainLoop", "TrainResult", "train", "train_step", "load_trained_model"]

METRIC_NAMES = ("loss", "color_loss", "eikonal_loss", "mask_loss", "psnr", "s", "samples")


@dataclasses.dataclass
class TrainResult:
    """What a call of `train` did.

    Attributes:
        run_dir: the run folder.
        iteration: iterations done in total (including before a resume).
        checkpoint: the last checkpoint written.
        metrics: the last logged metrics (empty if none were logged).
        seconds: wall-clock time of this call, less the time spent in hooks and in
            writing snapshots.
        stopped_early: whether `train.max_seconds` ended the run before `train.iters`.
        snapshots: one ``(mark, iteration, checkpoint)`` per snapshot mark of this call, in
            mark order (marks served by the same checkpoint repeat it).
        signal: ``SIGTERM`` / ``SIGINT`` when one stopped the run (after finishing the step
            and writing its checkpoint), else None.
        exit_code: the shell's code for that signal (143, 130), else 0.
    """

    run_dir: Path
    iteration: int
    checkpoint: Path
    metrics: dict
    seconds: float
    stopped_early: bool
    snapshots: list[tuple[float, int, Path]] = dataclasses.field(default_factory=list)
    signal: str | None = None
    exit_code: int = 0


def make_model(cfg: Config, device: str | torch.device = "cpu") -> NeuSModel:
    """The networks of `cfg`, initialised from `cfg.train.seed` (global RNG untouched)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.train.seed)
        model = build_model(cfg.model, background=cfg.render.n_outside > 0)
    return model.to(device)


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


def set_learning_rate(optimizer: torch.optim.Optimizer, cfg: Config, iteration: int) -> float:
    """Apply NeuS's schedule for `iteration` and return the learning rate."""
    t = cfg.train
    lr = t.lr * lr_factor(iteration, t.warm_up, t.iters, t.lr_alpha)
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


def draw_step_inputs(scene: Scene, cfg: Config, iteration: int, n_rays: int,
                     generator: torch.Generator, pool: PixelPool | None) -> StepInputs:
    """Draw one step's rays and random numbers (`StepInputs`), in a fixed order."""
    span = None
    if pool is None:
        batch, mask_scale = random_rays(scene, n_rays, generator), 1.0
    else:
        pick = random_picks(pool.pixels.shape[0], n_rays, generator, scene.device)
        batch, mask_scale = rays_at(scene, pool.pixels[pick]), pool.fraction
        span = pool.spans[pick] if pool.spans is not None else None
    r = cfg.render
    noise = draw_noise(r, n_rays, generator, scene.device) if r.perturb else None
    eik_idx = None
    if cfg.train.eikonal_fraction < 1.0:
        n_samples = n_rays * (r.n_samples + (r.n_importance if r.up_sample_steps else 0))
        eik_idx = eikonal_indices(n_samples, cfg.train.eikonal_fraction, generator,
                                  scene.device)
    mask = batch["mask"]
    mask = (mask > 0.5).float() if cfg.train.mask_weight > 0 else torch.ones_like(mask)
    anneal = (1.0 if cfg.train.anneal_end <= 0 else
              torch.tensor(cos_anneal_ratio(iteration, cfg.train.anneal_end),
                           device=scene.device))
    return StepInputs(batch["origins"], batch["dirs"], batch["rgb"], mask, noise, eik_idx,
                      anneal, mask_scale, span)


def render_and_loss(model: NeuSModel, inputs: StepInputs, cfg: Config, sampler,
                    bounds: tuple) -> tuple[Tensor, Tensor]:
    """Render a step's rays and compute its loss (what `train.compile` compiles).

    Returns:
        the loss () and the step's metrics (len(METRIC_NAMES),), detached.
    """
    with autocast(cfg, inputs.origins.device):
        out = render_rays(model, inputs.origins, inputs.dirs, cfg.render, sampler,
                          cos_anneal_ratio=inputs.anneal, create_graph=True, bounds=bounds,
                          noise=inputs.noise, span=inputs.span)
    losses = neus_loss(out, inputs.rgb, inputs.mask, cfg.train, mask_scale=inputs.mask_scale,
                       eikonal_idx=inputs.eikonal_idx)
    samples = out.active.sum() * out.t.shape[1]
    values = [losses[k] for k in METRIC_NAMES[:5]] + [out.s_val, samples]  # () each
    return losses["loss"], torch.stack(values).detach().float()  # stack promotes the count


@dataclasses.dataclass
class StepSetup:
    """What a run builds once and every step uses (all optional).

    Attributes:
        bounds: what narrows the rays besides the sphere (a visual hull), before the grid.
        sampler: the up-sampling draw (None: the config's).
        pool: draw the rays from these pixels only (`neus_l0.pixel_pool`; None: from all).
        compiled: a compiled `render_and_loss` (`neus_l0.compile_step`; None: eager).
    """

    bounds: tuple = ()
    sampler: object = None
    pool: PixelPool | None = None
    compiled: Callable | None = None


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
    set_learning_rate(optimizer, cfg, iteration)
    inputs = draw_step_inputs(scene, cfg, iteration, batch_size or cfg.train.batch_size,
                              generator, setup.pool)
    update_occupancy(occupancy, model, cfg, iteration)
    # the static bounds are in the looked-up spans when the pool kept them
    static = tuple(setup.bounds) if inputs.span is None else ()
    bounds = static + ((occupancy,) if occupancy is not None else ())
    # render and loss
    step_fn = setup.compiled or render_and_loss
    sampler = build_sampler(cfg.sampler) if setup.sampler is None else setup.sampler
    loss, metrics = step_fn(model, inputs, cfg, sampler, bounds)
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


class Clock:
    """Training time: the wall-clock since `start`, less the spans run in `paused()`."""

    def __init__(self) -> None:
        self.start = time.monotonic()
        self._paused = 0.0

    def elapsed(self) -> float:
        """Seconds of training time so far."""
        return time.monotonic() - self.start - self._paused

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Time spent inside does not count."""
        t0 = time.monotonic()
        try:
            yield
        finally:
            self._paused += time.monotonic() - t0


@dataclasses.dataclass
class TrainLoop:
    """What the loop and its callbacks share (built by `train`)."""

    cfg: Config
    run_dir: Path
    scene: Scene
    model: NeuSModel
    optimizer: torch.optim.Optimizer
    scaler: torch.amp.GradScaler
    generator: torch.Generator
    occupancy: OccupancyGrid | None = None
    setup: StepSetup = dataclasses.field(default_factory=StepSetup)
    iteration: int = 0
    rays: int = 0
    clock: Clock = dataclasses.field(default_factory=Clock)
    last_checkpoint: Path | None = None
    protected: set[Path] = dataclasses.field(default_factory=set)
    protect_snapshots: bool = False

    @property
    def device(self) -> torch.device:
        return self.scene.device

    @property
    def bounds(self) -> tuple:
        """Everything that narrows the rays: the setup's bounds, then the grid."""
        return tuple(self.setup.bounds) + ((self.occupancy,) if self.occupancy is not None else ())

    @contextlib.contextmanager
    def evaluating(self) -> Iterator[None]:
        """The model in eval mode without gradient, back in training mode after."""
        self.model.eval()
        try:
            with torch.no_grad():
                yield
        finally:
            self.model.train()

    def wait_for_device(self) -> None:
        """Let the queued steps finish (so that they count as training time)."""
        synchronize(self.device)

    def state(self) -> dict:
        """The checkpoint of the current iteration (see `neus_l0.checkpoint`)."""
        state = {
            "iteration": self.iteration,
            "batch_size": self.rays,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": rng_state(self.generator),
            "config": to_dict(self.cfg),
            "scale_mat": np.asarray(self.scene.scale_mat).tolist(),
            "has_background": self.model.background is not None,
        }
        if self.occupancy is not None:
            state["occupancy"] = self.occupancy.state_dict()
        if self.scaler.is_enabled():
            state["scaler"] = self.scaler.state_dict()
        return state

    def save(self) -> Path:
        """Write the checkpoint of this iteration and prune the old ones."""
        path = checkpoint_path(self.run_dir, self.iteration)
        keep = self.cfg.train.keep_checkpoints
        if not self.protect_snapshots:
            self.last_checkpoint = save_checkpoint(path, self.state(), keep=keep)
        else:
            self.last_checkpoint = save_checkpoint(path, self.state(), keep=0)
            prune_checkpoints(self.run_dir, keep, self.protected | {path})
        return self.last_checkpoint


def _check_scene(scene: Scene, cfg: Config) -> None:
    if cfg.train.mask_weight > 0 and not scene.has_masks:
        raise ConfigError(f"{scene.root}: train.mask_weight={cfg.train.mask_weight} but the "
                          "scene has no mask/ folder (use --conf womask or train.mask_weight=0)")


def _truncate_metrics(path: Path, iteration: int) -> None:
    """Keep only the metric lines up to `iteration` (after a resume)."""
    if not path.exists():
        return
    keep = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            if json.loads(line).get("iter", 0) <= iteration:
                keep.append(line)
        except json.JSONDecodeError:
            continue
    atomic_write_text(path, "".join(k + "\n" for k in keep))


def build_loop(scene: Scene, cfg: Config, run_dir: Path, device: torch.device,
               resume: bool) -> TrainLoop:
    """Networks, optimiser and generator, restored from the newest checkpoint on resume.

    Raises:
        NeusL0Error: nothing to resume, an existing run without `resume`, or a checkpoint
            that does not fit.
    """
    if not resume and latest_checkpoint(run_dir) is not None:
        raise NeusL0Error(f"{run_dir}: already holds checkpoints; pass --resume to continue "
                          "or choose another --out")
    found = load_newest_checkpoint(run_dir, map_location=device) if resume else None
    if resume and found is None:
        raise NeusL0Error(f"{run_dir}: nothing to resume (no checkpoints/ckpt_*.pt)")
    ckpt, state = found if found is not None else (None, None)
    _check_scene(scene, cfg)
    scene = scene.to(device)
    model = make_model(cfg, device)
    loop = TrainLoop(cfg=cfg, run_dir=run_dir, scene=scene, model=model,
                     optimizer=make_optimizer(model, cfg), scaler=make_scaler(cfg, device),
                     generator=torch.Generator(device=device),
                     occupancy=make_occupancy(cfg, device), rays=cfg.train.batch_size)
    loop.generator.manual_seed(cfg.train.seed)
    loop.setup.sampler = build_sampler(cfg.sampler)  # once: a compiled draw compiles once
    loop.setup.bounds = run_hull(scene, cfg, run_dir)
    loop.setup.pool = reachable_pixels(scene, cfg.render, loop.setup.bounds,
                                       background=model.background is not None)
    loop.setup.compiled = compiled_step(render_and_loss, cfg, device)
    if state is not None:
        loop.iteration, rays = restore_training(ckpt, state, model, loop.optimizer,
                                                loop.generator, loop.scaler, loop.occupancy)
        loop.rays = rays or loop.rays
        loop.last_checkpoint = ckpt
    return loop


def run_hull(scene: Scene, cfg: Config, run_dir: Path) -> tuple:
    """The run's static bounds: its visual hull, or without one the SfM point box.

    The hull exists only when the scene has masks and `render.hull.enabled` (views without
    masks carve nothing): carved at the first start and saved as ``RUN/hull.pt``; a resume
    loads that file. Each warning of the carving (a suspicious mask, named) is one line on
    stderr. Without a hull, `render.point_bound.enabled` and a ``sparse_points.npz`` in the
    scene folder (`neus-l0 colmap`) give the points' box (`neus_l0.point_bound`); else ().
    """
    import sys

    h = cfg.render.hull
    if not (h.enabled and scene.has_masks):
        p = cfg.render.point_bound
        box = PointBound.for_scene(scene, p.margin, p.min_views) if p.enabled else None
        if box is None:
            return ()
        print(f"neus-l0: {box.describe()}", file=sys.stderr, flush=True)
        return (box,)
    from neus_l0.hull import hull_for_run

    run_dir.mkdir(parents=True, exist_ok=True)
    hull = hull_for_run(scene, run_dir / "hull.pt", h.resolution, h.margin_px)
    for line in (hull.report.warnings if hull.report is not None else []):
        print(f"neus-l0: visual hull: {line}", file=sys.stderr, flush=True)
    return (hull,)


def _write_run_files(loop: TrainLoop) -> None:
    """``config.yaml`` and ``run.json``; the metrics cut back to the resumed iteration."""
    loop.run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(loop.run_dir / "config.yaml", dump_config(loop.cfg))
    scene = loop.scene
    atomic_write_json(loop.run_dir / "run.json", {
        "scene": str(scene.root), "scale_mat": np.asarray(scene.scale_mat).tolist(),
        "n_views": scene.n_views, "height": scene.height, "width": scene.width,
    })
    _truncate_metrics(loop.run_dir / "metrics.jsonl", loop.iteration)


def read_metrics(loop: TrainLoop, acc: Tensor, steps: int, last: Tensor,
                 window: tuple[float, int]) -> dict:
    """The metrics line of a log step: means over the window's `steps` steps.

    The loop's only host synchronisation. Also sets the next batch size (from this step's
    samples alone, so that a resume stays exact).

    Raises:
        NeusL0Error: a non-finite mean (training diverged).
    """
    *values, step_samples = torch.cat([acc / steps, last[-1:]]).tolist()
    now = loop.clock.elapsed()
    metrics = dict(zip(METRIC_NAMES, values, strict=True))
    metrics.update(rays=loop.rays)
    loop.rays = next_batch_size(loop.rays, step_samples, loop.cfg)
    metrics.update(iter=loop.iteration, lr=loop.optimizer.param_groups[0]["lr"],
                   its_per_s=(loop.iteration - window[1]) / max(now - window[0], 1e-9),
                   elapsed=now)
    if not all(math.isfinite(v) for v in values):
        raise NeusL0Error(f"{loop.run_dir}: training diverged at iteration {loop.iteration} "
                          f"(loss {metrics['loss']}); resume from the last checkpoint with a "
                          "lower train.lr")
    return metrics


def default_callbacks(cfg: Config, progress: bool, hooks: Sequence[Hook],
                      snapshots: Sequence[float]) -> list[TrainingCallback]:
    """The loop's own bookkeeping, in the order it runs at each point."""
    board = [TensorBoard()] if cfg.train.tensorboard else []
    sinks = [board[0].image] if board else []
    return [HookCallback(hooks), MetricsFile(), *board, ProgressBar(progress),
            Validation(sinks), Checkpoints(), Snapshots(snapshots)]


def train(scene: Scene, cfg: Config, run_dir: str | Path, device: str | torch.device = "cpu",
          resume: bool = False, progress: bool = True,
          stop_at: int | None = None, hooks: Sequence[Hook] = (),
          snapshots: Sequence[float] = (),
          callbacks: Sequence[TrainingCallback] = ()) -> TrainResult:
    """Train NeuS on `scene` and write the run folder.

    Args:
        scene: the loaded scene (moved to `device`).
        cfg: the run config. When resuming, pass the run's own config (``RUN/config.yaml``,
            as `neus-l0 train --resume` does) for a result identical to an uninterrupted run;
            changed settings such as `train.iters` or `train.lr` apply from the resumed
            iteration on, and changed network sizes are refused.
        run_dir: the output folder.
        device: ``cpu`` or ``cuda``.
        resume: continue from the newest checkpoint in ``run_dir``.
        progress: show a tqdm bar.
        stop_at: stop (and checkpoint) at this iteration as if interrupted, keeping the
            schedule of `train.iters` (for tests and staged runs).
        hooks: ``hook(iteration, model, scene, cfg) -> dict`` at each log step (model in
            eval mode, no gradient); their numbers join that line of ``metrics.jsonl``, and
            their time is not training time (`neus_l0.callbacks.HookCallback`).
        snapshots: loop-time marks in seconds that get a checkpoint
            (`neus_l0.callbacks.Snapshots`); the training itself is unchanged.
        callbacks: more `neus_l0.callbacks.TrainingCallback`s, run after the loop's own.

    Returns:
        a `TrainResult`.

    Raises:
        NeusL0Error: an existing run without `resume`, a NaN checkpoint, divergence, or
            a negative or non-finite snapshot mark.
    """
    try:
        own = default_callbacks(cfg, progress, hooks, snapshots)
    except ValueError as exc:
        raise NeusL0Error(str(exc)) from None
    if Path(run_dir).exists() and not Path(run_dir).is_dir():
        raise NeusL0Error(f"{run_dir}: is a file, not a run folder (choose another --out)")
    with RunLock(run_dir), StopOnSignal() as stop:
        loop = build_loop(scene, cfg, Path(run_dir), torch.device(device), resume)
        return _run_loop(loop, own + list(callbacks), stop_at, stop)


def _run_loop(loop: TrainLoop, cbs: list[TrainingCallback], stop_at: int | None,
              stop: StopOnSignal) -> TrainResult:
    """The loop itself: restore is done; step, log, validate / checkpoint, stop."""
    cfg = loop.cfg
    _write_run_files(loop)
    t = cfg.train
    acc = torch.zeros(len(METRIC_NAMES), device=loop.device)
    steps, stopped_early = 0, False
    for cb in cbs:
        cb.on_start(loop)
    # The budget (train.max_seconds) counts the loop from here: steps, logs, validation
    # renders and checkpoints, not the setup above.
    loop.clock = Clock()
    window = (0.0, loop.iteration)
    loop.model.train()
    while loop.iteration < t.iters:
        # step
        step = train_step(loop.model, loop.optimizer, loop.scene, cfg, loop.iteration,
                          loop.generator, occupancy=loop.occupancy, scaler=loop.scaler,
                          batch_size=loop.rays, setup=loop.setup)
        acc += step
        steps += 1
        loop.iteration += 1
        # log
        if loop.iteration % t.log_every == 0 or loop.iteration == t.iters:
            metrics = read_metrics(loop, acc, steps, step, window)
            for cb in cbs:
                cb.on_log(loop, metrics)
            acc.zero_()
            steps, window = 0, (loop.clock.elapsed(), loop.iteration)
        # validate, checkpoint, snapshots
        for cb in cbs:
            cb.after_step(loop)
        # stop
        over_time = t.max_seconds and loop.clock.elapsed() > t.max_seconds
        if (over_time or stop.requested or (stop_at is not None and loop.iteration >= stop_at)) \
                and loop.iteration < t.iters:
            stopped_early = True
            break
    for cb in cbs:
        cb.on_end(loop)
    if loop.last_checkpoint != checkpoint_path(loop.run_dir, loop.iteration):
        loop.save()
    snaps = next((cb.taken for cb in cbs if isinstance(cb, Snapshots)), [])
    return TrainResult(loop.run_dir, loop.iteration, loop.last_checkpoint,
                       _last_metrics(loop.run_dir), loop.clock.elapsed(), stopped_early, snaps,
                       signal=stop.signal_name if stop.requested else None,
                       exit_code=stop.exit_code)


def _last_metrics(run_dir: Path) -> dict:
    """The newest regular line of ``metrics.jsonl`` (empty when none was logged)."""
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        return {}
    for line in reversed(path.read_text(encoding="utf-8").splitlines()):
        m = json.loads(line)
        if "loss" in m:
            return m
    return {}
