"""Figures of a scene without ground truth (a real scan such as DTU's): the samplers' meshes
side by side, shaded, with zoomed crops on the places where the meshes differ most.

Without a true surface there is no error to colour and no pit or thin part to zoom on. What
can be shown honestly is where the samplers disagree: points sampled on each mesh's surface
are measured against every other mesh's surface (`neus_l0.figures.render.SurfaceDistance`),
and the K points farthest from another mesh, at least two region radii apart, become
regions shaped like features.json entries (``kind`` region, no axis), which the overview
boxes and the crops of `neus_l0.figures.make` already know how to draw.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from neus_l0.errors import NeusL0Error
from neus_l0.figures.make import FigureEntry, crop_to_content, describe_runs, load_mesh
from neus_l0.figures.runs import BenchRun

if TYPE_CHECKING:
    import trimesh

    from neus_l0.figures.views import Camera

#: Default region radius, as a share of the diagonal of the meshes' joint bounding box.
REGION_RADIUS = 0.06
#: Points sampled on each mesh's surface to find the regions.
SURFACE_SAMPLES = 20000


def surface_disagreement(meshes: dict[str, trimesh.Trimesh], samples: int = SURFACE_SAMPLES,
                         seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on every mesh's surface and each one's distance to the farthest other mesh.

    Args:
        meshes: {name: mesh} (two or more, world units).
        samples: points drawn on each surface (area-uniform, seeded by `seed`).

    Returns:
        points (N, 3) (`samples` per mesh, in the order of `meshes`) and disagreement (N,):
        the largest distance from the point to the surface of another mesh.
    """
    import trimesh

    from neus_l0.figures.render import SurfaceDistance

    if len(meshes) < 2:
        raise NeusL0Error(f"disagreement needs two meshes or more, got {len(meshes)}")
    names = list(meshes)
    pts = {s: np.asarray(trimesh.sample.sample_surface(meshes[s], samples, seed=seed)[0])
           for s in names}
    dist = {s: SurfaceDistance(meshes[s]) for s in names}
    points = np.concatenate([pts[s] for s in names])  # (M * samples, 3)
    differ = np.concatenate([np.max([dist[o](pts[s]) for o in names if o != s], axis=0)
                             for s in names])  # (M * samples,)
    return points, differ


def disagreement_regions(meshes: dict[str, trimesh.Trimesh], k: int = 4,
                         radius: float | None = None,
                         samples: int = SURFACE_SAMPLES) -> list[dict]:
    """The `k` places where the meshes differ most (deterministic).

    Greedy non-maximum suppression over `surface_disagreement`: the point that differs
    most, then the most differing point at least ``2 * radius`` from every centre taken.

    Args:
        meshes: {name: mesh} (two or more, world units).
        k: regions wanted (fewer when the surfaces hold no more far enough apart).
        radius: region radius (world units); default `REGION_RADIUS` of the diagonal of
            the meshes' joint bounding box.
        samples: points drawn on each surface.

    Returns:
        features.json-shaped entries in decreasing disagreement: ``kind`` "region",
        ``name`` "region 1 (differ 3.2)", ``center`` (3,), ``radius``, ``axis`` None and
        ``disagreement`` (world units: the centre's distance to the farthest other mesh).
    """
    points, differ = surface_disagreement(meshes, samples)
    if radius is None:
        bounds = np.concatenate([np.asarray(m.bounds) for m in meshes.values()])  # (2M, 3)
        radius = REGION_RADIUS * float(np.linalg.norm(np.ptp(bounds, axis=0)))
    free = np.isfinite(differ)
    regions = []
    while len(regions) < k and free.any():
        i = int(np.argmax(np.where(free, differ, -np.inf)))  # first of ties: deterministic
        c = points[i]
        free &= np.linalg.norm(points - c, axis=1) >= 2 * radius
        d = float(differ[i])
        regions.append({"kind": "region", "name": f"region {len(regions) + 1} (differ {d:.3g})",
                        "center": c.copy(), "radius": float(radius), "axis": None,
                        "disagreement": d})
    return regions


def render_real(meshes: dict[str, trimesh.Trimesh], cams: list[Camera], regions: list[dict],
                width: int, crop_size: int) -> tuple[int, dict, list, list[dict]]:
    """Shaded renders of every mesh: the overview and a crop per region.

    Returns:
        (overview camera index, {name: render} cropped to what is seen, the regions'
        overview boxes, [{name: render} per region] (each mesh clipped to a ball of 2.5
        region radii, seen by `feature_camera`)).
    """
    from neus_l0.figures.render import clip_to_ball, render_mesh
    from neus_l0.figures.views import feature_camera, overview_camera

    view = overview_camera(cams, regions)
    cam = cams[view].scaled(width / cams[view].width)
    over = {s: render_mesh(m, cam) for s, m in meshes.items()}
    boxes = crop_to_content(over, cam, regions)
    crops = []
    for f in regions:
        fcam = feature_camera(f, cams[view], crop_size)
        crops.append({s: render_mesh(clip_to_ball(m, f["center"], 2.5 * f["radius"]), fcam)
                      for s, m in meshes.items()})
    return view, over, boxes, crops


def _and(names: list[str]) -> str:
    """"a, b and c"."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def make_real_figures(scene_dir: Path, runs: dict[str, BenchRun], out: Path,
                      overview_width: int = 480, crop_size: int = 192, regions: int = 4,
                      log=print) -> list[FigureEntry]:
    """overview_shaded.png and regions_shaded.png of a scene without ground truth.

    Args:
        scene_dir: the scene (cameras_sphere.npz, image/; no gt_mesh.ply needed).
        runs: {sampler: finished run} (two or more, same scene, budget and seed).
        out: output folder (created).
        overview_width: width of the overview renders in pixels.
        crop_size: side of the square zoomed crops in pixels.
        regions: how many places of largest disagreement to box and zoom on.
        log: progress printer.

    Returns:
        the index entries.
    """
    from neus_l0.figures.compose import crops_figure, overview_figure
    from neus_l0.figures.render import shaded_rgb
    from neus_l0.figures.views import scene_cameras

    out.mkdir(parents=True, exist_ok=True)
    cams = scene_cameras(scene_dir)
    if not cams:
        raise NeusL0Error(f"{scene_dir / 'cameras_sphere.npz'}: no cameras")
    meshes = {s: load_mesh(r.mesh) for s, r in runs.items()}
    names, what, run_names = list(runs), describe_runs(runs), [r.run_dir.name for r in
                                                                runs.values()]
    log(f"figures: {what} (no ground truth); runs {', '.join(run_names)}")
    regs = disagreement_regions(meshes, regions)
    top = regs[0]["disagreement"] if regs else 0.0
    log(f"  {len(regs)} regions where the meshes differ most (largest {top:.3g} world units)")
    view, over, boxes, crops = render_real(meshes, cams, regs, overview_width, crop_size)
    log(f"  rendered the overview from camera {view} and {len(crops)} region crops")
    overview_figure(out / "overview_shaded.png", [(s, shaded_rgb(over[s]["shade"])) for s in names],
                    boxes, f"Meshes from scene camera {view} ({what}). No ground truth: boxes "
                    "mark the places where the meshes differ most")
    entries = [FigureEntry("overview_shaded.png",
                           f"the {_and(names)} meshes from scene camera {view}, shaded (the "
                           "scene has no ground truth, so no error colours), with numbered "
                           f"boxes on the {len(regs)} places where the meshes differ most: "
                           "points on one mesh's surface farthest from another mesh's surface, "
                           f"at least two region radii apart (largest distance {top:.3g} world "
                           "units)", run_names)]
    if regs:
        rows = [(f["name"], [shaded_rgb(c[s]["shade"]) for s in names], [""] * len(names))
                for f, c in zip(regs, crops, strict=True)]
        crops_figure(out / "regions_shaded.png", names, rows,
                     f"Zoom on the places where the meshes differ most ({what}). No ground "
                     "truth: which mesh is right is not known")
        entries.append(FigureEntry(
            "regions_shaded.png",
            "zoomed, shaded renders of each place where the meshes differ most (one row "
            "each, titled with the distance in world units from a point on one mesh to "
            "another mesh's surface; a virtual camera per region looking from the overview "
            f"camera's side; each mesh clipped to a ball of 2.5 region radii, radius "
            f"{regs[0]['radius']:.3g}); without ground truth this shows where the samplers "
            "differ, not which is right", run_names))
    log(f"  wrote {', '.join(e.file for e in entries)}")
    return entries
