"""`neus-l0 mesh --fill-missed`: the visual hull's points on pixels a mask sees and the mesh
misses, added as a solid (`neus_l0.mesh.missed_parts`)."""

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.cli import main
from neus_l0.data.cameras import look_at, projection_matrix
from neus_l0.mesh.extract import extract_mesh
from neus_l0.mesh.missed_parts import (
    GridSolid,
    missed_pixels,
    missed_points,
    missed_solid,
    solid_model,
)
from neus_l0.mesh.raster import silhouette, surface_samples

W, H = 80, 64
K = np.array([[90.0, 0.0, (W - 1) / 2], [0.0, 90.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
#: normalised -> world: world = 2 n + (0, 0, 0.8)
SCALE = np.diag([2.0, 2.0, 2.0, 1.0])
SCALE[:3, 3] = (0.0, 0.0, 0.8)


def cameras(elevations=(25, 50, 70), n=6, distance=7.0):
    """(V, 3, 4) upright cameras on rings around the world point (0, 0, 0.8)."""
    target = np.array([0.0, 0.0, 0.8])
    out = []
    for e in np.radians(elevations):
        for a in np.linspace(0, 2 * np.pi, n, endpoint=False) + e:
            eye = target + distance * np.array([np.cos(e) * np.cos(a),
                                                np.cos(e) * np.sin(a), np.sin(e)])
            out.append(projection_matrix(K, look_at(eye, target))[:3])
    return np.stack(out)


def box(extents, centre):
    b = trimesh.creation.box(extents)
    b.apply_translation(centre)
    return b


BODY = box((2.0, 2.0, 1.0), (0.0, 0.0, 0.5))
ROD = box((0.16, 0.16, 1.0), (0.55, -0.55, 1.5))  # on the body's top, 1.6 px across


class BoxField:
    """The body's exact SDF in the normalised frame (what `extract_mesh` reads)."""

    class _Sdf:
        def sdf(self, p):
            w = p.double() * 2.0 + torch.tensor([0.0, 0.0, 0.8], dtype=torch.float64)
            q = (w - torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)).abs() \
                - torch.tensor([1.0, 1.0, 0.5], dtype=torch.float64)
            out = q.clamp(min=0).norm(dim=-1) + q.max(dim=-1).values.clamp(max=0)
            return (out / 2.0).float().reshape(-1, 1)

    sdf = _Sdf()
    color = None


@pytest.fixture(scope="module")
def views(box_masks):
    P = cameras()
    return P, box_masks(P, [BODY, ROD], H, W)


def plain_missed_points(points, P, masks, missed, min_views):
    """The rule, point by point and view by view, in float64."""
    keep, count = [], []
    for x in points:
        inside, n = True, 0
        for p, m, miss in zip(P, masks, missed):
            h = p @ np.r_[x, 1.0]
            if h[2] <= 0:
                continue
            c, r = int(np.rint(h[0] / h[2])), int(np.rint(h[1] / h[2]))
            if not (0 <= c < W and 0 <= r < H):
                continue
            inside &= bool(m[r, c])
            n += int(miss[r, c])
        keep.append(inside and n >= min_views)
        count.append(n)
    return np.array(keep), np.array(count)


@pytest.mark.parametrize("seed", range(3))
def test_the_point_rule_agrees_with_a_plain_loop(views, seed):
    """Random masks and missed pixels, random points around the object: the same answer."""
    P, _ = views
    rng = np.random.default_rng(seed)
    masks = [rng.random((H, W)) < 0.9 for _ in P]
    missed = [m & (rng.random((H, W)) < 0.3) for m in masks]
    points = rng.uniform(-1.5, 1.5, size=(400, 3)) + [0.0, 0.0, 0.8]
    points[:5] = [0.0, 0.0, 30.0]  # far above: behind or off some images
    for min_views in (1, 2):
        keep, count = missed_points(points, P, masks, missed, min_views)
        ref_keep, ref_count = plain_missed_points(points, P, masks, missed, min_views)
        np.testing.assert_array_equal(count, ref_count)
        np.testing.assert_array_equal(keep, ref_keep)


def test_a_view_that_does_not_see_a_point_says_nothing(views):
    """A point behind every camera is inside (no view sees it) and on no missed pixel."""
    P, masks = views
    keep, count = missed_points(np.array([[0.0, 0.0, -1e6]]), P, masks,
                                [np.ones((H, W), bool)] * len(P), 0)
    assert keep.all() and count.tolist() == [0]


def test_the_silhouette_of_the_body_matches_its_mask_and_only_the_rod_is_missed(views, box_masks):
    """The mesh without the rod: its silhouette covers the body's mask (to the pixel it is
    grown by), and the missed pixels are the rod's, in the views that see it against the
    background."""
    P, masks = views
    body_masks = box_masks(P, [BODY], H, W)
    rod_masks = box_masks(P, [ROD], H, W)
    missed = missed_pixels(BODY, P, masks)
    for v in range(len(P)):
        assert not (missed[v] & body_masks[v]).any()
        assert (missed[v] <= rod_masks[v]).all()
    assert sum(int(m.sum()) for m in missed) > 0.3 * sum(int((r & ~b).sum())
                                                          for r, b in zip(rod_masks, body_masks))
    samples = surface_samples(BODY, P)
    for v, p in enumerate(P):
        cover = silhouette(samples, p, (H, W))
        assert (body_masks[v] <= cover).all()


def test_a_floater_seen_off_the_masks_covers_nothing(views):
    """A piece beside the rod that some views see off their masks (what training leaves
    where it smeared a thin part) does not hide the rod's pixels in the views where it
    overlaps them."""
    P, masks = views
    floater = trimesh.creation.icosphere(radius=0.12).apply_translation((0.85, -0.55, 1.6))
    with_floater = trimesh.util.concatenate([BODY, floater])
    plain = missed_pixels(BODY, P, masks)
    own = surface_samples(floater, P)
    assert any((silhouette(own, p, (H, W)) & m).any() for p, m in zip(P, plain))  # it hides some
    for a, b in zip(missed_pixels(with_floater, P, masks), plain):
        np.testing.assert_array_equal(a, b)


def test_the_missing_rod_is_found_and_nothing_else(views):
    """The first mesh lacks the rod; the points found lie at the rod, along most of its
    height, and the solid's pieces put a rod where the body's mesh had none."""
    P, masks = views
    solid, report = missed_solid(BODY, P, masks, SCALE, None, resolution=64)
    assert solid is not None and report["points"] > 0 and report["pieces"] >= 1
    idx = np.argwhere(solid.values.numpy() < 0) * solid.step + solid.origin  # normalised
    world = idx * 2.0 + [0.0, 0.0, 0.8]
    assert np.abs(world[:, :2] - [0.55, -0.55]).max() < 0.08 + 2 * 2 * solid.step
    assert world[:, 2].min() > 1.0 - 2 * solid.step
    assert np.ptp(world[:, 2]) > 0.6  # most of the rod's height (1.0)
    plain = extract_mesh(BoxField(), SCALE, resolution=64, clean=False)
    parts = extract_mesh(solid_model(solid), SCALE, resolution=64, clean=False)
    sparse = extract_mesh(solid_model(solid), SCALE, resolution=64, clean=False,
                          method="sparse")  # the block test finds the solid too
    assert len(sparse.faces) == len(parts.faces)
    filled = trimesh.util.concatenate([plain, parts])
    near = lambda m: np.hypot(m.vertices[:, 0] - 0.55, m.vertices[:, 1] + 0.55) < 0.3  # noqa
    assert not (near(plain) & (plain.vertices[:, 2] > 1.1)).any()
    assert (near(filled) & (filled.vertices[:, 2] > 1.5)).any()
    top = (np.abs(filled.vertices[:, :2]).max(axis=1) < 0.9) & (filled.vertices[:, 2] > 0.5)
    assert np.allclose(filled.vertices[top & ~near(filled), 2], 1.0, atol=1e-3)


def test_a_mesh_that_covers_the_masks_adds_nothing(views):
    P, masks = views
    solid, report = missed_solid(trimesh.util.concatenate([BODY, ROD]), P, masks, SCALE, None,
                                 resolution=48)
    assert solid is None and report["points"] == 0


def plain_solid(index, R, lo, shape):
    """The solid's values by brute force: the nearest grid point in / out of the set."""
    inside = np.zeros(shape, bool)
    inside[tuple((index - lo).T)] = True
    grid = np.argwhere(np.ones(shape, bool))
    ins, outs = grid[inside.ravel()], grid[~inside.ravel()]
    out = np.empty(len(grid))
    for k, g in enumerate(grid):
        if inside.ravel()[k]:
            out[k] = 0.5 - np.sqrt(((outs - g) ** 2).sum(1)).min()
        else:
            out[k] = np.sqrt(((ins - g) ** 2).sum(1)).min() - 0.5
    return out.reshape(shape) * 2.0 / (R - 1)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(*[st.integers(3, 9)] * 3), min_size=1, max_size=12, unique=True),
       st.integers(0, 2**31 - 1))
def test_the_solid_is_the_exact_grid_distance_and_interpolates_it(points, seed):
    R = 13
    index = np.array(points)
    solid = GridSolid.from_indices(index, R)
    lo = index.min(0) - 2
    assert np.allclose(solid.origin, lo * 2.0 / (R - 1) - 1.0)
    ref = plain_solid(index, R, lo, tuple(solid.values.shape))
    np.testing.assert_allclose(solid.values.numpy(), ref, atol=1e-6)
    # at the grid points the interpolation is the value; between them, trilinear
    node = torch.as_tensor(np.argwhere(ref < np.inf) * solid.step + solid.origin)
    np.testing.assert_allclose(solid.sdf(node).numpy(), ref.ravel(), atol=1e-5)
    rng = np.random.default_rng(seed)
    f = rng.uniform(0, np.array(ref.shape) - 1, size=(50, 3))
    i0 = np.minimum(np.floor(f).astype(int), np.array(ref.shape) - 2)
    t = f - i0
    want = np.zeros(len(f))
    for corner in np.ndindex(2, 2, 2):
        c = np.array(corner)
        wgt = np.prod(np.where(c, t, 1 - t), axis=1)
        want += wgt * ref[tuple((i0 + c).T)]
    got = solid.sdf(torch.as_tensor(f * solid.step + solid.origin)).numpy()
    np.testing.assert_allclose(got, want, atol=1e-5)
    # outside the box: the distance to it plus 1.5 cells, below the true distance
    far = torch.as_tensor(solid.origin - [1.0, 0.0, 0.0])[None]
    assert solid.sdf(far).item() == pytest.approx(1.0 + 1.5 * solid.step, rel=1e-5)
    cells = index * solid.step - 1.0
    out = rng.uniform(-3.0, 3.0, size=(200, 3))
    box_hi = solid.origin + (np.array(ref.shape) - 1) * solid.step
    out = out[((out < solid.origin) | (out > box_hi)).any(axis=1)]
    true = np.sqrt(((out[:, None] - cells[None]) ** 2).sum(-1)).min(1) - 0.5 * solid.step
    assert (solid.sdf(torch.as_tensor(out)).numpy() <= true + 1e-6).all()


def test_the_command_reports_what_it_filled(run_copy, capsys):
    out = run_copy.parent / "filled.ply"
    assert main(["mesh", str(run_copy), "--resolution", "40", "--fill-missed",
                 "--out", str(out), "--quiet", "--threads", "1"]) == 0
    said = capsys.readouterr().out
    assert "missed parts: " in said and " missed mask pixels" in said
    assert len(trimesh.load(out).faces) > 0
