"""The samplers never return NaN/inf, stay sorted and in range, whatever the weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reference_sampling import sample_l0_ref
from strategies import WEIGHT, check_samples, rays

from neus_l0.sampling.kernels import KINDS, maxblur, sample_l0, sample_pdf

DTYPES = [torch.float32, torch.float64]

@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=rays(), n=st.integers(1, 70), kind=st.sampled_from(KINDS),
       blur=st.booleans(), det=st.booleans(), dtype=st.sampled_from(DTYPES),
       seed=st.integers(0, 2**31 - 1))
def test_sample_l0_outputs_are_always_finite_sorted_and_in_range(data, n, kind, blur, det,
                                                                  dtype, seed):
    t_np, w_np = data
    with np.errstate(over="ignore"):
        t = torch.tensor(t_np, dtype=dtype)
        w = torch.tensor(w_np, dtype=dtype)
    out = sample_l0(t, w, n, kind=kind, blur=blur, det=det,
                    generator=torch.Generator().manual_seed(seed))
    check_samples(out, t, n)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=rays(), n=st.integers(1, 70), det=st.booleans(), dtype=st.sampled_from(DTYPES),
       seed=st.integers(0, 2**31 - 1))
def test_sample_pdf_outputs_are_always_finite_sorted_and_in_range(data, n, det, dtype, seed):
    t_np, w_np = data
    t = torch.tensor(t_np, dtype=dtype)
    w = torch.tensor(w_np[..., :-1], dtype=dtype)
    out = sample_pdf(t, w, n, det=det, generator=torch.Generator().manual_seed(seed))
    check_samples(out, t, n)


@settings(max_examples=60, deadline=None)
@given(w=st.lists(WEIGHT, min_size=1, max_size=30), dtype=st.sampled_from(DTYPES))
def test_maxblur_is_finite_and_at_least_pad(w, dtype):
    out = maxblur(torch.tensor(w, dtype=dtype), pad=0.01)
    assert torch.isfinite(out).all() and (out >= 0.01 * (1 - 1e-6)).all()


@settings(max_examples=40, deadline=None)
@given(data=rays(max_points=12), kind=st.sampled_from(KINDS), blur=st.booleans())
def test_sample_l0_float64_matches_reference_on_random_finite_rays(data, kind, blur):
    # Finite weights from every regime, in float64: the closed forms match quadrature.
    t_np, w_np = data
    w_np = np.where(np.isfinite(w_np), w_np, 0.0)
    w_np = np.clip(w_np, -1.0, 1e30)
    if (np.diff(t_np[0]) > 1e-3).sum() < 1:
        return
    t = torch.tensor(t_np[:1])
    w = torch.tensor(w_np[:1])
    n = 9
    got = sample_l0(t, w, n, kind=kind, blur=blur)[0].numpy()
    u = (np.arange(n) + 0.5) / n
    want, idx = sample_l0_ref(t_np[0], w_np[0], u, kind=kind, blur=blur)
    d = np.diff(t_np[0])[idx]
    assert np.all(np.abs(got - want) <= 1e-7 * np.maximum(d, 1e-300) + 1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_named_extreme_inputs(kind, dtype):
    """Each extreme case of the issue, with the exact answer where there is one."""
    z = torch.zeros(3, 6, dtype=dtype)
    t = torch.linspace(1.0, 2.0, 6, dtype=dtype).expand(3, 6)
    uniform = 1.0 + (torch.arange(4, dtype=dtype) + 0.5) / 4

    # all-zero and all-non-finite weights: uniform over the ray
    for w in (z, torch.full_like(z, float("nan")), torch.full_like(z, float("inf")),
              torch.full_like(z, -1.0)):
        for blur in (True, False):
            got = sample_l0(t, w, 4, kind=kind, blur=blur)
            torch.testing.assert_close(got, uniform.expand(3, 4))

    # a == b exactly everywhere, blur off: uniform; weights spanning 1e-30..1: finite
    got = sample_l0(t, torch.full_like(z, 0.3), 4, kind=kind, blur=False)
    torch.testing.assert_close(got, uniform.expand(3, 4))
    w = torch.tensor([1e-30, 1e-20, 1e-10, 1.0, 1e-25, 1e-30], dtype=dtype).expand(3, 6)
    check_samples(sample_l0(t, w, 64, kind=kind, blur=False), t, 64)

    # a or b == 0 with blur off: a single positive point has no mass for exp/inverse
    spike = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=dtype)
    got = sample_l0(t[0], spike, 4, kind=kind, blur=False)
    if kind == "linear":  # a tent: samples cluster around the spike at t = 1.4
        assert ((got > 1.2) & (got < 1.6)).all()
    else:
        torch.testing.assert_close(got, uniform)

    # N = 2 and n_samples = 1
    got = sample_l0(torch.tensor([0.0, 1.0], dtype=dtype), torch.tensor([1.0, 1.0],
                                                                        dtype=dtype), 1,
                    kind=kind)
    assert got.tolist() == [pytest.approx(0.5)]

    # duplicate positions: zero-length intervals get no samples but break nothing
    td = torch.tensor([0.0, 0.5, 0.5, 0.5, 1.0, 1.0], dtype=dtype)
    wd = torch.tensor([0.1, 1.0, 5.0, 1.0, 0.1, 9.0], dtype=dtype)
    check_samples(sample_l0(td, wd, 50, kind=kind), td, 50)
    tsame = torch.full((6,), 0.7, dtype=dtype)
    got = sample_l0(tsame, wd, 5, kind=kind)
    assert (got == 0.7).all()


def test_weights_scale_does_not_matter_without_blur():
    rng = np.random.default_rng(0)
    t = torch.tensor(np.sort(rng.uniform(0, 1, (8, 20)), axis=-1))
    w = torch.tensor(rng.uniform(0, 1, (8, 20)))
    for kind in KINDS:
        ref = sample_l0(t, w, 16, kind=kind, blur=False)
        for scale in (1e-30, 1e-5, 1e5, 1e30):
            torch.testing.assert_close(sample_l0(t, w * scale, 16, kind=kind, blur=False), ref,
                                       atol=1e-12, rtol=0)
