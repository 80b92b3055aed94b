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
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neus_l0.atomic import atomic_write, atomic_write_json, atomic_write_text
from neus_l0.checkpoint import (
    checkpoint_path,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    save_checkpoint,
)
from neus_l0.config import Config, config_from_dict, dump_config, to_dict
from neus_l0.data.rays import pixel_grid, pixel_rays, random_rays
from neus_l0.data.scene import Scene
from neus_l0.errors import ConfigError, NeusL0Error
from neus_l0.fields import NeuSModel, build_model
from neus_l0.losses import eikonal_subset, neus_loss
from neus_l0.occupancy import OccupancyGrid
from neus_l0.rendering import render_image, render_rays
from neus_l0.schedule import cos_anneal_ratio, lr_factor

#: A training hook: ``hook(iteration, model, scene, cfg) -> {name: number}``.
Hook = Callable[[int, NeuSModel, Scene, Config], dict]

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
    """

    run_dir: Path
    iteration: int
    checkpoint: Path
    metrics: dict
    seconds: float
    stopped_early: bool
    snapshots: list[tuple[float, int, Path]] = dataclasses.field(default_factory=list)


def make_model(cfg: Config, device: str | torch.device = "cpu") -> NeuSModel:
    """The networks of `cfg`, initialised from `cfg.train.seed` (global RNG untouched)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.train.seed)
        model = build_model(cfg.model, background=cfg.render.n_outside > 0)
    return model.to(device)


def make_optimizer(model: NeuSModel, cfg: Config) -> torch.optim.Adam:
    """Adam over every network's parameters at the peak learning rate.

    With ``train.amp = fp16`` on CUDA the fused Adam is used: it takes the gradient
    scaler's inf check on the device, so `GradScaler.step` needs no host synchronisation.
    """
    on_cuda = next(model.parameters()).is_cuda
    fused = cfg.train.amp == "fp16" and on_cuda
    return torch.optim.Adam(model.parameters(), lr=cfg.train.lr, fused=fused or None)


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
    """Re-test the grid every `render.occupancy.update_every` iterations (from 0)."""
    if grid is not None and iteration % cfg.render.occupancy.update_every == 0:
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


def train_step(model: NeuSModel, optimizer: torch.optim.Optimizer, scene: Scene, cfg: Config,
               iteration: int, generator: torch.Generator, *,
               occupancy: OccupancyGrid | None = None,
               scaler: torch.amp.GradScaler | None = None,
               batch_size: int | None = None) -> Tensor:
    """One optimisation step on a random batch of rays.

    No host synchronisation, except where a switch asks for one on CUDA: the occupancy
    grid's ray compaction (`render.occupancy.compact`, once per step) and its update
    (once per `update_every` steps).

    Args:
        model, optimizer: the networks and their optimiser.
        scene: the scene, on the training device.
        cfg: the run config.
        iteration: the current iteration (sets the learning rate and the cos annealing).
        generator: the source of the ray batch and of the sample jitter.
        occupancy: the occupancy grid (updated here every `update_every` iterations).
        scaler: the fp16 gradient scaler (`make_scaler`); None: none.
        batch_size: rays of this step (None: `train.batch_size`).

    Returns:
        (len(METRIC_NAMES),) detached metrics of this step, in `METRIC_NAMES` order
        (``samples``: foreground samples evaluated, active rays x samples per ray).
    """
    set_learning_rate(optimizer, cfg, iteration)
    batch = random_rays(scene, batch_size or cfg.train.batch_size, generator)
    use_mask = cfg.train.mask_weight > 0
    mask = (batch["mask"] > 0.5).float() if use_mask else torch.ones_like(batch["mask"])
    update_occupancy(occupancy, model, cfg, iteration)
    with autocast(cfg, scene.device):
        out = render_rays(model, batch["origins"], batch["dirs"], cfg.render, cfg.sampler,
                          cos_anneal_ratio=cos_anneal_ratio(iteration, cfg.train.anneal_end),
                          perturb=cfg.render.perturb, generator=generator, create_graph=True,
                          occupancy=occupancy)
    if cfg.train.eikonal_fraction < 1.0:
        out["gradient_error"] = eikonal_subset(out["gradients"], out["eikonal_mask"],
                                               cfg.train.eikonal_fraction, generator)
    losses = neus_loss(out, batch["rgb"], mask, cfg.train.igr_weight, cfg.train.mask_weight)
    optimizer.zero_grad(set_to_none=True)
    if scaler is not None and scaler.is_enabled():
        scaler.scale(losses["loss"]).backward()
        scaler.step(optimizer)
        scaler.update()
    else:
        losses["loss"].backward()
        optimizer.step()
    samples = out["active"].sum() * out["z_vals"].shape[1]
    values = [losses[k] for k in METRIC_NAMES[:5]] + [out["s_val"].reshape(()), samples]
    return torch.stack([v.detach().reshape(()) for v in values])


def validation_views(scene: Scene, view: int, downscale: int) -> tuple[Tensor, Tensor, Tensor]:
    """Rays and ground truth of every `downscale`-th pixel of one view.

    Returns:
        origins (h, w, 3), dirs (h, w, 3), rgb (h, w, 3).
    """
    xy = pixel_grid(scene.height, scene.width, scene.device)[::downscale, ::downscale]
    h, w, _ = xy.shape
    o, d = pixel_rays(scene.intrinsics[view], scene.c2w[view], xy.reshape(-1, 2))
    rgb = scene.images[view, ::downscale, ::downscale]
    return o.reshape(h, w, 3), d.reshape(h, w, 3), rgb


def validation_image(model: NeuSModel, scene: Scene, cfg: Config, view: int,
                     iteration: int, occupancy: OccupancyGrid | None = None) -> np.ndarray:
    """Ground truth | rendered colour | normals (camera frame) of a downscaled view.

    Returns:
        (h, 3w, 3) uint8 RGB.
    """
    o, d, rgb = validation_views(scene, view, max(1, cfg.train.val_downscale))
    out = render_image(model, o, d, cfg.render, cfg.sampler,
                       cos_anneal_ratio(iteration, cfg.train.anneal_end),
                       occupancy=occupancy)
    rot = scene.c2w[view, :3, :3]  # camera -> world
    normal_cam = out["normal"] @ rot  # (h, w, 3) world -> camera: n^T R = (R^T n)^T
    tiles = [rgb, out["color"].clamp(0, 1), (normal_cam * 0.5 + 0.5).clamp(0, 1)]
    img = torch.cat([t.detach().float().cpu() for t in tiles], dim=1)
    return (img.numpy() * 255.0 + 0.5).astype(np.uint8)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    def writer(tmp: Path) -> None:
        ok, buf = cv2.imencode(".png", rgb[..., ::-1])
        if not ok:
            raise NeusL0Error(f"{path}: cannot encode PNG")
        tmp.write_bytes(buf.tobytes())

    atomic_write(path, writer)


def _rng_state(generator: torch.Generator) -> dict:
    state = {"generator": generator.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _restore_rng(generator: torch.Generator, state: dict) -> None:
    generator.set_state(state["generator"].cpu())
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


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


def _snapshot_checkpoints(path: Path) -> set[Path]:
    """Checkpoints of the snapshot lines already in ``metrics.jsonl`` (before a resume)."""
    if not path.exists():
        return set()
    found = set()
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            m = json.loads(line)
        except json.JSONDecodeError:
            continue
        if "snapshot_s" in m and "iter" in m:
            found.add(checkpoint_path(path.parent, int(m["iter"])))
    return found


def _prune_checkpoints(run_dir: Path, keep: int, protected: set[Path]) -> None:
    """Delete all but the newest `keep` checkpoints that are not in `protected`."""
    if keep <= 0:
        return
    others = [p for p in list_checkpoints(run_dir) if p not in protected]
    for old in others[:-keep]:
        old.unlink(missing_ok=True)


def _check_scene(scene: Scene, cfg: Config) -> None:
    if cfg.train.mask_weight > 0 and not scene.has_masks:
        raise ConfigError(f"{scene.root}: train.mask_weight={cfg.train.mask_weight} but the "
                          "scene has no mask/ folder (use --conf womask or train.mask_weight=0)")


def train(scene: Scene, cfg: Config, run_dir: str | Path, device: str | torch.device = "cpu",
          resume: bool = False, progress: bool = True,
          stop_at: int | None = None, hooks: Sequence[Hook] = (),
          snapshots: Sequence[float] = ()) -> TrainResult:
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
        hooks: called as ``hook(iteration, model, scene, cfg) -> dict`` (model in eval mode,
            no gradient) each time metrics are logged; their numbers join that line of
            ``metrics.jsonl``. Their time is not counted in ``elapsed`` nor against
            ``train.max_seconds``, so budgets stay comparable with and without them.
        snapshots: loop-time marks in seconds (the clock of ``train.max_seconds``, restarted
            by a resume). When the loop time first reaches a mark, a checkpoint is written
            and ``{"snapshot_s": mark, "iter": iteration, "elapsed": loop time}`` appended to
            ``metrics.jsonl``; a mark the run does not reach is served by the final
            checkpoint (and recorded the same way). Writing a snapshot is not counted in
            ``elapsed`` nor against ``train.max_seconds`` (on CUDA the queued work is waited
            for first, and counted). Snapshot checkpoints are exempt from
            ``train.keep_checkpoints``. The training itself is unchanged (resume stays
            exact).

    Returns:
        a `TrainResult`.

    Raises:
        NeusL0Error: an existing run without `resume`, a NaN checkpoint, divergence, or
            a negative or non-finite snapshot mark.
    """
    from tqdm import tqdm

    run_dir = Path(run_dir)
    device = torch.device(device)
    marks = sorted(float(m) for m in snapshots)
    if not all(math.isfinite(m) and m >= 0 for m in marks):
        raise NeusL0Error(f"snapshots {list(snapshots)}: marks must be finite seconds >= 0")
    ckpt_state = None
    if resume:
        last = latest_checkpoint(run_dir)
        if last is None:
            raise NeusL0Error(f"{run_dir}: nothing to resume (no checkpoints/ckpt_*.pt)")
        ckpt_state = load_checkpoint(last, map_location=device)
    elif latest_checkpoint(run_dir) is not None:
        raise NeusL0Error(f"{run_dir}: already holds checkpoints; pass --resume to continue "
                          "or choose another --out")
    _check_scene(scene, cfg)
    scene = scene.to(device)

    model = make_model(cfg, device)
    optimizer = make_optimizer(model, cfg)
    scaler = make_scaler(cfg, device)
    occupancy = make_occupancy(cfg, device)
    generator = torch.Generator(device=device)
    generator.manual_seed(cfg.train.seed)
    iteration = 0
    rays = cfg.train.batch_size  # adapted at log steps under train.sample_budget
    if ckpt_state is not None:
        try:
            model.load_state_dict(ckpt_state["model"])
            optimizer.load_state_dict(ckpt_state["optimizer"])
        except (RuntimeError, ValueError, KeyError) as exc:
            raise NeusL0Error(f"{last}: does not fit the config's networks (resume with the "
                              f"run's config.yaml): {str(exc).splitlines()[0]}") from None
        _restore_rng(generator, ckpt_state["rng"])
        if occupancy is not None and "occupancy" in ckpt_state:
            occupancy.load_state_dict(ckpt_state["occupancy"])
        elif occupancy is not None:  # a checkpoint from a run without the grid
            occupancy.update(model.sdf.sdf, model.variance.inv_s())
        if "scaler" in ckpt_state:
            scaler.load_state_dict(ckpt_state["scaler"])
        iteration = int(ckpt_state["iteration"])
        rays = int(ckpt_state.get("batch_size", rays))
        del ckpt_state

    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(run_dir / "config.yaml", dump_config(cfg))
    atomic_write_json(run_dir / "run.json", {
        "scene": str(scene.root), "scale_mat": np.asarray(scene.scale_mat).tolist(),
        "n_views": scene.n_views, "height": scene.height, "width": scene.width,
    })
    metrics_path = run_dir / "metrics.jsonl"
    _truncate_metrics(metrics_path, iteration)
    protected = _snapshot_checkpoints(metrics_path) if marks else set()
    taken: list[tuple[float, int, Path]] = []

    def checkpoint() -> Path:
        state = {
            "iteration": iteration,
            "batch_size": rays,
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "rng": _rng_state(generator),
            "config": to_dict(cfg),
            "scale_mat": np.asarray(scene.scale_mat).tolist(),
            "has_background": model.background is not None,
        }
        if occupancy is not None:
            state["occupancy"] = occupancy.state_dict()
        if scaler.is_enabled():
            state["scaler"] = scaler.state_dict()
        if not marks:
            return save_checkpoint(checkpoint_path(run_dir, iteration), state,
                                   keep=cfg.train.keep_checkpoints)
        path = save_checkpoint(checkpoint_path(run_dir, iteration), state, keep=0)
        _prune_checkpoints(run_dir, cfg.train.keep_checkpoints, protected | {path})
        return path

    def snapshot(elapsed: float, final: bool) -> None:
        """Serve every pending mark up to `elapsed` (all of them when `final`)."""
        nonlocal last_ckpt
        path = checkpoint_path(run_dir, iteration)
        protected.add(path)  # before writing, so that its own pruning keeps it
        if last_ckpt != path:
            last_ckpt = checkpoint()
        with open(metrics_path, "a", encoding="utf-8") as f:
            while len(taken) < len(marks) and (final or marks[len(taken)] <= elapsed):
                mark = marks[len(taken)]
                taken.append((mark, iteration, path))
                f.write(json.dumps({"snapshot_s": mark, "iter": iteration,
                                    "elapsed": elapsed}) + "\n")

    def wait_for_device() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    t = cfg.train
    acc = torch.zeros(len(METRIC_NAMES), device=device)
    acc_n = 0
    last_metrics: dict = {}
    last_ckpt = latest_checkpoint(run_dir) if resume else None
    stopped_early = False
    bar = tqdm(total=t.iters, initial=iteration, disable=not progress, dynamic_ncols=True,
               desc="train")
    # The budget (train.max_seconds) counts the loop: steps, logs, validation renders and
    # checkpoints, not the setup above (loading, first-use imports inside torch).
    start_time = time.monotonic()
    log_t0, log_it0 = start_time, iteration
    model.train()
    while iteration < t.iters:
        step = train_step(model, optimizer, scene, cfg, iteration, generator,
                          occupancy=occupancy, scaler=scaler, batch_size=rays)
        acc += step
        acc_n += 1
        iteration += 1
        bar.update(1)
        if iteration % t.log_every == 0 or iteration == t.iters:
            # the loop's only host synchronisation: the means, and this step's samples
            *values, step_samples = torch.cat([acc / acc_n, step[-1:]]).tolist()
            now = time.monotonic()
            last_metrics = dict(zip(METRIC_NAMES, values, strict=True))
            last_metrics.update(rays=rays)
            # depends only on this step, not on the window, so a resume stays exact
            rays = next_batch_size(rays, step_samples, cfg)
            last_metrics.update(iter=iteration, lr=optimizer.param_groups[0]["lr"],
                                its_per_s=(iteration - log_it0) / max(now - log_t0, 1e-9),
                                elapsed=now - start_time)
            if not all(math.isfinite(v) for v in values):
                raise NeusL0Error(f"{run_dir}: training diverged at iteration {iteration} "
                                  f"(loss {last_metrics['loss']}); resume from the last "
                                  "checkpoint with a lower train.lr")
            if hooks:
                hook_t0 = time.monotonic()
                model.eval()
                with torch.no_grad():
                    for hook in hooks:
                        last_metrics.update(hook(iteration, model, scene, cfg))
                model.train()
                hook_seconds = time.monotonic() - hook_t0
                start_time += hook_seconds  # hooks do not count as training time
                now += hook_seconds
            with open(metrics_path, "a", encoding="utf-8") as f:
                f.write(json.dumps(last_metrics) + "\n")
            bar.set_postfix(loss=f"{values[0]:.4f}", psnr=f"{values[4]:.2f}",
                            s=f"{1.0 / values[5]:.1f}",
                            its=f"{last_metrics['its_per_s']:.1f}")
            acc.zero_()
            acc_n = 0
            log_t0, log_it0 = now, iteration
        if t.val_every and iteration % t.val_every == 0:
            view = (iteration // t.val_every) % scene.n_views
            model.eval()
            img = validation_image(model, scene, cfg, view, iteration, occupancy)
            model.train()
            _write_png(run_dir / "validation" / f"{iteration:07d}_v{view:03d}.png", img)
        if t.save_every and iteration % t.save_every == 0:
            last_ckpt = checkpoint()
        if len(taken) < len(marks) and time.monotonic() - start_time >= marks[len(taken)]:
            wait_for_device()  # the queued steps are training time
            snap_t0 = time.monotonic()
            snapshot(snap_t0 - start_time, final=False)
            snap_seconds = time.monotonic() - snap_t0
            start_time += snap_seconds  # snapshots do not count as training time either
            log_t0 += snap_seconds
        over_time = t.max_seconds and time.monotonic() - start_time > t.max_seconds
        if (over_time or (stop_at is not None and iteration >= stop_at)) \
                and iteration < t.iters:
            stopped_early = True
            break
    bar.close()
    if len(taken) < len(marks):  # marks beyond the end: the final checkpoint serves them
        wait_for_device()
        snapshot(time.monotonic() - start_time, final=True)
    if last_ckpt is None or last_ckpt != checkpoint_path(run_dir, iteration):
        last_ckpt = checkpoint()
    return TrainResult(run_dir, iteration, last_ckpt, last_metrics,
                       time.monotonic() - start_time, stopped_early, taken)


def load_trained_model(run_dir: str | Path, device: str | torch.device = "cpu",
                       checkpoint: str | Path | None = None) -> tuple[NeuSModel, Config, dict]:
    """The networks of a finished (or interrupted) run.

    Returns:
        model (eval mode), config, and the checkpoint dict without the heavy states
        (``iteration``, ``scale_mat``, ...).

    Raises:
        NeusL0Error: no checkpoint, or an unusable one.
    """
    path = Path(checkpoint) if checkpoint else latest_checkpoint(run_dir)
    if path is None:
        raise NeusL0Error(f"{run_dir}: no checkpoints/ckpt_*.pt (train first)")
    state = load_checkpoint(path, map_location=device)
    cfg = config_from_dict(state["config"])
    model = make_model(cfg, device)
    model.load_state_dict(state["model"])
    model.eval()
    info = {k: v for k, v in state.items() if k not in ("model", "optimizer", "rng")}
    info["path"] = path
    return model, cfg, info
