"""The NeuS-format loader and camera rays: round trips against the synthetic renderer's
cameras, reprojection into masks, rays through known points, downscale consistency, DTU."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import torch
import trimesh

from neus_l0.data.cameras import camera_z_depth, decompose_projection
from neus_l0.data.rays import image_rays, pixel_rays, random_rays
from neus_l0.formats.neus import load_scene, validate_scene


def _point_ray_distance(o, d, x):
    v = x - o
    return (v - (v * d).sum(-1, keepdim=True) * d).norm(dim=-1)


def test_loads_poses_and_intrinsics_that_rendered_it(tiny_scene):
    scene = load_scene(tiny_scene)
    info = json.loads((tiny_scene / "scene.json").read_text())
    K = np.array(info["cameras"]["intrinsics"])
    c2w_world = np.array(info["cameras"]["c2w_world"])
    assert scene.n_views == info["views"] == 8
    assert (scene.height, scene.width) == (48, 64)
    assert scene.has_masks
    assert scene.images.dtype == torch.float32 and scene.images.shape == (8, 48, 64, 3)
    assert scene.masks.shape == (8, 48, 64)
    assert scene.image_names == [f"{i:03d}.png" for i in range(8)]
    np.testing.assert_allclose(scene.intrinsics.numpy(), np.broadcast_to(K, (8, 3, 3)),
                               rtol=1e-5, atol=1e-3)
    sm = scene.scale_mat
    r, c = sm[0, 0], sm[:3, 3]
    np.testing.assert_allclose(info["sphere"]["radius"], r)
    c2w = scene.c2w.double().numpy()
    np.testing.assert_allclose(c2w[:, :3, :3], c2w_world[:, :3, :3], atol=1e-5)
    np.testing.assert_allclose(c2w[:, :3, 3] * r + c, c2w_world[:, :3, 3], atol=1e-2)
    # every camera sits outside the unit sphere and looks at its centre
    assert (np.linalg.norm(c2w[:, :3, 3], axis=-1) > 3.5).all()


def test_gt_points_reproject_inside_masks(tiny_scene):
    scene = load_scene(tiny_scene)
    pts = np.asarray(trimesh.load(tiny_scene / "gt_points.ply").vertices)
    assert len(pts) > 1000
    cams = np.load(tiny_scene / "cameras_sphere.npz")
    kernel = np.ones((3, 3), np.uint8)
    for i in range(scene.n_views):
        xy, z = camera_z_depth(cams[f"world_mat_{i}"], pts)
        assert (z > 0).all()
        px = np.rint(xy).astype(int)
        inside = ((px[:, 0] >= 0) & (px[:, 0] < scene.width) & (px[:, 1] >= 0)
                  & (px[:, 1] < scene.height))
        assert inside.all(), "the object must be fully in view"
        # projections of surface points lie in the silhouette (1 px slack for anti-aliasing)
        mask = cv2.dilate(scene.masks[i].numpy().astype(np.uint8), kernel) > 0
        assert mask[px[:, 1], px[:, 0]].mean() > 0.999


def test_pixel_rays_pass_through_projected_points():
    g = np.random.default_rng(0)
    B = 64
    Ks, c2ws, X, xy = [], [], [], []
    for _ in range(B):
        K = np.array([[g.uniform(200, 900), g.uniform(-1, 1), g.uniform(100, 300)],
                      [0, g.uniform(200, 900), g.uniform(80, 200)], [0, 0, 1]])
        q = np.linalg.qr(g.normal(size=(3, 3)))[0]
        q *= np.sign(np.linalg.det(q))
        c2w = np.eye(4)
        c2w[:3, :3] = q
        c2w[:3, 3] = g.normal(size=3) * 4
        x = c2w[:3, 3] + q @ np.array([g.uniform(-1, 1), g.uniform(-1, 1), g.uniform(2, 6)])
        h = K @ (np.linalg.inv(c2w) @ np.append(x, 1.0))[:3]
        Ks.append(K), c2ws.append(c2w), X.append(x), xy.append(h[:2] / h[2])
    Ks, c2ws, X, xy = (torch.tensor(np.array(a)) for a in (Ks, c2ws, X, xy))
    o, d = pixel_rays(Ks, c2ws, xy)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(B, dtype=d.dtype))
    assert _point_ray_distance(o, d, X).max() < 1e-9
    assert ((X - o) * d).sum(-1).min() > 0  # in front of the camera
    # shared K / pose broadcast like per-ray ones
    o1, d1 = pixel_rays(Ks[0], c2ws[0], xy[:5])
    o2, d2 = pixel_rays(Ks[:1].expand(5, 3, 3), c2ws[:1].expand(5, 4, 4), xy[:5])
    torch.testing.assert_close(d1, d2)


def test_decompose_recovers_k_and_pose():
    K = np.array([[700.0, 0.5, 190.0], [0, 710.0, 160.0], [0, 0, 1]])
    q = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    q *= np.sign(np.linalg.det(q))
    C = np.array([1.0, -2.0, 3.5])
    P = K @ np.hstack([q, (-q @ C)[:, None]])
    K2, c2w = decompose_projection(7.5 * P)  # any positive scale
    np.testing.assert_allclose(K2, K, atol=1e-8)
    np.testing.assert_allclose(c2w[:3, :3], q.T, atol=1e-10)
    np.testing.assert_allclose(c2w[:3, 3], C, atol=1e-10)


def test_image_and_random_rays_agree_with_images(tiny_scene):
    scene = load_scene(tiny_scene)
    o, d = image_rays(scene, 3)
    assert o.shape == d.shape == (48, 64, 3)
    g = torch.Generator().manual_seed(0)
    batch = random_rays(scene, 500, g)
    assert batch["origins"].shape == batch["dirs"].shape == batch["rgb"].shape == (500, 3)
    assert batch["mask"].shape == (500, 1)
    v, xy = batch["view"], batch["xy"]
    torch.testing.assert_close(batch["rgb"], scene.images[v, xy[:, 1], xy[:, 0]])
    sel = v == 3
    torch.testing.assert_close(batch["dirs"][sel], d[xy[sel, 1], xy[sel, 0]])
    again = random_rays(scene, 500, torch.Generator().manual_seed(0))
    torch.testing.assert_close(again["dirs"], batch["dirs"])
    # foreground rays hit the unit sphere
    fg = batch["mask"][:, 0] > 0.5
    assert fg.any()
    assert _point_ray_distance(batch["origins"][fg], batch["dirs"][fg],
                               torch.zeros(3)).max() < 1.0


def test_downscale_keeps_rays_consistent(tiny_scene):
    full = load_scene(tiny_scene)
    half = load_scene(tiny_scene, downscale=2)
    assert (half.height, half.width) == (24, 32)
    # the ray through a downscaled pixel centre is the ray through the centre of its block
    j = torch.tensor([[0.0, 0.0], [5.0, 7.0], [31.0, 23.0], [12.5, 3.25]])
    o1, d1 = pixel_rays(half.intrinsics[2], half.c2w[2], j)
    o2, d2 = pixel_rays(full.intrinsics[2], full.c2w[2], 2 * j + 0.5)
    torch.testing.assert_close(d1, d2)
    # pixel values are the block means (colour and ray describe the same footprint)
    block = full.images[2].reshape(24, 2, 32, 2, 3).mean(dim=(1, 3))
    torch.testing.assert_close(half.images[2], block, atol=1e-6, rtol=0)
    # a ground-truth point seen through a downscaled pixel's ray: the ray passes through it
    pts = np.asarray(trimesh.load(tiny_scene / "gt_points.ply").vertices)[:200]
    sm = half.scale_mat
    Xn = torch.tensor((pts - sm[:3, 3]) / sm[0, 0], dtype=torch.float32)
    w2c = torch.linalg.inv(half.c2w[2])
    h = (half.intrinsics[2] @ (w2c[:3, :3] @ Xn.T + w2c[:3, 3:])).T
    xy = h[:, :2] / h[:, 2:]
    o, d = pixel_rays(half.intrinsics[2], half.c2w[2], xy)
    assert _point_ray_distance(o, d, Xn).max() < 1e-4
    # and it lands where the full-res projection says, mapped by x_old = 2 x_new + 0.5
    hf = (full.intrinsics[2] @ (w2c[:3, :3] @ Xn.T + w2c[:3, 3:])).T
    torch.testing.assert_close(2 * xy + 0.5, hf[:, :2] / hf[:, 2:], atol=1e-3, rtol=0)
    # soft masks stay in [0, 1] and cover the same area
    assert 0 <= half.masks.min() and half.masks.max() <= 1
    assert abs(half.masks.mean() - full.masks.mean()) < 1e-5


def test_scene_without_masks_and_legacy_dtu_names(tiny_scene, tmp_path):
    root = tmp_path / "s"
    shutil.copytree(tiny_scene / "image", root / "image")
    # DTU names images 000000.png and masks 000.png: paired by sorted order
    for p in sorted((root / "image").iterdir()):
        p.rename(p.with_name(f"{int(p.stem):06d}.png"))
    cams = dict(np.load(tiny_scene / "cameras_sphere.npz"))
    cams.update({f"camera_mat_{i}": np.eye(4) for i in range(8)})  # extra keys: ignored
    cams.update({f"world_mat_inv_{i}": np.eye(4) for i in range(8)})
    np.savez(root / "cameras.npz", **cams)  # IDR's legacy name
    s = load_scene(root)
    assert not s.has_masks and bool((s.masks == 1).all())
    assert s.image_names[0] == "000000.png"
    ref = load_scene(tiny_scene)
    torch.testing.assert_close(s.c2w, ref.c2w)
    shutil.copytree(tiny_scene / "mask", root / "mask")
    s2 = load_scene(root)
    assert s2.has_masks
    torch.testing.assert_close(s2.masks, ref.masks)


def test_scene_to_device(tiny_scene):
    s = load_scene(tiny_scene).to("cpu")
    assert s.images.device.type == "cpu"
    assert s.device.type == "cpu"


def test_validate_summary(tiny_scene):
    info = validate_scene(tiny_scene)
    assert info["views"] == 8 and info["width"] == 64 and info["height"] == 48
    assert info["has_masks"] and 0.05 < info["mask_coverage"]["mean"] < 0.6
    assert info["sphere_radius"] == pytest.approx(
        json.loads((tiny_scene / "scene.json").read_text())["sphere"]["radius"])
    assert 3.5 < info["camera_distance"]["min"] <= info["camera_distance"]["max"] < 5
    assert info["warnings"] == []


def test_dtu_cameras_look_at_unit_sphere(shared_data):
    scene = load_scene(shared_data("dtu_scan65"))
    assert scene.n_views == 49 and scene.has_masks
    centres = scene.c2w[:, :3, 3].double()
    axes = scene.c2w[:, :3, 2].double()
    assert (centres.norm(dim=-1) > 1.5).all()
    assert _point_ray_distance(centres, axes, torch.zeros(3, dtype=torch.float64)).max() < 0.6
    assert ((-centres * axes).sum(-1) > 0).all()  # the origin is in front
    # foreground pixels' rays hit the unit sphere
    batch = random_rays(scene, 4000, torch.Generator().manual_seed(1))
    fg = batch["mask"][:, 0] > 0.5
    assert _point_ray_distance(batch["origins"][fg], batch["dirs"][fg],
                               torch.zeros(3)).max() < 1.0
