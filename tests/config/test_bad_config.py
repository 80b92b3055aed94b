"""Config numbers that cannot work (issue #27, "What to build" 2): refused before training,
naming the key (`neus_l0.config.checks`).
"""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("override", [
    "render.chunk=0", "train.save_every=-7", "train.max_seconds=-1", "train.lr=.nan",
    "render.chunk=-4", "train.igr_weight=-1", "train.lr_alpha=-1", "sampler.l0.pad=.inf",
    "train.warm_up=-1", "train.val_downscale=0", "train.keep_checkpoints=-1",
    "train.lr=.inf",
])
def test_a_config_number_that_cannot_work_is_refused_before_training(scene96, train_cli, tmp_path,
                                                                     override, refused):
    """Exit 2 naming the key; no run folder (so no checkpoint) is made."""
    run = tmp_path / "run"
    refused(train_cli(scene96, run, "train.iters=2", override),
            f"{override.split('=')[0]}:", alone=True)
    assert not run.exists()


def test_a_sharpness_beyond_neus_clamp_is_refused_before_training(scene96, train_cli, tmp_path,
                                                                  refused):
    """model.variance.init=100 (s = e^1000): exit 2 naming the key and NeuS's clamp."""
    refused(train_cli(scene96, tmp_path / "run", "model.variance.init=100"),
            "model.variance.init", "clamp", alone=True)
    assert not (tmp_path / "run").exists()
