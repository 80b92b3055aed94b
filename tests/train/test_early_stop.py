"""The early stop's detector (`neus_l0.train.early_stop`) on synthetic sequences."""

import math

import pytest
import torch

from neus_l0.train.early_stop import Plateau, surface_movement


def _first_stop(movements, **kw):
    p = Plateau(**kw)
    return next((i for i, m in enumerate(movements) if p.update(m)), None)


def test_a_converging_surface_stops_after_its_patience():
    moves = [0.5 * 0.6 ** k for k in range(30)]  # shrinks geometrically
    first_still = next(i for i, m in enumerate(moves) if m < 0.02)
    assert _first_stop(moves, tolerance=0.02, patience=3) == first_still + 2


def test_a_surface_still_learning_never_stops():
    assert _first_stop([0.05 + 0.01 * math.sin(k) for k in range(100)]) is None


def test_one_quiet_check_among_moving_ones_is_not_a_plateau():
    moves = [0.1, 0.1, 0.1, 0.1, 0.01, 0.1, 0.01, 0.01, 0.1] * 5
    assert _first_stop(moves, patience=3) is None


def test_no_verdict_before_the_least_checks():
    assert _first_stop([0.0] * 10, least_checks=5, patience=1) == 4


def test_surface_movement_reads_only_points_near_the_surface():
    before = torch.tensor([0.0, 0.01, 0.5, -0.8])
    after = torch.tensor([0.002, 0.012, 0.9, -0.1])  # far points moved a lot
    assert surface_movement(before, after, band=0.05) == pytest.approx(0.04, rel=1e-5)
    assert math.isinf(surface_movement(before, after + 5.0, band=0.05))


def test_a_converged_run_finishes_its_schedule_early(small, sphere_scene, tmp_path,
                                                    monkeypatch):
    import json

    from neus_l0.config.load import load_config
    from neus_l0.train import early_stop
    from neus_l0.train.loop import train

    monkeypatch.setattr(early_stop.Plateau, "update", lambda self, moved: True)
    cfg = load_config("demo", small + ["train.iters=40", "train.log_every=2",
                                       "train.early_stop=true", "train.compile=false"])
    result = train(sphere_scene(tmp_path / "scene"), cfg, tmp_path / "run", progress=False)
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert any("surface_moved" in m for m in lines)
    # the first verdict needs two probes (logs 4 and 8: iteration 16), then 5 % of 40 more
    assert result.iteration == 18 and not result.stopped_early
    assert lines[-1]["lr"] < 0.3 * cfg.train.lr  # the compressed schedule decays
