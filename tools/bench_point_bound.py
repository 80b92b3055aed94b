"""The SfM-point box (`neus_l0.bounds.points`) against the sphere, on `neus-l0 colmap` scenes.

Usage:
    python tools/bench_point_bound.py TRUE_DIR:COLMAP_DIR [...] [--margins 0 0.05 0.1 0.2]
                                      [--rays 2048] [--samples 32] [--fraction 0.02]

TRUE_DIR is a synthetic scene (`make_scene`), COLMAP_DIR what ``neus-l0 colmap
TRUE_DIR/image COLMAP_DIR --masks TRUE_DIR/mask`` wrote from its photos (the masks are used
only to pick rays through the object and for the reference hull; the point box never reads
them). The true surface is brought into the colmap scene's frame by the similarity that
takes the recovered camera centres onto the true ones (`compare_to_truth`). Printed per
scene and margin: the fraction of the true surface (gt_points + gt_mesh vertices) inside
the box, the fraction of the unit sphere it keeps, and, as `tools/bench_coarse_samples.py`
does, the fraction of 32 coarse samples on rays through mask pixels that lie within
`--fraction` of the object's size of the true surface. Also: what a carving of the space
away from the points would keep (the fraction of the true surface within d of some SfM
point), and the visual hull from the masks, for reference.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from neus_l0.bounds.hull import hull_from_scene
from neus_l0.bounds.points import PointBound
from neus_l0.bounds.spans import ray_bounds
from neus_l0.config.schema import RenderConfig
from neus_l0.data.points import POINTS_FILE, read_points
from neus_l0.evaluation.io import load_mesh, load_points
from neus_l0.evaluation.sample_distance import SurfaceDistance, object_rays
from neus_l0.experiments.photos_compare import compare_to_truth
from neus_l0.formats.neus import load_scene
from neus_l0.render.volume import coarse_z_vals


def truth_in_colmap_frame(true_dir: str, colmap_dir: str, scene) -> tuple:
    """The true mesh in the colmap world, and its points in the colmap normalised frame."""
    errs = compare_to_truth(colmap_dir, true_dir)
    s, R, t = errs["scale"], errs["R"], errs["t"]  # colmap world -> true world
    to_colmap = lambda p: (np.asarray(p) - t) @ R / s  # noqa: E731  (R^T (p - t) / s)
    verts, faces = load_mesh(f"{true_dir}/gt_mesh.ply")
    pts = np.concatenate([load_points(f"{true_dir}/gt_points.ply"), verts])
    sm = np.asarray(scene.scale_mat)
    unit = (to_colmap(pts) - sm[:3, 3]) / sm[0, 0]
    return to_colmap(verts), faces, unit, errs


def coarse_near(scene, surface, size_world, o, d, bounds, samples, fraction) -> tuple:
    """Fraction of coarse samples near the surface, active rays, mean interval length."""
    near, far, active = ray_bounds(o, d, RenderConfig(cull_outside_sphere=True), bounds)
    t = coarse_z_vals(near, far, samples, perturb=False)  # (B, n)
    pts = (o[:, None] + d[:, None] * t[..., None]).reshape(-1, 3).double().numpy()
    sm = np.asarray(scene.scale_mat)
    dist = surface(pts * sm[0, 0] + sm[:3, 3])
    return (float((dist < fraction * size_world).mean()), float(active.float().mean()),
            float((far - near).mean()))


def measure(pair: str, margins: list[float], rays: int, samples: int,
            fraction: float) -> list[str]:
    """Table rows of one scene."""
    true_dir, colmap_dir = pair.split(":")
    scene = load_scene(colmap_dir)
    verts_c, faces, gt_unit, errs = truth_in_colmap_frame(true_dir, colmap_dir, scene)
    surface = SurfaceDistance(verts_c, faces)
    size_world = float(np.linalg.norm(verts_c.max(0) - verts_c.min(0)))
    size_unit = size_world / float(scene.scale_mat[0, 0])
    pts, track = read_points(f"{colmap_dir}/{POINTS_FILE}", np.asarray(scene.scale_mat))
    o, d = object_rays(scene, rays)
    gt = torch.as_tensor(gt_unit, dtype=torch.float32)
    name = true_dir.rstrip("/").split("/")[-2]
    rows = []
    near_s, act_s, len_s = coarse_near(scene, surface, size_world, o, d, (), samples, fraction)
    rows.append(f"| {name} | sphere chord | 100 | 100 | {near_s:.3f} | {len_s:.2f} |")
    for m in margins:
        box = PointBound.from_points(pts, track, margin=m)
        inside = float(box.contains(gt).float().mean())
        near_b, act_b, len_b = coarse_near(scene, surface, size_world, o, d, (box,), samples,
                                           fraction)
        rows.append(f"| {name} | point box, margin {m:g} | {100 * inside:.2f} | "
                    f"{100 * box.fraction_of_sphere():.1f} | {near_b:.3f} | {len_b:.2f} |")
    hull = hull_from_scene(scene)
    near_h, _, len_h = coarse_near(scene, surface, size_world, o, d, (hull,), samples, fraction)
    rows.append(f"| {name} | visual hull (masks, reference) | "
                f"{100 * float(hull.contains(gt).float().mean()):.2f} | "
                f"{100 * hull.fraction_of_sphere():.1f} | {near_h:.3f} | {len_h:.2f} |")
    from scipy.spatial import cKDTree

    dist = cKDTree(pts[np.linalg.norm(pts, axis=-1) < 1.0]).query(gt_unit)[0]
    within = ", ".join(f"{100 * float((dist <= k * size_unit).mean()):.1f} % within "
                       f"{k:g} x size" for k in (0.02, 0.05, 0.1))
    n_in = int((np.linalg.norm(pts, axis=-1) < 1).sum())
    rows.append(f"<!-- {name}: {len(pts)} SfM points ({n_in} in the sphere); true surface "
                f"near a point: {within}; object size "
                f"{size_unit:.3f} (unit sphere radius 1); camera centre error "
                f"{100 * errs['center_err_mean_rel']:.2f} % of the size -->")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", metavar="TRUE_DIR:COLMAP_DIR")
    ap.add_argument("--margins", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.2])
    ap.add_argument("--rays", type=int, default=2048)
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--fraction", type=float, default=0.02)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"| scene | bounds | true surface inside (%) | sphere kept (%) | coarse samples "
          f"within {args.fraction:g} x size | mean interval (unit) |")
    print("|---|---|---:|---:|---:|---:|")
    for pair in args.pairs:
        for row in measure(pair, args.margins, args.rays, args.samples, args.fraction):
            print(row, flush=True)


if __name__ == "__main__":
    main()
