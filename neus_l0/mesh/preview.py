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
    from neus_l0.data.cameras import pixel_indices

    shade = np.full((height, width), np.nan)
    depth = np.full((height, width), np.inf)
    if len(mesh.faces) == 0:
        return shade, depth
    pts, face = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    normals = mesh.face_normals[face]
    col, row, z = pixel_indices(world_mat, pts, height, width)
    ok = col >= 0
    col, row, z, pts, normals = col[ok], row[ok], z[ok], pts[ok], normals[ok]
    P = np.asarray(world_mat, dtype=np.float64)[:3, :4]
    centre = -np.linalg.solve(P[:, :3], P[:, 3])
    view = pts - centre
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    lit = np.abs((normals * view).sum(1))  # two-sided head-light
    flat = row * width + col
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


def raster_render(mesh: trimesh.Trimesh, world_mat: np.ndarray, width: int,
                  height: int) -> dict[str, np.ndarray]:
    """Render a mesh exactly (z-buffered triangles, no holes) through a NeuS camera.

    Uses the vectorised torch rasteriser of `neus_l0.data.meshes.MeshSurface` (one ray per
    pixel centre, first hit by Moller-Trumbore, vertex normals interpolated), head-light
    shading as `splat_render`. Headless: no OpenGL, no GPU.

    Args:
        mesh: the mesh in world units.
        world_mat: (3, 4) or (4, 4) projection world -> pixels (pixel centres at integers).
        width, height: image size in pixels.

    Returns:
        dict with ``shade`` (H, W) in [0, 1] (NaN where nothing is seen), ``depth`` (H, W)
        camera-z depth (inf on a miss), ``points`` (H, W, 3) world hit points (NaN on a
        miss) and ``normals`` (H, W, 3) unit normals (0 on a miss).
    """
    import torch

    from neus_l0.data.cameras import decompose_projection
    from neus_l0.data.meshes import MeshSurface
    from neus_l0.data.raycast import RayGrid
    from neus_l0.data.rays import pixel_grid, pixel_rays

    shade = np.full((height, width), np.nan)
    depth = np.full((height, width), np.inf)
    points = np.full((height, width, 3), np.nan)
    normals = np.zeros((height, width, 3))
    out = {"shade": shade, "depth": depth, "points": points, "normals": normals}
    if len(mesh.faces) == 0:
        return out
    K, c2w = decompose_projection(world_mat)
    Kt = torch.as_tensor(K, dtype=torch.float64)[None]
    Tt = torch.as_tensor(c2w, dtype=torch.float64)[None]
    xy = pixel_grid(height, width).reshape(-1, 2).double()  # (HW, 2)
    o, d = pixel_rays(Kt[0], Tt[0], xy)  # (HW, 3) world units, unit directions
    grid = RayGrid(Kt, Tt, height, width, torch.zeros(1, 2, dtype=torch.float64),
                   o[None, None], d[None, None])
    surface = MeshSurface(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    t, n = surface.intersect_grid(grid)  # (1, 1, HW), (1, 1, HW, 3)
    t, n = t[0, 0].double(), n[0, 0].double()
    hit = torch.isfinite(t)
    x = o + t[:, None].where(hit[:, None], torch.zeros(())) * d  # (HW, 3)
    lit = (n * d).sum(-1).abs()  # two-sided head-light
    hit_np = hit.numpy().reshape(height, width)
    shade[hit_np] = 0.15 + 0.85 * lit.numpy().reshape(height, width)[hit_np]
    cam_z = (t * (d @ Tt[0, :3, 2])).numpy().reshape(height, width)
    depth[hit_np] = cam_z[hit_np]
    points[hit_np] = x.numpy().reshape(height, width, 3)[hit_np]
    normals[hit_np] = n.numpy().reshape(height, width, 3)[hit_np]
    return out
