"""The visual hull: conservative carving, safety on synthetic scenes, bad masks, ray bounds,
save/load, the mesh, and meshing inside the hull."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from neus_l0.bounds.hull import (
    DEFAULT_MARGIN_PX,
    VisualHull,
    carve_hull,
    check_hull,
    hull_from_scene,
)
from neus_l0.errors import NeusL0Error


def _make(tmp_path_factory, name: str, views: int = 16, width: int = 100,
          height: int = 75) -> Path:
    from neus_l0.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("hull") / Path(name).stem
    return make_scene(name, out, views=views, width=width, height=height, seed=0,
                      point_spacing=2.0, progress=False)


@pytest.fixture(scope="session")
def demo_scene(tmp_path_factory):
    """The built-in demo, 16 views at 100x75: folder and loaded `Scene`."""
    from neus_l0.formats.neus import load_scene

    root = _make(tmp_path_factory, "demo")
    return root, load_scene(root)


@pytest.fixture(scope="session")
def demo_hull(demo_scene):
    return hull_from_scene(demo_scene[1])


def _truth(root: Path, scene) -> torch.Tensor:
    """All true surface points (gt_points and gt_mesh vertices) in the normalised frame."""
    from neus_l0.evaluation.io import load_points

    S = scene.scale_mat
    pts = np.concatenate([load_points(root / "gt_points.ply"),
                          load_points(root / "gt_mesh.ply")])
    return torch.from_numpy((pts - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T).float()


def _erode(masks: torch.Tensor, px: int) -> torch.Tensor:
    """Erode binary masks by a disc of radius `px` pixels."""
    r = torch.arange(-px, px + 1, dtype=torch.float32)
    disc = ((r[:, None] ** 2 + r[None, :] ** 2) <= px * px + 1e-6).float()
    bg = (masks <= 0.5).float()[:, None]
    hit = F.conv2d(bg, disc[None, None], padding=px)[:, 0] > 0
    return (~hit).float() * (masks > 0.5).float()


def _safety(root: Path, scene, thin_ok: bool = True) -> dict:
    """Fraction of true surface points inside the default hull: clean, eroded 2 px, and
    with view 5's camera moved by 1 px (principal point), each carved afresh."""
    pts = _truth(root, scene)
    out = {}
    K1 = scene.intrinsics.clone()
    K1[5, 0, 2] += 1.0
    for case, m, K in (("clean", scene.masks, scene.intrinsics),
                       ("eroded", _erode(scene.masks, 2), scene.intrinsics),
                       ("moved", scene.masks, K1)):
        hull = carve_hull(m, K, scene.c2w)
        out[case] = float(hull.contains(pts).float().mean())
    return out


def _thin_points(root: Path, scene) -> torch.Tensor:
    """(P,) bool: truth points within the ball of a "thin" feature (features.json)."""
    import json

    feats = json.loads((root / "features.json").read_text())["features"]
    S = scene.scale_mat
    from neus_l0.evaluation.io import load_points

    pts = np.concatenate([load_points(root / "gt_points.ply"),
                          load_points(root / "gt_mesh.ply")])
    near = np.zeros(len(pts), bool)
    for f in feats:
        if f["kind"] == "thin":
            near |= np.linalg.norm(pts - np.array(f["center"]), axis=1) <= f["radius"] * 1.2
    del S
    return torch.from_numpy(near)


# --- the carving rule ----------------------------------------------------------------------


def _sphere_scene(V: int = 12, W: int = 80, H: int = 60, radius: float = 0.5):
    """Analytic masks of a ball of `radius` at the origin seen by V cameras on a ring."""
    from neus_l0.data.cameras import look_at

    f = 70.0
    K = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    Ks, c2ws, masks = [], [], []
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    for i in range(V):
        a = 2 * math.pi * i / V
        eye = np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 0.8 + 0.3 * (i % 3)])
        w2c = look_at(eye, np.zeros(3))
        c2w = torch.from_numpy(np.linalg.inv(w2c))
        # ray through each pixel centre meets the ball <=> distance from centre < radius
        d = torch.stack([(xs - K[0, 2]) / f, (ys - K[1, 2]) / f, torch.ones_like(xs)], -1)
        d = d @ c2w[:3, :3].T
        d = d / d.norm(dim=-1, keepdim=True)
        o = c2w[:3, 3]
        along = (-(o * d).sum(-1)).clamp_min(0)
        dist = (o + along[..., None] * d).norm(dim=-1)
        masks.append((dist < radius).float())
        Ks.append(K)
        c2ws.append(c2w.float())
    return torch.stack(masks), torch.stack(Ks), torch.stack(c2ws)


def test_ball_hull_contains_the_ball_and_is_tight():
    masks, K, c2w = _sphere_scene()
    hull = carve_hull(masks, K, c2w, resolution=64, margin_px=0.0)
    g = torch.randn(20000, 3, generator=torch.Generator().manual_seed(0))
    on = 0.5 * g / g.norm(dim=-1, keepdim=True)  # on the sphere of radius 0.5
    assert bool(hull.contains(on).all())
    assert bool(hull.contains(0.999 * on).all())
    far = 0.95 * g / g.norm(dim=-1, keepdim=True)  # well outside the ball
    # 12 views around a ring leave wedges above and below the ball; the equator is tight
    eq = far.clone()
    eq[:, 2] *= 0.1
    eq = 0.9 * eq / eq.norm(dim=-1, keepdim=True)
    assert float(hull.contains(eq).float().mean()) < 0.05
    # sphere fraction: the ball is 0.125 of the unit sphere's volume
    assert 0.125 < hull.fraction_of_sphere() < 0.6
    assert hull.report.warnings == []


def test_views_without_masks_or_outside_carve_nothing():
    masks, K, c2w = _sphere_scene()
    full = carve_hull(masks, K, c2w, resolution=32, has_masks=False)
    assert full.fraction_of_sphere() == 1.0
    # a camera that sees none of the sphere (looking away) carves nothing
    c2w_away = c2w.clone()
    c2w_away[:, :3, 2] *= -1
    c2w_away[:, :3, 0] *= -1
    away = carve_hull(masks * 0 + 0.0, K, c2w_away, resolution=32, margin_px=0.0)
    assert away.fraction_of_sphere() == 1.0


def test_margin_grows_the_hull_monotonically():
    masks, K, c2w = _sphere_scene()
    fr = [carve_hull(masks, K, c2w, resolution=48, margin_px=m).fraction_of_sphere()
          for m in (0.0, 2.0, 6.0)]
    assert fr[0] <= fr[1] <= fr[2] and fr[0] < fr[2]


def test_coarse_to_fine_matches_the_plain_carving():
    """R divisible by 4 carves coarse first; every cell the plain rule keeps stays kept."""
    from neus_l0.bounds import hull as H

    masks, K, c2w = _sphere_scene()
    dists = [H.background_distance(m) for m in masks]
    views = list(range(len(masks)))
    idx, count, _ = H._carve(64, dists, K, c2w, views, 1.0, torch.device("cpu"))
    idx2, cent = H._candidates(64, "cpu")
    plain, _ = H._carve_counts(cent, math.sqrt(3) / 64, dists, K, c2w, views, 1.0)
    assert torch.equal(idx, idx2)
    assert bool(((count == 0) <= (plain == 0)).all())  # hierarchical keeps no more ...
    # ... and removes only cells whose coarse parent was proved background
    assert float((count == 0).float().mean()) > 0.9 * float((plain == 0).float().mean())


# --- safety on the synthetic scenes -------------------------------------------------------


def test_demo_truth_inside_default_hull(demo_scene):
    root, scene = demo_scene
    got = _safety(root, scene)
    assert got["clean"] == 1.0
    assert got["eroded"] >= 0.999
    assert got["moved"] >= 0.999


@pytest.mark.slow
def test_pits_and_thin_truth_inside_default_hull(tmp_path_factory):
    from neus_l0.formats.neus import load_scene

    root = _make(tmp_path_factory, "pits-and-thin")
    scene = load_scene(root)
    got = _safety(root, scene)
    assert got["clean"] == 1.0
    assert got["moved"] >= 0.999
    # Erosion by 2 px removes every part thinner than 5 px from the masks (rods of radius
    # 1-3.5 and fins 1.5 and 4 thick are 1-3 px wide here): no margin brings them back.
    # Away from those thin features the eroded hull keeps >= 99.9 %.
    pts = _truth(root, scene)
    thin = _thin_points(root, scene)
    hull = carve_hull(_erode(scene.masks, 2), scene.intrinsics, scene.c2w)
    inside = hull.contains(pts)
    assert float(inside[~thin].float().mean()) >= 0.999


@pytest.mark.slow
def test_bunny_truth_inside_default_hull(tmp_path_factory, shared_data):
    bunny = shared_data("bunny")
    from neus_l0.formats.neus import load_scene

    # at 200x150 the ears are thin enough that 2 px of erosion loses 0.1 % (measured 99.899 %)
    root = _make(tmp_path_factory, str(bunny), width=300, height=225)
    got = _safety(root, load_scene(root))
    assert got["clean"] == 1.0
    assert got["eroded"] >= 0.999
    assert got["moved"] >= 0.999


# --- bad masks ------------------------------------------------------------------------------


def test_good_scene_has_no_warnings(demo_hull):
    rep = demo_hull.report
    assert rep.warnings == []
    assert all(s == "ok" for s in rep.status)
    assert min(rep.explained) == 1.0
    assert 0.1 < rep.fraction_kept < 0.6


def test_swapped_masks_are_named_and_left_out(demo_scene):
    root, scene = demo_scene
    m = scene.masks.clone()
    m[[2, 9]] = m[[9, 2]]
    hull = carve_hull(m, scene.intrinsics, scene.c2w, names=scene.image_names)
    rep = hull.report
    assert rep.status[2] == "excluded" and rep.status[9] == "excluded"
    text = "\n".join(rep.warnings)
    assert "view 2 (002.png)" in text and "view 9 (009.png)" in text
    assert "wrong view's mask" in text
    # left out, the two views cannot cut the object
    assert float(hull.contains(_truth(root, scene)).float().mean()) == 1.0


def test_swapped_masks_without_exclusion_cut_and_warn(demo_scene):
    root, scene = demo_scene
    m = scene.masks.clone()
    m[[2, 9]] = m[[9, 2]]
    hull = carve_hull(m, scene.intrinsics, scene.c2w, exclude_suspicious=False)
    assert float(hull.contains(_truth(root, scene)).float().mean()) < 0.99
    assert any("view 2" in w for w in hull.report.warnings)
    assert any("view 9" in w for w in hull.report.warnings)


def test_empty_mask_carves_nothing_and_warns(demo_scene):
    root, scene = demo_scene
    m = scene.masks.clone()
    m[3] = 0
    hull = carve_hull(m, scene.intrinsics, scene.c2w)
    assert hull.report.status[3] == "empty"
    assert any(w.startswith("view 3:") and "empty" in w for w in hull.report.warnings)
    assert float(hull.contains(_truth(root, scene)).float().mean()) == 1.0


def test_full_mask_warns(demo_scene):
    root, scene = demo_scene
    m = scene.masks.clone()
    m[4] = 1
    hull = carve_hull(m, scene.intrinsics, scene.c2w)
    assert hull.report.status[4] == "full"
    assert any(w.startswith("view 4:") and "all foreground" in w for w in hull.report.warnings)
    assert float(hull.contains(_truth(root, scene)).float().mean()) == 1.0


def test_check_hull_flags_a_hull_that_cuts(demo_scene, demo_hull):
    """A loaded hull audited against masks that see more than it holds."""
    _, scene = demo_scene
    occ = demo_hull.occupancy.clone()
    occ[:, :, 64:] = False  # cut off the upper half
    rep = check_hull(VisualHull(occ), scene.masks, scene.intrinsics, scene.c2w)
    assert any("meet the visual hull" in w for w in rep.warnings)
    assert check_hull(demo_hull, scene.masks, scene.intrinsics, scene.c2w).warnings == []


def test_bad_arguments_raise():
    masks, K, c2w = _sphere_scene(V=2)
    with pytest.raises(NeusL0Error, match="margin"):
        carve_hull(masks, K, c2w, margin_px=-1.0)
    with pytest.raises(NeusL0Error, match="resolution"):
        carve_hull(masks, K, c2w, resolution=2)


# --- ray bounds -------------------------------------------------------------------------------


def _sphere_near_far(o: torch.Tensor, d: torch.Tensor):
    b = (o * d).sum(-1, keepdim=True)
    c = (o * o).sum(-1, keepdim=True) - 1.0
    disc = (b * b - c).clamp_min(0).sqrt()
    return (-b - disc).clamp_min(0.0), -b + disc


def test_ray_bounds_never_cut_the_true_surface(demo_scene, demo_hull):
    """Rays through random pixels: every sign change of the true SDF along the ray inside
    [near, far] lies in [lo, hi]; rays that miss get (near, far) and hits False."""
    from neus_l0.data.rays import random_rays
    from neus_l0.synthetic.scene import WORLD_OFFSET
    from neus_l0.synthetic.shapes import Translated, builtin_shape

    _, scene = demo_scene
    sdf = Translated(builtin_shape("demo").sdf, WORLD_OFFSET)
    S = torch.from_numpy(scene.scale_mat)
    rays = random_rays(scene, 1500, torch.Generator().manual_seed(1))
    o, d = rays["origins"], rays["dirs"]
    near, far = _sphere_near_far(o, d)
    lo, hi, hits = demo_hull.ray_bounds(o, d, near, far)
    assert lo.shape == hi.shape == (1500, 1) and hits.shape == (1500,)
    assert bool((near <= lo).all() and (lo <= hi).all() and (hi <= far).all())
    assert bool((lo[~hits] == near[~hits]).all() and (hi[~hits] == far[~hits]).all())
    n = 3000
    t = near + (far - near) * torch.linspace(0, 1, n)  # (B, n)
    x = (o[:, None, :] + d[:, None, :] * t[..., None]).double()  # normalised
    xw = x @ S[:3, :3].T + S[:3, 3]
    f = sdf(xw.reshape(-1, 3)).reshape(len(o), n)
    cross = (f[:, :-1] > 0) != (f[:, 1:] > 0)  # (B, n-1)
    tc = 0.5 * (t[:, :-1] + t[:, 1:])
    lo_ok = torch.where(cross, tc >= lo - (far - near) / n, True).all()
    hi_ok = torch.where(cross, tc <= hi + (far - near) / n, True).all()
    assert bool(lo_ok) and bool(hi_ok)
    assert bool(hits[cross.any(-1)].all())  # a ray that meets the object meets the hull
    # and the bounds are tight: the average [lo, hi] is well below the sphere's chord
    ok = hits & cross.any(-1)
    assert float((hi - lo)[ok].mean()) < 0.8 * float((far - near)[ok].mean())
    # object-mask rays all meet the hull
    assert bool(hits[rays["mask"][:, 0] > 0.5].all())


def test_ray_bounds_closed_form_on_a_box():
    """A carved box [-0.5, 0.5]^3 (dilated by one cell, as `VisualHull` holds it): every ray
    that meets the box gets bounds around its chord, within 2 cells of the box; rays that
    pass farther than that miss."""
    R = 32
    occ = torch.zeros(R, R, R, dtype=torch.bool)
    occ[7:25, 7:25, 7:25] = True  # the box [-0.5, 0.5]^3 = cells 8..23, dilated by one
    hull = VisualHull(occ)
    g = torch.Generator().manual_seed(0)
    o = torch.randn(4000, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    target = 0.7 * (torch.rand(4000, 3, generator=g) * 2 - 1)
    d = target - o
    d = d / d.norm(dim=-1, keepdim=True)
    near, far = _sphere_near_far(o, d)
    lo, hi, hits = hull.ray_bounds(o, d, near, far)
    inv = 1.0 / d
    ta, tb = (-0.5 - o) * inv, (0.5 - o) * inv
    t0 = torch.minimum(ta, tb).amax(-1, keepdim=True)
    t1 = torch.maximum(ta, tb).amin(-1, keepdim=True)
    m = (t0 <= t1)[:, 0]
    assert m.sum() > 1000 and (~m).sum() > 500
    assert bool(hits[m].all())
    assert bool((lo[m] <= t0[m] + 1e-5).all() and (hi[m] >= t1[m] - 1e-5).all())
    cell = 2.0 / R
    # tight in space: the bound points are within 2 cells (L-inf) of the box, one for the
    # dilation and one for the widening
    for t in (lo, hi):
        p = o + t * d
        assert float(((p.abs() - 0.5).clamp_min(0).amax(-1))[hits].max()) <= 2 * cell + 1e-4
    # rays that pass the dilated box [-0.5625, 0.5625]^3 by more than a cell miss it
    ta, tb = (-0.5625 - cell - o) * inv, (0.5625 + cell - o) * inv
    far_miss = (torch.minimum(ta, tb).amax(-1) > torch.maximum(ta, tb).amin(-1))
    assert not bool(hits[far_miss].any())


def _dynamic_nodes(graph_module) -> list[str]:
    """Ops of a traced graph whose output shape depends on data (unbacked sizes)."""
    bad = []
    for node in graph_module.graph.nodes:
        val = node.meta.get("val")
        for t in val if isinstance(val, (tuple, list)) else [val]:
            if isinstance(t, torch.Tensor) and not all(isinstance(s, int) for s in t.shape):
                bad.append(str(node.target))
    return bad


def test_ray_bounds_has_fixed_shapes(demo_hull):
    """Traced with fake tensors, no op has a data-dependent shape and nothing syncs
    (a `.item()` or boolean indexing would show up or raise)."""
    from torch.fx.experimental.proxy_tensor import make_fx

    def fn(occ, o, d, n, f):
        return VisualHull(occ).ray_bounds(o, d, n, f)

    def masked(x):  # the check itself can fail: boolean indexing is caught
        return x[x > 0]

    assert _dynamic_nodes(make_fx(masked, tracing_mode="fake")(torch.randn(5)))
    o, d = torch.randn(7, 3), torch.randn(7, 3)
    near = torch.zeros(7, 1)
    g = make_fx(fn, tracing_mode="fake")(demo_hull.occupancy, o, d, near, near + 4)
    assert _dynamic_nodes(g) == []


# --- save / load / mesh ---------------------------------------------------------------------


def test_save_load_roundtrip(tmp_path, demo_hull):
    p = demo_hull.save(tmp_path / "hull.pt")
    back = VisualHull.load(p)
    assert torch.equal(back.occupancy, demo_hull.occupancy)
    assert back.margin_px == demo_hull.margin_px == DEFAULT_MARGIN_PX
    assert back.report.warnings == demo_hull.report.warnings
    assert back.report.fraction_kept == demo_hull.report.fraction_kept
    sd = demo_hull.state_dict()
    assert torch.equal(VisualHull.from_state_dict(sd).occupancy, demo_hull.occupancy)
    (tmp_path / "bad.pt").write_bytes(b"not a hull")
    with pytest.raises(NeusL0Error, match="bad.pt"):
        VisualHull.load(tmp_path / "bad.pt")
    with pytest.raises(NeusL0Error, match="not found"):
        VisualHull.load(tmp_path / "missing.pt")


def test_hull_for_run_carves_once_then_loads(tmp_path, demo_scene):
    from neus_l0.bounds.hull import hull_for_run

    _, scene = demo_scene
    path = tmp_path / "run" / "hull.pt"
    a = hull_for_run(scene, path, resolution=32)
    assert path.is_file() and a.resolution == 32
    b = hull_for_run(scene, path, resolution=64)  # the saved hull wins
    assert b.resolution == 32 and torch.equal(a.occupancy, b.occupancy)


def test_mesh_is_watertight_in_world_units_and_holds_the_truth(demo_scene, demo_hull):
    root, scene = demo_scene
    mesh = demo_hull.to_mesh(scene.scale_mat)
    assert mesh.is_watertight
    from neus_l0.evaluation.io import load_points

    pts = load_points(root / "gt_points.ply")
    lo, hi = mesh.bounds
    assert bool(((pts >= lo) & (pts <= hi)).all())
    # its volume is the kept fraction of the cube, in world units (within the chamfer of MC)
    S = scene.scale_mat
    cube = 8.0 * abs(np.linalg.det(S[:3, :3]))
    frac = float(demo_hull.occupancy.float().mean())
    assert 0.8 * frac < mesh.volume / cube <= 1.01 * frac


def test_inspect_hull_cli(tmp_path, demo_scene):
    root, _ = demo_scene
    out = tmp_path / "hull.ply"
    r = subprocess.run([sys.executable, "-m", "neus_l0.cli", "inspect", str(root), "--hull",
                        str(out), "--hull-resolution", "64", "--hull-margin", "1.5"],
                       capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    assert "visual hull  keeps" in r.stdout and "of the bounding sphere" in r.stdout
    import trimesh

    assert trimesh.load(out).is_watertight
    r = subprocess.run([sys.executable, "-m", "neus_l0.cli", "inspect", str(root),
                        "--hull-margin", "1"], capture_output=True, text=True, check=False)
    assert r.returncode == 2 and "--hull" in r.stderr and "Traceback" not in r.stderr


# --- meshing inside the hull ----------------------------------------------------------------


def _ball_hull(R: int = 64, radius: float = 0.55) -> VisualHull:
    from neus_l0.bounds.grid import cell_axis, dilate

    c = cell_axis(R)
    r2 = c[:, None, None] ** 2 + c[None, :, None] ** 2 + c[None, None, :] ** 2
    return VisualHull(dilate(r2 <= radius ** 2))


def _object_and_floater(p: torch.Tensor) -> torch.Tensor:
    obj = p.norm(dim=-1) - 0.5
    floater = (p - torch.tensor([0.8, 0.0, 0.0])).norm(dim=-1) - 0.08
    return torch.minimum(obj, floater)


@pytest.mark.parametrize("res", [65, 129])
def test_sparse_meshing_drops_the_floater_outside_the_hull(res):
    from neus_l0.mesh.extract import sparse_marching_cubes

    hull = _ball_hull()
    v0, f0, s0 = sparse_marching_cubes(_object_and_floater, res)
    v1, f1, s1 = sparse_marching_cubes(_object_and_floater, res, hull=hull)
    assert (v0[:, 0] > 0.7).any()  # without the hull, the floater is exported
    assert not (v1[:, 0] > 0.6).any()  # with it, nothing outside the hull
    assert s1.blocks_kept < s0.blocks_kept and s1.sdf_evals < s0.sdf_evals
    # the object itself is the same mesh
    keep0 = np.linalg.norm(v0, axis=1) < 0.6
    a = np.unique(np.round(v0[keep0], 6), axis=0)
    b = np.unique(np.round(v1, 6), axis=0)
    assert a.shape == b.shape and np.allclose(a, b)
    import trimesh

    assert trimesh.Trimesh(v1, f1).is_watertight


def test_hull_caps_a_leak_and_extract_mesh_dense_agrees():
    """A negative region that crosses the hull is capped at the hull: still watertight."""
    from neus_l0.mesh.extract import extract_mesh, sparse_marching_cubes

    hull = _ball_hull(radius=0.45)

    def slab(p):  # a thick slab that leaves the hull on all sides
        return p[:, 2].abs() - 0.2

    v, f, _ = sparse_marching_cubes(slab, 97, hull=hull)
    import trimesh

    m = trimesh.Trimesh(v, f)
    assert m.is_watertight
    assert np.linalg.norm(v, axis=1).max() < 0.45 + 3 * 2 / 64 + 0.05

    class Model:  # extract_mesh only needs model.sdf.sdf
        class sdf:  # noqa: N801
            @staticmethod
            def sdf(p):
                return _object_and_floater(p)

    mesh = extract_mesh(Model, np.eye(4), resolution=65, method="dense", clean=False,
                        hull=_ball_hull())
    assert not (np.asarray(mesh.vertices)[:, 0] > 0.6).any()
    assert mesh.is_watertight
