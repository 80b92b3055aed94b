"""`neus_l0.mesh.plane_sweep` and `photo_carve`: the plane sweep finds a textured plane's
true depth behind a raised mesh (to two steps); the depth map, the hull depth and the rays
against closed forms; the votes against a plain loop; the carved field is the difference of
the two; a pit whose floor sits raised is carved down to the true floor and no further."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.cli import main
from neus_l0.data.cameras import depth_projection, pixel_indices
from neus_l0.errors import NeusL0Error
from neus_l0.mesh import photo_carve as pc
from neus_l0.mesh import plane_sweep as ps
from neus_l0.mesh.missed_parts import GridSolid


def test_pixel_rays_project_back_onto_their_pixels_at_their_depth(plane_views):
    P, _ = plane_views
    g = np.random.default_rng(0)
    pix = g.uniform(0, 60, size=(50, 2))
    c, rays = ps.pixel_rays(P[2], pix)
    z = g.uniform(10, 90, size=50)
    X = c + rays * z[:, None]
    uvw = X @ depth_projection(P[2])[:, :3].T + depth_projection(P[2])[:, 3]
    assert np.allclose(uvw[:, :2] / uvw[:, 2:], pix, atol=1e-9)
    assert np.allclose(uvw[:, 2], z, atol=1e-9)


def test_the_depth_map_of_a_sampled_plane_is_its_exact_depth(plane_views):
    P, gray = plane_views
    plane = trimesh.creation.box(extents=(60, 60, 2)).apply_translation((0, 0, -1))
    samples, face = trimesh.sample.sample_surface(plane, 400_000, seed=0)
    depth, nrm = ps.depth_map(samples, np.asarray(plane.face_normals)[face], P[0],
                              gray.shape[1:], 0.75)
    ys, xs = np.mgrid[4:44:5, 4:60:5]
    c, rays = ps.pixel_rays(P[0], np.stack([xs.ravel(), ys.ravel()], -1).astype(float))
    truth = -c[2] / rays[:, 2]  # camera z where each pixel's ray meets z = 0
    assert np.abs(depth[ys.ravel(), xs.ravel()] - truth).max() < 0.05
    assert np.allclose(nrm[ys.ravel(), xs.ravel()], [0.0, 0.0, 1.0])


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-0.99, 0.99)] * 3), min_size=1, max_size=20))
def test_hull_depth_of_a_cube_is_the_distance_to_its_nearest_face(points):
    cube = trimesh.creation.box(extents=(2, 2, 2)).vertices
    p = np.asarray(points)
    assert np.allclose(ps.hull_depth(p, cube), 1 - np.abs(p).max(axis=1), atol=1e-9)
    assert (ps.hull_depth(p + np.where(p >= 0, 1.01, -1.01), cube) <= 0).all()  # outside


def test_the_sweep_finds_the_planes_depth_behind_a_raised_start(plane_views):
    """Started from the plane z = 3 (a raised floor), the best depth is the true one to
    within a step, with a low cost, and the start's cost is higher."""
    P, gray = plane_views
    g = np.random.default_rng(0)
    pix = np.stack([g.integers(20, 44, 30), g.integers(14, 34, 30)], -1)
    c, rays = ps.pixel_rays(P[0], pix.astype(float))
    truth = -c[2] / rays[:, 2]
    raised = (3.0 - c[2]) / rays[:, 2]
    up = np.tile([0.0, 0.0, 1.0], (30, 1))
    z, cost, cost0 = ps.sweep_depths(torch.as_tensor(gray), P, 0, pix, up, raised,
                                     np.arange(-1, 6.01, 0.125), chunk=7)
    assert np.abs(z - truth).max() <= 0.25  # two steps (bilinear reads of a curved texture)
    assert (cost < 0.02).all() and (cost0 > cost + 0.05).mean() > 0.9


def test_free_votes_count_the_views_whose_interval_holds_a_point(plane_views):
    """Intervals [55, 65] of camera depth over every pixel of views 0 and 1 (a stride-2 grid
    filled in by `interval_maps`): a point is voted for by exactly the views whose camera
    depth of it lies inside, against a plain loop."""
    P, gray = plane_views
    H, W = gray.shape[1:]
    ys, xs = np.mgrid[0:H:2, 0:W:2]
    pix = np.stack([xs.ravel(), ys.ravel()], -1)
    m = pc.interval_maps(pix, np.full(len(pix), 55.0), np.full(len(pix), 65.0), (H, W),
                         stride=2)
    assert not np.isnan(m[0]).any() and (m[1] == 65.0).all()
    maps = [m, m, None, None, None]
    g = np.random.default_rng(0)
    pts = np.column_stack([g.uniform(-10, 10, 200), g.uniform(-10, 10, 200),
                           g.uniform(-10, 10, 200)])
    got = pc.free_votes(pts, P, maps)
    for i, p in enumerate(pts):
        want = 0
        for v in (0, 1):
            col, row, z = pixel_indices(P[v], p[None], H, W)
            want += int(col[0] >= 0 and 55.0 <= z[0] <= 65.0)
        assert got[i] == want
    assert 0 < (got == 2).sum() < len(pts)


def test_the_carved_field_is_the_difference_of_the_two():
    class Ball:
        def sdf(self, p):
            return (p.norm(dim=-1) - 0.5).reshape(-1, 1)

    class M:
        sdf = Ball()

    index = np.argwhere(np.ones((3, 3, 3), bool)) + 9  # a small cube at the grid's middle
    solid = GridSolid.from_indices(index, 21)
    p = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.3, 0.0], [0.9, 0.0, 0.0]])
    got = pc.carved_model(M(), solid).sdf.sdf(p).reshape(-1)
    want = torch.maximum(Ball().sdf(p).reshape(-1), -solid.sdf(p))
    assert torch.allclose(got, want)
    assert got[0] > 0 > Ball().sdf(p)[0]  # the centre, inside the ball, is carved out
    assert got[1] < 0  # inside the ball, away from the cube: kept


def test_a_raised_pit_floor_is_carved_to_the_true_floor_and_no_further(plane_views):
    """The world is the textured plane z = 0 (every pixel sees it). The mesh: a block from
    z = -10 to 20 with a square pit whose floor sits raised at z = 3. The sweep from the pit
    floor finds z = 0; the carved points lie above the plane (none inside the true solid)
    and fill the pit's column between z = 0.5 and 2.5."""
    P, gray = plane_views
    walls = [trimesh.creation.box(bounds=b) for b in (
        [(-30, -30, -10), (30, 30, 3)], [(-30, -30, 3), (-6, 30, 20)],
        [(6, -30, 3), (30, 30, 20)], [(-6, -30, 3), (6, -6, 20)], [(-6, 6, 3), (6, 30, 20)])]
    block = trimesh.util.concatenate(walls)  # overlapping boxes: their inner faces are hidden
    masks = [np.ones(gray.shape[1:], bool) for _ in range(len(P))]
    scale = np.diag([40.0, 40.0, 40.0, 1.0])
    solid, report = pc.carve_solid(block, P, masks, gray, scale, 128)
    assert solid is not None and report["carving"] > 0, report
    inside = np.argwhere(solid.values.numpy() < 0)
    world = (solid.origin + inside * solid.step) * 40.0
    assert world[:, 2].min() > -1.0
    col = np.mgrid[-4:5:2, -4:5:2, 1:3:1].reshape(3, -1).T.astype(float)
    assert (solid.sdf(torch.as_tensor(col / 40.0)).numpy() < 0).mean() > 0.5


def test_the_command_reports_what_it_carved_and_names_a_missing_image(run_copy, capsys):
    """`neus-l0 mesh --photo-carve` on a trained run: a report line and a mesh; with a training
    view's image gone, one line that names the image folder."""
    out = run_copy.parent / "carved.ply"
    assert main(["mesh", str(run_copy), "--resolution", "40", "--photo-carve",
                 "--out", str(out), "--quiet", "--threads", "1"]) == 0
    said = capsys.readouterr().out
    assert "photo carve: " in said and " pixels swept in concavities" in said
    assert len(trimesh.load(out).faces) > 0
    scene = Path(json.loads((run_copy / "run.json").read_text())["scene"])
    copy = run_copy.parent / "scene"
    shutil.copytree(scene, copy)
    record = json.loads((run_copy / "run.json").read_text())
    record["scene"] = str(copy)
    (run_copy / "run.json").write_text(json.dumps(record))
    sorted((copy / "image").iterdir())[0].unlink()
    assert main(["mesh", str(run_copy), "--resolution", "40", "--photo-carve",
                 "--out", str(out), "--quiet", "--threads", "1"]) != 0
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"{copy / 'image'}: no image for training view" in err


def test_images_that_do_not_match_the_masks_are_refused(plane_views):
    """Images of another size than the masks (or one short) are named, never swept."""
    P, gray = plane_views
    box = trimesh.creation.box(extents=(20, 20, 20))
    masks = [np.ones(gray.shape[1:], bool) for _ in range(len(P))]
    with pytest.raises(NeusL0Error, match="--photo-carve: 5 images of .* must match"):
        pc.carve_solid(box, P, masks, gray[:, :-1], np.diag([40.0, 40, 40, 1]), 64)
    with pytest.raises(NeusL0Error, match="4 images"):
        pc.carve_solid(box, P, masks, gray[:4], np.diag([40.0, 40, 40, 1]), 64)
