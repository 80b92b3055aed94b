"""The budget's arithmetic (`neus_l0.train.budget`) on a fake clock, durations, and a
budget run's recorded schedule reproduced by a resume and by a re-run."""

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.duration import parse_seconds
from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError
from neus_l0.run.checkpoints import latest_checkpoint, load_checkpoint
from neus_l0.train.budget import (
    MARGIN,
    RESERVE_S,
    ScheduleWarp,
    StepCosts,
    default_setting,
    event_counts,
    plan_iterations,
    planned_config,
    retarget_end,
)
from neus_l0.train.loop import train
from neus_l0.train.schedule import lr_factor


@pytest.mark.parametrize("text, seconds", [("240", 240), ("90s", 90), ("10m", 600),
                                           ("1h", 3600), ("1.5h", 5400), (30, 30)])
def test_durations(text, seconds):
    assert parse_seconds(text, "--budget") == seconds


@pytest.mark.parametrize("bad", ["0", "-5", "abc", "1e9", "10 parsecs", -5, float("nan")])
def test_bad_budgets_get_one_line_naming_the_flag(bad):
    with pytest.raises(ConfigError) as err:
        parse_seconds(bad, "--budget", allow_zero=False)
    assert str(err.value).startswith("--budget: ") and "\n" not in str(err.value)


def test_the_plan_fits_the_time_left():
    costs = StepCosts(step_s=0.1, val_s=1.0, ckpt_s=0.5)
    plan = plan_iterations(240.0, 30.0, costs, n_val=7, n_ckpt=3)
    overhead = 7 * 1.0 + 4 * 0.5 + RESERVE_S
    assert plan.overhead_s == pytest.approx(overhead)
    assert plan.iters == int((240 - 30 - overhead) * (1 - MARGIN) / 0.1)
    assert plan.estimated_s <= 240.0
    assert "buys" in plan.line("demo")
    assert plan_iterations(10.0, 9.0, costs, 0, 0).iters == 0  # nothing fits: refused


def test_the_planned_config_keeps_its_landmarks_fractions():
    cfg = load_config("demo", ["train.anneal_end=700"])
    out = planned_config(cfg, 7000)  # twice demo's 3500
    t = out.train
    assert (t.iters, t.warm_up, t.anneal_end) == (7000, 200, 1400)
    assert (t.val_every, t.save_every) == (1000, 2000)
    assert out.model.sdf.encoding.update_steps == 200
    assert t.budget == 0 and t.max_seconds == 0  # the plan is the schedule
    assert event_counts(out) == event_counts(cfg)
    assert planned_config(cfg, 35).train.val_every == 5  # scaled, never switched off


def test_a_shorter_plan_compresses_the_configs_curve():
    """Below the config's length the schedule is compressed too: the landmarks keep their
    fraction and the learning rate reaches alpha at the plan's end."""
    cfg = load_config("demo", ["train.anneal_end=700"])  # 3500 iterations, warm-up 100
    t = planned_config(cfg, 2000).train
    assert (t.iters, t.warm_up, t.anneal_end, t.lr_decay_iters) == (2000, 57, 400, 0)
    assert (t.val_every, t.save_every) == (286, 571)  # events keep their number
    assert lr_factor(2000, t.warm_up, t.lr_decay_iters or t.iters, t.lr_alpha) == \
        pytest.approx(cfg.train.lr_alpha)
    assert planned_config(cfg, 35).train.warm_up == 1  # never switched off by rounding
    set_decay = planned_config(load_config("demo", ["train.lr_decay_iters=7000"]), 1750)
    assert set_decay.train.lr_decay_iters == 3500  # a set decay length scales with the plan


@settings(max_examples=60, deadline=None)
@given(st.integers(1000, 20000), st.floats(0.0, 1.0))  # warm-up of 25+ iterations: rounding < 2 %
def test_the_planned_learning_rate_is_the_configs_curve_at_the_mapped_iteration(iters, frac):
    """For any plan, the lr at a fraction of the planned run is the config's lr at the same
    fraction of its length."""
    cfg = load_config("demo", ["train.warm_up=100"])
    c, t = cfg.train, planned_config(cfg, iters).train
    i = frac * iters
    got = lr_factor(i, t.warm_up, t.lr_decay_iters or t.iters, t.lr_alpha)
    # the same fraction of the config's run (the warm-up rounds to whole iterations)
    want = lr_factor(frac * c.iters, c.warm_up, c.iters, c.lr_alpha)
    assert got == pytest.approx(want, abs=0.02)


def test_the_warp_is_continuous_and_ends_the_schedule():
    warp = ScheduleWarp(1000, 1000)
    assert not warp.warped and warp.at(400) == 400
    short = warp.retarget(400, 700)
    assert short.warped and short.at(400) == 400 and short.at(700) == 1000
    assert short.at(399) == 399  # unchanged before the bend
    again = short.retarget(550, 600)
    assert again.at(550) == pytest.approx(short.at(550)) and again.at(600) == 1000
    values = [again.at(i) for i in range(0, 601)]
    assert values == sorted(values)
    assert ScheduleWarp.from_dict(again.to_dict()) == again
    # the learning rate reaches its final factor at the new end
    assert lr_factor(again.at(600), 10, 1000, 0.05) == pytest.approx(0.05)


def test_an_ended_warp_keeps_the_map_before_its_end():
    short = ScheduleWarp(1000, 1000).retarget(400, 700)
    ended = short.ended(650)
    assert ended.end == 650 and ended.warped
    assert [ended.at(i) for i in range(651)][:650] == [short.at(i) for i in range(650)]
    assert ended.at(650) == 1000 and ScheduleWarp.from_dict(ended.to_dict()) == ended


def test_retarget_only_when_the_rest_overruns_or_leaves_time_unused():
    assert retarget_end(100, 1000, left_s=95.0, step_s=0.1, spare_s=4.0) is None  # 90 s fits
    assert retarget_end(100, 1000, 45.0, 0.1, 4.0) == 100 + int(41 / 0.1)
    assert retarget_end(100, 1000, 180.0, 0.1, 4.0) == 100 + int(176 / 0.1)
    assert retarget_end(999, 1000, left_s=0.0, step_s=1.0, spare_s=4.0) is None  # at its end


def _simulate(budget, start_s, step_s, slow_after_s, slowdown, log_every=50, most=0):
    """A run on a fake clock: plan from the first rate, slow down later, retarget at logs."""
    costs = StepCosts(step_s, ckpt_s=0.2)
    plan = plan_iterations(budget, start_s, costs, 0, 0, most=most)
    warp, now, i = ScheduleWarp(plan.iters, plan.iters), start_s, 0
    marks = [(now, 0)]
    while i < warp.end:
        now += step_s * (slowdown if now > slow_after_s else 1.0)
        i += 1
        if i % log_every == 0:
            marks = (marks + [(now, i)])[-4:]
            rate = (marks[-1][0] - marks[0][0]) / (marks[-1][1] - marks[0][1])
            end = retarget_end(i, warp.end, budget - now - 0.2 - RESERVE_S, rate, plan.spare_s,
                               plan.most)
            if end is not None:
                warp = warp.retarget(i, end)
    return plan, warp, now + 0.2  # the final checkpoint


@pytest.mark.parametrize("slowdown", [1.0, 1.5, 3.0, 0.5])
def test_a_run_on_a_fake_clock_ends_in_time_with_its_schedule_finished(slowdown):
    plan, warp, end_s = _simulate(240.0, 20.0, 0.05, slow_after_s=100.0, slowdown=slowdown)
    assert end_s <= 240.0 - RESERVE_S + 1e-6
    assert warp.at(warp.end) == plan.iters  # the schedule reached its end
    assert end_s > 0.85 * 240  # and used its time
    if slowdown == 1.0:
        assert not warp.warped and plan.spare_s > 0
    else:
        assert warp.warped and (warp.end < plan.iters) == (slowdown > 1)


def test_a_ceiling_caps_the_plan_and_lets_a_short_schedule_through():
    costs = StepCosts(step_s=0.1, val_s=1.0, ckpt_s=0.5)
    free = plan_iterations(240.0, 30.0, costs, 7, 3)
    assert plan_iterations(240.0, 30.0, costs, 7, 3, most=500).iters == 500
    assert plan_iterations(240.0, 30.0, costs, 7, 3, most=10 * free.iters).iters == free.iters
    assert plan_iterations(240.0, 30.0, costs, 7, 3, most=5).iters == 5  # under MIN_ITERS
    assert plan_iterations(10.0, 9.0, costs, 0, 0, most=5).iters == 0  # nothing fits
    capped = plan_iterations(240.0, 30.0, costs, 7, 3, most=500)
    # the spare a re-target keeps is the margin, not the time the ceiling left unused
    assert capped.spare_s == pytest.approx(MARGIN * (240 - 30 - capped.overhead_s) + 0.1)


@settings(max_examples=200, deadline=None)
@given(budget=st.floats(5, 5000), spent=st.floats(0, 100), step=st.floats(1e-3, 2.0),
       most=st.integers(1, 100000))
def test_a_ceiling_never_plans_more_nor_past_the_budget(budget, spent, step, most):
    costs = StepCosts(step_s=step, val_s=0.3, ckpt_s=0.2)
    free = plan_iterations(budget, spent, costs, 2, 1)
    capped = plan_iterations(budget, spent, costs, 2, 1, most=most)
    assert capped.iters <= most and capped.estimated_s <= max(budget, spent + capped.overhead_s)
    if free.iters:
        assert capped.iters == min(free.iters, most)


@pytest.mark.parametrize("slowdown", [1.0, 0.5, 2.0, 8.0])
def test_a_capped_run_never_stretches_past_its_ceiling_and_compresses_to_fit(slowdown):
    """`train.budget_up_to_iters` (the demo): 1000 iterations of 50 ms fit a 240 s budget
    with time to spare; faster steps do not lengthen them, slower ones compress them."""
    plan, warp, end_s = _simulate(240.0, 20.0, 0.05, slow_after_s=40.0, slowdown=slowdown,
                                  most=1000)
    assert plan.iters == 1000 and warp.end <= 1000
    assert warp.at(warp.end) == plan.iters  # the schedule reached its end
    assert end_s <= 240.0 - RESERVE_S + 1e-6
    if slowdown <= 2.0:  # slower steps that still fit are waited for
        assert warp.end == 1000 and end_s < 0.5 * 240
    else:  # 600 more steps of 400 ms do not fit: compressed to fill the budget
        assert warp.end < 1000 and end_s > 0.85 * 240


def test_the_device_default_and_its_ladder():
    assert default_setting("cpu") == ("demo", ())
    assert default_setting("cuda")[0] == "fast"
    assert default_setting("cpu", 60)[1] == ()
    assert "train.batch_size=256" in default_setting("cpu", 1200)[1]
    for device in ("cpu", "cuda"):
        for s in (30, 600, 3600):
            name, extra = default_setting(device, s)
            load_config(name, list(extra))  # every rung loads


@pytest.fixture
def scene(sphere_scene, tmp_path):
    return sphere_scene(tmp_path / "scene")


def test_resume_and_rerun_reproduce_the_recorded_schedule(small, scene, tmp_path,
                                                          monkeypatch):
    from neus_l0.train import budget_run

    real = budget_run.measure_costs

    def fake_clock(run, seconds):  # the measured steps run (and are undone); 10 s a step
        real(run, seconds=0.05)
        return StepCosts(step_s=10.0)

    monkeypatch.setattr(budget_run, "measure_costs", fake_clock)
    cfg = load_config("demo", small + ["train.budget=300", "train.compile=false"])
    part = train(scene, cfg, tmp_path / "a", progress=False, stop_at=5)
    recorded = load_config(tmp_path / "a" / "config.yaml")
    assert recorded.train.budget == 0 and recorded.train.iters > 5 and part.iteration == 5
    done = train(scene, recorded, tmp_path / "a", resume=True, progress=False)
    rerun = train(scene, recorded, tmp_path / "b", progress=False)
    assert done.iteration == rerun.iteration == recorded.train.iters
    a = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    b = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k


def test_a_run_its_deadline_stopped_is_finished_on_resume(
        small, scene, tmp_path, monkeypatch):
    """The deadline stops the run at iteration 4 of a longer plan: its checkpoint ends the
    schedule there, so a re-run (a resume) trains nothing; budget.json says why."""
    import json

    from neus_l0.train import budget_run

    real = budget_run.measure_costs
    monkeypatch.setattr(budget_run, "measure_costs",
                        lambda run, seconds: (real(run, seconds=0.05), StepCosts(10.0))[1])
    monkeypatch.setattr(budget_run.BudgetKeeper, "left_for_steps",
                        lambda self: 1.0 if self.run.iteration < 4 else 0.0)
    cfg = load_config("demo", small + ["train.budget=300", "train.compile=false",
                                       "train.save_every=2"])
    first = train(scene, cfg, tmp_path / "a", progress=False)
    recorded = load_config(tmp_path / "a" / "config.yaml")
    assert first.stopped_early and first.iteration == 4 < recorded.train.iters
    kept = json.loads((tmp_path / "a" / "budget.json").read_text())
    assert kept["done_iters"] == 4 and kept["retargets"][-1] == {
        "iter": 4, "end": 4, "was": recorded.train.iters, "deadline": True}
    before = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    again = train(scene, recorded, tmp_path / "a", resume=True, progress=False)
    assert again.iteration == 4 and not again.stopped_early
    after = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    assert after["iteration"] == 4 and after["schedule"]["end"] == 4
    for k in before["model"]:
        assert torch.equal(before["model"][k], after["model"][k]), k


def test_a_budget_on_resume_is_refused(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=3", "train.compile=false"])
    train(scene, cfg, tmp_path / "a", progress=False, stop_at=2)
    with pytest.raises(ConfigError, match="train.budget"):
        train(scene, dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, budget=30.0)),
              tmp_path / "a", resume=True, progress=False)
