"""Importance samplers along rays: NeRF's piecewise-constant PDF and the L0-Sampler.

Pure tensor functions over the last axis; any leading batch shape ("...") is allowed,
float32 and float64, CPU and CUDA. Names used throughout:

* ``t``       (..., N)    sorted positions along a ray (the L0 interpolation nodes)
* ``bins``    (..., N+1)  sorted bin edges (NeRF's piecewise-constant PDF)
* ``weights`` (..., N)    non-negative weights: at the positions ``t`` for ``sample_l0``,
                          of the bins ``[bins_i, bins_{i+1}]`` for ``sample_pdf``
* ``u``       (..., n)    quantiles in [0, 1) that the inverse CDF maps to positions

Weights may be any numbers: NaN, +-inf and negative values are treated as zero, and the
weights of each ray are rescaled by their maximum before use (the sampled distribution does
not depend on their scale, so 1e-30 or 1e30 are as good as 1). A ray whose weights carry no
mass at all is sampled uniformly over its range. Outputs are sorted, lie inside the input
range, contain no NaN or inf, and carry no gradient.

The L0-Sampler (Li & Zhang, CVPR 2024) interpolates the point weights ``w_i`` (after
``maxblur``) on each interval ``[t_i, t_{i+1}]`` of length ``D`` with ``a = w_i``, ``b = w_{i+1}``,
``L = ln b - ln a`` and ``s`` in [0, 1]:

======== ===================== ==================== =============================
kind     density on [0, 1]     mass / D             inverse CDF s(q), q in [0, 1)
======== ===================== ==================== =============================
exp      a (b/a)^s             a f(L)               log1p(q expm1(L)) / L
inverse  ab / ((a-b) s + b)    b / f(L)             expm1(-q L) / expm1(-L)
linear   a + (b-a) s           (a+b) / 2            q(a+b) / (a + sqrt((1-q)a^2 + q b^2))
======== ===================== ==================== =============================

with ``f(L) = expm1(L) / L`` (the logarithmic mean of a and b, divided by a). The inverse
CDFs are written for ``L <= 0`` only and mirrored (``s(q, L) = 1 - s(1-q, -L)``), which keeps
every ``exp``/``expm1`` argument non-positive: no overflow for any weight ratio. Where ``|L|``
is below ``eps ** (1/3)`` the 0/0 forms are replaced by their Taylor series (truncation below
float precision); no epsilon is ever added to a denominator. An interval with a zero
endpoint (possible only with ``blur=False``) carries no mass for ``exp`` and ``inverse``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "KINDS", "maxblur", "piece_inverse_cdf", "piece_mass", "quantiles", "sample_l0",
    "sample_pdf", "sanitize_weights",
]

#: Interpolation kinds accepted by :func:`sample_l0`.
KINDS = ("exp", "inverse", "linear")


def sanitize_weights(weights: Tensor) -> Tensor:
    """Replace NaN, +-inf and negative weights by zero.

    Args:
        weights: (..., N) any real weights.

    Returns:
        (..., N) finite, non-negative weights of the same dtype.
    """
    finite = torch.isfinite(weights) & (weights > 0)
    return torch.where(finite, weights, torch.zeros((), dtype=weights.dtype,
                                                    device=weights.device))


def _normalize_max(weights: Tensor) -> Tensor:
    """Divide each ray's (finite, non-negative) weights by their maximum; all-zero rays stay 0.

    Args:
        weights: (..., N) finite non-negative weights.

    Returns:
        (..., N) weights in [0, 1].
    """
    wmax = weights.amax(dim=-1, keepdim=True)  # (..., 1)
    return weights / torch.where(wmax > 0, wmax, torch.ones_like(wmax))


def maxblur(weights: Tensor, pad: float = 0.01) -> Tensor:
    """The L0-Sampler's max-blur (paper eq. 10, from mip-NeRF), edges replicated.

    ``w'_i = (max(w_{i-1}, w_i) + max(w_i, w_{i+1})) / 2 + pad`` with ``w_{-1} = w_0`` and
    ``w_N = w_{N-1}``. Non-finite and negative weights count as zero.

    Args:
        weights: (..., N) weights at N points, N >= 1.
        pad: constant added to every blurred weight (0.01 in the paper).

    Returns:
        (..., N) blurred weights, each >= pad.
    """
    w = sanitize_weights(weights)
    pair = torch.maximum(w[..., :-1], w[..., 1:])  # (..., N-1) max of neighbours
    left = torch.cat([w[..., :1], pair], dim=-1)  # max(w_{i-1}, w_i)
    right = torch.cat([pair, w[..., -1:]], dim=-1)  # max(w_i, w_{i+1})
    return 0.5 * left + 0.5 * right + pad  # halves first: no overflow near float max


def quantiles(shape: tuple[int, ...], n_samples: int, det: bool,
              generator: torch.Generator | None, dtype: torch.dtype,
              device: torch.device) -> Tensor:
    """Sorted quantiles u in [0, 1), one row of ``n_samples`` per ray.

    Deterministic: ``u_k = (k + 0.5) / n``. Random: stratified, ``u_k = (k + U_k) / n`` with
    ``U_k ~ U[0, 1)`` drawn from ``generator``.

    Args:
        shape: the leading batch shape (...).
        n_samples: n, the number of quantiles per ray.
        det: deterministic midpoints instead of stratified draws.
        generator: random source for ``det=False`` (on ``device``); None uses torch's global.
        dtype, device: of the result.

    Returns:
        (..., n) quantiles, sorted along the last axis, each in [0, 1).
    """
    k = torch.arange(n_samples, dtype=dtype, device=device)
    if det:
        return ((k + 0.5) / n_samples).expand(*shape, n_samples).contiguous()
    jitter = torch.rand(*shape, n_samples, generator=generator, dtype=dtype, device=device)
    u = (k + jitter) / n_samples
    # (k + U)/n can round up to 1 in float32 when U is within an ulp of 1.
    return u.clamp_(max=1.0 - torch.finfo(dtype).eps)


def _invert_cdf(cdf: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Locate quantiles in a piecewise CDF.

    Args:
        cdf: (..., M+1) non-decreasing, cdf[..., 0] == 0 and cdf[..., -1] == 1 exactly.
        u: (..., n) quantiles in [0, 1).

    Returns:
        idx: (..., n) int64 piece index i in [0, M-1] with cdf_i <= u < cdf_{i+1}.
        q: (..., n) the fraction of piece i's mass below u, in [0, 1].
    """
    n_pieces = cdf.shape[-1] - 1
    idx = torch.searchsorted(cdf, u, right=True).sub_(1).clamp_(0, n_pieces - 1)
    lo = torch.gather(cdf, -1, idx)
    hi = torch.gather(cdf, -1, idx + 1)
    width = hi - lo
    q = torch.where(width > 0, (u - lo) / torch.where(width > 0, width, 1.0), 0.0)
    return idx, q.clamp_(0.0, 1.0)


def _normalized_cdf(mass: Tensor, fallback: Tensor) -> tuple[Tensor, Tensor]:
    """Cumulative distribution over pieces, falling back where a ray has no mass.

    Args:
        mass: (..., M) finite non-negative piece masses.
        fallback: (..., M) finite non-negative masses used for rays whose ``mass`` sums to 0
            (e.g. the piece lengths, for uniform sampling); where those sum to 0 too, every
            piece gets equal mass.

    Returns:
        cdf: (..., M+1) with cdf[..., 0] = 0 and cdf[..., -1] = 1 exactly.
        degenerate: (..., 1) bool, True where ``mass`` was replaced.
    """
    degenerate = mass.sum(dim=-1, keepdim=True) <= 0
    fb_empty = fallback.sum(dim=-1, keepdim=True) <= 0
    fallback = torch.where(fb_empty, torch.ones_like(fallback), fallback)
    mass = torch.where(degenerate, fallback, mass)
    csum = torch.cumsum(mass, dim=-1)  # (..., M)
    total = csum[..., -1:]
    cdf = torch.cat([torch.zeros_like(total), csum[..., :-1] / total, torch.ones_like(total)],
                    dim=-1)
    return cdf, degenerate


@torch.no_grad()
def sample_pdf(bins: Tensor, weights: Tensor, n_samples: int, det: bool = True,
               generator: torch.Generator | None = None) -> Tensor:
    """NeRF's hierarchical volume sampling: inverse transform of a piecewise-constant PDF.

    Args:
        bins: (..., N+1) sorted bin edges.
        weights: (..., N) weight of each bin (any values; see the module notes).
        n_samples: n, samples per ray.
        det: midpoint quantiles ``(k + 0.5) / n`` instead of stratified random ones.
        generator: random source for ``det=False``.

    Returns:
        (..., n) sorted samples inside [bins_0, bins_N], without gradient.
    """
    if bins.shape[-1] != weights.shape[-1] + 1:
        raise ValueError(f"bins (..., N+1) and weights (..., N) disagree: "
                         f"{tuple(bins.shape)} vs {tuple(weights.shape)}")
    if weights.shape[-1] < 1:
        raise ValueError("sample_pdf needs at least one bin")
    bins = bins.detach()
    w = _normalize_max(sanitize_weights(weights.detach().to(bins.dtype)))  # (..., N)
    width = (bins[..., 1:] - bins[..., :-1]).clamp_min(0)  # (..., N)
    cdf, _ = _normalized_cdf(w, width)  # (..., N+1)
    u = quantiles(cdf.shape[:-1], n_samples, det, generator, bins.dtype, bins.device)
    idx, q = _invert_cdf(cdf, u)  # (..., n)
    lo = torch.gather(bins, -1, idx)
    d = torch.gather(width, -1, idx)
    return _finish(lo + q * d, bins)


def _finish(samples: Tensor, t: Tensor) -> Tensor:
    """Clamp samples into [t_0, t_last] and repair 1-ulp disorder from rounding.

    Args:
        samples: (..., n) samples, sorted up to rounding.
        t: (..., N) the sorted nodes or bin edges they were drawn between.

    Returns:
        (..., n) sorted samples inside [t_0, t_last].
    """
    samples = torch.maximum(samples, t[..., :1])
    samples = torch.cummax(samples, dim=-1).values
    return torch.minimum(samples, t[..., -1:])


def _expm1_over(L: Tensor, small: Tensor) -> Tensor:
    """f(L) = expm1(L) / L, with its series 1 + L/2 + L^2/6 where ``small``."""
    series = 1.0 + L * (0.5 + L / 6.0)
    return torch.where(small, series, torch.expm1(L) / torch.where(small, 1.0, L))


def _series_threshold(dtype: torch.dtype) -> float:
    """|L| below which closed forms switch to their second-order series (eps ** (1/3))."""
    return float(torch.finfo(dtype).eps) ** (1.0 / 3.0)


@torch.no_grad()
def sample_l0(t: Tensor, weights: Tensor, n_samples: int, kind: str = "exp",
              det: bool = True, blur: bool = True, pad: float = 0.01,
              generator: torch.Generator | None = None) -> Tensor:
    """The L0-Sampler: inverse transform of piecewise exponential / inverse / linear weights.

    Args:
        t: (..., N) sorted positions along each ray, N >= 2.
        weights: (..., N) weights at those positions (any values; see the module notes).
        n_samples: n, samples per ray.
        kind: ``"exp"`` (the paper's eq. 8-9), ``"inverse"`` (eq. 11-12, with the sign of
            the printed inverse CDF corrected) or ``"linear"``.
        det: midpoint quantiles ``(k + 0.5) / n`` instead of stratified random ones.
        blur: apply :func:`maxblur` with ``pad`` first (the paper does).
        pad: maxblur's pad.
        generator: random source for ``det=False``.

    Returns:
        (..., n) sorted samples inside [t_0, t_{N-1}], without gradient.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown L0 kind {kind!r}; expected one of {KINDS}")
    if t.shape != weights.shape:
        raise ValueError(f"t and weights must have the same shape (..., N): "
                         f"{tuple(t.shape)} vs {tuple(weights.shape)}")
    if t.shape[-1] < 2:
        raise ValueError("sample_l0 needs at least two positions per ray (N >= 2)")
    batch = t.shape[:-1]
    t = t.detach().reshape(-1, t.shape[-1])  # (R, N)
    w = weights.detach().to(t.dtype).reshape(t.shape)
    w = maxblur(w, pad) if blur else sanitize_weights(w)
    w = _normalize_max(w)  # (R, N) in [0, 1]
    a, b = w[:, :-1], w[:, 1:]  # (R, M) endpoint weights of the M = N-1 intervals
    d = (t[:, 1:] - t[:, :-1]).clamp_min(0)  # (R, M) interval lengths
    t_lo = t[:, :-1]
    u = quantiles((t.shape[0],), n_samples, det, generator, t.dtype, t.device)  # (R, n)
    if kind == "exp":
        out = _sample_exp(a, b, d, t_lo, u)
    else:
        out = _sample_q_kind(a, b, d, t_lo, u, kind)
    return _finish(out, t).reshape(*batch, n_samples)


def _gather_rows(table: Tensor, idx: Tensor) -> Tensor:
    """Rows of a per-interval table picked by per-sample interval indices.

    Args:
        table: (R, M, C) C values per interval.
        idx: (R, n) int64 interval index of each sample.

    Returns:
        (R, n, C) the picked rows (one indexed copy of C contiguous values per sample).
    """
    n_rays, n_int, n_ch = table.shape
    offset = torch.arange(n_rays, device=idx.device).unsqueeze(-1) * n_int  # (R, 1)
    flat = (idx + offset).reshape(-1)
    return table.reshape(n_rays * n_int, n_ch).index_select(0, flat).reshape(
        n_rays, idx.shape[-1], n_ch)


def _locate(cdf: Tensor, u: Tensor) -> Tensor:
    """Interval index i with cdf_i <= u < cdf_{i+1}; cdf (R, M+1), u (R, n) -> (R, n)."""
    return torch.searchsorted(cdf, u, right=True).sub_(1).clamp_(0, cdf.shape[-1] - 2)


def _sample_exp(a: Tensor, b: Tensor, d: Tensor, t_lo: Tensor, u: Tensor) -> Tensor:
    """Fused inverse transform for the exponential kind.

    A sample at quantile u in an interval (mass fraction ``width`` starting at cdf value
    ``lo``, ``q = (u - lo) / width``) lies at ``t_lo + D log1p(q expm1(L)) / L``. Written as
    ``t_lo + D (c + log1p(q K - P)) / L`` with ``K = expm1(L - c) + P``, ``P = -expm1(-c)``,
    which is the same number for any shift ``c >= 0``; ``c`` is 0 unless
    ``expm1(L) / width`` would exceed e^80, so nothing overflows. ``u`` enters as
    ``log1p(u alpha - beta)`` with ``alpha = K / width`` and ``beta = lo alpha + P``: each
    sample gathers four numbers and takes one log1p. The closed form is exact to rounding for
    every ``L != 0``; ``|L| < sqrt(tiny)`` (in practice ``a == b``, where 0/0 would appear,
    and rays that fall back to uniform) uses ``L = sqrt(tiny)``, for which the exponential
    equals the constant to within 1e-19 relative.

    Args:
        a, b: (R, M) endpoint weights in [0, 1]. d: (R, M) lengths. t_lo: (R, M) starts.
        u: (R, n) sorted quantiles in [0, 1).

    Returns:
        (R, n) positions, sorted up to rounding.
    """
    L, positive = _log_ratio(a, b)
    cdf, degenerate = _normalized_cdf(_exp_mass(a, b, L, positive) * d, d)  # (R, M+1)
    tiny = float(torch.finfo(a.dtype).tiny) ** 0.5
    L = torch.where(degenerate | ~positive | (L.abs() < tiny), tiny, L)
    lo, width = cdf[:, :-1], cdf[:, 1:] - cdf[:, :-1]
    width = torch.where(width > 0, width, 1.0)
    c = (L - torch.log(width) - _SHIFT).clamp_min(0.0)  # (R, M), almost always 0
    P = -torch.expm1(-c)
    alpha = (torch.expm1(L - c) + P) / width
    gamma = d / L
    table = torch.stack([alpha, lo * alpha + P, gamma, t_lo + c * gamma], dim=-1)  # (R, M, 4)
    rows = _gather_rows(table, _locate(cdf, u))  # (R, n, 4)
    x = torch.log1p((u * rows[..., 0] - rows[..., 1]).clamp_min(-1.0))
    return torch.addcmul(rows[..., 3], x, rows[..., 2])


def _exp_mass(a: Tensor, b: Tensor, L: Tensor, positive: Tensor) -> Tensor:
    """Mass per unit length of exponential pieces: the logarithmic mean of a and b.

    ``(b - a) / L`` where ``|L| > 1`` (no cancellation there, no overflow for any ratio),
    ``a expm1(L) / L`` below, with its series ``a (1 + L/2 + L^2/6)`` where ``|L|`` is tiny.

    Args:
        a, b: (...) endpoint weights. L: (...) ln(b/a) where ``positive``, else anything finite.
        positive: (...) bool, a > 0 and b > 0.

    Returns:
        (...) mass per unit length, 0 where not ``positive``.
    """
    big = L.abs() > 1.0
    small = L.abs() < _series_threshold(a.dtype)
    near = a * _expm1_over(torch.where(big, 0.0, L), small | big)
    far = (b - a) / torch.where(big, L, 1.0)
    return torch.where(positive, torch.where(big, far, near), 0.0)


#: ln of the largest intermediate the exp kind allows itself (e^80 < float32 max / 1e3).
_SHIFT = 80.0


def _sample_q_kind(a: Tensor, b: Tensor, d: Tensor, t_lo: Tensor, u: Tensor,
                   kind: str) -> Tensor:
    """Inverse transform for the ``inverse`` and ``linear`` kinds through the fraction q.

    Args:
        a, b: (R, M) endpoint weights in [0, 1]. d: (R, M) lengths. t_lo: (R, M) starts.
        u: (R, n) sorted quantiles in [0, 1).
        kind: ``"inverse"`` or ``"linear"``.

    Returns:
        (R, n) positions, sorted up to rounding.
    """
    cdf, degenerate = _normalized_cdf(piece_mass(a, b, kind) * d, d)  # (R, M+1)
    lo, width = cdf[:, :-1], cdf[:, 1:] - cdf[:, :-1]
    inv_w = 1.0 / torch.where(width > 0, width, 1.0)
    uniform = degenerate.expand_as(a).to(a.dtype)
    table = torch.stack([lo, inv_w, a, b, t_lo, d, uniform], dim=-1)  # (R, M, 7)
    rows = _gather_rows(table, _locate(cdf, u))  # (R, n, 7)
    q = ((u - rows[..., 0]) * rows[..., 1]).clamp_(0.0, 1.0)
    s = piece_inverse_cdf(rows[..., 2], rows[..., 3], q, kind)
    s = torch.where(rows[..., 6] > 0, q, s)  # uniform fallback: uniform inside each piece too
    return torch.addcmul(rows[..., 4], s, rows[..., 5])


def _log_ratio(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """L = ln b - ln a where both are positive, else 0; and the mask of those pieces."""
    positive = (a > 0) & (b > 0)
    one = torch.ones((), dtype=a.dtype, device=a.device)
    L = torch.log(torch.where(positive, b, one)) - torch.log(torch.where(positive, a, one))
    return L, positive


def piece_mass(a: Tensor, b: Tensor, kind: str) -> Tensor:
    """Mass per unit length of one interpolated piece with endpoint weights a and b.

    ``exp``: the logarithmic mean ``(b - a) / ln(b / a)`` = ``a expm1(L) / L``;
    ``inverse``: ``ab ln(b/a) / (b - a)`` = ``b L / expm1(L)``; ``linear``: ``(a + b) / 2``.
    Series where |L| is tiny; 0 where a or b is 0 for ``exp`` and ``inverse``.

    Args:
        a: (...) finite non-negative weight at the start of the piece.
        b: (...) finite non-negative weight at its end.
        kind: ``"exp"``, ``"inverse"`` or ``"linear"``.

    Returns:
        (...) the integral of the interpolant over s in [0, 1].
    """
    if kind == "linear":
        return 0.5 * a + 0.5 * b
    L, positive = _log_ratio(a, b)
    if kind == "exp":
        return _exp_mass(a, b, L, positive)
    f = _expm1_over(L, L.abs() < _series_threshold(a.dtype))  # expm1(L)/L > 0
    return torch.where(positive, b / f, 0.0)


def piece_inverse_cdf(a: Tensor, b: Tensor, q: Tensor, kind: str) -> Tensor:
    """Position s in [0, 1] below which a piece holds the fraction q of its mass.

    Args:
        a: (...) finite non-negative weight at the start of the piece.
        b: (...) finite non-negative weight at its end.
        q: (...) mass fractions in [0, 1].
        kind: ``"exp"``, ``"inverse"`` or ``"linear"``.

    Returns:
        (...) s in [0, 1]; a piece with no mass returns s = q.
    """
    a, b, q = torch.broadcast_tensors(a, b, q)
    if kind == "linear":
        den = a + torch.sqrt((1.0 - q) * a * a + q * b * b)
        s = torch.where(den > 0, q * (a + b) / torch.where(den > 0, den, 1.0), q)
    elif kind == "exp":
        zero = torch.zeros_like(a)
        one = torch.ones_like(a)
        s = _sample_exp(a.reshape(-1, 1), b.reshape(-1, 1), one.reshape(-1, 1),
                        zero.reshape(-1, 1), q.reshape(-1, 1)).reshape(q.shape)
    else:
        L, positive = _log_ratio(a, b)
        s = torch.where(positive, _inverse_kind_s(L, q), q)
    return s.clamp(0.0, 1.0)


def _inverse_kind_s(L: Tensor, q: Tensor) -> Tensor:
    """s(q) of the inverse kind, ``expm1(-qL) / expm1(-L)``, finite for every L.

    For ``L >= 0`` every exponent is <= 0. For ``L < 0`` (``M = -L > 0``) the direct form is
    used up to ``M = 80`` and ``exp((q-1)M) expm1(-qM) / expm1(-M)`` beyond, where ``e^M``
    would overflow. ``|L|`` below eps^(1/3) uses the second-order series
    ``q (1 + (1-q) L/2 + (1-q)(1-2q) L^2/12)``.

    Args:
        L: (...) ln(b/a), finite. q: (...) fractions in [0, 1].

    Returns:
        (...) s, in [0, 1] up to rounding.
    """
    small = L.abs() < _series_threshold(L.dtype)
    Ls = torch.where(small, 1.0, L)
    direct = torch.expm1(-q * Ls.clamp_min(-_SHIFT)) / torch.expm1(-Ls.clamp_min(-_SHIFT))
    M = (-Ls).clamp_min(1.0)
    far = torch.exp((q - 1.0) * M) * torch.expm1(-q * M) / torch.expm1(-M)
    closed = torch.where(Ls < -_SHIFT, far, direct)
    series = q + q * (1.0 - q) * L * (0.5 + (1.0 - 2.0 * q) * L / 12.0)
    return torch.where(small, series, closed)
