"""SSIM uses the field's window: an 11x11 Gaussian of sigma 1.5 (checked against a direct
implementation of Wang et al.'s formula)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import convolve2d

from neus_l0.render.views import SSIM_SIGMA, SSIM_WINDOW, ssim


def _reference(a: np.ndarray, b: np.ndarray) -> float:
    x = np.arange(SSIM_WINDOW) - SSIM_WINDOW // 2
    g = np.exp(-x**2 / (2 * SSIM_SIGMA**2))
    w = np.outer(g, g) / np.outer(g, g).sum()  # (11, 11)
    c1, c2 = 0.01**2, 0.03**2
    out = []
    for c in range(3):
        f = lambda img: convolve2d(img, w, mode="valid")  # noqa: E731
        mx, my = f(a[..., c]), f(b[..., c])
        vx, vy = f(a[..., c] ** 2) - mx**2, f(b[..., c] ** 2) - my**2
        cxy = f(a[..., c] * b[..., c]) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
        out.append(s.mean())
    return float(np.mean(out))


def test_ssim_is_the_gaussian_11x11_window():
    rng = np.random.default_rng(0)
    a = rng.random((30, 40, 3))
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)
    assert (SSIM_WINDOW, SSIM_SIGMA) == (11, 1.5)
    assert ssim(b, a) == pytest.approx(_reference(a, b), abs=1e-6)
    assert ssim(a[:10], a[:10]) is None  # under the window
