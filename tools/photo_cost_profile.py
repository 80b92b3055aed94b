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
from source_visibility import seen_by, true_normals  # a sibling tool (run as a script)

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


def view_costs(ctx: PhotoContext, view: int, xw: np.ndarray, normals: np.ndarray,
               xy: np.ndarray, offsets: list[float], geometry: dict,
               max_cost: float) -> tuple[np.ndarray, np.ndarray]:
    """One view's pixels `xy` (B, 2) seeing world points `xw` (B, 3) with true `normals`:
    the best-k cost at each offset (B, D; NaN where no source counts) and each source's
    cost at d = 0 with whether it sees the point, (B, M) each stacked as (2, B, M).
    `geometry`: the scene's ``scale``, ``centre``, ``depth`` and ``projections``."""
    scale, centre = geometry["scale"], geometry["centre"]
    cam = ctx.centres[view].double().numpy() * scale + centre
    ray = (xw - cam) / np.linalg.norm(xw - cam, axis=-1, keepdims=True)
    pix = torch.tensor(xy, dtype=torch.float32)
    nt = torch.tensor(normals, dtype=torch.float32)
    costs, at_zero = [], None
    for d in offsets:
        xn = torch.tensor((xw + d * ray - centre) / scale, dtype=torch.float32)
        c, ok = source_costs(ctx, view, pix, xn, nt)
        per_ray, any_ok = best_cost(c, ok & (c <= max_cost), ctx.best)
        costs.append(torch.where(any_ok, per_ray, torch.nan).numpy())
        if d == 0:
            seen = np.stack([seen_by(xw, np.array([int(j)]), geometry["depth"],
                                     geometry["projections"], geometry["tol"]) > 0
                             for j in ctx.sources[view]], -1)
            at_zero = np.stack([c.numpy(), seen])
    return np.stack(costs, -1), at_zero


def profile(root: Path, names: list[str] | None, offsets: list[float], sources: int,
            best: int, max_cost: float, pixels: int, tol: float) -> list[dict]:
    """Per feature: the mean best-`best` cost and the share of pixels lowest at each offset,
    and the cost quantiles of seeing and of occluded sources at d = 0 (pixels drawn with
    seed 0)."""
    pts, depth, projections = first_hits(root)
    path = root / "features.json"
    if not path.is_file():
        raise SystemExit(f"{path}: missing (a synthetic scene from neus-l0 synth has one)")
    feats = json.loads(path.read_text())["features"]
    if names is not None:
        missing = sorted(set(names) - {f["name"] for f in feats})
        if missing:
            raise SystemExit(f"{path}: no feature named {missing}")
        feats = [f for f in feats if f["name"] in names]
    scene = load_scene(root)
    ctx = PhotoContext.from_scene(scene, sources, 3, 1, best)
    geometry = {"scale": float(scene.scale_mat[0, 0]),
                "centre": np.asarray(scene.scale_mat[:3, 3]),
                "depth": depth, "projections": projections, "tol": tol}
    mesh = trimesh.load(root / "gt_mesh.ply", process=False)
    tree = cKDTree(np.asarray(mesh.triangles_center))
    rng = np.random.default_rng(0)
    rows = []
    for f in feats:
        inside = np.linalg.norm(pts - np.asarray(f["center"]), axis=-1) <= f["radius"]
        per_offset, seen_c, hidden_c = [], [], []
        for v in range(len(projections)):
            ys, xs = np.nonzero(inside[v])
            if len(xs) > pixels:
                keep = rng.choice(len(xs), pixels, replace=False)
                ys, xs = ys[keep], xs[keep]
            if len(xs) == 0:
                continue
            xw = pts[v][ys, xs]
            cam = ctx.centres[v].double().numpy() * geometry["scale"] + geometry["centre"]
            n = true_normals(mesh, tree, xw, np.broadcast_to(cam, xw.shape))
            c, (c0, seen) = view_costs(ctx, v, xw, n, np.stack([xs, ys], -1), offsets,
                                       geometry, max_cost)
            per_offset.append(c)
            seen_c.append(c0[seen > 0])
            hidden_c.append(c0[seen == 0])
        if per_offset:
            rows.append(_row(f["name"], np.concatenate(per_offset), np.concatenate(seen_c),
                             np.concatenate(hidden_c), len(offsets)))
    return rows


def _row(name: str, c: np.ndarray, seen_c: np.ndarray, hidden_c: np.ndarray,
         n_offsets: int) -> dict:
    """A feature's table row from its pixels' costs (P, D) and its sources' costs at d = 0."""
    counted = np.isfinite(c).all(-1)
    best_at = np.argmin(np.where(np.isfinite(c), c, np.inf), -1)[counted]
    q = [0.1, 0.5, 0.9]
    return {"feature": name, "pixels": int(len(c)), "counted": int(counted.sum()),
            "mean_cost": [float(np.nanmean(c[:, i])) for i in range(n_offsets)],
            "lowest_at": [float((best_at == i).mean()) if len(best_at) else 0.0
                          for i in range(n_offsets)],
            "seen_sources": int(seen_c.size), "hidden_sources": int(hidden_c.size),
            "seen_quantiles": np.quantile(seen_c, q).tolist() if seen_c.size else [],
            "hidden_quantiles": np.quantile(hidden_c, q).tolist() if hidden_c.size else []}


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
