"""Weights of (possibly weight-normalised) linear layers, computed once where that is safe.

`torch.nn.utils.parametrizations.weight_norm` recomputes ``g * v / |v|`` at every access of
``lin.weight``. Within one training step the SDF network is evaluated several times with the
same parameters (the up-sampling rounds without gradients, then the rendering pass), so
`layer_weight` keeps the weight computed without gradients until a parameter changes (its
version counter moves with every in-place update: optimiser steps, `load_state_dict`) and
recomputes it, with its graph, whenever gradients are enabled.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils import parametrize

_CACHE = "_neus_l0_weight_cache"


def layer_weight(lin: nn.Linear) -> Tensor:
    """The layer's weight (out, in); for a weight-normalised layer outside autograd, the
    cached ``g * v / |v|`` while `g` and `v` are unchanged."""
    return _weights(lin)[0]


def layer_weight_t(lin: nn.Linear) -> Tensor:
    """The transpose (in, out) of `layer_weight`, cached with it (one op less a call)."""
    return _weights(lin)[1]


def _weights(lin: nn.Linear) -> tuple[Tensor, Tensor]:
    """(weight (out, in), its transpose (in, out)), cached as `layer_weight` says."""
    if (not parametrize.is_parametrized(lin, "weight") or torch.is_grad_enabled()
            or torch.compiler.is_compiling()):
        w = lin.weight
        return w, w.t()
    originals = lin.parametrizations.weight
    g, v = originals.original0, originals.original1
    key = (g._version, v._version, g.data_ptr(), v.data_ptr(), g.dtype, g.device)
    cached = lin.__dict__.get(_CACHE)
    if cached is not None and cached[0] == key:
        return cached[1]
    w = lin.weight
    lin.__dict__[_CACHE] = (key, (w, w.t()))
    return w, w.t()


def linear(lin: nn.Linear, h: Tensor) -> Tensor:
    """`lin(h)` with `layer_weight`: h (..., in) -> (..., out); one ``addmm`` with the
    cached transpose for a 2-D `h` (what `F.linear` dispatches, less its transpose)."""
    if h.dim() != 2 or lin.bias is None:
        return F.linear(h, layer_weight(lin), lin.bias)
    return torch.addmm(lin.bias, h, layer_weight_t(lin))


def clear_weight_cache(module: nn.Module) -> None:
    """Forget every cached weight under `module` (call after each optimiser step).

    The version counters that `layer_weight` keys on do not move under every update: the
    fused Adam kernel writes the parameters without bumping them (measured, torch 2.13), so
    the training step clears the cache itself after the update.
    """
    for m in module.modules():
        m.__dict__.pop(_CACHE, None)
