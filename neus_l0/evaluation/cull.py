"""Remove mesh parts outside the scene's (dilated) object masks, as IDR / NeuS do for DTU.

Rule (`mask_keep_vertices`): every mask is dilated by a disk of radius `dilate` pixels. A
vertex is *inside* view i's image when it lies in front of the camera (camera z > 0) and its
pixel (rint(x), rint(y)) from `world_mat_i[:3, :4]` is within [0, W) x [0, H). The vertex is
kept when it falls on the dilated foreground in *every* view whose image it is inside; a
vertex inside no image is kept (as in IDR's culling). A face is kept when all three of its
vertices are; vertices no kept face uses are dropped.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neus_l0.data.cameras import (
    camera_file,
    depth_projection,
    pixel_indices,
    read_masks,
    read_world_mats,
)
from neus_l0.data.views import indexed_files
from neus_l0.errors import NeusL0Error

#: Dilation radius used for DTU's 1600 x 1200 masks (pixels).
DTU_DILATE = 24
#: Reference image width of that radius: the default scales the radius with the width.
DTU_WIDTH = 1600
#: Radii above this dilate by a distance transform (same mask, linear time).
LARGE_DILATE = 64


def default_dilation(width: int) -> int:
    """Dilation radius (pixels) for masks `width` pixels wide: round(24 * width / 1600)."""
    return int(round(DTU_DILATE * width / DTU_WIDTH))


def dilate_mask(mask: np.ndarray, radius: int) -> np.ndarray:
    """Dilate an (H, W) bool mask by a disk of `radius` pixels (returns (H, W) bool)."""
    import cv2

    if radius <= 0 or not mask.any():
        return mask.astype(bool)
    if radius > LARGE_DILATE:
        # a large disk kernel is slow in OpenCV; the exact Euclidean distance to the
        # foreground gives the same mask in linear time
        from scipy.ndimage import distance_transform_edt

        return distance_transform_edt(~mask.astype(bool)) <= radius
    k = 2 * radius + 1
    yy, xx = np.mgrid[:k, :k] - radius
    disk = (xx**2 + yy**2 <= radius**2).astype(np.uint8)
    return cv2.dilate(mask.astype(np.uint8), disk).astype(bool)


def mask_keep_vertices(vertices: np.ndarray, projections: np.ndarray,
                       masks: list[np.ndarray]) -> np.ndarray:
    """Which vertices every view that sees them puts on its (already dilated) foreground.

    Args:
        vertices: (V, 3) world points.
        projections: (n_views, 3, 4) world -> pixel projections.
        masks: n_views (H, W) bool masks (dilate them first).

    Returns:
        (V,) bool keep flags.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    p_n = depth_projection(projections)  # (n_views, 3, 4)
    keep = np.ones(len(vertices), dtype=bool)
    for p, m in zip(p_n, masks, strict=True):
        h, w = m.shape
        col, row, _ = pixel_indices(p, vertices, h, w)
        inside = col >= 0
        fg = np.zeros(len(vertices), dtype=bool)
        fg[inside] = m[row[inside], col[inside]]
        keep &= fg | ~inside
    return keep


def cull_faces(vertices: np.ndarray, faces: np.ndarray,
               keep_vertex: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the faces whose three vertices are kept; drop unused vertices.

    Args:
        vertices: (V, 3); faces: (F, 3); keep_vertex: (V,) bool.

    Returns:
        vertices (V', 3) and re-indexed faces (F', 3).
    """
    faces = np.asarray(faces, dtype=np.int64)
    f = faces[keep_vertex[faces].all(axis=1)]
    used = np.zeros(len(vertices), dtype=bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    return np.asarray(vertices)[used], remap[f]


def cull_mesh(vertices: np.ndarray, faces: np.ndarray, scene_dir: str | os.PathLike,
              dilate: int | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Cull a mesh with the masks and cameras of a NeuS-format scene folder.

    Args:
        vertices: (V, 3) world points; faces: (F, 3).
        scene_dir: folder with `cameras_sphere.npz` and `mask/*.png`.
        dilate: dilation radius in pixels (`None`: `default_dilation` of the mask width).

    Returns:
        vertices (V', 3), faces (F', 3), and info {"dilate_px", "views", "faces_before",
        "faces_after"}.

    Raises:
        NeusL0Error: missing/malformed cameras or masks.
    """
    all_projections = read_world_mats(scene_dir)
    by_view = read_masks(scene_dir)  # paired with the cameras by view number
    beyond = [i for i in by_view if i >= len(all_projections)]
    if beyond:
        raise NeusL0Error(f"{Path(scene_dir) / 'mask'}: masks of views {beyond} have no "
                          f"world_mat in {camera_file(scene_dir).name}")
    # every view with an image needs its mask (a camera with neither is a deleted view);
    # without image/, every camera does
    image_dir = Path(scene_dir) / "image"
    seen = ({i: f"image/{p.name}" for i, p in indexed_files(image_dir).items()}
            if image_dir.is_dir() else
            {i: f"world_mat_{i}" for i in range(len(all_projections))})
    no_mask = [name for i, name in seen.items() if i < len(all_projections) and i not in by_view]
    if no_mask:
        raise NeusL0Error(f"{Path(scene_dir) / 'mask'}: no mask for {no_mask[0]}"
                          f"{f' and {len(no_mask) - 1} more' if len(no_mask) > 1 else ''}")
    projections = all_projections[list(by_view)]
    masks = list(by_view.values())
    radius = default_dilation(masks[0].shape[1]) if dilate is None else int(dilate)
    masks = [dilate_mask(m, radius) for m in masks]
    keep = mask_keep_vertices(vertices, projections, masks)
    v, f = cull_faces(vertices, faces, keep)
    info = {"scene": str(scene_dir), "dilate_px": radius, "views": len(projections),
            "faces_before": int(len(faces)), "faces_after": int(len(f))}
    return v, f, info
