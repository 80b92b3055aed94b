"""NeuS's SDF network: an MLP with a skip connection, softplus(beta=100), geometric init,
and three ways to get its spatial gradient (`sdf_and_gradient`).

- ``autograd``: `torch.autograd.grad` of the output wrt the input; in training the graph of
  that gradient is kept (``create_graph``), so the loss's backward is a double backward.
- ``analytic``: the encoding's Jacobian in closed form (`Encoding.forward_jacobian`) carried
  forward through every Linear + softplus layer (value and d/dx, d/dy, d/dz together): the
  gradient is an ordinary differentiable tensor expression and the loss needs ONE ordinary
  backward. Equal to ``autograd`` to rounding.
- ``finite-difference``: central differences, the network evaluated at x and x +- h e_j in
  one batched pass (7 points per point); second-order accurate. With a hash grid h is half
  the cell of the finest ACTIVE level (the +-h stencil spans one cell: Neuralangelo ties its
  step to the finest active level too, so the gradient reaches the neighbouring cells'
  entries and sharpens as levels switch on), otherwise 1e-3 of the network's input. The
  4-point tetrahedral stencil is not offered: its gradient is only first-order accurate
  (its h^2 terms cancel only where the Hessian is diagonal).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm

from neus_l0.config.schema import SDFConfig
from neus_l0.errors import ConfigError
from neus_l0.fields.encodings import HashGridEncoding, build_encoding
from neus_l0.fields.linear import layer_weight_t, linear

#: Choices of `SDFConfig.gradient`.
GRADIENT_METHODS = ("autograd", "analytic", "finite-difference")

#: Finite-difference step of networks without a hash grid, in the network's input units.
FD_STEP = 1e-3


class SDFNetwork(nn.Module):
    """f(x) -> (sdf, feature). With geometric init the SDF starts as |x| - bias.

    Attributes:
        feature_dim: length of the feature vector returned after the SDF.
    """

    def __init__(self, cfg: SDFConfig) -> None:
        super().__init__()
        if cfg.gradient not in GRADIENT_METHODS:
            raise ConfigError(f"model.sdf.gradient: unknown choice {cfg.gradient!r} "
                              f"(choose from {', '.join(GRADIENT_METHODS)})")
        self.gradient = cfg.gradient
        self.encoding = build_encoding(cfg.encoding, 3)
        self.scale = cfg.scale
        self.skip = set(cfg.skip)
        self.feature_dim = cfg.feature_dim
        d_in = self.encoding.out_dim
        if self.skip and cfg.hidden <= d_in:
            raise ConfigError(f"model.sdf.hidden={cfg.hidden} must exceed the encoded input "
                              f"size {d_in} when model.sdf.skip is used")
        dims = [d_in] + [cfg.hidden] * cfg.layers + [1 + cfg.feature_dim]
        n_lin = len(dims) - 1
        layers = []
        for i in range(n_lin):
            in_dim = dims[i]  # for a skip layer this counts the re-concatenated input
            out_dim = dims[i + 1] - d_in if (i + 1) in self.skip else dims[i + 1]
            lin = nn.Linear(in_dim, out_dim)
            if cfg.geometric_init:
                _geometric_init(lin, i, n_lin, d_in, self.encoding.raw_dims,
                                i in self.skip, cfg.bias)
            layers.append(weight_norm(lin) if cfg.weight_norm else lin)
        self.layers = nn.ModuleList(layers)
        self.beta = cfg.softplus_beta
        self.activation = nn.Softplus(beta=cfg.softplus_beta)

    def forward(self, x: Tensor, count: bool = True) -> Tensor:
        """x (N, 3) in the normalised frame -> (N, 1 + feature_dim): sdf then feature
        (`count`: whether a training pass counts for the hash grid's level schedule)."""
        inputs = self.encoding(x * self.scale if self.scale != 1.0 else x, count=count)
        h = inputs
        last = len(self.layers) - 1
        for i, lin in enumerate(self.layers):
            if i in self.skip:
                h = torch.cat([h, inputs], dim=-1) / math.sqrt(2.0)
            h = linear(lin, h)
            if i < last:
                h = F.softplus(h, self.beta)
        return self._unscale(h)

    def _unscale(self, h: Tensor) -> Tensor:
        """(N, 1 + F) -> the same with the SDF divided by `scale`."""
        if self.scale == 1.0:
            return h
        return torch.cat([h[:, :1] / self.scale, h[:, 1:]], dim=-1)

    def forward_and_gradient(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The output and the SDF's spatial gradient by forward-mode differentiation.

        The encoding's Jacobian (N, 3, D) is carried through the MLP beside the value:
        a Linear layer maps it by W (the same weight, computed once), softplus multiplies
        it by sigmoid(beta z), a skip concatenates the input's Jacobian (and divides by
        sqrt 2 as the value). Only the SDF column of the last layer is propagated. With the
        input scale s the SDF is h_0(s x) / s, whose gradient is h_0'(s x): the Jacobian
        wrt the scaled input. Gradients wrt the parameters flow through both outputs by an
        ordinary backward.

        Args:
            x: (N, 3) points.

        Returns:
            output (N, 1 + feature_dim) as `forward`, gradient (N, 3).
        """
        inputs, jin = self.encoding.forward_jacobian(x * self.scale if self.scale != 1.0
                                                     else x)  # (N, D), (N, 3, D)
        h, jac = inputs, jin
        last = len(self.layers) - 1
        for i, lin in enumerate(self.layers):
            if i in self.skip:
                h = torch.cat([h, inputs], dim=-1) / math.sqrt(2.0)
                jac = torch.cat([jac, jin], dim=-1) / math.sqrt(2.0)
            wt = layer_weight_t(lin)  # (in, out)
            if i == last:
                h = torch.addmm(lin.bias, h, wt) if lin.bias is not None else h @ wt
                jac = jac @ wt[:, :1]  # (N, 3, 1): the SDF's column only
            else:
                z = torch.addmm(lin.bias, h, wt) if lin.bias is not None else h @ wt
                h = F.softplus(z, self.beta)
                jac = (jac @ wt) * torch.sigmoid(z * self.beta)[:, None, :]
        return self._unscale(h), jac[..., 0]

    def finite_difference_step(self) -> Tensor | float:
        """The step h of `finite-difference` in the normalised frame: half the cell of the
        hash grid's finest active level (a tensor, no host sync), else `FD_STEP`; both
        divided by `scale` (the network sees x * scale)."""
        enc = self.encoding
        if isinstance(enc, HashGridEncoding):
            return enc.bound / (enc.finest_active_resolution() * self.scale)
        return FD_STEP / self.scale

    def forward_and_finite_difference(self, x: Tensor, step: Tensor | float | None = None
                                      ) -> tuple[Tensor, Tensor]:
        """The output and central differences of the SDF, in one pass over 7 N points.

        Args:
            x: (N, 3) points.
            step: h (None: `finite_difference_step()`).

        Returns:
            output (N, 1 + feature_dim) at x, gradient (N, 3): (f(x + h e_j) - f(x - h e_j))
            / 2h, h = `finite_difference_step()`.
        """
        n = x.shape[0]
        h = self.finite_difference_step() if step is None else step
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        taps = torch.cat([eye.new_zeros(1, 3), eye, -eye]) * h  # (7, 3)
        out = self.forward((x + taps[:, None, :]).view(7 * n, 3)).view(7, n, -1)
        sdf = out[1:, :, 0]  # (6, N)
        grad = (sdf[:3] - sdf[3:]).t() / (2.0 * h)  # (N, 3)
        return out[0], grad

    def laplacian(self, x: Tensor, step: Tensor | float | None = None) -> Tensor:
        """The SDF's Laplacian by central differences, in one pass over 7 N points.

        Args:
            x: (N, 3) points (not differentiated through); step: h (None:
                `finite_difference_step()`).

        Returns:
            (N,) ``(sum_j f(x + h e_j) + f(x - h e_j) - 6 f(x)) / h^2`` in the normalised frame
            (the network's input x; exact for quadratics). The pass does not count for the
            hash grid's level schedule (it is the step's second).
        """
        n = x.shape[0]
        h = self.finite_difference_step() if step is None else step
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        taps = torch.cat([eye.new_zeros(1, 3), eye, -eye]) * h  # (7, 3)
        f = self.forward((x.detach() + taps[:, None, :]).view(7 * n, 3), count=False)
        f = f[:, 0].view(7, n)
        return (f[1:].sum(0) - 6.0 * f[0]) / (h * h)

    def sdf(self, x: Tensor) -> Tensor:
        """x (N, 3) -> sdf (N, 1)."""
        return self.forward(x)[:, :1]


def _geometric_init(lin: nn.Linear, i: int, n_lin: int, d_in: int, raw_dims: int,
                    is_skip: bool, bias: float) -> None:
    """IDR / SAL initialisation so that the network starts as the SDF |x| - bias."""
    out_dim = lin.out_features
    with torch.no_grad():
        if i == n_lin - 1:
            nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(lin.in_features),
                            std=1e-4)
            nn.init.constant_(lin.bias, -bias)
            return
        nn.init.constant_(lin.bias, 0.0)
        nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(out_dim))
        if i == 0 and d_in > raw_dims:
            lin.weight[:, raw_dims:] = 0.0  # only the raw point drives the first layer
        elif is_skip and d_in > raw_dims:
            lin.weight[:, -(d_in - raw_dims):] = 0.0  # encoded part of the skip input


def sdf_and_gradient(net: SDFNetwork, x: Tensor, create_graph: bool,
                     method: str | None = None) -> tuple[Tensor, Tensor]:
    """One forward pass and the SDF's spatial gradient.

    Args:
        net: the SDF network.
        x: (N, 3) points (need not require grad; they are not differentiated through).
        create_graph: keep the graph of the gradient (for the Eikonal loss and the colour
            network's normal input in training); False returns it detached.
        method: `autograd`, `analytic` or `finite-difference` (see the module docstring);
            None: the network's configured `gradient` (`autograd` for a module without
            that attribute).

    Returns:
        output (N, 1 + feature_dim) and gradient (N, 3). With `autograd` the output always
        carries its graph (it is computed with gradients enabled); with the other methods
        it follows the caller's grad mode, and so does the progressive hash grid's count
        of training passes.
    """
    if method is None:  # stand-ins of SDFNetwork (any module with forward) get autograd
        method = getattr(net, "gradient", "autograd")
    if method != "autograd":
        if method == "analytic":
            out, grad = net.forward_and_gradient(x.detach())
        elif method == "finite-difference":
            out, grad = net.forward_and_finite_difference(x.detach())
        else:
            raise ValueError(f"unknown gradient method {method!r} ({GRADIENT_METHODS})")
        return out, grad if create_graph else grad.detach()
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        out = net(x)
        (grad,) = torch.autograd.grad(out[:, :1], x, torch.ones_like(out[:, :1]),
                                      create_graph=create_graph)
    return out, grad
