"""`train.hit_color_floor`: with masks, the colour term on the colour of the surface a ray
hits (`neus_l0.train.losses.hit_color`) instead of NeuS's composite over black, which pulls
every silhouette outward."""

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.load import load_config
from neus_l0.config.schema import TrainConfig
from neus_l0.errors import ConfigError
from neus_l0.render.volume import RenderOutput
from neus_l0.train.losses import hit_color, neus_loss


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 16), st.floats(0.01, 1.0))
def test_it_matches_a_plain_loop(seed, b, floor):
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(b, 5, generator=g, dtype=torch.float64) / 5
    c = torch.rand(b, 5, 3, generator=g, dtype=torch.float64)
    color, ws = (w[..., None] * c).sum(1), w.sum(1, keepdim=True)
    got = hit_color(color, ws, floor)
    for i in range(b):
        den = max(float(ws[i, 0]), floor)
        for k in range(3):
            assert float(got[i, k]) == pytest.approx(float(color[i, k]) / den, rel=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.05, 0.9))
def test_above_the_floor_the_colour_term_does_not_pull_the_opacity(seed, floor):
    """Scaling all of a ray's weights by k leaves the term unchanged while the opacity stays
    above the floor (zero gradient in k); below it the term falls as the opacity grows."""
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(8, 6, generator=g, dtype=torch.float64) + 0.1
    opacity = floor + 0.05 + (0.95 - floor) * torch.rand(8, 1, generator=g, dtype=torch.float64)
    w = w / w.sum(1, keepdim=True) * opacity
    c = torch.rand(8, 6, 3, generator=g, dtype=torch.float64)
    target = torch.rand(8, 3, generator=g, dtype=torch.float64)
    k = torch.ones((), dtype=torch.float64, requires_grad=True)
    wk = w * k
    term = (hit_color((wk[..., None] * c).sum(1), wk.sum(1, keepdim=True), floor)
            - target).abs().sum()
    (dk,) = torch.autograd.grad(term, k)
    assert abs(float(dk)) < 1e-9
    low = w * (0.9 * floor / w.sum(1, keepdim=True))  # every ray below the floor
    k2 = torch.ones((), dtype=torch.float64, requires_grad=True)
    lk = low * k2
    dark = torch.zeros(8, 6, 3, dtype=torch.float64) + 0.3
    term2 = (hit_color((lk[..., None] * dark).sum(1), lk.sum(1, keepdim=True), floor)
             - 0.3).abs().sum()
    (dk2,) = torch.autograd.grad(term2, k2)
    assert float(dk2) < 0  # rendered too dark below the floor: more opacity lowers the term


def _sphere_loss(delta_s, s, floor, pixel=1.0, radius=30.0, grey=0.5):
    """Colour + mask terms of NeuS (`neus_loss`) for a disc image of an exact sphere whose
    SDF is offset by ``delta_s / s`` (negative: the surface outside), the colour network
    exact (the grey of the surface): each pixel's opacity is NeuS's for a ray whose SDF
    minimum is f, ``sigmoid(-s f)``."""
    n = int(radius / pixel) + 12
    x = (torch.arange(-n, n, dtype=torch.float64) + 0.5) * pixel
    rho = torch.hypot(*torch.meshgrid(x, x, indexing="ij")).reshape(-1, 1)
    mask = (rho < radius).double()
    a = torch.sigmoid(-s * (rho - radius + delta_s / s))
    b = a.shape[0]
    out = RenderOutput(color=a * grey * torch.ones(1, 3, dtype=torch.float64), weight_sum=a,
                       depth=a, normal=a, weights=a, gradients=torch.zeros(b, 1, 3),
                       sdf=a, eikonal_mask=torch.zeros(b, 1), t=a, t_fine=a, t_mid=a,
                       inside_sphere=a, active=a[:, 0] > 0, inv_s=torch.tensor(s))
    cfg = dataclasses.replace(TrainConfig(), mask_weight=0.1, hit_color_floor=floor)
    target = grey * torch.ones(b, 3, dtype=torch.float64)
    return float(neus_loss(out, target, mask, cfg)["loss"])


@pytest.mark.parametrize("s", [3.0, 10.0])
def test_on_an_exact_sphere_the_composite_pulls_the_silhouette_out_and_hit_colour_does_not(s):
    """The offset (in units of 1/s) at which colour + mask are lowest: NeuS's composite over
    black puts the surface more than 2/s outside; the hit colour within 0.35/s of the truth."""
    grid = [i / 20 for i in range(-120, 41)]
    best = {f: min(grid, key=lambda d, f=f: _sphere_loss(d, s, f)) for f in (0.0, 0.5)}
    assert best[0.0] < -2.0, best
    assert abs(best[0.5]) < 0.35, best


def test_the_floor_is_checked(tmp_path):
    with pytest.raises(ConfigError, match="hit_color_floor"):
        load_config(None, ["train.hit_color_floor=1.5"])


def test_a_white_background_is_refused_with_the_hit_colour(tiny_scene, tmp_path, train_cli):
    from neus_l0.cli import main

    argv = train_cli(tiny_scene, tmp_path / "run", "train.hit_color_floor=0.5",
                     "render.white_background=true")
    assert main(argv) == 2
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_run_with_the_hit_colour_trains(tiny_scene, tmp_path, train_cli):
    import json

    from neus_l0.cli import main

    assert main(train_cli(tiny_scene, tmp_path / "run", "train.hit_color_floor=0.5",
                          "train.iters=40")) == 0
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all(m["loss"] == m["loss"] for m in lines if "loss" in m)  # finite, not NaN
