"""`sampler.compile` (was `render.compile_sampler`): the compiled L0 draw against the eager one.

Compilation costs seconds per (kind, pad, shape family), so the default run checks the
configuration training uses (``exp``, pad 0.001, two batch shapes through one dynamic graph)
on adversarial weights; the slow test covers ``linear`` and pad 0 as well.
"""

import pytest
import torch

from neus_l0.samplers import SAMPLERS, L0Sampler, Sections, build_sampler
from neus_l0.sampling import sample_l0


@pytest.fixture(scope="module")
def compiled():
    pytest.importorskip("torch._inductor")
    return L0Sampler(kind="exp", compile=True)._draw


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


def _check(compiled, kinds, pads, shapes):
    for seed, (B, N) in enumerate(shapes):
        t, w = _adversarial(B, N, seed)
        for kind in kinds:
            for pad in pads:
                eager = sample_l0(t, w, 12, kind=kind, det=True, pad=pad)
                comp = compiled(t, w, 12, kind=kind, det=True, pad=pad)
                assert torch.isfinite(comp).all(), (kind, pad, B, N)
                torch.testing.assert_close(comp, eager, rtol=1e-5, atol=1e-5)


def test_compiled_exp_draw_equals_eager(compiled):
    _check(compiled, ["exp"], [0.001], [(16, 9), (40, 33)])


@pytest.mark.slow
def test_compiled_linear_and_unpadded_draws_equal_eager(compiled):
    _check(compiled, ["exp", "linear"], [0.0, 0.001, 0.01], [(8, 6), (16, 9), (64, 65)])


def test_the_compiled_sampler_draws_as_the_eager_one(compiled):
    from neus_l0.config import SamplerConfig

    g = torch.Generator().manual_seed(1)
    z = torch.sort(torch.rand(16, 9, generator=g), dim=-1).values
    w = torch.rand(16, 8, generator=g)
    sec = Sections(z=z, weights=w, prev_sdf=torch.zeros_like(w), next_sdf=-torch.ones_like(w),
                   inv_s=64.0)
    for name in SAMPLERS:  # l0-inverse, hvs and neus-exact stay eager
        a = build_sampler(SamplerConfig(name=name, pad=0.001)).draw(sec, 8)
        b = build_sampler(SamplerConfig(name=name, pad=0.001, compile=True)).draw(sec, 8)
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
