"""Importance samplers along rays: NeRF's piecewise-constant PDF and the L0-Sampler.

Pure tensor functions over the last axis; any leading batch shape ("...") is allowed,
float32 and float64, CPU and CUDA, no Python loops over rays or samples. Names:

* ``t``       (..., N)    sorted positions along a ray (the L0 interpolation nodes)
* ``bins``    (..., N+1)  sorted bin edges (NeRF's piecewise-constant PDF)
* ``weights`` (..., N)    weights: at the positions ``t`` for ``sample_l0``, of the bins
                          ``[bins_i, bins_{i+1}]`` for ``sample_pdf``
* ``u``       (..., n)    sorted quantiles in [0, 1) that the inverse CDF maps to positions

Weights may be any numbers: NaN, +-inf and negative values count as zero, and each ray's
weights are divided by their maximum (the distribution does not depend on their scale, so
1e-30 and 1e30 are as good as 1); after that, weights below the smallest normal float
(a ratio beyond 1e38 in float32) are flushed to zero. A ray whose weights carry no mass is
sampled uniformly over its range. Outputs are sorted, inside the input range, finite, and
carry no gradient.

Positions (``t``, ``bins``, ``z``) must be finite and sorted along the last axis. The
samplers check that (`check_positions`: one pass and one host synchronisation) and raise a
``ValueError`` naming the rays that are not, unless called with ``check=False``: NeuS's
up-sampling (`neus_l0.sampling.upsample`) builds sorted, finite positions itself and passes
``check=False``, so that the training step has no host synchronisation. Unchecked, unsorted
positions give meaningless samples and NaN positions NaN samples.

The L0-Sampler (Li & Zhang, CVPR 2024) interpolates the point weights (after ``maxblur``)
on each interval ``[t_i, t_{i+1}]`` of length ``D``, with ``a = w_i``, ``b = w_{i+1}``,
``L = ln(b/a)`` and ``s`` in [0, 1]:

======== ===================== ===================== =====================================
kind     density on [0, 1]     mass / D              inverse CDF s(q), q in [0, 1]
======== ===================== ===================== =====================================
exp      a (b/a)^s             a expm1(L) / L        log1p(q expm1(L)) / L
inverse  ab / ((a-b) s + b)    b L / expm1(L)        expm1(-q L) / expm1(-L)
linear   a + (b-a) s           (a + b) / 2           q (a+b) / (a + sqrt((1-q)a^2 + q b^2))
======== ===================== ===================== =====================================

Two implementations share these formulas. ``piece_mass`` and ``piece_inverse_cdf`` are the
plain ones, per piece, written as DESIGN.md states them: closed forms, and the second-order
series where ``|L| < eps^(1/3)`` (never an epsilon in a denominator). ``sample_l0`` runs a
fused form built for speed, with the same numbers to rounding (the tests hold both to a
float64 quadrature reference): ``expm1(L)`` is computed without a transcendental as
``E = (b - a) / a`` (exact to rounding, since ``b - a`` is), ``L = log1p(E)``, and
``a == b`` (``E == 0``) uses ``E = L = sqrt(tiny)``, for which ``log1p(q E) / L`` and
``a E / L`` equal their limits ``q`` and ``a`` to within 1e-19. Every closed form is exact
to rounding for ``L != 0``, so no series is needed there. Flushing sub-normal weights bounds
``|L|`` by ln(1/tiny) (87 in float32), so no exponential overflows.

``sample_neus_sections`` draws from NeuS's own opacity instead of an interpolant of the
weights. Section j, ``[z_j, z_{j+1}]``, carries the mass ``weights_j``; inside it NeuS's linear
SDF estimate runs from ``p = prev_sdf_j`` to ``n = next_sdf_j``, ``e(s) = p + (n - p) s``, and
with the logistic ``Phi(v) = sigmoid(inv_s v)`` the opacity below ``s`` is

    F(s) = (Phi(p) - Phi(e(s))) / (Phi(p) - Phi(n)).

With ``x = inv_s p``, ``y = inv_s n``, ``d = x - y >= 0`` and ``Delta = x - logit(...)`` the
quantile ``s(q) = Delta / d`` has the closed form (derived from the odds; no difference of
sigmoids is ever formed)

    Delta = log1p(A) - log1p(-B),  A = q expm1(d) sigmoid(y),  B = q (-expm1(-d)) sigmoid(-y),

both terms non-negative, so no cancellation, and ``Delta`` keeps its relative precision as
``d -> 0`` (``s -> q``, the uniform limit, is reached without a series). For ``d >= 1`` the same
terms are taken in log space (``log A = log q + d + log(-expm1(-d)) + logsigmoid(y)`` and
``1 - B = (1 - q) + q e^-d + q (1 - e^-d) sigmoid(y)``, a sum of non-negative terms), so no
exponential overflows at any sharpness. ``d < 0`` (an SDF that grows along the ray) is the
mirror image, ``s(q; x, y) = 1 - s(1 - q; y, x)``; ``d == 0`` (or a non-finite estimate) is
uniform.
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "KINDS", "check_positions", "maxblur", "neus_section_inverse_cdf", "l0_section_pieces",
    "piece_inverse_cdf", "piece_mass",
    "quantiles", "sample_l0", "sample_l0_sections", "sample_neus_sections", "sample_pdf",
    "sanitize_weights",
]

#: Interpolation kinds accepted by :func:`sample_l0`.
KINDS = ("exp", "inverse", "linear")


# ----------------------------------------------------------------------------- weights


def sanitize_weights(weights: Tensor) -> Tensor:
    """Replace NaN, +-inf and negative weights by zero.

    Args:
        weights: (..., N) any real weights.

    Returns:
        (..., N) finite, non-negative weights of the same dtype.
    """
    return torch.nan_to_num(weights, nan=0.0, posinf=0.0, neginf=0.0).clamp_min_(0.0)


def check_positions(t: Tensor, where: str = "t") -> None:
    """Refuse positions that are not finite and sorted (non-decreasing) along the last axis.

    One pass over `t` and one host synchronisation when they are fine; the samplers call it
    unless given ``check=False`` (see the module notes).

    Args:
        t: (..., N) positions along each ray.
        where: the caller and argument, for the message (``"sample_l0: t"``).

    Raises:
        ValueError: naming how many rays of the flattened batch are bad, and the first one.
    """
    rows = _rows(t.detach())
    finite = torch.isfinite(rows).all(dim=-1)  # (R,)
    ordered = (rows[:, 1:] >= rows[:, :-1]).all(dim=-1)  # (R,); NaN compares False
    if bool((finite & ordered).all()):
        return
    problems = []
    for bad, what in ((~finite, "hold NaN or inf"), (finite & ~ordered, "are not sorted")):
        n = int(bad.sum())
        if n:
            problems.append(f"{n} {what} (first: ray {int(bad.nonzero()[0, 0])})")
    raise ValueError(f"{where} must be finite and sorted along its last axis; of its "
                     f"{rows.shape[0]} rays (the batch flattened), {' and '.join(problems)}")


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
    half = 0.5 * torch.maximum(w[..., :-1], w[..., 1:])  # (..., N-1); halves: no overflow
    # h_{-1} = w_0 / 2, h_{N-1} = w_{N-1} / 2, so that w'_i = h_{i-1} + h_i + pad.
    h = torch.cat([0.5 * w[..., :1], half, 0.5 * w[..., -1:]], dim=-1)  # (..., N+1)
    return (h[..., :-1] + h[..., 1:]).add_(pad)


def _prepare_weights(weights: Tensor, dtype: torch.dtype, blur: bool, pad: float) -> Tensor:
    """Sanitise (and blur), divide by the ray maximum, and bound ratios by 1/tiny.

    Args:
        weights: (R, N) any weights.
        blur, pad: apply :func:`maxblur`. With ``pad > 0`` no weight can be 0, and weights
            below ``tiny`` (the ray maximum was above pad / tiny) are raised to ``tiny``;
            otherwise they are flushed to 0.

    Returns:
        (R, N) weights in {0} U [tiny, 1] (in [tiny, 1] with blur and pad > 0); a ray of
        zeros stays zeros.
    """
    w = weights.to(dtype)  # the samplers run without gradient: no detach needed
    # without blur only NaN and inf need replacing here: negative weights end up below tiny
    # after the division (by a positive max, or by tiny when no weight is positive) and the
    # threshold below zeroes them
    w = maxblur(w, pad) if blur else torch.nan_to_num(w, nan=0.0, posinf=0.0, neginf=0.0)
    # divided by the ray's max, at least tiny: a ray of zeros stays zeros, and a ray whose
    # max is sub-normal is scaled up by 1 / tiny instead (the draw does not depend on scale)
    w = w / w.amax(dim=-1, keepdim=True).clamp_min_(torch.finfo(dtype).tiny)  # (R, N)
    tiny = torch.finfo(dtype).tiny
    if _strictly_positive(blur, pad):
        return w.clamp_min_(tiny)
    return F.threshold(w, tiny, 0.0)  # w if w > tiny else 0: one op


def _strictly_positive(blur: bool, pad: float) -> bool:
    """Whether prepared weights can never be 0 (maxblur with a positive pad)."""
    return blur and pad > 0


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
    u = torch.rand(*shape, n_samples, generator=generator, dtype=dtype, device=device)
    u = u.add_(k).div_(n_samples)
    # (k + U)/n can round up to 1 in float32 when U is within an ulp of 1.
    return u.clamp_(max=1.0 - torch.finfo(dtype).eps)


# ----------------------------------------------------------------------------- the CDF


def _cdf(mass: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """Normalised cumulative masses, falling back to uniform where a ray has none.

    Args:
        mass: (R, M) finite non-negative piece masses.
        d: (R, M) piece lengths, used as masses (plus sqrt(tiny), so that a ray of
            zero-length pieces gets equal masses) for rays whose ``mass`` sums to 0.

    Returns:
        cdf: (R, M) the cdf at the end of each piece, contiguous; ``cdf[:, -1] == 1``
        exactly (piece i spans [cdf_{i-1}, cdf_i], cdf_{-1} = 0).
        degenerate: (R, 1) bool, True where ``mass`` was replaced.
    """
    degenerate = mass.sum(dim=-1, keepdim=True) <= 0  # (R, 1)
    mass = torch.where(degenerate, d + _flat(d.dtype), mass)
    csum = torch.cumsum(mass, dim=-1)
    return csum / csum[:, -1:], degenerate


#: On CUDA, keep the search out of Inductor's fusion (`opaque_searchsorted`): Inductor's
#: fused ``bucketize_binary_search`` inside a reduction kernel failed to compile in Triton
#: (torch 2.11, Triton 3.6). ``NEUS_L0_OPAQUE_SEARCHSORTED=0`` turns it off. The CPU keeps
#: the fused search.
OPAQUE_SEARCHSORTED_ON_CUDA = os.environ.get("NEUS_L0_OPAQUE_SEARCHSORTED", "1") != "0"


@torch.library.custom_op("neus_l0::searchsorted_right", mutates_args=())
def opaque_searchsorted(sorted_seq: Tensor, values: Tensor) -> Tensor:
    """``torch.searchsorted(sorted_seq, values, right=True)`` as an op Inductor cannot
    fuse (it calls the eager kernel).

    Args:
        sorted_seq: (R, M) sorted rows; values: (R, n).

    Returns:
        (R, n) int64.
    """
    return torch.searchsorted(sorted_seq, values, right=True)


@opaque_searchsorted.register_fake
def _(sorted_seq: Tensor, values: Tensor) -> Tensor:
    return values.new_empty(values.shape, dtype=torch.int64)


def search_right(cdf: Tensor, u: Tensor) -> Tensor:
    """`torch.searchsorted(cdf, u, right=True)`, through `opaque_searchsorted` on CUDA
    while `OPAQUE_SEARCHSORTED_ON_CUDA`."""
    if cdf.is_cuda and OPAQUE_SEARCHSORTED_ON_CUDA:
        return opaque_searchsorted(cdf.contiguous(), u.contiguous())
    return torch.searchsorted(cdf, u, right=True)


def _locate(cdf: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The piece of each quantile and the cdf at its ends.

    Args:
        cdf: (R, M) from `_cdf`, the cdf at the pieces' ends. u: (R, n) quantiles in [0, 1).

    Returns:
        idx (R, n) int64, the piece i with cdf_{i-1} <= u < cdf_i; lo, hi (R, n) the cdf at
        its ends (hi > lo: a piece that holds a quantile has mass).
    """
    idx = search_right(cdf, u).clamp_(max=cdf.shape[-1] - 1)
    starts = F.pad(cdf, (1, 0))  # (R, M+1): piece i starts at starts[:, i]
    return idx, torch.gather(starts, -1, idx), torch.gather(cdf, -1, idx)


def _fraction(u: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """q = (u - lo) / (hi - lo) in [0, 1], the quantile's position in its piece; all (R, n).

    hi > lo (`_locate`), so the division is finite; the clamp repairs rounding.
    """
    return ((u - lo) / (hi - lo)).clamp_(0.0, 1.0)


def _finish(samples: Tensor, t: Tensor) -> Tensor:
    """Clamp samples into [t_0, t_last] and repair 1-ulp disorder from rounding.

    Args:
        samples: (R, n) samples, sorted up to rounding.
        t: (R, N) the sorted nodes or bin edges they were drawn between.

    Returns:
        (R, n) sorted samples inside [t_0, t_last].
    """
    # max(cummax(s), t_0) == cummax(max(s, t_0)): one clamp against both ends after
    return torch.clamp(torch.cummax(samples, dim=-1).values, t[:, :1], t[:, -1:])


# ----------------------------------------------------------------------------- samplers


@torch.no_grad()
def sample_pdf(bins: Tensor, weights: Tensor, n_samples: int, det: bool = True,
               generator: torch.Generator | None = None, u: Tensor | None = None,
               lengths: Tensor | None = None, check: bool = True) -> Tensor:
    """NeRF's hierarchical volume sampling: inverse transform of a piecewise-constant PDF.

    Args:
        bins: (..., N+1) sorted bin edges.
        weights: (..., N) weight of each bin (any values; see the module notes).
        n_samples: n, samples per ray.
        det: midpoint quantiles ``(k + 0.5) / n`` instead of stratified random ones.
        generator: random source for ``det=False``.
        u: (R, n) quantiles drawn beforehand (see `sample_l0`).
        lengths: (..., N) the bins' lengths ``bins[1:] - bins[:-1]`` when the caller has
            them (NeuS's up-sampling does), else None.
        check: refuse bins that are not finite and sorted (`check_positions`; False: the
            caller guarantees them, and no host synchronisation happens).

    Returns:
        (..., n) sorted samples inside [bins_0, bins_N], without gradient.

    Raises:
        ValueError: shapes that disagree, no bin, or (with `check`) bad bins.
    """
    if bins.shape[-1] != weights.shape[-1] + 1:
        raise ValueError(f"bins (..., N+1) and weights (..., N) disagree: "
                         f"{tuple(bins.shape)} vs {tuple(weights.shape)}")
    if weights.shape[-1] < 1:
        raise ValueError("sample_pdf needs at least one bin")
    if check:
        check_positions(bins, "sample_pdf: bins")
    batch = bins.shape[:-1]
    bins = _rows(bins)  # (R, N+1); no gradient here, so no detach
    w = _prepare_weights(_rows(weights), bins.dtype, False, 0.0)
    lo_edge = bins[:, :-1]
    # sorted bins: lengths >= 0 (the clamp guards hand-made bins)
    d = (bins[:, 1:] - lo_edge).clamp_min_(0) if lengths is None else _rows(lengths)  # (R, N)
    cdf, _ = _cdf(w, d)
    if u is None:
        u = quantiles((bins.shape[0],), n_samples, det, generator, bins.dtype, bins.device)
    idx, lo, hi = _locate(cdf, u)  # (R, n)
    q = _fraction(u, lo, hi)
    out = torch.addcmul(torch.gather(lo_edge, -1, idx), q, torch.gather(d, -1, idx))
    return _unrows(_finish(out, bins), batch)


@torch.no_grad()
def sample_l0(t: Tensor, weights: Tensor, n_samples: int, kind: str = "exp",
              det: bool = True, blur: bool = True, pad: float = 0.01,
              generator: torch.Generator | None = None, u: Tensor | None = None,
              check: bool = True) -> Tensor:
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
        u: (R, n) the quantiles (`quantiles`) drawn beforehand, R the rays of the flattened
            batch (None: drawn here from `det` and `generator`).
        check: refuse positions that are not finite and sorted (`check_positions`; False:
            the caller guarantees them, and no host synchronisation happens).

    Returns:
        (..., n) sorted samples inside [t_0, t_{N-1}], without gradient.

    Raises:
        ValueError: an unknown kind, shapes that disagree, N < 2, or (with `check`) bad
            positions.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown L0 kind {kind!r}; expected one of {KINDS}")
    if t.shape != weights.shape:
        raise ValueError(f"t and weights must have the same shape (..., N): "
                         f"{tuple(t.shape)} vs {tuple(weights.shape)}")
    if t.shape[-1] < 2:
        raise ValueError("sample_l0 needs at least two positions per ray (N >= 2)")
    if check:
        check_positions(t, "sample_l0: t")
    batch = t.shape[:-1]
    t, weights = _rows(t), _rows(weights)  # (R, N); no gradient here, so no detach
    w = _prepare_weights(weights, t.dtype, blur, pad)  # (R, N)
    a, b = w[:, :-1], w[:, 1:]  # (R, M) endpoint weights of the M = N-1 intervals
    t_lo = t[:, :-1]
    d = (t[:, 1:] - t_lo).clamp_min_(0)  # (R, M) lengths
    if u is None:
        u = quantiles((t.shape[0],), n_samples, det, generator, t.dtype, t.device)  # (R, n)
    zeros = not _strictly_positive(blur, pad)  # can a piece have a zero end?
    sampler = {"exp": _fused_exp, "inverse": _fused_inverse, "linear": _fused_linear}[kind]
    return _unrows(_finish(sampler(a, b, d, t_lo, u, zeros), t), batch)


def _rows(x: Tensor) -> Tensor:
    """(..., K) -> (R, K), without an op when x is already 2-D."""
    return x if x.dim() == 2 else x.reshape(-1, x.shape[-1])


def _unrows(x: Tensor, batch: torch.Size) -> Tensor:
    """(R, K) -> (..., K) for the leading shape `batch`, without an op when it is 1-D."""
    return x if len(batch) == 1 else x.reshape(*batch, x.shape[-1])


def _growth(a: Tensor, b: Tensor, zeros: bool) -> tuple[Tensor, Tensor]:
    """E = expm1(L) = (b - a) / a and L = ln(b/a) per piece, with the module's conventions.

    ``L = sign(b - a) log1p(|b - a| / min(a, b))``: the argument of log1p is exact to
    rounding whichever end is larger, so L keeps full relative precision both when a ~ b
    and when one end is far below the other (where log1p(E), E ~ -1, would not). Both E
    and the log1p argument get ``sqrt(tiny)`` added: a no-op in floating point for every
    piece with a != b (their magnitude is at least eps / 2, and eps^2 / 4 > sqrt(tiny)),
    and the value that stands for a constant piece where a == b.

    Args:
        a, b: (R, M) endpoint weights in {0} U [tiny, 1].
        zeros: whether a or b can be 0 (else the masking is skipped).

    Returns:
        E: (R, M); -1 where a == 0 or b == 0 (L = -inf there: such pieces have no mass).
        L: (R, M).
    """
    flat = _flat(a.dtype)
    diff = b - a
    E = (diff / a).add_(flat)
    low = torch.minimum(a, b)
    L = torch.log1p(diff.abs().div_(low).add_(flat)).copysign_(diff)
    if zeros:
        empty = low <= 0  # a == 0 or b == 0
        E = E.masked_fill_(empty, -1.0)
        L = L.masked_fill_(empty, -float("inf"))
    return E, L


def _flat(dtype: torch.dtype) -> float:
    """The growth sqrt(tiny) that stands for a constant piece (its L equals it too)."""
    return float(torch.finfo(dtype).tiny) ** 0.5


def _make_flat(E: Tensor, L: Tensor, degenerate: Tensor) -> tuple[Tensor, Tensor]:
    """Turn every piece of the (R, 1) ``degenerate`` rays constant (uniform fallback)."""
    flat = _flat(E.dtype)
    return E.masked_fill(degenerate, flat), L.masked_fill(degenerate, flat)


def _fused_exp(a: Tensor, b: Tensor, d: Tensor, t_lo: Tensor, u: Tensor,
               zeros: bool) -> Tensor:
    """Exponential pieces: mass ``a E / L``, position ``t_lo + D log1p(q E) / L``.

    Args:
        a, b: (R, M) endpoint weights in {0} U [tiny, 1]. d: (R, M) lengths.
        t_lo: (R, M) starts. u: (R, n) sorted quantiles.
        zeros: whether a or b can be 0.

    Returns:
        (R, n) positions, sorted up to rounding.
    """
    E, L = _growth(a, b, zeros)
    mass = (a * E).div_(L).mul_(d)  # a == 0 or b == 0: E = -1, L = -inf, mass 0
    return _draw_exp(E, L, mass, d, t_lo, u, zeros)


def _draw_exp(E: Tensor, L: Tensor, mass: Tensor, d: Tensor, t_lo: Tensor, u: Tensor,
              zeros: bool) -> Tensor:
    """The inverse transform of exponential pieces given their growth and masses.

    Args:
        E, L: (R, M) growths (`_growth`). mass: (R, M) piece masses. d: (R, M) lengths.
        t_lo: (R, M) starts. u: (R, n) sorted quantiles.
        zeros: whether a piece can have a zero end.

    Returns:
        (R, n) positions, sorted up to rounding.
    """
    cdf, degenerate = _cdf(mass, d)
    if zeros:  # else a ray without mass has only zero-length pieces: any E, L will do
        E, L = _make_flat(E, L, degenerate)  # uniform fallback: constant pieces
    idx, lo, hi = _locate(cdf, u)
    # q E with q = (u - lo) / (hi - lo) unclamped in [0, 1] and E finite: finite
    y = ((u - lo) / (hi - lo)).mul_(torch.gather(E, -1, idx))
    x = torch.log1p(y.clamp_(min=-1.0 + torch.finfo(E.dtype).eps))
    return torch.addcmul(torch.gather(t_lo, -1, idx), x, torch.gather(d / L, -1, idx))


def _fused_inverse(a: Tensor, b: Tensor, d: Tensor, t_lo: Tensor, u: Tensor,
                   zeros: bool) -> Tensor:
    """Inverse (hyperbolic) pieces: mass ``b L / E``, position ``t_lo + D expm1(-qL)/expm1(-L)``.

    Args and returns as :func:`_fused_exp`.
    """
    E, L = _growth(a, b, zeros)
    mass = torch.where(torch.isfinite(L), b * L / E, 0.0).mul_(d)  # L = -inf: no mass
    cdf, degenerate = _cdf(mass, d)
    if zeros:
        E, L = _make_flat(E, L, degenerate)
    idx, lo, hi = _locate(cdf, u)
    q = _fraction(u, lo, hi)
    # s = expm1(-q L) / expm1(-L), with the series where |L| is small: constant pieces carry
    # L = sqrt(tiny), and compiled kernels' expm1 of so small an argument can be 0 (then
    # the ratio is 0 / 0), where libm's is exact (|L| <= 88 here, so no overflow)
    Li = torch.gather(L, -1, idx)  # (R, n)
    small = Li.abs() < _series_threshold(Li.dtype)
    Ls = torch.where(small, 1.0, Li)
    series = q + q * (1.0 - q) * Li * (0.5 + (1.0 - 2.0 * q) * Li / 12.0)
    s = torch.where(small, series, torch.expm1(-q * Ls) / torch.expm1(-Ls))
    return torch.addcmul(torch.gather(t_lo, -1, idx), s, torch.gather(d, -1, idx))


def _fused_linear(a: Tensor, b: Tensor, d: Tensor, t_lo: Tensor, u: Tensor,
                  zeros: bool) -> Tensor:
    """Linear pieces: mass ``(a + b) / 2``, position from the quadratic's stable root.

    Args and returns as :func:`_fused_exp`.
    """
    cdf, degenerate = _cdf((0.5 * (a + b)).mul_(d), d)
    idx, lo, hi = _locate(cdf, u)
    q = _fraction(u, lo, hi)
    one = torch.ones((), dtype=a.dtype, device=a.device)
    ai = torch.gather(torch.where(degenerate, one, a), -1, idx)
    bi = torch.gather(torch.where(degenerate, one, b), -1, idx)
    s = piece_inverse_cdf(ai, bi, q, "linear")
    return torch.addcmul(torch.gather(t_lo, -1, idx), s, torch.gather(d, -1, idx))


# ----------------------------------------------------------------------------- one piece


def _series_threshold(dtype: torch.dtype) -> float:
    """|L| below which the plain forms switch to their series (eps^(1/3): truncation < eps)."""
    return float(torch.finfo(dtype).eps) ** (1.0 / 3.0)


def _log_ratio(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """L = ln b - ln a where both are positive, else 0; and the mask of those pieces."""
    positive = (a > 0) & (b > 0)
    one = torch.ones((), dtype=a.dtype, device=a.device)
    L = torch.log(torch.where(positive, b, one)) - torch.log(torch.where(positive, a, one))
    return L, positive


def _expm1_over(L: Tensor, small: Tensor) -> Tensor:
    """f(L) = expm1(L) / L, with its series 1 + L/2 + L^2/6 where ``small``."""
    series = 1.0 + L * (0.5 + L / 6.0)
    return torch.where(small, series, torch.expm1(L) / torch.where(small, 1.0, L))


def piece_mass(a: Tensor, b: Tensor, kind: str) -> Tensor:
    """Mass per unit length of one interpolated piece (the plain, per-piece form).

    ``exp``: the logarithmic mean ``(b - a) / ln(b/a)``: ``a expm1(L) / L`` for ``L <= 1``,
    ``(b - a) / L`` above (no overflow); ``inverse``: ``b L / expm1(L)``; ``linear``:
    ``(a + b) / 2``. Series where ``|L|`` is tiny; 0 where a or b is 0 (exp, inverse).

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
    small = L.abs() < _series_threshold(a.dtype)
    if kind == "exp":
        big = L > 1.0
        near = a * _expm1_over(torch.where(big, 0.0, L), small | big)
        per = torch.where(big, (b - a) / torch.where(big, L, 1.0), near)
    else:
        per = b / _expm1_over(L.clamp_max(80.0), small)
    return torch.where(positive, per, 0.0)


def piece_inverse_cdf(a: Tensor, b: Tensor, q: Tensor, kind: str) -> Tensor:
    """Position s in [0, 1] below which a piece holds the fraction q of its mass.

    The plain, per-piece form: closed forms, the second-order series where
    ``|L| < eps^(1/3)`` (exp: ``q + q(1-q)L/2 + q(1-q)(1-2q)L^2/6``; inverse:
    ``q + q(1-q)L/2 + q(1-q)(1-2q)L^2/12``), and overflow-free rewrites where ``|L| > 60``.

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
        return s.clamp(0.0, 1.0)
    L, positive = _log_ratio(a, b)
    small = L.abs() < _series_threshold(a.dtype)
    Ls = torch.where(small, 1.0, L)
    if kind == "exp":
        direct = torch.log1p(q * torch.expm1(Ls.clamp_max(60.0))) / Ls
        far = 1.0 + torch.log(q + (1.0 - q) * torch.exp(-Ls.clamp_min(1.0))) / Ls
        closed = torch.where(Ls > 60.0, far, direct)
        series = q + q * (1.0 - q) * L * (0.5 + (1.0 - 2.0 * q) * L / 6.0)
    else:
        M = -Ls  # s = expm1(q M) / expm1(M)
        direct = torch.expm1(q * M.clamp_max(60.0)) / torch.expm1(M.clamp_max(60.0))
        Mf = M.clamp_min(1.0)
        far = torch.exp((q - 1.0) * Mf) * torch.expm1(-q * Mf) / torch.expm1(-Mf)
        closed = torch.where(M > 60.0, far, direct)
        series = q + q * (1.0 - q) * L * (0.5 + (1.0 - 2.0 * q) * L / 12.0)
    s = torch.where(small, series, closed)
    return torch.where(positive, s, q).clamp(0.0, 1.0)


# ----------------------------------------------------------------------------- NeuS sections


def neus_section_inverse_cdf(x: Tensor, y: Tensor, q: Tensor) -> Tensor:
    """Position s in [0, 1] below which a NeuS section holds the fraction q of its opacity.

    The section's logit runs linearly from ``x = inv_s * prev_sdf`` (s = 0) to
    ``y = inv_s * next_sdf`` (s = 1); the opacity density is ``sigmoid'(x + (y - x) s)``.
    See the module notes for the closed form and why it is stable.

    Args:
        x: (...) logit at the start of the section.
        y: (...) logit at its end.
        q: (...) opacity fractions in [0, 1].

    Returns:
        (...) s in [0, 1]; uniform (s = q) where x == y or x, y are not finite.
    """
    x, y, q = torch.broadcast_tensors(x, y, q)
    swap = y > x  # the mirror image: s(q; x, y) = 1 - s(1 - q; y, x)
    hi, lo = torch.where(swap, y, x), torch.where(swap, x, y)
    q = torch.where(swap, 1.0 - q, q)
    d = hi - lo  # (...) >= 0, or NaN
    ok = torch.isfinite(d) & (d >= torch.finfo(d.dtype).tiny)
    d = torch.where(ok, d, 1.0)
    lo = torch.where(ok, lo, 0.0)
    small = d < 1.0
    ds = torch.where(small, d, 0.0)  # d < 1: direct, no overflow, B <= 1 - 1/e
    A = q * torch.expm1(ds) * torch.sigmoid(lo)
    B = q * -torch.expm1(-ds) * torch.sigmoid(-lo)
    near = torch.log1p(A) - torch.log1p(-B)
    dl = torch.where(small, 1.0, d)  # d >= 1: log space
    log_m = torch.log(-torch.expm1(-dl))  # log(1 - e^-d), in [log(1 - 1/e), 0]
    log_q, log_q1, log_sy = torch.log(q), torch.log1p(-q), F.logsigmoid(lo)
    log_a = log_q + dl + log_m + log_sy
    log_1mb = torch.logsumexp(torch.stack([log_q1, log_q - dl, log_q + log_m + log_sy]), 0)
    far = F.softplus(log_a) - log_1mb
    s = (torch.where(small, near, far) / d).clamp(0.0, 1.0)
    s = torch.where(ok, s, q)
    return torch.where(swap, 1.0 - s, s)


@torch.no_grad()
def sample_neus_sections(z: Tensor, weights: Tensor, prev_sdf: Tensor, next_sdf: Tensor,
                         inv_s: float | Tensor, n_samples: int, det: bool = True,
                         generator: torch.Generator | None = None,
                         check: bool = True) -> Tensor:
    """Inverse transform of NeuS's own opacity: section masses, then the exact CDF inside.

    Args:
        z: (..., N) sorted section ends, N >= 2.
        weights: (..., N-1) mass of each section [z_j, z_{j+1}] (any values; see the module
            notes: non-finite and negative count as zero, a ray without mass is uniform).
        prev_sdf, next_sdf: (..., N-1) NeuS's linear SDF estimate at the start and end of
            each section (`prev_esti` / `next_esti` of its up-sampling).
        inv_s: the logistic sharpness, a number or a tensor broadcastable to (..., N-1).
        n_samples: n, samples per ray.
        det: midpoint quantiles ``(k + 0.5) / n`` instead of stratified random ones.
        generator: random source for ``det=False``.
        check: refuse section ends that are not finite and sorted (`check_positions`;
            False: the caller guarantees them, and no host synchronisation happens).

    Returns:
        (..., n) sorted samples inside [z_0, z_{N-1}], without gradient.

    Raises:
        ValueError: N < 2, shapes that disagree, or (with `check`) bad section ends.
    """
    N = z.shape[-1]
    if N < 2:
        raise ValueError("sample_neus_sections needs at least two section ends (N >= 2)")
    for name, v in (("weights", weights), ("prev_sdf", prev_sdf), ("next_sdf", next_sdf)):
        if v.shape != (*z.shape[:-1], N - 1):
            raise ValueError(f"z (..., N) and {name} (..., N-1) disagree: "
                             f"{tuple(z.shape)} vs {tuple(v.shape)}")
    if check:
        check_positions(z, "sample_neus_sections: z")
    batch = z.shape[:-1]
    dtype = z.dtype
    z = z.detach().reshape(-1, N)  # (R, N)
    w = _prepare_weights(weights.reshape(-1, N - 1), dtype, False, 0.0)  # (R, N-1)
    k = torch.as_tensor(inv_s, dtype=dtype, device=z.device).detach()
    x = (prev_sdf.detach().to(dtype) * k).expand(*batch, N - 1).reshape(-1, N - 1)
    y = (next_sdf.detach().to(dtype) * k).expand(*batch, N - 1).reshape(-1, N - 1)
    d = (z[:, 1:] - z[:, :-1]).clamp_min(0)  # (R, N-1)
    cdf, degenerate = _cdf(w, d)
    u = quantiles((z.shape[0],), n_samples, det, generator, dtype, z.device)  # (R, n)
    idx, lo, hi = _locate(cdf, u)
    q = _fraction(u, lo, hi)
    s = neus_section_inverse_cdf(torch.gather(x, -1, idx), torch.gather(y, -1, idx), q)
    s = torch.where(degenerate, q, s)  # a ray without mass: uniform inside each section too
    out = torch.addcmul(torch.gather(z[:, :-1], -1, idx), s, torch.gather(d, -1, idx))
    return _finish(out, z).reshape(*batch, n_samples)


# ----------------------------------------------------------------------------- L0 in sections


def _boundary_values(rho: Tensor, d: Tensor, kind: str) -> Tensor:
    """The interpolant's value at the section ends, from the section densities at midpoints.

    Between the midpoints of sections j-1 and j the shared end z_j lies at the fraction
    ``f = d_{j-1} / (d_{j-1} + d_j)``; there the kind's interpolant between ``rho_{j-1}`` and
    ``rho_j`` takes the value: ``exp`` the weighted geometric mean, ``linear`` the weighted
    arithmetic mean, ``inverse`` the weighted harmonic mean (0 where either is 0). The two
    outer ends repeat the outer sections' densities.

    Args:
        rho: (R, M) non-negative section densities; d: (R, M) section lengths.
        kind: ``exp``, ``inverse`` or ``linear``.

    Returns:
        (R, M+1) values at z_0 .. z_M.
    """
    a, b = rho[:, :-1], rho[:, 1:]  # (R, M-1) the two sections around each inner end
    span = d[:, :-1] + d[:, 1:]
    f = torch.where(span > 0, d[:, :-1] / torch.where(span > 0, span, 1.0), 0.5)
    if kind == "linear":
        inner = torch.lerp(a, b, f)
    elif kind == "exp":  # a^(1-f) b^f: 0 where either is 0 (0^x = 0 for x > 0), no log
        inner = a.pow(1.0 - f).mul_(b.pow(f))
    else:
        positive = (a > 0) & (b > 0)
        sa, sb = torch.where(positive, a, 1.0), torch.where(positive, b, 1.0)
        inner = torch.where(positive, 1.0 / torch.lerp(1.0 / sa, 1.0 / sb, f), 0.0)
    return torch.cat([rho[:, :1], inner, rho[:, -1:]], dim=-1)


@torch.no_grad()
def sample_l0_sections(z: Tensor, weights: Tensor, n_samples: int, kind: str = "exp",
                       det: bool = True, generator: torch.Generator | None = None,
                       u: Tensor | None = None, check: bool = True) -> Tensor:
    """The L0 interpolant inside NeuS's sections, each section keeping its own mass.

    The L0-Sampler's nodes are the section midpoints ``m_j`` with the section densities
    ``rho_j = w_j / d_j``; between nodes the weights are interpolated by the kind's law
    (`piece_inverse_cdf`). `sample_l0` draws from that interpolant as a whole, so a section's
    share of the samples is the interpolant's mass over it, not NeuS's weight. Here each
    section gets exactly its weight's share, as in NeuS's piecewise-constant draw
    (`sample_pdf`), and only the position inside the section follows the interpolant: two
    pieces, ``[z_j, m_j]`` from the end value ``g_j`` (`_boundary_values`) to ``rho_j``, and
    ``[m_j, z_{j+1}]`` from ``rho_j`` to ``g_{j+1}``, split by their masses. A section whose
    two pieces carry no mass (an exponential piece with a zero end) is sampled uniformly.

    Args:
        z: (..., N) sorted section ends, N >= 2.
        weights: (..., N-1) mass of each section (any values; see the module notes).
        n_samples: n, samples per ray.
        kind: ``exp``, ``inverse`` or ``linear``.
        det: midpoint quantiles ``(k + 0.5) / n`` instead of stratified random ones.
        generator: random source for ``det=False``.
        u: (R, n) the quantiles drawn beforehand (`quantiles`), R the rays of the flattened
            batch (None: drawn here from `det` and `generator`).
        check: refuse section ends that are not finite and sorted (`check_positions`;
            False: the caller guarantees them, and no host synchronisation happens).

    Returns:
        (..., n) sorted samples inside [z_0, z_{N-1}], without gradient.

    Raises:
        ValueError: an unknown kind, N < 2, shapes that disagree, or (with `check`) bad
            section ends.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown L0 kind {kind!r}; expected one of {KINDS}")
    N = z.shape[-1]
    if N < 2:
        raise ValueError("sample_l0_sections needs at least two section ends (N >= 2)")
    if weights.shape != (*z.shape[:-1], N - 1):
        raise ValueError(f"z (..., N) and weights (..., N-1) disagree: "
                         f"{tuple(z.shape)} vs {tuple(weights.shape)}")
    if check:
        check_positions(z, "sample_l0_sections: z")
    batch = z.shape[:-1]
    z, weights = _rows(z.detach()), _rows(weights)  # (R, N), (R, M)
    w = _prepare_weights(weights, z.dtype, False, 0.0)  # (R, M)
    if u is None:
        u = quantiles((z.shape[0],), n_samples, det, generator, z.dtype, z.device)  # (R, n)
    if kind == "exp":
        out = _sections_exp(z, w, u)
    else:
        a, b, d, t_lo = _half_pieces(z, w, kind)  # (R, 2M) each
        out = {"inverse": _fused_inverse, "linear": _fused_linear}[kind](a, b, d, t_lo, u, True)
    return _unrows(_finish(out, z), batch)


def _section_geometry(z: Tensor, w: Tensor, kind: str) -> tuple[Tensor, Tensor, Tensor]:
    """Section lengths d (R, M), densities rho (R, M, max 1) and end values g (R, M+1)."""
    d = (z[:, 1:] - z[:, :-1]).clamp_min(0)  # (R, M)
    tiny = torch.finfo(z.dtype).tiny
    rho = w / torch.maximum(d, 1e-3 * d.mean(dim=-1, keepdim=True)).clamp_min(tiny)
    rho = rho / rho.amax(dim=-1, keepdim=True).clamp_min(tiny)
    rho = rho.masked_fill_(rho < tiny, 0.0)  # {0} U [tiny, 1], as `_growth` expects
    return d, rho, _boundary_values(rho, d, kind)


def _unscaled_half_pieces(z: Tensor, w: Tensor, kind: str
                          ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The two pieces of each section before they are scaled to the section weights.

    Section j, ``[z_j, z_{j+1}]`` with midpoint ``m_j``, becomes the pieces ``[z_j, m_j]``
    (from ``g_j`` to ``rho_j``) and ``[m_j, z_{j+1}]`` (from ``rho_j`` to ``g_{j+1}``).

    Args:
        z: (R, M+1) sorted section ends. w: (R, M) prepared section weights.
        kind: ``exp``, ``inverse`` or ``linear`` (how the end values are interpolated).

    Returns:
        a, b, half, t_lo: (R, 2M) piece start and end values, lengths and starts, in order;
        d: (R, M) the section lengths.
    """
    R, M = w.shape
    d, rho, g = _section_geometry(z, w, kind)
    a = torch.stack([g[:, :-1], rho], dim=-1).reshape(R, 2 * M)
    b = torch.stack([rho, g[:, 1:]], dim=-1).reshape(R, 2 * M)
    half = (0.5 * d)[..., None].expand(R, M, 2).reshape(R, 2 * M)
    t_lo = torch.stack([z[:, :-1], z[:, :-1] + 0.5 * d], dim=-1).reshape(R, 2 * M)
    return a, b, half, t_lo, d


def _section_shares(mass: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Rescale the half pieces' masses so that each section carries its weight.

    Args:
        mass: (R, 2M) the interpolant's masses of the half pieces. w: (R, M) weights.

    Returns:
        mass: (R, 2M) rescaled (a section whose pieces carry no mass gives each half w / 2);
        flat: (R, 2M) bool, the halves of those sections (to be drawn as constant pieces).
    """
    R, M = w.shape
    mass = mass.reshape(R, M, 2)
    inner = mass.sum(dim=-1, keepdim=True)  # (R, M, 1)
    empty = inner <= 0  # no interpolant mass (a zero end): constant at the density
    mass = torch.where(empty, 0.5, mass / torch.where(empty, 1.0, inner)).mul_(w[..., None])
    return mass.reshape(R, 2 * M), empty.expand(R, M, 2).reshape(R, 2 * M)


def _sections_exp(z: Tensor, w: Tensor, u: Tensor) -> Tensor:
    """`sample_l0_sections` for the exponential kind, fused: the growths are computed once.

    A piece's growth (E, L) does not change when the piece is scaled, so the half pieces'
    masses are rescaled to the section weights without recomputing them.

    Args:
        z: (R, M+1) section ends. w: (R, M) prepared weights. u: (R, n) quantiles.

    Returns:
        (R, n) positions, sorted up to rounding.
    """
    a, b, half, t_lo, _ = _unscaled_half_pieces(z, w, "exp")
    E, L = _growth(a, b, True)
    mass, flat = _section_shares((a * E).div_(L).mul_(half), w)
    E, L = E.masked_fill(flat, _flat(E.dtype)), L.masked_fill(flat, _flat(E.dtype))
    return _draw_exp(E, L, mass, half, t_lo, u, True)


def l0_section_pieces(z: Tensor, weights: Tensor, kind: str = "exp"
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pieces `sample_l0_sections` draws from, for plots: two per section, in order.

    Args:
        z: (R, N) sorted section ends. weights: (R, N-1) section weights (any values).
        kind: ``exp``, ``inverse`` or ``linear``.

    Returns:
        a, b, d, t_lo: (R, 2(N-1)) each piece's density at its start and end (the densities
        integrate to the prepared weights: each ray's weights over their maximum), its length
        and its start.
    """
    z = z.detach()
    w = _prepare_weights(weights.reshape(z.shape[0], -1), z.dtype, False, 0.0)
    return _half_pieces(z, w, kind)


def _half_pieces(z: Tensor, w: Tensor, kind: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The two pieces of each section (`_unscaled_half_pieces`), scaled so that the section's
    mass is its weight (a scale changes no shape); a section with weight whose pieces carry
    no mass (an exponential or inverse piece with a zero end) becomes constant at w_j / d_j.

    Args:
        z: (R, M+1) sorted section ends. w: (R, M) prepared section weights.
        kind: ``exp``, ``inverse`` or ``linear``.

    Returns:
        a, b, d, t_lo: (R, 2M) piece start and end values (densities, divided by the ray's
        largest value: a section's pieces integrate to its weight over that), lengths and
        starts, in order.
    """
    a, b, half, t_lo, d = _unscaled_half_pieces(z, w, kind)
    own = piece_mass(a, b, kind) * half  # (R, 2M) the interpolant's masses
    mass, flat = _section_shares(own, w)
    scale = torch.where(own > 0, mass / torch.where(own > 0, own, 1.0), 0.0)
    level = (w / torch.where(d > 0, d, 1.0)).repeat_interleave(2, dim=-1)  # w_j / d_j
    a = torch.where(flat, level, a * scale)
    b = torch.where(flat, level, b * scale)
    # the fused samplers take values in {0} U [tiny, 1]: one scale per ray changes no draw
    top = torch.maximum(a, b).amax(dim=-1, keepdim=True).clamp_min(torch.finfo(a.dtype).tiny)
    tiny = torch.finfo(a.dtype).tiny
    a, b = a / top, b / top
    return a.masked_fill_(a < tiny, 0.0), b.masked_fill_(b < tiny, 0.0), half, t_lo
