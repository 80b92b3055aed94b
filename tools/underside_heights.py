"""Where `neus-l0 mesh --close-underside` would cut finished runs, and where else (#35).

For each run this extracts the first mesh (inside the run's hull, cleaned), counts which
training views see each vertex inside their masks (`neus_l0.mesh.underside.seen_counts`)
and reports the plane's height along up, half a mean edge below the lowest firm seen vertex
(`lowest_firm`, the ring of `MIN_RING`), under three rules:

- ``shipped``: a vertex counts when 1 view sees it (what `underside_plane` does);
- ``two_views``: only when 2 views see it;
- ``per_view_q10`` / ``per_view_q25``: each view's own lowest firm seen vertex, then the 10 %
  and 25 % quantile over the views (these two without the margin).

On a synthetic scene (``gt_mesh.ply``) the truth's lowest point along up is beside them.

    python tools/underside_heights.py RUN [RUN ...] [--resolution 256] [--json OUT]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import trimesh

from neus_l0.atomic import atomic_write_json
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.from_run import mesh_from_run, run_scene, training_views
from neus_l0.mesh.underside import MIN_RING, camera_up, lowest_firm, seen_counts


def heights(mesh: trimesh.Trimesh, projections: np.ndarray, masks: list[np.ndarray],
            margin: float = 0.5) -> dict:
    """The plane heights of the rules above for one first mesh (world units)."""
    up = camera_up(projections, mesh.bounds.mean(axis=0))
    h = np.asarray(mesh.vertices) @ up
    edge = float(mesh.edges_unique_length.mean())
    counts = seen_counts(mesh, projections, masks)
    if not (counts >= 1).any():
        raise NeusL0Error("no vertex of the mesh is seen inside a mask")
    per_view = []
    for v in range(len(masks)):
        seen = seen_counts(mesh, projections[v:v + 1], masks[v:v + 1]) > 0
        if seen.any():
            per_view.append(lowest_firm(h[seen], edge, MIN_RING))
    two = counts >= 2
    return {"up": up.tolist(), "edge": edge, "lowest_vertex": float(h.min()),
            "shipped": lowest_firm(h[counts >= 1], edge, MIN_RING) - margin * edge,
            "two_views": (lowest_firm(h[two], edge, MIN_RING) - margin * edge
                          if two.any() else None),
            "per_view_q10": float(np.quantile(per_view, 0.1)),
            "per_view_q25": float(np.quantile(per_view, 0.25))}


def report(run_dir: Path, resolution: int) -> dict:
    """`heights` of a run's first mesh, with the truth's lowest point when the scene has it.

    Raises:
        NeusL0Error: not a run, or its scene's masks missing (`training_views`).
    """
    projections, masks = training_views(run_dir)
    mesh = mesh_from_run(run_dir, resolution).mesh
    row = {"run": str(run_dir), **heights(mesh, projections, masks)}
    gt = Path(run_scene(run_dir)[0]) / "gt_mesh.ply"
    row["truth"] = (float((np.asarray(trimesh.load(gt).vertices) @ np.asarray(row["up"])).min())
                    if gt.is_file() else None)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="training run folders")
    ap.add_argument("--resolution", type=int, default=256, help="the first mesh's grid")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for run in args.runs:
        try:
            rows.append(report(run, args.resolution))
        except NeusL0Error as exc:
            print(f"underside_heights: {exc}")
            return 2
        r = rows[-1]
        two = "-" if r["two_views"] is None else f"{r['two_views']:.2f}"
        print(f"{run}: shipped {r['shipped']:.2f}, two views {two}, per view "
              f"q10 {r['per_view_q10']:.2f} q25 {r['per_view_q25']:.2f}, truth {r['truth']}")
    if args.json:
        atomic_write_json(args.json, {"runs": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
