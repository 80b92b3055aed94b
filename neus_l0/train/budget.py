"""`train.budget`: the arithmetic of a run that must end within a given time (pure).

A budget run (`neus_l0.train.loop`) measures, after the compile, what a step, a validation
render and a checkpoint cost (`StepCosts`, `neus_l0.train.probe`), then:

* `plan_iterations`: how many iterations fit in what is left of the budget, less the
  validations and checkpoints the schedule holds and a reserve for the final checkpoint;
* `planned_config`: the config with that `train.iters` and the schedule's landmarks
  (`warm_up`, `anneal_end`, the hash grid's `update_steps`, `val_every`, `save_every`)
  scaled to keep their fraction of the run, recorded with ``budget: 0`` (re-running it
  trains the same schedule);
* while it runs, `retarget_end` shortens the rest of the schedule when the steps slow down
  (another job starts), or lengthens it when they speed up, and `ScheduleWarp` maps the
  real iteration to the iteration of the recorded schedule, so that the learning rate, the
  anneal and the hash-grid levels still finish, compressed, instead of being cut off.

The capacity ladder (`LADDER`) picks rays, samples and the hash grid per budget for the
device's default setting.
"""

from __future__ import annotations

import dataclasses
import math

from neus_l0.config.schema import Config

#: Fraction of the time left for steps that the plan leaves unused (rate noise).
MARGIN = 0.025
#: Seconds kept for the end besides the final checkpoint's measured cost: closing the run
#: (events, budget.json) and the interpreter's exit with torch loaded.
RESERVE_S = 3.0
#: Fewest iterations a plan may have.
MIN_ITERS = 20
@dataclasses.dataclass(frozen=True)
class StepCosts:
    """Measured seconds: one training step, one validation render, one checkpoint."""

    step_s: float
    val_s: float = 0.0
    ckpt_s: float = 0.0


@dataclasses.dataclass(frozen=True)
class Plan:
    """What a budget bought.

    Attributes:
        budget_s: the budget; spent_s: already spent when planning (start-up, compile,
            the measured steps); iters: the planned iterations; costs: the measurements;
        overhead_s: the validations, checkpoints and reserve set aside; most: the ceiling
            on the iterations (0: none; ``train.budget_up_to_iters``).
    """

    budget_s: float
    spent_s: float
    iters: int
    costs: StepCosts
    overhead_s: float
    most: int = 0

    @property
    def spare_s(self) -> float:
        """Seconds the plan leaves unused: `MARGIN` of the time for steps (a plan the
        ceiling `most` cut leaves more unused; its spare is still the margin, so that a
        re-target fills the budget less the margin)."""
        free = self.budget_s - self.spent_s - self.overhead_s
        unused = free - self.iters * self.costs.step_s
        if 0 < self.most == self.iters:
            unused = min(unused, MARGIN * free + self.costs.step_s)
        return max(0.0, unused)

    @property
    def estimated_s(self) -> float:
        """The run's planned end-to-end seconds."""
        return self.spent_s + self.iters * self.costs.step_s + self.overhead_s

    def line(self, setting: str) -> str:
        """One line: what the budget bought."""
        return (f"budget {self.budget_s:.0f} s buys {self.iters} iterations of {setting} "
                f"({1000 * self.costs.step_s:.1f} ms a step, measured after "
                f"{self.spent_s:.1f} s of start-up and compile; "
                f"{self.overhead_s:.1f} s kept for validation and checkpoints)")


def plan_iterations(budget_s: float, spent_s: float, costs: StepCosts, n_val: int,
                    n_ckpt: int, most: int = 0) -> Plan:
    """The iterations that fit in `budget_s` when `spent_s` is gone.

    Args:
        n_val, n_ckpt: validations and checkpoints the planned schedule holds (their number
            does not depend on the iterations: the landmarks scale with them); the final
            checkpoint is always added.
        most: plan no more than this many (0: no ceiling).

    Returns:
        a `Plan`; its ``iters`` is 0 when not even `MIN_ITERS` (or `most`, if fewer) fit.
    """
    overhead = n_val * costs.val_s + (n_ckpt + 1) * costs.ckpt_s + RESERVE_S
    left = (budget_s - spent_s - overhead) * (1.0 - MARGIN)
    fit = int(left // costs.step_s) if costs.step_s > 0 and left > 0 else 0
    least = min(MIN_ITERS, most) if most > 0 else MIN_ITERS
    iters = min(fit, most) if most > 0 else fit
    return Plan(budget_s, spent_s, iters if fit >= least else 0, costs, overhead, most)


def event_counts(cfg: Config) -> tuple[int, int]:
    """(validations, intermediate checkpoints) of `cfg`'s schedule."""
    t = cfg.train
    n_val = t.iters // t.val_every if t.val_every else 0
    n_ckpt = t.iters // t.save_every if t.save_every else 0
    return n_val, n_ckpt


def _scaled(value: int, ratio: float, least: int) -> int:
    return max(least, round(value * ratio)) if value > 0 else value


def planned_config(cfg: Config, iters: int) -> Config:
    """`cfg` with `iters` iterations and its landmarks at the same fractions of the run.

    Scaled: ``train.warm_up``, ``train.anneal_end``, ``train.lr_decay_iters`` (when set),
    ``train.val_every``, ``train.save_every`` and the SDF hash grid's ``update_steps`` (at
    least 1 where they were on); ``train.budget`` and ``train.max_seconds`` become 0 (the plan
    is the schedule). A shorter plan compresses the schedule too: stopping part-way down the
    config's own (tried in session 11) scored within seed noise on the tuning scenes and worse
    on the held-out cup (docs/BENCHMARKS.md, "What does a --budget buy").
    """
    t = cfg.train
    r = iters / t.iters
    train = dataclasses.replace(
        t, iters=iters, warm_up=_scaled(t.warm_up, r, 1), anneal_end=_scaled(t.anneal_end, r, 1),
        lr_decay_iters=_scaled(t.lr_decay_iters, r, 1),
        val_every=_scaled(t.val_every, r, 1), save_every=_scaled(t.save_every, r, 1),
        budget=0.0, max_seconds=0.0, budget_up_to_iters=False)
    enc = cfg.model.sdf.encoding
    enc = dataclasses.replace(enc, update_steps=_scaled(enc.update_steps, r, 1))
    sdf = dataclasses.replace(cfg.model.sdf, encoding=enc)
    model = dataclasses.replace(cfg.model, sdf=sdf)
    return dataclasses.replace(cfg, train=train, model=model)


@dataclasses.dataclass(frozen=True)
class ScheduleWarp:
    """Real iteration -> iteration of the recorded schedule (piecewise linear).

    Attributes:
        base: the recorded schedule's length (`train.iters`).
        end: where the run ends (``base`` until a retarget shortens it).
        knots: ``(real, virtual)`` pairs where a retarget bent the map, ``((0, 0),)`` first;
            after the last knot the map runs straight to ``(end, base)``.
    """

    base: int
    end: int
    knots: tuple[tuple[int, float], ...] = ((0, 0.0),)

    @property
    def warped(self) -> bool:
        """Whether the map is not the identity."""
        return self.end != self.base

    def at(self, iteration: int) -> float:
        """The recorded schedule's iteration at real `iteration` (`base` from `end` on)."""
        if not self.warped:
            return float(iteration)
        points = [*self.knots, (self.end, float(self.base))]
        for (i0, v0), (i1, v1) in zip(points, points[1:], strict=False):
            if iteration < i1:
                return v0 + (iteration - i0) * (v1 - v0) / max(1, i1 - i0)
        return float(self.base)

    def retarget(self, iteration: int, end: int) -> ScheduleWarp:
        """The map that is unchanged up to `iteration` and reaches `base` at `end`."""
        return ScheduleWarp(self.base, max(end, iteration + 1), self._bent_at(iteration))

    def ended(self, iteration: int) -> ScheduleWarp:
        """The map of a run that ends at `iteration` (a budget's deadline stopped it there):
        unchanged before it, with the run's end at it, so that a resume finds it finished."""
        return ScheduleWarp(self.base, iteration, self._bent_at(iteration))

    def _bent_at(self, iteration: int) -> tuple[tuple[int, float], ...]:
        return (*[k for k in self.knots if k[0] < iteration], (iteration, self.at(iteration)))

    def to_dict(self) -> dict:
        return {"base": self.base, "end": self.end, "knots": [list(k) for k in self.knots]}

    @classmethod
    def from_dict(cls, data: dict) -> ScheduleWarp:
        return cls(int(data["base"]), int(data["end"]),
                   tuple((int(i), float(v)) for i, v in data["knots"]))


def retarget_end(iteration: int, end: int, left_s: float, step_s: float,
                 spare_s: float, most: int = 0) -> int | None:
    """A new end when the rest of the schedule would eat more than half the plan's spare
    time (`Plan.spare_s`) or leave more than twice it unused.

    Args:
        iteration: now; end: the current end; left_s: seconds left for steps (the budget
            less the time spent and the reserve); step_s: the recent seconds per iteration
            (including the loop's logging, validation and checkpoints); spare_s: the
            seconds the plan left unused; most: no end past this (0: no ceiling).

    Returns:
        the end that fills `left_s` less `spare_s` at `step_s` (at most `most`), or None
        when the rest fits or the run is at its end.
    """
    need = (end - iteration) * step_s
    if step_s <= 0 or end - iteration <= 1:
        return None
    if left_s - 2.0 * spare_s <= need <= left_s - 0.5 * spare_s:
        return None
    new = iteration + max(1, math.floor((left_s - spare_s) / step_s))
    if most > 0:
        new = min(new, most)
    return new if new != end else None


@dataclasses.dataclass(frozen=True)
class Rung:
    """One step of the capacity ladder: from `from_s` of budget on, these overrides."""

    from_s: float
    overrides: tuple[str, ...]


#: The default setting per device and its capacity per budget (rays, samples, hash grid);
#: the iterations come from the plan. First choice from docs/BENCHMARKS.md (demo's 16+16
#: samples and grid on the CPU, fast on CUDA); its tuning is the campaign of
#: docs/BENCHMARKS.md, "Chamfer against budget".
LADDER: dict[str, tuple[str, tuple[Rung, ...]]] = {
    "cpu": ("demo", (
        Rung(0.0, ()),
        Rung(600.0, ("train.batch_size=256",)),
    )),
    "cuda": ("fast", (
        Rung(0.0, ("train.batch_size=2048",)),
        Rung(180.0, ()),
    )),
}


def default_setting(device: str, budget_s: float = 0.0) -> tuple[str, tuple[str, ...]]:
    """The device's default config name and the ladder's overrides for `budget_s` (none
    without a budget)."""
    name, rungs = LADDER["cuda" if device == "cuda" else "cpu"]
    if budget_s <= 0:
        return name, ()
    chosen = [r for r in rungs if budget_s >= r.from_s]
    return name, chosen[-1].overrides if chosen else ()
