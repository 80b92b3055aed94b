"""Would carving only where a neighbourhood's sweeps agree leave the right surface alone?
(issue #35, outside training)

Ray by ray (`neus-l0 mesh --photo-carve` until session 24), a third of the cup's carving
rays ended more than a unit inside the true surface. This measures, against the exact
surface, the two-pass rule that `--photo-carve` now uses (`neus_l0.mesh.sweep_consensus.
consensus_rays`, whose cells and radius are in pixel footprints; here world units). Pass 1
sweeps the concave pixels (`neus_l0.mesh.plane_sweep.concave_pixels`, every 3rd row and
column) of every `--every`-th view, as `--photo-carve` does. Each ray's displacement along
the mesh normal, h = (best depth - mesh depth) |ray . n|, is pooled in cells of `--cell`
world units (the mesh point's cell and its normal's dominant signed axis; `consensus`).
A cell is flagged when it holds 3 rays or more from 2 views or more, its median h is at
least `MARGIN_PX` footprints, and 30 % of its rays lie within 2 footprints of that median.
Pass 2 sweeps every concave pixel of every view whose mesh point falls in a flagged cell.
A ray would carve when its cell (now dense) holds `--min-rays` from 2 views, `--agree` of
them within 2 footprints of the median, the median is at least `MARGIN_PX` footprints, the
ray itself lies within 2 footprints of the median, its cost is below `MAX_COST`, and the
mesh is not convex around it (`local_convexity` at least `--convex`: on the cup, the sweep's
planar patches end inside the thin handle on 87 % of its rays).

Prints, per feature of ``features.json`` (each ray counted in the first ball that holds its
true hit; the rest "elsewhere"), the rays that agree, those that would carve, the share of
those ending more than a unit inside the true surface, how far the mesh lies in front of the
truth on them and where the sweep ends (median best depth - true depth).

    python tools/carve_consensus.py SCENE MESH [--every 3] [--cell 10] [--min-rays 8]
        [--agree 0.3] [--convex -0.05] [--radius 4] [--out c.json]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

from neus_l0.atomic import atomic_write_json
from neus_l0.data.cameras import read_grays, read_masks
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.features import load_features
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.mesh import plane_sweep as ps
from neus_l0.mesh import sweep_consensus as sc
from neus_l0.mesh.raster import finest_footprint


def first_ball(points: np.ndarray, feats: list[dict]) -> np.ndarray:
    """(N,) the index of the first feature (``features.json``: ``center``, ``radius``) whose
    ball holds each point (N, 3); ``len(feats)`` for none (a NaN point included)."""
    out = np.full(len(points), len(feats))
    for f in reversed(range(len(feats))):
        inside = np.linalg.norm(points - np.asarray(feats[f]["center"]), axis=1) \
            <= feats[f]["radius"]
        out[inside] = f
    return out


def sweep_views(data: dict, views, stride: int, cells: set | None, cell: float) -> np.ndarray:
    """(N, 15) per swept ray of `views` (every `stride`-th pixel; only those whose mesh
    point lies in `cells`, when given): its view, the mesh's depth, the best depth, its cost,
    the true depth, the true hit (3), the mesh point (3), the mesh normal (3) and the
    displacement h along it."""
    rows = []
    for v in views:
        found = ps.concave_pixels(data["samples"], data["normals"], data["verts"],
                                  data["P"][v], data["masks"][v], data["foot"], stride)
        if found is None:
            continue
        pix, centre, rays, z0, n = found
        M = centre + rays * z0[:, None]
        if cells is not None:
            keep = np.array([tuple(k) in cells for k in sc.cell_keys(M, n, cell)], bool)
            if not keep.any():
                continue
            pix, rays, z0, n, M = pix[keep], rays[keep], z0[keep], n[keep], M[keep]
        zb, cb, _ = ps.sweep_depths(data["gray"], data["P"], v, pix, n, z0, data["offsets"])
        h = (zb - z0) * np.abs((rays * n).sum(1))
        truth = data["depth"][v][pix[:, 1], pix[:, 0]]
        X = data["pts"][v][pix[:, 1], pix[:, 0]]
        rows.append(np.column_stack([np.full(len(z0), v), z0, zb, cb, truth, X, M, n, h]))
    return np.concatenate(rows) if rows else np.zeros((0, 15))


def read_inputs(scene: Path, mesh_path: Path) -> dict:
    """The scene's exact first hits, cameras, masks, grey images and features, and the
    mesh's dense surface samples, for `sweep_views` (its keys).

    Raises:
        SystemExit: one line naming the file that is missing or does not match.
    """
    if not mesh_path.is_file():
        raise SystemExit(f"carve_consensus: {mesh_path}: no such mesh file")
    try:
        feats = load_features(scene)  # before the sweeps: a bad file fails now
        pts, depth, P = first_hits(scene)
        masks, grays = read_masks(scene), read_grays(scene)
    except NeusL0Error as exc:
        raise SystemExit(f"carve_consensus: {exc}") from None
    for name, got in (("mask", masks), ("image", grays)):
        if sorted(got) != list(range(len(P))):
            raise SystemExit(f"carve_consensus: {scene / name}: views {sorted(got)[:5]}... "
                             f"for {len(P)} cameras")
    mesh = trimesh.load(mesh_path, process=False, force="mesh")
    if len(mesh.faces) == 0:
        raise SystemExit(f"carve_consensus: {mesh_path}: no faces")
    foot = finest_footprint(mesh, P)
    samples, face = trimesh.sample.sample_surface(mesh, ps.sample_count(mesh, foot), seed=0)
    return {"pts": pts, "depth": depth, "P": P, "foot": foot, "samples": samples,
            "feats": feats, "normals": np.asarray(mesh.face_normals)[face],
            "verts": np.asarray(mesh.vertices, np.float64),
            "masks": [masks[v] for v in range(len(P))],
            "gray": torch.as_tensor(np.stack([grays[v] for v in range(len(P))])),
            "offsets": np.arange(-ps.BEFORE_PX, ps.REACH_PX + 1e-9, ps.STEP_PX) * foot}


def carving_rays(data: dict, a: argparse.Namespace) -> tuple:
    """The two passes (the module docstring): pass 1's rays (N1, 15), the flagged cells,
    pass 2's scored rays (N2, 15), and (N2,) bool the rays that agree and those that carve
    (agree where the mesh is not convex)."""
    P, foot = data["P"], data["foot"]
    tol, margin = 2 * foot, sc.MARGIN_PX * foot
    first = sweep_views(data, range(0, len(P), a.every), sc.STRIDE, None, a.cell)
    ok = first[:, 3] < ps.INVALID
    keys = sc.cell_keys(first[ok, 8:11], first[ok, 11:14], a.cell)
    med, agree, count = sc.consensus(keys, first[ok, 14], first[ok, 0], tol)
    flagged = {tuple(k) for k in keys[(count >= 3) & (med >= margin) & (agree >= 0.3)]}
    dense = sweep_views(data, range(len(P)), 1, flagged, a.cell)
    dense = dense[dense[:, 3] < ps.INVALID]
    med, agree, count = sc.consensus(sc.cell_keys(dense[:, 8:11], dense[:, 11:14], a.cell),
                                  dense[:, 14], dense[:, 0], tol)
    agreed = (sc.agreeing(dense[:, 14], med, agree, count, a.min_rays, a.agree, margin, tol)
              & (dense[:, 3] < sc.MAX_COST) & np.isfinite(dense[:, 4]))
    convexity = np.full(len(dense), np.nan)
    convexity[agreed] = sc.local_convexity(data["samples"], dense[agreed, 8:11],
                                        dense[agreed, 11:14], a.radius)
    with np.errstate(invalid="ignore"):
        carve = agreed & ~(convexity < a.convex)
    return first, flagged, dense, agreed, carve


def feature_rows(dense: np.ndarray, agreed: np.ndarray, carve: np.ndarray,
                 feats: list[dict]) -> list[dict]:
    """Per feature (and "elsewhere") that holds agreeing rays: how many agree, how many
    carve, the share of those ending more than a unit inside the truth, the median of how
    far the mesh lies in front of the truth and of where the sweep ends against it."""
    _, z0, zb, _, truth = dense[:, :5].T
    where = first_ball(dense[:, 5:8], feats)
    rows = []
    for f, name in enumerate([f["name"] for f in feats] + ["elsewhere"]):
        part = where == f
        k = part & carve
        if not (part & agreed).any():
            continue
        rows.append({"feature": name, "agree": int((part & agreed).sum()), "rays": int(k.sum()),
                     "overshoot": float(np.mean(zb[k] - truth[k] > 1.0)) if k.any() else None,
                     "mesh_in_front": float(np.median(truth[k] - z0[k])) if k.any() else None,
                     "sweep_minus_truth": float(np.median(zb[k] - truth[k])) if k.any()
                     else None})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a synthetic scene folder (neus-l0 synth)")
    ap.add_argument("mesh", type=Path, help="a mesh in world units (neus-l0 mesh)")
    ap.add_argument("--every", type=int, default=3, help="pass 1 sweeps every N-th view")
    ap.add_argument("--cell", type=float, default=10.0, help="cell side, world units")
    ap.add_argument("--min-rays", type=int, default=8)
    ap.add_argument("--agree", type=float, default=0.3)
    ap.add_argument("--convex", type=float, default=-0.05,
                    help="rays whose mesh point's local convexity is below this do not carve")
    ap.add_argument("--radius", type=float, default=4.0,
                    help="the local convexity's radius, world units")
    ap.add_argument("--out", type=Path, help="also write the table as JSON")
    a = ap.parse_args(argv)
    for flag, value in (("--every", a.every), ("--cell", a.cell), ("--radius", a.radius),
                        ("--min-rays", a.min_rays)):
        if not value > 0:
            raise SystemExit(f"carve_consensus: {flag} {value}: must be positive")
    data = read_inputs(a.scene, a.mesh)
    first, flagged, dense, agreed, carve = carving_rays(data, a)
    rows = feature_rows(dense, agreed, carve, data["feats"])
    print(f"pass 1: {len(first)} rays, {len(flagged)} cells flagged; pass 2: {len(dense)} rays, "
          f"{int(agreed.sum())} agree, {int(carve.sum())} of them where the mesh is not convex "
          f"(local convexity >= {a.convex:g} within {a.radius:g} units) would carve")
    print("| feature | rays agreeing | carving | ending > 1 inside | mesh in front by | "
          "sweep - truth |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        nums = [r[k] for k in ("overshoot", "mesh_in_front", "sweep_minus_truth")]
        cells = " | ".join("-" if x is None else f"{x:.2f}" for x in nums)
        print(f"| {r['feature']} | {r['agree']} | {r['rays']} | {cells} |")
    if a.out:
        atomic_write_json(a.out, {"scene": str(a.scene), "mesh": str(a.mesh), "rows": rows,
                                  "args": {k: str(v) for k, v in vars(a).items()}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
