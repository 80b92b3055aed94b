"""Where the photometric term (`train.photo`) pulls a feature's surface: its cost on exact
geometry, slid along each pixel's ray (issue #35: a deep cavity's floor comes out raised).

For every pixel whose first true hit (`first_hits`) lies in a feature's ball
(``features.json``), the true surface point is moved `d` world units along the pixel's ray
(d < 0: towards the camera, i.e. a floor raised) with the true normal kept, and the term's
cost is computed there exactly as training does (`plane_points`, `project`, `sample_gray`,
`ncc`, the best `--best` of the view's `--sources` nearest views by `best_cost`). Prints, per
feature and offset, the mean cost and the share of pixels whose cost is lowest at that
offset: a term that pulls the surface to the truth has both at d = 0.

With `--max-cost T` a source whose own cost exceeds T does not count (a pixel with none
left does not count): the rule `train.photo.max_cost` applies. The last table splits the
sources' costs at d = 0 by whether the source sees the point (its exact depth map within
`--tol`): how well a cost threshold separates an occluded source from a seeing one.

    python tools/photo_cost_profile.py SCENE [--features "cavity floor,outer wall"]
        [--offsets=-6,-4,-2,-1,0,1,2] [--sources 4] [--best 2] [--max-cost 1]
        [--pixels 400] [--out table.json]
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
from neus_l0.data.patches import ncc
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.formats.neus import load_scene
from neus_l0.train.photometric import (
    PhotoContext,
    best_cost,
    plane_points,
    project,
    sample_gray,
)


def source_costs(ctx: PhotoContext, view: int, xy: torch.Tensor, points: torch.Tensor,
                 normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each source's cost (B, M) and validity (B, M) for reference pixels `xy` (B, 2) of
    `view` seeing the planes through `points` (B, 3) with `normals` (B, 3) (normalised
    frame), as `neus_l0.train.photometric.photometric_term` scores them."""
    b = len(xy)
    v = torch.full((b,), view, dtype=torch.long)
    pix = xy[:, None, :] + ctx.offsets[None]  # (B, P, 2)
    ref, _ = sample_gray(ctx.gray, ctx.height, ctx.width, v[:, None], pix)
    pts = plane_points(ctx.centres[v], ctx.rays[v], pix, points, normals)
    src = ctx.sources[v]  # (B, M)
    uv, z = project(pts, ctx.proj[src], ctx.centres[src])
    vals, inside = sample_gray(ctx.gray, ctx.height, ctx.width, src[..., None], uv)
    facing = ((ctx.centres[src] - points[:, None, :]) * normals[:, None, :]).sum(-1) > 0
    valid = facing & (z > 0).all(-1) & inside.all(-1)
    return (1.0 - ncc(ref, vals)) * 0.5, valid


def sees(points_w: np.ndarray, views: np.ndarray, depth: np.ndarray,
         projections: np.ndarray, tol: float) -> np.ndarray:
    """(B, M) whether view ``views[b, m]`` sees world point ``points_w[b]``: its depth map
    at the point's pixel within `tol` of the point's own depth."""
    from neus_l0.data.cameras import depth_projection, pixel_indices

    H, W = depth.shape[1:]
    out = np.zeros(views.shape, dtype=bool)
    for j in np.unique(views):
        rows_b, cols_m = np.nonzero(views == j)
        col, row, z = pixel_indices(depth_projection(projections[j]), points_w[rows_b], H, W)
        ok = col >= 0
        there = np.full(len(rows_b), np.nan)
        there[ok] = depth[j][row[ok], col[ok]]
        out[rows_b, cols_m] = ok & (np.abs(there - z) < tol)
    return out


def profile(root: Path, names: list[str] | None, offsets: list[float], sources: int,
            best: int, max_cost: float, pixels: int, tol: float, seed: int = 0) -> list[dict]:
    """Per feature: the mean best-`best` cost and the share of pixels lowest at each offset,
    and the cost quantiles of seeing and of occluded sources at d = 0."""
    pts, depth, projections = first_hits(root)
    feats = json.loads((root / "features.json").read_text())["features"]
    if names is not None:
        missing = sorted(set(names) - {f["name"] for f in feats})
        if missing:
            raise SystemExit(f"{root / 'features.json'}: no feature named {missing}")
        feats = [f for f in feats if f["name"] in names]
    scene = load_scene(root)
    ctx = PhotoContext.from_scene(scene, sources, 3, 1, best)
    scale = float(scene.scale_mat[0, 0])
    centre = np.asarray(scene.scale_mat[:3, 3])
    mesh = trimesh.load(root / "gt_mesh.ply", process=False)
    tree = cKDTree(np.asarray(mesh.triangles_center))
    rng = np.random.default_rng(seed)
    rows = []
    for f in feats:
        inside = np.linalg.norm(pts - np.asarray(f["center"]), axis=-1) <= f["radius"]
        per_offset, seen_c, hidden_c = [], [], []
        for v in range(len(projections)):
            ys, xs = np.nonzero(inside[v])
            if len(xs) == 0:
                continue
            if len(xs) > pixels:
                keep = rng.choice(len(xs), pixels, replace=False)
                ys, xs = ys[keep], xs[keep]
            xw = pts[v][ys, xs]  # (B, 3) world
            cam = scene.c2w[v, :3, 3].double().numpy() * scale + centre
            _, face = tree.query(xw)
            n = np.asarray(mesh.face_normals)[face]
            n = np.where((((cam - xw) * n).sum(-1) < 0)[:, None], -n, n)
            ray = (xw - cam) / np.linalg.norm(xw - cam, axis=-1, keepdims=True)
            xy = torch.tensor(np.stack([xs, ys], -1), dtype=torch.float32)
            nt = torch.tensor(n, dtype=torch.float32)
            costs = []
            for d in offsets:
                xn = torch.tensor((xw + d * ray - centre) / scale, dtype=torch.float32)
                c, ok = source_costs(ctx, v, xy, xn, nt)
                ok = ok & (c <= max_cost)
                per_ray, any_ok = best_cost(c, ok, ctx.best)
                costs.append(torch.where(any_ok, per_ray, torch.nan).numpy())
                if d == 0:
                    vis = sees(xw, ctx.sources[v].numpy()[None].repeat(len(xw), 0), depth,
                               projections, tol)
                    cv = c.numpy()
                    seen_c.append(cv[vis])
                    hidden_c.append(cv[~vis])
            per_offset.append(np.stack(costs, -1))  # (B, D)
        if not per_offset:
            continue
        c = np.concatenate(per_offset)
        counted = np.isfinite(c).all(-1)
        best_at = np.argmin(np.where(np.isfinite(c), c, np.inf), -1)[counted]
        seen_c, hidden_c = np.concatenate(seen_c), np.concatenate(hidden_c)
        rows.append({
            "feature": f["name"], "pixels": int(len(c)), "counted": int(counted.sum()),
            "mean_cost": [float(np.nanmean(c[:, i])) for i in range(len(offsets))],
            "lowest_at": [float((best_at == i).mean()) if len(best_at) else 0.0
                          for i in range(len(offsets))],
            "seen_sources": int(seen_c.size), "hidden_sources": int(hidden_c.size),
            "seen_quantiles": np.quantile(seen_c, [0.1, 0.5, 0.9]).tolist() if seen_c.size
            else [], "hidden_quantiles": np.quantile(hidden_c, [0.1, 0.5, 0.9]).tolist()
            if hidden_c.size else []})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a synthetic scene folder (neus-l0 synth)")
    ap.add_argument("--features", default="", help="comma-separated names (default: all)")
    ap.add_argument("--offsets", default="-6,-4,-2,-1,0,1,2",
                    help="world units along the ray (negative: towards the camera)")
    ap.add_argument("--sources", type=int, default=4)
    ap.add_argument("--best", type=int, default=2)
    ap.add_argument("--max-cost", type=float, default=1.0,
                    help="a source costing more does not count (as train.photo.max_cost)")
    ap.add_argument("--pixels", type=int, default=400, help="pixels a view and feature, at most")
    ap.add_argument("--tol", type=float, default=1.5, help="depth tolerance, world units")
    ap.add_argument("--out", type=Path, help="also write the table as JSON")
    a = ap.parse_args(argv)
    names = [n.strip() for n in a.features.split(",") if n.strip()] or None
    try:
        offsets = [float(x) for x in a.offsets.split(",")]
    except ValueError:
        raise SystemExit(f"--offsets {a.offsets!r}: comma-separated numbers") from None
    if 0.0 not in offsets:
        raise SystemExit("--offsets: must include 0 (the true surface)")
    try:
        rows = profile(a.scene, names, offsets, a.sources, a.best, a.max_cost, a.pixels, a.tol)
    except NeusL0Error as exc:
        raise SystemExit(f"photo_cost_profile: {exc}") from None
    print("| feature | pixels (counted) | " + " | ".join(f"d={d:g}" for d in offsets) + " |")
    print("|---|---:|" + "---:|" * len(offsets))
    for r in rows:
        cells = [f"{m:.3f} ({s:.2f})" for m, s in zip(r["mean_cost"], r["lowest_at"])]
        print(f"| {r['feature']} | {r['pixels']} ({r['counted']}) | " + " | ".join(cells) + " |")
    print("\n| feature | seeing sources: cost q10 / q50 / q90 | occluded sources |")
    print("|---|---|---|")
    for r in rows:
        q = " / ".join(f"{x:.3f}" for x in r["seen_quantiles"])
        h = " / ".join(f"{x:.3f}" for x in r["hidden_quantiles"])
        print(f"| {r['feature']} | {r['seen_sources']}: {q} | {r['hidden_sources']}: {h} |")
    if a.out:
        atomic_write_json(a.out, {"scene": str(a.scene), "offsets": offsets,
                                  "sources": a.sources, "best": a.best,
                                  "max_cost": a.max_cost, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
