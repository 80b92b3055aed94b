"""The run's state that the loop and its callbacks share, and the training clock."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from neus_l0.bounds.error_map import map_state
from neus_l0.bounds.occupancy import OccupancyGrid
from neus_l0.bounds.spans import join_bounds
from neus_l0.config.load import to_dict
from neus_l0.config.schema import Config
from neus_l0.data.scene import Scene
from neus_l0.device import synchronize
from neus_l0.fields.model import NeuSModel
from neus_l0.run.checkpoints import (
    checkpoint_path,
    prune_checkpoints,
    rng_state,
    save_checkpoint,
)
from neus_l0.train.step import (
    StepSetup,
)


class Clock:
    """Training time: the wall-clock since `start`, less the spans run in `paused()`."""

    def __init__(self) -> None:
        self.start = time.monotonic()
        self._paused = 0.0

    def elapsed(self) -> float:
        """Seconds of training time so far."""
        return time.monotonic() - self.start - self._paused

    @property
    def paused_s(self) -> float:
        """Seconds spent in `paused()` so far (measurement hooks, snapshots)."""
        return self._paused

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Time spent inside does not count."""
        t0 = time.monotonic()
        try:
            yield
        finally:
            self._paused += time.monotonic() - t0


@dataclasses.dataclass
class RunState:
    """The run's state, which the loop and its callbacks share (built by `build_run_state`)."""

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
    good_checkpoint: Path | None = None  # while the watchdog suspects the run
    diverged: bool = False
    fingerprint: str = ""  # the scene's (`neus_l0.train.preflight.scene_fingerprint`)
    stop_requested: bool = False  # a callback asks the loop to stop (a budget's deadline)
    heldout: Scene | None = None  # the views kept out of training (train.holdout)
    views: dict = dataclasses.field(default_factory=dict)  # `holdout_split`'s record

    @property
    def end(self) -> int:
        """The iteration the run ends at: `train.iters`, or sooner when a budget run
        compressed its schedule (`StepSetup.warp`)."""
        warp = self.setup.warp
        return warp.end if warp is not None else self.cfg.train.iters

    @property
    def device(self) -> torch.device:
        return self.scene.device

    @property
    def bounds(self) -> tuple:
        """Everything that narrows the rays: the setup's bounds, then the grid."""
        return join_bounds(self.setup.bounds, self.occupancy)

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

    def checkpoint_state(self) -> dict:
        """The checkpoint of the current iteration (see `neus_l0.run.checkpoints`)."""
        state = {
            "iteration": self.iteration,
            "batch_size": self.rays,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": rng_state(self.generator),
            "config": to_dict(self.cfg),
            "scale_mat": np.asarray(self.scene.scale_mat).tolist(),
            "has_background": self.model.background is not None,
            "scene_fingerprint": self.fingerprint,
        }
        if self.setup.warp is not None and self.setup.warp.warped:
            state["schedule"] = self.setup.warp.to_dict()
        if self.cfg.model.color.view_warmup > 0:  # rendering from it uses the same weight
            state["view_scale"] = float(self.model.color.view_scale)
        if self.occupancy is not None:
            state["occupancy"] = self.occupancy.state_dict()
        if self.setup.pool is not None and self.setup.pool.error_map is not None:
            state["error_map"] = map_state(self.setup.pool.error_map)
        if self.scaler.is_enabled():
            state["scaler"] = self.scaler.state_dict()
        return state

    def save(self) -> Path | None:
        """Write the checkpoint of this iteration and prune the old ones, never the
        snapshots' nor, while the run is suspect, the last good one (`good_checkpoint`). A
        diverged run writes nothing more."""
        if self.diverged:
            return self.last_checkpoint
        path = checkpoint_path(self.run_dir, self.iteration)
        keep = self.cfg.train.keep_checkpoints
        if not (self.protect_snapshots or self.good_checkpoint):
            self.last_checkpoint = save_checkpoint(path, self.checkpoint_state(), keep=keep)
        else:
            self.last_checkpoint = save_checkpoint(path, self.checkpoint_state(), keep=0)
            good = {self.good_checkpoint} if self.good_checkpoint else set()
            prune_checkpoints(self.run_dir, keep, self.protected | good | {path})
        return self.last_checkpoint
