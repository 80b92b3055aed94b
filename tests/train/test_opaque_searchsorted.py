"""The CUDA-only opaque search (`neus_l0.sampling.kernels.opaque_searchsorted`) equals
torch.searchsorted, eagerly and compiled; the CPU keeps the plain search."""

import pytest
import torch

from neus_l0.sampling.kernels import opaque_searchsorted, search_right


def _rows(seed=0):
    g = torch.Generator().manual_seed(seed)
    cdf = torch.rand(37, 11, generator=g).cumsum(-1)
    cdf = cdf / cdf[:, -1:]
    u = torch.rand(37, 9, generator=g)
    u[0, :3] = cdf[0, :3]  # ties: right=True puts them after
    return cdf, u


def test_the_wrapper_equals_searchsorted():
    cdf, u = _rows()
    expect = torch.searchsorted(cdf, u, right=True)
    assert torch.equal(opaque_searchsorted(cdf, u), expect)
    assert torch.equal(search_right(cdf, u), expect)
    assert opaque_searchsorted(cdf, u).dtype == torch.int64


def test_the_wrapper_compiles_as_an_opaque_op():
    cdf, u = _rows(1)

    def f(c, x):
        return opaque_searchsorted(c, x).clamp(max=c.shape[-1] - 1) * 2

    got = torch.compile(f, fullgraph=True, dynamic=False)(cdf, u)
    assert torch.equal(got, f(cdf, u))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_on_cuda_the_search_goes_through_the_op():
    cdf, u = (x.cuda() for x in _rows(2))
    assert torch.equal(search_right(cdf, u), torch.searchsorted(cdf, u, right=True))
