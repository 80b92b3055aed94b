"""Where a mesh's accuracy error comes from, on a synthetic scene (issue #35: "flat faces").

Usage:
    python tools/accuracy_parts.py MESH SCENE_DIR [--holdout 8] [--points 300000] [--json OUT]

The scene's accuracy is the mean distance of the mesh's scored points to the true surface
(`neus_l0.evaluation.score`: points that some view observes, truncated at 20 world units).
This tool samples the mesh evenly, keeps the points the score keeps and splits their
distances into parts that tell a bumpy face from misplaced volume:

- ``under``: points below the lowest ground-truth point (the side no camera looks at: the
  synthetic scenes' cameras sit 20-70 degrees above the object). For them it also counts
  how many training views (every view but each ``--holdout``-th, as the bench trains) see
  them against the background, and their pixel distance to the mask there;
- ``top``: faces whose normal is within 10 degrees of up (flat tops);
- ``axis``: other faces within 10 degrees of an axis (flat sides);
- ``other``: the rest (curved parts, pit walls, rods).

Per part: its share of the scored points, its mean distance and its share of the summed
distance (the accuracy's share). Also the accuracy without ``under`` and distance bands.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error

#: Faces within this angle (degrees) of an axis count as flat.
FLAT_DEG = 10.0
#: Distance bands (world units) of the breakdown.
BANDS = (0.0, 0.5, 1.0, 2.0, 5.0, 20.0)


def face_parts(normals: np.ndarray, points: np.ndarray, lowest: float) -> np.ndarray:
    """(N,) part names of points with (N, 3) unit normals (z up) and (N, 3) positions."""
    cos = np.cos(np.deg2rad(FLAT_DEG))
    axis = np.abs(normals).max(1) > cos
    up = normals[:, 2] > cos
    part = np.where(up, "top", np.where(axis, "axis", "other")).astype(object)
    part[points[:, 2] < lowest - 1.0] = "under"
    return part


def part_table(dist: np.ndarray, part: np.ndarray) -> list[dict]:
    """Per part: share of points, mean distance, share of the summed distance (pure)."""
    total = float(dist.sum()) or 1.0
    rows = []
    for name in ("top", "axis", "other", "under"):
        sel = part == name
        rows.append({"part": name, "points": float(sel.mean()) if len(sel) else 0.0,
                     "mean": float(dist[sel].mean()) if sel.any() else float("nan"),
                     "accuracy share": float(dist[sel].sum() / total)})
    return rows


def band_table(dist: np.ndarray) -> list[dict]:
    """Per distance band of `BANDS`: share of points and of the summed distance (pure). The
    last band is closed: it holds the points truncated at the score's 20 units."""
    total = float(dist.sum()) or 1.0
    rows = []
    for k, (lo, hi) in enumerate(zip(BANDS[:-1], BANDS[1:])):
        last = k == len(BANDS) - 2
        sel = (dist >= lo) & ((dist <= hi) if last else (dist < hi))
        rows.append({"band": f"[{lo:g}, {hi:g}{']' if last else ')'}",
                     "points": float(sel.mean()) if len(sel) else 0.0,
                     "accuracy share": float(dist[sel].sum() / total)})
    return rows


def under_views(points: np.ndarray, scene_dir: Path, holdout: int) -> dict:
    """How the training views see (M, 3) world points: against the background in how many,
    and how many pixels from the mask's edge there."""
    import cv2

    from neus_l0.data.cameras import depth_projection, pixel_indices, read_masks
    from neus_l0.evaluation.synthetic import load_synthetic_gt

    gt = load_synthetic_gt(scene_dir)
    masks = read_masks(scene_dir)
    p_n = depth_projection(gt.projections)
    views = [v for v in range(len(p_n)) if not (holdout and v % holdout == 0)]
    seen = np.zeros(len(points), dtype=int)
    edge = []
    for v in views:
        h, w = gt.depths[v].shape
        col, row, _ = pixel_indices(p_n[v], points, h, w)
        inside = col >= 0
        bg = np.zeros(len(points), dtype=bool)
        bg[inside] = ~np.isfinite(gt.depths[v][row[inside], col[inside]])
        seen += bg
        if bg.any():
            dist = cv2.distanceTransform((~np.asarray(masks[v], dtype=bool)).astype(np.uint8),
                                         cv2.DIST_L2, 5)
            edge.append(dist[row[bg], col[bg]])
    edge_px = np.concatenate(edge) if edge else np.zeros(0)
    return {"training views": len(views),
            "seen against the background in a training view": float((seen > 0).mean())
            if len(points) else float("nan"),
            "views per point": float(seen.mean()) if len(points) else float("nan"),
            "pixels from the mask, median": float(np.median(edge_px)) if len(edge_px)
            else float("nan"),
            "pixels from the mask, 90th percentile": float(np.percentile(edge_px, 90))
            if len(edge_px) else float("nan")}


def analyse(mesh_path: Path, scene_dir: Path, holdout: int, n_points: int) -> dict:
    """The whole breakdown of one mesh (see the module docstring)."""
    import trimesh

    from neus_l0.evaluation.io import load_mesh
    from neus_l0.evaluation.score import ScoreSpec, load_ground_truth

    mesh = trimesh.Trimesh(*load_mesh(mesh_path), process=False)  # NeusL0Error: unreadable
    spec = ScoreSpec(scene=scene_dir, density=0.5)
    truth = load_ground_truth(spec)  # a synthetic scene's (NeusL0Error when it is not one)
    pts, face = trimesh.sample.sample_surface_even(mesh, n_points, seed=0)
    scored = truth.scored(pts, spec)
    pts, normals = pts[scored], mesh.face_normals[face][scored]
    dist = truth.distance(pts, spec.max_dist, 1)
    dist = np.where(np.isfinite(dist), dist, spec.max_dist)
    lowest = float(truth.points[:, 2].min())
    part = face_parts(normals, pts, lowest)
    bands = band_table(dist)
    under = part == "under"
    return {"mesh": str(mesh_path), "scene": str(scene_dir), "scored points": int(len(pts)),
            "accuracy": float(dist.mean()),
            "accuracy without under": float(dist[~under].mean()) if (~under).any()
            else float("nan"),
            "parts": part_table(dist, part), "bands": bands,
            "under": under_views(pts[under], scene_dir, holdout)}


def markdown(rep: dict) -> str:
    """The report as a few markdown lines."""
    lines = [f"accuracy (this sampling) {rep['accuracy']:.3f}, without `under` "
             f"{rep['accuracy without under']:.3f}, {rep['scored points']} scored points",
             "", "| part | points | mean distance | accuracy share |", "|---|---:|---:|---:|"]
    lines += [f"| {r['part']} | {r['points']:.3f} | {r['mean']:.3f} | {r['accuracy share']:.2f} |"
              for r in rep["parts"]]
    lines += ["", "| distance | points | accuracy share |", "|---|---:|---:|"]
    lines += [f"| {b['band']} | {b['points']:.3f} | {b['accuracy share']:.2f} |"
              for b in rep["bands"]]
    lines += ["", "under: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                       for k, v in rep["under"].items())]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--holdout", type=int, default=8,
                    help="every K-th view is held out of training (the bench's 8; 0: none)")
    ap.add_argument("--points", type=int, default=300000, help="mesh samples")
    ap.add_argument("--json", type=Path, default=None, help="also write the report here")
    args = ap.parse_args(argv)
    try:
        rep = analyse(args.mesh, args.scene, args.holdout, args.points)
    except (NeusL0Error, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(markdown(rep))
    if args.json:
        from neus_l0.atomic import atomic_write_json

        atomic_write_json(args.json, rep)
    return 0


if __name__ == "__main__":
    sys.exit(main())
