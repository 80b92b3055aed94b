"""`sample_l0_sections`: the L0 interpolant inside NeuS's sections, against a float64 reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from strategies import check_samples, rays

from neus_l0.sampling.kernels import KINDS, sample_l0_sections, sample_pdf


def _interp(kind: str, a: float, b: float, s: np.ndarray) -> np.ndarray:
    """The kind's interpolant from a (s = 0) to b (s = 1), written plainly."""
    if kind == "linear":
        return a + (b - a) * s
    if a <= 0 or b <= 0:
        return np.zeros_like(s)
    if kind == "exp":
        return a * (b / a) ** s
    return a * b / ((a - b) * s + b)


def _reference(z: np.ndarray, w: np.ndarray, n: int, kind: str) -> np.ndarray:
    """Plain float64 draw of one ray: section shares from w, then a quadrature CDF inside."""
    d = np.diff(z)
    rho = w / d
    mid = 0.5 * (z[:-1] + z[1:])
    g = [rho[0]]
    for j in range(1, len(w)):  # the interpolant between mid_{j-1} and mid_j, at z_j
        f = (z[j] - mid[j - 1]) / (mid[j] - mid[j - 1])
        g.append(float(_interp(kind, rho[j - 1], rho[j], np.array(f))))
    g.append(rho[-1])
    cdf = np.concatenate([[0.0], np.cumsum(w) / w.sum()])
    out = []
    for k in range(n):
        u = (k + 0.5) / n
        j = min(int(np.searchsorted(cdf, u, side="right")) - 1, len(w) - 1)
        q = (u - cdf[j]) / (cdf[j + 1] - cdf[j])
        s = np.linspace(0.0, 1.0, 20001)
        dens = np.where(s < 0.5, _interp(kind, g[j], rho[j], 2 * s),
                        _interp(kind, rho[j], g[j + 1], 2 * s - 1))
        c = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]))])
        s_q = np.interp(q, c / c[-1], s) if c[-1] > 0 else q
        out.append(z[j] + s_q * d[j])
    return np.array(out)


@pytest.mark.parametrize("kind", KINDS)
def test_matches_a_plain_float64_reference(kind):
    rng = np.random.default_rng(7)
    for _ in range(6):
        z = np.sort(rng.uniform(0.0, 2.0, 12))
        w = rng.uniform(0.0, 1.0, 11) ** 3 + 1e-4
        got = sample_l0_sections(torch.tensor(z), torch.tensor(w), 17, kind).numpy()
        np.testing.assert_allclose(got, _reference(z, w, 17, kind), rtol=0, atol=5e-6)  # trapezoid


@pytest.mark.parametrize("kind", KINDS)
def test_every_section_keeps_the_share_hvs_gives_it(kind):
    """The sections' shares are NeuS's weights: the same section for every quantile as hvs."""
    g = torch.Generator().manual_seed(0)
    z = torch.sort(torch.rand(64, 33, generator=g, dtype=torch.float64), dim=-1).values
    w = torch.rand(64, 32, generator=g, dtype=torch.float64) ** 4
    ours = sample_l0_sections(z, w, 16, kind)
    hvs = sample_pdf(z, w, 16)
    section = lambda s: torch.searchsorted(z, s, right=True)  # noqa: E731
    assert torch.equal(section(ours), section(hvs))


def test_flat_weights_on_equal_sections_are_uniform():
    z = torch.linspace(0.0, 1.0, 9, dtype=torch.float64).expand(3, 9)
    w = torch.full((3, 8), 0.25, dtype=torch.float64)
    for kind in KINDS:
        out = sample_l0_sections(z, w, 8, kind)
        torch.testing.assert_close(out, sample_pdf(z, w, 8), rtol=0, atol=1e-12)


def test_a_peak_section_leans_towards_its_heavier_neighbour():
    """Inside the peak section the samples sit nearer the side with more weight next door."""
    z = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)[None]
    left = sample_l0_sections(z, torch.tensor([[0.0, 0.3, 1.0, 0.01, 0.0]]), 400)
    right = sample_l0_sections(z, torch.tensor([[0.0, 0.01, 1.0, 0.3, 0.0]]), 400)
    inside = lambda s: s[(s > 0.4) & (s < 0.6)]  # noqa: E731
    assert inside(left).mean() < 0.5 < inside(right).mean()
    torch.testing.assert_close(inside(left).mean() - 0.5, 0.5 - inside(right).mean())


def test_histogram_of_random_draws_matches_the_reference_cdf():
    z = np.array([0.0, 0.3, 0.5, 0.6, 1.0])
    w = np.array([0.1, 0.6, 0.25, 0.05])
    gen = torch.Generator().manual_seed(1)
    s = sample_l0_sections(torch.tensor(z).expand(400, 5), torch.tensor(w).expand(400, 4), 250,
                           "exp", det=False, generator=gen).reshape(-1).numpy()
    ref = _reference(z, w, 4000, "exp")  # quantiles of the exact distribution
    for p in (0.1, 0.3, 0.5, 0.7, 0.9):
        assert np.quantile(s, p) == pytest.approx(np.quantile(ref, p), abs=4e-3)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=rays(), n=st.integers(1, 70), kind=st.sampled_from(KINDS), det=st.booleans(),
       dtype=st.sampled_from([torch.float32, torch.float64]), seed=st.integers(0, 2**31 - 1))
def test_outputs_are_always_finite_sorted_and_in_range(data, n, kind, det, dtype, seed):
    t_np, w_np = data
    with np.errstate(over="ignore"):
        z = torch.tensor(t_np, dtype=dtype)
        w = torch.tensor(w_np[:, :-1], dtype=dtype)
    out = sample_l0_sections(z, w, n, kind, det=det,
                             generator=torch.Generator().manual_seed(seed))
    check_samples(out, z, n)


@pytest.mark.parametrize("kind", KINDS)
def test_sections_next_to_empty_ones_keep_their_share(kind):
    """Zero weights beside a section (no interpolant mass for exp / inverse pieces there):
    its share is still its weight's, as hvs gives it, in every kind."""
    z = torch.tensor([[0.0, 0.1, 0.35, 0.4, 0.9, 1.0]], dtype=torch.float64)
    w = torch.tensor([[0.0, 0.6, 0.0, 0.3, 0.1]], dtype=torch.float64)
    out = sample_l0_sections(z, w, 1000, kind)
    section = torch.searchsorted(z, out, right=True)
    torch.testing.assert_close(section, torch.searchsorted(z, sample_pdf(z, w, 1000),
                                                           right=True))
    share = torch.stack([(section == j + 1).double().mean() for j in range(5)])
    torch.testing.assert_close(share, w[0] / w.sum(), atol=2e-3, rtol=0)


def test_plotted_pieces_integrate_to_each_sections_weight_in_every_kind():
    from neus_l0.sampling.kernels import l0_section_pieces, piece_mass

    z = torch.tensor([[0.0, 0.1, 0.35, 0.4, 0.9, 1.0]], dtype=torch.float64)
    w = torch.tensor([[0.0, 0.6, 0.0, 0.3, 0.1]], dtype=torch.float64)
    for kind in KINDS:
        a, b, d, _ = l0_section_pieces(z, w, kind)
        mass = (piece_mass(a, b, kind) * d).reshape(5, 2).sum(-1)
        # a flat section (constant at w_j / d_j) carries w_j too (up to one scale per ray)
        flat = (piece_mass(a, b, kind) == 0).reshape(5, 2).all(-1)
        mass = torch.where(flat, a.reshape(5, 2)[:, 0] * d.reshape(5, 2).sum(-1), mass)
        torch.testing.assert_close(mass / mass.sum(), w[0] / w.sum(), atol=1e-12, rtol=0,
                                   msg=kind)
