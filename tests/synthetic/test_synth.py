"""Synthetic scenes: NeuS-format output, exact ground truth, the `synth` command, mesh input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from neus_l0.cli import main
from neus_l0.data.cameras import camera_z_depth
from neus_l0.formats.neus import load_scene, validate_scene
from neus_l0.synthetic.scene import WORLD_OFFSET, make_scene
from neus_l0.synthetic.shapes import Translated, builtin_shape, project_to_surface


def _world_sdf(name):
    return Translated(builtin_shape(name).sdf, WORLD_OFFSET)


def test_synth_cli_writes_a_scene_that_loads_and_inspects(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["synth", "demo", str(out), "--views", "3", "--width", "40", "--height", "30",
               "--seed", "1", "--no-progress"])
    assert rc == 0
    for name in ("cameras_sphere.npz", "gt_mesh.ply", "gt_points.ply", "gt_depth.npz",
                 "features.json", "scene.json", "image/000.png", "mask/002.png"):
        assert (out / name).is_file(), name
    scene = load_scene(out)
    assert scene.n_views == 3 and (scene.width, scene.height) == (40, 30)
    assert main(["inspect", str(out)]) == 0
    assert "views        3" in capsys.readouterr().out
    info = json.loads((out / "scene.json").read_text())
    assert info["name"] == "demo" and info["seed"] == 1 and info["views"] == 3
    cams = np.load(out / "cameras_sphere.npz")
    assert sorted(cams.files) == sorted([f"world_mat_{i}" for i in range(3)]
                                        + [f"scale_mat_{i}" for i in range(3)])


def test_synth_rejects_unknown_scene(tmp_path, capsys):
    assert main(["synth", "no-such-scene", str(tmp_path / "x"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "no-such-scene" in err and err.count("\n") == 1


def test_ground_truth_is_exact(tiny_scene):
    sdf = _world_sdf("demo")
    pts = torch.tensor(np.asarray(trimesh.load(tiny_scene / "gt_points.ply").vertices))
    assert sdf(pts).abs().max() < 1e-9
    mesh = trimesh.load(tiny_scene / "gt_mesh.ply")
    assert sdf(torch.tensor(np.asarray(mesh.vertices))).abs().max() < 1e-9
    assert len(mesh.faces) > 1000


def test_depth_maps_hit_the_surface_and_match_masks(tiny_scene):
    sdf = _world_sdf("demo")
    info = json.loads((tiny_scene / "scene.json").read_text())
    K = np.array(info["cameras"]["intrinsics"])
    c2w = np.array(info["cameras"]["c2w_world"])
    depth = np.load(tiny_scene / "gt_depth.npz")
    scene = load_scene(tiny_scene)
    H, W = scene.height, scene.width
    ys, xs = np.mgrid[0:H, 0:W]
    for i in (0, 5):
        D = depth[f"depth_{i}"]
        assert D.shape == (H, W) and D.dtype == np.float32
        hit = np.isfinite(D)
        cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(D)], -1)
        X = c2w[i, :3, 3] + (cam[hit] * D[hit, None].astype(np.float64)) @ c2w[i, :3, :3].T
        assert sdf(torch.tensor(X)).abs().max() < 0.05
        # camera-z depth of the hit point as the documented formula computes it
        _, z = camera_z_depth(np.load(tiny_scene / "cameras_sphere.npz")[f"world_mat_{i}"], X)
        np.testing.assert_allclose(z, D[hit], rtol=1e-4)
        mask = scene.masks[i].numpy() > 0.5
        assert (mask == hit).mean() > 0.95


def test_images_look_like_a_scene(tiny_scene):
    scene = load_scene(tiny_scene)
    img, m = scene.images.numpy(), scene.masks.numpy() > 0.5
    assert 0.05 < m.mean() < 0.6
    assert img[m].std(0).min() > 0.04  # textured object
    assert img[~m].std(0).min() > 0.02  # non-trivial backdrop
    # the object is fully in view: no foreground on the image border
    assert not m[:, 0].any() and not m[:, -1].any()
    assert not m[:, :, 0].any() and not m[:, :, -1].any()


def test_features_in_world_units(tiny_scene):
    feats = json.loads((tiny_scene / "features.json").read_text())["features"]
    kinds = {f["kind"] for f in feats}
    assert kinds == {"pit", "thin"}
    sm = load_scene(tiny_scene).scale_mat
    for f in feats:
        c = np.array(f["center"])
        assert np.linalg.norm(c - sm[:3, 3]) < sm[0, 0]  # inside the object sphere
        assert f["radius"] > 0


def test_pits_and_thin_small(tmp_path):
    out = make_scene("pits-and-thin", tmp_path / "p", views=3, width=96, height=72,
                     gt_voxel=2.5, point_spacing=3.0, progress=False)
    feats = json.loads((out / "features.json").read_text())["features"]
    assert sum(f["kind"] == "pit" for f in feats) >= 5
    assert sum(f["kind"] == "thin" for f in feats) >= 5
    info = validate_scene(out)
    assert info["views"] == 3 and info["warnings"] == []
    sdf = _world_sdf("pits-and-thin")
    pts = torch.tensor(np.asarray(trimesh.load(out / "gt_points.ply").vertices))
    assert sdf(pts).abs().max() < 1e-6
    # the thinnest rod (r = 1) is in the ground-truth mesh
    rod = [f for f in feats if f["name"] == "rod r1"][0]
    v = np.asarray(trimesh.load(out / "gt_mesh.ply").vertices)
    near = np.linalg.norm(v[:, :2] - np.array(rod["center"][:2]), axis=1) < 1.5
    assert near.sum() > 20


def test_mesh_input(tmp_path):
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    path = tmp_path / "box.ply"
    box.export(path)
    out = make_scene(str(path), tmp_path / "m", views=4, width=48, height=36,
                     point_spacing=4.0, progress=False)
    scene = load_scene(out)
    assert scene.n_views == 4 and scene.has_masks
    mesh = trimesh.load(out / "gt_mesh.ply")
    assert max(mesh.extents) == pytest.approx(250.0)
    pts = np.asarray(trimesh.load(out / "gt_points.ply").vertices)
    assert len(pts) > 100
    # points lie on the box's faces and reproject into every mask
    c, half = mesh.bounds.mean(0), mesh.extents / 2
    np.testing.assert_allclose(np.abs((pts - c) / half).max(1), 1.0, atol=1e-9)
    cams = np.load(out / "cameras_sphere.npz")
    for i in range(4):
        xy, _ = camera_z_depth(cams[f"world_mat_{i}"], pts)
        px = np.rint(xy).astype(int)
        m = scene.masks[i].numpy()
        pad = np.pad(m, 1)  # 1 px slack at anti-aliased edges
        hitm = np.maximum.reduce([pad[1 + dy:1 + dy + 36, 1 + dx:1 + dx + 48]
                                  for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        assert hitm[px[:, 1], px[:, 0]].mean() > 0.999


def test_newton_projection_converges():
    sdf = builtin_shape("pits-and-thin").sdf
    x = torch.randn(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 60
    x = x[sdf(x).abs() < 0.5]  # near the surface, as marching-cubes vertices are
    assert len(x) > 100
    p = project_to_surface(sdf, x, iters=12)
    assert sdf(p).abs().max() < 1e-9
    assert (p - x).norm(dim=-1).max() < 1.0


def test_same_seed_same_scene(tmp_path):
    a = make_scene("demo", tmp_path / "a", views=2, width=32, height=24, gt_voxel=6.0,
                   point_spacing=6.0, progress=False)
    b = make_scene("demo", tmp_path / "b", views=2, width=32, height=24, gt_voxel=6.0,
                   point_spacing=6.0, progress=False)
    sa, sb = load_scene(a), load_scene(b)
    torch.testing.assert_close(sa.images, sb.images)
    torch.testing.assert_close(sa.c2w, sb.c2w)


@pytest.mark.parametrize("name, features", [("cup", ("cavity floor", "cavity rod r3")),
                                            ("well", ("shaft floor", "shaft rod r2"))])
def test_the_held_out_scenes_build(tmp_path, name, features):
    """The pits issue's held-out objects render as scenes with their named features."""
    out = make_scene(name, tmp_path / "s", views=2, width=32, height=24, spp=1,
                     gt_voxel=4.0, point_spacing=4.0, progress=False)
    meta = json.loads((out / "scene.json").read_text())
    names = [f["name"] for f in json.loads((out / "features.json").read_text())["features"]]
    assert meta["name"] == name and set(features) <= set(names)


def test_first_hits_lie_on_the_true_surface_and_a_bad_depth_file_is_named(tiny_scene, tmp_path):
    """`first_hits` lifts gt_depth.npz through each camera: the points lie on the demo's
    analytic surface (placed at WORLD_OFFSET); misses stay NaN; a depth file with a map
    missing is refused by name."""
    from neus_l0.errors import NeusL0Error
    from neus_l0.evaluation.synthetic import first_hits
    from neus_l0.synthetic.shapes import Translated, builtin_shape

    pts, depth, projections = first_hits(tiny_scene)
    assert pts.shape == depth.shape + (3,) and len(projections) == len(depth)
    hit = np.isfinite(depth)
    assert hit.any() and (~hit).any() and np.isnan(pts[~hit]).all()
    sdf = Translated(builtin_shape("demo").sdf, WORLD_OFFSET)
    d = sdf(torch.tensor(pts[hit], dtype=torch.float64)).abs()
    assert float(torch.quantile(d, 0.99)) < 0.05
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in ("cameras_sphere.npz", "scene.json"):
        (bad / f).write_bytes((tiny_scene / f).read_bytes())
    with np.load(tiny_scene / "gt_depth.npz") as z:
        np.savez(bad / "gt_depth.npz", **{k: z[k] for k in list(z.files)[:-1]})
    with pytest.raises(NeusL0Error, match="gt_depth.npz"):
        first_hits(bad)
