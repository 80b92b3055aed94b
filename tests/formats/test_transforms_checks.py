"""transforms.json inputs that used to pass unchecked or crash (issue #33 items 9 and 13):
each ends in one ``neus-l0 inspect: error:`` line naming the file and the frame."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from neus_l0.cli import main

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def transforms_scene(tiny_scene, tmp_path_factory) -> Path:
    """`tiny_scene` exported as a nerfstudio transforms.json scene (RGBA images)."""
    out = tmp_path_factory.mktemp("tf") / "scene"
    subprocess.run([sys.executable, str(ROOT / "tools" / "export_transforms.py"),
                    str(tiny_scene), str(out), "--kind", "nerfstudio", "--rgba"],
                   check=True, capture_output=True)
    return out


def edited(src: Path, dst: Path, edit) -> Path:
    """A copy of the scene `src` at `dst` whose transforms.json `edit(data)` changed."""
    shutil.copytree(src, dst)
    data = json.loads((dst / "transforms.json").read_text())
    edit(data)
    (dst / "transforms.json").write_text(json.dumps(data))
    return dst


def refused_line(capsys, scene: Path, *named: str) -> str:
    """`inspect` on `scene`: exit 2, one error line naming every `named`, no traceback."""
    rc = main(["inspect", str(scene)])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("neus-l0 inspect: error: ")]
    assert len(lines) == 1, err
    for needle in named:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _frame(i: int, key: str, value):
    def edit(data):
        data["frames"][i][key] = value
    return edit


def _duplicate(data):
    data["frames"][3]["file_path"] = data["frames"][1]["file_path"]


def _zero_angle(data):
    frame = data["frames"][5]
    del frame["fl_x"], frame["fl_y"]
    frame["camera_angle_x"] = 0


def _bottom_row(data):
    data["frames"][2]["transform_matrix"][3] = [0, 0, 0, 2]


@pytest.mark.parametrize("edit, named", [
    (_frame(4, "cx", 1000), ("frame 4", "principal point", "cx 1000")),
    (_duplicate, ("frames 1 and 3", "different poses")),
    (_bottom_row, ("frame 2", "bottom row")),
    (_zero_angle, ("frame 5", "camera_angle_x", "(0, pi)")),
], ids=["cx-outside", "one-image-two-poses", "bottom-row", "zero-field-of-view"])
def test_bad_frame_is_one_line(capsys, tmp_path, transforms_scene, edit, named):
    scene = edited(transforms_scene, tmp_path / "scene", edit)
    refused_line(capsys, scene, str(scene / "transforms.json"), *named)


def test_deeply_nested_json_is_one_line(capsys, tmp_path):
    (tmp_path / "transforms.json").write_text("[" * 100_000)
    refused_line(capsys, tmp_path, str(tmp_path / "transforms.json"), "nested too deeply")


def test_repeated_image_with_one_pose_loads(capsys, tmp_path, transforms_scene):
    def same(data):
        data["frames"].append(dict(data["frames"][0]))
    scene = edited(transforms_scene, tmp_path / "scene", same)
    assert main(["inspect", str(scene)]) == 0, capsys.readouterr().err
