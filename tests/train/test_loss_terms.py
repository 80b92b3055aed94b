"""`neus_loss`'s total: NeuS's three terms plus the caller's, each with its own weight, the
carve and fill terms (like the mask term) scaled by the fraction of pixels drawn from."""

from types import SimpleNamespace

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.load import load_config
from neus_l0.train.losses import EXTRA_TERMS, RayDraw, color_l1, eikonal, mask_bce, neus_loss

_weight = st.floats(0.0, 10.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**16), scale=st.floats(0.05, 1.0), present=st.sets(
    st.sampled_from([name for name, _, _ in EXTRA_TERMS])),
    weights=st.tuples(_weight, _weight, _weight, _weight))
def test_the_total_is_the_weighted_sum_of_its_terms(seed, scale, present, weights):
    """Against the sum written out in float64: a term the caller leaves out adds nothing and
    reports 0; only the carve and fill terms take the mask term's scale."""
    cw, pw, kw, fw = weights
    cfg = load_config("demo", [f"train.curvature_weight={cw}", f"train.photo.weight={pw}",
                               f"train.carve_weight={kw}", f"train.fill_weight={fw}",
                               "train.eikonal_fraction=1.0", "train.hit_color_floor=0.0"]).train
    g = torch.Generator().manual_seed(seed)
    b, n = 5, 4
    out = SimpleNamespace(color=torch.rand(b, 3, generator=g, dtype=torch.float64),
                          weight_sum=torch.rand(b, 1, generator=g, dtype=torch.float64),
                          gradients=torch.randn(b, n, 3, generator=g, dtype=torch.float64),
                          eikonal_mask=torch.ones(b, n, dtype=torch.float64))
    rgb = torch.rand(b, 3, generator=g, dtype=torch.float64)
    mask = (torch.rand(b, 1, generator=g) > 0.4).double()
    terms = {name: torch.rand((), generator=g, dtype=torch.float64) for name in sorted(present)}
    losses = neus_loss(out, rgb, mask, cfg, RayDraw(mask_scale=scale), terms)

    zero = torch.zeros((), dtype=torch.float64)
    t = {name: terms.get(name, zero) for name in ("curvature", "photo", "carve", "fill")}
    eik = eikonal(out.gradients, out.eikonal_mask)
    want = (color_l1(out.color, rgb, mask) + cfg.igr_weight * eik
            + cfg.mask_weight * scale * mask_bce(out.weight_sum, mask)
            + cw * t["curvature"] + pw * t["photo"] + kw * scale * t["carve"]
            + fw * scale * t["fill"])
    torch.testing.assert_close(losses["loss"], want, rtol=1e-12, atol=1e-12)
    for name, value in t.items():
        assert float(losses[f"{name}_loss"]) == float(value)


def test_a_uniform_draw_is_the_default():
    """No `RayDraw` is the uniform draw over every pixel, written out: the hit colour's L1
    (the demo's floor 0.5), the plain Eikonal mean and the mask BCE at scale 1."""
    cfg = load_config("demo", ["train.eikonal_fraction=1.0"]).train
    g = torch.Generator().manual_seed(3)
    out = SimpleNamespace(color=torch.rand(6, 3, generator=g, dtype=torch.float64),
                          weight_sum=torch.rand(6, 1, generator=g, dtype=torch.float64),
                          gradients=torch.randn(6, 4, 3, generator=g, dtype=torch.float64),
                          eikonal_mask=torch.ones(6, 4, dtype=torch.float64))
    rgb, mask = torch.rand(6, 3, generator=g, dtype=torch.float64), torch.ones(6, 1).double()
    hit = out.color / out.weight_sum.clamp_min(0.5)
    want = ((hit - rgb).abs().sum() / (6 + 1e-5) + cfg.igr_weight
            * eikonal(out.gradients, out.eikonal_mask)
            + cfg.mask_weight * mask_bce(out.weight_sum, mask))
    torch.testing.assert_close(neus_loss(out, rgb, mask, cfg)["loss"], want, rtol=1e-12,
                               atol=1e-12)
