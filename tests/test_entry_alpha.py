"""The opacity of the stretch a narrowed ray skips (`rendering.entry_alpha`)."""

import torch
from test_rendering import AnalyticSphere, sphere_model  # noqa: F401

from neus_l0.config import RenderConfig
from neus_l0.rendering import entry_alpha, render_rays


class StartsAt:
    """A `RayBounds` that starts every ray's samples at t = `t0` (ends unchanged)."""

    def __init__(self, t0: float) -> None:
        self.t0 = t0

    def ray_bounds(self, origins, dirs, near, far):
        lo = torch.maximum(near, torch.full_like(near, self.t0))
        return lo, far, torch.ones(origins.shape[0], dtype=torch.bool)


def test_closed_form_and_limits():
    s = torch.tensor([50.0])
    prev = torch.tensor([0.1, -0.2, -0.2, 0.3])
    slope = torch.tensor([-1.0, -1.0, 0.0, -1.0])
    skipped = torch.tensor([0.5, 0.5, 0.5, 0.0])
    a = entry_alpha(prev, slope, skipped, s)
    p64, k64, l64, s64 = prev.double(), slope.double(), skipped.double(), s.double()
    start = torch.sigmoid((p64 - k64 * l64) * s64)  # NeuS's section opacity, float64
    end = torch.sigmoid(p64 * s64)
    ref = ((start - end) / start) * (l64 > 0)
    torch.testing.assert_close(a.double(), ref, rtol=1e-5, atol=1e-6)
    assert a[0] < 0.01  # enters outside the object: transparent
    assert a[1] > 0.99  # enters inside, head-on: opaque
    assert a[2] < 0.01  # enters inside but parallel to the surface: nothing crossed
    assert a[3] == 0  # nothing skipped


def test_a_ray_entering_inside_the_object_is_opaque():
    model = sphere_model()  # |x| - 0.5
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 0.9, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    cfg = RenderConfig(n_samples=32, n_importance=32, up_sample_steps=2,
                       cull_outside_sphere=True)
    # bounds that start inside the sphere of radius 0.5 (t = 3 is the centre)
    out = render_rays(model, o, d, cfg, "hvs", bounds=[StartsAt(2.8)])
    assert out.weight_sum[0] > 0.99  # would be ~0 without the entry term: no crossing seen
    assert out.weight_sum[1] < 0.01  # misses the sphere: transparent
    # and bounds that start outside the object change nothing
    ref = render_rays(model, o, d, cfg, "hvs")
    near = render_rays(model, o, d, cfg, "hvs", bounds=[StartsAt(2.2)])
    assert (near.weight_sum - ref.weight_sum).abs().max() < 1e-3
