"""The opacity of the stretch a narrowed ray skips (`section_alpha`'s `skipped`)."""

import torch

from neus_l0.config.schema import RenderConfig
from neus_l0.render.volume import render_rays, section_alpha
from neus_l0.sampling.upsample import build_sampler


class StartsAt:
    """A `RayBounds` that starts every ray's samples at t = `t0` (ends unchanged)."""

    def __init__(self, t0: float) -> None:
        self.t0 = t0

    def ray_bounds(self, origins, dirs, near, far):
        lo = torch.maximum(near, torch.full_like(near, self.t0))
        return lo, far, torch.ones(origins.shape[0], dtype=torch.bool)


def _neus_alpha(start, end, s):
    """NeuS's guarded section opacity, float64."""
    p, n = torch.sigmoid(start * s), torch.sigmoid(end * s)
    return ((p - n + 1e-5) / (p + 1e-5)).clip(0.0, 1.0)


def test_closed_form_and_limits():
    s = torch.tensor([50.0])
    sdf = torch.tensor([[0.1, 0.05], [-0.2, -0.3], [-0.2, -0.2], [0.3, 0.2]])
    slope = torch.tensor([[-1.0, -1.0], [-1.0, -1.0], [0.0, 0.0], [-1.0, -0.5]])
    half = torch.full((4, 2), 0.02)
    skipped = torch.tensor([[0.5], [0.5], [0.5], [0.0]])
    a = section_alpha(sdf, slope, half, s, skipped)
    plain = section_alpha(sdf, slope, half, s)
    d, k, h, sk, s64 = sdf.double(), slope.double(), half.double(), skipped.double(), s.double()
    # the first section starts `skipped` earlier on the same linear model; the rest as NeuS
    reach = h + torch.cat([sk, torch.zeros_like(sk)], dim=-1)
    torch.testing.assert_close(a.double(), _neus_alpha(d - k * reach, d + k * h, s64),
                               rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(a[:, 1:], plain[:, 1:], rtol=0, atol=0)
    # the same as the stretch's own opacity (exact, no guards) composed with the section's
    start, mid = torch.sigmoid((d - k * (h + sk)) * s64), torch.sigmoid((d - k * h) * s64)
    stretch = ((start - mid) / start)[:, 0]
    composed = 1.0 - (1.0 - stretch) * (1.0 - plain[:, 0].double())
    torch.testing.assert_close(a[:, 0].double(), composed, rtol=0, atol=1e-4)
    assert 0 <= a[0, 0] - plain[0, 0] < 0.01  # enters outside the object: about nothing added
    assert a[1, 0] > 0.99  # enters inside, head-on: opaque
    assert a[2, 0] == plain[2, 0]  # enters inside but parallel to the surface: nothing crossed
    assert torch.equal(a[3], plain[3])  # nothing skipped


def test_a_ray_entering_inside_the_object_is_opaque(sphere_model):
    model = sphere_model()  # |x| - 0.5
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.9, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    cfg = RenderConfig(n_samples=32, n_importance=32, up_sample_steps=2,
                       cull_outside_sphere=True)
    # bounds that start inside the sphere of radius 0.5 (t = 3 is the centre)
    out = render_rays(model, o, d, cfg, build_sampler("hvs"), bounds=[StartsAt(2.8)])
    assert out.weight_sum[0] > 0.99  # would be ~0 without the entry term: no crossing seen
    assert out.weight_sum[1] < 0.01  # misses the sphere: transparent
    # and bounds that start outside the object change nothing
    ref = render_rays(model, o, d, cfg, build_sampler("hvs"))
    near = render_rays(model, o, d, cfg, build_sampler("hvs"), bounds=[StartsAt(2.2)])
    assert (near.weight_sum - ref.weight_sum).abs().max() < 1e-3
