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
