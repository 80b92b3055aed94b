"""`train.compile`: the step compiles without graph breaks and trains as the eager one."""

import pytest
import torch

from neus_l0.config.load import load_config
from neus_l0.errors import ConfigError
from neus_l0.fields.model import make_model
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.loop import train
from neus_l0.train.step import draw_step_inputs, render_and_loss

ANALYTIC = ["model.sdf.gradient=analytic"]


@pytest.mark.parametrize("conf,with_small,extra", [
    ("demo", False, []),
    ("demo", True, ["render.perturb=false", "train.eikonal_fraction=0.5"]),
    ("demo", False, ["sampler=hvs", "train.anneal_end=100"]),
    ("demo", True, ["train.curvature_weight=0.01"]),
], ids=["demo-extra0", "demo-extra1", "demo-extra2", "demo-curvature"])
def test_the_step_has_no_graph_break(small, sphere_scene, tmp_path, conf, with_small, extra):
    scene = sphere_scene(tmp_path / "s")
    cfg = load_config(conf, ANALYTIC + (small if with_small else []) + extra)
    model = make_model(cfg)
    inputs = draw_step_inputs(scene, cfg, 3, 64, torch.Generator().manual_seed(0), None)
    torch._dynamo.reset()
    ex = torch._dynamo.explain(render_and_loss)(model, inputs, cfg, build_sampler(cfg.sampler), ())
    assert ex.graph_break_count == 0, [b.reason for b in ex.break_reasons]
    assert ex.graph_count == 1


def test_compile_needs_a_gradient_without_double_backward(small, sphere_scene, tmp_path):
    cfg = load_config("demo", small + ["train.compile=true", "model.sdf.gradient=autograd",
                                       "train.iters=2"])
    with pytest.raises(ConfigError, match="model.sdf.gradient=analytic"):
        train(sphere_scene(tmp_path / "s"), cfg, tmp_path / "run", progress=False)


@pytest.mark.slow
def test_compiled_training_equals_eager_and_compiles_at_most_thrice(small, sphere_scene, tmp_path):
    from torch._dynamo.utils import counters

    scene = sphere_scene(tmp_path / "s")
    base = small + ANALYTIC + ["train.iters=50", "train.log_every=1",
                               "train.tensorboard=false"]
    eager = train(scene, load_config("demo", base), tmp_path / "eager", progress=False)
    torch._dynamo.reset()
    counters.clear()
    cfg = load_config("demo", base + ["train.compile=true"])
    part = train(scene, cfg, tmp_path / "comp", progress=False, stop_at=25)
    done = train(scene, cfg, tmp_path / "comp", progress=False, resume=True)
    assert part.iteration == 25 and done.iteration == eager.iteration == 50
    assert counters["stats"]["unique_graphs"] <= 3  # one compile, at most 2 recompiles
    import json
    curve = {}
    for run in ("eager", "comp"):
        lines = (tmp_path / run / "metrics.jsonl").read_text().splitlines()
        curve[run] = [json.loads(x)["loss"] for x in lines if "loss" in json.loads(x)]
    assert len(curve["eager"]) == len(curve["comp"]) == 50
    diff = torch.tensor(curve["eager"]) - torch.tensor(curve["comp"])
    assert diff[:5].abs().max() < 1e-5  # the same steps to float rounding ...
    assert (diff.abs() / torch.tensor(curve["eager"])).max() < 1e-2  # ... and curve


def test_the_step_with_looked_up_spans_has_no_graph_break(sphere_scene, tmp_path):
    """A run's step: rays from the pixel pool with their spans under the visual hull."""
    from neus_l0.bounds.pixel_pool import reachable_pixels
    from neus_l0.bounds.static import static_bounds

    scene = sphere_scene(tmp_path / "s")
    cfg = load_config("demo", ANALYTIC)
    model = make_model(cfg)
    bounds = static_bounds(scene, cfg, tmp_path / "run" / "hull.pt")
    pool = reachable_pixels(scene, cfg.render, bounds)
    assert bounds and pool.spans is not None
    inputs = draw_step_inputs(scene, cfg, 3, 64, torch.Generator().manual_seed(0), pool)
    assert inputs.span is not None
    torch._dynamo.reset()
    ex = torch._dynamo.explain(render_and_loss)(model, inputs, cfg, build_sampler(cfg.sampler), ())
    assert ex.graph_break_count == 0, [b.reason for b in ex.break_reasons]
    assert ex.graph_count == 1
