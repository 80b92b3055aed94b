"""transforms.json scenes (NeRF-synthetic, instant-ngp, nerfstudio), RGBA images, the object
sphere of formats that give none, undistortion, and the one-line errors.

The small demo scene (`tiny_scene`: 8 views, 64x48) is exported by `tools/export_transforms.py`
(run as a script) into each kind, in a rotated, rescaled and translated world frame; loading
the export must give the NeuS-format twin's rays mapped through that similarity.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh

from neus_l0.cli import main
from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.errors import SceneError
from neus_l0.formats.neus import load_scene
from neus_l0.formats.open import open_scene
from neus_l0.formats.transforms import load_views, read_transforms

TOOL = Path(__file__).resolve().parents[2] / "tools" / "export_transforms.py"
MOVE = ["--rotate", "40", "--scale", "0.01", "--translate", "1", "2", "-3"]
#: kind -> the exporter's extra arguments (nerfstudio: mask_path files; the others: RGBA).
KINDS = {"nerfstudio": [], "ngp": ["--rgba"], "blender": ["--rgba", "--holdout", "4"]}
QUIET = {"log": lambda line: None}


def _export(scene: Path, out: Path, kind: str, *extra: str) -> Path:
    r = subprocess.run([sys.executable, str(TOOL), str(scene), str(out), "--kind", kind,
                        *MOVE, *extra], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="module")
def exported(tiny_scene, tmp_path_factory):
    """kind -> (folder, new_to_original (4, 4)) of the three exports."""
    base = tmp_path_factory.mktemp("transforms")
    out = {}
    for kind, extra in KINDS.items():
        folder = _export(tiny_scene, base / kind, kind, *extra)
        sim = json.loads((folder / "similarity.json").read_text())
        out[kind] = folder, np.array(sim["new_to_original"])
    return out


@pytest.fixture(scope="module")
def opened(exported):
    """kind -> the loaded export (the nerfstudio one writes its sphere preview)."""
    return {kind: open_scene(folder, preview=kind == "nerfstudio", **QUIET)
            for kind, (folder, _) in exported.items()}


@pytest.fixture(scope="module")
def twin(tiny_scene):
    return load_scene(tiny_scene)


def _view_index(name: str) -> int:
    """The twin's view of an exported image name (frame_00003.png -> 2, r_5.png -> 5)."""
    stem = Path(name).stem
    return int(stem.split("_")[-1]) - (1 if stem.startswith("frame_") else 0)


def _world_rays(scene, view: int, K: torch.Tensor | None = None):
    """Origins (world units) and unit directions of every pixel of a view, float64."""
    xy = pixel_grid(scene.height, scene.width).reshape(-1, 2).double()
    Kv = (scene.intrinsics[view] if K is None else K).double()
    o, d = pixel_rays(Kv.expand(len(xy), 3, 3), scene.c2w[view].double().expand(len(xy), 4, 4),
                      xy)
    S = torch.from_numpy(scene.scale_mat)
    return o @ S[:3, :3].T + S[:3, 3], d


def _object(tiny_scene):
    v = np.asarray(trimesh.load(tiny_scene / "gt_mesh.ply", process=False).vertices)
    centre = 0.5 * (v.min(0) + v.max(0))
    return v, float(np.linalg.norm(v - centre, axis=1).max())


# --- the three kinds against the NeuS-format twin ------------------------------------------


@pytest.mark.parametrize("kind", list(KINDS))
def test_rays_match_the_neus_twin(kind, opened, exported, twin):
    scene, (_, back) = opened[kind], exported[kind]
    T = torch.from_numpy(back)
    s = torch.linalg.det(T[:3, :3]).abs() ** (1.0 / 3.0)
    assert scene.n_views == (6 if kind == "blender" else 8)
    for v, name in enumerate(scene.image_names):
        t = _view_index(name)
        K = twin.intrinsics[t].clone()
        if kind == "blender":  # the exporter centred the principal point (shifting the image)
            K[0, 2], K[1, 2] = (twin.width - 1) / 2, (twin.height - 1) / 2
        torch.testing.assert_close(scene.intrinsics[v], K, atol=1e-4, rtol=0)
        o, d = _world_rays(scene, v)
        o_ref, d_ref = _world_rays(twin, t, K)
        torch.testing.assert_close(o @ T[:3, :3].T + T[:3, 3], o_ref, atol=1e-3, rtol=0)
        torch.testing.assert_close(d @ (T[:3, :3] / s).T, d_ref, atol=1e-5, rtol=0)


@pytest.mark.parametrize("kind", list(KINDS))
def test_sphere_holds_the_object_and_is_tight(kind, opened, exported, tiny_scene):
    scene, (_, back) = opened[kind], exported[kind]
    to_new = np.linalg.inv(back)
    verts, r_obj = _object(tiny_scene)
    s = float(np.cbrt(np.linalg.det(to_new[:3, :3])))
    v_new = verts @ to_new[:3, :3].T + to_new[:3, 3]
    sm = scene.scale_mat
    radius = float(sm[0, 0])
    assert np.linalg.norm(v_new - sm[:3, 3], axis=1).max() < radius
    assert radius < 2.0 * s * r_obj  # not absurdly large (measured: about 1.5x)
    assert float(scene.c2w[:, :3, 3].norm(dim=-1).min()) > 1.0  # cameras outside
    assert scene.info["sphere"]["method"] == "visual hull"


def test_masks_and_images_come_from_mask_path_or_alpha(opened, twin):
    ns, ngp = opened["nerfstudio"], opened["ngp"]
    assert ns.info["masks"] == "mask_path" and ngp.info["masks"] == "alpha"
    assert ns.has_masks and ngp.has_masks
    torch.testing.assert_close(ns.masks, twin.masks)
    torch.testing.assert_close(ngp.masks, twin.masks)
    torch.testing.assert_close(ns.images, twin.images)
    # RGBA: colour composited over black
    torch.testing.assert_close(ngp.images, twin.images * twin.masks[..., None], atol=1e-6, rtol=0)


def test_meshes_come_out_in_the_input_world_frame(opened, exported, tiny_scene, sphere_model):
    """A field's mesh (here a ball of radius 0.5 in the normalised frame) meshed with the
    loaded scene's scale_mat is in the file's world frame: mapped back by the similarity, the
    twin's own cameras see its vertices where the loaded cameras see the ball."""
    from neus_l0.data.cameras import read_world_mats
    from neus_l0.mesh.extract import extract_mesh

    scene, (_, back) = opened["nerfstudio"], exported["nerfstudio"]
    mesh = extract_mesh(sphere_model(), scene.scale_mat, resolution=32, clean=False,
                        method="dense")
    v_new = np.asarray(mesh.vertices)
    sm = scene.scale_mat
    np.testing.assert_allclose(np.linalg.norm(v_new - sm[:3, 3], axis=1), 0.5 * sm[0, 0],
                               rtol=0.02)
    v_orig = v_new @ back[:3, :3].T + back[:3, 3]
    v_norm = (v_new - sm[:3, 3]) / sm[0, 0]
    P_twin = read_world_mats(tiny_scene)
    for v, name in enumerate(scene.image_names):
        h = v_orig @ P_twin[_view_index(name)][:, :3].T + P_twin[_view_index(name)][:, 3]
        c2w = scene.c2w[v].double().numpy()
        cam = (v_norm - c2w[:3, 3]) @ c2w[:3, :3]
        g = cam @ scene.intrinsics[v].double().numpy().T
        np.testing.assert_allclose(g[:, :2] / g[:, 2:], h[:, :2] / h[:, 2:], atol=1e-3)


def test_splits_share_the_train_sphere(opened, exported):
    folder, _ = exported["blender"]
    test = open_scene(folder, split="test", preview=False, **QUIET)
    assert test.image_names == ["test/r_0.png", "test/r_4.png"]
    np.testing.assert_array_equal(test.scale_mat, opened["blender"].scale_mat)
    assert test.info["split"] == "test"
    with pytest.raises(SceneError, match="no val split|transforms_val"):
        open_scene(exported["ngp"][0], split="val", preview=False, **QUIET)


def test_preview_and_inspect(opened, exported, capsys):
    folder, _ = exported["nerfstudio"]
    assert (folder / "sphere_preview.png").is_file()
    assert opened["nerfstudio"].info["preview"] == str(folder / "sphere_preview.png")
    assert main(["inspect", str(exported["ngp"][0])]) == 0
    out = capsys.readouterr().out
    assert "instant-ngp transforms.json" in out and "sphere from  visual hull" in out
    assert "from images' alpha" in out


# --- without masks: SfM points or the cameras' look-at point ---------------------------------


def _nerfstudio_copy(src: Path, dst: Path, edit) -> Path:
    shutil.copytree(src, dst)
    data = json.loads((dst / "transforms.json").read_text())
    edit(data)
    (dst / "transforms.json").write_text(json.dumps(data))
    return dst


def test_without_masks_points_or_cameras(exported, tiny_scene, tmp_path):
    src, back = exported["nerfstudio"]
    to_new = np.linalg.inv(back)
    verts, _ = _object(tiny_scene)
    pts = np.asarray(trimesh.load(tiny_scene / "gt_points.ply", process=False).vertices)
    pts_new = pts @ to_new[:3, :3].T + to_new[:3, 3]
    v_new = verts @ to_new[:3, :3].T + to_new[:3, 3]

    def no_masks(d):
        for f in d["frames"]:
            f.pop("mask_path")

    def with_points(d):
        no_masks(d)
        d["ply_file_path"] = "sparse_pc.ply"

    bare = _nerfstudio_copy(src, tmp_path / "bare", no_masks)
    sfm = _nerfstudio_copy(src, tmp_path / "sfm", with_points)
    trimesh.PointCloud(pts_new).export(sfm / "sparse_pc.ply")
    for folder, method in ((bare, "cameras"), (sfm, "SfM points")):
        scene = open_scene(folder, preview=False, **QUIET)
        assert not scene.has_masks and scene.info["sphere"]["method"] == method
        sm = scene.scale_mat
        assert np.linalg.norm(v_new - sm[:3, 3], axis=1).max() < sm[0, 0], method
        assert float(scene.c2w[:, :3, 3].norm(dim=-1).min()) > 1.0


def test_hull_cut_by_the_sphere_is_an_error_and_sphere_json_overrides(exported, tmp_path):
    """All-white masks: the hull fills the search sphere -> one-line error naming the file;
    a sphere.json next to it is used instead."""
    src, _ = exported["nerfstudio"]
    folder = tmp_path / "white"
    shutil.copytree(src, folder)
    for p in (folder / "masks").iterdir():
        cv2.imwrite(str(p), np.full((48, 64), 255, np.uint8))
    with pytest.raises(SceneError) as info:
        open_scene(folder, preview=False, **QUIET)
    msg = str(info.value)
    assert "\n" not in msg and "transforms.json" in msg and "reaches the search sphere" in msg
    assert "sphere.json" in msg
    (folder / "sphere.json").write_text(json.dumps({"center": [1.4, 2.0, -2.8], "radius": 2.0}))
    scene = open_scene(folder, preview=False, **QUIET)
    assert scene.info["sphere"]["method"] == "sphere.json" and scene.scale_mat[0, 0] == 2.0


# --- RGBA in NeuS format ----------------------------------------------------------------------


def test_rgba_neus_format_gives_the_masks(tiny_scene, tmp_path, capsys):
    root = tmp_path / "rgba"
    (root / "image").mkdir(parents=True)
    shutil.copy(tiny_scene / "cameras_sphere.npz", root)
    for p in sorted((tiny_scene / "image").glob("*.png")):
        mask = cv2.imread(str(tiny_scene / "mask" / p.name), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(root / "image" / p.name), np.dstack([cv2.imread(str(p)), mask]))
    for s in (1, 2):
        ref, got = load_scene(tiny_scene, downscale=s), open_scene(root, downscale=s)
        assert got.has_masks and got.info["masks"] == "alpha"
        torch.testing.assert_close(got.masks, ref.masks)
        if s == 1:
            torch.testing.assert_close(got.images, ref.images * ref.masks[..., None])
    err = capsys.readouterr().err
    assert "alpha" in err and len(err.strip().splitlines()) == 2  # one line per load
    # opaque alpha everywhere carries no mask
    for p in sorted((root / "image").glob("*.png")):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        img[..., 3] = 255
        cv2.imwrite(str(p), img)
    assert not load_scene(root).has_masks


# --- undistortion -----------------------------------------------------------------------------


def _pattern(x, y):
    return 0.5 + 0.4 * np.sin(x / 5.0) * np.cos(y / 7.0)


def _one_view_scene(root: Path, camera: dict, image: np.ndarray | None = None,
                    frame: dict | None = None) -> Path:
    (root / "images").mkdir(parents=True, exist_ok=True)
    if image is None:
        image = np.zeros((24, 32, 3), np.uint8)
    cv2.imwrite(str(root / "images" / "a.png"), image)
    f = {"file_path": "images/a", "transform_matrix": np.eye(4).tolist()}
    f.update(frame or {})
    (root / "transforms.json").write_text(json.dumps({**camera, "frames": [f]}))
    return root


def test_opencv_distortion_is_undistorted(tmp_path):
    """A pattern drawn through a known OPENCV camera comes back as the pinhole camera's."""
    W, H = 96, 72
    K = np.array([[80.0, 0.0, 47.3], [0.0, 80.0, 35.6], [0.0, 0.0, 1.0]])
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])  # k1 k2 p1 p2 k3
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    pix = np.stack([xs.ravel(), ys.ravel()], -1)[:, None, :]
    und = cv2.undistortPoints(pix, K, dist, P=K).reshape(H, W, 2)
    D = _pattern(und[..., 0], und[..., 1])  # the distorted photo of the pinhole pattern
    img = np.round(np.repeat(D[..., None], 3, -1) * 65535).astype(np.uint16)
    cam = {"camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5,
           "cy": K[1, 2] + 0.5, "w": W, "h": H, "k1": dist[0], "k2": dist[1], "p1": dist[2],
           "p2": dist[3]}
    views = load_views(read_transforms(_one_view_scene(tmp_path, cam, img)))
    assert "undistorted 1 of 1 views (OPENCV k1 -0.2" in views.undistorted
    K_new = views.intrinsics[0]
    src = (K @ np.linalg.inv(K_new) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])).T
    expected = _pattern(src[:, 0], src[:, 1]).reshape(H, W)
    err = np.abs(views.images[0, ..., 0] - expected)[2:-2, 2:-2]
    assert err.mean() < 0.003 and np.abs(D - _pattern(xs, ys)).mean() > 0.03


# --- bad inputs: one line naming the file -----------------------------------------------------


def _refused(root: Path, *fragments: str) -> None:
    with pytest.raises(SceneError) as info:
        load_views(read_transforms(root))
    msg = str(info.value)
    assert "\n" not in msg, msg
    for f in fragments:
        assert f in msg, msg


CAM = {"fl_x": 30.0, "w": 32, "h": 24}


@pytest.mark.parametrize("camera, frame, fragments", [
    ({"w": 32, "h": 24}, {}, ("transforms.json", "no focal length", "fl_x")),
    (CAM, {"transform_matrix": "nope"}, ("transforms.json", "frame 0", "transform_matrix")),
    (CAM, {"file_path": "images/missing"}, ("transforms.json", "images/missing", "not found")),
    ({**CAM, "camera_model": "OPENCV_FISHEYE", "k1": 0.1}, {},
     ("transforms.json", "OPENCV_FISHEYE", "not supported")),
    ({**CAM, "camera_model": "OPENCV", "k4": 0.01}, {}, ("transforms.json", "k4")),
    ({**CAM, "w": 40}, {}, ("a.png", "32x24", "40x24")),
])
def test_bad_transforms_are_one_line_errors(tmp_path, camera, frame, fragments):
    _refused(_one_view_scene(tmp_path, camera, frame=frame), *fragments)


def test_missing_frames_and_unknown_folders(tmp_path, capsys):
    root = _one_view_scene(tmp_path / "s", CAM)
    (root / "transforms.json").write_text(json.dumps(CAM))
    _refused(root, "transforms.json", "frames")
    (root / "transforms.json").write_text("{not json")
    _refused(root, "transforms.json", "JSON")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["inspect", str(empty)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "image/" in err and "transforms.json" in err
