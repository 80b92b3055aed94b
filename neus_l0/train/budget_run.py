"""A budget run's plan and its keeper, and the duration estimate of any run.

`plan_run` measures the run's costs after the compile (`neus_l0.train.probe`, undone
after), fixes the plan (`neus_l0.train.budget`), sets it on the run and says in one line
what the budget bought. `BudgetKeeper` then watches the step rate at every log step,
compresses the rest of the schedule when the steps slow down (stretches it when they speed
up), stops the run at the
deadline as a last resort, and writes ``RUN/budget.json``. `EstimateLine` measures the
step of a run without a budget on its first steps and prints the expected duration when it
is over half an hour.
"""

from __future__ import annotations

import dataclasses
import sys
import time

from neus_l0.atomic import atomic_write_json
from neus_l0.errors import NeusL0Error
from neus_l0.run.checkpoints import checkpoint_path
from neus_l0.train.budget import (
    RESERVE_S,
    Plan,
    ScheduleWarp,
    event_counts,
    plan_iterations,
    planned_config,
    retarget_end,
)
from neus_l0.train.callbacks import TrainingCallback
from neus_l0.train.probe import measure_costs
from neus_l0.train.state import RunState

#: Runs expected to take longer than this get a line with their estimate.
LONG_RUN_S = 1800.0


def _say(line: str) -> None:
    print(f"neus-l0: {line}", file=sys.stderr, flush=True)


def _hms(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.1f} min" if seconds >= 120 else f"{seconds:.0f} s"


def describe_setting(run: RunState) -> str:
    """Rays, samples and the SDF's encoding of the run, in a few words."""
    c = run.cfg
    enc = c.model.sdf.encoding
    sdf = (f"hash grid {enc.n_levels}x{enc.n_features} to {enc.finest_resolution}, "
           f"2^{enc.log2_hashmap_size}" if enc.kind == "hashgrid" else f"{enc.kind} encoding")
    return (f"{c.train.batch_size} rays x {c.render.n_samples}+{c.render.n_importance} "
            f"samples, {sdf}, SDF MLP {c.model.sdf.layers}x{c.model.sdf.hidden}")


class BudgetTooShort(NeusL0Error):
    """The budget does not leave room for `neus_l0.train.budget.MIN_ITERS` steps.

    Attributes:
        spent_s: what start-up and compile took (seconds, counted from the budget's start
            handed to `train`); step_s: a step's measured seconds; need_s: the least budget
            (from that same start) that would have trained.
    """

    def __init__(self, spent_s: float, step_s: float, need_s: float) -> None:
        self.spent_s, self.step_s, self.need_s = spent_s, step_s, need_s
        super().__init__(self.line("train.budget", 0.0))

    def line(self, given: str, before_s: float) -> str:
        """One line naming the budget as the user gave it (`given`), with `before_s`
        seconds spent before `train` started added to the times."""
        return (f"{given}: too short: start-up and compile took "
                f"{before_s + self.spent_s:.0f} s and a step {1000 * self.step_s:.0f} ms; give "
                f"at least {before_s + self.need_s:.0f} s")


def plan_run(run: RunState, started: float) -> BudgetKeeper:
    """Measure, plan and set the plan on `run` (its config, hash-grid level steps).

    Args:
        started: `time.monotonic()` when the budget started.

    Raises:
        NeusL0Error: the budget does not leave room for `neus_l0.train.budget.MIN_ITERS`.
    """
    budget = run.cfg.train.budget
    costs = measure_costs(run, seconds=min(3.0, max(0.5, 0.01 * budget)))
    most = run.cfg.train.iters if run.cfg.train.budget_up_to_iters else 0
    plan = plan_iterations(budget, time.monotonic() - started, costs, *event_counts(run.cfg),
                           most=most)
    if plan.iters == 0:
        raise BudgetTooShort(plan.spent_s, costs.step_s,
                             plan.spent_s + plan.overhead_s + 50 * costs.step_s)
    run.cfg = planned_config(run.cfg, plan.iters)
    enc = run.cfg.model.sdf.encoding
    grid = getattr(run.model.sdf, "encoding", None)
    if hasattr(grid, "set_update_steps"):
        grid.set_update_steps(enc.update_steps)
    run.setup.warp = ScheduleWarp(plan.iters, plan.iters)
    _say(plan.line(describe_setting(run)))
    return BudgetKeeper(plan, started)


class BudgetKeeper(TrainingCallback):
    """Keeps a planned run within its budget (see the module docstring)."""

    def __init__(self, plan: Plan, started: float, window: int = 3) -> None:
        self.plan, self.started, self.window = plan, started, window
        self.marks: list[tuple[float, int]] = []
        self.retargets: list[dict] = []
        self.said = 0  # the end the last printed re-target set
        self.deadline: int | None = None  # the iteration the deadline stopped the run at
        self.run: RunState | None = None

    def spent(self) -> float:
        """Seconds of the budget spent: the wall-clock since the start, less the time the
        loop's clock was paused (measurement hooks and snapshots of `neus-l0 bench`, which
        are not the run's: counted, their first calls looked like slow steps and squeezed
        the schedule)."""
        paused = self.run.clock.paused_s if self.run is not None else 0.0
        return time.monotonic() - self.started - paused

    def left_for_steps(self) -> float:
        """Seconds left before the end's reserve (final checkpoint)."""
        return self.plan.budget_s - self.spent() - self.plan.costs.ckpt_s - RESERVE_S

    def on_start(self, run: RunState) -> None:
        self.run = run
        self.marks = [(self.spent(), run.iteration)]
        self._write(run, None)

    def on_log(self, run: RunState, metrics: dict) -> None:
        self.marks = (self.marks + [(self.spent(), run.iteration)])[-(self.window + 1):]
        (t0, i0), (t1, i1) = self.marks[0], self.marks[-1]
        if len(self.marks) <= self.window or i1 <= i0:
            return  # judge the rate over `window` log intervals
        step_s = (t1 - t0) / (i1 - i0)
        end = retarget_end(run.iteration, run.end, self.left_for_steps(), step_s,
                           self.plan.spare_s, self.plan.most)
        if end is None:
            return
        was = run.end
        run.setup.warp = run.setup.warp.retarget(run.iteration, end)
        self.retargets.append({"iter": run.iteration, "end": end, "was": was,
                               "step_s": round(step_s, 5)})
        if self.said and abs(end - self.said) < 0.1 * self.said:
            return  # budget.json has every re-target; the terminal the large ones
        self.said = end
        how = "compressed" if end < was else "stretched"
        _say(f"steps now take {1000 * step_s:.1f} ms (planned "
             f"{1000 * self.plan.costs.step_s:.1f}): the rest of the schedule is {how} "
             f"to end at iteration {end} (was {was})")

    def after_step(self, run: RunState) -> None:
        if self.left_for_steps() <= 0 and run.iteration < run.end:
            run.stop_requested = True
            self.deadline = run.iteration

    def on_end(self, run: RunState) -> None:
        """Write budget.json; a run the deadline stopped ends there: its schedule's end
        moves to the stop (``"deadline": true`` in the re-targets) and its last checkpoint
        holds that, so that a re-run reuses it as finished. A run a signal stopped keeps
        its end and resumes."""
        if self.deadline is not None and self.deadline == run.iteration < run.end:
            self.retargets.append({"iter": run.iteration, "end": run.iteration,
                                   "was": run.end, "deadline": True})
            run.setup.warp = run.setup.warp.ended(run.iteration)
            if run.last_checkpoint == checkpoint_path(run.run_dir, run.iteration):
                run.save()  # written before the schedule ended: again, with the end
        self._write(run, run.iteration)

    def _write(self, run: RunState, done: int | None) -> None:
        p = self.plan
        atomic_write_json(run.run_dir / "budget.json", {
            "budget_s": p.budget_s, "spent_before_steps_s": round(p.spent_s, 2),
            "planned_iters": p.iters, "most_iters": p.most or None,
            "costs": dataclasses.asdict(p.costs),
            "estimated_s": round(p.estimated_s, 2), "retargets": self.retargets,
            "done_iters": done, "steps_end_s": round(self.spent(), 2) if done else None},
            within=run.run_dir)


class EstimateLine(TrainingCallback):
    """The run's duration, measured on its first steps after the first one (the compile):
    written to ``RUN/estimate.json`` and printed when over `LONG_RUN_S`."""

    def __init__(self, steps: int = 3, seconds: float = 2.0) -> None:
        self.steps, self.seconds = steps, seconds
        self.first: tuple[float, int] | None = None
        self.done = False

    def after_step(self, run: RunState) -> None:
        if self.done:
            return
        run.wait_for_device()
        now = run.clock.elapsed()
        if self.first is None:
            self.first = (now, run.iteration)
            return
        t0, i0 = self.first
        n = run.iteration - i0
        if n < self.steps or (now - t0 < self.seconds and n < 50):
            return
        self.done = True
        step_s = (now - t0) / n
        total = now + (run.end - run.iteration) * step_s
        atomic_write_json(run.run_dir / "estimate.json", {
            "iter": run.iteration, "step_s": round(step_s, 5), "measured_steps": n,
            "loop_s_now": round(now, 2), "estimated_loop_s": round(total, 2)},
            within=run.run_dir)
        if total > LONG_RUN_S:
            _say(f"this run should take about {_hms(total)} ({run.end - run.iteration} "
                 f"iterations left at {step_s:.2f} s a step, measured on {n} steps); "
                 f"--budget 30m (or any time) fits the schedule to a time")
