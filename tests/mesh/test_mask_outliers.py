"""`neus-l0 mesh --drop-outside-masks`: connected pieces that a view sees outside its mask are
dropped, the object's pieces (thin or hidden) kept (`neus_l0.mesh.mask_outliers`)."""

import json

import numpy as np
import pytest
import trimesh

from neus_l0.data.cameras import look_at, projection_matrix
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.mask_outliers import mask_outliers, outside_share

W = H = 64
K = np.array([[70.0, 0.0, (W - 1) / 2], [0.0, 70.0, (H - 1) / 2], [0.0, 0.0, 1.0]])


def cameras(elevations=(25, 55), n=6, distance=7.0):
    out = []
    for e in np.radians(elevations):
        for a in np.linspace(0, 2 * np.pi, n, endpoint=False) + e:
            eye = distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            out.append(projection_matrix(K, look_at(eye, np.zeros(3)))[:3])
    return np.stack(out)


def box(extents, centre):
    b = trimesh.creation.box(extents)
    b.apply_translation(centre)
    return b


OBJECT = box((2.0, 2.0, 1.0), (0, 0, 0.5))
ROD = box((0.06, 0.06, 1.2), (0.6, 0.6, 1.6))  # thin, apart from the box (a grid's cut)
HIDDEN = trimesh.creation.icosphere(radius=0.2).apply_translation((0, 0, 0.5))
FLOATER = trimesh.creation.icosphere(radius=0.15).apply_translation((1.6, 0.0, 0.8))


@pytest.fixture(scope="module")
def views(box_masks):
    P = cameras()
    return P, box_masks(P, [OBJECT, ROD], H, W)


def test_the_share_outside_is_counted_per_view(views):
    P, masks = views
    pts = np.array([[0.0, 0.0, 1.0], [0.5, -0.5, 0.5], [1.6, 0.0, 0.8], [3.0, 3.0, 0.0]])
    full = outside_share(pts, P, [np.ones((H, W), bool)] * len(P))
    empty = outside_share(pts, P, [np.zeros((H, W), bool)] * len(P))
    assert np.allclose(full, 0.0) and np.allclose(empty, 1.0)
    share = outside_share(pts[:2], P, masks)  # two points on the object
    assert np.allclose(share, 0.0)


def test_a_floater_goes_the_object_its_thin_part_and_a_hidden_piece_stay(views):
    P, masks = views
    mesh = trimesh.util.concatenate([OBJECT, ROD, HIDDEN, FLOATER])
    kept, dropped = mask_outliers(mesh, P, masks)
    assert len(dropped) == 1 and dropped[0]["faces"] == len(FLOATER.faces)
    assert dropped[0]["views"] >= 6
    assert abs(dropped[0]["diagonal"] - np.linalg.norm(np.ptp(FLOATER.vertices, 0))) < 1e-9
    assert len(kept.faces) == len(OBJECT.faces) + len(ROD.faces) + len(HIDDEN.faces)
    assert np.isclose(kept.area, OBJECT.area + ROD.area + HIDDEN.area)


def test_a_floater_within_the_masks_margin_stays(views):
    """A piece one pixel off the silhouette is within the 2-pixel margin (mask error)."""
    P, masks = views
    near = trimesh.creation.icosphere(radius=0.05).apply_translation((1.03, 0.0, 0.5))
    kept, dropped = mask_outliers(trimesh.util.concatenate([OBJECT, near]), P, masks)
    assert dropped == [] and len(kept.faces) == len(OBJECT.faces) + len(near.faces)
    _, strict = mask_outliers(trimesh.util.concatenate([OBJECT, near]), P, masks,
                              dilate_px=0)
    assert len(strict) == 1


def test_one_piece_is_never_split_and_all_outside_is_an_error(views):
    P, masks = views
    same, none = mask_outliers(OBJECT, P, masks)
    assert same is OBJECT and none == []
    with pytest.raises(NeusL0Error, match="every piece.*masks"):
        mask_outliers(trimesh.util.concatenate([OBJECT, FLOATER]), P,
                      [np.zeros((H, W), bool)] * len(P))


@pytest.mark.parametrize("damage", [
    lambda run: run.pop("scene"),
    lambda run: run.update(views="all"),  # not a dict
    lambda run: run.update(views={"train": [0, 999]}),  # no such camera
    lambda run: run.update(views={"train": "0,1"}),
])
def test_a_damaged_run_record_is_named(run_copy, refused, damage):
    record = run_copy / "run.json"
    run = json.loads(record.read_text())
    damage(run)
    record.write_text(json.dumps(run))
    refused(["mesh", str(run_copy), "--resolution", "32", "--drop-outside-masks",
             "--out", str(run_copy.parent / "m.ply")], "run.json")
