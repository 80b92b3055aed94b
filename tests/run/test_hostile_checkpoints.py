"""Checkpoints that pass the schema but do not fit the networks (second attack of #33): one
line naming the file through mesh, render and train --resume, never a traceback; a run
entry that is a FIFO is refused instead of blocking the run (`neus_l0.run`)."""

from __future__ import annotations

import os
import shutil

import pytest
import torch


def _tamper(run, change) -> None:
    """Rewrite every checkpoint of `run` with `change(state)` applied."""
    for path in sorted((run / "checkpoints").glob("ckpt_*.pt")):
        state = torch.load(path, weights_only=True)
        change(state)
        torch.save(state, path)


def _bias(state) -> str:
    return next(k for k in state["model"] if k.endswith("bias"))


@pytest.mark.parametrize("change, named", [
    (lambda s: s["model"].__setitem__(_bias(s), torch.zeros(3)), "size mismatch"),
    (lambda s: s["model"].__setitem__(_bias(s), torch.zeros(0)), "size mismatch"),
    (lambda s: s["model"].__setitem__("evil", torch.zeros(1)), "Unexpected key"),
    (lambda s: s["model"].__setitem__(_bias(s), s["model"][_bias(s)].long()), "torch.int64"),
    (lambda s: s["config"]["train"].__setitem__("lr", "zzz"), "its config is not valid"),
])
def test_a_checkpoint_that_does_not_fit_is_one_line(run_copy, refused, tmp_path, change, named):
    """mesh (newest and --checkpoint) and render: exit 2, one line naming the checkpoint."""
    _tamper(run_copy, change)
    newest = str(run_copy / "checkpoints" / "ckpt_0000004.pt")
    refused(["mesh", str(run_copy), "--resolution", "16", "--threads", "1"], newest, named)
    refused(["mesh", str(run_copy), "--checkpoint", newest, "--out", str(tmp_path / "m.ply"),
             "--resolution", "16", "--threads", "1"], newest, named)
    refused(["render", str(run_copy), "--frames", "1", "--no-video", "--threads", "1",
             "--out", str(tmp_path / "r")], newest, named)


def test_a_resume_with_foreign_weights_or_rng_is_one_line(scene96, trained96, tmp_path,
                                                          refused, resume_cli):
    """train --resume: a bias of another shape, then an RNG state of another size."""
    run_copy = shutil.copytree(trained96, tmp_path / "a")
    _tamper(run_copy, lambda s: s["model"].__setitem__(_bias(s), torch.zeros(3)))
    refused(resume_cli(scene96, run_copy, "train.iters=6"), "ckpt_0000004.pt", "size mismatch")
    run_copy = shutil.copytree(trained96, tmp_path / "b")
    _tamper(run_copy, lambda s: s["rng"].__setitem__("torch", torch.zeros(3, dtype=torch.uint8)))
    refused(resume_cli(scene96, run_copy, "train.iters=6"), "ckpt_0000004.pt",
            "random generator states do not load")


def test_a_fifo_metrics_file_is_refused_not_waited_on(scene96, run_copy, refused, resume_cli):
    """RUN/metrics.jsonl a named pipe: refused before the run opens it (it blocked forever)."""
    (run_copy / "metrics.jsonl").unlink()
    os.mkfifo(run_copy / "metrics.jsonl")
    refused(resume_cli(scene96, run_copy, "train.iters=6"), "metrics.jsonl", "not a file")
