"""The thin parts' own error: Chamfer sides inside a tube around each rod's axis (issue #35).

Usage:
    python tools/tube_errors.py SCENE MESH [MESH ...] [--tube 6] [--points 1000000]
                                [--json OUT]

The score's feature crops (`neus_l0.evaluation.features`) are balls that hold a feature
whole: a rod's ball has the rod's half-length as its radius, so it also holds what stands
near the rod (a cavity's floor around a rod's foot, the seat above a stool's leg, the slack
under it). This tool crops each thin feature that has an axis to the points within
``--tube`` world units of its axis segment (`neus_l0.evaluation.features.near_axis`): the
rod and a margin. Per mesh and rod:

- accuracy: the mean distance of the mesh's points in the tube (an even sample of
  ``--points`` on the mesh, kept where the score keeps them: observed by a view, inside the
  scene's box) to the nearest ground-truth point (``gt_points.ply``, about 0.5 apart:
  point-to-point, which the score refines to point-to-mesh), truncated at the score's
  ``max_dist`` as the score does;
- completeness: the mean distance of the ground-truth points in the tube to the mesh's
  sample, truncated alike;
- overall: their mean; and the point counts.

The score's own protocol (`neus-l0 eval`) is not changed: these numbers sit beside it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_write_json
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.features import load_features, near_axis


def _mean(d: np.ndarray, max_dist: float) -> float:
    d = d[d < max_dist]
    return float(d.mean()) if len(d) else float("nan")


def tube_rows(pred: np.ndarray, dist_pred: np.ndarray, gt: np.ndarray, dist_gt: np.ndarray,
              features: list[dict], tube: float, max_dist: float) -> list[dict]:
    """Per thin feature with an axis: the Chamfer sides of the points in its tube (pure).

    Args:
        pred: (N, 3) mesh points; dist_pred: (N,) their distances to the true surface.
        gt: (M, 3) true surface points; dist_gt: (M,) their distances to the mesh.
        features: `load_features` entries (others than thin ones with an axis are skipped).
        tube, max_dist: world units.
    """
    rows = []
    for f in features:
        if f["kind"] != "thin" or f.get("axis") is None:
            continue
        in_p, in_g = near_axis(pred, f, tube), near_axis(gt, f, tube)
        acc, comp = _mean(dist_pred[in_p], max_dist), _mean(dist_gt[in_g], max_dist)
        rows.append({"feature": f["name"], "accuracy": acc, "completeness": comp,
                     "overall": (acc + comp) / 2, "n_pred": int(in_p.sum()),
                     "n_gt": int(in_g.sum())})
    return rows


def mesh_tubes(mesh_path: Path, scene: Path, tube: float, n_points: int) -> list[dict]:
    """`tube_rows` of one mesh file on a synthetic scene."""
    import trimesh
    from scipy.spatial import cKDTree

    from neus_l0.evaluation.io import load_mesh
    from neus_l0.evaluation.score import ScoreSpec, load_ground_truth

    mesh = trimesh.Trimesh(*load_mesh(mesh_path), process=False)  # NeusL0Error: unreadable
    spec = ScoreSpec(scene=scene, density=0.5)
    truth = load_ground_truth(spec)  # NeusL0Error when the scene is not a synthetic one
    feats = load_features(scene)
    pts, _ = trimesh.sample.sample_surface_even(mesh, n_points, seed=0)
    near = np.zeros(len(pts), dtype=bool)
    for f in feats:
        if f["kind"] == "thin" and f.get("axis") is not None:
            near |= near_axis(pts, f, tube + spec.max_dist)
    kept = pts[near]
    kept = kept[truth.scored(kept, spec)]
    dist_pred, _ = cKDTree(truth.points).query(kept, distance_upper_bound=spec.max_dist)
    dist_gt, _ = cKDTree(pts).query(truth.points, distance_upper_bound=spec.max_dist)
    return tube_rows(kept, dist_pred, truth.points, dist_gt, feats, tube, spec.max_dist)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, help="the synthetic scene (features.json, ground truth)")
    ap.add_argument("meshes", type=Path, nargs="+", help="meshes in world units")
    ap.add_argument("--tube", type=float, default=6.0, help="world units from a rod's axis")
    ap.add_argument("--points", type=int, default=1_000_000, help="points sampled per mesh")
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    args = ap.parse_args(argv)
    if not (args.tube > 0 and args.points > 0):
        ap.error("--tube and --points must be positive")
    out = {}
    try:
        for mesh in args.meshes:
            out[str(mesh)] = mesh_tubes(mesh, args.scene, args.tube, args.points)
    except NeusL0Error as exc:
        print(f"tube_errors: {exc}")
        return 2
    for mesh, rows in out.items():
        print(f"{mesh}\n| feature | accuracy | completeness | overall | n_pred | n_gt |\n"
              "|---|---:|---:|---:|---:|---:|")
        for r in rows:
            print(f"| {r['feature']} | {r['accuracy']:.3f} | {r['completeness']:.3f} | "
                  f"{r['overall']:.3f} | {r['n_pred']} | {r['n_gt']} |")
    if args.json:
        atomic_write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
