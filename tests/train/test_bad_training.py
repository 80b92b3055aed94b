"""Training that cannot go on (issues #27 and #18): divergence, an unwritable or full disk,
`--out` a file, a signal. Exit codes and one line each (`neus_l0.train`).
"""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time

import pytest
import torch

from neus_l0.cli import main


def test_a_diverging_run_exits_non_zero_keeping_its_last_good_checkpoint(scene96, run_copy,
                                                                         refused, checkpoint_names,
                                                                         resume_cli):
    """train.lr=1000 from iteration 4: exit 2, one line naming the last good checkpoint,
    which is intact and the newest a resume finds (later ones are set aside)."""
    line = refused(resume_cli(scene96, run_copy, "--change-config", "train.iters=60",
                              "train.lr=1000", "train.save_every=5",
                              "train.log_every=5"),
                   "diverged at iteration", "the last good checkpoint is ckpt_")
    good = line.split("the last good checkpoint is ")[1].split(";")[0]
    assert [n for n in checkpoint_names(run_copy) if n.endswith(".pt")][-1] == good
    state = torch.load(run_copy / "checkpoints" / good, weights_only=True)
    assert state["iteration"] == int(good[5:12]) >= 4
    assert all(torch.isfinite(v).all() for v in state["model"].values())


def test_the_divergence_advice_is_a_command_that_runs(scene96, run_copy, refused, resume_cli):
    """The line's suggested resume is accepted (it needs --change-config)."""
    line = refused(resume_cli(scene96, run_copy, "--change-config", "train.iters=60",
                              "train.lr=1000", "train.log_every=5"), "diverged")
    assert "--change-config" in line


def test_an_unwritable_checkpoints_folder_is_named_before_training(scene96, train_cli, tmp_path,
                                                                   refused):
    """RUN/checkpoints cannot be made (a file is in the way; as root, permissions would not
    stop the write): exit 2 naming it, before the hull or any step."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoints").write_text("in the way")
    refused(train_cli(scene96, run, "train.iters=2"), f"{run / 'checkpoints'}",
            "cannot write there")
    assert sorted(p.name for p in run.iterdir()) == ["checkpoints"]


def test_a_full_disk_is_refused_before_training(scene96, train_cli, tmp_path, monkeypatch, refused,
                                                checkpoint_names):
    """1 MB free: exit 2 naming the run folder and the room the checkpoints need."""
    import neus_l0.train.preflight as preflight

    monkeypatch.setattr(preflight.shutil, "disk_usage",
                        lambda _p: shutil._ntuple_diskusage(2**40, 2**40 - 2**20, 2**20))
    run = tmp_path / "run"
    refused(train_cli(scene96, run, "train.iters=2"), str(run), "1 MB free",
            "the checkpoints need")
    assert checkpoint_names(run) == []


def test_a_disk_that_fills_during_training_is_one_line(scene96, train_cli, tmp_path, monkeypatch,
                                                       refused):
    """torch's "unexpected pos" at the second checkpoint: exit 2 naming the file; the first
    checkpoint stays and no temporary file is left."""
    real, calls = torch.save, []

    def full_disk(obj, f, *a, **kw):
        calls.append(f)
        if len(calls) >= 3:  # the hull, ckpt 2, then ckpt 4
            raise RuntimeError("[enforce fail at inline_container.cc:778] . unexpected pos "
                               "1234 vs 1180")
        return real(obj, f, *a, **kw)

    monkeypatch.setattr(torch, "save", full_disk)
    run = tmp_path / "run"
    refused(train_cli(scene96, run, "train.iters=6", "train.save_every=2"),
            f"{run / 'checkpoints' / 'ckpt_0000004.pt'}: cannot write", "is the disk full")
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["ckpt_0000002.pt"]


def test_18_1_train_out_that_is_a_file_is_one_line(scene96, train_cli, tmp_path, refused):
    """`train --out afile`: exit 2 naming it (was FileExistsError); the file is kept."""
    afile = tmp_path / "afile"
    afile.write_text("keep me\n")
    refused(train_cli(scene96, afile), f"--out {afile}", "not a folder", alone=True)
    assert afile.read_text() == "keep me\n"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_18_4_a_signal_checkpoints_and_exits_non_zero(scene96, train_cli, tmp_path, capsys, sig,
                                                      checkpoint_names, resume_cli):
    """SIGTERM / SIGINT during training: the step ends, a checkpoint is written, exit 143 /
    130 with one line; a resume continues from it."""
    run = tmp_path / "run"

    def preempt():  # a scheduler's signal, once training has logged
        deadline = time.monotonic() + 60
        while not (run / "metrics.jsonl").is_file() and time.monotonic() < deadline:
            time.sleep(0.01)
        os.kill(os.getpid(), sig)

    sender = threading.Thread(target=preempt, daemon=True)
    sender.start()
    rc = main(train_cli(scene96, run, "train.iters=100000", "train.max_seconds=60",
                        "train.log_every=2", "train.compile=false"))
    sender.join()
    captured = capsys.readouterr()
    assert rc == 128 + int(sig), captured
    assert "Traceback" not in captured.err
    (line,) = [ln for ln in captured.err.splitlines() if "stopped by" in ln]
    assert f"stopped by {signal.Signals(sig).name} at iteration" in line
    (ckpt,) = checkpoint_names(run)
    assert ckpt in line
    it = int(ckpt[5:12])
    assert main(resume_cli(scene96, run, f"train.iters={it + 2}")) == 0
    assert checkpoint_names(run)[-1] == f"ckpt_{it + 2:07d}.pt"
