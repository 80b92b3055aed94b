"""Chamfer scores with the DTU protocol against answers known in closed form."""

import json
import math

import numpy as np
import pytest
import trimesh
from scipy.integrate import quad
from scipy.io import savemat

from neus_l0.cli import main
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.chamfer import chamfer, in_box, nearest_distances, truncated_mean
from neus_l0.evaluation.dtu import (
    ObsMask,
    above_plane,
    evaluate_dtu,
    in_obs_mask,
    load_obs_mask,
    load_plane,
)
from neus_l0.evaluation.pointcloud import sample_mesh, thin_points

R = 10.0  # sphere radius (mm)


def fib_sphere(n, r, center=(0, 0, 0)):
    """n nearly uniform points on a sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    s = np.sqrt(1 - z**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], 1) * r + np.asarray(center)


def dense_sphere(r, spacing=0.12):
    return fib_sphere(int(4 * math.pi * r**2 / spacing**2), r)


def sphere_mesh(r=R, center=(0, 0, 0)):
    m = trimesh.creation.icosphere(subdivisions=6, radius=r)  # edges ~0.16 r / 10
    m.apply_translation(center)
    return m


def full_obs(lo=-40.0, hi=40.0, res=1.0):
    n = int(round((hi - lo) / res)) + 1
    return ObsMask(mask=np.ones((n, n, n), bool), bb=np.array([[lo] * 3, [hi] * 3]), res=res)


NO_PLANE = np.array([0.0, 0.0, 1.0, 1000.0])  # everything is above it


def score(mesh, gt, obs=None, plane=NO_PLANE, seed=0, **kw):
    pts = thin_points(sample_mesh(mesh.vertices, mesh.faces, 0.2), 0.2, seed=seed)
    res, masks = evaluate_dtu(pts, gt, obs if obs is not None else full_obs(), plane, **kw)
    return res


# The distances below are kept >= 1 everywhere: a predicted point set thinned to 0.2 then
# overestimates a distance d by about l^2 / (2 d) with l <~ 0.15 its lateral spacing (second
# order), instead of by ~l where the true distance is 0 (first order).


def test_offset_sphere_gives_offset_both_ways():
    d = 2.0
    res = score(sphere_mesh(R), dense_sphere(R + d))
    assert res.accuracy == pytest.approx(d, abs=0.01)
    assert res.completeness == pytest.approx(d, abs=0.01)
    assert res.overall == pytest.approx(d, abs=0.01)


def sphere_mean(fun):
    """Mean of fun(cos(angle to +x)) over a sphere, uniform in area (cos is uniform)."""
    return quad(lambda c: fun(c) / 2, -1, 1)[0]


def test_translated_sphere():
    t, d = 1.0, 3.0  # prediction: radius R centred at (t, 0, 0); GT: radius R + d at 0
    # accuracy: point R n + t e_x, distance to the GT sphere | |R n + t e_x| - (R + d) |
    acc = sphere_mean(lambda c: abs(math.sqrt(R * R + 2 * R * t * c + t * t) - (R + d)))
    # completeness: point (R + d) n, distance to the prediction | |(R + d) n - t e_x| - R |
    rd = R + d
    comp = sphere_mean(lambda c: abs(math.sqrt(rd * rd - 2 * rd * t * c + t * t) - R))
    assert acc != pytest.approx(comp, abs=0.02)  # the two sides differ here
    res = score(sphere_mesh(R, center=(t, 0, 0)), dense_sphere(rd))
    assert res.accuracy == pytest.approx(acc, abs=0.01)
    assert res.completeness == pytest.approx(comp, abs=0.01)


def capless_sphere(theta0, n_theta=200, n_phi=400):
    """The sphere of radius R without the cap of polar angle < theta0 (a UV grid whose
    first ring lies exactly on the rim, closed by a vertex at the south pole)."""
    th = np.linspace(theta0, math.pi, n_theta + 1)[:-1]
    ph = np.linspace(0, 2 * math.pi, n_phi, endpoint=False)
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    v = R * np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
    v = np.concatenate([v.reshape(-1, 3), [[0, 0, -R]]])
    idx = np.arange(n_theta * n_phi).reshape(n_theta, n_phi)
    a, b = idx[:-1], idx[1:]
    a1, b1 = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    f = np.concatenate([np.stack([a, b, b1], -1).reshape(-1, 3),
                        np.stack([a, b1, a1], -1).reshape(-1, 3)])
    last = idx[-1]
    f = np.concatenate([f, np.stack([last, np.full(n_phi, len(v) - 1), np.roll(last, -1)], -1)])
    return trimesh.Trimesh(v, f, process=False)


def missing_cap_completeness(theta0, d):
    """Mean distance of the sphere of radius R + d to the radius-R sphere without the cap
    of polar angle < theta0 (uniform in area over the GT sphere).

    A GT point at polar angle theta >= theta0 is d from the prediction; one at theta <
    theta0 is nearest to the rim at its azimuth: sqrt(a^2 + R^2 - 2 a R cos(theta0 - theta))
    with a = R + d. The area fraction of d(theta) is sin(theta) / 2 d(theta).
    """
    a = R + d
    cap = quad(lambda th: math.sqrt(a * a + R * R - 2 * a * R * math.cos(theta0 - th))
               * math.sin(th) / 2, 0, theta0)[0]
    return cap + d * (1 + math.cos(theta0)) / 2


def test_missing_cap_loses_completeness():
    theta0, d = math.radians(60), 2.0
    expected = missing_cap_completeness(theta0, d)
    assert expected > d + 0.5  # the cap costs a lot
    res = score(capless_sphere(theta0), dense_sphere(R + d))
    assert res.accuracy == pytest.approx(d, abs=0.01)
    assert res.completeness == pytest.approx(expected, abs=0.01)


def test_plane_removes_gt_points_below_it():
    theta0, d = math.radians(60), 2.0
    gt = dense_sphere(R + d)
    mesh = capless_sphere(theta0)
    mesh.apply_transform(np.diag([1, 1, -1, 1]))  # the missing cap is now at the bottom
    h = (R + d) * math.cos(theta0)
    plane = np.array([0, 0, 1.0, h])  # above: z > -h, the GT points the mesh covers
    res = score(mesh, gt, plane=plane)
    assert res.counts["gt_used"] == int((gt[:, 2] > -h).sum()) < len(gt)
    assert res.counts["gt_total"] == len(gt)
    assert res.completeness == pytest.approx(d, abs=0.01)
    without = score(mesh, gt)
    assert without.completeness == pytest.approx(missing_cap_completeness(theta0, d), abs=0.01)


def test_floaters_outside_obs_mask_are_ignored_inside_counted():
    D = 8.0
    gt = dense_sphere(R)
    floater = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    floater.apply_translation([0, 0, R + D])
    mesh = trimesh.util.concatenate([sphere_mesh(R), floater])
    pts = thin_points(sample_mesh(mesh.vertices, mesh.faces, 0.2), 0.2, seed=0)
    on_floater = pts[:, 2] > R + 2
    assert on_floater.sum() > 50

    base, _ = evaluate_dtu(pts[~on_floater], gt, full_obs(), NO_PLANE)
    obs = full_obs()
    k = int(round((R + D - 3 - obs.bb[0, 2]) / obs.res))
    obs.mask[:, :, k:] = False  # nothing above z = R + D - 3 is observed
    hidden, masks = evaluate_dtu(pts, gt, obs, NO_PLANE)
    assert not masks["pred_kept"][on_floater].any()
    assert masks["pred_in_box"][on_floater].all()
    assert hidden.counts["pred_kept"] == base.counts["pred_kept"]
    assert hidden.accuracy == pytest.approx(base.accuracy, abs=1e-12)

    seen, _ = evaluate_dtu(pts, gt, full_obs(), NO_PLANE)
    n_f = int(on_floater.sum())
    assert seen.counts["pred_kept"] == base.counts["pred_kept"] + n_f
    # independent: the floater points' distances to the GT sphere, in closed form
    f_dist = np.abs(np.linalg.norm(pts[on_floater], axis=1) - R)
    expected = (base.accuracy * base.counts["pred_kept"] + f_dist.sum()) / seen.counts["pred_kept"]
    assert seen.accuracy == pytest.approx(expected, abs=0.002)
    assert seen.accuracy > base.accuracy + 0.01
    # completeness uses the in-box points either way: the floater is far from the GT
    assert seen.completeness == pytest.approx(hidden.completeness, abs=1e-12)


def test_points_outside_the_box_are_ignored_for_both_sides():
    gt = dense_sphere(R, 0.2)
    obs = full_obs(-15, 15)  # box: [-75, 135)
    pts = np.concatenate([gt + 0.5 * gt / R, [[0, 0, -76.0], [0, 0, 134.0]]])
    res, masks = evaluate_dtu(pts, gt, obs, NO_PLANE)
    assert masks["pred_in_box"].tolist()[-2:] == [False, True]
    assert not masks["pred_kept"][-1]  # in the box but outside ObsMask's voxels


def test_floater_beyond_max_dist_is_dropped_from_the_mean():
    gt = dense_sphere(R)
    pts = np.concatenate([gt * (R + 1) / R, [[0, 0, R + 25.0], [0, 0, R + 19.5]]])
    res, _ = evaluate_dtu(pts, gt, full_obs(), NO_PLANE)
    assert res.counts["pred_kept"] == len(pts)
    assert res.counts["acc_within"] == len(pts) - 1
    assert res.accuracy == pytest.approx((len(gt) * 1.0 + 19.5) / (len(gt) + 1), abs=1e-3)


def square_mesh(kind, size=20.0):
    if kind == "two":
        v = np.array([[0, 0, 0], [size, 0, 0], [size, size, 0], [0, size, 0]], float)
        return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    if kind == "grid":
        g = np.linspace(0, size, 31)
        xx, yy = np.meshgrid(g, g, indexing="ij")
        v = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
        idx = np.arange(31 * 31).reshape(31, 31)
        a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        f = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                            np.stack([b, c, d], -1).reshape(-1, 3)])
        return trimesh.Trimesh(v, f, process=False)
    # a Delaunay triangulation of random interior points plus the corners
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(0)
    xy = np.concatenate([[[0, 0], [size, 0], [size, size], [0, size]],
                         rng.uniform(0, size, (300, 2))])
    v = np.concatenate([xy, np.zeros((len(xy), 1))], 1)
    return trimesh.Trimesh(v, Delaunay(xy).simplices, process=False)


def plane_points(size=20.0, z=1.0, spacing=0.05):
    g = np.arange(0, size + 1e-9, spacing)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], 1)


def test_results_do_not_depend_on_triangulation():
    gt = plane_points(z=1.0)
    results = [score(square_mesh(k), gt) for k in ("two", "grid", "delaunay")]
    for r in results:
        assert r.accuracy == pytest.approx(1.0, abs=0.005)
        assert r.completeness == pytest.approx(1.0, abs=0.02)
    accs = [r.accuracy for r in results]
    comps = [r.completeness for r in results]
    assert max(accs) - min(accs) < 0.003
    assert max(comps) - min(comps) < 0.005


def test_results_are_stable_across_seeds():
    mesh, gt = square_mesh("delaunay"), plane_points(z=1.0)
    res = [score(mesh, gt, seed=s) for s in range(3)]
    for r in res[1:]:
        assert r.accuracy == pytest.approx(res[0].accuracy, rel=0.002)
        assert r.completeness == pytest.approx(res[0].completeness, rel=0.002)


# --- small pieces -------------------------------------------------------------------------


def test_in_obs_mask_voxel_lookup():
    mask = np.zeros((3, 4, 5), bool)
    mask[1, 2, 3] = True
    obs = ObsMask(mask=mask, bb=np.array([[10.0, 20, 30], [12, 23, 34]]), res=1.0)
    pts = np.array([[11, 22, 33], [11.4, 22.4, 32.6], [11.6, 22, 33],
                    [9, 22, 33], [13, 22, 33], [11, 22, 35]], float)
    assert in_obs_mask(pts, obs).tolist() == [True, True, False, False, False, False]


def test_box_and_plane():
    pts = np.array([[0, 0, 0], [1, 1, 1], [-1, 0, 0.5]], float)
    assert in_box(pts, [0, 0, 0], [1, 1, 1]).tolist() == [True, False, False]
    assert above_plane(pts, np.array([0, 0, 1.0, -0.25])).tolist() == [False, True, True]


def test_truncated_mean_and_empty_cases():
    assert truncated_mean(np.array([1.0, 2.0, 30.0, np.inf]), 20) == 1.5
    assert math.isnan(truncated_mean(np.array([25.0]), 20))
    assert np.isinf(nearest_distances(np.zeros((2, 3)), np.zeros((0, 3)))).all()
    r = chamfer(np.zeros((0, 3)), np.ones((3, 3)), np.ones((3, 3)), np.zeros((0, 3)), 20)
    assert math.isnan(r.accuracy) and math.isnan(r.overall)


def test_nearest_distances_chunked_matches_brute_force():
    rng = np.random.default_rng(0)
    q, ref = rng.normal(size=(500, 3)), rng.normal(size=(300, 3))
    brute = np.linalg.norm(q[:, None] - ref[None], axis=-1).min(1)
    assert np.allclose(nearest_distances(q, ref, chunk=37), brute)
    bounded = nearest_distances(q, ref, upper_bound=0.3, chunk=37)
    assert np.allclose(bounded[brute < 0.3], brute[brute < 0.3])
    assert np.isinf(bounded[brute > 0.3]).all()


# --- files and the CLI --------------------------------------------------------------------


def write_dtu(root, stl, obs, plane, scan=24):
    (root / "Points" / "stl").mkdir(parents=True)
    (root / "ObsMask").mkdir()
    trimesh.PointCloud(stl).export(root / "Points" / "stl" / f"stl{scan:03d}_total.ply")
    savemat(root / "ObsMask" / f"ObsMask{scan}_10.mat",
            {"ObsMask": obs.mask.astype(np.uint8), "BB": obs.bb, "Res": np.array([[obs.res]])})
    savemat(root / "ObsMask" / f"Plane{scan}.mat", {"P": plane.reshape(1, 4)})
    return root


def test_cli_dtu_end_to_end(tmp_path, capsys):
    d = 2.0
    dtu = write_dtu(tmp_path / "dtu", dense_sphere(R + d, 0.2), full_obs(), NO_PLANE)
    mesh_path = tmp_path / "mesh.ply"
    sphere_mesh(R).export(mesh_path)
    maps = tmp_path / "maps"
    rc = main(["eval", str(mesh_path), "--dtu", str(dtu), "--scan", "24",
               "--error-maps", str(maps)])
    assert rc == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    report = json.loads(last)
    assert report == json.loads((tmp_path / "mesh.ply.eval.json").read_text())
    assert report["protocol"] == "dtu"
    assert report["accuracy"] == pytest.approx(d, abs=0.01)
    assert report["completeness"] == pytest.approx(d, abs=0.01)
    c = report["counts"]
    assert c["pred_sampled"] >= c["pred_thinned"] >= c["pred_in_box"] >= c["pred_kept"] > 0
    assert c["gt_used"] == c["gt_total"] > 0
    s = report["settings"]
    assert (s["density"], s["max_dist"], s["margin_low"], s["margin_high"]) == (0.2, 20, 60, 120)
    acc = trimesh.load(maps / "accuracy.ply", process=False)
    comp = trimesh.load(maps / "completeness.ply", process=False)
    assert len(acc.faces) == len(sphere_mesh(R).faces)
    assert len(comp.vertices) == c["gt_total"]
    # same colour scale: both sides are ~d/20 up the colormap, hence the same colour
    ca = np.asarray(acc.visual.vertex_colors)[:, :3].astype(int)
    cc = np.asarray(comp.colors)[:, :3].astype(int)
    assert np.abs(np.median(ca, 0) - np.median(cc, 0)).max() <= 3


def test_cli_json_path_and_missing_files(tmp_path, capsys):
    dtu = write_dtu(tmp_path / "dtu", dense_sphere(R, 0.3), full_obs(), NO_PLANE)
    mesh_path = tmp_path / "m.ply"
    sphere_mesh(R).export(mesh_path)
    out = tmp_path / "sub" / "r.json"
    assert main(["eval", str(mesh_path), "--dtu", str(dtu), "--scan", "24",
                 "--json", str(out)]) == 0
    assert json.loads(out.read_text())["accuracy"] < 0.2  # GT spacing 0.3
    capsys.readouterr()
    assert main(["eval", str(mesh_path), "--dtu", str(dtu), "--scan", "37"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ObsMask37_10.mat" in err and "not found" in err
    assert main(["eval", str(tmp_path / "nope.ply"), "--dtu", str(dtu), "--scan", "24"]) == 2
    assert "nope.ply" in capsys.readouterr().err


def test_mesh_without_faces_is_an_error(tmp_path, capsys):
    dtu = write_dtu(tmp_path / "dtu", dense_sphere(R, 0.5), full_obs(), NO_PLANE)
    pc = tmp_path / "points.ply"
    trimesh.PointCloud(dense_sphere(R, 1.0)).export(pc)
    assert main(["eval", str(pc), "--dtu", str(dtu), "--scan", "24"]) == 2
    err = capsys.readouterr().err
    assert "points.ply" in err and "no faces" in err


def test_bad_mat_files(tmp_path):
    bad = tmp_path / "bad.mat"
    bad.write_bytes(b"not a mat file at all")
    with pytest.raises(NeusL0Error, match="bad.mat"):
        load_obs_mask(bad)
    nokey = tmp_path / "nokey.mat"
    savemat(nokey, {"ObsMask": np.ones((2, 2, 2)), "BB": np.zeros((2, 3))})
    with pytest.raises(NeusL0Error, match="missing key.*Res"):
        load_obs_mask(nokey)
    plane = tmp_path / "plane.mat"
    savemat(plane, {"Q": np.zeros(4)})
    with pytest.raises(NeusL0Error, match="plane.mat: missing key"):
        load_plane(plane)
    savemat(plane, {"P": np.zeros(3)})
    with pytest.raises(NeusL0Error, match="4 values"):
        load_plane(plane)
