"""`neus-l0 mesh --close-underside`: the plane below everything the views see, and the SDF cut
flat there (`neus_l0.mesh.underside`)."""

import json
import shutil

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from neus_l0.cli import main
from neus_l0.data.cameras import look_at, projection_matrix, to_world
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.extract import extract_mesh
from neus_l0.mesh.from_run import plane_to_normalised
from neus_l0.mesh.underside import (
    camera_up,
    cut_below,
    lowest_firm,
    seen_counts,
    underside_line,
    underside_plane,
)

W = H = 96
K = np.array([[110.0, 0.0, (W - 1) / 2], [0.0, 110.0, (H - 1) / 2], [0.0, 0.0, 1.0]])


def rig(elevations, n_azimuths=8, distance=6.0, target=(0.0, 0.0, 0.0), rotate=None,
        azimuths=None):
    """(V, 3, 4) projections of upright cameras on rings at `elevations` (degrees) around
    `target`, all looking at it; `rotate` (3, 3) turns the whole rig (its up is then
    rotate @ z); `azimuths` (radians) replaces the even ring."""
    R = np.eye(3) if rotate is None else rotate
    target = np.asarray(target, dtype=np.float64)
    out = []
    for e in np.radians(elevations):
        ring = (np.linspace(0, 2 * np.pi, n_azimuths, endpoint=False) + 0.3 * e
                if azimuths is None else np.asarray(azimuths))
        for a in ring:
            eye = target + R @ (distance * np.array([np.cos(e) * np.cos(a),
                                                     np.cos(e) * np.sin(a), np.sin(e)]))
            out.append(projection_matrix(K, look_at(eye, target, up=R @ [0, 0, 1.0]))[:3])
    return np.stack(out)


def all_foreground(n):
    return [np.ones((H, W), dtype=bool)] * n


def box_with_sag(depth=0.35):
    """A 2 x 2 x 1 box (bottom at z = 0) with a shallow pyramid under it, apex at -depth
    (its faces slope 19 degrees for depth 0.35: hidden from views 20 degrees up or more),
    subdivided so that its faces have inner vertices."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (0, 1)], float)
    hull = trimesh.convex.convex_hull(np.vstack([corners, [[0, 0, -depth]]]))
    v, f = trimesh.remesh.subdivide_to_size(hull.vertices, hull.faces, max_edge=0.1)
    return trimesh.Trimesh(v, f)


@pytest.mark.parametrize("seed", range(5))
def test_up_is_exact_for_an_upright_rig_whatever_its_turn_and_azimuths(seed):
    """Upright cameras at uneven azimuths (one side of the object only, as DTU's): up is
    exact, where the mean direction to the cameras tilts far from it."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    target = rng.normal(size=3)
    az = rng.uniform(0, 2.0, size=7)  # radians: a third of the ring
    P = np.concatenate([rig([e], n_azimuths=1, rotate=R, target=target, azimuths=az)
                        for e in rng.uniform(20, 70, size=3)])
    up = camera_up(P, target)
    assert np.allclose(up, R @ [0, 0, 1.0], atol=1e-9)
    cams = np.stack([np.linalg.lstsq(p[:, :3], -p[:, 3], rcond=None)[0] for p in P])
    mean = (cams - target) / np.linalg.norm(cams - target, axis=1, keepdims=True)
    mean = mean.sum(0) / np.linalg.norm(mean.sum(0))
    assert np.degrees(np.arccos(mean @ R @ [0, 0, 1.0])) > 10  # the mean direction is off


def test_a_rolled_rig_falls_back_to_the_mean_direction():
    """Cameras rolled at random (not upright): up is the mean direction to the cameras."""
    rng = np.random.default_rng(0)
    P = []
    for k, e in enumerate(np.radians(np.repeat([30.0, 60.0], 6))):
        a = 2 * np.pi * k / 6
        eye = 6.0 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        w2c = look_at(eye, np.zeros(3))
        roll = Rotation.from_rotvec([0, 0, rng.uniform(-np.pi, np.pi)]).as_matrix()
        w2c[:3] = roll @ w2c[:3]
        P.append(projection_matrix(K, w2c)[:3])
    P = np.stack(P)
    cams = np.stack([np.linalg.lstsq(p[:, :3], -p[:, 3], rcond=None)[0] for p in P])
    mean = (cams / np.linalg.norm(cams, axis=1, keepdims=True)).mean(0)
    assert np.allclose(camera_up(P, np.zeros(3)), mean / np.linalg.norm(mean), atol=1e-9)


def test_cameras_all_around_have_no_up():
    with pytest.raises(NeusL0Error, match="surround"):
        camera_up(rig([-40, 0, 40]), np.zeros(3))


def test_the_top_is_seen_the_bottom_is_not_and_the_masks_count():
    mesh = box_with_sag()
    P = rig([20, 45, 70])
    counts = seen_counts(mesh, P, all_foreground(len(P)))
    z = mesh.vertices[:, 2]
    top = np.isclose(z, 1.0) & (np.abs(mesh.vertices[:, :2]).max(axis=1) < 0.95)
    assert (counts[top] >= 8).all()  # every ring sees the top
    assert (counts[z < -0.02] == 0).all()  # the pyramid faces away from every view
    side = (np.abs(mesh.vertices[:, 0]) > 0.999) & (z > 0.05) & (z < 0.95)
    assert (counts[side] > 0).all()  # the sides, down to near the bottom edge
    none = seen_counts(mesh, P, [np.zeros((H, W), dtype=bool)] * len(P))
    assert (none == 0).all()  # outside the masks nothing is seen


def test_the_plane_lies_just_under_the_box_and_nothing_without_a_sag():
    P = rig([20, 45, 70])
    mesh = box_with_sag()
    up, height = underside_plane(mesh, P, all_foreground(len(P)))
    assert np.allclose(up, [0, 0, 1], atol=1e-9)
    edge = mesh.edges_unique_length.mean()
    assert -edge - 1e-9 <= height < 0.0  # below the bottom edge, within the margin
    assert height > -0.35  # above the apex: the sag is cut
    v, f = trimesh.remesh.subdivide_to_size(*_box(), max_edge=0.1)
    assert underside_plane(trimesh.Trimesh(v, f), P, all_foreground(len(P))) is None


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=1, max_size=40), st.floats(0.1, 10),
       st.integers(1, 8))
def test_the_lowest_firm_height_matches_a_plain_count(heights, band, min_ring):
    h = np.array(heights)
    firm = [x for x in h if ((h >= x) & (h <= x + band)).sum() >= min_ring]
    assert lowest_firm(h, band, min_ring) == (min(firm) if firm else h.min())


def _spike(mesh, n, z=-0.3):
    """`mesh` with a small flat patch of about `n` vertices facing +x, hanging beside it at
    height `z` (outside the sag, 0.3 off the box's side): what the views see of it."""
    side = max(int(np.ceil(np.sqrt(n))), 2)
    ys, zs = np.meshgrid(np.linspace(-0.02, 0.02, side), np.linspace(z, z + 0.02, side))
    v = np.column_stack([np.full(ys.size, 1.3), ys.ravel(), zs.ravel()])
    i = np.arange(side * side).reshape(side, side)
    f = np.concatenate([np.column_stack([i[:-1, :-1].ravel(), i[:-1, 1:].ravel(),
                                         i[1:, 1:].ravel()]),
                        np.column_stack([i[:-1, :-1].ravel(), i[1:, 1:].ravel(),
                                         i[1:, :-1].ravel()])])
    return trimesh.util.concatenate([mesh, trimesh.Trimesh(v, f)])


def test_a_few_stray_seen_vertices_do_not_lower_the_plane_a_ring_of_them_does():
    P = rig([20, 45, 70])
    box = box_with_sag()
    edge = box.edges_unique_length.mean()
    stray = _spike(box, 4)  # 2 x 2 vertices: fewer than MIN_RING
    counts = seen_counts(stray, P, all_foreground(len(P)))
    assert (counts[len(box.vertices):] > 0).all()  # the views do see them
    _, height = underside_plane(stray, P, all_foreground(len(P)))
    assert -edge - 1e-9 <= height < 0.0  # as without them: just under the box
    _, height = underside_plane(stray, P, all_foreground(len(P)), min_ring=1)
    assert height < -0.3  # the plain lowest-seen rule goes under the stray patch
    ring = _spike(box, 9)  # 3 x 3 within one edge: a firm ring
    _, height = underside_plane(ring, P, all_foreground(len(P)))
    assert height < -0.3


def _box():
    b = trimesh.creation.box((2.0, 2.0, 1.0))
    b.apply_translation([0, 0, 0.5])
    return b.vertices, b.faces


def test_no_seen_vertex_is_a_clear_error():
    P = rig([20, 45])
    with pytest.raises(NeusL0Error, match="no vertex.*masks"):
        underside_plane(box_with_sag(), P, [np.zeros((H, W), dtype=bool)] * len(P))


SCALE = np.array([[40.0, 0, 0, 3.0], [0, 40.0, 0, -2.0], [0, 0, 40.0, 7.0], [0, 0, 0, 1.0]])


@pytest.mark.parametrize("method", ["dense", "sparse"])
def test_the_cut_sphere_has_a_flat_cap_at_the_plane(method):
    """A sphere of radius 0.5 cut at z = -0.2: the lowest vertices lie on the plane, the top is
    the sphere's, the mesh is closed and its volume is the spherical segment's."""
    model = _sphere_model(0.5)
    up, h = np.array([0.0, 0.0, 1.0]), -0.2
    mesh = extract_mesh(cut_below(model, up, h), SCALE, resolution=96, method=method,
                        clean=False)
    v = (mesh.vertices - SCALE[:3, 3]) / 40.0  # back to the normalised frame
    step = 2.0 / 95
    assert abs(v[:, 2].min() - h) < 0.5 * step and abs(v[:, 2].max() - 0.5) < 0.5 * step
    flat = np.abs(v[:, 2] - h) < 1e-3
    assert flat.sum() > 50  # the cap's vertices are on the plane
    assert mesh.is_watertight
    r = 0.5
    c = r + h  # the height of the cap below the plane
    expected = (4 / 3 * np.pi * r**3 - np.pi * c**2 * (3 * r - c) / 3) * 40.0**3
    assert abs(mesh.volume - expected) / expected < 0.02


def _sphere_model(radius):
    class Sdf:
        def sdf(self, p):
            return (p.norm(dim=-1) - radius)[:, None]

    class Model:
        sdf = Sdf()

    return Model()


def test_plane_to_normalised_keeps_the_plane():
    rng = np.random.default_rng(0)
    up = rng.normal(size=3)
    up /= np.linalg.norm(up)
    h = 12.5
    up_n, h_n = plane_to_normalised((up, h), SCALE)
    pts_n = rng.normal(size=(50, 3))
    side_n = pts_n @ up_n - h_n
    side_w = to_world(pts_n, SCALE) @ up - h
    assert np.allclose(side_w, 40.0 * side_n)


def test_the_command_cuts_a_run_below_what_its_views_see(run_copy, capsys):
    """Both mask-aware steps on a trained run: the cut, and the report of both."""
    out = run_copy.parent / "closed.ply"
    assert main(["mesh", str(run_copy), "--resolution", "48", "--close-underside",
                 "--drop-outside-masks", "--out", str(out), "--quiet", "--threads", "1"]) == 0
    said = capsys.readouterr().out
    assert "outside the masks:" in said
    mesh = trimesh.load(out)  # open where the run's visual hull cuts the 4-step sphere
    assert "closed at height" in said, said  # the init sphere's underside is unseen
    height = float(said.split("closed at height ")[1].split()[0])
    up = np.array(json.loads(said.split("along up ")[1].split(" (world")[0]))
    assert (mesh.vertices @ up).min() > height - 1e-3 * np.ptp(mesh.vertices)


def test_a_run_whose_scene_lost_its_masks_is_refused(run_copy, scene96_copy, refused):
    record = run_copy / "run.json"
    run = json.loads(record.read_text())
    run["scene"] = str(scene96_copy)
    record.write_text(json.dumps(run))
    shutil.rmtree(scene96_copy / "mask")
    refused(["mesh", str(run_copy), "--resolution", "32", "--close-underside",
             "--out", str(run_copy.parent / "m.ply")], "mask")


def test_the_line_names_the_plane():
    assert underside_line(None) == "underside: nothing below the lowest seen point"
    line = underside_line({"up": [0.0, 0.0, 1.0], "height": -2.5})
    assert line == "underside closed at height -2.500 along up [0.0, 0.0, 1.0] (world units)"
