"""The samplers against a float64 quadrature reference, closed forms and distributions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from reference_sampling import (
    l0_cdf,
    mass,
    sample_l0_ref,
    sample_pdf_ref,
)
from reference_sampling import (
    maxblur as maxblur_ref,
)

from neus_l0.sampling.kernels import (
    KINDS,
    maxblur,
    piece_inverse_cdf,
    piece_mass,
    quantiles,
    sample_l0,
    sample_pdf,
)

DTYPES = [torch.float32, torch.float64]


def _ray(rng: np.random.Generator, n: int, spiky: bool = True):
    """Sorted positions (uneven spacing) and NeuS-like weights: a bump plus noise."""
    t = np.sort(rng.uniform(0.5, 3.0, n))
    t[0], t[-1] = 0.5, 3.0
    centre = rng.uniform(1.0, 2.5)
    w = np.exp(-0.5 * ((t - centre) / rng.uniform(0.02, 0.3)) ** 2)
    if spiky:
        w = w + rng.uniform(0, 0.05, n) * (rng.uniform(size=n) < 0.3)
    return t, w


# ---------------------------------------------------------------- maxblur


def test_maxblur_matches_loop():
    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 17):
        w = rng.uniform(0, 1, n)
        got = maxblur(torch.tensor(w, dtype=torch.float64), pad=0.01).numpy()
        np.testing.assert_allclose(got, maxblur_ref(w, 0.01), rtol=0, atol=1e-15)


def test_maxblur_closed_form_on_a_spike():
    w = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0], dtype=torch.float64)
    got = maxblur(w, pad=0.0)
    # The spike spreads to its neighbours at half height and stays at the centre.
    assert got.tolist() == [0.0, 0.5, 1.0, 0.5, 0.0]
    assert maxblur(w, pad=0.01).min().item() == pytest.approx(0.01)


def test_maxblur_treats_non_finite_as_zero_and_never_overflows():
    w = torch.tensor([float("nan"), float("inf"), -3.0, 3e38, 3e38], dtype=torch.float32)
    got = maxblur(w, pad=0.0)
    assert torch.isfinite(got).all()
    assert got[0] == 0 and got[-1] == pytest.approx(3e38, rel=1e-6)


# ---------------------------------------------------------------- one piece


@pytest.mark.parametrize("kind", ["exp", "inverse", "linear"])
def test_piece_mass_matches_quadrature(kind):
    pairs = [(1.0, 1.0), (0.3, 0.3 * (1 + 1e-9)), (0.3, 0.3 * (1 + 1e-6)),
             (0.3, 0.3 * (1 + 1e-3)), (1.0, 2.0), (2.0, 1.0), (0.01, 1.0), (1.0, 1e-30),
             (1e-30, 1.0), (0.5, 0.0), (0.0, 0.5), (0.0, 0.0), (1e-12, 1e-12)]
    a = torch.tensor([p[0] for p in pairs], dtype=torch.float64)
    b = torch.tensor([p[1] for p in pairs], dtype=torch.float64)
    got = piece_mass(a, b, kind).numpy()
    want = np.array([mass(kind, *p) for p in pairs])
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-300)


def test_piece_mass_closed_forms():
    a = torch.tensor([1.0, 2.0], dtype=torch.float64)
    b = torch.tensor([math.e, 2.0], dtype=torch.float64)
    # exp: logarithmic mean (b - a) / ln(b/a); a == b gives a.
    assert piece_mass(a, b, "exp").tolist() == pytest.approx([math.e - 1.0, 2.0], rel=1e-14)
    # inverse: ab ln(b/a) / (b - a).
    assert piece_mass(a, b, "inverse").tolist() == pytest.approx([math.e / (math.e - 1.0), 2.0],
                                                                 rel=1e-14)


@pytest.mark.parametrize("kind", ["exp", "inverse", "linear"])
@pytest.mark.parametrize("dtype", DTYPES)
def test_piece_inverse_cdf_against_root_finding(kind, dtype):
    from reference_sampling import invert_piece

    rng = np.random.default_rng(1)
    pairs = [(1.0, 1.0), (0.4, 0.4 * (1 + 1e-7)), (0.4, 0.4 * (1 + 2e-3)), (1.0, 3.0),
             (3.0, 1.0), (1e-30, 1.0), (1.0, 1e-30), (1e-20, 1e-10), (0.2, 0.9)]
    qs = np.concatenate([[0.0, 1e-9, 0.5, 1 - 1e-7], rng.uniform(0, 1, 6)])
    # The reference gets the inputs as the tested dtype rounds them: near q = 1 (q = 0 when
    # the piece grows) s is ill-conditioned, and rounding q is not the sampler's error.
    qs = torch.tensor(qs, dtype=dtype).double().numpy()
    for a, b in pairs:
        if kind == "linear" and (a < 1e-10 or b < 1e-10):
            continue  # linear reference root-finding is ill-posed at a ~ 0; covered below
        a, b = (torch.tensor(v, dtype=dtype).item() for v in (a, b))
        want = np.array([invert_piece(kind, a, b, q) for q in qs])
        got = piece_inverse_cdf(torch.full((len(qs),), a, dtype=dtype),
                                torch.full((len(qs),), b, dtype=dtype),
                                torch.tensor(qs, dtype=dtype), kind).double().numpy()
        tol = 1e-10 if dtype == torch.float64 else 2e-6
        np.testing.assert_allclose(got, want, atol=tol, rtol=0, err_msg=f"{kind} a={a} b={b}")


def test_linear_piece_from_zero_is_sqrt():
    q = torch.linspace(0, 1, 11, dtype=torch.float64)
    s = piece_inverse_cdf(torch.zeros(11, dtype=torch.float64),
                          torch.ones(11, dtype=torch.float64), q, "linear")
    np.testing.assert_allclose(s.numpy(), np.sqrt(q.numpy()), atol=1e-15)


def test_inverse_kind_sampler_is_the_exp_kind_cdf():
    # Exp kind: F(s) = expm1(sL)/expm1(L), so its inverse CDF maps F(s) back to s; the inverse
    # kind's inverse CDF is expm1(-qL)/expm1(-L), i.e. the exp kind's CDF with -L.
    for L in (-3.0, -0.4, 0.9, 5.0):
        a = torch.tensor(1.0, dtype=torch.float64)
        b = torch.tensor(math.exp(L), dtype=torch.float64)
        for s in (0.1, 0.35, 0.8):
            q_exp = math.expm1(s * L) / math.expm1(L)
            got = piece_inverse_cdf(a, b, torch.tensor(q_exp, dtype=torch.float64), "exp")
            assert got.item() == pytest.approx(s, abs=1e-14)
            got = piece_inverse_cdf(a, b, torch.tensor(s, dtype=torch.float64), "inverse")
            assert got.item() == pytest.approx(math.expm1(-s * L) / math.expm1(-L), abs=1e-14)


def test_kinds_coincide_as_b_tends_to_a():
    q = torch.linspace(0, 1, 101, dtype=torch.float64)
    a = torch.full_like(q, 0.7)
    gaps = []
    for delta in (1e-1, 1e-2, 1e-3, 1e-4):
        b = a * (1 + delta)
        s = {k: piece_inverse_cdf(a, b, q, k) for k in KINDS}
        gaps.append(max((s["exp"] - s["linear"]).abs().max().item(),
                        (s["exp"] - s["inverse"]).abs().max().item()))
    # All three agree to first order in delta: the gap shrinks like delta^2.
    assert gaps[0] < 0.01
    for g0, g1 in zip(gaps, gaps[1:]):
        assert g1 < g0 / 50
    # And b == a exactly gives s == q for every kind, in both precisions.
    for dtype in DTYPES:
        qd, ad = q.to(dtype), a.to(dtype)
        for k in KINDS:
            torch.testing.assert_close(piece_inverse_cdf(ad, ad.clone(), qd, k), qd,
                                       atol=2 * torch.finfo(dtype).eps, rtol=0)


@pytest.mark.parametrize("kind", ["exp", "inverse"])
def test_series_and_closed_forms_are_exact_around_the_threshold(kind):
    from reference_sampling import invert_piece

    from neus_l0.sampling.kernels import _series_threshold

    thr = _series_threshold(torch.float64)
    qs = np.array([0.0, 0.1, 0.37, 0.5, 0.9, 1.0])
    for factor in (0.01, 0.5, 0.999, 1.001, 2.0, 100.0):
        for sign in (1.0, -1.0):
            b = math.exp(sign * factor * thr)
            want = np.array([invert_piece(kind, 1.0, b, q) for q in qs])
            got = piece_inverse_cdf(torch.ones(len(qs), dtype=torch.float64),
                                    torch.full((len(qs),), b, dtype=torch.float64),
                                    torch.tensor(qs), kind).numpy()
            np.testing.assert_allclose(got, want, atol=1e-13, rtol=0)
            m = piece_mass(torch.tensor(1.0, dtype=torch.float64),
                           torch.tensor(b, dtype=torch.float64), kind).item()
            assert m == pytest.approx(mass(kind, 1.0, b), rel=1e-13)


# ---------------------------------------------------------------- whole rays


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("blur", [True, False])
def test_sample_l0_matches_reference(kind, dtype, blur):
    rng = np.random.default_rng(2)
    n_rays, n_pts, n = 6, 12, 16
    ts, ws = zip(*[_ray(rng, n_pts) for _ in range(n_rays)])
    t = torch.tensor(np.stack(ts), dtype=dtype)
    w = torch.tensor(np.stack(ws), dtype=dtype)
    got = sample_l0(t, w, n, kind=kind, blur=blur).double().numpy()
    u = (np.arange(n) + 0.5) / n
    t64, w64 = t.double().numpy(), w.double().numpy()  # the inputs as the dtype holds them
    for r in range(n_rays):
        want, idx = sample_l0_ref(t64[r], w64[r], u, kind=kind, blur=blur)
        d = np.diff(t64[r])[idx]
        err = np.abs(got[r] - want) / d
        assert err.max() < (1e-9 if dtype == torch.float64 else 1e-5), (r, err.max())


@pytest.mark.parametrize("dtype", DTYPES)
def test_sample_pdf_matches_reference(dtype):
    rng = np.random.default_rng(3)
    n_rays, n_bins, n = 5, 20, 33
    bins = np.sort(rng.uniform(0, 4, (n_rays, n_bins + 1)), axis=-1)
    w = rng.uniform(0, 1, (n_rays, n_bins)) * (rng.uniform(size=(n_rays, n_bins)) < 0.6)
    got = sample_pdf(torch.tensor(bins, dtype=dtype), torch.tensor(w, dtype=dtype), n)
    u = (np.arange(n) + 0.5) / n
    for r in range(n_rays):
        want = sample_pdf_ref(bins[r], w[r], u)
        tol = 1e-12 if dtype == torch.float64 else 1e-5 * np.diff(bins[r]).max()
        np.testing.assert_allclose(got[r].double().numpy(), want, atol=tol, rtol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_uniform_weights_give_uniform_samples(kind):
    t = torch.linspace(2.0, 6.0, 33, dtype=torch.float64).expand(3, 33)
    w = torch.full((3, 33), 0.25, dtype=torch.float64)
    got = sample_l0(t, w, 8, kind=kind, blur=False)
    want = 2.0 + 4.0 * (torch.arange(8, dtype=torch.float64) + 0.5) / 8
    torch.testing.assert_close(got, want.expand(3, 8), atol=1e-12, rtol=0)
    # With blur the interior stays uniform too; only the first/last pieces match anyway.
    got_blur = sample_l0(t, w, 8, kind=kind, blur=True)
    torch.testing.assert_close(got_blur, want.expand(3, 8), atol=1e-12, rtol=0)
    got_hvs = sample_pdf(torch.linspace(2.0, 6.0, 34, dtype=torch.float64), w[0], 8)
    torch.testing.assert_close(got_hvs, want, atol=1e-12, rtol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_histogram_of_random_draws_matches_interpolated_density(kind):
    rng = np.random.default_rng(4)
    t_np, w_np = _ray(rng, 24, spiky=False)
    w_np = np.maximum(w_np, 1e-3)
    n_rays, n = 2000, 64  # 128k samples
    t = torch.tensor(t_np, dtype=torch.float64).expand(n_rays, -1)
    w = torch.tensor(w_np, dtype=torch.float64).expand(n_rays, -1)
    g = torch.Generator().manual_seed(0)
    x = sample_l0(t, w, n, kind=kind, det=False, generator=g).numpy().ravel()
    edges = np.linspace(t_np[0], t_np[-1], 41)
    counts, _ = np.histogram(x, bins=edges)
    expected = np.diff(l0_cdf(t_np, w_np, edges, kind=kind)) * x.size
    # Stratification makes the counts less variable than Poisson, so 5 sigma is loose.
    sigma = np.sqrt(np.maximum(expected, 1.0))
    assert np.all(np.abs(counts - expected) < 5 * sigma + 2), np.max(np.abs(counts - expected)
                                                                     / sigma)
    assert counts.sum() == x.size


def test_histogram_of_hvs_draws_matches_piecewise_constant_pdf():
    rng = np.random.default_rng(5)
    bins_np = np.sort(rng.uniform(0, 1, 17))
    bins_np[0], bins_np[-1] = 0.0, 1.0
    w_np = rng.uniform(0.05, 1, 16)
    n_rays, n = 2000, 64
    g = torch.Generator().manual_seed(1)
    x = sample_pdf(torch.tensor(bins_np).expand(n_rays, -1), torch.tensor(w_np).expand(n_rays, -1),
                   n, det=False, generator=g).numpy().ravel()
    counts, _ = np.histogram(x, bins=bins_np)
    expected = w_np / w_np.sum() * x.size
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected) + 2)


def test_batch_shapes_and_rows_are_independent():
    rng = np.random.default_rng(6)
    t = torch.tensor(np.sort(rng.uniform(0, 1, (2, 3, 10)), axis=-1))
    w = torch.tensor(rng.uniform(0, 1, (2, 3, 10)))
    for kind in KINDS:
        got = sample_l0(t, w, 7, kind=kind)
        assert got.shape == (2, 3, 7)
        for i in range(2):
            for j in range(3):
                torch.testing.assert_close(got[i, j], sample_l0(t[i, j], w[i, j], 7, kind=kind))
    got = sample_pdf(t, w[..., :-1], 5)
    assert got.shape == (2, 3, 5)


def test_random_sampling_is_reproducible_with_a_generator():
    t = torch.linspace(0, 1, 20).expand(4, 20)
    w = torch.rand(4, 20, generator=torch.Generator().manual_seed(9))
    for fn in (lambda g: sample_l0(t, w, 16, det=False, generator=g),
               lambda g: sample_pdf(t, w[:, :-1], 16, det=False, generator=g)):
        a = fn(torch.Generator().manual_seed(3))
        b = fn(torch.Generator().manual_seed(3))
        c = fn(torch.Generator().manual_seed(4))
        assert torch.equal(a, b) and not torch.equal(a, c)


def test_outputs_carry_no_gradient():
    t = torch.linspace(0, 1, 10).requires_grad_()
    w = torch.rand(10).requires_grad_()
    assert not sample_l0(t, w, 5).requires_grad
    assert not sample_pdf(t, w[:-1], 5).requires_grad


def test_quantiles_are_stratified_and_below_one():
    g = torch.Generator().manual_seed(0)
    u = quantiles((1000,), 8, det=False, generator=g, dtype=torch.float32,
                  device=torch.device("cpu"))
    k = torch.arange(8)
    assert ((u >= k / 8) & (u < (k + 1) / 8)).all()
    assert (u < 1).all()
    assert quantiles((1,), 4, True, None, torch.float64, torch.device("cpu")).tolist() == [
        [0.125, 0.375, 0.625, 0.875]]


def test_bad_arguments_raise_clear_errors():
    t = torch.linspace(0, 1, 5)
    with pytest.raises(ValueError, match="kind"):
        sample_l0(t, t, 3, kind="cubic")
    with pytest.raises(ValueError, match="same shape"):
        sample_l0(t, t[:-1], 3)
    with pytest.raises(ValueError, match="N >= 2"):
        sample_l0(t[:1], t[:1], 3)
    with pytest.raises(ValueError, match="disagree"):
        sample_pdf(t, t, 3)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("kind", KINDS)
def test_cuda_matches_cpu(kind):
    rng = np.random.default_rng(7)
    ts, ws = zip(*[_ray(rng, 64) for _ in range(256)])
    t = torch.tensor(np.stack(ts), dtype=torch.float32)
    w = torch.tensor(np.stack(ws), dtype=torch.float32)
    cpu = sample_l0(t, w, 32, kind=kind)
    gpu = sample_l0(t.cuda(), w.cuda(), 32, kind=kind).cpu()
    torch.testing.assert_close(gpu, cpu, atol=1e-5, rtol=0)
    torch.testing.assert_close(sample_pdf(t.cuda(), w[:, :-1].cuda(), 32).cpu(),
                               sample_pdf(t, w[:, :-1], 32), atol=1e-5, rtol=0)
