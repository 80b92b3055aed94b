"""Learning-rate and cos-annealing schedules of NeuS (pure functions of the iteration).

The iteration may be fractional: a budget run whose steps slowed down compresses the rest
of its schedule (`neus_l0.train.budget.ScheduleWarp`), so these see the schedule's
iteration, not the loop's.
"""

from __future__ import annotations

import math


def lr_factor(iteration: float, warm_up: int, total: int, alpha: float) -> float:
    """Linear warm-up to 1 over `warm_up` iterations, then cosine decay to `alpha` at `total`.

    Args:
        iteration: the current iteration (0-based).
        warm_up: warm-up length (0: none).
        total: the iteration where the decay ends.
        alpha: the final factor.

    Returns:
        the factor that multiplies the peak learning rate.
    """
    if iteration < warm_up:
        return iteration / warm_up
    progress = min(1.0, (iteration - warm_up) / max(1, total - warm_up))
    return (math.cos(math.pi * progress) + 1.0) * 0.5 * (1.0 - alpha) + alpha


def cos_anneal_ratio(iteration: float, anneal_end: int) -> float:
    """NeuS's cos-annealing ratio: min(1, iteration / anneal_end); 1 when anneal_end is 0."""
    if anneal_end <= 0:
        return 1.0
    return min(1.0, iteration / anneal_end)
