"""The SDF's spatial gradient three ways (`model.sdf.gradient`): analytic == autograd in
float64 (values and parameter gradients through one backward), finite differences converge
at second order, and the hash grid's steps and the weight-norm cache behave."""

import pytest
import torch

from neus_l0.config.schema import EncodingConfig, ModelConfig, SDFConfig
from neus_l0.errors import ConfigError
from neus_l0.fields.encodings import FrequencyEncoding, HashGridEncoding
from neus_l0.fields.linear import layer_weight
from neus_l0.fields.model import build_model
from neus_l0.fields.sdf import sdf_and_gradient


def _grid(**kw) -> EncodingConfig:
    args = dict(kind="hashgrid", n_levels=4, n_features=2, log2_hashmap_size=8,
                base_resolution=3, per_level_scale=1.7, n_freqs=0, init_scale=0.5)
    args.update(kw)
    return EncodingConfig(**args)


CASES = {
    "grid": SDFConfig(hidden=24, layers=2, skip=[], feature_dim=5, encoding=_grid()),
    "grid-progressive-lr": SDFConfig(hidden=24, layers=2, skip=[], feature_dim=5,
                                     encoding=_grid(start_level=2, update_steps=3,
                                                    lr_scale=3.0, bound=1.2)),
    "grid-bands-skip-scale": SDFConfig(hidden=40, layers=3, skip=[2], feature_dim=4,
                                       scale=1.7, encoding=_grid(n_freqs=2)),
    "freq-skip-wn-scale": SDFConfig(hidden=48, layers=4, skip=[2], feature_dim=6, scale=0.8,
                                    encoding=EncodingConfig(n_freqs=4)),
    "freq-no-input": SDFConfig(hidden=32, layers=2, skip=[], feature_dim=3, weight_norm=False,
                               encoding=EncodingConfig(n_freqs=3, include_input=False)),
    "identity": SDFConfig(hidden=16, layers=2, skip=[1], feature_dim=2,
                          encoding=EncodingConfig(kind="identity")),
}


def _net(cfg: SDFConfig, seed: int = 0):
    """A float64 SDF network with every parameter random (geometric init would zero the
    encoded columns of the first layer, hiding the encoding's derivative)."""
    torch.manual_seed(seed)
    net = build_model(ModelConfig(sdf=cfg)).sdf.double()
    with torch.no_grad():
        for name, p in net.named_parameters():
            if name.endswith("original0"):  # weight norm's g: keep the signal alive
                p.uniform_(1.0, 3.0)
            else:
                p.normal_(0.0, 0.4)
    return net


def _points(n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.9


def _rewind(net) -> None:
    """Undo the last training pass's count of a progressive hash grid (so that two methods
    are compared at the same step of the schedule)."""
    if isinstance(net.encoding, HashGridEncoding):
        with torch.no_grad():
            net.encoding.steps -= 1


@pytest.mark.parametrize("name", list(CASES))
def test_analytic_equals_autograd_in_float64(name):
    net = _net(CASES[name])
    x = _points(300)
    for _ in range(9):  # progressive: walk over the schedule (2, then 3, then 4 levels)
        ref_out, ref_grad = sdf_and_gradient(net, x, create_graph=True, method="autograd")
        _rewind(net)
        out, grad = sdf_and_gradient(net, x, create_graph=True, method="analytic")
        assert torch.allclose(out, ref_out, rtol=0, atol=1e-12)
        assert torch.allclose(grad, ref_grad, rtol=0, atol=1e-5)
        assert ref_grad.abs().max() > 0.1  # not trivially zero
    if isinstance(net.encoding, HashGridEncoding) and net.encoding.start_level < 4:
        assert int(net.encoding.active_levels()) == 4  # masked levels were exercised


@pytest.mark.parametrize("name", ["grid-progressive-lr", "grid-bands-skip-scale",
                                  "freq-skip-wn-scale"])
def test_analytic_parameter_gradients_equal_the_double_backward(name):
    """A loss on the value, the normal (Eikonal) and a colour-like use of the normal: one
    ordinary backward through the analytic gradient == autograd's double backward."""
    net = _net(CASES[name])
    x = _points(200, seed=2)
    d = torch.nn.functional.normalize(_points(200, seed=3), dim=-1)
    params = [p for p in net.parameters() if p.requires_grad]

    def loss(method):
        out, grad = sdf_and_gradient(net, x, create_graph=True, method=method)
        eik = ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        return eik + (out[:, 1:] * (grad * d).sum(-1, keepdim=True)).mean() + out[:, 0].mean()

    ref = torch.autograd.grad(loss("autograd"), params)
    _rewind(net)
    got = torch.autograd.grad(loss("analytic"), params)
    # (softplus returns z itself where beta z > 20: its derivative there is exactly 1 for
    # autograd and sigmoid(beta z) >= 1 - 2e-9 for the analytic path)
    for r, g in zip(ref, got, strict=True):
        assert torch.allclose(g, r, rtol=1e-6, atol=1e-7 * r.abs().max().item())
    assert sum(r.abs().sum() for r in ref) > 0


def test_encoding_jacobians_match_autograd():
    x = _points(20)
    for enc in (FrequencyEncoding(3, 3), FrequencyEncoding(3, 2, include_input=False),
                HashGridEncoding(EncodingConfig(kind="hashgrid", n_levels=3, log2_hashmap_size=6,
                                                base_resolution=2, per_level_scale=2.0,
                                                n_freqs=1, init_scale=1.0, bound=1.3)).double()):
        out, jac = enc.forward_jacobian(x)
        assert torch.allclose(out, enc(x), atol=1e-12)
        ref = torch.autograd.functional.jacobian(lambda p, e=enc: e(p).sum(0), x)  # (D, N, 3)
        assert torch.allclose(jac, ref.permute(1, 2, 0), atol=1e-12)


def test_analytic_is_zero_outside_the_grid_box_along_clamped_axes():
    net = _net(SDFConfig(hidden=16, layers=1, skip=[], feature_dim=2, weight_norm=False,
                         encoding=_grid(include_input=False)))
    x = torch.tensor([[1.5, 0.1, -0.2], [0.3, -2.0, 0.4]], dtype=torch.float64)
    _, g = sdf_and_gradient(net, x, create_graph=False, method="analytic")
    _, ref = sdf_and_gradient(net, x, create_graph=False, method="autograd")
    assert g[0, 0] == 0 and g[1, 1] == 0
    assert torch.allclose(g, ref, atol=1e-12)


def test_finite_differences_converge_at_second_order():
    net = _net(CASES["freq-skip-wn-scale"])
    with torch.no_grad():  # a smooth network: soften the softplus kinks
        net.beta = 2.0
    x = _points(64, seed=4)
    _, exact = sdf_and_gradient(net, x, create_graph=False, method="autograd")
    errs = []
    for h in (4e-2, 2e-2, 1e-2, 5e-3):
        _, g = net.forward_and_finite_difference(x, step=h)
        errs.append((g - exact).abs().max().item())
    ratios = [a / b for a, b in zip(errs, errs[1:], strict=False)]
    assert all(3.6 < r < 4.4 for r in ratios), (errs, ratios)
    # the configured step (1e-3 of the input, divided by scale) is accurate
    out, g = sdf_and_gradient(net, x, create_graph=False, method="finite-difference")
    assert net.finite_difference_step() == pytest.approx(1e-3 / 0.8)
    assert torch.allclose(g, exact, rtol=1e-4, atol=1e-3)
    assert torch.allclose(out, net(x), atol=1e-12)


def test_finite_difference_step_follows_the_finest_active_level():
    cfg = CASES["grid-progressive-lr"]
    net = _net(cfg)
    enc = net.encoding
    x = _points(8)
    steps = []
    for _ in range(7):
        steps.append(float(net.finite_difference_step()))
        _, g = sdf_and_gradient(net, x, create_graph=True, method="finite-difference")
        assert g.requires_grad and torch.isfinite(g).all()
    res = enc.resolutions
    # 2 levels active for 3 passes, then 3, then 4: half a cell of the finest active level
    assert steps == pytest.approx([1.2 / res[1]] * 3 + [1.2 / res[2]] * 3 + [1.2 / res[3]])
    assert int(enc.steps) == 7  # one training pass per call, not seven


@pytest.mark.parametrize("method", ["analytic", "finite-difference"])
def test_training_pass_count_and_detached_gradient(method):
    net = _net(CASES["grid-progressive-lr"])
    x = _points(8)
    sdf_and_gradient(net, x, create_graph=True, method=method)
    assert int(net.encoding.steps) == 1
    with torch.no_grad():
        out, g = sdf_and_gradient(net, x, create_graph=False, method=method)
    assert int(net.encoding.steps) == 1 and not g.requires_grad
    out, g = sdf_and_gradient(net, x, create_graph=False, method=method)
    assert not g.requires_grad and out.requires_grad


def test_configured_method_and_errors():
    cfg = SDFConfig(hidden=16, layers=1, skip=[], feature_dim=2, gradient="analytic",
                    encoding=EncodingConfig(n_freqs=2))
    net = _net(cfg)
    assert net.gradient == "analytic"
    x = _points(10)
    _, g = sdf_and_gradient(net, x, create_graph=True)
    _, ref = sdf_and_gradient(net, x, create_graph=True, method="autograd")
    assert torch.allclose(g, ref, atol=1e-8)
    with pytest.raises(ConfigError, match="model.sdf.gradient"):
        build_model(ModelConfig(sdf=SDFConfig(gradient="numerical")))
    with pytest.raises(ValueError, match="unknown gradient method"):
        sdf_and_gradient(net, x, create_graph=False, method="numerical")


def test_weight_norm_weight_is_cached_without_gradients_only():
    net = _net(CASES["freq-skip-wn-scale"])
    lin = net.layers[0]
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    x = _points(16)
    with torch.no_grad():
        w1 = layer_weight(lin)
        assert layer_weight(lin) is w1  # cached
        y1 = net(x)
    assert torch.equal(w1, lin.weight.detach())
    w_grad = layer_weight(lin)
    assert w_grad.requires_grad and w_grad is not w1  # with gradients: recomputed, graph kept
    net(x).square().sum().backward()
    assert lin.parametrizations.weight.original1.grad.abs().sum() > 0
    opt.step()
    with torch.no_grad():
        w2 = layer_weight(lin)
        assert w2 is not w1 and not torch.equal(w2, w1)  # the optimiser step invalidates it
        assert torch.equal(w2, lin.weight)
        assert not torch.equal(net(x), y1)
        net.load_state_dict({k: v.clone() for k, v in net.state_dict().items()})
        assert layer_weight(lin) is not w2  # load_state_dict too


@pytest.mark.parametrize("method", ["analytic", "finite-difference"])
def test_no_graph_breaks_for_torch_compile(method):
    """The two methods without double backward trace into one graph (progressive hash grid:
    the step count and the finest active level stay tensors, no host reads)."""
    torch._dynamo.reset()
    net = _net(CASES["grid-progressive-lr"]).float()
    x = _points(64).float()

    def f(p):
        out, g = sdf_and_gradient(net, p, create_graph=True, method=method)
        with torch.no_grad():
            s = net.sdf(p)
        return out, g, s

    explained = torch._dynamo.explain(f)(x)
    assert explained.graph_break_count == 0 and explained.graph_count == 1


def test_training_steps_match_autograd_end_to_end(tiny_scene):
    """The demo config's training step (one backward for `analytic`) gives autograd's
    losses step after step from the same state; finite differences stay close at first."""
    from neus_l0.config.load import load_config
    from neus_l0.fields.model import make_model
    from neus_l0.formats.neus import load_scene
    from neus_l0.train.step import make_optimizer, train_step

    scene = load_scene(tiny_scene)
    losses = {}
    for method in ("autograd", "analytic", "finite-difference"):
        cfg = load_config("demo", [f"model.sdf.gradient={method}", "train.batch_size=64"])
        torch.manual_seed(0)
        model = make_model(cfg)
        opt = make_optimizer(model, cfg)
        gen = torch.Generator().manual_seed(1)
        losses[method] = torch.stack([train_step(model, opt, scene, cfg, it, gen)[0]
                                      for it in range(6)])
    assert torch.allclose(losses["analytic"], losses["autograd"], rtol=1e-5, atol=1e-6)
    assert torch.allclose(losses["finite-difference"][:2], losses["autograd"][:2], rtol=0.05)
