"""The bounds a run keeps for all of its training: its visual hull, or its SfM point box.

Static means the bounds never change during a run, so the pixel pool can look each pixel's
span up once (`neus_l0.bounds.pixel_pool`); the occupancy grid, which follows the SDF, is
not one of them.
"""

from __future__ import annotations

import sys
from pathlib import Path

from neus_l0.bounds.hull import VisualHull, hull_for_run
from neus_l0.bounds.points import PointBound
from neus_l0.config.schema import Config
from neus_l0.data.scene import Scene


def static_bounds(scene: Scene, cfg: Config,
                  run_dir: Path) -> tuple[VisualHull | PointBound, ...]:
    """The run's static bounds: its visual hull, or without one the SfM point box, or none.

    The hull exists only when the scene has masks and `render.hull.enabled` (views without
    masks carve nothing): carved at the first start and saved as ``RUN/hull.pt``; a resume
    loads that file. Each warning of the carving (a suspicious mask, named) is one line on
    stderr. Without a hull, `render.point_bound.enabled` and a ``sparse_points.npz`` in the
    scene folder (`neus-l0 colmap`) give the points' box (`neus_l0.bounds.points`); else ().
    """
    h = cfg.render.hull
    if not (h.enabled and scene.has_masks):
        p = cfg.render.point_bound
        box = PointBound.for_scene(scene, p.margin, p.min_views) if p.enabled else None
        if box is None:
            return ()
        print(f"neus-l0: {box.describe()}", file=sys.stderr, flush=True)
        return (box,)
    run_dir.mkdir(parents=True, exist_ok=True)
    hull = hull_for_run(scene, run_dir / "hull.pt", h.resolution, h.margin_px)
    for line in (hull.report.warnings if hull.report is not None else []):
        print(f"neus-l0: visual hull: {line}", file=sys.stderr, flush=True)
    return (hull,)
