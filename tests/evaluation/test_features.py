"""`near_axis`: the tube crop around a thin feature's axis segment."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.evaluation.features import feature_label, near_axis


def _segment_distance(p, a, b) -> float:
    """Plain float64 distance from point p to the segment [a, b] (a reference)."""
    ab, ap = b - a, p - a
    t = min(1.0, max(0.0, float(np.dot(ap, ab) / np.dot(ab, ab))))
    return float(np.linalg.norm(ap - t * ab))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.5, 30.0), st.floats(0.1, 10.0))
def test_near_axis_against_a_plain_segment_distance(seed, half, tube):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    f = {"kind": "thin", "name": "rod", "center": rng.normal(size=3) * 10,
         "radius": half, "axis": axis * rng.uniform(0.5, 3.0)}  # not unit: normalised
    pts = f["center"] + rng.normal(size=(300, 3)) * (half + tube)
    u = axis / np.linalg.norm(axis)
    a, b = f["center"] - half * u, f["center"] + half * u
    ref = np.array([_segment_distance(p, a, b) for p in pts])
    got = near_axis(pts, f, tube)
    clear = np.abs(ref - tube) > 1e-9
    assert (got[clear] == (ref[clear] <= tube)).all()


def test_near_axis_closed_form_and_no_axis():
    f = {"kind": "thin", "name": "rod", "center": np.zeros(3), "radius": 10.0,
         "axis": np.array([0.0, 0.0, 1.0])}
    pts = np.array([[2.9, 0, 9.9], [3.1, 0, 0], [0, 0, 12.9], [0, 0, 13.1], [2.0, 2.0, -10.5],
                    [np.nan, 0, 0]])
    assert near_axis(pts, f, 3.0).tolist() == [True, False, True, False, True, False]
    with pytest.raises(ValueError, match="no axis"):
        near_axis(pts, {**f, "axis": None}, 3.0)


@pytest.mark.parametrize("axis", [[0.0, 0.0, 0.0], [float("nan"), 0.0, 1.0], [1.0, 0.0]])
def test_a_bad_axis_is_named_with_its_file(tmp_path, axis):
    """`load_features` refuses an axis of zero length, a NaN or the wrong size, naming the
    file and the feature; `near_axis` refuses a zero axis rather than crop nothing."""
    import json

    from neus_l0.errors import NeusL0Error
    from neus_l0.evaluation.features import load_features

    (tmp_path / "features.json").write_text(json.dumps({"features": [
        {"kind": "thin", "name": "rod r1", "center": [0, 0, 0], "radius": 5.0,
         "axis": axis}]}))
    with pytest.raises(NeusL0Error, match=r"features\.json.*rod r1.*axis"):
        load_features(tmp_path)
    with pytest.raises(ValueError, match="axis of length"):
        near_axis(np.zeros((2, 3)), {"name": "rod", "center": np.zeros(3), "radius": 1.0,
                                     "axis": np.zeros(3)}, 1.0)


def test_feature_label_puts_points_on_the_nearest_small_feature():
    """`feature_label`: a point within `tol` of a thin feature's axis segment
    (not past its ends) takes its label, a ball feature labels its ball, the smaller of two
    overlapping features wins, NaN points are `nothing` and the rest `open surface`."""
    feats = [{"kind": "pit", "name": "pit", "center": np.zeros(3), "radius": 20.0,
              "axis": np.array([0.0, 0.0, 1.0])},
             {"kind": "thin", "name": "rod", "center": np.array([5.0, 0.0, 0.0]),
              "radius": 10.0, "axis": np.array([0.0, 0.0, 1.0])}]
    pts = np.array([[np.nan] * 3, [100.0, 0, 0], [-15.0, 0, 0], [5.0, 2.9, 9.0],
                    [5.0, 3.1, 9.0], [5.0, 0.0, 12.9], [5.0, 0.0, 13.1], [40.0, 0.0, 0.0]])
    labels, names = feature_label(pts, feats, tol=3.0)
    assert names == ("nothing", "open surface", "pit", "rod")
    assert labels.tolist() == [0, 1, 2, 3, 2, 3, 2, 1]
    rng = np.random.default_rng(0)
    many = rng.uniform(-30, 30, (2000, 3))
    lab, _ = feature_label(many, feats, tol=3.0)
    d = many - feats[1]["center"]
    along = np.clip(d[:, 2], -10, 10)
    on_rod = np.hypot(d[:, 0], d[:, 1]) ** 2 + (d[:, 2] - along) ** 2 <= 9.0
    in_pit = np.linalg.norm(many, axis=1) <= 20.0
    assert ((lab == 3) == on_rod).all()
    assert ((lab == 2) == (in_pit & ~on_rod)).all()
