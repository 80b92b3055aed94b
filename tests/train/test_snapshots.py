"""`train(..., snapshots=[...])`: checkpoints at loop-time marks, not counted as training time.

The loop's clock is replaced by a fake one that advances exactly 1 s per training step (and
by whatever a monkeypatched slow checkpoint write adds), so every time below is exact.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import neus_l0.train.loop as train_module
import neus_l0.train.state as state_module
from neus_l0.config.load import load_config
from neus_l0.errors import NeusL0Error
from neus_l0.run.checkpoints import latest_checkpoint, list_checkpoints, load_checkpoint
from neus_l0.train.loop import train


class FakeClock:
    """Stands in for the `time` module inside `neus_l0.train` (only `monotonic`)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now


@pytest.fixture
def scene(sphere_scene, tmp_path):
    return sphere_scene(tmp_path / "scene")


@pytest.fixture
def clock(monkeypatch):
    """A fake loop clock: each training step takes exactly 1 s."""
    fake = FakeClock()
    real_step = train_module.train_step

    def step(*args, **kwargs):
        fake.now += 1.0
        return real_step(*args, **kwargs)

    monkeypatch.setattr(state_module, "time", fake)
    monkeypatch.setattr(train_module, "train_step", step)
    return fake


def _lines(run: Path) -> list[dict]:
    return [json.loads(s) for s in (run / "metrics.jsonl").read_text().splitlines()]


def _snapshot_lines(run: Path) -> list[dict]:
    return [m for m in _lines(run) if "snapshot_s" in m]


def test_snapshots_checkpoint_at_their_marks(small, scene, tmp_path, clock):
    cfg = load_config("demo", small + ["train.iters=12", "train.keep_checkpoints=1"])
    run = tmp_path / "run"
    res = train(scene, cfg, run, progress=False, snapshots=[6.5, 2.5, 6.0, 100.0])
    # loop time after step k is k s: 2.5 -> step 3, 6.0 -> step 6, 6.5 -> step 7; 100 s is
    # beyond the end (12 steps) and served by the final checkpoint
    expect = [(2.5, 3, 3.0), (6.0, 6, 6.0), (6.5, 7, 7.0), (100.0, 12, 12.0)]
    lines = _snapshot_lines(run)
    assert [(m["snapshot_s"], m["iter"], m["elapsed"]) for m in lines] == expect
    assert [(m, it) for m, it, _ in res.snapshots] == [(m, it) for m, it, _ in expect]
    assert res.iteration == 12 and res.seconds == 12.0 and not res.stopped_early
    assert res.snapshots[-1][2] == res.checkpoint == latest_checkpoint(run)
    # every snapshot stays on disk despite keep_checkpoints=1, and holds its iteration
    assert [p.name for p in list_checkpoints(run)] == [
        f"ckpt_{it:07d}.pt" for it in (3, 6, 7, 12)]
    for _, it, path in res.snapshots:
        assert load_checkpoint(path)["iteration"] == it
    # the regular metric lines are the ones a run without snapshots writes
    assert [m["iter"] for m in _lines(run) if "loss" in m] == [5, 10, 12]


def test_snapshot_writing_is_not_training_time(small, scene, tmp_path, clock, monkeypatch):
    base = small + ["train.iters=100", "train.max_seconds=10"]
    plain = train(scene, load_config("demo", base), tmp_path / "plain", progress=False)
    assert plain.iteration == 11 and plain.stopped_early  # 11 s > 10 s after step 11

    real_save = state_module.save_checkpoint

    def slow_save(*args, **kwargs):
        clock.now += 100.0  # each checkpoint write takes 100 s of wall-clock
        return real_save(*args, **kwargs)

    monkeypatch.setattr(state_module, "save_checkpoint", slow_save)
    run = tmp_path / "snap"
    res = train(scene, load_config("demo", base), run, progress=False,
                snapshots=[2.5, 5.0, 50.0])
    assert res.iteration == plain.iteration  # 200 s of snapshot writes did not shorten it
    snaps = _snapshot_lines(run)
    assert [(m["snapshot_s"], m["iter"], m["elapsed"]) for m in snaps] == [
        (2.5, 3, 3.0), (5.0, 5, 5.0), (50.0, 11, 11.0)]
    logged = [m for m in _lines(run) if "loss" in m]
    assert [(m["iter"], m["elapsed"]) for m in logged] == [(5, 5.0), (10, 10.0)]
    assert logged[1]["its_per_s"] == 1.0  # 5 steps in 5 s: the snapshot at 5 is excluded
    # the final checkpoint (which also serves the 50 s mark) counts, as without snapshots
    assert res.seconds == 11.0 + 100.0


def test_resume_with_snapshots_equals_uninterrupted(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=12", "train.keep_checkpoints=1"])
    marks = [0.0, 1e-4, 1e6]  # real clock: the first marks fall early, the last at the end
    plain = train(scene, cfg, tmp_path / "plain", progress=False)
    snap = train(scene, cfg, tmp_path / "snap", progress=False, snapshots=marks)
    assert [it for _, it, _ in snap.snapshots][-1] == 12
    part = train(scene, cfg, tmp_path / "resumed", progress=False, stop_at=5, snapshots=marks)
    assert part.iteration == 5 and part.snapshots[-1][1] == 5
    done = train(scene, cfg, tmp_path / "resumed", resume=True, progress=False,
                 snapshots=marks)
    assert done.iteration == 12 and done.snapshots[-1][1] == 12
    ref = load_checkpoint(latest_checkpoint(tmp_path / "plain"))
    for run in ("snap", "resumed"):
        other = load_checkpoint(latest_checkpoint(tmp_path / run))
        assert other["iteration"] == 12
        for k in ref["model"]:
            assert torch.equal(ref["model"][k], other["model"][k]), (run, k)
        for k in ref["optimizer"]["state"]:
            for name, v in ref["optimizer"]["state"][k].items():
                assert torch.equal(v, other["optimizer"]["state"][k][name]), (run, k, name)
        assert torch.equal(ref["rng"]["generator"], other["rng"]["generator"])
        regular = [m for m in _lines(tmp_path / run) if "loss" in m]
        assert [m["loss"] for m in regular] == [m["loss"] for m in _lines(tmp_path / "plain")]
    # the snapshots of both calls survive keep_checkpoints=1, the resumed one's too
    lines = _snapshot_lines(tmp_path / "resumed")
    assert len(lines) == 6 and lines[2]["iter"] == 5 and lines[-1]["iter"] == 12
    on_disk = {p.name for p in list_checkpoints(tmp_path / "resumed")}
    assert {f"ckpt_{m['iter']:07d}.pt" for m in lines} == on_disk
    assert plain.snapshots == []


def test_bad_marks_are_refused_before_anything_is_written(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=2"])
    for bad in ([-1.0], [float("nan")], [1.0, float("inf")]):
        with pytest.raises(NeusL0Error, match="snapshots"):
            train(scene, cfg, tmp_path / "run", progress=False, snapshots=bad)
    assert not (tmp_path / "run").exists()
