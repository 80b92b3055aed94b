"""Paired comparisons of two methods measured on the same units (scene x seed): the sign
test and a t interval on the differences.

Pure functions on plain sequences; the studies (`neus_l0.experiments.fork`) and the bench's
tables (`neus_l0.experiments.plots`) report with them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from math import comb

import numpy as np


def sign_test_p(wins: int, n: int) -> float:
    """Two-sided exact sign test: the probability, under "each pair is won with
    probability 1/2", of a split at least as uneven as `wins` of `n` (ties left out of `n`
    beforehand). 1.0 for n = 0.

    Raises:
        ValueError: `wins` outside 0..n.
    """
    if not 0 <= wins <= n:
        raise ValueError(f"wins {wins} outside 0..{n}")
    if n == 0:
        return 1.0
    k = min(wins, n - wins)
    return min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2**n)


def t_interval(x: Sequence[float], level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high): Student's t interval for the mean of `x` (n values).

    One value gives (x, -inf, inf); none gives NaNs.
    """
    from scipy.stats import t

    a = np.asarray(x, dtype=np.float64)
    if len(a) == 0:
        return math.nan, math.nan, math.nan
    mean = float(a.mean())
    if len(a) == 1:
        return mean, -math.inf, math.inf
    half = float(t.ppf(0.5 + level / 2, len(a) - 1) * a.std(ddof=1) / math.sqrt(len(a)))
    return mean, mean - half, mean + half


def compare(reference: Sequence[float], other: Sequence[float],
            lower_is_better: bool = True, level: float = 0.95) -> dict:
    """`other` against `reference`, pair by pair (the i-th values belong together).

    Pairs where either value is missing (None or not finite) are left out.

    Returns:
        n (pairs used), better (pairs where `other` is better), ties, diff (mean of
        other - reference) with its t interval diff_low / diff_high, rel (mean of
        other / reference - 1, in %) with rel_low / rel_high, and p (the sign test over the
        pairs that are not ties).
    """
    if len(reference) != len(other):
        raise ValueError(f"{len(reference)} reference values against {len(other)}")
    pairs = [(float(r), float(o)) for r, o in zip(reference, other)
             if r is not None and o is not None and math.isfinite(r) and math.isfinite(o)]
    d = [o - r for r, o in pairs]
    rel = [100.0 * (o / r - 1.0) for r, o in pairs if r != 0]
    ties = sum(x == 0 for x in d)
    better = sum((x < 0) if lower_is_better else (x > 0) for x in d)
    mean, lo, hi = t_interval(d, level)
    rmean, rlo, rhi = t_interval(rel, level)
    return {"n": len(pairs), "better": better, "ties": ties, "diff": mean, "diff_low": lo,
            "diff_high": hi, "rel": rmean, "rel_low": rlo, "rel_high": rhi,
            "p": sign_test_p(better, len(pairs) - ties)}
