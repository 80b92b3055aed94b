"""How many of a pixel's source views see what the pixel sees: the photometric term's
(`train.photo`) blind spot, measured on a synthetic scene's exact depth maps (issue #35).

For every pixel whose first true hit (`first_hits`) lies in a feature's ball
(``features.json``), the hit point is projected into the view's `--sources` nearest views
(`nearest_views`, as the term picks them); a source sees it when its own depth map at that
pixel (`pixel_indices`) lies within `--tol` world units of the point's depth. Prints, per
feature, the pixels and views counted and the share of pixels seen by 0, 1, 2, ... sources.

    python tools/source_visibility.py SCENE [--features "cavity floor,shaft floor"]
        [--sources 4] [--tol 1.5] [--out table.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from neus_l0.atomic import atomic_write_json
from neus_l0.data.cameras import decompose_projection, depth_projection, pixel_indices
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.train.photometric import nearest_views


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


def visibility_table(root: Path, names: list[str] | None, n_sources: int,
                     tol: float) -> list[dict]:
    """Per feature (all of ``features.json`` when `names` is None): pixels, views, and the
    share of pixels seen by k sources, k = 0 .. n_sources."""
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
    rows = []
    for f in feats:
        inside = np.linalg.norm(pts - np.asarray(f["center"]), axis=-1) <= f["radius"]
        counts, views = [], 0
        for v in range(len(projections)):
            sel = inside[v]
            if sel.any():
                views += 1
                counts.append(seen_by(pts[v][sel], sources[v], depth, projections, tol))
        all_counts = np.concatenate(counts) if counts else np.zeros(0, dtype=np.int64)
        hist = np.bincount(all_counts, minlength=sources.shape[1] + 1)
        rows.append({"feature": f["name"], "pixels": int(all_counts.size), "views": views,
                     "share_seen_by": [float(h) / max(1, all_counts.size) for h in hist]})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a synthetic scene folder (neus-l0 synth)")
    ap.add_argument("--features", default="", help="comma-separated names (default: all)")
    ap.add_argument("--sources", type=int, default=4, help="nearest views per view")
    ap.add_argument("--tol", type=float, default=1.5, help="depth tolerance, world units")
    ap.add_argument("--out", type=Path, help="also write the table as JSON")
    a = ap.parse_args(argv)
    names = [n.strip() for n in a.features.split(",") if n.strip()] or None
    try:
        rows = visibility_table(a.scene, names, a.sources, a.tol)
    except NeusL0Error as exc:  # a missing or malformed scene file, named
        raise SystemExit(f"source_visibility: {exc}") from None
    k = a.sources
    print("| feature | pixels | views | " + " | ".join(f"seen by {i}" for i in range(k + 1))
          + " |")
    print("|---|---:|---:|" + "---:|" * (k + 1))
    for r in rows:
        print(f"| {r['feature']} | {r['pixels']} | {r['views']} | "
              + " | ".join(f"{s:.2f}" for s in r["share_seen_by"]) + " |")
    if a.out:
        atomic_write_json(a.out, {"scene": str(a.scene), "sources": k, "tol": a.tol,
                                  "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
