"""`neus_l0.sampling.upsample`: the registry, the sampler objects, and NeuS's up-sampling rounds."""

from __future__ import annotations

import pytest
import torch

from neus_l0.bounds.sphere import near_far_from_sphere
from neus_l0.config.schema import SAMPLERS, L0Config, SamplerConfig
from neus_l0.render import volume as rendering
from neus_l0.sampling.kernels import sample_l0, sample_l0_sections
from neus_l0.sampling.upsample import (
    HVSSampler,
    L0Sampler,
    NeuSExactSampler,
    Sections,
    build_sampler,
    section_to_point_weights,
    up_sample,
    upsample_section_weights,
)
from neus_l0.synthetic.shapes import Sphere


def _sections(B: int = 6, N: int = 17, seed: int = 0) -> Sections:
    """NeuS sections of rays through a plane at depth 1.3 (uneven coarse positions)."""
    g = torch.Generator().manual_seed(seed)
    z = torch.sort(torch.rand(B, N, generator=g) * 2.0 + 0.3, dim=-1).values
    cos = 0.3 + 0.7 * torch.rand(B, 1, generator=g)
    sdf = (1.3 - z) * cos
    return upsample_section_weights(z, sdf, torch.full_like(z, 0.5), 64.0)


def test_registry_builds_every_name():
    for name in SAMPLERS:
        s = build_sampler(name)
        assert s.name == name and s.base_inv_s == 64.0
        out = s.draw(_sections(), 8)
        assert out.shape == (6, 8) and (out[:, 1:] >= out[:, :-1]).all()
    assert isinstance(build_sampler("hvs"), HVSSampler)
    assert isinstance(build_sampler("neus-exact"), NeuSExactSampler)
    assert build_sampler("l0-inverse").kind == "inverse"
    assert build_sampler(SamplerConfig(name="l0", l0=L0Config(kind="linear"))).kind == "linear"
    assert build_sampler(SamplerConfig(name="hvs", base_inv_s=32.0)).base_inv_s == 32.0
    with pytest.raises(ValueError, match="neus-exact"):
        build_sampler("nope")


def test_sections_of_a_plane_are_its_linear_sdf():
    sec = _sections()
    prev_sdf, next_sdf = sec.estimates()
    assert sec.weights.shape == prev_sdf.shape == (6, 16) and sec.inv_s == 64.0
    assert (prev_sdf >= next_sdf).all()
    # a linear SDF: NeuS's estimates are the SDF at the section ends (up to its 1e-5 guard)
    z = sec.z
    sdf = 0.5 * (prev_sdf + next_sdf)  # the midpoint value is exact
    slope = (prev_sdf - next_sdf)[:, 1:] / (z[:, 2:] - z[:, 1:-1])
    torch.testing.assert_close(slope, slope[:, :1].expand_as(slope), rtol=1e-3, atol=1e-3)
    assert torch.isfinite(sdf).all()
    assert (sec.weights >= 0).all() and sec.weights.sum(-1).max() <= 1.0 + 1e-4


def _neus_up_sample_weights(z, sdf, radius, inv_s):
    """NeuS's `up_sample` weights and estimates, written as NeuS writes them (float64)."""
    inside = ((radius[:, :-1] < 1.0) | (radius[:, 1:] < 1.0)).to(z.dtype)
    prev_sdf, next_sdf = sdf[:, :-1], sdf[:, 1:]
    prev_z, next_z = z[:, :-1], z[:, 1:]
    mid_sdf = (prev_sdf + next_sdf) * 0.5
    cos_val = (next_sdf - prev_sdf) / (next_z - prev_z + 1e-5)
    prev_cos = torch.cat([torch.zeros_like(cos_val[:, :1]), cos_val[:, :-1]], dim=-1)
    cos_val = torch.stack([prev_cos, cos_val], dim=-1).min(dim=-1).values
    cos_val = cos_val.clip(-1e3, 0.0) * inside
    dist = next_z - prev_z
    prev_esti = mid_sdf - cos_val * dist * 0.5
    next_esti = mid_sdf + cos_val * dist * 0.5
    prev_cdf = torch.sigmoid(prev_esti * inv_s)
    next_cdf = torch.sigmoid(next_esti * inv_s)
    alpha = (prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-7],
                                    dim=-1), dim=-1)[:, :-1]
    return alpha * trans, prev_esti, next_esti


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_section_weights_are_neus_formula(dtype):
    """The fused section weights equal NeuS's own code; radius=None equals all inside."""
    g = torch.Generator().manual_seed(3)
    z = torch.sort(torch.rand(64, 40, generator=g, dtype=torch.float64) * 2.0, dim=-1).values
    sdf = torch.randn(64, 40, generator=g, dtype=torch.float64) * 0.2
    radius = torch.rand(64, 40, generator=g, dtype=torch.float64) * 1.6
    z, sdf, radius = z.to(dtype), sdf.to(dtype), radius.to(dtype)
    tol = {"rtol": 1e-12, "atol": 1e-15} if dtype == torch.float64 else {}
    for inv_s in (64.0, 512.0):
        want_w, want_p, want_n = _neus_up_sample_weights(z, sdf, radius, inv_s)
        sec = upsample_section_weights(z, sdf, radius, inv_s)
        torch.testing.assert_close(sec.weights, want_w, **tol)
        torch.testing.assert_close(sec.estimates()[0], want_p, **tol)
        torch.testing.assert_close(sec.estimates()[1], want_n, **tol)
        torch.testing.assert_close(sec.lengths(), z[:, 1:] - z[:, :-1])
        inside = upsample_section_weights(z, sdf, None, inv_s)
        torch.testing.assert_close(inside.weights, _neus_up_sample_weights(
            z, sdf, torch.zeros_like(radius), inv_s)[0], **tol)


def test_hvs_draw_with_the_sections_lengths_is_the_plain_draw():
    """`sample_pdf(lengths=...)`, as the up-sampling calls it, draws what it draws without."""
    from neus_l0.sampling.kernels import quantiles, sample_pdf

    for weights in (_sections().weights, torch.zeros(6, 16)):  # and the uniform fallback
        sec = _sections()
        u = quantiles((6,), 16, True, None, sec.z.dtype, sec.z.device)
        with_len = sample_pdf(sec.z, weights, 16, u=u, lengths=sec.lengths())
        assert torch.equal(with_len, sample_pdf(sec.z, weights, 16, u=u))


def test_relative_pad_does_not_depend_on_the_weights_scale():
    sec = _sections()
    small = Sections(sec.z, sec.weights * 1e-3, *sec.estimates(), sec.inv_s)
    rel = L0Sampler(pad=0.01, pad_mode="relative", masses="interpolant")
    torch.testing.assert_close(rel.draw(small, 16), rel.draw(sec, 16))
    ab = L0Sampler(pad=0.01, pad_mode="absolute", masses="interpolant")
    assert not torch.allclose(ab.draw(small, 16), ab.draw(sec, 16))


def test_relative_pad_holds_a_bounded_share():
    """One sharp section: the samples outside it are the pad's, at most pad / (1 + pad)."""
    z = torch.linspace(0.0, 2.0, 65)[None]
    w = torch.zeros(1, 64)
    w[0, 30] = 0.9
    sec = Sections(z, w, torch.zeros_like(w), torch.zeros_like(w), 64.0)
    for pad in (0.01, 0.1):
        s = L0Sampler(pad=pad, pad_mode="relative", blur=True, masses="interpolant").draw(sec, 2000)
        away = ((s < z[0, 28]) | (s > z[0, 33])).float().mean().item()
        assert 0.0 < away <= pad / (1 + pad)
    none = L0Sampler(pad=0.5, pad_mode="none", masses="interpolant").draw(sec, 64)
    torch.testing.assert_close(none, L0Sampler(pad=0.0, masses="interpolant").draw(sec, 64))


def test_l0_sampler_is_sample_l0_on_point_weights():
    sec = _sections()
    s = L0Sampler(kind="inverse", pad=0.002, pad_mode="absolute", blur=True,
                  placement="endpoint", as_density=False, masses="interpolant")
    t, w = s.point_weights(sec)
    assert t.shape == sec.z.shape
    torch.testing.assert_close(s.draw(sec, 12), sample_l0(t, w, 12, kind="inverse", pad=0.002))
    plain = L0Sampler(masses="interpolant")  # the paper's draw: no maxblur, no pad
    t, w = plain.point_weights(sec)
    torch.testing.assert_close(plain.draw(sec, 12), sample_l0(t, w, 12, blur=False))
    default = L0Sampler()  # the default: section masses, the interpolant inside
    torch.testing.assert_close(default.draw(sec, 12), sample_l0_sections(sec.z, sec.weights, 12))
    # without blur the pad is added
    padded = L0Sampler(pad=0.05, pad_mode="absolute", masses="interpolant")
    t, w = padded.point_weights(sec)
    torch.testing.assert_close(w, section_to_point_weights(sec.z, sec.weights)[1] + 0.05)


def _sphere_rays(B: int = 32):
    g = torch.Generator().manual_seed(2)
    v = torch.nn.functional.normalize(torch.randn(B, 3, generator=g), dim=-1)
    target = 0.3 * torch.nn.functional.normalize(torch.randn(B, 3, generator=g), dim=-1)
    d = torch.nn.functional.normalize(target - 2.5 * v, dim=-1)
    return 2.5 * v, d


@pytest.mark.parametrize("name", SAMPLERS)
def test_up_sample_rounds(name):
    o, d = _sphere_rays()
    near, far = near_far_from_sphere(o, d)
    z = rendering.coarse_z_vals(near, far, 16, perturb=False)
    z_all, z_new = up_sample(Sphere((0.0, 0.0, 0.0), 0.5), o, d, z, build_sampler(name), 16, 2)
    assert z_all.shape == (32, 32) and z_new.shape == (32, 16)
    assert (z_all[:, 1:] >= z_all[:, :-1]).all()
    assert (z_new >= near).all() and (z_new <= far).all()
    for half in (z_new[:, :8], z_new[:, 8:]):  # sorted within each round
        assert (half[:, 1:] >= half[:, :-1]).all()
    same, none = up_sample(lambda p: p[:, 0], o, d, z, build_sampler(name), 0, 2)
    assert same is z and none.shape == (32, 0)


def test_neus_exact_lands_closer_to_a_sphere_than_hvs():
    """The exact CDF puts the fine samples nearer the first hit than NeuS's own draw."""
    o, d = _sphere_rays(64)
    b = (o * d).sum(-1)
    hit = -b - (b * b - ((o * o).sum(-1) - 0.25)).sqrt()  # (B,) ray-sphere intersection
    near, far = near_far_from_sphere(o, d)
    z = rendering.coarse_z_vals(near, far, 16, perturb=False)
    med = {}
    for name in ("hvs", "neus-exact"):
        _, z_new = up_sample(Sphere((0.0, 0.0, 0.0), 0.5), o, d, z, build_sampler(name), 16, 2)
        med[name] = (z_new - hit[:, None]).abs().median().item()
    assert med["neus-exact"] < 0.8 * med["hvs"]
