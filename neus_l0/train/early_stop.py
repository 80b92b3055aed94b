"""`train.early_stop`: end the run when the surface stops moving (off by default).

The probe: fixed points drawn once in the unit sphere; at every check the SDF is evaluated
at them, and the surface's movement is the median |SDF change| since the last check over
the points near the surface (|SDF| < `band`), in units of `band`. `Plateau` (pure) says
when that movement stayed under `tolerance` for `patience` checks in a row. The run then
does not stop dead: the rest of its schedule is compressed into `finish` of its length
(`neus_l0.train.budget.ScheduleWarp`), so the learning rate still decays, and one line
says so.
"""

from __future__ import annotations

import dataclasses
import sys

import torch
from torch import Tensor

from neus_l0.train.budget import ScheduleWarp
from neus_l0.train.callbacks import TrainingCallback
from neus_l0.train.state import RunState


@dataclasses.dataclass
class Plateau:
    """Whether a sequence of movements has flattened (pure).

    Attributes:
        tolerance: a movement under this counts as still; patience: checks in a row;
        least_checks: no verdict before this many movements (the early surface moves).
    """

    tolerance: float = 0.02
    patience: int = 3
    least_checks: int = 5
    seen: int = 0
    still: int = 0

    def update(self, movement: float) -> bool:
        """Add one movement; True once the surface has been still `patience` times."""
        self.seen += 1
        self.still = self.still + 1 if movement < self.tolerance else 0
        return self.seen >= self.least_checks and self.still >= self.patience


def surface_movement(before: Tensor, after: Tensor, band: float) -> float:
    """Median |after - before| / band over the points with |after| < band.

    Args:
        before, after: (N,) SDF values at the probe points at two checks.

    Returns:
        the movement; inf when no point is near the surface (nothing to judge yet).
    """
    near = after.abs() < band
    if not bool(near.any()):
        return float("inf")
    return float(((after - before).abs()[near]).median() / band)


class EarlyStop(TrainingCallback):
    """The probe at every `every`-th log step (see the module docstring)."""

    def __init__(self, points: int = 4096, every: int = 4, band: float = 0.05,
                 finish: float = 0.05) -> None:
        self.n, self.every, self.band, self.finish = points, every, band, finish
        self.plateau = Plateau()
        self.points: Tensor | None = None
        self.last: Tensor | None = None
        self.logs = 0
        self.fired = False

    def on_start(self, run: RunState) -> None:
        g = torch.Generator().manual_seed(run.cfg.train.seed + 1)
        p = torch.randn(self.n, 3, generator=g)
        r = torch.rand(self.n, 1, generator=g) ** (1 / 3)
        self.points = (p / p.norm(dim=1, keepdim=True) * r).to(run.device)

    def on_log(self, run: RunState, metrics: dict) -> None:
        self.logs += 1
        if self.logs % self.every:
            return
        with run.evaluating():
            sdf = run.model.sdf.sdf(self.points).reshape(-1).float()
        if self.last is not None:
            moved = surface_movement(self.last, sdf, self.band)
            metrics["surface_moved"] = moved
            if self.plateau.update(moved) and not self.fired:
                self.fired = True
                self._finish(run)
        self.last = sdf

    def _finish(self, run: RunState) -> None:
        warp = run.setup.warp or ScheduleWarp(run.cfg.train.iters, run.cfg.train.iters)
        end = run.iteration + max(1, round(self.finish * warp.base))
        if end >= warp.end:
            return
        run.setup.warp = warp.retarget(run.iteration, end)
        print(f"neus-l0: the surface stopped moving at iteration {run.iteration} "
              f"(train.early_stop): the schedule now ends at {end} (was {warp.end})",
              file=sys.stderr, flush=True)
