"""`inspect` says what `train` would refuse, and `train` warns of cameras inside the unit
sphere (issue #33 items 7 and 8).

Scenes: `scene96` (the demo object, 8 views at 96x72: the fit is judged from 72 pixels up)
and conftest's `tiny_scene` (64x48), with their ``scale_mat_i`` scaled, or exported as
transforms.json with a ``sphere.json`` that cuts the object.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from neus_l0.cli import main

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scene96(tmp_path_factory) -> Path:
    """The demo object, 8 views at 96x72 (read-only)."""
    from neus_l0.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("scene96") / "demo"
    return make_scene("demo", out, views=8, width=96, height=72, seed=0, gt_voxel=4.0,
                      point_spacing=2.0, progress=False)


def scaled(src: Path, dst: Path, factor: float) -> Path:
    """A copy of the NeuS-format scene `src` whose sphere radii are `factor` x."""
    shutil.copytree(src, dst)
    cams = dict(np.load(dst / "cameras_sphere.npz"))
    for key in [k for k in cams if k.startswith("scale_mat_") and "inv" not in k]:
        cams[key] = cams[key].copy()
        cams[key][:3, :3] *= factor
    np.savez(dst / "cameras_sphere.npz", **cams)
    return dst


def warnings_of(capsys, argv: list[str], needle: str) -> list[str]:
    """Run the CLI: exit 0, no traceback; the output's lines that name `needle`."""
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == 0 and "Traceback" not in err, err
    return [ln for ln in (out + err).splitlines() if needle in ln]


def test_inspect_says_train_refuses_a_cut_object(capsys, tmp_path, scene96):
    half = scaled(scene96, tmp_path / "half", 0.5)
    lines = warnings_of(capsys, ["inspect", str(half)], "train would refuse")
    assert len(lines) == 1 and "does not fit its unit sphere" in lines[0], lines


def test_inspect_says_train_refuses_a_cutting_sphere_json(capsys, tmp_path, scene96):
    out = tmp_path / "tf"
    subprocess.run([sys.executable, str(ROOT / "tools" / "export_transforms.py"),
                    str(scene96), str(out), "--kind", "nerfstudio", "--rgba"], check=True,
                   capture_output=True)
    sphere = json.loads((scene96 / "scene.json").read_text())["sphere"]
    (out / "sphere.json").write_text(json.dumps({"center": sphere["center"],
                                                 "radius": sphere["radius"] / 7}))
    lines = warnings_of(capsys, ["inspect", str(out)], "train would refuse")
    assert len(lines) == 1 and "sphere.json" in lines[0], lines


def test_inspect_passes_a_fitting_scene(capsys, scene96):
    assert warnings_of(capsys, ["inspect", str(scene96)], "warning") == []


def test_train_warns_of_cameras_inside(capsys, tmp_path, tiny_scene, small):
    big = scaled(tiny_scene, tmp_path / "big", 10.0)
    argv = ["train", str(big), "--out", str(tmp_path / "run"), "--conf", "demo",
            "--threads", "1", "--quiet", *small, "train.iters=1"]
    lines = warnings_of(capsys, argv, "warning")
    assert len(lines) == 1 and "inside the unit sphere" in lines[0], lines
