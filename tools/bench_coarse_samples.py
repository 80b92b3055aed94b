"""How close the coarse samples lie to the true surface, with and without the visual hull.

Usage:
    python tools/bench_coarse_samples.py SCENE [SCENE ...] [--rays 2048] [--samples 32]
                                         [--fraction 0.02] [--resolution 128] [--margin 2]

For rays through pixels inside each synthetic scene's masks (`object_rays`), the coarse
samples are placed as training places them without jitter (`coarse_z_vals`, `n` uniform
samples in the ray's bounds): in the unit sphere's chord (`render.cull_outside_sphere`),
and in the chord narrowed by the scene's default visual hull (`neus_l0.bounds.hull`). No network
is involved. Printed per scene: the fraction of coarse samples within `--fraction` of the
object's size (its ground-truth bounding-box diagonal) of the true surface, the mean
spacing of the samples in world units, and how much of the sphere the hull keeps.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from neus_l0.bounds.hull import hull_from_scene
from neus_l0.bounds.spans import ray_bounds
from neus_l0.config.schema import RenderConfig
from neus_l0.evaluation.sample_distance import SurfaceDistance, object_rays
from neus_l0.formats.neus import load_scene
from neus_l0.render.volume import coarse_z_vals


def measure(root: str, rays: int, samples: int, fraction: float, resolution: int,
            margin: float) -> list[str]:
    """Table rows (sphere, hull) of one scene."""
    scene = load_scene(root)
    surface = SurfaceDistance.from_scene_dir(root)
    from neus_l0.evaluation.io import load_mesh

    verts, _ = load_mesh(f"{root}/gt_mesh.ply")
    size = float(np.linalg.norm(verts.max(0) - verts.min(0)))
    hull = hull_from_scene(scene, resolution, margin)
    o, d = object_rays(scene, rays)
    scale = float(scene.scale_mat[0, 0])
    rows = []
    for name, bounds in (("sphere chord", ()), ("visual hull", (hull,))):
        near, far, active = ray_bounds(o, d, RenderConfig(cull_outside_sphere=True), bounds)
        t = coarse_z_vals(near, far, samples, perturb=False)  # (B, n)
        pts = (o[:, None] + d[:, None] * t[..., None]).reshape(-1, 3).double().numpy()
        world = pts * scale + np.asarray(scene.scale_mat)[:3, 3]
        dist = surface(world)
        close = float((dist < fraction * size).mean())
        spacing = float(((far - near) / (samples - 1)).mean()) * scale
        rows.append(f"| {root} | {name} | {close:.3f} | {spacing:.2f} | "
                    f"{float(active.float().mean()):.3f} | {hull.fraction_of_sphere():.3f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--rays", type=int, default=2048)
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--fraction", type=float, default=0.02)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--margin", type=float, default=2.0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"| scene | bounds | coarse samples within {args.fraction:g} x size | "
          "spacing (world) | rays with samples | hull keeps (sphere) |")
    print("|---|---|---:|---:|---:|---:|")
    for root in args.scenes:
        for row in measure(root, args.rays, args.samples, args.fraction, args.resolution,
                           args.margin):
            print(row)


if __name__ == "__main__":
    main()
