"""New cases of the second attack on #33, refused or handled in one line: ``eval --json``
onto a file of the input scene (it overwrote scene.json), a ``train --out`` whose name is
not UTF-8 text (a TensorBoard traceback after the run folder was made), ``--threads 10000``
(hours of thread contention) and a garbage ``hull.pt`` (a screenful of torch's advice)."""

from __future__ import annotations

import os

from neus_l0.device import free_cpu_threads


def test_eval_json_onto_a_file_of_the_scene_is_refused(trained96, scene96_copy, refused,
                                                       tmp_path):
    """--json SCENE/scene.json and SCENE/image/000.png: refused, the files unchanged."""
    mesh = tmp_path / "m.ply"
    from neus_l0.cli import main
    assert main(["mesh", str(trained96), "--resolution", "16", "--out", str(mesh)]) == 0
    for name in ("scene.json", "image/000.png"):
        target = scene96_copy / name
        before = target.read_bytes()
        refused(["eval", str(mesh), "--scene", str(scene96_copy), "--json", str(target),
                 "--density", "2", "--no-progress"], str(target), "a file of the input")
        assert target.read_bytes() == before


def test_a_run_folder_named_with_non_utf8_bytes_is_refused(tiny_scene, tmp_path, refused):
    """--out with a 0xfe byte or a newline: refused before anything is written."""
    for raw in (b"r\xfeun", b"r\nun"):
        out = os.fsdecode(bytes(tmp_path) + b"/" + raw)
        refused(["train", str(tiny_scene), "--out", out, "--threads", "1", "train.iters=2"],
                "not UTF-8")
        assert not os.path.exists(out)


def test_more_threads_than_cores_are_capped_with_a_line(capsys):
    """--threads 10000 on this machine: its cores, and one line saying so."""
    cores = len(os.sched_getaffinity(0))
    assert free_cpu_threads(10000) == cores
    assert "more than the" in capsys.readouterr().err
    assert free_cpu_threads(1) == 1


def test_a_garbage_hull_file_is_one_line(scene96, run_copy, refused, resume_cli):
    """RUN/hull.pt overwritten with junk: the resume names it in one short line."""
    (run_copy / "hull.pt").write_bytes(os.urandom(300))
    line = refused(resume_cli(scene96, run_copy, "train.iters=6"), "hull.pt",
                   "unreadable visual hull")
    assert "Please file an issue" not in line and len(line) < 400
