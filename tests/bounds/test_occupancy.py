"""Occupancy grid: never culls space that holds surface; ray spans cover occupied cells."""

import math

import pytest
import torch

from neus_l0.bounds.grid import cell_centres, dilate
from neus_l0.bounds.occupancy import (
    OccupancyGrid,
    grid_spans,
    occupancy_threshold,
    occupied_cells,
)
from neus_l0.config.load import load_config
from neus_l0.config.schema import OccupancyConfig
from neus_l0.errors import ConfigError

# ------------------------------------------------------------------------------------------
# Analytic SDFs (exact signed distances) with random placement and size.


def sphere_sdf(centre, radius):
    return lambda x: (x - centre).norm(dim=-1, keepdim=True) - radius


def box_sdf(centre, half):
    def f(x):
        q = (x - centre).abs() - half
        return (q.clamp_min(0).norm(dim=-1) + q.max(dim=-1).values.clamp_max(0))[:, None]
    return f


def torus_sdf(centre, major, minor):
    def f(x):
        p = x - centre
        q = torch.stack([p[:, :2].norm(dim=-1) - major, p[:, 2]], dim=-1)
        return q.norm(dim=-1, keepdim=True) - minor
    return f


def random_shape(kind, g):
    centre = (torch.rand(3, generator=g) - 0.5) * 0.4
    if kind == "sphere":
        return sphere_sdf(centre, 0.1 + 0.5 * torch.rand((), generator=g).item())
    if kind == "box":
        return box_sdf(centre, 0.05 + 0.4 * torch.rand(3, generator=g))
    major = 0.2 + 0.3 * torch.rand((), generator=g).item()
    return torus_sdf(centre, major, 0.02 + 0.1 * torch.rand((), generator=g).item())


def cells_with_surface(sdf_fn, R, sub=4):
    """(R, R, R) bool: cells where the SDF changes sign among sub^3 points of the cell
    (its corners included), so the true surface surely passes through them."""
    c = 2.0 / R
    lin = torch.linspace(0.0, 1.0, sub)
    off = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3) * c
    lo = cell_centres(R).reshape(-1, 3) - 0.5 * c  # (R^3, 3)
    pts = lo[:, None, :] + off[None]  # (R^3, sub^3, 3)
    s = sdf_fn(pts.reshape(-1, 3)).reshape(R**3, -1)
    return ((s.min(dim=-1).values <= 0) & (s.max(dim=-1).values >= 0)).reshape(R, R, R)


@pytest.mark.parametrize("kind", ["sphere", "box", "torus"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_never_culls_cells_the_surface_passes_through(kind, seed):
    g = torch.Generator().manual_seed(seed)
    sdf = random_shape(kind, g)
    R = 32
    truth = cells_with_surface(sdf, R)
    assert truth.any()
    for s in (20.0, 400.0, 1e5):  # soft to very sharp: the band shrinks to the geometric bound
        for block in (1, 4):
            occ = occupied_cells(sdf, R, torch.tensor([s]), margin=1.0, widths=6.0,
                                 block=block)
            assert not (truth & ~occ).any(), (kind, seed, s, block)
    # It does cull: at s = 1e5 the band is about one cell wide around the surface.
    assert occ.float().mean() < 0.5


def test_hierarchical_update_equals_testing_every_cell_for_true_sdfs():
    g = torch.Generator().manual_seed(3)
    for kind in ("sphere", "box", "torus"):
        sdf = random_shape(kind, g)
        s = torch.tensor([300.0])
        flat = occupied_cells(sdf, 32, s, 1.5, 6.0, block=1)
        hier = occupied_cells(sdf, 32, s, 1.5, 6.0, block=4)
        assert torch.equal(flat, hier), kind


def test_threshold_closed_form():
    thr = occupancy_threshold(0.1, torch.tensor([50.0]), 1.5, 6.0)
    assert thr.item() == pytest.approx(1.5 * math.sqrt(3) * 0.05 + 6.0 / 50.0)


def test_grid_follows_a_moving_sharpening_surface():
    """Updates with a growing sphere and a rising s: the current surface is always kept."""
    cfg = OccupancyConfig(enabled=True, resolution=32, hold=1, margin=1.0)
    grid = OccupancyGrid(cfg)
    assert grid.occ.all()  # everything until the first update
    for i, (r, s) in enumerate([(0.3, 20.0), (0.35, 60.0), (0.45, 200.0), (0.6, 1000.0),
                                (0.62, 5000.0), (0.62, 5000.0), (0.62, 5000.0)]):
        sdf = sphere_sdf(torch.zeros(3), r)
        grid.update(sdf, torch.tensor([s]))
        truth = cells_with_surface(sdf, 32)
        assert not (truth & ~grid.occ).any(), i
        assert torch.equal(grid.occ_dilated, dilate(grid.occ))
    # After `hold` + 1 unchanged updates only the current band remains.
    now = occupied_cells(sdf, 32, torch.tensor([5000.0]), 1.0, cfg.widths, cfg.block)
    assert torch.equal(grid.occ, now)
    assert grid.fraction_occupied() < 0.2


def test_dilate_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    occ = torch.rand(8, 8, 8, generator=g) < 0.05
    ref = torch.zeros_like(occ)
    for i, j, k in occ.nonzero().tolist():
        ref[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2, max(k - 1, 0):k + 2] = True
    assert torch.equal(dilate(occ), ref)


@pytest.mark.parametrize("seed", [0, 1])
def test_ray_spans_contain_every_occupied_cell_the_ray_crosses(seed):
    g = torch.Generator().manual_seed(seed)
    R = 16
    occ = torch.rand(R, R, R, generator=g) < 0.003
    B = 1000
    o = torch.randn(B, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    d = 0.6 * torch.randn(B, 3, generator=g) - o
    d = d / d.norm(dim=-1, keepdim=True)
    mid = -(o * d).sum(-1, keepdim=True)
    near, far = mid - 1.0, mid + 1.0
    lo, hi, active = grid_spans(dilate(occ), o, d, near, far)
    assert (lo >= near).all() and (hi <= far).all() and (lo <= hi).all()
    # Brute force: 3000 points along each ray, in undilated occupied cells.
    t = near + (far - near) * torch.linspace(0, 1, 3000)  # (B, 3000)
    p = o[:, None] + d[:, None] * t[..., None]
    ijk = torch.floor((p + 1.0) * R / 2).long()
    ok = ((ijk >= 0) & (ijk < R)).all(-1)
    ijk = ijk.clamp(0, R - 1)
    inside = occ[ijk[..., 0], ijk[..., 1], ijk[..., 2]] & ok
    crosses = inside.any(-1)
    assert crosses.any() and (~crosses).any()
    assert not (crosses & ~active).any()
    assert ((t >= lo - 1e-5) | ~inside).all() and ((t <= hi + 1e-5) | ~inside).all()
    # Rays that cross nothing (not even a neighbour of an occupied cell) are inactive.
    far_from_all = ~(ok & dilate(occ)[ijk[..., 0], ijk[..., 1], ijk[..., 2]]).any(-1)
    assert not (active & far_from_all).any()


def test_grid_state_dict_round_trip():
    cfg = OccupancyConfig(enabled=True, resolution=16)
    a = OccupancyGrid(cfg)
    a.update(sphere_sdf(torch.zeros(3), 0.5), torch.tensor([100.0]))
    b = OccupancyGrid(cfg)
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.occ, b.occ) and torch.equal(a.counter, b.counter)


def test_occupancy_config_is_off_in_the_neus_configs_and_checked():
    for name in ("wmask", "womask"):
        cfg = load_config(name)
        assert not cfg.render.occupancy.enabled and not cfg.render.cull_outside_sphere
        assert cfg.train.amp == "off" and cfg.train.eikonal_fraction == 1.0
    with pytest.raises(ConfigError, match="resolution"):
        load_config(None, ["render.occupancy.resolution=30", "render.occupancy.block=4"])
    with pytest.raises(ConfigError, match="margin"):
        load_config(None, ["render.occupancy.margin=0.5"])
    with pytest.raises(ConfigError, match="amp"):
        load_config(None, ["train.amp=fp8"])
