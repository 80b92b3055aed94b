"""Bad scene folders: one clear `SceneError` line naming the file; `inspect` exits 2."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from neus_l0.cli import main
from neus_l0.errors import SceneError
from neus_l0.formats.neus import load_scene


def _edit_cameras(root, **changes):
    cams = dict(np.load(root / "cameras_sphere.npz"))
    for k, v in changes.items():
        if v is None:
            cams.pop(k)
        else:
            cams[k] = v
    np.savez(root / "cameras_sphere.npz", **cams)


def _expect(root, *fragments):
    with pytest.raises(SceneError) as info:
        load_scene(root)
    msg = str(info.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, msg
    return msg


def test_copy_is_valid(scene_copy):
    assert load_scene(scene_copy).n_views == 8


def test_missing_scene_folder(tmp_path):
    _expect(tmp_path / "nope", "nope", "not found")


def test_missing_image_folder(scene_copy):
    shutil.rmtree(scene_copy / "image")
    _expect(scene_copy, "image", "missing")


def test_no_camera_file(scene_copy):
    (scene_copy / "cameras_sphere.npz").unlink()
    _expect(scene_copy, "cameras_sphere.npz")


def test_an_image_without_its_mask_is_named(scene_copy):
    (scene_copy / "mask" / "007.png").unlink()
    _expect(scene_copy, "mask", "no mask for 007.png")


def test_unreadable_image(scene_copy):
    (scene_copy / "image" / "003.png").write_bytes(b"not a png")
    _expect(scene_copy, "003.png", "unreadable")


def test_differently_sized_image(scene_copy):
    cv2.imwrite(str(scene_copy / "image" / "004.png"), np.zeros((40, 64, 3), np.uint8))
    _expect(scene_copy, "004.png", "64x40", "64x48")


def test_differently_sized_mask(scene_copy):
    cv2.imwrite(str(scene_copy / "mask" / "002.png"), np.zeros((48, 60, 3), np.uint8))
    _expect(scene_copy, "mask/002.png", "60x48")


def test_missing_world_mat(scene_copy):
    _edit_cameras(scene_copy, world_mat_5=None)
    _expect(scene_copy, "cameras_sphere.npz", "world_mat_5")


def test_missing_scale_mat(scene_copy):
    _edit_cameras(scene_copy, scale_mat_6=None)
    _expect(scene_copy, "cameras_sphere.npz", "scale_mat_6")


def test_singular_projection(scene_copy):
    P = np.array(np.load(scene_copy / "cameras_sphere.npz")["world_mat_1"])
    P[1, :3] = P[0, :3]  # rank-deficient 3x3 block
    _edit_cameras(scene_copy, world_mat_1=P)
    _expect(scene_copy, "cameras_sphere.npz", "view 1", "singular")


def test_non_finite_camera(scene_copy):
    P = np.array(np.load(scene_copy / "cameras_sphere.npz")["world_mat_2"])
    P[0, 0] = np.nan
    _edit_cameras(scene_copy, world_mat_2=P)
    _expect(scene_copy, "world_mat_2", "non-finite")


def test_wrong_shape_camera(scene_copy):
    _edit_cameras(scene_copy, world_mat_0=np.eye(3))
    _expect(scene_copy, "world_mat_0", "shape")


def test_all_empty_mask(scene_copy):
    # one empty mask is true data (tests/cli/test_faults.py); all of them is an error
    for p in (scene_copy / "mask").iterdir():
        cv2.imwrite(str(p), np.full((48, 64, 3), 100, np.uint8))
    _expect(scene_copy, "000.png", "every mask is empty")


def test_unreadable_camera_file(scene_copy):
    (scene_copy / "cameras_sphere.npz").write_bytes(b"garbage")
    _expect(scene_copy, "cameras_sphere.npz", "unreadable")


def test_bad_downscale(scene_copy):
    with pytest.raises(SceneError, match="downscale"):
        load_scene(scene_copy, downscale=0)


def test_inspect_reports_one_line_and_exit_2(scene_copy, capsys):
    _edit_cameras(scene_copy, world_mat_3=None)
    assert main(["inspect", str(scene_copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "world_mat_3" in err and "cameras_sphere.npz" in err


def test_inspect_prints_summary(scene_copy, capsys):
    assert main(["inspect", str(scene_copy)]) == 0
    out = capsys.readouterr().out
    assert "views        8" in out and "64 x 48" in out and "sphere radius" in out
    assert main(["inspect", "--json", str(scene_copy)]) == 0
