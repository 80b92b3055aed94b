"""Timed steps that leave no trace: measure what a step, a validation render and a
checkpoint cost on the run itself, then put the run's state back.

The training state (networks, optimiser, generator, occupancy grid, scaler, ray count) is
copied before and restored after, so the run then trains exactly as if nothing had been
measured (a budget run's plan, `train.compile: auto`'s eager step).
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

from neus_l0.atomic import atomic_torch_save
from neus_l0.fields.linear import clear_weight_cache
from neus_l0.run.checkpoints import restore_training
from neus_l0.train.budget import StepCosts
from neus_l0.train.state import RunState
from neus_l0.train.step import train_step


def _steps(run: RunState, n: int, first: int) -> None:
    for k in range(n):
        train_step(run.model, run.optimizer, run.scene, run.cfg, first + k, run.generator,
                   occupancy=run.occupancy, scaler=run.scaler, batch_size=run.rays,
                   setup=run.setup)


def time_steps(run: RunState, warm: int = 1, most: int = 20, seconds: float = 2.0) -> float:
    """Mean seconds of a training step, the run's state restored after.

    Args:
        warm: untimed steps first (the first call of a compiled step compiles).
        most: at most this many timed steps; timing stops earlier once `seconds` passed
            (at least one timed step).
    """
    saved = copy.deepcopy(run.checkpoint_state())
    try:
        _steps(run, warm, run.iteration)
        run.wait_for_device()
        t0, n = time.monotonic(), 0
        while n < most and (n == 0 or time.monotonic() - t0 < seconds):
            _steps(run, 1, run.iteration + warm + n)
            n += 1
            run.wait_for_device()
        return (time.monotonic() - t0) / n
    finally:
        restore_training(Path("(measured steps)"), saved, run.model, run.optimizer,
                         run.generator, run.scaler, run.occupancy)
        run.rays = int(saved["batch_size"])
        clear_weight_cache(run.model)


def validation_seconds(run: RunState) -> float:
    """Seconds of one validation render (0 when `train.val_every` is 0)."""
    if not run.cfg.train.val_every:
        return 0.0
    from neus_l0.train.validation import validation_image

    t0 = time.monotonic()
    with run.evaluating():
        validation_image(run.model, run.scene, run.cfg, 0, run.iteration, bounds=run.bounds,
                         sampler=run.setup.sampler)
    run.wait_for_device()
    return time.monotonic() - t0


def checkpoint_seconds(run: RunState) -> float:
    """Seconds to write one checkpoint (a scratch file in the run folder, removed)."""
    path = run.run_dir / ".budget_probe.pt"
    t0 = time.monotonic()
    try:
        atomic_torch_save(path, run.checkpoint_state(), within=run.run_dir)
        return time.monotonic() - t0
    finally:
        path.unlink(missing_ok=True)


def measure_costs(run: RunState, seconds: float = 2.0) -> StepCosts:
    """A step (after the compile), a validation render and a checkpoint, measured."""
    step = time_steps(run, warm=2, most=50, seconds=seconds)
    return StepCosts(step, validation_seconds(run), checkpoint_seconds(run))
