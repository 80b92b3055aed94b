"""Bad inputs of issue #27 that meet the views' pairing (`neus_l0.data.views`): names that
sort wrong as text, a deleted view, files that cannot pair, macOS resource forks. Each asserts
the exit code and one line naming the files, or the correct result.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from neus_l0.cli import main
from neus_l0.formats.neus import load_scene


def test_names_that_sort_wrong_as_text_pair_by_number(scene96, scene96_copy, capsys):
    """Unpadded names past 9 (0, 1, 10, 11, 2, ... as text) pair with their own cameras;
    inspect says the rule."""
    numbers = [0, 1, 2, 3, 4, 5, 10, 11]
    names = [f"{n}.png" for n in numbers]
    assert sorted(names) != names  # by position, view 2 would get camera 10
    cams = dict(np.load(scene96_copy / "cameras_sphere.npz"))
    np.savez(scene96_copy / "cameras_sphere.npz",
             **{f"{kind}_{n}": cams[f"{kind}_{i}"] for i, n in enumerate(numbers)
                for kind in ("world_mat", "scale_mat")})
    for folder in ("image", "mask"):
        for i, n in enumerate(numbers):
            (scene96_copy / folder / f"{i:03d}.png").rename(scene96_copy / folder / f"{n}.png")
    assert main(["inspect", str(scene96_copy)]) == 0
    assert "pairing      views pair by the last number" in capsys.readouterr().out
    got, ref = load_scene(scene96_copy), load_scene(scene96)
    assert got.image_names == names
    assert torch.equal(got.c2w, ref.c2w) and torch.equal(got.images, ref.images)
    assert torch.equal(got.masks, ref.masks)


def test_a_deleted_view_trains_on_the_rest_with_one_warning(scene96_copy, train_cli, tmp_path,
                                                           capsys):
    """Image and mask 005 deleted, world_mat_5 kept: a one-line warning, 7 views train."""
    (scene96_copy / "image" / "005.png").unlink()
    (scene96_copy / "mask" / "005.png").unlink()
    run = tmp_path / "run"
    assert main(train_cli(scene96_copy, run, "train.iters=2")) == 0
    warnings = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert len(warnings) == 1
    assert "world_mat_5" in warnings[0] and "7 views" in warnings[0]
    assert json.loads((run / "run.json").read_text())["n_views"] == 7


@pytest.mark.parametrize("case, named", [
    ("duplicate", ["001.png and view_1.png are both view 1"]),
    ("no-number", ["image/front.png: no view number"]),
    ("no-mask", ["mask: no mask for 007.png"]),
    ("no-camera", ["cameras_sphere.npz: missing world_mat_12 (012.png)"]),
])
def test_a_view_that_cannot_pair_is_an_error_naming_the_files(scene96_copy, train_cli, tmp_path,
                                                              case, named, refused):
    image, mask = scene96_copy / "image", scene96_copy / "mask"
    if case == "duplicate":
        shutil.copy(image / "001.png", image / "view_1.png")
    elif case == "no-number":
        shutil.copy(image / "001.png", image / "front.png")
    elif case == "no-mask":
        (mask / "007.png").unlink()
    else:
        shutil.copy(image / "001.png", image / "012.png")
        shutil.copy(mask / "001.png", mask / "012.png")
    refused(train_cli(scene96_copy, tmp_path / "run"), *named, "views pair by the last")
    assert not (tmp_path / "run").exists()


def test_macos_resource_forks_are_not_views(scene96_copy, capsys):
    """A ``._000.png`` beside the images: skipped, still 8 views."""
    (scene96_copy / "image" / "._000.png").write_bytes(b"\x00\x05\x16\x07 not a png")
    (scene96_copy / "mask" / "._000.png").write_bytes(b"\x00\x05\x16\x07 not a png")
    assert main(["inspect", str(scene96_copy)]) == 0
    captured = capsys.readouterr()
    assert "views        8" in captured.out and "Traceback" not in captured.err
