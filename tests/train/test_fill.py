"""`train.fill_weight`: silhouette filling, how far outside the surface the rays stay whose
mask is 1 but that render as misses (`neus_l0.train.losses.missed_rays`), and the mask BCE's
dead zone that it covers."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError
from neus_l0.fields.model import make_model
from neus_l0.render.volume import render_rays
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train import step
from neus_l0.train.losses import mask_bce, missed_rays
from neus_l0.train.step import silhouette_samples


def reference(sdf, full, inside, opacity, weight, margin=0.0):
    """A plain float64 loop: per ray in the mask that renders under 0.5, how far above
    `margin` its shallowest counted sample stays."""
    total = 0.0
    for b in range(sdf.shape[0]):
        if full[b] == 0 or float(opacity[b, 0]) >= 0.5:
            continue
        counted = [float(sdf[b, n]) for n in range(sdf.shape[1]) if inside[b, n] > 0]
        if counted:
            total += float(weight[b]) * max(0.0, min(counted) - margin)
    return total / sdf.shape[0]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 12), st.integers(1, 9), st.booleans(),
       st.sampled_from([0.0, 0.3]))
def test_it_matches_a_plain_loop(seed, b, n, weighted, margin):
    g = torch.Generator().manual_seed(seed)
    sdf = torch.randn(b, n, generator=g, dtype=torch.float64)
    full = (torch.rand(b, generator=g) < 0.6).double()
    inside = (torch.rand(b, n, generator=g) < 0.7).double()
    opacity = torch.rand(b, 1, generator=g, dtype=torch.float64)
    weight = torch.rand(b, generator=g, dtype=torch.float64) * 3 if weighted else None
    got = missed_rays(sdf, full, inside, opacity, weight, torch.tensor(margin, dtype=torch.float64))
    want = reference(sdf, full, inside, opacity, weight if weighted else torch.ones(b), margin)
    assert got.item() == pytest.approx(want, rel=1e-12, abs=1e-15)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_rays_that_hit_or_render_opaque_cost_nothing(seed):
    """A ray in the mask with a sample inside the surface, or one that renders 0.5 or more,
    and every ray off the mask: 0, and no gradient (no bias on a correct surface)."""
    g = torch.Generator().manual_seed(seed)
    sdf = torch.randn(16, 8, generator=g, dtype=torch.float64)
    full = (torch.rand(16, generator=g) < 0.5).double()
    opacity = torch.rand(16, 1, generator=g, dtype=torch.float64)
    hit = torch.rand(16, generator=g) < 0.5
    sdf[hit, 3] = -sdf[hit, 3].abs() - 1e-9  # these rays reach inside
    sdf = torch.where((~hit & (opacity[:, 0] < 0.5))[:, None] & (full[:, None] > 0),
                      -sdf.abs() - 1e-9, sdf).requires_grad_(True)
    loss = missed_rays(sdf, full, torch.ones(16, 8, dtype=torch.float64), opacity)
    loss.backward()
    assert loss.item() == 0.0
    assert torch.count_nonzero(sdf.grad) == 0


def test_the_gradient_reaches_only_each_missed_rays_shallowest_counted_sample():
    # ray 0 misses: its shallowest counted sample is 0.1 (0.05 is not counted); ray 1 is in
    # the mask but renders 0.7: nothing; ray 2 is off the mask: nothing; ray 3 misses by 0.3;
    # ray 4 has no counted sample: nothing
    sdf = torch.tensor([[0.3, 0.1, 0.05, 0.2],
                        [0.4, 0.2, 0.2, 0.3],
                        [0.9, 0.9, 0.9, 0.9],
                        [0.5, 0.3, 0.4, 0.6],
                        [0.5, 0.5, 0.5, 0.5]],
                       requires_grad=True)
    full = torch.tensor([1.0, 1.0, 0.0, 1.0, 1.0])
    opacity = torch.tensor([[0.01], [0.7], [0.0], [0.0], [0.0]])
    inside = torch.ones(5, 4)
    inside[0, 2] = 0.0
    inside[4] = 0.0
    loss = missed_rays(sdf, full, inside, opacity)
    assert loss.item() == pytest.approx((0.1 + 0.3) / 5)
    loss.backward()
    want = torch.zeros(5, 4)
    want[0, 1] = want[3, 1] = 1.0 / 5
    torch.testing.assert_close(sdf.grad, want)


def test_a_ray_within_the_margin_is_left_to_the_mask_bce():
    """Shallowest samples 0.1 and 0.5 above the surface, margin 0.3: only the second counts,
    by 0.2, and only its shallowest sample gets a gradient."""
    sdf = torch.tensor([[0.4, 0.1, 0.2], [0.9, 0.5, 0.7]], requires_grad=True)
    loss = missed_rays(sdf, torch.ones(2), torch.ones(2, 3), torch.zeros(2, 1), margin=0.3)
    assert loss.item() == pytest.approx(0.2 / 2)
    loss.backward()
    torch.testing.assert_close(sdf.grad, torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0]]))


def test_filling_grows_a_too_small_sphere_to_the_silhouette():
    """Parallel rays in a plane, masks of a disc of radius 0.3: minimising the term alone
    (each ray's opacity NeuS's single-crossing closed form, sigmoid(-s min f), s = 500) takes
    a sphere SDF |x| - r from r = 0.05 up to the farthest ray in the mask, and no further."""
    heights = torch.linspace(-0.95, 0.95, 39, dtype=torch.float64)  # ray offsets, 0.05 apart
    full = (heights.abs() <= 0.3 + 1e-9).double()
    t = torch.linspace(-1.0, 1.0, 201, dtype=torch.float64)  # a sample at t = 0
    pts = torch.stack([t[None, :].expand(39, 201), heights[:, None].expand(39, 201)], -1)
    dist = pts.norm(dim=-1)  # (39, 201)
    r = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([r], lr=0.5)
    inside = torch.ones(39, 201, dtype=torch.float64)
    for _ in range(400):
        opt.zero_grad()
        sdf = dist - r
        opacity = torch.sigmoid(-500.0 * sdf.amin(1, keepdim=True))
        missed_rays(sdf, full, inside, opacity).backward()
        opt.step()
    farthest_full = heights[full > 0].abs().max().item()  # 0.3
    assert farthest_full - 0.02 < r.item() <= farthest_full + 0.02


def test_the_mask_bce_has_a_dead_zone_the_term_does_not():
    """A ray in the mask that passes 8/s from a sphere, rendered by NeuS in float32: the
    mask BCE's gradient on the SDF network is exactly 0 (its clip at 1e-3), the term's is
    not. The reason thin parts that did not form early never form."""
    cfg = load_config("demo", ["train.compile=false", "model.sdf.gradient=analytic",
                               "render.perturb=false", "render.cull_outside_sphere=false",
                               "model.sdf.encoding.kind=frequency",
                               "model.sdf.encoding.n_freqs=0", "model.sdf.bias=0.5",
                               "model.variance.init=0.9"])  # s = exp(10 * 0.9) ~ 8100
    torch.manual_seed(0)
    model = make_model(cfg)
    s = float(model.variance.inv_s().detach())
    # rays along x at heights: one 8/s above the initial sphere (r = 0.5), one through it
    heights = torch.tensor([0.5 + 8.0 / s, 0.2])
    origins = torch.stack([torch.full((2,), -1.5), heights, torch.zeros(2)], -1)
    dirs = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    out = render_rays(model, origins, dirs, cfg.render, build_sampler(cfg.sampler))
    params = list(model.sdf.parameters())
    assert out.weight_sum[0, 0].item() < 1e-3 and out.weight_sum[1, 0].item() > 0.5
    bce = mask_bce(out.weight_sum[:1], torch.ones(1, 1))
    g_bce = torch.autograd.grad(bce, params, retain_graph=True, allow_unused=True)
    assert all(g is None or torch.count_nonzero(g) == 0 for g in g_bce)
    fill = missed_rays(out.sdf[:1], torch.ones(1), torch.ones_like(out.sdf[:1]),
                       out.weight_sum[:1])
    g_fill = torch.autograd.grad(fill, params, allow_unused=True)
    assert fill.item() > 0
    assert any(g is not None and torch.count_nonzero(g) > 0 for g in g_fill)


def test_the_step_with_the_term(small, sphere_scene, tmp_path, step_term):
    """On: the rays whose mask is 1 are marked, the loss holds weight x pool share x term
    and the metric reports it; off: nothing is marked and the metric is 0."""
    scene = sphere_scene(tmp_path / "s")
    # a sphere of radius 0.1 at the start: smaller than the object, so rays in it miss
    base = small + ["train.compile=false", "model.sdf.gradient=analytic",
                    "train.photo.weight=0", "model.sdf.bias=0.1"]
    on = load_config("demo", base + ["train.fill_weight=2.0"])
    torch.manual_seed(0)
    model = make_model(on)
    inputs, loss, fill = step_term(model, scene, on, "fill_loss")
    assert inputs.full is not None and torch.equal(inputs.full > 0, inputs.mask[:, 0] > 0.5)
    assert fill > 0
    inputs_off, loss_off, fill_off = step_term(model, scene, load_config("demo", base),
                                               "fill_loss")
    assert inputs_off.full is None and fill_off == 0.0
    assert loss - loss_off == pytest.approx(2.0 * inputs.mask_scale * fill, rel=1e-3, abs=1e-6)


def test_the_step_counts_only_samples_inside_the_silhouettes(small, sphere_scene, tmp_path,
                                                              step_term, monkeypatch):
    """`train.fill_silhouettes`: the term reads the shallowest sample among those inside
    every view's mask, so it is at least the plain term (a minimum over fewer samples), its
    gradient reaches only such samples, and a margin of 0 pushes further than 3/s."""
    scene = sphere_scene(tmp_path / "s")
    base = small + ["train.compile=false", "model.sdf.gradient=analytic",
                    "train.photo.weight=0", "model.sdf.bias=0.1", "train.fill_weight=1.0"]
    torch.manual_seed(0)
    model = make_model(load_config("demo", base))
    plain_in, _, plain = step_term(model, scene, load_config("demo", base), "fill_loss")
    on = load_config("demo", base + ["train.fill_silhouettes=true"])
    inputs, _, fill = step_term(model, scene, on, "fill_loss")
    assert plain_in.silhouettes is None and inputs.silhouettes is not None
    assert fill > 0 and fill >= plain - 1e-9
    _, _, deeper = step_term(model, scene, load_config("demo", base + [
        "train.fill_silhouettes=true", "train.fill_margin=0"]), "fill_loss")
    assert deeper > fill
    # the samples it may read: none outside the silhouettes is the shallowest it takes
    out = render_rays(model, inputs.origins, inputs.dirs, on.render, build_sampler(on.sampler),
                      create_graph=True, noise=inputs.noise)
    inside = silhouette_samples(inputs, out)
    assert 0 < inside.sum() < inside.numel()
    # only missed rays in the mask are tested, at most FILL_RAYS of them
    missed = (inputs.full > 0) & (out.weight_sum[:, 0].detach() < 0.5)
    assert not ((inside.sum(dim=1) > 0) & ~missed).any()
    # `fill_span`: a plain loop over the rays keeps those whose inside samples lie within
    # the span (the median extent here, so that some are kept and some dropped)
    t = out.t_mid.detach()
    extent = {b: float(t[b][inside[b] > 0].max() - t[b][inside[b] > 0].min())
              for b in range(t.shape[0]) if inside[b].any()}
    span = sorted(extent.values())[len(extent) // 2]
    short = silhouette_samples(inputs, out, span)
    kept = {b for b in range(t.shape[0]) if short[b].any()}
    assert kept == {b for b, e in extent.items() if e <= span}
    assert 0 < len(kept) < len(extent)
    assert all(torch.equal(short[b], inside[b]) for b in kept)
    # `fill_middle`: per ray, the one inside sample nearest the middle of the inside ones
    mid = silhouette_samples(inputs, out, 0.0, True)
    for b in range(t.shape[0]):
        if b not in extent:
            assert not mid[b].any()
            continue
        ts = t[b][inside[b] > 0]
        centre = 0.5 * float(ts.min() + ts.max())
        want = min(range(len(ts)), key=lambda i: abs(float(ts[i]) - centre))
        assert mid[b].sum() == 1 and float(t[b][mid[b] > 0][0]) == float(ts[want])
    monkeypatch.setattr(step, "FILL_RAYS", 4)
    rows = silhouette_samples(inputs, out).sum(dim=1) > 0
    assert missed.sum() > 4 and 0 < rows.sum() <= 4 and not (rows & ~missed).any()
    counted = out.inside_sphere * out.active[:, None].float() * inside
    g = torch.autograd.grad(missed_rays(out.sdf, inputs.full, counted, out.weight_sum),
                            out.sdf)[0]
    assert torch.all(g[inside == 0] == 0) and g.abs().sum() > 0


def test_range():
    assert load_config("demo").train.fill_weight >= 0.0
    with pytest.raises(ConfigError, match="fill_weight"):
        load_config("demo", ["train.fill_weight=-1"])
    with pytest.raises(ConfigError, match="fill_weight.*mask_weight"):
        load_config("demo", ["train.fill_weight=1", "train.mask_weight=0"])
    with pytest.raises(ConfigError, match="fill_margin"):
        load_config("demo", ["train.fill_margin=-6"])
    with pytest.raises(ConfigError, match="fill_span"):
        load_config("demo", ["train.fill_span=-0.1"])
    # the narrowing keys say what they need instead of doing nothing
    with pytest.raises(ConfigError, match="fill_silhouettes.*fill_weight"):
        load_config("demo", ["train.fill_silhouettes=true"])
    for key in ("train.fill_span=0.1", "train.fill_middle=true"):
        with pytest.raises(ConfigError, match="fill_silhouettes=true"):
            load_config("demo", ["train.fill_weight=1", key])
    load_config("demo", ["train.fill_weight=1", "train.fill_silhouettes=true",
                         "train.fill_span=0.1", "train.fill_middle=true"])


def test_a_run_builds_the_point_test_only_when_filling_asks(small, sphere_scene, tmp_path):
    """`build_run_state`: the views' silhouettes exist when `fill_silhouettes` is on with
    filling on (not with filling alone)."""
    from neus_l0.train.loop import build_run_state

    scene = sphere_scene(tmp_path / "s")
    base = small + ["train.compile=false", "train.photo.weight=0"]
    cases = ((["train.fill_weight=1", "train.fill_silhouettes=true"], scene, True),
             (["train.fill_weight=1"], scene, False))
    for i, (extra, sc, built) in enumerate(cases):
        run = build_run_state(sc, load_config("demo", base + extra), tmp_path / f"r{i}",
                              torch.device("cpu"), resume=False)
        assert (run.setup.silhouettes is not None) == built
        if built:
            sil = run.setup.silhouettes
            assert sil.covered.numel() == scene.n_views * scene.height * scene.width
            # every foreground pixel is covered, and the margin widens the masks
            assert bool(sil.covered.reshape(scene.masks.shape)[scene.masks > 0].all())
            assert sil.covered.sum() > (scene.masks > 0).sum()
