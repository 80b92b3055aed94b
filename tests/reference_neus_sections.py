"""A plain, slow float64 reference for `sample_neus_sections`: quadrature and root finding.

It shares no code with `neus_l0.sampling`: the density inside a section is NeuS's opacity
density written as the derivative of the logistic, ``sigmoid'(v) = sigmoid(v) sigmoid(-v)``
along the linear logit ``v(s) = x + (y - x) s``; masses come from `scipy.integrate.quad` and
quantiles from `scipy.optimize.brentq` on the integrated density.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import quad
from scipy.optimize import brentq


def _log_density(x: float, y: float, s: float) -> float:
    v = x + (y - x) * s
    return -abs(v) - 2.0 * math.log1p(math.exp(-abs(v)))  # log sigmoid'(v), overflow-free


def _integral(x: float, y: float, s0: float, s1: float, shift: float) -> float:
    """Integral of exp(log density - shift) over [s0, s1], split at the density's peak."""
    def f(s: float) -> float:
        return math.exp(_log_density(x, y, s) - shift)

    peak = x / (x - y) if x != y else 0.5  # where v(s) = 0
    pts = [p for p in (peak,) if s0 < p < s1]
    return quad(f, s0, s1, points=pts or None, epsabs=0.0, epsrel=1e-13, limit=500)[0]


def invert_section(x: float, y: float, q: float) -> float:
    """s in [0, 1] below which the section holds the fraction q of its opacity."""
    if not (math.isfinite(x) and math.isfinite(y)) or x == y:
        return q
    shift = max(_log_density(x, y, 0.0), _log_density(x, y, 1.0),
                _log_density(x, y, min(max(x / (x - y), 0.0), 1.0)))
    total = _integral(x, y, 0.0, 1.0, shift)
    if q <= 0:
        return 0.0
    if q >= 1:
        return 1.0
    return brentq(lambda s: _integral(x, y, 0.0, s, shift) - q * total, 0.0, 1.0,
                  xtol=1e-15, rtol=1e-15, maxiter=200)


def sample_neus_ref(z, weights, prev_sdf, next_sdf, inv_s, u):
    """Samples of one ray at quantiles u (float64 loops)."""
    z = np.asarray(z, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64).copy()
    w[~np.isfinite(w) | (w < 0)] = 0.0
    d = np.maximum(np.diff(z), 0.0)
    uniform = w.sum() <= 0
    if uniform:
        w = d.copy() if d.sum() > 0 else np.ones_like(d)
    cdf = np.concatenate([[0.0], np.cumsum(w) / w.sum()])
    out = []
    for uk in u:
        i = int(np.clip(np.searchsorted(cdf, uk, side="right") - 1, 0, len(d) - 1))
        width = cdf[i + 1] - cdf[i]
        q = (uk - cdf[i]) / width if width > 0 else 0.0
        s = q if uniform else invert_section(inv_s * prev_sdf[i], inv_s * next_sdf[i], q)
        out.append(z[i] + s * d[i])
    return np.array(out)
