"""The retired `sampler.compile` (was `render.compile_sampler`): the whole-step compile
(`train.compile`) covers the draw. Old configs and checkpoints still load, with one
warning, and draw as today's; the eager L0 draws survive adversarial weights.
"""

import pytest
import torch

from neus_l0.config.load import config_from_dict, load_config, to_dict
from neus_l0.config.schema import Config
from neus_l0.sampling.kernels import sample_l0


def _adversarial(B: int, N: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N) sorted positions and weights with the cases the sampler must survive."""
    g = torch.Generator().manual_seed(seed)
    t = torch.sort(torch.rand(B, N, generator=g), dim=-1).values
    w = torch.rand(B, N, generator=g) ** 6
    w[0] = 0.0                        # an all-zero ray
    w[1, ::2] = float("nan")          # non-finite weights count as zero
    w[2, N // 2] = 1e30               # one huge spike
    w[3] = 0.25                       # equal neighbours everywhere (a == b)
    w[4, 1:] = 1e-38                  # ratios beyond 1 / tiny
    w[5, -1] = float("inf")
    return t, w


@pytest.mark.parametrize("kind", ["exp", "linear", "inverse"])
@pytest.mark.parametrize("pad", [0.0, 0.001, 0.01])
def test_eager_draws_survive_adversarial_weights(kind, pad):
    for seed, (B, N) in enumerate([(16, 9), (40, 33)]):
        t, w = _adversarial(B, N, seed)
        s = sample_l0(t, w, 12, kind=kind, det=True, pad=pad)
        assert s.shape == (B, 12) and torch.isfinite(s).all(), (kind, pad, B, N)
        assert (s[:, 1:] >= s[:, :-1]).all()
        assert (s >= t[:, :1]).all() and (s <= t[:, -1:]).all()
        if pad == 0.0:  # the all-zero ray is uniform: as a ray of equal weights
            ref = sample_l0(t[:1], torch.ones_like(t[:1]), 12, kind=kind, det=True, pad=0.0,
                            blur=False)
            torch.testing.assert_close(s[0], ref[0], rtol=1e-5, atol=1e-5)


def test_old_configs_with_compile_load_with_one_warning(tmp_path):
    p = tmp_path / "old.yaml"
    p.write_text("sampler: l0\nrender: {compile_sampler: true, n_samples: 16}\n")
    with pytest.warns(FutureWarning, match="render.compile_sampler"):
        cfg = load_config(str(p))
    assert cfg.render.n_samples == 16 and cfg.sampler.name == "l0"
    assert not hasattr(cfg.sampler, "compile")
    with pytest.warns(FutureWarning, match="sampler.compile"):
        assert load_config("demo", ["sampler.compile=true"]) == load_config("demo")


def test_a_checkpoint_config_with_compile_loads_as_todays(recwarn):
    old = to_dict(Config())
    old["sampler"]["compile"] = False  # what sessions 1-5 dumped
    assert config_from_dict(old) == Config()
    assert any("sampler.compile" in str(w.message) for w in recwarn.list)


@pytest.mark.slow
def test_the_compiled_inverse_sections_draw_matches_eager():
    """Constant pieces carry L = sqrt(tiny); compiled kernels' expm1 of that can be 0, which
    made the inverse kind's position 0 / 0 (NaN) and stopped the compiled training step with
    an out-of-bounds hash-grid index. The draw now takes the series for small |L|."""
    import torch

    from neus_l0.sampling.kernels import sample_l0_sections

    torch.manual_seed(0)
    z = torch.sort(torch.rand(128, 33) * 2.0 + 0.5, dim=-1).values
    w = torch.rand(128, 32) ** 8
    w[::3] = 0.0
    w[1::7, 5:] = 1e-30

    def draw(z, w):
        return sample_l0_sections(z, w, 16, "inverse", det=True, check=False)

    eager = draw(z, w)
    assert torch.isfinite(eager).all()
    compiled = torch.compile(draw, fullgraph=True, dynamic=False)(z, w)
    assert torch.isfinite(compiled).all()
    assert torch.allclose(compiled, eager, atol=1e-5)
