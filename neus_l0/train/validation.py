"""Validation renders during training: ground truth | colour | normals of one view."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neus_l0.atomic import atomic_write_png
from neus_l0.bounds.spans import RayBounds
from neus_l0.config.schema import Config
from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.data.scene import Scene
from neus_l0.fields.model import NeuSModel
from neus_l0.render.volume import render_image
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.schedule import cos_anneal_ratio


def validation_views(scene: Scene, view: int, downscale: int) -> tuple[Tensor, Tensor, Tensor]:
    """Rays and ground truth of every `downscale`-th pixel of one view.

    Returns:
        origins (h, w, 3), dirs (h, w, 3), rgb (h, w, 3).
    """
    xy = pixel_grid(scene.height, scene.width, scene.device)[::downscale, ::downscale]
    h, w, _ = xy.shape
    o, d = pixel_rays(scene.intrinsics[view], scene.c2w[view], xy.reshape(-1, 2))
    rgb = scene.images[view, ::downscale, ::downscale]
    return o.reshape(h, w, 3), d.reshape(h, w, 3), rgb


def validation_image(model: NeuSModel, scene: Scene, cfg: Config, view: int, iteration: int,
                     bounds: Sequence[RayBounds] = (), sampler=None) -> np.ndarray:
    """Ground truth | rendered colour | normals (camera frame) of a downscaled view.

    Args:
        bounds: what narrows the rays (see `neus_l0.bounds.spans.ray_bounds`).
        sampler: the up-sampling draw (default: the config's).

    Returns:
        (h, 3w, 3) uint8 RGB.
    """
    o, d, rgb = validation_views(scene, view, max(1, cfg.train.val_downscale))
    out = render_image(model, o, d, cfg.render,
                       build_sampler(cfg.sampler) if sampler is None else sampler,
                       cos_anneal_ratio(iteration, cfg.train.anneal_end), bounds=bounds)
    rot = scene.c2w[view, :3, :3]  # camera -> world
    normal_cam = out["normal"] @ rot  # (h, w, 3) world -> camera: n^T R = (R^T n)^T
    tiles = [rgb, out["color"].clamp(0, 1), (normal_cam * 0.5 + 0.5).clamp(0, 1)]
    img = torch.cat([t.detach().float().cpu() for t in tiles], dim=1)
    return (img.numpy() * 255.0 + 0.5).astype(np.uint8)


def write_png(path: Path, rgb: np.ndarray, within: Path | None = None) -> None:
    """Write an (H, W, 3) uint8 RGB image atomically (inside the folder `within`)."""
    atomic_write_png(path, np.ascontiguousarray(rgb[..., ::-1]), within)
