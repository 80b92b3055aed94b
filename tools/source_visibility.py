"""How many of a pixel's source views see what the pixel sees: the photometric term's
(`train.photo`) blind spot, measured on a synthetic scene's exact depth maps (issue #35).

For every pixel whose first true hit (`first_hits`) lies in a feature's ball
(``features.json``), the hit point is projected into the view's `--sources` nearest views
(`nearest_views`, as the term picks them); a source sees it when its own depth map at that
pixel (`pixel_indices`) lies within `--tol` world units of the point's depth. With
`--normal-sources K` each pixel also gets K sources chosen by the true surface normal at its
hit (`normal_views`, as `train.photo.normal_sources` picks them from the rendered normal; the
normal of the ground-truth mesh's nearest face centre). Prints, per feature, the pixels and
views counted and the share of pixels seen by 0, 1, 2, ... sources.

    python tools/source_visibility.py SCENE [--features "cavity floor,shaft floor"]
        [--sources 4] [--normal-sources 0] [--tol 1.5] [--out table.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from neus_l0.atomic import atomic_write_json
from neus_l0.data.cameras import decompose_projection, depth_projection, pixel_indices
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.train.photometric import nearest_views, normal_views


def seen_by(points: np.ndarray, sources: np.ndarray, depth: np.ndarray,
            projections: np.ndarray, tol: float) -> np.ndarray:
    """(N,) how many of the views `sources` (M,) see the world points (N, 3): in the image,
    in front, and their depth map (camera z) at the point's pixel within `tol` of its own."""
    H, W = depth.shape[1:]
    count = np.zeros(len(points), dtype=np.int64)
    for j in sources:
        col, row, z = pixel_indices(depth_projection(projections[j]), points, H, W)
        inside = col >= 0
        there = np.full(len(points), np.nan)
        there[inside] = depth[j][row[inside], col[inside]]
        count += (inside & (np.abs(there - z) < tol)).astype(np.int64)
    return count


def seen_by_each(points: np.ndarray, sources: np.ndarray, depth: np.ndarray,
                 projections: np.ndarray, tol: float) -> np.ndarray:
    """(N,) as `seen_by`, with each point's own sources (N, K)."""
    count = np.zeros(len(points), dtype=np.int64)
    for j in np.unique(sources):
        has = (sources == j).any(axis=1)
        count[has] += seen_by(points[has], np.array([j]), depth, projections, tol)
    return count


def true_normals(mesh: trimesh.Trimesh, tree: cKDTree, points: np.ndarray,
                 cameras: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of the mesh's faces nearest (by centre) to the points, turned
    towards the cameras (N, 3) that see them."""
    _, face = tree.query(points)
    n = np.asarray(mesh.face_normals)[face]
    back = ((cameras - points) * n).sum(-1) < 0
    return np.where(back[:, None], -n, n)


def visibility_table(root: Path, names: list[str] | None, n_sources: int,
                     tol: float, normal_sources: int = 0) -> list[dict]:
    """Per feature (all of ``features.json`` when `names` is None): pixels, views, and the
    share of pixels seen by k sources, k = 0 .. n_sources + normal_sources."""
    pts, depth, projections = first_hits(root)
    path = root / "features.json"
    if not path.is_file():
        raise SystemExit(f"{path}: missing (a synthetic scene from neus-l0 synth has one)")
    feats = json.loads(path.read_text())["features"]
    if names is not None:
        missing = sorted(set(names) - {f["name"] for f in feats})
        if missing:
            raise SystemExit(f"{root / 'features.json'}: no feature named {missing}")
        feats = [f for f in feats if f["name"] in names]
    with np.load(root / "cameras_sphere.npz") as cams:  # the object sphere's centre
        centre = np.asarray(cams["scale_mat_0"], dtype=np.float64)[:3, 3]
    cams_at = np.stack([decompose_projection(P)[1][:3, 3] for P in projections])
    centres = torch.tensor(cams_at - centre)  # the term's frame, up to scale
    sources = nearest_views(centres, n_sources).numpy()
    k_normal = max(0, min(normal_sources, len(projections) - 1 - sources.shape[1]))
    if k_normal:
        mesh = trimesh.load(root / "gt_mesh.ply", process=False)
        tree = cKDTree(np.asarray(mesh.triangles_center))
    rows = []
    for f in feats:
        inside = np.linalg.norm(pts - np.asarray(f["center"]), axis=-1) <= f["radius"]
        counts, views = [], 0
        for v in range(len(projections)):
            sel = inside[v]
            if not sel.any():
                continue
            views += 1
            x = pts[v][sel]
            if not k_normal:
                counts.append(seen_by(x, sources[v], depth, projections, tol))
                continue
            n = true_normals(mesh, tree, x, np.broadcast_to(cams_at[v], x.shape))
            own = torch.full((len(x),), v, dtype=torch.long)
            near = torch.as_tensor(sources[v]).expand(len(x), -1)
            more = normal_views(torch.as_tensor(cams_at), torch.as_tensor(x),
                                torch.as_tensor(n), own, near, k_normal).numpy()
            counts.append(seen_by_each(x, np.concatenate([near.numpy(), more], axis=1),
                                       depth, projections, tol))
        all_counts = np.concatenate(counts) if counts else np.zeros(0, dtype=np.int64)
        hist = np.bincount(all_counts, minlength=sources.shape[1] + k_normal + 1)
        rows.append({"feature": f["name"], "pixels": int(all_counts.size), "views": views,
                     "share_seen_by": [float(h) / max(1, all_counts.size) for h in hist]})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a synthetic scene folder (neus-l0 synth)")
    ap.add_argument("--features", default="", help="comma-separated names (default: all)")
    ap.add_argument("--sources", type=int, default=4, help="nearest views per view")
    ap.add_argument("--normal-sources", type=int, default=0,
                    help="more sources per pixel, by the true normal (as "
                         "train.photo.normal_sources picks its stand-ins)")
    ap.add_argument("--tol", type=float, default=1.5, help="depth tolerance, world units")
    ap.add_argument("--out", type=Path, help="also write the table as JSON")
    a = ap.parse_args(argv)
    names = [n.strip() for n in a.features.split(",") if n.strip()] or None
    try:
        rows = visibility_table(a.scene, names, a.sources, a.tol, a.normal_sources)
    except NeusL0Error as exc:  # a missing or malformed scene file, named
        raise SystemExit(f"source_visibility: {exc}") from None
    k = len(rows[0]["share_seen_by"]) - 1 if rows else a.sources
    print("| feature | pixels | views | " + " | ".join(f"seen by {i}" for i in range(k + 1))
          + " |")
    print("|---|---:|---:|" + "---:|" * (k + 1))
    for r in rows:
        print(f"| {r['feature']} | {r['pixels']} | {r['views']} | "
              + " | ".join(f"{s:.2f}" for s in r["share_seen_by"]) + " |")
    if a.out:
        atomic_write_json(a.out, {"scene": str(a.scene), "sources": a.sources,
                                  "normal_sources": a.normal_sources, "tol": a.tol,
                                  "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
