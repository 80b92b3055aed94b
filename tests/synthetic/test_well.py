"""`well`: the second held-out object of the pits issue."""

import math

import pytest
import torch

from neus_l0.synthetic.shapes import WELL_RODS, WELL_SHAFT, builtin_shape, project_to_surface


def _sdf(shape, *pts):
    return shape.sdf(torch.tensor(pts, dtype=torch.float64)).tolist()


def test_the_shaft_is_deeper_than_wide_and_the_rods_stand_below_the_rim():
    well = builtin_shape("well")
    w, depth = WELL_SHAFT
    top = 45.0
    floor = top - depth
    feats = {f["name"]: f for f in well.features}
    cx, cy = feats["shaft floor"]["center"][:2]
    assert depth > 2 * w
    on_floor, above_floor, wall = _sdf(well, (cx, cy, floor), (cx, cy, floor + 1.0),
                                       (cx - w, cy, floor + depth / 2))
    assert abs(on_floor) < 1e-9 and abs(above_floor - 1.0) < 1e-9 and abs(wall) < 1e-9
    for (dx, dy), rr, h in WELL_RODS:
        assert max(abs(dx), abs(dy)) + rr < w and math.hypot(dx, dy) - rr > \
            feats["shaft floor"]["radius"] and floor + h < top
        side, cap = _sdf(well, (cx + dx + rr, cy + dy, floor + h / 2), (cx + dx, cy + dy,
                                                                         floor + h))
        assert abs(side) < 1e-9 and abs(cap) < 1e-9
    assert feats["bar r3"]["kind"] == "thin" and feats["pit r4 d20"]["kind"] == "pit"
    lo, hi = well.bounds
    corners = torch.tensor([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])], dtype=torch.float64)
    assert (well.sdf(corners) > 0).all()  # the box holds the shape


@pytest.mark.parametrize("name", ["demo", "pits-and-thin", "pits-deep", "cup", "well"])
def test_every_features_ball_holds_surface(name):
    """The scorer crops ground truth to each feature's ball (``<=`` its radius): surface
    points projected from the ball's neighbourhood must land inside it, in number (a pit as
    wide as half its depth once had a ball that only touched its wall and floor: no ground
    truth to score)."""
    shape = builtin_shape(name)
    g = torch.Generator().manual_seed(0)
    for f in shape.features:
        u = torch.randn(800, 3, generator=g, dtype=torch.float64)
        u = u / u.norm(dim=-1, keepdim=True) * torch.rand(800, 1, generator=g,
                                                            dtype=torch.float64) ** (1 / 3)
        centre = torch.tensor(f["center"], dtype=torch.float64)
        near = centre + 1.2 * f["radius"] * u
        on = project_to_surface(shape.sdf, near, iters=20)
        on = on[shape.sdf(on).abs() < 1e-6]
        inside = ((on - centre).norm(dim=-1) <= f["radius"]).sum().item()
        assert inside >= 30, (f["name"], inside)
