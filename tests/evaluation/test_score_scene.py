"""Synthetic-scene evaluation (`--scene`), mask culling (`--cull`) and their CLI.

The scene folder is built here from an analytic sphere: cameras from world_mat matrices
constructed by look-at, gt_depth and masks by exact ray-sphere intersection, gt_mesh.ply a
fine icosphere (its faces lie within 0.0008 of the sphere).
"""

import json
import math

import cv2
import numpy as np
import pytest
import trimesh

from neus_l0.cli import main
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.cull import cull_faces, cull_mesh, dilate_mask, mask_keep_vertices
from neus_l0.evaluation.pointcloud import sample_mesh, thin_points
from neus_l0.evaluation.synthetic import evaluate_synthetic, load_synthetic_gt, observed

RADIUS = 10.0
W, H, FOCAL = 120, 90, 90.0
K = np.array([[FOCAL, 0, (W - 1) / 2], [0, FOCAL, (H - 1) / 2], [0, 0, 1]])


def look_at(center):
    """World-to-camera R (3, 3), t (3,) for a camera at `center` looking at the origin."""
    z = -center / np.linalg.norm(center)
    up = np.array([0, 0, 1.0]) if abs(z[2]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    return r, -r @ center


def camera_centers(dist=60.0):
    ring = [(math.radians(a), math.radians(30 if i % 2 else -30))
            for i, a in enumerate(range(0, 360, 45))]
    cs = [dist * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
          for a, e in ring]
    return np.array(cs + [[0, 0, dist], [0, 0, -dist]])


def sphere_depth(center, r):
    """Camera-z depth of the first hit of the sphere (radius RADIUS at 0) per pixel centre."""
    rot, _ = look_at(center)
    xs, ys = np.meshgrid(np.arange(W), np.arange(H))
    d_cam = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T  # z = 1
    d = d_cam @ rot  # world directions (R^T d_cam), camera-z component 1
    a = (d * d).sum(-1)
    b = 2 * d @ center
    c = center @ center - r * r
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore"):
        s = (-b - np.sqrt(disc)) / (2 * a)
    return np.where(disc >= 0, s, np.inf).astype(np.float32)


def fib_sphere(n, r):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    s = np.sqrt(1 - z**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], 1) * r


def make_scene(root, flip_view=1):
    """Write a NeuS-format synthetic scene of a sphere (radius RADIUS) to `root`."""
    (root / "mask").mkdir(parents=True)
    cams, depths = {}, {}
    centers = camera_centers()
    for i, c in enumerate(centers):
        rot, t = look_at(c)
        wm = np.eye(4)
        wm[:3, :4] = K @ np.concatenate([rot, t[:, None]], 1)
        if i == flip_view:
            wm = -2.0 * wm  # same projection, opposite sign and scale
        cams[f"world_mat_{i}"] = wm
        cams[f"scale_mat_{i}"] = np.diag([RADIUS * 1.2] * 3 + [1.0])
        depths[f"depth_{i}"] = sphere_depth(c, RADIUS)
        m = np.isfinite(depths[f"depth_{i}"]).astype(np.uint8) * 255
        cv2.imwrite(str(root / "mask" / f"{i:03d}.png"), np.repeat(m[..., None], 3, -1))
    np.savez(root / "cameras_sphere.npz", **cams)
    np.savez(root / "gt_depth.npz", **depths)
    pts = fib_sphere(int(4 * math.pi * RADIUS**2 / 0.12**2), RADIUS)
    # keep what some camera sees: facing it (the sphere is convex) and inside its image
    seen = np.zeros(len(pts), bool)
    for c in centers:
        rot, t = look_at(c)
        h = (pts @ rot.T + t) @ K.T
        x, y = h[:, 0] / h[:, 2], h[:, 1] / h[:, 2]
        inside = (np.rint(x) >= 0) & (np.rint(x) < W) & (np.rint(y) >= 0) & (np.rint(y) < H)
        seen |= inside & (((c - pts) * pts).sum(1) > 0)
    trimesh.PointCloud(pts[seen]).export(root / "gt_points.ply")
    sphere_mesh(RADIUS, subdivisions=6).export(root / "gt_mesh.ply")
    return root


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("eval_scene") / "sphere")


def sphere_mesh(r, center=(0, 0, 0), subdivisions=5):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=r)
    m.apply_translation(center)
    return m


def test_observed_follows_depth_maps(scene):
    gt = load_synthetic_gt(scene)
    assert len(gt.projections) == len(gt.depths) == 10
    surface = fib_sphere(500, RADIUS)
    assert observed(surface, gt.projections, gt.depths).all()
    inside = np.array([[0, 0, 0.0], [0, 0, 5.0], [3, -3, 0.0]])
    assert not observed(inside, gt.projections, gt.depths).any()
    # 1 behind the surface: observed with the default tolerance (2); 4 behind: hidden
    # (the 3x3 window adds about one pixel footprint (0.55) times the surface slope)
    behind = fib_sphere(300, RADIUS - 1.0)
    assert observed(behind, gt.projections, gt.depths).all()
    assert not observed(fib_sphere(300, RADIUS - 4.0), gt.projections, gt.depths).any()
    assert observed(fib_sphere(300, RADIUS - 4.0), gt.projections, gt.depths, 6.0).all()
    # in front of the surface, but outside every image
    far = np.array([[500.0, 0, 0], [0, 0, 1e6]])
    assert not observed(far, gt.projections, gt.depths).any()


def score(scene, mesh, seed=0, **kw):
    gt = load_synthetic_gt(scene)
    pts = thin_points(sample_mesh(mesh.vertices, mesh.faces, 0.2), 0.2, seed=seed)
    return evaluate_synthetic(pts, gt, pred_mesh=(mesh.vertices, mesh.faces), **kw), pts


def test_offset_sphere_both_ways(scene):
    d = 1.0
    (res, _), _ = score(scene, sphere_mesh(RADIUS + d))
    assert res.distance == "point-to-mesh"
    assert res.accuracy == pytest.approx(abs(d), abs=0.01)
    assert res.completeness == pytest.approx(abs(d), abs=0.01)


def test_gt_mesh_scores_zero_against_its_own_scene(scene):
    """Point-to-mesh: no floor from the GT point spacing (point-to-point gave ~0.05 here)."""
    gt_mesh = trimesh.load(scene / "gt_mesh.ply", process=False)
    (res, masks), _ = score(scene, gt_mesh)
    assert res.accuracy < 1e-9  # the samples lie on gt_mesh's own triangles
    assert res.completeness < 0.001  # the exact sphere's points to its icosphere
    assert masks["pred_kept"].mean() > 0.99


def test_legacy_scene_without_gt_mesh_falls_back_to_points(scene, tmp_path):
    import shutil

    legacy = tmp_path / "legacy"
    shutil.copytree(scene, legacy)
    (legacy / "gt_mesh.ply").unlink()
    gt = load_synthetic_gt(legacy)
    assert gt.surface is None
    mesh = sphere_mesh(RADIUS + 1.0, subdivisions=4)
    pts = thin_points(sample_mesh(mesh.vertices, mesh.faces, 0.2), 0.2)
    res, _ = evaluate_synthetic(pts, gt)
    assert res.distance == "point-to-point"
    assert res.accuracy == pytest.approx(1.0, abs=0.1)
    res, _ = evaluate_synthetic(pts, gt, pred_mesh=(mesh.vertices, mesh.faces))
    assert res.distance == "accuracy: point-to-point, completeness: point-to-mesh"


def test_hidden_floater_ignored_visible_floater_counted(scene):
    hidden = sphere_mesh(2.0)  # inside the object: no camera sees it
    visible = sphere_mesh(1.0, center=(0, 0, RADIUS + 6))  # in front of the surface
    mesh = trimesh.util.concatenate([sphere_mesh(RADIUS), hidden, visible])
    (res, masks), pts = score(scene, mesh)
    r = np.linalg.norm(pts, axis=1)
    is_hidden = r < 3
    is_visible = pts[:, 2] > RADIUS + 3
    assert is_hidden.sum() > 50 and is_visible.sum() > 50
    assert not masks["pred_kept"][is_hidden].any()
    assert masks["pred_kept"][is_visible].all()
    main_part = ~is_hidden & ~is_visible
    assert masks["pred_kept"][main_part].all()
    # the visible floater's points add their closed-form distance |r - RADIUS| (~6)
    d_main = res.dist_pred[~is_visible[masks["pred_kept"]]]
    expected = (d_main.sum() + np.abs(r[is_visible] - RADIUS).sum()) / masks["pred_kept"].sum()
    assert res.accuracy == pytest.approx(expected, abs=0.003)
    assert res.accuracy > d_main.mean() + 0.05


def test_cull_removes_parts_outside_the_masks_and_keeps_the_object(scene):
    floater = trimesh.creation.box(extents=[2, 2, 2])
    floater.apply_translation([0, 0, 22])  # seen by side views above the silhouette
    sphere = sphere_mesh(RADIUS, subdivisions=4)
    mesh = trimesh.util.concatenate([sphere, floater])
    v, f, info = cull_mesh(mesh.vertices, mesh.faces, scene)
    assert info["faces_before"] == len(mesh.faces)
    assert info["faces_after"] == len(sphere.faces) == len(f)
    assert np.abs(np.linalg.norm(v, axis=1) - RADIUS).max() < 1e-6
    assert info["dilate_px"] == round(24 * W / 1600)


def test_cull_rule_details(scene):
    from neus_l0.data.cameras import read_masks, read_world_mats

    proj = read_world_mats(scene)
    masks = [dilate_mask(m, 0) for m in read_masks(scene).values()]
    pts = np.array([[0, 0, 0.0],        # inside the object: on every mask
                    [0, 0, 22.0],       # outside the masks of views that see it
                    [1e5, 1e5, 1e5]])   # inside no image: kept (IDR's rule)
    assert mask_keep_vertices(pts, proj, masks).tolist() == [True, False, True]
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], float)
    vv, ff = cull_faces(v, np.array([[0, 1, 2], [1, 2, 3]]), np.array([1, 1, 1, 0], bool))
    assert ff.tolist() == [[0, 1, 2]] and len(vv) == 3


def test_dilate_mask_is_a_disk():
    m = np.zeros((21, 21), bool)
    m[10, 10] = True
    d = dilate_mask(m, 3)
    yy, xx = np.mgrid[:21, :21]
    assert np.array_equal(d, (yy - 10) ** 2 + (xx - 10) ** 2 <= 9)


def test_cli_scene_with_cull_and_error_maps(scene, tmp_path, capsys):
    floater = trimesh.creation.box(extents=[2, 2, 2])
    floater.apply_translation([0, 0, 22])
    mesh = trimesh.util.concatenate([sphere_mesh(RADIUS + 1.0, subdivisions=4), floater])
    path = tmp_path / "pred.ply"
    mesh.export(path)
    # the prediction's silhouette is ~2 px wider than the masks: dilate by 5 px
    rc = main(["eval", str(path), "--scene", str(scene), "--cull", str(scene), "--cull-dilate", "5",
               "--error-maps", str(tmp_path / "maps"), "--vmax", "2"])
    assert rc == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["protocol"] == "synthetic"
    cull = report["settings"]["cull"]
    assert cull["dilate_px"] == 5
    assert cull["faces_after"] == len(sphere_mesh(RADIUS, subdivisions=4).faces)
    assert report["accuracy"] == pytest.approx(1.0, abs=0.03)
    assert report["completeness"] == pytest.approx(1.0, abs=0.03)
    assert report["counts"]["gt_used"] == report["counts"]["gt_total"]
    assert report["settings"]["depth_tol"] == 2.0
    assert report["settings"]["distance"] == "point-to-mesh"
    assert report["error_maps"]["vmax"] == 2.0
    acc = trimesh.load(tmp_path / "maps" / "accuracy.ply", process=False)
    assert len(acc.faces) == report["settings"]["cull"]["faces_after"]
    assert json.loads((tmp_path / "pred.ply.eval.json").read_text()) == report


def test_cli_gt_mesh_against_its_scene_with_error_maps(scene, tmp_path, capsys):
    from neus_l0.evaluation.error_maps import colorize

    rc = main(["eval", str(scene / "gt_mesh.ply"), "--scene", str(scene),
               "--error-maps", str(tmp_path / "maps"), "--vmax", "0.05",
               "--json", str(tmp_path / "r.json")])
    assert rc == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["settings"]["distance"] == "point-to-mesh"
    assert report["accuracy"] < 0.01 and report["completeness"] < 0.01
    # both maps coloured by the point-to-mesh distances (< 0.001, 2 % of the scale): the
    # pure-blue bottom of jet; nearest-GT-point distances (~0.05) would reach the top
    assert colorize(np.array([0.005]), 0.05)[0, :2].tolist() == [0, 0]
    for name in ("accuracy.ply", "completeness.ply"):
        cloud = trimesh.load(tmp_path / "maps" / name, process=False)
        rgba = np.asarray(cloud.visual.vertex_colors, dtype=int)
        assert (rgba[:, :2] == 0).all(), name


def test_cli_tiny_synth_scene_gt_mesh(tiny_scene, tmp_path, capsys):
    """`neus-l0 synth`'s coarse gt_mesh (marching cubes, voxel 4) against its own scene."""
    rc = main(["eval", str(tiny_scene / "gt_mesh.ply"), "--scene", str(tiny_scene),
               "--density", "1.0", "--json", str(tmp_path / "r.json")])
    assert rc == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["settings"]["distance"] == "point-to-mesh"
    assert report["accuracy"] < 0.01
    # what is left is gt_mesh's own faceting: the exact points to a voxel-4 mesh
    assert report["completeness"] < 0.15


def test_scene_errors(scene, tmp_path, capsys):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(scene, broken)
    (broken / "gt_depth.npz").unlink()
    with pytest.raises(NeusL0Error, match="gt_depth.npz: file not found"):
        load_synthetic_gt(broken)
    np.savez(broken / "gt_depth.npz", depth_0=np.zeros((H, W), np.float32))
    with pytest.raises(NeusL0Error, match="1 depth maps for 10 cameras"):
        load_synthetic_gt(broken)
    (broken / "mask" / "000.png").unlink()
    with pytest.raises(NeusL0Error, match="no mask for (image/000.png|world_mat_0)"):
        cull_mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), broken)
    mesh = tmp_path / "m.ply"
    sphere_mesh(RADIUS, subdivisions=2).export(mesh)
    assert main(["eval", str(mesh), "--scene", str(tmp_path / "missing")]) == 2
    assert "missing: scene folder not found" in capsys.readouterr().err
    assert main(["eval", str(mesh), "--dtu", str(tmp_path)]) == 2
    assert "--scan" in capsys.readouterr().err


@pytest.mark.slow
def test_synth_scene_gt_mesh_scores_zero_against_itself(tmp_path, capsys):
    """`neus-l0 synth`'s own gt_mesh.ply against its scene: zero, point-to-mesh."""
    from neus_l0.synthetic.scene import make_scene

    root = make_scene("demo", tmp_path / "demo", views=8, width=80, height=60, seed=0,
                      progress=False)
    rc = main(["eval", str(root / "gt_mesh.ply"), "--scene", str(root)])
    assert rc == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # point-to-point to GT points 0.5 apart gave ~0.25; point-to-mesh leaves only the
    # marching-cubes faceting of gt_mesh (measured 0.009 for completeness)
    assert report["settings"]["distance"] == "point-to-mesh"
    assert report["accuracy"] < 0.01
    assert report["completeness"] < 0.01
    assert report["counts"]["pred_kept"] > 0.5 * report["counts"]["pred_in_box"]  # 8 views


def test_score_mesh_spec_and_keyword_forms_agree(scene, tmp_path):
    """`score_mesh(mesh, ScoreSpec(...))` == `score_mesh(mesh, **fields)`; the CLI's
    defaults are `ScoreSpec`'s."""
    import argparse

    from neus_l0.commands import evaluate
    from neus_l0.evaluation.score import ScoreSpec, score_mesh

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    path = tmp_path / "pred.ply"
    mesh.export(path)
    a = score_mesh(path, ScoreSpec(scene=scene, density=1.0), log=lambda _m: None)
    b = score_mesh(path, ScoreSpec(scene=tmp_path), scene=scene, density=1.0,
                   log=lambda _m: None)
    for k in ("accuracy", "completeness", "overall", "counts", "settings"):
        assert a[k] == b[k]
    with pytest.raises(NeusL0Error, match="exactly one ground truth"):
        score_mesh(path, ScoreSpec())
    sub = argparse.ArgumentParser().add_subparsers()
    args = evaluate.add_parser(sub, "eval").parse_args(["m.ply", "--scene", "s"])
    defaults = ScoreSpec()
    for field in ("density", "max_dist", "margin_low", "margin_high", "depth_tol", "seed",
                  "workers", "cmap", "vmax", "cull_dilate"):
        assert getattr(args, field) == getattr(defaults, field), field
