"""Hypothesis strategies and checks the sampler tests share (`sampling/test_stress.py`,
`sampling/test_l0_sections.py`): a plain helper module, not a test module."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import strategies as st

# Weights from every regime: zeros, tiny, huge, non-finite, negative.
WEIGHT = st.one_of(
    st.just(0.0), st.just(float("nan")), st.just(float("inf")), st.just(-float("inf")),
    st.floats(-1.0, 0.0), st.floats(1e-30, 1.0), st.floats(1e-45, 1e-30),
    st.floats(1.0, 1e38), st.sampled_from([1e-30, 1.0, 1e-12, 0.5]),
)


@st.composite
def rays(draw, max_points: int = 40):
    """1 to 4 rays of 2 to `max_points` points: non-decreasing t (repeats included) and a
    WEIGHT at each point, as numpy arrays ``(t, w)`` of shape (rays, points)."""
    n_pts = draw(st.integers(2, max_points))
    n_rays = draw(st.integers(1, 4))
    steps = draw(st.lists(st.one_of(st.just(0.0), st.floats(1e-6, 1.0)),
                          min_size=n_rays * n_pts, max_size=n_rays * n_pts))
    start = draw(st.floats(-10.0, 10.0))
    t = start + np.cumsum(np.array(steps).reshape(n_rays, n_pts), axis=-1)
    w = np.array(draw(st.lists(WEIGHT, min_size=n_rays * n_pts, max_size=n_rays * n_pts)))
    return t, w.reshape(n_rays, n_pts)


def check_samples(out: torch.Tensor, t: torch.Tensor, n: int) -> None:
    """`n` samples per ray of `t`: finite, sorted and within the ray's first and last t."""
    assert out.shape == (*t.shape[:-1], n)
    assert torch.isfinite(out).all()
    assert (out[..., 1:] >= out[..., :-1]).all()
    assert (out >= t[..., :1]).all() and (out <= t[..., -1:]).all()
