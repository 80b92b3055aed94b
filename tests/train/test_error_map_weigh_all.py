"""`train.error_map.weigh_all`: the Eikonal term weighs an error map's rays by their
importance weights, so that it estimates the pool's own mean, as a uniform draw does."""

from types import SimpleNamespace

import pytest
import torch

from neus_l0.bounds.error_map import draw, new_error_map, refresh_table
from neus_l0.config.load import load_config
from neus_l0.train.losses import RayDraw, neus_loss


def _out(gradients: torch.Tensor, mask: torch.Tensor) -> SimpleNamespace:
    """What `neus_loss` reads of a render: B rays of N samples."""
    b = gradients.shape[0]
    return SimpleNamespace(color=torch.zeros(b, 3), weight_sum=torch.full((b, 1), 0.5),
                           gradients=gradients, eikonal_mask=mask)


def _eikonal(out, w, weigh_all: bool) -> float:
    cfg = load_config("demo", ["train.eikonal_fraction=1.0",
                               f"train.error_map.weigh_all={str(weigh_all).lower()}"]).train
    b = out.gradients.shape[0]
    losses = neus_loss(out, torch.zeros(b, 3), torch.ones(b, 1), cfg,
                       RayDraw(ray_weight=w, foreground=1.0))
    return float(losses["eikonal_loss"])


def test_the_weighted_eikonal_is_the_self_normalised_mean():
    """``sum(w m e) / sum(w m)`` with the option, the plain masked mean without it."""
    g = torch.Generator().manual_seed(0)
    grads = torch.randn(6, 4, 3, generator=g, dtype=torch.float64)
    mask = (torch.rand(6, 4, generator=g) > 0.3).double()
    w = torch.rand(6, generator=g, dtype=torch.float64) * 3 + 0.1
    e = (grads.norm(dim=-1) - 1) ** 2
    out = _out(grads, mask)
    wm = w[:, None] * mask
    assert _eikonal(out, w, True) == pytest.approx(float((wm * e).sum() / wm.sum()), rel=1e-6)
    assert _eikonal(out, w, False) == pytest.approx(float((mask * e).sum() / mask.sum()),
                                                    rel=1e-6)


def test_weighted_draws_estimate_the_pools_eikonal_mean():
    """20000 rays drawn by a map that favours the rays of large Eikonal residual: weighted,
    the term lands within 3 % of the pool's mean; unweighted, it leans to the map's rays
    (over 30 % high)."""
    g = torch.Generator().manual_seed(1)
    n = 2000
    e = torch.rand(n, generator=g, dtype=torch.float64) ** 3  # per-ray residual
    grads = torch.zeros(n, 1, 3, dtype=torch.float64)
    grads[:, 0, 0] = 1 + e.sqrt()  # (|grad| - 1)^2 = e
    mask = (torch.rand(n, 1, generator=g) > 0.2).double()
    emap = new_error_map(torch.arange(n), 0.8, 1.0)
    emap.error = e.float().clone()
    refresh_table(emap)
    idx, w = draw(emap, 20000, g)
    out = _out(grads[idx], mask[idx])
    pool = float((mask[:, 0] * e).sum() / mask.sum())
    assert _eikonal(out, w.double(), True) == pytest.approx(pool, rel=0.03)
    assert _eikonal(out, w.double(), False) > 1.3 * pool
