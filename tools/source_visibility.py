"""How many of a pixel's source views see what the pixel sees: the photometric term's
(`train.photo`) blind spot, measured on a synthetic scene's exact depth maps (issue #35).

For every pixel whose first true hit lies in a feature's ball (``features.json``), the hit
point is projected into the view's `--sources` nearest views (`nearest_views`, as the term
picks them); a source sees it when its own depth map at that pixel (nearest) lies within
`--tol` world units of the point's depth. Prints, per feature, the pixels and views counted
and the share of pixels seen by 0, 1, 2, ... sources.

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
from neus_l0.train.photometric import nearest_views


def first_hits(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(V, H, W, 3) world first hits of every pixel (NaN on misses), (V, H, W) depths along
    the optical axis, (V, 3, 3) K and (V, 4, 4) camera-to-world, from ``scene.json`` and
    ``gt_depth.npz``."""
    meta = json.loads((root / "scene.json").read_text())
    K = np.asarray(meta["cameras"]["intrinsics"], dtype=np.float64)
    c2w = np.asarray(meta["cameras"]["c2w_world"], dtype=np.float64)
    with np.load(root / "gt_depth.npz") as f:
        depth = np.stack([f[f"depth_{i}"] for i in range(len(c2w))]).astype(np.float64)
    H, W = depth.shape[1:]
    xs, ys = np.meshgrid(np.arange(W), np.arange(H))
    cam = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T  # (H, W, 3), z = 1
    d = np.where(np.isfinite(depth), depth, np.nan)[..., None]
    pts = np.einsum("vij,vhwj->vhwi", c2w[:, :3, :3], cam[None] * d) + c2w[:, None, None, :3, 3]
    return pts, depth, K, c2w


def seen_by(points: np.ndarray, sources: np.ndarray, depth: np.ndarray, K: np.ndarray,
            c2w: np.ndarray, tol: float) -> np.ndarray:
    """(N,) how many of the views `sources` (M,) see the world points (N, 3): in the image,
    in front, and their depth map at the (nearest) pixel within `tol` of the point's."""
    H, W = depth.shape[1:]
    count = np.zeros(len(points), dtype=np.int64)
    for j in sources:
        cam = (points - c2w[j, :3, 3]) @ c2w[j, :3, :3]  # R^T (X - c)
        z = cam[:, 2]
        uv = (cam @ K.T)[:, :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[:, None]
        u, v = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        there = np.full(len(points), np.nan)
        there[ok] = depth[j][v[ok], u[ok]]
        count += (ok & (np.abs(there - z) < tol)).astype(np.int64)
    return count


def visibility_table(root: Path, names: list[str] | None, n_sources: int,
                     tol: float) -> list[dict]:
    """Per feature (all of ``features.json`` when `names` is None): pixels, views, and the
    share of pixels seen by k sources, k = 0 .. n_sources."""
    pts, depth, K, c2w = first_hits(root)
    feats = json.loads((root / "features.json").read_text())["features"]
    if names is not None:
        missing = sorted(set(names) - {f["name"] for f in feats})
        if missing:
            raise SystemExit(f"{root / 'features.json'}: no feature named {missing}")
        feats = [f for f in feats if f["name"] in names]
    with np.load(root / "cameras_sphere.npz") as cams:  # the object sphere's centre
        centre = np.asarray(cams["scale_mat_0"], dtype=np.float64)[:3, 3]
    centres = torch.tensor(c2w[:, :3, 3] - centre)  # the term's frame, up to scale
    sources = nearest_views(centres, n_sources).numpy()
    rows = []
    for f in feats:
        inside = np.linalg.norm(pts - np.asarray(f["center"]), axis=-1) <= f["radius"]
        counts, views = [], 0
        for v in range(len(c2w)):
            sel = inside[v]
            if sel.any():
                views += 1
                counts.append(seen_by(pts[v][sel], sources[v], depth, K, c2w, tol))
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
    rows = visibility_table(a.scene, names, a.sources, a.tol)
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
