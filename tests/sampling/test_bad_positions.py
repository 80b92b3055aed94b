"""The sampling kernels against unsorted or non-finite positions (issue #27): refused by the
public functions, never checked on the training path (`neus_l0.sampling`).
"""

from __future__ import annotations

import math

import pytest
import torch


def _positions(bad: str) -> torch.Tensor:
    """(3, 4, 9) sorted positions with ray [1, 2] (the 7th of the flattened batch) made bad."""
    t = torch.linspace(0.0, 1.0, 9, dtype=torch.float64).repeat(3, 4, 1)
    t[0, 0, 3:5] = 0.4  # repeated positions are sorted
    if bad == "unsorted":
        t[1, 2] = t[1, 2].flip(-1)
    elif bad != "good":
        t[1, 2, 4] = {"nan": math.nan, "inf": math.inf}[bad]
    return t


def _draw(name: str, t: torch.Tensor, **kw) -> torch.Tensor:
    from neus_l0.sampling import kernels

    w = torch.ones_like(t[..., :-1])
    if name == "sample_l0":
        return kernels.sample_l0(t, torch.ones_like(t), 8, **kw)
    if name == "sample_neus_sections":
        return kernels.sample_neus_sections(t, w, -w, w, 64.0, 8, **kw)
    return getattr(kernels, name)(t, w, 8, **kw)


SAMPLER_FUNCTIONS = ["sample_pdf", "sample_l0", "sample_l0_sections", "sample_neus_sections"]


@pytest.mark.parametrize("name", SAMPLER_FUNCTIONS)
@pytest.mark.parametrize("bad, what", [("unsorted", "1 are not sorted"),
                                       ("nan", "1 hold NaN or inf"),
                                       ("inf", "1 hold NaN or inf")])
def test_the_samplers_refuse_unsorted_or_non_finite_positions(name, bad, what):
    """Unsorted positions gave zeros, NaN ones NaN: a ValueError naming the function, the
    rays and the first bad one (the batch flattened)."""
    with pytest.raises(ValueError) as exc:
        _draw(name, _positions(bad))
    msg = str(exc.value)
    assert msg.startswith(f"{name}: ") and "finite and sorted" in msg
    assert f"of its 12 rays (the batch flattened), {what} (first: ray 6)" in msg


@pytest.mark.parametrize("name", SAMPLER_FUNCTIONS)
def test_the_samplers_draw_inside_sorted_positions(name):
    """Sorted positions, repeats included: finite, sorted samples inside each ray."""
    t = _positions("good")
    out = _draw(name, t)
    assert torch.isfinite(out).all() and (out.diff(dim=-1) >= 0).all()
    assert (out >= t[..., :1]).all() and (out <= t[..., -1:]).all()


@pytest.mark.parametrize("sampler", ["hvs", "l0", "l0-linear", "neus-exact"])
def test_the_training_path_never_checks_positions(sampler, monkeypatch):
    """NeuS's up-sampling passes check=False: no host synchronisation in the step."""
    from neus_l0.sampling import kernels
    from neus_l0.sampling.upsample import build_sampler, up_sample

    def never(*_a, **_k):
        raise AssertionError("the up-sampling checked its positions")

    monkeypatch.setattr(kernels, "check_positions", never)
    g = torch.Generator().manual_seed(0)
    origins = torch.tensor([[0.0, 0.0, -2.0]]).repeat(4, 1)
    dirs = torch.nn.functional.normalize(torch.randn(4, 3, generator=g) * 0.1
                                         + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    z = torch.linspace(1.0, 3.0, 16).repeat(4, 1)
    z_all, _ = up_sample(lambda p: p.norm(dim=-1) - 0.5, origins, dirs, z,
                         build_sampler(sampler), 8, 2)
    assert z_all.shape == (4, 24) and (z_all.diff(dim=-1) >= 0).all()
    with pytest.raises(AssertionError, match="checked"):
        _draw("sample_pdf", _positions("good"))  # the public functions do check
