"""A resume keeps the run's original config.yaml and records what it changes; changing what
is learnt needs --change-config (issue #27 item 2)."""

import json

import yaml

from neus_l0.cli import main
from neus_l0.config.load import load_config
from neus_l0.run.resumes import FREE_ON_RESUME, recorded_overrides


def _train(tiny_scene, run, small, *extra):
    return main(["train", str(tiny_scene), "--conf", "demo", "--out", str(run), "--quiet",
                 *small, *extra])


def test_a_resume_records_its_changes_and_keeps_the_original(tiny_scene, tmp_path, small,
                                                               capsys):
    run = tmp_path / "run"
    assert _train(tiny_scene, run, small, "train.iters=4") == 0
    original = (run / "config.yaml").read_text()
    assert _train(tiny_scene, run, small, "--resume", "train.iters=6") == 0
    assert (run / "config.yaml").read_text() == original
    lines = [json.loads(x) for x in (run / "resumes.jsonl").read_text().splitlines()]
    assert lines == [{"iteration": 4, "overrides": ["train.iters=6"],
                      "changed": ["train.iters"]}]
    # a plain resume continues with what the run last used
    assert load_config(run / "config.yaml", recorded_overrides(run)).train.iters == 6


def test_changing_what_is_learnt_needs_the_flag(tiny_scene, tmp_path, small, capsys):
    run = tmp_path / "run"
    assert _train(tiny_scene, run, small, "train.iters=4") == 0
    capsys.readouterr()
    assert _train(tiny_scene, run, small, "--resume", "train.iters=6", "train.lr=1e-4") == 2
    err = capsys.readouterr().err
    assert "train.lr" in err and "--change-config" in err and len(err.strip().splitlines()) == 1
    assert not (run / "resumes.jsonl").exists()
    assert _train(tiny_scene, run, small, "--resume", "--change-config", "train.iters=6",
                  "train.lr=1e-4") == 0
    rec = json.loads((run / "resumes.jsonl").read_text())
    assert rec["changed"] == ["train.iters", "train.lr"] and rec["iteration"] == 4
    assert yaml.safe_load((run / "config.yaml").read_text())["train"]["lr"] != 1e-4


def test_the_free_keys_are_about_length_and_logging_only():
    assert not any(k.startswith(("model.", "sampler.")) for k in FREE_ON_RESUME)
    assert "train.lr" not in FREE_ON_RESUME and "train.iters" in FREE_ON_RESUME


def _final_model(run) -> dict:
    from neus_l0.run.checkpoints import latest_checkpoint, load_checkpoint

    return load_checkpoint(latest_checkpoint(run))["model"]


def _same(a: dict, b: dict) -> bool:
    import torch

    return all(torch.equal(a[k], b[k]) for k in a)


def test_stop_at_forks_a_run_on_the_full_schedule(tiny_scene, tmp_path, small, capsys):
    """`train --stop-at N` stops at N with a checkpoint, keeping train.iters' schedule, so
    that a resume ends where an uninterrupted run does, and copies of the stopped run can be
    resumed with another sampler from the same state (the fork study of issue #26)."""
    import shutil

    whole, base = tmp_path / "whole", tmp_path / "base"
    common = ("--threads", "1", "train.iters=8", "train.log_every=2", "train.val_every=0")
    assert _train(tiny_scene, whole, small, *common) == 0
    assert _train(tiny_scene, base, small, *common, "--stop-at", "4") == 0
    out = capsys.readouterr().out
    assert "stopped at --stop-at: 4 iterations" in out
    assert sorted(p.name for p in (base / "checkpoints").glob("ckpt_*.pt"))[-1] == \
        "ckpt_0000004.pt"
    fork = tmp_path / "fork"
    shutil.copytree(base, fork)
    assert _train(tiny_scene, base, small, *common, "--resume") == 0
    assert _same(_final_model(base), _final_model(whole))  # the same schedule and result
    assert _train(tiny_scene, fork, small, *common, "--resume", "--change-config",
                  "sampler=hvs") == 0
    assert json.loads((fork / "resumes.jsonl").read_text())["iteration"] == 4
    assert not _same(_final_model(fork), _final_model(whole))  # another draw from 4 on
    assert _train(tiny_scene, tmp_path / "x", small, "--stop-at", "0") == 2
    assert "--stop-at 0: must be at least 1" in capsys.readouterr().err
