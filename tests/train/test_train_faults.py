"""The trainer survives what clusters and users do: signals, a second run, resume; it logs
to TensorBoard."""

import os
import signal

import pytest
import torch

from neus_l0.config.load import load_config
from neus_l0.errors import NeusL0Error
from neus_l0.run.checkpoints import latest_checkpoint, load_checkpoint
from neus_l0.run.lock import RunLock
from neus_l0.train.loop import train


@pytest.fixture
def scene(sphere_scene, tmp_path):
    return sphere_scene(tmp_path / "scene")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_finishes_the_step_checkpoints_and_resume_is_exact(small, scene, tmp_path, sig):
    cfg = load_config("demo", small + ["train.iters=12", "train.log_every=1",
                                       "train.save_every=100", "train.tensorboard=false"])

    def send(iteration, *_):  # a scheduler's preemption, arriving during iteration 5's log
        if iteration == 5:
            os.kill(os.getpid(), sig)
        return {}

    part = train(scene, cfg, tmp_path / "b", progress=False, hooks=[send])
    assert part.signal == signal.Signals(sig).name and part.exit_code == 128 + int(sig)
    assert part.stopped_early and part.iteration == 5
    assert latest_checkpoint(tmp_path / "b").name == "ckpt_0000005.pt"
    assert signal.getsignal(sig) is not None  # handlers are restored after the run
    done = train(scene, cfg, tmp_path / "b", resume=True, progress=False)
    assert done.signal is None and done.exit_code == 0 and done.iteration == 12
    train(scene, cfg, tmp_path / "a", progress=False)
    ref = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    got = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    for k in ref["model"]:
        assert torch.equal(ref["model"][k], got["model"][k]), k


def test_a_second_training_into_the_same_folder_is_refused(small, scene, tmp_path):
    cfg = load_config("demo", small + ["train.iters=2", "train.tensorboard=false"])
    with RunLock(tmp_path / "run"), pytest.raises(NeusL0Error, match=f"PID {os.getpid()}"):
        train(scene, cfg, tmp_path / "run", progress=False)
    res = train(scene, cfg, tmp_path / "run", progress=False)  # released: it runs now
    assert res.iteration == 2
    assert not (tmp_path / "run" / ".lock").exists()


def test_an_out_that_is_a_file_is_refused(small, scene, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    cfg = load_config("demo", small + ["train.iters=2"])
    with pytest.raises(NeusL0Error, match="afile: is a file"):
        train(scene, cfg, afile, progress=False)
    assert afile.read_text() == "x"


def test_tensorboard_events_hold_the_training_curves(small, scene, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = load_config("demo", small + ["train.iters=6", "train.log_every=3",
                                       "train.val_every=6", "train.val_downscale=2"])
    train(scene, cfg, tmp_path / "run", progress=False)
    acc = EventAccumulator(str(tmp_path / "run"))
    acc.Reload()
    tags = acc.Tags()
    for name in ("loss", "psnr", "inv_s", "lr", "samples_per_ray", "its_per_s"):
        assert f"train/{name}" in tags["scalars"], name
    assert [e.step for e in acc.Scalars("train/loss")] == [3, 6]
    assert tags["images"], "the validation image is in TensorBoard too"
    lines = [line for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
             if '"loss"' in line]  # the log lines (the validation adds a val_psnr line)
    assert len(lines) == 2


def test_the_no_grad_passes_see_every_optimiser_update(small, scene):
    """The up-sampling's cached weight-norm weights follow the fused Adam's updates."""
    from neus_l0.fields.model import make_model
    from neus_l0.train.step import make_optimizer, train_step

    cfg = load_config("demo", small)
    model = make_model(cfg)
    opt = make_optimizer(model, cfg)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(64, 3) - 0.5
    for it in range(3):
        train_step(model, opt, scene, cfg, it, g)
        with torch.no_grad():
            cached = model.sdf.sdf(x)  # the path the up-sampling rounds take
        with torch.enable_grad():
            fresh = model.sdf.sdf(x)  # weights recomputed with their graph
        torch.testing.assert_close(cached, fresh.detach(), rtol=0, atol=0)
