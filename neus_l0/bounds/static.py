"""The bounds a run keeps for all of its training: its visual hull, or its SfM point box.

Static means the bounds never change during a run, so the pixel pool can look each pixel's
span up once (`neus_l0.bounds.pixel_pool`); the occupancy grid, which follows the SDF, is
not one of them.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from neus_l0.bounds.grid import cell_centres
from neus_l0.bounds.hull import VisualHull, hull_for_run
from neus_l0.bounds.points import PointBound
from neus_l0.config.schema import Config
from neus_l0.data.scene import Scene
from neus_l0.errors import SceneError

#: The share of the unit sphere's outer shell a visual hull may fill before the object counts
#: as cut by the sphere (at the default 128^3 hull). It sits between the few percent that
#: objects which fit leave in the shell and the larger share a cut object fills, and was
#: checked on scenes it was not tuned on (docs/benchmarks/bounds.md, "Numbers moved from
#: code comments"). A cut of a few percent of the radius fills less and is not caught. A
#: conservative hull reaches the shell even when the object fits, so one kept cell proves
#: nothing.
CUT_SHELL = 0.08
#: Fewer carving views than this give hulls too loose to judge the fit by...
CUT_MIN_VIEWS = 6
#: ...and so does a mask margin wider than this share of the image's smaller side (a 2 px
#: margin on a 48-pixel image widens every cone by 4 %).
CUT_MAX_MARGIN = 0.03


def static_bounds(scene: Scene, cfg: Config, hull_file: Path,
                  reuse: bool = False) -> tuple[VisualHull | PointBound, ...]:
    """The run's static bounds: its visual hull, or without one the SfM point box, or none.

    The hull exists only when the scene has masks and `render.hull.enabled` (views without
    masks carve nothing): carved and saved as `hull_file` (``RUN/hull.pt``) once it passes
    `check_fit` (a refused scene leaves none). With `reuse` (a resume: the caller knows the run
    has a checkpoint) that file is loaded; without, it is carved again (the file is then an
    earlier start's, maybe of another scene). Each warning of the carving (a suspicious mask,
    named) is one line on stderr. Without a hull, `render.point_bound.enabled` and a
    ``sparse_points.npz`` in the scene folder (`neus-l0 colmap`) give the points' box
    (`neus_l0.bounds.points`); else ().
    """
    h = cfg.render.hull
    if not (h.enabled and scene.has_masks):
        p = cfg.render.point_bound
        box = PointBound.for_scene(scene, p.margin, p.min_views) if p.enabled else None
        if box is None:
            return ()
        print(f"neus-l0: {box.describe()}", file=sys.stderr, flush=True)
        return (box,)
    hull_file.parent.mkdir(parents=True, exist_ok=True)
    hull = hull_for_run(scene, hull_file, h.resolution, h.margin_px, reuse=reuse,
                        check=lambda carved: check_fit(carved, scene))
    for line in (hull.report.warnings if hull.report is not None else []):
        print(f"neus-l0: visual hull: {line}", file=sys.stderr, flush=True)
    return (hull,)


def shell_fraction(hull: VisualHull) -> float:
    """The share of the unit sphere's outermost shell of cells (centres within 1.5 cells
    inside the sphere, or up to half a cell diagonal outside) that `hull` keeps."""
    R = hull.resolution
    cell = 2.0 / R
    r = cell_centres(R, hull.device).norm(dim=-1)
    shell = (r > 1.0 - 1.5 * cell) & (r <= 1.0 + math.sqrt(3.0) * cell / 2.0)
    return float((hull.occupancy & shell).sum()) / max(int(shell.sum()), 1)


def cameras_inside(scene: Scene) -> list[int]:
    """The views whose camera centre lies inside the unit sphere (the normalised frame)."""
    return (scene.c2w[:, :3, 3].norm(dim=-1) <= 1.0).nonzero().flatten().tolist()


def cameras_inside_warning(scene: Scene) -> str | None:
    """One line when cameras lie inside the unit sphere (which must hold the object and leave
    every camera outside: rays would start inside the volume the SDF models), else None."""
    inside = cameras_inside(scene)
    if not inside:
        return None
    shown = inside if len(inside) <= 8 else inside[:8] + ["..."]
    return (f"{scene.root}: the cameras of {len(inside)} of {scene.n_views} views "
            f"({', '.join(map(str, shown))}) are inside the unit sphere, which should hold "
            "the object only: the sphere (scale_mat) is likely too large; check it with "
            "`neus-l0 inspect`")


def train_verdict(scene: Scene, hull: VisualHull | None) -> dict:
    """What `neus-l0 train` would say about the scene's fit to its unit sphere.

    Args:
        hull: the scene's visual hull carved as training carves it (``render.hull``'s default
            resolution and margin), or None when the scene has no masks.

    Returns:
        ``{"refuses": LINE or None, "warnings": [LINE, ...], "shell": FRACTION or None}``:
        `check_fit`'s refusal, `cameras_inside_warning`, and the share of the sphere's outer
        shell the hull fills.
    """
    refuses = None
    if hull is not None:
        try:
            check_fit(hull, scene)
        except SceneError as exc:
            refuses = str(exc)
    warning = cameras_inside_warning(scene)
    return {"refuses": refuses, "warnings": [warning] if warning else [],
            "shell": None if hull is None else shell_fraction(hull)}


def check_fit(hull: VisualHull, scene: Scene) -> None:
    """Refuse a scene whose object the unit sphere cuts (`CUT_SHELL`), before training.

    Raises:
        SceneError: naming the scene, how much of the shell the hull fills, and the fix (or,
            when cameras are inside the sphere, so that it is far too large, naming them).
    """
    carving = sum(s == "ok" for s in hull.report.status) if hull.report else 0
    if carving < CUT_MIN_VIEWS or hull.margin_px > CUT_MAX_MARGIN * min(scene.height,
                                                                        scene.width):
        return
    frac = shell_fraction(hull)
    if frac <= CUT_SHELL:
        return
    inside = cameras_inside(scene)
    if inside:  # then the hull fills the shell because the sphere is far too large
        raise SceneError(
            f"{scene.root}: the cameras of views {inside} are inside the unit sphere, which "
            "must hold the object and leave the cameras outside: the scale_mat_i are of "
            "another scale than the world_mat_i; check them with `neus-l0 inspect`")
    method = scene.info.get("sphere", {}).get("method")
    what = ({"sphere.json": "the radius in sphere.json"}.get(method, "the sphere found for "
            "it: give one in sphere.json") if method else "the scale of every scale_mat_i")
    raise SceneError(
        f"{scene.root}: the object does not fit its unit sphere: the masks' visual hull "
        f"fills {frac:.0%} of the sphere's outer shell (an object inside fills a few %), so "
        f"training would clip the mesh; enlarge the sphere ({what}), "
        "e.g. by 1.5x, and check with `neus-l0 inspect --hull`, or set "
        "render.hull.enabled=false to train anyway")
