"""What a run checks before its first step (issue #27 item 2): images that decode fully,
one sphere for every view, numeric camera arrays, an object that fits the unit sphere, a
writable run folder with room, and a resume on the run's own scene."""

import dataclasses

import numpy as np
import pytest

from neus_l0.bounds.hull import hull_from_scene
from neus_l0.bounds.static import CUT_SHELL, shell_fraction
from neus_l0.config.load import load_config
from neus_l0.errors import NeusL0Error, SceneError
from neus_l0.formats.neus import load_scene
from neus_l0.train.loop import train
from neus_l0.train.preflight import check_writable, scene_fingerprint


def _cameras(root, **edit):
    path = root / "cameras_sphere.npz"
    data = dict(np.load(path))
    data.update(edit)
    np.savez(path, **data)


@pytest.mark.parametrize("cut", [12, 400])
def test_a_truncated_png_is_named(scene_copy, cut):
    """libpng refuses a cut PNG (unreadable); a JPEG cut short is what OpenCV decodes
    silently (next test)."""
    p = scene_copy / "image" / "003.png"
    p.write_bytes(p.read_bytes()[:-cut])
    with pytest.raises(SceneError, match=r"003\.png: (unreadable image|truncated PNG)"):
        load_scene(scene_copy)


def test_a_truncated_jpeg_is_named(scene_copy):
    import cv2

    for p in sorted((scene_copy / "image").glob("*.png")):
        img = cv2.imread(str(p))
        cv2.imwrite(str(p.with_suffix(".jpg")), img)
        p.unlink()
    assert load_scene(scene_copy).n_views == 8  # whole JPEGs load
    p = scene_copy / "image" / "005.jpg"
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(SceneError, match=r"005\.jpg: truncated JPEG"):
        load_scene(scene_copy)


def test_views_with_another_sphere_are_named(scene_copy):
    s = np.load(scene_copy / "cameras_sphere.npz")["scale_mat_4"].copy()
    s[:3, 3] += 1.0
    _cameras(scene_copy, scale_mat_4=s)
    with pytest.raises(SceneError, match=r"scale_mat_4 differ from scale_mat_0"):
        load_scene(scene_copy)


def test_object_arrays_in_the_camera_file_are_refused(scene_copy):
    path = scene_copy / "cameras_sphere.npz"
    data = dict(np.load(path))
    data["world_mat_2"] = np.array([data["world_mat_2"], "x"], dtype=object)
    np.savez(path, **data)
    with pytest.raises(SceneError, match=r"'world_mat_2' is not a numeric matrix"):
        load_scene(scene_copy)


def test_an_object_the_sphere_cuts_is_refused_before_training(tmp_path):
    """The demo object with its sphere halved: the hull fills the sphere's outer shell."""
    from neus_l0.synthetic.scene import make_scene

    root = make_scene("demo", tmp_path / "demo", views=12, width=120, height=90, seed=0,
                      gt_voxel=4.0, point_spacing=2.0, progress=False)
    fits = shell_fraction(hull_from_scene(load_scene(root)))
    path = root / "cameras_sphere.npz"
    data = dict(np.load(path))
    for k in [k for k in data if k.startswith("scale_mat_")]:
        m = data[k].copy()
        m[:3, :3] *= 0.5
        data[k] = m
    np.savez(path, **data)
    scene = load_scene(root)
    cut = shell_fraction(hull_from_scene(scene))
    assert fits < CUT_SHELL < cut, (fits, cut)
    cfg = load_config("demo", ["train.iters=2"])
    with pytest.raises(SceneError, match=r"does not fit its unit sphere: .* fills \d+%"):
        train(scene, cfg, tmp_path / "run", progress=False)


def test_an_unwritable_run_folder_is_named(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("in the way")
    with pytest.raises(NeusL0Error, match=r"file/run: cannot write there"):
        check_writable(blocker / "run", 0)


def test_too_little_disk_is_refused_with_the_numbers(tmp_path):
    with pytest.raises(NeusL0Error, match=r"MB free on its disk, but the checkpoints need"):
        check_writable(tmp_path / "run", 1 << 60)


def test_resume_on_another_scene_is_refused(small, sphere_scene, tmp_path):
    a = sphere_scene(tmp_path / "a")
    b = dataclasses.replace(sphere_scene(tmp_path / "b", radius=0.4), c2w=a.c2w.flip(0))
    assert scene_fingerprint(a) != scene_fingerprint(b)
    run = tmp_path / "run"
    train(a, load_config("demo", small + ["train.iters=4"]), run, progress=False)
    with pytest.raises(NeusL0Error, match=r"was trained on .*/a .* not on .*/b"):
        train(b, load_config("demo", small + ["train.iters=8"]), run, resume=True,
              progress=False)
    train(a, load_config("demo", small + ["train.iters=8"]), run, resume=True, progress=False)


def test_a_huge_scale_mat_loads_with_warnings_not_a_traceback(scene_copy, capsys):
    from neus_l0.cli import main

    path = scene_copy / "cameras_sphere.npz"
    data = dict(np.load(path))
    for k in [k for k in data if k.startswith("scale_mat_")]:
        m = data[k].copy()
        m[:3, :4] *= 1e30
        data[k] = m
    np.savez(path, **data)
    assert main(["inspect", str(scene_copy)]) == 0
    out = capsys.readouterr().out
    assert "cameras inside the unit sphere" in out


def test_a_one_view_scene_warns(scene_copy, capsys):
    for folder in ("image", "mask"):
        for p in sorted((scene_copy / folder).glob("*.png"))[1:]:
            p.unlink()
    assert load_scene(scene_copy).n_views == 1
    assert "one view only" in capsys.readouterr().err
