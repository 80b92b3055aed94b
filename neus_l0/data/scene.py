"""The `Scene` container: a scene's views, masks, cameras and object sphere as tensors, and
`scene_summary` (what `neus-l0 inspect` prints). The parsers that fill it live in
`neus_l0.formats` (`neus_l0.formats.neus`: the NeuS format; `neus_l0.formats.transforms`:
transforms.json; `neus_l0.formats.open.open_scene`: the one door).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
import torch


def ray_matrices(intrinsics: torch.Tensor, c2w: torch.Tensor) -> torch.Tensor:
    """Per-view matrices A = R K^-1 that map a pixel [x, y, 1] to its ray's direction.

    Computed in float64 (then cast back), once per scene: `rays_at` then needs one small
    product per ray (`pixel_rays` solves K per ray, which the same ray needs ~15 ops for).

    Args:
        intrinsics: (V, 3, 3) upper-triangular K; c2w: (V, 4, 4).

    Returns:
        (V, 3, 3) in intrinsics' dtype; ``A @ [x, y, 1]`` is the (unnormalised) direction.
    """
    k_inv = torch.linalg.inv(intrinsics.double())
    return (c2w[:, :3, :3].double() @ k_inv).to(intrinsics.dtype)


@dataclasses.dataclass
class Scene:
    """A loaded multi-view scene, everything on one device.

    Attributes:
        root: the scene folder.
        images: (n_views, H, W, 3) float32 RGB in [0, 1].
        masks: (n_views, H, W) float32, 1 = foreground (soft after a downscale); all ones
            when the scene has no ``mask/`` folder.
        has_masks: whether the scene came with masks.
        intrinsics: (n_views, 3, 3) float32, pixel units, after any downscale.
        c2w: (n_views, 4, 4) float32 camera-to-world poses in the normalised frame
            (the object's bounding sphere is the unit sphere).
        scale_mat: (4, 4) float64 numpy, normalised -> world (``scale_mat_0``).
        image_names: file names of the images, in view order.
        info: how the scene was read (``format``, ``masks`` = where the masks came from,
            and for non-NeuS formats the file and how the sphere was found); free-form,
            for summaries.
    """

    root: Path
    images: torch.Tensor
    masks: torch.Tensor
    has_masks: bool
    intrinsics: torch.Tensor
    c2w: torch.Tensor
    scale_mat: np.ndarray
    image_names: list[str]
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def n_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def device(self) -> torch.device:
        return self.images.device

    @functools.cached_property
    def ray_matrices(self) -> torch.Tensor:
        """(n_views, 3, 3) R K^-1 of each view (`ray_matrices`), computed on first use (a
        scene's cameras do not change after loading)."""
        return ray_matrices(self.intrinsics, self.c2w)

    @functools.cached_property
    def centres(self) -> torch.Tensor:
        """(n_views, 3) camera centres in the normalised frame, contiguous."""
        return self.c2w[:, :3, 3].contiguous()

    def to(self, device: str | torch.device) -> Scene:
        """Return a copy whose tensors live on `device`."""
        return dataclasses.replace(
            self, images=self.images.to(device), masks=self.masks.to(device),
            intrinsics=self.intrinsics.to(device), c2w=self.c2w.to(device))


def scene_summary(scene: Scene) -> dict:
    """Summarise a loaded scene (what `neus-l0 inspect` prints).

    Returns:
        A JSON-serialisable dict: ``root``, ``format``, ``camera_file``, ``views``,
        ``width``, ``height``, ``has_masks``, ``mask_source`` (``mask/``, ``alpha``,
        ``mask_path`` or ``none``), ``mask_coverage`` (min/mean/max foreground fraction),
        ``sphere_center`` and ``sphere_radius`` (world units), ``camera_distance``
        (min/mean/max in normalised units), ``focal`` (min/max, pixels), ``empty_masks``
        (views whose mask is empty), ``warnings`` (cameras inside the unit sphere or
        looking away from it, empty masks).
    """
    centres = scene.c2w[:, :3, 3].double().cpu().numpy()
    axes = scene.c2w[:, :3, 2].double().cpu().numpy()
    dist = np.linalg.norm(centres, axis=-1)
    # distance of the origin from each optical axis, and whether it lies in front
    along = -(centres * axes).sum(-1)
    miss = np.linalg.norm(centres + along[:, None] * axes, axis=-1)
    warnings = []
    inside = np.nonzero(dist <= 1.0)[0]
    if inside.size:
        warnings.append(f"cameras inside the unit sphere: views {inside.tolist()}")
    away = np.nonzero((along <= 0) | (miss > 1.0))[0]
    if away.size:
        warnings.append(f"optical axis misses the unit sphere: views {away.tolist()}")
    cover = scene.masks.mean(dim=(1, 2)).cpu().numpy()
    empty = np.nonzero(cover == 0)[0] if scene.has_masks else np.zeros(0, np.int64)
    if empty.size:
        files = scene.info.get("mask_files")
        names = ([files[i] for i in empty] if files
                 else [f"alpha of {scene.image_names[i]}" for i in empty])
        warnings.append(f"empty masks (all background in those views): views "
                        f"{empty.tolist()} ({', '.join(names)})")
    sm = scene.scale_mat
    fx = scene.intrinsics[:, 0, 0].double().cpu().numpy()
    info = scene.info
    return {
        "root": str(scene.root),
        "format": info.get("format", "neus"),
        "camera_file": info.get("camera_file", ""),
        "views": scene.n_views,
        "width": scene.width,
        "height": scene.height,
        "has_masks": scene.has_masks,
        "mask_source": info.get("masks", "mask/" if scene.has_masks else "none"),
        "mask_coverage": {"min": float(cover.min()), "mean": float(cover.mean()),
                          "max": float(cover.max())},
        "sphere_center": [float(v) for v in sm[:3, 3]],
        "sphere_radius": float(abs(np.linalg.det(sm[:3, :3])) ** (1.0 / 3.0)),
        "camera_distance": {"min": float(dist.min()), "mean": float(dist.mean()),
                            "max": float(dist.max())},
        "axis_miss": {"max": float(miss.max())},
        "focal": {"min": float(fx.min()), "max": float(fx.max())},
        "empty_masks": empty.tolist(),
        "pairing": info.get("pairing"),
        "view_indices": info.get("view_indices"),
        "unused_cameras": info.get("unused_cameras", []),
        "warnings": warnings,
    }
