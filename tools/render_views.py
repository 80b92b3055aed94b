"""Render a mesh through a scene's cameras next to the scene's own images (headless).

Usage:
    python tools/render_views.py MESH SCENE OUT.png [--views 0,16,30]

MESH is in world units (as `neus-l0 mesh` writes it); SCENE is a NeuS-format folder
(`image/`, `cameras_sphere.npz`). Top row: the input images; bottom row: the mesh shaded from
the same cameras (`neus_l0.figures.raster.raster_render`, no display or GPU needed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import matplotlib
import numpy as np
import trimesh

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from neus_l0.data.cameras import read_world_mats  # noqa: E402
from neus_l0.figures.raster import raster_render  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mesh", type=Path)
    p.add_argument("scene", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--views", default="0,16,30", help="view indices, comma-separated")
    args = p.parse_args()
    mesh = trimesh.load(args.mesh, force="mesh")
    world_mats = read_world_mats(args.scene)  # (V, 3, 4)
    images = sorted((args.scene / "image").glob("*.png"))
    views = [int(v) for v in args.views.split(",")]
    fig, ax = plt.subplots(2, len(views), figsize=(5 * len(views), 8), squeeze=False)
    for j, v in enumerate(views):
        img = cv2.imread(str(images[v]))[..., ::-1]
        shade = raster_render(mesh, world_mats[v], img.shape[1], img.shape[0])["shade"]
        ax[0, j].imshow(img)
        ax[0, j].set_title(f"input view {v}")
        ax[1, j].imshow(np.nan_to_num(shade, nan=1.0), cmap="gray", vmin=0, vmax=1)
        ax[1, j].set_title("reconstruction, same camera")
        for a in ax[:, j]:
            a.axis("off")
    fig.tight_layout()
    fig.savefig(args.out, dpi=70)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
