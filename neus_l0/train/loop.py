"""The NeuS training loop: Adam with warm-up and cosine decay, NeuS's losses, checkpoints.

`train(scene, cfg, run_dir)` writes into ``run_dir``:

* ``config.yaml``: the resolved config;
* ``metrics.jsonl``: one JSON line every ``train.log_every`` iterations (means over them);
* ``validation/NNNNNNN_vVVV.png``: ground truth | colour | normals of a downscaled view;
* ``checkpoints/ckpt_NNNNNNN.pt``: atomic checkpoints (see `neus_l0.run.checkpoints`), among
  them the snapshots that ``train(..., snapshots=[...])`` asks for at given loop times.

Randomness: the networks are initialised from ``train.seed`` (without touching torch's
global generator), and every random draw of the loop (ray batches, sample jitter) comes from
one `torch.Generator` whose state is checkpointed, so ``resume=True`` continues with exactly
the draws an uninterrupted run makes. The training step has no host synchronisation; the
accumulated metrics are read back every ``train.log_every`` iterations only.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neus_l0.atomic import atomic_write_json, atomic_write_text, remove_orphans
from neus_l0.bounds.error_map import restore_map
from neus_l0.bounds.pixel_pool import reachable_pixels, with_error_map
from neus_l0.bounds.silhouettes import Silhouettes
from neus_l0.bounds.static import cameras_inside_warning, static_bounds
from neus_l0.config.load import dump_config, load_config
from neus_l0.config.schema import Config
from neus_l0.data.scene import Scene
from neus_l0.data.split import holdout_split
from neus_l0.errors import ConfigError, NeusL0Error
from neus_l0.fields.model import make_model
from neus_l0.run.checkpoints import (
    checkpoint_iteration,
    checkpoint_path,
    latest_checkpoint,
    list_checkpoints,
    load_newest_checkpoint,
    restore_training,
)
from neus_l0.run.folder import check_run_entries
from neus_l0.run.lock import RunLock
from neus_l0.run.metrics import last_log_line
from neus_l0.run.metrics import truncate as truncate_metrics
from neus_l0.run.resumes import (
    ResumeRecord,
    as_overrides,
    changed_keys,
    record_resume,
    recorded_overrides,
)
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.budget import ScheduleWarp
from neus_l0.train.budget_run import EstimateLine, plan_run
from neus_l0.train.cache_folder import use_persistent_cache
from neus_l0.train.callbacks import (
    Checkpoints,
    Hook,
    HookCallback,
    MetricsFile,
    ProgressBar,
    Snapshots,
    TensorBoard,
    TrainingCallback,
    Validation,
)
from neus_l0.train.compile import compiled_step
from neus_l0.train.compile_auto import resolve_compile
from neus_l0.train.early_stop import EarlyStop
from neus_l0.train.photometric import PhotoContext
from neus_l0.train.preflight import (
    check_same_scene,
    check_step_memory,
    check_writable,
    checkpoint_bytes,
    device_memory,
    scene_fingerprint,
)
from neus_l0.train.probe import time_steps
from neus_l0.train.signals import StopOnSignal
from neus_l0.train.state import Clock, RunState
from neus_l0.train.step import (
    METRIC_NAMES,
    StepSetup,
    make_occupancy,
    make_optimizer,
    make_scaler,
    next_batch_size,
    render_and_loss,
    resumed_batch_size,
    train_step,
)
from neus_l0.train.watchdog import Watchdog


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
        stopped_early: whether `train.max_seconds` (or a budget's deadline) ended the run
            before its last iteration.
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


def _check_scene(scene: Scene, cfg: Config) -> None:
    """Refuse a mask loss without masks, and the hit colour over a white background; warn
    (one line) of cameras inside the unit sphere."""
    if cfg.train.mask_weight > 0 and not scene.has_masks:
        raise ConfigError(f"{scene.root}: train.mask_weight={cfg.train.mask_weight} but the "
                          "scene has no mask/ folder (use --conf womask or train.mask_weight=0)")
    if cfg.train.hit_color_floor > 0 and cfg.render.white_background:
        raise ConfigError(f"train.hit_color_floor={cfg.train.hit_color_floor} divides the "
                          "composite over black by the opacity; render.white_background adds "
                          "white behind it (turn one of them off)")
    line = cameras_inside_warning(scene)
    if line:
        print(f"neus-l0: warning: {line}", file=sys.stderr, flush=True)


def build_run_state(scene: Scene, cfg: Config, run_dir: Path, device: torch.device,
                    resume: bool) -> RunState:
    """Networks, optimiser and generator, restored from the newest checkpoint on resume.

    ``train.compile: auto`` is resolved here, on eager steps timed on the run itself when
    the setting was never measured (`neus_l0.train.compile_auto`).

    Raises:
        NeusL0Error: nothing to resume, an existing run without `resume`, or a checkpoint
            that does not fit.
    """
    ckpt, state = _found_checkpoint(scene, cfg, run_dir, device, resume)
    fingerprint = (check_same_scene(run_dir, scene, state) if resume
                   else scene_fingerprint(scene))
    check_run_entries(run_dir)
    scene = scene.to(device)
    _check_space(scene, cfg, run_dir, device)  # before the hull or any step
    setup = _static_setup(scene, cfg, run_dir)

    def measure() -> float:
        eager = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, compile=False))
        return time_steps(_new_run(scene, eager, run_dir, device, setup), warm=1, most=3,
                          seconds=5.0)

    cfg, line = resolve_compile(cfg, device.type, checkpoint_iteration(ckpt) if ckpt else 0,
                                run_dir, measure)
    if line:
        print(f"neus-l0: {line}", file=sys.stderr, flush=True)
    if cfg.train.compile:
        use_persistent_cache()  # before the optimiser imports torch._dynamo (the CLI did it too)
    run = _new_run(scene, cfg, run_dir, device, setup)
    run.fingerprint = fingerprint
    run.setup.compiled = compiled_step(render_and_loss, cfg, device)
    if state is not None:
        run.iteration, rays = restore_training(ckpt, state, run.model, run.optimizer,
                                                run.generator, run.scaler, run.occupancy)
        run.rays = resumed_batch_size(rays, cfg)
        _restore_error_map(run, state)
        run.last_checkpoint = ckpt
        run.setup.warp = _resumed_warp(state, cfg)
    return run


def _restore_error_map(run: RunState, state: dict) -> None:
    """The pool's error map as the checkpoint left it (a checkpoint without one, or one of
    another pool, leaves the map uniform, with a line saying so)."""
    emap = run.setup.pool.error_map if run.setup.pool is not None else None
    if emap is None:
        return
    if not restore_map(emap, state.get("error_map") or {}):
        print("neus-l0: the checkpoint holds no error map for this pool: the map restarts "
              "uniform", file=sys.stderr, flush=True)


def _found_checkpoint(scene: Scene, cfg: Config, run_dir: Path, device: torch.device,
                      resume: bool) -> tuple[Path | None, dict | None]:
    """The checkpoint to resume (None, None for a fresh run), after the run folder's checks
    and the removal of a killed writer's leftovers."""
    if not resume and latest_checkpoint(run_dir) is not None:
        raise NeusL0Error(f"{run_dir}: already holds checkpoints; pass --resume to continue "
                          "or choose another --out")
    # the run folder is locked: a temporary file in it is a killed writer's leftover
    left = [p for d in (run_dir, run_dir / "checkpoints", run_dir / "validation")
            for p in remove_orphans(d)]
    if left:
        print(f"neus-l0: removed {len(left)} temporary file(s) a killed run left behind, e.g. "
              f"{left[0]}", file=sys.stderr, flush=True)
    found = load_newest_checkpoint(run_dir, map_location=device) if resume else None
    if resume and found is None:
        raise NeusL0Error(f"{run_dir}: nothing to resume (no checkpoints/ckpt_*.pt)")
    _check_scene(scene, cfg)
    return found if found is not None else (None, None)


def _check_space(scene: Scene, cfg: Config, run_dir: Path, device: torch.device) -> None:
    """A step fits in memory (`check_step_memory`) and the run folder takes the checkpoints
    the schedule keeps (`check_writable`)."""
    t = cfg.train
    saves = (t.iters // t.save_every if t.save_every else 0) + 1
    kept = min(t.keep_checkpoints, saves) if t.keep_checkpoints else saves
    model = make_model(cfg, device)
    check_step_memory(model, cfg, device_memory(device))
    check_writable(run_dir, (kept + 1) * checkpoint_bytes(model, make_optimizer(model, cfg)))


def _static_setup(scene: Scene, cfg: Config, run_dir: Path) -> StepSetup:
    """What the steps use and no network changes: the sampler, the static bounds and the
    pixel pool."""
    setup = StepSetup(sampler=build_sampler(cfg.sampler))  # once: a compiled draw compiles once
    setup.bounds = static_bounds(scene, cfg, run_dir / "hull.pt",
                                 reuse=latest_checkpoint(run_dir) is not None)
    setup.pool = with_error_map(reachable_pixels(scene, cfg.render, setup.bounds,
                                                 background=cfg.render.n_outside > 0),
                                scene, cfg)
    ph = cfg.train.photo
    if ph.weight > 0 and scene.n_views < 2:
        print("neus-l0: warning: train.photo needs at least 2 training views, this run has "
              f"{scene.n_views}: the photometric term is off", file=sys.stderr, flush=True)
    elif ph.weight > 0:
        setup.photo = PhotoContext.from_scene(scene, ph.sources, ph.patch, ph.stride, ph.best,
                                              ph.normal_sources, ph.wide_sources)
    if cfg.train.fill_weight > 0 and cfg.train.fill_silhouettes and scene.has_masks:
        setup.silhouettes = Silhouettes.from_scene(scene, cfg.render.hull.margin_px)
    return setup


def _new_run(scene: Scene, cfg: Config, run_dir: Path, device: torch.device,
             setup: StepSetup) -> RunState:
    """A fresh `RunState` (networks from `train.seed`) sharing `setup`'s static parts."""
    model = make_model(cfg, device)
    run = RunState(cfg=cfg, run_dir=run_dir, scene=scene, model=model,
                   optimizer=make_optimizer(model, cfg), scaler=make_scaler(cfg, device),
                   generator=torch.Generator(device=device),
                   occupancy=make_occupancy(cfg, device), rays=cfg.train.batch_size,
                   setup=dataclasses.replace(setup, compiled=None, warp=None))
    run.generator.manual_seed(cfg.train.seed)
    return run


def _resumed_warp(state: dict, cfg: Config) -> ScheduleWarp | None:
    """The compressed schedule a budget run's checkpoint holds (None when it has none or
    `train.iters` changed since)."""
    if "schedule" not in state:
        return None
    warp = ScheduleWarp.from_dict(state["schedule"])
    return warp if warp.base == cfg.train.iters else None


def _write_run_files(run: RunState) -> None:
    """``config.yaml`` (a resume keeps the original and records what it changes in
    ``resumes.jsonl``: `neus_l0.run.resumes`) and ``run.json``; the metrics cut back to the
    resumed iteration."""
    run_dir = run.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    original = run_dir / "config.yaml"
    if run.iteration > 0 and original.is_file():
        before = load_config(original, recorded_overrides(run_dir))
        changed = changed_keys(before, run.cfg)
        if changed:
            record_resume(run_dir, ResumeRecord(run.iteration,
                                                as_overrides(run.cfg, changed), changed))
    else:
        atomic_write_text(original, dump_config(run.cfg), within=run_dir)
    scene = run.scene
    atomic_write_json(run_dir / "run.json", {
        "scene": str(scene.root), "scale_mat": np.asarray(scene.scale_mat).tolist(),
        "n_views": scene.n_views, "height": scene.height, "width": scene.width,
        "scene_fingerprint": run.fingerprint, "views": run.views,
    }, within=run_dir)
    dropped = truncate_metrics(run_dir, run.iteration)
    if dropped:
        print(f"neus-l0: {run_dir / 'metrics.jsonl'}: dropped {dropped} line(s) that are not "
              "UTF-8 JSON (damaged)", file=sys.stderr, flush=True)


def metrics_line(run: RunState, acc: Tensor, steps: int, last: Tensor,
                 window: tuple[float, int]) -> dict:
    """The metrics line of a log step: means over the window's `steps` steps.

    The loop's only host synchronisation. Also sets the next batch size (from this step's
    samples alone, so that a resume stays exact).
    """
    *values, step_samples = torch.cat([acc / steps, last[-1:]]).tolist()
    now = run.clock.elapsed()
    metrics = dict(zip(METRIC_NAMES, values, strict=True))
    metrics.update(rays=run.rays)
    run.rays = next_batch_size(run.rays, step_samples, run.cfg)
    metrics.update(iter=run.iteration, lr=run.optimizer.param_groups[0]["lr"],
                   its_per_s=(run.iteration - window[1]) / max(now - window[0], 1e-9),
                   elapsed=now)
    return metrics


def watch(run: RunState, watchdog: Watchdog, metrics: dict) -> str | None:
    """The watchdog's verdict on a log line; while the run is suspect, its last good
    checkpoint is kept from pruning (`RunState.good_checkpoint`)."""
    reason = watchdog.check(metrics)
    good = watchdog.last_good_iter
    if reason is None and good == run.iteration:
        run.good_checkpoint = None  # healthy: pruning as usual
    elif run.good_checkpoint is None:
        kept = [p for p in list_checkpoints(run.run_dir)
                if good is not None and checkpoint_iteration(p) <= good]
        run.good_checkpoint = kept[-1] if kept else None
    return reason


def stop_diverged(run: RunState, watchdog: Watchdog, reason: str) -> NeusL0Error:
    """Set aside the checkpoints written after the last good log line (``*.diverged``), so
    that a resume starts from the last good one, and say what happened and what to try."""
    run.diverged = True
    good = watchdog.last_good_iter
    kept = None
    for p in list_checkpoints(run.run_dir):
        if good is not None and checkpoint_iteration(p) <= good:
            kept = p
        else:
            p.rename(p.with_name(p.name + ".diverged"))
    lr = run.cfg.train.lr
    where = (f"the last good checkpoint is {kept.name}; resume from it with a lower "
             f"learning rate (--resume --change-config train.lr={lr / 10:g})"
             if kept is not None else
             f"no good checkpoint was written; start again with a lower train.lr "
             f"(e.g. {lr / 10:g})")
    return NeusL0Error(f"{run.run_dir}: training diverged at iteration {run.iteration} "
                       f"({reason}); {where}")


def default_callbacks(cfg: Config, progress: bool, hooks: Sequence[Hook],
                      snapshots: Sequence[float]) -> list[TrainingCallback]:
    """The loop's own bookkeeping, in the order it runs at each point."""
    board = [TensorBoard()] if cfg.train.tensorboard else []
    sinks = [board[0].image] if board else []
    scalars = [board[0].scalar] if board else []
    return [HookCallback(hooks), MetricsFile(), *board, ProgressBar(progress),
            Validation(sinks, scalars), Checkpoints(), Snapshots(snapshots)]


def train(scene: Scene, cfg: Config, run_dir: str | Path, device: str | torch.device = "cpu",
          resume: bool = False, progress: bool = True,
          stop_at: int | None = None, hooks: Sequence[Hook] = (),
          snapshots: Sequence[float] = (),
          callbacks: Sequence[TrainingCallback] = ()) -> TrainResult:
    """Train NeuS on `scene` and write the run folder.

    Args:
        scene: the loaded scene (moved to `device`); with ``train.holdout = K`` every K-th
            view is kept out of training (`neus_l0.data.split.holdout_split`), recorded in
            ``run.json`` and rendered by the validation.
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
            their time is not training time (`neus_l0.train.callbacks.HookCallback`).
        snapshots: loop-time marks in seconds that get a checkpoint
            (`neus_l0.train.callbacks.Snapshots`); the training itself is unchanged.
        callbacks: more `neus_l0.train.callbacks.TrainingCallback`s, run after the loop's own.

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
    started = time.monotonic()
    part, held, views = holdout_split(scene, cfg.train.holdout)
    with RunLock(run_dir), StopOnSignal() as stop:
        run = build_run_state(part, cfg, Path(run_dir), torch.device(device), resume)
        run.views, run.heldout = views, None if held is None else held.to(run.device)
        return _run_loop(run, _with_budget(run, own, started, resume) + list(callbacks),
                         stop_at, stop)


def _with_budget(run: RunState, own: list[TrainingCallback], started: float,
                 resume: bool) -> list[TrainingCallback]:
    """`own` with a budget run's plan and keeper (`neus_l0.train.budget_run`) or the
    duration estimate after it, and the early stop before it when `train.early_stop` is on
    (its number joins the metrics line before it is written)."""
    first = [EarlyStop()] if run.cfg.train.early_stop else []
    if run.cfg.train.budget <= 0:
        return [*first, *own, EstimateLine()]
    if resume:
        raise ConfigError(f"train.budget={run.cfg.train.budget:g}: a resumed run keeps the "
                          "schedule its config.yaml recorded; resume without a budget")
    return [*first, *own, plan_run(run, started)]


def _run_loop(run: RunState, cbs: list[TrainingCallback], stop_at: int | None,
              stop: StopOnSignal) -> TrainResult:
    """The loop itself: restore is done; step, log, validate / checkpoint, stop."""
    cfg = run.cfg
    _write_run_files(run)
    t = cfg.train
    acc = torch.zeros(len(METRIC_NAMES), device=run.device)
    steps, stopped_early = 0, False
    for cb in cbs:
        cb.on_start(run)
    # The budget (train.max_seconds) counts the loop from here: steps, logs, validation
    # renders and checkpoints, not the setup above.
    run.clock = Clock()
    window = (0.0, run.iteration)
    # where the run starts is good: a resumed checkpoint passed the watchdog before
    watchdog, diverged = Watchdog(last_good_iter=run.iteration or None), None
    run.model.train()
    while run.iteration < run.end:
        # step
        step = train_step(run.model, run.optimizer, run.scene, cfg, run.iteration,
                          run.generator, occupancy=run.occupancy, scaler=run.scaler,
                          batch_size=run.rays, setup=run.setup)
        acc += step
        steps += 1
        run.iteration += 1
        # log
        if run.iteration % t.log_every == 0 or run.iteration == run.end:
            metrics = metrics_line(run, acc, steps, step, window)
            reason = watch(run, watchdog, metrics)
            for cb in cbs:
                cb.on_log(run, metrics)
            if reason is not None:
                diverged = stop_diverged(run, watchdog, reason)
                break
            acc.zero_()
            steps, window = 0, (run.clock.elapsed(), run.iteration)
        # validate, checkpoint, snapshots
        for cb in cbs:
            cb.after_step(run)
        # stop
        over_time = (t.max_seconds and run.clock.elapsed() > t.max_seconds) or run.stop_requested
        if (over_time or stop.requested or (stop_at is not None and run.iteration >= stop_at)) \
                and run.iteration < run.end:
            stopped_early = True
            break
    for cb in cbs:
        cb.on_end(run)
    if diverged is not None:
        raise diverged
    if run.last_checkpoint != checkpoint_path(run.run_dir, run.iteration):
        run.save()
    snaps = next((cb.taken for cb in cbs if isinstance(cb, Snapshots)), [])
    return TrainResult(run.run_dir, run.iteration, run.last_checkpoint,
                       last_log_line(run.run_dir), run.clock.elapsed(), stopped_early, snaps,
                       signal=stop.signal_name if stop.requested else None,
                       exit_code=stop.exit_code)
