"""`sampler.compile` (was `render.compile_sampler`) is deprecated: the whole-step compile
(`train.compile`) covers the draw. Old configs still load, with one warning, and draw
eagerly; the eager L0 draws survive adversarial weights.
"""

import warnings

import pytest
import torch

import neus_l0.sampling.upsample as samplers_module
from neus_l0.config.load import load_config
from neus_l0.config.schema import SAMPLERS, SamplerConfig
from neus_l0.sampling.kernels import sample_l0
from neus_l0.sampling.upsample import L0Sampler, Sections, build_sampler


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


@pytest.fixture()
def fresh_warning(monkeypatch):
    monkeypatch.setattr(samplers_module, "_COMPILE_WARNED", False)


def test_sampler_compile_warns_once_and_draws_eagerly(fresh_warning):
    g = torch.Generator().manual_seed(1)
    z = torch.sort(torch.rand(16, 9, generator=g), dim=-1).values
    w = torch.rand(16, 8, generator=g)
    sec = Sections(z=z, weights=w, prev_sdf=torch.zeros_like(w), next_sdf=-torch.ones_like(w),
                   inv_s=64.0)
    with pytest.warns(FutureWarning, match="train.compile=true"):
        build_sampler(SamplerConfig(name="l0", compile=True))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per process: no second warning
        for name in SAMPLERS:
            a = build_sampler(SamplerConfig(name=name, pad=0.001)).draw(sec, 8)
            b = build_sampler(SamplerConfig(name=name, pad=0.001, compile=True)).draw(sec, 8)
            assert torch.equal(a, b), name
        assert L0Sampler(compile=True)._draw is sample_l0


def test_old_configs_with_compile_still_load(tmp_path, fresh_warning):
    p = tmp_path / "old.yaml"
    p.write_text("sampler: l0\nrender: {compile_sampler: true, n_samples: 16}\n")
    cfg = load_config(str(p))
    assert cfg.sampler.compile is True
    with pytest.warns(FutureWarning):
        sampler = build_sampler(cfg.sampler)
    assert sampler._draw is sample_l0
    assert load_config("demo", ["sampler.compile=true"]).sampler.compile is True
