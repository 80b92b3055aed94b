"""`model.color.view_warmup`: the view direction's encoding fades in over the first part of
the schedule, so that the colour cannot vary with the view before the surface settles."""

import pytest
import torch

from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError
from neus_l0.fields.color import ColorNetwork
from neus_l0.fields.model import make_model
from neus_l0.train.step import make_optimizer, train_step, view_scale


def test_the_weight_ramps_linearly_then_holds():
    cfg = load_config("demo", ["train.iters=1000", "model.color.view_warmup=0.2"])
    assert [view_scale(cfg, at) for at in (0, 50, 100, 200, 900)] == pytest.approx(
        [0.0, 0.25, 0.5, 1.0, 1.0])
    assert view_scale(load_config("demo", ["train.iters=1000"]), 0) == 1.0  # off: NeuS


def test_the_ramp_follows_the_schedules_length():
    """The ramp is a fraction of the schedule: of a planned run's length, and of
    ``train.lr_decay_iters`` when that is set."""
    from neus_l0.train.budget import planned_config

    cfg = load_config("demo", ["train.iters=1000", "model.color.view_warmup=0.2"])
    assert view_scale(planned_config(cfg, 2000), 200) == pytest.approx(0.5)
    assert view_scale(planned_config(cfg, 500), 50) == pytest.approx(0.5)
    longer = load_config("demo", ["train.iters=1000", "train.lr_decay_iters=2000",
                                  "model.color.view_warmup=0.2"])
    assert view_scale(longer, 200) == pytest.approx(0.5)


def test_range_and_off_by_default():
    assert load_config("demo").model.color.view_warmup == 0.0
    with pytest.raises(ConfigError, match="view_warmup"):
        load_config("demo", ["model.color.view_warmup=1.5"])


def test_at_zero_the_colour_ignores_the_view_exactly():
    cfg = load_config("demo").model.color
    net = ColorNetwork(cfg, 8)
    g = torch.Generator().manual_seed(0)
    pts, nrm, feat = (torch.randn(64, 3, generator=g), torch.randn(64, 3, generator=g),
                      torch.randn(64, 8, generator=g))
    v1, v2 = torch.randn(64, 3, generator=g), torch.randn(64, 3, generator=g)
    assert not torch.equal(net(pts, nrm, v1, feat), net(pts, nrm, v2, feat))
    net.view_scale.fill_(0.0)
    assert torch.equal(net(pts, nrm, v1, feat), net(pts, nrm, v2, feat))
    assert "view_scale" not in net.state_dict()  # set by the step, not saved


def test_the_step_sets_the_weight_from_the_schedule(small, sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path / "s")
    cfg = load_config("demo", small + ["train.iters=100", "model.color.view_warmup=0.5",
                                       "train.compile=false"])
    model = make_model(cfg)
    opt = make_optimizer(model, cfg)
    g = torch.Generator().manual_seed(0)
    for it, want in ((0, 0.0), (10, 0.2), (60, 1.0)):
        train_step(model, opt, scene, cfg, it, g, batch_size=16)
        assert model.color.view_scale.item() == pytest.approx(want)


def test_a_run_stopped_during_the_ramp_renders_with_its_weight(small, sphere_scene, tmp_path):
    """The checkpoint keeps the view weight of its last step; loading it for rendering sets
    it (a render with the full view encoding would show a colour the run never trained)."""
    from neus_l0.errors import NeusL0Error
    from neus_l0.run.checkpoints import latest_checkpoint, load_checkpoint, load_trained_model
    from neus_l0.train.loop import train

    scene = sphere_scene(tmp_path / "s")
    cfg = load_config("demo", small + ["train.iters=6", "model.color.view_warmup=1.0",
                                       "train.compile=false", "train.val_every=0"])
    train(scene, cfg, tmp_path / "run", progress=False)
    ckpt = latest_checkpoint(tmp_path / "run")
    state = load_checkpoint(ckpt)
    assert state["view_scale"] == pytest.approx(5 / 6)  # the last step was iteration 5
    model, _, _ = load_trained_model(tmp_path / "run")
    assert model.color.view_scale.item() == pytest.approx(5 / 6)
    state["view_scale"] = float("nan")
    torch.save(state, ckpt)
    with pytest.raises(NeusL0Error, match="view_scale"):
        load_trained_model(tmp_path / "run")
