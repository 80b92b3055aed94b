"""`neus-l0 colmap`: SfM on a synthetic scene's photos, --sparse text models, bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from neus_l0.cli import main
from neus_l0.data.cameras import decompose_projection
from neus_l0.errors import NeusL0Error
from neus_l0.experiments.photos_compare import compare_to_truth
from neus_l0.formats.neus import load_scene, validate_scene
from neus_l0.photos.sfm import check_models
from neus_l0.photos.sparse_io import SparseModel, read_model, write_text_model


@pytest.fixture(scope="module")
def photo_scene(tmp_path_factory):
    """A synthetic demo scene SfM registers reliably: 30 views at 400x300 (~25 s)."""
    from neus_l0.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("photos") / "demo"
    return make_scene("demo", out, views=30, width=400, height=300, seed=0, gt_voxel=3.0,
                      point_spacing=2.0, progress=False)


@pytest.fixture(scope="module")
def sfm_scene(photo_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("sfm") / "scene"
    assert main(["colmap", str(photo_scene / "image"), str(out), "--no-progress"]) == 0
    return out


def test_sfm_recovers_true_cameras(photo_scene, sfm_scene):
    errs = compare_to_truth(sfm_scene, photo_scene)
    assert len(errs["views"]) >= 27  # nearly every view registers
    assert errs["center_err_mean_rel"] < 0.01
    assert errs["rot_err_mean_deg"] < 1.0
    assert errs["gt_inside"] == 1.0  # the true surface lies inside the chosen sphere
    # ... and the sphere is not absurdly large
    assert errs["sphere_radius"] < 2.0 * errs["object_size"]


def test_sfm_scene_files(photo_scene, sfm_scene):
    info = validate_scene(sfm_scene)
    scene = load_scene(sfm_scene)
    sources = (sfm_scene / "sources.txt").read_text().split()
    missing = (sfm_scene / "unregistered.txt").read_text().split()
    assert len(sources) == scene.n_views == info["views"]
    assert sorted([Path(s).name for s in sources] + missing) == \
        sorted(p.name for p in (photo_scene / "image").iterdir())
    assert not info["warnings"]
    assert (sfm_scene / "sphere_preview.png").stat().st_size > 1000
    assert not (sfm_scene / "mask").exists()


def _true_text_model(scene_dir: Path, out: Path, views: list[int], n_points: int = 300):
    """COLMAP text model of the true cameras (world units) of `views`."""
    import trimesh

    data = np.load(scene_dir / "cameras_sphere.npz")
    names = sorted(p.name for p in (scene_dir / "image").iterdir())
    h, w = cv2.imread(str(scene_dir / "image" / names[0])).shape[:2]
    K, _ = decompose_projection(data["world_mat_0"])
    cams = {1: ("PINHOLE", w, h, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])}
    w2c = np.stack([np.linalg.inv(decompose_projection(data[f"world_mat_{i}"])[1])[:3]
                    for i in views])
    pts = np.asarray(trimesh.load(scene_dir / "gt_points.ply", process=False).vertices)
    pts = pts[np.random.default_rng(0).choice(len(pts), n_points, replace=False)]
    write_text_model(out, cams, [names[i] for i in views], np.ones(len(views), int), w2c, pts)
    return [data[f"world_mat_{i}"] for i in views]


def test_sparse_text_model_gives_true_cameras(tiny_scene, tmp_path):
    views = [0, 1, 2, 4, 5, 6, 7]  # view 3 left out: it must be reported, not dropped silently
    true_mats = _true_text_model(tiny_scene, tmp_path / "sparse", views)
    model = read_model(tmp_path / "sparse")
    assert model.n_views == len(views) and len(model.points) > 0
    out = tmp_path / "scene"
    assert main(["colmap", str(tiny_scene / "image"), str(out), "--sparse",
                 str(tmp_path / "sparse"), "--masks", str(tiny_scene / "mask"),
                 "--no-progress"]) == 0
    data = np.load(out / "cameras_sphere.npz")
    for k, wm in enumerate(true_mats):
        np.testing.assert_allclose(data[f"world_mat_{k}"][:3], wm[:3], rtol=1e-9, atol=1e-7)
    assert (out / "unregistered.txt").read_text().split() == ["003.png"]
    scene = load_scene(out)
    truth = load_scene(tiny_scene)
    sm, tm = scene.scale_mat, truth.scale_mat
    np.testing.assert_allclose(scene.intrinsics, truth.intrinsics[views], atol=1e-4)
    # camera centres agree in world units (the sphere normalisation undone)
    c_est = scene.c2w[:, :3, 3].double().numpy() * sm[0, 0] + sm[:3, 3]
    c_true = truth.c2w[views, :3, 3].double().numpy() * tm[0, 0] + tm[:3, 3]
    np.testing.assert_allclose(c_est, c_true, atol=1e-6 * tm[0, 0])
    np.testing.assert_allclose(scene.c2w[:, :3, :3], truth.c2w[views, :3, :3], atol=1e-5)
    # distortion-free cameras: images and masks come through unchanged
    np.testing.assert_array_equal(scene.images.numpy(), truth.images[views].numpy())
    assert scene.has_masks
    np.testing.assert_array_equal(scene.masks.numpy(), truth.masks[views].numpy())


def test_sphere_override(tiny_scene, tmp_path):
    _true_text_model(tiny_scene, tmp_path / "sparse", list(range(8)))
    out = tmp_path / "scene"
    assert main(["colmap", str(tiny_scene / "image"), str(out), "--sparse",
                 str(tmp_path / "sparse"), "--center", "1,2,3", "--radius", "150",
                 "--no-progress"]) == 0
    sm = load_scene(out).scale_mat
    np.testing.assert_allclose(sm[:3, 3], [1, 2, 3])
    assert sm[0, 0] == pytest.approx(150.0)


def _fails(argv, capsys, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for n in needles:
        assert str(n) in err, err
    return err


def _copy_photos(src: Path, dst: Path, n: int) -> Path:
    dst.mkdir(parents=True)
    for p in sorted((src / "image").iterdir())[:n]:
        shutil.copy(p, dst / p.name)
    return dst


def test_bad_photo_folders(tiny_scene, tmp_path, capsys):
    out = str(tmp_path / "out")
    _fails(["colmap", str(tmp_path / "nope"), out], capsys, "nope", "not found")
    (tmp_path / "empty").mkdir()
    _fails(["colmap", str(tmp_path / "empty"), out], capsys, "empty", "no photos")
    two = _copy_photos(tiny_scene, tmp_path / "two", 2)
    _fails(["colmap", str(two), out], capsys, "two", "at least 3")
    bad = _copy_photos(tiny_scene, tmp_path / "bad", 4)
    (bad / "002.png").write_bytes(b"not a png")
    _fails(["colmap", str(bad), out], capsys, "002.png", "unreadable")
    mixed = _copy_photos(tiny_scene, tmp_path / "mixed", 4)
    img = cv2.imread(str(mixed / "001.png"))
    cv2.imwrite(str(mixed / "001.png"), cv2.resize(img, (32, 24)))
    _fails(["colmap", str(mixed), out], capsys, "001.png", "differs")


def test_bad_sparse_and_options(tiny_scene, tmp_path, capsys):
    photos = str(tiny_scene / "image")
    out = str(tmp_path / "out")
    _fails(["colmap", photos, out, "--sparse", str(tmp_path)], capsys, "not a COLMAP")
    _true_text_model(tiny_scene, tmp_path / "two", [0, 5])
    _fails(["colmap", photos, out, "--sparse", str(tmp_path / "two")], capsys,
           "only 2 of 8", "overlap", "--matcher sequential", "--camera-model")
    _fails(["colmap", photos, out, "--radius", "2"], capsys, "--center")
    _fails(["colmap", photos, out, "--masks", str(tmp_path / "nomask")], capsys, "nomask")


def test_noise_photos_do_not_register(tmp_path, capsys):
    rng = np.random.default_rng(0)
    d = tmp_path / "noise"
    d.mkdir()
    for i in range(4):
        cv2.imwrite(str(d / f"{i}.png"), rng.integers(0, 255, (96, 128, 3), dtype=np.uint8))
    _fails(["colmap", str(d), str(tmp_path / "out"), "--no-progress"], capsys,
           str(d), "registered")


def _fake(names):
    n = len(names)
    return SparseModel(names=names, camera_ids=np.ones(n, int), cameras={},
                       w2c=np.zeros((n, 3, 4)), points=np.zeros((0, 3)),
                       track_len=np.zeros(0, int))


def test_check_models_rules():
    a = _fake([f"{i}.png" for i in range(10)])
    assert check_models([a], 12, "photos") is a
    overlapping = _fake(["0.png", "1.png", "2.png", "10.png"])  # shares views: not disjoint
    assert check_models([a, overlapping], 12, "photos") is a
    b = _fake([f"{i}.png" for i in range(10, 16)])
    with pytest.raises(NeusL0Error, match="2 disconnected models"):
        check_models([a, b], 16, "photos")
    with pytest.raises(NeusL0Error, match="only 10 of 30"):
        check_models([a], 30, "photos")
    with pytest.raises(NeusL0Error, match="registered no photos"):
        check_models([], 5, "photos")


def test_export_writes_the_sparse_points_and_their_box_holds_the_surface(tiny_scene, tmp_path):
    import torch

    from neus_l0.bounds.points import PointBound
    from neus_l0.bounds.sphere import sphere_chord
    from neus_l0.data.points import POINTS_FILE, read_points

    _true_text_model(tiny_scene, tmp_path / "sparse", list(range(8)))
    model = read_model(tmp_path / "sparse")
    out = tmp_path / "scene"
    assert main(["colmap", str(tiny_scene / "image"), str(out), "--sparse",
                 str(tmp_path / "sparse"), "--no-progress"]) == 0
    scene = load_scene(out)
    sm = np.asarray(scene.scale_mat)
    pts, track = read_points(out / POINTS_FILE, sm)
    np.testing.assert_allclose(pts * sm[0, 0] + sm[:3, 3], model.points, atol=1e-9)
    assert len(track) == len(model.points)
    box = PointBound.for_scene(scene, margin=0.2)
    gt = np.asarray(__import__("trimesh").load(tiny_scene / "gt_points.ply",
                                               process=False).vertices)
    gt = torch.as_tensor((gt - sm[:3, 3]) / sm[0, 0], dtype=torch.float32)  # (P, 3)
    assert bool(box.contains(gt).all())
    # every camera's ray through a true surface point keeps that point inside its bounds
    for v in range(scene.n_views):
        o = scene.c2w[v, :3, 3].expand(len(gt), 3)
        t = (gt - o).norm(dim=-1, keepdim=True)
        d = (gt - o) / t
        near, far, _ = sphere_chord(o, d)
        lo, hi, hits = box.ray_bounds(o, d, near, far)
        assert bool(hits.all()) and bool(((lo <= t + 1e-5) & (t <= hi + 1e-5)).all())
