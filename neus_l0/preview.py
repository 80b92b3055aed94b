"""Headless previews of meshes: shaded point-splat renders from a scene camera.

No OpenGL: the mesh is sampled densely, the samples are projected with the camera's
``world_mat`` and z-buffered per pixel, and shaded with a head-light on their face normals.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from neus_l0.atomic import atomic_path


def splat_render(mesh: trimesh.Trimesh, world_mat: np.ndarray, width: int, height: int,
                 n_points: int = 400_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Render a mesh as shaded splats seen through a NeuS camera.

    Args:
        mesh: the mesh in world units.
        world_mat: (3, 4) or (4, 4) projection world -> pixels (pixel centres at integers).
        width, height: image size in pixels.
        n_points: surface samples (more: fewer holes).
        seed: sampling seed.

    Returns:
        shade (H, W) float in [0, 1] (NaN where nothing is seen) and depth (H, W) camera-z
        (inf where nothing is seen).
    """
    from neus_l0.data.cameras import camera_z_depth

    shade = np.full((height, width), np.nan)
    depth = np.full((height, width), np.inf)
    if len(mesh.faces) == 0:
        return shade, depth
    pts, face = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    normals = mesh.face_normals[face]
    xy, z = camera_z_depth(world_mat, pts)
    px = np.rint(xy).astype(np.int64)
    ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < width) & (px[:, 1] >= 0) & (px[:, 1] < height)
    px, z, pts, normals = px[ok], z[ok], pts[ok], normals[ok]
    P = np.asarray(world_mat, dtype=np.float64)[:3, :4]
    centre = -np.linalg.solve(P[:, :3], P[:, 3])
    view = pts - centre
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    lit = np.abs((normals * view).sum(1))  # two-sided head-light
    flat = px[:, 1] * width + px[:, 0]
    order = np.lexsort((z, flat))  # by pixel, nearest first
    flat, z, lit = flat[order], z[order], lit[order]
    first = np.r_[True, flat[1:] != flat[:-1]]
    shade.reshape(-1)[flat[first]] = 0.15 + 0.85 * lit[first]
    depth.reshape(-1)[flat[first]] = z[first]
    return shade, depth


def side_by_side(path: str | Path, panels: list[tuple[str, np.ndarray]],
                 title: str | None = None) -> Path:
    """Save images (H, W) grey (NaN = background) or (H, W, 3) RGB next to each other (PNG)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.4), dpi=120)
    axes = np.atleast_1d(axes)
    for ax, (name, img) in zip(axes, panels, strict=True):
        if img.ndim == 2:
            shown = np.where(np.isnan(img), 1.0, img)
            ax.imshow(shown, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        else:
            ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
