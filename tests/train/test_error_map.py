"""Error-map ray sampling: the draw follows its weights, the weights keep the loss's
expectation, and a run trains with it on."""

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from neus_l0.bounds.error_map import (
    draw,
    draw_probabilities,
    importance_weights,
    new_error_map,
    pixel_tiles,
    refresh_table,
    update_errors,
)
from neus_l0.bounds.pixel_pool import with_error_map
from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError
from neus_l0.train.loop import train
from neus_l0.train.losses import color_l1, mask_bce, weighted_color_l1


def test_probabilities_mix_the_map_with_uniform():
    e = torch.tensor([0.0, 1.0, 3.0, 0.0])
    p = draw_probabilities(e, 0.5)
    assert p.sum().item() == pytest.approx(1.0)
    assert p.tolist() == pytest.approx([0.125, 0.125 + 0.125, 0.125 + 0.375, 0.125])
    assert draw_probabilities(torch.zeros(4), 0.9).tolist() == pytest.approx([0.25] * 4)
    assert draw_probabilities(e, 0.0).tolist() == pytest.approx([0.25] * 4)


def test_the_draw_matches_its_weights():
    """Pearson's chi-square of 20000 draws over 6 pixels under the 0.999 quantile."""
    emap = new_error_map(torch.arange(6), 0.8, 1.0)
    emap.error = torch.tensor([0.1, 5.0, 0.0, 1.0, 2.5, 0.4])
    refresh_table(emap)
    n = 20000
    idx, w = draw(emap, n, torch.Generator().manual_seed(0))
    counts = torch.bincount(idx, minlength=6).double()
    expected = n * emap.prob.double()
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < 20.5, (counts.tolist(), expected.tolist())  # chi2(5) 0.999 quantile: 20.5
    assert torch.allclose(w, 1.0 / (6 * emap.prob[idx]))
    assert (counts / n - emap.prob.double()).abs().max() < 0.01


def _per_ray(l_all, m_all, prob, picks):
    w = importance_weights(prob, picks)
    pred = torch.zeros(len(picks), 3)
    target = torch.stack([l_all[picks], torch.zeros(len(picks)), torch.zeros(len(picks))], -1)
    return pred, target, m_all[picks][:, None], w


def test_the_weights_keep_the_losses_expectation_exactly():
    """Every batch of 2 rays from 4 pixels, weighted by its probability: the weighted colour
    and mask terms' expectation is the pool's own masked mean colour and mean BCE."""
    l_all = torch.tensor([0.2, 1.5, 0.7, 3.0], dtype=torch.float64)  # per-pixel L1 error
    m_all = torch.tensor([1.0, 1.0, 0.0, 1.0], dtype=torch.float64)
    op_all = torch.tensor([0.9, 0.3, 0.2, 0.6], dtype=torch.float64)  # opacity
    fg = float(m_all.mean())
    prob = draw_probabilities(torch.tensor([0.5, 4.0, 0.1, 1.0]), 0.7)
    e_color = e_mask = 0.0
    for a, b in itertools.product(range(4), repeat=2):
        picks = torch.tensor([a, b])
        p_batch = float(prob[a] * prob[b])
        pred, target, mask, w = _per_ray(l_all, m_all, prob, picks)
        e_color += p_batch * float(weighted_color_l1(pred.double(), target, mask, w, fg))
        e_mask += p_batch * float(mask_bce(op_all[picks][:, None], mask, w))
    pool_color = float((l_all * m_all).sum() / m_all.sum())
    pool_mask = float(mask_bce(op_all[:, None], m_all[:, None]))
    assert e_color == pytest.approx(pool_color, rel=1e-12)
    assert e_mask == pytest.approx(pool_mask, rel=1e-12)


def test_uniform_weights_give_the_plain_terms_on_a_full_foreground():
    pred, target = torch.rand(5, 3), torch.rand(5, 3)
    mask, w = torch.ones(5, 1), torch.ones(5)
    assert float(weighted_color_l1(pred, target, mask, w, 1.0)) == pytest.approx(
        float(color_l1(pred, target, mask)), rel=1e-5)
    op = torch.rand(5, 1)
    assert float(mask_bce(op, mask, w)) == pytest.approx(float(mask_bce(op, mask)))


def test_update_blends_the_new_errors_into_the_tiles():
    emap = new_error_map(torch.tensor([0, 1, 1, 2]), 0.5, 0.25)
    emap.error += 1.0
    update_errors(emap, torch.tensor([1, 3]), torch.tensor([5.0, float("nan")]))
    assert emap.error.tolist() == pytest.approx([1.0, 2.0, 0.75])
    assert emap.prob.tolist() == pytest.approx([0.25] * 4)  # the table waits for a refresh
    refresh_table(emap)
    # pixels 1 and 2 share tile 1: both take its error
    expected = 0.5 / 4 + 0.5 * torch.tensor([1.0, 2.0, 2.0, 0.75]) / 5.75
    assert emap.prob.tolist() == pytest.approx(expected.tolist())


def test_tiles_group_blocks_of_one_view():
    H, W = 5, 6
    flat = torch.tensor([0, 1, 2, 7, 13, 29, H * W + 0, H * W + 1])  # view 0, then view 1
    t = pixel_tiles(flat, H, W, 2)
    # (y, x): (0,0) (0,1) (0,2) (1,1) (2,1) (4,5) | view 1: (0,0) (0,1)
    assert t[0] == t[1] == t[3] and t[2] != t[0] and t[4] != t[0]
    assert t[6] == t[7] and t[6] != t[0]
    assert sorted(set(t.tolist())) == list(range(len(set(t.tolist()))))
    assert pixel_tiles(flat, H, W, 1).tolist() == list(range(8))


def test_config_range_and_off_by_default():
    assert load_config("demo").train.error_map.fraction == 0.0
    with pytest.raises(ConfigError, match="error_map.fraction"):
        load_config("demo", ["train.error_map.fraction=1"])


def test_the_maps_share_warms_up_linearly_over_its_part_of_the_schedule():
    from neus_l0.train.step import map_fraction

    cfg = load_config("demo", ["train.iters=1000", "train.error_map.fraction=0.8",
                               "train.error_map.warmup=0.25"])
    got = [map_fraction(cfg, at) for at in (0, 125, 250, 600, 1000)]
    assert got == pytest.approx([0.0, 0.4, 0.8, 0.8, 0.8])
    off = load_config("demo", ["train.iters=1000", "train.error_map.fraction=0.8"])
    assert map_fraction(off, 0) == 0.8
    with pytest.raises(ConfigError, match="error_map.warmup"):
        load_config("demo", ["train.error_map.warmup=1.5"])


def test_the_step_rebuilds_the_table_at_the_warming_share():
    from neus_l0.bounds.pixel_pool import PixelPool
    from neus_l0.train.step import StepSetup, _schedule_position

    cfg = load_config("demo", ["train.iters=1000", "train.error_map.fraction=0.8",
                               "train.error_map.warmup=0.5", "train.log_every=50"])
    emap = new_error_map(torch.arange(10), 0.8, 0.3)
    emap.error = torch.arange(10.0)
    setup = StepSetup(pool=PixelPool(pixels=torch.arange(10), fraction=1.0, error_map=emap))
    opt = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    for it, want in ((0, 0.0), (250, 0.4), (260, 0.4), (300, 0.48), (900, 0.8)):
        _schedule_position(None, opt, cfg, it, setup)
        assert emap.fraction == pytest.approx(want)  # only log steps rebuild the table
        assert emap.prob.tolist() == pytest.approx(
            draw_probabilities(emap.error, want).float().tolist())


def test_warming_up_the_share_keeps_the_weights_unbiased():
    """A table rebuilt at a lower share draws more uniformly, and its importance weights
    still give every pixel ``P p w = 1``."""
    g = torch.Generator().manual_seed(3)
    err = torch.rand(400, generator=g) ** 4
    for f in (0.0, 0.3, 0.8):
        emap = new_error_map(torch.arange(400), f, 0.3)
        emap.error = err.clone()
        refresh_table(emap)
        idx = torch.arange(400)
        assert (400 * emap.prob * importance_weights(emap.prob, idx)).tolist() == \
            pytest.approx([1.0] * 400)
        assert float(emap.prob.min()) == pytest.approx((1 - f) / 400 + f * float(
            err.min() / err.sum()), rel=1e-5)


def test_the_pool_gets_a_map_only_when_asked(sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path / "s")
    assert with_error_map(None, scene, load_config("demo")) is None
    cfg = load_config("demo", ["train.error_map.fraction=0.5"])
    pool = with_error_map(None, scene, cfg)
    n = scene.n_views * scene.height * scene.width
    assert pool.pixels.numel() == n and pool.error_map.prob.numel() == n
    assert pool.error_map.foreground == pytest.approx(float((scene.masks > 0.5).float().mean()))


@pytest.mark.parametrize("weigh_all", ["false", "true"])
def test_a_run_with_the_error_map_trains(weigh_all, small, sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path / "scene")
    cfg = load_config("demo", small + ["train.iters=20", "train.error_map.fraction=0.5",
                                       f"train.error_map.weigh_all={weigh_all}"])
    res = train(scene, cfg, tmp_path / "run", progress=False)
    rows = [json.loads(line) for line in
            (Path(tmp_path / "run") / "metrics.jsonl").read_text().splitlines()]
    assert res.iteration == 20 and len(rows) == 4
    assert all(np.isfinite(r["loss"]) for r in rows)
    assert rows[-1]["loss"] < rows[0]["loss"]


def test_a_map_state_of_other_tiles_is_not_loaded():
    from neus_l0.bounds.error_map import map_state, restore_map
    from neus_l0.run.checkpoint_schema import schema_problem

    emap = new_error_map(torch.arange(6), 0.8, 0.5)
    emap.error = torch.tensor([0.0, 1.0, 2.0, 0.0, 0.0, 3.0])
    refresh_table(emap)
    state = map_state(emap)
    other = new_error_map(torch.arange(4), 0.8, 0.5)
    assert not restore_map(other, state) and other.error.sum() == 0
    again = new_error_map(torch.arange(6), 0.0, 0.5)
    assert restore_map(again, state) and torch.equal(again.prob, emap.prob)
    odd = new_error_map(torch.arange(6), 0.3, 0.5)  # a share out of range keeps the config's
    assert restore_map(odd, dict(state, fraction=7.0)) and odd.fraction == 0.3
    assert schema_problem({"iteration": 0, "model": {}, "optimizer": {
        "state": {}, "param_groups": []}, "rng": None, "config": {}, "scale_mat": None,
        "error_map": [1, 2]}) == "'error_map' is not a dict"


def test_resume_with_the_map_equals_uninterrupted(small, sphere_scene, tmp_path):
    """The map's errors and the table in use travel in the checkpoint: a run stopped
    between two table rebuilds and resumed draws the same rays as one that never stopped."""
    from neus_l0.run.checkpoints import latest_checkpoint, load_checkpoint

    scene = sphere_scene(tmp_path / "scene")
    cfg = load_config("demo", small + ["train.iters=12", "train.log_every=4",
                                       "train.error_map.fraction=0.8",
                                       "train.error_map.signal=depth_mask",
                                       "train.error_map.warmup=0.5", "train.error_map.tile=4"])
    train(scene, cfg, tmp_path / "a", progress=False)
    train(scene, cfg, tmp_path / "b", progress=False, stop_at=6)
    train(scene, cfg, tmp_path / "b", resume=True, progress=False)
    a = load_checkpoint(latest_checkpoint(tmp_path / "a"))
    b = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    assert a["error_map"]["error"].abs().sum() > 0
    for key in ("error", "table_error"):
        assert torch.equal(a["error_map"][key], b["error_map"][key]), key
    assert a["error_map"]["fraction"] == b["error_map"]["fraction"]
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k


@pytest.mark.parametrize("signal, weigh_all", [("colour", "false"), ("depth_mask", "true")])
def test_the_step_with_the_error_map_has_no_graph_break(signal, weigh_all, sphere_scene,
                                                        tmp_path):
    """The drawn weights enter the compiled step as a tensor; the per-ray errors leave it."""
    from neus_l0.bounds.pixel_pool import reachable_pixels
    from neus_l0.bounds.static import static_bounds
    from neus_l0.fields.model import make_model
    from neus_l0.sampling.upsample import build_sampler
    from neus_l0.train.step import draw_step_inputs, render_and_loss

    scene = sphere_scene(tmp_path / "s")
    cfg = load_config("demo", ["model.sdf.gradient=analytic", "train.error_map.fraction=0.5",
                               f"train.error_map.signal={signal}",
                               f"train.error_map.weigh_all={weigh_all}"])
    pool = with_error_map(reachable_pixels(scene, cfg.render, static_bounds(
        scene, cfg, tmp_path / "run" / "hull.pt")), scene, cfg)
    inputs = draw_step_inputs(scene, cfg, 3, 64, torch.Generator().manual_seed(0), pool)
    assert inputs.ray_weight is not None and inputs.pick.shape == (64,)
    torch._dynamo.reset()
    ex = torch._dynamo.explain(render_and_loss)(make_model(cfg), inputs, cfg,
                                                build_sampler(cfg.sampler), ())
    assert ex.graph_break_count == 0, [b.reason for b in ex.break_reasons]
    assert ex.graph_count == 1
