"""`cup`: the held-out object of the pits issue, and the torus its handle is made of."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.synthetic.shapes import CUP_CAVITY, CUP_RODS, Torus, builtin_shape


def _sdf(shape, *pts):
    return shape.sdf(torch.tensor(pts, dtype=torch.float64)).tolist()


@settings(max_examples=60, deadline=None)
@given(st.floats(-40, 40), st.floats(-40, 40), st.floats(-40, 40), st.integers(0, 2))
def test_the_torus_is_the_distance_to_its_ring_less_the_tube(x, y, z, axis):
    """Against a brute-force distance to 20000 points of the ring (within their spacing)."""
    t = Torus((1.0, -2.0, 3.0), axis, 12.0, 2.5)
    phi = torch.linspace(0, 2 * math.pi, 20001, dtype=torch.float64)[:-1]
    across = [i for i in range(3) if i != axis]
    ring = torch.zeros(20000, 3, dtype=torch.float64)
    ring[:, across[0]], ring[:, across[1]] = 12.0 * phi.cos(), 12.0 * phi.sin()
    ring += torch.tensor(t.center, dtype=torch.float64)
    p = torch.tensor([[x, y, z]], dtype=torch.float64)
    want = (ring - p).norm(dim=-1).min().item() - 2.5
    assert t(p).item() == pytest.approx(want, abs=12.0 * 2 * math.pi / 20000)


def test_the_cavity_is_as_deep_as_wide_and_the_rods_stand_below_the_rim():
    cup = builtin_shape("cup")
    r, depth = CUP_CAVITY
    top = 45.0
    floor = top - depth
    assert 2 * r == depth
    on_floor, in_cavity, rim_face = _sdf(cup, (0.0, -20.0, floor), (0.0, -20.0, top - 1),
                                         (0.0, -r - 10.0, top))
    assert abs(on_floor) < 1e-9 and in_cavity > 0.9 and abs(rim_face) < 1e-9
    floor_ball = next(f for f in cup.features if f["name"] == "cavity floor")
    for (dx, dy), rr, h in CUP_RODS:
        axis = math.hypot(dx, dy)
        assert axis + rr < r and axis - rr > floor_ball["radius"] and floor + h < top
        side, cap = _sdf(cup, (dx + rr, dy, floor + h / 2), (dx, dy, floor + h))
        assert abs(side) < 1e-9 and abs(cap) < 1e-9
    kinds = {f["name"]: f["kind"] for f in cup.features}
    assert kinds["handle r5"] == "thin" and kinds["dimple 1"] == "pit"

