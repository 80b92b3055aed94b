"""Run folders under stress (issues #27 and #18): a resume on another scene or with a new lr,
file modes, orphan temporaries, a corrupt newest checkpoint, a locked folder (`neus_l0.run`).
"""

from __future__ import annotations

import json
import os
import stat

from neus_l0.cli import main


def test_resume_on_another_scene_is_refused(scene96_copy, run_copy, refused, checkpoint_names,
                                            resume_cli):
    """A run trained on scene96, resumed on a 7-view scene: exit 2 naming both."""
    (scene96_copy / "image" / "005.png").unlink()
    (scene96_copy / "mask" / "005.png").unlink()
    before = checkpoint_names(run_copy)
    refused(resume_cli(scene96_copy, run_copy, "train.iters=6"), str(run_copy),
            "was trained on", "(8 views)", f"not on {scene96_copy} (7 views)")
    assert checkpoint_names(run_copy) == before


def test_outputs_get_mode_0644_under_umask_022(trained96, scene96, tmp_path):
    """A run's files, a mesh and an eval report: 0644, not the temporary file's 0600."""
    modes = {str(p.relative_to(trained96)): stat.S_IMODE(p.stat().st_mode)
             for p in trained96.rglob("*") if p.is_file()}
    for name in ("config.yaml", "run.json", "hull.pt", "checkpoints/ckpt_0000004.pt"):
        assert modes.pop(name) == 0o644, name
    assert set(modes.values()) <= {0o644}, modes
    old = os.umask(0o022)
    try:
        mesh = tmp_path / "m.ply"
        assert main(["mesh", str(trained96), "--resolution", "24", "--out", str(mesh)]) == 0
        report = tmp_path / "r.json"
        assert main(["eval", str(mesh), "--scene", str(scene96), "--json", str(report),
                     "--density", "2", "--no-progress"]) == 0
    finally:
        os.umask(old)
    assert stat.S_IMODE(mesh.stat().st_mode) == 0o644
    assert stat.S_IMODE(report.stat().st_mode) == 0o644


def test_resume_with_a_new_lr_keeps_config_yaml_and_records_it(scene96, run_copy, refused,
                                                               resume_cli):
    """--resume train.lr=1e5: refused without --change-config; with it, config.yaml stays
    the original and resumes.jsonl records the change."""
    original = (run_copy / "config.yaml").read_bytes()
    refused(resume_cli(scene96, run_copy, "train.lr=1e5"), "train.lr",
            "--change-config", alone=True)
    assert not (run_copy / "resumes.jsonl").exists()
    assert main(resume_cli(scene96, run_copy, "--change-config", "train.iters=6",
                           "train.lr=1e-4")) == 0
    assert (run_copy / "config.yaml").read_bytes() == original
    (record,) = [json.loads(x) for x in (run_copy / "resumes.jsonl").read_text().splitlines()]
    assert record["iteration"] == 4 and record["changed"] == ["train.iters", "train.lr"]
    assert "train.lr=0.0001" in record["overrides"]


def test_orphan_checkpoint_temporaries_are_removed_at_start(scene96, run_copy, capsys,
                                                            checkpoint_names, resume_cli):
    """`.ckpt_*.tmp.pt` (and any writer's temporary) a killed run left: removed, one line."""
    orphans = [run_copy / "checkpoints" / ".ckpt_0000006.pt.k1ll3d.tmp.pt",
               run_copy / ".config.yaml.k1ll3d.tmp.yaml"]
    for p in orphans:
        p.write_bytes(b"cut short")
    assert main(resume_cli(scene96, run_copy, "train.iters=6")) == 0
    assert not any(p.exists() for p in orphans)
    notes = [ln for ln in capsys.readouterr().err.splitlines() if "killed run left" in ln]
    assert len(notes) == 1 and "removed 2 temporary file(s)" in notes[0]
    assert checkpoint_names(run_copy)[-1] == "ckpt_0000006.pt"


def test_18_3_a_corrupt_newest_checkpoint_falls_back(scene96, run_copy, tmp_path, capsys, one_line,
                                                     checkpoint_names, resume_cli):
    """ckpt 4 truncated: mesh uses ckpt 2 and says so in one line, keeping the damaged file
    as .corrupt; a resume continues from ckpt 2."""
    newest = run_copy / "checkpoints" / "ckpt_0000004.pt"
    newest.write_bytes(newest.read_bytes()[:1000])
    mesh = tmp_path / "m.ply"
    assert main(["mesh", str(run_copy), "--resolution", "24", "--out", str(mesh)]) == 0
    captured = capsys.readouterr()
    assert one_line(captured.err).endswith("using ckpt_0000002.pt (iteration 2)")
    assert "iteration 2" in captured.out and mesh.is_file()
    assert checkpoint_names(run_copy) == ["ckpt_0000002.pt", "ckpt_0000004.pt.corrupt"]
    assert main(resume_cli(scene96, run_copy, "train.iters=4")) == 0
    assert checkpoint_names(run_copy) == ["ckpt_0000002.pt", "ckpt_0000004.pt",
                                     "ckpt_0000004.pt.corrupt"]


def test_18_5_a_second_training_into_a_locked_folder_is_refused(scene96, train_cli, tmp_path,
                                                                refused):
    """Two trainings into one folder: the second names the holder's PID; nothing written."""
    from neus_l0.run.lock import RunLock

    run = tmp_path / "run"
    with RunLock(run):
        refused(train_cli(scene96, run, "train.iters=2"), str(run),
                f"in use by PID {os.getpid()}")
    assert sorted(p.name for p in run.iterdir()) == []
