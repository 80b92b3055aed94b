"""Issue #33 items 2, 6, 15 and 16: what a resumed or new training writes into its run folder.

Nothing is written through a symlink that leads out of the run (``resumes.jsonl``,
``metrics.jsonl``, ``checkpoints/``, ``hull.pt``); a resume after ``run.json`` was deleted
still checks the scene (the checkpoint records its fingerprint); non-UTF-8 bytes in
``metrics.jsonl`` cost their line, with one warning; a run folder that cannot be written
(a read-only mount) is one line, not the lock's OSError.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import pytest
import torch

from neus_l0.cli import main
from neus_l0.run.checkpoints import list_checkpoints


def _resume(scene: Path, run: Path, *extra: str) -> list[str]:
    return ["train", str(scene), "--out", str(run), "--resume", "--quiet", "--threads", "1",
            *extra]


@pytest.fixture
def run(tiny_trained, tmp_path) -> Path:
    return Path(shutil.copytree(tiny_trained, tmp_path / "run"))


@pytest.fixture
def other_scene(tiny_scene, tmp_path) -> Path:
    """The tiny scene less one view: another scene."""
    root = Path(shutil.copytree(tiny_scene, tmp_path / "other"))
    for sub in ("image", "mask"):
        (root / sub / "007.png").unlink()
    return root


@pytest.mark.parametrize("name", ["resumes.jsonl", "metrics.jsonl", "run.json"])
def test_a_file_linked_out_of_the_run_is_not_written_through(run, tiny_scene, tmp_path,
                                                             name, refused):
    """train --resume with a changed train.iters appends to resumes.jsonl, rewrites
    metrics.jsonl and run.json: a link out of the run is refused, the target untouched."""
    outside = tmp_path / "outside.txt"
    outside.write_text("the user's file\n")
    target = run / name
    if target.exists():
        target.unlink()
    target.symlink_to(outside)
    refused(_resume(tiny_scene, run, "train.iters=6"), str(target), "symlink",
             "out of")
    assert outside.read_text() == "the user's file\n"


@pytest.mark.parametrize("name", ["checkpoints", "hull.pt"])
def test_an_entry_linked_out_of_the_run_is_refused_before_training(run, tiny_scene, tmp_path,
                                                                   name, refused):
    elsewhere = tmp_path / "elsewhere"
    shutil.move(run / name, elsewhere)
    (run / name).symlink_to(elsewhere)
    before = sorted(p.name for p in elsewhere.iterdir()) if elsewhere.is_dir() else None
    refused(_resume(tiny_scene, run, "train.iters=6"), str(run / name), "symlink")
    if before is not None:
        assert sorted(p.name for p in elsewhere.iterdir()) == before


def test_a_resume_without_run_json_on_another_scene_is_refused(run, other_scene, refused):
    (run / "run.json").unlink()
    before = [p.name for p in list_checkpoints(run)]
    refused(_resume(other_scene, run, "train.iters=6"), str(run), "was trained on",
             f"not on {other_scene}")
    assert [p.name for p in list_checkpoints(run)] == before


def test_a_resume_without_run_json_on_its_scene_continues_and_rebuilds_it(run, tiny_scene):
    (run / "run.json").unlink()
    assert main(_resume(tiny_scene, run, "train.iters=6")) == 0
    meta = json.loads((run / "run.json").read_text())
    assert meta["scene"] == str(tiny_scene) and meta["scene_fingerprint"]


def test_no_record_of_the_scene_at_all_is_refused(run, tiny_scene, refused):
    """run.json gone and a checkpoint from before fingerprints: the scene cannot be
    checked, so the resume is refused."""
    (run / "run.json").unlink()
    for path in list_checkpoints(run):
        state = torch.load(path, weights_only=True)
        del state["scene_fingerprint"]
        torch.save(state, path)
    refused(_resume(tiny_scene, run, "train.iters=6"), str(run / "run.json"),
             "cannot be checked")


def test_non_utf8_bytes_in_metrics_cost_their_line(run, tiny_scene, capsys):
    path = run / "metrics.jsonl"
    lines = path.read_bytes().splitlines(keepends=True)
    path.write_bytes(lines[0] + b"\xff\xfe{\"iter\": 3, \x80}\n" + b"".join(lines[1:]))
    assert main(_resume(tiny_scene, run, "train.iters=6")) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    warnings = [ln for ln in err.splitlines() if "metrics.jsonl" in ln]
    assert len(warnings) == 1 and "dropped 1 line" in warnings[0]
    text = path.read_bytes().decode("utf-8")
    assert [json.loads(ln)["iter"] for ln in text.splitlines()][-1] == 6


def test_a_read_only_run_folder_is_one_line(tiny_scene, small, tmp_path, monkeypatch,
                                            refused):
    """The lock is the first file a run creates; on a read-only mount (simulated: the tests
    may run as root, whom permissions do not stop) that is one line naming the folder."""
    real_open = os.open

    def read_only(path, flags, *args, **kwargs):
        if str(path).endswith(".lock") and flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
    run = tmp_path / "run"
    refused(["train", str(tiny_scene), "--conf", "demo", "--out", str(run), "--quiet",
                      "--threads", "1", *small, "train.iters=2"], str(run), "cannot write",
             "Read-only file system")
