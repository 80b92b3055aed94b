"""Issue #33 items 3, 4 and 5: what an output folder may hold, what synth may delete, and
outputs that are inputs.

Every command that writes a folder accepts a missing or empty one, or its own (a run, a
scene, ...); a folder of the user's (``config.yaml``, ``metrics.jsonl``, ``notes.txt``) is
refused in one line before any work, and left as it was. ``synth`` replaces only the files
its scene's ``scene.json`` lists. An output path equal to an input path is refused.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from neus_l0.cli import main

#: synth's flags for a small, quiet scene.
SYNTH_SMALL = ("--width", "32", "--height", "24", "--no-progress")


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def users_folder(tmp_path) -> Path:
    """A folder of the user's own config.yaml, metrics.jsonl and notes.txt."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "config.yaml").write_text("my: settings\n")
    (folder / "metrics.jsonl").write_text('{"my": 1}\n')
    (folder / "notes.txt").write_text("do not lose\n")
    return folder


@pytest.fixture(scope="module")
def trained(tiny_scene, small_overrides, tmp_path_factory) -> Path:
    """A run of 2 iterations on the tiny scene; read-only."""
    run = tmp_path_factory.mktemp("outs") / "run"
    assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(run), "--quiet",
                 "--threads", "1", *small_overrides, "train.iters=2"]) == 0
    return run


def _argvs(scene: Path, run: Path, out: Path) -> dict[str, list[str]]:
    """One call per command that writes a folder, writing into `out`."""
    mesh = scene / "gt_mesh.ply"
    return {
        "train": ["train", str(scene), "--conf", "demo", "--out", str(out), "--quiet",
                  "--threads", "1", "train.iters=2"],
        "demo": ["demo", "--out", str(out), "--quiet", "--threads", "1"],
        "synth": ["synth", "demo", str(out), *SYNTH_SMALL],
        "colmap": ["colmap", str(scene / "image"), str(out), "--no-progress"],
        "render": ["render", str(run), "--out", str(out), "--frames", "2", "--quiet"],
        "bench": ["bench", "--scenes", str(scene), "--seconds", "5", "--out", str(out),
                  "--quiet", "--no-plots"],
        "eval": ["eval", str(mesh), "--scene", str(scene), "--json", str(out.parent / "e.json"),
                 "--error-maps", str(out), "--no-progress"],
        "figures": ["figures", "--bench", str(run), "--out", str(out)],
        "study": ["study", "sampling", "--out", str(out), "--quick", "--rays", "4"],
    }


@pytest.mark.parametrize("command", ["train", "demo", "synth", "colmap", "render", "bench",
                                     "eval", "figures", "study"])
def test_a_users_folder_is_refused_by_every_command(tiny_scene, trained, users_folder,
                                                    command, refused):
    before = _snapshot(users_folder)
    argv = _argvs(tiny_scene, trained, users_folder)[command]
    refused(argv, str(users_folder), "holds", "give a new or empty folder")
    assert _snapshot(users_folder) == before
    assert sorted(p.name for p in users_folder.iterdir()) == ["config.yaml", "metrics.jsonl",
                                                              "notes.txt"]


def test_train_into_an_empty_folder_and_its_own_run_works(tiny_scene, small, tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    argv = ["train", str(tiny_scene), "--conf", "demo", "--out", str(out), "--quiet",
            "--threads", "1", *small, "train.iters=2"]
    assert main(argv) == 0
    (out / "notes.txt").write_text("my notes on this run\n")  # the run is still the tool's
    assert main(["train", str(tiny_scene), "--out", str(out), "--resume", "--quiet",
                 "--threads", "1", "train.iters=4"]) == 0
    assert (out / "notes.txt").read_text() == "my notes on this run\n"


def test_a_run_folder_is_not_a_render_folder(trained, tmp_path, refused):
    copy = Path(shutil.copytree(trained, tmp_path / "run"))
    other = tmp_path / "other"
    shutil.copytree(trained, other)
    refused(["render", str(copy), "--out", str(other), "--frames", "2", "--quiet"],
             str(other), "holds")


# ------------------------------------------------------------------------------------------
# synth deletes only what it wrote


@pytest.fixture
def synth_scene(tmp_path) -> Path:
    out = tmp_path / "scene"
    assert main(["synth", "demo", str(out), "--views", "3", *SYNTH_SMALL]) == 0
    return out


def test_synth_lists_what_it_wrote(synth_scene):
    files = json.loads((synth_scene / "scene.json").read_text())["files"]
    on_disk = sorted(str(p.relative_to(synth_scene)) for p in synth_scene.rglob("*")
                     if p.is_file())
    assert sorted(files) == on_disk


@pytest.mark.parametrize("stranger", ["image/retouched_000.psd", "mask/my_photo.jpg",
                                      "image/003.png", "notes.txt"])
def test_synth_keeps_a_file_it_did_not_write(synth_scene, stranger, refused):
    (synth_scene / stranger).write_bytes(b"the user's work")
    before = _snapshot(synth_scene)
    refused(["synth", "demo", str(synth_scene), "--views", "2", *SYNTH_SMALL],
             str(synth_scene), stranger, "did not write")
    assert _snapshot(synth_scene) == before


def test_synth_over_an_older_scene_without_a_list_holds_to_the_layout(synth_scene, refused):
    meta = json.loads((synth_scene / "scene.json").read_text())
    del meta["files"]
    (synth_scene / "scene.json").write_text(json.dumps(meta))
    (synth_scene / "image" / "retouched_000.psd").write_bytes(b"x")
    refused(["synth", "demo", str(synth_scene), "--views", "2", *SYNTH_SMALL],
             "image/retouched_000.psd")
    (synth_scene / "image" / "retouched_000.psd").unlink()
    assert main(["synth", "demo", str(synth_scene), "--views", "2", *SYNTH_SMALL]) == 0
    assert sorted(p.name for p in (synth_scene / "image").iterdir()) == ["000.png", "001.png"]


# ------------------------------------------------------------------------------------------
# an output is never an input


def test_eval_json_onto_its_mesh_is_refused(tiny_scene, tmp_path, refused):
    mesh = Path(shutil.copy(tiny_scene / "gt_mesh.ply", tmp_path / "m.ply"))
    before = mesh.read_bytes()
    refused(["eval", str(mesh), "--scene", str(tiny_scene), "--json", str(mesh)],
             f"--json {mesh}", "is the input")
    assert mesh.read_bytes() == before


def test_mesh_onto_its_checkpoint_is_refused(trained, tmp_path, refused):
    run = Path(shutil.copytree(trained, tmp_path / "run"))
    ckpt = sorted((run / "checkpoints").glob("ckpt_*.pt"))[-1]
    refused(["mesh", str(run), "--checkpoint", str(ckpt), "--out", str(ckpt)],
             "is the input")


def test_train_into_its_scene_is_refused(tiny_scene, tmp_path, refused):
    scene = Path(shutil.copytree(tiny_scene, tmp_path / "scene"))
    refused(["train", str(scene), "--conf", "demo", "--out", str(scene), "--quiet"],
             "is the input")


def test_synth_onto_its_mesh_is_refused(tiny_scene, tmp_path, refused):
    mesh = Path(shutil.copy(tiny_scene / "gt_mesh.ply", tmp_path / "m.ply"))
    refused(["synth", str(mesh), str(mesh), *SYNTH_SMALL], "is the input")
