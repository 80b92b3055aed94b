"""A budget counts the run's own time: what the loop's clock spends paused (the bench's
measurement hooks, snapshots) is not charged to it, so the keeper neither shortens the plan
for it nor takes it for slow steps."""

import dataclasses

import pytest

from neus_l0.train import budget_run
from neus_l0.train.budget import Plan, ScheduleWarp, StepCosts
from neus_l0.train.budget_run import BudgetKeeper
from neus_l0.train.state import Clock


@dataclasses.dataclass
class _Setup:
    warp: ScheduleWarp


@dataclasses.dataclass
class _Run:
    clock: Clock
    setup: _Setup
    iteration: int = 0
    end: int = 1000
    run_dir: object = None


class _Time:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


@pytest.fixture
def fake_time(monkeypatch):
    t = _Time()
    monkeypatch.setattr(budget_run.time, "monotonic", t)
    monkeypatch.setattr("neus_l0.train.state.time.monotonic", t)
    return t


def _keeper(monkeypatch, fake_time):
    plan = Plan(budget_s=20.0, spent_s=0.0, iters=1000, costs=StepCosts(0.01), overhead_s=3.0)
    keeper = BudgetKeeper(plan, started=fake_time.now)
    monkeypatch.setattr(keeper, "_write", lambda run, done: None)
    run = _Run(Clock(), _Setup(ScheduleWarp(1000, 1000)))
    keeper.on_start(run)
    return keeper, run


def test_paused_time_is_not_spent(monkeypatch, fake_time):
    keeper, run = _keeper(monkeypatch, fake_time)
    fake_time.now += 2.0
    with run.clock.paused():
        fake_time.now += 5.0  # a hook measuring for 5 s
    assert keeper.spent() == pytest.approx(2.0)
    assert run.clock.paused_s == pytest.approx(5.0)


def test_a_slow_hook_at_the_first_logs_does_not_retarget(monkeypatch, fake_time):
    """Steps at the planned 10 ms and a 1.5 s hook at every log: no retarget (counted, the
    hook made the steps look 4x slower and the schedule was squeezed)."""
    keeper, run = _keeper(monkeypatch, fake_time)
    for _ in range(6):
        fake_time.now += 50 * 0.01
        run.iteration += 50
        with run.clock.paused():
            fake_time.now += 1.5
        keeper.on_log(run, {})
    assert keeper.retargets == [] and run.setup.warp.end == 1000
