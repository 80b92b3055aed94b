"""`sample_neus_sections`: NeuS's exact within-section CDF against a float64 reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_neus_sections import invert_section, sample_neus_ref

from neus_l0.sampling.kernels import neus_section_inverse_cdf, quantiles, sample_neus_sections

PAIRS = [(0.3, -0.2), (5.0, -5.0), (100.0, 90.0), (-100.0, -200.0), (1e-3, 0.0),
         (500.0, -500.0), (3.0, 3.0001), (-2.0, 4.0), (0.0, -1e-6), (50.0, 49.5),
         (20.0, -0.5), (1.0, 0.0), (0.999, 0.0), (30.0, -30.0), (2.0, 2.0)]
QS = [0.0, 1e-6, 0.01, 0.3, 0.5, 0.9, 0.999, 1.0]


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-11), (torch.float32, 3e-6)])
def test_inverse_cdf_matches_quadrature(dtype, tol):
    for x, y in PAIRS:
        for q in QS:
            ref = invert_section(x, y, q)
            got = neus_section_inverse_cdf(torch.tensor(x, dtype=dtype),
                                           torch.tensor(y, dtype=dtype),
                                           torch.tensor(q, dtype=dtype)).item()
            assert got == pytest.approx(ref, abs=tol), (x, y, q)


def test_closed_form_limits():
    q = torch.linspace(0, 1, 11, dtype=torch.float64)
    # flat SDF (x == y) and the limit d -> 0: uniform, reached without a series
    assert torch.equal(neus_section_inverse_cdf(torch.tensor(2.0), torch.tensor(2.0), q), q)
    near = neus_section_inverse_cdf(torch.tensor(0.7, dtype=torch.float64),
                                    torch.tensor(0.7 - 1e-12, dtype=torch.float64), q)
    torch.testing.assert_close(near, q, rtol=0, atol=1e-12)
    # symmetric about the zero crossing: the median is where the logit crosses 0
    s = neus_section_inverse_cdf(torch.tensor(8.0, dtype=torch.float64),
                                 torch.tensor(-8.0, dtype=torch.float64), torch.tensor(0.5))
    assert s.item() == pytest.approx(0.5, abs=1e-12)
    # a sharp surface at s0 = x / (x - y): every quantile within ~ a few widths 1/d of s0
    x, y = torch.tensor(300.0, dtype=torch.float64), torch.tensor(-700.0, dtype=torch.float64)
    s = neus_section_inverse_cdf(x, y, torch.tensor([0.05, 0.95], dtype=torch.float64))
    assert (s - 0.3).abs().max().item() < 3.0 / 1000.0
    # non-finite estimates: uniform
    nan = torch.tensor(float("nan"))
    assert neus_section_inverse_cdf(nan, torch.tensor(0.0), torch.tensor(0.25)).item() == 0.25


def test_sampler_matches_reference_rays():
    rng = np.random.default_rng(3)
    for inv_s in (16.0, 64.0, 512.0):
        for _ in range(4):
            n = 9
            z = np.sort(rng.uniform(0.5, 3.0, n))
            sdf = 1.7 - z + 0.05 * rng.normal(size=n)
            prev, nxt = sdf[:-1], np.minimum(sdf[1:], sdf[:-1])
            w = rng.uniform(0, 1, n - 1) ** 3
            u = np.sort(rng.uniform(0, 1, 16))
            got = sample_neus_sections(
                torch.tensor(z)[None], torch.tensor(w)[None], torch.tensor(prev)[None],
                torch.tensor(nxt)[None], inv_s, 16)
            # the det quantiles of the sampler, fed to the reference
            uq = quantiles((1,), 16, True, None, torch.float64, torch.device("cpu"))[0]
            ref = sample_neus_ref(z, w, prev, nxt, inv_s, uq.numpy())
            np.testing.assert_allclose(got[0].numpy(), ref, rtol=0, atol=1e-10)
            del u


def test_degenerate_rays_are_uniform_and_outputs_are_sane():
    z = torch.linspace(0.0, 2.0, 5, dtype=torch.float32).expand(4, 5).contiguous()
    w = torch.rand(4, 4)
    w[0] = 0.0
    w[1] = float("nan")
    w[2, 1] = float("inf")
    prev = torch.tensor([1.0, 0.5, 0.0, -0.5]).expand(4, 4)
    nxt = prev - 0.5
    s = sample_neus_sections(z, w, prev, nxt, 64.0, 8)
    expected = (torch.arange(8) + 0.5) / 8 * 2.0
    torch.testing.assert_close(s[0], expected)  # all-zero weights: uniform over the ray
    torch.testing.assert_close(s[1], expected)
    assert torch.isfinite(s).all() and (s[:, 1:] >= s[:, :-1]).all()
    assert (s >= 0).all() and (s <= 2).all()
    with pytest.raises(ValueError, match="disagree"):
        sample_neus_sections(z, w[:, :3], prev, nxt, 64.0, 8)


def test_distribution_matches_the_cdf_on_many_samples():
    """1e5 stratified draws from one section: empirical CDF vs the ratio of sigmoids."""
    x, y = 6.0, -14.0
    z = torch.tensor([[0.0, 1.0]], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    s = sample_neus_sections(z, torch.ones(1, 1, dtype=torch.float64),
                             torch.tensor([[x]], dtype=torch.float64),
                             torch.tensor([[y]], dtype=torch.float64), 1.0, 100_000,
                             det=False, generator=g)[0]
    grid = torch.linspace(0.05, 0.95, 19, dtype=torch.float64)

    def sig(v):
        return 1.0 / (1.0 + math.exp(-v))

    cdf = torch.tensor([(sig(x) - sig(x + (y - x) * t)) / (sig(x) - sig(y)) for t in grid])
    emp = (s[None, :] <= grid[:, None]).double().mean(-1)
    assert (emp - cdf).abs().max().item() < 5e-3


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=6, max_size=6),
       st.lists(st.floats(0.0, 1e3, allow_nan=False), min_size=5, max_size=5),
       st.floats(1e-3, 1e4), st.sampled_from([torch.float32, torch.float64]))
def test_properties(sdf, w, inv_s, dtype):
    z = torch.tensor([0.1, 0.2, 0.25, 0.9, 1.5, 1.51], dtype=dtype)[None]
    sd = torch.tensor(sdf, dtype=dtype)
    prev, nxt = sd[:-1][None], sd[1:][None]
    s = sample_neus_sections(z, torch.tensor(w, dtype=dtype)[None], prev, nxt, inv_s, 12)
    assert s.dtype == dtype and torch.isfinite(s).all()
    assert (s[:, 1:] >= s[:, :-1]).all() and (s >= 0.1).all() and (s <= 1.51).all()
    q = torch.linspace(0, 1, 7, dtype=dtype)
    for i in range(5):  # monotone in q, inside [0, 1]
        si = neus_section_inverse_cdf(inv_s * prev[0, i], inv_s * nxt[0, i], q)
        assert (si[1:] >= si[:-1]).all() and (si >= 0).all() and (si <= 1).all()
