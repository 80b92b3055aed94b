"""Extracting a trained SDF's level set a little inside its zero level (`neus-l0 mesh --inset
K`, issue #35).

Measured on the synthetic scenes' exact SDFs, the zero level of a trained NeuS field sits
outside the true surface: the median mesh point lies 0.01-0.22 world units out and 53-69 %
of them lie outside, about 0.1-0.9 of the logistic's scale 1/s (NeuS's learned sharpness s,
``model.variance.inv_s()``), the width over which the rendering weights spread. The level
``f = -K / s`` is extracted instead: the mesh moves inward by K / s along the SDF's normal,
an offset that shrinks as training sharpens s. Off by default: at K = 0.5 it lowered the
Chamfer of 10 of 13 meshes (0.98x at 400x300, 0.95x on the demo scene; measured by moving
the vertices K/s along their normals, the option itself checked on two) but not on every
scene, and the demo's thin horn rose 13 % (docs/BENCHMARKS.md, issue #35's section).

Pure functions, except that `inset` wraps a model for `neus_l0.mesh.extract.extract_mesh`.
"""

from __future__ import annotations

import torch
from torch import Tensor


def logistic_scale(model) -> float:
    """1/s of a trained model (normalised units): the width of NeuS's logistic density."""
    with torch.no_grad():
        return float(1.0 / model.variance.inv_s().reshape(-1)[0].item())


class _InsetSdf:
    """An SDF network's ``sdf(p)`` plus a constant (its zero level moves inward)."""

    def __init__(self, sdf_net, delta: float):
        self.net = sdf_net
        self.delta = float(delta)

    def sdf(self, p: Tensor) -> Tensor:
        """(N, 1) the network's SDF at p (N, 3), raised by delta."""
        return self.net.sdf(p) + self.delta


class _InsetModel:
    """What `neus_l0.mesh.extract.extract_mesh` and the mesh steps read of a model, its SDF
    raised by `delta` (`inset`)."""

    def __init__(self, model, delta: float):
        self.sdf = _InsetSdf(model.sdf, delta)
        self.color = getattr(model, "color", None)


def inset(model, k: float) -> tuple[object, float]:
    """`model` whose zero level is the trained SDF's level ``-k / s`` (`logistic_scale`), and
    that offset in normalised units; `model` itself and 0.0 when k == 0.

    Raises:
        ValueError: k < 0 or not finite.
    """
    k = float(k)
    if not k >= 0 or k == float("inf"):
        raise ValueError(f"inset: K must be a finite number >= 0, got {k}")
    if k == 0:
        return model, 0.0
    delta = k * logistic_scale(model)
    return _InsetModel(model, delta), delta
