"""`train.carve_weight`: silhouette carving, how far inside the surface the rays whose mask is
0 go (`neus_l0.train.losses.free_space`)."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError
from neus_l0.fields.model import make_model
from neus_l0.train.losses import free_space
from neus_l0.train.step import draw_step_inputs


def reference(sdf, empty, inside, weight):
    """A plain float64 loop: per empty ray, the deepest counted sample's depth inside."""
    total = 0.0
    for b in range(sdf.shape[0]):
        if empty[b] == 0:
            continue
        deepest = 0.0
        for n in range(sdf.shape[1]):
            if inside[b, n] > 0 and -float(sdf[b, n]) > deepest:
                deepest = -float(sdf[b, n])
        total += float(weight[b]) * deepest
    return total / sdf.shape[0]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 12), st.integers(1, 9), st.booleans())
def test_it_matches_a_plain_loop(seed, b, n, weighted):
    g = torch.Generator().manual_seed(seed)
    sdf = torch.randn(b, n, generator=g, dtype=torch.float64)
    empty = (torch.rand(b, generator=g) < 0.5).double()
    inside = (torch.rand(b, n, generator=g) < 0.7).double()
    weight = torch.rand(b, generator=g, dtype=torch.float64) * 3 if weighted else None
    got = free_space(sdf, empty, inside, weight)
    want = reference(sdf, empty, inside, weight if weighted else torch.ones(b))
    assert got.item() == pytest.approx(want, rel=1e-12, abs=1e-15)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_an_sdf_that_agrees_with_the_masks_costs_nothing(seed):
    """Positive along every empty ray (negative elsewhere allowed): 0, and no gradient."""
    g = torch.Generator().manual_seed(seed)
    sdf = torch.randn(16, 8, generator=g, dtype=torch.float64)
    empty = (torch.rand(16, generator=g) < 0.5).double()
    sdf = torch.where(empty[:, None] > 0, sdf.abs() + 1e-9, sdf).requires_grad_(True)
    loss = free_space(sdf, empty, torch.ones(16, 8, dtype=torch.float64))
    loss.backward()
    assert loss.item() == 0.0
    assert torch.count_nonzero(sdf.grad) == 0


def test_the_gradient_reaches_only_each_empty_rays_deepest_counted_sample():
    # ray 0 is empty: its deepest counted sample is -0.2 (-0.5 is not counted); ray 1 is
    # empty: -0.4; ray 2 is not empty: nothing
    sdf = torch.tensor([[0.3, -0.2, -0.5, 0.1],
                        [-0.4, -0.1, 0.2, 0.3],
                        [-0.9, -0.9, -0.9, -0.9]],
                       requires_grad=True)
    empty = torch.tensor([1.0, 1.0, 0.0])
    inside = torch.tensor([[1.0, 1.0, 0.0, 1.0], [1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    loss = free_space(sdf, empty, inside)
    assert loss.item() == pytest.approx((0.2 + 0.4) / 3)
    loss.backward()
    want = torch.zeros(3, 4)
    want[0, 1] = want[1, 0] = -1.0 / 3
    torch.testing.assert_close(sdf.grad, want)


def test_carving_shrinks_a_too_large_sphere_to_the_silhouette():
    """Parallel rays in a plane, masks of a disc of radius 0.3: minimising the term alone
    takes a sphere SDF |x| - r from r = 0.8 down to the nearest empty ray's distance, and
    no further (the hinge has no gradient once the SDF agrees with the masks)."""
    heights = torch.linspace(-0.95, 0.95, 39, dtype=torch.float64)  # ray offsets, 0.05 apart
    empty = (heights.abs() > 0.3).double()
    t = torch.linspace(-1.0, 1.0, 64, dtype=torch.float64)
    pts = torch.stack([t[None, :].expand(39, 64), heights[:, None].expand(39, 64)], -1)
    dist = pts.norm(dim=-1)  # (39, 64)
    r = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([r], lr=0.5)
    for _ in range(400):
        opt.zero_grad()
        free_space(dist - r, empty, torch.ones(39, 64, dtype=torch.float64)).backward()
        opt.step()
    nearest_empty = heights[empty > 0].abs().min().item()  # 0.35
    assert nearest_empty - 0.02 < r.item() <= nearest_empty + 1e-9


def test_the_step_with_the_term(small, sphere_scene, tmp_path, step_term):
    """On: the rays whose mask is 0 are marked, the loss holds weight x pool share x term
    and the metric reports it; off: nothing is marked and the metric is 0."""
    scene = sphere_scene(tmp_path / "s")
    base = small + ["train.compile=false", "model.sdf.gradient=analytic",
                    "train.photo.weight=0", "model.sdf.bias=0.9"]
    on = load_config("demo", base + ["train.carve_weight=2.0"])
    torch.manual_seed(0)
    model = make_model(on)  # a sphere of radius 0.9 at the start: larger than the object
    inputs, loss, carve = step_term(model, scene, on, "carve_loss")
    assert inputs.empty is not None and torch.equal(inputs.empty > 0, inputs.mask[:, 0] == 0)
    assert carve > 0
    inputs_off, loss_off, carve_off = step_term(model, scene, load_config("demo", base),
                                                "carve_loss")
    assert inputs_off.empty is None and carve_off == 0.0
    assert loss - loss_off == pytest.approx(2.0 * inputs.mask_scale * carve, rel=1e-3, abs=1e-6)


def test_only_a_mask_of_exactly_0_marks_a_ray(small, sphere_scene, tmp_path):
    """A soft mask (a downscaled one) of 0.3 is background to the mask term (> 0.5 is
    foreground) but not empty: part of the pixel sees the object, so its ray is not carved."""
    scene = sphere_scene(tmp_path / "s")
    scene.masks = torch.where(scene.masks > 0, scene.masks, torch.full_like(scene.masks, 0.3))
    cfg = load_config("demo", small + ["train.compile=false", "train.photo.weight=0",
                                       "train.carve_weight=1"])
    inputs = draw_step_inputs(scene, cfg, 3, 256, torch.Generator().manual_seed(0), None)
    assert (inputs.mask[:, 0] == 0).any()  # the mask term reads them as background
    assert inputs.empty is not None and inputs.empty.sum().item() == 0


def test_range():
    assert load_config("demo").train.carve_weight >= 0.0
    with pytest.raises(ConfigError, match="carve_weight"):
        load_config("demo", ["train.carve_weight=-1"])
    with pytest.raises(ConfigError, match="carve_weight.*mask_weight"):
        load_config("demo", ["train.carve_weight=1", "train.mask_weight=0"])
