"""`train.compile: auto` measures the eager step of a setting it has not seen (a few timed
steps, undone) instead of trusting its per-sample cost model."""

import pytest
import torch

from neus_l0.config.load import load_config
from neus_l0.train.compile_auto import (
    UNSEEN_FACTOR,
    choose_compile,
    eager_key,
    eager_step_seconds,
    read_record,
    resolve_compile,
    worth_measuring,
)


@pytest.fixture
def record_home(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield tmp_path
    torch.set_num_threads(before)


def test_a_measured_step_replaces_the_cost_model(record_home):
    cfg = load_config("wmask", ["train.iters=20"])
    model = choose_compile(cfg, "cpu")
    measured = choose_compile(cfg, "cpu", eager_s=15.0)
    assert not model.measured and measured.measured and measured.eager_step_s == 15.0
    assert measured.saving_s == pytest.approx(20 * 15.0 * 0.55)
    assert "measured" in measured.line()


def test_unseen_settings_are_measured_once_then_read_from_the_record(record_home):
    cfg = load_config("wmask", ["train.iters=300"])
    calls = []

    def measure():
        calls.append(1)
        return 14.0

    out, line = resolve_compile(cfg, "cpu", measure=measure)
    assert calls == [1] and out.train.compile is True and "14000 ms, measured" in line
    key = eager_key(cfg, "cpu")
    assert read_record()[key]["eager_s"] == 14.0
    resolve_compile(cfg, "cpu", measure=measure)
    assert calls == [1]  # the record answers the second time


def test_runs_that_cannot_repay_a_compile_are_not_measured(record_home):
    cfg = load_config("demo", ["train.iters=4"])
    assert not worth_measuring(cfg, "cpu")
    step = UNSEEN_FACTOR * eager_step_seconds(cfg, "cpu")
    assert 4 * step * 0.55 < 12.0

    def measure():
        raise AssertionError("measured a run too short to compile")

    out, _ = resolve_compile(cfg, "cpu", measure=measure)
    assert out.train.compile is False


def test_a_budget_counts_a_cold_compile(record_home):
    cfg = load_config("demo", ["train.budget=60"])
    choice = choose_compile(cfg, "cpu", eager_s=0.08)
    assert choice.compile_s >= 45.0 and not choice.compile  # 60 s x 0.55 < 45 s


def test_a_budget_compiles_on_a_warm_cache(record_home):
    """The plan is made after the compile, so a warm cache's compile is counted as such: a
    60 s budget compiles (it stayed eager when a cold compile was counted)."""
    from neus_l0.train.cache_folder import compile_record_path
    from neus_l0.train.compile_auto import as_compiled, note_compile, step_key

    cfg = load_config("demo", ["train.budget=60"])
    key = step_key(as_compiled(cfg), "cpu")
    note_compile(key, 23.0, compile_record_path())
    note_compile(key, 5.8, compile_record_path())
    choice = choose_compile(cfg, "cpu", record=read_record(), eager_s=0.025)
    assert choice.warm and choice.compile_s == 5.8 and choice.compile  # 60 x 0.55 = 33 > 5.8
