"""The one mesh rasteriser: a mesh seen through a NeuS camera, headless, and pictures side by
side.

No OpenGL and no GPU: `raster_render` casts one ray per pixel centre at the mesh's triangles
(the torch rasteriser of `neus_l0.synthetic.meshes.MeshSurface`) and shades the first hit with
a head-light on its interpolated normal. `side_by_side` saves panels next to each other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from neus_l0.atomic import atomic_path


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

    Uses the vectorised torch rasteriser of `neus_l0.synthetic.meshes.MeshSurface` (one ray per
    pixel centre, first hit by Moller-Trumbore, vertex normals interpolated), two-sided
    head-light shading. Headless: no OpenGL, no GPU.

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
    from neus_l0.data.rays import pixel_grid, pixel_rays
    from neus_l0.synthetic.meshes import MeshSurface
    from neus_l0.synthetic.raycast import RayGrid

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
