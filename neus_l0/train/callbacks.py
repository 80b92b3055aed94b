"""The training loop's bookkeeping as callbacks at named points (nerfstudio's idea).

`neus_l0.train.loop.train` runs a short loop: restore, step, log, validate / checkpoint, stop.
Everything else it does is one of these callbacks, each called at a named point of the
loop with the run's state (`neus_l0.train.state.RunState`):

* ``on_start(run)``: once, before the first step;
* ``on_log(run, metrics)``: every ``train.log_every`` steps (and at the last), with the
  metrics line being built; a callback may add numbers to it before `MetricsFile` writes
  it (order matters: the loop calls callbacks in list order);
* ``after_step(run)``: after every step;
* ``on_end(run)``: once, after the last step (also after a stop by time, `stop_at` or a
  signal), before the final checkpoint.

The clock (`neus_l0.train.state.Clock`) counts training time; callbacks whose work must not count
(training hooks, snapshot checkpoints) run inside ``run.clock.paused()``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from neus_l0.run.checkpoints import checkpoint_path
from neus_l0.run.metrics import append_line, snapshot_lines
from neus_l0.train.state import RunState
from neus_l0.train.step import METRIC_NAMES

#: A training hook: ``hook(iteration, model, scene, cfg) -> {name: number}``.
Hook = Callable[..., dict]


def step_check(iteration: int, every: int) -> bool:
    """Whether a task due every `every` iterations runs at `iteration` (0: never)."""
    return every > 0 and iteration % every == 0


class TrainingCallback:
    """Base class: override the points you need (all do nothing by default)."""

    def on_start(self, run: RunState) -> None:
        """Before the first step."""

    def on_log(self, run: RunState, metrics: dict) -> None:
        """At a log step, with the metrics line being built."""

    def after_step(self, run: RunState) -> None:
        """After every step."""

    def on_end(self, run: RunState) -> None:
        """After the last step, before the final checkpoint."""


class HookCallback(TrainingCallback):
    """Training hooks (``hook(iteration, model, scene, cfg) -> dict``) at log steps.

    The model is in eval mode without gradient; the hooks' numbers join the metrics line,
    and their time is not training time (the clock is paused).
    """

    def __init__(self, hooks: Sequence[Hook]) -> None:
        self.hooks = list(hooks)

    def on_log(self, run: RunState, metrics: dict) -> None:
        if not self.hooks:
            return
        with run.clock.paused(), run.evaluating():
            for hook in self.hooks:
                metrics.update(hook(run.iteration, run.model, run.scene, run.cfg))


class MetricsFile(TrainingCallback):
    """Appends each metrics line to ``RUN/metrics.jsonl``."""

    def on_log(self, run: RunState, metrics: dict) -> None:
        append_line(run.run_dir, metrics)


class ProgressBar(TrainingCallback):
    """A tqdm bar with the loss, PSNR, s and iterations per second."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self.bar = None

    def on_start(self, run: RunState) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=run.cfg.train.iters, initial=run.iteration,
                        disable=not self.enabled, dynamic_ncols=True, desc="train")

    def after_step(self, run: RunState) -> None:
        self.bar.update(1)

    def on_log(self, run: RunState, metrics: dict) -> None:
        self.bar.total = run.end  # a budget run may have compressed its schedule
        self.bar.set_postfix(loss=f"{metrics['loss']:.4f}", psnr=f"{metrics['psnr']:.2f}",
                             inv_s=f"{metrics['inv_s']:.1f}", its=f"{metrics['its_per_s']:.1f}")

    def on_end(self, run: RunState) -> None:
        self.bar.close()


class Validation(TrainingCallback):
    """Every ``train.val_every`` steps: ground truth | colour | normals of one view, as a PNG
    ``RUN/validation/NNNNNNN_vVVV.png`` (VVV: the view's index in the full scene), and its
    PSNR as a line ``{"iter", "val_psnr", "val_view", "val_heldout"}`` of ``metrics.jsonl``.

    The views, taken in turn: the held-out ones (``train.holdout``), else up to
    `MAX_VIEWS` training views spread over the scene, so that each view's images form one
    series (one TensorBoard tag, ``validation/vVVV``, with a step slider). `sinks` get
    ``(step, tag, image)``, `scalar_sinks` ``(step, name, value)``.
    """

    MAX_VIEWS = 4

    def __init__(self, sinks: Sequence[Callable[[int, str, object], None]] = (),
                 scalar_sinks: Sequence[Callable[[int, str, float], None]] = ()) -> None:
        self.sinks = list(sinks)
        self.scalar_sinks = list(scalar_sinks)

    @classmethod
    def views(cls, run: RunState) -> list[tuple[object, int, int, bool]]:
        """(scene, index in it, index in the full scene, held out) of each validation view."""
        if run.heldout is not None:
            return [(run.heldout, i, v, True) for i, v in enumerate(run.views["heldout"])]
        n = run.scene.n_views
        picks = sorted({round(x) for x in np.linspace(0, n - 1, min(cls.MAX_VIEWS, n))})
        full = run.views.get("train") or list(range(n))
        return [(run.scene, i, full[i], False) for i in picks]

    def after_step(self, run: RunState) -> None:
        every = run.cfg.train.val_every
        if not step_check(run.iteration, every):
            return
        from neus_l0.render.views import psnr
        from neus_l0.train.validation import validation_image, write_png

        views = self.views(run)
        scene, i, view, held = views[(run.iteration // every) % len(views)]
        with run.evaluating():
            img = validation_image(run.model, scene, run.cfg, i, run.iteration,
                                   bounds=run.bounds, sampler=run.setup.sampler)
        write_png(run.run_dir / "validation" / f"{run.iteration:07d}_v{view:03d}.png", img,
                  within=run.run_dir)
        w = img.shape[1] // 3
        value = psnr(img[:, w:2 * w] / 255.0, img[:, :w] / 255.0)
        line = {"iter": run.iteration, "val_psnr": value, "val_view": view,
                "val_heldout": held}
        if scene.has_masks:  # the object alone: the background's error is not the surface's
            ds = max(1, run.cfg.train.val_downscale)
            fg = (scene.masks[i, ::ds, ::ds] > 0.5).cpu().numpy()
            line["val_psnr_mask"] = psnr(img[:, w:2 * w] / 255.0, img[:, :w] / 255.0, fg)
        append_line(run.run_dir, line)
        for sink in self.sinks:
            sink(run.iteration, f"validation/v{view:03d}", img)
        for sink in self.scalar_sinks:
            sink(run.iteration, "psnr_heldout" if held else "psnr", value)


class Checkpoints(TrainingCallback):
    """Every ``train.save_every`` steps, an atomic checkpoint."""

    def after_step(self, run: RunState) -> None:
        if step_check(run.iteration, run.cfg.train.save_every):
            run.save()


class Snapshots(TrainingCallback):
    """Checkpoints at loop-time marks (seconds of the training clock).

    When the clock first reaches a mark, a checkpoint is written and ``{"snapshot_s": mark,
    "iter": iteration, "elapsed": loop time}`` appended to ``metrics.jsonl``; marks the run
    does not reach are served by the final checkpoint. Writing them is not training time
    (the clock is paused; on CUDA the queued steps are waited for first, and counted), and
    their checkpoints are exempt from ``train.keep_checkpoints``.
    """

    def __init__(self, marks: Sequence[float]) -> None:
        self.marks = sorted(float(m) for m in marks)
        if not all(math.isfinite(m) and m >= 0 for m in self.marks):
            raise ValueError(f"snapshots {list(marks)}: marks must be finite seconds >= 0")
        self.taken: list[tuple[float, int, Path]] = []

    def on_start(self, run: RunState) -> None:
        if self.marks:
            run.protected |= {checkpoint_path(run.run_dir, int(m["iter"]))
                               for m in snapshot_lines(run.run_dir)}
            run.protect_snapshots = True

    def after_step(self, run: RunState) -> None:
        if len(self.taken) < len(self.marks) and run.clock.elapsed() >= self.marks[
                len(self.taken)]:
            run.wait_for_device()
            self._serve(run, final=False)

    def on_end(self, run: RunState) -> None:
        if len(self.taken) < len(self.marks):
            run.wait_for_device()
            self._serve(run, final=True)

    def _serve(self, run: RunState, final: bool) -> None:
        """Serve every pending mark up to now (all of them when `final`)."""
        elapsed = run.clock.elapsed()
        # the final checkpoint is written (and counted) with or without snapshots
        with contextlib.nullcontext() if final else run.clock.paused():
            path = checkpoint_path(run.run_dir, run.iteration)
            run.protected.add(path)  # before writing, so that its own pruning keeps it
            if run.last_checkpoint != path:
                run.save()
            while len(self.taken) < len(self.marks) and (
                    final or self.marks[len(self.taken)] <= elapsed):
                mark = self.marks[len(self.taken)]
                self.taken.append((mark, run.iteration, path))
                append_line(run.run_dir, {"snapshot_s": mark, "iter": run.iteration,
                                           "elapsed": elapsed})


class TensorBoard(TrainingCallback):
    """TensorBoard events in the run folder (``tensorboard --logdir RUN``): the losses,
    s, PSNR, learning rate, samples per ray, iterations per second, validation images."""

    #: The step's metrics (`neus_l0.train.step.METRIC_NAMES`, but the sample count, logged
    #: per ray) and the loop's learning rate and speed.
    SCALARS = (*(m for m in METRIC_NAMES if m != "samples"), "lr", "its_per_s")

    def __init__(self) -> None:
        self.logger = None

    def on_start(self, run: RunState) -> None:
        from neus_l0.train.tensorboard import TensorBoardLogger

        self.logger = TensorBoardLogger(run.run_dir, purge_step=run.iteration or None)
        _ = self.logger.writer  # import and open now: setup, not training time

    def on_log(self, run: RunState, metrics: dict) -> None:
        values = {k: metrics[k] for k in self.SCALARS if k in metrics}
        rays = metrics.get("rays") or run.rays
        values["samples_per_ray"] = metrics["samples"] / max(rays, 1)
        self.logger.scalars(run.iteration, values)

    def scalar(self, step: int, name: str, value: float) -> None:
        """A `Validation` scalar sink: ``validation/NAME``."""
        if self.logger is not None:
            self.logger.scalars(step, {name: value}, prefix="validation/")

    def image(self, step: int, tag: str, rgb) -> None:
        """A `Validation` sink."""
        if self.logger is not None:
            self.logger.image(step, tag, rgb)

    def on_end(self, run: RunState) -> None:
        self.logger.close()
