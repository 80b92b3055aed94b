"""Bad scene files (issues #27 and #18) the NeuS reader (`neus_l0.formats.neus`) names in one
line: object arrays in the camera file, one view, truncated images, a view whose scale_mat
differs, empty masks.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from neus_l0.cli import main


def edit_cameras(root: Path, **changes) -> None:
    """Set (or, with None, drop) entries of the scene's cameras_sphere.npz."""
    cams = dict(np.load(root / "cameras_sphere.npz"))
    for key, value in changes.items():
        if value is None:
            cams.pop(key)
        else:
            cams[key] = value
    np.savez(root / "cameras_sphere.npz", **cams)


def _as_jpegs(root: Path) -> None:
    for p in sorted((root / "image").glob("*.png")):
        cv2.imwrite(str(p.with_suffix(".jpg")), cv2.imread(str(p)))
        p.unlink()


def test_object_arrays_in_the_camera_file_are_named(scene96_copy, train_cli, tmp_path, refused,
                                                    checkpoint_names):
    """A cameras_sphere.npz holding an object array: exit 2 naming the file and the key."""
    cams = dict(np.load(scene96_copy / "cameras_sphere.npz"))
    cams["world_mat_2"] = np.array([cams["world_mat_2"], "x"], dtype=object)
    np.savez(scene96_copy / "cameras_sphere.npz", **cams)
    refused(train_cli(scene96_copy, tmp_path / "run"),
            "cameras_sphere.npz", "'world_mat_2' is not a numeric matrix")
    assert checkpoint_names(tmp_path / "run") == []


def test_a_one_view_scene_trains_with_a_warning(scene96_copy, train_cli, tmp_path, capsys):
    """One view left: it trains, and one line says NeuS needs many views."""
    for folder in ("image", "mask"):
        for p in sorted((scene96_copy / folder).glob("*.png"))[1:]:
            p.unlink()
    assert main(train_cli(scene96_copy, tmp_path / "run", "train.iters=2")) == 0
    err = capsys.readouterr().err
    assert len([ln for ln in err.splitlines() if "one view only" in ln]) == 1


@pytest.mark.parametrize("kind, name, cut", [
    ("png", "003.png", 12), ("png", "003.png", 400), ("jpg", "005.jpg", None),
], ids=["png-without-IEND", "png-cut", "jpeg-cut"])
def test_a_truncated_image_is_named(scene96_copy, train_cli, tmp_path, capfd, kind, name, cut,
                                    error_line, checkpoint_names):
    """A PNG or JPEG cut short (OpenCV decodes a JPEG silently): exit 2 naming it, and no
    decoder noise on stderr."""
    if kind == "jpg":
        _as_jpegs(scene96_copy)
    p = scene96_copy / "image" / name
    data = p.read_bytes()
    p.write_bytes(data[:-cut] if cut else data[: len(data) // 2])
    rc = main(train_cli(scene96_copy, tmp_path / "run", "train.iters=2"))
    err = capfd.readouterr().err
    assert rc == 2
    error_line(err, "train", f"{p}: truncated {'PNG' if kind == 'png' else 'JPEG'}")
    assert "libpng" not in err and "Premature end" not in err
    assert checkpoint_names(tmp_path / "run") == []


def test_a_view_whose_scale_mat_differs_is_named(scene96_copy, train_cli, tmp_path, refused):
    """One view's sphere moved: exit 2 naming the view and the first."""
    s = np.load(scene96_copy / "cameras_sphere.npz")["scale_mat_4"].copy()
    s[:3, 3] += 1.0
    edit_cameras(scene96_copy, scale_mat_4=s)
    refused(train_cli(scene96_copy, tmp_path / "run"), "cameras_sphere.npz",
            "scale_mat_4 differ from scale_mat_0")


def test_18_6_one_empty_mask_warns_and_all_empty_is_an_error(scene96_copy, train_cli, tmp_path,
                                                             capsys, refused, checkpoint_names):
    """One empty mask: a one-line warning naming it, training goes on; every mask empty:
    exit 2."""
    blank = np.zeros((72, 96, 3), np.uint8)
    cv2.imwrite(str(scene96_copy / "mask" / "005.png"), blank)
    assert main(train_cli(scene96_copy, tmp_path / "run", "train.iters=2")) == 0
    warned = [ln for ln in capsys.readouterr().err.splitlines() if "masks are empty" in ln]
    assert len(warned) == 1 and "005.png" in warned[0] and "1 of 8" in warned[0]
    for p in (scene96_copy / "mask").iterdir():
        cv2.imwrite(str(p), blank)
    refused(train_cli(scene96_copy, tmp_path / "run2", "train.iters=2"),
            "every mask is empty")
    assert checkpoint_names(tmp_path / "run2") == []
