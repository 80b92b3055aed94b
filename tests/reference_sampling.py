"""A plain, slow float64 reference for the samplers: numeric quadrature and root finding.

It shares no code with `neus_l0.sampling`: densities are written as the paper defines them
(not as the closed forms), masses come from `scipy.integrate.quad`, and inverse CDFs from
`scipy.optimize.brentq` on the integrated density.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import quad
from scipy.optimize import brentq


def density(kind: str, a: float, b: float, s: float) -> float:
    """The interpolant w(s) on s in [0, 1] between endpoint weights a and b."""
    if kind == "linear":
        return a + (b - a) * s
    if a <= 0 or b <= 0:
        return 0.0
    if kind == "exp":
        return a * (b / a) ** s
    if kind == "inverse":
        return a * b / (a * s + b * (1.0 - s))
    raise ValueError(kind)


_GRADED = [10.0 ** -k for k in range(1, 40)]


def _integral(kind: str, a: float, b: float, s0: float, s1: float) -> float:
    """Integral of the interpolant over [s0, s1] within [0, 1], by adaptive quadrature.

    The interpolants can put almost all their mass within 1e-30 of an end (the inverse kind
    with a ratio of 1e30), which a plain quadrature never sees; so the integral is split at
    the middle and each half is integrated from its end, with points graded towards it.
    """
    def f(x: float) -> float:
        return density(kind, a, b, x)

    total = 0.0
    lo_half = (s0, min(s1, 0.5))
    hi_half = (max(s0, 0.5), s1)
    if lo_half[1] > lo_half[0]:
        pts = [p for p in _GRADED if lo_half[0] < p < lo_half[1]]
        total += quad(f, lo_half[0], lo_half[1], points=pts or None, epsabs=0.0,
                      epsrel=1e-13, limit=500)[0]
    if hi_half[1] > hi_half[0]:
        # Integrate in y = 1 - s so that points near s = 1 are representable.
        def g(y: float) -> float:
            return density_y(kind, a, b, y)

        y0, y1 = 1.0 - hi_half[1], 1.0 - hi_half[0]
        pts = [p for p in _GRADED if y0 < p < y1]
        total += quad(g, y0, y1, points=pts or None, epsabs=0.0, epsrel=1e-13, limit=500)[0]
    return total


def density_y(kind: str, a: float, b: float, y: float) -> float:
    """The interpolant at s = 1 - y, written without forming 1 - y."""
    if kind == "linear":
        return b + (a - b) * y
    if a <= 0 or b <= 0:
        return 0.0
    if kind == "exp":
        return b * (a / b) ** y
    if kind == "inverse":
        return a * b / (a * (1.0 - y) + b * y)
    raise ValueError(kind)


def mass(kind: str, a: float, b: float) -> float:
    """Integral of the interpolant over [0, 1]."""
    return _integral(kind, a, b, 0.0, 1.0)


def maxblur(w: np.ndarray, pad: float) -> np.ndarray:
    """Paper eq. 10 written as a loop, edges replicated."""
    n = len(w)
    out = np.empty(n)
    for i in range(n):
        lo = w[max(i - 1, 0)]
        hi = w[min(i + 1, n - 1)]
        out[i] = (max(lo, w[i]) + max(w[i], hi)) / 2 + pad
    return out


def clean(w: np.ndarray) -> np.ndarray:
    """Non-finite and negative weights count as zero."""
    w = np.asarray(w, dtype=np.float64).copy()
    w[~np.isfinite(w) | (w < 0)] = 0.0
    return w


def invert_piece(kind: str, a: float, b: float, q: float) -> float:
    """s in [0, 1] with (integral of w over [0, s]) = q * mass, by root finding."""
    total = mass(kind, a, b)
    if total <= 0:
        return q
    target = q * total

    def f(s: float) -> float:
        return _integral(kind, a, b, 0.0, s) - target

    if q <= 0:
        return 0.0
    if q >= 1:
        return 1.0
    return brentq(f, 0.0, 1.0, xtol=1e-15, rtol=1e-15, maxiter=200)


def sample_l0_ref(t, w, u, kind="exp", blur=True, pad=0.01):
    """Samples of one ray at quantiles u; returns (samples, interval index of each)."""
    t = np.asarray(t, dtype=np.float64)
    w = clean(w)
    w = maxblur(w, pad) if blur else w
    if w.max() > 0:
        w = w / w.max()
    d = np.maximum(np.diff(t), 0.0)
    masses = np.array([mass(kind, w[i], w[i + 1]) * d[i] for i in range(len(d))])
    uniform = masses.sum() <= 0
    if uniform:
        masses = d.copy() if d.sum() > 0 else np.ones_like(d)
    cdf = np.concatenate([[0.0], np.cumsum(masses) / masses.sum()])
    out, idxs = [], []
    for uk in u:
        i = int(np.clip(np.searchsorted(cdf, uk, side="right") - 1, 0, len(d) - 1))
        width = cdf[i + 1] - cdf[i]
        q = (uk - cdf[i]) / width if width > 0 else 0.0
        s = q if uniform else invert_piece(kind, w[i], w[i + 1], q)
        out.append(t[i] + s * d[i])
        idxs.append(i)
    return np.array(out), np.array(idxs)


def sample_pdf_ref(bins, w, u):
    """NeRF's piecewise-constant inverse CDF for one ray, written as a loop."""
    bins = np.asarray(bins, dtype=np.float64)
    w = clean(w)
    width = np.maximum(np.diff(bins), 0.0)
    if w.sum() <= 0:
        w = width.copy() if width.sum() > 0 else np.ones_like(width)
    cdf = np.concatenate([[0.0], np.cumsum(w) / w.sum()])
    out = []
    for uk in u:
        i = int(np.clip(np.searchsorted(cdf, uk, side="right") - 1, 0, len(w) - 1))
        q = (uk - cdf[i]) / (cdf[i + 1] - cdf[i]) if cdf[i + 1] > cdf[i] else 0.0
        out.append(bins[i] + q * width[i])
    return np.array(out)


def l0_cdf(t, w, x, kind="exp", blur=True, pad=0.01):
    """The CDF of the interpolated density of one ray, evaluated at positions x (float64)."""
    t = np.asarray(t, dtype=np.float64)
    w = clean(w)
    w = maxblur(w, pad) if blur else w
    d = np.diff(t)
    masses = np.array([mass(kind, w[i], w[i + 1]) * d[i] for i in range(len(d))])
    total = masses.sum()
    cum = np.concatenate([[0.0], np.cumsum(masses)])
    out = []
    for xk in np.atleast_1d(x):
        if xk <= t[0]:
            out.append(0.0)
            continue
        if xk >= t[-1]:
            out.append(1.0)
            continue
        i = int(np.searchsorted(t, xk, side="right") - 1)
        s = (xk - t[i]) / d[i]
        part = _integral(kind, w[i], w[i + 1], 0.0, s) * d[i]
        out.append((cum[i] + part) / total)
    return np.array(out)
