"""Mesh formats users take away (GLB, STL, OFF), `python -m neus_l0`, `neus-l0 config show`."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from neus_l0.cli import main
from neus_l0.config.describe import describe, first_sentence
from neus_l0.config.load import load_config
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.extract import MESH_FORMATS, export_mesh

ROOT = Path(__file__).resolve().parents[2]


def _coloured_sphere() -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    m.vertices += np.array([100.0, -20.0, 7.5])  # world units, away from the origin
    rgb = (np.random.default_rng(0).random((len(m.vertices), 3)) * 255).astype(np.uint8)
    m.visual.vertex_colors = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1)
    return m


def test_glb_round_trip_keeps_vertices_faces_and_vertex_colours(tmp_path):
    m = _coloured_sphere()
    path = export_mesh(m, tmp_path / "m.glb")
    back = trimesh.load(path, force="mesh", process=False)
    # GLB stores float32 positions: world units to float32 precision
    np.testing.assert_allclose(back.vertices, m.vertices, rtol=0, atol=1e-4 * 150)
    np.testing.assert_array_equal(back.faces, m.faces)
    np.testing.assert_array_equal(back.visual.vertex_colors, m.visual.vertex_colors)


@pytest.mark.parametrize("kind", ["stl", "off", "ply", "obj"])
def test_other_formats_keep_the_geometry(tmp_path, kind):
    m = _coloured_sphere()
    back = trimesh.load(export_mesh(m, tmp_path / f"m.{kind}"), force="mesh")
    assert len(back.faces) == len(m.faces)
    np.testing.assert_allclose(np.sort(back.vertices, 0), np.sort(m.vertices, 0), atol=1e-4)


def test_an_unknown_suffix_is_refused_naming_the_formats(tmp_path):
    with pytest.raises(NeusL0Error, match=r"\.fbx.*\.glb"):
        export_mesh(_coloured_sphere(), tmp_path / "m.fbx")
    assert set(MESH_FORMATS) == {"ply", "obj", "glb", "stl", "off"}


def test_python_dash_m_runs_the_cli():
    out = subprocess.run([sys.executable, "-m", "neus_l0", "--version"], capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip().startswith("neus-l0 ")


def test_the_package_carries_an_mit_license():
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def test_every_config_key_is_listed_with_its_meaning():
    rows = describe(load_config("wmask"))
    keys = [k for k, _, _ in rows]
    assert len(keys) == len(set(keys)) and "train.lr" in keys and "sampler.name" in keys
    undocumented = [k for k, _, d in rows if not d]
    assert not undocumented, undocumented


def test_config_show_prints_the_resolved_values(capsys):
    assert main(["config", "show", "--conf", "demo", "train.iters=7", "sampler=hvs"]) == 0
    out = capsys.readouterr().out
    assert "demo.yaml with train.iters=7 sampler=hvs" in out.splitlines()[0]
    lines = {ln.split(":")[0]: ln for ln in out.splitlines()[1:]}
    assert lines["train.iters"].startswith("train.iters: 7 ") and "# Total iterations" in \
        lines["train.iters"]
    assert lines["sampler.name"].startswith("sampler.name: hvs ")


def test_config_show_refuses_a_bad_key_with_one_line(capsys):
    assert main(["config", "show", "train.nope=1"]) == 2
    err = capsys.readouterr().err
    assert "train.nope" in err and len(err.strip().splitlines()) == 1


def test_first_sentence_skips_abbreviations():
    assert first_sentence("The kind (e.g. `exp`). More text.") == "The kind (e.g. `exp`)."
    assert first_sentence("Maxblur (paper eq. 10) on. Next") == "Maxblur (paper eq. 10) on."
    assert first_sentence("x" * 200).endswith("...") and len(first_sentence("x" * 200)) == 110
