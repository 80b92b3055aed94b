"""`pits-deep`: pits-and-thin with a pit as deep as it is wide and rods standing in it."""

import json

import pytest
import torch

from neus_l0.synthetic.scene import ELEVATION_DEG, make_scene
from neus_l0.synthetic.shapes import (
    DEEP_FLOOR_RADIUS,
    DEEP_PIT,
    DEEP_PIT_RODS,
    builtin_shape,
    pits_and_thin_shape,
)


def _sdf(shape, *pts):
    return shape.sdf(torch.tensor(pts, dtype=torch.float64)).tolist()


def test_the_knob_adds_the_deep_pit_and_keeps_the_rest():
    plain, deep = pits_and_thin_shape(), builtin_shape("pits-deep")
    assert plain.name == "pits-and-thin" and deep.name == "pits-deep"
    assert deep.features[:len(plain.features)] == plain.features
    names = [f["name"] for f in deep.features[len(plain.features):]]
    assert names == ["deep pit r18 d36", "deep pit floor", "deep pit rod r1.5",
                     "deep pit rod r3", "deep pit rod r5"]
    (x, y), r, depth = DEEP_PIT
    assert 2 * r == depth  # as deep as it is wide
    top, floor = 25.0, 25.0 - depth
    # the floor and wall are surface, the pit is empty, the slab's face outside it is intact
    on_floor, on_wall, in_pit, face = _sdf(deep, (x, y, floor), (x + r, y, floor + 10),
                                           (x, y, top - 1), (x, y - r - 2, top))
    assert abs(on_floor) < 1e-9 and abs(on_wall) < 1e-9 and in_pit > 0.9 and abs(face) < 1e-9
    assert _sdf(plain, (x, y, floor))[0] < -5  # no pit without the knob


def test_the_rods_stand_on_the_floor_below_the_rim_clear_of_the_floor_ball():
    shape = builtin_shape("pits-deep")
    (x, y), r, depth = DEEP_PIT
    floor = 25.0 - depth
    for (dx, dy), rr, h in DEEP_PIT_RODS:
        axis = (dx * dx + dy * dy) ** 0.5
        assert axis + rr < r and axis - rr >= DEEP_FLOOR_RADIUS  # inside the pit, off the ball
        assert floor + h < 25.0  # below the rim
        side, top = _sdf(shape, (x + dx + rr, y + dy, floor + h / 2), (x + dx, y + dy, floor + h))
        assert abs(side) < 1e-9 and abs(top) < 1e-9


def test_the_scene_names_the_floor_and_rods_and_views_from_above(tmp_path):
    assert ELEVATION_DEG == (20.0, 70.0)
    out = make_scene("pits-deep", tmp_path / "s", views=2, width=32, height=24, spp=1,
                     gt_voxel=4.0, point_spacing=4.0, progress=False)
    feats = {f["name"]: f for f in json.loads((out / "features.json").read_text())["features"]}
    assert feats["deep pit floor"]["kind"] == "pit"
    assert feats["deep pit floor"]["radius"] == pytest.approx(DEEP_FLOOR_RADIUS)
    assert {feats[f"deep pit rod r{r:g}"]["kind"] for _, r, _ in DEEP_PIT_RODS} == {"thin"}
    meta = json.loads((out / "scene.json").read_text())
    assert meta["name"] == "pits-deep" and meta["cameras"]["elevation_deg"] == [20.0, 70.0]
