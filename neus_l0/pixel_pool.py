"""The pixels worth drawing in training: those whose rays can reach the surface.

With culling on (`render.cull_outside_sphere`, a visual hull), a ray that misses the unit
sphere or the hull has zero opacity inside its bounds by construction: rendered, it costs
network work and gives no gradient (its colour is the background constant, its mask term
BCE(0, mask) a constant). So training draws its rays from the other pixels only, keeping
every batch's shape fixed and every ray useful; `neus_l0.losses.neus_loss` scales the mask
term by the pool's fraction of all pixels, which keeps NeuS's expected gradient (the
colour term is a mean over foreground rays, which all lie in the pool). With a background
model every pixel counts, and there is no pool.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
from torch import Tensor

from neus_l0.config import RenderConfig
from neus_l0.data.rays import image_rays
from neus_l0.data.scene import Scene
from neus_l0.rendering import RayBounds, ray_bounds


@dataclasses.dataclass
class PixelPool:
    """Pixels to draw training rays from.

    Attributes:
        pixels: (P,) int64 flat indices ``view * H * W + y * W + x``, on the scene's device.
        fraction: P over all pixels of the scene.
    """

    pixels: Tensor
    fraction: float


def reachable_pixels(scene: Scene, cfg: RenderConfig, bounds: Sequence[RayBounds] = (),
                     background: bool = False, chunk: int = 1 << 16) -> PixelPool | None:
    """The pixels whose rays cross the unit sphere and every one of `bounds`.

    Args:
        scene: the scene (its device does the work).
        cfg: `cull_outside_sphere`.
        bounds: static narrowing objects (a visual hull; not the occupancy grid, which
            changes during training).
        background: whether a background model renders the rays (then: None).
        chunk: rays per `ray_bounds` call.

    Returns:
        the pool, or None when every pixel counts (no culling, a background model, or no
        pixel reachable -- then training draws from all, as NeuS).
    """
    if background or not (cfg.cull_outside_sphere or bounds):
        return None
    hw = scene.height * scene.width
    found = []
    for v in range(scene.n_views):
        o, d = (x.reshape(-1, 3) for x in image_rays(scene, v))
        for s in range(0, hw, chunk):
            active = ray_bounds(o[s:s + chunk], d[s:s + chunk], cfg, bounds)[2]
            found.append(active.nonzero().squeeze(1) + (v * hw + s))
    pixels = torch.cat(found)
    if pixels.numel() == 0:
        return None
    return PixelPool(pixels=pixels, fraction=pixels.numel() / (scene.n_views * hw))
