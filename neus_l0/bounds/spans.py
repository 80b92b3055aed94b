"""Per-ray bounds: where a ray's samples go, joined from the sphere and the narrowing bounds.

`ray_bounds` starts from NeuS's [mid - 1, mid + 1] (no culling) or the unit sphere's chord,
and narrows it by each `RayBounds` (visual hull, SfM point box, occupancy grid) in turn.
`packed_spans` packs the result for rays whose bounds never change (a pixel's ray under the
visual hull), so a step gathers them instead of computing them.

Shapes: B rays; `origins`, `dirs` (B, 3), `near`, `far` (B, 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import torch
from torch import Tensor

from neus_l0.bounds.sphere import near_far_from_sphere, sphere_chord
from neus_l0.config.schema import RenderConfig


class RayBounds(Protocol):
    """Something that narrows rays' [near, far] to where the surface can be.

    `neus_l0.bounds.occupancy.OccupancyGrid`, `neus_l0.bounds.hull.VisualHull` and
    `neus_l0.bounds.points.PointBound` are ones. Fixed shapes: no boolean indexing, no host
    synchronisation.
    """

    def ray_bounds(self, origins: Tensor, dirs: Tensor, near: Tensor,
                   far: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """origins, dirs (B, 3); near, far (B, 1) -> lo, hi (B, 1), hits (B,) bool."""
        ...


def join_bounds(static: Sequence[RayBounds], grid: RayBounds | None) -> tuple[RayBounds, ...]:
    """The bounds a ray batch is narrowed by, in order: the static ones (visual hull or SfM
    point box), then the occupancy grid when there is one."""
    return tuple(static) + ((grid,) if grid is not None else ())


def ray_bounds(origins: Tensor, dirs: Tensor, cfg: RenderConfig,
               bounds: Sequence[RayBounds] = ()) -> tuple[Tensor, Tensor, Tensor]:
    """Where each ray's samples go, and whether it gets any.

    Without culling (`cfg.cull_outside_sphere` off and no `bounds`): NeuS's [mid - 1,
    mid + 1] for every ray. Otherwise the chord of the unit sphere, narrowed in turn by each
    of `bounds`; a ray that misses the sphere or any of them is inactive.

    Args:
        origins, dirs: (B, 3) unit `dirs`.
        cfg: `cull_outside_sphere`.
        bounds: narrowing objects (visual hull, occupancy grid), applied in order.

    Returns:
        near, far: (B, 1) with far > near; active: (B,) bool.
    """
    return _ray_bounds(origins, dirs, cfg, bounds)[:3]


def packed_spans(origins: Tensor, dirs: Tensor, cfg: RenderConfig,
              bounds: Sequence[RayBounds] = ()) -> tuple[Tensor, Tensor]:
    """What `render_rays` would compute of each ray's bounds, packed for reuse as its `span`.

    For rays whose bounds never change (a pixel's ray under a visual hull), computed once.

    Returns:
        span: (B, 4) near, far, and where the ray enters and leaves the unit sphere;
        active: (B,) bool (see `ray_bounds`).
    """
    near, far, active, entry, exit_ = _ray_bounds(origins, dirs, cfg, bounds)
    return torch.cat([near, far, entry, exit_], dim=-1), active


def _ray_bounds(origins: Tensor, dirs: Tensor, cfg: RenderConfig,
                bounds: Sequence[RayBounds] = (), span: Tensor | None = None
                ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """`ray_bounds`, and (B, 1) where each ray enters and leaves the unit sphere (its `near`
    and `far` before `bounds` narrowed them; `near` and `far` themselves without culling).

    `span` (B, 4) from `packed_spans` replaces the sphere and the static bounds it was made
    with (its rays are active); `bounds` then narrows it further."""
    if span is not None:
        near, far, entry, exit_ = span[:, :, None].unbind(1)  # (B, 1) each
        active = torch.ones(origins.shape[0], dtype=torch.bool, device=near.device)
        for b in bounds:
            near, far, hits = b.ray_bounds(origins, dirs, near, far)
            active = active & hits
        if bounds:
            far = torch.maximum(far, near + 1e-6)
        return near, far, active, entry, exit_
    if not cfg.cull_outside_sphere and not bounds:
        near, far = near_far_from_sphere(origins, dirs)
        active = torch.ones(origins.shape[0], dtype=torch.bool, device=near.device)
        return near, far, active, near, far
    near, far, active = sphere_chord(origins, dirs)
    entry, exit_ = near, far
    for b in bounds:
        near, far, hits = b.ray_bounds(origins, dirs, near, far)
        active = active & hits
    far = torch.maximum(far, near + 1e-6)  # a tangent ray still gets a proper interval
    return near, far, active, entry, exit_
