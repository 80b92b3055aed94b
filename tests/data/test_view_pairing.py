"""Views pair with their masks and cameras by the number in their names, never by sorted
position (issue #27 item 1): unpadded names, gaps, duplicates, names without a number."""

import shutil

import pytest
import torch

from neus_l0.cli import main
from neus_l0.data.views import view_index
from neus_l0.errors import SceneError
from neus_l0.formats.neus import load_scene


@pytest.mark.parametrize("name, index", [
    ("000.png", 0), ("0.png", 0), ("000123.png", 123), ("image_12.jpg", 12),
    ("IMG_0012.JPG", 12), ("cam3_view07.png", 7), ("front.png", None), ("r_5.png", 5),
])
def test_the_view_index_is_the_last_number_in_the_name(name, index):
    assert view_index(name) == index


def test_unpadded_names_pair_with_their_own_cameras(tiny_scene, scene_copy):
    """0.png .. 7.png (and masks likewise) sort as 0, 1, 10, ... by name; by number they
    give exactly the padded scene."""
    for folder in ("image", "mask"):
        for p in sorted((scene_copy / folder).glob("*.png")):
            p.rename(p.with_name(f"{int(p.stem)}.png"))
    ref = load_scene(tiny_scene)
    got = load_scene(scene_copy)
    assert torch.equal(got.c2w, ref.c2w) and torch.equal(got.images, ref.images)
    assert torch.equal(got.masks, ref.masks)
    assert got.image_names == [f"{i}.png" for i in range(8)]


def test_view_numbers_past_nine_do_not_sort_as_text(tiny_scene, scene_copy):
    """Renumber views 0..7 as 3..10: name order (10, 3, 4, ...) differs from number order."""
    import numpy as np

    cams = dict(np.load(scene_copy / "cameras_sphere.npz"))
    new = {}
    for i in range(8):
        for kind in ("world_mat", "scale_mat"):
            new[f"{kind}_{i + 3}"] = cams[f"{kind}_{i}"]
    np.savez(scene_copy / "cameras_sphere.npz", **new)
    for folder in ("image", "mask"):
        for p in sorted((scene_copy / folder).glob("*.png"), reverse=True):
            p.rename(p.with_name(f"{int(p.stem) + 3}.png"))
    got, ref = load_scene(scene_copy), load_scene(tiny_scene)
    assert torch.equal(got.c2w, ref.c2w) and torch.equal(got.images, ref.images)


def test_a_deleted_view_leaves_a_gap_not_a_shift(tiny_scene, scene_copy, capsys):
    (scene_copy / "image" / "005.png").unlink()
    (scene_copy / "mask" / "005.png").unlink()
    got, ref = load_scene(scene_copy), load_scene(tiny_scene)
    assert got.n_views == 7
    keep = [0, 1, 2, 3, 4, 6, 7]
    assert torch.equal(got.c2w, ref.c2w[keep]) and torch.equal(got.images, ref.images[keep])
    err = capsys.readouterr().err
    assert "world_mat_5" in err and "7 views" in err and len(err.strip().splitlines()) == 1


def test_two_files_of_one_view_are_an_error_naming_both(scene_copy):
    shutil.copy(scene_copy / "image" / "001.png", scene_copy / "image" / "view_1.png")
    with pytest.raises(SceneError, match=r"001\.png and view_1\.png are both view 1"):
        load_scene(scene_copy)


def test_a_file_without_a_number_is_an_error_naming_it(scene_copy):
    shutil.copy(scene_copy / "image" / "001.png", scene_copy / "image" / "front.png")
    with pytest.raises(SceneError, match=r"front\.png: no view number"):
        load_scene(scene_copy)


def test_an_image_without_its_camera_is_an_error_naming_both(scene_copy):
    shutil.copy(scene_copy / "image" / "001.png", scene_copy / "image" / "012.png")
    shutil.copy(scene_copy / "mask" / "001.png", scene_copy / "mask" / "012.png")
    with pytest.raises(SceneError, match=r"cameras_sphere\.npz: missing world_mat_12 \(012"):
        load_scene(scene_copy)


def test_macos_resource_forks_are_not_views(tiny_scene, scene_copy):
    (scene_copy / "image" / "._000.png").write_bytes(b"\x00\x05\x16\x07 not a png")
    assert load_scene(scene_copy).n_views == load_scene(tiny_scene).n_views


def test_inspect_prints_the_pairing_rule(scene_copy, capsys):
    assert main(["inspect", str(scene_copy)]) == 0
    out = capsys.readouterr().out
    assert "pairing      views pair by the last number" in out and "views 0 .. 7" in out
