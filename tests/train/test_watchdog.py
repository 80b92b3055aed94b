"""Divergence is a failure: the watchdog's verdicts, and a diverging run that stops with its
last good checkpoint intact and one line saying what to try (issue #27 item 3)."""

import math

import pytest
import torch

from neus_l0.cli import main
from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError, NeusL0Error
from neus_l0.run.checkpoints import list_checkpoints, load_checkpoint
from neus_l0.train.loop import train
from neus_l0.train.watchdog import LOSS_LIMIT, PATIENCE, PSNR_DROP, Watchdog


def _line(it, loss=0.2, psnr=20.0, **extra):
    return {"iter": it, "loss": loss, "psnr": psnr, "inv_s": 30.0, **extra}


def test_a_healthy_run_is_never_stopped_even_when_psnr_wobbles():
    w = Watchdog()
    for i, p in enumerate([14, 17, 19, 18.5, 21, 20.2, 23, 22.9, 24]):
        assert w.check(_line(10 * (i + 1), psnr=p)) is None
    assert w.last_good_iter == 90 and w.best_psnr == 24


@pytest.mark.parametrize("key", ["loss", "psnr", "inv_s", "eikonal_loss"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_any_non_finite_number_is_a_divergence(key, value):
    assert key in Watchdog().check(_line(10, **{key: value}))


def test_an_exploding_loss_is_a_divergence():
    w = Watchdog()
    assert w.check(_line(10, loss=LOSS_LIMIT * 0.99)) is None
    assert "exploded" in w.check(_line(20, loss=LOSS_LIMIT * 1.01))


def test_a_psnr_that_falls_and_stays_down_is_a_divergence_and_good_stays_before_it():
    w = Watchdog()
    w.check(_line(10, psnr=25.0))
    for k in range(1, PATIENCE):
        assert w.check(_line(10 + 10 * k, psnr=25.0 - PSNR_DROP - 0.5)) is None
    assert "PSNR fell" in w.check(_line(10 + 10 * PATIENCE, psnr=25.0 - PSNR_DROP - 0.5))
    assert w.last_good_iter == 10
    # a dip that comes back resets the count
    w = Watchdog()
    w.check(_line(10, psnr=25.0))
    w.check(_line(20, psnr=20.0))
    w.check(_line(30, psnr=24.0))
    assert w.suspect == 0 and w.last_good_iter == 30


def test_a_resumed_run_that_diverges_keeps_its_last_good_checkpoint(small, sphere_scene,
                                                                     tmp_path):
    scene = sphere_scene(tmp_path / "s")
    run = tmp_path / "run"
    base = small + ["train.save_every=10", "train.keep_checkpoints=1"]
    train(scene, load_config("demo", base + ["train.iters=20"]), run, progress=False)
    assert [p.name for p in list_checkpoints(run)] == ["ckpt_0000020.pt"]
    bad = load_config("demo", base + ["train.iters=80", "train.lr=1000"])
    with pytest.raises(NeusL0Error) as exc:
        train(scene, bad, run, resume=True, progress=False)
    msg = str(exc.value)
    assert "diverged at iteration" in msg and "ckpt_0000020.pt" in msg and "train.lr=" in msg
    assert len(msg.splitlines()) == 1
    # the good checkpoint is the newest a resume finds; nothing newer is left to load
    assert [p.name for p in list_checkpoints(run)] == ["ckpt_0000020.pt"]
    state = load_checkpoint(run / "checkpoints" / "ckpt_0000020.pt")
    assert state["iteration"] == 20
    assert all(torch.isfinite(v).all() for v in state["model"].values())


def test_the_cli_exits_non_zero_with_one_line_on_divergence(tiny_scene, tmp_path, capsys,
                                                            small):
    rc = main(["train", str(tiny_scene), "--conf", "demo", "--out", str(tmp_path / "run"),
               "--quiet", *small, "train.iters=60", "train.lr=1000"])
    err = capsys.readouterr().err
    assert rc == 2 and "diverged" in err and "Traceback" not in err
    assert len([x for x in err.splitlines() if "error:" in x]) == 1


def test_a_sharpness_beyond_neus_clamp_is_refused_before_training():
    with pytest.raises(ConfigError, match="model.variance.init"):
        load_config("demo", ["model.variance.init=100"])
