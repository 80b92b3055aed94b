"""Score one mesh: the whole `neus-l0 eval` pipeline as a function returning the report.

The protocol and the report's fields are documented in docs/EVALUATION.md.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def score_mesh(mesh: str | Path, *, scene: str | Path | None = None,
               dtu_dir: str | Path | None = None, scan: int | None = None,
               cull: str | Path | None = None, cull_dilate: int | None = None,
               error_maps: str | Path | None = None, vmax: float | None = None,
               cmap: str = "jet", density: float = 0.2, max_dist: float = 20.0,
               margin_low: float = 60.0, margin_high: float = 120.0, depth_tol: float = 2.0,
               seed: int = 0, workers: int = -1,
               log: Callable[[str], None] = _stderr) -> dict:
    """Chamfer distance of a mesh (world units) to a synthetic scene's or DTU's ground truth.

    Args:
        mesh: predicted mesh file (PLY/OBJ), world units.
        scene: synthetic scene folder (gt_points.ply, gt_depth.npz, cameras_sphere.npz).
        dtu_dir, scan: DTU evaluation folder (Points/stl, ObsMask) and scan number.
        cull: scene folder whose dilated masks cull the mesh first (NeuS's no-mask protocol).
        cull_dilate: mask dilation in pixels (default: round(24 * width / 1600)).
        error_maps: folder for accuracy.ply / completeness.ply coloured by distance.
        vmax, cmap: error-map colour scale top (default max_dist) and matplotlib colormap.
        density: sampling density and thinning radius. max_dist: distance cut-off.
        margin_low, margin_high: evaluation box margins. depth_tol: synthetic visibility
            tolerance. seed: thinning order. workers: kd-tree threads (-1: all cores).
        log: progress messages.

    Returns:
        The report (see docs/EVALUATION.md): accuracy, completeness, overall, counts,
        settings, ...

    Raises:
        NeusL0Error: bad arguments or unreadable / malformed files.
    """
    from neus_l0 import __version__
    from neus_l0.evaluation import dtu, synthetic
    from neus_l0.evaluation.chamfer import nearest_distances
    from neus_l0.evaluation.io import load_mesh, load_points
    from neus_l0.evaluation.pointcloud import sample_mesh, thin_points

    mesh = Path(mesh)
    if (scene is None) == (dtu_dir is None):
        raise NeusL0Error("give exactly one ground truth: a synthetic scene or a DTU folder")
    if dtu_dir is not None and scan is None:
        raise NeusL0Error("--dtu needs --scan (the DTU scan number)")
    for name, value in (("density", density), ("max-dist", max_dist)):
        if not value > 0:
            raise NeusL0Error(f"--{name} must be positive")
    t0 = time.perf_counter()

    # Ground truth first, so that a bad GT path fails before the slow part.
    if dtu_dir is not None:
        if not Path(dtu_dir).is_dir():
            raise NeusL0Error(f"{dtu_dir}: DTU evaluation folder not found")
        paths = dtu.dtu_paths(dtu_dir, scan)
        obs = dtu.load_obs_mask(paths["obs_mask"])
        plane = dtu.load_plane(paths["plane"])
        gt_points = load_points(paths["stl"])
        protocol = "dtu"
        gt_info = {"dtu_dir": str(dtu_dir), "scan": scan,
                   **{k: str(v) for k, v in paths.items()}}
    else:
        gt = synthetic.load_synthetic_gt(scene)
        gt_points = gt.points
        protocol = "synthetic"
        gt_info = {"scene": str(scene)}

    vertices, faces = load_mesh(mesh)
    counts = {"mesh_vertices": len(vertices), "mesh_faces": len(faces)}
    cull_info = None
    if cull is not None:
        from neus_l0.evaluation.cull import cull_mesh

        vertices, faces, cull_info = cull_mesh(vertices, faces, cull, cull_dilate)
        if len(faces) == 0:
            raise NeusL0Error(f"{mesh}: no faces left after culling with {cull}/mask")
        counts.update(culled_vertices=len(vertices), culled_faces=len(faces))

    sampled = sample_mesh(vertices, faces, density)
    counts["pred_sampled"] = len(sampled)
    pred = thin_points(sampled, density, seed=seed)
    del sampled
    counts["pred_thinned"] = len(pred)
    log(f"eval: {counts['pred_sampled']} points sampled, {len(pred)} after thinning "
        f"({time.perf_counter() - t0:.1f} s)")

    margins = dict(margin_low=margin_low, margin_high=margin_high)
    if protocol == "dtu":
        res, masks = dtu.evaluate_dtu(pred, gt_points, obs, plane, max_dist,
                                      workers=workers, **margins)
    else:
        res, masks = synthetic.evaluate_synthetic(pred, gt, max_dist, depth_tol=depth_tol,
                                                  workers=workers,
                                                  pred_mesh=(vertices, faces), **margins)
    counts.update(res.counts)

    maps = None
    if error_maps is not None:
        from neus_l0.evaluation.error_maps import write_error_maps

        top = vmax if vmax is not None else max_dist
        if protocol == "dtu":
            _, v_scored = dtu.evaluation_region(vertices, obs, **margins)
        else:
            _, v_scored = synthetic.evaluation_region(vertices, gt, depth_tol=depth_tol,
                                                      **margins)
        if protocol == "dtu":
            v_dist = nearest_distances(vertices, gt_points, upper_bound=top, workers=workers)
        else:  # the same distance as accuracy (point-to-mesh with gt_mesh.ply)
            v_dist = gt.distance_to_gt(vertices, top, workers=workers)
        gt_dist = np.full(len(gt_points), np.inf)
        gt_dist[masks["gt_used"]] = res.dist_gt
        written = write_error_maps(error_maps, vertices, faces, v_dist, v_scored,
                                   gt_points, gt_dist, masks["gt_used"], top, cmap)
        maps = {"vmax": top, "cmap": cmap, **{k: str(v) for k, v in written.items()}}

    settings = {"protocol": protocol, "density": density, "thin_radius": density,
                "max_dist": max_dist, "margin_low": margin_low, "margin_high": margin_high,
                "seed": seed, "distance": res.distance, "cull": cull_info}
    if protocol == "synthetic":
        settings["depth_tol"] = depth_tol
    return {
        "protocol": protocol,
        "mesh": str(mesh),
        "gt": gt_info,
        "accuracy": _num(res.accuracy),
        "completeness": _num(res.completeness),
        "overall": _num(res.overall),
        "counts": {k: int(v) for k, v in counts.items()},
        "settings": settings,
        "error_maps": maps,
        "seconds": round(time.perf_counter() - t0, 3),
        "version": __version__,
    }
