"""Rendering: sphere bounds, the up-sampling weights, every sampler on an analytic sphere."""

import dataclasses

import pytest
import torch
from torch import nn

from neus_l0.bounds.sphere import near_far_from_sphere
from neus_l0.config.schema import SAMPLERS, ColorConfig, RenderConfig, VarianceConfig
from neus_l0.fields.color import ColorNetwork
from neus_l0.fields.model import NeuSModel, build_model
from neus_l0.fields.variance import SingleVariance
from neus_l0.render.volume import (
    coarse_z_vals,
    draw_noise,
    outside_z_vals,
    render_image,
    render_rays,
)
from neus_l0.sampling.upsample import (
    Sections,
    build_sampler,
    section_to_point_weights,
    transmittance,
    upsample_section_weights,
)
from neus_l0.train.losses import eikonal

RADIUS = 0.5  # of the `sphere_model` fixture's sphere (tests/conftest.py)


def rays_at_sphere(n=256, seed=0):
    """Rays from distance 3 towards points near the centre, and the analytic first hit.

    `hit` marks rays that meet the sphere well away from grazing (whose opacity is low by
    design); `t_hit` is their first intersection.
    """
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    d = torch.randn(n, 3, generator=g) * 0.15 - o
    d = d / d.norm(dim=-1, keepdim=True)
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - RADIUS**2)
    hit = disc > 0.01
    t_hit = -b - disc.clamp_min(0).sqrt()
    return o, d, hit, t_hit


def disc_miss(o, d):
    b = (o * d).sum(-1)
    return b * b - ((o * o).sum(-1) - RADIUS**2) < -0.01


def test_near_far_is_the_unit_sphere_chord():
    o, d, _, _ = rays_at_sphere(64)
    near, far = near_far_from_sphere(o, d)
    assert torch.allclose(far - near, torch.full_like(near, 2.0))
    mid = 0.5 * (near + far)
    closest = o + mid * d
    assert ((closest * d).sum(-1)).abs().max() < 1e-5  # mid is the closest point to 0


def test_coarse_and_outside_samples():
    near, far = torch.zeros(4, 1), torch.full((4, 1), 2.0)
    z = coarse_z_vals(near, far, 16, perturb=False)
    assert torch.allclose(z[0], torch.linspace(0, 2, 16))
    g = torch.Generator().manual_seed(0)
    zp = coarse_z_vals(near, far, 16, perturb=True, generator=g)
    assert ((zp - z).abs() <= 1.0 / 16 + 1e-6).all()
    zo = outside_z_vals(far, 8, 16, perturb=True, generator=g)
    assert zo.shape == (4, 8) and (zo > far).all()
    assert (zo[:, 1:] >= zo[:, :-1]).all()


def test_upsample_weights_peak_at_the_surface():
    z = torch.linspace(0.0, 2.0, 65)[None]  # a ray through the centre from distance 1
    sdf = (z - 1.0).abs() - RADIUS  # surface at z = 0.5 and 1.5
    radius = (z - 1.0).abs()
    w = upsample_section_weights(z, sdf, radius, 64.0).weights
    assert w.shape == (1, 64)
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    assert (mids[0, w[0].argmax()] - 0.5).abs() < 2.0 / 64
    assert w.sum() <= 1.0 + 1e-5


def test_transmittance():
    alpha = torch.tensor([[0.5, 0.5, 1.0, 0.3]])
    assert torch.allclose(transmittance(alpha), torch.tensor([[1.0, 0.5, 0.25, 0.0]]), atol=1e-6)


def test_section_to_point_weights():
    z = torch.tensor([[0.0, 1.0, 1.5, 3.5]])
    w = torch.tensor([[0.2, 0.3, 0.4]])
    t, p = section_to_point_weights(z, w, "midpoint", as_density=False)
    assert torch.allclose(t, torch.tensor([[0.5, 1.25, 2.5]])) and torch.equal(p, w)
    t, p = section_to_point_weights(z, w, "endpoint", as_density=False)
    assert torch.equal(t, z)
    assert torch.allclose(p, torch.tensor([[0.2, 0.25, 0.35, 0.4]]))
    # as densities: weight / length, scaled by the mean length (uniform sections unchanged)
    _, p = section_to_point_weights(z, w, "midpoint", as_density=True)
    mean = 3.5 / 3
    assert torch.allclose(p, torch.tensor([[0.2 / 1.0, 0.3 / 0.5, 0.4 / 2.0]]) * mean)
    zu = torch.linspace(0, 1, 5)[None]
    _, pu = section_to_point_weights(zu, w[:, :3].repeat(1, 2)[:, :4], "midpoint")
    assert torch.allclose(pu, w[:, :3].repeat(1, 2)[:, :4])


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_draw_fine_samples_inside_range_and_sorted(sampler):
    z = torch.sort(torch.rand(32, 20), dim=-1).values
    w = torch.rand(32, 19)
    sec = Sections(z=z, weights=w, prev_sdf=torch.rand(32, 19), next_sdf=-torch.rand(32, 19),
                   inv_s=64.0)
    s = build_sampler(sampler).draw(sec, 16)
    assert s.shape == (32, 16) and torch.isfinite(s).all()
    assert (s[:, 1:] >= s[:, :-1]).all()
    assert (s >= z[:, :1] - 1e-6).all() and (s <= z[:, -1:] + 1e-6).all()


def test_unknown_sampler():
    with pytest.raises(ValueError, match="unknown sampler"):
        build_sampler("nope")


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_fine_samples_cluster_at_an_analytic_sphere(sphere_model, sampler):
    torch.manual_seed(0)
    model = sphere_model()
    cfg = RenderConfig()
    o, d, hit, t_hit = rays_at_sphere(256)
    out = render_rays(model, o, d, cfg, build_sampler(sampler), create_graph=False)
    for f in dataclasses.fields(out):
        assert torch.isfinite(getattr(out, f.name)).all(), f.name
    assert out.t_fine.shape == (256, 64) and out.t.shape == (256, 128)
    err = (out.t_fine[hit] - t_hit[hit, None]).abs()
    # most fine samples lie within a few 1/inv_s of the first surface hit
    assert (err < 0.02).float().mean() > 0.5, sampler
    assert err.median() < 0.02
    # the rendered depth and opacity see the sphere
    assert (out.depth[hit, 0] - t_hit[hit]).abs().mean() < 5e-3
    assert (out.weight_sum[hit] > 0.95).all()
    assert (out.weight_sum[disc_miss(o, d)] < 0.05).all()
    # normals of hit rays point back to the camera and are about unit length
    n = out.normal[hit]
    cos = (n * d[hit]).sum(-1)
    assert (cos < 0).all() and cos.mean() < -0.8


def test_l0_midpoint_default_at_least_as_tight_as_endpoint(sphere_model):
    """The documented default: midpoints cluster the fine samples no worse than endpoints."""
    model = sphere_model()
    o, d, hit, t_hit = rays_at_sphere(256)
    frac = {}
    for placement in ("midpoint", "endpoint"):
        from neus_l0.config.schema import L0Config, SamplerConfig

        out = render_rays(model, o, d, RenderConfig(),
                          build_sampler(SamplerConfig(l0=L0Config(placement=placement))))
        frac[placement] = ((out.t_fine[hit] - t_hit[hit, None]).abs() < 0.005).float().mean()
    assert frac["midpoint"] >= frac["endpoint"] - 0.01


def test_render_rays_gradients_and_background():
    torch.manual_seed(0)
    from neus_l0.config.schema import ModelConfig, SDFConfig

    mcfg = ModelConfig(sdf=SDFConfig(hidden=64, layers=2, skip=[], feature_dim=16))
    mcfg.color.hidden = mcfg.background.hidden = 32
    mcfg.background.layers, mcfg.background.skip = 2, []
    model = build_model(mcfg, background=True)
    cfg = RenderConfig(n_samples=16, n_importance=16, up_sample_steps=2, n_outside=8)
    o, d, _, _ = rays_at_sphere(32)
    g = torch.Generator().manual_seed(0)
    out = render_rays(model, o, d, cfg, build_sampler("l0"), cos_anneal_ratio=0.5,
                      noise=draw_noise(cfg, 32, g, o.device), create_graph=True)
    assert out.weights.shape == (32, 32 + 8)
    assert out.gradients.shape == (32, 32, 3)
    for f in dataclasses.fields(out):
        assert torch.isfinite(getattr(out, f.name)).all(), f.name
    loss = out.color.sum() + eikonal(out.gradients, out.eikonal_mask)
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert model.background.rgb.weight.grad.abs().sum() > 0


def test_render_is_deterministic_given_the_generator(sphere_model):
    model = sphere_model()
    o, d, _, _ = rays_at_sphere(16)
    outs = [render_rays(model, o, d, RenderConfig(), build_sampler("l0"),
                        noise=draw_noise(RenderConfig(), 16, torch.Generator().manual_seed(3),
                                         o.device)).t for _ in range(2)]
    assert torch.equal(outs[0], outs[1])


def test_render_image_shapes(sphere_model):
    model = sphere_model()
    o, d, _, _ = rays_at_sphere(12)
    out = render_image(model, o.reshape(3, 4, 3), d.reshape(3, 4, 3),
                       RenderConfig(n_samples=16, n_importance=16, up_sample_steps=2),
                       build_sampler("l0"), chunk=5)
    assert out["color"].shape == (3, 4, 3) and out["depth"].shape == (3, 4)
    assert not out["color"].requires_grad


# ------------------------------------------------------------------------------------------
# Skipping work: sphere culling and the occupancy grid.


@pytest.fixture
def counting_model(analytic_sphere):
    """A factory like `sphere_model`, whose sphere counts the points it is evaluated at."""

    class CountingSphere(analytic_sphere):
        """`AnalyticSphere` that counts the points it is evaluated at."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.points = 0

        def forward(self, x):
            self.points += x.shape[0]
            return super().forward(x)

    def make(s_init=0.6):
        return NeuSModel(CountingSphere(), ColorNetwork(ColorConfig(hidden=16, layers=2), 8),
                         SingleVariance(VarianceConfig(init=s_init)))

    return make


def sphere_grid(model, resolution=64):
    from neus_l0.bounds.occupancy import OccupancyGrid
    from neus_l0.config.schema import OccupancyConfig

    grid = OccupancyGrid(OccupancyConfig(enabled=True, resolution=resolution))
    grid.update(model.sdf.sdf, model.variance.inv_s())
    return grid


@pytest.mark.parametrize("sampler", ["hvs", "l0"])
def test_grid_gives_the_same_render_on_rays_that_hit(sphere_model, sampler):
    torch.manual_seed(0)
    model = sphere_model()
    o, d, hit, t_hit = rays_at_sphere(256)
    ref = render_rays(model, o, d, RenderConfig(), build_sampler(sampler))
    grid = sphere_grid(model)
    assert grid.fraction_occupied() < 0.1
    for compact in (True, False):
        cfg = RenderConfig(cull_outside_sphere=True)
        cfg.occupancy.compact = compact
        out = render_rays(model, o, d, cfg, build_sampler(sampler), bounds=(grid,))
        for f in dataclasses.fields(out):
            assert torch.isfinite(getattr(out, f.name)).all(), f.name
        assert out.active[hit].all()
        assert (out.color[hit] - ref.color[hit]).abs().max() < 1e-3
        assert (out.depth[hit] - ref.depth[hit]).abs().max() < 2e-3
        assert (out.depth[hit, 0] - t_hit[hit]).abs().mean() < 5e-3
        assert (out.weight_sum[hit] - ref.weight_sum[hit]).abs().max() < 2e-3
        # samples only inside the tightened span: none more than the band (about
        # 1.5 half-diagonals + 6 / s + a dilated cell + a lookup step) before the surface
        assert (out.t[hit].min(dim=-1).values > t_hit[hit] - 0.25).all()
        assert (ref.t[hit].min(dim=-1).values < t_hit[hit] - 0.4).all()


def test_rays_that_cross_no_occupied_cell_do_no_sdf_work(counting_model):
    model = counting_model()
    grid = sphere_grid(model)
    # rays through the unit sphere that pass the r = 0.5 sphere at distance >= 0.8
    o = torch.tensor([[-3.0, 0.8, 0.0], [-3.0, 0.0, -0.85], [0.9, -3.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    out = render_rays(model, o, d, RenderConfig(), build_sampler("l0"), bounds=(grid,),
                      create_graph=True)
    assert not out.active.any()
    assert torch.equal(out.weight_sum, torch.zeros(3, 1))
    assert torch.equal(out.color, torch.zeros(3, 3))
    assert eikonal(out.gradients, out.eikonal_mask) == 0
    # mixed with hitting rays, only those are evaluated
    o2 = torch.cat([o, torch.tensor([[-3.0, 0.0, 0.0]])])
    d2 = torch.cat([d, torch.tensor([[1.0, 0.0, 0.0]])])
    cfg = RenderConfig(n_samples=16, n_importance=16, up_sample_steps=2)
    out = render_rays(model, o2, d2, cfg, build_sampler("l0"), bounds=(grid,))
    assert out.active.tolist() == [False, False, False, True]
    # render_rays keeps every batch's shape (inactive rays are masked); render_image skips
    # their networks: only the hitting ray is evaluated
    per_ray = 16 + 8 + 32  # coarse + one intermediate round + the final pass
    model.sdf.points = 0
    img = render_image(model, o2.reshape(2, 2, 3), d2.reshape(2, 2, 3), cfg, build_sampler("l0"),
                       bounds=(grid,))
    assert model.sdf.points == per_ray
    assert torch.equal(img["weight_sum"].reshape(-1)[:3], torch.zeros(3))
    model.sdf.points = 0
    render_image(model, o.reshape(1, 3, 3), d.reshape(1, 3, 3), cfg, build_sampler("l0"),
                 bounds=(grid,))
    assert model.sdf.points == 0


def test_rays_missing_the_sphere_get_no_samples(counting_model):
    model = counting_model()
    o = torch.tensor([[-3.0, 1.2, 0.0], [0.0, 0.0, 3.0], [-3.0, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # miss, behind, hit
    cfg = RenderConfig(n_samples=16, n_importance=16, up_sample_steps=2,
                       cull_outside_sphere=True)
    out = render_rays(model, o, d, cfg, build_sampler("l0"))
    assert out.active.tolist() == [False, False, True]
    model.sdf.points = 0
    render_image(model, o.reshape(1, 3, 3), d.reshape(1, 3, 3), cfg, build_sampler("l0"))
    assert model.sdf.points == 16 + 8 + 32
    assert torch.equal(out.weight_sum[:2], torch.zeros(2, 1))
    assert out.weight_sum[2] > 0.99
    # the hitting ray's coarse samples lie on its chord of the unit sphere, [2, 4]
    z = out.t[2]
    assert z.min() >= 2.0 - 1e-5 and z.max() <= 4.0 + 1e-5


def test_no_background_network_with_masks(sphere_model):
    from neus_l0.config.load import load_config
    from neus_l0.fields.model import make_model

    cfg = load_config("wmask", ["model.sdf.hidden=48", "model.color.hidden=16"])
    assert cfg.train.mask_weight > 0 and cfg.render.n_outside == 0
    assert make_model(cfg).background is None
    assert make_model(load_config("womask")).background is not None

    class Forbidden(nn.Module):
        def forward(self, *args):
            raise AssertionError("the background model was called")

    model = sphere_model()
    model.background = Forbidden()
    o, d, _, _ = rays_at_sphere(8)
    render_rays(model, o, d, RenderConfig(n_outside=0), build_sampler("l0"))


def test_culling_keeps_the_background_model_for_missed_rays():
    torch.manual_seed(0)
    from neus_l0.config.schema import ModelConfig, SDFConfig

    mcfg = ModelConfig(sdf=SDFConfig(hidden=32, layers=2, skip=[], feature_dim=8))
    mcfg.color.hidden = mcfg.background.hidden = 16
    mcfg.background.layers, mcfg.background.skip = 2, []
    model = build_model(mcfg, background=True)
    cfg = RenderConfig(n_samples=8, n_importance=8, up_sample_steps=2, n_outside=8,
                       cull_outside_sphere=True)
    o = torch.tensor([[-3.0, 1.5, 0.0], [-3.0, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    out = render_rays(model, o, d, cfg, build_sampler("l0"), create_graph=True)
    assert out.active.tolist() == [False, True]
    assert (out.weights[0, -8:] > 0).all()  # the background still renders the miss
    out.color.sum().backward()
    assert model.background.rgb.weight.grad.abs().sum() > 0


def test_eikonal_subset_estimates_the_full_term():
    from neus_l0.train.losses import eikonal_subset

    g = torch.Generator().manual_seed(0)
    grads = torch.randn(64, 32, 3, generator=g)
    mask = (torch.rand(64, 32, generator=g) < 0.7).float()
    full = (mask * (grads.norm(dim=-1) - 1.0) ** 2).sum() / mask.sum()
    sub = torch.stack([eikonal_subset(grads, mask, 0.25, g) for _ in range(50)])
    assert (sub.mean() - full).abs() < 0.05 * full
    assert torch.isclose(eikonal_subset(grads, torch.zeros_like(mask), 0.5, g),
                         torch.zeros(()))


def test_transmittance_backward_equals_cumprods_in_float64():
    """The closed-form backward of `transmittance` against autograd's cumprod backward."""
    g = torch.Generator().manual_seed(0)
    alpha = torch.rand(6, 9, generator=g, dtype=torch.float64)
    alpha[0, 4] = 1.0  # an opaque sample: factor 1e-7
    alpha[1] = 0.0
    w = torch.randn(6, 9, generator=g, dtype=torch.float64)
    a1 = alpha.clone().requires_grad_(True)
    ones = torch.ones(6, 1, dtype=torch.float64)
    ref = torch.cumprod(torch.cat([ones, 1.0 - a1 + 1e-7], dim=-1), dim=-1)[:, :-1]
    (g_ref,) = torch.autograd.grad((ref * w).sum(), a1)
    a2 = alpha.clone().requires_grad_(True)
    got = transmittance(a2)
    (g_got,) = torch.autograd.grad((got * w).sum(), a2)
    torch.testing.assert_close(got, ref.detach(), rtol=0, atol=1e-15)
    torch.testing.assert_close(g_got, g_ref, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(transmittance, (alpha[:, :5].clone().requires_grad_(True),))
