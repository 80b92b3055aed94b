"""The ray count a resumed run continues with (second attack of #33): a checkpoint's
``batch_size`` of 10**12 exhausted memory, and ``--change-config train.batch_size=N`` was
ignored without the sample budget (`neus_l0.train.step.resumed_batch_size`)."""

from __future__ import annotations

import json

import torch

from neus_l0.config.load import load_config
from neus_l0.train.step import resumed_batch_size


def test_the_resumed_count_stays_in_the_configs_bounds():
    """Budget off: the config's batch size; budget on: clamped to [batch/8, 8*batch]."""
    cfg = load_config("demo")
    cfg.train.sample_budget = 0
    assert resumed_batch_size(10**12, cfg) == cfg.train.batch_size
    assert resumed_batch_size(0, cfg) == cfg.train.batch_size
    cfg.train.sample_budget = 1000
    assert resumed_batch_size(10**12, cfg) == 8 * cfg.train.batch_size
    assert resumed_batch_size(1, cfg) == max(1, cfg.train.batch_size // 8)
    assert resumed_batch_size(cfg.train.batch_size + 1, cfg) == cfg.train.batch_size + 1


def test_a_damaged_batch_size_and_a_changed_one(scene96, run_copy, resume_cli, capsys):
    """A checkpoint claiming 10**12 rays resumes; --change-config batch_size=8 is used."""
    for path in (run_copy / "checkpoints").glob("ckpt_*.pt"):
        state = torch.load(path, weights_only=True)
        state["batch_size"] = 10**12
        torch.save(state, path)
    from neus_l0.cli import main
    assert main(resume_cli(scene96, run_copy, "train.iters=5")) == 0, capsys.readouterr().err
    assert main([*resume_cli(scene96, run_copy, "train.iters=6", "train.batch_size=8",
                             "train.log_every=1", "train.sample_budget=0"),
                 "--change-config"]) == 0, capsys.readouterr().err
    last = json.loads((run_copy / "metrics.jsonl").read_text().splitlines()[-1])
    assert last["rays"] == 8, last
