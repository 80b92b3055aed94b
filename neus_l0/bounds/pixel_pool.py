"""The pixels worth drawing in training: those whose rays can reach the surface.

With culling on (`render.cull_outside_sphere`, a visual hull), a ray that misses the unit
sphere or the hull has zero opacity inside its bounds by construction: rendered, it costs
network work and gives no gradient (its colour is the background constant, its mask term
BCE(0, mask) a constant). So training draws its rays from the other pixels only, keeping
every batch's shape fixed and every ray useful; `neus_l0.train.losses.neus_loss` scales the mask
term by the pool's fraction of all pixels, which keeps NeuS's expected gradient (the
colour term is a mean over foreground rays, which all lie in the pool). With a background
model every pixel counts, and there is no pool.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import torch
from torch import Tensor

from neus_l0.bounds.error_map import ErrorMap, new_error_map, pixel_tiles
from neus_l0.bounds.spans import RayBounds, packed_spans
from neus_l0.config.schema import Config, RenderConfig
from neus_l0.data.rays import rays_at
from neus_l0.data.scene import Scene

#: Largest pool whose rays' spans are kept (16 bytes a pixel: 1 GiB); a bigger pool's
#: steps compute their bounds themselves.
MAX_SPAN_PIXELS = 1 << 26


@dataclasses.dataclass
class PixelPool:
    """Pixels to draw training rays from.

    Attributes:
        pixels: (P,) int64 flat indices ``view * H * W + y * W + x``, on the scene's device.
        fraction: P over all pixels of the scene.
        spans: (P, 4) float32 each pixel's ray span (near, far, sphere entry, sphere exit;
            `neus_l0.bounds.spans.packed_spans`) under the static bounds the pool was made with,
            or None (no static bounds, or more than `MAX_SPAN_PIXELS` pixels). The bounds
            are static and a pixel's ray is fixed, so a step looks them up instead of
            computing them.
        error_map: the running error of each pool pixel that the step draws from
            (`neus_l0.bounds.error_map`; `train.error_map`), or None (uniform draws).
    """

    pixels: Tensor
    fraction: float
    spans: Tensor | None = None
    error_map: ErrorMap | None = None


def hull_silhouette(occupancy: Tensor, intrinsics: Tensor, c2w: Tensor, height: int,
                    width: int) -> Tensor:
    """Pixels whose rays may meet a voxel set: a conservative silhouette.

    Every boundary cell (an occupied cell with an empty 6-neighbour or on the grid's edge;
    the silhouette of a solid is its boundary's) is projected by its centre, and the image
    of those centres is dilated by the largest projected radius of a cell's bounding ball
    over all of them: each cell's footprint lies in the disc of its own radius around its
    centre, so the union of footprints is covered.

    Args:
        occupancy: (R, R, R) bool over ``[-1, 1]^3``.
        intrinsics: (3, 3); c2w: (4, 4) camera-to-world, normalised frame.
        height, width: the image size.

    Returns:
        (H, W) bool, True where a ray may meet an occupied cell.
    """
    R = occupancy.shape[0]
    cell = 2.0 / R
    occ = occupancy.bool()
    pad = torch.nn.functional.pad(occ[None, None].float(), (1, 1, 1, 1, 1, 1))[0, 0]
    interior = torch.ones_like(occ)
    for axis in range(3):
        for shift in (0, 2):
            interior &= pad.narrow(axis, shift, R).narrow((axis + 1) % 3, 1, R) \
                .narrow((axis + 2) % 3, 1, R).bool()
    ijk = (occ & ~interior).nonzero().to(c2w.dtype)  # (M, 3) boundary cells
    out = torch.zeros(height, width, dtype=torch.bool, device=c2w.device)
    if ijk.numel() == 0:
        return out
    centres = -1.0 + cell * (ijk + 0.5)
    cam = (centres - c2w[:3, 3]) @ c2w[:3, :3]  # (M, 3) camera frame
    z = cam[:, 2]
    ball = cell * 3**0.5 / 2.0
    if (z <= ball).any():  # a cell at or behind the camera: every pixel may see it
        return torch.ones_like(out)
    uv = (cam @ intrinsics.T)[:, :2] / z[:, None]  # (M, 2) pixel coordinates (x, y)
    focal = float(intrinsics[0, 0].abs().max(intrinsics[1, 1].abs()))
    radius = int(math.ceil(float((focal * ball / (z - ball)).max()))) + 1
    x, y = uv[:, 0].round().long(), uv[:, 1].round().long()
    keep = (x >= -radius) & (x < width + radius) & (y >= -radius) & (y < height + radius)
    x, y = x[keep] + radius, y[keep] + radius
    canvas = torch.zeros(height + 2 * radius, width + 2 * radius, device=c2w.device)
    canvas[y, x] = 1.0
    grown = torch.nn.functional.max_pool2d(canvas[None, None], 2 * radius + 1, stride=1,
                                           padding=radius)[0, 0]
    return grown[radius:radius + height, radius:radius + width] > 0


def reachable_pixels(scene: Scene, cfg: RenderConfig, bounds: Sequence[RayBounds] = (),
                     background: bool = False, chunk: int = 1 << 16) -> PixelPool | None:
    """The pixels whose rays cross the unit sphere and every one of `bounds`.

    A bound with an ``occupancy`` grid (a visual hull) is first tested by its silhouette
    (`hull_silhouette`, cheap), and only the pixels inside it by `ray_bounds`.

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
    grids = [b.occupancy for b in bounds if isinstance(getattr(b, "occupancy", None), Tensor)]
    found, spans = [], []
    for v in range(scene.n_views):
        candidates = torch.arange(hw, device=scene.device)
        for grid in grids:
            sil = hull_silhouette(grid.to(scene.device), scene.intrinsics[v], scene.c2w[v],
                                  scene.height, scene.width).reshape(-1)
            candidates = candidates[sil[candidates]]
        for s in range(0, candidates.numel(), chunk):
            rows = candidates[s:s + chunk] + v * hw
            rays = rays_at(scene, rows)  # the very rays a step draws: its spans fit exactly
            span, active = packed_spans(rays["origins"], rays["dirs"], cfg, bounds)
            found.append(rows[active])
            spans.append(span[active])
    pixels = torch.cat(found)
    if pixels.numel() == 0:
        return None
    # spans only under static bounds: the sphere's chord alone is cheaper to recompute
    # than to look up, and a span tells `render_rays` that the rays were narrowed
    kept = torch.cat(spans) if bounds and pixels.numel() <= MAX_SPAN_PIXELS else None
    return PixelPool(pixels=pixels, fraction=pixels.numel() / (scene.n_views * hw), spans=kept)


def with_error_map(pool: PixelPool | None, scene: Scene, cfg: Config) -> PixelPool | None:
    """`pool` with an error map when ``train.error_map.fraction`` > 0 (else `pool` as is).

    Without a pool (every pixel counts) the map covers a pool of every pixel. Its tiles
    are ``train.error_map.tile`` pixels square. The map's
    foreground share is that of the pool's pixels whose mask is > 0.5 (1 when the run
    does not use masks, ``train.mask_weight`` 0).
    """
    c = cfg.train.error_map
    if c.fraction <= 0:
        return pool
    if pool is None:
        n = scene.n_views * scene.height * scene.width
        pool = PixelPool(pixels=torch.arange(n, device=scene.device), fraction=1.0)
    fg = 1.0
    if cfg.train.mask_weight > 0:
        fg = float((scene.masks.reshape(-1)[pool.pixels] > 0.5).float().mean())
    tiles = pixel_tiles(pool.pixels, scene.height, scene.width, c.tile)
    pool.error_map = new_error_map(tiles, c.fraction, c.decay, max(fg, 1e-6))
    return pool
