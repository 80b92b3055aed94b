"""The error map's ``depth`` signal (how deep behind its hull entry a ray's surface lies)
and ``depth_mask`` (that plus the ray's mask error)."""

import types

import pytest
import torch

from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError
from neus_l0.render.volume import render_rays
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.losses import ray_errors


def _out(depth, weight_sum, t0):
    return types.SimpleNamespace(depth=torch.tensor(depth)[:, None],
                                 weight_sum=torch.tensor(weight_sum)[:, None],
                                 t=torch.stack([torch.tensor(t0), torch.tensor(t0) + 1], -1),
                                 color=torch.zeros(len(depth), 3))


def _four_rays(weight_sum):
    """Four rays: on, on, off and on the mask, surfaces at 0.9 / 0.3 / 0.7 / 0.5, entering
    the hull at 0.5 / 0.4 / 0.2 / 0.1; (out, mask, near, rgb)."""
    out = _out([0.9, 0.3, 0.7, 0.5], weight_sum, [0.1, 0.2, 0.3, 0.4])
    mask = torch.tensor([[1.0], [1.0], [0.0], [1.0]])
    return out, mask, torch.tensor([0.5, 0.4, 0.2, 0.1]), torch.zeros(4, 3)


def test_depth_signal_closed_form():
    out, mask, near, rgb = _four_rays([1.0, 1.0, 0.5, 0.0])
    got = ray_errors(out, rgb, mask, True, "depth", near)
    # behind the entry; in front of it (0); off the mask: the mean of the rays on it
    assert got.tolist() == pytest.approx([0.4, 0.0, 0.8 / 3, 0.4])
    # without a hull the first sample is the entry; without masks the opacity weighs it
    assert ray_errors(out, rgb, mask, True, "depth").tolist() == pytest.approx(
        [0.8, 0.1, 1.0 / 3, 0.1])
    assert ray_errors(out, rgb, mask, False, "depth", near).tolist() == pytest.approx(
        [0.4, 0.0, 0.25, 0.0])
    assert not ray_errors(out, rgb, mask, True, "depth", near).requires_grad


def test_depth_mask_signal_adds_the_mask_error_closed_form():
    out, mask, near, rgb = _four_rays([1.0, 0.75, 0.5, 0.0])
    got = ray_errors(out, rgb, mask, True, "depth_mask", near)
    # ``depth`` as above, plus |opacity - mask|: 0, 0.25, 0.5 (slack off the mask), 1 (a miss)
    assert got.tolist() == pytest.approx([0.4, 0.25, 0.8 / 3 + 0.5, 0.4 + 1.0])
    # without masks there is no mask error: as ``depth``
    assert ray_errors(out, rgb, mask, False, "depth_mask", near).tolist() == pytest.approx(
        ray_errors(out, rgb, mask, False, "depth", near).tolist())
    assert not got.requires_grad


def test_depth_mask_draws_the_slack_under_an_object_more_than_depth_does():
    """Pool pixels off the mask where the render still shows surface (slack under an
    object) keep about their uniform share under ``depth`` at fraction 0.8 (however wrong
    they render), and get several times it under ``depth_mask``."""
    from neus_l0.bounds.error_map import draw_probabilities

    g = torch.Generator().manual_seed(1)
    n = 4000
    on = (torch.rand(n, generator=g) > 0.3).float()
    deep = torch.where(torch.rand(n, generator=g) < 0.05, 0.5, 0.01)
    slack = (on == 0) & (torch.rand(n, generator=g) < 0.2)
    opacity = torch.where(on > 0, 1.0, torch.where(slack, 0.6, 0.0))
    share = {}
    for signal in ("depth", "depth_mask"):
        errs = torch.zeros(n)
        for start in range(0, n, 100):
            sl = slice(start, start + 100)
            out = _out(deep[sl].tolist(), opacity[sl].tolist(), [0.0] * 100)
            errs[sl] = ray_errors(out, torch.zeros(100, 3), on[sl, None], True, signal,
                                  torch.zeros(100))
        share[signal] = float(draw_probabilities(errs, 0.8)[slack].sum())
    uniform = float(slack.float().mean())
    assert share["depth"] == pytest.approx(uniform, rel=0.1)
    assert share["depth_mask"] > 3 * uniform


def test_colour_signal_unchanged_by_default():
    out = _out([0.5, 0.5], [0.25, 1.0], [0.0, 0.0])
    out.color = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    mask = torch.tensor([[1.0], [0.0]])
    got = ray_errors(out, torch.zeros(2, 3), mask, True)
    assert got.tolist() == pytest.approx([0.5 + 0.75, 1.0])


def test_config_choice():
    assert load_config("demo").train.error_map.signal == "colour"
    for name in ("depth", "depth_mask"):
        cfg = load_config("demo", [f"train.error_map.signal={name}"])
        assert cfg.train.error_map.signal == name
    with pytest.raises(ConfigError, match="signal"):
        load_config("demo", ["train.error_map.signal=normal"])


def test_rays_into_a_pit_score_its_depth_and_open_rays_nothing(analytic_sphere, sphere_model):
    """A ball of radius 0.5 with a pit (radius 0.15, floor at z = 0.1) rendered straight down:
    rays into the pit score the floor's depth behind the ball's top (0.4), rays that meet the
    open surface score about 0 (the ball is its own hull here)."""

    class Pitted(analytic_sphere):
        def forward(self, x):
            d = super().forward(x)
            r = x[:, :2].norm(dim=-1, keepdim=True)
            pit = torch.maximum(r - 0.15, 0.1 - x[:, 2:3])  # inside < 0
            return torch.cat([torch.maximum(d[:, :1], -pit), d[:, 1:]], -1)

    model = sphere_model(s_init=0.8)
    model.sdf = Pitted()
    cfg = load_config("demo", ["render.n_samples=64", "render.n_importance=64"])
    xy = torch.tensor([[0.0, 0.0], [0.05, -0.04], [0.3, 0.0], [-0.25, 0.2]])
    origins = torch.cat([xy, torch.full((4, 1), 0.95)], -1)
    dirs = torch.tensor([[0.0, 0.0, -1.0]]).expand(4, 3)
    with torch.no_grad():
        out = render_rays(model, origins, dirs, cfg.render, build_sampler(cfg.sampler),
                          cos_anneal_ratio=1.0, create_graph=False)
    top = 0.95 - (0.25 - (xy ** 2).sum(-1)).sqrt()  # entry into the ball
    err = ray_errors(out, torch.zeros(4, 3), torch.ones(4, 1), True, "depth", top)
    assert err[:2].tolist() == pytest.approx((0.85 - top[:2]).tolist(), abs=0.02)
    assert err[2:].max() < 0.02


def test_rays_off_the_mask_keep_their_uniform_share_on_average():
    """Over a pool where a fifth of the pixels are off the mask, a map fed with the depth
    signal gives them a fifth of its mass (in expectation over batches), so the rays that
    carve the hull's slack are not starved."""
    from neus_l0.bounds.error_map import draw_probabilities

    g = torch.Generator().manual_seed(0)
    n = 5000
    on = (torch.rand(n, generator=g) > 0.2).float()
    deep = torch.rand(n, generator=g) ** 3  # a few deep pixels
    signal = torch.zeros(n)
    for start in range(0, n, 100):  # batches of 100 rays, each pixel once
        sl = slice(start, start + 100)
        out = _out(deep[sl].tolist(), [1.0] * 100, [0.0] * 100)
        signal[sl] = ray_errors(out, torch.zeros(100, 3), on[sl, None], True, "depth",
                                torch.zeros(100))
    p = draw_probabilities(signal, 1.0)
    off_share = float(p[on == 0].sum())
    assert off_share == pytest.approx(float((on == 0).float().mean()), abs=0.02)
    deep_on = (on == 1) & (deep > 0.5)
    assert float(p[deep_on].sum()) > 2 * float(deep_on.float().mean())


def test_a_large_pool_refreshes_its_table_less_often():
    from neus_l0.bounds.error_map import PIXELS_PER_STEP, refresh_interval

    assert refresh_interval(10_000, 50) == 50
    assert refresh_interval(1_344_701, 50) == -(-1_344_701 // PIXELS_PER_STEP) == 337
    assert refresh_interval(0, 0) == 1
