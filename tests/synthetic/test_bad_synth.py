"""`neus-l0 synth`'s bad inputs (issue #27): an interrupted or shrunk scene loses no data,
degenerate meshes and numbers are refused, a folder that is not a scene is never replaced.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import neus_l0.synthetic.scene as synthetic
from neus_l0.cli import main
from neus_l0.formats.neus import load_scene

#: synth's flags for a small, quiet scene.
SYNTH_SMALL = ("--width", "32", "--height", "24", "--no-progress")


def _small_scene(out: Path, views: int) -> Path:
    return synthetic.make_scene("demo", out, views=views, width=32, height=24, gt_voxel=6.0,
                                point_spacing=6.0, progress=False)


def _ply(path: Path, vertices, faces) -> Path:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}",
             "property float x", "property float y", "property float z",
             f"element face {len(faces)}", "property list uchar int vertex_indices",
             "end_header"]
    lines += [" ".join(str(c) for c in v) for v in vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


TETRA = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]


TETRA_FACES = [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]


@pytest.mark.parametrize("where", ["render", "png"])
def test_synth_interrupted_keeps_the_old_scene(tmp_path, monkeypatch, where, snapshot):
    out = _small_scene(tmp_path / "scene", views=4)
    before = snapshot(out)
    calls = {"n": 0}

    def failing(real):
        def wrapped(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] == 3:
                raise RuntimeError("injected failure")
            return real(*args, **kwargs)
        return wrapped

    if where == "render":  # one view per batch: fails on the third view
        monkeypatch.setattr(synthetic, "RAYS_PER_BATCH", 1)
        monkeypatch.setattr(synthetic, "render_views", failing(synthetic.render_views))
    else:  # fails while writing the second view's image
        monkeypatch.setattr(synthetic, "_write_png", failing(synthetic._write_png))
    with pytest.raises(RuntimeError, match="injected"):
        synthetic.make_scene("demo", out, views=6, width=32, height=24, seed=1,
                             gt_voxel=6.0, point_spacing=6.0, progress=False)
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no temporary left
    assert load_scene(out).n_views == 4


def test_synth_fewer_views_leaves_no_stale_images(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["synth", "demo", str(out), "--views", "6", *SYNTH_SMALL]) == 0
    assert main(["synth", "demo", str(out), "--views", "3", *SYNTH_SMALL]) == 0
    for sub in ("image", "mask"):
        assert sorted(p.name for p in (out / sub).iterdir()) == ["000.png", "001.png",
                                                                  "002.png"]
    assert sorted(np.load(out / "cameras_sphere.npz").files) == sorted(
        [f"world_mat_{i}" for i in range(3)] + [f"scale_mat_{i}" for i in range(3)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 0
    assert "views        3" in capsys.readouterr().out


@pytest.mark.parametrize("vertices, faces, why", [
    ([[1, 1, 1]] * 4, TETRA_FACES, "all vertices are the same point"),
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], TETRA_FACES, "zero surface area"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], "lie in one plane"),
    (TETRA, [], "no triangles"),
    ([*TETRA[:3], ["nan", 0, 1]], TETRA_FACES, "NaN or infinite"),
    (TETRA, [[0, 1, 9], *TETRA_FACES[1:]], "do not exist"),
], ids=["one-point", "zero-area", "one-triangle", "no-faces", "nan", "bad-index"])
def test_synth_degenerate_mesh(tmp_path, vertices, faces, why, refused):
    mesh = _ply(tmp_path / "bad.ply", vertices, faces)
    out = tmp_path / "out"
    refused(["synth", str(mesh), str(out), "--views", "2", *SYNTH_SMALL],
            str(mesh), why, alone=True)
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.ply"]


def test_synth_solid_mesh_still_works(tmp_path):
    mesh = _ply(tmp_path / "tetra.ply", TETRA, TETRA_FACES)
    out = synthetic.make_scene(str(mesh), tmp_path / "t", views=2, width=32, height=24,
                               point_spacing=8.0, progress=False)
    assert load_scene(out).n_views == 2


def test_an_all_equal_vertex_obj_is_refused_by_synth(tmp_path, refused, one_point_obj):
    """(Was a ZeroDivisionError.) synth: exit 2 naming the file, no scene written."""
    obj = one_point_obj(tmp_path / "point.obj", (1, 1, 1))
    refused(["synth", str(obj), str(tmp_path / "out"), "--views", "2", *SYNTH_SMALL],
            str(obj), "all vertices are the same point", alone=True)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("flags, named", [
    (["--views", "0"], "--views 0"), (["--width", "7"], "--width 7"),
    (["--height", "-3"], "--height -3"), (["--spp", "0"], "--spp 0"),
    (["--seed", "-1"], "--seed -1"),
    (["--width", "100000", "--height", "100000"], "of memory"),
])
def test_synth_numeric_flags(tmp_path, flags, named, refused):
    out = tmp_path / "out"
    refused(["synth", "demo", str(out), "--no-progress", *flags], named, alone=True)
    assert not out.exists()


def test_synth_never_replaces_a_folder_that_is_not_a_scene(tmp_path, refused):
    own = tmp_path / "mine"
    own.mkdir()
    (own / "notes.txt").write_text("keep me")
    refused(["synth", "demo", str(own), "--views", "2", *SYNTH_SMALL],
            str(own), "not a synthetic scene", alone=True)
    scene = _small_scene(tmp_path / "scene", views=2)
    (scene / "run").mkdir()
    refused(["synth", "demo", str(scene), "--views", "2", *SYNTH_SMALL],
            "holds run", alone=True)
    assert (own / "notes.txt").read_text() == "keep me" and (scene / "run").is_dir()
