"""`train.curvature_weight`: Neuralangelo's curvature term, the mean |Laplacian| of the SDF by
central differences at a random subset of the step's samples."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.load import load_config
from neus_l0.config.schema import SDFConfig
from neus_l0.errors import ConfigError
from neus_l0.fields.encodings import HashGridEncoding
from neus_l0.fields.model import make_model
from neus_l0.fields.sdf import SDFNetwork
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.losses import LOSS_NAMES, curvature
from neus_l0.train.step import (
    draw_step_inputs,
    make_optimizer,
    render_and_loss,
    train_step,
)


class QuadraticSDF(SDFNetwork):
    """An `SDFNetwork` whose SDF is the quadratic x^T A x + b.x + c (Laplacian 2 tr A)."""

    def __init__(self, a: torch.Tensor, b: torch.Tensor, c: float) -> None:
        super().__init__(SDFConfig(layers=1, hidden=8, feature_dim=2, skip=[],
                                   geometric_init=False))
        self.a, self.b, self.c = a, b, c

    def forward(self, x: torch.Tensor, count: bool = True) -> torch.Tensor:
        f = ((x @ self.a) * x).sum(-1, keepdim=True) + x @ self.b[:, None] + self.c
        return torch.cat([f, torch.zeros(x.shape[0], 2, dtype=x.dtype)], dim=-1)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(1e-3, 0.2))
def test_the_laplacian_is_exact_on_quadratics(seed, h):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(3, 3, generator=g, dtype=torch.float64)
    net = QuadraticSDF(a, torch.randn(3, generator=g, dtype=torch.float64), 0.3)
    x = torch.rand(50, 3, generator=g, dtype=torch.float64) * 2 - 1
    lap = net.laplacian(x, h)
    assert lap.shape == (50,)
    torch.testing.assert_close(lap, torch.full((50,), 2 * a.trace().item(),
                                               dtype=torch.float64), rtol=1e-6, atol=1e-6)


def test_the_laplacian_of_a_smooth_network_matches_autograds_hessian_trace():
    """A frequency-encoded MLP (smooth): central differences at h = 1e-3 against the trace of
    autograd's Hessian, in float64."""
    torch.manual_seed(0)
    cfg = load_config("wmask", ["model.sdf.layers=3", "model.sdf.hidden=32",
                                  "model.sdf.skip=[]"]).model.sdf
    net = SDFNetwork(cfg).double()
    x = (torch.rand(20, 3, dtype=torch.float64) - 0.5)
    want = []
    for p in x:
        hess = torch.autograd.functional.hessian(lambda q: net.sdf(q[None])[0, 0], p)
        want.append(hess.trace())
    torch.testing.assert_close(net.laplacian(x, 1e-3), torch.stack(want), rtol=1e-3,
                               atol=1e-3)


def test_the_term_is_the_masked_mean_of_absolute_laplacians():
    lap = torch.tensor([2.0, -4.0, 1.0, -8.0])
    mask = torch.tensor([1.0, 1.0, 0.0, 1.0])
    assert curvature(lap, mask).item() == pytest.approx(14.0 / 3.0, rel=1e-5)
    assert curvature(lap, torch.zeros(4)).item() == 0.0  # an empty mask: 0, not NaN


def test_the_step_with_the_term(small, sphere_scene, tmp_path):
    """On: the loss holds the weighted term, the metric reports it, the hash grid's level
    counter still counts one pass a step, and the term has a gradient; off: the metric is 0
    and no subset is drawn."""
    scene = sphere_scene(tmp_path / "s")
    on = load_config("demo", small + ["train.curvature_weight=0.01",
                                      "train.curvature_fraction=0.25", "train.compile=false",
                                      "model.sdf.gradient=analytic"])
    torch.manual_seed(0)
    model = make_model(on)
    inputs = draw_step_inputs(scene, on, 3, 32, torch.Generator().manual_seed(0), None)
    r = on.render
    k = math.ceil(0.25 * 32 * (r.n_samples + r.n_importance))
    assert inputs.curvature_idx is not None and inputs.curvature_idx.shape == (k,)
    loss, metrics, _ = render_and_loss(model, inputs, on, build_sampler(on.sampler), ())
    values = dict(zip(LOSS_NAMES, metrics.tolist(), strict=False))
    assert values["curvature_loss"] > 0
    off = load_config("demo", small + ["train.compile=false", "model.sdf.gradient=analytic"])
    inputs_off = draw_step_inputs(scene, off, 3, 32, torch.Generator().manual_seed(0), None)
    assert inputs_off.curvature_idx is None
    loss_off, m_off, _ = render_and_loss(model, inputs_off, off, build_sampler(off.sampler), ())
    assert dict(zip(LOSS_NAMES, m_off.tolist(), strict=False))["curvature_loss"] == 0.0
    # the same rays (the subset is drawn after them): the difference is the weighted term
    assert loss.item() - loss_off.item() == pytest.approx(0.01 * values["curvature_loss"],
                                                          rel=1e-3, abs=1e-6)
    grids = [m for m in model.modules() if isinstance(m, HashGridEncoding)]
    before = [int(m.steps) for m in grids]
    opt = make_optimizer(model, on)
    g = torch.Generator().manual_seed(1)
    for it in range(3):
        train_step(model, opt, scene, on, it, g, batch_size=16)
    assert [int(m.steps) for m in grids] == [b + 3 for b in before]


def test_range(small):
    assert load_config("demo").train.curvature_weight == 0.0
    with pytest.raises(ConfigError, match="curvature_weight"):
        load_config("demo", ["train.curvature_weight=-1"])
    with pytest.raises(ConfigError, match="curvature_fraction"):
        load_config("demo", ["train.curvature_fraction=0"])
